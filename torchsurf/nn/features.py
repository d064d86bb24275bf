"""Rotation-invariant features of surface data from its tangential gradients.

For data ``u`` ``(B, C, D, H, W)`` on a surface, ``grad_S u_c = P grad u_c`` by central
differences (:func:`torchsurf.operators.functional.tangential_gradient`); the features are
``|grad_S u_c|`` for each channel and, optionally, ``<grad_S u_i, grad_S u_j>`` for each pair
``i < j``: invariant under rotations of the shape and of the grid's axes (to discretisation).
They are scale-free: gradients are measured **per cell** (``h grad_S u``, units of ``u``), so
the same data on a grid of the same resolution gives the same features whatever the shape's
world size.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .._checks import check_choice, check_count, check_flag, check_positive
from ..backend import PATHS
from ..flows._integrators import with_ring
from ..operators import functional
from ..surface import ImplicitSurface, check_data, check_surface


def _band_and_ring(surface: ImplicitSurface) -> Tensor:
    """``surface.band_mask()`` and the ring its stencils read, bool ``(B, 1, D, H, W)`` (packed
    on bricks), found once per surface."""
    return surface.kept(("band and ring",),
                        lambda: with_ring(surface.band_mask(), surface.layout))


def feature_count(channels: int, pairs: bool = True) -> int:
    """Number of features of ``channels`` channels: ``C`` norms plus ``C (C - 1) / 2`` products
    (with ``pairs``)."""
    channels = check_count(channels, "channels")
    return channels + (channels * (channels - 1) // 2 if check_flag(pairs, "pairs") else 0)


def gradient_features(u: Tensor, surface: ImplicitSurface, pairs: bool = True,
                      eps: float = 1e-6, path: str = "auto") -> Tensor:
    """``|h grad_S u_c|`` per channel, then ``<h grad_S u_i, h grad_S u_j>`` for ``i < j``.

    Args:
        u: ``(B, C, D, H, W)``; ``surface`` has batch 1 or B. On a
            :class:`~torchsurf.bricks.BrickSurface`, packed ``(N, C, 8, 8, 8)`` (the result
            is packed too).
        surface: the implicit surface.
        pairs: include the products of every pair of channels.
        eps: the norms are ``sqrt(|h grad_S u_c|^2 + eps^2)``, units of ``u``: finite
            gradients where the data is flat.
        path: how the stencils run (:mod:`torchsurf.backend`).

    Returns:
        ``(B, feature_count(C, pairs), D, H, W)``: norms (units of ``u``) in channel order,
        then products (units of ``u^2``) in the order ``(0, 1), (0, 2), ..., (C - 2, C - 1)``.
        The band's features read ``u`` on the band and its ring only; NaN or infinity beyond
        the ring is read as 0, so that it reaches neither them nor their gradients (a band
        loss's backward multiplies it by 0). NaN or infinity in the band or ring propagates,
        as through any PyTorch function (:class:`LearnedDiffusion` refuses it).
    """
    check_surface(surface)
    check_data(u, "u", surface)
    check_flag(pairs, "pairs")
    check_positive(eps, "eps")
    check_choice(path, "path", PATHS)
    channels = u.shape[1]
    pad = None if surface.layout is None else surface.layout.halo
    # non-finite values beyond the ring read as 0: out of the derivatives (0 * NaN in a backward)
    u = torch.where(_band_and_ring(surface).to(u.device) | torch.isfinite(u), u, 0.0)
    gradient = functional.tangential_gradient(u, surface.normal, surface.spacing, path, pad)
    gradient = (gradient * surface.spacing).unflatten(1, (channels, 3))
    features = [torch.sqrt((gradient * gradient).sum(dim=2) + eps * eps)]
    if pairs and channels > 1:
        i, j = torch.triu_indices(channels, channels, offset=1, device=u.device)
        features.append((gradient[:, i] * gradient[:, j]).sum(dim=2))
    return torch.cat(features, dim=1)


class GradientFeatures(nn.Module):
    """Module form of :func:`gradient_features`.

    Shapes: ``(B, C, D, H, W)`` -> ``(B, feature_count(C, pairs), D, H, W)``.

    Args:
        pairs, eps, path: as :func:`gradient_features`'s.
    """

    def __init__(self, pairs: bool = True, eps: float = 1e-6, path: str = "auto") -> None:
        super().__init__()
        self.pairs = check_flag(pairs, "pairs")
        self.eps = check_positive(eps, "eps")
        self.path = check_choice(path, "path", PATHS)

    def forward(self, u: Tensor, surface: ImplicitSurface) -> Tensor:
        """:func:`gradient_features` of ``u`` ``(B, C, D, H, W)`` on ``surface``: ``(B, C +
        C(C-1)/2, D, H, W)`` (``C`` without pairs)."""
        return gradient_features(u, surface, self.pairs, self.eps, self.path)

    def extra_repr(self) -> str:
        return f"pairs={self.pairs}"
