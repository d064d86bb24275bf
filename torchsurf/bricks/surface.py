"""``BrickSurface``: an implicit surface whose fields are stored as the bricks of its band."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .._checks import MismatchError, check_entry, check_finite, check_positive, check_tensor
from .._inference import outside_inference
from .._transforms import refuse_vmapped_phi
from ..grid import Grid
from ..sampling import weighted_taps
from ..surface import CROSSING_CELLS, ImplicitSurface, check_eps
from .layout import BRICK, BrickLayout

STENCIL_REACH = 2
"""Nodes, along each axis, that the operators read around a band node they update (the
compiled flux forms read ``u`` two nodes away, the normals one node away read ``phi`` one
further). Band nodes closer than this to a brick that is not stored are left out of the band."""

ONCE = "slicing"
"""The path of the halos a surface forms once (of ``phi``, its inside mask, its normals and
weight): eager, since compiling the gather costs seconds that one call never pays back."""


class BrickSurface(ImplicitSurface):
    """The zero level set of ``phi`` stored as 8^3 bricks around it (:mod:`torchsurf.bricks`).

    The same surface as :class:`~torchsurf.ImplicitSurface` of the dense ``phi`` — same normals,
    weight ``W``, band and curvatures at every stored node, to rounding — with every field packed
    ``(N, C, 8, 8, 8)`` on :attr:`layout`: memory and work grow with the surface's area, not with
    its box, and shapes on boxes of different sizes share a batch (a batch index per brick).
    Laplace–Beltrami, curvature, closest-point re-extension and :class:`~torchsurf.flows.HeatFlow`
    run on it (docs/bricks.md lists what does).

    Build it with :func:`torchsurf.bricks.from_dense` or :func:`torchsurf.bricks.from_mesh`,
    which store every node that the band's stencils read and check that the band stays
    :data:`STENCIL_REACH` nodes inside each grid's box (bricks have no box faces to stop the
    flux at).

    Args:
        phi: ``(N, 1, 8, 8, 8)`` packed on ``layout``, world units, negative inside.
        layout: the bricks.
        band_width: half-width of the band, world units (default ``3 * spacing``).
        eps: as in :class:`~torchsurf.ImplicitSurface`.
        evolving_widths: half-width, world units, of the band flows evolve on by default
            (:meth:`evolving_widths`), one per batch entry or one for all, each at least
            ``band_width``; the bricks must store every node that band's stencils read.
            Default ``band_width``. :func:`~torchsurf.bricks.from_dense` passes the dense
            surface's (wider where ``phi`` is a distance).

    Attributes:
        phi, grad_norm, normal, weight: as in :class:`~torchsurf.ImplicitSurface`, packed
            ``(N, K, 8, 8, 8)``.
        gradient_scale: the median ``|grad phi|`` on S of each brick's batch entry,
            ``(N, 1, 1, 1, 1)``.
    """

    def __init__(self, phi: Tensor, layout: BrickLayout, band_width: float | None = None,
                 eps: float = 1e-6, evolving_widths: float | Sequence[float] | None = None
                 ) -> None:
        torch.nn.Module.__init__(self)
        if not isinstance(layout, BrickLayout):
            raise TypeError(f"layout must be a torchsurf.bricks.BrickLayout, got "
                            f"{type(layout).__name__}")
        check_tensor(phi, "phi")
        refuse_vmapped_phi(phi, "BrickSurface")
        layout.check_field(phi, "phi")
        if phi.shape[1] != 1:
            raise ValueError(f"phi must have 1 channel, got shape {tuple(phi.shape)}")
        check_finite(phi, "phi")
        self.layout = layout.to(phi.device)
        self.band_width = check_positive(
            3.0 * layout.spacing if band_width is None else band_width, "band_width"
        )
        self.eps = check_eps(eps)
        self._evolving = self._checked_widths(evolving_widths, layout.batch_size)
        self._assemble_kept(phi)

    def _checked_widths(self, widths: float | Sequence[float | None] | None,
                        count: int) -> tuple[float | None, ...]:
        """One width per entry, ``None`` for ``band_width`` (which it then follows)."""
        if widths is None:
            return (None,) * count
        if not isinstance(widths, (list, tuple)):
            widths = (widths,) * count
        if len(widths) != count:
            raise ValueError(f"evolving_widths must hold one width per batch entry ({count}), "
                             f"got {len(widths)}")
        widths = tuple(None if w is None else check_positive(w, "evolving_widths")
                       for w in widths)
        narrowest = min((w for w in widths if w is not None), default=self.band_width)
        if narrowest < self.band_width:
            raise ValueError(f"evolving_widths must be at least band_width={self.band_width:g}, "
                             f"got {narrowest:g}")
        return tuple(None if w == self.band_width else w for w in widths)

    def evolving_widths(self) -> tuple[float, ...]:
        """Half-width, world units, of the band flows evolve on by default, one per batch
        entry: what the constructor was given (:func:`~torchsurf.bricks.from_dense` stores
        the dense surface's :meth:`~torchsurf.ImplicitSurface.evolving_widths`), and never
        less than ``band_width`` (a wider ``band_width`` set later)."""
        return tuple(self.band_width if w is None else max(w, self.band_width)
                     for w in self._evolving)

    def _reassemble(self) -> None:
        self.layout = self.layout.to(self.phi.device)  # its tables are not buffers
        self._forget_stencilled()  # kept in the former place
        super()._reassemble()

    def _forget_stencilled(self) -> None:
        for key in [key for key in self.__dict__ if key.startswith("_stencilled_")]:
            del self.__dict__[key]

    @property
    def band_width(self) -> float:
        """Half-width of the band, world units. Setting it drops what was kept for the former
        width; a width beyond the band the bricks were built for (and the flows' bands they
        store) is refused where it would leave out nodes within it of S (:meth:`check_band_held`)."""
        return self._band_width

    @band_width.setter
    def band_width(self, value: float) -> None:
        value = check_positive(value, "band_width")
        if "phi" in self._buffers:  # not while the constructor sets it
            self.check_band_held(value, "band_width")
        ImplicitSurface.band_width.fset(self, value)

    def _forget_kept(self) -> None:
        self.__dict__.pop("_entries", None)  # built with the former width
        super()._forget_kept()

    def _assemble(self, phi: Tensor) -> None:
        self.__dict__.pop("_entries", None)  # built on the former phi
        super()._assemble(phi)

    def _placement(self) -> dict:
        layout = self.layout
        return {"coords": layout.coords.cpu(), "batch": layout.batch.cpu(),
                "grids": [(g.shape, g.spacing, g.origin) for g in layout.grids],
                "evolving_widths": list(self.evolving_widths())}

    def set_extra_state(self, state: dict) -> None:
        """As :meth:`ImplicitSurface.set_extra_state`, with the bricks and the flows' band
        widths (``band_width`` for a state saved without them)."""
        super().set_extra_state(state)
        self._evolving = self._checked_widths(state.get("evolving_widths"), self.batch_size)

    def _place(self, state: dict) -> None:
        layout, grids = self.layout, tuple(Grid(*grid) for grid in state["grids"])
        coords, batch = state["coords"], state["batch"]
        if (grids != layout.grids or not torch.equal(coords, layout.coords.cpu())
                or not torch.equal(batch, layout.batch.cpu())):
            self.layout = BrickLayout(coords, batch, grids).to(self.phi.device)
            self._forget_stencilled()  # the former layout's

    @property
    def grids(self) -> tuple[Grid, ...]:
        """One grid per batch entry."""
        return self.layout.grids

    @property
    def grid(self) -> Grid:
        """The grid of a single-entry surface (a batch of several has :attr:`grids`)."""
        if self.layout.batch_size != 1:
            raise ValueError(
                f"this BrickSurface holds {self.layout.batch_size} entries, each on its own grid: "
                "use surface.grids"
            )
        return self.layout.grids[0]

    @grid.setter
    def grid(self, value: Grid) -> None:
        ImplicitSurface.grid.fset(self, value)  # refused once built

    @property
    def batch_size(self) -> int:
        """Number of batch entries ``B`` (shapes), whatever the number of bricks."""
        return self.layout.batch_size

    @property
    def spacing(self) -> float:
        """The spacing ``h`` every entry shares, world units."""
        return self.layout.spacing

    def _pad(self, volume: Tensor, mode: str) -> Tensor:
        """The neighbours' values: bricks have no box faces, so ``mode`` has nothing to say
        (the builders keep the band away from them). Eager: ``phi`` is haloed once per surface,
        where compiling the gather on a 512^3 build cost 3-7 s."""
        return self.layout.halo(volume, 1, ONCE)

    def _haloed_geometry(self) -> tuple[Tensor, Tensor]:
        return self.layout.halo(self.normal, 1, ONCE), self.layout.halo(self.weight, 1, ONCE)

    def _crossing_nodes(self, phi: Tensor) -> Tensor:
        inside = phi < 0
        haloed = self.layout.halo(inside, 1, ONCE)
        crossing = torch.zeros_like(inside)
        core = slice(1, 1 + BRICK)
        for axis in range(3):
            for shift in (0, 2):
                window = [core, core, core]
                window[axis] = slice(shift, shift + BRICK)
                crossing |= haloed[:, :, window[0], window[1], window[2]] != inside
        return crossing & self._stencilled(1)

    def _entry_max(self, values: Tensor) -> Tensor:
        return self.layout.entry_max(values)

    def _gradient_scale(self, crossing: Tensor, values: Tensor) -> Tensor:
        batch = self.layout.batch.to(values.device)
        scales = []
        for b in range(self.layout.batch_size):
            entry = values[crossing & (batch == b).view(-1, 1, 1, 1, 1)]
            if entry.numel() == 0:
                raise ValueError(
                    f"phi has no zero crossing in batch entry {b}: every entry must be negative "
                    "somewhere (inside) and positive somewhere (outside)"
                )
            scales.append(entry.median())
        return torch.stack(scales)[batch].view(-1, 1, 1, 1, 1)

    def band_mask(self, width: float | None = None) -> Tensor:
        """Nodes within ``width`` of S (default ``band_width``), ``(N, 1, 8, 8, 8)``.

        Only nodes inside their box whose neighbours within :data:`STENCIL_REACH` are stored
        count: the builders store all of them around the band they were asked for.
        """
        return super().band_mask(width) & self._stencilled(STENCIL_REACH)

    def _near_crossing(self, cells: int) -> Tensor:
        """The dense surface's limit (:meth:`ImplicitSurface.band_mask`): the crossing nodes
        grown by ``cells`` 3x3x3 dilations across the stored bricks (eager halos: formed once);
        kept per ``cells``."""

        def grow() -> Tensor:
            near = self._crossing_nodes(self.phi.detach())
            if cells >= CROSSING_CELLS:  # the dense count's cap: every node
                return torch.ones_like(near)
            for _ in range(cells):
                near = self.layout.dilate(near, ONCE)
            return near

        return self.kept(("near crossing", cells), grow)

    def _stencilled(self, cells: int) -> Tensor:
        """Nodes inside their box whose neighbours within ``cells`` are all stored."""
        key = f"_stencilled_{cells}"
        if key not in self.__dict__:
            mask = self.layout.inside & self.layout.interior(cells)
            self.__dict__[key] = mask.to(self.phi.device)
        return self.__dict__[key]

    def check_field(self, value: object, name: str, channels: int | None = None) -> Tensor:
        """``value`` checked as a packed field on this surface: ``(N, C, 8, 8, 8)``."""
        field = check_tensor(value, name)
        self.layout.check_field(field, name)
        if channels is not None and field.shape[1] != channels:
            raise ValueError(f"{name} must have {channels} channels, got shape {tuple(field.shape)}")
        if field.shape[1] == 0:
            raise ValueError(f"{name} must have at least one channel, got shape "
                             f"{tuple(field.shape)}")
        return field

    def entries(self) -> list[tuple[Tensor, BrickSurface]]:
        """Each batch entry alone: ``(rows, surface)``, ``rows`` ``(N_b,)`` its bricks' rows in
        the packed fields. Kept (not when ``phi`` requires grad: then rebuilt per call)."""
        if self.batch_size == 1:
            return [(torch.arange(len(self.layout), device=self.phi.device), self)]
        cached = self.__dict__.get("_entries")
        if cached is not None:
            return cached
        batch = self.layout.batch
        parts = []
        widths = self.evolving_widths()
        with outside_inference():  # kept: an evaluation's rows must serve a training call
            for b, grid in enumerate(self.grids):
                rows = (batch == b).nonzero().squeeze(1)
                layout = BrickLayout(self.layout.coords[rows].cpu(),
                                     torch.zeros(len(rows), dtype=torch.long), [grid])
                rows = rows.to(self.phi.device)
                parts.append((rows, BrickSurface(self.phi[rows], layout, self.band_width,
                                                 self.eps, widths[b])))
        if not self.phi.requires_grad:
            self.__dict__["_entries"] = parts
        return parts

    def sample(self, field: Tensor, points: Tensor, entry: int = 0) -> Tensor:
        """Trilinear interpolation of a packed ``field`` at world ``points`` of batch ``entry``:
        the numbers :func:`torchsurf.sample` gives on the dense volume.

        Args:
            field: ``(N, C, 8, 8, 8)``.
            points: ``(V, 3)`` world ``(x, y, z)``, same dtype and device as ``field``; each
                point's 8 surrounding nodes must be stored (points near S are).
            entry: the batch entry the points belong to.

        Returns:
            ``(C, V)``; differentiable in ``field`` and ``points``.

        Raises:
            ValueError: a point lies outside the entry's box or next to a brick that is not
                stored.
        """
        self.check_field(field, "field")
        entry = self._check_points(points, entry)
        _check_like_field(points, "points", field)
        grid = self.grids[entry]
        return self._sample(field, grid.world_to_index(points), entry,
                            grid.world_rounding(points.dtype), shown=points)

    def sample_at_index(self, field: Tensor, index: Tensor, entry: int = 0) -> Tensor:
        """:meth:`sample` at continuous node indices ``index`` ``(V, 3)`` ``(i, j, k)`` of the
        entry's grid instead of world points (no rounding of world coordinates: a grid far
        from the origin keeps float32's precision). Returns ``(C, V)``."""
        self.check_field(field, "field")
        entry = self._check_points(index, entry, "index")
        _check_like_field(index, "index", field)
        return self._sample(field, index, entry, name="index")

    def _sample(self, field: Tensor, index: Tensor, entry: int, slack: float = 0.0,
                name: str = "points", shown: Tensor | None = None) -> Tensor:
        """:meth:`sample_at_index` of checked arguments, the box widened by ``slack`` cells;
        ``name`` is what the caller called the points, ``shown`` what to quote of them in an
        error (``index`` by default)."""
        inside, fraction, corners = self._cell_corners(index, entry, slack)
        shown = index if shown is None else shown
        if not bool(inside.all()):
            raise ValueError(_some_points(name, ~inside, shown) + " lie outside the box of "
                             f"entry {entry} ({self.grids[entry]})")
        unstored = torch.zeros_like(inside)
        for _, brick, _ in corners:
            unstored |= brick < 0
        if bool(unstored.any()):
            raise ValueError(_some_points(name, unstored, shown) + " lie next to a brick that "
                             "is not stored (farther from S than the band and its reach)")
        flat = field.transpose(0, 1).reshape(field.shape[1], -1)
        weights = [torch.where(offset.bool(), fraction, 1 - fraction).prod(dim=1)
                   for offset, _, _ in corners]

        def summed(product: Callable[[Tensor, Tensor], Tensor]) -> Tensor:
            value = None
            for (_, _, source), weight in zip(corners, weights, strict=True):
                term = product(flat[:, source], weight)
                value = term if value is None else value + term
            return value

        value = summed(torch.mul)
        if bool(torch.isfinite(value.detach()).all()):
            return value
        # read, or at a tap of weight 0 (sampling.weighted_taps)?
        largest = max(self.grids[entry].shape) - 1
        return summed(lambda values, weight: weighted_taps(values, weight, largest))

    def samplable(self, points: Tensor, entry: int = 0) -> Tensor:
        """``(V,)`` bool: ``points`` ``(V, 3)`` (world ``(x, y, z)``) that :meth:`sample` can
        read, inside the entry's box with the 8 nodes of their cell stored."""
        entry = self._check_points(points, entry)
        grid = self.grids[entry]
        return self._samplable(grid.world_to_index(points), entry,
                               grid.world_rounding(points.dtype))

    def samplable_at_index(self, index: Tensor, entry: int = 0) -> Tensor:
        """:meth:`samplable` at continuous node indices ``index`` ``(V, 3)`` ``(i, j, k)`` of
        the entry's grid (:meth:`sample_at_index`)."""
        entry = self._check_points(index, entry, "index")
        return self._samplable(index, entry)

    def _samplable(self, index: Tensor, entry: int, slack: float = 0.0) -> Tensor:
        inside, _, corners = self._cell_corners(index, entry, slack)
        for _, brick, _ in corners:
            inside = inside & (brick >= 0)
        return inside

    def check_band_held(self, width: float, name: str = "width") -> None:
        """Raise ``ValueError`` naming ``name`` where :meth:`band_mask` of ``width`` leaves out
        nodes within ``width`` of S that it would hold with the bricks around them stored: a
        ``width`` beyond the band the bricks were built for, whose outer nodes would keep
        their values in an extension. (Nodes whose direct neighbours are not stored either
        have no distance to test; a wider band always leaves out some of the former.)"""
        if width <= min(self.evolving_widths()):  # stored by the builder for every entry
            return

        def count() -> list[int]:
            measurable = ImplicitSurface.band_mask(self, width) & self._stencilled(1)
            per_brick = (measurable & ~self.band_mask(width)).flatten(1).sum(dim=1)
            return torch.zeros(self.batch_size, dtype=torch.long).index_add_(
                0, self.layout.batch.cpu(), per_brick.cpu()).tolist()

        left_out = count() if self.phi.requires_grad else self.kept(("left out", width), count)
        if any(left_out):
            entries = ", ".join(f"{n} of entry {b}" for b, n in enumerate(left_out) if n)
            where = "" if self.batch_size == 1 else f" ({entries})"
            raise ValueError(
                f"{name}={width:g} reaches {sum(left_out)} nodes within it of S{where} whose "
                f"neighbours this BrickSurface does not store (its bricks hold a narrower band): "
                f"build it with torchsurf.bricks.from_dense or from_mesh at band_width >= "
                f"{width:g}"
            )

    def _check_points(self, points: Tensor, entry: int, name: str = "points") -> int:
        """Check ``points`` ``(V, 3)`` and return ``entry`` as an ``int`` (numpy and 0-d
        integer tensors too)."""
        check_tensor(points, name)
        if points.dim() != 2 or points.shape[1] != 3:
            raise ValueError(f"{name} must have shape (V, 3), got {tuple(points.shape)}")
        check_finite(points.detach(), name)
        return check_entry(entry, self.batch_size)

    def _cell_corners(self, index: Tensor, entry: int, slack: float = 0.0
                      ) -> tuple[Tensor, Tensor, list[tuple[Tensor, Tensor, Tensor]]]:
        """For continuous node indices ``index`` ``(V, 3)`` of ``entry``: inside its box
        ``(V,)``, the fraction ``(V, 3)`` within the cell (points outside clamped to the box),
        and per corner of the cell its offset ``(3,)``, brick row ``(V,)`` (-1: not stored)
        and packed node ``(V,)``."""
        grid = self.grids[entry]
        inside = grid.contains_index(index.detach(), tolerance=1e-4 + slack)
        high = torch.tensor(grid.shape[::-1], dtype=index.dtype, device=index.device) - 1
        index = torch.minimum(index.clamp(min=0), high)
        low = index.detach().floor().clamp(max=high - 1).long()
        lookup = self.layout.lookup.to(index.device)
        corners = []
        for corner in range(8):
            offset = torch.tensor([corner & 1, (corner >> 1) & 1, corner >> 2],
                                  device=index.device)
            x, y, z = (low + offset).unbind(1)
            brick = lookup[entry, z // BRICK, y // BRICK, x // BRICK]
            source = brick * BRICK**3 + (z % BRICK) * BRICK * BRICK + (y % BRICK) * BRICK \
                + x % BRICK
            corners.append((offset, brick, source))
        return inside, index - low, corners

    def to_dense(self, field: Tensor, fill: float = 0.0) -> list[Tensor]:
        """One dense ``(1, C, D_b, H_b, W_b)`` volume per entry (:meth:`BrickLayout.to_dense`)."""
        return self.layout.to_dense(field, fill)

    def from_dense(self, volume: Tensor | list[Tensor]) -> Tensor:
        """Dense data ``(B, C, D, H, W)`` or one volume per entry, packed ``(N, C, 8, 8, 8)``."""
        return self.layout.from_dense(volume)

    def extra_repr(self) -> str:
        return (f"bricks={len(self.layout)}, batch_size={self.batch_size}, "
                f"spacing={self.spacing:g}, band_width={self.band_width:g}, eps={self.eps:g}")


def _check_like_field(points: Tensor, name: str, field: Tensor) -> None:
    if points.dtype != field.dtype or points.device != field.device:
        raise MismatchError(
            f"{name} ({points.dtype}, {points.device}) must have the dtype and device of "
            f"field ({field.dtype}, {field.device})"
        )


def _some_points(name: str, which: Tensor, shown: Tensor) -> str:
    """``"points: 3 of 40, e.g. points[7] = [x, y, z],"`` for the points ``which`` ``(V,)``
    (bool) of ``shown`` ``(V, 3)``, the start of an error that names them."""
    first = int(which.nonzero()[0, 0])
    values = ", ".join(f"{float(v):.6g}" for v in shown[first].detach())
    return (f"{name}: {int(which.sum())} of {len(which)}, e.g. {name}[{first}] = "
            f"[{values}],")
