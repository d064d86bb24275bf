"""Bad or unusual input to the public entries: refused clearly before any work, or accepted."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsurf as ts
from torchsurf._checks import check_count
from torchsurf.flows import HeatFlow


@pytest.mark.parametrize(
    "value", [True, False, np.bool_(True), torch.tensor(True), "3", None, 3 + 0j,
              torch.tensor([3, 4])],
)
def test_counts_refuse_what_is_not_a_number_with_a_type_error(value):
    with pytest.raises(TypeError, match="steps must be a whole number >= 1, got"):
        check_count(value, "steps")


@pytest.mark.parametrize("value", [2.5, float("nan"), float("inf"), 0, -3, np.int64(0),
                                   torch.tensor(2.5)])
def test_counts_refuse_fractions_and_small_values_with_a_value_error(value):
    with pytest.raises(ValueError, match="steps must be a whole number >= 1, got"):
        check_count(value, "steps")


@pytest.mark.parametrize("value", [4, 4.0, np.int64(4), np.float32(4.0), torch.tensor(4),
                                   torch.tensor(4.0)])
def test_counts_accept_every_spelling_of_a_whole_number(value):
    assert check_count(value, "steps") == 4
    assert type(check_count(value, "steps")) is int


@pytest.mark.parametrize(
    "make",
    [lambda: HeatFlow(0.01, steps=True), lambda: HeatFlow(0.01, max_iterations=False),
     lambda: HeatFlow(0.01, reextend_every=True), lambda: ts.Grid.cube(np.bool_(True), 1.0),
     lambda: ts.mesh.fit_grid(__import__("trimesh").creation.box(), resolution=True),
     lambda: ts.sdf.trefoil(ts.Grid.cube(9, 1.5), samples=True)],
)
def test_bools_given_as_counts_raise_type_errors(make):
    with pytest.raises(TypeError, match="must be a whole number"):
        make()


def _sphere17() -> tuple[ts.Grid, ts.ImplicitSurface]:
    grid = ts.Grid.cube(17, 1.5)
    return grid, ts.ImplicitSurface(ts.sdf.sphere(grid), grid)


def test_meta_tensors_are_refused_by_name_and_device():
    grid, surface = _sphere17()
    with pytest.raises(ValueError, match="phi is on the meta device"):
        ts.ImplicitSurface(ts.sdf.sphere(grid).to("meta"), grid)
    u0 = torch.zeros(1, 1, *grid.shape, device="meta")
    with pytest.raises(ValueError, match="u0 is on the meta device"):
        HeatFlow(0.01)(u0, surface)
    with pytest.raises(ValueError, match="u is on the meta device"):
        ts.operators.laplace_beltrami(u0, surface)
    with pytest.raises(ValueError, match="diffusivity is on the meta device"):
        HeatFlow(0.01, diffusivity=torch.ones(2, device="meta"))
    with pytest.raises(ValueError, match="time is on the meta device"):
        HeatFlow(torch.tensor(0.01, device="meta"))
