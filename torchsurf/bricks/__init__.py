"""Band storage as 8^3 bricks: memory and work that grow with the surface's area.

- :class:`BrickLayout`: the bricks (coordinates, batch index, neighbour table), halo gathering
  and conversions to and from dense volumes;
- :class:`BrickSurface`: an :class:`~torchsurf.ImplicitSurface` stored on a layout;
- :func:`from_dense` (the small-case route, and the reference) and :func:`from_mesh` (straight
  from triangle meshes, no dense volume at any point); :func:`cat` batches surfaces of any box;
- :func:`fit_grids`: several meshes, each at its own resolution, on grids of one spacing (one
  batch); :class:`BrickMeshAdapter`: their vertex data into and out of the packed band.

docs/bricks.md describes the layout, what runs on it and its measured cost.
"""

from .adapter import BrickMeshAdapter
from .build import cat, from_dense, from_mesh
from .fit import FittedMeshes, fit_grids
from .layout import BRICK, BrickLayout, bricks_of_mask
from .surface import BrickSurface

__all__ = [
    "BRICK",
    "BrickLayout",
    "BrickMeshAdapter",
    "BrickSurface",
    "FittedMeshes",
    "bricks_of_mask",
    "cat",
    "fit_grids",
    "from_dense",
    "from_mesh",
]
