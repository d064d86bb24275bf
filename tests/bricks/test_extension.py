"""Extension on bricks: every method equals the dense extension on the band; batches; gradients."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf import bricks
from torchsurf.flows import Extension, closest_point_extension, pde_extension


def _data(grid, channels=2, seed=0):
    """Data that varies along the normals (so that extending changes it), scaled so that its
    largest value lies near S (the pde method's stopping scale)."""
    points = grid.points(dtype=torch.float64)
    radius = points.norm(dim=-1)
    u = torch.stack([torch.sin(3 * points[..., c]) * torch.exp(-(radius - 1.0) ** 2)
                     for c in range(channels)])
    return u[None]


@pytest.mark.parametrize("settings", [
    {"method": "closest_point"},
    {"method": "closest_point", "interpolation": "cubic"},
    {"method": "pde"},
    {"method": "pde", "width": 0.2, "tolerance": 1e-4},
])
def test_extension_equals_the_dense_extension_on_the_band(torus, settings):
    dense, surface = torus
    u = _data(dense.grid)
    extension = Extension(**settings)
    expected = extension(u, dense)
    (result,) = surface.to_dense(extension(surface.from_dense(u), surface))
    band = dense.band_mask(settings.get("width"))
    assert not torch.allclose(expected * band, u * band)  # it did extend
    assert torch.allclose(result * band, expected * band, atol=1e-12, rtol=0)


def test_extension_of_a_batch_equals_each_entry_alone(two_boxes):
    sphere, torus, both = two_boxes
    u = torch.randn(len(both.layout), 2, 8, 8, 8, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(1))
    count = len(sphere.layout)
    band = both.band_mask()
    for function in (closest_point_extension, pde_extension):
        together = function(u, both)
        alone = torch.cat([function(u[:count], sphere), function(u[count:], torus)])
        assert torch.allclose(together * band, alone * band, atol=1e-13, rtol=0), function
    mask = both.band_mask(0.15)
    together = closest_point_extension(u, both, interpolation="cubic", mask=mask)
    assert torch.equal(together[~mask.expand_as(u)], u[~mask.expand_as(u)])


def test_gradcheck_linear_closest_point_extension_on_bricks_in_data_and_phi():
    grid = ts.Grid.cube(21, 2.0)
    reference = bricks.from_dense(ts.sdf.sphere(grid, 1.0).double(), grid)
    band = reference.band_mask()
    picked = band.flatten().nonzero().flatten()[::61]
    u = torch.randn(len(reference.layout), 1, 8, 8, 8, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(2), requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x: closest_point_extension(x, reference).flatten()[picked], (u,), fast_mode=True)
    base = reference.phi.detach()

    def in_phi(scale):
        surface = bricks.BrickSurface(base * scale, reference.layout, reference.band_width)
        return closest_point_extension(u.detach(), surface).flatten()[picked]

    scale = torch.ones((), dtype=torch.float64).add(0.05).requires_grad_()
    assert torch.autograd.gradcheck(in_phi, (scale,))


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_gradcheck_closest_point_extension_on_bricks_in_phi_alone(interpolation):
    """``phi`` learned, the data fixed: the native tricubic gather (which records no graph)
    must not run where the stencil's weights need a gradient from ``phi``."""
    grid = ts.Grid.cube(19, 1.6)
    points = grid.points(dtype=torch.float64)
    reference = bricks.from_dense(ts.sdf.sphere(grid, 0.75).double(), grid)
    bump = reference.from_dense(torch.sin(3 * points[..., 0] - points[..., 2])[None, None])
    u = reference.from_dense(torch.sin(3 * points[..., 0] + 2 * points[..., 1])[None, None])
    picked = reference.band_mask().flatten().nonzero().flatten()[::37]

    def in_phi(amount):
        surface = bricks.BrickSurface(reference.phi.detach() + amount * bump, reference.layout,
                                      reference.band_width)
        return closest_point_extension(u, surface, interpolation=interpolation).flatten()[picked]

    amount = torch.full((), 0.02, dtype=torch.float64, requires_grad=True)
    assert in_phi(amount).requires_grad
    assert torch.autograd.gradcheck(in_phi, (amount,))


def test_packed_data_is_required_on_bricks(torus):
    dense, surface = torus
    with pytest.raises(ValueError, match=r"u must be a packed band field"):
        Extension()(torch.zeros(1, 1, *dense.grid.shape, dtype=torch.float64), surface)


@pytest.mark.parametrize("settings", [
    {"method": "closest_point"},
    {"method": "closest_point", "interpolation": "cubic"},
    {"method": "pde"},
])
def test_a_width_beyond_the_stored_band_is_refused_or_equals_dense(settings):
    """A width wider than the bricks' band left 113 nodes within it unextended (the band
    drops nodes whose neighbours are not stored), 0.4 off the dense extension, silently; the
    bricks built at that width equal the dense extension."""
    grid = ts.Grid.cube(41, 1.3)
    h = grid.spacing
    centre = torch.tensor([0.07, -0.05, 0.11], dtype=torch.float64)
    phi = ((grid.points(dtype=torch.float64) - centre).norm(dim=-1) - 0.6)[None, None]
    dense = ts.ImplicitSurface(phi, grid)
    u = _data(grid, channels=1)
    extension = Extension(width=4 * h, **settings)
    narrow = bricks.from_dense(dense, flow_band=False)
    with pytest.raises(ValueError, match=r"width=.* reaches \d+ nodes .* band_width >= \d"):
        extension(narrow.from_dense(u), narrow)
    band = dense.band_mask(4 * h)
    for wide in (bricks.from_dense(phi, grid, band_width=4 * h, flow_band=False),
                 bricks.from_dense(dense)):  # holding the flows' 5-cell band
        (result,) = wide.to_dense(extension(wide.from_dense(u), wide))
        assert torch.allclose(result * band, extension(u, dense) * band, atol=1e-12, rtol=0)


def test_linear_extension_to_a_mask_beyond_the_stored_bricks_is_refused(torus):
    """The linear path failed in the sampler, naming 'points', which the caller never gave."""
    _, surface = torus
    everywhere = torch.ones(len(surface.layout), 1, 8, 8, 8, dtype=torch.bool)
    u = surface.from_dense(_data(surface.grid))
    for interpolation in ("linear", "cubic"):
        with pytest.raises(ValueError, match="reads nodes outside the stored bricks"):
            closest_point_extension(u, surface, interpolation=interpolation, mask=everywhere)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("limited", [False, True])
def test_native_brick_interpolation_equals_the_gathers(dtype, limited):
    """``path="auto"`` re-extends on bricks by a C kernel reading the stencil's compact form
    (:func:`torchsurf.flows._native_gather.brick_tricubic`): the same values as the eager
    gathers to rounding, with the limiter clamping the same nodes (random data: many), on
    three channels, for every node of the band and for a stencil that keeps only the nodes
    whose taps are readable."""
    from torchsurf.flows import _native_gather
    from torchsurf.flows.extension import cubic_stencil

    if _native_gather.LIBRARY.load() is None:
        pytest.skip("no C compiler")
    grid = ts.Grid.cube(33, 1.8)
    surface = bricks.from_dense(ts.ImplicitSurface(ts.sdf.torus(grid, 0.9, 0.35, dtype=dtype),
                                                   grid))
    u = surface.from_dense(torch.rand(1, 3, *grid.shape, dtype=dtype,
                                      generator=torch.Generator().manual_seed(3)))
    before = u.clone()
    mask = surface.band_mask()
    full = cubic_stencil(surface, mask, limited=limited)
    part = cubic_stencil(surface, mask, limited=limited, readable=mask)
    assert 0 < len(part.targets) < len(full.targets)
    for stencil in (full, part):
        native = stencil.apply(u, path="auto")
        gathered = stencil.apply(u, path="slicing")
        tolerance = 1e-6 if dtype == torch.float32 else 1e-14
        torch.testing.assert_close(native, gathered, rtol=0, atol=tolerance)
        assert not torch.equal(native, u)
    torch.testing.assert_close(u, before, rtol=0, atol=0)
    if limited:
        free = cubic_stencil(surface, mask).apply(u, path="slicing")
        assert float((free - native).abs().max()) > 1e-2  # the limiter clamped values


def test_native_readability_check_equals_the_tap_gathers(torus, monkeypatch):
    """A stencil with ``readable`` keeps the nodes whose 64 taps are all stored and readable:
    the C check (:func:`torchsurf.flows._native_gather.brick_taps_readable`, no ``(n, 64)``
    positions formed) keeps the same nodes as the gathered positions, here with taps in
    bricks that are not stored (every stored node a target) and a random tenth of the nodes
    unreadable."""
    from torchsurf.flows import _native_gather
    from torchsurf.flows.extension import BrickCubicStencil

    if _native_gather.LIBRARY.load() is None:
        pytest.skip("no C compiler")
    _, surface = torus
    everywhere = torch.ones(len(surface.layout), 1, 8, 8, 8, dtype=torch.bool)
    readable = torch.rand(everywhere.shape, generator=torch.Generator().manual_seed(7)) > 0.1
    native = BrickCubicStencil(surface, everywhere, readable=readable)
    monkeypatch.setattr(_native_gather, "brick_taps_readable", lambda *args: None)
    gathered = BrickCubicStencil(surface, everywhere, readable=readable)
    assert 0 < len(native.targets) < everywhere.sum() // 2
    assert torch.equal(native.targets, gathered.targets)
    for mine, reference in zip((native.bases, native.local, native.weights),
                               (gathered.bases, gathered.local, gathered.weights), strict=True):
        assert torch.equal(mine, reference)
