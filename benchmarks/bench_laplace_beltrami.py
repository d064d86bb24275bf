"""Benchmark of ``ts.laplace_beltrami`` against a plain numpy Appendix-B reference.

For each size ``n`` (unit sphere, ``Grid.cube(n, 1.5)``, float32, ``u`` of shape
``(1, 1, n, n, n)``) the script times, per scheme (octant, the default, symmetric,
conservative, central) and per path (slicing, conv3d, compiled):

- the forward ``ts.laplace_beltrami(u, surface, scheme, path)`` with ``u`` not requiring grad;
- the forward that records the graph (``u.requires_grad_(True)``) and the backward alone
  (``out.backward(grad)`` timed by itself, the forward run untimed before it);
- the compile time of the compiled path (first call, excluded from the medians);

and in the same run a plain numpy reference of the paper's Appendix B (the conservative scheme,
``(1/W) D- . (W P D+ u)``), the memory bandwidth of the machine (a ~512 MB float32 copy) and
the traffic limit of one application: 24 bytes per voxel (read ``u``, the three components of
``n`` and ``W``, write the result) at that bandwidth.

Run it with the allocator tunables the figures in docs/benchmarks.md use::

    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        PYTHONPATH=. python benchmarks/bench_laplace_beltrami.py --output docs/benchmarks.md

``GLIBC_TUNABLES`` is read by glibc when the process starts, so it must be set in the
environment of the command; the script only records the value it finds.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import re
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from _report import write_section  # benchmarks/_report.py, beside this script

import torchsurf as ts

SCHEMES = ("symmetric", "conservative", "octant", "central")
PATHS = ("slicing", "conv3d", "compiled")
BYTES_PER_VOXEL = 24  # read u (4), n (12), W (4); write the result (4); float32
TEAM_TUNABLES = "glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736"
SLOW_CALL_S = 5.0
SECTION = "bench_laplace_beltrami"


# --------------------------------------------------------------------------------------------
# numpy reference: the paper's Appendix B
# --------------------------------------------------------------------------------------------


def numpy_normals(phi: np.ndarray, spacing: float, eps: float = 1e-6
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Central-difference normals of ``phi`` ``(D, H, W)``; ``(n (3, D, H, W) in x, y, z, W)``.

    Second-order one-sided differences on the faces of the box (the same numbers as central
    differences with ``phi`` extrapolated quadratically, which is what :class:`ImplicitSurface`
    does); ``|grad phi| = sqrt(|g|^2 + eps^2)``, ``n = g / max(|grad phi|, 1e-3 * slope)`` and
    the operators' weight ``W = max(|grad phi|, 0.65 * slope, 0.05 * median |grad phi| over the
    nodes next to a sign change)``, ``slope`` the one-sided differences' root mean square along each axis.
    """
    gz, gy, gx = np.gradient(phi, spacing, edge_order=2)
    gradient = np.stack([gx, gy, gz])
    norm = np.sqrt((gradient**2).sum(axis=0) + eps**2)
    inside = phi < 0
    crossing = np.zeros_like(inside)
    for axis in range(3):
        ahead = [slice(None)] * 3
        behind = [slice(None)] * 3
        ahead[axis], behind[axis] = slice(1, None), slice(None, -1)
        change = inside[tuple(ahead)] != inside[tuple(behind)]
        crossing[tuple(ahead)] |= change
        crossing[tuple(behind)] |= change
    values = np.sort(norm[crossing])
    median = values[(len(values) - 1) // 2]
    squared_slope = np.zeros_like(phi)
    for axis in range(3):
        steps = np.diff(phi, axis=axis) / spacing
        # the differences to the quadratically extrapolated nodes beyond the faces
        first = 2 * np.take(steps, [0], axis=axis) - np.take(steps, [1], axis=axis)
        last = 2 * np.take(steps, [-1], axis=axis) - np.take(steps, [-2], axis=axis)
        forward = np.concatenate([steps, last], axis=axis)
        backward = np.concatenate([first, steps], axis=axis)
        squared_slope += (forward**2 + backward**2) / 2
    slope = np.sqrt(squared_slope + eps**2)
    return (gradient / np.maximum(norm, 1e-3 * slope),
            np.maximum(np.maximum(norm, 0.65 * slope), 0.05 * median))


class AppendixB:
    """Plain numpy ``L u = (1/W) D- . (W P D+ u)`` (the paper's Appendix B) with reused buffers.

    Normals and ``W`` are computed once, at construction. The call does the paper's steps with
    numpy slicing, in place where natural: forward differences ``g = D+ u`` (zero on the last
    node of each axis: ``u`` replicated beyond the box), ``v = g - (g . n) n``, flux ``W v``
    with no flux through the faces of the box, backward-difference divergence, ``/ (h^2 W)``.

    Args:
        phi: ``(D, H, W)`` signed distance, world units.
        spacing: grid spacing ``h``.
        dtype: float32 or float64.
    """

    def __init__(self, phi: np.ndarray, spacing: float, dtype: np.dtype = np.float32,
                 eps: float = 1e-6) -> None:
        normal, weight = numpy_normals(np.asarray(phi, dtype=np.float64), spacing, eps)
        self.nx, self.ny, self.nz = (np.ascontiguousarray(c, dtype=dtype) for c in normal)
        self.weight = np.ascontiguousarray(weight, dtype=dtype)
        self.scale = np.ascontiguousarray(1.0 / (spacing**2 * weight), dtype=dtype)
        shape = phi.shape
        self.gx, self.gy, self.gz, self.dot, self.out = (
            np.empty(shape, dtype=dtype) for _ in range(5)
        )

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """``L u`` for ``u`` ``(D, H, W)``; returns an internal buffer (copy it to keep it)."""
        gx, gy, gz, dot, out = self.gx, self.gy, self.gz, self.dot, self.out
        nx, ny, nz, weight = self.nx, self.ny, self.nz, self.weight
        # 1. forward differences (index units; 1/h^2 applied at the end)
        np.subtract(u[:, :, 1:], u[:, :, :-1], out=gx[:, :, :-1])
        gx[:, :, -1] = 0.0
        np.subtract(u[:, 1:], u[:, :-1], out=gy[:, :-1])
        gy[:, -1] = 0.0
        np.subtract(u[1:], u[:-1], out=gz[:-1])
        gz[-1] = 0.0
        # 3. v = g - (g . n) n, times W (out is scratch here)
        np.multiply(gx, nx, out=dot)
        np.multiply(gy, ny, out=out)
        dot += out
        np.multiply(gz, nz, out=out)
        dot += out
        for g, n in ((gx, nx), (gy, ny), (gz, nz)):
            np.multiply(dot, n, out=out)
            g -= out
            g *= weight
        # no flux through the faces of the box
        gx[:, :, -1] = 0.0
        gy[:, -1] = 0.0
        gz[-1] = 0.0
        # 4. backward-difference divergence, then 1 / (h^2 W)
        np.copyto(out, gx)
        out[:, :, 1:] -= gx[:, :, :-1]
        out += gy
        out[:, 1:] -= gy[:, :-1]
        out += gz
        out[1:] -= gz[:-1]
        out *= self.scale
        return out


# --------------------------------------------------------------------------------------------
# timing helpers
# --------------------------------------------------------------------------------------------


def sample_times(function: Callable[[], object], repeats: int,
                 setup: Callable[[], object] | None = None) -> list[float]:
    """Wall times of ``repeats`` calls of ``function()`` in seconds (``setup`` untimed)."""
    times = []
    for _ in range(repeats):
        if setup is not None:
            setup()
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return times


def median_time(function: Callable[[], object], repeats: int,
                setup: Callable[[], object] | None = None) -> float:
    """Median wall time of ``function()`` in seconds over ``repeats`` calls (``setup`` untimed)."""
    return statistics.median(sample_times(function, repeats, setup))


def _cpu_jiffies() -> tuple[int, int] | None:
    """``(busy, total)`` jiffies of all CPUs from /proc/stat (None where unavailable)."""
    try:
        with open("/proc/stat") as stat:
            fields = [int(v) for v in stat.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return sum(fields) - idle, sum(fields)


def _own_cpu_seconds() -> float:
    times = os.times()
    return times.user + times.system


class ForeignLoad:
    """Fraction of the machine's CPU time used by other processes between start and stop."""

    def __init__(self) -> None:
        self.start = _cpu_jiffies()
        self.own = _own_cpu_seconds()

    def stop(self) -> float | None:
        end = _cpu_jiffies()
        if self.start is None or end is None or end[1] == self.start[1]:
            return None
        ticks = os.sysconf("SC_CLK_TCK")
        busy = (end[0] - self.start[0]) / ticks
        total = (end[1] - self.start[1]) / ticks
        own = _own_cpu_seconds() - self.own
        return max(0.0, (busy - own) / total)


def wait_for_idle(max_wait_s: float, threshold: float = 0.25, log=print) -> float | None:
    """Wait (at most ``max_wait_s``) until other processes use < ``threshold`` of the CPUs.

    Returns the last measured foreign load. The benchmark shares its machine with other work;
    two threads on two cores slow down far more than the CPU time taken from them when one
    thread is descheduled, so this keeps the medians honest.
    """
    deadline = time.monotonic() + max_wait_s
    load = None
    waited = False
    while True:
        probe = ForeignLoad()
        time.sleep(0.5)
        load = probe.stop()
        if load is None or load < threshold or time.monotonic() > deadline:
            break
        if not waited:
            log(f"  waiting for other processes to leave the CPUs (foreign load {load:.0%})")
            waited = True
    return load


class IdleWaiter:
    """:func:`wait_for_idle` with a cap per wait and a total budget for the whole run."""

    def __init__(self, each_s: float, budget_s: float, log=print) -> None:
        self.each_s, self.budget_s, self.log = each_s, budget_s, log
        self.spent_s = 0.0

    def __call__(self) -> None:
        remaining = self.budget_s - self.spent_s
        if self.each_s <= 0 or remaining <= 0:
            return
        start = time.monotonic()
        wait_for_idle(min(self.each_s, remaining), log=self.log)
        self.spent_s += time.monotonic() - start


def memory_bandwidth(megabytes: int = 512, repeats: int = 7) -> dict[str, float]:
    """Copy bandwidth in GB/s (read + write counted) of a ``megabytes`` float32 copy.

    Returns the numpy (``b[:] = a``) and torch (``b.copy_(a)``) medians.
    """
    count = megabytes * 2**20 // 4
    a = np.ones(count, dtype=np.float32)
    b = np.empty_like(a)
    b[:] = a
    numpy_s = median_time(lambda: b.__setitem__(slice(None), a), repeats)
    ta, tb = torch.from_numpy(a), torch.from_numpy(b)
    tb.copy_(ta)
    torch_s = median_time(lambda: tb.copy_(ta), repeats)
    moved = 2 * a.nbytes
    return {"numpy": moved / numpy_s / 1e9, "torch": moved / torch_s / 1e9}


@dataclass
class Row:
    n: int
    scheme: str
    path: str
    forward_ms: float | None = None
    forward_min_ms: float | None = None
    forward_grad_ms: float | None = None
    backward_ms: float | None = None
    backward_min_ms: float | None = None
    compile_s: float | None = None
    compile_grad_s: float | None = None
    note: str = ""
    error: str = ""


@dataclass
class SizeResult:
    n: int
    repeats: int
    numpy_ms: float
    numpy_min_ms: float
    limit_ms: float = float("nan")
    foreign_load: float | None = None
    rows: list[Row] = field(default_factory=list)


def make_case(n: int, dtype: torch.dtype = torch.float32, seed: int = 0):
    """Unit sphere on ``Grid.cube(n, 1.5)`` and random data ``u`` ``(1, 1, n, n, n)``."""
    grid = ts.Grid.cube(n, 1.5)
    phi = ts.sdf.sphere(grid, dtype=dtype)
    surface = ts.ImplicitSurface(phi, grid)
    generator = torch.Generator().manual_seed(seed)
    u = torch.rand((1, 1, n, n, n), generator=generator, dtype=dtype)
    return grid, phi, surface, u


def _ms(times: list[float]) -> tuple[float, float]:
    return 1e3 * statistics.median(times), 1e3 * min(times)


def _bench_row(row: Row, surface, u: torch.Tensor, grad: torch.Tensor, repeats: int,
               wait: Callable[[], None]) -> None:
    """Fill ``row`` with the figures of one scheme and path."""

    def forward(x: torch.Tensor = u) -> torch.Tensor:
        return ts.laplace_beltrami(x, surface, scheme=row.scheme, path=row.path)

    start = time.perf_counter()
    forward()
    first = time.perf_counter() - start
    if row.path == "compiled":
        row.compile_s = first
        forward()
    elif first > SLOW_CALL_S:
        row.forward_ms = 1e3 * first
        row.note = f"one call {first:.1f} s > {SLOW_CALL_S:g} s: rest skipped"
        return
    def quiet(warm_up) -> None:
        # after waiting, one untimed call: the first call after a pause runs on cold caches
        wait()
        warm_up()

    quiet(forward)
    row.forward_ms, row.forward_min_ms = _ms(sample_times(forward, repeats))

    # graph-recording forward, then backward alone
    x = u.detach().clone().requires_grad_(True)
    start = time.perf_counter()
    forward(x).backward(grad)
    first = time.perf_counter() - start
    if row.path == "compiled":
        row.compile_grad_s = first
        forward(x).backward(grad)
    x.grad = None
    quiet(lambda: forward(x))
    row.forward_grad_ms = 1e3 * median_time(lambda: forward(x), repeats)
    holder: dict[str, torch.Tensor] = {}

    def setup() -> None:
        x.grad = None
        holder["out"] = forward(x)

    quiet(lambda: forward(x).backward(grad))
    row.backward_ms, row.backward_min_ms = _ms(
        sample_times(lambda: holder["out"].backward(grad), repeats, setup)
    )


def bench_size(n: int, repeats: int, schemes=SCHEMES, paths=PATHS, log=print,
               wait: Callable[[], None] = lambda: None) -> SizeResult:
    """Every figure for one size."""
    # one shape at a time: the compiled functions recompile per shape, scheme and grad mode,
    # and dynamo's recompile limit (8 per function) would otherwise be reached across sizes.
    torch._dynamo.reset()
    grid, phi, surface, u = make_case(n)
    reference = AppendixB(phi[0, 0].numpy(), grid.spacing)
    u_np = u[0, 0].numpy()
    load = ForeignLoad()
    wait()
    reference(u_np)
    numpy_ms, numpy_min_ms = _ms(sample_times(lambda: reference(u_np), repeats))
    log(f"n={n}: numpy Appendix B {numpy_ms:.2f} ms (min {numpy_min_ms:.2f})")
    result = SizeResult(n=n, repeats=repeats, numpy_ms=numpy_ms, numpy_min_ms=numpy_min_ms)
    grad = torch.randn_like(u)

    for scheme in schemes:
        for path in paths:
            row = Row(n=n, scheme=scheme, path=path)
            result.rows.append(row)
            try:
                _bench_row(row, surface, u, grad, repeats, wait)
            except Exception as error:  # report, keep benchmarking the rest
                row.error = f"{type(error).__name__}: {error}"
                log(traceback.format_exc())
            if row.note:
                log(f"  {scheme:12s} {path:8s} {row.note}")
                continue
            log(f"  {scheme:12s} {path:8s} fwd {_fmt(row.forward_ms)} ms "
                f"(min {_fmt(row.forward_min_ms)}), fwd(grad) {_fmt(row.forward_grad_ms)} ms, "
                f"bwd {_fmt(row.backward_ms)} ms (min {_fmt(row.backward_min_ms)})"
                + (f", compile {row.compile_s:.1f}+{row.compile_grad_s or 0:.1f} s"
                   if row.compile_s is not None else "")
                + (f"  ERROR {row.error}" if row.error else ""))
    result.foreign_load = load.stop()
    return result


# --------------------------------------------------------------------------------------------
# reporting
# --------------------------------------------------------------------------------------------


def _fmt(value: float | None, digits: int = 2) -> str:
    return "—" if value is None else f"{value:.{digits}f}"


def _ratio(a: float | None, b: float | None) -> str:
    return "—" if a is None or b is None or b == 0 else f"{a / b:.2f}"


def machine_info() -> dict[str, str]:
    model = platform.processor() or "unknown"
    try:
        lscpu = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        found = re.search(r"^Model name:\s*(.+)$", lscpu, re.MULTILINE)
        if found:
            model = found.group(1).strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return {
        "cpu": model,
        "cores": str(os.cpu_count()),
        "torch threads": str(torch.get_num_threads()),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
    }


def command_line(argv: list[str]) -> str:
    tunables = os.environ.get("GLIBC_TUNABLES")
    prefix = f"GLIBC_TUNABLES={tunables} " if tunables else ""
    args = " ".join(shlex.quote(a) for a in argv)
    return f"{prefix}PYTHONPATH=. python benchmarks/bench_laplace_beltrami.py {args}".rstrip()


def markdown(results: list[SizeResult], bandwidth: dict[str, float], argv: list[str],
             run_notes: str = "") -> str:
    tunables = os.environ.get("GLIBC_TUNABLES")
    allocator = (f"`GLIBC_TUNABLES={tunables}`" if tunables
                 else "default glibc allocator (`GLIBC_TUNABLES` unset)")
    if tunables and tunables != TEAM_TUNABLES:
        allocator += " (not the team's setting)"
    info = machine_info()
    best = max(bandwidth.values())
    lines = [
        f"Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}. "
        f"Machine: {info['cpu']}, {info['cores']} cores, torch {info['torch']} "
        f"({info['torch threads']} threads), numpy {info['numpy']}, Python {info['python']}.",
        "",
        f"Allocator: {allocator}.",
        "",
        "Command:",
        "",
        "```",
        command_line(argv),
        "```",
        "",
        "Memory bandwidth (512 MB float32 copy, read + write counted, median of 7): "
        f"numpy {bandwidth['numpy']:.1f} GB/s, torch {bandwidth['torch']:.1f} GB/s. "
        f"Traffic limit of one application = {BYTES_PER_VOXEL} bytes/voxel × n³ / "
        f"{best:.1f} GB/s (the faster copy). {run_notes}".rstrip(),
        "",
        "Unit sphere on `Grid.cube(n, 1.5)`, float32, `u` random `(1, 1, n, n, n)`. Medians "
        "(and minima) of the repeats given per size, after warm-up; the compiled path's first "
        "calls (compilation) are excluded and listed as compile time (no-grad forward + "
        "grad-recording forward and backward). `numpy` is the plain numpy Appendix-B "
        "reference (conservative scheme) in benchmarks/bench_laplace_beltrami.py; "
        "speed-up = numpy time / torch time, medians, every scheme against that one "
        "reference (symmetric does twice the stencil work of conservative; octant sums its "
        "eight compositions in closed form). `fwd` has `u` not requiring "
        "grad; `fwd (grad)` records the graph; `bwd` is `out.backward(grad)` alone; "
        "`bwd / fwd` divides the medians of those two. Foreign load: the share of the "
        "machine's CPU time used by other processes (including torch.compile's worker "
        "processes) while the size ran; the script waits for the machine to go quiet before "
        "each timed block (`--idle-wait`, within `--idle-budget`), but figures taken under "
        "foreign load are "
        "pessimistic, the minima less so.",
        "",
    ]
    for result in results:
        load = ("unknown" if result.foreign_load is None
                else f"{100 * result.foreign_load:.0f}%")
        lines += [
            f"### n = {result.n} (n³ = {result.n ** 3:,} voxels), {result.repeats} repeats",
            "",
            f"numpy Appendix B: {result.numpy_ms:.2f} ms (min {result.numpy_min_ms:.2f}); "
            f"traffic limit: {result.limit_ms:.2f} ms; foreign load: {load}.",
            "",
            "| scheme | path | fwd ms | fwd min ms | speed-up vs numpy | fwd / limit "
            "| fwd (grad) ms | bwd ms | bwd min ms | bwd / fwd | compile s | note |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
        ]
        for row in result.rows:
            compile_s = ("—" if row.compile_s is None
                         else f"{row.compile_s:.1f} + {row.compile_grad_s or 0:.1f}")
            note = row.note or (f"error: {row.error}" if row.error else "")
            lines.append(
                f"| {row.scheme} | {row.path} | {_fmt(row.forward_ms)} "
                f"| {_fmt(row.forward_min_ms)} | {_ratio(result.numpy_ms, row.forward_ms)} "
                f"| {_ratio(row.forward_ms, result.limit_ms)} | {_fmt(row.forward_grad_ms)} "
                f"| {_fmt(row.backward_ms)} | {_fmt(row.backward_min_ms)} "
                f"| {_ratio(row.backward_ms, row.forward_ms)} | {compile_s} | {note} |"
            )
        lines.append("")
    return "\n".join(lines)


def section_key() -> str:
    tunables = os.environ.get("GLIBC_TUNABLES")
    if not tunables:
        return "default allocator"
    return "team GLIBC_TUNABLES" if tunables == TEAM_TUNABLES else f"GLIBC_TUNABLES={tunables}"


def main(argv: list[str] | None = None) -> list[SizeResult]:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 256])
    parser.add_argument("--repeats", type=int, default=7, help="timed calls per figure")
    parser.add_argument("--repeats-large", type=int, default=3,
                        help="timed calls per figure for n >= 256, at most --repeats")
    parser.add_argument("--schemes", nargs="+", default=list(SCHEMES), choices=SCHEMES)
    parser.add_argument("--paths", nargs="+", default=list(PATHS), choices=PATHS)
    parser.add_argument("--output", type=Path, default=None,
                        help="write/replace this benchmark's section in this markdown file "
                             "(e.g. docs/benchmarks.md)")
    parser.add_argument("--idle-wait", type=float, default=15.0,
                        help="seconds to wait at most, before each timed block, for other "
                             "processes to leave the CPUs (0: do not wait)")
    parser.add_argument("--idle-budget", type=float, default=180.0,
                        help="total seconds the whole run may spend waiting for idle CPUs")
    parser.add_argument("--warm-cache", action="store_true",
                        help="use torch.compile's shared on-disk cache (default: a fresh "
                             "private cache directory, so that compile times are cold)")
    args = parser.parse_args(argv)
    if args.warm_cache:
        return run(args, argv)
    cache_dir = tempfile.mkdtemp(prefix="bench_lb_inductor_")
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = cache_dir
    try:
        return run(args, argv)
    finally:
        shutil.rmtree(cache_dir, ignore_errors=True)


def run(args: argparse.Namespace, argv: list[str]) -> list[SizeResult]:
    """The benchmark proper, for parsed ``args`` (``argv`` is quoted in the report)."""

    def log(message: str) -> None:
        print(message, file=sys.stderr, flush=True)

    log(f"GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', '(unset)')}")
    wait = IdleWaiter(args.idle_wait, args.idle_budget, log)
    wait()
    load = ForeignLoad()
    bandwidth = memory_bandwidth()
    bandwidth_load = load.stop()
    best = max(bandwidth.values())
    log(f"bandwidth: numpy {bandwidth['numpy']:.1f} GB/s, torch {bandwidth['torch']:.1f} GB/s")
    results = []
    for n in args.sizes:
        repeats = args.repeats if n < 256 else min(args.repeats, args.repeats_large)
        result = bench_size(n, repeats, args.schemes, args.paths, log, wait)
        result.limit_ms = 1e3 * BYTES_PER_VOXEL * n**3 / (best * 1e9)
        results.append(result)
    run_notes = (
        ("" if bandwidth_load is None
         else f"Foreign load during the bandwidth copy: {100 * bandwidth_load:.0f}%. ")
        + f"Time spent waiting for idle CPUs: {wait.spent_s:.0f} s."
    )
    body = markdown(results, bandwidth, argv, run_notes)
    print(body)
    if args.output is not None:
        key = section_key()  # one section per allocator setting
        write_section(args.output, f"{SECTION} [{key}]",
                      f"## Laplace–Beltrami forward and backward ({key})", body)
        log(f"wrote section to {args.output}")
    return results


if __name__ == "__main__":
    main()
