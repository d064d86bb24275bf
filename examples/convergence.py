"""Convergence of the Laplace–Beltrami schemes on the exact cases of :mod:`torchsurf.exact`.

Prints a table of the max-norm error on the nodes within one cell of the surface and the
observed order between successive grids, for a sphere harmonic of each degree and a torus, and
writes it as Markdown (default ``outputs/convergence.md``).

    python examples/convergence.py [--sizes 17 33 65] [--output outputs/convergence.md]
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
from pathlib import Path

import torch

import torchsurf as ts
from torchsurf import exact

SCHEMES = ("octant", "symmetric", "conservative", "central")  # the default first


def cases() -> dict[str, exact.Case]:
    """Case name -> factory of the case on an ``n^3`` grid."""
    table = {
        f"sphere, l={degree}": (lambda n, degree=degree: exact.sphere_harmonic(degree, n))
        for degree in (1, 2, 3, 4)
    }
    table["torus"] = exact.torus_function
    return table


def convergence_table(sizes: list[int]) -> str:
    """Markdown table: one row per case, scheme and grid, with error and observed order."""
    rows = [
        "| case | scheme | n | h | max error near S | relative | order |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, make in cases().items():
        grids = {n: make(n) for n in sizes}
        for scheme in SCHEMES:
            previous = None
            for n, case in grids.items():
                surface = ts.ImplicitSurface(case.phi, case.grid)
                value = ts.laplace_beltrami(case.u, surface, scheme=scheme)
                mask = exact.near(case)
                error = exact.max_error(value, case.exact, mask)
                relative = error / float(case.exact[mask].abs().max())
                order = ""
                if previous is not None:
                    ratio = math.log(previous[0] / error) / math.log(previous[1] / case.grid.spacing)
                    order = f"{ratio:.2f}"
                rows.append(
                    f"| {name} | {scheme} | {n} | {case.grid.spacing:.4f} | {error:.3e} "
                    f"| {relative:.2e} | {order} |"
                )
                previous = (error, case.grid.spacing)
    return "\n".join(rows) + "\n"


def write_atomically(path: Path, text: str) -> None:
    """Write ``text`` to ``path`` through a temporary file, so no half-written file is left."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile("w", dir=path.parent, delete=False, suffix=".tmp") as tmp:
        tmp.write(text)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp.name, 0o666 & ~umask)  # a plain file's mode, not the temporary's 0600
    os.replace(tmp.name, path)


def main() -> None:
    description = __doc__.splitlines()[0].replace(":mod:", "").replace("`", "")
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--sizes", type=int, nargs="+", default=[17, 33, 65],
                        help="grid sizes n (n^3 nodes), coarse to fine (default: 17 33 65)")
    parser.add_argument("--output", type=Path, default=Path("outputs/convergence.md"),
                        help="Markdown table written here (default: outputs/convergence.md)")
    args = parser.parse_args()
    torch.set_default_dtype(torch.float64)
    table = convergence_table(args.sizes)
    print(table)
    header = (
        "# Laplace–Beltrami convergence\n\nMax-norm error on the nodes within one grid cell of "
        "S, float64; order between successive grids.\n\n"
    )
    write_atomically(args.output, header + table)
    print(f"written to {args.output}")


if __name__ == "__main__":
    main()
