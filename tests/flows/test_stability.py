"""The flows on the surfaces users bring: meshes' distance fields, thin tubes, scaled phi.

A heat flow obeys the maximum principle, so ``max |u(t)| <= max |u0|`` on every shape; total
variation flows too. These are the cases where the time-dependent band of earlier versions
reached nodes where phi is not a distance and blew up (inf at t = 0.005 on an icosphere's
``from_mesh`` phi, 1e7 on a 0.12 trefoil tube, NaN through ``MeshAdapter`` on the shared meshes).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import pytest
import torch
import trimesh

import torchsurf as ts

MESH_DIR = Path(
    os.environ.get("TORCHSURF_MESH_DIR", Path(__file__).resolve().parents[2] / "../shared/data/meshes")
)
MESHES = ["armadillo.obj", "bunny.obj", "bunny_closed.obj", "fandisk.obj", "spot.obj",
          "teapot.obj", "teapot_closed.obj", "trefoil_knot.obj"]


def mesh_surface(name: str, resolution: int) -> ts.ImplicitSurface:
    path = MESH_DIR / name
    if not path.is_file():
        pytest.skip(f"test mesh {name} not found in {MESH_DIR} (set TORCHSURF_MESH_DIR)")
    return ts.MeshAdapter(trimesh.load(path, force="mesh"), resolution=resolution).surface


def diagonal(surface: ts.ImplicitSurface) -> float:
    """Length of the diagonal of the box around the band, world units."""
    points = surface.grid.points()[surface.band_mask()[0, 0]]
    return float((points.max(0).values - points.min(0).values).norm())


def noise(surface: ts.ImplicitSurface) -> torch.Tensor:
    generator = torch.Generator().manual_seed(0)
    return torch.rand((1, 1, *surface.grid.shape), generator=generator)


def assert_maximum_principle(flow: ts.Flow, surface: ts.ImplicitSurface) -> None:
    u0 = noise(surface)
    with torch.no_grad():
        u = flow(u0, surface)
    band = flow.band_mask(surface).expand_as(u)
    assert torch.isfinite(u).all()
    assert float(u[band].max()) <= float(u0.max()) + 1e-6
    assert float(u[band].min()) >= float(u0.min()) - 1e-6
    # the flow did smooth: the band's spread shrank well below the noise's
    assert float(u[band].std()) < 0.5 * float(u0[band].std())


@pytest.mark.parametrize("name", MESHES)
def test_heat_flow_on_meshes_keeps_the_maximum_principle(name):
    surface = mesh_surface(name, 64)
    time = (0.1 * diagonal(surface)) ** 2
    assert_maximum_principle(ts.HeatFlow(time, path="slicing"), surface)


@pytest.mark.slow
@pytest.mark.parametrize("name", MESHES)
def test_heat_flow_on_meshes_keeps_the_maximum_principle_128(name):
    surface = mesh_surface(name, 128)
    time = (0.1 * diagonal(surface)) ** 2
    assert_maximum_principle(ts.HeatFlow(time), surface)


@pytest.mark.parametrize(
    "name", ["bunny_closed.obj", pytest.param("fandisk.obj", marks=pytest.mark.slow)]
)
def test_total_variation_on_meshes_keeps_the_maximum_principle(name):
    surface = mesh_surface(name, 64)
    size = diagonal(surface)
    flow = ts.AnisotropicFlow(0.1 * size**2, eps=1.0 / size, path="slicing")
    u0 = noise(surface)
    with torch.no_grad():
        u = flow(u0, surface)
    band = flow.band_mask(surface).expand_as(u)
    assert float(u[band].max()) <= float(u0.max()) + 1e-6
    assert float(u[band].min()) >= float(u0.min()) - 1e-6


@pytest.mark.parametrize("tube", [0.12, 0.2])
@pytest.mark.parametrize("resolution", [64, pytest.param(128, marks=pytest.mark.slow)])
def test_heat_flow_on_thin_trefoil_tubes(tube, resolution):
    grid = ts.Grid.cube(resolution, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.trefoil(grid, tube_radius=tube), grid)
    time = (0.1 * diagonal(surface)) ** 2
    assert_maximum_principle(ts.HeatFlow(time, path="slicing"), surface)


@pytest.mark.parametrize("time", [0.005, 0.01])
def test_heat_flow_on_an_icosphere_distance_field(time):
    grid = ts.Grid.cube(64, 1.5)
    phi = ts.sdf.from_mesh(trimesh.creation.icosphere(subdivisions=4), grid)
    surface = ts.ImplicitSurface(phi, grid)
    u0 = torch.randn((1, 1, 64, 64, 64), generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        u = ts.HeatFlow(time, path="slicing")(u0, surface)
    band = surface.band_mask().expand_as(u)
    assert torch.isfinite(u).all()
    assert float(u[band].abs().max()) <= float(u0[band].abs().max())


def test_scaled_phi_gives_the_same_flow():
    """``1000 * phi`` is the same surface: same band, same stable step, same result."""
    grid = ts.Grid.cube(33, 1.5)
    phi = ts.sdf.torus(grid, 0.9, 0.35, dtype=torch.float64)
    u0 = torch.rand((1, 1, 33, 33, 33), generator=torch.Generator().manual_seed(1),
                    dtype=torch.float64)
    results = [ts.HeatFlow(0.01)(u0, ts.ImplicitSurface(scale * phi, grid)) for scale in (1, 1000)]
    torch.testing.assert_close(results[1], results[0], rtol=0, atol=1e-9)


def test_readme_mesh_route_stays_bounded():
    """``MeshAdapter`` then ``HeatFlow`` with their defaults, as the README shows them."""
    path = MESH_DIR / "bunny_closed.obj"
    if not path.is_file():
        pytest.skip(f"test mesh bunny_closed.obj not found in {MESH_DIR}")
    mesh = trimesh.load(path, process=False)
    adapter = ts.MeshAdapter(mesh, resolution=48)
    x = torch.rand(1, 1, len(mesh.vertices), generator=torch.Generator().manual_seed(0))
    u0 = adapter.encode(x)
    size = float(((mesh.bounds[1] - mesh.bounds[0]) ** 2).sum() ** 0.5)
    with torch.no_grad():
        u = ts.HeatFlow(time=(0.03 * size) ** 2)(u0, adapter.surface)
    assert float(u.abs().max()) <= float(u0.abs().max()) * (1 + 1e-6)
    back = adapter.decode(u)
    assert float(back.std()) < float(x.std())


FAST_MESHES = ["bunny.obj", "fandisk.obj"]  # trefoil_knot.obj with -m slow (15 s)
"""Meshes the default run checks the Chebyshev semigroup on; the others run with ``-m slow``."""


def _meshes_fast_first() -> list:
    return [name if name in FAST_MESHES else pytest.param(name, marks=pytest.mark.slow)
            for name in MESHES]


@pytest.mark.parametrize("name", _meshes_fast_first())
@pytest.mark.parametrize("fraction", [0.02, 0.1])
def test_chebyshev_heat_semigroup_keeps_constants_and_the_maximum_principle(name, fraction):
    """``method="chebyshev"`` on a mesh's 3-cell band, where 10-20% of the ring's nodes read
    ring nodes: a constant stays constant to the last bit (it came back in [0.991, 1.25] when the
    ring was read as zeros, within a few float32 ulps before the expansion ran about an offset)
    and noise stays within its range (it grew to 20 at long times)."""
    surface = mesh_surface(name, 48)
    flow = ts.HeatFlow((fraction * diagonal(surface)) ** 2, method="chebyshev", path="slicing")
    band = flow.band_mask(surface)
    with torch.no_grad():
        constant = flow(torch.full((1, 1, *surface.grid.shape), 2.0), surface)
    # exactly: the expansion and the ring's fill run about the first band node's value
    assert float((constant[band] - 2.0).abs().max()) == 0.0
    assert_maximum_principle(flow, surface)


@pytest.mark.parametrize("storage", ["packed", "volume", "bricks"])
def test_the_semigroup_brings_no_extremum_from_its_ring_at_short_times(storage):
    """The ring's unlimited fill overshoots rough data (up to 1.066 from noise in [0, 1) on
    fandisk at 48^3), and the limited re-extension of the result took its bounds from it:
    1.0167 at 1e-6 h^2, and -1.5e-4 from data >= 0 at 32^3. Packed values (phi fixed), the
    volume operators (phi requiring grad) and bricks."""
    path = MESH_DIR / "fandisk.obj"
    if not path.is_file():
        pytest.skip(f"test mesh fandisk.obj not found in {MESH_DIR} (set TORCHSURF_MESH_DIR)")
    mesh = trimesh.load(path, force="mesh")
    grid = ts.mesh.fit_grid(mesh, 48)
    u0 = torch.rand((1, 1, *grid.shape), generator=torch.Generator().manual_seed(0),
                    dtype=torch.float64).float()
    if storage == "bricks":  # the same nodes in a box 3 cells wider a side (bricks need room)
        grid = ts.Grid(tuple(n + 6 for n in grid.shape), grid.spacing,
                       tuple(o - 3 * grid.spacing for o in grid.origin))
        surface = ts.bricks.from_dense(ts.sdf.from_mesh(mesh, grid), grid)
        u0 = surface.layout.from_dense([torch.nn.functional.pad(u0, (3,) * 6)])
    else:
        surface = ts.ImplicitSurface(ts.sdf.from_mesh(mesh, grid).requires_grad_(
            storage == "volume"), grid)
    band = surface.band_mask()
    for layer in (ts.nn.LearnedDiffusion(1, time=1e-6, learn_time=False, path="slicing"),
                  ts.HeatFlow(1e-6 * surface.spacing**2, method="chebyshev", path="slicing")):
        with torch.no_grad():
            u = layer(u0, surface)
        inside = band.expand_as(u)
        assert float(u0.min()) <= float(u[inside].min())
        assert float(u[inside].max()) <= float(u0.max())


@pytest.mark.parametrize("name", ["bunny.obj", "fandisk.obj"])
@pytest.mark.parametrize("time", [0.01, 16.0])
def test_learned_diffusion_keeps_the_maximum_principle_on_meshes(name, time):
    """``LearnedDiffusion`` (one expansion, ``h^2`` units): constants stay constant, noise within
    its range at a short time (the unlimited re-extension of the result overshot it by 5%) and
    a long one."""
    surface = mesh_surface(name, 48)
    layer = ts.nn.LearnedDiffusion(1, time=time, learn_time=False, path="slicing")
    band = surface.band_mask()
    u0 = noise(surface)
    with torch.no_grad():
        constant = layer(torch.ones_like(u0), surface)
        u = layer(u0, surface)
    assert float((constant[band] - 1.0).abs().max()) == 0.0
    assert float(u[band].max()) <= float(u0.max()) + 1e-6
    assert float(u[band].min()) >= float(u0.min()) - 1e-6


def _streak_problem(resolution: int) -> tuple[ts.ImplicitSurface, torch.Tensor, torch.Tensor]:
    """Noise and the swirl ``(-y, x, 0.3)`` on the trefoil mesh's phi (a tube about 2.7 cells
    thick at 32^3, its strands closer than the band at the knot's centre)."""
    path = MESH_DIR / "trefoil_knot.obj"
    if not path.is_file():
        pytest.skip(f"test mesh trefoil_knot.obj not found in {MESH_DIR}")
    mesh = ts.mesh.load(path)
    grid = ts.mesh.fit_grid(mesh, resolution, margin=0.1)
    surface = ts.ImplicitSurface(ts.sdf.from_mesh(mesh, grid), grid)
    x, y, _ = grid.points().unbind(-1)
    direction = torch.stack((-y, x, torch.full_like(x, 0.3)))[None]
    u0 = ts.FlowVisualization.noise(surface, generator=torch.Generator().manual_seed(0))
    return surface, u0, direction


def test_flow_visualization_with_rkc_keeps_the_range_on_a_thin_knot():
    """The default method stays within the noise's range where Euler's steps grow (below)."""
    surface, u0, direction = _streak_problem(32)
    flow = ts.FlowVisualization(200 * surface.spacing**2)
    with torch.no_grad():
        u = flow(u0, surface, direction=direction)
    band = flow.band_mask(surface).expand_as(u)
    assert 0.4 < float(u[band].min()) and float(u[band].max()) < 0.6


def test_a_flow_that_leaves_its_range_warns():
    """Forward Euler's steps of flow visualisation with the band's re-extensions grow on the
    thin knot (to [-0.42, 0.89] from noise in [0, 1] at 100 h^2, docs/band.md §5): the call says
    so, names the method and the remedy, and still returns its result."""
    surface, u0, direction = _streak_problem(32)
    flow = ts.FlowVisualization(100 * surface.spacing**2, method="euler")
    with pytest.warns(RuntimeWarning, match=r"left the range of u0 .*method='rkc'") as caught:
        with torch.no_grad():
            u = flow(u0, surface, direction=direction)
    assert len(caught) == 1 and caught[0].filename == __file__
    band = flow.band_mask(surface).expand_as(u)
    assert float(u[band].min()) < -0.1


def test_the_range_check_runs_on_bricks_too():
    """The same knot built straight into bricks: the check reduces the packed band and ring.
    A batch of two entries is integrated one entry at a time (``forward`` re-entered); the
    warning still names the caller's line."""
    path = MESH_DIR / "trefoil_knot.obj"
    if not path.is_file():
        pytest.skip(f"test mesh trefoil_knot.obj not found in {MESH_DIR}")
    mesh = ts.mesh.load(path)
    grid = ts.mesh.fit_grid(mesh, 32, margin=0.2)
    surface = ts.bricks.from_mesh(mesh, grid)
    x, y, _ = surface.layout.from_dense(grid.points().permute(3, 0, 1, 2)[None]).unbind(1)
    direction = torch.stack((-y, x, torch.full_like(x, 0.3)), dim=1)
    u0 = ts.FlowVisualization.noise(surface, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        rkc = ts.FlowVisualization(100 * surface.spacing**2)(u0, surface, direction=direction)
        pair = ts.bricks.cat([surface, surface])
        with pytest.warns(RuntimeWarning, match="left the range of u0") as caught:
            ts.FlowVisualization(100 * surface.spacing**2, method="euler")(
                torch.cat([u0, u0]), pair, direction=torch.cat([direction, direction]))
    assert {warning.filename for warning in caught} == {__file__}
    band = surface.band_mask().expand_as(rkc)
    assert 0.4 < float(rkc[band].min()) and float(rkc[band].max()) < 0.6


def _range_warnings(caught) -> list:
    return [w for w in caught if "left the range of u0" in str(w.message)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_constant_and_barely_varying_data_do_not_warn(dtype):
    """RKC's stages move a float32 constant by rounding; its range is zero: the check's range
    is at least RANGE_ROUNDING units of the data's magnitude (it warned by 1e31 on 0.3)."""
    grid = ts.Grid.cube(20, 1.2)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.8).to(dtype), grid)
    noise = torch.rand((1, 1, *grid.shape), generator=torch.Generator().manual_seed(0),
                       dtype=dtype)
    flow = ts.HeatFlow(10 * grid.spacing**2)
    for u0 in (torch.full_like(noise, 0.3), torch.full_like(noise, -7.7),
               torch.full_like(noise, 1e4), 1e4 + 0.01 * noise,
               torch.cat([noise, torch.full_like(noise, 0.3)], dim=1)):
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)
            flow(u0, surface)


def test_each_entry_is_held_to_its_own_range_and_a_call_warns_once():
    """Euler beyond its stable step grows on noise; a smooth entry of range 24 in the same batch
    does not hide it, and a batch integrated one entry at a time (entries with different bands)
    warns once."""
    grid = ts.Grid.cube(24, 1.2)
    phi = ts.sdf.sphere(grid, 0.8)
    noise = torch.rand((2, 1, *grid.shape), generator=torch.Generator().manual_seed(0))
    z = grid.points()[..., 2][None, None].float()
    batches = [(ts.ImplicitSurface(phi, grid), torch.cat([noise[:1], 10 * z])),
               (ts.ImplicitSurface(torch.cat([phi, 0.3 * torch.tanh(phi / 0.3)]), grid), noise)]
    for surface, u0 in batches:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            ts.HeatFlow(0.05, method="euler", steps=14)(u0, surface)  # a flow warns once
        assert len(_range_warnings(caught)) == 1, [str(w.message)[:80] for w in caught]
        assert _range_warnings(caught)[0].filename == __file__


@pytest.mark.parametrize("method", ["euler", "heun", "rkc", "implicit", "crank_nicolson",
                                    "midpoint", "rk4"])
@pytest.mark.parametrize("offset", [0.0, 0.5])
def test_a_checkerboard_on_a_grid_aligned_plane_is_damped(method, offset):
    """On a flat S aligned with the grid the Gershgorin bound is the operator's top eigenvalue:
    at Euler's and Heun's limit step ``2 / rho`` (and torchdiffeq's fixed steps at their
    limits) a checkerboard kept its full size after ``4 h^2`` (0.90 after ``40 h^2``) with S
    between two node layers (offset 0.5; through a layer, offset 0, the band's bound was not
    reached). The exact flow leaves ``exp(-4 h^2 lambda)`` of it, nothing; every method now
    leaves about 2%."""
    if method in ("midpoint", "rk4"):
        pytest.importorskip("torchdiffeq")
    n = 20
    grid = ts.Grid.cube(n, bound=1.0)
    h = grid.spacing
    z = grid.points(dtype=torch.float64)[..., 2]
    surface = ts.ImplicitSurface((z - offset * h)[None, None], grid)
    k = torch.arange(n)
    checkerboard = ((k[:, None, None] + k[None, :, None] + k[None, None, :]) % 2 * 2 - 1)
    u = ts.HeatFlow(time=4 * h * h, method=method)(checkerboard[None, None].double(), surface)
    near = surface.distance() < h
    assert u[near].abs().max() < 0.05


def _two_spheres(n: int, gap_cells: float):
    """Two spheres of radius 0.6 ``gap_cells`` cells apart, their exact distance (the union's),
    and ``u0`` 1 on one and 0 on the other: the exact flow leaves it as it is."""
    grid = ts.Grid.cube(n, bound=1.5)
    points = grid.points(dtype=torch.float64)
    centre = torch.tensor([0.6 + gap_cells * grid.spacing / 2, 0.0, 0.0], dtype=torch.float64)
    phi = torch.minimum((points - centre).norm(dim=-1), (points + centre).norm(dim=-1)) - 0.6
    return ts.ImplicitSurface(phi[None, None], grid), (points[..., 0] > 0).double()[None, None]


def test_the_semigroup_warns_when_it_leaves_its_range_too():
    """Two spheres two cells apart: their bands overlap and the stencils couple the two
    sheets (README, "close parts of S"); ``method="chebyshev"`` left [0, 1] by 0.34 of it at
    ``60 h^2`` (by 0.83 at ``960 h^2``) without a word, as the stepping methods warn. Alone and
    as the entries of a batch, the call's line is named."""
    surface, u0 = _two_spheres(48, 2.0)
    flow = ts.HeatFlow(60 * surface.spacing**2, method="chebyshev")
    with pytest.warns(RuntimeWarning, match=r"method='chebyshev', \d+ applications.*finer grid"
                      ) as caught:
        u = flow(u0, surface)
    assert [w.filename for w in _range_warnings(caught)] == [__file__]
    assert float(u.max()) > 1.25
    pair = ts.ImplicitSurface(torch.cat([surface.phi, surface.phi]), surface.grid)
    with pytest.warns(RuntimeWarning, match="method='chebyshev'") as caught:
        ts.HeatFlow(60 * surface.spacing**2, method="chebyshev")(torch.cat([u0, u0]), pair)
    assert [w.filename for w in _range_warnings(caught)] == [__file__]


def test_channels_and_entries_apart_warn_once():
    """A heat flow whose channels of different diffusivities and whose batch entries each run
    alone still warns once per call, naming the caller's line."""
    surface, u0 = _two_spheres(48, 2.0)
    pair = ts.ImplicitSurface(torch.cat([surface.phi, surface.phi]), surface.grid)
    flow = ts.HeatFlow(60 * surface.spacing**2, method="euler",
                       diffusivity=torch.tensor([1.0, 0.5], dtype=torch.float64))
    with pytest.warns(RuntimeWarning, match="left the range") as caught:
        flow(torch.cat([u0, u0]).expand(2, 2, *u0.shape[2:]), pair)
    assert [w.filename for w in _range_warnings(caught)] == [__file__]


def _sine_across(surface: ts.ImplicitSurface) -> torch.Tensor:
    """``sin(x / 6h)`` about the box's middle, extended along the normals: ``(1, 1, D, H, W)``."""
    x = surface.grid.points()[..., 0]
    wave = torch.sin((x - float(x.mean())) / (6 * surface.spacing))[None, None]
    return ts.Extension(interpolation="cubic")(wave, surface)


@pytest.mark.parametrize("make", [
    lambda t: ts.HeatFlow(t, learn_time=True, max_time=10 * t),
    lambda t: ts.HeatFlow(t, learn_diffusivity=True, max_diffusivity=10.0),
    lambda t: ts.HeatFlow(t, method="euler", learn_time=True, max_time=10 * t),
    lambda t: ts.HeatFlow(t, method="chebyshev", learn_time=True, max_time=10 * t),
])
def test_a_bound_far_above_a_learned_value_does_not_change_the_flow(make):
    """The steps are planned for the bound; the band's re-extensions must follow the time the
    diffusion takes, as the fixed flow's do: scheduled by the bound's time, ten times as many
    moved u(T) by 0.39 (a range of 2) on this bunny, where RKC and Euler differ by 3e-3."""
    surface = mesh_surface("bunny.obj", 40)
    u0 = _sine_across(surface)
    time = 5 * surface.spacing**2
    flow = make(time)
    fixed = ts.HeatFlow(time, method=flow.method)
    band = fixed.band_mask(surface)
    with torch.no_grad():
        difference = (flow(u0, surface) - fixed(u0, surface)).abs()[band.expand_as(u0)].max()
    assert float(difference) < 1e-2


@pytest.mark.parametrize("bound", [None, 10.0])
def test_learned_per_channel_diffusivities_run_apart(bound):
    """Each channel of a learned per-channel diffusivity is its own flow, as a fixed vector's
    are: run together, the steps and re-extensions followed D = 10 and the channel of D = 1 was
    0.39 off its own flow on this bunny (data of range 2). The gradient reaches each entry as
    it reaches a single learned diffusivity."""
    surface = mesh_surface("bunny.obj", 40)
    u1 = _sine_across(surface)
    time = 5 * surface.spacing**2
    flow = ts.HeatFlow(time, diffusivity=[1.0, 10.0], learn_diffusivity=True, max_diffusivity=bound)
    out = flow(torch.cat([u1, u1], 1), surface)
    band = flow.band_mask(surface)
    gradients = torch.autograd.grad(out[band.expand_as(out)].square().sum(), flow.diffusivity.raw)[0]
    for channel, value in enumerate((1.0, 10.0)):
        alone = ts.HeatFlow(time, diffusivity=[value], learn_diffusivity=True, max_diffusivity=bound)
        single = alone(u1, surface)
        difference = (out[:, channel:channel + 1] - single).detach().abs()[band].max()
        assert float(difference) < 1e-5
        expected = torch.autograd.grad(single[band].square().sum(), alone.diffusivity.raw)[0]
        torch.testing.assert_close(gradients[channel], expected[0], rtol=1e-4, atol=0)


def test_limited_cubic_extension_repeated_on_its_result_stays_in_range():
    """Unlimited, fifty cubic extensions of their own result on this bunny's thin parts grew a
    sine of range 2 to [-5.0, 6.0]; limited (the flows' clamp), each stays within its taps'
    range, and on smooth data it is the unlimited extension to 1e-4."""
    surface = mesh_surface("bunny.obj", 40)
    x = surface.grid.points()[..., 0]
    u = torch.sin((x - float(x.mean())) / (6 * surface.spacing))[None, None]
    band = surface.band_mask()
    limited = ts.Extension(interpolation="cubic", limited=True)
    once = limited(u, surface)
    assert float((once - ts.Extension(interpolation="cubic")(u, surface)).abs()[band].max()) < 1e-3
    repeated = once
    for _ in range(49):
        repeated = limited(repeated, surface)
    assert float(repeated[band].abs().max()) <= 1.0 + 1e-6


def test_learned_per_channel_diffusivities_of_equal_values_run_together(monkeypatch):
    """A learned vector that starts equal (a common initialisation) ran each channel alone, at
    C runs' cost; channels of one current value run as one flow, each entry of the parameter
    still given its own channel's gradient."""
    grid = ts.Grid.cube(21, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    u = torch.rand(1, 3, *grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    time = 4 * grid.spacing**2
    flow = ts.HeatFlow(time, diffusivity=[2.0, 1.0, 2.0], learn_diffusivity=True).double()
    runs = []
    original = ts.HeatFlow._channels_apart

    def counted(self, u0, *args):
        runs.append([channels for _, channels in args[2]])
        return original(self, u0, *args)

    monkeypatch.setattr(ts.HeatFlow, "_channels_apart", counted)
    out = flow(u, surface)
    assert runs == [[[0, 2], [1]]]
    grads = torch.autograd.grad(out[:, 0].sum() + 2 * out[:, 2].sum(), flow.diffusivity.raw)[0]
    assert grads[1] == 0 and grads[0] != 0 and grads[2] != 0 and grads[0] != grads[2]


def test_a_training_loop_warns_of_its_steps_once():
    """A learned time's steps warned at every call with that call's numbers (a step of 0.0567,
    then 0.0557, ...), which Python's filter, once per text and line, printed each iteration:
    100 warnings in 50 iterations of Euler beyond its stable step. Each kind is now given once
    a flow."""
    grid = ts.Grid.cube(20, 1.5)
    x, y, z = grid.points().unbind(-1)
    surface = ts.ImplicitSurface((x**2 + y**2 + z**2 - 0.8)[None, None], grid)
    clean = (z / (x**2 + y**2 + z**2).sqrt().clamp(min=1e-6))[None, None]
    generator = torch.Generator().manual_seed(3)
    flow = ts.HeatFlow(10 * grid.spacing**2, method="euler", steps=3, learn_time=True)
    optimizer = torch.optim.Adam(flow.parameters(), lr=0.02)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for _ in range(6):
            noisy = clean + 0.1 * torch.randn(clean.shape, generator=generator)
            loss = ts.nn.band_mse(flow(noisy, surface), clean, surface)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    texts = [str(w.message) for w in caught]
    assert sum("exceeds the stable explicit step" in text for text in texts) == 1, texts
    assert sum("left the range of u0" in text for text in texts) <= 1, texts
