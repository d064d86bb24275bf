"""Turk's two-chemical reaction–diffusion on a surface (the paper's §3.3).

``a_t = s (16 - a b) + D_a L a``, ``b_t = s (a b - b - beta) + D_b L b``, with ``L`` the
intrinsic Laplacian or, for anisotropic patterns, ``D_a (1/W) div(W (T . P grad a) T)`` along a
unit tangent field ``T``. ``beta = 12 + uniform noise in [-noise, noise]`` is drawn once per call
from the given ``torch.Generator``, so a seeded generator reproduces the pattern; on a
:class:`~torchsurf.bricks.BrickSurface` the same numbers at the same nodes as on the dense grid
(:meth:`torchsurf.bricks.BrickLayout.rand`), so the pattern is the dense one.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .. import backend
from .._checks import check_generator, check_nonnegative, check_positive, check_real
from ..operators import directional_bound, functional, laplace_beltrami
from ..surface import ImplicitSurface, check_direction, tangent_unit
from ._integrators import System, tensors, with_ring
from .base import Flow, data_shape


class ReactionDiffusion(Flow):
    """Turk (1991) reaction–diffusion of ``(a, b)``, time in Turk's units (one unit = one of
    his iterations).

    Diffusivities are world units squared per unit time; by default Turk's grid values,
    ``D_a = h^2 / 4`` and ``D_b = h^2 / 16``, so the pattern scale is a few cells, and it grows
    as ``s`` shrinks.

    ``b`` is clamped at 0 at the start and after every step (Turk's rule; with torchdiffeq
    methods at the start, between their pieces and at the output times): a ``u0`` whose ``b``
    is negative somewhere starts from 0 there, and its gradient there is 0.

    Spectral bound: ``max(D_a rho_a, D_b rho) + s (max a + max b + 1)``, the diffusion's
    (``rho`` the Gershgorin bound of the band's Laplace–Beltrami operator, about ``10 / h^2``
    on a distance, 14-16 on meshes' phi;
    ``rho_a`` that of the directional operator along ``direction`` if one is given, or ``rho``)
    and the reaction's (its Jacobian has entries ``s a``, ``s b``, ``s``); Euler steps ``1.8 /``
    that (0.9 of the stability limit the bound guarantees).

    Args:
        time: end time (Turk's iterations).
        rate: reaction rate ``s`` (Turk: 1/128).
        diffusivity_a, diffusivity_b: ``D_a``, ``D_b``, world units squared (default Turk's).
        beta: mean of Turk's ``beta``, a finite number.
        noise: half-width of ``beta``'s uniform noise about its mean, >= 0.
        **kwargs: integration settings of :class:`Flow` (explicit or torchdiffeq); the default
            method is ``"euler"``, as Turk's: the pattern grows from the reaction's unstable
            modes, which Runge–Kutta–Chebyshev's long steps do not resolve.

    Call: ``flow(u0, surface, direction=None, generator=None)``, ``u0`` ``(B, 2, D, H, W)``
    (``a``, ``b``; :meth:`initial` gives Turk's ``a = b = 4``), ``direction`` an optional
    tangent field ``(B or 1, 3, D, H, W)`` for anisotropic patterns. Returns ``(B, 2, D, H, W)``.
    On a :class:`~torchsurf.bricks.BrickSurface`, ``u0`` and ``direction`` are packed
    ``(N, C, 8, 8, 8)``; the reaction terms are pointwise and apply to the packed values as
    they are.
    """

    supports_bricks = True
    linear = False

    def __init__(
        self,
        time: float,
        rate: float = 1.0 / 128.0,
        diffusivity_a: float | None = None,
        diffusivity_b: float | None = None,
        beta: float = 12.0,
        noise: float = 0.1,
        **kwargs: object,
    ) -> None:
        kwargs.setdefault("method", "euler")
        super().__init__(time, **kwargs)
        self.rate = check_positive(rate, "rate")
        self.diffusivity_a = None if diffusivity_a is None else check_positive(
            diffusivity_a, "diffusivity_a")
        self.diffusivity_b = None if diffusivity_b is None else check_positive(
            diffusivity_b, "diffusivity_b")
        self.beta = check_real(beta, "beta")
        self.noise = check_nonnegative(noise, "noise")

    @staticmethod
    def initial(surface: ImplicitSurface, batch: int = 1) -> Tensor:
        """Turk's start ``a = b = 4``, ``(batch, 2, D, H, W)`` in the surface's dtype (on a
        :class:`~torchsurf.bricks.BrickSurface`, packed ``(N, 2, 8, 8, 8)``)."""
        return torch.full(data_shape(surface, batch, 2), 4.0, dtype=surface.phi.dtype,
                          device=surface.phi.device)

    def _diffusivities(self, surface: ImplicitSurface) -> tuple[float, float]:
        h2 = surface.spacing**2
        return (self.diffusivity_a or h2 / 4.0, self.diffusivity_b or h2 / 16.0)

    def system(self, u0: Tensor, surface: ImplicitSurface, direction: Tensor | None = None,
               generator: torch.Generator | None = None) -> System:
        """:meth:`Flow.system` of the two species ``u0`` ``(B, 2, D, H, W)``; ``direction``
        ``(B or 1, 3, D, H, W)`` for the anisotropic variant (as in ``forward``), ``generator``
        for the reaction's random ``beta``."""
        if u0.shape[1] != 2:
            raise ValueError(f"u0 must have 2 channels (a, b), got shape {tuple(u0.shape)}")
        check_generator(generator)
        band = self.band_mask(surface)
        d_a, d_b = self._diffusivities(surface)
        beta = self.beta + self.noise * (2.0 * _uniform_noise(u0, surface, generator) - 1.0)
        given = None
        if direction is not None:
            region = with_ring(band, surface.layout)
            given = check_direction(direction, u0, surface, region)
            direction = tangent_unit(given, surface)
        s = self.rate
        pad = None if surface.layout is None else surface.layout.halo
        # on bricks the field's halo is gathered once per flow, not at every evaluation
        haloed_direction = None if pad is None or direction is None else pad(direction, 1)

        def rate(u: Tensor) -> Tensor:
            a, b = u[:, :1], u[:, 1:]
            if direction is None:
                diffusion_a = laplace_beltrami(a, surface)
            else:
                diffusion_a = functional.directional_form(
                    a, surface.normal, surface.weight, surface.spacing, direction,
                    haloed=surface.haloed(), pad=pad, haloed_direction=haloed_direction)
            return backend.run(_TURK, "auto", u, a, b, diffusion_a,
                               laplace_beltrami(b, surface), beta, band, s, d_a, d_b)

        # the largest a and b in the band: values outside it are never read
        largest = torch.where(band, u0.detach(), -torch.inf).amax(dim=(0, 2, 3, 4))
        reaction = float(largest.sum() + 1.0)
        bound_b = self.operator_bound(surface)
        bound_a = bound_b if direction is None else directional_bound(
            surface, direction, width=self.evolving_width(surface))
        rho = max(d_a * bound_a, d_b * bound_b) + s * max(reaction, 1.0)
        return System(rate, band, rho, project=_nonnegative_b,
                      # the given field too: the tangent one, computed from it and from
                      # phi, is not declared where phi needs gradients (_recompute.independent)
                      params=tensors(surface.normal, surface.weight, direction,
                                     haloed_direction, given),
                      growth=s * max(reaction, TURK_SUPPLY), reaction=True)

    def _entries_apart(self, u0: Tensor, surface: ImplicitSurface, times: object,
                       inputs: dict[str, Tensor]) -> Tensor | None:
        """As :meth:`Flow._entries_apart`, and data of several entries on a dense surface of
        one run apart too: the step follows the data's largest ``a`` and ``b`` (the reaction's
        bound), and a shared plan made one entry's result depend on the others' (a start at
        ``a = b = 16`` beside Turk's shortened its steps: 6.3e-4 off at ``t = 3000``; apart,
        a batch of 8 at 21^3 takes 1.3 times as long). Each entry's noise is drawn in turn
        from the one generator, the numbers one draw for the batch gives on the CPU."""
        apart = super()._entries_apart(u0, surface, times, inputs)
        count = u0.shape[0]
        direction = inputs.get("direction")
        if (apart is not None or surface.layout is not None or count == 1
                or isinstance(direction, Tensor) and direction.shape[:1] not in ((1,), (count,))):
            return apart  # (a direction of another batch is refused by the batch's call)
        return self._each_data_entry(u0, surface, times, inputs)

    def extra_repr(self) -> str:
        return (f"{super().extra_repr()}, rate={self.rate:g}, beta={self.beta:g}, "
                f"noise={self.noise:g}")


TURK_SUPPLY = 16.0
"""The constant of Turk's ``a_t = s (16 - a b)``. The reaction's Jacobian grows ``b`` at up to
``s (a - 1)``, and ``a`` rises above its start as the pattern forms (from 4 to 7.3 by
``t = 10^4`` on a 32^3 sphere): the growth RKC's steps are limited for
(:attr:`~torchsurf.flows._integrators.System.growth`) is ``s`` times the larger of this and the
start's largest ``a + b + 1``. Without a growth RKC took steps of 86 there and diverged."""


def _turk_rate(a: Tensor, b: Tensor, diffusion_a: Tensor, diffusion_b: Tensor, beta: Tensor,
               band: Tensor, s: float, d_a: float, d_b: float, path: str = "slicing") -> Tensor:
    """Turk's ``(a_t, b_t)`` from ``a``, ``b`` and their diffusion terms, zero outside the band.

    One pointwise expression: compiled (:mod:`torchsurf.backend`) it is a single pass over
    memory instead of a dozen (at 128^3 they took half of each step's time).
    """
    da = s * (16.0 - a * b) + d_a * diffusion_a
    db = s * (a * b - b - beta) + d_b * diffusion_b
    return torch.where(band, torch.cat((da, db), dim=1), 0.0)


_TURK = backend.Kernel("turk_reaction", _turk_rate, _turk_rate, lambda *args: args,
                       fused_when_eager=True)


def _nonnegative_b(u: Tensor) -> Tensor:
    """Keep the concentration ``b`` at or above 0 after each step, as Turk does.

    Without it, ``b`` crossing 0 turns the ``a b`` coupling into growth and the run reaches
    NaN (a 41^3 run at ``s = 1/32`` did by ``s t = 20``). Gradients are zero where ``b`` is clamped.
    """
    lowest = u.new_tensor([-torch.inf, 0.0]).view(1, 2, 1, 1, 1)
    return u.clamp(min=lowest)


@torch.compiler.disable
def _uniform_noise(u0: Tensor, surface: ImplicitSurface, generator: torch.Generator | None
                   ) -> Tensor:
    """Uniform ``[0, 1)`` noise of one channel shaped like ``u0`` (dense or packed), in its
    dtype. Drawn in float64 whatever that dtype, so that a seed gives one pattern in float32
    and float64, and drawn as is under ``torch.compile``: inductor would draw its own numbers
    for a ``torch.rand`` in its graph, and ``torch.manual_seed`` would not give the pattern of
    the call as is."""
    if surface.layout is None:
        return torch.rand((u0.shape[0], 1, *u0.shape[2:]), generator=generator,
                          dtype=torch.float64, device="cpu").to(u0.device, u0.dtype)
    return surface.layout.rand(1, generator, torch.float64).to(u0.dtype)

