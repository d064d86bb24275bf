"""Level sets of sampled volumes as triangle meshes, and redistancing through them."""

from __future__ import annotations

import numpy as np
import torch
from scipy import ndimage
from skimage import measure

from . import _mesh_sdf
from .grid import Grid
from .sampling import sample

NODE_SNAP = 1e-9
"""A crossing closer than this fraction of its edge to a node is put on the node: where the
volume equals the level at a node only to rounding (a plane through nodes of a moved grid),
the crossings around it fell 1e-16 apart and left triangles of no area."""

LEVEL_SNAP = 1e-12
"""A node whose value differs from the level by less than this share of the volume's largest
difference from it (or than four units of the volume's rounding of the level) is taken to lie
on the level: a box's faces on node planes held ``+-1e-16`` in float64, and cells with three
such corners were cut diagonally (8% of the box's area lost; float32 rounded them to 0 and was
exact)."""

OFF_LEVEL = 1e-20
"""How far off the level a node on it is put, relative to the largest difference, when
marching cubes runs: every corner then lies strictly on one side and the cells close (the
crossings at that node are put on it afterwards, :data:`NODE_SNAP`); read as on the level,
marching cubes left one-triangle holes where the level passed through a node. Each connected
part of such nodes joins the side fewer of its neighbours lie strictly on (below on a tie):
the region whose faces it holds, so that a box whose faces hold the level keeps its edges
whichever side is its inside (put always below, ``-phi``'s box lost 12% of its area; always
above, ``phi``'s); a shape with concave edges too keeps one of the two kinds of edge."""

NEWTON_ITERATIONS = 40
"""Most iterations of the closest-point refinement. Its tangential move is scaled by the local
curvature (:data:`TANGENTIAL_SLOWEST`), so that it converges about quadratically where ``S`` is
smooth; unscaled, the rate was the distance times the curvature, and the iteration diverged
beyond a distance of one radius of curvature outside a convex part."""
TANGENTIAL_SLOWEST = 0.5
"""The tangential move is ``r_t / (1 + d kappa)`` (exact on a sphere), with the divisor at
least this: inside a convex part ``1 + d kappa`` falls to 0 at the medial axis."""
NEWTON_TOLERANCE = 1e-7
"""A point is settled once its last move is below this many cells."""
NEWTON_CHUNK = 2**17
"""Points refined together (memory of the sampler's taps and their gradients)."""
NEWTON_CYCLE = 0.05
"""A point whose steps keep this length or less, in cells, without settling alternates across a
face between two cells: the interpolant is only continuous there, its gradient jumps, and
the iteration crosses the face back and forth by a fixed step (a closest point on a node plane
through a sphere's centre: 0.0025 cells). The midpoint of its last two positions is kept."""
BAND_SLACK = 0.5
"""Cells beyond the band within which nodes are refined (and then clamped to the band)."""
NEWTON_STEP = 1.0
"""Longest step, in cells, of the closest-point refinement: a point asked to move further has
jumped towards another part of ``S`` (medial axis) and keeps the marching-cubes distance."""
NEWTON_REACH = 0.5
"""A refined distance further than this many cells from the marching-cubes one is not
trusted (medial axis, creases of ``phi``): that node keeps the marching-cubes distance."""


def level_set(volume: np.ndarray, grid: Grid, level: float = 0.0,
              mask: np.ndarray | None = None, epsilon: float | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes (scikit-image, Lewiner) of ``volume == level``.

    Args:
        volume: ``(D, H, W)`` samples at the nodes of ``grid``.
        grid: the grid.
        level: the iso-value.
        mask: ``(D, H, W)`` bool, the nodes that hold samples (cells with a node outside it
            are skipped), or ``None`` for all.
        epsilon: the machine epsilon of the dtype the samples were computed in (default
            ``volume``'s): values within four of its units of ``level`` lie on it.

    Returns:
        vertices ``(V, 3)`` float64 world ``(x, y, z)`` and faces ``(F, 3)`` int64, wound so
        that the normals point towards values above ``level`` (outward for ``phi``). No two
        vertices coincide and no face repeats a vertex, also where ``volume`` equals
        ``level`` at nodes (:func:`_merge_coincident`).

    Raises:
        ValueError: ``volume`` never crosses ``level``.
    """
    held = volume if mask is None else volume[mask]
    low, high = (held.min(), held.max()) if held.size else (np.nan, np.nan)

    def never(how: str = "") -> ValueError:
        known = "" if mask is None else " on the known nodes"
        return ValueError(f"phi never crosses the level {level:g}{how} (range [{low:g}, "
                          f"{high:g}]{known}): there is no surface to extract")

    if held.size == 0 or not (low <= level <= high) or low == high:
        raise never()
    if low == level or high == level:  # |x|: two sheets on the nodes where it touches
        raise never(", it only touches it at nodes")
    # scikit-image picks the crossed edges in float32: about the level and scaled to 1 in
    # float64 first (phi + 1e7 at level 1e7 gave half the sphere's radius off, phi * 1e100 an
    # IndexError, phi * 1e-46 no crossing); the crossings are solved again in float64 below
    shifted = volume.astype(np.float64) - level
    reach = np.abs(shifted if mask is None else shifted[mask]).max()
    scaled = shifted / reach
    # and within the volume's own rounding of the level (float32 -phi - 0.3 at level -0.3)
    if epsilon is None:
        epsilon = float(np.finfo(volume.dtype).eps) if volume.dtype.kind == "f" else 0.0
    rounding = 4 * epsilon * abs(level)
    on_level = np.abs(shifted) < LEVEL_SNAP * reach + rounding
    if on_level.any():
        scaled[on_level] = np.where(_fewer_above(scaled, on_level), OFF_LEVEL, -OFF_LEVEL)
    try:
        index, faces, _, _ = measure.marching_cubes(scaled, level=0.0,
                                                    gradient_direction="ascent", mask=mask)
    except (RuntimeError, ValueError) as error:  # no cell crosses: the level only touched
        # (also to within LEVEL_SNAP, where every node then lies on one side), or masked out
        raise never(" in any cell") from error
    snapped = np.where(on_level, level, volume)  # what marching cubes saw, in float64
    index, faces = _merge_coincident(_crossings_in_float64(snapped, index, level), faces)
    if len(faces) == 0:  # every triangle had no area: the level touched at nodes only
        raise never(", it only touches it at nodes")
    # scikit-image orders vertex coordinates like the array axes, (z, y, x).
    vertices = grid.spacing * index[:, ::-1] + np.asarray(grid.origin)
    return np.ascontiguousarray(vertices), np.ascontiguousarray(faces, dtype=np.int64)


def _fewer_above(scaled: np.ndarray, on_level: np.ndarray) -> np.ndarray:
    """For each node of ``on_level``: whether its connected part of ``on_level`` (26
    neighbours) has fewer neighbours strictly above the level (``scaled > 0`` off
    ``on_level``) than strictly below it, summed over the part. One side for a whole part:
    decided node by node, neighbouring nodes on the level took different sides where a
    concave edge met a face, and the crossings between them, on their nodes, joined four
    faces at an edge (a cross of three bars: 31 such edges)."""
    box = np.ones((3, 3, 3))
    above = ndimage.convolve((~on_level & (scaled > 0)).astype(np.int64), box, mode="constant")
    below = ndimage.convolve((~on_level & (scaled < 0)).astype(np.int64), box, mode="constant")
    parts, count = ndimage.label(on_level, structure=box)
    labels = parts[on_level]
    above_sum = np.bincount(labels, weights=above[on_level], minlength=count + 1)
    below_sum = np.bincount(labels, weights=below[on_level], minlength=count + 1)
    return (above_sum < below_sum)[labels]


def _crossings_in_float64(volume: np.ndarray, index: np.ndarray, level: float) -> np.ndarray:
    """Recompute marching-cubes vertices ``(V, 3)`` (array-axis order) in float64.

    scikit-image returns float32 positions; each vertex lies on a grid edge, so the edge is
    recovered from the position and the linear crossing is solved again from the volume. A
    position on a node (the crossing closer to it than float32 resolves, or ``volume == level``
    there) is that node exactly: its edge is not known, and every vertex there coincides; so
    is a crossing within :data:`NODE_SNAP` of a node.
    """
    rounded = np.rint(index)
    on_node = (index == rounded).all(axis=1)
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
    fraction[on_node] = 0.0
    fraction = np.clip(fraction, 0.0, 1.0)
    fraction[fraction < NODE_SNAP] = 0.0
    fraction[fraction > 1.0 - NODE_SNAP] = 1.0
    crossing = low.astype(np.float64)
    crossing[rows, axis] += fraction
    return crossing


def _merge_coincident(points: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``points`` ``(V, 3)`` at the same position made one, in order of first use, and
    the faces ``(F, 3)`` left with a repeated vertex dropped.

    Where the volume equals the level at a node, marching cubes puts a vertex on each crossing
    edge at that node, and the triangles between two of them have no area. Merging them and
    dropping those triangles keeps the winding of the others and closes the mesh as before:
    a dropped triangle ``(a, a, b)`` held both orientations of its one edge ``a b``.
    """
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    if len(first) == len(points):
        return points, faces
    order = np.argsort(first)
    renumber = np.empty_like(order)
    renumber[order] = np.arange(len(order))
    faces = renumber[inverse.reshape(-1)][faces]
    distinct = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) \
        & (faces[:, 2] != faces[:, 0])
    return points[first[order]], faces[distinct]


MISSED_DEPTH = 0.1
"""How far, in cells, :func:`missed_crossings` wants the interpolant past zero between two
nodes of one sign before it counts the pair: a surface grazing a grid line dips by rounding."""

MISSED_REACH = 100.0
"""How far from zero, in cells, the four values an edge's interpolant reads may lie for
:func:`missed_crossings` to count it: a sentinel value beyond the band (``-1e9``, ``1e3``)
swings the interpolant far past zero beside it, with no part of S there (a thin quadric sheet
reads values of tens of cells)."""


def missed_crossings(volume: np.ndarray) -> int:
    """Pairs of neighbouring nodes of one sign (along any axis) between which ``volume``'s
    tricubic interpolant (:func:`torchsurf.sampling.sample`, ``"cubic"``) crosses zero and goes
    more than :data:`MISSED_DEPTH` cells past it, the four nodes it reads within
    :data:`MISSED_REACH` cells of zero: parts of its zero set thinner than a cell, which the
    nodes' signs, and so marching cubes, do not see. Cells are measured by the volume's median
    difference across the edges S crosses. Only the middles of the grid's edges are read: a
    wire thinner than a cell through the centres of cells' faces is not counted."""
    steps, missed = [], []
    for axis in range(3):
        def along(start: int, stop: int | None, axis: int = axis) -> np.ndarray:
            index = [slice(None)] * 3
            index[axis] = slice(start, stop)
            return volume[tuple(index)]

        if volume.shape[axis] < 4:
            continue
        before, low, high, after = along(0, -3), along(1, -2), along(2, -1), along(3, None)
        middle = (9.0 * (low + high) - before - after) / 16.0  # the interpolant at mid-edge
        same = np.sign(low) == np.sign(high)
        steps.append(np.abs(high - low)[np.sign(low) * np.sign(high) < 0])
        farthest = np.maximum(np.maximum(np.abs(before), np.abs(low)),
                              np.maximum(np.abs(high), np.abs(after)))
        missed.append((same, middle, np.sign(low), farthest))
    crossing_steps = np.concatenate(steps) if steps else np.zeros(0)
    if len(crossing_steps) == 0:
        return 0
    cell = float(np.median(crossing_steps))
    return int(sum(np.count_nonzero(same & (middle * side < -MISSED_DEPTH * cell)
                                    & (farthest <= MISSED_REACH * cell))
                   for same, middle, side, farthest in missed))


def redistance(volume: np.ndarray, grid: Grid, band: float) -> np.ndarray:
    """Signed distance ``(D, H, W)`` to the zero set of ``volume``, exact within ``band``.

    The zero set is the marching-cubes surface of ``volume`` (linear interpolation along grid
    edges, so it passes through the same edge crossings as ``volume``); every node within
    ``band`` gets its exact distance to that surface, with the sign of ``volume``; the others
    get ``+-band``. The surface separates the nodes of opposite sign, so signs and distances
    agree.
    """
    vertices, faces = level_set(volume, grid, 0.0)
    # the facets lie inside convex parts of S: a node at the band's edge can be further from
    # them than from S
    found = _mesh_sdf.refine_band(vertices, faces, grid, band + BAND_SLACK * grid.spacing)
    distance = interpolant_distance(volume, grid, found.nodes, found.closest, found.distance)
    sign = np.sign(volume)
    near_sign = sign[found.nodes[:, 2], found.nodes[:, 1], found.nodes[:, 0]]
    near = near_sign * np.minimum(distance, band)
    return _mesh_sdf.to_volume(grid, found.nodes, near, sign * band)


def interpolant_distance(volume: np.ndarray, grid: Grid, nodes: np.ndarray, start: np.ndarray,
                         fallback: np.ndarray) -> np.ndarray:
    """Distances ``(N,)`` from ``nodes`` to the zero set of ``volume``'s tricubic interpolant.

    The marching-cubes surface is only ``O(h^2)`` close to the zero set and flat between its
    vertices: distances to it have Hessians of order one, so curvatures computed from them do
    not converge (47 % off on a sphere at every resolution). Starting from the closest points
    on it, each node's closest point ``y`` on ``p = 0`` (``p`` the interpolant of
    :func:`torchsurf.sampling.sample`, ``"cubic"``, ``O(h^4)``) is found by Newton's iteration
    on ``p(y) = 0`` and ``x - y`` parallel to ``grad p(y)`` (Chopp 2001): ``y += -p g / |g|^2
    + r_t / (1 + d kappa)``, ``r = x - y``, ``g = grad p(y)``, ``r_t = r - (r . g) g / |g|^2``
    its tangential part, ``d`` the signed distance and ``kappa`` the normal curvature of
    ``p = 0`` along ``r_t`` (from the interpolant's Hessian; without that factor the iteration
    overshot by ``d kappa`` and diverged beyond one radius of curvature outside a convex part:
    0.1 cells off around a sphere of radius 4 cells); a point alternating across a cell face by
    a short step keeps its last two positions' midpoint (:data:`NEWTON_CYCLE`). Where a step
    is longer than :data:`NEWTON_STEP` cells, or the point does not settle otherwise or lands
    more than :data:`NEWTON_REACH` cells from the marching-cubes distance, that ``fallback``
    distance is kept.

    Args:
        volume: ``(D, H, W)`` float64.
        nodes: ``(N, 3)`` node indices ``(i, j, k)`` along ``(x, y, z)``.
        start: ``(N, 3)`` world closest points on the marching-cubes surface.
        fallback: ``(N,)`` distances to it.
    """
    if len(nodes) > NEWTON_CHUNK:  # the cubic sampler's taps cost about 1.5 kB a point
        return np.concatenate([
            interpolant_distance(volume, grid, nodes[k:k + NEWTON_CHUNK],
                                 start[k:k + NEWTON_CHUNK], fallback[k:k + NEWTON_CHUNK])
            for k in range(0, len(nodes), NEWTON_CHUNK)
        ])
    if len(nodes) == 0:
        return fallback
    field = torch.from_numpy(np.ascontiguousarray(volume))[None, None]
    origin = torch.tensor(grid.origin, dtype=torch.float64)
    points = origin + grid.spacing * torch.from_numpy(nodes).to(torch.float64)
    closest = torch.from_numpy(start).clone()
    low, high = origin, origin + grid.spacing * (torch.tensor(grid.shape[::-1]) - 1)
    settled = torch.zeros(len(nodes), dtype=torch.bool)
    previous = closest.clone()
    last_move = torch.full((len(nodes),), float("inf"), dtype=torch.float64)
    active = torch.arange(len(nodes))
    for _ in range(NEWTON_ITERATIONS):
        at = closest[active].requires_grad_(True)
        offset = points[active] - at.detach()
        with torch.enable_grad():
            value = sample(field, at, grid, "cubic")[0, 0]
            (gradient,) = torch.autograd.grad(value.sum(), at, create_graph=True)
            squared = (gradient * gradient).sum(-1, keepdim=True).detach()
            tangential = offset - (offset * gradient.detach()).sum(-1, keepdim=True) \
                * gradient.detach() / squared
            length = tangential.norm(dim=-1, keepdim=True)
            direction = tangential / length.clamp(min=torch.finfo(torch.float64).tiny)
            (bending,) = torch.autograd.grad((gradient * direction).sum(), at)
        at, value, gradient = at.detach(), value.detach(), gradient.detach()
        # y moved by the whole tangential r overshoots by 1 + d kappa (kappa the normal
        # curvature of p = 0 along the move, d the signed distance): at d kappa >= 1 it diverged
        norm = squared.sqrt()
        curvature = (bending * direction).sum(-1, keepdim=True) / norm
        signed = (offset * gradient).sum(-1, keepdim=True) / norm
        overshoot = (1 + signed * curvature).clamp(min=TANGENTIAL_SLOWEST)
        step = tangential / overshoot - value[:, None] * gradient / squared
        moved = step.norm(dim=-1)
        usable = torch.isfinite(moved) & (moved <= NEWTON_STEP * grid.spacing)
        previous[active[usable]] = at[usable]
        last_move[active[usable]] = moved[usable]
        closest[active[usable]] = torch.minimum(torch.maximum(at[usable] + step[usable], low),
                                                high)
        done = usable & (moved <= NEWTON_TOLERANCE * grid.spacing)
        settled[active[done]] = True
        active = active[usable & ~done]  # a point that jumps is left to the fallback
        if len(active) == 0:
            break
    cycling = torch.zeros_like(settled)
    cycling[active] = last_move[active] <= NEWTON_CYCLE * grid.spacing
    closest[cycling] = 0.5 * (closest[cycling] + previous[cycling])
    settled |= cycling
    distance = (points - closest).norm(dim=-1).numpy()
    trusted = settled.numpy() & (np.abs(distance - fallback) <= NEWTON_REACH * grid.spacing)
    return np.where(trusted, distance, fallback)
