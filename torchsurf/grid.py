"""The uniform Cartesian grid that volumes live on, and its coordinate conversions."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ._checks import check_positive, check_tensor


def _check_points(points: object, name: str) -> Tensor:
    points = check_tensor(points, name)
    if points.dim() == 0 or points.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3) (x, y, z), got {tuple(points.shape)}")
    return points


@dataclass(frozen=True)
class Grid:
    """A uniform grid of nodes with equal spacing along x, y and z.

    Node ``(k, j, i)`` of a volume ``(B, C, D, H, W)`` sits at the world position
    ``origin + spacing * (i, j, k)`` in ``(x, y, z)``: axis D is z, H is y, W is x.

    Args:
        shape: number of nodes ``(D, H, W)``, at least 3 along every axis.
        spacing: distance between neighbouring nodes, world units.
        origin: world position ``(x0, y0, z0)`` of node ``(0, 0, 0)``.

    Example:
        >>> grid = Grid.cube(33, bound=1.5)
        >>> grid.points().shape
        torch.Size([33, 33, 33, 3])
    """

    shape: tuple[int, int, int]
    spacing: float
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        shape = tuple(self.shape)
        if len(shape) != 3 or any(isinstance(n, bool) or int(n) != n or n < 3 for n in shape):
            raise ValueError(
                f"shape must be three whole sizes (D, H, W), each >= 3, got {self.shape!r}"
            )
        shape = tuple(int(n) for n in shape)
        origin = tuple(float(x) for x in self.origin)
        if len(origin) != 3:
            raise ValueError(f"origin must be three coordinates (x0, y0, z0), got {self.origin!r}")
        object.__setattr__(self, "shape", shape)
        object.__setattr__(self, "spacing", check_positive(self.spacing, "spacing"))
        object.__setattr__(self, "origin", origin)

    @classmethod
    def cube(cls, n: int, bound: float) -> Grid:
        """An ``n^3`` grid whose nodes span ``[-bound, bound]^3`` (spacing ``2 bound / (n - 1)``)."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 3:
            raise ValueError(f"n must be a whole number of nodes >= 3, got {n!r}")
        check_positive(bound, "bound")
        return cls(shape=(n, n, n), spacing=2.0 * bound / (n - 1), origin=(-bound,) * 3)

    @property
    def size(self) -> tuple[float, float, float]:
        """World extent ``(x, y, z)`` from the first node to the last."""
        depth, height, width = self.shape
        return tuple(self.spacing * (n - 1) for n in (width, height, depth))

    def points(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None
               ) -> Tensor:
        """World coordinates of every node.

        Returns:
            ``(D, H, W, 3)`` tensor of ``(x, y, z)``.
        """
        dtype = dtype or torch.get_default_dtype()
        axes = [
            self.origin[axis] + self.spacing * torch.arange(n, dtype=dtype, device=device)
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
        last = index.new_tensor([n - 1 for n in reversed(self.shape)])
        slack = tolerance + 8 * torch.finfo(index.dtype).eps * last
        return ((index >= -slack) & (index <= last + slack)).all(dim=-1)
