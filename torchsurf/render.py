"""Pictures of data on a surface: marching cubes, values sampled at the vertices, panels side by
side, drawn off screen by pyvista when it is installed, by matplotlib otherwise
(``pip install torchsurf[render]`` installs both).

The surface is extracted once (:func:`torchsurf.mesh.extract`), each volume is sampled at its
vertices (:func:`torchsurf.sample`), and every panel is drawn with the same camera, fitted to the
shape: an orthographic view from ``elevation`` and ``azimuth`` degrees. pyvista (VTK, off screen
through EGL or OSMesa when there is no display) draws with a depth buffer and smooth shading;
matplotlib, the fallback, culls back faces and paints the triangles far to near with Lambert
shading (faces in front of one another can be mis-ordered). :func:`resolve_renderer` says which
one ``"auto"`` takes and why. PNGs are written to a temporary file in the target folder and
renamed into place, so a reader never sees half a picture.
"""

from __future__ import annotations

import functools
import importlib.util
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from torch import Tensor

from ._checks import check_entry, check_spatial_shape, check_volume
from .grid import Grid
from .sampling import sample
from .surface import ImplicitSurface

__all__ = [
    "AXES",
    "Camera",
    "FILE_MODE",
    "FLAT_SPAN",
    "MODES",
    "PICTURE_WIDTH_MAX",
    "RENDERERS",
    "ROUNDING_SPAN",
    "colours",
    "fit_camera",
    "render_panels",
    "resolve_renderer",
    "vertex_values",
    "write_png",
]

AXES = ("x", "y", "z")
MODES = ("scalar", "rgb", "field")
_UMASK = os.umask(0)
os.umask(_UMASK)
FILE_MODE = 0o666 & ~_UMASK
"""Permissions of the files written (those of ``open``): ``mkstemp``'s own 0600 would hide
the pictures from everyone else."""
RENDERERS = ("auto", "pyvista", "matplotlib")
"""Values of ``renderer``: ``"auto"`` is pyvista when it can draw off screen, else matplotlib."""

PICTURE_WIDTH_MAX = 16384
"""Pixels a side of the largest picture :func:`render_panels` draws: off-screen VTK drew
wider ones black (16500 pixels wide), so both renderers refuse them."""


def _matplotlib():  # noqa: ANN202
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.collections import PolyCollection
        from matplotlib.figure import Figure
    except ImportError as error:
        raise ImportError(
            "torchsurf.render draws with matplotlib, an optional dependency: "
            "pip install 'torchsurf[render]' (or pip install matplotlib)"
        ) from error
    return Figure, FigureCanvasAgg, PolyCollection


def vertex_values(volume: Tensor, mesh: trimesh.Trimesh, grid: Grid | ImplicitSurface,
                  entry: int | None = None) -> np.ndarray:
    """``volume`` sampled trilinearly at ``mesh``'s vertices: ``(V, C)`` float64.

    Args:
        volume: ``(B, C, D, H, W)`` on ``grid``, or packed ``(N, C, 8, 8, 8)`` when ``grid`` is
            a :class:`~torchsurf.bricks.BrickSurface`.
        mesh: vertices in world units, inside the box (on bricks, within the stored nodes).
        grid: the volume's grid, or the surface that holds it.
        entry: the batch entry the mesh belongs to (``volume[entry]``, or the brick surface's
            shape ``entry``); ``None`` when there is only one.
    """
    if not isinstance(grid, (Grid, ImplicitSurface)):
        raise TypeError(f"grid must be a torchsurf.Grid or the surface holding the volume, got "
                        f"{type(grid).__name__}")
    vertices = np.asarray(getattr(mesh, "vertices", None))
    if vertices.ndim != 2 or vertices.shape[1:] != (3,) or vertices.dtype.kind not in "fiu":
        raise TypeError(f"mesh must be a trimesh.Trimesh (or hold .vertices (V, 3)), got "
                        f"{type(mesh).__name__}")
    packed = isinstance(grid, ImplicitSurface) and grid.layout is not None
    if packed:
        grid.check_field(volume, "volume")
    else:
        check_volume(volume, "volume")
    count = grid.batch_size if packed else volume.shape[0]
    if entry is None:
        if count != 1:
            what = (f"the surface holds {count} shapes" if packed else
                    f"volume holds {count} volumes, shape {tuple(volume.shape)}")
            raise ValueError(f"{what}: give entry, the one the mesh belongs to")
        entry = 0
    entry = check_entry(entry, count)
    box = (grid.grids[entry] if packed else grid if isinstance(grid, Grid) else grid.grid)
    if not packed:
        check_spatial_shape(volume, "volume", box.shape, "grid")
    # world to node indices in float64, then the volume's dtype: a grid far from the origin
    # keeps the precision of its cells (1e5 away, float32 world points are off 0.06 cell)
    vertices = torch.as_tensor(vertices, dtype=torch.float64)
    outside = ~box.contains(vertices, tolerance=1e-4)
    if bool(outside.any()):
        first = int(outside.nonzero()[0, 0])
        high = tuple(o + s for o, s in zip(box.origin, box.size, strict=True))
        raise ValueError(
            f"mesh: {int(outside.sum())} of {len(vertices)} vertices lie outside the grid's box "
            f"{box.origin} to {high}, e.g. vertex {first} at {vertices[first].tolist()}"
        )
    index = box.world_to_index(vertices).to(volume.dtype).to(volume.device)
    if packed:
        try:
            values = grid.sample_at_index(volume.detach(), index, entry)
        except ValueError as error:  # the sampler names its points, not the mesh
            raise ValueError(f"mesh: its vertices are read on the bricks of entry {entry}, and "
                             f"{error}") from error
    else:
        at_zero = Grid(box.shape, 1.0, (0.0, 0.0, 0.0))  # node indices as world points
        values = sample(volume[entry:entry + 1].detach(), index, at_zero)[0]
    return values.T.to("cpu", torch.float64).numpy()


ROUNDING_SPAN = 1e-6
"""Values spread by at most this, relative to their magnitude, are one constant carrying float32
rounding (a few units of 1.2e-7): equalized, they take the map's middle colour (their ranks
spread one ulp over the whole map); a wider spread is a pattern, and equalized."""

FLAT_SPAN = 1e-4
"""Default limits closer than this, relative to their magnitude, are widened to it about their
middle: float32 rounding spreads a constant by about 1e-7 of it (a float32 constant read at a
torus's vertices: 1.7e-7), which the map would otherwise stretch over all its colours; widened
to 1e-6, such vertices still took 0.46 and 0.63 of a grey map (a few thousandths now)."""


def colours(values: np.ndarray, mode: str = "scalar", colormap: str = "viridis",
            limits: tuple[float, float] | None = None, equalize: bool = False) -> np.ndarray:
    """Per-vertex RGB ``(V, 3)`` in ``[0, 1]`` from values ``(V, C)``.

    ``"scalar"`` (C = 1): ``colormap`` over ``limits`` (default the 1st and 99th percentiles),
    or, with ``equalize``, over each value's rank among the vertices (histogram equalisation:
    every colour of the map is used equally often, which shows the streaks of a flow
    visualisation whose values cluster near their mean); ``"rgb"`` (C = 3): clipped to
    ``[0, 1]``; ``"field"`` (C = 3, unit vectors up to sign): ``|T_x|, |T_y|, |T_z|``; a vertex
    with a NaN component is grey in both (a field undefined on an axis). In the
    scalar modes, NaN or infinite values are grey and do not set the limits; equal values
    share a colour, and default limits closer than :data:`FLAT_SPAN` of their magnitude are
    widened to it about their middle (a constant, or one carrying float32 rounding, takes the
    map's middle colour; equalized, a spread within :data:`ROUNDING_SPAN` does; a few
    vertices off it, the map's ends).
    ``limits``: ``(low, high)``, finite, ``low < high``.
    """
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    values = np.asarray(values, dtype=np.float64)
    channels = 1 if mode == "scalar" else 3
    if values.ndim != 2 or values.shape[1] != channels:
        raise ValueError(f"mode={mode!r} needs values of shape (V, {channels}), got "
                         f"{values.shape}")
    if mode in ("rgb", "field"):  # a vertex with a NaN component is grey, as in the scalar modes
        rgb = np.clip(np.abs(values) if mode == "field" else values, 0.0, 1.0)
        rgb[np.isnan(values).any(axis=1)] = 0.5
        return rgb
    Figure, _, _ = _matplotlib()
    from matplotlib import colormaps

    if colormap not in colormaps:
        raise ValueError(f"colormap must name a matplotlib colormap (e.g. 'viridis'), got "
                         f"{colormap!r}")
    if equalize and limits is not None:
        raise ValueError("give limits or equalize=True, not both")
    if limits is not None:
        if isinstance(limits, torch.Tensor):
            limits = limits.detach().cpu().numpy()
        bounds = np.asarray(limits, dtype=np.float64)
        if bounds.shape != (2,) or not np.isfinite(bounds).all() or not bounds[0] < bounds[1]:
            raise ValueError(f"limits must be two finite numbers (low, high) with low < high, "
                             f"got {limits!r}")
    missing = ~np.isfinite(values[:, 0])  # grey, and left out of the limits
    finite = values[~missing, 0]
    if equalize:
        # equal values share the mean of their ranks, so that they share a colour
        _, inverse, counts = np.unique(finite, return_inverse=True, return_counts=True)
        mean_rank = np.cumsum(counts) - 0.5 * (counts + 1)
        scaled = np.zeros(len(values))
        # a constant (to ROUNDING_SPAN of its magnitude: float32 rounding): the map's middle
        # colour, as for default limits
        largest = float(np.abs(finite).max(initial=0.0))
        # in units of the largest magnitude: a spread near the float's range does not overflow
        spread = float(np.ptp(finite / largest)) if largest > 0 else 0.0
        flat = spread <= ROUNDING_SPAN
        scaled[~missing] = 0.5 if flat else mean_rank[inverse] / (len(finite) - 1)
    else:
        low, high = (bounds if limits is not None else
                     np.percentile(finite, [1.0, 99.0]) if len(finite) else (0.0, 1.0))
        # in units of the limits' magnitude: values near the float's range do not overflow
        magnitude = max(abs(float(low)), abs(float(high)), np.finfo(np.float64).tiny)
        low, high = low / magnitude, high / magnitude
        middle, span = low / 2 + high / 2, high - low
        if limits is None:
            span = max(span, FLAT_SPAN)
        with np.errstate(invalid="ignore", over="ignore"):
            scaled = 0.5 + (values[:, 0] / magnitude - middle) / span
        missing |= np.isnan(scaled)  # an overflow beyond the limits is their end's colour
    rgb = colormaps[colormap](np.clip(np.where(missing, 0.0, scaled), 0.0, 1.0))[:, :3]
    rgb[missing] = 0.5
    return rgb


@dataclass(frozen=True)
class Camera:
    """An orthographic view: unit ``right``, ``up`` and ``towards`` (from the shape to the
    viewer) world vectors ``(3,)``, and the visible window ``(x0, x1, y0, y1)`` on screen."""

    right: np.ndarray
    up: np.ndarray
    towards: np.ndarray
    window: tuple[float, float, float, float]

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Screen ``(N, 2)`` and depth ``(N,)`` (larger is nearer) of world points ``(N, 3)``."""
        return np.stack((points @ self.right, points @ self.up), axis=1), points @ self.towards


def fit_camera(vertices: np.ndarray, elevation: float = 25.0, azimuth: float = -60.0,
               up: str = "z", aspect: float = 1.0, margin: float = 0.08) -> Camera:
    """The camera seeing all of ``vertices`` ``(V, 3)`` from ``elevation``, ``azimuth``
    (degrees; azimuth 0 looks from the axis after ``up`` in x, y, z order), ``up`` an axis
    name, the window of ``aspect`` (width / height) with ``margin`` free on each side."""
    if up not in AXES:
        raise ValueError(f"up must be one of {AXES}, got {up!r}")
    if not -90.0 <= elevation <= 90.0:
        raise ValueError(f"elevation must be in [-90, 90] degrees, got {elevation!r}")
    if not math.isfinite(azimuth):
        raise ValueError(f"azimuth must be a finite number of degrees, got {azimuth!r}")
    if np.shape(vertices)[-1:] != (3,) or np.size(vertices) == 0:
        raise ValueError(f"vertices must have shape (V, 3) with V >= 1, got {np.shape(vertices)}")
    k = AXES.index(up)
    axis_up = np.eye(3)[k]
    front = np.eye(3)[(k + 1) % 3]
    side = np.cross(axis_up, front)
    el, az = math.radians(elevation), math.radians(azimuth)
    towards = math.cos(el) * (math.cos(az) * front + math.sin(az) * side) + math.sin(el) * axis_up
    right = np.cross(axis_up, towards)
    right = right / np.linalg.norm(right) if np.linalg.norm(right) > 1e-9 else side
    screen_up = np.cross(towards, right)
    camera = Camera(right, screen_up, towards, (0.0, 1.0, 0.0, 1.0))
    screen, _ = camera.project(np.asarray(vertices, dtype=np.float64))
    low, high = screen.min(axis=0), screen.max(axis=0)
    centre = 0.5 * (low + high)
    half = 0.5 * (high - low) * (1.0 + 2.0 * margin)
    half_width = max(half[0], half[1] * aspect, 1e-12)
    half_height = half_width / aspect
    window = (centre[0] - half_width, centre[0] + half_width,
              centre[1] - half_height, centre[1] + half_height)
    return Camera(right, screen_up, towards, tuple(float(w) for w in window))


def _draw(axes, mesh: trimesh.Trimesh, vertex_colours: np.ndarray, camera: Camera,
          poly_collection) -> None:  # noqa: ANN001
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    corners = vertices[faces]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normals, axis=1)
    normals = normals / np.where(length > 0, length, 1.0)[:, None]
    facing = normals @ camera.towards
    keep = facing > 0
    screen, depth = camera.project(vertices)
    order = np.argsort(depth[faces[keep]].mean(axis=1))
    kept = faces[keep][order]
    light = camera.towards + 0.5 * camera.up + 0.3 * camera.right
    light = light / np.linalg.norm(light)
    shade = 0.35 + 0.65 * np.clip(normals[keep][order] @ light, 0.0, 1.0)
    face_colours = vertex_colours[kept].mean(axis=1) * shade[:, None]
    collection = poly_collection(screen[kept], facecolors=np.clip(face_colours, 0.0, 1.0),
                                 edgecolors="none", antialiased=False)
    axes.add_collection(collection)
    axes.set_xlim(camera.window[0], camera.window[1])
    axes.set_ylim(camera.window[2], camera.window[3])
    axes.set_aspect("equal")
    axes.set_axis_off()


def _pyvista():  # noqa: ANN202
    if not os.environ.get("DISPLAY"):
        # without an X server, VTK tries X first and logs an error before its EGL fallback
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista

    return pyvista


@functools.cache
def _pyvista_problem() -> str | None:
    """Why pyvista cannot draw off screen here (``None``: it can), probed once per process."""
    if importlib.util.find_spec("pyvista") is None:
        return "pyvista is not installed"
    try:
        pyvista = _pyvista()
        plotter = pyvista.Plotter(off_screen=True, window_size=(16, 16))
        try:
            plotter.add_mesh(pyvista.Sphere())
            plotter.screenshot(return_img=True)
        finally:
            plotter.close()
    except Exception as error:  # VTK reports a missing OpenGL context in many ways
        return f"pyvista could not draw off screen ({type(error).__name__}: {error})"
    return None


def resolve_renderer(renderer: str = "auto") -> tuple[str, str]:
    """The renderer ``renderer`` names, and why: ``("pyvista" or "matplotlib", reason)``.

    ``"auto"`` takes pyvista when it is installed and draws off screen (probed once per
    process with a 16-pixel picture), matplotlib otherwise; the reason says which held.

    Raises:
        ValueError: ``renderer`` is not one of :data:`RENDERERS`.
        ImportError: ``"pyvista"`` asked for and unusable (the message says why).
    """
    if renderer not in RENDERERS:
        raise ValueError(f"renderer must be one of {RENDERERS}, got {renderer!r}")
    if renderer == "matplotlib":
        return "matplotlib", "asked for"
    problem = _pyvista_problem()
    if problem is None:
        return "pyvista", "off screen" if renderer == "pyvista" else "installed, off screen"
    if renderer == "pyvista":
        raise ImportError(f"renderer='pyvista': {problem}; pip install 'torchsurf[render]', "
                          "or use renderer='matplotlib'")
    return "matplotlib", f"fallback: {problem}"


def _pyvista_image(mesh: trimesh.Trimesh, panels: list[tuple[str, np.ndarray]],
                   camera: Camera, width: int, height: int) -> np.ndarray:
    """The panels drawn by pyvista side by side: an RGB image ``(height, count * width, 3)``."""
    pyvista = _pyvista()
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces)
    cells = np.hstack((np.full((len(faces), 1), 3), faces)).ravel()
    normals = _vertex_normals(vertices, faces)
    x0, x1, y0, y1 = camera.window
    depth = float((vertices @ camera.towards).max())
    extent = float(np.ptp(vertices @ camera.towards)) + (x1 - x0)
    centre = 0.5 * (x0 + x1) * camera.right + 0.5 * (y0 + y1) * camera.up + depth * camera.towards
    plotter = pyvista.Plotter(off_screen=True, shape=(1, len(panels)), border=False,
                              window_size=(len(panels) * width, height))
    try:
        for index, (title, vertex_colours) in enumerate(panels):
            plotter.subplot(0, index)
            plotter.set_background("white")
            surface = pyvista.PolyData(vertices, cells)
            surface.point_data["colours"] = np.round(255 * np.clip(vertex_colours, 0, 1)).astype(
                np.uint8)
            # the faces' own winding gives the normals: VTK's smooth shading would re-orient
            # them by walking edges, which flips patches where S touches itself at a node
            surface.point_data["normals"] = normals
            surface.point_data.active_normals_name = "normals"
            plotter.add_mesh(surface, scalars="colours", rgb=True, interpolation="phong",
                             show_scalar_bar=False)
            plotter.add_text(title, position="upper_edge", color="black",
                             font_size=_fitted_points(title, width, max(6, min(11, height // 40))))
            plotter.camera.focal_point = tuple(centre - extent * camera.towards)
            plotter.camera.position = tuple(centre + extent * camera.towards)
            plotter.camera.up = tuple(camera.up)
            plotter.camera.parallel_projection = True
            plotter.camera.parallel_scale = 0.5 * (y1 - y0)
            plotter.camera.clipping_range = (1e-3 * extent, 4.0 * extent)
        return plotter.screenshot(return_img=True)[..., :3]
    finally:
        plotter.close()


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals ``(V, 3)`` at the vertices, from the faces' winding: trimesh's (weighted
    by each face's angle at the vertex), on the vertices scaled to a unit box first. trimesh
    takes no face below an absolute area of 1e-13: a shape of cells under about 3e-7 world
    units came out with every normal zero, drawn black."""
    low, high = vertices.min(axis=0), vertices.max(axis=0)
    size = float((high - low).max())
    scaled = (vertices - low) / (size if size > 0 else 1.0)
    return np.asarray(trimesh.Trimesh(scaled, faces, process=False).vertex_normals)


def render_panels(mesh: trimesh.Trimesh, panels: list[tuple[str, np.ndarray]], path: str | Path,
                  width: int = 400, height: int = 400, elevation: float = 25.0,
                  azimuth: float = -60.0, up: str = "z", renderer: str = "auto") -> Path:
    """Draw ``mesh`` once per panel, side by side, and write a PNG atomically.

    Args:
        mesh: the surface (e.g. :func:`torchsurf.mesh.extract`), outward normals.
        panels: ``(title, vertex colours (V, 3) in [0, 1])`` for each panel, left to right.
        path: the PNG's path, ending in ``.png`` or with no suffix (another, such as
            ``.jpg``, raises ``ValueError``: the bytes would be a PNG's); its folder is created.
        width, height: pixels of one panel (the picture is ``len(panels) * width`` by
            ``height``).
        elevation, azimuth, up: the view (:func:`fit_camera`).
        renderer: one of :data:`RENDERERS` (:func:`resolve_renderer`).

    Returns:
        The path written.
    """
    for name, pixels in (("width", width), ("height", height)):
        if isinstance(pixels, bool) or not isinstance(pixels, (int, np.integer)) or pixels < 1:
            raise ValueError(f"{name} must be a positive whole number of pixels, got {pixels!r}")
    if not panels:
        raise ValueError("panels: give at least one (title, colours) pair")
    if len(panels) * int(width) > PICTURE_WIDTH_MAX or int(height) > PICTURE_WIDTH_MAX:
        raise ValueError(f"width, height: {len(panels)} panels of {width} x {height} pixels make "
                         f"a picture beyond {PICTURE_WIDTH_MAX} pixels a side, which off-screen "
                         "rendering draws black")
    if len(mesh.vertices) == 0:
        raise ValueError("mesh has no vertices: nothing to draw")
    finite = np.isfinite(np.asarray(mesh.vertices, dtype=np.float64)).all(axis=1)
    if not finite.all():
        raise ValueError(f"mesh has {int((~finite).sum())} of {len(finite)} vertices that are "
                         f"NaN or infinite, e.g. vertex {int(np.flatnonzero(~finite)[0])}")
    if Path(path).suffix.lower() not in ("", ".png"):
        raise ValueError(f"path {str(path)!r}: the picture is a PNG, give a path ending in "
                         f".png (or with no suffix), not {Path(path).suffix!r}")
    used, _ = resolve_renderer(renderer)
    Figure, FigureCanvasAgg, PolyCollection = _matplotlib()
    for index, (_, vertex_colours) in enumerate(panels):
        if np.shape(vertex_colours) != (len(mesh.vertices), 3):
            raise ValueError(f"panels[{index}]: colours must have shape (V, 3) = "
                             f"({len(mesh.vertices)}, 3), got {np.shape(vertex_colours)}")
        rgb = np.asarray(vertex_colours, dtype=np.float64)
        outside = ~((rgb >= 0.0) & (rgb <= 1.0))  # NaN too
        if outside.any():
            raise ValueError(f"panels[{index}]: colours must lie in [0, 1] (as render.colours "
                             f"gives them), got {int(outside.sum())} outside, e.g. "
                             f"{float(rgb[outside][0]):g}")
    width, height = int(width), int(height)
    panels = [(title, np.asarray(c, dtype=np.float64)) for title, c in panels]
    count = len(panels)
    dpi = 100
    figure = Figure(figsize=(count * width / dpi, height / dpi), dpi=dpi, facecolor="white")
    FigureCanvasAgg(figure)
    camera = fit_camera(np.asarray(mesh.vertices), elevation, azimuth, up, aspect=width / height)
    if used == "pyvista":
        figure.figimage(_pyvista_image(mesh, panels, camera, width, height))
        return write_png(figure, path)
    for index, (title, vertex_colours) in enumerate(panels):
        axes = figure.add_axes((index / count, 0.0, 1.0 / count, 1.0))
        _draw(axes, mesh, vertex_colours, camera, PolyCollection)
        axes.text(0.5, 0.98, title, transform=axes.transAxes, ha="center", va="top",
                  fontsize=_fitted_points(title, width, max(7, min(12, height // 30)), dpi))
    return write_png(figure, path)


def _fitted_points(title: str, width: int, points: float, dpi: int = 100) -> float:
    """A panel title's font size: ``points``, or less where the title (about 0.6 em a
    character) would span more than 95% of the panel's ``width`` pixels; at least 5 points."""
    by_width = 0.95 * width * 72.0 / (0.6 * dpi * max(1, len(title)))
    return max(5.0, min(float(points), by_width))


def write_png(figure, path: str | Path) -> Path:  # noqa: ANN001
    """Save a matplotlib figure as PNG to a temporary file beside ``path``, then rename it
    into place (``os.replace``: atomic on one file system)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".png")
    try:
        with os.fdopen(handle, "wb") as stream:
            figure.savefig(stream, format="png", dpi=figure.dpi)
            os.fchmod(stream.fileno(), FILE_MODE)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path
