"""``ImplicitSurface``: one fixed surface ``phi = 0`` (or a batch) and what derives from it."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from . import curvature, stencils
from ._checks import check_finite, check_positive, check_spatial_shape, check_volume
from .grid import Grid


class ImplicitSurface(nn.Module):
    """The zero level set of ``phi`` on ``grid``, with its normals, band and curvatures.

    ``|grad phi|`` and the unit normals are computed once, by central differences with
    ``phi`` extrapolated linearly beyond the grid, and reused by every operator. When ``phi``
    requires grad they stay in its graph (build the surface again after each optimiser step).

    Args:
        phi: ``(B, 1, D, H, W)``, negative inside, positive outside, world units; ideally a
            signed distance function near the surface. Every batch entry must change sign.
        grid: the grid ``phi`` is sampled on; ``grid.shape == (D, H, W)``.
        band_width: half-width of the band ``|phi| <= band_width`` in world units
            (default ``3 * grid.spacing``).
        eps: regularisation of ``|grad phi|`` as ``sqrt(|grad phi|^2 + eps^2)``, in the units
            of ``|grad phi|`` (1 for a distance function); keeps normals and their gradients
            finite where ``grad phi`` vanishes (the medial axis).

    Attributes:
        phi: ``(B, 1, D, H, W)``.
        grad_norm: ``W = sqrt(|grad phi|^2 + eps^2)``, ``(B, 1, D, H, W)``.
        normal: ``grad phi / W``, ``(B, 3, D, H, W)`` in ``(x, y, z)`` order.

    Example:
        >>> grid = Grid.cube(33, bound=1.5)
        >>> from torchsurf import sdf
        >>> surface = ImplicitSurface(sdf.sphere(grid, radius=1.0), grid)
        >>> surface.normal.shape
        torch.Size([1, 3, 33, 33, 33])
    """

    phi: Tensor
    grad_norm: Tensor
    normal: Tensor

    def __init__(
        self, phi: Tensor, grid: Grid, band_width: float | None = None, eps: float = 1e-6
    ) -> None:
        super().__init__()
        if not isinstance(grid, Grid):
            raise TypeError(f"grid must be a torchsurf.Grid, got {type(grid).__name__}")
        check_volume(phi, "phi", channels=1)
        check_spatial_shape(phi, "phi", grid.shape, "grid")
        check_finite(phi, "phi")
        lowest = phi.detach().flatten(1).min(dim=1).values
        highest = phi.detach().flatten(1).max(dim=1).values
        missing = ((lowest > 0) | (highest < 0) | (highest == lowest)).nonzero().flatten()
        if len(missing) > 0:
            raise ValueError(
                f"phi has no zero crossing in batch entries {missing.tolist()}: every entry "
                "must be negative somewhere (inside) and positive somewhere (outside)"
            )
        self.grid = grid
        self.band_width = check_positive(
            3.0 * grid.spacing if band_width is None else band_width, "band_width"
        )
        self.eps = check_positive(eps, "eps")
        gradient = stencils.apply(stencils.pad(phi, "linear"), stencils.CENTRAL)[:, 0]
        gradient = gradient / grid.spacing
        grad_norm = torch.sqrt((gradient**2).sum(dim=1, keepdim=True) + self.eps**2)
        self.register_buffer("phi", phi, persistent=False)
        self.register_buffer("grad_norm", grad_norm, persistent=False)
        self.register_buffer("normal", gradient / grad_norm, persistent=False)
        self.register_buffer("_mean_curvature", None, persistent=False)
        self.register_buffer("_haloed_normal", None, persistent=False)
        self.register_buffer("_haloed_grad_norm", None, persistent=False)

    @property
    def batch_size(self) -> int:
        """Number of surfaces ``B``."""
        return self.phi.shape[0]

    @property
    def spacing(self) -> float:
        """Grid spacing ``h``, world units."""
        return self.grid.spacing

    def band(self, width: float | None = None) -> Tensor:
        """Boolean mask ``|phi| <= width`` (default ``band_width``); ``(B, 1, D, H, W)``."""
        width = self.band_width if width is None else check_positive(width, "width")
        return self.phi.abs() <= width

    def haloed(self) -> tuple[Tensor, Tensor]:
        """``normal`` and ``grad_norm`` with a halo of one node on every side.

        ``grad_norm`` is replicated; ``normal`` is mirrored in the box's faces
        (:func:`torchsurf.stencils.pad_mirrored`), as the octant scheme needs.

        ``(B, 3, D + 2, H + 2, W + 2)`` and ``(B, 1, D + 2, H + 2, W + 2)``, for kernels that
        read neighbours without padding (the compiled operators). Computed once and kept, on
        the same terms as :meth:`mean_curvature`.
        """
        if self._haloed_normal is not None:
            return self._haloed_normal, self._haloed_grad_norm
        normal = stencils.pad_mirrored(self.normal)
        grad_norm = stencils.pad(self.grad_norm, "replicate")
        if torch.is_grad_enabled() or not self.phi.requires_grad:
            self._haloed_normal, self._haloed_grad_norm = normal, grad_norm
        return normal, grad_norm

    def hessian(self) -> Tensor:
        """Second derivatives of ``phi``, ``(B, 6, D, H, W)`` in the order xx, yy, zz, xy, xz, yz.

        Central differences, world units (``1 / length``).
        """
        padded = stencils.pad(self.phi, "linear")
        return stencils.apply(padded, stencils.HESSIAN)[:, 0] / self.spacing**2

    def _gradient(self) -> Tensor:
        return self.normal * self.grad_norm

    def mean_curvature(self) -> Tensor:
        """Mean curvature ``H = div n`` of the level set through each node; ``(B, 1, D, H, W)``.

        The sum of the principal curvatures (sphere of radius R: ``2 / R``), second order in the
        spacing. Computed once and kept (except when computed without autograd from a ``phi``
        that requires grad, so that a later call still carries the graph).
        """
        if self._mean_curvature is not None:
            return self._mean_curvature
        value = curvature.mean_curvature(self._gradient(), self.hessian(), self.grad_norm)
        if torch.is_grad_enabled() or not self.phi.requires_grad:
            self._mean_curvature = value
        return value

    def gaussian_curvature(self) -> Tensor:
        """Gaussian curvature ``K`` of the level set through each node; ``(B, 1, D, H, W)``.

        ``K = grad phi^T adj(Hess phi) grad phi / |grad phi|^4`` (sphere: ``1 / R^2``).
        """
        return curvature.gaussian_curvature(self._gradient(), self.hessian(), self.grad_norm)

    def principal_curvatures(self) -> tuple[Tensor, Tensor]:
        """Principal curvatures ``(k1, k2)``, ``k1 >= k2``, each ``(B, 1, D, H, W)``.

        Regularised at umbilics as described in :meth:`principal_directions`.
        """
        k1, k2, _, _ = self._principal()
        return k1, k2

    def principal_directions(self) -> tuple[Tensor, Tensor]:
        """Unit principal directions ``(e1, e2)`` of ``k1`` and ``k2``, each ``(B, 3, D, H, W)``.

        Tangent eigenvectors of the shape operator ``P Hess(phi) P / |grad phi|``, defined up
        to sign, orthonormal. At umbilic points (every point of a sphere) no direction is
        preferred: ``e1`` is then a fixed tangent (the coordinate axis least aligned with ``n``,
        made orthogonal to it) and the curvatures differ by ``eps`` =
        ``1e-6 / spacing``; values and gradients stay finite.
        """
        _, _, e1, e2 = self._principal()
        return e1, e2

    def _principal(self) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        return curvature.principal(
            self.hessian(), self.normal, self.grad_norm, eps=1e-6 / self.spacing
        )

    def extra_repr(self) -> str:
        return (
            f"batch_size={self.batch_size}, grid={self.grid}, band_width={self.band_width:g}, "
            f"eps={self.eps:g}"
        )
