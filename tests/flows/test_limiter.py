"""The closest-point stencils' limiter: bounds continuous in the point, within the taps' range,
holding the cell's range; the same in every form (eager, compiled terms, the packed C kernel)."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import _limiter
from torchsurf.flows.extension import _interpolate_gathered, _interpolate_terms
from torchsurf.sampling import cubic_lagrange_weights

SHAPE = (8, 9, 10)
NODES = 8 * 9 * 10


def _stencil_at(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Corners ``(3, N, 4)`` and Lagrange weights ``(3, N, 4)`` of points ``(N, 3)`` (x, y, z)
    inside ``SHAPE``, the cell taken as ``floor`` of each coordinate."""
    base = points.floor()
    corners = torch.stack([base[:, a: a + 1].long() + torch.arange(-1, 3) for a in range(3)])
    weights = torch.stack([torch.stack(cubic_lagrange_weights(points[:, a] - base[:, a]), dim=1)
                           for a in range(3)])
    return corners, weights


def _limited(flat: torch.Tensor, points: torch.Tensor, path: str = "eager") -> torch.Tensor:
    corners, weights = _stencil_at(points)
    depth, height, width = SHAPE
    form = _interpolate_gathered if path == "eager" else _interpolate_terms
    return form(flat, corners, weights, height, width, True)


def test_limited_values_are_continuous_across_cell_faces(generator):
    """Points a hair either side of a node plane fall in different cells: with the cell's own
    range as bounds the values differed by up to the data's scale (that made the flows jump
    under any change of ``phi`` at symmetric placements); the limiter's bounds agree there."""
    flat = torch.rand(2, NODES, dtype=torch.float64, generator=generator)
    inner = 2.0 + torch.rand(400, 3, dtype=torch.float64, generator=generator) * 2.0
    for axis in range(3):
        on_plane = inner.clone()
        on_plane[:, axis] = 3.0
        below, above = on_plane.clone(), on_plane.clone()
        below[:, axis] -= 1e-12
        above[:, axis] += 1e-12
        for path in ("eager", "terms"):
            a, b = _limited(flat, below, path), _limited(flat, above, path)
            assert float((a - b).abs().max()) < 1e-9
    # random data leave the cubic outside some cell's range: the bounds were exercised
    free = _interpolate_gathered(flat, *_stencil_at(inner), 9, 10, False)
    assert float((free - _limited(flat, inner)).abs().max()) > 1e-2


def test_bounds_hold_the_cell_and_stay_within_the_taps(generator):
    flat = torch.randn(3, NODES, dtype=torch.float64, generator=generator)
    points = 1.0 + torch.rand(500, 3, dtype=torch.float64, generator=generator) * 4.0
    corners, weights = _stencil_at(points)
    x, y, z = corners.unbind(0)
    sources = ((z[:, :, None, None] * 9 + y[:, None, :, None]) * 10
               + x[:, None, None, :]).flatten(1)
    gathered = flat[:, sources]
    low, high, lowest, highest = _limiter.bounds_and_sources(
        gathered, _limiter.corner_weights(*weights.unbind(0)))
    cell = gathered[..., _limiter.CELL]
    assert bool((low <= cell.amin(-1) + 1e-12).all() and (high >= cell.amax(-1) - 1e-12).all())
    assert bool((low >= gathered.amin(-1) - 1e-12).all() and (high <= gathered.amax(-1) + 1e-12).all())
    # the taps named for each corner hold that corner's extreme of its 27
    extremes = _limiter.corner_extremes(gathered)
    torch.testing.assert_close(gathered.gather(2, lowest), extremes[0], rtol=0, atol=0)
    torch.testing.assert_close(gathered.gather(2, highest), extremes[1], rtol=0, atol=0)
    # both forms of the bounds and of the clamp give the same values
    torch.testing.assert_close(_limited(flat, points, "terms"), _limited(flat, points),
                               rtol=1e-12, atol=1e-12)


def test_a_point_on_a_node_takes_the_nodes_value(generator):
    flat = torch.randn(1, NODES, dtype=torch.float64, generator=generator)
    points = torch.tensor([[2.0, 3.0, 4.0], [3.0, 2.0, 1.0], [4.0, 4.0, 3.0]], dtype=torch.float64)
    expected = flat[0, ((points[:, 2] * 9 + points[:, 1]) * 10 + points[:, 0]).long()]
    torch.testing.assert_close(_limited(flat, points)[0], expected, rtol=0, atol=1e-14)


@pytest.mark.parametrize("fraction", [-0.3, 1.4])
def test_corner_weights_stay_convex_for_points_past_the_cell(fraction):
    weights = torch.stack(cubic_lagrange_weights(torch.tensor([fraction], dtype=torch.float64)),
                          dim=1)
    corners = _limiter.corner_weights(weights, weights, weights)
    assert bool((corners >= 0).all()) and float(corners.sum()) == pytest.approx(1.0)


def _mostly_ones(shape: tuple[int, ...], generator: torch.Generator) -> torch.Tensor:
    """0/1 data in float32, 1 at 90% of the nodes: most cells all ones, their cubic above 1
    where a 0 lies among the outer taps, the bounds ``sum_c lambda_c 1`` formed there."""
    return (torch.rand(shape, dtype=torch.float64, generator=generator) < 0.9).float()


def test_limited_values_stay_within_the_datas_range_to_the_last_bit(generator):
    """The bounds' weighted sums round (the weights sum to ``1 +- ulp``): unguarded, values
    clamped to ``sum_c lambda_c 1`` exceeded 1 by an ulp in float32, a new extremum."""
    flat = _mostly_ones((2, NODES), generator)
    points = 1.0 + torch.rand(4000, 3, dtype=torch.float64, generator=generator) * 5.0
    corners, weights = _stencil_at(points)
    for path in ("eager", "terms"):
        value = _interpolate_gathered(flat, corners, weights.float(), 9, 10, True) \
            if path == "eager" else _interpolate_terms(flat, corners, weights.float(), 9, 10, True)
        assert float(value.max()) <= 1.0 and float(value.min()) >= 0.0, path
    free = _interpolate_gathered(flat, corners, weights.float(), 9, 10, False)
    assert float(free.max()) > 1.01  # the cubic overshot: the bounds were formed



@pytest.mark.parametrize("storage", ["dense", "bricks", "bricks forming their taps"])
def test_every_path_limits_the_same_values(storage, monkeypatch):
    """The eager forms limit as they gather; a compiled form returns each cell's range beside
    the value and the values outside it are limited apart
    (:func:`_limiter.clamp_outside_range`). Compilation is replaced by the plain function, so
    that the compiled form's branch runs in seconds. Bricks keep each node's 64 tap positions
    up to ``KEEP_SOURCES_NODES`` nodes and form them above (the 512^3 bunny's band)."""
    from torchsurf import backend, bricks
    from torchsurf.flows import extension
    from torchsurf.flows.extension import cubic_stencil

    monkeypatch.setattr(backend, "compiled", lambda function, *options, **named: function)
    if storage == "bricks forming their taps":
        monkeypatch.setattr(extension, "KEEP_SOURCES_NODES", 0)
    grid = ts.Grid.cube(21, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.8, dtype=torch.float64), grid)
    u = torch.rand(1, 2, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(3))
    if storage != "dense":
        surface = bricks.from_dense(surface)
        u = surface.from_dense(u)
    mask = surface.band_mask()
    results = {path: cubic_stencil(surface, mask, limited=True).apply(u, path=path)
               for path in ("slicing", "compiled")}
    free = cubic_stencil(surface, mask).apply(u, path="slicing")
    assert float((free - results["slicing"]).abs().max()) > 1e-2  # values were limited
    torch.testing.assert_close(results["compiled"], results["slicing"], rtol=0, atol=1e-12)
