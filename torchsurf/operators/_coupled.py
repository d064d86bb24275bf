"""Coupled edge-stopping diffusion and the harmonic-map rate, in two passes.

``L u = (1/W) div(W g(|P grad u|) P grad u)`` with ``|P grad u|^2`` summed over the channels
(the p-harmonic map's diffusion, the paper's eq. 11), in the flux form of :mod:`._flux_form`:
per composition ``s`` (:data:`SIDES`), ``v_s = P D_s u`` and the flux ``W g_s v_s`` with
``g_s = g(|v_s|)``. Optionally plus ``u (E + eps^2)^power`` with ``E = sum_c |P grad u_c|^2`` by
central differences (the harmonic map's energy term), and zero outside a mask (the band).

``g_s`` depends on every channel, so it is formed in a first pass over the grid plus one halo
layer and kept (fused with the fluxes, each channel's fluxes would recompute it from all
channels: 3.5x slower at 3 channels); the second pass differences the fluxes.

- :func:`fused_coupled_rate`: the passes as pointwise expressions for the compiler, in two
  arrangements of the same numbers. Without a graph to record, by faces (the sum below): pass
  one keeps ``a_s`` and, per channel, ``a_s m_s`` (and the energy factor) on the haloed grid;
  pass two forms each face's flux from them and differences it, so no flux is stored (the p = 1
  harmonic map's rate at 128^3, 3 channels: 37-41 against 48-61 ms by compositions, which
  store every flux component of every channel, 18 volumes, and read them back). While autograd
  records, by compositions (pass one :func:`_composition_scales`, pass two
  :func:`._flux_form.fused_flux_form`): their compiled backward is 1.7-2x faster.
- :func:`eager_coupled_rate`: the same numbers op by op, by faces. Writing
  ``v_s = D_s u - n m_s`` with ``m_s = n . D_s u``, every composition that crosses the face
  between ``x`` and ``x + e_a`` differences ``u`` across it, so the face carries

      Phi_a(x) = K_a(x) (u(x + e_a) - u(x)) - sum_s n_a(y_s) a_s(y_s) m_s(y_s),
      K_a(x) = sum_s a_s(y_s),   a_s = W g_s,   y_s = x if s_a = +1, x + e_a if s_a = -1,

  and ``L u (x) = sum_a [Phi_a(x) - Phi_a(x - e_a)] / (h^2 S W)`` (differences in index units,
  ``S`` compositions, no flux through the faces of the grid's box): the differences of ``u``
  are formed once for every composition and the energy, ``a_s`` and ``a_s m_s`` once per node,
  each face's flux once.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from .. import stencils
from ..stencils import masked, shifted
from ._flux_form import SIDES, Components, _haloed_slice, fused_flux_form
from .diffusivity import Diffusivity


def _squared_sum(parts: list[Tensor]) -> Tensor:
    total = parts[0] * parts[0]
    for part in parts[1:]:
        total = total + part * part
    return total


def _channel_sum(values: list[Tensor]) -> Tensor:
    """The sum over the channels of every tensor in ``values``, ``(B, 1, ...)``; a sum of
    slices, which stays one pointwise kernel when compiled."""
    total = None
    for value in values:
        for channel in value.unbind(dim=1):
            total = channel if total is None else total + channel
    return total[:, None]


def _composition_scales(
    padded_u: Tensor, haloed_normal: Tensor, spacing: float, diffusivity: Diffusivity,
    contrast: float | Tensor, eps: float, scheme: str,
) -> list[Tensor]:
    """Pass one by compositions: ``g(|P D_s u|)`` per composition on the haloed grid, from
    ``u`` with a halo of two nodes as one tensor (split into channels, the compiled backward
    scatters every channel's reads over all channels: 147 against 84 ms at 128^3)."""
    normal = [haloed_normal[:, a: a + 1] for a in range(3)]
    scales = []
    for side in SIDES[scheme]:
        centre = _haloed_slice(padded_u, stencils.CENTRE)
        gradient = [(_haloed_slice(padded_u, stencils.unit(a, s)) - centre) * (s / spacing)
                    for a, s in enumerate(side)]
        along = gradient[0] * normal[0] + gradient[1] * normal[1] + gradient[2] * normal[2]
        squared = _squared_sum([g - along * n for g, n in zip(gradient, normal, strict=True)])
        magnitude = torch.sqrt(_channel_sum([squared]) + eps * eps)
        scales.append(diffusivity(magnitude, contrast))
    return scales


def _energy_factor(channels: Sequence[Tensor], haloed_normal: Tensor, spacing: float,
                   eps: float, power: float) -> Tensor:
    """``(E + eps^2)^power`` at the interior nodes; ``channels``: ``u`` with a halo of two
    nodes, split into tensors of one channel."""
    normal = [haloed_normal[:, a: a + 1, 1:-1, 1:-1, 1:-1] for a in range(3)]
    squared = []
    for u in channels:
        u = u[..., 1:-1, 1:-1, 1:-1]
        gradient = [0.5 * shifted(u, stencils.unit(a, 1)) - 0.5 * shifted(u, stencils.unit(a, -1))
                    for a in range(3)]
        squared.append(_tangential_squared(gradient, normal))
    return (_channel_sum(squared) / (spacing * spacing) + eps * eps) ** power


def _tangential_squared(gradient: list[Tensor], normal: list[Tensor]) -> Tensor:
    """``|P g|^2`` from ``P g`` itself: ``|g|^2 - (g . n)^2`` cancels where ``g`` lies along
    ``n`` (float32: below zero, and a NaN energy factor for ``p = 1``)."""
    along = gradient[0] * normal[0] + gradient[1] * normal[1] + gradient[2] * normal[2]
    return _squared_sum([g - along * n for g, n in zip(gradient, normal, strict=True)])


def _finish(total: Tensor, u: Tensor, energy: Tensor | None, mask: Tensor | None) -> Tensor:
    return masked(total if energy is None else total + u * energy, mask)


def _scaled_flux(v: Components, fields: Sequence[Tensor], side: int) -> Components:
    scale = fields[side]
    return scale * v[0], scale * v[1], scale * v[2]


def _sum(values: list[Tensor]) -> Tensor:
    """``values[0] + values[1] + ...``; on tensors of one channel, where :func:`_channel_sum`'s
    views would make the compiler store every term before the sum (5 ms at 128^3)."""
    total = values[0]
    for value in values[1:]:
        total = total + value
    return total


def _face_products(
    channels: Sequence[Tensor], haloed_normal: Tensor, haloed_weight: Tensor, spacing: float,
    diffusivity: Diffusivity, contrast: float | Tensor, eps: float, scheme: str,
    power: float | None,
) -> tuple[list[list[Tensor]], list[list[Tensor]], Tensor | None]:
    """Pass one of the face arrangement, on the haloed grid: per composition ``s`` and channel
    ``c``, ``a_s = W g_s`` (one tensor for every channel, unless the contrast is per channel)
    and ``a_s m_s`` with ``m_s = n . D_s u_c`` (index units); the energy factor
    ``(E + eps^2)^power`` (``None`` without ``power``).

    ``channels``: ``u`` with a halo of two nodes, split into tensors of one channel.
    """
    normal = [haloed_normal[:, a: a + 1] for a in range(3)]
    scales, products = [], []
    for side in SIDES[scheme]:
        squared, alongs = [], []
        for u in channels:
            centre = _haloed_slice(u, stencils.CENTRE)
            difference = [(_haloed_slice(u, stencils.unit(a, s)) - centre) * s
                          for a, s in enumerate(side)]
            along = (difference[0] * normal[0] + difference[1] * normal[1]
                     + difference[2] * normal[2])
            squared.append(_squared_sum([d - along * n for d, n in zip(difference, normal,
                                                                        strict=True)]))
            alongs.append(along)
        magnitude = torch.sqrt(_sum(squared) / (spacing * spacing) + eps * eps)
        scale = haloed_weight * diffusivity(magnitude, contrast)
        per_channel = (scale.split(1, dim=1) if scale.shape[1] > 1
                       else [scale] * len(channels))
        scales.append(per_channel)
        products.append([a * along for a, along in zip(per_channel, alongs, strict=True)])
    energy = None
    if power is not None:
        squared = []
        for u in channels:
            central = [0.5 * _haloed_slice(u, stencils.unit(a, 1))
                       - 0.5 * _haloed_slice(u, stencils.unit(a, -1)) for a in range(3)]
            squared.append(_tangential_squared(central, normal))
        energy = (_sum(squared) / (spacing * spacing) + eps * eps) ** power
    return scales, products, energy


def _inner_faces(like: Tensor, axis: int, ahead: bool) -> Tensor:
    """1 where a node's face towards ``+e_axis`` (``ahead``) or ``-e_axis`` lies inside the box,
    else 0; broadcastable to ``like`` ``(..., D, H, W)``. Varies along ``axis`` only."""
    dim = like.dim() - 1 - axis
    length = like.shape[dim]
    index = torch.arange(length, device=like.device, dtype=torch.int32)
    shape = [1] * like.dim()
    shape[dim] = length
    return (index != (length - 1 if ahead else 0)).to(like.dtype).view(shape)


def _face_divergence(
    haloed_u: Tensor, haloed_normal: Tensor, grad_norm: Tensor, spacing: float,
    scales: Sequence[Tensor], products: Sequence[Tensor], scheme: str, box_faces: bool,
) -> Tensor:
    """Pass two of the face arrangement for one channel: ``sum_a [Phi_a(x) - Phi_a(x - e_a)]
    / (h^2 S W)`` (module docstring), ``Phi_a`` from ``u``, ``a_s`` and ``a_s m_s`` of the
    haloed grid (``haloed_u`` ``(B, 1, D + 2, H + 2, W + 2)``); ``(B, 1, D, H, W)``."""
    sides = SIDES[scheme]
    total = None
    for a in range(3):
        normal = haloed_normal[:, a: a + 1]

        def flux(node: stencils.Offset, a: int = a, normal: Tensor = normal) -> Tensor:
            """``Phi_a`` through the face between ``node`` and ``node + e_a``."""
            after = stencils.add(node, stencils.unit(a))
            across = shifted(haloed_u, after) - shifted(haloed_u, node)
            result = None
            for scale, product, side in zip(scales, products, sides, strict=True):
                at = node if side[a] == 1 else after
                term = shifted(scale, at) * across - shifted(normal, at) * shifted(product, at)
                result = term if result is None else result + term
            return result

        ahead, behind = flux(stencils.CENTRE), flux(stencils.unit(a, -1))
        if box_faces:
            ahead = ahead * _inner_faces(grad_norm, a, True)
            behind = behind * _inner_faces(grad_norm, a, False)
        term = ahead - behind
        total = term if total is None else total + term
    return total / (spacing * spacing * len(sides) * grad_norm)


def _face_rate(
    padded_u: Tensor, haloed_normal: Tensor, haloed_weight: Tensor, grad_norm: Tensor,
    spacing: float, diffusivity: Diffusivity, contrast: float | Tensor, eps: float, scheme: str,
    power: float | None, mask: Tensor | None, box_faces: bool,
) -> Tensor:
    """:func:`fused_coupled_rate` by the face arrangement (no graph to record)."""
    channels = padded_u.split(1, dim=1)
    scales, products, energy = _face_products(channels, haloed_normal, haloed_weight, spacing,
                                              diffusivity, contrast, eps, scheme, power)
    torch._dynamo.graph_break()  # keep a_s and a_s m_s: every face reads them
    if energy is not None:
        energy = energy[..., 1:-1, 1:-1, 1:-1]
    rates = []
    for c, u in enumerate(channels):
        rate = _face_divergence(u[..., 1:-1, 1:-1, 1:-1], haloed_normal, grad_norm, spacing,
                                [scale[c] for scale in scales],
                                [product[c] for product in products], scheme, box_faces)
        rates.append(_finish(rate, u[..., 2:-2, 2:-2, 2:-2], energy, mask))
    return _stacked(rates)


def _stacked(rates: Sequence[Tensor]) -> Tensor:
    """``torch.cat(rates, dim=1)`` of ``(B, 1, ...)`` tensors. For one volume, as a stack of
    ``(...)`` blocks: the compiler writes each block in place, where for a concatenation along
    the channels it stores channels-last and transposes (128^3, 3 channels: 20 against 27 ms).
    A batch (symbolic when compiled: one graph serves every size) or packed bricks are
    concatenated."""
    batch = rates[0].shape[0]
    if not isinstance(batch, int) or batch != 1:
        return torch.cat(rates, dim=1)
    return torch.stack([rate[0, 0] for rate in rates])[None]


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
    recording = torch.is_grad_enabled() and any(
        isinstance(t, Tensor) and t.requires_grad
        for t in (padded_u, haloed_normal, haloed_weight, grad_norm, contrast))
    if not recording:
        return _face_rate(padded_u, haloed_normal, haloed_weight, grad_norm, spacing,
                          diffusivity, contrast, eps, scheme, power, mask, box_faces)
    # While autograd records, the compiled backward decides the cost: g_s from whole tensors,
    # and g_s, the energy and the last pointwise step each as their own graph (128^3, 3
    # channels, forward and backward: 0.39 s against 0.60 s as two graphs per channel).
    channels = padded_u.split(1, dim=1)
    scales = _composition_scales(padded_u, haloed_normal, spacing, diffusivity, contrast, eps,
                                 scheme)
    torch._dynamo.graph_break()
    energy = None if power is None else _energy_factor(channels, haloed_normal, spacing, eps,
                                                      power)
    torch._dynamo.graph_break()  # keep g_s in memory: every channel's fluxes read it
    total = fused_flux_form(padded_u, haloed_normal, haloed_weight, grad_norm, spacing,
                            _scaled_flux, scales, scheme, box_faces=box_faces)
    torch._dynamo.graph_break()
    return _finish(total, padded_u[..., 2:-2, 2:-2, 2:-2], energy, mask)


def _window(axis: int, start: int, stop: int | None, inner: slice) -> tuple:
    """Index ``(..., z, y, x)``: ``start:stop`` along world ``axis``, ``inner`` along the others."""
    index = [inner] * 3
    index[2 - axis] = slice(start, stop)
    return (..., *index)


def eager_coupled_rate(
    padded_u: Tensor, haloed_normal: Tensor, haloed_weight: Tensor, grad_norm: Tensor,
    spacing: float, diffusivity: Diffusivity, contrast: float | Tensor, eps: float, scheme: str,
    power: float | None = None, mask: Tensor | None = None, box_faces: bool = True,
    coupled: bool = True,
) -> Tensor:
    """:func:`fused_coupled_rate`'s numbers, arranged for eager evaluation (same arguments;
    ``coupled=False`` measures ``|P grad u|`` per channel, the uncoupled edge-stopping form).

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
        total = (squared.sum(dim=1, keepdim=True) if coupled else squared) / (spacing * spacing)
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
        squared = _tangential_squared(central, normal)
        energy = (squared.sum(dim=1, keepdim=True) / (spacing * spacing) + eps * eps) ** power
    total = result / (spacing * spacing * len(sides) * grad_norm)
    return _finish(total, padded_u[..., 2:-2, 2:-2, 2:-2], energy, mask)
