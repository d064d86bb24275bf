"""torchsurf: variational problems and PDEs on implicit surfaces, as PyTorch modules.

Bertalmío, Cheng, Osher & Sapiro (2001): data on the zero level set of ``phi`` is extended
to a band around it and every intrinsic operator is computed on the Cartesian grid.
"""

from . import backend, bricks, datasets, exact, flows, mesh, nn, operators, sdf, shape_batch, stencils
from ._checks import MismatchError
from .flows import (
    AnisotropicFlow,
    ColorDenoise,
    Extension,
    Flow,
    FlowVisualization,
    HarmonicMapFlow,
    HeatFlow,
    ReactionDiffusion,
)
from .grid import Grid
from .mesh import MeshAdapter
from .operators import (
    AnisotropicDiffusion,
    DirectionalDiffusion,
    IntrinsicDivergence,
    IntrinsicGradient,
    LaplaceBeltrami,
    anisotropic_diffusion,
    directional_diffusion,
    intrinsic_divergence,
    intrinsic_gradient,
    laplace_beltrami,
)
from .sampling import sample
from .shape_batch import AnalyticShape, MeshBatchAdapter
from .surface import ImplicitSurface

__version__ = "0.1.0"

__all__ = [
    "AnalyticShape",
    "AnisotropicDiffusion",
    "AnisotropicFlow",
    "ColorDenoise",
    "Extension",
    "Flow",
    "FlowVisualization",
    "HarmonicMapFlow",
    "HeatFlow",
    "ReactionDiffusion",
    "DirectionalDiffusion",
    "Grid",
    "ImplicitSurface",
    "IntrinsicDivergence",
    "IntrinsicGradient",
    "LaplaceBeltrami",
    "MeshAdapter",
    "MeshBatchAdapter",
    "MismatchError",
    "anisotropic_diffusion",
    "backend",
    "bricks",
    "datasets",
    "directional_diffusion",
    "exact",
    "flows",
    "intrinsic_divergence",
    "intrinsic_gradient",
    "laplace_beltrami",
    "mesh",
    "nn",
    "operators",
    "sample",
    "sdf",
    "shape_batch",
    "stencils",
]
