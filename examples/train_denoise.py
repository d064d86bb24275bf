"""Train a small denoiser built from ``torchsurf.nn`` layers on noisy signals over several shapes.

Signals (smooth and piecewise constant, :mod:`torchsurf.datasets`) are drawn on four training
shapes and one held-out shape, all put on one grid at a normalised size
(:class:`torchsurf.MeshBatchAdapter`), and Gaussian noise is added at every node. A network of
learned diffusions and diffusion blocks (:class:`Denoiser`) is trained with Adam to raise the
signals' mean PSNR over the band, then evaluated on held-out signals on the training shapes and on signals on
the held-out shape against two tuned baselines: the heat flow at the best fixed time and
total-variation flow at the best fixed time, each picked by a sweep on the training signals of
each kind. Writes a table (``results.md``, ``results.csv``), pictures of the held-out shape
(``heldout_*.png``) and the trained weights (``denoiser.pt``) to ``--output``, all written
aside first and renamed into place once every one is ready (a failed run leaves the former
results as they were).

    python examples/train_denoise.py [--output outputs/train_denoise] [--quick]

Times are scale-free: the heat and learned diffusion times are in units of ``h^2`` (the squared
grid spacing, docs/learning.md), the total-variation times in units of ``h`` (total variation
moves a unit jump by about one cell per unit of that time). docs/learning.md ("Training a
denoiser") has the default run's table and what it shows.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import io
import math
import os
import signal
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor, nn

import torchsurf as ts
from torchsurf import render
from torchsurf.datasets import DERIVED_SEED_LIMIT, KINDS, SignalDataset, derived_seed

SWEEP_CHUNKS = 4
"""Chunks of training signals the baselines' times are picked on (16 signals per kind with
the four default shapes)."""
MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off")
HEAT_TIMES = (0.1, 0.2, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0)
"""Heat times swept for the baseline, ``h^2`` units."""
TV_TIMES = (0.012, 0.025, 0.05, 0.1, 0.2)
"""Total-variation times swept for the baseline, ``h`` units (data in ``[0, 1]``)."""
TV_EPS = 0.05
"""Regularisation of ``|grad_S u|`` in total variation, units of the data per cell."""
METHODS = ("noisy", "heat", "total variation", "learned")
SETS = ("held-out signals", "held-out shape")
Method = Callable[[Tensor, ts.ImplicitSurface], Tensor]
"""A denoiser: noisy ``(B, 1, D, H, W)`` and its surface -> ``(B, 1, D, H, W)``."""


def training_shapes() -> list[ts.AnalyticShape | trimesh.Trimesh]:
    """The default training shapes: sphere, box, capsule and an ellipsoid (a mesh made in
    code, so that no file is needed), in their own units."""
    ellipsoid = trimesh.creation.icosphere(subdivisions=4)
    ellipsoid.apply_scale((1.0, 0.7, 0.45))
    return [
        ts.AnalyticShape("sphere"),
        ts.AnalyticShape("box", {"half_size": (0.5, 0.4, 0.3)}),
        ts.AnalyticShape("capsule"),
        ellipsoid,
    ]


def heldout_shape() -> ts.AnalyticShape:
    """The default held-out shape: a torus (genus one, saddles), which no training shape has."""
    return ts.AnalyticShape("torus", {"major_radius": 1.0, "minor_radius": 0.5})


@contextlib.contextmanager
def eager_stencils(eager: bool) -> Iterator[None]:
    """Within the block, keep every stencil eager when ``eager`` (no ``torch.compile``).

    ``path="auto"`` (:mod:`torchsurf.backend`) compiles a kernel once a call's volume reaches
    ``COMPILE_MIN_VOXELS`` voxels or its eager time ``COMPILE_PAYBACK_SECONDS``. The default
    run earns that back (a training iteration at 32^3 costs 2.5x less compiled), a
    ``--quick`` run of seconds does not: the closest-point re-extension inside every diffusion
    alone compiles five variants (limited or not, first batch entry or not), seconds each.
    Both thresholds are raised to infinity and restored on exit.
    """
    saved = ts.backend.COMPILE_MIN_VOXELS, ts.backend.COMPILE_PAYBACK_SECONDS
    if eager:
        ts.backend.COMPILE_MIN_VOXELS, ts.backend.COMPILE_PAYBACK_SECONDS = math.inf, math.inf
    try:
        yield
    finally:
        ts.backend.COMPILE_MIN_VOXELS, ts.backend.COMPILE_PAYBACK_SECONDS = saved


def mesh_paths(names: Sequence[str], directory: str | None, flag: str = "--meshes"
               ) -> list[Path]:
    """``names`` resolved against ``directory`` (``--mesh-dir``); absolute paths as given.

    Raises:
        FileNotFoundError: a name that is no mesh file, naming ``flag`` (the option that gave
            it) and the path tried.
    """
    paths = []
    for name in names:
        path = Path(name)
        if not path.is_absolute():
            if directory is None:
                raise FileNotFoundError(
                    f"{flag} {name!r}: a relative name needs --mesh-dir or $TORCHSURF_MESH_DIR"
                )
            path = Path(directory) / path
        if not path.is_file() or path.suffix.lower() not in MESH_SUFFIXES:
            raise FileNotFoundError(f"{flag} {name!r}: no mesh file {str(path)!r} "
                                    f"(one of {', '.join(MESH_SUFFIXES)})")
        paths.append(path)
    return paths


@dataclass
class SignalSet:
    """Noisy and clean signals on a batch of shapes, grouped in chunks of one fixed layout.

    Chunk ``k`` holds items ``k * size .. (k + 1) * size - 1`` of a :class:`SignalDataset`,
    whose shapes repeat as ``0, 1, ..., S - 1`` and whose kinds alternate every ``S`` items,
    so that every chunk lies on the same ``surface`` (the shapes' ``phi`` repeated): the
    stencils and spectral bound built for it are reused for every chunk.

    Attributes:
        noisy, clean: ``(N, 1, D, H, W)``, data in ``[0, 1]`` plus noise.
        kinds: ``(N,)`` the kind of each item, from :data:`torchsurf.datasets.KINDS`.
        surface: the surface of one chunk, batch ``size``.
        size: items per chunk.
    """

    noisy: Tensor
    clean: Tensor
    kinds: list[str]
    surface: ts.ImplicitSurface
    size: int

    @classmethod
    def draw(cls, phi: Tensor, grid: ts.Grid, rounds: int, repeats: int, noise: float, seed: int,
             cells: int, frequency: float) -> SignalSet:
        """``rounds * 2 * S`` signals on the ``S`` shapes of ``phi`` ``(S, 1, D, H, W)``: one
        smooth and one piecewise-constant signal per shape and round; chunks of ``repeats``
        rounds."""
        shapes = phi.shape[0]
        dataset = SignalDataset(ts.ImplicitSurface(phi, grid), length=rounds * 2 * shapes,
                                noise=noise, seed=seed, smooth={"frequency": frequency},
                                piecewise_constant={"cells": cells})
        items = [dataset[i] for i in range(len(dataset))]
        noisy = torch.stack([item["noisy"] for item in items])
        clean = torch.stack([item["clean"] for item in items])
        size = 2 * shapes * repeats
        surface = ts.ImplicitSurface(phi.repeat(2 * repeats, 1, 1, 1, 1), grid)
        return cls(noisy, clean, [item["kind"] for item in items], surface, size)

    def __len__(self) -> int:
        return len(self.kinds) // self.size

    def first(self, chunks: int) -> SignalSet:
        """The first ``chunks`` chunks (all of them if there are fewer)."""
        end = min(chunks, len(self)) * self.size
        return SignalSet(self.noisy[:end], self.clean[:end], self.kinds[:end], self.surface,
                         self.size)

    def chunk(self, k: int) -> tuple[Tensor, Tensor]:
        """Noisy and clean signals of chunk ``k``, ``(size, 1, D, H, W)`` each."""
        part = slice(k * self.size, (k + 1) * self.size)
        return self.noisy[part], self.clean[part]

    def mask(self, kind: str) -> Tensor:
        """``(N,)`` bool: the items of ``kind``."""
        return torch.tensor([k == kind for k in self.kinds])

    def psnr(self, methods: dict[str, Method]) -> Tensor:
        """PSNR (dB) over the band of every item, ``(N,)``, each item denoised by the method
        of its kind (``methods[kind](noisy, surface)``; a method shared by the kinds runs once
        per chunk)."""
        scores = []
        for k in range(len(self)):
            noisy, clean = self.chunk(k)
            kinds = self.kinds[k * self.size:(k + 1) * self.size]
            outputs: dict[int, Tensor] = {}
            with torch.no_grad():
                for kind in set(kinds):
                    method = methods[kind]
                    if id(method) not in outputs:
                        outputs[id(method)] = ts.nn.psnr(method(noisy, self.surface), clean,
                                                         self.surface)
            scores.append(torch.stack([outputs[id(methods[kind])][b]
                                       for b, kind in enumerate(kinds)]))
        return torch.cat(scores)


class Denoiser(nn.Module):
    """Noisy scalar data on the band -> denoised data, from ``torchsurf.nn`` layers.

    ``u`` is copied into ``channels`` channels diffused for their own learned times
    (:class:`torchsurf.nn.LearnedDiffusion`, spread from ``0.1`` to ``3`` ``h^2``), passed
    through ``blocks`` :class:`torchsurf.nn.DiffusionBlock`, and read out by a linear map plus
    a pointwise MLP on the band's nodes that also sees ``u`` itself (the node's own noisy value,
    which every diffusion replaces by a re-extension from S). The head's last layer starts at
    zero and the linear readout on the channel diffused for about ``start`` ``h^2``: the
    untrained model is the heat flow for that time.

    Args:
        channels: ``C``, channels of the diffusions and blocks (at least 2).
        blocks: number of :class:`~torchsurf.nn.DiffusionBlock`.
        hidden: width of the blocks' and the head's hidden layers.
        start: the diffusion time, ``h^2`` units, the readout starts from.

    Shapes: ``u`` ``(B, 1, D, H, W)`` on a surface of batch 1 or ``B`` -> ``(B, 1, D, H, W)``;
    values outside the band are those of the readout (not meaningful).
    """

    def __init__(self, channels: int = 4, blocks: int = 1, hidden: int = 32,
                 start: float = 0.35) -> None:
        super().__init__()
        if channels < 2:
            raise ValueError(f"channels must be at least 2, got {channels}")
        if blocks < 0:
            raise ValueError(f"blocks must be non-negative, got {blocks}")
        times = np.geomspace(0.1, 3.0, channels)
        self.lift = ts.nn.LearnedDiffusion(channels, time=times.tolist())
        self.blocks = nn.ModuleList([
            ts.nn.DiffusionBlock(channels, hidden, time=np.geomspace(0.1, 1.0, channels).tolist())
            for _ in range(blocks)
        ])
        self.readout = nn.Linear(channels, 1)
        self.head = nn.Sequential(nn.Linear(channels + 1, hidden), nn.ReLU(), nn.Linear(hidden, 1))
        with torch.no_grad():
            self.readout.weight.zero_()
            self.readout.bias.zero_()
            self.readout.weight[0, int(np.abs(np.log(times / start)).argmin())] = 1.0
            self.head[-1].weight.zero_()
            self.head[-1].bias.zero_()

    def forward(self, u: Tensor, surface: ts.ImplicitSurface) -> Tensor:
        if u.dim() != 5 or u.shape[1] != 1:
            raise ValueError(f"u must have shape (B, 1, D, H, W), got {tuple(u.shape)}")
        v = self.lift(u.expand(-1, self.lift.channels, -1, -1, -1), surface)
        for block in self.blocks:
            v = block(v, surface)
        out = self.readout(v.movedim(1, -1))  # (B, D, H, W, 1)
        band = surface.band_mask().expand(u.shape[0], 1, *u.shape[2:])[:, 0]
        nodes = torch.cat([v, u], dim=1).movedim(1, -1)[band]  # (N, C + 1)
        update = out.new_zeros(out.shape).masked_scatter(band[..., None], self.head(nodes))
        return (out + update).movedim(-1, 1)


def heat(time: float, spacing: float) -> ts.HeatFlow:
    """The heat flow for ``time`` ``h^2`` (Chebyshev semigroup, :class:`torchsurf.HeatFlow`),
    on a grid of spacing ``h`` (world units)."""
    return ts.HeatFlow(time * spacing**2, method="chebyshev")


def total_variation(time: float, spacing: float) -> ts.AnisotropicFlow:
    """Total-variation flow for ``time`` ``h`` units (:class:`torchsurf.AnisotropicFlow`), on a
    grid of spacing ``h`` (world units), ``|grad_S u|`` regularised by :data:`TV_EPS`."""
    return ts.AnisotropicFlow(time * spacing, "total_variation", eps=TV_EPS / spacing)


def sweep(data: SignalSet, flow: nn.Module, times: Sequence[float], scale: float
          ) -> dict[str, tuple[float, float]]:
    """The best of ``times`` for each kind by mean PSNR over ``data``.

    ``flow`` is integrated once per chunk to ``times[-1] * scale`` and read at every time
    (``times=``). Returns ``{kind: (best time, its mean PSNR in dB)}``.
    """
    scores = []
    for k in range(len(data)):
        noisy, clean = data.chunk(k)
        with torch.no_grad():
            outputs = flow(noisy, data.surface, times=[t * scale for t in times])
        scores.append(torch.stack([ts.nn.psnr(o, clean, data.surface) for o in outputs]))
    scores = torch.cat(scores, dim=1)  # (times, N)
    best = {}
    for kind in KINDS:
        mean = scores[:, data.mask(kind)].mean(dim=1)
        i = int(mean.argmax())
        best[kind] = (float(times[i]), float(mean[i]))
    return best


def train(model: Denoiser, data: SignalSet, iterations: int, lr: float, seed: int,
          report_every: int) -> list[float]:
    """Adam on the mean PSNR over the band (minus it, dB), one random chunk per iteration, the
    learning rate decayed to zero by a cosine. Returns the mean PSNR of every iteration.

    The mean of the signals' PSNR, rather than the mean squared error of the batch, gives each
    signal the same weight whatever its error: piecewise-constant signals, whose errors are
    five times larger, would otherwise decide the training alone."""
    optimiser = torch.optim.Adam(model.parameters(), lr=lr)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, max(iterations, 1))
    order = torch.Generator().manual_seed(derived_seed(seed, 3))
    scores = []
    start = time.perf_counter()
    for iteration in range(iterations):
        k = int(torch.randint(len(data), (1,), generator=order))
        noisy, clean = data.chunk(k)
        score = ts.nn.psnr(model(noisy, data.surface), clean, data.surface).mean()
        optimiser.zero_grad()
        (-score).backward()
        optimiser.step()
        schedule.step()
        scores.append(float(score.detach()))
        if (iteration + 1) % report_every == 0 or iteration + 1 == iterations:
            print(f"  iteration {iteration + 1}/{iterations}: mean PSNR "
                  f"{np.mean(scores[-report_every:]):.2f} dB, {time.perf_counter() - start:.0f} s",
                  flush=True)
    return scores


@contextlib.contextmanager
def staged_outputs(output: Path) -> Iterator[Path]:
    """A hidden folder in ``output`` to write every result into; when the block ends, each
    file is renamed into ``output`` (one after the other, after all are written), so that a
    run that fails or is stopped before then leaves the former results as they were, not a
    mix of new and old; a failure removes the folder."""
    output.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=output, prefix=".staged."))
    try:
        yield staging
        for path in sorted(staging.iterdir()):
            os.chmod(path, render.FILE_MODE)
            os.replace(path, output / path.name)
    finally:
        for path in staging.iterdir():
            path.unlink()
        staging.rmdir()


def tables(scores: dict[tuple[str, str, str], float],
           chosen: dict[str, dict[str, tuple[float, float]]]) -> tuple[str, str]:
    """The Markdown and CSV tables of ``scores`` (mean PSNR in dB per method, set and kind);
    ``chosen`` names each baseline's time per kind (:func:`sweep`)."""
    columns = [(s, k) for s in SETS for k in KINDS]
    lines = [
        "| method | " + " | ".join(f"{s}, {k.replace('_', '-')}" for s, k in columns) + " |",
        "|---|" + "---|" * len(columns),
    ]
    units = {"heat": " h^2", "total variation": " h"}  # the sweeps' units
    for method in METHODS:
        label = method
        if method in chosen:
            label += " (" + ", ".join(
                f"{k.split('_')[0]} t = {chosen[method][k][0]:g}{units.get(method, '')}"
                for k in KINDS) + ")"
        lines.append(f"| {label} | " + " | ".join(f"{scores[method, s, k]:.2f}"
                                                 for s, k in columns) + " |")
    lines.append("| learned - heat | " + " | ".join(
        f"{scores['learned', s, k] - scores['heat', s, k]:+.2f}" for s, k in columns) + " |")
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["method", "set", "kind", "psnr_db"])
    for method in METHODS:
        for s, k in columns:
            writer.writerow([method, s, k, f"{scores[method, s, k]:.4f}"])
    return "\n".join(lines) + "\n", buffer.getvalue()


def pictures(data: SignalSet, grid: ts.Grid, methods: dict[str, dict[str, Method]],
             output: Path, width: int) -> list[Path]:
    """One PNG per kind, ``heldout_<kind>.png``: the first item of that kind in ``data`` on
    its surface, clean, noisy and denoised by each of ``methods`` (``{name: {kind: method}}``),
    coloured on ``[0, 1]``, each panel's PSNR (dB) in its title.

    The methods run on the whole first chunk, on the surface they were run on before: a
    surface of another batch size would build its stencils and compile its kernels again."""
    noisy, clean = data.chunk(0)
    written = []
    for kind in KINDS:
        b = data.kinds.index(kind)
        mesh = ts.mesh.extract(data.surface.phi[b:b + 1], grid)
        volumes = {"clean": clean}
        with torch.no_grad():
            for name, by_kind in methods.items():
                volumes[name] = by_kind[kind](noisy, data.surface)
        panels = []
        for name, volume in volumes.items():
            title = name
            if name != "clean":
                title += f" {float(ts.nn.psnr(volume, clean, data.surface)[b]):.1f} dB"
            values = render.vertex_values(volume[b:b + 1], mesh, grid)
            panels.append((title, render.colours(values, limits=(0.0, 1.0))))
        written.append(render.render_panels(mesh, panels, output / f"heldout_{kind}.png",
                                            width=width, height=3 * width // 4,
                                            elevation=40.0))
    return written


def unwritable_folder(output: Path) -> str | None:
    """Why the results could not be written into the folder ``output`` (created with its
    parents if missing), or ``None`` when they can: its first existing folder must take a new
    folder (tried and removed; permission bits alone pass root on /proc)."""
    for folder in (output, *output.absolute().parents):
        if folder.exists():
            if not folder.is_dir():
                return f"{folder} is not a folder"
            try:
                os.rmdir(tempfile.mkdtemp(prefix=".train_denoise-", dir=folder))
            except OSError as error:
                return f"cannot make a folder in {folder} ({error.strerror or error})"
            return None
    return None


def parse(argv: Sequence[str] | None = None) -> argparse.Namespace:
    # no abbreviations: --quick keeps the options given beside it by their full names
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0].replace("`", ""),
                                     allow_abbrev=False,
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--output", type=Path, default=Path("outputs/train_denoise"),
                        help="folder for results.md, results.csv, the pictures and the weights")
    parser.add_argument("--resolution", type=int, default=32,
                        help="grid nodes per axis (at least 16: a band of 3 cells per shape)")
    parser.add_argument("--channels", type=int, default=4, help="channels of the network")
    parser.add_argument("--blocks", type=int, default=1, help="DiffusionBlocks in the network")
    parser.add_argument("--hidden", type=int, default=32, help="hidden width of the MLPs")
    parser.add_argument("--iterations", type=int, default=100, help="Adam iterations")
    parser.add_argument("--lr", type=float, default=5e-3, help="Adam's initial learning rate")
    parser.add_argument("--train-rounds", type=int, default=16,
                        help="training signals per shape and kind")
    parser.add_argument("--test-rounds", type=int, default=4,
                        help="held-out signals per training shape and kind (the held-out shape "
                             "gets as many as all training shapes together)")
    parser.add_argument("--noise", type=float, default=0.1,
                        help="standard deviation of the noise (signals lie in [0, 1])")
    parser.add_argument("--cells", type=int, default=12, help="regions of a piecewise-constant signal")
    parser.add_argument("--frequency", type=float, default=2.0,
                        help="highest frequency of a smooth signal, periods per shape size")
    parser.add_argument("--seed", type=int, default=0,
                        help="seed of the signals, the noise and the initial weights")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (None: torch's)")
    parser.add_argument("--mesh-dir", default=os.environ.get("TORCHSURF_MESH_DIR"),
                        help="folder of --meshes and --heldout-mesh ($TORCHSURF_MESH_DIR if "
                             "set)")
    parser.add_argument("--meshes", nargs="*", default=[],
                        help="mesh files added to the training shapes")
    parser.add_argument("--heldout-mesh", default=None,
                        help="a mesh file to hold out instead of the torus")
    parser.add_argument("--picture-size", type=int, default=320, help="pixels of one panel")
    parser.add_argument("--eager", action="store_true",
                        help="never compile the stencils (torchsurf.backend's thresholds raised)")
    parser.add_argument("--quick", action="store_true",
                        help="a tiny smoke run (seconds): small grid, network and data")
    args = parser.parse_args(argv)
    if args.quick:  # the options given beside --quick stand
        given = {word.split("=")[0] for word in (sys.argv[1:] if argv is None else argv)}
        quick = {"resolution": 24, "channels": 2, "blocks": 1, "hidden": 8, "iterations": 2,
                 "train_rounds": 1, "test_rounds": 1, "picture_size": 120}
        for name, value in quick.items():
            if "--" + name.replace("_", "-") not in given:
                setattr(args, name, value)
        args.eager = True
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads must be an integer of at least 1, got {args.threads}")
    unwritable = unwritable_folder(args.output)
    if unwritable is not None:  # found now, not after the run's minutes of work
        parser.error(f"--output {args.output}: {unwritable}")

    def resolved(name: str) -> Path:
        return (Path(args.mesh_dir or ".") / name).resolve()

    if args.heldout_mesh is not None and any(
            resolved(args.heldout_mesh) == resolved(mesh) for mesh in args.meshes):
        parser.error(f"--heldout-mesh {args.heldout_mesh} is also among --meshes: the held-out "
                     "shape must not be trained on")
    for name, least in (("resolution", 16), ("channels", 2), ("blocks", 0), ("hidden", 1),
                        ("iterations", 1), ("train_rounds", 1), ("test_rounds", 1), ("cells", 1),
                        ("picture_size", 16)):
        if getattr(args, name) < least:
            parser.error(f"--{name.replace('_', '-')} must be an integer of at least {least}, "
                         f"got {getattr(args, name)}")
    for name in ("lr", "noise", "frequency"):
        finfo = torch.finfo(torch.float32)
        if not finfo.tiny <= getattr(args, name) <= finfo.max:
            parser.error(f"--{name} must be a positive number float32 holds, got "
                         f"{getattr(args, name)}")
    if not 0 <= args.seed < DERIVED_SEED_LIMIT:
        parser.error(f"--seed must be an integer in [0, 2**32), got {args.seed}")
    try:
        mesh_paths(args.meshes, args.mesh_dir)
        if args.heldout_mesh is not None:
            mesh_paths([args.heldout_mesh], args.mesh_dir, "--heldout-mesh")
    except FileNotFoundError as error:
        parser.error(str(error))
    return args


def main(argv: Sequence[str] | None = None) -> dict[tuple[str, str, str], float]:
    """Run the example with the command-line arguments ``argv`` (default ``sys.argv``);
    returns the table's scores ``{(method, set, kind): mean PSNR in dB}``."""
    args = parse(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    with eager_stencils(args.eager):
        return run(args)


def run(args: argparse.Namespace) -> dict[tuple[str, str, str], float]:
    """Data, baselines, training, evaluation, table and pictures (:func:`main`)."""
    begin = time.perf_counter()
    shapes = training_shapes()
    shapes += [ts.mesh.load(path) for path in mesh_paths(args.meshes, args.mesh_dir)]
    held = (ts.mesh.load(mesh_paths([args.heldout_mesh], args.mesh_dir, "--heldout-mesh")[0])
            if args.heldout_mesh else heldout_shape())
    print(f"shapes: {len(shapes)} for training and 1 held out on a {args.resolution}^3 grid",
          flush=True)
    batch = ts.MeshBatchAdapter([*shapes, held], resolution=args.resolution)
    grid, spacing = batch.grid, batch.grid.spacing
    train_phi, held_phi = batch.phi[:-1], batch.phi[-1:]
    options = {"noise": args.noise, "cells": args.cells, "frequency": args.frequency}
    try:
        training = SignalSet.draw(train_phi, grid, args.train_rounds, 1,
                                  seed=derived_seed(args.seed, 0), **options)
        held_signals = SignalSet.draw(train_phi, grid, args.test_rounds, 1,
                                      seed=derived_seed(args.seed, 1), **options)
        held_shape = SignalSet.draw(held_phi, grid, args.test_rounds * len(shapes), len(shapes),
                                    seed=derived_seed(args.seed, 2), **options)
    except ValueError as error:
        if "['cells']" not in str(error):
            raise
        raise SystemExit(f"error: --cells {args.cells} is too many at --resolution "
                         f"{args.resolution}: {error}") from None
    print(f"signals: {len(training.kinds)} training, {len(held_signals.kinds)} held out on the "
          f"training shapes, {len(held_shape.kinds)} on the held-out shape "
          f"({time.perf_counter() - begin:.0f} s)", flush=True)

    sweep_data = training.first(SWEEP_CHUNKS)
    heat_best = sweep(sweep_data, heat(max(HEAT_TIMES), spacing), HEAT_TIMES, spacing**2)
    tv_best = sweep(sweep_data, total_variation(max(TV_TIMES), spacing), TV_TIMES, spacing)
    for name, best in (("heat (h^2)", heat_best), ("total variation (h)", tv_best)):
        print(f"best {name} times on training signals: " + ", ".join(
            f"{kind} {t:g} ({p:.2f} dB)" for kind, (t, p) in best.items())
            + f" ({time.perf_counter() - begin:.0f} s)", flush=True)

    model = Denoiser(args.channels, args.blocks, args.hidden)
    print(f"training {sum(p.numel() for p in model.parameters())} parameters, "
          f"{args.iterations} iterations of {training.size} signals", flush=True)
    train(model, training, args.iterations, args.lr, args.seed,
          report_every=max(1, args.iterations // 10))
    model.eval()
    print("learned times (h^2): lift " + ", ".join(f"{t:.3g}" for t in model.lift.time.tolist()),
          flush=True)

    methods: dict[str, dict[str, Method]] = {
        "noisy": dict.fromkeys(KINDS, lambda u, surface: u),
        "heat": {kind: heat(heat_best[kind][0], spacing) for kind in KINDS},
        "total variation": {kind: total_variation(tv_best[kind][0], spacing) for kind in KINDS},
        "learned": dict.fromkeys(KINDS, model),
    }
    scores: dict[tuple[str, str, str], float] = {}
    for set_name, data in zip(SETS, (held_signals, held_shape), strict=True):
        for method in METHODS:
            values = data.psnr(methods[method])
            for kind in KINDS:
                scores[method, set_name, kind] = float(values[data.mask(kind)].mean())
        print(f"evaluated on the {set_name} ({time.perf_counter() - begin:.0f} s)", flush=True)
    elapsed = time.perf_counter() - begin
    markdown, table = tables(scores, {"heat": heat_best, "total variation": tv_best})
    print(markdown, flush=True)
    output = args.output
    header = (
        "# Denoising on implicit surfaces: learned against heat and total variation\n\n"
        f"Mean PSNR (dB) over the band, noise {args.noise:g}, grid {args.resolution}^3, "
        f"{len(shapes)} training shapes, {args.iterations} iterations, seed {args.seed}; "
        "heat times in h^2, total-variation times in h, each the best on the training signals "
        f"of its kind. {elapsed:.0f} s to this table, {torch.get_num_threads()} thread(s).\n\n"
    )
    with staged_outputs(output) as staging:
        (staging / "results.md").write_text(header + markdown)
        (staging / "results.csv").write_text(table)
        torch.save(model.state_dict(), staging / "denoiser.pt")
        drawn = pictures(held_shape, grid, methods, staging, args.picture_size)
    for path in drawn:
        print(f"written {output / path.name}", flush=True)
    print(f"written {output / 'results.md'}, {output / 'results.csv'}, {output / 'denoiser.pt'} "
          f"({time.perf_counter() - begin:.0f} s in all)", flush=True)
    return scores


def _exit_on_terminate(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


if __name__ == "__main__":
    # SIGTERM (kill, a job scheduler) ends the run through staged_outputs' cleanup, as Ctrl-C
    # does: by default it left the hidden staging folder behind
    signal.signal(signal.SIGTERM, _exit_on_terminate)
    main()
