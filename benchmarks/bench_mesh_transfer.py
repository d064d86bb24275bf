"""Accuracy of ``MeshAdapter``'s transfer: vertex values -> band -> vertex values.

For each mesh (normalised to a bounding-box diagonal of 1), resolution and decoding order, the
script encodes ``u = sin(2 pi a . x)`` (``a = 2 (0.48, 0.6, 0.64)``, the signal of
``bench_mesh_heat.py``) given at the vertices and decodes it again, directly ("round trip")
and after one tricubic closest-point re-extension of the whole band ("re-extended"), which is
what every flow does to
its data before it returns it. Errors are over the vertices, relative to ``max |u|``: the
maximum, and the median (which shows the order where a few thin parts hold the maximum).

Run::

    PYTHONPATH=. python benchmarks/bench_mesh_transfer.py --meshes spot armadillo bunny_closed \\
        --resolutions 64 96 128 --output docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
import trimesh
from _report import cpu_model, write_section  # benchmarks/_report.py, beside this script
from bench_mesh_heat import MESH_DIR, normalised, signal

import torchsurf as ts
from torchsurf.flows.extension import CubicStencil

SECTION = "bench_mesh_transfer"


def errors(adapter: ts.MeshAdapter, values: torch.Tensor) -> tuple[float, float, float, float]:
    """Max and median relative error of the round trip, then of the re-extended round trip."""
    volume = adapter.encode(values)
    extended = CubicStencil(adapter.surface, adapter.band_mask).apply(volume)
    scale = float(values.abs().max())
    result = []
    for field in (volume, extended):
        error = (adapter.decode(field) - values).abs() / scale
        result += [float(error.max()), float(error.median())]
    return tuple(result)


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=["spot", "armadillo", "bunny_closed"])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[64, 96, 128])
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)
    lines = [
        f"Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}. "
        f"{cpu_model()}, torch {torch.__version__}, float64, {torch.get_num_threads()} "
        f"threads, GLIBC_TUNABLES=`{os.environ.get('GLIBC_TUNABLES', 'unset')}`.",
        "",
        f"Command: `PYTHONPATH=. python benchmarks/bench_mesh_transfer.py {' '.join(argv)}`",
        "",
        "Meshes normalised to a box diagonal of 1; signal `sin(2π a·x)`, `a = 2 (0.48, 0.6, 0.64)`, at the "
        "vertices. Errors over the vertices relative to max |u|, as max / median. `order 1`: "
        "trilinear sampling at the vertices (before issue 11); `order 2`: the closest-point "
        "weights (the default). `re-extended`: decoded after one tricubic closest-point "
        "re-extension of the band, as a flow leaves its data. `build s`: the adapter, order 2.",
        "",
        "| mesh | vertices | resolution | order 1 round trip | order 2 round trip "
        "| order 1 re-extended | order 2 re-extended | build s |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name in args.meshes:
        mesh = normalised(trimesh.load(MESH_DIR / f"{name}.obj", force="mesh"))
        values = torch.as_tensor(signal(np.asarray(mesh.vertices)))[None, None]
        for resolution in args.resolutions:
            grid = ts.mesh.fit_grid(mesh, resolution)
            first = errors(ts.MeshAdapter(mesh, grid, dtype=torch.float64, order=1), values)
            start = time.perf_counter()
            adapter = ts.MeshAdapter(mesh, grid, dtype=torch.float64, order=2)
            build = time.perf_counter() - start
            second = errors(adapter, values)
            cells = [f"{a:.1e} / {b:.1e}" for a, b in
                     ((first[0], first[1]), (second[0], second[1]),
                      (first[2], first[3]), (second[2], second[3]))]
            row = (f"| {name} | {len(mesh.vertices)} | {resolution} | " + " | ".join(cells)
                   + f" | {build:.1f} |")
            print(row, flush=True)
            lines.append(row)
    body = "\n".join(lines) + "\n"
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION, "## Mesh transfer: MeshAdapter round trip", body.rstrip("\n"))


if __name__ == "__main__":
    main()
