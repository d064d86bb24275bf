"""The heat semigroup ``exp(t Lap_S)`` on a surface's band, by Chebyshev expansion.

``u(t) = exp(t L) u0`` for each channel's own time, with ``L`` the divergence-form
Laplace–Beltrami (:func:`torchsurf.operators.functional.divergence_form`) evaluated on the
band, and the ring of nodes its stencils read around the band **re-extended from the band at
every application** by the tricubic closest-point stencil (:class:`CubicStencil`, unlimited so
that it is linear):

    L u = M W^-1 A E (M u),      M: the band mask,  A = W Lap_S (symmetric),  E: the re-extension.

Some ring nodes' closest-point taps land in the ring itself (10-20% of the ring on ``from_mesh``
phi, whose band is 3 cells wide; a few on analytic distances): ``E`` fills the ring from the band
and then sweeps over those nodes until their values settle (:class:`RingFill`), so that ``E``
reproduces constants. Reading the ring as zeros instead gave the ring values of 0.99-1.09 for a
constant 1, and ``exp(t L)`` of a constant left it by up to 25% (48^3 bunny, fandisk).

That is the operator the explicit flows integrate (their ring is re-extended at every
evaluation of the rate), so the result matches theirs; the symmetric alternatives were measured
and rejected (docs/learning.md): with the ring held fixed (a Dirichlet condition, the implicit
methods' choice within a step) the data at the band's edge drifts from the surface's values as
soon as the diffusion length exceeds a cell, and on the sphere the l = 1..4 harmonics at
``t = 10 h^2`` carry errors of 1-15% (against 0.2-0.5% re-extended).

``L`` is not self-adjoint; its transpose ``M E^T A W^-1 M`` is applied exactly (``E^T`` scatters
each ring node's value back to the nodes it was read from), so backward is the same Chebyshev
expansion run on the incoming gradient with ``L^T`` (:mod:`torchsurf.flows.chebyshev`). The real
parts of the spectrum of ``L`` lie within the Gershgorin bound ``rho`` of the band operator
(:func:`torchsurf.operators.laplace_beltrami_bound`) times :data:`BOUND_MARGIN`, but some
eigenvalues lie off the real axis (on a 13^3 sphere 366 of 1364 have ``|Im lambda| h^2 > 1e-3``,
up to 0.23, against ``rho h^2`` near 11): long times therefore run as powers of shorter
expansions (:data:`torchsurf.flows.chebyshev.PIECE_HALF_WIDTH`).

When ``phi`` does not require grad, ``L`` is a fixed sparse matrix: the expansion then runs on
the band's values alone, packed ``(band nodes, C, K)``, with ``A``, ``E`` and their transposes
assembled once per surface and kept on it (:class:`~torchsurf.flows._packed_band.PackedBand`;
equal to the volume operators to rounding). Its cost is that of the band and ring's nodes,
10-20% of the box at 64^3-128^3, where the volume operators run over the whole box or every
stored brick (``LearnedDiffusion`` at 64^3, batch 4, four channels: 0.5 s forward against 8.8 s).
A ``phi`` that requires grad runs the volume operators.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from .. import _memory, backend
from .._stack import caller_stacklevel
from ..operators import functional
from ..operators.spectrum import keep_laplace_beltrami_bound, laplace_beltrami_bound
from ..surface import ImplicitSurface
from . import chebyshev
from ._integrators import with_ring
from ._packed_band import Fill, PackedBand, PackedRegion
from ._reextension import check_reextension_width, kept_stencil, reextend
from .extension import BrickCubicStencil, CubicStencil, cubic_stencil

BOUND_MARGIN = 1.1
"""The expansion's interval is ``[-BOUND_MARGIN rho, 0]``: the re-extended ring makes ``L``
slightly non-normal, and the cost of the margin is ``sqrt(1.1)``, 5% more terms."""

Stencil = CubicStencil | BrickCubicStencil

PACKED_NODE_BYTES = 600
"""Bytes the packed operator keeps per node of the band and ring, about (float32: 556 and 574
measured on the 128^3 sphere and bunny, docs/benchmarks.md)."""

MAX_RING_SWEEPS = 32
"""Most sweeps over the ring nodes that read the ring (:class:`RingFill`). Each sweep shrinks the
change of a constant's ring values 15-300 times on the shared meshes at 32^3-64^3, so float32
settles in 3-6 sweeps and float64 in about twice as many."""

BAND_SHARE = 0.5
"""Least sum of the band taps' weights of a ring node that is re-extended from its closest
point (:class:`RingFill`); 0.93-1.09 on the shared meshes' ``from_mesh`` phi."""

SETTLED = 1e-6
"""A change of a constant's ring values below which sweeps that no longer shrink it stop
without a warning (:func:`_sweeps_to_settle`)."""


def _chained_nodes(first: Stencil, ring: Tensor, dtype: torch.dtype, path: str) -> Tensor:
    """The ring nodes whose taps read a ring node, a mask like ``ring``: after one pass of
    ``first`` over data that is NaN on the ring and zero elsewhere, the ring nodes still NaN."""
    with torch.no_grad():
        probe = torch.where(ring, torch.nan, 0.0).to(dtype)
        return ring & torch.isnan(first.apply(probe, path))


def _sweeps_to_settle(start: Callable[[Tensor, str], Tensor], chained: Stencil, band: Tensor,
                      dtype: torch.dtype, path: str) -> int:
    """Sweeps of ``chained`` after ``start`` (the band's values to the ring's first values)
    until the ring values of a constant change by at
    most four rounding units, or stop shrinking (a node whose closest point is itself, on a
    medial axis, reads itself with weight near 1 and keeps its value); warns if a change of more
    than :data:`SETTLED` is left."""
    with torch.no_grad():
        ones = torch.ones(band.shape, dtype=dtype, device=band.device)
        values = start(ones, path)
        change = torch.inf
        for sweep in range(1, MAX_RING_SWEEPS + 1):
            settled = chained.apply(values, path)
            change, last = float((settled - values).abs().max()), change
            values = settled
            if change <= 4.0 * torch.finfo(dtype).eps or (change > 0.5 * last
                                                          and change <= SETTLED):
                return sweep
    if change > SETTLED:
        warnings.warn(
            f"the ring's re-extension did not settle in {sweep} sweeps (last change "
            f"{change:.2g} on a constant): exp(t L) may not keep constants constant on this "
            "surface", RuntimeWarning, stacklevel=caller_stacklevel(),
        )
    return sweep


class RingFill:
    """``E M``: the band's values kept, the ring's re-extended from the band and ring along
    normals (linear tricubic closest-point stencils), the rest zero.

    The ring is first filled from the band with the ring read as zero; the ring nodes whose
    taps read ring nodes (``chained``) are then swept ``sweeps`` times, each sweep reading the
    values of the last, until a constant's ring values change by no more than rounding: the
    fixed point of re-extension on the ring, which reproduces constants. Ring nodes whose taps
    leave the band and ring, or whose band taps carry less than :data:`BAND_SHARE` of their
    weight (``orphans``: only where phi is not a distance, e.g. a saturated ``tanh(sdf / h)``,
    whose band reaches nodes with far closest points, some of which read only each other) take
    the mean of their 3x3x3 band neighbours and are not swept; they read zero before (a
    constant 0.7 diffused to [0.002, 0.707] on the 48^3 bunny's ``tanh(sdf / h)``).

    Args:
        surface: the implicit surface (batch 1 or B), or a brick surface.
        width: the band's half-width, world units.
        band, region: the band and the band with its ring, bool masks of the surface's storage.
        path: how the stencils run while the fill is assembled (:mod:`torchsurf.backend`; once
            per surface and width, by the first caller's path).

    Attributes:
        first: the stencil of every ring node.
        chained: the stencil of the ring nodes that read the ring, or ``None`` if none does.
        sweeps: the number of sweeps of ``chained``.
        orphans: the ring nodes ``first`` does not write, or ``None`` if there are none.
        neighbours: the number of band nodes among each node's 3x3x3 neighbours (at least 1),
            like the masks, or ``None`` without orphans.
    """

    def __init__(self, surface: ImplicitSurface, width: float, band: Tensor,
                 region: Tensor, path: str = "auto") -> None:
        self.band, self.layout = band, surface.layout
        ring = region & ~band
        self.first = kept_stencil(surface, width, "ring", ring, region, limited=False)
        dtype = surface.phi.dtype

        def assemble() -> tuple[Tensor | None, Tensor | None, Stencil | None, int]:
            """Host reads: computed once per surface and kept (``torch.compile`` then traces
            :meth:`apply` without a break)."""
            with torch.no_grad():  # a ring node the stencil drops keeps its input, 0
                from_band = self.first.apply(band.to(dtype), path)
            orphans = ring & (from_band < BAND_SHARE)
            self.orphans = orphans if bool(orphans.any()) else None
            self.neighbours = None if self.orphans is None else self._box_sum(
                band.to(dtype)).clamp(min=1.0)
            chained = _chained_nodes(self.first, ring, dtype, path) & ~orphans
            if not bool(chained.any()):
                return self.orphans, self.neighbours, None, 0
            stencil = cubic_stencil(surface, chained, limited=False, readable=region)
            return (self.orphans, self.neighbours, stencil,
                    _sweeps_to_settle(self._start, stencil, band, dtype, path))

        parts = (assemble() if surface.phi.requires_grad
                 else surface.kept(("ring fill", width), assemble))
        self.orphans, self.neighbours, self.chained, self.sweeps = parts

    def _in_place(self, x: Tensor) -> dict:
        """The sweeps write over their own (fresh) volume on dense storage outside autograd."""
        dense = isinstance(self.chained, CubicStencil)
        return {"in_place": True} if dense and not (
            torch.is_grad_enabled() and x.requires_grad) else {}

    def _box_sum(self, x: Tensor) -> Tensor:
        """The sum of ``x`` over each node's 3x3x3 neighbours (zero beyond the box or the
        stored bricks)."""
        if self.layout is None:
            return F.avg_pool3d(x, 3, stride=1, padding=1, count_include_pad=True) * 27.0
        return F.avg_pool3d(self.layout.halo(x, 1), 3, stride=1) * 27.0

    def _adopt_orphans(self, inside: Tensor, values: Tensor) -> Tensor:
        """``values`` with each orphan set to the mean of ``inside``'s band neighbours."""
        mean = self._box_sum(inside) / self.neighbours.to(inside.dtype)
        return torch.where(self.orphans, mean, values)

    def _adopted_transpose(self, g: Tensor) -> Tensor:
        """The transpose of :meth:`_adopt_orphans` (linear in both), by autograd: ``(gradient
        of inside, gradient of values)``."""
        with torch.enable_grad():
            inside = torch.zeros_like(g, requires_grad=True)
            values = torch.zeros_like(g, requires_grad=True)
            return torch.autograd.grad(self._adopt_orphans(inside, values), (inside, values), g)

    def _start(self, x: Tensor, path: str = "auto") -> Tensor:
        """The ring's values before the sweeps: ``first`` and the orphans' means."""
        inside = torch.where(self.band, x, x.new_zeros(()))
        values = self.first.apply(inside, path)
        return values if self.orphans is None else self._adopt_orphans(inside, values)

    def apply(self, x: Tensor, path: str = "auto") -> Tensor:
        """``E M x`` for ``x`` like the masks (``(B, C, D, H, W)`` or packed)."""
        values = self._start(x, path)
        options = self._in_place(values)
        for _ in range(self.sweeps):
            values = self.chained.apply(values, path, **options)
        return values

    def transpose(self, g: Tensor) -> Tensor:
        """``M E^T g``: the sweeps' transposes in reverse order, then the first pass's."""
        options = self._in_place(g)
        for sweep in range(self.sweeps):
            g = self.chained.transpose(g, **(options if sweep else {}))
        to_inside = None
        if self.orphans is not None:
            to_inside, g = self._adopted_transpose(g)
        g = self.first.transpose(g)
        if to_inside is not None:
            g = g + to_inside
        return torch.where(self.band, g, g.new_zeros(()))


class BandLaplacian:
    """``L`` of the module docstring on one surface: ``apply``, ``transpose`` and its bound.

    On a :class:`~torchsurf.bricks.BrickSurface` every field is packed ``(N, C, 8, 8, 8)``:
    ``A`` reads the haloed bricks, ``E`` and ``E^T`` are the :class:`BrickCubicStencil`'s, and
    a batch of several entries shares one bound (the largest entry's: each entry's result is
    its own ``exp(t L)`` to the expansion's tolerance).

    Args:
        surface: the implicit surface (batch 1 or B), or a brick surface.
        scheme: ``"octant"`` (default), ``"symmetric"`` or ``"conservative"``.
        band_width: half-width of the band, world units (default ``surface.band_width``).
        path: how the stencils run (:mod:`torchsurf.backend`).

    Attributes:
        band: ``(B or 1, 1, D, H, W)`` (or packed ``(N, 1, 8, 8, 8)``) bool, the nodes that
            evolve.
        region: the band and its ring (the nodes the result is written to).
        ring: the ring's re-extension from the band, ``E M`` (:class:`RingFill`).
        extension: the limited closest-point stencil of the whole region (the flows' own), which
            re-extends the result (:func:`heat_semigroup`).
        bound: ``BOUND_MARGIN`` times the Gershgorin bound of ``Lap_S`` on the band,
            ``1 / world length^2``.
    """

    def __init__(self, surface: ImplicitSurface, scheme: str = "octant",
                 band_width: float | None = None, path: str = "auto") -> None:
        if scheme not in functional.SCHEMES:
            raise ValueError(
                f"scheme must be one of {functional.SCHEMES} (the divergence forms), got {scheme!r}"
            )
        width = surface.band_width if band_width is None else float(band_width)
        check_reextension_width(width, surface.spacing)  # the ring is re-extended each time
        surface.check_band_held(width, "band_width")
        self.surface, self.scheme, self.path, self.width = surface, scheme, path, width
        self.band = surface.band_mask(width)
        self.region = with_ring(self.band, surface.layout)
        # the region's stencil first: the ring's takes its rows (kept_stencil)
        self.extension = kept_stencil(surface, width, "region", self.region, self.region,
                                      limited=True)
        self.ring = RingFill(surface, width, self.band, self.region, path)
        self.packed()  # before the bound: its rows give it (kept_packing)
        self.bound = BOUND_MARGIN * laplace_beltrami_bound(surface, scheme, width)

    def packed(self) -> PackedBand | None:
        """The operator on packed band values (:class:`~torchsurf.flows._packed_band.PackedBand`),
        assembled once and kept on the surface (at construction, before the bound, which its
        rows give: a ``BandLaplacian`` applied through volumes alone pays it too); ``None``
        when ``phi`` requires grad (the operator's weights are then in its graph), where
        compiled volume stencils are asked for (``path="compiled"``, or ``"auto"`` under
        ``TORCHSURF_COMPILE=always``), or when its matrices would not fit in a quarter of the
        memory available (:data:`PACKED_NODE_BYTES`)."""
        if self.differentiable or self.path == "compiled" or (
                self.path == "auto" and backend.COMPILE == "always"):
            return None
        return self.surface.kept(("packed band laplacian", self.scheme, self.width),
                                 self._assemble_packed)

    def _assemble_packed(self) -> PackedBand | None:
        """The packed operator, or ``None`` (the volume path, kept as the choice) when its
        matrices would not fit (:func:`fits_packed`)."""
        packing = kept_packing(self.surface, self.scheme, self.width, self.band, self.region)
        return None if packing is None else PackedBand(packing, self.ring)

    @property
    def differentiable(self) -> bool:
        """The geometry is in ``phi``'s graph (``phi`` requires grad)."""
        return self.surface.phi.requires_grad

    def _weighted(self, x: Tensor) -> Tensor:
        """``A x = W Lap_S x`` (symmetric negative semi-definite)."""
        surface = self.surface
        return functional.divergence_form(
            x, surface.normal, surface.weight, surface.spacing, self.scheme, self.path,
            weighted=True, haloed=surface.haloed(),
            pad=None if surface.layout is None else surface.layout.halo,
        )

    def apply(self, x: Tensor) -> Tensor:
        """``L x = M W^-1 A E (M x)`` for ``x`` ``(B, C, D, H, W)``."""
        image = self._weighted(self.ring.apply(x, self.path)) / self.surface.weight
        return torch.where(self.band, image, x.new_zeros(()))

    def transpose(self, g: Tensor) -> Tensor:
        """``L^T g = M E^T A W^-1 (M g)`` (``A`` symmetric)."""
        inside = torch.where(self.band, g / self.surface.weight, g.new_zeros(()))
        return self.ring.transpose(self._weighted(inside))


def fits_packed(region: Tensor) -> bool:
    """Whether packed matrices of the band and ring ``region`` (a bool mask) take at most a
    quarter of the memory available (:data:`PACKED_NODE_BYTES` a node)."""
    available = _memory.available_bytes(region.device)
    return available is None or int(region.sum()) * PACKED_NODE_BYTES <= available / 4


def kept_packing(surface: ImplicitSurface, scheme: str, width: float, band: Tensor,
                 region: Tensor) -> PackedRegion | None:
    """The band of half-width ``width`` and its ring packed, with ``W^-1 A`` of ``scheme``
    (:class:`~torchsurf.flows._packed_band.PackedRegion`), assembled once and kept on the
    surface (shared by the heat semigroup and the heat flow), or ``None`` when it would not fit
    (:func:`fits_packed`). The rows it forms give the band's Gershgorin bound too, which it
    keeps for :func:`~torchsurf.operators.laplace_beltrami_bound`: asked for first, the packing
    spares the bound its own pass over the rows."""
    packing = surface.kept(
        ("packed region", scheme, width),
        lambda: PackedRegion(surface, scheme, band, region) if fits_packed(region) else None)
    if packing is not None:
        keep_laplace_beltrami_bound(surface, scheme, width, packing.band_bound)
    return packing


class _Extend(torch.autograd.Function):
    """``E x`` for a linear stencil ``E`` with fixed weights (a :class:`CubicStencil` or a
    :class:`RingFill`); backward ``E^T g``, nothing saved (autograd through the gather would
    keep 64 values per node)."""

    @staticmethod
    def forward(ctx, stencil, x, path="auto"):  # noqa: ANN001, ANN205
        ctx.stencil, ctx.batch = stencil, x.shape[0]
        return stencil.apply(x, path)

    @staticmethod
    @backend.part_of_recorded
    def backward(ctx, grad_output):  # noqa: ANN001, ANN205
        grad = ctx.stencil.transpose(grad_output)
        return None, grad if grad.shape[0] == ctx.batch else grad.sum(dim=0, keepdim=True), None


def _first_band_values(u: Tensor, band: Tensor, entries: Tensor | None = None,
                       count: int = 0) -> Tensor:
    """``u``'s values ``(B, C, 1, ...)`` at the first node of ``band`` (bool, broadcastable to
    ``u``'s first channel) of each row's entry, read without a host sync: ``entries`` ``(B,)``
    names the entry, of ``count``, of each row (a brick's shape); ``None`` makes each row its
    own. Node 0 of an entry with no band node."""
    rows, channels = u.shape[:2]
    mask = band.expand(rows, 1, *u.shape[2:]).reshape(rows, -1)
    first = mask.to(torch.uint8).argmax(dim=1).view(rows, 1, 1).expand(rows, channels, 1)
    values = u.reshape(rows, channels, -1).gather(2, first)
    if entries is not None:  # each row takes its entry's first row holding band nodes
        index = torch.arange(rows, device=u.device)
        held = torch.where(mask.any(dim=1), index, rows)
        firsts = torch.full((count,), rows, dtype=torch.long, device=u.device)
        firsts = firsts.scatter_reduce(0, entries, held, "amin")
        values = values.index_select(0, torch.where(firsts < rows, firsts, 0)[entries])
    return values.view(rows, channels, *([1] * (u.dim() - 2)))


def _ring_within_band_range(u: Tensor, band: Tensor, region: Tensor, entries: Tensor | None,
                            count: int) -> Tensor:
    """``u`` ``(B, C, D, H, W)`` with its ring nodes (``region & ~band``) clamped to the range
    of the band's values of their row's entry (per channel): ``entries`` ``(B,)`` names the
    entry, of ``count``, of each row (a brick's shape); ``None`` makes each row its own. The
    ring's unlimited fill overshoots rough data (fandisk ``from_mesh`` at 48^3: ring values up
    to 1.066 from data in ``[0, 1)``), and the limited re-extension that reads it took its
    bounds from there (1.0167 at 1e-6 h^2)."""
    inside = band.expand_as(u)
    low = torch.where(inside, u, math.inf).amin(dim=(2, 3, 4))
    high = torch.where(inside, u, -math.inf).amax(dim=(2, 3, 4))
    if entries is not None:
        index = entries.view(-1, 1).expand_as(low)
        low = low.new_full((count, u.shape[1]), math.inf).scatter_reduce(
            0, index, low, "amin").index_select(0, entries)
        high = high.new_full((count, u.shape[1]), -math.inf).scatter_reduce(
            0, index, high, "amax").index_select(0, entries)
    shape = (*low.shape, 1, 1, 1)
    clamped = torch.minimum(torch.maximum(u, low.view(shape)), high.view(shape))
    return torch.where(region & ~band, clamped, u)


def heat_semigroup(u0: Tensor, operator: BandLaplacian, times: Tensor,
                   largest: float | None = None, extend_first: bool = False) -> Tensor:
    """``exp(t_c L) u0`` per channel on the band, then re-extended along normals.

    As the flows do after each step, the result is re-extended from its values near S to the
    whole band and its ring (the tricubic closest-point stencil, limited to the range of each
    point's cell as the flows' is), so that it is constant along the normals: every level set
    in the band carries the surface's solution, and the re-extension creates no new extremum
    (unlimited, it overshot rough data by 5-8% at short times on the 48^3 bunny and fandisk).
    The ring it reads is filled by the expansion's own linear (unlimited) fill, its values
    clamped to the range of their entry's band values first (they reached 1.066 from data in
    ``[0, 1)`` on fandisk's 48^3 ``from_mesh`` phi, and the result 1.0167 at 1e-6 h^2).

    Args:
        u0: ``(B, C, D, H, W)``; only its band values are read.
        operator: the band's :class:`BandLaplacian`.
        times: ``(C,)`` or ``()``, positive, world units squared (may require grad).
        largest: a float no smaller than any of ``times``: the expansion's terms are counted
            for it on the host, and nothing is read from ``times`` (``torch.compile`` traces the
            call whole). ``None``: counted for the largest of ``times``, read on the host (a
            graph break).
        extend_first: re-extend ``u0`` along the normals first (its values near S to the
            whole band), so that the result reads ``u0`` near S only. A stepping flow
            re-extends within about a cell-crossing time; one expansion spans its whole time,
            and from data varying along the normals (``sin 2x cos y + ...`` on a sphere at
            32^3, ``5 h^2``) it read the data off S into the result: 2.8e-3 of the range off
            (``LearnedDiffusion``: 1.1e-2) against 7.6e-5 for RKC (an audit, 2026-12-07).

    Returns:
        ``(B, C, D, H, W)``: the band and its ring hold ``u(t)`` (constant along normals),
        other nodes ``u0``'s values.
        Gradients reach ``u0``'s band values, ``times`` and (by recomputation) ``phi``.
    """
    packed = operator.packed()
    if packed is not None:
        # expanded and filled about each entry's first band node's values, which both keep
        # (L annihilates constants, the ring's weights sum to 1): a constant stays one to the
        # last bit, where the float32 sums of the coefficients and weights are 1 only to a
        # few ulps; large offsets lose less. The offsets are detached: the map keeps
        # constants, so their gradient is zero, which float32 sums left at 1e-3 at each first
        # node
        region = packed.packing
        values = (region.stencil(operator.extension).apply(region.pack_region(u0))
                  [:region.band_count] if extend_first else packed.pack(u0))
        offsets = values.detach()
        result = chebyshev.expansion(
            packed.apply, values - region.entry_offsets(offsets, len(values)), times,
            operator.bound, adjoint=packed.transpose, largest=largest,
        )
        # the final re-extension on packed values too: the region's limited stencil as a
        # PackedStencil (half the layer's training iteration when it gathered volumes)
        filled = region.ring_within_band_range(Fill.apply(packed, result)
                                               + region.entry_offsets(offsets))
        extended = packed.unpack(packed.packing.stencil(operator.extension).apply(filled), u0)
        return torch.where(operator.region, extended, u0)
    # data of batch 1 on a surface of batch B: B entries, as on packed values
    u0 = u0.expand(max(u0.shape[0], operator.band.shape[0]), *u0.shape[1:])
    if extend_first:
        u0 = torch.where(operator.region, reextend(operator.extension, u0, operator.path), u0)
    layout = operator.surface.layout  # a brick's entry is its shape's, as on packed values
    entries = None if layout is None else layout.batch.to(u0.device)
    offset = _first_band_values(u0.detach(), operator.band, entries,
                                0 if layout is None else len(layout.grids))
    inside = torch.where(operator.band, u0 - offset, u0.new_zeros(()))
    result = chebyshev.expansion(
        operator.apply, inside, times, operator.bound, adjoint=operator.transpose,
        differentiable_operator=operator.differentiable, reads=(operator.surface.phi,),
        largest=largest,
    )
    if operator.differentiable:
        filled = operator.ring.apply(result, operator.path) + offset
    else:
        filled = _Extend.apply(operator.ring, result, operator.path) + offset
    filled = _ring_within_band_range(filled, operator.band, operator.region, entries,
                                     0 if layout is None else len(layout.grids))
    extended = reextend(operator.extension, filled, operator.path)
    return torch.where(operator.region, extended, u0)
