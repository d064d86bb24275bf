"""``ImplicitSurface``: one fixed surface ``phi = 0`` (or a batch) and what derives from it."""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager, nullcontext
from contextvars import ContextVar
from typing import TYPE_CHECKING, NamedTuple, TypeVar

import numpy as np
import torch
from scipy import ndimage
from torch import Tensor, nn

from . import _memory, curvature, stencils
from ._checks import (
    SUPPORTED_DTYPES,
    MismatchError,
    check_batch,
    check_finite,
    check_positive,
    check_spatial_shape,
    check_volume,
)
from ._inference import outside_inference
from ._stack import caller_stacklevel
from ._transforms import (
    exporting,
    outside_transforms,
    plain_values,
    refuse_vmapped_phi,
    saving_through_hooks,
)
from ._vectors import tangential_part
from .grid import Grid

__all__ = [
    "BAND_EDGE_SLACK",
    "CROSSING_CELLS",
    "DIRECTION_FLOOR",
    "DISTANCE_FLOOR",
    "DISTANCE_TOLERANCE",
    "FACE_LAYERS",
    "FLAT_RATIO",
    "FLAT_SAMPLES",
    "ImplicitSurface",
    "MAX_EPS",
    "MINIMUM_WEIGHT",
    "OBLIQUE_NORMAL",
    "PARALLEL_NORMAL",
    "SATURATION_RATIO",
    "TANGENT_FLOOR",
    "WEIGHT_FLOOR",
    "WIDE_BAND_CELLS",
    "check_data",
    "check_direction",
    "check_direction_batch",
    "check_eps",
    "check_surface",
    "check_tangential",
    "power_of_two_below",
    "tangent_unit",
]

if TYPE_CHECKING:
    from .bricks.layout import BrickLayout

T = TypeVar("T")

WEIGHT_FLOOR = 0.65
"""The operators' weight ``W`` is never below this fraction of the node's slope scale
(:func:`_squared_slope`, the one-sided differences' root mean square), which is
``|grad phi|`` to ``O(h^2)`` where ``phi`` is smooth: the floor acts only where central
differences collapse (a kink or an extremum of phi), whatever the size of ``|grad phi|``
along S. At a kink (one-sided slopes equal and opposite) ``W`` is 0.65 of their size: the
stability bound of the 0.2 trefoil at 64^3 is 15.2 / h^2 (a distance's: 10), as with the
former ``0.49 max(|D+|, |D-|)``. Not ``1 / sqrt(2)``: next to a shape's mirror plane between two
node planes (the 8 nodes around the centre of a sphere centred in a cell) one of the two
one-sided differences vanishes and the central one is exactly that fraction of the slope,
where ``W`` would sit on the floor's kink (autograd's derivative in ``phi`` one side's)."""
DIRECTION_FLOOR = 1e-3
"""The normal is ``grad phi / max(|grad phi|, DIRECTION_FLOOR * slope)``: a unit vector, except
where the central differences cancel to this fraction of the one-sided slopes (the centre of
a sphere, the axis of a torus, when a node falls on them). There every direction is as good,
the gradient is the rounding of ``phi``, and a unit normal would turn by any amount under any
change of ``phi`` (its derivative ``1 / (eps |grad phi|)``, 1e12 and more); the normal is
short instead, the operators there nearly isotropic, and re-extension leaves such nodes out
(:func:`torchsurf.flows._closest.has_direction`)."""
MINIMUM_WEIGHT = 0.05
"""Nor below this fraction of ``gradient_scale`` (a plateau of ``phi`` at the band's edge):
small enough for a ``|grad phi|`` that varies twentyfold along S to keep its own value."""
DISTANCE_FLOOR = 0.5
"""Distances to S are measured as ``|phi| / max(|grad phi|, DISTANCE_FLOOR * gradient_scale)``:
where ``phi`` flattens away from S (``tanh(phi / h)``, an occupancy-like field)
``|phi| / |grad phi|`` grows without bound, while ``phi``'s typical slope on S keeps the
estimate within reach."""

BAND_EDGE_SLACK = 1e-4
"""Bands hold the nodes within ``width (1 + BAND_EDGE_SLACK)`` of S: grids and shapes of round
numbers put nodes at exactly ``width`` (a sphere of radius 4 h centred on a node has nodes 3 h
from S), where any change of ``phi`` would add or drop them and the flows' output would jump;
the slack moves the edge off such placements."""

CROSSING_CELLS = 255
"""Chessboard distances to S are counted up to this many cells (``uint8``): a node farther
counts as this far, and a band of at least this many cells holds every node its distance
admits."""

WIDE_BAND_CELLS = 5.0
"""Half-width (cells) of the band flows evolve on a surface whose ``phi`` is a distance out to
it and its ring (:meth:`ImplicitSurface.evolving_widths`): wide enough that RKC steps of up to
``6 (5 - 2 sqrt(3))^2 / rho`` may hold the ring
(:func:`~torchsurf.flows._integrators.ring_held`), which costs nothing in the dense operators
(they run over the whole box) and saves the ring's re-extension at every stage: 1.5x faster to
the same error on a sphere at 37^3-65^3 (docs/band.md, section 1b)."""

DISTANCE_TOLERANCE = 0.1
"""``phi`` counts as a distance where ``|grad phi|`` is within this fraction of
``gradient_scale``: the medial axis, thin features and the edge of the band in which a mesh's
distance was computed all fall outside it."""


def _crossing(inside: Tensor) -> Tensor:
    """Nodes of a dense ``(B, 1, D, H, W)`` bool volume with a neighbour on the other side."""
    if torch.compiler.is_compiling():
        return _crossing_traced(inside)
    crossing = torch.zeros_like(inside)
    for dim in (2, 3, 4):
        change = inside.narrow(dim, 1, inside.shape[dim] - 1) != inside.narrow(
            dim, 0, inside.shape[dim] - 1
        )
        crossing.narrow(dim, 1, inside.shape[dim] - 1).logical_or_(change)
        crossing.narrow(dim, 0, inside.shape[dim] - 1).logical_or_(change)
    return crossing


def _crossing_traced(inside: Tensor) -> Tensor:
    """:func:`_crossing` for a traced graph: in ``uint8`` and without in-place ORs of views,
    whose masked bool loads inductor's CPU code generation did not compile in torch 2.13
    (``VecMask<int,1>`` against ``VecMask<float,1>``)."""
    side = inside.to(torch.uint8)
    crossing = torch.zeros_like(side)
    for dim in (2, 3, 4):
        if side.shape[dim] < 2:
            continue
        before, after = stencils.replicated_shifts(side, dim)
        crossing = crossing | (before ^ side) | (after ^ side)
    return crossing > 0


def _squared_slope(padded: Tensor) -> Tensor:
    """The square of the slope scale ``sqrt(sum_a (D+_a phi^2 + D-_a phi^2) / 2)``, in phi's
    units per cell, from ``phi`` with a halo of one node; ``(B, 1, D, H, W)``.

    Each axis's term is ``central^2 + (h/2 D+D-_a phi)^2``: never below ``|central gradient|``,
    within ``O(h^2)`` of it where ``phi`` is smooth, and where the central difference shrinks
    because the slope changes within the cell (a kink of a distance: the medial axis, features
    thinner than two cells, the edge of a clamped band) the one-sided slopes' root mean square.
    A smooth function of ``phi``: ``max(|D+|, |D-|)`` had a kink wherever the two were equal,
    which symmetric placements make exact (a torus's core circle through nodes), and the
    weight's floor with it, where autograd's derivative in ``phi`` was one side's."""
    forward = stencils.apply(padded, stencils.FORWARD)[:, 0]
    backward = stencils.apply(padded, stencils.BACKWARD)[:, 0]
    return ((forward**2 + backward**2) / 2).sum(dim=1, keepdim=True)


def power_of_two_below(value: Tensor) -> Tensor:
    """The power of two at or below each (positive) value: ``2^floor(log2(value))``, exact."""
    return torch.exp2(torch.floor(torch.log2(value.clamp_min(torch.finfo(value.dtype).tiny))))


def _per_entry(mask: Tensor, layout: BrickLayout | None) -> Tensor:
    """The true nodes of ``mask`` ``(B, 1, D, H, W)`` (packed ``(N, 1, 8, 8, 8)`` on bricks)
    counted per batch entry: ``(B,)`` long."""
    counts = mask.flatten(1).sum(dim=1)
    if layout is None:
        return counts
    batch = layout.batch.to(counts.device)
    return counts.new_zeros(layout.batch_size).index_add_(0, batch, counts)


_WARNED_ALREADY: ContextVar[bool] = ContextVar("torchsurf_surface_warned_already", default=False)
"""Set by :func:`warned_already` while this thread builds surfaces whose ``phi`` was checked."""


@contextmanager
def warned_already() -> Iterator[None]:
    """Surfaces built in this block skip the checks that warn of their ``phi`` (a batch's
    entry, whose batch surface warned already). Only this thread's: a ``warnings`` filter had
    done it, which is global, and threads overlapping in it left it in place for good, every
    later ``RuntimeWarning`` of the process silenced. Not for use while ``torch.compile``
    traces (a context variable's set breaks the graph; surfaces built then skip the checks)."""
    token = _WARNED_ALREADY.set(True)
    try:
        yield
    finally:
        _WARNED_ALREADY.reset(token)


def _warn_floored_on_surface(crossing: Tensor, grad_norm: Tensor, scale: Tensor,
                             layout: BrickLayout | None = None) -> None:
    """Warn where ``|grad phi|`` next to S falls below :data:`MINIMUM_WEIGHT` of its median
    ``scale``: the weight is floored there, so the operators are not intrinsic (a ``phi`` with
    the same zero set but a gentler gradient would give other values)."""
    ratio = grad_norm / scale
    floored = crossing & (ratio < MINIMUM_WEIGHT)
    if bool(floored.any()):
        flagged = _per_entry(floored, layout) > 0
        entries = flagged.nonzero().flatten().tolist()
        near = int(_per_entry(crossing, layout)[flagged].sum())
        which = _entries_named(entries, len(flagged))
        warnings.warn(
            f"phi: |grad phi| next to S falls to {float(ratio[crossing].min()):.3g} of its "
            f"median there at {int(floored.sum())} of {near} nodes{which} (below "
            f"MINIMUM_WEIGHT = {MINIMUM_WEIGHT}): the operators' weight W is floored at those "
            "nodes and they are no longer intrinsic; make phi a distance near S first "
            "(torchsurf.sdf.redistance), or, if it is one, resolve the features thinner than "
            "a few cells with a finer grid",
            RuntimeWarning, stacklevel=caller_stacklevel(),
        )


FLAT_RATIO = 0.6
"""``phi`` whose distances next to S (``|phi| / |grad phi|``) add up, across S, to less than this
share of the nodes' spacing along the normal (1 for a distance; 1/3 for ``d^3``, 1/2 for
``d |d|``) is warned about (:func:`_warn_flat_at_surface`)."""

SATURATION_RATIO = 0.9
"""``phi`` whose ``|phi|`` grows, over the cell beyond the nodes next to S, by less than this
share of what a distance's would (``|grad phi| h |n_a|``), on both sides of S
(:func:`_saturation_share`: the larger side's median), is warned about, per batch entry
(:func:`_warn_flat_at_surface`). Measured at 17^3-65^3: 1.00-1.15 for distances (spheres down
to a radius of 1.5 cells, tori down to 0.75 cell thick, the shared meshes' ``sdf.from_mesh``
at 24^3-64^3, a thin trimesh torus), 1.01-1.02 for ``d exp(3x)`` on a sphere, 1.04-1.46 for a
plane's distance times ``exp(s x)``, 1.03-1.12 for ``r^2 - R^2``; 0.94-0.99, 0.88-0.93,
0.82-0.85 and 0.56-0.60 for ``tanh(d / eps)`` with ``eps`` 2, 1.5, 1.2 and 0.7 cells,
0.80-0.83 for ``atan(d / h)``. On a sphere at 33^3 the heat flow's error was 2e-2 and 0.25
for ``eps`` 0.6 and 0.2 cells, 1.3e-2 for 1.1 cells, and 7-16 times the distance's at 2
cells, against 1e-3 on the distance. Not warned: a phi that saturates on one side of S only
(0.96-1.14; heat 1e-2 to 3.4e-2 off), since a distance also grows less on one side, towards a
thin part's axis; nor a distance truncated beyond the cell next to S."""

FLAT_SAMPLES = 4096
"""Each batch entry's node pairs across S are read for :func:`_warn_flat_at_surface` at an
even stride of ``count // FLAT_SAMPLES`` (all of them below twice this many): between this many
and twice this many of an entry with more."""


class _Pairs(NamedTuple):
    """Nodes next to S that :func:`_warn_flat_at_surface` reads, each with its neighbour one node
    towards S along the axis of the normal's largest component; every field ``(M,)``, in the
    order of the nodes (so by batch entry). Indices are into ``phi`` flattened."""

    entry: Tensor
    """The node's batch entry, long."""
    node: Tensor
    """The node's index, long."""
    step: Tensor
    """``node + step`` is the neighbour towards S, long (``±`` the axis's stride)."""
    ahead: Tensor
    """How many nodes lie beyond the node in the direction of ``step``, long."""
    behind: Tensor
    """How many lie beyond it the other way, long."""
    along: Tensor
    """The normal's component on the axis, phi's dtype."""


def _sampled_crossing(crossing: Tensor) -> Tensor:
    """The indices into ``crossing`` ``(B, 1, D, H, W)`` flattened of its true nodes, ``(M,)``
    long, ascending: each entry's at an even stride (:data:`FLAT_SAMPLES`) over them (a
    stride over the batch left a small entry beside large ones too few to judge)."""
    nodes = crossing.reshape(-1).nonzero()[:, 0]
    if len(nodes) < 2 * FLAT_SAMPLES:  # no entry holds enough to stride over
        return nodes
    entry = nodes // crossing[0].numel()
    counts = torch.bincount(entry, minlength=crossing.shape[0])
    first = torch.cumsum(counts, 0) - counts
    rank = torch.arange(len(nodes), device=nodes.device) - first[entry]
    return nodes[rank % (counts // FLAT_SAMPLES).clamp_min(1)[entry] == 0]


def _pairs_across(phi: Tensor, nodes: Tensor, normal: Tensor) -> _Pairs:
    """:class:`_Pairs` of ``nodes`` ``(M,)`` (indices into ``phi`` ``(B, 1, D, H, W)``
    flattened) and their normals ``(B, 3, D, H, W)``: the axis of each normal's largest
    component, and the step along it towards S (the normal's way outside S, against it
    inside)."""
    depth, height, width = phi.shape[2:]
    volume = depth * height * width
    entry = nodes // volume
    channels = torch.arange(3, device=nodes.device) * volume
    n = torch.take(normal, (nodes + 2 * volume * entry)[:, None] + channels)  # (M, 3): x, y, z
    axis = n.abs().argmax(dim=1)
    along = n.gather(1, axis[:, None])[:, 0]
    inside = torch.take(phi, nodes) < 0
    towards = inside == (along > 0)
    stride, size = torch.tensor([[1, width, height * width], [width, height, depth]],
                                device=nodes.device)[:, axis]
    coordinate = nodes // stride % size  # an entry's volume is a multiple of stride * size
    last = size - 1 - coordinate
    return _Pairs(entry=entry, node=nodes, step=torch.where(towards, stride, -stride),
                  ahead=torch.where(towards, last, coordinate),
                  behind=torch.where(towards, coordinate, last), along=along)


def _entry_spans(entry: Tensor, batch: int) -> list[slice]:
    """Each batch entry's run of ``entry`` ``(M,)`` (ascending): its elements' slice."""
    if batch == 1:
        return [slice(0, len(entry))]
    ends = torch.cumsum(torch.bincount(entry, minlength=batch), 0).tolist()
    return [slice(start, end) for start, end in zip([0, *ends[:-1]], ends, strict=True)]


def _count_per_entry(masks: Tensor, entry: Tensor, batch: int) -> Tensor:
    """The true elements of each of ``masks`` ``(G, M, ...)`` per batch entry (``entry``
    ``(M,)``): ``(G, batch)`` long."""
    per_node = masks.reshape(len(masks), len(entry), -1).sum(dim=2)
    if batch == 1:
        return per_node.sum(dim=1, keepdim=True)
    return per_node.new_zeros(len(masks), batch).index_add_(1, entry, per_node)


def _reduce_per_entry(values: Tensor, entry: Tensor, batch: int, how: str) -> Tensor:
    """``amin`` or ``amax`` (``how``) of ``values`` ``(M, k)`` per batch entry: ``(batch,)``;
    an entry of no elements gets 0."""
    reduce = torch.amin if how == "amin" else torch.amax
    per_node = reduce(values, dim=1)
    if batch == 1:
        return reduce(per_node, dim=0, keepdim=True)
    return per_node.new_zeros(batch).scatter_reduce_(0, entry, per_node, how, include_self=False)


def _lower_median(values: Tensor, mask: Tensor, count: int) -> Tensor:
    """What ``values[mask].median()`` is (the lower middle value), ``count`` being
    ``mask.sum()`` (at least 1) and every value of ``mask`` finite: 0-d (a zero as ``0.0``,
    never ``-0.0``: zeros of both signs tie)."""
    return torch.where(mask, values, math.inf).flatten().kthvalue((count + 1) // 2).values + 0.0


def _warn_flat_at_surface(phi: Tensor, crossing: Tensor, grad_norm: Tensor, floor: Tensor,
                          normal: Tensor, spacing: float) -> None:
    """Warn when ``phi`` ``(B, 1, D, H, W)`` flattens at S (``phi = g(d)`` with ``g'(0) = 0``,
    such as ``d^3``): its first-order distances ``|phi| / |grad phi|`` then shrink by a factor
    near S (``d / 3``), and with them the band, the closest points and every re-extension; or
    flattens beyond S (``tanh(d / eps)`` with ``eps`` below a cell or two), where the normals
    and weights of the band's outer nodes are then those of a nearly constant ``phi``.

    Read at up to :data:`FLAT_SAMPLES` nodes of ``crossing``: each with its neighbour across S
    along the axis of the normal's largest component ``a``, whose distances add up to
    ``h |n_a|`` for a distance (warned when their median share is below :data:`FLAT_RATIO`),
    and with its neighbour away from S on that axis, whose ``|phi|`` exceeds the node's by
    ``|grad phi| h |n_a|`` for a distance (warned when the median share is below
    :data:`SATURATION_RATIO`). ``floor``: ``(B, 1, 1, 1, 1)``, the least ``|grad phi|`` the
    distances divide by. Both checks read the same pairs (those reaching out of the box left
    out), and each reads its counts and its medians for the whole batch at once."""
    nodes = _sampled_crossing(crossing)
    if len(nodes) == 0:
        return
    pairs = _pairs_across(phi, nodes, normal)
    across = torch.where(pairs.ahead >= 1, pairs.node + pairs.step, pairs.node)  # in the box
    ends = torch.stack((pairs.node, across), dim=1)  # (M, 2)
    ends_phi, ends_norm = torch.take(phi, ends), torch.take(grad_norm, ends)
    separated = (pairs.ahead >= 1) & ((ends_phi[:, 0] < 0) != (ends_phi[:, 1] < 0))
    spans = _entry_spans(pairs.entry, phi.shape[0])
    _warn_saturated(pairs, phi, ends_phi, ends_norm, separated, spans, spacing)
    _warn_flat_pairs(pairs, ends_phi, ends_norm, separated, spans,
                     torch.take(floor, pairs.entry), spacing)


def _warn_flat_pairs(pairs: _Pairs, ends_phi: Tensor, ends_norm: Tensor, separated: Tensor,
                     spans: list[slice], floor: Tensor, spacing: float) -> None:
    """The first check of :func:`_warn_flat_at_surface`, per batch entry (``spans``, their
    pairs): ``ends_phi`` and ``ends_norm`` ``(M, 2)``, phi and ``|grad phi|`` at each node and
    its neighbour towards S; ``separated`` ``(M,)``, the pairs S separates; ``floor`` ``(M,)``,
    the least ``|grad phi|`` of each pair's entry."""
    distances = ends_phi.abs() / torch.maximum(ends_norm, floor[:, None])
    ratio = (distances[:, 0] + distances[:, 1]) / (spacing * pairs.along.abs())
    kept = separated & torch.isfinite(ratio)  # a normal with no component on its axis: 0 / 0
    counts = _count_per_entry(kept[None], pairs.entry, len(spans))[0].tolist()
    judged = [index for index, count in enumerate(counts) if count >= 8]
    if not judged:
        return
    medians = torch.stack([_lower_median(ratio[spans[index]], kept[spans[index]], counts[index])
                           for index in judged]).tolist()
    # per batch entry: a flat entry beside distances is not averaged away
    flat = [(index, median) for index, median in zip(judged, medians, strict=True)
            if median < FLAT_RATIO]
    if flat:
        share = min(share for _, share in flat)
        which = _entries_named([index for index, _ in flat], len(spans))
        warnings.warn(
            f"phi{which}: its distances next to S (|phi| / |grad phi|) add up, across S, to "
            f"{', '.join(f'{s:.2f}' for _, s in flat)} of the nodes' spacing along the normal "
            f"(1 for a distance): phi flattens at S (as d^3 does), so the band, the closest "
            f"points and the flows read distances up to {1 / share:.1f} times too short; make "
            "phi a distance near S first (torchsurf.sdf.redistance)",
            RuntimeWarning, stacklevel=caller_stacklevel(),
        )


def _warn_saturated(pairs: _Pairs, phi: Tensor, ends_phi: Tensor, ends_norm: Tensor,
                    separated: Tensor, spans: list[slice], spacing: float) -> None:
    """The second check of :func:`_warn_flat_at_surface`, per batch entry (``spans``, their
    pairs) of ``phi`` ``(B, 1, D, H, W)``: ``ends_phi`` and ``ends_norm`` ``(M, 2)``, phi and
    ``|grad phi|`` at each node and its neighbour towards S; ``separated`` ``(M,)``, the pairs
    S separates. The neighbours beyond each node of a pair, away from S (beyond the node: any
    pair's; beyond its neighbour: a separated pair's), are read, on both sides of S."""
    beyond = torch.stack((pairs.node - pairs.step, pairs.node + 2 * pairs.step), dim=1)
    kept = torch.stack(((pairs.ahead >= 1) & (pairs.behind >= 1),
                        separated & (pairs.ahead >= 2)), dim=1)  # (M, 2), in the box
    far = torch.take(phi, torch.where(kept, beyond, pairs.node[:, None])).abs()
    growth = (far - ends_phi.abs()) / (ends_norm * spacing * pairs.along.abs()[:, None])
    kept &= torch.isfinite(growth)  # a normal with no component on its axis: 0 / 0
    slope = ends_norm * pairs.along.abs()[:, None]
    mine = _steep_enough(slope, kept, pairs.entry, spans)
    inside = ends_phi < 0
    sides = torch.stack((mine & inside, mine & ~inside))
    counts = _count_per_entry(sides, pairs.entry, len(spans)).T.tolist()  # (B, 2)
    shares = _saturation_shares(growth, mine, sides, counts, spans)
    flattened = [(index, share) for index, share in enumerate(shares)
                 if share is not None and share < SATURATION_RATIO]
    if not flattened:
        return
    described = ", ".join(f"{share:.2f}" for _, share in flattened)
    which = _entries_named([index for index, _ in flattened], len(spans))
    warnings.warn(
        f"phi{which}: |phi| grows over the cell beyond the nodes next to S by {described} of "
        "what a distance's would: phi flattens away from S (as tanh(d / eps) does with eps "
        "below a cell or two), so the band's outer normals and weights are those of a "
        "nearly constant phi and the flows lose accuracy; make phi a distance near S "
        "first (torchsurf.sdf.redistance)",
        RuntimeWarning, stacklevel=caller_stacklevel(),
    )


def _steep_enough(slope: Tensor, kept: Tensor, entry: Tensor, spans: list[slice]) -> Tensor:
    """``kept`` ``(M, 2)`` less the samples whose ``slope`` (``|grad phi| |n_a|``) is below
    :data:`MINIMUM_WEIGHT` of its entry's median (``torch.quantile``'s): a node whose slope
    along the axis collapsed (a sphere's centre: the weight check warns of it) says nothing
    (radius 0.6 h: -2e5). Only entries whose least slope is below twice that fraction of their
    largest can lose any, and only theirs are read."""
    batch = len(spans)
    lowest = _reduce_per_entry(torch.where(kept, slope, math.inf), entry, batch, "amin")
    highest = _reduce_per_entry(torch.where(kept, slope, -math.inf), entry, batch, "amax")
    spread = (lowest < 2 * MINIMUM_WEIGHT * highest).nonzero()[:, 0].tolist()
    if not spread:
        return kept
    kept = kept.clone()
    for index in spread:
        mine, steep = kept[spans[index]], slope[spans[index]]
        mine &= steep >= MINIMUM_WEIGHT * torch.quantile(steep[mine], 0.5)
    return kept


def _saturation_shares(growth: Tensor, mine: Tensor, sides: Tensor, counts: list[list[int]],
                       spans: list[slice]) -> list[float | None]:
    """Each entry's share for :func:`_warn_saturated` (``None`` below 8 samples): the larger of
    the two sides' median ``growth`` (a side of fewer than 8 samples left out). A phi that
    saturates flattens on both sides of S; a distance grows less only on one, towards a thin
    part's axis (a tube a cell thick: inside 0 to 0.9, outside 1.05 to 1.16), and so does a phi
    scaled along the normal (a plane's distance times ``exp(s x)``: less on one side by what it
    grows more on the other). ``growth``, ``mine`` ``(M, 2)``; ``sides`` ``(2, M, 2)``, the
    samples of ``mine`` inside S and outside; ``counts``, theirs per entry ``(B, 2)``."""
    medians: list[Tensor] = []
    owners: list[int] = []
    for index, (span, (inner, outer)) in enumerate(zip(spans, counts, strict=True)):
        judged = [(side, count) for side, count in zip(sides[:, span], (inner, outer), strict=True)
                  if count >= 8]
        if not judged and inner + outer >= 8:
            judged = [(mine[span], inner + outer)]
        medians += [_lower_median(growth[span], side, count) for side, count in judged]
        owners += [index] * len(judged)
    shares: list[float | None] = [None] * len(spans)
    read = torch.stack(medians).tolist() if medians else []
    for index, median in zip(owners, read, strict=True):
        shares[index] = median if shares[index] is None else max(shares[index], median)
    return shares


def _entries_named(entries: list[int], batch: int) -> str:
    """`` (batch entries [...])`` naming ``entries`` in a batch of several, else nothing."""
    return "" if batch == 1 else f" (batch entries {entries})"


FACE_LAYERS = 2
"""S crossing a cell of the box's outer ``FACE_LAYERS`` layers of nodes (within about two
cells of a face) where its level sets leave the box obliquely is warned about
(:func:`_warn_oblique_at_faces`)."""

OBLIQUE_NORMAL = math.sin(math.radians(3.0))
"""A normal whose component across a face exceeds this (more than 3 degrees out of the face's
plane), and is not within 3 degrees of the face's own normal, meets the face obliquely
(:func:`_warn_oblique_at_faces`). The bound was 30 degrees: a sphere cut by a face at 5, 11
and 20 degrees went unwarned while its Laplace–Beltrami of degree-2 harmonic data was 2.3 to
4.9 times its largest value off at the two outer layers (33^3-65^3), as wrong as at the angles
warned about; and a plane parallel to a face within its two outer layers was warned about
though its results equal those of the plane in the middle of the box (its normal lines run
along the face's, as the replicated data do; an audit, 2026-12-07)."""

PARALLEL_NORMAL = math.cos(math.radians(3.0))
"""See :data:`OBLIQUE_NORMAL`."""


def _warn_oblique_at_faces(crossing: Tensor, normal: Tensor) -> None:
    """Warn where S crosses the outer :data:`FACE_LAYERS` layers of nodes of a face (nodes of
    ``crossing`` ``(B, 1, D, H, W)``, a neighbour across S) whose normal ``(B, 3, D, H, W)``,
    extrapolated linearly along the face's normal to the wall half a cell beyond the outer
    nodes, lies more than 3 degrees out of the face's plane and more than 3 degrees from the
    face's normal (:data:`OBLIQUE_NORMAL`).

    The stencils see no flux through the faces, which can hold for level sets that meet them at
    right angles (a cylinder along an axis, with data symmetric about the face: README.md) and
    not for those of a surface that turns back near a face or leaves it at any other angle:
    the octant Laplace–Beltrami of a degree-2 harmonic on a unit sphere one cell from the faces
    was 44% and 94% wrong over the 3-cell band at 25^3 and 49^3 (21% and 48% at two cells,
    1.4% and 0.2% at three; remeasured 2026-12-06, relative max). Read from the zero set, not
    from ``|phi| / W``, which is no distance where ``phi`` is none."""
    if not _reaches_faces(crossing):
        return
    hits = sum(_oblique_across(crossing, normal, axis) for axis in range(3))
    if bool(hits.any()):
        which = _entries_named(hits.nonzero().flatten().tolist(), crossing.shape[0])
        warnings.warn(
            f"phi: S comes within about {FACE_LAYERS} cells of the grid's faces{which}, where "
            f"its level sets leave the box obliquely ({int(hits.sum())} nodes next to S in the "
            f"outer {FACE_LAYERS} layers): the stencils assume no flux through the faces, so "
            "operators and flows are wrong near there; give the grid a margin of a few cells "
            "(Grid.cube's bound, mesh.fit_grid's margin)",
            RuntimeWarning, stacklevel=caller_stacklevel(),
        )


def _face_layers(size: int) -> int:
    """How many of an axis's outer layers of ``size`` nodes :func:`_warn_oblique_at_faces`
    reads at each of its two faces."""
    return min(FACE_LAYERS, size - 1)


def _reaches_faces(crossing: Tensor) -> bool:
    """Whether any node of ``crossing`` ``(B, 1, D, H, W)`` lies in the outer layers that
    :func:`_warn_oblique_at_faces` reads (S kept off the faces: none, and nothing to read)."""
    inner = crossing
    for dim in (2, 3, 4):
        layers = _face_layers(crossing.shape[dim])
        inner = inner.narrow(dim, layers, max(crossing.shape[dim] - 2 * layers, 0))
    return bool(crossing.sum() != inner.sum())


def _oblique_across(crossing: Tensor, normal: Tensor, axis: int) -> Tensor:
    """The nodes of ``crossing`` ``(B, 1, D, H, W)`` in the outer layers at the two faces across
    ``axis`` (normal channel x, y, z <-> dims W, H, D) whose normal's component across them,
    extrapolated to the wall, is oblique (:func:`_warn_oblique_at_faces`), counted per batch
    entry: ``(B,)`` long. The layers of both faces are read at once, with each layer's inward
    neighbours."""
    dim = 4 - axis
    size = normal.shape[dim]
    layers = range(_face_layers(size))  # 0: the outermost
    nodes = [*layers, *(size - 1 - layer for layer in layers)]
    inward = [*(layer + 1 for layer in layers), *(size - 2 - layer for layer in layers)]
    index = torch.tensor([nodes, inward], device=normal.device)
    # the wall lies layer + 1/2 cells beyond the nodes of each layer
    beyond = torch.tensor([layer + 0.5 for layer in layers] * 2, dtype=normal.dtype,
                          device=normal.device).view([-1 if d == dim else 1 for d in range(5)])
    component = normal[:, axis: axis + 1]
    at = component.index_select(dim, index[0])
    # the component at the wall, half a cell beyond the outer nodes: S's curvature tilts the
    # normals of nodes in from it (a sphere cut through its equator at the wall, whose nodes'
    # normals lean 1.5 h / R out of the face's plane)
    wall = (at + beyond * (at - component.index_select(dim, index[1]))).abs()
    oblique = ((wall > OBLIQUE_NORMAL) & (wall < PARALLEL_NORMAL)
               & crossing.index_select(dim, index[0]))
    return oblique.flatten(1).sum(dim=1)


def _cells_to_crossing(phi: Tensor) -> Tensor:
    """The chessboard distance, in cells, from each node to the nearest node with a neighbour
    across S (at most :data:`CROSSING_CELLS`), ``(B, 1, D, H, W)`` uint8 on ``phi``'s device.
    Chessboard: ten times faster than the Euclidean transform (0.4 s against 3.8 s at 256^3),
    and never above it."""
    crossing = _crossing(phi < 0).cpu().numpy()
    cells = [np.minimum(ndimage.distance_transform_cdt(~entry[0], metric="chessboard"),
                        CROSSING_CELLS)
             for entry in crossing]
    return torch.from_numpy(np.stack(cells)[:, None].astype(np.uint8)).to(phi.device)


def _part_of_larger(phi: Tensor) -> bool:
    """``phi`` does not require grad and is a view of a tensor holding more than it."""
    return not phi.requires_grad and phi._base is not None and phi._base.numel() > phi.numel()


_DERIVE_ON_LOAD = "_derive_geometry_on_load"
"""Key of a copied surface's state whose geometry is derived again from its ``phi``."""


MAX_EPS = 0.1
"""The largest ``eps`` of :class:`ImplicitSurface`, relative to ``phi``'s typical slope on S:
larger values shrink the normals where ``phi`` is a distance (to 0.70 of unit length at 1, 0.1
at 10, and NaN from the infinite weight at 1e30) and widen the band (the whole box at 10)."""


def check_eps(eps: object) -> float:
    """``eps`` if it is a positive number of at most :data:`MAX_EPS`; raises naming it."""
    value = check_positive(eps, "eps")
    if value > MAX_EPS:
        raise ValueError(
            f"eps must be at most {MAX_EPS:g} (relative to phi's typical |grad phi| on S; it "
            f"only keeps the normals finite where grad phi vanishes), got {eps!r}: larger "
            "values shrink the normals where phi is a distance and widen the band")
    return value


def _fingerprint(phi: Tensor) -> Tensor:
    """Integer sums of ``phi``'s values' bit patterns, ``(3,)`` int64: all of them, and each
    row's and each column's weighted by its place, so that a value changed, or moved, changes
    them (two rows or columns of equal sums exchanged would not). ``-0.0`` counts as ``0.0``.
    Two reductions over ``phi``: 0.5 ms at 64^3, 2% of building the surface."""
    values = phi.detach() + 0.0  # -0.0 + 0.0 is 0.0
    bits = values.view(torch.int64 if values.element_size() == 8 else torch.int32)
    rows = bits.reshape(-1, bits.shape[-1])
    by_row = rows.sum(dim=1, dtype=torch.int64)
    by_column = rows.sum(dim=0, dtype=torch.int64)
    return torch.stack((by_row.sum(),
                        (by_row * torch.arange(len(by_row), device=phi.device)).sum(),
                        (by_column * torch.arange(len(by_column), device=phi.device)).sum()))


def _same_values(phi: Tensor, fingerprint: Tensor | None) -> bool:
    """Whether ``phi`` holds the values whose :func:`_fingerprint` is ``fingerprint``
    (``None``: not taken, as while ``torch.compile`` traced the surface's construction)."""
    return (fingerprint is not None and fingerprint.device == phi.device
            and bool(torch.equal(_fingerprint(phi), fingerprint)))


def _article(name: str) -> str:
    """``name`` with its indefinite article ("an ImplicitSurface", "a BrickSurface")."""
    return f"{'an' if name[:1].lower() in 'aeiou' else 'a'} {name}"


def _ddp_hint() -> str:
    """Where processes run together, what writes a module's buffers in place unasked."""
    distributed = torch.distributed
    if not (distributed.is_available() and distributed.is_initialized()):
        return ""
    return ("; DistributedDataParallel writes rank 0's buffers into every rank's before each "
            "forward (broadcast_buffers=True), a surface's phi among them if the surface is a "
            "submodule of the wrapped model: pass the surface to forward instead, or give "
            "broadcast_buffers=False")


class ImplicitSurface(nn.Module):
    """The zero level set of ``phi`` on ``grid``, with its normals, band and curvatures.

    ``|grad phi|`` and the unit normals are computed once, by central differences with
    ``phi`` extrapolated quadratically beyond the grid (second-order one-sided differences at
    the box's faces), and reused by every operator. When ``phi`` requires grad they stay in its
    graph, which one ``backward`` frees: build the surface again for every backward (each
    optimiser step, and each mini-batch of a gradient accumulation; a second backward through
    one surface raises PyTorch's "backward through the graph a second time"), or pass
    ``retain_graph=True`` to all but the last.
    ``surface.to(...)`` (``.double()``, a device) moves ``phi`` and derives the rest again from
    it: the same numbers as a surface built from the moved ``phi``; a move that changes
    nothing keeps everything, what flows kept included (unless ``phi`` requires grad: its
    geometry is derived again, in a new graph). Changing ``phi`` in place
    afterwards (``phi.copy_``, ``phi.mul_``) makes every method raise ``RuntimeError``, unless
    it was written with the values it held (a model's buffers averaged by
    ``AveragedModel(use_buffers=True)``, broadcast by ``DistributedDataParallel``); changes
    that leave no trace in its version counter are not seen: writes through ``phi.data``,
    and in-place changes between calls of code compiled by an outer ``torch.compile``
    (the check is a host read, which compiled code skips). Replacing ``phi`` (assigning
    ``surface.phi``, or swapping it in with ``torch.func.functional_call``) raises too, and
    :attr:`grid` cannot be set. Build a new surface from a new ``phi`` instead.

    Its ``state_dict`` holds ``phi`` and where it lies (:meth:`get_extra_state`; everything
    else is derived): loading another surface's state of the same shape, alone or inside a
    model or an adapter, makes this surface that one (its ``phi`` copied, never shared).
    Setting :attr:`band_width` or :attr:`eps` drops or derives again what depends on them.

    Nothing assumes that ``phi`` is a distance in world units: widths are measured as
    :meth:`distance` (``|phi| / |grad phi|``, floored at half ``gradient_scale``; so
    ``1000 * phi`` is the same surface with the same band), and where
    central differences of ``phi`` collapse (the medial axis, features thinner than two cells,
    the edge of the band in which a mesh's distance was computed) the operators' weight ``W``
    is floored at :data:`WEIGHT_FLOOR` times the slopes on either side of the node, so that an
    explicit step chosen for the surface stays stable there (docs/band.md). Where ``phi`` is
    smooth the floor does not act, whatever ``|grad phi|`` is: ``W = |grad phi|`` keeps the
    divergence forms intrinsic for any ``phi`` with the right zero set.

    Args:
        phi: ``(B, 1, D, H, W)``, negative inside, positive outside, world units; ideally a
            signed distance function near the surface. Every batch entry must change sign.
        grid: the grid ``phi`` is sampled on; ``grid.shape == (D, H, W)``.
        band_width: half-width of the band ``|phi| / W <= band_width``, world units
            (default ``3 * grid.spacing``); the flows evolve the data in this band.
        eps: regularisation of ``|grad phi|`` as ``sqrt(|grad phi|^2 + (eps s)^2)``, relative
            to ``s = gradient_scale`` (the typical ``|grad phi|`` on S, 1 for a distance
            function), so that it means the same for ``phi`` and ``c * phi``; keeps normals
            and their gradients finite where ``grad phi`` vanishes (the medial axis). At most
            :data:`MAX_EPS`.

    Attributes:
        phi: ``(B, 1, D, H, W)``.
        grad_norm: ``sqrt(|grad phi|^2 + (eps * gradient_scale)^2)``, ``(B, 1, D, H, W)``.
        normal: ``grad phi / grad_norm``, ``(B, 3, D, H, W)`` in ``(x, y, z)`` order.
        gradient_scale: the median of ``|grad phi|`` over the nodes next to a sign change of
            ``phi`` (1 for a distance function), ``(B, 1, 1, 1, 1)``.
        weight: ``W = max(grad_norm, WEIGHT_FLOOR * slope, MINIMUM_WEIGHT *
            gradient_scale)``, ``slope`` the root mean square of the one-sided differences of
            ``phi`` along each axis (:func:`_squared_slope`); the weight of every
            divergence-form operator ``(1/W) div(W ...)``, ``(B, 1, D, H, W)``.

    Example:
        >>> grid = Grid.cube(33, bound=1.5)
        >>> from torchsurf import sdf
        >>> surface = ImplicitSurface(sdf.sphere(grid, radius=1.0), grid)
        >>> surface.normal.shape
        torch.Size([1, 3, 33, 33, 33])
    """

    phi: Tensor
    grad_norm: Tensor
    normal: Tensor
    gradient_scale: Tensor
    weight: Tensor

    def __init__(
        self, phi: Tensor, grid: Grid, band_width: float | None = None, eps: float = 1e-6
    ) -> None:
        super().__init__()
        if not isinstance(grid, Grid):
            raise TypeError(f"grid must be a torchsurf.Grid, got {type(grid).__name__}")
        check_volume(phi, "phi", channels=1)
        refuse_vmapped_phi(phi, type(self).__name__)
        check_spatial_shape(phi, "phi", grid.shape, "grid")
        _memory.check_fits(
            _memory.surface_bytes(phi.shape[0], grid.shape, phi.dtype),
            f"ImplicitSurface of phi with shape {tuple(phi.shape)}", phi.device,
        )
        check_finite(phi, "phi")
        lowest = phi.detach().flatten(1).min(dim=1).values
        highest = phi.detach().flatten(1).max(dim=1).values
        missing = ((lowest >= 0) | (highest <= 0)).nonzero().flatten()
        if len(missing) > 0:
            raise ValueError(
                f"phi has no zero crossing in batch entries {missing.tolist()}: every entry "
                "must be negative somewhere (inside) and positive somewhere (outside)"
            )
        self.grid = grid
        self.band_width = check_positive(
            3.0 * grid.spacing if band_width is None else band_width, "band_width"
        )
        self.eps = check_eps(eps)
        self._assemble_kept(phi)

    @property
    def grid(self) -> Grid:
        """Where the nodes lie (:class:`~torchsurf.Grid`). Fixed once the surface is built: the
        normals, weight and band are derived on it (build a new surface for another grid)."""
        return self._grid

    @grid.setter
    def grid(self, value: Grid) -> None:
        if "phi" in self._buffers:
            raise AttributeError(
                f"{type(self).__name__}.grid is fixed once built: its normals, weight and band "
                f"were derived on it; build a new surface, {type(self).__name__}(phi, grid)")
        self._grid = value

    layout = None
    """How the fields are stored: ``None`` for dense volumes (a :class:`torchsurf.bricks.BrickSurface`
    has its :class:`~torchsurf.bricks.BrickLayout`)."""

    def _assemble(self, phi: Tensor) -> None:
        """``grad_norm``, ``normal``, ``gradient_scale`` and ``weight`` from ``phi``."""
        padded = self._pad(phi, "quadratic")
        gradient = stencils.apply(padded, stencils.CENTRAL)[:, 0]
        gradient = gradient / self.spacing
        # squares of |grad phi| in units of a power of two per entry (exact to divide and
        # multiply by): c * phi with c near the float's range (1e20 in float32) neither
        # overflows nor underflows them, and other phi give the same bits as without
        magnitude = power_of_two_below(self._entry_max(gradient.detach().abs().amax(dim=1, keepdim=True)))
        unit_gradient = gradient / magnitude
        squared = (unit_gradient**2).sum(dim=1, keepdim=True)
        self.register_buffer("phi", phi, persistent=False)
        # the tensor itself, not registered (phi may be a Parameter): a phi assigned or swapped in
        self.__dict__["_phi_assembled"] = phi
        # the median of the squares, then its root: no sqrt of zeros in phi's graph
        crossing = self._crossing_nodes(phi.detach())
        scale = self._gradient_scale(crossing, squared).sqrt()
        # eps is relative to the typical |grad phi| on S, so that c * phi is the same surface
        # for every c > 0 (an absolute eps swamps |grad phi| once phi is scaled down)
        floor = self.eps * scale.detach().clamp_min(torch.finfo(phi.dtype).tiny)
        unit_norm = torch.sqrt(squared + floor**2)
        grad_norm = unit_norm * magnitude
        slope = torch.sqrt(_squared_slope(padded / magnitude) / self.spacing**2 + floor**2)
        self.register_buffer("grad_norm", grad_norm, persistent=False)
        directed_norm = torch.maximum(unit_norm, DIRECTION_FLOOR * slope)
        self.register_buffer("normal", unit_gradient / directed_norm, persistent=False)
        # the curvatures divide by it, and fade out where phi has no direction (_faded)
        self.register_buffer("_directed_norm", directed_norm * magnitude, persistent=False)
        fade = torch.where(directed_norm > unit_norm, (squared / directed_norm**2) ** 2, 1.0)
        self.register_buffer("_curvature_fade", fade, persistent=False)
        self.register_buffer("gradient_scale", scale * magnitude, persistent=False)
        weight = torch.maximum(unit_norm, WEIGHT_FLOOR * slope)
        weight = torch.maximum(weight, MINIMUM_WEIGHT * scale) * magnitude
        self.register_buffer("weight", weight, persistent=False)
        if not torch.compiler.is_compiling() and not _WARNED_ALREADY.get():
            _warn_floored_on_surface(crossing, unit_norm.detach(), scale.detach(), self.layout)
            if self.layout is None:  # bricks keep their band off the box's faces
                _warn_oblique_at_faces(crossing, self.normal.detach())
                _warn_flat_at_surface(phi.detach(), crossing, grad_norm.detach(),
                                      DISTANCE_FLOOR * (scale * magnitude).detach(),
                                      self.normal.detach(), self.spacing)
        self._phi_version = phi._version
        self.__dict__["_phi_fingerprint"] = (None if torch.compiler.is_compiling()
                                             else _fingerprint(phi))
        self._phi_required_grad = phi.requires_grad
        self.register_buffer("_mean_curvature", None, persistent=False)
        self.register_buffer("_haloed_normal", None, persistent=False)
        self.register_buffer("_haloed_weight", None, persistent=False)
        self._kept: dict[tuple, object] = {}
        self._kept_versions: dict[tuple, int | None] = {}

    @property
    def band_width(self) -> float:
        """Half-width of the band, world units. Setting it drops what flows and layers kept for
        the former width (:meth:`kept`)."""
        return self._band_width

    @band_width.setter
    def band_width(self, value: float) -> None:
        self._band_width = check_positive(value, "band_width")
        self._forget_kept()

    @property
    def eps(self) -> float:
        """The floor of ``grad_norm``, relative to :attr:`gradient_scale`. Setting it derives
        the normals and the weight again."""
        return self._eps

    @eps.setter
    def eps(self, value: float) -> None:
        self._eps = check_eps(value)
        if "phi" in self._buffers:
            self._reassemble()

    def _forget_kept(self) -> None:
        """Drop what was derived from the band (its width changed)."""
        self.__dict__.get("_kept", {}).clear()
        self.__dict__.get("_kept_versions", {}).clear()

    def get_extra_state(self) -> dict:
        """What :meth:`state_dict` holds of a surface (under ``"_extra_state"``): ``phi``
        (detached) and where it lies, every other tensor being derived from them, so that
        loading another surface's state makes this one that surface."""
        return {"phi": self.phi.detach(), "band_width": self.band_width, "eps": self.eps,
                **self._placement()}

    def _placement(self) -> dict:
        grid = self.grid
        return {"shape": grid.shape, "spacing": grid.spacing, "origin": grid.origin}

    def set_extra_state(self, state: dict) -> None:
        """Load a state of :meth:`get_extra_state`: ``phi``, its grid, band width and eps.
        ``phi`` must have this surface's shape (as a loaded buffer must); it is copied into this
        surface's dtype and device, and the geometry derived from it again."""
        if not isinstance(state, dict) or not {"phi", "band_width", "eps"} <= state.keys():
            raise ValueError(f"{type(self).__name__}: a loaded state must be the dict of "
                             "get_extra_state(), holding phi, band_width and eps")
        phi = state["phi"]
        if not isinstance(phi, Tensor) or phi.shape != self.phi.shape:
            shape = tuple(phi.shape) if isinstance(phi, Tensor) else type(phi).__name__
            raise ValueError(
                f"{type(self).__name__}: the loaded phi has shape {shape} but this surface's phi "
                f"has {tuple(self.phi.shape)}: build a surface of the loaded phi instead")
        band_width = check_positive(state["band_width"], "band_width")
        eps = check_eps(state["eps"])
        self._place(state)
        self._band_width, self._eps = band_width, eps
        self._assemble_kept(phi.detach().to(dtype=self.phi.dtype, device=self.phi.device,
                                            copy=True))

    def _place(self, state: dict) -> None:
        grid = Grid(state["shape"], state["spacing"], state["origin"])
        check_spatial_shape(self.phi, "the loaded phi", grid.shape, "its grid")
        self._grid = grid

    def forward(self, *args: object, **kwargs: object) -> Tensor:
        """Not called: a surface is the geometry operators, flows and layers are given
        (``flow(u, surface)``); calling it raises ``TypeError``."""
        raise TypeError(f"{type(self).__name__} is not called: pass it to an operator, flow or "
                        "layer, e.g. torchsurf.laplace_beltrami(u, surface) or flow(u, surface)")

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_phi_source"] = None  # the caller's view: a copy has its own phi
        # what flows derived and kept (stencils, packed bands: 25 MB on a 24^3 trefoil after
        # a few flows, against 55 kB of phi) is derived again by the copy when it needs it;
        # a DataLoader's spawned workers receive the dataset's surfaces pickled
        state["_kept"], state["_kept_versions"] = {}, {}
        if self.phi.requires_grad:
            # the geometry is in phi's graph: a copy derives its own from the copied phi (a
            # copied normal would be a leaf cut off from the copy's phi, and deepcopy refuses
            # tensors with a graph); a phi computed from others (bricks.from_dense of a phi
            # that requires grad) is copied as a leaf, as pickle copies it
            phi = self.phi
            if not phi.is_leaf:
                warnings.warn(
                    f"copying {_article(type(self).__name__)} whose phi is computed from other tensors "
                    "(it has a graph): the copy's phi is a leaf of its own, and gradients "
                    "through the copy stop there, not at what phi was computed from (copied "
                    "parameters included); build the surface from them in forward instead",
                    RuntimeWarning, stacklevel=caller_stacklevel())
                phi = phi.detach().requires_grad_()
            state["_buffers"] = {name: phi if name == "phi" else None for name in self._buffers}
            state["_phi_assembled"] = phi
            state[_DERIVE_ON_LOAD] = True
        return state

    def __setstate__(self, state: dict) -> None:
        # a copy (copy.deepcopy, pickle) holds fresh tensors, copied with the geometry derived
        # from them: it starts a new record of in-place changes
        derive = state.pop(_DERIVE_ON_LOAD, False)
        if "grid" in state and "_grid" not in state:  # pickled before 2026-12-07
            state["_grid"] = state.pop("grid")
        state.setdefault("_phi_assembled", state.get("_buffers", {}).get("phi"))
        super().__setstate__(state)
        if derive:
            self._reassemble()
        self._phi_version = self.phi._version
        self._phi_required_grad = self.phi.requires_grad
        if self._mean_curvature is not None:
            self._mean_curvature_version = self._mean_curvature._version

    def _apply(self, fn, recurse=True):  # noqa: ANN001, ANN202
        # .to(), .double(), .cuda(): the normals, the weight and what flows kept are derived
        # again from phi in its new dtype and place, as a surface built from the moved phi
        probe = fn(torch.empty(0, dtype=self.phi.dtype, device=self.phi.device))
        if probe.is_meta:
            raise NotImplementedError(
                f"{type(self).__name__} cannot move to the meta device: its normals, weight and "
                "band are derived from phi's values; the surface is left as it was")
        if probe.dtype != self.phi.dtype and probe.dtype not in SUPPORTED_DTYPES:
            # model.half(): the rest of the model converts, the surface keeps its dtype
            warnings.warn(
                f"{type(self).__name__} stays {self.phi.dtype}: torchsurf computes in float32 or "
                f"float64, not {probe.dtype} (feed it data of its dtype, or autocast)",
                RuntimeWarning, stacklevel=caller_stacklevel())
            device = probe.device
            result = super()._apply(lambda tensor: tensor.to(device), recurse)
            self._reassemble()
            return result
        before = dict(self._buffers)
        result = super()._apply(fn, recurse)
        # a move that changed nothing (.to(its device)) keeps what flows kept; a phi that
        # requires grad gets its geometry in a new graph, as it always did
        if self.phi.requires_grad or any(self._buffers[name] is not tensor
                                         for name, tensor in before.items()):
            self._reassemble()
        return result

    def _reassemble(self) -> None:
        source = self.__dict__.get("_phi_source")
        self._assemble_kept(self.phi)
        self._phi_source = source  # moved (.to()), still the caller's view's values

    def _assemble_kept(self, phi: Tensor) -> None:
        """:meth:`_assemble`, outside ``torch.inference_mode`` (:func:`outside_inference`);
        a ``phi`` made under it is copied (an inference tensor has no version counter for
        :meth:`_current_phi`), and so is a ``phi`` that does not require grad and views part
        of a larger tensor: writing the rest of its base (the next entry of a batch being
        filled) bumps the view's version counter too, so a changed version is then told from
        a change of the view by comparing the view with the copy. A ``phi`` that requires
        grad gets its geometry in its graph even under ``torch.no_grad`` or
        ``inference_mode``: a later training call's gradient to ``phi`` would otherwise miss
        the normals' and weight's part, silently."""
        tracing = torch.compiler.is_compiling()
        view = not tracing and _part_of_larger(phi)
        # the caller's view, to tell its own changes from its base's elsewhere
        self._phi_source: tuple[Tensor, int] | None = (phi, phi._version) if view else None
        with outside_inference(), torch.enable_grad() if phi.requires_grad else nullcontext():
            if view or not tracing and phi.is_inference():
                phi = phi.clone()
            self._assemble(phi)
            if phi.requires_grad and not tracing:  # traced, it would break the graph
                # formed here, in phi's graph as built: formed first inside a user's
                # torch.utils.checkpoint region (use_reentrant=False), it was kept with that
                # region's graph, the recomputation saved fewer tensors than the forward
                # (CheckpointError), and every later call through the surface failed so
                self.haloed()

    def kept(self, key: tuple, compute: Callable[[], T]) -> T:
        """``compute()``, computed on the first call with ``key`` and kept on this surface.

        What flows and layers derive from a surface once (the band's spectral bound, its
        closest-point stencils). Kept on the surface, not in a module-level table keyed by
        surfaces: ``torch.compile`` then guards on an attribute of its input, where it would
        guard on the position of the surface among a table's weak keys, which moves when
        another surface is collected (the guard then fails to build). Under ``torch.export``
        what is kept is read, and nothing new is kept: its fake tensors hold no values, and
        later calls as is read them.
        """
        if exporting():  # export's fake tensors are no values to keep for later calls
            if key in self.__dict__.get("_kept", {}):
                return self._kept[key]
            with outside_inference(), outside_transforms(self.phi):
                return compute()
        versions = self.__dict__.setdefault("_kept_versions", {})
        version = versions.get(key)
        if key not in self._kept or (version is not None and not torch.compiler.is_compiling()
                                     and self._kept[key]._version != version):
            # a kept tensor modified in place (a flow's band mask a caller narrowed) is
            # computed again: later flows would otherwise read the caller's edit
            if torch.compiler.is_compiling():
                # run as is inside a trace: a surface's bands and stencils are formed once, and
                # compiling them cost a fresh surface's first compiled call more than the layer
                # (a graph break; docs/learning.md, "A model compiled whole"). Disabled here,
                # not by a decorator, which would import torch._dynamo with this module
                torch.compiler.disable(self._keep)(key, compute)
            else:
                self._keep(key, compute)
        return self._kept[key]

    def _keep(self, key: tuple, compute: Callable[[], object]) -> None:
        """:meth:`kept`'s computation: ``compute()`` kept under ``key``."""
        with outside_inference(), outside_transforms(self.phi):
            value = compute()
        self._kept[key] = value
        self.__dict__["_kept_versions"][key] = value._version if isinstance(value, Tensor) else None

    def is_kept(self, key: tuple) -> bool:
        """Whether :meth:`kept` holds a value for ``key``."""
        return key in self._kept

    def clear_kept(self) -> None:
        """Drop what flows and layers kept on this surface (:meth:`kept`: bands, bounds,
        closest-point stencils, packed operators); the next call forms them again.

        They stay while the surface lives: one heat flow, one anisotropic flow and one
        ``LearnedDiffusion`` call grew the live memory by 36 / 55 / 77 MB on a torus at 32^3 /
        40^3 / 48^3 (an audit, 2026-12-07), so a dataset that holds hundreds of surfaces and flows each of
        them holds that much per surface (:class:`~torchsurf.datasets.SignalDataset` keeps
        the state of its last few). Call this on surfaces you keep but will not flow on
        again soon. Each band width a surface is flowed at keeps its own band, stencils and
        packed operator, and nothing drops an older width's: a sweep of 60 ``band_width``
        values grew a 32^3 sphere's kept state by 23 MB a width, to 1.4 GB (an audit,
        2026-12-07); clear it between widths.
        """
        self._forget_kept()

    def _pad(self, volume: Tensor, mode: str) -> Tensor:
        """``volume`` with a halo of one node (``mode`` at the box's faces)."""
        return stencils.pad(volume, mode)

    def _crossing_nodes(self, phi: Tensor) -> Tensor:
        """The nodes with a neighbour across S, bool, shaped like ``phi``."""
        return _crossing(phi < 0)

    def _entry_max(self, values: Tensor) -> Tensor:
        """The largest of ``values`` ``(B, 1, D, H, W)`` in each batch entry, ``(B, 1, 1, 1, 1)``."""
        return values.amax(dim=(1, 2, 3, 4), keepdim=True)

    def _gradient_scale(self, crossing: Tensor, values: Tensor) -> Tensor:
        """Median of ``values`` over the ``crossing`` nodes (:meth:`_crossing_nodes`);
        ``(B, 1, 1, 1, 1)``."""
        scales = [values[b][crossing[b]].median() for b in range(values.shape[0])]
        return torch.stack(scales).view(-1, 1, 1, 1, 1)

    def check_field(self, value: object, name: str, channels: int | None = None) -> Tensor:
        """``value`` checked as data on this surface (see :func:`check_data`)."""
        volume = check_volume(value, name, channels=channels)
        check_spatial_shape(volume, name, self.grid.shape, "surface.grid")
        check_batch(volume, name, self.batch_size, "surface")
        return volume

    @property
    def batch_size(self) -> int:
        """Number of surfaces ``B``."""
        return self.phi.shape[0]

    @property
    def spacing(self) -> float:
        """Grid spacing ``h``, world units."""
        return self.grid.spacing

    def signed_distance(self) -> Tensor:
        """Signed distance to S to first order, world units; ``(B, 1, D, H, W)``, in ``phi``'s
        graph: ``phi / max(grad_norm, DISTANCE_FLOOR * gradient_scale)``, the Newton step to S
        where ``|grad phi|`` is not far below its typical value on S (:data:`DISTANCE_FLOOR`).
        Closest points are ``x - signed_distance() * normal`` to first order."""
        return self._current_phi() / torch.maximum(self.grad_norm,
                                                   DISTANCE_FLOOR * self.gradient_scale)

    def distance(self) -> Tensor:
        """Unsigned distance to S to first order, ``|signed_distance()|`` without autograd,
        world units; ``(B, 1, D, H, W)``."""
        with torch.no_grad():
            return self.signed_distance().abs()

    def band_mask(self, width: float | None = None) -> Tensor:
        """Boolean mask of the nodes within ``width`` of S (default ``band_width``).

        Distances are :meth:`distance`'s, world units; ``(B, 1, D, H, W)``. On a
        dense grid, only nodes within ``floor(width / h) + 1`` cells (chessboard distance) of a
        node with a neighbour across S count: a node farther lies more than ``width`` from S.
        Where ``phi`` saturates (``tanh(phi / h)``, an occupancy-like field) ``|phi| / W`` is
        small far from S, and the band was the whole box (a sphere at 40^3: 64000 nodes
        against 13032 for its distance; 31080 now, 38824 with the former bound of
        ``width + sqrt(3) h``, whose outer shell of nodes kept their start through a heat
        flow: docs/band.md, section 2).
        """
        width = self.band_width if width is None else check_positive(width, "width")
        reach = width * (1 + BAND_EDGE_SLACK)
        # The closest point p of S to a node lies in a cell that S crosses, whose corners include
        # a crossing node within one cell of p along every axis: a node k cells (chessboard)
        # from the nearest crossing node is at least (k - 1) h from S. No node of a distance's
        # band is lost
        limit = math.floor(min(reach / self.spacing + 1, CROSSING_CELLS))
        return (self.distance() <= reach) & self._near_crossing(limit)

    def check_band_held(self, width: float, name: str = "width") -> None:
        """Raise ``ValueError`` naming ``name`` where :meth:`band_mask` of ``width`` would
        leave out nodes within ``width`` of S: never on a dense grid, which holds every node
        (a :class:`~torchsurf.bricks.BrickSurface` holds the bricks it was built for)."""

    def evolving_widths(self) -> tuple[float, ...]:
        """Half-width, world units, of the band flows evolve on by default, one per batch entry
        (:meth:`torchsurf.flows.Flow.evolving_width`).

        :data:`WIDE_BAND_CELLS` cells for an entry whose ``phi`` is a distance
        (``|grad phi|`` within :data:`DISTANCE_TOLERANCE` of ``gradient_scale``) at every node
        within that width of S and the ring of nodes beyond it (an analytic distance,
        ``1000 * sdf``, a phi ``redistance``d with ``band_width=7 * h``: its default 5 cells
        stop short of the ring); ``band_width`` elsewhere (``sdf.from_mesh``'s
        5-cell distances, thin features, phi that is not a distance). Kept on the surface while
        ``phi`` needs no gradient.
        """
        self._current_phi()  # the kept widths belong to phi as the surface was built
        if self.phi.requires_grad:
            return self._distance_widths()
        return self.kept(("evolving widths",), self._distance_widths)

    def _distance_widths(self) -> tuple[float, ...]:
        wide = WIDE_BAND_CELLS * self.spacing
        if wide <= self.band_width:
            return (self.band_width,) * self.batch_size
        reach = self.distance() <= wide + self.spacing * math.sqrt(3.0)
        deviation = (self.grad_norm.detach() / self.gradient_scale.detach() - 1.0).abs()
        far = ((deviation > DISTANCE_TOLERANCE) & reach).flatten(1).any(dim=1)
        return tuple(self.band_width if bool(f) else wide for f in far)

    def _near_crossing(self, cells: int) -> Tensor:
        """Nodes within ``cells`` (chessboard distance) of a node with a neighbour across S,
        ``(B, 1, D, H, W)`` bool; ``cells`` at most :data:`CROSSING_CELLS` (:meth:`band_mask`
        caps it: compared as ``uint8``, 256 would wrap to 0)."""
        found = self.kept(("cells_to_crossing",), self._crossing_cells)
        return found <= cells

    def _crossing_cells(self) -> Tensor:
        """:func:`_cells_to_crossing` of ``phi``'s values, beneath any ``torch.func`` transform
        (numpy reads them: a ``phi`` under ``jvp`` has no storage of its own)."""
        values = plain_values(self.phi)
        with outside_transforms():
            return _cells_to_crossing(values)

    def haloed(self) -> tuple[Tensor, Tensor]:
        """``normal`` and ``weight`` with a halo of one node on every side.

        ``weight`` is replicated; ``normal`` is mirrored in the box's faces
        (:func:`torchsurf.stencils.pad_mirrored`), as the octant scheme needs.

        ``(B, 3, D + 2, H + 2, W + 2)`` and ``(B, 1, D + 2, H + 2, W + 2)``, for kernels that
        read neighbours without padding (the compiled operators). Computed once and kept, on
        the same terms as :meth:`mean_curvature`.
        """
        self._current_phi()
        if self._haloed_normal is not None:
            return self._haloed_normal, self._haloed_weight
        with outside_inference(), outside_transforms(self.phi):
            normal, weight = self._haloed_geometry()
        if (torch.is_grad_enabled() or not self.phi.requires_grad) and not exporting():
            self._haloed_weight = weight  # first: readers test the normal
            self._haloed_normal = normal
        return normal, weight

    def _haloed_geometry(self) -> tuple[Tensor, Tensor]:
        return stencils.pad_mirrored(self.normal), stencils.pad(self.weight, "replicate")

    def _current_phi(self) -> Tensor:
        """``phi``, unless it was modified in place or replaced after the normals and weight
        were derived from it (they would then belong to another surface), or made to require
        grad after them (they would then be outside its graph, and its gradient would miss their part)."""
        phi = self.phi  # once: a buffer's read goes through nn.Module.__getattr__
        if not torch.compiler.is_compiling():
            refuse_vmapped_phi(phi, type(self).__name__)  # stack_module_state's phis
        # traced too (no host read); torch.export swaps every buffer for a fake of its own
        if phi is not self.__dict__.get("_phi_assembled") and not exporting():
            raise RuntimeError(
                "phi was replaced after this surface was built (assigned, or swapped in by "
                "torch.func.functional_call): its normals, weight and band belong to the former "
                "phi; build a new surface from the new phi, ImplicitSurface(phi, grid) (in a "
                "model's forward, to learn or swap phi: the surface is differentiable in it)")
        if torch.compiler.is_compiling():
            return phi
        source = self.__dict__.get("_phi_source")
        changed = phi._version != self._phi_version
        if changed and _same_values(phi, self.__dict__.get("_phi_fingerprint")):
            # written in place with its own values: an averaged model's buffers
            # (AveragedModel(use_buffers=True)), DistributedDataParallel's broadcast
            self._phi_version, changed = phi._version, False
        if not changed and source is not None and source[0]._version != source[1]:
            view = source[0].to(dtype=phi.dtype, device=phi.device)
            changed = not torch.equal(view, phi)  # or the rest of its base was
            if not changed:
                self._phi_source = (source[0], source[0]._version)
        if changed:
            raise RuntimeError(
                "phi was modified in place after this surface was built: its normals and "
                "weight belong to the former values; build a new surface from the new phi "
                "(or pass phi.clone() to keep a phi you will change)" + _ddp_hint()
            )
        if phi.requires_grad and not self._phi_required_grad:
            raise RuntimeError(
                "phi was made to require grad after this surface was built: its normals and "
                "weight are not in phi's graph, and phi's gradient would miss their part; call "
                "phi.requires_grad_() before building the surface (or build a new one)"
            )
        return phi

    def hessian(self) -> Tensor:
        """Second derivatives of ``phi``, ``(B, 6, D, H, W)`` in the order xx, yy, zz, xy, xz, yz.

        Central differences, world units (``1 / length``).
        """
        padded = self._pad(self._current_phi(), "quadratic")
        return stencils.apply(padded, stencils.HESSIAN)[:, 0] / self.spacing**2

    def _gradient(self) -> Tensor:
        """``grad phi`` where it has a direction; shortened with the normal elsewhere
        (:data:`DIRECTION_FLOOR`), so that ``_gradient() / _directed_norm`` is the normal."""
        return self.normal * self._directed_norm

    def mean_curvature(self) -> Tensor:
        """Mean curvature ``H = div n`` of the level set through each node; ``(B, 1, D, H, W)``.

        The sum of the principal curvatures (sphere of radius R: ``2 / R``), second order in the
        spacing; at the nodes of the box's faces (``phi``'s quadratic extrapolation there),
        first order where S leaves the face obliquely (a sphere whose normal there is 11
        degrees from the face's plane: 0.9% of ``2 / R`` at 97^3), second order where it meets
        it at right angles (and where its normal is 11 degrees from the face's normal).
        Second order where ``phi`` is smooth on the grid's scale (a distance, ``r^2 - R^2``);
        a ``phi`` that bends within a few cells of S keeps a fixed error (``tanh(d / 2h)``: 8%
        of ``H`` on a sphere, sampled on S, at every resolution; at the nodes within ``h / 2``
        of S the largest error grows with the resolution, 14% to 26% from 24^3 to 64^3;
        README.md, "Curvature").
        Computed once and kept (except when computed without autograd from a ``phi`` that
        requires grad, so that a later call still carries the graph; and computed again if the
        tensor returned was modified in place).
        """
        kept = self._mean_curvature
        self._current_phi()  # the kept value belongs to phi as the surface was built
        if kept is not None and (torch.compiler.is_compiling()
                                 or kept._version == self._mean_curvature_version):
            return kept
        with outside_inference(), outside_transforms(self.phi):
            value = self._faded(curvature.mean_curvature(self._gradient(), self.hessian(),
                                                         self._directed_norm))
        if ((torch.is_grad_enabled() or not self.phi.requires_grad) and not exporting()
                and not (self.phi.requires_grad and saving_through_hooks())):
            self._mean_curvature_version = value._version  # first: readers test the value
            self._mean_curvature = value
        return value

    def gaussian_curvature(self) -> Tensor:
        """Gaussian curvature ``K`` of the level set through each node; ``(B, 1, D, H, W)``.

        ``K = grad phi^T adj(Hess phi) grad phi / |grad phi|^4`` (sphere: ``1 / R^2``).
        """
        return self._faded(curvature.gaussian_curvature(self._gradient(), self.hessian(),
                                                        self._directed_norm))

    def principal_curvatures(self) -> tuple[Tensor, Tensor]:
        """Principal curvatures ``(k1, k2)``, ``k1 >= k2``, each ``(B, 1, D, H, W)``.

        Regularised at umbilics as described in :meth:`principal_directions`.
        """
        k1, k2, _, _ = self._principal()
        return k1, k2

    def principal_directions(self) -> tuple[Tensor, Tensor]:
        """Unit principal directions ``(e1, e2)`` of ``k1`` and ``k2``, each ``(B, 3, D, H, W)``.

        Tangent eigenvectors of the shape operator ``P Hess(phi) P / |grad phi|``, defined up
        to sign, orthonormal. At umbilic points (every point of a sphere) no direction is
        preferred: ``e1`` is then a fixed tangent (the coordinate axis least aligned with ``n``,
        made orthogonal to it) and the curvatures are kept at least ``eps`` =
        ``1e-6 / spacing`` apart; values and gradients stay finite. (A sampled sphere's shape
        operator is umbilic only to its discretisation error, which separates them more.)
        At a node where ``grad phi`` vanishes (the centre of a sphere or an ellipsoid centred
        on a node) ``n`` and the choice of tangent are not differentiable in ``phi``: the
        gradient there is one of the one-sided ones, and ``gradcheck`` in ``phi`` through the
        directions fails if such a node lies in the band.
        """
        _, _, e1, e2 = self._principal()
        return e1, e2

    def _principal(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        k1, k2, e1, e2 = curvature.principal(
            self.hessian(), self.normal, self._directed_norm, eps=1e-6 / self.spacing
        )
        return self._faded(k1), self._faded(k2), e1, e2

    def _faded(self, value: Tensor) -> Tensor:
        """A curvature faded out where ``phi`` has no direction (:data:`DIRECTION_FLOOR`): by
        ``(|grad phi| / floor)^4`` (the central differences, without ``eps``), exactly 1
        elsewhere. There the level set through the node is a point or a line (the centre of a
        sphere, the axis of a torus), its curvature ``tr(Hess) / |grad phi|`` unbounded and its
        derivative in ``phi`` ill-conditioned (``gradcheck`` failed on spheres centred on a
        node); faded, it goes to 0, flat at the exact centre."""
        return value * self._curvature_fade

    def extra_repr(self) -> str:
        return (
            f"batch_size={self.batch_size}, grid={self.grid}, band_width={self.band_width:g}, "
            f"eps={self.eps:g}"
        )


def check_surface(surface: object) -> ImplicitSurface:
    """Raise ``TypeError`` unless ``surface`` is an :class:`ImplicitSurface`, and
    ``RuntimeError`` if its ``phi`` was modified in place or replaced after it was built (its
    normals and weight would belong to the former ``phi``)."""
    if not isinstance(surface, ImplicitSurface):
        raise TypeError(
            f"surface must be a torchsurf.ImplicitSurface, got {type(surface).__name__}"
        )
    surface._current_phi()
    return surface


def check_data(value: object, name: str, surface: object, channels: int | None = None) -> Tensor:
    """``value`` checked as data on ``surface``: a volume ``(B, C, D, H, W)`` with the grid's spatial
    shape, batch 1 or the surface's, the surface's dtype and device (and ``channels``, if given).

    Raises ``TypeError`` or ``ValueError`` naming ``name`` (:class:`MismatchError`, both, for a
    dtype or device); returns the volume.
    """
    surface = check_surface(surface)
    volume = surface.check_field(value, name, channels)
    phi = surface.phi
    if volume.dtype != phi.dtype or volume.device != phi.device:
        raise MismatchError(
            f"{name} has dtype {volume.dtype} on {volume.device} but surface has "
            f"{phi.dtype} on {phi.device}; move one of them with .to()"
        )
    return volume


def check_direction_batch(direction: Tensor, u: Tensor, name: str,
                          surface: ImplicitSurface) -> None:
    """Raise ``ValueError`` unless a dense ``direction``'s batch is 1, ``u``'s (named ``name``)
    or the surface's: a tangent field widens the data's batch only as the surface does (``u``
    of batch 1 on a surface of batch B gives B results, with or without a field)."""
    allowed = {1, u.shape[0], surface.batch_size}
    if surface.layout is None and direction.shape[0] not in allowed:
        raise ValueError(f"direction has batch size {direction.shape[0]} but {name} has "
                         f"{u.shape[0]} and surface {surface.batch_size}: it must be 1, "
                         f"{name}'s or the surface's")


def check_direction(direction: object, u0: Tensor, surface: ImplicitSurface,
                    region: Tensor) -> Tensor:
    """``direction`` checked as a flow's tangent field for ``u0``: data on ``surface`` with 3
    channels, batch 1, ``u0``'s or the surface's (dense), finite where the flow reads it
    (``region``, bool, the flow's band and its ring).

    Raises:
        ValueError: naming ``direction``, its shape and what was expected.
    """
    field = check_data(direction, "direction", surface, channels=3)
    check_direction_batch(field, u0, "u0", surface)
    if not torch.compiler.is_compiling():
        check_finite(torch.where(region, field, 0.0), "direction (in the band and its ring)")
        check_tangential(field, surface, region, "direction")
    return field


def check_tangential(field: Tensor, surface: ImplicitSurface, region: Tensor,
                     name: str) -> None:
    """Raise naming ``name`` where most of a batch entry's ``region`` (bool) holds no part of
    ``field`` ``(B, 3, ...)`` tangent to the level sets (a zero field, or one along the
    normals): :func:`tangent_unit` sends it to 0 there, and a flow would not diffuse along it
    (or would follow rounding), without a word. Isolated zeros (a sphere's tangent field has
    some) are fine. Not checked while ``torch.compile`` traces (a host read)."""
    if torch.compiler.is_compiling():
        return
    tangent, squared = _tangential_part(field.detach(), surface.normal.detach())
    none = (tangent**2).sum(dim=1, keepdim=True) <= TANGENT_FLOOR**2 * squared
    region = region.expand_as(none)
    layout = surface.layout
    share = _per_entry(none & region, layout) / _per_entry(region, layout).clamp_min(1)
    if bool((share > 0.5).any()):
        worst = float(share.max())
        raise ValueError(
            f"{name} has no part tangent to the level sets at {worst:.0%} of the band's "
            "nodes (it is zero, or along the normals, there), where the flow would follow "
            "nothing but rounding; give a field with a tangent part (e.g. "
            "torchsurf.signals.principal_direction, swirl_field)")


def _tangential_part(field: Tensor, normal: Tensor) -> tuple[Tensor, Tensor]:
    """``P T`` of ``field`` ``(B, 3, ...)`` and ``|T|^2`` ``(B, 1, ...)``."""
    squared = (field**2).sum(dim=1, keepdim=True)
    return tangential_part(field, normal), squared


def tangent_unit(field: Tensor, surface: ImplicitSurface) -> Tensor:
    """``P T / |P T|``: ``field`` ``(B, 3, D, H, W)`` made tangent to the level sets and unit.

    Where ``|P T|`` falls below about ``TANGENT_FLOOR |T|`` (``T`` along the normal) the
    result goes smoothly to 0. The floor is relative to ``|T|`` at each node, so ``c T`` gives
    the same result for every ``c > 0`` (an absolute floor shrank a field of size 1e-12 by a
    quarter).

    Raises:
        ValueError: naming ``field`` unless it is data on ``surface`` with 3 channels
            (:class:`MismatchError` for another dtype or device).
    """
    field = check_data(field, "field", surface, channels=3)
    tangent, squared = _tangential_part(field, surface.normal)
    floor = TANGENT_FLOOR**2 * squared + torch.finfo(field.dtype).tiny
    return tangent / torch.sqrt((tangent**2).sum(dim=1, keepdim=True) + floor)


TANGENT_FLOOR = 1e-6
"""Below this fraction of ``|T|``, :func:`tangent_unit` lets ``P T`` shrink to 0 (its
derivative there is about ``1 / (TANGENT_FLOOR |T|)``)."""
