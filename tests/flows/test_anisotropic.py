"""AnisotropicFlow: energy descent of total variation, edges kept sharper than by heat."""

from __future__ import annotations

import math

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import AnisotropicFlow, HeatFlow
from torchsurf.operators._flux_form import SIDES, projected_gradient


def tv_energy(u, surface, eps):
    """``sum W sqrt(|P D u|^2 + eps^2)``, averaged over the sides of the symmetric scheme."""
    total = 0.0
    for side in SIDES["symmetric"]:
        v = projected_gradient(u, surface.normal, surface.spacing, side, "slicing")
        total += float((surface.weight * torch.sqrt((v**2).sum(2) + eps**2)).sum())
    return total / 2


def step_case(n=25, dtype=torch.float64):
    grid = ts.Grid.cube(n, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=dtype), grid)
    z = grid.points(dtype=dtype)[..., 2]
    return (z > 0.1).to(dtype)[None, None], surface


def test_total_variation_energy_never_increases():
    u0, surface = step_case(17)
    eps = 0.5
    flow = AnisotropicFlow(0.004, eps=eps)
    energies = [tv_energy(u, surface, eps) for u in flow(u0, surface, times=[0.001, 0.002, 0.003, 0.004])]
    energies = [tv_energy(u0, surface, eps), *energies]
    assert all(b <= a + 1e-12 for a, b in zip(energies, energies[1:], strict=False)), energies
    assert energies[-1] < energies[0]


def test_total_variation_keeps_a_step_sharper_than_heat():
    u0, surface = step_case(25)
    time = 0.01
    heat = HeatFlow(time)(u0, surface)
    tv = AnisotropicFlow(time, eps=0.05)(u0, surface)
    near = (surface.phi.abs() <= surface.spacing).expand_as(u0)
    z = surface.grid.points(dtype=u0.dtype)[..., 2][None, None]
    edge = near & ((z - 0.1).abs() < 0.25)

    def sharpness(u):
        return float(((u - 0.5).abs())[edge].mean())   # 0.5 everywhere when fully blurred

    assert sharpness(tv) > sharpness(heat) + 0.05, (sharpness(tv), sharpness(heat))


@pytest.mark.parametrize("diffusivity", ["perona_malik", "charbonnier"])
def test_edge_stopping_flows_run_and_learn_contrast(diffusivity):
    u0, surface = step_case(9)
    flow = AnisotropicFlow(0.01, diffusivity=diffusivity, contrast=[0.5], learn_contrast=True,
                           steps=3).double()
    u = flow(u0, surface)
    assert u.shape == u0.shape and torch.isfinite(u).all()
    u.square().sum().backward()
    assert flow.contrast.raw.grad is not None


def test_total_variation_refuses_a_contrast_to_learn():
    """Its g reads no contrast: the parameter never got a gradient (an audit)."""
    with pytest.raises(ValueError, match=r"^learn_contrast=True: total variation's g"):
        AnisotropicFlow(0.01, learn_contrast=True)


def test_nonlinear_flow_refuses_implicit_and_callable_needs_bound():
    u0, surface = step_case(9)
    with pytest.raises(ValueError, match="method"):
        AnisotropicFlow(0.01, method="implicit")(u0, surface)
    with pytest.raises(ValueError, match="max_diffusivity"):
        AnisotropicFlow(0.01, diffusivity=lambda s, k: 1 / (1 + s))


def smooth_case(n=24):
    grid = ts.Grid.cube(n, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    p = grid.points(dtype=torch.float64)
    r = p.norm(dim=-1).clamp_min(1e-9)
    u0 = (p[..., 0] * p[..., 1] / r**2 + 0.5 * p[..., 2] / r)[None, None]
    return u0, surface, surface.phi.abs() <= grid.spacing


@pytest.mark.parametrize(("diffusivity", "cells", "options"),
                         [("perona_malik", 4.0, {}), ("total_variation", 2.0, {"eps": 0.1})])
def test_default_rkc_is_accurate_in_time_on_resolved_data(diffusivity, cells, options):
    """Without the band's refresh, RKC's few long steps are closer to the flow (Euler with 16x
    the stable steps) than Euler's stable steps: 7e-5 / 8e-5 against 6e-4 / 1.9e-4 at 24^3.
    With it, both are also as far apart as their refresh schedules (docs/band.md §4)."""
    u0, surface, near = smooth_case()
    time = cells * surface.spacing**2

    def run(method, steps=None, reextend_every="auto"):
        flow = AnisotropicFlow(time, diffusivity, method=method, steps=steps,
                               reextend_every=reextend_every, **options)
        return flow(u0, surface)

    rho = AnisotropicFlow(time, diffusivity, **options).system(u0, surface).spectral_radius
    stable = math.ceil(time * rho / 2)
    reference = run("euler", 16 * stable, None)
    rkc = float((run("rkc", None, None) - reference)[near].abs().max())
    euler = float((run("euler", None, None) - reference)[near].abs().max())
    assert rkc < 0.5 * euler, (rkc, euler)
    assert rkc < 2e-4, rkc


@pytest.mark.parametrize("name", ["total_variation", "perona_malik", "charbonnier"])
def test_the_librarys_own_diffusivity_functions_are_taken_like_their_names(name):
    """Given as functions they asked for ``max_diffusivity`` and lost the maximum principle's
    check."""
    function = getattr(ts.operators.diffusivity, name)
    by_function, by_name = AnisotropicFlow(0.01, function), AnisotropicFlow(0.01, name)
    assert by_function.max_diffusivity == by_name.max_diffusivity
    assert by_function.keeps_range and by_name.keeps_range


def test_requested_times_do_not_add_reextensions_to_steps_that_hold_the_ring():
    """RKC steps that hold the ring (a 5-cell band) were re-extended every few steps counted,
    and requested times split the steps: times=[t/2, t] re-extended three times where the
    flow alone did twice, and moved a Perona-Malik flow's u(t) by 0.055 near S (0.096 with
    four times), 100 times what more steps change."""
    grid = ts.Grid.cube(40, bound=1.3)
    h = grid.spacing
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=0.9, dtype=torch.float64), grid)
    points = grid.points(dtype=torch.float64)
    closest = points - (surface.phi / surface.grad_norm)[0, 0, ..., None] \
        * surface.normal[0].permute(1, 2, 3, 0)
    x, y, _ = closest.unbind(-1)
    u0 = ((x > 0.1).double() + 2 * (y > 0.2).double())[None, None]
    near = surface.band_mask(h)
    time = 4 * h * h
    flow = ts.AnisotropicFlow(time, diffusivity="perona_malik", contrast=0.2 / h)
    alone = flow(u0, surface)
    for times in ([time / 2, time], [time / 4, time / 2, 3 * time / 4, time]):
        assert float((flow(u0, surface, times=times)[-1] - alone)[near].abs().max()) < 2e-3


def test_total_variation_does_not_swing_with_the_steps_or_the_requested_times():
    """The band's re-extensions come once a cell-crossing time, by the time reached: a whole
    period of floor(12 / (rho dt)) steps re-extended at every step where 12 / (rho dt) lay in
    [1, 2), and requested times shortened it. Jumps on a torus, t rho = 82: RKC with 16 and 20
    steps differed by 0.06-0.2 from fine Euler steps, and times=[t/2, t] moved u(t) by 0.07."""
    grid = ts.Grid.cube(25, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.torus(grid, major_radius=0.9, minor_radius=0.35,
                                              dtype=torch.float64), grid)
    points = grid.points(dtype=torch.float64)
    closest = points - (surface.phi / surface.grad_norm)[0, 0, ..., None] \
        * surface.normal[0].permute(1, 2, 3, 0)
    x, y, _ = closest.unbind(-1)
    u0 = ((x > 0.2).double() + 2 * (y > 0.3).double())[None, None]
    near = surface.band_mask(surface.spacing)
    time = 0.005
    results = [ts.AnisotropicFlow(time, eps=0.05, steps=steps)(u0, surface) for steps in (16, 20)]
    results.append(ts.AnisotropicFlow(time, eps=0.05)(u0, surface, times=[time / 2, time])[-1])
    for other in results[1:]:
        assert float((other - results[0])[near].abs().max()) < 5e-3


def test_a_run_too_long_for_total_variations_eps_names_eps():
    """A small mesh's total variation with the default eps (units of u per world length: a
    tiny fraction of a cell there) planned tens of thousands of steps, and the warning asked
    only whether the time was in the flow's units, when eps set the operator's bound."""
    grid = ts.Grid.cube(13, 1.5e-3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1e-3), grid)
    u0 = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"Or eps: .* per cell of this grid"):
        AnisotropicFlow(2e-3 * 1e-3, eps=1e-6)(u0, surface)
    with pytest.raises(ValueError) as refused:  # a bound of the user's: eps is not the cause
        AnisotropicFlow(2e-3 * 1e-3, eps=1.0, max_diffusivity=1e6)(u0, surface)
    assert "Or eps" not in str(refused.value)
    unit = ts.flows.harmonic.normalize(torch.randn(1, 3, *grid.shape, dtype=u0.dtype,
                                                   generator=torch.Generator().manual_seed(1)))
    with pytest.raises(ValueError, match=r"Or eps: .* diffusivity 1e\+06"):
        ts.HarmonicMapFlow(2e-3 * 1e-3, p=1, eps=1e-6)(unit, surface)


def test_eps_and_diffusivity_set_after_building_set_the_steps_bound():
    """The bound ``max g`` follows ``eps`` and ``diffusivity`` set on a built flow (it kept
    the former bound: 0.06 and 0.42 from a flow built with the new settings)."""
    grid = ts.Grid.cube(20, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0, dtype=torch.float64), grid)
    u = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                   generator=torch.Generator().manual_seed(3))
    flow = AnisotropicFlow(4e-3, eps=1.0)
    flow.eps = 0.1
    assert flow.max_diffusivity == pytest.approx(10.0)
    assert torch.equal(flow(u, surface), AnisotropicFlow(4e-3, eps=0.1)(u, surface))
    flow.diffusivity = ts.operators.DIFFUSIVITIES["perona_malik"]
    assert flow.max_diffusivity == 1.0 and flow.keeps_range
    assert torch.equal(flow(u, surface),
                       AnisotropicFlow(4e-3, diffusivity="perona_malik", eps=0.1)(u, surface))
    with pytest.raises(ValueError, match="eps"):
        flow.eps = -1.0
    flow.diffusivity = "charbonnier"  # by name, as the constructor takes it
    assert flow.max_diffusivity == 1.0 and flow.keeps_range and "charbonnier" in repr(flow)
    assert torch.equal(flow(u, surface),
                       AnisotropicFlow(4e-3, diffusivity="charbonnier", eps=0.1)(u, surface))
    flow.diffusivity = "total_varation"
    with pytest.raises(ValueError, match="diffusivity"):
        _ = flow.max_diffusivity
    flow.diffusivity = lambda magnitude, contrast: 1.0 / (1.0 + magnitude)
    with pytest.raises(ValueError, match="max_diffusivity"):
        flow(u, surface)
    flow.max_diffusivity = 1.0
    assert not flow.keeps_range and flow.max_diffusivity == 1.0


def test_a_flow_pickled_with_plain_attributes_loads_and_runs():
    """Flows pickled before ``eps`` and ``max_diffusivity`` became properties held them (and
    ``keeps_range``) as plain attributes: loaded now, they run as they did."""
    import pickle

    grid = ts.Grid.cube(16, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0, dtype=torch.float64), grid)
    u = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                   generator=torch.Generator().manual_seed(3))
    flow = AnisotropicFlow(4e-3, eps=0.5)
    expected = flow(u, surface)
    state = flow.__dict__.copy()
    state["eps"], state["max_diffusivity"] = state.pop("_eps"), 2.0
    del state["_max_diffusivity"]
    state["keeps_range"] = True
    old = AnisotropicFlow.__new__(AnisotropicFlow)
    old.__setstate__(pickle.loads(pickle.dumps(state)))
    assert old.eps == 0.5 and old.max_diffusivity == 2.0 and old.keeps_range
    assert torch.equal(old(u, surface), expected)
