"""Warm calls of the nonlinear flows (and of the heat flow on bricks), against a baseline checkout.

What a user waits for once a surface's state is built: each run is a fresh process that builds
its surface, calls the flow once (compiling, forming stencils) and times the second call in CPU
seconds. With ``--baseline`` (the root of another checkout, e.g. a ``git worktree`` of an older
commit) its runs alternate with this checkout's, so that the machine's drift falls on both;
read the ratios.

Cases (``--cases``):

- ``perona_malik``: ``AnisotropicFlow`` (Perona–Malik, contrast ``1 / h``) to ``4 h^2`` on noise
  in ``[0, 1]``, a dense ``MeshAdapter`` of ``bunny_closed.obj`` at ``--resolution``;
- ``harmonic``: ``HarmonicMapFlow`` (p = 1) to ``5 h^2`` of a random unit tangent field on the
  torus ``(0.9, 0.4)`` in ``[-1.5, 1.5]^3`` at ``--resolution``;
- ``reaction_diffusion``: Turk's spots (``rate = 1 / 16``) to ``t = 50`` on the bunny's adapter;
- ``tv_bricks``: total variation (``eps = 1 / h``, symmetric scheme, ``path="slicing"``) to
  ``2 h`` on the bunny's bricks (``bricks.from_mesh``), first call on a fresh surface
  (its bound: the brick rows in closed form since 2026-12-07).

Run with one thread and the team's allocator setting::

    OMP_NUM_THREADS=1 \\
    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        python benchmarks/bench_nonlinear.py --resolution 48 --runs 3 --baseline /tmp/old
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

from _report import (
    add_alternation_arguments,
    alternated,
    checkouts,
    checksum_offsets,
    figures,
    run_context,
    worker_result,
    write_section,
)
from bench_mesh_heat import MESH_DIR

ROOT = Path(__file__).resolve().parents[1]
SECTION = "bench_nonlinear"
CASES = ("perona_malik", "harmonic", "reaction_diffusion", "tv_bricks")


def worker(case: str, resolution: int) -> dict[str, float]:
    """One run in this process: the case's flow called twice; CPU seconds of each call."""
    import time

    import torch

    import torchsurf as ts

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    generator = torch.Generator().manual_seed(0)
    bunny = Path(MESH_DIR) / "bunny_closed.obj"
    if case == "harmonic":
        grid = ts.Grid.cube(resolution, 1.5)
        surface = ts.ImplicitSurface(ts.sdf.torus(grid, 0.9, 0.4), grid)
        field = ts.surface.tangent_unit(torch.randn((1, 3, *grid.shape), generator=generator),
                                        surface)
        flow = ts.flows.HarmonicMapFlow(time=5 * grid.spacing**2)
        call = lambda: flow(field, surface)  # noqa: E731
    elif case == "tv_bricks":
        mesh = ts.mesh.load(bunny)
        # at least the 6 free cells bricks need (as bench_bricks.py)
        grid = ts.mesh.fit_grid(mesh, resolution,
                                margin=max(0.15, 6.0 / max(resolution - 13, 1)))
        surface = ts.bricks.from_mesh(mesh, grid)
        data = surface.layout.rand(1, generator=generator)
        flow = ts.AnisotropicFlow(time=2 * grid.spacing, eps=1.0 / grid.spacing,
                                  scheme="symmetric", path="slicing")
        call = lambda: flow(data, surface)  # noqa: E731
    else:
        adapter = ts.MeshAdapter(ts.mesh.load(bunny), resolution=resolution)
        surface, grid = adapter.surface, adapter.grid
        if case == "perona_malik":
            data = torch.rand((1, 1, *grid.shape), generator=generator)
            flow = ts.AnisotropicFlow(time=4 * grid.spacing**2, diffusivity="perona_malik",
                                      contrast=1.0 / grid.spacing)
            call = lambda: flow(data, surface)  # noqa: E731
        else:
            data = torch.full((1, 2, *grid.shape), 4.0)
            flow = ts.flows.ReactionDiffusion(time=50.0, rate=0.0625)
            call = lambda: flow(data, surface, generator=torch.Generator().manual_seed(0))  # noqa: E731
    times = []
    for _ in range(2):
        start = time.process_time()
        result = call()
        times.append(time.process_time() - start)
    return {"first": times[0], "second": times[1], "checksum": float(result.double().sum())}


def run_once(root: Path, case: str, resolution: int) -> dict[str, float]:
    """:func:`worker` in a fresh process importing torchsurf from ``root``."""
    return worker_result(__file__, root, ["--cases", case, "--resolution", str(resolution)])


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--resolution", type=int, default=48)
    add_alternation_arguments(parser, runs=3)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.cases[0], args.resolution)))
        return
    roots = checkouts(ROOT, args.baseline)
    rows = ["| case | n | checkout | first call s | second call s "
            "| result's sum, off this checkout's first run by |",
            "|---|---:|---|---:|---:|---:|"]
    for case in args.cases:
        runs = alternated(roots, args.runs,
                          lambda root, case=case: run_once(root, case, args.resolution))
        reference = runs["this"][0]["checksum"]
        for name in roots:
            rows.append(f"| {case} | {args.resolution} | {name} "
                        f"| {figures(runs[name], 'first', 2)} "
                        f"| {figures(runs[name], 'second', 2)} "
                        f"| {checksum_offsets(runs[name], reference)} |")
            print(rows[-1], flush=True)
        if "baseline" in runs:
            ratios = [statistics.median(r[key] for r in runs["this"])
                      / statistics.median(r[key] for r in runs["baseline"])
                      for key in ("first", "second")]
            rows.append(f"| | | this ÷ baseline, medians | {ratios[0]:.2f} | {ratios[1]:.2f} | |")
            print(rows[-1], flush=True)
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))  # the workers' count
    body = "\n".join([
        f"{run_context()}; the runs' `OMP_NUM_THREADS="
        f"{os.environ.get('OMP_NUM_THREADS', 'unset')}` (one thread where unset). CPU "
        "seconds; each run one fresh "
        "process, the checkouts alternated. The last column: how far each run's result, "
        "summed in float64, lies from this checkout's first run's, relative.",
        "",
        f"    python benchmarks/bench_nonlinear.py {' '.join(argv)}",
        "",
        *rows,
    ])
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION, "## Warm calls of the nonlinear flows", body)


if __name__ == "__main__":
    main()
