"""Bad or unusual input to the public entries: refused clearly before any work, or accepted."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import torchsurf as ts
from torchsurf._checks import check_count
from torchsurf.flows import HeatFlow


@pytest.mark.parametrize(
    "value", [True, False, np.bool_(True), torch.tensor(True), "3", None, 3 + 0j,
              torch.tensor([3, 4])],
)
def test_counts_refuse_what_is_not_a_number_with_a_type_error(value):
    with pytest.raises(TypeError, match="steps must be a whole number >= 1, got"):
        check_count(value, "steps")


@pytest.mark.parametrize("value", [2.5, float("nan"), float("inf"), 0, -3, np.int64(0),
                                   torch.tensor(2.5)])
def test_counts_refuse_fractions_and_small_values_with_a_value_error(value):
    with pytest.raises(ValueError, match="steps must be a whole number >= 1, got"):
        check_count(value, "steps")


@pytest.mark.parametrize("value", [4, 4.0, np.int64(4), np.float32(4.0), torch.tensor(4),
                                   torch.tensor(4.0)])
def test_counts_accept_every_spelling_of_a_whole_number(value):
    assert check_count(value, "steps") == 4
    assert type(check_count(value, "steps")) is int


@pytest.mark.parametrize(
    "make",
    [lambda: HeatFlow(0.01, steps=True), lambda: HeatFlow(0.01, max_iterations=False),
     lambda: HeatFlow(0.01, reextend_every=True), lambda: ts.Grid.cube(np.bool_(True), 1.0),
     lambda: ts.mesh.fit_grid(__import__("trimesh").creation.box(), resolution=True),
     lambda: ts.sdf.trefoil(ts.Grid.cube(9, 1.5), samples=True)],
)
def test_bools_given_as_counts_raise_type_errors(make):
    with pytest.raises(TypeError, match="must be a whole number"):
        make()


def _sphere17() -> tuple[ts.Grid, ts.ImplicitSurface]:
    grid = ts.Grid.cube(17, 1.5)
    return grid, ts.ImplicitSurface(ts.sdf.sphere(grid), grid)


def test_the_functional_layer_names_a_device_mismatch_and_no_channel():
    """Its checks compared dtypes only: another device or C = 0 ended in raw torch errors."""
    from torchsurf.operators import functional

    grid, surface = _sphere17()
    u = torch.rand(1, 2, *grid.shape)
    normal, weight, h = surface.normal, surface.weight, grid.spacing
    with pytest.raises(ts.MismatchError, match="normal is on meta but u is on cpu"):
        functional.divergence_form(u, normal.to("meta"), weight, h)
    with pytest.raises(ts.MismatchError, match="weight is on meta"):
        functional.divergence_form(u, normal, weight.to("meta"), h)
    with pytest.raises(ValueError, match="u must have at least one channel"):
        functional.divergence_form(u[:, :0], normal, weight, h)
    with pytest.raises(ValueError, match="u must have at least one channel"):
        functional.tangential_gradient(u[:, :0], normal, h)


def test_a_surface_called_like_a_layer_says_how_it_is_used():
    grid, surface = _sphere17()
    with pytest.raises(TypeError, match="is not called: pass it to an operator"):
        surface(torch.zeros(1, 1, *grid.shape))


def test_meta_tensors_are_refused_by_name_and_device():
    grid, surface = _sphere17()
    with pytest.raises(ValueError, match="phi is on the meta device"):
        ts.ImplicitSurface(ts.sdf.sphere(grid).to("meta"), grid)
    u0 = torch.zeros(1, 1, *grid.shape, device="meta")
    with pytest.raises(ValueError, match="u0 is on the meta device"):
        HeatFlow(0.01)(u0, surface)
    with pytest.raises(ValueError, match="u is on the meta device"):
        ts.operators.laplace_beltrami(u0, surface)
    with pytest.raises(ValueError, match="diffusivity is on the meta device"):
        HeatFlow(0.01, diffusivity=torch.ones(2, device="meta"))
    with pytest.raises(ValueError, match="time is on the meta device"):
        HeatFlow(torch.tensor(0.01, device="meta"))


def test_modules_build_under_a_meta_default_device_and_name_a_learned_one_on_meta():
    """Under ``with torch.device("meta")`` a flow's settings became meta tensors whose checks
    raised "Tensor.item() cannot be called on meta tensors"; a learned layer moved to another
    device than its data's raised the same, where the flows name the mismatch."""
    grid, surface = _sphere17()
    with torch.device("meta"):
        layers = [HeatFlow(0.01, diffusivity=[1.0, 2.0]), ts.AnisotropicFlow(0.01),
                  ts.nn.LearnedDiffusion(2)]
    u = torch.rand(1, 2, *grid.shape, generator=torch.Generator().manual_seed(0))
    for layer in layers:
        assert torch.isfinite(layer(u, surface)).all()
    for layer in (ts.nn.LearnedDiffusion(2), ts.nn.DiffusionBlock(2)):
        with pytest.raises(ts.MismatchError, match="on cpu but the learned times are .* on meta"):
            layer.to("meta")(u, surface)
    flow = HeatFlow(0.01, diffusivity=[1.0, 2.0], learn_diffusivity=True, max_diffusivity=5.0)
    with pytest.raises(ts.MismatchError, match="learned diffusivity is torch.float32 on meta"):
        flow.to("meta")(u, surface)
    with pytest.raises(ValueError, match="device='meta' holds no values"):
        ts.sdf.sphere(grid, device="meta")


@pytest.mark.parametrize("first_use", ["torch.inference_mode()", 'torch.device("meta")'])
def test_a_first_use_under_a_mode_leaves_usable_constants(first_use):
    """The package imports its modules on first use: inside ``torch.inference_mode`` their
    constant tensors became inference tensors, and every later training call with a ``phi``
    that requires grad failed ('Inference tensors cannot be saved for backward'); under
    ``with torch.device("meta")`` they became meta tensors, and every later flow failed."""
    import subprocess
    import sys

    script = f"""
import torch, torchsurf as ts
grid = ts.Grid.cube(13, 1.5)
surface = ts.ImplicitSurface(ts.sdf.sphere(grid).requires_grad_(), grid)
u = torch.rand(1, 1, *grid.shape)
with {first_use}:
    layer = ts.nn.LearnedDiffusion(1)
    if not torch.empty(0).is_meta:
        layer(u, surface)
ts.nn.LearnedDiffusion(1)(u, surface).square().sum().backward()
from torchsurf.flows import _limiter
constants = (_limiter.BLOCKS, _limiter._OFFSETS, _limiter._CELL_TAPS)
assert not any(t.is_inference() or t.is_meta for t in constants)
print("trained")
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0 and "trained" in result.stdout, result.stderr[-2000:]


@pytest.mark.parametrize(
    "times",
    [[0.05, 0.1], (0.05, 0.1), np.array([0.05, 0.1]), torch.tensor([0.05, 0.1]),
     torch.tensor([0.05, 0.1], dtype=torch.float64), [np.float32(0.05), torch.tensor(0.1)]],
)
def test_times_as_sequences_arrays_and_tensors_give_the_same_flow(times):
    grid, surface = _sphere17()
    u0 = ts.sdf.sphere(grid).clamp(-0.3, 0.3)
    flow = HeatFlow(0.1, steps=8)
    reference = flow(u0, surface, times=[0.05, 0.1])
    result = flow(u0, surface, times=times)
    assert result.shape == (2, *u0.shape)
    torch.testing.assert_close(result, reference)
    torch.testing.assert_close(result[-1], flow(u0, surface))


def test_times_may_start_at_zero_where_u_is_u0():
    grid, surface = _sphere17()
    u0 = ts.sdf.sphere(grid).clamp(-0.3, 0.3)
    flow = HeatFlow(0.1, steps=8)
    result = flow(u0, surface, times=torch.linspace(0, 0.1, 3))
    assert result.shape == (3, *u0.shape)
    assert torch.equal(result[0], u0)
    torch.testing.assert_close(result[1:], flow(u0, surface, times=[0.05, 0.1]))
    assert torch.equal(flow(u0, surface, times=[0])[0], u0)


@pytest.mark.parametrize(
    ("times", "error", "match"),
    [
        (0.1, TypeError, r"times must be a sequence .*got 0.1 \(float\); for one time use"),
        (torch.tensor(0.1), TypeError, "tensor of shape \\(\\) .*for one time use"),
        (torch.tensor([[0.05, 0.1]]), TypeError, r"tensor of shape \(1, 2\)"),
        (torch.tensor([True]), TypeError, "dtype torch.bool"),
        ("0.1", TypeError, "times must be a sequence"),
        ({0.05, 0.1}, TypeError, "times must be a sequence"),
        ([], ValueError, "at least one time"),
        ([0.05, float("nan")], ValueError, r"times\[1\] must be a finite number >= 0"),
        (torch.tensor([0.05, float("inf")]), ValueError, r"times\[1\] must be a finite"),
        ([-0.05, 0.1], ValueError, r"times\[0\] must be a finite number >= 0"),
        ([0.1, 0.05], ValueError, r"increase strictly, got times\[0\] = 0.1 then times\[1\] = 0.05"),
        ([0.05, 0.05], ValueError, "increase strictly"),
        ([0.2], ValueError, "must not exceed the flow's time 0.1"),
        ([True], TypeError, r"times\[0\] must be a finite number >= 0, got True"),
        (torch.tensor([0.05, 0.1], requires_grad=True), ValueError, "must not require grad"),
    ],
)
def test_bad_times_are_refused_before_any_work(times, error, match, monkeypatch):
    grid, surface = _sphere17()
    flow = HeatFlow(0.1)
    monkeypatch.setattr(flow, "system", lambda *a, **k: pytest.fail("work started"))
    with pytest.raises(error, match=match):
        flow(torch.zeros(1, 1, *grid.shape), surface, times=times)


def test_float32_times_that_round_above_the_end_are_the_end():
    grid, surface = _sphere17()
    flow = HeatFlow(0.1, steps=8)
    u0 = ts.sdf.sphere(grid).clamp(-0.3, 0.3)
    assert float(torch.tensor(0.1)) > 0.1
    torch.testing.assert_close(flow(u0, surface, times=torch.tensor([0.1]))[0], flow(u0, surface))


def test_linear_flows_refuse_times_far_beyond_their_equilibrium():
    grid, surface = _sphere17()
    u0 = torch.zeros(1, 1, *grid.shape)
    for method in ("rkc", "euler", "implicit"):
        with pytest.raises(ValueError, match=r"time=10000 is \d+ times the time the diffusion "
                                             r"takes to cross the whole grid"):
            HeatFlow(1e4, method=method)(u0, surface)
    assert HeatFlow(1.0)(u0, surface).shape == u0.shape  # 1/30 of the crossing time: runs


def test_too_many_steps_name_steps_and_many_evaluations_warn():
    from torchsurf.flows._integrators import LONG_RUN, System, plan_steps

    grid, surface = _sphere17()
    with pytest.raises(ValueError, match=r"steps=1000000000 is too many"):
        HeatFlow(0.01, steps=10**9)(torch.zeros(1, 1, *grid.shape), surface)
    system = System(lambda u: u, surface.band_mask(), spectral_radius=100.0)
    with pytest.warns(RuntimeWarning, match=r"evaluations of the rate \(more than 100000"):
        plan = plan_steps("heun", system, 1.8 * (LONG_RUN // 2 + 10) / 100.0, None)
    assert plan.count == LONG_RUN // 2 + 10


def test_reaction_diffusion_ignores_nan_outside_its_band():
    from torchsurf.flows import ReactionDiffusion

    _, surface = _sphere17()
    u0 = ReactionDiffusion.initial(surface)
    clean = ReactionDiffusion(1.0)(u0, surface, generator=torch.Generator().manual_seed(0))
    u0[0, :, 0, 0, 0] = float("nan")  # a corner, far from the sphere
    dirty = ReactionDiffusion(1.0)(u0, surface, generator=torch.Generator().manual_seed(0))
    band = surface.band_mask()[0, 0]
    torch.testing.assert_close(dirty[:, :, band], clean[:, :, band])


def test_a_diverging_integration_raises_instead_of_returning_nan():
    from torchsurf.flows._integrators import System

    class Exploding(HeatFlow):
        def system(self, u0, surface, **inputs):
            band = self.band_mask(surface)
            return System(lambda u: torch.where(band, u * 1e30 + 1e30, 0.0), band, 1.0)

    grid, surface = _sphere17()
    with pytest.raises(FloatingPointError, match=r"Exploding \(method='euler', 4 steps .* diverged"):
        Exploding(0.5, method="euler", steps=4)(torch.ones(1, 1, *grid.shape), surface)


def test_harmonic_map_flow_checks_p_and_eps_by_name():
    import numpy as np

    from torchsurf.flows import HarmonicMapFlow

    assert HarmonicMapFlow(0.1, p=np.float32(1.5)).p == 1.5
    with pytest.raises(TypeError, match="p must be"):
        HarmonicMapFlow(0.1, p=True)
    with pytest.raises(TypeError, match="eps"):
        HarmonicMapFlow(0.1, eps="0.1")
    with pytest.raises(ValueError, match="1 <= p <= 2"):
        HarmonicMapFlow(0.1, p=3)


def test_tangent_fields_and_colour_images_are_checked_by_name():
    grid = ts.Grid.cube(16, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    field = torch.rand(3, 3, *grid.shape)
    with pytest.raises(ValueError, match="direction has batch size 3 but u0 has 1"):
        ts.ReactionDiffusion(10.0)(ts.ReactionDiffusion.initial(surface), surface, direction=field)
    with pytest.raises(ValueError, match="direction has batch size 3 but u0 has 2"):
        ts.FlowVisualization(1e-3)(torch.rand(2, 1, *grid.shape), surface, direction=field)
    nan = torch.full((1, 3, *grid.shape), float("nan"))
    with pytest.raises(ValueError, match=r"direction \(in the band and its ring\)"):
        ts.FlowVisualization(1e-3)(torch.rand(1, 1, *grid.shape), surface, direction=nan)
    image = torch.rand(1, 3, *grid.shape)
    image[surface.band_mask().expand_as(image)] = float("nan")
    with pytest.raises(ValueError, match=r"image \(in the band and its ring\)"):
        ts.ColorDenoise(1e-3)(image, surface)


def test_harmonic_maps_refuse_data_that_are_not_unit_vectors():
    grid = ts.Grid.cube(16, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    with pytest.raises(ValueError, match="at least 2 channels"):
        ts.HarmonicMapFlow(1e-3)(torch.rand(1, 1, *grid.shape), surface)
    with pytest.raises(ValueError, match="zero vectors"):
        ts.HarmonicMapFlow(1e-3)(torch.zeros(1, 3, *grid.shape), surface)


def test_flow_settings_that_require_grad_are_refused_not_detached():
    """A tensor requiring grad given as a flow's time, diffusivity or contrast lost its gradient
    silently; the learn_* options own such parameters."""
    parameter = torch.nn.Parameter(torch.tensor(0.5))
    for make, name in ((lambda: HeatFlow(parameter), "time"),
                       (lambda: HeatFlow(0.01, diffusivity=parameter), "diffusivity"),
                       (lambda: ts.AnisotropicFlow(0.01, "perona_malik", contrast=parameter),
                        "contrast")):
        with pytest.raises(ValueError, match=f"learn_{name}=True"):
            make()
    assert HeatFlow(parameter.detach()).time_value.maximum() == 0.5


@pytest.mark.parametrize("time", ["1", None, True, [1.0, True], 1 + 2j, torch.tensor(True)])
def test_learned_diffusion_refuses_times_that_are_not_numbers(time):
    with pytest.raises(TypeError, match="time"):
        ts.nn.LearnedDiffusion(2, time=time)


def test_from_function_returns_the_requested_dtype_and_refuses_integers():
    grid = ts.Grid.cube(8, 1.0)
    phi = ts.sdf.from_function(grid, lambda p: p.double().norm(dim=-1) - 0.5, dtype=torch.float32)
    assert phi.dtype == torch.float32
    with pytest.raises(TypeError, match="floating-point"):
        ts.sdf.from_function(grid, lambda p: (p.norm(dim=-1) > 0.5).long())


def test_cubic_sampling_of_no_points_is_empty():
    grid = ts.Grid.cube(8, 1.0)
    field = torch.rand(2, 3, 8, 8, 8)
    for interpolation in ("linear", "cubic"):
        assert ts.sample(field, torch.zeros(0, 3), grid, interpolation).shape == (2, 3, 0)


def test_functional_layer_checks_channel_counts_dtypes_spacing_and_scheme():
    from torchsurf.operators import functional

    grid = ts.Grid.cube(12, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 1, *grid.shape)
    normal, weight, h = surface.normal, surface.weight, surface.spacing
    with pytest.raises(ValueError, match="normal must be"):
        functional.divergence_form(u, normal[:, :1], weight, h)
    with pytest.raises(ValueError, match="direction must be"):
        functional.directional_form(u, normal, weight, h, normal[:, :2])
    with pytest.raises(TypeError, match="normal is torch.float64 but u is torch.float32"):
        functional.tangential_gradient(u, normal.double(), h)
    with pytest.raises(TypeError, match="u must be a float32 or float64 tensor"):
        functional.tangential_gradient(u.half(), normal, h)
    with pytest.raises(ValueError, match="spacing"):
        functional.divergence_form(u, normal, weight, 0.0)
    with pytest.raises(ValueError, match="scheme must be one of"):
        functional.divergence_form(u, normal, weight, h, scheme="central")
    curvature = surface.mean_curvature()
    with pytest.raises(ValueError, match="spacing"):
        functional.central_laplace_beltrami(u, normal, curvature, -h)
    with pytest.raises(ValueError, match="mean_curvature must be"):
        functional.central_laplace_beltrami(u, normal, normal, h)
    with pytest.raises(TypeError, match="normal is torch.float64 but u is torch.float32"):
        functional.central_laplace_beltrami(u, normal.double(), curvature, h)
    with pytest.raises(ValueError, match="v must hold 3 components a channel"):
        functional.tangential_divergence(u.expand(1, 4, *grid.shape), normal, weight, h)


def test_functional_layer_checks_grids_batches_and_the_spacing_type():
    """Mismatched grids and batches reached torch's bare size errors, naming the padded sizes;
    spacing=True ran as a spacing of 1."""
    from torchsurf.operators import functional

    grid = ts.Grid.cube(12, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    normal, weight, h = surface.normal, surface.weight, surface.spacing
    u = torch.rand(1, 1, *grid.shape)
    wider = torch.rand(1, 1, 12, 12, 13)
    with pytest.raises(ValueError, match=r"normal must be .* of u \(1, 1, 12, 12, 13\).*got shape "
                                         r"\(1, 3, 12, 12, 12\)"):
        functional.divergence_form(wider, normal, weight, h)
    with pytest.raises(ValueError, match=r"normal must be .*of v \(1, 3, 12, 12, 13\)"):
        functional.tangential_divergence(wider.expand(1, 3, 12, 12, 13), normal, weight, h)
    with pytest.raises(ValueError, match=r"weight must be .* got shape \(1, 1, 1, 1, 1\)"):
        functional.divergence_form(u, normal, weight[:, :, :1, :1, :1], h)
    with pytest.raises(ValueError, match=r"batch sizes of u, normal, weight must be equal or 1, "
                                         r"got \[2, 3\]"):
        functional.divergence_form(u.expand(3, 1, *grid.shape), normal.expand(2, 3, *grid.shape),
                                   weight, h)
    with pytest.raises(ValueError, match=r"batch sizes .* equal or 1, got \[2, 3\]"):
        functional.divergence_form(u, normal.expand(2, 3, *grid.shape),
                                   weight.expand(3, 1, *grid.shape), h)
    with pytest.raises(TypeError, match="spacing must be a finite positive number, got True"):
        functional.divergence_form(u, normal, weight, True)
    expected = functional.divergence_form(u, normal, weight, h)
    for spacing in (np.float64(h), torch.tensor(h, dtype=torch.float64)):
        torch.testing.assert_close(functional.divergence_form(u, normal, weight, spacing),
                                   expected, rtol=0, atol=0)
    # a batch of u over one geometry and one u over a batch of geometry both broadcast
    assert functional.divergence_form(u.expand(2, 1, *grid.shape), normal, weight, h).shape[0] == 2
    assert functional.divergence_form(u, normal.expand(2, 3, *grid.shape),
                                      weight.expand(2, 1, *grid.shape), h).shape[0] == 2


def test_directional_diffusion_refuses_a_direction_batch_that_u_does_not_have():
    grid = ts.Grid.cube(12, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 1, *grid.shape)
    direction = torch.zeros(2, 3, *grid.shape)
    with pytest.raises(ValueError, match="direction has batch size 2 but u has 1"):
        ts.directional_diffusion(u, surface, direction)


def test_a_direction_of_the_surfaces_batch_widens_u_as_the_surface_does():
    """u of batch 1 on a surface of batch 2 gives two results; a direction of the surface's
    batch (its principal directions, say) is each entry's own, as for one entry alone."""
    grid = ts.Grid.cube(15, 1.5)
    phi = torch.cat([ts.sdf.sphere(grid, 1.0), ts.sdf.torus(grid, 0.8, 0.35)])
    surface = ts.ImplicitSurface(phi, grid)
    torch.manual_seed(0)
    u = torch.rand(1, 1, *grid.shape)
    direction = torch.randn(2, 3, *grid.shape)
    both = ts.directional_diffusion(u, surface, direction)
    flowed = ts.FlowVisualization(1e-3)(u, surface, direction=direction)
    assert both.shape == flowed.shape == (2, 1, *grid.shape)
    for b in range(2):
        alone = ts.ImplicitSurface(phi[b:b + 1], grid)
        entry = direction[b:b + 1]
        torch.testing.assert_close(both[b:b + 1], ts.directional_diffusion(u, alone, entry))
        torch.testing.assert_close(flowed[b:b + 1],
                                   ts.FlowVisualization(1e-3)(u, alone, direction=entry))
    with pytest.raises(ValueError, match="direction has batch size 3 but surface has 2"):
        ts.directional_diffusion(u, surface, torch.randn(3, 3, *grid.shape))


def _bad_calls() -> list:
    import trimesh

    from torchsurf import bricks, config, datasets, exact, render, signals
    from torchsurf.flows import ColorDenoise
    from torchsurf.shape_batch import AnalyticShape

    grid = ts.Grid.cube(24, 1.5)
    sphere = bricks.from_dense(ts.sdf.sphere(grid, 0.8), grid)
    other_eps = bricks.from_dense(ts.ImplicitSurface(ts.sdf.sphere(grid, 0.8), grid, eps=1e-3))
    dense = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.8), grid)
    mesh = trimesh.creation.icosphere(1)
    nan_point = torch.tensor([[float("nan"), 0.0, 0.0]])
    return [
        (lambda: AnalyticShape("sphere", {"radius": -1.0}), ValueError, r"parameters of 'sphere': radius"),
        (lambda: AnalyticShape("torus", {"minor": 0.3}), ValueError, "not 'minor'"),
        (lambda: bricks.from_mesh([], []), ValueError, "at least one mesh"),
        (lambda: sphere.sample(sphere.phi, nan_point), ValueError, "points must hold finite"),
        (lambda: sphere.sample(sphere.phi, nan_point.nan_to_num(), entry=0.0), ValueError,
         "entry must be"),
        (lambda: bricks.cat([sphere, other_eps]), ValueError, "one eps"),
        (lambda: bricks.cat([sphere, sphere]).layout.from_dense(
            [torch.zeros(1, *grid.shape), torch.zeros(2, *grid.shape)]),
         ValueError, "same number of channels"),
        (lambda: config.load("heat_sphere", "grid.size=16"), TypeError, "list of 'key=value'"),
        (lambda: render.vertex_values(torch.zeros(2, 1, *grid.shape), mesh, grid), ValueError,
         "holds 2 volumes.*give entry"),
        (lambda: render.vertex_values(torch.zeros(2, 1, *grid.shape), mesh, grid, entry=2),
         ValueError, r"entry must be an integer in \[0, 2\)"),
        # AttributeErrors from deep inside, naming neither
        (lambda: render.vertex_values(torch.zeros(1, 1, *grid.shape), mesh, "grid"), TypeError,
         "grid must be a torchsurf.Grid"),
        (lambda: render.vertex_values(torch.zeros(1, 1, *grid.shape), np.zeros((4, 3)), grid),
         TypeError, "mesh must be a trimesh.Trimesh"),
        (lambda: signals.checkerboard(grid.points().permute(3, 0, 1, 2)[None], 0.5, (0.0, 0.0)),
         ValueError, "origin"),
        (lambda: signals.uniform_noise(dense, -1, 0), ValueError, "channels"),
        (lambda: datasets.SignalDataset(dense, length=2)[np.float64(1.0)], TypeError,
         "index must be an integer"),
        (lambda: exact.sphere_harmonic(5, 16), ValueError, "degree must be"),
        # a case whose torus fell between the nodes: ImplicitSurface failed on it later
        (lambda: exact.torus_function(9), ValueError, "no node lies inside the torus"),
        (lambda: ColorDenoise(1.0, chroma=3), TypeError, "chroma must be a flow"),
        # torch's reduction error and an indexing error, naming no mask
        (lambda: exact.max_error(dense.phi, dense.phi, dense.phi < -10), ValueError,
         "mask selects no node"),
        (lambda: exact.max_error(dense.phi, dense.phi, (dense.phi < 0).float()), TypeError,
         "mask must be a bool tensor, got torch.float32"),
        # torch's broadcasting error, naming neither
        (lambda: exact.max_error(dense.phi[..., :4], dense.phi, dense.phi < 0), ValueError,
         r"exact has shape .*must broadcast to value's shape"),
        (lambda: exact.max_error(dense.phi, dense.phi, (dense.phi < 0)[..., :4]), ValueError,
         r"mask has shape .*must broadcast to value's shape"),
        (lambda: exact.torus_function("20"), TypeError, "n must be a whole number"),
        (lambda: ts.FlowVisualization.noise(dense, generator=1), TypeError,
         "generator must be a torch.Generator or None, got int"),
        (lambda: sphere.layout.rand(1, generator=7), TypeError, "generator must be"),
        (lambda: ts.FlowVisualization(1e-3)(torch.rand(1, 1, *grid.shape), dense,
                                            torch.rand(1, 3, *grid.shape)),
         TypeError, "direction is a keyword argument"),
        (lambda: datasets.smooth_signal(dense, seed=1.7), ValueError, "seed"),
        (lambda: datasets.SignalDataset(dense, length=2, smooth={"cells": 3}), ValueError,
         "not \\['cells'\\]"),
        (lambda: render.colours(np.zeros((4, 1)), mode="rgb"), ValueError, "needs values"),
        (lambda: ts.MeshAdapter(mesh, resolution=16).encode(torch.zeros(0, 1, len(mesh.vertices))),
         ValueError, "B, C at least 1"),
        (lambda: ts.MeshAdapter(mesh, resolution=16, order=1).decode(torch.zeros(1, 1, 8, 8, 8)),
         ValueError, "volume has spatial shape"),
    ]


def test_colours_of_missing_values_are_grey_and_conversions_stay_float64():
    from torchsurf import render

    rgb = render.colours(np.array([[0.0], [np.nan], [1.0]]))
    assert np.allclose(rgb[1], 0.5) and np.isfinite(rgb).all() and not np.allclose(rgb[0], rgb[2])
    # equalised: a missing value takes no rank (-inf ranked first shifted the others' colours)
    ranked = render.colours(np.array([[-np.inf], [0.0], [1.0], [np.nan]]), equalize=True)
    assert np.allclose(ranked[[0, 3]], 0.5)
    assert np.allclose(ranked[1:3], render.colours(np.array([[0.0], [1.0]]), equalize=True))
    batch = ts.MeshBatchAdapter([ts.AnalyticShape("sphere")], resolution=16).float()
    assert batch.scale.dtype == batch.centre.dtype == torch.float64


def test_bad_arguments_are_named():
    """Inputs that raised raw IndexError/KeyError/shape errors or were taken silently."""
    for call, error, match in _bad_calls():
        with pytest.raises(error, match=match):
            call()


def test_points_of_analytic_shapes_are_checked_where_they_are_given():
    # each raised "object of type 'float' has no len()", and AnalyticShape accepted a scalar
    # half_size that only failed once a MeshBatchAdapter sampled it
    grid = ts.Grid.cube(9, bound=1.0)
    for make, name in ((lambda: ts.sdf.sphere(grid, center=0.0), "center"),
                       (lambda: ts.sdf.box(grid, half_size=0.5), "half_size"),
                       (lambda: ts.sdf.capsule(grid, start=0.0), "start"),
                       (lambda: ts.AnalyticShape("box", {"half_size": 0.5}), "half_size")):
        with pytest.raises(ValueError, match=f"{name} must have three entries"):
            make()
    with pytest.raises(TypeError, match="each entry of center must be a finite real number"):
        ts.sdf.sphere(grid, center=(0.0, 0.0, "a"))
    with pytest.raises(ValueError, match="parameters of 'sphere': radius must be"):
        ts.AnalyticShape("sphere", {"radius": -1.0})
    # integer node indices: torch.finfo raised on them
    inside = grid.contains_index(torch.tensor([[1, 2, 3], [9, 0, 0]]))
    assert inside.tolist() == [True, False]


def test_dtype_mismatches_raise_one_error_that_both_except_clauses_catch():
    from torchsurf.operators import functional

    grid = ts.Grid.cube(32, 1.6)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    bricks = ts.bricks.from_dense(surface)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64)
    packed = torch.rand(len(bricks.layout), 1, 8, 8, 8, dtype=torch.float64)
    wrong = [
        lambda: ts.laplace_beltrami(u, surface),
        lambda: ts.HeatFlow(0.01)(u, surface),
        lambda: ts.nn.LearnedDiffusion(1)(u, surface),
        lambda: functional.tangential_gradient(u, surface.normal, surface.spacing),
        lambda: ts.sample(u, torch.zeros(1, 3), grid),
        lambda: ts.laplace_beltrami(packed, bricks),
        lambda: bricks.sample(packed, torch.zeros(1, 3)),
    ]
    for call in wrong:
        for clause in (TypeError, ValueError, ts.MismatchError):
            with pytest.raises(clause, match="float64|float32"):
                call()


def _under_autocast_cases(grid: ts.Grid) -> dict:
    phi = ts.sdf.sphere(grid, 1.0)
    u = torch.rand(1, 2, *grid.shape, generator=torch.Generator().manual_seed(0))
    h2 = grid.spacing**2

    def surface() -> ts.ImplicitSurface:
        return ts.ImplicitSurface(phi, grid)

    return {
        "Laplace-Beltrami by conv3d": lambda: ts.laplace_beltrami(u, surface(), path="conv3d"),
        "Gaussian curvature": lambda: surface().gaussian_curvature(),
        "smooth signal": lambda: ts.datasets.smooth_signal(surface(), 2),
        "capsule": lambda: ts.sdf.capsule(grid, (-0.5, 0.0, 0.0), (0.5, 0.1, 0.0), 0.3),
        "Chebyshev heat": lambda: HeatFlow(4 * h2, method="chebyshev")(u, surface()),
        "LearnedDiffusion": lambda: ts.nn.LearnedDiffusion(2)(u, surface()),
    }


@pytest.mark.parametrize("name", list(_under_autocast_cases(ts.Grid.cube(5, 1.0))))
def test_autocast_leaves_torchsurfs_computations_in_the_datas_dtype(name):
    """CPU autocast lowered torchsurf's convolutions and products to bfloat16 and returned
    float32: Laplace-Beltrami by conv3d 126% off at 48^3, curvatures, signals, a capsule's
    distance and the limiter's interpolation weights (an audit, 2026-12-07)."""
    case = _under_autocast_cases(ts.Grid.cube(24, 2.0))[name]
    expected = case()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        result = case()
    assert result.dtype == expected.dtype
    assert torch.equal(result, expected)
