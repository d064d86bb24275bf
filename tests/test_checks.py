"""torchsurf._checks: the shared validation of numbers, dtypes and volumes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsurf as ts
from torchsurf._checks import (
    check_dtype,
    check_flag,
    check_nonnegative,
    check_positive,
    check_positive_tensor,
    check_real,
    check_tensor,
    check_volume,
)


@pytest.mark.parametrize(
    "value", [0.5, 2, np.float32(0.5), np.float64(0.5), np.int64(2), torch.tensor(0.5),
              torch.tensor(2, dtype=torch.int64)],
)
def test_positive_accepts_python_numpy_and_0d_tensor_numbers(value):
    result = check_positive(value, "time")
    assert type(result) is float and result == float(value)


@pytest.mark.parametrize(
    "value", [True, False, np.bool_(True), "1", None, 1 + 0j, torch.tensor([1.0, 2.0]),
              torch.tensor(True)],
)
def test_positive_refuses_what_is_not_a_real_number_naming_it(value):
    with pytest.raises(TypeError, match="time must be a finite positive number"):
        check_positive(value, "time")


@pytest.mark.parametrize("value", [0.0, -1, float("nan"), float("inf"), np.float32("nan")])
def test_positive_refuses_values_naming_them(value):
    with pytest.raises(ValueError, match=r"spacing must be a finite positive number, got"):
        check_positive(value, "spacing")


def test_real_and_nonnegative():
    assert check_real(np.float32(-2.0), "beta") == -2.0
    assert check_nonnegative(0, "noise") == 0.0
    with pytest.raises(TypeError, match="beta"):
        check_real("12", "beta")
    with pytest.raises(ValueError, match="beta must be a finite"):
        check_real(float("nan"), "beta")
    with pytest.raises(ValueError, match="noise must be a finite number >= 0"):
        check_nonnegative(-0.1, "noise")


@pytest.mark.parametrize("value", [torch.tensor([1.0, 0.0]), torch.tensor(-1.0),
                                   torch.tensor([1.0, float("nan")]), torch.tensor(float("inf"))])
def test_positive_tensor_refuses_zero_negative_and_non_finite(value):
    with pytest.raises(ValueError, match="contrast must hold finite positive values"):
        check_positive_tensor(value, "contrast")


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.float16, torch.bfloat16,
                                   torch.complex64, "float32"])
def test_dtype_refuses_all_but_float32_and_float64(dtype):
    with pytest.raises(TypeError, match=r"dtype must be .*torch\.float32 or torch\.float64"):
        check_dtype(dtype)


def test_dtype_default():
    assert check_dtype(None) == torch.get_default_dtype()
    assert check_dtype(torch.float64) == torch.float64


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_tensors_are_refused_naming_the_argument(dtype):
    with pytest.raises(TypeError, match=r"u must be a floating-point tensor .*float32 or "
                                        rf"torch.float64.*got dtype {dtype}"):
        check_tensor(torch.zeros(2, dtype=dtype), "u")


@pytest.mark.parametrize("shape", [(1, 0, 5, 5, 5), (0, 1, 5, 5, 5)])
def test_empty_volume_refused(shape):
    with pytest.raises(ValueError, match=r"u must hold at least one volume and one channel"):
        check_volume(torch.zeros(shape), "u")


def test_flags_take_booleans_only() -> None:
    assert check_flag(True, "coupled") is True
    assert check_flag(np.bool_(False), "coupled") is False
    assert check_flag(torch.tensor(True), "coupled") is True
    for value in ("False", 0, 1.0, None, torch.tensor([True])):
        with pytest.raises(TypeError, match="coupled must be True or False"):
            check_flag(value, "coupled")


def test_a_string_flag_is_not_read_by_its_truth() -> None:
    # bool("False") is True: coupled="False" used to mean coupled=True
    grid = ts.Grid.cube(9, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    u = torch.rand(1, 2, *grid.shape)
    with pytest.raises(TypeError, match="coupled"):
        ts.anisotropic_diffusion(u, surface, "perona_malik", contrast=0.5, coupled="False")
    with pytest.raises(TypeError, match="coupled"):
        ts.AnisotropicDiffusion("perona_malik", contrast=0.5, coupled="False")
    with pytest.raises(TypeError, match="adjoint"):
        ts.HeatFlow(0.1, adjoint="no")
    with pytest.raises(TypeError, match="tangent must be True or False, got 'False'"):
        ts.HarmonicMapFlow(0.1, tangent="False")  # had been read as tangent=True
