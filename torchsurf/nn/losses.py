"""Losses and quality measures of surface data, over the band only."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .._checks import check_positive
from ..surface import ImplicitSurface, check_data, check_surface


def _squared_errors(prediction: Tensor, target: Tensor, surface: ImplicitSurface,
                    width: float | None) -> tuple[Tensor, Tensor]:
    """Per batch entry: the sum of squared errors over the band and the count of its values
    (on a :class:`~torchsurf.bricks.BrickSurface`, per entry of its batch)."""
    check_surface(surface)
    check_data(prediction, "prediction", surface)
    check_data(target, "target", surface)
    if prediction.shape != target.shape:
        raise ValueError(
            f"prediction has shape {tuple(prediction.shape)} but target has "
            f"{tuple(target.shape)}; they must match"
        )
    # data of batch 1 on a surface of batch B is measured on each of the B surfaces
    batch = max(prediction.shape[0], surface.batch_size) if surface.layout is None else \
        prediction.shape[0]
    if width is not None:  # bricks built for a narrower band would leave nodes out
        surface.check_band_held(check_positive(width, "width"))
    band = surface.band_mask(width).expand(batch, 1, *prediction.shape[2:])
    errors = torch.where(band, prediction - target, prediction.new_zeros(()))
    counts = (band.sum(dim=(1, 2, 3, 4)) * prediction.shape[1]).to(prediction.dtype)
    totals = (errors * errors).sum(dim=(1, 2, 3, 4))
    if surface.layout is not None:
        # packed rows are bricks: sum them into their batch entries
        entry = surface.layout.batch.to(prediction.device)
        per_entry = prediction.new_zeros((2, surface.batch_size))
        totals, counts = per_entry.index_add(1, entry, torch.stack([totals, counts])).unbind(0)
    _check_nonempty(counts, surface, width)
    return totals, counts


def _check_nonempty(counts: Tensor, surface: ImplicitSurface, width: float | None) -> None:
    """Raise ``ValueError`` if a batch entry's band holds no node (its mean would be NaN); not
    while ``torch.compile`` traces (the check reads the counts on the host)."""
    if torch.compiler.is_compiling() or counts.numel() == 0:
        return
    empty = (counts == 0).nonzero().flatten().tolist()
    if empty:
        used = surface.band_width if width is None else width
        raise ValueError(
            f"the band holds no node at width {used:g} (world units) for batch entries "
            f"{empty}: nothing to measure; pass a wider width (surface.band_width is "
            f"{surface.band_width:g}) or check that phi crosses zero on the grid"
        )


def band_mse(prediction: Tensor, target: Tensor, surface: ImplicitSurface,
             width: float | None = None) -> Tensor:
    """Mean squared error over the band's nodes (all batch entries and channels).

    Args:
        prediction, target: ``(B, C, D, H, W)``, same shape; ``surface`` has batch 1 or B. On
            a :class:`~torchsurf.bricks.BrickSurface`, packed ``(N, C, 8, 8, 8)``.
        surface: the implicit surface.
        width: the band's half-width, world units (default ``surface.band_width``).

    Returns:
        A 0-d tensor, units of the data squared. Values beyond the band are not read; NaN or
        infinity in the band gives NaN or infinity, as any PyTorch loss would.
    """
    total, counts = _squared_errors(prediction, target, surface, width)
    return total.sum() / counts.sum()


def psnr(prediction: Tensor, target: Tensor, surface: ImplicitSurface, peak: float = 1.0,
         width: float | None = None) -> Tensor:
    """Peak signal-to-noise ratio over the band, ``10 log10(peak^2 / MSE)``, per batch entry.

    Args:
        prediction, target: ``(B, C, D, H, W)``, same shape (packed ``(N, C, 8, 8, 8)`` on a
            :class:`~torchsurf.bricks.BrickSurface`).
        surface: the implicit surface.
        peak: the data's peak-to-peak range (1 for data in ``[0, 1]``), units of the data.
        width: the band's half-width, world units (default ``surface.band_width``).

    Returns:
        ``(B,)`` (one per batch entry of a brick surface), decibels (``inf`` where the
        prediction is exact, or its MSE below the dtype's smallest normal number; such an
        entry passes a zero gradient, so a mean over a batch holding one still trains on the
        others). NaN in an entry's band makes that entry NaN, infinity ``-inf``; the other
        entries keep their values.
    """
    check_positive(peak, "peak")
    total, counts = _squared_errors(prediction, target, surface, width)
    mse = total / counts
    # exact, or below the dtype's normal numbers, where log10's derivative 1 / (mse ln 10)
    # overflows (its gradient would be 0 * inf, or inf)
    exact = mse < torch.finfo(mse.dtype).tiny
    ratio = 20.0 * math.log10(peak) - 10.0 * torch.log10(
        torch.where(exact, torch.ones_like(mse), mse))
    return torch.where(exact, torch.full_like(ratio, math.inf), ratio)
