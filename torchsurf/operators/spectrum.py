"""Bounds on the spectrum of the assembled operators: what sets a stable explicit step.

Every operator of torchsurf is a stencil on the 3x3x3 neighbourhood of a node. Colour the nodes
by ``(i mod 3, j mod 3, k mod 3)``: the 27 indicator volumes of the colours, applied to the
operator, give every coefficient of the assembled matrix, since no 3x3x3 neighbourhood holds two
nodes of one colour. The largest absolute row sum over the band (Gershgorin's circle theorem)
then bounds the spectral radius of the operator restricted to the band, on whatever surface the
user brought: a thin feature, a medial axis or a ``phi`` that is not a distance raise the
coefficients there, and the bound with them, instead of blowing up a step chosen from the nominal
``h^2 / 6``.

The divergence-form schemes' rows are formed where they are needed, from the schemes' closed
forms (:func:`laplace_beltrami_rows`; on bricks from each brick's haloed geometry), instead of
probing the whole volume: the 27 eager probes of the octant scheme on a 200^3 box took 8.6 s
(one thread), the rows of its band a fraction of that; on a 64^3 bunny's bricks the symmetric
scheme's 27 probes took 0.33 s.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from .._checks import check_choice, check_count, check_dtype, check_positive
from .._stack import caller_stacklevel
from ..stencils import NEIGHBOURHOOD, BoxNeighbours
from ..surface import ImplicitSurface, check_surface
from ._flux_form import flux_form_rows
from ._octant import octant_rows
from .diffusion import directional_diffusion
from .laplace_beltrami import SCHEMES, laplace_beltrami

COLOURS = 27
"""Probe volumes needed for a stencil of radius one."""

ROWS_AT_ONCE = 2**18
"""Nodes whose rows :func:`laplace_beltrami_rows` forms at once in the bound (27 values and
about as many temporaries a node)."""


ROW_SCHEMES = ("octant", "symmetric", "conservative")
"""The schemes whose rows :func:`laplace_beltrami_rows` forms (the divergence forms)."""


def laplace_beltrami_rows(surface: ImplicitSurface, nodes: Tensor, scheme: str = "octant"
                          ) -> Tensor:
    """The rows of the Laplace–Beltrami matrix of a surface at some of its nodes.

    The matrix is the volume operator's (:func:`laplace_beltrami` with ``scheme``), no-flux
    faces included; each row is formed from the scheme's closed form (the octant one-pass
    expression of :mod:`torchsurf.operators._octant`, the flux schemes' compositions of
    :mod:`torchsurf.operators._flux_form`), not by applying the operator. On bricks the rows
    read the geometry with its halo (:meth:`~torchsurf.ImplicitSurface.haloed`), as the
    operator does.

    Args:
        surface: a :class:`~torchsurf.surface.ImplicitSurface`, dense (batch ``B``) or bricks
            (``N`` stored bricks).
        nodes: ``(R,)`` integer flat positions in ``(B, D, H, W)`` (dense) or in the packed
            ``(N, 8, 8, 8)`` (bricks).
        scheme: ``"octant"`` (default), ``"symmetric"`` or ``"conservative"``.

    Returns:
        ``(R, 27)`` in the surface's dtype: the coefficient of each node's neighbour at offset
        :data:`torchsurf.stencils.NEIGHBOURHOOD` ``[k]`` (all offsets ``(dz, dy, dx)`` in
        ``{-1, 0, 1}^3``, ``dz`` slowest), zero at offsets beyond the box (``u`` is replicated
        across the faces, so those coefficients are added to the face node's); units
        ``1 / world length^2``. On bricks a neighbour in a brick that is not stored reads zero
        in the operator, and its entry is the one the halo's zero geometry gives (a band node's
        neighbours are all stored).

    Raises:
        ValueError: ``scheme`` is not one of :data:`ROW_SCHEMES`, or ``nodes`` is not a 1-D
            integer tensor of positions in the surface's storage.
        TypeError: ``nodes`` is not a tensor.
    """
    check_choice(scheme, "scheme", ROW_SCHEMES)
    if not isinstance(nodes, Tensor):
        raise TypeError(f"nodes must be a torch.Tensor, got {type(nodes).__name__}")
    if nodes.dim() != 1 or nodes.dtype.is_floating_point or nodes.dtype.is_complex \
            or nodes.dtype == torch.bool:
        raise ValueError(f"nodes must be a 1-D integer tensor of flat positions, got shape "
                         f"{tuple(nodes.shape)} and dtype {nodes.dtype}")
    if surface.layout is None:
        depth, height, width = surface.grid.shape
        size = surface.batch_size * depth * height * width
        storage = f"the surface's {surface.batch_size} volume(s) of {depth}x{height}x{width}"
    else:
        side = surface.phi.shape[-1]
        size = len(surface.layout) * side**3
        storage = f"the surface's {len(surface.layout)} bricks of {side}^3 nodes"
    if len(nodes) and (int(nodes.min()) < 0 or int(nodes.max()) >= size):
        raise ValueError(f"nodes must lie in [0, {size}) ({storage}), got values from "
                         f"{int(nodes.min())} to {int(nodes.max())}")
    return _rows_in(surface, scheme, *_row_frame(surface, nodes.long())[:4])


def _rows_in(surface: ImplicitSurface, scheme: str, normal: Tensor, weight: Tensor,
             entry: Tensor, at: tuple[Tensor, Tensor, Tensor]) -> Tensor:
    """The rows of ``scheme`` at the nodes ``entry, at`` of the volumes ``normal, weight``
    (:func:`_row_frame`)."""
    if scheme == "octant":
        return octant_rows(normal, weight, surface.spacing, entry, at)
    return flux_form_rows(normal, weight, surface.spacing, scheme, entry, at)


def _row_frame(surface: ImplicitSurface, nodes: Tensor
               ) -> tuple[Tensor, Tensor, Tensor, tuple[Tensor, Tensor, Tensor],
                          tuple[int, int, int]]:
    """The volumes the rows at ``nodes`` are formed in: ``(normal, weight, entry, at,
    shape)``. A dense surface's own geometry, batch entries and grid indices; on bricks each
    brick's haloed geometry ``(N, C, 10, 10, 10)`` as a volume of its own, the nodes at their
    places in it (no node on its faces)."""
    if surface.layout is None:
        entry, at = _node_coordinates(nodes, surface.grid.shape)
        return surface.normal, surface.weight, entry, at, surface.grid.shape
    normal, weight = surface.haloed()
    side = surface.phi.shape[-1]
    local = nodes % side**3
    at = (local // side**2 + 1, (local // side) % side + 1, local % side + 1)
    return normal, weight, nodes // side**3, at, tuple(normal.shape[-3:])


def _probes(mask: Tensor, channels: range, colour: Tensor | None = None) -> Tensor:
    """Indicator volumes of the colours in ``channels``, restricted to ``mask``.

    ``mask``: ``(B, 1, D, H, W)`` bool; returns ``(B, len(channels), D, H, W)`` float.
    ``colour``: each node's colour, broadcastable to ``mask`` (default: from its position in
    ``mask``'s grid).
    """
    if colour is None:
        shape = mask.shape[-3:]
        k, j, i = (torch.arange(n, device=mask.device) % 3 for n in shape)
        colour = (k[:, None, None] * 9 + j[None, :, None] * 3 + i[None, None, :])
    wanted = torch.tensor(list(channels), device=mask.device).view(1, -1, 1, 1, 1)
    return ((colour == wanted) & mask).to(torch.get_default_dtype())


def gershgorin_bound(
    operator: Callable[[Tensor], Tensor], mask: Tensor, dtype: torch.dtype | None = None,
    chunk: int = 9, colour: Tensor | None = None,
) -> float:
    """Largest absolute row sum of ``x -> mask * operator(mask * x)`` over the nodes of ``mask``.

    An upper bound of the spectral radius of the operator restricted to ``mask`` (nodes outside
    held fixed), for any linear operator whose stencil reaches one node in each direction.

    Args:
        operator: linear map of volumes ``(B, C, D, H, W) -> (B, C, D, H, W)``, channel by
            channel (every torchsurf operator with a fixed surface).
        mask: ``(B, 1, D, H, W)`` bool, the nodes that evolve.
        dtype: of the probes (default: the default dtype).
        chunk: colours probed per call (memory: ``chunk`` volumes).
        colour: ``(B, 1, D, H, W)`` colour ``(k mod 3) 9 + (j mod 3) 3 + i mod 3`` of each node
            from its grid index, for fields not stored as whole grids (packed bricks:
            :meth:`torchsurf.bricks.BrickLayout.colours`); default from ``mask``'s grid.

    Returns:
        The bound, in the operator's units (``1 / world length^2`` for a diffusion operator).
    """
    _check_bound_arguments(operator, mask, chunk, colour)
    if dtype is not None:
        dtype = check_dtype(dtype)
    total = None
    with torch.no_grad():
        for start in range(0, COLOURS, chunk):
            probes = _probes(mask, range(start, min(start + chunk, COLOURS)), colour)
            if dtype is not None:
                probes = probes.to(dtype)
            image = operator(probes).abs().sum(dim=1, keepdim=True)
            total = image if total is None else total + image
        total = torch.where(mask, total, torch.zeros((), dtype=total.dtype, device=total.device))
        return float(total.max())


def _check_bound_arguments(operator: object, mask: object, chunk: object,
                           colour: object) -> None:
    """Raise naming the argument unless :func:`gershgorin_bound`'s inputs are as documented."""
    if not callable(operator):
        raise TypeError(f"operator must be a callable (a linear map of volumes), got "
                        f"{type(operator).__name__}")
    if not isinstance(mask, Tensor) or mask.dtype != torch.bool:
        got = f"dtype {mask.dtype}" if isinstance(mask, Tensor) else type(mask).__name__
        raise TypeError(f"mask must be a bool volume (B, 1, D, H, W), got {got}")
    if mask.dim() != 5 or mask.shape[1] != 1:
        raise ValueError(f"mask must be a bool volume (B, 1, D, H, W), got shape {tuple(mask.shape)}")
    check_count(chunk, "chunk")
    if colour is not None:
        if not isinstance(colour, Tensor):
            raise TypeError(f"colour must be a tensor, got {type(colour).__name__}")
        try:
            torch.broadcast_shapes(colour.shape, mask.shape)
        except RuntimeError:
            raise ValueError(f"colour must broadcast to mask's shape {tuple(mask.shape)}, got "
                             f"shape {tuple(colour.shape)}") from None


def laplace_beltrami_bound(
    surface: ImplicitSurface, scheme: str = "octant", width: float | None = None
) -> float:
    """Gershgorin bound of ``Lap_S`` (:func:`laplace_beltrami`) restricted to the band.

    Computed once per surface, scheme and width, and kept on the surface. On a
    distance function it is close to ``10 / h^2``; where ``|grad phi|`` departs from 1 the
    floored weight of :class:`ImplicitSurface` keeps it within a small factor of that.

    Args:
        surface: the implicit surface, dense or bricks, batch ``B``.
        scheme: as in :func:`laplace_beltrami`.
        width: the band's half-width, world units (default ``surface.band_width``).

    Returns:
        The bound, ``1 / world length^2``: one float, the largest over the batch's entries.

    Raises:
        ValueError: the band of ``width`` holds no node.
    """
    check_surface(surface)
    width = surface.band_width if width is None else check_positive(width, "width")

    def formed() -> float:
        bound = _band_bound(surface, scheme, width)
        if bound == 0.0:
            raise ValueError(
                f"width: the band of half-width {width:g} (world units; h = "
                f"{surface.spacing:g}) holds no node, so there is no bound to give: widen it to "
                "a cell or more")
        return _warned_if_wild(bound, surface)

    return surface.kept(("laplace_beltrami_bound", scheme, width), formed)


def keep_laplace_beltrami_bound(surface: ImplicitSurface, scheme: str, width: float,
                                bound: float) -> float:
    """Keep on ``surface`` the bound :func:`laplace_beltrami_bound` gives for ``scheme`` and
    ``width``, formed elsewhere from the same rows (the heat flow's packed operator forms them
    anyway: its assembly and the bound formed each its own, a tenth of a fresh surface's first
    flow), and warned about like it; a bound already kept is kept as it is.

    Args:
        surface: an implicit surface, dense or bricks.
        scheme, width: as in :func:`laplace_beltrami_bound` (``width`` given, world units).
        bound: the largest :func:`gershgorin_sums` of :func:`laplace_beltrami_rows` at the
            band's nodes, ``1 / world length^2``.

    Returns:
        The bound kept (``bound``, or the one kept before).
    """
    return surface.kept(("laplace_beltrami_bound", scheme, float(width)),
                        lambda: _warned_if_wild(bound, surface))


WILD_BOUND_CELLS = 1000.0
"""A Laplace–Beltrami bound above this many ``1 / h^2`` is warned about: 10-33 ``/ h^2`` were
measured on distance functions, ``phi`` scaled or not a distance (``r^2 - 1``, ``(r - 1)^3``:
28-32 at 40^3), thin tori and every shared mesh at 24^3-48^3 (the central scheme on meshes:
30-33); one sentinel value of ``-1e9`` 2.7 cells inside a sphere raised it to 6.7e9."""


def _warned_if_wild(bound: float, surface: ImplicitSurface) -> float:
    """``bound``, warned about when it exceeds :data:`WILD_BOUND_CELLS` ``/ h^2``: the flows'
    steps follow it, and their refusals would otherwise blame the time's units."""
    cells = bound * surface.spacing**2
    if cells > WILD_BOUND_CELLS:
        warnings.warn(
            f"phi: the Laplace–Beltrami operator's bound over the band is {cells:.3g} / h^2, "
            "against 10-33 / h^2 on distance functions and meshes: |grad phi| jumps near S "
            "(a sentinel or singular value of phi beside the band?), and flows on this surface "
            f"take about {cells / 15:.3g} times their usual steps, or are refused. "
            "torchsurf.sdf.redistance(phi, grid) makes phi a distance",
            RuntimeWarning, stacklevel=caller_stacklevel(),
        )
    return bound


def directional_bound(
    surface: ImplicitSurface, direction: Tensor, scheme: str = "symmetric",
    width: float | None = None,
) -> float:
    """Gershgorin bound of :func:`directional_diffusion` along ``direction``, restricted to the
    band.

    Diffusion along one tangent direction (``T T^T`` against ``P``) has a smaller bound than
    Laplace–Beltrami's, by how much depends on the scheme: on the teapot's smoothed principal
    direction at 64^3, 12.2 against 15.4 for the symmetric schemes (0.79); a swirl on a sphere,
    11.4 against 12.7 (0.90), and about half with the octant scheme (units ``1 / h^2``).
    Not kept: it depends on ``direction``.

    Args:
        surface: the implicit surface, dense or bricks, batch ``B``.
        direction: ``T``, ``(B or 1, 3, D, H, W)`` (packed ``(N, 3, 8, 8, 8)`` on bricks),
            a tangent direction field, as in :func:`directional_diffusion`.
        scheme: as in :func:`directional_diffusion`.
        width: the band's half-width, world units (default ``surface.band_width``).

    Returns:
        The bound, ``1 / world length^2``: one float, the largest over the batch's entries.
    """
    width = surface.band_width if width is None else float(width)
    return _bound_on_band(
        surface, width, lambda x, path: directional_diffusion(x, surface, direction, scheme, path)
    )


def _band_bound(surface: ImplicitSurface, scheme: str, width: float) -> float:
    check_choice(scheme, "scheme", SCHEMES)
    if scheme in ROW_SCHEMES:
        return _bound_from_rows(surface, surface.band_mask(width), scheme)
    return _bound_on_band(surface, width,
                          lambda x, path: laplace_beltrami(x, surface, scheme, path))


def _bound_on_band(surface: ImplicitSurface, width: float,
                   operator: Callable[[Tensor, str], Tensor]) -> float:
    mask = surface.band_mask(width)
    dtype = surface.phi.dtype
    if surface.layout is None:
        return gershgorin_bound(lambda x: operator(x, "slicing"), mask, dtype)
    # bricks: one colour at a time, on the path "auto" picks, keeps the memory to a few
    # fields (nine eager colours held 1 GB at 192^3, three compiled 1.4 GB at 512^3)
    return gershgorin_bound(
        lambda x: operator(x, "auto"), mask, dtype, chunk=1,
        colour=surface.layout.colours().to(mask.device),
    )


def _bound_from_rows(surface: ImplicitSurface, mask: Tensor, scheme: str) -> float:
    """:func:`gershgorin_bound` of ``Lap_S`` on ``mask`` from its rows
    (:func:`laplace_beltrami_rows`), dense or bricks: on bricks the 27 colour probes it
    replaced took 0.33 of a 64^3 bunny's 0.36 s of total variation's setup."""
    nodes = mask.reshape(-1).nonzero().squeeze(1)
    # whether each node of the rows' volumes evolves: the mask, haloed on bricks
    evolves = mask if surface.layout is None else surface.layout.halo(mask, 1, "slicing")
    evolves = evolves.reshape(-1)
    largest = 0.0
    with torch.no_grad():
        for start in range(0, len(nodes), ROWS_AT_ONCE):
            part = nodes[start: start + ROWS_AT_ONCE]
            normal, weight, entry, at, shape = _row_frame(surface, part)
            rows = _rows_in(surface, scheme, normal, weight, entry, at)
            box = BoxNeighbours(at, shape)
            first = entry * math.prod(shape)
            evolving = [evolves[first + box.neighbour(offset)[0]] for offset in NEIGHBOURHOOD]
            largest = max(largest, float(gershgorin_sums(rows, evolving).max()))
    return largest


def gershgorin_sums(rows: Tensor, evolving: Sequence[Tensor]) -> Tensor:
    """Each row's sum of ``|entry|`` over its evolving columns: ``rows`` ``(R, 27)`` as
    :func:`laplace_beltrami_rows` gives them, ``evolving[k]`` ``(R,)`` bool, whether the
    neighbour at :data:`~torchsurf.stencils.NEIGHBOURHOOD` ``[k]`` evolves (any value where the
    row's entry is zero). ``(R,)``, summed column after column (the same rounding wherever the
    rows come from)."""
    total = rows.new_zeros(rows.shape[0])
    for k, inside in enumerate(evolving):
        total += torch.where(inside, rows[:, k].abs(), 0.0)
    return total


def _node_coordinates(nodes: Tensor, shape: tuple[int, int, int]
                      ) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]]:
    """Batch entry and grid indices ``(z, y, x)`` of flat positions in ``(B, D, H, W)``."""
    depth, height, width = shape
    return nodes // (depth * height * width), (
        (nodes // (height * width)) % depth, (nodes // width) % height, nodes % width)
