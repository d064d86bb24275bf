"""A flow's forward under ``torch.compile``: traced whole (no graph break) wherever its steps can
be planned on the host, and ``max_time`` giving what the unbounded learned time gives."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import AnisotropicFlow, HarmonicMapFlow, HeatFlow
from torchsurf.flows._positive import Positive


@pytest.fixture(scope="module")
def sphere():
    grid = ts.Grid.cube(9, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 2, *grid.shape, generator=torch.Generator().manual_seed(0))
    return u, surface


def _break_reasons(module: torch.nn.Module, u: torch.Tensor, surface: ts.ImplicitSurface,
                   grad: bool = False) -> list[str]:
    """``torch._dynamo.explain``'s graph-break reasons for ``module(u, surface)`` (without grad
    unless ``grad``), after one eager call (the surface's band, bound and stencils, computed
    once and kept)."""
    with torch.set_grad_enabled(grad):
        module(u, surface)
        torch._dynamo.reset()
        try:
            explanation = torch._dynamo.explain(module)(u, surface)
        finally:
            torch._dynamo.reset()
    return [f"{reason.reason}"[:300] for reason in explanation.break_reasons]


def _flows(h2: float) -> dict[str, torch.nn.Module]:
    """Flows of one stable Euler step (a short trace) on a grid of spacing ``sqrt(h2)``."""
    step = h2 / 40
    return {
        "fixed time": HeatFlow(step, method="euler", steps=1),
        "learned time and diffusivity, bounded": HeatFlow(
            step, method="euler", steps=1, learn_time=True, max_time=1.5 * step,
            diffusivity=[1.0, 2.0], learn_diffusivity=True, max_diffusivity=3.0,
        ),
        "total variation": AnisotropicFlow(step / 100, method="euler", steps=1),
        # the contrast's check read a per-channel tensor on the host at every rate (3 breaks)
        "Perona-Malik, per-channel contrast": AnisotropicFlow(
            step / 100, "perona_malik", contrast=[1.0, 2.0], method="euler", steps=1),
        "Perona-Malik, learned contrast": AnisotropicFlow(
            step / 100, "perona_malik", contrast=[1.0, 2.0], learn_contrast=True,
            method="euler", steps=1),
        "AnisotropicDiffusion, per-channel contrast": ts.AnisotropicDiffusion(
            "perona_malik", contrast=torch.tensor([1.0, 2.0])),
    }


@pytest.mark.parametrize("name", list(_flows(1.0)))
def test_flow_forward_traces_without_graph_break(sphere, name):
    u, surface = sphere
    flow = _flows(surface.spacing**2)[name]
    assert _break_reasons(flow, u, surface) == []


@pytest.mark.parametrize("name", ["learned time and diffusivity, bounded",
                                  "Perona-Malik, learned contrast"])
def test_learned_flow_traces_without_graph_break_while_autograd_records(sphere, name):
    """Training traces the forward with autograd recording: the band's re-extension went
    through an autograd function whose backward dynamo traced with it, and its host-sized
    selections broke the graph (three breaks, the steps run eagerly)."""
    u, surface = sphere
    flow = _flows(surface.spacing**2)[name]
    assert _break_reasons(flow, u.requires_grad_(), surface, grad=True) == []


def test_unbounded_learned_time_breaks_only_where_it_is_read(sphere):
    """The documented remaining break: the steps follow the learned time, read on the host."""
    u, surface = sphere
    flow = HeatFlow(surface.spacing**2 / 40, method="euler", steps=1, learn_time=True)
    reasons = _break_reasons(flow, u, surface)
    assert reasons and all("item()" in reason for reason in reasons), reasons


@pytest.mark.slow
def test_rkc_and_chebyshev_forward_trace_without_graph_break(sphere):
    u, surface = sphere
    h2 = surface.spacing**2
    for flow in (HeatFlow(4 * h2), HeatFlow(4 * h2, method="chebyshev"),
                 HeatFlow(4 * h2, learn_time=True, max_time=8 * h2)):
        assert _break_reasons(flow, u, surface) == [], flow


@pytest.mark.parametrize("method", ["rkc", "implicit"])
def test_bounded_learned_time_integrates_the_same_flow(method):
    """``max_time`` at the time (above its float32 rounding): the same steps, the same numbers
    and gradient; twice the time: more, shorter steps of the same flow (the band is re-extended
    once per cell-crossing time and at the end, so the two hold the ring for different steps:
    2.5 % of the scale apart at one band-edge node of this 13^3 grid, 0.7 % when both
    re-extended after every step)."""
    case = ts.exact.sphere_harmonic(2, 13, dtype=torch.float64)  # smooth: no stiff modes
    u, surface = case.u, ts.ImplicitSurface(case.phi, case.grid)
    h2 = surface.spacing**2
    results = []
    for bound in (None, h2 * (1 + 1e-6), 2 * h2):
        flow = HeatFlow(h2, method=method, learn_time=True, max_time=bound).double()
        value = flow(u, surface)
        value.square().sum().backward()
        results.append((value.detach(), flow.time_value.raw.grad))
    torch.testing.assert_close(results[1][0], results[0][0], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(results[1][1], results[0][1], rtol=1e-10, atol=1e-12)
    scale = results[0][0].abs().max()
    torch.testing.assert_close(results[2][0], results[0][0], rtol=0, atol=3e-2 * scale)
    torch.testing.assert_close(results[2][1], results[0][1], rtol=5e-2, atol=0)


def test_bound_clamps_the_learned_value_and_is_its_maximum():
    parameter = Positive([1.0, 2.0], "time", learnable=True, bound=3.0, bound_name="max_time")
    assert parameter.maximum() == 3.0
    with torch.no_grad():
        parameter.raw.fill_(10.0)
    assert torch.equal(parameter.value(), torch.full((2,), 3.0))
    parameter.value().sum().backward()
    assert torch.equal(parameter.raw.grad, torch.zeros(2))


def test_bound_is_refused_below_the_value_or_for_a_fixed_one():
    with pytest.raises(ValueError, match="max_time=1 is below the initial time"):
        HeatFlow(2.0, learn_time=True, max_time=1.0)
    with pytest.raises(ValueError, match="max_time bounds a learnable time"):
        HeatFlow(2.0, max_time=3.0)
    with pytest.raises(ValueError, match="max_diffusivity"):
        HeatFlow(1.0, learn_diffusivity=True, max_diffusivity=-1.0)


def test_a_bound_may_equal_the_initial_value(sphere):
    """float32(0.1) exceeds 0.1: a learned time at its bound, which the docs advise for
    compiling, was refused as "max_time=0.1 is below the initial time 0.1"."""
    u, surface = sphere
    for layer in (HeatFlow(0.1, learn_time=True, max_time=0.1, method="euler"),
                  ts.nn.LearnedDiffusion(2, time=0.1, max_time=0.1)):
        layer(u, surface).sum().backward()
        assert all(torch.isfinite(p.grad).all() for p in layer.parameters())
    for value in (1e-3, 0.01, 0.05, 0.2, 0.3, 1.5):  # clamped a step above: no gradient
        flow = HeatFlow(value, learn_time=True, max_time=value)
        layer = ts.nn.LearnedDiffusion(1, time=value, max_time=value)
        time = flow.time_value.value()
        grads = torch.autograd.grad(time + layer.time.sum(), [flow.time_value.raw, layer.raw_time])
        assert time <= value and layer.time.max() <= value and all(g.abs().min() > 0 for g in grads)
    with pytest.raises(ValueError, match="below the initial time"):
        HeatFlow(0.1, learn_time=True, max_time=0.1 * (1 - 1e-6))


def test_fixed_vector_maximum_is_kept_on_the_host_and_follows_a_loaded_state():
    flow = HeatFlow(0.1, diffusivity=[1.0, 2.0])
    assert flow.diffusivity.maximum() == 2.0
    state = flow.state_dict()
    state["diffusivity.values"] = torch.tensor([4.0, 0.5])
    flow.load_state_dict(state)
    assert flow.diffusivity.maximum() == 4.0


@pytest.mark.parametrize("method", ["heun", "rkc"])
def test_a_fixed_diffusivity_of_several_values_runs_its_channels_apart_when_traced(method):
    """The values are kept on the host, so a traced call groups the channels as the call as is
    does: run together for the largest value, the second channel was 1.5e-2 off (Heun, 12^3)."""
    grid = ts.Grid.cube(12, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 3, *grid.shape, generator=torch.Generator().manual_seed(0))
    flow = HeatFlow(grid.spacing**2 / 2, diffusivity=[1.0, 0.5, 1.0], method=method)
    with torch.no_grad():
        expected = flow(u, surface)
        torch._dynamo.reset()
        try:
            result = torch.compile(flow, backend="aot_eager", fullgraph=True)(u, surface)
        finally:
            torch._dynamo.reset()
    torch.testing.assert_close(result, expected, rtol=1e-5, atol=1e-6)


def test_inductor_compiles_a_flow_whole(sphere):
    """``torch.compile(flow, fullgraph=True)`` with the default backend (inductor) gives the
    eager numbers: in torch 2.13 the band's dilation, in-place ORs of bool views, generated C++
    that did not compile (``VecMask<int,1>`` against ``VecMask<float,1>``)."""
    u, surface = sphere
    flow = HeatFlow(surface.spacing**2 / 40, method="euler", steps=1)
    with torch.no_grad():
        expected = flow(u, surface)
        torch._dynamo.reset()
        try:
            result = torch.compile(flow, fullgraph=True)(u, surface)
        finally:
            torch._dynamo.reset()
    torch.testing.assert_close(result, expected, rtol=1e-5, atol=1e-6)


def test_inductor_compiles_a_flow_on_a_fresh_surface():
    """Compiled before any eager call, the surface's sign-change nodes are traced too: as
    in-place ORs of bool views they generated the same C++ that did not compile."""
    grid = ts.Grid.cube(9, 1.5)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(3))
    flow = HeatFlow(grid.spacing**2 / 40, method="euler", steps=1)
    with torch.no_grad():
        torch._dynamo.reset()
        try:
            result = torch.compile(flow)(u, ts.ImplicitSurface(ts.sdf.sphere(grid), grid))
        finally:
            torch._dynamo.reset()
        expected = flow(u, ts.ImplicitSurface(ts.sdf.sphere(grid), grid))
    torch.testing.assert_close(result, expected, rtol=1e-5, atol=1e-6)


def test_inductor_compiles_an_edge_stopping_flow_with_heun_steps(sphere):
    """A Heun step re-extends the band between its two rates; the replicated halo of the second
    rate, read through that gather, stopped inductor's range analysis in torch 2.13 (``vr must
    not be None``) until the halo was traced as concatenated copies of the faces."""
    u, surface = sphere
    flow = AnisotropicFlow(surface.spacing**2 / 40, "perona_malik", method="heun", steps=1)
    with torch.no_grad():
        expected = flow(u, surface)
        torch._dynamo.reset()
        try:
            result = torch.compile(flow)(u, surface)
        finally:
            torch._dynamo.reset()
    torch.testing.assert_close(result, expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("shape", [(1, 1, 7, 5, 6), (2, 1, 1, 4, 3), (1, 1, 3, 1, 1)])
def test_traced_sign_changes_and_halo_equal_the_eager_ones(shape):
    from torchsurf.stencils import _replicated_halo_traced, replicated_halo
    from torchsurf.surface import _crossing, _crossing_traced

    values = torch.randn(shape, generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(_crossing_traced(values < 0), _crossing(values < 0), rtol=0, atol=0)
    assert _crossing(values < 0).any() or min(shape[2:]) == 1
    for width in (1, 2):
        torch.testing.assert_close(_replicated_halo_traced(values, width),
                                   replicated_halo(values, width), rtol=0, atol=0)


@pytest.mark.parametrize("shape", [(1, 1, 7, 5, 6), (2, 1, 1, 4, 3), (1, 1, 3, 1, 1)])
def test_traced_ring_dilation_equals_the_eager_one(shape):
    from torchsurf.flows._integrators import _with_ring_traced, with_ring

    band = torch.rand(shape, generator=torch.Generator().manual_seed(1)) < 0.15
    band.view(-1)[0] = True
    torch.testing.assert_close(_with_ring_traced(band), with_ring(band), rtol=0, atol=0)


def test_a_flow_recording_its_steps_traces_without_graph_break(sphere):
    """Under autograd the steps run as recomputed segments; while traced, as
    ``torch.utils.checkpoint`` regions, which the trace enters (the segments' own autograd
    function and the walk of the reads' graph nodes broke the graph at every segment)."""
    u, surface = sphere
    flow = _flows(surface.spacing**2)["learned time and diffusivity, bounded"]
    assert _break_reasons(flow, u.clone().requires_grad_(), surface, grad=True) == []


@pytest.mark.slow
def test_inductor_compiles_a_flow_recording_its_steps(sphere):
    """Compiled whole with inductor, a learned flow's result and gradients (in ``u``, the time
    and the diffusivity) are the eager ones."""
    u, surface = sphere
    flow = _flows(surface.spacing**2)["learned time and diffusivity, bounded"]

    def value_and_grads(module):
        x = u.clone().requires_grad_()
        flow.zero_grad()
        out = module(x, surface)
        out.square().sum().backward()
        return out.detach(), x.grad, *(p.grad.clone() for p in flow.parameters())

    expected = value_and_grads(flow)
    torch._dynamo.reset()
    try:
        result = value_and_grads(torch.compile(flow))
    finally:
        torch._dynamo.reset()
    torch.testing.assert_close(result, expected, rtol=1e-5, atol=1e-5)  # float32, data O(1)


class _CoupledDiffusion(torch.nn.Module):
    def forward(self, u: torch.Tensor, surface: ts.ImplicitSurface) -> torch.Tensor:
        return ts.anisotropic_diffusion(u, surface, "perona_malik", 0.7, coupled=True)


def test_coupled_operators_and_harmonic_maps_trace_without_graph_break(sphere):
    """The coupled kernel ran its one-pass form while traced, whose graph breaks shape our own
    compiled graphs (3 breaks); the harmonic map flow read its growth bound, which only RKC's
    own plan uses, from the data (2 breaks)."""
    u, surface = sphere
    unit = u / u.norm(dim=1, keepdim=True)
    assert _break_reasons(_CoupledDiffusion(), u, surface) == []
    flow = HarmonicMapFlow(surface.spacing**2 / 400, method="euler", steps=1)
    assert _break_reasons(flow, unit, surface) == []


def test_the_compiled_path_traces_in_an_outer_compile_for_a_batch(sphere):
    """path='compiled' marked the batch dimension dynamic inside the outer trace, which dynamo
    refuses (a bare AssertionError) for a batch of two or more."""
    u, surface = sphere
    batch = torch.cat([u, 2 * u])
    expected = ts.intrinsic_gradient(batch, surface, path="slicing")
    torch._dynamo.reset()
    try:
        traced = torch.compile(lambda x: ts.intrinsic_gradient(x, surface, path="compiled"),
                               backend="eager", fullgraph=True)
        assert torch.allclose(traced(batch), expected, atol=1e-6)
    finally:
        torch._dynamo.reset()


def test_flows_on_bricks_trace_without_graph_break():
    """On bricks the heat flow read the size of its band on the host (a break, and
    fullgraph=True failed) and the haloed kernels read the backend's context variable while
    traced (7-8 breaks in the Perona-Malik and harmonic map flows)."""
    grid = ts.Grid.cube(17, 2.0)
    packed = ts.bricks.from_dense(ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9), grid))
    u = packed.from_dense(torch.rand(1, 3, *grid.shape, generator=torch.Generator().manual_seed(1)))
    unit = u / u.norm(dim=1, keepdim=True)
    h2 = packed.spacing**2
    for flow, data in ((HeatFlow(h2 / 40, method="euler", steps=1), u),
                       (AnisotropicFlow(h2 / 100, "perona_malik", contrast=2.0, method="euler",
                                        steps=1), u),
                       (HarmonicMapFlow(h2 / 400, method="euler", steps=1), unit)):
        assert _break_reasons(flow, data, packed) == [], flow


def test_the_compiled_path_is_kept_by_the_heat_semigroup(sphere, monkeypatch):
    """path='compiled' was ignored by the Chebyshev semigroup on a fixed phi: it ran the packed
    band matrices (bit for bit path='slicing'), where the docs promise the compiled volume
    stencils."""
    from torchsurf.flows.exponential import BandLaplacian

    _, surface = sphere
    assert BandLaplacian(surface, path="compiled").packed() is None
    assert BandLaplacian(surface, path="slicing").packed() is not None
    monkeypatch.setattr(ts.backend, "COMPILE", "always")  # compiles "auto", not an eager path
    assert BandLaplacian(surface, path="auto").packed() is None
    assert BandLaplacian(surface, path="slicing").packed() is not None


@pytest.mark.parametrize("method", ["euler", pytest.param("chebyshev", marks=pytest.mark.slow)])
def test_phi_gradient_through_a_compiled_flow_is_the_eager_one(method):
    """The surface's haloed geometry, first formed inside a traced checkpoint segment, was kept
    with that segment's graph: phi's gradient came out twice the eager one (Euler steps;
    aot_eager, and inductor once the flow compiled), and ``chebyshev``'s recomputed pieces
    saved other tensors than their forward (``CheckpointError``)."""
    grid = ts.Grid.cube(11, 1.5)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(3),
                   dtype=torch.float64)
    phi0 = ts.sdf.sphere(grid, 0.6, center=(0.031, -0.017, 0.043), dtype=torch.float64)
    flow = (AnisotropicFlow(grid.spacing**2 / 8, "perona_malik", method="euler", steps=1,
                            reextend_every=None) if method == "euler"
            else HeatFlow(2 * grid.spacing**2, method="chebyshev"))

    def phi_gradient(compiled: bool) -> torch.Tensor:
        phi = phi0.clone().requires_grad_()
        torch._dynamo.reset()
        try:
            layer = torch.compile(flow, backend="aot_eager") if compiled else flow
            layer(u, ts.ImplicitSurface(phi, grid)).square().sum().backward()
        finally:
            torch._dynamo.reset()
        return phi.grad

    torch.testing.assert_close(phi_gradient(True), phi_gradient(False), rtol=1e-10, atol=1e-12)


@pytest.mark.slow
def test_a_compiled_reaction_diffusion_draws_the_eager_noise_under_a_global_seed():
    """Traced, inductor replaced the noise's ``torch.rand`` by its own random numbers: the same
    ``torch.manual_seed`` gave another pattern (2.0e-3 on a scale of 4)."""
    grid = ts.Grid.cube(10, 1.6)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = ts.ReactionDiffusion.initial(surface) + 0.1 * torch.rand(
        1, 2, *grid.shape, generator=torch.Generator().manual_seed(5))
    flow = ts.ReactionDiffusion(2.0, method="euler")
    with torch.no_grad():
        torch.manual_seed(7)
        expected = flow(u, surface)
        torch._dynamo.reset()
        try:
            torch.manual_seed(7)
            result = torch.compile(flow)(u, surface)
        finally:
            torch._dynamo.reset()
    torch.testing.assert_close(result, expected, rtol=0, atol=2e-5)


@pytest.mark.parametrize("kind", ["heat", "anisotropic"])
def test_a_fresh_surface_is_prepared_as_is_once_and_then_traced_whole(kind):
    """What a flow keeps on a surface was formed where each piece was first read inside the
    trace: about 20 graph breaks on a fresh surface (an Euler heat step), each piece compiled
    apart, and a recompile on the second call. The flow now runs as is once, outside the
    trace, and the rest is one graph; the next call compiles nothing."""
    from torch._dynamo.testing import CompileCounter

    grid = ts.Grid.cube(9, 1.5)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(3))
    flow = (HeatFlow(grid.spacing**2 / 40, method="euler", steps=1) if kind == "heat"
            else AnisotropicFlow(1e-3, method="euler", steps=1))
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    counter = CompileCounter()
    with torch.no_grad():
        torch._dynamo.reset()
        try:
            compiled = torch.compile(flow, backend=counter)
            first = compiled(u, surface)
            graphs = counter.frame_count
            second = compiled(u, surface)
        finally:
            torch._dynamo.reset()
        expected = flow(u, ts.ImplicitSurface(ts.sdf.sphere(grid), grid))
    assert graphs <= 2, graphs
    assert counter.frame_count == graphs  # the second call compiled nothing
    torch.testing.assert_close(first, expected, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(second, expected, rtol=1e-5, atol=1e-6)


def test_a_layer_compiled_in_place_runs_as_is_first_without_recursing():
    """``Module.compile()`` compiles the module's call: the run as is went back into it, without
    end (RecursionError, a review, 2026-12-07); ``times`` as an iterator was used up by it."""
    grid = ts.Grid.cube(9, 1.5)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(3))
    h2 = grid.spacing**2
    calls = []
    for layer in (HeatFlow(h2, method="euler"), ts.nn.LearnedDiffusion(1, max_time=2.0)):
        layer.register_forward_hook(lambda *_: calls.append(1))
        expected = layer(u, ts.ImplicitSurface(ts.sdf.sphere(grid), grid))
        calls.clear()
        torch._dynamo.reset()
        try:
            layer.compile(backend="aot_eager")
            with torch.no_grad():
                result = layer(u, ts.ImplicitSurface(ts.sdf.sphere(grid), grid))
        finally:
            torch._dynamo.reset()
        torch.testing.assert_close(result, expected.detach(), rtol=1e-5, atol=1e-6)
        assert len(calls) == 1  # the run as is calls no hooks
    flow = HeatFlow(h2, method="euler")
    torch._dynamo.reset()
    try:
        with torch.no_grad():
            several = torch.compile(flow, backend="aot_eager")(
                u, ts.ImplicitSurface(ts.sdf.sphere(grid), grid), times=iter([0.3 * h2, h2]))
    finally:
        torch._dynamo.reset()
    assert several.shape == (2, *u.shape)


def test_layers_of_one_class_share_the_mark_and_the_range_warning_is_given():
    """Marked by the layer object, one compiled function given four layers of one class
    recompiled for each; the run as is had silenced its warnings, and the range warning, which
    a traced call skips, was lost; a flow input named ``layer`` clashed with the run's own
    argument (a review, 2026-12-07)."""
    from torch._dynamo.testing import CompileCounter

    grid = ts.Grid.cube(9, 1.5)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(3))
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    layers = [ts.nn.LearnedDiffusion(1, max_time=2.0) for _ in range(4)]
    for layer in layers:
        layer(u, surface)
    counter = CompileCounter()
    torch._dynamo.reset()
    try:
        compiled = torch.compile(lambda layer, v: layer(v, surface), backend=counter)
        with torch.no_grad():
            for layer in layers:
                compiled(layer, u)
        assert counter.frame_count == 1
        unstable = HeatFlow(2 * grid.spacing**2, method="euler", steps=1)
        with pytest.warns(RuntimeWarning, match="left the range of u0"), torch.no_grad():
            torch.compile(unstable, backend="aot_eager")(
                u, ts.ImplicitSurface(ts.sdf.sphere(grid), grid))
    finally:
        torch._dynamo.reset()
    from torchsurf._as_is import run_as_is_first
    run_as_is_first(layers[0], u, surface, layer=1)  # an input of that name is passed on
