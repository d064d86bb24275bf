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

from .._as_is import run_as_is_first
from .._checks import (
    MismatchError,
    as_real_tensor,
    check_choice,
    check_count,
    check_finite,
    check_flag,
    check_positive,
)
from .._precision import apply_keeping_dtype
from .._transforms import refuse_transforms, saved_plainly_in_checkpoints
from ..backend import PATHS
from ..flows._positive import HostValues, range_note, raw_within
from ..flows.chebyshev import MAX_APPLICATIONS, TooManyApplications
from ..flows.exponential import BandLaplacian, heat_semigroup
from ..operators import functional
from ..surface import ImplicitSurface, check_data, check_surface

FLOOR = 1e-6
"""Smallest learned time, ``h^2`` units: softplus alone can underflow to exactly 0."""


def check_times(times: Tensor) -> None:
    """Raise ``ValueError`` naming ``time`` unless the learned ``times`` ``(C,)`` (``h^2``
    units) are finite and positive: a step of the optimiser diverged. Read on the host."""
    if not bool((torch.isfinite(times) & (times > 0)).all()):
        raise ValueError(
            f"time must be finite and positive (h^2 units), got {times.detach().tolist()!r}: an "
            "optimiser step diverged (layer.time)"
        )


def _reread_largest_time(module: LearnedDiffusion, _: object) -> None:
    """After ``load_state_dict``: the loaded fixed times' maximum (see ``HostValues``)."""
    module._largest.of(module.fixed_time)


class LearnedDiffusion(nn.Module):
    """``u_c -> exp(t_c h^2 Lap_S) u_c`` on the surface's band, ``t_c > 0`` learned per channel.

    ``Lap_S`` is the divergence-form Laplace–Beltrami of ``scheme`` on the band of
    ``surface.band_width``, the ring of nodes around the band re-extended along normals from the
    band at every operator application (:mod:`torchsurf.flows.exponential`). Nodes beyond the
    band and its ring are returned unchanged; the band's values are the only ones read.

    Cost: a number of applications of the operator forward that grows as ``sqrt(t_c h^2 rho)``
    (``rho ~ 11 / h^2``; for the largest ``t_c`` in float32 about ``12 sqrt(t) + 3``: 15 at
    ``t = 1``, 41 at 10, 85 at 45; 1.4 times as many in float64) up to about
    ``45 h^2``, beyond which the expansion runs in pieces and the cost grows as ``t``
    (:data:`torchsurf.flows.chebyshev.PIECE_HALF_WIDTH`), as many in backward, each on the
    band's nodes alone when ``phi`` does not require grad (its operators assembled on the first
    call and kept on the surface: :mod:`torchsurf.flows.exponential`); memory for
    backward: the input and the times, whatever the times (gradients to a
    ``phi`` that requires grad recompute the expansion, ``O(sqrt(terms))`` volumes kept per
    piece).

    Args:
        channels: ``C``, the number of channels (one time each).
        time: initial times, ``h^2`` units: a positive number or ``C`` of them (learned times
            at least ``2e-6`` at construction; trained, they stay above ``1e-6``, the
            softplus's floor).
        learn_time: make the times an ``nn.Parameter`` (``softplus(raw) + 1e-6``); otherwise
            they are a buffer (``fixed_time``, which may be changed in place or replaced).
        max_time: with ``learn_time``, the largest time, ``h^2`` units: the times are clamped
            to it (no gradient beyond) and the expansion's length is planned for it on the host,
            so that the forward reads nothing from the parameter and ``torch.compile`` traces
            it whole (docs/learning.md). ``None`` (default): the length follows the largest
            current time, read on the host at each call (one graph break). Costs what the time
            ``max_time`` costs, whatever the times: ``sqrt(max_time)`` operator applications up
            to about ``45 h^2``, then ``max_time`` (pieces). A constructor argument, so not in
            the ``state_dict`` (which holds ``raw_time`` only): give the same ``max_time`` to
            the layer a state is loaded into, since an optimiser's momentum may have moved
            ``raw_time`` beyond the clamp, and without it that time applies.
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
                 learn_time: bool = True, scheme: str = "octant", path: str = "auto",
                 max_time: float | None = None) -> None:
        super().__init__()
        self.channels = check_count(channels, "channels")
        if isinstance(time, Tensor) and time.requires_grad:
            raise ValueError(
                "time is a tensor that requires grad: the layer takes its times as initial "
                "values and would drop that gradient; learn_time=True (the default) makes them "
                "its parameter, or pass time.detach()"
            )
        initial = as_real_tensor(time, "time",
                                 f"a positive number or {self.channels} of them (h^2 units)")
        note = range_note(time, initial)
        if initial.dim() == 0:
            initial = initial.expand(self.channels).clone()
        if (initial.shape != (self.channels,) or initial.is_complex()
                or not bool((torch.isfinite(initial) & (initial > 0)).all())):
            raise ValueError(
                f"time must be a positive number or {self.channels} of them (h^2 units), got "
                f"{time!r}{note}"
            )
        self.learn_time = check_flag(learn_time, "learn_time")
        self.max_time = None if max_time is None else check_positive(max_time, "max_time")
        if self.max_time is not None and not self.learn_time:
            raise ValueError("max_time bounds learned times; learn_time=False here")
        if (self.max_time is not None  # within float rounding: a time at its bound is allowed
                and float(initial.max()) > self.max_time * (1 + torch.finfo(initial.dtype).eps)):
            raise ValueError(
                f"max_time={self.max_time:g} is below the initial time {time!r}; it must be at "
                "least as large"
            )
        if self.learn_time:
            if float(initial.min()) < 2 * FLOOR * (1 - 1e-4):  # float32 rounds 2e-6 down
                raise ValueError(
                    f"learned times must be at least {2 * FLOOR:g} (h^2 units; softplus keeps "
                    f"them above {FLOOR:g}), got {time!r}"
                )
            self.raw_time = nn.Parameter(raw_within(initial, FLOOR, self.max_time))
        else:
            self.register_buffer("fixed_time", initial)
            self._largest = HostValues("fixed_time", self.fixed_time, shape=(channels,))
            self.register_load_state_dict_post_hook(_reread_largest_time)
        self.scheme = check_choice(scheme, "scheme", functional.SCHEMES)
        self.path = check_choice(path, "path", PATHS)

    @property
    def time(self) -> Tensor:
        """The times ``(C,)``, ``h^2`` units (in the graph of the parameter when learned;
        clamped to ``max_time`` when given)."""
        if not self.learn_time:
            return self.fixed_time
        time = F.softplus(self.raw_time) + FLOOR
        return time if self.max_time is None else torch.clamp(time, max=self.max_time)

    def largest_time(self) -> float | None:
        """A host float no smaller than every time, ``h^2`` units, read from no tensor:
        ``max_time``, or the largest fixed time; ``None`` for learned times without
        ``max_time``. Fixed times are read again at every call (outside torch.compile)."""
        return self.max_time if self.learn_time else self._largest.of(self.fixed_time)

    @saved_plainly_in_checkpoints
    def forward(self, u: Tensor, surface: ImplicitSurface) -> Tensor:
        """Diffuse ``u`` ``(B, C, D, H, W)``; returns ``(B, C, D, H, W)`` (class docstring)."""
        run_as_is_first(self, u, surface)
        check_surface(surface)
        refuse_transforms(type(self).__name__, u, forward_mode=False, phi=surface.phi,
                          why="its exp(t L) is an autograd Function with a backward only")
        check_data(u, "u", surface, channels=self.channels)
        if self.learn_time and (u.dtype, u.device) != (self.raw_time.dtype, self.raw_time.device):
            raise MismatchError(
                f"u is {u.dtype} on {u.device} but the learned times are {self.raw_time.dtype} on "
                f"{self.raw_time.device}: move one of them (layer.to(u.device, u.dtype) or "
                f"u.to(...))")
        operator = BandLaplacian(surface, self.scheme, path=self.path)
        check_finite(torch.where(operator.band, u.detach(), 0.0), "u (in the band)")
        area = surface.spacing**2
        largest = self.largest_time()
        times = self.time
        bound = None if largest is None else largest * area
        if torch.compiler.is_compiling():  # traced whole: no host reads, no handler
            return heat_semigroup(u, operator, times.to(u.dtype) * area, bound, extend_first=True)
        if self.learn_time:
            check_times(times)
        try:
            return heat_semigroup(u, operator, times.to(u.dtype) * area, bound, extend_first=True)
        except TooManyApplications as error:
            raise ValueError(
                f"time: {error.time / area:g} h^2 needs {error.applications} applications of the "
                f"operator (more than {MAX_APPLICATIONS}; time * rho = "
                f"{error.time * error.bound:.3g}), hours of work and a likely unit error: the "
                "layer's times are in units of h^2"
            ) from error

    def _apply(self, fn, recurse=True):  # noqa: ANN001, ANN202
        return apply_keeping_dtype(self, ("fixed_time",), lambda: super(LearnedDiffusion, self)
                                   ._apply(fn, recurse))

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: object,
                              **kwargs: object) -> None:
        if not self.learn_time:
            self._largest.check_loaded(state_dict, prefix + "fixed_time")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        bound = "" if self.max_time is None else f", max_time={self.max_time:g}"
        return (f"channels={self.channels}, scheme={self.scheme!r}, learn_time={self.learn_time}"
                f"{bound}")
