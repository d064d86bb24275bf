"""Edge-stopping intrinsic diffusion ``u_t = (1/W) div(W g(|P grad u|) P grad u)`` (the paper's §3.1)."""

from __future__ import annotations

from torch import Tensor, nn

from .._checks import check_choice, check_positive
from ..backend import PATHS
from ..operators import functional
from ..operators.diffusion import (
    FLUX_SCHEMES,
    channel_contrast,
    resolve_diffusivity,
    stored_diffusivity,
)
from ..operators.diffusivity import DIFFUSIVITIES, Diffusivity
from ..surface import ImplicitSurface
from ._integrators import System, eps_stiffness, tensors
from ._positive import Positive
from .base import Flow

_BOUNDED = ("perona_malik", "charbonnier")


class AnisotropicFlow(Flow):
    """Total-variation, Perona–Malik or Charbonnier flow of scalar (or per-channel) data on S.

    ``|P grad u|`` is regularised as ``sqrt(|P grad u|^2 + eps^2)``
    (:func:`torchsurf.anisotropic_diffusion`). The flow is the gradient descent of
    ``sum W G(|P D u|)`` (``G' = s g(s)``), so a stable step never increases that energy; the
    band's re-extensions between steps can, where S has sharp creases (docs/band.md, "Sharp
    creases").

    Spectral bound: ``max g * rho``, ``rho`` the Gershgorin bound of the band's
    Laplace–Beltrami operator (about ``10 / h^2`` on a distance, 14-15 on meshes' phi;
    docs/band.md): ``max g = 1`` for
    Perona–Malik and Charbonnier, ``1 / eps`` for total variation (so TV's explicit steps scale
    with ``eps`` and its RKC stages with ``sqrt(1 / eps)``; choose ``eps`` at the scale of the
    smallest gradient worth keeping). For a callable ``g``, pass ``max_diffusivity``.

    Time accuracy: the steps matter less than the band's re-extensions. On the unit sphere at
    24^3 (box ``[-1.5, 1.5]^3``, float64, Perona–Malik to ``4 h^2`` on ``3 z^2 - 1`` of the
    direction), RKC's 8 default steps are 6.0e-4 from 64 RKC steps and Euler's 29 are 9.0e-4
    from 464 Euler steps, and those two finer runs are 2.4e-3 apart: runs differ
    mostly in how often they re-extend the band, which on noise at the grid's scale is part of
    the smoothing
    (at 40^3 with noise 0.2, Perona–Malik's result moved by 0.11 when re-extended twice as
    often). Compare noisy runs at the same method and settings (docs/band.md §4). For total
    variation keep the default RKC: Euler's and Heun's re-extensions, every ``12 / rho`` with
    ``rho`` growing as ``1 / eps``, kept 0.982 of a calibrable hemisphere's plateau where the
    exact flow, and RKC, leave 0.95 (unit sphere, 24^3, ``t = 0.05``).

    The edge-stopping diffusivities damp little across edges: on surfaces thinner than the band
    or folded within it, keep the default method; Perona–Malik's Euler steps grew without bound
    on a trefoil mesh at 32^3 where RKC's did not (docs/band.md §5; a call that leaves the
    range of ``u0`` warns, :attr:`~torchsurf.flows.Flow.keeps_range`).

    Args:
        time: physical end time, world units squared times ``g``.
        diffusivity: ``"total_variation"`` (default), ``"perona_malik"``, ``"charbonnier"`` or
            a callable ``g(magnitude, contrast)``.
        contrast: edge threshold ``K``, units of ``u`` per world length; a positive number or
            one per channel ``(C,)``.
        learn_contrast: make ``K`` an ``nn.Parameter`` (kept positive by softplus); refused
            for ``"total_variation"``, which reads no ``K``.
        eps: regularisation of ``|P grad u|``, units of ``u`` per world length.
        max_diffusivity: upper bound of ``g`` for a callable ``diffusivity`` (else read
            from ``diffusivity`` and ``eps``: :attr:`max_diffusivity`).
        scheme: ``"symmetric"`` (default), ``"conservative"`` or ``"octant"``.
            ``"symmetric"`` is not mirror-symmetric: data even in ``x`` on a sphere (32^3) is
            not even after a total-variation flow (3.3e-2 of the range on noise; Perona-Malik
            1.0e-2); ``"octant"`` keeps the grid's mirrors and quarter turns to rounding.
        path: how stencils are applied.
        **kwargs: the integration settings of :class:`Flow` (no implicit methods: nonlinear).

    Shapes: ``u0`` ``(B, C, D, H, W)`` -> ``(B, C, D, H, W)``.
    """

    supports_bricks = True
    linear = False

    def __init__(
        self,
        time: float,
        diffusivity: str | Diffusivity = "total_variation",
        contrast: float | Tensor = 1.0,
        learn_contrast: bool = False,
        eps: float = 1e-2,
        max_diffusivity: float | None = None,
        scheme: str = "symmetric",
        path: str = "auto",
        **kwargs: object,
    ) -> None:
        super().__init__(time, **kwargs)
        self.diffusivity = stored_diffusivity(diffusivity)
        if self._name() == "total_variation" and learn_contrast:
            raise ValueError("learn_contrast=True: total variation's g(s) = 1 / s reads no "
                             "contrast, so its parameter would never get a gradient; learn "
                             "the time, or choose 'perona_malik' or 'charbonnier'")
        self.contrast = Positive(contrast, "contrast", learnable=learn_contrast)
        self.eps = eps
        self.max_diffusivity = max_diffusivity
        _ = self.max_diffusivity  # a callable g without a bound is refused here
        self.scheme = check_choice(scheme, "scheme", FLUX_SCHEMES)
        self.path = check_choice(path, "path", PATHS)

    def _name(self) -> str | None:
        """The library's name of :attr:`diffusivity` (a name, checked, or the library's
        function itself), or ``None`` for a user's own ``g``."""
        if isinstance(self.diffusivity, str):
            return check_choice(self.diffusivity, "diffusivity", tuple(DIFFUSIVITIES))
        return next((key for key, g in DIFFUSIVITIES.items() if self.diffusivity is g), None)

    def __setstate__(self, state: dict) -> None:
        # a flow pickled before eps and max_diffusivity were properties (2026-12-07) holds
        # them, and keeps_range, as plain attributes
        for old, new in (("eps", "_eps"), ("max_diffusivity", "_max_diffusivity")):
            if old in state:
                state[new] = state.pop(old)
        state.pop("keeps_range", None)
        super().__setstate__(state)

    @property
    def keeps_range(self) -> bool:
        """Whether the flow keeps ``u`` within the range of ``u0``: the library's own ``g``
        (a user's own may be negative somewhere)."""
        return self._name() is not None

    @property
    def eps(self) -> float:
        """Regularisation of ``|P grad u|``, units of ``u`` per world length; settable (total
        variation's bound follows it)."""
        return self._eps

    @eps.setter
    def eps(self, value: float) -> None:
        self._eps = check_positive(value, "eps")

    @property
    def max_diffusivity(self) -> float:
        """The upper bound of ``g`` that the steps follow: the one given, else ``1 / eps``
        for total variation and 1 for Perona–Malik and Charbonnier, read from the current
        :attr:`diffusivity` and :attr:`eps` (settable; ``None`` for those defaults).

        Raises:
            ValueError: a callable ``diffusivity`` without a bound given.
        """
        if self._max_diffusivity is not None:
            return self._max_diffusivity
        name = self._name()
        if name == "total_variation":
            return 1.0 / self.eps
        if name in _BOUNDED:
            return 1.0
        raise ValueError(
            "max_diffusivity: give the upper bound of a callable diffusivity g "
            "(it sets the spectral bound max g * rho of the steps)"
        )

    @max_diffusivity.setter
    def max_diffusivity(self, value: float | None) -> None:
        self._max_diffusivity = (None if value is None
                                 else check_positive(value, "max_diffusivity"))

    def system(self, u0: Tensor, surface: ImplicitSurface, **inputs: Tensor) -> System:
        """:meth:`Flow.system` of the edge-stopping flow: its rate in the band, ``u0``
        ``(B, C, D, H, W)`` (packed on bricks), no inputs besides."""
        if inputs:
            raise TypeError(f"AnisotropicFlow takes no extra inputs, got {sorted(inputs)}")
        band = self.band_mask(surface)
        contrast = self.contrast.value()
        if isinstance(contrast, Tensor):
            contrast = contrast.to(u0.dtype)
        shaped = channel_contrast(contrast, u0)
        diffusivity = resolve_diffusivity(self.diffusivity)
        pad = None if surface.layout is None else surface.layout.halo

        def rate(u: Tensor) -> Tensor:
            # the band's mask applied in the operator's own pass
            return functional.edge_stopping_form(
                u, surface.normal, surface.weight, surface.spacing, diffusivity, shaped,
                self.eps, False, self.scheme, self.path, haloed=surface.haloed(), pad=pad,
                mask=band)

        rho = self.max_diffusivity * self.operator_bound(surface, self.scheme)
        # a g that is a module learns its parameters through the recomputed steps too
        learned = tuple(self.diffusivity.parameters()) if isinstance(self.diffusivity,
                                                                     nn.Module) else ()
        set_by_eps = (self._name() == "total_variation"
                      and self.max_diffusivity == 1.0 / self.eps)  # not a bound of the user's
        stiffness = (eps_stiffness(self.eps, self.max_diffusivity, surface.spacing)
                     if set_by_eps else None)
        return System(rate, band, rho, stiffness=stiffness,
                      params=tensors(contrast, surface.normal, surface.weight, *learned))

    def extra_repr(self) -> str:
        name = self._name() or getattr(self.diffusivity, "__name__", "custom")
        return (f"{super().extra_repr()}, diffusivity={name!r}, eps={self.eps:g}, "
                f"scheme={self.scheme!r}")
