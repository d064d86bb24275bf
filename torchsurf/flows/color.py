"""Colour denoising on a surface: brightness and chroma flowed apart (the paper's §3.2)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .._checks import check_positive
from ..surface import ImplicitSurface, check_data
from .anisotropic import AnisotropicFlow
from .base import Flow
from .harmonic import HarmonicMapFlow


class ColorDenoise(nn.Module):
    """Denoise RGB data: chroma ``c = I / |I|`` by a harmonic map flow, brightness ``b = |I|``
    by a scalar flow, result ``b c``.

    Args:
        time: end time of both flows (physical time), unless ``chroma``/``brightness`` are given.
        p: exponent of the chroma's harmonic map flow (1, the paper's figure 3, by default).
        chroma: the flow for the chroma (a :class:`HarmonicMapFlow`); default
            ``HarmonicMapFlow(time, p=p, **kwargs)``.
        brightness: the flow for the brightness (any scalar :class:`Flow`); default
            total variation, ``AnisotropicFlow(time, eps=0.1, **kwargs)``.
        eps: regularisation of ``|I|``, units of ``I``.
        **kwargs: integration settings of :class:`Flow` for the default flows.

    Shapes: ``(B, 3, D, H, W) -> (B, 3, D, H, W)`` (any number of colour channels works).
    """

    def __init__(
        self,
        time: float,
        p: float = 1.0,
        chroma: Flow | None = None,
        brightness: Flow | None = None,
        eps: float = 1e-6,
        **kwargs: object,
    ) -> None:
        super().__init__()
        self.chroma = chroma if chroma is not None else HarmonicMapFlow(time, p=p, **kwargs)
        self.brightness = (
            brightness if brightness is not None else AnisotropicFlow(time, eps=0.1, **kwargs)
        )
        self.eps = check_positive(eps, "eps")

    def forward(self, image: Tensor, surface: ImplicitSurface) -> Tensor:
        check_data(image, "image", surface)
        brightness = torch.sqrt((image**2).sum(dim=1, keepdim=True) + self.eps**2)
        chroma = image / brightness
        return self.brightness(brightness, surface) * self.chroma(chroma, surface)
