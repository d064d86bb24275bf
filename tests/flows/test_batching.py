"""Batching of every flow: a batch of B signals over one surface, and over B surfaces, gives row by
row what each signal gives alone on its own surface (the flows issue: "Every flow runs on a batch
of B signals over one surface, and on B surfaces, with the same code").

Each check is shown able to fail: the two rows of a batch differ, and element 1 run on the wrong
surface differs from the batched result by orders of magnitude more than the tolerance.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import pytest
import torch
from torch import Tensor, nn

import torchsurf as ts
from torchsurf.flows import (
    AnisotropicFlow,
    ColorDenoise,
    Extension,
    FlowVisualization,
    HarmonicMapFlow,
    HeatFlow,
    ReactionDiffusion,
)
from torchsurf.flows.harmonic import normalize

DTYPE = torch.float64
N = 13
GRID = ts.Grid.cube(N, bound=1.5)
NOISE_SEED = 5
TIGHT = {"rtol": 1e-10, "atol": 1e-12}
# implicit methods: conjugate gradients freeze each volume once it has converged, so a batch
# iterates every volume exactly as often as a run alone would
SOLVED = TIGHT
# element 1 on the wrong surface, or the two rows of a batch, must differ by at least this
DIFFERENT = 1e-4


def points() -> Tensor:
    """World coordinates as channels ``(1, 3, D, H, W)``."""
    return GRID.points(dtype=DTYPE).permute(3, 0, 1, 2)[None]


def noise(seed: int, channels: int) -> Tensor:
    generator = torch.Generator().manual_seed(seed)
    return torch.randn((1, channels, N, N, N), generator=generator, dtype=DTYPE)


def scalar(seed: int) -> Tensor:
    return noise(seed, 1)


def unit_vectors(seed: int) -> Tensor:
    return normalize(points() + 0.4 * noise(seed, 3))


def rgb(seed: int) -> Tensor:
    return 0.5 + 0.15 * noise(seed, 3)


def turk(seed: int) -> Tensor:
    """Turk's start ``a = b = 4``, perturbed differently for each seed."""
    return 4.0 + 0.5 * noise(seed, 2).tanh()


def smooth(seed: int) -> Tensor:
    x, y, z = points().unbind(1)
    return (x + 0.5 * y * z if seed == 0 else torch.sin(2 * y) + z)[:, None]


def rotation(element: int) -> Tensor:
    """A tangent-ish field ``(1, 3, D, H, W)``: rotation about z (even elements) or x (odd)."""
    x, y, z = points().unbind(1)
    zero = torch.zeros_like(x)
    fields = ((-y, x, zero), (zero, -z, y))
    return torch.stack(fields[element % 2], dim=1)


@dataclass(frozen=True)
class Case:
    """A flow, how to make its signal for a seed, and which extra inputs its call takes."""

    flow: Callable[[], nn.Module]
    signal: Callable[[int], Tensor]
    direction: bool = False
    generator: bool = False
    tolerance: dict = field(default_factory=lambda: TIGHT)


CASES = {
    "heat_euler": Case(lambda: HeatFlow(0.02), scalar),
    "heat_heun": Case(lambda: HeatFlow(0.02, method="heun"), scalar),
    "heat_chebyshev": Case(lambda: HeatFlow(0.02, method="chebyshev"), scalar),
    "heat_crank_nicolson": Case(
        lambda: HeatFlow(0.02, method="crank_nicolson", steps=2), scalar, tolerance=SOLVED
    ),
    "total_variation": Case(lambda: AnisotropicFlow(0.01, eps=0.5), scalar),
    "perona_malik": Case(lambda: AnisotropicFlow(0.02, "perona_malik", contrast=0.5), scalar),
    "charbonnier": Case(lambda: AnisotropicFlow(0.02, "charbonnier", contrast=0.5), scalar),
    "harmonic_p2": Case(lambda: HarmonicMapFlow(0.02), unit_vectors),
    "harmonic_p1": Case(lambda: HarmonicMapFlow(0.005, p=1.0, eps=0.5), unit_vectors),
    "harmonic_tangent": Case(lambda: HarmonicMapFlow(0.02, tangent=True), unit_vectors),
    "color_denoise": Case(lambda: ColorDenoise(0.004), rgb),
    # steps fixed (dt = 0.5, under the stable h^2 / (6 D_a) = 2/3): the automatic step also
    # reads the largest a and b of the whole batch
    "reaction_diffusion": Case(lambda: ReactionDiffusion(10.0, steps=20), turk, generator=True),
    # the automatic re-extension period, like the automatic step, follows the batch's bound,
    # which the directional operator takes from each element's own field: fixed, like the steps
    "reaction_diffusion_directional": Case(
        lambda: ReactionDiffusion(10.0, steps=20, reextend_every=4), turk, direction=True,
        generator=True,
    ),
    "flow_visualization": Case(lambda: FlowVisualization(0.02, isotropic=0.1), scalar, direction=True),
    "flow_visualization_implicit": Case(
        lambda: FlowVisualization(0.02, method="implicit", steps=2), scalar, direction=True,
        tolerance=SOLVED,
    ),
    "extension_closest_point": Case(lambda: Extension("closest_point"), scalar),
    "extension_closest_point_cubic": Case(lambda: Extension(interpolation="cubic"), scalar),
    "heat_reextended": Case(lambda: HeatFlow(0.02, steps=4, reextend_every=2), scalar),
    # on this grid the default tolerance is never met: both run all max_steps
    "extension_pde": Case(lambda: Extension("pde"), scalar),
    # ... with a looser tolerance the loop stops early; it used to stop on the largest change
    # over the whole batch (a volume alone stopped 3 steps before it did beside another)
    "extension_pde_converged": Case(lambda: Extension("pde", tolerance=1e-3), smooth),
}
NAMES = list(CASES)


@pytest.fixture(scope="module")
def surfaces() -> tuple[ts.ImplicitSurface, ts.ImplicitSurface, ts.ImplicitSurface]:
    """Surface 0, surface 1, and both stacked into one surface of batch 2."""
    first = ts.sdf.sphere(GRID, radius=1.0, dtype=DTYPE)
    second = ts.sdf.sphere(GRID, radius=0.8, center=(0.1, -0.05, 0.15), dtype=DTYPE)
    return (
        ts.ImplicitSurface(first, GRID),
        ts.ImplicitSurface(second, GRID),
        ts.ImplicitSurface(torch.cat((first, second)), GRID),
    )


def run(case: Case, flow: nn.Module, u0: Tensor, surface: ts.ImplicitSurface, first: int,
        per_element: bool) -> Tensor:
    """``flow(u0, surface, ...)`` where ``u0``'s rows are elements ``first, first + 1, ...`` of the
    batch: each element gets its own direction field (``per_element``; otherwise all share
    element 0's, batch 1) and its own share of the generator's noise."""
    inputs: dict[str, object] = {}
    if case.direction:
        elements = range(first, first + u0.shape[0]) if per_element else [0]
        inputs["direction"] = torch.cat([rotation(k) for k in elements])
    if case.generator:
        # ReactionDiffusion draws beta's noise (B, 1, D, H, W) in one go: skip what the
        # elements before ``first`` would have taken, so each element sees the same noise
        generator = torch.Generator().manual_seed(NOISE_SEED)
        torch.rand((first, 1, N, N, N), generator=generator, dtype=DTYPE)
        inputs["generator"] = generator
    return flow(u0, surface, **inputs)


def check_batch(result: Tensor, u0: Tensor) -> None:
    assert result.shape == u0.shape == (2, u0.shape[1], N, N, N)
    assert torch.isfinite(result).all()
    assert (result[0] - result[1]).abs().max() > DIFFERENT


@pytest.mark.parametrize("name", NAMES)
def test_batch_of_signals_over_one_surface(name, surfaces):
    case, (surface, _, _) = CASES[name], surfaces
    flow = case.flow()
    u0 = torch.cat((case.signal(0), case.signal(1)))
    together = run(case, flow, u0, surface, 0, per_element=False)
    check_batch(together, u0)
    for k in range(2):
        alone = run(case, flow, u0[k:k + 1], surface, k, per_element=False)
        torch.testing.assert_close(together[k:k + 1], alone, **case.tolerance)


@pytest.mark.parametrize("name", NAMES)
def test_batch_of_signals_over_a_batch_of_surfaces(name, surfaces):
    case, (first, second, both) = CASES[name], surfaces
    flow = case.flow()
    u0 = torch.cat((case.signal(0), case.signal(1)))
    together = run(case, flow, u0, both, 0, per_element=True)
    check_batch(together, u0)
    for k, surface in enumerate((first, second)):
        alone = run(case, flow, u0[k:k + 1], surface, k, per_element=True)
        torch.testing.assert_close(together[k:k + 1], alone, **case.tolerance)
    # the check can fail: element 1 on surface 0 is far from element 1 on surface 1
    wrong = run(case, flow, u0[1:], first, 1, per_element=True)
    assert (wrong - together[1:]).abs().max() > DIFFERENT


@pytest.mark.parametrize("make", [
    lambda h2: ts.HeatFlow(30 * h2), lambda h2: ts.HeatFlow(30 * h2, method="chebyshev"),
    lambda h2: ts.HeatFlow(30 * h2, method="euler"), lambda h2: ts.flows.AnisotropicFlow(2 * h2),
])
def test_entries_of_one_band_width_and_different_bounds_equal_their_runs_alone(make):
    """An off-centre sphere and a box, both on 3-cell bands, have different operator bounds:
    the shared plan of the batch's largest bound left the sphere 2.6e-4 (RKC) and 6.2e-4
    (chebyshev) off its run alone at t = 30 h^2; each entry is now integrated alone."""
    grid = ts.Grid.cube(18, bound=1.6)
    phis = [ts.sdf.sphere(grid, radius=0.9, center=(0.03, -0.02, 0.05), dtype=torch.float64),
            ts.sdf.box(grid, dtype=torch.float64)]
    both = ts.ImplicitSurface(torch.cat(phis), grid)
    flow = make(grid.spacing**2)
    assert len(set(flow._entry_widths(both))) == 1
    u = torch.rand(2, 1, *grid.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    together = flow(u, both)
    for b, phi in enumerate(phis):
        assert torch.equal(together[b:b + 1], flow(u[b:b + 1], ts.ImplicitSurface(phi, grid))), b


def test_a_batch_integrated_entry_by_entry_does_not_warn_about_its_surface_again():
    """Each entry's own surface repeated the batch surface's warnings (S near the box's
    faces) at the first flow call."""
    import warnings

    grid = ts.Grid.cube(16, bound=1.05)
    phi = torch.cat([ts.sdf.sphere(grid, 1.0), ts.sdf.sphere(grid, 0.5)])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        surface = ts.ImplicitSurface(phi, grid)
        built = len(caught)
        ts.HeatFlow(0.01)(torch.rand(2, 1, *grid.shape, generator=torch.Generator().manual_seed(0)),
                          surface)
    assert built == 1 and len(caught) == 1
