"""Carving geometry: silhouettes prepared once per class, grid bounds, voxel -> sampling maps.

Frames and units
----------------
* **Silhouettes** are exact signed distance maps ``sdf (M, H, W)`` (pixels, negative
  inside, zero level half-way between a foreground and a background pixel centre:
  :func:`carvi_torch.sdf.signed_distance`) with scaled orthographic cameras
  ``ScaledOrthographic (M)`` in the same canvas pixels (image x right, y down, pixel
  centres at integers).
* **Reference camera frame** of proposal ``b``: ``p = (x, y, z) = (u, v, depth)`` in
  pixels of the reference canvas; depth 0 is the object-frame origin
  (``z = s_r R_r[2] . X``). A point ``p`` maps to the object frame by
  ``cameras[r].from_camera_frame(p)`` and into view ``m`` by ``cameras[m].project``;
  composed, ``u_m = A p + c`` with ``A = (s_m / s_r) R_m[:2] R_r^T`` (2x3) and
  ``c = t_m - A[:, :2] t_r``: one affine map per (proposal, view), folded together
  with the voxel-to-camera map and the normalisation of ``grid_sample`` into one
  ``(2, 4)`` matrix from voxel indices to sampling coordinates.
* **Voxel grid**: ``(D, H, W)`` = (depth, y, x) indices with ``D = H = W =
  resolution``, voxel centres at integer indices, and ``voxel_to_camera (4, 4)``
  mapping ``(d, h, w, 1)`` to ``(x, y, z, 1)``::

      x = x0 + sx * w,   y = y0 + sy * h,   z = z0 + sz * d

  i.e. ``voxel_to_camera = [[0, 0, sx, x0], [0, sy, 0, y0], [sz, 0, 0, z0], [0, 0, 0, 1]]``
  (a permutation of axes, so its determinant is ``-sx sy sz < 0``). Spacing is
  **anisotropic**: each axis has its own step, so that every proposal has the same
  ``(D, H, W)`` and a batch is one tensor.
* **Bounds**. ``x`` and ``y``: the reference mask's bounding box extended by half a
  pixel (the zero level of the sdf) is the *extent*; it is tiled by ``resolution -
  2`` voxel cells (centres ``1 .. resolution - 2``, cell edges on the extent's
  edges, so a box-shaped hull has exactly its volume) plus one voxel on each side
  whose centre lies half a voxel outside the extent: the outer layer is always
  exterior. Depth: every interior point projects inside each view's
  mask, hence inside its bounding box; with the reference box this bounds ``z``
  through each row of ``u_m = A p + c`` (interval arithmetic, one interval per view
  and image axis, intersected). The result is capped to ``|z| <= s_r max_m rho_m /
  s_m`` where ``rho_m`` is the radius of view ``m``'s mask around ``t_m`` (the
  projection of the object origin) plus one pixel diagonal: the ball of the largest
  silhouette, in object units times the reference scale. The cap only binds when the
  views leave depth (nearly) unconstrained, e.g. a reference with only its own
  mirror, whose view direction is parallel to it. Inconsistent views (an empty
  intersection) give the span between their intervals; the depth extent is at least
  one pixel. The depth extent is tiled like ``x`` and ``y``.

Example:
    >>> masks = torch.zeros(1, 32, 32, dtype=torch.bool); masks[0, 8:24, 10:22] = True
    >>> box, nonempty, radius = mask_geometry(torch.where(masks, -1.0, 1.0), torch.tensor([[16.0, 16.0]]))
    >>> box[0].tolist(), bool(nonempty[0])
    ([9.5, 21.5, 7.5, 23.5], True)
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from ..cameras import ScaledOrthographic

__all__ = ["PAD", "BIG", "UNUSED", "CarveMaps", "prepare_maps", "extend_maps", "mask_geometry", "proposal_geometry",
           "column_hw", "column_terms", "check_indices", "check_sdf", "as_maps"]

#: Width (pixels) of the band that extends every distance map beyond its canvas.
PAD = 8


#: Finite stand-in for ``+inf`` distances (empty masks).
BIG = 1.0e6


#: Cone value of an unused view slot: below any real cost, so never the maximum.
UNUSED = -1.0e30


#: Maps extended (and measured) at once by :func:`prepare_maps` (bounds its temporary memory).
_PREP_CHUNK = 256


@dataclass
class CarveMaps:
    """Silhouettes prepared once for many carvings: extended maps, cameras, mask geometry.

    A carving reads every map it uses many times (once per proposal that uses it), so the
    per-map work -- checks, the extension beyond the canvas (:func:`extend_maps`), bounding
    boxes and radii (:func:`mask_geometry`) -- is done once here, and a proposal names its
    views by *entry* index. An entry is a map seen by one camera; several entries may share
    a map (:meth:`with_entries`, e.g. the rotated cameras of a rotationally symmetric
    reference), so no map is ever copied per proposal.

    Attributes:
        ext: ``(K + 1, H + 2 PAD, W + 2 PAD)`` float32 extended maps; the last one is the
            unused-slot map (``UNUSED`` everywhere).
        entry_map: ``(M,)`` long, the map (row of ``ext``) of each entry.
        cameras: ``ScaledOrthographic (M)`` float64, one per entry.
        box: ``(M, 4)`` float64, nonempty: ``(M,)`` bool, radius: ``(M,)`` float64: the
            :func:`mask_geometry` of each entry (the radius is about the entry's ``t``).
        size: ``(H, W)`` of the canvas.
    """

    ext: torch.Tensor
    entry_map: torch.Tensor
    cameras: ScaledOrthographic
    box: torch.Tensor
    nonempty: torch.Tensor
    radius: torch.Tensor
    size: tuple[int, int]

    def __len__(self) -> int:
        return self.entry_map.shape[0]

    @property
    def device(self) -> torch.device:
        return self.ext.device

    @property
    def unused(self) -> int:
        """Row of ``ext`` that unused view slots sample."""
        return self.ext.shape[0] - 1

    def sdf(self, i: int | torch.Tensor) -> torch.Tensor:
        """The canvas part of the map(s) of entry ``i``: ``(H, W)`` (or ``(n, H, W)``) float32 signed distances."""
        return self.ext[self.entry_map[i]][..., PAD:-PAD, PAD:-PAD]

    def with_entries(self, maps: torch.Tensor, cameras: ScaledOrthographic) -> "CarveMaps":
        """These entries plus ``E`` more: entry ``M + e`` is map ``maps[e]`` seen by ``cameras[e]``.

        Args:
            maps: ``(E,)`` long map indices (rows of ``ext``, ``< K``), e.g. ``entry_map[i]``.
            cameras: ``ScaledOrthographic (E)`` in the canvas pixels of those maps.
        """
        maps = torch.as_tensor(maps, device=self.device).long().reshape(-1)
        if len(cameras) != maps.shape[0]:
            raise ValueError(f"with_entries: {maps.shape[0]} maps but {len(cameras)} cameras")
        if maps.numel() and (int(maps.min()) < 0 or int(maps.max()) >= self.unused):
            raise ValueError(f"with_entries: map indices must lie in [0, {self.unused})")
        cams = _checked_cameras(cameras, self.device)
        box, nonempty, radius = _chunked_geometry(self.ext, maps, cams.t)
        return CarveMaps(self.ext, torch.cat([self.entry_map, maps]), ScaledOrthographic.cat([self.cameras, cams]),
                         torch.cat([self.box, box]), torch.cat([self.nonempty, nonempty]),
                         torch.cat([self.radius, radius]), self.size)


def _checked_cameras(cameras, device) -> ScaledOrthographic:
    if not isinstance(cameras, ScaledOrthographic):
        raise ValueError(f"cameras must be a ScaledOrthographic, got {type(cameras).__name__}")
    cams = cameras.to(device=device, dtype=torch.float64)
    if len(cams) and not bool(((cams.s > 0) & torch.isfinite(cams.s)).all()):
        raise ValueError("cameras.s must be finite and positive")
    return cams


def _chunked_geometry(ext: torch.Tensor, maps: torch.Tensor, t: torch.Tensor):
    """:func:`mask_geometry` of the canvas part of ``ext[maps]`` about ``t``, a chunk of maps at a time."""
    parts = [mask_geometry(ext[maps[i:i + _PREP_CHUNK], PAD:-PAD, PAD:-PAD], t[i:i + _PREP_CHUNK])
             for i in range(0, maps.shape[0], _PREP_CHUNK)]
    if not parts:
        dev = ext.device
        return (torch.zeros(0, 4, dtype=torch.float64, device=dev), torch.zeros(0, dtype=torch.bool, device=dev),
                torch.zeros(0, dtype=torch.float64, device=dev))
    return tuple(torch.cat(x) for x in zip(*parts))


def prepare_maps(sdf, cameras: ScaledOrthographic, *, count: int | None = None) -> CarveMaps:
    """Prepare signed distance maps for :func:`carve_proposals` (entry ``i`` = map ``i`` seen by ``cameras[i]``).

    Args:
        sdf: ``(M, H, W)`` float signed distance maps (:func:`carvi_torch.sdf.signed_distance`),
            or a function ``sdf(start, stop) -> (stop - start, H, W)`` giving them a chunk at a
            time (then ``count = M`` is required), so the full ``sdf`` never needs to exist
            beside the extended maps.
        cameras: ``ScaledOrthographic (M)`` in the maps' pixels.
        count: ``M`` when ``sdf`` is a function.

    Returns:
        :class:`CarveMaps`. Values are the same, bit for bit, as the maps
        :func:`carve_proposals` prepares from a plain ``sdf`` tensor.
    """
    if callable(sdf) and not isinstance(sdf, torch.Tensor):
        if count is None:
            raise ValueError("prepare_maps: count is required when sdf is a function")
        M, source = int(count), sdf
    else:
        if not isinstance(sdf, torch.Tensor) or sdf.dim() != 3 or not sdf.is_floating_point():
            raise ValueError(f"sdf must be a floating (M, H, W) tensor, got {getattr(sdf, 'shape', type(sdf))}")
        M, source = sdf.shape[0], (lambda a, b: sdf[a:b])
    if M == 0:
        raise ValueError("sdf must hold at least one map")
    if not isinstance(cameras, ScaledOrthographic) or len(cameras) != M:
        raise ValueError(f"cameras must be a ScaledOrthographic of length {M} (one per map), got "
                         f"{len(cameras) if isinstance(cameras, ScaledOrthographic) else type(cameras)}")
    ext = None
    for start in range(0, M, _PREP_CHUNK):
        part = source(start, min(M, start + _PREP_CHUNK))
        if not isinstance(part, torch.Tensor) or part.dim() != 3 or not part.is_floating_point():
            raise ValueError(f"sdf must give floating (n, H, W) maps, got {getattr(part, 'shape', type(part))}")
        H, W = part.shape[1:]
        if H < 2 or W < 2:
            raise ValueError(f"sdf maps must be at least 2x2 pixels, got {tuple(part.shape[1:])}")
        if torch.isnan(part).any():
            raise ValueError(f"sdf contains NaN (maps {start} to {start + part.shape[0] - 1})")
        if ext is None:
            ext = torch.empty(M + 1, H + 2 * PAD, W + 2 * PAD, device=part.device)
            ext[M] = UNUSED
        ext[start:start + part.shape[0]] = extend_maps(part.detach().to(torch.float32).clamp(-BIG, BIG))
    cams = _checked_cameras(cameras, ext.device)
    entry = torch.arange(M, device=ext.device)
    box, nonempty, radius = _chunked_geometry(ext, entry, cams.t)
    return CarveMaps(ext, entry, cams, box, nonempty, radius, (ext.shape[1] - 2 * PAD, ext.shape[2] - 2 * PAD))


def check_indices(M: int, reference, views, resolution, device):
    """Proposal indices as long tensors on ``device``, checked against ``M`` entries (one host read)."""
    reference = torch.as_tensor(reference, device=device)
    views = torch.as_tensor(views, device=device)
    if reference.dim() != 1 or reference.is_floating_point() or reference.dtype == torch.bool:
        raise ValueError(f"reference must be a (B,) integer tensor, got {tuple(reference.shape)} {reference.dtype}")
    B = reference.shape[0]
    if views.dim() != 2 or views.shape[0] != B or views.is_floating_point() or views.dtype == torch.bool:
        raise ValueError(f"views must be a (B, V) = ({B}, V) integer tensor, got {tuple(views.shape)} {views.dtype}")
    if not isinstance(resolution, int) or not 4 <= resolution <= 2048:
        raise ValueError(f"resolution must be an int in [4, 2048], got {resolution!r}")
    reference, views = reference.long(), views.long()
    if B:
        lo_r, hi_r, lo_v, hi_v = torch.stack([reference.min(), reference.max(),
                                              views.min() if views.numel() else reference.min(),
                                              views.max() if views.numel() else reference.min()]).tolist()
        if lo_r < 0 or hi_r >= M:
            raise ValueError(f"reference indices must lie in [0, {M}), got range [{lo_r}, {hi_r}]")
        if views.numel() and (lo_v < -1 or hi_v >= M):
            raise ValueError(f"views indices must lie in [0, {M}) or be -1 (unused), got range [{lo_v}, {hi_v}]")
    return reference, views


def check_sdf(sdf, cameras) -> int:
    """Check plain ``(M, H, W)`` maps and their ``M`` cameras; returns ``M``."""
    if not isinstance(sdf, torch.Tensor) or sdf.dim() != 3 or not sdf.is_floating_point():
        raise ValueError(f"sdf must be a floating (M, H, W) tensor, got {getattr(sdf, 'shape', type(sdf))}")
    M, H, W = sdf.shape
    if M == 0 or H < 2 or W < 2:
        raise ValueError(f"sdf must hold at least one map of at least 2x2 pixels, got {tuple(sdf.shape)}")
    if not isinstance(cameras, ScaledOrthographic) or len(cameras) != M:
        raise ValueError(f"cameras must be a ScaledOrthographic of length {M} (one per map), got "
                         f"{len(cameras) if isinstance(cameras, ScaledOrthographic) else type(cameras)}")
    return M


def as_maps(sdf, cameras, reference, views, resolution):
    """``(CarveMaps, reference, views)``: the given maps, or the maps of a plain ``sdf`` tensor.

    From a plain tensor only the maps the proposals use are prepared, and the indices are
    renumbered into them.
    """
    if isinstance(sdf, CarveMaps):
        if cameras is not None and cameras is not sdf.cameras:
            raise ValueError("pass cameras=None with prepared CarveMaps (they hold their cameras)")
        reference, views = check_indices(len(sdf), reference, views, resolution, sdf.device)
        return sdf, reference, views
    M = check_sdf(sdf, cameras)
    reference, views = check_indices(M, reference, views, resolution, sdf.device)
    used, inverse = torch.unique(torch.cat([reference, views.clamp(min=0).flatten()]), return_inverse=True)
    if used.numel() == 0:
        used = torch.zeros(1, dtype=torch.long, device=sdf.device)
    maps = prepare_maps(sdf[used], cameras.to(sdf.device)[used])
    ref_u = inverse[: reference.shape[0]]
    views_u = torch.where(views >= 0, inverse[reference.shape[0]:].view_as(views), torch.full_like(views, -1))
    return maps, ref_u, views_u


def _mm(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Small matrix product ``a (..., n, k) @ b (..., k, m)`` written as elementwise sums.

    Unlike ``@`` (which may pick different BLAS kernels for different batch sizes),
    the result of each entry does not depend on the batch, so a proposal carved
    alone gets bit-identical coordinates to the same proposal carved in a batch.
    """
    out = a[..., :, 0, None] * b[..., None, 0, :]
    for k in range(1, a.shape[-1]):
        out = out + a[..., :, k, None] * b[..., None, k, :]
    return out


def mask_geometry(sdf: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bounding boxes and radii of the masks ``sdf < 0``.

    Args:
        sdf: ``(K, H, W)`` float signed distance maps.
        t: ``(K, 2)`` image position of each camera's object origin.

    Returns:
        ``box (K, 4)`` float64 ``(x_lo, x_hi, y_lo, y_hi)``: the extent of the
        silhouette (foreground pixel centres extended by half a pixel; the whole
        canvas for an empty mask); ``nonempty (K,)`` bool; ``radius (K,)`` float64:
        largest distance from ``t`` to a foreground pixel centre plus one pixel
        diagonal (0 for an empty mask).
    """
    K, H, W = sdf.shape
    fg = sdf < 0
    cols = fg.any(dim=1)  # (K, W)
    rows = fg.any(dim=2)  # (K, H)
    nonempty = cols.any(dim=1)
    x_lo = cols.int().argmax(dim=1)
    x_hi = W - 1 - cols.flip(1).int().argmax(dim=1)
    y_lo = rows.int().argmax(dim=1)
    y_hi = H - 1 - rows.flip(1).int().argmax(dim=1)
    half = torch.tensor([-0.5, 0.5, -0.5, 0.5], device=sdf.device, dtype=torch.float64)
    box = torch.stack([x_lo, x_hi, y_lo, y_hi], dim=1).double() + half
    full = torch.tensor([-0.5, W - 0.5, -0.5, H - 0.5], device=sdf.device, dtype=torch.float64)
    box = torch.where(nonempty[:, None], box, full)
    xs = torch.arange(W, device=sdf.device, dtype=torch.float64)
    ys = torch.arange(H, device=sdf.device, dtype=torch.float64)
    t = t.to(torch.float64)
    d2 = (xs[None, None, :] - t[:, 0, None, None]) ** 2 + (ys[None, :, None] - t[:, 1, None, None]) ** 2
    far = torch.where(fg, d2, torch.zeros((), dtype=torch.float64, device=sdf.device)).flatten(1).amax(dim=1)
    radius = torch.where(nonempty, far.sqrt() + math.sqrt(2.0), torch.zeros_like(far))
    return box, nonempty, radius


def proposal_geometry(box: torch.Tensor, nonempty: torch.Tensor, radius: torch.Tensor, cams: ScaledOrthographic,
                      reference: torch.Tensor, views: torch.Tensor, resolution: int, map_size: tuple[int, int]):
    """Grid bounds and the index -> sampling-coordinate maps of a batch of proposals.

    Args:
        box, nonempty, radius: per map, from :func:`mask_geometry` (``(M, 4)``, ``(M,)``, ``(M,)``).
        cams: ``ScaledOrthographic (M)`` (float64 preferred).
        reference: ``(B,)`` long map indices; views: ``(B, V)`` long, ``-1`` = unused.
        resolution: voxels per axis.
        map_size: ``(Hp, Wp)`` size of the extended maps that are sampled
            (canvas plus ``PAD`` on each side).

    Returns:
        ``T (B, 4, 4)`` float64 voxel_to_camera; ``G (B, V, 2, 4)`` float64 mapping
        ``(d, h, w, 1)`` to the ``grid_sample`` coordinates (``align_corners=True``) of
        the view's extended map; ``G_ref (B, 2, 4)`` the same for the reference (its
        depth column is exactly 0); ``scale (B, V)`` float64 ``s_r / s_m`` (1 for
        unused slots).
    """
    f64 = dict(dtype=torch.float64, device=box.device)
    B, V = views.shape
    valid = views >= 0
    vi = views.clamp(min=0)
    R, s, t = cams.R.to(**f64), cams.s.to(**f64), cams.t.to(**f64)
    sr = s[reference]
    rb = box[reference]
    A, c = _view_maps(R, s, t, reference, vi)
    z_lo, z_hi = _depth_bounds(A, c, rb, box[vi].reshape(B, V, 2, 2), valid & nonempty[vi])
    rho = torch.where(valid, radius[vi] / s[vi], torch.zeros_like(s[vi]))
    cap = sr * torch.maximum(radius[reference] / sr, rho.amax(dim=1) if V else torch.zeros_like(sr))
    T = _voxel_to_camera(rb, z_lo, z_hi, cap, resolution)

    Hp, Wp = map_size
    norm = torch.tensor([2.0 / (Wp - 1), 2.0 / (Hp - 1)], **f64)
    G = _to_sampling(T, A, c, norm)
    eye = torch.eye(3, **f64)[:2].expand(B, 2, 3)
    G_ref = _to_sampling(T, eye, torch.zeros(B, 2, **f64), norm)
    scale = torch.where(valid, sr[:, None] / s[vi], torch.ones_like(s[vi]))
    return T, G, G_ref, scale


def _view_maps(R: torch.Tensor, s: torch.Tensor, t: torch.Tensor, reference: torch.Tensor, vi: torch.Tensor
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """``u_m = A p + c``, ``p`` in the reference camera frame: ``A (B, V, 2, 3)``, ``c (B, V, 2)`` float64 of the
    views ``vi (B, V)``, from every map's ``R (M, 3, 3)``, ``s (M,)``, ``t (M, 2)``."""
    Rr, sr, tr = R[reference], s[reference], t[reference]
    A = (s[vi] / sr[:, None])[..., None, None] * _mm(R[vi][:, :, :2, :], Rr.transpose(-1, -2)[:, None])  # (B, V, 2, 3)
    c = t[vi] - _mm(A[..., :2], tr[:, None, :, None])[..., 0]  # (B, V, 2)
    return A, c


def _depth_bounds(A: torch.Tensor, c: torch.Tensor, rb: torch.Tensor, vb: torch.Tensor, seen: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth interval ``(B,)``, ``(B,)`` of the reference box ``rb (B, 4)`` that every view keeps inside its box.

    ``A (B, V, 2, 3)``, ``c (B, V, 2)``: :func:`_view_maps`; ``vb (B, V, axis, lo/hi)``: the views' boxes;
    ``seen (B, V)`` bool: slots that bound (used, non-empty). One interval per image axis (interval
    arithmetic); inconsistent views give the span between their bounds; no view bounds: infinite."""
    B = A.shape[0]
    a0, a1, a2 = A[..., 0], A[..., 1], A[..., 2]  # (B, V, 2)
    X0, X1 = rb[:, 0, None, None], rb[:, 1, None, None]
    Y0, Y1 = rb[:, 2, None, None], rb[:, 3, None, None]
    xy_lo = torch.minimum(a0 * X0, a0 * X1) + torch.minimum(a1 * Y0, a1 * Y1)
    xy_hi = torch.maximum(a0 * X0, a0 * X1) + torch.maximum(a1 * Y0, a1 * Y1)
    lo = vb[..., 0] - c - xy_hi  # a2 z >= lo
    hi = vb[..., 1] - c - xy_lo  # a2 z <= hi
    usable = seen[..., None] & (a2.abs() > 1e-9)
    safe = torch.where(usable, a2, torch.ones_like(a2))
    z_a, z_b = lo / safe, hi / safe
    inf = torch.full_like(z_a, math.inf)
    unbounded = torch.full((B, 1), math.inf, dtype=torch.float64, device=A.device)  # so that V = 0 reduces too
    z_lo = torch.cat([torch.where(usable, torch.minimum(z_a, z_b), -inf).flatten(1), -unbounded], 1).amax(dim=1)
    z_hi = torch.cat([torch.where(usable, torch.maximum(z_a, z_b), inf).flatten(1), unbounded], 1).amin(dim=1)
    return torch.minimum(z_lo, z_hi), torch.maximum(z_lo, z_hi)


def _voxel_to_camera(rb: torch.Tensor, z_lo: torch.Tensor, z_hi: torch.Tensor, cap: torch.Tensor, n: int
                     ) -> torch.Tensor:
    """``T (B, 4, 4)`` float64 voxel ``(d, h, w, 1)`` -> reference camera frame.

    x, y: the reference box ``rb (B, 4)`` tiled by ``n - 2`` voxel cells, plus one voxel each side; depth: the
    interval ``z_lo``-``z_hi`` ``(B,)`` clipped to ``[-cap, cap]`` and at least one pixel long, tiled likewise."""
    sx = (rb[:, 1] - rb[:, 0]) / (n - 2)
    sy = (rb[:, 3] - rb[:, 2]) / (n - 2)
    x0 = rb[:, 0] - sx / 2
    y0 = rb[:, 2] - sy / 2
    z_lo = torch.minimum(torch.maximum(z_lo, -cap), cap)
    z_hi = torch.minimum(torch.maximum(z_hi, -cap), cap)
    mid, half = (z_lo + z_hi) / 2, torch.clamp((z_hi - z_lo) / 2, min=0.5)
    z_lo, z_hi = mid - half, mid + half
    sz = (z_hi - z_lo) / (n - 2)
    z0 = z_lo - sz / 2
    T = torch.zeros(rb.shape[0], 4, 4, dtype=torch.float64, device=rb.device)
    T[:, 0, 2], T[:, 0, 3] = sx, x0
    T[:, 1, 1], T[:, 1, 3] = sy, y0
    T[:, 2, 0], T[:, 2, 3] = sz, z0
    T[:, 3, 3] = 1.0
    return T


def _to_sampling(T: torch.Tensor, Am: torch.Tensor, cm: torch.Tensor, norm: torch.Tensor) -> torch.Tensor:
    """``(..., 2, 4)`` voxel index -> ``grid_sample`` coordinates of maps ``u = Am p + cm`` (``(..., 2, 3)``,
    ``(..., 2)``), through ``T (B, 4, 4)`` and the extended map's ``norm (2,)``."""
    B = T.shape[0]
    T3 = T[:, :3].reshape((B,) + (1,) * (Am.dim() - 3) + (3, 4))
    P = _mm(Am, T3)
    P[..., 3] = P[..., 3] + cm + PAD
    P = P * norm[:, None]
    P[..., 3] = P[..., 3] - 1.0
    return P


def extend_maps(sdf: torch.Tensor, pad: int = PAD) -> torch.Tensor:
    """Extend distance maps beyond their canvas by a band of ``pad`` pixels.

    The band holds ``sdf(clamp(q)) + |q - clamp(q)|`` at pixel centre ``q``: the value of
    the nearest canvas pixel plus the distance to the canvas, so outside the canvas is
    outside the silhouette (a foreground pixel on the border has ``sdf = -0.5``).

    Args:
        sdf: ``(K, H, W)`` float.

    Returns:
        ``(K, H + 2 pad, W + 2 pad)`` float32; ``out[:, pad:-pad, pad:-pad] == sdf``.
    """
    K, H, W = sdf.shape
    rep = F.pad(sdf[:, None].to(torch.float32), (pad, pad, pad, pad), mode="replicate")[:, 0]
    q = lambda n: torch.arange(-pad, n + pad, device=sdf.device, dtype=torch.float32)  # noqa: E731
    dx = torch.clamp(-q(W), min=0) + torch.clamp(q(W) - (W - 1), min=0)
    dy = torch.clamp(-q(H), min=0) + torch.clamp(q(H) - (H - 1), min=0)
    return rep + torch.sqrt(dy[:, None] ** 2 + dx[None, :] ** 2)


def column_hw(cols: torch.Tensor, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat column indices ``h * width + w`` (any shape, long, ``0 <= h, w < width <= 2048``) to float32 ``(h, w)``.

    In float32 arithmetic (about 3x faster than int64 division on the CPU in a scratch measurement)
    and exact: ``h = floor((c + 0.5) / width)``, where ``c + 0.5`` is exact (``c < 2**22``) and
    the exact quotient ``h + (w + 0.5) / width`` lies at least ``0.5 / width >= 2**-12`` from
    every integer, more than the error of either division a device may use: correctly rounded
    (the CPU) or a multiply by the rounded reciprocal (CUDA's tensor-by-scalar division), each
    within about an ulp of a value below 2048 (``2**-13``). ``tests/test_carve.py`` checks both
    forms at every width up to 2048.
    """
    c = cols.to(torch.float32)
    h = torch.floor((c + 0.5) / width)
    return h, c - h * width


def column_terms(G: torch.Tensor, h: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """In-plane part of the sampling coordinates of columns, for any number of maps per proposal.

    Args:
        G: ``(N, ..., 2, 4)`` float32 index -> sampling maps (e.g. ``(N, 2, 4)``, or
            ``(N, V, 2, 4)`` for every view slot at once).
        h, w: ``(N, K)`` float32 row and column indices of the columns (:func:`column_hw`).

    Returns:
        ``(N, ..., 2, K)`` float32: ``(G[..., i, 1] h + G[..., i, 2] w) + G[..., i, 3]``
        (elementwise, so a column's value depends neither on which other columns are present
        nor on how many maps are computed at once).
    """
    shape = (h.shape[0],) + (1,) * (G.dim() - 2) + (h.shape[1],)
    h, w = h.view(shape), w.view(shape)
    return (G[..., 1, None] * h + G[..., 2, None] * w) + G[..., 3, None]
