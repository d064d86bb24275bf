"""Checkpointed integration: the same gradients, a fraction of the memory kept for backward."""

from __future__ import annotations

import pytest
import torch

import torchsurf as ts


def _saved_bytes(run) -> tuple[torch.Tensor, int]:
    total = 0

    def pack(tensor):
        nonlocal total
        total += tensor.numel() * tensor.element_size()
        return tensor

    with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
        value = run()
    return value, total


@pytest.mark.parametrize("method,steps", [("euler", 64), ("rkc", None), ("heun", 36)])
def test_checkpointing_keeps_gradients_and_cuts_saved_memory(method, steps):
    grid = ts.Grid.cube(17, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid, dtype=torch.float64), grid)
    generator = torch.Generator().manual_seed(0)
    u0 = torch.rand((1, 2, *grid.shape), dtype=torch.float64, generator=generator)
    weights = torch.rand(u0.shape, dtype=torch.float64, generator=generator)
    results = {}
    for checkpoint in (False, True):
        flow = ts.HeatFlow(0.02, learn_diffusivity=True, method=method, steps=steps,
                           checkpoint=checkpoint).double()
        start = u0.clone().requires_grad_(True)
        value, saved = _saved_bytes(lambda flow=flow, start=start: flow(start, surface))
        (value * weights).sum().backward()
        grads = (start.grad, *(p.grad for p in flow.parameters()))
        results[checkpoint] = (value.detach(), grads, saved)
    plain, kept = results[False], results[True]
    torch.testing.assert_close(kept[0], plain[0], rtol=1e-12, atol=1e-12)
    for a, b in zip(kept[1], plain[1], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    assert kept[2] < plain[2] / 3, (kept[2], plain[2])


def test_checkpoint_auto_follows_autograd_and_bad_values_are_refused():
    grid = ts.Grid.cube(9, 1.5)
    surface = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
    u0 = torch.rand((1, 1, *grid.shape))
    flow = ts.HeatFlow(0.01)
    system = flow.system(u0, surface)
    assert not flow._checkpointing(u0, surface, system)
    assert flow._checkpointing(u0.requires_grad_(True), surface, system)
    with torch.no_grad():
        assert not flow._checkpointing(u0, surface, system)
    with pytest.raises(TypeError, match="checkpoint"):
        ts.HeatFlow(0.01, checkpoint="yes")
