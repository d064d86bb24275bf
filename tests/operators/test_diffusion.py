"""Gradient, divergence, edge-stopping and directional diffusion against exact answers."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import skewed_box_surface

import torchsurf as ts
from torchsurf.exact import SPHERE_CENTER, SPHERE_RADIUS, polar_angle_frame, torus_function


def _sphere(n: int):
    grid = ts.Grid.cube(n, bound=1.4)
    phi = ts.sdf.sphere(grid, SPHERE_RADIUS, center=SPHERE_CENTER, dtype=torch.float64)
    cos, sin, e_theta, r = polar_angle_frame(grid.points(dtype=torch.float64))
    away_from_poles = (phi.abs() <= grid.spacing) & (sin.abs() > 0.6)[None, None]
    return grid, ts.ImplicitSurface(phi, grid), cos, sin, e_theta, r, away_from_poles


def _vector(field: torch.Tensor) -> torch.Tensor:
    return field.permute(3, 0, 1, 2)[None]


def _order(errors: list[float]) -> float:
    return math.log2(errors[0] / errors[1])


def test_gradient_and_divergence_second_order():
    """``grad_S cos(theta) = -(sin(theta) / r) e_theta`` and its divergence ``-2 cos / r^2``."""
    gradient_errors, divergence_errors = [], []
    for n in (33, 65):
        grid, surface, cos, sin, e_theta, r, mask = _sphere(n)
        u = cos[None, None]
        gradient = ts.intrinsic_gradient(u, surface)
        exact = _vector(-(sin / r)[..., None] * e_theta)
        gradient_errors.append(float((gradient - exact).abs()[mask.expand(1, 3, n, n, n)].max()))
        divergence = ts.intrinsic_divergence(exact, surface)
        exact_divergence = (-2 * cos / r**2)[None, None]
        divergence_errors.append(float((divergence - exact_divergence).abs()[mask].max()))
    assert _order(gradient_errors) > 1.8, gradient_errors
    assert _order(divergence_errors) > 1.8, divergence_errors


@pytest.mark.parametrize("scheme,order", [("symmetric", 1.8), ("conservative", 0.9)])
def test_total_variation_is_geodesic_curvature_of_level_curves(scheme, order):
    """``div_S(grad_S u / |grad_S u|)`` for ``u = cos(theta)`` is ``-cot(theta) / r``."""
    errors = []
    for n in (33, 65):
        grid, surface, cos, sin, _, r, mask = _sphere(n)
        value = ts.anisotropic_diffusion(cos[None, None], surface, eps=1e-6, scheme=scheme)
        exact = (-cos / sin / r)[None, None]
        errors.append(float((value - exact).abs()[mask].max()))
    assert _order(errors) > order, errors


@pytest.mark.parametrize("diffusivity", ["perona_malik", "charbonnier"])
def test_edge_stopping_reduces_to_laplace_beltrami_for_large_contrast(diffusivity):
    case = torus_function(21)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    expected = ts.laplace_beltrami(case.u, surface, scheme="symmetric")
    value = ts.anisotropic_diffusion(case.u, surface, diffusivity, contrast=1e8)
    torch.testing.assert_close(value, expected, rtol=1e-9, atol=1e-9)


def test_edge_stopping_scales_flux_by_diffusivity():
    """For ``u = cos(theta)`` on a sphere ``|grad_S u| = sin/r``; Perona–Malik reduces the flux."""
    grid, surface, cos, *_ = _sphere(33)
    u = cos[None, None]
    weak = ts.anisotropic_diffusion(u, surface, "perona_malik", contrast=0.2)
    strong = ts.anisotropic_diffusion(u, surface, "perona_malik", contrast=50.0)
    band = surface.band_mask(grid.spacing)
    assert float(weak.abs()[band].mean()) < 0.5 * float(strong.abs()[band].mean())


def test_custom_diffusivity_callable():
    case = torus_function(17)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    value = ts.anisotropic_diffusion(case.u, surface, lambda s, k: 2.0 * torch.ones_like(s))
    torch.testing.assert_close(value, 2.0 * ts.laplace_beltrami(case.u, surface, scheme="symmetric"))
    # a scalar g broadcasts; a result of another shape, or none, is named as g's
    torch.testing.assert_close(
        ts.anisotropic_diffusion(case.u, surface, lambda s, k: torch.tensor(2.0)), value)
    with pytest.raises(ValueError, match=r"diffusivity <lambda> returned shape \(3,\)"):
        ts.anisotropic_diffusion(case.u, surface, lambda s, k: torch.ones(3))
    with pytest.raises(TypeError, match="diffusivity <lambda> must return a tensor"):
        ts.anisotropic_diffusion(case.u, surface, lambda s, k: None)
    # a float32 result on float64 data came back float64 from the operator and was named by
    # the flows as their own normal's mismatch; a 0-d or integer result does not promote
    assert case.u.dtype == torch.float64
    for g in (lambda s, k: torch.ones_like(s, dtype=torch.float32),
              lambda s, k: torch.ones_like(s, dtype=torch.float32).expand_as(s)):
        with pytest.raises(TypeError, match=r"diffusivity <lambda> returned torch.float32 .* "
                                            r"magnitude of torch.float64"):
            ts.anisotropic_diffusion(case.u, surface, g)
        with pytest.raises(TypeError, match="diffusivity <lambda> returned torch.float32"):
            ts.AnisotropicFlow(1e-3, g, max_diffusivity=1.0)(case.u, surface)
    torch.testing.assert_close(
        ts.anisotropic_diffusion(case.u, surface, lambda s, k: 2 * torch.ones_like(s).long()),
        value)


def test_a_module_diffusivity_keeps_its_parameters_registered():
    class Scaled(torch.nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.scale = torch.nn.Parameter(torch.tensor(2.0, dtype=torch.float64))

        def forward(self, s: torch.Tensor, k: float) -> torch.Tensor:
            return self.scale * torch.ones_like(s)

    case = torus_function(13)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    for module in (ts.operators.AnisotropicDiffusion(Scaled()),
                   ts.flows.AnisotropicFlow(1e-3, Scaled(), max_diffusivity=2.0)):
        (scale,) = module.parameters() if isinstance(module, ts.operators.AnisotropicDiffusion) \
            else [p for name, p in module.named_parameters() if name.endswith("scale")]
        module(case.u, surface).sum().backward()
        assert scale.grad is not None and float(scale.grad.abs()) > 0


def test_directional_diffusion_along_and_across_meridians():
    grid, surface, cos, sin, e_theta, r, mask = _sphere(33)
    u = cos[None, None]
    along = ts.directional_diffusion(u, surface, _vector(e_theta))
    across_direction = torch.linalg.cross(surface.normal[0].permute(1, 2, 3, 0), e_theta, dim=-1)
    across = ts.directional_diffusion(u, surface, _vector(across_direction))
    laplacian = ts.laplace_beltrami(u, surface, scheme="symmetric")
    exact = (-2 * cos / r**2)[None, None]
    assert float((along - exact).abs()[mask].max()) < 0.06
    assert float((along - laplacian).abs()[mask].max()) < 0.06
    assert float(across.abs()[mask].max()) < 0.03 * float(exact.abs()[mask].max())


def test_directional_along_both_principal_directions_is_laplace_beltrami():
    case = torus_function(33)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    e1, e2 = surface.principal_directions()
    total = ts.directional_diffusion(case.u, surface, e1) + ts.directional_diffusion(
        case.u, surface, e2
    )
    expected = ts.laplace_beltrami(case.u, surface, scheme="symmetric")
    # e1 e1^T + e2 e2^T = P needs unit normals at every node the stencil reads: the 3-cell
    # band reaches the tube's core circle (r = 3h), where grad phi vanishes
    band = surface.band_mask(2 * surface.spacing)
    assert float((total - expected).abs()[band].max()) < 1e-6 * float(expected.abs()[band].max())


@pytest.mark.parametrize("coupled", [False, True])
@pytest.mark.parametrize("path", ["slicing", "conv3d", "compiled"])
def test_masked_edge_stopping_form_is_the_masked_operator(path, coupled):
    """``mask=`` zeroes the result outside a flow's band in the kernel's own pass: the numbers
    of masking the operator's result, forward and backward, on every path and on bricks."""
    from torchsurf import bricks
    from torchsurf.operators import functional
    from torchsurf.operators.diffusivity import DIFFUSIVITIES

    grid = ts.Grid.cube(33, 2.1)
    dense = ts.ImplicitSurface(ts.sdf.torus(grid, 0.9, 0.4).double(), grid)
    u = torch.randn((1, 2, 33, 33, 33), dtype=torch.float64,
                    generator=torch.Generator().manual_seed(8))
    g = torch.randn_like(u)
    mask = dense.band_mask(2 * dense.spacing)
    arguments = (DIFFUSIVITIES["perona_malik"], 2.0, 0.1, coupled, "symmetric", path)
    results = []
    for masked in (True, False):
        x = u.clone().requires_grad_(True)
        value = functional.edge_stopping_form(x, dense.normal, dense.weight, dense.spacing,
                                              *arguments, haloed=dense.haloed(),
                                              mask=mask if masked else None)
        value = value if masked else torch.where(mask, value, 0.0)
        (value * g).sum().backward()
        results.append((value.detach(), x.grad))
    assert bool((results[0][0][~mask.expand_as(u)] == 0).all())
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-10, atol=1e-10)

    packed = bricks.from_dense(dense)
    on_bricks = functional.edge_stopping_form(
        packed.from_dense(u), packed.normal, packed.weight, packed.spacing, *arguments,
        haloed=packed.haloed(), pad=packed.layout.halo, mask=packed.from_dense(mask))
    band = packed.band_mask().expand(-1, 2, -1, -1, -1)
    torch.testing.assert_close(on_bricks[band], packed.from_dense(results[0][0])[band])


@pytest.mark.parametrize("scheme", ["symmetric", "conservative", "octant"])
@pytest.mark.parametrize("power", [None, 0.5])
@pytest.mark.parametrize("per_channel", [False, True])
def test_coupled_rate_arrangements_equal_the_modular_form(scheme, power, per_channel):
    """The coupled rate's two compiled arrangements (faces from kept ``a_s`` and ``a_s m_s``
    without a graph to record; the compositions' fluxes while recording), run eagerly, against
    the modular flux form plus the energy term: a box that is not a cube, ``phi`` not a
    distance, two shapes in the batch, a mask, a contrast per channel or not; and the two
    arrangements against each other on a brick's open faces."""
    from torchsurf.flows.harmonic import power_diffusivity
    from torchsurf.operators import _coupled
    from torchsurf.operators.diffusivity import perona_malik
    from torchsurf.operators.functional import _coupled_eager

    grid, surface = skewed_box_surface()
    generator = torch.Generator().manual_seed(5)
    u = torch.nn.functional.normalize(
        torch.randn(2, 3, 9, 10, 11, dtype=torch.float64, generator=generator), dim=1)
    mask = surface.band_mask(2 * surface.spacing)
    padded = torch.nn.functional.pad(u, (2,) * 6, mode="replicate")
    diffusivity, contrast = (
        (perona_malik, torch.tensor([0.5, 1.0, 2.0], dtype=torch.float64).view(1, 3, 1, 1, 1))
        if per_channel else (power_diffusivity, -1.0))
    common = (surface.weight, grid.spacing, diffusivity, contrast, 0.2, scheme, power, mask)
    expected = _coupled_eager(u, surface.normal, surface.weight, grid.spacing, diffusivity,
                              contrast, 0.2, power, scheme, mask, None, path="slicing")
    recording = padded.clone().requires_grad_(True)
    for box_faces in (True, False):
        faces = _coupled.fused_coupled_rate(padded, *surface.haloed(), *common,
                                            box_faces=box_faces)
        compositions = _coupled.fused_coupled_rate(recording, *surface.haloed(), *common,
                                                   box_faces=box_faces).detach()
        torch.testing.assert_close(faces, compositions, rtol=1e-12, atol=1e-9)
        if box_faces:
            torch.testing.assert_close(faces, expected, rtol=1e-12, atol=1e-9)
    assert faces.is_contiguous()


@pytest.mark.parametrize("scheme", ["symmetric", "conservative", "octant"])
def test_directional_diffusion_projects_inside_the_fluxes_as_projecting_first(scheme):
    """The operator projects ``T`` within its fluxes (``tangent=True``), not as a field of its
    own first (which took as long as the operator): the same numbers as ``P T`` given, on
    every eager arrangement, in a box whose faces cut S, for a ``T`` with a large normal part
    and batches that broadcast."""
    from torchsurf.operators import functional

    grid, surface = skewed_box_surface()
    generator = torch.Generator().manual_seed(3)
    u = torch.rand(2, 2, *grid.shape, generator=generator, dtype=torch.float64)
    direction = torch.randn(1, 3, *grid.shape, generator=generator, dtype=torch.float64)
    normal, weight = surface.normal, surface.weight
    tangent = direction - (direction * normal).sum(1, keepdim=True) * normal
    for path in ("slicing", "conv3d"):
        expected = functional.directional_form(u, normal, weight, surface.spacing, tangent,
                                               scheme, path, haloed=surface.haloed())
        result = ts.directional_diffusion(u, surface, direction, scheme, path)
        # T . v and P T . v differ by (T . n)(v . n), v . n a rounding of v: 3e-12 of the
        # largest value on noise
        tolerance = {"rtol": 1e-10, "atol": 1e-11 * float(expected.abs().max())}
        torch.testing.assert_close(result, expected, **tolerance)
        one_pass = functional._DIRECTIONAL_TANGENT.fused(*functional._directional_halo(
            u, normal, weight, surface.spacing, direction, scheme, False, True, surface.haloed()))
        torch.testing.assert_close(one_pass, expected, **tolerance)


@pytest.mark.parametrize("batch", [1, 2])
def test_directional_diffusion_drops_the_normal_part_of_its_direction(batch):
    """A direction with a part along the normals gave a flux off the level sets: T = (1, 0, 0)
    on a sphere was 12% off P T near S, with no word; the flows project it, the operator did
    not."""
    grid, surface, cos, sin, e_theta, r, mask = _sphere(25)
    u = (cos * sin)[None, None].expand(batch, 2, -1, -1, -1)
    constant = torch.zeros(1, 3, *grid.shape, dtype=torch.float64)
    constant[:, 0] = 1.0
    normal = surface.normal
    tangent = constant - (constant * normal).sum(1, keepdim=True) * normal
    expected = ts.directional_diffusion(u, surface, tangent)
    for direction in (constant, tangent + 2.5 * normal):
        got = ts.DirectionalDiffusion()(u, surface, direction.expand(batch, -1, -1, -1, -1))
        assert torch.allclose(got, expected, atol=1e-12 * float(expected.abs().max()))
    along_normal = ts.directional_diffusion(u, surface, normal)
    assert float(along_normal[mask.expand_as(along_normal)].abs().max()) < 1e-9
    bound = ts.operators.directional_bound(surface, constant)
    assert bound == pytest.approx(ts.operators.directional_bound(surface, tangent))


@pytest.mark.parametrize("path", ["slicing", "auto"])
def test_tangential_gradient_energy_is_the_squared_tangential_gradient_and_never_negative(path):
    """``sum_c |P grad u_c|^2`` equals the squares of ``tangential_gradient`` (float64), and
    stays near float64 in float32 where u varies mostly along the normal: formed as
    ``|g|^2 - (g . n)^2`` it went down to -3.0e-3 here (-4.3e-3 in the audit's case),
    against a largest true value 4e-4."""
    grid = ts.Grid.cube(33, bound=1.4)
    phi = ts.sdf.sphere(grid, dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid)
    x = grid.points(dtype=torch.float64)[..., 0][None, None]
    u = torch.cat([100.0 * phi + 0.01 * torch.sin(2.0 * x), torch.cos(3.0 * x)], dim=1)
    functional = ts.operators.functional
    energy = functional.tangential_gradient_energy(u, surface.normal, grid.spacing, path)
    gradient = functional.tangential_gradient(u, surface.normal, grid.spacing, "slicing")
    torch.testing.assert_close(energy, gradient.square().sum(dim=1, keepdim=True),
                               rtol=1e-12, atol=1e-12)
    band = surface.band_mask()
    low = functional.tangential_gradient_energy(u[:, :1].float(), surface.normal.float(),
                                                grid.spacing, path)
    high = functional.tangential_gradient_energy(
        u[:, :1], surface.normal, grid.spacing, path)
    assert float((low.double() - high)[band].abs().max()) < 1e-3 * float(high[band].max()) + 2e-6
