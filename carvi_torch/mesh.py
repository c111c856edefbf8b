"""Meshes of voxel grids: marching cubes, connected components, transforms, export.

Frames and units
----------------
A voxel grid is a ``(D, H, W)`` = (depth, y, x) occupancy with voxel centres at
integer indices and a ``voxel_to_camera (4, 4)`` matrix mapping the homogeneous
index vector ``(d, h, w, 1)`` to the camera-frame point ``(x, y, z, 1)`` (reference
camera frame: ``x, y`` image pixels, ``z`` depth in pixels; see
:mod:`carvi_torch.carve`). Meshes built here are written in that camera frame.

The surface is the 0.5 level of the zero-padded occupancy (skimage's Lewiner
marching cubes, run at ``LEVEL = 0.5 - 1e-3``: at exactly 0.5 the saddle value of every
ambiguous face ties with the level, neighbouring cubes then resolve it differently
and the mesh has holes, measured on random grids; just below 0.5 the ties are
broken one way, so occupied voxels sharing only an edge are joined, which keeps the
thin imprinted layers of a carving in one piece). The surface passes (within 0.001
voxel) half-way between an occupied and an empty voxel centre,
so the enclosed volume is close to ``count * |det voxel_to_camera[:3, :3]|``
(corners and edges of the voxel set are chamfered). Faces are wound
counter-clockwise seen from outside (trimesh's convention: ``mesh.volume > 0``),
whatever the handedness of ``voxel_to_camera``.

Everything here is CPU-side (numpy, scipy, skimage, trimesh); torch inputs are
accepted and copied to the CPU.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Literal, get_args

import numpy as np
from scipy import ndimage
from skimage.measure import marching_cubes

from .io.outputs import atomic_write

if TYPE_CHECKING:
    import trimesh

__all__ = ["occupancy_to_mesh", "largest_component", "transform_mesh", "write_mesh", "read_mesh_arrays", "empty_mesh",
           "trimesh_mesh", "MESH_FORMATS", "MeshFormat"]

#: Mesh file formats :func:`write_mesh` writes (by the path's extension).
MeshFormat = Literal["ply", "obj", "glb", "stl", "off"]
MESH_FORMATS: tuple[str, ...] = get_args(MeshFormat)
#: Marching-cubes level on the 0/1 occupancy (see the module docstring).
LEVEL = 0.5 - 1e-3


def _is_tensor(x) -> bool:
    """Whether ``x`` is a torch tensor, without importing torch (the writer processes never need it)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(x, torch.Tensor)


def _to_numpy(x, name: str, dtype=None) -> np.ndarray:
    if _is_tensor(x):
        x = x.detach().cpu().numpy()
    try:
        return np.asarray(x, dtype=dtype)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name}: cannot convert to an array ({e})") from None


def trimesh_mesh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """``trimesh.Trimesh(vertices, faces, process=False)``. trimesh is imported here, on first use: a run's
    main process meshes nothing on the CPU (measured: 1.82 against 1.87 s of CPU for its imports)."""
    import trimesh

    return trimesh.Trimesh(vertices=vertices, faces=faces, process=False)


def empty_mesh() -> trimesh.Trimesh:
    """A mesh with no vertices and no faces (what an empty occupancy gives)."""
    return trimesh_mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume enclosed by a closed triangle mesh (sum of origin tetrahedra), float64."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->", a, np.cross(b, c))) / 6.0


def occupancy_to_mesh(occupancy, voxel_to_camera, *, largest_component: bool = False,
                      connectivity: int = 3) -> trimesh.Trimesh:
    """Closed surface of an occupancy grid, in the grid's camera frame.

    Marching cubes (level ``LEVEL``, just below 0.5) on the occupancy padded with one empty voxel on every
    side, so the surface is closed even where the occupancy touches the grid border;
    vertices are mapped from ``(d, h, w)`` indices through ``voxel_to_camera``.

    Args:
        occupancy: ``(D, H, W)`` bool tensor or array.
        voxel_to_camera: ``(4, 4)`` float, ``(d, h, w, 1) -> (x, y, z, 1)``.
        largest_component: keep only the largest connected component first
            (see :func:`largest_component`).
        connectivity: 1 (faces), 2 (edges) or 3 (corners), for ``largest_component``.

    Returns:
        ``trimesh.Trimesh`` (float64 vertices in the camera frame, outward-facing
        faces, ``volume > 0``); an empty occupancy gives an empty mesh.

    Example:
        >>> import torch
        >>> occ = torch.zeros(4, 4, 4, dtype=torch.bool); occ[1:3, 1:3, 1:3] = True
        >>> m = occupancy_to_mesh(occ, torch.eye(4))
        >>> bool(m.is_watertight), bool(m.volume > 0)
        (True, True)
    """
    occ = _to_numpy(occupancy, "occupancy", dtype=bool)
    if occ.ndim != 3:
        raise ValueError(f"occupancy must be (D, H, W), got shape {occ.shape}")
    T = _to_numpy(voxel_to_camera, "voxel_to_camera", dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ValueError(f"voxel_to_camera must be a finite (4, 4) matrix, got shape {T.shape}")
    if largest_component:
        occ = _largest_component_np(occ, connectivity)
    if not occ.any():
        return empty_mesh()
    padded = np.pad(occ.astype(np.float32), 1)
    verts, faces, _, _ = marching_cubes(padded, level=LEVEL, method="lewiner", allow_degenerate=False)
    verts = verts.astype(np.float64) - 1.0  # indices of the unpadded grid
    faces = faces.astype(np.int64)
    # Orient outward in index space (independent of skimage's winding convention),
    # then account for the handedness of the index -> camera map.
    flip = _signed_volume(verts, faces) < 0
    if np.linalg.det(T[:3, :3]) < 0:
        flip = not flip
    if flip:
        faces = faces[:, ::-1].copy()
    cam = verts @ T[:3, :3].T + T[:3, 3]
    return trimesh_mesh(cam, faces)


def largest_component(occupancy, connectivity: int = 3):
    """Keep the largest connected component of an occupancy grid (or of each of a batch).

    Components come from ``scipy.ndimage.label`` with
    ``generate_binary_structure(3, connectivity)``; a batch is labelled in one call
    with no connectivity across its leading axis. Ties go to the component met first
    in ``(d, h, w)`` raster order. CPU-side.

    Args:
        occupancy: ``(D, H, W)`` or ``(B, D, H, W)`` bool tensor or array.
        connectivity: 1 (6-neighbourhood, faces), 2 (18, edges) or 3 (26, corners).

    Returns:
        The same type, shape and device as the input, bool; empty grids stay empty.

    Example:
        >>> occ = np.zeros((1, 1, 5), bool); occ[0, 0, [0, 2, 3]] = True
        >>> largest_component(occ).astype(int)
        array([[[0, 0, 1, 1, 0]]])
    """
    is_tensor = _is_tensor(occupancy)
    occ = _to_numpy(occupancy, "occupancy", dtype=bool)
    if occ.ndim not in (3, 4):
        raise ValueError(f"occupancy must be (D, H, W) or (B, D, H, W), got shape {occ.shape}")
    out = _largest_component_np(occ, connectivity)
    if is_tensor:
        return sys.modules["torch"].from_numpy(out).to(occupancy.device)
    return out


def _largest_component_np(occ: np.ndarray, connectivity: int) -> np.ndarray:
    """:func:`largest_component` on a ``(D, H, W)`` or ``(B, D, H, W)`` bool array."""
    if connectivity not in (1, 2, 3):
        raise ValueError(f"connectivity must be 1, 2 or 3, got {connectivity!r}")
    batched = occ.reshape((-1,) + occ.shape[-3:])
    structure = np.zeros((3, 3, 3, 3), dtype=bool)
    structure[1] = ndimage.generate_binary_structure(3, connectivity)
    labels, n = ndimage.label(batched, structure=structure)
    keep = np.zeros(n + 1, dtype=bool)
    if n > 0:
        counts = np.bincount(labels.ravel(), minlength=n + 1)[1:]
        # Labels are numbered in raster order and never span two batch items, so item
        # b owns the labels up to the running maximum of the labels of items <= b.
        ends = np.maximum.accumulate(labels.reshape(len(batched), -1).max(axis=1))
        item = np.searchsorted(ends, np.arange(1, n + 1), side="left")
        order = np.lexsort((np.arange(n), -counts, item))  # per item: largest first, ties: lowest label
        first = np.ones(n, dtype=bool)
        first[1:] = item[order][1:] != item[order][:-1]
        keep[1 + order[first]] = True
    return keep[labels].reshape(occ.shape)


def transform_mesh(mesh: trimesh.Trimesh, A) -> trimesh.Trimesh:
    """A copy of ``mesh`` with vertices mapped by the affine ``A (4, 4)`` (e.g. canvas -> image pixels).

    ``x' = A[:3, :3] x + A[:3, 3]``. When ``det A[:3, :3] < 0`` (a reflection) the faces
    are reversed, so they stay outward-facing.

    Args:
        mesh: a ``trimesh.Trimesh``.
        A: ``(4, 4)`` tensor or array with last row ``(0, 0, 0, 1)``.

    Returns:
        A new ``trimesh.Trimesh``.
    """
    A = _to_numpy(A, "A", dtype=np.float64)
    if A.shape != (4, 4) or not np.isfinite(A).all():
        raise ValueError(f"A must be a finite (4, 4) matrix, got shape {A.shape}")
    if not np.allclose(A[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"A must be affine (last row 0, 0, 0, 1), got last row {A[3].tolist()}")
    verts = np.asarray(mesh.vertices, dtype=np.float64) @ A[:3, :3].T + A[:3, 3]
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if np.linalg.det(A[:3, :3]) < 0:
        faces = faces[:, ::-1].copy()
    return trimesh_mesh(verts.reshape(-1, 3), faces.reshape(-1, 3))


def write_mesh(mesh: trimesh.Trimesh, path: str | os.PathLike, sync: bool = True) -> Path:
    """Write ``mesh`` atomically (``sync``: :func:`~carvi_torch.io.outputs.atomic_write`); the file type follows
    the extension.

    ``.ply`` (binary), ``.obj``, ``.glb``, ``.stl`` or ``.off``; a path without an
    extension gets ``.ply``. Parent folders are created.

    Returns:
        The path written.
    """
    path = Path(path)
    ext = path.suffix.lower().lstrip(".")
    if ext == "":
        path = path.with_suffix(".ply")
        ext = "ply"
    if ext not in MESH_FORMATS:
        raise ValueError(f"path: unsupported mesh extension {path.suffix!r}; use one of {MESH_FORMATS}")
    data = mesh.export(file_type=ext)
    if isinstance(data, str):
        data = data.encode("utf-8")
    return atomic_write(path, lambda f: f.write(data), sync)


def read_mesh_arrays(path: str | os.PathLike, used_only: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` float64 and faces ``(F, 3)`` int64 of a mesh file as written (no processing: no vertex
    merged, no face dropped). PLY, :func:`write_mesh`'s default, is parsed by trimesh's PLY reader alone, without
    building a ``Trimesh`` (about half ``trimesh.load``'s time on the default run's meshes); the other formats go
    through ``trimesh.load``.

    Raises ``ValueError`` when the file holds no face, vertices that are not finite ``(V, 3)`` numbers (with
    ``used_only``, only those a face names must be finite: a model's unused vertices do not count), or a face
    index outside ``[0, V)``; what the parser raises on a file it cannot read (``OSError``, ``ValueError``,
    ``KeyError``, ...) propagates.

    Example:
        >>> import tempfile
        >>> path = write_mesh(trimesh_mesh(np.eye(3), np.array([[0, 1, 2]])), Path(tempfile.mkdtemp()) / "t.ply")
        >>> v, f = read_mesh_arrays(path)
        >>> v.shape, v.dtype, f.tolist()
        ((3, 3), dtype('float64'), [[0, 1, 2]])
    """
    v, f = _ply_arrays(path) if str(path).lower().endswith(".ply") else (None, None)
    if f is None:
        import trimesh

        m = trimesh.load(path, force="mesh", process=False)
        v, f = getattr(m, "vertices", np.zeros((0, 3))), getattr(m, "faces", np.zeros((0, 3)))
    v = np.asarray(v, dtype=np.float64)
    f = np.asarray(f, dtype=np.int64).reshape(-1, 3)
    if len(f) == 0:
        raise ValueError("mesh has no faces")
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"mesh vertices of shape {v.shape} are not (V, 3) finite numbers")
    if f.min() < 0 or f.max() >= len(v):
        raise ValueError(f"mesh face index {int(f.min() if f.min() < 0 else f.max())} is outside its "
                         f"{len(v)} vertices")
    if not np.isfinite(v[np.unique(f)] if used_only else v).all():
        raise ValueError(f"mesh vertices of shape {v.shape} are not (V, 3) finite numbers"
                         + (" (among those its faces name)" if used_only else ""))
    return v, f


def _ply_arrays(path) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Vertices and triangles of a PLY file read by trimesh's parser alone, or ``(None, None)`` where its faces are
    other polygons than triangles (``trimesh.load`` splits them)."""
    from trimesh.exchange.ply import load_ply

    with open(path, "rb") as fh:
        kw = load_ply(fh)
    f = np.asarray(kw.get("faces", np.zeros((0, 3))))
    if f.ndim != 2 or (len(f) and f.shape[1] != 3):
        return None, None
    return kw["vertices"], f
