"""What compiling costs and what it buys: first calls, steady times and the path ``"auto"`` picks.

For each public operator and each learning layer, on a unit sphere on ``Grid.cube(n, 1.5)``
with data ``(B, C, n, n, n)`` (default ``n = 64``, ``B = 4``, float32), and for each ``path``
of :data:`torchsurf.backend.PATHS`, one fresh process measures:

- ``first fwd``: the process's first call, no grad (for ``"compiled"``, the compiler's start-up
  and the kernels' compilation; for a flow, also what the surface computes once: the band's
  bound, the closest-point stencils);
- ``first train``: the first forward + backward after it, data (and a layer's parameters)
  requiring grad (the grad-recording and backward kernels compile here);
- ``steady fwd`` / ``steady train``: the fastest of ``--repeats`` calls once warm.

Each measurement runs in a fresh process with an empty inductor cache
(``TORCHINDUCTOR_CACHE_DIR`` a new directory: a new machine, a CI job) and, for the paths that
compile (``--warm-paths``), again with the cache the first run left (a later process on the same
machine). After the first calls, the calls go on until ``"auto"`` has decided every kernel
(compiled once its eager time paid back and compared with eager) and the paths it picks stop
changing (``--warmup-budget`` seconds at most): ``auto warm-up s``, the time that took. The
table lists what ``"auto"`` picked in a steady forward + backward (counts of kernel calls per
path). ``warm_up`` is ``"auto"`` with the first calls inside :func:`torchsurf.backend.warm_up`.

Operators: ``laplace_beltrami`` in each scheme, ``anisotropic_diffusion`` (total variation,
per channel in the symmetric and octant schemes, and coupled over 3 channels),
``directional_diffusion``, ``intrinsic_gradient``,
``intrinsic_divergence`` (3 channels), and the rates of the heat, anisotropic (TV),
harmonic-map (3 channels) and colour (3 channels) flows; layers: ``HeatFlow`` (RKC, ``t = 16
h^2``), ``AnisotropicFlow`` (TV, ``eps = 1e-2``, ``t = h^2 / 4``), ``LearnedDiffusion`` and
``DiffusionBlock`` (4 channels, times ``0.5, 2, 8, 32 h^2``).

Run with one thread and the team's allocator setting; the machine is shared, so compare ratios
within one run::

    OMP_NUM_THREADS=1 \\
    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        PYTHONPATH=. python benchmarks/bench_compile.py --output docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import collections
import contextlib
import datetime
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from _report import write_section  # benchmarks/_report.py, beside this script

import torchsurf as ts
from torchsurf import backend
from torchsurf.flows import AnisotropicFlow, ColorDenoise, HarmonicMapFlow, HeatFlow

SECTION = "bench_compile"
FIRST_CALL_TARGET_S = 10.0
"""The issue's target for the first call of a layer at 64^3."""

OPERATORS = (
    "lb_octant", "lb_symmetric", "lb_conservative", "lb_central", "anisotropic_tv",
    "anisotropic_tv_octant", "anisotropic_coupled", "directional", "gradient", "divergence", "heat_rate",
    "anisotropic_rate", "harmonic_rate", "colour_rate",
)
LAYERS = ("HeatFlow", "AnisotropicFlow", "LearnedDiffusion", "DiffusionBlock")
CHANNELS = {"anisotropic_coupled": 3, "divergence": 3, "harmonic_rate": 3, "colour_rate": 3,
            "LearnedDiffusion": 4, "DiffusionBlock": 4}
LEARNED_TIMES = [0.5, 2.0, 8.0, 32.0]
"""``h^2`` units: the example of docs/learning.md."""


@dataclass
class Measurement:
    """One process's figures; seconds for first calls, milliseconds for steady calls."""

    item: str
    path: str
    cache: str
    first_forward_s: float
    first_train_s: float
    warmup_s: float
    steady_forward_ms: float
    steady_train_ms: float
    picks_forward: dict[str, int] = field(default_factory=dict)
    picks_train: dict[str, int] = field(default_factory=dict)
    error: str = ""


def _unit(shape: tuple[int, ...], generator: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    u = torch.randn(shape, generator=generator, dtype=dtype)
    return u / u.norm(dim=1, keepdim=True)


def build(item: str, path: str, n: int, batch: int, dtype: torch.dtype
          ) -> tuple[Callable[[torch.Tensor], torch.Tensor], torch.Tensor, list[torch.Tensor]]:
    """``(call, data, parameters)``: ``call(data)`` is the operator or layer on ``path``."""
    grid = ts.Grid.cube(n, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=dtype), grid)
    surface.haloed()
    h = surface.spacing
    generator = torch.Generator().manual_seed(0)
    channels = CHANNELS.get(item, 1)
    shape = (batch, channels, n, n, n)
    data = torch.rand(shape, generator=generator, dtype=dtype)
    parameters: list[torch.Tensor] = []
    if item.startswith("lb_"):
        scheme = item[3:]
        return (lambda u: ts.laplace_beltrami(u, surface, scheme, path)), data, parameters
    if item in ("anisotropic_tv", "anisotropic_tv_octant"):
        scheme = "octant" if item.endswith("octant") else "symmetric"
        return (lambda u: ts.anisotropic_diffusion(u, surface, eps=1e-2, scheme=scheme,
                                                   path=path)), data, []
    if item == "anisotropic_coupled":
        data = _unit(shape, generator, dtype)
        return (lambda u: ts.anisotropic_diffusion(u, surface, eps=1e-2, coupled=True,
                                                   path=path)), data, []
    if item == "directional":
        direction = _unit((1, 3, n, n, n), generator, dtype)
        return (lambda u: ts.directional_diffusion(u, surface, direction, path=path)), data, []
    if item == "gradient":
        return (lambda u: ts.intrinsic_gradient(u, surface, path)), data, []
    if item == "divergence":
        return (lambda v: ts.intrinsic_divergence(v, surface, path)), data, []
    if item == "heat_rate":
        return HeatFlow(16 * h * h, path=path).system(data, surface).rate, data, []
    if item == "anisotropic_rate":
        return AnisotropicFlow(h * h, path=path).system(data, surface).rate, data, []
    if item == "harmonic_rate":
        data = _unit(shape, generator, dtype)
        return HarmonicMapFlow(h * h, path=path).system(data, surface).rate, data, []
    if item == "colour_rate":
        colour = ColorDenoise(h * h, path=path)
        chroma = colour.chroma.system(_unit(shape, generator, dtype), surface).rate
        brightness = colour.brightness.system(data[:, :1], surface).rate

        def colour_rate(image: torch.Tensor) -> torch.Tensor:
            norm = torch.sqrt((image**2).sum(dim=1, keepdim=True) + colour.eps**2)
            return torch.cat([chroma(image / norm), brightness(norm)], dim=1)

        return colour_rate, data, []
    if item in ("HeatFlow", "AnisotropicFlow"):
        flow = (HeatFlow(16 * h * h, path=path) if item == "HeatFlow"
                else AnisotropicFlow(h * h / 4, path=path))
        return (lambda u: flow(u, surface)), data, []
    if item == "LearnedDiffusion":
        layer = ts.nn.LearnedDiffusion(channels, time=LEARNED_TIMES, path=path).to(dtype)
    elif item == "DiffusionBlock":
        layer = ts.nn.DiffusionBlock(channels, time=LEARNED_TIMES, path=path).to(dtype)
        torch.nn.init.normal_(layer.mlp[-1].weight, std=0.1, generator=generator)
    else:
        raise ValueError(f"unknown item {item!r}; choose from {OPERATORS + LAYERS}")
    return (lambda u: layer(u, surface)), data, list(layer.parameters())


def _recorded(function: Callable[[], object]) -> tuple[float, dict[str, int]]:
    """Wall seconds of ``function()`` and the paths ``"auto"`` picked inside it."""
    with backend.recorded_paths() as picks:
        start = time.perf_counter()
        function()
        seconds = time.perf_counter() - start
    return seconds, dict(collections.Counter(picks))


def _pending() -> bool:
    """Whether ``"auto"`` has a kernel it has not decided on yet: still eager and not paid
    back, or compiled and not yet compared with eager (the backend's own record)."""
    return any(timing.pending for timing in backend._TIMINGS.values())


def measure(item: str, path: str, cache: str, n: int, batch: int, dtype: torch.dtype,
            repeats: int, warmup_budget: float) -> Measurement:
    """Run ``item`` on ``path`` in this process (which should be fresh) and time it;
    ``path="warm_up"`` is ``"auto"`` with the first two calls in :func:`backend.warm_up`."""
    warming = backend.warm_up() if path == "warm_up" else contextlib.nullcontext()
    call, data, parameters = build(item, "auto" if path == "warm_up" else path, n, batch, dtype)
    leaf = data.clone().requires_grad_(True)
    weights: list[torch.Tensor] = []  # a fixed random cotangent, shaped as the output

    def forward() -> None:
        with torch.no_grad():
            call(data)

    def train() -> None:
        for p in [leaf, *parameters]:
            p.grad = None
        output = call(leaf)
        if not weights:
            weights.append(torch.rand(output.shape, generator=torch.Generator().manual_seed(1),
                                      dtype=dtype))
        (output * weights[0]).sum().backward()

    with warming:
        first_forward, _ = _recorded(forward)
        first_train, _ = _recorded(train)
    # warm up until "auto" has decided every kernel and the paths picked stop changing
    start, history = time.perf_counter(), []
    while True:
        seconds_f, picks_f = _recorded(forward)
        seconds_t, picks_t = _recorded(train)
        history.append((seconds_f + seconds_t, picks_f, picks_t))
        settled = len(history) >= 3 and all(h[1:] == history[-1][1:] for h in history[-3:])
        if (settled and not _pending()) or time.perf_counter() - start > warmup_budget:
            break
    warmup = time.perf_counter() - start
    forward_s = min(_recorded(forward)[0] for _ in range(repeats))
    train_s = min(_recorded(train)[0] for _ in range(repeats))
    return Measurement(item, path, cache, first_forward, first_train, warmup, 1e3 * forward_s,
                       1e3 * train_s, history[-1][1], history[-1][2])


def _child(args: argparse.Namespace, item: str, path: str, cache: str, cache_dir: str
           ) -> Measurement:
    """:func:`measure` in a fresh process with ``cache_dir`` as inductor's cache."""
    command = [sys.executable, __file__, "--child", item, path, cache, "--size", str(args.size),
               "--batch", str(args.batch), "--dtype", args.dtype, "--threads",
               str(args.threads), "--repeats", str(args.repeats), "--warmup-budget",
               str(args.warmup_budget)]
    environment = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=cache_dir,
                       OMP_NUM_THREADS=str(args.threads), TORCHSURF_COMPILE="auto")
    result = subprocess.run(command, capture_output=True, text=True, env=environment,
                            timeout=args.timeout)
    lines = [line for line in result.stdout.splitlines() if line.startswith("{")]
    if result.returncode != 0 or not lines:
        tail = (result.stderr.strip().splitlines() or ["no output"])[-1]
        nan = float("nan")
        return Measurement(item, path, cache, nan, nan, nan, nan, nan, error=tail[:200])
    return Measurement(**json.loads(lines[-1]))


def _read_record(path: Path | None) -> dict[tuple[str, str], tuple[Measurement, Measurement | None]]:
    """The rows a run interrupted earlier wrote to ``path`` (one JSON pair a line), by
    ``(item, path)``: they are not measured again."""
    if path is None or not path.exists():
        return {}
    rows = {}
    for line in path.read_text().splitlines():
        cold, warm = json.loads(line)
        rows[cold["item"], cold["path"]] = (Measurement(**cold), warm and Measurement(**warm))
    return rows


def _seconds(value: float) -> str:
    return "—" if value != value else f"{value:.1f}"


def _ms(value: float) -> str:
    return "—" if value != value else (f"{value:.0f}" if value >= 100 else f"{value:.1f}")


def _pick_text(picks: dict[str, int]) -> str:
    if not picks:
        return "—"
    return ", ".join(f"{path} {count}" for path, count in sorted(picks.items()))


def table(rows: list[tuple[Measurement, Measurement | None]]) -> str:
    """Markdown table of (cold, warm) measurement pairs."""
    lines = [
        "| item | path | first fwd s, cold / warm | first train s, cold / warm | "
        "steady fwd ms | steady train ms | auto warm-up s | picked (steady train) |",
        "|---|---|---:|---:|---:|---:|---:|---|",
    ]
    for cold, warm in rows:
        warm_forward = "—" if warm is None else _seconds(warm.first_forward_s)
        warm_train = "—" if warm is None else _seconds(warm.first_train_s)
        warm = warm or cold
        forward = min(cold.steady_forward_ms, warm.steady_forward_ms)
        train = min(cold.steady_train_ms, warm.steady_train_ms)
        automatic = cold.path in ("auto", "warm_up")
        picks = _pick_text(warm.picks_train) if automatic else ""
        warmup = _seconds(warm.warmup_s) if automatic else ""
        note = f" ({cold.error or warm.error})" if cold.error or warm.error else ""
        lines.append(
            f"| {cold.item}{note} | {cold.path} | {_seconds(cold.first_forward_s)} / "
            f"{warm_forward} | {_seconds(cold.first_train_s)} / {warm_train} | {_ms(forward)} | "
            f"{_ms(train)} | {warmup} | {picks} |"
        )
    return "\n".join(lines)


def machine(args: argparse.Namespace) -> str:
    """One line naming the CPU, the threads, torch and the allocator setting."""
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    allocator = os.environ.get("GLIBC_TUNABLES", "default")
    return (f"{model}, {os.cpu_count()} cores, torch {torch.__version__}, {args.threads} "
            f"thread(s), allocator `GLIBC_TUNABLES={allocator}`")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=64, help="n: grid of n^3 nodes")
    parser.add_argument("--batch", type=int, default=4, help="B")
    parser.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5, help="steady calls timed (fastest kept)")
    parser.add_argument("--operators", nargs="*", default=list(OPERATORS), choices=OPERATORS)
    parser.add_argument("--layers", nargs="*", default=list(LAYERS), choices=LAYERS)
    paths = (*backend.PATHS, "warm_up")
    parser.add_argument("--paths", nargs="+", default=list(paths), choices=paths,
                        help="warm_up: auto, its first calls inside torchsurf.backend.warm_up()")
    parser.add_argument("--layer-paths", nargs="+", choices=paths,
                        help="paths for the layers (default: --paths)")
    parser.add_argument("--warmup-budget", type=float, default=240.0,
                        help="seconds of warm-up at most before the steady calls")
    parser.add_argument("--timeout", type=float, default=3600.0, help="seconds per process")
    parser.add_argument("--warm-paths", nargs="*", default=["auto", "compiled", "warm_up"],
                        choices=paths, help="paths also run with the cache a cold run left")
    parser.add_argument("--output", type=Path, help="write the table into this markdown file")
    parser.add_argument("--record", type=Path,
                        help="append each row to this JSON-lines file, and skip the rows it "
                        "already holds (to resume an interrupted run)")
    parser.add_argument("--child", nargs=3, metavar=("ITEM", "PATH", "CACHE"),
                        help=argparse.SUPPRESS)
    return parser.parse_args(argv)


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    dtype = getattr(torch, args.dtype)
    if args.child:
        torch.set_num_threads(args.threads)
        item, path, cache = args.child
        result = measure(item, path, cache, args.size, args.batch, dtype, args.repeats,
                         args.warmup_budget)
        print(json.dumps(asdict(result)), flush=True)
        return
    started = datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")
    load_start = os.getloadavg()[0]
    recorded = _read_record(args.record)
    rows: list[tuple[Measurement, Measurement | None]] = []
    jobs = [(item, args.paths) for item in args.operators]
    jobs += [(item, args.layer_paths or args.paths) for item in args.layers]
    for item, paths in jobs:
        for path in paths:
            if (item, path) in recorded:
                rows.append(recorded[item, path])
                continue
            with tempfile.TemporaryDirectory(prefix="inductor-") as cache_dir:
                cold = _child(args, item, path, "cold", cache_dir)
                warm = (_child(args, item, path, "warm", cache_dir) if path in args.warm_paths
                        else None)
            rows.append((cold, warm))
            if args.record is not None:
                with args.record.open("a") as record:
                    record.write(json.dumps([asdict(cold), warm and asdict(warm)]) + "\n")
            print(table([rows[-1]]).splitlines()[-1], flush=True)
    load_end = os.getloadavg()[0]
    warmed = [path for path in args.warm_paths if any(path in paths for _, paths in jobs)]
    command = " ".join(["python", "benchmarks/bench_compile.py", *map(shlex.quote, argv or sys.argv[1:])])
    body = "\n".join([
        f"Date: {started}. Machine: {machine(args)}; load average {load_start:.1f} at the "
        f"start, {load_end:.1f} at the end (a shared machine: figures taken under other "
        "jobs' load are pessimistic, the ratios within a row are what to read).",
        "",
        f"Command: `OMP_NUM_THREADS={args.threads} PYTHONPATH=. {command}`",
        "",
        f"Unit sphere on `Grid.cube({args.size}, 1.5)`, data `({args.batch}, C, {args.size}, "
        f"{args.size}, {args.size})` {args.dtype} (C = 1 unless named). Every row is a fresh "
        "process with an empty `TORCHINDUCTOR_CACHE_DIR` (`cold`)"
        + (f", and for {', '.join(warmed)} a second one with the cache the first left "
           "(`warm`). " if warmed else ". ") +
        "`first fwd`: the process's first call, no grad; `first train`: the "
        "first forward + backward after it; steady: the fastest of "
        f"{args.repeats} calls once warm. `picked`: the kernel calls of one steady forward + "
        "backward under `path=\"auto\"`, by the path it chose.",
        "",
        table(rows),
    ])
    print()
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION,
                      "## Compile cost: first calls, steady calls, the path auto picks", body)


if __name__ == "__main__":
    main()
