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
first (the surface's kept stencils); times are one call, eager, seconds.

    OMP_NUM_THREADS=1 PYTHONPATH=. python benchmarks/bench_narrow_band.py --cells 16 24 32
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


def case(cells: int, layout: str) -> tuple[ts.ImplicitSurface, torch.Tensor, ts.Grid]:
    """The surface (dense ``r^2 - R^2`` or bricks of ``r - R``) at ``cells`` per radius, and
    ``u0`` on it (dense, or packed on bricks)."""
    spacing = RADIUS / cells
    nodes = 2 * round(1.4 * cells) + 1
    grid = ts.Grid((nodes,) * 3, spacing, (-spacing * (nodes - 1) / 2,) * 3)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    r = (x * x + y * y + z * z).sqrt()
    u0 = ((x + 0.5 * y) / r)[None, None]
    if layout == "dense":
        return ts.ImplicitSurface((r * r - RADIUS**2)[None, None], grid), u0, grid
    surface = ts.bricks.from_dense(ts.ImplicitSurface((r - RADIUS)[None, None], grid))
    return surface, surface.from_dense(u0), grid


def run(cells: int, layout: str) -> list[str]:
    surface, u0, grid = case(cells, layout)
    end = DECAY * RADIUS**2 / 2
    directions = fibonacci_sphere(1500)
    exact = math.exp(-DECAY) * (directions[:, 0] + 0.5 * directions[:, 1])
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
        dense = u if layout == "dense" else surface.to_dense(u)[0]
        read = ts.sample(dense, RADIUS * directions, grid, interpolation="cubic")[0, 0]
        error = float((read - exact).abs().max() / exact.abs().max())
        steps = flow.last_plan.count
        rows.append(f"| {layout} | {cells} | {name} | {steps} | {end * rho / steps:.1f} "
                    f"| {error:.2e} | {seconds:.2f} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, nargs="+", default=[16, 24, 32],
                        help="cells per radius")
    parser.add_argument("--layouts", nargs="+", default=["dense", "bricks"],
                        choices=["dense", "bricks"])
    parser.add_argument("--output", type=Path, default=None,
                        help="also write the table into this markdown file")
    args = parser.parse_args()
    warnings.simplefilter("ignore", RuntimeWarning)  # the former bound's steps warn of nothing
    lines = ["| surface | cells per radius | method | steps | dt rho | max relative error on S "
             "| seconds |", "|---|---:|---|---:|---:|---:|---:|"]
    print("\n".join(lines), flush=True)
    for layout in args.layouts:
        for cells in args.cells:
            rows = run(cells, layout)
            print("\n".join(rows), flush=True)
            lines += rows
    if args.output is not None:
        from _report import cpu_model, write_section  # benchmarks/_report.py, beside this script
        body = (f"{cpu_model()}, {torch.get_num_threads()} thread(s), torch "
                f"{torch.__version__}.\n\n" + "\n".join(lines))
        write_section(args.output, "narrow-band", "### Heat flow on a 3-cell band", body)


if __name__ == "__main__":
    main()
