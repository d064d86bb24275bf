"""A problem moved far from the world's origin gives the same numbers in float32.

The re-extension's closest points are formed in node indices: in world coordinates, float32
rounded them to ``eps * |origin| / h`` of a cell (2e-2 of a cell at x = 1e4 here), and a heat
flow's result moved by 2e-3 against 4e-7 at the origin.
"""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf import bricks

N, RADIUS, CENTRE = 33, 0.8, (0.1, -0.07, 0.05)


def _problem(offset: float, dense: bool = True):
    spacing = 2.6 / (N - 1)
    grid = ts.Grid(shape=(N, N, N), spacing=spacing, origin=(offset - 1.3, -1.3, -1.3))
    centre = (offset + CENTRE[0], CENTRE[1], CENTRE[2])
    phi = ts.sdf.sphere(grid, RADIUS, center=centre, dtype=torch.float32)
    x = grid.points(dtype=torch.float64, relative_to=centre)
    data = (torch.sin(2 * x[..., 0]) + x[..., 1] * x[..., 2]).float()[None, None]
    surface = ts.ImplicitSurface(phi, grid)
    if dense:
        return surface, data
    packed = bricks.from_dense(surface)
    return packed, packed.from_dense(data)


OPERATIONS = {
    "heat rkc": lambda u, s: ts.HeatFlow(time=0.02)(u, s),
    "heat chebyshev": lambda u, s: ts.HeatFlow(time=0.02, method="chebyshev")(u, s),
    "extension cubic": lambda u, s: ts.Extension(interpolation="cubic")(u, s),
    "extension linear": lambda u, s: ts.Extension(interpolation="linear")(u, s),
}


@pytest.mark.parametrize("dense", [True, False], ids=["dense", "bricks"])
@pytest.mark.parametrize("name", list(OPERATIONS))
def test_float32_results_do_not_depend_on_where_the_problem_sits(name, dense):
    operation = OPERATIONS[name]
    here_surface, here_data = _problem(0.0, dense)
    far_surface, far_data = _problem(1e4, dense)
    here = operation(here_data, here_surface)
    far = operation(far_data, far_surface)
    band = here_surface.band_mask().expand_as(here)
    assert torch.equal(here_surface.band_mask(), far_surface.band_mask())
    difference = float((far - here)[band].abs().max())
    # the same problem: only phi's own rounding at x = 1e4 differs (about 1e-7 of data of size 1)
    assert difference < 2e-6, difference
