"""Trilinear sampling of volumes at world points (mesh vertices, probes)."""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from ._checks import check_batch, check_finite, check_tensor, check_volume
from .grid import Grid

# Points this many cells outside the grid's box are still accepted (and read the border), so
# that points on the boundary survive floating-point rounding.
_OUTSIDE_TOLERANCE = 1e-4


def sample(field: Tensor, points: Tensor, grid: Grid) -> Tensor:
    """Trilinear interpolation of ``field`` at world ``points``.

    Exact for fields linear in ``(x, y, z)``; differentiable with respect to ``field`` and
    ``points`` (``torch.nn.functional.grid_sample`` with ``align_corners=True``, so the first
    and last nodes sit exactly at the grid's box).

    Args:
        field: ``(B, C, D, H, W)`` values at the nodes of ``grid``.
        points: ``(V, 3)`` or ``(B, V, 3)`` world ``(x, y, z)``, inside the grid's box; same
            dtype and device as ``field``. A batch of 1 on either side broadcasts.
        grid: the grid ``field`` is sampled on.

    Returns:
        ``(B, C, V)``.

    Raises:
        ValueError: a point lies outside the grid's box (by more than 1e-4 of a cell).

    Example:
        >>> import torch
        >>> grid = Grid.cube(5, bound=1.0)
        >>> x = grid.points()[..., 0][None, None]            # the field u = x
        >>> sample(x, torch.tensor([[0.3, -0.2, 0.1]]), grid)
        tensor([[[0.3000]]])
    """
    if not isinstance(grid, Grid):
        raise TypeError(f"grid must be a torchsurf.Grid, got {type(grid).__name__}")
    check_volume(field, "field")
    check_tensor(points, "points")
    if tuple(field.shape[-3:]) != grid.shape:
        raise ValueError(
            f"field has spatial shape {tuple(field.shape[-3:])} but grid has {grid.shape}; "
            "they must agree"
        )
    if points.dim() not in (2, 3) or points.shape[-1] != 3:
        raise ValueError(
            f"points must have shape (V, 3) or (B, V, 3), got {tuple(points.shape)}"
        )
    if points.dtype != field.dtype or points.device != field.device:
        raise TypeError(
            f"points ({points.dtype}, {points.device}) must have the dtype and device of "
            f"field ({field.dtype}, {field.device})"
        )
    check_finite(points, "points")
    _check_inside(points, grid)
    if points.dim() == 2:
        points = points[None]
    check_batch(points, "points", field.shape[0], "field")
    batch = max(field.shape[0], points.shape[0])
    normalized = grid.world_to_normalized(points).expand(batch, -1, -1)
    values = F.grid_sample(
        field.expand(batch, -1, -1, -1, -1),
        normalized[:, :, None, None, :],
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )
    return values[:, :, :, 0, 0]


def _check_inside(points: Tensor, grid: Grid) -> None:
    outside = ~grid.contains(points.detach(), tolerance=_OUTSIDE_TOLERANCE)
    if bool(outside.any()):
        first = tuple(int(i) for i in outside.nonzero()[0])
        low = grid.origin
        high = tuple(o + s for o, s in zip(grid.origin, grid.size, strict=True))
        raise ValueError(
            f"points: {int(outside.sum())} of {outside.numel()} points lie outside the grid's "
            f"box {low} to {high}, e.g. points[{', '.join(map(str, first))}] = "
            f"{points[first].tolist()}"
        )
