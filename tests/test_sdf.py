"""Analytic signed distance functions: exact values, unit gradient, shapes and errors."""

import math

import pytest
import torch

import torchsurf as ts
from torchsurf import Grid, sdf

# nodes at -1, -0.75, ..., 1 along every axis: every test point below is a node
GRID = Grid.cube(9, bound=1.0)


def value_at(phi, point):
    """``phi`` at the node of ``GRID`` sitting at world ``point`` ``(x, y, z)``."""
    i, j, k = (round((c + 1.0) / GRID.spacing) for c in point)
    return float(phi[0, 0, k, j, i])


@pytest.mark.parametrize(
    ("point", "expected"),
    [
        ((0.0, 0.0, 0.0), -0.5),
        ((0.25, 0.0, 0.0), -0.25),
        ((0.0, -0.5, 0.0), 0.0),
        ((1.0, 1.0, 1.0), math.sqrt(3.0) - 0.5),
        ((0.5, 0.0, -0.75), math.sqrt(0.25 + 0.5625) - 0.5),
    ],
)
def test_sphere_values(point, expected):
    phi = sdf.sphere(GRID, radius=0.5, dtype=torch.float64)
    assert value_at(phi, point) == pytest.approx(expected, abs=1e-14)


def test_sphere_center():
    phi = sdf.sphere(GRID, radius=0.25, center=(0.5, -0.25, 0.0), dtype=torch.float64)
    assert value_at(phi, (0.5, -0.25, 0.0)) == pytest.approx(-0.25, abs=1e-14)
    assert value_at(phi, (0.5, 0.5, 0.0)) == pytest.approx(0.5, abs=1e-14)
    assert value_at(phi, (0.0, -0.25, 0.0)) == pytest.approx(0.25, abs=1e-14)


@pytest.mark.parametrize(
    ("point", "expected"),
    [
        ((0.75, 0.0, 0.0), -0.25),  # on the core circle
        ((0.0, -0.75, 0.0), -0.25),
        ((0.0, 0.0, 0.0), 0.5),  # centre of the hole
        ((0.0, 1.0, 0.0), 0.0),  # outer equator
        ((0.0, 0.5, 0.0), 0.0),  # inner equator
        ((-0.75, 0.0, 0.25), 0.0),  # top of the tube
        ((0.0, 0.0, 1.0), math.sqrt(0.75**2 + 1.0) - 0.25),
        ((0.5, 0.5, 0.5), math.sqrt((math.sqrt(0.5) - 0.75) ** 2 + 0.25) - 0.25),
    ],
)
def test_torus_values(point, expected):
    phi = sdf.torus(GRID, major_radius=0.75, minor_radius=0.25, dtype=torch.float64)
    assert value_at(phi, point) == pytest.approx(expected, abs=1e-14)


def test_torus_center():
    phi = sdf.torus(GRID, 0.5, 0.25, center=(0.25, 0.0, -0.25), dtype=torch.float64)
    assert value_at(phi, (0.75, 0.0, -0.25)) == pytest.approx(-0.25, abs=1e-14)
    assert value_at(phi, (0.25, 0.0, -0.25)) == pytest.approx(0.25, abs=1e-14)
    assert value_at(phi, (0.25, 0.5, 0.25)) == pytest.approx(0.25, abs=1e-14)


@pytest.mark.parametrize(
    ("point", "expected"),
    [
        ((0.0, 0.0, 0.0), -0.25),  # nearest face is z
        ((0.25, 0.0, 0.0), -0.25),
        ((0.0, 0.5, 0.0), -0.25),  # x and y faces at 0.5 and 0.25 from here
        ((0.0, 0.0, 0.25), 0.0),  # on the z face
        ((1.0, 0.0, 0.0), 0.5),  # outside, facing x
        ((1.0, 1.0, 0.5), math.sqrt(0.25 + 0.0625 + 0.0625)),  # outside, near a corner
        ((-0.75, -1.0, 0.0), math.sqrt(0.0625 + 0.0625)),  # outside, near an edge
    ],
)
def test_box_values(point, expected):
    phi = sdf.box(GRID, half_size=(0.5, 0.75, 0.25), dtype=torch.float64)
    assert value_at(phi, point) == pytest.approx(expected, abs=1e-14)


@pytest.mark.parametrize(
    ("point", "expected"),
    [
        ((0.0, 0.0, 0.0), -0.25),
        ((0.0, 0.0, 0.5), -0.25),  # end point of the segment
        ((0.5, 0.0, 0.25), 0.25),  # beside the segment
        ((0.0, 0.0, 1.0), 0.25),  # beyond the end, on the axis
        ((0.5, 0.0, 1.0), math.sqrt(0.5) - 0.25),  # beyond the end, off axis
        ((0.0, -0.75, -0.75), math.sqrt(0.5625 + 0.0625) - 0.25),
    ],
)
def test_capsule_values(point, expected):
    phi = sdf.capsule(GRID, start=(0.0, 0.0, -0.5), end=(0.0, 0.0, 0.5), radius=0.25,
                      dtype=torch.float64)
    assert value_at(phi, point) == pytest.approx(expected, abs=1e-14)


def test_capsule_oblique():
    phi = sdf.capsule(GRID, start=(-0.5, -0.5, 0.0), end=(0.5, 0.5, 0.0), radius=0.25,
                      dtype=torch.float64)
    assert value_at(phi, (0.0, 0.0, 0.0)) == pytest.approx(-0.25, abs=1e-14)
    assert value_at(phi, (0.5, -0.5, 0.0)) == pytest.approx(math.sqrt(0.5) - 0.25, abs=1e-14)
    assert value_at(phi, (1.0, 1.0, 0.0)) == pytest.approx(math.sqrt(0.5) - 0.25, abs=1e-14)


# A grid whose nodes avoid the kinks below, and a tiny step for central differences of the
# continuous function (sampling on grids whose origin is shifted by +-delta).
UNIT_GRID = Grid(shape=(19, 19, 19), spacing=0.13, origin=(-1.21, -1.19, -1.17))
DELTA = 1e-6


def _numerical_gradient_norm(make):
    components = []
    for axis in range(3):
        shift = [0.0, 0.0, 0.0]
        shift[axis] = DELTA
        plus = Grid(UNIT_GRID.shape, UNIT_GRID.spacing,
                    tuple(o + s for o, s in zip(UNIT_GRID.origin, shift, strict=True)))
        minus = Grid(UNIT_GRID.shape, UNIT_GRID.spacing,
                     tuple(o - s for o, s in zip(UNIT_GRID.origin, shift, strict=True)))
        components.append((make(plus) - make(minus)) / (2 * DELTA))
    return torch.stack(components).square().sum(0).sqrt()[0, 0]


def _box_kinks(p):
    """Inside: where two faces are equally near, and the mid-planes where the nearest face flips."""
    excess = p.abs() - torch.tensor([0.5, 0.7, 0.3], dtype=p.dtype)
    ordered, nearest = excess.sort(dim=-1)
    inside = ordered[..., 2] < 0
    tie = ordered[..., 2] - ordered[..., 1] < 0.02
    mid_plane = p.gather(-1, nearest[..., 2:]).squeeze(-1).abs() < 0.02
    return inside & (tie | mid_plane)


def _capsule_axis(p):
    t = p[..., 2].clamp(-0.5, 0.5)
    return (p - torch.stack((torch.zeros_like(t),) * 2 + (t,), -1)).norm(dim=-1) < 0.05


@pytest.mark.parametrize(
    ("make", "kink"),
    [
        (lambda g: sdf.sphere(g, 0.8, center=(0.1, 0.0, -0.1), dtype=torch.float64),
         lambda p: (p - torch.tensor([0.1, 0.0, -0.1], dtype=p.dtype)).norm(dim=-1) < 0.05),
        (lambda g: sdf.torus(g, 0.8, 0.3, dtype=torch.float64),
         lambda p: (p[..., :2].norm(dim=-1) < 0.05)
         | ((p[..., :2].norm(dim=-1) - 0.8).hypot(p[..., 2]) < 0.05)),
        (lambda g: sdf.box(g, half_size=(0.5, 0.7, 0.3), dtype=torch.float64), _box_kinks),
        (lambda g: sdf.capsule(g, (0.0, 0.0, -0.5), (0.0, 0.0, 0.5), 0.3, dtype=torch.float64),
         _capsule_axis),
    ],
    ids=["sphere", "torus", "box", "capsule"],
)
def test_unit_gradient(make, kink):
    """``|grad phi| = 1`` everywhere except on the medial axis (and the capsule's segment)."""
    norm = _numerical_gradient_norm(make)
    smooth = ~kink(UNIT_GRID.points(dtype=torch.float64))
    assert smooth.sum() > 0.9 * smooth.numel()
    torch.testing.assert_close(norm[smooth], torch.ones_like(norm[smooth]), rtol=0, atol=1e-7)


@pytest.mark.parametrize("make", [sdf.sphere, sdf.torus, sdf.box, sdf.capsule])
def test_shape_dtype_and_sign(make):
    grid = Grid((5, 6, 7), spacing=0.4, origin=(-1.2, -1.0, -0.8))
    phi = make(grid)
    assert phi.shape == (1, 1, 5, 6, 7)
    assert phi.dtype == torch.get_default_dtype()
    assert make(grid, dtype=torch.float64).dtype == torch.float64
    assert phi.min() < 0 < phi.max()


def test_from_function():
    grid = Grid((3, 4, 5), spacing=0.5)
    phi = sdf.from_function(grid, lambda p: p[..., 0] + 2 * p[..., 1] - p[..., 2],
                            dtype=torch.float64)
    assert phi.shape == (1, 1, 3, 4, 5)
    assert phi.dtype == torch.float64
    assert float(phi[0, 0, 2, 3, 4]) == 2.0 + 3.0 - 1.0


@pytest.mark.parametrize(
    "function",
    [
        lambda p: p,  # (D, H, W, 3)
        lambda p: p[..., :1],  # (D, H, W, 1)
        lambda p: p[..., 0][None],  # (1, D, H, W)
        lambda p: p[..., 0].flatten(),
        lambda p: p[..., 0].numpy(),
    ],
)
def test_from_function_rejects_wrong_shape(function):
    with pytest.raises(ValueError, match="function"):
        sdf.from_function(Grid((3, 4, 5), spacing=0.5), function)


def test_from_function_names_a_function_that_is_none_or_gives_nan():
    """A number raised "'float' object is not callable", and NaN values came back as phi."""
    grid = Grid((3, 4, 5), spacing=0.5)
    with pytest.raises(TypeError, match="function must map world points .* got float"):
        sdf.from_function(grid, 3.0)
    with pytest.raises(ValueError, match="function returned NaN or infinity at 60 of 60 nodes"):
        sdf.from_function(grid, lambda p: p[..., 0] * float("nan"))
    with pytest.raises(ValueError, match="function returned NaN or infinity at 48 of 60"):
        sdf.from_function(grid, lambda p: p[..., 0].double() * 1e300)  # beyond float32 once cast
    with pytest.raises(ValueError, match="the distance is NaN or infinite .* beyond its range"):
        sdf.sphere(Grid.cube(5, bound=1e25), radius=1e24)


def test_an_analytic_shape_keeps_its_parameters_as_given():
    """The parameters were copied shallowly: a centre list or a radius tensor changed in place
    afterwards moved the checked shape (phi by 0.6), or turned its bounds inside out."""
    from torchsurf.shape_batch import AnalyticShape

    centre, radius = [0.1, 0.0, 0.0], torch.tensor(0.5)
    shape = AnalyticShape("sphere", {"center": centre, "radius": radius})
    grid = Grid.cube(9, 1.0)
    before, bounds = shape.phi(grid), shape.bounds()
    centre[0] = 0.4
    radius.fill_(-2.0)
    assert torch.equal(shape.phi(grid), before)
    assert all((a == b).all() for a, b in zip(shape.bounds(), bounds, strict=True))
    learned = torch.tensor(0.7, requires_grad=True)  # the copy stays in its graph
    AnalyticShape("sphere", {"radius": learned}).phi(grid).sum().backward()
    assert learned.grad is not None and float(learned.grad) == -grid.shape[0] ** 3
    AnalyticShape("sphere", {"radius": learned * 1.0})  # not a leaf: was refused by deepcopy


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda g: sdf.sphere(g, radius=0.0), "radius"),
        (lambda g: sdf.sphere(g, radius=-1.0), "radius"),
        (lambda g: sdf.sphere(g, center=(0.0, 0.0)), "center"),
        (lambda g: sdf.torus(g, major_radius=-1.0), "major_radius"),
        (lambda g: sdf.torus(g, minor_radius=0.0), "minor_radius"),
        (lambda g: sdf.box(g, half_size=(0.5, 0.5)), "half_size"),
        (lambda g: sdf.box(g, half_size=(0.5, -0.5, 0.5)), "half_size"),
        (lambda g: sdf.capsule(g, radius=0.0), "radius"),
        (lambda g: sdf.capsule(g, start=(0.0, 0.0)), "start"),
        (lambda g: sdf.capsule(g, start=(0.1, 0.2, 0.3), end=(0.1, 0.2, 0.3)), "start"),
    ],
)
def test_invalid_arguments(call, name):
    with pytest.raises(ValueError, match=name):
        call(Grid.cube(5, 1.0))


def test_trefoil_is_the_exact_distance_to_the_smooth_knot():
    grid = Grid.cube(33, bound=1.6)
    phi = sdf.trefoil(grid, tube_radius=0.15, scale=0.45, dtype=torch.float64)
    points = grid.points(dtype=torch.float64).reshape(-1, 3)
    chosen = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(0))[:2000]
    t = torch.linspace(0, 2 * torch.pi, 200_001, dtype=torch.float64)[:-1]
    curve = 0.45 * torch.stack(
        (torch.sin(t) + 2 * torch.sin(2 * t), torch.cos(t) - 2 * torch.cos(2 * t), -torch.sin(3 * t)),
        dim=-1,
    )
    dense = torch.cdist(points[chosen], curve).min(dim=1).values - 0.15
    torch.testing.assert_close(phi.reshape(-1)[chosen], dense, rtol=0, atol=1e-6)


def test_trefoil_tube_is_a_closed_genus_one_surface():
    from torchsurf import mesh

    grid = Grid.cube(65, bound=1.6)
    surface = mesh.extract(sdf.trefoil(grid), grid)
    assert surface.is_watertight
    assert surface.euler_number == 0


def test_trefoil_rejects_a_self_intersecting_tube():
    with pytest.raises(ValueError, match="tube_radius must be below"):
        sdf.trefoil(Grid.cube(9, bound=1.6), tube_radius=0.3, scale=0.4)


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.bool, torch.float16])
def test_unsupported_dtype_refused(dtype):
    """Not float zeros in silence: the dtype is named and float32/float64 offered."""
    with pytest.raises(TypeError, match=r"dtype must be .*torch\.float32 or torch\.float64"):
        sdf.sphere(GRID, dtype=dtype)
    with pytest.raises(TypeError, match="dtype must be"):
        sdf.from_function(GRID, lambda p: p[..., 0], dtype=dtype)


@pytest.mark.parametrize("make", [
    lambda grid, c, dtype: ts.sdf.sphere(grid, 0.75, center=c, dtype=dtype),
    lambda grid, c, dtype: ts.sdf.torus(grid, 0.6, 0.25, center=c, dtype=dtype),
    lambda grid, c, dtype: ts.sdf.box(grid, (0.5, 0.4, 0.3), center=c, dtype=dtype),
    lambda grid, c, dtype: ts.sdf.capsule(grid, (c[0], c[1], c[2] - 0.3),
                                          (c[0], c[1], c[2] + 0.3), 0.4, dtype=dtype),
])
def test_float32_distances_keep_their_precision_far_from_the_origin(make) -> None:  # noqa: ANN001
    # the differences to the centre are taken in float64 before the cast: in float32 after it,
    # a sphere at x = 1000 was 4e-5 off and its curvature error grew with the resolution
    centre = (1000.013, -0.021, 0.037)
    grid = ts.Grid((33, 33, 33), spacing=1.0 / 16, origin=(999.0, -1.0, -1.0))
    single = make(grid, centre, torch.float32)
    double = make(grid, centre, torch.float64)
    assert (single.double() - double).abs().max() < 1e-6


def test_points_relative_to_a_point() -> None:
    grid = ts.Grid((4, 5, 6), spacing=0.5, origin=(1e4, 2.0, -3.0))
    relative = grid.points(torch.float32, relative_to=(1e4 + 0.1, 2.0, -3.0))
    exact = grid.points(torch.float64) - torch.tensor([1e4 + 0.1, 2.0, -3.0], dtype=torch.float64)
    assert relative.dtype == torch.float32
    assert (relative.double() - exact).abs().max() < 1e-6
    with pytest.raises(ValueError, match="relative_to"):
        grid.points(relative_to=(1.0, 2.0))


def test_a_torus_whose_tube_reaches_its_axis_is_refused():
    """minor_radius >= major_radius (horn, spindle) gave -0.300 where the distance is -0.458."""
    grid = Grid.cube(9, 1.0)
    with pytest.raises(ValueError, match="minor_radius=0.5 must be below major_radius=0.2"):
        sdf.torus(grid, major_radius=0.2, minor_radius=0.5)
    with pytest.raises(ValueError, match="minor_radius=1 must be below major_radius=1"):
        sdf.torus(grid, major_radius=1.0, minor_radius=1.0)


def test_a_trefoil_of_too_few_samples_is_refused():
    """With 16 samples four band nodes were 1.2 cells off at 33^3."""
    with pytest.raises(ValueError, match="samples"):
        sdf.trefoil(Grid.cube(9, 1.5), samples=16)
