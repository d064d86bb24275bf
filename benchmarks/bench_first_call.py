"""First calls of the flows on a mesh through a dense ``MeshAdapter``, against a baseline checkout.

What a user pays once per surface: a flow's first call builds the surface's stencils, the
Gershgorin bound of its operator and (for ``HeatFlow``) the packed band operator before it
steps; the second call reuses them. Each run is a fresh process (nothing kept between runs):
it builds ``MeshAdapter(mesh, resolution=n)``, then calls the flow twice on noise in ``[0, 1]``
and reports both wall times and the process's resident peak. With ``--baseline`` (the root of
another checkout, e.g. a ``git worktree`` of an older commit), its runs alternate with this
checkout's, so that the machine's drift falls on both; read the ratios.

Flows: ``heat`` is ``HeatFlow(time=(8 h)^2)`` (RKC on packed band values, octant scheme);
``tv`` is ``AnisotropicFlow`` (total variation, scheme ``"symmetric"``, ``eps = 1 / h``) to
``2 h``.

Run with one thread and the team's allocator setting::

    OMP_NUM_THREADS=1 \\
    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        python benchmarks/bench_first_call.py --resolution 200 --baseline /tmp/old
"""

from __future__ import annotations

import argparse
import datetime
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
    cpu_model,
    figures,
    worker_result,
    write_section,
)
from bench_mesh_heat import MESH_DIR

ROOT = Path(__file__).resolve().parents[1]
SECTION = "bench_first_call"
FLOWS = ("heat", "tv")


def worker(mesh: str, resolution: int, flow_name: str) -> dict[str, float]:
    """One run in this process: the adapter, then the flow twice; seconds and GB."""
    import resource
    import time

    import torch
    import trimesh

    import torchsurf as ts

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    start = time.perf_counter()
    adapter = ts.MeshAdapter(trimesh.load(Path(MESH_DIR) / f"{mesh}.obj", force="mesh"),
                             resolution=resolution)
    surface, h = adapter.surface, adapter.grid.spacing
    setup = time.perf_counter() - start
    u = torch.rand((1, 1, *adapter.grid.shape), generator=torch.Generator().manual_seed(0))
    if flow_name == "heat":
        flow = ts.HeatFlow(time=(8 * h) ** 2)
    else:
        flow = ts.AnisotropicFlow(time=2 * h, eps=1.0 / h)
    times = []
    for _ in range(2):
        start = time.perf_counter()
        result = flow(u, surface)
        times.append(time.perf_counter() - start)
    return {"setup": setup, "first": times[0], "second": times[1],
            # GB of 1e9 bytes (ru_maxrss is in KiB), as bench_bricks' and the 4 GB target's
            "peak_gb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9,
            "checksum": float(result.double().sum())}


def run_once(root: Path, mesh: str, resolution: int, flow: str) -> dict[str, float]:
    """:func:`worker` in a fresh process importing torchsurf from ``root``."""
    return worker_result(__file__, root, ["--meshes", mesh, "--resolution", str(resolution),
                                          "--flows", flow])


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=["bunny_closed"])
    parser.add_argument("--resolution", type=int, default=200)
    parser.add_argument("--flows", nargs="+", choices=FLOWS, default=list(FLOWS))
    add_alternation_arguments(parser, runs=2)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.meshes[0], args.resolution, args.flows[0])))
        return
    roots = checkouts(ROOT, args.baseline)
    rows = ["| mesh | n | flow | checkout | first call s | second call s | resident peak GB "
            "| result's sum, off this checkout's first run by |",
            "|---|---:|---|---|---:|---:|---:|---:|"]
    for mesh in args.meshes:
        for flow in args.flows:
            runs = alternated(roots, args.runs,
                              lambda root, mesh=mesh, flow=flow: run_once(
                                  root, mesh, args.resolution, flow))
            reference = runs["this"][0]["checksum"]
            for name in roots:
                rows.append(f"| {mesh} | {args.resolution} | {flow} | {name} "
                            f"| {figures(runs[name], 'first', 1)} "
                            f"| {figures(runs[name], 'second', 1)} "
                            f"| {figures(runs[name], 'peak_gb', 2)} "
                            f"| {checksum_offsets(runs[name], reference)} |")
                print(rows[-1], flush=True)
            if "baseline" in runs:
                ratio = (statistics.median(r["first"] for r in runs["this"])
                         / statistics.median(r["first"] for r in runs["baseline"]))
                rows.append(f"| | | | first call, this ÷ baseline | {ratio:.2f} | | | |")
                print(rows[-1], flush=True)
    allocator = os.environ.get("GLIBC_TUNABLES", "glibc default")
    body = "\n".join([
        f"{datetime.date.today()}, {cpu_model()}, {os.cpu_count()} cores, "
        f"`OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}`, allocator: "
        f"`{allocator}`. Each figure one fresh process, the checkouts alternated. "
        "The last column: how far each run's result, summed in float64, lies from this "
        "checkout's first run's, relative (0: the same sum).",
        "",
        f"    python benchmarks/bench_first_call.py {' '.join(argv)}",
        "",
        *rows,
    ])
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION, "## First calls of flows through a dense MeshAdapter",
                      body)


if __name__ == "__main__":
    main()
