"""Compiled against eager, per operator, in one process: steady times and what ``"auto"`` picks.

The quick companion of ``bench_compile.py`` (which runs every row in fresh processes, cold and
warm inductor cache, hours on the shared machine): here each operator of
``bench_compile.OPERATORS`` is built on ``path="slicing"``, ``"compiled"`` and ``"auto"`` in
this one process, and timed (the fastest of ``--repeats`` calls) for a no-grad forward and a
forward + backward. For ``"auto"`` the payback is shortened to ``--payback`` seconds so that it
goes through its whole decision in seconds: eager calls, compile once the variant's eager time
pays back, :data:`torchsurf.backend.COMPARED_CALLS` compiled calls, back to eager if slower.
``compiled first s`` is the first forward + backward on ``"compiled"`` (the compiler's start-up
lands on the first operator; give a fresh ``TORCHINDUCTOR_CACHE_DIR`` for cold compiles).
One JSON object a line is appended to ``--output``::

    OMP_NUM_THREADS=1 \\
    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
    TORCHINDUCTOR_CACHE_DIR=$(mktemp -d) PYTHONPATH=. \\
        python benchmarks/bench_compile_steady.py --size 48 --batch 4 --output steady.jsonl
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_compile  # noqa: E402
from _report import run_context  # noqa: E402

from torchsurf import backend  # noqa: E402


def fastest(function: Callable[[], None], repeats: int) -> float:
    """The fastest of ``repeats`` calls of ``function``, seconds."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def calls(call: Callable[[torch.Tensor], torch.Tensor], data: torch.Tensor
          ) -> tuple[Callable[[], None], Callable[[], None]]:
    """``(forward, train)``: a no-grad forward of ``call`` on ``data``, and a forward +
    backward with a fixed random cotangent."""
    leaf = data.clone().requires_grad_(True)
    weights: list[torch.Tensor] = []

    def forward() -> None:
        with torch.no_grad():
            call(data)

    def train() -> None:
        leaf.grad = None
        output = call(leaf)
        if not weights:
            weights.append(torch.rand(output.shape, generator=torch.Generator().manual_seed(1)))
        (output * weights[0]).sum().backward()

    return forward, train


def measure(item: str, size: int, batch: int, repeats: int, payback: float, budget: float
            ) -> dict[str, object]:
    """One operator on the three paths; milliseconds for steady calls, seconds otherwise."""
    row: dict[str, object] = {"item": item, "n": size, "batch": batch}
    for path in ("slicing", "compiled", "auto"):
        call, data, _ = bench_compile.build(item, path, size, batch, torch.float32)
        forward, train = calls(call, data)
        start = time.perf_counter()
        forward()
        train()
        row[f"{path}_first_s"] = round(time.perf_counter() - start, 2)
        if path == "auto":
            backend.COMPILE_PAYBACK_SECONDS = payback
            backend._TIMINGS.clear()
            start = time.perf_counter()
            while time.perf_counter() - start < budget:
                forward()
                train()
                if not any(timing.pending for timing in backend._TIMINGS.values()):
                    break
            decided = not any(timing.pending for timing in backend._TIMINGS.values())
            # None: the budget ran out with a variant still measuring
            row["auto_decided_s"] = round(time.perf_counter() - start, 1) if decided else None
            row["auto_variants"] = len(backend._TIMINGS)
            row["auto_slower_variants"] = sum(t.slower for t in backend._TIMINGS.values())
        row[f"{path}_fwd_ms"] = round(1e3 * fastest(forward, repeats), 2)
        row[f"{path}_train_ms"] = round(1e3 * fastest(train, repeats), 2)
        if path == "auto":
            with backend.recorded_paths() as picks:
                forward()
                train()
            row["auto_picks"] = dict(collections.Counter(picks))
    return row


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=48)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--payback", type=float, default=1.0,
                        help="COMPILE_PAYBACK_SECONDS for the 'auto' rows")
    parser.add_argument("--budget", type=float, default=60.0,
                        help="seconds at most for 'auto' to decide")
    parser.add_argument("--operators", nargs="*", default=list(bench_compile.OPERATORS),
                        choices=bench_compile.OPERATORS)
    parser.add_argument("--output", type=Path, required=True, help="JSON lines, appended")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    backend.COMPILE = "auto"
    args.output.parent.mkdir(parents=True, exist_ok=True)  # before the first minute of work
    for item in args.operators:
        row = measure(item, args.size, args.batch, args.repeats, args.payback, args.budget)
        row["context"] = run_context()
        print(json.dumps(row), flush=True)
        with args.output.open("a") as output:
            output.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
