"""Grid: layout of nodes, coordinate conversions, grid_sample agreement, errors."""

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from torchsurf import Grid


def test_cube_spacing_origin_size():
    grid = Grid.cube(33, bound=1.5)
    assert grid.shape == (33, 33, 33)
    assert grid.spacing == 3.0 / 32
    assert grid.origin == (-1.5, -1.5, -1.5)
    assert grid.size == (3.0, 3.0, 3.0)


def test_points_shape_order_and_values():
    grid = Grid(shape=(4, 5, 6), spacing=0.25, origin=(1.0, -2.0, 0.5))
    points = grid.points(dtype=torch.float64)
    assert points.shape == (4, 5, 6, 3)
    assert points.dtype == torch.float64
    k, j, i = torch.meshgrid(
        torch.arange(4.0), torch.arange(5.0), torch.arange(6.0), indexing="ij"
    )
    expected = torch.stack((1.0 + 0.25 * i, -2.0 + 0.25 * j, 0.5 + 0.25 * k), dim=-1)
    torch.testing.assert_close(points, expected.double(), rtol=0, atol=1e-15)
    # channel 0 (x) varies along W only, channel 2 (z) along D only
    assert points[0, 0, 1, 0] - points[0, 0, 0, 0] == 0.25
    assert bool((points[..., 0] == points[:1, :1, :, 0]).all())
    assert bool((points[..., 2] == points[:, :1, :1, 2]).all())
    assert grid.size == (1.25, 1.0, 0.75)


def test_points_default_dtype():
    assert Grid.cube(3, 1.0).points().dtype == torch.get_default_dtype()


def test_round_trips(generator):
    grid = Grid(shape=(7, 9, 11), spacing=0.3, origin=(-1.0, 0.5, 2.0))
    world = torch.rand(50, 3, generator=generator, dtype=torch.float64) * 4 - 1
    index = grid.world_to_index(world)
    torch.testing.assert_close(grid.index_to_world(index), world, rtol=0, atol=1e-13)
    normalized = grid.world_to_normalized(world)
    torch.testing.assert_close(grid.normalized_to_world(normalized), world, rtol=0, atol=1e-13)
    # nodes land on integer indices (i, j, k) in (x, y, z) order
    points = grid.points(dtype=torch.float64)
    index = grid.world_to_index(points)
    k, j, i = torch.meshgrid(
        torch.arange(7.0), torch.arange(9.0), torch.arange(11.0), indexing="ij"
    )
    torch.testing.assert_close(index, torch.stack((i, j, k), -1).double(), rtol=0, atol=1e-12)


def test_normalized_corners():
    grid = Grid(shape=(5, 6, 7), spacing=0.5, origin=(1.0, 2.0, 3.0))
    first = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    last = first + 0.5 * torch.tensor([6.0, 5.0, 4.0], dtype=torch.float64)
    torch.testing.assert_close(grid.world_to_normalized(first), -torch.ones(3).double())
    torch.testing.assert_close(grid.world_to_normalized(last), torch.ones(3).double())
    torch.testing.assert_close(grid.world_to_normalized((first + last) / 2), torch.zeros(3).double())


def test_normalized_matches_grid_sample(generator):
    """Trilinear interpolation is exact for an affine field: grid_sample must return it exactly."""
    grid = Grid(shape=(6, 8, 10), spacing=0.2, origin=(-0.7, 0.3, 1.1))
    coefficients = torch.tensor([1.5, -2.0, 0.75], dtype=torch.float64)
    field = grid.points(dtype=torch.float64) @ coefficients + 0.25
    lower = torch.tensor(grid.origin, dtype=torch.float64)
    upper = lower + torch.tensor(grid.size, dtype=torch.float64)
    world = lower + (upper - lower) * torch.rand(200, 3, generator=generator, dtype=torch.float64)
    normalized = grid.world_to_normalized(world)
    sampled = F.grid_sample(
        field[None, None], normalized[None, None, None], mode="bilinear", align_corners=True
    ).flatten()
    torch.testing.assert_close(sampled, world @ coefficients + 0.25, rtol=0, atol=1e-12)


def test_contains():
    grid = Grid(shape=(3, 4, 5), spacing=1.0, origin=(0.0, 0.0, 0.0))
    points = torch.tensor(
        [
            [0.0, 0.0, 0.0],
            [4.0, 3.0, 2.0],
            [2.5, 1.5, 0.5],
            [4.01, 1.0, 1.0],
            [1.0, -0.01, 1.0],
            [1.0, 1.0, 2.01],
            [1.0, 3.01, 1.0],
        ]
    )
    assert grid.contains(points).tolist() == [True, True, True, False, False, False, False]
    assert grid.contains(points.reshape(7, 1, 3)).shape == (7, 1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "grid",
    [Grid.cube(7, 1.1), Grid((3, 3, 3), 0.1, (0.1, 0.1, 0.1)), Grid((5, 6, 7), 0.3, (0.7, 0.2, 1.1))],
    ids=["cube", "offset-0.1", "offset-mixed"],
)
def test_contains_every_node(grid, dtype):
    """Each node of the grid lies in its own box, whatever the rounding of origin + h * i."""
    assert bool(grid.contains(grid.points(dtype=dtype)).all())


@pytest.mark.parametrize(
    ("kwargs", "error", "name"),
    [
        (dict(shape=(3, 3), spacing=1.0), ValueError, "shape"),
        (dict(shape=(3, 2, 3), spacing=1.0), ValueError, "shape"),
        (dict(shape=(3, 3, 3), spacing=0.0), ValueError, "spacing"),
        (dict(shape=(3, 3, 3), spacing=-1.0), ValueError, "spacing"),
        (dict(shape=(3, 3, 3), spacing=float("nan")), ValueError, "spacing"),
        (dict(shape=(3, 3, 3), spacing=float("inf")), ValueError, "spacing"),
        (dict(shape=(3, 3, 3), spacing=1.0, origin=(0.0, 0.0)), ValueError, "origin"),
    ],
)
def test_invalid_grid(kwargs, error, name):
    with pytest.raises(error, match=name):
        Grid(**kwargs)


def test_invalid_cube():
    with pytest.raises(ValueError, match="bound"):
        Grid.cube(5, bound=-1.0)
    with pytest.raises(ValueError):
        Grid.cube(2, bound=1.0)


@pytest.mark.parametrize(
    ("method", "name"),
    [
        ("world_to_index", "points"),
        ("index_to_world", "index"),
        ("world_to_normalized", "points"),
        ("normalized_to_world", "normalized"),
        ("contains", "points"),
    ],
)
def test_conversion_rejects_non_tensor(method, name):
    grid = Grid.cube(5, 1.0)
    with pytest.raises(TypeError, match=name):
        getattr(grid, method)([0.0, 0.0, 0.0])


@pytest.mark.parametrize("method", ["world_to_index", "world_to_normalized", "contains"])
@pytest.mark.parametrize("last", [1, 4])
def test_conversion_rejects_wrong_last_dimension(method, last):
    """``(..., 3)`` is required; a trailing 1 must not broadcast silently into 3 coordinates."""
    grid = Grid.cube(5, 1.0)
    with pytest.raises(ValueError, match="points"):
        getattr(grid, method)(torch.zeros(4, last))


def test_numpy_and_0d_tensor_numbers_are_accepted():
    grid = Grid(shape=(5, np.int64(6), 7), spacing=np.float32(0.1), origin=np.zeros(3))
    assert grid.shape == (5, 6, 7) and grid.spacing == pytest.approx(0.1)
    assert all(type(n) is int for n in grid.shape) and all(type(x) is float for x in grid.origin)
    assert Grid.cube(np.int64(17), np.float64(1.5)).shape == (17, 17, 17)
    assert Grid.cube(torch.tensor(5), torch.tensor(1.0)) == Grid.cube(5, 1.0)


@pytest.mark.parametrize(
    ("make", "error", "name"),
    [
        (lambda: Grid((5, 5, 5), True), TypeError, "spacing"),
        (lambda: Grid((5, 5, 5), "0.1"), TypeError, "spacing"),
        (lambda: Grid((5, True, 5), 1.0), TypeError, "shape"),
        (lambda: Grid(5, 1.0), ValueError, "shape"),
        (lambda: Grid.cube(True, 1.0), TypeError, "n must be"),
        (lambda: Grid.cube(17.5, 1.0), ValueError, "n must be"),
        (lambda: Grid.cube(5, True), TypeError, "bound"),
        (lambda: Grid((5, 5, 5), 1.0, (0.0, float("nan"), 0.0)), ValueError, "origin"),
        (lambda: Grid((5, 5, 5), 1.0, (0.0, float("inf"), 0.0)), ValueError, "origin"),
        (lambda: Grid((5, 5, 5), 1.0, (0.0, "a", 0.0)), TypeError, "origin"),
    ],
)
def test_bools_strings_and_non_finite_origin_refused(make, error, name):
    with pytest.raises(error, match=name):
        make()


@pytest.mark.parametrize("dtype", [torch.int64, torch.bool, torch.float16])
def test_points_refuse_unsupported_dtypes(dtype):
    with pytest.raises(TypeError, match="dtype must be"):
        Grid.cube(5, 1.0).points(dtype=dtype)


@pytest.mark.parametrize(("shape", "spacing", "origin"), [
    ((7, 9, 11), 0.13, (1000.5, -2000.25, 3.0)),
    ((17, 17, 17), 0.01, (100.003, 0.0, 0.0)),
])
def test_every_node_is_contained_in_float32_far_from_the_origin(shape, spacing, origin):
    """The slack was a few rounding errors of the index range; the index of a world point is
    rounded at the point's own scale (4e-4 cells 1000 away in float32): 616 of 693 nodes
    were outside."""
    grid = Grid(shape, spacing, origin)
    for dtype in (torch.float32, torch.float64):
        assert bool(grid.contains(grid.points(dtype=dtype)).all())


def test_contains_index_checks_its_arguments():
    grid = Grid((5, 5, 5), 0.5)
    with pytest.raises(TypeError, match="index must be a torch.Tensor"):
        grid.contains_index(np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"index must have shape \(\.\.\., 3\)"):
        grid.contains_index(torch.zeros(2, 2))
    for tolerance, error in ((float("nan"), ValueError), (float("inf"), ValueError),
                             (True, TypeError)):  # a bool is a type's error, as elsewhere
        with pytest.raises(error, match="tolerance must be a finite number"):
            grid.contains_index(torch.zeros(2, 3), tolerance)
        with pytest.raises(error, match="tolerance must be a finite number"):
            grid.contains(torch.zeros(2, 3), tolerance)


def test_contains_takes_numpy_and_0d_tensor_tolerances_and_names_others():
    grid = Grid.cube(5, bound=1.0)
    point = torch.tensor([[1.2, 0.0, 0.0]])  # 0.4 cells outside
    for tolerance in (np.float32(0.5), torch.tensor(0.5), 0.5):
        assert bool(grid.contains(point, tolerance=tolerance))
    with pytest.raises(TypeError, match="tolerance must be a finite number of cells"):
        grid.contains(point, tolerance="0.5")
    with pytest.raises(ValueError, match="tolerance must be a finite number of cells"):
        grid.contains(point, tolerance=float("inf"))


def test_world_rounding_is_the_float32_rounding_far_from_the_origin_not_ten_times_it():
    """8 units of rounding at the farthest coordinate: 9.5 cells at 1e5 and spacing 0.01, where
    float32 places a point to 0.39 cells, so points 9 cells outside were taken as inside."""
    grid = Grid((17, 17, 17), 0.01, (1e5, 1e5, 1e5))
    assert 0.39 < grid.world_rounding(torch.float32) < 2.5
    outside = torch.tensor([[1e5 + 0.16 + 0.05, 1e5 + 0.08, 1e5 + 0.08]], dtype=torch.float32)
    assert not bool(grid.contains(outside))
