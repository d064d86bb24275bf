"""Finite-difference stencils, defined once, and the two ways of applying them.

A :class:`Stencil` is a list of taps (offset, weight) in index units on a 3x3x3 neighbourhood.
Each stencil exists as a conv3d kernel (:meth:`Stencil.kernel`) and as shifted slices; both
paths read the same taps, so they give the same numbers (tests check it).

Padding is a separate step (:func:`pad`, :func:`pad_flux`): a stencil is applied to a volume
that already carries a halo of one node on every side, and returns the interior. A later
narrow-band layout supplies its own halos and reuses the stencil step unchanged.

Axis conventions: a volume is ``(..., D, H, W)``; offsets are ``(dz, dy, dx)`` in that order;
vector components (and stencil banks of first derivatives) are in ``(x, y, z)`` order.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from . import backend
from ._checks import check_choice
from ._precision import in_data_dtype

__all__ = [
    "BACKWARD",
    "CENTRAL",
    "CENTRE",
    "FORWARD",
    "HESSIAN",
    "MIXED",
    "NEIGHBOURHOOD",
    "PAD_MODES",
    "PATHS",
    "SECOND",
    "BoxNeighbours",
    "Stencil",
    "add",
    "apply",
    "contract",
    "masked",
    "neighbour_in_box",
    "neighbourhood_column",
    "one_sided",
    "opposite",
    "pad",
    "pad_flux",
    "pad_mirrored",
    "per_axis",
    "shifted",
    "unit",
]

Offset = tuple[int, int, int]

PATHS = ("auto", "slicing", "conv3d")
PAD_MODES = ("replicate", "linear", "quadratic", "zeros")


@dataclass(frozen=True)
class Stencil:
    """A finite-difference stencil: taps ``((dz, dy, dx), weight)`` within one node of the centre.

    Weights are in index units: divide the result by ``spacing ** order``.
    """

    name: str
    taps: tuple[tuple[Offset, float], ...]

    def kernel(self, dtype: torch.dtype | None = None, device: torch.device | str | None = None
               ) -> Tensor:
        """The stencil as a ``(3, 3, 3)`` conv3d kernel (cross-correlation, centre at ``[1,1,1]``)."""
        kernel = torch.zeros(3, 3, 3, dtype=dtype, device=device)
        for (dz, dy, dx), weight in self.taps:
            kernel[1 + dz, 1 + dy, 1 + dx] += weight
        return kernel


def unit(axis: int, step: int = 1) -> Offset:
    """Offset ``(dz, dy, dx)`` of ``step`` nodes along world axis ``axis`` (0 = x, 1 = y, 2 = z)."""
    offset = [0, 0, 0]
    offset[2 - axis] = step
    return tuple(offset)


def add(a: Offset, b: Offset) -> Offset:
    """The offset ``a + b``."""
    return tuple(p + q for p, q in zip(a, b, strict=True))


_AXES = "xyz"
CENTRE: Offset = (0, 0, 0)


NEIGHBOURHOOD: list[Offset] = [(dz, dy, dx) for dz in (-1, 0, 1) for dy in (-1, 0, 1)
                               for dx in (-1, 0, 1)]
"""The 27 offsets of a node's 3x3x3 block, ``dz`` slowest: the columns of an assembled
operator's rows (:func:`torchsurf.operators.spectrum.laplace_beltrami_rows`)."""


def neighbour_in_box(at: Sequence[Tensor], offset: Offset, shape: Sequence[int]
                     ) -> tuple[Tensor, list[Tensor]]:
    """Nodes ``at + offset`` clamped to the box, as replicated data reads them.

    Args:
        at: ``(z, y, x)`` grid indices, ``(R,)`` each.
        offset: ``(dz, dy, dx)``.
        shape: the box ``(D, H, W)``.

    Returns:
        The flat positions ``(R,)`` in one ``D x H x W`` volume, and per index ``(z, y, x)``
        whether the node lay beyond the box (bool ``(R,)``).
    """
    moved = [a + o for a, o in zip(at, offset, strict=True)]
    beyond = [(m < 0) | (m >= n) for m, n in zip(moved, shape, strict=True)]
    z, y, x = (m.clamp(0, n - 1) for m, n in zip(moved, shape, strict=True))
    return (z * shape[1] + y) * shape[2] + x, beyond


class BoxNeighbours:
    """Nodes of one ``D x H x W`` box and their neighbours within one node, as
    :func:`neighbour_in_box` and :func:`neighbourhood_column` give them, formed once for many
    offsets.

    When no node lies on a face of the box (a band away from the box's faces: the usual case),
    every neighbour is a fixed flat offset away and none lies beyond a face; the arithmetic then
    takes one addition per offset instead of a dozen passes.

    Args:
        at: ``(z, y, x)`` grid indices, ``(R,)`` each, within the box.
        shape: the box ``(D, H, W)``.
    """

    def __init__(self, at: Sequence[Tensor], shape: Sequence[int]) -> None:
        self.at, self.shape = tuple(at), tuple(int(n) for n in shape)
        z, y, x = self.at
        self.flat = (z * self.shape[1] + y) * self.shape[2] + x
        on_face = torch.zeros_like(z, dtype=torch.bool)
        for a, n in zip(self.at, self.shape, strict=True):
            on_face |= (a <= 0) | (a >= n - 1)
        self.on_faces = bool(on_face.any())  # one host read for every offset

    def delta(self, offset: Offset) -> int:
        """The flat distance of ``offset`` in the box."""
        dz, dy, dx = offset
        return (dz * self.shape[1] + dy) * self.shape[2] + dx

    def neighbour(self, offset: Offset) -> tuple[Tensor, list[Tensor] | None]:
        """:func:`neighbour_in_box` of ``offset``: the clamped flat positions ``(R,)`` and, per
        index ``(z, y, x)``, whether the node lay beyond the box; ``None`` for the latter when
        no node is on a face (none lies beyond)."""
        if self.on_faces:
            return neighbour_in_box(self.at, offset, self.shape)
        return self.flat + self.delta(offset), None

    def column(self, offset: Offset) -> int | Tensor:
        """:func:`neighbourhood_column` of ``offset``: one index into :data:`NEIGHBOURHOOD`
        when no node is on a face, else ``(R,)``."""
        if self.on_faces:
            return neighbourhood_column(offset, neighbour_in_box(self.at, offset, self.shape)[1])
        dz, dy, dx = offset
        return ((dz + 1) * 3 + dy + 1) * 3 + dx + 1


def neighbourhood_column(offset: Offset, beyond: Sequence[Tensor]) -> Tensor:
    """The index in :data:`NEIGHBOURHOOD` of ``offset`` folded onto the box: its components
    that lead beyond the box (``beyond``, from :func:`neighbour_in_box`) set to 0, as
    replicated data folds a node beyond a face onto the face node. ``(R,)`` int64."""
    folded = [torch.where(out, 0, o) + 1 for out, o in zip(beyond, offset, strict=True)]
    return (folded[0] * 3 + folded[1]) * 3 + folded[2]

FORWARD: tuple[Stencil, ...] = tuple(
    Stencil(f"forward_{_AXES[a]}", ((CENTRE, -1.0), (unit(a), 1.0))) for a in range(3)
)
"""Forward differences ``u[i+1] - u[i]`` along x, y, z."""

BACKWARD: tuple[Stencil, ...] = tuple(
    Stencil(f"backward_{_AXES[a]}", ((unit(a, -1), -1.0), (CENTRE, 1.0))) for a in range(3)
)
"""Backward differences ``u[i] - u[i-1]`` along x, y, z."""

CENTRAL: tuple[Stencil, ...] = tuple(
    Stencil(f"central_{_AXES[a]}", ((unit(a, -1), -0.5), (unit(a), 0.5))) for a in range(3)
)
"""Central differences ``(u[i+1] - u[i-1]) / 2`` along x, y, z."""

SECOND: tuple[Stencil, ...] = tuple(
    Stencil(f"second_{_AXES[a] * 2}", ((unit(a, -1), 1.0), (CENTRE, -2.0), (unit(a), 1.0)))
    for a in range(3)
)
"""Second differences ``u[i+1] - 2 u[i] + u[i-1]`` along x, y, z."""

_PAIRS = ((0, 1), (0, 2), (1, 2))

MIXED: tuple[Stencil, ...] = tuple(
    Stencil(
        f"mixed_{_AXES[a]}{_AXES[b]}",
        tuple(
            (add(unit(a, sa), unit(b, sb)), 0.25 * sa * sb) for sa in (1, -1) for sb in (1, -1)
        ),
    )
    for a, b in _PAIRS
)
"""Central mixed differences for xy, xz, yz."""

HESSIAN: tuple[Stencil, ...] = SECOND + MIXED
"""Second derivatives in the order xx, yy, zz, xy, xz, yz."""


Side = int | tuple[int, int, int]


def per_axis(side: Side) -> tuple[int, int, int]:
    """``side`` as one sign per axis ``(x, y, z)``: +1 forward differences, -1 backward."""
    sides = (side,) * 3 if isinstance(side, int) else tuple(side)
    if len(sides) != 3 or any(s not in (1, -1) for s in sides):
        raise ValueError(f"side must be +1, -1 or three of them (x, y, z), got {side!r}")
    return sides


def opposite(side: Side) -> tuple[int, int, int]:
    """The other one-sided differences on every axis."""
    return tuple(-s for s in per_axis(side))


def one_sided(side: Side) -> tuple[Stencil, ...]:
    """One-sided differences along x, y, z: forward where ``side`` is +1, backward where -1.

    ``side`` is one sign for all three axes or a sign per axis.
    """
    return tuple((FORWARD if s == 1 else BACKWARD)[a] for a, s in enumerate(per_axis(side)))


def _check_layout(value: object, name: str, layout: str, ndim: int,
                  components: int | None = None, minimum: int = 1, floating: bool = True
                  ) -> Tensor:
    """Raise naming ``name`` unless ``value`` is a tensor (floating, if ``floating``) of
    ``ndim`` dimensions (``layout`` its description), dimension ``ndim - 4`` holding
    ``components`` if given, and at least ``minimum`` nodes along each of the last three axes."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a tensor {layout}, got {type(value).__name__}")
    shape = tuple(value.shape)
    if (value.dim() != ndim or (components is not None and shape[ndim - 4] != components)
            or min(shape[-3:]) < minimum):
        nodes = f" with at least {minimum} nodes a side" if minimum > 1 else ""
        raise ValueError(f"{name} must be {layout}{nodes}, got shape {shape}")
    if floating and not value.is_floating_point():
        raise TypeError(f"{name} must be a floating-point tensor {layout}, got dtype "
                        f"{value.dtype}")
    return value


def replicated_shifts(volume: Tensor, dim: int) -> tuple[Tensor, Tensor]:
    """Each node's neighbours before and after it along ``dim``, the first and last node
    standing for their missing ones: two tensors shaped like ``volume``, formed by
    concatenation (traced graphs fuse it; inductor did not compile in-place ORs of bool
    views)."""
    length = volume.shape[dim]
    before = torch.cat([volume.narrow(dim, 0, 1), volume.narrow(dim, 0, length - 1)], dim)
    after = torch.cat([volume.narrow(dim, 1, length - 1), volume.narrow(dim, length - 1, 1)], dim)
    return before, after


def replicated_halo(volume: Tensor, width: int) -> Tensor:
    """``volume`` ``(B, C, D, H, W)`` with a halo of ``width`` copies of its edge nodes on
    every side of the last three axes: ``(B, C, D + 2 width, H + 2 width, W + 2 width)``.
    While traced, by concatenating each face's copies: ``F.pad(mode="replicate")``'s clamped
    indices, read through a gather (the band's re-extension), stopped inductor's range
    analysis in torch 2.13 (``vr must not be None``)."""
    if not torch.compiler.is_compiling():
        return F.pad(volume, (width,) * 6, mode="replicate")
    return _replicated_halo_traced(volume, width)


def _replicated_halo_traced(volume: Tensor, width: int) -> Tensor:
    """:func:`replicated_halo` by concatenation."""
    for dim in (2, 3, 4):
        first = volume.narrow(dim, 0, 1).expand(*volume.shape[:dim], width, *volume.shape[dim + 1:])
        last = volume.narrow(dim, volume.shape[dim] - 1, 1).expand_as(first)
        volume = torch.cat([first, volume, last], dim)
    return volume


def pad(volume: Tensor, mode: str = "replicate") -> Tensor:
    """Add a halo of one node on every side of the last three axes.

    Args:
        volume: ``(B, C, D, H, W)``.
        mode: ``"replicate"`` copies the edge (zero normal derivative: the data's default),
            ``"linear"`` extrapolates ``2 u[0] - u[1]`` (exact for affine fields),
            ``"quadratic"`` extrapolates ``3 u[0] - 3 u[1] + u[2]`` (exact for quadratic
            fields; along the diagonal at edges and corners: the default for ``phi``, whose
            central differences at the face nodes are then the second-order one-sided ones),
            ``"zeros"`` fills zeros. The last three axes need at least 3 nodes for
            ``"quadratic"``.

    Returns:
        ``(B, C, D + 2, H + 2, W + 2)``.
    """
    check_choice(mode, "mode", PAD_MODES)
    _check_layout(volume, "volume", "(B, C, D, H, W)", 5, minimum=2 if mode == "linear" else 1,
                  floating=mode in ("linear", "quadratic"))  # extrapolation would promote
    if volume.dtype == torch.bool and mode != "zeros":
        raise TypeError(f"volume is a bool mask, which pads with mode='zeros' only, got "
                        f"mode={mode!r}")
    halo = (1, 1, 1, 1, 1, 1)
    if mode == "zeros":
        return F.pad(volume, halo)
    replicated = F.pad(volume, halo, mode="replicate")
    if mode == "replicate":
        return replicated
    reflected = F.pad(volume, halo, mode="reflect")
    if mode == "linear":
        return 2.0 * replicated - reflected
    if min(volume.shape[-3:]) < 3:
        raise ValueError(f"volume must have at least 3 nodes along each of its last three axes "
                         f"for mode='quadratic', got shape {tuple(volume.shape)}")
    return 3.0 * (replicated - reflected) + _reflected_twice(volume)


def _reflected_twice(volume: Tensor) -> Tensor:
    """``volume`` with a halo of one node holding the values two nodes in from each face
    (``u[2]`` beyond ``u[0]``; ``u[2, 2]`` at an edge), ``(B, C, D + 2, H + 2, W + 2)``."""
    wide = F.pad(volume, (2, 2, 2, 2, 2, 2), mode="reflect")
    for dim in (-3, -2, -1):
        n = volume.shape[dim]
        keep = torch.tensor([0, *range(2, n + 2), n + 3], device=volume.device)
        wide = wide.index_select(dim, keep)
    return wide


def pad_mirrored(field: Tensor) -> Tensor:
    """Halo a vector field by mirroring it in the faces of the grid's box.

    Values are replicated, and the component normal to each face changes sign in the halo
    beyond that face (``n_x`` beyond the faces ``x = const``, ...): the reflection of the field
    that goes with replicated data. A normal field haloed this way makes every cross
    coefficient ``n_a n_b`` (``a != b``) odd across the faces, which is what the octant scheme
    needs there (:mod:`torchsurf.operators._octant`).

    Args:
        field: ``(B, 3, D, H, W)``, components in ``(x, y, z)`` order.

    Returns:
        ``(B, 3, D + 2, H + 2, W + 2)``.
    """
    _check_layout(field, "field", "(B, 3, D, H, W)", 5, components=3, floating=False)
    if field.dtype == torch.bool or not (field.is_floating_point() or field.dtype.is_signed):
        raise TypeError(f"field must hold signed numbers (its halo changes their sign), got dtype "
                        f"{field.dtype}")
    replicated = F.pad(field, (1, 1, 1, 1, 1, 1), mode="replicate")
    components = []
    for axis in range(3):
        component = replicated[:, axis: axis + 1]
        dim = component.dim() - 1 - axis
        length = component.shape[dim]
        index = torch.arange(length, device=field.device)
        halo = (index == 0) | (index == length - 1)
        sign = torch.where(halo, -1.0, 1.0).to(field.dtype)
        shape = [1] * component.dim()
        shape[dim] = length
        components.append(component * sign.view(shape))
    return torch.cat(components, dim=1)


def pad_flux(flux: Tensor, side: Side) -> Tensor:
    """Halo a face-centred flux so that nothing flows through the faces of the grid's box.

    A one-sided gradient of side ``+1`` puts component ``x`` of node ``i`` on the face
    ``i + 1/2``; the face beyond the last node lies outside the box and carries no flux
    (side ``-1``: the face before the first node). Those values are zeroed and the halo is
    zero, which makes the divergence applied next the exact negative adjoint of the
    replicate-padded one-sided gradient.

    Args:
        flux: ``(B, C, 3, D, H, W)``, components in ``(x, y, z)`` order.
        side: ``+1`` or ``-1`` (or one per axis), the side of the differences that produced
            the flux.

    Returns:
        ``(B, C, 3, D + 2, H + 2, W + 2)``.
    """
    _check_layout(flux, "flux", "(B, C, 3, D, H, W)", 6, components=3, floating=False)
    sides = per_axis(side)
    components = []
    for axis in range(3):
        component = flux[:, :, axis]
        dim = component.dim() - 1 - axis
        length = component.shape[dim]
        if sides[axis] == 1:
            inner = component.narrow(dim, 0, length - 1)
            low, high = 1, 2
        else:
            inner = component.narrow(dim, 1, length - 1)
            low, high = 2, 1
        widths = [1, 1, 1, 1, 1, 1]
        widths[2 * axis], widths[2 * axis + 1] = low, high
        components.append(F.pad(inner, widths))
    return torch.stack(components, dim=2)


def _concrete(path: str, volume: Tensor) -> str:
    """``path`` made concrete: ``"auto"`` is the faster eager path for the device
    (:func:`torchsurf.backend.eager_path`)."""
    check_choice(path, "path", PATHS)
    return backend.eager_path(volume) if path == "auto" else path


def masked(result: Tensor, mask: Tensor | None) -> Tensor:
    """``result`` with zeros where ``mask`` (bool, broadcastable) is false; ``None``: as it is.
    One pointwise step, so a compiled operator applies a flow's band in its own pass."""
    return result if mask is None else torch.where(mask, result, 0.0)


def shifted(padded: Tensor, offset: Offset) -> Tensor:
    """The interior of a halo-1 volume shifted by ``offset``: ``u[k + dz, j + dy, i + dx]``."""
    dz, dy, dx = offset
    depth, height, width = (n - 2 for n in padded.shape[-3:])
    return padded[..., 1 + dz: 1 + dz + depth, 1 + dy: 1 + dy + height, 1 + dx: 1 + dx + width]


def _sliced(padded: Tensor, stencil: Stencil) -> Tensor:
    result = None
    for offset, weight in stencil.taps:
        term = weight * shifted(padded, offset)
        result = term if result is None else result + term
    return result


def _bank_kernel(bank: Sequence[Stencil], like: Tensor) -> Tensor:
    return torch.stack([s.kernel(dtype=like.dtype, device=like.device) for s in bank])


def apply(padded: Tensor, bank: Sequence[Stencil], path: str = "auto") -> Tensor:
    """Apply every stencil of ``bank`` to every channel of a haloed volume.

    Args:
        padded: ``(B, C, D + 2, H + 2, W + 2)``, e.g. from :func:`pad`.
        bank: ``K`` stencils.
        path: ``"slicing"``, ``"conv3d"`` or ``"auto"`` (the faster for the device).

    Returns:
        ``(B, C, K, D, H, W)`` in index units.
    """
    _check_layout(padded, "padded", "(B, C, D + 2, H + 2, W + 2)", 5, minimum=3)
    path = _concrete(path, padded)
    if path == "slicing":
        return torch.stack([_sliced(padded, stencil) for stencil in bank], dim=2)
    batch, channels = padded.shape[:2]
    weight = _bank_kernel(bank, padded)[:, None]
    with in_data_dtype(padded):
        out = F.conv3d(padded.reshape(batch * channels, 1, *padded.shape[2:]), weight)
    return out.view(batch, channels, len(bank), *out.shape[2:])


def contract(padded: Tensor, bank: Sequence[Stencil], path: str = "auto") -> Tensor:
    """Apply stencil ``k`` of ``bank`` to component ``k`` and sum: a divergence-like contraction.

    Args:
        padded: ``(B, C, K, D + 2, H + 2, W + 2)``, e.g. from :func:`pad_flux`.
        bank: ``K`` stencils.
        path: as in :func:`apply`.

    Returns:
        ``(B, C, D, H, W)`` in index units.
    """
    _check_layout(padded, "padded", f"(B, C, {len(bank)}, D + 2, H + 2, W + 2) for a bank of "
                  f"{len(bank)} stencils", 6, components=len(bank), minimum=3)
    path = _concrete(path, padded)
    if path == "slicing":
        result = _sliced(padded[:, :, 0], bank[0])
        for k in range(1, len(bank)):
            result = result + _sliced(padded[:, :, k], bank[k])
        return result
    batch, channels, components = padded.shape[:3]
    weight = _bank_kernel(bank, padded)[None]
    with in_data_dtype(padded):
        out = F.conv3d(padded.reshape(batch * channels, components, *padded.shape[3:]), weight)
    return out.view(batch, channels, *out.shape[2:])
