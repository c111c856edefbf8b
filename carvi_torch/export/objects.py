"""Per-object computations of the training export: occupancy that keeps thin parts, depth, surface samples.

Everything here takes host (numpy) data of one object and returns numpy arrays, so that export
worker processes run it without sharing state; it imports numpy and trimesh (for the mesh files), not
torch, so that the workers start fast.

Occupancy is *any-overlap* (supersampled): every voxel of the reconstruction's grid is a small
box (the marching-cubes surface at level 0.5 runs along these boxes' faces); a cell of the
exported grid is occupied when a sub-sample of an occupied box falls in it, with sub-samples
spaced at most half a cell apart. A part one voxel thick therefore stays occupied at any
resolution, where sampling cell centres drops it whenever no centre falls inside it.

Example (a plate one voxel thick, seen by a grid whose centres all miss it):
    >>> import numpy as np
    >>> occ = np.zeros((8, 8, 8), bool); occ[4, 2:6, 2:6] = True   # [d, h, w]: a plate at depth 4
    >>> v2t = np.diag([0.5, 0.5, 0.5, 1.0])                        # cell i has its centre at voxel 2i + 1
    >>> [int(layer.sum()) for layer in splat_occupancy(occ, v2t, 4)]  # cell centres 3 and 5 miss the plate
    [0, 0, 4, 0]
"""
from __future__ import annotations

import functools
import math
import sys
import zipfile
import zlib

import numpy as np
from scipy import ndimage
from trimesh.exchange import ply as _ply  # noqa: F401 - mesh.read_mesh_arrays' parser, loaded before the workers fork

from ..io.layout import SETTINGS_MEMBER, held_fingerprint, held_settings, same_canvas
from ..mesh import read_mesh_arrays
from ..runtime import ignore_interrupt, watch_parent
from .raster import zbuffer

__all__ = ["splat_occupancy", "view_depth_frame", "view_occupancy", "canonical_occupancy", "depth_map",
           "sample_surface", "canvas_to_class", "export_object", "safe_export_object",
           "safe_export_objects", "init_worker", "OtherInputs", "OtherCanvas", "UnreadableFiles", "READ_ERRORS",
           "OTHER_CANVAS"]

#: Most sub-samples per voxel and axis (a target cell finer than a quarter voxel is not a use case).
MAX_SUBSAMPLES = 4


def surface_voxel_indices(occ: np.ndarray) -> np.ndarray:
    """Indices ``(N, 3)`` float32 of the occupied voxels with an empty (or outside) 6-neighbour, in C order:
    what a 6-neighbour erosion removes (``scipy.ndimage.binary_erosion``, the outside empty)."""
    occ = np.asarray(occ, dtype=bool)
    return np.argwhere(occ & ~ndimage.binary_erosion(occ)).astype(np.float32)


@functools.lru_cache(maxsize=4)
def _axis_centres(res: int) -> np.ndarray:
    return np.arange(res, dtype=np.float64) + 0.5


def _centre_hits(occ: np.ndarray, A: np.ndarray, b: np.ndarray, res: int, lo: np.ndarray, hi: np.ndarray,
                 out: np.ndarray) -> None:
    """Set the cells of ``out`` ``(res, res, res)`` whose centre lies in an occupied voxel's box (its nearest
    voxel is occupied). Only the cells around the target-space box of the occupied voxels' boxes
    (``lo``, ``hi``: their first and last voxel index per axis) are tested, one cell of margin around it:
    no other centre is near an occupied box."""
    corners = np.stack(np.meshgrid(*[(lo[j] - 0.5, hi[j] + 0.5) for j in range(3)], indexing="ij"), -1)
    t = corners.reshape(-1, 3) @ A.T + b
    first = np.clip(np.floor(t.min(axis=0)).astype(np.int64) - 1, 0, res)
    last = np.clip(np.floor(t.max(axis=0)).astype(np.int64) + 2, 0, res)
    if (last <= first).any():
        return
    c = _axis_centres(res)
    centres = np.stack(np.meshgrid(*[c[first[j]:last[j]] for j in range(3)], indexing="ij"), -1).reshape(-1, 3)
    src = np.rint((centres - b) @ np.linalg.inv(A).T).astype(np.int64)
    s0, s1, s2 = src[:, 0], src[:, 1], src[:, 2]
    D, H, W = occ.shape
    inside = np.flatnonzero((s0 >= 0) & (s0 < D) & (s1 >= 0) & (s1 < H) & (s2 >= 0) & (s2 < W))
    hit = np.zeros(len(src), dtype=bool)
    hit[inside] = occ.ravel()[(s0[inside] * H + s1[inside]) * W + s2[inside]]
    out[first[0]:last[0], first[1]:last[1], first[2]:last[2]] |= hit.reshape(tuple(last - first))


def splat_occupancy(occ: np.ndarray, voxel_to_target: np.ndarray, res: int,
                    boundary: np.ndarray | None = None) -> np.ndarray:
    """Any-overlap occupancy ``(res, res, res)`` of the boxes of ``occ``'s occupied voxels.

    Args:
        occ: ``(D, H, W)`` bool source grid.
        voxel_to_target: ``(4, 4)`` affine: source voxel index ``(d, h, w, 1)`` -> continuous target
            index ``(i0, i1, i2, 1)``; target cell ``[i0, i1, i2]`` covers ``[i, i + 1)`` on each axis.
        res: target side.
        boundary: :func:`surface_voxel_indices` of ``occ``, when the caller has it already (one grid, two targets).

    Returns:
        ``(res, res, res)`` bool: a cell is occupied when its centre lies in an occupied voxel's box, or
        when a sub-sample of a boundary voxel's box lands in it (``k_j`` sub-samples along source axis
        ``j``: the fewest that space them at most half a target cell apart, at most
        :data:`MAX_SUBSAMPLES`). Interior boxes are covered by the centre test, boundary boxes (all of a
        thin part's) by their sub-samples.
    """
    occ = np.asarray(occ, dtype=bool)
    out = np.zeros((res, res, res), dtype=bool)
    A = voxel_to_target[:3, :3].astype(np.float64)
    b = voxel_to_target[:3, 3].astype(np.float64)
    idx = surface_voxel_indices(occ) if boundary is None else boundary
    if len(idx) == 0:  # no occupied voxel (every occupied region has a boundary)
        return out
    # 1. cell centres inside an occupied box (nearest voxel); the boundary spans the occupied voxels
    _centre_hits(occ, A, b, res, idx.min(axis=0).astype(np.float64), idx.max(axis=0).astype(np.float64), out)
    # 2. sub-samples of the boundary boxes
    k = [int(min(MAX_SUBSAMPLES, max(1, math.ceil(2.0 * float(np.abs(A[:, j]).sum()))))) for j in range(3)]
    subs = [(np.arange(n, dtype=np.float32) + 0.5) / n - 0.5 for n in k]
    offs = np.stack(np.meshgrid(*subs, indexing="ij"), -1).reshape(-1, 3)  # voxel units
    Af = A.astype(np.float32)
    pts = ((idx @ Af.T + b.astype(np.float32))[:, None, :] + (offs @ Af.T)[None]).reshape(-1, 3)
    cell = np.floor(pts).astype(np.int64)
    c0, c1, c2 = cell[:, 0], cell[:, 1], cell[:, 2]
    ok = np.flatnonzero((c0 >= 0) & (c0 < res) & (c1 >= 0) & (c1 < res) & (c2 >= 0) & (c2 < res))
    out.ravel()[(c0[ok] * res + c1[ok]) * res + c2[ok]] = True
    return out


def view_depth_frame(boundary: np.ndarray, voxel_to_canvas: np.ndarray, canvas_size: int, res: int
                     ) -> tuple[float, float]:
    """The depth axis ``(depth_centre, cell_depth)`` of the view grid, in canvas pixels: centred on the depth
    extent of the occupied voxels' boxes (``boundary``: :func:`surface_voxel_indices`, which spans them), and one
    cell ``C / res`` deep (cubic cells) unless the boxes reach deeper than ``(res - 2)`` such cells; then the
    cells deepen so that the middle ``res - 2`` of them hold the whole extent. The first and last layers of
    depth therefore stay empty (``res >= 3``): the whole object is inside.

    Example (a rod 200 voxels deep, seen by a 128 canvas: cells deepen from 4 to 200/30 pixels):
        >>> b = np.array([[0.0, 0, 0], [199.0, 0, 0]])                   # (d, h, w): its two end voxels
        >>> v2c = np.array([[0, 0, 1, 0], [0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1]], float)  # z = d
        >>> centre, cell = view_depth_frame(b, v2c, 128, 32)
        >>> centre, round(cell * 30, 6)
        (99.5, 200.0)
    """
    if len(boundary) == 0:
        return 0.0, canvas_size / float(res)
    corners = np.array(np.meshgrid(*[(-0.5, 0.5)] * 3, indexing="ij")).reshape(3, -1).T
    lo, hi = boundary.min(axis=0).astype(np.float64), boundary.max(axis=0).astype(np.float64)
    box = np.where(corners < 0, lo - 0.5, hi + 0.5)  # the 8 corners of the boxes' bounding box (voxel index)
    z = box @ voxel_to_canvas[2, :3] + voxel_to_canvas[2, 3]
    z0, z1 = float(z.min()), float(z.max())
    inner = max(res - 2.0, 1.0)  # the layers that hold the object (all of them below 3: no spare ones)
    return 0.5 * (z0 + z1), max(canvas_size / float(res), (z1 - z0) / inner)


def view_occupancy(occ: np.ndarray, voxel_to_canvas: np.ndarray, canvas_size: int, res: int,
                   depth_centre: float, boundary: np.ndarray | None = None,
                   cell_depth: float | None = None) -> np.ndarray:
    """Occupancy ``(res, res, res)`` ``[depth, y, x]`` over the canvas square and a range of depth around the centre.

    Cell ``j`` on ``x`` (and ``y``) covers canvas pixels ``[j C/res - 0.5, (j + 1) C/res - 0.5)``; on depth
    ``[zc + (j - res/2) dz, zc + (j + 1 - res/2) dz)``, ``dz = cell_depth`` (default ``C / res``; see
    :func:`view_depth_frame` for the one that holds the whole object).
    """
    f = res / float(canvas_size)
    fz = f if cell_depth is None else 1.0 / float(cell_depth)
    canvas_to_target = np.zeros((4, 4))  # (x, y, z, 1) -> (i_depth, i_y, i_x, 1)
    canvas_to_target[0, 2], canvas_to_target[0, 3] = fz, res / 2.0 - fz * depth_centre
    canvas_to_target[1, 1], canvas_to_target[1, 3] = f, 0.5 * f
    canvas_to_target[2, 0], canvas_to_target[2, 3] = f, 0.5 * f
    canvas_to_target[3, 3] = 1.0
    return splat_occupancy(occ, canvas_to_target @ voxel_to_canvas, res, boundary)


def canvas_to_class(R: np.ndarray, s: float, t: np.ndarray) -> np.ndarray:
    """``(4, 4)`` affine from the canvas camera frame ``(u, v, z)`` to the class frame,
    ``X = R^T [(u - t_x) / s, (v - t_y) / s, z / s]`` for the canvas camera ``(R, s, t)``."""
    M = np.eye(4)
    M[:3, :3] = R.T / s
    M[:3, 3] = -(R.T[:, :2] @ t) / s
    return M


def canonical_occupancy(occ: np.ndarray, voxel_to_canvas: np.ndarray, R: np.ndarray, s: float, t: np.ndarray,
                        extent: float, res: int, boundary: np.ndarray | None = None) -> np.ndarray:
    """Occupancy ``(res, res, res)`` ``[z, y, x]`` of the class frame over ``[-extent, extent]^3``.

    ``(R, s, t)`` is the object's canvas camera (class frame -> canvas pixels); ``boundary``: see
    :func:`splat_occupancy`.
    """
    f = res / (2.0 * extent)
    class_to_target = np.zeros((4, 4))  # (X, Y, Z, 1) -> (i_z, i_y, i_x, 1)
    class_to_target[0, 2] = class_to_target[1, 1] = class_to_target[2, 0] = f
    class_to_target[:3, 3] = f * extent
    class_to_target[3, 3] = 1.0
    return splat_occupancy(occ, class_to_target @ canvas_to_class(R, s, t) @ voxel_to_canvas, res, boundary)


def depth_map(vertices: np.ndarray, faces: np.ndarray, canvas_size: int, depth_centre: float) -> np.ndarray:
    """First-surface depth ``(C, C)`` float32 of a canvas-frame mesh at every canvas pixel centre, relative
    to ``depth_centre`` (z-buffer rasterisation, :func:`~carvi_torch.export.raster.zbuffer`; ``+inf`` where
    the ray misses)."""
    v = np.asarray(vertices, dtype=np.float64)
    z = zbuffer(v[:, :2], v[:, 2], faces, canvas_size, canvas_size)
    return z - np.float32(depth_centre)


def sample_surface(vertices: np.ndarray, faces: np.ndarray, count: int, rng: np.random.Generator
                   ) -> tuple[np.ndarray, np.ndarray]:
    """``count`` area-uniform surface points ``(count, 3)`` and the unit normals of their faces ``(count, 3)``.

    Example:
        >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float); f = np.array([[0, 1, 2]])
        >>> p, n = sample_surface(v, f, 5, np.random.default_rng(0))
        >>> bool((p.sum(1) <= 1 + 1e-9).all()), n[0].tolist()
        (True, [0.0, 0.0, 1.0])
    """
    # coordinate-major (3, F) arrays: every product below runs over contiguous rows
    vt, ft = np.ascontiguousarray(vertices.T), np.ascontiguousarray(faces.T)
    p0 = vt[:, ft[0]]
    (ux, uy, uz), (vx, vy, vz) = vt[:, ft[1]] - p0, vt[:, ft[2]] - p0  # the two edges from corner 0
    cross = np.stack([uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx])  # as np.cross computes them
    area2 = np.sqrt(cross[0] * cross[0] + cross[1] * cross[1] + cross[2] * cross[2])  # np.linalg.norm's sums
    cum = np.cumsum(area2)
    fidx = np.minimum(np.searchsorted(cum, rng.random(count) * cum[-1], side="right"), len(faces) - 1)
    r1, r2 = np.sqrt(rng.random(count)), rng.random(count)
    w = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)  # uniform barycentric coordinates
    pts = np.einsum("pk,pkc->pc", w, vertices[faces[fidx]])
    normals = cross[:, fidx].T / np.maximum(area2[fidx], 1e-300)[:, None]
    return pts, normals


# =========================================================================== one object (worker processes)


class OtherInputs(ValueError):
    """An object's files were made from other inputs than the annotation file's (its input fingerprint)."""


#: The reason of an object whose voxels were carved on another canvas than the one ``config.yaml`` gives (a class
#: a later run with another ``canvas_size`` or ``canvas_margin`` did not touch): its grid would not line up.
OTHER_CANVAS = ("carved on another canvas than config.yaml's (canvas_size or canvas_margin changed since); rerun "
                "reconstruct on its class")


class OtherCanvas(ValueError):
    """An object's voxels were carved on another canvas than the job's (:data:`OTHER_CANVAS`)."""


class UnreadableFiles(ValueError):
    """An object's voxels or mesh file cannot be read (missing, partial or corrupt) or holds unusable data (an
    occupancy that is not a 3-D grid with an occupied voxel, a voxel transform that is not 4 x 4 finite
    numbers, a face index outside the mesh's vertices)."""


#: What reading a partial or corrupt ``.npz`` or mesh file raises: ``np.load`` (``EOFError`` on an empty file,
#: ``zipfile.BadZipFile`` on a cut or damaged one, ``zlib.error`` on damaged compressed data, ``KeyError`` on
#: a missing member, ``ValueError``, ``MemoryError`` on a damaged ``.npy`` header that declares a shape no machine
#: holds: numpy allocates the array before it reads it), trimesh's PLY reader (``ValueError``, ``IndexError`` on a
#: cut header), and the file system (``OSError``). Anything else is a fault of the export, not of the files: it is
#: raised.
READ_ERRORS = (OSError, EOFError, ValueError, KeyError, IndexError, MemoryError, zipfile.BadZipFile, zlib.error)


def _unreadable(path, e: BaseException) -> UnreadableFiles:
    return UnreadableFiles(f"unreadable outputs: {path}: {type(e).__name__}: {e}")


#: The voxel transforms a voxels file may hold (the export uses the first it has).
VOXEL_TRANSFORMS = ("voxel_to_canvas", "voxel_to_camera")


def _check_voxels(vox: dict) -> None:
    """``ValueError`` naming what is wrong with a voxels file's members: no occupancy or no voxel transform, an
    occupancy that is not a non-empty 3-D grid of numbers with at least one occupied voxel, or a transform that
    is not 4 x 4 finite numbers."""
    if "occupancy" not in vox or not set(VOXEL_TRANSFORMS) & vox.keys():
        raise KeyError("no occupancy grid or no voxel transform in the voxels file")
    occ = vox["occupancy"]
    if occ.ndim != 3 or occ.size == 0 or occ.dtype.kind not in "biuf":
        raise ValueError(f"occupancy of shape {occ.shape} ({occ.dtype}) is not a 3-D grid")
    if not occ.astype(bool).any():
        raise ValueError(f"occupancy {occ.shape} has no occupied voxel")
    for k in VOXEL_TRANSFORMS:
        m = vox.get(k)
        if m is not None and (m.shape != (4, 4) or m.dtype.kind not in "iuf" or not np.isfinite(m).all()):
            raise ValueError(f"{k} of shape {m.shape} is not 4 x 4 finite numbers")


#: The members of a voxels file that record the canvas its grid was carved on.
CANVAS_MEMBERS = ("canvas_scale", "canvas_offset")


def _other_canvas(z, canvas: tuple, fingerprint: str | None) -> bool:
    """Whether the opened voxels file ``z`` records a canvas other than ``canvas`` (``(scale, (x, y))``, the
    object's canvas as the export loads it); False also where it records none, where its canvas or fingerprint
    cannot be read (:data:`READ_ERRORS`: the rest of the read says what is wrong), and where it was made from
    other inputs than ``fingerprint``. Any other error is a fault of the caller: it is raised."""
    try:  # members are read one by one (about 0.1 ms each): the fingerprint only where the canvas differs
        held = {k: z[k] for k in CANVAS_MEMBERS if k in z.files}
        if same_canvas(held, canvas) is not False:
            return False
        return not (fingerprint and held_fingerprint(z) not in (None, fingerprint))
    except READ_ERRORS:
        return False


def _read_voxels(path, canvas: tuple | None = None, fingerprint: str | None = None) -> dict:
    """The members of an object's voxels file that the export uses, the file opened once. :class:`OtherCanvas`
    where it records a canvas other than ``canvas`` (:func:`_other_canvas`; checked first, not where ``canvas``
    is None); else :class:`UnreadableFiles` when it cannot be read, lacks its grid or transform, or holds
    unusable ones (:func:`_check_voxels`)."""
    try:
        with np.load(path) as z:
            if canvas is not None and _other_canvas(z, canvas, fingerprint):
                raise OtherCanvas(OTHER_CANVAS)
            vox = {k: np.asarray(z[k]) for k in ("occupancy", *VOXEL_TRANSFORMS, "input_fingerprint",
                                                 SETTINGS_MEMBER) if k in z.files}
        _check_voxels(vox)
    except OtherCanvas:
        raise
    except READ_ERRORS as e:
        raise _unreadable(path, e) from e
    return vox


def _read_mesh(path) -> tuple[np.ndarray, np.ndarray]:
    """:func:`~carvi_torch.mesh.read_mesh_arrays`, :class:`UnreadableFiles` when the file cannot be read or holds
    no usable mesh."""
    try:
        return read_mesh_arrays(path)
    except READ_ERRORS as e:
        raise _unreadable(path, e) from e


def export_object(job: dict) -> dict:
    """Every field of one object from its job (host data and file paths; built by
    :func:`carvi_torch.export.run.export`); the ids are filled in by the caller. Raises :class:`OtherCanvas`
    when the voxels file records a canvas other than the job's (``canvas_scale``, ``canvas_offset``),
    :class:`OtherInputs` when it holds an input fingerprint other than the job's ``fingerprint`` (the annotations
    changed since the object was made, or its redo failed and left an earlier run's files), and
    :class:`UnreadableFiles` when its voxels or mesh file cannot be read. ``settings``: the settings its voxels file
    records (:func:`~carvi_torch.io.layout.held_settings`, ``None``: none), which the export weighs
    (:class:`~carvi_torch.export.source.SettingsTally`) into ``made_with_run_settings``."""
    a, b = float(job["canvas_scale"]), np.asarray(job["canvas_offset"], dtype=np.float64)
    z = _read_voxels(job["voxels"], (a, b), job.get("fingerprint"))
    held = held_fingerprint(z)
    if held is not None and job.get("fingerprint") and held != job["fingerprint"]:
        raise OtherInputs("its files were made from other inputs than the annotation file's (rerun reconstruct)")
    occ = z["occupancy"].astype(bool)
    boundary = surface_voxel_indices(occ)  # shared by both occupancies
    image_to_canvas = np.diag([a, a, a, 1.0])
    image_to_canvas[:2, 3] = b
    v2canvas = z["voxel_to_canvas"] if "voxel_to_canvas" in z else image_to_canvas @ z["voxel_to_camera"]
    cam = job["camera"]
    R = np.asarray(cam["R"], dtype=np.float64)
    s, t = float(cam["s"]), np.asarray(cam["t"], dtype=np.float64)
    s_c, t_c = a * s, a * t + b  # the canvas camera
    verts, faces = _read_mesh(job["mesh"])
    verts = verts * a + image_to_canvas[:3, 3]
    C, res = job["canvas"], job["resolution"]
    depth_centre, cell_depth = view_depth_frame(boundary, v2canvas, C, res)
    pts, normals = sample_surface(verts, faces, job["points"], np.random.default_rng(job["seed"]))
    to_class = canvas_to_class(R, s_c, t_c)
    out = {
        "mask": job["mask"], "keypoints": job["keypoints"], "visible": job["visible"],
        "crop_box": np.concatenate([-b / a, (C - 1.0 - b) / a]).astype(np.float32),
        "canvas_scale": np.float32(a), "canvas_offset": b.astype(np.float32),
        "R": R.astype(np.float32), "s": np.float32(s), "t": t.astype(np.float32),
        "viewpoint": np.array(job["viewpoint"], dtype=np.float32),
        "quality": np.float32(job["quality"]),
        "occupancy_view": view_occupancy(occ, v2canvas, C, res, depth_centre, boundary, cell_depth),
        "view_depth": np.array([depth_centre, cell_depth], dtype=np.float32),
        "occupancy_canonical": canonical_occupancy(occ, v2canvas, R, s_c, t_c, job["extent"], res, boundary),
        "depth": depth_map(verts, faces, C, depth_centre),
        "points": pts @ to_class[:3, :3].T + to_class[:3, 3], "normals": normals @ R,
        "class_index": np.int64(job["class_index"]),
        "settings": held_settings(z),  # not a field: the export tallies it (made_with_run_settings)
    }
    if job["mesh_field"]:
        out["mesh_vertices"] = verts @ to_class[:3, :3].T + to_class[:3, 3]
        out["mesh_faces"] = faces
    return out


def safe_export_object(job: dict) -> tuple[dict | None, str | None]:
    """:func:`export_object`, or ``(None, reason)`` when the object's files are partial, corrupt, made from
    other inputs or carved on another canvas (the object is reported, the export goes on); any other exception
    is raised."""
    try:
        return export_object(job), None
    except (OtherCanvas, OtherInputs, UnreadableFiles) as e:
        return None, str(e)


def safe_export_objects(jobs: list[dict]) -> list[tuple[dict | None, str | None]]:
    """:func:`safe_export_object` of each job (one task of a worker process)."""
    return [safe_export_object(job) for job in jobs]


def init_worker(run_pid: int) -> None:
    """An export worker process: one torch thread where torch is imported (the processes are the
    parallelism; the worker's own work is numpy, and it does not import torch). It ignores Ctrl-C, which a
    terminal sends to the whole process group: the main process handles it and stops the pool. It exits
    when the export that started it (``run_pid``) is gone, killed even with SIGKILL
    (:func:`~carvi_torch.runtime.watch_parent`), and the forkserver that forked it follows."""
    ignore_interrupt()
    watch_parent(run_pid)
    torch = sys.modules.get("torch")
    if torch is not None:
        torch.set_num_threads(1)
