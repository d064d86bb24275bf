"""The band Laplacian on packed band values: equal to the volume operator it is read off, its
transpose the adjoint, and the heat semigroup's results and gradients those of the volume path."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import _gather_matrix, _native_gather, _packed_band, exponential
from torchsurf.flows._gather_matrix import GatherMatrix
from torchsurf.flows.exponential import BandLaplacian, heat_semigroup
from torchsurf.operators import functional, laplace_beltrami_bound

from ._probed_reference import REACH, probed_by_colours
from .test_stability import MESH_DIR


def _surface(kind: str) -> ts.ImplicitSurface:
    """Float64 surfaces with what the packed operator must get right: a batch of two shapes,
    a band reaching the box's faces (the probes' crop), ``phi`` not a distance (orphan ring
    nodes), a mesh's ``from_mesh`` phi (ring nodes chained through the ring), two shapes
    stored as bricks, a wavy quadric (not a distance) stored as bricks."""
    if kind == "two shapes":
        grid = ts.Grid.cube(23, 1.5)
        phi = torch.cat([ts.sdf.torus(grid, dtype=torch.float64),
                         ts.sdf.sphere(grid, 0.9, dtype=torch.float64)])
    elif kind == "at the faces":
        grid = ts.Grid.cube(21, 1.5)
        phi = ts.sdf.sphere(grid, 1.42, dtype=torch.float64)
    elif kind == "bricks":
        grid = ts.Grid.cube(32, 2.2)
        phi = torch.cat([ts.sdf.torus(grid, dtype=torch.float64),
                         ts.sdf.sphere(grid, 0.9, dtype=torch.float64)])
        return ts.bricks.from_dense(phi, grid)
    elif kind == "bricks quadric":
        grid = ts.Grid.cube(30, 1.9)
        x, y, z = grid.points(dtype=torch.float64).unbind(-1)
        quadric = (x / 1.05) ** 2 + (y / 1.2) ** 2 + (z / 0.9) ** 2 - 1.0
        return ts.bricks.from_dense((quadric * (1.0 + 0.3 * torch.sin(3.0 * x)))[None, None],
                                    grid)
    elif kind == "tanh":
        grid = ts.Grid.cube(25, 2.4)
        phi = torch.tanh(ts.sdf.sphere(grid, 0.8, dtype=torch.float64) / grid.spacing)
    else:
        path = MESH_DIR / "bunny_closed.obj"
        if not path.is_file():
            pytest.skip(f"test mesh bunny_closed.obj not found in {MESH_DIR}")
        grid = ts.mesh.fit_grid(str(path), 28)
        return ts.ImplicitSurface(ts.sdf.from_mesh(str(path), grid, dtype=torch.float64), grid)
    return ts.ImplicitSurface(phi, grid)


def _fields(surface: ts.ImplicitSurface, count: int, seed: int) -> list[torch.Tensor]:
    """``count`` random float64 fields of two channels in the surface's storage (a batch of 3
    on a dense surface of batch 1)."""
    generator = torch.Generator().manual_seed(seed)
    if surface.layout is not None:
        return [surface.layout.rand(2, generator=generator, dtype=torch.float64) - 0.5
                for _ in range(count)]
    batch = 3 if surface.batch_size == 1 else surface.batch_size
    return [torch.randn((batch, 2, *surface.grid.shape), generator=generator,
                       dtype=torch.float64) for _ in range(count)]


def _volume(packed, values: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """Band values ``(band nodes, C, K)`` as a volume, zero elsewhere."""
    ring = values.new_zeros((len(packed.nodes) - packed.band_count, *values.shape[1:]))
    return packed.unpack(torch.cat([values, ring]), like)


@pytest.mark.parametrize("form", ["native", "bagged", "padded"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_gather_matrix_is_the_matrix_it_holds(dtype, form, monkeypatch):
    """Rows of very different lengths (reordered when padded), repeated positions (summed), an
    empty row, exact zeros (dropped); the transpose too; by the C kernel, by ``embedding_bag``
    (where the kernel does not run) and by the padded gathers (the other dtypes')."""
    if form == "native" and _native_gather.LIBRARY.load() is None:
        pytest.skip(f"no C kernel here: {_native_gather.LIBRARY.unavailable_reason()}")
    if form != "native":
        monkeypatch.setattr(_native_gather, "applies", lambda *args: False)
    if form == "padded":
        monkeypatch.setattr(_gather_matrix, "BAGGED", ())
    generator = torch.Generator().manual_seed(0)
    rows = torch.cat([torch.zeros(40, dtype=torch.long), torch.randint(1, 30, (60,),
                                                                        generator=generator)])
    columns = torch.randint(0, 17, (100,), generator=generator)
    values = torch.randn(100, generator=generator, dtype=torch.float64)
    values[5] = 0.0
    dense = torch.zeros(31, 17, dtype=torch.float64).index_put_((rows, columns), values,
                                                                accumulate=True)
    matrix = GatherMatrix(rows, columns, values, (31, 17))
    x = torch.randn(17, 3, generator=generator, dtype=torch.float64)
    g = torch.randn(31, 3, generator=generator, dtype=torch.float64)
    tolerance = 1e-13 if dtype == torch.float64 else 1e-5
    for _ in range(2):  # the second call reuses the converted weights
        torch.testing.assert_close(matrix.apply(x.to(dtype)).double(), dense @ x,
                                   rtol=tolerance, atol=tolerance)
    torch.testing.assert_close(matrix.transposed().apply(g.to(dtype)).double(), dense.T @ g,
                               rtol=tolerance, atol=tolerance)
    if form == "padded":
        assert matrix._padded.order is not None  # row 0 holds most entries: reordered
    empty = GatherMatrix(rows[:0], columns[:0], values[:0], (4, 17))
    assert torch.equal(empty.apply(x), x.new_zeros(4, 3))
    with pytest.raises(ValueError, match="must be \\(17, F\\)"):
        matrix.apply(g)


@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative"])
def test_reach_holds_each_schemes_coefficients(scheme):
    """The probes' colours assume ``A`` couples nodes at most ``REACH`` apart along each axis:
    ``A`` of single nodes on a torus (curved both ways) stays within it."""
    grid = ts.Grid.cube(21, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.torus(grid, dtype=torch.float64), grid)
    reach = REACH[scheme]
    for node in [(10, 10, 3), (10, 4, 10), (7, 8, 9), (10, 13, 3), (4, 6, 12)]:
        u = torch.zeros((1, 1, *grid.shape), dtype=torch.float64)
        u[(0, 0, *node)] = 1.0
        image = functional.divergence_form(u, surface.normal, surface.weight, surface.spacing,
                                           scheme, "slicing", weighted=True)
        support = image[0, 0].nonzero()
        assert len(support) > 7
        assert int((support - torch.tensor(node)).abs().max()) <= reach


@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative"])
@pytest.mark.parametrize("kind", ["two shapes", "at the faces", "tanh", "bunny", "bricks"])
def test_packed_operator_is_the_volume_operator(kind, scheme):
    """``L`` and ``L^T`` on packed values equal the volume operator's on the band to rounding,
    and the transpose is the adjoint."""
    surface = _surface(kind)
    operator = BandLaplacian(surface, scheme, path="slicing")
    packed = operator.packed()
    if kind == "tanh":
        assert operator.ring.orphans is not None
    if kind == "bunny":
        assert operator.ring.chained is not None and packed.sweeps > 0
    u, v = _fields(surface, 2, seed=1)
    inside = torch.where(operator.band, u, 0.0)
    for dense, mine in ((operator.apply(inside), packed.apply(packed.pack(u))),
                        (torch.where(operator.band, operator.transpose(inside), 0.0),
                         packed.transpose(packed.pack(u)))):
        scale = float(dense.abs().max())
        assert float((_volume(packed, mine, u) - dense).abs().max()) < 1e-13 * scale
    x, y = packed.pack(u), packed.pack(v)
    torch.testing.assert_close((packed.apply(x) * y).sum(), (x * packed.transpose(y)).sum(),
                               rtol=1e-12, atol=0.0)
    region = torch.where(operator.region, operator.ring.apply(inside), 0.0)
    torch.testing.assert_close(packed.unpack(packed.fill(x), u), region, rtol=0.0,
                               atol=1e-13 * float(region.abs().max()))


def _odd_box_surface() -> ts.ImplicitSurface:
    """An ellipsoid's ``phi`` that is not a distance (a quadric times a factor varying along
    x), in a box of three different sides that cuts the surface at one face and comes within a
    cell of it at two others."""
    grid = ts.Grid((19, 23, 17), 0.13, (-1.2, -1.5, -1.0))
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    phi = (x / 1.05) ** 2 + (y / 1.3) ** 2 + (z / 0.9) ** 2 - 1.0
    return ts.ImplicitSurface(phi[None, None] * (1.0 + 0.5 * torch.sin(3.0 * x))[None, None],
                              grid)


@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative"])
@pytest.mark.parametrize("kind", ["two shapes", "at the faces", "tanh", "bunny", "odd box",
                                  "bricks", "bricks quadric"])
def test_formed_rows_equal_the_probes(kind, scheme):
    """``W^-1 A`` formed in closed form at the band's rows (a dense surface's geometry, or each
    brick's haloed) equals, entry by entry, the one read off the volume operator by colour
    probes; its bound is the float a fresh surface's ``laplace_beltrami_bound`` gives."""
    surface = _odd_box_surface() if kind == "odd box" else _surface(kind)
    operator = BandLaplacian(surface, scheme, path="slicing")
    packed = operator.packed().packing
    storage, rows = packed.storage, packed.nodes[:packed.band_count]
    count = len(packed.nodes)
    formed, bound = _packed_band._formed_rows(surface, scheme, storage, rows, packed.lookup,
                                              count, packed.band_count)
    fresh = (ts.ImplicitSurface(surface.phi.clone(), surface.grid) if surface.layout is None
             else ts.bricks.BrickSurface(surface.phi.clone(), surface.layout))
    assert bound == laplace_beltrami_bound(fresh, scheme, operator.width)  # the same float
    probed = probed_by_colours(surface, scheme, operator.region, storage, rows, packed.lookup,
                               count)
    mine, reference = _sparse(formed), _sparse(probed)
    assert reference.values().abs().min() > 0 and len(reference.values()) > 19 * len(rows) // 2
    scale = float(reference.values().abs().max())
    assert float((mine - reference).coalesce().values().abs().max()) < 1e-13 * scale


def test_brick_storage_reads_each_nodes_grid_neighbours():
    """The packed positions of every node's 27 neighbours on bricks (the brick's neighbour
    table and the node's local index, wrapped) equal those read from each entry's dense
    volume of positions: -1 beyond the entry's box (boxes of 21 and 30 nodes, not whole
    bricks) or in a brick that is not stored."""
    grids = [ts.Grid(shape=(n, n, n), spacing=0.1, origin=(-0.05 * (n - 1),) * 3) for n in (21, 30)]
    surface = ts.bricks.cat([ts.bricks.from_dense(ts.sdf.sphere(g, r, dtype=torch.float64), g)
                             for g, r in zip(grids, (0.45, 0.85), strict=True)])
    layout = surface.layout
    count = len(layout) * ts.bricks.BRICK**3
    positions = torch.arange(count, dtype=torch.float64).view(-1, 1, 8, 8, 8)
    volumes = layout.to_dense(positions, fill=-1.0)
    storage = _packed_band._Storage(surface, surface.band_mask())
    nodes = torch.arange(count)
    found = storage.neighbourhood(nodes)
    entry = layout.batch[nodes // ts.bricks.BRICK**3]
    at = layout.node_index().transpose(0, 1).reshape(3, -1)
    for column, offset in enumerate(ts.stencils.NEIGHBOURHOOD):
        expected = torch.full((count,), -1, dtype=torch.long)
        for b, volume in enumerate(volumes):
            moved = [a[entry == b] + o for a, o in zip(at, offset, strict=True)]
            inside = torch.stack([(m >= 0) & (m < n) for m, n in
                                  zip(moved, volume.shape[-3:], strict=True)]).all(0)
            z, y, x = (m.clamp(0, n - 1) for m, n in zip(moved, volume.shape[-3:], strict=True))
            expected[entry == b] = torch.where(inside, volume[0, 0, z, y, x].long(), -1)
        assert torch.equal(found[:, column], expected), offset
        assert torch.equal(storage.neighbour(nodes, offset), expected)
    assert 0 < int((found < 0).sum()) < found.numel() // 2
    with pytest.raises(ValueError, match="within one node"):  # 9 along x had read wrong nodes
        storage.neighbour(nodes, (0, 0, 9))


def _sparse(matrix: GatherMatrix) -> torch.Tensor:
    """A :class:`GatherMatrix` as a coalesced sparse COO tensor."""
    counts = (matrix.offsets[1:] - matrix.offsets[:-1]).long()
    rows = torch.repeat_interleave(torch.arange(matrix.shape[0]), counts)
    indices = torch.stack([rows, matrix.columns.long()])
    return torch.sparse_coo_tensor(indices, matrix.values(torch.float64), matrix.shape).coalesce()


@pytest.mark.parametrize("kind", ["two shapes", "bunny", "bricks"])
def test_heat_semigroup_equals_the_volume_path(kind, monkeypatch):
    """Results and gradients (data and times) of the packed path against the volume path's."""
    surface = _surface(kind)
    operator = BandLaplacian(surface, path="slicing")
    u, grad = _fields(surface, 2, seed=2)
    times = torch.tensor([1.5, 12.0], dtype=torch.float64) * surface.spacing**2

    def run() -> tuple[torch.Tensor, ...]:
        data, t = u.clone().requires_grad_(), times.clone().requires_grad_()
        result = heat_semigroup(data, operator, t)
        return (result.detach(), *torch.autograd.grad((result * grad).sum(), (data, t)))

    packed = run()
    monkeypatch.setattr(BandLaplacian, "packed", lambda self: None)
    volume = run()
    for mine, reference in zip(packed, volume, strict=True):
        torch.testing.assert_close(mine, reference, rtol=1e-10, atol=1e-10)


def test_the_expansion_runs_no_volume_stencil(monkeypatch):
    """Once the packed operator is assembled, an expansion applies the band's matrices only: no
    Laplace–Beltrami stencil over the volume (it cost 8 s of the 9 s forward at 64^3, batch
    4)."""
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    layer = ts.nn.LearnedDiffusion(2, time=[1.0, 9.0])
    u = torch.rand(2, 2, *grid.shape, generator=torch.Generator().manual_seed(0))
    layer(u, surface)
    calls = []
    original = functional.divergence_form
    monkeypatch.setattr(functional, "divergence_form",
                        lambda *args, **kwargs: calls.append(1) or original(*args, **kwargs))
    layer(u.requires_grad_(), surface).sum().backward()
    assert calls == []
    assert exponential.BandLaplacian(surface).packed() is surface.kept(
        ("packed band laplacian", "octant", surface.band_width), lambda: None)


def test_gradcheck_on_a_batch_of_two_shapes():
    """Each entry's nodes packed after the other's: gradients of the data and times."""
    grid = ts.Grid.cube(11, 1.5)
    phi = torch.cat([ts.sdf.sphere(grid, dtype=torch.float64),
                     ts.sdf.sphere(grid, 0.8, dtype=torch.float64)])
    surface = ts.ImplicitSurface(phi, grid)
    operator = BandLaplacian(surface, path="slicing")
    assert operator.packed() is not None
    generator = torch.Generator().manual_seed(4)
    u0 = torch.rand((2, 2, *grid.shape), generator=generator, dtype=torch.float64)
    directions = torch.randn((4, *u0.shape), generator=generator, dtype=torch.float64)

    def run(along: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        return heat_semigroup(u0 + torch.tensordot(along, directions, dims=1), operator, t)

    along = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    times = (torch.tensor([0.5, 3.0], dtype=torch.float64) * grid.spacing**2).requires_grad_()
    assert torch.autograd.gradcheck(run, (along, times), fast_mode=True)


def test_the_volume_path_when_the_matrices_would_not_fit(monkeypatch):
    """Matrices beyond a quarter of the memory available: the volume operators, chosen once
    and kept; the results are the same."""
    grid = ts.Grid.cube(15, 1.5)
    generator = torch.Generator().manual_seed(5)
    u = torch.rand((2, 2, *grid.shape), generator=generator, dtype=torch.float64)
    times = torch.tensor([1.0, 4.0], dtype=torch.float64) * grid.spacing**2
    results = []
    for node_bytes in (exponential.PACKED_NODE_BYTES, 2**60):
        monkeypatch.setattr(exponential, "PACKED_NODE_BYTES", node_bytes)
        surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
        operator = BandLaplacian(surface, path="slicing")
        assert (operator.packed() is None) == (node_bytes == 2**60)
        results.append(heat_semigroup(u, operator, times))
    torch.testing.assert_close(results[0], results[1], rtol=1e-10, atol=1e-10)


def test_more_float32_columns_than_the_kernel_takes_go_through_it_in_groups(monkeypatch):
    """The limited re-extension's C kernel takes 16 float32 columns: a batch of 17 fell back to
    gathering 64 values a row and column (0.1 s -> 1.2 s at 48^3 and 460 MB above the field).
    Groups of columns now go through the kernel, and the fallback without it gathers in
    chunks: both equal the entries run apart."""
    grid = ts.Grid.cube(24, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    u0 = torch.rand(17, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    flow = ts.HeatFlow(time=20 * grid.spacing**2)
    apart = torch.cat([flow(u0[:16], surface), flow(u0[16:], surface)])
    kernel, answers = _native_gather.limited, []

    def recorded(*args, **kwargs):
        answers.append(kernel(*args, **kwargs))
        return answers[-1]

    with monkeypatch.context() as patch:
        patch.setattr(_packed_band._native_gather, "limited", recorded)
        torch.testing.assert_close(flow(u0, surface), apart, rtol=0, atol=1e-6)
    if _native_gather.LIBRARY.load() is not None:  # every re-extension went through the kernel
        assert answers and all(answer is not None for answer in answers)
    monkeypatch.setattr(_packed_band, "GATHER_ROWS", 100)
    monkeypatch.setattr(_packed_band._native_gather, "limited", lambda *args, **kwargs: None)
    torch.testing.assert_close(flow(u0, ts.ImplicitSurface(surface.phi, grid)), apart,
                               rtol=0, atol=1e-5)
