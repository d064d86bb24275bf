"""Signed distance functions sampled on a grid as ``phi`` volumes: analytic shapes, meshes,
and the redistancing of any implicit function.

``phi`` is negative inside and positive outside. The shapes and :func:`from_mesh` return
``(1, 1, D, H, W)`` exact distances (:func:`from_function` samples whatever it is given);
:func:`redistance` maps ``(B, 1, D, H, W)`` to ``(B, 1, D, H, W)``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from . import _isosurface, _memory, _mesh_sdf
from ._checks import (
    check_choice,
    check_count,
    check_device,
    check_dtype,
    check_finite,
    check_positive,
    check_real,
    check_spatial_shape,
    check_triple,
    check_volume,
)
from ._mesh_input import MeshLike, as_trimesh, triangle_arrays
from ._precision import in_data_dtype
from ._stack import caller_stacklevel
from .grid import Grid

__all__ = [
    "BAND_NODES",
    "NARROW_BAND_NODES",
    "box",
    "capsule",
    "from_function",
    "from_mesh",
    "redistance",
    "sphere",
    "torus",
    "trefoil",
]

Point = Sequence[float]


def from_function(
    grid: Grid,
    function: Callable[[Tensor], Tensor],
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Sample an implicit function at every node of ``grid``.

    Args:
        grid: the grid.
        function: maps world points ``(D, H, W, 3)`` ``(x, y, z)`` to values ``(D, H, W)``.
        dtype, device: of the points given to ``function`` (default dtype, CPU).

    Returns:
        ``phi`` ``(1, 1, D, H, W)``.
    """
    return _sampled(grid, function, dtype, device, None, "function")


def _sampled(grid: Grid, function: Callable[[Tensor], Tensor], dtype: torch.dtype | None,
             device: torch.device | str | None, center: Point | None,
             source: str | None = None) -> Tensor:
    """:func:`from_function`, ``function`` given the points relative to ``center`` (computed
    in float64 before the cast: :meth:`Grid.points`'s ``relative_to``); ``source``: what the
    errors name (``"function"``, a user's; ``None``, a shape of this module's)."""
    if not isinstance(grid, Grid):
        raise TypeError(f"grid must be a torchsurf.Grid, got {type(grid).__name__}")
    dtype = check_dtype(dtype)
    device = check_device(device)
    if not callable(function):
        raise TypeError(f"function must map world points (D, H, W, 3) to values (D, H, W), got "
                        f"{type(function).__name__}")
    if center is not None:
        center = check_triple(center, "center", check_real)
    _memory.check_fits(_memory.sampled_bytes(grid.shape, dtype),
                       f"sampling a function on a {grid.shape} grid", device)
    points = grid.points(dtype=dtype, device=device, relative_to=center)
    values = function(points)
    if not isinstance(values, Tensor) or tuple(values.shape) != tuple(grid.shape):
        shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
        raise ValueError(
            f"function must map points (D, H, W, 3) to a tensor (D, H, W) = {grid.shape}, "
            f"got {shape}"
        )
    if not values.is_floating_point():
        raise TypeError(f"function must return real floating-point values, got {values.dtype}")
    values = values.to(dtype)
    if not bool(torch.isfinite(values).all()):
        bad, count = int((~torch.isfinite(values)).sum()), values.numel()
        if source is not None:
            raise ValueError(f"{source} returned NaN or infinity at {bad} of {count} nodes (in "
                             f"{values.dtype})")
        raise ValueError(f"the distance is NaN or infinite at {bad} of {count} nodes in "
                         f"{values.dtype}: the grid or the shape's sizes lie beyond its range")
    return values[None, None]


def sphere(
    grid: Grid,
    radius: float = 1.0,
    center: Point = (0.0, 0.0, 0.0),
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Signed distance to the sphere ``|x - center| = radius``; ``(1, 1, D, H, W)``.

    Sampled at ``grid``'s nodes, lengths in world units, in ``dtype`` (default: torch's
    default dtype) on ``device`` (default: the CPU).
    """
    check_positive(radius, "radius")
    return _sampled(grid, lambda local: local.norm(dim=-1) - radius, dtype, device, center)


def torus(
    grid: Grid,
    major_radius: float = 1.0,
    minor_radius: float = 0.4,
    center: Point = (0.0, 0.0, 0.0),
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Signed distance to the torus around the z axis through ``center``; ``(1, 1, D, H, W)``.

    The tube of radius ``minor_radius`` follows the circle of radius ``major_radius`` in the
    plane ``z = center z``.

    Sampled at ``grid``'s nodes, lengths in world units, in ``dtype`` (default: torch's
    default dtype) on ``device`` (default: the CPU).
    """
    check_positive(major_radius, "major_radius")
    check_positive(minor_radius, "minor_radius")
    if minor_radius >= major_radius:
        raise ValueError(
            f"minor_radius={minor_radius:g} must be below major_radius={major_radius:g}: a tube "
            "that reaches the axis (a horn or spindle torus) is not at the distance to the ring "
            "minus the tube's radius inside (2 cells off at 0.2 / 0.5); give its distance to "
            "from_function, or its mesh to from_mesh")

    def distance(local: Tensor) -> Tensor:
        ring = local[..., :2].norm(dim=-1) - major_radius
        return torch.sqrt(ring**2 + local[..., 2] ** 2) - minor_radius

    return _sampled(grid, distance, dtype, device, center)


def box(
    grid: Grid,
    half_size: Point = (0.5, 0.5, 0.5),
    center: Point = (0.0, 0.0, 0.0),
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Signed distance to the axis-aligned box of half extents ``half_size`` ``(x, y, z)``
    about ``center``; ``(1, 1, D, H, W)``.

    Sampled at ``grid``'s nodes, lengths in world units, in ``dtype`` (default: torch's
    default dtype) on ``device`` (default: the CPU).
    """
    half_size = check_triple(half_size, "half_size", check_real)
    for length in half_size:
        check_positive(length, "half_size")

    def distance(local: Tensor) -> Tensor:
        excess = local.abs() - local.new_tensor(half_size)
        outside = excess.clamp(min=0).norm(dim=-1)
        inside = excess.max(dim=-1).values.clamp(max=0)
        return outside + inside

    return _sampled(grid, distance, dtype, device, center)


def capsule(
    grid: Grid,
    start: Point = (0.0, 0.0, -0.5),
    end: Point = (0.0, 0.0, 0.5),
    radius: float = 0.4,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Signed distance to the capsule of ``radius`` around the segment ``start``–``end``;
    ``(1, 1, D, H, W)``.

    Sampled at ``grid``'s nodes, lengths in world units, in ``dtype`` (default: torch's
    default dtype) on ``device`` (default: the CPU).
    """
    check_positive(radius, "radius")
    start = check_triple(start, "start", check_real)
    end = check_triple(end, "end", check_real)

    axis64 = [float(b) - float(a) for a, b in zip(start, end, strict=True)]
    if axis64 == [0.0, 0.0, 0.0]:
        raise ValueError("start and end must differ")

    def distance(local: Tensor) -> Tensor:
        axis = local.new_tensor(axis64)
        with in_data_dtype(local):
            t = ((local @ axis) / torch.dot(axis, axis)).clamp(0.0, 1.0)
        return (local - t[..., None] * axis).norm(dim=-1) - radius

    return _sampled(grid, distance, dtype, device, start)


def _trefoil_curve(t: Tensor, scale: float) -> tuple[Tensor, Tensor, Tensor]:
    """Point, first and second derivative ``(..., 3)`` of the trefoil at parameters ``t``."""
    s1, c1 = torch.sin(t), torch.cos(t)
    s2, c2 = 2 * s1 * c1, c1 * c1 - s1 * s1
    s3, c3 = s1 * (3 - 4 * s1 * s1), c1 * (4 * c1 * c1 - 3)
    point = torch.stack((s1 + 2 * s2, c1 - 2 * c2, -s3), dim=-1)
    velocity = torch.stack((c1 + 4 * c2, -s1 + 4 * s2, -3 * c3), dim=-1)
    acceleration = torch.stack((-s1 - 8 * s2, -c1 + 8 * c2, 9 * s3), dim=-1)
    return scale * point, scale * velocity, scale * acceleration


def _refined_distance(points: Tensor, t: Tensor, scale: float) -> Tensor:
    """Distance from ``points`` ``(N, 3)`` to the trefoil, Newton-refined from parameters ``t``."""
    for _ in range(3):  # quadratic convergence from within half a sample spacing
        point, velocity, acceleration = _trefoil_curve(t, scale)
        offset = point - points
        slope = (offset * velocity).sum(-1)
        curvature = (velocity * velocity).sum(-1) + (offset * acceleration).sum(-1)
        t = t - slope / curvature.clamp(min=1e-12)
    return (_trefoil_curve(t, scale)[0] - points).norm(dim=-1)


def trefoil(
    grid: Grid,
    tube_radius: float = 0.12,
    scale: float = 0.4,
    center: Point = (0.0, 0.0, 0.0),
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    samples: int = 192,
    chunk: int = 65536,
) -> Tensor:
    """Signed distance to a tube of ``tube_radius`` around a trefoil knot; ``(1, 1, D, H, W)``.

    The core curve is ``scale * (sin t + 2 sin 2t, cos t - 2 cos 2t, -sin 3t)`` about ``center``
    (about ``6 scale`` across). Strands come within ``1.21 scale`` of each other, so the tube
    is embedded for ``tube_radius < 0.6 scale``. Each node's closest curve parameter is found
    among ``samples`` (at least 24: with 16, four band nodes were 1.2 cells off at 33^3)
    points of the curve and refined by Newton's method on
    ``(c(t) - x) . c'(t) = 0``, so the distance is that to the smooth curve (to rounding), not
    to a polyline. A genus-1 surface that is always available, unlike the mesh files.

    Sampled at ``grid``'s nodes, lengths in world units, in ``dtype`` (default: torch's
    default dtype) on ``device`` (default: the CPU).
    ``chunk`` nodes are compared with the ``samples`` curve points at once (a ``(chunk,
    samples)`` distance table).
    """
    check_positive(tube_radius, "tube_radius")
    check_positive(scale, "scale")
    if tube_radius >= 0.6 * scale:
        raise ValueError(
            f"tube_radius must be below 0.6 * scale = {0.6 * scale:g} for the tube not to "
            f"intersect itself, got {tube_radius!r}"
        )
    samples = check_count(samples, "samples", minimum=24)  # 16: 1.2 cells off at 33^3
    chunk = check_count(chunk, "chunk")

    def distance(local: Tensor) -> Tensor:
        flat = local.reshape(-1, 3)
        compute = flat.double()
        t_samples = torch.linspace(0, 2 * torch.pi, samples + 1, dtype=torch.float64,
                                   device=flat.device)[:-1]
        curve = _trefoil_curve(t_samples, scale)[0].float()
        # Pairs of samples on different strands: the strands nearest in space are over
        # 1 radian apart in t, so a node nearly equidistant to two is refined from both.
        apart = torch.remainder(t_samples[None] - t_samples[:, None], 2 * torch.pi)
        other_strand = (apart > 1.0) & (apart < 2 * torch.pi - 1.0)
        result = []
        for block in compute.split(chunk):
            coarse = torch.cdist(block.float(), curve)
            nearest = coarse.argmin(dim=1)
            other = coarse.masked_fill(~other_strand[nearest], float("inf")).argmin(dim=1)
            distance = torch.minimum(
                _refined_distance(block, t_samples[nearest], scale),
                _refined_distance(block, t_samples[other], scale),
            )
            result.append(distance - tube_radius)
        return torch.cat(result).to(local.dtype).reshape(local.shape[:-1])

    return _sampled(grid, distance, dtype, device, center)


BAND_NODES = 5
"""Default half-width of the band of :func:`from_mesh` and :func:`redistance`, in grid spacings:
the default band of :class:`~torchsurf.ImplicitSurface` (3) plus two nodes along an axis. Not
every value an operator on the band reads: the normals at its stencils' diagonal neighbours
difference ``phi`` out to ``3 + 2 sqrt(3)`` (6.5) cells, where ``phi`` is clamped at 5, so the
operators there differ from those of an exact distance by up to 3e-5 relative (spot and
bunny_closed at 56^3, float64; an audit); ``band_width = 7 h`` makes them equal (as
:func:`torchsurf.bricks.from_mesh`'s exact reach of 3.5 cells beyond its band does)."""


NARROW_BAND_NODES = 4.0
"""A ``band_width`` of fewer grid spacings than this is warned about by :func:`from_mesh` and
:func:`redistance`: ``phi`` clamped inside what the operators on the surface's band read costs
them accuracy. Heat flow of ``z / r`` to ``t = 0.05`` on an icosphere (5 subdivisions) at
48^3, float64, largest error on S: 1.4e-4 with the default 5, 2.2e-4 with 4, 1.6e-3 with 3.5,
3.4e-3 with 3, 6.7e-3 with 2 (an exact sphere distance clamped alike gives the same)."""


def _band(grid: Grid, band_width: float | None, clamps: bool = True) -> float:
    """``band_width`` checked (default :data:`BAND_NODES` cells); warned of below
    :data:`NARROW_BAND_NODES` cells where it ``clamps`` phi (the adapters compute phi out to 5
    cells whatever their band)."""
    if not isinstance(grid, Grid):
        raise TypeError(f"grid must be a torchsurf.Grid, got {type(grid).__name__}")
    if band_width is None:
        return BAND_NODES * grid.spacing
    width = check_positive(band_width, "band_width")
    if clamps and width < NARROW_BAND_NODES * grid.spacing * (1 - 1e-9):
        warnings.warn(
            f"band_width = {width / grid.spacing:.3g} grid spacings clamps phi inside what the "
            f"operators on the surface's band read (about {NARROW_BAND_NODES:g} spacings and "
            "more): flows and operators lose accuracy there (a heat flow on a sphere: 24x at 3 "
            f"spacings); keep it at least {NARROW_BAND_NODES:g} (default {BAND_NODES})",
            RuntimeWarning, stacklevel=caller_stacklevel())
    return width


def from_mesh(
    mesh: MeshLike,
    grid: Grid,
    band_width: float | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
    sign: str = "auto",
) -> Tensor:
    """Signed distance to a triangle mesh, exact in a narrow band, clamped to ``+-band_width`` beyond.

    Every node within ``band_width`` of the mesh gets its exact distance to the nearest triangle
    (libigl's AABB tree, float64); only the nodes near the surface are visited (bricks of nodes
    far from the mesh are skipped whole). Signs come from the generalised winding number
    (inside where it exceeds 1/2; libigl's fast winding number), so meshes with holes or several
    components still get a sensible inside; signs are right everywhere except in a thin shell
    around holes, where the winding number passes 1/2. An opening wider than the band is
    closed by a cap of phi's zero set on which phi jumps from ``-band_width`` to
    ``+band_width`` (a ``RuntimeWarning``: operators and flows run on it too). A closed part
    wholly inside another and wound like it (normals out: an eye modelled inside a head) is
    solid within solid, no part of S, with a ``RuntimeWarning`` (wound inward, it is a
    cavity). Faces wound against their neighbours (an edge of two faces that both traverse it
    the same way) are re-oriented first (``trimesh.repair.fix_winding``, with a
    ``RuntimeWarning``): both sign methods need a consistent winding. Vertices are matched by
    position, so a triangle soup (three vertices of its own per face, as STL stores it) is
    wound and closed like the indexed mesh.

    Args:
        mesh: a ``trimesh.Trimesh``, a path to any file trimesh reads, or a pair
            ``(vertices (V, 3), faces (F, 3))``; world coordinates ``(x, y, z)``.
        grid: the grid to sample on.
        band_width: half-width of the band, world units (default ``5 * grid.spacing``, see
            :data:`BAND_NODES`; below :data:`NARROW_BAND_NODES` spacings, warned of).
        dtype, device: of the result (``torch.float32`` or ``torch.float64``; default dtype, CPU).
        sign: ``"auto"`` (default), ``"winding"`` or ``"pseudonormal"``. ``"winding"`` asks
            the winding number at every node near the mesh; ``"pseudonormal"`` signs the band
            by the angle-weighted pseudonormal of the closest feature (exact for closed,
            consistently wound meshes without self-intersections, and several times faster);
            ``"auto"`` takes ``"pseudonormal"`` when every edge joins two oppositely wound
            faces, else ``"winding"``; it also takes ``"winding"`` where the winding number at
            up to 40,000 band nodes (at the band's edge and spread over it) disagrees with the
            pseudonormals (closed parts that intersect, or one wound against the others).
            A closed mesh wound inward as a whole (every outermost part's normals pointing
            in) is turned outward first for ``"pseudonormal"`` and ``"auto"``;
            ``"winding"`` refuses it.
            Beyond the band the sign is always the winding number's: node by node where a
            far brick's centre has one between 0.1 and 0.9 (across a hole), else the
            centre's for the whole brick.

    Returns:
        ``phi`` ``(1, 1, D, H, W)``: negative inside, positive outside, world units.

    Raises:
        ValueError: the mesh is invalid (see :func:`torchsurf.mesh.load`), or no node of the
            grid lies inside it, or none outside (mesh outside the grid, enclosing nothing,
            or larger than the grid).
        MemoryError: before any work, if the grid cannot fit (:mod:`torchsurf._memory`).

    Faces of zero area are kept: the distance to them is exact and they change no sign (vertex
    data read on one, :class:`~torchsurf.MeshAdapter`, interpolate along its longest edge).

    Example:
        >>> import trimesh
        >>> grid = Grid.cube(33, bound=1.5)
        >>> phi = from_mesh(trimesh.creation.icosphere(subdivisions=3), grid)
        >>> phi.shape
        torch.Size([1, 1, 33, 33, 33])
    """
    width = _band(grid, band_width)
    check_choice(sign, "sign", _mesh_sdf.SIGN_METHODS)
    dtype = check_dtype(dtype)
    device = check_device(device)
    mesh = as_trimesh(mesh, "mesh")
    _memory.check_fits(
        _memory.mesh_sdf_bytes(grid.shape, grid.spacing, width, float(mesh.area), dtype),
        f"sdf.from_mesh on a {grid.shape} grid",
    )
    vertices, faces = triangle_arrays(mesh)
    phi, _ = _mesh_sdf.signed_band(vertices, faces, grid, width, sign)
    _mesh_sdf.check_sides(phi, vertices, faces, grid, "mesh")
    return torch.as_tensor(phi, dtype=dtype, device=device)[None, None]


def redistance(phi: Tensor, grid: Grid, band_width: float | None = None) -> Tensor:
    """Turn any implicit function into a signed distance function in the band.

    Every node within ``band_width`` of the zero set gets its distance to the zero set of
    ``phi``'s tricubic interpolant (:func:`torchsurf.sampling.sample`, ``O(h^4)`` for a smooth
    ``phi``), with the sign of ``phi``; the others get ``+-band_width``. The closest points
    start on the marching-cubes surface of ``phi`` and are refined by Newton's iteration on the
    interpolant (Chopp 2001, its tangential step scaled by the curvature), so that the result
    is smooth enough for curvatures: distances to the flat triangles alone left the mean
    curvature of a sphere 47 % off at every resolution, now second order
    (``tests/test_redistance.py``); where ``phi`` is its own interpolant (a quadratic) the
    result is exact to 1e-5 cells across the band, also around features 4 cells thick or more
    (a flattened ellipsoid 3 cells thick: 0.26 cells too long at nodes 4 cells out beside its
    rim, 33^3). Sharp edges and corners of S are rounded about a cell deep: a box's exact
    distance moves by up to 0.65 cells outside beside its corners (0.56 beside its edges, 0.07
    inside), and a second pass moves it again (an audit, 2026-12-06).
    The zero set is known inside the box only: next to a face that S crosses, a node gets its
    distance to the part of S inside, which is too long where S leaves the face obliquely (a
    sphere's ``r^2 - R^2``, ``R = 0.7``, centre 0.4 inside a face: up to 1.4 cells off at the
    face nodes at 33^3 to 65^3, no finer grid helps, normals 22 degrees off) and up to 0.025
    cells where it meets the face at right angles (33^3; first order): keep S a few cells
    inside the box, as :class:`~torchsurf.ImplicitSurface` warns.
    Where the iteration does not settle (near the medial axis, at creases of ``phi``) a node
    keeps its distance to the triangles. Parts of S thinner than about a cell that pass between
    nodes of one sign are not seen, and are lost: a tilted ellipsoid's quadric 0.8 / 1.6 cells
    thick had 35% / 14% of its area over half a cell off afterwards (33^3); a ``RuntimeWarning``
    counts the pairs of neighbouring nodes of one sign between which the interpolant crosses
    zero (mid-edge points only: a wire through the centres of cells' faces is lost unwarned).
    A distance's interpolant does not cross zero across a sheet thinner than a cell (``(6 -
    8 t) / 16`` cells at mid-edge for a sheet ``t`` cells thick), so such a sheet in a
    distance (``from_mesh``, unions of ``sdf`` shapes) is lost unwarned: only a smooth ``phi``
    whose interpolant holds the sheet (a quadric) is warned of.
    ``|grad phi| = 1`` in the band, except at the medial axis. Not differentiable: the result
    is detached from ``phi``'s graph. About four times the cost of the triangles alone (97^3:
    2.9 s against 0.65 s).

    Args:
        phi: ``(B, 1, D, H, W)``, negative inside, positive outside, any scale; every batch
            entry must change sign.
        grid: the grid ``phi`` is sampled on.
        band_width: half-width of the band, world units (default ``5 * grid.spacing``).
            Flows evolve a 5-cell band where ``phi`` is a distance out to it and the ring
            beyond (:meth:`~torchsurf.ImplicitSurface.evolving_widths`): give ``7 *
            grid.spacing`` for that; the default gets the 3-cell band. Below
            :data:`NARROW_BAND_NODES` spacings, warned of.

    Returns:
        ``(B, 1, D, H, W)`` signed distance, world units, ``phi``'s dtype and device.

    Example:
        >>> grid = Grid.cube(33, bound=1.5)
        >>> ellipsoid = from_function(grid, lambda p: (p**2 / p.new_tensor([1.0, 0.6, 0.4])**2)
        ...                           .sum(-1) - 1)
        >>> redistance(ellipsoid, grid).shape
        torch.Size([1, 1, 33, 33, 33])
    """
    width = _band(grid, band_width)
    check_volume(phi, "phi", channels=1)
    check_spatial_shape(phi, "phi", grid.shape, "grid")
    check_finite(phi, "phi")
    entries = []
    for index, entry in enumerate(phi.detach().to("cpu", torch.float64).numpy()[:, 0]):
        try:
            if not (entry.min() < 0.0 < entry.max()):  # a plateau of zeros only touches 0
                raise ValueError(f"phi must change sign (negative inside, positive outside), "
                                 f"its range is [{entry.min():g}, {entry.max():g}]")
            entries.append(_isosurface.redistance(entry, grid, width))
        except ValueError as error:
            raise ValueError(f"phi batch entry {index}: {error}") from error
        missed = _isosurface.missed_crossings(entry)
        if missed:
            where = "" if phi.shape[0] == 1 else f" (batch entry {index})"
            pairs = "1 pair" if missed == 1 else f"{missed} pairs"
            warnings.warn(
                f"phi{where}: its interpolant crosses zero between {pairs} of neighbouring "
                "nodes of one sign: parts of S thinner than about a cell, or a phi that varies "
                "too fast between nodes for its interpolant (a distance cubed does). "
                "redistance sees S through the nodes' signs and leaves those crossings out (a "
                "sheet 0.8 cells thick had 35% of its area over half a cell off after it): "
                "sample phi on a finer grid",
                RuntimeWarning, stacklevel=caller_stacklevel(),
            )
    return torch.as_tensor(np.stack(entries)[:, None], dtype=phi.dtype, device=phi.device)
