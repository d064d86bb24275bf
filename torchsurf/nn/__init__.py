"""Learning layers on implicit surfaces: learned diffusion, gradient features, residual blocks,
band-masked losses (docs/learning.md)."""

from .diffusion import LearnedDiffusion

__all__ = ["LearnedDiffusion"]
