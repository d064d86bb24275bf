"""Positive flow parameters (times, diffusivities, contrasts), optionally learnable.

A learnable value is stored as an unconstrained ``nn.Parameter`` ``raw`` and read as
``softplus(raw)``, so that an optimiser can never make it zero or negative; a fixed value stays
a Python float (exact, no round trip through the parametrisation).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def _inverse_softplus(value: Tensor) -> Tensor:
    """``x`` with ``softplus(x) == value`` for ``value > 0`` (stable for large values)."""
    return value + torch.log(-torch.expm1(-value))


class Positive(nn.Module):
    """A positive number or per-channel vector ``(C,)``, fixed or learnable through softplus.

    Args:
        value: the initial value: a number, or a sequence/tensor of shape ``(C,)``, all > 0.
        name: the argument's name, used in error messages.
        learnable: register ``softplus^-1(value)`` as an ``nn.Parameter``.
    """

    def __init__(self, value: float | Tensor, name: str, learnable: bool = False) -> None:
        super().__init__()
        self.name = name
        tensor = torch.as_tensor(value, dtype=torch.get_default_dtype())
        if tensor.dim() > 1 or not bool(torch.isfinite(tensor).all()) or not bool((tensor > 0).all()):
            raise ValueError(
                f"{name} must be a finite positive number or a vector (C,) of them, got {value!r}"
            )
        self.learnable = bool(learnable)
        self.fixed: float | Tensor | None = None
        if self.learnable:
            self.raw = nn.Parameter(_inverse_softplus(tensor.detach().clone()))
        elif tensor.dim() == 0:
            self.fixed = float(value)
        else:
            self.register_buffer("values", tensor.detach().clone())

    @property
    def channels(self) -> int | None:
        """``C`` for a per-channel value, ``None`` for a single number."""
        value = self.raw if self.learnable else (None if self.fixed is not None else self.values)
        return None if value is None or value.dim() == 0 else value.shape[0]

    def value(self) -> float | Tensor:
        """The positive value: a float, or a tensor ``()`` / ``(C,)`` in the graph of ``raw``."""
        if self.learnable:
            return F.softplus(self.raw)
        return self.fixed if self.fixed is not None else self.values

    def maximum(self) -> float:
        """The largest entry, as a float (for step-size bounds)."""
        value = self.value()
        return value if isinstance(value, float) else float(value.detach().max())

    def volume(self, like: Tensor) -> float | Tensor:
        """The value shaped to broadcast over a volume ``(B, C, D, H, W)`` like ``like``."""
        value = self.value()
        if isinstance(value, float):
            return value
        if value.dim() == 1 and value.shape[0] not in (1, like.shape[1]):
            raise ValueError(
                f"{self.name} has {value.shape[0]} entries but the data has {like.shape[1]} "
                "channels; give one value or one per channel"
            )
        value = value.to(dtype=like.dtype, device=like.device)
        return value.view(1, -1, 1, 1, 1) if value.dim() == 1 else value

    def extra_repr(self) -> str:
        return f"{self.name}, learnable={self.learnable}"
