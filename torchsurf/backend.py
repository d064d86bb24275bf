"""Where every operator's stencil arithmetic runs: the one place that chooses, by measurement.

An operator is a :class:`Kernel`: a reference composition of stencils that runs eagerly on any
device (by shifted slices or by conv3d), and optionally a one-pass form over haloed inputs that
``torch.compile`` fuses into a single sweep over memory. :func:`run` picks the path:

- ``"slicing"`` / ``"conv3d"``: eager. Slices are faster on CPU (conv3d with few channels falls
  back to im2col there, 2-5x slower), conv3d elsewhere; ``"auto"`` takes the faster one for the
  device when it stays eager.
- ``"compiled"``: the one-pass form, compiled once per shape (docs/benchmarks.md: the octant
  Laplace–Beltrami at 128^3 runs at 1.5x the memory-traffic limit, 7x faster than eager).
- ``"auto"``: compiled when it pays. Compiling costs seconds for each kernel and shape, so
  ``"auto"`` compiles a volume of at least :data:`COMPILE_MIN_VOXELS` voxels at once, and a
  smaller one, when autograd does not record the call, as soon as the eager time measured on
  that kernel and shape in this process reaches :data:`COMPILE_PAYBACK_SECONDS`, the measured
  cost of compiling it: a flow run many times is compiled after a few seconds of eager work,
  while a one-off call never waits for a compiler.

Inside a function that ``torch.compile`` is tracing every operator stays eager, so that the
outer compiler sees plain tensor operations. Compiled kernels have no double backward: pass an
eager ``path`` to differentiate twice.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ._checks import check_choice

PATHS = ("auto", "slicing", "conv3d", "compiled")
"""Values of every operator's ``path`` argument."""

EAGER_PATHS = ("slicing", "conv3d")

COMPILE_MIN_VOXELS = 64**3
"""Volumes (batch x channels x voxels) at least this large are compiled on their first call."""

COMPILE_PAYBACK_SECONDS = 4.0
"""Eager seconds spent on one kernel and shape after which ``"auto"`` compiles it.

About the time ``torch.compile`` takes for one of the operators on this machine class
(2-6 s per kernel and shape, docs/benchmarks.md), so that ``"auto"`` never spends more than
about twice what the better choice in hindsight would have.
"""

RECOMPILE_LIMIT = 64
"""Dynamo's per-function limit on compiled variants, raised to at least this on first compile."""


@dataclass(frozen=True)
class Kernel:
    """One operator, in the forms :func:`run` chooses between.

    Attributes:
        name: for error messages and the eager-time ledger.
        eager: ``eager(*args, path=...)``, the reference composition of stencils, for
            ``path`` in :data:`EAGER_PATHS`.
        fused: ``fused(*haloed_args)``, one pointwise expression over haloed inputs, or
            ``None`` when the operator has no fused form (it is then never compiled).
        halo: ``halo(*args) -> haloed_args``, run eagerly before ``fused`` (padding outside a
            compiled kernel keeps its loads contiguous: 3-4x faster at 128^3).
        fused_when_eager: run ``fused`` (uncompiled) for ``"slicing"`` too, when it is the
            faster eager form.
        dynamic: compile with dynamic shapes (one variant for every size; for kernels whose
            sizes vary from call to call, such as a gather over a surface's band nodes).
    """

    name: str
    eager: Callable[..., Tensor]
    fused: Callable[..., Tensor] | None = None
    halo: Callable[..., tuple] | None = None
    fused_when_eager: bool = False
    dynamic: bool = False


def eager_path(volume: Tensor) -> str:
    """The faster eager path for ``volume``'s device: slicing on CPU, conv3d elsewhere."""
    return "slicing" if volume.device.type == "cpu" else "conv3d"


def _raise_recompile_limit() -> None:
    """Let each kernel keep a variant per shape, grad mode and direction (forward/adjoint).

    Dynamo's default of 8 variants per function is spent by two or three grid sizes (each
    needs a no-grad forward, a recording forward and the adjoint), after which it silently
    runs the function eagerly, 10-30x slower. The setting is process-wide; it is only raised.
    """
    config = torch._dynamo.config
    for name in ("recompile_limit", "cache_size_limit"):  # renamed in torch 2.6
        if hasattr(config, name) and getattr(config, name) < RECOMPILE_LIMIT:
            setattr(config, name, RECOMPILE_LIMIT)
    _keep_buffers()


def _keep_buffers() -> None:
    """Turn AOTAutograd's donated buffers off, process-wide, where this torch has them.

    With them a compiled kernel's backward refuses ``backward(retain_graph=True)``, which
    gradcheck and several losses on one graph use. They are read when the backward is
    compiled, during the first backward, so the setting cannot be scoped to the call.
    """
    try:
        import torch._functorch.config as functorch_config
    except ImportError:
        return
    if getattr(functorch_config, "donated_buffer", False):
        functorch_config.donated_buffer = False


@functools.cache
def compiled(function: Callable[..., Tensor], dynamic: bool = False) -> Callable[..., Tensor]:
    """``function`` compiled once per process (shapes specialised unless ``dynamic``)."""
    _raise_recompile_limit()
    return torch.compile(function, dynamic=dynamic)


_EAGER_SECONDS: dict[tuple, float] = {}
"""Eager time measured per (kernel, shape, dtype, device, grad mode) in this process."""


def _ledger_key(kernel: Kernel, volume: Tensor) -> tuple:
    return (kernel.name, tuple(volume.shape), volume.dtype, volume.device.type,
            torch.is_grad_enabled())


@dataclass
class _Decisions:
    paths: list[str] = field(default_factory=list)
    replaying: bool = False
    position: int = 0


_DECISIONS: contextvars.ContextVar[_Decisions | None] = contextvars.ContextVar(
    "torchsurf_backend_decisions", default=None
)


class _Using:
    """Makes ``decisions`` the active record while entered; re-entrant (a checkpoint's
    recomputation may run once per backward)."""

    def __init__(self, decisions: _Decisions, replaying: bool) -> None:
        self.decisions, self.replaying = decisions, replaying
        self.tokens: list[contextvars.Token] = []

    def __enter__(self) -> None:
        if self.replaying:
            self.decisions.replaying, self.decisions.position = True, 0
        self.tokens.append(_DECISIONS.set(self.decisions))

    def __exit__(self, *exc: object) -> None:
        _DECISIONS.reset(self.tokens.pop())


def recorded_decisions() -> tuple[contextlib.AbstractContextManager, contextlib.AbstractContextManager]:
    """Two context managers: the first records every path :func:`resolve` picks, the second
    replays them in the same order (as often as it is entered).

    For ``torch.utils.checkpoint(context_fn=...)``: the recomputation in backward must run the
    same kernels as the forward did, although ``"auto"`` may have decided to compile since.
    """
    decisions = _Decisions()
    return _Using(decisions, replaying=False), _Using(decisions, replaying=True)


def resolve(path: str, volume: Tensor, kernel: Kernel | None = None,
            recording: bool = False) -> str:
    """The concrete path for ``volume``: ``"slicing"``, ``"conv3d"`` or ``"compiled"``.

    Args:
        path: one of :data:`PATHS`.
        volume: the data the operator is applied to, ``(B, C, D, H, W)``.
        kernel: the operator, when known: ``"auto"`` then also weighs the eager time already
            spent on it (see the module's docstring).
        recording: autograd records the call. The eager-time rule then never switches a
            small volume to the compiled kernel, whose backward cannot be differentiated
            again (gradcheck, double backward) and would change in the middle of a run.
    """
    check_choice(path, "path", PATHS)
    if path != "auto":
        return path
    decisions = _DECISIONS.get()
    if decisions is not None and decisions.replaying:
        decisions.position += 1
        return decisions.paths[decisions.position - 1]
    chosen = _choose(volume, kernel, recording)
    if decisions is not None:
        decisions.paths.append(chosen)
    return chosen


def _choose(volume: Tensor, kernel: Kernel | None, recording: bool) -> str:
    if torch.compiler.is_compiling() or (kernel is not None and kernel.fused is None):
        return eager_path(volume)
    if volume.numel() >= COMPILE_MIN_VOXELS:
        return "compiled"
    if not recording and kernel is not None and _EAGER_SECONDS.get(
        _ledger_key(kernel, volume), 0.0
    ) >= COMPILE_PAYBACK_SECONDS:
        return "compiled"
    return eager_path(volume)


def run(kernel: Kernel, path: str, volume: Tensor, *args: object) -> Tensor:
    """Apply ``kernel`` to ``args`` on the path chosen for ``volume``.

    Args:
        kernel: the operator.
        path: one of :data:`PATHS`.
        volume: the data, whose size, device and dtype decide ``"auto"``.
        *args: the operator's arguments (the same for every path).

    Returns:
        What the kernel returns; every path gives the same numbers to rounding.
    """
    if torch.compiler.is_compiling() and path in ("auto", *EAGER_PATHS):
        # traced by an outer torch.compile: plain tensor operations, no ledger or record
        # (a context variable and a clock would each break the outer graph)
        concrete = eager_path(volume) if path == "auto" else path
        if concrete == "slicing" and kernel.fused_when_eager:
            return kernel.fused(*kernel.halo(*args))
        return kernel.eager(*args, path=concrete)
    recording = torch.is_grad_enabled() and any(
        isinstance(a, Tensor) and a.requires_grad for a in args
    )
    concrete = resolve(path, volume, kernel, recording)
    if concrete == "compiled":
        if kernel.fused is None:
            raise ValueError(f"path='compiled': {kernel.name} has no compiled form")
        return compiled(kernel.fused, kernel.dynamic)(*kernel.halo(*args))
    if concrete == "slicing" and kernel.fused_when_eager:
        def evaluate() -> Tensor:
            return kernel.fused(*kernel.halo(*args))
    else:
        def evaluate() -> Tensor:
            return kernel.eager(*args, path=concrete)
    if path != "auto" or kernel.fused is None or volume.device.type != "cpu":
        return evaluate()
    start = time.perf_counter()
    result = evaluate()
    key = _ledger_key(kernel, volume)
    _EAGER_SECONDS[key] = _EAGER_SECONDS.get(key, 0.0) + time.perf_counter() - start
    return result


def run_haloed(kernel: Kernel, path: str, volume: Tensor, *haloed_args: object) -> Tensor:
    """Apply ``kernel``'s one-pass form to inputs the caller has already haloed.

    For storage that brings its own halos (:meth:`torchsurf.bricks.BrickLayout.halo`): the
    reference composition of stencils pads at a box's faces, which a brick does not have, so
    every path evaluates ``kernel.fused``, compiled or not as :func:`resolve` decides.

    Args:
        kernel: the operator; it must have a fused form.
        path: one of :data:`PATHS` (``"slicing"`` and ``"conv3d"`` both run it eagerly).
        volume: the data, whose size decides ``"auto"``.
        *haloed_args: the fused form's arguments.
    """
    if kernel.fused is None:
        raise ValueError(f"{kernel.name} has no one-pass form to run on haloed inputs")
    recording = torch.is_grad_enabled() and any(
        isinstance(a, Tensor) and a.requires_grad for a in haloed_args
    )
    if resolve(path, volume, kernel, recording) == "compiled":
        return compiled(kernel.fused, kernel.dynamic)(*haloed_args)
    if path != "auto" or volume.device.type != "cpu":
        return kernel.fused(*haloed_args)
    start = time.perf_counter()
    result = kernel.fused(*haloed_args)
    key = _ledger_key(kernel, volume)
    _EAGER_SECONDS[key] = _EAGER_SECONDS.get(key, 0.0) + time.perf_counter() - start
    return result
