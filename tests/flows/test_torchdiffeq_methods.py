"""torchdiffeq's methods through the flows: every one right on the heat flow, its options
checked, runaway runs refused before the work, and the record of steps true."""

from __future__ import annotations

import math

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import HeatFlow
from torchsurf.flows._integrators import FIXED_STEP

pytest.importorskip("torchdiffeq")

TIME = 0.05


@pytest.fixture(scope="module")
def sphere():
    grid = ts.Grid.cube(21, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    u0 = (z / (x * x + y * y + z * z).sqrt().clamp_min(1e-6))[None, None]
    near = surface.distance() <= grid.spacing
    return surface, u0, near


@pytest.mark.parametrize("method, time", [("heun2", TIME), ("rk4", TIME),
                                          ("fixed_adams", TIME / 10), ("explicit_adams", 0.002)])
def test_every_fixed_step_method_takes_a_stable_step_by_default(sphere, method, time):
    """heun2 and fixed_adams took one step per piece (not in the fixed-step list), and
    explicit_adams Euler's step, 600 times its stable one: 0.12 off on the l = 1 harmonic.
    (The Adams methods' stable steps are short: shorter times keep the test fast.)"""
    surface, u0, near = sphere
    exact = math.exp(-2 * time) * u0
    reference = HeatFlow(time)(u0, surface)
    noisy = u0 + 0.1 * torch.randn(u0.shape, generator=torch.Generator().manual_seed(0),
                                   dtype=u0.dtype)
    flow = HeatFlow(time, method=method)
    error = (flow(u0, surface) - exact)[near].abs().max()
    assert error < 1.2 * (reference - exact)[near].abs().max()
    assert flow.last_plan.count is not None and flow.last_plan.count >= 4
    smoothed = flow(noisy, surface)
    assert (smoothed - HeatFlow(time)(noisy, surface))[near].abs().max() < 0.02


def test_the_fixed_step_list_is_torchdiffeqs():
    from torchdiffeq._impl.odeint import SOLVERS
    from torchdiffeq._impl.solvers import FixedGridODESolver

    fixed = {name for name, solver in SOLVERS.items() if issubclass(solver, FixedGridODESolver)}
    assert fixed == set(FIXED_STEP)


@pytest.mark.parametrize(
    "options, error, match",
    [({"step_size": -1e-3}, ValueError, r"options\['step_size'\]"),
     ({"step_size": 0}, ValueError, r"options\['step_size'\]"),
     ({"rtol": -1.0}, ValueError, r"options\['rtol'\]"),
     ({"atol": float("nan")}, ValueError, r"options\['atol'\]"),
     ({"max_num_steps": 2.5}, ValueError, r"options\['max_num_steps'\]"),
     ("abc", TypeError, "options must be a dict")],
)
def test_options_are_checked_by_name(options, error, match):
    with pytest.raises(error, match=match):
        HeatFlow(TIME, method="rk4", options=options)


def test_tolerances_a_method_ignores_or_cannot_meet_and_a_named_norm_are_refused():
    """rtol on rk4 was ignored without a word (rtol=1e3 gave the run of no options), rtol and
    atol of 0 ended in "steps shrank" naming neither, norm="max" in a bare TypeError."""
    with pytest.raises(ValueError, match=r"options\['rtol'\] is for .* own steps"):
        HeatFlow(TIME, method="rk4", options={"rtol": 1e3})
    with pytest.raises(ValueError, match="both 0"):
        HeatFlow(TIME, method="dopri5", options={"rtol": 0, "atol": 0})
    with pytest.raises(TypeError, match=r"options\['norm'\] must be a function"):
        HeatFlow(TIME, method="dopri5", options={"norm": "max"})
    HeatFlow(TIME, method="dopri5", options={"rtol": 0, "atol": 1e-8})
    # the Adams-Moulton corrector of these two iterates to them (a review)
    HeatFlow(TIME, method="implicit_adams", options={"rtol": 1e-6, "atol": 1e-8})
    HeatFlow(TIME, method="fixed_adams", options={"rtol": 1e-6})


def test_a_step_size_is_refused_for_a_method_that_chooses_its_steps():
    HeatFlow(TIME, method="rk4", options={"step_size": 1e-3})
    with pytest.raises(ValueError, match="fixed-step methods"):
        HeatFlow(TIME, method="dopri5", options={"step_size": 1e-3})


def test_a_fixed_step_run_of_too_many_steps_is_refused_before_any_work(sphere):
    surface, u0, _ = sphere
    with pytest.raises(ValueError, match="needs 50000000 steps of method='rk4'"):
        HeatFlow(TIME, method="rk4", options={"step_size": 1e-9})(u0, surface)


def test_an_adaptive_run_stops_with_an_error_after_max_num_steps(sphere):
    surface, u0, _ = sphere
    flow = HeatFlow(TIME, method="dopri5", options={"max_num_steps": 3, "rtol": 1e-10,
                                                      "atol": 1e-12})
    with pytest.raises(RuntimeError, match="method='dopri5' took more than 3 steps"):
        flow(u0, surface)


def test_torchdiffeqs_other_stops_are_named(sphere, monkeypatch):
    """torchdiffeq stops a run whose steps shrink without end with a bare AssertionError
    ("underflow in dt ..."), which leaked through every flow; it is now a RuntimeError naming
    the method and the remedy."""
    import torchdiffeq

    def underflow(*args, **kwargs):
        raise AssertionError("underflow in dt 7.5e-19")

    surface, u0, _ = sphere
    monkeypatch.setattr(torchdiffeq, "odeint", underflow)
    with pytest.raises(RuntimeError, match=r"method='dopri5' stopped \(underflow in dt .*'rkc'"):
        HeatFlow(TIME, method="dopri5")(u0, surface)


def test_steps_given_to_an_adaptive_method_are_not_recorded_as_taken(sphere):
    surface, u0, _ = sphere
    flow = HeatFlow(TIME, method="dopri5", steps=3)
    flow(u0, surface)
    assert flow.last_plan.count is None
    rk4 = HeatFlow(TIME, method="rk4")
    rk4(u0, surface)
    assert rk4.last_plan.count == math.ceil(TIME / (1.8 / rk4_rho(rk4, u0, surface)) - 1e-9)


def rk4_rho(flow: HeatFlow, u0: torch.Tensor, surface: ts.ImplicitSurface) -> float:
    return flow.system(u0, surface).spectral_radius


def test_options_given_to_a_built_in_method_are_refused_as_torchdiffeq_settings():
    """A step_size for RKC was refused as 'chooses its own steps (rtol, atol)'."""
    with pytest.raises(ValueError, match="options and adjoint are torchdiffeq settings"):
        HeatFlow(TIME, method="rkc", options={"step_size": 1e-3})


def test_steps_and_a_step_size_together_are_refused():
    """``steps=`` overrode ``options['step_size']`` without a word, and the stability warning
    then asked for the step size already given."""
    with pytest.raises(ValueError, match=r"steps=3 and options\['step_size'\] both"):
        HeatFlow(TIME, method="rk4", steps=3, options={"step_size": TIME / 10})


def test_adaptive_steps_meet_their_tolerance_on_the_band_whatever_the_box():
    """torchdiffeq's default error norm is over the whole state: the nodes beyond the band,
    which never change, diluted the error, so a box with more room around the same surface took
    longer steps (Perona–Malik at rtol 1e-5: 2.2e-6 off in a 24^3 box, 1.0e-4 in a 47^3 one).
    The flows' norm is over the band: the same surface, spacing and data in a box twice as wide
    give the same result to the tolerance (here 7e-6 apart at rtol 1e-4, 1.3e-2 before)."""
    spacing = 0.125
    results = []
    for half in (1.5, 3.0):
        grid = ts.Grid.cube(int(round(2 * half / spacing)) + 1, bound=half)
        phi = ts.sdf.sphere(grid, radius=1.0, center=(0.03, -0.05, 0.02), dtype=torch.float64)
        surface = ts.ImplicitSurface(phi, grid)
        x, y, z = grid.points(dtype=torch.float64).unbind(-1)
        u0 = torch.sin(2 * x + y) * torch.cos(3 * z)
        flow = ts.AnisotropicFlow(4 * spacing**2, "perona_malik", contrast=0.5,
                                  method="dopri5", options={"rtol": 1e-4, "atol": 1e-6})
        out = flow(u0[None, None], surface)[0, 0]
        near = surface.distance()[0, 0] <= spacing
        inner = [slice(None)] * 3 if half == 1.5 else [slice(12, -12)] * 3
        results.append((out[inner], near[inner]))
    (small, near), (large, _) = results
    assert small.shape == large.shape
    assert float((small - large)[near].abs().max()) < 1e-4


def test_float32_times_at_a_pieces_end_and_times_that_round_together_are_each_returned():
    """The pieces between re-extensions end at ``k end / pieces``; a float32 requested time a
    rounding short of one was a time of the solve equal to that end once in float32 data, and
    torchdiffeq refused it ("t must be strictly increasing") with an error that blamed a stiff
    flow. Each time now comes back, equal to the float64 time's result to rounding."""
    case = ts.exact.sphere_harmonic(2, 21, dtype=torch.float32)
    surface = ts.ImplicitSurface(case.phi, case.grid)
    flow = HeatFlow(TIME, method="rk4")
    third = flow(case.u, surface, times=[TIME / 3, TIME])
    for times in (torch.tensor([TIME / 3, TIME]), [TIME / 3 * (1 - 1e-9), TIME / 3, TIME]):
        results = flow(case.u, surface, times=times)
        assert results.shape[0] == len(times)
        torch.testing.assert_close(results[-2:], third, rtol=0, atol=1e-6)
    assert flow(case.u, surface, times=[TIME - 1e-9, TIME]).shape[0] == 2
    # a time that is 0 in float32 is the start: one more time of the solve equal to it
    tiny = flow(case.u, surface, times=[1e-46, 1e-30, TIME])
    torch.testing.assert_close(tiny[0], tiny[1], rtol=0, atol=1e-6)


def test_scipy_solver_takes_its_explicit_solvers_and_refuses_the_dense_jacobians(sphere):
    """scipy's default LSODA formed a dense Jacobian of the volume: an IndexError after
    'lsoda: Illegal input detected' on a 25^3 harmonic map, numpy's 91 GiB MemoryError on a
    48^3 heat flow. Refused by name before any work; RK45 runs to the heat flow's accuracy."""
    pytest.importorskip("scipy")
    surface, u0, near = sphere
    for options in (None, {"solver": "LSODA"}, {"solver": "BDF"}):
        named = "(the default)" if options is None else options["solver"]
        with pytest.raises(ValueError, match=rf"method='scipy_solver' with options\['solver'\]"
                                             rf"=.*{named}.*dense Jacobian.*'RK45'"):
            HeatFlow(TIME, method="scipy_solver", options=options)
    flow = HeatFlow(TIME, method="scipy_solver", options={"solver": "RK45"})
    result = flow(u0, surface)
    exact = math.exp(-2 * TIME) * u0
    assert float((result - exact)[near].abs().max()) < 2 * float(
        (HeatFlow(TIME)(u0, surface) - exact)[near].abs().max())


def test_scipy_solver_classes_names_and_a_solve_that_stops_early(sphere, monkeypatch):
    """An explicit solver given as its class runs; a name scipy lacks is not called stiff;
    a solve that stopped on the way had returned u0 as u(T) (or an IndexError with times)."""
    pytest.importorskip("scipy")
    from scipy.integrate import RK45

    surface, u0, near = sphere
    HeatFlow(TIME, method="scipy_solver", options={"solver": RK45})
    with pytest.raises(ValueError, match=r"'rk45'\]?.*not one of scipy's explicit"):
        HeatFlow(TIME, method="scipy_solver", options={"solver": "rk45"})
    flow = HeatFlow(TIME, method="scipy_solver", options={"solver": "RK45"})
    system = flow.system
    calls = []

    def failing(*args, **kwargs):
        built = system(*args, **kwargs)
        rate = built.rate

        def turning_nan(u):
            calls.append(1)
            return rate(u) * (float("nan") if len(calls) > 20 else 1.0)

        built.rate = turning_nan
        return built

    monkeypatch.setattr(flow, "system", failing)
    with pytest.raises(RuntimeError, match=r"stopped at 1 of the 2 times .*solve_ivp gave up"):
        flow(u0, surface)
