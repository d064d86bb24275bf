"""Colour denoising on a surface: brightness and chroma flowed apart (the paper's §3.2)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from .._checks import check_finite, check_positive
from .._transforms import refuse_transforms
from ..surface import ImplicitSurface, check_data, check_surface
from ._positive import check_learned_values
from .anisotropic import AnisotropicFlow
from .base import Flow
from .harmonic import HarmonicMapFlow
from .heat import HeatFlow
from .reaction_diffusion import ReactionDiffusion
from .visualization import FlowVisualization


class ColorDenoise(nn.Module):
    """Denoise RGB data: chroma ``c = I / |I|`` by a harmonic map flow, brightness ``b = |I|``
    by a scalar flow, result ``b c``.

    Brightness and chroma are pointwise, so on a :class:`~torchsurf.bricks.BrickSurface` (data
    packed ``(N, 3, 8, 8, 8)``) the module runs whenever both its flows do
    (:attr:`supports_bricks`; the default ones do).

    Args:
        time: end time of the default flows (physical time); needed unless both ``chroma`` and
            ``brightness`` are given, refused when they are (each flow has its own time).
            With ``p = 1`` both default flows are total-variation flows, whose time is in world
            units (times ``|I|`` for the brightness), not world units squared: a shape scaled
            by ``s`` needs ``s * time`` for about the same result (the bunny at 40³ scaled
            by 10: 0.009 rms apart, against 0.32 rms of change; spot at 40³ scaled by 10 or
            0.1: 0.028-0.031 apart, against 0.18, the brightness's ``eps`` making the
            difference: with it scaled as well they agree to 1e-15).
        p: exponent of the default chroma flow (1, the paper's figure 3, by default); refused
            with ``chroma``.
        chroma: the flow for the chroma, a :class:`HarmonicMapFlow` (or a module of your own
            that keeps unit vectors); default ``HarmonicMapFlow(time, p=p, **kwargs)``.
        brightness: the flow for the brightness, a scalar flow (not a
            :class:`HarmonicMapFlow`); default total variation,
            ``AnisotropicFlow(time, eps=0.1, **kwargs)``, its ``eps`` in units of ``|I|`` per
            world length (small against noise's gradients on shapes of unit size, not
            negligible: above; give your own flow, its ``eps`` scaled with the shape, for
            shapes far from it).
        eps: regularisation of ``|I|``, units of ``I``.
        **kwargs: integration settings of :class:`Flow` for the default flows; refused when both
            flows are given.

    A black node (every channel 0) has no hue: its chroma starts grey, ``(1, ..., 1) / sqrt(C)``,
    and takes its neighbours' as the flow runs; its brightness starts at ``eps``.

    Ranges: the brightness stays within its start's range on the band and the chroma at unit
    length, but a channel alone may leave its range: where a bright, nearly grey region meets
    a saturated one, the grey side's chroma turns towards the other's hue under its own
    brightness (pale grey 0.95 beside pure green: green rises above 1; uniform RGB noise in
    ``[0, 1]`` on a 64³ bunny, 0.156 across, at ``t = 10 h²``: up to 1.36). Clamp the result if
    the channels must stay in ``[0, 1]``.

    Shapes: ``(B, C, D, H, W) -> (B, C, D, H, W)``, ``C >= 2`` colour channels (3 for RGB).
    """

    def __init__(
        self,
        time: float | None = None,
        p: float | None = None,
        chroma: nn.Module | None = None,
        brightness: nn.Module | None = None,
        eps: float = 1e-6,
        **kwargs: object,
    ) -> None:
        super().__init__()
        for name, flow in (("chroma", chroma), ("brightness", brightness)):
            if flow is not None and not isinstance(flow, torch.nn.Module):
                raise TypeError(f"{name} must be a flow (an nn.Module called as flow(u, "
                                f"surface)) or None, got {type(flow).__name__}")
        from ..nn import DiffusionBlock, LearnedDiffusion  # nn builds on the flows

        if isinstance(chroma, (HeatFlow, AnisotropicFlow, ReactionDiffusion, FlowVisualization,
                               ColorDenoise, LearnedDiffusion, DiffusionBlock)):
            raise TypeError(f"chroma must keep unit vectors (a HarmonicMapFlow, or a flow of "
                            f"your own), got {type(chroma).__name__}, which does not")
        if isinstance(brightness, (HarmonicMapFlow, ReactionDiffusion, FlowVisualization,
                                   ColorDenoise)):
            raise TypeError(f"brightness must flow one scalar channel, |I| (a HeatFlow, an "
                            f"AnisotropicFlow, or a flow of your own), got "
                            f"{type(brightness).__name__}")
        both_given = chroma is not None and brightness is not None
        unused = [name for name, ignored in (("time", both_given and time is not None),
                                             ("p", chroma is not None and p is not None))
                  if ignored] + (list(kwargs) if both_given else [])
        if unused:
            raise ValueError(f"{', '.join(unused)}: not used, since the flows they set are given "
                             "(chroma and brightness keep their own settings)")
        if time is None and not both_given:
            raise TypeError("time is needed for the default flows (chroma or brightness not "
                            "given)")
        self.chroma = chroma if chroma is not None else HarmonicMapFlow(
            time, p=1.0 if p is None else p, **kwargs)
        self.brightness = (
            brightness if brightness is not None else AnisotropicFlow(time, eps=0.1, **kwargs)
        )
        self.eps = check_positive(eps, "eps")

    @property
    def supports_bricks(self) -> bool:
        """Whether both flows run on a :class:`~torchsurf.bricks.BrickSurface`."""
        return all(getattr(flow, "supports_bricks", False)
                   for flow in (self.chroma, self.brightness))

    def forward(self, image: Tensor, surface: ImplicitSurface) -> Tensor:
        """The denoised ``image``: ``(B, C, D, H, W)`` (or packed ``(N, C, 8, 8, 8)`` on a
        :class:`~torchsurf.bricks.BrickSurface`), ``C >= 2``, in the same shape."""
        # its flows check forward mode themselves
        refuse_transforms("ColorDenoise", image, phi=getattr(surface, "phi", None))
        check_surface(surface)
        if surface.layout is not None and not self.supports_bricks:
            names = [type(flow).__name__ for flow in (self.chroma, self.brightness)
                     if not getattr(flow, "supports_bricks", False)]
            raise NotImplementedError(
                f"ColorDenoise: {' and '.join(names)} does not run on a BrickSurface yet; "
                "use flows that do or the dense ImplicitSurface (docs/bricks.md)"
            )
        check_data(image, "image", surface)
        for name in ("brightness", "chroma"):  # named here rather than as the flow's own u0
            check_learned_values(getattr(self, name), image, "image",
                                 f"ColorDenoise's {name} flow")
        if image.shape[1] < 2:
            raise ValueError(f"image must have at least 2 colour channels (a chroma of one "
                             f"channel is constant), got shape {tuple(image.shape)}")
        if not torch.compiler.is_compiling() and isinstance(self.chroma, Flow):
            region = self.chroma.region_mask(surface)
            check_finite(torch.where(region, image, 0.0), "image (in the band and its ring)")
        squared = (image**2).sum(dim=1, keepdim=True)
        brightness = torch.sqrt(squared + self.eps**2)
        grey = image.new_full((), image.shape[1] ** -0.5)
        chroma = torch.where(squared > 0, image / brightness, grey)
        return self.brightness(brightness, surface) * self.chroma(chroma, surface)
