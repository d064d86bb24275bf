"""The Chebyshev heat semigroup on bricks: the brick stencil's transpose, equality with the dense
semigroup (HeatFlow and LearnedDiffusion), batches, and gradients in the data and the times."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf import Grid, bricks
from torchsurf.flows._integrators import with_ring
from torchsurf.flows.exponential import BandLaplacian, heat_semigroup
from torchsurf.flows.extension import BrickCubicStencil, CubicStencil


def _data(grid, channels=2, seed=0):
    return torch.randn(1, channels, *grid.shape, dtype=torch.float64,
                       generator=torch.Generator().manual_seed(seed))


def test_brick_stencil_transpose_is_the_adjoint_and_equals_the_dense_one(torus):
    dense, surface = torus
    band, packed_band = dense.band_mask(), surface.band_mask()
    ring = with_ring(band) & ~band
    packed_ring = with_ring(packed_band, surface.layout) & ~packed_band
    stencil = BrickCubicStencil(surface, packed_ring)
    x, y = (surface.from_dense(_data(dense.grid, seed=s)) for s in (1, 2))
    torch.testing.assert_close((stencil.apply(x) * y).sum(), (x * stencil.transpose(y)).sum(),
                               rtol=1e-13, atol=0)
    u = _data(dense.grid, seed=3)
    (scattered,) = surface.to_dense(stencil.transpose(surface.from_dense(u)), fill=float("nan"))
    stored = ~scattered.isnan()
    expected = CubicStencil(dense, ring).transpose(u)
    torch.testing.assert_close(scattered[stored], expected[stored], rtol=0, atol=1e-13)
    with pytest.raises(ValueError, match="limited stencil is not linear"):
        BrickCubicStencil(surface, packed_ring, limited=True).transpose(x)


@pytest.mark.parametrize("time", [0.01, 0.1])
def test_chebyshev_heat_flow_equals_the_dense_flow_on_the_band_and_ring(torus, time):
    dense, surface = torus
    u = _data(dense.grid)
    flow = ts.flows.HeatFlow(time=time, method="chebyshev")
    expected = flow(u, dense)
    (result,) = surface.to_dense(flow(surface.from_dense(u), surface))
    region = with_ring(dense.band_mask())
    assert torch.allclose(result * region, expected * region, atol=1e-13, rtol=0)


def test_learned_diffusion_on_bricks_equals_the_dense_layer(torus):
    dense, surface = torus
    u = _data(dense.grid)
    layer = ts.nn.LearnedDiffusion(2, time=[1.0, 6.0]).double()
    expected = layer(u, dense).detach()
    (result,) = surface.to_dense(layer(surface.from_dense(u), surface).detach())
    region = with_ring(dense.band_mask())
    assert torch.allclose(result * region, expected * region, atol=1e-13, rtol=0)


def test_a_batch_shares_one_bound_and_equals_each_entry_to_the_tolerance(two_boxes):
    sphere, torus, both = two_boxes
    u = torch.randn(len(both.layout), 1, 8, 8, 8, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(4))
    count = len(sphere.layout)
    flow = ts.flows.HeatFlow(time=0.02, method="chebyshev")
    together = flow(u, both)
    alone = torch.cat([flow(u[:count], sphere), flow(u[count:], torus)])
    band = both.band_mask()
    assert torch.allclose(together * band, alone * band, atol=1e-12, rtol=0)


def test_gradcheck_chebyshev_on_bricks_in_the_data_and_the_times():
    """Along four random directions of ``u0`` and two times (``fast_mode``: a random
    projection of the output)."""
    grid = Grid.cube(21, 2.0)
    surface = bricks.from_dense(ts.sdf.sphere(grid, 1.0).double(), grid)
    operator = BandLaplacian(surface, path="slicing")
    generator = torch.Generator().manual_seed(5)
    u0 = torch.rand(len(surface.layout), 2, 8, 8, 8, dtype=torch.float64, generator=generator)
    directions = torch.randn((4, *u0.shape), dtype=torch.float64, generator=generator)
    times = torch.tensor([0.3, 2.0], dtype=torch.float64) * grid.spacing**2

    def run(along: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return heat_semigroup(u0 + torch.tensordot(along, directions, dims=1), operator, t)

    along = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (along, times.requires_grad_(True)), fast_mode=True)


def test_gradcheck_chebyshev_on_bricks_in_phi():
    """Through ``phi`` (closest points, normals and ``W`` recomputed in backward), along a
    one-parameter family of shapes on one layout."""
    grid = Grid.cube(21, 2.0)
    phi = ts.sdf.sphere(grid, 1.0).double()
    layout = bricks.from_dense(phi, grid).layout
    generator = torch.Generator().manual_seed(7)
    bump = torch.rand(phi.shape, dtype=torch.float64, generator=generator)
    u0 = torch.rand(len(layout), 1, 8, 8, 8, dtype=torch.float64, generator=generator)
    times = torch.tensor([1.5 * grid.spacing**2], dtype=torch.float64, requires_grad=True)

    def run(scale: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        surface = bricks.BrickSurface(layout.from_dense(phi + scale * bump), layout)
        return heat_semigroup(u0, BandLaplacian(surface, path="slicing"), t)

    scale = torch.tensor(0.01, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (scale, times), fast_mode=True)
