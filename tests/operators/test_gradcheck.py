"""Every operator through ``torch.autograd.gradcheck`` in float64, w.r.t. the data and phi."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts

N = 7
GRID = ts.Grid.cube(N, bound=1.0)


def _phi() -> torch.Tensor:
    generator = torch.Generator().manual_seed(3)
    phi = ts.sdf.sphere(GRID, radius=0.6, center=(0.05, 0.0, -0.04), dtype=torch.float64)
    return phi + 0.02 * torch.randn(phi.shape, dtype=torch.float64, generator=generator)


def _data(channels: int = 1) -> torch.Tensor:
    generator = torch.Generator().manual_seed(4)
    return torch.randn(1, channels, N, N, N, dtype=torch.float64, generator=generator)


DIRECTION = ts.ImplicitSurface(_phi(), GRID).principal_directions()[0].detach()


OPERATORS = {
    "lb_symmetric": lambda u, s: ts.laplace_beltrami(u, s, scheme="symmetric"),
    "lb_conservative": lambda u, s: ts.laplace_beltrami(u, s, scheme="conservative"),
    "lb_octant": lambda u, s: ts.laplace_beltrami(u, s, scheme="octant"),
    "lb_central": lambda u, s: ts.laplace_beltrami(u, s, scheme="central"),
    "gradient": lambda u, s: ts.intrinsic_gradient(u, s),
    "divergence": lambda u, s: ts.intrinsic_divergence(torch.cat([u, u**2, -u], 1), s),
    "tv": lambda u, s: ts.anisotropic_diffusion(u, s, "total_variation", eps=0.5),
    "perona_malik": lambda u, s: ts.anisotropic_diffusion(u, s, "perona_malik", contrast=0.7),
    "charbonnier_coupled": lambda u, s: ts.anisotropic_diffusion(
        torch.cat([u, u.flip(-1)], 1), s, "charbonnier", contrast=0.7, coupled=True,
        scheme="conservative",
    ),
    "directional": lambda u, s: ts.directional_diffusion(u, s, DIRECTION),
}


@pytest.mark.parametrize("name", list(OPERATORS))
def test_gradcheck_data(name):
    surface = ts.ImplicitSurface(_phi(), GRID)
    u = _data().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda u: OPERATORS[name](u, surface), (u,), fast_mode=True)


@pytest.mark.parametrize("name", list(OPERATORS))
def test_gradcheck_phi(name):
    u = _data()
    phi = _phi().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda phi: OPERATORS[name](u, ts.ImplicitSurface(phi, GRID)), (phi,), fast_mode=True
    )


def test_gradcheck_contrast_parameter():
    surface = ts.ImplicitSurface(_phi(), GRID)
    u = _data(channels=2)
    contrast = torch.tensor([0.5, 0.9], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda k: ts.anisotropic_diffusion(u, surface, "perona_malik", contrast=k), (contrast,)
    )


@pytest.mark.parametrize("name", ["mean", "gaussian", "principal"])
def test_gradcheck_curvature_at_umbilics(name):
    center = (0.05, 0.0, -0.04)  # keeps the medial axis, where |grad phi| -> eps, off the nodes
    phi = ts.sdf.sphere(GRID, radius=0.6, center=center, dtype=torch.float64).requires_grad_(True)

    def curvature(phi):
        surface = ts.ImplicitSurface(phi, GRID)
        if name == "mean":
            return surface.mean_curvature()
        if name == "gaussian":
            return surface.gaussian_curvature()
        return torch.cat([*surface.principal_curvatures(), *surface.principal_directions()], 1)

    value = curvature(phi)
    assert torch.isfinite(value).all()
    if name != "principal":
        assert torch.autograd.gradcheck(curvature, (phi,), fast_mode=True)
    else:
        value.sum().backward()
        assert torch.isfinite(phi.grad).all()
