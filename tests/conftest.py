"""Shared helpers for the tests: exact geometry of the validation cases with exact answers and orders.

Everything here takes and returns tensors; points are ``(..., 3)`` world ``(x, y, z)`` as
:meth:`torchsurf.Grid.points` gives them, and :func:`channels` turns such a field into the
``(1, C, D, H, W)`` layout the library uses.
"""

from __future__ import annotations

import math
import os

# "auto" never compiles in the tests (it would after seconds of eager work on a kernel, which
# many tests reach: a compile costs 10-90 s here and would land in whichever test crosses
# the threshold). The compiled kernels are tested where they are asked for by name
# (path="compiled", warm_up, tests/test_compiled_kernels.py, tests marked ``compiled``: long
# runs compiled from their first call), and "auto"'s choice in tests/test_backend.py.
# TORCHSURF_COMPILE=auto runs the whole suite as a user's process would.
os.environ.setdefault("TORCHSURF_COMPILE", "never")

# pytest-xdist runs the suite in one process per core (pyproject.toml): each takes one thread,
# as OpenMP threads spinning beside another process's would slow both
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    os.environ.setdefault("OMP_NUM_THREADS", "1")

import pytest  # noqa: E402
import torch  # noqa: E402
from torch import Tensor  # noqa: E402

from torchsurf import backend  # noqa: E402

if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    torch.set_num_threads(int(os.environ["OMP_NUM_THREADS"]))  # were torch imported already

backend.COMPILE = backend._compile_mode_from_environment()  # were torchsurf imported already


def channels(field: Tensor) -> Tensor:
    """``(D, H, W)`` or ``(D, H, W, C)`` to ``(1, C, D, H, W)``."""
    if field.dim() == 3:
        return field[None, None]
    return field.permute(3, 0, 1, 2)[None]


def interior(shape, margin: int = 1) -> Tensor:
    """Boolean ``(1, 1, D, H, W)``: nodes at least ``margin`` nodes away from the grid's faces."""
    mask = torch.zeros(shape, dtype=torch.bool)
    mask[tuple(slice(margin, n - margin) for n in shape)] = True
    return mask[None, None]


def near_surface(phi: Tensor, width: float, margin: int = 1) -> Tensor:
    """Boolean mask like ``phi``: ``|phi| <= width`` away from the grid's faces."""
    return (phi.abs() <= width) & interior(phi.shape[-3:], margin)


def skewed_box_surface():
    """A box that is not a cube (9 x 10 x 11 nodes) and an ellipsoid whose ``phi`` is not a
    distance (``W`` varies across it), float64: ``(grid, surface)``, where every composition of
    a flux-form kernel and the box's faces are in play."""
    import torchsurf as ts

    grid = ts.Grid((9, 10, 11), spacing=0.15, origin=(-0.8, -0.7, -0.6))
    points = grid.points(dtype=torch.float64)
    phi = ((points / torch.tensor([0.5, 0.6, 0.4], dtype=torch.float64)) ** 2).sum(-1) - 1
    phi = phi * (1.3 + 0.4 * points[..., 1])
    return grid, ts.ImplicitSurface(phi[None, None], grid)


def observed_order(error_coarse: float, error_fine: float, h_coarse: float, h_fine: float
                   ) -> float:
    """Convergence order ``log(e_coarse / e_fine) / log(h_coarse / h_fine)``."""
    return math.log(error_coarse / error_fine) / math.log(h_coarse / h_fine)


def sphere_curvatures(radius: Tensor | float) -> tuple[Tensor | float, Tensor | float]:
    """Mean and Gaussian curvature ``(2 / R, 1 / R^2)`` of a sphere with outward normal."""
    return 2.0 / radius, 1.0 / radius**2


def torus_angles(points: Tensor, major_radius: float, minor_radius: float | None = None
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """Torus coordinates of world points, torus centred at the origin around the z axis.

    Returns ``(theta, v, rho)``: the angle around the z axis, the tube angle (``v = 0`` on the
    outer equator, ``pi / 2`` on top) and the distance to the core circle, i.e. the tube radius
    of the torus (same ``major_radius``) whose surface passes through the point. A torus SDF
    with minor radius ``r`` has ``phi = rho - r``; pass ``rho`` as the minor radius of the other
    torus helpers to get the exact geometry of the level set through each point.
    ``minor_radius`` does not enter (the angles do not depend on it); it is accepted so that
    calls read ``torus_angles(points, R, r)``.
    """
    del minor_radius
    x, y, z = points.unbind(dim=-1)
    theta = torch.atan2(y, x)
    radial = torch.sqrt(x**2 + y**2) - major_radius
    return theta, torch.atan2(z, radial), torch.sqrt(radial**2 + z**2)


def torus_principal_curvatures(v: Tensor, major_radius: float, minor_radius: Tensor | float
                               ) -> tuple[Tensor, Tensor]:
    """``(k1, k2) = (1 / r, cos v / (R + r cos v))``: meridian (tube) and parallel curvature."""
    k1 = torch.ones_like(v) / minor_radius
    k2 = torch.cos(v) / (major_radius + minor_radius * torch.cos(v))
    return k1, k2


def torus_curvatures(v: Tensor, major_radius: float, minor_radius: Tensor | float
                     ) -> tuple[Tensor, Tensor]:
    """``H = (R + 2 r cos v) / (r (R + r cos v))``, ``K = cos v / (r (R + r cos v))``."""
    R, r, c = major_radius, minor_radius, torch.cos(v)
    mean = (R + 2 * r * c) / (r * (R + r * c))
    gaussian = c / (r * (R + r * c))
    return mean, gaussian


def torus_directions(theta: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Unit meridian (increasing ``v``) and parallel (increasing ``theta``) directions, ``(..., 3)``.

    The meridian carries the curvature ``1 / r`` (``k1``), the parallel ``cos v / (R + r cos v)``.
    """
    meridian = torch.stack(
        (-torch.sin(v) * torch.cos(theta), -torch.sin(v) * torch.sin(theta), torch.cos(v)), dim=-1
    )
    parallel = torch.stack((-torch.sin(theta), torch.cos(theta), torch.zeros_like(theta)), dim=-1)
    return meridian, parallel


def ellipsoid_gaussian_curvature(points: Tensor, a: Tensor | float, b: Tensor | float,
                                 c: Tensor | float) -> Tensor:
    """``K = 1 / (a^2 b^2 c^2 (x^2/a^4 + y^2/b^4 + z^2/c^4)^2)`` at a point on it.

    ``a, b, c`` may be tensors broadcasting against ``points[..., 0]`` (one ellipsoid per point).
    """
    x, y, z = points.unbind(dim=-1)
    return 1.0 / ((a * b * c) ** 2 * (x**2 / a**4 + y**2 / b**4 + z**2 / c**4) ** 2)


@pytest.fixture
def generator() -> torch.Generator:
    """A seeded generator, so that random inputs are the same on every run."""
    return torch.Generator().manual_seed(0)


@pytest.fixture(autouse=True)
def _compile_when_marked(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A test marked ``compiled`` (minutes of eager work on a few kernels, which a user's run
    would compile) runs with ``TORCHSURF_COMPILE=always``: compiled from the first call, not
    after a payback that would land the compile in the middle of the test."""
    if request.node.get_closest_marker("compiled") is not None:
        monkeypatch.setattr(backend, "COMPILE", "always")


@pytest.fixture(autouse=True)
def _seeded_global_rng() -> None:
    """Each test starts from the same global RNG state, whatever ran before it: module
    initialisers and unseeded draws give the same values in any order or subset of tests."""
    torch.manual_seed(0)
