"""ReactionDiffusion: a pattern grows from Turk's near-uniform start, reproducibly, its scale set by s."""

from __future__ import annotations

import math

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import ReactionDiffusion
from torchsurf.operators import intrinsic_gradient


@pytest.fixture(scope="module")
def surface():
    grid = ts.Grid.cube(21, bound=1.3)
    return ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0), grid)


def variance_on_surface(u, surface):
    near = (surface.phi.abs() <= surface.spacing)[0, 0]
    return float(u[0, 1][near].var())


def test_an_entry_of_data_on_one_surface_is_its_run_alone(surface):
    """The step follows the data's largest a and b: planned for the whole batch, Turk's start
    beside a start four times larger took 306 steps instead of 286 and came out 3e-4 off its
    run alone. Each entry is planned alone now; the generator's draws are the batch's."""
    start = ReactionDiffusion.initial(surface)
    flow = ReactionDiffusion(time=100.0)
    alone = flow(start, surface, generator=torch.Generator().manual_seed(1))
    both = flow(torch.cat([start, 4 * start]), surface,
                generator=torch.Generator().manual_seed(1))
    # to rounding: "auto" may compile a kernel between two calls
    torch.testing.assert_close(both[:1], alone, rtol=0, atol=1e-6)
    generator = torch.Generator().manual_seed(1)
    torch.rand((1, 1, *start.shape[2:]), generator=generator, dtype=torch.float64)
    second = flow(4 * start, surface, generator=generator)  # drawn after the first entry's
    torch.testing.assert_close(both[1:], second, rtol=0, atol=1e-6)


@pytest.mark.compiled
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
    # "auto" may switch a kernel from eager to compiled between two calls (docs: every path
    # gives the same numbers to rounding), so the same seed gives the pattern to rounding
    torch.testing.assert_close(first, second, rtol=1e-5, atol=1e-5)
    assert float((first - other).abs().max()) > 1e-2


def test_anisotropic_variant_runs_along_a_tangent_field(surface):
    u0 = ReactionDiffusion.initial(surface, batch=2)
    e1, _ = surface.principal_directions()
    u = ReactionDiffusion(time=20.0)(u0, surface, direction=e1,
                                    generator=torch.Generator().manual_seed(0))
    assert u.shape == u0.shape and torch.isfinite(u).all()


def wavelength_on_surface(u, surface):
    """Characteristic wavelength of ``b`` on S, world units: ``2 pi std(b) / rms |grad_S b|``.

    Over the nodes within one cell of S. For ``b = mean + A cos(k . x)`` the ratio
    ``rms |grad_S b| / std(b)`` is ``k``, so this is ``2 pi / k``; for a mixture it is a
    ``k^2``-weighted mean. Central differences read ``sin(k h) / h`` for ``k``, which biases short
    wavelengths up a little (+8% at 9 cells) and damps the grid-scale noise of ``beta``.
    """
    near = (surface.phi.abs() <= surface.spacing)[0, 0]
    b = u[:, 1:]
    gradient = (intrinsic_gradient(b, surface)[0] ** 2).sum(dim=0)[near].mean()
    return 2 * math.pi * float(b[0, 0][near].std()) / float(gradient.sqrt())


@pytest.fixture(scope="module")
def sphere41():
    grid = ts.Grid.cube(41, bound=1.3)
    return ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0), grid)


def wavelengths_in_cells(surface, rates, seed):
    """Wavelength of the pattern, cells, after running each rate ``s`` to ``s t = 4``."""
    u0 = ReactionDiffusion.initial(surface)
    lengths = []
    for rate in rates:
        u = ReactionDiffusion(time=4.0 / rate, rate=rate)(
            u0, surface, generator=torch.Generator().manual_seed(seed))
        assert torch.isfinite(u).all()
        lengths.append(wavelength_on_surface(u, surface) / surface.spacing)
    return lengths


def assert_scale_follows_the_rate(rates, cells):
    """Wavelengths within -20%/+25% of ``(pi / 2) / sqrt(s)`` cells; log-log slope -0.5 +- 0.15."""
    predicted = [math.pi / 2 / math.sqrt(rate) for rate in rates]
    report = f"measured {[round(c, 2) for c in cells]}, predicted {[round(p, 2) for p in predicted]}"
    for length, expected in zip(cells, predicted, strict=True):
        assert 0.8 < length / expected < 1.25, report
    x = [math.log(rate) for rate in rates]
    y = [math.log(length) for length in cells]
    mx, my = sum(x) / len(x), sum(y) / len(y)
    slope = sum((a - mx) * (b - my) for a, b in zip(x, y, strict=True)) / sum((a - mx) ** 2 for a in x)
    assert -0.65 < slope < -0.35, f"slope {slope:.3f}; {report}"


@pytest.mark.compiled
def test_pattern_scale_follows_the_rate(sphere41):
    """The pattern's wavelength scales like ``1 / sqrt(s)``: ``s`` = 1/128 and 1/32, ratio 2.

    Turk's reaction–diffusion model: with ``t' = s t`` and ``x' = sqrt(s) x`` the equations lose ``s``,
    ``a_t' = 16 - a b + D_a L' a`` and ``b_t' = a b - b - beta + D_b L' b``, so at equal ``s t``
    the patterns of two rates are the same up to a length scale ``1 / sqrt(s)`` (the sphere's
    fixed radius and the per-node noise of ``beta`` break this only mildly). Linearised about
    ``a = b = 4``, the growing modes peak at ``k^2 = 2 s / sqrt(D_a D_b) = 16 s / h^2`` with
    Turk's ``D_a = h^2 / 4``, ``D_b = h^2 / 16``: wavelength ``(pi / 2) h / sqrt(s)``, 17.8 cells
    at ``s = 1/128``, 12.6 at 1/64, 8.9 at 1/32; log-log slope -1/2.

    Runs end at ``s t = 4``: the variance of ``b`` has grown ~40-fold since ``s t = 1/4`` and
    the pattern is still near the linear regime. Measured on 41^3, seeds 0-7, cells at
    s = 1/128, 1/64, 1/32: 17.4-18.6, 12.8-13.3, 9.7-10.0; slope -0.42 to -0.46 (the
    central-difference gradient lengthens 9-cell waves by 8%, so about -0.45 is expected).
    With ``s`` ignored (fixed at 1/128 or 1/32 inside the flow) the slope was -0.23 or -0.05.
    """
    rates = [1 / 128, 1 / 32]
    assert_scale_follows_the_rate(rates, wavelengths_in_cells(sphere41, rates, seed=0))


@pytest.mark.slow
@pytest.mark.compiled
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_pattern_scale_follows_the_rate_over_seeds(sphere41, seed):
    """As :func:`test_pattern_scale_follows_the_rate` over three rates (1/128, 1/64, 1/32) and
    other seeds; the wavelength also falls monotonically with ``s``."""
    rates = [1 / 128, 1 / 64, 1 / 32]
    cells = wavelengths_in_cells(sphere41, rates, seed)
    assert cells[0] > cells[1] > cells[2], cells
    assert_scale_follows_the_rate(rates, cells)


@pytest.mark.compiled
def test_long_run_stays_finite_with_b_nonnegative(sphere41):
    """Without Turk's clamp of ``b`` at 0 this run (``s t = 20``) ended in NaN."""
    u0 = ReactionDiffusion.initial(sphere41)
    flow = ReactionDiffusion(time=640.0, rate=1.0 / 32.0)
    u = flow(u0, sphere41, generator=torch.Generator().manual_seed(0))
    assert torch.isfinite(u).all()
    assert float(u[:, 1].min()) == 0.0  # the pattern is saturated: b reaches the clamp
    assert float(u[:, 0].max()) < 10.0


def test_needs_two_channels(surface):
    with pytest.raises(ValueError, match="u0"):
        ReactionDiffusion(time=1.0)(ReactionDiffusion.initial(surface)[:, :1], surface)


def test_a_seed_given_as_generator_is_refused_naming_it(surface):
    # torch.rand raised its own TypeError, naming none of this call's arguments
    flow = ReactionDiffusion(1.0)
    with pytest.raises(TypeError, match="generator must be a torch.Generator or None, got int"):
        flow(ReactionDiffusion.initial(surface), surface, generator=1)


def test_direction_batch_mismatch_names_direction_and_u0(surface):
    u0 = ReactionDiffusion.initial(surface, batch=2)
    direction = torch.zeros(3, 3, *surface.grid.shape)
    with pytest.raises(ValueError, match="direction has batch size 3 but u0 has 2"):
        ReactionDiffusion(1.0, steps=1)(u0, surface, direction=direction)


def test_directional_step_comes_from_each_chemicals_own_operator():
    """With a direction, ``a`` diffuses along it only: the bound is ``max(D_a rho_T, D_b rho)``
    (``rho_T`` the directional operator's Gershgorin bound), not ``D_a`` times Laplace-Beltrami's,
    so the stable Euler step is longer and the run takes fewer steps."""
    from torchsurf.operators import directional_bound, laplace_beltrami_bound

    grid = ts.Grid.cube(24, bound=1.6)
    torus = ts.ImplicitSurface(ts.sdf.torus(grid), grid)
    u0 = ReactionDiffusion.initial(torus)
    e1, _ = torus.principal_directions()
    flow = ReactionDiffusion(time=10.0, rate=1.0 / 16.0)
    d_a, d_b = grid.spacing**2 / 4.0, grid.spacing**2 / 16.0
    system = flow.system(u0, torus, direction=e1)
    rho_t, rho = directional_bound(torus, e1), laplace_beltrami_bound(torus)
    assert system.spectral_radius == pytest.approx(
        max(d_a * rho_t, d_b * rho) + (4.0 + 4.0 + 1.0) / 16.0, rel=1e-6)
    assert d_a * rho_t < d_a * laplace_beltrami_bound(torus, "symmetric")


def test_rkc_limits_its_steps_for_the_reactions_growth():
    """RKC on a long run: its steps stay within the reaction's growth (``a`` rises to 8 as the
    spots form, so ``b`` grows at up to ``s (a - 1)``); with no growth given it took 13 steps
    of 96 here and returned NaN (and 86 steps of 116 at ``s = 1/128``, ``t = 10^4``)."""
    grid = ts.Grid.cube(24, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    flow = ReactionDiffusion(1250.0, rate=1.0 / 16.0, method="rkc")
    with torch.no_grad():
        u = flow(ReactionDiffusion.initial(surface), surface,
                 generator=torch.Generator().manual_seed(0))
    band = flow.band_mask(surface)[0, 0]
    a, b = u[0, 0][band], u[0, 1][band]
    assert torch.isfinite(u[0][:, band]).all()
    assert float(b.min()) >= 0.0
    assert float(a.max()) > 6.0 and float(b.std()) > 0.5  # spots, not the homogeneous start
    assert float(a.max()) < 16.0


@pytest.mark.parametrize("method", ["rkc", "euler"])
def test_a_diverged_run_advises_another_method_only_when_there_is_one(monkeypatch, method):
    import torchsurf.flows.base as base

    monkeypatch.setattr(base, "integrate", lambda method, system, u0, schedule: [u0 * torch.nan])
    grid = ts.Grid.cube(16, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    with pytest.raises(FloatingPointError, match="diverged") as raised:
        ReactionDiffusion(10.0, method=method)(ReactionDiffusion.initial(surface), surface)
    assert ("use method='rkc'" in str(raised.value)) == (method != "rkc")


def test_a_seed_gives_one_pattern_in_float32_and_float64(surface):
    """The noise was drawn in u0's dtype: other numbers altogether in float32."""
    grid = surface.grid
    double = ts.ImplicitSurface(surface.phi.double(), grid)
    flow = ReactionDiffusion(time=50.0)
    results = [flow(ReactionDiffusion.initial(s), s, generator=torch.Generator().manual_seed(3))
               for s in (surface, double)]
    band = double.band_mask().expand_as(results[1])
    change = float((results[1] - ReactionDiffusion.initial(double))[band].abs().max())
    difference = float((results[0].double() - results[1])[band].abs().max())
    assert difference < 1e-3 * change


def test_a_direction_that_requires_grad_gets_its_gradient_through_checkpoints(surface):
    """The direction was not declared to the recomputed segments: backward raised."""
    points = surface.grid.points()
    direction = torch.stack([-points[..., 1], points[..., 0], 0.3 + 0 * points[..., 2]])[None]
    direction = direction.double().requires_grad_()
    double = ts.ImplicitSurface(surface.phi.double(), surface.grid)
    u0 = ReactionDiffusion.initial(double) + 0.1 * torch.rand(
        1, 2, *surface.grid.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    gradients = []
    for checkpoint in ("auto", False):
        flow = ReactionDiffusion(time=2.0, noise=0.0, checkpoint=checkpoint)
        out = flow(u0, double, direction=direction)
        (gradient,) = torch.autograd.grad(out[:, :1].square().sum(), direction)
        gradients.append(gradient)
    assert float(gradients[1].abs().max()) > 0
    torch.testing.assert_close(gradients[0], gradients[1], rtol=1e-9, atol=1e-12)


def _reaction_ode(a: float, b: float, end: float, s: float = 1 / 128, beta: float = 12.0
                  ) -> tuple[float, float]:
    """Turk's reaction without diffusion (spatially constant data), by RK4 steps of 0.01."""
    def rate(a: float, b: float) -> tuple[float, float]:
        return s * (16 - a * b), s * (a * b - b - beta)

    dt = 0.01
    for _ in range(round(end / dt)):
        k1 = rate(a, b)
        k2 = rate(a + dt / 2 * k1[0], b + dt / 2 * k1[1])
        k3 = rate(a + dt / 2 * k2[0], b + dt / 2 * k2[1])
        k4 = rate(a + dt * k3[0], b + dt * k3[1])
        a += dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        b += dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    return a, b


def test_constant_data_follow_the_reactions_ode_and_converge_in_steps():
    """Constant data's exact flow is the reaction's ODE. Heun held the ring between
    re-extensions, which pulled the band back toward S's former values: here 1.1e-4 at 80 steps
    and 9.4e-5 at 160. The ring now follows every evaluation: second order (1.2e-5, 3.1e-6)."""
    grid = ts.Grid.cube(20, bound=1.3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    near = (surface.distance() <= 0.5 * grid.spacing)[:, 0]
    start = ReactionDiffusion.initial(surface)
    start[:, 0], start[:, 1] = 6.0, 3.0
    end = 60.0
    exact = torch.tensor(_reaction_ode(6.0, 3.0, end), dtype=torch.float64)
    errors = {}
    for steps in (80, 160):
        out = ReactionDiffusion(end, noise=0.0, method="heun", steps=steps)(start, surface)
        errors[steps] = max(float((out[:, c][near] - exact[c]).abs().max()) for c in range(2))
    assert errors[160] < 5e-6
    assert errors[80] / errors[160] > 3.5  # second order
