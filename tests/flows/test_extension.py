"""Extension: values on S kept, data made constant along the normals."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import Extension
from torchsurf.flows._integrators import with_ring


def case(n=33, dtype=torch.float64):
    grid = ts.Grid.cube(n, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=dtype), grid)
    points = grid.points(dtype=dtype)
    x, y, z = points.unbind(-1)
    r = points.norm(dim=-1).clamp(min=1e-3)
    # a function of the direction only (constant along normals), and one that varies along them
    extended = (x * y / r**2 + z / r)[None, None]
    u = extended * (1 + 2 * (r - 1))[None, None]
    return u, extended, surface


@pytest.mark.parametrize("method", ["closest_point", "pde"])
def test_extension_makes_data_constant_along_normals(method):
    u, extended, surface = case()
    out = Extension(method)(u, surface)
    band = (surface.band_mask() & (surface.phi.abs() <= 2 * surface.spacing))
    before = float((u - extended).abs()[band].max())
    after = float((out - extended).abs()[band].max())
    assert after < 0.2 * before, (before, after)
    outside = ~surface.band_mask()
    assert torch.equal(out[outside], u[outside])


def test_pde_extension_keeps_nodes_on_the_surface():
    grid = ts.Grid.cube(21, bound=1.0)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=0.5, dtype=torch.float64), grid)
    generator = torch.Generator().manual_seed(0)
    u = torch.rand((1, 1, 21, 21, 21), generator=generator, dtype=torch.float64)
    out = Extension("pde")(u, surface)
    on = surface.phi == 0
    assert on.any()
    assert torch.equal(out[on], u[on])


def test_closest_point_keeps_values_on_the_surface_up_to_interpolation():
    u, extended, surface = case(33)
    out = Extension("closest_point")(extended, surface)
    near = surface.phi.abs() <= 0.5 * surface.spacing
    assert float((out - extended).abs()[near].max()) < 2e-2


def test_extension_is_differentiable_and_rejects_bad_input():
    u, _, surface = case(9)
    u = u.requires_grad_()
    Extension()(u, surface).sum().backward()
    assert torch.isfinite(u.grad).all()
    with pytest.raises(ValueError, match="method"):
        Extension("nearest")
    with pytest.raises(ValueError, match="u"):
        Extension()(u[0], surface)


def test_settings_the_method_would_ignore_are_refused():
    """They were accepted and ignored: the pde extension with interpolation='cubic', the
    closest-point one with a tolerance or max_steps, a width beside a mask (an audit)."""
    u, _, surface = case(9)
    with pytest.raises(ValueError, match=r"^interpolation='cubic' .* method='pde' interpolates"):
        Extension("pde", interpolation="cubic")
    for settings in ({"tolerance": 0.5}, {"max_steps": 1}):
        with pytest.raises(ValueError, match=r"^tolerance and max_steps bound the pde"):
            Extension(**settings)
    with pytest.raises(ValueError, match=r"^give width or mask, not both"):
        ts.flows.closest_point_extension(u, surface, width=0.5 * surface.spacing,
                                         mask=surface.band_mask())
    assert Extension("pde", tolerance=1e-3, max_steps=4).max_steps == 4


def test_cubic_closest_point_reproduces_cubic_polynomials():
    """Tricubic Lagrange interpolation is exact for cubics: the extension equals the cubic at
    each band node's closest point (nodes whose stencil stays inside the box)."""
    grid = ts.Grid((15, 16, 17), spacing=0.12, origin=(-0.95, -0.9, -0.85))
    phi = ts.sdf.sphere(grid, radius=0.6, center=(0.03, -0.02, 0.05), dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid)

    def cubic(points):
        x, y, z = points.unbind(-1)
        return 0.3 + x - 2 * y * z + x**2 * y + 0.5 * z**3 - x * y * z + y**3

    points = grid.points(dtype=torch.float64)
    out = ts.flows.Extension(interpolation="cubic")(cubic(points)[None, None], surface)
    step = (surface.phi / surface.weight) * surface.normal
    closest = points - step[0].permute(1, 2, 3, 0)
    band = surface.band_mask()[0, 0]
    torch.testing.assert_close(out[0, 0][band], cubic(closest)[band], rtol=0, atol=1e-12)
    linear = ts.flows.Extension()(cubic(points)[None, None], surface)
    assert float((linear[0, 0] - cubic(closest)).abs()[band].max()) > 1e-3


def test_fixed_band_with_reextension_is_as_accurate_as_evolving_a_wide_band():
    """The 3-cell band re-extended by tricubic closest points against a band as wide as the
    diffusion length held at u0 (the scheme before the band was fixed): at 33^3, l = 2,
    t = 0.05, 4.5e-3 against 5.7e-3 (octant scheme, 500 points on S). Without re-extension the
    narrow band's stale ring costs it a factor 2.9 (1.3e-2)."""
    grid = ts.Grid.cube(33, bound=1.4)
    phi = ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid)
    points = grid.points(dtype=torch.float64)
    z = points[..., 2] / points.norm(dim=-1).clamp(min=1e-9)
    u0 = (3 * z**2 - 1)[None, None]
    count = 500
    i = torch.arange(count, dtype=torch.float64) + 0.5
    height = 1 - 2 * i / count
    angle = torch.pi * (1 + 5**0.5) * i
    ring = torch.sqrt(1 - height**2)
    on_s = torch.stack((ring * torch.cos(angle), ring * torch.sin(angle), height), dim=-1)
    exact = (3 * height**2 - 1) * torch.exp(torch.tensor(-6 * 0.05, dtype=torch.float64))

    def error(flow):
        values = ts.sample(flow(u0, surface), on_s, grid)[0, 0]
        return float((values - exact).abs().max() / exact.abs().max())

    wide = error(ts.HeatFlow(0.05, method="euler", band_width=0.75, reextend_every=None))
    narrow = 3 * grid.spacing  # on this exact distance the flows' default band is 5 cells
    fixed = error(ts.HeatFlow(0.05, band_width=narrow))
    stale = error(ts.HeatFlow(0.05, reextend_every=None, band_width=narrow))
    assert fixed < wide, (fixed, wide)
    assert stale > 2.5 * fixed, (stale, fixed)


@pytest.mark.parametrize("interpolation", ["linear", "cubic"])
def test_closest_point_gradcheck_in_data_and_phi(interpolation):
    """Off-centre sphere and a band edge between nodes: on a centred sphere some closest points
    fall exactly on nodes, where the interpolants' derivatives jump."""
    grid = ts.Grid.cube(13, bound=1.5)
    phi = ts.sdf.sphere(grid, radius=0.93, center=(0.031, -0.047, 0.023), dtype=torch.float64)
    generator = torch.Generator().manual_seed(0)
    u = torch.rand((1, 1, 13, 13, 13), dtype=torch.float64, generator=generator)
    direction = torch.randn((1, 1, 13, 13, 13), dtype=torch.float64, generator=generator)
    extension = Extension(width=0.7, interpolation=interpolation)

    def run(u, c):
        return extension(u, ts.ImplicitSurface(phi + 0.01 * c * direction, grid))

    c = torch.zeros((), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(run, (u.requires_grad_(), c), fast_mode=True)


@pytest.mark.parametrize("limited", [False, True])
def test_interpolation_forms_agree(limited):
    """The 64-term form the compiled path runs equals the eager single gather, limiter included."""
    from torchsurf.flows.extension import _interpolate_gathered, _interpolate_terms

    generator = torch.Generator().manual_seed(5)
    depth, height, width = 6, 7, 8
    flat = torch.randn(2, depth * height * width, dtype=torch.float64, generator=generator)
    count = 40
    sizes = torch.tensor([width, height, depth])[:, None, None]
    corners = (torch.randint(0, 10, (3, count, 1), generator=generator) + torch.arange(4)) % sizes
    weights = torch.randn(3, count, 4, dtype=torch.float64, generator=generator)
    eager = _interpolate_gathered(flat, corners, weights, height, width, limited)
    terms = _interpolate_terms(flat, corners, weights, height, width, limited)
    torch.testing.assert_close(terms, eager, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("limited", [False, True])
def test_anchored_form_agrees_with_the_kept_sources(limited):
    """A stencil with no tap clamped at the box keeps each node's first tap; the compiled path's
    form reads its 64 taps at fixed offsets from it: the same numbers as the eager gather, and
    as a stencil that keeps all 64 sources."""
    from torchsurf.flows.extension import (
        CubicStencil,
        _anchored_gathered,
        _anchored_terms,
        _kept_gathered,
    )

    grid = ts.Grid.cube(21, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=0.8, dtype=torch.float64), grid)
    stencil = CubicStencil(surface, surface.band_mask(), limited=limited)
    assert stencil.anchors[0] is not None
    touching = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.4, dtype=torch.float64), grid)
    near_face = CubicStencil(touching, touching.band_mask(), limited=limited)
    assert near_face.anchors[0] is None  # S a cell from the box's faces: taps clamped there
    flat = torch.randn(2, 21**3, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    sources, anchors, by_offset = stencil.sources[0], stencil.anchors[0], stencil.weights_by_offset[0]
    weights = stencil.parts[0][2]
    kept = _kept_gathered(flat, sources, weights, limited)
    arguments = (flat, sources, anchors, by_offset, 21 * 21, 21, limited)
    torch.testing.assert_close(_anchored_gathered(*arguments), kept, rtol=0, atol=0)
    torch.testing.assert_close(_anchored_terms(*arguments), kept, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_limited_stencil_by_the_c_kernel_agrees_with_the_gathers(dtype):
    """A limited dense stencil on the ``"auto"`` path runs the packed band's C kernel a channel
    at a time: the same values as the eager gathers to rounding, on a batch of two surfaces
    (one cut by the box's faces: clamped taps, no anchors), data with jumps, in place too."""
    from torchsurf.flows import _native_gather
    from torchsurf.flows.extension import CubicStencil

    if _native_gather.LIBRARY.load() is None:
        pytest.skip("no C compiler: the kernel does not run")
    grid = ts.Grid.cube(26, 1.5)
    phi = torch.cat([ts.sdf.torus(grid, 0.8, 0.3, dtype=dtype),
                     ts.sdf.sphere(grid, 1.4, dtype=dtype)])
    with pytest.warns(RuntimeWarning, match="faces"):
        surface = ts.ImplicitSurface(phi, grid)
    stencil = CubicStencil(surface, surface.band_mask(), limited=True)
    generator = torch.Generator().manual_seed(4)
    u = (torch.rand((2, 3, *grid.shape), dtype=dtype, generator=generator) > 0.5).to(dtype)
    u = u + 0.1 * torch.randn(u.shape, dtype=dtype, generator=generator)
    native = stencil.apply(u, "auto")
    assert sorted(stencil._separable) == [0, 1]  # the kernel ran for both entries
    eager = stencil.apply(u, "slicing")
    tolerance = 1e-12 if dtype == torch.float64 else 2e-6
    torch.testing.assert_close(native, eager, rtol=0, atol=tolerance)
    assert not torch.equal(native, u)
    written = u.clone()
    assert stencil.apply(written, "auto", in_place=True) is written
    assert torch.equal(written, native)
    # recording a gradient takes the differentiable gathers
    grad_u = u.clone().requires_grad_()
    torch.testing.assert_close(stencil.apply(grad_u, "auto").detach(), eager, rtol=0,
                               atol=tolerance)


def test_limited_closest_point_stencil_is_the_same_in_a_scaled_and_moved_frame():
    """Closest points on faces aligned with the grid lie on node planes: the limiter's cell
    must not depend on how rounding falls in the frame the shape is given in."""
    from torchsurf.flows.extension import CubicStencil

    grid = ts.Grid.cube(29, 1.4)
    scale, shift = 3.7, (0.31, -2.2, 5.0)
    moved = ts.Grid(grid.shape, scale * grid.spacing,
                    tuple(scale * o + s for o, s in zip(grid.origin, shift, strict=True)))
    half, centre = (0.62, 0.47, 0.81), (0.05, -0.1, 0.0)
    phi = ts.sdf.box(grid, half, centre, dtype=torch.float64)
    phi_moved = ts.sdf.box(moved, tuple(scale * a for a in half),
                           tuple(scale * c + s for c, s in zip(centre, shift, strict=True)),
                           dtype=torch.float64)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    results = []
    for surface in (ts.ImplicitSurface(phi, grid), ts.ImplicitSurface(phi_moved, moved)):
        band = surface.band_mask()
        results.append(CubicStencil(surface, band, limited=True).apply(u))
    torch.testing.assert_close(results[1], results[0], rtol=0, atol=1e-12)


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_pde_extension_does_not_depend_on_the_scale_of_phi(scale):
    """Its upwind sign was ``phi / sqrt(phi^2 + h^2)``, mixing phi's units with h: 1e-3 * phi
    gave a result 74 % away. It now reads the distance ``phi / W``."""
    grid = ts.Grid.cube(24, 1.5)
    x, _, z = grid.points(dtype=torch.float64).unbind(-1)
    u = torch.sin(3 * x + 2 * z)[None, None]
    phi = ts.sdf.sphere(grid, 1.0, dtype=torch.float64)
    extension = Extension("pde")
    expected = extension(u, ts.ImplicitSurface(phi, grid))
    torch.testing.assert_close(extension(u, ts.ImplicitSurface(scale * phi, grid)), expected)


def test_pde_extension_of_data_plus_a_constant_is_the_extension_plus_the_constant():
    """It stopped on the change relative to the largest ``|u|``: an offset of 1e4 stopped it
    after a few steps (error 0.107 against 0.021 for ``u``). It now stops on ``u``'s range."""
    u, _, surface = case(29)
    expected = ts.flows.pde_extension(u, surface, tolerance=1e-5)
    shifted = ts.flows.pde_extension(u + 1e4, surface, tolerance=1e-5) - 1e4
    band = surface.band_mask()
    torch.testing.assert_close(shifted * band, expected * band, rtol=0, atol=1e-9)


def test_extension_arguments_are_checked_by_name():
    grid = ts.Grid.cube(12, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    u = torch.rand(1, 1, *grid.shape)
    for steps in (0, -5, 2.5):
        with pytest.raises(ValueError, match="max_steps"):
            Extension("pde", max_steps=steps)
        with pytest.raises(ValueError, match="max_steps"):
            ts.flows.pde_extension(u, surface, max_steps=steps)
    with pytest.raises(TypeError, match="mask must be a bool tensor"):
        ts.flows.closest_point_extension(u, surface, mask=torch.ones_like(u))
    with pytest.raises(ValueError, match=r"mask must have shape \(B or 1, 1, 12, 12, 12\)"):
        ts.flows.closest_point_extension(u, surface, mask=torch.ones(1, 1, 3, 3, 3, dtype=torch.bool))
    meta = torch.ones(1, 1, *grid.shape, dtype=torch.bool, device="meta")
    with pytest.raises(ValueError, match="mask is on meta but u is on cpu"):
        ts.flows.closest_point_extension(u, surface, mask=meta)
    with pytest.raises(ValueError, match="limited=True clamps tricubic values"):
        Extension(limited=True)
    with pytest.raises(TypeError, match="limited"):
        Extension(interpolation="cubic", limited="yes")


def test_limited_cubic_extension_is_differentiable_in_data_and_phi():
    grid = ts.Grid.cube(10, 1.5)
    phi = ts.sdf.sphere(grid, 0.9, center=(0.05, -0.03, 0.02), dtype=torch.float64)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    extension = Extension(interpolation="cubic", limited=True)
    surface = ts.ImplicitSurface(phi, grid)
    assert torch.autograd.gradcheck(lambda x: extension(x, surface), (u.requires_grad_(),),
                                    fast_mode=True)
    phi = phi.requires_grad_()
    assert torch.autograd.gradcheck(
        lambda p: extension(u.detach(), ts.ImplicitSurface(p, grid)), (phi,), atol=1e-6,
        fast_mode=True)


def _off_centre_sphere(storage: str, seed: int):
    """A 24^3 grid, a sphere off the nodes on it (dense or bricks), and uniform data on it."""
    grid = ts.Grid.cube(24, 1.5)
    phi = ts.sdf.sphere(grid, 0.9, center=(0.03, -0.02, 0.01), dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid) if storage == "dense" else ts.bricks.from_dense(phi, grid)
    u = torch.rand(1, 1, *grid.shape, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(seed))
    if surface.layout is not None:
        u = surface.layout.from_dense(u)
    return grid, surface, u


@pytest.mark.parametrize("storage", ["dense", "bricks"])
@pytest.mark.parametrize("kind", ["linear", "cubic", "pde"])
def test_non_finite_data_where_read_is_refused_and_beyond_it_left_alone(kind, storage):
    """A NaN in the band spread through the extension silently (flows refuse it). Tricubic
    interpolation and the PDE also read a little beyond a 3-cell band: NaN there had reached
    515 band nodes (cubic; 5150 of 5370 at a 2-cell band) and stopped the PDE's march after
    one step, and 1e3 there moved band values by 0.07 (cubic) and 23 (PDE), silently. What is
    read must be finite; what is not read changes nothing."""
    grid, surface, u = _off_centre_sphere(storage, seed=0)
    extension = (Extension("pde") if kind == "pde"
                 else Extension(interpolation=kind))
    band = surface.band_mask()
    if kind == "cubic":
        read = band | ts.flows.extension._read_by(ts.flows.extension.cubic_stencil(surface, band), band)
    elif kind == "pde":
        read = with_ring(band, surface.layout)
    else:
        read = band
    assert bool((read & ~band).any()) == (kind != "linear")
    inside = u.clone()
    inside[tuple(band.nonzero()[0])] = float("nan")
    with pytest.raises(ValueError, match=r"u \(in the band.*\) must hold finite values"):
        extension(inside, surface)
    if kind != "linear":
        with pytest.raises(ValueError, match=r"u \(in the band and .*\) must hold finite values"):
            extension(torch.where(band, u, float("nan")), surface)
    clean = extension(u, surface)
    for beyond in (float("nan"), 1e3):
        result = extension(torch.where(read, u, beyond), surface)
        torch.testing.assert_close(result[band.expand_as(result)], clean[band.expand_as(clean)],
                                   rtol=0, atol=1e-14)
        far = ~read.expand_as(result)
        assert torch.equal(result[far].isnan(), torch.full_like(result[far], beyond).isnan())


@pytest.mark.parametrize("storage", ["dense", "bricks"])
def test_linear_extension_of_a_narrow_band_refuses_what_it_reads_beyond_it(storage):
    """Trilinear interpolation reads the cell around each closest point, up to sqrt(3) cells
    from S: with a band of half a cell, NaN beyond it came back at every band node (1309 of
    1309 at 33^3), with no error."""
    grid, surface, u = _off_centre_sphere(storage, seed=1)
    narrow = 0.5 * grid.spacing
    band = surface.band_mask(narrow)
    with pytest.raises(ValueError, match=r"u \(at the nodes its trilinear interpolation reads, "
                                         r"up to sqrt\(3\) cells from S\) must hold finite"):
        Extension(width=narrow)(torch.where(band, u, float("nan")), surface)
    wide = surface.band_mask(2.0 * grid.spacing)
    result = Extension(width=narrow)(torch.where(wide, u, float("nan")), surface)
    assert bool(result[band.expand_as(result)].isfinite().all())


def test_extension_takes_a_path_and_slicing_never_compiles(monkeypatch):
    """``Extension`` had no ``path=``: its tricubic gathers could only be kept eager by
    ``TORCHSURF_COMPILE=never`` (docs/learning.md says a layer given ``"slicing"`` never
    compiles)."""
    from torchsurf import backend
    from torchsurf.bricks import _native as brick_native
    from torchsurf.flows import _native_gather

    monkeypatch.setenv("TORCHSURF_NATIVE", "never")  # the gathers then run through backend
    for library in (_native_gather.LIBRARY, brick_native.LIBRARY):
        monkeypatch.setattr(library, "_state", {})
    compiled: list[object] = []
    monkeypatch.setattr(backend, "compiled", lambda f, *options: compiled.append(f) or f)
    grid = ts.Grid.cube(15, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.9), grid)
    u = torch.rand(1, 1, 15, 15, 15, generator=torch.Generator().manual_seed(0))
    results = {}
    for path in ("slicing", "auto"):
        with backend.warm_up():
            results[path] = ts.Extension(interpolation="cubic", limited=True, path=path)(u, surface)
        assert bool(compiled) == (path == "auto")
    torch.testing.assert_close(results["slicing"], results["auto"])
    assert "path='slicing'" in repr(ts.Extension(path="slicing"))
    with pytest.raises(ValueError, match="path"):
        ts.Extension(path="fast")


def test_cubic_extension_keeps_its_stencil_while_phi_needs_no_gradient(monkeypatch):
    """Its stencil was formed at every call: 7x its application at 64^3 (an audit)."""
    from torchsurf.flows import extension

    formed = []
    original = extension.cubic_stencil
    monkeypatch.setattr(extension, "cubic_stencil",
                        lambda *args, **kwargs: formed.append(1) or original(*args, **kwargs))
    grid = ts.Grid.cube(21, 1.5)
    phi = ts.sdf.torus(grid, dtype=torch.float64)
    u = torch.randn(1, 2, *grid.shape, dtype=torch.float64,
                    generator=torch.Generator().manual_seed(3))
    surface = ts.ImplicitSurface(phi, grid)
    first = ts.flows.closest_point_extension(u, surface, interpolation="cubic")
    assert torch.equal(ts.flows.closest_point_extension(u, surface, interpolation="cubic"), first)
    assert len(formed) == 1
    learned = ts.ImplicitSurface(phi.clone().requires_grad_(), grid)  # its weights in the graph
    for _ in range(2):
        again = ts.flows.closest_point_extension(u, learned, interpolation="cubic")
    assert len(formed) == 3 and torch.equal(again.detach(), first)


@pytest.mark.parametrize("storage", ["dense", "bricks"])
def test_a_restricted_stencil_is_the_one_formed_for_its_mask(storage):
    """The ring's stencil is taken from the region's rows (``restricted``): it must be what
    ``cubic_stencil`` forms for the ring with the same readable region, tensor for tensor."""
    from torchsurf.flows.extension import cubic_stencil

    grid = ts.Grid.cube(30, 2.0)
    phi = torch.cat([ts.sdf.torus(grid, dtype=torch.float64),
                     ts.sdf.sphere(grid, 0.9, dtype=torch.float64)])
    surface = ts.ImplicitSurface(phi, grid)
    if storage == "bricks":
        surface = ts.bricks.from_dense(phi, grid)
    band = surface.band_mask()
    region = with_ring(band, surface.layout)
    ring = region & ~band
    whole = cubic_stencil(surface, region, limited=True, readable=region)
    taken = whole.restricted(ring & ts.flows._closest.has_direction(surface), limited=False)
    formed = cubic_stencil(surface, ring, limited=False, readable=region)
    assert taken.limited is False
    if storage == "bricks":
        for name in ("targets", "bases", "second", "local", "weights", "sources"):
            assert torch.equal(getattr(taken, name), getattr(formed, name))
        return
    assert len(taken.parts) == len(formed.parts) == 2
    for mine, theirs in zip(taken.parts, formed.parts, strict=True):
        assert all(torch.equal(a, b) for a, b in zip(mine, theirs, strict=True))
    for name in ("sources", "anchors", "weights_by_offset"):
        for a, b in zip(getattr(taken, name), getattr(formed, name), strict=True):
            assert (a is None and b is None) or torch.equal(a, b)


@pytest.mark.parametrize("kind", ["heat", "perona_malik", "harmonic"])
def test_forward_mode_tangents_go_through_the_flows(kind):
    """The C kernels read raw memory: data carrying a forward-mode tangent (or a torch.func
    wrapper) take the differentiable paths. The tangent equals a central difference (the
    kernels had dropped it: 0.96 off for Perona–Malik, 0.52 for the packed heat flow)."""
    import torch.autograd.forward_ad as forward_ad

    grid = ts.Grid.cube(14, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.torus(grid, 0.8, 0.35, dtype=torch.float64), grid)
    generator = torch.Generator().manual_seed(0)
    channels = 3 if kind == "harmonic" else 1
    u = torch.rand((1, channels, *grid.shape), dtype=torch.float64, generator=generator)
    if kind == "harmonic":
        u = u / u.norm(dim=1, keepdim=True)
    direction = torch.rand(u.shape, dtype=torch.float64, generator=generator)
    h2 = surface.spacing**2
    flow = {"heat": lambda: ts.HeatFlow(3 * h2),
            "perona_malik": lambda: ts.AnisotropicFlow(3 * h2, diffusivity="perona_malik"),
            "harmonic": lambda: ts.flows.HarmonicMapFlow(h2, reextend_every=1)}[kind]()
    with torch.no_grad():
        difference = (flow(u + 1e-6 * direction, surface)
                      - flow(u - 1e-6 * direction, surface)) / 2e-6
    with forward_ad.dual_level():
        tangent = forward_ad.unpack_dual(
            flow(forward_ad.make_dual(u, direction), surface)).tangent
    assert float((tangent - difference).abs().max()) < 1e-7 * float(difference.abs().max())
    jvp = torch.func.jvp(lambda x: flow(x, surface), (u,), (direction,))[1]
    assert float((jvp - difference).abs().max()) < 1e-7 * float(difference.abs().max())
