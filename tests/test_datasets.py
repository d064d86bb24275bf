"""torchsurf.datasets: random surface signals on batches of shapes, deterministic under a seed."""

from __future__ import annotations

import pytest
import torch
from torch.utils.data import DataLoader

import torchsurf as ts
from torchsurf import datasets
from torchsurf.shape_batch import AnalyticShape, MeshBatchAdapter


@pytest.fixture(scope="module")
def shapes() -> MeshBatchAdapter:
    return MeshBatchAdapter([AnalyticShape("sphere"), AnalyticShape("torus", {"minor_radius": 0.4})],
                            resolution=25, margin=0.15, dtype=torch.float64)


def test_smooth_signal_is_deterministic_in_range_and_smooth(shapes: MeshBatchAdapter) -> None:
    surface = shapes.surface
    u = datasets.smooth_signal(surface, channels=2, frequency=2.0, seed=3)
    assert u.shape == (2, 2, 25, 25, 25) and u.dtype == torch.float64
    torch.testing.assert_close(u, datasets.smooth_signal(surface, channels=2, seed=3))
    assert not torch.equal(u, datasets.smooth_signal(surface, channels=2, seed=4))
    band = surface.band_mask().expand_as(u)
    assert float(u[band].min()) == 0.0 and float(u[band].max()) == 1.0
    # low frequency: neighbouring band nodes differ little
    step = (u[..., 1:] - u[..., :-1]).abs()[band[..., 1:] & band[..., :-1]]
    assert float(step.max()) < 0.35


def test_piecewise_constant_signal_has_few_values(shapes: MeshBatchAdapter) -> None:
    surface = shapes.surface
    u = datasets.piecewise_constant_signal(surface, channels=1, cells=5, seed=1)
    assert u.shape == (2, 1, 25, 25, 25)
    for b in range(2):
        assert 2 <= len(torch.unique(u[b][surface.band_mask()[b]])) <= 5
    torch.testing.assert_close(u, datasets.piecewise_constant_signal(surface, cells=5, seed=1))


def test_signals_are_constant_along_normals() -> None:
    grid = ts.Grid.cube(33, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    u = datasets.smooth_signal(surface, frequency=1.0, seed=0)
    radial = grid.points(dtype=torch.float64)
    direction = radial / radial.norm(dim=-1, keepdim=True)
    # the exact closest point of a sphere is the direction: u at two radii along a ray agrees
    inner = ts.sample(u, 0.95 * direction[16, 16, 20:][None].reshape(-1, 3), grid)
    outer = ts.sample(u, 1.05 * direction[16, 16, 20:][None].reshape(-1, 3), grid)
    assert float((inner - outer).abs().max()) < 0.02


def test_dataset_items_are_deterministic_and_cycle(shapes: MeshBatchAdapter) -> None:
    data = datasets.SignalDataset(shapes, length=6, channels=1, noise=0.1, seed=7,
                                  piecewise_constant={"cells": 6})
    first = data[4]
    again = datasets.SignalDataset(shapes, length=6, noise=0.1, seed=7,
                                   piecewise_constant={"cells": 6})[4]
    torch.testing.assert_close(first["noisy"], again["noisy"])
    assert [data[i]["shape"] for i in range(6)] == [0, 1, 0, 1, 0, 1]
    assert [data[i]["kind"] for i in range(4)] == ["smooth", "smooth", "piecewise_constant",
                                                   "piecewise_constant"]
    noise = first["noisy"] - first["clean"]
    assert 0.08 < float(noise.std()) < 0.12
    other = datasets.SignalDataset(shapes, length=6, noise=0.1, seed=8)[4]
    assert not torch.equal(other["clean"], first["clean"])
    with pytest.raises(IndexError):
        data[6]


def test_dataloader_batches_with_their_surfaces(shapes: MeshBatchAdapter) -> None:
    data = datasets.SignalDataset(shapes, length=4, seed=0)
    batch = next(iter(DataLoader(data, batch_size=3)))
    assert batch["noisy"].shape == (3, 1, 25, 25, 25)
    surface = data.surface(batch["shape"])
    assert surface.batch_size == 3
    torch.testing.assert_close(surface.phi[1], shapes.phi[1])
    assert data.band_mask(batch["shape"]).shape == (3, 1, 25, 25, 25)
    flow = ts.HeatFlow(time=1e-3)
    assert flow(batch["noisy"], surface).shape == batch["noisy"].shape


def test_bad_input_raises(shapes: MeshBatchAdapter) -> None:
    with pytest.raises(ValueError, match="kind"):
        datasets.signal("stripes", shapes.surface)
    with pytest.raises(ValueError, match="kinds"):
        datasets.SignalDataset(shapes, length=2, kinds="smooth")
    with pytest.raises(TypeError, match="shapes must be"):
        datasets.SignalDataset(torch.zeros(1, 1, 5, 5, 5), length=2)
    from torchsurf import bricks

    grid = ts.Grid.cube(25, 1.6)
    packed = bricks.from_dense(ts.ImplicitSurface(ts.sdf.sphere(grid), grid))
    with pytest.raises(TypeError, match="shapes must hold dense volumes"):
        datasets.SignalDataset(packed, length=2)
    with pytest.raises(ValueError, match="noise"):
        datasets.SignalDataset(shapes, length=2, noise=-1.0)
    with pytest.raises(ValueError, match="frequency"):
        datasets.smooth_signal(shapes.surface, frequency=0.0)
    with pytest.raises(ValueError, match="seed"):  # numpy's error on the first item before
        datasets.SignalDataset(shapes, length=2, seed=-1)


def test_derived_seeds_do_not_collide() -> None:
    seeds = {datasets.derived_seed(s, i) for s in range(20) for i in range(20)}
    assert len(seeds) == 400


def test_piecewise_constant_signal_has_as_many_regions_as_asked(shapes: MeshBatchAdapter) -> None:
    # centres drawn with repeats gave 38 or 39 regions for cells=40 in most of these 16 seeds
    surface = shapes.surface
    band = surface.band_mask()[:, 0]
    for seed in range(16):
        u = datasets.piecewise_constant_signal(surface, cells=40, seed=seed)
        assert [len(u[b, 0][band[b]].unique()) for b in range(2)] == [40, 40], seed
    near = surface.distance()[0, 0] <= surface.spacing
    candidates = len(ts.signals.closest_points(surface)[0].permute(1, 2, 3, 0)[near].unique(dim=0))
    with pytest.raises(ValueError, match=f"cells = {candidates + 1} is more than the "
                                         f"{candidates} distinct closest points of the nodes "
                                         "within one spacing of S"):
        datasets.piecewise_constant_signal(surface, cells=candidates + 1)


def test_centres_at_one_closest_point_make_one_candidate() -> None:
    """In float32, nodes on one normal line can share their closest point to the last bit: two
    such centres made one region (seeds 3, 28 and 33 gave 39 regions of 40)."""
    shapes = MeshBatchAdapter([AnalyticShape("sphere"),
                               AnalyticShape("torus", {"minor_radius": 0.3})], resolution=25)
    band = shapes.surface.band_mask()[:, 0]
    for seed in (3, 28, 33):
        u = datasets.piecewise_constant_signal(shapes.surface, cells=40, seed=seed)
        assert [len(u[b, 0][band[b]].unique()) for b in range(2)] == [40, 40], seed


def test_piecewise_constant_regions_do_not_move_with_the_problem() -> None:
    """The regions' nearest-centre test ran torch.cdist's matrix-product form in float32 on
    world coordinates: a sphere moved to 1e3 changed the value of 24% of its band's nodes."""
    grid = ts.Grid.cube(24, 1.5)
    shift = 1e3
    moved_grid = ts.Grid(grid.shape, grid.spacing, tuple(o + shift for o in grid.origin))
    here = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    there = ts.ImplicitSurface(ts.sdf.sphere(moved_grid, center=(shift,) * 3), moved_grid)
    band = here.band_mask()
    a = datasets.piecewise_constant_signal(here, 1, seed=3)
    b = datasets.piecewise_constant_signal(there, 1, seed=3)
    # what is left: nodes within float32's rounding of world coordinates at 1e3 (6e-5) of a
    # region's edge
    assert float((a != b)[band].double().mean()) < 2e-3


def test_the_surface_of_a_batch_is_kept_for_its_shapes():
    """The layers derive their stencils once per surface object: the same shapes give the same
    surface, while among the most recent ones; a pickled dataset (a DataLoader's worker) does
    not carry them."""
    import pickle

    grid = ts.Grid.cube(12, bound=1.5)
    phi = torch.cat([ts.sdf.sphere(grid, 1.0), ts.sdf.torus(grid, 0.8, 0.3)])
    dataset = datasets.SignalDataset(ts.ImplicitSurface(phi, grid), length=4)
    first = dataset.surface([0, 1])
    assert dataset.surface(torch.tensor([0, 1])) is first
    assert dataset.surface([1, 0]) is not first
    torch.testing.assert_close(dataset.surface([1, 0]).phi, phi.flip(0), rtol=0, atol=0)
    for shapes in [[0], [1], [0, 0], [1, 1], [1, 1, 0]][:datasets.KEPT_SURFACES]:
        dataset.surface(shapes)
    assert dataset.surface([0, 1]) is not first  # the least recently used was dropped
    assert pickle.loads(pickle.dumps(dataset))._batch_surfaces == {}


def test_a_dataset_keeps_the_given_surfaces_eps() -> None:
    """It rebuilt its surfaces from phi and the band width: eps = 0.5 became 1e-6, moving the
    normals by 0.10 and the items' clean signals by 0.16 in the band."""
    grid = ts.Grid.cube(17, bound=1.5)
    given = ts.ImplicitSurface(ts.sdf.sphere(grid), grid, band_width=0.4, eps=0.05)
    dataset = datasets.SignalDataset(given, length=2, seed=0, kinds=["smooth"])
    assert dataset.surface([0]).eps == 0.05
    band = given.band_mask()
    expected = datasets.smooth_signal(given, seed=datasets.derived_seed(0, 0))
    torch.testing.assert_close(dataset[0]["clean"][None][band], expected[band])


def test_signal_options_and_shape_indices_are_checked_when_given(shapes: MeshBatchAdapter) -> None:
    """Options were checked at the first item (in a DataLoader's worker), a list of options
    failed in dict(), and shape indices out of range failed bare or, negative, picked a shape
    from the end."""
    with pytest.raises(ValueError, match=r"smooth\['frequency'\] must be a finite positive"):
        datasets.SignalDataset(shapes, length=2, smooth={"frequency": -2.0})
    with pytest.raises(ValueError, match=r"piecewise_constant\['cells'\] must be a whole"):
        datasets.SignalDataset(shapes, length=2, piecewise_constant={"cells": 0})
    with pytest.raises(TypeError, match="smooth must be a dict of smooth_signal's options"):
        datasets.SignalDataset(shapes, length=2, smooth=[1])
    data = datasets.SignalDataset(shapes, length=2)
    for wrong in ([-1], [0, 5]):
        with pytest.raises(IndexError, match=r"shapes must lie in \[0, 2\)"):
            data.surface(wrong)
        with pytest.raises(IndexError, match=r"shapes must lie in \[0, 2\)"):
            data.band_mask(wrong)
    with pytest.raises(ValueError, match="shapes must be a non-empty"):
        data.band_mask([0.5])
    with pytest.raises(TypeError, match="surface must be a torchsurf.ImplicitSurface"):
        datasets.smooth_signal("s")
    with pytest.raises(TypeError, match="surface must be a torchsurf.ImplicitSurface"):
        datasets.piecewise_constant_signal(None)
    # more regions than a shape has candidate centres failed at the first item only
    with pytest.raises(ValueError, match=r"piecewise_constant\['cells'\] = 1000000 is more .* "
                                         r"surface 0"):
        datasets.SignalDataset(shapes, length=2, piecewise_constant={"cells": 10**6})
    datasets.SignalDataset(shapes, length=2, kinds=["smooth"], piecewise_constant={"cells": 10**6})
    with pytest.raises(TypeError, match="index must be an integer, got True"):  # was item 1
        data[True]


def test_seeds_beyond_32_bits_are_refused() -> None:
    """numpy's SeedSequence splits a seed into 32-bit words: derived_seed(2**32 + 5, 0) was
    derived_seed(5, 1), so a dataset seeded 2**32 + 5 repeated another's items."""
    assert datasets.derived_seed(2**32 - 1, 0) != datasets.derived_seed(2**32 - 1, 1)
    with pytest.raises(ValueError, match=r"seed must be a whole number in \[0, 2\*\*32\)"):
        datasets.derived_seed(2**32 + 5, 0)
    with pytest.raises(ValueError, match=r"keys\[1\] must be a whole number in \[0, 2\*\*32\)"):
        datasets.derived_seed(5, 0, 2**32)


def test_derived_seeds_tell_keys_apart_but_trailing_zeros_as_documented():
    from torchsurf.datasets import derived_seed

    assert derived_seed(5, 3) == derived_seed(5, 3, 0) == derived_seed(5, 3, 0, 0)
    assert len({derived_seed(5, 3), derived_seed(5, 3, 1), derived_seed(5, 4),
                derived_seed(6, 3)}) == 4


def test_a_dataset_keeps_as_many_batch_surfaces_as_asked():
    """Batches of 3 over 5 shapes in order cycle through 5 distinct batches: with 4 kept,
    every batch built its surface again (a training step 3.2x slower, an audit, 2026-12-07)."""
    grid = ts.Grid.cube(13, 1.5)
    phis = torch.cat([ts.sdf.sphere(grid, r) for r in (0.5, 0.6, 0.7, 0.8, 0.9)])
    data = datasets.SignalDataset(ts.ImplicitSurface(phis, grid), length=15, kept_surfaces=5)
    order = [[(3 * b + k) % 5 for k in range(3)] for b in range(5)]
    first = [data.surface(shapes) for shapes in order]
    assert all(data.surface(shapes) is kept for shapes, kept in zip(order, first, strict=True))
    with pytest.raises(ValueError, match="kept_surfaces"):
        datasets.SignalDataset(ts.ImplicitSurface(phis, grid), length=15, kept_surfaces=0)
