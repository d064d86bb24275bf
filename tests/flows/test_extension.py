"""Extension: values on S kept, data made constant along the normals."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import Extension


def case(n=33, dtype=torch.float64):
    grid = ts.Grid.cube(n, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=dtype), grid)
    points = grid.points(dtype=dtype)
    x, y, z = points.unbind(-1)
    r = points.norm(dim=-1).clamp(min=1e-3)
    # a function of the direction only (constant along normals), and one that varies along them
    extended = (x * y / r**2 + z / r)[None, None]
    u = extended * (1 + 2 * (r - 1))[None, None]
    return u, extended, surface


@pytest.mark.parametrize("method", ["closest_point", "pde"])
def test_extension_makes_data_constant_along_normals(method):
    u, extended, surface = case()
    out = Extension(method)(u, surface)
    band = (surface.band() & (surface.phi.abs() <= 2 * surface.spacing))
    before = float((u - extended).abs()[band].max())
    after = float((out - extended).abs()[band].max())
    assert after < 0.2 * before, (before, after)
    outside = ~surface.band()
    assert torch.equal(out[outside], u[outside])


def test_pde_extension_keeps_nodes_on_the_surface():
    grid = ts.Grid.cube(21, bound=1.0)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=0.5, dtype=torch.float64), grid)
    generator = torch.Generator().manual_seed(0)
    u = torch.rand((1, 1, 21, 21, 21), generator=generator, dtype=torch.float64)
    out = Extension("pde")(u, surface)
    on = surface.phi == 0
    assert on.any()
    assert torch.equal(out[on], u[on])


def test_closest_point_keeps_values_on_the_surface_up_to_interpolation():
    u, extended, surface = case(33)
    out = Extension("closest_point")(extended, surface)
    near = surface.phi.abs() <= 0.5 * surface.spacing
    assert float((out - extended).abs()[near].max()) < 2e-2


def test_extension_is_differentiable_and_rejects_bad_input():
    u, _, surface = case(9)
    u = u.requires_grad_()
    Extension()(u, surface).sum().backward()
    assert torch.isfinite(u.grad).all()
    with pytest.raises(ValueError, match="method"):
        Extension("nearest")
    with pytest.raises(ValueError, match="u"):
        Extension()(u[0], surface)
