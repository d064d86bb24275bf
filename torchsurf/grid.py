"""The uniform Cartesian grid that volumes live on, and its coordinate conversions."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from ._checks import (
    as_float,
    check_count,
    check_device,
    check_dtype,
    check_positive,
    check_real,
    check_tensor,
    check_triple,
)

__all__ = [
    "Grid",
    "MIN_MARGIN_CELLS",
    "default_margin",
]


def _check_points(points: object, name: str) -> Tensor:
    points = check_tensor(points, name)
    if points.dim() == 0 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3) (x, y, z), got {tuple(points.shape)}")
    return points


def _check_tolerance(tolerance: object) -> float:
    """``tolerance`` of :meth:`Grid.contains`: a finite number of cells (negative: a box
    shrunk by that many cells)."""
    number = as_float(tolerance, "tolerance", "a finite number of cells")  # numpy, 0-d too
    if not math.isfinite(number):
        raise ValueError(f"tolerance must be a finite number of cells, got {tolerance!r}")
    return number


def _size(value: object, name: str) -> int:
    """One size of ``shape``: a whole number >= 3 (integral floats such as ``17.0`` too)."""
    return check_count(value, name, minimum=3)


MIN_MARGIN_CELLS = 3.0
"""Free cells a fitted grid leaves, by default, on each side of a shape's box: the
stencils read a node beyond the band, and :class:`~torchsurf.ImplicitSurface` warns when ``S``
comes within two cells of the grid's faces. The 3-cell band then reaches to about a cell from
the faces, where the stencils read the face layer's extrapolated ``phi``, so results there
depend a little on the box: the same ``phi`` and nodes in a box 6 cells wider a side moved
flows on spot's ``from_mesh`` at 32^3 by up to 1e-6 (heat, RKC), 6e-6 (total variation), 1.4e-5
(Perona–Malik) and 7e-4 (harmonic map, p = 2, 3 h^2) (an audit, 2026-12-06); give a wider
``margin`` where that matters."""


def default_margin(resolution: int, fraction: float, min_cells: float = MIN_MARGIN_CELLS
                   ) -> float:
    """The margin of a cubic grid fitted to a shape: ``fraction`` of the shape's longest side,
    widened where that leaves fewer than ``min_cells`` cells on each side.

    A margin ``m`` (fraction of the longest side) on a ``resolution``-node grid leaves
    ``m (resolution - 1) / (1 + 2 m)`` cells; ``fraction = 0.1`` leaves three from 37 nodes up.
    Grids of fewer than ``4 min_cells + 1`` nodes keep a quarter of their cells free on each
    side.

    Args:
        resolution: nodes per axis, at least 3.
        fraction: the margin wanted, fraction of the longest side.
        min_cells: the fewest free cells on each side.

    Returns:
        The margin, fraction of the longest side, at least ``fraction``.
    """
    cells = min(min_cells, (resolution - 1) / 4)
    return max(fraction, cells / (resolution - 1 - 2 * cells))


@dataclass(frozen=True)
class Grid:
    """A uniform grid of nodes with equal spacing along x, y and z.

    Node ``(k, j, i)`` of a volume ``(B, C, D, H, W)`` sits at the world position
    ``origin + spacing * (i, j, k)`` in ``(x, y, z)``: axis D is z, H is y, W is x.

    Args:
        shape: number of nodes ``(D, H, W)``, whole numbers, at least 3 along every axis.
        spacing: distance between neighbouring nodes, world units; finite and > 0.
        origin: world position ``(x0, y0, z0)`` of node ``(0, 0, 0)``; finite.

    Numbers may be Python, numpy or 0-d tensors; bools are refused.

    Example:
        >>> grid = Grid.cube(33, bound=1.5)
        >>> grid.points().shape
        torch.Size([33, 33, 33, 3])
    """

    shape: tuple[int, int, int]
    spacing: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "shape", check_triple(self.shape, "shape", _size))
        object.__setattr__(self, "spacing", check_positive(self.spacing, "spacing"))
        object.__setattr__(self, "origin", check_triple(self.origin, "origin", check_real))

    @classmethod
    def cube(cls, n: int, bound: float) -> Grid:
        """An ``n^3`` grid whose nodes span ``[-bound, bound]^3`` (spacing ``2 bound / (n - 1)``).

        ``n`` is a whole number >= 3 (Python, numpy or a 0-d integer tensor) and ``bound`` a
        finite positive number.
        """
        n = check_count(n, "n", minimum=3)
        bound = check_positive(bound, "bound")
        return cls(shape=(n, n, n), spacing=2.0 * bound / (n - 1), origin=(-bound,) * 3)

    @property
    def size(self) -> tuple[float, float, float]:
        """World extent ``(x, y, z)`` from the first node to the last."""
        depth, height, width = self.shape
        return tuple(self.spacing * (n - 1) for n in (width, height, depth))

    def points(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None,
               relative_to: Sequence[float] | None = None) -> Tensor:
        """World coordinates of every node.

        Args:
            dtype: ``torch.float32`` or ``torch.float64`` (default: the default dtype).
            device: where to put them (default CPU).
            relative_to: a point ``(x, y, z)``: the coordinates are ``x - relative_to``,
                computed in float64 before the cast to ``dtype``, so that a grid far from the
                origin keeps float32's relative precision in the differences (a sphere
                centred at x = 1000: 4e-5 error in float32 subtracting afterwards, 1e-8 here).

        Returns:
            ``(D, H, W, 3)`` tensor of ``(x, y, z)``.
        """
        dtype = check_dtype(dtype)
        device = check_device(device)
        if relative_to is None:
            relative_to = (0.0, 0.0, 0.0)
        if len(relative_to) != 3:
            raise ValueError(f"relative_to must be a point (x, y, z), got {relative_to!r}")
        axes = [
            ((self.origin[axis] - float(relative_to[axis]))
             + self.spacing * torch.arange(n, dtype=torch.float64, device=device)).to(dtype)
            for axis, n in enumerate(reversed(self.shape))
        ]
        z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
        return torch.stack((x, y, z), dim=-1)

    def world_to_index(self, points: Tensor) -> Tensor:
        """World ``(..., 3)`` ``(x, y, z)`` to continuous node indices ``(..., 3)`` ``(i, j, k)``."""
        points = _check_points(points, "points")
        origin = points.new_tensor(self.origin)
        return (points - origin) / self.spacing

    def index_to_world(self, index: Tensor) -> Tensor:
        """Continuous node indices ``(..., 3)`` ``(i, j, k)`` to world ``(..., 3)`` ``(x, y, z)``."""
        index = _check_points(index, "index")
        return index * self.spacing + index.new_tensor(self.origin)

    def world_to_normalized(self, points: Tensor) -> Tensor:
        """World ``(..., 3)`` to the ``[-1, 1]`` coordinates of ``grid_sample(align_corners=True)``.

        The first node maps to -1 and the last to +1 along each axis; the order stays
        ``(x, y, z)``, which is the order ``torch.nn.functional.grid_sample`` reads.
        """
        index = self.world_to_index(points)
        last = index.new_tensor([n - 1 for n in reversed(self.shape)])
        return 2.0 * index / last - 1.0

    def normalized_to_world(self, normalized: Tensor) -> Tensor:
        """Inverse of :meth:`world_to_normalized`."""
        normalized = _check_points(normalized, "normalized")
        last = normalized.new_tensor([n - 1 for n in reversed(self.shape)])
        return self.index_to_world((normalized + 1.0) * 0.5 * last)

    def contains(self, points: Tensor, tolerance: float = 0.0) -> Tensor:
        """Boolean ``(...)``: whether each world point ``(..., 3)`` lies inside the grid's box.

        Points on the box's faces count as inside, with a slack of a few rounding errors of
        the index computation (so that every node of the grid is contained) plus
        ``tolerance`` grid cells.
        """
        index = self.world_to_index(points)
        return self.contains_index(index, _check_tolerance(tolerance)
                                   + self.world_rounding(index.dtype))

    def world_rounding(self, dtype: torch.dtype) -> float:
        """Cells by which the index of a world point in ``dtype`` may be off through rounding
        at its world coordinate's scale: the point's and the origin's rounding, half a unit
        in the last place each, taken twice. Far from the origin in float32 that is 1.8e-3
        cells at 1000.5 and spacing 0.13 (2.4e-4 measured), 2.4 cells at 1e5 and spacing 0.01
        (0.39 measured: float32 cannot place a point there more finely)."""
        farthest = max(abs(x) for x in (*self.origin, *(o + s for o, s in
                                                           zip(self.origin, self.size, strict=True))))
        return 2 * torch.finfo(dtype).eps * farthest / self.spacing

    def contains_index(self, index: Tensor, tolerance: float = 0.0) -> Tensor:
        """:meth:`contains` for continuous node indices ``(..., 3)`` ``(i, j, k)`` (integer
        indices too); ``tolerance`` in cells (negative: the box shrunk by as many)."""
        if not isinstance(index, Tensor):
            raise TypeError(f"index must be a torch.Tensor, got {type(index).__name__}")
        if index.dim() == 0 or index.shape[-1] != 3:
            raise ValueError(f"index must have shape (..., 3) (i, j, k), got "
                             f"{tuple(index.shape)}")
        tolerance = _check_tolerance(tolerance)
        if not index.is_floating_point():
            index = index.to(torch.float64)
        last = index.new_tensor([n - 1 for n in reversed(self.shape)])
        slack = tolerance + 8 * torch.finfo(index.dtype).eps * last
        return ((index >= -slack) & (index <= last + slack)).all(dim=-1)
