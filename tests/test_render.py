"""torchsurf.render: colours, the fitted camera, panels side by side written atomically."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
import trimesh

import torchsurf as ts

pytest.importorskip("matplotlib")
from matplotlib import image as mpimg  # noqa: E402

from torchsurf import render  # noqa: E402


def test_colours_modes():
    values = np.linspace(0, 1, 10)[:, None]
    scalar = render.colours(values, "scalar", "viridis", (0.0, 1.0))
    assert scalar.shape == (10, 3) and (scalar[0] != scalar[-1]).any()
    field = render.colours(np.array([[-1.0, 0.0, 0.0], [0.0, 0.6, -0.8]]), "field")
    assert np.allclose(field, [[1, 0, 0], [0, 0.6, 0.8]])
    rgb = render.colours(np.array([[1.5, -0.2, 0.5]]), "rgb")
    assert np.allclose(rgb, [[1.0, 0.0, 0.5]])
    with pytest.raises(ValueError, match="mode"):
        render.colours(values, "hsv")


def test_a_constant_with_rounding_is_one_colour_and_huge_values_do_not_overflow():
    """The default limits stretched a constant's float32 rounding (6e-8 of 0.7) over the whole
    map, while the exact constant took its bottom; +-1e308 overflowed the span to NaN, drawn
    black, and collapsed every other value onto one colour."""
    exact = np.full((50, 1), 0.7)
    rounded = exact + np.random.default_rng(0).uniform(-6e-8, 6e-8, size=exact.shape)
    middle = render.colours(np.array([[0.5]]), limits=(0.0, 1.0))
    assert np.allclose(render.colours(exact), middle)
    # within a hundredth of the map of its middle (all of it, then 0.13 at FLAT_SPAN = 1e-6),
    # equalized too (its ranks spread it over the whole map)
    for drawn in (render.colours(rounded), render.colours(rounded, equalize=True)):
        assert np.allclose(drawn, middle, atol=0.01), np.unique(drawn.round(3), axis=0)
    # a pattern of a few hundred float32 ulps (heat near equilibrium) is still equalized
    ramp = (0.5 + 1e-5 * np.linspace(-1.0, 1.0, 200)).astype(np.float32)[:, None]
    assert len(np.unique(render.colours(ramp, equalize=True).round(3), axis=0)) > 50
    # limits given as a tensor, as values may be
    assert np.allclose(render.colours(np.array([[0.5]]), limits=torch.tensor([0.0, 1.0])),
                       middle)
    # a few vertices off a constant (a point source) still stand out: the map's two ends
    sparse = render.colours(np.array([0.0] * 995 + [1.0] * 5)[:, None])
    ends = render.colours(np.array([[0.0], [1.0]]), limits=(0.0, 1.0))
    assert np.allclose(sparse[-1], ends[1]) and not np.allclose(sparse[0], sparse[-1])
    huge = render.colours(np.array([[1e308], [-1e308], [0.0], [np.nan]]))
    assert np.isfinite(huge).all() and (huge[0] != huge[1]).any()
    assert np.allclose(huge[3], 0.5) and not np.allclose(huge[:3], 0.0)


def test_equalized_colours_use_the_whole_map():
    values = np.sort(np.random.default_rng(0).normal(size=1000))[:, None]
    middle = slice(250, 750)
    stretched = render.colours(values, "scalar", "gray")
    equalized = render.colours(values, "scalar", "gray", equalize=True)
    # percentiles leave the middle half of a normal sample 29 % of the map; ranks give it half
    assert np.ptp(stretched[middle, 0]) < 0.35
    assert np.ptp(equalized[middle, 0]) > 0.48
    assert equalized[0, 0] == pytest.approx(0.0) and equalized[-1, 0] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="not both"):
        render.colours(values, "scalar", "gray", (0.0, 1.0), equalize=True)
    # one finite value is a constant: the map's middle, as two equal values (it took the bottom)
    middle = render.colours(np.array([[5.0], [5.0]]), equalize=True)[0]
    for single in (np.array([[5.0]]), np.array([[5.0], [np.nan], [np.nan]])):
        assert np.allclose(render.colours(single, equalize=True)[0], middle)
    assert np.allclose(middle, render.colours(np.array([[0.5]]), limits=(0.0, 1.0)))
    with warnings.catch_warnings():  # their spread overflowed (a RuntimeWarning), an audit's
        warnings.simplefilter("error")
        huge = render.colours(np.array([[-1.7e308], [0.0], [1.7e308]]), "scalar", "gray",
                              equalize=True)
    assert np.allclose(huge[:, 0], [0.0, 0.5, 1.0], atol=0.01)  # the map's 256 steps


def test_pictures_too_wide_to_draw_and_empty_meshes_are_refused(tmp_path):
    """Off-screen VTK drew a picture over 16384 pixels wide black without a word; an empty
    mesh failed in numpy's reduction."""
    import trimesh

    mesh = trimesh.creation.icosphere(1)
    grey = np.full((len(mesh.vertices), 3), 0.5)
    with pytest.raises(ValueError, match="beyond 16384 pixels a side"):
        render.render_panels(mesh, [("a", grey)] * 5, tmp_path / "wide.png", width=3300,
                             height=64, renderer="matplotlib")
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    with pytest.raises(ValueError, match="mesh has no vertices"):
        render.render_panels(empty, [("a", np.zeros((0, 3)))], tmp_path / "empty.png",
                             renderer="matplotlib")
    with pytest.raises(ValueError, match=r"vertices must have shape \(V, 3\)"):
        render.fit_camera(np.zeros((0, 3)))
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("up", ["x", "y", "z"])
def test_camera_sees_every_vertex(up):
    vertices = np.random.default_rng(0).normal(size=(200, 3)) * [3.0, 1.0, 0.5] + 10.0
    camera = render.fit_camera(vertices, 30.0, 40.0, up, aspect=2.0)
    screen, _ = camera.project(vertices)
    x0, x1, y0, y1 = camera.window
    assert (screen[:, 0] > x0).all() and (screen[:, 0] < x1).all()
    assert (screen[:, 1] > y0).all() and (screen[:, 1] < y1).all()
    assert (x1 - x0) == pytest.approx(2.0 * (y1 - y0))
    assert np.allclose(np.cross(camera.right, camera.up), camera.towards)


def test_vertex_values_sample_the_volume():
    grid = ts.Grid.cube(9, bound=1.0)
    x = grid.points()[..., 0][None, None]
    mesh = trimesh.Trimesh([[0.1, 0.2, 0.3], [-0.5, 0.0, 0.0], [0.0, 0.5, 0.0]], [[0, 1, 2]])
    assert np.allclose(render.vertex_values(x, mesh, grid)[:, 0], [0.1, -0.5, 0.0], atol=1e-6)


@pytest.mark.parametrize("layout", ["dense", "bricks"])
def test_vertex_values_keep_their_precision_far_from_the_origin(layout):
    """World vertices were cast to the volume's float32 before the grid's origin was taken
    off: 1e5 away a vertex moved 0.06 cell."""
    from torchsurf import bricks

    offset = 1e5
    near = ts.Grid.cube(29, 1.6)
    grid = ts.Grid(near.shape, near.spacing, tuple(o + offset for o in near.origin))
    mesh = trimesh.creation.icosphere(subdivisions=2)
    mesh.apply_translation([offset] * 3)
    x = grid.points(dtype=torch.float64)[..., 0] - offset  # exact in float64, then float32
    volume = x.float()[None, None]
    where = grid
    if layout == "bricks":
        phi = (grid.points(dtype=torch.float64) - offset).norm(dim=-1) - 1
        where = bricks.from_dense(ts.ImplicitSurface(phi.float()[None, None], grid))
        volume = where.from_dense(volume)
    values = render.vertex_values(volume, mesh, where)[:, 0]
    assert np.abs(values - (mesh.vertices[:, 0] - offset)).max() < 1e-3 * grid.spacing


def test_panels_side_by_side_written_atomically(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=2)
    height = mesh.vertices[:, 2]
    panels = [("height", render.colours(height[:, None])),
              ("normal", render.colours(mesh.vertex_normals, "field"))]
    path = render.render_panels(mesh, panels, tmp_path / "sub" / "ball.png", width=80, height=60)
    picture = mpimg.imread(path)
    assert picture.shape[:2] == (60, 160)
    assert picture[:, :80, :3].std() > 0.05 and picture[:, 80:, :3].std() > 0.05
    assert [p.name for p in path.parent.iterdir()] == ["ball.png"]
    # the permissions open() would give, not the temporary file's private 0600
    assert path.stat().st_mode & 0o777 == render.FILE_MODE
    with pytest.raises(ValueError, match=r"panels\[0\]"):
        render.render_panels(mesh, [("bad", np.zeros((3, 3)))], tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()


def test_render_extracted_surface_data(tmp_path):
    grid = ts.Grid.cube(16, bound=1.3)
    phi = ts.sdf.torus(grid)
    mesh = ts.mesh.extract(phi, grid)
    z = grid.points()[..., 2][None, None]
    colours = render.colours(render.vertex_values(z, mesh, grid))
    path = render.render_panels(mesh, [("z", colours)], tmp_path / "torus.png", 40, 40,
                                elevation=60.0)
    assert mpimg.imread(path).shape[:2] == (40, 40)
    assert torch.is_tensor(z)


def test_renderer_auto_falls_back_to_matplotlib_and_says_why(monkeypatch, tmp_path):
    assert render.resolve_renderer("matplotlib") == ("matplotlib", "asked for")
    monkeypatch.setattr(render, "_pyvista_problem", lambda: "pyvista is not installed")
    assert render.resolve_renderer("auto") == ("matplotlib",
                                               "fallback: pyvista is not installed")
    with pytest.raises(ImportError, match="not installed"):
        render.resolve_renderer("pyvista")
    with pytest.raises(ValueError, match="renderer"):
        render.resolve_renderer("blender")
    mesh = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(ImportError, match="not installed"):
        render.render_panels(mesh, [("a", np.ones((len(mesh.vertices), 3)))],
                             tmp_path / "a.png", renderer="pyvista")


def test_pyvista_draws_the_panels_the_size_asked(tmp_path):
    if render.resolve_renderer("auto")[0] != "pyvista":
        pytest.skip(render.resolve_renderer("auto")[1])
    mesh = trimesh.creation.icosphere(subdivisions=2)
    panels = [("height", render.colours(mesh.vertices[:, 2:])),
              ("normal", render.colours(mesh.vertex_normals, "field"))]
    path = render.render_panels(mesh, panels, tmp_path / "ball.png", 80, 60, renderer="pyvista")
    picture = mpimg.imread(path)
    assert picture.shape[:2] == (60, 160)
    assert picture[:, :80, :3].std() > 0.05 and picture[:, 80:, :3].std() > 0.05


@pytest.mark.parametrize("renderer", ["matplotlib", "pyvista"])
def test_a_tiny_shape_is_drawn_as_the_same_shape_at_unit_size(tmp_path, renderer):
    """A sphere of radius 1e-7 is the unit sphere's picture: pyvista drew it black (trimesh's
    normals are zero below an absolute face area of 1e-13)."""
    if renderer == "pyvista" and render.resolve_renderer("auto")[0] != "pyvista":
        pytest.skip(render.resolve_renderer("auto")[1])
    pictures = []
    for radius in (1.0, 1e-7):
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
        grey = np.full((len(mesh.vertices), 3), 0.6)
        path = render.render_panels(mesh, [("", grey)], tmp_path / f"{radius}.png", 60, 60,
                                    renderer=renderer)
        pictures.append(mpimg.imread(path)[..., :3])
    assert pictures[0][20:40, 20:40].mean() > 0.3  # lit, not black
    assert np.abs(pictures[1] - pictures[0]).mean() < 0.01


def test_a_mesh_not_finite_or_a_path_not_png_is_refused(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    grey = np.full((len(mesh.vertices), 3), 0.6)
    broken = trimesh.Trimesh(mesh.vertices.copy(), mesh.faces, process=False)
    broken.vertices[5] = np.nan
    with pytest.raises(ValueError, match=r"mesh has 1 of 42 vertices that are NaN or infinite, "
                                         r"e.g. vertex 5"):
        render.render_panels(broken, [("a", grey)], tmp_path / "a.png", renderer="matplotlib")
    for name in ("a.jpg", "a.pdf"):  # PNG bytes had been written under those names
        with pytest.raises(ValueError, match=r"give a path ending in .png \(or with no suffix\), "
                                             r"not '\.(jpg|pdf)'"):
            render.render_panels(mesh, [("a", grey)], tmp_path / name, renderer="matplotlib")
    assert list(tmp_path.iterdir()) == []


def test_colours_refuse_what_they_would_misdraw():
    """Equal values share a colour under equalize (they had ranks by vertex order); the
    channel count and limits are checked (a scalar of 3 channels showed the first; limits
    (1, 0) or NaN painted every vertex the lowest colour)."""
    ties = np.r_[np.zeros(5), np.ones(5)][:, None]
    grey = render.colours(ties, "scalar", "gray", equalize=True)[:, 0]
    assert np.ptp(grey[:5]) == 0 and np.ptp(grey[5:]) == 0 and grey[5] > grey[0]
    values = np.linspace(0, 1, 3)[:, None]
    with pytest.raises(ValueError, match=r"needs values of shape \(V, 1\)"):
        render.colours(np.repeat(values, 3, axis=1), "scalar")
    with pytest.raises(ValueError, match=r"needs values of shape \(V, 3\)"):
        render.colours(np.ones((2, 4)), "rgb")
    for limits in [(1.0, 0.0), (float("nan"), 1.0), (0.0,), (0.0, 0.0)]:
        with pytest.raises(ValueError, match="limits must be two finite numbers"):
            render.colours(values, "scalar", "gray", limits)


def test_panels_refuse_bad_sizes_and_colours(tmp_path):
    mesh = trimesh.creation.icosphere(subdivisions=1)
    grey = np.full((len(mesh.vertices), 3), 0.5)
    for width in (0, -5, 10.5, True):
        with pytest.raises(ValueError, match="width must be a positive whole number"):
            render.render_panels(mesh, [("a", grey)], tmp_path / "a.png", width=width,
                                 renderer="matplotlib")
    with pytest.raises(ValueError, match="height must be"):
        render.render_panels(mesh, [("a", grey)], tmp_path / "a.png", height=0,
                             renderer="matplotlib")
    for bad in (np.nan, 1.5):
        colours = grey.copy()
        colours[3, 1] = bad
        with pytest.raises(ValueError, match=r"panels\[1\]: colours must lie in \[0, 1\]"):
            render.render_panels(mesh, [("a", grey), ("b", colours)], tmp_path / "a.png",
                                 renderer="matplotlib")
    assert not list(tmp_path.iterdir())


def test_vertex_values_take_the_entry_of_a_batch():
    """A two-shape brick surface (or a batch of volumes) gave entry 0's values at the mesh of
    entry 1, silently; entry picks the shape, and is required where there are several."""
    from torchsurf import bricks

    grid = ts.Grid((24, 24, 24), 0.1, (0.0, 0.0, 0.0))
    distance = (grid.points(torch.float64) - 1.15).norm(dim=-1)
    phi = torch.stack([distance - 0.7, distance - 0.5])[:, None]
    data = torch.stack([torch.zeros_like(distance), torch.ones_like(distance)])[:, None]
    inner = ts.mesh.extract(phi[1:], grid)
    surface = bricks.from_dense(phi, grid)
    for where, volume in ((surface, surface.from_dense(data)), (grid, data)):
        with pytest.raises(ValueError, match="give entry"):
            render.vertex_values(volume, inner, where)
        assert np.allclose(render.vertex_values(volume, inner, where, entry=1), 1.0, atol=1e-12)
        assert np.allclose(render.vertex_values(volume, inner, where, entry=0), 0.0, atol=1e-12)


def test_vertex_values_outside_the_box_are_named_in_world_coordinates():
    grid = ts.Grid((10, 10, 10), 0.1, (3.0, -2.0, 7.0))
    mesh = trimesh.Trimesh([[10.0, 0.0, 0.0], [3.5, -1.5, 7.5], [3.6, -1.5, 7.5]], [[0, 1, 2]],
                           process=False)
    with pytest.raises(ValueError, match=r"1 of 3 vertices lie outside the grid's box "
                                         r"\(3.0, -2.0, 7.0\).*vertex 0 at \[10.0, 0.0, 0.0\]"):
        render.vertex_values(torch.zeros(1, 1, 10, 10, 10), mesh, grid)


def test_vertex_values_name_the_volume_when_its_shape_is_wrong():
    grid = ts.Grid.cube(12, bound=1.0)
    mesh = trimesh.Trimesh([[0.1, 0.2, 0.3], [-0.5, 0.0, 0.0], [0.0, 0.5, 0.0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match=r"volume has spatial shape \(8, 8, 8\) but grid has"):
        render.vertex_values(torch.zeros(1, 1, 8, 8, 8), mesh, grid)
    with pytest.raises(ValueError, match="volume"):
        render.vertex_values(torch.zeros(8, 8, 8), mesh, grid)


@pytest.mark.parametrize("mode", ["rgb", "field"])
def test_a_nan_vector_is_grey_as_a_nan_scalar_is(mode):
    """A field undefined on an axis came out NaN, against colours' own contract, and the
    panels then refused colours' output."""
    values = np.array([[0.2, -0.9, 0.4], [np.nan, 0.1, 0.2], [1.5, 0.3, -0.2]])
    rgb = render.colours(values, mode)
    assert np.isfinite(rgb).all() and (rgb >= 0).all() and (rgb <= 1).all()
    assert rgb[1].tolist() == [0.5, 0.5, 0.5]
