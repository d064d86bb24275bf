"""Closest-point re-extension under autograd that stores one volume, not 64 values a node.

Autograd through a stencil's gather (:class:`~torchsurf.flows.extension.CubicStencil`,
:class:`~torchsurf.flows.extension.BrickCubicStencil`) keeps the ``(C, N, 64)`` gathered values
and the ``(N, 64)`` source indices of every application: in a flow, one set per stage, several
times the band's own size each. When the stencil's weights are fixed (``phi`` does not require
grad), :func:`reextend` applies it without autograd and keeps only its input; backward forms
the taps again, a chunk of nodes at a time, and scatters the incoming gradient back along
them. For a limited stencil (each value clamped to bounds continuous in its point,
:mod:`._limiter`), a clamped node sends its gradient to the nodes that set the bound, each
corner's extreme with that corner's trilinear weight, the others along their 64 taps: the
derivative of ``min(max(value, low), high)`` away from ties.
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch import Tensor

from .. import backend
from .._native import carries_tangents
from .._transforms import refuse_batched_backward
from ..surface import ImplicitSurface
from . import _closest, _limiter
from .extension import BrickCubicStencil, CubicStencil, _brick_sources, cubic_stencil, stencil_key

MIN_BAND_CELLS = 2.9
"""Narrowest band (in cells) that re-extension allows: the 4^3 nodes a tricubic stencil reads
around a closest point lie within ``2 sqrt(3) h`` of S, and the band with its ring holds every
node within ``band_width + h / sqrt(3)`` of S."""


def check_reextension_width(width: float, spacing: float, alternative: str = "") -> None:
    """Raise ``ValueError`` naming ``band_width`` when ``width`` is below
    :data:`MIN_BAND_CELLS` cells of ``spacing`` (``alternative``: what else the caller can do,
    appended to the advice)."""
    if width < MIN_BAND_CELLS * spacing * (1 - 1e-6):
        raise ValueError(
            f"band_width={width:g} is {width / spacing:.2f} cells of this grid; re-extension "
            f"reads closest points up to {MIN_BAND_CELLS} cells from S: use band_width >= "
            f"{MIN_BAND_CELLS * spacing:.4g}{alternative}"
        )

Stencil = CubicStencil | BrickCubicStencil


def kept_stencil(surface: ImplicitSurface, width: float | None, kind: str, mask: Tensor,
                 region: Tensor, limited: bool) -> Stencil:
    """The closest-point stencil of ``mask`` reading only ``region`` (the band of half-width
    ``width`` and its ring; ``kind`` names the mask, e.g. ``"ring"`` or ``"region"``), for the
    surface's storage; kept on the surface unless ``phi`` requires grad (its weights are then in
    ``phi``'s graph). The ring's is taken from the region's rows when that is kept (the stencils
    of one width all read its region): forming it again took a third of a fresh surface's
    stencils."""
    if surface.phi.requires_grad:
        return cubic_stencil(surface, mask, limited=limited, readable=region)

    def formed() -> Stencil:
        if kind == "ring":  # within the region: its stencil's rows, where already formed
            for whole in (stencil_key(width, "region", flag) for flag in (True, False)):
                if surface.is_kept(whole):
                    region_stencil = surface.kept(whole, lambda: None)
                    return region_stencil.restricted(mask & _closest.has_direction(surface),
                                                     limited)
        return cubic_stencil(surface, mask, limited=limited, readable=region)

    return surface.kept(stencil_key(width, kind, limited), formed)

CHUNK = 2**15
"""Nodes whose taps are formed at once in backward (about 1 kB of temporaries a node)."""


def reextend(stencil: Stencil, u: Tensor, path: str = "auto") -> Tensor:
    """``stencil.apply(u)``; under autograd with fixed weights, through :class:`_Reextend`.

    Args:
        stencil: a closest-point stencil whose weights are not in ``phi``'s graph (built from a
            ``phi`` that does not require grad), dense or on bricks.
        u: ``(B, C, D, H, W)`` dense or ``(N, C, 8, 8, 8)`` packed, matching the stencil.
        path: how the stencil's gather runs (:data:`torchsurf.backend.PATHS`).

    Returns:
        The re-extended field, like ``u``; a new tensor.
    """
    weights = stencil.parts[0][2] if isinstance(stencil, CubicStencil) else stencil.weights
    if (torch.is_grad_enabled() and u.requires_grad and not weights.requires_grad
            and not torch.compiler.is_compiling() and not carries_tangents(u)):
        # traced, the gather's own derivative: dynamo traces an autograd function's backward
        # with its forward, and this one's host-sized selections broke the graph there
        return _Reextend.apply(stencil, u, path)
    return stencil.apply(u, path)


class _Reextend(torch.autograd.Function):
    @staticmethod
    def forward(ctx, stencil, u, path="auto"):  # noqa: ANN001, ANN205
        ctx.stencil = stencil
        with torch.no_grad():
            result = stencil.apply(u, path)
        # a limited stencil's backward tells the values it may have clamped by those it wrote
        ctx.save_for_backward(u, *(_written(stencil, result) if stencil.limited else ()))
        return result

    @staticmethod
    @backend.part_of_recorded
    def backward(ctx, grad_output):  # noqa: ANN001, ANN205
        u, *written = ctx.saved_tensors
        if ctx.stencil.limited:  # the limiter's scatter of clamped taps has no batching rule
            refuse_batched_backward("the band's limited re-extension", grad_output)
        return None, _vector_jacobian(ctx.stencil, u.detach(), grad_output, written or None), None


def _written(stencil: Stencil, result: Tensor) -> list[Tensor]:
    """The values ``stencil.apply`` wrote into ``result``: ``(C, n)`` per part of the stencil
    (one for bricks), in the order of its targets."""
    if isinstance(stencil, BrickCubicStencil):
        return [result.transpose(0, 1).reshape(result.shape[1], -1)[:, stencil.targets]]
    return [result[b].reshape(result.shape[1], -1)[:, stencil.parts[min(b, len(stencil.parts) - 1)][0]]
            for b in range(result.shape[0])]


def _vector_jacobian(stencil: Stencil, u: Tensor, g: Tensor,
                     written: list[Tensor] | None = None) -> Tensor:
    """``g^T d(stencil.apply(u)) / du`` for ``u`` and ``g`` of the same shape; ``written``
    (:func:`_written`), where known, spares a limited stencil most of its gather again."""
    if isinstance(stencil, BrickCubicStencil):
        channels = u.shape[1]
        flat = u.transpose(0, 1).reshape(channels, -1)
        incoming = g.transpose(0, 1).reshape(channels, -1)
        result = _scatter_back(flat, incoming, stencil.targets, _brick_taps(stencil),
                               stencil.limited, None if written is None else written[0])
        return result.view(channels, u.shape[0], *u.shape[2:]).transpose(0, 1)
    results = []
    for b in range(max(u.shape[0], len(stencil.parts))):
        part = min(b, len(stencil.parts) - 1)
        targets, corners, weights = stencil.parts[part]
        volume = u[min(b, u.shape[0] - 1)]
        flat = volume.reshape(volume.shape[0], -1)
        incoming = g[b].reshape(g.shape[1], -1)
        taps = _dense_taps(targets, corners, weights.to(u.dtype), *volume.shape[-2:],
                           stencil.sources[part])
        results.append(_scatter_back(flat, incoming, targets, taps, stencil.limited,
                                     None if written is None else written[b])
                       .reshape(volume.shape))
    result = torch.stack(results)
    return result if result.shape[0] == u.shape[0] else result.sum(dim=0, keepdim=True)


def _separable(weights: Tensor) -> Tensor:
    """The 64 tap weights ``(n, 64)`` from the per-axis weights ``(3, n, 4)`` (z, y, x order)."""
    wx, wy, wz = weights.unbind(0)
    return (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).flatten(1)


def _dense_taps(targets: Tensor, corners: Tensor, weights: Tensor, height: int, width: int,
                kept: Tensor | None = None) -> Iterator[tuple[slice, Tensor, Tensor]]:
    """Chunks ``(nodes, sources (n, 64), taps (n, 64))`` of a dense stencil part; the sources
    from ``kept`` (the stencil's ``(M, 64)`` tap positions) where it keeps them."""
    for start in range(0, len(targets), CHUNK):
        nodes = slice(start, start + CHUNK)
        if kept is not None:
            sources = kept[nodes].long()
        else:
            x, y, z = corners[:, nodes].long().unbind(0)
            sources = ((z[:, :, None, None] * height + y[:, None, :, None]) * width
                       + x[:, None, None, :]).flatten(1)
        yield nodes, sources, _separable(weights[:, nodes])


def _brick_taps(stencil: BrickCubicStencil) -> Iterator[tuple[slice, Tensor, Tensor]]:
    """Chunks ``(nodes, sources (n, 64), taps (n, 64))`` of a brick stencil, packed indices."""
    for start in range(0, len(stencil.targets), CHUNK):
        nodes = slice(start, start + CHUNK)
        sources = _brick_sources(stencil.bases[:, nodes], stencil.second[:, nodes],
                                 stencil.local[:, nodes])
        yield nodes, sources, _separable(stencil.weights[:, nodes])


def _scatter_back(flat: Tensor, incoming: Tensor, targets: Tensor,
                  chunks: Iterator[tuple[slice, Tensor, Tensor]], limited: bool,
                  written: Tensor | None = None) -> Tensor:
    """``incoming`` ``(C, M)`` with the targets' entries moved back to their sources.

    ``flat`` ``(C, M)`` is the stencil's input (read only when ``limited``, to find which
    values were clamped and by which nodes' values). ``written`` ``(C, n)``: the values the
    stencil wrote at its targets, if known. The bounds hold the cell's range, so a value was
    clamped only if it left that range, and then it was written at a bound outside it: only
    the values written outside or at the edge of their cell's range have their 64 taps
    gathered again (without ``written``, only those whose interpolated value leaves it form
    their bounds).
    """
    result = incoming.index_fill(1, targets, 0.0)
    for nodes, sources, taps in chunks:
        moved = incoming[:, targets[nodes]]  # (C, n)
        taps = taps.to(flat.dtype)
        if not limited:
            result.index_add_(1, sources.flatten(), (moved[..., None] * taps).flatten(1))
            continue
        if written is None:
            gathered = flat[:, sources]  # (C, n, 64)
            value = (gathered * taps).sum(dim=-1)
            cell = _limiter.cell_values(gathered)
            leaving = (value < cell.amin(-1)) | (value > cell.amax(-1))
        else:
            cell = flat[:, sources[:, _limiter.CELL]]  # (C, n, 8)
            kept = written[:, nodes]
            leaving = (kept <= cell.amin(-1)) | (kept >= cell.amax(-1))
        outside = leaving.any(dim=0).nonzero()[:, 0]
        free = torch.ones_like(moved, dtype=torch.bool)
        clamps = []
        if len(outside):
            if written is None:
                gathered, value = gathered[:, outside], value[:, outside]
            else:
                gathered = flat[:, sources[outside]]
                value = (gathered * taps[outside]).sum(dim=-1)
            corners = _limiter.corner_weights_of_taps(taps[outside])  # (k, 8)
            low, high, lowest, highest = _limiter.bounds_and_sources(gathered, corners)
            tied = _limiter.ties(value, low, high, gathered.abs().amax(-1))  # not clamps
            below, above = (value < low) & ~tied, (value > high) & ~tied
            free[:, outside] = ~(below | above)
            clamps = [(below, lowest), (above, highest)]
        result.index_add_(1, sources.flatten(), ((moved * free)[..., None] * taps).flatten(1))
        for clamped, extremes in clamps:
            channel, node = clamped.nonzero(as_tuple=True)
            if len(node) == 0:
                continue
            at = outside[node]
            reached = sources[at[:, None], extremes[channel, node]].long()  # (k, 8)
            result.index_put_((channel[:, None].expand_as(reached), reached),
                              moved[channel, at][:, None] * corners[node], accumulate=True)
    return result
