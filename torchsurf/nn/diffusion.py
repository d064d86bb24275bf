"""``LearnedDiffusion``: heat diffusion on the surface with one learned time per channel.

Each channel ``c`` becomes ``exp(t_c h^2 Lap_S) u_c`` (DiffusionNet's learned diffusion, with
no eigendecomposition): the heat semigroup on the surface's band by Chebyshev expansion
(:func:`torchsurf.flows.exponential.heat_semigroup`), whose cost grows as ``sqrt(t_c)`` and whose
backward stores no step (docs/learning.md).

Times are **scale-free, in units of h^2**, the squared spacing of the surface's grid: ``t = 1``
diffuses over about one cell (diffusion length ``sqrt(2 t) h``) whatever the world size of the
shape, so a model trained on shapes normalised to one grid transfers to any shape put on a grid
of the same resolution.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._checks import check_choice, check_count
from ..backend import PATHS
from ..flows.exponential import BandLaplacian, heat_semigroup
from ..operators import functional
from ..surface import ImplicitSurface, check_data, check_surface


def _inverse_softplus(value: Tensor) -> Tensor:
    return value + torch.log(-torch.expm1(-value))


FLOOR = 1e-6
"""Smallest learned time, ``h^2`` units: softplus alone can underflow to exactly 0."""


class LearnedDiffusion(nn.Module):
    """``u_c -> exp(t_c h^2 Lap_S) u_c`` on the surface's band, ``t_c > 0`` learned per channel.

    ``Lap_S`` is the divergence-form Laplace–Beltrami of ``scheme`` on the band of
    ``surface.band_width``, the ring of nodes around the band re-extended along normals from the
    band at every operator application (:mod:`torchsurf.flows.exponential`). Nodes beyond the
    band and its ring are returned unchanged; the band's values are the only ones read.

    Cost: about ``sqrt(t_c h^2 rho)`` applications of the operator forward (``rho ~ 12 / h^2``,
    so about ``4 sqrt(t)`` to ``5 sqrt(t)`` in float32 for the largest ``t_c``), as many in
    backward; memory for backward: the input and the times, whatever the times (gradients to a
    ``phi`` that requires grad recompute the expansion, ``O(sqrt(terms))`` volumes kept).

    Args:
        channels: ``C``, the number of channels (one time each).
        time: initial times, ``h^2`` units: a positive number or ``C`` of them.
        learn_time: make the times an ``nn.Parameter`` (``softplus(raw) + 1e-6``); otherwise
            they are a buffer.
        scheme: ``"octant"`` (default), ``"symmetric"`` or ``"conservative"``
            (:func:`torchsurf.laplace_beltrami`).
        path: how the stencils run (:mod:`torchsurf.backend`).

    Shapes: ``u`` ``(B, C, D, H, W)`` on a surface of batch 1 or ``B`` -> ``(B, C, D, H, W)``;
    on a :class:`~torchsurf.bricks.BrickSurface`, packed ``(N, C, 8, 8, 8)`` -> the same.

    Example:
        >>> import torch
        >>> import torchsurf as ts
        >>> grid = ts.Grid.cube(17, bound=1.5)
        >>> surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
        >>> layer = ts.nn.LearnedDiffusion(2, time=[1.0, 4.0])
        >>> layer(torch.rand(3, 2, 17, 17, 17), surface).shape
        torch.Size([3, 2, 17, 17, 17])
    """

    def __init__(self, channels: int, time: float | list[float] | Tensor = 1.0,
                 learn_time: bool = True, scheme: str = "octant", path: str = "auto") -> None:
        super().__init__()
        self.channels = check_count(channels, "channels")
        initial = torch.as_tensor(time, dtype=torch.get_default_dtype()).detach().clone()
        if initial.dim() == 0:
            initial = initial.expand(self.channels).clone()
        if (initial.shape != (self.channels,) or initial.is_complex()
                or not bool((torch.isfinite(initial) & (initial > 0)).all())):
            raise ValueError(
                f"time must be a positive number or {self.channels} of them (h^2 units), got "
                f"{time!r}"
            )
        self.learn_time = bool(learn_time)
        if self.learn_time:
            self.raw_time = nn.Parameter(_inverse_softplus(initial - FLOOR))
        else:
            self.register_buffer("fixed_time", initial)
        self.scheme = check_choice(scheme, "scheme", functional.SCHEMES)
        self.path = check_choice(path, "path", PATHS)

    @property
    def time(self) -> Tensor:
        """The times ``(C,)``, ``h^2`` units (in the graph of the parameter when learned)."""
        if self.learn_time:
            return F.softplus(self.raw_time) + FLOOR
        return self.fixed_time

    def forward(self, u: Tensor, surface: ImplicitSurface) -> Tensor:
        """Diffuse ``u`` ``(B, C, D, H, W)``; returns ``(B, C, D, H, W)`` (class docstring)."""
        check_surface(surface)
        check_data(u, "u", surface, channels=self.channels)
        operator = BandLaplacian(surface, self.scheme, path=self.path)
        times = self.time.to(u.dtype) * surface.spacing**2
        return heat_semigroup(u, operator, times)

    def extra_repr(self) -> str:
        return f"channels={self.channels}, scheme={self.scheme!r}, learn_time={self.learn_time}"
