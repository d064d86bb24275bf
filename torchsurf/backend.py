"""Where every operator's stencil arithmetic runs: the one place that chooses, by measurement.

An operator is a :class:`Kernel`: a reference composition of stencils that runs eagerly on any
device (by shifted slices or by conv3d), and optionally a one-pass form over haloed inputs that
``torch.compile`` fuses into a single sweep over memory. :func:`run` picks the path:

- ``"slicing"`` / ``"conv3d"``: eager. Slices are faster on CPU (conv3d with few channels falls
  back to im2col there, 2-5x slower), conv3d elsewhere; ``"auto"`` takes the faster one for the
  device when it stays eager.
- ``"compiled"``: the one-pass form, compiled once per shape (docs/benchmarks.md: the octant
  Laplace–Beltrami at 128^3 runs at 1.5x the memory-traffic limit, 7x faster than eager).
- ``"auto"``: compiled when it pays, by measurement. Compiling costs seconds for each kernel
  and shape, and the first compile in a process more (the compiler's start-up:
  docs/benchmarks.md, "Compile cost"), so on the CPU ``"auto"`` runs a kernel eagerly until
  the eager time measured on that kernel and shape in this process reaches
  :data:`COMPILE_PAYBACK_SECONDS` times the kernel's :attr:`Kernel.compile_weight`, about what
  compiling it costs, and compiles it then: a call
  with less eager work than that never waits for a compiler, a flow run or a training loop is
  compiled after seconds of eager work, and no run spends more than about twice what the
  better choice in hindsight would have. Inside a flow, which plans its steps
  (:func:`planned`), it compiles earlier, as soon as the eager time its remaining steps would
  spend in the kernel reaches that payback. It then times the compiled kernel too, and goes back
  to eager for good if its fastest call is slower than the fastest eager one; a call autograd
  records is timed forward and backward together, so a compiled backward slower than eager's
  keeps the kernel eager. While autograd
  records the call, volumes below :data:`COMPILE_MIN_VOXELS` stay eager (gradcheck and double
  backward on small grids). Volumes of :data:`COMPILE_AT_ONCE_VOXELS` voxels are compiled on
  their first call, and off the CPU (where nothing is timed) those of
  :data:`COMPILE_MIN_VOXELS`. A kernel compiled for one batch size of two or more serves the
  others (a dynamic batch size). :func:`warm_up` compiles at once, for a warm-up call. If a
  compile fails (inductor needs a working C++ compiler), ``"auto"`` runs that call's one-pass
  form eagerly, warns once, and stays eager for every kernel in the process.

What ``"auto"`` measures and compiles is per *variant*: what one compiled graph is specialised
on (the kernel, its arguments' shapes unless the kernel is dynamic, dtype, device, its flags
and other non-tensor arguments, and whether autograd records the call and for which inputs).
Each variant pays back its own compile, so that a flag or a grad mode seen once in a run of
another never brings a compile of its own. A call autograd does not record runs the compiled
kernel without grad on detached inputs: one inference variant, whatever the grad mode and the
inputs' ``requires_grad``.

The environment variable ``TORCHSURF_COMPILE`` (read at import, kept in :data:`COMPILE`) sets
what ``"auto"`` does: ``auto`` (default) as above, ``never`` (always eager, for short scripts,
test suites and debugging; ``path="compiled"`` and :func:`warm_up` still compile), ``always``
(compile every kernel on its first call, as inside :func:`warm_up`).

Inside a function that ``torch.compile`` is tracing every operator stays eager, so that the
outer compiler sees plain tensor operations. Compiled kernels have no double backward: pass an
eager ``path`` to differentiate twice.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import math
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import torch
from torch import Tensor

from ._checks import check_choice
from ._native import carries_tangents
from ._stack import caller_stacklevel

__all__ = [
    "COMPARED_CALLS",
    "COMPILE",
    "COMPILE_AT_ONCE_VOXELS",
    "COMPILE_MIN_VOXELS",
    "COMPILE_MODES",
    "COMPILE_PAYBACK_SECONDS",
    "EAGER_PATHS",
    "Kernel",
    "PATHS",
    "RECOMPILE_LIMIT",
    "compiled",
    "eager_path",
    "part_of_recorded",
    "planned",
    "recorded_paths",
    "resolve",
    "run",
    "run_haloed",
    "run_on_path",
    "step_taken",
    "warm_up",
]

PATHS = ("auto", "slicing", "conv3d", "compiled")
"""Values of every operator's ``path`` argument."""

EAGER_PATHS = ("slicing", "conv3d")

COMPILE_MODES = ("auto", "never", "always")
"""Values of :data:`COMPILE` (and of the environment variable ``TORCHSURF_COMPILE``)."""


def _compile_mode_from_environment() -> str:
    value = os.environ.get("TORCHSURF_COMPILE", "auto").strip().lower() or "auto"
    if value not in COMPILE_MODES:
        raise ValueError(
            f"TORCHSURF_COMPILE must be one of {COMPILE_MODES}, got {value!r}"
        )
    return value


COMPILE = _compile_mode_from_environment()
"""What ``path="auto"`` does in this process: ``"auto"`` compiles a variant once its eager
time pays back, ``"never"`` stays eager, ``"always"`` compiles on the first call. Read from
``TORCHSURF_COMPILE`` at import; assign another of :data:`COMPILE_MODES` to change it."""

COMPILE_MIN_VOXELS = 64**3
"""Smallest volume (batch x channels x voxels) that ``"auto"`` compiles while autograd records
the call (a compiled backward cannot be differentiated again, as gradcheck and double backward
on small grids do); off the CPU, the volumes it compiles at once."""

COMPILE_AT_ONCE_VOXELS = 2**23
"""Volumes at least this large (``203^3``; batch x channels x voxels) are compiled on their
first call: one eager application of a Laplace–Beltrami costs about 0.3 s there (77 ms at
``128^3``, docs/benchmarks.md), so a flow spends a compile's time in eager work within its
first call; the brick layout's figures at ``512^3`` (docs/bricks.md) were measured so."""

COMPILE_PAYBACK_SECONDS = 10.0
"""Eager seconds measured on one kernel and shape (and grad mode) after which ``"auto"``
compiles it: about what compiling it costs, the compiler's start-up included, with a warm
inductor cache on this machine class (docs/benchmarks.md, "Compile cost"; an empty cache costs
2-4x more), so that ``"auto"`` never spends more than about twice what the better choice in
hindsight would have."""

COMPARED_CALLS = 3
"""Compiled calls of a kernel and shape that ``"auto"`` times (besides the one that compiles)
before comparing the fastest with the fastest eager call."""

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
        eager_fused: ``fused``'s numbers arranged for eager evaluation (fewer full-volume
            temporaries), run instead of ``fused`` whenever the one-pass form runs eagerly.
        trusted_indices: ``fused``'s indirect loads read index tensors the library built, in
            bounds by construction: compiled without inductor's check of every such load
            (the tricubic gather of a 37^3 sphere's band: 1.5 ms against 2.9 ms).
        breaks_graph: ``fused`` shapes its own compiled graphs with
            ``torch._dynamo.graph_break()``: traced by an outer ``torch.compile``, the eager
            arrangement (:meth:`fused_eagerly`) runs instead, which has no break.
        compile_weight: what compiling one variant of ``fused`` costs, in units of a typical
            kernel's compile: ``"auto"`` compiles a variant once its eager time reaches
            ``compile_weight * COMPILE_PAYBACK_SECONDS`` (:data:`COMPILE_PAYBACK_SECONDS`).
        exponents: ``exponents(haloed_args)``, the positions of the numbers ``fused`` raises
            to a power: they reach the compiled kernel as numbers, not 0-d tensors
            (:func:`_run_compiled`), so that inductor writes ``s ** -1.0`` as a reciprocal
            and ``s ** 0.0`` as 1 (as a tensor, a general power: the harmonic-map rate 1.8x
            slower); a graph per exponent, of which a flow has one or two.
        realize_reads_threshold: inductor's ``realize_reads_threshold`` for ``fused``,
            :data:`REALIZE_READS_THRESHOLD` unless given: how many reads of an intermediate
            it recomputes before writing it to memory once (a kernel whose fluxes are read
            at many offsets may gain from a higher one; measure).
    """

    name: str
    eager: Callable[..., Tensor]
    fused: Callable[..., Tensor] | None = None
    halo: Callable[..., tuple] | None = None
    fused_when_eager: bool = False
    dynamic: bool = False
    eager_fused: Callable[..., Tensor] | None = None
    trusted_indices: bool = False
    breaks_graph: bool = False
    compile_weight: float = 1.0
    exponents: Callable[[tuple], tuple[int, ...]] | None = None
    realize_reads_threshold: int | None = None

    def __post_init__(self) -> None:
        if not (isinstance(self.compile_weight, (int, float)) and self.compile_weight > 0
                and math.isfinite(self.compile_weight)):
            raise ValueError(f"Kernel {self.name!r}: compile_weight must be a positive finite "
                             f"number, got {self.compile_weight!r}")

    def fused_eagerly(self, *haloed_args: object) -> Tensor:
        """The one-pass form evaluated eagerly (:attr:`eager_fused` if given)."""
        return (self.eager_fused or self.fused)(*haloed_args)


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


def _compile_in_process_after_fork() -> None:
    """In a process forked after torchsurf was imported, inductor compiles in the process
    itself (``compile_threads = 1``): its pool of compile workers does not survive a fork, and a
    child's first compile of a kernel at a new shape waited on it forever (an audit: a
    ``multiprocessing`` pool of fork children after ``"auto"`` compiled in the parent; plain
    ``torch.compile`` hangs the same way). The kernels the parent compiled run as they were."""
    try:
        import torch._inductor.config as inductor_config
    except ImportError:
        return
    inductor_config.compile_threads = 1


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_compile_in_process_after_fork)


@functools.cache
def compiled(function: Callable[..., Tensor], dynamic: bool = False,
             trusted_indices: bool = False, realize_reads_threshold: int | None = None
             ) -> Callable[..., Tensor]:
    """``function`` compiled once per process (shapes specialised unless ``dynamic``; without
    bounds checks on indirect loads when ``trusted_indices``, :attr:`Kernel.trusted_indices`;
    inductor's ``realize_reads_threshold`` :data:`REALIZE_READS_THRESHOLD` unless given)."""
    _raise_recompile_limit()
    options: dict[str, object] = {
        "realize_reads_threshold": (REALIZE_READS_THRESHOLD if realize_reads_threshold is None
                                    else realize_reads_threshold)}
    if trusted_indices:
        options["assert_indirect_indexing"] = False
    return torch.compile(function, dynamic=dynamic, options=options)


REALIZE_READS_THRESHOLD = 7
"""Inductor's ``realize_reads_threshold`` for the compiled kernels: its default 4 plus the up
to three numbers (spacing, contrast, eps) a kernel reads as 0-d tensors (:func:`_run_compiled`).
Those reads had tipped the projected gradients of total variation over the default, so they
were written to and read back from memory rather than recomputed where used: 1.7x the time at
128^3 (30 against 17 ms; docs/benchmarks.md)."""


def _tensors(values: tuple | list) -> Iterator[Tensor]:
    """The tensors among ``values``, also inside tuples and lists (a ``haloed`` pair)."""
    for value in values:
        if isinstance(value, Tensor):
            yield value
        elif isinstance(value, (tuple, list)):
            yield from _tensors(value)


def _describe(value: object, batch: int, dynamic: bool, recording: bool) -> object:
    """What a compiled graph of a kernel is specialised on in one argument ``value``.

    A tensor: its dtype, whether autograd records it (only while the call is recorded: other
    calls run the compiled kernel on detached inputs), and its shape, with the batch size
    ``batch`` of two or more generalised (one variant serves them all) and every size left out
    for a ``dynamic`` kernel. Floats are left out (they reach the compiled kernel as 0-d
    tensors, :func:`_run_compiled`), and integers for a dynamic kernel (symbolic); other
    values (flags, scheme names, functions) are kept as they are.
    """
    if isinstance(value, Tensor):
        grad = recording and value.requires_grad
        if dynamic:
            return ("tensor", value.dim(), value.dtype, grad)
        shape = tuple(value.shape)
        if batch > 1 and shape and shape[0] == batch:
            shape = ("batch", *shape[1:])
        return ("tensor", shape, value.dtype, grad)
    if isinstance(value, (tuple, list)):
        return tuple(_describe(item, batch, dynamic, recording) for item in value)
    if type(value) is float or (dynamic and isinstance(value, int)
                                 and not isinstance(value, bool)):
        return type(value).__name__
    try:
        hash(value)
    except TypeError:
        return (type(value).__name__, id(value))
    return value


def _variant(kernel: Kernel, volume: Tensor, args: tuple, recording: bool) -> tuple:
    """The compiled variant a call of ``kernel`` on ``args`` runs (or would run): the key of
    :data:`_TIMINGS`. Calls with the same key share one compiled graph, and so one payback."""
    batch = volume.shape[0]
    kept = kernel.exponents(args) if kernel.exponents is not None else ()
    return (kernel.name, volume.device.type, recording, batch > 1,
            tuple(arg if i in kept and type(arg) is float
                  else _describe(arg, batch, kernel.dynamic, recording)
                  for i, arg in enumerate(args)))


def _shapes(args: tuple) -> tuple:
    """The exact shapes of the tensors among ``args``: calls comparable in time."""
    return tuple(tuple(t.shape) for t in _tensors(args))


@dataclass
class _Timings:
    """Wall times of one compiled variant (:func:`_variant`) under ``"auto"`` in this process.

    ``eager_seconds`` sums every eager call of the variant, forward and backward (what pays for
    compiling it); the fastest eager and compiled calls are kept per exact shape (a call autograd
    records counts its forward and its backward together), and the compiled kernel is
    :attr:`slower` once, at some shape, its fastest of more than :data:`COMPARED_CALLS` calls
    (the first one, which compiles, left out) is slower than the fastest eager call there.
    """

    eager_seconds: float = 0.0
    compiled: bool = False
    slower: bool = False
    compared: bool = False
    eager_fastest: dict[tuple, float] = field(default_factory=dict)
    compiled_calls: dict[tuple, int] = field(default_factory=dict)
    compiled_fastest: dict[tuple, float] = field(default_factory=dict)

    def record(self, path: str, shapes: tuple, seconds: float) -> None:
        """Add one call of ``seconds`` on ``path`` with tensors of ``shapes``."""
        self.charge(path, seconds)
        self.compare(path, shapes, seconds)

    def charge(self, path: str, seconds: float) -> None:
        """Add ``seconds`` of work on ``path`` to what pays for compiling (eager work only)."""
        if path != "compiled":
            self.eager_seconds += seconds

    def compare(self, path: str, shapes: tuple, seconds: float) -> None:
        """Weigh one whole call of ``seconds`` on ``path`` (forward, and backward when
        autograd recorded it) against the other path's fastest at ``shapes``."""
        if path != "compiled":
            self.eager_fastest[shapes] = min(self.eager_fastest.get(shapes, math.inf), seconds)
            return
        self.compiled = True
        calls = self.compiled_calls.get(shapes, 0)
        self.compiled_calls[shapes] = calls + 1
        if calls == 0:  # the first compiled call at a shape may compile
            return
        fastest = min(self.compiled_fastest.get(shapes, math.inf), seconds)
        self.compiled_fastest[shapes] = fastest
        if calls >= COMPARED_CALLS and shapes in self.eager_fastest:
            self.compared = True
            self.slower = self.slower or fastest > self.eager_fastest[shapes]

    @property
    def compiled_slower(self) -> bool:
        """The compiled kernel was measured slower than eager: ``"auto"`` stays eager."""
        return self.slower

    @property
    def pending(self) -> bool:
        """``"auto"`` has not decided on this variant yet: still eager, or compiled and not
        yet compared with eager."""
        return not self.slower and not self.compared


_TIMINGS: dict[tuple, _Timings] = {}
"""What :func:`run` measured per compiled variant (:func:`_variant`) in this process, at most
:data:`TIMED_VARIANTS` of them (the one run least recently dropped first), in the order they
last ran."""

TIMED_VARIANTS = 1024
"""Most variants :data:`_TIMINGS` holds. A diffusivity made anew for each call (a lambda in a
loop) is a new variant each time: the ledger grew by one entry a call, and as the lambdas'
reused addresses hash alike, each call took longer than the one before (1.3 to 12.6 ms at 16^3
over 12,000 calls; an audit, 2026-12-07)."""


_TIMINGS_LOCK = threading.Lock()
"""Held while :func:`_timings` reorders the ledger (never while tracing: not reached then)."""


def _timings(variant: tuple) -> _Timings:
    """The ledger's entry for ``variant``, moved to the end (the most recently run), or added
    there if new (the least recently run dropped past :data:`TIMED_VARIANTS`): a kernel run at
    every call keeps its measured eager time while lambdas made anew come and go."""
    with _TIMINGS_LOCK:  # threads calling kernels at once had both dropped one entry: KeyError
        timings = _TIMINGS.pop(variant, None)
        if timings is None:
            while len(_TIMINGS) >= TIMED_VARIANTS:
                del _TIMINGS[next(iter(_TIMINGS))]
            timings = _Timings()
        _TIMINGS[variant] = timings
        return timings


_COMPILE_FAILURE: list[str] = []
"""Why a compile chosen by ``"auto"`` failed in this process (empty while none has):
``"auto"`` then stays eager for every kernel (:func:`_compiled_or_eager`)."""


def _compiled_or_eager(kernel: Kernel, volume: Tensor, haloed_args: tuple, recording: bool,
                       eager: Callable[[], Tensor]) -> Tensor:
    """The compiled kernel, chosen by ``"auto"``; if compiling it fails (no working C++
    compiler, an inductor error), ``eager()`` instead, and ``"auto"`` stays eager from then
    on in this process, with one ``RuntimeWarning``. An error that ``eager()`` raises too is the
    caller's own, and is raised as eager raises it."""
    try:
        return _run_compiled(kernel, volume, haloed_args, recording)
    except Exception as error:  # eager() raises the caller's own errors again
        result = eager()
        first_line = (str(error).strip().splitlines() or [""])[0]
        reason = f"{type(error).__name__}: {first_line[:300]}"
        if not _COMPILE_FAILURE:
            warnings.warn(
                f"torchsurf: compiling {kernel.name} failed ({reason}); path='auto' runs every "
                "operator eagerly from now on in this process (the same numbers, slower). Set "
                "TORCHSURF_COMPILE=never to skip the attempt, or give inductor a working C++ "
                "compiler", RuntimeWarning, stacklevel=caller_stacklevel())
        _COMPILE_FAILURE.append(reason)
        return result


def _channels_last(value: object) -> bool:
    """A 5-D tensor laid out channels-last (``torch.channels_last_3d``), not contiguous."""
    return (isinstance(value, Tensor) and value.dim() == 5 and not value.is_contiguous()
            and value.is_contiguous(memory_format=torch.channels_last_3d))


def _run_compiled(kernel: Kernel, volume: Tensor, args: tuple, recording: bool) -> Tensor:
    """``kernel.fused(*args)`` compiled.

    For a batch of two or more, the size of every tensor with that batch is dynamic (one
    variant serves every such batch size, as fast as the specialised one: docs/benchmarks.md,
    "Compile cost"), so that a new batch size, such as an epoch's last batch, neither
    recompiles nor waits for its own eager time to pay back. A call autograd does not record
    runs without grad on detached inputs: the same inference graph whatever the grad mode and
    the inputs' ``requires_grad`` (dynamo guards on both).
    """
    if carries_tangents(*_tensors(args)):
        # compiled, forward-mode tangents were dropped (path="compiled": operators' tangents
        # 0, flows' 0.5 off); the same one-pass form, eagerly, carries them
        return kernel.fused_eagerly(*args)
    if not recording:  # before marking: a detached tensor is a new object, unmarked
        args = tuple(arg.detach() if isinstance(arg, Tensor) else arg for arg in args)
    # dynamo guards on the memory format: channels-last data compiled a kernel of its own
    args = tuple(arg.contiguous() if _channels_last(arg) else arg for arg in args)
    # numbers (a grid's spacing, a contrast) as 0-d tensors: dynamo guards on a float's value,
    # and every mesh of its own spacing, every contrast, had compiled a graph of its own. In the
    # data's dtype, as eager arithmetic reads a number: float64 ones made inductor compute
    # float32 kernels in float64 (total variation 1.7x, directional diffusion 1.4x slower).
    number = volume.dtype if volume.is_floating_point() else torch.float64
    kept = kernel.exponents(args) if kernel.exponents is not None else ()
    args = tuple(torch.tensor(arg, dtype=number) if type(arg) is float and i not in kept else arg
                 for i, arg in enumerate(args))
    batch = volume.shape[0]
    if batch > 1:
        for arg in args:
            if isinstance(arg, Tensor) and arg.dim() > 0 and arg.shape[0] == batch:
                torch._dynamo.maybe_mark_dynamic(arg, 0)
    function = compiled(kernel.fused, kernel.dynamic, kernel.trusted_indices,
                        kernel.realize_reads_threshold)
    if recording:
        return function(*args)
    with torch.no_grad():
        return function(*args)


_AT_ONCE: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "torchsurf_backend_compile_at_once", default=False
)


@contextlib.contextmanager
def warm_up() -> Iterator[None]:
    """Inside, ``"auto"`` compiles every kernel it runs at once (where it has a compiled form
    not measured slower than eager), instead of after :data:`COMPILE_PAYBACK_SECONDS` of
    eager work.

    For a warm-up call: one forward and backward of a model at the shapes, dtype and grad
    modes it will run with compiles the kernels it will need, so that the calls that follow
    run compiled from the start (docs/learning.md, "Warm-up and torch.compile")::

        with torchsurf.backend.warm_up():
            model(u, surface).sum().backward()
    """
    token = _AT_ONCE.set(True)
    try:
        yield
    finally:
        _AT_ONCE.reset(token)


@dataclass
class _Plan:
    """Steps a caller has planned (:func:`planned`) and taken, and per variant the eager
    seconds and steps taken when the plan first ran it."""

    total: int
    done: int = 0
    seen: dict[tuple, tuple[float, int]] = field(default_factory=dict)

    def remaining_eager_seconds(self, variant: tuple, eager_seconds: float) -> float:
        """The eager seconds ``variant`` would take over the plan's remaining steps, at the
        rate measured since the plan first ran it (0 before one whole step measured it)."""
        start_seconds, start_step = self.seen.setdefault(variant, (eager_seconds, self.done))
        steps = self.done - start_step
        if steps < 1:
            return 0.0
        return (eager_seconds - start_seconds) / steps * (self.total - self.done)


_PLAN: contextvars.ContextVar[_Plan | None] = contextvars.ContextVar(
    "torchsurf_backend_plan", default=None
)


@contextlib.contextmanager
def planned(steps: int) -> Iterator[None]:
    """Inside, the caller takes ``steps`` steps that each run the same kernels, and calls
    :func:`step_taken` after each: ``"auto"`` then also compiles a variant as soon as the eager
    time the remaining steps would spend in it, at the rate measured so far, reaches its
    payback (:data:`COMPILE_PAYBACK_SECONDS` times :attr:`Kernel.compile_weight`), instead of
    after that much eager work (a long flow compiles after its first step, not after seconds
    of eager work). The flows' integrators plan their steps."""
    token = _PLAN.set(_Plan(int(steps)))
    try:
        yield
    finally:
        _PLAN.reset(token)


def step_taken() -> None:
    """One of the steps of the innermost :func:`planned` is done (nothing outside one, or
    while ``torch.compile`` traces the caller)."""
    if torch.compiler.is_compiling():
        return
    plan = _PLAN.get()
    if plan is not None:
        plan.done += 1


_RECORDED: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "torchsurf_backend_recorded", default=False
)


def part_of_recorded(function: Callable) -> Callable:
    """Decorates a custom ``autograd.Function``'s ``backward``, inside which autograd records
    nothing: its calls are taken for part of a recorded computation, and ``"auto"`` keeps
    volumes below :data:`COMPILE_MIN_VOXELS` eager there too, so that a gradcheck's analytical
    Jacobian never changes kernel halfway (its two backward passes must agree exactly: a
    compile in between failed it as "not reentrant"). Not for ``forward``, which also runs
    where nothing is recorded (``no_grad`` flows, whose small volumes must still compile once
    they pay: an implicit flow at 48^3 ran 3.7 times as long), and whose rounding a
    gradcheck's finite differences tolerate. Nothing while ``torch.compile`` traces (every
    kernel then runs its eager form)."""

    @functools.wraps(function)
    def recorded(*args: object, **kwargs: object) -> object:
        if torch.compiler.is_compiling():
            return function(*args, **kwargs)
        token = _RECORDED.set(True)
        try:
            return function(*args, **kwargs)
        finally:
            _RECORDED.reset(token)

    return recorded


_PICKS: contextvars.ContextVar[list[str] | None] = contextvars.ContextVar(
    "torchsurf_backend_picks", default=None
)


@contextlib.contextmanager
def recorded_paths() -> Iterator[list[str]]:
    """Inside, every path ``"auto"`` picks is appended to the list this yields, in order (for
    benchmarks and diagnostics: which kernels ran compiled)::

        with torchsurf.backend.recorded_paths() as picks:
            flow(u, surface)
        collections.Counter(picks)  # e.g. {"compiled": 40, "slicing": 8}
    """
    picks: list[str] = []
    token = _PICKS.set(picks)
    try:
        yield picks
    finally:
        _PICKS.reset(token)


def resolve(path: str, volume: Tensor, kernel: Kernel | None = None,
            recording: bool = False, args: tuple | None = None) -> str:
    """The concrete path for ``volume``: ``"slicing"``, ``"conv3d"`` or ``"compiled"``.

    Args:
        path: one of :data:`PATHS`.
        volume: the data the operator is applied to, ``(B, C, D, H, W)``.
        kernel: the operator: ``"auto"`` weighs the times measured on it (see the module's
            docstring); without it, or without a compiled form, ``"auto"`` stays eager.
        recording: autograd records the call. ``"auto"`` then never switches a volume
            smaller than :data:`COMPILE_MIN_VOXELS` to the compiled kernel, whose backward
            cannot be differentiated again (gradcheck, double backward).
        args: the kernel's arguments, which name its compiled variant (default: ``volume``
            alone).
    """
    return _resolve(path, volume, kernel, recording, (volume,) if args is None else args)[0]


def _resolve(path: str, volume: Tensor, kernel: Kernel | None, recording: bool, args: tuple
             ) -> tuple[str, tuple | None]:
    """:func:`resolve`, and the variant whose ledger times the call (``None``: not timed)."""
    check_choice(path, "path", PATHS)
    if path != "auto":
        return path, None
    if not torch.compiler.is_compiling() and carries_tangents(*_tensors(args)):
        # a compiled kernel drops forward-mode tangents (the flows' tangents were 0.1-1.0
        # off once "auto" had compiled their stencils): such data stay eager
        chosen, variant = eager_path(volume), None
    else:
        timed = (kernel is not None and kernel.fused is not None
                 and volume.device.type == "cpu" and not torch.compiler.is_compiling())
        variant = _variant(kernel, volume, args, recording) if timed else None
        chosen = _choose(volume, kernel, recording, variant)
    picks = _PICKS.get()
    if picks is not None:
        picks.append(chosen)
    return chosen, variant


def _choose(volume: Tensor, kernel: Kernel | None, recording: bool, variant: tuple | None
            ) -> str:
    if COMPILE not in COMPILE_MODES:  # assigned in the program, not read from the environment
        raise ValueError(f"torchsurf.backend.COMPILE must be one of {COMPILE_MODES}, got "
                         f"{COMPILE!r}")
    eager = eager_path(volume)
    if torch.compiler.is_compiling() or kernel is None or kernel.fused is None:
        return eager
    large = volume.numel() >= COMPILE_MIN_VOXELS
    if (recording or _RECORDED.get()) and not large:
        return eager
    at_once = _AT_ONCE.get() or COMPILE == "always"
    if (COMPILE == "never" and not _AT_ONCE.get()) or _COMPILE_FAILURE:
        return eager
    if volume.device.type != "cpu":
        return "compiled" if large or at_once else eager
    timings = _TIMINGS.get(variant) or _Timings()
    if timings.slower:
        return eager
    payback = COMPILE_PAYBACK_SECONDS * kernel.compile_weight
    plan = _PLAN.get()
    if (at_once or volume.numel() >= COMPILE_AT_ONCE_VOXELS or timings.compiled
            or timings.eager_seconds >= payback
            or (plan is not None and variant is not None
                and plan.remaining_eager_seconds(variant, timings.eager_seconds) >= payback)):
        return "compiled"
    return eager


def _recording(args: tuple) -> bool:
    return torch.is_grad_enabled() and any(t.requires_grad for t in _tensors(args))


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
    return run_on_path(kernel, path, volume, *args)[0]


def run_on_path(kernel: Kernel, path: str, volume: Tensor, *args: object
                ) -> tuple[Tensor, str]:
    """:func:`run`, and the concrete path it took (``"slicing"``, ``"conv3d"`` or
    ``"compiled"``): for kernels whose forms differ in what they leave to the caller."""
    if torch.compiler.is_compiling():
        # traced by an outer torch.compile: plain tensor operations, no ledger, record or
        # compile of our own (a context variable, a clock and marking a dimension dynamic
        # would each break the outer graph or fail in it); "compiled" traces the one-pass form
        concrete = eager_path(volume) if path == "auto" else path
        if concrete == "compiled" and kernel.fused is None:
            raise ValueError(f"path='compiled': {kernel.name} has no compiled form")
        if concrete == "compiled" or (concrete == "slicing" and kernel.fused_when_eager):
            haloed = kernel.halo(*args)
            form = kernel.fused_eagerly if kernel.breaks_graph else kernel.fused
            return form(*haloed), concrete
        return kernel.eager(*args, path=concrete), concrete
    recording = _recording(args)
    concrete, variant = _resolve(path, volume, kernel, recording, args)
    if concrete == "compiled" and kernel.fused is None:
        raise ValueError(f"path='compiled': {kernel.name} has no compiled form")

    def evaluate(args: tuple) -> Tensor:
        if concrete == "compiled" and path == "auto":
            # the one-pass form uncompiled if compiling fails: what the caller of a
            # "compiled" path expects (some kernels' forms return different things)
            haloed = kernel.halo(*args)
            return _compiled_or_eager(kernel, volume, haloed, recording,
                                      lambda: kernel.fused_eagerly(*haloed))
        if concrete == "compiled":
            return _run_compiled(kernel, volume, kernel.halo(*args), recording)
        if concrete == "slicing" and kernel.fused_when_eager:
            return kernel.fused_eagerly(*kernel.halo(*args))
        return kernel.eager(*args, path=concrete)

    return _timed(variant, concrete, volume, recording, args, evaluate), concrete


def _timed(variant: tuple | None, concrete: str, volume: Tensor, recording: bool, args: tuple,
           evaluate: Callable[[tuple], Tensor]) -> Tensor:
    """``evaluate(args)``, its wall time recorded under ``variant`` (``"auto"`` on the CPU).

    While ``"auto"`` has not decided a variant that autograd records (and could compile), the
    call's backward is timed too, and the call is weighed by forward and backward together: a
    compiled kernel whose backward is slower than eager's loses even when its forward wins.
    """
    if variant is None:
        return evaluate(args)
    timings = _timings(variant)
    shapes = _shapes(args)
    watched = (recording and timings.pending and COMPILE != "never"
               and volume.numel() >= COMPILE_MIN_VOXELS)
    if not watched:
        start = time.perf_counter()
        result = evaluate(args)
        timings.record(concrete, shapes, time.perf_counter() - start)
        return result
    clock = _BackwardClock()
    args = clock.watch_inputs(args)
    start = time.perf_counter()
    result = evaluate(args)
    forward = time.perf_counter() - start
    timings.charge(concrete, forward)

    def backward_done(backward: float) -> None:
        timings.charge(concrete, backward)
        timings.compare(concrete, shapes, forward + backward)

    return clock.watch_output(result, backward_done)


class _BackwardClock:
    """Times the backward of what runs between :meth:`watch_inputs` and :meth:`watch_output`.

    Identity nodes on the inputs and on the output: autograd runs a graph's nodes latest-made
    first, so on the CPU the output's node starts the call's backward and the inputs' node,
    reached once every gradient of the call's own nodes is formed, ends it.
    """

    def __init__(self) -> None:
        self.started: float | None = None
        self.done: Callable[[float], None] | None = None

    def watch_inputs(self, args: tuple) -> tuple:
        positions = [i for i, arg in enumerate(args)
                     if isinstance(arg, Tensor) and arg.requires_grad]
        watched = _ClockEnd.apply(self, *(args[i] for i in positions))
        if len(positions) == 1:
            watched = (watched,)
        args = list(args)
        for i, tensor in zip(positions, watched, strict=True):
            args[i] = tensor
        return tuple(args)

    def watch_output(self, result: Tensor, done: Callable[[float], None]) -> Tensor:
        if not isinstance(result, Tensor) or not result.requires_grad:
            return result
        self.done = done
        return _ClockStart.apply(self, result)

    def start(self) -> None:
        self.started = time.perf_counter()

    def stop(self) -> None:
        if self.started is not None and self.done is not None:
            self.done(time.perf_counter() - self.started)
        self.started = None


class _ClockStart(torch.autograd.Function):
    @staticmethod
    def forward(ctx, clock: _BackwardClock, result: Tensor) -> Tensor:
        ctx.clock = clock
        return result.view_as(result)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple:
        ctx.clock.start()
        return None, grad


class _ClockEnd(torch.autograd.Function):
    @staticmethod
    def forward(ctx, clock: _BackwardClock, *inputs: Tensor) -> Tensor | tuple[Tensor, ...]:
        ctx.clock = clock
        ctx.set_materialize_grads(False)
        views = tuple(tensor.view_as(tensor) for tensor in inputs)
        return views[0] if len(views) == 1 else views

    @staticmethod
    def backward(ctx, *grads: Tensor | None) -> tuple:
        ctx.clock.stop()
        return (None, *grads)


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
    if torch.compiler.is_compiling():  # traced by an outer torch.compile, as in run_on_path
        check_choice(path, "path", PATHS)
        return (kernel.fused_eagerly if kernel.breaks_graph else kernel.fused)(*haloed_args)
    recording = _recording(haloed_args)
    concrete, variant = _resolve(path, volume, kernel, recording, haloed_args)
    if concrete == "compiled" and path == "auto":
        return _timed(variant, concrete, volume, recording, haloed_args,
                      lambda args: _compiled_or_eager(kernel, volume, args, recording,
                                                      lambda: kernel.fused_eagerly(*args)))
    if concrete == "compiled":
        return _timed(variant, concrete, volume, recording, haloed_args,
                      lambda args: _run_compiled(kernel, volume, args, recording))
    return _timed(variant, concrete, volume, recording, haloed_args,
                  lambda args: kernel.fused_eagerly(*args))
