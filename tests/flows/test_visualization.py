"""FlowVisualization: noise becomes streaks, correlated along T far more than across it."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import FlowVisualization


# "rkc", the default, is what `torchsurf run flowvis_*` uses: its damped stages smooth across
# as little as the exact flow (before the damping, its long steps left no streaks)
@pytest.mark.parametrize("options", [{"method": "implicit", "steps": 4}, {"method": "rkc"}])
def test_streaks_are_correlated_along_the_field_not_across(options):
    grid = ts.Grid.cube(33, bound=1.3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0), grid)
    points = grid.points()
    x, y, _ = points.unbind(-1)
    # T: circles around the z axis (east); across it: the meridians (south)
    east = torch.stack((-y, x, torch.zeros_like(x)), dim=0)[None]
    noise = FlowVisualization.noise(surface, generator=torch.Generator().manual_seed(0))
    u = FlowVisualization(0.02, **options)(noise, surface, direction=east)
    u = (u - u.mean())[0, 0]
    # near the +x axis, east is +y (volume dim 1) and the meridians run along z (dim 0)
    mask = ((surface.phi.abs() <= surface.spacing)[0, 0] & (points[..., 1].abs() < 0.2)
            & (points[..., 2].abs() < 0.5) & (points[..., 0] > 0))

    def correlation(dim: int, shift: int = 2) -> float:
        both = mask & torch.roll(mask, shifts=shift, dims=dim)
        a, b = u[both], torch.roll(u, shifts=shift, dims=dim)[both]
        return float((a * b).mean() / (a.std() * b.std()))

    along, across = correlation(1), correlation(0)
    assert along > 3 * abs(across), (along, across)


def test_explicit_and_implicit_agree():
    grid = ts.Grid.cube(13, bound=1.3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    e1, _ = surface.principal_directions()
    noise = FlowVisualization.noise(surface, generator=torch.Generator().manual_seed(1))
    same_problem = {"band_width": 0.6, "reextend_every": None}
    explicit = FlowVisualization(0.01, isotropic=0.1, method="euler", steps=100, **same_problem)(
        noise, surface, direction=e1)
    implicit = FlowVisualization(0.01, isotropic=0.1, method="crank_nicolson", steps=10,
                                 **same_problem)(noise, surface, direction=e1)
    assert (explicit - implicit).abs().max() < 5e-3


def test_the_direction_field_is_scale_free():
    # tangent_unit divided by sqrt(|P T|^2 + 1e-24): a field of size 1e-12 moved the result by
    # 0.24, and where P T = 0 (the poles' nodes) d/dT reached 1.7e10
    grid = ts.Grid.cube(15, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    x, y, _ = grid.points(dtype=torch.float64).unbind(-1)
    direction = torch.stack([-y, x, 0.3 + 0 * x])[None]
    noise = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                       generator=torch.Generator().manual_seed(0))
    flow = ts.FlowVisualization(0.01)
    reference = flow(noise, surface, direction=direction)
    for scale in (1e-6, 1e-13):
        torch.testing.assert_close(flow(noise, surface, direction=scale * direction), reference,
                                   rtol=0, atol=1e-12)
    leaf = direction.clone().requires_grad_(True)
    weights = torch.randn(reference.shape, dtype=torch.float64,
                          generator=torch.Generator().manual_seed(1))
    (flow(noise, surface, direction=leaf) * weights * surface.band_mask()).sum().backward()
    assert float(leaf.grad.abs().max()) < 1e3


@pytest.mark.parametrize("make", [lambda s: torch.zeros_like(s.normal), lambda s: s.normal.clone()])
def test_a_field_with_no_tangent_part_is_refused(make):
    """A zero field, or the normals, were sent to 0 by tangent_unit: flow visualisation then
    diffused nothing, reaction–diffusion's a not at all, without a word."""
    grid = ts.Grid.cube(21, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u0 = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    for flow, data in ((ts.flows.FlowVisualization(0.01), u0),
                       (ts.flows.ReactionDiffusion(1.0), ts.flows.ReactionDiffusion.initial(surface))):
        with pytest.raises(ValueError, match="direction has no part tangent"):
            flow(data, surface, direction=make(surface))


def test_a_field_zero_on_part_of_the_surface_is_taken_on_bricks_as_on_the_dense_grid():
    """The share of nodes with no tangent part was taken per brick on bricks: a swirl zero below
    z = -0.5 (a quarter of the sphere) was refused there, and taken on the dense grid."""
    from torchsurf import bricks, signals

    grid = ts.Grid.cube(40, bound=1.6)
    dense = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0), grid)
    packed = bricks.from_dense(dense)
    flow = FlowVisualization(grid.spacing**2)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    for surface, data in ((dense, u), (packed, packed.from_dense(u))):
        field = signals.swirl_field(surface, "z")
        field = field * (signals.node_points(surface)[:, 2:3] > -0.5).to(field.dtype)
        assert torch.isfinite(flow(data, surface, direction=field)).all()


def test_unknown_inputs_and_a_negative_isotropic_weight_are_named():
    """generator= reached an internal method's TypeError; the isotropic weight's error said
    'positive' while 0 is its default (an audit)."""
    with pytest.raises(ValueError, match=r"^isotropic must be a finite number >= 0"):
        FlowVisualization(0.01, isotropic=-1.0)
    grid = ts.Grid.cube(9, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    u0 = FlowVisualization.noise(surface)
    with pytest.raises(TypeError, match=r"^FlowVisualization takes direction= only, got "
                                        r"\['generator'\]"):
        FlowVisualization(0.01)(u0, surface, direction=ts.signals.swirl_field(surface),
                                generator=torch.Generator())
