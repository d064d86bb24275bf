"""Mesh input: degenerate faces, meshes with no inside on the grid, what trimesh hides."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
import trimesh

import torchsurf as ts
from torchsurf import _mesh_sdf


@pytest.fixture(scope="module")
def icosphere() -> tuple[np.ndarray, np.ndarray]:
    mesh = trimesh.creation.icosphere(subdivisions=2)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


GRID = ts.Grid.cube(17, 1.5)


def test_degenerate_faces_on_the_surface_change_nothing(icosphere):
    vertices, faces = icosphere
    reference = ts.sdf.from_mesh((vertices, faces), GRID)
    a, b = faces[0, 0], faces[0, 1]  # an edge of the mesh
    repeated = np.vstack([faces, [[a, a, b]]])
    torch.testing.assert_close(ts.sdf.from_mesh((vertices, repeated), GRID), reference)
    midpoint = np.vstack([vertices, (vertices[a] + vertices[b]) / 2])
    sliver = np.vstack([faces, [[a, b, len(vertices)]]])  # three collinear corners
    torch.testing.assert_close(ts.sdf.from_mesh((midpoint, sliver), GRID), reference)
    adapter = ts.MeshAdapter((vertices, repeated), GRID)
    values = torch.from_numpy(vertices[:, 2]).float()[None, None]
    assert adapter.encode(values).shape == (1, 1, *GRID.shape)


@pytest.mark.parametrize("layout", ["dense", "bricks"])
def test_zero_area_faces_on_the_edges_encode_as_the_clean_mesh(layout):
    """A zero-area face on an edge may be the closest face of points on that edge (libigl
    returns either face of a tie); its weights went all to the nearest corner, and vertex data
    read there stepped by half an edge: 0.14 at 3% of a sphere's band at 40^3 (an audit,
    2026-12-07). Now linear along the edge, as the edge's own faces give."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    vertices, faces, edges = np.asarray(mesh.vertices), np.asarray(mesh.faces), mesh.edges_unique
    slivers = np.stack([edges[:, 0], edges[:, 0], edges[:, 1]], axis=1)  # (a, a, b)
    flat = np.stack([edges[:, 0], edges[:, 1], edges[:, 0]], axis=1)[::2]  # (a, b, a)
    dirty = (vertices, np.concatenate([faces, slivers, flat]))
    values = torch.from_numpy(vertices.T[None].copy())  # x, y, z: linear data, (1, 3, V)
    if layout == "bricks":
        values = [values[0].T]  # one (V, C) per mesh
    grid = ts.Grid.cube(40, 2.2)  # 5 cells between the band and the faces, as bricks need
    adapter = ts.MeshAdapter if layout == "dense" else ts.bricks.BrickMeshAdapter
    clean, with_slivers = (adapter(m, grid, dtype=torch.float64) for m in (mesh, dirty))
    torch.testing.assert_close(with_slivers.encode(values), clean.encode(values),
                               rtol=0, atol=1e-12)


def test_weights_on_a_zero_area_face_are_linear_along_its_longest_edge():
    corners = np.array([[[0.0, 0, 0], [0.0, 0, 0], [2.0, 0, 0]],   # two corners coincide
                        [[0.0, 0, 0], [2.0, 0, 0], [0.5, 0, 0]],   # three collinear corners
                        [[1.0, 1, 1], [1.0, 1, 1], [1.0, 1, 1]]])  # a point
    points = np.array([[0.5, 0, 0], [1.5, 0, 0], [1.0, 1, 1]])
    weights = _mesh_sdf._on_longest_edge(corners, points)
    np.testing.assert_allclose((weights[:, :, None] * corners).sum(axis=1), points)
    assert (weights >= 0).all() and np.allclose(weights.sum(axis=1), 1.0)
    np.testing.assert_allclose(weights[1], [0.25, 0.75, 0.0])  # between the far ends only


@pytest.mark.parametrize(
    "arrays",
    [(np.eye(3), np.array([[0, 0, 1], [1, 2, 2]])),
     (np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]))],
)
def test_a_mesh_of_degenerate_faces_only_is_refused(arrays):
    for make in (ts.sdf.from_mesh, ts.MeshAdapter):
        with pytest.raises(ValueError, match="mesh has no area: all its . faces are degenerate"):
            make(arrays, GRID)


@pytest.mark.parametrize(
    ("arrays", "match"),
    [((np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]])),
      r"no node of the grid lies inside it \(the mesh spans x \[0, 1\].*the grid x \[-1.5, 1.5\]"),
     (lambda v, f: (v + 10, f), r"no node of the grid lies inside it \(the mesh spans x \[9"),
     (lambda v, f: (v * 10, f), "every node of the grid lies inside it"),
     ],
)
def test_meshes_with_no_surface_on_the_grid_are_named(icosphere, arrays, match):
    arrays = arrays(*icosphere) if callable(arrays) else arrays
    for make in (ts.sdf.from_mesh, ts.MeshAdapter):
        with pytest.raises(ValueError, match=match):
            make(arrays, GRID)


@pytest.mark.parametrize("build", ["dense", "bricks"])
def test_a_plate_thinner_than_a_cell_names_the_spacing(build):
    # a 0.03-thick plate between the nodes of a 0.0345 spacing: no node inside
    plate = trimesh.creation.box(extents=(0.6, 0.6, 0.03))
    grid = ts.Grid.cube(30, 0.5)
    make = ts.sdf.from_mesh if build == "dense" else ts.bricks.from_mesh
    name = "mesh" if build == "dense" else r"meshes\[0\]"
    with pytest.raises(ValueError, match=rf"^{name}: no node of the grid lies inside it .*"
                                         r"thinner than the grid's spacing \(h = 0.03448\)"):
        make(plate, grid)
    make(plate, ts.Grid.cube(60, 0.5))  # resolved at half the spacing


def test_nan_vertices_are_caught_unless_trimesh_already_dropped_them(icosphere, tmp_path):
    vertices, faces = icosphere
    broken = vertices.copy()
    broken[5] = np.nan
    for mesh in ((broken, faces), trimesh.Trimesh(broken, faces, process=False)):
        with pytest.raises(ValueError, match="vertices must be finite.*vertex 5"):
            ts.sdf.from_mesh(mesh, GRID)
    path = tmp_path / "broken.obj"
    trimesh.Trimesh(broken, faces, process=False).export(path)
    with pytest.raises(ValueError, match="vertices must be finite"):
        ts.sdf.from_mesh(path, GRID)
    # trimesh's default processing drops the vertex and its faces before torchsurf sees them
    processed = trimesh.Trimesh(broken, faces)
    assert len(processed.vertices) == len(vertices) - 1


def _flipped(faces: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    faces = faces.copy()
    faces[chosen] = faces[chosen][:, ::-1]
    return faces


@pytest.mark.parametrize("size", [1e-8, 1.0, 300.0])
def test_a_mesh_file_merges_duplicates_at_a_distance_relative_to_its_size(size, tmp_path):
    """trimesh merges a file's vertices closer than 1e-8 world units: a mesh 1e-7 across, written
    at full precision, came back with 95 of its 2930 vertices (and phi 2 cells off) without a
    word (this one, 2e-8 across, with 20 of 162). Now the merge is relative: every vertex of a
    small mesh is kept, and the duplicates of a triangle soup are merged at any size."""
    mesh = trimesh.creation.icosphere(subdivisions=2)
    vertices, faces = np.asarray(mesh.vertices) * size + 0.3 * size, np.asarray(mesh.faces)

    def written(name: str, points: np.ndarray, triangles: np.ndarray) -> str:
        lines = [f"v {x!r} {y!r} {z!r}" for x, y, z in points.tolist()]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in triangles.tolist()]
        path = tmp_path / name
        path.write_text("\n".join(lines) + "\n")
        return str(path)

    loaded = ts.mesh.load(written("indexed.obj", vertices, faces))
    assert len(loaded.vertices) == len(vertices)
    np.testing.assert_array_equal(np.asarray(loaded.vertices), vertices)
    soup = ts.mesh.load(written("soup.obj", vertices[faces.reshape(-1)],
                                np.arange(3 * len(faces)).reshape(-1, 3)))
    assert len(soup.vertices) == len(vertices)


@pytest.mark.parametrize("which", ["random quarter", "half x > 0"])
def test_faces_wound_against_their_neighbours_are_reoriented(which):
    """An icosphere with some faces flipped: the winding number of such a mesh is meaningless
    (with a random quarter flipped, 72% of the inside was signed outside, without a word). The
    faces are re-oriented before signing, with a warning, and phi equals the clean mesh's."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    if which == "random quarter":
        chosen = np.random.default_rng(0).random(len(faces)) < 0.25
    else:
        chosen = mesh.triangles_center[:, 0] > 0
    grid = ts.Grid.cube(24, 1.5)
    clean = ts.sdf.from_mesh((vertices, faces), grid, dtype=torch.float64)
    with pytest.warns(RuntimeWarning, match="wound against their neighbours") as caught:
        phi = ts.sdf.from_mesh((vertices, _flipped(faces, chosen)), grid, dtype=torch.float64)
    assert caught[0].filename == __file__
    torch.testing.assert_close(phi, clean, atol=1e-12, rtol=0)


@pytest.mark.parametrize("which", ["random quarter", "every face"])
@pytest.mark.parametrize("storage", ["dense", "bricks"])
def test_a_triangle_soup_is_wound_and_closed_by_position(which, storage):
    """A soup (three vertices of its own per face, as STL stores it) shares no vertex index:
    its clashing faces went unseen (a quarter flipped: 4417 of 17,808 inside nodes signed
    outside at 40^3, unwarned) and, every face flipped, it was refused as wound inward under
    sign='auto'. Vertices are now matched by position: the soup's phi is the clean mesh's."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    chosen = (np.random.default_rng(1).random(len(faces)) < 0.25 if which == "random quarter"
              else np.ones(len(faces), dtype=bool))
    flipped = _flipped(faces, chosen)
    soup = (vertices[flipped].reshape(-1, 3), np.arange(3 * len(faces)).reshape(-1, 3))
    grid = ts.Grid.cube(24, 2.0)
    build = ((lambda m: ts.sdf.from_mesh(m, grid, dtype=torch.float64)) if storage == "dense"
             else (lambda m: ts.bricks.from_mesh(m, grid, dtype=torch.float64).phi))
    clean = build((vertices, faces))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        phi = build(soup)
    wound = [w for w in caught if "wound against their neighbours" in str(w.message)]
    assert len(wound) == (1 if which == "random quarter" else 0)
    torch.testing.assert_close(phi, clean, atol=1e-12, rtol=0)


def test_faces_with_a_repeated_vertex_are_neither_clashes_nor_open_edges():
    """Faces ``[a, a, b]`` (zero area, no winding) added to a well-wound closed mesh had
    ``from_mesh`` warn that faces were wound against their neighbours and ask the user to fix
    a winding that was right; the mesh is still closed, signed by pseudonormals, and phi is
    the clean mesh's."""
    mesh = trimesh.creation.icosphere(subdivisions=3)
    vertices, faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    chosen = faces[::9]
    degenerate = np.concatenate([np.stack([chosen[:, 0], chosen[:, 0], chosen[:, 1]], 1),
                                 np.stack([chosen[:, 2], chosen[:, 1], chosen[:, 1]], 1)])
    padded = np.concatenate([faces, degenerate])
    assert _mesh_sdf._wound_against_neighbours(padded, len(vertices)) == 0
    assert _mesh_sdf._is_closed(padded, len(vertices))
    grid = ts.Grid.cube(20, 1.5)
    clean = ts.sdf.from_mesh((vertices, faces), grid, dtype=torch.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        phi = ts.sdf.from_mesh((vertices, padded), grid, dtype=torch.float64)
    torch.testing.assert_close(phi, clean, atol=1e-12, rtol=0)


def test_edges_of_more_than_two_faces_are_not_clashes():
    """Two cubes sharing one edge, each wound consistently: that edge has four faces, two
    traversing it each way, and nothing is re-oriented."""
    first = trimesh.creation.box(extents=(1.0, 1.0, 1.0))
    second = first.copy()
    second.apply_translation((1.0, 1.0, 0.0))
    both = trimesh.util.concatenate([first, second])
    both.merge_vertices()
    assert _mesh_sdf._wound_against_neighbours(np.asarray(both.faces), len(both.vertices)) == 0
    flipped = _flipped(np.asarray(both.faces), np.arange(len(both.faces)) == 0)
    assert _mesh_sdf._wound_against_neighbours(flipped, len(both.vertices)) == 3


def test_two_meshes_for_one_are_named():
    """A list of two meshes is not read as ``(vertices, faces)``: the error says what to use."""
    mesh = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(TypeError, match="mesh must be one mesh.*MeshBatchAdapter"):
        ts.MeshAdapter([mesh, mesh.copy()], resolution=9)
    with pytest.raises(TypeError, match="mesh must be one mesh"):
        ts.sdf.from_mesh([mesh, mesh.copy()], GRID)


def test_misfits_of_mesh_and_grid_and_of_arguments_are_named():
    """Found by an audit: bricks built on a grid inside the mesh failed later, naming no mesh
    (the bricks' fill passed for the outside); one pair (vertices, faces) given as
    MeshBatchAdapter's shapes was read as two shapes and refused as not being a pair; a
    CUDA device on a CPU build failed late in torch; vertices requiring grad were detached."""
    import warnings

    from torchsurf import bricks

    sphere = trimesh.creation.icosphere(subdivisions=2)
    inside = ts.Grid.cube(24, bound=0.45)
    with pytest.raises(ValueError, match=r"meshes\[0\]: every node of the grid lies inside it"):
        bricks.from_mesh([sphere], [inside])
    pair = (np.asarray(sphere.vertices), np.asarray(sphere.faces))
    with pytest.raises(TypeError, match=r"one pair \(vertices, faces\).*\[\(vertices, faces\)\]"):
        ts.MeshBatchAdapter(pair, resolution=16)
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device='cuda': this torch has no CUDA device"):
            ts.MeshAdapter(sphere, resolution=16, device="cuda")
    vertices = torch.as_tensor(sphere.vertices).requires_grad_()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        ts.sdf.from_mesh((vertices, torch.as_tensor(sphere.faces)), ts.Grid.cube(16, 1.4))
    assert any("not differentiable in the vertex positions" in str(w.message) for w in caught)


def test_a_part_inside_another_and_wound_like_it_is_named():
    """An eye inside a head, both wound outward: the winding number counts the inner part as
    solid within solid, phi is negative on both sides of it and its surface is gone, without a
    word (an inverted part was warned of). Now it is named; a cavity, a union of intersecting
    parts and one part are not."""
    outer = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    inner = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    cavity = inner.copy()
    cavity.invert()
    left, right = (trimesh.creation.icosphere(subdivisions=2, radius=0.5) for _ in range(2))
    left.apply_translation((-0.3, 0.0, 0.0))
    right.apply_translation((0.3, 0.0, 0.0))
    grid = ts.Grid.cube(24, 1.3)
    with pytest.warns(RuntimeWarning, match="1 closed part.*wholly inside") as caught:
        ts.sdf.from_mesh(trimesh.util.concatenate([outer, inner]), grid)
    assert caught[0].filename == __file__
    # a mesh stored twice is one part (each face was a part of its own: a false warning, and a
    # winding-number pass per face, which ran for minutes on a bunny)
    doubled = trimesh.Trimesh(outer.vertices, np.concatenate([outer.faces, outer.faces]),
                              process=False)
    for mesh in (trimesh.util.concatenate([outer, cavity]), trimesh.util.concatenate([left, right]),
                 outer, doubled):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            ts.sdf.from_mesh(mesh, grid)
