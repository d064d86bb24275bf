"""Intrinsic differential operators on implicit surfaces: functions and their modules."""

from . import functional
from .differential import (
    IntrinsicDivergence,
    IntrinsicGradient,
    intrinsic_divergence,
    intrinsic_gradient,
)
from .diffusion import (
    AnisotropicDiffusion,
    DirectionalDiffusion,
    anisotropic_diffusion,
    directional_diffusion,
)
from .diffusivity import DIFFUSIVITIES, charbonnier, perona_malik, total_variation
from .laplace_beltrami import LaplaceBeltrami, laplace_beltrami
from .spectrum import (
    directional_bound,
    gershgorin_bound,
    laplace_beltrami_bound,
    laplace_beltrami_rows,
)

__all__ = [
    "DIFFUSIVITIES",
    "AnisotropicDiffusion",
    "DirectionalDiffusion",
    "IntrinsicDivergence",
    "IntrinsicGradient",
    "LaplaceBeltrami",
    "anisotropic_diffusion",
    "charbonnier",
    "directional_bound",
    "directional_diffusion",
    "functional",
    "gershgorin_bound",
    "intrinsic_divergence",
    "intrinsic_gradient",
    "laplace_beltrami",
    "laplace_beltrami_bound",
    "laplace_beltrami_rows",
    "perona_malik",
    "total_variation",
]
