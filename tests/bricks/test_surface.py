"""BrickSurface against the dense ImplicitSurface: geometry, operators, gradients, meshes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

import torchsurf as ts
from torchsurf import Grid, bricks

MESHES = Path(__file__).resolve().parents[3] / "shared" / "data" / "meshes"


def _dense_of(surface):
    """``(phi, grid)`` of entry 0 of a brick surface as a dense volume."""
    return surface.to_dense(surface.phi)[0], surface.grids[0]


def _on_band(dense_surface, brick_surface, packed):
    """The packed field as a dense volume, and the dense band mask."""
    (volume,) = brick_surface.to_dense(packed)
    return volume, dense_surface.band_mask()


def test_geometry_equals_the_dense_surface_on_the_band(torus):
    dense, surface = torus
    band = dense.band_mask()
    for name in ("phi", "grad_norm", "normal", "weight"):
        (volume,) = surface.to_dense(getattr(surface, name))
        assert torch.equal(volume * band, getattr(dense, name) * band), name
    assert torch.equal(surface.gradient_scale.unique(), dense.gradient_scale.flatten())
    for name in ("mean_curvature", "gaussian_curvature"):
        (volume,) = surface.to_dense(getattr(surface, name)())
        assert torch.allclose(volume * band, getattr(dense, name)() * band, atol=1e-12), name
    (k1,), (k2,) = (surface.to_dense(k) for k in surface.principal_curvatures())
    d1, d2 = dense.principal_curvatures()
    assert torch.allclose(k1 * band, d1 * band, atol=1e-10)
    assert torch.allclose(k2 * band, d2 * band, atol=1e-10)


def test_geometry_equals_the_dense_surface_one_node_beyond_the_band():
    """docs/bricks.md: the same numbers within one node of the band, on phi that is no distance
    too (an ellipsoid's algebraic phi, off the grid's centre); two nodes out, a node beside an
    unstored brick reads zeros there (normals flipped, H off by 17 on this ellipsoid)."""
    grid = Grid.cube(33, bound=1.5)
    p = grid.points(dtype=torch.float64, relative_to=(0.03, -0.02, 0.01))
    phi = (p[..., 0] ** 2 + (p[..., 1] / 0.7) ** 2 + (p[..., 2] / 0.5) ** 2 - 1)[None, None]
    dense, surface = ts.ImplicitSurface(phi, grid), bricks.from_dense(phi, grid)
    band = dense.band_mask().double()
    (stored,) = surface.to_dense(surface.layout.inside.double())
    near = (torch.nn.functional.max_pool3d(band, 3, stride=1, padding=1) > 0) & (stored > 0)
    assert int(near.sum()) > int((band > 0).sum())
    fields = {"normal": (surface.normal, dense.normal),
              "mean_curvature": (surface.mean_curvature(), dense.mean_curvature()),
              "gaussian_curvature": (surface.gaussian_curvature(), dense.gaussian_curvature()),
              "k1": (surface.principal_curvatures()[0], dense.principal_curvatures()[0])}
    for name, (packed, expected) in fields.items():
        (volume,) = surface.to_dense(packed)
        assert torch.equal(volume * near, expected * near), name


def test_band_is_the_dense_band_and_scale_free(torus):
    dense, surface = torus
    (band,) = surface.to_dense(surface.band_mask().double())
    assert torch.equal(band > 0, dense.band_mask())
    scaled = bricks.from_dense(1000.0 * dense.phi, dense.grid)
    assert torch.equal(scaled.band_mask(), surface.band_mask())
    assert len(surface.layout) < 0.5 * 5**3  # bricks hold the band, not the box


def test_a_band_that_reaches_the_box_faces_is_refused():
    """A band one node from the faces asks for a grid that much wider; one on the faces cannot
    say how much (the surface may leave the box: a sphere centred on a face was told "2 nodes
    wider on each side", which was refused again), and asks for a grid holding the shape."""
    grid = Grid.cube(33, 1.5)
    with pytest.raises(ValueError, match=r"within 1 node of its grid's faces .* needs 2.* at "
                                         r"least 1 node wider on each side .*fit_grids"):
        bricks.from_dense(ts.sdf.sphere(grid, 1.15), grid)
    for phi in (ts.sdf.torus(grid, 1.0, 0.45), ts.sdf.sphere(grid, 1.45),
                ts.sdf.sphere(grid, 0.8, center=(1.5, 0.0, 0.0))):
        with pytest.raises(ValueError, match=r"reaches its grid's faces .* the surface may leave "
                                             r"the box.* 2 nodes to spare .*fit_grids"):
            bricks.from_dense(phi, grid)


@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative", "central"])
def test_laplace_beltrami_equals_the_dense_operator_on_the_band(torus, scheme):
    dense, surface = torus
    u = torch.randn(1, 3, *dense.grid.shape, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(0))
    expected = ts.laplace_beltrami(u, dense, scheme)
    packed = surface.from_dense(u)
    (result,) = surface.to_dense(ts.laplace_beltrami(packed, surface, scheme))
    band = dense.band_mask()
    scale = expected.abs().max()
    assert torch.allclose(result * band, expected * band, atol=1e-13 * scale, rtol=0)


def test_dense_data_are_refused_with_the_expected_shape(torus):
    dense, surface = torus
    with pytest.raises(ValueError, match=r"\(\d+, C, 8, 8, 8\)"):
        ts.laplace_beltrami(torch.zeros(1, 1, *dense.grid.shape, dtype=torch.float64), surface)


def test_gradcheck_laplace_beltrami_on_bricks_in_data_and_phi():
    grid = Grid.cube(21, 2.0)
    dense = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0).double(), grid)
    reference = bricks.from_dense(dense)
    layout = reference.layout
    band = reference.band_mask()
    u = torch.randn(len(layout), 1, 8, 8, 8, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(1))
    picked = band.flatten().nonzero()[:: 97].flatten()

    def in_u(x):
        return ts.laplace_beltrami(x, reference).flatten()[picked]

    assert torch.autograd.gradcheck(in_u, (u.requires_grad_(),), eps=1e-6, atol=1e-6,
                                    fast_mode=True)

    # phi perturbed at the nodes the picked outputs read (and a few more)
    base = reference.phi.detach()
    moved = (reference.layout.dilate(reference.layout.dilate(
        torch.zeros_like(band).flatten().index_fill(0, picked[:3], True).view_as(band)
    ))).flatten().nonzero().flatten()[::3]

    def in_phi(delta):
        phi = base.flatten().index_add(0, moved, delta).view_as(base)
        surface = bricks.BrickSurface(phi, layout, reference.band_width)
        return ts.laplace_beltrami(u.detach(), surface).flatten()[picked[:3]]

    delta = torch.zeros(len(moved), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(in_phi, (delta,), eps=1e-6, atol=1e-5, fast_mode=True)


def test_cat_batches_boxes_of_different_shapes(two_boxes):
    sphere, torus, both = two_boxes
    assert both.batch_size == 2 and both.grids == (*sphere.grids, *torus.grids)
    assert torch.equal(both.band_mask(), torch.cat([sphere.band_mask(), torus.band_mask()]))
    u = torch.randn(len(both.layout), 2, 8, 8, 8, dtype=torch.float64)
    together = ts.laplace_beltrami(u, both)
    alone = torch.cat([ts.laplace_beltrami(u[: len(sphere.layout)], sphere),
                       ts.laplace_beltrami(u[len(sphere.layout):], torus)])
    band = both.band_mask()
    assert torch.equal(together * band, alone * band)
    with pytest.raises(ValueError, match="grids"):
        both.grid  # noqa: B018


def test_cat_refuses_mixed_dtypes_and_spacings_naming_the_entry(two_boxes):
    """A float32 entry was promoted to float64 silently, and entries of two spacings were
    refused for their band widths (which follow the spacing) instead of the spacing."""
    sphere, torus, _ = two_boxes
    single = bricks.from_dense(sphere.to_dense(sphere.phi)[0].float(), sphere.grids[0])
    with pytest.raises(ts.MismatchError, match=r"surfaces\[1\] has phi of torch.float32"):
        bricks.cat([sphere, single])
    coarse_grid = ts.Grid(shape=(25, 25, 25), spacing=0.15, origin=(-1.8,) * 3)
    coarse = bricks.from_dense(ts.sdf.sphere(coarse_grid, 0.9).double(), coarse_grid)
    with pytest.raises(ValueError, match=r"surfaces\[2\] has grid spacing 0.15"):
        bricks.cat([sphere, torus, coarse])
    # an audit's: which entry differed, and what was given, went unsaid
    other = bricks.from_dense(*_dense_of(sphere), eps=10 * sphere.eps)
    with pytest.raises(ValueError, match=r"^surfaces\[2\] has eps .* one batch has one eps"):
        bricks.cat([sphere, torus, other])
    with pytest.raises(TypeError, match=r"^surfaces\[1\] must be a BrickSurface, got "
                                        r"ImplicitSurface"):
        bricks.cat([sphere, ts.ImplicitSurface(*_dense_of(sphere))])
    with pytest.raises(ValueError, match=r"^surfaces must be a non-empty sequence"):
        bricks.cat([])
    with pytest.raises(ValueError, match=r"^fill=1e\+39 cannot be held by field's dtype "
                                         r"torch.float32"):
        sphere.layout.to_dense(torch.zeros(len(sphere.layout), 1, 8, 8, 8), fill=1e39)
    with pytest.raises(ValueError, match=r"^index: 1 of 2, e\.g\. index\[1\] = \[400, 1, 1\], "
                                         r"lie outside the box of entry 0"):
        sphere.sample_at_index(sphere.phi, torch.tensor([[1.0, 1.0, 1.0],
                                                         [400.0, 1.0, 1.0]]).double())



@pytest.mark.skipif(not (MESHES / "spot.obj").exists(), reason="shared meshes not present")
@pytest.mark.parametrize("size", [40, 37, 41, 42])
def test_from_mesh_equals_the_dense_distance_on_every_stored_node_that_matters(size):
    """At 37^3 the last bricks reach 3 nodes beyond the box and the band comes within 3 nodes
    of its faces: stored nodes beyond the box held +-reach, W was 1.5 at face nodes and took
    15 of them into the band."""
    mesh = ts.mesh.load(MESHES / "spot.obj")
    grid = ts.mesh.fit_grid(mesh, size, margin=0.15)
    surface = bricks.from_mesh(mesh, grid, dtype=torch.float64)
    reach = surface.band_width + bricks.build.EXACT_REACH * grid.spacing
    dense_phi = ts.sdf.from_mesh(mesh, grid, band_width=reach, dtype=torch.float64)
    (phi,) = surface.to_dense(surface.phi, fill=float("nan"))
    stored = ~phi.isnan()
    assert torch.allclose(phi[stored], dense_phi[stored], atol=1e-12)
    dense = ts.ImplicitSurface(dense_phi, grid)
    (band,) = surface.to_dense(surface.band_mask().double())
    assert torch.equal(band > 0, dense.band_mask())
    # beyond the box, near S: extrapolated from the last three nodes, as the dense surface reads
    extrapolated = surface.layout.from_dense(dense_phi, fill="quadratic")
    beyond = ~surface.layout.inside
    assert int(beyond.sum()) > 1000 or size % 8 == 0  # 40 nodes: no brick reaches past the box
    assert torch.allclose(surface.phi[beyond], extrapolated[beyond], atol=1e-12)


def test_intrinsic_gradient_divergence_and_sampling_equal_the_dense_ones(torus):
    dense, surface = torus
    u = torch.randn(1, 2, *dense.grid.shape, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(5))
    packed = surface.from_dense(u)
    band = dense.band_mask()
    (gradient,) = surface.to_dense(ts.intrinsic_gradient(packed, surface))
    expected = ts.intrinsic_gradient(u, dense)
    assert torch.allclose(gradient * band, expected * band, atol=1e-12 * expected.abs().max())
    # the divergence of a field given on the band and its ring, as the band's nodes read it
    region = ts.flows.base.with_ring(band)
    field = torch.randn(1, 6, *dense.grid.shape, dtype=torch.float64,
                        generator=torch.Generator().manual_seed(6)) * region
    (divergence,) = surface.to_dense(ts.intrinsic_divergence(surface.from_dense(field), surface))
    expected = ts.intrinsic_divergence(field, dense)
    assert divergence.shape == (1, 2, *dense.grid.shape)
    assert torch.allclose(divergence * band, expected * band, atol=1e-12 * expected.abs().max())
    vertices = torch.as_tensor(ts.mesh.extract(dense.phi, dense.grid).vertices)
    sampled = surface.sample(packed, vertices)
    assert sampled.shape == (2, len(vertices))
    assert torch.allclose(sampled, ts.sample(u, vertices, dense.grid)[0], atol=1e-12)
    for entry in (np.int64(0), torch.tensor(0)):  # an index read from an array or a tensor
        assert torch.equal(surface.sample(packed, vertices, entry), sampled)
        assert bool(surface.samplable(vertices, entry).all())
    with pytest.raises(ValueError, match=r"entry must be an integer in \[0, 1\), got 1"):
        surface.sample(packed, vertices, np.int64(1))
    with pytest.raises(ValueError, match="entry must be an integer"):
        surface.sample(packed, vertices, 0.0)
    with pytest.raises(ValueError, match=r"^points: 1 of 1, e\.g\. points\[0\] = \[0, 0, 2\.05\], "
                                         "lie next to a brick that is not stored"):
        surface.sample(packed, torch.tensor([[0.0, 0.0, 2.05]], dtype=torch.float64))  # far
    far = dense.grid.world_to_index(torch.tensor([[0.0, 0.0, 2.05]], dtype=torch.float64))
    with pytest.raises(ValueError, match=r"^index: 1 of 1, .* lie next to a brick that is not"):
        surface.sample_at_index(packed, far)  # named "points" before
    # NaN beyond a band of 1.5 cells: the vertices' trilinear taps of weight 0 read it
    marked = surface.from_dense(torch.where(dense.band_mask(1.5 * dense.grid.spacing), u,
                                            torch.nan))
    assert torch.equal(surface.sample(marked, vertices), sampled)
    with pytest.raises(ValueError, match="outside the box"):
        surface.sample(packed, torch.full((1, 3), 5.0, dtype=torch.float64))
    with pytest.raises(TypeError, match="points .*torch.float32.* must have the dtype"):
        surface.sample(packed, vertices.float())
    with pytest.raises(TypeError, match="index .*torch.float32.* must have the dtype"):
        surface.sample_at_index(packed, dense.grid.world_to_index(vertices).float())


def test_to_moves_the_layout_and_forgets_what_was_derived_in_the_old_dtype():
    grid = Grid.cube(25, 2.1)
    phi = ts.sdf.torus(grid, 0.9, 0.4)
    u0 = torch.rand((1, 1, *grid.shape), generator=torch.Generator().manual_seed(3))
    for dense in (False, True):
        made = ts.ImplicitSurface(phi, grid) if dense else bricks.from_dense(phi, grid)
        fresh = ts.ImplicitSurface(phi.double(), grid) if dense else bricks.from_dense(
            phi.double(), grid)
        data = u0 if dense else made.from_dense(u0)
        flow = ts.HeatFlow(2 * grid.spacing**2)
        flow(data, made)  # keeps a float32 spectral bound and stencils on the surface
        moved = made.double()
        assert moved.phi.dtype == torch.float64
        if not dense:
            assert moved.layout.lookup.device == moved.phi.device
        torch.testing.assert_close(flow(data.double(), moved), flow(data.double(), fresh),
                                   rtol=0, atol=0)


def test_a_surface_forms_its_own_halos_eagerly(torus, monkeypatch):
    """The halos a surface forms once (of phi, its inside mask, normals and weight) never
    compile, whatever the backend's mode: compiling the gather cost 3-7 s of a 512^3 build."""
    from torchsurf import backend

    dense, _ = torus
    monkeypatch.setattr(backend, "COMPILE", "always")
    paths = []
    run = backend.run
    monkeypatch.setattr(backend, "run", lambda kernel, path, *args: (
        paths.append((kernel.name, backend.resolve(path, args[0], kernel, args=args[1:])))
        or run(kernel, path, *args)))
    surface = bricks.from_dense(dense)
    surface.haloed()
    halos = [path for name, path in paths if name == "brick_halo"]
    assert len(halos) >= 4 and set(halos) == {"slicing"}


def test_world_points_far_from_the_origin_sample_as_on_the_dense_grid():
    """A float32 point on the box's face at origin 1000 has index 19.000244 (rounding at the
    world scale): the dense sampler read it, the bricks' refused it as outside."""
    grid = ts.Grid((20, 20, 20), spacing=0.01, origin=(1000.0, 1000.0, 1000.0))
    centre = 1000.0 + 0.095
    phi = ts.sdf.sphere(grid, radius=0.05, center=(centre,) * 3, dtype=torch.float32)
    packed = bricks.from_dense(ts.ImplicitSurface(phi, grid))
    point = torch.tensor([[1000.19, centre, centre]], dtype=torch.float32)
    assert bool(grid.contains(point))
    assert packed.samplable(point).tolist() == [True]
    torch.testing.assert_close(packed.sample(packed.phi, point), ts.sample(phi, point, grid)[0])
    beyond = torch.tensor([[1000.192, centre, centre]], dtype=torch.float32)  # 0.2 cells out
    assert not bool(grid.contains(beyond))
    assert packed.samplable(beyond).tolist() == [False]


def test_a_band_past_the_cell_count_cap_equals_the_dense_band(monkeypatch):
    """Dense counts cells to S up to CROSSING_CELLS and takes a band that wide as every node;
    the bricks dilated that many times and dropped nodes farther out (shown with the cap
    lowered to 4: a 255-cell band needs a box of over 520 nodes)."""
    import torchsurf.bricks.surface as brick_surface
    import torchsurf.surface as dense_surface

    monkeypatch.setattr(dense_surface, "CROSSING_CELLS", 4)
    monkeypatch.setattr(brick_surface, "CROSSING_CELLS", 4)
    grid = ts.Grid.cube(40, bound=1.0)
    phi = ts.sdf.sphere(grid, radius=0.3, dtype=torch.float64)
    dense = ts.ImplicitSurface(phi, grid, band_width=7 * grid.spacing)
    packed = bricks.from_dense(dense)
    on_bricks = packed.layout.to_dense(packed.band_mask().double())[0] > 0
    assert int(dense.band_mask().sum()) > 0
    assert torch.equal(on_bricks, dense.band_mask())


def test_the_flows_band_widths_follow_entries_cat_copies_and_states(two_boxes):
    """``evolving_widths`` are checked, kept by ``cat``, by each entry alone, by deep copies
    and by a loaded state (a state without them gives ``band_width``)."""
    import copy

    sphere, torus, _ = two_boxes
    h = sphere.spacing
    layout = sphere.layout
    with pytest.raises(ValueError, match="evolving_widths must be at least band_width"):
        bricks.BrickSurface(sphere.phi, layout, 3 * h, evolving_widths=2 * h)
    with pytest.raises(ValueError, match=r"one width per batch entry \(1\), got 2"):
        bricks.BrickSurface(sphere.phi, layout, 3 * h, evolving_widths=[4 * h, 4 * h])
    wide = bricks.BrickSurface(sphere.phi, layout, 3 * h, evolving_widths=4 * h)
    both = bricks.cat([wide, torus])
    assert both.evolving_widths() == (4 * h, torus.band_width)
    assert [entry.evolving_widths() for _, entry in both.entries()] == [(4 * h,), (torus.band_width,)]
    assert copy.deepcopy(both).evolving_widths() == both.evolving_widths()
    plain = bricks.BrickSurface(sphere.phi.clone(), layout, 3 * h)
    plain.load_state_dict(wide.state_dict())
    assert plain.evolving_widths() == (4 * h,)
    state = wide.state_dict()
    del state["_extra_state"]["evolving_widths"]
    plain.load_state_dict(state)
    assert plain.evolving_widths() == (3 * h,)


def test_sample_refuses_a_field_not_packed_on_the_layout(torus):
    """``sample`` read a dense volume, or a field of twice the bricks, as if packed: wrong
    numbers and no error (``sample_at_index`` checked)."""
    dense, surface = torus
    points = torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)
    packed = surface.from_dense(torch.zeros(1, 1, *dense.grid.shape, dtype=torch.float64))
    for field in (torch.zeros(1, 1, *dense.grid.shape, dtype=torch.float64),
                  torch.cat([packed, packed]), packed[: len(packed) // 2]):
        with pytest.raises(ValueError, match="field must be a packed band field"):
            surface.sample(field, points)


def test_packing_entries_of_different_dtypes_is_refused(two_boxes):
    _, _, both = two_boxes
    first, second = (torch.zeros(1, 1, *grid.shape) for grid in both.grids)
    with pytest.raises(ts.MismatchError, match=r"volume\[1\] is torch.float64 .* volume\[0\]"):
        both.layout.from_dense([first, second.double()])


def test_a_wider_band_width_is_refused_where_the_bricks_do_not_hold_it():
    """Set wider than the bricks were built for, the band kept u0 at the nodes it left out
    (2.48 off the dense flow at 5 cells, silently); within the flows' stored band it equals a
    fresh surface, and each entry of a batch runs with it."""
    grid = Grid.cube(33, 2.0)
    h = grid.spacing
    distance = ts.sdf.sphere(grid, 1.0, center=(0.04, -0.03, 0.02), dtype=torch.float64)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    quadric = ((x * x + y * y + z * z) - 0.8**2)[None, None]  # not a distance: 3 cells
    narrow = bricks.from_dense(quadric, grid)
    with pytest.raises(ValueError, match=r"band_width=.* reaches \d+ nodes"):
        narrow.band_width = 5 * h
    assert narrow.band_width == pytest.approx(3 * h)
    wide = bricks.from_dense(distance, grid)
    assert wide.evolving_widths() == pytest.approx((5 * h,))
    both = bricks.cat([wide, bricks.from_dense(distance, grid)])
    both.band_width = 4 * h
    fresh = bricks.from_dense(distance, grid, band_width=4 * h)
    u = fresh.from_dense(torch.rand(1, 1, *grid.shape, dtype=torch.float64,
                                    generator=torch.Generator().manual_seed(1)))
    flow = ts.HeatFlow(0.01)
    together = flow(torch.cat([u, u]), both)
    assert torch.equal(together[: len(u)], flow(u, fresh))
    # judged per entry: beside the wide entry, the narrow one was let through (an audit)
    mixed = bricks.cat([bricks.from_dense(quadric, grid), wide])
    with pytest.raises(ValueError, match=r"^width=.* reaches (\d+) nodes within it of S "
                                         r"\(\1 of entry 0\)"):
        ts.flows.closest_point_extension(mixed.from_dense(torch.rand(2, 1, *grid.shape).double()),
                                         mixed, width=5 * h)


def test_a_brick_batch_evaluated_under_inference_mode_then_trains():
    """The batch's kept entry rows were inference tensors: the next training call raised
    'Inference tensors cannot be saved for backward'."""
    grid = Grid.cube(29, 1.4)
    one = bricks.from_dense(ts.sdf.sphere(grid, 0.8, dtype=torch.float64), grid)
    both = bricks.cat([one, bricks.from_dense(ts.sdf.sphere(grid, 0.7, dtype=torch.float64), grid)])
    u = torch.rand(len(both.layout), 1, 8, 8, 8, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(2))
    flow = ts.HeatFlow(0.01)
    with torch.inference_mode():
        flow(u, both)
    trained = u.clone().requires_grad_()
    flow(trained, both).sum().backward()
    assert torch.isfinite(trained.grad).all()


def test_edge_stopping_on_bricks_evaluated_under_inference_mode_then_trains():
    """The layout's halo and kernel tables were kept as inference tensors by the first call:
    the next training call raised 'Inference tensors cannot be saved for backward'."""
    grid = Grid.cube(21, 1.5)
    surface = bricks.from_dense(ts.sdf.sphere(grid, 0.6), grid)
    x, y, z = grid.points().unbind(-1)
    u = surface.from_dense((x + y * z)[None, None])
    with torch.inference_mode():
        expected = ts.anisotropic_diffusion(u, surface, "perona_malik", contrast=0.5)
    trained = u.clone().requires_grad_()
    result = ts.anisotropic_diffusion(trained, surface, "perona_malik", contrast=0.5)
    result.square().sum().backward()
    torch.testing.assert_close(result.detach(), expected, rtol=0, atol=0)
    assert torch.isfinite(trained.grad).all() and trained.grad.abs().sum() > 0


def test_bricks_of_a_phi_that_requires_grad_keep_its_graph_under_no_grad_and_inference():
    """Built under no_grad the packed phi lost its graph (a silently missing part of phi's
    gradient); a heat flow under inference_mode read the row bits' version counter of an
    inference mask ('Inference tensors do not track version counter')."""
    grid = Grid.cube(17, 1.6)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    data = (x + y * z)[None, None]

    def phi_gradient(no_grad: bool) -> torch.Tensor:
        phi = ts.sdf.sphere(grid, 0.5, dtype=torch.float64).requires_grad_()
        with torch.no_grad() if no_grad else torch.enable_grad():
            surface = bricks.from_dense(phi, grid)
        assert surface.phi.requires_grad
        ts.laplace_beltrami(surface.from_dense(data), surface).square().sum().backward()
        return phi.grad

    torch.testing.assert_close(phi_gradient(True), phi_gradient(False), rtol=0, atol=0)
    phi = ts.sdf.sphere(grid, 0.5).requires_grad_()
    surface = bricks.from_dense(phi, grid)
    u = surface.from_dense(torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(4)))
    with torch.inference_mode():
        inferred = ts.HeatFlow(0.01)(u, surface)
    with torch.no_grad():
        torch.testing.assert_close(inferred, ts.HeatFlow(0.01)(u, surface))


@pytest.mark.parametrize("grids", ["g", 64, [None]])
def test_from_mesh_names_grids_that_are_not_grids(grids):
    """A string for the grid failed on "'str' object has no attribute 'spacing'"."""
    import trimesh

    with pytest.raises(TypeError, match="grids must be a torchsurf.Grid"):
        bricks.from_mesh(trimesh.creation.icosphere(subdivisions=1), grids)
