"""The compressed-row products' C kernel (:mod:`torchsurf.flows._native_gather`) against dense
matrices: every column width it has a kernel for, both dtypes, gradients of any order, threads,
and the ``embedding_bag`` fallback where it cannot run."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import HeatFlow, _native_gather
from torchsurf.flows._gather_matrix import GatherMatrix


@pytest.fixture(scope="module")
def native_available():
    if _native_gather.LIBRARY.load() is None:
        pytest.skip(f"no C kernel here: {_native_gather.LIBRARY.unavailable_reason()}")


def _matrix(rows: int, columns: int, seed: int) -> tuple[GatherMatrix, torch.Tensor]:
    """Rows of 0 to 30 entries, repeated positions among them; the matrix and its dense form."""
    generator = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 31, (rows,), generator=generator)
    counts[3] = 0
    row = torch.repeat_interleave(torch.arange(rows), counts)
    column = torch.randint(0, columns, (len(row),), generator=generator)
    value = torch.randn(len(row), generator=generator, dtype=torch.float64)
    dense = torch.zeros(rows, columns, dtype=torch.float64).index_put_((row, column), value,
                                                                       accumulate=True)
    return GatherMatrix(row, column, value, (rows, columns)), dense


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_every_width_is_the_dense_product(native_available, dtype, monkeypatch):
    """Widths 1-33 (each one-pass kernel and a second pass) and 67 (three passes)."""
    matrix, dense = _matrix(50, 23, seed=1)
    called = []
    product = _native_gather.product
    monkeypatch.setattr(_native_gather, "product", lambda *a: called.append(1) or product(*a))
    monkeypatch.setitem(_native_gather.MAX_COLUMNS, dtype, 1 << 62)
    tolerance = 1e-13 if dtype == torch.float64 else 2e-5
    for width in [*range(1, 34), 67]:
        x = torch.randn(23, width, dtype=torch.float64)
        torch.testing.assert_close(matrix.apply(x.to(dtype)).double(), dense @ x,
                                   rtol=tolerance, atol=tolerance)
    assert len(called) == 34


def test_a_strided_x_is_read_as_its_values(native_available):
    matrix, dense = _matrix(20, 11, seed=2)
    wide = torch.randn(11, 6, dtype=torch.float64)
    x = wide[:, ::2]
    assert not x.is_contiguous()
    torch.testing.assert_close(matrix.apply(x), dense @ x, rtol=1e-13, atol=1e-13)


def test_gradients_of_first_and_second_order(native_available):
    matrix, _ = _matrix(17, 13, seed=3)
    x = torch.randn(13, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(matrix.apply, (x,))
    assert torch.autograd.gradgradcheck(matrix.apply, (x,))


def test_rows_split_between_threads_give_one_threads_numbers(native_available, monkeypatch):
    matrix, _ = _matrix(400, 90, seed=4)
    x = torch.randn(90, 5)
    monkeypatch.setattr(_native_gather, "THREAD_MIN_ROWS", 16)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        alone = matrix.apply(x)
        torch.set_num_threads(3)
        assert torch.equal(matrix.apply(x), alone)
    finally:
        torch.set_num_threads(threads)


def test_without_the_kernel_embedding_bag_gives_the_numbers(monkeypatch, tmp_path):
    matrix, dense = _matrix(30, 12, seed=5)
    x = torch.randn(12, 4, dtype=torch.float64, requires_grad=True)
    monkeypatch.setattr(_native_gather.LIBRARY, "_state", {})
    monkeypatch.setenv("TORCHSURF_NATIVE", "never")
    assert not _native_gather.applies(matrix.offsets, x)
    assert "TORCHSURF_NATIVE=never" in _native_gather.LIBRARY.unavailable_reason()
    torch.testing.assert_close(matrix.apply(x), dense @ x, rtol=1e-13, atol=1e-13)
    assert torch.autograd.gradcheck(matrix.apply, (x,))


def test_wide_float32_data_is_left_to_embedding_bag(native_available):
    matrix, _ = _matrix(10, 7, seed=6)
    narrow, wide = torch.randn(7, 16), torch.randn(7, 17)
    assert _native_gather.applies(matrix.offsets, narrow)
    assert not _native_gather.applies(matrix.offsets, wide)
    assert _native_gather.applies(matrix.offsets, wide.double())


def _packed_stencil():
    """A sphere's packed region and its band's limited closest-point stencil (a flow's)."""
    grid = ts.Grid.cube(15, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0, dtype=torch.float64), grid)
    flow = HeatFlow(2 * surface.spacing**2, reextend_every=1)
    flow(torch.rand(1, 1, *grid.shape, dtype=torch.float64), surface)
    packing = next(v for k, v in surface._kept.items() if k[0] == "packed region")
    return packing, next(iter(packing._stencils.values()))[1]


def test_the_packed_stencils_clamp_keeps_nans_as_torch_does(native_available, monkeypatch):
    """A NaN at a cell's node or among the taps stays NaN in the re-extended value, with the C
    clamp as with ``aminmax``."""
    packing, stencil = _packed_stencil()
    z = torch.rand(len(packing.nodes), 1, 2, dtype=torch.float64)
    z[int(stencil.taps[0, 21]), 0, 1] = float("nan")  # a node of the first target's cell
    native = stencil.apply(z)
    monkeypatch.setattr(_native_gather, "limited", lambda *args: None)
    expected = stencil.apply(z)
    assert torch.equal(torch.isnan(native), torch.isnan(expected))
    assert bool(torch.isnan(native).any())
    torch.testing.assert_close(native.nan_to_num(), expected.nan_to_num(), rtol=1e-15,
                               atol=1e-15)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_one_column_by_row_blocks_reads_no_padding(native_available, dtype):
    """Rows of 0-30 entries in blocks of 8 (the last block partial): a row shorter than its
    block's longest never reads the padded slots, so an infinite value of ``x`` reaches only
    the rows that read it, as in a row-by-row product."""
    matrix, dense = _matrix(61, 19, seed=7)
    x = torch.randn(19, 1, dtype=torch.float64)
    x[0] = float("inf")  # the padded slots' column
    out = matrix.apply(x.to(dtype)).double()
    assert matrix._blocks is not None
    reads = dense[:, 0] != 0
    assert bool(reads.any()) and bool((~reads).any())
    assert not bool(torch.isfinite(out[reads]).any())
    finite = x.clone()
    finite[0] = 0.0
    tolerance = 1e-13 if dtype == torch.float64 else 2e-5
    torch.testing.assert_close(out[~reads], (dense @ finite)[~reads], rtol=tolerance,
                               atol=tolerance)
    assert matrix.nbytes() > 4 * len(matrix._blocks.columns)
    other = torch.float32 if dtype == torch.float64 else torch.float64  # the layout's 2nd dtype
    torch.testing.assert_close(matrix.apply(finite.to(other)).double(), dense @ finite,
                               rtol=2e-5, atol=2e-5)


def test_the_packed_stencils_gradient_is_torchs_and_passes_gradcheck(native_available,
                                                                     monkeypatch):
    """Rough data (many values clamped): the C clamp's recorded codes give the gradient of
    autograd through torch's clamp (no ties in random data), and gradcheck holds."""
    packing, stencil = _packed_stencil()
    generator = torch.Generator().manual_seed(8)
    z = torch.rand(len(packing.nodes), 1, 3, dtype=torch.float64, generator=generator)
    g = torch.randn(z.shape, dtype=torch.float64, generator=generator)
    grads = []
    for native in (True, False):
        with monkeypatch.context() as patch:
            if not native:
                patch.setattr(_native_gather, "limited", lambda *args: None)
            x = z.clone().requires_grad_()
            out = stencil.apply(x)
            grads.append(torch.autograd.grad((out * g).sum(), x)[0])
    flat = z.reshape(z.shape[0], -1)
    written = stencil.apply(z).reshape(flat.shape)[stencil.rows]
    assert int((written != stencil.matrix.apply(flat)).sum()) > 10  # the clamp's gradients
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-13, atol=1e-13)
    small = z[:, :, :1].clone().requires_grad_()
    assert torch.autograd.gradcheck(stencil.apply, (small,), eps=1e-7, atol=1e-6)


def test_the_packed_stencils_values_stay_within_the_datas_range(native_available, monkeypatch):
    """0/1 data in float32, 1 at 90% of the nodes: where the cubic overshoots 1 the bounds
    ``sum_c lambda_c 1`` are formed, and their rounding (weights summing to ``1 +- ulp``) left
    values an ulp above 1, a new extremum; by the C kernel and by torch."""
    packing, stencil = _packed_stencil()
    generator = torch.Generator().manual_seed(9)
    z = (torch.rand(len(packing.nodes), 1, 8, generator=generator) < 0.9).float()
    assert float(stencil.matrix.apply(z.reshape(len(z), -1)).max()) > 1.01
    for native in (True, False):
        with monkeypatch.context() as patch:
            if not native:
                patch.setattr(_native_gather, "limited", lambda *args: None)
            value = stencil.apply(z)
        assert float(value.max()) <= 1.0 and float(value.min()) >= 0.0, native


needs_custom_ops = pytest.mark.skipif(not _native_gather.TRACEABLE,
                                      reason="torch.library.custom_op needs torch >= 2.4")


@needs_custom_ops
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_custom_operators_pass_opcheck(native_available, dtype):
    """``torch.library.opcheck``: schemas, fake (meta) results of the kernels' shapes and
    strides, autograd registration, and the ops traced by ``make_fx`` as called eagerly."""
    matrix, _ = _matrix(29, 13, seed=11)
    offsets, columns, values = matrix.offsets, matrix.columns, matrix.values(dtype)
    x = torch.randn(13, 3, dtype=dtype, requires_grad=True)
    one = torch.randn(13, 1, dtype=dtype, requires_grad=True)
    blocks = _native_gather.RowBlocks(offsets, columns, values).laid(dtype)
    g = torch.randn(29, 2, dtype=dtype, requires_grad=True)
    ops = torch.ops.torchsurf
    torch.library.opcheck(ops.csr_product, (offsets, columns, values, x, 29, []))
    torch.library.opcheck(ops.csr_product, (offsets, columns, values, one, 29, blocks))
    torch.library.opcheck(ops.csr_scatter, (offsets, columns, values, g, 13))
    packing, stencil = _packed_stencil()
    z = torch.rand(len(packing.nodes), 3, dtype=dtype, requires_grad=True,
                   generator=torch.Generator().manual_seed(12))
    args = (z, stencil.matrix.offsets, stencil.matrix.columns, stencil.matrix.values(dtype),
            stencil.taps, stencil.corners.to(dtype), stencil.rows)
    torch.library.opcheck(ops.limited, args)


@needs_custom_ops
def test_a_compiled_packed_stencil_calls_the_kernels_and_gives_their_numbers(native_available):
    """Traced by ``torch.compile`` the clamped re-extension and the products are the custom
    operators (not inductor's gathers): the eager values and gradients, float64."""
    packing, stencil = _packed_stencil()
    z = torch.rand(len(packing.nodes), 1, 2, dtype=torch.float64,
                   generator=torch.Generator().manual_seed(13))
    g = torch.randn(z.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(14))

    def value_and_grad(function):
        x = z.clone().requires_grad_()
        out = function(x)
        return out.detach(), torch.autograd.grad((out * g).sum(), x)[0]

    expected = value_and_grad(stencil.apply)
    torch._dynamo.reset()
    try:
        explanation = torch._dynamo.explain(stencil.apply)(z)
        compiled = value_and_grad(torch.compile(stencil.apply, fullgraph=True))
    finally:
        torch._dynamo.reset()
    called = {str(node.target) for graph in explanation.graphs for node in graph.graph.nodes}
    assert any("torchsurf.limited" in target for target in called), sorted(called)
    torch.testing.assert_close(compiled, expected, rtol=1e-12, atol=1e-12)


def test_row_blocks_laid_out_in_chunks_equal_the_whole_layout(monkeypatch):
    """:class:`~torchsurf.flows._native_gather.RowBlocks` lays out ``LAYOUT_ROWS`` rows at a
    time (its int64 positions of every entry at once had been the 256^3 bunny heat flow's
    peak, 2.4 GB): chunks that split blocks of 8 and rows of 0 entries give the same layout."""
    matrix, _ = _matrix(50, 23, seed=5)
    offsets, columns, values = matrix.offsets, matrix.columns, matrix.values(torch.float64)
    whole = _native_gather.RowBlocks(offsets, columns, values)
    monkeypatch.setattr(_native_gather, "LAYOUT_ROWS", 3)
    chunked = _native_gather.RowBlocks(offsets, columns, values)
    for a, b in zip(whole.tensors(), chunked.tensors(), strict=True):
        assert torch.equal(a, b)
    assert len(whole.tensors()) >= 4
    # the layout's slots hold every entry: the dense product through it is the matrix's
    x = torch.randn(23, 1, dtype=torch.float64)
    if _native_gather.LIBRARY.load() is not None:
        assert torch.allclose(_native_gather.product(offsets, columns, values, x, 50, chunked),
                              matrix.apply(x))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("columns", [1, 3, 8])
@pytest.mark.parametrize("scattered_share", [1 / 3, 2 / 3])
def test_separable_stencils_one_pass_is_the_product_and_clamp(native_available, dtype,
                                                              columns, scattered_share,
                                                              monkeypatch):
    """A limited tricubic stencil by its separable layouts against the compressed-row product
    and the clamp: rows whose taps lie 4 by 4 side by side (runs) mixed with rows whose taps do
    not (blocks of 8, the last one partial), one to eight columns, rough data (values clamped),
    a subset of the nodes as targets; the other nodes are copied. Several columns take the
    layouts only where most rows lie in runs."""
    from torchsurf.flows import _limiter
    from torchsurf.flows.extension import tap_weights

    generator = torch.Generator().manual_seed(21)
    nodes, count = 300, 45
    starts = torch.randint(0, nodes - 4, (count, 16), generator=generator)
    taps = (starts[:, :, None] + torch.arange(4)).reshape(count, 64)
    scattered = torch.arange(count) % 3 < round(3 * scattered_share)
    taps[scattered] = torch.randint(0, nodes, (int(scattered.sum()), 64), generator=generator)
    taps = taps.to(torch.int32)
    fractions = torch.rand(3, count, generator=generator, dtype=torch.float64)
    t = fractions[..., None]
    axes = torch.cat([-t * (1 - t) ** 2 / 2, (2 - 5 * t**2 + 3 * t**3) / 2,
                      t * (1 + 4 * t - 3 * t**2) / 2, -(t**2) * (1 - t) / 2], dim=-1)
    weights = tap_weights(axes)
    corners = _limiter.corner_weights_of_taps(weights)
    rows = torch.randperm(nodes, generator=generator)[:count]
    matrix = GatherMatrix.of_rows(taps.long(), weights, nodes)
    stencil = _native_gather.SeparableStencil(taps, axes, corners, rows)
    z = torch.rand(nodes, columns, generator=generator, dtype=torch.float64).to(dtype)
    taken = columns == 1 or stencil.runs_share >= _native_gather.RUNS_SHARE
    assert (stencil.parts(columns, dtype) is not None) == taken
    monkeypatch.setattr(_native_gather, "RUNS_SHARE", 0.0)  # the layouts whatever the share
    one_pass = _native_gather._limited_separable(z, stencil)
    names = [name for name, _, _ in stencil.parts(columns, dtype)]
    assert names == ["limited_runs", "limited_tricubic"]
    two_passes = _native_gather.limited(z, matrix, taps, corners.to(dtype), rows)
    clamped = one_pass[rows] != matrix.apply(z)
    assert int(clamped.sum()) > 5
    tolerance = 1e-14 if dtype == torch.float64 else 2e-6
    torch.testing.assert_close(one_pass, two_passes, rtol=tolerance, atol=tolerance)
    others = torch.ones(nodes, dtype=torch.bool)
    others[rows] = False
    assert torch.equal(one_pass[others], z[others])
