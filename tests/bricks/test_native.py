"""The octant Laplace–Beltrami's C kernel on bricks against the eager one-pass form."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

import torchsurf as ts
from torchsurf import Grid, bricks
from torchsurf._native import _whole
from torchsurf.bricks import _native
from torchsurf.operators import functional


def _octant(surface, u, path, mask=None, weighted=False):
    return functional.divergence_form(
        u, surface.normal, surface.weight, surface.spacing, "octant", path, weighted=weighted,
        haloed=surface.haloed(), pad=surface.layout.halo, mask=mask)


@pytest.fixture(scope="module")
def native_available():
    if _native.library() is None:
        pytest.skip(f"no native kernel here: {_native.unavailable_reason()}")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize("weighted", [False, True])
def test_native_octant_equals_the_eager_form(two_boxes, native_available, dtype, masked,
                                             weighted):
    """A batch of two boxes of odd shapes and origins, three channels, every stored node (bricks
    at the edge of the stored ones read missing neighbours as zeros) or the band's."""
    _, _, both = two_boxes
    surface = both.to(dtype)
    u = torch.randn(len(surface.layout), 3, 8, 8, 8, dtype=dtype,
                    generator=torch.Generator().manual_seed(3))
    mask = surface.band_mask() if masked else None
    native = surface.layout.native_octant(u, *surface.haloed(), surface.spacing, weighted, mask)
    assert native is not None
    eager = _octant(surface, u, "slicing", mask, weighted)
    tolerance = 1e-6 if dtype == torch.float32 else 1e-13
    assert (native - eager).abs().max() <= tolerance * eager.abs().max()
    if masked:
        assert not native[~mask.expand_as(native)].any()
    assert torch.equal(_octant(surface, u, "auto", mask, weighted), native)


def test_native_octant_reads_views_of_any_brick_and_channel_strides(two_boxes,
                                                                    native_available):
    """Halos come packed channel-major (``(C, N)`` in memory); data may be a channel slice."""
    _, _, surface = two_boxes
    wide = torch.randn(4, len(surface.layout), 8, 8, 8, dtype=torch.float64)
    u = wide.transpose(0, 1)[:, 1:3]
    assert not u.is_contiguous()
    native = surface.layout.native_octant(u, *surface.haloed(), surface.spacing, False, None)
    assert native is not None
    assert torch.allclose(native, _octant(surface, u.contiguous(), "slicing"), rtol=0,
                          atol=1e-13 * float(native.abs().max()))


def test_native_octant_follows_a_mask_written_in_place(torus, native_available):
    _, surface = torus
    u = torch.randn(len(surface.layout), 1, 8, 8, 8, dtype=torch.float64)
    mask = surface.band_mask().clone()
    first = _octant(surface, u, "auto", mask)
    mask[:, :, :, :, ::2] = False
    second = _octant(surface, u, "auto", mask)
    assert not torch.equal(first, second)
    assert torch.allclose(second, _octant(surface, u, "slicing", mask), atol=1e-12)


def test_native_octant_has_the_adjoint_backward(torus, native_available):
    """Autograd reaches ``u`` through the self-adjoint backward, which runs the kernel too."""
    _, surface = torus
    band = surface.band_mask()
    u = torch.randn(len(surface.layout), 2, 8, 8, 8, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda v: _octant(surface, v, "auto", band), (u,),
                                    eps=1e-6, atol=1e-7, fast_mode=True)
    upstream = torch.randn_like(u)
    (native,) = torch.autograd.grad(_octant(surface, u, "auto", band), u, upstream)
    (eager,) = torch.autograd.grad(_octant(surface, u, "slicing", band), u, upstream)
    assert torch.allclose(native, eager, rtol=0, atol=1e-12 * float(eager.abs().max()))


def test_native_octant_steps_aside_for_a_gradient_to_the_geometry(torus, native_available):
    _, surface = torus
    u = torch.randn(len(surface.layout), 1, 8, 8, 8, dtype=torch.float64)
    normal, weight = (t.detach().requires_grad_() for t in surface.haloed())
    assert surface.layout.native_octant(u, normal, weight, surface.spacing, False, None) is None
    with torch.no_grad():
        assert surface.layout.native_octant(u, normal, weight, surface.spacing, False,
                                            None) is not None


def test_without_a_compiler_the_operators_take_their_other_paths(torus, monkeypatch, tmp_path):
    _, surface = torus
    u = torch.randn(len(surface.layout), 1, 8, 8, 8, dtype=torch.float64)
    expected = _octant(surface, u, "slicing")
    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", str(tmp_path / "no-such-compiler"))
    with pytest.warns(RuntimeWarning, match="unavailable.*no-such-compiler"):  # once, not silent
        assert surface.layout.native_octant(u, *surface.haloed(), surface.spacing, False,
                                            None) is None
    assert "no-such-compiler" in _native.unavailable_reason()
    assert torch.allclose(ts.laplace_beltrami(u, surface), expected, atol=1e-12)
    assert list(tmp_path.iterdir()) == []

    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.delenv("CC")
    monkeypatch.setenv("TORCHSURF_NATIVE", "never")
    assert _native.library() is None
    assert "TORCHSURF_NATIVE=never" in _native.unavailable_reason()


def test_the_kernel_is_compiled_into_the_cache_folder_once(monkeypatch, tmp_path,
                                                          native_available):
    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_CACHE_DIR", str(tmp_path / "cache"))
    assert _native.library() is not None
    built = list((tmp_path / "cache").iterdir())
    assert len(built) == 1 and built[0].suffix == ".so"  # no leftover source or folder
    stamp = built[0].stat().st_mtime_ns
    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    assert _native.library() is not None
    assert built[0].stat().st_mtime_ns == stamp


def test_a_compiler_that_refuses_the_vector_flags_builds_it_plainly(monkeypatch, tmp_path,
                                                                     native_available):
    """A wrapper around the C compiler that fails on gcc's x86 flag, as another compiler would."""
    wrapper = tmp_path / "cc"
    wrapper.write_text('#!/bin/sh\nfor a in "$@"; do [ "$a" = -mprefer-vector-width=256 ] && '
                       'exit 1; done\nexec cc "$@"\n')
    wrapper.chmod(0o755)
    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", str(wrapper))
    assert _native.library() is not None
    assert len(list((tmp_path / "cache").iterdir())) == 1


def test_a_compiler_given_with_its_arguments_builds_it(monkeypatch, tmp_path, native_available):
    """``CC="ccache gcc"`` / ``"gcc -std=c11"`` (make's convention) was run as one file name,
    not found, and every C kernel was off without a word."""
    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("CC", "env cc")
    assert _native.library() is not None, _native.unavailable_reason()


def test_a_bad_native_mode_is_named(monkeypatch):
    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_NATIVE", "sometimes")
    with pytest.raises(ValueError, match="TORCHSURF_NATIVE must be one of"):
        _native.library()
    # the reason is given, not raised
    assert "TORCHSURF_NATIVE must be one of" in _native.unavailable_reason()


def test_a_cached_library_cut_short_is_compiled_again(monkeypatch, tmp_path, native_available):
    """Loading a library truncated after it was cached killed the process with SIGBUS."""
    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_CACHE_DIR", str(tmp_path / "cache"))
    assert _native.library() is not None
    (built,) = (tmp_path / "cache").iterdir()
    whole = built.read_bytes()
    built.write_bytes(whole[: len(whole) // 2])
    assert not _whole(built)
    script = ("import torch; from torchsurf.bricks import _native; "
              "assert _native.library() is not None, _native.unavailable_reason()")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                            env={**os.environ, "TORCHSURF_CACHE_DIR": str(tmp_path / "cache")},
                            timeout=300)
    assert result.returncode == 0, (result.returncode, result.stderr[-2000:])
    assert built.read_bytes() == whole or _whole(built)


def test_the_compilers_arguments_name_their_own_build(monkeypatch, tmp_path, native_available):
    """``CC="cc -ffast-math"`` and ``CC=cc`` shared one file: a fast-math build, loaded later
    under plain ``cc``, turned on flush-to-zero for the whole process."""
    monkeypatch.setenv("TORCHSURF_CACHE_DIR", str(tmp_path / "cache"))
    for compiler in ("cc", "cc -std=c11"):
        monkeypatch.setattr(_native.LIBRARY, "_state", {})
        monkeypatch.setenv("CC", compiler)
        assert _native.library() is not None, _native.unavailable_reason()
    assert len(list((tmp_path / "cache").iterdir())) == 2


def test_native_octant_runs_in_parts_on_threads(native_available, monkeypatch):
    """Bricks split between threads give the numbers of one thread, bit for bit."""
    grid = Grid.cube(49, 1.5)
    surface = bricks.from_dense(ts.sdf.sphere(grid, 1.1), grid)
    u = torch.randn(len(surface.layout), 1, 8, 8, 8)
    monkeypatch.setattr(_native, "THREAD_MIN_BRICKS", 8)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        alone = _octant(surface, u, "auto")
        torch.set_num_threads(3)
        assert torch.equal(_octant(surface, u, "auto"), alone)
    finally:
        torch.set_num_threads(threads)


def test_a_compiled_function_on_bricks_gives_the_same_numbers(torus, native_available,
                                                             monkeypatch):
    """While torch.compile traces, the operator leaves the C kernel (a ctypes call) aside."""
    _, surface = torus

    def refused(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("the C kernel was called while torch.compile traced")

    monkeypatch.setattr(bricks.BrickLayout, "native_octant", refused)
    u = torch.randn(len(surface.layout), 1, 8, 8, 8, dtype=torch.float64)
    band = surface.band_mask()
    compiled = torch.compile(lambda v: _octant(surface, v, "auto", band), backend="eager")
    torch.testing.assert_close(compiled(u), _octant(surface, u, "slicing", band), rtol=0,
                               atol=1e-12 * float(_octant(surface, u, "slicing", band).abs().max()))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_band_reads_its_geometry_packed_with_the_numbers_of_the_haloed_planes(
        two_boxes, native_available, dtype, monkeypatch):
    """With a mask the kernel reads the rows it needs from a plan packed once; bit for bit
    what it computes from the haloed planes, on a batch with missing neighbours and odd boxes,
    the packing and the kernel each split between threads."""
    monkeypatch.setattr(_native, "THREAD_MIN_BRICKS", 8)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)   # what in_threads splits by
    _, _, both = two_boxes
    surface = both.to(dtype)
    layout = surface.layout
    u = torch.randn(len(layout), 2, 8, 8, 8, dtype=dtype,
                    generator=torch.Generator().manual_seed(5))
    band = surface.band_mask()
    normal, weight = surface.haloed()
    tables = (layout.neighbours.contiguous(), layout.present.to(torch.uint8).contiguous())
    planes = _native.octant(u, normal, weight, *tables, _native._RowBits(), surface.spacing,
                            False, band)
    plan = _native._GeometryPlan()

    def packed() -> torch.Tensor:
        return _native.octant(u, normal, weight, *tables, _native._RowBits(), surface.spacing,
                              False, band, plan)

    assert torch.equal(packed(), planes) and _kept_plan(plan) is None   # one application: no packing
    assert torch.equal(packed(), planes) and _kept_plan(plan) is not None
    assert torch.equal(packed(), planes)
    offsets, rows = _kept_plan(plan)
    assert len(layout) >= 3 * 8   # three parts, for the packing and for the kernel
    assert offsets.shape == (len(layout) + 1,) and rows.numel() == 40 * int(offsets[-1])
    assert rows.numel() < 0.8 * (normal.numel() + weight.numel())


def test_the_packed_geometry_is_kept_for_the_same_band_and_follows_changes(torus,
                                                                          native_available):
    _, surface = torus
    layout = surface.layout
    u = torch.randn(len(layout), 1, 8, 8, 8, dtype=torch.float64)
    band = surface.band_mask()
    _octant(surface, u, "auto", band)
    first = _octant(surface, u, "auto", band)
    kept = _kept_plan(layout._geometry_plan)[1]
    again = _octant(surface, u, "auto", surface.band_mask())   # a new mask, the same band
    assert _kept_plan(layout._geometry_plan)[1] is kept
    assert torch.equal(again, first)

    narrower = band.clone()
    narrower[:, :, :, ::2] = False
    for _ in range(2):
        assert torch.allclose(_octant(surface, u, "auto", narrower),
                              _octant(surface, u, "slicing", narrower), atol=1e-12)
    assert _kept_plan(layout._geometry_plan) is not None
    assert _kept_plan(layout._geometry_plan)[1] is not kept

    normal, weight = (t.clone() for t in surface.haloed())
    tables = (layout.neighbours.contiguous(), layout.present.to(torch.uint8).contiguous())
    plan, bits = _native._GeometryPlan(), _native._RowBits()

    def octant() -> torch.Tensor:
        return _native.octant(u, normal, weight, *tables, bits, surface.spacing, False, band,
                              plan)

    octant()
    before = octant()
    assert _kept_plan(plan) is not None
    normal[:, :, 5:] = 0.0   # written in place: the plan kept must not be read
    after = octant()
    assert not torch.allclose(after, before)
    assert torch.equal(octant(), after)   # packed again, from the new geometry
    assert _kept_plan(plan) is not None
    fresh = _native.octant(u, normal, weight, *tables, _native._RowBits(), surface.spacing,
                           False, band, None)
    assert torch.equal(after, fresh)


def _kept_plan(plan: _native._GeometryPlan) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The packed rows ``plan`` keeps, or ``None``."""
    return None if plan._kept is None else plan._kept[2]


def test_threads_sharing_a_layout_never_read_one_bands_plan_with_anothers_bits(
        torus, native_available, monkeypatch):
    """Threads applying the kernel to one layout with two bands: the plan's key, bits and
    packed rows were kept apart, and a call for band B landing while band A's rows were packed
    left A's rows kept beside B's bits; B's next call read them (values 17 times the result's
    size, NaN in a flow). Here B's call is made to land inside A's packing, deterministically."""
    _, surface = torus
    layout = surface.layout
    layout._geometry_plan = _native._GeometryPlan()   # nothing kept from other tests
    u = torch.randn(len(layout), 1, 8, 8, 8, dtype=torch.float64)
    wide, narrow = surface.band_mask(), surface.band_mask(1.5 * surface.spacing)
    expected = {id(mask): _octant(surface, u, "slicing", mask) for mask in (wide, narrow)}
    packing_in_threads = _native.in_threads
    interleaved = []

    def with_the_other_band_landing(run, count, least):
        # the first work split over threads that is a packing (the wide band's second call)
        if not interleaved and _kept_plan(layout._geometry_plan) is None and \
                layout._geometry_plan._kept is not None and "pack" in run.__code__.co_freevars:
            interleaved.append(None)
            interleaved[0] = _octant(surface, u, "auto", narrow)
        return packing_in_threads(run, count, least)

    monkeypatch.setattr(_native, "in_threads", with_the_other_band_landing)
    for _ in range(2):
        torch.testing.assert_close(_octant(surface, u, "auto", wide), expected[id(wide)])
    assert interleaved
    for mask in (narrow, narrow, wide, wide, narrow):
        torch.testing.assert_close(_octant(surface, u, "auto", mask), expected[id(mask)])
    torch.testing.assert_close(interleaved[0], expected[id(narrow)])


def test_a_surface_pickles_after_the_kernel_ran_on_a_band(torus, native_available):
    """The row bits and the packed geometry are caches holding weak references: they pickle
    empty and are made again (a surface sent to a DataLoader worker, saved with a model)."""
    import pickle

    _, surface = torus
    u = torch.randn(len(surface.layout), 1, 8, 8, 8, dtype=torch.float64)
    band = surface.band_mask()
    _octant(surface, u, "auto", band)
    expected = _octant(surface, u, "auto", band)
    assert _kept_plan(surface.layout._geometry_plan) is not None
    copied = pickle.loads(pickle.dumps(surface))
    assert _kept_plan(copied.layout._geometry_plan) is None
    for _ in range(2):
        assert torch.equal(_octant(copied, u, "auto", copied.band_mask()), expected)
    assert _kept_plan(copied.layout._geometry_plan) is not None


@pytest.mark.parametrize("cached", ["empty", "another library"])
def test_a_cached_file_that_is_not_the_kernel_is_built_again(monkeypatch, tmp_path, cached,
                                                               native_available):
    """A cached file that failed to load kept the kernel off for good, and one that loaded
    without the kernel's functions raised AttributeError from every operator on bricks."""
    import subprocess

    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_CACHE_DIR", str(tmp_path / "first"))
    assert _native.library() is not None
    (built,) = (tmp_path / "first").iterdir()
    spoilt = tmp_path / "second" / built.name  # a path this process has not loaded
    spoilt.parent.mkdir()
    if cached == "empty":
        spoilt.write_bytes(b"")
    else:
        source = tmp_path / "other.c"
        source.write_text("int other(void) { return 1; }\n")
        subprocess.run(["cc", "-shared", "-fPIC", "-o", str(spoilt), str(source)], check=True)
    monkeypatch.setattr(_native.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_CACHE_DIR", str(spoilt.parent))
    loaded = _native.library()  # no exception: the kernel, or its other paths
    if cached == "empty":  # nothing was loaded from that path: the rebuilt file loads now
        assert loaded is not None
    else:  # the loader keeps the first file opened at a path: the next process reads it
        assert loaded is not None or "does not load" in _native.unavailable_reason()
    assert all(name.encode() in spoilt.read_bytes() for name in _native.LIBRARY._functions)
