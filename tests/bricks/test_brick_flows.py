"""Flow visualisation, harmonic maps, colour and reaction–diffusion on bricks: every integrator
equals the dense flow on the band to rounding; a batch of shapes equals each shape alone;
gradients through a brick step.

Float64 throughout, compared relative to the largest value on the band (``1e-10``; measured
differences are ``1e-15``-``1e-14``, summation order).
"""

from __future__ import annotations

import math

import pytest
import torch

import torchsurf as ts
from torchsurf import Grid, backend, bricks
from torchsurf._vectors import tangential_part
from torchsurf.flows import (
    ColorDenoise,
    FlowVisualization,
    HarmonicMapFlow,
    HeatFlow,
    ReactionDiffusion,
)
from torchsurf.flows.harmonic import normalize
from torchsurf.operators import functional

RELATIVE = 1e-10


@pytest.fixture(autouse=True, scope="module")
def eager():
    """Many small calls of one kernel and shape would make ``path="auto"`` compile it after a
    few seconds of eager time (tens of seconds of compiling here): keep every kernel eager, and
    keep this module's eager time off the ledger, which would make the next modules' calls of
    the same kernels and shapes compile."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(backend, "COMPILE_PAYBACK_SECONDS", math.inf)
        patch.setattr(backend, "_TIMINGS", {})
        yield


def _assert_equal_on_band(packed, expected, surface, dense):
    """``packed`` on ``surface`` equals the dense ``expected`` at the dense band's nodes."""
    (result,) = surface.to_dense(packed)
    band = dense.band_mask().expand_as(expected)
    difference = float((result - expected)[band].abs().max())
    scale = float(expected[band].abs().max())
    assert difference <= RELATIVE * scale, (difference, scale)


def _east(points):
    """The tangent field ``(-y, x, 0)`` of shapes around the z axis, ``(..., 3, ...)`` from
    points with their components along dim 1."""
    x, y = points[:, :1], points[:, 1:2]
    return torch.cat((-y, x, torch.zeros_like(x)), dim=1)


def _dense_points(grid):
    return grid.points(dtype=torch.float64).permute(3, 0, 1, 2)[None]


def _noise(grid, channels, seed):
    return torch.randn(1, channels, *grid.shape, dtype=torch.float64,
                       generator=torch.Generator().manual_seed(seed))


# --- the operators --------------------------------------------------------------------------


@pytest.mark.parametrize("scheme", ["symmetric", "conservative", "octant"])
def test_directional_diffusion_and_gradient_energy_equal_the_dense_operators(torus, scheme):
    dense, surface = torus
    u = _noise(dense.grid, 2, 0)
    direction = _east(_dense_points(dense.grid))
    packed_u, packed_direction = surface.from_dense(u), surface.from_dense(direction)
    expected = ts.directional_diffusion(u, dense, direction, scheme)
    result = ts.directional_diffusion(packed_u, surface, packed_direction, scheme)
    _assert_equal_on_band(result, expected, surface, dense)
    # the operator diffuses along P T, the functional form along the T it is given
    tangent = tangential_part(packed_direction, surface.normal)
    haloed = surface.layout.halo(tangent, 1)
    kept = functional.directional_form(
        packed_u, surface.normal, surface.weight, surface.spacing, tangent, scheme,
        haloed=surface.haloed(), pad=surface.layout.halo, haloed_direction=haloed)
    assert torch.equal(kept, result)
    energy = functional.tangential_gradient_energy(u, dense.normal, dense.spacing)
    packed_energy = functional.tangential_gradient_energy(
        packed_u, surface.normal, surface.spacing, pad=surface.layout.halo)
    _assert_equal_on_band(packed_energy, energy, surface, dense)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_noise_on_bricks_is_the_dense_noise_node_for_node(two_boxes, dtype):
    _, _, both = two_boxes
    layout = both.layout
    packed = layout.rand(2, torch.Generator().manual_seed(3), dtype)
    generator = torch.Generator().manual_seed(3)
    volumes = [torch.rand((1, 2, *grid.shape), generator=generator, dtype=dtype)
               for grid in layout.grids]
    inside = layout.inside.expand_as(packed)
    assert torch.equal(packed[inside], layout.from_dense(volumes)[inside])
    noise = FlowVisualization.noise(both, generator=torch.Generator().manual_seed(3))
    assert noise.shape == (len(layout), 1, 8, 8, 8) and noise.dtype == torch.float64
    assert ReactionDiffusion.initial(both).shape == (len(layout), 2, 8, 8, 8)
    with pytest.raises(ValueError, match="batch=3"):
        FlowVisualization.noise(both, batch=3)


# --- the flows against the dense flows --------------------------------------------------------


@pytest.mark.parametrize("method", ["rkc", "euler", "heun", "implicit", "crank_nicolson"])
def test_flow_visualization_equals_the_dense_flow_on_the_band(torus, method):
    dense, surface = torus
    u = FlowVisualization.noise(dense, generator=torch.Generator().manual_seed(0))
    packed_u = FlowVisualization.noise(surface, generator=torch.Generator().manual_seed(0))
    direction = _east(_dense_points(dense.grid)) + 0.3 * _noise(dense.grid, 3, 1)
    options = {"tolerance": 1e-13} if method in ("implicit", "crank_nicolson") else {}
    flow = FlowVisualization(0.01, isotropic=0.2, method=method, **options)
    expected = flow(u, dense, direction=direction)
    result = flow(packed_u, surface, direction=surface.from_dense(direction))
    _assert_equal_on_band(result, expected, surface, dense)


@pytest.mark.parametrize("method", ["rkc", "euler", "heun"])
@pytest.mark.parametrize("settings", [
    {"p": 2.0},
    {"p": 1.0, "eps": 0.5, "tangent": True},
    {"p": 1.5, "scheme": "conservative"},
])
def test_harmonic_map_flow_equals_the_dense_flow_on_the_band(torus, method, settings):
    dense, surface = torus
    u = normalize(_dense_points(dense.grid) + 0.3 * _noise(dense.grid, 3, 2))
    flow = HarmonicMapFlow(0.004, method=method, **settings)
    expected = flow(u, dense)
    _assert_equal_on_band(flow(surface.from_dense(u), surface), expected, surface, dense)


@pytest.mark.parametrize("method", ["rkc", "euler", "heun"])
def test_colour_denoising_equals_the_dense_flow_on_the_band(torus, method):
    dense, surface = torus
    z = _dense_points(dense.grid)[:, 2:]
    image = torch.cat((0.6 + 0.3 * (z > 0), 0.4 + 0 * z, 0.5 - 0.2 * (z > 0)), dim=1)
    image = image + 0.1 * _noise(dense.grid, 3, 3)
    flow = ColorDenoise(0.002, method=method)
    _assert_equal_on_band(flow(surface.from_dense(image), surface), flow(image, dense),
                          surface, dense)


def test_colour_denoising_with_an_implicit_heat_flow_for_the_brightness(torus):
    dense, surface = torus
    image = 0.5 + 0.2 * _noise(dense.grid, 3, 4)
    flow = ColorDenoise(0.002, brightness=HeatFlow(0.002, method="implicit", tolerance=1e-13))
    assert flow.supports_bricks
    _assert_equal_on_band(flow(surface.from_dense(image), surface), flow(image, dense),
                          surface, dense)


@pytest.mark.parametrize("method", ["euler", "heun", "rkc"])
def test_reaction_diffusion_equals_the_dense_flow_on_the_band(torus, method):
    """Turk's ``beta`` noise drawn from one seed: the same numbers at the same nodes."""
    dense, surface = torus
    u = ReactionDiffusion.initial(dense) + torch.rand(
        1, 2, *dense.grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    flow = ReactionDiffusion(time=20.0, method=method)
    expected = flow(u, dense, generator=torch.Generator().manual_seed(0))
    result = flow(surface.from_dense(u), surface, generator=torch.Generator().manual_seed(0))
    _assert_equal_on_band(result, expected, surface, dense)


def test_anisotropic_reaction_diffusion_equals_the_dense_flow_on_the_band(torus):
    dense, surface = torus
    u = ReactionDiffusion.initial(dense)
    e1, _ = dense.principal_directions()
    flow = ReactionDiffusion(time=20.0)
    expected = flow(u, dense, direction=e1, generator=torch.Generator().manual_seed(1))
    result = flow(ReactionDiffusion.initial(surface), surface, direction=surface.from_dense(e1),
                  generator=torch.Generator().manual_seed(1))
    _assert_equal_on_band(result, expected, surface, dense)


# --- batches ------------------------------------------------------------------------------------


def _assert_batch_equals_each_alone(two_boxes, run):
    """``run(surface, rows)`` on the batch equals it on each shape alone, on the band."""
    sphere, torus, both = two_boxes
    count = len(sphere.layout)
    together = run(both, slice(None))
    alone = torch.cat([run(sphere, slice(0, count)), run(torus, slice(count, None))])
    band = both.band_mask().expand_as(together)
    assert torch.allclose(together[band], alone[band], atol=1e-12, rtol=0)


@pytest.mark.parametrize("method", ["rkc", "implicit"])
def test_flow_visualization_batch_of_shapes_equals_each_alone(two_boxes, method):
    both = two_boxes[2]
    u = both.layout.rand(1, torch.Generator().manual_seed(6), torch.float64)
    direction = _east(both.layout.points(torch.float64))
    flow = FlowVisualization(0.01, method=method)
    _assert_batch_equals_each_alone(
        two_boxes, lambda surface, rows: flow(u[rows], surface, direction=direction[rows]))


def test_harmonic_map_batch_of_shapes_equals_each_alone(two_boxes):
    points = two_boxes[2].layout.points(torch.float64)
    generator = torch.Generator().manual_seed(7)
    u = normalize(points + 0.3 * torch.randn(points.shape, generator=generator,
                                             dtype=torch.float64))
    flow = HarmonicMapFlow(0.002, p=1.0, eps=0.5, tangent=True)
    _assert_batch_equals_each_alone(two_boxes, lambda surface, rows: flow(u[rows], surface))


def test_colour_denoising_batch_of_shapes_equals_each_alone(two_boxes):
    points = two_boxes[2].layout.points(torch.float64)
    generator = torch.Generator().manual_seed(11)
    image = 0.5 + 0.2 * torch.randn(points.shape, generator=generator, dtype=torch.float64)
    colour = ColorDenoise(0.0005)
    _assert_batch_equals_each_alone(two_boxes, lambda surface, rows: colour(image[rows], surface))


def test_reaction_diffusion_batch_of_shapes_equals_each_alone(two_boxes):
    """Entries draw their boxes' noise in turn from the one generator: the torus alone equals
    the batch's second entry once its generator has drawn the sphere's box."""
    sphere, _, both = two_boxes
    direction = _east(both.layout.points(torch.float64))
    flow = ReactionDiffusion(time=10.0)

    def run(surface, rows):
        generator = torch.Generator().manual_seed(8)
        if surface.batch_size == 1 and surface.grids[0] != sphere.grids[0]:
            torch.rand((1, 1, *sphere.grids[0].shape), generator=generator, dtype=torch.float64)
        return flow(ReactionDiffusion.initial(surface), surface, direction=direction[rows],
                    generator=generator)

    _assert_batch_equals_each_alone(two_boxes, run)


# --- gradients ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_sphere():
    grid = Grid.cube(21, 2.0)
    return bricks.from_dense(ts.sdf.sphere(grid, 1.0).double(), grid)


def test_gradcheck_harmonic_map_step_on_bricks_in_the_data(small_sphere):
    surface = small_sphere
    points = surface.layout.points(torch.float64)
    generator = torch.Generator().manual_seed(9)
    u = normalize(points + 0.3 * torch.randn(points.shape, generator=generator,
                                             dtype=torch.float64))
    band = surface.band_mask().expand_as(u)
    flow = HarmonicMapFlow(0.001, method="euler", steps=1)
    assert torch.autograd.gradcheck(lambda x: flow(x, surface)[band],
                                    (u.requires_grad_(),), fast_mode=True)


@pytest.mark.parametrize("method", ["euler", "implicit"])
def test_gradcheck_flow_visualization_step_on_bricks_in_data_and_direction(small_sphere, method):
    surface = small_sphere
    generator = torch.Generator().manual_seed(10)
    u = surface.layout.rand(1, generator, torch.float64)
    points = surface.layout.points(torch.float64)
    direction = _east(points) + 0.3 * torch.randn(points.shape, generator=generator,
                                                  dtype=torch.float64)
    band = surface.band_mask()
    options = {"tolerance": 1e-13} if method == "implicit" else {}
    flow = FlowVisualization(0.002, isotropic=0.1, method=method, steps=1, **options)
    assert torch.autograd.gradcheck(
        lambda x, t: flow(x, surface, direction=t)[band],
        (u.requires_grad_(), direction.requires_grad_()), fast_mode=True, atol=1e-6)


def test_a_moved_batch_of_entries_integrates_in_its_new_dtype():
    """The entries a flow split off a multi-entry surface are kept; ``.double()`` derives
    them again (they were kept in float32, and the flow refused float64 data)."""
    grid = Grid.cube(24, 1.5)
    phi = torch.cat([ts.sdf.sphere(grid, 0.8), ts.sdf.sphere(grid, 0.6)])
    surface = bricks.from_dense(phi, grid)
    u = torch.rand(len(surface.layout), 1, 8, 8, 8, generator=torch.Generator().manual_seed(0))
    flow = HeatFlow((2 * grid.spacing) ** 2)
    single = flow(u, surface)
    surface.double()
    assert all(entry.phi.dtype == torch.float64 for _, entry in surface.entries())
    double = flow(u.double(), surface)
    assert double.dtype == torch.float64
    torch.testing.assert_close(double.float(), single, atol=1e-5, rtol=0)
