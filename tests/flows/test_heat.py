"""HeatFlow: exact decay of sphere harmonics for every integrator, energy, batching, gradients."""

from __future__ import annotations

import math
import warnings

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import HeatFlow, base
from torchsurf.flows import _integrators as integrators
from torchsurf.flows._packed_band import PackedStencil
from torchsurf.sampling import sample

TIME = 0.05


def fibonacci_sphere(count: int, dtype: torch.dtype) -> torch.Tensor:
    """``count`` nearly uniform unit vectors ``(count, 3)``."""
    i = torch.arange(count, dtype=dtype) + 0.5
    z = 1 - 2 * i / count
    r = torch.sqrt(1 - z**2)
    angle = math.pi * (1 + 5**0.5) * i
    return torch.stack((r * torch.cos(angle), r * torch.sin(angle), z), dim=-1)


def harmonics(n: int, dtype: torch.dtype):
    """Degrees 1..4 as four channels, their surface, and their values on S at unit directions."""
    cases = [ts.exact.sphere_harmonic(degree, n, dtype=dtype) for degree in (1, 2, 3, 4)]
    u0 = torch.cat([case.u for case in cases], dim=1)
    surface = ts.ImplicitSurface(cases[0].phi, cases[0].grid)
    return u0, surface


def decay_errors(u: torch.Tensor, surface: ts.ImplicitSurface, time: float,
                 interpolation: str = "linear") -> list[float]:
    """Max error on S of each harmonic channel against ``exp(-l(l+1)t/R^2) f``, relative to
    the exact amplitude at ``time``, ``u`` read at the points by ``interpolation``."""
    directions = fibonacci_sphere(2000, u.dtype)
    radius = ts.exact.SPHERE_RADIUS
    points = directions * radius + directions.new_tensor(ts.exact.SPHERE_CENTER)
    x, y, z = directions.unbind(-1)
    shapes = (z, 3 * z**2 - 1, x * y * z, 35 * z**4 - 30 * z**2 + 3)
    values = sample(u, points, surface.grid, interpolation)[0]
    errors = []
    for degree, (shape, value) in enumerate(zip(shapes, values, strict=True), start=1):
        exact = shape * math.exp(-degree * (degree + 1) * time / radius**2)
        errors.append(float((value - exact).abs().max() / exact.abs().max()))
    return errors


@pytest.fixture(scope="module")
def sphere33():
    return harmonics(33, torch.float32)


# Measured at 33^3 (float32, t = 0.05, the 3-cell band re-extended), relative errors for
# l = 1..4: rkc 2.1e-3 4.8e-3 6.1e-3 2.4e-2 (8 steps: 1.7e-2); euler 2.4e-3 7.3e-3 1.7e-2
# 2.7e-2; crank_nicolson(5) 2.1e-3 5.1e-3 1.2e-2 9.8e-3. l = 4 has 8 cells per wavelength
# here; the errors are the space discretisation's and fall as h^2 (test below and at 65^3).
@pytest.mark.parametrize(
    ("method", "settings"),
    [
        ("rkc", {}),
        ("euler", {}),
        ("crank_nicolson", {"steps": 5}),
    ],
)
def test_sphere_harmonics_decay(sphere33, method, settings):
    u0, surface = sphere33
    u = HeatFlow(TIME, method=method, **settings)(u0, surface)
    errors = decay_errors(u, surface, TIME)
    assert max(errors[:3]) < 2e-2, errors
    assert errors[3] < 3e-2, errors


def test_sphere_harmonics_decay_torchdiffeq(sphere33):
    pytest.importorskip("torchdiffeq")
    u0, surface = sphere33
    flow = HeatFlow(TIME, method="dopri5", options={"rtol": 1e-4, "atol": 1e-6})
    errors = decay_errors(flow(u0, surface), surface, TIME)
    assert max(errors) < 2.5e-2, errors


def test_torchdiffeq_methods_converge_at_second_order():
    """rk4 on the l = 2 harmonic at 33^3 and 49^3 (float64, read tricubically), against RKC in
    the same run: the band re-extended as often as RKC's steps re-extend it. With pieces of the
    diffusion time across the band, 1.3e-3 and 7.7e-4 (order 1.3; RKC 1.2e-3, 5.1e-4)."""
    pytest.importorskip("torchdiffeq")
    errors = {}
    for method in ("rk4", "rkc"):
        for n in (33, 49):
            case = ts.exact.sphere_harmonic(2, n, dtype=torch.float64)
            surface = ts.ImplicitSurface(case.phi, case.grid)
            with torch.no_grad():
                u = HeatFlow(TIME, method=method)(case.u, surface)
            directions = fibonacci_sphere(2000, torch.float64)
            points = (directions * ts.exact.SPHERE_RADIUS
                      + directions.new_tensor(ts.exact.SPHERE_CENTER))
            shape = 3 * directions[:, 2] ** 2 - 1
            exact = shape * math.exp(-6 * TIME / ts.exact.SPHERE_RADIUS**2)
            value = sample(u, points, surface.grid, "cubic")[0, 0]
            errors[method, n] = float((value - exact).abs().max() / exact.abs().max())
    order = math.log(errors["rk4", 33] / errors["rk4", 49]) / math.log(48 / 32)
    assert order > 1.8, errors
    assert errors["rk4", 49] < 1.2 * errors["rkc", 49], errors


@pytest.mark.slow
@pytest.mark.parametrize("method", ["euler", "heun", "implicit", "crank_nicolson", "dopri5"])
def test_sphere_harmonics_decay_65(method):
    """Every integrator within the issue's 0.5 % at 65^3, read tricubically (read trilinearly,
    l = 4 carries the read-out's own ``O(h^2)`` error: explicit Euler 5.9e-3 before the flows'
    band widened, 6.7e-3 after; tricubically 1.3e-3). The space error alone is about 4.5e-3 at
    l = 4 here (explicit Euler's lower figure is a cancellation with its time error), so
    backward Euler, first order in time, is allowed its own time error on top,
    ``lambda^2 t dt / 2`` with ``lambda = 20 / R^2`` (6.4e-4 at 1200 steps; measured 5.2e-3 in
    all; 5.9e-3 when the band was re-extended after every step, docs/band.md)."""
    if method == "dopri5":
        pytest.importorskip("torchdiffeq")
    u0, surface = harmonics(65, torch.float64)
    settings = {"crank_nicolson": {"steps": 20}, "implicit": {"steps": 1200}}.get(method, {})
    u = HeatFlow(TIME, method=method, **settings)(u0, surface)
    errors = decay_errors(u, surface, TIME, interpolation="cubic")
    allowed = 5e-3
    if method == "implicit":
        rate = 20 / ts.exact.SPHERE_RADIUS**2
        allowed += rate**2 * TIME * (TIME / settings["steps"]) / 2
    assert max(errors) < allowed, errors


@pytest.mark.parametrize(("method", "few", "many"),
                         [("rkc", None, 200), ("implicit", 40, 400), ("crank_nicolson", 10, 100)])
def test_more_steps_do_not_add_reextension_error(method, few, many):
    """The band is re-extended once per cell-crossing time, not after every step: each
    re-extension errs a little, and when every step added one, ten times the steps gave ten
    times the error (17^3, l = 1: RKC 2.6e-3 -> 3.0e-2 with 200 steps, backward Euler 7.8e-3
    -> 5.3e-2 with 40 -> 400, Crank-Nicolson 3.0e-3 -> 1.7e-2 with 10 -> 100). Now the
    errors stay those of the space discretisation (and shrink with the time step)."""
    u0, surface = harmonics(17, torch.float64)
    coarse, fine = (decay_errors(HeatFlow(TIME, method=method, steps=steps)(u0, surface),
                                 surface, TIME, interpolation="cubic") for steps in (few, many))
    assert max(fine[:3]) < 2.5e-2, fine
    for degree in range(4):
        assert fine[degree] < 1.1 * coarse[degree], (coarse, fine)


def test_an_early_requested_time_is_as_accurate_as_a_flow_to_it_alone():
    """Requested times split the steps planned for the last; the first of ``times=[2 h^2,
    10 h^2]`` got two of RKC's eight steps, and 0/1 data there (the modes near the grid's
    scale not yet decayed) missed a fine-step reference by 1.1e-2 against 9.6e-4 for a flow to
    2 h^2 alone (torus, 30^3). No step up to a requested time is now longer than a flow to
    that time alone takes, so the first result is as accurate as that flow's; many evenly
    spaced times add few steps (the early ones need them)."""
    grid = ts.Grid.cube(27, 1.7)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.1, dtype=torch.float64), grid)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    u0 = ((x + 0.3 * y > 0.1) ^ (z > 0.2)).to(torch.float64)[None, None]
    early, late = 2 * grid.spacing**2, 10 * grid.spacing**2
    both = HeatFlow(late)(u0, surface, times=[early, late])
    alone = HeatFlow(early)(u0, surface)
    reference = HeatFlow(early, method="euler", steps=300)(u0, surface)
    band = HeatFlow(late).band_mask(surface).expand_as(u0)
    errors = [float((u - reference)[band].abs().max()) for u in (both[0], alone)]
    assert errors[0] < 1.5 * errors[1], errors  # 9.7e-2 against 8.5e-3 before, 2.8e-3 now
    frames = HeatFlow(late)
    frames(u0, surface, times=[late * (k + 1) / 20 for k in range(20)])
    assert frames.last_plan.count <= 3 * 20, frames.last_plan


def test_requested_times_do_not_add_reextension_error():
    """Requested times split RKC's steps (at least one step each); the re-extension period
    follows the steps actually taken, so fifty results cost no accuracy at the last (17^3,
    l = 1: 2.9e-3 against 1.7e-3 when the period followed the planned steps)."""
    u0, surface = harmonics(17, torch.float64)
    flow = HeatFlow(TIME)
    single = decay_errors(flow(u0, surface), surface, TIME, interpolation="cubic")
    times = [TIME * (k + 1) / 50 for k in range(50)]
    last = decay_errors(flow(u0, surface, times=times)[-1], surface, TIME, interpolation="cubic")
    for degree in range(4):
        assert last[degree] < 1.1 * single[degree], (single, last)


def test_rkc_stays_second_order_where_its_steps_hold_the_ring_longest():
    """l = 1 on a sphere of radius 0.7 at 16 and 28 cells per radius, decayed by e^-0.6: the
    default plan holds the ring through steps at the bound. With the bound at
    12 (w - 2 sqrt(3))^2 the stale ring's error reached the nodes the re-extension reads, and
    the error grew with the grid: 1.6e-4 then 2.2e-4 (a floor near 3.5e-4 by 56 cells); at
    6 (w - 2 sqrt(3))^2, 5.5e-4 then 1.6e-4."""
    radius, time = 0.7, 0.6 * 0.7**2 / 2
    errors = []
    for cells in (16, 28):
        spacing = radius / cells
        nodes = 2 * round(1.4 * cells) + 1
        grid = ts.Grid((nodes,) * 3, spacing, (-spacing * (nodes - 1) / 2,) * 3)
        x, y, z = grid.points(dtype=torch.float64).unbind(-1)
        r = (x * x + y * y + z * z).sqrt()
        surface = ts.ImplicitSurface((r - radius)[None, None], grid)
        u = HeatFlow(time)(((x + 0.5 * y) / r)[None, None], surface)
        directions = fibonacci_sphere(1500, torch.float64)
        exact = math.exp(-0.6) * (directions[:, 0] + 0.5 * directions[:, 1])
        read = sample(u, radius * directions, grid, "cubic")[0, 0]
        errors.append(float((read - exact).abs().max() / exact.abs().max()))
    order = math.log(errors[0] / errors[1]) / math.log(28 / 16)
    assert order > 1.8, (errors, order)


def test_rkc_on_a_band_too_narrow_to_hold_the_ring_re_extends_it_as_often_as_heun():
    """phi = r^2 - R^2 (not a distance: the 3-cell band, the ring refreshed at every stage),
    R = 0.7, l = 1 decayed by e^-0.6, 16 cells per radius. The band's data drift off S's values
    between its re-extensions, by more the longer the period: RKC's 16 steps of 48 / rho erred
    2.9e-3; Heun re-extending after each of its steps of 2 / rho errs 8.2e-4, by default
    (every 12 / rho) 1.3e-4, where the drift and the re-extensions' own error happen to cancel.
    RKC's steps are now no longer than 12 / rho: 5.5e-4."""
    radius, time, cells = 0.7, 0.6 * 0.7**2 / 2, 16
    spacing = radius / cells
    nodes = 2 * round(1.4 * cells) + 1
    grid = ts.Grid((nodes,) * 3, spacing, (-spacing * (nodes - 1) / 2,) * 3)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    r = (x * x + y * y + z * z).sqrt()
    surface = ts.ImplicitSurface((r * r - radius**2)[None, None], grid)
    u0 = ((x + 0.5 * y) / r)[None, None]
    directions = fibonacci_sphere(1500, torch.float64)
    exact = math.exp(-0.6) * (directions[:, 0] + 0.5 * directions[:, 1])
    errors = {}
    for name, flow in (("rkc", HeatFlow(time)),
                       ("heun, every step", HeatFlow(time, method="heun", reextend_every=1))):
        read = sample(flow(u0, surface), radius * directions, grid, "cubic")[0, 0]
        errors[name] = float((read - exact).abs().max() / exact.abs().max())
        if name == "rkc":
            step_times_rho = flow.last_plan.step * flow.system(u0, surface).spectral_radius
    assert errors["rkc"] < errors["heun, every step"], errors
    assert step_times_rho <= integrators.RKC_REFRESHED_STEP * (1 + 1e-9)


def test_rkc_steps_that_hold_the_ring_share_its_reextension(sphere33, monkeypatch):
    """RKC's eight steps at 33^3 to half the time are short for their time error (``dt rho``
    4, the band's held-ring bound 14.2): three of them share one re-extension of band and ring
    (3 calls, not 8), with the errors of one per step."""
    u0, surface = sphere33
    calls = []
    reextend = base.reextend

    def counted(stencil, u, path="auto"):
        calls.append(stencil)
        return reextend(stencil, u, path)

    monkeypatch.setattr(base, "reextend", counted)
    packed_apply = PackedStencil.apply  # the same re-extensions on packed values

    def counted_packed(stencil, z):
        calls.append(stencil)
        return packed_apply(stencil, z)

    monkeypatch.setattr(PackedStencil, "apply", counted_packed)
    time = TIME / 2
    shared = decay_errors(HeatFlow(time)(u0, surface), surface, time, interpolation="cubic")
    count = len(calls)
    calls.clear()
    each = decay_errors(HeatFlow(time, reextend_every=1)(u0, surface), surface, time,
                        interpolation="cubic")
    assert count == 3 and len(calls) == 8, (count, len(calls))
    for degree in range(4):
        assert shared[degree] < 1.1 * each[degree], (each, shared)


def small_case(n: int = 17, dtype: torch.dtype = torch.float64, seed: int = 0):
    grid = ts.Grid.cube(n, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=dtype), grid)
    generator = torch.Generator().manual_seed(seed)
    u0 = torch.rand((1, 1, n, n, n), generator=generator, dtype=dtype)
    return u0, surface


def dirichlet_energy(u, surface):
    """``-u^T A u / 2`` with ``A = W L``: the energy the symmetric scheme descends."""
    return float(-(u * surface.weight * ts.laplace_beltrami(u, surface)).sum() / 2)


def test_energy_never_increases():
    u0, surface = small_case()
    energies = [dirichlet_energy(u, surface)
                for u in HeatFlow(0.02)(u0, surface, times=[0.005, 0.01, 0.015, 0.02])]
    energies = [dirichlet_energy(u0, surface), *energies]
    assert all(b <= a for a, b in zip(energies, energies[1:], strict=False)), energies
    assert energies[-1] < 0.5 * energies[0]


def test_implicit_agrees_with_explicit():
    """On one discrete problem (a wide band held at u0 outside: no re-extension), every
    integrator converges to the same answer."""
    u0, surface = small_case()
    settings = {"band_width": 0.6, "reextend_every": None}
    explicit = HeatFlow(0.01, method="euler", steps=200, **settings)(u0, surface)
    for method, steps in (("rkc", 20), ("crank_nicolson", 20), ("implicit", 200)):
        other = HeatFlow(0.01, method=method, steps=steps, **settings)(u0, surface)
        assert (explicit - other).abs().max() < 2e-3, method


def test_only_the_band_and_its_ring_change_and_input_untouched():
    u0, surface = small_case()
    copy = u0.clone()
    flow = HeatFlow(0.01, band_width=0.6)
    u = flow(u0, surface)
    band = surface.band_mask(0.6)
    region = torch.nn.functional.max_pool3d(band.double(), 3, stride=1, padding=1) > 0
    assert torch.equal(u[~region.expand_as(u)], u0[~region.expand_as(u)])
    assert not torch.equal(u[band.expand_as(u)], u0[band.expand_as(u)])
    assert torch.equal(u0, copy)


def test_nan_outside_the_band_and_ring_stays_there():
    u0, surface = small_case()
    band = surface.band_mask()
    region = torch.nn.functional.max_pool3d(band.double(), 3, stride=1, padding=1) > 0
    u0 = torch.where(region, u0, torch.nan)
    u = HeatFlow(0.01)(u0, surface)
    assert torch.isfinite(u[region.expand_as(u)]).all()
    with pytest.raises(ValueError, match="u0"):
        HeatFlow(0.01)(torch.where(band, torch.nan, u0), surface)


def test_a_band_too_narrow_for_reextension_is_refused():
    u0, surface = small_case()
    with pytest.raises(ValueError, match="band_width"):
        HeatFlow(0.01, band_width=2 * surface.spacing)(u0, surface)
    HeatFlow(0.01, band_width=2 * surface.spacing, reextend_every=None)(u0, surface)


def test_times_returns_each_time_and_end_matches():
    u0, surface = small_case()
    flow = HeatFlow(0.01, steps=20)
    both = flow(u0, surface, times=[0.005, 0.01])
    assert both.shape == (2, *u0.shape)
    torch.testing.assert_close(both[-1], flow(u0, surface))
    # a generator is read once (its check used it up: "an empty sequence")
    torch.testing.assert_close(flow(u0, surface, times=(t for t in [0.005, 0.01])), both)


def test_batch_of_signals_and_of_surfaces():
    u0, surface = small_case()
    u1, _ = small_case(seed=1)
    batch = torch.cat((u0, u1))
    flow = HeatFlow(0.005)
    together = flow(batch, surface)
    torch.testing.assert_close(together[1:], flow(u1, surface))
    surfaces = ts.ImplicitSurface(surface.phi.expand(2, -1, -1, -1, -1), surface.grid)
    torch.testing.assert_close(flow(batch, surfaces), together)


def test_per_channel_diffusivity_is_per_channel_time():
    u0, surface = small_case()
    two = torch.cat((u0, u0), dim=1)
    u = HeatFlow(0.005, diffusivity=[1.0, 2.0], steps=40)(two, surface)
    torch.testing.assert_close(u[:, 1:], HeatFlow(0.01, steps=40)(u0, surface))


def test_learnable_time_and_diffusivity_get_gradients():
    u0, surface = small_case(9)
    for method in ("euler", "implicit"):
        flow = HeatFlow(0.01, learn_time=True, diffusivity=[1.0], learn_diffusivity=True,
                        method=method, steps=3).double()
        flow(u0, surface).square().sum().backward()
        grads = [p.grad for p in flow.parameters()]
        assert len(grads) == 2 and all(g is not None and torch.isfinite(g).all() for g in grads)
        assert flow.time > 0 and bool(flow.diffusivity.value() > 0)


def directions(count: int, n: int = 9, seed: int = 2) -> torch.Tensor:
    """``count`` random volumes ``(count, 1, 1, n, n, n)``: gradcheck along these directions."""
    generator = torch.Generator().manual_seed(seed)
    return torch.randn((count, 1, 1, n, n, n), generator=generator, dtype=torch.float64)


@pytest.mark.parametrize(
    "method", ["euler", "implicit", pytest.param("crank_nicolson", marks=pytest.mark.slow)]
)
def test_gradcheck_data_diffusivity_and_time(method):
    u0, surface = small_case(9)
    basis = directions(3)
    flow = HeatFlow(0.01, diffusivity=[1.3], learn_diffusivity=True, learn_time=True,
                    method=method, steps=2, band_width=1.1).double()
    coefficients = torch.zeros(3, dtype=torch.float64, requires_grad=True)

    def run(coefficients, raw_time, raw_diffusivity):
        u = u0 + (coefficients[:, None, None, None, None, None] * basis).sum(0)
        parameters = {"time_value.raw": raw_time, "diffusivity.raw": raw_diffusivity}
        return torch.func.functional_call(flow, parameters, (u, surface))

    inputs = (coefficients, flow.time_value.raw.detach().clone().requires_grad_(),
              flow.diffusivity.raw.detach().clone().requires_grad_())
    assert torch.autograd.gradcheck(run, inputs, eps=1e-6, atol=1e-7, fast_mode=True)


def test_fixed_values_per_channel_swapped_in_with_grad_get_their_gradient():
    """functional_call swapping a fixed diffusivity per channel for values that require grad:
    the channels of each value ran apart with each value rebuilt from host floats, and the
    values' gradient was None without a word (where the values were equal it arrived)."""
    u0, surface = small_case(9)
    basis = directions(2, seed=5)
    flow = HeatFlow(0.01, diffusivity=[1.0, 2.0], method="euler", band_width=1.1).double()

    def run(values, coefficients):
        u = u0.expand(-1, 2, -1, -1, -1) + (coefficients[:, None, None, None, None, None]
                                             * basis).sum(0)
        return torch.func.functional_call(flow, {"diffusivity.values": values}, (u, surface))

    values = torch.tensor([3.0, 0.5], dtype=torch.float64, requires_grad=True)
    coefficients = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (values, coefficients), eps=1e-6, atol=1e-7,
                                    fast_mode=True)


def test_a_learned_time_gets_its_gradient_with_a_given_torchdiffeq_step_size():
    """A step_size given to a fixed-step torchdiffeq method ended torchdiffeq's grid with a
    partial step, whose length depends on the time outside autograd's graph: d/dtime came
    out 3% off (step_size = t / 10.37). The steps are now equal, the given one the longest."""
    pytest.importorskip("torchdiffeq")
    u0, surface = small_case(9)
    time = 3 * surface.spacing**2
    flow = HeatFlow(time, method="rk4", learn_time=True,
                    options={"step_size": time / 10.37}).double()
    raw = flow.time_value.raw.detach().clone().requires_grad_()

    def run(raw_time):
        return torch.func.functional_call(flow, {"time_value.raw": raw_time}, (u0, surface))

    assert torch.autograd.gradcheck(run, (raw,), eps=1e-6, atol=1e-7, rtol=1e-4, fast_mode=True)


@pytest.mark.parametrize("method", ["euler", "chebyshev"])
def test_requested_times_of_a_learned_time_need_max_time(method):
    """``times=`` are fractions of ``max_time`` applied to the learned time: gradcheck holds.
    Without ``max_time`` they would be fractions of the time's current value, read anew at each
    call: the output at ``t < time`` did not move with the parameter while autograd gave it a
    gradient (-0.74 on this kind of case), so that combination is refused."""
    u0, surface = small_case(9)
    spacing = surface.spacing
    with pytest.raises(ValueError, match="max_time"):
        HeatFlow(2 * spacing**2, learn_time=True, method=method).double()(
            u0, surface, times=[spacing**2])
    steps = None if method == "chebyshev" else 16
    flow = HeatFlow(2 * spacing**2, learn_time=True, max_time=3 * spacing**2, method=method,
                    steps=steps, band_width=1.1).double()

    weights = torch.rand((2, *u0.shape), dtype=u0.dtype, generator=torch.Generator().manual_seed(1))

    def run(raw_time):
        value = torch.func.functional_call(flow, {"time_value.raw": raw_time}, (u0, surface),
                                           {"times": [spacing**2, 3 * spacing**2]})
        return (value * weights).sum()  # one output: one backward per check

    raw = flow.time_value.raw.detach().clone().requires_grad_()
    assert float(torch.autograd.grad(run(raw), raw)[0].abs()) > 1e-3
    assert torch.autograd.gradcheck(run, (raw,), eps=1e-6, atol=1e-7)


@pytest.mark.parametrize("method, steps", [
    ("implicit", 2), ("rkc", 2),
    ("crank_nicolson", 3),  # short steps on 3 cells: the ring is refreshed before each one
])
def test_gradcheck_phi_through_the_flow_and_its_reextension(method, steps):
    """Off-centre sphere: on a centred one some closest points fall exactly on nodes, where the
    tricubic re-extension's derivatives jump."""
    grid = ts.Grid.cube(13, bound=1.5)
    phi0 = ts.sdf.sphere(grid, radius=0.93, center=(0.031, -0.047, 0.023), dtype=torch.float64)
    basis = 0.05 * directions(2, n=13)
    u0, _ = small_case(13)
    flow = HeatFlow(0.01, method=method, steps=steps, band_width=3 * grid.spacing)

    def run(coefficients):
        phi = phi0 + (coefficients[:, None, None, None, None, None] * basis).sum(0)
        return flow(u0, ts.ImplicitSurface(phi, grid))

    coefficients = torch.zeros(2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (coefficients,), eps=1e-6, atol=1e-7, fast_mode=True)


def test_torchdiffeq_adjoint_matches_direct_backprop():
    pytest.importorskip("torchdiffeq")
    u0, surface = small_case(9)
    grads = []
    for adjoint in (False, True):
        flow = HeatFlow(0.01, method="dopri5", learn_diffusivity=True, adjoint=adjoint,
                        options={"rtol": 1e-9, "atol": 1e-11}).double()
        flow(u0, surface).square().sum().backward()
        grads.append(next(flow.parameters()).grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-8)


def test_missing_torchdiffeq_is_explained(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name == "torchdiffeq":
            raise ImportError("No module named 'torchdiffeq'")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    u0, surface = small_case(9)
    with pytest.raises(ImportError, match="pip install torchdiffeq"):
        HeatFlow(0.01, method="dopri5")(u0, surface)


def test_bad_arguments_name_themselves():
    u0, surface = small_case(9)
    with pytest.raises(ValueError, match="time"):
        HeatFlow(-1.0)
    with pytest.raises(ValueError, match="steps"):
        HeatFlow(0.1, steps=0)
    with pytest.raises(ValueError, match="diffusivity"):
        HeatFlow(0.1, diffusivity=0.0)
    with pytest.raises(ValueError, match="scheme"):
        HeatFlow(0.1, scheme="upwind")
    for method in ("implicit", "crank_nicolson", "chebyshev"):
        with pytest.raises(ValueError, match=f"method='{method}'.*scheme='central'"):
            HeatFlow(0.1, method=method, scheme="central")
    flow = HeatFlow(0.1, method="implicit")
    flow.scheme = "central"  # changed after construction: refused when run
    with pytest.raises(ValueError, match="method"):
        flow(u0, surface)
    with pytest.raises(ValueError, match="u0"):
        HeatFlow(0.1)(u0[0], surface)
    with pytest.raises(ValueError, match="times"):
        HeatFlow(0.1)(u0, surface, times=[0.2])
    with pytest.raises(ValueError, match="diffusivity"):
        HeatFlow(0.01, diffusivity=[1.0, 2.0, 3.0])(torch.cat((u0, u0), 1), surface)


def test_progress_bar_and_reextension_hooks_run(capsys):
    pytest.importorskip("tqdm")
    u0, surface = small_case(9)
    u = HeatFlow(0.01, steps=4, progress=True, reextend_every=2)(u0, surface)
    assert torch.isfinite(u).all()
    assert "HeatFlow" in capsys.readouterr().err


def test_absurd_step_counts_are_refused_before_any_work():
    u0, surface = small_case()
    with pytest.raises(ValueError, match="steps"):
        HeatFlow(1e4, method="euler")(u0, surface)
    with pytest.raises(ValueError, match="steps"):
        HeatFlow(0.01, steps=10**7)(u0, surface)


def test_explicit_steps_beyond_the_stable_step_warn():
    u0, surface = small_case()
    # the steps do grow: the result leaves the range of u0, which warns too
    with pytest.warns(RuntimeWarning, match="stable explicit step"), \
            pytest.warns(RuntimeWarning, match="left the range of u0"):
        HeatFlow(0.3, method="euler", steps=2)(u0, surface)


def test_implicit_steps_holding_a_three_cell_bands_ring_too_long_warn():
    """On a band that never holds its ring, Crank-Nicolson's error at 30 steps grew with the
    grid, silently (1.8e-3 / 4.2e-3 / 1.1e-2 at 33^3 / 49^3 / 65^3, an audit): steps longer
    than a cell's crossing time warn; on the exact distance's 5-cell band they do not."""
    grid = ts.Grid.cube(33, bound=1.2)
    r = grid.points(dtype=torch.float64, relative_to=(0.04, -0.02, 0.03)).norm(dim=-1)
    u0 = torch.rand(1, 1, *grid.shape, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(0))
    time = 0.3 * 0.7**2
    quadric = ts.ImplicitSurface((r * r - 0.49)[None, None], grid)  # not a distance: 3 cells
    with pytest.warns(RuntimeWarning, match=r"crank_nicolson step holds the ring of this 3.0-cell "
                                            r"band.* Use steps >= \d+"):
        HeatFlow(time, method="crank_nicolson", steps=10)(u0, quadric)
    distance = ts.ImplicitSurface((r - 0.7)[None, None], grid)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        HeatFlow(time, method="crank_nicolson", steps=10)(u0, distance)
        HeatFlow(time, method="implicit")(u0, quadric)  # its own steps hold it short enough


def test_counts_accept_numpy_and_refuse_bools():
    import numpy as np

    assert HeatFlow(0.01, steps=np.int64(4)).steps == 4
    assert HeatFlow(0.01, steps=torch.tensor(4)).steps == 4
    with pytest.raises(TypeError, match="steps"):
        HeatFlow(0.01, steps=True)
    with pytest.raises(ValueError, match="reextend_every"):
        HeatFlow(0.01, reextend_every=0)


def test_torchdiffeq_settings_are_refused_with_built_in_methods():
    with pytest.raises(ValueError, match="options"):
        HeatFlow(0.01, method="rkc", options={"rtol": 1e-3})
    with pytest.raises(ValueError, match="adjoint"):
        HeatFlow(0.01, method="euler", adjoint=True)


def test_an_unknown_method_is_refused_when_the_flow_is_built():
    with pytest.raises(ValueError, match="method='bogus' is unknown.*rkc.*dopri5"):
        HeatFlow(0.01, method="bogus")
    with pytest.raises(ValueError, match="method='chebyshev' is unknown"):
        ts.AnisotropicFlow(0.01, method="chebyshev")
    with pytest.raises(TypeError, match="method must be a string"):
        HeatFlow(0.01, method=3)
    assert HeatFlow(0.01, method="chebyshev").method == "chebyshev"


def test_chebyshev_over_a_long_time_stays_second_order():
    """One expansion over many band-crossing times lets the band's level sets drift apart:
    in pieces, with the band re-extended between them, it keeps RKC's accuracy."""
    u0, surface = harmonics(25, torch.float64)
    time = 0.3  # 22 h^2: one expansion was 1.5-8 times RKC's error (l = 1..3)
    chebyshev = decay_errors(HeatFlow(time, method="chebyshev")(u0, surface), surface, time,
                             "cubic")
    rkc = decay_errors(HeatFlow(time, steps=32)(u0, surface), surface, time, "cubic")
    assert max(c / r for c, r in zip(chebyshev[:3], rkc[:3], strict=True)) < 1.3


def test_chebyshev_integrates_entries_whose_bands_differ_apart():
    """A sphere's phi is a distance far out, a thin trefoil's is not: their bands differ, and
    each entry must get its own (the narrowest band for both left the sphere's outer band
    nodes unevolved: 0.55 off)."""
    grid = ts.Grid.cube(32, 1.5)
    phi = torch.cat([ts.sdf.sphere(grid, 1.0), ts.sdf.trefoil(grid, 0.2)])
    u0 = torch.rand(2, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    flow = HeatFlow(4 * grid.spacing**2, method="chebyshev")
    together = flow(u0, ts.ImplicitSurface(phi, grid))
    for b in range(2):
        alone = flow(u0[b:b + 1], ts.ImplicitSurface(phi[b:b + 1], grid))
        torch.testing.assert_close(together[b:b + 1], alone, atol=1e-6, rtol=0)


def test_rkc_holds_its_accuracy_over_long_times() -> None:
    # l = 1 to t = R^2 (106 h^2 at 33^3): RKC's default 8 steps re-extended the ring at every
    # stage and stayed 1.7 % off the decayed amplitude; steps that hold the ring, 2.7e-3
    from torchsurf.exact import SPHERE_CENTER, SPHERE_RADIUS

    case = ts.exact.sphere_harmonic(1, 33)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    time = SPHERE_RADIUS**2
    index = torch.arange(2000, dtype=torch.float64) + 0.5
    z = 1 - 2 * index / 2000
    angle = math.pi * (1 + 5**0.5) * index
    ring = (1 - z * z).sqrt()
    directions = torch.stack([ring * angle.cos(), ring * angle.sin(), z], dim=-1)
    points = torch.tensor(SPHERE_CENTER, dtype=torch.float64) + SPHERE_RADIUS * directions
    decay = math.exp(-2 * time / SPHERE_RADIUS**2)
    result = ts.HeatFlow(time)(case.u, surface)
    values = ts.sample(result, points, case.grid, interpolation="cubic")[0, 0]
    assert float((values - decay * z).abs().max()) < 5e-3 * decay


@pytest.mark.parametrize("method", ["implicit", "crank_nicolson", "rkc"])
@pytest.mark.parametrize("dtype, offset, tolerance", [(torch.float64, 1e7, 1e-7),
                                                      (torch.float32, 1e3, 8e-4)])
def test_steps_smooth_data_on_an_offset_as_without_it(method, dtype, offset, tolerance):
    """The theta methods solve for each step's change, whose right-hand side holds no offset
    (solved for u_new, the solver's relative tolerance stopped with the change 3% wrong at 1e7
    in float64; float32: 1e3, 4%); RKC's stages combine changes, not values (1.3e-3 at 1e3 in
    float32 before, now 3.8e-4: the data's own rounding there is 6e-5)."""
    grid = ts.Grid.cube(20, 1.2)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.8).to(dtype), grid)
    noise = torch.rand((1, 1, *grid.shape), generator=torch.Generator().manual_seed(0),
                       dtype=dtype)
    flow = HeatFlow(10 * grid.spacing**2, method=method, steps=None if method == "rkc" else 4)
    band = flow.band_mask(surface).expand_as(noise)
    plain = flow(noise, surface)
    shifted = flow(noise + offset, surface) - offset
    assert float((shifted - plain)[band].abs().max()) < tolerance


def test_a_diverged_torchdiffeq_run_names_its_steps_as_torchdiffeq_took_them():
    """Its message said 'None steps of <the whole time>': it names the equal steps a
    fixed-step method took (an adaptive one's, "torchdiffeq's own steps")."""
    pytest.importorskip("torchdiffeq")
    grid = ts.Grid.cube(24, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9, center=(0.05, 0.02, -0.03)), grid)
    u = torch.rand(1, 1, 24, 24, 24, generator=torch.Generator().manual_seed(0))
    end = 20 * grid.spacing**2
    with pytest.warns(RuntimeWarning, match="rk4 step of .* exceeds its stable step"), \
            pytest.raises(FloatingPointError, match="2 steps of") as raised:
        HeatFlow(time=end, method="rk4", options={"step_size": end / 2})(u, surface)
    assert "None" not in str(raised.value)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)   # its default step is stable: no warning
        assert torch.isfinite(HeatFlow(time=end, method="rk4")(u, surface)).all()


def test_an_unstable_torchdiffeq_step_given_by_steps_asks_for_more_steps():
    """Its advice was options={'step_size': ...}, which is refused beside steps=."""
    pytest.importorskip("torchdiffeq")
    grid = ts.Grid.cube(16, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9), grid)
    u = torch.rand(1, 1, 16, 16, 16, generator=torch.Generator().manual_seed(0))
    end = 20 * grid.spacing**2
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            HeatFlow(time=end, method="midpoint", steps=2)(u, surface)
        except FloatingPointError:
            pass
    advice = [str(w.message) for w in caught if "midpoint step" in str(w.message)]
    assert len(advice) == 1 and "step_size" not in advice[0], advice
    needed = int(advice[0].split("Use steps >= ")[1].split(",")[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # the advice holds: stable, no warning
        assert torch.isfinite(HeatFlow(time=end, method="midpoint", steps=needed)(u, surface)).all()


@pytest.mark.parametrize(("options", "message"), [
    (dict(method="chebyshev"), "re-extension reads closest points up to 2.9 cells"),
    (dict(method="euler", reextend_every=None), "band holds no node"),
    (dict(method="implicit", reextend_every=None), "band holds no node"),
])
def test_a_band_without_nodes_is_refused_naming_band_width(options, message):
    """A plane halfway between node layers, band_width 0.4 cells: no node is that close (the
    Chebyshev expansion divided by the empty band's bound of 0; it re-extends at every
    application, so it refuses any band under 2.9 cells, which always holds nodes)."""
    grid = ts.Grid((8, 8, 8), 0.1)
    x = torch.arange(8, dtype=torch.float64) * 0.1 - 0.35
    phi = x.view(1, 1, 1, 1, 8).expand(1, 1, 8, 8, 8).clone()
    surface = ts.ImplicitSurface(phi, grid)
    u0 = torch.rand(1, 1, 8, 8, 8, dtype=torch.float64)
    with pytest.raises(ValueError, match=rf"band_width=0.04 is 0.40 cells.*{message}|{message}.*"
                                         r"band_width=0.04 is 0.40 cells"):
        HeatFlow(1e-3, band_width=0.04, **options)(u0, surface)


@pytest.mark.parametrize("layout", ["dense", "bricks"])
def test_a_batch_entry_whose_band_holds_no_node_is_named(layout):
    """Entry 1's box has its faces halfway between node layers, entry 0's on them: the batch
    came back with entry 1 unchanged, while entry 1 alone was refused."""
    grid = ts.Grid((24, 24, 24), 0.1)
    boxes = [ts.sdf.box(grid, half_size=half, center=(1.2, 1.2, 1.2), dtype=torch.float64)
             for half in ((0.5, 0.5, 0.5), (0.55, 0.55, 0.55))]
    surface = ts.ImplicitSurface(torch.cat(boxes), grid)
    if layout == "bricks":
        surface = ts.bricks.from_dense(surface)
    u0 = torch.rand(surface.phi.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match=r"(band holds no node in batch entry \[1\]|batch entry 1: "
                                         r"the flow.s band holds no node): "
                                         r"band_width=0.04 is 0.40 cells"):
        HeatFlow(1e-3, band_width=0.04, method="euler", reextend_every=None)(u0, surface)


def test_requested_times_never_lengthen_a_given_step():
    """Each interval took round(steps x its share) steps: times 1.49 steps apart made every
    Euler step 1.49 times the stable one and the flow blew up (range [-23, 23] against
    [-1, 2.1]), with last_plan still reporting the given steps."""
    u0, surface = harmonics(25, torch.float64)
    flow = HeatFlow(0.1, method="euler")
    flow(u0, surface)
    steps, step = flow.last_plan.count, flow.last_plan.step
    fixed = HeatFlow(0.1, method="euler", steps=steps)
    alone = fixed(u0, surface)
    times = [1.49 * step * k for k in range(1, int(steps / 1.49) + 1)]
    times = [t for t in times if t < 0.1 * (1 - 1e-3)] + [0.1]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # neither unstable nor leaving the data's range
        result = fixed(u0, surface, times=times)[-1]
    assert fixed.last_plan.count > steps
    errors = decay_errors(result, surface, 0.1, "cubic")
    assert max(errors) < 1.5 * max(decay_errors(alone, surface, 0.1, "cubic")), errors


def test_chebyshev_refuses_what_the_other_methods_refuse():
    """Its path skipped the step planner's checks: time=10 ran 259 pieces (3.6 s) on a 17^3
    sphere and 1e6 would have run for days; a 1-cell band ran with errors of 0.06."""
    grid = ts.Grid.cube(17, 1.0)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.6), grid)
    u0 = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    for method in ("rkc", "chebyshev"):
        with pytest.raises(ValueError, match="times the time the diffusion takes to cross"):
            HeatFlow(1e3, method=method)(u0, surface)
        with pytest.raises(ValueError, match="band_width=0.125 is 1.00 cells of this grid"):
            HeatFlow(1e-3, method=method, band_width=grid.spacing)(u0, surface)


def test_times_inside_a_torchdiffeq_step_are_re_extended():
    """dopri5 returned u(0.3 T) of times=[0.3 T, T] as integrated, not constant along the
    normals: 0.3 off a run to 0.3 T alone 4-5 cells from S."""
    pytest.importorskip("torchdiffeq")
    u0, surface = harmonics(25, torch.float64)
    flow = HeatFlow(0.02, method="dopri5", options={"rtol": 1e-6, "atol": 1e-8})
    early = flow(u0, surface, times=[0.006, 0.02])[0]
    alone = HeatFlow(0.006, method="dopri5", options={"rtol": 1e-6, "atol": 1e-8})(u0, surface)
    band = flow.band_mask(surface)
    assert float(((early - alone) * band).abs().max()) < 1e-3


def test_times_taken_as_the_end_and_gradients_the_times_would_lose():
    u0, surface = harmonics(17, torch.float64)
    flow = HeatFlow(0.01)
    below = float(torch.tensor(0.01, dtype=torch.float32))  # 0.00999999977648258
    assert torch.equal(flow(u0, surface, times=[below])[0], flow(u0, surface))
    wanted = torch.tensor(0.005, dtype=torch.float64, requires_grad=True)
    with pytest.raises(ValueError, match=r"times\[0\] requires grad"):
        flow(u0, surface, times=[wanted, 0.01])


@pytest.mark.parametrize("method", ["rkc", "euler", "implicit"])
def test_requested_times_in_float32_give_the_float64_times_results(method):
    """A float32 time just above a whole number of steps (5.0000002) added a step to its
    interval, and one just below a multiple of the re-extension period a re-extension: the
    result moved by 6e-5 to 2e-4, a fifth of Euler's whole error, for times moved by 1e-9."""
    case = ts.exact.sphere_harmonic(2, 33, dtype=torch.float64)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    for end in (0.0384, 0.0407, 0.0453):
        times = [end / 3, 2 * end / 3, end]
        flow = HeatFlow(end, method=method)
        given = flow(case.u, surface, times=times)
        count = flow.last_plan.count
        rounded = flow(case.u, surface, times=torch.tensor(times, dtype=torch.float32))
        assert flow.last_plan.count == count
        torch.testing.assert_close(rounded, given, rtol=0, atol=1e-7)  # u_t dt: 8e-9
    # times on multiples of the time a cell's crossing takes, 12 / rho (the re-extension
    # marks of Euler and Heun, and the implicit steps' plan, rounded them apart; a review)
    rho = HeatFlow(0.01, method=method).system(case.u, surface).spectral_radius
    times = [12.0 / rho * k for k in range(1, 11)]
    flow = HeatFlow(times[-1], method=method)
    given = flow(case.u, surface, times=times)
    count = flow.last_plan.count
    rounded = flow(case.u, surface, times=torch.tensor(times, dtype=torch.float32))
    assert flow.last_plan.count == count
    torch.testing.assert_close(rounded, given, rtol=0, atol=1e-7)


@pytest.mark.parametrize("method", ["euler", "implicit", "rk4"])
def test_two_times_within_the_end_slack_are_two_times(method):
    """Both entries of ``[T (1 - 1e-7), T]`` were taken as ``T``: Euler, Heun and the implicit
    methods divided by a zero interval (ZeroDivisionError), rk4 and dopri5 returned one result
    for two times. Each result is now as close to the exact decay as the flow's own."""
    if method == "rk4":
        pytest.importorskip("torchdiffeq")
    u0, surface = harmonics(17, torch.float64)
    end = 0.01
    flow = HeatFlow(end, method=method)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        alone = decay_errors(flow(u0, surface), surface, end)
        out = flow(u0, surface, times=[end * (1 - 1e-7), end])
    assert out.shape[0] == 2
    for result in out:
        for error, reference in zip(decay_errors(result, surface, end), alone, strict=True):
            assert error <= 1.2 * reference + 1e-5, (error, reference)
    with pytest.raises(ValueError, match=r"times\[0\]"):
        HeatFlow(end)(u0, surface, times=[end * (1 + 1e-7), end * (1 + 2e-7)])


@pytest.mark.parametrize("method", ["rkc", "euler", "crank_nicolson", "chebyshev"])
def test_each_diffusivity_runs_with_its_own_steps(method):
    """Channels of ``D = (1, 100, 1)`` were planned together for ``D = 100``: the ``D = 1``
    channels took its re-extensions too and erred 5-9 times as much as alone (l = 2 harmonic,
    33^3-49^3; under ``"chebyshev"`` its pieces, a change of 3.7e-2 on noise beside
    ``D = 30``). Each group of channels now runs alone: the result equals each channel's own
    flow, in the caller's channel order, with requested times and gradients."""
    case = ts.exact.sphere_harmonic(2, 21, dtype=torch.float64)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    u0 = torch.cat([case.u, 2 * case.u, -case.u], dim=1).requires_grad_(True)
    steps = {"steps": 6} if method == "crank_nicolson" else {}
    flow = HeatFlow(0.01, diffusivity=torch.tensor([1.0, 100.0, 1.0], dtype=torch.float64),
                    method=method, **steps)
    u = flow(u0, surface, times=[0.005, 0.01])
    for channel, d in enumerate((1.0, 100.0, 1.0)):
        alone = HeatFlow(0.01, diffusivity=d, method=method, **steps)(
            u0[:, channel:channel + 1].detach(), surface, times=[0.005, 0.01])
        torch.testing.assert_close(u[:, :, channel:channel + 1], alone, rtol=0, atol=1e-13)
    u[-1].sum().backward()
    assert u0.grad is not None and bool(torch.isfinite(u0.grad).all())
    assert u0.grad[:, 0].abs().sum() > 0 and u0.grad[:, 1].abs().sum() > 0


def test_chebyshev_with_a_learned_time_keeps_sqrt_of_its_pieces_for_backward():
    """Beyond a quarter of the band's crossing time the expansions run in pieces, and autograd
    kept every piece's input: 0.83 / 13.4 MB saved at 1 / 100 h^2 (25^3, batch 2, two channels);
    groups of sqrt(pieces) recomputed in backward keep 0.5 / 2.0 MB, the same gradient."""
    grid = ts.Grid.cube(25, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    u = torch.rand(2, 2, *grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    saved = {}
    for cells in (1.0, 100.0):
        flow = HeatFlow(cells * grid.spacing**2, method="chebyshev", learn_time=True).double()
        sizes = []

        def pack(tensor, sizes=sizes):
            sizes.append(tensor.numel() * tensor.element_size())
            return tensor

        with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
            out = flow(u, surface)
        saved[cells] = sum(sizes)
    assert saved[100.0] < 5 * saved[1.0]
    (grad,) = torch.autograd.grad(out.square().sum(), flow.time_value.raw)
    step = 1e-4
    with torch.no_grad():
        ends = []
        for sign in (1, -1):
            flow.time_value.raw += sign * step
            ends.append(float(flow(u, surface).square().sum()))
            flow.time_value.raw -= sign * step
    assert float(grad) == pytest.approx((ends[0] - ends[1]) / (2 * step), rel=1e-5)


def test_a_band_just_wider_than_the_ring_bound_takes_no_flood_of_steps():
    """A step may hold the ring for 6 (w - 2 sqrt(3))^2 / rho on a band of w cells, which
    vanishes as w nears 2 sqrt(3): a heat flow on a band of 3.47 cells took 51,070 steps (18 s,
    against 0.14 s at 3.6 cells), and at 3.465 cells refused the time. Beyond
    HELD_RING_LINEAR_STEPS times its steps, a linear flow re-extends the ring at its stages."""
    grid = ts.Grid.cube(32, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(8))
    h = grid.spacing
    narrow = HeatFlow(0.01, band_width=3.4 * h)
    expected = narrow(u, surface)
    for cells in (3.465, 3.47, 3.6):
        flow = HeatFlow(0.01, band_width=cells * h)
        result = flow(u, surface)
        assert flow.last_plan.count <= integrators.HELD_RING_LINEAR_STEPS * integrators.RKC_STEPS
        near = surface.band_mask(1.5 * h).expand_as(u)
        assert (result - expected)[near].abs().max() < 5e-3  # measured 6.2e-4 to 3.2e-3
