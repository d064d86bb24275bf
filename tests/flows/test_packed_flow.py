"""HeatFlow's explicit integrators on packed band and ring values: the volume path's results and
gradients to rounding, on every storage and option that reaches them, and no volume stencil in
the steps."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf import bricks
from torchsurf.flows import HeatFlow, base, heat
from torchsurf.flows.exponential import BandLaplacian
from torchsurf.operators import functional

from .test_packed_band import _fields, _surface


def _both(make_flow, u: torch.Tensor, surface: ts.ImplicitSurface, monkeypatch,
          **call: object) -> tuple[torch.Tensor, torch.Tensor]:
    """The flow's result packed, then on volumes (``packed_system`` declined)."""
    packed = make_flow()(u, surface, **call)
    with monkeypatch.context() as patch:
        patch.setattr(HeatFlow, "packed_system", lambda self, *args: None)
        volume = make_flow()(u, surface, **call)
    return packed, volume


@pytest.mark.parametrize("kind", ["two shapes", "bunny", "tanh", "bricks"])
@pytest.mark.parametrize("options", [
    {}, {"reextend_every": 1}, {"method": "euler", "cells": 0.5}, {"diffusivity": [1.0, 2.5]},
    {"cells": 60.0}, {"scheme": "symmetric"},
])
def test_packed_flow_is_the_volume_flow(kind, options, monkeypatch):
    """RKC (the ring held or re-extended at every stage, as the plan decides), Euler,
    per-channel diffusivity, long times (many re-extensions), a flux-form scheme."""
    surface = _surface(kind)
    options = dict(options)
    time = options.pop("cells", 8.0) * surface.spacing**2
    u = _fields(surface, 1, seed=6)[0]
    u = u - u.min()
    packed, volume = _both(lambda: HeatFlow(time, **options), u, surface, monkeypatch)
    scale = float(volume.abs().max())
    assert float((packed - volume).abs().max()) < 1e-12 * scale


def test_packed_flow_returns_requested_times(monkeypatch):
    surface = _surface("two shapes")
    u = _fields(surface, 1, seed=7)[0]
    end = 12.0 * surface.spacing**2
    packed, volume = _both(lambda: HeatFlow(end), u, surface, monkeypatch,
                           times=[0.0, end / 3, end])
    assert packed.shape == (3, *u.shape)
    torch.testing.assert_close(packed, volume, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("kind", ["bunny", "bricks"])
@pytest.mark.parametrize("learned", ["time", "diffusivity"])
def test_packed_flow_gradients_are_the_volume_flows(kind, learned, monkeypatch):
    """Gradients of the data and of a learned time or diffusivity (checkpointed steps)."""
    surface = _surface(kind)
    u = _fields(surface, 1, seed=8)[0].abs()
    grad = _fields(surface, 1, seed=9)[0]
    time = 6.0 * surface.spacing**2

    def make() -> HeatFlow:
        if learned == "time":
            return HeatFlow(time, learn_time=True).double()
        return HeatFlow(time, diffusivity=[1.0, 2.0], learn_diffusivity=True).double()

    results = []
    for patched in (False, True):
        with monkeypatch.context() as patch:
            if patched:
                patch.setattr(HeatFlow, "packed_system", lambda self, *args: None)
            flow = make()
            data = u.clone().requires_grad_()
            out = flow(data, surface)
            parameters = [p for p in flow.parameters() if p.requires_grad]
            results.append((out.detach(), *torch.autograd.grad((out * grad).sum(),
                                                               [data, *parameters])))
    for packed, volume in zip(*results, strict=True):
        torch.testing.assert_close(packed, volume, rtol=1e-10, atol=1e-10)


def test_packed_flow_runs_no_volume_stencil_in_its_steps(monkeypatch):
    """Once the packing is kept on the surface, the steps gather the band's matrices: no
    Laplace–Beltrami stencil over the volume."""
    grid = ts.Grid.cube(21, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(2, 1, *grid.shape, generator=torch.Generator().manual_seed(0))
    flow = HeatFlow(10 * surface.spacing**2)
    flow(u, surface)
    calls = []
    original = functional.divergence_form
    monkeypatch.setattr(functional, "divergence_form",
                        lambda *args, **kwargs: calls.append(1) or original(*args, **kwargs))
    result = flow(u, surface)
    assert calls == []
    band = flow.band_mask(surface)
    inside = result[band.expand_as(result)]
    assert float(inside.min()) >= float(u.min()) and float(inside.max()) <= float(u.max())


def test_a_learned_phi_integrates_volumes():
    """``phi`` requiring grad: the geometry is in its graph, the flow runs on volumes, and
    gradients reach ``phi``."""
    grid = ts.Grid.cube(13, 1.5)
    phi = ts.sdf.sphere(grid, dtype=torch.float64).requires_grad_()
    surface = ts.ImplicitSurface(phi, grid)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(1))
    flow = HeatFlow(4 * surface.spacing**2)
    assert flow.packed_system(flow.system(u, surface), u, surface) is None
    flow(u, surface).sum().backward()
    assert phi.grad is not None and float(phi.grad.abs().sum()) > 0


def test_a_subclass_with_its_own_equation_integrates_it():
    """A subclass that overrides ``system`` keeps its own rate (the packed rate is HeatFlow's)."""
    from torchsurf.flows._integrators import System

    class Decay(HeatFlow):
        def system(self, u0, surface, **inputs):
            band = self.band_mask(surface)
            return System(lambda u: torch.where(band, -u, 0.0), band, 1.0)

    grid = ts.Grid.cube(13, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(2))
    result = Decay(1.0, method="euler", steps=100)(u, surface)
    band = Decay(1.0).band_mask(surface).expand_as(result)
    # decayed by 0.99^100 = 0.366 from data in [0, 1]; heat would keep values near the mean
    assert 0.0 <= float(result[band].min()) and float(result[band].max()) <= 0.99**100 + 1e-12


def test_volume_stencils_where_asked_for_and_on_large_bricks(monkeypatch):
    """``path="compiled"`` keeps the volume stencils (faster for one channel on small grids),
    and so do brick surfaces whose band and ring exceed ``PACKED_BRICK_NODES`` (the C kernel,
    and the bricks' memory bound)."""
    grid = ts.Grid.cube(13, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(3))
    for path, packs in (("auto", True), ("slicing", True), ("compiled", False)):
        flow = HeatFlow(4 * surface.spacing**2, path=path)
        assert (flow.packed_system(flow.system(u, surface), u, surface) is not None) == packs
    bricks = _surface("bricks")
    v = _fields(bricks, 1, seed=4)[0]
    flow = HeatFlow(4 * bricks.spacing**2)
    system = flow.system(v, bricks)
    assert flow.packed_system(system, v, bricks) is not None
    monkeypatch.setattr(heat, "PACKED_BRICK_NODES", int(system.region.sum()) - 1)
    assert flow.packed_system(flow.system(v, bricks), v, bricks) is None


def test_the_flow_and_the_semigroup_share_one_packing():
    """The band's packing and ``W^-1 A`` are assembled once per surface and band width, for the
    heat flow and the heat semigroup alike."""
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(5))
    flow = HeatFlow(4 * surface.spacing**2)
    flow(u, surface)
    width = flow.evolving_width(surface)
    packing = surface.kept(("packed region", "octant", width), lambda: None)
    assert packing is not None
    assert BandLaplacian(surface, band_width=width).packed().packing is packing


def test_large_brick_bands_flow_by_the_re_extension_kernel_as_packed_ones(monkeypatch):
    """Bricks whose band and ring exceed ``PACKED_BRICK_NODES`` (a 256^3 bunny's) flow on
    volumes, re-extending by the C kernel of ``BrickCubicStencil`` (the 512^3 bunny's flow:
    259 -> 58 s): the same flow as the packed one to rounding, inside the start's range on
    both entries of a batch, the caller's data untouched."""
    from torchsurf.flows import _native_gather

    if _native_gather.LIBRARY.load() is None:
        pytest.skip("no C compiler")
    bricks = _surface("bricks")
    v = _fields(bricks, 1, seed=6)[0]
    before = v.clone()
    packed = HeatFlow(6 * bricks.spacing**2)(v, bricks)
    ran = []
    kernel = _native_gather.brick_tricubic
    monkeypatch.setattr(_native_gather, "brick_tricubic",
                        lambda *args: ran.append(1) or kernel(*args))
    monkeypatch.setattr(heat, "PACKED_BRICK_NODES", 0)
    volume = HeatFlow(6 * bricks.spacing**2)(v, bricks)
    assert ran  # the kernel re-extended the band and its ring
    band = bricks.band_mask().expand_as(v)
    torch.testing.assert_close(volume[band], packed[band], rtol=0, atol=1e-12)
    for entry in range(bricks.batch_size):
        rows = (bricks.layout.batch == entry)
        start, end = v[rows][band[rows]], volume[rows][band[rows]]
        assert float(start.min()) - 1e-12 <= float(end.min())
        assert float(end.max()) <= float(start.max()) + 1e-12
        assert float(end.std()) < 0.5 * float(start.std())
    torch.testing.assert_close(v, before, rtol=0, atol=0)


def _radial_square_surface() -> ts.ImplicitSurface:
    """``phi = r^2 - R^2`` (not a distance): the 3-cell band, whose ring RKC re-extends at every
    stage."""
    grid = ts.Grid.cube(25, 1.4)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    return ts.ImplicitSurface((x * x + y * y + z * z - 0.7**2)[None, None], grid)


def _counting_fused_stages(monkeypatch) -> list[str]:
    """Record each whole step and each stage the native RKC stages run."""
    from torchsurf.flows import _packed_band

    calls = []
    step, stage = _packed_band.FusedStage.step, _packed_band.FusedStage.__call__
    monkeypatch.setattr(_packed_band.FusedStage, "step",
                        lambda self, *args: calls.append("step") or step(self, *args))
    monkeypatch.setattr(_packed_band.FusedStage, "__call__",
                        lambda self, *args: calls.append("stage") or stage(self, *args))
    return calls


def _flow_packing(surface: ts.ImplicitSurface):
    """The packed region a flow kept on ``surface``, or on its first entry's surface (a flow
    integrates the entries of a batch of several surfaces apart)."""
    for kept in (surface._kept, *(value._kept for key, value in surface._kept.items()
                                  if key[0] == "entry surface")):
        for key, value in kept.items():
            if key[0] == "packed region":
                return value
    raise AssertionError("no packed region kept")


def _held_surface(kind: str) -> ts.ImplicitSurface:
    """Distances on the default 5-cell band, whose ring a heat flow's RKC steps hold."""
    if kind == "sphere":
        grid = ts.Grid.cube(31, 1.5)
        return ts.ImplicitSurface(ts.sdf.sphere(grid, 0.8, dtype=torch.float64), grid)
    return _surface(kind)


@pytest.mark.parametrize("kind", ["sphere", "at the faces", "two shapes", "bricks", "r^2 - R^2"])
@pytest.mark.parametrize("options", [
    {}, {"diffusivity": 2.5}, {"cells": 60.0}, {"scheme": "symmetric"},
    {"learn_time": True, "max_time": 16.0},
])
def test_one_columns_native_stages_are_the_volume_flow(kind, options, monkeypatch):
    """One signal of one channel, no gradient: RKC's stages run natively (the operator's rows
    and the stage's combination in one pass) and give the volume path's numbers; where a step
    holds the ring, a whole step is one call; where it does not (a 3-cell band: bricks, ``phi``
    not a distance, the two shapes' small box), the ring is re-extended before each stage; a
    diffusivity scales them. A learned time (scaled into the rate) keeps the stages that apply
    the flow's own rate."""
    surface = _radial_square_surface() if kind == "r^2 - R^2" else _held_surface(kind)
    options = dict(options)
    cells = options.pop("cells", 8.0)
    if "max_time" in options:
        options["max_time"] *= surface.spacing**2
    u = _fields(surface, 1, seed=6)[0][:, :1]
    if surface.layout is None:
        u = u[:surface.batch_size]
    u = u - u.min()
    calls = _counting_fused_stages(monkeypatch)
    held = []
    ring_held = base.ring_held
    monkeypatch.setattr(base, "ring_held", lambda *args, **kwargs: held.append(
        ring_held(*args, **kwargs)) or held[-1])
    with torch.no_grad():
        packed, volume = _both(lambda: HeatFlow(cells * surface.spacing**2, **options).double(),
                               u, surface, monkeypatch)
    scale = float(volume.abs().max())
    assert float((packed - volume).abs().max()) < 1e-12 * scale
    assert held[0] == (kind in ("sphere", "at the faces"))
    if "learn_time" in options:
        assert calls == []
    elif held[0]:
        assert calls and set(calls) == {"step"}  # one thread or few rows: whole steps
    else:
        assert "stage" in calls  # the ring re-extended before each stage


def test_native_stages_split_between_threads_give_one_calls_numbers(monkeypatch):
    """Rows split between threads run the stages one by one, each split: the same numbers as a
    whole step in one call, bit for bit; and those of the eager stages to rounding."""
    from torchsurf.flows import _native_gather

    if _native_gather.LIBRARY.load() is None:
        pytest.skip("no C compiler")
    surface = _held_surface("sphere")
    u = _fields(surface, 1, seed=3)[0][:1, :1]
    flow = HeatFlow(12 * surface.spacing**2).double()
    calls = _counting_fused_stages(monkeypatch)
    with torch.no_grad():
        whole = flow(u, surface)
        assert calls and set(calls) == {"step"}
        calls.clear()
        threads = torch.get_num_threads()
        monkeypatch.setattr(_native_gather, "THREAD_MIN_ROWS", 64)
        try:
            torch.set_num_threads(2)
            split = flow(u, surface)
        finally:
            torch.set_num_threads(threads)
        assert "stage" in calls  # the whole step declined
        monkeypatch.setattr(HeatFlow, "packed_system", lambda self, *args: None)
        volume = flow(u, surface)
    assert torch.equal(split, whole)
    torch.testing.assert_close(whole, volume, rtol=1e-12, atol=1e-12)


def test_one_pass_re_extension_is_the_product_and_clamp(monkeypatch):
    """The packed stencils' one-pass kernel (separable weights formed in the kernel, the
    limiter's test on the taps just read) against the product and the clamp in two passes:
    rough data (many values clamped), one and three columns, both dtypes, the band's stencil
    (every node a target) and the ring's (a few)."""
    from torchsurf.flows import _native_gather

    if _native_gather.LIBRARY.load() is None:
        pytest.skip("no C compiler")
    surface = _surface("two shapes")
    flow = HeatFlow(6 * surface.spacing**2, reextend_every=1).double()
    u = _fields(surface, 1, seed=4)[0][:, :1]
    flow(u, surface)
    packing = _flow_packing(surface)
    stencils = [stencil for _, stencil in packing._stencils.values()]
    assert {len(s.rows) == len(packing.nodes) for s in stencils} == {True, False}
    generator = torch.Generator().manual_seed(5)
    for dtype in (torch.float64, torch.float32):
        for columns in (1, 3):
            z = torch.rand(len(packing.nodes), columns, 1, generator=generator).to(dtype)
            for stencil in stencils:
                one_pass = _native_gather._limited_separable(
                    z.reshape(len(z), -1), stencil.separable()).reshape(z.shape)
                if stencil.separable().parts(columns, dtype) is not None:  # what apply takes
                    assert torch.equal(stencil.apply(z), one_pass)
                with monkeypatch.context() as patch:
                    patch.setattr(stencil, "separable", None)
                    two_passes = stencil.apply(z)
                clamped = stencil.apply(z).reshape(len(z), -1)[stencil.rows] != (
                    stencil.matrix.apply(z.reshape(len(z), -1)))
                assert int(clamped.sum()) > 10
                tolerance = 1e-14 if dtype == torch.float64 else 1e-6
                torch.testing.assert_close(one_pass, two_passes, rtol=tolerance, atol=tolerance)
                untouched = torch.ones(len(z), dtype=torch.bool)
                untouched[stencil.rows] = False
                assert torch.equal(one_pass[untouched], z[untouched])


@pytest.mark.parametrize("kind", ["sphere", "two shapes"])
def test_packed_results_are_checked_and_unpacked_as_volumes(kind):
    """A packed flow's checks and output read its packed values: the range it left (per channel
    and batch entry) is the volumes' where the packing holds one volume's nodes, and the values
    written onto ``u0`` are ``u0`` with the band and ring replaced, gradients included (a batch
    of shapes too, whose entries a flow integrates apart)."""
    from torchsurf.flows._integrators import with_ring

    surface = _held_surface(kind)
    u = _fields(surface, 1, seed=11)[0]
    flow = HeatFlow(4 * surface.spacing**2)
    flow(u, surface)
    packing = _flow_packing(surface)
    if surface.batch_size > 1:  # integrated apart: the first entry's packing
        surface, u = surface._kept[("entry surface", 0)], u[:1]
    band = flow.band_mask(surface)
    region = with_ring(band, None)
    start = packing.pack_region(u)
    generator = torch.Generator().manual_seed(12)
    results = [start * 1.3 - 0.1, start + 0.2 * torch.randn(start.shape, generator=generator,
                                                            dtype=start.dtype)]
    volumes = [torch.where(region, packing.unpack(r, u), u) for r in results]
    if packing.entries == 1:  # else the packed nodes mix the entries: the flow checks volumes
        assert base._packed_range_excess(start, results, packing.band_count) == pytest.approx(
            base._range_excess(u, volumes, region, band, False), rel=1e-14)

    values = results[1].clone().requires_grad_()
    like = u.clone().requires_grad_()
    g = torch.randn(u.shape, generator=generator, dtype=u.dtype)
    got = packing.unpack_onto(values, like, region)
    expected = torch.where(region, packing.unpack(values, like), like)
    assert torch.equal(got, expected)
    for a, b in zip(torch.autograd.grad((got * g).sum(), [values, like]),
                    torch.autograd.grad((expected * g).sum(), [values, like]), strict=True):
        assert torch.equal(a, b)


def test_one_columns_packed_values_have_the_standard_strides():
    """Packed values of one column and the native stages' results are laid out with the
    standard strides: ``(nodes, 1, 1)`` permuted from ``(1, 1, nodes)`` kept strides
    ``(1, nodes, nodes)``, contiguous to torch, whose copies of such a tensor ran 15x slower
    (0.59 against 0.04 ms for 131k nodes)."""
    surface = _held_surface("sphere")
    u = torch.rand((1, 1, *surface.grid.shape), generator=torch.Generator().manual_seed(2),
                   dtype=torch.float64)
    flow = HeatFlow(8 * surface.spacing**2)
    flow(u, surface)
    packing = _flow_packing(surface)
    packed = packing.pack_region(u)
    assert packed.shape == (len(packing.nodes), 1, 1) and packed.stride() == (1, 1, 1)
    from torchsurf.flows import _native_gather
    if _native_gather.LIBRARY.load() is None:
        return
    column = packed.reshape(-1, 1)
    rate0 = torch.zeros((packing.band_count, 1), dtype=torch.float64)
    stage = _native_gather.rkc_stage(packing.weighted, column, column, column, rate0,
                                     (0.5, 0.1, 0.01, 0.01))
    assert stage.stride() == (1, 1)


def test_native_stages_under_inference_mode_on_a_channel_slice(monkeypatch):
    """A user's call under ``torch.inference_mode`` on one channel sliced out of a
    channels-last field (not contiguous): the native stages run and give the volume flow's
    numbers; the caller's field is untouched."""
    surface = _held_surface("sphere")
    field = torch.rand((1, *surface.grid.shape, 3), generator=torch.Generator().manual_seed(4),
                       dtype=torch.float64).permute(0, 4, 1, 2, 3)
    before = field.clone()
    u = field[:, 1:2]
    assert not u.is_contiguous()
    calls = _counting_fused_stages(monkeypatch)
    with torch.inference_mode():
        packed, volume = _both(lambda: HeatFlow(10 * surface.spacing**2), u, surface, monkeypatch)
    assert calls
    torch.testing.assert_close(packed, volume, rtol=1e-12, atol=1e-12)
    assert torch.equal(field, before)


@pytest.mark.parametrize("kind", ["sphere", "two shapes"])
@pytest.mark.parametrize("channels", [3, 8])
def test_several_columns_native_stages_are_the_volume_flow(kind, channels, monkeypatch):
    """Several channels (up to ``STAGE_COLUMNS``): the stages run natively row by row, one
    call a stage (no whole step), the ring held or re-extended before each, and give the
    volume flow's numbers."""
    surface = _held_surface(kind)
    batch = surface.batch_size
    u = torch.rand((batch, channels, *surface.grid.shape),
                   generator=torch.Generator().manual_seed(13), dtype=torch.float64)
    calls = _counting_fused_stages(monkeypatch)
    with torch.no_grad():
        packed, volume = _both(lambda: HeatFlow(8 * surface.spacing**2, diffusivity=1.7),
                               u, surface, monkeypatch)
    assert "stage" in calls
    torch.testing.assert_close(packed, volume, rtol=1e-12, atol=1e-12)


def _inference_tensors(root: object) -> list[str]:
    """Paths to every inference tensor reachable from ``root`` (containers and objects'
    attributes)."""
    found, seen, stack = [], set(), [("root", root)]
    while stack:
        path, value = stack.pop()
        if id(value) in seen:
            continue
        seen.add(id(value))
        if isinstance(value, torch.Tensor):
            if value.is_inference():
                found.append(path)
        elif isinstance(value, (tuple, list)):
            stack += [(f"{path}[{i}]", item) for i, item in enumerate(value)]
        elif isinstance(value, dict):
            stack += [(f"{path}[{key!r}]", item) for key, item in value.items()]
        elif hasattr(value, "__dict__") and not isinstance(value, type) and not callable(value):
            stack += [(f"{path}.{key}", item) for key, item in vars(value).items()]
    return found


@pytest.mark.parametrize("layout", ["dense", "bricks"])
@pytest.mark.parametrize("method", ["rkc", "euler", "chebyshev"])
def test_an_evaluation_under_inference_mode_keeps_no_inference_tensor(layout, method):
    """The packed band's layouts (blocks, separable runs, values per dtype) are formed at their
    first use: under ``torch.inference_mode`` they were inference tensors, kept on the surface,
    and the next training call on it failed ("Inference tensors cannot be saved for
    backward"). Now nothing kept is, and that call's gradient is a fresh surface's."""
    grid = ts.Grid.cube(22, 1.5)
    phi = ts.sdf.sphere(grid, 0.9).double()
    u = torch.rand(1, 2, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(3))

    def surface_and_data():
        if layout == "dense":
            return ts.ImplicitSurface(phi, grid), u
        surface = bricks.from_dense(phi, grid)
        return surface, surface.from_dense(u)

    flow = ts.flows.HeatFlow(time=0.01, method=method)
    evaluated, data = surface_and_data()
    with torch.inference_mode():
        flow(data, evaluated)
    assert _inference_tensors(evaluated._kept) == []
    gradients = []
    for surface in (evaluated, surface_and_data()[0]):
        leaf = data.clone().requires_grad_()
        (flow(leaf, surface) * data).sum().backward()
        gradients.append(leaf.grad)
    torch.testing.assert_close(gradients[0], gradients[1], rtol=1e-12, atol=1e-12)
