"""Flow visualisation on a surface: noise diffused along a tangent field (the paper's §3.4)."""

from __future__ import annotations

import torch
from torch import Tensor

from .._checks import check_generator, check_nonnegative
from ..operators import functional
from ..surface import ImplicitSurface, check_direction, tangent_unit
from ._integrators import Linear, System, tensors, with_ring, zero_outside
from .base import Flow, data_shape


class FlowVisualization(Flow):
    """``u_t = (1/W) div(W (T . P grad u) T) + iso Lap_S u``: streaks along ``T`` from noise.

    ``T`` is made tangent and unit (``P T / |P T|``), which makes the operator symmetric
    negative semi-definite in the W-weighted inner product, so ``"implicit"`` works too.

    Spectral bound: ``(1 + iso) rho``, ``rho`` the Gershgorin bound of the band's
    Laplace–Beltrami operator (``|T| = 1``, ``P <= I``).

    Runs on a :class:`~torchsurf.bricks.BrickSurface` too (``u0`` and ``T`` packed
    ``(N, C, 8, 8, 8)``), equal to the dense flow on the band (docs/bricks.md).

    The operator damps nothing across ``T``: on surfaces thinner than the band or folded within
    it, or where ``phi`` is far from a distance, keep the default method (RKC), where Euler's,
    Heun's and backward Euler's many more re-extensions grew without bound (a trefoil mesh at
    32^3 and 48^3, docs/band.md §5; ``phi = d^3`` of a 24^3 sphere at 100 h^2: Euler
    [-1.1e4, 1.1e4], Heun [-7e3, 6.5e3], RKC in range; a call that leaves the range of ``u0``
    warns, :attr:`~torchsurf.flows.Flow.keeps_range`).

    Args:
        time: physical end time, world units squared (streak length about ``sqrt(time)``).
        isotropic: weight ``iso`` of a small isotropic term (0 by default).
        **kwargs: integration settings of :class:`Flow`.

    Call: ``flow(u0, surface, direction=T)`` with ``u0`` ``(B, C, D, H, W)`` (e.g.
    :meth:`noise`) and ``T`` ``(B or 1, 3, D, H, W)``; returns ``(B, C, D, H, W)``.
    """

    supports_bricks = True
    linear = True
    keeps_range = True

    def __init__(self, time: float, isotropic: float = 0.0, **kwargs: object) -> None:
        super().__init__(time, **kwargs)
        self.isotropic = check_nonnegative(isotropic, "isotropic")

    @staticmethod
    def noise(surface: ImplicitSurface, batch: int = 1,
              generator: torch.Generator | None = None) -> Tensor:
        """Uniform noise in ``[0, 1)``, ``(batch, 1, D, H, W)`` in the surface's dtype, drawn in
        float64 (a seed gives the same picture in float32 and float64).

        On a :class:`~torchsurf.bricks.BrickSurface`, packed ``(N, 1, 8, 8, 8)``: the same
        numbers, node for node, as on the dense grid of each entry
        (:meth:`~torchsurf.bricks.BrickLayout.rand`).
        """
        shape = data_shape(surface, batch, 1)
        check_generator(generator)
        if surface.layout is not None:
            return surface.layout.rand(1, generator, torch.float64).to(surface.phi.dtype)
        values = torch.rand(shape, generator=generator, dtype=torch.float64)
        return values.to(surface.phi.device, surface.phi.dtype)

    def system(self, u0: Tensor, surface: ImplicitSurface, direction: Tensor | None = None,
               **inputs: Tensor) -> System:
        """:meth:`Flow.system` of the noise ``u0`` ``(B, C, D, H, W)`` smeared along
        ``direction`` ``(B or 1, 3, D, H, W)``, the tangent field ``T`` (required)."""
        if inputs:
            raise TypeError(f"FlowVisualization takes direction= only, got {sorted(inputs)} (its "
                            f"noise is the u0 given: FlowVisualization.noise(surface, "
                            f"generator=...) draws one)")
        if direction is None:
            raise TypeError("direction: FlowVisualization needs a tangent field T, "
                            "flow(u0, surface, direction=T)")
        band = self.band_mask(surface)
        region = with_ring(band, surface.layout)
        given = check_direction(direction, u0, surface, region)
        direction = tangent_unit(given, surface)
        outside = ~band
        spacing, isotropic = surface.spacing, self.isotropic
        pad = None if surface.layout is None else surface.layout.halo

        def laplacian(u: Tensor, weight: Tensor, normal: Tensor, direction: Tensor,
                      haloed: tuple[Tensor, Tensor] | None = None,
                      haloed_direction: Tensor | None = None, weighted: bool = False) -> Tensor:
            result = functional.directional_form(
                u, normal, weight, spacing, direction, "symmetric", weighted=weighted,
                haloed=haloed, pad=pad, haloed_direction=haloed_direction,
            )
            if isotropic:
                result = result + isotropic * functional.divergence_form(
                    u, normal, weight, spacing, "symmetric", weighted=weighted, haloed=haloed,
                    pad=pad,
                )
            return result

        # the rate reads the surface's kept halos; the implicit operator reads its parameters,
        # through which conjugate gradients' backward differentiates: on a dense volume it pads
        # them itself, on bricks their halos are parameters too (one gather per flow, not per
        # iteration)
        haloed = surface.haloed()
        geometry = (surface.weight, surface.normal, direction)
        haloed_direction = None if pad is None else pad(direction, 1)
        if pad is not None:
            geometry = (*geometry, haloed[0], haloed[1], haloed_direction)

        def operator(x: Tensor, weight: Tensor, normal: Tensor, direction: Tensor,
                     *halos: Tensor) -> Tensor:
            kept = (halos[0], halos[1]) if halos else None
            return laplacian(x, weight, normal, direction, kept, halos[2] if halos else None,
                             weighted=True)

        def rate(u: Tensor) -> Tensor:
            return zero_outside(laplacian(u, *geometry[:3], haloed, haloed_direction), outside)

        rho = (1.0 + self.isotropic) * self.operator_bound(surface, "symmetric")
        # the given field too: the tangent one, computed from it and from phi, is not
        # declared where phi needs gradients (_recompute.independent)
        return System(rate, band, rho, linear=Linear(operator, geometry),
                      params=tensors(*geometry, given))

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, isotropic={self.isotropic:g}"
