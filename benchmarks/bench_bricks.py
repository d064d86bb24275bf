"""Band storage as bricks: scale on a mesh, cost against the dense volume, time to solution.

Five parts, each against a baseline measured in the same run (peak: against the target):

- **scale**: ``bunny_closed.obj`` (``--mesh``) on a ``--resolution``^3 grid (512 by default)
  built straight into bricks (:func:`torchsurf.bricks.from_mesh`): build time, bricks, stored
  and band voxels, peak memory; one Laplace–Beltrami application (compiled, warm, median) and
  its halo gather, against the traffic limit of the band's voxels (24 bytes each at the copy
  bandwidth measured in the run), and the same by the C kernel ``path="auto"`` runs on bricks
  (every stored node, and the band only as a flow applies it); a heat flow on noise to
  ``t = (8 h)^2`` (a visible smoothing), its time and the noise left.
- **ratio**: one application on bricks against the dense volume, a sphere of radius 1.2 on
  ``[-1.5, 1.5]^3`` at ``--ratio-resolution``^3 (256): time ratio against voxel ratios, the
  compiled path over every stored node and the C kernel on the band.
- **solution**: heat flow to ``t = 0.05`` on the unit sphere (``3 z^2 - 1``) at the spacing of
  ``bench_heat_flow.py``'s ``n^3`` box for each ``n`` of ``--sizes`` (the bricks' box a few cells
  wider: they keep their band off its faces, and store only the band's bricks), on bricks with
  ``--solution-method`` (the default RKC), sampled error at 2000 points, against the mesh peer of
  ``bench_heat_flow.py`` (cotangent Laplacian, lumped mass, SuperLU backward Euler on the
  icosphere of matching resolution, fewest steps reaching 1e-3).
- **batch** (``--parts batch``, its own section): the five shared shapes (``--batch-meshes``),
  each at its own resolution (``--batch-resolutions``, :func:`torchsurf.bricks.fit_grids`) in
  one brick batch, float32, eager stencils: build and heat flow to ``t = (4 h)^2`` (each shape's
  own 4 cells), against each shape alone in its own units on its own grid to its own time, each
  run in a fresh process: times, peak resident memory and live peak, the largest difference of
  an entry to its shape alone and the maximum principle on each entry.
- **peak** (``--parts peak``, printed alone): a user's run in a fresh process, the scale part's
  build and heat flow with nothing else timed, and its resident peak (the scale part's process
  also times the compiled operator over every stored node, which leaves its heap larger).

    PYTHONPATH=. python benchmarks/bench_bricks.py --output docs/benchmarks.md
    PYTHONPATH=. python benchmarks/bench_bricks.py --resolution 128 --ratio-resolution 96 --sizes 49
    PYTHONPATH=. python benchmarks/bench_bricks.py --parts ratio scale  # C kernel, compiled
    PYTHONPATH=. python benchmarks/bench_bricks.py --parts solution --sizes 25 29 --solution-method euler
    PYTHONPATH=. python benchmarks/bench_bricks.py --parts batch --output docs/benchmarks.md

Peak memory is the process's maximum resident set (``ru_maxrss``), so it is cumulative: the
scale part runs first (the batch part's runs each have a process of their own).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from _report import cpu_model, write_section  # benchmarks/_report.py, beside this script

import torchsurf as ts
from torchsurf import bricks
from torchsurf.bricks import _native
from torchsurf.operators import functional

SECTION = "bench_bricks"
BYTES_PER_VOXEL = 24
"""Traffic of one Laplace–Beltrami application per voxel: ``u`` read, result written, and
normals and weight read (float32), as in ``bench_laplace_beltrami.py``."""
MESHES = Path(os.environ.get("TORCHSURF_MESH_DIR",
                             Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"))


def _load_sibling(name: str):
    path = Path(__file__).with_name(f"{name}.py")
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


_heat_bench = _load_sibling("bench_heat_flow")
_learned_bench = _load_sibling("bench_learned_diffusion")


def peak_gb() -> float:
    """Maximum resident set of this process so far, GB (``ru_maxrss`` is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9


def copy_bandwidth() -> float:
    """Copy bandwidth, GB/s, measured in a child process (``bench_laplace_beltrami``'s
    ``memory_bandwidth``): its 1 GB of buffers would otherwise count in this process's peak
    memory, which the scale part reports."""
    code = ("import json, sys; sys.path.insert(0, sys.argv[1]); import bench_laplace_beltrami "
            "as b; print(json.dumps(max(b.memory_bandwidth().values())))")
    done = subprocess.run([sys.executable, "-c", code, str(Path(__file__).parent)],
                          capture_output=True, text=True, check=True)
    return float(done.stdout.strip().splitlines()[-1])


RATIO_PAIRS = 7
"""Dense and brick applications timed alternately this many times (``--parts ratio``)."""


def median_ms(function, repeats: int = 5) -> float:
    function()
    function()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append(time.perf_counter() - start)
    return 1e3 * statistics.median(samples)


def scale(mesh_path: Path, resolution: int, bandwidth: float) -> dict[str, float]:
    mesh = ts.mesh.load(mesh_path)
    # 5% of the mesh a side, and at least the 6 free cells bricks need (small --resolution)
    grid = ts.mesh.fit_grid(mesh, resolution, margin=max(0.05, 6.0 / max(resolution - 13, 1)))
    start = time.perf_counter()
    surface = bricks.from_mesh(mesh, grid, dtype=torch.float32)
    build_s = time.perf_counter() - start
    layout = surface.layout
    band = surface.band_mask()
    band_voxels = int(band.sum())
    stored = len(layout) * bricks.BRICK**3
    built_gb = peak_gb()
    u = torch.randn(len(layout), 1, 8, 8, 8, generator=torch.Generator().manual_seed(0))
    start = time.perf_counter()
    ts.laplace_beltrami(u, surface, path="compiled")
    first_s = time.perf_counter() - start
    lb_ms = median_ms(lambda: ts.laplace_beltrami(u, surface, path="compiled"))
    halo_ms = median_ms(lambda: layout.halo(u, 1))
    native_ms, native_band_ms, planes_ms, native_first_s = _native_times(u, surface, band)
    limit_ms = 1e3 * BYTES_PER_VOXEL * band_voxels / (bandwidth * 1e9)
    stored_limit_ms = 1e3 * BYTES_PER_VOXEL * stored / (bandwidth * 1e9)
    time_ = (8 * grid.spacing) ** 2
    flow = ts.flows.HeatFlow(time=time_)
    start = time.perf_counter()
    with torch.no_grad():
        flow(u, surface)
    flow_first_s = time.perf_counter() - start
    start = time.perf_counter()
    with torch.no_grad():
        smoothed = flow(u, surface)
    flow_s = time.perf_counter() - start
    return {
        "resolution": resolution, "spacing": grid.spacing, "build_s": build_s,
        "bricks": len(layout), "stored": stored, "band": band_voxels,
        "dense": math.prod(grid.shape), "built_gb": built_gb, "first_s": first_s,
        "lb_ms": lb_ms, "halo_ms": halo_ms, "limit_ms": limit_ms, "native_ms": native_ms,
        "native_band_ms": native_band_ms, "native_first_s": native_first_s,
        "planes_ms": planes_ms,
        "stored_limit_ms": stored_limit_ms, "flow_time": time_, "flow_s": flow_s,
        "flow_first_s": flow_first_s,
        "noise_before": float(u[band].std()), "noise_after": float(smoothed[band].std()),
        "peak_gb": peak_gb(),
    }


def peak_run(mesh_path: Path, resolution: int) -> dict[str, float]:
    """A user's run alone, in this (fresh) process: the bricks built from the mesh and the
    heat flow of :func:`scale` called twice; its resident peak, with nothing else timed in the
    process (the scale part also times the compiled operator over every stored node, whose
    halos leave the heap larger)."""
    mesh = ts.mesh.load(mesh_path)
    grid = ts.mesh.fit_grid(mesh, resolution, margin=max(0.05, 6.0 / max(resolution - 13, 1)))
    start = time.perf_counter()
    surface = bricks.from_mesh(mesh, grid, dtype=torch.float32)
    build_s = time.perf_counter() - start
    built_gb = peak_gb()
    u = torch.randn(len(surface.layout), 1, 8, 8, 8, generator=torch.Generator().manual_seed(0))
    flow = ts.flows.HeatFlow(time=(8 * grid.spacing) ** 2)
    seconds = []
    with torch.no_grad():
        for _ in range(2):
            start = time.perf_counter()
            flow(u, surface)
            seconds.append(time.perf_counter() - start)
    return {"resolution": resolution, "build_s": build_s, "built_gb": built_gb,
            "flow_first_s": seconds[0], "flow_s": seconds[1], "steps": flow.last_plan.count,
            "peak_gb": peak_gb()}


def peak(mesh_path: Path, resolution: int) -> str:
    """:func:`peak_run` in a fresh process, as Markdown."""
    arguments = [sys.executable, __file__, "--mesh", str(mesh_path), "--resolution",
                 str(resolution), "--peak-run"]
    done = subprocess.run(arguments, capture_output=True, text=True, check=True)
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    return (f"**A user's run alone** ({resolution}³ `{mesh_path.name}`, a fresh process: "
            f"`bricks.from_mesh`, then `HeatFlow` to (8 h)² twice): build {figures['build_s']:.1f} s, "
            f"peak after the build {figures['built_gb']:.2f} GB, flow {figures['flow_s']:.1f} s "
            f"(first call {figures['flow_first_s']:.1f} s, {figures['steps']} steps), "
            f"**peak {figures['peak_gb']:.2f} GB**.")


def _on_band(u, surface, band, path: str = "auto"):  # noqa: ANN001, ANN202
    """The octant operator on the band only, as a flow applies it (zero elsewhere)."""
    return functional.divergence_form(u, surface.normal, surface.weight, surface.spacing,
                                      "octant", path, haloed=surface.haloed(),
                                      pad=surface.layout.halo, mask=band)


def _on_band_planes(surface, band):  # noqa: ANN001, ANN202
    """The C kernel on the band reading the haloed geometry's planes, as it did before the
    packed rows (2026-12-03): the same run's baseline for them."""
    layout = surface.layout
    normal, weight = surface.haloed()
    tables = (layout.neighbours.contiguous(), layout.present.to(torch.uint8).contiguous())
    bits = _native._RowBits()
    return lambda u: _native.octant(u, normal, weight, *tables, bits, surface.spacing, False,
                                    band)


def _native_times(u, surface, band) -> tuple[float, float, float, float]:  # noqa: ANN001
    """The C kernel (``path="auto"`` on bricks, :mod:`torchsurf.bricks._native`): every stored
    node, the band only, and the band reading the haloed planes (alternated with the former),
    ms, and the loading of its library (compiling it when not cached: what a first call adds
    to the kernel's own time), s."""
    start = time.perf_counter()
    if _native.library() is None:
        return math.nan, math.nan, math.nan, math.nan
    first_s = time.perf_counter() - start
    planes = _on_band_planes(surface, band)
    band_ms, planes_ms = [], []
    for _ in range(RATIO_PAIRS):
        band_ms.append(median_ms(lambda: _on_band(u, surface, band), 3))
        planes_ms.append(median_ms(lambda: planes(u), 3))
    return (median_ms(lambda: ts.laplace_beltrami(u, surface)), statistics.median(band_ms),
            statistics.median(planes_ms), first_s)


def ratio(resolution: int) -> dict[str, float]:
    grid = ts.Grid.cube(resolution, 1.5)
    dense = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.2), grid)
    surface = bricks.from_dense(dense, flow_band=False)  # the operator's band alone
    u = torch.randn(1, 1, *grid.shape, generator=torch.Generator().manual_seed(1))
    packed = surface.from_dense(u)
    # alternated, so that the host's bursts fall on both: the ratio of each pair, and its median
    band = surface.band_mask()
    dense_ms, brick_ms, ratios, native_ms, native_ratios = [], [], [], [], []
    planes = _on_band_planes(surface, band) if _native.library() is not None else None
    planes_ms = []
    for _ in range(RATIO_PAIRS):
        dense_ms.append(median_ms(lambda: ts.laplace_beltrami(u, dense, path="compiled"), 3))
        brick_ms.append(median_ms(lambda: ts.laplace_beltrami(packed, surface, path="compiled"),
                                  3))
        native_ms.append(median_ms(lambda: _on_band(packed, surface, band), 3))
        ratios.append(brick_ms[-1] / dense_ms[-1])
        native_ratios.append(native_ms[-1] / dense_ms[-1])
        if planes is not None:
            planes_ms.append(median_ms(lambda: planes(packed), 3))
    return {
        "resolution": resolution, "dense_ms": statistics.median(dense_ms),
        "brick_ms": statistics.median(brick_ms), "ratios": ratios,
        "native_ms": statistics.median(native_ms), "native_ratios": native_ratios,
        "planes_ms": statistics.median(planes_ms) if planes_ms else math.nan,
        "stored": len(surface.layout) * bricks.BRICK**3,
        "band": int(surface.band_mask().sum()), "dense": resolution**3,
    }


SOLUTION_MARGIN = 3
"""Cells added around the dense benchmark's box (same spacing) for bricks, which keep their
band two nodes from the box's faces: they store only the band's bricks, so a wider box costs
nothing."""


def solution_grid(n: int) -> ts.Grid:
    """The dense benchmark's ``n^3`` grid's spacing on a box :data:`SOLUTION_MARGIN` cells
    wider on every side."""
    spacing = 2 * _heat_bench.BOUND / (n - 1)
    return ts.Grid.cube(n + 2 * SOLUTION_MARGIN,
                        bound=_heat_bench.BOUND + SOLUTION_MARGIN * spacing)


def solution(sizes: list[int], target: float, method: str = "rkc"
             ) -> tuple[list[dict], object]:
    """Steady-state time to ``t = 0.05``: the flow runs once untimed, with every kernel compiled
    from the first call (``COMPILE_PAYBACK_SECONDS = 0``), so that ``"auto"`` does not switch
    from eager to compiled in the middle of the timed run."""
    payback = ts.backend.COMPILE_PAYBACK_SECONDS
    ts.backend.COMPILE_PAYBACK_SECONDS = 0.0
    try:
        return _solution(sizes, target, method)
    finally:
        ts.backend.COMPILE_PAYBACK_SECONDS = payback


def _solution(sizes: list[int], target: float, method: str) -> tuple[list[dict], object]:
    rows = []
    for n in sizes:
        grid = solution_grid(n)
        phi = ts.sdf.sphere(grid, radius=1.0)
        points = grid.points()
        z = points[..., 2] / points.norm(dim=-1).clamp(min=1e-9)
        surface = bricks.from_dense(phi, grid)
        packed = surface.from_dense((3 * z**2 - 1)[None, None])
        flow = ts.flows.HeatFlow(time=_heat_bench.TIME, method=method)
        flow(packed, surface)  # compile and the surface's one-off work out of the time
        result, seconds = _heat_bench.median_timed(
            lambda flow=flow, packed=packed, surface=surface: flow(packed, surface))
        (volume,) = surface.to_dense(result)
        rows.append({"n": n, "seconds": seconds, "steps": flow.last_plan.count,
                     "error": _heat_bench.sampled_error(volume, grid),
                     "samples": _heat_bench.surface_samples(phi, grid)})
    reaching = [r for r in rows if r["error"] <= target]
    best = min(reaching, key=lambda r: r["seconds"]) if reaching else None
    # the smallest icosphere and fewest steps reaching the target (a coarser one stops short)
    peer = _heat_bench.accuracy_matched(target) if best is not None else None
    return rows, (best, peer)


BATCH_SECTION = "bench_bricks_batch"
BATCH_MESHES = ("bunny_closed", "spot", "armadillo", "teapot_closed", "fandisk")
BATCH_RESOLUTIONS = (96, 64, 80, 56, 48)
BATCH_CELLS = 4.0
"""The batch's heat flow runs to ``(BATCH_CELLS h)^2``: that many of each shape's own cells."""


def _batch_signal(points: torch.Tensor, spacing: float) -> torch.Tensor:
    """Smooth data at batch-frame points ``(N, 3, 8, 8, 8)``, waves of about ten cells."""
    x, y, z = (points[:, axis: axis + 1] / spacing for axis in range(3))
    return torch.sin(0.6 * x) * torch.cos(0.45 * (y + z))


class _Clock:
    """Wall seconds and this thread's CPU seconds since it was made: on a machine shared with
    other jobs the CPU time is the work (the library runs on one thread; the memory sampler's
    thread is not counted), the wall time what a user waits."""

    def __init__(self) -> None:
        self.wall, self.cpu = time.perf_counter(), time.thread_time()

    def read(self) -> tuple[float, float]:
        return time.perf_counter() - self.wall, time.thread_time() - self.cpu


def batch_run(meshes: list[Path], resolutions: list[int], cells: float, which: int | None,
              output: Path, repeats: int = 2) -> dict:
    """One run of the batch part in this process: the batch (``which`` is ``None``) or shape
    ``which`` alone in its own units; the flow's first call, then the fastest of ``repeats``
    more. Saves the flow's result, band and start to ``output``."""
    _learned_bench._eager_everywhere()
    loaded = [ts.mesh.load(path) for path in meshes]
    fitted = bricks.fit_grids(loaded, resolutions)
    before, live = _learned_bench._resident_mb(), _learned_bench.LivePeak()
    allocated = live.now()
    clock = _Clock()
    if which is None:
        surface = bricks.from_mesh(fitted.meshes, fitted.grids, dtype=torch.float32)
        points = surface.layout.points(torch.float32)
    else:
        surface = bricks.from_mesh(loaded[which], fitted.own_grid(which), dtype=torch.float32)
        centre = fitted.centre[which].to(torch.float32).view(1, 3, 1, 1, 1)
        points = float(fitted.scale[which]) * (surface.layout.points(torch.float32) - centre)
    build = clock.read()
    u0 = _batch_signal(points, fitted.spacing)
    flow_time = (cells * fitted.spacing) ** 2
    if which is not None:
        flow_time = float(fitted.shape_time(flow_time)[which])
    flow = ts.flows.HeatFlow(time=flow_time)
    calls = []
    with torch.no_grad():
        for _ in range(1 + repeats):
            clock = _Clock()
            result = flow(u0, surface)
            calls.append(clock.read())
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 - before
    band = surface.band_mask()
    torch.save({"u": result, "u0": u0, "band": band,
                "region": surface.layout.dilate(band), "counts": surface.layout.counts()}, output)
    return {"which": which, "bricks": len(surface.layout), "band": int(band.sum()),
            "build_wall": build[0], "first_cpu": calls[0][1],
            "steady_cpu": min(cpu for _, cpu in calls[1:]),
            "steady_wall": min(wall for wall, _ in calls[1:]),
            "peak_mb": peak, "live_mb": live.stop() - allocated}


def _spawn_batch_run(meshes: list[Path], resolutions: list[int], cells: float,
                     which: int | None, output: Path) -> dict:
    arguments = [sys.executable, __file__, "--batch-meshes", *map(str, meshes),
                 "--batch-resolutions", *map(str, resolutions), "--batch-cells", str(cells),
                 "--batch-run", "batch" if which is None else str(which), str(output)]
    done = subprocess.run(arguments, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def batch(meshes: list[Path], resolutions: list[int], cells: float) -> dict:
    """The batch and each shape alone, each in a fresh process; their figures, the largest
    difference of each entry to its shape alone, and the maximum principle on each entry."""
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        together = _spawn_batch_run(meshes, resolutions, cells, None, folder / "batch.pt")
        alone = [_spawn_batch_run(meshes, resolutions, cells, b, folder / f"{b}.pt")
                 for b in range(len(meshes))]
        saved = torch.load(folder / "batch.pt")
        differences, excess = [], []
        start = 0
        for b, count in enumerate(saved["counts"]):
            rows = slice(start, start + count)
            start += count
            own = torch.load(folder / f"{b}.pt")
            band, u = saved["band"][rows], saved["u"][rows]
            differences.append(float((u - own["u"])[band].abs().max()))
            before = saved["u0"][rows][saved["region"][rows]]
            excess.append(max(float(u[band].max() - before.max()),
                              float(before.min() - u[band].min())))
    return {"batch": together, "alone": alone, "differences": differences, "excess": excess,
            "names": [Path(m).stem for m in meshes], "resolutions": resolutions, "cells": cells}


def batch_markdown(result: dict) -> str:
    """The batch part's section body."""
    threads = torch.get_num_threads()
    names, resolutions = result["names"], result["resolutions"]
    together, alone = result["batch"], result["alone"]
    lines = [
        f"Run of {time.strftime('%Y-%m-%d')}, {cpu_model()}, {os.cpu_count()} cores, torch "
        f"{torch.__version__}, {threads} thread(s), float32, eager stencils, allocator: "
        f"GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', 'default')}, load average at the "
        f"end {os.getloadavg()[0]:.1f}. Command: `PYTHONPATH=. python "
        f"benchmarks/bench_bricks.py {' '.join(sys.argv[1:])}`.",
        "",
        f"{len(names)} shapes ({', '.join(names)}), each at its own resolution "
        "(`bricks.fit_grids`: one spacing, each shape scaled to span its grid), built "
        "straight into one brick batch (`bricks.from_mesh`), then `HeatFlow` (RKC) to "
        f"t = ({result['cells']:g} h)^2, each shape's own cells; against each shape alone "
        "in its own units on its own grid, to its own time (`FittedMeshes.shape_time`). Each "
        "run in a fresh process. Times: the build's wall seconds (libigl runs threads of its "
        "own), the flow's CPU seconds on its one thread (the machine is shared: its wall time "
        "depends on the other jobs), first call (with the surface's bound and stencils) and "
        "the fastest of two more calls (its wall time too). Memory above what the process "
        "held before the build: resident peak (`ru_maxrss`) and live peak (`mallinfo2`).",
        "",
        "| run | bricks | band voxels | build (wall s) | flow, first (CPU s) | flow (CPU s) | "
        "flow (wall s) | resident peak (MB) | live peak (MB) | max difference to alone | "
        "maximum principle excess |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def row(label: str, run: dict, difference: str = "", excess: str = "") -> str:
        return (f"| {label} | {run['bricks']:,} | {run['band']:,} | "
                f"{run['build_wall']:.1f} | {run['first_cpu']:.1f} | {run['steady_cpu']:.1f} | "
                f"{run['steady_wall']:.1f} | {run['peak_mb']:.0f} | {run['live_mb']:.0f} | "
                f"{difference} | {excess} |")

    for b, (name, n, run) in enumerate(zip(names, resolutions, alone, strict=True)):
        lines.append(row(f"{name} alone, {n}^3", run, f"{result['differences'][b]:.1e}",
                         f"{result['excess'][b]:.1e}"))
    total = {key: sum(run[key] for run in alone)
             for key in ("bricks", "band", "build_wall", "first_cpu", "steady_cpu",
                         "steady_wall", "peak_mb", "live_mb")}
    lines.append(row(f"sum of the {len(names)} alone", total))
    lines.append(row("**the batch**", together))
    lines += [
        "",
        "Batch against the sum of the shapes alone: build "
        f"x{together['build_wall'] / total['build_wall']:.2f} (wall), flow "
        f"x{together['first_cpu'] / total['first_cpu']:.2f} (first call) and "
        f"x{together['steady_cpu'] / total['steady_cpu']:.2f} (CPU); resident peak "
        f"x{together['peak_mb'] / total['peak_mb']:.2f} "
        f"(x{together['peak_mb'] / max(run['peak_mb'] for run in alone):.2f} the largest "
        f"alone), live peak x{together['live_mb'] / total['live_mb']:.2f} "
        f"(x{together['live_mb'] / max(run['live_mb'] for run in alone):.2f} the largest "
        "alone). Differences are the largest over each entry's band (data of size 1, float32);"
        " the maximum principle excess is how far the result leaves the range of the start "
        "over the band and its ring (negative: inside).",
    ]
    return "\n".join(lines)


def markdown(args, bandwidth: float, scaled: dict | None, ratioed: dict | None,
             solved: tuple | None) -> str:
    threads = torch.get_num_threads()
    lines = [
        f"Run of {time.strftime('%Y-%m-%d')}, {cpu_model()}, "
        f"{os.cpu_count()} cores, torch {torch.__version__}, {threads} thread(s), float32, "
        f"allocator: GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', 'default')}, load "
        f"average at the end {os.getloadavg()[0]:.1f}. Copy bandwidth measured in the run: "
        f"{bandwidth:.1f} GB/s. Command: `PYTHONPATH=. python benchmarks/bench_bricks.py "
        f"{' '.join(sys.argv[1:])}`.",
        "",
    ]
    if scaled is not None:
        s = scaled
        lines += [
            f"**Scale**: {Path(args.mesh).name} at {s['resolution']}^3 (h = {s['spacing']:.3g}), "
            f"built straight into bricks.",
            "",
            "| figure | value |",
            "|---|---|",
            f"| build (`bricks.from_mesh`) | {s['build_s']:.1f} s |",
            f"| bricks / stored voxels / band voxels | {s['bricks']:,} / {s['stored'] / 1e6:.2f} M"
            f" / {s['band'] / 1e6:.2f} M ({100 * s['band'] / s['dense']:.2f}% of the "
            f"{s['dense'] / 1e6:.3g} M-voxel box) |",
            f"| peak memory after the build | {s['built_gb']:.2f} GB |",
            f"| one Laplace–Beltrami application, compiled | {s['lb_ms']:.1f} ms (first call "
            f"{s['first_s']:.1f} s) |",
            f"| of which the halo gather | {s['halo_ms']:.1f} ms |",
            f"| one application by the C kernel (`path=\"auto\"`), every stored node / the band "
            f"only (as a flow applies it) | {s['native_ms']:.1f} ms / "
            f"{s['native_band_ms']:.1f} ms (loading the kernel first: {s['native_first_s']:.2f} s); the band "
            f"reading the haloed planes instead of the packed rows (alternated, medians of "
            f"{RATIO_PAIRS}): {s['planes_ms']:.1f} ms |",
            f"| traffic limit of the band's voxels / of the stored voxels | {s['limit_ms']:.2f} ms"
            f" / {s['stored_limit_ms']:.2f} ms (compiled: ratio "
            f"{s['lb_ms'] / s['limit_ms']:.1f} / {s['lb_ms'] / s['stored_limit_ms']:.1f}; the C "
            f"kernel on the band: {s['native_band_ms'] / s['limit_ms']:.1f} / "
            f"{s['native_band_ms'] / s['stored_limit_ms']:.1f}) |",
            f"| heat flow on noise to t = (8 h)^2 | {s['flow_s']:.1f} s (first call, with "
            f"compiling and the surface's stencils: {s['flow_first_s']:.1f} s), noise std "
            f"{s['noise_before']:.2f} → {s['noise_after']:.3f} |",
            f"| peak memory at the end | {s['peak_gb']:.2f} GB |",
            "",
        ]
    if ratioed is not None:
        r = ratioed
        lines += [
            f"**Against the dense volume**: sphere radius 1.2 on [-1.5, 1.5]^3 at "
            f"{r['resolution']}^3, one compiled application: dense {r['dense_ms']:.1f} ms, "
            f"bricks {r['brick_ms']:.1f} ms (medians of {len(r['ratios'])} alternated pairs); "
            f"time ratio {statistics.median(r['ratios']):.3f} (median; pairs "
            f"{', '.join(f'{x:.3f}' for x in r['ratios'])}), stored/dense voxels "
            f"{r['stored'] / r['dense']:.3f}, band/dense voxels {r['band'] / r['dense']:.3f}. "
            f"The C kernel on the band only (`path=\"auto\"`, as a flow applies it): "
            f"{r['native_ms']:.1f} ms, time ratio {statistics.median(r['native_ratios']):.3f} "
            f"(pairs {', '.join(f'{x:.3f}' for x in r['native_ratios'])}); reading the "
            f"haloed planes instead of the packed rows (the same pairs): {r['planes_ms']:.1f} ms, "
            f"{r['planes_ms'] / r['native_ms']:.2f}x.",
            "",
        ]
    if solved is not None:
        rows, (best, peer) = solved
        lines += [f"**Time to solution**: heat to t = 0.05 on the unit sphere, "
                  f"`method=\"{args.solution_method}\"` on bricks, at the spacing of the dense "
                  f"benchmark's n^3 box (bricks on a box {SOLUTION_MARGIN} cells wider a side).",
                  "", "| n | steps | seconds | sampled error |", "|---|---|---|---|"]
        lines += [f"| {r['n']} | {r['steps']} | {r['seconds']:.4f} | {r['error']:.2e} |"
                  for r in rows]
        if best is not None and peer is not None:
            lines += ["", f"Mesh peer: icosphere({peer.subdivisions}), {peer.vertices} vertices, "
                      f"{peer.steps} backward Euler steps, {peer.seconds:.3f} s, error "
                      f"{peer.error:.2e}; bricks at n = {best['n']} / peer = "
                      f"{best['seconds'] / peer.seconds:.2f} (target ≤ 0.1)."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> str:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mesh", default=str(MESHES / "bunny_closed.obj"))
    parser.add_argument("--resolution", type=int, default=512,
                        help="the scale part's grid (nodes a side, at least 24)")
    parser.add_argument("--ratio-resolution", type=int, default=256,
                        help="the ratio part's grid (nodes a side, at least 51: the sphere's "
                             "band stays 5 cells off the box)")
    parser.add_argument("--sizes", type=int, nargs="+", default=[65, 81, 97])
    parser.add_argument("--target", type=float, default=1e-3)
    parser.add_argument("--solution-method", default="rkc",
                        choices=["rkc", "euler", "heun"])
    parser.add_argument("--parts", nargs="+", default=["scale", "ratio", "solution"],
                        choices=["scale", "ratio", "solution", "batch", "peak"])
    parser.add_argument("--batch-meshes", nargs="+", type=Path,
                        default=[MESHES / f"{name}.obj" for name in BATCH_MESHES])
    parser.add_argument("--batch-resolutions", type=int, nargs="+",
                        default=list(BATCH_RESOLUTIONS))
    parser.add_argument("--batch-cells", type=float, default=BATCH_CELLS)
    parser.add_argument("--batch-run", nargs=2, metavar=("WHICH", "OUTPUT"),
                        help=argparse.SUPPRESS)
    parser.add_argument("--peak-run", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.peak_run:
        figures = peak_run(Path(args.mesh), args.resolution)
        print(json.dumps(figures))
        return json.dumps(figures)
    if "peak" in args.parts:
        body = peak(Path(args.mesh), args.resolution)
        print(body)
        if args.parts == ["peak"]:
            return body
    if args.batch_run is not None:
        which = None if args.batch_run[0] == "batch" else int(args.batch_run[0])
        figures = batch_run(args.batch_meshes, args.batch_resolutions, args.batch_cells, which,
                            Path(args.batch_run[1]))
        print(json.dumps(figures))
        return json.dumps(figures)
    if "batch" in args.parts:
        body = batch_markdown(batch(args.batch_meshes, args.batch_resolutions,
                                    args.batch_cells))
        print(body)
        if args.output is not None:
            write_section(args.output, BATCH_SECTION,
                          "### Bricks: five shapes at their own resolutions in one batch", body,
                          after=SECTION)
        if args.parts == ["batch"]:
            return body
    bandwidth = copy_bandwidth()
    scaled = scale(Path(args.mesh), args.resolution, bandwidth) if "scale" in args.parts else None
    ratioed = ratio(args.ratio_resolution) if "ratio" in args.parts else None
    solved = (solution(args.sizes, args.target, args.solution_method)
              if "solution" in args.parts else None)
    body = markdown(args, bandwidth, scaled, ratioed, solved)
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION, "## Band storage as bricks", body)
    return body


if __name__ == "__main__":
    main()
