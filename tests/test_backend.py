"""The backend's choice of path, and the tensor-level operators every path runs."""

from __future__ import annotations

import math
import os
import random
import time
import warnings

import pytest
import torch

import torchsurf as ts
from torchsurf import backend
from torchsurf.operators import functional


@pytest.fixture(autouse=True)
def auto_compiles(monkeypatch):
    """These tests are about what ``"auto"`` compiles: as in a user's process (the suite's
    conftest sets ``TORCHSURF_COMPILE=never``)."""
    monkeypatch.setattr(backend, "COMPILE", "auto")


def _kernel(name: str, calls: list[str], fused: bool = True) -> backend.Kernel:
    def eager(x, *, path):
        calls.append(path)
        return x + 1

    def fused_form(x):
        calls.append("fused")
        return x + 1

    return backend.Kernel(name, eager, fused_form if fused else None, lambda x: (x,))


def test_auto_stays_eager_until_the_measured_eager_time_pays_for_compiling(monkeypatch):
    calls: list[str] = []
    kernel = _kernel("test_payback", calls)
    volume = torch.zeros(1, 1, 4, 4, 4)
    compiled: list[object] = []
    monkeypatch.setattr(backend, "compiled", lambda f, *options: compiled.append(f) or f)
    clock = iter(float(t) for t in range(100))
    monkeypatch.setattr(backend.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 3.0)
    for _ in range(3):  # each eager call is measured at one second
        assert backend.resolve("auto", volume, kernel) == "slicing"
        backend.run(kernel, "auto", volume, volume)
    assert backend.resolve("auto", volume, kernel) == "compiled"
    backend.run(kernel, "auto", volume, volume)
    assert calls == ["slicing", "slicing", "slicing", "fused"]
    assert compiled == [kernel.fused]
    # another shape has its own ledger
    assert backend.resolve("auto", torch.zeros(1, 1, 5, 4, 4), kernel) == "slicing"


def test_a_kernel_that_costs_more_to_compile_waits_for_more_eager_time(monkeypatch):
    """``compile_weight``: a kernel whose compile costs three typical ones compiles after three
    times the payback of eager work (the coupled harmonic-map rate: a 128^3 flow with 13 s of
    eager work took 91 s once it compiled with an empty inductor cache)."""
    calls: list[str] = []
    kernel = backend.Kernel("test_heavy", lambda x, *, path: calls.append(path) or x + 1,
                            lambda x: calls.append("fused") or x + 1, lambda x: (x,),
                            compile_weight=3.0)
    volume = torch.zeros(1, 1, 4, 4, 4)
    monkeypatch.setattr(backend, "compiled", lambda f, *options: f)
    clock = iter(float(t) for t in range(100))
    monkeypatch.setattr(backend.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 2.0)
    for _ in range(6):  # one second each
        backend.run(kernel, "auto", volume, volume)
    backend.run(kernel, "auto", volume, volume)
    assert calls == ["slicing"] * 6 + ["fused"]
    with pytest.raises(ValueError, match="compile_weight"):
        backend.Kernel("bad", kernel.eager, kernel.fused, compile_weight=0.0)


def test_inside_a_plan_auto_compiles_once_the_remaining_steps_would_pay_for_it(monkeypatch):
    """A flow plans its steps (``backend.planned``): a kernel whose remaining steps' eager time
    reaches the payback compiles after the first step measured it; a short plan stays eager
    (and a kernel first seen mid-plan is measured from there)."""
    calls: list[str] = []
    volume = torch.zeros(1, 1, 4, 4, 4)
    monkeypatch.setattr(backend, "compiled", lambda f, *options: f)
    clock = iter(float(t) for t in range(1000))
    monkeypatch.setattr(backend.time, "perf_counter", lambda: next(clock))
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 5.0)

    def steps(kernel: backend.Kernel, count: int, taken: int) -> None:
        with backend.planned(count):
            for _ in range(taken):
                backend.run(kernel, "auto", volume, volume)  # one second each
                backend.step_taken()

    steps(_kernel("test_long_plan", calls), count=10, taken=3)
    assert calls == ["slicing", "fused", "fused"]  # 9 steps left at 1 s >= 5 s
    calls.clear()
    steps(_kernel("test_short_plan", calls), count=4, taken=4)
    assert calls == ["slicing"] * 4  # 3, 2, 1 s left: below the payback
    calls.clear()
    late = _kernel("test_late", calls)
    with backend.planned(10):
        for step in range(10):
            if step >= 8:
                backend.run(late, "auto", volume, volume)
            backend.step_taken()
    assert calls == ["slicing", "slicing"]  # first seen with 2 steps left
    backend.step_taken()  # outside a plan: nothing to count


def test_auto_never_compiles_on_a_first_call_but_inside_warm_up():
    """Even a large volume runs eagerly until its eager time pays for compiling it (the first
    compile in a process costs seconds to a minute); :func:`backend.warm_up` compiles at once,
    never a kernel without a compiled form."""
    calls: list[str] = []
    big = torch.zeros(1, 1, 64, 64, 64)
    assert backend.resolve("auto", big, _kernel("big", calls)) == "slicing"
    assert backend.resolve("auto", big, _kernel("big", calls), recording=True) == "slicing"
    with backend.warm_up():
        assert backend.resolve("auto", big, _kernel("big", calls)) == "compiled"
        assert backend.resolve("auto", big, _kernel("plain", calls, fused=False)) == "slicing"
    assert backend.resolve("auto", big, _kernel("big", calls)) == "slicing"
    with pytest.raises(ValueError, match="no compiled form"):
        backend.run(_kernel("plain", calls, fused=False), "compiled", big, big)


def test_auto_goes_back_to_eager_for_good_when_compiled_is_measured_slower(monkeypatch):
    calls: list[str] = []
    kernel = _kernel("test_slower", calls)
    volume = torch.zeros(1, 1, 4, 4, 4)
    monkeypatch.setattr(backend, "compiled", lambda f, *options: f)
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 2.0)
    # eager calls take one second each, compiled ones two (the first of them compiles)
    durations = iter([1.0, 1.0] + [5.0] + [2.0] * backend.COMPARED_CALLS)
    clock = {"now": 0.0, "start": True}

    def perf_counter() -> float:
        if not clock["start"]:
            clock["now"] += next(durations)
        clock["start"] = not clock["start"]
        return clock["now"]

    monkeypatch.setattr(backend.time, "perf_counter", perf_counter)
    for _ in range(2 + 1 + backend.COMPARED_CALLS):
        backend.run(kernel, "auto", volume, volume)
    assert calls == ["slicing"] * 2 + ["fused"] * (1 + backend.COMPARED_CALLS)
    assert backend.resolve("auto", volume, kernel) == "slicing"
    with backend.warm_up():
        assert backend.resolve("auto", volume, kernel) == "slicing"


def _failing_compiler(attempts: list[object]):
    """A ``backend.compiled`` whose kernels fail as inductor does without a C++ compiler."""
    def compile_(function, *options):
        def call(*args):
            attempts.append(function)
            raise RuntimeError("InvalidCxxCompiler: No working C++ compiler found")
        return call
    return compile_


def test_auto_runs_eagerly_for_good_with_one_warning_when_compiling_fails(monkeypatch):
    """No C++ compiler (or an inductor error): the default path gave the error to the user,
    and tried again, seconds each, at every later call."""
    calls: list[str] = []
    attempts: list[object] = []
    kernel, other = _kernel("test_fails", calls), _kernel("test_fails_too", calls)
    volume = torch.zeros(1, 1, 4, 4, 4)
    monkeypatch.setattr(backend, "compiled", _failing_compiler(attempts))
    monkeypatch.setattr(backend, "_COMPILE_FAILURE", [])
    with backend.warm_up(), pytest.warns(RuntimeWarning, match=r"test_fails failed.*C\+\+"):
        out = backend.run(kernel, "auto", volume, volume)
    assert torch.equal(out, volume + 1) and calls == ["fused"] and len(attempts) == 1
    with backend.warm_up(), warnings.catch_warnings():
        warnings.simplefilter("error")
        for chosen in (kernel, other):
            assert backend.resolve("auto", volume, chosen) == "slicing"
            assert torch.equal(backend.run(chosen, "auto", volume, volume), volume + 1)
    assert calls == ["fused", "slicing", "slicing"] and len(attempts) == 1
    with pytest.raises(RuntimeError, match="InvalidCxxCompiler"):  # asked for: the error
        backend.run(kernel, "compiled", volume, volume)


def test_a_compile_error_without_a_message_falls_back_too(monkeypatch):
    """The warning's reason took the message's first line: an empty one raised IndexError."""
    def compile_(function, *options):
        def call(*args):
            raise AssertionError()
        return call

    monkeypatch.setattr(backend, "compiled", compile_)
    monkeypatch.setattr(backend, "_COMPILE_FAILURE", [])
    volume = torch.zeros(1, 1, 4, 4, 4)
    with backend.warm_up(), pytest.warns(RuntimeWarning, match="AssertionError"):
        out = backend.run(_kernel("test_silent", []), "auto", volume, volume)
    assert torch.equal(out, volume + 1)


def test_an_error_of_the_callers_own_is_raised_as_eager_raises_it(monkeypatch):
    attempts: list[object] = []

    def eager(x, *, path):
        raise ValueError("the caller's own mistake")

    kernel = backend.Kernel("test_own_error", eager, lambda x: eager(x, path="fused"),
                            lambda x: (x,))
    monkeypatch.setattr(backend, "compiled", _failing_compiler(attempts))
    monkeypatch.setattr(backend, "_COMPILE_FAILURE", [])
    with backend.warm_up(), pytest.raises(ValueError, match="own mistake"):
        backend.run(kernel, "auto", torch.zeros(1, 1, 4, 4, 4), torch.zeros(1, 1, 4, 4, 4))


def test_a_flow_falls_back_to_what_the_compiled_form_returns(monkeypatch):
    """The closest-point gather's compiled form returns the value with its cell's range, which
    the caller of a "compiled" path reads; the fallback must return the same (the eager form's
    value alone failed as ``clamp_outside_range() missing 2 required positional arguments``)."""
    from torchsurf.bricks import _native as brick_native
    from torchsurf.flows import _native_gather

    monkeypatch.setenv("TORCHSURF_NATIVE", "never")  # as without a C compiler
    for library in (_native_gather.LIBRARY, brick_native.LIBRARY):
        monkeypatch.setattr(library, "_state", {})
    grid = ts.Grid.cube(17, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9), grid)
    u = torch.rand(1, 1, 17, 17, 17, generator=torch.Generator().manual_seed(0))
    extension = ts.Extension(interpolation="cubic", limited=True)  # a flow's re-extension
    expected = extension(u, surface)
    attempts: list[object] = []
    monkeypatch.setattr(backend, "compiled", _failing_compiler(attempts))
    monkeypatch.setattr(backend, "_COMPILE_FAILURE", [])
    with backend.warm_up(), pytest.warns(RuntimeWarning, match="failed"):
        out = extension(u, surface)
    assert attempts and torch.allclose(out, expected, rtol=0, atol=1e-6)


class _Costly(torch.autograd.Function):
    """``x + 1``, advancing a fake clock by ``forward`` and ``backward`` seconds."""

    @staticmethod
    def forward(ctx, x, clock, forward, backward):
        clock["now"] += forward
        ctx.clock, ctx.backward_seconds = clock, backward
        return x + 1

    @staticmethod
    def backward(ctx, grad):
        ctx.clock["now"] += ctx.backward_seconds
        return grad, None, None, None


def test_auto_weighs_forward_and_backward_when_autograd_records_the_call(monkeypatch):
    """A compiled kernel whose forward is faster but whose backward is slower than eager's,
    summed, is measured slower: ``"auto"`` goes back to eager for good."""
    clock = {"now": 0.0}
    calls: list[str] = []

    def eager(x, *, path):
        calls.append(path)
        return _Costly.apply(x, clock, 1.0, 1.0)

    def fused(x):
        calls.append("fused")
        return _Costly.apply(x, clock, 0.5, 5.0)

    kernel = backend.Kernel("test_backward_slower", eager, fused, lambda x: (x,))
    monkeypatch.setattr(backend, "compiled", lambda f, *options: f)
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 4.0)
    monkeypatch.setattr(backend, "COMPILE_MIN_VOXELS", 1)
    monkeypatch.setattr(backend.time, "perf_counter", lambda: clock["now"])
    volume = torch.zeros(1, 1, 4, 4, 4, requires_grad=True)
    for _ in range(2 + 1 + backend.COMPARED_CALLS):
        backend.run(kernel, "auto", volume, volume).sum().backward()
    # two eager calls of 1 + 1 s pay for compiling; the compiled ones take 0.5 + 5 s
    assert calls == ["slicing"] * 2 + ["fused"] * (1 + backend.COMPARED_CALLS)
    assert backend.resolve("auto", volume, kernel, recording=True) == "slicing"
    torch.testing.assert_close(volume.grad, torch.full_like(volume, 6.0))
    # forward alone the compiled kernel is faster: calls autograd does not record (a variant of
    # their own, paid by four eager seconds) stay compiled
    detached, calls[:] = volume.detach(), []
    for _ in range(4 + 1 + backend.COMPARED_CALLS):
        backend.run(kernel, "auto", detached, detached)
    assert calls == ["slicing"] * 4 + ["fused"] * (1 + backend.COMPARED_CALLS)
    assert backend.resolve("auto", detached, kernel) == "compiled"


def test_explicit_paths_are_taken_as_given_and_unknown_ones_refused():
    volume = torch.zeros(1, 1, 4, 4, 4)
    for path in ("slicing", "conv3d", "compiled"):
        assert backend.resolve(path, volume) == path
    with pytest.raises(ValueError, match="path"):
        backend.resolve("fast", volume)


def _geometry(n: int = 13, dtype=torch.float64):
    grid = ts.Grid((n, n + 1, n + 2), spacing=2.6 / n, origin=(-1.3, -1.3, -1.3))
    points = grid.points(dtype=dtype)
    phi = ((points / torch.tensor([0.9, 1.0, 0.8], dtype=dtype)) ** 2).sum(-1) - 1
    phi = phi * (1.2 + 0.3 * points[..., 0])  # not a distance: W varies
    return grid, ts.ImplicitSurface(phi[None, None], grid)


def test_tensor_level_operators_are_what_the_surface_level_functions_compute():
    grid, surface = _geometry()
    generator = torch.Generator().manual_seed(0)
    u = torch.randn(2, 3, *grid.shape, dtype=torch.float64, generator=generator)
    direction = torch.randn(1, 3, *grid.shape, dtype=torch.float64, generator=generator)
    n, w, h = surface.normal, surface.weight, surface.spacing
    for scheme in functional.SCHEMES:
        torch.testing.assert_close(
            functional.divergence_form(u, n, w, h, scheme),
            ts.laplace_beltrami(u, surface, scheme),
        )
        torch.testing.assert_close(
            functional.divergence_form(u, n, w, h, scheme, weighted=True),
            w * ts.laplace_beltrami(u, surface, scheme),
        )
    torch.testing.assert_close(
        functional.edge_stopping_form(u, n, w, h, ts.operators.perona_malik, 2.0, 1e-2, True),
        ts.anisotropic_diffusion(u, surface, "perona_malik", 2.0, 1e-2, coupled=True),
    )
    tangent = direction - (direction * n).sum(1, keepdim=True) * n  # the surface function's P T
    torch.testing.assert_close(
        functional.directional_form(u, n, w, h, tangent, weighted=True),
        w * ts.directional_diffusion(u, surface, direction),
    )
    gradient = functional.tangential_gradient(u, n, h)
    torch.testing.assert_close(gradient, ts.intrinsic_gradient(u, surface))
    torch.testing.assert_close(
        functional.tangential_gradient_energy(u, n, h),
        (gradient**2).sum(dim=1, keepdim=True),
    )


@pytest.mark.parametrize("operator", ["coupled_total_variation", "directional_weighted"])
def test_compiled_fused_kernels_match_the_eager_reference(operator):
    """The one-pass kernels compiled, against the stencil compositions, forward and backward."""
    grid, surface = _geometry(11, torch.float32)
    generator = torch.Generator().manual_seed(1)
    u0 = torch.randn(2, 3, *grid.shape, generator=generator)
    direction = torch.randn(1, 3, *grid.shape, generator=generator)
    n, w, h = surface.normal, surface.weight, surface.spacing
    results = []
    for path in ("slicing", "compiled"):
        u = u0.clone().requires_grad_(True)
        if operator == "coupled_total_variation":
            value = functional.edge_stopping_form(
                u, n, w, h, ts.operators.total_variation, 1.0, 0.5, True, "symmetric", path
            )
        else:
            value = functional.directional_form(u, n, w, h, direction, path=path, weighted=True)
        value.square().sum().backward()
        results.append((value.detach(), u.grad))
    scale = results[0][0].abs().max()
    torch.testing.assert_close(results[1][0], results[0][0], rtol=1e-4, atol=1e-5 * scale)
    gradient_scale = results[0][1].abs().max()
    torch.testing.assert_close(results[1][1], results[0][1], rtol=1e-4, atol=1e-5 * gradient_scale)


def test_recorded_paths_list_what_auto_picked(monkeypatch):
    kernel = _kernel("test_picks", [])
    volume = torch.zeros(1, 1, 4, 4, 4)
    monkeypatch.setattr(backend, "compiled", lambda f, *options: f)
    with backend.recorded_paths() as picks:
        backend.resolve("auto", volume, kernel)
        backend.resolve("slicing", volume, kernel)  # not a choice of "auto": not listed
        monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 0.0)
        backend.resolve("auto", volume, kernel)
    backend.resolve("auto", volume, kernel)  # outside: not listed
    assert picks == ["slicing", "compiled"]


def test_recorded_calls_switch_by_eager_time_only_on_large_volumes(monkeypatch):
    """A gradcheck or a double backward on a small grid must not find a compiled kernel under
    it mid-run; training at 64^3 is compiled once it pays."""
    kernel = _kernel("test_recording", [])
    volume = torch.zeros(1, 1, 4, 4, 4)
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 0.0)
    assert backend.resolve("auto", volume, kernel, recording=False) == "compiled"
    assert backend.resolve("auto", volume, kernel, recording=True) == "slicing"
    with backend.warm_up():
        assert backend.resolve("auto", volume, kernel, recording=True) == "slicing"
    big = torch.zeros(1, 1, 64, 64, 64)
    assert backend.resolve("auto", big, kernel, recording=True) == "compiled"



@pytest.mark.parametrize("scheme", ["octant", "symmetric"])
def test_a_custom_backward_on_a_small_volume_stays_eager(monkeypatch, scheme):
    """The operator's own adjoint runs where autograd records nothing, and found a compiled
    kernel once enough eager time had passed: a gradcheck on a 10^3 grid then failed as "not
    reentrant" (its two backward passes differed at rounding)."""
    grid = ts.Grid.cube(10, bound=1.0)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=0.7, dtype=torch.float64), grid)
    u = torch.rand(1, 2, *grid.shape, dtype=torch.float64, requires_grad=True)
    loss = ts.laplace_beltrami(u, surface, scheme).square().sum()
    monkeypatch.setattr(backend, "COMPILE", "auto")
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 0.0)
    with backend.recorded_paths() as picks:
        loss.backward()
    assert picks and "compiled" not in picks


def test_compiled_kernels_allow_backward_with_retain_graph():
    """AOTAutograd's donated buffers refuse retain_graph (gradcheck, several losses on one graph)."""
    from torchsurf.flows.extension import _INTERPOLATION

    generator = torch.Generator().manual_seed(0)
    flat = torch.randn(1, 6 * 7 * 8, dtype=torch.float64, generator=generator)
    sizes = torch.tensor([8, 7, 6])[:, None, None]
    corners = (torch.randint(0, 4, (3, 30, 1), generator=generator) + torch.arange(4)) % sizes
    weights = torch.randn(3, 30, 4, dtype=torch.float64, generator=generator, requires_grad=True)
    value = backend.run(_INTERPOLATION, "compiled", flat[None], flat, corners, weights, 7, 8, True)
    loss = value.square().sum()
    loss.backward(retain_graph=True)
    loss.backward()


def _scaled(x: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    return x * weight + 1


def test_one_compiled_variant_serves_every_batch_size_of_two_or_more(monkeypatch):
    """A new batch size (an epoch's last batch) neither recompiles nor waits for its own eager
    time to pay back."""
    kernel = backend.Kernel("test_any_batch", lambda x, weight, *, path: _scaled(x, weight),
                            _scaled, lambda x, weight: (x, weight))
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 0.0)
    weight = torch.rand(1, 1, 5, 5, 5)
    counters = torch._dynamo.utils.counters["stats"]
    results = {}
    for batch in (2, 3, 5):
        x = torch.rand(batch, 1, 5, 5, 5)
        if batch == 3:
            compiled_before = counters["unique_graphs"]
        results[batch] = (backend.run(kernel, "auto", x, x, weight), _scaled(x, weight))
    assert counters["unique_graphs"] == compiled_before
    for actual, expected in results.values():
        torch.testing.assert_close(actual, expected)
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", math.inf)
    for batch, expected in ((4, "compiled"), (1, "slicing")):
        x = torch.rand(batch, 1, 5, 5, 5)
        assert backend.resolve("auto", x, kernel, args=(x, weight)) == expected


def test_numbers_compile_no_graph_of_their_own():
    """A grid's spacing and a contrast reached the compiled kernels as floats, on whose values
    dynamo guards: each mesh of its own spacing, each contrast, compiled its own graph (about
    10 s each), and past 64 the kernels silently ran eager. They now share one; the results
    equal the eager path's."""
    counters = torch._dynamo.utils.counters["stats"]
    u = torch.rand(1, 1, 12, 12, 12, generator=torch.Generator().manual_seed(0))
    for first, *others in ([1.5, 1.6, 1.7], [0.5, 0.6]):
        for value in (first, *others):
            if value == others[0]:
                before = counters["unique_graphs"]
            if first == 1.5:
                grid = ts.Grid.cube(12, bound=value)
                surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.7), grid)
                results = [ts.laplace_beltrami(u, surface, path=path)
                           for path in ("compiled", "slicing")]
            else:
                results = [ts.anisotropic_diffusion(u, surface, "perona_malik", contrast=value,
                                                    path=path) for path in ("compiled", "slicing")]
            torch.testing.assert_close(*results)
        assert counters["unique_graphs"] == before, (first, others)


def test_only_kernels_that_build_their_indices_skip_inductors_bounds_checks(monkeypatch):
    from torchsurf.flows import extension
    from torchsurf.operators import functional

    seen = []
    monkeypatch.setattr(torch, "compile", lambda f, **kwargs: seen.append(kwargs) or f)
    backend.compiled.cache_clear()
    try:
        for kernel in (extension._ANCHORED_INTERPOLATION, functional._OCTANT):
            backend.compiled(kernel.fused, kernel.dynamic, kernel.trusted_indices)
    finally:
        backend.compiled.cache_clear()
    assert seen[0]["options"]["assert_indirect_indexing"] is False
    assert "assert_indirect_indexing" not in seen[1]["options"]
    # the numbers' 0-d tensor reads had made inductor write total variation's projected
    # gradients to memory (1.7x its time at 128^3); every kernel compiles with the raised bound
    assert all(kwargs["options"]["realize_reads_threshold"] == backend.REALIZE_READS_THRESHOLD
               for kwargs in seen)
    # the projecting directional kernel recomputes its face fluxes (with 7 inductor stored
    # them: the operator 1.3x slower at 96^3)
    kernel = functional._DIRECTIONAL_TANGENT
    try:
        backend.compiled(kernel.fused, kernel.dynamic, kernel.trusted_indices,
                         kernel.realize_reads_threshold)
    finally:
        backend.compiled.cache_clear()
    assert seen[-1]["options"]["realize_reads_threshold"] == functional.TANGENT_REALIZE_READS > 7


def test_a_users_diffusivity_is_one_variant_and_is_not_kept_alive(monkeypatch):
    """Each call wrapped the user's g anew, and the wrapper counted by identity: every call a
    variant of its own (never compiled, one ledger entry a call), each holding g."""
    import gc
    import weakref

    monkeypatch.setattr(backend, "COMPILE", "never")
    grid = ts.Grid.cube(11, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))

    class Lorentzian(torch.nn.Module):
        def forward(self, magnitude, contrast):
            return 1.0 / (1.0 + (magnitude / contrast) ** 2)

    g = Lorentzian()
    before = len(backend._TIMINGS)
    results = [ts.anisotropic_diffusion(u, surface, g, 0.7, path="auto") for _ in range(5)]
    assert len(backend._TIMINGS) == before + 1
    assert torch.equal(results[0], ts.anisotropic_diffusion(u, surface, "perona_malik", 0.7,
                                                            path="auto"))
    alive = weakref.ref(g)
    del g
    gc.collect()
    assert alive() is None


def test_exponents_reach_compiled_kernels_as_numbers(monkeypatch):
    """The p-harmonic map's exponents had reached inductor as 0-d tensors with the other
    numbers: a general power instead of a reciprocal or 1, its rate 1.8x slower at 96^3. The
    spacing stays a tensor (one graph for every grid)."""
    from torchsurf.flows.harmonic import power_diffusivity
    from torchsurf.operators import functional

    seen = []
    monkeypatch.setattr(backend, "compiled",
                        lambda fused, *flags: lambda *args: seen.append(args) or fused(*args))
    grid = ts.Grid.cube(12, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.randn(1, 3, *grid.shape, generator=torch.Generator().manual_seed(0))
    for exponent, expected in ((-1.0, (9, 6)), (None, (9,))):
        diffusivity = power_diffusivity if exponent is not None else ts.operators.diffusivity.perona_malik
        contrast = exponent if exponent is not None else 0.5
        compiled = functional.harmonic_map_rate(u, surface.normal, surface.weight, surface.spacing,
                                                diffusivity, contrast, 0.01, 0.5, path="compiled")
        eager = functional.harmonic_map_rate(u, surface.normal, surface.weight, surface.spacing,
                                             diffusivity, contrast, 0.01, 0.5, path="slicing")
        torch.testing.assert_close(compiled, eager)
        args = seen[-1]
        assert functional._coupled_exponents(args) == expected
        # the variant key of path="auto" (un-haloed arguments) keeps the exponents' values too
        raw = (u, surface.normal, surface.weight, surface.spacing, diffusivity, contrast, 0.01,
               0.5, "symmetric", None, None)
        assert [raw[i] for i in functional._coupled_exponents(raw)] == [args[i] for i in expected]
        assert all(type(args[i]) is float for i in expected)
        numbers = [i for i in (4, 6, 7) if i not in expected]
        assert all(isinstance(args[i], torch.Tensor) and args[i].dim() == 0 for i in numbers)


def test_channels_last_data_compiles_no_graph_of_its_own():
    """dynamo guards on the memory format: channels-last data compiled its own kernel (9-22 s
    on a first call), where permuted or stepped layouts reused the graph."""
    counters = torch._dynamo.utils.counters["stats"]
    grid = ts.Grid.cube(12, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.7), grid)
    u = torch.rand(1, 2, *grid.shape, generator=torch.Generator().manual_seed(1))
    expected = ts.laplace_beltrami(u, surface, path="compiled")
    before = counters["unique_graphs"]
    last = u.contiguous(memory_format=torch.channels_last_3d)
    torch.testing.assert_close(ts.laplace_beltrami(last, surface, path="compiled"), expected)
    assert counters["unique_graphs"] == before


_FORKED_KERNEL = None


def _compiled_in_a_child(width: int) -> float:
    return float(_FORKED_KERNEL(torch.ones(3, width)).sum())


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_compiles_a_new_shape_instead_of_waiting_forever():
    """A child forked after the parent compiled waited forever on its first compile of a new
    shape (inductor's compile workers do not survive a fork; "auto" compiles by itself, so a
    user of a fork pool never chose to compile): forked children now compile in-process."""
    import multiprocessing

    # a kernel no earlier run compiled (a new constant: no cached graph nor library), so that
    # the parent and the child compile
    scale = 1.0 + random.random()
    global _FORKED_KERNEL
    _FORKED_KERNEL = torch.compile(lambda x: (x.sin() * scale + x.cos()).sum(-1))
    _FORKED_KERNEL(torch.ones(3, 5))
    from torch._inductor import async_compile
    AsyncCompile = async_compile.AsyncCompile
    if (not hasattr(AsyncCompile, "use_process_pool")
            or getattr(async_compile, "get_compile_threads", lambda: 2)() <= 1):
        pytest.skip("inductor has no pool of compile workers to wait on here")
    ready = time.monotonic() + 60  # the parent's workers up, as in a long run
    while not AsyncCompile.use_process_pool():
        if time.monotonic() > ready:
            pytest.skip("inductor started no compile workers here")
        time.sleep(0.2)
    with multiprocessing.get_context("fork").Pool(1) as pool:
        value = pool.apply_async(_compiled_in_a_child, (7,)).get(timeout=60)
    assert value == pytest.approx(3 * 7 * (scale * math.sin(1.0) + math.cos(1.0)), rel=1e-5)


def test_the_ledger_of_variants_keeps_the_newest(monkeypatch):
    """A diffusivity made anew for each call is a variant of its own: the ledger keeps the
    ``TIMED_VARIANTS`` run most recently (it grew by one a call, each call slower than the
    last), and a kernel run at every call stays with its measured time."""
    monkeypatch.setattr(backend, "COMPILE", "never")
    monkeypatch.setattr(backend, "TIMED_VARIANTS", 8)
    monkeypatch.setattr(backend, "_TIMINGS", {})
    grid = ts.Grid.cube(9, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    gs = [lambda magnitude, contrast, k=k: 1.0 / (1.0 + k + magnitude) for k in range(20)]
    for g in gs:
        ts.laplace_beltrami(u, surface, path="auto")  # a kernel run at every call
        ts.anisotropic_diffusion(u, surface, g, 0.7, path="auto")
    assert len(backend._TIMINGS) == 8
    hot = [variant for variant in backend._TIMINGS if variant[0].startswith("laplace")]
    assert len(hot) == 1 and backend._TIMINGS[hot[0]].eager_seconds > 0  # kept, not dropped
    newest = list(backend._TIMINGS)[-1]
    ts.anisotropic_diffusion(u, surface, gs[-1], 0.7, path="auto")  # known: nothing dropped
    assert list(backend._TIMINGS)[-1] == newest and len(backend._TIMINGS) == 8


def test_data_with_forward_tangents_stay_eager_on_auto(monkeypatch):
    """A compiled kernel drops forward-mode tangents: ``"auto"`` keeps such data eager, even
    where it would compile at once (the flows' tangents were 0.1-1.0 off)."""
    import torch.autograd.forward_ad as forward_ad

    monkeypatch.setattr(backend, "COMPILE", "always")
    grid = ts.Grid.cube(12, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    generator = torch.Generator().manual_seed(0)
    u = torch.rand((1, 1, *grid.shape), dtype=torch.float64, generator=generator)
    direction = torch.rand(u.shape, dtype=torch.float64, generator=generator)
    with backend.recorded_paths() as picks:
        with forward_ad.dual_level():
            out = ts.laplace_beltrami(forward_ad.make_dual(u, direction), surface, path="auto")
            tangent = forward_ad.unpack_dual(out).tangent
    assert picks and "compiled" not in picks
    expected = ts.laplace_beltrami(direction, surface, path="slicing")  # the operator is linear
    torch.testing.assert_close(tangent, expected, rtol=1e-12, atol=1e-12)
