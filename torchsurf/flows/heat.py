"""Intrinsic heat flow ``u_t = D (1/W) div(W P grad u)`` (the paper's §2)."""

from __future__ import annotations

import functools
import math
from collections.abc import Iterator, Sequence
from dataclasses import replace

import numpy as np
import torch
from torch import Tensor

from .. import backend
from .._as_is import run_as_is_first
from .._checks import check_choice, check_finite
from .._native import carries_tangents
from .._transforms import refuse_transforms, saved_plainly_in_checkpoints
from ..backend import PATHS
from ..operators import functional, laplace_beltrami
from ..operators.laplace_beltrami import SCHEMES
from ..surface import ImplicitSurface, check_data, check_surface
from . import chebyshev
from ._integrators import (
    IMPLICIT,
    Linear,
    System,
    check_before_equilibrium,
    tensors,
    zero_outside,
)
from ._packed_band import FusedStage, PackedRegion
from ._positive import ChannelOf, Positive, check_learned_values
from ._recompute import declared, recomputed
from .base import (
    PACKED_METHODS,
    RANGE_SLACK,
    Flow,
    _check_times,
    _diagonal_cells,
    _range_excess,
    _warn_range_left,
    check_times_of_learned_time,
    keep_geometry_before_steps,
    placed,
)
from .exponential import BandLaplacian, heat_semigroup, kept_packing

SYMMETRIC_SCHEMES = functional.SCHEMES

CHEBYSHEV_PIECE = 3.0
"""``method="chebyshev"`` applies ``exp(t L)`` in pieces of ``t rho`` at most this times the
band's half-width in cells squared (a quarter of the time the diffusion takes to cross it),
re-extending the band between pieces: the level sets off S evolve on their own and drift apart
within one expansion. Sphere R = 0.8, l = 3, decay 0.5, float64, maximum relative error on S
with 1 / 2 / 4 / 8 / 16 pieces: 65^3 (t = 24 h^2) 1.21e-3, 8.4e-4, 7.7e-4, 7.6e-4, 7.5e-4;
97^3 (55 h^2) 1.31e-3, 5.2e-4, 3.9e-4, 3.5e-4, 3.4e-4 (RKC with 32 steps: 7.6e-4, 3.4e-4).
This rule takes 4 and 8."""


PACKED_BRICK_NODES = 2**20
"""Most band and ring nodes of a flow on bricks integrated on packed values
(:meth:`HeatFlow.packed_system`). The packed steps' matrices and their assembly cost about 2 kB
a node at the peak: the 256^3 bunny's 1.1 M nodes, packed, ran 1.5x faster than on the C kernel
(7.0 against 10.7 s to (8 h)^2) but peaked at 3.7 GB against 1.6 GB; the 512^3 bunny's 4.6 M
would not keep to its 4 GB."""


class HeatFlow(Flow):
    """Heat flow on the surface: ``u_t = D Lap_S u``, ``Lap_S`` by :func:`torchsurf.laplace_beltrami`.

    With the second-order schemes (the default octant, or symmetric), sampled on S, the flow
    is second order in ``h`` without any re-extension (octant scheme, explicit Euler, sphere of
    radius 1 on ``[-1.4, 1.4]^3``, l = 2, t = 0.05: relative error 1.4e-3, 5.8e-4, 3.4e-4 at
    65^3, 97^3, 129^3, sampled trilinearly at 2000 points on S, docs/benchmarks.md; most of it
    the trilinear read's own, 1.41e-3 on the exact solution at 65^3: read tricubically,
    ``sample(..., interpolation="cubic")``, the flow's error there is 1.2e-4).

    The default integrator is Runge–Kutta–Chebyshev (:class:`Flow`), with stages from a
    Gershgorin bound ``rho`` of the operator assembled on the band (close to ``10 / h^2`` on a
    distance function, ``dt <= h^2 / 6``). On a 3-cell band (``phi`` not a distance,
    ``from_mesh``'s band, bricks), whose ring its stages refresh, its steps last at most
    ``12 / rho``, the period at which Euler and Heun re-extend the band: the band's data drift
    off S between re-extensions, and steps of up to ``108 / rho`` erred up to six times as much
    (:data:`~torchsurf.flows._integrators.RKC_REFRESHED_STEP`, docs/band.md).
    ``"implicit"`` and ``"crank_nicolson"`` solve ``(W - theta dt D A) u_new = ...`` with
    ``A = W Lap_S`` symmetric negative semi-definite (schemes ``"octant"``, ``"symmetric"`` and
    ``"conservative"``) by conjugate gradients; any step size is stable. Crank–Nicolson is not
    L-stable: a step with ``dt rho >> 1`` multiplies the fastest modes (grid-scale noise) by
    nearly -1 instead of damping them, so few steps keep noise (an audit: noise on the 64^3
    unit sphere to 22 h^2, mean ``|grad_S u|`` near S 0.055 with 10 steps and 2.6 with 3, against
    0.025 for the default RKC and 0.027 for ``"implicit"`` with 10 steps). Smooth data lose
    nothing; to smooth noise in few steps use ``"implicit"`` (backward Euler). Where the band
    cannot hold its ring through a step (a 3-cell band), the ring is re-extended before each
    step and held through it, and Crank–Nicolson is then about first order in time: a sphere
    at 24^3 (3-cell band), l = 2, ``T = 0.03``, 10 / 20 / 40 / 80 / 160 steps 4.6e-4, 1.7e-4,
    6.7e-5, 3.0e-5, 1.5e-5 from the converged flow; with ``reextend_every=None`` order 2.00
    (an audit, 2026-12-07).

    With those schemes and ``phi`` fixed (not requiring grad), the explicit integrators
    (``"rkc"``, ``"euler"``, ``"heun"``) run on the band and ring's values alone: the rate is
    ``D W^-1 A`` as a sparse matrix read off the volume operator, the ring's and the band's
    re-extensions the same closest-point stencils as gathers, all assembled on the first call
    and kept on the surface (:class:`~torchsurf.flows._packed_band.PackedRegion`); the results
    equal the volume integration's to rounding, at the cost of the band's nodes instead of the
    box's (unit sphere, 64^3, batch 4, to 16 h^2: 0.23 s against 1.2-2.4 s with eager volume
    stencils; 65^3, batch 1: 0.14 against 0.22 s compiled). A ``phi`` that requires grad, a
    brick surface of more than :data:`PACKED_BRICK_NODES` band and ring nodes, a subclass with
    its own :meth:`system`, ``reextend_every=None`` or ``path="compiled"`` integrate volumes.

    ``method="chebyshev"`` applies the heat semigroup ``exp(t D Lap_S)`` by Chebyshev
    expansions (:func:`torchsurf.flows.exponential.heat_semigroup`, divergence-form schemes
    only): about ``sqrt(t D rho)`` operator applications per expansion instead of RKC's steps,
    the ring re-extended at every application and no step stored for backward (its backward is
    the transposed expansion). Times longer than a quarter of the band-crossing time are split
    into that many expansions with the band re-extended in between (:data:`CHEBYSHEV_PIECE`;
    one expansion over a long time loses second order), so the cost grows as ``sqrt(t)`` up to
    that time and as ``t`` beyond. With a learned time or diffusivity, backward keeps the input
    of every ``sqrt(pieces)``-th piece and recomputes the others (saved for backward at 25^3,
    batch 2, two channels: 0.50 / 2.0 / 4.0 MB at 1 / 100 / 400 h^2, against 0.83 / 13.4 /
    52.9 MB when every piece's input was kept; 1.4x the time);
    :class:`torchsurf.nn.LearnedDiffusion`, whose pieces run inside one backward with no band
    re-extension between them, keeps the same memory at any time.
    ``steps``, ``options`` and ``adjoint`` are refused with it, ``reextend_every`` and
    ``checkpoint`` do not apply. It is opt-in: the
    other methods' results and options stay as they were.

    The flow is linear in ``u0`` but for the re-extension's limiter, which clamps each value to
    the range of its cell: scaling, negation and added constants give the scaled, negated and
    shifted flow to rounding, sums not quite (``flow(u + 2 v) - flow(u) - 2 flow(v)`` on a
    torus at 32^3, ``4 h^2``, ``u`` noise and ``v`` smooth: 9.9e-5 of the largest value with
    RKC, 7.7e-4 with ``"chebyshev"``, which re-extends its input first; 2e-15 with
    ``reextend_every=None``).

    Args:
        time: physical end time, world units squared (with ``D = 1``).
        diffusivity: ``D``, a positive number or one per channel ``(C,)``. Per-channel
            values run each distinct value's channels (a learned vector's current values) with
            their own steps and re-extensions: each channel's result is its own flow's (fixed
            values under ``torch.compile`` too; a learned vector's channels run together there,
            planned for its largest value or ``max_diffusivity``).
        learn_diffusivity: make ``D`` an ``nn.Parameter`` (kept positive by softplus).
        max_diffusivity: with ``learn_diffusivity``, the largest ``D``: ``D`` is clamped to it
            and the steps are planned for it (no host read of the parameter, as ``max_time``).
        scheme: ``"octant"`` (default), ``"symmetric"``, ``"conservative"`` or ``"central"``
            (explicit and torchdiffeq methods only: not symmetric).
        path: how stencils are applied (see :func:`torchsurf.laplace_beltrami`).
        **kwargs: the integration settings of :class:`Flow` (``method``, ``steps``, ...).

    Shapes: ``u0`` ``(B, C, D, H, W)`` -> ``(B, C, D, H, W)``.

    Example:
        >>> import torch
        >>> import torchsurf as ts
        >>> case = ts.exact.sphere_harmonic(2, 17, dtype=torch.float32)
        >>> surface = ts.ImplicitSurface(case.phi, case.grid)
        >>> ts.flows.HeatFlow(time=0.01)(case.u, surface).shape
        torch.Size([1, 1, 17, 17, 17])
    """

    supports_bricks = True
    linear = True
    keeps_range = True
    extra_methods = ("chebyshev",)

    def __init__(
        self,
        time: float,
        diffusivity: float | Tensor = 1.0,
        learn_diffusivity: bool = False,
        max_diffusivity: float | None = None,
        scheme: str = "octant",
        path: str = "auto",
        **kwargs: object,
    ) -> None:
        super().__init__(time, **kwargs)
        if self.method == "chebyshev" and (self.steps is not None or self.options or self.adjoint):
            raise ValueError(
                "method='chebyshev' takes no steps, options or adjoint: it applies "
                "exp(t D Lap_S) in one expansion whose length follows the time"
            )
        self.diffusivity = Positive(diffusivity, "diffusivity", learnable=learn_diffusivity,
                                    bound=max_diffusivity, bound_name="max_diffusivity")
        self.scheme = check_choice(scheme, "scheme", SCHEMES)
        if self.method in (*IMPLICIT, "chebyshev") and self.scheme not in SYMMETRIC_SCHEMES:
            raise ValueError(
                f"method={self.method!r} needs a divergence-form scheme {SYMMETRIC_SCHEMES}, got "
                f"scheme={self.scheme!r}, which is not symmetric: use one of those schemes, or "
                "method 'rkc', 'euler', 'heun' or a torchdiffeq method with 'central'"
            )
        self.path = check_choice(path, "path", PATHS)

    def system(self, u0: Tensor, surface: ImplicitSurface, **inputs: Tensor) -> System:
        """:meth:`Flow.system` of the heat flow: ``D L u`` in the band, ``u0``
        ``(B, C, D, H, W)`` (packed on bricks), no inputs besides."""
        if inputs:
            raise TypeError(f"HeatFlow takes no inputs besides u0 and surface, got {sorted(inputs)}")
        band = self.band_mask(surface)
        d = self.diffusivity.volume(u0)
        unit = isinstance(d, float) and d == 1.0
        scheme, path = self.scheme, self.path
        pad = None if surface.layout is None else surface.layout.halo
        divergence = scheme in functional.SCHEMES
        outside = None if divergence else ~band

        def rate(u: Tensor) -> Tensor:
            if divergence:
                # the band's mask applied by the operator (in its own pass for the octant)
                value = functional.divergence_form(
                    u, surface.normal, surface.weight, surface.spacing, scheme, path,
                    haloed=surface.haloed(), pad=pad, mask=band)
                return value if unit else value * d
            value = laplace_beltrami(u, surface, scheme, path)
            return zero_outside(value if unit else value * d, outside)

        linear = None
        if self.scheme in SYMMETRIC_SCHEMES:
            spacing = surface.spacing

            def operator(x: Tensor, weight: Tensor, normal: Tensor, haloed_weight: Tensor,
                         haloed_normal: Tensor, *diffusivity: Tensor) -> Tensor:
                scale = diffusivity[0] if diffusivity else d
                return scale * functional.divergence_form(
                    x, normal, weight, spacing, scheme, path, weighted=True,
                    haloed=(haloed_normal, haloed_weight), pad=pad,
                )

            haloed_normal, haloed_weight = surface.haloed()
            geometry = (surface.weight, surface.normal, haloed_weight, haloed_normal)
            linear = Linear(operator, geometry + ((d,) if isinstance(d, Tensor) else ()))
        self._packing(surface)  # first: its rows give the bound too (kept_packing)
        rho = self.diffusivity.maximum() * self.operator_bound(surface, self.scheme)
        params = tensors(d, surface.normal, surface.weight)
        return System(rate, band, rho, linear=linear, params=params, isotropic=True)

    def packed_system(self, system: System, u0: Tensor, surface: ImplicitSurface
                      ) -> tuple[System, PackedRegion] | None:
        """With a divergence-form scheme and ``phi`` fixed, the rate on packed band and ring
        values: ``D W^-1 A z`` on the band's rows by the matrix read off the volume operator
        (:class:`~torchsurf.flows._packed_band.PackedRegion`, assembled once and kept on the
        surface), the explicit steps and re-extensions on the band and ring's nodes alone.
        ``None`` (volumes) for a subclass that defines its own :meth:`system`; on bricks whose
        band and ring hold more than :data:`PACKED_BRICK_NODES` nodes (the flow's stencils as
        matrices, about 2 kB a node at their assembly, would strain the 4 GB the 512^3 bunny's
        flow keeps to; there the C kernel applies the octant rate on the band's bricks); and
        where compiled volume stencils are asked for (``path="compiled"``,
        or ``"auto"`` under ``TORCHSURF_COMPILE=always``); and for data carrying a forward-mode
        tangent or a ``torch.func`` wrapper, which the packed products would drop."""
        if carries_tangents(u0, surface.phi, *self.parameters()):
            return None
        packing = self._packing(surface)
        if packing is None:
            return None
        d = self.diffusivity.volume(u0)
        unit = isinstance(d, float) and d == 1.0

        def rate(z: Tensor) -> Tensor:
            value = packing.laplacian(z)
            if unit:
                return value
            return value * (d.reshape(1, -1, 1) if isinstance(d, Tensor) else d)

        fused = (FusedStage(packing, d) if isinstance(d, float) and self.path == "auto"
                 else None)
        packed = replace(system, rate=rate, band=packing.band_mask(), layout=None,
                         params=tensors(d), linear_stage=fused)
        return packed, packing

    def _packing(self, surface: ImplicitSurface) -> PackedRegion | None:
        """The packed band and ring this flow's explicit steps run on (:meth:`packed_system`),
        assembled once and kept on the surface, or ``None`` where they run on volumes."""
        if (self.method not in PACKED_METHODS or self.reextend_every is None
                or self.scheme not in functional.SCHEMES or surface.phi.requires_grad
                or type(self).system is not HeatFlow.system  # a subclass's own equation
                or self.path == "compiled"
                or (self.path == "auto" and backend.COMPILE == "always")):
            return None
        width = self.evolving_width(surface)
        region = self.region_mask(surface)
        if surface.layout is not None and surface.kept(  # a host read, once per surface
                ("band and ring nodes", width), lambda: int(region.sum())
        ) > PACKED_BRICK_NODES:
            return None
        return kept_packing(surface, self.scheme, width, self.band_mask(surface), region)

    def _share_of_planned_rate(self) -> float:
        """:meth:`Flow._share_of_planned_rate`, times the share of ``max_diffusivity`` a
        learned diffusivity takes (the steps are planned for the bound's ``rho``)."""
        return super()._share_of_planned_rate() * self.diffusivity.share_of_bound()

    @saved_plainly_in_checkpoints
    def forward(
        self, u0: Tensor, surface: ImplicitSurface,
        times: Sequence[float] | Tensor | np.ndarray | None = None, **inputs: Tensor,
    ) -> Tensor:
        """Integrate from ``u0`` to the end time (:meth:`Flow.forward`; ``"chebyshev"`` here)."""
        times = list(times) if isinstance(times, Iterator) else times  # read once
        run_as_is_first(self, u0, surface, times, **inputs)
        if isinstance(u0, Tensor):  # before the groups read the diffusivity on its device
            check_learned_values(self, u0, "u0", type(self).__name__)
        groups = self._diffusivity_groups(u0)
        if groups is not None:
            return self._channels_apart(u0, surface, times, groups, inputs)
        if self.method != "chebyshev":
            return super().forward(u0, surface, times, **inputs)
        if inputs:
            raise TypeError(f"HeatFlow takes no inputs besides u0 and surface, got {sorted(inputs)}")
        if self.scheme not in SYMMETRIC_SCHEMES:
            raise ValueError(
                f"method='chebyshev' needs a divergence-form scheme {SYMMETRIC_SCHEMES}, got "
                f"scheme={self.scheme!r}"
            )
        check_surface(surface)
        refuse_transforms("HeatFlow", u0, forward_mode=False, phi=surface.phi,
                          why="method='chebyshev': the explicit methods 'euler', 'heun' and 'rkc' "
                              "have one")
        check_data(u0, "u0", surface)
        check_times_of_learned_time(self.time_value, times)
        separately = self._entries_apart(u0, surface, times, {})
        if separately is not None:
            return separately
        width = self.evolving_width(surface)
        wanted = None if times is None else _check_times(times, self.time_value.maximum())
        self._check_memory(u0, surface, surface.band_mask(width),
                           0 if wanted is None else len(wanted))  # each entry before its work
        keep_geometry_before_steps(surface)
        operator = BandLaplacian(surface, self.scheme, width, self.path)
        if not torch.compiler.is_compiling():  # a host read: it would break a compiled graph
            check_finite(torch.where(operator.band, u0, 0.0), "u0 (in the band)")
        d = self.diffusivity.volume(u0)
        rate = (d.reshape(-1) if isinstance(d, Tensor) else u0.new_tensor(d)).expand(u0.shape[1])
        horizon = self.time * rate
        # host floats (read from the parameters only when learned without a bound)
        end = self.time_value.maximum()
        largest = end * self.diffusivity.maximum()
        bound = float(operator.bound)
        check_before_equilibrium(largest, bound, _diagonal_cells(surface))
        # re-extended once a piece of the diffusion's own time, not of the bounds' (a learned
        # time or diffusivity below its bound: :meth:`_share_of_planned_rate`)
        piece = (CHEBYSHEV_PIECE * (width / surface.spacing) ** 2 / bound
                 / self._share_of_planned_rate())
        outer = max(1, math.ceil(largest / piece * (1 - 1e-9)))
        inner = chebyshev.pieces_for(largest / outer, bound)
        terms = chebyshev.count_terms("exp", largest / outer / inner, bound, u0.dtype)
        chebyshev.check_applications(outer * inner * (terms - 1), largest, bound)

        def semigroup(fraction: float) -> Tensor:
            pieces = max(1, math.ceil(largest * fraction / piece * (1 - 1e-9)))

            def run(u: Tensor, count: int, first: bool) -> Tensor:
                for piece in range(count):  # u0 read near S only (heat_semigroup)
                    u = heat_semigroup(u, operator, horizon * (fraction / pieces),
                                       largest * fraction / pieces,
                                       extend_first=first and piece == 0)
                return u

            # sqrt(pieces) pieces at a time recomputed in backward: autograd kept every
            # piece's input (a learned time at 64^3, batch 4, 1 -> 100 h^2: 58 -> 197 MB),
            # and with phi's graph every piece's re-extensions too (21 MB a piece at 20^3)
            reads = (declared((horizon, operator.surface.phi)) if operator.differentiable
                     else tensors(horizon))
            group = math.ceil(math.sqrt(pieces))
            u = u0
            for start in range(0, pieces, group):
                u = recomputed(functools.partial(run, count=min(group, pieces - start),
                                                 first=start == 0), u, reads,
                               what="HeatFlow(method='chebyshev')")
            return u

        if times is None:
            results = [semigroup(1.0)]
        else:
            results = [u0 if t == 0 else semigroup(t / end) for t in _check_times(times, end)]
        if not torch.compiler.is_compiling():  # a host read: it would break a traced graph
            excess = _range_excess(u0, results, operator.region, operator.band,
                                   surface.layout is not None)
            applications = f"{outer * inner * (terms - 1)} applications of the operator"
            gathered = self._gathered_excesses()
            if gathered is not None:  # one entry of a batch: its caller warns
                gathered.append((excess, applications))
            elif excess > RANGE_SLACK:
                _warn_range_left(self, excess, applications)
        return results[0] if times is None else torch.stack(results)

    def _diffusivity_groups(self, u0: Tensor) -> list[tuple[Positive, list[int]]] | None:
        """The diffusivity of each group of channels that runs alone, ``[(D, channels), ...]``:
        the channels of each distinct value together (a learned vector's in the graph of its
        parameter: :class:`~torchsurf.flows._positive.ChannelOf`). ``None`` where all channels
        run together: one diffusivity, one distinct value, and a learned vector under
        ``torch.compile`` (its values are a host read; its steps then follow its largest entry
        or ``max_diffusivity``). A fixed vector's values are kept on the host, so its channels
        run apart traced too (until 2026-12-07 they ran together: ``[1.0, 0.5]``, ``h^2 / 2`` at
        12^3, the second channel 1.5e-2 off the call as is with Heun steps, now 1.8e-7).
        Apart, C channels cost about C runs' fixed costs: 8 channels of 8 values at 33^3,
        batch 2, forward and backward, 1.20 against 0.68 s together. ``"chebyshev"`` is split too: its
        expansion is exact in each channel's time, but its pieces, and the band's
        re-extensions between them, follow the largest (a channel of ``D = 1`` beside one of
        ``D = 30`` moved by 3.7e-2 on noise)."""
        whole = self.diffusivity
        if whole.channels is None or whole.channels == 1 or not isinstance(u0, Tensor):
            return None
        values = whole.fixed_entries()
        if values is None:
            if torch.compiler.is_compiling():
                return None
            values = tuple(whole.value().detach().cpu().tolist())
        whole.volume(u0)  # the channel count checked against u0
        groups: dict[float, list[int]] = {}
        for channel, value in enumerate(values):
            groups.setdefault(value, []).append(channel)
        if len(groups) == 1:
            return None
        if whole.learnable or whole.values_require_grad():  # the groups in the values' graph
            return [(ChannelOf(whole, group), group) for group in groups.values()]
        return self._fixed_groups(groups)

    def _fixed_groups(self, groups: dict[float, list[int]]) -> list[tuple[Positive, list[int]]]:
        """One fixed :class:`Positive` per distinct value, kept for the values last grouped."""
        key = tuple((value, tuple(channels)) for value, channels in groups.items())
        kept = self.__dict__.get("_fixed_group_values")
        if kept is None or kept[0] != key:
            kept = self.__dict__["_fixed_group_values"] = (key, [
                (Positive(value, "diffusivity"), channels) for value, channels in groups.items()])
        return kept[1]

    def _channels_apart(self, u0: Tensor, surface: ImplicitSurface, times: object,
                        groups: list[tuple[Positive, list[int]]], inputs: dict[str, Tensor]
                        ) -> Tensor:
        """Each group of channels integrated with its own steps and re-extensions: planned
        together for the largest, a channel of ``D = 1`` beside one of ``D = 100`` erred 5-9
        times as much as alone (33^3-49^3, every stepping method; the re-extensions, once per
        cell-crossing time of the fastest channel, each add a little), and a learned ``D = 1``
        beside ``D = 10`` on a 40^3 bunny at ``5 h^2`` was 0.39 off its own flow (data of
        range 2)."""
        excesses, gathering = self._gather_excesses()
        result = None
        try:
            for diffusivity, channels in groups:
                index = torch.tensor(channels, device=u0.device)
                part = self._forward_with(diffusivity, u0.index_select(-4, index), surface, times,
                                          inputs)
                result = placed(result, part, index, u0.shape[-4], -4)
        finally:
            self._stop_gathering(gathering)
        self._warn_gathered(excesses, gathering)
        return result

    def _forward_with(self, diffusivity: Positive, u0: Tensor, surface: ImplicitSurface,
                      times: object, inputs: dict[str, Tensor]) -> Tensor:
        """:meth:`forward` with one group's ``diffusivity``, run by a shallow copy of this flow
        that holds it (its submodules and settings shared): the module itself is not changed,
        as other threads may be calling it (the swapped submodule had run their channels with
        this group's value, 10 of 15 concurrent calls 0.27 off, and could be left in place for
        good); a subclass's own :meth:`system` reads the group's value as ``self.diffusivity``.
        What a subclass writes on ``self`` in a group's run lands on the copy. Traced, the
        submodule is swapped instead (dynamo cannot copy a module), as the graph's own change:
        nothing changes while the compiled code runs, unless the group's run breaks the graph
        (eager code then sees the group's value on the module)."""
        if torch.compiler.is_compiling():
            whole = self._modules["diffusivity"]
            self._modules["diffusivity"] = diffusivity
            try:
                return self.forward(u0, surface, times, **inputs)
            finally:
                self._modules["diffusivity"] = whole
        part = object.__new__(type(self))  # not copy.copy: no __reduce_ex__ or __getstate__
        part.__dict__.update(self.__dict__)  # (a parametrized module refuses to be copied so)
        part._modules = {**self._modules, "diffusivity": diffusivity}
        part.__dict__["_part_of"] = self  # its runs' range excesses are this call's
        result = part.forward(u0, surface, times, **inputs)
        self.last_plan = part.last_plan
        return result

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, scheme={self.scheme!r}"
