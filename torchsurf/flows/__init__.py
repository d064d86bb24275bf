"""Flows on implicit surfaces (the paper's §2): heat, anisotropic, harmonic maps, colour,
reaction–diffusion, flow visualisation and data extension, with explicit, implicit
(conjugate gradients) and torchdiffeq integration."""

from ._integrators import (
    EQUILIBRIUM_CROSSINGS,
    IMPLICIT,
    INTEGRATORS,
    MAX_STEPS,
    BeyondEquilibrium,
    Plan,
    check_method,
)
from .anisotropic import AnisotropicFlow
from .base import Flow
from .color import ColorDenoise
from .extension import Extension, closest_point_extension, pde_extension
from .harmonic import HarmonicMapFlow
from .heat import HeatFlow
from .reaction_diffusion import ReactionDiffusion
from .visualization import FlowVisualization

__all__ = [
    "EQUILIBRIUM_CROSSINGS",
    "IMPLICIT",
    "INTEGRATORS",
    "MAX_STEPS",
    "AnisotropicFlow",
    "BeyondEquilibrium",
    "ColorDenoise",
    "Extension",
    "Flow",
    "FlowVisualization",
    "HarmonicMapFlow",
    "HeatFlow",
    "Plan",
    "ReactionDiffusion",
    "check_method",
    "closest_point_extension",
    "pde_extension",
]
