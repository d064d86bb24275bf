"""Nonlinear and directional intrinsic diffusion operators in divergence form (the paper's §2).

- :func:`anisotropic_diffusion`: ``(1/W) div(W g(|P grad u|) P grad u)`` (total variation,
  Perona–Malik, Charbonnier);
- :func:`directional_diffusion`: ``(1/W) div(W (T . P grad u) T)`` along a tangent field T.

Both use the one-sided compositions of :func:`torchsurf.laplace_beltrami` (``"symmetric"``,
``"conservative"`` or ``"octant"``), so with ``g = 1`` (or ``T T^T = P``) they reduce to it with
the same scheme. Their default is ``"symmetric"``, not the Laplace–Beltrami default
``"octant"``: with a nonlinear flux the eight octant compositions do not collapse into one
cheap pass, and cost four times the two symmetric ones.
"""

from __future__ import annotations

import weakref

import torch
from torch import Tensor, nn

from .. import backend
from .._checks import MismatchError, check_choice, check_flag, check_positive, check_positive_tensor
from .._precision import apply_keeping_dtype
from ..surface import ImplicitSurface, check_data, check_direction_batch
from . import functional
from .diffusivity import DIFFUSIVITIES, Diffusivity
from .functional import FLUX_SCHEMES


class CheckedDiffusivity:
    """A user's diffusivity ``g(magnitude, contrast)`` whose result is checked: a tensor of the
    magnitude's shape (or broadcasting to it without widening it), and of its floating dtype
    and device unless 0-d. Otherwise the error came from deep in the stencils, naming padded
    sizes, or from a flow naming its own tensors, and the operators silently returned another
    dtype."""

    def __init__(self, g: Diffusivity) -> None:
        # held weakly where g allows it: torchsurf.backend keeps the arguments of the variants
        # it measured, which would otherwise keep a user's g (a module and its parameters)
        # alive for the whole process; the caller holds g while it runs
        try:
            self._g = weakref.ref(g)
        except TypeError:
            self._g = lambda: g
        self._id = id(g)
        self.__name__ = getattr(g, "__name__", type(g).__name__)

    @property
    def g(self) -> Diffusivity | None:
        """The wrapped ``g`` (``None`` once it is gone)."""
        return self._g()

    # Equal for the same g: each call wraps g anew, and torchsurf.backend keys its compiled
    # variants and eager-time ledger on the arguments; by identity, every call was a variant
    # of its own, never compiled, and the ledger grew by one entry a call.
    def __eq__(self, other: object) -> bool:
        return (isinstance(other, CheckedDiffusivity) and other._id == self._id
                and other.g is self.g)

    def __hash__(self) -> int:
        return hash((CheckedDiffusivity, self._id))

    def __call__(self, magnitude: Tensor, contrast: float | Tensor) -> Tensor:
        value = self.g(magnitude, contrast)
        if not isinstance(value, Tensor):
            raise TypeError(
                f"diffusivity {self.__name__} must return a tensor shaped like its magnitude "
                f"argument {tuple(magnitude.shape)}, got {type(value).__name__}"
            )
        try:
            fits = torch.broadcast_shapes(value.shape, magnitude.shape) == magnitude.shape
        except RuntimeError:
            fits = False
        if not fits:
            raise ValueError(
                f"diffusivity {self.__name__} returned shape {tuple(value.shape)} for a "
                f"magnitude of shape {tuple(magnitude.shape)}: g(s, K) acts on each value of s"
            )
        # a 0-d tensor takes the data's dtype in arithmetic, as an integer or bool result does
        promotes = value.is_floating_point() and value.dtype != magnitude.dtype
        if value.dim() > 0 and (promotes or value.device != magnitude.device):
            raise MismatchError(
                f"diffusivity {self.__name__} returned {value.dtype} on {value.device} for a "
                f"magnitude of {magnitude.dtype} on {magnitude.device}: g(s, K) must keep the "
                "dtype and device of s (the data's)"
            )
        return value


def stored_diffusivity(diffusivity: str | Diffusivity) -> Diffusivity:
    """What a module keeps: the library's function for a name, else the callable as given (an
    ``nn.Module`` ``g`` then registers as a submodule, its parameters the module's); its
    forward passes it through :func:`resolve_diffusivity`."""
    return diffusivity if callable(diffusivity) else resolve_diffusivity(diffusivity)


def resolve_diffusivity(diffusivity: str | Diffusivity) -> Diffusivity:
    """A diffusivity callable from its name in :data:`DIFFUSIVITIES`, the library's own
    function itself, or a user's callable wrapped to check its results
    (:class:`CheckedDiffusivity`)."""
    if isinstance(diffusivity, CheckedDiffusivity) or any(
            diffusivity is g for g in DIFFUSIVITIES.values()):
        return diffusivity
    if callable(diffusivity):
        return CheckedDiffusivity(diffusivity)
    return DIFFUSIVITIES[check_choice(diffusivity, "diffusivity", tuple(DIFFUSIVITIES))]


def channel_contrast(contrast: float | Tensor, u: Tensor) -> float | Tensor:
    """A checked contrast: a float, or a tensor ``()`` / ``(C,)`` shaped to broadcast over
    ``u`` ``(B, C, D, H, W)``."""
    if not isinstance(contrast, Tensor):
        return check_positive(contrast, "contrast")
    check_positive_tensor(contrast, "contrast")
    if contrast.dim() == 0:
        return contrast
    if contrast.dim() != 1 or contrast.shape[0] not in (1, u.shape[1]):
        raise ValueError(
            f"contrast must be a number, a scalar tensor or a tensor (C,) = ({u.shape[1]},), "
            f"got shape {tuple(contrast.shape)}"
        )
    if contrast.dtype != u.dtype or contrast.device != u.device:
        raise MismatchError(
            f"contrast is {contrast.dtype} on {contrast.device} but u is {u.dtype} on "
            f"{u.device}: convert one of them (a (C,) contrast would change u's dtype)")
    return contrast.view(1, -1, 1, 1, 1)


def anisotropic_diffusion(
    u: Tensor,
    surface: ImplicitSurface,
    diffusivity: str | Diffusivity = "total_variation",
    contrast: float | Tensor = 1.0,
    eps: float = 1e-3,
    coupled: bool = False,
    scheme: str = "symmetric",
    path: str = "auto",
) -> Tensor:
    """Edge-stopping intrinsic diffusion ``(1/W) div(W g(|P grad u|) P grad u)``.

    ``|P grad u|`` is regularised as ``sqrt(|P grad u|^2 + eps^2)`` so that the operator and
    its gradients stay finite where the data is flat. Explicit steps of
    ``u_t = L u`` are stable for ``dt <= h^2 / (6 max g)``; for total variation ``max g = 1/eps``.

    The operator converges at second order once ``g(|P grad u|)`` varies over several cells;
    where it changes within a cell or two (a contrast ``K`` small against the data's gradients)
    the grid does not resolve it: on a torus function with Perona–Malik at ``K = 1.5`` the error
    stayed at 40-75% up to 64^3 (at ``K = 6``: orders 2.1-2.5; an audit, 2026-12-07).
    ``|P grad u|`` is read from one-sided differences, off by about ``h |Hess u| / 2`` (the
    Hessian's normal part too), so the second-order regime also needs ``h |Hess u|`` small
    against ``eps`` (or ``K``): on a torus with data that varies along the normals, total
    variation at ``eps = 0.5`` erred by 4-10% at 48^3-64^3 with no steady order, 2.8% at
    ``eps = 1`` and 1.4% at ``eps = 2``, converging (an audit, 2026-12-07). Data constant along
    the normals (the flows' re-extended data) feel it less (4.3% at ``eps = 0.5``, 64^3).

    Args:
        u: ``(B, C, D, H, W)``.
        surface: the implicit surface (batch 1 or B).
        diffusivity: ``"total_variation"`` (default; eq. 10), ``"perona_malik"``,
            ``"charbonnier"``, or a callable ``g(magnitude, contrast)``.
        contrast: edge threshold ``K`` in units of ``u`` per world length: a number, or a
            tensor ``()`` or ``(C,)`` (for example a positive ``nn.Parameter``); finite and > 0.
        eps: regularisation of ``|P grad u|``, units of ``u`` per world length.
        coupled: measure ``|P grad u|`` over all channels together (vector-valued data, as in
            the harmonic-map flow) instead of per channel.
        scheme: ``"symmetric"`` (default), ``"conservative"`` (Appendix B) or ``"octant"``
            (see :func:`torchsurf.laplace_beltrami`).
            ``"symmetric"`` is not mirror-symmetric: data even in ``x`` on a sphere (32^3) is
            not even after a total-variation flow (3.3e-2 of the range on noise; Perona-Malik
            1.0e-2); ``"octant"`` keeps the grid's mirrors and quarter turns to rounding.
        path: how stencils are applied (see :func:`torchsurf.laplace_beltrami`).

    Returns:
        ``(B, C, D, H, W)``, units of ``u`` per world length squared times ``g``.
    """
    check_data(u, "u", surface)
    check_choice(scheme, "scheme", FLUX_SCHEMES)
    check_choice(path, "path", backend.PATHS)
    return functional.edge_stopping_form(
        u, surface.normal, surface.weight, surface.spacing, resolve_diffusivity(diffusivity),
        channel_contrast(contrast, u), check_positive(eps, "eps"), check_flag(coupled, "coupled"),
        scheme, path,
        haloed=surface.haloed(), pad=None if surface.layout is None else surface.layout.halo,
    )


def directional_diffusion(
    u: Tensor,
    surface: ImplicitSurface,
    direction: Tensor,
    scheme: str = "symmetric",
    path: str = "auto",
) -> Tensor:
    """Diffusion along a tangent field: ``(1/W) div(W (T . P grad u) T)`` (eq. 14, §3.4).

    Explicit steps are stable for ``dt <= h^2 / (6 max |T|^2)``.

    Args:
        u: ``(B, C, D, H, W)``; on a :class:`~torchsurf.bricks.BrickSurface`, a packed field
            ``(N, C, 8, 8, 8)``.
        surface: the implicit surface (batch 1 or B).
        direction: ``T``, ``(B or 1, 3, D, H, W)`` in ``(x, y, z)`` order (packed
            ``(N, 3, 8, 8, 8)`` on bricks), usually of unit length (e.g. a principal
            direction); its part along the normals is dropped (``P T`` is used, so that the
            result is intrinsic: ``T`` and ``P T`` give the same, and the normals nothing).
            Nothing checks that it has a tangent part: a field along the normals (or zero)
            gives zero, where :class:`~torchsurf.FlowVisualization` refuses it.
        scheme: ``"symmetric"`` (default), ``"conservative"`` or ``"octant"``.
        path: how stencils are applied.

    Returns:
        ``(B, C, D, H, W)``.
    """
    check_data(u, "u", surface)
    check_data(direction, "direction", surface, channels=3)
    check_direction_batch(direction, u, "u", surface)
    check_choice(scheme, "scheme", FLUX_SCHEMES)
    check_choice(path, "path", backend.PATHS)
    return functional.directional_form(
        u, surface.normal, surface.weight, surface.spacing, direction, scheme, path,
        haloed=surface.haloed(), pad=None if surface.layout is None else surface.layout.halo,
        tangent=True,
    )


def _initial_contrast(contrast: float | Tensor) -> float | Tensor:
    """``contrast`` checked as far as it can be before the data is seen (its channel count is
    checked in the forward): a number, or a tensor ``()`` / ``(C,)``, finite and positive."""
    if not isinstance(contrast, Tensor):
        return check_positive(contrast, "contrast")
    check_positive_tensor(contrast.detach(), "contrast")
    if contrast.dim() > 1:
        raise ValueError(f"contrast must be a number, a scalar tensor or a tensor (C,), got "
                         f"shape {tuple(contrast.shape)}")
    return contrast


class AnisotropicDiffusion(nn.Module):
    """Module form of :func:`anisotropic_diffusion`: ``(B, C, D, H, W) -> (B, C, D, H, W)``.

    ``contrast`` may be an ``nn.Parameter`` (shape ``()`` or ``(C,)``); it is registered with
    the module so that an optimiser sees it. A contrast computed from a parameter (such as
    ``log_contrast.exp()``, to keep it positive) belongs in the call of the functional form,
    :func:`anisotropic_diffusion`, made at every step by a module of one's own: given here it
    would be computed once, and refused; the parameter must have the data's dtype and device
    (:class:`~torchsurf.MismatchError`). Another tensor that records no gradient is copied into
    a buffer: it follows ``.to()`` and ``state_dict``, and is read in the data's dtype, as the
    flows' fixed values are.

    Args:
        diffusivity, contrast, eps, coupled, scheme, path: as :func:`anisotropic_diffusion`'s
            (``diffusivity`` a name or a callable ``g(magnitude, contrast)``; ``contrast`` and
            ``eps`` in units of ``u`` per world length).
    """

    def __init__(
        self,
        diffusivity: str | Diffusivity = "total_variation",
        contrast: float | Tensor = 1.0,
        eps: float = 1e-3,
        coupled: bool = False,
        scheme: str = "symmetric",
        path: str = "auto",
    ) -> None:
        super().__init__()
        self.diffusivity = stored_diffusivity(diffusivity)
        contrast = _initial_contrast(contrast)
        if (isinstance(contrast, Tensor) and not isinstance(contrast, nn.Parameter)
                and contrast.grad_fn is not None):
            raise ValueError(
                "contrast is computed from a parameter (it requires grad and is no "
                "nn.Parameter): computed once here, its graph would be backpropagated through "
                "twice at the second step; pass the nn.Parameter itself, or call "
                "torchsurf.anisotropic_diffusion(u, surface, ..., contrast=log_contrast.exp()) "
                "in your module's forward")
        if (isinstance(contrast, Tensor) and not isinstance(contrast, nn.Parameter)
                and not contrast.requires_grad):
            self.register_buffer("contrast", contrast.clone())
        else:
            self.contrast = contrast
        self.eps = check_positive(eps, "eps")
        self.coupled = check_flag(coupled, "coupled")
        self.scheme = check_choice(scheme, "scheme", FLUX_SCHEMES)
        self.path = check_choice(path, "path", backend.PATHS)

    def _apply(self, fn, recurse=True):  # noqa: ANN001, ANN202
        return apply_keeping_dtype(self, ("contrast",), lambda: super(AnisotropicDiffusion, self)
                                   ._apply(fn, recurse))

    def forward(self, u: Tensor, surface: ImplicitSurface) -> Tensor:
        """``(1/W) div(W g(|P grad u|) P grad u)``: ``(B, C, D, H, W) -> (B, C, D, H, W)``, units
        of ``u`` per world length squared (:func:`anisotropic_diffusion`)."""
        contrast = self.contrast
        if isinstance(contrast, Tensor) and not contrast.requires_grad:
            contrast = contrast.to(u.dtype)  # a fixed setting, as the flows' fixed values
        return anisotropic_diffusion(
            u, surface, self.diffusivity, contrast, self.eps, self.coupled, self.scheme,
            self.path,
        )

    def extra_repr(self) -> str:
        name = next((key for key, value in DIFFUSIVITIES.items() if value is self.diffusivity),
                    getattr(self.diffusivity, "__name__", repr(self.diffusivity)))
        contrast = (f"{self.contrast:g}" if not isinstance(self.contrast, Tensor)
                    else f"tensor{tuple(self.contrast.shape)}")
        return (f"{name!r}, contrast={contrast}, eps={self.eps:g}, coupled={self.coupled}, "
                f"scheme={self.scheme!r}, path={self.path!r}")


class DirectionalDiffusion(nn.Module):
    """Module form of :func:`directional_diffusion`: ``(B, C, D, H, W) -> (B, C, D, H, W)``.

    Args:
        scheme, path: as :func:`directional_diffusion`'s.
    """

    def __init__(self, scheme: str = "symmetric", path: str = "auto") -> None:
        super().__init__()
        self.scheme = check_choice(scheme, "scheme", FLUX_SCHEMES)
        self.path = check_choice(path, "path", backend.PATHS)

    def forward(self, u: Tensor, surface: ImplicitSurface, direction: Tensor) -> Tensor:
        """Diffusion of ``u`` ``(B, C, D, H, W)`` on ``surface`` along ``direction`` ``(B or 1,
        3, D, H, W)``: ``(B, C, D, H, W)`` (:func:`directional_diffusion`)."""
        return directional_diffusion(u, surface, direction, self.scheme, self.path)

    def extra_repr(self) -> str:
        return f"scheme={self.scheme!r}, path={self.path!r}"
