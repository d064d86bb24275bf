"""torchsurf's products and convolutions run in the data's dtype, under ``torch.autocast`` too."""

from __future__ import annotations

import contextlib

import torch
from torch import Tensor


def in_data_dtype(tensor: Tensor) -> contextlib.AbstractContextManager:
    """Autocast turned off on ``tensor``'s device for one convolution or product of
    torchsurf's (its stencils, curvatures, interpolation weights, signals). Autocast lowers
    exactly those ops to bfloat16 or float16, and second differences lose everything there:
    Laplace-Beltrami at 48^3 came out 126% off under CPU autocast, the Gaussian curvature
    1.1e-2 off (an audit, 2026-12-07). The caller's own layers keep its autocast."""
    return torch.autocast(tensor.device.type, enabled=False)
