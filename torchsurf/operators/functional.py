"""Intrinsic operators on tensors: what the surface-level functions, the flows and users call.

Each takes the geometry as tensors rather than an :class:`~torchsurf.ImplicitSurface`, so that
autograd reaches every one of them and a flow can hand them to its integrator:

- ``normal``: unit normals ``n = grad phi / |grad phi|``, ``(B or 1, 3, D, H, W)`` in
  ``(x, y, z)`` order (:attr:`ImplicitSurface.normal`);
- ``weight``: ``W``, the floored ``|grad phi|`` of the divergence forms, ``(B or 1, 1, D, H, W)``
  (:attr:`ImplicitSurface.weight`);
- ``spacing``: the grid spacing ``h``, world units;
- ``haloed``: optionally ``(normal, weight)`` with a halo of one node, as
  :meth:`ImplicitSurface.haloed` keeps them, which spares the compiled kernels their padding.

Data ``u`` is ``(B, C, D, H, W)``. Every function takes ``path`` (:mod:`torchsurf.backend`):
``"auto"`` (default), ``"slicing"``, ``"conv3d"`` or ``"compiled"``, all giving the same numbers
to rounding. Each checks its arguments' shapes (channel counts, batch sizes that broadcast,
equal grids, masks, haloed geometry, contrast), dtypes, flags, spacing and scheme, not their
values; the surface-level functions
(:func:`torchsurf.laplace_beltrami`, ...) check everything.

The divergence forms ``L u = (1/W) div(W f(P grad u))`` come in three schemes (see
:func:`torchsurf.laplace_beltrami` for their orders and errors): ``"octant"``, ``"symmetric"``,
``"conservative"``. The linear ones are ``W^-1 A`` with ``A`` symmetric negative semi-definite;
``weighted=True`` returns ``A u = W L u``, the form conjugate gradients needs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .. import backend, stencils
from .._checks import SUPPORTED_DTYPES, check_alike, check_flag, check_positive
from .._native import carries_tangents
from .._vectors import tangential_part
from ..stencils import masked, replicated_halo
from ._coupled import eager_coupled_rate, fused_coupled_rate
from ._flux_form import (
    SIDES,
    Components,
    FluxMap,
    flux_form,
    fused_flux_form,
)
from ._octant import eager_octant, fused_octant
from .diffusivity import Diffusivity

SCHEMES = ("octant", "symmetric", "conservative")
"""The divergence-form schemes."""


def _check_inputs(u: Tensor, normal: Tensor, spacing: float, weight: Tensor | None = None,
                  scheme: str | None = None, schemes: Sequence[str] = SCHEMES,
                  direction: Tensor | None = None, mean_curvature: Tensor | None = None,
                  vector: bool = False, required: Sequence[str] = ("weight",)) -> float:
    """The cheap checks of this layer's arguments (shapes, dtypes, the spacing and the scheme):
    what would otherwise give a wrong shape, a bare ``KeyError`` or a size mismatch between
    padded tensors deep in a kernel. Shapes and dtypes only, no values; the surface-level
    functions check the rest. ``vector``: ``u`` is a field of 3-vectors, ``(B, 3C, D, H, W)``
    (named ``v``); ``required``: the optional arguments the caller needs (``None`` among them
    is a ``TypeError``). Returns the spacing as a float."""
    data = "v" if vector else "u"
    for name, value in ((data, u), ("normal", normal), ("weight", weight),
                        ("direction", direction), ("mean_curvature", mean_curvature)):
        if value is None and (name in required or name in (data, "normal")):
            raise TypeError(f"{name} must be a torch.Tensor, got None")
        if value is not None and not isinstance(value, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
        if value is not None and value.dtype not in SUPPORTED_DTYPES:
            raise TypeError(f"{name} must be a float32 or float64 tensor (the dtypes torchsurf "
                            f"supports), got dtype {value.dtype}")
    if u.dim() != 5:
        raise ValueError(f"{data} must be a (B, C, D, H, W) tensor, got shape {tuple(u.shape)}")
    if u.shape[1] == 0:
        raise ValueError(f"{data} must have at least one channel, got shape {tuple(u.shape)}")
    if 0 in u.shape[2:]:
        raise ValueError(f"{data} must have nodes along every axis, got shape {tuple(u.shape)}")
    if vector and u.shape[1] % 3:
        raise ValueError(f"v must hold 3 components a channel, (B, 3C, D, H, W), got "
                         f"{u.shape[1]} channels (shape {tuple(u.shape)})")
    check_alike([(data, u, None), ("normal", normal, 3), ("weight", weight, 1),
                 ("direction", direction, 3), ("mean_curvature", mean_curvature, 1)])
    spacing = check_positive(spacing, "spacing")
    if scheme is not None and scheme not in schemes:
        raise ValueError(f"scheme must be one of {tuple(schemes)}, got {scheme!r}")
    return spacing


def _check_extras(u: Tensor, normal: Tensor, mask: Tensor | None = None, haloed: object = None,
                  weighted: object = False, diffusivity: object = None,
                  contrast: object = None) -> None:
    """The cheap checks of the optional arguments (shapes and types, no values): a mask of
    another shape broadcast the result to it, a haloed geometry without its halo failed deep
    in a kernel, and ``weighted="no"`` was read as true."""
    spatial = tuple(u.shape[2:])
    if mask is not None:
        if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
            raise TypeError(f"mask must be a bool tensor, got "
                            f"{mask.dtype if isinstance(mask, Tensor) else type(mask).__name__}")
        batch = max(u.shape[0], normal.shape[0])  # the result's: u and the geometry broadcast
        if (mask.dim() != 5 or mask.shape[1] != 1 or mask.shape[0] not in (1, batch)
                or tuple(mask.shape[2:]) != spatial):
            raise ValueError(f"mask must have shape ({batch} or 1, 1, *{spatial}) for u of shape "
                             f"{tuple(u.shape)} and normal of shape {tuple(normal.shape)}, got "
                             f"{tuple(mask.shape)}")
    if haloed is not None:
        halo = tuple(n + 2 for n in spatial)
        if (not isinstance(haloed, (tuple, list)) or len(haloed) != 2
                or not all(isinstance(t, Tensor) and t.dim() == 5 for t in haloed)):
            raise TypeError("haloed must be a pair (normal, weight) of 5-D tensors with a halo "
                            "of one node, or None")
        for name, tensor, channels in (("haloed[0] (normal)", haloed[0], 3),
                                       ("haloed[1] (weight)", haloed[1], 1)):
            if tensor.shape[1] != channels or tuple(tensor.shape[2:]) != halo:
                raise ValueError(f"{name} must have shape (B or 1, {channels}, *{halo}) (one "
                                 f"node of halo around u's {spatial}), got {tuple(tensor.shape)}")
    check_flag(weighted, "weighted")
    if diffusivity is not None and not callable(diffusivity):
        raise TypeError(f"diffusivity must be a function g(magnitude, contrast) (see "
                        f"torchsurf.operators.diffusivity; the surface-level "
                        f"anisotropic_diffusion takes names), got {diffusivity!r}")
    if isinstance(contrast, Tensor):
        result = (max(u.shape[0], normal.shape[0]), *u.shape[1:])
        try:
            shape = tuple(torch.broadcast_shapes(contrast.shape, result))
        except RuntimeError:
            shape = None
        if shape != result:
            raise ValueError(f"contrast must broadcast to the result's shape {result} (e.g. "
                             f"(1, C, 1, 1, 1)), got shape {tuple(contrast.shape)}")


Haloed = tuple[Tensor, Tensor] | None

Pad = Callable[[Tensor, int], Tensor]
"""``pad(u, width) -> u`` with a halo of ``width`` nodes from where ``u`` is stored: for packed
band fields, :meth:`torchsurf.bricks.BrickLayout.halo`. Given, an operator runs its one-pass
form on the haloed inputs (``haloed`` geometry required) and imposes no box faces. A ``pad``
bound to an object with a ``native_octant`` method (a brick layout) lets ``path="auto"`` run
the octant scheme by that method where it applies (:mod:`torchsurf.bricks._native`)."""


def _geometry_halo(normal: Tensor, weight: Tensor, haloed: Haloed) -> tuple[Tensor, Tensor]:
    if haloed is not None:
        return haloed
    return stencils.pad_mirrored(normal), stencils.pad(weight, "replicate")


def _weighted(result: Tensor, weight: Tensor, weighted: bool) -> Tensor:
    return weight * result if weighted else result


# --- Laplace–Beltrami: the octant scheme and the flux-form schemes -------------------------


def _octant_eager(u, normal, weight, spacing, weighted, haloed, mask, *, path):  # noqa: ANN001, ANN202
    result = flux_form(u, normal, weight, spacing, None, (), "octant", path)
    return masked(_weighted(result, weight, weighted), mask)


def _octant_halo(u, normal, weight, spacing, weighted, haloed, mask):  # noqa: ANN001, ANN202
    return (replicated_halo(u, 1), *_geometry_halo(normal, weight, haloed), weight, spacing, weighted,
            mask)


_OCTANT = backend.Kernel(
    "laplace_beltrami_octant", _octant_eager, fused_octant, _octant_halo, fused_when_eager=True,
    eager_fused=eager_octant,
)


def _flux_lb_eager(u, normal, weight, spacing, scheme, weighted, haloed, *, path):  # noqa: ANN001, ANN202
    return _weighted(flux_form(u, normal, weight, spacing, None, (), scheme, path), weight, weighted)


def _flux_lb_fused(padded_u, haloed_normal, haloed_weight, weight, spacing, scheme, weighted):  # noqa: ANN001, ANN202
    return fused_flux_form(
        padded_u, haloed_normal, haloed_weight, weight, spacing, None, (), scheme, weighted
    )


def _flux_lb_halo(u, normal, weight, spacing, scheme, weighted, haloed):  # noqa: ANN001, ANN202
    return (replicated_halo(u, 2), *_geometry_halo(normal, weight, haloed), weight, spacing, scheme,
            weighted)


_FLUX_LB = backend.Kernel("laplace_beltrami_flux_form", _flux_lb_eager, _flux_lb_fused, _flux_lb_halo)


def _flux_lb_open(padded_u, haloed_normal, haloed_weight, weight, spacing, scheme, weighted):  # noqa: ANN001, ANN202
    return fused_flux_form(padded_u, haloed_normal, haloed_weight, weight, spacing, None, (),
                           scheme, weighted, box_faces=False)


_FLUX_LB_OPEN = backend.Kernel("laplace_beltrami_flux_form_open", _flux_lb_eager, _flux_lb_open)


def _require_haloed(haloed: Haloed) -> tuple[Tensor, Tensor]:
    if haloed is None:
        raise ValueError("pad= needs haloed=(normal, weight) with a halo of one node")
    return haloed


def _apply_linear(u, normal, weight, spacing, scheme, weighted, haloed, path, pad=None,  # noqa: ANN001, ANN202
                  mask=None):
    if pad is not None:
        haloed_normal, haloed_weight = _require_haloed(haloed)
        if scheme == "octant":
            native = getattr(getattr(pad, "__self__", None), "native_octant", None)
            # not while torch.compile traces: the outer compiler sees plain tensor operations
            if path == "auto" and native is not None and not torch.compiler.is_compiling():
                result = native(u, haloed_normal, haloed_weight, spacing, weighted, mask)
                if result is not None:
                    return result
            return backend.run_haloed(_OCTANT, path, u, pad(u, 1), haloed_normal, haloed_weight,
                                      weight, spacing, weighted, mask)
        return masked(backend.run_haloed(_FLUX_LB_OPEN, path, u, pad(u, 2), haloed_normal,
                                          haloed_weight, weight, spacing, scheme, weighted), mask)
    if scheme == "octant":
        return backend.run(_OCTANT, path, u, u, normal, weight, spacing, weighted, haloed, mask)
    return masked(backend.run(_FLUX_LB, path, u, u, normal, weight, spacing, scheme, weighted,
                               haloed), mask)


class _SelfAdjoint(torch.autograd.Function):
    """Backward of ``L`` w.r.t. ``u`` by its transpose ``L^T g = W L(g / W)``: one
    forward-sized pass, where backpropagating through the stencils costs about twice as much.
    Only for a fixed geometry (no gradient to the normals or ``W``). With a mask ``M``
    (``M L u``), ``L^T M g``."""

    @staticmethod
    def forward(ctx, u, normal, weight, spacing, scheme, weighted, haloed, path, pad, mask):  # noqa: ANN001, ANN205
        ctx.geometry = (normal, weight, spacing, scheme, weighted, haloed, path, pad, mask,
                        u.shape[0])
        return _apply_linear(u, normal, weight, spacing, scheme, weighted, haloed, path, pad,
                             mask)

    @staticmethod
    @backend.part_of_recorded
    def backward(ctx, grad_output):  # noqa: ANN001, ANN205
        normal, weight, spacing, scheme, weighted, haloed, path, pad, mask, batch = ctx.geometry
        source = masked(grad_output, mask)
        # A = W L is symmetric: (W^-1 A)^T g = A (g / W), and A^T g = A g
        source = source if weighted else source / weight
        grad_u = _apply_linear(source, normal, weight, spacing, scheme, True, haloed, path, pad)
        if grad_u.shape[0] != batch:
            grad_u = grad_u.sum(dim=0, keepdim=True)
        return grad_u, None, None, None, None, None, None, None, None, None


def divergence_form(
    u: Tensor, normal: Tensor, weight: Tensor, spacing: float, scheme: str = "octant",
    path: str = "auto", weighted: bool = False, haloed: Haloed = None, pad: Pad | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """The Laplace–Beltrami operator ``L u = (1/W) div(W P grad u)`` in divergence form.

    Args:
        u: ``(B, C, D, H, W)``, or packed band bricks ``(N, C, 8, 8, 8)`` with ``pad``.
        normal, weight, spacing, haloed: the geometry (module docstring).
        scheme: ``"octant"`` (default), ``"symmetric"`` or ``"conservative"``.
        path: how the stencils run (:mod:`torchsurf.backend`).
        weighted: return ``W L u`` (symmetric negative semi-definite) instead.
        pad: how ``u`` gets its halo (:data:`Pad`); ``None`` for a dense volume.
        mask: ``(B or 1, 1, D, H, W)`` bool (packed like ``u`` with ``pad``): the result is zero
            where it is false (a flow's band); the octant scheme applies it in its one pass.

    Returns:
        ``u``'s shape, units of ``u`` per world length squared (times ``W`` if weighted).
    """
    spacing = _check_inputs(u, normal, spacing, weight, scheme)
    _check_extras(u, normal, mask, haloed, weighted)
    if normal.requires_grad or weight.requires_grad or carries_tangents(u) or not (
            torch.is_grad_enabled() and u.requires_grad):
        # no autograd node needed where autograd records nothing (a custom Function's call
        # costs as much as the stencil itself at 37^3)
        return _apply_linear(u, normal, weight, spacing, scheme, weighted, haloed, path, pad,
                             mask)
    return _SelfAdjoint.apply(u, normal, weight, spacing, scheme, weighted, haloed, path, pad,
                              mask)


# --- Nonlinear and directional fluxes ------------------------------------------------------


def edge_stopping_flux(
    diffusivity: Diffusivity, contrast: float | Tensor, eps: float, coupled: bool
) -> FluxMap:
    """The flux map ``v -> g(sqrt(|v|^2 + eps^2), K) v`` of edge-stopping diffusion.

    ``|v|^2`` sums over the channels too when ``coupled``. ``contrast`` is a float or a tensor
    broadcastable to ``(B, C, D, H, W)``.
    """
    def flux(v: Components, fields: Sequence[Tensor], side: int) -> Components:
        scale = _edge_scale(v, diffusivity, contrast, eps, coupled)
        return scale * v[0], scale * v[1], scale * v[2]

    return flux


def _edge_scale(v: Components, diffusivity: Diffusivity, contrast: float | Tensor, eps: float,
                coupled: bool) -> Tensor:
    squared = v[0] * v[0] + v[1] * v[1] + v[2] * v[2]
    if coupled:  # a sum of slices stays one pointwise kernel when compiled
        channels = squared.unbind(dim=1)
        squared = channels[0]
        for channel in channels[1:]:
            squared = squared + channel
        squared = squared[:, None]
    return diffusivity(torch.sqrt(squared + eps * eps), contrast)


def directional_flux(v: Components, fields: Sequence[Tensor], side: int) -> Components:
    """The flux map ``v -> (T . v) T`` of directional diffusion, ``T = fields[0]`` ``(B, 3, ...)``."""
    t = fields[0]
    tx, ty, tz = t[:, 0:1], t[:, 1:2], t[:, 2:3]
    along = v[0] * tx + v[1] * ty + v[2] * tz
    return along * tx, along * ty, along * tz


def tangent_directional_flux(v: Components, fields: Sequence[Tensor], side: int) -> Components:
    """The flux map ``v -> (P T . v) P T`` for ``T = fields[0]`` and the unit normals
    ``n = fields[1]`` (both ``(B, 3, ...)``), ``P T = T - (T . n) n``: with ``v`` tangent at
    the node (a projected gradient) ``P T . v = T . v``, so the flux is ``(T . v) P T``, with
    ``P T`` formed pointwise where it is read (no projected field is stored)."""
    t, n = fields
    tx, ty, tz = t[:, 0:1], t[:, 1:2], t[:, 2:3]
    nx, ny, nz = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    along = v[0] * tx + v[1] * ty + v[2] * tz
    normal_part = tx * nx + ty * ny + tz * nz
    return (along * (tx - normal_part * nx), along * (ty - normal_part * ny),
            along * (tz - normal_part * nz))


def _edge_eager(u, normal, weight, spacing, diffusivity, contrast, eps, coupled, scheme, haloed,  # noqa: ANN001, ANN202
                mask=None, *, path):
    flux = edge_stopping_flux(diffusivity, contrast, eps, coupled)
    return masked(flux_form(u, normal, weight, spacing, flux, (), scheme, path), mask)


def _edge_fused(padded_u, haloed_normal, haloed_weight, weight, spacing, diffusivity, contrast,  # noqa: ANN001, ANN202
                eps, coupled, scheme, mask=None, box_faces=True):
    flux = edge_stopping_flux(diffusivity, contrast, eps, coupled)
    return masked(fused_flux_form(padded_u, haloed_normal, haloed_weight, weight, spacing, flux,
                                   (), scheme, box_faces=box_faces), mask)


def _edge_halo(u, normal, weight, spacing, diffusivity, contrast, eps, coupled, scheme, haloed,  # noqa: ANN001, ANN202
               mask=None):
    return (replicated_halo(u, 2), *_geometry_halo(normal, weight, haloed), weight, spacing,
            diffusivity, contrast, eps, coupled, scheme, mask)


def _edge_fused_eagerly(padded_u, haloed_normal, haloed_weight, weight, spacing, diffusivity,  # noqa: ANN001, ANN202
                        contrast, eps, coupled, scheme, mask=None, box_faces=True):
    return eager_coupled_rate(padded_u, haloed_normal, haloed_weight, weight, spacing,
                              diffusivity, contrast, eps, scheme, mask=mask,
                              box_faces=box_faces, coupled=coupled)


_EDGE_STOPPING = backend.Kernel("edge_stopping", _edge_eager, _edge_fused, _edge_halo,
                                fused_when_eager=True, eager_fused=_edge_fused_eagerly)


def _edge_fused_open(padded_u, haloed_normal, haloed_weight, weight, spacing, diffusivity,  # noqa: ANN001, ANN202
                     contrast, eps, coupled, scheme, mask=None):
    return _edge_fused(padded_u, haloed_normal, haloed_weight, weight, spacing, diffusivity,
                       contrast, eps, coupled, scheme, mask, box_faces=False)


def _edge_open_eagerly(padded_u, haloed_normal, haloed_weight, weight, spacing, diffusivity,  # noqa: ANN001, ANN202
                       contrast, eps, coupled, scheme, mask=None):
    return _edge_fused_eagerly(padded_u, haloed_normal, haloed_weight, weight, spacing,
                               diffusivity, contrast, eps, coupled, scheme, mask,
                               box_faces=False)


_EDGE_STOPPING_OPEN = backend.Kernel("edge_stopping_open", _edge_eager, _edge_fused_open,
                                     eager_fused=_edge_open_eagerly)


def edge_stopping_form(
    u: Tensor, normal: Tensor, weight: Tensor, spacing: float, diffusivity: Diffusivity,
    contrast: float | Tensor, eps: float, coupled: bool = False, scheme: str = "symmetric",
    path: str = "auto", haloed: Haloed = None, pad: Pad | None = None,
    mask: Tensor | None = None,
) -> Tensor:
    """Edge-stopping diffusion ``(1/W) div(W g(|P grad u|) P grad u)``, ``|.|`` regularised by ``eps``.

    Args:
        u: ``(B, C, D, H, W)``, or packed band bricks ``(N, C, 8, 8, 8)`` with ``pad``.
        normal, weight, spacing, haloed: the geometry (module docstring).
        diffusivity: ``g(magnitude, contrast)``, pointwise (:mod:`torchsurf.operators.diffusivity`).
        contrast: ``K``, a float or a tensor broadcastable to ``(B, C, D, H, W)`` (e.g. ``(1, C, 1, 1, 1)``).
        eps: regularisation of ``|P grad u|``, units of ``u`` per world length.
        coupled: measure ``|P grad u|`` over all channels together.
        scheme: ``"symmetric"`` (default), ``"conservative"`` or ``"octant"``.
        path: how the stencils run.
        pad: how ``u`` gets its halo (:data:`Pad`); ``None`` for a dense volume.
        mask: ``(B or 1, 1, D, H, W)`` bool (packed like ``u`` with ``pad``): the result is zero
            where it is false (a flow's band), in the kernel's own pass.

    Returns:
        ``u``'s shape.
    """
    spacing = _check_inputs(u, normal, spacing, weight, scheme, FLUX_SCHEMES)
    _check_extras(u, normal, mask, haloed, diffusivity=diffusivity, contrast=contrast)
    check_flag(coupled, "coupled")
    if coupled and u.shape[1] > 1:
        return harmonic_map_rate(u, normal, weight, spacing, diffusivity, contrast, eps, None,
                                 scheme, path, mask, haloed, pad)
    if pad is not None:
        haloed_normal, haloed_weight = _require_haloed(haloed)
        return backend.run_haloed(_EDGE_STOPPING_OPEN, path, u, pad(u, 2), haloed_normal,
                                  haloed_weight, weight, spacing, diffusivity, contrast, eps,
                                  coupled, scheme, mask)
    return backend.run(_EDGE_STOPPING, path, u, u, normal, weight, spacing, diffusivity,
                       contrast, eps, coupled, scheme, haloed, mask)


def _coupled_eager(u, normal, weight, spacing, diffusivity, contrast, eps, power, scheme, mask,  # noqa: ANN001, ANN202
                   haloed, *, path):
    flux = edge_stopping_flux(diffusivity, contrast, eps, True)
    result = flux_form(u, normal, weight, spacing, flux, (), scheme, path)
    if power is not None:
        energy = _energy_eager(u, normal, spacing, path=path) + eps * eps
        result = result + u * energy**power
    return masked(result, mask)


def _coupled_halo(u, normal, weight, spacing, diffusivity, contrast, eps, power, scheme, mask,  # noqa: ANN001, ANN202
                  haloed):
    return (replicated_halo(u, 2), *_geometry_halo(normal, weight, haloed), weight, spacing,
            diffusivity, contrast, eps, scheme, power, mask)


COUPLED_COMPILE_WEIGHT = 3.0
"""Compiling the coupled (harmonic-map, colour) rate costs 2.2-3.0x a Laplace–Beltrami's at
64^3 with an empty inductor cache, and more with a dynamic batch of bricks (about 70 s at
128^3): :attr:`backend.Kernel.compile_weight` (docs/benchmarks.md, "Compile weights")."""


def _coupled_exponents(args: tuple) -> tuple[int, ...]:
    """The energy term's power, and the contrast of a diffusivity that raises to it
    (``exponent_contrast``, the p-harmonic map's ``s^(p-2)``): their positions in ``args``,
    the arguments of :func:`harmonic_map_rate`'s kernels as :func:`torchsurf.backend.run`
    takes them (``..., diffusivity, contrast, eps, power, scheme, ...``) or haloed
    (``..., diffusivity, contrast, eps, scheme, power, ...``)."""
    diffusivity = next(i for i, arg in enumerate(args)
                       if callable(arg) and not isinstance(arg, torch.Tensor))
    power = diffusivity + (4 if isinstance(args[diffusivity + 3], str) else 3)
    if getattr(args[diffusivity], "exponent_contrast", False):
        return (power, diffusivity + 1)
    return (power,)


_COUPLED = backend.Kernel("coupled_flux_form", _coupled_eager, fused_coupled_rate, _coupled_halo,
                          fused_when_eager=True, eager_fused=eager_coupled_rate,
                          breaks_graph=True, compile_weight=COUPLED_COMPILE_WEIGHT,
                          exponents=_coupled_exponents)


def _coupled_open(padded_u, haloed_normal, haloed_weight, weight, spacing, diffusivity, contrast,  # noqa: ANN001, ANN202
                  eps, scheme, power, mask):
    return fused_coupled_rate(padded_u, haloed_normal, haloed_weight, weight, spacing,
                              diffusivity, contrast, eps, scheme, power, mask, box_faces=False)


def _coupled_open_eagerly(padded_u, haloed_normal, haloed_weight, weight, spacing, diffusivity,  # noqa: ANN001, ANN202
                          contrast, eps, scheme, power, mask):
    return eager_coupled_rate(padded_u, haloed_normal, haloed_weight, weight, spacing,
                              diffusivity, contrast, eps, scheme, power, mask, box_faces=False)


_COUPLED_OPEN = backend.Kernel("coupled_flux_form_open", _coupled_eager, _coupled_open,
                               eager_fused=_coupled_open_eagerly, breaks_graph=True,
                               compile_weight=COUPLED_COMPILE_WEIGHT,
                               exponents=_coupled_exponents)


def harmonic_map_rate(
    u: Tensor, normal: Tensor, weight: Tensor, spacing: float, diffusivity: Diffusivity,
    contrast: float | Tensor, eps: float, power: float | None, scheme: str = "symmetric",
    path: str = "auto", mask: Tensor | None = None, haloed: Haloed = None,
    pad: Pad | None = None,
) -> Tensor:
    """Coupled edge-stopping diffusion plus the harmonic map's energy term, in one kernel.

    ``(1/W) div(W g(|P grad u|) P grad u_i) + u_i (|P grad u|^2 + eps^2)^power``, with
    ``|P grad u|^2`` summed over the channels: regularised by ``eps`` in ``g`` as in
    :func:`edge_stopping_form` (``coupled=True``), by central differences in the energy term as
    in :func:`tangential_gradient_energy`. With ``g(s) = s^(p-2)`` and ``power = p / 2`` it is
    the p-harmonic map flow's rate (the paper's eq. 11). Two passes over memory when compiled:
    docs/benchmarks.md.

    Args:
        u: ``(B, C, D, H, W)``, or packed band bricks ``(N, C, 8, 8, 8)`` with ``pad``.
        normal, weight, spacing, haloed: the geometry (module docstring).
        diffusivity, contrast: ``g(magnitude, contrast)``, as in :func:`edge_stopping_form`.
        eps: regularisation of ``|P grad u|``, units of ``u`` per world length.
        power: the energy term's exponent; ``None`` leaves the term out (then this is
            :func:`edge_stopping_form` with ``coupled=True``).
        scheme: ``"symmetric"`` (default), ``"conservative"`` or ``"octant"``.
        path: how the stencils run.
        mask: ``(B or 1, 1, D, H, W)`` bool (packed like ``u`` with ``pad``): the result is zero
            where it is false (a flow's band).
        pad: how ``u`` gets its halo (:data:`Pad`); ``None`` for a dense volume.

    Returns:
        ``u``'s shape.
    """
    spacing = _check_inputs(u, normal, spacing, weight, scheme, FLUX_SCHEMES)
    _check_extras(u, normal, mask, haloed, diffusivity=diffusivity, contrast=contrast)
    if pad is not None:
        haloed_normal, haloed_weight = _require_haloed(haloed)
        return backend.run_haloed(_COUPLED_OPEN, path, u, pad(u, 2), haloed_normal,
                                  haloed_weight, weight, spacing, diffusivity, contrast, eps,
                                  scheme, power, mask)
    return backend.run(_COUPLED, path, u, u, normal, weight, spacing, diffusivity, contrast, eps,
                       power, scheme, mask, haloed)


def _directional_eager(u, normal, weight, spacing, direction, scheme, weighted, tangent, haloed,  # noqa: ANN001, ANN202
                       *, path):
    if tangent:  # eagerly, P T once costs less than within each composition's fluxes
        direction = tangential_part(direction, normal)
    result = flux_form(u, normal, weight, spacing, directional_flux, (direction,), scheme, path)
    return _weighted(result, weight, weighted)


def _directional_projected_eagerly(padded_u, haloed_normal, haloed_weight, weight, spacing,  # noqa: ANN001, ANN202
                                   haloed_direction, scheme, weighted, tangent, box_faces=True):
    """:func:`_directional_fused`'s numbers to rounding, evaluated eagerly with ``P T`` formed
    once (in a box's faces from mirrored normals: the fluxes there cross closed faces)."""
    if tangent:
        haloed_direction = tangential_part(haloed_direction, haloed_normal)
    return _directional_fused(padded_u, haloed_normal, haloed_weight, weight, spacing,
                              haloed_direction, scheme, weighted, False, box_faces)


def _directional_fused(padded_u, haloed_normal, haloed_weight, weight, spacing, haloed_direction,  # noqa: ANN001, ANN202
                       scheme, weighted, tangent, box_faces=True):
    flux, fields = _directional_flux(haloed_direction, haloed_normal, tangent)
    return fused_flux_form(padded_u, haloed_normal, haloed_weight, weight, spacing, flux,
                           fields, scheme, weighted, box_faces=box_faces)


def _directional_flux(direction: Tensor, normal: Tensor, tangent: bool
                      ) -> tuple[FluxMap, tuple[Tensor, ...]]:
    if tangent:
        return tangent_directional_flux, (direction, normal)
    return directional_flux, (direction,)


def _directional_halo(u, normal, weight, spacing, direction, scheme, weighted, tangent, haloed):  # noqa: ANN001, ANN202
    return (replicated_halo(u, 2), *_geometry_halo(normal, weight, haloed), weight, spacing,
            replicated_halo(direction, 1), scheme, weighted, tangent)


_DIRECTIONAL = backend.Kernel("directional", _directional_eager, _directional_fused, _directional_halo)
TANGENT_REALIZE_READS = 10
"""Inductor's ``realize_reads_threshold`` for the directional kernels that project ``T``
(:func:`tangent_directional_flux`): with the default (:data:`torchsurf.backend.REALIZE_READS_THRESHOLD`)
inductor writes each composition's face fluxes to memory; recomputed, the operator takes about
the time of one given a tangent ``T`` (docs/benchmarks.md)."""
_DIRECTIONAL_TANGENT = backend.Kernel("directional_tangent", _directional_eager, _directional_fused,
                                      _directional_halo,
                                      eager_fused=_directional_projected_eagerly,
                                      realize_reads_threshold=TANGENT_REALIZE_READS)


def _directional_fused_open(padded_u, haloed_normal, haloed_weight, weight, spacing,  # noqa: ANN001, ANN202
                            haloed_direction, scheme, weighted, tangent):
    return _directional_fused(padded_u, haloed_normal, haloed_weight, weight, spacing,
                              haloed_direction, scheme, weighted, tangent, box_faces=False)


_DIRECTIONAL_OPEN = backend.Kernel("directional_open", _directional_eager, _directional_fused_open)
_DIRECTIONAL_TANGENT_OPEN = backend.Kernel(
    "directional_tangent_open", _directional_eager, _directional_fused_open,
    eager_fused=lambda *args: _directional_projected_eagerly(*args, box_faces=False),
    realize_reads_threshold=TANGENT_REALIZE_READS)


def directional_form(
    u: Tensor, normal: Tensor, weight: Tensor, spacing: float, direction: Tensor,
    scheme: str = "symmetric", path: str = "auto", weighted: bool = False, haloed: Haloed = None,
    pad: Pad | None = None, haloed_direction: Tensor | None = None, tangent: bool = False,
) -> Tensor:
    """Diffusion along a tangent field ``(1/W) div(W (T . P grad u) T)``.

    Args:
        u: ``(B, C, D, H, W)``, or packed band bricks ``(N, C, 8, 8, 8)`` with ``pad``.
        normal, weight, spacing, haloed: the geometry (module docstring).
        direction: ``T``, ``(B or 1, 3, D, H, W)`` in ``(x, y, z)`` order (packed
            ``(N, 3, 8, 8, 8)`` with ``pad``).
        scheme: ``"symmetric"`` (default), ``"conservative"`` or ``"octant"``.
        path: how the stencils run.
        weighted: return ``W L u`` (symmetric negative semi-definite) instead.
        pad: how ``u`` gets its halo (:data:`Pad`); ``None`` for a dense volume.
        haloed_direction: with ``pad``, ``direction`` with its halo of one node when the caller
            keeps it (a flow applies the operator many times to one field); default
            ``pad(direction, 1)``.
        tangent: use ``P T = T - (T . n) n`` in place of ``T``: compiled, within the fluxes
            (:func:`tangent_directional_flux`: projecting ``T`` before the call took as long
            as the operator), eagerly once before them; what
            :func:`torchsurf.directional_diffusion` asks. ``False`` for a ``T`` the caller
            keeps tangent.

    Returns:
        ``u``'s shape.
    """
    spacing = _check_inputs(u, normal, spacing, weight, scheme, FLUX_SCHEMES, direction,
                           required=("weight", "direction"))
    _check_extras(u, normal, haloed=haloed, weighted=weighted)
    check_flag(tangent, "tangent")
    if pad is not None:
        haloed_normal, haloed_weight = _require_haloed(haloed)
        if haloed_direction is None:
            haloed_direction = pad(direction, 1)
        return backend.run_haloed(_DIRECTIONAL_TANGENT_OPEN if tangent else _DIRECTIONAL_OPEN,
                                  path, u, pad(u, 2), haloed_normal, haloed_weight, weight,
                                  spacing, haloed_direction, scheme, weighted, tangent)
    return backend.run(_DIRECTIONAL_TANGENT if tangent else _DIRECTIONAL, path, u, u, normal,
                       weight, spacing, direction, scheme, weighted, tangent, haloed)


# --- Central differences: gradient, divergence, the non-conservative Laplace–Beltrami --------


def _gradient_padded(padded_u: Tensor, normal: Tensor, spacing: float, path: str = "slicing"
                     ) -> Tensor:
    gradient = stencils.apply(padded_u, stencils.CENTRAL, path) / spacing
    n = normal[:, None]
    projected = gradient - (gradient * n).sum(dim=2, keepdim=True) * n
    return projected.flatten(1, 2)


def _gradient_eager(u, normal, spacing, *, path):  # noqa: ANN001, ANN202
    return _gradient_padded(stencils.pad(u, "replicate"), normal, spacing, path)


def _gradient_halo(u, normal, spacing):  # noqa: ANN001, ANN202
    return stencils.pad(u, "replicate"), normal, spacing


_GRADIENT = backend.Kernel("tangential_gradient", _gradient_eager, _gradient_padded, _gradient_halo)


def tangential_gradient(u: Tensor, normal: Tensor, spacing: float, path: str = "auto",
                        pad: Pad | None = None) -> Tensor:
    """``P grad u`` by central differences, second order.

    Args:
        u: ``(B, C, D, H, W)``, or packed band bricks ``(N, C, 8, 8, 8)`` with ``pad``.
        normal, spacing: the geometry (module docstring).
        path: how the stencils run.
        pad: how ``u`` gets its halo (:data:`Pad`); ``None`` for a dense volume.

    Returns:
        ``(B, 3C, D, H, W)`` (or ``(N, 3C, 8, 8, 8)``): channels ``3c, 3c+1, 3c+2`` are the
        ``x, y, z`` components for channel ``c``, units of ``u`` per world length.
    """
    spacing = _check_inputs(u, normal, spacing, required=())
    if pad is not None:
        return backend.run_haloed(_GRADIENT, path, u, pad(u, 1), normal, spacing)
    return backend.run(_GRADIENT, path, u, u, normal, spacing)


def _energy_padded(padded_u: Tensor, normal: Tensor, spacing: float, path: str = "slicing"
                   ) -> Tensor:
    total = None
    for c in range(padded_u.shape[1]):
        gradient = stencils.apply(padded_u[:, c: c + 1], stencils.CENTRAL, path)[:, 0]
        # |P g|^2 from P g itself: |g|^2 - (g . n)^2 cancelled to -4e-3 in float32 where u
        # varies mostly along n (100 phi + 0.01 sin 2x), 11 times the energy's own size
        tangent = gradient - (gradient * normal).sum(dim=1, keepdim=True) * normal
        squared = (tangent * tangent).sum(dim=1, keepdim=True)
        total = squared if total is None else total + squared
    return total / (spacing * spacing)


def _energy_eager(u, normal, spacing, *, path):  # noqa: ANN001, ANN202
    return _energy_padded(stencils.pad(u, "replicate"), normal, spacing, path)


_ENERGY = backend.Kernel("tangential_gradient_energy", _energy_eager, _energy_padded, _gradient_halo)


def tangential_gradient_energy(u: Tensor, normal: Tensor, spacing: float, path: str = "auto",
                               pad: Pad | None = None) -> Tensor:
    """``sum_c |P grad u_c|^2`` by central differences, without forming the gradient.

    Args:
        u: ``(B, C, D, H, W)``, or packed band bricks ``(N, C, 8, 8, 8)`` with ``pad``.
        normal, spacing: the geometry (module docstring).
        path: how the stencils run.
        pad: how ``u`` gets its halo (:data:`Pad`); ``None`` for a dense volume.

    Returns:
        ``(B, 1, D, H, W)`` (or ``(N, 1, 8, 8, 8)``), units of ``u`` squared per world length
        squared.
    """
    spacing = _check_inputs(u, normal, spacing, required=())
    if pad is not None:
        return backend.run_haloed(_ENERGY, path, u, pad(u, 1), normal, spacing)
    return backend.run(_ENERGY, path, u, u, normal, spacing)


def _tangential_flux(v: Tensor, normal: Tensor, weight: Tensor) -> Tensor:
    """``W P v`` for ``v`` ``(B, 3C, ...)``, laid out the same way."""
    field = v.unflatten(1, (-1, 3))
    n = normal[:, None]
    return ((field - (field * n).sum(dim=2, keepdim=True) * n) * weight[:, None]).flatten(1, 2)


def _flux_divergence(padded_flux: Tensor, weight: Tensor, spacing: float, path: str = "slicing"
                     ) -> Tensor:
    padded = padded_flux.unflatten(1, (-1, 3))
    return stencils.contract(padded, stencils.CENTRAL, path) / (spacing * weight)


def _divergence(v: Tensor, normal: Tensor, weight: Tensor, spacing: float, path: str = "slicing"
                ) -> Tensor:
    # the flux is padded here, inside any compiled kernel: haloing v, the normals and W
    # outside instead measured slower (13.9 ms against 7.9 ms at 128^3, three channels)
    padded = stencils.pad(_tangential_flux(v, normal, weight), "replicate")
    return _flux_divergence(padded, weight, spacing, path)


def _divergence_eager(v, normal, weight, spacing, *, path):  # noqa: ANN001, ANN202
    return _divergence(v, normal, weight, spacing, path)


_DIVERGENCE = backend.Kernel(
    "tangential_divergence", _divergence_eager, _divergence, lambda *args: args
)


def _flux_divergence_eager(padded_flux, weight, spacing, *, path):  # noqa: ANN001, ANN202
    return _flux_divergence(padded_flux, weight, spacing, path)


_FLUX_DIVERGENCE = backend.Kernel(
    "tangential_divergence_of_haloed_flux", _flux_divergence_eager, _flux_divergence,
    lambda *args: args,
)


def tangential_divergence(v: Tensor, normal: Tensor, weight: Tensor, spacing: float,
                          path: str = "auto", pad: Pad | None = None) -> Tensor:
    """``(1/W) div(W P v)`` by central differences.

    Args:
        v: ``(B, 3C, D, H, W)``, laid out as :func:`tangential_gradient` returns, or packed
            band bricks ``(N, 3C, 8, 8, 8)`` with ``pad``.
        normal, weight, spacing: the geometry (module docstring).
        path: how the stencils run.
        pad: how the flux ``W P v`` gets its halo (:data:`Pad`); ``None`` for a dense volume.

    Returns:
        ``(B, C, D, H, W)`` (or ``(N, C, 8, 8, 8)``), units of ``v`` per world length.
    """
    spacing = _check_inputs(v, normal, spacing, weight, vector=True)
    if pad is not None:
        return backend.run_haloed(_FLUX_DIVERGENCE, path, v,
                                  pad(_tangential_flux(v, normal, weight), 1), weight, spacing)
    return backend.run(_DIVERGENCE, path, v, v, normal, weight, spacing)


def _central_padded(padded_u: Tensor, normal: Tensor, mean_curvature: Tensor, spacing: float,
                    path: str = "slicing") -> Tensor:
    gradient = stencils.apply(padded_u, stencils.CENTRAL, path) / spacing
    xx, yy, zz, xy, xz, yz = stencils.apply(padded_u, stencils.HESSIAN, path).unbind(dim=2)
    nx, ny, nz = normal[:, None].unbind(dim=2)
    laplacian = xx + yy + zz
    normal_second = (
        nx * nx * xx + ny * ny * yy + nz * nz * zz
        + 2.0 * (nx * ny * xy + nx * nz * xz + ny * nz * yz)
    )
    normal_first = (gradient * normal[:, None]).sum(dim=2)
    return (laplacian - normal_second) / spacing**2 - mean_curvature * normal_first


def _central_eager(u, normal, mean_curvature, spacing, *, path):  # noqa: ANN001, ANN202
    return _central_padded(stencils.pad(u, "replicate"), normal, mean_curvature, spacing, path)


def _central_halo(u, normal, mean_curvature, spacing):  # noqa: ANN001, ANN202
    return stencils.pad(u, "replicate"), normal, mean_curvature, spacing


_CENTRAL = backend.Kernel("laplace_beltrami_central", _central_eager, _central_padded, _central_halo)


def central_laplace_beltrami(
    u: Tensor, normal: Tensor, mean_curvature: Tensor, spacing: float, path: str = "auto",
    pad: Pad | None = None,
) -> Tensor:
    """``Lap u - n^T (Hess u) n - H dn u`` by central differences (not in divergence form).

    Args:
        u: ``(B, C, D, H, W)``, or packed band bricks ``(N, C, 8, 8, 8)`` with ``pad``.
        normal, spacing: the geometry (module docstring).
        mean_curvature: ``H = div n``, ``(B or 1, 1, D, H, W)`` (or packed), 1 / world length.
        path: how the stencils run.
        pad: how ``u`` gets its halo (:data:`Pad`); ``None`` for a dense volume.

    Returns:
        ``(B, C, D, H, W)`` (or ``(N, C, 8, 8, 8)``), units of ``u`` per world length squared.
    """
    spacing = _check_inputs(u, normal, spacing, mean_curvature=mean_curvature,
                           required=("mean_curvature",))
    if pad is not None:
        return backend.run_haloed(_CENTRAL, path, u, pad(u, 1), normal, mean_curvature, spacing)
    return backend.run(_CENTRAL, path, u, u, normal, mean_curvature, spacing)


FLUX_SCHEMES = tuple(SIDES)
"""Schemes of the edge-stopping and directional forms."""
