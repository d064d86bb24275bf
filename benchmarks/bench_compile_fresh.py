"""First compiled calls of a flow on a surface it has not run on, against one warmed by a call.

``torch.compile(flow)`` on a fresh surface: a flow traced on a surface it has not run on runs
once as is first, outside the trace (``torchsurf._as_is.run_as_is_first``), and the rest
is one graph. The baseline in the same run is the route the docs advised before: one call as
is on the surface, then the compiled calls. Each figure is one fresh process with a fresh
``TORCHINDUCTOR_CACHE_DIR`` (inductor's cache cold), three compiled calls timed, and the graphs
compiled counted (``torch._dynamo.testing.CompileCounterWithBackend("inductor")``). With
``--baseline`` (the root of another checkout), its runs alternate with this checkout's.

Cases: ``heat``, ``HeatFlow(4 h^2)`` (RKC) on the unit sphere at ``--size``, no grad;
``learned``, the same with a learned time (``max_time = 8 h^2``), forward and backward of
``out.square().sum()``; ``bricks``, ``heat`` on the bricks of a sphere of radius 0.6 at
``--size + 7``.

Run with one thread and the team's allocator setting::

    OMP_NUM_THREADS=1 \\
    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        python benchmarks/bench_compile_fresh.py --size 9 --output docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import tempfile
from pathlib import Path

from _report import (
    add_alternation_arguments,
    alternated,
    checkouts,
    cpu_model,
    worker_result,
    write_section,
)

ROOT = Path(__file__).resolve().parents[1]
SECTION = "bench_compile_fresh"
CASES = ("heat", "learned", "bricks")
ROUTES = ("fresh", "after a call as is")


def worker(case: str, route: str, size: int) -> dict[str, float]:
    """One run in this process: three compiled calls; seconds, graphs and the difference."""
    import time

    import torch
    from torch._dynamo.testing import CompileCounterWithBackend

    import torchsurf as ts

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    generator = torch.Generator().manual_seed(3)
    if case == "bricks":
        grid = ts.Grid.cube(size + 7, 1.5)
        surface = ts.bricks.from_dense(ts.sdf.sphere(grid, 0.6), grid)
        u = surface.layout.rand(1, generator)
    else:
        grid = ts.Grid.cube(size, 1.5)
        surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
        u = torch.rand(1, 1, *grid.shape, generator=generator)
    h2 = grid.spacing**2
    learned = case == "learned"
    flow = (ts.HeatFlow(4 * h2, learn_time=True, max_time=8 * h2) if learned
            else ts.HeatFlow(4 * h2))

    def call(layer: torch.nn.Module) -> torch.Tensor:
        with torch.set_grad_enabled(learned):
            result = layer(u, surface)
            if learned:
                result.square().sum().backward()
        return result.detach()

    if route != "fresh":
        call(flow)
    counter = CompileCounterWithBackend("inductor")
    compiled = torch.compile(flow, backend=counter)
    seconds = []
    for _ in range(3):
        start = time.perf_counter()
        result = call(compiled)
        seconds.append(time.perf_counter() - start)
    difference = float((result - call(flow)).abs().max())
    return {"first": seconds[0], "second": seconds[1], "third": seconds[2],
            "graphs": counter.frame_count, "difference": difference}


def run_once(root: Path, case: str, route: str, size: int) -> dict[str, float]:
    """:func:`worker` in a fresh process importing torchsurf from ``root``, inductor's cache
    in a new directory."""
    with tempfile.TemporaryDirectory(prefix="inductor-") as cache:
        return worker_result(__file__, root, ["--cases", case, "--route", route,
                                              "--size", str(size)],
                             {"TORCHINDUCTOR_CACHE_DIR": cache})


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--size", type=int, default=9, help="nodes along each axis (bricks: +7)")
    parser.add_argument("--route", choices=ROUTES, default="fresh", help=argparse.SUPPRESS)
    add_alternation_arguments(parser, runs=1)
    args = parser.parse_args(argv)
    if args.worker:
        print(json.dumps(worker(args.cases[0], args.route, args.size)))
        return
    roots = checkouts(ROOT, args.baseline)
    rows = ["| case | checkout | route | compiled calls s (1st, 2nd, 3rd) | graphs "
            "| largest difference from as is |", "|---|---|---|---|---:|---:|"]
    for case in args.cases:
        firsts = {}
        for route in ROUTES:
            runs = alternated(roots, args.runs, lambda root, case=case, route=route: run_once(
                root, case, route, args.size))
            for name, results in runs.items():
                for run in results:
                    rows.append(f"| {case} | {name} | {route} | {run['first']:.1f}, "
                                f"{run['second']:.1f}, {run['third']:.1f} | {run['graphs']} "
                                f"| {run['difference']:.1e} |")
                    print(rows[-1], flush=True)
                firsts[name, route] = statistics.median(
                    run["first"] + run["second"] for run in results)
        ratio = firsts["this", "fresh"] / firsts["this", ROUTES[1]]
        rows.append(f"| {case} | this | fresh ÷ after a call as is (two first calls) "
                    f"| {ratio:.2f} | | |")
        print(rows[-1], flush=True)
    allocator = os.environ.get("GLIBC_TUNABLES", "glibc default")
    body = "\n".join([
        f"{datetime.date.today()}, {cpu_model()}, {os.cpu_count()} cores, "
        f"`OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}`, allocator: "
        f"`{allocator}`. Each row one fresh process with inductor's cache cold. The route "
        "\"after a call as is\" times its compiled calls after one call as is on the surface "
        "(not counted), the advice before fresh surfaces traced whole.",
        "",
        f"    python benchmarks/bench_compile_fresh.py {' '.join(argv)}",
        "",
        *rows,
    ])
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION,
                      "## First compiled calls on a fresh surface", body)


if __name__ == "__main__":
    main()
