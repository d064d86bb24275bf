"""p-harmonic map flow of unit vectors ``u : S -> S^{m-1}`` (the paper's §3.2)."""

from __future__ import annotations

import torch
from torch import Tensor

from .._checks import check_choice, check_flag, check_positive, check_real
from .._vectors import tangential_part
from ..backend import PATHS
from ..operators import functional
from ..operators.functional import FLUX_SCHEMES
from ..surface import ImplicitSurface, check_tangential
from ._integrators import INTEGRATORS, System, eps_stiffness, tensors, with_ring
from .base import Flow


def power_diffusivity(magnitude: Tensor, exponent: float) -> Tensor:
    """``g(s) = s^exponent``: the p-harmonic map's diffusivity with ``exponent = p - 2``."""
    return magnitude**exponent


power_diffusivity.exponent_contrast = True  # type: ignore[attr-defined]  (torchsurf.backend)


def normalize(u: Tensor, eps: float = 1e-12) -> Tensor:
    """``u / |u|`` over the channels of ``(B, C, D, H, W)`` (zero vectors stay zero).

    Each vector is first divided by its largest component (a constant to autograd: the result
    does not depend on it), so that its squares neither overflow nor underflow: vectors of
    length 1e20 or 1e-20 in float32 came out zero or not unit; ``eps`` then only keeps zero
    vectors finite."""
    largest = u.detach().abs().amax(dim=1, keepdim=True)
    scaled = u / torch.where(largest > 0, largest, torch.ones_like(largest))
    return scaled / torch.sqrt((scaled**2).sum(dim=1, keepdim=True) + eps**2)


class HarmonicMapFlow(Flow):
    """``du_i/dt = (1/W) div(W |P grad u|^(p-2) P grad u_i) + u_i |P grad u|^p``, renormalised.

    ``|P grad u|^2 = sum_i |P grad u_i|^2`` couples the channels (the coupled norm of
    :func:`torchsurf.anisotropic_diffusion` with ``g(s) = s^(p-2)``), regularised by ``eps``.
    After every explicit step ``u <- u / |u|`` in the band and its ring; elsewhere ``u`` is
    returned as it is. torchdiffeq's methods project at the start, between their pieces and at
    the requested times, and integrate the rate without its part along ``u``, which keeps
    ``|u|`` in between (the rate as it is pushed ``|u|`` off 1 and ended in NaN, or 0.10 from
    the converged flow where it did not; ``tests/flows/test_harmonic.py``). With
    ``tangent=True`` the field is kept tangent to the level sets (``u <- P u / |P u|``; the
    rate too, under torchdiffeq), for direction fields on S.

    Spectral bound: ``eps^(p-2) rho`` (``max g = eps^(p-2)``), ``rho`` the Gershgorin bound of
    the band's Laplace–Beltrami operator (about ``10 / h^2`` on a distance, 14-15 on meshes'
    phi). Growth: the largest
    ``|P grad u0|^p`` in the band, the rate at which the energy term pushes ``u`` outwards
    before it is renormalised; RKC steps are kept short against it (a field with sign jumps,
    ``4 / h^2`` at p = 2, takes more steps).

    Time accuracy: on noisy fields RKC's long steps are far from the flow at the given time
    (the renormalisation after each step is part of the scheme, and the noise sets the
    coefficients): against a converged explicit-Euler run, a noisy unit field on a sphere at
    40^3, ``p = 2`` to ``5 h^2``, differed by up to 0.26 with the default RKC, 0.09 with
    Euler's stable steps. Pass ``method="euler"`` (or ``steps=``) where the result at a given
    time matters.

    Args:
        time: physical end time.
        p: exponent, ``1 <= p <= 2`` (1: the paper's figure 2, direction fields; 2: harmonic maps).
        eps: regularisation of ``|P grad u|``, units of ``u`` per world length.
        tangent: constrain ``u`` (3 channels) to the tangent plane of the level sets; a
            ``u0`` with no tangent part over most of the band (the normals) is refused.
        scheme: ``"symmetric"`` (default), ``"conservative"`` or ``"octant"`` (``"symmetric"``
            is not mirror-symmetric; see :class:`AnisotropicFlow`).
        path: how stencils are applied.
        **kwargs: integration settings of :class:`Flow` (explicit or torchdiffeq).

    Runs on a :class:`~torchsurf.bricks.BrickSurface` too (``u0`` packed ``(N, m, 8, 8, 8)``),
    equal to the dense flow on the band (docs/bricks.md).

    Shapes: ``u0`` ``(B, m, D, H, W)`` with ``|u0| = 1`` (other lengths are made 1 at the
    start, zero vectors in the band and its ring refused) -> ``(B, m, D, H, W)``.
    """

    supports_bricks = True
    linear = False

    def __init__(
        self,
        time: float,
        p: float = 2.0,
        eps: float = 1e-1,
        tangent: bool = False,
        scheme: str = "symmetric",
        path: str = "auto",
        **kwargs: object,
    ) -> None:
        super().__init__(time, **kwargs)
        p = check_real(p, "p")
        if not 1 <= p <= 2:
            raise ValueError(f"p must be a number with 1 <= p <= 2, got {p!r}")
        self.p, self.eps = p, check_positive(eps, "eps")
        self.tangent = check_flag(tangent, "tangent")
        self.scheme = check_choice(scheme, "scheme", FLUX_SCHEMES)
        self.path = check_choice(path, "path", PATHS)

    def system(self, u0: Tensor, surface: ImplicitSurface, **inputs: Tensor) -> System:
        """:meth:`Flow.system` of the harmonic map flow of unit vectors ``u0``
        ``(B, C, D, H, W)``, ``C >= 2`` (3 with ``tangent``), no inputs besides."""
        if inputs:
            raise TypeError(f"HarmonicMapFlow takes no extra inputs, got {sorted(inputs)}")
        if self.tangent and u0.shape[1] != 3:
            raise ValueError(f"u0 must have 3 channels with tangent=True, got {u0.shape[1]}")
        if u0.shape[1] < 2:
            raise ValueError(f"u0 must have at least 2 channels (unit vectors), got shape "
                             f"{tuple(u0.shape)}")
        band = self.band_mask(surface)
        region = with_ring(band, surface.layout)
        if not torch.compiler.is_compiling():
            largest = torch.where(region, u0.detach().abs().amax(dim=1, keepdim=True), 1.0)
            if bool((largest == 0).any()):
                raise ValueError("u0 must be unit vectors in the band and its ring; it has zero "
                                 "vectors there, which no renormalisation can make unit")
            if self.tangent:  # P u / |P u| would follow rounding: the directions are noise
                check_tangential(u0, surface, region, "u0 (tangent=True)")
        zero = u0.new_zeros(())
        exponent = self.p - 2.0
        normal, weight, haloed = surface.normal, surface.weight, surface.haloed()
        spacing, eps, path = surface.spacing, self.eps, self.path
        pad = None if surface.layout is None else surface.layout.halo

        between_pieces = self.method not in INTEGRATORS

        def rate(u: Tensor) -> Tensor:
            du = functional.harmonic_map_rate(
                u, normal, weight, spacing, power_diffusivity, exponent, eps, self.p / 2.0,
                self.scheme, path, band, haloed, pad,
            )
            if self.tangent:  # keeps a tangent u tangent between the projections too
                du = tangential_part(du, normal)
            if between_pieces:  # |u| kept: the radial part, which grows off the unit sphere
                length2 = (u * u).sum(dim=1, keepdim=True).clamp_min(torch.finfo(u.dtype).tiny)
                du = du - (du * u).sum(dim=1, keepdim=True) / length2 * u
            return du

        def project(u: Tensor) -> Tensor:
            # in the band and its ring only, as Flow promises (a brick surface's normals equal
            # the dense ones only within the stencils' reach of the band)
            v = u
            if self.tangent:
                n = surface.normal
                v = v - (v * n).sum(dim=1, keepdim=True) * n
            return torch.where(region, normalize(v), u)

        rho = self.eps**exponent * self.operator_bound(surface, self.scheme)
        growth = 0.0
        if self.method == "rkc" and self.steps is None:  # only RKC's own plan reads it
            with torch.no_grad():
                energy = functional.tangential_gradient_energy(project(u0.detach()), normal,
                                                               spacing, path, pad) + eps**2
                growth = float(torch.where(band, energy ** (self.p / 2.0), zero).max())
        stiffness = (eps_stiffness(eps, eps**exponent, spacing) if self.p < 2 else None)
        return System(rate, band, rho, project=project, stiffness=stiffness,
                      params=tensors(surface.normal, surface.weight), growth=growth)

    def _entries_apart(self, u0: Tensor, surface: ImplicitSurface, times: object,
                       inputs: dict[str, Tensor]) -> Tensor | None:
        """As :meth:`Flow._entries_apart`, and where RKC plans its own steps, which follow the
        data's largest ``|P grad u|^p`` (``growth``), data of several entries on a dense
        surface of one run apart too: a smooth field beside a random one took 12 steps
        instead of its 8 and moved by 1.0e-5 (unit sphere, 40^3)."""
        apart = super()._entries_apart(u0, surface, times, inputs)
        if (apart is not None or surface.layout is not None or u0.shape[0] == 1
                or self.method != "rkc" or self.steps is not None):
            return apart
        return self._each_data_entry(u0, surface, times, inputs)

    def extra_repr(self) -> str:
        return f"{super().extra_repr()}, p={self.p:g}, eps={self.eps:g}, tangent={self.tangent}"

