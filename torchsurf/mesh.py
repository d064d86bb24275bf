"""Triangle meshes in and out: loading, grids that fit them, marching cubes, vertex data.

A mesh enters as a signed distance volume (:func:`torchsurf.sdf.from_mesh`); data on its
vertices enters the band around it constant along the normals (:func:`to_band`, the value at
the closest point of the mesh) and leaves by weights, around each vertex, that reproduce the
closest points the band nodes stand for (:meth:`MeshAdapter.decode`). :class:`MeshAdapter` keeps
all of it for one mesh; :class:`torchsurf.shape_batch.MeshBatchAdapter` puts several shapes on one
grid.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from torch import Tensor, nn

from . import _isosurface, _memory, _mesh_sdf, _vertex_decode, sdf
from ._checks import (
    check_count,
    check_device,
    check_dtype,
    check_loaded_shapes,
    check_module_dtype,
    check_nonnegative,
    check_positive,
    check_spatial_shape,
    check_tensor,
    check_volume,
)
from ._mesh_input import MeshLike, as_trimesh, triangle_arrays, warn_unused_vertices
from ._precision import apply_keeping_dtype
from .grid import Grid, default_margin
from .sampling import sample
from .surface import ImplicitSurface

__all__ = [
    "DECODE_ORDERS",
    "MIN_BAND_CELLS",
    "MeshAdapter",
    "check_adapter_band",
    "check_decode_order",
    "extract",
    "fit_grid",
    "load",
    "to_band",
]


def load(mesh: MeshLike) -> trimesh.Trimesh:
    """A checked ``trimesh.Trimesh`` from a mesh, a file path or ``(vertices, faces)``.

    Args:
        mesh: a ``trimesh.Trimesh`` (returned as it is); a path to any file trimesh reads
            (its raw arrays checked, then trimesh's processing merges vertices closer than
            1e-8 of the mesh's longest side and drops unreferenced ones); or a pair
            ``(vertices (V, 3), faces (F, 3))`` of arrays or tensors, kept as given.

    Raises:
        FileNotFoundError, ValueError, TypeError: naming ``mesh`` and what is wrong (no file,
            unreadable file, empty mesh, NaN vertices, non-triangular faces, bad indices,
            only zero-area faces).

    A ``trimesh.Trimesh`` that trimesh processed (its default) has already dropped NaN
    vertices and their faces: build it with ``process=False`` to have them checked.
    """
    return as_trimesh(mesh, "mesh")


def fit_grid(mesh: MeshLike, resolution: int = 64, margin: float | None = None) -> Grid:
    """A cubic ``resolution^3`` grid around the mesh's bounding box.

    Args:
        mesh: as in :func:`load`.
        resolution: nodes along each axis (at least 3).
        margin: free space on each side, as a fraction of the box's longest side; keep it
            larger than the band you will ask for. ``None``: 10%, and at least
            :data:`~torchsurf.grid.MIN_MARGIN_CELLS` cells (:func:`~torchsurf.grid.default_margin`;
            wider than 10% below 37 nodes). Bricks keep their band two nodes more off the
            faces, which 10% leaves only from about 50 nodes (refused at 48 on spot,
            bunny_closed and the fandisk): fit their grids with
            :func:`torchsurf.bricks.fit_grids`.

    Returns:
        A grid centred on the box, spacing ``longest side * (1 + 2 margin) / (resolution - 1)``.
    """
    mesh = as_trimesh(mesh, "mesh")
    resolution = check_count(resolution, "resolution", minimum=3)
    margin = (default_margin(resolution, 0.1) if margin is None
              else check_nonnegative(margin, "margin"))
    vertices, faces = triangle_arrays(mesh)
    used = vertices[np.unique(faces)]
    low, high = used.min(axis=0), used.max(axis=0)
    extent = float((high - low).max()) * (1.0 + 2.0 * margin)
    if extent == 0:
        raise ValueError("mesh: all its vertices coincide, there is no box to fit")
    origin = (low + high) / 2 - extent / 2
    return Grid((resolution,) * 3, extent / (resolution - 1), tuple(float(x) for x in origin))


def extract(phi: Tensor, grid: Grid, level: float = 0.0, mask: Tensor | None = None
            ) -> trimesh.Trimesh:
    """The level set ``phi == level`` as a triangle mesh, by marching cubes (scikit-image).

    Args:
        phi: ``(1, 1, D, H, W)``, one surface (index a batch as ``phi[b:b + 1]``).
        grid: the grid ``phi`` is sampled on.
        level: the iso-value, units of ``phi``.
        mask: ``(1, 1, D, H, W)`` bool, the nodes where ``phi`` is known (e.g. the stored
            bricks of a :class:`~torchsurf.bricks.BrickSurface` made dense): every cell within
            one node of an unknown node is skipped, so that no value outside it is read;
            ``None``: every node.

    Returns:
        A ``trimesh.Trimesh`` in world coordinates ``(x, y, z)``, normals pointing towards
        larger ``phi`` (outward); watertight wherever the level set stays inside the grid and
        does not touch itself (two sheets through a node where ``phi == level`` share its
        vertex, and an edge there can join four faces); no two vertices coincide and no face
        has zero area, also where ``phi == level`` at nodes. A node within 1e-12 of ``phi``'s
        largest difference from the level is taken to lie on it, and, with the nodes on the
        level connected to it, on the side fewer of their neighbours lie on while the cells
        are triangulated (``_isosurface.LEVEL_SNAP``,
        ``OFF_LEVEL``): a box whose faces lie on node planes keeps its edges, in float64 as in
        float32 and whichever side is its inside, and a level through nodes closes.

    Raises:
        ValueError: ``phi`` never crosses ``level`` (also where it only touches it at nodes).
    """
    if not isinstance(grid, Grid):
        raise TypeError(f"grid must be a torchsurf.Grid, got {type(grid).__name__}")
    check_volume(phi, "phi", channels=1)
    check_spatial_shape(phi, "phi", grid.shape, "grid")
    if phi.shape[0] != 1:
        raise ValueError(
            f"phi must hold one surface, shape (1, 1, D, H, W), got {tuple(phi.shape)}; "
            "extract batch entry b with phi[b:b + 1]"
        )
    volume = phi.detach().to("cpu", torch.float64).numpy()[0, 0]
    known = None
    if mask is not None:
        if tuple(mask.shape) != tuple(phi.shape) or mask.dtype != torch.bool:
            raise ValueError(f"mask must be a bool tensor of phi's shape {tuple(phi.shape)}, got "
                             f"{mask.dtype} of shape {tuple(mask.shape)}")
        # scikit-image checks one corner of each cell against its mask: keep only the nodes
        # whose 3x3x3 neighbourhood is known
        unknown = (~mask.detach().cpu()).to(torch.float32)
        known = (F.max_pool3d(unknown, 3, stride=1, padding=1) == 0).numpy()[0, 0]
    if not np.isfinite(volume if known is None else volume[known]).all():
        raise ValueError("phi must hold finite values only, found NaN or infinity")
    vertices, faces = _isosurface.level_set(volume, grid, float(level), known,
                                            torch.finfo(phi.dtype).eps)
    return trimesh.Trimesh(vertices, faces, process=False)


class MeshAdapter(nn.Module):
    """Moves signals between the vertices of one mesh and the band around it.

    Built once per mesh: the signed distance ``phi`` (:func:`torchsurf.sdf.from_mesh`), the
    :class:`~torchsurf.ImplicitSurface` on it, and for every band node the closest point on
    the mesh as a triangle and barycentric weights. Then

    - :meth:`encode` ``(B, C, V) -> (B, C, D, H, W)``: each band node takes the value at its
      closest point (barycentric interpolation of the vertex values), so the data is constant
      along the normals; nodes beyond the band get 0;
    - :meth:`decode` ``(B, C, D, H, W) -> (B, C, V)``: with ``order=2`` (default), a weighted
      sum over the ``4^3`` nodes around each vertex whose weights reproduce every affine
      function of the closest points the nodes stand for (constants to rounding, the
      coordinates to about 1e-4 of their range or better: the solve is regularised,
      ``_vertex_decode.REGULARISATION``); with ``order=1``, trilinear
      sampling at the vertices (:func:`torchsurf.sample`).

    Why ``order=2``: a band node holds the value at its closest point, not at itself. On a
    triangle mesh the closest-point map bends at every edge and vertex (the facets meet at an
    angle), so trilinear weights at a vertex average values from points that do not average
    to the vertex: an error ``O(h |grad u| angle)``, first order in ``h`` for a fixed mesh
    (docs/benchmarks.md, "Mesh transfer"). The ``order=2`` weights are the trilinear weights
    corrected, by least change (a small regularised solve per vertex, done once), so that
    they sum to 1 and reproduce

    - every piecewise-linear function of the mesh (each hat function ``hat_j`` the vertex's
      nodes read: ``sum_n w_n hat_j(c_n) = [j = i]``, ``c_n`` the mesh closest points), which
      is what :meth:`encode` writes: the round trip returns the vertex values to about 1e-5
      whatever they are, where the nodes read at most 16 vertices (facets as large as the
      cells or larger: uniform noise on the vertices came back within 1e-4 at 20% / 64% / 78%
      of spot's 2.9k vertices at 64^3 / 96^3 / 128^3, 7% / 35% of teapot_closed's 3.3k at
      64^3 / 128^3, none of bunny_closed's 35k, and off by up to 0.6-0.85 of its range at the
      others, where the constraints below, which noise does not obey, apply); where they read
      more (small facets), every affine function of the mesh closest points instead, the
      mesh's own interpolation error being below the grid's, and the hats of the vertices read
      more than 4.5 cells away (the far corners of long facets, where the data bends and
      affine functions do not follow: trimesh's capsule, its side one strip of triangles,
      came back 2.8e-2 / 9.8e-3 / 5.8e-3 off at 32^3 / 48^3 / 64^3, against 8.8e-2 / 4.7e-2
      / 1.0e-2 with affine functions alone); and affine functions alone where reproducing
      the hats would take weights of 1-norm above 4 (many small coplanar facets: the
      fandisk's flat parts reached 47 and amplified data 1.8x);
    - every affine function of the grid's closest points ``g_n = x_n - d_n n_n``,
      ``d = surface.signed_distance()`` (what the flows' re-extension reads from,
      :mod:`torchsurf.flows.extension`),
      so that a smooth field left by a flow comes back with an error ``O(h^2 |u''|)``.

    Measured relative max error of the round trip of ``sin(2 pi a . x)``,
    ``a = 2 (0.48, 0.6, 0.64)`` (other directions differ by up to about 60%: icosphere(5) with
    ``a`` along ``(0.8, -0.2, 0.5)`` gave 7.0e-3 / 2.3e-3 / 2.2e-3 at 32^3 / 48^3 / 64^3), on
    meshes scaled to a box diagonal of 1, at 64^3 / 96^3 / 128^3: spot (2.9k vertices, facets
    of several cells) 9.3e-3 / 4.1e-3 / 2.6e-3, median 6e-4 / 8e-7 / 4e-7; armadillo 1.3e-2 /
    6.8e-3 / 3.7e-3; bunny_closed 1.7e-2 / 8.1e-3 / 4.6e-3 (``order=1``: 3.3e-2 / 1.8e-2 /
    1.2e-2, 4.7e-2 / 2.7e-2 / 2.0e-2, 3.4e-2 / 2.5e-2 / 1.9e-2). On a mesh with sharp creases
    the worst vertex need not improve with the grid: teapot_closed's max error was 3.5e-2 /
    1.3e-2 / 1.4e-2 at 48^3 / 72^3 / 96^3 while its median fell from 3.1e-3 to 6.7e-4, the
    worst vertices on creases of dihedral angle near 120 degrees, where the closest-point map
    is not smooth; on the fandisk the max error of ``sin(3x) cos(2y) + z^2`` (longest side 2)
    fell only at first order, 5.5e-3 / 4.5e-3 / 2.7e-3 at 48^3 / 64^3 / 96^3, at a vertex on a
    flat part within two cells of a crease, while its median fell at second order. Building the
    weights adds 25-50% to the adapter's setup.

    Second order is what the grid's own error does once the mesh is finer than the cells: for a
    fixed mesh whose facets are half a cell to a cell wide, the worst vertex converges at order
    1-1.5 on average, unevenly (``sin`` above, icosphere(5) scaled like the meshes above:
    4.3e-3 / 2.5e-3 / 1.6e-3 / 1.0e-3 at 32^3 / 48^3 / 64^3 / 96^3; bunny_closed 1.9e-2 /
    1.7e-2 at 48^3 / 64^3; over three smooth functions from 64^3 to 128^3, bunny_closed's and
    armadillo's max error falls 1.9-4.5 times, their median 2.8-3.0 times, order 1.5-1.6),
    second order
    where the facets are well below a cell (icosphere(6): orders 2.1, 2.0) and exact where they
    are far above it (the hats). ``order=2`` reads the ``4^3`` nodes around a vertex, so parts
    of the mesh (or sheets of one surface) closer than 3 cells mix: two spheres 1 / 2 / 2.5
    cells apart holding 0 and 1 came back up to 0.083 / 0.045 / 0.028 off at the vertices
    facing each other (``order=1``: exact; 3 cells apart: exact). Its weights are not all
    positive, so data with a sharp edge (what total variation keeps) may decode outside the
    range of the values it reads: a 0/1 step on the fandisk at 48^3 after total variation, in
    [0.0005, 0.9985] on the band, decoded in [-0.063, 1.183] (teapot, spot: -0.018, 1.026; an
    audit); ``order=1`` (trilinear, positive weights) stays within it.

    Vertices at one position are one hat function: a mesh storing a seam as two copies of its
    vertices with different values (a texture seam) encodes a blend of the two and decodes
    neither (armadillo at 56^3, 200 copies holding ``u + 1`` beside ``u``: up to 1.04 off);
    with equal values on the copies the round trip is exact.

    Both maps are linear and differentiable. Tensors follow ``.to()`` as a layer's weights do:
    an adapter built in float32 and moved to float64 keeps ``phi`` and its weights as float32
    rounded them (a constant decodes 8e-8 off, against 4e-16 built with
    ``dtype=torch.float64``).

    Args:
        mesh: as in :func:`load`; vertex ``v`` of the signals is ``mesh.vertices[v]``.
        grid: the grid (default :func:`fit_grid` of the mesh at ``resolution``).
        resolution: nodes per axis of the default grid.
        band_width: half-width of the band that holds the data, world units (default
            ``5 * grid.spacing``; at least ``sqrt(3) * grid.spacing``, :data:`MIN_BAND_CELLS`).
            ``phi`` is exact to at least the default's width whatever it is.
        dtype, device: of the tensors (default dtype, CPU).
        sign: how ``phi`` is signed, see :func:`torchsurf.sdf.from_mesh`.
        order: ``2`` (default) or ``1``, the decoding described above. ``order=1`` samples
            at the vertices as stored, in ``dtype``: in float32 far from the origin it loses
            what float32 loses of them (a mesh of size 1 at 1e5 / 1e6: round trip 2.7e-2 /
            1.6e-1 against 6.6e-3 at the origin; an audit, 2026-12-07), where ``order=2``'s
            weights, formed in float64, do not (2.6e-3 at every offset).

    Attributes:
        grid: the grid.
        surface: the :class:`~torchsurf.ImplicitSurface` of ``phi`` (its own default band).
        vertices: ``(V, 3)`` world ``(x, y, z)``.
        band_mask: ``(1, 1, D, H, W)`` bool, the nodes :meth:`encode` fills.

    Example:
        >>> adapter = MeshAdapter(trimesh.creation.icosphere(subdivisions=3), resolution=33)
        >>> values = adapter.vertices[:, 2][None, None]          # (1, 1, V): the height z
        >>> volume = adapter.encode(values)                       # (1, 1, 33, 33, 33)
        >>> adapter.decode(volume).shape
        torch.Size([1, 1, 642])
    """

    vertices: Tensor
    band_mask: Tensor
    _band_index: Tensor
    _corners: Tensor
    _weights: Tensor
    _decode_index: Tensor | None
    _decode_weights: Tensor | None

    def __init__(
        self,
        mesh: MeshLike,
        grid: Grid | None = None,
        resolution: int = 64,
        band_width: float | None = None,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
        sign: str = "auto",
        order: int = 2,
    ) -> None:
        super().__init__()
        dtype = check_dtype(dtype)
        device = check_device(device)
        self.order = check_decode_order(order)
        mesh = as_trimesh(mesh, "mesh")
        grid = fit_grid(mesh, resolution) if grid is None else grid
        width = check_adapter_band(sdf._band(grid, band_width, clamps=False), grid.spacing)
        reach = max(width, sdf.BAND_NODES * grid.spacing)
        _memory.check_fits(
            _memory.mesh_adapter_bytes(grid.shape, grid.spacing, reach, float(mesh.area), dtype,
                                       len(mesh.vertices), self.order),
            f"MeshAdapter on a {grid.shape} grid",
        )
        vertices, faces = triangle_arrays(mesh)
        # phi exact to at least the default band whatever the data's band: the decode's closest
        # points read its normals up to 4.5 cells out (at band_width = 2 h, phi cut off there
        # put them 1.7 cells off, and the decode differed from BrickMeshAdapter's by 0.1)
        phi, found = _mesh_sdf.signed_band(vertices, faces, grid, reach, sign)
        _mesh_sdf.check_sides(phi, vertices, faces, grid, "mesh")
        # decode reads the grid at every vertex (order 2 solves for weights around each now);
        # order 1 encodes on a grid holding part of the mesh (to_band), and refuses to decode
        self._outside: str | None = None
        try:
            _check_vertices_in_box(vertices, faces, grid)
        except ValueError as error:
            if order == 2:
                raise
            self._outside = str(error)
        warn_unused_vertices(vertices, faces, "mesh")
        inside = found.distance <= width
        weights, _ = _mesh_sdf.barycentric(
            vertices, faces, found.face[inside], found.closest[inside]
        )
        nodes = found.nodes[inside]
        height, width_nodes = grid.shape[1], grid.shape[2]
        flat = (nodes[:, 2] * height + nodes[:, 1]) * width_nodes + nodes[:, 0]
        self.band_width = width
        self.surface = ImplicitSurface(
            torch.as_tensor(phi, dtype=dtype, device=device)[None, None], grid
        )
        mask = torch.zeros(int(np.prod(grid.shape)), dtype=torch.bool, device=device)
        mask[torch.as_tensor(flat, device=device)] = True
        self.register_buffer("vertices", torch.as_tensor(vertices, dtype=dtype, device=device))
        self.register_buffer("band_mask", mask.reshape(1, 1, *grid.shape))
        self.register_buffer("_band_index", torch.as_tensor(flat, device=device))
        self.register_buffer("_corners", torch.as_tensor(faces[found.face[inside]], device=device))
        self.register_buffer("_weights", torch.as_tensor(weights, dtype=dtype, device=device))
        decode_index = decode_weights = None
        if order == 2:
            mesh_points = np.einsum("nk,nkd->nd", weights, vertices[faces[found.face[inside]]])
            decode_index, decode_weights = _decode_stencil(
                grid, torch.as_tensor(vertices), torch.as_tensor(flat),
                [torch.as_tensor(mesh_points), _grid_closest_points(self.surface, flat)],
                (torch.as_tensor(faces[found.face[inside]]), torch.as_tensor(weights)),
            )
            decode_index = decode_index.to(device)
            decode_weights = decode_weights.to(dtype=dtype, device=device)
        self.register_buffer("_decode_index", decode_index)
        self.register_buffer("_decode_weights", decode_weights)

    @property
    def phi(self) -> Tensor:
        """The signed distance ``(1, 1, D, H, W)``, negative inside, world units."""
        return self.surface.phi

    @property
    def grid(self) -> Grid:
        """The grid (its surface's: a loaded state brings its own)."""
        return self.surface.grid

    def _apply(self, fn, recurse=True):  # noqa: ANN001, ANN202
        # model.half(): the vertices and weights stay in their dtype, as the surface does
        # (converted and back they had moved by 2.4e-4: round trip 3e-4 off)
        return apply_keeping_dtype(self, ("vertices", "_weights", "_decode_weights"),
                                   lambda: super(MeshAdapter, self)._apply(fn, recurse))

    def encode(self, values: Tensor) -> Tensor:
        """Vertex values ``(B, C, V)`` -> volume ``(B, C, D, H, W)``, constant along normals.
        ``values`` must have the adapter's dtype and device (:class:`MismatchError`).

        Each node takes the mesh's piecewise-linear interpolant at its closest point, which
        bends at every edge: second derivatives of the encoded field (Laplace-Beltrami, a
        layer's gradient features of it) carry an error of about the edge length over ``h``
        times the data's second derivative, growing as the grid is refined under a fixed mesh
        (``x`` on unit icospheres, where ``Lap_S x = -2 x``: 0.97 off at edges of ``0.94 h``,
        2.2 at ``2.0 h``, 0.53 at ``0.5 h``). A short heat flow first smooths the bends: after
        ``HeatFlow(h^2)``, 0.15, 0.58 and 0.08 (the mesh's own polygonal error remains)."""
        check_module_dtype(check_tensor(values, "values"), "values", self.vertices, "adapter")
        return _scatter_to_band(
            values, self._band_index, self._corners, self._weights, self.grid, len(self.vertices)
        )

    def decode(self, volume: Tensor) -> Tensor:
        """Volume ``(B, C, D, H, W)`` -> values ``(B, C, V)`` at the vertices (see ``order``),
        of the adapter's dtype and device (:class:`MismatchError`)."""
        check_volume(volume, "volume")
        check_module_dtype(volume, "volume", self.vertices, "adapter")
        check_spatial_shape(volume, "volume", self.grid.shape, "grid")
        if self._outside is not None:
            raise ValueError(self._outside)
        if self._decode_index is None:
            return sample(volume, self.vertices.to(volume.dtype), self.grid)
        flat = volume.reshape(*volume.shape[:2], -1)[..., self._decode_index]
        return (flat * self._decode_weights.to(volume.dtype)).sum(dim=-1)

    def forward(self, values: Tensor) -> Tensor:
        """:meth:`encode`: vertex values ``(B, C, V)`` -> volume ``(B, C, D, H, W)`` on
        :attr:`grid`, constant along normals in the band."""
        return self.encode(values)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: object,
                              **kwargs: object) -> None:
        check_loaded_shapes(self, state_dict, prefix)  # before the surface takes another mesh
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return (
            f"vertices={len(self.vertices)}, grid={self.grid.shape}, "
            f"spacing={self.grid.spacing:g}, band_width={self.band_width:g}, order={self.order}"
        )


def _check_vertices_in_box(vertices: np.ndarray, faces: np.ndarray, grid: Grid) -> None:
    """Raise naming a vertex of ``vertices`` ``(V, 3)`` outside ``grid``'s box (``decode`` reads
    the grid at every vertex), and saying so when no face of ``faces`` uses it."""
    outside = ~grid.contains(torch.as_tensor(vertices), tolerance=1e-4).numpy()
    unused = np.ones(len(vertices), dtype=bool)
    unused[faces.reshape(-1)] = False
    stray = outside & unused
    if stray.any():
        raise ValueError(
            f"mesh: {int(stray.sum())} vertices that no face uses lie outside the grid's box, "
            f"e.g. vertex {int(np.flatnonzero(stray)[0])} (fit_grid fits the faces); decode "
            "reads the grid at every vertex: remove them first "
            "(mesh.remove_unreferenced_vertices())"
        )
    if outside.any():
        raise ValueError(
            f"mesh: {int(outside.sum())} of {len(vertices)} vertices lie outside the grid's "
            f"box, e.g. vertex {int(np.flatnonzero(outside)[0])}; decode reads the grid at "
            "every vertex, so the grid must hold the whole mesh (fit_grid)"
        )


MIN_BAND_CELLS = 3**0.5
"""Narrowest ``band_width`` of a :class:`MeshAdapter`, in cells: the nodes of the cell around a
vertex lie within ``sqrt(3) h`` of it, so of the mesh, and the decoding reads them."""


DECODE_ORDERS = (1, 2)


def check_decode_order(order: object) -> int:
    """``order`` if it is one of :data:`DECODE_ORDERS` (not a bool); raises naming it."""
    if isinstance(order, bool) or order not in DECODE_ORDERS:
        raise ValueError(f"order must be one of {DECODE_ORDERS}, got {order!r}")
    return int(order)


def check_adapter_band(width: float, spacing: float) -> float:
    """``width`` if the band holds the 8 nodes around every vertex (at least
    :data:`MIN_BAND_CELLS` cells); raises naming ``band_width`` otherwise."""
    if width < MIN_BAND_CELLS * spacing:
        raise ValueError(
            f"band_width must be at least sqrt(3) * spacing = {MIN_BAND_CELLS * spacing:g}, so "
            f"that the 8 nodes around every vertex hold data, got {width:g}"
        )
    return width


def _grid_closest_points(surface: ImplicitSurface, flat: np.ndarray) -> Tensor:
    """``x - d n``, ``d = surface.signed_distance()`` (the closest points of the flows' re-extension,
    :mod:`torchsurf.flows.extension`) at the flat node indices ``flat``, float64 world
    ``(N, 3)``."""
    index = torch.as_tensor(flat, device=surface.phi.device)
    step = (surface.signed_distance() * surface.normal)[0].reshape(3, -1)[:, index]
    points = surface.grid.points(dtype=torch.float64).reshape(-1, 3)[index.cpu()]
    return points - step.T.to("cpu", torch.float64)


def _decode_stencil(grid: Grid, vertices: Tensor, band_index: Tensor, references: list[Tensor],
                    triangles: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor]:
    """Decoding weights of the ``4^3`` nodes around each vertex, float64
    (:func:`torchsurf._vertex_decode.weights`).

    Args:
        grid: the grid.
        vertices: ``(V, 3)`` world.
        band_index: ``(N,)`` flat indices of the nodes that hold data.
        references: ``(N, 3)`` world points, per band node, that the weights must reproduce
            (``sum_n w_n p_n = v``).
        triangles: each band node's mesh closest point as its triangle's corners ``(N, 3)``
            (vertex indices) and barycentric weights ``(N, 3)``: the weights then reproduce
            the mesh's hat functions where they can (:class:`torchsurf._vertex_decode.Hats`).

    Returns:
        ``index`` ``(V, 64)`` flat node indices and ``weights`` ``(V, 64)``, 0 on nodes
        outside the band.
    """
    depth, height, width = grid.shape
    found = _vertex_decode.cells(grid, vertices)
    x, y, z = found.nodes
    index = ((z[:, :, None, None] * height + y[:, None, :, None]) * width
             + x[:, None, None, :]).flatten(1)
    row = torch.full((depth * height * width,), -1, dtype=torch.long)
    row[band_index] = torch.arange(len(band_index))
    row = row[index]
    usable = found.inside & (row >= 0)
    row = row.clamp(min=0)
    hats = None
    if triangles is not None:
        corners, barycentric = triangles
        # vertices at one position (a triangle soup, as STL stores it) are one hat function:
        # counted apart, a soup's vertices read past HAT_LIMIT and lost their exact decode
        positions, same = torch.unique(vertices, dim=0, return_inverse=True)
        hats = _vertex_decode.Hats(same[corners[row]], barycentric[row], same, positions)
    weights = _vertex_decode.weights(found, usable, vertices,
                                     [points[row] for points in references], grid.spacing, hats)
    return _vertex_decode.onto_weighted_taps(index, weights), weights


def _scatter_to_band(values: Tensor, band_index: Tensor, corners: Tensor, weights: Tensor,
                         grid: Grid, vertex_count: int) -> Tensor:
    """Scatter barycentric interpolants of ``values`` ``(B, C, V)`` into ``(B, C, D, H, W)``.

    Band node ``band_index[n]`` (flat index into ``D * H * W``) gets
    ``sum_k weights[n, k] * values[..., corners[n, k]]``; every other node gets 0.
    """
    check_tensor(values, "values")
    if values.dim() != 3 or values.shape[-1] != vertex_count or 0 in values.shape[:2]:
        raise ValueError(
            f"values must have shape (B, C, V) with V = {vertex_count} vertices and B, C at "
            f"least 1, got {tuple(values.shape)}"
        )
    weights = weights.to(values.dtype)
    interpolated = (values[..., corners] * weights).sum(dim=-1)
    batch, channels = values.shape[:2]
    volume = values.new_zeros(batch, channels, int(np.prod(grid.shape)))
    volume = volume.index_copy(2, band_index, interpolated)
    return volume.reshape(batch, channels, *grid.shape)


def to_band(values: Tensor, mesh: MeshLike, grid: Grid, band_width: float | None = None
            ) -> Tensor:
    """Vertex values ``(B, C, V)`` on ``mesh`` -> a volume ``(B, C, D, H, W)`` in the band.

    Each node within ``band_width`` of the mesh takes the barycentric interpolant of the vertex
    values at its closest point on the mesh (constant along the normals); the others get 0.
    The functional form of :meth:`MeshAdapter.encode`; build a :class:`MeshAdapter` to reuse
    the closest points. ``band_width``: world units, as :class:`MeshAdapter`'s (default
    ``5 * grid.spacing``, at least ``sqrt(3) * grid.spacing``, :data:`MIN_BAND_CELLS`).
    """
    check_tensor(values, "values")
    if band_width is not None:
        check_positive(band_width, "band_width")
    adapter = MeshAdapter(mesh, grid, band_width=band_width, dtype=values.dtype,
                          device=values.device, order=1)  # encodes only: no decoding weights
    return adapter.encode(values)
