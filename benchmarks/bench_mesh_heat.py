"""Heat flow through ``MeshAdapter`` with its defaults, against a cotangent-Laplacian reference.

For each mesh (normalised to a bounding-box diagonal of 1) and each resolution, the script
encodes a smooth vertex signal, runs ``HeatFlow(time=t)`` with every default (RKC, fixed band,
octant scheme), decodes at the vertices and compares with the reference on the mesh itself:
the cotangent Laplacian ``L`` and lumped (Voronoi) mass ``M`` of libigl, integrated by
Crank–Nicolson with ``--reference-steps`` steps (``(M - dt/2 L) u' = (M + dt/2 L) u``, sparse LU).
The error is ``max |u - u_ref| / max |u0|`` over the vertices (and the RMS in the same units).

The signal is ``sin(2 pi (a . x))`` for a fixed direction ``a`` with ``|a| = 2`` (two periods across
the box), and ``t = (0.05 diag)^2`` by default. Refining the grid should make the error fall
towards the reference's own discretisation error (a mesh of 10^4-10^5 faces: far finer than the
grids).

Run::

    GLIBC_TUNABLES=glibc.malloc.mmap_threshold=4294967296:glibc.malloc.trim_threshold=68719476736 \\
        PYTHONPATH=. python benchmarks/bench_mesh_heat.py --meshes bunny_closed spot \\
        --resolutions 64 96 128 --output docs/benchmarks.md
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import sys
import time
from pathlib import Path

import igl
import numpy as np
import scipy.sparse as sparse
import scipy.sparse.linalg as sparse_linalg
import torch
import trimesh
from _report import cpu_model, write_section  # benchmarks/_report.py, beside this script

import torchsurf as ts

SECTION = "bench_mesh_heat"
MESH_DIR = Path(os.environ.get("TORCHSURF_MESH_DIR",
                               Path(__file__).resolve().parents[2] / "shared" / "data" / "meshes"))


def normalised(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh centred at the origin with a bounding-box diagonal of 1."""
    mesh = mesh.copy()
    low, high = mesh.bounds
    mesh.apply_translation(-(low + high) / 2)
    mesh.apply_scale(1.0 / float(np.linalg.norm(high - low)))
    return mesh


def signal(vertices: np.ndarray) -> np.ndarray:
    """``sin(2 pi a . x)``, ``a`` fixed with ``|a| = 2``; ``(V,)``."""
    direction = np.array([0.48, 0.6, 0.64])
    direction = 2.0 * direction / np.linalg.norm(direction)
    return np.sin(2 * math.pi * vertices @ direction)


def cotangent_heat(mesh: trimesh.Trimesh, u0: np.ndarray, time_end: float, steps: int
                   ) -> np.ndarray:
    """Crank–Nicolson heat flow ``M u' = L u`` on the mesh (libigl cotangent ``L``, Voronoi ``M``)."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    laplacian = igl.cotmatrix(vertices, faces)
    mass = igl.massmatrix(vertices, faces, igl.MASSMATRIX_TYPE_VORONOI)
    dt = time_end / steps
    left = sparse.csc_matrix(mass - 0.5 * dt * laplacian)
    right = sparse.csr_matrix(mass + 0.5 * dt * laplacian)
    solve = sparse_linalg.factorized(left)
    u = u0.copy()
    for _ in range(steps):
        u = solve(right @ u)
    return u


def run_case(mesh: trimesh.Trimesh, resolution: int, time_end: float, u0: np.ndarray
             ) -> dict[str, float]:
    start = time.perf_counter()
    adapter = ts.MeshAdapter(mesh, resolution=resolution)
    setup = time.perf_counter() - start
    values = torch.as_tensor(u0, dtype=torch.float32)[None, None]
    start = time.perf_counter()
    with torch.no_grad():
        field = ts.HeatFlow(time=time_end)(adapter.encode(values), adapter.surface)
        decoded = adapter.decode(field)[0, 0].double().numpy()
    flow = time.perf_counter() - start
    return {"setup_s": setup, "flow_s": flow, "decoded": decoded}


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--meshes", nargs="+", default=["bunny_closed", "spot", "armadillo"])
    parser.add_argument("--resolutions", type=int, nargs="+", default=[64, 96, 128])
    parser.add_argument("--time-fraction", type=float, default=0.05,
                        help="t = (fraction x bounding-box diagonal)^2")
    parser.add_argument("--reference-steps", type=int, default=200)
    parser.add_argument("--threads", type=int, default=None,
                        help="torch threads (default: torch's, e.g. from OMP_NUM_THREADS)")
    parser.add_argument("--output", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    time_end = args.time_fraction**2
    lines = [
        f"Date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}. "
        f"{cpu_model()}, torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"GLIBC_TUNABLES=`{os.environ.get('GLIBC_TUNABLES', 'unset')}`.",
        "",
        f"Command: `PYTHONPATH=. python benchmarks/bench_mesh_heat.py {' '.join(argv)}`",
        "",
        f"Meshes normalised to a box diagonal of 1; `t = {time_end:g}` "
        f"(({args.time_fraction:g} diag)²); signal `sin(2π a·x)`, `|a| = 2`. Reference: "
        f"cotangent Laplacian on the mesh, Crank–Nicolson, {args.reference_steps} steps. "
        "Errors over the vertices, relative to max |u0|. `flow s` is encode + flow + decode.",
        "",
        "| mesh | vertices | resolution | max error | RMS error | setup s | flow s |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name in args.meshes:
        mesh = normalised(trimesh.load(MESH_DIR / f"{name}.obj", force="mesh"))
        u0 = signal(np.asarray(mesh.vertices))
        reference = cotangent_heat(mesh, u0, time_end, args.reference_steps)
        scale = np.abs(u0).max()
        change = np.abs(reference - u0).max() / scale
        print(f"{name}: {len(mesh.vertices)} vertices, reference changed u by {change:.3f}")
        for resolution in args.resolutions:
            result = run_case(mesh, resolution, time_end, u0)
            error = result["decoded"] - reference
            max_error = np.abs(error).max() / scale
            rms = np.sqrt(np.mean(error**2)) / scale
            row = (f"| {name} | {len(mesh.vertices)} | {resolution} | {max_error:.2e} "
                   f"| {rms:.2e} | {result['setup_s']:.1f} | {result['flow_s']:.1f} |")
            print(row, flush=True)
            lines.append(row)
    body = "\n".join(lines) + "\n"
    print(body)
    if args.output is not None:
        write_section(args.output, SECTION, "## Heat flow on meshes through MeshAdapter", body.rstrip("\n"))


if __name__ == "__main__":
    main()
