"""Segments of a flow run without a graph and recomputed in backward.

``torch.utils.checkpoint`` (non-reentrant) records every operation of a segment in forward and
drops only the saved tensors: the graph's thousands of small nodes stay alive until backward,
interleaved on the heap with the volumes freed between them. glibc's allocator then splits the
freed volumes' holes for those small objects and can no longer reuse them for the next volume:
a learned Perona–Malik flow at 64^3, batch 4, held 6.3 GB resident for 52 MB of live data after
its forward (docs/learning.md, "The unrolled flows under autograd"). :func:`recomputed` runs the
segment under ``no_grad`` instead (nothing kept but its input), links the result to the
segment's input and to the tensors it reads that need gradients with one node, and recomputes
the segment under autograd in backward. While ``torch.compile`` traces, a segment is a
``torch.utils.checkpoint`` region instead: the trace enters it (it cannot enter the autograd
function, whose backward walks the graph) and the compiled backward recomputes it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .._native import carries_tangents
from .._transforms import refuse_batched_backward

SEGMENT = "a checkpointed flow segment (recomputed in backward)"
"""What :func:`recomputed` names in its refusals unless told."""


def recomputed(function: Callable[[Tensor], Tensor], u: Tensor, reads: Sequence[Tensor],
               what: str = SEGMENT) -> Tensor:
    """``function(u)``, differentiable in ``u`` and ``reads``, keeping nothing but them.

    Args:
        function: ``(B, C, D, H, W) -> (B, C, D, H, W)``; every tensor it reads that needs a
            gradient, besides its argument, must be among ``reads``.
        u: its input.
        reads: the tensors ``function`` reads from outside that may need gradients, none
            computed from another (:func:`independent`: each gradient is delivered once).
            Backward checks the recomputed graph and raises if ``function`` reached a leaf
            needing gradients other than through them (a gradient would be lost).
        what: the segment as the user knows it, named where backward refuses a second
            derivative or a batch of gradients.
    """
    reads = [t for t in reads if isinstance(t, Tensor) and t.requires_grad]
    # forward mode stores nothing per step: data carrying tangents run plainly (the autograd
    # Function has no forward derivative: a learned time's flow under forward_ad failed in it)
    if not torch.is_grad_enabled() or not (u.requires_grad or reads) or carries_tangents(u):
        return function(u)
    if torch.compiler.is_compiling():  # a traced graph recomputes what it checkpoints
        return torch.utils.checkpoint.checkpoint(function, u, use_reentrant=False)
    with torch.no_grad():
        result = function(u)
    if result is u:  # nothing to recompute (an autograd Function must not return its input)
        return u
    return _Recompute.apply(function, what, result, u, *reads)


def refuse_second_derivatives(what: str, grad: Tensor) -> None:
    """Raise in a ``backward`` that autograd runs with ``create_graph=True`` (grad mode on):
    ``what`` computes its gradient without a graph, so a second derivative through it (a
    gradient penalty, a Hessian-vector product) would silently miss its part; and on a batch
    of gradients ``grad`` (:func:`~torchsurf._transforms.refuse_batched_backward`)."""
    refuse_batched_backward(what, grad)
    if torch.is_grad_enabled():
        raise RuntimeError(
            f"{what} has no second derivative: autograd.grad(..., create_graph=True) through it "
            "(gradient penalties, Hessian-vector products) would silently miss a part of the "
            "result. Take first derivatives only through torchsurf's flows and learned layers"
        )


class _Recompute(torch.autograd.Function):
    @staticmethod
    def forward(ctx, function, what, result, u, *reads):
        ctx.function, ctx.what = function, what
        ctx.save_for_backward(u, *reads)  # saved: an in-place change before backward raises
        return result

    @staticmethod
    def backward(ctx, grad):
        refuse_second_derivatives(ctx.what, grad)
        u, *reads = ctx.saved_tensors
        with torch.enable_grad():
            x = u.detach().requires_grad_(u.requires_grad)
            out = ctx.function(x)
        wanted = ([x] if u.requires_grad else []) + list(reads)
        if out.grad_fn is None:
            return None, None, None, None, *(None for _ in reads)
        _check_reads(out, wanted)
        # retain: reaching a read may run nodes of the forward's graph (a surface's geometry
        # from phi) that its own backward, and the other segments, run again
        grads = list(torch.autograd.grad(out, wanted, grad, allow_unused=True, retain_graph=True))
        grad_u = grads.pop(0) if u.requires_grad else None
        return None, None, None, grad_u, *grads


def _node(tensor: Tensor):
    """The graph node a gradient for ``tensor`` is delivered to."""
    if tensor.grad_fn is not None:
        return tensor.grad_fn
    with torch.enable_grad():
        return tensor.view_as(tensor).grad_fn.next_functions[0][0]  # its AccumulateGrad


def _check_reads(out: Tensor, wanted: Sequence[Tensor]) -> None:
    """Raise if ``out``'s graph reaches a leaf needing gradients other than by ``wanted``: the
    segment read a tensor it was not told of, whose share of that leaf's gradient would be
    lost. (Tensors derived from ``wanted`` ones, such as a surface's kept haloed geometry, are
    fine: their paths lead to a wanted tensor, through which the gradient flows.)"""
    known = {_node(t) for t in wanted}
    seen, stack = set(), [out.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen or node in known:
            continue
        seen.add(node)
        if type(node).__name__ == "AccumulateGrad":
            raise RuntimeError(
                "a recomputed flow segment read a tensor that needs gradients but is not among "
                "its declared inputs (System.params): its gradient would be lost; declare it "
                f"in the flow's System (leaf of shape {tuple(node.variable.shape)})"
            )
        stack.extend(next_node for next_node, _ in node.next_functions)


def declared(values: Sequence[object]) -> tuple[Tensor, ...]:
    """The reads to declare to :func:`recomputed`: :func:`independent` ones; while
    ``torch.compile`` traces, every tensor among ``values`` that needs gradients (there
    :func:`recomputed` checkpoints by ``torch.utils.checkpoint``, which finds its reads itself,
    and a traced tensor's graph nodes cannot be walked)."""
    if torch.compiler.is_compiling():
        return tuple(v for v in values if isinstance(v, Tensor) and v.requires_grad)
    return independent(values)


def independent(values: Sequence[object]) -> tuple[Tensor, ...]:
    """The tensors among ``values`` that need gradients, less those computed from another of
    them (and repeats).

    Differentiating a result with respect to ``phi`` and to ``normal``, computed from ``phi``,
    gives ``phi``'s total gradient (through ``normal`` too) and ``normal``'s; delivering both
    would count the path through ``normal`` twice. Keeping the ancestors alone counts it once.
    With grad disabled (``no_grad``, ``inference_mode``) nothing is differentiated: none.
    """
    if not torch.is_grad_enabled():  # inference_mode's tensors have no graph to walk
        return ()
    tensors, ids = [], set()
    for value in values:
        if isinstance(value, Tensor) and value.requires_grad and id(value) not in ids:
            tensors.append(value)
            ids.add(id(value))
    nodes = [_node(t) for t in tensors]
    kept = []
    for tensor, node in zip(tensors, nodes, strict=True):
        others = {other for other in nodes if other is not node}
        if tensor.grad_fn is None or not _reaches(tensor.grad_fn, others):
            kept.append(tensor)
    return tuple(kept)


def _reaches(start, targets: set) -> bool:
    """Whether the graph upstream of node ``start`` holds one of ``targets``."""
    seen, stack = set(), [next_node for next_node, _ in start.next_functions]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        if node in targets:
            return True
        seen.add(node)
        stack.extend(next_node for next_node, _ in node.next_functions)
    return False
