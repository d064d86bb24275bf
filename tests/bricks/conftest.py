"""Surfaces shared by the brick tests: each is compared against the dense surface it came from."""

from __future__ import annotations

import pytest

import torchsurf as ts
from torchsurf import Grid, bricks


@pytest.fixture(scope="module")
def torus():
    """A torus on 33^3 with room around its band: (dense surface, brick surface), float64."""
    grid = Grid.cube(33, 2.1)
    dense = ts.ImplicitSurface(ts.sdf.torus(grid, 0.9, 0.4).double(), grid)
    return dense, bricks.from_dense(dense)


@pytest.fixture(scope="module")
def two_boxes():
    """A sphere and a torus on boxes of different shapes and origins, one spacing:
    ``(sphere, torus, both)`` as brick surfaces, ``both`` their batch."""
    spacing = 0.1
    small = Grid(shape=(29, 29, 29), spacing=spacing, origin=(-1.4,) * 3)
    long = Grid(shape=(33, 41, 39), spacing=spacing, origin=(-1.9, -2.0, -1.6))
    sphere = bricks.from_dense(ts.sdf.sphere(small, 0.9).double(), small)
    torus = bricks.from_dense(ts.sdf.torus(long, 1.0, 0.4).double(), long)
    return sphere, torus, bricks.cat([sphere, torus])
