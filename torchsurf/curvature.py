"""Curvature of level sets from the gradient and Hessian of ``phi`` (the paper's §2 and its references).

Pure functions of tensors: ``gradient`` is ``(B, 3, D, H, W)`` in ``(x, y, z)`` order,
``hessian`` is ``(B, 6, D, H, W)`` in the order ``xx, yy, zz, xy, xz, yz`` and ``grad_norm``
is the regularised ``|grad phi|`` ``(B, 1, D, H, W)``. Curvatures are in inverse world units,
positive for a sphere with the outward normal (``H = 2 / R``, ``K = 1 / R^2``).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ._checks import check_alike, check_positive, check_tensor
from ._precision import in_data_dtype
from ._vectors import tangential_part

__all__ = [
    "gaussian_curvature",
    "mean_curvature",
    "principal",
    "tangent_basis",
]


def _check_fields(**fields: tuple[Tensor, int]) -> None:
    """Raise naming the argument unless each ``name=(tensor, channels)`` is a float32 or float64
    ``(B, channels, ...)`` tensor, all of one dtype and grid, their batch sizes equal or 1."""
    for name, (value, _) in fields.items():
        check_tensor(value, name)
    check_alike([(name, value, channels) for name, (value, channels) in fields.items()])


def _matrix(hessian: Tensor) -> Tensor:
    """``(B, 6, ...)`` packed Hessian to ``(B, 3, 3, ...)``."""
    xx, yy, zz, xy, xz, yz = hessian.unbind(dim=1)
    rows = ((xx, xy, xz), (xy, yy, yz), (xz, yz, zz))
    return torch.stack([torch.stack(row, dim=1) for row in rows], dim=1)


def _quadratic(matrix: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """``a^T M b`` per voxel: ``M`` ``(B, 3, 3, ...)``, ``a``, ``b`` ``(B, 3, ...)`` -> ``(B, 1, ...)``."""
    with in_data_dtype(a):
        return torch.einsum("bi...,bij...,bj...->b...", a, matrix, b)[:, None]


def mean_curvature(gradient: Tensor, hessian: Tensor, grad_norm: Tensor) -> Tensor:
    """``H = div(grad phi / |grad phi|) = (|g|^2 tr(Hess) - g^T Hess g) / |g|^3``; ``(B, 1, ...)``.

    Formed as ``tr(S) - n^T S n`` with ``S = Hess / |g|`` and ``n = g / |g|``: no power of
    ``phi``'s scale above one, so ``c * phi`` gives the same numbers for any ``c`` float32 holds
    (``|g|^3`` overflowed float32 from ``c = 1e13``).

    Args:
        gradient: ``grad phi`` ``(B, 3, ...)`` in ``(x, y, z)`` order.
        hessian: ``Hess phi`` ``(B, 6, ...)`` in the order ``xx, yy, zz, xy, xz, yz``.
        grad_norm: the regularised ``|grad phi|`` ``(B, 1, ...)`` (positive: it divides).
    """
    _check_fields(gradient=(gradient, 3), hessian=(hessian, 6), grad_norm=(grad_norm, 1))
    scaled = hessian / grad_norm
    normal = gradient / grad_norm
    trace = scaled[:, 0:1] + scaled[:, 1:2] + scaled[:, 2:3]
    return trace - _quadratic(_matrix(scaled), normal, normal)


def gaussian_curvature(gradient: Tensor, hessian: Tensor, grad_norm: Tensor) -> Tensor:
    """``K = g^T adj(Hess) g / |g|^4``; ``(B, 1, ...)``, formed as ``n^T adj(Hess / |g|) n``
    (the adjugate is quadratic in its matrix) so that no power of ``phi``'s scale above one
    appears (``|g|^4`` overflowed float32 from ``c = 1e10``).

    Args:
        gradient: ``grad phi`` ``(B, 3, ...)`` in ``(x, y, z)`` order.
        hessian: ``Hess phi`` ``(B, 6, ...)`` in the order ``xx, yy, zz, xy, xz, yz``.
        grad_norm: the regularised ``|grad phi|`` ``(B, 1, ...)`` (positive: it divides).
    """
    _check_fields(gradient=(gradient, 3), hessian=(hessian, 6), grad_norm=(grad_norm, 1))
    gradient = gradient / grad_norm
    xx, yy, zz, xy, xz, yz = (hessian / grad_norm).unbind(dim=1)
    adjugate = _matrix(
        torch.stack(
            (
                yy * zz - yz**2,
                xx * zz - xz**2,
                xx * yy - xy**2,
                xz * yz - zz * xy,
                xy * yz - yy * xz,
                xy * xz - xx * yz,
            ),
            dim=1,
        )
    )
    return _quadratic(adjugate, gradient, gradient)


def _unit_vectors(normal: Tensor, index: Tensor) -> Tensor:
    return torch.zeros_like(normal).scatter_(1, index, 1.0)


def tangent_basis(normal: Tensor) -> tuple[Tensor, Tensor]:
    """Two orthonormal tangents ``(t1, t2)`` to ``normal``; each ``(B, 3, ...)``.

    Gram–Schmidt of the two coordinate axes least aligned with ``n``: their parts orthogonal to
    ``n`` never fall below ``sqrt(2/3)`` and ``1/sqrt(3)`` of unit length for a unit normal, and
    where ``n`` vanishes (the medial axis) the axes themselves are returned, so values and
    gradients stay finite everywhere (the choice jumps where the ordering of ``|n_i|`` changes).
    """
    _check_fields(normal=(normal, 3))
    order = normal.abs().argsort(dim=1)
    first = _unit_vectors(normal, order[:, 0:1])
    second = _unit_vectors(normal, order[:, 1:2])
    t1 = tangential_part(first, normal)
    t1 = t1 / t1.norm(dim=1, keepdim=True)
    t2 = tangential_part(second, normal)
    t2 = t2 - (t2 * t1).sum(dim=1, keepdim=True) * t1
    return t1, t2 / t2.norm(dim=1, keepdim=True)


def principal(
    hessian: Tensor, normal: Tensor, grad_norm: Tensor, eps: float
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Principal curvatures and directions from the shape operator ``P Hess P / |grad phi|``.

    The shape operator is written in the tangent basis of :func:`tangent_basis` as a symmetric
    2x2 matrix ``[[m11, m12], [m12, m22]]`` and diagonalised in closed form, with the
    eigenvalue gap regularised as ``r = sqrt((m11 - m22)^2 + 4 m12^2 + eps^2)``.

    At an umbilic (``m11 = m22``, ``m12 = 0``; every point of a sphere) the directions are not
    defined: the first direction returned is ``t1`` and the curvatures are ``mean ± eps / 2``,
    all finite with finite gradients.

    Args:
        hessian: ``Hess phi`` ``(B, 6, ...)`` in the order ``xx, yy, zz, xy, xz, yz``.
        normal: the unit normal ``grad phi / |grad phi|`` ``(B, 3, ...)``.
        grad_norm: the regularised ``|grad phi|`` ``(B, 1, ...)`` (positive: it divides).
        eps: regularisation of the eigenvalue gap, inverse world units, > 0.

    Returns:
        ``k1, k2`` ``(B, 1, ...)`` with ``k1 >= k2``, and unit directions ``e1, e2``
        ``(B, 3, ...)``, orthonormal and tangent.
    """
    _check_fields(hessian=(hessian, 6), normal=(normal, 3), grad_norm=(grad_norm, 1))
    eps = check_positive(eps, "eps")
    t1, t2 = tangent_basis(normal)
    matrix = _matrix(hessian)
    m11 = _quadratic(matrix, t1, t1) / grad_norm
    m22 = _quadratic(matrix, t2, t2) / grad_norm
    m12 = _quadratic(matrix, t1, t2) / grad_norm
    half_trace = 0.5 * (m11 + m22)
    a = m11 - m22
    b = 2.0 * m12
    gap = torch.sqrt(a**2 + b**2 + eps**2)
    # Two expressions of the same eigenvector; each is used where its norm is at least eps.
    along_t1 = torch.where(a >= 0, a + gap, b)
    along_t2 = torch.where(a >= 0, b, gap - a)
    length = torch.sqrt(along_t1**2 + along_t2**2)
    e1 = (along_t1 * t1 + along_t2 * t2) / length
    e2 = (along_t1 * t2 - along_t2 * t1) / length
    return half_trace + 0.5 * gap, half_trace - 0.5 * gap, e1, e2
