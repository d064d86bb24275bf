"""Input validation shared by every public entry point: one place words the errors."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor


def check_tensor(value: object, name: str) -> Tensor:
    """Raise ``TypeError`` naming ``name`` unless ``value`` is a floating-point tensor."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    if not value.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor, got dtype {value.dtype}")
    return value


def check_volume(value: object, name: str, channels: int | None = None) -> Tensor:
    """Check that ``value`` is a floating-point volume ``(B, C, D, H, W)``.

    Args:
        value: the tensor to check.
        name: the argument's name, used in the error message.
        channels: the required ``C``, or ``None`` for any.
    """
    volume = check_tensor(value, name)
    if volume.dim() != 5:
        raise ValueError(
            f"{name} must be a volume of shape (B, C, D, H, W), got shape {tuple(volume.shape)}"
        )
    if channels is not None and volume.shape[1] != channels:
        raise ValueError(
            f"{name} must have {channels} channel(s), shape (B, {channels}, D, H, W), "
            f"got shape {tuple(volume.shape)}"
        )
    return volume


def check_finite(value: Tensor, name: str) -> Tensor:
    """Raise ``ValueError`` naming ``name`` if ``value`` holds NaN or infinity."""
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} must hold finite values only, found NaN or infinity")
    return value


def check_spatial_shape(value: Tensor, name: str, shape: Sequence[int], against: str) -> None:
    """Raise ``ValueError`` unless the last three sizes of ``value`` equal ``shape``."""
    if tuple(value.shape[-3:]) != tuple(shape):
        raise ValueError(
            f"{name} has spatial shape {tuple(value.shape[-3:])} but {against} has "
            f"{tuple(shape)}; they must agree"
        )


def check_batch(value: Tensor, name: str, batch: int, against: str) -> None:
    """Raise ``ValueError`` unless ``value``'s batch size is 1 or equals ``batch``, or vice versa."""
    size = value.shape[0]
    if size != batch and size != 1 and batch != 1:
        raise ValueError(
            f"{name} has batch size {size} but {against} has {batch}; "
            "they must be equal or one of them must be 1"
        )


def check_choice(value: str, name: str, choices: Sequence[str]) -> str:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {sorted(choices)}, got {value!r}")
    return value


def check_positive(value: float, name: str) -> float:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is a finite number > 0."""
    if not isinstance(value, (int, float)) or not value > 0 or value == float("inf"):
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")
    return float(value)


def check_count(value: object, name: str, minimum: int = 1) -> int:
    """A whole number ``>= minimum``: Python, numpy or 0-d integer tensors; never a bool."""
    if isinstance(value, Tensor) and value.dim() == 0 and not value.is_floating_point():
        value = int(value)
    if hasattr(value, "__index__") and not isinstance(value, (bool, Tensor)):
        value = value.__index__()
        if value >= minimum:
            return int(value)
    if isinstance(value, int) and not isinstance(value, bool) and value >= minimum:
        return value
    raise ValueError(f"{name} must be a whole number >= {minimum}, got {value!r}")
