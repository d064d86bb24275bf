"""Sampling of volumes at world points (mesh vertices, probes): trilinear or tricubic."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.autograd import forward_ad

from ._checks import MismatchError, check_batch, check_choice, check_finite, check_tensor, check_volume
from ._transforms import batched_by_vmap, functorch_levels
from .grid import Grid

__all__ = [
    "FACE_CELLS",
    "INTERPOLATIONS",
    "SAMPLE_CHUNK",
    "UNREAD_WEIGHT",
    "cubic_lagrange_weights",
    "sample",
    "weighted_taps",
]

INTERPOLATIONS = ("linear", "cubic")
"""Values of :func:`sample`'s ``interpolation``."""

SAMPLE_CHUNK = 2**15
"""Points whose ``4^3`` taps are gathered at once by the tricubic sampler (about 1.5 kB of
temporaries a point and channel)."""

FACE_CELLS = 1e-3
"""Linear reads of points within this many cells of a face of the box (or beyond) go through
their cell's polynomial; the others through ``torch.nn.functional.grid_sample``, which is
faster but clamps points on a face into the box with no gradient across it."""

# Points this many cells outside the grid's box are still accepted (their boundary cell's
# polynomial extended to them), so that points on the boundary survive floating-point rounding.
_OUTSIDE_TOLERANCE = 1e-4


def cubic_lagrange_weights(t: Tensor) -> list[Tensor]:
    """Lagrange weights of the nodes at offsets -1, 0, 1, 2 for a point at ``t`` (fractions of a
    cell from node 0: in [0, 1] between the middle nodes, in [-1, 0] or [1, 2] for a one-sided
    stencil): exact for cubic polynomials, each weight shaped like ``t``."""
    return [
        -t * (t - 1) * (t - 2) / 6,
        (t + 1) * (t - 1) * (t - 2) / 2,
        -(t + 1) * t * (t - 2) / 2,
        (t + 1) * t * (t - 1) / 6,
    ]


def sample(field: Tensor, points: Tensor, grid: Grid, interpolation: str = "linear") -> Tensor:
    """Trilinear (default) or tricubic interpolation of ``field`` at world ``points``.

    ``"linear"``: exact for fields linear in ``(x, y, z)``, error ``O(h^2)``
    (``torch.nn.functional.grid_sample`` with ``align_corners=True``, so the first and last
    nodes sit exactly at the grid's box; within :data:`FACE_CELLS` of a face, the cell's own
    polynomial). ``"cubic"``: tensor-product Lagrange interpolation on
    the ``4^3`` nodes around each point (the stencil of the flows' closest-point
    re-extension), exact for polynomials of degree 3 in each coordinate, error ``O(h^4)``,
    up to the box's faces (in the first and last cell of an axis the four nodes are the
    first or last four: one-sided; along an axis of three nodes, linear, exact for degree 1
    there).
    Reading a second-order solution trilinearly adds an ``O(h^2)`` error of the read-out's
    own, often larger than the solution's (heat flow on a sphere at 65^3, RKC's default
    steps: 1.2e-3 read trilinearly, 2.6e-4 tricubically; docs/benchmarks.md). Both are
    differentiable with respect to ``field`` and ``points``, also at points on the box's faces
    and corners (the gradient of the cell inside).

    Args:
        field: ``(B, C, D, H, W)`` values at the nodes of ``grid``.
        points: ``(V, 3)`` or ``(B, V, 3)`` world ``(x, y, z)``, inside the grid's box; same
            dtype and device as ``field``. A batch of 1 on either side broadcasts.
        grid: the grid ``field`` is sampled on.
        interpolation: ``"linear"`` or ``"cubic"``.

    Returns:
        ``(B, C, V)``.

    Raises:
        ValueError: a point lies outside the grid's box by more than 1e-4 of a cell and the
            rounding of world points in their dtype (:meth:`~torchsurf.Grid.world_rounding`:
            cells in float32 far from the origin).
        NotImplementedError: under ``torch.func.vmap`` (the box check and the choice of
            points read near a face are host decisions: batch along ``B`` instead, with
            ``points`` ``(B, V, 3)``); forward mode with ``"linear"`` (``grid_sample`` has no
            forward derivative; ``"cubic"`` has). ``torch.func.grad`` and reverse mode run.

    Example:
        >>> import torch
        >>> grid = Grid.cube(5, bound=1.0)
        >>> x = grid.points()[..., 0][None, None]            # the field u = x
        >>> sample(x, torch.tensor([[0.3, -0.2, 0.1]]), grid)
        tensor([[[0.3000]]])
    """
    if not isinstance(grid, Grid):
        raise TypeError(f"grid must be a torchsurf.Grid, got {type(grid).__name__}")
    check_choice(interpolation, "interpolation", INTERPOLATIONS)
    check_volume(field, "field")
    check_tensor(points, "points")
    if tuple(field.shape[-3:]) != grid.shape:
        packed = (" (a packed field of bricks? sample it with its BrickSurface's .sample)"
                  if tuple(field.shape[-3:]) == (8, 8, 8) else "")
        raise ValueError(
            f"field has spatial shape {tuple(field.shape[-3:])} but grid has {grid.shape}; "
            f"they must agree{packed}"
        )
    if points.dim() not in (2, 3) or points.shape[-1] != 3:
        raise ValueError(
            f"points must have shape (V, 3) or (B, V, 3), got {tuple(points.shape)}"
        )
    if points.dtype != field.dtype or points.device != field.device:
        raise MismatchError(
            f"points ({points.dtype}, {points.device}) must have the dtype and device of "
            f"field ({field.dtype}, {field.device})"
        )
    _refuse_transforms(interpolation, field, points)
    check_finite(points, "points")
    index = grid.world_to_index(points)  # once: the box's test and both reads derive from it
    _check_inside(points, index, grid)
    if points.dim() == 2:
        points, index = points[None], index[None]
    check_batch(points, "points", field.shape[0], "field")
    batch = max(field.shape[0], points.shape[0])
    field = field.expand(batch, -1, -1, -1, -1)
    index = index.expand(batch, -1, -1)
    if interpolation == "cubic":
        return _interpolate(field, index, cubic=True)
    # grid.world_to_normalized(points), from the index it computes
    normalized = 2.0 * index / index.new_tensor(field.shape[:1:-1]).sub(1) - 1.0
    values = F.grid_sample(field, normalized[:, :, None, None, :], mode="bilinear",
                           padding_mode="border", align_corners=True)[:, :, :, 0, 0]
    # grid_sample clamps a point on a face (or rounded onto it) into the box, with no gradient
    # across the face: those points are read through their cell's own polynomial instead; so
    # are non-finite values, which grid_sample also takes from taps of weight zero
    sizes = torch.tensor(field.shape[:1:-1], device=index.device, dtype=index.dtype)
    near_face = ((index.detach() <= FACE_CELLS) | (index.detach() >= sizes - 1 - FACE_CELLS))
    redone = near_face.any(dim=-1).any(dim=0) | ~torch.isfinite(values.detach()).all(1).all(0)
    columns = redone.nonzero()[:, 0]
    if len(columns) == 0:
        return values
    return values.index_copy(2, columns, _interpolate(field, index[:, columns], cubic=False))


def _refuse_transforms(interpolation: str, field: Tensor, points: Tensor) -> None:
    """Name :func:`sample` where a transform of its inputs would fail inside it with PyTorch's
    generic message ("data-dependent control flow" for a batch of ``vmap``; grid_sample's for a
    linear read's tangent); transforms of other tensors around a call pass. Nothing while
    ``torch.compile`` traces (the queries are C functions dynamo cannot trace)."""
    if torch.compiler.is_compiling():
        return
    if any(batched_by_vmap(tensor) for tensor in (field, points)):
        raise NotImplementedError(
            "sample does not run under torch.func.vmap: which points lie in the box, and which "
            "are read near its faces, are decided on the host; batch along B instead (field "
            "(B, C, D, H, W) with points (B, V, 3); docs/learning.md, 'Derivatives')")
    if interpolation == "linear" and any(
            forward_ad.unpack_dual(level).tangent is not None
            for tensor in (field, points) for level in functorch_levels(tensor)):
        raise NotImplementedError(
            "sample(interpolation='linear') has no forward-mode derivative (PyTorch's "
            "grid_sample has none): use interpolation='cubic', or reverse mode "
            "(docs/learning.md, 'Derivatives')")


def _interpolate(field: Tensor, index: Tensor, cubic: bool) -> Tensor:
    """Trilinear or tricubic Lagrange values of ``field`` ``(B, C, D, H, W)`` at fractional
    node indices ``index`` ``(B, V, 3)`` (``x, y, z``); ``(B, C, V)``.

    A point's weights are polynomials in its offset from a base node that is fixed by the
    point's cell alone (clamped into the box, never by the point's own clamping), so a point on
    a face of the box has the gradient of the cell inside it, as any other point of that cell.
    """
    sizes = field.shape[:1:-1]  # W, H, D: the sizes along x, y, z
    # cubic: the second of the stencil's four nodes (base - 1 .. base + 2), the cell's first
    # node moved in beside the faces along an axis of four nodes or more so that all four lie
    # in the box (one-sided there, still exact for cubics); a shorter axis, and every axis of
    # the linear read, keeps the cell (a point on the last face at t = 1) and is linear in it
    base = torch.stack([index[..., axis].detach().floor().clamp(
        *((1, size - 3) if cubic and size >= 4 else (0, max(size - 2, 0))))
        for axis, size in enumerate(sizes)], dim=-1)
    fraction = index - base
    offsets = torch.arange(-1, 3, device=field.device) if cubic else torch.arange(0, 2, device=field.device)
    nodes, weights = [], []
    for axis, size in enumerate(sizes):
        nodes.append((base[..., axis, None].long() + offsets).clamp(0, size - 1))  # (B, V, taps)
        t = fraction[..., axis]
        if not cubic:
            weights.append(torch.stack([1 - t, t], dim=-1))
        elif size >= 4:
            weights.append(torch.stack(cubic_lagrange_weights(t), dim=-1))
        else:
            zero = torch.zeros_like(t)
            weights.append(torch.stack([zero, 1 - t, t, zero], dim=-1))
    (x, y, z), (wx, wy, wz) = nodes, weights
    height, width = field.shape[-2:]
    flat = field.flatten(2)
    results = []
    for start in range(0, max(index.shape[1], 1), SAMPLE_CHUNK):  # one (empty) chunk for no point
        part = slice(start, start + SAMPLE_CHUNK)
        taps = ((z[:, part, :, None, None] * height + y[:, part, None, :, None]) * width
                + x[:, part, None, None, :]).flatten(2)  # (B, v, taps^3)
        tap_weights = (wz[:, part, :, None, None] * wy[:, part, None, :, None]
                       * wx[:, part, None, None, :]).flatten(2)
        gathered = flat.gather(2, taps.flatten(1)[:, None].expand(-1, flat.shape[1], -1))
        gathered = gathered.view(*flat.shape[:2], *taps.shape[1:])
        values = (gathered * tap_weights[:, None]).sum(dim=-1)
        if not bool(torch.isfinite(values.detach()).all()):  # read, or at a tap of weight 0?
            values = weighted_taps(gathered, tap_weights[:, None], max(sizes) - 1).sum(dim=-1)
        results.append(values)
    return torch.cat(results, dim=-1)


UNREAD_WEIGHT = 8.0
"""A tap whose weight is within this many units of its dtype's rounding times the grid's
largest index of zero is not read (:func:`weighted_taps`): a point on a node whose index
``world_to_index`` rounds (spacing 0.08125) left weights of 1e-16, not 0."""


def weighted_taps(values: Tensor, weights: Tensor, largest_index: int) -> Tensor:
    """``values * weights`` (broadcast), with the products of non-finite values at taps whose
    weight is zero to rounding (:data:`UNREAD_WEIGHT`) set to zero: a point on a node or a
    cell's face does not read them, and a NaN or inf a field marks beyond its band would
    otherwise make its value NaN. The samplers take it only where the plain products' sum is
    not finite (it costs four more passes over the taps). The backward is the plain
    product's: gradients of finite values are unchanged, and the gradient to the weights (the
    points) at such a tap is NaN, as the value beyond the point it would need is unknown."""
    unread = UNREAD_WEIGHT * torch.finfo(weights.dtype).eps * max(largest_index, 1)
    return _WeightedTaps.apply(values, weights, unread)


class _WeightedTaps(torch.autograd.Function):
    """:func:`weighted_taps`; its derivatives are the plain product's (also under
    ``torch.func``'s transforms)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(values: Tensor, weights: Tensor, unread: float) -> Tensor:
        skipped = ~torch.isfinite(values) & (weights.abs() <= unread)
        return torch.where(skipped, values.new_zeros(()), values * weights)

    @staticmethod
    def setup_context(ctx, inputs: tuple, output: Tensor) -> None:  # noqa: ANN001
        values, weights, _ = inputs
        ctx.save_for_backward(values, weights)
        ctx.save_for_forward(values, weights)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, Tensor | None, None]:  # noqa: ANN001
        values, weights = ctx.saved_tensors
        to_values = (grad * weights).sum_to_size(values.shape) if ctx.needs_input_grad[0] \
            else None
        to_weights = (grad * values).sum_to_size(weights.shape) if ctx.needs_input_grad[1] \
            else None
        return to_values, to_weights, None

    @staticmethod
    def jvp(ctx, values_tangent: Tensor | None, weights_tangent: Tensor | None,  # noqa: ANN001
            _: object) -> Tensor:
        values, weights = ctx.saved_tensors
        terms = [tangent * other for tangent, other in ((values_tangent, weights),
                                                         (weights_tangent, values))
                 if tangent is not None]
        return terms[0] if len(terms) == 1 else terms[0] + terms[1]


def _check_inside(points: Tensor, index: Tensor, grid: Grid) -> None:
    """Raise ``ValueError`` naming a point of ``points`` ``(V, 3)`` or ``(B, V, 3)`` (world;
    ``index``, their node indices) outside the grid's box (:meth:`Grid.contains`)."""
    index = index.detach()
    outside = ~grid.contains_index(index, _OUTSIDE_TOLERANCE + grid.world_rounding(index.dtype))
    if bool(outside.any()):
        first = tuple(int(i) for i in outside.nonzero()[0])
        low = grid.origin
        high = tuple(o + s for o, s in zip(grid.origin, grid.size, strict=True))
        raise ValueError(
            f"points: {int(outside.sum())} of {outside.numel()} points lie outside the grid's "
            f"box {low} to {high}, e.g. points[{', '.join(map(str, first))}] = "
            f"{points[first].tolist()}"
        )
