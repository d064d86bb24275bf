"""Batching, dtypes, modules, and the errors bad inputs raise."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.exact import torus_function

CASE = torus_function(13)
SURFACE = ts.ImplicitSurface(CASE.phi, CASE.grid)


def test_batch_of_signals_over_one_surface_and_batch_of_surfaces():
    generator = torch.Generator().manual_seed(5)
    u = torch.randn(3, 2, 13, 13, 13, dtype=torch.float64, generator=generator)
    batched = ts.laplace_beltrami(u, SURFACE)
    for b in range(3):
        torch.testing.assert_close(batched[b: b + 1], ts.laplace_beltrami(u[b: b + 1], SURFACE))
    phis = torch.cat([CASE.phi, CASE.phi * 1.3 + 0.05, CASE.phi - 0.1])
    surfaces = ts.ImplicitSurface(phis, CASE.grid)
    per_surface = ts.laplace_beltrami(u, surfaces, scheme="central")
    for b in range(3):
        single = ts.ImplicitSurface(phis[b: b + 1], CASE.grid)
        torch.testing.assert_close(
            per_surface[b: b + 1], ts.laplace_beltrami(u[b: b + 1], single, scheme="central")
        )
    broadcast = ts.laplace_beltrami(u[:1], surfaces)
    assert broadcast.shape == (3, 2, 13, 13, 13)


def test_float32_matches_float64():
    surface32 = ts.ImplicitSurface(CASE.phi.float(), CASE.grid)
    for operator in (ts.laplace_beltrami, ts.anisotropic_diffusion, ts.intrinsic_gradient):
        value32 = operator(CASE.u.float(), surface32)
        value64 = operator(CASE.u, SURFACE)
        assert value32.dtype == torch.float32
        torch.testing.assert_close(value32.double(), value64, rtol=1e-4, atol=1e-3)


def test_inputs_are_not_modified():
    u = CASE.u.clone()
    phi = CASE.phi.clone()
    surface = ts.ImplicitSurface(phi, CASE.grid)
    ts.laplace_beltrami(u, surface).sum()
    ts.anisotropic_diffusion(u, surface)
    surface.principal_directions()
    assert torch.equal(u, CASE.u) and torch.equal(phi, CASE.phi)


def test_modules_match_functions():
    u = CASE.u
    torch.testing.assert_close(
        ts.LaplaceBeltrami("central")(u, SURFACE), ts.laplace_beltrami(u, SURFACE, "central")
    )
    torch.testing.assert_close(ts.IntrinsicGradient()(u, SURFACE), ts.intrinsic_gradient(u, SURFACE))
    v = ts.intrinsic_gradient(u, SURFACE)
    torch.testing.assert_close(
        ts.IntrinsicDivergence()(v, SURFACE), ts.intrinsic_divergence(v, SURFACE)
    )
    contrast = torch.nn.Parameter(torch.tensor(0.5, dtype=torch.float64))
    module = ts.AnisotropicDiffusion("perona_malik", contrast=contrast)
    assert any(p is contrast for p in module.parameters())
    torch.testing.assert_close(
        module(u, SURFACE), ts.anisotropic_diffusion(u, SURFACE, "perona_malik", contrast=0.5)
    )
    direction = SURFACE.principal_directions()[0]
    torch.testing.assert_close(
        ts.DirectionalDiffusion()(u, SURFACE, direction),
        ts.directional_diffusion(u, SURFACE, direction),
    )


@pytest.mark.parametrize(
    "call,match",
    [
        (
            lambda: ts.laplace_beltrami(CASE.u[0], SURFACE),
            r"u must be a volume .*got shape \(1, 13, 13, 13\)",
        ),
        (lambda: ts.laplace_beltrami(CASE.u[..., :-1], SURFACE), "u has spatial shape"),
        (lambda: ts.laplace_beltrami(CASE.u.float(), SURFACE), "u has dtype torch.float32"),
        (lambda: ts.laplace_beltrami(CASE.u.long(), SURFACE), "u must be a floating-point"),
        (lambda: ts.laplace_beltrami(CASE.u, CASE.phi), "surface must be a torchsurf"),
        (lambda: ts.laplace_beltrami(CASE.u, SURFACE, scheme="upwind"), "scheme must be one of"),
        (lambda: ts.laplace_beltrami(CASE.u, SURFACE, path="gpu"), "path must be one of"),
        (lambda: ts.LaplaceBeltrami(scheme="nope"), "scheme must be one of"),
        (
            lambda: ts.laplace_beltrami(
                CASE.u.expand(2, 1, 13, 13, 13),
                ts.ImplicitSurface(CASE.phi.expand(3, 1, 13, 13, 13), CASE.grid),
            ),
            "u has batch size 2 but surface has 3",
        ),
        (lambda: ts.intrinsic_divergence(CASE.u.expand(1, 2, 13, 13, 13), SURFACE), "3C channels"),
        (lambda: ts.anisotropic_diffusion(CASE.u, SURFACE, "gaussian"), "diffusivity must be"),
        (lambda: ts.anisotropic_diffusion(CASE.u, SURFACE, contrast=-1.0), "contrast must be"),
        (
            lambda: ts.anisotropic_diffusion(CASE.u, SURFACE, contrast=torch.ones(4).double()),
            r"contrast must be .* \(C,\) = \(1,\)",
        ),
        (lambda: ts.anisotropic_diffusion(CASE.u, SURFACE, eps=0.0), "eps must be"),
        (lambda: ts.anisotropic_diffusion(CASE.u, SURFACE, scheme="central"), "scheme must be"),
        (lambda: ts.directional_diffusion(CASE.u, SURFACE, CASE.u), "direction must have 3"),
    ],
)
def test_bad_inputs_raise_naming_the_argument(call, match):
    with pytest.raises((ValueError, TypeError), match=match):
        call()


def test_direction_batch_mismatch_names_direction_and_u():
    u = CASE.u.expand(2, 1, 13, 13, 13)
    direction = CASE.u.expand(3, 3, 13, 13, 13)
    with pytest.raises(ValueError, match="direction has batch size 3 but u has 2"):
        ts.directional_diffusion(u, SURFACE, direction)


def test_zero_channels_refused():
    with pytest.raises(ValueError, match=r"u must hold at least one volume and one channel"):
        ts.laplace_beltrami(CASE.u[:, :0], SURFACE)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_refused_naming_the_argument(dtype):
    with pytest.raises(TypeError, match=rf"u must be .*float32 or torch.float64.*{dtype}"):
        ts.laplace_beltrami(CASE.u.to(dtype), SURFACE)
    with pytest.raises(TypeError, match=rf"phi must be .*{dtype}"):
        ts.ImplicitSurface(CASE.phi.to(dtype), CASE.grid)


@pytest.mark.parametrize("contrast", [torch.tensor(0.0), torch.tensor(-1.0),
                                      torch.tensor([float("nan")]), torch.tensor(float("inf"))])
def test_contrast_tensor_must_be_finite_and_positive(contrast):
    with pytest.raises(ValueError, match="contrast must hold finite positive values"):
        ts.anisotropic_diffusion(CASE.u, SURFACE, contrast=contrast.double())
    with pytest.raises(ValueError, match="contrast"):
        ts.operators.AnisotropicDiffusion(contrast=contrast.double())(CASE.u, SURFACE)


@pytest.mark.parametrize("contrast", [-1.0, 0.0, float("nan"), torch.tensor(-1.0),
                                      torch.ones(2, 2)])
def test_the_module_refuses_a_bad_contrast_when_built(contrast):
    """It was taken, and refused at the first forward only, unlike a bad eps."""
    with pytest.raises(ValueError, match="contrast must"):
        ts.AnisotropicDiffusion("perona_malik", contrast=contrast)


def test_the_module_keeps_a_contrast_parameter_registered():
    contrast = torch.nn.Parameter(torch.tensor([0.5], dtype=torch.float64))
    module = ts.AnisotropicDiffusion("perona_malik", contrast=contrast)
    assert module.contrast is contrast
    assert any(p is contrast for p in module.parameters())


def test_functional_layer_names_arguments_of_the_wrong_type():
    """A numpy u or normal raised "'numpy.ndarray' object has no attribute 'dim'", an int64 u a
    ValueError, and float16 inputs ran (every other layer refuses them)."""
    functional = ts.operators.functional
    grid = ts.Grid.cube(9, 1.3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.7), grid)
    u = torch.rand(1, 1, 9, 9, 9)
    normal, weight, h = surface.normal, surface.weight, grid.spacing
    for call, name in ((lambda: functional.divergence_form(u.numpy(), normal, weight, h), "u"),
                       (lambda: functional.divergence_form(u, normal.numpy(), weight, h), "normal"),
                       (lambda: functional.tangential_gradient(u.long(), normal, h), "u"),
                       (lambda: functional.divergence_form(u.half(), normal.half(), weight.half(), h),
                        "u")):
        with pytest.raises(TypeError, match=rf"^{name} must be"):
            call()


def test_functional_layer_names_a_missing_tensor():
    """``weight=None`` raised "'NoneType' object has no attribute 'dim'" (or 'shape') deep in
    a kernel; every function that needs a tensor now names it."""
    from torchsurf.operators.diffusivity import total_variation

    functional = ts.operators.functional
    grid = ts.Grid.cube(9, 1.3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.7), grid)
    u = torch.rand(1, 1, 9, 9, 9)
    v = torch.rand(1, 3, 9, 9, 9)
    normal, weight, h = surface.normal, surface.weight, grid.spacing
    calls = {
        "weight": [lambda: functional.divergence_form(u, normal, None, h),
                   lambda: functional.edge_stopping_form(u, normal, None, h, total_variation,
                                                         1.0, 1e-6),
                   lambda: functional.harmonic_map_rate(v, normal, None, h, total_variation,
                                                        1.0, 1e-6, None),
                   lambda: functional.directional_form(u, normal, None, h, v),
                   lambda: functional.tangential_divergence(v, normal, None, h)],
        "direction": [lambda: functional.directional_form(u, normal, weight, h, None)],
        "mean_curvature": [lambda: functional.central_laplace_beltrami(u, normal, None, h)],
        "normal": [lambda: functional.tangential_gradient(u, None, h)],
        "u": [lambda: functional.tangential_gradient_energy(None, normal, h)],
    }
    for name, group in calls.items():
        for call in group:
            with pytest.raises(TypeError, match=rf"^{name} must be a torch.Tensor, got None"):
                call()


def test_functional_layer_checks_masks_halos_flags_and_contrast():
    """A mask of three channels broadcast the result to three (u has one), a float mask or one
    of another grid and a haloed geometry without its halo failed deep in a kernel,
    weighted="no" was read as true, a diffusivity's name was called, and a contrast of the
    wrong shape failed broadcasting inside the flux."""
    from torchsurf.operators.diffusivity import total_variation

    functional = ts.operators.functional
    u, normal, weight, h = CASE.u, SURFACE.normal, SURFACE.weight, SURFACE.spacing
    band = SURFACE.band_mask()
    for call, error, match in (
        (lambda: functional.divergence_form(u, normal, weight, h, mask=band.expand(-1, 3, -1, -1, -1)),
         ValueError, r"mask must have shape \(1 or 1, 1, \*\(13, 13, 13\)\) .* got \(1, 3,"),
        (lambda: functional.divergence_form(u, normal, weight, h, mask=band.double()),
         TypeError, "mask must be a bool tensor, got torch.float64"),
        (lambda: functional.divergence_form(u, normal, weight, h, mask=band[..., :12]),
         ValueError, "mask must have shape"),
        (lambda: functional.divergence_form(u, normal, weight, h, haloed=(normal, weight)),
         ValueError, r"haloed\[0\] \(normal\) must have shape \(B or 1, 3, \*\(15, 15, 15\)\)"),
        (lambda: functional.divergence_form(u, normal, weight, h, weighted="no"),
         TypeError, "weighted must be True or False"),
        (lambda: functional.edge_stopping_form(u, normal, weight, h, "perona_malik", 1.0, 1e-3),
         TypeError, "diffusivity must be a function"),
        (lambda: functional.edge_stopping_form(u, normal, weight, h, total_variation,
                                               torch.ones(5, dtype=u.dtype), 1e-3),
         ValueError, r"contrast must broadcast to the result's shape \(1, 1, 13, 13, 13\)"),
        (lambda: functional.tangential_gradient(u[..., :0], normal[..., :0], h),
         ValueError, "u must have nodes along every axis"),
    ):
        with pytest.raises(error, match=match):
            call()
    masked = functional.divergence_form(u, normal, weight, h, mask=band, haloed=SURFACE.haloed(),
                                        weighted=torch.tensor(False))
    pair = ts.ImplicitSurface(torch.cat([CASE.phi, 1.2 * CASE.phi]), CASE.grid)  # u broadcast
    both = functional.divergence_form(u, pair.normal, pair.weight, h, mask=pair.band_mask())
    assert both.shape[0] == 2 and torch.equal(both[:1], masked)
    assert torch.equal(masked, torch.where(band, functional.divergence_form(u, normal, weight, h),
                                           0.0))
