"""The heat flow on a 3-cell band: the default RKC against its former step bound and Heun.

On a 3-cell band (phi not a distance, ``from_mesh``'s band, bricks) the flow cannot hold the
band's outer ring stale: every evaluation of the rate re-extends it from S, and the band itself
is re-extended between steps, about once per cell-crossing time ``12 / rho``. Between those
re-extensions the band's data drift off S's values, so the error depends on how long the period
is (docs/band.md, section 1). RKC's steps there were up to ``108 / rho`` long (its 16 fewest
steps); they are now at most ``RKC_REFRESHED_STEP / rho`` (12) for the heat flow.

Case: sphere R = 0.7 in a box of half-width 1.4 R, ``u0 = (x + 0.5 y) / r`` (degree 1),
decayed by ``e^-0.6`` at ``t = 0.6 R^2 / 2``, float64; the error is the largest difference on
S (1500 Fibonacci points, read tricubically), relative to the exact amplitude. Surfaces: phi =
``r^2 - R^2`` on the dense grid, and ``r - R`` on bricks. Rows per surface and size: the default
RKC; RKC with the former count ``max(16, ceil(t rho / 108))`` (the baseline, same run); Heun
with its default re-extension; Heun re-extending after every step. Each flow runs once untimed
first (the surface's kept stencils); times are one call on ``path="auto"``, seconds.

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/bench_narrow_band.py --cells 16 24 32

``--sweep`` instead tabulates the signed amplitude error against the period ``P / rho`` between
the band's re-extensions, for Heun (steps of ``2 / rho``, ``reextend_every = P / 2``), RKC in
short steps (``dt rho = 4``, ``reextend_every = P / 4``) and RKC in one step a period
(``dt rho = P``). ``--phis`` compares the default RKC and Heun on several phi of the same
sphere: the distance, a multiple of it, ``r^2 - R^2`` and ``(r - R)(1 + x / 2R)`` (docs/band.md,
section 1).

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/bench_narrow_band.py --sweep --cells 16
    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/bench_narrow_band.py --phis --cells 16 24
"""

from __future__ import annotations

import argparse
import math
import time
import warnings
from pathlib import Path

import torch

import torchsurf as ts
from torchsurf.flows import HeatFlow

FORMER_LONGEST = 108.0
"""The former longest ``dt rho`` of RKC's steps on a 3-cell band: ``12 w^2`` with ``w = 3``."""

RADIUS = 0.7
DECAY = 0.6


def fibonacci_sphere(count: int) -> torch.Tensor:
    """``count`` nearly even unit vectors, ``(count, 3)`` float64."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    height = 1 - 2 * i / count
    angle = math.pi * (1 + 5**0.5) * i
    ring = torch.sqrt(1 - height**2)
    return torch.stack((ring * torch.cos(angle), ring * torch.sin(angle), height), dim=-1)


PHIS = {
    "r - R": lambda x, r: r - RADIUS,
    "3 (r - R)": lambda x, r: 3 * (r - RADIUS),
    "r^2 - R^2": lambda x, r: r * r - RADIUS**2,
    "(r - R)(1 + x / 2R)": lambda x, r: (r - RADIUS) * (1 + 0.5 * x / RADIUS),
}
"""The phi of ``--phis``: the sphere's distance, a multiple of it, and two that are not
distances (the second not even a function of ``r``)."""


def case(cells: int, layout: str, phi: str = "r^2 - R^2"
         ) -> tuple[ts.ImplicitSurface, torch.Tensor, ts.Grid]:
    """The surface (dense ``phi``, ``r^2 - R^2`` by default, or bricks of ``r - R``) at
    ``cells`` per radius, and ``u0`` on it (dense, or packed on bricks)."""
    spacing = RADIUS / cells
    nodes = 2 * round(1.4 * cells) + 1
    grid = ts.Grid((nodes,) * 3, spacing, (-spacing * (nodes - 1) / 2,) * 3)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    r = (x * x + y * y + z * z).sqrt()
    u0 = ((x + 0.5 * y) / r)[None, None]
    if layout == "dense":
        return ts.ImplicitSurface(PHIS[phi](x, r)[None, None], grid), u0, grid
    surface = ts.bricks.from_dense(ts.ImplicitSurface((r - RADIUS)[None, None], grid),
                                   flow_band=False)  # the 3-cell band, as the dense phi's
    return surface, surface.from_dense(u0), grid


def errors_on_sphere(u: torch.Tensor, surface: ts.ImplicitSurface, grid: ts.Grid
                     ) -> tuple[float, float]:
    """The largest error on S relative to the exact amplitude, and the signed error of the
    amplitude (least-squares fit of the values read on S to the exact ones, minus one)."""
    directions = fibonacci_sphere(1500)
    exact = math.exp(-DECAY) * (directions[:, 0] + 0.5 * directions[:, 1])
    dense = u if surface.layout is None else surface.to_dense(u)[0]
    read = ts.sample(dense, RADIUS * directions, grid, interpolation="cubic")[0, 0]
    largest = float((read - exact).abs().max() / exact.abs().max())
    amplitude = float((read * exact).sum() / (exact * exact).sum()) - 1.0
    return largest, amplitude


def run(cells: int, layout: str) -> list[str]:
    surface, u0, grid = case(cells, layout)
    end = DECAY * RADIUS**2 / 2
    rho = HeatFlow(end).system(u0, surface).spectral_radius
    flows = {
        "rkc (default)": HeatFlow(end),
        "rkc, former bound (dt rho <= 108)": HeatFlow(
            end, steps=max(16, math.ceil(end * rho / FORMER_LONGEST))),
        "heun": HeatFlow(end, method="heun"),
        "heun, band re-extended every step": HeatFlow(end, method="heun", reextend_every=1),
    }
    rows = []
    for name, flow in flows.items():
        flow(u0, surface)
        start = time.perf_counter()
        u = flow(u0, surface)
        seconds = time.perf_counter() - start
        error, _ = errors_on_sphere(u, surface, grid)
        steps = flow.last_plan.count
        rows.append(f"| {layout} | {cells} | {name} | {steps} | {end * rho / steps:.1f} "
                    f"| {error:.2e} | {seconds:.2f} |")
    return rows


SWEEP_PERIODS = (4, 8, 12, 16, 24, 48)
"""Periods ``P`` (times ``1 / rho``) between the band's re-extensions in ``--sweep``."""


def sweep(cells: int, layout: str, periods: tuple[int, ...] = SWEEP_PERIODS) -> list[str]:
    """Signed amplitude errors against the period between re-extensions: Heun, RKC in short
    steps and RKC in one step a period (each row ``| P | heun | rkc short | rkc long |``)."""
    surface, u0, grid = case(cells, layout)
    end = DECAY * RADIUS**2 / 2
    rho = HeatFlow(end).system(u0, surface).spectral_radius
    rows = []
    for period in periods:
        flows = (HeatFlow(end, method="heun", steps=math.ceil(end * rho / 2),
                          reextend_every=max(1, period // 2)),
                 HeatFlow(end, steps=math.ceil(end * rho / 4), reextend_every=max(1, period // 4)),
                 HeatFlow(end, steps=math.ceil(end * rho / period)))
        cells_ = [f"{errors_on_sphere(flow(u0, surface), surface, grid)[1]:+.2e}"
                  for flow in flows]
        rows.append(f"| {layout} | {cells} | {period} | " + " | ".join(cells_) + " |")
    return rows


def phis(cells: int) -> list[str]:
    """The default RKC and Heun on each phi of :data:`PHIS` (dense): band width in cells,
    steps, largest and signed amplitude errors of each."""
    end = DECAY * RADIUS**2 / 2
    rows = []
    for name in PHIS:
        surface, u0, grid = case(cells, "dense", name)
        for method in ("rkc", "heun"):
            flow = HeatFlow(end, method=method)
            largest, amplitude = errors_on_sphere(flow(u0, surface), surface, grid)
            width = flow.evolving_width(surface) / surface.spacing
            rows.append(f"| {name} | {cells} | {width:.0f} | {method} | {flow.last_plan.count} "
                        f"| {largest:.2e} | {amplitude:+.2e} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, nargs="+", default=[16, 24, 32],
                        help="cells per radius, at least 12 (the box of 1.4 radii leaves "
                             "bricks too few cells below, and --phis's data is NaN at the "
                             "centre the 5-cell band reaches)")
    parser.add_argument("--layouts", nargs="+", default=["dense", "bricks"],
                        choices=["dense", "bricks"])
    parser.add_argument("--sweep", action="store_true",
                        help="signed errors against the period between re-extensions instead")
    parser.add_argument("--phis", action="store_true",
                        help="the default RKC and Heun on several phi of the sphere instead")
    parser.add_argument("--output", type=Path, default=None,
                        help="also write the table into this markdown file")
    args = parser.parse_args()
    if min(args.cells) < 12:
        parser.error(f"--cells must be at least 12 cells per radius, got {min(args.cells)}")
    warnings.simplefilter("ignore", RuntimeWarning)  # the former bound's steps warn of nothing
    if args.sweep or args.phis:
        if args.output is not None:
            parser.error("--output writes the main table only; --sweep and --phis print theirs")
        if args.sweep:
            print("| surface | cells per radius | period P (1 / rho) | heun | rkc, dt rho = 4 "
                  "| rkc, dt rho = P |\n|---|---:|---:|---:|---:|---:|", flush=True)
            for layout in args.layouts:
                for cells in args.cells:
                    print("\n".join(sweep(cells, layout)), flush=True)
        if args.phis:
            print("| phi | cells per radius | band cells | method | steps | max relative error "
                  "| amplitude error |\n|---|---:|---:|---|---:|---:|---:|", flush=True)
            for cells in args.cells:
                print("\n".join(phis(cells)), flush=True)
        return
    lines = ["| surface | cells per radius | method | steps | dt rho | max relative error on S "
             "| seconds |", "|---|---:|---|---:|---:|---:|---:|"]
    print("\n".join(lines), flush=True)
    for layout in args.layouts:
        for cells in args.cells:
            rows = run(cells, layout)
            print("\n".join(rows), flush=True)
            lines += rows
    if args.output is not None:
        from _report import run_context, write_section  # benchmarks/_report.py, beside it
        body = f"{run_context()}.\n\n" + "\n".join(lines)
        write_section(args.output, "narrow-band", "### Heat flow on a 3-cell band", body)


if __name__ == "__main__":
    main()
