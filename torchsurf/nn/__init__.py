"""Learning layers on implicit surfaces: learned diffusion, gradient features, residual blocks,
band-masked losses (docs/learning.md)."""

from .blocks import DiffusionBlock
from .diffusion import LearnedDiffusion
from .features import GradientFeatures, feature_count, gradient_features
from .losses import band_mse, psnr

__all__ = [
    "DiffusionBlock",
    "GradientFeatures",
    "LearnedDiffusion",
    "band_mse",
    "feature_count",
    "gradient_features",
    "psnr",
]
