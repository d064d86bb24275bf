"""Gershgorin bounds of the assembled operators, by colour probing."""

from __future__ import annotations

import warnings

import pytest
import torch

import torchsurf as ts
from torchsurf.operators.spectrum import (
    gershgorin_bound,
    laplace_beltrami_bound,
    laplace_beltrami_rows,
)
from torchsurf.stencils import NEIGHBOURHOOD


def dense_matrix(operator, mask: torch.Tensor) -> torch.Tensor:
    """The operator restricted to ``mask``, assembled column by column (the plain reference)."""
    nodes = mask.flatten().nonzero().squeeze(1)
    columns = []
    for node in nodes:
        probe = torch.zeros(mask.numel(), dtype=torch.float64)
        probe[node] = 1.0
        columns.append(operator(probe.view(mask.shape)).flatten()[nodes])
    return torch.stack(columns, dim=1)


@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative", "central"])
def test_probing_gives_the_exact_largest_row_sum(scheme):
    grid = ts.Grid.cube(11, 1.5)
    phi = ts.sdf.torus(grid, 0.9, 0.4, dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid)
    mask = surface.band_mask()

    def operator(x):
        return torch.where(mask, ts.laplace_beltrami(torch.where(mask, x, 0.0), surface, scheme), 0.0)

    matrix = dense_matrix(operator, mask)
    expected = float(matrix.abs().sum(dim=1).max())
    assert gershgorin_bound(operator, mask, torch.float64) == pytest.approx(expected, rel=1e-12)
    # a bound of the spectrum: every eigenvalue lies within it
    assert float(torch.linalg.eigvals(matrix).abs().max()) <= expected * (1 + 1e-12)


def test_bound_is_near_twelve_over_h_squared_on_a_distance_function():
    grid = ts.Grid.cube(33, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    h2 = grid.spacing**2
    assert 9.5 < laplace_beltrami_bound(surface, "octant") * h2 < 12.5
    assert 12.0 < laplace_beltrami_bound(surface, "symmetric") * h2 < 13.5


def test_bound_is_kept_per_surface_and_follows_the_scale_of_phi_not():
    grid = ts.Grid.cube(25, 1.5)
    phi = ts.sdf.sphere(grid, dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid)
    first = laplace_beltrami_bound(surface)
    assert laplace_beltrami_bound(surface) == first
    scaled = ts.ImplicitSurface(1000 * phi, grid)
    assert laplace_beltrami_bound(scaled) == pytest.approx(first, rel=1e-9)


def test_floored_weight_bounds_the_operator_at_thin_features():
    """A trefoil tube of 0.2 at 64^3 has nodes with |grad phi| = 0.13 in its band (the knot's
    strands come close): the floored weight keeps the bound within 1.55x of a distance's
    (15.2 / h^2 measured; 31.5 / h^2 with W = |grad phi| unfloored)."""
    grid = ts.Grid.cube(64, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.trefoil(grid, tube_radius=0.2), grid)
    assert float(surface.grad_norm[surface.band_mask()].min()) < 0.3
    assert laplace_beltrami_bound(surface) * grid.spacing**2 < 1.55 * 10.0


def test_a_wild_bound_names_phi():
    """One sentinel value of -1e9 inside a sphere raised the bound to about 6e9 / h^2, and the
    flows' refusals blamed the time's units; the bound warns naming phi, once per surface."""
    grid = ts.Grid.cube(17, bound=1.5)
    phi = ts.sdf.sphere(grid, radius=0.5)
    surface = ts.ImplicitSurface(phi, grid)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        laplace_beltrami_bound(surface)
    wild = phi.clone()
    wild[0, 0, 8, 8, 8] = -1e9
    surface = ts.ImplicitSurface(wild, grid)
    with pytest.warns(RuntimeWarning, match=r"phi: the Laplace–Beltrami operator's bound .*e\+09"):
        laplace_beltrami_bound(surface)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        laplace_beltrami_bound(surface)  # kept: said once


def test_directional_bound_is_the_largest_row_sum_of_the_directional_operator():
    from torchsurf import bricks
    from torchsurf.operators import directional_bound, directional_diffusion
    from torchsurf.surface import tangent_unit

    grid = ts.Grid.cube(11, 1.5)
    phi = ts.sdf.torus(grid, 0.9, 0.4, dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid)
    mask = surface.band_mask()
    generator = torch.Generator().manual_seed(3)
    direction = tangent_unit(torch.randn(1, 3, 11, 11, 11, generator=generator,
                                         dtype=torch.float64), surface)

    def operator(x):
        inside = torch.where(mask, x, 0.0)
        return torch.where(mask, directional_diffusion(inside, surface, direction), 0.0)

    matrix = dense_matrix(operator, mask)
    expected = float(matrix.abs().sum(dim=1).max())
    assert directional_bound(surface, direction) == pytest.approx(expected, rel=1e-12)
    assert float(torch.linalg.eigvals(matrix).abs().max()) <= expected * (1 + 1e-12)
    # one direction carries about half Laplace-Beltrami's coefficients
    assert expected < laplace_beltrami_bound(surface, "symmetric")

    big = ts.Grid.cube(24, 2.2)
    dense = ts.ImplicitSurface(ts.sdf.torus(big, 0.9, 0.4, dtype=torch.float64), big)
    field = dense.principal_directions()[0]
    packed = bricks.from_dense(dense)
    assert directional_bound(packed, packed.from_dense(field)) == pytest.approx(
        directional_bound(dense, field), rel=1e-9)


def _cut_ellipsoids() -> ts.ImplicitSurface:
    """A batch of two ``phi`` that are not distances (a quadric times a varying factor), in a
    box of three different sides that cuts both surfaces."""
    grid = ts.Grid((7, 9, 8), 0.3, (-1.0, -1.3, -0.9))
    x, y, z = grid.points(dtype=torch.float64).unbind(-1)
    quadric = (x / 1.05) ** 2 + (y / 1.3) ** 2 + (z / 0.9) ** 2 - 1.0
    phi = torch.stack([quadric * (1.0 + 0.5 * torch.sin(3.0 * x)),
                       torch.tanh(2.0 * quadric) + 0.1 * y])[:, None]
    return ts.ImplicitSurface(phi, grid)


@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative"])
def test_rows_are_the_volume_operators_matrix(scheme):
    """Each row formed in closed form equals the one assembled column by column from the
    volume operator, faces included (a neighbour beyond a face folds onto the face node)."""
    surface = _cut_ellipsoids()
    shape = surface.grid.shape
    batch, size = 2, surface.grid.shape[0] * shape[1] * shape[2]
    columns = []
    for node in range(batch * size):
        probe = torch.zeros(batch * size, dtype=torch.float64)
        probe[node] = 1.0
        columns.append(ts.laplace_beltrami(probe.view(batch, 1, *shape), surface, scheme)
                       .flatten())
    matrix = torch.stack(columns, dim=1)
    nodes = torch.arange(batch * size)
    rows = laplace_beltrami_rows(surface, nodes, scheme)
    assembled = torch.zeros_like(matrix)
    entry = nodes // size
    at = ((nodes // (shape[1] * shape[2])) % shape[0], (nodes // shape[2]) % shape[1],
          nodes % shape[2])
    for k, offset in enumerate(NEIGHBOURHOOD):
        z, y, x = ((a + o).clamp(0, n - 1) for a, o, n in zip(at, offset, shape, strict=True))
        assembled.index_put_((nodes, ((entry * shape[0] + z) * shape[1] + y) * shape[2] + x),
                             rows[:, k], accumulate=True)
    scale = float(matrix.abs().max())
    assert float((assembled - matrix).abs().max()) < 1e-13 * scale
    # rows of nodes at a face hold nothing beyond it
    assert float(rows[at[2] == 0][:, [k for k, o in enumerate(NEIGHBOURHOOD) if o[2] < 0]]
                 .abs().max()) == 0.0


@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative"])
def test_dense_bound_from_rows_equals_the_probes(scheme):
    """The dense bound, from rows formed in closed form, is the colour probes' bound of the
    same operator: on surfaces cut by the box and not distances, a batch, a thin torus."""
    thin = ts.Grid.cube(25, 1.3)
    for surface in (_cut_ellipsoids(), ts.ImplicitSurface(
            ts.sdf.torus(thin, 0.8, 0.07, dtype=torch.float64), thin)):
        mask = surface.band_mask()

        def operator(x, surface=surface, mask=mask):
            inside = torch.where(mask, x, 0.0)
            return torch.where(mask, ts.laplace_beltrami(inside, surface, scheme), 0.0)

        probed = gershgorin_bound(operator, mask, torch.float64)
        assert laplace_beltrami_bound(surface, scheme) == pytest.approx(probed, rel=1e-12)


def _wavy_bricks(dtype: torch.dtype) -> ts.ImplicitSurface:
    """Bricks of a batch of two: a torus and a wavy quadric (not a distance)."""
    from torchsurf import bricks

    grid = ts.Grid.cube(30, 1.9)
    x, y, z = grid.points(dtype=dtype).unbind(-1)
    quadric = (x / 1.05) ** 2 + (y / 1.2) ** 2 + (z / 0.9) ** 2 - 1.0
    phi = torch.cat([ts.sdf.torus(grid, 0.8, 0.3, dtype=dtype),
                     (quadric * (1.0 + 0.3 * torch.sin(3.0 * x)))[None, None]])
    return bricks.from_dense(phi, grid)


@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative"])
def test_brick_rows_are_the_brick_operators_matrix(scheme):
    """On bricks each row, formed on its brick's haloed geometry, holds the brick operator's
    coefficients: applied to a field, the rows give the operator's values at the band's nodes
    (whose neighbours are all stored)."""
    surface = _wavy_bricks(torch.float64)
    layout = surface.layout
    u = layout.rand(1, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    nodes = surface.band_mask().reshape(-1).nonzero().squeeze(1)
    rows = laplace_beltrami_rows(surface, nodes, scheme)
    haloed = layout.halo(u, 1, "slicing").reshape(len(layout), -1)
    side = 10
    local = nodes % 512
    at = (local // 64 + 1, (local // 8) % 8 + 1, local % 8 + 1)
    values = torch.zeros(len(nodes), dtype=torch.float64)
    for k, (dz, dy, dx) in enumerate(NEIGHBOURHOOD):
        flat = ((at[0] + dz) * side + at[1] + dy) * side + at[2] + dx
        values += rows[:, k] * haloed[nodes // 512, flat]
    expected = ts.laplace_beltrami(u, surface, scheme, "slicing").reshape(-1)[nodes]
    assert float((values - expected).abs().max()) < 1e-12 * float(expected.abs().max())


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("scheme", ["octant", "symmetric", "conservative"])
def test_brick_bound_from_rows_equals_the_probes(scheme, dtype):
    """The bricks' bound, from rows formed in closed form, is the colour probes' bound of the
    brick operator (restricted to the band) to rounding."""
    surface = _wavy_bricks(dtype)
    mask = surface.band_mask()

    def operator(x):
        inside = torch.where(mask, x, 0.0)
        return torch.where(mask, ts.laplace_beltrami(inside, surface, scheme, "slicing"), 0.0)

    probed = gershgorin_bound(operator, mask, dtype, chunk=1,
                              colour=surface.layout.colours())
    tolerance = 1e-12 if dtype == torch.float64 else 1e-6
    assert laplace_beltrami_bound(surface, scheme) == pytest.approx(probed, rel=tolerance)


def test_rows_refuse_what_they_cannot_form():
    """A scheme without a divergence form and positions outside the volumes or bricks are
    named in the errors."""
    from torchsurf import bricks

    surface = _cut_ellipsoids()
    with pytest.raises(ValueError, match="scheme"):
        laplace_beltrami_rows(surface, torch.tensor([3]), "central")
    with pytest.raises(ValueError, match=r"nodes must lie in \[0, 1008\)"):
        laplace_beltrami_rows(surface, torch.tensor([0, 1008]))
    with pytest.raises(ValueError, match="1-D integer tensor.*float32"):
        laplace_beltrami_rows(surface, torch.tensor([1.0]))
    with pytest.raises(ValueError, match=r"shape \(1, 2\)"):
        laplace_beltrami_rows(surface, torch.tensor([[1, 2]]))
    grid = ts.Grid.cube(24, 2.0)
    packed = bricks.from_dense(ts.ImplicitSurface(ts.sdf.sphere(grid), grid))
    size = len(packed.layout) * 512
    with pytest.raises(ValueError, match=rf"nodes must lie in \[0, {size}\).*bricks of 8\^3"):
        laplace_beltrami_rows(packed, torch.tensor([size]))
    assert laplace_beltrami_rows(surface, torch.zeros(0, dtype=torch.int64)).shape == (0, 27)


@pytest.mark.parametrize("mask, operator, message", [
    (torch.ones(1, 1, 5, 5, 5), None, "mask must be a bool volume"),
    (torch.ones(1, 2, 5, 5, 5, dtype=torch.bool), None, "mask"),
    (torch.ones(1, 5, 5, 5, dtype=torch.bool), None, "mask"),
    (torch.ones(1, 1, 5, 5, 5, dtype=torch.bool), "laplace_beltrami", "operator must be a callable"),
])
def test_bad_arguments_are_named(mask, operator, message):
    """A float mask raised torch's "bitwise_and_cpu not implemented", a 4-D mask returned a bound
    silently, a string operator raised "'str' object is not callable"."""
    with pytest.raises((TypeError, ValueError), match=message):
        gershgorin_bound(operator or (lambda x: x), mask, torch.float64)


def test_the_bound_names_a_band_without_nodes_a_bad_width_and_a_bad_surface():
    """A band of 1e-9 had given a bound of 0 (a step computed from it infinite), a width "0.3"
    passed through float(), and a tensor for the surface failed on a missing attribute."""
    from torchsurf import bricks
    from torchsurf.operators import laplace_beltrami_bound

    grid = ts.Grid.cube(24, 2.0)
    dense = ts.ImplicitSurface(ts.sdf.sphere(grid, 0.93), grid)
    for surface in (dense, bricks.from_dense(dense)):
        with pytest.raises(ValueError, match="holds no node"):
            laplace_beltrami_bound(surface, "octant", 1e-9)
        assert laplace_beltrami_bound(surface, "octant") > 0  # the refusal was not kept
    with pytest.raises(TypeError, match="width"):
        laplace_beltrami_bound(dense, "octant", "0.3")
    with pytest.raises(ValueError, match="width"):
        laplace_beltrami_bound(dense, "octant", -1.0)
    with pytest.raises(TypeError, match="surface must be"):
        laplace_beltrami_bound(dense.phi)
