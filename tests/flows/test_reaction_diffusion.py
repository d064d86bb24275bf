"""ReactionDiffusion: a pattern grows from Turk's near-homogeneous start, reproducibly."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import ReactionDiffusion


@pytest.fixture(scope="module")
def surface():
    grid = ts.Grid.cube(21, bound=1.3)
    return ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0), grid)


def variance_on_surface(u, surface):
    near = (surface.phi.abs() <= surface.spacing)[0, 0]
    return float(u[0, 1][near].var())


def test_pattern_grows_from_the_homogeneous_start(surface):
    u0 = ReactionDiffusion.initial(surface)
    flow = ReactionDiffusion(time=400.0)
    u = flow(u0, surface, generator=torch.Generator().manual_seed(0))
    early = ReactionDiffusion(time=50.0)(u0, surface, generator=torch.Generator().manual_seed(0))
    assert variance_on_surface(u0, surface) == 0.0
    assert variance_on_surface(u, surface) > 10 * variance_on_surface(early, surface) > 0
    assert torch.isfinite(u).all()


def test_seeded_generator_reproduces_the_pattern(surface):
    u0 = ReactionDiffusion.initial(surface)
    flow = ReactionDiffusion(time=50.0)
    first = flow(u0, surface, generator=torch.Generator().manual_seed(7))
    second = flow(u0, surface, generator=torch.Generator().manual_seed(7))
    other = flow(u0, surface, generator=torch.Generator().manual_seed(8))
    assert torch.equal(first, second)
    assert not torch.equal(first, other)


def test_anisotropic_variant_runs_along_a_tangent_field(surface):
    u0 = ReactionDiffusion.initial(surface, batch=2)
    e1, _ = surface.principal_directions()
    u = ReactionDiffusion(time=20.0)(u0, surface, direction=e1,
                                    generator=torch.Generator().manual_seed(0))
    assert u.shape == u0.shape and torch.isfinite(u).all()


def test_needs_two_channels(surface):
    with pytest.raises(ValueError, match="u0"):
        ReactionDiffusion(time=1.0)(ReactionDiffusion.initial(surface)[:, :1], surface)
