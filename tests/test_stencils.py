"""Finite-difference stencils: exactness on polynomials, the two paths, padding, adjointness."""

import pytest
import torch

from torchsurf import stencils

PATHS = ["slicing", "conv3d"]
SHAPE = (5, 6, 7)  # D, H, W: unequal so that an axis mix-up cannot go unnoticed


def _index_coordinates(shape=SHAPE, dtype=torch.float64):
    """``x, y, z`` in index units (``x = i`` along W, ``y = j`` along H, ``z = k`` along D)."""
    z, y, x = torch.meshgrid(*(torch.arange(n, dtype=dtype) for n in shape), indexing="ij")
    return x, y, z


class Quadratic:
    """``u = c0 + g . x + x^T A x / 2`` with fixed random coefficients, and its exact derivatives."""

    def __init__(self, generator):
        self.c0 = torch.randn((), generator=generator, dtype=torch.float64)
        self.g = torch.randn(3, generator=generator, dtype=torch.float64)
        a = torch.randn(3, 3, generator=generator, dtype=torch.float64)
        self.a = a + a.T

    def __call__(self, x, y, z):
        p = torch.stack((x, y, z), -1)
        return self.c0 + p @ self.g + 0.5 * ((p @ self.a) * p).sum(-1)

    def gradient(self, x, y, z):
        """``(3, ...)`` exact gradient at ``(x, y, z)``."""
        p = torch.stack((x, y, z), -1)
        return (self.g + p @ self.a).movedim(-1, 0)


def _interior(volume):
    return volume[..., 1:-1, 1:-1, 1:-1]


@pytest.mark.parametrize("path", PATHS)
def test_central_second_mixed_exact_for_quadratics(path, generator):
    u = Quadratic(generator)
    x, y, z = _index_coordinates()
    padded = stencils.pad(u(x, y, z)[None, None], "replicate")
    central = stencils.apply(padded, stencils.CENTRAL, path=path)[0, 0]
    torch.testing.assert_close(_interior(central), _interior(u.gradient(x, y, z)),
                               rtol=0, atol=1e-12)
    hessian = stencils.apply(padded, stencils.HESSIAN, path=path)[0, 0]
    a = u.a
    expected = [a[0, 0], a[1, 1], a[2, 2], a[0, 1], a[0, 2], a[1, 2]]  # xx yy zz xy xz yz
    for k, value in enumerate(expected):
        torch.testing.assert_close(_interior(hessian[k]), torch.full((3, 4, 5), float(value),
                                   dtype=torch.float64), rtol=0, atol=1e-12)


@pytest.mark.parametrize("path", PATHS)
def test_one_sided_exact_at_half_nodes(path, generator):
    """``D+ u[i] = u'(i + 1/2)`` and ``D- u[i] = u'(i - 1/2)`` exactly for quadratics."""
    u = Quadratic(generator)
    x, y, z = _index_coordinates()
    padded = stencils.pad(u(x, y, z)[None, None], "replicate")
    for side in (1, -1):
        differences = stencils.apply(padded, stencils.one_sided(side), path=path)[0, 0]
        for axis in range(3):
            shifted = [x, y, z]
            shifted[axis] = shifted[axis] + 0.5 * side
            expected = u.gradient(*shifted)[axis]
            torch.testing.assert_close(_interior(differences[axis]), _interior(expected),
                                       rtol=0, atol=1e-12)


@pytest.mark.parametrize("path", PATHS)
def test_one_sided_exact_for_affine(path, generator):
    g = torch.randn(3, generator=generator, dtype=torch.float64)
    x, y, z = _index_coordinates()
    padded = stencils.pad((0.3 + g[0] * x + g[1] * y + g[2] * z)[None, None], "linear")
    for bank in (stencils.FORWARD, stencils.BACKWARD, stencils.CENTRAL):
        differences = stencils.apply(padded, bank, path=path)[0, 0]
        for axis in range(3):
            # linear padding makes the differences exact on the boundary too
            torch.testing.assert_close(differences[axis], torch.full(SHAPE, float(g[axis]),
                                       dtype=torch.float64), rtol=0, atol=1e-12)


def test_bank_names_and_order():
    assert [s.name for s in stencils.FORWARD] == ["forward_x", "forward_y", "forward_z"]
    assert [s.name for s in stencils.HESSIAN] == [
        "second_xx", "second_yy", "second_zz", "mixed_xy", "mixed_xz", "mixed_yz"
    ]
    assert stencils.one_sided(1) == stencils.FORWARD
    assert stencils.one_sided(-1) == stencils.BACKWARD
    kernel = stencils.CENTRAL[0].kernel(dtype=torch.float64)
    expected = torch.zeros(3, 3, 3, dtype=torch.float64)
    expected[1, 1, 2], expected[1, 1, 0] = 0.5, -0.5  # x runs along the last axis (W)
    assert torch.equal(kernel, expected)
    for bank in (stencils.FORWARD, stencils.BACKWARD, stencils.CENTRAL, stencils.HESSIAN):
        for stencil in bank:  # derivatives of constants vanish
            assert float(stencil.kernel(dtype=torch.float64).sum()) == 0.0


@pytest.mark.parametrize("side", [0, 2, -2])
def test_one_sided_rejects_bad_side(side):
    with pytest.raises(ValueError, match="side"):
        stencils.one_sided(side)
    with pytest.raises(ValueError, match="side"):
        stencils.pad_flux(torch.zeros(1, 1, 3, 3, 3, 3), side)


BANKS = {
    "forward": stencils.FORWARD,
    "backward": stencils.BACKWARD,
    "central": stencils.CENTRAL,
    "hessian": stencils.HESSIAN,
}


@pytest.mark.parametrize("bank", BANKS.values(), ids=BANKS.keys())
def test_apply_paths_agree(bank, generator):
    padded = torch.randn(2, 3, 7, 8, 9, generator=generator, dtype=torch.float64)
    sliced = stencils.apply(padded, bank, path="slicing")
    convolved = stencils.apply(padded, bank, path="conv3d")
    assert sliced.shape == (2, 3, len(bank), 5, 6, 7)
    torch.testing.assert_close(convolved, sliced, rtol=0, atol=1e-13)
    torch.testing.assert_close(stencils.apply(padded, bank), sliced, rtol=0, atol=0)


@pytest.mark.parametrize("bank", BANKS.values(), ids=BANKS.keys())
def test_contract_paths_agree(bank, generator):
    padded = torch.randn(2, 3, len(bank), 7, 8, 9, generator=generator, dtype=torch.float64)
    sliced = stencils.contract(padded, bank, path="slicing")
    convolved = stencils.contract(padded, bank, path="conv3d")
    assert sliced.shape == (2, 3, 5, 6, 7)
    torch.testing.assert_close(convolved, sliced, rtol=0, atol=1e-13)
    expected = sum(
        stencils.apply(padded[:, :, k], [stencil], path="slicing")[:, :, 0]
        for k, stencil in enumerate(bank)
    )
    torch.testing.assert_close(sliced, expected, rtol=0, atol=1e-13)


def test_invalid_path():
    with pytest.raises(ValueError, match="path"):
        stencils.apply(torch.zeros(1, 1, 3, 3, 3), stencils.CENTRAL, path="fft")
    with pytest.raises(ValueError, match="path"):
        stencils.contract(torch.zeros(1, 1, 3, 3, 3, 3), stencils.CENTRAL, path="fft")


def test_pad_replicate_and_zeros(generator):
    volume = torch.randn(2, 3, *SHAPE, generator=generator, dtype=torch.float64)
    replicated = stencils.pad(volume, "replicate")
    assert replicated.shape == (2, 3, 7, 8, 9)
    assert torch.equal(_interior(replicated), volume)
    assert torch.equal(replicated[..., 0, 1:-1, 1:-1], volume[..., 0, :, :])
    assert torch.equal(replicated[..., 1:-1, -1, 1:-1], volume[..., :, -1, :])
    assert torch.equal(replicated[..., 1:-1, 1:-1, 0], volume[..., :, :, 0])
    assert torch.equal(replicated[..., 0, 0, 0], volume[..., 0, 0, 0])
    assert torch.equal(replicated[..., -1, -1, -1], volume[..., -1, -1, -1])
    zeros = stencils.pad(volume, "zeros")
    assert torch.equal(_interior(zeros), volume)
    halo = torch.ones_like(zeros, dtype=torch.bool)
    halo[..., 1:-1, 1:-1, 1:-1] = False
    assert bool((zeros[halo] == 0).all())
    assert torch.equal(stencils.pad(volume), replicated)  # replicate is the default


def test_pad_linear_exact_for_affine(generator):
    g = torch.randn(3, generator=generator, dtype=torch.float64)
    x, y, z = _index_coordinates((SHAPE[0] + 2, SHAPE[1] + 2, SHAPE[2] + 2))
    affine = 0.7 + g[0] * (x - 1) + g[1] * (y - 1) + g[2] * (z - 1)  # index -1 .. n
    padded = stencils.pad(_interior(affine)[None, None], "linear")
    # every halo node, faces, edges and corners, holds the affine field's value
    torch.testing.assert_close(padded[0, 0], affine, rtol=0, atol=1e-12)


def test_pad_quadratic_exact_for_quadratics(generator):
    c = torch.randn(10, generator=generator, dtype=torch.float64)
    x, y, z = (a - 1 for a in _index_coordinates((SHAPE[0] + 2, SHAPE[1] + 2, SHAPE[2] + 2)))
    quadratic = (c[0] + c[1] * x + c[2] * y + c[3] * z + c[4] * x * x + c[5] * y * y + c[6] * z * z
                 + c[7] * x * y + c[8] * x * z + c[9] * y * z)
    padded = stencils.pad(_interior(quadratic)[None, None], "quadratic")
    torch.testing.assert_close(padded[0, 0], quadratic, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="at least 3 nodes"):
        stencils.pad(torch.zeros(1, 1, 3, 2, 3), "quadratic")


def test_pad_invalid_mode():
    with pytest.raises(ValueError, match="mode"):
        stencils.pad(torch.zeros(1, 1, 3, 3, 3), "reflect")


@pytest.mark.parametrize("side", [1, -1])
def test_pad_flux_layout(side, generator):
    flux = torch.randn(2, 1, 3, *SHAPE, generator=generator, dtype=torch.float64)
    padded = stencils.pad_flux(flux, side)
    assert padded.shape == (2, 1, 3, 7, 8, 9)
    inner = _interior(padded)
    # the face beyond the box (side +1: after the last node; -1: before the first) is zeroed
    dropped = -1 if side == 1 else 0
    for axis in range(3):
        dim = -1 - axis
        kept = inner[:, :, axis].clone()
        original = flux[:, :, axis].clone()
        assert bool((kept.select(dim, dropped) == 0).all())
        kept.select(dim, dropped).zero_()
        original.select(dim, dropped).zero_()
        assert torch.equal(kept, original)
    halo = torch.ones_like(padded, dtype=torch.bool)
    halo[..., 1:-1, 1:-1, 1:-1] = False
    assert bool((padded[halo] == 0).all())


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("side", [1, -1])
def test_pad_flux_divergence_is_negative_adjoint(side, path, generator):
    """``<D_side u, f> = -<u, D_-side . pad_flux(f)>`` for every u and f: summation by parts."""
    u = torch.randn(2, 3, *SHAPE, generator=generator, dtype=torch.float64)
    f = torch.randn(2, 3, 3, *SHAPE, generator=generator, dtype=torch.float64)
    gradient = stencils.apply(stencils.pad(u, "replicate"), stencils.one_sided(side), path=path)
    divergence = stencils.contract(stencils.pad_flux(f, side), stencils.one_sided(-side),
                                   path=path)
    lhs = (gradient * f).sum()
    rhs = -(u * divergence).sum()
    torch.testing.assert_close(lhs, rhs, rtol=1e-13, atol=1e-12)
    assert abs(float(lhs)) > 1.0  # not a trivially vanishing pairing


@pytest.mark.parametrize("side", [1, -1])
def test_pad_flux_divergence_matches_autograd_adjoint(side, generator):
    """The same identity seen through autograd: the transpose of the gradient is -divergence."""
    u = torch.randn(1, 2, *SHAPE, generator=generator, dtype=torch.float64, requires_grad=True)
    f = torch.randn(1, 2, 3, *SHAPE, generator=generator, dtype=torch.float64)
    gradient = stencils.apply(stencils.pad(u, "replicate"), stencils.one_sided(side))
    (transpose,) = torch.autograd.grad(gradient, u, grad_outputs=f)
    divergence = stencils.contract(stencils.pad_flux(f, side), stencils.one_sided(-side))
    torch.testing.assert_close(transpose, -divergence, rtol=0, atol=1e-12)


def test_pad_mirrored_negates_the_component_normal_to_each_face(generator):
    field = torch.randn(2, 3, 4, 5, 6, dtype=torch.float64, generator=generator)
    padded = stencils.pad_mirrored(field)
    assert padded.shape == (2, 3, 6, 7, 8)
    torch.testing.assert_close(padded[..., 1:-1, 1:-1, 1:-1], field)
    for axis in range(3):
        dim = 4 - axis  # x varies along the last dimension
        for halo, edge in ((0, 0), (-1, -1)):
            index = [slice(None), slice(None), slice(1, -1), slice(1, -1), slice(1, -1)]
            index[dim] = halo
            inside = [slice(None)] * 5
            inside[dim] = edge
            sign = torch.ones(3, dtype=field.dtype)
            sign[axis] = -1.0
            expected = sign.view(1, 3, 1, 1) * field[tuple(inside)]
            torch.testing.assert_close(padded[tuple(index)], expected)


def test_the_padding_and_application_steps_refuse_other_layouts_naming_the_argument():
    """pad_mirrored kept 3 of two vector fields' 6 channels and pad_flux 3 of 5 components,
    silently; the others failed inside torch, naming nothing (an audit)."""
    volume = torch.rand(1, 6, 5, 5, 5, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"^field must be \(B, 3, D, H, W\), got shape "
                                         r"\(1, 6, 5, 5, 5\)"):
        stencils.pad_mirrored(volume)
    with pytest.raises(ValueError, match=r"^field must be \(B, 3, D, H, W\), got shape "
                                         r"\(3, 5, 5, 5\)"):
        stencils.pad_mirrored(volume[0, :3])
    with pytest.raises(ValueError, match=r"^flux must be \(B, C, 3, D, H, W\), got shape "
                                         r"\(1, 1, 5, 5, 5, 5\)"):
        stencils.pad_flux(volume[:, None, :5], 1)
    with pytest.raises(ValueError, match=r"^flux must be .* got shape \(1, 3, 6, 6, 6\)"):
        stencils.pad_flux(torch.rand(1, 3, 6, 6, 6), 1)
    with pytest.raises(ValueError, match=r"^volume must be \(B, C, D, H, W\) with at least 2 "
                                         r"nodes a side, got shape \(1, 1, 1, 4, 4\)"):
        stencils.pad(torch.rand(1, 1, 1, 4, 4), "linear")
    with pytest.raises(ValueError, match=r"^volume must be \(B, C, D, H, W\), got shape "
                                         r"\(4, 4, 4\)"):
        stencils.pad(torch.rand(4, 4, 4))
    with pytest.raises(TypeError, match=r"^padded must be a floating-point tensor .* got dtype "
                                        r"torch.int64"):
        stencils.apply(torch.ones(1, 1, 5, 5, 5, dtype=torch.long), stencils.CENTRAL, "conv3d")
    with pytest.raises(ValueError, match=r"^padded must be \(B, C, 3, D \+ 2, H \+ 2, W \+ 2\) "
                                         r"for a bank of 3 stencils"):
        stencils.contract(torch.rand(1, 1, 2, 5, 5, 5), stencils.CENTRAL)
    # the layouts they document still run, and a mask pads as before (a review)
    assert stencils.pad(torch.ones(1, 1, 3, 3, 3, dtype=torch.bool), "zeros").shape == (1, 1, 5, 5, 5)
    assert stencils.pad(torch.ones(1, 1, 3, 3, 3, dtype=torch.long)).dtype == torch.long
    # what cannot pad is named: a mask replicated, integers extrapolated (they came back float32),
    # unsigned components mirrored (-1 wrapped to 255)
    with pytest.raises(TypeError, match=r"^volume is a bool mask, which pads with mode='zeros'"):
        stencils.pad(torch.ones(1, 1, 3, 3, 3, dtype=torch.bool))
    with pytest.raises(TypeError, match=r"^volume must be a floating-point tensor"):
        stencils.pad(torch.ones(1, 1, 3, 3, 3, dtype=torch.long), "linear")
    with pytest.raises(TypeError, match=r"^field must hold signed numbers"):
        stencils.pad_mirrored(torch.ones(1, 3, 3, 3, 3, dtype=torch.uint8))
    assert stencils.pad_mirrored(volume[:, :3]).shape == (1, 3, 7, 7, 7)
    assert stencils.contract(torch.rand(1, 2, 3, 5, 5, 5), stencils.CENTRAL).shape == (1, 2, 3, 3, 3)


@pytest.mark.parametrize("shape", [(5, 6, 7), (3, 3, 3), (1, 4, 4), (2, 2, 9)])
def test_box_neighbours_equal_the_clamped_neighbours(shape):
    """:class:`BoxNeighbours`' shortcut (no node on a face) and its fallback give what
    ``neighbour_in_box`` and ``neighbourhood_column`` give, node by node."""
    from torchsurf.stencils import (
        NEIGHBOURHOOD,
        BoxNeighbours,
        neighbour_in_box,
        neighbourhood_column,
    )

    z, y, x = torch.meshgrid(*(torch.arange(n) for n in shape), indexing="ij")
    every = [a.reshape(-1) for a in (z, y, x)]
    inner = [a[1:-1, 1:-1, 1:-1].reshape(-1) for a in (z, y, x)]
    for at in (every, inner):
        box = BoxNeighbours(at, shape)
        for offset in NEIGHBOURHOOD:
            flat, beyond = neighbour_in_box(at, offset, shape)
            mine, my_beyond = box.neighbour(offset)
            assert torch.equal(mine, flat)
            column = box.column(offset)
            expected = neighbourhood_column(offset, beyond)
            if my_beyond is None:
                assert not any(bool(b.any()) for b in beyond)
                assert bool((expected == column).all())
            else:
                assert all(torch.equal(a, b) for a, b in zip(my_beyond, beyond, strict=True))
                assert torch.equal(column, expected)
