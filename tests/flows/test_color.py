"""ColorDenoise: chroma and brightness flowed apart, noise removed, shapes kept."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts
from torchsurf.flows import ColorDenoise, HeatFlow


def test_colour_denoising_reduces_noise_on_the_surface():
    grid = ts.Grid.cube(17, bound=1.3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    z = grid.points(dtype=torch.float64)[..., 2][None, None]
    clean = torch.cat((0.6 + 0.3 * (z > 0), 0.4 + 0 * z, 0.5 - 0.2 * (z > 0)), dim=1)
    generator = torch.Generator().manual_seed(0)
    noisy = clean + 0.1 * torch.randn(clean.shape, generator=generator, dtype=clean.dtype)
    near = (surface.phi.abs() <= surface.spacing).expand_as(clean)
    flow = ColorDenoise(0.004, brightness=HeatFlow(0.004))
    out = flow(noisy, surface)
    assert out.shape == clean.shape
    before = float((noisy - clean)[near].square().mean())
    after = float((out - clean)[near].square().mean())
    assert after < 0.5 * before, (before, after)
    assert torch.isfinite(ColorDenoise(0.001)(noisy, surface)).all()


def test_black_nodes_get_a_grey_chroma_and_a_single_channel_is_named():
    """A black node (every channel 0, as clamping a noisy image leaves) had a zero chroma,
    which the harmonic map flow refused; one channel was refused as ``u0``."""
    grid = ts.Grid.cube(21, bound=1.3)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, radius=1.0, dtype=torch.float64), grid)
    image = torch.full((1, 3, *grid.shape), 0.5, dtype=torch.float64)
    band = surface.band_mask()[0, 0]
    black = band.nonzero()[:5]
    image[0, :, black[:, 0], black[:, 1], black[:, 2]] = 0.0
    image.requires_grad_()
    out = ColorDenoise(0.002, brightness=HeatFlow(0.002))(image, surface)
    assert torch.isfinite(out).all()
    near = band.expand_as(out[0])
    values = out[0][near].detach()
    # the default RKC on the octant scheme (not monotone: docs) lifts the brightness's maximum
    # by 1e-4 of it next to the black nodes' dips; Euler steps do not
    assert float(values.min()) >= 0.0 and float(values.max()) <= 0.5 * (1 + 3e-4)
    # the black nodes took their grey neighbours' chroma: grey, brightened by the heat flow
    at_black = out[0, :, black[:, 0], black[:, 1], black[:, 2]]
    assert torch.allclose(at_black, at_black[:1].expand_as(at_black), atol=1e-12)
    (gradient,) = torch.autograd.grad(out[0][near].sum(), image)
    assert torch.isfinite(gradient).all()
    with pytest.raises(ValueError, match="image must have at least 2 colour channels"):
        ColorDenoise(0.001)(image[:, :1].detach(), surface)


def test_brightness_keeps_its_range_and_chroma_its_length_but_channels_may_leave_theirs():
    """What the model promises: ``|I|`` stays within its start's range (total variation's
    maximum principle) and the chroma on the unit sphere. A channel alone does not: a bright,
    nearly grey node whose chroma turns towards a primary colour gains in that channel
    (docstring): on a torus half pale grey, half pure green, the grey side's chroma turns
    green near the border under its brightness of about ``sqrt(3)``."""
    grid = ts.Grid.cube(25, bound=2.0)
    phi = ts.sdf.torus(grid, major_radius=1.0, minor_radius=0.4, dtype=torch.float64)
    surface = ts.ImplicitSurface(phi, grid)
    x = grid.points(dtype=torch.float64)[..., 0][None, None]
    grey = torch.full_like(x, 0.95)
    image = torch.cat((torch.where(x < 0, grey, 0.0), torch.where(x < 0, grey, 1.0),
                       torch.where(x < 0, grey, 0.0)), dim=1)
    flow = ColorDenoise(4 * surface.spacing**2)
    out = flow(image, surface)
    band = flow.brightness.band_mask(surface)[0, 0]
    brightness_in, brightness_out = image[0].norm(dim=0)[band], out[0].norm(dim=0)[band]
    assert float(brightness_out.max()) <= float(brightness_in.max()) * (1 + 1e-9)
    assert float(brightness_out.min()) >= float(brightness_in.min()) * (1 - 1e-9)
    assert float(out[0][:, band].min()) >= 0.0
    assert float(out[0, 1][band].max()) > 1.05  # green left [0, 1]: clamp if it must not


def test_settings_the_given_flows_would_ignore_are_refused():
    """``time``, ``p`` and integration settings set only the default flows: with both flows
    given they were ignored without a word (``time=123, method="euler"`` ran the flows' own)."""
    from torchsurf.flows import HarmonicMapFlow

    chroma, brightness = HarmonicMapFlow(0.01), HeatFlow(0.01)
    with pytest.raises(ValueError, match="time: not used"):
        ColorDenoise(123.0, chroma=chroma, brightness=brightness)
    with pytest.raises(ValueError, match="p: not used"):
        ColorDenoise(0.01, p=2.0, chroma=chroma)
    with pytest.raises(ValueError, match="method, steps: not used"):
        ColorDenoise(chroma=chroma, brightness=brightness, method="euler", steps=3)
    with pytest.raises(TypeError, match="time is needed"):
        ColorDenoise(chroma=chroma)
    flow = ColorDenoise(chroma=chroma, brightness=brightness)
    assert flow.chroma is chroma and flow.brightness is brightness
    # one flow given: time and settings go to the other
    flow = ColorDenoise(0.02, brightness=brightness, method="euler")
    assert flow.chroma.method == "euler" and float(flow.chroma.time) == pytest.approx(0.02)
    assert ColorDenoise(0.02, p=2.0).chroma.p == 2.0


def test_flows_of_the_wrong_kind_are_refused():
    """A scalar flow as ``chroma`` left the chroma off the unit sphere; a harmonic map as
    ``brightness`` failed inside it speaking of ``u0``."""
    from torchsurf.flows import AnisotropicFlow, FlowVisualization, HarmonicMapFlow, ReactionDiffusion

    with pytest.raises(TypeError, match="chroma must keep unit vectors.*AnisotropicFlow"):
        ColorDenoise(0.01, chroma=AnisotropicFlow(0.01))
    with pytest.raises(TypeError, match="chroma must keep unit vectors.*LearnedDiffusion"):
        ColorDenoise(0.01, chroma=ts.nn.LearnedDiffusion(3, time=8.0))
    for flow in (HarmonicMapFlow(0.01), ReactionDiffusion(1.0), FlowVisualization(0.01)):
        with pytest.raises(TypeError, match=f"brightness must flow one scalar.*{type(flow).__name__}"):
            ColorDenoise(0.01, brightness=flow)


def test_a_chroma_flow_of_ones_own_is_taken():
    """A Flow subclass of the user's that keeps unit vectors was refused as 'a scalar flow'."""
    from torchsurf.flows import Flow

    class Projected(Flow):  # its system (unit vectors kept) is the user's business
        pass

    chroma = Projected(0.01)
    assert ColorDenoise(0.01, chroma=chroma).chroma is chroma
