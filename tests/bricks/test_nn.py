"""The learning layers on bricks: gradient features, DiffusionBlock and the band losses give
the dense results on the band, per batch entry for a batch of shapes."""

from __future__ import annotations

import torch

import torchsurf as ts
from torchsurf.nn import DiffusionBlock, GradientFeatures, band_mse, psnr


def _data(surface, channels, seed):
    return surface.layout.rand(channels, torch.Generator().manual_seed(seed), torch.float64)


def test_gradient_features_and_block_equal_the_dense_ones_with_their_gradients(torus):
    dense, surface = torus
    band = dense.band_mask()
    u = _data(surface, 2, 0)
    (volume,) = surface.to_dense(u)
    (features,) = surface.to_dense(GradientFeatures()(u, surface))
    expected = GradientFeatures()(volume, dense)
    assert torch.allclose(features * band, expected * band, atol=1e-13)

    block = DiffusionBlock(2, time=[0.5, 2.0]).double()
    torch.nn.init.normal_(block.mlp[-1].weight, generator=torch.Generator().manual_seed(1))
    target = _data(surface, 2, 2)
    (target_volume,) = surface.to_dense(target)
    grads = []
    for data, goal, where in ((u, target, surface), (volume, target_volume, dense)):
        block.zero_grad()
        output = block(data, where)
        band_mse(output, goal, where).backward()
        grads.append([p.grad.clone() for p in block.parameters()])
        if where is surface:
            (packed_output,) = surface.to_dense(output)
        else:
            dense_output = output
    assert torch.allclose(packed_output * band, dense_output * band, atol=1e-13)
    for on_bricks, on_dense in zip(*grads, strict=True):
        assert torch.allclose(on_bricks, on_dense, rtol=1e-9, atol=1e-12)


def test_band_losses_are_per_entry_of_a_brick_batch(two_boxes):
    sphere, torus, both = two_boxes
    prediction, target = _data(both, 1, 3), _data(both, 1, 4)
    rows = [rows for rows, _ in both.entries()]
    alone = [psnr(prediction[r], target[r], entry) for r, (_, entry) in zip(rows, both.entries(),
                                                                           strict=True)]
    together = psnr(prediction, target, both)
    assert together.shape == (2,)
    torch.testing.assert_close(together, torch.cat(alone))
    squared = [band_mse(prediction[r], target[r], entry) * entry.band_mask().sum()
               for r, (_, entry) in zip(rows, both.entries(), strict=True)]
    torch.testing.assert_close(band_mse(prediction, target, both) * both.band_mask().sum(),
                               sum(squared))


def test_training_signals_on_a_brick_batch_are_the_dense_signals_on_each_band():
    from torchsurf import Grid, bricks
    from torchsurf.datasets import piecewise_constant_signal, smooth_signal

    grid = Grid(shape=(33, 41, 39), spacing=0.1, origin=(-1.9, -2.0, -1.6))
    phi = torch.cat([ts.sdf.sphere(grid, 0.9), ts.sdf.torus(grid, 1.0, 0.4)]).double()
    dense = ts.ImplicitSurface(phi, grid)
    packed_surface = bricks.from_dense(dense)
    band = dense.band_mask()
    for make in (smooth_signal, piecewise_constant_signal):
        packed = make(packed_surface, channels=2, seed=5)
        assert packed.shape == (len(packed_surface.layout), 2, 8, 8, 8)
        result = torch.cat(packed_surface.to_dense(packed))
        expected = make(dense, channels=2, seed=5)
        assert torch.allclose(result * band, expected * band, atol=1e-12), make.__name__


def test_widths_beyond_the_stored_bricks_are_refused_by_losses_and_flows():
    """``band_mse`` / ``psnr`` with a ``width`` (and a flow with a ``band_width``) wider than
    the bricks hold measured or evolved fewer nodes than the dense surface (5097 against 5421
    at 5 cells in an audit's case), silently; within the stored band they equal the dense."""
    import pytest

    from torchsurf import bricks

    grid = ts.Grid.cube(22, bound=1.6)
    h = grid.spacing
    dense = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9, center=(0.03, -0.02, 0.01),
                                             dtype=torch.float64), grid)
    surface = bricks.from_dense(dense)
    generator = torch.Generator().manual_seed(0)
    prediction, target = (torch.rand(1, 1, *grid.shape, dtype=torch.float64, generator=generator)
                          for _ in range(2))
    packed = surface.from_dense(prediction), surface.from_dense(target)
    torch.testing.assert_close(band_mse(*packed, surface, width=3 * h),
                               band_mse(prediction, target, dense, width=3 * h), rtol=1e-14, atol=0)
    for loss in (band_mse, psnr):
        with pytest.raises(ValueError, match=r"width=.* reaches \d+ nodes"):
            loss(*packed, surface, width=5 * h)
    with pytest.raises(ValueError, match=r"band_width=.* reaches \d+ nodes"):
        ts.HeatFlow(0.01, band_width=5 * h)(packed[0], surface)
