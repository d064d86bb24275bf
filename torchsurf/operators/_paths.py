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


@functools.cache
def compiled(function: Callable[..., Tensor]) -> Callable[..., Tensor]:
    """``function`` compiled once per process (shapes specialised)."""
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
