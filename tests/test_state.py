"""Module state: what ``state_dict`` holds of surfaces and adapters, and what loading changes.

A surface is derived from ``phi`` and its grid; loading another surface's state (directly, or
inside an adapter or a user's model) must give that surface, never keep the former geometry
under the loaded buffers.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
import trimesh

import torchsurf as ts
from torchsurf import bricks


def _sphere_mesh(radius: float, shift: tuple[float, float, float]) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    mesh.apply_translation(shift)
    return mesh


def test_a_surface_loaded_from_another_is_that_surface():
    grid = ts.Grid.cube(24, 1.5)
    phi_a = ts.sdf.sphere(grid, radius=1.0)
    phi_b = ts.sdf.torus(grid, 0.9, 0.35)
    kept_b = phi_b.clone()
    a, b = ts.ImplicitSurface(phi_a, grid), ts.ImplicitSurface(phi_b, grid, band_width=0.4)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    before_a = phi_a.clone()
    assert a.load_state_dict(b.state_dict()).missing_keys == []
    assert torch.equal(phi_a, before_a)  # the caller's tensors are never written to
    assert torch.equal(a.phi, b.phi) and a.phi is not b.phi and a.band_width == 0.4
    torch.testing.assert_close(ts.laplace_beltrami(u, a), ts.laplace_beltrami(u, b),
                               rtol=0, atol=0)
    torch.testing.assert_close(ts.HeatFlow(0.01)(u, a), ts.HeatFlow(0.01)(u, b), rtol=0, atol=0)
    phi_b.mul_(2.0)  # a later edit of the source's phi does not reach the loaded copy
    assert torch.equal(a.phi, kept_b)


def test_a_surface_state_survives_a_weights_only_file_and_changes_dtype_and_grid():
    grid = ts.Grid.cube(20, 1.5)
    other = ts.Grid((20, 20, 20), grid.spacing, (-1.4, -1.5, -1.3))
    source = ts.ImplicitSurface(ts.sdf.sphere(other, radius=1.0, center=(0.1, 0.0, 0.2)), other)
    buffer = io.BytesIO()
    torch.save(source.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)
    target = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=0.8), grid).double()
    target.load_state_dict(state)
    assert target.grid == other and target.phi.dtype == torch.float64
    torch.testing.assert_close(target.normal.float(), source.normal)


def test_a_surface_refuses_a_state_of_another_shape_by_name():
    small, large = ts.Grid.cube(16, 1.5), ts.Grid.cube(20, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(small), small)
    with pytest.raises(ValueError, match=r"loaded phi has shape \(1, 1, 20, 20, 20\) but this "
                                         r"surface's phi has \(1, 1, 16, 16, 16\)"):
        surface.load_state_dict(ts.ImplicitSurface(ts.sdf.sphere(large), large).state_dict())


def test_a_model_holding_a_surface_loads_the_other_models_surface():
    grid = ts.Grid.cube(20, 1.5)

    class Model(torch.nn.Module):
        def __init__(self, radius: float) -> None:
            super().__init__()
            self.surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=radius), grid)
            self.operator = ts.LaplaceBeltrami()

        def forward(self, u: torch.Tensor) -> torch.Tensor:
            return self.operator(u, self.surface)

    a, b = Model(0.8), Model(1.1)
    a.load_state_dict(b.state_dict())
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(1))
    assert torch.equal(a(u), b(u))


def test_a_brick_surface_loads_another_layout():
    grid = ts.Grid.cube(40, 1.5)
    h = grid.spacing
    a = bricks.from_dense(ts.ImplicitSurface(ts.sdf.sphere(grid, 0.6, (-4 * h, 0, 0)), grid))
    b = bricks.from_dense(ts.ImplicitSurface(ts.sdf.sphere(grid, 0.6, (4 * h, 0, 0)), grid))
    assert len(a.layout) == len(b.layout)
    assert not torch.equal(a.layout.coords, b.layout.coords)
    a.load_state_dict(b.state_dict())
    assert torch.equal(a.layout.coords, b.layout.coords)
    u = torch.rand(len(b.layout), 1, 8, 8, 8, generator=torch.Generator().manual_seed(2))
    assert torch.equal(ts.laplace_beltrami(u, a), ts.laplace_beltrami(u, b))
    assert torch.equal(a.band_mask(), b.band_mask())


def test_a_mesh_adapter_loaded_from_another_mesh_is_that_meshs_adapter():
    grid = ts.Grid.cube(24, 1.5)
    first = _sphere_mesh(0.8, (0.0, 0.0, 0.0))
    second = _sphere_mesh(0.8, (grid.spacing, 0.0, 0.0))
    a, b = ts.MeshAdapter(first, grid), ts.MeshAdapter(second, grid)
    a.load_state_dict(b.state_dict())
    values = torch.randn(1, 1, len(first.vertices), generator=torch.Generator().manual_seed(3))
    flow = ts.HeatFlow(0.01)
    assert torch.equal(a.phi, b.phi)
    assert torch.equal(a.decode(flow(a.encode(values), a.surface)),
                       b.decode(flow(b.encode(values), b.surface)))


def test_a_mesh_batch_adapter_keeps_its_adapters_and_surface_with_the_loaded_shapes():
    squashed = trimesh.creation.icosphere(subdivisions=2)
    squashed.apply_scale((1.0, 0.8, 0.6))
    turned = squashed.copy()
    turned.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 0, 1)))
    a = ts.MeshBatchAdapter([squashed], resolution=24)
    b = ts.MeshBatchAdapter([turned], resolution=24)
    a.load_state_dict(b.state_dict())
    assert torch.equal(a.adapters[0].phi, b.adapters[0].phi)
    assert torch.equal(a.surface.phi, b.phi) and a.surface.phi is a.phi
    assert torch.equal(a.surface.normal, b.surface.normal)


def test_a_brick_mesh_adapter_loaded_from_another_mesh_encodes_onto_its_bricks():
    grid = ts.Grid.cube(40, 1.5)
    h = grid.spacing
    first = _sphere_mesh(0.6, (-4 * h, 0.0, 0.0))
    second = _sphere_mesh(0.6, (4 * h, 0.0, 0.0))  # one brick along x
    a, b = bricks.BrickMeshAdapter(first, grid), bricks.BrickMeshAdapter(second, grid)
    assert len(a.surface.layout) == len(b.surface.layout)
    a.load_state_dict(b.state_dict())
    values = [torch.randn(len(first.vertices), 1, generator=torch.Generator().manual_seed(4))]
    assert torch.equal(a.surface.to_dense(a.encode(values))[0],
                       b.surface.to_dense(b.encode(values))[0])
    assert all(torch.equal(x, y) for x, y in zip(a.decode(a.encode(values)),
                                                 b.decode(b.encode(values)), strict=True))


@pytest.mark.parametrize("layout", ["dense", "bricks"])
def test_a_new_band_width_is_the_band_every_flow_and_layer_uses(layout):
    grid = ts.Grid.cube(32, 1.8)
    x, y, z = grid.points().unbind(-1)
    phi = (((x**2 + y**2 + z**2).sqrt() - 1.0) * (1.5 + 0.3 * x))[None, None]  # not a distance
    h = grid.spacing

    def build(width: float | None) -> ts.ImplicitSurface:
        dense = ts.ImplicitSurface(phi, grid, band_width=width)
        return dense if layout == "dense" else bricks.from_dense(dense, band_width=width)

    surface, fresh = build(None), build(4 * h)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(5))
    if layout == "bricks":
        u = surface.from_dense(u)
    heat = ts.HeatFlow(0.02)
    block = ts.nn.DiffusionBlock(1)
    with torch.no_grad():
        block.mlp[-1].weight.normal_(std=0.3, generator=torch.Generator().manual_seed(0))
        heat(u, surface), block(u, surface)
        surface.band_width = 4 * h
        assert torch.equal(heat(u, surface), heat(u, fresh))
        assert torch.equal(block(u, surface), block(u, fresh))


def test_a_new_eps_derives_the_geometry_again():
    grid = ts.Grid.cube(20, 1.5)
    phi = ts.sdf.sphere(grid)
    surface = ts.ImplicitSurface(phi, grid)
    surface.eps = 0.05
    fresh = ts.ImplicitSurface(phi, grid, eps=0.05)
    assert torch.equal(surface.grad_norm, fresh.grad_norm)
    with pytest.raises(ValueError, match="eps"):
        surface.eps = -1.0
    # eps = 1 shrank the normals to 0.70 without a word, 1e30 made the weight infinite
    for eps in (1.0, 1e30):
        with pytest.raises(ValueError, match=r"eps must be at most 0.1 .*got"):
            surface.eps = eps
        with pytest.raises(ValueError, match=r"eps must be at most 0.1"):
            ts.ImplicitSurface(phi, grid, eps=eps)
    assert surface.eps == 0.05


def test_a_tensor_contrast_is_module_state_and_must_match_the_datas_dtype():
    grid = ts.Grid.cube(20, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 2, *grid.shape, generator=torch.Generator().manual_seed(6))
    a = ts.AnisotropicDiffusion("perona_malik", contrast=torch.tensor([0.5, 0.7]))
    b = ts.AnisotropicDiffusion("perona_malik", contrast=torch.tensor([0.2, 0.3]))
    a.load_state_dict(b.state_dict())
    assert torch.equal(a(u, surface), b(u, surface))
    assert a.double().contrast.dtype == torch.float64
    with pytest.raises(ts.MismatchError, match="contrast is torch.float64 .* u is torch.float32"):
        ts.anisotropic_diffusion(u, surface, "perona_malik", torch.tensor([0.5, 0.7]).double())


def test_fixed_settings_keep_their_dtype_when_the_model_changes_its_own():
    """``model.half()`` rounded a flow's fixed diffusivities and a layer's fixed times to
    float16 (1.3 -> 1.2998; the float32 flow 5.9e-5 off), and ``.float()`` did not undo it:
    they are settings, cast to the data's dtype where they are used."""
    grid = ts.Grid.cube(16, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 2, *grid.shape, generator=torch.Generator().manual_seed(6))

    def model() -> torch.nn.Sequential:
        return torch.nn.Sequential(
            ts.flows.HeatFlow(grid.spacing**2, diffusivity=torch.tensor([1.3, 2.7])),
            ts.flows.AnisotropicFlow(1e-3, "perona_malik", contrast=[0.3, 0.7]),
            ts.nn.LearnedDiffusion(2, time=[1.3, 2.7], learn_time=False),
            ts.AnisotropicDiffusion("perona_malik", contrast=torch.tensor([0.3, 0.7])))

    def run(layers: torch.nn.Sequential, data: torch.Tensor, on: ts.ImplicitSurface):
        flowed = layers[2](layers[1](layers[0](data, on), on), on)
        return flowed + 1e-3 * layers[3](flowed, on)

    expected = run(model(), u, surface)
    converted = model().half().float()
    assert converted[0].diffusivity.values.dtype == torch.float32
    assert torch.equal(run(converted, u, surface), expected)
    doubled = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    result = run(model().double(), u.double(), doubled)
    torch.testing.assert_close(result.float(), expected, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kind", ["dense", "batch", "bricks"])
def test_adapters_keep_their_weights_dtype_when_the_model_changes_its_own(kind):
    """``model.half()`` rounded the adapters' vertices and interpolation weights to float16
    while their surface stayed float32, and ``.float()`` did not undo it (the round trip of
    the vertices' coordinates 3.0e-4 off a fresh adapter)."""
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=0.7)
    mesh.apply_translation((0.05, -0.02, 0.03))

    def make() -> torch.nn.Module:
        if kind == "dense":
            return ts.MeshAdapter(mesh, resolution=14)
        if kind == "batch":
            return ts.MeshBatchAdapter([mesh, mesh], resolution=14)
        return bricks.BrickMeshAdapter(mesh, ts.Grid.cube(20, bound=3.0))

    fresh = make()
    with pytest.warns(RuntimeWarning, match="stays torch.float32"):  # the surface's
        converted = torch.nn.ModuleList([make(), ts.flows.HeatFlow(1e-3)]).half().float()[0]
    for name, tensor in fresh.state_dict().items():
        if isinstance(tensor, torch.Tensor):
            assert torch.equal(converted.state_dict()[name], tensor), name
    if kind == "dense":
        xyz = torch.as_tensor(mesh.vertices, dtype=torch.float32).T[None]
        assert torch.equal(converted.decode(converted.encode(xyz)),
                           fresh.decode(fresh.encode(xyz)))


def test_a_refused_setting_names_its_key():
    """A model of several flows refused a loaded setting as 'diffusivity must hold finite
    positive values', without saying which flow's."""
    model = torch.nn.Sequential(ts.flows.HeatFlow(1e-3, diffusivity=torch.tensor([1.0, 2.0])),
                                ts.flows.HeatFlow(1e-3, diffusivity=torch.tensor([1.0, 2.0])),
                                ts.nn.LearnedDiffusion(2, time=[1.0, 2.0], learn_time=False))
    for key, value in (("1.diffusivity.values", [1.0, -0.5]),
                       ("2.fixed_time", [1.0, 2.0, 3.0])):
        state = model.state_dict()
        state[key] = torch.tensor(value)
        with pytest.raises(ValueError, match=f"loading '{key}': "):
            model.load_state_dict(state)
    assert model[1].diffusivity.values.tolist() == [1.0, 2.0]  # refused before written
    assert model[2].fixed_time.tolist() == [1.0, 2.0]


def test_a_refused_state_leaves_the_surface_as_it_was():
    grid = ts.Grid.cube(16, 1.5)
    other = ts.Grid((16, 16, 16), grid.spacing, (-1.4, -1.5, -1.5))
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    state = ts.ImplicitSurface(ts.sdf.sphere(other), other).state_dict()
    state["_extra_state"] = {**state["_extra_state"], "band_width": -1.0}
    with pytest.raises(ValueError, match="band_width"):
        surface.load_state_dict(state)
    assert surface.grid == grid


@pytest.mark.parametrize("kind", ["dense", "batch", "bricks"])
def test_a_refused_adapter_state_leaves_the_adapter_as_it_was(kind):
    """The state of an adapter of another mesh was refused for its vertices after the surface
    had taken the other mesh's phi: encode -> flow -> decode was then 0.30 off, without a word."""
    small = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    other = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    other.apply_translation((0.15, 0.0, 0.0))
    grid = ts.Grid.cube(40, 1.5)
    build = {"dense": lambda mesh: ts.MeshAdapter(mesh, grid),
             "batch": lambda mesh: ts.MeshBatchAdapter([mesh], resolution=20),
             "bricks": lambda mesh: bricks.BrickMeshAdapter(mesh, grid)}[kind]
    adapter = build(small)
    before = {key: value.clone() for key, value in adapter.state_dict().items()
              if isinstance(value, torch.Tensor)}
    with pytest.raises(ValueError, match="the state of another mesh or grid"):
        adapter.load_state_dict(build(other).state_dict())
    after = adapter.state_dict()
    assert all(torch.equal(after[key], value) for key, value in before.items())
    assert torch.equal(adapter.surface.phi, build(small).surface.phi)


def test_a_contrast_computed_from_a_parameter_is_refused_by_the_module_form():
    """Held as a plain attribute, it failed the second training step with torch's "backward
    through the graph a second time", deepcopy, and .double()."""
    log_contrast = torch.nn.Parameter(torch.tensor([0.0, 0.3]))
    with pytest.raises(ValueError, match="contrast is computed from a parameter"):
        ts.AnisotropicDiffusion("perona_malik", contrast=log_contrast.exp())
    contrast = torch.nn.Parameter(torch.tensor([1.0, 1.3]))
    module = ts.AnisotropicDiffusion("perona_malik", contrast=contrast)
    assert any(p is contrast for p in module.parameters())
    leaf = torch.tensor([0.5, 0.8], requires_grad=True)  # no graph to backpropagate twice
    assert ts.AnisotropicDiffusion("perona_malik", contrast=leaf).contrast is leaf


def test_a_pickled_surface_leaves_what_flows_derived_from_it_behind():
    """A DataLoader's spawned workers receive the dataset's surfaces pickled: after a few flows
    a 24^3 trefoil's pickle was 25 MB (its kept stencils and packed bands) against 0.45 MB
    fresh (0.73 MB now, with the halos formed on first use). The copy derives them again,
    to the same numbers."""
    import pickle

    grid = ts.Grid.cube(24, bound=1.0)
    surface = ts.ImplicitSurface(ts.sdf.trefoil(grid, center=(0.01, 0.0, 0.0)), grid)
    fresh = len(pickle.dumps(surface))
    u = torch.rand(2, 1, 24, 24, 24, generator=torch.Generator().manual_seed(0))
    flows = [ts.HeatFlow(4 * grid.spacing**2), ts.HeatFlow(4 * grid.spacing**2, method="chebyshev")]
    before = [flow(u, surface) for flow in flows]
    blob = pickle.dumps(surface)
    assert len(blob) <= 2 * fresh  # lazily formed halos; not the kept 25 MB
    copy = pickle.loads(blob)
    for flow, expected in zip(flows, before, strict=True):
        assert torch.equal(flow(u, copy), expected)
