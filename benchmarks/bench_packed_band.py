"""The band Laplacian and HeatFlow on packed band values against the volume path, in one process.

For each shape and grid: the band's share of the box, the time to assemble the packed
operator (``PackedBand``: the volume operator's rows in closed form and the ring's stencils as
gather matrices), the bytes it keeps, and one application of ``L`` (``L x = M W^-1 A E M x``,
the operator of ``exp(t L)``) forward and transposed, packed against the volume path's
``BandLaplacian.apply`` / ``transpose``, their calls alternated (medians; the ratio is the
figure to read on a shared machine). ``u`` is ``(batch, channels, n, n, n)`` float32.

Run with one thread and the team's allocator setting::

    OMP_NUM_THREADS=1 \\
    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        PYTHONPATH=. python benchmarks/bench_packed_band.py --sizes 64 128 --output docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import statistics
import sys
import time
from pathlib import Path

import torch
import trimesh
from _report import cpu_model, write_section
from bench_mesh_heat import MESH_DIR

import torchsurf as ts
from torchsurf.flows import HeatFlow
from torchsurf.flows._packed_band import PackedBand, PackedRegion
from torchsurf.flows.exponential import BandLaplacian

SECTION = "bench_packed_band"


def surface_of(shape: str, n: int) -> ts.ImplicitSurface:
    """The unit sphere on ``Grid.cube(n, 1.5)``, or a mesh of ``MESH_DIR`` fitted to ``n``."""
    if shape == "sphere":
        grid = ts.Grid.cube(n, 1.5)
        return ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    mesh = trimesh.load(MESH_DIR / f"{shape}.obj", force="mesh")
    grid = ts.mesh.fit_grid(mesh, n)
    return ts.ImplicitSurface(ts.sdf.from_mesh(mesh, grid), grid)


def kept_bytes(packed: PackedBand) -> int:
    """Bytes of the packed operator's index and weight tensors and its node lookup."""
    total = sum(t.numel() * t.element_size() for t in (packed.nodes, packed.packing.lookup))
    for name in ("weighted", "weighted_transposed", "first", "first_transposed", "chained",
                 "chained_transposed"):
        matrix = getattr(packed, name, None)
        total += 0 if matrix is None else matrix.nbytes()
    return total


def timed(function, repeats: int) -> list[float]:  # noqa: ANN001
    """Milliseconds of each of ``repeats`` calls."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(1e3 * (time.perf_counter() - start))
    return times


def measure(shape: str, n: int, batch: int, channels: int, repeats: int) -> dict[str, float]:
    surface = surface_of(shape, n)
    operator = BandLaplacian(surface, path="slicing")
    start = time.perf_counter()
    packed = PackedBand(PackedRegion(operator.surface, operator.scheme, operator.band,
                                     operator.region), operator.ring)
    build = time.perf_counter() - start
    u = torch.rand(batch, channels, *surface.grid.shape, generator=torch.Generator().manual_seed(0))
    inside = torch.where(operator.band, u, 0.0)
    x = packed.pack(u)
    volume_apply, volume_transpose, packed_apply, packed_transpose = [], [], [], []
    with torch.no_grad():
        for _ in range(repeats):  # alternated: load bursts hit both
            volume_apply += timed(lambda: operator.apply(inside), 1)
            packed_apply += timed(lambda: packed.apply(x), 1)
            volume_transpose += timed(lambda: operator.transpose(inside), 1)
            packed_transpose += timed(lambda: packed.transpose(x), 1)
    band = int(operator.band.sum())
    return {
        "band": band, "share": len(packed.nodes) / operator.band.numel(),
        "build": build, "kept": kept_bytes(packed) / 2**20,
        "volume": statistics.median(volume_apply), "packed": statistics.median(packed_apply),
        "volume_t": statistics.median(volume_transpose),
        "packed_t": statistics.median(packed_transpose),
    }


def flow_times(shape: str, n: int, batch: int, channels: int, repeats: int
               ) -> dict[str, float]:
    """``HeatFlow(16 h^2)`` (RKC, the default) on packed values against volumes: first call
    (with what the surface computes once: stencils, bound, packing) on a fresh surface, then
    the median of ``repeats`` calls, alternated; and the largest difference of the results."""
    figures: dict[str, float] = {}
    results, surfaces = {}, {}
    packed_system = HeatFlow.packed_system
    u = None
    for name in ("volume", "packed"):
        HeatFlow.packed_system = (packed_system if name == "packed"
                                  else lambda self, *args: None)
        surface = surface_of(shape, n)
        if u is None:
            u = torch.rand(batch, channels, *surface.grid.shape,
                           generator=torch.Generator().manual_seed(0))
        flow = HeatFlow(16 * surface.spacing**2)
        with torch.no_grad():
            start = time.perf_counter()
            results[name] = flow(u, surface)
            figures[f"{name}_first"] = time.perf_counter() - start
        surfaces[name] = surface
    HeatFlow.packed_system = packed_system
    steady: dict[str, list[float]] = {"volume": [], "packed": []}
    with torch.no_grad():
        for _ in range(repeats):
            for name in ("volume", "packed"):
                HeatFlow.packed_system = (packed_system if name == "packed"
                                          else lambda self, *args: None)
                surface = surfaces[name]
                flow = HeatFlow(16 * surface.spacing**2)
                steady[name] += timed(lambda flow=flow, surface=surface: flow(u, surface), 1)
    HeatFlow.packed_system = packed_system
    figures["volume"] = statistics.median(steady["volume"])
    figures["packed"] = statistics.median(steady["packed"])
    figures["difference"] = float((results["packed"] - results["volume"]).abs().max())
    return figures


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", nargs="+", default=["sphere", "bunny_closed"])
    parser.add_argument("--sizes", type=int, nargs="+", default=[64, 128])
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--channels", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--output", type=Path, default=None)
    parser.add_argument("--flow-repeats", type=int, default=3,
                        help="calls of HeatFlow per path (0: no flow rows)")
    args = parser.parse_args(argv)
    rows = [
        "| shape | n | band nodes | band + ring share of box | assembly s | kept MB "
        "| L volume ms | L packed ms | ratio | L^T volume ms | L^T packed ms | ratio |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for shape in args.shapes:
        for n in args.sizes:
            m = measure(shape, n, args.batch, args.channels, args.repeats)
            rows.append(
                f"| {shape} | {n} | {m['band']:,} | {100 * m['share']:.1f}% "
                f"| {m['build']:.2f} | {m['kept']:.0f} | {m['volume']:.1f} | {m['packed']:.1f} "
                f"| {m['packed'] / m['volume']:.3f} | {m['volume_t']:.1f} | {m['packed_t']:.1f} "
                f"| {m['packed_t'] / m['volume_t']:.3f} |")
            print(rows[-1], flush=True)
    flows = [
        "| shape | n | first call, volume s | first call, packed s | steady, volume ms "
        "| steady, packed ms | ratio | largest difference |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for shape in args.shapes if args.flow_repeats else []:
        for n in args.sizes:
            f = flow_times(shape, n, args.batch, 1, args.flow_repeats)
            flows.append(
                f"| {shape} | {n} | {f['volume_first']:.2f} | {f['packed_first']:.2f} "
                f"| {f['volume']:.0f} | {f['packed']:.0f} | {f['packed'] / f['volume']:.3f} "
                f"| {f['difference']:.1e} |")
            print(flows[-1], flush=True)
    allocator = os.environ.get("GLIBC_TUNABLES", "glibc default")
    lines = [
        f"{datetime.date.today()}, {cpu_model()}, {os.cpu_count()} cores, torch "
        f"{torch.__version__}, {torch.get_num_threads()} thread(s), allocator: `{allocator}`. "
        f"`u` `({args.batch}, {args.channels}, n, n, n)` float32; medians of {args.repeats} "
        "alternated calls; the volume path eager (`path=\"slicing\"`). The packed operator "
        "touches the band and ring's nodes: read each ratio against their share of the box.",
        "",
        "    OMP_NUM_THREADS=1 GLIBC_TUNABLES=... PYTHONPATH=. python "
        f"benchmarks/bench_packed_band.py {' '.join(argv)}",
        "",
        *rows,
        "",
        f"`HeatFlow(16 h^2)` (RKC, the default), `u` `({args.batch}, 1, n, n, n)`, without "
        "grad: its explicit steps on packed values against the same on volumes (the flow's "
        "`packed_system` declined; default path, its stencils eager within the backend's "
        "payback), each on a fresh surface for its first call, then the "
        f"median of {args.flow_repeats} alternated calls; the difference is the largest "
        "between the two results (float32).",
        "",
        *(flows if args.flow_repeats else []),
    ]
    body = "\n".join(lines) + "\n"
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION,
                      "## The band Laplacian on packed band values against the volume operators",
                      body)


if __name__ == "__main__":
    main()
