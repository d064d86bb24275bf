"""BrickLayout: halos, dense conversions, dilation and the tables, against dense references."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from torchsurf import Grid
from torchsurf.bricks import BRICK, BrickLayout, bricks_of_mask
from torchsurf.flows._integrators import with_ring


def _scattered_layout(shape=(21, 30, 17), seed=0) -> tuple[BrickLayout, Grid]:
    """Every other brick of a box whose sides are not multiples of 8: many absent neighbours."""
    grid = Grid(shape=shape, spacing=0.1)
    generator = torch.Generator().manual_seed(seed)
    extent = [-(-n // BRICK) for n in shape]
    occupied = torch.rand(extent, generator=generator) < 0.6
    occupied.view(-1)[0] = True
    coords = occupied.nonzero()
    return BrickLayout(coords, torch.zeros(len(coords), dtype=torch.long), [grid]), grid


def _reference_halo(packed, layout, width):
    """Each brick's haloed block cut from the whole box of bricks, zeros where none is stored."""
    nz, ny, nx = layout.extent
    channels = packed.shape[1]
    full = torch.zeros(channels, nz * BRICK, ny * BRICK, nx * BRICK, dtype=packed.dtype)
    for row, (z, y, x) in enumerate((layout.coords * BRICK).tolist()):
        full[:, z: z + BRICK, y: y + BRICK, x: x + BRICK] = packed[row]
    full = F.pad(full, (width,) * 6)
    side = BRICK + 2 * width
    return torch.stack([full[:, z: z + side, y: y + side, x: x + side]
                        for z, y, x in (layout.coords * BRICK).tolist()])


@pytest.mark.parametrize("width", [1, 2, 3])
def test_halo_equals_the_dense_neighbourhood_with_zeros_where_no_brick_is(width):
    layout, grid = _scattered_layout()
    packed = torch.randn(len(layout), 2, BRICK, BRICK, BRICK, dtype=torch.float64)
    haloed = layout.halo(packed, width)
    assert haloed.shape == (len(layout), 2, *(BRICK + 2 * width,) * 3)
    assert torch.equal(haloed, _reference_halo(packed, layout, width))
    assert not layout.present.all()  # the case has missing neighbours


def test_halo_is_differentiable_and_its_adjoint_sums_the_copies():
    layout, grid = _scattered_layout(seed=1)
    field = torch.randn(len(layout), 1, BRICK, BRICK, BRICK, dtype=torch.float64,
                        requires_grad=True)
    weights = torch.randn(len(layout), 1, BRICK + 2, BRICK + 2, BRICK + 2, dtype=torch.float64)
    (grad,) = torch.autograd.grad((layout.halo(field, 1) * weights).sum(), field)
    # <halo(x), w> = <x, halo^T w>: check on a random x
    probe = torch.randn_like(field)
    assert torch.allclose((layout.halo(probe, 1) * weights).sum(), (probe * grad).sum())


@pytest.mark.parametrize("dtype", [torch.float32, torch.bool])
def test_compiled_halo_equals_the_eager_one_and_the_reference(dtype, monkeypatch):
    """The halo's gather as one compiled pass (what ``"auto"`` runs on large layouts): the same
    values as eagerly and as the reference, bool fields (``dilate``) kept bool, and the same
    gradient."""
    from torchsurf import backend

    layout, grid = _scattered_layout(seed=2)
    generator = torch.Generator().manual_seed(3)
    packed = torch.rand(len(layout), 2, BRICK, BRICK, BRICK, generator=generator)
    packed = packed > 0.5 if dtype == torch.bool else packed
    results = {}
    for path in ("slicing", "compiled"):
        monkeypatch.setattr(backend, "run", lambda kernel, _, *args, p=path, run=backend.run:
                            run(kernel, p, *args))
        results[path] = layout.halo(packed, 2)
        monkeypatch.undo()
    assert results["compiled"].dtype == dtype
    assert torch.equal(results["compiled"], results["slicing"])
    assert torch.equal(results["compiled"], _reference_halo(packed, layout, 2))
    if dtype == torch.bool:
        return
    weights = torch.randn(len(layout), 2, *(BRICK + 2,) * 3, generator=generator)
    grads = []
    for path in ("slicing", "compiled"):
        field = packed.clone().requires_grad_(True)
        monkeypatch.setattr(backend, "run", lambda kernel, _, *args, p=path, run=backend.run:
                            run(kernel, p, *args))
        (layout.halo(field, 1) * weights).sum().backward()
        monkeypatch.undo()
        grads.append(field.grad)
    torch.testing.assert_close(grads[1], grads[0])


def test_dense_round_trip_and_shapes():
    layout, grid = _scattered_layout(seed=2)
    volume = torch.randn(1, 3, *grid.shape)
    (back,) = layout.to_dense(layout.from_dense(volume), fill=float("nan"))
    stored = ~back.isnan()
    assert back.shape == volume.shape
    assert torch.equal(back[stored], volume[stored])
    assert stored.sum() == layout.inside.sum() * 3
    integers = layout.from_dense(torch.ones(1, 1, *grid.shape, dtype=torch.int64))
    assert int(layout.to_dense(integers, fill=-1)[0].min()) == -1
    with pytest.raises(ValueError, match=r"fill=0.5 cannot be held by field's dtype torch.int64"):
        layout.to_dense(integers, fill=0.5)  # it had truncated to 0, like the stored zeros
    # -1 in uint8 wrapped to 255, 5 in bool was True, 300 in int8 and NaN in int32 raised
    # torch's own errors naming no argument
    for dtype, fill in ((torch.uint8, -1), (torch.bool, 5), (torch.int8, 300),
                        (torch.int32, float("nan"))):
        with pytest.raises(ValueError, match=rf"fill={fill!r} cannot be held by field's dtype"):
            layout.to_dense(integers.to(dtype), fill=fill)
    assert bool(layout.to_dense(integers.bool(), fill=False)[0].any())
    with pytest.raises(ValueError, match=r"fill=1j cannot be held by field's dtype "
                                         r"torch.float32 \(not complex\)"):
        layout.to_dense(layout.from_dense(volume), fill=1j)  # math.isfinite's bare TypeError
    with pytest.raises(ValueError, match=r"not complex"):  # its imaginary part was dropped
        layout.to_dense(layout.from_dense(volume), fill=np.complex64(1j))
    with pytest.raises(ValueError, match=r"volume\[0\] must be one volume .* got \(2, 3, "):
        layout.from_dense([torch.cat([volume, volume])])  # the second had been dropped


def test_linear_fill_extends_affine_data_exactly_beyond_the_box():
    grid = Grid(shape=(11, 13, 9), spacing=0.5)
    layout = BrickLayout(torch.tensor([[1, 1, 1]]), torch.tensor([0]), [grid])
    k, j, i = torch.meshgrid(*(torch.arange(n, dtype=torch.float64) for n in grid.shape),
                             indexing="ij")
    affine = (0.3 * k - 1.2 * j + 2.0 * i + 0.7)[None, None]
    packed = layout.from_dense(affine, fill="linear")
    kk, jj, ii = (layout.node_index()[0].to(torch.float64))
    assert torch.allclose(packed[0, 0], 0.3 * kk - 1.2 * jj + 2.0 * ii + 0.7)


def test_dilate_matches_the_dense_ring_on_stored_nodes():
    layout, grid = _scattered_layout(seed=3)
    mask = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(4)) < 0.02
    packed = layout.from_dense(mask.double()) > 0
    packed &= layout.inside
    (grown,) = layout.to_dense(layout.dilate(packed).double(), fill=-1.0)
    (kept,) = layout.to_dense(packed.double())
    dense = with_ring(kept > 0)
    valid = layout.to_dense(layout.interior(1).double(), fill=0.0)[0] > 0
    assert torch.equal((grown > 0) & valid, dense & valid)


def test_interior_marks_nodes_whose_neighbours_are_all_stored():
    grid = Grid(shape=(24, 8, 8), spacing=1.0)
    layout = BrickLayout(torch.tensor([[0, 0, 0], [1, 0, 0]]), torch.tensor([0, 0]), [grid])
    inner = layout.interior(2)
    # brick 0: only its +z neighbour is stored; two nodes from every other face
    expected = torch.zeros(BRICK, BRICK, BRICK, dtype=torch.bool)
    expected[2:, 2:6, 2:6] = True
    assert torch.equal(inner[0, 0], expected)
    layout = BrickLayout(torch.tensor([[a, b, c] for a in range(3) for b in range(3)
                                       for c in range(3)]), torch.zeros(27, dtype=torch.long),
                         [Grid(shape=(24, 24, 24), spacing=1.0)])
    centre = layout.interior(2)[13, 0]
    assert centre.all()
    corner = layout.interior(2)[0, 0]
    assert corner[2:, 2:, 2:].all() and not corner[:2].any()


def test_colours_repeat_with_period_three_in_grid_indices():
    layout, _ = _scattered_layout(seed=5)
    index = layout.node_index()
    expected = (index[:, 0] % 3) * 9 + (index[:, 1] % 3) * 3 + index[:, 2] % 3
    assert torch.equal(layout.colours()[:, 0], expected)


def test_bricks_of_mask_and_entries_of_different_boxes():
    grids = [Grid(shape=(20, 20, 20), spacing=0.1), Grid(shape=(9, 40, 12), spacing=0.1)]
    masks = [torch.zeros(g.shape, dtype=torch.bool) for g in grids]
    masks[0][10, 10, 10] = True
    masks[1][8, 39, 0] = True
    layout = bricks_of_mask(masks, grids)
    assert layout.counts() == [1, 1]
    assert layout.coords.tolist() == [[1, 1, 1], [1, 4, 0]]
    assert not layout.present[:, :13].any() and not layout.present[:, 14:].any()


def test_a_mask_not_of_its_grids_shape_is_named():
    """A (5, 5, 5) mask for a (29, 35, 45) grid gave a layout of one brick without a word."""
    grid = Grid(shape=(29, 35, 45), spacing=0.1)
    for mask in (torch.ones(5, 5, 5, dtype=torch.bool), torch.ones(45, 35, 29, dtype=torch.bool)):
        with pytest.raises(ValueError, match=r"masks\[0\] must be a tensor of its grid's shape "
                                             r"\(29, 35, 45\), got \(" + str(mask.shape[0])):
            bricks_of_mask([mask], [grid])
    mask = torch.zeros(grid.shape, dtype=torch.uint8)
    mask[2, 2, 2] = mask[12, 2, 2] = 1
    assert len(bricks_of_mask([mask], [grid])) == 2


def test_a_mask_that_is_not_bool_is_refused():
    """A float mask of 0.5 or an integer one of 256 had stored nothing there (cast to uint8)."""
    grid = Grid(shape=(16, 8, 8), spacing=0.1)
    for dtype, value in ((torch.float32, 0.5), (torch.int64, 256)):
        mask = torch.zeros(grid.shape, dtype=dtype)
        mask[2, 2, 2] = mask[12, 2, 2] = value
        with pytest.raises(TypeError, match=rf"masks\[0\] must be a bool \(or uint8\) tensor, "
                                            rf"got {dtype}"):
            bricks_of_mask([mask], [grid])


@pytest.mark.parametrize("coords, batch, grids, message", [
    ([[0, 0, 0]], [0], [Grid((8, 8, 8), 0.1), Grid((8, 8, 8), 0.2)], "one spacing"),
    ([[0, 0, 0], [0, 0, 0]], [0, 0], [Grid((8, 8, 8), 0.1)], "repeat"),
    ([[1, 0, 0]], [0], [Grid((8, 8, 8), 0.1)], "inside"),
    ([[0, 0]], [0], [Grid((8, 8, 8), 0.1)], r"\(N, 3\)"),
    ([[0, 0, 0]], [1], [Grid((8, 8, 8), 0.1)], "batch indices"),
])
def test_bad_tables_are_refused(coords, batch, grids, message):
    with pytest.raises(ValueError, match=message):
        BrickLayout(torch.tensor(coords), torch.tensor(batch), grids)


def test_bad_tables_of_fractions_or_bools_are_refused_not_truncated():
    grid = Grid((16, 16, 16), 0.1)
    with pytest.raises(TypeError, match="coords must hold integers .* torch.float32"):
        BrickLayout(torch.tensor([[1.9, 0.2, 0.7]]), torch.tensor([0]), [grid])
    with pytest.raises(TypeError, match="batch must hold integers .* torch.bool"):
        BrickLayout(torch.tensor([[1, 0, 0]]), torch.tensor([False]), [grid])
    assert BrickLayout([[1, 0, 0]], [0], [grid]).coords.dtype == torch.int64


def test_fields_of_the_wrong_shape_are_refused_with_the_expected_shape():
    layout, _ = _scattered_layout()
    with pytest.raises(ValueError, match=rf"\({len(layout)}, C, 8, 8, 8\)"):
        layout.check_field(torch.zeros(len(layout) + 1, 1, 8, 8, 8), "u")
    expected = rf"must be a packed band field of shape \({len(layout)}, C, 8, 8, 8\)"
    for wrong in (torch.zeros(len(layout) + 3, 1, 8, 8, 8), torch.zeros(len(layout), 8, 8, 8),
                  torch.zeros(len(layout), 1, 6, 6, 6)):
        with pytest.raises(ValueError, match="field " + expected):
            layout.halo(wrong)
        with pytest.raises(ValueError, match="x " + expected):
            layout.entry_max(wrong)
        with pytest.raises(ValueError, match="mask " + expected):
            layout.dilate(wrong.bool())
    with pytest.raises(ValueError, match="mask must be a bool field"):
        layout.dilate(torch.zeros(len(layout), 1, 8, 8, 8))
    with pytest.raises(ValueError, match="width must be an integer in"):
        layout.halo(torch.zeros(len(layout), 1, 8, 8, 8), 1.5)


def test_from_dense_refuses_an_unknown_fill_and_reads_non_contiguous_volumes():
    grid = Grid(shape=(9, 9, 9), spacing=1.0)
    layout = BrickLayout(torch.tensor([[0, 0, 0], [1, 1, 1]]), torch.tensor([0, 0]), [grid])
    volume = torch.randn(1, 9, 9, 9).transpose(1, 3)
    with pytest.raises(ValueError, match="fill"):
        layout.from_dense([volume], fill="zeros")
    packed = layout.from_dense([volume])
    assert torch.equal(packed[0, 0], volume[0, :8, :8, :8])
