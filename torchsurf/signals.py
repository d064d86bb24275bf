"""Data to put on a surface: images wrapped onto it, checkerboards, seeded noise, unit tangent
fields and colour conversions.

Every function returns a volume ``(B, C, D, H, W)`` on the surface's grid (or takes one), in
the surface's dtype; on a :class:`~torchsurf.bricks.BrickSurface`, a packed field
``(N, C, 8, 8, 8)`` of its stored nodes instead. Patterns are evaluated at the first-order
closest point of each node on S (:func:`closest_points`), so they are constant along the
normals, as the flows expect (the paper's §2). Colour conversions are kornia's, applied to
the channels of a volume.
"""

from __future__ import annotations

import math
from pathlib import Path

import kornia.color
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from . import _memory
from ._checks import (
    MismatchError,
    as_real_tensor,
    check_choice,
    check_count,
    check_nonnegative,
    check_positive,
    check_real,
    check_tensor,
    check_triple,
    check_volume,
)
from .curvature import tangent_basis
from .flows import HeatFlow
from .grid import Grid
from .operators import laplace_beltrami_bound
from .sampling import sample
from .surface import ImplicitSurface, check_data, tangent_unit

__all__ = [
    "AXES",
    "COLOUR_SPACES",
    "EULER_SMOOTHING_STEPS",
    "IMAGES",
    "PROJECTIONS",
    "SEED_LIMIT",
    "SMOOTHING_STEP",
    "SMOOTHING_STEPS",
    "axis_field",
    "builtin_image",
    "checkerboard",
    "chroma_brightness",
    "closest_points",
    "gaussian_noise",
    "generator",
    "gray",
    "load_image",
    "node_points",
    "orient",
    "perturb_field",
    "principal_direction",
    "project_image",
    "rgb_from",
    "rgb_to",
    "surface_noise",
    "swirl_field",
    "uniform_noise",
]

PROJECTIONS = ("spherical", "cylindrical", "planar", "triplanar")
AXES = ("x", "y", "z")
IMAGES = ("colour_wheel", "colour_checker", "checker")
COLOUR_SPACES = ("hsv", "hls", "lab", "luv", "xyz", "ycbcr", "yuv")


def node_points(surface: ImplicitSurface) -> Tensor:
    """World ``(x, y, z)`` of every node: ``(1, 3, D, H, W)``, or packed ``(N, 3, 8, 8, 8)`` on a
    :class:`~torchsurf.bricks.BrickSurface`."""
    if surface.layout is not None:
        return surface.layout.points(surface.phi.dtype).to(surface.phi.device)
    points = surface.grid.points(dtype=surface.phi.dtype, device=surface.phi.device)
    return points.permute(3, 0, 1, 2)[None]


def closest_points(surface: ImplicitSurface) -> Tensor:
    """``x - phi grad phi / |grad phi|^2``, the first-order closest point on S of every node.

    Returns:
        ``(B, 3, D, H, W)`` world ``(x, y, z)`` (packed ``(N, 3, 8, 8, 8)`` on bricks).
    """
    return node_points(surface) - surface.phi / surface.grad_norm * surface.normal


def _axis_index(axis: str) -> int:
    return AXES.index(check_choice(axis, "axis", AXES))


def checkerboard(points: Tensor, tile: float, origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
                 ) -> Tensor:
    """A solid checkerboard of cubes of side ``tile`` (world units) seen at ``points``.

    Args:
        points: ``(B, 3, D, H, W)`` world ``(x, y, z)`` (e.g. :func:`closest_points`).
        tile: side of the cubes, world units.
        origin: a corner of the cubes, world ``(x, y, z)``.

    Returns:
        ``(B, 1, D, H, W)``, values 0 and 1.
    """
    check_volume(points, "points", channels=3)
    as_real_tensor(origin, "origin", "world (x, y, z)")  # refuses bools, strings, complex
    # the numbers as given, in float64: the default dtype would round them before the floor
    corner = torch.as_tensor(np.asarray(origin.detach().cpu() if isinstance(origin, Tensor)
                                        else origin, dtype=np.float64))
    if corner.shape != (3,) or not bool(torch.isfinite(corner).all()):
        raise ValueError(f"origin must be three finite numbers, world (x, y, z), got {origin!r}")
    corner = corner.to(points)
    tile = check_positive(tile, "tile")
    cells = torch.floor((points - corner.view(1, 3, 1, 1, 1)) / tile)
    return torch.remainder(cells.sum(dim=1, keepdim=True), 2.0) + 0.0  # no -0.0


def builtin_image(name: str, size: int = 256) -> Tensor:
    """A 2-D RGB image that needs no file, ``(3, size, size)`` in ``[0, 1]``.

    ``"colour_wheel"``: hue by angle around the centre, saturation by radius (HSV through
    kornia); ``"colour_checker"``: 8 x 8 squares, dark and light alternating, hue changing
    from square to square; ``"checker"``: 8 x 8 black and white squares.
    """
    check_choice(name, "image", IMAGES)
    size = check_count(size, "size")
    axis = torch.linspace(-1.0, 1.0, size)
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    column, row = torch.floor((x + 1) * 4).clamp(max=7), torch.floor((y + 1) * 4).clamp(max=7)
    parity = torch.remainder(column + row, 2.0)
    if name == "checker":
        return parity.expand(3, size, size).clone()
    if name == "colour_checker":
        hue = torch.remainder(column * 0.9 + row * 2.3, 2 * math.pi)
        hsv = torch.stack((hue, torch.full_like(x, 0.8), 0.3 + 0.65 * parity))
        return kornia.color.hsv_to_rgb(hsv[None])[0]
    hue = torch.remainder(torch.atan2(y, x), 2 * math.pi)
    saturation = (x**2 + y**2).sqrt().clamp(max=1.0)
    value = torch.full_like(x, 0.95)
    return kornia.color.hsv_to_rgb(torch.stack((hue, saturation, value))[None])[0]


def load_image(path: str | Path) -> Tensor:
    """An image file as ``(C, H, W)`` float32 in ``[0, 1]`` (C = 3, or 1 for gray files).

    Read by scikit-image; an alpha channel is dropped. Integer pixels are divided by their
    type's largest value (255 for 8 bits, 65535 for 16 bits, ...); floating-point pixels are
    taken as they are.

    Raises:
        ValueError: pixels below 0 (a signed integer file), or floating-point pixels outside
            ``[0, 1]``, naming the file and the range found.
    """
    from skimage import io

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image: no file {str(path)!r}")
    array = np.asarray(io.imread(str(path)))
    scale = float(np.iinfo(array.dtype).max) if np.issubdtype(array.dtype, np.integer) else 1.0
    values = array.astype(np.float64) / scale
    if values.size and not (values.min() >= 0 and values.max() <= 1):
        raise ValueError(
            f"image: {str(path)!r} holds {array.dtype} pixels in [{array.min()}, {array.max()}]; "
            f"expected [0, {'1' if scale == 1.0 else int(scale)}]"
        )
    image = torch.as_tensor(values.astype(np.float32))
    if image.dim() == 2:
        image = image[..., None]
    colours = 1 if image.shape[-1] <= 2 else 3  # gray (+ alpha) or RGB (+ alpha)
    return image[..., :colours].permute(2, 0, 1).contiguous()


def _lookup(image: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Bilinear samples of ``image`` ``(C, Hi, Wi)`` at ``u``, ``v`` in ``[-1, 1]`` (left to
    right, bottom to top), both ``(B, D, H, W)``; returns ``(B, C, D, H, W)``."""
    batch, depth = u.shape[:2]
    where = torch.stack((u, -v), dim=-1).reshape(batch, depth, -1, 2)
    values = F.grid_sample(image.to(u.dtype)[None].expand(batch, -1, -1, -1), where,
                           mode="bilinear", padding_mode="border", align_corners=True)
    return values.reshape(batch, image.shape[0], *u.shape[1:])


def project_image(
    image: Tensor,
    points: Tensor,
    projection: str,
    box: tuple[Tensor, Tensor],
    axis: str = "z",
    normal: Tensor | None = None,
) -> Tensor:
    """Wrap a 2-D image onto points of a surface.

    - ``"spherical"``: longitude around ``axis`` (from the box's centre) across the image's
      width, latitude across its height;
    - ``"cylindrical"``: longitude across the width, height along ``axis`` within the box
      across the height;
    - ``"planar"``: the image seen along ``axis``, stretched over the box;
    - ``"triplanar"``: the three planar projections blended by ``n_i^4`` (needs ``normal``).

    Args:
        image: ``(C, Hi, Wi)``.
        points: ``(B, 3, D, H, W)`` world ``(x, y, z)`` on S (:func:`closest_points`).
        projection: one of :data:`PROJECTIONS`.
        box: the shape's bounding box, ``(low, high)`` world ``(x, y, z)`` tensors ``(3,)``.
        axis: the projection's axis, ``"x"``, ``"y"`` or ``"z"``.
        normal: ``(B, 3, D, H, W)`` unit normals, for ``"triplanar"``.

    Returns:
        ``(B, C, D, H, W)``.
    """
    image = check_tensor(image, "image")
    if image.dim() != 3 or image.shape[1] < 1 or image.shape[2] < 1:
        raise ValueError(f"image must have shape (C, H, W) with H, W >= 1, got "
                         f"{tuple(image.shape)}")
    if not image.is_floating_point():
        raise TypeError(f"image must be a floating-point tensor, got {image.dtype}")
    if not bool(torch.isfinite(image).all()):
        raise ValueError("image holds NaN or infinity: every projected value would read it")
    check_volume(points, "points", channels=3)
    check_choice(projection, "projection", PROJECTIONS)
    low, high = _check_box(box, points)
    local = (points - 0.5 * (low + high)) / (0.5 * (high - low))
    k = _axis_index(axis)
    i, j = [a for a in range(3) if a != k]
    if projection == "triplanar":
        if normal is None:
            raise ValueError("normal: the triplanar projection blends by the normals, give them")
        check_volume(normal, "normal", channels=3)
        if (normal.dtype, normal.device) != (points.dtype, points.device) or (
                normal.shape[2:] != points.shape[2:]
                or normal.shape[0] not in (1, points.shape[0])):
            raise MismatchError(
                f"normal must be (B or 1, 3, D, H, W) {points.dtype} on {points.device} like "
                f"points {tuple(points.shape)}, got {tuple(normal.shape)} {normal.dtype} on "
                f"{normal.device}")
        weights = normal**4
        weights = weights / weights.sum(dim=1, keepdim=True).clamp(min=1e-12)
        result = 0
        for a in range(3):
            first, second = [b for b in range(3) if b != a]
            result = result + weights[:, a:a + 1] * _lookup(image, local[:, first], local[:, second])
        return result
    if projection == "planar":
        return _lookup(image, local[:, i], local[:, j])
    centred = points - 0.5 * (low + high)
    longitude = torch.atan2(centred[:, j], centred[:, i]) / math.pi
    if projection == "cylindrical":
        return _lookup(image, longitude, local[:, k].clamp(-1.0, 1.0))
    radius = centred.norm(dim=1).clamp(min=1e-12)
    latitude = torch.asin((centred[:, k] / radius).clamp(-1.0, 1.0)) / (0.5 * math.pi)
    return _lookup(image, longitude, latitude)


def _check_box(box: object, points: Tensor) -> tuple[Tensor, Tensor]:
    """``box`` = ``(low, high)``, each three finite world coordinates (tensors, arrays or
    sequences) with ``low < high`` on every axis, as ``(1, 3, 1, 1, 1)`` tensors like
    ``points``."""
    try:
        low, high = box
    except (TypeError, ValueError):
        raise ValueError(f"box must be a pair (low, high) of world (x, y, z) corners, got "
                         f"{box!r}") from None
    corners = []
    for name, corner in (("box's low", low), ("box's high", high)):
        if isinstance(corner, Tensor):
            corner = corner.detach().cpu().reshape(-1).tolist() if corner.dim() <= 1 else corner
        corners.append(check_triple(corner, name, check_real))
    if any(a >= b for a, b in zip(*corners, strict=True)):
        raise ValueError(f"box: low {corners[0]} must lie below high {corners[1]} on every axis")
    # tensors as given (a corner, or its three entries): a box that requires grad keeps it
    def kept(given: object, checked: tuple[float, float, float]) -> Tensor:
        if isinstance(given, Tensor):
            return given.to(points)
        if any(isinstance(entry, Tensor) for entry in given):
            return torch.stack([torch.as_tensor(entry).to(points).reshape(()) for entry in given])
        return points.new_tensor(checked)

    return tuple(kept(given, checked).view(1, 3, 1, 1, 1)
                 for given, checked in zip((low, high), corners, strict=True))


SEED_LIMIT = 2**32
"""Seeds lie in ``[0, 2^32)``: ``torch.Generator.manual_seed`` takes 64-bit seeds, but the CPU
generator (mt19937) keeps their low 32 bits, so ``2^32`` drew what ``0`` draws."""


def _drawn_as(dtype: torch.dtype) -> torch.dtype:
    """The dtype noise of ``dtype`` is drawn in: float64's as float32, so that float32 and
    float64 runs of one seed get the same numbers; narrower dtypes their own (float32 numbers
    below 1 can round to 1 in them)."""
    return torch.float32 if dtype == torch.float64 else dtype


def generator(seed: int) -> torch.Generator:
    """A CPU ``torch.Generator`` seeded with ``seed`` (a whole number in ``[0, 2^32)``,
    :data:`SEED_LIMIT`): the same seed gives the same noise, different seeds different noise."""
    seed = check_count(seed, "seed", minimum=0)
    if seed >= SEED_LIMIT:
        raise ValueError(f"seed must be a whole number in [0, 2**32) (the CPU generator keeps "
                         f"32 bits of a seed: larger ones repeat smaller ones), got {seed}")
    return torch.Generator().manual_seed(seed)


def gaussian_noise(like: Tensor, std: float, seed: int, surface: ImplicitSurface | None = None
                   ) -> Tensor:
    """Gaussian noise of standard deviation ``std``, shaped and typed like ``like``, seeded.

    The numbers are drawn in float32 for float64 too, so that float32 and float64 runs of one
    seed get the same noise (to float32's digits). Entry ``b`` of a batch gets the
    ``b``-th part of one stream, laid out as ``like``. With a
    :class:`~torchsurf.bricks.BrickSurface` ``surface`` (``like`` packed ``(N, C, 8, 8, 8)``),
    the stream is laid out over the entries' dense grids one after the other and packed: on
    bricks of one box, the numbers the dense batch gets, node for node.
    """
    check_tensor(like, "like")
    check_nonnegative(std, "std")
    draw = generator(seed)
    if surface is not None and surface.layout is not None:
        sizes = [like.shape[1] * math.prod(grid.shape) for grid in surface.grids]
        stream = torch.randn(sum(sizes), generator=draw, dtype=_drawn_as(like.dtype))
        stream = stream.to(like.dtype)
        volumes = [part.view(1, like.shape[1], *grid.shape)
                   for part, grid in zip(stream.split(sizes), surface.grids, strict=True)]
        return std * surface.layout.from_dense(volumes).to(like.device)
    noise = torch.randn(like.shape, generator=draw, dtype=_drawn_as(like.dtype))
    return std * noise.to(like.device, like.dtype)


def uniform_noise(surface: ImplicitSurface, channels: int, seed: int) -> Tensor:
    """Uniform noise in ``[0, 1)`` at every node, ``(1, channels, D, H, W)``, seeded, drawn in
    float32 for float64 too, as :func:`gaussian_noise`'s. Every entry of a batch shares it; packed
    ``(N, channels, 8, 8, 8)`` on bricks, each entry gets what its dense grid gets alone, node
    for node (the same numbers on entries of one box)."""
    channels = check_count(channels, "channels")
    if surface.layout is not None:
        volumes = [_uniform_volume(channels, grid, seed, surface.phi.dtype)
                   for grid in surface.grids]
        return surface.layout.from_dense(volumes).to(surface.phi.device)
    values = _uniform_volume(channels, surface.grid, seed, surface.phi.dtype)
    return values.to(surface.phi.device)


def _uniform_volume(channels: int, grid: Grid, seed: int, dtype: torch.dtype) -> Tensor:
    """``(1, channels, *grid.shape)`` uniform numbers in ``[0, 1)`` of ``seed``, as ``dtype``."""
    values = torch.rand((1, channels, *grid.shape), generator=generator(seed),
                        dtype=_drawn_as(dtype))
    return values.to(dtype)


def surface_noise(surface: ImplicitSurface, channels: int, seed: int, grain: float = 1.0
                  ) -> Tensor:
    """Seeded value noise on S, constant along the normals: ``(1, channels, D, H, W)`` (packed
    ``(N, channels, 8, 8, 8)`` on bricks, the same values at the same nodes).

    Uniform values in ``[0, 1)`` on a lattice of spacing ``grain`` cells, interpolated
    trilinearly at each node's closest point on S (:func:`closest_points`). ``grain`` sets the
    size of the noise's specks: flow visualisation (the paper's §3.4) draws streaks as wide as
    them, and specks of one cell are averaged away by the pictures' trilinear sampling.

    Args:
        surface: the surface (batch 1).
        channels: number of independent noise channels.
        seed: the seed; the same seed and grain give the same noise.
        grain: lattice spacing, cells, > 0.
    """
    channels = check_count(channels, "channels")
    grain = check_positive(grain, "grain")
    grid = surface.grid
    if surface.batch_size != 1:
        raise ValueError(f"surface must hold one shape, got a batch of {surface.batch_size}")
    lattice = Grid(tuple(math.ceil((n - 1) / grain) + 1 for n in grid.shape),
                   grain * grid.spacing, grid.origin)
    _memory.check_fits(channels * math.prod(lattice.shape) * surface.phi.dtype.itemsize,
                       f"surface_noise's lattice of grain {grain:g} cells {lattice.shape} (a "
                       "grain below 1 cell draws specks the grid cannot show)",
                       surface.phi.device)
    values = _uniform_volume(channels, lattice, seed, surface.phi.dtype).to(surface.phi.device)
    low = torch.tensor(grid.origin, dtype=values.dtype, device=values.device)
    high = low + torch.tensor(grid.size, dtype=values.dtype, device=values.device)
    # nodes far from S can have closest points outside the box: their values are never read
    points = closest_points(surface)
    shape = (points.shape[0], channels, *points.shape[2:])
    points = points.permute(0, 2, 3, 4, 1).reshape(-1, 3)
    points = torch.minimum(torch.maximum(points, low), high)
    values = sample(values, points, lattice)[0]  # (C, M), M nodes in the order of `shape`
    return values.view(channels, shape[0], -1).transpose(0, 1).reshape(shape)


def axis_field(surface: ImplicitSurface, axis: str = "z") -> Tensor:
    """The tangent part of a coordinate axis, ``P e_axis / |P e_axis|`` (the projected gradient
    of that coordinate), ``(B, 3, D, H, W)``; undefined (0-length before normalising) where the
    normal is along the axis."""
    direction = torch.zeros_like(surface.normal)
    direction[:, _axis_index(axis)] = 1.0
    return tangent_unit(direction, surface)


def swirl_field(surface: ImplicitSurface, axis: str = "z",
                centre: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Tensor:
    """The rotation about an axis through ``centre``, ``e_axis x (x - centre)``, made tangent
    and unit: ``(B, 3, D, H, W)``. On a surface of revolution about that axis it is already
    tangent (the parallels: on a torus, the minor principal direction, oriented); it vanishes
    only on the axis."""
    centre = check_triple(centre, "centre", check_real)
    points = node_points(surface)
    offset = points - points.new_tensor(centre).view(1, 3, 1, 1, 1)
    direction = torch.zeros_like(offset)
    direction[:, _axis_index(axis)] = 1.0
    return tangent_unit(torch.cross(direction, offset, dim=1), surface)


def orient(field: Tensor, reference: Tensor) -> Tensor:
    """``field`` with each vector's sign flipped to agree with ``reference`` (both
    ``(B, 3, D, H, W)``): a line field (principal directions, defined up to sign) made a
    vector field wherever the reference is smooth."""
    check_volume(field, "field", channels=3)
    check_volume(reference, "reference", channels=3)
    if (reference.dtype, reference.device) != (field.dtype, field.device):
        raise MismatchError(f"reference is {reference.dtype} on {reference.device} but field is "
                            f"{field.dtype} on {field.device}: they must match")
    if reference.shape[2:] != field.shape[2:] or reference.shape[0] not in (1, field.shape[0]):
        raise ValueError(f"reference must be (B or 1, 3, D, H, W) with field's B and (D, H, W), "
                         f"{tuple(field.shape)}, got shape {tuple(reference.shape)}")
    sign = torch.where((field * reference).sum(dim=1, keepdim=True) < 0, -1.0, 1.0)
    return field * sign.to(field.dtype)


def _line_tensor(direction: Tensor) -> Tensor:
    """``e e^T`` packed as ``(B, 6, ...)``: xx, yy, zz, xy, xz, yz (the same for ``-e``)."""
    x, y, z = direction.unbind(dim=1)
    return torch.stack((x * x, y * y, z * z, x * y, x * z, y * z), dim=1)


def _major_tangent(tensor: Tensor, normal: Tensor) -> Tensor:
    """The unit tangent eigenvector of the largest eigenvalue of a packed symmetric tensor,
    closed form in a tangent basis."""
    xx, yy, zz, xy, xz, yz = tensor.unbind(dim=1)
    t1, t2 = tangent_basis(normal)

    def quadratic(a: Tensor, b: Tensor) -> Tensor:
        ax, ay, az = a.unbind(dim=1)
        bx, by, bz = b.unbind(dim=1)
        return (ax * (xx * bx + xy * by + xz * bz) + ay * (xy * bx + yy * by + yz * bz)
                + az * (xz * bx + yz * by + zz * bz))

    angle = 0.5 * torch.atan2(2.0 * quadratic(t1, t2), quadratic(t1, t1) - quadratic(t2, t2))
    return torch.cos(angle)[:, None] * t1 + torch.sin(angle)[:, None] * t2


def principal_direction(surface: ImplicitSurface, which: str = "max", smoothing: float = 0.0,
                        coarse: ImplicitSurface | None = None) -> Tensor:
    """A unit principal direction field, raw or smoothed, ``(B, 3, D, H, W)``, up to sign.

    ``which="max"`` follows the larger principal curvature ``k1``, ``"min"`` the smaller
    (:meth:`ImplicitSurface.principal_directions`). With ``smoothing > 0`` the line field is
    smoothed without regard to sign: the tensor ``|k1 - k2| e e^T`` (directions weighted by how
    well they are defined, so flat and umbilic regions take their neighbours' direction) is
    run through the heat flow for a diffusion length of ``smoothing`` cells
    (``t = (smoothing h)^2 / 2``), and the direction is its major tangent eigenvector. On a
    scanned or faceted mesh the raw directions change from node to node; smoothed, they
    follow the shape.

    The heat flow's cost grows with the area in cells times ``smoothing^2``; over many cells of a
    fine grid, give ``coarse``, the same shape on a coarser grid: the tensor is then formed and
    smoothed there, for the same length in world units, and read back (trilinear) at the
    closest points on S of this surface's nodes. At 256^3 on the teapot, 16 cells took 65 s on
    the surface itself and 14 s on a 128^3 ``coarse`` (docs/cli.md). The coarse grid must
    still span several cells of smoothing: its own raw directions jitter from node to node.

    Args:
        surface: the surface.
        which: ``"max"`` or ``"min"``.
        smoothing: diffusion length, cells of ``surface``; 0 for the raw directions.
        coarse: optional surface (dense or bricks) of the same shape and batch on a coarser
            grid, to smooth on (only with ``smoothing > 0``).

    Returns:
        ``(B, 3, D, H, W)``, or packed ``(N, 3, 8, 8, 8)`` on a
        :class:`~torchsurf.bricks.BrickSurface`.
    """
    check_choice(which, "which", ("max", "min"))
    smoothing = check_nonnegative(smoothing, "smoothing")
    if smoothing == 0.0:
        if coarse is not None:
            raise ValueError("coarse: only used with smoothing > 0 (the raw directions are "
                             "the surface's own)")
        e1, e2 = surface.principal_directions()
        return e1 if which == "max" else e2
    length = smoothing * surface.spacing
    if coarse is None:
        smoothed = _smoothed_line_tensor(surface, length)
    else:
        _check_coarse(coarse, surface)
        smoothed = _at_closest_points(_smoothed_line_tensor(coarse, length), coarse, surface)
    major = _major_tangent(smoothed, surface.normal)
    if which == "max":
        return major
    return tangent_unit(torch.cross(surface.normal, major, dim=1), surface)


EULER_SMOOTHING_STEPS = 32
"""Smoothings that explicit Euler does in at most this many steps take it instead of RKC."""

SMOOTHING_STEP = 108.0
"""``dt * rho`` of the RKC steps of a longer smoothing (at least :data:`SMOOTHING_STEPS` of
them). A direction field's smoothing needs no second-order accuracy: on a mesh's 3-cell band
the heat flow's own steps, at most ``12 / rho`` long there (docs/band.md, section 1), took the
16-cell smoothing of ``stripes_teapot`` at 64^3 from 1.2 s to 3.1 s."""

SMOOTHING_STEPS = 16
"""Fewest RKC steps of a smoothing (RKC's own fewest where its stages re-extend the ring)."""


def _smoothed_line_tensor(surface: ImplicitSurface, length: float) -> Tensor:
    """``|k1 - k2| e1 e1^T`` (packed, :func:`_line_tensor`) after a heat flow of diffusion
    length ``length`` (world units)."""
    e1, _ = surface.principal_directions()
    k1, k2 = surface.principal_curvatures()
    tensor = (k1 - k2).abs() * _line_tensor(e1)
    time = 0.5 * length**2
    explicit_steps = time * laplace_beltrami_bound(surface) / 2.0
    # Short smoothings take Euler: RKC's fewest steps re-extend the ring at every stage (over
    # 2 cells on the knot at 256^3: 4.2 s against 32.5 s, the same field to 1e-3 on average)
    if explicit_steps <= EULER_SMOOTHING_STEPS:
        flow = HeatFlow(time, method="euler")
    else:
        flow = HeatFlow(time, steps=max(SMOOTHING_STEPS,
                                        math.ceil(2.0 * explicit_steps / SMOOTHING_STEP)))
    return flow(tensor, surface)


def _check_coarse(coarse: ImplicitSurface, surface: ImplicitSurface) -> None:
    if not isinstance(coarse, ImplicitSurface):
        raise TypeError(f"coarse must be a torchsurf.ImplicitSurface (or BrickSurface), got "
                        f"{type(coarse).__name__}")
    if coarse.batch_size != surface.batch_size:
        raise ValueError(f"coarse must have the surface's batch size {surface.batch_size}, got "
                         f"{coarse.batch_size}")
    if coarse.spacing < surface.spacing:
        raise ValueError(f"coarse must be coarser than the surface: spacing {coarse.spacing:g} "
                         f"< {surface.spacing:g}")


def _at_closest_points(field: Tensor, coarse: ImplicitSurface, surface: ImplicitSurface
                       ) -> Tensor:
    """``field`` on ``coarse``, read (trilinear) at the closest points on S of ``surface``'s
    nodes; 0 at nodes whose closest point ``coarse`` cannot read (far from S, where ``phi``
    need not be a distance and no flow reads the field)."""
    points = torch.nan_to_num(closest_points(surface).to(field.dtype))
    channels = field.shape[1]
    out = points.new_zeros((points.shape[0], channels, *points.shape[2:]))
    entries = ([(torch.tensor([b]), None) for b in range(surface.batch_size)]
               if surface.layout is None else surface.entries())
    for b, (rows, _) in enumerate(entries):
        flat = points[rows].permute(0, 2, 3, 4, 1).reshape(-1, 3)
        if coarse.layout is None:
            readable = coarse.grid.contains(flat)
            values = sample(field[b:b + 1], flat[readable], coarse.grid)[0]
        else:
            readable = coarse.samplable(flat, b)
            values = coarse.sample(field, flat[readable], b)
        spread = values.new_zeros((channels, flat.shape[0]))
        spread[:, readable] = values
        out[rows] = spread.view(channels, len(rows), *points.shape[2:]).transpose(0, 1)
    return out


def perturb_field(field: Tensor, surface: ImplicitSurface, std: float, seed: int) -> Tensor:
    """``field`` ``(B, 3, D, H, W)`` (packed ``(N, 3, 8, 8, 8)`` on a
    :class:`~torchsurf.bricks.BrickSurface`) plus seeded Gaussian noise of ``std`` per
    component, made tangent and unit."""
    check_data(field, "field", surface, channels=3)
    return tangent_unit(field + gaussian_noise(field, std, seed, surface), surface)


def rgb_to(rgb: Tensor, space: str) -> Tensor:
    """RGB volume ``(B, 3, D, H, W)`` in ``[0, 1]`` to another colour space (kornia's
    conventions: HSV hue in radians, Lab ``L`` in ``[0, 100]``)."""
    check_volume(rgb, "rgb", channels=3)
    check_choice(space, "space", COLOUR_SPACES)
    convert = getattr(kornia.color, f"rgb_to_{space}")
    return _as_images(convert, rgb)


def rgb_from(values: Tensor, space: str) -> Tensor:
    """The inverse of :func:`rgb_to`: ``(B, 3, D, H, W)`` in ``space`` to RGB."""
    check_volume(values, "values", channels=3)
    check_choice(space, "space", COLOUR_SPACES)
    convert = getattr(kornia.color, f"{space}_to_rgb")
    return _as_images(convert, values)


def gray(rgb: Tensor) -> Tensor:
    """Luma of an RGB volume ``(B, 3, D, H, W)`` -> ``(B, 1, D, H, W)`` (kornia's weights)."""
    check_volume(rgb, "rgb", channels=3)
    return _as_images(kornia.color.rgb_to_grayscale, rgb)


def _as_images(convert, volume: Tensor) -> Tensor:  # noqa: ANN001
    """Apply a kornia colour function ``(*, 3, H, W) -> (*, C, H, W)`` to ``(B, 3, D, H, W)``."""
    batch, _, depth, height, width = volume.shape
    result = convert(volume.reshape(batch, 3, depth * height, width))
    return result.reshape(batch, -1, depth, height, width)


def chroma_brightness(rgb: Tensor, eps: float = 1e-6) -> tuple[Tensor, Tensor]:
    """Split RGB ``(B, 3, D, H, W)`` into chroma ``I / |I|`` ``(B, 3, ...)`` (unit vectors) and
    brightness ``|I|`` ``(B, 1, ...)``, ``|I|`` regularised as ``sqrt(|I|^2 + eps^2)``
    (the paper's §3.2, colour denoising)."""
    check_volume(rgb, "rgb", channels=3)
    eps = check_positive(eps, "eps")
    brightness = torch.sqrt((rgb**2).sum(dim=1, keepdim=True) + eps**2)
    return rgb / brightness, brightness
