"""HarmonicMapFlow: unit length kept, identity map of the sphere stationary, energy descent."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import HarmonicMapFlow
from torchsurf.flows._integrators import with_ring
from torchsurf.flows.harmonic import normalize


def sphere(n=17, dtype=torch.float64):
    grid = ts.Grid.cube(n, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=dtype), grid)
    identity = normalize(grid.points(dtype=dtype).permute(3, 0, 1, 2)[None])
    return identity, surface


def noisy(identity, amount=0.3, seed=0):
    generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(identity.shape, generator=generator, dtype=identity.dtype)
    return normalize(identity + amount * noise)


def dirichlet_energy(u, surface):
    return float(-(u * surface.weight * ts.laplace_beltrami(u, surface)).sum() / 2)


@pytest.mark.parametrize("p", [1.0, 1.5, 2.0])
def test_unit_length_is_kept(p):
    identity, surface = sphere(13)
    u = HarmonicMapFlow(0.002, p=p, eps=0.5)(noisy(identity), surface)
    norms = u.norm(dim=1)
    torch.testing.assert_close(norms, torch.ones_like(norms))


@pytest.mark.parametrize("settings", [{"method": "euler"}, {"method": "heun", "steps": 20}, {}])
def test_vectors_of_other_lengths_are_made_unit_before_the_first_step(settings):
    """The built-in integrators took their first step from the lengths given, not from the unit
    vectors the docstring says they are made (an audit)."""
    identity, surface = sphere(13)
    unit = noisy(identity)
    lengths = 0.5 + torch.rand(unit[:, :1].shape, generator=torch.Generator().manual_seed(3),
                               dtype=unit.dtype)
    flow = HarmonicMapFlow(0.002, p=1.5, eps=0.5, **settings)
    region = with_ring(flow.band_mask(surface), None).expand_as(unit)  # beyond: as given
    torch.testing.assert_close(flow(unit * lengths, surface)[region], flow(unit, surface)[region],
                               rtol=0, atol=1e-12)


def test_identity_map_of_the_sphere_is_stationary():
    identity, surface = sphere(17)
    near = (surface.phi.abs() <= surface.spacing).expand_as(identity)
    start = noisy(identity, 0.2)
    flow = HarmonicMapFlow(0.01)
    still = (flow(identity, surface) - identity).abs()[near].max()
    moved = (flow(start, surface) - start).abs()[near].max()
    assert still < 0.05 * moved, (float(still), float(moved))


def test_harmonic_energy_never_increases():
    identity, surface = sphere(13)
    u0 = noisy(identity)
    flow = HarmonicMapFlow(0.004)
    energies = [dirichlet_energy(u, surface)
                for u in (u0, *flow(u0, surface, times=[0.001, 0.002, 0.003, 0.004]))]
    assert all(b <= a for a, b in zip(energies, energies[1:], strict=False)), energies


def test_tangent_constraint_keeps_fields_tangent():
    identity, surface = sphere(13)
    generator = torch.Generator().manual_seed(3)
    field = torch.randn(identity.shape, generator=generator, dtype=identity.dtype)
    u = HarmonicMapFlow(0.002, tangent=True)(normalize(field), surface)
    band = surface.band_mask().expand_as(u[:, :1])
    along = (u * surface.normal).sum(1, keepdim=True)
    assert along[band].abs().max() < 1e-9  # rounding: the normals are unit to eps^2 / |grad phi|^2


def test_a_tangent_flow_refuses_data_along_the_normals():
    """u0 = the normals with tangent=True ran: P u / |P u| made unit vectors of rounding, which
    pointed opposite ways in float32 and float64."""
    identity, surface = sphere(13)
    across = torch.zeros_like(identity)
    across[:, 0] = 1.0
    normal = torch.where(surface.normal.norm(dim=1, keepdim=True) > 0.5, surface.normal, across)
    with pytest.raises(ValueError, match=r"u0 \(tangent=True\) has no part tangent .* at (100|9\d)%"):
        HarmonicMapFlow(0.002, tangent=True)(normal, surface)
    HarmonicMapFlow(0.002)(normal, surface)  # without the constraint: a map like any other


@pytest.mark.parametrize("method", ["rk4", "midpoint", "dopri5"])
def test_tangent_fields_from_noise_under_torchdiffeq(method):
    """torchdiffeq's methods project only between their pieces: a raw noise field ran a whole
    piece before it was first made tangent, its normal part grew, and rk4 and midpoint ended
    in NaN (dopri5 in torchdiffeq's "underflow in dt" AssertionError), at 40^3 with the
    default steps as with ten times shorter ones (here, at 24^3 in float64: rk4 and dopri5).
    Now the start is projected and the rate keeps a tangent field tangent and unit; the
    result is finite, unit and tangent."""
    pytest.importorskip("torchdiffeq")
    n = 24
    grid = ts.Grid.cube(n, bound=1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    generator = torch.Generator().manual_seed(0)
    field = normalize(torch.randn((1, 3, n, n, n), generator=generator, dtype=torch.float64))
    time, eps = 3 * surface.spacing**2, 0.1 / surface.spacing
    u = HarmonicMapFlow(time, p=2.0, eps=eps, tangent=True, method=method)(field, surface)
    band = surface.band_mask()
    assert bool(torch.isfinite(u).all())
    torch.testing.assert_close(u.norm(dim=1, keepdim=True)[band],
                               torch.ones_like(u[:, :1])[band])
    assert (u * surface.normal).sum(1, keepdim=True)[band].abs().max() < 1e-9


@pytest.fixture(scope="module")
def converged_flow():
    """A noisy start on the sphere at 21^3 and the flow to ``t = 0.004`` by 1000 Euler steps."""
    identity, surface = sphere(21)
    u0 = noisy(identity)
    return surface, u0, HarmonicMapFlow(0.004, method="euler", steps=1000)(u0, surface)


@pytest.mark.parametrize("method", ["rk4", "dopri5"])
def test_torchdiffeq_methods_follow_the_flow(method, converged_flow):
    """Between their projections torchdiffeq's methods integrated the rate as it is, whose
    radial part pushes ``|u|`` off 1 (the growth term ``u |P grad u|^p`` against the discrete
    diffusion's ``u . L u``): 0.10 from the converged flow at 21^3 (both methods; RKC 0.024).
    With the radial part removed, 5.9e-4 (rk4) and 1.4e-4 (dopri5)."""
    pytest.importorskip("torchdiffeq")
    surface, u0, converged = converged_flow
    u = HarmonicMapFlow(0.004, method=method)(u0, surface)
    near = (surface.distance() < surface.spacing).expand_as(u)
    assert (u - converged)[near].abs().max() < 5e-3


def test_bad_exponent_is_named():
    with pytest.raises(ValueError, match="p must"):
        HarmonicMapFlow(0.1, p=3.0)


def test_an_entry_of_data_runs_as_it_would_alone():
    """RKC's steps follow the data's largest |P grad u|^p: planned for the batch, a smooth field
    beside a random one took 12 steps instead of its 8 and moved by 1.0e-5 (40^3)."""
    identity, surface = sphere(40)
    x, y, z = identity[0]
    smooth = normalize(identity + 0.3 * torch.stack([y, -x, 0 * z])[None])
    random = normalize(torch.randn(identity.shape, dtype=identity.dtype,
                                   generator=torch.Generator().manual_seed(0)))
    flow = HarmonicMapFlow(0.05)
    both = flow(torch.cat([smooth, random]), surface)
    alone = flow(smooth, surface)
    torch.testing.assert_close(both[:1], alone, rtol=0, atol=1e-12)


def test_the_energy_factor_stays_finite_in_float32_where_u_varies_along_the_normal():
    """The p = 1 rate's factor (E + eps^2)^(-1/2) formed E as |g|^2 - (g . n)^2, which fell
    below -eps^2 in float32 for unit vectors rotating along n: 24 NaN in the rate, and the flow
    refused as diverged (a review). E is now |P g|^2 from P g itself."""
    from torchsurf.flows.harmonic import power_diffusivity

    grid = ts.Grid.cube(40, 1.5)
    phi = ts.sdf.sphere(grid)
    surface = ts.ImplicitSurface(phi, grid)
    band = surface.band_mask()
    u = torch.cat([torch.cos(20 * phi), torch.sin(20 * phi), torch.zeros_like(phi)], 1)
    rate = ts.operators.functional.harmonic_map_rate(
        u, surface.normal, surface.weight, grid.spacing, power_diffusivity, -1.0, 1e-3, 0.5,
        "symmetric", "slicing", band)
    assert bool(torch.isfinite(rate).all())
    assert bool(torch.isfinite(ts.HarmonicMapFlow(1e-4, p=1.0, eps=1e-3)(u, surface)).all())


@pytest.mark.parametrize("magnitude", [1e-30, 1e-15, 1e20, 1e30])
def test_vectors_of_any_length_are_made_unit_at_the_start(magnitude):
    """Their squares overflowed or underflowed in float32: vectors of length 1e20 came out zero
    without a word, 1e-15 ones 0.06 off the unit start's flow, 1e-19 ones were refused as zero."""
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, 1.0), grid)
    x, y, z = grid.points().unbind(-1)
    v = torch.stack([torch.cos(3 * x + y), torch.sin(3 * x + y) * torch.cos(2 * z),
                     torch.sin(3 * x + y) * torch.sin(2 * z)])[None]
    flow = HarmonicMapFlow(0.01, p=1, eps=0.1)
    band = surface.band_mask().expand_as(v)
    torch.testing.assert_close(flow(magnitude * v, surface)[band], flow(v, surface)[band],
                               rtol=0, atol=2e-6)
    with pytest.raises(ValueError, match="zero vectors"):
        flow(torch.zeros_like(v), surface)
