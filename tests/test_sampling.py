"""torchsurf.sample: trilinear sampling of volumes at world points."""

from __future__ import annotations

import math

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


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_points_on_the_faces_and_corners_keep_the_field_gradient(interpolation) -> None:
    # a point on a face is in the cell inside it: moving it inward changes the value at the
    # field's rate (linear reads through a clamping sampler had 0 across the face)
    field = linear_field(GRID, (0.7, -1.3, 2.1, 0.4))
    low = torch.tensor(GRID.origin, dtype=torch.float64)
    high = low + torch.tensor(GRID.size, dtype=torch.float64)
    inside = (low + high) / 2
    points = torch.stack([low, high, torch.stack([low[0], inside[1], inside[2]]),
                          torch.stack([inside[0], high[1], inside[2]]),
                          torch.stack([inside[0], inside[1], low[2]])]).requires_grad_(True)
    sample(field, points, GRID, interpolation).sum().backward()
    expected = torch.tensor([0.7, -1.3, 2.1], dtype=torch.float64).expand(len(points), 3)
    torch.testing.assert_close(points.grad, expected, atol=1e-10, rtol=0)
    corner = high[None].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: sample(field, p, GRID, interpolation), (corner,))


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


def cubic_field(grid: ts.Grid, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, object]:
    """A polynomial of degree 3 in each coordinate, on ``grid`` and as a function of points."""

    def value(points: torch.Tensor) -> torch.Tensor:
        x, y, z = points.unbind(-1)
        return 0.3 * x**3 * y - 1.1 * (y**2) * (z**3) + 0.7 * x * y * z + 2 * z**2 - 0.5

    return value(grid.points(dtype=dtype))[None, None], value


def test_cubic_exact_for_polynomials_of_degree_three_per_axis() -> None:
    field, value = cubic_field(GRID)
    points = random_points(GRID, 200)
    in_face_cells = ~GRID.contains(points, tolerance=-1.0)  # in the first or last cell
    assert int(in_face_cells.sum()) > 50
    result = sample(field, points, GRID, interpolation="cubic")[0, 0]
    # up to the faces: one-sided stencils there (repeating the face's node was first order)
    torch.testing.assert_close(result, value(points), atol=1e-12, rtol=0)
    assert not torch.allclose(sample(field, points, GRID)[0, 0], value(points), atol=1e-6)


def test_cubic_along_an_axis_of_three_nodes_is_exact_for_linear_fields() -> None:
    """Cubic along the long axes, linear along the short one (it gave 1.544 for 1.6)."""
    grid = ts.Grid(shape=(3, 9, 7), spacing=0.25, origin=(0.1, -0.4, 0.3))
    points = grid.points(dtype=torch.float64)
    x, y, z = points.unbind(-1)
    field = (2 * z + 1 + (y**3 - x**2) * 0.5)[None, None]
    inside = random_points(grid, 60)
    px, py, pz = inside.unbind(-1)
    expected = 2 * pz + 1 + (py**3 - px**2) * 0.5
    result = sample(field, inside, grid, interpolation="cubic")[0, 0]
    torch.testing.assert_close(result, expected, atol=1e-12, rtol=0)


def test_cubic_nodes_and_faces_are_exact() -> None:
    field = torch.randn(2, 3, *GRID.shape, dtype=torch.float64)
    nodes = GRID.points(dtype=torch.float64).reshape(-1, 3)
    values = sample(field, nodes, GRID, interpolation="cubic")
    torch.testing.assert_close(values, field.flatten(2), atol=1e-12, rtol=0)
    # a point on the box's last face in x, between nodes in y and z: the face's values,
    # interpolated cubically along it
    point = torch.tensor([[GRID.origin[0] + GRID.size[0], 0.1, 0.9]], dtype=torch.float64)
    face = sample(field, point, GRID, interpolation="cubic")
    index = GRID.world_to_index(point)[0]
    assert float(index[0]) == GRID.shape[2] - 1
    torch.testing.assert_close(face[..., 0], _cubic_on_face(field, index), atol=1e-12, rtol=0)


def _cubic_on_face(field: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """The 2-D Lagrange interpolant in ``y, z`` on the last ``x`` plane, written out."""
    from torchsurf.sampling import cubic_lagrange_weights

    result = 0
    (j0, tj), (k0, tk) = [(int(index[a].floor()), index[a] - index[a].floor()) for a in (1, 2)]
    wy, wz = cubic_lagrange_weights(tj), cubic_lagrange_weights(tk)
    for b in range(4):
        for a in range(4):
            j = min(max(j0 - 1 + a, 0), field.shape[-2] - 1)
            k = min(max(k0 - 1 + b, 0), field.shape[-3] - 1)
            result = result + wy[a] * wz[b] * field[:, :, k, j, -1]
    return result


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_order_of_accuracy_on_a_smooth_field(interpolation) -> None:
    """Error at 400 random points of ``sin(x) cos(2y) exp(z/2)`` in the inner 80% of the box
    (beside a face the repeated border node is first order): order 2 and 4."""
    errors = []
    for n in (17, 33):
        grid = ts.Grid.cube(n, 1.0)
        points = grid.points(dtype=torch.float64)
        x, y, z = points.unbind(-1)
        field = (torch.sin(x) * torch.cos(2 * y) * torch.exp(z / 2))[None, None]
        probe = random_points(grid, 400) * 0.8
        px, py, pz = probe.unbind(-1)
        exact = torch.sin(px) * torch.cos(2 * py) * torch.exp(pz / 2)
        errors.append(float((sample(field, probe, grid, interpolation)[0, 0] - exact).abs().max()))
    order = math.log2(errors[0] / errors[1])
    expected = {"linear": 2.0, "cubic": 4.0}[interpolation]
    assert abs(order - expected) < 0.4, (errors, order)


def test_cubic_batches_like_linear_and_broadcasts() -> None:
    field = torch.randn(3, 2, *GRID.shape, dtype=torch.float64)
    points = random_points(GRID, 10, batch=3)
    together = sample(field, points, GRID, interpolation="cubic")
    assert together.shape == (3, 2, 10)
    for b in range(3):
        alone = sample(field[b:b + 1], points[b], GRID, interpolation="cubic")
        torch.testing.assert_close(together[b:b + 1], alone, atol=0, rtol=0)
    shared = sample(field, points[0], GRID, interpolation="cubic")
    torch.testing.assert_close(shared[1], sample(field[1:2], points[0], GRID, "cubic")[0])


def test_cubic_gradcheck() -> None:
    grid = ts.Grid(shape=(4, 5, 6), spacing=0.5, origin=(0.0, 0.0, 0.0))
    field = torch.randn(1, 2, *grid.shape, dtype=torch.float64, requires_grad=True)
    points = (random_points(grid, 5) * 0.8 + 0.1).requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda f, p: sample(f, p, grid, interpolation="cubic"), (field, points))


def test_cubic_chunks_agree(monkeypatch) -> None:
    field = torch.randn(1, 1, *GRID.shape, dtype=torch.float64)
    points = random_points(GRID, 37)
    whole = sample(field, points, GRID, interpolation="cubic")
    monkeypatch.setattr(ts.sampling, "SAMPLE_CHUNK", 8)
    torch.testing.assert_close(sample(field, points, GRID, interpolation="cubic"), whole,
                               atol=0, rtol=0)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
@pytest.mark.parametrize("marker", [math.nan, math.inf])
def test_values_no_point_reads_stay_out_of_its_value(interpolation, marker) -> None:
    """A point on a node or a cell's face gives taps beyond it weight 0; NaN or inf marked
    there (beyond a band) made its value NaN, 0 * NaN: 382 of a torus's 2104 vertices read
    cubically."""
    grid = ts.Grid.cube(13, 1.3)  # spacing 0.108333: indices of nodes off by rounding
    field = linear_field(grid, (0.7, -0.4, 1.3, 0.2))
    lines = torch.zeros(grid.shape, dtype=torch.bool)
    lines[4, 5, :] = lines[7, 3, :] = True  # two rows of nodes along x
    marked = torch.where(lines, field, marker)
    x = grid.origin[0] + grid.spacing * torch.tensor([0.0, 2.0, 3.25, 6.5, 11.9, 12.0],
                                                     dtype=torch.float64)
    points = torch.cat([
        torch.stack([x, torch.full_like(x, grid.origin[1] + j * grid.spacing),
                     torch.full_like(x, grid.origin[2] + k * grid.spacing)], 1)
        for k, j in ((4, 5), (7, 3))])  # on the rows
    expected = sample(field, points, grid, interpolation)
    assert torch.allclose(sample(marked, points, grid, interpolation), expected, atol=1e-14)
    inside = points.clone().requires_grad_()  # finite fields keep their gradients exactly
    sample(field, inside, grid, interpolation).sum().backward()
    assert torch.allclose(inside.grad, torch.tensor([0.7, -0.4, 1.3], dtype=torch.float64)
                          .expand_as(inside), atol=1e-12)
    # across the rows the derivative needs the marked values: unknown (NaN), not a finite
    # number (the NaN taken as 0 gave -4.33 for 2, a review's)
    inside.grad = None
    sample(marked, inside, grid, interpolation).sum().backward()
    assert not bool(inside.grad.isfinite().any())
    off_the_lines = points + torch.tensor([0.0, 0.3 * grid.spacing, 0.0], dtype=torch.float64)
    assert not bool(sample(marked, off_the_lines, grid, interpolation).isfinite().any())


def test_unknown_interpolation_is_refused() -> None:
    with pytest.raises(ValueError, match="interpolation"):
        sample(torch.zeros(1, 1, *GRID.shape), torch.zeros(1, 3), GRID, interpolation="spline")


def test_a_packed_field_is_pointed_to_its_surface_s_sampler() -> None:
    with pytest.raises(ValueError, match=r"packed field of bricks\? sample it with its BrickSurface"):
        sample(torch.zeros(5, 1, 8, 8, 8), torch.zeros(1, 3), GRID)


def test_torch_func_transforms_go_through_the_samplers() -> None:
    """``torch.func.jvp`` and ``jacrev`` of the cubic sampler worked, then failed through its
    unread-tap product (an autograd.Function without ``setup_context``; a review's)."""
    grid = ts.Grid.cube(9, 1.0)
    field = linear_field(grid, (2.0, 3.0, -1.0, 1.0))
    marked = field.clone()
    marked[..., 6:] = math.nan  # beyond x = 0.5
    point = torch.tensor([[0.25, 0.0, 0.0]], dtype=torch.float64)
    for volume, finite in ((field, True), (marked, False)):
        def read(q: torch.Tensor, volume: torch.Tensor = volume) -> torch.Tensor:
            return sample(volume, q, grid, "cubic")

        assert float(read(point)) == pytest.approx(1.5)
        _, along_x = torch.func.jvp(read, (point,), (torch.tensor([[1.0, 0.0, 0.0]]).double(),))
        jacobian = torch.func.jacrev(read)(point).flatten()
        if finite:
            assert float(along_x) == pytest.approx(2.0)
            assert torch.allclose(jacobian, torch.tensor([2.0, 3.0, -1.0]).double())
        else:  # the derivative needs the marked values: unknown
            assert not bool(jacobian.isfinite().any())
