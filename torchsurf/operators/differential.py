"""Intrinsic gradient ``P grad u`` and divergence ``(1/W) div(W P v)`` with central differences."""

from __future__ import annotations

from torch import Tensor, nn

from .. import backend
from .._checks import check_choice
from ..surface import ImplicitSurface, check_data
from . import functional


def intrinsic_gradient(u: Tensor, surface: ImplicitSurface, path: str = "auto") -> Tensor:
    """Surface gradient ``grad_S u = P grad u`` (the paper's §2), central differences, second order.

    Args:
        u: ``(B, C, D, H, W)`` (on a :class:`~torchsurf.bricks.BrickSurface`, packed
            ``(N, C, 8, 8, 8)``).
        surface: the implicit surface (batch 1 or B), dense or bricks.
        path: how stencils are applied (see :func:`torchsurf.laplace_beltrami`).

    Returns:
        ``(B, 3C, D, H, W)``: channels ``3c, 3c+1, 3c+2`` are the ``x, y, z`` components of the
        gradient of channel ``c``, units of ``u`` per world length.
    """
    check_data(u, "u", surface)
    check_choice(path, "path", backend.PATHS)
    pad = None if surface.layout is None else surface.layout.halo
    return functional.tangential_gradient(u, surface.normal, surface.spacing, path, pad)


def intrinsic_divergence(v: Tensor, surface: ImplicitSurface, path: str = "auto") -> Tensor:
    """Surface divergence ``div_S v = (1/W) div(W P v)`` (the paper's §2), central differences.

    For a tangent field this is the divergence on the level set through each node; the normal
    part of ``v`` is removed first.

    Args:
        v: ``(B, 3C, D, H, W)``, ``C`` vector fields laid out as by :func:`intrinsic_gradient`
            (on a :class:`~torchsurf.bricks.BrickSurface`, packed ``(N, 3C, 8, 8, 8)``).
        surface: the implicit surface (batch 1 or B), dense or bricks.
        path: how stencils are applied.

    Returns:
        ``(B, C, D, H, W)`` (packed ``(N, C, 8, 8, 8)`` on bricks), units of ``v`` per world
        length.
    """
    check_data(v, "v", surface)
    if v.shape[1] % 3 != 0:
        raise ValueError(
            f"v must have 3C channels (x, y, z per field), got shape {tuple(v.shape)}"
        )
    check_choice(path, "path", backend.PATHS)
    pad = None if surface.layout is None else surface.layout.halo
    return functional.tangential_divergence(v, surface.normal, surface.weight, surface.spacing,
                                            path, pad)


class IntrinsicGradient(nn.Module):
    """Module form of :func:`intrinsic_gradient`: ``(B, C, D, H, W) -> (B, 3C, D, H, W)``.

    Args:
        path: how stencils are applied, one of :data:`torchsurf.backend.PATHS` (``"auto"``
            chooses by measurement; see :func:`intrinsic_gradient`).
    """

    def __init__(self, path: str = "auto") -> None:
        super().__init__()
        self.path = check_choice(path, "path", backend.PATHS)

    def forward(self, u: Tensor, surface: ImplicitSurface) -> Tensor:
        """``P grad u`` per channel of ``u`` on ``surface``: ``(B, C, D, H, W) -> (B, 3C, D, H,
        W)``, units of ``u`` per world length (:func:`intrinsic_gradient`)."""
        return intrinsic_gradient(u, surface, path=self.path)

    def extra_repr(self) -> str:
        return f"path={self.path!r}"


class IntrinsicDivergence(nn.Module):
    """Module form of :func:`intrinsic_divergence`: ``(B, 3C, D, H, W) -> (B, C, D, H, W)``.

    Args:
        path: how stencils are applied, one of :data:`torchsurf.backend.PATHS` (``"auto"``
            chooses by measurement; see :func:`intrinsic_divergence`).
    """

    def __init__(self, path: str = "auto") -> None:
        super().__init__()
        self.path = check_choice(path, "path", backend.PATHS)

    def forward(self, v: Tensor, surface: ImplicitSurface) -> Tensor:
        """The intrinsic divergence of tangent fields ``v`` ``(B, 3C, D, H, W)`` (x, y, z per
        field) on ``surface``: ``(B, C, D, H, W)``, units of ``v`` per world length
        (:func:`intrinsic_divergence`)."""
        return intrinsic_divergence(v, surface, path=self.path)

    def extra_repr(self) -> str:
        return f"path={self.path!r}"
