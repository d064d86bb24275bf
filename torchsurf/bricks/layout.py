"""``BrickLayout``: which 8^3 bricks of which grids hold a band, and how they touch.

A band field is stored packed, ``(N, C, 8, 8, 8)``: one row per brick, bricks of every batch
entry together (a batch index per brick, as PyTorch3D's packed meshes or fVDB's grid batches).
Entries may have boxes of different shapes and origins; they share the spacing. Stencils read
across brick faces through :meth:`BrickLayout.halo`, which gathers a halo of ``g`` nodes from
the 26 neighbours into ``(N, C, 8 + 2g, 8 + 2g, 8 + 2g)``: the haloed input every compiled
kernel of :mod:`torchsurf.operators.functional` already takes. Pointwise work (1x1x1
convolutions, activations, losses) applies to the packed values as they are.

Bricks tile each entry's box from its first node; a box whose side is not a multiple of 8
leaves nodes of the last bricks outside it (:attr:`BrickLayout.inside` is ``False`` there). A
neighbour that is not stored reads as zeros. Band nodes never read one (the builders store
every node the band's stencils reach), and a divergence-form operator then stays exactly
symmetric on the stored nodes: zero ``u`` and zero weight beyond them, a principal submatrix of
the dense operator with that geometry.
"""

from __future__ import annotations

import itertools
import math
import numbers
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from .. import backend
from .._checks import MismatchError, check_choice, check_generator, check_tensor
from .._inference import outside_inference
from ..grid import Grid
from . import _native

BRICK = 8
"""Nodes along each side of a brick."""

FILLS = ("replicate", "linear", "quadratic")
"""How :meth:`BrickLayout.from_dense` fills the nodes of a brick beyond its entry's box."""

OFFSETS: tuple[tuple[int, int, int], ...] = tuple(itertools.product((-1, 0, 1), repeat=3))
"""The 27 brick offsets ``(dz, dy, dx)`` of the neighbour table, ``(0, 0, 0)`` (itself) at 13."""


def bricks_along(shape: Sequence[int]) -> tuple[int, int, int]:
    """Bricks along ``(D, H, W)`` that tile a box of ``shape`` nodes."""
    return tuple(-(-int(n) // BRICK) for n in shape)


def _halo_gather_eager(rows: Tensor, sources: Tensor, missing: Tensor, *,
                       path: str = "slicing") -> Tensor:
    """``rows`` ``(C, M)`` at ``sources``, zero where ``missing``: one ``index_select``."""
    return rows.index_select(1, sources).masked_fill_(missing, 0)


def _halo_gather_fused(rows: Tensor, sources: Tensor, missing: Tensor) -> Tensor:
    """The same as one compiled pass (256^3 sphere, one channel, one thread: 6.6 ms against
    8.1 ms with the test for a missing neighbour formed from the index, 9.1-12 ms eagerly)."""
    return torch.where(missing, rows.new_zeros(()), rows[:, sources])


_HALO_GATHER = backend.Kernel("brick_halo", _halo_gather_eager, _halo_gather_fused,
                              lambda *args: args, dynamic=True, trusted_indices=True)


def _check_fill(fill: float, dtype: torch.dtype) -> None:
    """Refuse, naming ``fill``, a value that ``dtype`` cannot hold: a complex number in a real
    dtype, a fraction, NaN or infinity in an integer dtype, one beyond its range (-1 in uint8
    wrapped to 255), or anything but 0 or 1 in bool (5 was taken as True)."""
    if isinstance(fill, numbers.Complex) and not isinstance(fill, numbers.Real) \
            and not dtype.is_complex:
        raise ValueError(f"fill={fill!r} cannot be held by field's dtype {dtype} (not complex): "
                         "give a real value")
    if dtype.is_floating_point:
        largest = torch.finfo(dtype).max
        if math.isfinite(fill) and abs(fill) > largest:  # inf and NaN fill as they are
            raise ValueError(f"fill={fill!r} cannot be held by field's dtype {dtype} (largest "
                             f"{largest:.4g}): give a value it holds")
        return
    if dtype.is_complex:
        return
    if dtype == torch.bool:
        holds = fill in (0, 1)
    else:
        limits = torch.iinfo(dtype)
        holds = math.isfinite(fill) and fill == int(fill) and limits.min <= fill <= limits.max
    if not holds:
        raise ValueError(f"fill={fill!r} cannot be held by field's dtype {dtype}: give a value "
                         "it holds, or a floating-point field")


class BrickLayout:
    """The bricks of a batch of band fields: coordinates, batch index, neighbours.

    Args:
        coords: ``(N, 3)`` integer brick coordinates ``(bz, by, bx)``: brick ``(bz, by, bx)`` of
            an entry holds its nodes ``8 bz + (0..7)`` along D, and so on.
        batch: ``(N,)`` the batch entry of each brick, in ``[0, len(grids))``.
        grids: one :class:`~torchsurf.Grid` per batch entry, all with the same spacing.

    Attributes:
        coords, batch: as given (int64, on the CPU unless moved with :meth:`to`).
        grids: the grids.
        neighbours: ``(N, 27)`` int64 row of the neighbour at each of :data:`OFFSETS`, the brick
            itself where that neighbour is not stored (its values are then read as zeros).
        present: ``(N, 27)`` bool, the neighbour is stored.
        inside: ``(N, 1, 8, 8, 8)`` bool, the node lies in its entry's box.

    Bricks of one entry must be distinct and inside its box.
    """

    def __init__(self, coords: Tensor, batch: Tensor, grids: Sequence[Grid]) -> None:
        grids = tuple(grids)
        if not grids or not all(isinstance(g, Grid) for g in grids):
            raise TypeError("grids must be a non-empty sequence of torchsurf.Grid")
        spacings = {g.spacing for g in grids}
        if len(spacings) > 1:
            raise ValueError(
                f"grids must share one spacing (bricks of one batch are stencilled together), "
                f"got spacings {sorted(spacings)}"
            )
        coords = _integer_tensor(coords, "coords")
        batch = _integer_tensor(batch, "batch")
        if coords.dim() != 2 or coords.shape[1] != 3:
            raise ValueError(f"coords must have shape (N, 3), got {tuple(coords.shape)}")
        if batch.shape != coords.shape[:1]:
            raise ValueError(
                f"batch must have shape ({coords.shape[0]},) like coords' rows, got "
                f"{tuple(batch.shape)}"
            )
        if len(batch) == 0:
            raise ValueError("a brick layout needs at least one brick, got none")
        if int(batch.min()) < 0 or int(batch.max()) >= len(grids):
            raise ValueError(f"batch indices must lie in [0, {len(grids)}), got "
                             f"[{int(batch.min())}, {int(batch.max())}]")
        extents = torch.tensor([bricks_along(g.shape) for g in grids])
        if bool((coords < 0).any()) or bool((coords >= extents[batch]).any()):
            raise ValueError("coords must lie inside each entry's box of bricks")
        self.coords, self.batch, self.grids = coords, batch, grids
        self.extent = tuple(int(n) for n in extents.max(dim=0).values)
        self.lookup = self._lookup()
        if int((self.lookup >= 0).sum()) != len(coords):
            raise ValueError("coords must not repeat a brick of the same batch entry")
        self.neighbours, self.present = self._neighbours()
        self._halo_indices: dict[tuple[int, torch.device], tuple[Tensor, Tensor]] = {}
        self._row_bits = _native._RowBits()
        self._geometry_plan = _native._GeometryPlan()
        self.inside = self._inside()

    # --- construction -------------------------------------------------------------------

    def _lookup(self) -> Tensor:
        """``(B, nbz, nby, nbx)`` int64 row of each stored brick, ``-1`` elsewhere."""
        lookup = torch.full((len(self.grids), *self.extent), -1, dtype=torch.long)
        z, y, x = self.coords.unbind(1)
        lookup[self.batch, z, y, x] = torch.arange(len(self.coords))
        return lookup

    def _neighbours(self) -> tuple[Tensor, Tensor]:
        padded = F.pad(self.lookup, (1, 1, 1, 1, 1, 1), value=-1)
        rows = []
        z, y, x = self.coords.unbind(1)
        for dz, dy, dx in OFFSETS:
            rows.append(padded[self.batch, z + 1 + dz, y + 1 + dy, x + 1 + dx])
        table = torch.stack(rows, dim=1)
        present = table >= 0
        own = torch.arange(len(self.coords))[:, None].expand_as(table)
        return torch.where(present, table, own), present

    def _inside(self) -> Tensor:
        shapes = torch.tensor([g.shape for g in self.grids])[self.batch]
        local = torch.arange(BRICK)
        axes = [
            (self.coords[:, axis, None] * BRICK + local) < shapes[:, axis, None]
            for axis in range(3)
        ]
        inside = axes[0][:, :, None, None] & axes[1][:, None, :, None] & axes[2][:, None, None, :]
        return inside[:, None]

    # --- sizes -----------------------------------------------------------------------------

    def __len__(self) -> int:
        return len(self.coords)

    @property
    def batch_size(self) -> int:
        """Number of batch entries ``B``."""
        return len(self.grids)

    @property
    def spacing(self) -> float:
        """The spacing ``h`` every entry shares, world units."""
        return self.grids[0].spacing

    @property
    def device(self) -> torch.device:
        """The device of the brick tables (and of the fields packed on them)."""
        return self.coords.device

    def to(self, device: torch.device | str) -> BrickLayout:
        """The same layout with its tables on ``device``."""
        moved = object.__new__(BrickLayout)
        moved.__dict__.update({
            key: value.to(device) if isinstance(value, Tensor) else value
            for key, value in self.__dict__.items()
        })
        moved._halo_indices = {}
        moved._row_bits = _native._RowBits()
        moved._geometry_plan = _native._GeometryPlan()
        moved.__dict__.pop("_native_tables", None)
        return moved

    def counts(self) -> list[int]:
        """Bricks of each batch entry."""
        return torch.bincount(self.batch, minlength=self.batch_size).tolist()

    def __repr__(self) -> str:
        return (f"BrickLayout(bricks={len(self)}, batch_size={self.batch_size}, "
                f"shapes={[g.shape for g in self.grids]}, spacing={self.spacing:g})")

    # --- stencils --------------------------------------------------------------------------

    def check_field(self, value: Tensor, name: str) -> None:
        """Raise ``ValueError`` naming ``name`` unless ``value`` is ``(N, C, 8, 8, 8)``."""
        if not isinstance(value, Tensor):
            raise TypeError(f"{name} must be a tensor, got {type(value).__name__}")
        if value.dim() != 5 or value.shape[0] != len(self) or value.shape[2:] != (BRICK,) * 3:
            raise ValueError(
                f"{name} must be a packed band field of shape ({len(self)}, C, {BRICK}, {BRICK}, "
                f"{BRICK}) for this layout of {len(self)} bricks, got {tuple(value.shape)}"
            )

    def halo(self, field: Tensor, width: int = 1, path: str = "auto") -> Tensor:
        """``field`` ``(N, C, 8, 8, 8)`` with ``width`` nodes of its neighbours on every side.

        One gather from a table of the haloed bricks' sources (kept per width, 5 bytes per
        haloed node), compiled where :mod:`torchsurf.backend` finds it pays (``path="auto"``;
        ``"slicing"`` for a one-off halo, whose compiling would cost more than it saves);
        zeros where a neighbour is not stored; differentiable.

        Returns:
            ``(N, C, 8 + 2 width, 8 + 2 width, 8 + 2 width)``.
        """
        self.check_field(field, "field")
        if isinstance(width, bool) or not isinstance(width, int) or not 1 <= width <= BRICK:
            raise ValueError(f"width must be an integer in [1, {BRICK}], got {width!r}")
        n, channels = field.shape[:2]
        side = BRICK + 2 * width
        sources, missing = self._halo_index(width, field.device)
        rows = field.reshape(n, channels, -1).transpose(0, 1).reshape(channels, -1)
        gathered = backend.run(_HALO_GATHER, path, field, rows, sources, missing)
        return gathered.view(channels, n, side, side, side).transpose(0, 1)

    def native_octant(self, u: Tensor, haloed_normal: Tensor, haloed_weight: Tensor,
                      spacing: float, weighted: bool, mask: Tensor | None) -> Tensor | None:
        """The octant Laplace–Beltrami of ``u`` ``(N, C, 8, 8, 8)`` by the C kernel that reads
        halos in place and evaluates only the rows of ``mask`` (:mod:`torchsurf.bricks._native`),
        or ``None`` where that kernel does not apply. What ``path="auto"`` runs on bricks."""
        if "_native_tables" not in self.__dict__:
            with outside_inference():  # kept for later calls (an inference tensor would fail them)
                self._native_tables = (self.neighbours.contiguous(),
                                       self.present.to(torch.uint8).contiguous())
        return _native.octant(u, haloed_normal, haloed_weight, *self._native_tables,
                              self._row_bits, spacing, weighted, mask, self._geometry_plan)

    def _halo_index(self, width: int, device: torch.device) -> tuple[Tensor, Tensor]:
        """``(N (8 + 2 width)^3,)`` source of each haloed node in the packed nodes (int32 up to
        2^31 nodes), and whether its neighbour is not stored (its source then reads node 0)."""
        key = (width, device)
        cached = self._halo_indices.get(key)
        if cached is not None:
            return cached
        with outside_inference():  # kept for later calls (an inference tensor would fail them)
            cached = self._formed_halo_index(width, device)
        self._halo_indices[key] = cached
        return cached

    def _formed_halo_index(self, width: int, device: torch.device) -> tuple[Tensor, Tensor]:
        """:meth:`_halo_index`, formed."""
        along = torch.arange(-width, BRICK + width)
        offset = torch.where(along < 0, -1, torch.where(along >= BRICK, 1, 0))
        local = along - offset * BRICK
        which = ((offset[:, None, None] + 1) * 9 + (offset[None, :, None] + 1) * 3
                 + offset[None, None, :] + 1).flatten()
        inside = (local[:, None, None] * BRICK * BRICK + local[None, :, None] * BRICK
                  + local[None, None, :]).flatten()
        dtype = torch.int32 if len(self) * BRICK**3 < 2**31 else torch.long
        source = self.neighbours.to(dtype)[:, which]
        source *= BRICK**3
        source += inside.to(dtype)
        missing = ~self.present[:, which]
        source.masked_fill_(missing, 0)
        return source.flatten().to(device), missing.flatten().to(device)

    def entry_max(self, x: Tensor) -> Tensor:
        """The largest value of each batch entry and channel of a packed ``x``
        ``(N, C, 8, 8, 8)``, each brick given its entry's: ``(N, C, 1, 1, 1)``."""
        self.check_field(x, "x")
        per_brick = x.amax(dim=(2, 3, 4))
        batch = self.batch.to(x.device)
        per_entry = per_brick.new_full((self.batch_size, x.shape[1]), -torch.inf).scatter_reduce(
            0, batch[:, None].expand_as(per_brick), per_brick, "amax")
        return per_entry[batch][..., None, None, None]

    def dilate(self, mask: Tensor, path: str = "auto") -> Tensor:
        """``mask`` ``(N, 1, 8, 8, 8)`` bool and every node a 3x3x3 stencil on it reads
        (``path``: the halo's, :meth:`halo`)."""
        self.check_field(mask, "mask")
        if mask.dtype != torch.bool or mask.shape[1] != 1:
            raise ValueError(f"mask must be a bool field of shape ({len(self)}, 1, {BRICK}, "
                             f"{BRICK}, {BRICK}), got dtype {mask.dtype} and shape "
                             f"{tuple(mask.shape)}")
        grown = self.halo(mask, 1, path)
        for dim in (2, 3, 4):
            length = grown.shape[dim]
            grown = (grown.narrow(dim, 0, length - 2) | grown.narrow(dim, 1, length - 2)
                     | grown.narrow(dim, 2, length - 2))
        return grown

    def interior(self, cells: int) -> Tensor:
        """``(N, 1, 8, 8, 8)`` bool: every node within ``cells`` of the node (along each axis) is
        stored. Where it is not, a stencil of that reach reads a missing neighbour's stand-in."""
        local = torch.arange(BRICK, device=self.device)
        near = {-1: local < cells, 0: torch.ones_like(local, dtype=torch.bool),
                1: local >= BRICK - cells}
        reads = torch.stack([
            near[dz][:, None, None] & near[dy][None, :, None] & near[dx][None, None, :]
            for dz, dy, dx in OFFSETS
        ]).reshape(len(OFFSETS), -1)
        missing = (~self.present).to(torch.float32) @ reads.to(torch.float32)
        return (missing == 0).view(-1, 1, BRICK, BRICK, BRICK)

    def node_index(self) -> Tensor:
        """``(N, 3, 8, 8, 8)`` int64 index ``(k, j, i)`` of each node in its entry's grid (D, H, W
        order)."""
        local = torch.arange(BRICK, device=self.device)
        start = self.coords * BRICK
        return torch.stack([
            (start[:, axis, None] + local).view(
                -1, *[BRICK if a == axis else 1 for a in range(3)]
            ).expand(-1, BRICK, BRICK, BRICK)
            for axis in range(3)
        ], dim=1)

    def points(self, dtype: torch.dtype | None = None) -> Tensor:
        """World coordinates ``(x, y, z)`` of every node, ``(N, 3, 8, 8, 8)``."""
        dtype = dtype or torch.get_default_dtype()
        index = self.node_index().flip(1).to(dtype)
        origins = torch.tensor([g.origin for g in self.grids], dtype=dtype, device=self.device)
        return origins[self.batch].view(-1, 3, 1, 1, 1) + self.spacing * index

    def colours(self) -> Tensor:
        """``(N, 1, 8, 8, 8)`` uint8 colour ``(k mod 3) 9 + (j mod 3) 3 + i mod 3`` of each node:
        no 3x3x3 neighbourhood holds two nodes of one colour (:mod:`torchsurf.operators.spectrum`).
        Formed per axis, then broadcast: one byte a node."""
        local = torch.arange(BRICK, device=self.device)
        k, j, i = ((self.coords[:, axis, None] * BRICK + local) % 3 for axis in range(3))
        k, j, i = (part.to(torch.uint8) for part in (k, j, i))
        colour = (9 * k[:, :, None, None] + 3 * j[:, None, :, None] + i[:, None, None, :])
        return colour[:, None]

    def rand(self, channels: int = 1, generator: torch.Generator | None = None,
             dtype: torch.dtype | None = None) -> Tensor:
        """Uniform noise in ``[0, 1)`` at every stored node, ``(N, C, 8, 8, 8)`` on the layout's
        device: the numbers ``torch.rand((1, C, D_b, H_b, W_b), generator=generator)`` gives
        each entry's box, the entries drawn in turn (nodes beyond a box repeat its edge).

        Drawn on the CPU one layer of bricks (8 planes of a box) at a time, so that memory stays
        at one slab: a CPU generator fills a uniform tensor one number after another, so
        consecutive draws continue the dense volume's stream (tests/bricks check it). Every
        number of the boxes is drawn, so the time grows with their volume.
        """
        check_generator(generator)
        dtype = dtype or torch.get_default_dtype()
        coords, batch = self.coords.cpu(), self.batch.cpu()
        packed = torch.empty((len(self), channels, BRICK, BRICK, BRICK), dtype=dtype)
        for b, grid in enumerate(self.grids):
            depth, height, width = grid.shape
            layers = bricks_along(grid.shape)[0]
            rows_of_layer = [((batch == b) & (coords[:, 0] == bz)).nonzero().squeeze(1)
                             for bz in range(layers)]
            for c in range(channels):
                for bz, rows in enumerate(rows_of_layer):
                    planes = min(BRICK, depth - bz * BRICK)
                    slab = torch.rand((1, planes, height, width), generator=generator, dtype=dtype)
                    slab = _pad_to_bricks(slab, "replicate")[0]
                    ny, nx = slab.shape[1] // BRICK, slab.shape[2] // BRICK
                    tiles = slab.reshape(BRICK, ny, BRICK, nx, BRICK).permute(1, 3, 0, 2, 4)
                    packed[rows, c] = tiles[coords[rows, 1], coords[rows, 2]]
        return packed.to(self.device)

    # --- dense volumes ---------------------------------------------------------------------

    def from_dense(self, volume: Tensor | Sequence[Tensor], fill: str = "replicate") -> Tensor:
        """The bricks of dense volumes, ``(N, C, 8, 8, 8)``.

        Args:
            volume: ``(B, C, D, H, W)`` when every entry has the same box, or a sequence of one
                ``(1, C, D_b, H_b, W_b)`` (or ``(C, D_b, H_b, W_b)``) volume per entry, each on
                its entry's grid.
            fill: values of the nodes outside an entry's box: ``"replicate"`` (its edge) or
                ``"linear"`` (extrapolated from its last two nodes) or ``"quadratic"`` (the
                first node beyond the box ``3 u[-1] - 3 u[-2] + u[-3]``, as the dense surface
                pads ``phi``, the next ones on the line through it and ``u[-1]``: right for
                ``phi``).
        """
        check_choice(fill, "fill", FILLS)
        volumes = self._entries(volume, "volume")
        rows = []
        for b, entry in enumerate(volumes):
            padded = _pad_to_bricks(entry, fill)
            c = padded.shape[0]
            nz, ny, nx = (n // BRICK for n in padded.shape[1:])
            tiles = padded.reshape(c, nz, BRICK, ny, BRICK, nx, BRICK).permute(1, 3, 5, 0, 2, 4, 6)
            selected = (self.batch == b).nonzero().squeeze(1)
            z, y, x = self.coords[selected].unbind(1)
            rows.append((selected, tiles[z, y, x]))
        channels = rows[0][1].shape[1]
        if any(values.shape[1] != channels for _, values in rows):
            raise ValueError(f"volume: every entry must have the same number of channels, got "
                             f"{[int(values.shape[1]) for _, values in rows]}")
        pieces = volumes[0].new_empty((len(self), channels, BRICK, BRICK, BRICK))
        for selected, values in rows:
            pieces = pieces.index_copy(0, selected.to(pieces.device), values)
        return pieces

    def to_dense(self, field: Tensor, fill: float = 0.0) -> list[Tensor]:
        """Dense volumes of a packed field: one ``(1, C, D_b, H_b, W_b)`` per entry, ``fill``
        outside the stored bricks; differentiable."""
        self.check_field(field, "field")
        _check_fill(fill, field.dtype)
        channels = field.shape[1]
        volumes = []
        for b, grid in enumerate(self.grids):
            nz, ny, nx = bricks_along(grid.shape)
            tiles = field.new_full((nz, ny, nx, channels, BRICK, BRICK, BRICK), fill)
            selected = (self.batch == b).nonzero().squeeze(1)
            z, y, x = self.coords[selected].unbind(1)
            tiles = tiles.index_put((z, y, x), field[selected.to(field.device)])
            dense = tiles.permute(3, 0, 4, 1, 5, 2, 6).reshape(
                channels, nz * BRICK, ny * BRICK, nx * BRICK
            )
            d, h, w = grid.shape
            volumes.append(dense[None, :, :d, :h, :w])
        return volumes

    def _entries(self, volume: Tensor | Sequence[Tensor], name: str) -> list[Tensor]:
        if isinstance(volume, Tensor):
            if volume.dim() != 5 or volume.shape[0] != self.batch_size:
                raise ValueError(
                    f"{name} must be (B, C, D, H, W) with B = {self.batch_size}, got "
                    f"{tuple(volume.shape)}"
                )
            entries = list(volume.unbind(0))
        else:
            entries = [check_tensor(v, f"{name}[{b}]") for b, v in enumerate(volume)]
            for b, entry in enumerate(entries):
                if entry.dim() == 5 and entry.shape[0] != 1:
                    raise ValueError(
                        f"{name}[{b}] must be one volume (1, C, D, H, W) or (C, D, H, W), got "
                        f"{tuple(entry.shape)}: a batch of {entry.shape[0]} for one entry")
            entries = [v[0] if v.dim() == 5 else v for v in entries]
            for b, entry in enumerate(entries):
                if (entry.dtype, entry.device) != (entries[0].dtype, entries[0].device):
                    raise MismatchError(
                        f"{name}[{b}] is {entry.dtype} on {entry.device} but {name}[0] is "
                        f"{entries[0].dtype} on {entries[0].device}: the entries of one packed "
                        "field must match"
                    )
            if len(entries) != self.batch_size:
                raise ValueError(
                    f"{name} must hold one volume per batch entry ({self.batch_size}), got "
                    f"{len(entries)}"
                )
        for b, (entry, grid) in enumerate(zip(entries, self.grids, strict=True)):
            if entry.dim() != 4 or tuple(entry.shape[1:]) != tuple(grid.shape):
                raise ValueError(
                    f"{name}[{b}] must be (C, {', '.join(map(str, grid.shape))}) on grid "
                    f"{b}, got {tuple(entry.shape)}"
                )
        return entries


def _integer_tensor(value: object, name: str) -> Tensor:
    """``value`` as an int64 tensor; ``TypeError`` naming ``name`` for floats or bools (a
    float brick coordinate would be truncated without a word)."""
    tensor = torch.as_tensor(value)
    if tensor.dtype == torch.bool or tensor.is_floating_point() or tensor.is_complex():
        raise TypeError(f"{name} must hold integers (brick coordinates and batch indices), got "
                        f"dtype {tensor.dtype}")
    return tensor.long()


def _pad_to_bricks(volume: Tensor, fill: str) -> Tensor:
    """``(C, D, H, W)`` padded at the far end of each axis to a multiple of 8."""
    for dim in (1, 2, 3):
        length = volume.shape[dim]
        missing = -length % BRICK
        if missing == 0:
            continue
        last = volume.narrow(dim, length - 1, 1)
        if fill in ("linear", "quadratic") and length > 1:
            slope = last - volume.narrow(dim, length - 2, 1)
            if fill == "quadratic" and length > 2:
                slope = 2.0 * slope - (volume.narrow(dim, length - 2, 1)
                                       - volume.narrow(dim, length - 3, 1))
            steps = torch.arange(1, missing + 1, dtype=volume.dtype, device=volume.device)
            shape = [1] * volume.dim()
            shape[dim] = missing
            extra = last + slope * steps.view(shape)
        else:
            extra = last.expand(*[missing if d == dim else -1 for d in range(volume.dim())])
        volume = torch.cat([volume, extra], dim=dim)
    return volume


def bricks_of_mask(masks: Sequence[Tensor], grids: Sequence[Grid]) -> BrickLayout:
    """The layout of the bricks that hold a node of each ``(D_b, H_b, W_b)`` bool (or uint8)
    mask, the shape of ``grids[b]``."""
    coords, batch = [], []
    if len(masks) != len(grids):
        raise ValueError(f"masks and grids must pair up, got {len(masks)} and {len(grids)}")
    for b, (mask, grid) in enumerate(zip(masks, grids, strict=True)):
        if not isinstance(mask, Tensor) or tuple(mask.shape) != tuple(grid.shape):
            shape = tuple(mask.shape) if isinstance(mask, Tensor) else type(mask).__name__
            raise ValueError(f"masks[{b}] must be a tensor of its grid's shape "
                             f"{tuple(grid.shape)}, got {shape}")
        if mask.dtype not in (torch.bool, torch.uint8):  # 0.5 and 256 cast to 0, unseen
            raise TypeError(f"masks[{b}] must be a bool (or uint8) tensor, got {mask.dtype} "
                            "(compare it, e.g. mask > 0)")
        padded = F.pad(mask.to(torch.uint8), _far_padding(mask.shape))
        nz, ny, nx = (n // BRICK for n in padded.shape)
        occupied = padded.view(nz, BRICK, ny, BRICK, nx, BRICK).amax(dim=(1, 3, 5)) > 0
        found = occupied.nonzero()
        coords.append(found)
        batch.append(torch.full((len(found),), b, dtype=torch.long))
    return BrickLayout(torch.cat(coords).cpu(), torch.cat(batch), grids)


def _far_padding(shape: Sequence[int]) -> tuple[int, ...]:
    pads = []
    for n in reversed(tuple(shape)):
        pads += [0, -n % BRICK]
    return tuple(pads)
