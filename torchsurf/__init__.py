"""torchsurf: variational problems and PDEs on implicit surfaces, as PyTorch modules."""

from . import sdf, stencils
from .grid import Grid
from .operators import LaplaceBeltrami, laplace_beltrami
from .surface import ImplicitSurface

__version__ = "0.1.0"

__all__ = [
    "Grid",
    "ImplicitSurface",
    "LaplaceBeltrami",
    "laplace_beltrami",
    "sdf",
    "stencils",
]
