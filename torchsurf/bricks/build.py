"""Brick surfaces from dense ``phi`` or straight from triangle meshes."""

from __future__ import annotations

import math
from collections.abc import Sequence
from contextlib import nullcontext

import numpy as np
import torch
from torch import Tensor

from .. import _memory, _mesh_sdf
from .._checks import MismatchError, check_choice, check_device, check_dtype, check_positive
from .._inference import outside_inference
from .._mesh_input import MeshLike, as_trimesh, is_array_pair, triangle_arrays
from ..grid import Grid
from ..surface import ImplicitSurface
from .layout import BRICK, BrickLayout, bricks_of_mask
from .surface import STENCIL_REACH, BrickSurface

REACH_CELLS = STENCIL_REACH
"""Nodes stored beyond the band along each axis (:data:`~torchsurf.bricks.surface.STENCIL_REACH`)."""

EXACT_REACH = 3.5
"""Cells beyond the band within which :func:`from_mesh` computes exact distances: every node
within two nodes of a band node along each axis lies within ``2 sqrt(3) h`` of it."""


def _grown(mask: Tensor, cells: int) -> Tensor:
    """``(D, H, W)`` bool dilated by ``cells`` nodes along every axis (a cube)."""
    grown = mask[None, None].float()
    grown = torch.nn.functional.max_pool3d(grown, 2 * cells + 1, stride=1, padding=cells)
    return grown[0, 0] > 0


def from_dense(phi: Tensor | ImplicitSurface, grid: Grid | None = None,
               band_width: float | None = None, eps: float = 1e-6,
               flow_band: bool = True) -> BrickSurface:
    """The bricks of a dense ``phi`` that hold its band and every node the band's stencils read.

    The small-case route (and the reference the band path is tested against): it builds the
    dense :class:`~torchsurf.ImplicitSurface` to find the band. Large grids should come
    from :func:`from_mesh`, which never forms the dense volume.

    Args:
        phi: ``(B, 1, D, H, W)`` on ``grid``, or an :class:`~torchsurf.ImplicitSurface` (whose
            grid, band width and ``eps`` are then used).
        grid: the grid of ``phi`` (not with a surface).
        band_width: half-width of the band, world units (default ``3 * grid.spacing``).
        eps: as in :class:`~torchsurf.ImplicitSurface`.
        flow_band: also store the band flows evolve on the dense surface
            (:meth:`~torchsurf.ImplicitSurface.evolving_widths`: 5 cells where ``phi`` is a
            distance out to them, as an analytic distance is), so that flows on the bricks
            evolve it too and equal the dense flows; 1.1-1.5x the bricks of the 3-cell
            band, as the shape sits on the bricks (spheres of 8-20 cells' radius at six
            offsets each; 1.74 measured at 49^3). An entry whose
            wider band would come within :data:`REACH_CELLS` nodes of its box's faces keeps
            its surface's band. ``False``: the surface's band only.

    Returns:
        A :class:`BrickSurface` whose band, and fields on it, equal the dense surface's.
    """
    if isinstance(phi, ImplicitSurface):
        if grid is not None:
            raise ValueError("grid must be None when phi is an ImplicitSurface (it has its own)")
        dense = phi
    else:
        if grid is None:
            raise TypeError("from_dense(phi, grid): grid is required with a phi tensor")
        dense = ImplicitSurface(phi, grid, band_width, eps)
    band = dense.band_mask()
    for b in range(dense.batch_size):
        check_clear_of_faces(band[b, 0].nonzero(), dense.grid, b)
    widths = list(dense.evolving_widths()) if flow_band else [dense.band_width] * dense.batch_size
    bands = {width: dense.band_mask(width) for width in set(widths) - {dense.band_width}}
    bands[dense.band_width] = band
    for b, width in enumerate(widths):  # bricks have no faces: a wider band must stay clear
        if _clearance(bands[width][b, 0].nonzero(), dense.grid) < REACH_CELLS:
            widths[b] = dense.band_width
    masks = [_grown(bands[width][b, 0], REACH_CELLS) for b, width in enumerate(widths)]
    grids = [dense.grid] * dense.batch_size
    layout = bricks_of_mask(masks, grids)
    # a phi that requires grad stays in the bricks' graph under no_grad or inference_mode,
    # as a dense surface's geometry does (ImplicitSurface._assemble_kept)
    with outside_inference(), torch.enable_grad() if dense.phi.requires_grad else nullcontext():
        packed = layout.from_dense(dense.phi, fill="quadratic")
    return BrickSurface(packed, layout, dense.band_width, dense.eps, widths)


def from_mesh(meshes: MeshLike | Sequence[MeshLike], grids: Grid | Sequence[Grid],
              band_width: float | None = None, dtype: torch.dtype | None = None,
              sign: str = "auto") -> BrickSurface:
    """Signed distance bricks of one or several meshes, built without any dense volume.

    Each mesh gets its own grid (all with one spacing); only the bricks within
    ``band_width + 3.5 h`` of a mesh are visited and stored (exact distances from libigl's AABB
    tree, signs as in :func:`torchsurf.sdf.from_mesh`). Nodes of stored bricks farther than
    that hold ``+-(band_width + 3.5 h)``.

    Args:
        meshes: a mesh (``trimesh.Trimesh``, path, or ``(vertices, faces)``) or a sequence.
        grids: a :class:`~torchsurf.Grid` per mesh (or one for a single mesh).
        band_width: half-width of the surface's band, world units (default ``3 h``).
        dtype: of ``phi`` (default: the default dtype).
        sign: ``"auto"``, ``"winding"`` or ``"pseudonormal"`` (:func:`torchsurf.sdf.from_mesh`).

    Returns:
        A :class:`BrickSurface` with one batch entry per mesh.

    Example:
        >>> import trimesh
        >>> from torchsurf import Grid, bricks
        >>> grid = Grid.cube(64, bound=1.5)
        >>> surface = bricks.from_mesh(trimesh.creation.icosphere(subdivisions=3), grid)
        >>> surface.phi.shape[1:]
        torch.Size([1, 8, 8, 8])
    """
    meshes, grids = mesh_list(meshes, grids)
    check_choice(sign, "sign", _mesh_sdf.SIGN_METHODS)
    spacing = grids[0].spacing
    width = check_positive(3.0 * spacing if band_width is None else band_width, "band_width")
    surface, _ = signed_bricks(meshes, grids, width, width + EXACT_REACH * spacing, dtype, sign)
    return surface


def mesh_list(meshes: MeshLike | Sequence[MeshLike], grids: Grid | Sequence[Grid]
              ) -> tuple[list[MeshLike], list[Grid]]:
    """``meshes`` and ``grids`` as two lists of one entry per mesh; raises unless they pair up."""
    if not isinstance(meshes, (list, tuple)) or is_array_pair(meshes):
        meshes = [meshes]
    if isinstance(grids, Grid):
        grids = [grids]
    try:
        grids = list(grids)
    except TypeError:
        grids = [grids]
    for b, grid in enumerate(grids):
        if not isinstance(grid, Grid):
            raise TypeError(f"grids must be a torchsurf.Grid or a sequence of one per mesh; "
                            f"entry {b} is {type(grid).__name__}: {grid!r}")
    if len(meshes) == 0:
        raise ValueError("meshes must hold at least one mesh, got none")
    if len(grids) != len(meshes):
        raise ValueError(f"grids must hold one Grid per mesh ({len(meshes)}), got {len(grids)}")
    return list(meshes), grids


MeshBand = tuple[np.ndarray, np.ndarray, _mesh_sdf.SignedBand]
"""A mesh's float64 vertices ``(V, 3)``, int64 faces ``(F, 3)`` and its signed band."""


def signed_bricks(meshes: list[MeshLike], grids: list[Grid], band_width: float, reach: float,
                  dtype: torch.dtype | None, sign: str,
                  device: torch.device | str | None = None
                  ) -> tuple[BrickSurface, list[MeshBand]]:
    """:func:`from_mesh` with exact distances within ``reach`` (at least ``band_width + 3.5 h``),
    on ``device``, returning each mesh's arrays and signed band too (its nodes' closest points
    on the mesh)."""
    dtype = check_dtype(dtype)
    device = check_device(device)
    numpy_dtype = torch.empty(0, dtype=dtype).numpy().dtype
    loaded = [as_trimesh(mesh, f"meshes[{b}]") for b, mesh in enumerate(meshes)]
    arrays = [triangle_arrays(mesh) for mesh in loaded]
    # before the distances: a mesh far larger than the grid's cells ran for minutes, then
    # failed allocating 30 GiB
    area = sum(float(mesh.area) for mesh in loaded)
    _memory.check_fits(_memory.mesh_band_bytes(grids[0].spacing, reach, area),
                       f"bricks of {len(arrays)} mesh(es) of total area {area:.4g} at spacing "
                       f"{grids[0].spacing:.4g}")
    coords, batch, values, bands = [], [], [], []
    for b, ((vertices, faces), grid) in enumerate(zip(arrays, grids, strict=True)):
        signed = _mesh_sdf.signed_near(vertices, faces, grid, reach, sign)
        in_band = np.abs(signed.near) <= band_width
        check_clear_of_faces(torch.from_numpy(signed.band.nodes[in_band][:, ::-1].copy()), grid, b)
        entry_coords, entry_values = _brick_values(signed, grid, reach, numpy_dtype)
        # the nodes' own signs, not the bricks' fill (+reach beyond it): a grid inside the
        # mesh passed on the fill and failed later, naming no mesh
        signs = np.concatenate([signed.near, *(np.where(inside, -1.0, 1.0)
                                               for inside in signed.far_inside)])
        _mesh_sdf.check_sides(signs, vertices, faces, grid, f"meshes[{b}]")
        coords.append(entry_coords)
        batch.append(np.full(len(entry_coords), b))
        values.append(entry_values)
        bands.append((vertices, faces, signed))
    layout = BrickLayout(torch.from_numpy(np.concatenate(coords)),
                         torch.from_numpy(np.concatenate(batch)), grids)
    phi = torch.from_numpy(np.concatenate(values)).to(device=device)[:, None]
    surface = BrickSurface(phi, layout, band_width)
    _check_formed_band_clear_of_faces(surface)
    return surface, bands


def _check_formed_band_clear_of_faces(surface: BrickSurface) -> None:
    """:func:`check_clear_of_faces` on the band ``surface`` forms (``|phi| / W``), which may hold
    a node whose exact distance is beyond ``band_width``, at the nodes whose gradient reads
    stored values only; only bricks that reach within :data:`REACH_CELLS` nodes of a face are
    looked at (none, with a margin)."""
    layout = surface.layout
    shapes = torch.tensor([grid.shape for grid in layout.grids])[layout.batch]
    start = layout.coords * BRICK
    near_face = ((start < REACH_CELLS) | (start + BRICK - 1 >= shapes - REACH_CELLS)).any(dim=1)
    if not bool(near_face.any()):
        return
    rows = near_face.nonzero().squeeze(1)
    # where a gradient stencil reads a brick that is not stored (zeros), W is not phi's
    trusted = layout.inside & layout.interior(1)
    band = (ImplicitSurface.band_mask(surface).cpu() & trusted.cpu())[rows, 0]
    local = torch.arange(BRICK)
    nodes = (start[rows, None, None, None, :]
             + torch.stack(torch.meshgrid(local, local, local, indexing="ij"), dim=-1))
    for b, grid in enumerate(layout.grids):
        mine = band & (layout.batch[rows] == b).view(-1, 1, 1, 1)
        check_clear_of_faces(nodes[mine], grid, b)


def _clearance(band_nodes: Tensor, grid: Grid) -> int | float:
    """Nodes between the band's nodes ``(M, 3)`` and the nearest face of ``grid``'s box
    (infinite for no node)."""
    if len(band_nodes) == 0:
        return math.inf
    return int(torch.minimum(band_nodes.min(dim=0).values,
                             torch.tensor(grid.shape) - 1 - band_nodes.max(dim=0).values).min())


def check_clear_of_faces(band_nodes: Tensor, grid: Grid, entry: int) -> None:
    """Raise ``ValueError`` if a band node ``(M, 3)`` ``(k, j, i)`` lies within
    :data:`REACH_CELLS` nodes of the faces of ``grid``'s box (bricks have no faces to stop the
    flux at: the dense and band results would differ there)."""
    clearance = _clearance(band_nodes, grid)
    if clearance == 0:
        raise ValueError(
            f"the band of batch entry {entry} reaches its grid's faces (grid shape "
            f"{grid.shape}): the surface may leave the box, and a wider grid must hold the "
            f"whole shape and its band with {REACH_CELLS} nodes to spare on each side "
            "(torchsurf.bricks.fit_grids fits a mesh's grid to it; torchsurf.mesh.fit_grid's "
            "margin is a fraction of the mesh's size), or, if phi is not a distance (its band "
            "then reaches far from S), torchsurf.sdf.redistance(phi, grid) first"
        )
    if clearance < REACH_CELLS:
        wider = REACH_CELLS - clearance
        raise ValueError(
            f"the band of batch entry {entry} comes within {clearance} "
            f"node{'' if clearance == 1 else 's'} of its grid's faces (grid shape {grid.shape}), "
            f"it needs {REACH_CELLS}; bricks have no box faces to stop the flux at: use a grid "
            f"at least {wider} node{'' if wider == 1 else 's'} wider on each side "
            "(torchsurf.bricks.fit_grids leaves room by default; torchsurf.mesh.fit_grid's "
            "margin is a fraction of the mesh's size), or, if phi is "
            "not a distance (its band then reaches far from S), "
            "torchsurf.sdf.redistance(phi, grid) first"
        )


def cat(surfaces: Sequence[BrickSurface]) -> BrickSurface:
    """One batch of the entries of several :class:`BrickSurface` (boxes of any shape, one
    spacing, band width, dtype and device); entries keep their order.

    Packed fields of the parts join the same way: ``torch.cat(fields)`` along dim 0.
    """
    surfaces = list(surfaces)
    if not surfaces:
        raise ValueError("surfaces must be a non-empty sequence of BrickSurface, got none")
    for index, surface in enumerate(surfaces):
        if not isinstance(surface, BrickSurface):
            raise TypeError(f"surfaces[{index}] must be a BrickSurface, got "
                            f"{type(surface).__name__} (torchsurf.bricks.from_dense stores a "
                            f"dense surface's phi as bricks)")
    first = surfaces[0]
    for index, surface in enumerate(surfaces[1:], start=1):
        if (surface.phi.dtype, surface.phi.device) != (first.phi.dtype, first.phi.device):
            raise MismatchError(
                f"surfaces[{index}] has phi of {surface.phi.dtype} on {surface.phi.device}, "
                f"surfaces[0] of {first.phi.dtype} on {first.phi.device}: one batch needs one "
                "dtype and device (move them with .to())"
            )
        if surface.grids[0].spacing != first.grids[0].spacing:
            raise ValueError(
                f"surfaces[{index}] has grid spacing {surface.grids[0].spacing!r}, surfaces[0] "
                f"{first.grids[0].spacing!r}: bricks of one batch share one spacing "
                "(torchsurf.bricks.fit_grids gives several meshes one)"
            )
        for setting in ("band_width", "eps"):
            if getattr(surface, setting) != getattr(first, setting):
                raise ValueError(
                    f"surfaces[{index}] has {setting} {getattr(surface, setting)!r}, "
                    f"surfaces[0] {getattr(first, setting)!r}: one batch has one {setting}")
    offsets = np.cumsum([0] + [s.batch_size for s in surfaces[:-1]])
    layout = BrickLayout(
        torch.cat([s.layout.coords.cpu() for s in surfaces]),
        torch.cat([s.layout.batch.cpu() + int(o) for s, o in zip(surfaces, offsets, strict=True)]),
        [g for s in surfaces for g in s.grids],
    )
    phi = torch.cat([s.phi for s in surfaces])
    return BrickSurface(phi, layout, surfaces[0].band_width, surfaces[0].eps,
                        [w for s in surfaces for w in s.evolving_widths()])


def _brick_values(signed: _mesh_sdf.SignedBand, grid: Grid, reach: float, dtype: np.dtype
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The bricks holding a node within ``reach`` and their values ``(M, 8, 8, 8)`` in
    ``dtype``, bricks in ``(bz, by, bx)`` order.

    Nodes of those bricks outside ``reach`` lie in far bricks of the refinement finer than a
    brick; each takes ``+-reach`` by its side.
    """
    nodes = signed.band.nodes
    extent = [-(-n // BRICK) for n in grid.shape[::-1]]  # x, y, z
    key = _brick_key(nodes, extent)
    stored = np.zeros(math.prod(extent), dtype=bool)
    stored[key] = True
    unique = np.flatnonzero(stored)
    row_of = np.zeros(len(stored), dtype=np.int64)
    row_of[unique] = np.arange(len(unique))
    values = np.full((len(unique), BRICK, BRICK, BRICK), reach, dtype=dtype)
    for (size, corners), inside in zip(signed.band.far_corners, signed.far_inside, strict=True):
        if size >= BRICK or len(corners) == 0:
            continue
        corner_key = _brick_key(corners, extent)
        kept = stored[corner_key]
        block = (corners[kept] % BRICK) // size
        blocks = BRICK // size
        view = values.reshape(-1, blocks, size, blocks, size, blocks, size)
        view[row_of[corner_key[kept]], block[:, 2], :, block[:, 1], :, block[:, 0], :] = \
            np.where(inside[kept], -reach, reach)[:, None, None, None]
    flat = row_of[key]
    for axis in (2, 1, 0):
        flat *= BRICK
        flat += nodes[:, axis] % BRICK
    values.reshape(-1)[flat] = signed.near
    bz = unique // (extent[0] * extent[1])
    by = (unique // extent[0]) % extent[1]
    bx = unique % extent[0]
    coords = np.stack([bz, by, bx], axis=1)
    _extrapolate_beyond_box(values, coords, grid.shape, stored, row_of, extent)
    return coords, values


def _extrapolate_beyond_box(values: np.ndarray, coords: np.ndarray, shape: tuple[int, int, int],
                            stored: np.ndarray, row_of: np.ndarray, extent: list[int]) -> None:
    """Fill the nodes of the last bricks beyond the box ``shape`` in place, extrapolated from
    the box's last three nodes along each axis in turn (z, y, x), as
    :meth:`BrickLayout.from_dense` does with ``fill="quadratic"``: the geometry at the faces is
    then the dense surface's (a jump to ``+-reach`` there made ``|grad phi|`` 1.5 at face
    nodes and took them into the band). Where the box's last nodes begin their brick and the
    brick before it is not stored, the extrapolation is linear, or the values are repeated
    (such nodes lie farther than ``reach`` from the mesh)."""
    strides = (extent[0] * extent[1], extent[0], 1)
    for axis in range(3):
        length = shape[axis]
        last = (length - 1) % BRICK
        if last == BRICK - 1:
            continue
        rows = np.flatnonzero(coords[:, axis] == (length - 1) // BRICK)
        if len(rows) == 0:
            continue
        along = values[rows].swapaxes(1, 1 + axis)  # (M, 8, ., .): the axis first
        edge = along[:, last].copy()
        key = coords[rows] @ np.array(strides) - strides[axis]
        previous = stored[key] if coords[rows, axis].min() > 0 else np.zeros(len(rows), bool)
        before_rows = values[row_of[key[previous]]].swapaxes(1, 1 + axis)
        layers = np.concatenate([np.zeros_like(along[:, :BRICK]), along], axis=1)
        layers[previous, :BRICK] = before_rows   # the axis's 16 nodes from the brick before
        known = np.ones(len(rows), bool) if last >= 1 else previous
        before = np.where(known[:, None, None], layers[:, BRICK + last - 1], edge)
        slope = edge - before
        if length > 2:
            known = known if last >= 2 else previous
            second = np.where(known[:, None, None], layers[:, BRICK + last - 2], 2.0 * before - edge)
            slope = 2.0 * slope - (before - second)
        for step in range(1, BRICK - last):
            along[:, last + step] = edge + step * slope
        values[rows] = along.swapaxes(1, 1 + axis)


def _brick_key(nodes: np.ndarray, extent: list[int]) -> np.ndarray:
    """``(N,)`` index of the brick of each node ``(i, j, k)`` among ``extent`` ``(x, y, z)``
    bricks, ``z`` slowest."""
    key = nodes[:, 2] // BRICK
    key *= extent[1]
    key += nodes[:, 1] // BRICK
    key *= extent[0]
    key += nodes[:, 0] // BRICK
    return key
