"""Shapes of very different sizes, each at its own resolution, in one brick batch: each entry's
heat flow equals the shape alone in its own units, and keeps the maximum principle."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

import torchsurf as ts
from torchsurf import bricks
from torchsurf.flows._integrators import with_ring

MESHES = Path(__file__).resolve().parents[3] / "shared" / "data" / "meshes"
SHARED = ("bunny_closed", "spot", "armadillo", "teapot_closed", "fandisk")


@pytest.fixture(autouse=True)
def eager(monkeypatch):
    """No compiling in the middle of a test (``"auto"`` compiles after a few eager seconds)."""
    monkeypatch.setattr(ts.backend, "COMPILE_PAYBACK_SECONDS", math.inf)


def _signal(points: torch.Tensor, spacing: float) -> torch.Tensor:
    """Smooth data ``(N, 1, 8, 8, 8)`` at batch-frame points ``(N, 3, 8, 8, 8)``, waves of
    about ten cells."""
    x, y, z = (points[:, axis: axis + 1] / spacing for axis in range(3))
    return torch.sin(0.6 * x) * torch.cos(0.45 * (y + z))


def _check_batch_against_each_alone(meshes, resolutions, cells=3.0, dtype=torch.float64):
    """Heat to ``(cells h)^2`` on the batch; each entry against its shape alone (own units,
    own grid, ``shape_time``), and the maximum principle. Returns the largest difference."""
    fitted = bricks.fit_grids(meshes, resolutions)
    surface = bricks.from_mesh(fitted.meshes, fitted.grids, dtype=dtype)
    h = fitted.spacing
    u0 = _signal(surface.layout.points(dtype), h)
    flow_time = (cells * h) ** 2
    u = ts.flows.HeatFlow(time=flow_time)(u0, surface)
    band = surface.band_mask()
    worst = 0.0
    for b, (rows, entry) in enumerate(surface.entries()):
        alone = bricks.from_mesh(meshes[b], fitted.own_grid(b), dtype=dtype)
        assert torch.equal(alone.layout.coords, entry.layout.coords)
        assert torch.equal(alone.band_mask(), band[rows])
        scale = float(fitted.scale[b])
        own_points = alone.layout.points(dtype)
        centre = fitted.centre[b].to(dtype).view(1, 3, 1, 1, 1)
        alone_u = ts.flows.HeatFlow(time=float(fitted.shape_time(flow_time)[b]))(
            _signal(scale * (own_points - centre), h), alone)
        on_band = band[rows]
        worst = max(worst, float((alone_u - u[rows])[on_band].abs().max()))
        region = with_ring(on_band, entry.layout)
        start = u0[rows][region]
        assert float(u[rows][on_band].max()) <= float(start.max()) + 1e-12, b
        assert float(u[rows][on_band].min()) >= float(start.min()) - 1e-12, b
        assert float(u[rows][on_band].std()) < 0.95 * float(u0[rows][on_band].std()), b
    return worst


def test_fit_grids_gives_each_mesh_its_resolution_at_one_spacing():
    meshes = [trimesh.creation.icosphere(2, radius=3.0), trimesh.creation.box((0.2, 0.1, 0.05))]
    fitted = bricks.fit_grids(meshes, [24, 40], margin=5)
    assert [g.shape for g in fitted.grids] == [(24,) * 3, (40,) * 3]
    assert fitted.spacing == pytest.approx(1 / 39) and fitted.grids[0].spacing == fitted.spacing
    for b, mesh in enumerate(fitted.meshes):
        extent = mesh.bounds[1] - mesh.bounds[0]
        assert extent.max() == pytest.approx((fitted.grids[b].shape[0] - 11) * fitted.spacing)
        assert mesh.bounds.sum(axis=0) == pytest.approx([0, 0, 0], abs=1e-12)
    own = fitted.own_grid(1)
    assert own.spacing == pytest.approx(0.2 / 29)
    corner = torch.tensor([own.origin], dtype=torch.float64)
    back = fitted.to_shape(torch.tensor([fitted.grids[1].origin], dtype=torch.float64), 1)
    torch.testing.assert_close(back, corner)
    torch.testing.assert_close(fitted.shape_time(1.0), fitted.scale**-2)


def test_fit_grids_refuses_bad_input_by_name():
    sphere = trimesh.creation.icosphere(1)
    with pytest.raises(ValueError, match="resolutions must hold one number per mesh"):
        bricks.fit_grids([sphere, sphere], [32])
    with pytest.raises(ValueError, match=r"resolutions\[0\] = 12 leaves no cells"):
        bricks.fit_grids([sphere], 12, margin=6)
    with pytest.raises(TypeError, match="meshes must be a sequence"):
        bricks.fit_grids(sphere, 32)
    with pytest.raises(ValueError, match="entry must be an integer in"):
        bricks.fit_grids([sphere], 32).own_grid(1)
    # an audit's: a pair was split into two meshes, an array of resolutions refused, a float or
    # bool entry failed inside torch
    with pytest.raises(TypeError, match=r"^meshes is one pair \(vertices, faces\)"):
        bricks.fit_grids((np.asarray(sphere.vertices), np.asarray(sphere.faces)), 32)
    fitted = bricks.fit_grids([sphere, sphere], np.array([32, 24]))
    assert [g.shape[0] for g in fitted.grids] == [32, 24]
    for entry in (0.5, True):
        with pytest.raises(ValueError, match=r"^entry must be an integer in \[0, 2\), got"):
            fitted.to_shape(torch.zeros(1, 3), entry)
        with pytest.raises(ValueError, match=r"^entry must be an integer in \[0, 2\), got"):
            fitted.own_grid(entry)
    assert fitted.own_grid(np.int64(1)) == fitted.own_grid(1)


def test_heat_flow_on_shapes_of_very_different_sizes_equals_each_shape_alone():
    """A sphere of radius 3, a capsule 0.3 long and a torus 110 wide at 24^3, 32^3, 40^3."""
    meshes = [trimesh.creation.icosphere(3, radius=3.0),
              trimesh.creation.capsule(height=0.2, radius=0.05, count=[24, 24]),
              trimesh.creation.torus(major_radius=40.0, minor_radius=15.0)]
    assert _check_batch_against_each_alone(meshes, [24, 32, 40]) < 1e-12


@pytest.mark.skipif(not (MESHES / "fandisk.obj").exists(), reason="shared meshes not present")
def test_the_five_shared_shapes_at_small_resolutions_equal_each_shape_alone():
    meshes = [ts.mesh.load(MESHES / f"{name}.obj") for name in SHARED]
    assert _check_batch_against_each_alone(meshes, [32, 24, 28, 24, 28], cells=2.0) < 1e-12


@pytest.mark.slow
@pytest.mark.skipif(not (MESHES / "fandisk.obj").exists(), reason="shared meshes not present")
def test_the_five_shared_shapes_at_48_to_96_equal_each_shape_alone():
    meshes = [ts.mesh.load(MESHES / f"{name}.obj") for name in SHARED]
    assert _check_batch_against_each_alone(meshes, [96, 64, 80, 56, 48]) < 1e-12
