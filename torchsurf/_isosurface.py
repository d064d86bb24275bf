"""Level sets of sampled volumes as triangle meshes, and redistancing through them."""

from __future__ import annotations

import numpy as np
from skimage import measure

from . import _mesh_sdf
from .grid import Grid


def level_set(volume: np.ndarray, grid: Grid, level: float = 0.0,
              mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes (scikit-image, Lewiner) of ``volume == level``.

    Args:
        volume: ``(D, H, W)`` samples at the nodes of ``grid``.
        grid: the grid.
        level: the iso-value.
        mask: ``(D, H, W)`` bool, the nodes that hold samples (cells with a node outside it
            are skipped), or ``None`` for all.

    Returns:
        vertices ``(V, 3)`` float64 world ``(x, y, z)`` and faces ``(F, 3)`` int64, wound so
        that the normals point towards values above ``level`` (outward for ``phi``).

    Raises:
        ValueError: ``volume`` never crosses ``level``.
    """
    held = volume if mask is None else volume[mask]
    if held.size == 0 or not (held.min() <= level <= held.max()) or held.min() == held.max():
        low, high = (held.min(), held.max()) if held.size else (np.nan, np.nan)
        raise ValueError(
            f"phi never crosses the level {level:g} (range [{low:g}, {high:g}]): there is no "
            "surface to extract"
        )
    index, faces, _, _ = measure.marching_cubes(volume, level=level, gradient_direction="ascent",
                                                mask=mask)
    index = _crossings_in_float64(volume, index, level)
    # scikit-image orders vertex coordinates like the array axes, (z, y, x).
    vertices = grid.spacing * index[:, ::-1] + np.asarray(grid.origin)
    return np.ascontiguousarray(vertices), np.ascontiguousarray(faces, dtype=np.int64)


def _crossings_in_float64(volume: np.ndarray, index: np.ndarray, level: float) -> np.ndarray:
    """Recompute marching-cubes vertices ``(V, 3)`` (array-axis order) in float64.

    scikit-image returns float32 positions; each vertex lies on a grid edge, so the edge is
    recovered from the position and the linear crossing is solved again from the volume.
    """
    rounded = np.rint(index)
    axis = np.abs(index - rounded).argmax(axis=1)
    rows = np.arange(len(index))
    low = rounded.astype(np.int64)
    low[rows, axis] = np.floor(index[rows, axis]).astype(np.int64)
    high = low.copy()
    high[rows, axis] = np.minimum(high[rows, axis] + 1, np.array(volume.shape)[axis] - 1)
    below = volume[low[:, 0], low[:, 1], low[:, 2]]
    above = volume[high[:, 0], high[:, 1], high[:, 2]]
    step = above - below
    fraction = np.where(step != 0, (level - below) / np.where(step != 0, step, 1.0), 0.0)
    crossing = low.astype(np.float64)
    crossing[rows, axis] += np.clip(fraction, 0.0, 1.0)
    return crossing


def redistance(volume: np.ndarray, grid: Grid, band: float) -> np.ndarray:
    """Signed distance ``(D, H, W)`` to the zero set of ``volume``, exact within ``band``.

    The zero set is the marching-cubes surface of ``volume`` (linear interpolation along grid
    edges, so it passes through the same edge crossings as ``volume``); every node within
    ``band`` gets its exact distance to that surface, with the sign of ``volume``; the others
    get ``+-band``. The surface separates the nodes of opposite sign, so signs and distances
    agree.
    """
    vertices, faces = level_set(volume, grid, 0.0)
    found = _mesh_sdf.refine_band(vertices, faces, grid, band)
    sign = np.sign(volume)
    near_sign = sign[found.nodes[:, 2], found.nodes[:, 1], found.nodes[:, 0]]
    near = near_sign * np.minimum(found.distance, band)
    return _mesh_sdf.to_volume(grid, found.nodes, near, sign * band)
