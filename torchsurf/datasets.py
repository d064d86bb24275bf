"""Synthetic training data: random signals on a batch of surfaces, clean and with seeded noise.

Signals are evaluated at the closest point on S of every node (:func:`torchsurf.signals.closest_points`),
so they are constant along the normals, as the flows expect, where ``phi`` is a distance near S
(the analytic shapes, :func:`torchsurf.sdf.from_mesh`, :class:`SignalDataset`'s own surfaces).
Those first-order points miss S where ``phi`` is not a distance: on an ellipsoid's
``x^2/a^2 + y^2/b^2 + z^2/c^2 - 1`` (40^3) a smooth signal varied across the band by up to 0.10
of its range (0.04 within a cell of S) against the same signal on the ``redistance``d ``phi``;
call :func:`torchsurf.sdf.redistance` first for such a ``phi``. Lengths are in the units of the
grid: on a :class:`~torchsurf.shape_batch.MeshBatchAdapter` every shape has size 1 there, so a
frequency of 2 is two periods across any shape. Everything is deterministic under ``seed``.
"""

from __future__ import annotations

import inspect
import operator
from collections.abc import Iterator, Sequence

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset

from ._checks import check_choice, check_count, check_nonnegative, check_positive
from ._precision import in_data_dtype
from .shape_batch import MeshBatchAdapter
from .signals import closest_points, gaussian_noise, generator
from .surface import ImplicitSurface, check_surface

__all__ = [
    "DERIVED_SEED_LIMIT",
    "KEPT_SURFACES",
    "KINDS",
    "SignalDataset",
    "derived_seed",
    "piecewise_constant_signal",
    "signal",
    "smooth_signal",
]

KINDS = ("smooth", "piecewise_constant")


DERIVED_SEED_LIMIT = 2**32
"""The seed and keys of :func:`derived_seed` lie in ``[0, 2^32)``: numpy's ``SeedSequence``
splits larger numbers into 32-bit words, so ``(2^32 + 5, 0)`` would be ``(5, 1)``."""


def derived_seed(seed: int, *keys: int) -> int:
    """A seed for item ``keys`` of a run seeded ``seed`` (numpy's ``SeedSequence``; ``seed``
    and ``keys`` whole numbers in ``[0, 2^32)``): ``(seed, i)`` never collides with
    ``(seed + 1, i - 1)``, and distinct keys give independent streams unless their 32-bit
    seeds coincide, which among ``n`` items has odds of about ``n^2 / 2^33`` (a coincident pair
    is likely from about 90 000 items on). Trailing zero keys are not told apart (numpy pads
    short entropy with zeros): ``(seed, i)``, ``(seed, i, 0)`` and ``(seed, i, 0, 0)`` give one
    stream, so end keys that must differ with a nonzero number (:class:`SignalDataset` draws an
    item's signal from ``(seed, i)`` and its noise from ``(seed, i, 1)``)."""
    for name, value in (("seed", seed), *((f"keys[{k}]", key) for k, key in enumerate(keys))):
        value = check_count(value, name, minimum=0)
        if value >= DERIVED_SEED_LIMIT:
            raise ValueError(f"{name} must be a whole number in [0, 2**32), got {value}")
    return int(np.random.SeedSequence([int(seed), *map(int, keys)]).generate_state(1)[0])


def _rescale(values: Tensor, band: Tensor, surface: ImplicitSurface) -> Tensor:
    """Each entry and channel of ``values`` ``(B, C, ...)`` mapped to ``[0, 1]`` by its min and
    max over ``band`` ``(B or 1, 1, ...)``; on a brick surface the rows are bricks and each
    batch entry's bricks share its min and max."""
    inside = band.expand_as(values)
    low = torch.where(inside, values, torch.inf).flatten(2).amin(-1)
    high = torch.where(inside, values, -torch.inf).flatten(2).amax(-1)
    if surface.layout is not None:
        rows = surface.layout.batch.to(values.device)
        entry, size = rows[:, None].expand_as(low), (surface.batch_size, low.shape[1])
        low = low.new_full(size, torch.inf).scatter_reduce(0, entry, low, "amin")[rows]
        high = high.new_full(size, -torch.inf).scatter_reduce(0, entry, high, "amax")[rows]
    shape = (*values.shape[:2],) + (1,) * (values.dim() - 2)
    low, high = low.view(shape), high.view(shape)
    return ((values - low) / (high - low).clamp(min=torch.finfo(values.dtype).tiny)).clamp(0, 1)


def _field_shape(surface: ImplicitSurface, channels: int) -> tuple[int, ...]:
    """``(B, C, D, H, W)``, or packed ``(N, C, 8, 8, 8)`` on a brick surface."""
    if surface.layout is None:
        return (surface.batch_size, channels, *surface.grid.shape)
    return (len(surface.layout), channels, *surface.phi.shape[2:])


def _rows_of_entries(surface: ImplicitSurface) -> Tensor:
    """The batch entry of each row of a field: ``(B,)`` dense, ``(N,)`` on bricks."""
    if surface.layout is None:
        return torch.arange(surface.batch_size, device=surface.phi.device)
    return surface.layout.batch.to(surface.phi.device)


def smooth_signal(surface: ImplicitSurface, channels: int = 1, frequency: float = 2.0,
                  modes: int = 8, seed: int = 0) -> Tensor:
    """A random low-frequency signal: a sum of ``modes`` plane waves at the closest points.

    ``u(x) = sum_m a_m sin(2 pi k_m . p(x) + phase_m)``, ``p`` the closest point on S, ``k_m``
    of random direction and length uniform in ``[frequency / 2, frequency]`` (periods per unit
    length), ``a_m`` standard normal, ``phase_m`` uniform; then each entry and channel is
    rescaled to ``[0, 1]`` over the surface's band.

    Args:
        surface: ``B`` surfaces, dense or a :class:`~torchsurf.bricks.BrickSurface` (whose
            band gets the dense grid's values for the same seed).
        channels: ``C``.
        frequency: the highest wave number, periods per unit length of the grid.
        modes: waves per channel.
        seed: the same seed gives the same signal for the same surfaces and channels; the
            draws are laid out by batch entry and channel, so an entry of a batch is not the
            signal the same seed gives its surface alone (:class:`SignalDataset` draws each
            item on its own surface).

    Returns:
        ``(B, C, D, H, W)`` (packed ``(N, C, 8, 8, 8)`` on bricks) in ``[0, 1]``, the
        surface's dtype and device.
    """
    surface = check_surface(surface)
    channels = check_count(channels, "channels")
    frequency = check_positive(frequency, "frequency")
    modes = check_count(modes, "modes")
    dtype = surface.phi.dtype
    batch = surface.batch_size
    random = generator(seed)
    direction = torch.randn(batch, channels, modes, 3, generator=random, dtype=torch.float64)
    length = frequency * (0.5 + 0.5 * torch.rand(batch, channels, modes, 1, generator=random,
                                                 dtype=torch.float64))
    wave = (2 * torch.pi * length * direction / direction.norm(dim=-1, keepdim=True)).to(dtype)
    amplitude = torch.randn(batch, channels, modes, generator=random, dtype=torch.float64)
    phase = 2 * torch.pi * torch.rand(batch, channels, modes, generator=random,
                                      dtype=torch.float64)
    device = surface.phi.device
    wave, amplitude, phase = (t.to(dtype=dtype, device=device) for t in (wave, amplitude, phase))
    rows = _rows_of_entries(surface)
    wave, amplitude, phase = wave[rows], amplitude[rows], phase[rows]
    points = closest_points(surface)  # (B, 3, D, H, W), or packed
    values = torch.zeros(_field_shape(surface, channels), dtype=dtype, device=device)
    for m in range(modes):  # one wave at a time: memory of one (B, C, D, H, W) volume
        with in_data_dtype(points):
            angle = torch.einsum("bck,bkdhw->bcdhw", wave[:, :, m], points)
        values += amplitude[:, :, m, None, None, None] * torch.sin(
            angle + phase[:, :, m, None, None, None])
    return _rescale(values, surface.band_mask(), surface)


def piecewise_constant_signal(surface: ImplicitSurface, channels: int = 1, cells: int = 12,
                              seed: int = 0) -> Tensor:
    """A random piecewise-constant signal: ``cells`` regions with uniform random values.

    The regions are the Voronoi cells, in space, of ``cells`` points drawn at random among the
    closest points of the nodes next to S; every node takes the value of the cell its own closest
    point falls in, so the regions are patches of S bounded by curves, constant along normals.

    Args:
        surface: ``B`` surfaces, dense or a :class:`~torchsurf.bricks.BrickSurface` (whose
            band gets the dense grid's values for the same seed).
        channels: ``C``; the channels share the regions and differ in their values.
        cells: regions per surface, at most the nodes within one spacing of S (their centres
            are drawn among those nodes' closest points, without repeats).
        seed: the same seed gives the same signal for the same surfaces and channels; the
            draws are laid out by batch entry and channel, so an entry of a batch is not the
            signal the same seed gives its surface alone (:class:`SignalDataset` draws each
            item on its own surface).

    Returns:
        ``(B, C, D, H, W)`` (packed ``(N, C, 8, 8, 8)`` on bricks), values uniform in
        ``[0, 1)``, the surface's dtype and device.
    """
    surface = check_surface(surface)
    channels = check_count(channels, "channels")
    cells = check_count(cells, "cells")
    random = generator(seed)
    dtype, device = surface.phi.dtype, surface.phi.device
    result = torch.empty(_field_shape(surface, channels), dtype=dtype, device=device).flatten(2)
    for b, mine, entry_points, candidates, same_point in _entry_candidates(surface):
        pick = _distinct_draws(same_point, cells, random, f"surface {b}")
        centres = entry_points[:, candidates[pick.to(device)]]  # (3, cells)
        # in float64 about the centres' mean, by differences: cdist's matrix-product form
        # (|x|^2 + |c|^2 - 2 x.c) in float32 swapped a third of the regions of a shape at 1e3
        middle = centres.double().mean(dim=1, keepdim=True)
        nearest = torch.cdist((entry_points.double() - middle).T, (centres.double() - middle).T,
                              compute_mode="donot_use_mm_for_euclid_dist").argmin(dim=1)  # (n,)
        values = torch.rand(channels, cells, generator=random, dtype=torch.float64)
        values = values.to(dtype=dtype, device=device)
        result[mine] = values[:, nearest].view(channels, len(mine), -1).transpose(0, 1)
    return result.view(_field_shape(surface, channels))


def _point_classes(points: Tensor) -> Tensor:
    """The class of each of ``points`` ``(3, n)``, int64 ``(n,)``, equal for equal points: nodes
    on one normal line can share their closest point to the last bit (float32), and such
    centres would make one region, so they count as one candidate."""
    return torch.unique(points.T.cpu(), dim=0, return_inverse=True)[1]


def _entry_candidates(surface: ImplicitSurface) -> Iterator[tuple[int, Tensor, Tensor, Tensor,
                                                                  Tensor]]:
    """Per batch entry ``b``, where :func:`piecewise_constant_signal` draws its centres:
    ``(b, rows, points, candidates, classes)``: the entry's rows of the storage, the closest
    points of its nodes ``(3, n)``, the indices of the nodes within one spacing of S (in the
    dense grid's order on bricks, so that the same nodes are drawn) and each one's class
    (:func:`_point_classes`)."""
    points = closest_points(surface).flatten(2)  # (B, 3, n), or (N, 3, 512) on bricks
    near = (surface.distance() <= surface.spacing).flatten(2)[:, 0]  # (B, n)
    rows = _rows_of_entries(surface)
    order = None if surface.layout is None else _dense_order(surface)
    for b in range(surface.batch_size):
        mine = (rows == b).nonzero().squeeze(1)
        entry_points = points[mine].transpose(0, 1).flatten(1)  # (3, n)
        candidates = near[mine].flatten().nonzero().squeeze(1)
        if order is not None:
            candidates = candidates[order[mine].flatten()[candidates].argsort()]
        yield b, mine, entry_points, candidates, _point_classes(entry_points[:, candidates])


def _refuse_more_cells(classes: Tensor, wanted: int, name: str, key: str = "cells") -> int:
    """The number of distinct classes among ``classes``; raises naming ``key`` if ``wanted``
    regions are more than that on ``name``."""
    distinct = int(classes.max()) + 1 if len(classes) else 0
    if wanted > distinct:
        raise ValueError(
            f"{key} = {wanted} is more than the {distinct} distinct closest points of the nodes "
            f"within one spacing of S on {name}, among which the regions' centres are drawn: "
            f"ask for at most {distinct}"
        )
    return distinct


def _check_cells(surface: ImplicitSurface, cells: int, key: str) -> None:
    """Refuse ``cells`` regions of :func:`piecewise_constant_signal` on ``surface`` where an
    entry has fewer candidate centres, naming ``key``."""
    for b, _, _, _, classes in _entry_candidates(surface):
        _refuse_more_cells(classes, cells, f"surface {b}", key)


def _distinct_draws(classes: Tensor, wanted: int, random: torch.Generator, name: str) -> Tensor:
    """``wanted`` indices into ``classes`` ``(count,)`` (the int64 class of each candidate), no
    two of one class: uniform draws, each repeat of a class drawn again (the draws are those
    of ``torch.randint`` wherever none repeats)."""
    count, distinct = len(classes), _refuse_more_cells(classes, wanted, name)
    pick = torch.randint(count, (wanted,), generator=random)
    while True:
        seen = torch.zeros(distinct, dtype=torch.bool)
        repeated = torch.zeros(wanted, dtype=torch.bool)
        for position, value in enumerate(classes[pick].tolist()):
            repeated[position] = seen[value]
            seen[value] = True
        if not repeated.any():
            return pick
        pick[repeated] = torch.randint(count, (int(repeated.sum()),), generator=random)


def _dense_order(surface: ImplicitSurface) -> Tensor:
    """Each stored node's flat index in its entry's dense grid, packed ``(N, 8, 8, 8)``."""
    index = surface.layout.node_index().to(surface.phi.device)  # (N, 3, 8, 8, 8), (k, j, i)
    shapes = torch.tensor([g.shape for g in surface.grids], device=index.device)
    height, width = (shapes[surface.layout.batch.to(index.device), axis] for axis in (1, 2))
    view = (-1, 1, 1, 1)
    return (index[:, 0] * height.view(view) + index[:, 1]) * width.view(view) + index[:, 2]


def signal(kind: str, surface: ImplicitSurface, channels: int = 1, seed: int = 0,
           **options: float) -> Tensor:
    """:func:`smooth_signal` (``kind="smooth"``) or :func:`piecewise_constant_signal`
    (``"piecewise_constant"``) with their ``options``; ``(B, C, D, H, W)``."""
    check_choice(kind, "kind", KINDS)
    make = smooth_signal if kind == "smooth" else piecewise_constant_signal
    return make(surface, channels=channels, seed=seed, **options)


KEPT_SURFACES = 4
"""How many batch surfaces :meth:`SignalDataset.surface` keeps, the most recently used."""


_OPTION_CHECKS = {"frequency": check_positive, "modes": check_count, "cells": check_count}
"""How the signal functions check their options; the dataset checks them when it is built, not
at its first item (in a DataLoader's worker)."""


def _signal_options(options: object, name: str, make: object) -> dict:
    """``options`` for ``make`` (a signal function) checked by name: a mapping of its own
    keyword arguments, each value in its range."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise TypeError(f"{name} must be a dict of {make.__name__}'s options, got "
                        f"{type(options).__name__}")
    accepted = set(inspect.signature(make).parameters) - {"surface", "channels", "seed"}
    unknown = set(options) - accepted
    if unknown:
        raise ValueError(f"{name}: {make.__name__} takes {sorted(accepted)}, not "
                         f"{sorted(unknown)}")
    return {key: _OPTION_CHECKS[key](value, f"{name}[{key!r}]") if key in _OPTION_CHECKS
            else value for key, value in options.items()}


class SignalDataset(Dataset):
    """Noisy and clean random signals on a batch of shapes, item by item, deterministic.

    Item ``i`` lies on shape ``i % B``, is of kind ``kinds[(i // B) % len(kinds)]``, and is
    drawn from ``derived_seed(seed, i)``: the same ``(seed, i)`` always gives the same item,
    whatever was drawn before. Noise is Gaussian, independent at every node.

    Args:
        shapes: a :class:`~torchsurf.shape_batch.MeshBatchAdapter` or an
            :class:`~torchsurf.ImplicitSurface` of ``B`` surfaces on one grid.
        length: number of items.
        kinds: signal kinds to cycle through, from :data:`KINDS`.
        channels: ``C``.
        noise: standard deviation of the noise (signals lie in ``[0, 1]``).
        seed: the run's seed, a whole number in ``[0, 2^32)``.
        smooth, piecewise_constant: options of :func:`smooth_signal` and
            :func:`piecewise_constant_signal` (``frequency``, ``modes``; ``cells``).
        kept_surfaces: how many batch surfaces :meth:`surface` keeps, the most recently used
            (default :data:`KEPT_SURFACES`); at least the number of distinct batches a fixed
            order of shapes cycles through, for each to be reused.

    Items are dicts: ``"noisy"`` and ``"clean"`` ``(C, D, H, W)``, ``"shape"`` the shape's
    index (an ``int``), ``"kind"`` the kind. A ``DataLoader`` stacks them into ``(N, C, D, H, W)``;
    :meth:`surface` gives the matching surfaces, :meth:`band_mask` the nodes to score.

    Example:
        >>> import torchsurf as ts
        >>> grid = ts.Grid.cube(17, bound=1.5)
        >>> shapes = ts.ImplicitSurface(ts.sdf.sphere(grid), grid)
        >>> item = SignalDataset(shapes, length=4, seed=1)[3]
        >>> item["noisy"].shape, item["kind"]
        (torch.Size([1, 17, 17, 17]), 'piecewise_constant')
    """

    def __init__(
        self,
        shapes: MeshBatchAdapter | ImplicitSurface,
        length: int,
        kinds: Sequence[str] = KINDS,
        channels: int = 1,
        noise: float = 0.1,
        seed: int = 0,
        smooth: dict | None = None,
        piecewise_constant: dict | None = None,
        kept_surfaces: int = KEPT_SURFACES,
    ) -> None:
        surface = shapes.surface if isinstance(shapes, MeshBatchAdapter) else shapes
        if not isinstance(surface, ImplicitSurface):
            raise TypeError(
                "shapes must be a MeshBatchAdapter or an ImplicitSurface, got "
                f"{type(shapes).__name__}"
            )
        if surface.layout is not None:
            raise TypeError(
                "shapes must hold dense volumes; a BrickSurface (band stored as bricks) is not "
                "supported here: give the dense surface (e.g. the one bricks.from_dense took)"
            )
        if isinstance(kinds, str) or len(kinds) == 0:
            raise ValueError(f"kinds must be a non-empty sequence of {KINDS}, got {kinds!r}")
        self.kinds = tuple(check_choice(kind, "kinds", KINDS) for kind in kinds)
        self.length = check_count(length, "length")
        self.channels = check_count(channels, "channels")
        self.noise = check_nonnegative(noise, "noise")
        self.seed = check_count(seed, "seed", minimum=0)
        self.kept_surfaces = check_count(kept_surfaces, "kept_surfaces")
        derived_seed(self.seed, 0)  # refuses a seed outside [0, 2^32) by name
        self.options = {"smooth": _signal_options(smooth, "smooth", smooth_signal),
                        "piecewise_constant": _signal_options(
                            piecewise_constant, "piecewise_constant", piecewise_constant_signal)}
        self.grid = surface.grid
        self.phi = surface.phi.detach().clone()  # its own: loading the adapter's state copies
        # into the adapter's phi in place, which the surfaces built here must not see
        self._band_width, self._eps = surface.band_width, surface.eps
        self._surfaces = [ImplicitSurface(self.phi[b:b + 1], self.grid, self._band_width,
                                          self._eps) for b in range(surface.batch_size)]
        self._batch_surfaces: dict[tuple[int, ...], ImplicitSurface] = {}
        if "piecewise_constant" in self.kinds:
            cells = self.options["piecewise_constant"].get(
                "cells", inspect.signature(piecewise_constant_signal).parameters["cells"].default)
            _check_cells(surface, cells, "piecewise_constant['cells']")

    def __getstate__(self) -> dict:
        # a DataLoader's worker draws items; the batch surfaces stay with the training loop
        return {**self.__dict__, "_batch_surfaces": {}}

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> dict[str, Tensor | int | str]:
        try:
            if isinstance(index, bool):
                raise TypeError
            index = operator.index(index)
        except TypeError:
            raise TypeError(f"index must be an integer, got {index!r}") from None
        if not -self.length <= index < self.length:
            raise IndexError(f"index {index} out of range for {self.length} items")
        index %= self.length
        shape = index % len(self._surfaces)
        kind = self.kinds[(index // len(self._surfaces)) % len(self.kinds)]
        seed = derived_seed(self.seed, index)
        clean = signal(kind, self._surfaces[shape], self.channels, seed, **self.options[kind])[0]
        noisy = clean + gaussian_noise(clean, self.noise, derived_seed(self.seed, index, 1))
        return {"noisy": noisy, "clean": clean, "shape": shape, "kind": kind}

    def surface(self, shapes: Tensor | Sequence[int]) -> ImplicitSurface:
        """The surfaces of a batch of items, ``shapes`` their ``"shape"`` indices ``(N,)``.

        The same surface object is returned for the same indices while they are among the
        ``kept_surfaces`` most recently asked for: what the layers derive from a surface
        once (its stencils, band Laplacian and band nodes) is kept on it, and a new surface
        derives them again (10x the cost of a ``LearnedDiffusion`` forward and backward at
        32^3). Batches that repeat their shapes (items of one shape, or a fixed order of
        shapes, as ``examples/train_denoise.py`` draws them) reuse their surface while they
        are no more than ``kept_surfaces`` distinct batches: batches of 3 over 5 shapes in
        order cycle through 5, and with the default 4 every one was built again (a training
        step 3.2x slower; an audit, 2026-12-07): pass ``kept_surfaces=5`` there.
        """
        index = self._shape_indices(shapes)
        key = tuple(index.flatten().tolist())
        surface = self._batch_surfaces.pop(key, None)
        if surface is None:
            surface = ImplicitSurface(self.phi[index], self.grid, self._band_width, self._eps)
        self._batch_surfaces[key] = surface  # the most recent last
        while len(self._batch_surfaces) > self.kept_surfaces:
            self._batch_surfaces.pop(next(iter(self._batch_surfaces)))
        return surface

    def band_mask(self, shapes: Tensor | Sequence[int]) -> Tensor:
        """``(N, 1, D, H, W)`` bool, the band of each item's surface (where to score)."""
        index = self._shape_indices(shapes)
        return torch.cat([self._surfaces[int(b)].band_mask() for b in index.cpu()])

    def _shape_indices(self, shapes: Tensor | Sequence[int]) -> Tensor:
        """``shapes`` as a ``(N,)`` long tensor of shape indices in ``[0, B)``; raises naming
        ``shapes`` otherwise (a negative index would pick a shape from the end silently)."""
        try:
            index = torch.as_tensor(shapes, device=self.phi.device)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"shapes must be a sequence or tensor of shape indices, got "
                            f"{shapes!r}") from None
        if index.dim() != 1 or index.is_floating_point() or index.is_complex() or (
                index.dtype == torch.bool) or len(index) == 0:
            raise ValueError(f"shapes must be a non-empty (N,) sequence of integer shape "
                             f"indices, got {shapes!r}")
        count = len(self._surfaces)
        if bool(((index < 0) | (index >= count)).any()):
            raise IndexError(f"shapes must lie in [0, {count}) (the items' \"shape\"), got "
                             f"{index.tolist()}")
        return index.long()
