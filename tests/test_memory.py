"""Work that cannot fit in memory is refused before it starts, with the estimate."""

from __future__ import annotations

import math
import time

import pytest
import torch
import trimesh

import torchsurf as ts
from torchsurf import _memory
from torchsurf.flows import HeatFlow


@pytest.fixture
def little_memory(monkeypatch):
    """Pretend 1 MiB is available."""
    monkeypatch.setattr(_memory, "available_bytes", lambda device=None: 2**20)
    monkeypatch.delenv(_memory.ENVIRONMENT_SWITCH, raising=False)


def _no_work(*args, **kwargs):
    pytest.fail("work started before the memory check")


def test_available_memory_is_read_on_linux():
    available = _memory.available_bytes()
    if available is None:
        pytest.skip("no /proc/meminfo")
    assert 0 < available < 2**50
    assert _memory.available_bytes("meta") is None


def test_from_mesh_refuses_before_computing_any_distance(little_memory, monkeypatch):
    monkeypatch.setattr(ts._mesh_sdf, "signed_band", _no_work)
    grid = ts.Grid.cube(33, 1.5)
    with pytest.raises(MemoryError, match=r"sdf.from_mesh on a \(33, 33, 33\) grid needs at "
                                          r"least \d+ bytes .* only 1048576 bytes"):
        ts.sdf.from_mesh(trimesh.creation.icosphere(subdivisions=2), grid)
    with pytest.raises(MemoryError, match=r"MeshAdapter on a \(33, 33, 33\) grid needs"):
        ts.MeshAdapter(trimesh.creation.icosphere(subdivisions=2), grid)


def test_shapes_and_surfaces_refuse_before_any_work(little_memory, monkeypatch):
    grid = ts.Grid.cube(65, 1.5)
    monkeypatch.setattr(ts.Grid, "points", _no_work)
    with pytest.raises(MemoryError, match=r"sampling a function on a \(65, 65, 65\) grid"):
        ts.sdf.sphere(grid)
    phi = torch.zeros(2, 1, *grid.shape)
    with pytest.raises(MemoryError, match=r"ImplicitSurface of phi with shape \(2, 1, 65, 65, 65\)"):
        ts.ImplicitSurface(phi, grid)


def test_flows_refuse_before_any_work(monkeypatch):
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u0 = torch.zeros(4, 3, *grid.shape)
    flow = HeatFlow(0.01)
    expected = _memory.flow_bytes(tuple(u0.shape), 1, u0.dtype, False,
                                  int(surface.band_mask().sum()))
    assert expected > 2 * u0.numel() * 4  # the result and a rate at least
    monkeypatch.setattr(_memory, "available_bytes", lambda device=None: expected - 1)
    monkeypatch.setattr(flow, "system", _no_work)
    with pytest.raises(MemoryError, match=rf"HeatFlow on u0 of shape \(4, 3, 17, 17, 17\) needs "
                                          rf"at least {expected} bytes"):
        flow(u0, surface)
    monkeypatch.setenv(_memory.ENVIRONMENT_SWITCH, "0")
    with pytest.raises(pytest.fail.Exception, match="work started"):
        flow(u0, surface)


def test_chebyshev_heat_and_extension_check_too(little_memory):
    """HeatFlow(method="chebyshev") and Extension ran whatever the memory (10^5 channels went
    straight to a 104 GB allocation)."""
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u0 = torch.zeros(16, 3, *grid.shape)  # 1.8 MiB of working volumes at least
    with pytest.raises(MemoryError, match=r"HeatFlow on u0 of shape \(16, 3, 17, 17, 17\)"):
        HeatFlow(0.01, method="chebyshev")(u0, surface)
    with pytest.raises(TypeError, match="times must be a sequence"):  # checked before its len
        HeatFlow(0.01, method="chebyshev")(u0, surface, times=0.005)
    for extension in (ts.flows.Extension(), ts.flows.Extension(method="pde")):
        with pytest.raises(MemoryError, match=r"Extension on u of shape \(16, 3, 17, 17, 17\)"):
            extension(u0, surface)


@pytest.mark.parametrize("value", ["false", "off", "00", "no"])
def test_a_switch_value_that_is_not_0_or_1_is_refused(monkeypatch, value):
    """Only 0 turned the check off; other values kept it on without a word."""
    monkeypatch.setenv(_memory.ENVIRONMENT_SWITCH, value)
    with pytest.raises(ValueError, match=rf"TORCHSURF_MEMORY_CHECK must be 0 .* got '{value}'"):
        _memory.check_fits(1, "work")
    monkeypatch.setenv(_memory.ENVIRONMENT_SWITCH, " 1 ")
    _memory.check_fits(1, "work")


def test_the_results_of_requested_times_are_counted(monkeypatch):
    """200 requested times return 200 results, stacked: they were not counted, and such a call
    passed the check and died in the allocator after the whole flow (an audit, 48^3)."""
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u0 = torch.zeros(4, 1, *grid.shape)
    flow = HeatFlow(0.01)
    band = int(surface.band_mask().sum())
    alone = _memory.flow_bytes(tuple(u0.shape), 1, u0.dtype, False, band)
    expected = _memory.flow_bytes(tuple(u0.shape), 1, u0.dtype, False, band, snapshots=200)
    assert expected == alone + 2 * 200 * u0.numel() * 4
    monkeypatch.setattr(_memory, "available_bytes", lambda device=None: expected - 1)
    monkeypatch.setattr(flow, "system", _no_work)
    with pytest.raises(MemoryError, match=rf"needs at least {expected} bytes"):
        flow(u0, surface, times=torch.linspace(0, 0.01, 201)[1:].tolist())


def test_a_run_that_fits_is_not_refused():
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    assert HeatFlow(0.01)(torch.zeros(1, 1, *grid.shape), surface).shape == (1, 1, 17, 17, 17)


def test_from_mesh_on_a_3000_cubed_grid_is_refused_at_once():
    grid = ts.Grid.cube(3000, 1.5)
    available = _memory.available_bytes()
    if available is None or available > 16 * math.prod(grid.shape):
        pytest.skip("needs Linux with less than 432 GB available")
    start = time.perf_counter()
    with pytest.raises(MemoryError, match=r"needs at least \d+ bytes .*only \d+ bytes"):
        ts.sdf.from_mesh(trimesh.creation.icosphere(subdivisions=2), grid)
    with pytest.raises(MemoryError, match="sampling a function"):
        ts.sdf.sphere(grid)
    assert time.perf_counter() - start < 5.0


def test_a_device_torch_cannot_read_is_named():
    """``device="gpu"`` raised torch's own RuntimeError from inside the memory check."""
    grid = ts.Grid.cube(9, 1.0)
    with pytest.raises(ValueError, match="device must name a torch device.*'gpu'"):
        ts.sdf.sphere(grid, 0.5, device="gpu")


def test_every_entry_taking_a_device_names_one_torch_cannot_read():
    """The entries that build tensors from meshes or grids raised torch's raw RuntimeError."""
    import trimesh

    from torchsurf import bricks

    grid = ts.Grid.cube(12, 1.5)
    mesh = trimesh.creation.icosphere(subdivisions=1)
    entries = {
        "Grid.points": lambda: grid.points(device="gpu"),
        "sdf.from_mesh": lambda: ts.sdf.from_mesh(mesh, grid, device="gpu"),
        "MeshAdapter": lambda: ts.MeshAdapter(mesh, resolution=12, device="gpu"),
        "MeshBatchAdapter": lambda: ts.MeshBatchAdapter([mesh], resolution=12, device="gpu"),
        "bricks.BrickMeshAdapter": lambda: bricks.BrickMeshAdapter(mesh, grid, device="gpu"),
    }
    for name, call in entries.items():
        with pytest.raises(ValueError, match="device must name a torch device.*'gpu'"):
            call()
            pytest.fail(name)


def test_an_adapter_counts_its_decoding_weights(monkeypatch):
    """The order=2 weights of a mesh's vertices dominate the adapter's memory (bunny, 35k
    vertices: 374 MB live at 32^3 against an estimate of 1.9 MB that left them out)."""
    mesh = trimesh.creation.icosphere(subdivisions=6)  # 40,962 vertices
    grid = ts.mesh.fit_grid(mesh, 16)
    both = [_memory.mesh_adapter_bytes(grid.shape, grid.spacing, 3 * grid.spacing,
                                       float(mesh.area), None, len(mesh.vertices), order)
            for order in (1, 2)]
    assert both[1] - both[0] >= 8_000 * len(mesh.vertices)
    monkeypatch.setattr(_memory, "available_bytes", lambda device=None: (both[0] + both[1]) // 2)
    monkeypatch.delenv(_memory.ENVIRONMENT_SWITCH, raising=False)
    ts.MeshAdapter(mesh, grid, order=1)
    with pytest.raises(MemoryError, match="MeshAdapter"):
        ts.MeshAdapter(mesh, grid, order=2)


def test_bricks_from_a_mesh_far_larger_than_the_cells_are_refused_before_any_work(monkeypatch):
    """A trefoil mesh 300 units across at h = 0.035 ran for six minutes, then failed
    allocating 30 GiB in the distances' refinement: its band alone needs 111 GiB."""
    monkeypatch.setattr(_memory, "available_bytes", lambda device=None: 2**30)
    monkeypatch.delenv(_memory.ENVIRONMENT_SWITCH, raising=False)
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    grid = ts.Grid.cube(24, bound=80.0)
    fine = ts.Grid((8000,) * 3, 0.02, (-80.0,) * 3)
    assert ts.bricks.from_mesh(mesh, grid).batch_size == 1
    with pytest.raises(MemoryError, match=r"bricks of 1 mesh\(es\) of total area .* needs at least"):
        ts.bricks.from_mesh(mesh, fine)
