"""What compiling one operator's no-grad forward costs, against its eager call: the weights
``"auto"`` gives its kernels (:attr:`torchsurf.backend.Kernel.compile_weight`).

For each operator of ``bench_compile.OPERATORS`` named, one fresh process with an empty inductor
cache (a new ``TORCHINDUCTOR_CACHE_DIR``) first compiles a trivial function (the compiler's
start-up, paid once per process, reported apart), then times, on ``Grid.cube(n, 1.5)`` with
batch 1, float32: the fastest of three eager (``"slicing"``) calls, the first ``"compiled"``
call, and the fastest of three compiled calls after it. ``compile s`` is the first compiled
call minus a steady one; ``weight`` is that over the first operator's (Laplace–Beltrami's,
by default): what the kernel's ``compile_weight`` should be near.

Run with one thread and the team's allocator setting, on a machine as quiet as can be had::

    OMP_NUM_THREADS=1 \\
    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        PYTHONPATH=. python benchmarks/bench_compile_cost.py --size 64
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
DEFAULT_OPERATORS = ("lb_octant", "anisotropic_tv", "anisotropic_tv_octant", "directional",
                     "gradient", "divergence", "anisotropic_coupled", "harmonic_rate",
                     "colour_rate")


def measure(item: str, size: int) -> dict[str, float]:
    """In this process (fresh, with an empty inductor cache): the compiler's start-up, the
    eager and compiled steady calls and the first compiled call of ``item``, seconds."""
    sys.path.insert(0, str(HERE))
    import bench_compile  # beside this script; imports torchsurf

    start = time.perf_counter()
    torch.compile(lambda x: (x * 2 + 1).sin())(torch.randn(64))
    figures = {"startup_s": time.perf_counter() - start}
    for path in ("slicing", "compiled"):
        call, data, _ = bench_compile.build(item, path, size, 1, torch.float32)
        with torch.no_grad():
            start = time.perf_counter()
            call(data)
            first = time.perf_counter() - start
            steady = []
            for _ in range(3):
                start = time.perf_counter()
                call(data)
                steady.append(time.perf_counter() - start)
        figures[f"{path}_first_s"], figures[f"{path}_s"] = first, min(steady)
    figures["compile_s"] = figures["compiled_first_s"] - figures["compiled_s"]
    return figures


def in_fresh_process(item: str, size: int) -> dict[str, float]:
    """:func:`measure` in a child process with its own empty inductor cache."""
    with tempfile.TemporaryDirectory() as cache:
        environment = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=cache)
        output = subprocess.run(
            [sys.executable, __file__, "--child", item, "--size", str(size)],
            env=environment, check=True, capture_output=True, text=True).stdout
    return json.loads(output.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=64)
    parser.add_argument("--operators", nargs="*", default=list(DEFAULT_OPERATORS))
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1")))
    if args.child:
        print(json.dumps(measure(args.child, args.size)))
        return
    from _report import run_context  # benchmarks/_report.py, beside this script
    print(f"{run_context()}; {args.size}^3, batch 1, float32")
    print("| operator | eager ms | compiled ms | compile s (empty cache) | weight | start-up s |")
    print("|---|---:|---:|---:|---:|---:|")
    reference = None
    for item in args.operators:
        figures = in_fresh_process(item, args.size)
        reference = reference or figures["compile_s"]
        print(f"| {item} | {1e3 * figures['slicing_s']:.1f} | {1e3 * figures['compiled_s']:.1f} | "
              f"{figures['compile_s']:.1f} | {figures['compile_s'] / reference:.1f} | "
              f"{figures['startup_s']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
