"""Several shapes on one grid, each centred and scaled to a common size, as one batch.

Meshes and analytic shapes (:mod:`torchsurf.sdf`) cannot share a batch when each has its own
grid (:func:`torchsurf.mesh.fit_grid` fits the spacing to the shape). :class:`MeshBatchAdapter`
maps every shape ``b`` to normalised coordinates ``x' = scale_b (x - centre_b)``, in which its
bounding box is centred at the origin and its longest side is ``size``; all shapes then live on
one cubic grid and their ``phi`` stack into ``(B, 1, D, H, W)``. Distances scale by
``scale_b``, so a diffusion time ``t'`` on the common grid is ``t' / scale_b^2`` in the shape's
own units (:meth:`MeshBatchAdapter.shape_time`).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import trimesh
from torch import Tensor, nn

from . import sdf
from ._checks import (
    check_count,
    check_device,
    check_dtype,
    check_like_first,
    check_loaded_shapes,
    check_module_dtype,
    check_nonnegative,
    check_positive,
    check_tensor,
    check_volume,
)
from ._mesh_input import MeshLike, as_trimesh, is_array_pair, triangle_arrays
from .grid import Grid, default_margin
from .mesh import MeshAdapter, check_adapter_band, check_decode_order, extract
from .surface import ImplicitSurface

__all__ = [
    "ANALYTIC",
    "AnalyticShape",
    "MeshBatchAdapter",
]

ANALYTIC = ("sphere", "torus", "box", "capsule", "trefoil")


def _copied(value: object) -> object:
    """``value`` with its containers and tensors copied, so that the caller's lists or tensors
    changed later do not change a checked shape: a tensor is cloned in its graph (a radius
    requiring grad still gets its gradient)."""
    if isinstance(value, Tensor):
        return value.clone()
    if isinstance(value, dict):
        return {key: _copied(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_copied(item) for item in value)
    if isinstance(value, np.ndarray):
        return value.copy()
    return value


def _values(value: object) -> object:
    """``value`` with its tensors as numpy arrays, out of any graph: the numbers of a shape's
    parameters (its bounds are numbers, not part of a gradient)."""
    if isinstance(value, Tensor):
        return value.detach().cpu().numpy()
    if isinstance(value, (list, tuple)):
        return type(value)(_values(item) for item in value)
    return value


def _requiring_grad(parameters: Mapping[str, object]) -> list[str]:
    """The names of ``parameters`` that hold a tensor requiring grad."""
    def requires(value: object) -> bool:
        if isinstance(value, Tensor):
            return value.requires_grad
        return isinstance(value, (list, tuple)) and any(requires(item) for item in value)
    return [key for key, value in parameters.items() if requires(value)]


def _trefoil_reach(parameters: Mapping[str, object]) -> np.ndarray:
    """``(2, 3)`` box of the trefoil's core curve (:func:`torchsurf.sdf.trefoil`)."""
    scale = float(parameters.get("scale", 0.4))
    t = np.linspace(0, 2 * math.pi, 4097)
    curve = scale * np.stack((np.sin(t) + 2 * np.sin(2 * t), np.cos(t) - 2 * np.cos(2 * t),
                              -np.sin(3 * t)), axis=1)
    return np.stack((curve.min(axis=0), curve.max(axis=0)))


@dataclass(frozen=True)
class AnalyticShape:
    """An analytic shape of :mod:`torchsurf.sdf`, by function name and keyword arguments.

    Args:
        name: ``"sphere"``, ``"torus"``, ``"box"``, ``"capsule"`` or ``"trefoil"``.
        parameters: keyword arguments of that function other than ``grid``, ``dtype`` and
            ``device`` (e.g. ``{"major_radius": 1.0, "minor_radius": 0.3}``), world units.

    Example:
        >>> AnalyticShape("torus", {"minor_radius": 0.3}).bounds()[1]
        array([1.3, 1.3, 0.3])
    """

    name: str
    parameters: Mapping[str, object] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        if not isinstance(self.parameters, Mapping):
            raise TypeError(f"parameters must be a mapping of keyword arguments, got "
                            f"{type(self.parameters).__name__}")
        object.__setattr__(self, "parameters", _copied(dict(self.parameters)))
        if self.name not in ANALYTIC:
            raise ValueError(f"name must be one of {ANALYTIC}, got {self.name!r}")
        for key in ("grid", "dtype", "device"):
            if key in self.parameters:
                raise ValueError(f"parameters must not hold {key!r}: the batch chooses it")
        accepted = set(inspect.signature(getattr(sdf, self.name)).parameters) - {
            "grid", "dtype", "device"}
        for key in self.parameters:
            if key not in accepted:
                raise ValueError(f"parameters: torchsurf.sdf.{self.name} takes "
                                 f"{sorted(accepted)}, not {key!r}")
        try:  # the function's own checks, on the smallest grid
            getattr(sdf, self.name)(Grid.cube(3, bound=1.0), **self.parameters)
        except (TypeError, ValueError) as error:
            raise type(error)(f"parameters of {self.name!r}: {error}") from error

    def phi(self, grid: Grid, dtype: torch.dtype | None = None,
            device: torch.device | str | None = None) -> Tensor:
        """The exact signed distance on ``grid`` (the shape's own units), ``(1, 1, D, H, W)``."""
        return getattr(sdf, self.name)(grid, dtype=dtype, device=device, **self.parameters)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The bounding box ``(low, high)``, world ``(x, y, z)`` arrays ``(3,)``."""
        p = {key: _values(value) for key, value in self.parameters.items()}
        centre = np.asarray(p.get("center", (0.0, 0.0, 0.0)), dtype=np.float64)
        if self.name == "sphere":
            reach = np.full(3, float(p.get("radius", 1.0)))
        elif self.name == "torus":
            major, minor = float(p.get("major_radius", 1.0)), float(p.get("minor_radius", 0.4))
            reach = np.array([major + minor, major + minor, minor])
        elif self.name == "box":
            reach = np.asarray(p.get("half_size", (0.5, 0.5, 0.5)), dtype=np.float64)
        elif self.name == "capsule":
            ends = np.array([p.get("start", (0.0, 0.0, -0.5)), p.get("end", (0.0, 0.0, 0.5))],
                            dtype=np.float64)
            radius = float(p.get("radius", 0.4))
            return ends.min(axis=0) - radius, ends.max(axis=0) + radius
        else:
            low, high = _trefoil_reach(p)
            tube = float(p.get("tube_radius", 0.12))
            return centre + low - tube, centre + high + tube
        return centre - reach, centre + reach


Shape = MeshLike | AnalyticShape


def _surface_of_loaded_phi(adapter: MeshBatchAdapter, incompatible: object) -> None:
    """After ``load_state_dict`` (its surface's own state loaded too): the surface of the
    loaded ``phi`` buffer on the loaded grid, built on the buffer, so that ``adapter.phi`` and
    its surface stay one."""
    adapter.grid = adapter.surface.grid
    adapter.surface = ImplicitSurface(adapter.phi, adapter.grid)


class MeshBatchAdapter(nn.Module):
    """Several meshes and analytic shapes on one grid, normalised, with their vertex data.

    Shape ``b`` is moved to normalised coordinates ``x' = scale_b (x - centre_b)``: its
    bounding box centred at the origin, its longest side ``size``. The common grid is
    ``Grid.cube(resolution, bound=size (1 + 2 margin) / 2)``. A mesh gets a
    :class:`~torchsurf.mesh.MeshAdapter` there (its ``phi``, the band, encode and decode, of
    ``order``); an analytic shape gets its exact ``phi`` (:class:`AnalyticShape`), and as
    vertices those of the marching-cubes mesh of that ``phi`` (:func:`torchsurf.mesh.extract`),
    whose adapter moves its vertex data.

    Args:
        shapes: a sequence of meshes (as in :func:`torchsurf.mesh.load`) and
            :class:`AnalyticShape`.
        resolution: nodes per axis of the common grid.
        size: longest side of every shape's box, normalised units.
        margin: free space on each side of the box, fraction of ``size``. ``None``: 15%, and
            at least :data:`~torchsurf.grid.MIN_MARGIN_CELLS` cells
            (:func:`~torchsurf.grid.default_margin`; wider than 15% below 27 nodes).
        band_width: half-width of the band the adapters fill, normalised units (default
            ``5 * spacing``).
        dtype, device: of the tensors (default dtype, CPU).
        order: decoding of the adapters, see :class:`~torchsurf.mesh.MeshAdapter`.

    Attributes:
        grid: the common grid.
        phi: ``(B, 1, D, H, W)``, normalised units, negative inside.
        surface: the :class:`~torchsurf.ImplicitSurface` of the batch (default band).
        scale: ``(B,)`` float64, the factor from a shape's own units to normalised units.
        centre: ``(B, 3)`` float64, the box centre of each shape in its own units.
        vertices: list of ``B`` tensors ``(V_b, 3)``, normalised coordinates.
        adapters: ``nn.ModuleList`` of the ``B`` :class:`~torchsurf.mesh.MeshAdapter`.

    Example:
        >>> batch = MeshBatchAdapter([trimesh.creation.icosphere(),
        ...                           AnalyticShape("torus", {"minor_radius": 0.3})],
        ...                          resolution=33)
        >>> batch.phi.shape
        torch.Size([2, 1, 33, 33, 33])
        >>> values = [v[:, :1] for v in batch.vertices]          # x of every vertex, (V_b, 1)
        >>> [d.shape[1] for d in batch.decode(batch.encode(values))]
        [1, 1]
    """

    phi: Tensor
    scale: Tensor
    centre: Tensor

    def __init__(
        self,
        shapes: Sequence[Shape],
        resolution: int = 64,
        size: float = 1.0,
        margin: float | None = None,
        band_width: float | None = None,
        dtype: torch.dtype | None = None,
        device: torch.device | str | None = None,
        order: int = 2,
    ) -> None:
        super().__init__()
        if isinstance(shapes, (str, AnalyticShape, trimesh.Trimesh)) or not isinstance(
            shapes, Sequence
        ):
            raise TypeError(
                "shapes must be a sequence (list or tuple) of meshes and AnalyticShape, got "
                f"{type(shapes).__name__}"
            )
        if len(shapes) == 0:
            raise ValueError("shapes must hold at least one shape, got an empty sequence")
        if is_array_pair(shapes):
            raise TypeError("shapes is one pair (vertices, faces), read as two shapes: give a "
                            "sequence of shapes, [(vertices, faces)] for one mesh")
        resolution = check_count(resolution, "resolution", minimum=3)
        size = check_positive(size, "size")
        margin = (default_margin(resolution, 0.15) if margin is None
                  else check_nonnegative(margin, "margin"))
        dtype = check_dtype(dtype)
        device = check_device(device)
        order = check_decode_order(order)
        self.grid = Grid.cube(resolution, bound=0.5 * size * (1.0 + 2.0 * margin))
        if band_width is not None:
            check_adapter_band(sdf._band(self.grid, band_width, clamps=False),
                               self.grid.spacing)
        phis, scales, centres, adapters = [], [], [], []
        for index, shape in enumerate(shapes):
            name = f"shapes[{index}]"
            if isinstance(shape, AnalyticShape):
                learned = _requiring_grad(shape.parameters)
                if learned:
                    raise ValueError(
                        f"{name}: parameters {learned} require grad, but the batch normalises "
                        f"each shape (its scale and centre) from their values outside autograd, "
                        f"so gradients to them would be wrong (a sphere's radius: -0.625 where "
                        f"the normalised sphere does not depend on it); pass detached values, "
                        f"or call torchsurf.sdf.{shape.name}(grid, ...) for a phi "
                        f"differentiable in them")
                low, high = shape.bounds()
            else:
                mesh = as_trimesh(shape, name)
                vertices, faces = triangle_arrays(mesh)
                used = vertices[np.unique(faces)]
                low, high = used.min(axis=0), used.max(axis=0)
            longest = float((high - low).max())
            if longest == 0:
                raise ValueError(f"{name}: its bounding box has no extent")
            scale, centre = size / longest, (low + high) / 2
            try:
                if isinstance(shape, AnalyticShape):
                    own = Grid(self.grid.shape, self.grid.spacing / scale,
                               tuple(float(c) for c in centre + np.asarray(self.grid.origin) / scale))
                    phi = scale * shape.phi(own, dtype=torch.float64)
                    try:
                        mesh = extract(phi, self.grid)
                    except ValueError as error:
                        raise ValueError(
                            f"{shape.name} {dict(shape.parameters)} is not resolved by this "
                            f"grid of {resolution} nodes a side: {error}; raise resolution"
                        ) from error
                    phi = phi.to(dtype=dtype, device=device)
                else:
                    mesh = trimesh.Trimesh(scale * (vertices - centre), faces, process=False)
                    phi = None
                adapter = MeshAdapter(mesh, self.grid, band_width=band_width, dtype=dtype,
                                      device=device, order=order)
            except ValueError as error:
                raise ValueError(f"{name}: {error}") from error
            phis.append(adapter.phi if phi is None else phi)
            scales.append(scale)
            centres.append(centre)
            adapters.append(adapter)
        self.adapters = nn.ModuleList(adapters)
        self.register_buffer("phi", torch.cat(phis))
        self.register_buffer("scale", torch.tensor(scales, dtype=torch.float64))
        self.register_buffer("centre", torch.as_tensor(np.stack(centres), dtype=torch.float64))
        self.surface = ImplicitSurface(self.phi, self.grid)
        self.register_load_state_dict_post_hook(_surface_of_loaded_phi)

    def _apply(self, fn, recurse=True):  # noqa: ANN001, ANN202
        # .float() / .half() convert floating buffers: the conversions stay float64 (documented),
        # their values too (converted and back, .half() moved them by 2.4e-4), on the new device
        scale, centre = self.scale, self.centre
        result = super()._apply(fn, recurse)
        device = self.scale.device
        self.scale, self.centre = scale.to(device), centre.to(device)
        if self.surface.phi.dtype == self.phi.dtype:  # each moved its own copy: one phi again
            self.phi = self.surface.phi  # (.half() leaves the surface float32, warning)
        return result

    def __len__(self) -> int:
        return len(self.adapters)

    @property
    def vertices(self) -> list[Tensor]:
        """The vertices of every shape, ``(V_b, 3)`` normalised ``(x, y, z)``."""
        return [adapter.vertices for adapter in self.adapters]

    def encode(self, values: Sequence[Tensor]) -> Tensor:
        """Per-vertex values of every shape -> the batch volume.

        Args:
            values: ``B`` tensors ``(V_b, C)``, the same ``C`` and dtype for all.

        Returns:
            ``(B, C, D, H, W)``: entry ``b`` is shape ``b``'s values in its band
            (:meth:`MeshAdapter.encode`), 0 beyond.
        """
        if isinstance(values, Tensor) or len(values) != len(self):
            raise ValueError(
                f"values must be a sequence of {len(self)} tensors (V_b, C), one per shape, "
                f"got {type(values).__name__}"
                + ("" if isinstance(values, Tensor) else f" of length {len(values)}")
            )
        volumes = []
        for b, (entry, adapter) in enumerate(zip(values, self.adapters, strict=True)):
            count = len(adapter.vertices)
            check_tensor(entry, f"values[{b}]")
            if entry.dim() != 2 or entry.shape[0] != count or entry.shape[1] == 0:
                raise ValueError(f"values[{b}] must have shape ({count}, C), C at least 1, got "
                                 f"{tuple(entry.shape)}")
            check_like_first(entry, values[0], f"values[{b}]", "values[0]")
            check_module_dtype(entry, f"values[{b}]", adapter.vertices, "adapter")
            volumes.append(adapter.encode(entry.T[None]))
        return torch.cat(volumes)

    def decode(self, volume: Tensor) -> list[Tensor]:
        """The batch volume ``(B, C, D, H, W)`` -> ``B`` tensors ``(V_b, C)`` at the vertices."""
        check_volume(volume, "volume")
        if volume.shape[0] != len(self):
            raise ValueError(
                f"volume must hold the {len(self)} shapes in its batch, got shape "
                f"{tuple(volume.shape)}"
            )
        return [adapter.decode(volume[b:b + 1])[0].T
                for b, adapter in enumerate(self.adapters)]

    def forward(self, values: Sequence[Tensor]) -> Tensor:
        """:meth:`encode`: ``B`` tensors ``(V_b, C)`` -> the batch volume ``(B, C, D, H, W)``,
        as :class:`MeshAdapter` is called."""
        return self.encode(values)

    def shape_time(self, time: float) -> Tensor:
        """A diffusion time on the common grid in every shape's own units, ``(B,)`` float64:
        ``time / scale_b^2`` (times are lengths squared)."""
        return check_nonnegative(time, "time") / self.scale**2

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: object,
                              **kwargs: object) -> None:
        check_loaded_shapes(self, state_dict, prefix)  # before the surface takes another mesh
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return f"shapes={len(self)}, grid={self.grid.shape}, spacing={self.grid.spacing:g}"
