"""Edge-stopping diffusivities ``g(s)`` of the gradient magnitude ``s = |P grad u|`` (the paper's §2).

Each maps a magnitude tensor ``s > 0`` and a contrast ``K`` (same units as ``s``, a float or a
tensor broadcastable to ``s``) to the diffusivity; :data:`DIFFUSIVITIES` names them.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

Diffusivity = Callable[[Tensor, "float | Tensor"], Tensor]


def total_variation(magnitude: Tensor, contrast: float | Tensor) -> Tensor:
    """``g(s) = 1 / s``: total-variation flow (the paper's eq. 10); ``contrast`` is unused.

    ``magnitude``: ``|grad_S u| = s``, any shape (``(B, 1 or C, D, H, W)`` from the operators),
    data units per world length; ``contrast`` ``K``: the same units, a float or a tensor that
    broadcasts against it. Returns ``g`` elementwise, ``magnitude``'s shape."""
    return 1.0 / magnitude


def perona_malik(magnitude: Tensor, contrast: float | Tensor) -> Tensor:
    """``g(s) = 1 / (1 + (s / K)^2)``: Perona–Malik, stops diffusion across edges ``s >> K``.

    ``magnitude``: ``|grad_S u| = s``, any shape (``(B, 1 or C, D, H, W)`` from the operators),
    data units per world length; ``contrast`` ``K``: the same units, a float or a tensor that
    broadcasts against it. Returns ``g`` elementwise, ``magnitude``'s shape."""
    return 1.0 / (1.0 + (magnitude / contrast) ** 2)


def charbonnier(magnitude: Tensor, contrast: float | Tensor) -> Tensor:
    """``g(s) = 1 / sqrt(1 + (s / K)^2)``: Charbonnier, convex, TV-like for ``s >> K``.

    ``magnitude``: ``|grad_S u| = s``, any shape (``(B, 1 or C, D, H, W)`` from the operators),
    data units per world length; ``contrast`` ``K``: the same units, a float or a tensor that
    broadcasts against it. Returns ``g`` elementwise, ``magnitude``'s shape."""
    return torch.rsqrt(1.0 + (magnitude / contrast) ** 2)


DIFFUSIVITIES: dict[str, Diffusivity] = {
    "total_variation": total_variation,
    "perona_malik": perona_malik,
    "charbonnier": charbonnier,
}
