"""torchsurf.shape_batch: several meshes and analytic shapes on one normalised grid."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

import torchsurf as ts
from torchsurf.shape_batch import AnalyticShape, MeshBatchAdapter

SPOT = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "meshes" / "spot.obj"


@pytest.fixture(scope="module")
def batch() -> MeshBatchAdapter:
    box = trimesh.creation.box(extents=(4.0, 2.0, 1.0))
    box.apply_translation((10.0, -3.0, 1.0))
    ellipsoid = trimesh.creation.icosphere(subdivisions=3)
    ellipsoid.apply_scale((0.2, 0.3, 0.1))
    return MeshBatchAdapter(
        [ellipsoid, box, AnalyticShape("sphere", {"radius": 3.0, "center": (1.0, 2.0, 3.0)})],
        resolution=33, size=1.0, dtype=torch.float64,
    )


def test_shapes_share_one_normalised_grid(batch: MeshBatchAdapter) -> None:
    assert batch.phi.shape == (3, 1, 33, 33, 33)
    assert batch.surface.batch_size == 3
    assert batch.grid == ts.Grid.cube(33, bound=0.65)
    torch.testing.assert_close(batch.scale, torch.tensor([1 / 0.6, 1 / 4.0, 1 / 6.0],
                                                         dtype=torch.float64))
    torch.testing.assert_close(batch.centre[1], torch.tensor([10.0, -3.0, 1.0],
                                                             dtype=torch.float64))
    for vertices in batch.vertices:  # every box centred, longest side 1
        low, high = vertices.min(0).values, vertices.max(0).values
        assert float((high - low).max()) == pytest.approx(1.0, abs=2 * batch.grid.spacing)
        assert float((high + low).abs().max()) < 2 * batch.grid.spacing


def test_analytic_phi_is_exact_and_scaled(batch: MeshBatchAdapter) -> None:
    points = batch.grid.points(dtype=torch.float64)
    expected = points.norm(dim=-1) - 0.5  # radius 3 scaled by 1/6
    torch.testing.assert_close(batch.phi[2, 0], expected)
    # a mesh's phi is the distance to the scaled mesh, in normalised units
    box = batch.phi[1, 0]
    assert float(box[16, 16, 16]) == pytest.approx(-0.125, abs=1e-9)  # half of 1/4 (z extent)


def test_encode_decode_lists(batch: MeshBatchAdapter) -> None:
    values = [torch.stack((v[:, 0], v[:, 1] * v[:, 2] + 1.0), dim=1) for v in batch.vertices]
    originals = [v.clone() for v in values]
    volume = batch.encode(values)
    assert volume.shape == (3, 2, 33, 33, 33)
    decoded = batch.decode(volume)
    for out, value, original in zip(decoded, values, originals, strict=True):
        assert out.shape == value.shape
        torch.testing.assert_close(value, original)
        assert float((out - value).abs().max()) < 0.01
    # each entry of the batch is that shape's own adapter
    torch.testing.assert_close(volume[1:2], batch.adapters[1].encode(values[1].T[None]))
    assert torch.equal(batch(values), volume)  # called, it encodes, as MeshAdapter does


def test_shape_time_converts_by_the_square_of_the_scale(batch: MeshBatchAdapter) -> None:
    torch.testing.assert_close(batch.shape_time(0.01),
                               0.01 / torch.tensor([1 / 0.6, 0.25, 1 / 6.0],
                                                   dtype=torch.float64) ** 2)


def test_a_flow_on_the_batch_matches_each_shape_alone() -> None:
    shapes = [AnalyticShape("sphere"), AnalyticShape("torus", {"minor_radius": 0.35})]
    batch = MeshBatchAdapter(shapes, resolution=25, dtype=torch.float64)
    values = [v[:, 2:3].clone() for v in batch.vertices]
    flow = ts.HeatFlow(time=2e-3)
    together = flow(batch.encode(values), batch.surface)
    for b in range(2):
        alone = flow(batch.encode(values)[b:b + 1], ts.ImplicitSurface(batch.phi[b:b + 1],
                                                                         batch.grid))
        torch.testing.assert_close(together[b:b + 1], alone)


def test_load_state_dict_derives_the_surface_from_the_loaded_phi() -> None:
    """The surface is built on the adapter's phi buffer, which loading copies into in place:
    its normals and weight are those of the loaded phi (its own state, or a changed one)."""
    sphere = MeshBatchAdapter([AnalyticShape("sphere", {"radius": 1.0})], resolution=21)
    u = torch.rand(1, 1, 21, 21, 21, generator=torch.Generator().manual_seed(0))
    before = ts.laplace_beltrami(u, sphere.surface)
    grad_norm = sphere.surface.grad_norm.clone()
    sphere.load_state_dict(sphere.state_dict())
    torch.testing.assert_close(ts.laplace_beltrami(u, sphere.surface), before)
    data = ts.datasets.SignalDataset(sphere, length=2)  # built on the adapter: its own phi
    item = data[1]["noisy"]
    state = sphere.state_dict()
    state["phi"] = 2.0 * state["phi"]
    sphere.load_state_dict(state)
    assert torch.equal(sphere.surface.phi, state["phi"])
    torch.testing.assert_close(sphere.surface.grad_norm, 2.0 * grad_norm)
    assert torch.equal(data[1]["noisy"], item)


def test_analytic_shape_bounds() -> None:
    low, high = AnalyticShape("torus", {"major_radius": 1.0, "minor_radius": 0.3}).bounds()
    np.testing.assert_allclose(high, [1.3, 1.3, 0.3])
    low, high = AnalyticShape("capsule").bounds()
    np.testing.assert_allclose(low, [-0.4, -0.4, -0.9])
    low, high = AnalyticShape("trefoil", {"scale": 0.4, "tube_radius": 0.1}).bounds()
    grid = ts.Grid.cube(65, bound=1.6)
    inside = ts.sdf.trefoil(grid, tube_radius=0.1, scale=0.4)[0, 0] < 0
    points = grid.points()[inside]
    assert (points.min(0).values.numpy() >= low - 1e-6).all()
    assert (points.max(0).values.numpy() <= high + 1e-6).all()
    assert float(points[:, 0].max()) > high[0] - grid.spacing


def test_bad_input_raises() -> None:
    with pytest.raises(ValueError, match="name must be one of"):
        AnalyticShape("cube")
    with pytest.raises(ValueError, match="grid"):
        AnalyticShape("sphere", {"grid": None})
    with pytest.raises(TypeError, match="shapes must be a sequence"):
        MeshBatchAdapter(AnalyticShape("sphere"))
    with pytest.raises(ValueError, match="at least one shape"):
        MeshBatchAdapter([])
    with pytest.raises(ValueError, match=r"shapes\[1\]"):
        MeshBatchAdapter([AnalyticShape("sphere"), (np.zeros((0, 3)), np.zeros((0, 3), int))])
    batch = MeshBatchAdapter([AnalyticShape("sphere")], resolution=13)
    count = len(batch.vertices[0])
    with pytest.raises(ValueError, match="one per shape"):
        batch.encode(torch.zeros(count, 1))
    with pytest.raises(ValueError, match=r"values\[0\] must have shape"):
        batch.encode([torch.zeros(count + 1, 1)])
    with pytest.raises(TypeError, match=r"values\[0\] must be a floating-point"):
        batch.encode([torch.zeros(count, 1, dtype=torch.int64)])
    pair = MeshBatchAdapter([AnalyticShape("sphere"), AnalyticShape("sphere")], resolution=13)
    with pytest.raises(ValueError, match=r"values\[1\] has 1 channels of torch.float64"):
        pair.encode([torch.zeros(count, 1), torch.zeros(count, 1, dtype=torch.float64)])
    with pytest.raises(ValueError, match=r"values\[1\] has 2 channels"):
        pair.encode([torch.zeros(count, 1), torch.zeros(count, 2)])
    with pytest.raises(ValueError, match="volume must hold the 1 shapes"):
        batch.decode(torch.zeros(2, 1, 13, 13, 13))
    with pytest.raises(ts.MismatchError, match=r"values\[0\] is torch.float64 .* adapter is torch.float32"):
        batch.encode([torch.zeros(count, 1, dtype=torch.float64)])
    with pytest.raises(ts.MismatchError, match=r"volume is torch.float64 .* adapter is torch.float32"):
        batch.decode(torch.zeros(1, 1, 13, 13, 13, dtype=torch.float64))


def test_errors_name_the_shape_or_the_argument() -> None:
    """A shape too thin for the grid names its index and the remedy; a bad ``order`` or
    ``band_width`` names the argument, not the first shape."""
    with pytest.raises(ValueError, match=r"shapes\[1\]: box .* not resolved .* raise resolution"):
        MeshBatchAdapter([AnalyticShape("sphere"),
                          AnalyticShape("box", {"half_size": (1.0, 1.0, 0.005)})], resolution=16)
    with pytest.raises(ValueError, match=r"^order must be one of"):
        MeshBatchAdapter([AnalyticShape("sphere")], resolution=16, order=0)
    with pytest.raises(ValueError, match=r"^band_width must be at least"):
        MeshBatchAdapter([AnalyticShape("sphere")], resolution=16, band_width=0.001)


def test_an_analytic_shape_keeps_its_own_parameters() -> None:
    """The checked parameters are copied: the caller's dict changed later changes nothing, and
    shapes hash like the frozen dataclass they are."""
    parameters = {"radius": 0.5}
    shape = AnalyticShape("sphere", parameters)
    parameters["radius"] = -2.0
    assert shape.parameters == {"radius": 0.5}
    assert hash(shape) == hash(AnalyticShape("sphere", {"radius": 0.5}))
    assert shape == AnalyticShape("sphere", {"radius": 0.5})


def test_parameters_requiring_grad_are_refused_by_the_batch_and_read_by_bounds() -> None:
    """The batch normalises each shape, so its phi is no function of a radius; autograd gave
    -0.625 for a sphere's (finite differences: 0). A tensor centre requiring grad failed in
    ``bounds`` with numpy's error, and the checks warned of a scalar read from a graph."""
    import warnings

    radius = torch.tensor(0.8, dtype=torch.float64, requires_grad=True)
    centre = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        shape = AnalyticShape("sphere", {"radius": radius, "center": centre})
        low, high = shape.bounds()
    assert np.allclose(low, -0.8) and np.allclose(high, 0.8)
    shape.phi(ts.Grid.cube(6, bound=1.0), dtype=torch.float64).sum().backward()
    assert radius.grad is not None and float(radius.grad) != 0.0  # its own phi stays differentiable
    with pytest.raises(ValueError, match=r"^shapes\[1\]: parameters \['radius', 'center'\] require "
                                         r"grad"):
        MeshBatchAdapter([AnalyticShape("torus"), shape], resolution=16)


@pytest.mark.skipif(not SPOT.exists(), reason="shared meshes not present")
def test_mesh_files_and_shapes_mix() -> None:
    batch = MeshBatchAdapter([SPOT, AnalyticShape("trefoil")], resolution=33)
    assert batch.phi.shape == (2, 1, 33, 33, 33)
    assert len(batch.vertices[0]) == 2930
    assert math.isfinite(float(batch.surface.mean_curvature().abs().max()))


def test_a_dtype_conversion_keeps_the_scales_float64_values() -> None:
    """.half() converted scale and centre and back to float64: off by 2.4e-4."""
    shapes = [trimesh.creation.icosphere(subdivisions=2, radius=0.7),
              AnalyticShape("torus", {"major_radius": 1.3, "minor_radius": 0.37})]
    batch = MeshBatchAdapter(shapes, resolution=17)
    scale, centre = batch.scale.clone(), batch.centre.clone()
    for convert in (batch.half, batch.float, batch.double):
        convert()
        assert batch.scale.dtype == torch.float64 and torch.equal(batch.scale, scale)
        assert torch.equal(batch.centre, centre)


def test_a_moved_adapter_keeps_one_phi_with_its_surface():
    """``.double()`` / ``.to()`` moved the adapter's ``phi`` buffer and its surface's apart, so
    an in-place edit of ``adapter.phi`` no longer reached the surface (1.08 apart after x2)."""
    adapter = MeshBatchAdapter([AnalyticShape("sphere"), AnalyticShape("capsule")], resolution=16)
    for move in (lambda m: m.double(), lambda m: m.to(torch.float32), lambda m: m.to("cpu")):
        move(adapter)
        assert adapter.surface.phi is adapter.phi
