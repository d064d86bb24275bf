"""Validation of operator inputs against the surface they act on."""

from __future__ import annotations

from torch import Tensor

from .._checks import check_batch, check_spatial_shape, check_volume
from ..surface import ImplicitSurface


def check_surface(surface: object) -> ImplicitSurface:
    """Raise ``TypeError`` unless ``surface`` is an :class:`ImplicitSurface`."""
    if not isinstance(surface, ImplicitSurface):
        raise TypeError(
            f"surface must be a torchsurf.ImplicitSurface, got {type(surface).__name__}"
        )
    return surface


def check_data(value: object, name: str, surface: object, channels: int | None = None) -> Tensor:
    """Check a volume ``(B, C, D, H, W)`` against ``surface``: spatial shape, batch, dtype, device."""
    surface = check_surface(surface)
    volume = check_volume(value, name, channels=channels)
    check_spatial_shape(volume, name, surface.grid.shape, "surface.grid")
    check_batch(volume, name, surface.batch_size, "surface")
    if volume.dtype != surface.phi.dtype or volume.device != surface.phi.device:
        raise ValueError(
            f"{name} has dtype {volume.dtype} on {volume.device} but surface has "
            f"{surface.phi.dtype} on {surface.phi.device}; move one of them with .to()"
        )
    return volume
