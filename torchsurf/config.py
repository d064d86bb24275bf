"""Experiment files: the typed schema of a ``torchsurf run`` config, loading and checking.

A config is YAML matched against the dataclasses below by omegaconf (structured configs): an
unknown key or a value of the wrong type is refused by omegaconf with the key's path, and
:func:`load` then checks ranges and the combinations of settings, again naming the key, before
anything is computed. Every error is a :class:`ConfigError` whose message starts with the key's
path (``flow.eps: ...``).

Scale-free units (docs/cli.md): a surface's size is the diagonal ``L`` of its bounding box and
``h`` the grid spacing; ``flow.time`` is in units of ``L^q`` (``time_unit: diagonal``), ``h^q``
(``cells``) or physical (``world``), ``q`` the order of the flow in space (2 for heat,
Perona–Malik, flow visualisation and harmonic maps with ``p = 2``; ``p`` for harmonic maps,
1 for total variation and colour denoising's brightness, ``p`` for its chroma), so that one
config works on a sphere of radius 1 and on a 0.15-wide bunny. Reaction–diffusion time is in
Turk's iterations (``turk``). Gradient settings (``eps``, ``contrast``) are in units of the
data's range per cell.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from dataclasses import field as _field
from enum import Enum
from importlib import resources
from pathlib import Path
from typing import Any

import yaml
from omegaconf import MISSING, DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

CONFIG_SUFFIX = ".yaml"
MESH_DIR_VARIABLE = "TORCHSURF_MESH_DIR"


class ConfigError(ValueError):
    """A config that cannot run: the message starts with the offending key's path."""

    def __init__(self, key: str, message: str) -> None:
        super().__init__(f"{key}: {message}" if key else message)
        self.key = key


class Shape(Enum):
    """Where the surface comes from: an analytic signed distance or a mesh file."""

    sphere = "sphere"
    torus = "torus"
    trefoil = "trefoil"
    box = "box"
    capsule = "capsule"
    mesh = "mesh"


class SignalKind(Enum):
    """The data put on the surface before the flow."""

    checkerboard = "checkerboard"
    image = "image"
    noise = "noise"
    field = "field"
    turk = "turk"


class Projection(Enum):
    """How a 2-D image is wrapped onto the surface (:func:`torchsurf.signals.project_image`)."""

    spherical = "spherical"
    cylindrical = "cylindrical"
    planar = "planar"
    triplanar = "triplanar"


class Axis(Enum):
    """A coordinate axis."""

    x = "x"
    y = "y"
    z = "z"


class FieldKind(Enum):
    """A unit tangent field (:mod:`torchsurf.signals`)."""

    principal_max = "principal_max"
    principal_min = "principal_min"
    axis = "axis"
    swirl = "swirl"


class FlowKind(Enum):
    """The flow run on the signal."""

    heat = "heat"
    total_variation = "total_variation"
    perona_malik = "perona_malik"
    harmonic = "harmonic"
    color = "color"
    reaction_diffusion = "reaction_diffusion"
    visualization = "visualization"


class TimeUnit(Enum):
    """Unit of ``flow.time`` (see the module docstring)."""

    diagonal = "diagonal"
    cells = "cells"
    world = "world"
    turk = "turk"


class Layout(Enum):
    """How the run stores its volumes (docs/bricks.md): the dense box, the band's 8^3 bricks,
    or ``auto`` (bricks from :data:`BRICKS_FROM` nodes per axis where the margin allows)."""

    auto = "auto"
    dense = "dense"
    bricks = "bricks"


BRICKS_FROM = 64
"""Grid size from which ``layout: auto`` stores bricks, where ``grid.margin`` leaves them the
:data:`BRICK_MARGIN_CELLS` they need (below :data:`BRICKS_ALWAYS_FROM`; from there always).
At the shipped mesh configs' sizes (64^3-96^3) bricks ran the flow stage in 0.37-0.75 of the
dense time (flow visualisation on the trefoil 0.37, colour denoising of the teapot 0.39, spots
0.45, harmonic maps 0.65-0.66, Perona-Malik and total variation 0.71; the heat flow 1.03-1.11), with
the same metrics to 1e-6; at 48^3 dense ran the built-in shapes 2-3x faster (docs/cli.md,
"Dense or bricks")."""

BRICKS_ALWAYS_FROM = 128
"""Grid size from which ``layout: auto`` stores bricks whatever the margin (a margin too small
for them is refused, naming ``grid.layout=dense``: a dense volume there is large)."""

DENSE_MARGIN_CELLS = 2.0
"""Free cells dense volumes need around the shape's box: S two cells inside the box, where
:class:`~torchsurf.ImplicitSurface` stops warning that the operators are wrong near the faces
(grid sizes 10-18 at the default margin had passed the former one cell and then warned; at a
margin of 0 the sphere's poles touched the faces and the pictures showed it flattened)."""

BRICK_MARGIN_CELLS = 5.0
"""Free cells the bricks layout needs around the shape's box: the 3-cell band and the 2 nodes
its stencils read (:func:`torchsurf.bricks.from_mesh` refuses less)."""


class Renderer(Enum):
    """What draws the pictures (:func:`torchsurf.render.resolve_renderer`)."""

    auto = "auto"
    pyvista = "pyvista"
    matplotlib = "matplotlib"


@dataclass
class SurfaceConfig:
    """``shape``: a built-in signed distance or ``mesh``; ``mesh``: a file path, resolved
    against the config's folder, then ``$TORCHSURF_MESH_DIR``; ``params``: keyword arguments
    of the :mod:`torchsurf.sdf` function (e.g. ``radius``, ``major_radius``)."""

    shape: Shape = Shape.sphere
    mesh: str | None = None
    params: dict[str, Any] = _field(default_factory=dict)


@dataclass
class GridConfig:
    """``size``: nodes per axis (a cube); ``margin``: free space on each side of the shape's
    box, a fraction of its longest side; ``layout``: dense volumes, the band's bricks, or
    ``auto`` (bricks from :data:`BRICKS_FROM` nodes per axis where the margin allows)."""

    size: int = 64
    margin: float = 0.15
    layout: Layout = Layout.auto


@dataclass
class SignalConfig:
    """The initial data; ``noise``: standard deviation of added Gaussian noise (units of the
    data's range; for a field, of each component before re-normalising); ``grain``: with
    ``kind: noise``, the size of the noise's specks, cells. The settings of one kind
    (:data:`SIGNAL_SETTINGS`) stay ``null`` with the others and take :data:`SIGNAL_DEFAULTS`
    when unset."""

    kind: SignalKind = SignalKind.checkerboard
    tiles: float | None = None
    image: str | None = None
    projection: Projection | None = None
    axis: Axis | None = None
    gray: bool | None = None
    noise: float = 0.0
    grain: float | None = None
    seed: int = 0


@dataclass
class FieldConfig:
    """A unit tangent field: principal directions (``smoothing``: length in cells of the
    sign-free smoothing, 0 for none; ``orient``: an axis whose swirl fixes their signs), the
    projection of an ``axis``, or the ``swirl``, the rotation about ``axis`` through the
    shape's centre. ``smoothing_grid``: on finer grids the smoothing runs on a coarser one of
    at least this many nodes per axis (:func:`smoothing_size`); 0 keeps it on the run's grid."""

    kind: FieldKind = FieldKind.principal_max
    axis: Axis = Axis.z
    smoothing: float = 2.0
    orient: Axis | None = None
    smoothing_grid: int = 64


SMOOTHING_MIN_CELLS = 8.0
"""The fewest cells of the coarse grid a coarsened smoothing may span (:func:`smoothing_size`)."""


def smoothing_size(size: int, field: FieldConfig) -> int:
    """Nodes per axis of the grid ``field``'s smoothing runs on, for a run of ``size`` nodes:
    ``size / f`` for the largest power of two ``f`` that keeps at least ``smoothing_grid`` nodes
    and :data:`SMOOTHING_MIN_CELLS` cells of smoothing there (``size`` itself when ``f = 1``).
    The cost of the smoothing grows with the area in cells times the smoothing in cells
    squared, so each halving saves about 16x."""
    factor = 1
    while (field.smoothing_grid > 0 and size // (2 * factor) >= field.smoothing_grid
           and field.smoothing / (2 * factor) >= SMOOTHING_MIN_CELLS):
        factor *= 2
    return size if factor == 1 else size // factor


@dataclass
class FlowConfig:
    """The flow; settings left ``null`` take the flow's default, settings that the flow does
    not use must stay ``null``."""

    kind: FlowKind = FlowKind.heat
    time: float = 1e-3
    time_unit: TimeUnit | None = None
    method: str | None = None
    steps: int | None = None
    eps: float | None = None
    contrast: float | None = None
    p: float | None = None
    rate: float | None = None
    isotropic: float | None = None


@dataclass
class RenderConfig:
    """Pictures: one PNG of ``panels`` side by side (``clean``, ``input``, ``output``), each
    ``width x height`` pixels, seen from ``elevation``/``azimuth`` degrees with ``up`` up, drawn
    by ``renderer`` (``auto``: pyvista when it draws off screen, else matplotlib)."""

    width: int = 400
    height: int = 400
    panels: list[str] = _field(default_factory=lambda: ["input", "output"])
    colormap: str = "viridis"
    elevation: float = 25.0
    azimuth: float = -60.0
    up: Axis = Axis.z
    renderer: Renderer = Renderer.auto


@dataclass
class Experiment:
    """One ``torchsurf run``: a surface, a signal on it, a flow, and the pictures."""

    name: str = MISSING
    description: str = ""
    surface: SurfaceConfig = _field(default_factory=SurfaceConfig)
    grid: GridConfig = _field(default_factory=GridConfig)
    signal: SignalConfig = _field(default_factory=SignalConfig)
    field: FieldConfig | None = None
    flow: FlowConfig = _field(default_factory=FlowConfig)
    render: RenderConfig = _field(default_factory=RenderConfig)
    threads: int | None = None


FLOW_SETTINGS: dict[FlowKind, tuple[str, ...]] = {
    FlowKind.heat: (),
    FlowKind.total_variation: ("eps",),
    FlowKind.perona_malik: ("contrast",),
    FlowKind.harmonic: ("p", "eps"),
    FlowKind.color: ("p", "eps"),
    FlowKind.reaction_diffusion: ("rate",),
    FlowKind.visualization: ("isotropic",),
}
"""The optional settings each flow reads; the others must stay ``null``."""

UNCAPPED_METHODS = ("scipy_solver",)
"""torchdiffeq methods a config refuses: their work has no cap (docs/cli.md, ``flow.method``)."""

LINEAR_FLOWS = (FlowKind.heat, FlowKind.visualization)
"""The flows whose rate is linear and symmetric: the implicit methods solve only those."""

FLOW_DEFAULTS: dict[str, float] = {"eps": 0.05, "contrast": 0.1, "p": 1.0, "rate": 1.0 / 16.0,
                                   "isotropic": 0.0}
"""Defaults of the optional flow settings (``eps``, ``contrast``: data range per cell)."""

SIGNAL_SETTINGS: dict[SignalKind, tuple[str, ...]] = {
    SignalKind.checkerboard: ("tiles",),
    SignalKind.image: ("image", "projection", "axis", "gray"),
    SignalKind.noise: ("grain",),
    SignalKind.field: (),
    SignalKind.turk: (),
}
"""The settings each signal reads besides ``noise`` and ``seed``; the others must stay
``null``."""

SIGNAL_DEFAULTS: dict[str, object] = {"tiles": 8.0, "image": "colour_wheel",
                                      "projection": Projection.spherical, "axis": Axis.z,
                                      "gray": False, "grain": 1.0}
"""Defaults of the settings of :data:`SIGNAL_SETTINGS` (``tiles`` along the box diagonal,
``grain`` in cells)."""

FLOW_SIGNALS: dict[FlowKind, tuple[SignalKind, ...]] = {
    FlowKind.heat: (SignalKind.checkerboard, SignalKind.image, SignalKind.noise),
    FlowKind.total_variation: (SignalKind.checkerboard, SignalKind.image),
    FlowKind.perona_malik: (SignalKind.checkerboard, SignalKind.image),
    FlowKind.harmonic: (SignalKind.field,),
    FlowKind.color: (SignalKind.image,),
    FlowKind.reaction_diffusion: (SignalKind.turk,),
    FlowKind.visualization: (SignalKind.noise,),
}
"""The signals each flow accepts."""

PANELS = ("clean", "input", "output")

THREADS_MAX = 1024
"""The most threads a config may ask for (torch itself crashes on some 10^5)."""

PICTURE_WIDTH_MAX = 16384
"""The widest picture, all panels side by side: :data:`torchsurf.render.PICTURE_WIDTH_MAX`
(not imported from there, which would load matplotlib and trimesh with the config)."""

NOISE_MAX = 1e3
"""The largest ``signal.noise``: a thousand times the data's range already buries any signal
(``1e300`` overflowed float32 into NaN after the surface was built, exit 1)."""

SEED_MAX = 2**32 - 1
"""The largest seed (:data:`torchsurf.signals.SEED_LIMIT`: torch's CPU generator keeps 32 bits
of a seed, so ``2^32`` repeated ``0``)."""

NAME_MAX = 200
"""The longest run name: its files' temporary names add about 30 characters, and file
systems take 255."""


def flow_setting(flow: FlowConfig, name: str) -> float:
    """``flow.<name>`` or its default from :data:`FLOW_DEFAULTS`."""
    value = getattr(flow, name)
    return FLOW_DEFAULTS[name] if value is None else float(value)


def signal_setting(signal: SignalConfig, name: str) -> Any:
    """``signal.<name>`` or its default from :data:`SIGNAL_DEFAULTS`."""
    value = getattr(signal, name)
    return SIGNAL_DEFAULTS[name] if value is None else value


def time_unit(flow: FlowConfig) -> TimeUnit:
    """``flow.time_unit``, by default ``turk`` for reaction–diffusion, ``diagonal`` otherwise."""
    if flow.time_unit is not None:
        return flow.time_unit
    return TimeUnit.turk if flow.kind is FlowKind.reaction_diffusion else TimeUnit.diagonal


def _check_margin(grid: GridConfig, where: str) -> None:
    """Refuse a margin of fewer than :data:`BRICK_MARGIN_CELLS` cells on ``grid`` when it takes
    the bricks layout, of fewer than :data:`DENSE_MARGIN_CELLS` on dense volumes; ``where``
    says which grid, in the message."""
    bricks = layout(grid) is Layout.bricks
    least = BRICK_MARGIN_CELLS if bricks else DENSE_MARGIN_CELLS
    size, margin = grid.size, grid.margin
    cells = _margin_cells(grid)
    if cells < least:
        needed = least / (size - 1 - 2 * least)
        advice = (f"use grid.margin >= {math.ceil(needed * 1000) / 1000:g}"
                  if 0 < needed <= 1 else "use a larger grid.size")
        what = ("the bricks layout needs {:g} (the band and the nodes its stencils read)"
                if bricks else "dense volumes need {:g} (S two cells inside the box; closer, "
                "the operators are wrong near the faces, and at 0 the shape is cut flat)")
        raise ConfigError("grid.margin", f"{margin:g} leaves {cells:.2f} cells around the "
                          f"shape {where}; {what.format(least)}: {advice}"
                          + (", or grid.layout=dense" if bricks else ""))


def layout(grid: GridConfig) -> Layout:
    """``grid.layout`` with ``auto`` resolved: bricks from :data:`BRICKS_FROM` nodes per axis
    where the margin leaves :data:`BRICK_MARGIN_CELLS`, and from :data:`BRICKS_ALWAYS_FROM`."""
    if grid.layout is not Layout.auto:
        return grid.layout
    if grid.size >= BRICKS_ALWAYS_FROM:
        return Layout.bricks
    if grid.size >= BRICKS_FROM and _margin_cells(grid) >= BRICK_MARGIN_CELLS:
        return Layout.bricks
    return Layout.dense


def _margin_cells(grid: GridConfig) -> float:
    """The free cells ``grid.margin`` leaves around the shape's box."""
    return grid.margin * (grid.size - 1) / (1 + 2 * grid.margin)


def builtin_folder() -> Path:
    """The folder of the configs shipped with the package."""
    return Path(str(resources.files("torchsurf") / "configs"))


def builtin_names() -> list[str]:
    """Names of the shipped configs, sorted."""
    return sorted(path.stem for path in builtin_folder().glob(f"*{CONFIG_SUFFIX}"))


def find(config: str | os.PathLike) -> Path:
    """A config's file: ``config`` as a path if it exists, else a shipped config's name.

    Raises:
        ConfigError: neither (the message lists the shipped names).
    """
    path = Path(config)
    if path.is_file():
        return path
    name = path.name[: -len(CONFIG_SUFFIX)] if path.name.endswith(CONFIG_SUFFIX) else path.name
    shipped = builtin_folder() / f"{name}{CONFIG_SUFFIX}"
    if path.parent == Path(".") and shipped.is_file():
        return shipped
    raise ConfigError(
        "", f"no config file {str(config)!r} and no shipped config of that name; shipped: "
        f"{', '.join(builtin_names())}"
    )


MERGE_ERRORS = (OmegaConfBaseException, TypeError)
"""What merging a config with the schema raises; ``TypeError`` for a list given where the
schema has a mapping, or the reverse ("Cannot merge incompatible container types")."""


def _omegaconf_error(error: Exception, raw: DictConfig, overrides: list[str]
                     ) -> ConfigError:
    """``error`` as a :class:`ConfigError` starting with the key's path; where omegaconf names
    none (a value given for a whole section), the file's key if the file fails alone, else the
    first override that fails with it."""
    key = getattr(error, "full_key", "") or ""
    message = _message(error)
    if not key:
        try:
            OmegaConf.merge(OmegaConf.structured(Experiment), raw)
        except MERGE_ERRORS as alone:
            return ConfigError(_failing_section(raw), _message(alone))
        for item in overrides:
            try:
                OmegaConf.merge(OmegaConf.structured(Experiment), raw,
                                OmegaConf.from_dotlist([item]))
            except MERGE_ERRORS:
                return ConfigError(item.partition("=")[0].strip(),
                                   f"cannot take {item!r}: {message}")
    return ConfigError(str(key), message)


def _message(error: Exception) -> str:
    """The first line of omegaconf's message, in the config's terms."""
    if isinstance(error, TypeError):
        return "a list given where a mapping is expected, or a mapping where a list is"
    return str(getattr(error, "msg", "") or error).splitlines()[0]


def _failing_section(raw: DictConfig, path: tuple[str, ...] = ()) -> str:
    """The deepest key of the file (dotted) that does not merge with the schema alone."""
    for name in raw:
        nested: Any = {name: raw[name]}
        for outer in reversed(path):
            nested = {outer: nested}
        try:
            OmegaConf.merge(OmegaConf.structured(Experiment), nested)
        except MERGE_ERRORS:
            if isinstance(raw[name], DictConfig) and _merges((*path, str(name))):
                inner = _failing_section(raw[name], (*path, str(name)))
                if inner:
                    return inner
            return ".".join((*path, str(name)))
    return ""


def _merges(path: tuple[str, ...]) -> bool:
    """Whether an empty mapping merges with the schema at ``path``: the key takes a mapping."""
    empty: Any = {}
    for outer in reversed(path):
        empty = {outer: empty}
    try:
        OmegaConf.merge(OmegaConf.structured(Experiment), empty)
    except MERGE_ERRORS:
        return False
    return True


def parse_overrides(overrides: list[str]) -> list[str]:
    """Check ``key=value`` overrides (``--set``); returns them as given."""
    if isinstance(overrides, (str, bytes)) or not all(isinstance(item, str) for item in overrides):
        raise TypeError(f"overrides must be a list of 'key=value' strings, got {overrides!r}")
    for item in overrides:
        key, equals, _ = item.partition("=")
        if not equals or not key.strip():
            raise ConfigError("--set", f"expected key=value, got {item!r}")
    return overrides


TEXT_KEYS = ("name", "description", "surface.mesh", "signal.image", "flow.method",
             "render.colormap")
"""Settings that hold text: their ``--set`` values are taken as written (YAML would read
``name=yes`` as ``True`` and ``name=010`` as ``8``), but for ``null``."""


DECIMAL_INTEGER = re.compile(r"[-+]?(0|[1-9][0-9]*)")
"""How an integer setting is written; YAML 1.1, which omegaconf reads, takes ``032`` as the
octal 26, ``0x40`` as 64, ``1_00`` as 100 and ``1:30`` as 90."""


def _refuse_unusual_numbers(node: yaml.Node, path: str = "") -> None:
    """Raise naming the key of a plain (unquoted) number in ``node`` (composed YAML) that is
    not written in decimal digits (:data:`DECIMAL_INTEGER`; floats without ``_`` or ``:``):
    it would run with another number than the one written. :data:`TEXT_KEYS` are left to
    :func:`_refuse_quoted_numbers`."""
    if path in TEXT_KEYS:
        return
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            _refuse_unusual_numbers(value, f"{path}.{key.value}" if path else str(key.value))
    elif isinstance(node, yaml.SequenceNode):
        for index, item in enumerate(node.value):
            _refuse_unusual_numbers(item, f"{path}[{index}]")
    elif isinstance(node, yaml.ScalarNode) and node.style is None:
        text = node.value
        if ((node.tag.endswith(":int") and not DECIMAL_INTEGER.fullmatch(text))
                or (node.tag.endswith(":float") and ("_" in text or ":" in text))
                or (node.tag.endswith(":str") and "_" in text and _is_number(text))):
            read = yaml.safe_load(text)
            reading = (f"YAML would read it as the text {read!r}, not a number"
                       if isinstance(read, str) else f"YAML would read it as {read!r}")
            raise ConfigError(path, f"{text} is not written in decimal digits: {reading} (a "
                              "leading 0 as octal, 0x as hexadecimal, _ dropped where it reads "
                              "a number, 1:30 as 90); write the number plainly")


def _dotlist(overrides: list[str]) -> DictConfig:
    """``overrides`` as a config, values read as YAML, the :data:`TEXT_KEYS`' as written."""
    parsed = OmegaConf.from_dotlist(overrides)
    for item in overrides:
        key, _, text = item.partition("=")
        key, text = key.strip(), text.strip()
        try:
            _refuse_unusual_numbers(yaml.compose(text, Loader=yaml.SafeLoader), key)
        except yaml.YAMLError:
            pass  # from_dotlist has read it: omegaconf's own reading is the one reported
        quoted = len(text) >= 2 and text[0] == text[-1] and text[0] in "'\""
        if key in TEXT_KEYS and text not in ("null", "~", "") and not quoted:
            OmegaConf.update(parsed, key, text, merge=False)
    return parsed


def _drop_replaced_mappings(raw: DictConfig, given: DictConfig, overrides: list[str]) -> None:
    """Remove from the file's ``raw`` settings each mapping an override gives whole
    (``surface.params={}``), so that it replaces the file's instead of merging into it
    (``surface.params.radius=2`` still changes one entry)."""
    for item in overrides:
        key = item.partition("=")[0].strip()
        if not isinstance(OmegaConf.select(given, key, default=None), DictConfig):
            continue
        *parents, last = key.split(".")
        node: Any = raw
        for part in parents:
            node = node.get(part) if isinstance(node, DictConfig) else None
        if isinstance(node, DictConfig) and last in node:
            del node[last]


def _refuse_interpolations(given: object, path: str = "") -> None:
    """Raise naming the key of a value holding an omegaconf interpolation (``${...}``): they
    half-worked (resolved in text settings, environment values copied into the record;
    refused in numbers as quoted text, or "not found" through ``--set``)."""
    if isinstance(given, dict):
        for key, value in given.items():
            _refuse_interpolations(value, f"{path}.{key}" if path else str(key))
    elif isinstance(given, list):
        for index, value in enumerate(given):
            _refuse_interpolations(value, f"{path}[{index}]")
    elif isinstance(given, str) and "${" in given:
        raise ConfigError(path, f"interpolations are not supported, got {given!r}: write the "
                          "value itself (a relative mesh path is looked for beside the config, "
                          f"then in ${MESH_DIR_VARIABLE})")


def _refuse_quoted_numbers(given: object, merged: DictConfig, path: str = "") -> None:
    """Raise naming the key of a value that omegaconf would convert to the setting's type: a
    number written as a string (``steps: '5'``), a number or a boolean where text belongs
    (``name: 010``, which YAML reads as 8; ``name: yes``, True), a number where a boolean
    belongs (``signal.gray: 1``). A setting of the wrong type is refused, whatever it looks
    like."""
    if isinstance(given, dict):
        for key, value in given.items():
            _refuse_quoted_numbers(value, merged, f"{path}.{key}" if path else str(key))
        return
    read = OmegaConf.select(merged, path, default=None)
    if isinstance(given, str):
        if isinstance(read, bool):
            raise ConfigError(path, f"must be true or false, got the string {given!r} (remove "
                              "the quotes)")
        if isinstance(read, (int, float)) and not isinstance(read, bool):
            if _is_non_finite(given):  # `--set flow.time=nan`: YAML reads nan, inf as strings
                raise ConfigError(path, f"must be a finite number, got {given}")
            raise ConfigError(path, f"must be a number, got the string {given!r}: YAML reads "
                              "a number in quotes as text, and one with a leading zero (048) "
                              "too; write it unquoted, without the zero")
    elif isinstance(given, (bool, int, float)) and isinstance(read, str):
        raise ConfigError(path, f"must be text, got {given!r} (YAML reads 010 as the number 8 "
                          "and yes as true): write the text in quotes")
    elif isinstance(given, (int, float)) and not isinstance(given, bool) and isinstance(read, bool):
        raise ConfigError(path, f"must be true or false, got {given!r}")


def _is_number(text: str) -> bool:
    """Whether Python reads ``text`` as a number, as omegaconf does ``5_0e-5`` (which PyYAML's
    resolver leaves as text)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


def _is_non_finite(text: str) -> bool:
    try:
        return not math.isfinite(float(text))
    except ValueError:
        return False


def load(config: str | os.PathLike, overrides: list[str] | None = None) -> tuple[Experiment, Path]:
    """Read, merge with ``overrides`` (``["grid.size=24", ...]``) and check a config.

    Returns:
        The :class:`Experiment` and the config's folder (against which mesh paths resolve).

    Raises:
        ConfigError: the first problem found, its message starting with the key's path.
    """
    path = find(config)
    try:
        raw = OmegaConf.load(path)
    except Exception as error:  # yaml's own errors carry the line and column
        raise ConfigError("", f"{path} is not valid YAML: {error}") from error
    if not isinstance(raw, DictConfig):
        raise ConfigError("", f"{path} must hold a mapping of settings, got a list")
    _refuse_unusual_numbers(yaml.compose(path.read_text(encoding="utf-8"), Loader=yaml.SafeLoader))
    overrides = parse_overrides(overrides or [])
    _refuse_interpolations(OmegaConf.to_container(raw, resolve=False))
    for item in overrides:
        key, _, value = item.partition("=")
        _refuse_interpolations(value, key.strip())
    try:
        given = _dotlist(overrides)
        _drop_replaced_mappings(raw, given, overrides)
        merged = OmegaConf.merge(OmegaConf.structured(Experiment), raw, given)
        experiment = OmegaConf.to_object(merged)
    except MERGE_ERRORS as error:
        raise _omegaconf_error(error, raw, overrides or []) from error
    for source in (raw, given):
        _refuse_quoted_numbers(OmegaConf.to_container(source, resolve=False), merged)
    _take_paths_from_the_current_folder(experiment, overrides)
    check(experiment)
    return experiment, path.resolve().parent


FILE_KEYS = {"surface.mesh": ("surface", "mesh"), "signal.image": ("signal", "image")}
"""Settings that name a file, as ``(section, field)``."""


def _take_paths_from_the_current_folder(experiment: Experiment, overrides: list[str]) -> None:
    """A relative file path given with ``--set`` names a file of the current folder where one
    is there (made absolute); otherwise it is looked up beside the config as in a file."""
    for item in overrides:
        key = item.partition("=")[0].strip()
        if key not in FILE_KEYS:
            continue
        section, field_name = FILE_KEYS[key]
        value = getattr(getattr(experiment, section), field_name)
        if value is None or Path(value).expanduser().is_absolute():
            continue
        here = Path.cwd() / Path(value).expanduser()
        if here.is_file():
            setattr(getattr(experiment, section), field_name, str(here.resolve()))


def to_dict(experiment: Experiment) -> dict[str, Any]:
    """The experiment as plain data (enums as their names), e.g. for JSON."""
    return OmegaConf.to_container(OmegaConf.structured(experiment), enum_to_str=True)


def _positive(value: float, key: str) -> None:
    if not value > 0 or value == float("inf"):
        raise ConfigError(key, f"must be a finite number > 0, got {value!r}")


def _at_least_zero(value: float, key: str) -> None:
    if not (math.isfinite(value) and value >= 0):
        raise ConfigError(key, f"must be a finite number >= 0, got {value!r}")


def _is_file_stem(name: str) -> bool:
    """``name`` can name a file in the output folder: no separator, no leading dot."""
    allowed = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-.")
    return bool(name) and not name.startswith(".") and set(name) <= allowed


def _check_field_settings_read(field_config: FieldConfig) -> None:
    """Refuse a ``field`` setting changed from its default that its kind does not read:
    ``axis`` and ``swirl`` read only ``axis``; the principal directions all but ``axis``."""
    defaults = FieldConfig()
    directions = field_config.kind in (FieldKind.principal_max, FieldKind.principal_min)
    unread = ("axis",) if directions else ("smoothing", "orient", "smoothing_grid")
    for name in unread:
        if getattr(field_config, name) != getattr(defaults, name):
            reads = ("smoothing, orient, smoothing_grid" if directions else "axis")
            raise ConfigError(f"field.{name}", f"not read by field.kind="
                              f"{field_config.kind.name} (it reads {reads}); remove it, or, "
                              "where a config file sets it, give the section whole: --set "
                              f"\"field={{kind: {field_config.kind.name}}}\"")


def check(experiment: Experiment) -> None:
    """Ranges and combinations of an experiment's settings (types are checked by omegaconf).

    Raises:
        ConfigError: naming the key.
    """
    if not _is_file_stem(experiment.name) or len(experiment.name) > NAME_MAX:
        raise ConfigError("name", f"must be a file name of at most {NAME_MAX} letters, digits, "
                          f"'_', '-' and '.' (it names the output files), not starting with "
                          f"'.', got {experiment.name!r}")
    if experiment.surface.shape is Shape.mesh and not experiment.surface.mesh:
        raise ConfigError("surface.mesh", "shape: mesh needs a mesh file path")
    if experiment.surface.shape is not Shape.mesh and experiment.surface.mesh:
        raise ConfigError("surface.mesh", f"a mesh file is only read with shape: mesh, not "
                          f"shape: {experiment.surface.shape.name}")
    if experiment.grid.size < 8:
        raise ConfigError("grid.size", f"must be an integer >= 8, got {experiment.grid.size}")
    if not 0 <= experiment.grid.margin <= 1:
        raise ConfigError("grid.margin", f"must be in [0, 1], got {experiment.grid.margin}")
    _check_margin(experiment.grid, f"at grid.size={experiment.grid.size}")
    signal = experiment.signal
    size = experiment.grid.size
    _check_signal_settings(signal)
    tiles, grain = signal_setting(signal, "tiles"), signal_setting(signal, "grain")
    _positive(tiles, "signal.tiles")
    if tiles < 1:  # 1e-300 passed: a constant signal, nothing for the flow to show
        raise ConfigError("signal.tiles", f"must be at least 1 (a tile longer than the box's "
                          f"diagonal paints the shape in one or two colours), got {tiles!r}")
    if tiles > 4 * size:
        raise ConfigError("signal.tiles", f"must be at most 4 x grid.size = {4 * size} (finer "
                          f"tiles than the grid resolves), got {tiles!r}")
    _positive(grain, "signal.grain")
    if grain > (size - 1) / 2:
        raise ConfigError("signal.grain", f"must be at most (grid.size - 1) / 2 = "
                          f"{(size - 1) / 2:g} cells (two specks across the grid), got "
                          f"{grain!r}")
    _at_least_zero(signal.noise, "signal.noise")
    if signal.noise > NOISE_MAX:
        raise ConfigError("signal.noise", f"must be at most {NOISE_MAX:g} (standard deviations "
                          f"of the data's range 0-1), got {signal.noise!r}")
    if signal.noise > 0 and signal.kind in (SignalKind.noise, SignalKind.turk):
        raise ConfigError("signal.noise", f"must be 0 with signal.kind={signal.kind.name} "
                          f"(the signal is noise itself), got {signal.noise!r}")
    if not 0 <= signal.seed <= SEED_MAX:
        raise ConfigError("signal.seed", f"must be an integer in [0, {SEED_MAX}], got "
                          f"{signal.seed}")
    flow = experiment.flow
    _positive(flow.time, "flow.time")
    if flow.steps is not None and flow.steps < 1:
        raise ConfigError("flow.steps", f"must be an integer >= 1, got {flow.steps}")
    from .flows import IMPLICIT, MAX_STEPS, HeatFlow, check_method
    from .flows._integrators import ADAPTIVE_STEPS

    if flow.steps is not None and flow.steps > MAX_STEPS:
        raise ConfigError("flow.steps", f"must be at most {MAX_STEPS}, got {flow.steps}")
    if flow.method is not None:
        extra = HeatFlow.extra_methods if flow.kind is FlowKind.heat else ()
        try:
            check_method(flow.method, extra)
        except (TypeError, ValueError) as error:
            raise ConfigError("flow.method", str(error)) from None
        if flow.method in UNCAPPED_METHODS:
            raise ConfigError("flow.method", f"{flow.method} runs scipy's integrators on the "
                              "host with no cap on their work (500 s for a 24^3 sphere that "
                              "rk4 takes in 0.1 s); use rkc, euler, heun or dopri5")
        if flow.method in IMPLICIT and flow.kind not in LINEAR_FLOWS:
            raise ConfigError("flow.method", f"{flow.method} solves a linear system each step: "
                              f"only for flow.kind {' or '.join(k.name for k in LINEAR_FLOWS)}, "
                              f"not {flow.kind.name}; use rkc, euler, heun or a torchdiffeq "
                              "method")
        if flow.steps is not None and flow.method in ADAPTIVE_STEPS:
            raise ConfigError("flow.steps", f"method {flow.method} chooses its own steps: "
                              "remove flow.steps (its tolerances are torchdiffeq's defaults)")
        if flow.kind is FlowKind.heat and flow.steps is not None:
            try:  # the flow's own refusal of steps for a method that takes none (chebyshev)
                HeatFlow(1.0, method=flow.method, steps=flow.steps)
            except ValueError as error:
                raise ConfigError("flow.steps", str(error)) from None
    allowed = FLOW_SETTINGS[flow.kind]
    for name in FLOW_DEFAULTS:
        value = getattr(flow, name)
        if value is None:
            continue
        if name not in allowed:
            listed = ", ".join(allowed) or "none besides time, time_unit, method, steps"
            raise ConfigError(f"flow.{name}", f"not a setting of flow.kind={flow.kind.name} "
                              f"(its settings: {listed})")
        if name == "p":
            if not 1 <= value <= 2:
                raise ConfigError("flow.p", f"must be in [1, 2], got {value}")
        elif name == "isotropic":
            _at_least_zero(value, "flow.isotropic")
        else:
            _positive(value, f"flow.{name}")
    unit = time_unit(flow)
    if (unit is TimeUnit.turk) != (flow.kind is FlowKind.reaction_diffusion):
        raise ConfigError("flow.time_unit", "turk is the unit of reaction_diffusion, and "
                          f"its only one; got {unit.name} with flow.kind={flow.kind.name}")
    if signal.kind not in FLOW_SIGNALS[flow.kind]:
        names = ", ".join(kind.name for kind in FLOW_SIGNALS[flow.kind])
        raise ConfigError("signal.kind", f"flow.kind={flow.kind.name} takes signal.kind "
                          f"{names}, got {signal.kind.name}")
    if flow.kind is FlowKind.color and signal.gray:
        raise ConfigError("signal.gray", "flow.kind=color needs colour data, not gray")
    needs_field = flow.kind is FlowKind.visualization or signal.kind is SignalKind.field
    if needs_field and experiment.field is None:
        raise ConfigError("field", f"flow.kind={flow.kind.name} with signal.kind="
                          f"{signal.kind.name} needs a tangent field (field: {{kind: ...}})")
    reads_field = needs_field or flow.kind is FlowKind.reaction_diffusion
    if experiment.field is not None and not reads_field:
        raise ConfigError("field", f"not read by flow.kind={flow.kind.name} with signal.kind="
                          f"{signal.kind.name} (a tangent field is read by visualization, "
                          f"reaction_diffusion and signal.kind=field); remove the section")
    if experiment.field is not None:
        _at_least_zero(experiment.field.smoothing, "field.smoothing")
        _check_field_settings_read(experiment.field)
    if experiment.field is not None and not (experiment.field.smoothing_grid == 0
                                             or experiment.field.smoothing_grid >= 8):
        raise ConfigError("field.smoothing_grid",
                          f"must be 0 or >= 8, got {experiment.field.smoothing_grid}")
    if experiment.field is not None and experiment.field.kind not in (FieldKind.axis,
                                                                      FieldKind.swirl):
        coarse = smoothing_size(experiment.grid.size, experiment.field)
        if coarse != experiment.grid.size:  # the field's smoothing builds the shape there too
            _check_margin(GridConfig(coarse, experiment.grid.margin,
                                           experiment.grid.layout),
                                f"on the {coarse}^3 grid the field's smoothing runs on "
                                f"(field.smoothing_grid={experiment.field.smoothing_grid})")
    render = experiment.render
    for key in ("width", "height"):
        if not 16 <= getattr(render, key) <= 4096:
            raise ConfigError(f"render.{key}", f"must be in [16, 4096] pixels, got "
                              f"{getattr(render, key)}")
    if not render.panels:
        raise ConfigError("render.panels", f"name at least one of {', '.join(PANELS)}")
    if len(render.panels) * render.width > PICTURE_WIDTH_MAX:
        raise ConfigError("render.width", f"{len(render.panels)} panels of {render.width} pixels "
                          f"make a picture wider than {PICTURE_WIDTH_MAX} pixels, which off-screen "
                          "rendering draws black")
    if not -90.0 <= render.elevation <= 90.0:
        raise ConfigError("render.elevation", f"must be in [-90, 90] degrees, got "
                          f"{render.elevation}")
    if not math.isfinite(render.azimuth):
        raise ConfigError("render.azimuth", f"must be a finite number of degrees, got "
                          f"{render.azimuth}")
    _check_colormap(render.colormap)
    for index, panel in enumerate(render.panels):
        if panel not in PANELS:
            raise ConfigError(f"render.panels[{index}]",
                              f"must be one of {', '.join(PANELS)}, got {panel!r}")
    if experiment.threads is not None and not 1 <= experiment.threads <= THREADS_MAX:
        raise ConfigError("threads", f"must be an integer in [1, {THREADS_MAX}], got "
                          f"{experiment.threads}")


def _check_signal_settings(signal: SignalConfig) -> None:
    """Refuse a set signal setting that ``signal.kind`` does not read, saying how to unset it."""
    allowed = SIGNAL_SETTINGS[signal.kind]
    for name in SIGNAL_DEFAULTS:
        if getattr(signal, name) is not None and name not in allowed:
            listed = ", ".join(allowed) or "none besides noise, seed"
            raise ConfigError(f"signal.{name}", f"not a setting of signal.kind="
                              f"{signal.kind.name} (its settings: {listed}); "
                              f"--set signal.{name}=null unsets it")


def _check_colormap(name: str) -> None:
    """Raise unless matplotlib (the ``render`` extra) knows the colormap ``name``; without
    matplotlib the run fails at its pictures anyway, with its own message."""
    try:
        from matplotlib import colormaps
    except ImportError:
        return
    if name not in colormaps:
        raise ConfigError("render.colormap", f"must name a matplotlib colormap (e.g. viridis, "
                          f"magma, gray), got {name!r}")


def resolve_mesh(mesh: str, folder: Path) -> Path:
    """A mesh path: as given if absolute, else against ``folder``, then ``$TORCHSURF_MESH_DIR``.

    Raises:
        ConfigError: ``surface.mesh`` is in none of them (the message lists where it looked).
    """
    path = Path(mesh).expanduser()
    candidates = [path] if path.is_absolute() else [folder / path]
    directory = os.environ.get(MESH_DIR_VARIABLE)
    if directory and not path.is_absolute():
        candidates.append(Path(directory) / path)
    for candidate in candidates:
        if candidate.is_file():
            # absolute, so the record names it wherever it is read from; the file itself not
            # resolved: a link's target may have no extension (a hub cache's blobs) to tell
            # the format, while its folder is (a "..", folded as text, left a linked folder)
            return candidate.absolute().parent.resolve() / candidate.name
    folders = [str(c) for c in candidates if c.is_dir()]
    if folders:
        raise ConfigError("surface.mesh", f"{mesh!r} is a folder ({folders[0]}), not a mesh "
                          "file: name the file in it")
    where = ", ".join(str(c) for c in candidates)
    unset = "" if directory else f" (${MESH_DIR_VARIABLE} is not set)"
    first = ("" if path.is_absolute() else
             f"; a relative path is looked for in the folder of the config that names it, "
             f"then in ${MESH_DIR_VARIABLE}; one given with --set first in the current folder, "
             f"{Path.cwd()}")
    raise ConfigError("surface.mesh", f"{mesh!r} not found; looked at {where}{unset}{first}")
