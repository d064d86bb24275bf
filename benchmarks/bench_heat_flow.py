"""Heat flow to t = 0.05 on the unit sphere: wall time and sampled error of each integrator.

Every run starts from the l = 2 harmonic ``3 z^2 - 1`` extended along normals on an ``n^3``
grid spanning ``[-1.4, 1.4]^3`` and flows to ``t = 0.05``; the error is the largest difference on
S (2000 Fibonacci points, trilinear sampling) from ``exp(-6 t) f``, relative to the exact
amplitude. Rows: torchsurf explicit Euler (stable step ``h^2 / 6``), backward Euler and
Crank–Nicolson with conjugate gradients, an adaptive torchdiffeq method (dopri5, if installed),
and the numpy Appendix-B explicit reference of ``bench_laplace_beltrami.py`` (first order).

    python benchmarks/bench_heat_flow.py --sizes 65 129 --implicit-steps 10
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

import torchsurf as ts
from torchsurf.flows import HeatFlow
from torchsurf.sampling import sample

TIME = 0.05
BOUND = 1.4


def _reference_module():
    path = Path(__file__).with_name("bench_laplace_beltrami.py")
    spec = importlib.util.spec_from_file_location("bench_laplace_beltrami", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    return module


def case(n: int, dtype: torch.dtype):
    grid = ts.Grid.cube(n, bound=BOUND)
    phi = ts.sdf.sphere(grid, radius=1.0, dtype=dtype)
    points = grid.points(dtype=dtype)
    z = points[..., 2] / points.norm(dim=-1).clamp(min=1e-9)
    return grid, phi, (3 * z**2 - 1)[None, None]


def sampled_error(u: torch.Tensor, grid: ts.Grid) -> float:
    count = 2000
    i = torch.arange(count, dtype=u.dtype) + 0.5
    z = 1 - 2 * i / count
    r = torch.sqrt(1 - z**2)
    angle = math.pi * (1 + 5**0.5) * i
    points = torch.stack((r * torch.cos(angle), r * torch.sin(angle), z), dim=-1)
    exact = (3 * z**2 - 1) * math.exp(-6 * TIME)
    return float((sample(u, points, grid)[0, 0] - exact).abs().max() / exact.abs().max())


def timed(run):
    start = time.perf_counter()
    result = run()
    return result, time.perf_counter() - start


def bench(n: int, implicit_steps: int, dtype: torch.dtype, reference: bool) -> list[tuple]:
    grid, phi, u0 = case(n, dtype)
    surface = ts.ImplicitSurface(phi, grid)
    # compile the operator for this shape (>= 64^3) untimed, with and without autograd
    ts.laplace_beltrami(u0, surface)
    with torch.no_grad():
        ts.laplace_beltrami(u0, surface)
    rows = []
    flows = {
        "euler (h^2/6)": HeatFlow(TIME),
        f"implicit ({implicit_steps} steps)": HeatFlow(TIME, method="implicit", steps=implicit_steps),
        f"crank_nicolson ({implicit_steps} steps)": HeatFlow(
            TIME, method="crank_nicolson", steps=implicit_steps),
    }
    if importlib.util.find_spec("torchdiffeq") is not None:
        flows["dopri5 (rtol 1e-4)"] = HeatFlow(
            TIME, method="dopri5", options={"rtol": 1e-4, "atol": 1e-6})
    for name, flow in flows.items():
        u, seconds = timed(lambda flow=flow: flow(u0, surface))
        rows.append((n, name, seconds, sampled_error(u, grid)))
    if reference:
        module = _reference_module()
        numpy_dtype = np.float64 if dtype == torch.float64 else np.float32
        operator = module.AppendixB(phi[0, 0].numpy(), grid.spacing, dtype=numpy_dtype)
        band = (phi[0, 0].abs() <= HeatFlow(TIME).diffusion_length() * 2 + 3 * grid.spacing)
        band = band.numpy().astype(numpy_dtype)
        steps = math.ceil(TIME / (grid.spacing**2 / 6))
        dt = numpy_dtype(TIME / steps)

        def run() -> np.ndarray:
            u = u0[0, 0].numpy().astype(numpy_dtype).copy()
            for _ in range(steps):
                u += dt * band * operator(u)
            return u

        u, seconds = timed(run)
        error = sampled_error(torch.from_numpy(u)[None, None].to(dtype), grid)
        rows.append((n, "numpy Appendix B euler", seconds, error))
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[65, 129])
    parser.add_argument("--implicit-steps", type=int, default=10)
    parser.add_argument("--float64", action="store_true")
    parser.add_argument("--no-reference", action="store_true")
    args = parser.parse_args(argv)
    dtype = torch.float64 if args.float64 else torch.float32
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {dtype}")
    print("| n | method | wall time (s) | max relative error on S |")
    print("|---|---|---|---|")
    for n in args.sizes:
        for row in bench(n, args.implicit_steps, dtype, not args.no_reference):
            print(f"| {row[0]} | {row[1]} | {row[2]:.2f} | {row[3]:.2e} |", flush=True)


if __name__ == "__main__":
    main()
