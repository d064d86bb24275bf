"""A layer traced on a surface it has not run on runs once as is first (``torch.compile``)."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from ._transforms import exporting
from .surface import ImplicitSurface

SETTINGS = ("method", "scheme", "path", "band_width", "reextend_every", "steps",
            "interpolation", "width", "limited")
"""The layer attributes that decide what it keeps on a surface, in its mark (with its class)."""


def run_as_is_first(layer: nn.Module, u0: object, surface: object, /, *args: object,
                    **inputs: object) -> None:
    """While ``torch.compile`` traces ``layer`` on a surface it has not run on:
    ``layer.forward(u0, surface, *args, **inputs)`` as is, once, outside the trace and without
    autograd (nor the layer's own hooks; its submodules' run), so that what the layer keeps on
    the surface (its bands, stencils, bounds, packed operators: :meth:`ImplicitSurface.kept`)
    is formed in one graph break. Formed where each is first read, they broke the traced graph
    about 20 times on a fresh surface (an Euler heat step: its first compiled call at 9^3 took
    37 s, now 14.5 s) and each piece compiled apart.

    A call as is marks the surface for layers like this one (its class and :data:`SETTINGS`,
    the data's batch, channels and dtype; not the layer object, whose identity a compiled
    function would guard on, recompiling for each layer); a traced call on a marked surface
    traces whole. The run gives its warnings (the traced call skips the checks that give some:
    a flow that left the range of ``u0``), and leaves the random state as it found it, the
    global one and any generator among ``inputs`` (a reaction's noise is then the pattern of
    the traced call's own draw)."""
    if (not isinstance(surface, ImplicitSurface) or not isinstance(u0, Tensor) or u0.dim() < 2
            or exporting()):
        return  # the layer's own checks name what is wrong
    marker = _ran_as_is(layer, u0)
    if not torch.compiler.is_compiling():
        surface.kept(marker, lambda: True)  # this call forms what the layer keeps
    elif not surface.is_kept(marker):
        generators = [value for value in inputs.values() if isinstance(value, torch.Generator)]
        torch.compiler.disable(_run_without_grad)(layer, u0, surface, args, inputs, generators)


def _ran_as_is(layer: nn.Module, u0: Tensor) -> tuple:
    """The mark a call of ``layer`` on ``u0`` as is leaves on its surface."""
    settings = tuple(getattr(layer, name, None) for name in SETTINGS)
    return ("ran as is", type(layer).__qualname__, settings, u0.shape[0], u0.shape[1], u0.dtype)


def _run_without_grad(layer: nn.Module, u0: Tensor, surface: ImplicitSurface, args: tuple,
                      inputs: dict, generators: list[torch.Generator]) -> None:
    surface.kept(_ran_as_is(layer, u0), lambda: True)  # first: a nested call of it returns
    states = [generator.get_state() for generator in generators]
    devices = [u0.device] if u0.device.type == "cuda" else []
    # forward, not the module's call: no compiled call (Module.compile) to recurse into
    with torch.random.fork_rng(devices=devices), torch.no_grad():
        layer.forward(u0, surface, *args, **inputs)
    for generator, state in zip(generators, states, strict=True):
        generator.set_state(state)
