"""Checkpointed integration: the same gradients, a fraction of the memory kept for backward."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows._recompute import recomputed


def _saved_bytes(run) -> tuple[torch.Tensor, int]:
    total = 0

    def pack(tensor):
        nonlocal total
        total += tensor.numel() * tensor.element_size()
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        value = run()
    return value, total


# steps enough that what each step saves dominates: the packed steps save little (RKC's plan of
# 3 steps saved 0.79 MB without checkpointing, 0.45 MB with it, mostly the call's own)
@pytest.mark.parametrize("method,steps", [("euler", 64), ("rkc", 16), ("heun", 36)])
def test_checkpointing_keeps_gradients_and_cuts_saved_memory(method, steps):
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    generator = torch.Generator().manual_seed(0)
    u0 = torch.rand((1, 2, *grid.shape), dtype=torch.float64, generator=generator)
    weights = torch.rand(u0.shape, dtype=torch.float64, generator=generator)
    results = {}
    for checkpoint in (False, True):
        flow = ts.HeatFlow(0.02, learn_diffusivity=True, method=method, steps=steps,
                           checkpoint=checkpoint).double()
        start = u0.clone().requires_grad_(True)
        value, saved = _saved_bytes(lambda flow=flow, start=start: flow(start, surface))
        (value * weights).sum().backward()
        grads = (start.grad, *(p.grad for p in flow.parameters()))
        results[checkpoint] = (value.detach(), grads, saved)
    plain, kept = results[False], results[True]
    torch.testing.assert_close(kept[0], plain[0], rtol=1e-12, atol=1e-12)
    for a, b in zip(kept[1], plain[1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    assert kept[2] < plain[2] / 3, (kept[2], plain[2])


def test_checkpoint_auto_follows_autograd_and_bad_values_are_refused():
    grid = ts.Grid.cube(9, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u0 = torch.rand((1, 1, *grid.shape))
    flow = ts.HeatFlow(0.01)
    system = flow.system(u0, surface)
    assert not flow._checkpointing(u0, surface, system)
    assert flow._checkpointing(u0.requires_grad_(True), surface, system)
    with torch.no_grad():
        assert not flow._checkpointing(u0, surface, system)
    with pytest.raises(TypeError, match="checkpoint"):
        ts.HeatFlow(0.01, checkpoint="yes")


def _graph_nodes(tensor: torch.Tensor) -> int:
    seen, stack = set(), [tensor.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        stack.extend(next_node for next_node, _ in node.next_functions)
    return len(seen)


def _flow_cases():
    return [
        ("perona_malik", lambda: ts.AnisotropicFlow(0.02, "perona_malik", contrast=2.0,
                                                     learn_contrast=True, learn_time=True)),
        ("heat, learned time", lambda: ts.HeatFlow(0.02, learn_time=True, method="euler")),
        ("harmonic", lambda: ts.HarmonicMapFlow(0.005)),
    ]


@pytest.mark.parametrize("name,make", _flow_cases(), ids=[c[0] for c in _flow_cases()])
def test_checkpointed_flows_keep_their_gradients_in_u_parameters_and_phi(name, make):
    """The recomputed segments give every gradient the recorded run gives: the data's, the
    flow's parameters' and the level set function's (read through the surface's geometry)."""
    grid = ts.Grid.cube(13, 1.5)
    generator = torch.Generator().manual_seed(1)
    base = ts.sdf.sphere(grid, dtype=torch.float64) * 1.3  # not a distance: W varies
    channels = 3 if name == "harmonic" else 2
    u0 = torch.rand((1, channels, *grid.shape), dtype=torch.float64, generator=generator)
    if name == "harmonic":
        u0 = u0 - 0.5
        u0 = u0 / u0.norm(dim=1, keepdim=True)
    weights = torch.rand(u0.shape, dtype=torch.float64, generator=generator)
    results = {}
    for checkpoint in (False, True):
        torch.manual_seed(0)
        flow = make().double()
        flow.checkpoint = checkpoint
        phi = base.clone().requires_grad_(True)
        surface = ts.ImplicitSurface(phi, grid)
        start = u0.clone().requires_grad_(True)
        value = flow(start, surface)
        if checkpoint:
            assert _graph_nodes(value) < 64, _graph_nodes(value)
        (value * weights).sum().backward()
        results[checkpoint] = (value.detach(), start.grad, phi.grad,
                               *(p.grad for p in flow.parameters()))
    for kept, plain in zip(results[True], results[False], strict=True):
        assert plain is not None and kept is not None
        torch.testing.assert_close(kept, plain, rtol=1e-9, atol=1e-12)


def test_a_segment_that_reads_an_undeclared_tensor_needing_gradients_raises():
    from torchsurf.flows._recompute import recomputed

    scale = torch.tensor(2.0, dtype=torch.float64, requires_grad=True)
    u = torch.rand(1, 1, 3, 3, 3, dtype=torch.float64, requires_grad=True)
    declared = recomputed(lambda x: scale * x.sin(), u, [scale])
    declared.sum().backward()
    torch.testing.assert_close(u.grad, scale.detach() * u.detach().cos())
    torch.testing.assert_close(scale.grad, u.detach().sin().sum())
    hidden = recomputed(lambda x: (scale * 1.5) * x.sin(), u, [])
    with pytest.raises(RuntimeError, match="declared inputs"):
        hidden.sum().backward()


def test_a_segment_whose_input_changed_in_place_before_backward_raises():
    from torchsurf.flows._recompute import recomputed

    u = torch.rand(1, 1, 3, 3, 3, dtype=torch.float64, requires_grad=True)
    start = u * 1.0
    result = recomputed(lambda x: x.sin(), start, [])
    start.add_(1.0)  # the recomputation would read the changed values
    with pytest.raises(RuntimeError, match="inplace"):
        result.sum().backward()


def test_chebyshev_expansion_with_a_learned_phi_recomputes_its_groups(monkeypatch):
    """The heat semigroup by Chebyshev expansion on a ``phi`` that requires grad: its groups of
    terms run without a graph (what stays is the geometry's graph from ``phi`` and the first two
    terms, not a dozen nodes a term) and backward gives the gradients in ``u``, the time and
    ``phi`` that the recurrence recorded whole gives."""
    import torchsurf.flows.chebyshev as chebyshev
    import torchsurf.flows.heat as heat

    grid = ts.Grid.cube(13, 1.5)
    generator = torch.Generator().manual_seed(4)
    base = ts.sdf.sphere(grid, dtype=torch.float64) * 1.3
    u0 = torch.rand((1, 2, *grid.shape), dtype=torch.float64, generator=generator)
    weights = torch.rand(u0.shape, dtype=torch.float64, generator=generator)
    results, nodes = {}, {}
    for recorded in (True, False):
        if recorded:
            for module in (chebyshev, heat):
                monkeypatch.setattr(module, "recomputed", lambda function, u, reads, what="": function(u))
        else:
            monkeypatch.undo()
        flow = ts.HeatFlow(6 * grid.spacing**2, method="chebyshev", learn_time=True).double()
        phi = base.clone().requires_grad_(True)
        start = u0.clone().requires_grad_(True)
        value = flow(start, ts.ImplicitSurface(phi, grid))
        nodes[recorded] = _graph_nodes(value)
        (value * weights).sum().backward()
        results[recorded] = (value.detach(), start.grad, phi.grad,
                             *(p.grad for p in flow.parameters()))
    assert nodes[False] < nodes[True] / 4, nodes
    for kept, plain in zip(results[False], results[True], strict=True):
        assert plain is not None and kept is not None
        torch.testing.assert_close(kept, plain, rtol=1e-9, atol=1e-12)


def test_chebyshev_pieces_on_a_learned_phi_are_recomputed_in_groups():
    """With phi needing gradients the Chebyshev semigroup's pieces ran one after another under
    autograd, each keeping its re-extensions' graph (21 MB a piece at 20^3, 402 MB at 128 h^2):
    they are now recomputed sqrt(pieces) at a time, as with a fixed phi, so what the forward
    keeps does not grow with the time."""
    grid = ts.Grid.cube(14, 1.5)
    base = ts.sdf.sphere(grid, radius=0.8, center=(0.03, -0.02, 0.01), dtype=torch.float64)
    u0 = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                    generator=torch.Generator().manual_seed(6))
    kept = {}
    for cells in (2, 64):
        flow = ts.HeatFlow(cells * grid.spacing**2, method="chebyshev", learn_time=True).double()
        value = flow(u0, ts.ImplicitSurface(base.clone().requires_grad_(True), grid))
        kept[cells] = _graph_nodes(value)
    assert kept[64] <= kept[2] + 8, kept


def test_recomputing_the_identity_passes_the_input_through():
    """A step that changes nothing (a re-extension not due) returns its input itself; an
    autograd Function may not, so ``recomputed`` passes it through and gradients keep flowing
    (a bounded learned time once lost its whole gradient this way)."""
    u = torch.rand(1, 1, 3, 3, 3, dtype=torch.float64, requires_grad=True)
    scale = torch.tensor(2.0, dtype=torch.float64, requires_grad=True)
    value = recomputed(lambda v: v, u * scale, [scale])
    value.sum().backward()
    assert torch.allclose(scale.grad, u.detach().sum())
    assert torch.allclose(u.grad, torch.full_like(u, 2.0))


def test_checkpointed_results_at_several_times_keep_their_gradients():
    """Each requested result is re-extended into what is returned (not into the state), by a
    step recomputed in backward; its choice depends on the step count at that time only, so
    the gradients equal the recorded run's whatever backward recomputes first (here, the
    re-extension period is 15 steps: backward recomputes steps 11-15 before the result at
    step 10, which a choice read from the last step seen got wrong)."""
    grid = ts.Grid.cube(13, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    generator = torch.Generator().manual_seed(2)
    u0 = torch.rand((1, 1, *grid.shape), dtype=torch.float64, generator=generator)
    weights = torch.rand((3, *u0.shape), dtype=torch.float64, generator=generator)
    results = {}
    for checkpoint in (False, True):
        flow = ts.HeatFlow(0.19, steps=40, learn_time=True, max_time=0.2,
                           checkpoint=checkpoint).double()
        start = u0.clone().requires_grad_(True)
        value = flow(start, surface, times=[0.05, 0.175, 0.2])
        (value * weights).sum().backward()
        results[checkpoint] = (value.detach(), start.grad, flow.time_value.raw.grad)
    for kept, plain in zip(results[True], results[False], strict=True):
        torch.testing.assert_close(kept, plain, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("name", ["visualization", "reaction_diffusion"])
def test_a_direction_field_keeps_its_gradient_when_phi_needs_one_too(name):
    """The tangent field, made from the given one and phi's normals, was the only direction
    the flows declared: with phi needing gradients too it was left out as computed from
    another, so checkpointed segments raised in backward and ``adjoint=True`` returned no
    gradient for the given field."""
    pytest.importorskip("torchdiffeq")
    grid = ts.Grid.cube(12, 1.5)
    generator = torch.Generator().manual_seed(3)
    base = ts.sdf.sphere(grid, radius=0.8, center=(0.05, -0.03, 0.02), dtype=torch.float64)
    field = torch.randn((1, 3, *grid.shape), dtype=torch.float64, generator=generator)
    u = torch.rand((1, 1, *grid.shape), dtype=torch.float64, generator=generator)
    h2 = grid.spacing**2
    if name == "visualization":
        u0, call = u, {}

        def make(**options):
            return ts.FlowVisualization(2 * h2, **options)
    else:
        u0, call = torch.cat([4 + u, 4 - u], dim=1), {"generator": None}

        def make(**options):
            return ts.ReactionDiffusion(20.0, **options)

    def gradients(flow):
        phi = base.clone().requires_grad_(True)
        direction = field.clone().requires_grad_(True)
        options = dict(call)
        if "generator" in options:
            options["generator"] = torch.Generator().manual_seed(1)
        value = flow(u0, ts.ImplicitSurface(phi, grid), direction=direction, **options)
        return torch.autograd.grad(value.square().sum(), (direction, phi), allow_unused=True)

    plain = gradients(make(method="euler", checkpoint=False))
    kept = gradients(make(method="euler", checkpoint=True))
    for a, b in zip(kept, plain, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)
    # the adjoint gives the continuous gradient, rk4 the discrete one: 0.6% and 1.4% apart here
    direct = gradients(make(method="rk4"))
    adjoint = gradients(make(method="rk4", adjoint=True))
    assert adjoint[0] is not None
    for a, b in zip(adjoint, direct, strict=True):
        assert float((a - b).norm() / b.norm()) < 0.03


def test_checkpointed_flows_run_under_inference_mode():
    """``enable_grad`` does not leave inference mode: finding the declared reads walked a graph
    that is not there ('NoneType' object has no attribute 'next_functions') when phi, or a
    diffusivity module's parameters, needed gradients."""
    grid = ts.Grid.cube(14, 1.5)
    phi = ts.sdf.sphere(grid, radius=0.9).requires_grad_(True)
    u = torch.rand((1, 1, *grid.shape), generator=torch.Generator().manual_seed(2))
    for make in (lambda: ts.HeatFlow(0.01, checkpoint=True),
                 lambda: ts.AnisotropicFlow(0.01, "perona_malik", learn_contrast=True,
                                            checkpoint=True)):
        with torch.no_grad():
            expected = make()(u, ts.ImplicitSurface(phi, grid))
        with torch.inference_mode():
            value = make()(u, ts.ImplicitSurface(phi, grid))
        torch.testing.assert_close(value, expected, rtol=0, atol=0)


def test_requested_times_do_not_multiply_the_checkpoints():
    """Groups were sqrt(steps) of each interval between requested times, so 16 evenly spaced
    times saved 95 volumes for backward against 14 for one (222 Euler steps at 17^3); groups
    are now sqrt(all the steps): 46, about two a requested time."""
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0, dtype=torch.float64), grid)
    u0 = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                    generator=torch.Generator().manual_seed(0))
    end = 40 * grid.spacing**2
    saved = {}
    for count in (1, 16):
        flow = ts.HeatFlow(end, method="euler", learn_time=True, max_time=end).double()
        times = torch.linspace(0, end, count + 1)[1:].tolist()
        _, saved[count] = _saved_bytes(lambda flow=flow, times=times: flow(u0, surface,
                                                                             times=times))
    assert saved[16] < 4 * saved[1], saved


@pytest.mark.parametrize("make", [lambda: ts.nn.LearnedDiffusion(1, time=1.5),
                                  lambda: ts.HeatFlow(0.02, learn_time=True),
                                  lambda: ts.HeatFlow(0.02, scheme="central"),
                                  lambda: _Operator(scheme="central")])  # mean curvature kept
def test_a_users_checkpoint_around_a_layer_on_a_learned_phi(make):
    """torch.utils.checkpoint(layer, u, surface, use_reentrant=False) on a surface whose phi
    requires grad: the surface's haloed geometry (and mean curvature) was first formed inside
    the region and kept with its graph, so the recomputation saved fewer tensors than the
    forward (CheckpointError), and every later call through the surface, plain ones too,
    failed the same way. Now the same gradients as a plain call, before and after."""
    grid = ts.Grid.cube(14, 1.7)
    phi = ts.sdf.sphere(grid, 1.0, center=(0.03, -0.02, 0.05), dtype=torch.float64)
    phi.requires_grad_(True)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(0))
    layer = make().double()

    def phi_gradient(call) -> torch.Tensor:  # the surface's geometry is read again: retained
        (gradient,) = torch.autograd.grad(call().square().sum(), phi, retain_graph=True)
        return gradient

    expected = phi_gradient(lambda: layer(u, ts.ImplicitSurface(phi, grid)))
    surface = ts.ImplicitSurface(phi, grid)
    for call in (lambda: torch.utils.checkpoint.checkpoint(layer, u, surface, use_reentrant=False),
                 lambda: torch.utils.checkpoint.checkpoint(layer, u, surface, use_reentrant=False),
                 lambda: layer(u, surface)):
        torch.testing.assert_close(phi_gradient(call), expected, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("make", [
    lambda: ts.AnisotropicFlow(0.01, "perona_malik", learn_contrast=True),
    lambda: ts.HeatFlow(0.01, learn_time=True, max_time=0.02),
    lambda: ts.HeatFlow(0.01, method="chebyshev", learn_time=True, max_time=0.02),
    lambda: ts.nn.LearnedDiffusion(1, time=3.0),
])
def test_a_users_checkpoint_recomputes_a_flow_once(make):
    """Inside torch.utils.checkpoint (non-reentrant) with phi learned, each recomputed segment's
    backward walked into the tensors formed from phi in the region, whose saved tensors were
    the region's: the region ran its whole forward again once a segment (5 to 9 times here; a
    total variation flow at 14^3: backward 34 s against 4 s called plainly). Now once, with
    the plain call's gradients."""
    grid = ts.Grid.cube(11, 1.6)
    base = ts.sdf.sphere(grid, 0.9, center=(0.04, -0.03, 0.02), dtype=torch.float64)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(5))
    layer = make().double()
    runs = 0

    def region(data, surface):
        nonlocal runs
        runs += 1
        return layer(data, surface).sin()

    def gradients(call):
        phi = base.clone().requires_grad_(True)
        data = u.clone().requires_grad_(True)
        value = call(data, ts.ImplicitSurface(phi, grid))
        wanted = (data, phi, *(p for p in layer.parameters() if p.requires_grad))
        return torch.autograd.grad(value.square().sum(), wanted)

    expected = gradients(region)
    runs = 0
    checkpointed = gradients(lambda data, surface: torch.utils.checkpoint.checkpoint(
        region, data, surface, use_reentrant=False))
    assert runs == 2  # the forward, and one recomputation in backward
    for value, reference in zip(checkpointed, expected, strict=True):
        torch.testing.assert_close(value, reference, rtol=1e-12, atol=1e-12)


class _Operator(torch.nn.Module):
    """``laplace_beltrami(u, surface, scheme)`` as a module (the central scheme reads the
    surface's kept mean curvature)."""

    def __init__(self, scheme: str) -> None:
        super().__init__()
        self.scheme = scheme

    def forward(self, u: torch.Tensor, surface: ts.ImplicitSurface) -> torch.Tensor:
        return ts.laplace_beltrami(u, surface, scheme=self.scheme)
