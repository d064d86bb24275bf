"""Second-order Runge–Kutta–Chebyshev: coefficients, stability bound, order."""

from __future__ import annotations

import math

import pytest
import torch

from torchsurf.flows._rkc import coefficients, rkc_step, stages_for


def stability_polynomial(stages: int, z: float) -> float:
    """``R(z)``: one step of ``u' = lambda u`` with ``dt lambda = z``, from ``u = 1``."""
    u = torch.ones(1, dtype=torch.float64)
    return float(rkc_step(lambda x: z * x, u, 1.0, stages))


@pytest.mark.parametrize("stages", [2, 3, 5, 16, 60])
def test_stable_on_the_whole_interval_and_not_beyond(stages):
    beta = coefficients(stages).stability
    assert 0.39 * stages**2 < beta < 0.5 * stages**2
    grid = torch.linspace(-beta, 0.0, 2001, dtype=torch.float64)
    values = [abs(stability_polynomial(stages, float(z))) for z in grid]
    assert max(values) <= 1.0 + 1e-9
    assert abs(stability_polynomial(stages, -2.0 * beta)) > 1.0


@pytest.mark.parametrize("stages,bound", [(3, 0.58), (9, 0.51), (40, 0.51)])
def test_stiff_modes_are_damped(stages, bound):
    """Away from the slow modes the polynomial stays small: noise is smoothed, not kept
    (the textbook damping 2/13 leaves 0.95)."""
    beta = coefficients(stages).stability
    grid = torch.linspace(-beta, -2.0, 2001, dtype=torch.float64)
    assert max(abs(stability_polynomial(stages, float(z))) for z in grid) < bound


def test_default_heat_flow_smooths_noise_like_the_exact_flow():
    """RKC with the textbook damping (2/13) left 60x the roughness of the exact flow."""
    import torchsurf as ts

    grid = ts.Grid.cube(33, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    noise = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                       generator=torch.Generator().manual_seed(0))
    time = 30 * surface.spacing**2
    near = surface.band_mask(surface.spacing)

    def roughness(u):
        gradient = ts.intrinsic_gradient(u, surface)
        return gradient.square().sum(dim=1, keepdim=True).sqrt()[near].mean()

    exact = ts.HeatFlow(time, method="euler", steps=600)(noise, surface)
    default = ts.HeatFlow(time)(noise, surface)
    assert roughness(default) < 1.3 * roughness(exact), (roughness(default), roughness(exact))


def test_second_order_in_time():
    errors = []
    for count in (4, 8, 16):
        u = torch.ones(1, dtype=torch.float64)
        for _ in range(count):
            u = rkc_step(lambda x: -3.0 * x, u, 1.0 / count, 5)
        errors.append(abs(float(u) - math.exp(-3.0)))
    orders = [math.log2(a / b) for a, b in zip(errors, errors[1:], strict=False)]
    assert all(1.9 < order < 2.5 for order in orders), orders


@pytest.mark.parametrize("load", [0.5, 10.0, 157.0, 5000.0])
def test_fewest_stages_that_are_stable(load):
    stages = stages_for(load)
    assert coefficients(stages).stability >= load
    assert stages == 2 or coefficients(stages - 1).stability < load


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_stage_combination_is_the_same_on_every_path(dtype):
    """One compiled pass, five eager passes and the tensor arithmetic of a learned step give
    the same step (the compiled kernel's weights are 0-d tensors: one graph for every stage)."""
    generator = torch.Generator().manual_seed(1)
    u = torch.randn((2, 3, 9, 10, 11), dtype=dtype, generator=generator)
    weights = torch.rand((1, 3, 1, 1, 1), dtype=dtype, generator=generator)

    def rate(x):
        return -weights * x + 0.1 * x.roll(1, dims=-1)

    eager = rkc_step(rate, u, 0.3, 7, "slicing")
    compiled = rkc_step(rate, u, 0.3, 7, "compiled")
    learned = rkc_step(rate, u, torch.tensor(0.3, dtype=dtype), 7, "slicing")
    tolerance = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(compiled, eager, rtol=tolerance, atol=tolerance)
    torch.testing.assert_close(learned, eager, rtol=tolerance, atol=tolerance)
    assert not torch.equal(eager, u)


@pytest.mark.parametrize("path", ["compiled", "auto"])
def test_a_flow_runs_its_stages_on_its_own_path(path, monkeypatch):
    import torchsurf as ts
    from torchsurf.flows import _rkc

    seen = []
    run = _rkc.backend.run

    def recording(kernel, chosen, *args):
        if kernel is _rkc._STAGE:
            seen.append(chosen)
        return run(kernel, chosen, *args)

    monkeypatch.setattr(_rkc.backend, "run", recording)
    monkeypatch.setattr(_rkc, "STAGE_COMPILE_MIN_VOXELS", 0)
    # the route is under test, not inductor (its kernels: tests/test_compiled_kernels.py);
    # compiling the flow's kernels cost 44 s here with a cold cache
    monkeypatch.setattr(_rkc.backend, "compiled", lambda function, *options: function)
    grid = ts.Grid.cube(13, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    # more channels than the native stages take (tests/flows/test_packed_flow.py)
    from torchsurf.flows._native_gather import STAGE_COLUMNS

    u = torch.rand((1, STAGE_COLUMNS + 1, *grid.shape), generator=torch.Generator().manual_seed(0))
    ts.HeatFlow(0.01, path=path)(u, surface)
    assert seen and set(seen) == {path}


@pytest.mark.parametrize("value", [0.3, -7.7, 1e4])
def test_a_step_keeps_a_constant_exactly(value):
    """The stages combine changes (increment form): the textbook weights (1 - mu - nu, mu,
    nu) do not sum to 1 in float32 and moved 0.3 by 2.6e-6 in 32 stages."""
    u = torch.full((1, 1, 4, 4, 4), value, dtype=torch.float32)
    for stages in (4, 8, 16, 32):
        assert torch.equal(rkc_step(torch.zeros_like, u, 0.5, stages, path="slicing"), u)
