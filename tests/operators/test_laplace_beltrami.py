"""Laplace–Beltrami schemes: exact cases with measured orders, reference stencil, adjointness."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from conftest import skewed_box_surface

import torchsurf as ts
from torchsurf.exact import max_error, near, sphere_harmonic, torus_function

SCHEMES = ("symmetric", "conservative", "octant", "central")


def _order(errors: list[float]) -> float:
    return math.log2(errors[0] / errors[1])


def _errors(make_case, sizes, scheme):
    errors = []
    for n in sizes:
        case = make_case(n)
        surface = ts.ImplicitSurface(case.phi, case.grid)
        value = ts.laplace_beltrami(case.u, surface, scheme=scheme, path="slicing")
        errors.append(max_error(value, case.exact, near(case)))
    return errors


@pytest.mark.parametrize("degree", [1, 2, 3, 4])
@pytest.mark.parametrize("scheme", ["symmetric", "octant", "central"])
def test_sphere_harmonics_second_order(degree, scheme):
    errors = _errors(lambda n: sphere_harmonic(degree, n), (33, 65), scheme)
    assert _order(errors) > 1.8, errors


@pytest.mark.parametrize("scheme,low,high", [
    ("symmetric", 1.8, 3.0), ("octant", 1.8, 3.0), ("central", 1.8, 3.2), ("conservative", 0.7, 1.6),
])
def test_torus_measured_order(scheme, low, high):
    errors = _errors(torus_function, (33, 65), scheme)
    assert low < _order(errors) < high, errors


def _torus_cases(n: int):
    """Three functions of the torus angles with their exact Laplace–Beltrami (R = 1, r = 0.4)."""
    from torchsurf.exact import TORUS_RADII, torus_coordinates

    grid = ts.Grid.cube(n, bound=1.6)
    theta, v, rho, ring = torus_coordinates(grid.points(dtype=torch.float64))
    phi = ts.sdf.torus(grid, *TORUS_RADII, dtype=torch.float64)
    functions = {
        "sin v": (torch.sin(v), -torch.sin(v) / rho**2 - torch.sin(v) * torch.cos(v) / (rho * ring)),
        "cos theta": (torch.cos(theta), -torch.cos(theta) / ring**2),
        "cos 2theta cos v": (
            torch.cos(2 * theta) * torch.cos(v),
            torch.cos(2 * theta) * (-4 * torch.cos(v) / ring**2 - torch.cos(v) / rho**2
                                    + torch.sin(v) ** 2 / (rho * ring)),
        ),
    }
    return grid, phi, functions


@pytest.mark.parametrize("scheme,bound", [(None, 5e-3), ("symmetric", 1e-2)])
def test_relative_error_on_torus_at_129(scheme, bound):
    """The issue's target for the default scheme: below 5e-3 at 129^3 on three functions.

    The two-composition symmetric scheme misses it (measured 3.8e-3 to 9.5e-3); its bound
    only guards against regressions.
    """
    grid, phi, functions = _torus_cases(129)
    surface = ts.ImplicitSurface(phi, grid)
    mask = phi.abs() <= grid.spacing
    options = {} if scheme is None else {"scheme": scheme}
    for name, (u, exact) in functions.items():
        value = ts.laplace_beltrami(u[None, None], surface, **options)
        exact = exact[None, None]
        relative = float((value - exact).abs()[mask].max() / exact.abs()[mask].max())
        assert relative < bound, (name, relative)


def test_default_scheme_is_octant():
    assert ts.LaplaceBeltrami().scheme == "octant"
    assert ts.flows.HeatFlow(time=0.1).scheme == "octant"


def _appendix_b_reference(u: np.ndarray, phi: np.ndarray, h: float) -> np.ndarray:
    """The paper's Appendix B written out with numpy, valid two nodes away from the faces."""
    def shift(a, axis, step):
        return np.roll(a, -step, axis=axis)

    axes = (2, 1, 0)
    grad_phi = [(shift(phi, a, 1) - shift(phi, a, -1)) / (2 * h) for a in axes]
    gradient_norm = np.sqrt(sum(g**2 for g in grad_phi) + 1e-12)
    inside = phi < 0
    crossing = np.zeros_like(inside)
    for a in range(3):
        crossing |= (shift(inside, a, 1) != inside) | (shift(inside, a, -1) != inside)
    slope = np.sqrt(sum((shift(phi, a, 1) - phi)**2 + (phi - shift(phi, a, -1))**2
                        for a in axes) / (2 * h**2) + 1e-12)
    median = np.sort(gradient_norm[crossing])[(crossing.sum() - 1) // 2]
    norm = np.maximum(np.maximum(gradient_norm, 0.65 * slope), 0.05 * median)
    normal = [g / np.maximum(gradient_norm, 1e-3 * slope) for g in grad_phi]
    forward = [(shift(u, a, 1) - u) / h for a in axes]
    along = sum(f * n for f, n in zip(forward, normal, strict=True))
    flux = [norm * (f - along * n) for f, n in zip(forward, normal, strict=True)]
    return sum((f - shift(f, a, -1)) / h for f, a in zip(flux, axes, strict=True)) / norm


def test_conservative_equals_plain_appendix_b():
    grid = ts.Grid.cube(21, bound=1.2)
    generator = torch.Generator().manual_seed(0)
    phi = ts.sdf.torus(grid, 0.7, 0.3, dtype=torch.float64)
    phi = phi * (1.0 + 0.3 * grid.points(dtype=torch.float64)[..., 0])  # not a distance function
    u = torch.randn(1, 1, 21, 21, 21, dtype=torch.float64, generator=generator)
    surface = ts.ImplicitSurface(phi, grid, eps=1e-6)
    value = ts.laplace_beltrami(u, surface, scheme="conservative")[0, 0].numpy()
    reference = _appendix_b_reference(u[0, 0].numpy(), phi[0, 0].numpy(), grid.spacing)
    inner = (slice(2, -2),) * 3
    np.testing.assert_allclose(value[inner], reference[inner], rtol=1e-10, atol=1e-9)


def _weighted_pair(scheme: str):
    grid = ts.Grid.cube(13, bound=1.0)
    generator = torch.Generator().manual_seed(1)
    points = grid.points(dtype=torch.float64)
    phi = (points**2 / torch.tensor([0.6, 0.4, 0.5], dtype=torch.float64) ** 2).sum(-1) - 1
    surface = ts.ImplicitSurface(phi[None, None], grid)
    u, v = torch.randn(2, 2, 1, 13, 13, 13, dtype=torch.float64, generator=generator)
    weight = surface.weight
    lu = ts.laplace_beltrami(u, surface, scheme=scheme)
    lv = ts.laplace_beltrami(v, surface, scheme=scheme)
    return float((v * weight * lu).sum()), float((u * weight * lv).sum()), float((u * weight * lu).sum())


@pytest.mark.parametrize("scheme", ["symmetric", "conservative", "octant"])
def test_weighted_symmetric_negative_semidefinite(scheme):
    vlu, ulv, ulu = _weighted_pair(scheme)
    assert vlu == pytest.approx(ulv, rel=1e-12)
    assert ulu < 0


def test_central_scheme_is_not_symmetric():
    vlu, ulv, _ = _weighted_pair("central")
    assert abs(vlu - ulv) > 1e-3 * abs(vlu)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_embedding_invariance(scheme):
    """phi and g(phi) = phi + phi^3 / 2 (g' > 0) give the same operator on S, to O(h^p)."""
    differences = []
    for n in (33, 65):
        case = torus_function(n)
        stretched = case.phi + 0.5 * case.phi**3
        values = [
            ts.laplace_beltrami(case.u, ts.ImplicitSurface(p, case.grid), scheme=scheme)
            for p in (case.phi, stretched)
        ]
        differences.append(max_error(values[0], values[1], near(case, 0.5)))
    assert differences[1] < differences[0] / 1.8, differences


@pytest.mark.parametrize("scheme", SCHEMES)
def test_paths_agree(scheme):
    case = torus_function(17)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    u = torch.randn(case.u.shape, dtype=case.u.dtype, generator=torch.Generator().manual_seed(4))
    reference = ts.laplace_beltrami(u, surface, scheme=scheme, path="slicing")
    conv = ts.laplace_beltrami(u, surface, scheme=scheme, path="conv3d")
    # W-weighted: at the torus's centre W is ~0 and dividing by it magnifies rounding
    weight = surface.weight
    torch.testing.assert_close(weight * conv, weight * reference, rtol=1e-12, atol=1e-9)


def test_compiled_path_matches_eager_forward_and_backward():
    case = sphere_harmonic(2, 17, dtype=torch.float32)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    results = []
    for path in ("slicing", "compiled"):
        u = case.u.clone().requires_grad_(True)
        value = ts.laplace_beltrami(u, surface, path=path)
        value.square().sum().backward()
        results.append((value.detach(), u.grad))
    torch.testing.assert_close(results[1][0], results[0][0], rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(results[1][1], results[0][1], rtol=1e-5, atol=1e-2)


def _charbonnier_like(v, fields, side):
    scale = 1 / torch.sqrt(1 + v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
    return scale * v[0], scale * v[1], scale * v[2]


def _coupled_tv(v, fields, side):
    from torchsurf.operators.functional import edge_stopping_flux

    return edge_stopping_flux(lambda s, k: 1 / s, 1.0, 0.3, True)(v, fields, side)


@pytest.mark.parametrize("scheme", ["symmetric", "conservative", "octant"])
@pytest.mark.parametrize("flux_map", [None, _charbonnier_like, _coupled_tv, "directional"])
def test_fused_formulation_equals_modular(scheme, flux_map):
    """The single-expression form that the compiled path runs, checked eagerly on a box grid,
    with a phi that is not a distance (W varies) and every kind of flux map."""
    from torchsurf.operators._flux_form import flux_form, fused_flux_form
    from torchsurf.operators.functional import directional_flux

    grid, surface = skewed_box_surface()
    generator = torch.Generator().manual_seed(2)
    u = torch.randn(2, 3, 9, 10, 11, dtype=torch.float64, generator=generator)
    fields = ()
    if flux_map == "directional":
        flux_map = directional_flux
        fields = (torch.randn(2, 3, 9, 10, 11, dtype=torch.float64, generator=generator),)
    haloed_fields = tuple(torch.nn.functional.pad(f, (1,) * 6, mode="replicate") for f in fields)
    padded = torch.nn.functional.pad(u, (2,) * 6, mode="replicate")
    weight = surface.weight
    fused = fused_flux_form(padded, *surface.haloed(), weight, grid.spacing, flux_map,
                            haloed_fields, scheme)
    modular = flux_form(u, surface.normal, weight, grid.spacing, flux_map, fields, scheme, "slicing")
    torch.testing.assert_close(weight * fused, weight * modular, rtol=1e-12, atol=1e-10)
    if flux_map is None or flux_map is directional_flux:
        weighted = fused_flux_form(padded, *surface.haloed(), weight, grid.spacing, flux_map,
                                   haloed_fields, scheme, weighted=True)
        torch.testing.assert_close(weighted, weight * modular, rtol=1e-12, atol=1e-10)


def test_octant_one_pass_equals_the_eight_compositions():
    """The closed form the octant scheme runs, against its definition, at every node.

    A non-distance ``phi`` on a box that is not a cube, so that ``W`` varies and the box's faces
    (where the mirrored normals stand in for the compositions' zero flux) are in play.
    """
    from torchsurf.operators._flux_form import flux_form
    from torchsurf.operators._octant import fused_octant

    grid, surface = skewed_box_surface()
    u = torch.randn(2, 3, 9, 10, 11, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    haloed_normal, haloed_weight = surface.haloed()
    weight = surface.weight
    fused = fused_octant(ts.stencils.pad(u, "replicate"), haloed_normal, haloed_weight, weight, grid.spacing)
    reference = flux_form(u, surface.normal, weight, grid.spacing, None, (), "octant", "slicing")
    torch.testing.assert_close(weight * fused, weight * reference, rtol=1e-12, atol=1e-9)
    transpose = fused_octant(
        ts.stencils.pad(u / weight, "replicate"), haloed_normal, haloed_weight, weight, grid.spacing,
        weighted=True,
    )
    expected = weight * flux_form(
        u / weight, surface.normal, weight, grid.spacing, None, (), "octant", "slicing"
    )
    torch.testing.assert_close(transpose, expected, rtol=1e-12, atol=1e-9)


def test_compiling_raises_dynamo_recompile_limit_but_never_lowers_it():
    """Dynamo's default of 8 variants per function ran out at the third grid size."""
    from torchsurf import backend

    config = torch._dynamo.config
    with config.patch(recompile_limit=8):
        backend._raise_recompile_limit()
        assert config.recompile_limit == backend.RECOMPILE_LIMIT
    with config.patch(recompile_limit=1000):
        backend._raise_recompile_limit()
        assert config.recompile_limit == 1000


@pytest.mark.parametrize("scheme", ["octant", "symmetric"])
@pytest.mark.parametrize("path", ["slicing", "conv3d", "compiled"])
def test_masked_divergence_form_is_the_masked_operator_on_every_path(scheme, path):
    """``mask=`` zeroes the result outside a flow's band (the octant scheme in its own pass):
    the same numbers as masking the operator's result, forward and backward."""
    from torchsurf.operators import functional

    case = sphere_harmonic(2, 17, dtype=torch.float64)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    mask = surface.band_mask(2 * surface.spacing)
    geometry = (surface.normal, surface.weight, surface.spacing, scheme, path)
    u = torch.randn(case.u.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    g = torch.randn_like(u)
    results = []
    for masked in (True, False):
        x = u.clone().requires_grad_(True)
        value = functional.divergence_form(x, *geometry, haloed=surface.haloed(),
                                           mask=mask if masked else None)
        value = value if masked else torch.where(mask, value, 0.0)
        (value * g).sum().backward()
        results.append((value.detach(), x.grad))
    assert bool((results[0][0][~mask.expand_as(u)] == 0).all())
    assert results[0][0].abs().max() > 1.0
    torch.testing.assert_close(results[0][0], results[1][0], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(results[0][1], results[1][1], rtol=1e-10, atol=1e-10)


def test_masked_octant_gradcheck_and_bricks():
    """The masked octant form's adjoint (``L^T M g``) by gradcheck; on bricks the masked form
    equals the dense one on the band."""
    from torchsurf import bricks
    from torchsurf.operators import functional

    grid = ts.Grid.cube(33, 2.1)
    dense = ts.ImplicitSurface(ts.sdf.torus(grid, 0.9, 0.4).double(), grid)
    packed = bricks.from_dense(dense)
    u = torch.randn((1, 1, 33, 33, 33), dtype=torch.float64,
                    generator=torch.Generator().manual_seed(6))
    mask = dense.band_mask(2 * dense.spacing)
    expected = functional.divergence_form(u, dense.normal, dense.weight, dense.spacing,
                                          haloed=dense.haloed(), mask=mask)
    on_bricks = functional.divergence_form(
        packed.from_dense(u), packed.normal, packed.weight, packed.spacing,
        haloed=packed.haloed(), pad=packed.layout.halo, mask=packed.from_dense(mask))
    band = packed.band_mask()
    torch.testing.assert_close(on_bricks[band], packed.from_dense(expected)[band])

    small = sphere_harmonic(2, 9, dtype=torch.float64)
    surface = ts.ImplicitSurface(small.phi, small.grid)
    small_mask = surface.band_mask(2 * surface.spacing)
    x = torch.randn(small.u.shape, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(7)).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda v: functional.divergence_form(v, surface.normal, surface.weight, surface.spacing,
                                             path="slicing", haloed=surface.haloed(),
                                             mask=small_mask), (x,))


def test_exact_cases_take_integer_tensors_and_leave_degenerate_level_sets_out_of_near():
    """A 0-d integer tensor is a degree (it had failed in a dict lookup), and the torus case's
    nodes on the z axis and the core circle, whose level sets are no torus (0/0 there), are
    NaN in ``exact`` and not in :func:`near`: ``max_error`` over ``near`` was NaN at n = 11."""
    assert torch.equal(sphere_harmonic(torch.tensor(2), 9).exact, sphere_harmonic(2, 9).exact)
    case = torus_function(11)
    undefined = ~case.exact.isfinite()
    assert int(undefined.sum()) > 0 and bool((undefined & (case.phi.abs() <= case.grid.spacing)).any())
    assert not bool((near(case) & undefined).any())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a torus of 0.4 on cells of 0.7: |grad phi| falls at kinks
        surface = ts.ImplicitSurface(case.phi, case.grid)
        error = max_error(ts.laplace_beltrami(case.u, surface), case.exact, near(case))
    assert math.isfinite(error)
    # at n = 21 rounding puts core-circle nodes such as (0.6, -0.8, 0) 1e-16 off the circle:
    # their exact values were a finite 8e31, read within two cells (a review)
    case = torus_function(21)
    core = (case.grid.points()[..., 0] - 0.6).abs().lt(1e-12) & (case.grid.points()[..., 1] + 0.8
                                                                 ).abs().lt(1e-12)
    core &= case.grid.points()[..., 2].abs().lt(1e-12)
    assert bool(core.any()) and bool(case.exact[0, 0][core].isnan().all())
