"""Every intrinsic operator against one Laplace–Beltrami application per channel, in one run.

For each size ``n`` (unit sphere on ``Grid.cube(n, 1.5)``, float32) and each operator the
script times the forward with data not requiring grad (median of ``--repeats`` calls after
warm-up), the forward that records the graph plus its backward, and the first call (compile
time on the compiled path). The first no-grad call and the first recorded one run inside
:func:`torchsurf.backend.warm_up`, so that ``"auto"`` runs what it settles on in a long run
(compiled) rather than the eager calls before its payback. Each figure is divided by the
channels the operator acts on and by the octant Laplace–Beltrami's time measured in the same
run, their calls alternated. The forward times are the process's CPU time
(``time.process_time``), not wall time: on a machine shared with other jobs the wall-time ratio
of Laplace–Beltrami against itself read 0.46–1.02 over six runs (an audit, load average 5–6),
the CPU-time one 0.97–1.01; run with one thread (``--threads 1``), where the process's CPU time
is the kernels' own. The traffic limit of one
Laplace–Beltrami application (24 bytes per voxel at the measured copy bandwidth) is printed
beside them.

Operators: the Laplace–Beltrami schemes; edge-stopping diffusion (total variation,
Perona–Malik; per channel and coupled over 3 channels, as the harmonic-map and colour flows use
it); directional diffusion; the intrinsic gradient; the rate of the harmonic-map flow (coupled
diffusion + gradient energy, 3 channels) and of the colour flow (per step, the harmonic map of
the chroma plus the total variation of the brightness; per channel of the RGB image).

Run with the team's allocator setting and one thread (the issue's figures are single-thread)::

    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        PYTHONPATH=. python benchmarks/bench_operators.py --sizes 128 --threads 1 \\
        --output docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import datetime
import importlib.util
import os
import shlex
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch
from _report import write_section  # benchmarks/_report.py, beside this script

import torchsurf as ts
from torchsurf.flows import ColorDenoise, HarmonicMapFlow

SECTION = "bench_operators"
MAX_RATIO = 2.0
"""Target: every operator within this factor of one Laplace–Beltrami application per channel."""


def _load_sibling(name: str):
    path = Path(__file__).with_name(f"{name}.py")
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


_lb_bench = _load_sibling("bench_laplace_beltrami")


@dataclass
class Case:
    name: str
    channels: int
    call: Callable[[torch.Tensor], torch.Tensor]
    data: Callable[[int], torch.Tensor]


@dataclass
class Row:
    name: str
    channels: int
    first_s: float
    forward_ms: float
    backward_ms: float
    ratio: float
    """Forward time per channel over Laplace–Beltrami's, timed alternately."""


def alternated_times(first: Callable[[], object], second: Callable[[], object], repeats: int,
                     clock: Callable[[], float] = time.process_time
                     ) -> tuple[list[float], list[float]]:
    """Times in seconds by ``clock`` (default the process's CPU time) of ``repeats`` calls of
    each, ``first`` and ``second`` in turn."""
    times: tuple[list[float], list[float]] = ([], [])
    for _ in range(repeats):
        for function, samples in zip((first, second), times, strict=True):
            start = clock()
            function()
            samples.append(clock() - start)
    return times


def _flow_rate(flow: ts.flows.Flow, surface: ts.ImplicitSurface, u0: torch.Tensor
               ) -> Callable[[torch.Tensor], torch.Tensor]:
    system = flow.system(u0, surface)
    return system.rate


def cases(surface: ts.ImplicitSurface, n: int, path: str) -> list[Case]:
    """The operators, each a function of data ``(1, C, n, n, n)``."""
    generator = torch.Generator().manual_seed(0)

    def scalar(channels: int) -> torch.Tensor:
        return torch.rand((1, channels, n, n, n), generator=generator)

    def unit(channels: int) -> torch.Tensor:
        u = torch.randn((1, channels, n, n, n), generator=generator)
        return u / u.norm(dim=1, keepdim=True)

    direction = unit(3)
    harmonic_u0 = unit(3)
    harmonic = _flow_rate(HarmonicMapFlow(1e-3, path=path), surface, harmonic_u0)
    colour = ColorDenoise(1e-3, path=path)
    colour_rates = colour.chroma.system(harmonic_u0, surface).rate, \
        colour.brightness.system(scalar(1), surface).rate

    def colour_state(channels: int) -> torch.Tensor:
        """What ``ColorDenoise``'s two flows evolve: the chroma (3) and the brightness (1)."""
        return torch.cat([unit(3), scalar(1) + 0.5], dim=1)

    def colour_rate(state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        # each step evaluates both rates; the image's conversion to and from them is once
        # per call, not per step, and not timed here
        return colour_rates[0](state[:, :3]), colour_rates[1](state[:, 3:])

    return [
        Case("laplace_beltrami octant", 1, lambda u: ts.laplace_beltrami(u, surface, path=path), scalar),
        Case("laplace_beltrami symmetric", 1,
             lambda u: ts.laplace_beltrami(u, surface, "symmetric", path), scalar),
        Case("laplace_beltrami conservative", 1,
             lambda u: ts.laplace_beltrami(u, surface, "conservative", path), scalar),
        Case("anisotropic TV", 1, lambda u: ts.anisotropic_diffusion(u, surface, eps=1e-2, path=path),
             scalar),
        Case("anisotropic Perona–Malik", 1,
             lambda u: ts.anisotropic_diffusion(u, surface, "perona_malik", path=path), scalar),
        Case("anisotropic TV octant", 1,
             lambda u: ts.anisotropic_diffusion(u, surface, scheme="octant", path=path), scalar),
        Case("anisotropic coupled (3 ch)", 3,
             lambda u: ts.anisotropic_diffusion(u, surface, coupled=True, path=path), unit),
        Case("directional", 1, lambda u: ts.directional_diffusion(u, surface, direction, path=path),
             scalar),
        Case("intrinsic gradient", 1, lambda u: ts.intrinsic_gradient(u, surface, path), scalar),
        Case("harmonic-map rate (3 ch)", 3, harmonic, unit),
        Case("colour rate (3 ch)", 3, colour_rate, colour_state),
    ]


def time_case(case: Case, repeats: int, baseline: Case) -> Row:
    u = case.data(case.channels)
    base_u = baseline.data(baseline.channels)
    # the first calls inside warm_up: "auto" compiles at once what a flow run or a training
    # loop compiles after seconds of eager work, so that the rows are its steady state
    with torch.no_grad():
        start = time.perf_counter()
        with ts.backend.warm_up():
            case.call(u)
        first = time.perf_counter() - start
        case.call(u)
        times, base_times = alternated_times(lambda: case.call(u),
                                             lambda: baseline.call(base_u), repeats)
        forward = statistics.median(times)
        ratio = forward / statistics.median(base_times) / case.channels
    leaf = u.clone().requires_grad_(True)

    def forward_backward() -> None:
        values = case.call(leaf)
        values = values if isinstance(values, tuple) else (values,)
        torch.autograd.backward(values, [torch.ones_like(v) for v in values])

    with ts.backend.warm_up():
        forward_backward()

    both = statistics.median(_lb_bench.sample_times(forward_backward, max(3, repeats // 2)))
    return Row(case.name, case.channels, first, 1e3 * forward, 1e3 * both, ratio)


def bench_size(n: int, repeats: int, path: str, log=print, only: list[str] | None = None
               ) -> list[Row]:
    grid = ts.Grid.cube(n, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float32), grid)
    rows = []
    every = cases(surface, n, path)
    chosen = every if only is None else [every[0]] + [
        case for case in every[1:] if any(case.name.startswith(prefix) for prefix in only)]
    for case in chosen:
        row = time_case(case, repeats, every[0])
        log(f"  n={n} {row.name}: first {row.first_s:.1f} s, fwd {row.forward_ms:.2f} ms, "
            f"fwd+bwd {row.backward_ms:.2f} ms, "
            f"per ch / LB {row.ratio:.2f}")
        rows.append(row)
    return rows


def markdown(results: dict[int, list[Row]], bandwidth: dict[str, float], path: str,
             argv: list[str]) -> str:
    info = _lb_bench.machine_info()
    tunables = os.environ.get("GLIBC_TUNABLES")
    allocator = f"`GLIBC_TUNABLES={tunables}`" if tunables else "default glibc allocator"
    best = max(bandwidth.values())
    command = " ".join(shlex.quote(a) for a in argv)
    prefix = f"GLIBC_TUNABLES={tunables} " if tunables else ""
    lines = [
        f"Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}. "
        f"Machine: {info['cpu']}, {info['cores']} cores, torch {info['torch']} "
        f"({info['torch threads']} threads). Allocator: {allocator}. Path: `{path}`.",
        "",
        f"Command: `{prefix}PYTHONPATH=. python benchmarks/bench_operators.py {command}`",
        "",
        f"Copy bandwidth {best:.1f} GB/s. Unit sphere on `Grid.cube(n, 1.5)`, float32. "
        "`fwd ms` is the process's CPU time of a forward (`time.process_time`; wall time "
        "on a shared machine varied twice as much); `fwd + bwd ms` is wall time. "
        "`per ch / LB` is the forward time per channel over the octant Laplace–Beltrami's, "
        "their calls alternated (medians of each; target "
        f"≤ {MAX_RATIO:g}). `first s` is the first call "
        "(compilation on the compiled path).",
        "",
    ]
    for n, rows in results.items():
        limit_ms = 1e3 * _lb_bench.BYTES_PER_VOXEL * n**3 / (best * 1e9)
        lines += [
            f"### n = {n}: traffic limit of one Laplace–Beltrami application {limit_ms:.2f} ms",
            "",
            "| operator | channels | fwd ms | per ch / LB | fwd + bwd ms | first s |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for row in rows:
            lines.append(
                f"| {row.name} | {row.channels} | {row.forward_ms:.2f} "
                f"| {row.ratio:.2f} | {row.backward_ms:.2f} | {row.first_s:.1f} |"
            )
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict[int, list[Row]]:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[128])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--path", default="auto", choices=ts.backend.PATHS)
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument("--cases", nargs="+", default=None,
                        help="time only the operators whose names start with these (the first, "
                        "the octant Laplace-Beltrami, always runs: it is the baseline)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    bandwidth = _lb_bench.memory_bandwidth()
    print(f"copy bandwidth: {max(bandwidth.values()):.1f} GB/s")
    results = {n: bench_size(n, args.repeats, args.path, only=args.cases) for n in args.sizes}
    body = markdown(results, bandwidth, args.path, argv)
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION, "## Every operator against Laplace–Beltrami", body)
    return results


if __name__ == "__main__":
    main()
