"""A per-object ``quality`` in [0, 1] (higher: more reliable): what the run itself can tell about an object's error.

Signals (each computed where the information exists, ``None`` otherwise):

- ``keypoint_residual``: RMS distance between the object's visible keypoints and the final camera's
  projection of the mean shape (of the object's shape group), as a fraction of the canvas side.
- ``visible_keypoints``: how many keypoints the object shows (what SfM had to go on).
- ``refinement_deg``: angle (degrees) by which silhouette refinement turned the SfM camera (a large
  turn: keypoints and silhouette disagreed).
- ``rotational``: the class is rotationally symmetric (its viewpoint about the axis is a guess).
- ``silhouette_inside``: fraction of the projected mean-shape keypoints that land inside the mask
  (recorded, not combined: it did not rank the errors, see docs/export.md).
- ``mirror_deg``: angle (degrees) between the camera of the object and the camera of its mirrored
  copy mirrored back (``diag(-1, 1, 1) R P`` with ``P`` the symmetry plane): the two are estimated
  separately, so their disagreement is a self-consistency check of the viewpoint.
- ``camera_from``: ``sfm`` / ``ground_truth`` / ``mean_shape`` / ``silhouette`` (cameras.json).
- ``reconstruction_iou``: IoU of the selected reconstruction's silhouette (its occupancy projected
  along the reference camera's rays) with the mask, in canvas pixels.
- ``surrogates_from``: which surrogate fallback made the reconstruction (``puffball`` the last).

:func:`combine` turns them into ``quality``: a product of monotone factors, each in (0, 1], of the
signals present (a missing signal is a factor of 1). The scales are set by hand, one per signal, and
the result is measured against true errors on CAD renders (``docs/export.md#quality``).

Example:
    >>> round(combine({"keypoint_residual": 0.0, "silhouette_inside": 1.0, "mirror_deg": 0.0,
    ...                "camera_from": "sfm", "reconstruction_iou": 1.0, "surrogates_from": "triplet"}), 3)
    1.0
    >>> combine({"mirror_deg": 30.0}) < combine({"mirror_deg": 5.0})
    True
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["camera_signals", "reconstruction_iou", "combine", "SCALES", "CAMERA_FROM", "FALLBACK", "VISIBLE_HALF",
           "ROTATIONAL"]

#: Value of each continuous signal at which its factor ``1 / (1 + (v / scale)^2)`` is 1/2.
SCALES = {"keypoint_residual": 0.04, "refinement_deg": 5.0, "mirror_deg": 25.0}
#: ``visible_keypoints`` enter as ``n / (n + VISIBLE_HALF)``.
VISIBLE_HALF = 8.0
#: Factor of a rotationally symmetric class.
ROTATIONAL = 0.5
#: Factor per camera source (the unseen-image paths guess more).
CAMERA_FROM = {"sfm": 1.0, "ground_truth": 1.0, "mean_shape": 0.6, "silhouette": 0.3}
#: Factor per surrogate level; levels not named here (the intermediate fallbacks) take ``FALLBACK["other"]``.
FALLBACK = {"triplet": 1.0, "rotated_views": 1.0, "puffball": 0.3, "other": 0.8}


def _geodesic_deg(A, B):
    """Angle (degrees) of ``A B^T`` for ``(N, 3, 3)`` rotation tensors."""
    import torch

    tr = torch.einsum("nij,nij->n", A, B)
    return torch.rad2deg(torch.acos(((tr - 1) / 2).clamp(-1.0, 1.0)))


def camera_signals(coll, vp) -> list[dict]:
    """Per original object of the class, ``keypoint_residual``, ``silhouette_inside``, ``mirror_deg``,
    ``visible_keypoints``, ``refinement_deg`` and ``rotational`` (``None`` where the object has no camera,
    no visible keypoint, no mirrored camera, or no SfM camera; ``refinement_deg`` also for true cameras).

    Args:
        coll: the class (``N`` originals, canvas pixels); vp: its
            :class:`~carvi_torch.viewpoints.Viewpoints` (``2N`` rows; cameras in the SfM frame).
    """
    import torch  # here, not at the top: writer processes import this module for reconstruction_iou

    n = len(coll)
    cams = vp.cameras
    R, s, t = cams.R[:n].double().cpu(), cams.s[:n].double().cpu(), cams.t[:n].double().cpu()
    k = vp.groups.k
    labels = vp.groups.labels[:n].cpu().long() if k > 1 else torch.zeros(n, dtype=torch.long)
    shapes = torch.stack([(vp.groups.shape(g) if k > 1 else vp.shape).double().cpu() for g in range(k)])  # (k, K, 3)
    kp, vis = coll.keypoints.double().cpu(), coll.visible.cpu()
    masks = coll.masks.cpu()
    has = vp.has_camera.cpu().tolist()
    sfm_ok = vp.sfm_valid[:n].cpu().tolist()
    turn = _geodesic_deg(vp.sfm_cameras.R[:n].double().cpu(), R).tolist()
    rotational = getattr(getattr(coll, "meta", None), "symmetry", "none") == "rotational"
    mirror = [None] * n
    if vp.mirrored and vp.reflection is not None:
        from .cameras import FLIP_X  # here: writer processes import this module without torch

        pred = FLIP_X.double() @ R @ vp.reflection.double().cpu()
        ang = _geodesic_deg(pred, cams.R[n:2 * n].double().cpu()).tolist()
        mirror = [a if has[i] and has[i + n] and math.isfinite(a) else None for i, a in enumerate(ang)]
    res, inside = _projection_signals(s, R, t, shapes[labels] if n else None, kp, vis, masks)
    counts = vis.sum(1).tolist()
    out = []
    for i in range(n):
        if not has[i]:
            out.append({"keypoint_residual": None, "silhouette_inside": None, "mirror_deg": None,
                        "visible_keypoints": counts[i], "refinement_deg": None, "rotational": rotational})
            continue
        out.append({"keypoint_residual": res[i], "silhouette_inside": inside[i], "mirror_deg": mirror[i],
                    "visible_keypoints": counts[i],
                    "refinement_deg": turn[i] if sfm_ok[i] and math.isfinite(turn[i])
                    and getattr(vp, "source", "estimate") != "gt" else None,
                    "rotational": rotational})
    return out


def _projection_signals(s, R, t, S, kp, vis, masks) -> tuple[list, list]:
    """Per object, the RMS distance (over the canvas size) of its visible keypoints from the projections of its
    shape's points, and the fraction of those points that fall inside its mask (``None``: no visible keypoint
    with a point, no finite point), all objects at once.

    Args:
        s, R, t: ``(N,)``, ``(N, 3, 3)``, ``(N, 2)`` float64 cameras; S: ``(N, K, 3)`` each object's shape
            (non-finite rows: keypoints the shape lacks), ``None`` when ``N = 0``; kp, vis: ``(N, K, 2)``,
            ``(N, K)``; masks: ``(N, C, C)`` bool canvases.
    """
    import torch

    if S is None:
        return [], []
    n, C = len(S), masks.shape[-1]
    ok = torch.isfinite(S).all(-1)  # (N, K)
    uv = s[:, None, None] * torch.where(ok[..., None], S, 0.0) @ R[:, :2].transpose(1, 2) + t[:, None]
    v = vis & ok
    d2 = torch.where(v, (uv - torch.where(v[..., None], kp, 0.0)).pow(2).sum(-1), 0.0)
    m = v.sum(1)
    rms = (d2.sum(1) / m.clamp(min=1)).sqrt() / C
    px = uv.round().long()
    inb = ok & ((px >= 0) & (px < C)).all(-1)
    pc = px.clamp(0, C - 1)
    hit = masks[torch.arange(n)[:, None], pc[..., 1], pc[..., 0]] & inb
    points = ok.sum(1)
    frac = hit.sum(1).float() / points.clamp(min=1).float()  # float32, as a mean of booleans
    return ([float(r) if k else None for r, k in zip(rms.tolist(), m.tolist())],
            [float(f) if k else None for f, k in zip(frac.tolist(), points.tolist())])


def reconstruction_iou(occupancy: np.ndarray, voxel_to_canvas: np.ndarray, mask: np.ndarray) -> float:
    """IoU of the silhouette of ``occupancy (D, H, W)`` (a grid whose depth axis is the camera's ray, as
    the carving builds it) with the canvas ``mask (C, C)``; nearest voxel column per canvas pixel centre.

    Example:
        >>> occ = np.zeros((2, 4, 4), bool); occ[:, 1:3, 1:3] = True
        >>> m = np.zeros((4, 4), bool); m[1:3, 1:4] = True
        >>> reconstruction_iou(occ, np.eye(4)[[2, 1, 0, 3]], m)  # (d, h, w) -> (x=w, y=h, z=d)
        0.6666666666666666
    """
    A = np.asarray(voxel_to_canvas, dtype=np.float64)
    sil = np.asarray(occupancy, dtype=bool).any(axis=0)  # (H, W)
    # canvas (x, y) -> voxel (h, w) through the x, y rows of the affine restricted to the (h, w) columns
    M = A[:2, 1:3]
    if abs(A[0, 0]) > 1e-6 * np.abs(M).max() or abs(A[1, 0]) > 1e-6 * np.abs(M).max():
        raise ValueError("the grid's depth axis is not the camera's ray")
    inv = np.linalg.inv(M)
    on_axes = inv[0, 0] == 0 and inv[1, 1] == 0 and sil.size > 0
    proj = (_silhouette_on_canvas_axes if on_axes else _silhouette_on_canvas)(sil, inv, A[:2, 3], mask.shape[0])
    m = np.asarray(mask, dtype=bool)
    union = int((proj | m).sum())
    return float((proj & m).sum()) / union if union else 0.0


def _silhouette_on_canvas(sil: np.ndarray, inv: np.ndarray, offset: np.ndarray, C: int) -> np.ndarray:
    """``(C, C)`` bool: the silhouette ``sil (H, W)`` at every canvas pixel centre, its nearest column ``(h, w) =
    rint(inv @ ((x, y) - offset))`` (``inv``: the ``(2, 2)`` inverse of the (h, w) -> (x, y) map)."""
    ys, xs = np.mgrid[0:C, 0:C]
    xy = np.stack([xs.ravel() - offset[0], ys.ravel() - offset[1]], 1)
    hw = np.rint(xy @ inv.T).astype(np.int64)
    ok = (hw >= 0).all(1) & (hw[:, 0] < sil.shape[0]) & (hw[:, 1] < sil.shape[1])
    proj = np.zeros(C * C, dtype=bool)
    proj[ok] = sil[hw[ok, 0], hw[ok, 1]]
    return proj.reshape(C, C)


def _silhouette_on_canvas_axes(sil: np.ndarray, inv: np.ndarray, offset: np.ndarray, C: int) -> np.ndarray:
    """:func:`_silhouette_on_canvas` where ``h`` follows ``y`` alone and ``w`` ``x`` alone (``inv`` zero on its
    diagonal: the carving's grids, aligned with the canvas): one row and one column index per canvas line, the
    same values (each index its one product, the other term an exact zero)."""
    lines = np.arange(C, dtype=np.float64)
    h = np.rint((lines - offset[1]) * inv[0, 1]).astype(np.int64)
    w = np.rint((lines - offset[0]) * inv[1, 0]).astype(np.int64)
    oh, ow = (h >= 0) & (h < sil.shape[0]), (w >= 0) & (w < sil.shape[1])
    return sil[np.clip(h, 0, sil.shape[0] - 1)][:, np.clip(w, 0, sil.shape[1] - 1)] & oh[:, None] & ow[None, :]


def _half_at(value: float, scale: float) -> float:
    """``1 / (1 + (value / scale)^2)``: 1 at 0, 1/2 at ``scale``, decreasing."""
    return 1.0 / (1.0 + (value / scale) ** 2)


def combine(signals: dict) -> float:
    """``quality`` in [0, 1] from the signals present (see the module docstring); 1 when none is."""
    q = 1.0
    for key, scale in SCALES.items():
        v = signals.get(key)
        if v is not None and math.isfinite(v):
            q *= _half_at(v, scale)
    n = signals.get("visible_keypoints")
    if n is not None:
        q *= n / (n + VISIBLE_HALF)
    if signals.get("rotational"):
        q *= ROTATIONAL
    iou = signals.get("reconstruction_iou")
    if iou is not None:
        q *= max(0.05, iou)
    src = signals.get("camera_from")
    if src is not None:
        q *= CAMERA_FROM.get(src, 0.3)
    lv = signals.get("surrogates_from")
    if lv is not None:
        q *= FALLBACK.get(lv, FALLBACK["other"])
    return float(min(1.0, max(0.0, q)))
