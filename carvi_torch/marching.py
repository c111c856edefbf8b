"""Batched marching cubes of occupancy grids in torch, on any device (the GPU's meshing).

:func:`carvi_torch.mesh.occupancy_to_mesh` meshes one grid at a time with scikit-image on the
host. This module meshes a batch of grids at once with torch operators, on the grids' device,
and gives the same meshes: the same vertices (float tolerance) and the same triangles.

How it matches scikit-image
---------------------------
On a 0/1 occupancy at the level ``LEVEL`` (just below 0.5, :mod:`carvi_torch.mesh`), every
decision of scikit-image's Lewiner marching cubes inside a cube (its case, and the face and
interior tests of the ambiguous cases) depends on that cube's eight corners alone, and every
vertex lies on a cube edge at ``LEVEL`` from its empty end. So the triangles of a cube are a
function of its 8-bit corner pattern, and :func:`case_table` reads them off scikit-image
itself, one 2 x 2 x 2 grid per pattern (256 calls, once per process). The batched op then
(1) computes every cube's pattern, (2) looks up the triangles of the cubes the surface
crosses, (3) names each triangle corner by its grid edge, so that neighbouring cubes share
vertices, and (4) numbers the distinct edges per grid (a sort). The triangles keep
scikit-image's winding; :func:`occupancy_to_meshes` then orients and maps them exactly as
:func:`~carvi_torch.mesh.occupancy_to_mesh` does. Vertices come in a different order
(sorted by edge), faces in cube order.

:func:`marching_cubes_naive` is the same construction as a plain loop over cubes with a
dictionary of edges (a reference for tests); ``tests/test_marching.py`` checks both against
scikit-image on random and reconstructed grids.

Example:
    >>> occ = torch.zeros(1, 4, 4, 4, dtype=torch.bool); occ[0, 1:3, 1:3, 1:3] = True
    >>> mc = marching_cubes(occ)
    >>> mc.vertex_counts.tolist(), mc.face_counts.tolist()
    ([24], [44])
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from .mesh import LEVEL

__all__ = ["MarchingCubes", "case_table", "marching_cubes", "marching_cubes_naive", "occupancy_to_meshes",
           "MAX_TRIANGLES", "Mesher", "resolve_mesher"]

#: Who meshes a run's objects (``mesh.mesher``): see :func:`resolve_mesher`.
Mesher = Literal["auto", "skimage", "torch"]

#: Most triangles scikit-image's Lewiner table puts in one cube of a 0/1 occupancy.
MAX_TRIANGLES = 5
#: Cube corners ``(d, h, w)`` offsets; corner ``k`` has bit ``k`` of a cube's pattern.
CORNERS = [(d, h, w) for d in (0, 1) for h in (0, 1) for w in (0, 1)]
#: Cubes meshed per step of :func:`marching_cubes` (bounds the memory of its temporaries).
CUBES_PER_STEP = 2 ** 26


def resolve_mesher(mesher: Mesher, device: torch.device) -> Literal["skimage", "torch"]:
    """``auto``: ``torch`` (this module, batched on the device, in the run's process) on CUDA, where the host's
    meshing limited the run; ``skimage`` (writer processes) elsewhere: on the CPU the torch op is no faster
    than scikit-image and the writers overlap it with the carving (docs/benchmarks.md).

    Example:
        >>> resolve_mesher("auto", torch.device("cpu")), resolve_mesher("torch", torch.device("cpu"))
        ('skimage', 'torch')
    """
    if mesher == "auto":
        return "torch" if torch.device(device).type == "cuda" else "skimage"
    return mesher


@functools.lru_cache(maxsize=1)
def case_table() -> np.ndarray:
    """``(256, MAX_TRIANGLES, 3)`` int64 triangles of each cube pattern, as scikit-image makes them.

    Entry ``3 * corner + axis`` names the cube edge from ``CORNERS[corner]`` along ``axis``
    (0: d, 1: h, 2: w); ``-1`` pads. Read off ``skimage.measure.marching_cubes`` (Lewiner, level
    ``LEVEL``) on one 2 x 2 x 2 grid per pattern.

    Example:
        >>> t = case_table()
        >>> t.shape, int((t[0] >= 0).sum()), int((t[1] >= 0).all(axis=1).sum())
        ((256, 5, 3), 0, 1)
    """
    from skimage.measure import marching_cubes as sk_marching_cubes

    table = np.full((256, MAX_TRIANGLES, 3), -1, dtype=np.int64)
    for pattern in range(1, 255):
        cube = np.zeros((2, 2, 2), np.float32)
        for k, c in enumerate(CORNERS):
            cube[c] = pattern >> k & 1
        verts, faces, _, _ = sk_marching_cubes(cube, level=LEVEL, method="lewiner", allow_degenerate=False)
        frac = np.abs(verts - np.round(verts)) > 1e-4
        if len(faces) > MAX_TRIANGLES or not (frac.sum(axis=1) == 1).all():
            raise RuntimeError(f"scikit-image's marching cubes: pattern {pattern} is not an edge-vertex case "
                               f"({len(faces)} triangles)")
        axis = frac.argmax(axis=1)
        low = np.floor(verts + 1e-4).astype(np.int64)  # the edge's lower end
        corner = low[:, 0] * 4 + low[:, 1] * 2 + low[:, 2]
        table[pattern, :len(faces)] = (3 * corner + axis)[faces]
    return table


@functools.lru_cache(maxsize=8)
def _device_tables(device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The case table on ``device``; its triangle counts; each edge code's ``(d, h, w, axis)`` offsets."""
    t = torch.from_numpy(case_table())
    codes = torch.arange(24)
    corner = torch.tensor(CORNERS)[codes // 3]
    offsets = torch.cat([corner, (codes % 3)[:, None]], dim=1)
    return t.to(device), (t[:, :, 0] >= 0).sum(1).to(device), offsets.to(device)


@dataclass
class MarchingCubes:
    """The meshes of a batch of ``B`` grids, packed.

    Attributes:
        vertices: ``(V, 3)`` float64 ``(d, h, w)`` indices of the unpadded grids, grid by grid.
        faces: ``(F, 3)`` long, indices into ``vertices`` (packed: grid ``b``'s faces index its own vertices).
        vertex_counts, face_counts: ``(B,)`` long per grid (a grid without surface has 0 and 0).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    vertex_counts: torch.Tensor
    face_counts: torch.Tensor

    def split(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Per grid ``(vertices (V_b, 3), faces (F_b, 3))`` with faces indexing the grid's own vertices."""
        vs = self.vertices.split(self.vertex_counts.tolist())
        starts = torch.cumsum(self.vertex_counts, 0) - self.vertex_counts
        fs = (self.faces - starts.repeat_interleave(self.face_counts)[:, None]).split(self.face_counts.tolist())
        return list(zip(vs, fs))


def _patterns(padded: torch.Tensor) -> torch.Tensor:
    """``(B, D + 1, H + 1, W + 1)`` uint8 corner pattern of every cube of ``padded (B, D + 2, H + 2, W + 2)``."""
    B, D, H, W = padded.shape
    pattern = torch.zeros(B, D - 1, H - 1, W - 1, dtype=torch.uint8, device=padded.device)
    for k, (d, h, w) in enumerate(CORNERS):
        pattern |= padded[:, d:D - 1 + d, h:H - 1 + h, w:W - 1 + w].to(torch.uint8) << k
    return pattern


def _crossed_cubes(padded: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat indices ``(A,)`` (into the ``(B, D + 1, H + 1, W + 1)`` cubes) and patterns of the cubes that
    the surface crosses."""
    pattern = _patterns(padded).flatten()
    crossed = ((pattern != 0) & (pattern != 255)).nonzero().squeeze(1)
    return crossed, pattern[crossed].long()


def marching_cubes(occupancy: torch.Tensor) -> MarchingCubes:
    """Meshes of a batch of occupancy grids (zero-padded by one voxel: closed surfaces), on their device.

    Args:
        occupancy: ``(B, D, H, W)`` bool (any device).

    Returns:
        :class:`MarchingCubes` on the same device: vertices in ``(d, h, w)`` index space of the
        grid, triangles wound as scikit-image winds them (not yet oriented).
    """
    if occupancy.dim() != 4:
        raise ValueError(f"occupancy must be (B, D, H, W), got shape {tuple(occupancy.shape)}")
    B = occupancy.shape[0]
    cubes = max(1, (occupancy[0].numel() if B else 1) * 2)
    step = max(1, CUBES_PER_STEP // cubes)
    parts = [_marching_cubes(occupancy[b:b + step].bool()) for b in range(0, B, step)]
    if not parts:
        dev = occupancy.device
        z = torch.zeros(0, dtype=torch.long, device=dev)
        return MarchingCubes(torch.zeros(0, 3, dtype=torch.float64, device=dev), z.view(0, 3), z, z)
    offsets = torch.cumsum(torch.stack([p.vertices.new_tensor(len(p.vertices)) for p in parts]), 0)
    offsets = [0] + [int(o) for o in offsets[:-1]]
    return MarchingCubes(torch.cat([p.vertices for p in parts]),
                         torch.cat([p.faces + o for p, o in zip(parts, offsets)]),
                         torch.cat([p.vertex_counts for p in parts]), torch.cat([p.face_counts for p in parts]))


def _marching_cubes(occupancy: torch.Tensor) -> MarchingCubes:
    """:func:`marching_cubes` of one batch (all of it in memory at once)."""
    dev = occupancy.device
    B = occupancy.shape[0]
    padded = torch.nn.functional.pad(occupancy, (1, 1, 1, 1, 1, 1))
    Dp, Hp, Wp = padded.shape[1:]
    table, counts, offsets = _device_tables(dev)
    crossed, pattern = _crossed_cubes(padded)
    # the cube's (b, d, h, w) from its flat index over (B, Dp - 1, Hp - 1, Wp - 1)
    w = crossed % (Wp - 1)
    h = crossed // (Wp - 1) % (Hp - 1)
    d = crossed // ((Wp - 1) * (Hp - 1)) % (Dp - 1)
    b = crossed // ((Wp - 1) * (Hp - 1) * (Dp - 1))
    tri = table[pattern]  # (A, 5, 3) edge codes
    has = torch.arange(MAX_TRIANGLES, device=dev)[None] < counts[pattern][:, None]  # (A, 5)
    cube_of_tri = has.nonzero()[:, 0]
    codes = tri[has]  # (T, 3), in cube order then table order
    off = offsets[codes]  # (T, 3, 4)
    # a vertex is named by its edge: (b, lower corner in the padded grid, axis)
    key = ((((b[cube_of_tri, None] * Dp + d[cube_of_tri, None] + off[..., 0]) * Hp + h[cube_of_tri, None]
             + off[..., 1]) * Wp + w[cube_of_tri, None] + off[..., 2]) * 3 + off[..., 3])
    edges, inverse = torch.unique(key.flatten(), sorted=True, return_inverse=True)
    axis = edges % 3
    corner = edges // 3
    pw, ph, pd = corner % Wp, corner // Wp % Hp, corner // (Wp * Hp) % Dp
    pb = corner // (Wp * Hp * Dp)
    low_occupied = padded[pb, pd, ph, pw]
    t = LEVEL + low_occupied.to(torch.float64) * (1.0 - 2.0 * LEVEL)  # LEVEL from the empty end
    verts = torch.stack([pd, ph, pw], dim=1).to(torch.float64) - 1.0  # indices of the unpadded grid
    verts[torch.arange(len(edges), device=dev), axis] += t
    return MarchingCubes(verts, inverse.view(-1, 3), torch.bincount(pb, minlength=B),
                         torch.bincount(b[cube_of_tri], minlength=B))


def marching_cubes_naive(occupancy) -> tuple[np.ndarray, np.ndarray]:
    """:func:`marching_cubes` of one ``(D, H, W)`` grid as a plain loop over its cubes (a reference).

    Returns ``(vertices (V, 3) float64, faces (F, 3) int64)``, vertices in first-use order.
    """
    occ = np.pad(np.asarray(occupancy, dtype=bool), 1)
    table = case_table()
    index: dict[tuple, int] = {}
    verts, faces = [], []
    D, H, W = occ.shape
    for d in range(D - 1):
        for h in range(H - 1):
            for w in range(W - 1):
                pattern = sum(int(occ[d + a, h + b, w + c]) << k for k, (a, b, c) in enumerate(CORNERS))
                for tri in table[pattern]:
                    if tri[0] < 0:
                        break
                    face = []
                    for code in tri:
                        a, b, c = CORNERS[code // 3]
                        low, axis = (d + a, h + b, w + c), int(code % 3)
                        if (low, axis) not in index:
                            p = np.array(low, dtype=np.float64) - 1.0
                            p[axis] += (1.0 - LEVEL) if occ[low] else LEVEL
                            index[(low, axis)] = len(verts)
                            verts.append(p)
                        face.append(index[(low, axis)])
                    faces.append(face)
    return np.array(verts, dtype=np.float64).reshape(-1, 3), np.array(faces, dtype=np.int64).reshape(-1, 3)


def _orient_and_map(mc: MarchingCubes, voxel_to_camera: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertices mapped to the camera frame and faces wound outward there (per grid), as in
    :func:`carvi_torch.mesh.occupancy_to_mesh`: outward in index space, reversed when ``det T < 0``."""
    B = len(mc.vertex_counts)
    v, f = mc.vertices, mc.faces
    face_b = torch.arange(B, device=f.device).repeat_interleave(mc.face_counts)
    vert_b = torch.arange(B, device=f.device).repeat_interleave(mc.vertex_counts)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    volume = torch.zeros(B, dtype=torch.float64, device=f.device).index_add_(
        0, face_b, (a * torch.linalg.cross(b, c)).sum(1))
    T = voxel_to_camera.to(device=v.device, dtype=torch.float64)
    L = T[:, :3, :3]
    det = (L[:, 0] * torch.linalg.cross(L[:, 1], L[:, 2])).sum(1)  # no solver library on the device for a sign
    flip = (volume < 0) ^ (det < 0)
    faces = torch.where(flip[face_b][:, None], f.flip(1), f)
    cam = torch.einsum("vij,vj->vi", T[vert_b, :3, :3], v) + T[vert_b, :3, 3]
    return cam, faces


def occupancy_to_meshes(occupancy: torch.Tensor, voxel_to_camera: torch.Tensor, *,
                        vertex_dtype: torch.dtype = torch.float64,
                        face_dtype: torch.dtype = torch.int64) -> list[tuple[np.ndarray, np.ndarray]]:
    """Closed surfaces of a batch of grids in their camera frames: :func:`~carvi_torch.mesh.occupancy_to_mesh`
    for every grid at once, on the grids' device.

    Args:
        occupancy: ``(B, D, H, W)`` bool; voxel_to_camera: ``(B, 4, 4)`` float, ``(d, h, w, 1) -> (x, y, z, 1)``.
        vertex_dtype, face_dtype: the returned arrays' types, cast on the device (computed in float64 and
            int64): a PLY file's float32 and int32 copy half the bytes to the host and none there.

    Returns:
        Per grid ``(vertices (V, 3), faces (F, 3))`` numpy arrays (host) of those types, faces
        outward; a grid without surface gives ``(0, 3)`` arrays.

    Example:
        >>> occ = torch.zeros(2, 4, 4, 4, dtype=torch.bool); occ[0, 1:3, 1:3, 1:3] = True
        >>> [(len(v), len(f)) for v, f in occupancy_to_meshes(occ, torch.eye(4).expand(2, 4, 4))]
        [(24, 44), (0, 0)]
    """
    if voxel_to_camera.shape != (len(occupancy), 4, 4):
        raise ValueError(f"voxel_to_camera must be (B, 4, 4) with B = {len(occupancy)}, got "
                         f"{tuple(voxel_to_camera.shape)}")
    mc = marching_cubes(occupancy)
    cam, faces = _orient_and_map(mc, voxel_to_camera)
    starts = torch.cumsum(mc.vertex_counts, 0) - mc.vertex_counts
    faces = faces - starts.repeat_interleave(mc.face_counts)[:, None]
    vs = cam.to(vertex_dtype).cpu().numpy()
    fs = faces.to(face_dtype).cpu().numpy()
    vc, fc = mc.vertex_counts.tolist(), mc.face_counts.tolist()
    vo, fo = np.cumsum([0] + vc), np.cumsum([0] + fc)
    return [(vs[vo[i]:vo[i + 1]], fs[fo[i]:fo[i + 1]]) for i in range(len(vc))]
