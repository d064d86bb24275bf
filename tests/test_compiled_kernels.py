"""The compiled path, asked for by name: what ``"auto"`` compiles is bounded (one graph per
variant, each paying back its own compile), the ``TORCHSURF_COMPILE`` setting, a flow's
``path`` reaching every kernel it runs, and every operator's compiled kernel against eager.

The rest of the suite runs with ``TORCHSURF_COMPILE=never`` (tests/conftest.py): the tests here
set the mode they are about.
"""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf import backend
from torchsurf.flows import HeatFlow


def _graphs() -> int:
    """Graphs dynamo has compiled in this process."""
    return torch._dynamo.utils.counters["stats"]["unique_graphs"]


def _scaled_sum(x: torch.Tensor, weight: torch.Tensor, scale: float, clamp: bool
                ) -> torch.Tensor:
    value = x * weight * scale
    return value.clamp(min=0.0) if clamp else value


def _flag_kernel(name: str, calls: list[str]) -> backend.Kernel:
    def eager(x, weight, scale, clamp, *, path):  # noqa: ANN001, ANN202
        calls.append(path)
        return _scaled_sum(x, weight, scale, clamp)

    def fused(x, weight, scale, clamp):  # noqa: ANN001, ANN202
        calls.append("fused")
        return _scaled_sum(x, weight, scale, clamp)

    return backend.Kernel(name, eager, fused, lambda *args: args)


def test_each_variant_pays_back_its_own_compile(monkeypatch):
    """Eager time spent with one flag value, one grad mode, does not pay for compiling
    another: each compiles once its own eager time reaches the payback."""
    monkeypatch.setattr(backend, "COMPILE", "auto")
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 3.0)
    monkeypatch.setattr(backend, "compiled", lambda f, *options: f)
    clock = iter(float(t) for t in range(1000))
    monkeypatch.setattr(backend.time, "perf_counter", lambda: next(clock))  # 1 s a call
    calls: list[str] = []
    kernel = _flag_kernel("test_variant_payback", calls)
    x, weight = torch.rand(1, 1, 4, 4, 4), torch.rand(1, 1, 4, 4, 4)
    for _ in range(3):
        backend.run(kernel, "auto", x, x, weight, 2.0, False)
    backend.run(kernel, "auto", x, x, weight, 2.0, False)
    assert calls[-1] == "fused"
    backend.run(kernel, "auto", x, x, weight, 2.0, True)  # the other flag: still eager
    assert calls[-1] == "slicing"
    assert backend.resolve("auto", x, kernel, args=(x, weight, 2.0, True)) == "slicing"
    # the same graph whatever the grad mode and requires_grad of an unrecorded call
    with torch.no_grad():
        leaf = x.clone().requires_grad_(True)
        assert backend.resolve("auto", leaf, kernel, args=(leaf, weight, 2.0, False)) == "compiled"
    # a recorded call is another graph (it compiles a backward): its own payback
    big = torch.rand(1, 1, 64, 64, 64, requires_grad=True)
    big_weight = torch.rand(1, 1, 64, 64, 64)
    assert backend.resolve("auto", big, kernel, recording=True,
                           args=(big, big_weight, 2.0, False)) == "slicing"


def test_unrecorded_calls_run_one_compiled_graph(monkeypatch):
    """Grad enabled or not, inputs requiring grad or not: a call autograd does not record runs
    one inference graph (dynamo would compile one per grad mode and requires_grad)."""
    monkeypatch.setattr(backend, "COMPILE", "always")
    kernel = backend.Kernel("test_one_inference_graph",
                            lambda x, w, s, c, *, path: _scaled_sum(x, w, s, c), _scaled_sum,
                            lambda *args: args)
    x, weight = torch.rand(2, 1, 5, 5, 5), torch.rand(1, 1, 5, 5, 5)
    expected = _scaled_sum(x, weight, 0.5, True)
    backend.run(kernel, "auto", x, x, weight, 0.5, True)
    before = _graphs()
    with torch.no_grad():
        leaf = x.clone().requires_grad_(True)
        torch.testing.assert_close(backend.run(kernel, "auto", leaf, leaf, weight, 0.5, True),
                                   expected)
        other_batch = torch.rand(3, 1, 5, 5, 5)
        backend.run(kernel, "auto", other_batch, other_batch, weight, 0.5, True)
    torch.testing.assert_close(backend.run(kernel, "auto", x, x, weight, 0.5, True), expected)
    assert _graphs() == before


def test_compile_setting_never_stays_eager_and_always_compiles_at_once(monkeypatch):
    calls: list[str] = []
    kernel = _flag_kernel("test_setting", calls)
    huge = torch.zeros(1, 1, 1, 1, 1).expand(1, 1, 256, 256, 256)  # 2^24 voxels, no memory
    small = torch.zeros(1, 1, 4, 4, 4)
    monkeypatch.setattr(backend, "COMPILE", "never")
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", 0.0)
    assert backend.resolve("auto", huge, kernel) == "slicing"
    assert backend.resolve("auto", small, kernel) == "slicing"
    assert backend.resolve("compiled", small, kernel) == "compiled"
    with backend.warm_up():  # asked for in the code: compiles
        assert backend.resolve("auto", small, kernel) == "compiled"
    monkeypatch.setattr(backend, "COMPILE", "always")
    monkeypatch.setattr(backend, "COMPILE_PAYBACK_SECONDS", float("inf"))
    assert backend.resolve("auto", small, kernel) == "compiled"
    # a recorded call on a small volume stays eager (double backward, gradcheck)
    assert backend.resolve("auto", small, kernel, recording=True) == "slicing"


@pytest.mark.parametrize("value, expected", [(None, "auto"), ("never", "never"),
                                             (" Always ", "always"), ("", "auto")])
def test_compile_setting_is_read_from_the_environment(monkeypatch, value, expected):
    if value is None:
        monkeypatch.delenv("TORCHSURF_COMPILE", raising=False)
    else:
        monkeypatch.setenv("TORCHSURF_COMPILE", value)
    assert backend._compile_mode_from_environment() == expected


def test_compile_setting_refuses_unknown_values(monkeypatch):
    monkeypatch.setenv("TORCHSURF_COMPILE", "sometimes")
    with pytest.raises(ValueError, match="TORCHSURF_COMPILE must be one of"):
        backend._compile_mode_from_environment()


@pytest.fixture(scope="module")
def sphere13():
    grid = ts.Grid.cube(13, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(2, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    return u, surface


def test_an_eager_flow_path_compiles_nothing_even_its_reextension(monkeypatch, sphere13):
    """``path="slicing"`` reaches the closest-point gather too (it ran ``"auto"`` whatever the
    flow was given)."""
    monkeypatch.setattr(backend, "COMPILE", "always")
    u, surface = sphere13
    before = _graphs()
    HeatFlow(4 * surface.spacing**2, path="slicing")(u, surface)
    assert _graphs() == before


def test_an_eager_layer_compiles_nothing_even_its_ring_fill(monkeypatch, sphere13):
    """A learned diffusion given ``path="slicing"`` assembled its ring's re-extension (once per
    surface) with ``"auto"``, which compiles the tricubic gather under ``always``."""
    monkeypatch.setattr(backend, "COMPILE", "always")
    u, surface = sphere13
    fresh = ts.ImplicitSurface(surface.phi.clone(), surface.grid)  # nothing kept on it yet
    before = _graphs()
    ts.nn.LearnedDiffusion(1, time=[0.5], path="slicing")(u, fresh)
    assert _graphs() == before


def test_an_assigned_compile_setting_is_checked(monkeypatch, sphere13):
    """A mistyped ``backend.COMPILE = "Never"`` ran as ``"auto"`` without a word."""
    monkeypatch.setattr(backend, "COMPILE", "Never")
    u, surface = sphere13
    with pytest.raises(ValueError, match=r"torchsurf.backend.COMPILE must be one of .* 'Never'"):
        ts.laplace_beltrami(u, surface)


def test_a_compiled_flow_compiles_once_for_every_unrecorded_call(monkeypatch, sphere13):
    """A heat flow with re-extension compiled from its first call (``always``): its kernels
    (the octant Laplace–Beltrami, the limited tricubic gather) compile on the first call and
    serve no-grad calls, grad-enabled ones, data requiring grad and other batch sizes of two
    or more without another compile, with eager's numbers."""
    u, surface = sphere13
    flow = HeatFlow(4 * surface.spacing**2)
    with torch.no_grad():
        expected = HeatFlow(4 * surface.spacing**2, path="slicing")(u, surface)
    monkeypatch.setattr(backend, "COMPILE", "always")
    first = flow(u, surface)
    compiled_after_first = _graphs()
    with torch.no_grad():
        again = flow(u.clone().requires_grad_(True), surface)
        flow(torch.cat([u, u[:1]]), surface)
    flow(u, surface)
    assert _graphs() == compiled_after_first
    for result in (first, again):
        torch.testing.assert_close(result, expected, rtol=1e-5, atol=1e-5)


def _operators(n: int = 9):
    """``name -> call(path)`` of every operator with a compiled kernel, on a 9^3 sphere."""
    grid = ts.Grid.cube(n, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    generator = torch.Generator().manual_seed(2)
    u = torch.rand(2, 1, n, n, n, generator=generator)
    three = torch.nn.functional.normalize(torch.randn(2, 3, n, n, n, generator=generator), dim=1)
    direction = torch.randn(1, 3, n, n, n, generator=generator)
    calls = {f"laplace_beltrami_{scheme}": (lambda path, s=scheme: ts.laplace_beltrami(
        u, surface, s, path)) for scheme in ("octant", "symmetric", "conservative", "central")}
    calls.update({
        "anisotropic_tv": lambda path: ts.anisotropic_diffusion(u, surface, eps=1e-2, path=path),
        "anisotropic_coupled": lambda path: ts.anisotropic_diffusion(
            three, surface, eps=1e-2, coupled=True, path=path),
        "directional": lambda path: ts.directional_diffusion(u, surface, direction, path=path),
        "gradient": lambda path: ts.intrinsic_gradient(u, surface, path),
        "divergence": lambda path: ts.intrinsic_divergence(three, surface, path),
        "heat_flow_reextended": lambda path: HeatFlow(surface.spacing**2, path=path)(u, surface),
    })
    return calls


@pytest.mark.slow
@pytest.mark.parametrize("name", list(_operators()))
def test_every_operator_compiled_equals_eager(name):
    """Each operator's compiled kernel (one compile each: slow on an empty inductor cache)."""
    call = _operators()[name]
    with torch.no_grad():
        expected, actual = call("slicing"), call("compiled")
    scale = float(expected.abs().max())
    torch.testing.assert_close(actual, expected, rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.slow
def test_coupled_rate_compiled_serves_every_batch_size_and_brick_count():
    """The harmonic-map rate's compiled face arrangement: one graph for batches of 2 and 3 and
    one for layouts of different brick counts (a per-entry unrolling would specialise each),
    equal to eager."""
    from torchsurf import bricks
    from torchsurf.flows.harmonic import power_diffusivity
    from torchsurf.operators import functional

    def rate(u, surface, pad=None, path="compiled"):
        return functional.harmonic_map_rate(
            u, surface.normal, surface.weight, surface.spacing, power_diffusivity, -1.0, 0.1,
            0.5, "symmetric", path, None, surface.haloed(), pad)

    grid = ts.Grid.cube(21, 2.1)
    generator = torch.Generator().manual_seed(4)
    with torch.no_grad():
        for surfaces in ([ts.ImplicitSurface(ts.sdf.sphere(grid, 0.8), grid)] * 2,
                         [bricks.from_dense(ts.ImplicitSurface(ts.sdf.sphere(grid, r), grid))
                          for r in (0.8, 0.6)]):
            graphs = None
            for batch, surface in zip((2, 3), surfaces, strict=True):
                u = torch.nn.functional.normalize(
                    torch.randn(batch, 3, 21, 21, 21, generator=generator), dim=1)
                pad = None
                if surface.layout is not None:
                    u, pad = surface.from_dense(u[:1]), surface.layout.halo
                compiled = rate(u, surface, pad)
                torch.testing.assert_close(compiled, rate(u, surface, pad, "slicing"),
                                           rtol=1e-4, atol=1e-4)
                graphs = _graphs() if graphs is None else graphs
            assert _graphs() == graphs
