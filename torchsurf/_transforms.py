"""Which derivatives an entry point can take beyond reverse-mode autograd, and a clear refusal
of the others.

Every operator runs under ``torch.func.grad``, ``vmap`` and ``jvp`` and forward-mode AD
(:mod:`torch.autograd.forward_ad`). Flows, extensions and the learned layers read host values
(step counts from bounds, masks through numpy) and call C kernels on raw memory, which
``torch.func.grad`` and ``vmap`` wrap every tensor against: they refuse both, naming what to use
instead (``torch.autograd.grad`` or ``loss.backward()``, and a batch dimension). Forward-mode AD
runs through the flows whose steps are plain tensor operations (Euler, Heun, RKC) and is
refused where a step is an autograd ``Function`` without a forward derivative (implicit solves,
Chebyshev expansions, recomputed torchdiffeq pieces, the learned layers) or an operation
PyTorch has none for (``grid_sample`` in a dense volume's closest-point extension); ``phi``
itself under a transform is refused by all of them (a dual ``phi`` of
:mod:`torch.autograd.forward_ad` runs). A surface forms what it keeps beneath any transform
(:func:`outside_transforms`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from typing import TypeVar

import torch
from torch import Tensor
from torch.autograd import forward_ad

_GUIDE = "docs/learning.md, 'Derivatives'"


def active_transforms() -> set[str]:
    """Names (``"Grad"``, ``"Vmap"``, ``"Jvp"``, ...) of the ``torch.func`` transforms the
    call runs under; empty outside any (or on a PyTorch without the query)."""
    functorch = getattr(torch._C, "_functorch", None)
    stack = getattr(functorch, "get_interpreter_stack", None)
    if stack is None:
        return set()
    return {interpreter.key().name for interpreter in (stack() or ())}


def saving_through_hooks() -> bool:
    """Whether autograd saves tensors through default hooks here: a non-reentrant
    ``torch.utils.checkpoint`` region (whose recomputation must save what its forward saved,
    so nothing in ``phi``'s graph formed there may be kept for later calls), or
    ``torch.autograd.graph.save_on_cpu``. ``False`` while ``torch.compile`` traces and on a
    PyTorch without the query."""
    if torch.compiler.is_compiling():
        return False
    top = getattr(torch._C._autograd, "_top_saved_tensors_default_hooks", None)
    return top is not None and top(False) is not None


def checkpoint_phase() -> str | None:
    """Where autograd saves tensors through ``torch.utils.checkpoint``'s hooks here:
    ``"forward"`` (a non-reentrant region's forward), ``"recomputation"`` (its recomputation
    in backward), or ``None`` (neither, while ``torch.compile`` traces, or on a PyTorch
    without the query)."""
    if torch.compiler.is_compiling():
        return None
    top = getattr(torch._C._autograd, "_top_saved_tensors_default_hooks", None)
    hooks = None if top is None else top(False)
    if hooks is None or getattr(hooks[0], "__module__", None) != "torch.utils.checkpoint":
        return None
    return ("recomputation" if "_recomputation_hook" in getattr(hooks[0], "__qualname__", "")
            else "forward")


_Forward = TypeVar("_Forward", bound=Callable)


def saved_plainly_in_checkpoints(forward: _Forward) -> _Forward:
    """``forward`` saving its tensors for backward itself inside a ``torch.utils.checkpoint``
    region (non-reentrant), as when called outside one.

    A flow keeps only each recomputed segment's input (:mod:`torchsurf.flows._recompute`),
    and the backward of each segment is a separate ``autograd.grad`` whose graph reaches the
    tensors the flow formed from ``phi`` (the re-extension's weights, the geometry). Saved
    through the region's hooks, each of those graph runs asked the region for them again,
    and the region recomputed its whole forward each time: once a segment (a Perona–Malik
    flow at 14^3 with ``phi`` learned: backward 5.5 s against 1.2 s called plainly). Only
    where ``phi`` requires grad (else no segment reaches back into the region, and the
    region's savings stand). The saved tensors are detached when packed (autograd restores
    their graph when it unpacks them); the tensor itself would hold an output's own node (a
    reference cycle the collector cannot see). In the region's recomputation the call runs
    without a graph: its forward kept its own, and the region's later operations need only
    its value (a graph built there too doubled the peak of backward).
    """

    @functools.wraps(forward)
    def saving_plainly(*args: object, **kwargs: object) -> object:
        phase = checkpoint_phase() if torch.is_grad_enabled() else None
        if phase is None or not any(_learned_phi(value) for value in (*args, *kwargs.values())):
            return forward(*args, **kwargs)
        if phase == "recomputation":
            with torch.no_grad():
                result = forward(*args, **kwargs)
            return result.detach().requires_grad_(True)
        with torch.autograd.graph.saved_tensors_hooks(_detached, _as_saved):
            return forward(*args, **kwargs)

    return saving_plainly  # type: ignore[return-value]


def _learned_phi(value: object) -> bool:
    """Whether ``value`` is a surface (anything with a ``phi`` tensor) whose ``phi`` requires
    grad."""
    phi = getattr(value, "phi", None)
    return isinstance(phi, Tensor) and phi.requires_grad


def _detached(tensor: Tensor) -> Tensor:
    return tensor.detach()


def _as_saved(tensor: Tensor) -> Tensor:
    return tensor


def exporting() -> bool:
    """Whether ``torch.export`` traces the call (``False`` on a PyTorch without the query)."""
    query = getattr(torch.compiler, "is_exporting", None)
    return bool(query()) if query is not None else False


def functorch_levels(tensor: Tensor) -> Iterator[Tensor]:
    """``tensor`` and the tensors beneath its ``torch.func`` wrappers, outermost first."""
    functorch = getattr(torch._C, "_functorch", None)
    wrapped = getattr(functorch, "is_functorch_wrapped_tensor", None)
    yield tensor
    while wrapped is not None and wrapped(tensor):
        tensor = functorch.get_unwrapped(tensor)
        yield tensor


def batched_by_vmap(tensor: Tensor) -> bool:
    """Whether ``tensor``, or a tensor beneath its ``torch.func`` wrappers, is a batch of
    ``torch.func.vmap``."""
    batched = getattr(getattr(torch._C, "_functorch", None), "is_batchedtensor", None)
    return batched is not None and any(batched(t) for t in functorch_levels(tensor))


def refuse_vmapped_phi(phi: Tensor, owner: str) -> None:
    """Raise ``NotImplementedError`` naming ``owner`` for a ``phi`` batched by
    ``torch.func.vmap``: a surface's band and bounds are formed from its values on the host
    (functorch's own "data-dependent control flow" error had named none of it)."""
    if batched_by_vmap(phi):
        raise NotImplementedError(
            f"{owner} does not take a phi batched by torch.func.vmap: its band and bounds are "
            "formed from phi's values on the host; stack the phis along B instead "
            f"({owner}(torch.cat(phis), grid) is a batch of surfaces; {_GUIDE})")


def plain_values(tensor: Tensor) -> Tensor:
    """``tensor``'s values, detached, beneath any ``torch.func`` wrapper (``jvp``, ``grad``):
    what numpy and C code can read (a wrapped ``phi``'s band mask had failed with "Cannot
    access data pointer of Tensor that doesn't have storage"). Not for a batched tensor."""
    return list(functorch_levels(tensor.detach()))[-1]


def refuse_batched_backward(what: str, grad: Tensor) -> None:
    """Raise ``NotImplementedError`` naming ``what`` in a ``backward`` that autograd runs on a
    batch of gradients (``torch.autograd.grad(..., is_grads_batched=True)``,
    ``torch.autograd.functional.jacobian(..., vectorize=True)``, ``torch.func.vmap`` over a
    backward): ``what``'s backward runs C kernels on raw memory, or host-planned solves, which
    batched tensors do not have ("Cannot access data pointer of Tensor that doesn't have
    storage" had named nothing). Nothing while ``torch.compile`` traces (the queries are C
    functions dynamo cannot trace: they broke a compiled backward's graph)."""
    if torch.compiler.is_compiling():
        return
    functorch = getattr(torch._C, "_functorch", None)
    checks = [getattr(functorch, name, None)
              for name in ("is_legacy_batchedtensor", "is_batchedtensor")]
    if any(check is not None and check(grad) for check in checks) or "Vmap" in active_transforms():
        raise NotImplementedError(
            f"{what} has no batched backward: take each gradient apart (jacobian(..., "
            "vectorize=False), autograd.grad without is_grads_batched, a loop over the "
            f"outputs' gradients) ({_GUIDE})")


def refuse_transforms(what: str, *tensors: Tensor, refused: tuple[str, ...] = ("grad", "vmap"),
                      forward_mode: bool = True, why: str = "", phi: Tensor | None = None
                      ) -> None:
    """Raise ``NotImplementedError`` naming ``what`` under the ``refused`` ``torch.func``
    transforms (of ``"grad"`` and ``"vmap"``), and, unless ``forward_mode``, under
    ``torch.func.jvp`` or for any of ``tensors`` carrying a forward-mode tangent (``why`` says
    what stops it); and for a ``phi`` under any transform (its band and stencils are formed
    from its values by numpy and C code); and under ``torch.export``, which traces with fake
    tensors that hold no values to plan steps from. A few microseconds; nothing while
    ``torch.compile`` traces."""
    if exporting():
        raise NotImplementedError(
            f"{what} does not run under torch.export: its band, steps and stencils are planned "
            "from the values of phi and the settings, which export's fake tensors do not hold; "
            "torch.compile(model) compiles it (docs/learning.md, 'A model compiled whole'); "
            "the operators (laplace_beltrami, ...) export")
    if torch.compiler.is_compiling():
        return
    if torch.jit.is_tracing():
        raise NotImplementedError(
            f"{what} does not run under torch.jit.trace (nor torch.onnx's export by tracing): "
            "its steps and stencils run C kernels and host decisions a trace "
            "cannot record (a traced HeatFlow replayed uninitialised memory); torch.compile "
            "compiles it (docs/learning.md, 'A model compiled whole')")
    active = active_transforms()
    wrapped = getattr(getattr(torch._C, "_functorch", None), "is_functorch_wrapped_tensor", None)
    if active and phi is not None and wrapped is not None and wrapped(phi):
        raise NotImplementedError(
            f"{what} does not run with phi under a torch.func transform (jvp, grad or vmap in "
            "phi): its band and stencils are formed from phi's values by numpy and C code; use "
            f"torch.autograd.forward_ad (a dual phi) or reverse mode ({_GUIDE})")
    for name, instead in (("grad", "torch.autograd.grad(loss, inputs) or loss.backward()"),
                          ("vmap", "a batch dimension: stack the inputs along B")):
        if name in refused and name.capitalize() in active:
            raise NotImplementedError(
                f"{what} does not run under torch.func.{name}: it reads host values and "
                f"calls kernels on raw memory, which the transform wraps; use {instead} ({_GUIDE})")
    if forward_mode:
        return
    if "Jvp" in active or any(
            isinstance(t, Tensor) and forward_ad.unpack_dual(t).tangent is not None for t in tensors):
        raise NotImplementedError(
            f"{what} has no forward-mode derivative{' (' + why + ')' if why else ''}: use "
            f"reverse mode (torch.autograd.grad), or a method listed in {_GUIDE}")


@contextmanager
def outside_transforms(*reads: Tensor) -> Iterator[None]:
    """Run the block beneath every active ``torch.func`` transform, so that what it computes
    from ``reads`` (plain tensors: a surface's ``phi``) is plain too: a surface's kept state
    formed under ``torch.func.jvp`` had been the transform's wrapped tensors, which the numpy
    and C code forming it refused ("Cannot access data pointer of Tensor that doesn't have
    storage") on a surface's first call. Nothing changes outside transforms, or where one of
    ``reads`` is itself transformed (``phi`` under the transform: its state is the
    transform's)."""
    functorch = getattr(torch._C, "_functorch", None)
    stack = getattr(functorch, "get_interpreter_stack", None)
    depth = len((stack() if stack is not None else None) or ())
    wrapped = getattr(functorch, "is_functorch_wrapped_tensor", None)
    if depth == 0 or wrapped is None or any(wrapped(t) for t in reads):
        yield
        return
    from torch._functorch.pyfunctorch import temporarily_pop_interpreter_stack

    with ExitStack() as popped:
        for _ in range(depth):
            popped.enter_context(temporarily_pop_interpreter_stack())
        yield
