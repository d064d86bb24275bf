"""Flows on bricks: every integrator equals the dense flow on the band; batches; gradients."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

import torchsurf as ts
from torchsurf import Grid, bricks
from torchsurf.flows._integrators import with_ring
from torchsurf.flows.extension import BrickCubicStencil, CubicStencil
from torchsurf.operators.spectrum import laplace_beltrami_bound

MESHES = Path(__file__).resolve().parents[3] / "shared" / "data" / "meshes"


def _data(grid, channels=2, seed=0):
    return torch.randn(1, channels, *grid.shape, dtype=torch.float64,
                       generator=torch.Generator().manual_seed(seed))


def test_bound_ring_and_closest_point_stencil_equal_the_dense_ones(torus):
    dense, surface = torus
    assert laplace_beltrami_bound(surface) == pytest.approx(laplace_beltrami_bound(dense), rel=1e-12)
    band, packed_band = dense.band_mask(), surface.band_mask()
    region = with_ring(band)
    packed_region = with_ring(packed_band, surface.layout)
    (grown,) = surface.to_dense(packed_region.double())
    assert torch.equal(grown > 0, region)
    u = _data(dense.grid)
    expected = CubicStencil(dense, region, limited=True).apply(u)
    (result,) = surface.to_dense(
        BrickCubicStencil(surface, packed_region, limited=True).apply(surface.from_dense(u)))
    # to rounding: bricks interpolate by a C kernel whose sums round in their own order
    torch.testing.assert_close(result * region, expected * region, rtol=0, atol=1e-14)
    assert float(((result - u) * region).abs().max()) > 0.1  # the ring was re-extended


@pytest.mark.parametrize("kept", [True, False])
@pytest.mark.parametrize("path", ["slicing", "compiled"])
def test_closest_point_stencil_applied_in_chunks_equals_the_dense_one(torus, monkeypatch, kept,
                                                                      path):
    """A brick stencil gathers ``APPLY_CHUNK`` nodes at a time (bounded temporaries on large
    bands): small chunks, with the taps' packed indices kept or formed, give the dense
    stencil's numbers on every path."""
    from torchsurf.flows import extension

    dense, surface = torus
    region = with_ring(dense.band_mask())
    packed_region = with_ring(surface.band_mask(), surface.layout)
    monkeypatch.setattr(extension, "APPLY_CHUNK", 1000)
    monkeypatch.setattr(extension, "KEEP_SOURCES_NODES", 2**20 if kept else 0)
    stencil = BrickCubicStencil(surface, packed_region, limited=True)
    assert len(stencil.targets) > 3 * extension.APPLY_CHUNK
    assert (stencil.sources is not None) == kept
    u = _data(dense.grid).float()
    expected = CubicStencil(dense, region, limited=True).apply(u)
    (result,) = surface.to_dense(stencil.apply(surface.from_dense(u), path))
    torch.testing.assert_close(result * region, expected * region, rtol=0, atol=1e-5)


@pytest.mark.parametrize("method", ["rkc", "euler", "heun", "implicit", "crank_nicolson", "rk4"])
def test_heat_flow_equals_the_dense_flow_on_the_band(torus, method):
    """Every fixed-step integrator, torchdiffeq's ``rk4`` too (the adaptive ones take their
    error norms over the stored nodes, so they choose other steps: docs/bricks.md)."""
    dense, surface = torus
    u = _data(dense.grid)
    steps = {"implicit": 4, "rk4": 20}.get(method)
    flow = ts.flows.HeatFlow(time=0.01, method=method, steps=steps)
    expected = flow(u, dense)
    (result,) = surface.to_dense(flow(surface.from_dense(u), surface))
    band = dense.band_mask()
    assert torch.allclose(result * band, expected * band, atol=1e-12, rtol=0)


@pytest.mark.parametrize("method", ["rkc", "euler"])
def test_bricks_of_a_distance_run_the_dense_flows_wider_band(method):
    """On an analytic distance a dense flow evolves ``WIDE_BAND_CELLS`` cells (RKC then holds
    the ring); ``from_dense`` stores that band too, and the bricks' flow equals the dense one to
    rounding. With ``flow_band=False`` the bricks hold the surface's 3-cell band and evolve it,
    as the dense flow given that band does."""
    grid = Grid.cube(41, 2.0)
    dense = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0).double(), grid)
    u = torch.randn(1, 1, *grid.shape, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(4))
    band = dense.band_mask()
    flow = ts.flows.HeatFlow(time=0.02, method=method)
    wide = flow.evolving_width(dense)
    assert wide == pytest.approx(ts.surface.WIDE_BAND_CELLS * grid.spacing)

    surface = bricks.from_dense(dense)
    assert flow.evolving_width(surface) == wide
    (result,) = surface.to_dense(flow(surface.from_dense(u), surface))
    assert torch.allclose(result * band, flow(u, dense) * band, atol=1e-12, rtol=0)

    narrow = bricks.from_dense(dense, flow_band=False)
    assert len(narrow.layout) < len(surface.layout)
    assert flow.evolving_width(narrow) == narrow.band_width
    (result,) = narrow.to_dense(flow(narrow.from_dense(u), narrow))
    same_band = ts.flows.HeatFlow(time=0.02, method=method, band_width=dense.band_width)(u, dense)
    assert torch.allclose(result * band, same_band * band, atol=1e-12, rtol=0)
    assert not torch.allclose(result * band, flow(u, dense) * band, atol=1e-6, rtol=0)


def test_bricks_keep_the_surfaces_band_where_the_wider_one_nears_the_box():
    """A sphere 6 cells from the faces: its 5-cell band would come within 2 nodes of them,
    where bricks have no faces to stop the flux at; that entry keeps its 3-cell band, the other
    of the batch does not, and each equals the dense flow on its band alone."""
    grid = Grid.cube(33, 2.0)
    radii = (2.0 - 6 * grid.spacing, 1.2)
    phi = torch.cat([ts.sdf.sphere(grid, r) for r in radii]).double()
    dense = ts.ImplicitSurface(phi, grid)
    wide = ts.surface.WIDE_BAND_CELLS * grid.spacing
    assert dense.evolving_widths() == pytest.approx((wide, wide))
    surface = bricks.from_dense(dense)
    assert surface.evolving_widths() == pytest.approx((dense.band_width, wide))
    u = torch.randn(2, 1, *grid.shape, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(5))
    result = surface.to_dense(ts.flows.HeatFlow(time=0.01)(surface.from_dense(u), surface))
    for b, width in enumerate((dense.band_width, wide)):
        alone = ts.ImplicitSurface(phi[b:b + 1], grid)
        expected = ts.flows.HeatFlow(time=0.01, band_width=width)(u[b:b + 1], alone)
        band = alone.band_mask()
        assert torch.allclose(result[b] * band, expected * band, atol=1e-12, rtol=0), b


@pytest.mark.parametrize("sharpness", [0.1, 0.05])
def test_saturated_phi_gets_the_dense_band_and_flow(sharpness):
    """``tanh(d / w)``: ``|phi| / W`` stays small far from S, where the dense band keeps only
    nodes near a crossing; the bricks' band did not, and took in 30% more nodes."""
    grid = Grid.cube(48, 2.35)
    phi = torch.tanh(ts.sdf.sphere(grid, 0.8).double() / sharpness)
    dense = ts.ImplicitSurface(phi, grid)
    surface = bricks.from_dense(dense)
    band = dense.band_mask()
    (brick_band,) = surface.to_dense(surface.band_mask())
    assert torch.equal(brick_band, band)
    u = torch.randn(1, 1, *grid.shape, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(1))
    flow = ts.flows.HeatFlow(time=0.01)
    (result,) = surface.to_dense(flow(surface.from_dense(u), surface))
    assert torch.allclose(result * band, flow(u, dense) * band, atol=1e-12, rtol=0)


def test_heat_flow_batch_of_shapes_on_their_own_boxes_equals_each_alone(two_boxes):
    sphere, torus, both = two_boxes
    u = torch.randn(len(both.layout), 1, 8, 8, 8, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(3))
    count = len(sphere.layout)
    for method in ("rkc", "implicit"):
        flow = ts.flows.HeatFlow(time=0.01, method=method)
        together = flow(u, both)
        alone = torch.cat([flow(u[:count], sphere), flow(u[count:], torus)])
        band = both.band_mask()
        assert torch.allclose(together * band, alone * band, atol=1e-12, rtol=0), method


def test_heat_flow_on_bricks_keeps_the_maximum_principle_on_a_mesh():
    mesh_file = MESHES / "bunny_closed.obj"
    if not mesh_file.exists():
        pytest.skip("shared meshes not present")
    mesh = ts.mesh.load(mesh_file)
    grid = ts.mesh.fit_grid(mesh, 40, margin=0.15)
    surface = bricks.from_mesh(mesh, grid)
    assert len(surface.layout) * 512 < ts.backend.COMPILE_MIN_VOXELS  # eager: no compile time
    points = surface.layout.points()
    # smooth data in [-1, 1]
    u0 = torch.sin(40.0 * points[:, :1]) * torch.cos(30.0 * points[:, 1:2] + 20 * points[:, 2:])
    u = ts.flows.HeatFlow(time=(6 * grid.spacing) ** 2)(u0, surface)
    band = surface.band_mask()
    low, high = u0[with_ring(band, surface.layout)].min(), u0[with_ring(band, surface.layout)].max()
    assert u[band].max() <= high + 1e-6 and u[band].min() >= low - 1e-6
    assert u[band].std() < 0.8 * u0[band].std()  # and it did smooth


def test_heat_flow_on_bricks_solves_the_sphere_exactly_to_second_order():
    errors = []
    for n in (33, 49):
        case = ts.exact.sphere_harmonic(2, n, dtype=torch.float64)
        surface = bricks.from_dense(case.phi, case.grid)
        u = ts.flows.HeatFlow(time=0.05)(surface.from_dense(case.u), surface)
        (volume,) = surface.to_dense(u)
        decay = -6.0 * 0.05 / ts.exact.SPHERE_RADIUS**2
        exact = case.u * torch.exp(torch.tensor(decay, dtype=torch.float64))
        on_s = case.phi.abs() < 0.5 * case.grid.spacing
        errors.append(float((volume - exact)[on_s].abs().max() / exact[on_s].abs().max()))
    assert errors[1] < errors[0] / 1.7, errors


def test_gradcheck_heat_flow_on_bricks_in_the_data():
    grid = Grid.cube(21, 2.0)
    surface = bricks.from_dense(ts.sdf.sphere(grid, 1.0).double(), grid)
    flow = ts.flows.HeatFlow(time=0.004, method="euler", steps=2)
    u = torch.randn(len(surface.layout), 1, 8, 8, 8, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(2), requires_grad=True)
    band = surface.band_mask()
    assert torch.autograd.gradcheck(lambda x: flow(x, surface)[band], (u,), fast_mode=True)


@pytest.mark.parametrize("settings", [
    {"diffusivity": "total_variation", "eps": 0.1},
    {"diffusivity": "perona_malik", "contrast": 0.5, "scheme": "octant"},
])
def test_anisotropic_flow_equals_the_dense_flow_on_the_band(torus, settings):
    dense, surface = torus
    u = torch.rand(1, 2, *dense.grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(4))
    flow = ts.flows.AnisotropicFlow(time=0.003, **settings)
    expected = flow(u, dense)
    (result,) = surface.to_dense(flow(surface.from_dense(u), surface))
    band = dense.band_mask()
    assert torch.allclose(result * band, expected * band, atol=1e-12, rtol=0)
    coupled = ts.anisotropic_diffusion(u, dense, settings["diffusivity"], coupled=True)
    (packed,) = surface.to_dense(ts.anisotropic_diffusion(
        surface.from_dense(u), surface, settings["diffusivity"], coupled=True))
    assert torch.allclose(packed * band, coupled * band, atol=1e-12 * coupled.abs().max())


def test_flows_not_ported_to_bricks_say_so(torus):
    _, surface = torus
    u = torch.zeros(len(surface.layout), 3, 8, 8, 8, dtype=torch.float64)
    with pytest.raises(NotImplementedError, match="BrickSurface"):
        ts.flows.Flow(time=0.01)(u, surface)  # a flow that does not declare supports_bricks
    with pytest.raises(NotImplementedError, match="Flow does not run on a BrickSurface"):
        ts.flows.ColorDenoise(0.01, brightness=ts.flows.Flow(time=0.01))(u, surface)


def test_flows_keep_their_band_and_ring_and_dilate_once_per_surface(torus, monkeypatch):
    """The ring around a flow's band is a halo gather on bricks: formed on the first call and
    kept beside the band, with the same numbers; re-formed at every call while phi needs grad."""
    dense, surface = torus
    u = surface.from_dense(_data(dense.grid, channels=1))
    flow = ts.flows.HeatFlow(time=0.004)
    first = flow(u, surface)
    band = flow.band_mask(surface)
    assert torch.equal(flow.region_mask(surface), with_ring(band, surface.layout))
    calls = []
    dilate = type(surface.layout).dilate
    monkeypatch.setattr(type(surface.layout), "dilate",
                        lambda self, *a, **k: calls.append(1) or dilate(self, *a, **k))
    assert torch.equal(flow(u, surface), first)
    assert calls == []
    learned = bricks.BrickSurface(surface.phi.clone().requires_grad_(), surface.layout)
    flow(u, learned)
    assert len(calls) >= 1


def test_heat_flow_on_bricks_differentiates_a_learned_phi_alone():
    """The data fixed, ``phi`` learned: the flow's re-extensions take their gradient to
    ``phi`` (the native gather, which records no graph, does not run): the dense flow's."""
    grid = Grid.cube(19, 1.6)
    points = grid.points(dtype=torch.float64)
    base = ts.sdf.sphere(grid, 0.75).double()
    bump = torch.sin(3 * points[..., 0] - points[..., 2])[None, None]
    u = torch.sin(3 * points[..., 0] + 2 * points[..., 1])[None, None]
    weight = torch.cos(5 * points[..., 0] - points[..., 1])[None, None]
    layout = bricks.from_dense(base, grid).layout
    flow = ts.flows.HeatFlow(time=0.01, method="euler", steps=3, band_width=3 * grid.spacing)
    gradients = []
    for layer in ("dense", "bricks"):
        amount = torch.full((), 0.02, dtype=torch.float64, requires_grad=True)
        phi = base + amount * bump
        if layer == "dense":
            surface = ts.ImplicitSurface(phi, grid)
            loss = (weight * surface.band_mask() * flow(u, surface)).sum()
        else:
            surface = bricks.BrickSurface(layout.from_dense(phi, fill="quadratic"), layout)
            loss = (surface.from_dense(weight) * surface.band_mask()
                    * flow(surface.from_dense(u), surface)).sum()
        (gradient,) = torch.autograd.grad(loss, amount)
        gradients.append(gradient)
    assert abs(float(gradients[0])) > 1e-3
    torch.testing.assert_close(gradients[1], gradients[0], rtol=1e-9, atol=0)
