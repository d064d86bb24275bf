"""Run one experiment config (:mod:`torchsurf.config`): surface, signal, flow, pictures, record.

:func:`prepare` does everything that can fail on the config alone (mesh path, shape
parameters) before any computation; :func:`run` then builds the surface, puts the signal on
it, runs the flow, and writes ``<name>.png`` (the panels side by side) and ``<name>.json``
(the config as resolved, the flow's settings as run, the physical values the scale-free
settings became, stage times, versions) into the output folder.
"""

from __future__ import annotations

import inspect
import json
import math
import os
import platform
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh
from torch import Tensor

from . import bricks, flows, render, sdf, signals
from . import config as cfg
from . import mesh as meshes
from ._mesh_sdf import boundary_edges
from ._signals import signals_held
from .bricks.layout import bricks_along
from .config import (
    ConfigError,
    Experiment,
    FlowKind,
    Layout,
    Shape,
    SignalKind,
    TimeUnit,
    signal_setting,
)
from .grid import Grid
from .surface import ImplicitSurface

SHAPES: dict[Shape, Callable[..., Tensor]] = {
    Shape.sphere: sdf.sphere, Shape.torus: sdf.torus, Shape.trefoil: sdf.trefoil,
    Shape.box: sdf.box, Shape.capsule: sdf.capsule,
}
_NOT_PARAMS = ("grid", "dtype", "device")

FLOW_ORDER = {FlowKind.heat: 2.0, FlowKind.perona_malik: 2.0, FlowKind.visualization: 2.0,
              FlowKind.total_variation: 1.0, FlowKind.color: 1.0}
"""``q`` of the time unit ``L^q`` (harmonic maps: ``p``): how the flow's time scales with size."""


@dataclass
class Prepared:
    """A checked experiment, ready to run: the config, its shape's parameters, the mesh file."""

    experiment: Experiment
    folder: Path
    params: dict[str, Any]
    mesh_path: Path | None
    mesh: trimesh.Trimesh | None = None
    """The mesh file, read (and checked) by :func:`prepare`."""


@dataclass
class Result:
    """What a run wrote and measured; ``flow`` the flow's settings as run
    (:func:`flow_as_run`)."""

    picture: Path
    record: Path
    stages: dict[str, float]
    physical: dict[str, float]
    metrics: dict[str, float] = field(default_factory=dict)
    flow: dict[str, Any] = field(default_factory=dict)


def _shape_params(shape: Shape, params: dict[str, Any]) -> dict[str, Any]:
    """The sdf function's keyword arguments with the config's ``params`` checked against them."""
    signature = inspect.signature(SHAPES[shape])
    accepted = {name: p.default for name, p in signature.parameters.items()
                if name not in _NOT_PARAMS and p.default is not inspect.Parameter.empty}
    for key, value in params.items():
        if key not in accepted:
            raise ConfigError(f"surface.params.{key}", f"not a parameter of shape: {shape.name} "
                              f"(its parameters: {', '.join(accepted)})")
        default = accepted[key]
        if isinstance(default, tuple) and (not isinstance(value, (list, tuple))
                                            or len(value) != len(default)):
            raise ConfigError(f"surface.params.{key}", f"must be a list of {len(default)} "
                              f"numbers, got {value!r}")
        if isinstance(default, (int, float)) and not isinstance(value, (int, float)):
            raise ConfigError(f"surface.params.{key}", f"must be a number, got {value!r}")
    merged = {**accepted, **params}
    return {k: tuple(v) if isinstance(v, list) else v for k, v in merged.items()}


def prepare(config: str | os.PathLike, overrides: list[str] | None = None) -> Prepared:
    """Load and check a config and everything it names, without computing anything.

    Raises:
        ConfigError: naming the key at fault.
    """
    experiment, folder = cfg.load(config, overrides)
    surface = experiment.surface
    mesh_path, mesh, params = None, None, {}
    if surface.shape is Shape.mesh:
        if surface.params:
            raise ConfigError("surface.params", "a mesh takes no shape parameters")
        mesh_path = cfg.resolve_mesh(surface.mesh, folder)
        try:  # read now, so that a file that is no mesh fails before any work
            mesh = meshes.load(str(mesh_path))
        except (TypeError, ValueError) as error:
            raise ConfigError("surface.mesh", f"{str(mesh_path)!r} cannot be read as a mesh: "
                              f"{error}") from None
    else:
        params = _shape_params(surface.shape, dict(surface.params))
        try:  # the shape's own checks, on a grid of 27 nodes: before any real work
            SHAPES[surface.shape](Grid((3, 3, 3), 1.0), dtype=torch.float64, **params)
        except (TypeError, ValueError) as error:
            raise ConfigError("surface.params", str(error)) from None
        _check_extent(surface.shape, params)
    image_name = signal_setting(experiment.signal, "image")
    if experiment.signal.kind is SignalKind.image and image_name not in signals.IMAGES:
        image = Path(image_name).expanduser()
        image = image if image.is_absolute() else folder / image
        if not image.is_file():
            first = ("" if Path(image_name).expanduser().is_absolute() else
                     "; a relative path is looked for in the folder of the config that names "
                     f"it; one given with --set first in the current folder, {Path.cwd()}")
            raise ConfigError("signal.image", f"neither a built-in image "
                              f"({', '.join(signals.IMAGES)}) nor a file: {str(image)!r}"
                              f"{first}")
        try:  # read now, so that a file that is no image fails before any work
            channels = signals.load_image(image).shape[0]
        except Exception as error:  # noqa: BLE001 (scikit-image raises its readers' errors)
            raise ConfigError("signal.image", f"{str(image)!r} cannot be read as an image: "
                              f"{type(error).__name__}: {error}") from None
        if experiment.flow.kind is cfg.FlowKind.color and channels < 3:
            raise ConfigError("signal.image", f"flow.kind=color needs a colour image; "
                              f"{str(image)!r} has one channel")
    if experiment.render.renderer is cfg.Renderer.pyvista:
        try:
            render.resolve_renderer("pyvista")
        except ImportError as error:
            raise ConfigError("render.renderer", str(error)) from error
    prepared = Prepared(experiment, folder, params, mesh_path, mesh)
    _check_physical_time(prepared)
    return prepared


TIME_MARGIN = 1e3
"""How far inside float32's range (its smallest normal number to its largest) a flow's
physical time must lie when estimated from the shape's bounding box before any work (the
diagonal and spacing measured later differ from the estimate by less than this)."""


def _check_physical_time(prepared: Prepared) -> None:
    """Raise :class:`ConfigError` naming ``flow.time`` when its physical value, estimated from
    the shape's bounding box, would round to 0 or overflow in float32 (the flow refused it
    only after the surface was built, naming the physical value)."""
    experiment = prepared.experiment
    low, high = _shape_box(prepared)
    extent = high - low
    spacing = (float(extent.max()) * (1.0 + 2.0 * experiment.grid.margin)
               / (experiment.grid.size - 1))
    settings = physical_settings(experiment, float(np.linalg.norm(extent)), spacing)
    limits = torch.finfo(torch.float32)
    for name in [name for name in ("time", "chroma_time") if name in settings]:
        physical = settings[name]
        if not TIME_MARGIN * limits.tiny <= physical <= limits.max / TIME_MARGIN:
            unit = cfg.time_unit(experiment.flow).name
            what = "" if name == "time" else " for the chroma (in L^p)"
            raise ConfigError("flow.time", f"{experiment.flow.time:g} ({unit}) is about "
                              f"{physical:.3g} in world units{what} on this shape, outside "
                              f"what float32 grids hold ({TIME_MARGIN * limits.tiny:.0e} to "
                              f"{limits.max / TIME_MARGIN:.0e})")


SHAPE_EXTENT = (1e-6, 1e6)
"""Sizes (world units) a built-in shape's bounding box may span: the grid is fitted to it, and
float32 spacings and their squares (the operators divide by ``h^2``) stay far from float32's
limits only within this range (the flows are measured scale-free there, docs/cli.md)."""


def _check_extent(shape: Shape, params: dict[str, Any]) -> None:
    """Raise :class:`ConfigError` naming ``surface.params`` for a shape too small or too large
    for float32 grids (a radius of 1e-20 failed in the flow, 1e300 in the distances)."""
    low, high = _builtin_box(shape, params)
    extent = float(np.max(high - low))
    centre = float(np.abs(0.5 * (low + high)).max())
    smallest, largest = SHAPE_EXTENT
    if not (smallest <= extent <= largest) or centre > largest:
        raise ConfigError("surface.params", f"the {shape.value} spans {extent:g} world units "
                          f"around a centre {centre:g} from the origin; built-in shapes must span "
                          f"{smallest:g} to {largest:g} and lie within {largest:g} of the origin "
                          "(float32 grids)")


def _builtin_box(shape: Shape, p: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box ``(low, high)`` of a built-in shape with parameters ``p``."""
    if shape is Shape.capsule:
        ends = np.array([p["start"], p["end"]], dtype=np.float64)
        return ends.min(axis=0) - p["radius"], ends.max(axis=0) + p["radius"]
    half = {
        Shape.sphere: lambda: np.full(3, p["radius"]),
        Shape.torus: lambda: np.array([p["major_radius"] + p["minor_radius"]] * 2
                                      + [p["minor_radius"]]),
        Shape.trefoil: lambda: np.array([3 * p["scale"] + p["tube_radius"]] * 2
                                        + [p["scale"] + p["tube_radius"]]),
        Shape.box: lambda: np.asarray(p["half_size"], dtype=np.float64),
    }[shape]()
    centre = np.asarray(p["center"], dtype=np.float64)
    return centre - half, centre + half


def frame_centre(prepared: Prepared) -> np.ndarray:
    """The world point ``(3,)`` float64 the run computes about: the centre of the shape's
    bounding box (a built-in's from its parameters, a mesh's from its vertices). The surface is
    built in a frame centred there, so that float32 grids keep their cells wherever the shape
    lies (a sphere of radius 1e-3 at x = 5e5 lost its checkerboard in float32 world points)."""
    low, high = _shape_box(prepared)
    return 0.5 * (low + high)


def _shape_box(prepared: Prepared) -> tuple[np.ndarray, np.ndarray]:
    """The bounding box ``(low, high)`` of the config's shape in world coordinates, float64
    ``(3,)`` each: a built-in's from its parameters, a mesh's from its vertices."""
    if prepared.mesh_path is not None:
        mesh = prepared.mesh if prepared.mesh is not None else meshes.load(str(prepared.mesh_path))
        low, high = np.asarray(mesh.bounds, dtype=np.float64)
        return low, high
    return _builtin_box(prepared.experiment.surface.shape, prepared.params)


def _moved(shape: Shape, params: dict[str, Any], offset: np.ndarray) -> dict[str, Any]:
    """A built-in shape's parameters with its position moved by ``offset`` ``(3,)``."""
    moved = dict(params)
    for key in ("center", "start", "end"):
        if key in moved:
            moved[key] = tuple(float(x) for x in np.asarray(moved[key], dtype=np.float64) + offset)
    return moved


def open_edges(prepared: Prepared) -> int:
    """How many edges of the config's mesh belong to one face only (0: closed, or no mesh;
    :func:`torchsurf._mesh_sdf.boundary_edges`)."""
    if prepared.mesh_path is None:
        return 0
    mesh = prepared.mesh if prepared.mesh is not None else meshes.load(str(prepared.mesh_path))
    return boundary_edges(np.asarray(mesh.vertices), np.asarray(mesh.faces))


def build_surface(prepared: Prepared) -> ImplicitSurface:
    """The grid and signed distance the config names, as an :class:`ImplicitSurface`, or a
    :class:`~torchsurf.bricks.BrickSurface` when the config's layout is bricks (a mesh then
    goes straight into bricks, without a dense volume); in the frame centred at
    :func:`frame_centre` (world coordinates minus it)."""
    experiment = prepared.experiment
    size, margin = experiment.grid.size, experiment.grid.margin
    packed = cfg.layout(experiment.grid) is Layout.bricks
    centre = frame_centre(prepared)
    if prepared.mesh_path is not None:
        mesh = prepared.mesh if prepared.mesh is not None else meshes.load(str(prepared.mesh_path))
        mesh = mesh.copy()
        # not apply_translation: trimesh skips a move within 1e-8 of the identity, and a mesh
        # 1e-9 across was left in place while the record said it had moved (9 cells off)
        mesh.vertices = np.asarray(mesh.vertices) - centre
        grid = meshes.fit_grid(mesh, size, margin)
        try:  # the mesh read, but no surface on the grid (one triangle, an open sheet)
            if packed:
                return bricks.from_mesh(mesh, grid)
            phi = sdf.from_mesh(mesh, grid)
        except ValueError as error:
            raise ConfigError("surface.mesh", f"{prepared.mesh_path}: {error}") from error
    else:
        shape = experiment.surface.shape
        params = _moved(shape, prepared.params, -centre)
        low, high = _builtin_box(shape, params)
        side = float((high - low).max()) * (1.0 + 2.0 * margin)
        origin = tuple(float(x) for x in 0.5 * (low + high) - 0.5 * side)
        grid = Grid((size,) * 3, side / (size - 1), origin)
        phi = SHAPES[shape](grid, **params)
        if packed:
            return bricks.from_dense(phi, grid)
    return ImplicitSurface(phi, grid)


def extract_mesh(surface: ImplicitSurface) -> trimesh.Trimesh:
    """The marching-cubes mesh of ``surface``'s zero level set (on bricks, from the stored
    nodes made dense: the cells next to a node that is not stored are skipped)."""
    if surface.layout is None:
        return meshes.extract(surface.phi, surface.grid)
    phi, = surface.to_dense(surface.phi, fill=surface.band_width)
    stored, = surface.to_dense(torch.ones_like(surface.phi, dtype=torch.bool), fill=False)
    return meshes.extract(phi, surface.grid, mask=stored)


def coarse_surface(prepared: Prepared) -> ImplicitSurface | None:
    """The config's shape on the grid its field's smoothing runs on
    (:func:`torchsurf.config.smoothing_size`; the layout as the config says for that size), or
    ``None`` when that is the run's own grid."""
    experiment = prepared.experiment
    field = experiment.field
    if field is None or field.kind in (cfg.FieldKind.axis, cfg.FieldKind.swirl):
        return None
    size = cfg.smoothing_size(experiment.grid.size, field)
    if size == experiment.grid.size:
        return None
    grid = replace(experiment.grid, size=size)
    return build_surface(replace(prepared, experiment=replace(experiment, grid=grid)))


def tangent_field(config: cfg.FieldConfig, surface: ImplicitSurface,
                  centre: tuple[float, float, float], coarse: ImplicitSurface | None = None
                  ) -> Tensor:
    """The unit tangent field ``(1, 3, D, H, W)`` a ``field:`` section describes; ``centre``
    is the shape's, world ``(x, y, z)``; ``coarse`` the surface its smoothing runs on, if not
    ``surface`` (:func:`coarse_surface`)."""
    kind = config.kind
    if kind is cfg.FieldKind.axis:
        return signals.axis_field(surface, config.axis.name)
    if kind is cfg.FieldKind.swirl:
        return signals.swirl_field(surface, config.axis.name, centre)
    which = "max" if kind is cfg.FieldKind.principal_max else "min"
    field = signals.principal_direction(surface, which, config.smoothing, coarse)
    if config.orient is not None:
        field = signals.orient(field, signals.swirl_field(surface, config.orient.name, centre))
    return field


def build_signal(prepared: Prepared, surface: ImplicitSurface, box: tuple[Tensor, Tensor],
                 diagonal: float, field: Tensor | None) -> tuple[Tensor, Tensor]:
    """The clean signal and the flow's input (the clean one with noise), ``(1, C, D, H, W)``."""
    signal = prepared.experiment.signal
    kind = signal.kind
    points = signals.closest_points(surface)
    if kind is SignalKind.checkerboard:
        tiles = signal_setting(signal, "tiles")
        clean = signals.checkerboard(points, diagonal / tiles, tuple(box[0].tolist()))
    elif kind is SignalKind.image:
        name = signal_setting(signal, "image")
        if name in signals.IMAGES:
            image = signals.builtin_image(name)
        else:
            image_path = Path(name).expanduser()
            image = signals.load_image(image_path if image_path.is_absolute()
                                       else prepared.folder / image_path)
        clean = signals.project_image(image, points, signal_setting(signal, "projection").name,
                                      box, signal_setting(signal, "axis").name, surface.normal)
        if signal_setting(signal, "gray") and clean.shape[1] == 3:
            clean = signals.gray(clean)
    elif kind is SignalKind.noise:
        clean = signals.surface_noise(surface, 1, signal.seed, signal_setting(signal, "grain"))
    elif kind is SignalKind.field:
        clean = field
    else:
        clean = flows.ReactionDiffusion.initial(surface)
    if signal.noise == 0 or kind in (SignalKind.noise, SignalKind.turk):
        return clean, clean
    if kind is SignalKind.field:
        return clean, signals.perturb_field(clean, surface, signal.noise, signal.seed)
    return clean, clean + signals.gaussian_noise(clean, signal.noise, signal.seed, surface)


def physical_settings(experiment: Experiment, diagonal: float, spacing: float
                      ) -> dict[str, float]:
    """The world-unit values of the scale-free flow settings (docs/cli.md)."""
    flow = experiment.flow
    unit = cfg.time_unit(flow)
    result: dict[str, float] = {}
    if flow.kind is FlowKind.harmonic:
        order = cfg.flow_setting(flow, "p")
    else:
        order = FLOW_ORDER.get(flow.kind, 0.0)
    length = {TimeUnit.diagonal: diagonal, TimeUnit.cells: spacing}.get(unit)
    result["time"] = flow.time * (length**order if length is not None else 1.0)
    if flow.kind is FlowKind.color:  # its chroma is a p-harmonic map flow: time in L^p
        p = cfg.flow_setting(flow, "p")
        result["chroma_time"] = flow.time * (length**p if length is not None else 1.0)
    for name in cfg.FLOW_SETTINGS[flow.kind]:
        value = cfg.flow_setting(flow, name)
        result[name] = value / spacing if name in ("eps", "contrast") else value
    if flow.kind is FlowKind.perona_malik:
        result["eps"] = PERONA_MALIK_EPS * result["contrast"]
    return result


PERONA_MALIK_EPS = 1e-2
"""Perona–Malik's regularisation ``eps``, a share of its ``contrast``, so scale-free like it:
the flows' default ``1e-2`` data per world length outweighed the gradients on shapes hundreds
of units across (``perona_malik_torus`` scaled by 1e3 at 48^3 removed 12% of the noise it
removes at size 1, by 1e5 none); 0.77% of the contrast at size 1 there."""


@contextmanager
def _time_named(experiment: Experiment, physical: dict[str, float]) -> Iterator[None]:
    """A flow's refusal of a time far beyond its equilibrium as a :class:`ConfigError` naming
    ``flow.time`` in the config's unit (the flow names the world value, once the surface is
    built: the equilibrium depends on its operator)."""
    try:
        yield
    except flows.BeyondEquilibrium as error:
        unit = cfg.time_unit(experiment.flow).name
        isotropic = experiment.flow.isotropic
        faster = (f"; the diffusion includes flow.isotropic = {isotropic:g} times an isotropic "
                  "term, which speeds it up as much: lower it or the time"
                  if isotropic is not None and isotropic > 1.0 else "")
        raise ConfigError("flow.time", (
            f"{experiment.flow.time:g} ({unit}) is {physical['time']:.3g} in world units on "
            f"this shape, {error.crossings:.3g} times the time the diffusion takes to cross "
            f"the whole grid: the flow reaches its equilibrium long before, and more than "
            f"{flows.EQUILIBRIUM_CROSSINGS} times is refused as a likely unit error"
            f"{faster}")) from error


def build_flow(experiment: Experiment, physical: dict[str, float], progress: bool
               ) -> torch.nn.Module:
    """The flow module of the config, with its physical settings."""
    flow = experiment.flow
    options: dict[str, Any] = {"progress": progress}
    if flow.method is not None:
        options["method"] = flow.method
    if flow.steps is not None:
        options["steps"] = flow.steps
    t = physical["time"]
    kind = flow.kind
    if kind is FlowKind.heat:
        return flows.HeatFlow(t, **options)
    if kind is FlowKind.total_variation:
        return flows.AnisotropicFlow(t, "total_variation", eps=physical["eps"], **options)
    if kind is FlowKind.perona_malik:
        return flows.AnisotropicFlow(t, "perona_malik", contrast=physical["contrast"],
                                     eps=physical["eps"], **options)
    if kind is FlowKind.harmonic:
        tangent = experiment.signal.kind is SignalKind.field
        return flows.HarmonicMapFlow(t, p=physical["p"], eps=physical["eps"], tangent=tangent,
                                     **options)
    if kind is FlowKind.color:
        chroma = flows.HarmonicMapFlow(physical["chroma_time"], p=physical["p"],
                                       eps=physical["eps"], **options)
        brightness = flows.AnisotropicFlow(t, eps=physical["eps"], **options)
        return flows.ColorDenoise(chroma=chroma, brightness=brightness)
    if kind is FlowKind.reaction_diffusion:
        return flows.ReactionDiffusion(t, rate=physical["rate"], **options)
    return flows.FlowVisualization(t, isotropic=physical["isotropic"], **options)


def flow_as_run(experiment: Experiment, module: torch.nn.Module) -> dict[str, Any]:
    """The config's ``flow`` section with the values the run used where it left a default
    (``null``): the time unit, the optional settings the flow reads, the integration method and
    the steps ``module`` took in its last call. For colour denoising, ``steps`` maps its
    ``brightness`` and ``chroma`` flows to theirs."""
    flow = experiment.flow
    if isinstance(module, flows.ColorDenoise):
        method = module.chroma.method
        steps = {name: _steps_taken(getattr(module, name)) for name in ("brightness", "chroma")}
    else:
        method, steps = module.method, _steps_taken(module)
    return {
        "kind": flow.kind.name, "time": flow.time, "time_unit": cfg.time_unit(flow).name,
        **{name: cfg.flow_setting(flow, name) for name in cfg.FLOW_SETTINGS[flow.kind]},
        "method": method, "steps": steps,
    }


def output_paths(name: str, out: str | Path) -> tuple[Path, Path]:
    """The picture and the record a run of the config ``name`` writes into ``out``:
    ``<out>/<name>.png`` and ``<out>/<name>.json``."""
    out = Path(out)
    return out / f"{name}.png", out / f"{name}.json"


def _steps_taken(flow: flows.Flow) -> int | None:
    """The steps ``flow`` took in its last call (:attr:`torchsurf.flows.Flow.last_plan`),
    ``None`` for a method without a step count (adaptive torchdiffeq, ``chebyshev``)."""
    return None if flow.last_plan is None else flow.last_plan.count


def _versions() -> dict[str, str]:
    from importlib import metadata

    from . import __version__

    found = {"torchsurf": __version__, "python": platform.python_version()}
    for name in ("torch", "numpy", "kornia", "omegaconf", "matplotlib", "scikit-image", "trimesh",
                 "pyvista", "vtk"):
        try:
            found[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            found[name] = "not installed"
    return found


def _staged_json(data: dict[str, Any], path: Path) -> Path:
    """``data`` as indented JSON in a hidden temporary file beside ``path``, to be renamed
    into place; nothing is left behind if writing fails."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".json")
    try:
        with os.fdopen(handle, "w") as stream:
            json.dump(data, stream, indent=2)
            stream.write("\n")
            os.fchmod(stream.fileno(), render.FILE_MODE)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return Path(temporary)


@contextmanager
def _threads(count: int | None):  # noqa: ANN202
    previous = torch.get_num_threads()
    if count is not None:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def _panel_colours(experiment: Experiment, values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Vertex colours of each panel: textures on a shared ``[0, 1]`` scale, reaction–diffusion
    on its own percentiles, noise and its flow visualisation histogram-equalised, fields and
    colour as themselves."""
    kind = experiment.signal.kind
    colormap = experiment.render.colormap
    result = {}
    for name, vertex in values.items():
        if kind is SignalKind.field:
            result[name] = render.colours(vertex, "field")
        elif vertex.shape[1] == 3:
            result[name] = render.colours(vertex, "rgb")
        elif kind is SignalKind.noise:
            result[name] = render.colours(vertex, "scalar", colormap, equalize=True)
        elif kind is SignalKind.turk:  # the first species
            result[name] = render.colours(vertex[:, :1], "scalar", colormap)
        else:
            result[name] = render.colours(vertex, "scalar", colormap, (0.0, 1.0))
    return result


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)))


def _sign_free_rms(field: Tensor, clean: Tensor, near: Tensor) -> float:
    """RMS over the nodes of ``near`` (``(B, 1, ...)`` bool) of ``min(|T - T0|, |T + T0|)``
    per component, ``T`` ``field`` and ``T0`` ``clean`` ``(B, 3, ...)`` (line fields: ``T``
    and ``-T`` are one direction)."""
    apart = (field - clean).square().sum(dim=1, keepdim=True)
    opposite = (field + clean).square().sum(dim=1, keepdim=True)
    squared = torch.minimum(apart, opposite)[near.expand_as(apart)]
    return float((squared.mean() / field.shape[1]).sqrt())


def run(prepared: Prepared, out: str | os.PathLike, progress: bool = False,
        log: Callable[[str], None] = print, command: Sequence[str] | None = None) -> Result:
    """Run a prepared experiment and write its picture and record into ``out``; ``command``,
    the command line that asked for it, goes into the record (default ``sys.argv``)."""
    experiment = prepared.experiment
    stages: dict[str, float] = {}
    clock = time.perf_counter()

    def stage(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        stages[name] = round(now - clock, 3)
        clock = now

    with _threads(experiment.threads):
        surface = build_surface(prepared)
        extracted = extract_mesh(surface)
        low, high = (torch.tensor(b, dtype=surface.phi.dtype) for b in extracted.bounds)
        diagonal = float((high - low).norm())
        spacing = surface.spacing
        n = experiment.grid.size
        stored = "dense" if surface.layout is None else (
            f"bricks: {len(surface.layout)} of {math.prod(bricks_along(surface.grid.shape))} "
            "stored")
        log(f"{experiment.name}: {experiment.surface.shape.name} on {n}^3 nodes ({stored}), "
            f"spacing h = {spacing:.4g}, box diagonal L = {diagonal:.4g} "
            f"({diagonal / spacing:.0f} cells)")
        edges = open_edges(prepared)
        if edges:
            log(f"surface.mesh is open ({edges} edges of one face only): phi's sign (the "
                "winding number) closes its holes, so the picture and the RMS figures at its "
                "vertices include a surface across them that the mesh does not have")
        stage("surface")
        centre = tuple(float(c) for c in 0.5 * (low + high))
        field = None
        if experiment.field is not None:
            coarse = coarse_surface(prepared)
            if coarse is not None:
                log(f"field: smoothed over {experiment.field.smoothing:g} cells on a coarser "
                    f"{coarse.grid.shape[0]}^3 grid")
            field = tangent_field(experiment.field, surface, centre, coarse)
        clean, start = build_signal(prepared, surface, (low, high), diagonal, field)
        stage("signal")
        physical = physical_settings(experiment, diagonal, spacing)
        unit = cfg.time_unit(experiment.flow)
        settings = ", ".join(f"{k} = {v:.4g}" for k, v in physical.items())
        log(f"{experiment.flow.kind.name}: time {experiment.flow.time:g} ({unit.name}); "
            f"physical {settings}")
        module = build_flow(experiment, physical, progress)
        kind = experiment.flow.kind
        with torch.no_grad(), _time_named(experiment, physical):
            if kind is FlowKind.reaction_diffusion:
                inputs = {"generator": signals.generator(experiment.signal.seed)}
                if field is not None:
                    inputs["direction"] = field
                output = module(start, surface, **inputs)[:, :1]
                start = start[:, :1]
            elif kind is FlowKind.visualization:
                output = module(start, surface, direction=field)
            else:
                output = module(start, surface)
        if not bool(torch.isfinite(output[surface.band_mask().expand_as(output)]).all()):
            raise FloatingPointError(f"{experiment.name}: the flow produced NaN or infinity")
        ran = flow_as_run(experiment, module)
        stage("flow")
        volumes = {"clean": clean, "input": start, "output": output}
        field_signal = experiment.signal.kind is SignalKind.field
        if field_signal:
            # Shown sign-free, |T| per component at the nodes: sampling T itself would
            # average opposite signs of a line field to nothing.
            volumes = {name: volume.abs() for name, volume in volumes.items()}
        values = {name: render.vertex_values(volumes[name], extracted, surface)
                  for name in ("clean", "input", "output")}
        metrics: dict[str, float] = {}
        if experiment.signal.noise > 0 and kind not in (FlowKind.reaction_diffusion,
                                                        FlowKind.visualization):
            if field_signal:  # the directions themselves, not |T|'s components
                near = surface.distance() <= spacing
                metrics = {"rms_input": _sign_free_rms(start, clean, near),
                           "rms_output": _sign_free_rms(output, clean, near)}
                where = "at the nodes within a cell of S, sign-free"
            else:
                metrics = {"rms_input": _rms(values["input"], values["clean"]),
                           "rms_output": _rms(values["output"], values["clean"])}
                where = "at the vertices"
            log(f"RMS error against the clean signal {where}: input "
                f"{metrics['rms_input']:.4f}, output {metrics['rms_output']:.4f}")
        colours = _panel_colours(experiment, values)
        titles = {"clean": "clean", "input": "input" if experiment.signal.noise == 0 else "noisy",
                  "output": f"{kind.name.replace('_', ' ')}, t = {experiment.flow.time:g}"}
        render_config = experiment.render
        renderer, why = render.resolve_renderer(render_config.renderer.name)
        log(f"render: {renderer} ({why})")
        picture, record = output_paths(experiment.name, out)
        out = Path(out)
        # picture and record are both written aside, then renamed into place, the picture
        # first: a failure (or a stop) at any point before leaves neither new, nor the aside
        drawn = out / f".{experiment.name}.{os.getpid()}.png"
        staged = None
        try:
            render.render_panels(
                extracted, [(titles[p], colours[p]) for p in render_config.panels], drawn,
                render_config.width, render_config.height, render_config.elevation,
                render_config.azimuth, render_config.up.name, renderer,
            )
            stage("render")
            staged = _write_record(prepared, surface, n, spacing, diagonal, ran, physical,
                                   metrics, stages, picture, renderer, record,
                                   list(sys.argv if command is None else command))
            for target in (picture, record):  # what would stop a rename, before either is made
                if target.is_dir():
                    raise IsADirectoryError(f"{target} is a folder: the run cannot write its "
                                            "file")
            with signals_held():  # an interrupt between the two would leave one of them new
                os.replace(drawn, picture)
                os.replace(staged, record)
        except BaseException:
            drawn.unlink(missing_ok=True)
            if staged is not None:
                staged.unlink(missing_ok=True)
            raise
    return Result(picture, record, stages, physical, metrics, ran)


def _write_record(prepared: Prepared, surface: ImplicitSurface, n: int, spacing: float,
                  diagonal: float, ran: dict[str, Any], physical: dict[str, float],
                  metrics: dict[str, float], stages: dict[str, float], picture: Path,
                  renderer: str, path: Path, command: list[str]) -> Path:
    """The run's JSON record (config as requested, grid and flow as run, metrics, timings,
    versions) written beside ``path``, in a temporary file to be renamed to it."""
    experiment = prepared.experiment
    layout = cfg.layout(experiment.grid)
    return _staged_json({
        "config": cfg.to_dict(experiment),
        "mesh": None if prepared.mesh_path is None else str(prepared.mesh_path),
        "grid": {"size": n, "spacing": spacing,
                 "origin": [float(o + c) for o, c in zip(surface.grid.origin,
                                                         frame_centre(prepared), strict=True)],
                 "layout": layout.name,
                 "bricks": None if surface.layout is None else len(surface.layout)},
        "diagonal": diagonal,
        "flow": ran,
        "physical": physical,
        "metrics": metrics,
        "stages_seconds": stages,
        "picture": picture.name,
        "renderer": renderer,
        "command": command,
        "versions": _versions(),
    }, path)
