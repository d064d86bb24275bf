"""A flow reads nothing outside its band and the ring of nodes around it.

Near a medial axis, a thin feature or a sharp edge the first-order closest point
``x - (phi / W) n`` of a node lands cells away from S, and its tricubic taps reached nodes that
no flow evolves: on a 33^3 torus, 24 of 11,972 region nodes did, and values there moved band
values by 52. The closest points are now refined (:mod:`torchsurf.flows._closest`) and a node
whose taps still leave the region (only where phi is not a distance) is left out of the
re-extension: values outside the band and its ring cannot change the result, on any shape.
"""

from __future__ import annotations

import pytest
import torch
import trimesh

import torchsurf as ts
from torchsurf.flows import _closest
from torchsurf.flows.base import with_ring
from torchsurf.flows.extension import CubicStencil, _dense_tap_indices

from .test_stability import MESH_DIR


def _torus() -> ts.ImplicitSurface:
    grid = ts.Grid.cube(33, 1.5)
    return ts.ImplicitSurface(ts.sdf.torus(grid, 1.0, 0.3), grid)


def _trefoil() -> ts.ImplicitSurface:
    grid = ts.Grid.cube(40, 1.5)
    return ts.ImplicitSurface(ts.sdf.trefoil(grid, tube_radius=0.2), grid)


def _mesh(name: str, resolution: int = 40) -> ts.ImplicitSurface:
    path = MESH_DIR / name
    if not path.is_file():
        pytest.skip(f"test mesh {name} not found in {MESH_DIR} (set TORCHSURF_MESH_DIR)")
    mesh = trimesh.load(path, force="mesh")
    grid = ts.mesh.fit_grid(mesh, resolution)
    return ts.ImplicitSurface(ts.sdf.from_mesh(mesh, grid), grid)


def _sign_flip() -> ts.ImplicitSurface:
    """A sphere whose phi changes sign across the plane x = 0.3 without crossing zero: what
    an open mesh's holes do to ``from_mesh`` (the shared bunny at 128^3)."""
    grid = ts.Grid.cube(24, 1.5)
    phi = ts.sdf.sphere(grid, 1.0)
    return ts.ImplicitSurface(torch.where(grid.points()[..., 0] > 0.3, -phi, phi), grid)


SHAPES = {
    "torus": _torus,
    "trefoil": _trefoil,
    "fandisk": lambda: _mesh("fandisk.obj"),
    "sign flip": _sign_flip,
}

FLOWS = {
    "heat rkc": lambda t: ts.HeatFlow(t),
    "heat euler": lambda t: ts.HeatFlow(t, method="euler"),
    "heat implicit": lambda t: ts.HeatFlow(t, method="implicit"),
    "heat chebyshev": lambda t: ts.HeatFlow(t, method="chebyshev"),
    "perona-malik": lambda t: ts.AnisotropicFlow(t, "perona_malik", contrast=1.0 / t**0.5),
}


def _tap_count_outside(surface: ts.ImplicitSurface, stencil: CubicStencil, region: torch.Tensor
                       ) -> int:
    targets, corners, _ = stencil.parts[0]
    inside = _closest.taps_inside(region[0, 0].reshape(-1),
                                  _dense_tap_indices(corners, *surface.grid.shape[1:]),
                                  len(targets))
    return int((~inside).sum())


@pytest.mark.parametrize("shape", ["torus", "trefoil", "fandisk"])
def test_refined_closest_points_read_only_the_band_and_its_ring(shape):
    surface = SHAPES[shape]()
    region = with_ring(surface.band_mask())
    # without the refinement these shapes have 24, 30 and 48 such nodes at these sizes
    assert _tap_count_outside(surface, CubicStencil(surface, region, limited=True), region) == 0


def test_refinement_leaves_good_closest_points_exactly_as_they_were():
    grid = ts.Grid.cube(24, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    region = with_ring(surface.band_mask())
    nodes = grid.world_to_index(grid.points(dtype=torch.float64)).float()
    step = (surface.phi / surface.weight / grid.spacing) * surface.normal
    index = nodes - step[0].permute(1, 2, 3, 0)
    targets, _, weights = CubicStencil(surface, region).parts[0]
    at = index.reshape(-1, 3)[targets]
    expected = torch.stack([torch.stack(ts.sampling.cubic_lagrange_weights(a - a.floor()), 1)
                            for a in at.unbind(1)])
    assert torch.equal(weights, expected)



def test_refined_points_are_continuous_where_they_cross_the_tolerance():
    """A plane ``z = 5`` (distance in cells) read by a tilted normal: first-order points at
    distances a hair either side of the tolerance were moved by half a cell or not at all;
    the growing share of the step makes the refined points continuous in ``phi``."""
    size = 12
    z = torch.arange(size, dtype=torch.float64)[:, None, None].expand(size, size, size)
    distance = (z - 5.0).contiguous()
    normal = torch.stack([torch.full_like(distance, 0.6), torch.zeros_like(distance),
                          torch.full_like(distance, 0.8)])
    read = _closest.dense_reader(distance, normal)
    tolerance = _closest.REFINE_TOLERANCE
    at = torch.tensor([[5.0, 5.0, 5.0 + tolerance + offset]
                       for offset in (-1e-9, 1e-9, -0.6 * tolerance)], dtype=torch.float64)
    refined = _closest.refine(at, read)
    assert float((refined[0] - refined[1]).abs().max()) < 1e-8
    assert float((refined[1] - at[1]).abs().max()) > 0.1  # the step was taken
    # within half the tolerance a point is left exactly as it was
    assert torch.equal(refined[2], at[2])


CASES = [("torus", flow) for flow in FLOWS] + [("sign flip", flow) for flow in FLOWS] + [
    ("trefoil", "heat rkc"), ("trefoil", "heat chebyshev"), ("fandisk", "heat rkc"),
    ("fandisk", "perona-malik")]


@pytest.mark.parametrize(("shape", "flow"), CASES)
def test_values_outside_the_band_and_ring_do_not_reach_the_result(shape, flow):
    surface = SHAPES[shape]()
    h = surface.spacing
    made = FLOWS[flow](4 * h * h)
    generator = torch.Generator().manual_seed(1)
    u0 = torch.rand((1, 1, *surface.grid.shape), generator=generator)
    region = with_ring(made.band_mask(surface))
    far = torch.where(region, u0, 1e3)
    with torch.no_grad():
        clean, dirty = made(u0, surface), made(far, surface)
    torch.testing.assert_close(dirty[region.expand_as(dirty)], clean[region.expand_as(clean)],
                               rtol=0, atol=1e-6)
    # and the heat flows keep the maximum principle on the band
    if flow.startswith("heat"):
        band = made.band_mask(surface).expand_as(clean)
        assert float(clean[band].max()) <= float(u0[region].max()) + 1e-6
        assert float(clean[band].min()) >= float(u0[region].min()) - 1e-6


def test_a_node_whose_taps_leave_what_it_may_read_is_left_out_and_keeps_its_value():
    surface = _sign_flip()
    region = with_ring(surface.band_mask())
    assert _tap_count_outside(surface, CubicStencil(surface, region), region) > 0
    stencil = CubicStencil(surface, region, limited=True, readable=region)
    assert _tap_count_outside(surface, stencil, region) == 0
    left_out = int(region.sum()) - len(stencil.parts[0][0])
    assert 0 < left_out < 20
    u = torch.rand((1, 1, *surface.grid.shape), generator=torch.Generator().manual_seed(2))
    result = stencil.apply(u)
    kept = region.clone().reshape(-1)
    kept[stencil.parts[0][0]] = False
    assert torch.equal(result.reshape(-1)[kept], u.reshape(-1)[kept])
