"""``DiffusionBlock``: diffuse, take gradient features, mix pointwise, add back (DiffusionNet's
block on an implicit surface's band)."""

from __future__ import annotations

import inspect
import math

import torch
from torch import Tensor, nn

from .._as_is import run_as_is_first
from .._checks import MismatchError, check_count, check_flag
from .._transforms import refuse_transforms
from ..surface import ImplicitSurface, check_data, check_surface
from .diffusion import LearnedDiffusion
from .features import feature_count, gradient_features


def _band_nodes(surface: ImplicitSurface) -> Tensor:
    """Indices ``(N,)`` of the nodes of ``surface.band_mask()`` among its ``B * D * H * W``,
    found once per surface: a forward that ``torch.compile`` traces then reads a tensor of
    known size instead of selecting by a mask (a size known only from the data: a graph
    break)."""
    return surface.kept(("band nodes",), lambda: surface.band_mask().flatten().nonzero()[:, 0])


_DIFFUSION_ARGUMENTS = set(inspect.signature(LearnedDiffusion).parameters) - {"channels", "time"}
"""The keyword arguments :class:`DiffusionBlock` passes on to :class:`LearnedDiffusion`."""


class DiffusionBlock(nn.Module):
    """``u + MLP([d, features(d)])`` on the band, ``d = LearnedDiffusion(u)``.

    The MLP is pointwise (a 1x1x1 convolution: ``Linear -> ReLU -> Linear`` on each node's
    ``C + feature_count(C)`` values) and is **evaluated at the band's nodes only** (those of
    ``surface.band_mask()``): they are gathered, mixed and scattered back. Outside the band the
    block returns ``u`` as it is (the next diffusion reads the band only and re-extends the
    rest). The last layer starts at zero, so a new block is the identity.

    Args:
        channels: ``C``, channels in and out.
        hidden: width of the MLP's hidden layer (default ``2 C`` plus its
            ``C + feature_count(C, pairs)`` inputs).
        time: initial diffusion times, ``h^2`` units (:class:`LearnedDiffusion`).
        pairs: use the products of pairs of channels' gradients as features.
        **diffusion: other arguments of :class:`LearnedDiffusion` (``scheme``, ``path``,
            ``learn_time``); ``path`` also applies to the gradient features.

    Shapes: ``(B, C, D, H, W)`` on a surface of batch 1 or ``B`` -> ``(B, C, D, H, W)`` (data
    of batch 1 on a surface of batch ``B`` gives ``B`` entries, as the flows do); on a
    :class:`~torchsurf.bricks.BrickSurface`, packed ``(N, C, 8, 8, 8)`` -> the same.
    """

    def __init__(self, channels: int, hidden: int | None = None, time: float | list[float] = 1.0,
                 pairs: bool = True, **diffusion: object) -> None:
        super().__init__()
        self.channels = channels = check_count(channels, "channels")
        self.pairs = check_flag(pairs, "pairs")
        inputs = channels + feature_count(channels, self.pairs)
        hidden = 2 * channels + inputs if hidden is None else check_count(hidden, "hidden")
        unknown = sorted(set(diffusion) - _DIFFUSION_ARGUMENTS)
        if unknown:
            raise TypeError(
                f"DiffusionBlock got unexpected keyword arguments {unknown}; besides its own it "
                f"takes LearnedDiffusion's {sorted(_DIFFUSION_ARGUMENTS)}")
        self.diffusion = LearnedDiffusion(channels, time=time, **diffusion)
        self.mlp = nn.Sequential(nn.Linear(inputs, hidden), nn.ReLU(), nn.Linear(hidden, channels))
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)

    def forward(self, u: Tensor, surface: ImplicitSurface) -> Tensor:
        """``u + MLP([d, features(d)])`` on the band, ``u`` beyond: ``(B, C, D, H, W)`` (or
        packed ``(N, C, 8, 8, 8)``) -> the same shape (the class's docstring)."""
        run_as_is_first(self, u, surface)
        check_surface(surface)
        refuse_transforms(type(self).__name__, u, forward_mode=False, phi=surface.phi,
                          why="its diffusion's exp(t L) is an autograd Function with a backward "
                              "only")
        check_data(u, "u", surface, channels=self.channels)
        weight = self.mlp[0].weight
        if u.dtype != weight.dtype:
            raise MismatchError(f"u is {u.dtype} but the block's MLP is {weight.dtype}: convert one "
                            f"of them (block.to({u.dtype}) or u.to({weight.dtype}))")
        if surface.layout is None and u.shape[0] == 1 and surface.batch_size > 1:
            u = u.expand(surface.batch_size, *u.shape[1:])  # one datum on every surface
        diffused = self.diffusion(u, surface)
        features = torch.cat([
            diffused, gradient_features(diffused, surface, self.pairs, path=self.diffusion.path)
        ], dim=1)
        batch, size = u.shape[0], math.prod(u.shape[2:])
        index = _band_nodes(surface).to(u.device)
        if surface.layout is None and surface.batch_size != batch:  # one surface for every entry
            index = (torch.arange(batch, device=u.device)[:, None] * size + index).flatten()
        nodes = features.permute(0, 2, 3, 4, 1).reshape(batch * size, -1).index_select(0, index)
        update = self.mlp(nodes)  # (N, C)
        scattered = u.new_zeros(batch * size, self.channels).index_copy(0, index, update)
        return u + scattered.view(batch, *u.shape[2:], self.channels).permute(0, 4, 1, 2, 3)

    def extra_repr(self) -> str:
        return f"channels={self.channels}, pairs={self.pairs}"
