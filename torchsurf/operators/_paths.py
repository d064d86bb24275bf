"""How an operator's stencil composition runs: eagerly (slicing or conv3d) or compiled.

``"compiled"`` hands the slicing composition of a whole operator to ``torch.compile``, which
fuses it into one pass over memory (docs/benchmarks.md). Compiling costs seconds the first time
for each shape, so ``"auto"`` compiles only volumes of at least ``COMPILE_MIN_VOXELS`` voxels
and leaves small calls (tests, gradcheck) eager.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from torch import Tensor

from .. import stencils
from .._checks import check_choice

PATHS = ("auto", "slicing", "conv3d", "compiled")
COMPILE_MIN_VOXELS = 64**3


RECOMPILE_LIMIT = 64
"""Dynamo's per-function limit on compiled variants, raised to at least this on first compile."""


def _raise_recompile_limit() -> None:
    """Let each operator keep a variant per shape, grad mode and direction (forward/adjoint).

    Dynamo's default of 8 variants per function is spent by two or three grid sizes (each
    needs a no-grad forward, a recording forward and the adjoint), after which it silently
    runs the function eagerly, 10-30x slower. The setting is process-wide; it is only raised.
    """
    config = torch._dynamo.config
    for name in ("recompile_limit", "cache_size_limit"):  # renamed in torch 2.6
        if hasattr(config, name) and getattr(config, name) < RECOMPILE_LIMIT:
            setattr(config, name, RECOMPILE_LIMIT)


@functools.cache
def compiled(function: Callable[..., Tensor]) -> Callable[..., Tensor]:
    """``function`` compiled once per process (shapes specialised)."""
    _raise_recompile_limit()
    return torch.compile(function, dynamic=False)


def resolve(path: str, volume: Tensor) -> str:
    """The concrete path for ``volume``: one of ``"slicing"``, ``"conv3d"``, ``"compiled"``."""
    check_choice(path, "path", PATHS)
    if path != "auto":
        return path
    large = volume.numel() >= COMPILE_MIN_VOXELS
    if large and not torch.compiler.is_compiling():
        return "compiled"
    return stencils.resolve_path("auto", volume)


def run(function: Callable[..., Tensor], path: str, volume: Tensor, *args: object) -> Tensor:
    """Call ``function(*args, path=...)`` on the path chosen for ``volume``."""
    path = resolve(path, volume)
    if path == "compiled":
        return compiled(function)(*args, path="slicing")
    return function(*args, path=path)
