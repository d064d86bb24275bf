"""Refuse, before any work, what cannot fit in memory.

The rule: an entry point that allocates whole volumes (:func:`torchsurf.sdf.from_function` and
the shapes, :func:`torchsurf.sdf.from_mesh`, :class:`torchsurf.MeshAdapter`,
:class:`torchsurf.ImplicitSurface`, every flow's call, :class:`~torchsurf.flows.Extension`) first
estimates the bytes it will hold at once, and raises ``MemoryError`` stating that estimate and
the memory available when the estimate exceeds it. The estimates are lower bounds, counted from
the arrays the algorithm must keep at the same time (listed by each function below), so a
refusal is always right; a run that passes may still need more (temporaries,
``torch.compile``).

"Available" is ``MemAvailable`` from ``/proc/meminfo`` (Linux) for work on the CPU: the memory
the kernel can hand out without swapping, after what the process already holds (the surface,
``u0``). On other systems and devices nothing is checked. Setting the environment variable
``TORCHSURF_MEMORY_CHECK=0`` turns the check off (``1``, the default, or empty keeps it; other
values raise ``ValueError``).
"""

from __future__ import annotations

import math
import os

import torch

from ._checks import check_device
from ._vertex_decode import DECODE_CHUNK

ENVIRONMENT_SWITCH = "TORCHSURF_MEMORY_CHECK"

STENCIL_TAPS = 64
"""Source nodes per node of the flows' tricubic closest-point stencil (4^3)."""


def available_bytes(device: torch.device | str | None = None) -> int | None:
    """Memory that ``device`` can still allocate, in bytes, or ``None`` when unknown.

    CPU on Linux: ``MemAvailable`` of ``/proc/meminfo``. Anything else: ``None`` (no check).
    """
    if device is not None and (str(device) == "meta" or check_device(device).type != "cpu"):
        return None
    try:
        with open("/proc/meminfo", encoding="ascii") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024  # the file counts kB
    except (OSError, ValueError, IndexError):
        return None
    return None


def _readable(count: float) -> str:
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB"):
        if count < 1024 or unit == "TiB":
            return f"{count:.3g} {unit}" if unit != "bytes" else f"{int(count)} bytes"
        count /= 1024
    return f"{count} bytes"  # pragma: no cover


def check_fits(estimate: float, what: str, device: torch.device | str | None = None) -> None:
    """Raise ``MemoryError`` if ``estimate`` bytes exceed the memory ``device`` has available.

    Args:
        estimate: bytes the work will hold at once (a lower bound).
        what: the work, for the message (e.g. ``"sdf.from_mesh on a (3000, 3000, 3000) grid"``).
        device: where the work allocates (default CPU).
    """
    switch = os.environ.get(ENVIRONMENT_SWITCH, "1").strip()
    if switch == "0":
        return
    if switch not in ("1", ""):  # "false" or "off" had left the check on without a word
        raise ValueError(f"{ENVIRONMENT_SWITCH} must be 0 (no check) or 1 (the default), got "
                         f"{switch!r}")
    available = available_bytes(device)
    if available is None or estimate <= available:
        return
    raise MemoryError(
        f"{what} needs at least {int(estimate)} bytes ({_readable(estimate)}, a lower bound) but "
        f"only {available} bytes ({_readable(available)}) are available (MemAvailable in "
        "/proc/meminfo); use a coarser grid, a smaller batch or fewer channels, or set "
        f"{ENVIRONMENT_SWITCH}=0 to skip this check"
    )


def _itemsize(dtype: torch.dtype | None) -> int:
    return (torch.get_default_dtype() if dtype is None else dtype).itemsize


def sampled_bytes(shape: tuple[int, int, int], dtype: torch.dtype | None) -> int:
    """A function sampled on the grid: the points ``(D, H, W, 3)`` and the values ``(D, H, W)``."""
    return 4 * math.prod(shape) * _itemsize(dtype)


def surface_bytes(batch: int, shape: tuple[int, int, int], dtype: torch.dtype | None) -> int:
    """An :class:`~torchsurf.ImplicitSurface` from ``phi``: ``grad_norm``, ``normal`` (3),
    ``weight`` and the gradient (3) it is computed from; 8 volumes ``(B, 1, D, H, W)``."""
    return 8 * batch * math.prod(shape) * _itemsize(dtype)


MESH_BAND_NODE_BYTES = 100
"""Bytes per band node of the mesh distance: node index (24), closest point (24), world point
(24), distance (8), face (8), sign and signed distance (9)."""


def mesh_sdf_bytes(shape: tuple[int, int, int], spacing: float, band: float, area: float,
                   dtype: torch.dtype | None) -> int:
    """Signed distance to a mesh of total triangle ``area`` on a grid: the volume of far
    bricks' signs and the result, both float64 ``(D, H, W)`` (16 bytes a node) before the
    conversion to ``dtype``; the band's nodes, about ``area * 2 band / spacing^3`` of them
    (at most every node), :data:`MESH_BAND_NODE_BYTES` each."""
    nodes = math.prod(shape)
    band_part = min(MESH_BAND_NODE_BYTES * nodes, mesh_band_bytes(spacing, band, area))
    return int(max(16, 8 + _itemsize(dtype)) * nodes + band_part)


def mesh_band_bytes(spacing: float, reach: float, area: float) -> int:
    """The band nodes' part of :func:`mesh_sdf_bytes` alone, what building bricks from a mesh
    of triangle ``area`` holds at least (no dense volume): about ``area * 2 reach / spacing^3``
    nodes within ``reach`` of it, :data:`MESH_BAND_NODE_BYTES` each."""
    return int(MESH_BAND_NODE_BYTES * area * 2.0 * reach / spacing**3)


def flow_bytes(
    data: tuple[int, ...], surface_batch: int, dtype: torch.dtype, implicit: bool,
    band_nodes: int | None, snapshots: int = 0,
) -> int:
    """One call of a flow on data of shape ``data`` ``(B, C, D, H, W)``.

    Working volumes of the data's shape besides ``u0``: the result and a rate (2), or for the
    implicit methods the conjugate-gradient iterate, residual, direction, image and right-hand
    side (5). On a surface's first call (``band_nodes`` not ``None``): its closest points
    (``(D, H, W, 3)`` and ``(B_s, D, H, W, 3)``) and the tricubic stencil of its band,
    :data:`STENCIL_TAPS` int32 indices and weights per band node; plus three bool masks
    ``(B_s, 1, D, H, W)`` (band, ring, both). With ``snapshots`` requested times: each
    result, twice (kept, then stacked into the returned tensor; 200 times at 48^3, batch 4,
    had been let through at 3.7 MiB and died in the allocator after the whole flow).
    """
    batch, channels, *spatial = data
    nodes = math.prod(spatial)
    itemsize = dtype.itemsize
    volume = max(batch, surface_batch) * channels * nodes * itemsize
    working = (5 if implicit else 2) * volume + 2 * snapshots * volume
    masks = 3 * surface_batch * nodes
    first_call = 0
    if band_nodes is not None:
        first_call = ((3 + 3 * surface_batch) * nodes * itemsize
                      + band_nodes * STENCIL_TAPS * (4 + itemsize))
    return working + masks + first_call


DECODE_SOLVE_BYTES = 40_000
"""Bytes a vertex of a chunk of ``order=2`` decoding weights solved at once holds
(:data:`torchsurf._vertex_decode.DECODE_CHUNK` of them; about 50 kB measured)."""

DECODE_KEPT_BYTES = 8_000
"""Bytes an ``order=2`` adapter holds per vertex while it builds its decoding weights: 8.2 kB
measured (live peak of spot, its subdivision, the armadillo and bunny, 2.9k-35k vertices, at
32^3: about 89 MB plus this a vertex, whatever the grid)."""


def mesh_adapter_bytes(shape: tuple[int, int, int], spacing: float, band: float, area: float,
                       dtype: torch.dtype | None, vertices: int = 0, order: int = 1) -> int:
    """:class:`~torchsurf.MeshAdapter`: the mesh distance (:func:`mesh_sdf_bytes`), then its
    float64 result, its copy in ``dtype`` and the surface built on it
    (:func:`surface_bytes`) at once; with ``order=2``, the decoding weights of its
    ``vertices`` (:data:`DECODE_SOLVE_BYTES`, :data:`DECODE_KEPT_BYTES`: what dominates on
    meshes of many vertices, 36-200x the rest on bunny at 32^3-64^3)."""
    nodes = math.prod(shape)
    surface = (8 + _itemsize(dtype)) * nodes + surface_bytes(1, shape, dtype)
    decoding = 0
    if order == 2:
        decoding = DECODE_SOLVE_BYTES * min(vertices, DECODE_CHUNK) + DECODE_KEPT_BYTES * vertices
    return max(mesh_sdf_bytes(shape, spacing, band, area, dtype), surface) + decoding
