"""Signed distance functions of analytic shapes, sampled on a grid as ``phi`` volumes.

Every function returns ``phi`` of shape ``(1, 1, D, H, W)``: negative inside, positive outside,
``|grad phi| = 1`` (exact distances, except :func:`from_function`, which samples whatever it is
given).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from ._checks import check_positive
from .grid import Grid

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
    points = grid.points(dtype=dtype, device=device)
    values = function(points)
    if not isinstance(values, Tensor) or tuple(values.shape) != tuple(grid.shape):
        shape = tuple(values.shape) if isinstance(values, Tensor) else type(values).__name__
        raise ValueError(
            f"function must map points (D, H, W, 3) to a tensor (D, H, W) = {grid.shape}, "
            f"got {shape}"
        )
    return values[None, None]


def _centered(points: Tensor, center: Point) -> Tensor:
    if len(center) != 3:
        raise ValueError(f"center must be three coordinates (x, y, z), got {center!r}")
    return points - points.new_tensor(center)


def sphere(
    grid: Grid,
    radius: float = 1.0,
    center: Point = (0.0, 0.0, 0.0),
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Signed distance to the sphere ``|x - center| = radius``; ``(1, 1, D, H, W)``."""
    check_positive(radius, "radius")
    return from_function(
        grid, lambda p: _centered(p, center).norm(dim=-1) - radius, dtype=dtype, device=device
    )


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
    """
    check_positive(major_radius, "major_radius")
    check_positive(minor_radius, "minor_radius")

    def distance(points: Tensor) -> Tensor:
        local = _centered(points, center)
        ring = local[..., :2].norm(dim=-1) - major_radius
        return torch.sqrt(ring**2 + local[..., 2] ** 2) - minor_radius

    return from_function(grid, distance, dtype=dtype, device=device)


def box(
    grid: Grid,
    half_size: Point = (0.5, 0.5, 0.5),
    center: Point = (0.0, 0.0, 0.0),
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Signed distance to the axis-aligned box of half extents ``half_size`` ``(x, y, z)``."""
    if len(half_size) != 3:
        raise ValueError(f"half_size must be three lengths (x, y, z), got {half_size!r}")
    for length in half_size:
        check_positive(length, "half_size")

    def distance(points: Tensor) -> Tensor:
        excess = _centered(points, center).abs() - points.new_tensor(half_size)
        outside = excess.clamp(min=0).norm(dim=-1)
        inside = excess.max(dim=-1).values.clamp(max=0)
        return outside + inside

    return from_function(grid, distance, dtype=dtype, device=device)


def capsule(
    grid: Grid,
    start: Point = (0.0, 0.0, -0.5),
    end: Point = (0.0, 0.0, 0.5),
    radius: float = 0.4,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Signed distance to the capsule of ``radius`` around the segment ``start``–``end``."""
    check_positive(radius, "radius")
    if len(start) != 3 or len(end) != 3:
        raise ValueError(f"start and end must be points (x, y, z), got {start!r}, {end!r}")

    def distance(points: Tensor) -> Tensor:
        a = points.new_tensor(start)
        axis = points.new_tensor(end) - a
        length2 = torch.dot(axis, axis)
        if float(length2) == 0.0:
            raise ValueError("start and end must differ")
        t = (((points - a) @ axis) / length2).clamp(0.0, 1.0)
        return (points - a - t[..., None] * axis).norm(dim=-1) - radius

    return from_function(grid, distance, dtype=dtype, device=device)
