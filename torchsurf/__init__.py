"""torchsurf: variational problems and PDEs on implicit surfaces, as PyTorch modules.

Bertalmío, Cheng, Osher & Sapiro (2001): data on the zero level set of ``phi`` is extended
to a band around it and every intrinsic operator is computed on the Cartesian grid.

The package's names are loaded on first use (``torchsurf.HeatFlow`` imports
``torchsurf.flows`` then), so that ``import torchsurf`` and the ``torchsurf`` command start
without importing torch, trimesh and the rest: an interrupt during those imports could be
swallowed by a library's optional-import guard, and the command holds interrupts across them.
"""

from __future__ import annotations

import importlib
import pkgutil
import sys
from typing import TYPE_CHECKING

__version__ = "0.1.0"

_SUBMODULES = ("backend", "bricks", "datasets", "exact", "flows", "mesh", "nn", "operators",
               "sdf", "shape_batch", "stencils")

_NAMES = {
    "MismatchError": "_checks",
    **dict.fromkeys(("AnisotropicFlow", "ColorDenoise", "Extension", "Flow", "FlowVisualization",
                     "HarmonicMapFlow", "HeatFlow", "ReactionDiffusion"), "flows"),
    "Grid": "grid",
    "MeshAdapter": "mesh",
    **dict.fromkeys(("AnisotropicDiffusion", "DirectionalDiffusion", "IntrinsicDivergence",
                     "IntrinsicGradient", "LaplaceBeltrami", "anisotropic_diffusion",
                     "directional_diffusion", "intrinsic_divergence", "intrinsic_gradient",
                     "laplace_beltrami"), "operators"),
    "sample": "sampling",
    "AnalyticShape": "shape_batch",
    "MeshBatchAdapter": "shape_batch",
    "ImplicitSurface": "surface",
}

__all__ = [
    "AnalyticShape",
    "AnisotropicDiffusion",
    "AnisotropicFlow",
    "ColorDenoise",
    "DirectionalDiffusion",
    "Extension",
    "Flow",
    "FlowVisualization",
    "Grid",
    "HarmonicMapFlow",
    "HeatFlow",
    "ImplicitSurface",
    "IntrinsicDivergence",
    "IntrinsicGradient",
    "LaplaceBeltrami",
    "MeshAdapter",
    "MeshBatchAdapter",
    "MismatchError",
    "ReactionDiffusion",
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


def __getattr__(name: str) -> object:
    if name in _NAMES:
        value = getattr(_import(f"{__name__}.{_NAMES[name]}"), name)
    elif name in _public_submodules():
        value = _import(f"{__name__}.{name}")
    else:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    globals()[name] = value
    return value


def _import(module: str) -> object:
    """``module`` imported outside ``torch.inference_mode``: a first use inside an evaluation
    loop would otherwise make the modules' constant tensors inference tensors, which every
    later call that autograd records would fail to save."""
    torch = sys.modules.get("torch")
    if torch is None or not torch.is_inference_mode_enabled():
        return importlib.import_module(module)
    with torch.inference_mode(False):
        return importlib.import_module(module)


def _public_submodules() -> set[str]:
    """The package's modules and subpackages whose names do not start with ``_``."""
    return {info.name for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_")}


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__, *_public_submodules()})


if TYPE_CHECKING:
    from . import backend, bricks, datasets, exact, flows, mesh, nn, operators, sdf, shape_batch, stencils
    from . import cli as cli
    from . import config as config
    from . import curvature as curvature
    from . import experiment as experiment
    from . import grid as grid
    from . import render as render
    from . import sampling as sampling
    from . import signals as signals
    from . import surface as surface
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
