"""torchsurf.sdf.redistance: any implicit function to a signed distance in the band."""

from __future__ import annotations

import math

import pytest
import torch

import torchsurf as ts
from torchsurf.sampling import sample

AXES = (1.0, 0.7, 0.5)


def ellipsoid(grid: ts.Grid, scale: float = 1.0) -> torch.Tensor:
    """``scale * (x^2/a^2 + y^2/b^2 + z^2/c^2 - 1)``: the right zero set, far from a distance."""
    return ts.sdf.from_function(
        grid, lambda p: scale * ((p**2 / p.new_tensor(AXES) ** 2).sum(-1) - 1),
        dtype=torch.float64,
    )


def on_ellipsoid(count: int) -> torch.Tensor:
    generator = torch.Generator().manual_seed(1)
    polar = torch.rand(count, generator=generator, dtype=torch.float64) * math.pi
    azimuth = torch.rand(count, generator=generator, dtype=torch.float64) * 2 * math.pi
    return torch.stack(
        (AXES[0] * polar.sin() * azimuth.cos(), AXES[1] * polar.sin() * azimuth.sin(),
         AXES[2] * polar.cos()), dim=-1
    )


@pytest.fixture(scope="module")
def redistanced() -> tuple[ts.Grid, torch.Tensor]:
    grid = ts.Grid.cube(61, bound=1.3)
    return grid, ts.sdf.redistance(ellipsoid(grid), grid)


def test_unit_gradient_in_the_band(redistanced: tuple[ts.Grid, torch.Tensor]) -> None:
    grid, phi = redistanced
    gradient = torch.gradient(phi[0, 0], spacing=grid.spacing)
    norm = torch.sqrt(sum(g**2 for g in gradient))
    inner_band = phi[0, 0].abs() < 3 * grid.spacing
    deviation = (norm[inner_band] - 1).abs()
    assert deviation.max() < 0.05
    assert deviation.mean() < 0.01


def test_zero_set_stays_in_place(redistanced: tuple[ts.Grid, torch.Tensor]) -> None:
    grid, phi = redistanced
    moved = sample(phi, on_ellipsoid(2000), grid).abs().max()
    assert moved < 0.1 * grid.spacing


def test_sign_kept_and_band_clamped(redistanced: tuple[ts.Grid, torch.Tensor]) -> None:
    grid, phi = redistanced
    original = ellipsoid(grid)
    assert torch.equal(torch.sign(phi), torch.sign(original))
    band = ts.sdf.BAND_NODES * grid.spacing
    assert phi.abs().max() == pytest.approx(band)


def test_scale_of_the_input_does_not_matter() -> None:
    grid = ts.Grid.cube(33, bound=1.3)
    once = ts.sdf.redistance(ellipsoid(grid), grid)
    scaled = ts.sdf.redistance(ellipsoid(grid, scale=40.0), grid)
    torch.testing.assert_close(once, scaled, atol=1e-12, rtol=0)


def test_batch_dtype_and_band() -> None:
    grid = ts.Grid.cube(25, bound=1.3)
    sphere = ts.sdf.sphere(grid, radius=0.8)
    batch = torch.cat((sphere, ellipsoid(grid).float()))
    result = ts.sdf.redistance(batch, grid, band_width=0.2)
    assert result.shape == batch.shape and result.dtype == torch.float32
    assert result.abs().max() <= 0.2 + 1e-6
    assert not batch.requires_grad
    torch.testing.assert_close(result[:1], sphere.clamp(-0.2, 0.2), atol=0.02, rtol=0)


def test_bad_input_raises() -> None:
    grid = ts.Grid.cube(9, bound=1.0)
    with pytest.raises(ValueError, match="phi"):
        ts.sdf.redistance(torch.ones(1, 1, 9, 9, 9), grid)
    with pytest.raises(ValueError, match="phi"):
        ts.sdf.redistance(torch.ones(1, 9, 9, 9), grid)
    with pytest.raises(ValueError, match="phi"):
        ts.sdf.redistance(torch.full((1, 1, 9, 9, 9), float("nan")), grid)
    with pytest.raises(ValueError, match="band_width"):
        ts.sdf.redistance(ts.sdf.sphere(grid, 0.5), grid, band_width=-1.0)
