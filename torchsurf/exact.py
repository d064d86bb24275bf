"""Exact validation cases for the intrinsic operators , evaluated band-wide.

Used by the tests and by ``examples/convergence.py``; each case is a grid, a distance function
``phi`` ``(1, 1, D, H, W)``, data ``u`` ``(1, 1, D, H, W)`` and the exact ``Lap_S u``.

Data constant along the normals of a distance function is a function on every level set at
once, so each node can be compared with the exact operator on the level set through it: the
concentric sphere of radius ``|x - c|``, or the torus with the same core circle and tube radius
``rho``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from . import sdf
from ._checks import check_count, check_tensor
from .grid import Grid

__all__ = [
    "Case",
    "SPHERE_CENTER",
    "SPHERE_RADIUS",
    "TORUS_MARGIN_CELLS",
    "TORUS_RADII",
    "max_error",
    "near",
    "polar_angle_frame",
    "sphere_harmonic",
    "torus_coordinates",
    "torus_function",
]

SPHERE_CENTER = (0.04, -0.03, 0.02)
SPHERE_RADIUS = 0.9
TORUS_RADII = (1.0, 0.4)


@dataclass
class Case:
    """One exact case: ``exact`` is ``Lap_S u`` on the level set through each node.

    Attributes:
        grid: the grid.
        phi: ``(1, 1, D, H, W)`` the surface's signed distance, world units.
        u: ``(1, 1, D, H, W)`` the data, constant along the normals.
        exact: ``(1, 1, D, H, W)`` its Laplace–Beltrami value, units of ``u`` per world
            length squared.
    """

    grid: Grid
    phi: Tensor
    u: Tensor
    exact: Tensor


def _sphere_frame(points: Tensor) -> tuple[Tensor, Tensor]:
    """Unit direction from the sphere's centre and the distance to it."""
    local = points - points.new_tensor(SPHERE_CENTER)
    radius = local.norm(dim=-1).clamp(min=1e-9)
    return local / radius[..., None], radius


def sphere_harmonic(degree: int, n: int, dtype: torch.dtype = torch.float64) -> Case:
    """Spherical harmonic of ``degree`` 1..4: ``Lap_S u = -l(l+1) u / r^2``.

    The sphere of radius :data:`SPHERE_RADIUS` about :data:`SPHERE_CENTER` (off the nodes'
    symmetry), on ``Grid.cube(n, bound=1.4)``; ``u`` is the harmonic of the direction from the
    centre, so constant along the normals, and ``exact`` holds ``-l(l+1) u / r^2`` with ``r``
    each node's own distance from the centre (the Laplace–Beltrami operator of the level set
    through it). Tensors ``(1, 1, n, n, n)`` in ``dtype``.
    """
    degree = check_count(degree, "degree")  # refuses bools and fractions by name
    if degree not in (1, 2, 3, 4):
        raise ValueError(f"degree must be 1, 2, 3 or 4, got {degree!r}")
    grid = Grid.cube(n, bound=1.4)
    points = grid.points(dtype=dtype)
    direction, r = _sphere_frame(points)
    x, y, z = direction.unbind(-1)
    harmonics = {1: z, 2: 3 * z**2 - 1, 3: x * y * z, 4: 35 * z**4 - 30 * z**2 + 3}
    u = harmonics[degree]
    exact = -degree * (degree + 1) * u / r**2
    phi = sdf.sphere(grid, SPHERE_RADIUS, center=SPHERE_CENTER, dtype=dtype)
    return Case(grid, phi, u[None, None], exact[None, None])


def torus_coordinates(points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """``(theta, v, rho, ring)`` of ``points`` ``(..., 3)`` world ``(x, y, z)`` about the torus
    of :data:`TORUS_RADII` centred at the origin, each ``(...)``: azimuth and tube angle
    (radians, ``v = 0`` on the outer equator), distance from the tube's core circle and from the
    z axis (world units)."""
    x, y, z = points.unbind(-1)
    ring = torch.sqrt(x**2 + y**2)
    radial = ring - TORUS_RADII[0]
    return torch.atan2(y, x), torch.atan2(z, radial), torch.sqrt(radial**2 + z**2), ring


TORUS_MARGIN_CELLS = 3
"""Fewest cells :func:`torus_function` leaves between the torus and the box's faces."""


def torus_function(n: int, dtype: torch.dtype = torch.float64) -> Case:
    """``u = cos v + sin(2 theta) sin v`` on the torus ``R = 1, r = 0.4`` (:data:`TORUS_RADII`),
    ``theta`` about the z axis and ``v`` about the tube; tensors ``(1, 1, n, n, n)`` in
    ``dtype``, ``exact`` on the level set through each node.

    On a torus ``Lap f = f_tt / ring^2 + f_vv / rho^2 - sin v f_v / (rho ring)``. The box is
    ``[-1.6, 1.6]^3``, or wider where that leaves fewer than :data:`TORUS_MARGIN_CELLS` cells
    between the torus and the faces (below 49 nodes a side): the stencils assume no flux
    through the faces, and the surface warns closer.

    ``exact`` is NaN at nodes whose level set is no torus: on the z axis (odd ``n``) and on the
    core circle, within a cell of S on grids coarser than about 15 nodes a side;
    :func:`near` leaves them out.
    """
    n = check_count(n, "n")
    if n < 2 * TORUS_MARGIN_CELLS + 3:
        raise ValueError(f"n must be at least {2 * TORUS_MARGIN_CELLS + 3} (the torus and "
                         f"{TORUS_MARGIN_CELLS} cells on each side), got {n}")
    outer = TORUS_RADII[0] + TORUS_RADII[1]
    grid = Grid.cube(n, bound=max(1.6, outer * (n - 1) / (n - 1 - 2 * TORUS_MARGIN_CELLS)))
    theta, v, rho, ring = torus_coordinates(grid.points(dtype=dtype))
    u = torch.cos(v) + torch.sin(2 * theta) * torch.sin(v)
    u_tt = -4 * torch.sin(2 * theta) * torch.sin(v)
    u_v = -torch.sin(v) + torch.sin(2 * theta) * torch.cos(v)
    u_vv = -u
    exact = u_tt / ring**2 + u_vv / rho**2 - torch.sin(v) * u_v / (rho * ring)
    degenerate = 1e-9 * grid.spacing  # rounding puts core-circle nodes 1e-16 off it
    exact = exact.masked_fill((ring < degenerate) | (rho < degenerate), float("nan"))
    phi = sdf.torus(grid, *TORUS_RADII, dtype=dtype)
    if not bool((phi < 0).any()):
        raise ValueError(f"n={n}: at spacing {grid.spacing:.3g} no node lies inside the torus's "
                         f"tube (radius {TORUS_RADII[1]}), so it has no surface on the grid; "
                         "use n >= 11")
    return Case(grid, phi, u[None, None], exact[None, None])


def polar_angle_frame(points: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """For the sphere case: ``(cos theta, sin theta, e_theta, r)``, ``e_theta`` ``(..., 3)``.

    ``theta`` is the polar angle from +z about the sphere's centre and ``e_theta`` the unit
    tangent pointing towards increasing ``theta`` (southwards).
    """
    direction, r = _sphere_frame(points)
    cos = direction[..., 2]
    sin = torch.sqrt((1 - cos**2).clamp(min=1e-12))
    e_theta = (cos[..., None] * direction - points.new_tensor((0.0, 0.0, 1.0))) / sin[..., None]
    return cos, sin, e_theta, r


def near(case: Case, cells: float = 1.0) -> Tensor:
    """Boolean ``(1, 1, D, H, W)``: nodes within ``cells`` grid spacings of the surface where
    ``case.exact`` is defined (finite)."""
    return (case.phi.abs() <= cells * case.grid.spacing) & case.exact.isfinite()


def max_error(value: Tensor, exact: Tensor, mask: Tensor) -> float:
    """Largest ``|value - exact|`` over the nodes of ``mask``: ``value`` and ``exact``
    ``(B, C, D, H, W)``, ``mask`` bool ``(B or 1, 1, D, H, W)``; in ``value``'s units."""
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        raise TypeError(f"mask must be a bool tensor, got "
                        f"{getattr(mask, 'dtype', type(mask).__name__)}")
    value, exact = check_tensor(value, "value"), check_tensor(exact, "exact")
    for name, other in (("exact", exact), ("mask", mask)):
        if other.dim() != value.dim() or any(
                o not in (1, v) for o, v in zip(other.shape, value.shape, strict=True)):
            raise ValueError(f"{name} has shape {tuple(other.shape)}; it must broadcast to "
                             f"value's shape {tuple(value.shape)} (sizes equal or 1)")
    if not mask.any():
        raise ValueError(f"mask selects no node (shape {tuple(mask.shape)}): no error to take "
                         "the largest of")
    return float((value - exact).abs()[mask.expand_as(value)].max())
