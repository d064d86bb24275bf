"""torchsurf.signals: patterns read at closest points, images wrapped onto surfaces, seeded
noise, unit tangent fields and colour conversions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import torchsurf as ts
from torchsurf import signals


@pytest.fixture(scope="module")
def torus():
    grid = ts.Grid.cube(24, bound=1.6)
    return ts.ImplicitSurface(ts.sdf.torus(grid), grid)


@pytest.fixture(scope="module")
def sphere():
    grid = ts.Grid.cube(20, bound=1.4)
    return ts.ImplicitSurface(ts.sdf.sphere(grid), grid)


def test_closest_points_lie_on_the_sphere(sphere):
    points = signals.closest_points(sphere)
    band = sphere.band_mask()[0, 0]
    radius = points[0].norm(dim=0)[band]
    assert torch.allclose(radius, torch.ones_like(radius), atol=2e-2)


def test_checkerboard_alternates_and_is_constant_along_normals(sphere):
    points = signals.closest_points(sphere)
    board = signals.checkerboard(points, 0.5)
    assert board.shape == (1, 1, 20, 20, 20)
    assert set(board.unique().tolist()) == {0.0, 1.0}
    cells = torch.tensor([[[0.1, 0.1, 0.1], [0.6, 0.1, 0.1], [0.6, 0.6, 0.1]]]).permute(0, 2, 1)
    values = signals.checkerboard(cells[..., None, None], 0.5).flatten().tolist()
    assert values == [0.0, 1.0, 0.0]
    with pytest.raises(ValueError, match="tile"):
        signals.checkerboard(points, 0.0)


@pytest.mark.parametrize("name", signals.IMAGES)
def test_builtin_images_are_rgb_in_the_unit_range(name):
    image = signals.builtin_image(name, size=32)
    assert image.shape == (3, 32, 32)
    assert image.min() >= 0 and image.max() <= 1 and image.std() > 0.1


@pytest.mark.parametrize("projection", signals.PROJECTIONS)
def test_project_image_reads_the_image_where_expected(sphere, projection):
    image = torch.linspace(0, 1, 16).expand(1, 16, 16).clone()   # grows left to right
    points = signals.closest_points(sphere)
    box = (torch.full((3,), -1.0), torch.full((3,), 1.0))
    values = signals.project_image(image, points, projection, box, "z", sphere.normal)
    assert values.shape == (1, 1, 20, 20, 20)
    assert 0 <= values.min() and values.max() <= 1
    if projection == "planar":   # seen along z: the value grows with x
        x = points[0, 0]
        assert torch.allclose(values[0, 0], ((x + 1) / 2).clamp(0, 1), atol=1e-5)
    if projection in ("spherical", "cylindrical"):   # longitude: -x side is the image's edges
        east = torch.tensor([[1.0, 0.0, 0.0]]).T.reshape(1, 3, 1, 1, 1)
        value = signals.project_image(image, east, projection, box)
        assert value.item() == pytest.approx(0.5, abs=0.05)


def test_project_image_refuses_bad_input(sphere):
    points = signals.closest_points(sphere)
    box = (torch.full((3,), -1.0), torch.full((3,), 1.0))
    with pytest.raises(ValueError, match="projection"):
        signals.project_image(torch.rand(3, 8, 8), points, "conical", box)
    with pytest.raises(ValueError, match="image"):
        signals.project_image(torch.rand(8, 8), points, "planar", box)
    with pytest.raises(ValueError, match="normal"):
        signals.project_image(torch.rand(3, 8, 8), points, "triplanar", box)


@pytest.mark.parametrize("case", ["nan box", "flat box", "two-entry box", "not a pair",
                                  "float64 normal", "two-channel normal", "image list",
                                  "empty image", "integer image", "nan image"])
def test_project_image_names_what_is_wrong(sphere, case):
    """A NaN box had projected a constant, a box with low == high every node to the image's
    border, and float64 normals had promoted the float32 result, all silently; other cases
    failed inside reshape or grid_sample."""
    points = signals.closest_points(sphere)
    image, box, normal = torch.rand(3, 8, 8), (-torch.ones(3), torch.ones(3)), sphere.normal
    projection, expected = "planar", ValueError
    if case == "nan box":
        box, match = (torch.full((3,), math.nan), torch.ones(3)), "box's low"
    elif case == "flat box":
        box, match = (torch.zeros(3), torch.zeros(3)), "must lie below high"
    elif case == "two-entry box":
        box, match = (torch.zeros(2), torch.ones(2)), "three entries"
    elif case == "not a pair":
        box, match = torch.ones(3), "pair"
    elif case in ("float64 normal", "two-channel normal"):
        projection, expected, match = "triplanar", (ValueError, TypeError), "normal"
        normal = normal.double() if case == "float64 normal" else normal[:, :2]
    elif case == "image list":
        image, expected, match = [[0.0]], TypeError, "image"
    elif case == "empty image":
        image, match = torch.rand(3, 0, 8), "image"
    elif case == "integer image":
        image, expected, match = torch.ones(3, 8, 8, dtype=torch.int64), TypeError, "image"
    else:
        image[0, 1, 1], match = math.nan, "image"
    with pytest.raises(expected, match=match):
        signals.project_image(image, points, projection, box, normal=normal)
    # lists and arrays are boxes too
    plain = signals.project_image(torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(0)),
                                  points, "planar", ([-1, -1, -1], np.ones(3)))
    assert plain.dtype == points.dtype and bool(torch.isfinite(plain).all())
    low = torch.full((3,), -1.0, requires_grad=True)  # a box requiring grad keeps its gradient
    signals.project_image(torch.rand(3, 8, 8), points, "planar", (low, torch.ones(3))).sum().backward()
    assert low.grad is not None and bool(low.grad.abs().sum() > 0)
    entries = [torch.tensor(-1.0, requires_grad=True) for _ in range(3)]  # three 0-d entries
    signals.project_image(torch.rand(3, 8, 8), points, "planar", (entries, torch.ones(3))).sum().backward()
    assert entries[0].grad is not None


def test_load_image_reads_a_png(tmp_path):
    from skimage import io

    array = (np.arange(48, dtype=np.uint8).reshape(4, 4, 3) * 5)
    io.imsave(tmp_path / "small.png", array, check_contrast=False)
    image = signals.load_image(tmp_path / "small.png")
    assert image.shape == (3, 4, 4)
    assert torch.allclose(image, torch.as_tensor(array).permute(2, 0, 1) / 255.0)
    with pytest.raises(FileNotFoundError, match="image"):
        signals.load_image(tmp_path / "missing.png")


@pytest.mark.parametrize("dtype", [np.uint16, np.int16, np.uint32, np.float32])
def test_load_image_scales_every_integer_type_to_the_unit_range(tmp_path, dtype):
    """Only 8- and 16-bit unsigned files were scaled: int16 came back in [0, 32767]."""
    imageio = pytest.importorskip("imageio.v3")
    peak = np.iinfo(dtype).max if np.issubdtype(dtype, np.integer) else 1.0
    array = np.zeros((4, 4), dtype=dtype)
    array[0, 0], array[1, 1] = peak, peak // 2 if np.issubdtype(dtype, np.integer) else 0.5
    imageio.imwrite(tmp_path / "image.tif", array)
    image = signals.load_image(tmp_path / "image.tif")
    assert image.shape == (1, 4, 4)
    assert float(image.max()) == 1.0 and abs(float(image[0, 1, 1]) - 0.5) < 1e-4
    if dtype in (np.int16, np.float32):
        array[2, 2] = -1
        imageio.imwrite(tmp_path / "negative.tif", array)
        with pytest.raises(ValueError, match=r"negative.tif' holds .* pixels in \[-1"):
            signals.load_image(tmp_path / "negative.tif")


@pytest.mark.parametrize("channels, kept", [(2, 1), (4, 3)])
def test_load_image_drops_the_alpha_of_gray_and_colour_files(tmp_path, channels, kept):
    from PIL import Image

    array = (np.arange(30 * channels, dtype=np.uint8).reshape(6, 5, channels) * 3)
    Image.fromarray(array, mode={2: "LA", 4: "RGBA"}[channels]).save(tmp_path / "alpha.png")
    image = signals.load_image(tmp_path / "alpha.png")
    assert image.shape == (kept, 6, 5)
    assert torch.allclose(image, torch.as_tensor(array[..., :kept]).permute(2, 0, 1) / 255.0)


def test_noise_is_seeded(sphere):
    like = torch.zeros(1, 2, 4, 4, 4)
    assert torch.equal(signals.gaussian_noise(like, 0.3, 7), signals.gaussian_noise(like, 0.3, 7))
    assert not torch.equal(signals.gaussian_noise(like, 0.3, 7), signals.gaussian_noise(like, 0.3, 8))
    uniform = signals.uniform_noise(sphere, 1, 0)
    assert uniform.shape == (1, 1, 20, 20, 20) and 0 <= uniform.min() and uniform.max() < 1


def test_surface_noise_is_seeded_constant_along_normals_and_grained(sphere):
    noise = signals.surface_noise(sphere, 2, seed=3, grain=2.0)
    assert noise.shape == (1, 2, 20, 20, 20) and 0 <= noise.min() and noise.max() < 1
    assert torch.equal(noise, signals.surface_noise(sphere, 2, seed=3, grain=2.0))
    assert not torch.equal(noise, signals.surface_noise(sphere, 2, seed=4, grain=2.0))
    # nodes on the +x axis either side of S share their closest point, hence their value
    grid = ts.Grid.cube(21, bound=1.4)
    odd = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    on_axis = signals.surface_noise(odd, 1, seed=3, grain=2.0)[0, 0, 10, 10]
    assert float(on_axis[16]) == pytest.approx(float(on_axis[17]), abs=1e-5)
    band = sphere.band_mask()[0, 0]

    def neighbour_correlation(volume):
        a, b = volume[0, 0][band], torch.roll(volume, 1, dims=4)[0, 0][band]
        return float(torch.corrcoef(torch.stack((a, b)))[0, 1])

    fine = neighbour_correlation(signals.surface_noise(sphere, 1, seed=3, grain=1.0))
    coarse = neighbour_correlation(signals.surface_noise(sphere, 1, seed=3, grain=4.0))
    assert coarse > fine + 0.2, (fine, coarse)
    with pytest.raises(ValueError, match="grain"):
        signals.surface_noise(sphere, 1, seed=0, grain=0.0)


def _unit_and_tangent(field, surface):
    band = surface.band_mask()[0, 0]
    length = field[0].norm(dim=0)[band]
    normal_part = (field * surface.normal).sum(dim=1)[0][band]
    assert torch.allclose(length, torch.ones_like(length), atol=1e-5)
    assert normal_part.abs().max() < 1e-5


def test_axis_and_swirl_fields(torus):
    axis = signals.axis_field(torus, "x")
    swirl = signals.swirl_field(torus, "z")
    _unit_and_tangent(swirl, torus)
    points = torus.grid.points().permute(3, 0, 1, 2)[None]
    around = torch.stack((-points[:, 1], points[:, 0], torch.zeros_like(points[:, 0])), dim=1)
    band = torus.band_mask()[0, 0]
    alignment = (swirl * around).sum(1)[0][band].abs() / around[0].norm(dim=0)[band]
    assert alignment.min() > 0.99
    assert (swirl * around).sum(1)[0][band].min() > 0, "the swirl turns one way"
    _unit_and_tangent(axis, torus)


def test_smoothed_principal_direction_keeps_a_clean_field():
    grid = ts.Grid.cube(20, bound=1.5)
    torus = ts.ImplicitSurface(ts.sdf.torus(grid), grid)
    raw = signals.principal_direction(torus, "max")
    smoothed = signals.principal_direction(torus, "max", smoothing=1.0)
    _unit_and_tangent(smoothed, torus)
    band = torus.band_mask()[0, 0]
    agreement = (raw * smoothed).sum(1)[0][band].abs()
    assert agreement.median() > 0.99
    minor = signals.principal_direction(torus, "min")
    assert (minor * raw).sum(1)[0][band].abs().max() < 1e-4
    oriented = signals.orient(minor, signals.swirl_field(torus))
    assert (oriented * signals.swirl_field(torus)).sum(1)[0][band].min() > 0.9


def test_a_long_smoothing_keeps_rkcs_long_steps(monkeypatch):
    """A direction field's smoothing needs no second-order accuracy in time: over 12 cells of a
    3-cell band (phi = r^2 - R^2, not a distance) it takes steps of ``108 / rho``, not the heat
    flow's own ``12 / rho`` there (2.6 times the time on stripes_teapot at 64^3)."""
    plans = []

    class Recorded(ts.HeatFlow):
        def forward(self, *args, **kwargs):
            result = super().forward(*args, **kwargs)
            plans.append((self.last_plan, self.time_value.maximum()))
            return result

    monkeypatch.setattr(signals, "HeatFlow", Recorded)
    grid = ts.Grid.cube(28, bound=1.4)
    x, y, z = grid.points().unbind(-1)
    ellipsoid = ts.ImplicitSurface(((x / 1.1) ** 2 + y**2 + (z / 0.8) ** 2 - 1)[None, None], grid)
    field = signals.principal_direction(ellipsoid, "max", smoothing=12.0)
    _unit_and_tangent(field, ellipsoid)
    rho = ts.operators.laplace_beltrami_bound(ellipsoid)
    assert plans
    for plan, end in plans:
        assert plan.count == max(signals.SMOOTHING_STEPS,
                                 math.ceil(end * rho / signals.SMOOTHING_STEP))
        assert plan.count < end * rho / 12 / 2


def test_perturbed_field_is_unit_and_tangent(torus):
    noisy = signals.perturb_field(signals.swirl_field(torus), torus, 0.5, seed=1)
    _unit_and_tangent(noisy, torus)


@pytest.mark.parametrize("space", signals.COLOUR_SPACES)
def test_colour_conversions_round_trip(space):
    rgb = torch.rand(1, 3, 3, 4, 5, generator=torch.Generator().manual_seed(0))
    back = signals.rgb_from(signals.rgb_to(rgb, space), space)
    assert back.shape == rgb.shape
    assert torch.allclose(back, rgb, atol=1e-3)


def test_gray_and_chroma_brightness():
    rgb = torch.rand(2, 3, 3, 4, 5)
    assert signals.gray(rgb).shape == (2, 1, 3, 4, 5)
    chroma, brightness = signals.chroma_brightness(rgb)
    assert torch.allclose(chroma * brightness, rgb, atol=1e-5)
    assert torch.allclose(chroma.norm(dim=1), torch.ones(2, 3, 4, 5), atol=1e-4)
    with pytest.raises(ValueError, match="space"):
        signals.rgb_to(rgb, "cmyk")
    assert math.isfinite(float(brightness.min()))


def test_signals_on_bricks_equal_the_dense_ones_in_the_band():
    from torchsurf import bricks

    grid = ts.Grid.cube(32, bound=2.0)
    dense = ts.ImplicitSurface(ts.sdf.torus(grid), grid)
    packed = bricks.from_dense(dense)
    band = packed.band_mask().expand(-1, 3, -1, -1, -1)
    for make in (signals.node_points, signals.closest_points,
                 lambda s: signals.surface_noise(s, 2, seed=5, grain=1.5),
                 lambda s: signals.swirl_field(s, "z", (0.1, 0.0, 0.0)),
                 lambda s: signals.gaussian_noise(signals.node_points(s), 0.3, 2, s),
                 lambda s: signals.uniform_noise(s, 2, 4)):  # was dense on bricks
        expected = packed.from_dense(make(dense))
        got = make(packed)
        assert got.shape == expected.shape
        where = band[:, :got.shape[1]]
        assert torch.allclose(got[where], expected[where], atol=1e-5)


def test_noise_on_bricks_of_several_shapes_is_the_dense_batch_noise():
    """Bricks drew each entry's noise from the stream's next numbers one entry at a time, while
    the dense batch draws them all at once: torch's normal numbers come in blocks of 16, so from
    the second entry on the noise differed (by 5.6 at 34^3), and uniform noise was drawn anew
    for every entry where the dense grid gives all entries the same."""
    from torchsurf import bricks

    grid = ts.Grid.cube(34, bound=2.2)
    phi = torch.cat([ts.sdf.sphere(grid, 0.6), ts.sdf.torus(grid, 0.9, 0.35)])
    dense = ts.ImplicitSurface(phi, grid)
    packed = bricks.from_dense(dense)
    band = packed.band_mask().expand(-1, 2, -1, -1, -1)
    pairs = [(signals.gaussian_noise(torch.zeros(2, 2, *grid.shape), 1.0, 7),
              signals.gaussian_noise(packed.from_dense(torch.zeros(2, 2, *grid.shape)), 1.0, 7,
                                     packed)),
             (signals.uniform_noise(dense, 2, 7).expand(2, -1, -1, -1, -1),
              signals.uniform_noise(packed, 2, 7))]
    for expected, got in pairs:
        assert torch.equal(got[band], packed.from_dense(expected)[band])


def test_noise_is_the_same_in_float32_and_float64():
    """float64 noise was drawn in float64, other numbers than float32's for one seed (a dataset
    item's noise was 0.69 off between the dtypes, its clean signal 3e-7)."""
    grid = ts.Grid.cube(12, bound=1.5)
    for dtype in (torch.float32, torch.float64):
        surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=dtype), grid)
        noise = signals.gaussian_noise(torch.zeros(2, 1, 12, 12, 12, dtype=dtype), 0.5, 3)
        uniform = signals.uniform_noise(surface, 1, 3)
        assert noise.dtype == uniform.dtype == dtype
        if dtype == torch.float32:
            first = (noise.double(), uniform.double())
    assert torch.equal(noise, first[0]) and torch.equal(uniform, first[1])
    assert float(noise.std()) == pytest.approx(0.5, rel=0.05)


def test_smoothing_on_a_coarse_grid_follows_the_shape():
    """On a capsule's cylinder the larger principal curvature 1/r turns around the axis: the
    field smoothed on a grid half as fine and read back at the closest points follows it, and
    equals on bricks what it is on the dense grid."""
    from torchsurf import bricks

    def capsule(n):
        grid = ts.Grid.cube(n, bound=2.2)
        phi = ts.sdf.capsule(grid, (0.0, 0.0, -0.6), (0.0, 0.0, 0.6), radius=0.6)
        return ts.ImplicitSurface(phi, grid)

    fine, coarse = capsule(48), capsule(24)
    points = signals.node_points(fine)[0]
    cylinder = fine.band_mask()[0, 0] & (points[2].abs() < 0.35)
    around = torch.stack((-points[1], points[0], torch.zeros_like(points[0])))
    around = around / around.norm(dim=0).clamp(min=1e-9)
    smoothed = signals.principal_direction(fine, "max", smoothing=4.0, coarse=coarse)
    _unit_and_tangent(smoothed, fine)
    agreement = (around * smoothed[0]).sum(0)[cylinder].abs()
    assert agreement.min() > 0.999
    minor = signals.principal_direction(fine, "min", smoothing=4.0, coarse=coarse)
    assert (minor * smoothed).sum(1)[0][fine.band_mask()[0, 0]].abs().max() < 1e-4

    packed, packed_coarse = bricks.from_dense(fine), bricks.from_dense(coarse)
    where = packed.band_mask()[:, 0]
    expected = packed.from_dense(smoothed)
    for surface in (packed_coarse, coarse):
        got = signals.principal_direction(packed, "max", smoothing=4.0, coarse=surface)
        assert (got * expected).sum(1)[where].abs().min() > 1 - 1e-4


def test_coarse_smoothing_refuses_what_it_cannot_use():
    fine_grid, coarse_grid = ts.Grid.cube(20, bound=1.6), ts.Grid.cube(12, bound=1.6)
    fine = ts.ImplicitSurface(ts.sdf.torus(fine_grid), fine_grid)
    coarse = ts.ImplicitSurface(ts.sdf.torus(coarse_grid), coarse_grid)
    with pytest.raises(ValueError, match="coarse: only used with smoothing > 0"):
        signals.principal_direction(fine, "max", coarse=coarse)
    with pytest.raises(ValueError, match="coarse must be coarser"):
        signals.principal_direction(coarse, "max", 2.0, coarse=fine)
    pair = ts.ImplicitSurface(ts.sdf.torus(coarse_grid).expand(2, -1, -1, -1, -1), coarse_grid)
    with pytest.raises(ValueError, match="batch size 1"):
        signals.principal_direction(fine, "max", 2.0, coarse=pair)
    with pytest.raises(TypeError, match="coarse must be"):
        signals.principal_direction(fine, "max", 2.0, coarse=coarse.phi)


def test_noise_counts_and_seeds_are_checked_by_name():
    grid = ts.Grid.cube(9, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    assert signals.uniform_noise(surface, 2.0, 0).shape == (1, 2, 9, 9, 9)  # a whole float
    assert signals.surface_noise(surface, np.int64(2), 0).shape == (1, 2, 9, 9, 9)
    for bad, error in ((0, ValueError), (-1, ValueError), (2.5, ValueError), ("a", TypeError)):
        with pytest.raises(error, match="channels must be a whole number >= 1"):
            signals.surface_noise(surface, bad, 0)
        with pytest.raises(error, match="channels must be a whole number >= 1"):
            signals.uniform_noise(surface, bad, 0)
    assert signals.generator(2**32 - 1).initial_seed() == 2**32 - 1
    # the CPU generator keeps 32 bits: 2**32 drew what 0 draws
    with pytest.raises(ValueError, match=r"seed must be a whole number in \[0, 2\*\*32\)"):
        signals.gaussian_noise(torch.zeros(1, 1, 3, 3, 3), 1.0, 2**32)
    # a grain of 1e-3 cells asked the allocator for 48 TB at 9^3 (RuntimeError from it)
    with pytest.raises(MemoryError, match="surface_noise's lattice of grain 0.001"):
        signals.surface_noise(surface, 1, 0, grain=1e-3)


@pytest.mark.parametrize("centre, error", [((0.0, 0.0), ValueError), ("abc", TypeError),
                                           ((0.0, math.nan, 0.0), ValueError)])
def test_swirl_centre_is_checked_by_name(torus, centre, error):
    """A NaN centre had made every value NaN; a short one failed inside a reshape."""
    with pytest.raises(error, match="centre"):
        signals.swirl_field(torus, "z", centre)


def test_fields_and_parameters_that_would_broadcast_or_mislead_are_refused(torus):
    """orient widened its result to the reference's batch and read a one-channel reference;
    perturb_field turned a scalar field into a unit tangent field; a NaN origin painted NaN."""
    shape = torus.grid.shape
    field = torch.randn(1, 3, *shape)
    oriented = signals.orient(field, torch.randn(1, 3, *shape))
    assert oriented.shape == field.shape
    assert signals.orient(field.expand(2, 3, *shape), field).shape == (2, 3, *shape)
    for reference in (torch.randn(2, 3, *shape), torch.randn(1, 1, *shape),
                      torch.randn(1, 3, 24, 24, 25)):
        with pytest.raises(ValueError, match="reference must"):
            signals.orient(field, reference)
    for bad in (torch.rand(1, 1, *shape), torch.rand(3, *shape), torch.rand(1, 3, 24, 24, 25)):
        with pytest.raises(ValueError, match="field"):
            signals.perturb_field(bad, torus, 0.1, 0)
    rgb = torch.rand(1, 3, 4, 4, 4)
    for eps in (float("nan"), -1.0, 0.0):
        with pytest.raises(ValueError, match="eps must be a finite positive number"):
            signals.chroma_brightness(rgb, eps)
    points = signals.closest_points(torus)
    with pytest.raises(ValueError, match="origin must be three finite numbers"):
        signals.checkerboard(points, 0.3, (math.nan, 0.0, 0.0))
    with pytest.raises(TypeError, match="origin must be world"):
        signals.checkerboard(points, 0.3, "abc")
    assert torch.equal(signals.checkerboard(points, 0.3, np.array([0.1, 0.0, 0.0])),
                       signals.checkerboard(points, 0.3, (0.1, 0.0, 0.0)))
    with pytest.raises(TypeError, match="like must be a floating-point tensor"):
        signals.gaussian_noise(torch.zeros(1, 1, 3, 3, 3, dtype=torch.long), 1.0, 0)
    for size in (0, -3):
        with pytest.raises(ValueError, match="size must be a whole number >= 1"):
            signals.builtin_image("checker", size)


def test_tensor_seeds_and_far_origins_keep_every_digit():
    """A tensor seed went through float: seeds 2^53 and 2^53 + 1 drew the same noise (seeds
    now lie below 2^32; 2^24 and 2^24 + 1 are one float32). A checkerboard's origin was
    rounded to float32 before the floor that picks a tile."""
    like = torch.zeros(1, 1, 4, 4, 4)
    for seed in (2**24 + 1, 2**32 - 1):
        assert torch.equal(signals.gaussian_noise(like, 1.0, torch.tensor(seed)),
                           signals.gaussian_noise(like, 1.0, seed))
    assert not torch.equal(signals.gaussian_noise(like, 1.0, torch.tensor(2**24)),
                           signals.gaussian_noise(like, 1.0, torch.tensor(2**24 + 1)))
    point = torch.tensor([1000.3 - 1e-5, 0.5, 0.5], dtype=torch.float64).view(1, 3, 1, 1, 1)
    for origin in ((1000.3, 0.0, 0.0), np.array([1000.3, 0.0, 0.0]),
                   torch.tensor([1000.3, 0.0, 0.0], dtype=torch.float64)):
        assert float(signals.checkerboard(point, 1.0, origin)) == 1.0  # the tile below 1000.3


def test_tangent_unit_and_orient_check_their_fields():
    """Both took a field of 1 channel, of another dtype or with a spatial size of 1 silently
    (tangent_unit broadcast it to (1, 3, D, H, W))."""
    grid = ts.Grid.cube(9, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    good = torch.ones(1, 3, 9, 9, 9)
    assert signals.tangent_unit(good, surface).shape == good.shape
    for bad in (torch.ones(1, 1, 9, 9, 9), torch.ones(1, 3, 9, 9, 1), torch.ones(3, 9, 9, 9)):
        with pytest.raises(ValueError, match="field"):
            signals.tangent_unit(bad, surface)
    with pytest.raises(ts.MismatchError, match="field"):
        signals.tangent_unit(good.double(), surface)
    with pytest.raises(ts.MismatchError, match="reference"):
        signals.orient(good.double(), good)
