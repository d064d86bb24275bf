"""A layer wrapped whole in ``torch.compile`` (inductor) against the same layer called as is.

Called as is, a layer runs its operators on ``path="auto"`` (warmed here with
``torchsurf.backend.warm_up()``, so its kernels are compiled where that pays) and its packed
products and clamped re-extension in C. Wrapped whole, the traced graph calls the same C kernels
as custom operators (``torch.ops.torchsurf``) and inductor compiles the rest. Each row: the first
compiled call (trace and compile; a forward alone, then a forward and backward), then the median of
``--pairs`` alternated steady calls of each and their ratio, and the largest difference of the
outputs. A table is printed; ``--write`` puts it into docs/benchmarks.md::

    OMP_NUM_THREADS=1 \\
    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        PYTHONPATH=. python benchmarks/bench_compile_whole.py --size 32 --batch 4
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import cpu_model, write_section  # noqa: E402

import torchsurf as ts  # noqa: E402


def layers(h2: float) -> dict[str, Callable[[], torch.nn.Module]]:
    """The layers measured, times in units of ``h2`` (the grid spacing squared)."""
    return {
        "HeatFlow (rkc, learned time, max_time)":
            lambda: ts.HeatFlow(4 * h2, learn_time=True, max_time=8 * h2),
        "LearnedDiffusion": lambda: ts.nn.LearnedDiffusion(1, time=[2.0], max_time=4.0),
        "DiffusionBlock": lambda: ts.nn.DiffusionBlock(1, time=[2.0], max_time=4.0),
    }


def measure(name: str, size: int, batch: int, grad: bool, pairs: int) -> dict[str, object]:
    grid = ts.Grid.cube(size, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0), grid)
    u = torch.rand(batch, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    layer = layers(surface.spacing**2)[name]()

    def run(module: torch.nn.Module) -> torch.Tensor:
        with torch.set_grad_enabled(grad):
            out = module(u, surface)
            if grad:
                out.square().sum().backward()
        return out.detach()

    with ts.backend.warm_up():
        expected = run(layer)
    run(layer)
    torch._dynamo.reset()
    compiled = torch.compile(layer)
    start = time.perf_counter()
    result = run(compiled)
    first = time.perf_counter() - start
    run(compiled)
    eager, whole = [], []
    for _ in range(pairs):
        for module, times in ((layer, eager), (compiled, whole)):
            start = time.perf_counter()
            run(module)
            times.append(time.perf_counter() - start)
    torch._dynamo.reset()
    ratios = [w / e for w, e in zip(whole, eager, strict=True)]
    return {"layer": name, "grad": grad, "first": first, "eager": statistics.median(eager),
            "whole": statistics.median(whole), "ratio": statistics.median(ratios),
            "difference": float((result - expected).abs().max())}


def inductor_cache_is_empty() -> bool:
    """Whether inductor's cache directory (``TORCHINDUCTOR_CACHE_DIR``, else its default) holds
    nothing yet: the first compiled calls then compile every kernel."""
    from torch._inductor.runtime.cache_dir_utils import cache_dir

    directory = Path(cache_dir())
    return not directory.exists() or not any(directory.iterdir())


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=32)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--pairs", type=int, default=7)
    parser.add_argument("--write", type=Path, default=None,
                        help="markdown file to put the table into (docs/benchmarks.md)")
    args = parser.parse_args(argv)
    cache = "cold" if inductor_cache_is_empty() else "warm"
    rows = []
    for name in layers(1.0):
        for grad in (False, True):
            row = measure(name, args.size, args.batch, grad, args.pairs)
            rows.append(row)
            print(row, flush=True)
    lines = ["| layer | grad | first compiled call s | as is ms | compiled whole ms | ratio "
             "(median of pairs) | largest difference |", "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['layer']} | {'forward + backward' if r['grad'] else 'no grad'} | "
              f"{r['first']:.1f} | {1e3 * r['eager']:.1f} | {1e3 * r['whole']:.1f} | "
              f"{r['ratio']:.2f} | {r['difference']:.1e} |" for r in rows]
    machine = (f"{cpu_model()}, {os.cpu_count()} cores, "
               f"{torch.get_num_threads()} thread(s), torch {torch.__version__}, "
               f"GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', 'unset')}, "
               f"inductor cache {cache}")
    body = (f"`bench_compile_whole.py --size {args.size} --batch {args.batch} "
            f"--pairs {args.pairs}`, "
            f"{time.strftime('%Y-%m-%d')}, {machine}. \"As is\": the layer called directly "
            "after `torchsurf.backend.warm_up()`; \"compiled whole\": `torch.compile(layer)` with "
            "the default backend (inductor), whose graph calls the C kernels as custom operators "
            "(docs/learning.md, \"A model compiled whole\"). Each call a forward, or a forward and "
            "backward of `out.square().sum()`.\n\n" + "\n".join(lines) + "\n")
    print(body)
    if args.write is not None:
        write_section(args.write, "compile-whole", "## A layer compiled whole", body)


if __name__ == "__main__":
    main()
