"""Gradient features, the residual diffusion block and the band-masked losses."""

from __future__ import annotations

import math

import pytest
import torch

import torchsurf as ts
from torchsurf.nn import (
    DiffusionBlock,
    GradientFeatures,
    band_mse,
    feature_count,
    gradient_features,
    psnr,
)


@pytest.fixture(scope="module")
def sphere():
    grid = ts.Grid.cube(33, 1.4)
    phi = ts.sdf.sphere(grid, radius=0.9, dtype=torch.float64)
    return grid, ts.ImplicitSurface(phi, grid)


def test_gradient_norm_of_the_height_function(sphere):
    """``u = z`` on a sphere of radius R: ``|grad_S u| = sin(polar angle)``, per cell ``h sin``."""
    grid, surface = sphere
    points = grid.points(dtype=torch.float64)
    z = points[..., 2] / points.norm(dim=-1).clamp(min=1e-9)  # extended along normals
    u = z[None, None]
    features = gradient_features(u, surface, eps=1e-12)
    near = surface.band_mask(grid.spacing)
    radius = points.norm(dim=-1)[None, None]
    exact = grid.spacing * torch.sqrt((1 - z**2).clamp(min=0))[None, None] / radius
    error = (features - exact).abs()[near].max()
    assert error < 0.02 * grid.spacing, float(error / grid.spacing)


def test_features_are_rotation_invariant_products(sphere):
    grid, surface = sphere
    generator = torch.Generator().manual_seed(0)
    u = torch.rand((2, 3, *grid.shape), generator=generator, dtype=torch.float64)
    features = GradientFeatures()(u, surface)
    assert features.shape == (2, feature_count(3), *grid.shape) == (2, 6, *grid.shape)
    gradient = ts.operators.functional.tangential_gradient(u, surface.normal, grid.spacing)
    gradient = (gradient * grid.spacing).unflatten(1, (3, 3))
    torch.testing.assert_close(features[:, 4], (gradient[:, 0] * gradient[:, 2]).sum(dim=1))
    torch.testing.assert_close(features[:, 1] ** 2, (gradient[:, 1] ** 2).sum(dim=1) + 1e-12)
    # a rotation of the channels' common frame leaves norms and products unchanged: swapping
    # the grid's x and y axes on data and surface permutes the nodes only
    swapped = ts.ImplicitSurface(surface.phi.transpose(3, 4), grid)
    again = gradient_features(u.transpose(3, 4), swapped)
    torch.testing.assert_close(again, features.transpose(3, 4), rtol=1e-10, atol=1e-10)
    assert gradient_features(u, surface, pairs=False).shape[1] == 3


def test_block_starts_as_identity_and_changes_only_the_band(sphere):
    grid, surface = sphere
    generator = torch.Generator().manual_seed(1)
    u = torch.rand((2, 2, *grid.shape), generator=generator, dtype=torch.float64)
    block = DiffusionBlock(2, hidden=8, time=[1.0, 2.0]).double()
    torch.testing.assert_close(block(u, surface), u)
    torch.nn.init.normal_(block.mlp[-1].weight, generator=generator)
    out = block(u, surface)
    outside = ~surface.band_mask().expand_as(u)
    torch.testing.assert_close(out[outside], u[outside])
    assert (out - u).abs()[~outside].max() > 1e-3
    # the same as the MLP applied as a 1x1x1 convolution everywhere, then masked
    diffused = block.diffusion(u, surface)
    features = torch.cat([diffused, gradient_features(diffused, surface)], dim=1)
    first, last = block.mlp[0], block.mlp[2]
    hidden = torch.relu(torch.nn.functional.conv3d(features, first.weight[..., None, None, None],
                                                   first.bias))
    update = torch.nn.functional.conv3d(hidden, last.weight[..., None, None, None], last.bias)
    torch.testing.assert_close(out, torch.where(~outside, u + update, u))


def test_block_gradients_reach_every_parameter(sphere):
    grid, surface = sphere
    generator = torch.Generator().manual_seed(2)
    u = torch.rand((1, 2, *grid.shape), generator=generator, dtype=torch.float64)
    block = DiffusionBlock(2, hidden=4).double()
    # every parameter drawn from the test's generator, and the hidden units alive on the band:
    # with the global RNG's draw, all four ReLUs can be dead (features are O(1) at most)
    torch.nn.init.normal_(block.mlp[0].weight, generator=generator)
    torch.nn.init.constant_(block.mlp[0].bias, 3.0)
    torch.nn.init.normal_(block.mlp[-1].weight, generator=generator)
    band_mse(block(u, surface), u.flip(2), surface).backward()
    for name, parameter in block.named_parameters():
        assert parameter.grad is not None and parameter.grad.abs().sum() > 0, name


def test_band_mse_and_psnr(sphere):
    grid, surface = sphere
    generator = torch.Generator().manual_seed(3)
    target = torch.rand((2, 2, *grid.shape), generator=generator, dtype=torch.float64)
    noise = torch.zeros_like(target)
    noise[0] = 0.1
    noise[1] = 0.01
    band = surface.band_mask()
    noise = torch.where(band, noise, 5.0)  # errors outside the band do not count
    mse = band_mse(target + noise, target, surface)
    expected = (0.1**2 + 0.01**2) / 2
    torch.testing.assert_close(mse, torch.tensor(expected, dtype=torch.float64))
    db = psnr(target + noise, target, surface)
    torch.testing.assert_close(db, torch.tensor([20.0, 40.0], dtype=torch.float64))
    torch.testing.assert_close(psnr(target + noise, target, surface, peak=10.0),
                               torch.tensor([40.0, 60.0], dtype=torch.float64))
    assert math.isinf(float(psnr(target, target, surface)[0]))
    with pytest.raises(ValueError, match="target"):
        band_mse(target, target[:, :1], surface)
    with pytest.raises(ValueError, match="peak"):
        psnr(target, target, surface, peak=0.0)
    with pytest.raises(ValueError, match="band holds no node"):  # its mean was NaN
        band_mse(target, target, surface, width=1e-9)
    with pytest.raises(ValueError, match=r"band holds no node .* batch entries \[0, 1\]"):
        psnr(target, target, surface, width=1e-9)


def test_an_exact_entry_of_psnr_passes_a_zero_gradient(sphere):
    """An exact entry's PSNR is inf; its gradient was NaN (``inf * 0``) and, through a mean
    over the batch, turned every parameter's gradient to NaN."""
    grid, surface = sphere
    generator = torch.Generator().manual_seed(5)
    target = torch.rand((2, 1, *grid.shape), generator=generator, dtype=torch.float64)
    prediction = target.clone()
    prediction[1] += 0.1 * torch.randn(target[1].shape, generator=generator, dtype=target.dtype)
    prediction.requires_grad_()
    db = psnr(prediction, target, surface)
    assert math.isinf(float(db[0])) and math.isfinite(float(db[1]))
    (gradient,) = torch.autograd.grad(db.mean(), prediction)
    assert torch.isfinite(gradient).all() and float(gradient[0].abs().max()) == 0.0
    (alone,) = torch.autograd.grad(psnr(prediction[1:], target[1:], surface).mean(), prediction)
    torch.testing.assert_close(gradient[1], alone[1] / 2)
    # float32 off by 1e-20: MSE 1e-40 is not 0, but peak^2 / MSE overflows (a review found NaN)
    single = ts.ImplicitSurface(surface.phi.float(), grid)
    near = torch.zeros((2, 1, *grid.shape))
    off = (near + torch.tensor([1e-20, 0.1]).view(2, 1, 1, 1, 1)).requires_grad_()
    db = psnr(off, near, single)
    assert math.isinf(float(db[0])) and math.isfinite(float(db[1]))
    (gradient,) = torch.autograd.grad(db.mean(), off)
    assert torch.isfinite(gradient).all() and float(gradient[0].abs().max()) == 0.0
    # MSE 1e-30 to 1e-20: finite decibels, and a finite gradient (it was inf, the division's
    # derivative overflowing)
    for offset in (1e-15, 1e-12, 1e-10):
        off = (near + torch.tensor([offset, 0.1]).view(2, 1, 1, 1, 1)).requires_grad_()
        db = psnr(off, near, single)
        (gradient,) = torch.autograd.grad(db.mean(), off)
        assert math.isfinite(float(db[0])) and torch.isfinite(gradient).all(), offset


def test_arguments_are_checked_and_named():
    """Read by their truth, ``pairs=1`` passed and ``pairs="no"`` counted as true; a keyword
    that LearnedDiffusion does not take was reported as LearnedDiffusion's."""
    grid = ts.Grid.cube(10, 1.4)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=0.9), grid)
    u = torch.rand((1, 2, *grid.shape))
    with pytest.raises(TypeError, match="pairs"):
        gradient_features(u, surface, pairs=1)
    with pytest.raises(TypeError, match=r"DiffusionBlock got unexpected keyword arguments \['bogus'\]"):
        DiffusionBlock(2, bogus=1)
    DiffusionBlock(2, scheme="symmetric", learn_time=False)  # LearnedDiffusion's own pass
    with pytest.raises(TypeError, match="learned times are torch.float32"):
        ts.nn.LearnedDiffusion(2)(u.double(), ts.ImplicitSurface(surface.phi.double(), grid))
    fixed = ts.nn.LearnedDiffusion(2, learn_time=False)  # no parameter: follows the data
    assert fixed(u.double(), ts.ImplicitSurface(surface.phi.double(), grid)).dtype == torch.float64


def test_data_of_batch_one_on_a_surface_of_batch_two_gives_two_entries():
    """As the flows and LearnedDiffusion do, the block and the losses take one datum on each
    of the surface's entries (the block indexed out of range, the losses raised torch's own
    expand error)."""
    grid = ts.Grid.cube(17, 1.4)
    phi = torch.cat([ts.sdf.sphere(grid, radius=0.9, dtype=torch.float64),
                     ts.sdf.torus(grid, 0.8, 0.35, dtype=torch.float64)])
    pair = ts.ImplicitSurface(phi, grid)
    u = torch.rand((1, 2, *grid.shape), generator=torch.Generator().manual_seed(4),
                   dtype=torch.float64)
    block = DiffusionBlock(2).double()
    torch.nn.init.normal_(block.mlp[-1].weight, generator=torch.Generator().manual_seed(5))
    both = block(u, pair)
    assert both.shape == (2, 2, *grid.shape)
    for b in range(2):
        alone = ts.ImplicitSurface(phi[b:b + 1], grid)
        torch.testing.assert_close(both[b:b + 1], block(u, alone))
        torch.testing.assert_close(psnr(u + 0.1, u, pair)[b], psnr(u + 0.1, u, alone)[0])
    torch.testing.assert_close(band_mse(u + 0.1, u, pair), torch.tensor(0.01, dtype=torch.float64))


def test_counts_given_as_whole_floats_or_bad_are_named():
    block = DiffusionBlock(2.0)  # check_count's contract: integral floats are counts
    assert block.channels == 2 and isinstance(block.channels, int)
    assert block.mlp[-1].out_features == 2
    assert feature_count(3) == 6 and feature_count(3, pairs=False) == 3
    for bad in (-3, 0, 2.5):
        with pytest.raises(ValueError, match="channels must be a whole number >= 1"):
            feature_count(bad)
