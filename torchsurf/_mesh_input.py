"""Turn what a user calls a mesh (a ``trimesh.Trimesh``, a file, or arrays) into a checked one."""

from __future__ import annotations

import math
import os
import warnings

import numpy as np
import torch
import trimesh

from ._stack import caller_stacklevel

MeshLike = trimesh.Trimesh | str | os.PathLike | tuple


def _as_array(value: object) -> np.ndarray:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu().numpy()
    return np.asarray(value)


def _read(path: str | os.PathLike, name: str) -> trimesh.Trimesh:
    if os.path.isdir(path):
        raise IsADirectoryError(f"{name}: {os.fspath(path)!r} is a directory, not a mesh file")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{name}: no mesh file at {os.fspath(path)!r}")
    try:
        # unprocessed: trimesh's processing would silently drop non-finite vertices and their
        # faces, which the check below must see first
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as error:  # trimesh raises many types for unreadable files
        raise ValueError(
            f"{name}: trimesh could not read {os.fspath(path)!r} as a triangle mesh ({error})"
        ) from error
    if not isinstance(loaded, trimesh.Trimesh):
        raise ValueError(
            f"{name}: {os.fspath(path)!r} holds no triangle mesh (trimesh read a "
            f"{type(loaded).__name__})"
        )
    _check_arrays(np.asarray(loaded.vertices), np.asarray(loaded.faces),
                  f"{name} ({os.fspath(path)!r})")
    # trimesh's processing (merge duplicates, drop unreferenced), with its merge distance
    # relative to the mesh's size: its default, 1e-8 world units, collapsed a mesh 1e-7 across
    # to 95 of its 2930 vertices without a word
    loaded.merge_vertices(digits_vertex=merge_digits(np.asarray(loaded.vertices),
                                                     np.asarray(loaded.faces)))
    loaded.metadata["processed"] = True
    return loaded


MERGE_DISTANCE = 1e-8
"""Vertices of a mesh file closer than this fraction of the mesh's longest side are merged
(trimesh's default merge distance, 1e-8, made relative: a unit mesh merges as trimesh does)."""


def merge_digits(vertices: np.ndarray, faces: np.ndarray) -> int:
    """The decimal digits of the vertex coordinates trimesh's merge compares
    (``Trimesh.merge_vertices(digits_vertex=...)``): :data:`MERGE_DISTANCE` of the longest side
    of the referenced vertices' box, and no more digits than int64 holds for the coordinates."""
    used = vertices[np.unique(faces)]
    extent = float(np.ptp(used, axis=0).max())
    digits = math.ceil(-math.log10(MERGE_DISTANCE * extent)) if extent > 0 else 8
    largest = float(np.abs(used).max())
    if largest > 0:
        digits = min(digits, math.floor(math.log10(2.0**62 / largest)))
    return digits


def as_trimesh(mesh: MeshLike, name: str = "mesh") -> trimesh.Trimesh:
    """Check ``mesh`` and return it as a ``trimesh.Trimesh``; raise naming ``name`` otherwise.

    Args:
        mesh: a ``trimesh.Trimesh`` (used as it is, never modified); a path to any file
            trimesh reads (its raw arrays checked, then processed as trimesh does, merging
            vertices closer than :data:`MERGE_DISTANCE` of the mesh's longest side and dropping
            unreferenced ones); or a pair
            ``(vertices, faces)`` of arrays or tensors, ``(V, 3)`` world ``(x, y, z)`` and
            ``(F, 3)`` vertex indices, kept as given.
        name: the argument's name, for the error messages.

    Raises:
        FileNotFoundError: the path names no file (``IsADirectoryError``: a directory).
        TypeError: ``mesh`` is none of the above.
        ValueError: the file cannot be read, the mesh is empty, has non-finite vertices,
            non-triangular faces, face indices out of range, or only degenerate (zero-area)
            faces. A few degenerate faces are kept (see :func:`degenerate_faces`).

    A ``trimesh.Trimesh`` built with trimesh's default ``process=True`` has already dropped
    non-finite vertices and the faces that use them, leaving a hole that nothing records;
    build it with ``process=False``, or pass the file or the arrays, to have them checked.
    """
    if isinstance(mesh, (str, os.PathLike)):
        mesh = _read(mesh, name)
    elif isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        if any(isinstance(part, (trimesh.Trimesh, str, os.PathLike)) for part in mesh):
            raise TypeError(
                f"{name} must be one mesh, got a {type(mesh).__name__} of two meshes (read as "
                "(vertices, faces)): for several meshes use torchsurf.MeshBatchAdapter or one "
                "call per mesh"
            )
        if isinstance(mesh[0], torch.Tensor) and mesh[0].requires_grad:
            warnings.warn(f"{name}: its vertices require grad, but a mesh is taken as data: "
                          "phi and the adapters are not differentiable in the vertex positions "
                          "(no gradient reaches them)", UserWarning, stacklevel=caller_stacklevel())
        vertices = _as_array(mesh[0])
        faces = _as_array(mesh[1])
        _check_arrays(vertices, faces, name)
        mesh = trimesh.Trimesh(
            vertices.astype(np.float64), faces.astype(np.int64), process=False, validate=False
        )
    elif isinstance(mesh, trimesh.Scene):
        raise TypeError(
            f"{name} must be a trimesh.Trimesh, got a trimesh.Scene of {len(mesh.geometry)} "
            "geometries: merge them with scene.to_mesh(), or load the file with "
            "trimesh.load(path, force='mesh') (or pass its path)"
        )
    elif not isinstance(mesh, trimesh.Trimesh):
        raise TypeError(
            f"{name} must be a trimesh.Trimesh, a path to a mesh file, or a pair "
            f"(vertices, faces), got {type(mesh).__name__}"
        )
    _check_arrays(np.asarray(mesh.vertices), np.asarray(mesh.faces), name)
    return mesh


def is_array_pair(value: object) -> bool:
    """Whether ``value`` is one mesh as arrays, ``(vertices (V, 3), faces (F, 3))`` (numpy or
    tensors), not a sequence of two meshes."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        return False
    shapes = [np.shape(part) if isinstance(part, (np.ndarray, torch.Tensor)) else None
              for part in value]
    return all(shape is not None and len(shape) == 2 and shape[1] == 3 for shape in shapes)


def _check_arrays(vertices: np.ndarray, faces: np.ndarray, name: str) -> None:
    """Check raw vertices ``(V, 3)`` and faces ``(F, 3)``; raise ``ValueError`` naming ``name``."""
    if vertices.size == 0 or faces.size == 0:
        raise ValueError(
            f"{name} is empty: it has {len(vertices)} vertices and {len(faces)} faces"
        )
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"{name}: vertices must have shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(
            f"{name}: faces must be triangles, shape (F, 3), got {faces.shape}; "
            "triangulate polygons first (e.g. trimesh.Trimesh(..., process=True))"
        )
    if not np.issubdtype(vertices.dtype, np.number) or np.iscomplexobj(vertices):
        raise ValueError(f"{name}: vertices must be real numbers, got dtype {vertices.dtype}")
    bad = np.flatnonzero(~np.isfinite(vertices).all(axis=1))
    if len(bad):
        raise ValueError(
            f"{name}: vertices must be finite, found NaN or infinity in {len(bad)} of "
            f"{len(vertices)} vertices (first: vertex {bad[0]} = {vertices[bad[0]].tolist()})"
        )
    if not np.issubdtype(faces.dtype, np.integer):
        raise ValueError(f"{name}: faces must hold integer vertex indices, got {faces.dtype}")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(
            f"{name}: face indices must lie in [0, {len(vertices) - 1}], "
            f"got [{faces.min()}, {faces.max()}]"
        )
    if degenerate_faces(vertices, faces).all():
        raise ValueError(
            f"{name} has no area: all its {len(faces)} faces are degenerate (a repeated vertex "
            "index or three collinear corners), so it bounds nothing"
        )


def degenerate_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Boolean ``(F,)``: faces of zero area, ``|e1 x e2| <= 1e-12 * (longest edge)^2``.

    Such a face is a segment or a point. The mesh distance keeps it (the distance to it is
    exact, and it never changes a sign: it spans no solid angle and its pseudonormal is not
    used), so a mesh with a few of them gives the same ``phi`` as without them.
    """
    corner = vertices[faces].astype(np.float64)
    edges = corner[:, [1, 2, 0]] - corner
    cross = np.linalg.norm(np.cross(edges[:, 0], -edges[:, 2]), axis=1)
    longest = (edges**2).sum(axis=2).max(axis=1)
    return cross <= 1e-12 * longest


def triangle_arrays(mesh: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    """Contiguous float64 vertices ``(V, 3)`` and int64 faces ``(F, 3)``, copies of the mesh's."""
    vertices = np.ascontiguousarray(mesh.vertices, dtype=np.float64).copy()
    faces = np.ascontiguousarray(mesh.faces, dtype=np.int64).copy()
    return vertices, faces


def warn_unused_vertices(vertices: np.ndarray, faces: np.ndarray, name: str) -> None:
    """Warn when vertices ``(V, 3)`` are used by no face of ``faces`` ``(F, 3)``: an adapter
    decodes at every vertex, and such a vertex has no surface behind it (it reads the band
    near it, 0 far from the mesh)."""
    unused = np.ones(len(vertices), dtype=bool)
    unused[faces.reshape(-1)] = False
    if unused.any():
        warnings.warn(
            f"{name}: {int(unused.sum())} of {len(vertices)} vertices are used by no face, e.g. "
            f"vertex {int(np.flatnonzero(unused)[0])}; decode gives them what the band holds "
            "near them (0 far from the mesh), not their own values: remove them first "
            "(mesh.remove_unreferenced_vertices())",
            RuntimeWarning, stacklevel=caller_stacklevel())
