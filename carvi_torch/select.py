"""Reconstruction selection: average masks per principal direction, proposal scores.

The selection stage (:mod:`carvi_torch.pipeline`; paper, "Reconstruction selection"): every proposal
of a reference instance is projected onto three planes, one perpendicular to each
principal direction, and compared with the class' average mask on that plane
(:func:`score_proposals`); proposals that miss the fewest visible reference keypoints rank first,
then the closest to the class average (:func:`rank_proposals`). The selected shape is the
voxel-wise majority vote of the ``select.consensus`` best-ranked valid proposals
(:func:`vote_proposals`, 5 by default); ``consensus=1`` keeps the best proposal alone, the paper's
choice. On the CPU the projection's boundary test and splat run in the package's compiled library
(``carvi_torch/kernels/splat_planes.h``, the same planes bit for bit; torch operators where it does not load
and on other devices).

Plane convention. Plane ``j`` is perpendicular to axis ``e_j = axes[j]`` and spanned by
the two other axes in cyclic order, ``(e_a, e_b) = (axes[(j+1) % 3], axes[(j+2) % 3])``,
so ``e_a x e_b = e_j`` for right-handed axes. A ``(G, G)`` plane image has rows along
``b`` and columns along ``a``, both sampled at ``-extent + 2 extent k / (G - 1)``,
``k = 0 .. G-1`` (object units, about ``centre``): pixel ``[i, k]`` is the object-frame
point ``centre + a_k e_a + b_i e_b``. Read like an image (x right = ``e_a``, y down =
``e_b``), plane ``j`` is the orthographic view of a camera looking along ``+e_j``.

Voxel grids follow the package convention: occupancy ``(D, H, W)`` = (depth, y, x) of the
reference camera frame and ``voxel_to_camera (4, 4)`` maps the homogeneous index
``(d, h, w, 1)`` to the camera-frame point ``(x, y, z, 1)`` (pixels of the reference
image), voxel centres at integer indices.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from . import native_library
from .cameras import ScaledOrthographic
from .surrogates import check_axes, object_share

__all__ = [
    "plane_axes",
    "plane_centre",
    "plane_extent",
    "plane_points",
    "average_masks",
    "project_proposals",
    "score_proposals",
    "keypoint_misses",
    "rank_proposals",
    "SelectionReference",
    "class_reference",
    "Selection",
    "select_proposals",
    "vote_proposals",
    "boundary_voxels",
    "supersampling",
]


# --------------------------------------------------------------------------- planes


def plane_axes(axes: torch.Tensor) -> torch.Tensor:
    """In-plane axes of the three planes: ``(3, 2, 3)``, ``[j] = (e_a, e_b)``.

    ``e_a = axes[(j+1) % 3]``, ``e_b = axes[(j+2) % 3]`` (cyclic, so ``e_a x e_b = e_j``
    for a right-handed ``axes``).

    Args:
        axes: ``(3, 3)`` principal axes (rows).
    """
    check_axes(axes)
    idx = torch.tensor([[1, 2], [2, 0], [0, 1]], device=axes.device)
    return axes[idx]


def plane_centre(S: torch.Tensor) -> torch.Tensor:
    """Centroid ``(3,)`` of the finite rows of a mean shape ``S (K, 3)``: the natural plane centre."""
    if not isinstance(S, torch.Tensor) or S.dim() != 2 or S.shape[-1] != 3:
        raise ValueError("S must be a (K, 3) tensor")
    X = S[torch.isfinite(S).all(dim=-1)]
    if X.shape[0] == 0:
        raise ValueError("S has no finite row")
    return X.mean(dim=0)


def plane_extent(S: torch.Tensor, factor: float = 1.3, centre: torch.Tensor | None = None) -> float:
    """Half-width of the selection planes: ``factor`` x the largest distance of a finite
    keypoint of ``S`` from ``centre`` (default: their centroid, :func:`plane_centre`).

    Args:
        S: ``(K, 3)`` mean shape, object units; NaN rows ignored.
        factor: margin (``> 0``).
        centre: optional ``(3,)``; use the same centre for the plane functions.

    Returns:
        a positive float (object units).

    Example:
        >>> plane_extent(torch.tensor([[1.0, 0, 0], [-1.0, 0, 0]]))
        1.3
    """
    if not factor > 0:
        raise ValueError(f"factor must be > 0, got {factor}")
    c = plane_centre(S) if centre is None else centre.to(S)
    X = S[torch.isfinite(S).all(dim=-1)]
    r = float((X - c).norm(dim=-1).max())
    if not r > 0:
        raise ValueError("S must have two distinct finite keypoints to define a plane extent")
    return factor * r


def _check_plane(plane_size: int, extent: float | None) -> None:
    if extent is None:
        raise ValueError("extent is required: the planes' half-width in object units, e.g. plane_extent(S)")
    if int(plane_size) < 2:
        raise ValueError(f"plane_size must be >= 2, got {plane_size}")
    extent = float(extent)
    if not (extent > 0 and math.isfinite(extent)):
        raise ValueError(f"extent must be a positive finite float, got {extent}")


def plane_points(axes: torch.Tensor, plane_size: int, extent: float,
                 centre: torch.Tensor | None = None) -> torch.Tensor:
    """Object-frame points of the three plane grids: ``(3, G, G, 3)``.

    ``[j, i, k] = centre + a_k e_a + b_i e_b`` (module docstring), ``G = plane_size``.

    Example:
        >>> plane_points(torch.eye(3), 3, 1.0)[2, 0, 2]   # plane 2: (e_a, e_b) = (x, y)
        tensor([ 1., -1.,  0.])
    """
    _check_plane(plane_size, extent)
    extent = float(extent)
    pa = plane_axes(axes)  # (3, 2, 3)
    g = torch.linspace(-extent, extent, int(plane_size), dtype=axes.dtype, device=axes.device)
    pts = g[None, None, :, None] * pa[:, None, None, 0, :] + g[None, :, None, None] * pa[:, None, None, 1, :]
    if centre is not None:
        pts = pts + centre.to(pts)
    return pts


# --------------------------------------------------------------------------- average masks


def average_masks(
    masks: torch.Tensor,
    cameras: ScaledOrthographic,
    labels: torch.Tensor,
    axes: torch.Tensor,
    plane_size: int = 64,
    extent: float | None = None,
    centre: torch.Tensor | None = None,
    mode: str = "bilinear",
    chunk: int = 256,
    weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Average mask of each principal direction's cluster, in the class frame.

    Every member ``n`` of cluster ``j`` (``labels[n] == j``) is aligned into plane ``j``
    by its camera: the plane point ``centre + a e_a + b e_b`` is projected into image
    ``n`` (``cameras.project``) and the mask looked up there (``grid_sample``,
    ``align_corners=True`` with ``norm = 2 pix / (size - 1) - 1``, zeros outside the
    image). For a view exactly along ``+-e_j`` this is the silhouette in plane
    coordinates; a back view sees the plane mirrored and the projection undoes it. The
    aligned masks of a cluster are averaged.

    Args:
        masks: ``(N, H, W)`` bool, canvas masks.
        cameras: ``N`` cameras (canvas pixels) of the same instances.
        labels: ``(N,)`` long cluster labels in ``{-1, 0, 1, 2}``.
        axes: ``(3, 3)`` principal axes (rows).
        plane_size: ``G``.
        extent: half-width of the planes (object units), e.g. :func:`plane_extent`;
            required (the ``None`` default only raises).
        centre: optional ``(3,)`` plane centre (default the object-frame origin).
        mode: ``"bilinear"`` (soft) or ``"nearest"`` lookup.
        chunk: members aligned at once (bounds memory; not a per-instance loop).
        weights: optional ``(N,)`` non-negative member weights (e.g.
            :func:`carvi_torch.surrogates.object_share`): each average is then the weighted mean.

    Returns:
        ``averages (3, G, G)`` float32 in ``[0, 1]`` (zeros for a direction without
        members) and ``counts (3,)`` long, members per direction; on the masks' device.
    """
    if not isinstance(masks, torch.Tensor) or masks.dim() != 3:
        raise ValueError("masks must be a (N, H, W) tensor")
    n, h, w = masks.shape
    if len(cameras) != n:
        raise ValueError(f"cameras must hold N={n} cameras like masks, got {len(cameras)}")
    if not isinstance(labels, torch.Tensor) or labels.shape != (n,):
        raise ValueError(f"labels must be a ({n},) tensor")
    if mode not in ("bilinear", "nearest"):
        raise ValueError(f"mode must be 'bilinear' or 'nearest', got {mode!r}")
    check_axes(axes)
    _check_plane(plane_size, extent)
    extent = float(extent)
    if h < 2 or w < 2:
        raise ValueError("masks must be at least 2x2 pixels")
    dev = masks.device
    G = int(plane_size)
    labels = labels.to(dev).long()
    pts = plane_points(axes.to(device=dev, dtype=torch.float32), G, extent, centre).reshape(3, G * G, 3)
    members = (labels >= 0).nonzero().squeeze(-1)
    counts = torch.bincount(labels[members], minlength=3)[:3]
    sums = torch.zeros(3, G * G, dtype=torch.float32, device=dev)
    scale = torch.tensor([2.0 / (w - 1), 2.0 / (h - 1)], device=dev)
    cameras = cameras.to(device=dev, dtype=torch.float32)
    if int(chunk) < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    chunk = int(chunk)
    weights = torch.ones(n, device=dev) if weights is None else weights.to(device=dev, dtype=torch.float32)
    for start in range(0, members.numel(), chunk):
        idx = members[start : start + chunk]
        cams = cameras[idx]
        uv = cams.project(pts[labels[idx]])  # (c, G*G, 2)
        grid = (uv * scale - 1.0).reshape(-1, G, G, 2)
        m = masks[idx].to(torch.float32).unsqueeze(1)  # (c, 1, H, W)
        vals = F.grid_sample(m, grid, mode=mode, padding_mode="zeros", align_corners=True)  # (c,1,G,G)
        sums.index_add_(0, labels[idx], vals.reshape(-1, G * G) * weights[idx, None])
    total = torch.zeros(3, dtype=sums.dtype, device=dev).index_add_(0, labels[members], weights[members])
    averages = sums / torch.where(total > 0, total, torch.ones_like(total))[:, None]
    return averages.reshape(3, G, G), counts


# --------------------------------------------------------------------------- proposals


def _check_grids(occupancy: torch.Tensor, voxel_to_camera: torch.Tensor) -> None:
    if not isinstance(occupancy, torch.Tensor) or occupancy.dim() != 4:
        raise ValueError("occupancy must be a (B, D, H, W) tensor")
    b = occupancy.shape[0]
    if not isinstance(voxel_to_camera, torch.Tensor) or voxel_to_camera.shape != (b, 4, 4):
        raise ValueError(f"voxel_to_camera must be ({b}, 4, 4) like occupancy's batch")


#: Default ``chunk_voxels`` of :func:`project_proposals` per device type.
_CHUNK_VOXELS = {"cpu": 1 << 20, "cuda": 1 << 27}
#: Default ``chunk_voxels`` of :func:`project_proposals` with the compiled splat, per torch intra-op thread (its
#: threads take whole grids; at least the torch operators' CPU chunk).
_NATIVE_CHUNK_VOXELS_PER_THREAD = 1 << 19
#: Default ``chunk_points`` of :func:`project_proposals` per device type.
_CHUNK_POINTS = {"cpu": 1 << 22, "cuda": 1 << 24}


def boundary_voxels(occupancy: torch.Tensor) -> torch.Tensor:
    """``(B, D, H, W)`` bool: occupied voxels with an empty voxel (or the grid edge) among their 26 neighbours.

    The 3x3x3 dilation of the empty set (padded with empty voxels) is separable: an OR over
    three shifted slices along each axis in turn, on bool tensors (a few passes over
    ``B D H W`` bytes; no float pooling).
    """
    B, D, H, W = occupancy.shape
    empty = torch.ones(B, D + 2, H + 2, W + 2, dtype=torch.bool, device=occupancy.device)
    torch.bitwise_not(occupancy, out=empty[:, 1:-1, 1:-1, 1:-1])
    near = torch.bitwise_or(empty[:, :-2], empty[:, 1:-1])
    near |= empty[:, 2:]  # (B, D, H + 2, W + 2)
    near2 = torch.bitwise_or(near[:, :, :-2], near[:, :, 1:-1])
    near2 |= near[:, :, 2:]  # (B, D, H, W + 2)
    near3 = torch.bitwise_or(near2[..., :-2], near2[..., 1:-1])
    near3 |= near2[..., 2:]  # (B, D, H, W)
    near3 &= occupancy
    return near3


def supersampling(A: torch.Tensor, spacing: float, supersample: int | None) -> torch.Tensor:
    """``(B, 3)`` long sub-voxel points per index axis of each grid (the rule of :func:`project_proposals`)."""
    if supersample is not None:
        return torch.full((A.shape[0], 3), int(supersample), dtype=torch.long, device=A.device)
    edges = A[:, :, :3].norm(dim=1)  # (B, 3) voxel edge per index axis, object units
    return torch.ceil(math.sqrt(3.0) * edges / spacing).clamp(1, 8).long()


def _axis_tables(U: torch.Tensor, sizes: tuple[int, int, int], ms: tuple[int, int, int]) -> list[torch.Tensor]:
    """Plane-sample coordinates of the sub-voxel points, one lookup table per index axis.

    For grids ``U (b, 3, 4)`` (plane units per index, constant last), the point of voxel
    ``(d, h, w)`` with sub-voxel offsets ``(o_d, o_h, o_w)`` has coordinates
    ``Ld[:, i_d, b*D + d] + Lh[:, i_h, b*H + h] + Lw[:, i_w, b*W + w]`` (float32 sums of
    float64 products rounded once), ``o = (i + 0.5) / m - 0.5``.

    Returns:
        ``[Ld, Lh, Lw]``, each ``(3 * m, b * size)`` float32 (row ``c * m + i``: coordinate ``c``, offset ``i``).
    """
    dev = U.device
    out = []
    for axis, (size, m) in enumerate(zip(sizes, ms)):
        pos = ((torch.arange(m, dtype=torch.float64, device=dev)[:, None] + 0.5) / m - 0.5
               + torch.arange(size, dtype=torch.float64, device=dev))  # (m, size)
        L = U[:, :, axis].T[:, None, :, None] * pos[None, :, None, :]  # (3, m, b, size)
        if axis == 0:
            L = L + U[:, :, 3].T[:, None, :, None]
        out.append(L.to(torch.float32).reshape(3 * m, -1))
    return out


def _splat_operators(device: torch.device, native: bool | None):
    """The compiled library's operators when the splat runs there (``native``: None = on the CPU where the
    library loads, False = never, True = always, an error where it cannot)."""
    return None if native is False else native_library.operators_on(device, required=bool(native))


def _splat(out: torch.Tensor, occupancy: torch.Tensor, U: torch.Tensor, rows: torch.Tensor, ms: tuple[int, int, int],
           G: int, chunk_points: int, ops=None) -> None:
    """Set the plane samples hit by the sub-voxel points of the boundary voxels of some grids.

    Args:
        out: ``(B * 3 * (G + 2)^2,)`` bool planes with a one-sample border that takes every
            point off the plane (coordinates are clamped to ``[-1, G]``).
        occupancy: ``(B, D, H, W)`` bool grids of every plane set in ``out``.
        U: ``(b, 3, 4)`` index -> plane-sample coordinates of the grids ``rows``, all with the sub-sampling ``ms``.
        rows: ``(b,)`` long the grids to splat (their positions in ``occupancy`` and ``out``).
        ops: the compiled library's operators (:func:`_splat_operators`): its ``splat_planes`` does the same
            (``carvi_torch/kernels/splat_planes.h``, the same float32 sums and rounding, the grids in parallel);
            None: torch operators, ``chunk_points`` sub-voxel points at a time.
    """
    dev = occupancy.device
    D, H, W = occupancy.shape[1:]
    md, mh, mw = ms
    m3 = md * mh * mw
    Gp = G + 2
    Ld, Lh, Lw = _axis_tables(U, (D, H, W), ms)
    if ops is not None:  # the kernel reads the grids in place
        ops.splat_planes(out, occupancy, Ld, Lh, Lw, rows.contiguous(), md, mh, mw, G)
        return
    occupancy = occupancy[rows]
    voxels = boundary_voxels(occupancy).nonzero()  # (M, 4) b, d, h, w
    base = rows * (3 * Gp * Gp) + Gp + 1  # + Gp + 1: the border shift of both coordinates
    per = max(1, int(chunk_points) // m3)
    for start in range(0, voxels.shape[0], per):
        bi, di, hi, wi = voxels[start:start + per].unbind(-1)
        M = bi.shape[0]
        g = [torch.empty(3, m, M, device=dev) for m in ms]
        for L, gi, idx, m in ((Ld, g[0], bi * D + di, md), (Lh, g[1], bi * H + hi, mh), (Lw, g[2], bi * W + wi, mw)):
            flat_g = gi.view(3 * m, M)
            for r in range(3 * m):  # 1-D gathers (the fast kind)
                torch.index_select(L[r], 0, idx, out=flat_g[r])
        u = g[0][:, :, None, None, :] + g[1][:, None, :, None, :]
        u = u + g[2][:, None, None, :, :]  # (3, md, mh, mw, M)
        k = u.view(3, m3, M).round_().clamp_(-1, G).long()
        at = base[bi]
        for j in range(3):  # the three planes: (a, b) = (u[(j+1)%3], u[(j+2)%3])
            a, b = (j + 1) % 3, (j + 2) % 3
            flat = torch.add(k[a], k[b], alpha=Gp)
            flat += at + j * Gp * Gp
            out.index_fill_(0, flat.view(-1), True)


def _splat_settings(dev: torch.device, native: bool | None, chunk_points: int | None, chunk_voxels: int | None):
    """``(operators, chunk_points, chunk_voxels)`` of :func:`project_proposals` on ``dev``: the compiled splat's
    operators (or ``None``: the torch operators) and the chunk sizes, their defaults filled in and checked."""
    ops = _splat_operators(dev, native)
    kind = dev.type if dev.type in _CHUNK_VOXELS else "cuda"
    if chunk_voxels is None:
        chunk_voxels = _CHUNK_VOXELS[kind] if ops is None else max(
            _CHUNK_VOXELS["cpu"], _NATIVE_CHUNK_VOXELS_PER_THREAD * torch.get_num_threads())
    chunk_points = _CHUNK_POINTS[kind] if chunk_points is None else chunk_points
    if int(chunk_points) < 1 or int(chunk_voxels) < 1:
        raise ValueError(f"chunk_points and chunk_voxels must be >= 1, got {chunk_points}, {chunk_voxels}")
    return ops, chunk_points, chunk_voxels


def _plane_map(voxel_to_camera: torch.Tensor, ref_cameras: ScaledOrthographic, axes: torch.Tensor,
               centre: torch.Tensor | None, dev: torch.device) -> torch.Tensor:
    """``A (B, 3, 4)`` float64: plane coordinates along the three axes of each grid's voxel index, ``c = A h``
    (``c = axes R^T (T[:3] h - [t, 0]) / s - axes centre``); checked finite."""
    B = voxel_to_camera.shape[0]
    T = voxel_to_camera.to(device=dev, dtype=torch.float64)
    cams = ref_cameras.to(device=dev, dtype=torch.float64)
    shift = torch.zeros(B, 3, 4, dtype=torch.float64, device=dev)
    shift[:, :2, 3] = cams.t
    ax = axes.to(device=dev, dtype=torch.float64)
    A = ax @ cams.R.transpose(-1, -2) @ (T[:, :3, :] - shift) / cams.s[:, None, None]
    if centre is not None:
        A[:, :, 3] -= ax @ centre.to(device=dev, dtype=torch.float64)
    if not bool(torch.isfinite(A).all()):
        raise ValueError("voxel_to_camera and ref_cameras must map every grid to finite plane coordinates")
    return A


def project_proposals(
    occupancy: torch.Tensor,
    voxel_to_camera: torch.Tensor,
    ref_cameras: ScaledOrthographic,
    axes: torch.Tensor,
    plane_size: int = 64,
    extent: float | None = None,
    centre: torch.Tensor | None = None,
    supersample: int | None = None,
    chunk_points: int | None = None,
    chunk_voxels: int | None = None,
    native: bool | None = None,
) -> torch.Tensor:
    """Orthographic projections of voxel proposals onto the three principal planes.

    Each occupied voxel is treated as a cube (edges = the first three columns of
    ``voxel_to_camera``) sampled at ``m_d m_h m_w`` sub-voxel points (offsets
    ``(i + 0.5) / m - 0.5``, ``i < m``, along each index axis). The points go to the
    reference camera frame, to the object frame (``ref_cameras.from_camera_frame``), to
    plane coordinates ``(a, b)`` (module docstring) -- one affine map per grid, applied
    through per-axis lookup tables -- and set their nearest plane sample (round half to
    even).

    Holes: the automatic sub-sampling takes, for each grid, ``m_i = ceil(sqrt(3) * edge_i /
    spacing)`` points along each index axis ``i`` (``edge_i`` that grid's voxel edge along the
    axis in object units; ``spacing = 2 extent / (G - 1)``; clipped to 8). The voxel edges are
    orthogonal, so the sub-cubes' half-diagonal ``sqrt(sum (edge_i / m_i)^2) / 2`` is at most
    ``spacing / 2``: every plane sample whose centre lies in the projection of an occupied
    voxel cube is set (no holes, even for voxels coarser than the plane), and a set sample's
    centre lies within ``spacing / 2`` of that projection (a dilation of at most half a
    sample). The rule is per grid, so a grid's projection does not depend on the other grids
    of the batch (grids are processed in groups of equal ``m``).

    Only boundary voxels are splatted (occupied voxels with an empty voxel, or the grid's
    edge, among their 26 neighbours): a ray through an occupied cube leaves the occupied set
    through a boundary cube, so the projection is the same, at a fraction of the cost.

    Args:
        occupancy: ``(B, D, H, W)`` bool proposals.
        voxel_to_camera: ``(B, 4, 4)`` index -> reference camera frame.
        ref_cameras: ``B`` reference cameras (the frame of each grid).
        axes: ``(3, 3)`` principal axes (rows).
        plane_size: ``G``.
        extent: plane half-width (object units), required (see :func:`plane_extent`).
        centre: optional ``(3,)`` plane centre (default the object-frame origin).
        supersample: ``m`` (``>= 1``) or ``None`` for the rule above.
        chunk_points: sub-voxel points handled at once by the torch operators (bounds memory); default
            ``2**22`` on the CPU, ``2**24`` on other devices. The compiled splat takes no such chunks.
        chunk_voxels: voxels of the grids handled at once (the torch operators' dense boundary pass; the
            compiled splat's grids go to its threads a chunk at a time); default ``2**20`` on the CPU with the
            torch operators (a few MB stay in its caches), ``2**19`` per intra-op thread and at least ``2**20``
            with the compiled splat (4 grids of 60^3 on 2 threads, 38 on 16), ``2**27`` on other devices (few,
            large kernels).
        native: the boundary test and the splat in the compiled library's ``splat_planes``
            (``carvi_torch/kernels/splat_planes.h``; the same planes bit for bit, the grids in parallel on torch's
            intra-op threads): None (default) on the CPU where the library loads, False never, True always (an
            error where it cannot).

    Returns:
        ``(B, 3, G, G)`` bool on the occupancy's device.
    """
    _check_grids(occupancy, voxel_to_camera)
    check_axes(axes)
    _check_plane(plane_size, extent)
    extent = float(extent)
    B = occupancy.shape[0]
    if len(ref_cameras) != B:
        raise ValueError(f"ref_cameras must hold B={B} cameras, got {len(ref_cameras)}")
    if supersample is not None and int(supersample) < 1:
        raise ValueError(f"supersample must be None or >= 1, got {supersample}")
    ops, chunk_points, chunk_voxels = _splat_settings(occupancy.device, native, chunk_points, chunk_voxels)
    dev = occupancy.device
    G = int(plane_size)
    Gp = G + 2
    if B == 0:
        return torch.zeros(0, 3, G, G, dtype=torch.bool, device=dev)
    A = _plane_map(voxel_to_camera, ref_cameras, axes, centre, dev)
    spacing = 2.0 * extent / (G - 1)
    ms = supersampling(A, spacing, supersample)
    # In plane-sample units u = (c + extent) / spacing, a sample's index is round(u).
    U = A / spacing
    U[:, :, 3] += extent / spacing
    D, H, W = occupancy.shape[1:]
    out = torch.zeros(B * 3 * Gp * Gp, dtype=torch.bool, device=dev)
    groups: dict[tuple, list[int]] = {}
    for b, key in enumerate(map(tuple, ms.tolist())):  # one host read per call
        groups.setdefault(key, []).append(b)
    per = max(1, int(chunk_voxels) // max(1, D * H * W))
    if ops is not None:
        occupancy = occupancy.contiguous()  # once: the kernel reads every chunk's grids in place
    for key, members in groups.items():
        members = torch.tensor(members, device=dev)
        for c0 in range(0, len(members), per):
            rows = members[c0:c0 + per]
            _splat(out, occupancy, U[rows], rows, key, G, chunk_points, ops)
    return out.view(B, 3, Gp, Gp)[:, :, 1:-1, 1:-1].contiguous()


def score_proposals(projections: torch.Tensor, averages: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Distance of each proposal to the class average: lower is better.

    ``score[b] = sum_{j : counts[j] > 0} mean_{i,k} |projections[b, j, i, k] - averages[j, i, k]|``.

    Args:
        projections: ``(B, 3, G, G)`` bool or float (:func:`project_proposals`).
        averages: ``(3, G, G)`` float (:func:`average_masks`).
        counts: ``(3,)`` members per direction.

    Returns:
        ``(B,)`` float32 (zeros if no direction has members).
    """
    if not isinstance(projections, torch.Tensor) or projections.dim() != 4 or projections.shape[1] != 3:
        raise ValueError("projections must be a (B, 3, G, G) tensor")
    if not isinstance(averages, torch.Tensor) or averages.shape != projections.shape[1:]:
        raise ValueError(f"averages must be {tuple(projections.shape[1:])} like the projections' planes")
    if not isinstance(counts, torch.Tensor) or counts.shape != (3,):
        raise ValueError("counts must be a (3,) tensor")
    diff = (projections.to(torch.float32) - averages.to(device=projections.device, dtype=torch.float32)).abs()
    per_dir = diff.mean(dim=(-2, -1))  # (B, 3)
    use = (counts.to(projections.device) > 0).to(torch.float32)
    return (per_dir * use).sum(dim=-1)


def keypoint_misses(
    occupancy: torch.Tensor, voxel_to_camera: torch.Tensor, keypoints: torch.Tensor, visible: torch.Tensor,
    columns: torch.Tensor | None = None,
) -> torch.Tensor:
    """Visible reference keypoints that the proposal's silhouette does not cover.

    The grid must be aligned with the reference camera (``voxel_to_camera[:2, 0] == 0``:
    the depth index moves along the viewing ray only), so a ray is a column ``(h, w)``.
    A keypoint ``(x, y)`` is mapped to its nearest column by inverting the 2x2 block
    ``voxel_to_camera[:2, 1:3]``; it is missed when that column has no occupied voxel
    or lies outside the grid.

    Args:
        occupancy: ``(B, D, H, W)`` bool.
        voxel_to_camera: ``(B, 4, 4)``.
        keypoints: ``(B, K, 2)`` reference keypoints, canvas pixels ``(x, y)``.
        visible: ``(B, K)`` bool.
        columns: optional ``(B, H, W)`` bool ``occupancy.any(dim=1)`` when known already
            (:attr:`carvi_torch.carve.ProposalGrids.columns`); saves a pass over the grids.

    Returns:
        ``(B,)`` long.
    """
    _check_grids(occupancy, voxel_to_camera)
    B, D, H, W = occupancy.shape
    if (not isinstance(keypoints, torch.Tensor) or keypoints.dim() != 3 or keypoints.shape[0] != B
            or keypoints.shape[-1] != 2):
        raise ValueError(f"keypoints must be a ({B}, K, 2) tensor")
    K = keypoints.shape[1]
    if not isinstance(visible, torch.Tensor) or visible.shape != (B, K):
        raise ValueError(f"visible must be a ({B}, {K}) tensor")
    dev = occupancy.device
    T = voxel_to_camera.to(device=dev, dtype=torch.float64)
    scale = T[:, :2, 1:3].abs().amax(dim=(-2, -1)).clamp_min(1e-12)
    if bool((T[:, :2, 0].abs() > 1e-6 * scale[:, None]).any()):
        raise ValueError("voxel_to_camera must align the depth index with the viewing ray (T[:2, 0] == 0)")
    if columns is not None and tuple(columns.shape) != (B, H, W):
        raise ValueError(f"columns must be ({B}, {H}, {W}) like occupancy.any(dim=1), got {tuple(columns.shape)}")
    column = occupancy.any(dim=1) if columns is None else columns.to(dev).bool()  # (B, H, W)
    rhs = keypoints.to(device=dev, dtype=torch.float64) - T[:, None, :2, 3]  # (B, K, 2)
    hw = torch.linalg.solve(T[:, None, :2, 1:3].expand(B, K, 2, 2), rhs)  # (B, K, 2) = (h, w)
    hw = torch.round(hw)
    finite = torch.isfinite(hw).all(dim=-1)
    hi = torch.nan_to_num(hw[..., 0], nan=-1.0)
    wi = torch.nan_to_num(hw[..., 1], nan=-1.0)
    inside = finite & (hi >= 0) & (hi <= H - 1) & (wi >= 0) & (wi <= W - 1)
    hi = hi.clamp(0, H - 1).long()
    wi = wi.clamp(0, W - 1).long()
    bidx = torch.arange(B, device=dev)[:, None].expand(B, K)
    covered = inside & column[bidx, hi, wi]
    return (visible.to(dev).bool() & ~covered).sum(dim=-1)


def rank_proposals(
    scores: torch.Tensor, misses: torch.Tensor, valid: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Order every reference's proposals: valid first, then fewest keypoint misses, then
    lowest score (NaN scores after finite ones); ties keep the proposal order.

    Args:
        scores: ``(R, P)`` float (:func:`score_proposals`).
        misses: ``(R, P)`` int (:func:`keypoint_misses`).
        valid: ``(R, P)`` bool.

    Returns:
        ``order (R, P)`` long proposal indices, best first, and ``best (R,)`` long, the
        best valid proposal, ``-1`` for a reference with none.

    Example:
        >>> order, best = rank_proposals(torch.tensor([[0.1, 0.2, 0.0]]), torch.tensor([[1, 0, 0]]),
        ...                              torch.tensor([[True, True, False]]))
        >>> order.tolist(), best.tolist()
        ([[1, 0, 2]], [1])
    """
    if not isinstance(scores, torch.Tensor) or scores.dim() != 2:
        raise ValueError("scores must be a (R, P) tensor")
    if not isinstance(misses, torch.Tensor) or misses.shape != scores.shape:
        raise ValueError(f"misses must be {tuple(scores.shape)} like scores")
    if not isinstance(valid, torch.Tensor) or valid.shape != scores.shape:
        raise ValueError(f"valid must be {tuple(scores.shape)} like scores")
    dev = scores.device
    s = torch.nan_to_num(scores.to(torch.float64), nan=float("inf"))
    isnan = torch.isnan(scores)
    # Successive stable sorts, least significant key first.
    order = torch.argsort(s, dim=-1, stable=True)
    order = order.gather(1, torch.argsort(isnan.gather(1, order).to(torch.int8), dim=-1, stable=True))
    order = order.gather(1, torch.argsort(misses.to(dev).long().gather(1, order), dim=-1, stable=True))
    invalid = ~valid.to(dev).bool()
    order = order.gather(1, torch.argsort(invalid.gather(1, order).to(torch.int8), dim=-1, stable=True))
    any_valid = valid.to(dev).bool().any(dim=-1)
    if order.shape[1]:
        best = torch.where(any_valid, order[:, 0], torch.full_like(order[:, 0], -1))
    else:
        best = torch.full((order.shape[0],), -1, dtype=torch.long, device=dev)
    return order, best


# --------------------------------------------------------------------------- a class's selection


@dataclass
class SelectionReference:
    """What every proposal of a class is scored against: the average masks on the three planes.

    Attributes:
        axes: ``(3, 3)`` principal directions (rows); centre: ``(3,)``; extent: half-side of the
            planes (object units); averages: ``(3, G, G)`` float average masks; counts: ``(3,)``
            long members per average (:func:`average_masks`).
    """

    axes: torch.Tensor
    centre: torch.Tensor
    extent: float
    averages: torch.Tensor
    counts: torch.Tensor
    plane_size: int


def class_reference(shape: torch.Tensor, masks: torch.Tensor, cameras: ScaledOrthographic, labels: torch.Tensor,
                    axes: torch.Tensor, plane_size: int, groups: torch.Tensor | None = None) -> SelectionReference:
    """The class's :class:`SelectionReference` from its mean shape ``(K, 3)``, masks ``(N, H, W)``,
    cameras ``(N)``, cluster labels ``(N,)`` and principal directions ``(3, 3)``. With ``groups``
    (``(N,)`` long physical objects) every member is weighted by
    :func:`carvi_torch.surrogates.object_share`, so each object counts once in its cluster's average."""
    centre = plane_centre(shape)
    extent = plane_extent(shape, centre=centre)
    weights = None if groups is None else object_share(labels, groups.to(labels.device))
    avg, counts = average_masks(masks, cameras, labels, axes, plane_size=plane_size, extent=extent, centre=centre,
                                weights=weights)
    return SelectionReference(axes, centre, extent, avg, counts, plane_size)


@dataclass
class Selection:
    """The ranked proposals of ``R`` references with ``P`` proposals each (host tensors but the grids and the
    selected occupancy).

    Attributes:
        grids: the carved proposals (:class:`carvi_torch.carve.ProposalGrids`, on the device).
        pos: ``(R * P,)`` long position of each proposal in ``grids`` (-1: not carved).
        scores: ``(R, P)`` float (``inf``: not carved); misses: ``(R, P)`` long (``10**6``: not carved).
        ok: ``(R, P)`` bool valid and not empty; valid: ``(R, P)`` bool a valid triplet.
        best: ``(R,)`` long best proposal (-1: none).
        best_occupancy: ``(R, D, H, W)`` bool selected grids, on the grids' device (the writer meshes them
            there and takes them to the host once); best_transform: ``(R, 4, 4)`` float64 voxel -> canvas.
    """

    grids: object
    pos: torch.Tensor
    scores: torch.Tensor
    misses: torch.Tensor
    ok: torch.Tensor
    valid: torch.Tensor
    best: torch.Tensor
    best_occupancy: torch.Tensor
    best_transform: torch.Tensor

    def take_grids(self, rows: list[int], grids) -> None:
        """References ``rows`` (positions in this selection) take ``grids`` (:class:`carvi_torch.carve.ProposalGrids`
        of ``len(rows)``, e.g. puffballs where no proposal was left) as their selected shape: ``best`` -1."""
        idx = torch.as_tensor(rows, dtype=torch.long)
        self.best_occupancy[idx.to(self.best_occupancy.device)] = grids.occupancy.to(self.best_occupancy.device)
        self.best_transform[idx] = grids.voxel_to_camera.double().cpu()
        self.best[idx.to(self.best.device)] = -1


def vote_proposals(occupancy: torch.Tensor, voxel_to_camera: torch.Tensor, rows: torch.Tensor
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Voxel-wise majority vote of several proposals of each reference, on a common grid.

    The proposals of one reference share their grid's columns (the reference's box) and differ only
    in their depth range. The common grid spans the union of the voted proposals' depth ranges with
    the same number ``D`` of depth steps; each proposal is read there at its nearest depth (empty
    outside its range), and a voxel is occupied when more than half of the voted proposals hold it.
    A column that the vote leaves empty but the first proposal fills keeps the first proposal's
    column (so imprinting's guarantee, every foreground column filled, holds). With one proposal the
    result is that proposal, voxel for voxel.

    Args:
        occupancy: ``(B, D, H, W)`` bool carved proposals; voxel_to_camera: ``(B, 4, 4)``, aligned
            with the reference camera (depth index along ``z`` only).
        rows: ``(R, K)`` long positions in ``B`` of each reference's voted proposals, best first, ``-1``
            unused (the first of every row must be used).

    Returns:
        ``occupancy (R, D, H, W)`` bool and ``voxel_to_camera (R, 4, 4)`` float64.

    Example:
        >>> occ = torch.zeros(3, 4, 1, 1, dtype=torch.bool)
        >>> occ[0, 1:3], occ[1, 1:4], occ[2, 0:1] = True, True, True
        >>> T = torch.eye(4).expand(3, 4, 4).clone(); T[:, 2, 0] = 1.0; T[:, 2, 3] = 0.0
        >>> out, T_out = vote_proposals(occ, T, torch.tensor([[0, 1, 2]]))
        >>> out[0, :, 0, 0].tolist()
        [False, True, True, False]
    """
    R, K = rows.shape
    B, D = occupancy.shape[:2]
    dev = occupancy.device
    used = rows >= 0
    r = rows.clamp(min=0).to(dev)
    T = voxel_to_camera.to(device=dev, dtype=torch.float64)[r]  # (R, K, 4, 4)
    sz, z0 = T[..., 2, 0], T[..., 2, 3]
    z_end = z0 + sz * (D - 1)
    inf = torch.full_like(z0, math.inf)
    lo = torch.where(used, torch.minimum(z0, z_end), inf).amin(dim=1)
    hi = torch.where(used, torch.maximum(z0, z_end), -inf).amax(dim=1)
    step = (hi - lo) / max(D - 1, 1)
    first_up = sz[:, 0] >= 0  # keep the first proposal's depth direction
    start = torch.where(first_up, lo, hi)
    step = torch.where(first_up, step, -step)
    z = start[:, None] + step[:, None] * torch.arange(D, device=dev, dtype=torch.float64)  # (R, D)
    votes = torch.zeros((R,) + tuple(occupancy.shape[1:]), dtype=torch.int16, device=dev)
    first = None
    for k in range(K):
        step_k = torch.where(sz[:, k, None] == 0, 1.0, sz[:, k, None])
        idx = torch.round((z - z0[:, k, None]) / step_k)
        inside = (idx >= 0) & (idx <= D - 1) & used[:, k, None]
        read = occupancy[r[:, k, None], idx.clamp(0, D - 1).long()] & inside[..., None, None]  # (R, D, H, W)
        votes += read
        if k == 0:
            first = read
    out = votes * 2 > used.sum(dim=1).to(dev)[:, None, None, None]
    lost = ~out.any(dim=1) & first.any(dim=1)  # (R, H, W)
    out = torch.where(lost[:, None], first, out)
    T_out = T[:, 0].clone()
    T_out[:, 2, 0], T_out[:, 2, 3] = step, start
    return out, T_out


def select_proposals(grids, keep: torch.Tensor, valid: torch.Tensor, cameras: ScaledOrthographic,
                     keypoints: torch.Tensor, visible: torch.Tensor, reference: SelectionReference,
                     consensus: int = 1) -> Selection:
    """Score, rank and pick the best of every reference's proposals.

    Args:
        grids: :class:`carvi_torch.carve.ProposalGrids` of the carved proposals ``keep``.
        keep: ``(B,)`` long positions, in the ``R * P`` reference-major proposals, of the carved ones.
        valid: ``(R, P)`` bool valid triplets.
        cameras: ``(B)`` reference cameras of the carved proposals; keypoints: ``(B, K, 2)``;
            visible: ``(B, K)`` bool.
        reference: the class's :class:`SelectionReference`.
        consensus: the selected grid is the majority vote (:func:`vote_proposals`) of this many of the
            best-ranked valid proposals (``1``: the best proposal alone, the paper's choice).

    Returns:
        :class:`Selection`; the scores and ranks come back to the host in one transfer each, the
        selected grids stay on the device (the writer meshes them there).
    """
    R, P = valid.shape
    dev = valid.device
    ref = reference
    proj = project_proposals(grids.occupancy, grids.voxel_to_camera, cameras, ref.axes, plane_size=ref.plane_size,
                             extent=ref.extent, centre=ref.centre)
    sc = score_proposals(proj, ref.averages, ref.counts)
    miss = keypoint_misses(grids.occupancy, grids.voxel_to_camera, keypoints, visible, columns=grids.columns)
    scores = torch.full((R * P,), float("inf"), device=dev)
    misses = torch.full((R * P,), 10 ** 6, dtype=torch.long, device=dev)
    empty = torch.ones(R * P, dtype=torch.bool, device=dev)
    scores[keep], misses[keep], empty[keep] = sc, miss, grids.empty
    ok = valid.reshape(-1) & ~empty
    order, best = rank_proposals(scores.view(R, P), misses.view(R, P), ok.view(R, P))
    pos = torch.full((R * P,), -1, dtype=torch.long, device=dev)
    pos[keep] = torch.arange(len(keep), device=dev)
    if len(keep) and consensus > 1:
        top = order[:, :consensus]
        rows = torch.where(ok.view(R, P).gather(1, top), pos.view(R, P).gather(1, top), torch.full_like(top, -1))
        rows[:, 0] = rows[:, 0].clamp(min=0)  # a reference without a valid proposal: a placeholder, never used
        best_occ, best_T = vote_proposals(grids.occupancy, grids.voxel_to_camera, rows)
        best_T = best_T.cpu()
    elif len(keep):
        best_pos = pos.view(R, P).gather(1, best.clamp(min=0)[:, None])[:, 0].clamp(min=0)
        best_occ = grids.occupancy[best_pos]
        best_T = grids.voxel_to_camera[best_pos].double().cpu()
    else:  # no valid proposal: nothing will be written
        n = grids.occupancy.shape[-1]
        best_occ = torch.zeros(R, n, n, n, dtype=torch.bool, device=grids.occupancy.device)
        best_T = torch.zeros(R, 4, 4, dtype=torch.float64)
    return Selection(grids=grids, pos=pos.cpu(), scores=scores.view(R, P).cpu(), misses=misses.view(R, P).cpu(),
                     ok=ok.view(R, P).cpu(), valid=valid.cpu(), best=best.cpu(), best_occupancy=best_occ,
                     best_transform=best_T)
