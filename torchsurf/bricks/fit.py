"""Several meshes, each at its own resolution, on grids of one spacing: what a brick batch needs.

Bricks of one batch share the spacing (:class:`~torchsurf.bricks.BrickLayout`), while meshes
come in units of their own (the shared bunny spans 0.16, the teapot 6.4). :func:`fit_grids`
moves mesh ``b`` to batch coordinates ``x' = scale_b (x - centre_b)``, in which its bounding
box is centred at the origin and its longest side spans ``resolutions[b] - 1 - 2 margin`` cells
of the common spacing, and gives it a cubic grid of ``resolutions[b]`` nodes around it. Each
shape is then resolved as on its own grid of that resolution (:meth:`FittedMeshes.own_grid`:
the same nodes in the shape's units), and distances scale by ``scale_b``: a diffusion time
``t'`` in batch coordinates is ``t' / scale_b^2`` in the shape's units
(:meth:`FittedMeshes.shape_time`), the same number of cells squared for every shape.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import Tensor

from .._checks import check_count, check_entry, check_nonnegative, check_positive
from .._mesh_input import MeshLike, as_trimesh, is_array_pair, triangle_arrays
from ..grid import Grid

MARGIN_CELLS = 6.0
"""Default free cells between each shape's box and its grid's faces: the default band of 3
cells and the 2 nodes its stencils read need 5 (:func:`torchsurf.bricks.from_mesh` refuses
less), one more absorbs a closest point just outside the box."""


@dataclass(frozen=True)
class FittedMeshes:
    """Meshes in batch coordinates with their grids (:func:`fit_grids`).

    Attributes:
        meshes: the meshes moved to batch coordinates ``x' = scale_b (x - centre_b)``.
        grids: one cubic grid per mesh, all with :attr:`spacing`, centred at the origin.
        scale: ``(B,)`` float64, the factor from a shape's own units to batch units.
        centre: ``(B, 3)`` float64, each shape's box centre ``(x, y, z)`` in its own units.
    """

    meshes: tuple[trimesh.Trimesh, ...]
    grids: tuple[Grid, ...]
    scale: Tensor
    centre: Tensor

    def __len__(self) -> int:
        return len(self.meshes)

    @property
    def spacing(self) -> float:
        """The common spacing ``h``, batch units."""
        return self.grids[0].spacing

    def own_grid(self, entry: int) -> Grid:
        """The grid of shape ``entry`` in its own units: the same nodes as ``grids[entry]``."""
        entry = check_entry(entry, len(self))
        scale = float(self.scale[entry])
        grid = self.grids[entry]
        origin = tuple(float(c) + o / scale for c, o in zip(self.centre[entry], grid.origin,
                                                            strict=True))
        return Grid(grid.shape, grid.spacing / scale, origin)

    def to_shape(self, points: Tensor, entry: int) -> Tensor:
        """Batch coordinates ``(..., 3)`` of shape ``entry`` in its own units ``(..., 3)``."""
        entry = check_entry(entry, len(self))
        centre = self.centre[entry].to(dtype=points.dtype, device=points.device)
        return points / float(self.scale[entry]) + centre

    def shape_time(self, time: float) -> Tensor:
        """A diffusion time in batch units, in every shape's own units: ``time / scale_b^2``,
        ``(B,)`` float64 (a heat or Perona–Malik time is a length squared; a total-variation
        time is a length, ``time / scale_b``, and a contrast or ``eps`` converts as ``u`` per
        length: docs/bricks.md)."""
        return check_nonnegative(time, "time") / self.scale**2


def fit_grids(meshes: Sequence[MeshLike], resolutions: int | Sequence[int],
              margin: float = MARGIN_CELLS, spacing: float | None = None) -> FittedMeshes:
    """Each mesh moved and scaled so that its own cubic grid of ``resolutions[b]`` nodes has
    the common ``spacing``; what :func:`torchsurf.bricks.from_mesh` batches.

    Args:
        meshes: a sequence of meshes (as in :func:`torchsurf.mesh.load`).
        resolutions: nodes along each axis of each mesh's grid (one number for all, or one per
            mesh), each at least ``2 margin + 2``.
        margin: free cells on each side of a mesh's box (default :data:`MARGIN_CELLS`): its
            longest side spans ``resolutions[b] - 1 - 2 margin`` cells.
        spacing: the common spacing, batch units (default ``1 / (max(resolutions) - 1)``: the
            largest grid spans ``[-0.5, 0.5]^3``).

    Returns:
        The :class:`FittedMeshes`.

    Example:
        >>> import trimesh
        >>> fitted = fit_grids([trimesh.creation.icosphere(), trimesh.creation.box()], [40, 24])
        >>> [g.shape[0] for g in fitted.grids], fitted.grids[0].spacing == fitted.grids[1].spacing
        ([40, 24], True)
    """
    if isinstance(meshes, (str, trimesh.Trimesh)) or not isinstance(meshes, Sequence):
        raise TypeError(f"meshes must be a sequence of meshes, got {type(meshes).__name__}")
    if is_array_pair(meshes):
        raise TypeError("meshes is one pair (vertices, faces), read as two meshes: give a "
                        "sequence of meshes, [(vertices, faces)] for one mesh")
    if isinstance(resolutions, (np.ndarray, torch.Tensor)) and resolutions.ndim == 1:
        resolutions = resolutions.tolist()
    if len(meshes) == 0:
        raise ValueError("meshes must hold at least one mesh, got an empty sequence")
    if isinstance(resolutions, Sequence):
        if len(resolutions) != len(meshes):
            raise ValueError(f"resolutions must hold one number per mesh ({len(meshes)}), got "
                             f"{len(resolutions)}")
        counts = [check_count(n, f"resolutions[{b}]", minimum=3)
                  for b, n in enumerate(resolutions)]
    else:
        counts = [check_count(resolutions, "resolutions", minimum=3)] * len(meshes)
    margin = check_nonnegative(margin, "margin")
    spacing = (1.0 / (max(counts) - 1) if spacing is None
               else check_positive(spacing, "spacing"))
    moved, grids, scales, centres = [], [], [], []
    for b, (mesh, count) in enumerate(zip(meshes, counts, strict=True)):
        cells = count - 1 - 2.0 * margin
        if cells <= 0:
            raise ValueError(
                f"resolutions[{b}] = {count} leaves no cells for the mesh inside a margin of "
                f"{margin:g} cells on each side: use more than {2 * margin + 1:g} nodes"
            )
        vertices, faces = triangle_arrays(as_trimesh(mesh, f"meshes[{b}]"))
        used = vertices[np.unique(faces)]
        low, high = used.min(axis=0), used.max(axis=0)
        longest = float((high - low).max())
        if longest == 0:
            raise ValueError(f"meshes[{b}]: all its vertices coincide, there is no box to fit")
        scale, centre = cells * spacing / longest, (low + high) / 2
        moved.append(trimesh.Trimesh(scale * (vertices - centre), faces, process=False))
        grids.append(Grid((count,) * 3, spacing, (-0.5 * (count - 1) * spacing,) * 3))
        scales.append(scale)
        centres.append(centre)
    return FittedMeshes(tuple(moved), tuple(grids), torch.tensor(scales, dtype=torch.float64),
                        torch.as_tensor(np.stack(centres), dtype=torch.float64))
