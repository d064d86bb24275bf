"""Mesh -> narrow-band signed distance: torchsurf.sdf.from_mesh against libigl's full grid.

Run from the repository root:

    PYTHONPATH=. python benchmarks/bench_mesh_sdf.py [--resolution 128] [--large 256]

Uses the test meshes in ``$TORCHSURF_MESH_DIR`` (default ``../shared/data/meshes``); without
them it falls back to icospheres of similar size. Prints a Markdown table: the mesh, its faces,
the grid, the band's half-width, the sign method, wall-clock time, process CPU time (all
threads), and a note with the largest difference from libigl's full-grid signed distance
(clamped to the band) where that is computed.
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from pathlib import Path

import igl
import numpy as np
import torch
import trimesh
from _report import cpu_model  # benchmarks/_report.py, beside this script

import torchsurf as ts
from torchsurf.mesh import fit_grid

MESH_DIR = Path(
    os.environ.get("TORCHSURF_MESH_DIR", Path(__file__).resolve().parents[1] / "../shared/data/meshes")
)


def timed(function: Callable[..., object], *args: object, **kwargs: object
          ) -> tuple[object, float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    result = function(*args, **kwargs)
    return result, time.perf_counter() - wall, time.process_time() - cpu


def load(name: str, fallback_subdivisions: int) -> tuple[str, trimesh.Trimesh]:
    path = MESH_DIR / name
    if path.is_file():
        return name, trimesh.load(path)
    return (f"icosphere({fallback_subdivisions})",
            trimesh.creation.icosphere(subdivisions=fallback_subdivisions))


def row(label: str, mesh: trimesh.Trimesh, resolution: int, band_nodes: int, sign: str,
        wall: float, cpu: float, extra: str = "") -> str:
    return (f"| {label} | {len(mesh.faces):,} | {resolution}³ | {band_nodes} h | {sign} | "
            f"{wall:.2f} | {cpu:.2f} | {extra} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--large", type=int, default=256)
    parser.add_argument("--skip-full-grid", action="store_true")
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads (default: torch's, which follows OMP_NUM_THREADS)")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    print(f"machine: {cpu_model()}, {os.cpu_count()} CPUs, {torch.get_num_threads()} torch "
          f"threads, allocator: {os.environ.get('GLIBC_TUNABLES', 'glibc default')}, "
          f"load average {os.getloadavg()[0]:.1f} at start")
    print()
    print("| mesh | faces | grid | band | sign | wall s | CPU s | note |")
    print("|---|---|---|---|---|---|---|---|")
    for name, fallback in (("bunny_closed.obj", 6), ("bunny.obj", 6)):
        label, mesh = load(name, fallback)
        grid = fit_grid(mesh, args.resolution, margin=0.1)
        for band_nodes in (5, 3):
            band = band_nodes * grid.spacing
            phi, wall, cpu = timed(ts.sdf.from_mesh, mesh, grid, band_width=band, dtype=torch.float64)
            print(row(label, mesh, args.resolution, band_nodes, "auto", wall, cpu), flush=True)
        if args.skip_full_grid:
            continue
        points = grid.points(dtype=torch.float64).numpy().reshape(-1, 3)
        vertices = np.asarray(mesh.vertices, dtype=np.float64)
        faces = np.asarray(mesh.faces, dtype=np.int64)
        (full, *_), wall, cpu = timed(
            igl.signed_distance, points, vertices, faces,
            igl.SignedDistanceType.SIGNED_DISTANCE_TYPE_FAST_WINDING_NUMBER,
        )
        full = full.reshape(grid.shape)
        band = 3 * grid.spacing
        ours = phi[0, 0].numpy()
        in_band = np.abs(full) < band
        distance_gap = np.abs(np.abs(ours[in_band]) - np.abs(full[in_band])).max()
        sign_gap = int((np.sign(ours) != np.sign(full))[np.abs(full) > 1e-9].sum())
        note = (f"libigl full grid (FWN sign): max abs-distance gap in band "
                f"{distance_gap:.1e} ({distance_gap / mesh.extents.max():.1e} of bbox), "
                f"{sign_gap} nodes signed differently")
        print(row(label, mesh, args.resolution, 0, "igl FWN", wall, cpu, note), flush=True)

    label, mesh = load("bunny_closed.obj", 8)
    if label == "bunny_closed.obj":
        mesh = mesh.subdivide().subdivide()
        label = "bunny_closed.obj subdivided twice"
    grid = fit_grid(mesh, args.large, margin=0.1)
    _, wall, cpu = timed(ts.sdf.from_mesh, mesh, grid, dtype=torch.float64)
    print(row(label, mesh, args.large, 5, "auto", wall, cpu), flush=True)
    _, wall, cpu = timed(ts.sdf.from_mesh, mesh, grid, dtype=torch.float64, sign="winding")
    print(row(label, mesh, args.large, 5, "winding", wall, cpu), flush=True)


if __name__ == "__main__":
    main()
