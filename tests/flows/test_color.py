"""ColorDenoise: chroma and brightness flowed apart, noise removed, shapes kept."""

from __future__ import annotations

import torch

import torchsurf as ts
from torchsurf.flows import ColorDenoise, HeatFlow


def test_colour_denoising_reduces_noise_on_the_surface():
    grid = ts.Grid.cube(17, bound=1.3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    z = grid.points(dtype=torch.float64)[..., 2][None, None]
    clean = torch.cat((0.6 + 0.3 * (z > 0), 0.4 + 0 * z, 0.5 - 0.2 * (z > 0)), dim=1)
    generator = torch.Generator().manual_seed(0)
    noisy = clean + 0.1 * torch.randn(clean.shape, generator=generator, dtype=clean.dtype)
    near = (surface.phi.abs() <= surface.spacing).expand_as(clean)
    flow = ColorDenoise(0.004, brightness=HeatFlow(0.004))
    out = flow(noisy, surface)
    assert out.shape == clean.shape
    before = float((noisy - clean)[near].square().mean())
    after = float((out - clean)[near].square().mean())
    assert after < 0.5 * before, (before, after)
    assert torch.isfinite(ColorDenoise(0.001)(noisy, surface)).all()
