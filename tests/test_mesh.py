"""torchsurf.mesh: loading, fitted grids, marching cubes, vertex data in the band."""

from __future__ import annotations

import math
import os
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

import torchsurf as ts
from torchsurf import mesh as tsm
from torchsurf.flows.extension import CubicStencil


def test_extract_sphere_area_and_volume() -> None:
    grid = ts.Grid.cube(48, bound=1.3)
    surface = tsm.extract(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    assert isinstance(surface, trimesh.Trimesh) and surface.is_watertight
    assert surface.area == pytest.approx(4 * math.pi, rel=0.01)
    assert surface.volume == pytest.approx(4 / 3 * math.pi, rel=0.01)  # positive: outward
    radius = np.linalg.norm(surface.vertices, axis=1)
    assert np.abs(radius - 1).max() < 0.1 * grid.spacing


def _half_box_on_node_planes() -> tuple[torch.Tensor, ts.Grid, float]:
    """``z <= 0`` inside the box ``|x|, |y| <= 0.75, |z| <= 0.5``: every face on a node plane
    (spacing 1/8, dyadic node positions, so phi is exactly 0 there)."""
    grid = ts.Grid.cube(17, bound=1.0)
    box = ts.sdf.box(grid, half_size=(0.75, 0.75, 0.5), dtype=torch.float64)
    height = grid.points(dtype=torch.float64)[..., 2][None, None]
    return torch.maximum(height, box), grid, 2 * 1.5**2 + 4 * 1.5 * 0.5


def _sphere_through_nodes() -> tuple[torch.Tensor, ts.Grid, float]:
    """A sphere of radius 10 cells about a node: some nodes lie on it."""
    grid = ts.Grid.cube(33, bound=1.2)
    radius = 10 * grid.spacing
    return ts.sdf.sphere(grid, radius=radius, dtype=torch.float64), grid, 4 * math.pi * radius**2


def _assert_no_degenerate_faces(surface, grid: ts.Grid) -> None:  # noqa: ANN001
    corners = surface.vertices[surface.faces]
    areas = 0.5 * np.linalg.norm(
        np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    assert areas.min() >= 1e-12 * grid.spacing**2
    nearest, _ = cKDTree(surface.vertices).query(surface.vertices, k=2)
    assert nearest[:, 1].min() >= 1e-9 * grid.spacing


@pytest.mark.parametrize(("case", "area_tolerance"),
                         [(_half_box_on_node_planes, 1e-12), (_sphere_through_nodes, 5e-3)],
                         ids=["plane-in-box", "sphere"])
def test_extract_where_phi_vanishes_at_nodes_has_no_degenerate_faces(case, area_tolerance) -> None:
    phi, grid, area = case()
    surface = tsm.extract(phi, grid)
    _assert_no_degenerate_faces(surface, grid)
    assert surface.is_watertight and surface.is_winding_consistent
    assert surface.euler_number == 2 and len(np.unique(surface.faces)) == len(surface.vertices)
    assert surface.volume > 0  # still wound outward
    assert surface.area == pytest.approx(area, rel=area_tolerance)


def test_extract_where_phi_vanishes_at_nodes_to_rounding_has_no_degenerate_faces() -> None:
    """A tilted plane through nodes of a grid far from the origin: phi is 0 there only to
    rounding, and the crossings around those nodes fell 1e-16 apart (faces of no area)."""
    grid = ts.Grid((23, 19, 21), 0.13, (3.0, -7.0, 0.5))
    points = grid.points(dtype=torch.float64)
    normal = torch.tensor([0.3, -0.8, 0.52], dtype=torch.float64)
    offset = float((torch.tensor(grid.origin, dtype=torch.float64) + 1.3) @ normal)
    phi = ((points * normal).sum(-1) - offset)[None, None]
    surface = tsm.extract(phi, grid)
    _assert_no_degenerate_faces(surface, grid)
    assert (surface.face_normals @ normal.numpy()).min() > 0.99
    assert surface.is_winding_consistent


def test_extract_keeps_a_vertex_on_its_node_when_a_neighbour_is_on_the_level_too() -> None:
    # the crossing on the y edge is closer to node (1, 1, 1) than float32 resolves, and the
    # neighbour along z is on the level too (to within LEVEL_SNAP of phi's range): each is a
    # vertex on its node exactly, and the mesh closes
    phi = torch.ones(1, 1, 4, 4, 4, dtype=torch.float64)
    phi[0, 0, 1, 1, 1], phi[0, 0, 2, 1, 1], phi[0, 0, 1, 2, 1] = 1e-17, 1e-18, -1.0
    surface = tsm.extract(phi, ts.Grid((4, 4, 4), 1.0))
    for node in ([1.0, 1.0, 1.0], [1.0, 1.0, 2.0]):
        assert np.linalg.norm(surface.vertices - node, axis=1).min() == 0.0
    assert surface.is_watertight


@pytest.mark.parametrize("offset, scale", [(1e7, 1.0), (0.0, 1e-46), (0.0, 1e100)])
def test_extract_works_in_float64_where_phi_needs_it(offset, scale) -> None:
    """scikit-image picks the crossed edges in float32: phi + 1e7 at level 1e7 came out half a
    radius off (area 29.1 against 12.5), phi * 1e-46 crossed nowhere, phi * 1e100 raised an
    IndexError."""
    grid = ts.Grid.cube(32, bound=2.0)
    phi = (grid.points(dtype=torch.float64).norm(dim=-1) - 1.0)[None, None]
    reference = tsm.extract(phi, grid)
    mesh = tsm.extract(phi * scale + offset, grid, level=offset)
    assert len(mesh.faces) == len(reference.faces)
    assert mesh.area == pytest.approx(reference.area, rel=1e-9)


def test_extract_level_and_world_coordinates() -> None:
    grid = ts.Grid(shape=(30, 31, 32), spacing=0.1, origin=(1.0, -2.0, 0.5))
    center = (2.5, -0.5, 2.0)
    phi = ts.sdf.sphere(grid, radius=0.8, center=center, dtype=torch.float64)
    surface = tsm.extract(phi, grid, level=0.2)
    radius = np.linalg.norm(surface.vertices - np.array(center), axis=1)
    np.testing.assert_allclose(radius, 1.0, atol=0.01)


def test_extract_skips_the_cells_outside_the_mask() -> None:
    grid = ts.Grid.cube(24, bound=1.3)
    phi = ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64)
    whole = tsm.extract(phi, grid)
    everywhere = tsm.extract(phi, grid, mask=torch.ones_like(phi, dtype=torch.bool))
    np.testing.assert_array_equal(whole.faces, everywhere.faces)
    # nodes at x > 0.3 unknown and filled with a wrong sign: no surface there, none made up
    known = grid.points(dtype=torch.float64)[..., 0][None, None] <= 0.3
    half = tsm.extract(torch.where(known, phi, -1.0), grid, mask=known)
    assert 0 < len(half.faces) < len(whole.faces)
    assert half.vertices[:, 0].max() <= 0.3 + 1e-9
    assert np.abs(np.linalg.norm(half.vertices, axis=1) - 1).max() < 0.1 * grid.spacing
    with pytest.raises(ValueError, match="mask"):
        tsm.extract(phi, grid, mask=known.double())


def test_extract_bad_input_raises() -> None:
    grid = ts.Grid.cube(9, bound=1.0)
    phi = ts.sdf.sphere(grid, radius=0.5)
    with pytest.raises(ValueError, match="phi must hold one surface"):
        tsm.extract(torch.cat((phi, phi)), grid)
    with pytest.raises(ValueError, match="phi never crosses"):
        tsm.extract(phi, grid, level=5.0)
    with pytest.raises(ValueError, match="phi"):
        tsm.extract(phi[0], grid)


def test_extract_refuses_a_level_that_is_only_touched() -> None:
    """phi reaching the level at nodes without crossing it gave a mesh of one vertex and no
    face, or scikit-image's bare RuntimeError."""
    grid = ts.Grid((8, 8, 8), 1.0)
    points = grid.points(torch.float64)
    with pytest.raises(ValueError, match="never crosses the level 0, it only touches it"):
        tsm.extract((points - 3).norm(dim=-1)[None, None], grid)
    # |x| on a node plane (an unsigned distance) gave two coincident sheets wound both ways
    for touching in (-(points[..., 0] - 3).abs(), (points[..., 0] - 3).abs(),
                     ts.sdf.box(grid, half_size=(2.0, 2.0, 2.0), center=(3.0, 3.0, 3.0),
                                dtype=torch.float64)[0, 0].abs()):
        with pytest.raises(ValueError, match="never crosses the level 0, it only touches it"):
            tsm.extract(touching[None, None], grid)
    wide = ts.Grid((12, 12, 12), 1.0)
    x = wide.points(torch.float64)[..., 0]
    known = ((x <= 2) | (x >= 9))[None, None]
    with pytest.raises(ValueError, match="in any cell .*on the known nodes"):
        tsm.extract((x - 5.5)[None, None], wide, mask=known)


def test_fit_grid_holds_the_mesh_with_margin() -> None:
    mesh = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    grid = tsm.fit_grid(mesh, 41, margin=0.25)
    assert grid.shape == (41, 41, 41)
    assert grid.spacing == pytest.approx(2.0 * 1.5 / 40)
    assert bool(grid.contains(torch.from_numpy(mesh.vertices).float()).all())
    assert grid.origin[0] == pytest.approx(-1.5)
    with pytest.raises(ValueError, match="resolution"):
        tsm.fit_grid(mesh, 2)


@pytest.mark.parametrize("resolution", [13, 16, 24, 36, 37, 64])
def test_default_grids_leave_three_cells_around_the_shape(resolution: int) -> None:
    # a 10% margin left 1.2 cells at 16^3 and 1.8 at 24^3: MeshAdapter and MeshBatchAdapter
    # then warned that S came within two cells of the faces of the grid they had chosen
    mesh = trimesh.creation.box(extents=(2.0, 1.0, 0.5))
    grid = tsm.fit_grid(mesh, resolution)
    free = (grid.origin[0] + 1.0) / -grid.spacing
    assert free == pytest.approx(max(3.0, 0.1 * (resolution - 1) / 1.2))
    sphere = trimesh.creation.icosphere(subdivisions=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ts.MeshAdapter(sphere, resolution=resolution, dtype=torch.float64)
        batch = ts.MeshBatchAdapter([sphere, ts.AnalyticShape("torus")], resolution=resolution,
                                    dtype=torch.float64)
    free = (batch.grid.origin[0] + 0.5) / -batch.grid.spacing
    assert free >= 3 - 1e-9 and (resolution < 27 or free == pytest.approx(
        0.15 * (resolution - 1) / 1.3))


def test_load_errors_name_the_mesh(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="mesh is empty"):
        tsm.load((np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)))
    with pytest.raises(ValueError, match="faces must be triangles"):
        tsm.load((np.eye(4, 3), np.array([[0, 1, 2, 3]])))
    with pytest.raises(FileNotFoundError, match="mesh"):
        tsm.load(tmp_path / "missing.obj")
    mesh = trimesh.creation.icosphere(subdivisions=1)
    assert tsm.load(mesh) is mesh


def round_trip_error(resolution: int, subdivisions: int) -> float:
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    adapter = tsm.MeshAdapter(mesh, tsm.fit_grid(mesh, resolution, 0.2), dtype=torch.float64)
    v = adapter.vertices
    values = torch.stack((v[:, 0] * v[:, 1] + v[:, 2], torch.sin(2 * v[:, 0])))[None]
    return float((adapter.decode(adapter.encode(values)) - values).abs().max())


def test_round_trip_is_second_order() -> None:
    # mesh refined with the grid, so that its facets shrink with h too
    coarse = round_trip_error(33, 4)
    fine = round_trip_error(65, 5)
    order = math.log2(coarse / fine)
    assert order > 1.7, (coarse, fine, order)


def test_a_triangle_soup_round_trips_like_the_merged_mesh() -> None:
    """Each face with its own three vertices (as STL stores a mesh), passed as arrays: vertices
    at one position are one hat function, so the soup decodes as the merged mesh does (its
    duplicates had been counted apart, past ``HAT_LIMIT``: 4.7e-3 against 1.6e-5), on dense
    volumes and on bricks."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    soup = (mesh.vertices[mesh.faces].reshape(-1, 3), np.arange(3 * len(mesh.faces)).reshape(-1, 3))
    grid = ts.Grid.cube(44, bound=43 * 1.2 / 39)  # spacing 2.4 / 39, room for the bricks' band

    def smooth(v: torch.Tensor) -> torch.Tensor:
        return torch.sin(2 * v[:, 0]) * torch.cos(v[:, 1]) + v[:, 2] ** 2

    errors = []
    for given in (mesh, soup):
        dense = tsm.MeshAdapter(given, grid, dtype=torch.float64)
        values = smooth(dense.vertices)[None, None]
        errors.append(float((dense.decode(dense.encode(values)) - values).abs().max()))
        bricks = ts.bricks.BrickMeshAdapter([given], [grid], dtype=torch.float64)
        values = [smooth(bricks.vertices[0])[:, None]]
        errors.append(float((bricks.decode(bricks.encode(values))[0] - values[0]).abs().max()))
    assert max(errors) < 5e-5, errors


@pytest.fixture(scope="module")
def adapter() -> tsm.MeshAdapter:
    return tsm.MeshAdapter(trimesh.creation.icosphere(subdivisions=2), resolution=25,
                           dtype=torch.float64)


def test_adapter_shapes_and_band(adapter: tsm.MeshAdapter) -> None:
    vertices = len(adapter.vertices)
    values = torch.randn(2, 3, vertices, dtype=torch.float64)
    volume = adapter.encode(values)
    assert volume.shape == (2, 3, 25, 25, 25)
    assert adapter.decode(volume).shape == (2, 3, vertices)
    assert (volume[:, :, ~adapter.band_mask[0, 0]] == 0).all()
    assert adapter.band_mask.sum() > 0
    assert adapter.phi.shape == (1, 1, 25, 25, 25)
    torch.testing.assert_close(adapter(values), volume)


def test_encode_is_constant_along_normals() -> None:
    adapter = tsm.MeshAdapter(trimesh.creation.icosphere(subdivisions=4), resolution=25,
                              dtype=torch.float64)
    direction = adapter.vertices / adapter.vertices.norm(dim=1, keepdim=True)
    volume = adapter.encode(direction[:, 2][None, None])  # z / |z|: constant along rays
    points = adapter.grid.points(dtype=torch.float64)
    band = adapter.band_mask[0, 0] & (points.norm(dim=-1) > 0.3)
    expected = points[..., 2] / points.norm(dim=-1)
    assert (volume[0, 0][band] - expected[band]).abs().max() < 0.03  # facets of about 0.08


def test_encode_decode_gradcheck() -> None:
    adapter = tsm.MeshAdapter(trimesh.creation.icosphere(subdivisions=0), resolution=9,
                              dtype=torch.float64)
    values = torch.randn(1, 1, len(adapter.vertices), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda u: adapter.decode(adapter.encode(u)), (values,))


def test_to_band_matches_the_adapter(adapter: tsm.MeshAdapter) -> None:
    values = torch.randn(1, 2, len(adapter.vertices), dtype=torch.float64)
    mesh = trimesh.creation.icosphere(subdivisions=2)
    torch.testing.assert_close(tsm.to_band(values, mesh, adapter.grid), adapter.encode(values))


def test_adapter_bad_values_raise(adapter: tsm.MeshAdapter) -> None:
    with pytest.raises(ValueError, match="values"):
        adapter.encode(torch.zeros(1, 1, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="volume"):
        adapter.decode(torch.zeros(1, 25, 25, 25, dtype=torch.float64))


def test_adapter_refuses_data_of_another_dtype(adapter: tsm.MeshAdapter) -> None:
    """float32 data on a float64 adapter came back float32 through float64 weights cast down
    (and float64 data on a float32 adapter through float32 weights), silently."""
    values = torch.zeros(1, 1, len(adapter.vertices))
    with pytest.raises(ts.MismatchError, match=r"values is torch.float32 .* adapter is torch.float64"):
        adapter.encode(values)
    volume = adapter.encode(values.double())
    with pytest.raises(ts.MismatchError, match=r"volume is torch.float32 .* adapter is torch.float64"):
        adapter.decode(volume.float())


TETRAHEDRON = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n{extra}f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n{faces}"


@pytest.mark.parametrize(
    ("extra", "faces", "match"),
    [
        ("v nan 0 0\n", "f 5 2 3\n", r"mesh \(.*\): vertices must be finite.*vertex 4"),
        ("v 0 inf 0\n", "f 5 2 3\n", r"mesh \(.*\): vertices must be finite"),
        ("", "f 9 2 3\n", r"mesh: .*could not read"),
    ],
)
def test_bad_mesh_file_refused_before_trimesh_drops_anything(tmp_path, extra, faces, match):
    """trimesh's processing drops a NaN vertex and its faces; the raw arrays are checked first."""
    path = tmp_path / "bad.obj"
    path.write_text(TETRAHEDRON.format(extra=extra, faces=faces))
    with pytest.raises(ValueError, match=match):
        tsm.load(path)
    with pytest.raises(ValueError, match=match):
        ts.sdf.from_mesh(path, ts.Grid.cube(9, 1.5))


def test_mesh_file_without_faces_refused(tmp_path):
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(ValueError, match=r"mesh \(.*\) is empty"):
        tsm.load(path)


def test_good_mesh_file_still_merged_like_trimesh(tmp_path):
    path = tmp_path / "sphere.stl"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    loaded, reference = tsm.load(path), trimesh.load(path, force="mesh")
    np.testing.assert_array_equal(loaded.vertices, reference.vertices)
    np.testing.assert_array_equal(loaded.faces, reference.faces)


@pytest.mark.parametrize(
    ("vertices", "faces", "match"),
    [
        (np.zeros((3, 3)), np.zeros((0, 3), dtype=np.int64), "mesh is empty"),
        (np.eye(3), np.array([[0, 1, 3]]), r"face indices must lie in \[0, 2\]"),
        (np.eye(3), np.array([[-1, 1, 2]]), r"face indices must lie in \[0, 2\]"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]]), np.array([[0, 1, 2]]),
         "vertices must be finite.*vertex 2"),
        (np.eye(3), np.array([[0.0, 1.0, 2.0]]), "faces must hold integer"),
    ],
)
def test_bad_mesh_arrays_refused(vertices, faces, match):
    with pytest.raises(ValueError, match=match):
        ts.sdf.from_mesh((vertices, faces), ts.Grid.cube(9, 1.5))


@pytest.mark.parametrize("dtype", [torch.int64, torch.float16])
def test_mesh_dtype_refused_before_any_work(dtype):
    sphere = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(TypeError, match="dtype must be"):
        ts.sdf.from_mesh(sphere, ts.Grid.cube(9, 1.5), dtype=dtype)
    with pytest.raises(TypeError, match="dtype must be"):
        tsm.MeshAdapter(sphere, ts.Grid.cube(9, 1.5), dtype=dtype)


def _spot_like() -> trimesh.Trimesh:
    """A fixed mesh finer than the grids below but with visible facets: icosphere(4), r = 1."""
    return trimesh.creation.icosphere(subdivisions=4)


def _transfer_error(order: int, resolution: int, function, reextend: bool = False  # noqa: ANN001
                    ) -> float:
    mesh = _spot_like()
    adapter = tsm.MeshAdapter(mesh, tsm.fit_grid(mesh, resolution, 0.2), dtype=torch.float64,
                              order=order)
    values = function(adapter.vertices)[None, None]
    volume = adapter.encode(values)
    if reextend:  # what every flow does to its data before returning it
        volume = CubicStencil(adapter.surface, adapter.band_mask).apply(volume)
    decoded = adapter.decode(volume)
    return float((decoded - values).abs().max() / values.abs().max())


def test_order_two_reproduces_affine_functions_where_trilinear_does_not() -> None:
    # Affine data is affine at every closest point, so the order-2 weights return it exactly (to
    # their regularisation); trilinear weights average closest points that bend at every edge.
    def affine(v):  # noqa: ANN001, ANN202
        return 0.3 * v[:, 0] - 0.7 * v[:, 1] + 0.2 * v[:, 2] + 2.0

    # measured: order 2 2.9e-5, order 1 7.4e-4
    assert _transfer_error(2, 33, affine) < 1e-4
    assert _transfer_error(1, 33, affine) > 4e-4


def test_order_two_round_trip_beats_trilinear_on_a_fixed_mesh() -> None:
    def smooth(v):  # noqa: ANN001, ANN202
        return torch.sin(2 * v[:, 0] + v[:, 1]) * torch.cos(1.5 * v[:, 2])

    first = [_transfer_error(1, n, smooth) for n in (33, 65)]
    second = [_transfer_error(2, n, smooth) for n in (33, 65)]
    # measured: order 1 8.0e-3, 3.9e-3; order 2 2.0e-3, 1.1e-3
    assert second[0] < first[0] / 3 and second[1] < first[1] / 3, (first, second)
    # after a tricubic closest-point re-extension, as a flow leaves it: 7.9e-3 against 1.9e-3
    assert _transfer_error(2, 33, smooth, True) < _transfer_error(1, 33, smooth, True) / 3


@pytest.mark.parametrize(("subdivisions", "resolution"), [(1, 40), (2, 48)])
def test_order_two_returns_piecewise_linear_data_on_coarse_facets(subdivisions: int,
                                                                    resolution: int) -> None:
    # facets spanning several cells: what encode writes (the piecewise-linear interpolant of
    # the vertex values) comes back at every vertex, whatever the values, as a cotangent
    # method's own representation would; measured 3.6e-6 and 3.6e-6 (8e-4 and 1e-3 when the
    # weights reproduced affine functions of the closest points only)
    mesh = trimesh.creation.icosphere(subdivisions=subdivisions)
    adapter = tsm.MeshAdapter(mesh, resolution=resolution, dtype=torch.float64)
    generator = torch.Generator().manual_seed(subdivisions)
    values = torch.rand(2, 1, len(mesh.vertices), generator=generator, dtype=torch.float64)
    error = (adapter.decode(adapter.encode(values)) - values).abs().max()
    assert error < 5e-5, float(error)


def test_order_two_converges_at_second_order_on_a_fine_fixed_mesh() -> None:
    # icosphere(5): facets (0.04) smaller than the cells, the mesh held fixed
    mesh = trimesh.creation.icosphere(subdivisions=5)
    error = []
    for resolution in (17, 33):
        adapter = tsm.MeshAdapter(mesh, tsm.fit_grid(mesh, resolution, 0.2), dtype=torch.float64)
        v = adapter.vertices
        values = (torch.sin(2 * v[:, 0] + v[:, 1]) * torch.cos(1.5 * v[:, 2]))[None, None]
        error.append(float((adapter.decode(adapter.encode(values)) - values).abs().max()))
    assert math.log2(error[0] / error[1]) > 1.6, error


def test_order_two_decode_gradcheck_and_errors() -> None:
    adapter = tsm.MeshAdapter(trimesh.creation.icosphere(subdivisions=1), resolution=9,
                              dtype=torch.float64)
    volume = torch.randn(1, 2, 9, 9, 9, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(adapter.decode, (volume,))
    with pytest.raises(ValueError, match="volume"):
        adapter.decode(torch.zeros(1, 1, 8, 9, 9, dtype=torch.float64))
    with pytest.raises(ValueError, match="order"):
        tsm.MeshAdapter(trimesh.creation.icosphere(subdivisions=1), resolution=9, order=3)
    big = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(ValueError, match="outside the grid"):
        tsm.MeshAdapter(big, ts.Grid.cube(17, bound=0.95))


MESH_DIR = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "meshes"


@pytest.mark.parametrize("order", [1, 2])
def test_decoding_reads_nothing_beyond_the_band(order: int) -> None:
    """Nodes beyond a narrow band carry weight 0: marking them NaN or infinite (unknown
    values) must not reach a vertex (0 * NaN is NaN)."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    grid = tsm.fit_grid(mesh, 33)
    adapter = tsm.MeshAdapter(mesh, grid, band_width=2 * grid.spacing, dtype=torch.float64,
                              order=order)
    volume = adapter.encode(adapter.vertices[:, 2][None, None])
    expected = adapter.decode(volume)
    for mark in (float("nan"), float("inf")):
        assert torch.equal(adapter.decode(volume.masked_fill(~adapter.band_mask, mark)),
                           expected)


@pytest.mark.parametrize("name", ["fandisk.obj", "teapot.obj"])
def test_order_two_decode_does_not_amplify_data_on_flat_parts(name: str) -> None:
    """Where a vertex's taps read many small coplanar facets, its hat-reproducing weights
    reached a 1-norm of 47-59 at 64^3 and uniform noise in [0, 1] decoded to [-0.53, 1.28]
    (fandisk) and [-0.11, 1.03] (teapot); such vertices keep the affine-reproducing weights."""
    path = Path(os.environ.get("TORCHSURF_MESH_DIR", MESH_DIR)) / name
    if not path.is_file():
        pytest.skip(f"test mesh {name} not found (set TORCHSURF_MESH_DIR)")
    adapter = tsm.MeshAdapter(trimesh.load(path, force="mesh"), resolution=64)
    volume = torch.rand((1, 1, *adapter.grid.shape), generator=torch.Generator().manual_seed(0))
    decoded = adapter.decode(volume)
    assert float(decoded.min()) > -0.06 and float(decoded.max()) < 1.06, (
        float(decoded.min()), float(decoded.max()))
    constant = adapter.decode(torch.full_like(volume, 2.0))
    # the weights sum to 1 exactly (the Tikhonov term left them up to 5e-4 off)
    assert float((constant - 2.0).abs().max()) < 1e-5


@pytest.mark.parametrize(("name", "resolution"), [("teapot.obj", 33), ("bunny_closed.obj", 33)])
def test_order_two_decodes_constants_exactly(name: str, resolution: int) -> None:
    path = Path(os.environ.get("TORCHSURF_MESH_DIR", MESH_DIR)) / name
    if not path.is_file():
        pytest.skip(f"test mesh {name} not found (set TORCHSURF_MESH_DIR)")
    adapter = tsm.MeshAdapter(trimesh.load(path, force="mesh"), resolution=resolution,
                              dtype=torch.float64)
    ones = torch.ones((1, 1, *adapter.grid.shape), dtype=torch.float64)
    assert float((adapter.decode(ones) - 1).abs().max()) < 1e-12


def test_order_two_weights_do_not_depend_on_the_mesh_scale() -> None:
    """A band node whose closest point lies on an edge reads the corner opposite it with
    weight 0; libigl breaks the tie between the edge's two triangles by rounding, and
    counting that corner moved two of spot's vertices across HAT_LIMIT at scales 0.37 and 3
    (1e-3 before libigl's queries were centred on the mesh): weights 0.093 off, decoded heat
    3e-3 off."""
    path = Path(os.environ.get("TORCHSURF_MESH_DIR", MESH_DIR)) / "spot.obj"
    if not path.is_file():
        pytest.skip("test mesh spot.obj not found (set TORCHSURF_MESH_DIR)")
    mesh = trimesh.load(path, process=False)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    reference = tsm.MeshAdapter((vertices, faces), resolution=40, dtype=torch.float64)
    for scale in (0.37, 3.0):
        scaled = tsm.MeshAdapter((vertices * scale, faces), resolution=40, dtype=torch.float64)
        assert torch.equal(scaled._decode_index, reference._decode_index)
        difference = float((scaled._decode_weights - reference._decode_weights).abs().max())
        assert difference < 1e-10, (scale, difference)


def test_order_two_weights_are_solved_by_chunks_of_vertices(monkeypatch) -> None:
    """The decoding weights are solved ``DECODE_CHUNK`` vertices at a time (all of
    bunny_closed's 35k vertices at once peaked 1.8 GB whatever the grid): chunks of 7 vertices
    give the weights of one solve to rounding (batched solves of other sizes round
    differently), hat functions and all."""
    from torchsurf import _vertex_decode

    path = Path(os.environ.get("TORCHSURF_MESH_DIR", MESH_DIR)) / "spot.obj"
    if not path.is_file():
        pytest.skip("test mesh spot.obj not found (set TORCHSURF_MESH_DIR)")
    mesh = trimesh.load(path, force="mesh")
    monkeypatch.setattr(_vertex_decode, "DECODE_CHUNK", 10**9)
    whole = tsm.MeshAdapter(mesh, resolution=24, dtype=torch.float64)
    monkeypatch.setattr(_vertex_decode, "DECODE_CHUNK", 7)
    chunked = tsm.MeshAdapter(mesh, resolution=24, dtype=torch.float64)
    assert torch.equal(chunked._decode_index, whole._decode_index)
    difference = float((chunked._decode_weights - whole._decode_weights).abs().max())
    assert difference < 1e-12, difference
    assert float(whole._decode_weights.abs().sum(dim=1).max()) > 1.0  # corrected, not trilinear


def test_a_band_too_narrow_for_the_decoding_is_refused() -> None:
    # at 0.3 h an encoded constant decoded to [0, 0.885] and at 0.01 h the build crashed
    mesh = trimesh.creation.icosphere(subdivisions=2)
    grid = tsm.fit_grid(mesh, 24)
    for order in (1, 2):
        with pytest.raises(ValueError, match="band_width must be at least sqrt"):
            tsm.MeshAdapter(mesh, grid, band_width=1.5 * grid.spacing, order=order)
    with pytest.raises(ValueError, match="order must be one of"):
        tsm.MeshAdapter(mesh, grid, order=True)
    with pytest.raises(ValueError, match="sign must be one of"):
        tsm.MeshAdapter(mesh, grid, sign="windng")
    adapter = tsm.MeshAdapter(mesh, grid, band_width=1.8 * grid.spacing, order=1)
    ones = torch.ones(1, 1, len(mesh.vertices))
    assert float((adapter.decode(adapter.encode(ones)) - 1).abs().max()) < 1e-5


def test_decoding_on_a_grid_that_cuts_the_mesh_names_the_mesh() -> None:
    """order=1's decode named ``points``, an argument the caller never passed; it names the mesh
    as order=2 does when built (order=1 still encodes there: to_band on part of a mesh)."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    grid = ts.Grid.cube(21, bound=0.9)
    message = r"mesh: 42 of 162 vertices lie outside the grid's box.*decode reads the grid"
    with pytest.raises(ValueError, match=message):
        tsm.MeshAdapter(mesh, grid, order=2)
    adapter = tsm.MeshAdapter(mesh, grid, order=1)
    volume = adapter.encode(torch.ones(1, 1, len(mesh.vertices)))
    with pytest.raises(ValueError, match=message):
        adapter.decode(volume)


def test_a_vertex_no_face_uses_is_named_when_it_leaves_the_box() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    stray = trimesh.Trimesh(np.vstack([mesh.vertices, [[5.0, 0.0, 0.0]]]), mesh.faces,
                            process=False)
    with pytest.raises(ValueError, match="no face uses.*remove_unreferenced_vertices"):
        tsm.MeshAdapter(stray, resolution=17)


def test_a_vertex_no_face_uses_inside_the_box_is_warned_about() -> None:
    from torchsurf import bricks

    mesh = trimesh.creation.icosphere(subdivisions=2)
    stray = trimesh.Trimesh(np.vstack([mesh.vertices, [[0.5, 0.0, 0.0]]]), mesh.faces,
                            process=False)
    for order in (1, 2):
        with pytest.warns(RuntimeWarning, match="1 of 163 vertices are used by no face"):
            tsm.MeshAdapter(stray, resolution=17, order=order)
    with pytest.warns(RuntimeWarning, match=r"meshes\[1\]: 1 of 163"):
        bricks.BrickMeshAdapter([mesh, stray], [ts.Grid.cube(33, 1.5)] * 2)


def test_to_band_encodes_on_a_grid_holding_part_of_the_mesh() -> None:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    grid = ts.Grid((17, 17, 9), spacing=2.4 / 16, origin=(-1.2, -1.2, -1.2))  # x up to 0
    values = torch.as_tensor(mesh.vertices[:, 2], dtype=torch.float32)[None, None]
    volume = tsm.to_band(values, mesh, grid)
    assert volume.shape == (1, 1, 17, 17, 9) and bool(torch.isfinite(volume).all())


def test_long_facets_beside_small_ones_come_back_where_the_data_bends(monkeypatch) -> None:
    """A capsule's side is one strip of triangles many cells long, its caps many small ones:
    the seam vertices read more than HAT_LIMIT vertices, and their weights reproduced affine
    functions only, which do not follow the piecewise-linear data's bend at the strip's far
    corners (trimesh's default capsule at 32^3: 8.8e-2 of the range off at the seams). The
    hats of the vertices read from beyond FAR_CELLS are now reproduced too: here 8.0e-3 / 2.5e-3
    at 32^3 / 48^3 against 4.0e-2 / 2.4e-2."""
    from torchsurf import _vertex_decode

    mesh = trimesh.creation.capsule(height=1.4, radius=0.3, count=(24, 24))
    values = torch.as_tensor(np.cos(3.0 * mesh.vertices[:, 2] + mesh.vertices[:, 0]))[None, None]

    def error(resolution: int) -> float:
        adapter = tsm.MeshAdapter(mesh, resolution=resolution, dtype=torch.float64)
        back = adapter.decode(adapter.encode(values))
        return float((back - values).abs().max() / values.abs().max())

    now = [error(n) for n in (32, 48)]
    monkeypatch.setattr(_vertex_decode, "FAR_CELLS", math.inf)
    affine = [error(n) for n in (32, 48)]
    assert now[0] < affine[0] / 2 and now[1] < affine[1] / 2, (now, affine)


def test_extract_is_watertight_where_the_level_passes_through_nodes() -> None:
    """A torus extracted at a level its phi holds at two nodes, where S crosses: marching cubes
    read those nodes as on the level and left a one-triangle hole (Euler number -2)."""
    grid = ts.Grid((21, 23, 25), 0.1, (-1.2, -1.1, -1.0))
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    phi = torch.sqrt((torch.sqrt(x**2 + y**2) - 0.6) ** 2 + z**2)[None, None]
    level = float(phi[0, 0, 12, 13, 6])
    assert int((phi == level).sum()) == 2
    mesh = tsm.extract(phi, grid, level=level)
    assert mesh.is_watertight and mesh.euler_number == 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("sign, offset", [(1.0, 0.0), (-1.0, 0.0), (1.0, 0.3), (-1.0, -0.3)])
def test_extract_keeps_a_box_whose_faces_lie_on_node_planes(dtype, sign, offset) -> None:
    """In float64 the faces' nodes held +-1e-16, and cells with three such corners were cut
    across: 8% of the area lost (float32 rounded them to 0 and was exact). Put always below
    the level, -phi's box lost 12% (its inside above); float32's rounding of phi + 0.3 at
    level 0.3, the same."""
    grid = ts.Grid.cube(25, 1.2)
    h = grid.spacing
    phi = sign * ts.sdf.box(grid, half_size=(6 * h, 4 * h, 5 * h), dtype=dtype) + offset
    mesh = tsm.extract(phi, grid, level=offset)
    sides = 2 * torch.tensor([6 * h, 4 * h, 5 * h], dtype=torch.float64)
    area = 2 * float(sides[0] * sides[1] + sides[1] * sides[2] + sides[0] * sides[2])
    assert mesh.is_watertight
    assert mesh.area == pytest.approx(area, rel=1e-9)
    assert sign * mesh.volume == pytest.approx(float(sides.prod()), rel=1e-9)  # outward: +


def test_extract_names_a_level_crossed_only_within_rounding() -> None:
    """Every node snapped to one side: scikit-image's 'Surface level must be within volume
    data range' reached the user."""
    phi = -torch.ones(1, 1, 5, 5, 5, dtype=torch.float64)
    phi[0, 0, 2, 2, 2] = 1e-13
    with pytest.raises(ValueError, match="phi never crosses the level 0"):
        tsm.extract(phi, ts.Grid((5, 5, 5), 1.0))


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_extract_closes_a_cross_of_bars_on_node_planes(sign) -> None:
    """Concave edges where the bars meet: nodes on the level deciding their side one by one
    took different sides there, and 31 edges joined four faces."""
    grid = ts.Grid.cube(25, 1.2)
    h = grid.spacing
    points = grid.points(dtype=torch.float64)

    def bar(half_size):
        q = points.abs() - torch.tensor(half_size, dtype=torch.float64)
        return q.clamp(min=0).norm(dim=-1) + q.max(dim=-1).values.clamp(max=0)

    cross = torch.minimum(torch.minimum(bar((8 * h, 2 * h, 2 * h)), bar((2 * h, 8 * h, 2 * h))),
                          bar((2 * h, 2 * h, 8 * h)))
    mesh = tsm.extract(sign * cross[None, None], grid)
    assert mesh.is_watertight
    # its convex edges kept, its concave ones cut across a cell: 3.2% short, either sign
    assert 0.96 * 672 * h**2 < mesh.area < 0.975 * 672 * h**2
