"""``BrickMeshAdapter``: vertex data of one or several meshes into and out of a brick batch."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor, nn

from .. import _mesh_sdf, _vertex_decode, sdf
from .._checks import (
    check_device,
    check_dtype,
    check_like_first,
    check_loaded_shapes,
    check_module_dtype,
    check_positive,
    check_tensor,
)
from .._mesh_input import MeshLike, warn_unused_vertices
from .._precision import apply_keeping_dtype
from ..grid import Grid
from ..mesh import check_adapter_band, check_decode_order
from .build import EXACT_REACH, MeshBand, mesh_list, signed_bricks
from .layout import BRICK, BrickLayout


def _packed_index(layout: BrickLayout, entry: int, x: Tensor, y: Tensor, z: Tensor) -> Tensor:
    """Packed index (among the ``N 512`` nodes) of the nodes ``(x, y, z)`` (broadcast) of batch
    ``entry``, ``-1`` where their brick is not stored."""
    brick = layout.lookup[entry, z // BRICK, y // BRICK, x // BRICK]
    inside = (z % BRICK) * BRICK * BRICK + (y % BRICK) * BRICK + x % BRICK
    return torch.where(brick >= 0, brick * BRICK**3 + inside, -1)


class BrickMeshAdapter(nn.Module):
    """Moves signals between the vertices of one or several meshes and their band stored as
    bricks: :class:`~torchsurf.mesh.MeshAdapter` on a :class:`BrickSurface`, built without
    any dense volume.

    Mesh ``b`` is built on ``grids[b]`` (one spacing for all: for meshes of different sizes,
    :func:`torchsurf.bricks.fit_grids`) into one :class:`BrickSurface` with an entry per mesh
    (as :func:`torchsurf.bricks.from_mesh` does), every node within ``band_width`` of a mesh
    keeping its closest point on it. Then, as :class:`~torchsurf.mesh.MeshAdapter` does on a
    dense volume,

    - :meth:`encode`: vertex values -> packed field ``(N, C, 8, 8, 8)``: each node within
      ``band_width`` of a mesh takes the barycentric interpolant at its closest point (constant
      along the normals), every other node 0;
    - :meth:`decode`: packed field -> vertex values: with ``order=2`` (default) a weighted sum
      over the ``4^3`` nodes around each vertex that reproduces the closest points the nodes
      stand for (:class:`~torchsurf.mesh.MeshAdapter` says why), with ``order=1`` trilinear
      sampling (:meth:`BrickSurface.sample`).

    Both equal the dense adapter's on each mesh's grid to rounding
    (tests/bricks/test_adapter.py); both are linear and differentiable.

    Args:
        meshes: a mesh (as in :func:`torchsurf.mesh.load`) or a sequence.
        grids: a :class:`~torchsurf.Grid` per mesh, one spacing (or one grid for one mesh),
            each leaving 5 cells between its faces and its mesh's band
            (:func:`~torchsurf.bricks.from_mesh`) and holding the whole mesh.
        band_width: half-width of the band :meth:`encode` fills, world units (default
            ``5 * spacing``, as :class:`~torchsurf.mesh.MeshAdapter`).
        dtype, device: of the tensors (default dtype, CPU).
        sign: how ``phi`` is signed (:func:`torchsurf.sdf.from_mesh`).
        order: ``2`` (default) or ``1``, the decoding. ``order=1`` samples at the vertices
            as stored, in ``dtype``, and loses in float32 far from the origin what
            :class:`~torchsurf.mesh.MeshAdapter`'s ``order=1`` loses there.

    Attributes:
        surface: the :class:`BrickSurface`, one entry per mesh, its own default band (3 cells).
        vertices: list of ``B`` tensors ``(V_b, 3)``, world ``(x, y, z)``.
        band_mask: ``(N, 1, 8, 8, 8)`` bool, the nodes :meth:`encode` fills.

    Example:
        >>> import trimesh
        >>> from torchsurf import bricks
        >>> meshes = [trimesh.creation.icosphere(), trimesh.creation.box((0.1, 0.2, 0.3))]
        >>> fitted = bricks.fit_grids(meshes, [32, 24])
        >>> adapter = bricks.BrickMeshAdapter(fitted.meshes, fitted.grids)
        >>> field = adapter.encode([v[:, :1] for v in adapter.vertices])   # x of every vertex
        >>> [tuple(values.shape) for values in adapter.decode(field)]
        [(642, 1), (8, 1)]
    """

    band_mask: Tensor
    _band_index: Tensor
    _corners: Tensor
    _weights: Tensor
    _decode_index: Tensor | None
    _decode_weights: Tensor | None

    def __init__(self, meshes: MeshLike | Sequence[MeshLike], grids: Grid | Sequence[Grid],
                 band_width: float | None = None, dtype: torch.dtype | None = None,
                 device: torch.device | str | None = None, sign: str = "auto",
                 order: int = 2) -> None:
        super().__init__()
        dtype = check_dtype(dtype)
        device = check_device(device)
        self.order = check_decode_order(order)
        meshes, grids = mesh_list(meshes, grids)
        spacing = grids[0].spacing
        width = check_adapter_band(sdf.BAND_NODES * spacing if band_width is None
                                   else check_positive(band_width, "band_width"), spacing)
        surface_width = 3.0 * spacing
        reach = max(width, surface_width + EXACT_REACH * spacing)
        self.band_width = width
        self.surface, bands = signed_bricks(meshes, grids, surface_width, reach, dtype, sign,
                                            device)
        layout = self.surface.layout.to("cpu")
        for b, (vertices, mesh_faces, _) in enumerate(bands):
            warn_unused_vertices(vertices, mesh_faces, f"meshes[{b}]")
        nodes, faces, barycentric, offset = [], [], [], 0
        for vertices, mesh_faces, signed in bands:
            near = signed.band.distance <= width
            face = mesh_faces[signed.band.face[near]]
            weights, _ = _mesh_sdf.barycentric(vertices, mesh_faces, signed.band.face[near],
                                               signed.band.closest[near])
            nodes.append(torch.from_numpy(signed.band.nodes[near]))
            faces.append(torch.from_numpy(face) + offset)
            barycentric.append(weights)
            offset += len(vertices)
        band_index = torch.cat([_packed_index(layout, b, *n.unbind(1))
                                for b, n in enumerate(nodes)])
        self._counts = [len(vertices) for vertices, _, _ in bands]
        for b, (vertices, _, _) in enumerate(bands):
            self.register_buffer(f"_vertices_{b}",
                                 torch.as_tensor(vertices, dtype=dtype, device=device))
        mask = torch.zeros(len(layout) * BRICK**3, dtype=torch.bool)
        mask[band_index] = True
        self.register_buffer("band_mask", mask.view(-1, 1, BRICK, BRICK, BRICK).to(device))
        self.register_buffer("_band_index", band_index.to(device))
        self.register_buffer("_corners", torch.cat(faces).to(device))
        self.register_buffer("_weights", torch.as_tensor(np.concatenate(barycentric),
                                                         dtype=dtype, device=device))
        decode_index = decode_weights = None
        if order == 2:
            decode_index, decode_weights = self._decode_stencil(layout, bands, nodes, barycentric,
                                                                band_index)
            decode_index = decode_index.to(device)
            decode_weights = decode_weights.to(dtype=dtype, device=device)
        self.register_buffer("_decode_index", decode_index)
        self.register_buffer("_decode_weights", decode_weights)

    def _decode_stencil(self, layout: BrickLayout, bands: list[MeshBand], nodes: list[Tensor],
                        barycentric: list[np.ndarray], band_index: Tensor
                        ) -> tuple[Tensor, Tensor]:
        """Packed indices and weights ``(V_total, 64)`` of the ``4^3`` nodes around every
        vertex (:func:`torchsurf._vertex_decode.weights`), float64."""
        row = torch.full((len(layout) * BRICK**3,), -1, dtype=torch.long)
        row[band_index] = torch.arange(len(band_index))
        mesh_points, grid_points = [], []
        for b, ((vertices, faces, signed), weights) in enumerate(
                zip(bands, barycentric, strict=True)):
            near = signed.band.distance <= self.band_width
            corners = vertices[faces[signed.band.face[near]]]
            mesh_points.append(torch.from_numpy(np.einsum("nk,nkd->nd", weights, corners)))
            grid = layout.grids[b]
            origin = torch.tensor(grid.origin, dtype=torch.float64)
            grid_points.append(origin + grid.spacing * nodes[b].to(torch.float64))
        surface = self.surface
        step = (surface.signed_distance() * surface.normal).transpose(0, 1).reshape(3, -1)
        step = step[:, band_index.to(step.device)].T.to("cpu", torch.float64)
        references = [torch.cat(mesh_points), torch.cat(grid_points) - step]
        corners = self._corners.to("cpu").long()
        triangle_weights = torch.as_tensor(np.concatenate(barycentric))
        # vertices at one position in one mesh are one hat function (MeshAdapter's decode)
        unique, same = torch.unique(torch.cat([
            torch.cat([torch.full((len(vertices), 1), float(b), dtype=torch.float64),
                       torch.from_numpy(vertices)], dim=1)
            for b, (vertices, _, _) in enumerate(bands)]), dim=0, return_inverse=True)
        indices, weights, offset = [], [], 0
        for b, (vertices, _, _) in enumerate(bands):
            grid = layout.grids[b]
            points = torch.from_numpy(vertices)
            outside = ~grid.contains(points, tolerance=1e-4)
            if bool(outside.any()):
                raise ValueError(
                    f"meshes[{b}]: {int(outside.sum())} of {len(vertices)} vertices lie outside "
                    f"its grid's box, e.g. vertex {int(outside.nonzero()[0, 0])}; order=2 "
                    "decodes at every vertex, so the grid must hold the whole mesh"
                )
            cells = _vertex_decode.cells(grid, points)
            x, y, z = cells.nodes
            index = _packed_index(layout, b, x[:, None, None, :], y[:, None, :, None],
                                  z[:, :, None, None]).flatten(1)
            tap_row = torch.where(index >= 0, row[index.clamp(min=0)], -1)
            usable = cells.inside & (tap_row >= 0)
            tap_row = tap_row.clamp(min=0)
            hats = _vertex_decode.Hats(same[corners[tap_row]], triangle_weights[tap_row],
                                       same[offset + torch.arange(len(vertices))], unique[:, 1:])
            vertex_weights = _vertex_decode.weights(
                cells, usable, points, [points_set[tap_row] for points_set in references],
                grid.spacing, hats)
            weights.append(vertex_weights)
            indices.append(_vertex_decode.onto_weighted_taps(index.clamp(min=0), vertex_weights))
            offset += len(vertices)
        return torch.cat(indices), torch.cat(weights)

    @property
    def vertices(self) -> list[Tensor]:
        """The vertices of every mesh, ``(V_b, 3)`` world ``(x, y, z)``."""
        return [getattr(self, f"_vertices_{b}") for b in range(len(self._counts))]

    @property
    def phi(self) -> Tensor:
        """The signed distance, packed ``(N, 1, 8, 8, 8)``, negative inside, world units."""
        return self.surface.phi

    def __len__(self) -> int:
        return len(self._counts)

    def _apply(self, fn, recurse=True):  # noqa: ANN001, ANN202
        # model.half(): the vertices and weights stay in their dtype, as the surface does
        names = (*(f"_vertices_{b}" for b in range(len(self._counts))), "_weights",
                 "_decode_weights")
        return apply_keeping_dtype(self, names,
                                   lambda: super(BrickMeshAdapter, self)._apply(fn, recurse))

    def encode(self, values: Sequence[Tensor]) -> Tensor:
        """Vertex values of every mesh -> packed field.

        Args:
            values: ``B`` tensors ``(V_b, C)``, one per mesh, the same ``C`` and dtype.

        Returns:
            ``(N, C, 8, 8, 8)``: the barycentric interpolant at each band node's closest point
            on its mesh, 0 beyond the band.
        """
        if isinstance(values, Tensor) or len(values) != len(self):
            raise ValueError(
                f"values must be a sequence of {len(self)} tensors (V_b, C), one per mesh, got "
                f"{type(values).__name__}"
                + ("" if isinstance(values, Tensor) else f" of length {len(values)}")
            )
        for b, (entry, count) in enumerate(zip(values, self._counts, strict=True)):
            check_tensor(entry, f"values[{b}]")
            if entry.dim() != 2 or entry.shape[0] != count or entry.shape[1] == 0:
                raise ValueError(
                    f"values[{b}] must have shape ({count}, C), C at least 1, got "
                    f"{tuple(entry.shape)}"
                )
            check_like_first(entry, values[0], f"values[{b}]", "values[0]")
        check_module_dtype(values[0], "values[0]", self._weights, "adapter")
        joined = torch.cat(list(values))
        interpolated = (joined[self._corners] * self._weights.to(joined.dtype)[..., None]).sum(1)
        channels = joined.shape[1]
        flat = joined.new_zeros((len(self.surface.layout) * BRICK**3, channels))
        flat = flat.index_copy(0, self._band_index, interpolated)
        return flat.T.reshape(channels, -1, BRICK, BRICK, BRICK).transpose(0, 1).contiguous()

    def decode(self, field: Tensor) -> list[Tensor]:
        """Packed field ``(N, C, 8, 8, 8)`` -> ``B`` tensors ``(V_b, C)`` at the vertices (see
        ``order``)."""
        self.surface.check_field(field, "field")
        check_module_dtype(field, "field", self._weights, "adapter")
        if self._decode_index is None:
            return [self.surface.sample(field, vertices.to(field.dtype), b).T
                    for b, vertices in enumerate(self.vertices)]
        flat = field.transpose(0, 1).reshape(field.shape[1], -1)
        values = (flat[:, self._decode_index] * self._decode_weights.to(field.dtype)).sum(-1)
        return [part.T for part in values.split(self._counts, dim=1)]

    def forward(self, values: Sequence[Tensor]) -> Tensor:
        """:meth:`encode`."""
        return self.encode(values)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: object,
                              **kwargs: object) -> None:
        check_loaded_shapes(self, state_dict, prefix)  # before the surface takes another mesh
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return (f"meshes={len(self)}, vertices={self._counts}, bricks={len(self.surface.layout)}, "
                f"spacing={self.surface.spacing:g}, band_width={self.band_width:g}, "
                f"order={self.order}")
