"""Re-extension under autograd without the stored gather: the same gradients as autograd
through the stencil, dense and on bricks, limited or not."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf import bricks
from torchsurf.flows._integrators import with_ring
from torchsurf.flows._reextension import _Reextend, _vector_jacobian, reextend
from torchsurf.flows.extension import cubic_stencil


@pytest.fixture(scope="module")
def sphere() -> ts.ImplicitSurface:
    grid = ts.Grid.cube(14, 1.4)
    return ts.ImplicitSurface(ts.sdf.sphere(grid, radius=0.8, dtype=torch.float64), grid)


@pytest.fixture(scope="module")
def torus_bricks() -> ts.ImplicitSurface:
    grid = ts.Grid.cube(25, 2.1)
    return bricks.from_dense(ts.ImplicitSurface(ts.sdf.torus(grid, 0.9, 0.4).double(), grid))


def _ring(surface: ts.ImplicitSurface) -> torch.Tensor:
    band = surface.band_mask()
    return with_ring(band, surface.layout) & ~band


def _field(surface: ts.ImplicitSurface, batch: int, generator: torch.Generator) -> torch.Tensor:
    shape = ((len(surface.layout), 2, 8, 8, 8) if surface.layout is not None
             else (batch, 2, *surface.grid.shape))
    return torch.rand(shape, generator=generator, dtype=torch.float64, requires_grad=True)


@pytest.mark.parametrize("limited", [False, True])
@pytest.mark.parametrize("storage", ["dense", "bricks"])
def test_gradient_equals_autograd_through_the_stencil(sphere, torus_bricks, storage, limited,
                                                     generator):
    surface = sphere if storage == "dense" else torus_bricks
    stencil = cubic_stencil(surface, _ring(surface), limited=limited)
    u = _field(surface, 2, generator)
    weights = torch.rand(u.shape, generator=generator, dtype=torch.float64)
    out = reextend(stencil, u)
    assert out.grad_fn is not None and "Reextend" in type(out.grad_fn).__name__
    # equal to the last bit unlimited on dense; limited, or on bricks, the untracked forward
    # runs a C kernel (_native_gather.limited_rows, brick_tricubic), whose sums round in
    # another order than the gathers'
    torch.testing.assert_close(out, stencil.apply(u), rtol=0,
                               atol=0 if storage == "dense" and not limited else 1e-15)
    mine, = torch.autograd.grad((out * weights).sum(), u)
    reference, = torch.autograd.grad((stencil.apply(u) * weights).sum(), u)
    torch.testing.assert_close(mine, reference, rtol=1e-12, atol=1e-12)
    # without the written values (every value's bounds formed again where it leaves its cell)
    unwritten = _vector_jacobian(stencil, u.detach(), weights)
    torch.testing.assert_close(unwritten, reference, rtol=1e-12, atol=1e-12)
    # the limiter clamps somewhere on random data, so both branches are exercised
    if limited:
        free = cubic_stencil(surface, _ring(surface), limited=False).apply(u)
        assert (free - out).abs().max() > 1e-3


def test_gradcheck_dense_limited(sphere, generator):
    stencil = cubic_stencil(sphere, _ring(sphere), limited=True)
    u = _field(sphere, 1, generator)
    assert torch.autograd.gradcheck(lambda x: _Reextend.apply(stencil, x), (u,), fast_mode=True)


def test_batch_one_data_on_a_batch_of_two(generator):
    grid = ts.Grid.cube(14, 1.4)
    phi = torch.cat([ts.sdf.sphere(grid, radius=r, dtype=torch.float64) for r in (0.7, 0.8)])
    surface = ts.ImplicitSurface(phi, grid)
    stencil = cubic_stencil(surface, _ring(surface), limited=True)
    u = _field(surface, 1, generator)
    weights = torch.rand((2, *u.shape[1:]), generator=generator, dtype=torch.float64)
    mine, = torch.autograd.grad((reextend(stencil, u) * weights).sum(), u)
    reference, = torch.autograd.grad((stencil.apply(u) * weights).sum(), u)
    assert mine.shape == u.shape
    torch.testing.assert_close(mine, reference, rtol=1e-12, atol=1e-12)


def test_untracked_calls_and_learned_geometry_take_the_plain_path(sphere, generator):
    stencil = cubic_stencil(sphere, _ring(sphere), limited=True)
    u = _field(sphere, 1, generator)
    with torch.no_grad():
        assert reextend(stencil, u).grad_fn is None
    phi = sphere.phi.detach().clone().requires_grad_(True)
    learned = ts.ImplicitSurface(phi, sphere.grid)
    moving = cubic_stencil(learned, _ring(learned), limited=True)
    out = reextend(moving, u)
    assert "Reextend" not in type(out.grad_fn).__name__
    out.sum().backward()
    assert phi.grad is not None and phi.grad.abs().sum() > 0


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("storage", ["dense", "bricks"])
@pytest.mark.parametrize("kind", ["heat euler", "heat rkc", "learned", "extension"])
def test_the_gradient_at_constant_data_is_the_linear_stencils(storage, kind, dtype):
    """On constant data the tricubic value misses the constant by a few units of roundoff
    either way, and the limiter's clamps were decided by rounding: the gradient of a heat flow
    (linear: its gradient is the same at any data) was 0.84-0.96 off its gradient at generic
    data. Ties within roundoff now take the stencil's own derivative (``_limiter.TIES``), on
    every path: the eager and compiled clamps, the C kernels and the re-extension's backward."""
    grid = ts.Grid.cube(22, 2.0)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    phi = (((x - 0.1) / 1.05) ** 2 + (y + 0.05) ** 2 + (z / 0.9) ** 2).sqrt() - 0.95
    dense = ts.ImplicitSurface(phi[None, None].to(dtype), grid)
    surface = dense if storage == "dense" else bricks.from_dense(dense)
    h2 = grid.spacing**2
    apply = {"heat euler": ts.HeatFlow(h2, method="euler"), "heat rkc": ts.HeatFlow(2 * h2),
             "learned": ts.nn.LearnedDiffusion(1, time=2.0).to(dtype),
             "extension": ts.flows.Extension(interpolation="cubic", limited=True)}[kind]
    shape = (1, 1, *grid.shape)
    # linear in (x, y, z): its values never leave their limiter's bounds (the flows keep it
    # nearly so), the flows act as their linear stencils
    generic = (0.5 + 0.1 * x + 0.05 * y - 0.07 * z)[None, None].to(dtype)
    weights = torch.rand(shape, dtype=torch.float64,
                         generator=torch.Generator().manual_seed(7)).to(dtype)
    if storage == "bricks":
        generic, weights = surface.from_dense(generic), surface.from_dense(weights)
    weights = weights * surface.band_mask()

    def gradient(u: torch.Tensor) -> torch.Tensor:
        u = u.clone().requires_grad_()
        return torch.autograd.grad((weights * apply(u, surface)).sum(), u)[0]

    at_constant = gradient(torch.full_like(generic, 0.5))
    at_generic = gradient(generic)
    difference = float((at_constant - at_generic).norm() / at_generic.norm())
    # the extension alone: 0 (0.44 before); after a flow, the few clamps the linear data meet
    # leave 1e-8 to 1e-6 (0.39-0.50 before)
    assert difference < 1e-5


@pytest.mark.parametrize("offset", [10.0, 100.0])
@pytest.mark.parametrize("kind", ["extension", "heat"])
def test_real_clamps_of_offset_float32_data_are_not_taken_for_ties(kind, offset):
    """A tie margin of 64 units of roundoff of the taps' magnitude took real clamps of float32
    data offset by 10 for ties (gradients 2e-3 to 4e-3 off float64's; 4e-7 before the
    margin), 8 units those of data offset by 20 to 100: ties are now only where the bounds
    are one to rounding (data constant there), whatever the offset."""
    grid = ts.Grid.cube(24, 2.0)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    phi = ((((x - 0.07) / 1.1) ** 2 + (y + 0.03) ** 2 + (z / 0.85) ** 2).sqrt() - 0.9)[None, None]
    generator = torch.Generator().manual_seed(3)
    rough = torch.rand((1, 1, *grid.shape), dtype=torch.float64, generator=generator)
    weights = torch.rand(rough.shape, dtype=torch.float64, generator=generator)
    apply = (ts.flows.Extension(interpolation="cubic", limited=True) if kind == "extension"
             else ts.HeatFlow(2 * grid.spacing**2))
    gradients = []
    for dtype, shift in ((torch.float64, 0.0), (torch.float32, offset)):
        surface = ts.ImplicitSurface(phi.to(dtype), grid)
        u = (rough + shift).to(dtype).requires_grad_()
        loss = ((weights * surface.band_mask()).to(dtype) * apply(u, surface)).sum()
        gradients.append(torch.autograd.grad(loss, u)[0].double())
    error = float((gradients[1] - gradients[0]).norm() / gradients[0].norm())
    assert error < 1e-4
