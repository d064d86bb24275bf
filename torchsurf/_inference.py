"""Values kept across calls are built outside ``torch.inference_mode``."""

from __future__ import annotations

import contextlib

import torch


def outside_inference() -> contextlib.AbstractContextManager:
    """Where a value that is kept for later calls (on a surface, in a stencil or a packed
    band) is built under ``torch.inference_mode`` (an evaluation loop's): build it as under
    ``torch.no_grad`` instead. A kept inference tensor could not be saved for backward by a
    later training call on the same surface ("Inference tensors cannot be saved for
    backward")."""
    if torch.compiler.is_compiling() or not torch.is_inference_mode_enabled():
        return contextlib.nullcontext()
    stack = contextlib.ExitStack()
    stack.enter_context(torch.inference_mode(False))
    stack.enter_context(torch.no_grad())
    return stack
