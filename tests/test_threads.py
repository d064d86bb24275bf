"""Python threads sharing a flow and a surface (a thread pool serving requests): what a call
needs for itself lives in the call (context variables, locals), not on the shared module, so
concurrent calls give the serial calls' numbers and leave the module as it was."""

import threading
import warnings
from concurrent.futures import ThreadPoolExecutor

import pytest
import torch

import torchsurf as ts
from torchsurf import bricks
from torchsurf.flows import base


def _concurrent(call, requests, rounds=3):
    """``call`` on each request from as many threads, ``rounds`` times: the results."""
    with ThreadPoolExecutor(len(requests)) as pool:
        return [list(pool.map(call, requests)) for _ in range(rounds)]


@pytest.mark.parametrize("method", ["rkc", "chebyshev"])
def test_a_diffusivity_per_channel_from_several_threads(method):
    """Each value's channels ran apart by swapping the flow's diffusivity submodule for the
    group's: other threads' calls ran every channel with that group's value (10 of 15 calls
    0.27 off on data of size 1), and a swap could stay in place for good."""
    grid = ts.Grid.cube(20, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    h2 = grid.spacing**2
    flow = ts.HeatFlow(4 * h2, diffusivity=torch.tensor([1.0, 0.25]), method=method)
    generator = torch.Generator().manual_seed(0)
    requests = [torch.randn(1, 2, *grid.shape, generator=generator) for _ in range(3)]
    with torch.no_grad():
        serial = [flow(u, surface) for u in requests]
        for results in _concurrent(lambda u: flow(u, surface), requests):
            for result, expected in zip(results, serial, strict=True):
                torch.testing.assert_close(result, expected, rtol=0, atol=1e-5)
    assert torch.equal(flow.diffusivity.value(), torch.tensor([1.0, 0.25]))  # left as it was


def test_range_warnings_one_per_call_and_each_threads_own(monkeypatch):
    """A call whose runs go apart (batch entries, channel groups) gathers their range excesses
    for one warning. The list was the flow's attribute, so a concurrent call on the same flow
    could add to it or take its warning; and a group run by a copy of the flow must still
    count as its call's. One unstable Euler step on noise leaves the range (one warning per
    call, for a batch of two surfaces and two channel groups); on constants it does not. The
    threads' half catches the former race only when calls overlap (3 of 5 runs failed on
    c3416b4); the first half checks the groups' copies count as their call."""
    grid = ts.Grid.cube(12, 1.5)
    h2 = grid.spacing**2
    batch = ts.ImplicitSurface(torch.cat([ts.sdf.sphere(grid, 1.0), ts.sdf.sphere(grid, 0.8)]),
                               grid)
    flow = ts.HeatFlow(2 * h2, diffusivity=torch.tensor([1.0, 0.25]), method="euler", steps=1)
    noise = torch.rand(2, 2, *grid.shape, generator=torch.Generator().manual_seed(0))
    constant = torch.full_like(noise, 0.5)
    warned = []
    monkeypatch.setattr(base, "_warn_range_left",
                        lambda *args: warned.append(threading.get_ident()))
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")   # the step's own warning (beyond the stable step)
        flow(noise, batch)
        assert len(warned) == 1
        warned.clear()
        requests = [noise, constant, noise, constant]
        with ThreadPoolExecutor(len(requests)) as pool:
            calls = list(pool.map(lambda u: (threading.get_ident(), bool(u.std() > 0),
                                             flow(u, batch)), requests))
    # threads may serve several requests: each noisy request warned once, no constant one did
    noisy = sorted(ident for ident, is_noise, _ in calls if is_noise)
    assert sorted(warned) == noisy


def test_brick_surfaces_shared_by_threads_with_other_bands():
    """One brick surface, two bands (flows of two band widths) from two threads: the C
    kernel's kept row bits and packed geometry are the layout's, shared; they are kept as one
    tuple each, so no call reads one band's rows with another's bits
    (tests/bricks/test_native.py makes that interleaving happen deterministically)."""
    grid = ts.Grid.cube(32, 1.5)
    surface = bricks.from_dense(ts.sdf.sphere(grid, 1.0), grid)
    h = grid.spacing
    flows = [ts.HeatFlow(8 * h * h, reextend_every=None),
             ts.HeatFlow(8 * h * h, reextend_every=None, band_width=2 * h)]
    u = torch.randn(len(surface.layout), 1, 8, 8, 8, generator=torch.Generator().manual_seed(2))
    with torch.no_grad():
        serial = [flow(u, surface) for flow in flows]
        for results in _concurrent(lambda flow: flow(u, surface), flows):
            for result, expected in zip(results, serial, strict=True):
                torch.testing.assert_close(result, expected, rtol=0, atol=1e-5)


def test_no_call_leaves_a_warnings_filter_behind():
    """A dense batch's entry surfaces were built under warnings.catch_warnings with a filter
    ignoring RuntimeWarning: global, so threads overlapping in it left the filter in place for
    good (10 of 10 processes), and every later RuntimeWarning of the process, torchsurf's and
    numpy's, was silenced. They now skip their checks by a context variable of their thread."""
    grid = ts.Grid.cube(16, 1.5)
    flow = ts.HeatFlow(2 * grid.spacing**2)
    u = torch.rand(2, 1, *grid.shape, generator=torch.Generator().manual_seed(3))

    def request(radius: float) -> torch.Tensor:
        phi = torch.cat([ts.sdf.sphere(grid, radius), ts.sdf.torus(grid, 0.8, 0.3)])
        return flow(u, ts.ImplicitSurface(phi, grid))

    before = list(warnings.filters)
    _concurrent(request, [0.9, 1.0, 1.1], rounds=2)
    assert warnings.filters == before
    with pytest.warns(RuntimeWarning, match="stays torch.float32"):  # warnings still reach
        ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid).half()


def test_scipy_solvers_run_without_touching_the_warnings_filters(monkeypatch):
    """torchdiffeq hands scipy's explicit solvers a min_step they do not read; scipy's warning
    of it was silenced by a global filter for the whole solve. The solver class now takes the
    argument itself: no filter, and no warning."""
    torchdiffeq = pytest.importorskip("torchdiffeq")
    grid = ts.Grid.cube(12, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0, dtype=torch.float64), grid)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    filters_at_solve = []
    solve = torchdiffeq.odeint

    def recording(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        filters_at_solve.append(list(warnings.filters))
        return solve(*args, **kwargs)

    monkeypatch.setattr(torchdiffeq, "odeint", recording)
    flow = ts.HeatFlow(grid.spacing**2, method="scipy_solver",
                       options={"solver": "RK45", "rtol": 1e-6, "atol": 1e-8})
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # scipy's min_step warning would raise here
        outside = list(warnings.filters)
        result = flow(u, surface)
    assert filters_at_solve and all(filters == outside for filters in filters_at_solve)
    reference = ts.HeatFlow(grid.spacing**2)(u, surface)
    band = surface.band_mask().expand_as(u)
    assert (result - reference)[band].abs().max() < 1e-2


def test_a_packed_heat_flow_s_gradient_does_not_depend_on_the_thread_count():
    """Backward summed the gradient of each entry's offset (zero: the operator annihilates
    constants) over the band's rows, in an order that follows torch's threads: at 1 and 2
    threads the gradient differed by 4.0e-5 of 3.6 at 9383 nodes (float32, 52^3); the offsets
    are now detached, and the gradient is the same bit for bit."""
    grid = ts.Grid.cube(52, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.torus(grid, 0.9, 0.42), grid)
    x, y, z = grid.points().unbind(-1)
    u0 = (torch.sin(4.1 * x) * torch.cos(3.3 * y) + 0.5 * z * x)[None, None]
    weights = torch.rand(u0.shape, generator=torch.Generator().manual_seed(7))
    flow = ts.HeatFlow(6 * grid.spacing**2)
    before = torch.get_num_threads()
    gradients = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            u = u0.clone().requires_grad_(True)
            (gradient,) = torch.autograd.grad((flow(u, surface) * weights).sum(), u)
            gradients.append(gradient)
    finally:
        torch.set_num_threads(before)
    assert torch.equal(gradients[0], gradients[1])
