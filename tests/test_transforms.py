"""torch.func transforms and forward-mode AD: the operators run under each; the flows, the
extensions and the learned layers run where documented and refuse the rest by name
(``torchsurf._transforms``, docs/learning.md "Derivatives")."""

import pytest
import torch
import torch.autograd.forward_ad as forward_ad

import torchsurf as ts


@pytest.fixture(scope="module")
def ellipsoid():
    grid = ts.Grid.cube(18, 1.6)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    # not a distance: |grad phi| varies over S
    phi = ((x / 1.1) ** 2 + y**2 + (z / 0.8) ** 2 - 1.0)[None, None]
    surface = ts.ImplicitSurface(phi, grid)
    generator = torch.Generator().manual_seed(3)
    u = torch.rand((2, 1, *grid.shape), dtype=torch.float64, generator=generator)
    return surface, u


@pytest.mark.parametrize("operator", ["octant", "symmetric", "anisotropic", "gradient"])
def test_operators_run_under_torch_func(ellipsoid, operator):
    """grad, vmap and jvp of an operator equal reverse-mode autograd, a loop over the batch
    and a central difference (the octant scheme's autograd Function refused grad before)."""
    surface, u = ellipsoid
    apply = {
        "octant": lambda v: ts.laplace_beltrami(v, surface),
        "symmetric": lambda v: ts.laplace_beltrami(v, surface, scheme="symmetric"),
        "anisotropic": lambda v: ts.anisotropic_diffusion(v, surface, "perona_malik",
                                                          contrast=0.5),
        "gradient": lambda v: ts.intrinsic_gradient(v, surface),
    }[operator]
    weights = torch.linspace(-1, 1, u.numel() // u.shape[0] * (3 if operator == "gradient" else 1),
                             dtype=u.dtype)

    def loss(v: torch.Tensor) -> torch.Tensor:
        return (apply(v).reshape(-1) * weights.repeat(v.shape[0])).square().sum()

    leaf = u.clone().requires_grad_()
    expected = torch.autograd.grad(loss(leaf), leaf)[0]
    assert torch.allclose(torch.func.grad(loss)(u), expected, rtol=1e-10, atol=1e-12)

    mapped = torch.func.vmap(apply)(u[:, None])[:, 0]
    assert torch.allclose(mapped, apply(u), rtol=1e-12, atol=1e-12)

    direction = torch.rand(u.shape, dtype=u.dtype, generator=torch.Generator().manual_seed(4))
    tangent = torch.func.jvp(apply, (u,), (direction,))[1]
    difference = (apply(u + 1e-6 * direction) - apply(u - 1e-6 * direction)) / 2e-6
    scale = float(difference.abs().max())
    assert float((tangent - difference).abs().max()) < 1e-6 * scale
    if operator != "anisotropic":  # linear: exactly the map of the direction
        assert torch.allclose(tangent, apply(direction), rtol=1e-12, atol=1e-12 * scale)


def _flows(surface):
    h2 = surface.spacing**2
    return {
        "heat rkc": ts.HeatFlow(2 * h2),
        "heat implicit": ts.HeatFlow(2 * h2, method="implicit"),
        "heat chebyshev": ts.HeatFlow(2 * h2, method="chebyshev"),
        "total variation": ts.AnisotropicFlow(2 * h2, diffusivity="total_variation"),
        "learned": ts.nn.LearnedDiffusion(1).double(),
        "block": ts.nn.DiffusionBlock(1).double(),
        "extension": ts.flows.Extension(),
        "closest_point_extension": lambda v, s: ts.flows.closest_point_extension(v, s),
        "pde_extension": lambda v, s: ts.flows.pde_extension(v, s),
    }


_NAMES = {"heat rkc": "HeatFlow", "heat implicit": "HeatFlow", "heat chebyshev": "HeatFlow",
          "total variation": "AnisotropicFlow", "learned": "LearnedDiffusion",
          "block": "DiffusionBlock", "extension": "Extension",
          "closest_point_extension": "closest_point_extension",
          "pde_extension": "pde_extension"}


@pytest.mark.parametrize("transform", ["grad", "vmap"])
@pytest.mark.parametrize("kind", list(_NAMES))
def test_flows_refuse_grad_and_vmap_by_name(ellipsoid, transform, kind):
    """Under torch.func.grad or vmap a flow failed deep inside ("Cannot access data pointer of
    Tensor that doesn't have storage", or a data-dependent control flow error); now it says
    what it is and what to use instead."""
    surface, u = ellipsoid
    apply = _flows(surface)[kind]
    if transform == "grad":
        call = lambda: torch.func.grad(lambda v: apply(v, surface).sum())(u)  # noqa: E731
        instead = "torch.autograd.grad"
    else:
        call = lambda: torch.func.vmap(lambda v: apply(v, surface))(u[:, None])  # noqa: E731
        instead = "batch dimension"
    with pytest.raises(NotImplementedError, match=f"{_NAMES[kind]} does not run under "
                                                  f"torch.func.{transform}.*{instead}"):
        call()


@pytest.mark.parametrize("kind", ["heat implicit", "heat chebyshev", "learned", "block",
                                  "extension", "closest_point_extension"])
@pytest.mark.parametrize("mode", ["forward_ad", "jvp"])
def test_forward_mode_refused_where_there_is_none(ellipsoid, kind, mode):
    """Where a step has no forward derivative (autograd Functions with a backward only,
    grid_sample in a dense trilinear extension), forward-mode AD names what refuses it."""
    surface, u = ellipsoid
    apply = _flows(surface)[kind]
    direction = torch.ones_like(u)
    with pytest.raises(NotImplementedError,
                       match=rf"{_NAMES[kind]}(\(interpolation='linear'\) on a dense volume)? "
                             "has no forward-mode derivative"):
        if mode == "jvp":
            torch.func.jvp(lambda v: apply(v, surface), (u,), (direction,))
        else:
            with forward_ad.dual_level():
                apply(forward_ad.make_dual(u, direction), surface)


@pytest.mark.parametrize("kind", ["heat rkc", "perona_malik", "pde_extension",
                                  "cubic extension"])
def test_forward_mode_where_documented(ellipsoid, kind):
    """The explicit methods, the PDE extension and the tricubic extension carry tangents:
    equal to a central difference."""
    surface, u = ellipsoid
    flows = _flows(surface)
    flows["cubic extension"] = ts.flows.Extension(interpolation="cubic")
    flows["perona_malik"] = ts.AnisotropicFlow(2 * surface.spacing**2, "perona_malik", contrast=0.5)
    apply = flows[kind]
    direction = torch.rand(u.shape, dtype=u.dtype, generator=torch.Generator().manual_seed(5))
    with torch.no_grad():
        difference = (apply(u + 1e-6 * direction, surface)
                      - apply(u - 1e-6 * direction, surface)) / 2e-6
    with forward_ad.dual_level():
        tangent = forward_ad.unpack_dual(apply(forward_ad.make_dual(u, direction),
                                               surface)).tangent
    assert float((tangent - difference).abs().max()) < 1e-6 * float(difference.abs().max())


def test_outside_any_transform_nothing_is_refused():
    from torchsurf._transforms import active_transforms, refuse_transforms

    assert active_transforms() == set()
    refuse_transforms("anything", torch.zeros(2), forward_mode=False)  # no transform: no error
    names = []
    torch.func.vmap(lambda v: names.append(active_transforms()) or v)(torch.zeros(2, 1))
    assert names == [{"Vmap"}]


@pytest.mark.parametrize("storage", ["dense", "bricks"])
def test_jvp_on_a_fresh_surface(storage):
    """The surface's kept state (band, stencils) formed under torch.func.jvp had been wrapped
    tensors, refused by the numpy and C code forming it: a first call failed ("Cannot access
    data pointer"); it is now formed beneath the transform, and later plain calls reuse it."""
    grid = ts.Grid.cube(22, 2.0)
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    phi = (((x / 1.1) ** 2 + y**2 + (z / 0.8) ** 2).sqrt() - 1.0)[None, None]
    surface = ts.ImplicitSurface(phi, grid)
    if storage == "bricks":
        surface = ts.bricks.from_dense(surface)
    generator = torch.Generator().manual_seed(3)
    u = torch.rand((1, 1, *grid.shape), dtype=torch.float64, generator=generator)
    direction = torch.rand(u.shape, dtype=u.dtype, generator=generator)
    if storage == "bricks":
        u, direction = surface.from_dense(u), surface.from_dense(direction)
    flow = ts.HeatFlow(2 * surface.spacing**2)
    tangent = torch.func.jvp(lambda v: flow(v, surface), (u,), (direction,))[1]
    assert not torch._C._functorch.is_functorch_wrapped_tensor(surface.band_mask())
    with torch.no_grad():
        difference = (flow(u + 1e-6 * direction, surface)
                      - flow(u - 1e-6 * direction, surface)) / 2e-6
    assert float((tangent - difference).abs().max()) < 1e-6 * float(difference.abs().max())


def test_forward_mode_through_a_learned_time():
    """A learned time records the steps in recomputed groups and re-extensions by autograd
    Functions without forward derivatives: forward_ad failed inside them."""
    grid = ts.Grid.cube(18, 1.6)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    u = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                   generator=torch.Generator().manual_seed(1))
    direction = torch.ones_like(u)
    flow = ts.HeatFlow(2 * surface.spacing**2, learn_time=True).double()
    with forward_ad.dual_level():
        tangent = forward_ad.unpack_dual(flow(forward_ad.make_dual(u, direction),
                                              surface)).tangent
    with torch.no_grad():
        difference = (flow(u + 1e-6 * direction, surface)
                      - flow(u - 1e-6 * direction, surface)) / 2e-6
    assert float((tangent - difference).abs().max()) < 1e-6 * float(difference.abs().max())


def test_colour_denoising_and_brick_extensions_refuse_by_their_own_name():
    grid = ts.Grid.cube(22, 2.0)
    dense = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9), grid)
    image = torch.rand((1, 3, *grid.shape))
    with pytest.raises(NotImplementedError, match="ColorDenoise does not run under torch.func.vmap"):
        torch.func.vmap(lambda v: ts.ColorDenoise(0.01)(v, dense))(image[:, None])
    with pytest.raises(NotImplementedError, match="ColorDenoise does not run under torch.func.grad"):
        torch.func.grad(lambda v: ts.ColorDenoise(0.01)(v, dense).sum())(image)
    packed = ts.bricks.from_dense(dense)
    field = packed.from_dense(image[:, :1])
    with pytest.raises(NotImplementedError, match="Extension does not run under torch.func.vmap"):
        torch.func.vmap(lambda v: ts.flows.Extension()(v, packed))(field[:, None])


@pytest.mark.parametrize("path", ["compiled", "slicing"])
def test_forward_mode_on_every_path(path):
    """path="compiled" ran its compiled kernel under no_grad on detached inputs: an
    operator's tangent was 0, a heat flow's 0.5 off; now the one-pass form runs eagerly there."""
    grid = ts.Grid.cube(20, 2.0)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9, dtype=torch.float64), grid)
    u = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                   generator=torch.Generator().manual_seed(1))
    direction = torch.rand(u.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    for apply in (lambda v: ts.laplace_beltrami(v, surface, path=path),
                  lambda v: ts.HeatFlow(2 * surface.spacing**2, path=path)(v, surface)):
        tangent = torch.func.jvp(apply, (u,), (direction,))[1]
        with torch.no_grad():
            difference = (apply(u + 1e-6 * direction) - apply(u - 1e-6 * direction)) / 2e-6
        assert float((tangent - difference).norm() / difference.norm()) < 1e-7


def test_forward_mode_in_phi():
    """A dual phi through the heat flow's packed steps gave a tangent of None (the packed
    path chose on phi.requires_grad only); phi under torch.func.jvp is refused by name."""
    grid = ts.Grid.cube(20, 2.0)
    phi = ts.sdf.sphere(grid, 0.9, dtype=torch.float64)
    shift = torch.full_like(phi, 0.01)
    u = torch.rand((1, 1, *grid.shape), dtype=torch.float64,
                   generator=torch.Generator().manual_seed(1))
    flow = ts.HeatFlow(4 * grid.spacing**2)
    with forward_ad.dual_level():
        tangent = forward_ad.unpack_dual(
            flow(u, ts.ImplicitSurface(forward_ad.make_dual(phi, shift), grid))).tangent
    with torch.no_grad():
        difference = (flow(u, ts.ImplicitSurface(phi + 1e-6 * shift, grid))
                      - flow(u, ts.ImplicitSurface(phi - 1e-6 * shift, grid))) / 2e-6
    assert tangent is not None
    assert float((tangent - difference).norm() / difference.norm()) < 1e-5
    with pytest.raises(NotImplementedError, match="HeatFlow does not run with phi under"):
        torch.func.jvp(lambda p: flow(u, ts.ImplicitSurface(p, grid)), (phi,), (shift,))


def test_a_phi_batched_by_vmap_is_refused_by_the_surface_by_name():
    """functorch's "data-dependent control flow" error had named nothing of torchsurf's."""
    grid = ts.Grid.cube(12, 1.6)
    phis = torch.stack([ts.sdf.sphere(grid, 0.8), ts.sdf.sphere(grid, 0.6)])
    with pytest.raises(NotImplementedError, match="ImplicitSurface does not take a phi batched"):
        torch.func.vmap(lambda p: ts.ImplicitSurface(p, grid).mean_curvature())(phis)


def test_band_functions_run_with_phi_under_jvp():
    """The band's cells to the nearest crossing are read by numpy: under jvp in phi they had
    failed ("Cannot access data pointer of Tensor that doesn't have storage")."""
    grid = ts.Grid.cube(16, 1.6)
    phi = ts.sdf.sphere(grid, 0.8, dtype=torch.float64)
    shift = torch.rand(phi.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    u = torch.rand((1, 2, *grid.shape), dtype=torch.float64,
                   generator=torch.Generator().manual_seed(1))

    def features(p: torch.Tensor) -> torch.Tensor:
        return ts.nn.gradient_features(u, ts.ImplicitSurface(p, grid))

    value, tangent = torch.func.jvp(features, (phi,), (shift,))
    difference = (features(phi + 1e-6 * shift) - features(phi - 1e-6 * shift)) / 2e-6
    assert torch.equal(value, features(phi))
    assert float((tangent - difference).norm() / difference.norm()) < 1e-6
    mask, mask_tangent = torch.func.jvp(
        lambda p: ts.ImplicitSurface(p, grid).band_mask().double(), (phi,), (shift,))
    assert torch.equal(mask.bool(), ts.ImplicitSurface(phi, grid).band_mask())
    assert not mask_tangent.any()


def test_export_keeps_nothing_on_the_surface_and_flows_refuse_it_by_name():
    """torch.export's fake tensors were kept on the surface (its haloed normals, its mean
    curvature): later calls as is returned them and failed on reading them."""
    grid = ts.Grid.cube(14, 1.6)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(0))

    class Holder(torch.nn.Module):
        def __init__(self, layer: torch.nn.Module | None = None) -> None:
            super().__init__()
            self.surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0) + 0.013, grid)
            self.layer = layer

        def forward(self, u: torch.Tensor) -> torch.Tensor:
            if self.layer is not None:
                return self.layer(u, self.surface)
            return ts.laplace_beltrami(u, self.surface, scheme="central")

    model = Holder()
    expected = model(u)
    model.surface.clear_kept()
    exported = torch.export.export(model, (u,))
    torch.testing.assert_close(exported.module()(u), expected)
    after = model(u)
    assert type(after) is torch.Tensor and torch.equal(after, expected)
    assert type(model.surface.mean_curvature()) is torch.Tensor
    with pytest.raises(NotImplementedError, match="HeatFlow does not run under torch.export"):
        torch.export.export(Holder(ts.HeatFlow(grid.spacing**2)), (u,))


def test_a_batched_backward_is_refused_by_name_where_kernels_read_raw_memory():
    """jacobian(vectorize=True) through a flow failed with "Cannot access data pointer of
    Tensor that doesn't have storage" (or a missing batching rule) naming nothing of the
    flow's; operators and extensions run batched and equal the loop."""
    grid = ts.Grid.cube(10, 1.6)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0, dtype=torch.float64) + 0.013, grid)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(0))
    rows = surface.band_mask().reshape(-1).nonzero()[:3, 0]
    h2 = grid.spacing**2
    for layer in (ts.HeatFlow(2 * h2), ts.HeatFlow(2 * h2, method="implicit"),
                  ts.nn.LearnedDiffusion(1).double()):
        with pytest.raises(NotImplementedError, match="has no batched backward"):
            torch.autograd.functional.jacobian(
                lambda v, layer=layer: layer(v, surface).reshape(-1)[rows], u, vectorize=True)
    extension = ts.flows.Extension(interpolation="cubic")
    def read(v: torch.Tensor) -> torch.Tensor:
        return extension(v, surface).reshape(-1)[rows]
    torch.testing.assert_close(torch.autograd.functional.jacobian(read, u, vectorize=True),
                               torch.autograd.functional.jacobian(read, u), rtol=0, atol=0)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_sample_refuses_vmap_by_name_and_runs_the_rest(interpolation):
    """Under vmap sample failed with PyTorch's "data-dependent control flow" naming nothing of
    sample's; a linear read's tangent with grid_sample's message. grad and the cubic read's
    forward mode run and agree with reverse mode and the batch along B."""
    grid = ts.Grid.cube(9, 1.2)
    generator = torch.Generator().manual_seed(4)
    field = torch.rand(3, 1, *grid.shape, dtype=torch.float64, generator=generator)
    points = torch.rand(3, 6, 3, dtype=torch.float64, generator=generator) * 2 - 1
    with pytest.raises(NotImplementedError, match="sample does not run under torch.func.vmap"):
        torch.func.vmap(lambda f, p: ts.sample(f[None], p, grid, interpolation))(field, points)
    scales = torch.rand(4, dtype=torch.float64, generator=generator)  # transforms around a call
    read = ts.sample(field, points, grid, interpolation).sum()
    around = lambda x: x * ts.sample(field, points, grid, interpolation).sum()  # noqa: E731
    torch.testing.assert_close(torch.func.vmap(around)(scales), scales * read)
    torch.testing.assert_close(torch.func.jvp(around, (scales,), (scales,))[1], scales * read)
    weights = torch.rand(3, 1, 6, dtype=torch.float64, generator=generator)
    grad = torch.func.grad(lambda p: (ts.sample(field, p, grid, interpolation) * weights).sum())(points)
    moved = points.clone().requires_grad_(True)
    (ts.sample(field, moved, grid, interpolation) * weights).sum().backward()
    torch.testing.assert_close(grad, moved.grad, rtol=0, atol=0)
    tangent = torch.rand_like(points)
    read = lambda p: ts.sample(field, p, grid, interpolation)  # noqa: E731
    if interpolation == "linear":
        with pytest.raises(NotImplementedError, match="interpolation='cubic'"):
            torch.func.jvp(read, (points,), (tangent,))
        return
    _, derivative = torch.func.jvp(read, (points,), (tangent,))
    step = 1e-6
    central = (read(points + step * tangent) - read(points - step * tangent)) / (2 * step)
    torch.testing.assert_close(derivative, central, rtol=1e-6, atol=1e-8)


def test_jit_trace_is_refused_by_the_layers_and_runs_the_operators():
    """torch.jit.trace of a HeatFlow gave no error and replayed uninitialised memory (6.5e27
    off); the operators' batch check compared traced sizes as tensors ("the batch sizes of u,
    normal, weight must be equal or 1, got [tensor(1), tensor(1), tensor(1)]")."""
    grid = ts.Grid.cube(24, 1.7)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    u = torch.rand(1, 1, *grid.shape, generator=torch.Generator().manual_seed(6))
    for layer in (ts.HeatFlow(2 * grid.spacing**2), ts.nn.LearnedDiffusion(1), ts.flows.Extension()):
        with pytest.raises(NotImplementedError, match=f"{type(layer).__name__} does not run under "
                                                      "torch.jit.trace"):
            torch.jit.trace(lambda v, layer=layer: layer(v, surface), (u,), check_trace=False)
    bricks = ts.bricks.from_dense(surface.phi, grid)
    packed = torch.rand(len(bricks.layout), 1, 8, 8, 8, generator=torch.Generator().manual_seed(7))
    for on, data in ((surface, u), (bricks, packed)):
        operator = lambda v, on=on: ts.laplace_beltrami(v, on)  # noqa: E731
        traced = torch.jit.trace(operator, (data,), check_trace=False)
        torch.testing.assert_close(traced(data), operator(data), rtol=1e-5, atol=1e-4)
