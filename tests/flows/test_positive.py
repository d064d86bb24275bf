"""Positive flow parameters: what they accept, what they refuse, and that they stay > 0."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsurf as ts
from torchsurf.flows import AnisotropicFlow, HeatFlow, ReactionDiffusion
from torchsurf.flows._positive import FLOOR, Positive


@pytest.mark.parametrize("value", [True, "1", np.bool_(True), torch.tensor(True), [1.0, True],
                                   ["1", "2"], 1j])
def test_refuses_bools_and_strings_naming_the_parameter(value):
    with pytest.raises(TypeError, match=r"diffusivity.* must be a finite positive number"):
        Positive(value, "diffusivity")


@pytest.mark.parametrize("value", [0.0, -2.0, float("nan"), [], torch.ones(1, 1), [1.0, -1.0],
                                   torch.tensor([1.0, float("nan")])])
def test_refuses_values_naming_the_parameter_and_value(value):
    with pytest.raises(ValueError, match="contrast must be a finite positive number"):
        Positive(value, "contrast")


def test_a_positive_value_that_rounds_to_zero_says_so():
    with pytest.raises(ValueError, match=r"got 1e-300, which rounds to 0 in torch.float32"):
        HeatFlow(1e-300)
    with pytest.raises(ValueError, match=r"got \[0.001, 1e-60\], which rounds to 0"):
        Positive([1e-3, 1e-60], "time")
    for not_positive in (0.0, [1e-3, 0.0], -1e-300):
        with pytest.raises(ValueError) as refused:
            Positive(not_positive, "time")
        assert "rounds to 0" not in str(refused.value)


def test_a_value_that_overflows_or_is_a_vector_where_one_number_is_taken_says_so():
    """time=1e300 was called not 'finite' and a flow's time offered a vector, then refused it."""
    with pytest.raises(ValueError, match=r"time must be a single finite positive number, got "
                                         r"1e\+300, which overflows to infinity in torch.float32"):
        HeatFlow(1e300)
    with pytest.raises(ValueError, match=r"time must be a single finite positive number, got "
                                         r"\[0.1, 0.2\]$"):
        HeatFlow([0.1, 0.2])
    with pytest.raises(ValueError, match=r"time must be a positive number or 2 of them .*"
                                         r"overflows to infinity"):
        ts.nn.LearnedDiffusion(2, time=1e300)
    assert Positive([0.1, 0.2], "contrast").channels == 2


@pytest.mark.parametrize("value", [np.float32(0.5), np.int64(2), torch.tensor(0.5),
                                   torch.tensor(2)])
def test_accepts_numpy_and_0d_tensor_scalars(value):
    for learnable in (False, True):
        parameter = Positive(value, "time", learnable=learnable)
        assert float(torch.as_tensor(parameter.value()).detach()) == pytest.approx(float(value))


@pytest.mark.parametrize("raw", [-1e4, -200.0, -60.0])
def test_learnable_value_never_reaches_zero(raw):
    parameter = Positive([2.0, 3.0], "diffusivity", learnable=True)
    with torch.no_grad():
        parameter.raw.fill_(raw)
    value = parameter.value()
    assert bool((value > 0).all())
    assert bool((value >= FLOOR * 2.0).all())


def test_learnable_value_follows_softplus():
    """Not the identity: a negative raw value still gives a positive value, softplus(raw)."""
    parameter = Positive(1.0, "time", learnable=True)
    with torch.no_grad():
        parameter.raw.fill_(-3.0)
    expected = float(torch.nn.functional.softplus(torch.tensor(-3.0)))
    assert float(parameter.value().detach()) == pytest.approx(expected, rel=1e-6)


def test_diverged_learnable_value_names_the_parameter():
    parameter = Positive(1.0, "diffusivity", learnable=True)
    with torch.no_grad():
        parameter.raw.fill_(float("nan"))
    with pytest.raises(ValueError, match="diffusivity is no longer finite"):
        parameter.maximum()


def test_flows_refuse_bool_and_string_parameters():
    with pytest.raises(TypeError, match="time"):
        HeatFlow(True)
    with pytest.raises(TypeError, match="diffusivity"):
        HeatFlow(0.1, diffusivity="1")
    with pytest.raises(TypeError, match="contrast"):
        AnisotropicFlow(0.1, contrast=True)
    HeatFlow(np.float32(0.1), diffusivity=torch.tensor(2.0))


@pytest.mark.parametrize("contrast", [torch.tensor([1.0, 0.0]), torch.tensor(-1.0),
                                      torch.tensor(float("nan"))])
def test_anisotropic_flow_refuses_bad_contrast_tensors(contrast):
    with pytest.raises(ValueError, match="contrast"):
        AnisotropicFlow(0.1, contrast=contrast)


@pytest.mark.parametrize(("kwargs", "error", "name"), [
    (dict(beta="12"), TypeError, "beta"),
    (dict(beta=True), TypeError, "beta"),
    (dict(beta=float("nan")), ValueError, "beta"),
    (dict(noise="0.1"), TypeError, "noise"),
    (dict(noise=-0.1), ValueError, "noise"),
])
def test_reaction_diffusion_refuses_bad_beta_and_noise(kwargs, error, name):
    with pytest.raises(error, match=name):
        ReactionDiffusion(10.0, **kwargs)


def test_reaction_diffusion_accepts_numpy_beta():
    flow = ReactionDiffusion(10.0, beta=np.float32(12.0), noise=np.float64(0.0))
    assert flow.beta == 12.0 and flow.noise == 0.0


def test_compiled_code_sees_fixed_values_loaded_from_a_checkpoint():
    positive = Positive(torch.tensor([1.0, 2.0]), "diffusivity")
    scaled = torch.compile(lambda x: x * positive.maximum(), backend="eager")
    assert float(scaled(torch.ones(()))) == 2.0
    positive.load_state_dict({"values": torch.tensor([10.0, 3.0])})
    assert float(scaled(torch.ones(()))) == 10.0
    learned = ts.nn.LearnedDiffusion(2, time=[0.5, 1.0], learn_time=False)
    largest = torch.compile(lambda x: x * learned.largest_time(), backend="eager")
    assert float(largest(torch.ones(()))) == 1.0
    learned.load_state_dict({"fixed_time": torch.tensor([20.0, 1.0])})
    assert float(largest(torch.ones(()))) == 20.0


@pytest.mark.slow  # a minute of tracing
def test_compiled_flows_see_fixed_values_loaded_from_a_checkpoint():
    """Compiled code read the host maximum of a fixed diffusivity last read eagerly: loading
    D = 10 over D = 1 ran steps planned for 1, and the flow diverged (7e8 off, finite)."""
    grid = ts.Grid.cube(16, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    u = torch.randn(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    flow = HeatFlow(time=0.02, diffusivity=torch.tensor([1.0]))
    compiled = torch.compile(flow, backend="eager")
    compiled(u, surface)
    flow.load_state_dict({"diffusivity.values": torch.tensor([10.0])})
    fresh = HeatFlow(time=0.02, diffusivity=torch.tensor([10.0]))(u, surface)
    band = surface.band_mask()
    assert float(((compiled(u, surface) - fresh) * band).abs().max()) < 1e-5


@pytest.mark.parametrize("make", [
    lambda h2: HeatFlow(3 * h2, learn_time=True),
    lambda h2: HeatFlow(3 * h2, diffusivity=[1.0, 2.0], learn_diffusivity=True),
    lambda h2: AnisotropicFlow(3 * h2, "perona_malik", contrast=[0.5, 0.7], learn_contrast=True),
], ids=["time", "diffusivity", "contrast"])
def test_learned_parameters_must_have_the_datas_dtype_fixed_ones_follow_it(make):
    """A flow moved to float64 ran float32 data silently (its learned values cast at every
    call) while ``nn.LearnedDiffusion`` refused it: learned values are weights, as a PyTorch
    layer's; fixed tensors are settings, read in the data's dtype."""
    grid = ts.Grid.cube(12, bound=1.4)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9), grid)
    u = torch.rand(1, 2, 12, 12, 12, generator=torch.Generator().manual_seed(0))
    flow = make(grid.spacing**2).double()
    with pytest.raises(ts.MismatchError, match=r"u0 is torch.float32 .* learned \w+ is "
                                               r"torch.float64"):
        flow(u, surface)
    assert flow.float()(u, surface).dtype == torch.float32
    fixed = HeatFlow(3 * grid.spacing**2, diffusivity=torch.tensor([1.0, 2.0],
                                                                   dtype=torch.float64))
    assert fixed(u, surface).dtype == torch.float32
    module = ts.AnisotropicDiffusion("perona_malik",
                                     contrast=torch.tensor([0.5, 0.7], dtype=torch.float64))
    colour = ts.ColorDenoise(chroma=ts.HarmonicMapFlow(grid.spacing**2),
                             brightness=make(grid.spacing**2)).double()  # named as given
    with pytest.raises(ts.MismatchError, match=r"image is torch.float32 .* ColorDenoise's "
                                               r"brightness flow's learned"):
        colour(torch.rand(1, 3, 12, 12, 12), surface)
    torch.testing.assert_close(module(u, surface),
                               ts.AnisotropicDiffusion("perona_malik",
                                                       contrast=torch.tensor([0.5, 0.7]))(u, surface))


def test_a_float64_vector_setting_is_kept_unrounded():
    """A (C,) diffusivity or contrast given in float64 was stored in float32: a heat flow of
    diffusivity [1/3, 1/3] was 3e-9 off its scalar 1/3 here on float64 data, after .double()
    too."""
    grid = ts.Grid.cube(17, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    u = torch.rand(1, 2, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(0))
    time = 5 * grid.spacing**2
    for vector in (torch.tensor([1 / 3, 1 / 3], dtype=torch.float64), np.array([1 / 3, 1 / 3])):
        flow = ts.HeatFlow(time, diffusivity=vector)
        assert flow.diffusivity.values.dtype == torch.float64
        scalar = ts.HeatFlow(time, diffusivity=1 / 3)(u, surface)
        torch.testing.assert_close(flow(u, surface), scalar, rtol=0, atol=1e-14)
    assert ts.HeatFlow(time, diffusivity=[0.5, 1.0]).diffusivity.values.dtype == torch.float32
    tiny = Positive(torch.tensor([1e-50, 1.0], dtype=torch.float64), "diffusivity")
    assert float(tiny.values[0]) == 1e-50  # checked unrounded: it had "rounded to 0" in float32
