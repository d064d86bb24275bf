"""Conjugate gradients: converges, refuses non-finite residuals, warns when it gives up."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows._solve import SolverOptions, conjugate_gradient


def spd_operator(n: int = 8, dtype: torch.dtype = torch.float64):
    generator = torch.Generator().manual_seed(1)
    matrix = torch.randn(n, n, generator=generator, dtype=dtype)
    matrix = matrix @ matrix.T + 0.01 * torch.eye(n, dtype=dtype)

    def apply(x: torch.Tensor) -> torch.Tensor:
        flat = x.reshape(*x.shape[:2], -1, 1)
        return (matrix @ flat).reshape(x.shape)

    return apply


def rhs(batch: int = 2, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    return torch.randn(batch, 1, 2, 2, 2, generator=torch.Generator().manual_seed(2), dtype=dtype)


def test_converges_to_the_tolerance():
    operator, b = spd_operator(), rhs()
    x, iterations = conjugate_gradient(operator, b, torch.zeros_like(b), SolverOptions(1e-10))
    assert iterations <= 20
    torch.testing.assert_close(operator(x), b, atol=1e-8, rtol=0)


def test_tolerance_is_honoured():
    operator, b = spd_operator(), rhs()
    _, loose = conjugate_gradient(operator, b, torch.zeros_like(b), SolverOptions(1e-2))
    _, tight = conjugate_gradient(operator, b, torch.zeros_like(b), SolverOptions(1e-12))
    assert loose < tight


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_residual_raises(bad):
    operator, b = spd_operator(), rhs()
    b[1, 0, 0, 0, 0] = bad
    with pytest.raises(FloatingPointError, match="NaN or infinite at iteration 0"):
        conjugate_gradient(operator, b, torch.zeros_like(b), SolverOptions())


def test_not_converging_warns_with_residual_and_tolerance():
    operator, b = spd_operator(), rhs()
    with pytest.warns(RuntimeWarning, match=r"max_iterations = 2 .*relative residual .*"
                                            r"tolerance 1e-10"):
        _, iterations = conjugate_gradient(
            operator, b, torch.zeros_like(b), SolverOptions(1e-10, max_iterations=2))
    assert iterations == 2


def test_zero_iterations_warns():
    operator, b = spd_operator(), rhs()
    with pytest.warns(RuntimeWarning, match="max_iterations = 0"):
        x, _ = conjugate_gradient(operator, b, torch.zeros_like(b),
                                  SolverOptions(max_iterations=0))
    assert bool((x == 0).all())


def test_float32_batch_with_a_zero_right_hand_side_stays_finite():
    """A volume converged at exactly 0 residual must not turn NaN while another iterates."""
    operator, b = spd_operator(dtype=torch.float32), rhs(dtype=torch.float32)
    b[1] = 0
    x, _ = conjugate_gradient(operator, b, torch.zeros_like(b), SolverOptions(1e-5))
    assert bool(torch.isfinite(x).all())
    assert bool((x[1] == 0).all())
    torch.testing.assert_close(operator(x), b, atol=1e-3, rtol=0)


@pytest.mark.parametrize("method", ["implicit", "crank_nicolson"])
def test_implicit_flows_warn_when_conjugate_gradients_stop_early(method):
    import torchsurf as ts
    from torchsurf.flows import HeatFlow

    grid = ts.Grid.cube(11, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    u0 = grid.points(dtype=torch.float64)[..., 2][None, None]
    with pytest.warns(RuntimeWarning, match="conjugate gradients stopped at max_iterations = 1"):
        HeatFlow(0.05, method=method, steps=1, max_iterations=1)(u0, surface)


@pytest.mark.parametrize("method", ["implicit", "crank_nicolson"])
@pytest.mark.parametrize("dtype, factors", [(torch.float32, (1e-25, 1e-12, 1e12, 1e20)),
                                            (torch.float64, (1e-160, 1e150))])
def test_implicit_flows_are_equivariant_in_the_data_scale(method, dtype, factors):
    """``flow(k u0) = k flow(u0)``: in float32 the squared norms of data near 1e-20 underflowed
    and the solve stopped at once (0.49 off at k = 1e-25), near 1e19 they overflowed
    (FloatingPointError); the explicit methods were equivariant. Now to rounding. A batch of
    two scales at once gives each its own."""
    import torchsurf as ts

    grid = ts.Grid.cube(16, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=dtype), grid)
    u0 = torch.rand((1, 1, 16, 16, 16), generator=torch.Generator().manual_seed(0), dtype=dtype)
    flow = ts.HeatFlow(8 * surface.spacing**2, method=method)
    reference = flow(u0, surface)
    band = flow.band_mask(surface)
    rounding = 64 * torch.finfo(dtype).eps
    for k in factors:
        scaled = flow(k * u0, surface) / k
        assert (scaled - reference)[band].abs().max() < rounding, k
    both = flow(torch.cat([factors[0] * u0, factors[-1] * u0]), surface)
    for entry, k in enumerate((factors[0], factors[-1])):
        assert (both[entry:entry + 1] / k - reference)[band].abs().max() < rounding, k


@pytest.mark.parametrize("make", [
    lambda method: ts.AnisotropicFlow(0.01, method=method),
    lambda method: ts.HarmonicMapFlow(0.01, method=method),
    lambda method: ts.ReactionDiffusion(1.0, method=method),
], ids=["anisotropic", "harmonic", "reaction_diffusion"])
@pytest.mark.parametrize("method", ["implicit", "crank_nicolson"])
def test_nonlinear_flows_refuse_implicit_methods_when_built(make, method):
    """They were built, and refused at the first call, inside a training loop, as an error of
    "batch entry 0"."""
    with pytest.raises(ValueError, match=rf"method='{method}'.* is not linear"):
        make(method)
    for linear in (ts.HeatFlow(0.01, method=method), ts.FlowVisualization(0.01, method=method)):
        assert linear.method == method
