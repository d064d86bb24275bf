"""torchsurf computes in the data's dtype: its products and convolutions under ``torch.autocast``
too, and its fixed settings kept through a module's conversion to a dtype it does not compute in."""

from __future__ import annotations

import contextlib
from collections.abc import Callable

import torch
from torch import Tensor, nn

from ._checks import SUPPORTED_DTYPES


def in_data_dtype(tensor: Tensor) -> contextlib.AbstractContextManager:
    """Autocast turned off on ``tensor``'s device for one convolution or product of
    torchsurf's (its stencils, curvatures, interpolation weights, signals). Autocast lowers
    exactly those ops to bfloat16 or float16, and second differences lose everything there:
    Laplace-Beltrami at 48^3 came out 126% off under CPU autocast, the Gaussian curvature
    1.1e-2 off (an audit, 2026-12-07). The caller's own layers keep its autocast."""
    return torch.autocast(tensor.device.type, enabled=False)


def apply_keeping_dtype(module: nn.Module, names: tuple[str, ...],
                        apply: Callable[[], nn.Module]) -> nn.Module:
    """``apply()`` (the module's ``nn.Module._apply``), with its buffers ``names`` kept in
    their dtype where it would turn them into one torchsurf does not compute in (moved to the
    device it moves them to): fixed settings, cast to the data's dtype where they are used.
    ``model.half()`` had rounded them for float32 data (a diffusivity of 1.3 to 1.2998, the
    flow 5.9e-5 off; an audit, 2026-12-07); ``.double()`` and ``.float()`` convert them."""
    before = {name: module._buffers[name] for name in names
              if module._buffers.get(name) is not None}
    result = apply()
    for name, tensor in before.items():
        moved = module._buffers[name]
        if moved.dtype != tensor.dtype and moved.dtype not in SUPPORTED_DTYPES:
            module._buffers[name] = tensor.to(device=moved.device)
    return result
