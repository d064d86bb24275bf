"""Heat flow to t = 0.05 on the unit sphere: wall time and sampled error of each integrator.

Every run starts from the l = 2 harmonic ``3 z^2 - 1`` extended along normals on an ``n^3``
grid spanning ``[-1.4, 1.4]^3`` and flows to ``t = 0.05``; the error is the largest difference on
S (2000 Fibonacci points) from ``exp(-6 t) f``, relative to the exact amplitude, read from the
grid solution by tricubic interpolation (``sample(..., interpolation="cubic")``, fourth order, so
that the read-out adds nothing to a second-order solution's error); the trilinear read-out's
error, which adds an ``O(h^2)`` of its own (1.4e-3 on the exact solution at 65^3), is shown
beside it. Rows: torchsurf's default (Runge–Kutta–Chebyshev on the band the flow chooses: 5
cells on this exact distance), the same on the 3-cell band of a surface whose phi is a distance
only near S, explicit Euler (step ``1.8 / rho`` from the band operator's Gershgorin bound),
backward Euler and Crank–Nicolson with conjugate gradients, an adaptive torchdiffeq method
(dopri5, if installed), and the numpy Appendix-B explicit reference of
``bench_laplace_beltrami.py`` (first order, on a band widened by the diffusion length, as
torchsurf did before its band was fixed). Each torchsurf flow runs once untimed first, inside
:func:`torchsurf.backend.warm_up` (its kernels compiled: ``--eager`` keeps them eager), so
compilation and what the surface computes once (the spectral bound, the closest-point stencils)
are not in the times; the time is the median of 3 calls.

Mesh peer rows do the same job on ``trimesh.creation.icosphere(k)``: cotangent Laplacian ``L``
and lumped Voronoi mass ``M`` (libigl, float64), backward Euler ``(M - dt L) u' = M u`` with one
SuperLU factorisation (``scipy.sparse.linalg.splu``), the solution read at the same 2000 points
by barycentric interpolation at their closest points on the mesh. Its time covers operators,
factorisation and all steps (median of 3), not building the icosphere nor the error. Two rows
per n: the icosphere whose vertex count is closest (in ratio) to the grid's surface samples
(half the nodes with ``|phi| <= h``, about ``area / h^2``) with the fewest steps reaching
``--mesh-target``; and the smallest icosphere and fewest steps reaching the error of the
fastest torchsurf row (or ``--match-error``). Steps come from a ladder ``4 * 2^(j / 2)``; if
none reaches the target, the row shows the icosphere's best error, marked "floor".

    python benchmarks/bench_heat_flow.py --sizes 65 81 97 129 --reference-sizes 129 161 193

The closing summary takes, for each method, the fastest run whose error is at most
``--mesh-target`` (1e-3), and gives two ratios: the numpy reference's time over the fastest
torchsurf method's (target >= 20) and the fastest torchsurf method's over the mesh peer's
(target <= 0.1; the default RKC's ratio is printed too).

    python benchmarks/bench_heat_flow.py --sizes 65 129 --implicit-steps 10
    python benchmarks/bench_heat_flow.py --sizes 65 129 --mesh-peer-only --subdivisions 4 5 6
    python benchmarks/bench_heat_flow.py --paired 37 --pairs 9   # the default against the peer, alternated
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import math
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import igl
import numpy as np
import scipy.sparse as sparse
import torch
import trimesh
from scipy.sparse.linalg import splu

import torchsurf as ts
from torchsurf.flows import HeatFlow
from torchsurf.sampling import sample

TIME = 0.05
BOUND = 1.4
POINTS = 2000
STEP_LADDER = tuple(round(4 * 2 ** (j / 2)) for j in range(17))  # 4, 6, 8, 11, ..., 724, 1024
MAX_SUBDIVISIONS = 7
REFERENCE_NAME = "numpy Appendix B euler"


class Row(NamedTuple):
    """One line of the table; ``samples`` is surface samples (grid) or vertices (mesh)."""

    n: int | None
    method: str
    samples: int
    seconds: float
    error: float
    ratio: float | None = None
    trilinear_error: float | None = None


class MeshRun(NamedTuple):
    """A timed mesh-peer run; ``reached`` says whether the error met the requested target."""

    subdivisions: int
    vertices: int
    steps: int
    seconds: float
    error: float
    reached: bool = True


def _reference_module():
    path = Path(__file__).with_name("bench_laplace_beltrami.py")
    spec = importlib.util.spec_from_file_location("bench_laplace_beltrami", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    return module


def case(n: int, dtype: torch.dtype):
    """Grid, unit-sphere SDF and the normally extended initial data ``3 z^2 - 1`` on ``n^3`` nodes."""
    grid = ts.Grid.cube(n, bound=BOUND)
    phi = ts.sdf.sphere(grid, radius=1.0, dtype=dtype)
    points = grid.points(dtype=dtype)
    z = points[..., 2] / points.norm(dim=-1).clamp(min=1e-9)
    return grid, phi, (3 * z**2 - 1)[None, None]


def fibonacci_sphere(count: int = POINTS) -> np.ndarray:
    """``count`` nearly uniform points on the unit sphere, shape ``(count, 3)``, float64."""
    i = np.arange(count) + 0.5
    z = 1 - 2 * i / count
    r = np.sqrt(1 - z**2)
    angle = math.pi * (1 + 5**0.5) * i
    return np.stack((r * np.cos(angle), r * np.sin(angle), z), axis=-1)


def relative_error(values: np.ndarray | torch.Tensor, points: np.ndarray | torch.Tensor) -> float:
    """Largest error of ``values`` at ``points`` against ``exp(-6 t)(3 z^2 - 1)``, over its amplitude."""
    exact = (3 * points[:, 2] ** 2 - 1) * math.exp(-6 * TIME)
    return float(abs(values - exact).max() / abs(exact).max())


def sampled_error(u: torch.Tensor, grid: ts.Grid, interpolation: str = "cubic") -> float:
    """Error of the grid solution ``u``, read at the Fibonacci points by ``interpolation``."""
    points = torch.from_numpy(fibonacci_sphere()).to(u.dtype)
    return relative_error(sample(u, points, grid, interpolation)[0, 0], points)


def timed(run):
    """``run()`` and its wall time in seconds."""
    start = time.perf_counter()
    result = run()
    return result, time.perf_counter() - start


def median_timed(run, repeats: int = 3):
    """``run()`` and the median of ``repeats`` wall times in seconds."""
    results = [timed(run) for _ in range(repeats)]
    return results[-1][0], statistics.median(seconds for _, seconds in results)


def bench(n: int, implicit_steps: int, dtype: torch.dtype, reference: bool,
          warm: bool = True) -> list[Row]:
    """Time every torchsurf integrator (and the numpy reference) on the ``n^3`` grid."""
    grid, phi, u0 = case(n, dtype)
    samples = surface_samples(phi, grid)
    surface = ts.ImplicitSurface(phi, grid)
    rows = []
    flows = {
        "rkc (default)": HeatFlow(TIME),
        "rkc (3-cell band)": HeatFlow(TIME, band_width=3 * grid.spacing),
        "euler (1.8/rho)": HeatFlow(TIME, method="euler"),
        f"implicit ({implicit_steps} steps)": HeatFlow(TIME, method="implicit", steps=implicit_steps),
        f"crank_nicolson ({implicit_steps} steps)": HeatFlow(
            TIME, method="crank_nicolson", steps=implicit_steps),
    }
    if importlib.util.find_spec("torchdiffeq") is not None:
        flows["dopri5 (rtol 1e-4)"] = HeatFlow(
            TIME, method="dopri5", options={"rtol": 1e-4, "atol": 1e-6})
    for flow in flows.values():
        # compiled variants, the surface's spectral bound and closest-point stencils: untimed
        with ts.backend.warm_up() if warm else contextlib.nullcontext():
            flow(u0, surface)
    for name, flow in flows.items():
        u, seconds = median_timed(lambda flow=flow: flow(u0, surface))
        rows.append(Row(n, name, samples, seconds, sampled_error(u, grid),
                        trilinear_error=sampled_error(u, grid, "linear")))
    if reference:
        rows.append(reference_row(n, dtype))
    return rows


def reference_row(n: int, dtype: torch.dtype) -> Row:
    """The numpy Appendix-B explicit reference on the ``n^3`` grid, in the band the flows use."""
    grid, phi, u0 = case(n, dtype)
    module = _reference_module()
    numpy_dtype = np.float64 if dtype == torch.float64 else np.float32
    operator = module.AppendixB(phi[0, 0].numpy(), grid.spacing, dtype=numpy_dtype)
    band = (phi[0, 0].abs() <= 2 * math.sqrt(TIME) + 3 * grid.spacing)
    band = band.numpy().astype(numpy_dtype)
    steps = math.ceil(TIME / (grid.spacing**2 / 6))
    dt = numpy_dtype(TIME / steps)

    def run() -> np.ndarray:
        u = u0[0, 0].numpy().astype(numpy_dtype).copy()
        for _ in range(steps):
            u += dt * band * operator(u)
        return u

    u, seconds = timed(run)
    solution = torch.from_numpy(u)[None, None].to(dtype)
    return Row(n, REFERENCE_NAME, surface_samples(phi, grid), seconds,
               sampled_error(solution, grid), trilinear_error=sampled_error(solution, grid, "linear"))


def family(row: Row) -> str:
    """What a row's method is, without its settings: ``"euler"``, ``"mesh peer"``, ..."""
    if row.method.startswith("mesh peer"):
        return "mesh peer"
    return row.method if row.method == REFERENCE_NAME else row.method.split(" (")[0]


def time_to_accuracy(rows: list[Row], target: float) -> list[str]:
    """Markdown summary: per method, the fastest run reaching ``target``, and the target ratios."""
    best: dict[str, Row] = {}
    for row in rows:
        name = family(row)
        if row.error <= target and (name not in best or row.seconds < best[name].seconds):
            best[name] = row
    lines = [f"Time to reach t = {TIME} with error <= {target:.0e} (fastest run of each method):", "",
             "| method | n | wall time (s) | error |", "|---|---|---:|---:|"]
    lines += [f"| {name} | {'—' if row.n is None else row.n} | {row.seconds:.3f} | {row.error:.2e} |"
              for name, row in sorted(best.items(), key=lambda item: item[1].seconds)]
    ours = [row for name, row in best.items() if name not in (REFERENCE_NAME, "mesh peer")]
    fastest = min(ours, key=lambda row: row.seconds, default=None)
    lines.append("")
    for name, wording in ((REFERENCE_NAME, "numpy reference ÷ fastest torchsurf (target >= 20)"),
                          ("mesh peer", "fastest torchsurf ÷ mesh peer (target <= 0.1)")):
        if fastest is None or name not in best:
            lines.append(f"{wording}: not measured (no run reached the target)")
            continue
        other = best[name]
        ratio = other.seconds / fastest.seconds if name == REFERENCE_NAME else fastest.seconds / other.seconds
        lines.append(f"{wording}: {ratio:.2f}")
    # the default's own row, not its family's fastest (a 3-cell band is rkc too)
    default = min((row for row in rows if row.method == "rkc (default)" and row.error <= target),
                  key=lambda row: row.seconds, default=None)
    if default is not None and "mesh peer" in best:
        lines.append(f"default (rkc) ÷ mesh peer: "
                     f"{default.seconds / best['mesh peer'].seconds:.2f}")
    return lines


def paired(n: int, pairs: int, target: float, warm: bool = True, method: str = "rkc"
           ) -> list[str]:
    """The flow (``method``, default settings) at ``n^3`` and the mesh peer at ``target``, timed
    alternately ``pairs`` times in this process: each pair's ratio, so that the machine's drift
    falls on both."""
    grid, phi, u0 = case(n, torch.float32)
    surface = ts.ImplicitSurface(phi, grid)
    flow = HeatFlow(TIME, method=method)
    with ts.backend.warm_up() if warm else contextlib.nullcontext():
        u = flow(u0, surface)
    error = sampled_error(u, grid)
    peer = accuracy_matched(target)
    vertices, faces = icosphere(peer.subdivisions)
    ratios, ours, theirs = [], [], []
    for _ in range(pairs):
        ours.append(timed(lambda: flow(u0, surface))[1])
        theirs.append(timed(lambda: mesh_heat_flow(vertices, faces, peer.steps))[1])
        ratios.append(ours[-1] / theirs[-1])
    return [
        f"Paired: {method} at {n}^3 (error {error:.2e}) against the mesh peer "
        f"icosphere({peer.subdivisions}), {peer.steps} BE steps (error {peer.error:.2e}), "
        f"alternated {pairs} times:",
        f"{method} s: {' '.join(f'{t:.3f}' for t in ours)}",
        f"mesh s: {' '.join(f'{t:.3f}' for t in theirs)}",
        f"ratios: {' '.join(f'{r:.2f}' for r in ratios)}; median {statistics.median(ratios):.2f}",
    ]


def surface_samples(phi: torch.Tensor, grid: ts.Grid) -> int:
    """Half the nodes within one cell of S (``|phi| <= h``): about ``area / h^2``."""
    return int((phi.abs() <= grid.spacing).sum()) // 2


def icosphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (float64, on the unit sphere) and faces (int64) of trimesh's icosphere."""
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


def corner_cotangents(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Cotangent of each face's angle at each of its corners, shape ``(faces, 3)``."""
    cot = np.empty(faces.shape)
    for c in range(3):
        a = vertices[faces[:, (c + 1) % 3]] - vertices[faces[:, c]]
        b = vertices[faces[:, (c + 2) % 3]] - vertices[faces[:, c]]
        cot[:, c] = (a * b).sum(axis=1) / np.linalg.norm(np.cross(a, b), axis=1)
    return cot


def cotangent_laplacian(vertices: np.ndarray, faces: np.ndarray, cot: np.ndarray) -> sparse.csc_matrix:
    """Negative semi-definite cotangent Laplacian: edge weight half the cotangent of each opposite angle."""
    # corner c's cotangent weighs the edge between the other two corners
    i = np.concatenate([faces[:, (c + 1) % 3] for c in range(3)])
    j = np.concatenate([faces[:, (c + 2) % 3] for c in range(3)])
    weight = 0.5 * cot.T.ravel()
    count = len(vertices)
    off_diagonal = sparse.coo_matrix(
        (np.concatenate((weight, weight)), (np.concatenate((i, j)), np.concatenate((j, i)))),
        shape=(count, count)).tocsc()
    return (off_diagonal - sparse.diags(np.asarray(off_diagonal.sum(axis=1)).ravel())).tocsc()


def voronoi_areas(vertices: np.ndarray, faces: np.ndarray, cot: np.ndarray) -> np.ndarray:
    """Mixed Voronoi area of each vertex (obtuse faces split 1/2 to the obtuse corner, 1/4 to the others)."""
    corners = [vertices[faces[:, c]] for c in range(3)]
    area = 0.5 * np.linalg.norm(np.cross(corners[1] - corners[0], corners[2] - corners[0]), axis=1)
    opposite = np.stack([((corners[(c + 2) % 3] - corners[(c + 1) % 3]) ** 2).sum(axis=1)
                         for c in range(3)], axis=1)
    # corner c owns (|edge c, c+1|^2 cot(c+2) + |edge c, c+2|^2 cot(c+1)) / 8 of a non-obtuse face
    share = np.stack([(opposite[:, (c + 2) % 3] * cot[:, (c + 2) % 3]
                       + opposite[:, (c + 1) % 3] * cot[:, (c + 1) % 3]) / 8 for c in range(3)], axis=1)
    obtuse = cot < 0
    fallback = np.where(obtuse, area[:, None] / 2, area[:, None] / 4)
    share = np.where(obtuse.any(axis=1, keepdims=True), fallback, share)
    return np.bincount(faces.ravel(), weights=share.ravel(), minlength=len(vertices))


def mesh_operators(vertices: np.ndarray, faces: np.ndarray,
                   source: str = "igl") -> tuple[sparse.csc_matrix, np.ndarray]:
    """Cotangent Laplacian and lumped Voronoi mass (diagonal), from libigl or this file's numpy code."""
    if source == "igl":
        laplacian = igl.cotmatrix(vertices, faces)
        mass = igl.massmatrix(vertices, faces, igl.MASSMATRIX_TYPE_VORONOI).diagonal()
        return sparse.csc_matrix(laplacian), mass
    cot = corner_cotangents(vertices, faces)
    return cotangent_laplacian(vertices, faces, cot), voronoi_areas(vertices, faces, cot)


def mesh_heat_flow(vertices: np.ndarray, faces: np.ndarray, steps: int, source: str = "igl") -> np.ndarray:
    """Backward Euler to ``TIME`` in ``steps`` steps from ``3 z^2 - 1``, one factorisation for all steps."""
    laplacian, mass = mesh_operators(vertices, faces, source)
    dt = TIME / steps
    solver = splu((sparse.diags(mass) - dt * laplacian).tocsc())
    z = vertices[:, 2] / np.linalg.norm(vertices, axis=1)
    u = 3 * z**2 - 1
    for _ in range(steps):
        u = solver.solve(mass * u)
    return u


def mesh_sampler(vertices: np.ndarray, faces: np.ndarray,
                 points: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
    """Barycentric interpolation of vertex values at the closest points of ``points`` on the mesh."""
    _, face, closest = igl.point_mesh_squared_distance(points, vertices, faces)
    corners = faces[face]
    weights = trimesh.triangles.points_to_barycentric(vertices[corners], closest)
    return lambda values: (weights * values[corners]).sum(axis=1)


def mesh_error(subdivisions: int, steps: int, source: str = "igl") -> float:
    """Error of the mesh peer at the Fibonacci points, measured as for the grid."""
    vertices, faces = icosphere(subdivisions)
    points = fibonacci_sphere()
    values = mesh_sampler(vertices, faces, points)(mesh_heat_flow(vertices, faces, steps, source))
    return relative_error(values, points)


def mesh_peer(subdivisions: int, steps: int, source: str = "igl", repeats: int = 3) -> MeshRun:
    """Median wall time over ``repeats`` of the mesh peer (operators, factorisation, steps) and its error."""
    vertices, faces = icosphere(subdivisions)
    seconds = statistics.median(
        timed(lambda: mesh_heat_flow(vertices, faces, steps, source))[1] for _ in range(repeats))
    return MeshRun(subdivisions, len(vertices), steps, seconds, mesh_error(subdivisions, steps, source))


def fewest_steps(subdivisions: int, target: float, source: str = "igl") -> tuple[int, bool]:
    """First ladder step count whose error is at most ``target``, else the best one and ``False``.

    The error is not monotone in the steps (time and space errors have opposite signs), so the
    ladder is scanned in order; it stops once two rungs in a row fail to beat the best error.
    """
    best_steps, best_error, worse = STEP_LADDER[0], math.inf, 0
    for steps in STEP_LADDER:
        error = mesh_error(subdivisions, steps, source)
        if error <= target:
            return steps, True
        if error < best_error:
            best_steps, best_error, worse = steps, error, 0
        else:
            worse += 1
            if worse == 2:
                break
    return best_steps, False


def closest_subdivision(samples: int) -> int:
    """Icosphere subdivision whose vertex count ``10 * 4^k + 2`` is closest in ratio to ``samples``."""
    return min(range(MAX_SUBDIVISIONS + 1),
               key=lambda k: abs(math.log((10 * 4**k + 2) / samples)))


def mesh_peer_at_target(subdivisions: int, target: float, source: str = "igl") -> MeshRun:
    """Timed mesh peer on this icosphere with the fewest ladder steps reaching ``target``."""
    steps, reached = fewest_steps(subdivisions, target, source)
    return mesh_peer(subdivisions, steps, source)._replace(reached=reached)


def accuracy_matched(target: float, source: str = "igl") -> MeshRun:
    """The smallest icosphere (then fewest steps) reaching ``target``; the finest one's floor if none does."""
    for subdivisions in range(2, MAX_SUBDIVISIONS + 1):
        steps, reached = fewest_steps(subdivisions, target, source)
        if reached or subdivisions == MAX_SUBDIVISIONS:
            return mesh_peer(subdivisions, steps, source)._replace(reached=reached)
    raise AssertionError("unreachable")


def mesh_row(n: int | None, run: MeshRun, label: str, ours: Row | None) -> Row:
    """Table row of a mesh run; the ratio is the torchsurf row ``ours``'s time over the mesh's."""
    floor = "" if run.reached else ", floor"
    method = f"mesh peer icosphere({run.subdivisions}), {run.steps} BE steps, {label}{floor}"
    ratio = None if ours is None else ours.seconds / run.seconds
    return Row(n, method, run.vertices, run.seconds, run.error, ratio)


def mesh_rows(n: int, grid_rows: list[Row], target: float, match_error: float | None,
              source: str = "igl") -> list[Row]:
    """The samples-matched and the error-matched mesh-peer rows for the ``n^3`` grid."""
    ours = fastest_torchsurf(grid_rows)
    grid = ts.Grid.cube(n, bound=BOUND)
    samples = surface_samples(ts.sdf.sphere(grid, radius=1.0), grid)
    by_samples = mesh_peer_at_target(closest_subdivision(samples), target, source)
    rows = [mesh_row(n, by_samples, f"{samples:,} grid samples, target {target:.0e}", ours)]
    whose = "given"
    if match_error is None and ours is not None:
        match_error, whose = ours.error, f"{ours.method}'s"
    if match_error is not None:
        rows.append(mesh_row(n, accuracy_matched(match_error, source),
                             f"matched to {whose} error {match_error:.2e}", ours))
    return rows


def fastest_torchsurf(rows: list[Row]) -> Row | None:
    """The fastest torchsurf row (the numpy reference excluded), or ``None``."""
    candidates = [row for row in rows if row.method != REFERENCE_NAME]
    return min(candidates, key=lambda row: row.seconds, default=None)


def format_row(row: Row) -> str:
    """Markdown line of ``row``."""
    n = "—" if row.n is None else row.n
    ratio = "" if row.ratio is None else f"{row.ratio:.2f}"
    trilinear = "" if row.trilinear_error is None else f"{row.trilinear_error:.2e}"
    return (f"| {n} | {row.method} | {row.samples:,} | {row.seconds:.3f} | {row.error:.2e} "
            f"| {trilinear} | {ratio} |")


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[65, 129])
    parser.add_argument("--implicit-steps", type=int, default=10)
    parser.add_argument("--float64", action="store_true")
    parser.add_argument("--paired", type=int, metavar="N",
                        help="only time the default flow at N^3 against the mesh peer, alternated")
    parser.add_argument("--pairs", type=int, default=9)
    parser.add_argument("--paired-method", default="rkc", choices=("rkc", "euler", "heun"),
                        help="the flow's method in --paired (default settings otherwise)")
    parser.add_argument("--eager", action="store_true",
                        help="no warm-up: the untimed first call is not in backend.warm_up()")
    parser.add_argument("--no-reference", action="store_true")
    parser.add_argument("--reference-sizes", type=int, nargs="+",
                        help="grids for the numpy reference (default: --sizes); it is first order and "
                        "needs finer grids than the flows to reach the same error")
    peer = parser.add_mutually_exclusive_group()
    peer.add_argument("--no-mesh-peer", action="store_true", help="skip the mesh-peer rows")
    peer.add_argument("--mesh-peer-only", action="store_true", help="skip the torchsurf rows")
    parser.add_argument("--mesh-target", type=float, default=1e-3,
                        help="error the samples-matched mesh row must reach (default 1e-3)")
    parser.add_argument("--match-error", type=float, nargs="+",
                        help="error per size for the error-matched mesh row (default: fastest torchsurf row)")
    parser.add_argument("--subdivisions", type=int, nargs="+", default=[],
                        help="extra mesh-peer rows (n shown as —) at these icosphere subdivisions")
    parser.add_argument("--mesh-operators", choices=("igl", "numpy"), default="igl",
                        help="cotangent Laplacian and Voronoi mass from libigl or this file's numpy code")
    args = parser.parse_args(argv)
    if args.match_error is not None and len(args.match_error) != len(args.sizes):
        parser.error("--match-error needs one error per size")
    return args


def main(argv: list[str] | None = None) -> None:
    """Print the markdown table for the requested sizes."""
    args = parse_args(argv)
    if args.paired is not None:
        print("\n".join(paired(args.paired, args.pairs, args.mesh_target, warm=not args.eager,
                                method=args.paired_method)))
        return
    dtype = torch.float64 if args.float64 else torch.float32
    from _report import run_context  # benchmarks/_report.py, beside this script
    print(f"{run_context()}; {dtype}; mesh peer float64, scipy splu, {args.mesh_operators} "
          "operators")
    print("| n | method | surface samples / vertices | wall time (s) | max relative error on S "
          "| read trilinearly | fastest torchsurf time ÷ mesh time |")
    print("|---|---|---:|---:|---:|---:|---:|")
    match_errors = args.match_error or [None] * len(args.sizes)
    reference_sizes = [] if args.no_reference or args.mesh_peer_only else (
        args.reference_sizes if args.reference_sizes is not None else args.sizes)
    every_row = []
    for n, match_error in zip(args.sizes, match_errors, strict=True):
        rows = [] if args.mesh_peer_only else bench(n, args.implicit_steps, dtype,
                                                    n in reference_sizes, warm=not args.eager)
        if not args.no_mesh_peer:
            rows += mesh_rows(n, rows, args.mesh_target, match_error, args.mesh_operators)
        for row in rows:
            print(format_row(row), flush=True)
        every_row += rows
    for n in sorted(set(reference_sizes) - set(args.sizes)):
        row = reference_row(n, dtype)
        print(format_row(row), flush=True)
        every_row.append(row)
    for subdivisions in [] if args.no_mesh_peer else args.subdivisions:
        run = mesh_peer_at_target(subdivisions, args.mesh_target, args.mesh_operators)
        row = mesh_row(None, run, f"target {args.mesh_target:.0e}", None)
        print(format_row(row), flush=True)
        every_row.append(row)
    print()
    print("\n".join(time_to_accuracy(every_row, args.mesh_target)))


if __name__ == "__main__":
    main()
