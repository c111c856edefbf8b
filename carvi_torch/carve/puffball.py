"""Puffball: a shape from one silhouette alone, the last fallback of an object no proposal can carve.

Twarog, Tappen, Adelson, "Playing with Puffball: simple scale-invariant inflation for use in
vision and graphics" (2012): the union of the balls of the medial axis, blended softly, gives a
height field ``h(x, y)`` over the mask; the solid is the slab ``|z| <= h(x, y)``, symmetric about
depth 0 (the object origin's depth in the reference camera frame). :func:`puffball_grids`
voxelises it on the carving's grids (:mod:`carvi_torch.carve.geometry`: the mask box tiled by
``resolution - 2`` cells plus one exterior voxel each side), so the pipeline treats it like any
carved proposal.

Example:
    >>> m = torch.zeros(1, 24, 24, dtype=torch.bool); m[0, 6:18, 8:16] = True
    >>> g = puffball_grids(m, resolution=12)
    >>> g.occupancy.shape, bool(g.occupancy.any()), bool(g.empty[0])
    (torch.Size([1, 12, 12, 12]), True, False)
"""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from skimage import morphology

from .grids import ProposalGrids

__all__ = ["medial_balls", "puffball_height", "puffball_grids", "check_mask"]


def check_mask(mask) -> torch.Tensor:
    """``mask`` as a ``(H, W)`` bool tensor; ``ValueError`` for any other number of dimensions."""
    m = torch.as_tensor(mask)
    if m.dim() != 2:
        raise ValueError(f"mask must be (H, W), got {tuple(m.shape)}")
    return m.bool()


def medial_balls(mask: torch.Tensor, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Medial-axis points of a silhouette and their grassfire radii (CPU-side: scikit-image).

    ``skimage.morphology.medial_axis(mask, return_distance=True)``: the skeleton pixels and,
    for each, the Euclidean distance from its centre to the nearest background pixel
    centre (pixels). The ball of that radius around a medial point holds foreground pixel
    centres only. scikit-image breaks ties in the thinning at random; ``seed`` fixes them,
    so the result is deterministic.

    Args:
        mask: ``(H, W)`` bool silhouette (any device).
        seed: seed of the tie-breaking.

    Returns:
        ``centres (M, 2)`` float32 ``(x, y)`` pixel coordinates and ``radii (M,)`` float32,
        on the mask's device. An empty mask gives ``M = 0``.

    Example:
        >>> m = torch.zeros(5, 5, dtype=torch.bool); m[1:4, 1:4] = True
        >>> c, r = medial_balls(m)
        >>> c[r.argmax()].tolist(), float(r.max())
        ([2.0, 2.0], 2.0)
    """
    m = check_mask(mask)
    skel, dist = morphology.medial_axis(m.cpu().numpy(), return_distance=True, rng=seed)
    ys, xs = np.nonzero(skel)
    centres = torch.from_numpy(np.stack([xs, ys], axis=1).astype(np.float32))
    radii = torch.from_numpy(dist[ys, xs].astype(np.float32))
    return centres.to(m.device), radii.to(m.device)


def puffball_height(mask: torch.Tensor, chunk_elems: int = 1 << 24) -> torch.Tensor:
    """Puffball height field of a silhouette (pixels), as the reference implementation blends it.

    For a foreground pixel ``p`` and the medial balls ``(q, r_q)`` of :func:`medial_balls`
    that cover it (``|p - q| <= r_q``),

        ``h(p) = log(1 + sum_q exp(sqrt(r_q^2 - |p - q|^2)))``,

    a soft maximum of the heights of the balls' upper hemispheres (it exceeds the largest
    by at most ``log(1 + number of covering balls)``). Evaluated for pixels x medial points
    in chunks of at most ``chunk_elems`` pairs, with ``logsumexp`` for stability; squared
    distances between pixel centres are integers, so the covering test is exact. A
    foreground pixel no medial ball covers (rare, digital medial axes are not exact) is
    given its own ball, of its distance to the background. Background pixels get 0.

    Args:
        mask: ``(H, W)`` bool.
        chunk_elems: pixel x medial-point pairs per chunk.

    Returns:
        ``(H, W)`` float32 on the mask's device; ``h >= log 2`` on the foreground.
    """
    m = check_mask(mask)
    centres, radii = medial_balls(m)
    h = torch.zeros(m.shape, dtype=torch.float32, device=m.device)
    if centres.shape[0] == 0:
        return h
    ys, xs = torch.nonzero(m, as_tuple=True)
    pix = torch.stack([xs, ys], dim=1).float()  # (N, 2)
    per = max(1, chunk_elems // centres.shape[0])
    r2 = torch.round(radii.double() ** 2).float()  # squared distances between pixel centres: integers
    out = []
    for s in range(0, pix.shape[0], per):
        diff = pix[s:s + per, None, :] - centres[None, :, :]  # (n, M, 2), exact for pixel coordinates
        d2 = (diff * diff).sum(-1)  # (n, M)
        cover = d2 <= r2[None, :]
        height = torch.sqrt(torch.clamp(r2[None, :] - d2, min=0.0))
        lse = torch.logsumexp(torch.where(cover, height, torch.full_like(height, -torch.inf)), dim=1)
        out.append(torch.where(cover.any(dim=1), torch.logaddexp(torch.zeros_like(lse), lse),
                               torch.full_like(lse, torch.nan)))
    val = torch.cat(out)
    lost = torch.isnan(val)
    if bool(lost.any()):
        from ..sdf import distance_to_background

        own = distance_to_background(m[None].cpu())[0].to(m.device)[ys[lost], xs[lost]]
        val[lost] = torch.logaddexp(torch.zeros_like(own), own)
    h[ys, xs] = val
    return h


def _grid_axes(mask: torch.Tensor, hmax: float, n: int) -> torch.Tensor:
    """``voxel_to_camera (4, 4)`` of a puffball grid: the mask box in x, y and ``[-hmax, hmax]`` in depth,
    each tiled by ``n - 2`` cells plus one exterior voxel on each side (the carving's layout)."""
    ys, xs = torch.nonzero(mask, as_tuple=True)
    lo = torch.stack([xs.min(), ys.min()]).double() - 0.5
    hi = torch.stack([xs.max(), ys.max()]).double() + 0.5
    zl, zh = -hmax - 0.5, hmax + 0.5
    sx, sy = (hi - lo) / (n - 2)
    sz = (zh - zl) / (n - 2)
    T = torch.zeros(4, 4, dtype=torch.float64)
    T[0, 2], T[0, 3] = sx, lo[0] - sx / 2
    T[1, 1], T[1, 3] = sy, lo[1] - sy / 2
    T[2, 0], T[2, 3] = sz, zl - sz / 2
    T[3, 3] = 1.0
    return T


def _voxelise(h: torch.Tensor, T: torch.Tensor, n: int) -> torch.Tensor:
    """``(n, n, n)`` bool: voxels whose centre satisfies ``|z| <= h(x, y)``, ``h`` read at the nearest pixel
    (the silhouette is the mask's pixels, as a carved hull's is)."""
    H, W = h.shape
    idx = torch.arange(n, dtype=torch.float64)
    x = T[0, 2] * idx + T[0, 3]
    y = T[1, 1] * idx + T[1, 3]
    z = T[2, 0] * idx + T[2, 3]
    gx = 2 * x / max(W - 1, 1) - 1
    gy = 2 * y / max(H - 1, 1) - 1
    grid = torch.stack(torch.meshgrid(gy, gx, indexing="ij")[::-1], dim=-1).float()  # (n, n, 2) as (x, y)
    hv = F.grid_sample(h[None, None].float(), grid[None], mode="nearest", padding_mode="zeros",
                       align_corners=True)[0, 0]  # (n: y, n: x)
    return (z.abs()[:, None, None] <= hv.double()[None]) & (hv[None] > 0)


def puffball_grids(masks: torch.Tensor, resolution: int = 60) -> ProposalGrids:
    """Puffball solids of ``B`` silhouettes as carving results, one grid each.

    Args:
        masks: ``(B, H, W)`` bool canvas silhouettes (the references).
        resolution: voxels per axis.

    Returns:
        :class:`~carvi_torch.carve.grids.ProposalGrids` on the masks' device (``empty`` for an empty
        mask; ``column_cost`` is 0 where the mask covers a column's centre, 1 elsewhere).
    """
    if masks.dim() != 3:
        raise ValueError(f"masks must be (B, H, W), got {tuple(masks.shape)}")
    n, dev = int(resolution), masks.device
    B = masks.shape[0]
    occ = torch.zeros(B, n, n, n, dtype=torch.bool)
    T = torch.eye(4, dtype=torch.float64).repeat(B, 1, 1)
    for b in range(B):
        m = masks[b].cpu().bool()
        if not bool(m.any()):
            continue
        h = puffball_height(m)
        T[b] = _grid_axes(m, float(h.max()), n)
        occ[b] = _voxelise(h, T[b], n)
    columns = occ.any(dim=1)
    return ProposalGrids(occupancy=occ.to(dev), voxel_to_camera=T.float().to(dev),
                         empty=~occ.flatten(1).any(dim=1).to(dev), reference_columns=columns.to(dev),
                         column_cost=torch.where(columns, 0.0, 1.0).to(dev), cost=None, columns=columns.to(dev))
