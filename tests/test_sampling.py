"""torchsurf.sample: trilinear sampling of volumes at world points."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.sampling import sample

GRID = ts.Grid(shape=(6, 7, 8), spacing=0.25, origin=(-1.0, -0.5, 0.3))


def linear_field(grid: ts.Grid, coefficients: tuple[float, float, float, float],
                 dtype: torch.dtype = torch.float64) -> torch.Tensor:
    a, b, c, d = coefficients
    points = grid.points(dtype=dtype)
    return (a * points[..., 0] + b * points[..., 1] + c * points[..., 2] + d)[None, None]


def random_points(grid: ts.Grid, count: int, batch: int | None = None,
                  dtype: torch.dtype = torch.float64) -> torch.Tensor:
    generator = torch.Generator().manual_seed(0)
    shape = (count, 3) if batch is None else (batch, count, 3)
    unit = torch.rand(shape, generator=generator, dtype=dtype)
    return unit * torch.tensor(grid.size, dtype=dtype) + torch.tensor(grid.origin, dtype=dtype)


def test_exact_for_linear_fields() -> None:
    field = linear_field(GRID, (0.7, -1.3, 2.1, 0.4))
    points = random_points(GRID, 50)
    expected = points @ torch.tensor([0.7, -1.3, 2.1], dtype=torch.float64) + 0.4
    torch.testing.assert_close(sample(field, points, GRID)[0, 0], expected, atol=1e-12, rtol=0)


def test_nodes_and_corners_are_exact() -> None:
    field = torch.randn(1, 2, *GRID.shape, dtype=torch.float64)
    corners = torch.tensor([GRID.origin, [o + s for o, s in zip(GRID.origin, GRID.size, strict=True)]],
                           dtype=torch.float64)
    values = sample(field, corners, GRID)
    torch.testing.assert_close(values[..., 0], field[:, :, 0, 0, 0])
    torch.testing.assert_close(values[..., 1], field[:, :, -1, -1, -1])


def test_shapes_and_batch_broadcast() -> None:
    field = torch.randn(3, 4, *GRID.shape)
    assert sample(field, random_points(GRID, 5, dtype=torch.float32), GRID).shape == (3, 4, 5)
    assert sample(field, random_points(GRID, 5, 3, torch.float32), GRID).shape == (3, 4, 5)
    one = field[:1]
    assert sample(one, random_points(GRID, 5, 3, torch.float32), GRID).shape == (3, 4, 5)


def test_gradient_with_respect_to_points_is_the_field_gradient() -> None:
    field = linear_field(GRID, (0.7, -1.3, 2.1, 0.4))
    points = random_points(GRID, 20).requires_grad_(True)
    sample(field, points, GRID).sum().backward()
    expected = torch.tensor([0.7, -1.3, 2.1], dtype=torch.float64).expand(20, 3)
    torch.testing.assert_close(points.grad, expected, atol=1e-10, rtol=0)


def test_gradcheck() -> None:
    grid = ts.Grid(shape=(3, 4, 3), spacing=0.5)
    field = torch.randn(1, 2, *grid.shape, dtype=torch.float64, requires_grad=True)
    points = (random_points(grid, 4) * 0.9 + 0.05).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda f, p: sample(f, p, grid), (field, points))


def test_points_outside_the_grid_raise() -> None:
    field = torch.zeros(1, 1, *GRID.shape)
    points = torch.tensor([[0.0, 0.0, 0.5], [5.0, 0.0, 0.5]])
    with pytest.raises(ValueError, match=r"points.*outside.*points\[1\]"):
        sample(field, points, GRID)


@pytest.mark.parametrize(
    ("field", "points", "error"),
    [
        (torch.zeros(1, *GRID.shape), torch.zeros(1, 3), ValueError),
        (torch.zeros(1, 1, *GRID.shape), torch.zeros(1, 2), ValueError),
        (torch.zeros(1, 1, 3, 3, 3), torch.zeros(1, 3), ValueError),
        (torch.zeros(1, 1, *GRID.shape), torch.zeros(1, 3, dtype=torch.float64), TypeError),
        (torch.zeros(2, 1, *GRID.shape), torch.zeros(3, 1, 3), ValueError),
        (torch.zeros(1, 1, *GRID.shape), torch.full((1, 3), float("nan")), ValueError),
    ],
)
def test_bad_input_raises(field: torch.Tensor, points: torch.Tensor, error: type) -> None:
    with pytest.raises(error):
        sample(field, points, GRID)
