"""Coupled edge-stopping diffusion and the harmonic-map rate, by faces, in two passes.

``L u = (1/W) div(W g(|P grad u|) P grad u)`` with ``|P grad u|^2`` summed over the channels
(the p-harmonic map's diffusion, the paper's eq. 11), in the flux form of :mod:`._flux_form`:
per composition ``s`` (:data:`SIDES`), ``v_s = P D_s u`` and ``a_s = W g(|v_s|)``. Optionally
plus ``u (E + eps^2)^power`` with ``E = sum_c |P grad u_c|^2`` by central differences (the
harmonic map's energy term) and zero outside a mask (the band).

Writing ``v_s = D_s u - n m_s`` with ``m_s = n . D_s u``, every composition that crosses the face
between a node ``x`` and ``x + e_a`` differences ``u`` across that face, so the face carries

    Phi_a(x) = K_a(x) (u(x + e_a) - u(x)) - sum_s n_a(y_s) a_s(y_s) m_s(y_s),
    K_a(x) = sum_s a_s(y_s),   y_s = x if s_a = +1, x + e_a if s_a = -1,

and ``L u (x) = sum_a [Phi_a(x) - Phi_a(x - e_a)] / (h^2 S W)``, ``S`` compositions, no flux
through the faces of the grid's box. The same numbers as :func:`._flux_form.flux_form` with the
coupled flux map, to rounding.

Pass one reads every channel at every node of the grid plus one halo layer and keeps ``a_s``
(and the energy factor); pass two forms the faces. ``g`` depends on all channels, so fusing
the passes would recompute it for every channel's neighbours (3.5x slower at 3 channels).

- :func:`fused_coupled_rate`: the passes as two pointwise expressions for the compiler,
  the second recomputing ``m_s`` where it needs it (cheaper than storing it per channel).
- :func:`eager_coupled_rate`: the same numbers op by op, each face's flux formed once, over
  views of one padded input.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .. import stencils
from ..stencils import Offset, shifted
from ._flux_form import SIDES, _haloed_slice, _open_faces
from .diffusivity import Diffusivity


def _squared_sum(parts: list[Tensor]) -> Tensor:
    total = parts[0] * parts[0]
    for part in parts[1:]:
        total = total + part * part
    return total


def _channel_sum(values: list[Tensor]) -> Tensor:
    total = values[0]
    for value in values[1:]:
        total = total + value
    return total


def _face_scales(
    padded_u: Tensor, haloed_normal: Tensor, haloed_weight: Tensor, spacing: float,
    diffusivity: Diffusivity, contrast: float | Tensor, eps: float, scheme: str,
    power: float | None,
) -> tuple[list[Tensor], Tensor | None]:
    """Pass one, fused: ``a_s = W g(|P D_s u|)`` per composition on the haloed grid, and
    ``(E + eps^2)^power`` on the haloed grid (``None`` without ``power``).

    Written per channel, so that the channel sums stay inside one loop when compiled.
    """
    normal = [haloed_normal[:, a: a + 1] for a in range(3)]
    channels = [padded_u[:, c: c + 1] for c in range(padded_u.shape[1])]
    scales = []
    for side in SIDES[scheme]:
        squared = []
        for u in channels:
            centre = _haloed_slice(u, stencils.CENTRE)
            gradient = [(_haloed_slice(u, stencils.unit(a, s)) - centre) * (s / spacing)
                        for a, s in enumerate(side)]
            along = gradient[0] * normal[0] + gradient[1] * normal[1] + gradient[2] * normal[2]
            squared.append(_squared_sum([g - along * n for g, n in zip(gradient, normal,
                                                                        strict=True)]))
        magnitude = torch.sqrt(_channel_sum(squared) + eps * eps)
        scales.append(haloed_weight * diffusivity(magnitude, contrast))
    if power is None:
        return scales, None
    squared = []
    for u in channels:
        gradient = [0.5 * _haloed_slice(u, stencils.unit(a, 1))
                    - 0.5 * _haloed_slice(u, stencils.unit(a, -1)) for a in range(3)]
        along = gradient[0] * normal[0] + gradient[1] * normal[1] + gradient[2] * normal[2]
        squared.append(_squared_sum(gradient) - along * along)
    energy = (_channel_sum(squared) / (spacing * spacing) + eps * eps) ** power
    return scales, energy


def _shifted_faces(mask: Tensor, axis: int, step: int) -> Tensor:
    """``mask`` (:func:`._flux_form._open_faces`, varying along ``axis`` only) at the interior
    nodes shifted by ``step`` along ``axis``."""
    dim = mask.dim() - 1 - axis
    length = mask.shape[dim] - 2
    return mask.narrow(dim, 1 + step, length)


def _finish(total: Tensor, u: Tensor, grad_norm: Tensor, spacing: float, sides: int,
            energy: Tensor | None, mask: Tensor | None) -> Tensor:
    result = total / (spacing * spacing * sides * grad_norm)
    if energy is not None:
        result = result + u * energy
    if mask is not None:
        result = torch.where(mask, result, 0.0)
    return result


def fused_coupled_rate(
    padded_u: Tensor, haloed_normal: Tensor, haloed_weight: Tensor, grad_norm: Tensor,
    spacing: float, diffusivity: Diffusivity, contrast: float | Tensor, eps: float, scheme: str,
    power: float | None = None, mask: Tensor | None = None, box_faces: bool = True,
) -> Tensor:
    """The coupled flux form (plus the energy term, masked) as two pointwise passes.

    Args:
        padded_u: ``(B, C, D + 4, H + 4, W + 4)``, halo of two nodes.
        haloed_normal, haloed_weight: ``(B or 1, 3 | 1, D + 2, H + 2, W + 2)``, halo of one.
        grad_norm: ``W``, ``(B or 1, 1, D, H, W)``.
        diffusivity, contrast, eps: ``g(sqrt(|P grad u|^2 + eps^2), contrast)``.
        scheme: one of :data:`SIDES`.
        power: add ``u (E + eps^2)^power`` (``None``: no energy term).
        mask: ``(B or 1, 1, D, H, W)`` bool; zero where it is false.
        box_faces: no flux through the outer faces (``False`` for bricks).

    Returns:
        ``(B, C, D, H, W)``.
    """
    scales, energy = _face_scales(padded_u, haloed_normal, haloed_weight, spacing, diffusivity,
                                  contrast, eps, scheme, power)
    torch._dynamo.graph_break()  # keep a_s in memory: every channel's faces read it
    sides = SIDES[scheme]
    u = padded_u[..., 1:-1, 1:-1, 1:-1]
    normal = [haloed_normal[:, a: a + 1] for a in range(3)]
    masks = [_open_faces(u, a, 1) for a in range(3)] if box_faces else None

    def difference(axis: int, lower: Offset) -> Tensor:
        return shifted(u, stencils.add(lower, stencils.unit(axis))) - shifted(u, lower)

    def along(side: tuple[int, int, int], at: Offset) -> Tensor:
        total = None
        for b, s in enumerate(side):
            lower = at if s == 1 else stencils.add(at, stencils.unit(b, -1))
            term = shifted(normal[b], at) * difference(b, lower)
            total = term if total is None else total + term
        return total

    def face(axis: int, at: Offset) -> Tensor:
        ahead = stencils.add(at, stencils.unit(axis))
        coefficient, normal_part = None, None
        for k, side in enumerate(sides):
            node = at if side[axis] == 1 else ahead
            scale = shifted(scales[k], node)
            term = shifted(normal[axis], node) * scale * along(side, node)
            coefficient = scale if coefficient is None else coefficient + scale
            normal_part = term if normal_part is None else normal_part + term
        flux = coefficient * difference(axis, at) - normal_part
        if masks is not None:
            flux = flux * _shifted_faces(masks[axis], axis, at[2 - axis])
        return flux

    total = None
    for axis in range(3):
        term = face(axis, stencils.CENTRE) - face(axis, stencils.unit(axis, -1))
        total = term if total is None else total + term
    centre = None if energy is None else shifted(energy, stencils.CENTRE)
    return _finish(total, shifted(u, stencils.CENTRE), grad_norm, spacing, len(sides), centre,
                   mask)


def _window(axis: int, start: int, stop: int | None, inner: slice) -> tuple:
    """Index ``(..., z, y, x)``: ``start:stop`` along world ``axis``, ``inner`` along the others."""
    index = [inner] * 3
    index[2 - axis] = slice(start, stop)
    return (..., *index)


def eager_coupled_rate(
    padded_u: Tensor, haloed_normal: Tensor, haloed_weight: Tensor, grad_norm: Tensor,
    spacing: float, diffusivity: Diffusivity, contrast: float | Tensor, eps: float, scheme: str,
    power: float | None = None, mask: Tensor | None = None, box_faces: bool = True,
) -> Tensor:
    """:func:`fused_coupled_rate`'s numbers, arranged for eager evaluation (same arguments).

    Differences of ``u`` are formed once per face and shared by every composition and the
    energy; ``a_s`` and ``a_s m_s`` once per node; each face's flux once. In-place updates
    only touch fresh accumulators, so autograd records the arrangement as it is.
    """
    sides = SIDES[scheme]
    interior = slice(1, -1)
    # face differences u(y + e_a) - u(y), y from two nodes before the box to one after it
    # along a (the haloed grid and one more node), the haloed grid across
    differences = [padded_u[_window(a, 1, None, interior)] - padded_u[_window(a, 0, -1, interior)]
                   for a in range(3)]
    normal = [haloed_normal[:, a: a + 1] for a in range(3)]
    scales, fluxes = [], []
    for side in sides:
        gradient = [d[_window(a, 1, None, slice(None))] if s == 1
                    else d[_window(a, 0, -1, slice(None))] for a, (d, s) in
                    enumerate(zip(differences, side, strict=True))]
        along = gradient[0] * normal[0]
        along = along.addcmul_(gradient[1], normal[1]).addcmul_(gradient[2], normal[2])
        squared = None
        for g, n in zip(gradient, normal, strict=True):
            tangential = torch.addcmul(g, n, along, value=-1.0)
            squared = (tangential * tangential if squared is None
                       else squared.addcmul_(tangential, tangential))
        total = squared.sum(dim=1, keepdim=True) / (spacing * spacing)
        scale = haloed_weight * diffusivity(torch.sqrt(total + eps * eps), contrast)
        scales.append(scale)
        fluxes.append(scale * along)
    # a face's nodes: ``x`` (first) and ``x + e_a`` (second), faces from the haloed grid's first
    # node to its last but one along a, the box's interior across
    result = None
    for a in range(3):
        first, second = _window(a, 0, -1, interior), _window(a, 1, None, interior)
        coefficient, normal_part = None, None
        for k, side in enumerate(sides):
            node = first if side[a] == 1 else second
            scale = scales[k][node]
            coefficient = scale if coefficient is None else coefficient + scale
            term = normal[a][node] * fluxes[k][node]
            normal_part = term if normal_part is None else normal_part.add_(term)
        across = differences[a][_window(a, 1, -1, interior)]
        flux = torch.addcmul(-normal_part, coefficient, across)
        if box_faces:  # the first and last faces along a lie on the box
            flux[_window(a, 0, 1, slice(None))] = 0.0
            flux[_window(a, -1, None, slice(None))] = 0.0
        term = flux[_window(a, 1, None, slice(None))] - flux[_window(a, 0, -1, slice(None))]
        result = term if result is None else result.add_(term)
    energy = None
    if power is not None:
        central = [0.5 * differences[a][_window(a, 2, -1, interior)]
                   + 0.5 * differences[a][_window(a, 1, -2, interior)] for a in range(3)]
        normal = [n[..., 1:-1, 1:-1, 1:-1] for n in normal]
        along = central[0] * normal[0]
        along = along.addcmul_(central[1], normal[1]).addcmul_(central[2], normal[2])
        squared = central[0] * central[0]
        squared = squared.addcmul_(central[1], central[1]).addcmul_(central[2], central[2])
        squared = squared.addcmul_(along, along, value=-1.0)
        energy = (squared.sum(dim=1, keepdim=True) / (spacing * spacing) + eps * eps) ** power
    u = padded_u[..., 2:-2, 2:-2, 2:-2]
    return _finish(result, u, grad_norm, spacing, len(sides), energy, mask)
