"""Extension of data off the surface, constant along the normals (the paper's §2).

Two ways:

- ``"closest_point"``: ``u(x) <- u(x - d(x) n(x))``, ``d = surface.signed_distance()``
  (``phi / max(|grad phi|, 0.5 s)``, ``s = surface.gradient_scale``), the value at the
  (first-order) closest point of S, read by trilinear interpolation (Ruuth & Merriman 2008)
  or, with ``interpolation="cubic"``, tricubic at the closest point refined on the
  interpolated phi (:mod:`._closest`). One pass; nodes on S keep their values up to
  the interpolation error, ``O(h^2)`` or ``O(h^4)``. Across the band the closest points add
  theirs: on an exact distance the central-difference normal's ``O(h^2)`` error moves them
  by ``|phi| O(h^2)``, so tricubic extension is third order there (sphere R = 0.8, data
  constant along the normals, 24^3 / 48^3 / 96^3: 5.2e-3, 4.0e-4, 3.8e-5; fourth order on
  ``r^2 - R^2``, whose differences are exact); and where ``phi`` is not a distance the
  first-order closest point misses S by ``O(phi^2)``, a fraction of a cell too small for the
  refinement to act, so data that varies along the normals is extended at second order,
  tricubic no better than trilinear (``r^2 - R^2``: 1.0e-2 for both at 96^3). Where the
  level sets of ``phi`` are not parallel to S (not a function of the distance alone), the
  point also misses the foot of the normal along S by ``O(phi^2)``, which the refinement does
  not see: tricubic is then second order even for data constant along the normals, no better
  than trilinear (a sphere R = 0.7 with ``phi = (r - R)(1 + x / 2)``, 20^3 / 40^3 / 80^3:
  1.4e-1, 3.3e-2, 7.8e-3 either way, against 4.4e-5 tricubic at 80^3 on its distance; an
  ellipsoid's ``sum (x_i / a_i)^2 - 1``: 1.2e-2 at 80^3). Redistance such ``phi``
  (:func:`torchsurf.sdf.redistance`) where the extension's accuracy matters.
  Near a face of the box the taps are clamped into it: with S 0.3 cells from the faces, the
  nodes whose closest point lies within 2 cells of a face were extended at first order
  tricubic (7.1e-3, 3.0e-3, 1.4e-3 at 20^3 / 40^3 / 80^3), second order trilinear
  (5.0e-3, 1.2e-3, 3.0e-4).
- ``"pde"``: ``u_t + sign(phi) n . grad u = 0`` with first-order upwind differences, stepped at
  CFL number 1/2 until the largest change per step falls below ``tolerance`` (the paper's §2).
  Information flows outwards from S, so nodes where ``phi = 0`` are not changed at all.

Both update only the band ``|phi| <= width`` and keep ``u`` elsewhere, and its nodes with no
normal (``grad phi`` zero there to rounding: the mid-plane of a slab thinner than two cells on
the nodes) keep their values too. Both run on a
:class:`~torchsurf.bricks.BrickSurface` (packed fields), with the dense results' values.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .. import _memory, backend, stencils
from .._as_is import run_as_is_first
from .._checks import check_choice, check_count, check_finite, check_flag, check_positive
from .._native import carries_tangents
from .._transforms import refuse_transforms
from ..bricks.layout import BRICK, BrickLayout
from ..sampling import cubic_lagrange_weights
from ..surface import ImplicitSurface, check_data
from . import _closest, _limiter, _native_gather
from ._integrators import with_ring

Limit = bool | Literal["eager"]
"""Where a tricubic kernel limits its values (:mod:`._limiter`): ``False`` nowhere, ``True``
in every form, ``"eager"`` in the eager forms only, which hold the 64 taps' values anyway (the
compiled forms then return ``(3, C, N)``: the value and its cell's least and greatest node
values, and leave the limiting to :func:`._limiter.clamp_outside_range`: see
:func:`_limit_flag`)."""

METHODS = ("closest_point", "pde")


INTERPOLATIONS = ("linear", "cubic")


def closest_point_extension(
    u: Tensor, surface: ImplicitSurface, width: float | None = None,
    interpolation: str = "linear", mask: Tensor | None = None, path: str = "auto",
) -> Tensor:
    """``u(x - d n)`` inside the band, ``d = surface.signed_distance()``, interpolated from the
    grid (module docstring).

    Args:
        u: ``(B, C, D, H, W)``; ``surface`` has batch 1 or B. On a
            :class:`~torchsurf.bricks.BrickSurface`, a packed field ``(N, C, 8, 8, 8)``.
        surface: the implicit surface.
        width: half-width of the band to extend in, world units (default the surface's).
        interpolation: ``"linear"`` (trilinear, error ``O(h^2)``: repeated every few steps
            of a flow, it smooths the data and costs second-order flows their accuracy; it
            reads the nodes of the cell around each point, up to ``sqrt(3)`` cells from S) or
            ``"cubic"`` (tricubic Lagrange on the 4^3 nodes around each point, error
            ``O(h^4)`` at the point, third order across the band (module docstring),
            evaluated at band nodes only; it reads nodes up to ``2 sqrt(3)``
            cells from S, beyond a narrower band; its stencil for the band of ``width`` is
            formed at the first call and kept on the surface while ``phi`` needs no gradient).
        mask: bool ``(B or 1, 1, D, H, W)`` (packed ``(N, 1, 8, 8, 8)`` on bricks): the nodes
            to extend to, instead of the band of ``width``.
        path: how the tricubic gather runs (:data:`torchsurf.backend.PATHS`: ``"slicing"``
            never compiles it); the trilinear extension is one ``grid_sample`` on every path.

    Returns:
        ``(B, C, D, H, W)`` (packed ``(N, C, 8, 8, 8)`` on bricks: the dense result's values).

    Like a PyTorch function, it reads no values to check them: NaN or infinity where it reads
    ``u`` reaches every node whose interpolation reads it (one node of a tricubic extension:
    about a hundred). :class:`Extension` and the flows refuse such ``u``, naming it.
    """
    refuse_transforms("closest_point_extension", u, phi=getattr(surface, "phi", None))
    check_data(u, "u", surface)
    check_choice(interpolation, "interpolation", INTERPOLATIONS)
    check_choice(path, "path", backend.PATHS)
    if width is not None and mask is not None:
        raise ValueError("give width or mask, not both: mask names the nodes to extend to, "
                         "instead of the band of width")
    band = _band_to_extend(surface, width) if mask is None else _check_mask(mask, u, surface)
    if interpolation == "cubic":
        if mask is not None or surface.phi.requires_grad:  # weights in phi's graph
            return cubic_stencil(surface, band).apply(u, path)
        # kept: forming it took 7x its application (0.086 against 0.012 s at 64^3)
        return surface.kept(stencil_key(width, "extension", False),
                            lambda: cubic_stencil(surface, band)).apply(u, path)
    if surface.layout is not None:
        return _brick_linear_extension(u, surface, band)
    refuse_transforms("closest_point_extension(interpolation='linear') on a dense volume", u,
                      refused=(), forward_mode=False,
                      why="PyTorch's grid_sample has none; interpolation='cubic' has one")
    closest = _closest_indices(surface, u.dtype)
    batch = max(u.shape[0], closest.shape[0])
    last = closest.new_tensor([n - 1 for n in reversed(surface.grid.shape)])
    sampled = F.grid_sample(
        u.expand(batch, -1, -1, -1, -1),
        (2.0 * closest / last - 1.0).expand(batch, -1, -1, -1, -1),
        mode="bilinear",
        padding_mode="border",
        align_corners=True,
    )
    return torch.where(band, sampled, u)


def stencil_key(width: float | None, kind: str, limited: bool) -> tuple:
    """The key under which a closest-point stencil of the band of half-width ``width`` is kept
    on its surface (``kind`` names its mask: ``"region"``, ``"ring"``, ``"extension"``)."""
    return ("closest-point stencil", width, kind, bool(limited))


def _band_to_extend(surface: ImplicitSurface, width: float | None) -> Tensor:
    """``surface.band_mask(width)``; on bricks, refused (naming ``width``) where it would leave
    out nodes the bricks cannot stencil (:meth:`~torchsurf.bricks.BrickSurface.check_band_held`):
    they would keep their values."""
    if width is not None:
        surface.check_band_held(check_positive(width, "width"))
    return surface.band_mask(width)


def _check_mask(mask: object, u: Tensor, surface: ImplicitSurface) -> Tensor:
    """``mask`` if it is a bool tensor ``(B or 1, 1, D, H, W)`` matching ``u`` (packed
    ``(N, 1, 8, 8, 8)`` on bricks); raises naming ``mask`` otherwise."""
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        kind = mask.dtype if isinstance(mask, Tensor) else type(mask).__name__
        raise TypeError(f"mask must be a bool tensor, got {kind}")
    if surface.layout is not None:
        fits = mask.shape == (u.shape[0], 1, *u.shape[2:])
        expected = f"({u.shape[0]}, 1, {', '.join(map(str, u.shape[2:]))})"
    else:
        fits = (mask.dim() == 5 and mask.shape[1] == 1 and mask.shape[2:] == u.shape[2:]
                and mask.shape[0] in (1, u.shape[0], surface.batch_size))
        expected = f"(B or 1, 1, {', '.join(map(str, u.shape[2:]))})"
    if not fits:
        raise ValueError(f"mask must have shape {expected}, like u {tuple(u.shape)}; got "
                         f"{tuple(mask.shape)}")
    if mask.device != u.device:
        raise ValueError(f"mask is on {mask.device} but u is on {u.device}: they must match")
    return mask


TIE_EPS = 64
"""A fractional index within ``TIE_EPS`` units of rounding (relative to its size) below a node
plane counts as on it (:func:`_cell`)."""


def _cell(at: Tensor) -> Tensor:
    """The first node of the cell that holds each fractional index ``at``, a point within
    rounding below a node plane taken as on it. A closest point on a face aligned with the grid
    lies on a node plane exactly; rounding would put it in either cell, and the limiter's range
    (that cell's 8 nodes) with it: the snap makes the choice the same in any frame (a shape
    scaled and moved with its grid)."""
    at = at.detach()
    slack = TIE_EPS * torch.finfo(at.dtype).eps * (1.0 + at.abs())
    return (at + slack).floor()


def _cubic_stencil(at: Tensor, targets: Tensor, shape: tuple[int, int, int]
                   ) -> tuple[Tensor, Tensor, Tensor]:
    """The tricubic interpolation of one volume of ``shape`` at ``at``, for the nodes
    ``targets``.

    Stored by axis: the 4 node indices and 4 Lagrange weights along each of ``x, y, z``
    (96 bytes per node in float32), from which the 64 taps are formed where they are read.

    Args:
        at: ``(N, 3)`` fractional ``(x, y, z)`` node indices of the points to read.
        targets: ``(N,)`` flat indices of the nodes to fill.
        shape: ``(D, H, W)``.

    Returns:
        ``targets``; ``corners`` ``(3, N, 4)`` the node indices along ``x, y, z`` around each
        point (clamped to the box: replicated data); ``weights`` ``(3, N, 4)`` their Lagrange
        weights (in ``at``'s graph).
    """
    depth, height, width = shape
    base = _cell(at)
    offsets = torch.arange(-1, 3, device=at.device)
    corners = torch.stack([
        (base[:, axis: axis + 1].long() + offsets).clamp(0, size - 1)
        for axis, size in enumerate((width, height, depth))
    ])
    if depth * height * width < 2**31:
        corners = corners.to(torch.int32)
    weights = torch.stack([torch.stack(cubic_lagrange_weights(at[:, axis] - base[:, axis]), dim=1)
                           for axis in range(3)])
    return targets, corners, weights


def tap_weights(weights: Tensor) -> Tensor:
    """The 64 tap weights ``(N, 64)`` (tap ``(z, y, x)`` at ``16 z + 4 y + x``) of separable tricubic
    ``weights`` ``(3, N, 4)`` (x, y, z)."""
    wx, wy, wz = weights.unbind(0)
    return (wz[:, :, None, None] * wy[:, None, :, None] * wx[:, None, None, :]).flatten(1)


def _dense_tap_indices(corners: Tensor, height: int, width: int) -> Callable[[slice], Tensor]:
    """Flat positions ``(n, 64)`` of the taps of a slice of a dense stencil's nodes."""
    def taps(part: slice) -> Tensor:
        x, y, z = corners[:, part].long().unbind(0)
        return ((z[:, :, None, None] * height + y[:, None, :, None]) * width
                + x[:, None, None, :]).flatten(1)
    return taps


def _dense_part(surface: ImplicitSurface, index: Tensor, mask: Tensor, readable: Tensor | None,
                entry: int) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """One volume's stencil: the masked nodes' closest points (``index`` ``(D, H, W, 3)``,
    first order) refined (:mod:`._closest`), without the nodes whose taps leave ``readable``
    ``(D, H, W)`` (when given); and their 64 tap positions where :class:`CubicStencil` keeps
    them (formed once, for that check too), else ``None``."""
    targets = mask.reshape(-1).nonzero().squeeze(1)
    distance = surface.signed_distance()[entry, 0] / surface.spacing
    read = _closest.dense_reader(distance, surface.normal[entry])
    at = _closest.refine(index.reshape(-1, 3)[targets], read)
    targets, corners, weights = _cubic_stencil(at, targets, mask.shape)
    taps = _dense_tap_indices(corners, *mask.shape[1:])
    sources = None
    if len(targets) <= KEEP_SOURCES_NODES:
        small = math.prod(mask.shape) < 2**31
        sources = taps(slice(None)).to(torch.int32 if small else torch.long)
        taps = sources.__getitem__
    if readable is None:
        return targets, corners, weights, sources
    keep = _closest.taps_inside(readable.reshape(-1), taps, len(targets))
    if bool(keep.all()):
        return targets, corners, weights, sources
    return (targets[keep], corners[:, keep], weights[:, keep],
            None if sources is None else sources[keep])


def _interpolate_gathered(flat: Tensor, corners: Tensor, weights: Tensor, height: int,
                          width: int, limited: Limit, *, path: str = "slicing") -> Tensor:
    """``sum_k w_k flat[:, source_k]`` over the 64 taps of each node, ``(C, N)``, optionally
    limited (:mod:`._limiter`); ``corners`` and ``weights`` ``(3, N, 4)``.

    Eagerly: one gather of ``(C, N, 64)``, fewest operations.
    """
    x, y, z = corners.long().unbind(0)
    sources = ((z[:, :, None, None] * height + y[:, None, :, None]) * width
               + x[:, None, None, :]).flatten(1)
    return _gathered_sum(flat, sources, weights, limited)


def _gathered_sum(flat: Tensor, sources: Tensor, weights: Tensor, limited: Limit) -> Tensor:
    """The tricubic sum of ``flat[:, sources]`` (``sources`` ``(N, 64)``, int32 or int64, in
    the order ``16 z + 4 y + x``) with separable ``weights`` ``(3, N, 4)``; limited unless
    ``limited`` is ``False`` (:data:`Limit`: the eager forms)."""
    taps = tap_weights(weights)
    # index_select takes int32 sources as they are kept, and gathers twice as fast as
    # flat[:, sources] (30k nodes, 4 channels: 37 against 80 ms, one thread)
    gathered = flat.index_select(1, sources.flatten()).view(flat.shape[0], *sources.shape)
    value = (gathered * taps).sum(dim=-1)
    if limited:
        value = _limiter.clamp_gathered(value, gathered, weights)
    return value


def _summed_terms(tap: Callable[[int, int, int], Tensor], weights: Tensor, limited: Limit,
                  by_offset: bool = False) -> Tensor:
    """The tricubic sum as 64 terms ``tap(k, j, i)`` (the values at offsets ``k, j, i`` along
    z, y, x), with separable ``weights`` ``(3, N, 4)`` (``(3, 4, N)`` if ``by_offset``):
    compiled, one loop over the nodes; limited only if ``limited is True``. With ``limited ==
    "eager"``, ``(3, C, N)``: the value, then the least and greatest of its cell's 8 nodes
    (:data:`Limit`), for the caller to limit the few values outside that range."""
    wx, wy, wz = (w.t() if by_offset else w for w in weights.unbind(0))
    value = None
    taps: list[Tensor] = []
    for k in range(4):
        for j in range(4):
            weight = wz[:, k] * wy[:, j]
            for i in range(4):
                values = tap(k, j, i)
                taps.append(values)
                term = (weight * wx[:, i]) * values
                value = term if value is None else value + term
    if limited == "eager":
        cell = [taps[position] for position in _limiter.CELL]
        least = most = cell[0]
        for node in cell[1:]:
            least, most = torch.minimum(least, node), torch.maximum(most, node)
        return torch.stack((value, least, most))
    if limited is True:
        low, high = _limiter.corner_extremes_of_taps(taps)
        corners = _limiter.corner_weights(wx, wy, wz).t()
        lower, upper = _limiter.bounds_of_lists(low, high, list(corners))
        magnitude = low[0].abs()
        for extreme in (*low[1:], *high):
            magnitude = torch.maximum(magnitude, extreme.abs())
        value = _limiter.limit(value, lower, upper, magnitude)
    return value


def _interpolate_terms(flat: Tensor, corners: Tensor, weights: Tensor, height: int, width: int,
                       limited: Limit) -> Tensor:
    """The same as 64 gathered terms: compiled, one loop over the nodes with no ``(N, 64)``
    temporary of indices or weights (1.9 ms against 2.9 ms at 81^3, one thread)."""
    x, y, z = corners.long().unbind(0)

    def tap(k: int, j: int, i: int) -> Tensor:
        return flat[:, (z[:, k] * height + y[:, j]) * width + x[:, i]]

    return _summed_terms(tap, weights, limited)


GATHER_COMPILE_WEIGHT = 4.0
"""Compiling a tricubic gather (dynamic shapes) costs about four times a Laplace–Beltrami's,
the compiler's start-up included: about 35 s with an empty inductor cache (float64, a 40^3
bunny's band; docs/benchmarks.md, "Compile weights"): :attr:`backend.Kernel.compile_weight`."""


_INTERPOLATION = backend.Kernel(
    "tricubic_interpolation", _interpolate_gathered, _interpolate_terms, lambda *args: args,
    dynamic=True, trusted_indices=True, compile_weight=GATHER_COMPILE_WEIGHT,
)


class CubicStencil:
    """Tricubic closest-point interpolation, assembled once, applied to any data.

    ``apply(u)`` replaces ``u`` at the masked nodes by the tricubic interpolant of ``u`` at
    their closest points on S: the same numbers as :func:`closest_point_extension` with
    ``interpolation="cubic"``, at the cost of one gather of 64 values per node.

    Args:
        surface: the implicit surface (batch 1 or B).
        mask: ``(B or 1, 1, D, H, W)`` bool, the nodes to fill.
        limited: clamp each value to bounds within the range of its taps, continuous in the
            point (:mod:`torchsurf.flows._limiter`), so that re-extension never creates a new
            extremum (data with jumps, maximum principle).
        readable: ``(B or 1, 1, D, H, W)`` bool, the nodes the stencil may read; a masked node
            whose taps leave it is left out (it keeps its value): only where ``phi`` is not a
            distance, once its closest point is refined (:mod:`torchsurf.flows._closest`).
            ``None``: every node may be read.
    """

    def __init__(self, surface: ImplicitSurface, mask: Tensor, limited: bool = False,
                 readable: Tensor | None = None) -> None:
        self.limited = check_flag(limited, "limited")
        index = _closest_indices(surface, surface.phi.dtype)
        batch = max(index.shape[0], mask.shape[0])
        parts = [
            _dense_part(surface, index[min(b, index.shape[0] - 1)],
                        mask[min(b, mask.shape[0] - 1), 0],
                        None if readable is None else readable[min(b, readable.shape[0] - 1), 0],
                        min(b, surface.phi.shape[0] - 1))
            for b in range(batch)
        ]
        self.parts = [part[:3] for part in parts]
        self._lay_out(mask.shape, [part[3] for part in parts])

    def restricted(self, mask: Tensor, limited: bool = False) -> CubicStencil:
        """This stencil at the nodes of ``mask`` alone (``(B or 1, 1, D, H, W)`` bool, within
        the mask it was formed for), ``limited`` as in the constructor: what
        :func:`cubic_stencil` forms for ``mask`` with the same ``readable``, row for row (a
        node's closest point, taps and weights are its own), without forming them again."""
        stencil = CubicStencil.__new__(CubicStencil)
        stencil.limited = check_flag(limited, "limited")
        stencil.parts, sources = [], []
        for b, (targets, corners, weights) in enumerate(self.parts):
            keep = mask[min(b, mask.shape[0] - 1), 0].reshape(-1)[targets]
            stencil.parts.append((targets[keep], corners[:, keep], weights[:, keep]))
            sources.append(None if self.sources[b] is None else self.sources[b][keep])
        stencil._lay_out(mask.shape, sources)
        return stencil

    def _lay_out(self, shape: torch.Size, sources: list[Tensor | None]) -> None:
        """The gathers' forms of :attr:`parts` in a volume of ``shape`` (``sources``: each
        part's tap positions where already formed)."""
        # each node's 64 flat tap positions, kept (4 bytes a tap) up to KEEP_SOURCES_NODES
        # nodes: the eager gather then skips forming them at every call
        height, width = shape[-2:]
        small = math.prod(shape[-3:]) < 2**31
        self.sources = [
            given if given is not None else
            _dense_tap_indices(corners, height, width)(slice(None)).to(
                torch.int32 if small else torch.long)
            if len(targets) <= KEEP_SOURCES_NODES else None
            for given, (targets, corners, _) in zip(sources, self.parts, strict=True)
        ]
        # where no tap is clamped at the box's faces, the 64 taps sit at fixed offsets from
        # the first: the compiled gather then loads one index a node instead of 64
        offsets = _dense_tap_indices(torch.arange(4).expand(3, 1, 4), height, width)(
            slice(None))[0]
        self.anchors = [
            None if kept is None or not bool((kept == kept[:, :1] + offsets.to(kept)).all())
            else kept[:, 0].contiguous()
            for kept in self.sources
        ]
        self.weights_by_offset = [
            None if anchors is None else weights.transpose(1, 2).contiguous()
            for anchors, (_, _, weights) in zip(self.anchors, self.parts, strict=True)
        ]
        self._separable: dict[int, _native_gather.SeparableStencil] = {}

    def apply(self, u: Tensor, path: str = "auto", in_place: bool = False) -> Tensor:
        """``u`` ``(B, C, D, H, W)`` with the masked nodes re-extended; a new tensor.

        ``path``: how the gather runs (:data:`torchsurf.backend.PATHS`; the flow's own path).
        ``in_place``: write the masked nodes into ``u`` itself (contiguous, batch no smaller
        than the stencil's, outside autograd) and return it: each volume's values are all read
        before any is written, so the result is the same, without a copy of the volume.
        """
        check_choice(path, "path", backend.PATHS)
        if in_place and (not u.is_contiguous() or u.shape[0] < len(self.parts)):
            in_place = False
        batch = max(u.shape[0], len(self.parts))
        results = []
        for b in range(batch):
            part = min(b, len(self.parts) - 1)
            targets = self.parts[part][0]
            volume = u[min(b, u.shape[0] - 1)]
            flat = volume.reshape(volume.shape[0], -1).contiguous()  # channels-last: a view
            value = self._native_values(part, flat) if path == "auto" else None
            if value is None:
                value = self._gathered_values(part, volume, flat, path)
            if in_place:
                flat.index_copy_(1, targets, value)
            else:
                results.append(flat.index_copy(1, targets, value).reshape(volume.shape))
        return u if in_place else torch.stack(results)

    def _gathered_values(self, part: int, volume: Tensor, flat: Tensor, path: str) -> Tensor:
        """The values ``(C, n)`` of :attr:`parts` ``[part]`` at its nodes by the eager or
        compiled gathers of ``flat`` ``(C, M)``, the flat view of ``volume`` ``(C, D, H, W)``."""
        _, corners, weights = self.parts[part]
        height, width = volume.shape[-2:]
        weights = weights.to(volume.dtype)
        limit = _limit_flag(self.limited)
        if self.anchors[part] is not None:
            value, taken = backend.run_on_path(
                _ANCHORED_INTERPOLATION, path, volume[None], flat, self.sources[part],
                self.anchors[part], self.weights_by_offset[part].to(volume.dtype),
                height * width, width, limit)
        elif self.sources[part] is not None:
            value, taken = backend.run_on_path(_KEPT_INTERPOLATION, path, volume[None], flat,
                                               self.sources[part], weights, limit)
        else:
            value, taken = backend.run_on_path(_INTERPOLATION, path, volume[None], flat,
                                               corners, weights, height, width, limit)
        if limit == "eager" and taken == "compiled":
            kept = self.sources[part]
            taps = (_dense_tap_indices(corners, height, width) if kept is None
                    else kept.__getitem__)
            value = _limiter.clamp_outside_range(*value.unbind(0), flat, taps, weights)
        return value

    def _native_values(self, part: int, flat: Tensor) -> Tensor | None:
        """The limited values ``(C, n)`` of :attr:`parts` ``[part]`` by the C kernel of the
        packed band's stencils (:func:`._native_gather.limited_rows`, a channel at a time:
        no copy of the volume), or ``None`` where it does not run (not limited, tap positions
        not kept in 32 bits, a gradient to record, to the data or from ``phi`` to the
        weights, or a forward-mode tangent, not the CPU, no compiler). The compiled
        gathers and the eager limiter took 0.8 of a reaction–diffusion step's re-extension
        (spots on a 48^3 bunny); the layout is formed at the first call and kept."""
        if torch.compiler.is_compiling():  # a traced flow traces the gathers
            return None
        kept = self.sources[part]
        targets, _, weights = self.parts[part]
        if (not self.limited or kept is None or kept.dtype != torch.int32
                or (torch.is_grad_enabled() and (flat.requires_grad or weights.requires_grad))
                or carries_tangents(flat, weights)):
            return None
        if part not in self._separable:
            self._separable[part] = _native_gather.SeparableStencil(
                kept, weights, _limiter.corner_weights(*weights.unbind(0)),
                torch.arange(len(targets), device=targets.device))
        stencil = self._separable[part]
        values = []
        for channel in flat:
            value = _native_gather.limited_rows(channel[:, None], stencil)
            if value is None:
                return None
            values.append(value[:, 0])
        return torch.stack(values)

    def transpose(self, v: Tensor, in_place: bool = False) -> Tensor:
        """The transpose of :meth:`apply` (``limited=False`` only, where it is linear).

        ``v`` ``(B, C, D, H, W)`` with each masked node's value zeroed and scattered back, with
        its 64 tricubic weights, to the nodes :meth:`apply` reads it from; a new tensor, or
        ``v`` itself written over if ``in_place`` (as in :meth:`apply`).
        """
        if self.limited:
            raise ValueError("CubicStencil.transpose: a limited stencil is not linear")
        in_place = in_place and v.is_contiguous()
        results = []
        for b in range(v.shape[0]):
            targets, corners, weights = self.parts[min(b, len(self.parts) - 1)]
            volume = v[b]
            height, width = volume.shape[-2:]
            flat = volume.reshape(volume.shape[0], -1).contiguous()  # channels-last: a view
            x, y, z = corners.long().unbind(0)
            sources = ((z[:, :, None, None] * height + y[:, None, :, None]) * width
                       + x[:, None, None, :]).flatten()
            taps = tap_weights(weights.to(v.dtype))
            moved = (flat[:, targets, None] * taps).flatten(1)
            if in_place:
                flat.index_fill_(1, targets, 0.0).index_add_(1, sources, moved)
            else:
                kept = flat.index_fill(1, targets, 0.0)
                results.append(kept.index_add(1, sources, moved).reshape(volume.shape))
        return v if in_place else torch.stack(results)


def _corner_base(bases: list[Tensor], second: tuple[Tensor, Tensor, Tensor], k: int, j: int,
                 i: int) -> Tensor:
    """The first packed index of the brick that holds tap ``(k, j, i)``: one of the (at most)
    8 bricks a 4^3 block meets, picked by whether the tap lies in the second brick per axis."""
    z, y, x = second
    low = torch.where(z[:, k], bases[4], bases[0]), torch.where(z[:, k], bases[5], bases[1])
    high = torch.where(z[:, k], bases[6], bases[2]), torch.where(z[:, k], bases[7], bases[3])
    pair = (torch.where(y[:, j], high[0], low[0]), torch.where(y[:, j], high[1], low[1]))
    return torch.where(x[:, i], pair[1], pair[0])


def _brick_sources(bases: Tensor, second: Tensor, local: Tensor) -> Tensor:
    """The packed index of each of the 64 taps of each node, ``(M, 64)`` in the order
    ``16 z + 4 y + x``, from a :class:`BrickCubicStencil`'s ``bases``, ``second`` and ``local``:
    each tap's brick is the node's ``4 z + 2 y + x`` of its (at most) 8, picked by whether the
    tap lies in the second brick per axis (as :func:`_corner_base`, in one gather)."""
    z, y, x = (bit.long() for bit in second.unbind(0))
    corner = 4 * z[:, :, None, None] + 2 * y[:, None, :, None] + x[:, None, None, :]
    zl, yl, xl = local.long().unbind(0)
    offset = zl[:, :, None, None] + yl[:, None, :, None] + xl[:, None, None, :]
    count = corner.shape[0]
    return bases.long().t().gather(1, corner.view(count, 64)) + offset.view(count, 64)


def _brick_gathered(flat: Tensor, bases: Tensor, second: Tensor, local: Tensor, weights: Tensor,
                    limited: Limit, *, path: str = "slicing") -> Tensor:
    """Bricks' :func:`_interpolate_gathered`: one gather of ``(C, M, 64)``."""
    return _gathered_sum(flat, _brick_sources(bases, second, local), weights, limited)


def _brick_terms(flat: Tensor, bases: Tensor, second: Tensor, local: Tensor, weights: Tensor,
                 limited: Limit) -> Tensor:
    """Bricks' :func:`_interpolate_terms`: compiled; each tap's brick is picked among its
    node's 8 by comparisons, not looked up (3x faster at 96^3)."""
    corners = [b.long() for b in bases.unbind(0)]
    bits = second.unbind(0)
    zl, yl, xl = local.long().unbind(0)

    def tap(k: int, j: int, i: int) -> Tensor:
        return flat[:, _corner_base(corners, bits, k, j, i) + zl[:, k] + yl[:, j] + xl[:, i]]

    return _summed_terms(tap, weights, limited)


_BRICK_INTERPOLATION = backend.Kernel(
    "tricubic_interpolation_bricks", _brick_gathered, _brick_terms, lambda *args: args,
    dynamic=True, trusted_indices=True, compile_weight=GATHER_COMPILE_WEIGHT,
)


def _kept_gathered(flat: Tensor, sources: Tensor, weights: Tensor, limited: Limit, *,
                   path: str = "slicing") -> Tensor:
    """:func:`_brick_gathered` from the kept ``(M, 64)`` packed sources of each node."""
    return _gathered_sum(flat, sources, weights, limited)


def _kept_terms(flat: Tensor, sources: Tensor, weights: Tensor, limited: Limit) -> Tensor:
    """:func:`_brick_terms` from the kept ``(M, 64)`` packed sources: one load a tap instead
    of picking its brick among 8 (4x faster at 128^3, identical numbers)."""

    def tap(k: int, j: int, i: int) -> Tensor:
        return flat[:, sources[:, 16 * k + 4 * j + i].long()]

    return _summed_terms(tap, weights, limited)


_KEPT_INTERPOLATION = backend.Kernel(
    "tricubic_interpolation_kept", _kept_gathered, _kept_terms, lambda *args: args,
    dynamic=True, trusted_indices=True, compile_weight=GATHER_COMPILE_WEIGHT,
)


def _anchored_gathered(flat: Tensor, sources: Tensor, anchors: Tensor, weights: Tensor,
                       plane: int, row: int, limited: Limit, *, path: str = "slicing") -> Tensor:
    """A dense stencil without clamped taps, eagerly: the kept sources' gather (``weights``
    ``(3, 4, N)``)."""
    return _gathered_sum(flat, sources, weights.transpose(1, 2), limited)


def _anchored_terms(flat: Tensor, sources: Tensor, anchors: Tensor, weights: Tensor,
                    plane: int, row: int, limited: Limit) -> Tensor:
    """The same compiled: tap ``(k, j, i)`` at ``anchor + k plane + j row + i`` (one index
    load a node instead of 64; 1.1 against 1.5 ms a band re-extension at 37^3, one thread),
    ``weights`` ``(3, 4, N)``."""
    anchor = anchors.long()

    def tap(k: int, j: int, i: int) -> Tensor:
        return flat[:, anchor + (k * plane + j * row + i)]

    return _summed_terms(tap, weights, limited, by_offset=True)


_ANCHORED_INTERPOLATION = backend.Kernel(
    "tricubic_interpolation_anchored", _anchored_gathered, _anchored_terms,
    lambda *args: args, dynamic=True, trusted_indices=True,
    compile_weight=GATHER_COMPILE_WEIGHT,
)


STENCIL_CHUNK = 2**17
"""Nodes whose brick stencil is assembled at once (about 1 kB of temporaries a node)."""

APPLY_CHUNK = 2**18
"""Nodes a brick stencil's application gathers at once: the temporaries of the gather (the
compiled kernel's index buffers, about 250 bytes a node; the eager ``(C, n, 64)`` values and
indices) stay bounded by the chunk, not the band (the band's re-extension of a 512^3 bunny,
4.6 M nodes: 1.1 GB of them at once, the flow's peak memory 4.13 -> 3.19 GB)."""

KEEP_SOURCES_NODES = 2**20
"""A brick stencil of at most this many nodes keeps the packed index of each of its 64 taps
(256 bytes a node, 256 MB at most) instead of forming them at every application: 4x faster
(65,574 ring nodes of the bunny at 128^3, two channels: 8.8 ms against 38 ms). Larger
stencils (the band and ring of a 512^3 bunny, 1.1 M ring nodes) form them, to keep memory to
about 125 bytes a node (docs/bricks.md: 512^3 under 4 GB)."""


class BrickCubicStencil:
    """:class:`CubicStencil` on a :class:`~torchsurf.bricks.BrickSurface`: the same numbers at
    the same nodes (to rounding), reading packed fields ``(N, C, 8, 8, 8)``.

    Applied on the CPU with no gradient to record, under ``path="auto"``, by a C kernel that
    reads this compact form (:func:`._native_gather.brick_tricubic`: no ``(n, 64)`` tap
    positions formed, nothing compiled); otherwise by the eager or compiled gathers.

    Each node keeps the first packed index of the (at most) 8 bricks its 4^3 taps meet, and per
    axis whether each tap lies in the second brick, its in-brick offset and its weight (about
    125 bytes per node); where the gathers run, a stencil of at most
    :data:`KEEP_SOURCES_NODES` nodes also keeps the packed index of each tap (256 bytes more a
    node, 4x faster to gather). Taps are clamped to
    each entry's box, as the dense stencil replicates its data.

    Args:
        surface: a :class:`~torchsurf.bricks.BrickSurface`.
        mask: ``(N, 1, 8, 8, 8)`` bool, the nodes to fill.
        limited: as in :class:`CubicStencil`.
        readable: ``(N, 1, 8, 8, 8)`` bool, as in :class:`CubicStencil` (taps in bricks that
            are not stored are outside it).

    Raises:
        ValueError: without ``readable``, a tap falls in a brick that is not stored (a closest
            point too near the edge of the stored band).
    """

    def __init__(self, surface: ImplicitSurface, mask: Tensor, limited: bool = False,
                 readable: Tensor | None = None) -> None:
        self.limited = check_flag(limited, "limited")
        self.targets = mask.reshape(-1).nonzero().squeeze(1)
        distance = surface.signed_distance() / surface.spacing
        fields = _closest.brick_fields(distance, surface.normal)
        parts = [self._assemble(surface, self.targets[start: start + STENCIL_CHUNK], distance,
                                fields)
                 for start in range(0, len(self.targets), STENCIL_CHUNK)]
        if not parts:
            parts = [self._assemble(surface, self.targets, distance, fields)]
        del fields
        self.bases, self.second, self.local, self.weights = (
            torch.cat(pieces, dim=1) for pieces in zip(*parts, strict=True))
        if readable is not None:
            keep = _native_gather.brick_taps_readable(self.bases, self.second, self.local,
                                                      readable.reshape(-1))
            if keep is None:
                keep = _closest.taps_inside(readable.reshape(-1), self._tap_indices,
                                            len(self.targets))
            if not bool(keep.all()):
                self.targets = self.targets[keep]
                self.bases, self.second, self.local, self.weights = (
                    part[:, keep] for part in (self.bases, self.second, self.local, self.weights))
        elif bool((self.bases < 0).any()):
            raise ValueError(
                "closest-point re-extension reads nodes outside the stored bricks: build the "
                "BrickSurface with torchsurf.bricks.from_dense or from_mesh at this band width"
            )
        self._sources: Tensor | None = None

    def restricted(self, mask: Tensor, limited: bool = False) -> BrickCubicStencil:
        """:meth:`CubicStencil.restricted` on bricks: ``mask`` ``(N, 1, 8, 8, 8)`` bool."""
        stencil = BrickCubicStencil.__new__(BrickCubicStencil)
        stencil.limited = check_flag(limited, "limited")
        keep = mask.reshape(-1)[self.targets]
        stencil.targets = self.targets[keep]
        stencil.bases, stencil.second, stencil.local, stencil.weights = (
            part[:, keep] for part in (self.bases, self.second, self.local, self.weights))
        stencil._sources = None if self._sources is None else self._sources[keep]
        return stencil

    @property
    def sources(self) -> Tensor | None:
        """The packed position of each node's 64 taps, ``(n, 64)``, for a stencil of at most
        :data:`KEEP_SOURCES_NODES` nodes (else ``None``): formed at the first use by the
        gathers or the backward and kept; the C kernel of ``path="auto"`` needs none."""
        if self._sources is None and len(self.targets) <= KEEP_SOURCES_NODES:
            self._sources = torch.cat([
                self._tap_indices(slice(start, start + STENCIL_CHUNK)).to(self.bases.dtype)
                for start in range(0, max(len(self.targets), 1), STENCIL_CHUNK)
            ])
        return self._sources

    def _gathered(self, u: Tensor, flat: Tensor, weights: Tensor, path: str, part: slice
                  ) -> Tensor:
        """The values ``(C, n)`` at the nodes ``part`` by the eager or compiled gathers."""
        limit = _limit_flag(self.limited)
        if self.sources is not None:
            value, taken = backend.run_on_path(_KEPT_INTERPOLATION, path, u, flat,
                                               self.sources[part], weights[:, part], limit)
        else:
            value, taken = backend.run_on_path(
                _BRICK_INTERPOLATION, path, u, flat, self.bases[:, part],
                self.second[:, part], self.local[:, part], weights[:, part], limit)
        if limit == "eager" and taken == "compiled":
            value = self._clamp_outside_range(value, flat, part, weights[:, part])
        return value

    def _clamp_outside_range(self, value: Tensor, flat: Tensor, part: slice,
                             weights: Tensor) -> Tensor:
        """:func:`._limiter.clamp_outside_range` for a slice of the nodes, ``value`` the
        compiled interpolation's ``(3, C, n)``."""
        if self.sources is not None:
            return _limiter.clamp_outside_range(*value.unbind(0), flat,
                                                self.sources[part].__getitem__, weights)
        first = part.start

        def taps(nodes: Tensor) -> Tensor:
            return _brick_sources(self.bases[:, first + nodes], self.second[:, first + nodes],
                                  self.local[:, first + nodes])

        return _limiter.clamp_outside_range(*value.unbind(0), flat, taps, weights)

    def _tap_indices(self, part: slice) -> Tensor:
        """Packed positions ``(n, 64)`` of the taps of a slice of the nodes, negative for a
        tap in a brick that is not stored."""
        return _brick_sources(self.bases[:, part], self.second[:, part], self.local[:, part])

    @staticmethod
    def _assemble(surface: ImplicitSurface, targets: Tensor, distance: Tensor,
                  fields: list[Tensor]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The stencil of ``targets`` (packed node indices), read from the surface's fields at
        those nodes only; ``distance`` is the packed ``phi / (W h)``, ``fields`` the
        closest points' reads (:func:`._closest.brick_fields`). Bases of bricks that are not
        stored are negative."""
        layout = surface.layout
        device = surface.phi.device
        index, batch = _brick_closest_indices(surface, targets, distance)
        shapes = torch.tensor([g.shape[::-1] for g in layout.grids], device=device)[batch]
        lookup = layout.lookup.to(device)
        at = _closest.refine(index, _closest.brick_reader(fields, lookup, batch, shapes))
        extent_z, extent_y, extent_x = layout.extent
        base = _cell(at)
        offsets = torch.arange(-1, 3, device=device)
        x, y, z = ((base[:, axis: axis + 1].long() + offsets).clamp(
            torch.zeros_like(shapes[:, axis: axis + 1]), shapes[:, axis: axis + 1] - 1)
            for axis in range(3))
        block = ((batch[:, None] * extent_z + z // BRICK) * extent_y * extent_x,
                 (y // BRICK) * extent_x, x // BRICK)
        lookup = lookup.reshape(-1)
        bases = torch.stack([lookup[block[0][:, a] + block[1][:, b] + block[2][:, c]]
                             for a in (0, 3) for b in (0, 3) for c in (0, 3)])
        bases = bases * BRICK**3
        if len(layout) * BRICK**3 < 2**31:
            bases = bases.to(torch.int32)
        second = torch.stack([part != part[:, :1] for part in block])
        local = torch.stack([(z % BRICK) * BRICK * BRICK, (y % BRICK) * BRICK,
                             x % BRICK]).to(torch.int16)
        weights = torch.stack([
            torch.stack(cubic_lagrange_weights(at[:, axis] - base[:, axis]), dim=1) for axis in range(3)
        ])
        return bases, second, local, weights

    def apply(self, u: Tensor, path: str = "auto") -> Tensor:
        """``u`` ``(N, C, 8, 8, 8)`` with the masked nodes re-extended; a new tensor.

        ``path``: how the gather runs (:data:`torchsurf.backend.PATHS`; the flow's own path).
        """
        check_choice(path, "path", backend.PATHS)
        channels = u.shape[1]
        flat = u.transpose(0, 1).reshape(channels, -1).contiguous()  # channels-last: a view
        weights = self.weights.to(u.dtype)
        value = self._interpolated(u, flat, weights, path)
        result = flat.index_copy(1, self.targets, value)
        return result.view(channels, *u.shape[:1], *u.shape[2:]).transpose(0, 1)

    def _interpolated(self, u: Tensor, flat: Tensor, weights: Tensor, path: str) -> Tensor:
        """The values ``(C, n)`` at the masked nodes: by the C kernel where it runs (in one
        call, into one tensor: it needs no temporaries), else by the eager or compiled
        gathers, :data:`APPLY_CHUNK` nodes at a time."""
        if path == "auto" and len(self.targets) > 0:
            value = _native_gather.brick_tricubic(flat, self.bases, self.second, self.local,
                                                  weights, self.limited, slice(None))
            if value is not None:
                return value
        values = [self._gathered(u, flat, weights, path, slice(start, start + APPLY_CHUNK))
                  for start in range(0, max(len(self.targets), 1), APPLY_CHUNK)]
        return values[0] if len(values) == 1 else torch.cat(values, dim=1)

    def transpose(self, v: Tensor) -> Tensor:
        """The transpose of :meth:`apply` (``limited=False`` only, where it is linear), as
        :meth:`CubicStencil.transpose`: ``v`` ``(N, C, 8, 8, 8)`` with each masked node's value
        zeroed and scattered back, with its 64 tricubic weights, to the nodes :meth:`apply`
        reads it from; a new tensor. Scattered :data:`STENCIL_CHUNK` nodes at a time."""
        if self.limited:
            raise ValueError("BrickCubicStencil.transpose: a limited stencil is not linear")
        channels = v.shape[1]
        flat = v.transpose(0, 1).reshape(channels, -1).contiguous()  # channels-last: a view
        result = flat.index_fill(1, self.targets, 0.0)
        weights = self.weights.to(v.dtype)
        for start in range(0, len(self.targets), STENCIL_CHUNK):
            part = slice(start, start + STENCIL_CHUNK)
            sources = _brick_sources(self.bases[:, part], self.second[:, part],
                                     self.local[:, part])
            taps = tap_weights(weights[:, part])
            moved = flat[:, self.targets[part], None] * taps
            result = result.index_add(1, sources.flatten(), moved.flatten(1))
        return result.view(channels, *v.shape[:1], *v.shape[2:]).transpose(0, 1)


def _brick_closest_indices(surface: ImplicitSurface, targets: Tensor,
                           distance: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """``x - d n`` (``d = surface.signed_distance()``) at the packed node indices ``targets``
    ``(M,)`` of a brick surface, in continuous node indices ``(M, 3)`` ``(i, j, k)`` of each
    node's entry's grid, and each node's batch entry ``(M,)``. ``distance``: the packed
    ``d / h`` if already formed.

    Formed as the dense :func:`_closest_indices`, with the same rounding, so that the limiter
    of a stencil picks the same cell."""
    layout = surface.layout
    device, dtype = surface.phi.device, surface.phi.dtype
    row = targets // BRICK**3
    batch = layout.batch.to(device)[row]
    inside = targets % BRICK**3
    local_index = torch.stack([inside // (BRICK * BRICK), (inside // BRICK) % BRICK,
                               inside % BRICK], dim=1)
    nodes = (layout.coords.to(device)[row] * BRICK + local_index).flip(1).to(dtype)

    def at_targets(field: Tensor) -> Tensor:
        return field.reshape(field.shape[0], field.shape[1], -1)[row, :, inside]

    normal = at_targets(surface.normal)
    if distance is None:
        distance = surface.signed_distance() / surface.spacing
    distance = at_targets(distance)[:, 0]
    return nodes - distance[:, None] * normal, batch


def _brick_linear_extension(u: Tensor, surface: ImplicitSurface, mask: Tensor) -> Tensor:
    """The trilinear closest-point extension of a packed ``u`` ``(N, C, 8, 8, 8)`` at the
    nodes of ``mask`` (:meth:`~torchsurf.bricks.BrickSurface.sample` at their closest points,
    entry by entry)."""
    targets = mask.reshape(-1).nonzero().squeeze(1)
    index, batch = _brick_closest_indices(surface, targets)
    channels = u.shape[1]
    flat = u.transpose(0, 1).reshape(channels, -1)
    value = flat.new_zeros((channels, len(targets)))
    for entry in range(surface.batch_size):
        selected = (batch == entry).nonzero().squeeze(1)
        if not len(selected):
            continue
        points = index[selected].to(u.dtype)
        if not bool(surface.samplable_at_index(points, entry).all()):
            raise ValueError(
                "closest-point extension reads nodes outside the stored bricks (or the box) at "
                "some nodes of mask: give a mask within the band, or build the BrickSurface "
                "with torchsurf.bricks.from_dense or from_mesh at a wider band width"
            )
        value = value.index_copy(1, selected, surface.sample_at_index(u, points, entry))
    result = flat.index_copy(1, targets, value)
    return result.view(channels, *u.shape[:1], *u.shape[2:]).transpose(0, 1)


def _limit_flag(limited: bool) -> Limit:
    """Where a limited stencil's kernels clamp their values themselves (:data:`Limit`): in
    every form where an outer ``torch.compile`` traces them (no data-dependent shapes);
    otherwise in the eager forms only, which hold the 64 taps and test the values against
    their cells' ranges at little cost. After a compiled form, which
    returns each cell's range beside the value, :func:`._limiter.clamp_outside_range` limits
    the few values outside their cell's range
    (1% of random data, 0.01% of smooth data): the bounds cost 2.4x the compiled
    interpolation where every node forms them."""
    if not limited:
        return False
    return True if torch.compiler.is_compiling() else "eager"


def cubic_stencil(surface: ImplicitSurface, mask: Tensor, limited: bool = False,
                  readable: Tensor | None = None) -> CubicStencil | BrickCubicStencil:
    """The closest-point stencil for ``surface``'s storage: dense or bricks; the nodes of
    ``mask`` where the normal has no direction (:func:`._closest.has_direction`) are left out
    and keep their values."""
    mask = mask & _closest.has_direction(surface)
    if surface.layout is not None:
        return BrickCubicStencil(surface, mask, limited, readable)
    return CubicStencil(surface, mask, limited, readable)


def _read_by(stencil: CubicStencil | BrickCubicStencil, like: Tensor) -> Tensor:
    """The nodes ``stencil`` reads, a bool mask shaped like ``like`` (``(B or 1, 1, D, H, W)``,
    or packed ``(N, 1, 8, 8, 8)``)."""
    if isinstance(stencil, BrickCubicStencil):
        read = torch.zeros(like.numel(), dtype=torch.bool, device=like.device)
        for start in range(0, len(stencil.targets), STENCIL_CHUNK):
            taps = stencil._tap_indices(slice(start, start + STENCIL_CHUNK)).long().flatten()
            read[taps[taps >= 0]] = True
        return read.view(like.shape)
    height, width = like.shape[-2:]
    read = torch.zeros(len(stencil.parts), like[0].numel(), dtype=torch.bool, device=like.device)
    for b, (targets, corners, _) in enumerate(stencil.parts):
        taps = _dense_tap_indices(corners, height, width)
        for start in range(0, len(targets), STENCIL_CHUNK):
            read[b, taps(slice(start, start + STENCIL_CHUNK)).flatten()] = True
    return read.view(len(stencil.parts), *like.shape[1:])


def _closest_indices(surface: ImplicitSurface, dtype: torch.dtype) -> Tensor:
    """``x - d n``, ``d = surface.signed_distance()``, at every node, in continuous node
    indices ``(B, D, H, W, 3)`` ``(i, j, k)``.

    Formed in index units (node index minus ``d n / h``), never in world coordinates: in
    float32 a grid far from the world's origin would otherwise round every closest point to
    a fraction of a cell (``eps * |origin| / h``)."""
    depth, height, width = surface.grid.shape
    device = surface.phi.device
    z, y, x = torch.meshgrid(*(torch.arange(n, dtype=dtype, device=device)
                               for n in (depth, height, width)), indexing="ij")
    nodes = torch.stack([x, y, z], dim=-1)
    step = (surface.signed_distance() / surface.spacing) * surface.normal
    return nodes - step.permute(0, 2, 3, 4, 1)


def _upwind_step(u: Tensor, velocity: Tensor, spacing: float, cfl: float,
                 layout: BrickLayout | None) -> Tensor:
    """One upwind step of ``u_t + velocity . grad u = 0``; ``velocity`` ``(B or 1, 3, D, H, W)``
    (packed ``(N, 3, 8, 8, 8)`` with ``layout``)."""
    padded = stencils.pad(u, "replicate") if layout is None else layout.halo(u, 1)
    forward = stencils.apply(padded, stencils.FORWARD) / spacing
    backward = stencils.apply(padded, stencils.BACKWARD) / spacing
    c = velocity[:, None]
    derivative = torch.where(c > 0, backward, forward)
    dt = cfl * spacing / 3.0
    return u - dt * (c * derivative).sum(dim=2)


def _volume_max(x: Tensor, layout: BrickLayout | None) -> Tensor:
    """The largest value of each volume and channel of ``x``, shaped to broadcast over it:
    ``(B, C, 1, 1, 1)``; with ``layout``, each brick gets its batch entry's, ``(N, C, 1, 1, 1)``."""
    return x.amax(dim=(2, 3, 4), keepdim=True) if layout is None else layout.entry_max(x)


def pde_extension(
    u: Tensor,
    surface: ImplicitSurface,
    width: float | None = None,
    tolerance: float = 1e-6,
    max_steps: int | None = None,
) -> Tensor:
    """``u_t + sign(phi) n . grad u = 0`` marched in the band (upwind, CFL 1/2): the paper's
    extension, information carried away from S along the normals.

    ``sign(phi)`` is smoothed as ``d / sqrt(d^2 + h^2)``, ``d`` the signed distance
    (:meth:`~torchsurf.surface.ImplicitSurface.signed_distance`, world units whatever the
    scale of ``phi``). The step is ``dt = h / 6``
    (``|n|_1 <= sqrt 3``, so the CFL number is at most 1/2). Each volume and channel stops
    when the largest change of a step is at most ``tolerance`` times the range of ``u`` over
    its band (so ``u + c`` is extended as ``u``, plus ``c``); the loop ends when all have, or
    after ``max_steps`` (default: enough to cross the band twice).

    The discrete march has no exact steady state: the smoothed sign lets the nodes next to S
    exchange values across it, and the upwind scheme's numerical diffusion smears the data on
    S a little more with every step (a sphere at 40^3, error against the exact extension: 2.1e-2
    at the default 46 steps, 4.1e-2 at 200, 1.1e-1 at 1000). Prefer
    :func:`closest_point_extension` (tricubic: 1.3e-3 over the band there, 3.0e-4 within a
    cell of S) unless the paper's method itself
    is wanted; keep ``max_steps`` near its default.

    On a :class:`~torchsurf.bricks.BrickSurface` each batch entry and channel stops on its own
    too, on the range over its band: the dense result.

    Args:
        u: ``(B, C, D, H, W)``, or packed ``(N, C, 8, 8, 8)`` on bricks.
        surface: the implicit surface.
        width: half-width of the band, world units (default the surface's).
        tolerance: relative change per step at which to stop.
        max_steps: upper bound on the steps.

    Returns:
        ``u``'s shape.
    """
    refuse_transforms("pde_extension", u, phi=getattr(surface, "phi", None))
    check_data(u, "u", surface)
    check_positive(tolerance, "tolerance")
    h = surface.spacing
    width = surface.band_width if width is None else check_positive(width, "width")
    if max_steps is None:
        max_steps = int(12 * width / h) + 10
    else:
        max_steps = check_count(max_steps, "max_steps")
    band = _band_to_extend(surface, width)
    distance = surface.signed_distance()  # world units, whatever the scale of phi
    sign = distance / torch.sqrt(distance**2 + h**2)
    velocity = sign * surface.normal
    layout = surface.layout
    # each volume and channel stops on its own, so that its result does not depend on its batch
    values = u.detach()
    highest = _volume_max(torch.where(band, values, -torch.inf), layout)
    lowest = -_volume_max(torch.where(band, -values, -torch.inf), layout)
    scale = (highest - lowest).clamp(min=torch.finfo(u.dtype).tiny)
    active = torch.ones_like(scale, dtype=torch.bool)
    for _ in range(max_steps):
        updated = torch.where(band & active, _upwind_step(u, velocity, h, 0.5, layout), u)
        change = _volume_max(torch.where(band, (updated - u).detach().abs(), 0.0), layout)
        u = updated
        active = active & (change > tolerance * scale)
        if not bool(active.any()):
            break
    return u


class Extension(nn.Module):
    """Extend data constant along the normals of ``surface``, inside its band.

    Args:
        method: ``"closest_point"`` (default) or ``"pde"`` (see the module docstring).
        width: half-width of the band to extend in, world units (default the surface's).
        tolerance: ``"pde"`` only: relative change per step at which to stop (default
            1e-6).
        max_steps: ``"pde"`` only: upper bound on the steps.
        interpolation: ``"closest_point"`` only: ``"linear"`` (default) or ``"cubic"`` (see
            :func:`closest_point_extension`).
        limited: ``"cubic"`` only: clamp each value to bounds at least as wide as the range
            of the cell its closest point lies in, within the range of its ``4^3`` taps and
            continuous in the point (each corner's 27 neighbours' extremes, weighted
            trilinearly: the flows' limiter, :mod:`torchsurf.flows._limiter`), so that an
            extension repeated on its own result (a "step, then extend" loop of one's own) stays
            within the data's range. Unlimited, cubic extension is exact for cubics (where the
            taps lie in the box: closest points within 1.5 cells of a box face read clamped
            taps, 7.6e-3 off a cubic of range 1.5 with S 0.3 cells from the faces) but, where
            the surface's sheets come within a few cells (a mesh's thin parts at a coarse grid),
            repeating it can grow without bound: on a 40^3 bunny ``from_mesh``, 6.4 after 50
            repetitions and 8e5 after 200 (data of range 2); limited, it stays in range.
        path: how the tricubic gathers run (:data:`torchsurf.backend.PATHS`; ``"slicing"``
            never compiles them, as a flow given it).

    Shapes: ``(B, C, D, H, W) -> (B, C, D, H, W)``; on a
    :class:`~torchsurf.bricks.BrickSurface`, packed ``(N, C, 8, 8, 8) -> (N, C, 8, 8, 8)``.
    """

    def __init__(
        self,
        method: str = "closest_point",
        width: float | None = None,
        tolerance: float | None = None,
        max_steps: int | None = None,
        interpolation: str = "linear",
        limited: bool = False,
        path: str = "auto",
    ) -> None:
        super().__init__()
        self.method = check_choice(method, "method", METHODS)
        self.path = check_choice(path, "path", backend.PATHS)
        self.interpolation = check_choice(interpolation, "interpolation", INTERPOLATIONS)
        self.limited = check_flag(limited, "limited")
        if self.limited and (method != "closest_point" or interpolation != "cubic"):
            raise ValueError("limited=True clamps tricubic values: it needs method='closest_point' "
                             f"and interpolation='cubic', got {method!r} and {interpolation!r}")
        if method == "pde" and interpolation != "linear":
            raise ValueError(f"interpolation={interpolation!r} chooses how the closest-point "
                             "extension interpolates; method='pde' interpolates nothing")
        if method != "pde" and (tolerance is not None or max_steps is not None):
            raise ValueError(f"tolerance and max_steps bound the pde extension's steps; "
                             f"method={method!r} takes no steps (got tolerance={tolerance!r}, "
                             f"max_steps={max_steps!r})")
        self.width = None if width is None else check_positive(width, "width")
        self.tolerance = 1e-6 if tolerance is None else check_positive(tolerance, "tolerance")
        self.max_steps = None if max_steps is None else check_count(max_steps, "max_steps")

    def forward(self, u: Tensor, surface: ImplicitSurface) -> Tensor:
        """``u`` ``(B, C, D, H, W)`` (packed ``(N, C, 8, 8, 8)`` on bricks) extended inside the
        band of :attr:`width`; nodes beyond it are returned as they are.

        What is read: trilinear interpolation reads the ``2^3`` nodes of the cell around each
        closest point, up to ``sqrt(3)`` cells from S, beyond a band narrower than that (with
        the default band, the band only); tricubic interpolation reads the ``4^3`` nodes around
        each closest point, up to ``2 sqrt(3)`` cells from S; ``"pde"`` reads the band and the
        nodes next to it. ``u`` may hold anything (NaN too) where nothing is read.

        Raises:
            ValueError: ``u`` holds NaN or infinity where it is read (the flows refuse it too:
                it would spread through the extension silently).
        """
        run_as_is_first(self, u, surface)
        # first: under vmap, u is one entry
        trilinear_dense = (self.method == "closest_point" and self.interpolation == "linear"
                           and getattr(surface, "layout", None) is None)
        refuse_transforms(type(self).__name__, u, phi=getattr(surface, "phi", None),
                          forward_mode=not trilinear_dense,
                          why="interpolation='linear' on a dense volume: PyTorch's grid_sample "
                              "has none; interpolation='cubic' has one")
        check_data(u, "u", surface)
        band = _band_to_extend(surface, self.width)
        if not torch.compiler.is_compiling():  # the band's size and the memory: host reads
            # the result and the values read (the flows' two working volumes) and, for the
            # tricubic stencil formed at each call, the band's closest points and taps
            cubic = self.method == "closest_point" and self.interpolation == "cubic"
            _memory.check_fits(
                _memory.flow_bytes(tuple(u.shape), surface.batch_size, u.dtype, False,
                                   int(band.sum()) if cubic else None),
                f"{type(self).__name__} on u of shape {tuple(u.shape)}", u.device)
        if self.method == "closest_point" and self.interpolation == "cubic":
            stencil = cubic_stencil(surface, band, limited=self.limited)
            check_finite(torch.where(band | _read_by(stencil, band), u.detach(), 0.0),
                         "u (in the band and the nodes its cubic interpolation reads)")
            return stencil.apply(u, self.path)
        if self.method == "closest_point":
            check_finite(torch.where(band, u.detach(), 0.0), "u (in the band)")
            extended = closest_point_extension(u, surface, mask=band, path=self.path)
            # a value read beyond a band narrower than sqrt(3) cells makes its nodes' result NaN
            check_finite(torch.where(band, extended.detach(), 0.0),
                         "u (at the nodes its trilinear interpolation reads, up to sqrt(3) cells "
                         "from S)")
            return extended
        check_finite(torch.where(with_ring(band, surface.layout), u.detach(), 0.0),
                     "u (in the band and next to it)")
        return pde_extension(u, surface, self.width, self.tolerance, self.max_steps)

    def extra_repr(self) -> str:
        return (f"method={self.method!r}, width={self.width}, interpolation={self.interpolation!r}"
                + (", limited=True" if self.limited else "")
                + (f", path={self.path!r}" if self.path != "auto" else ""))
