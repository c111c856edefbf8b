"""Keep the better of an object's SfM and refined cameras, judged without ground truth.

The refinement never raises its own energy (keypoints plus a one-sided silhouette term that only
pulls the projected mean shape into the mask), so that energy cannot tell when a refined camera
is worse than its SfM camera: with a mean shape that is not the object's own, the silhouette term
can turn the camera until the shape fits inside the mask, at the cost of the keypoints. Two
measures the refinement does not optimise judge the pair instead:

* **keypoint growth**: how much the refinement raised the RMS reprojection error of the visible
  keypoints, over the diagonal of the mask's bounding box;
* **hull agreement**: the intersection over union of the mask and the convex hull of the projected
  mean shape (a two-sided silhouette agreement: a shape turned to hide inside the mask covers
  less of it).

A refined camera is *suspect* when the keypoint growth exceeds :data:`KEYPOINT_GROWTH` and the hull
agreement rises by less than :data:`HULL_GAIN`: it pays for its silhouette fit with the keypoints
and gains little two-sided agreement. ``refine_keep="class"`` (the default) keeps the SfM cameras of
the whole class when more than :data:`CLASS_SUSPECT` of its objects' refined cameras are suspect
(the mean shape itself does not fit the class's silhouettes: the CAD trains, 41-72% of their rows at 8
views and 45-46% at 30, against at most 27% in any other class of those renders and 2% of the VOC
aeroplanes; docs/viewpoints.md); ``"objects"`` keeps each suspect object's SfM camera.

A third test judges each object on its own, with either rule: **tilt**. Photographs are taken with a
level camera, so the image x axes of a class's cameras are horizontal in the object frame, and the
direction most perpendicular to all of them (over the SfM cameras) is the class's up
(:func:`class_up`). A refined camera that shows that up tilted in the image (:func:`image_tilt`:
the angle between the projected up and the image's up, 180 degrees upside down) by more than
``max_tilt_deg`` and by :data:`TILT_MARGIN_DEG` more than its SfM camera does is *tilted*: the
silhouette term turned it into a pose no photographer takes (a boat whose mean shape fits its mask
upside down); it keeps its SfM camera. A class whose up is not clear (:data:`UP_MARGIN`), and a camera
looking nearly along the up (:data:`MIN_UP_LENGTH`), are not judged this way.

Example:
    >>> import torch
    >>> from carvi_torch.cameras import ScaledOrthographic
    >>> S = torch.tensor([[-10., -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]])
    >>> cam = ScaledOrthographic(torch.eye(3)[None], torch.ones(1), torch.tensor([[16., 16.]]))
    >>> mask = torch.zeros(1, 32, 32, dtype=torch.bool); mask[0, 6:27, 6:27] = True
    >>> round(float(hull_agreement(S, cam, mask)[0]), 2)
    1.0
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from ..cameras import ScaledOrthographic

__all__ = ["CameraKeep", "KEYPOINT_GROWTH", "HULL_GAIN", "CLASS_SUSPECT", "TILT_MARGIN_DEG", "UP_MARGIN",
           "MIN_UP_LENGTH", "CameraChoice", "kept_rows", "hull_agreement", "hull_agreement_reference", "keypoint_rms",
           "box_diagonal", "choose_cameras", "class_up", "image_tilt", "tilted"]

#: Which camera an object with an SfM camera keeps after refinement: ``refined`` (always the refined
#: one, the paper's), ``class`` (the SfM cameras of a class most of whose refined cameras are suspect)
#: or ``objects`` (the SfM camera of every object whose refined one is suspect); with ``class`` and
#: ``objects`` a tilted refined camera keeps its SfM camera too; module docstring.
CameraKeep = Literal["refined", "class", "objects"]

#: A refined camera whose keypoint RMS error exceeds its SfM camera's by more than this fraction of
#: the mask's box diagonal is suspect.
KEYPOINT_GROWTH = 0.01
#: ... and is replaced by the SfM camera unless its hull agreement is higher by at least this much.
HULL_GAIN = 0.05
#: ``refine_keep="class"``: the class keeps its SfM cameras when more than this fraction of its rows
#: with an SfM camera have a suspect refined camera.
CLASS_SUSPECT = 1 / 3
#: A refined camera is tilted when its image tilt of the class's up exceeds ``max_tilt_deg`` and its SfM
#: camera's by more than this many degrees.
TILT_MARGIN_DEG = 20.0
#: The class's up is used only when the second-smallest eigenvalue of the image x axes' scatter exceeds the
#: smallest this many times (photographs from level cameras: 8-230 on the CAD renders at 8 views per model).
UP_MARGIN = 4.0
#: The tilt is judged only where both cameras show the class's up at least this long (elevation within 60
#: degrees): a VOC aeroplane seen from below (SfM 0.28, elevation -53 degrees) has no meaningful tilt.
MIN_UP_LENGTH = 0.5


@dataclass
class CameraChoice:
    """Per row (``(M,)`` each): ``suspect`` bool (the refined camera is suspect), the two cameras' keypoint
    RMS errors (pixels), hull agreements (NaN where the keypoint error did not grow enough for them to
    matter) and the box diagonal (pixels)."""

    suspect: torch.Tensor
    rms_sfm: torch.Tensor
    rms_refined: torch.Tensor
    hull_sfm: torch.Tensor
    hull_refined: torch.Tensor
    diagonal: torch.Tensor


def _hull_mask(points: np.ndarray, size: int) -> np.ndarray:
    """``(size, size)`` bool: the pixels whose centres lie in the convex hull of ``points (P, 2)`` (x, y), its
    boundary included (scikit-image's polygon fill); empty for fewer than 3 points or collinear ones."""
    from scipy.spatial import ConvexHull, QhullError
    from skimage.draw import polygon

    out = np.zeros((size, size), dtype=bool)
    if len(points) < 3:
        return out
    try:
        hull = points[ConvexHull(points).vertices]
    except (QhullError, ValueError):
        return out  # collinear or coincident points: no area
    rr, cc = polygon(hull[:, 1], hull[:, 0], shape=(size, size))
    out[rr, cc] = True
    return out


def hull_agreement_reference(shape: torch.Tensor, cams: ScaledOrthographic, masks: torch.Tensor) -> torch.Tensor:
    """:func:`hull_agreement` one row at a time: scipy's convex hull filled by scikit-image's polygon (the
    reference of the batched op; rows of collinear points have no hull and agree 0)."""
    keep = torch.isfinite(shape).all(-1)
    P = cams.project(shape[keep].to(cams.R.dtype)).detach().double().cpu().numpy()  # (M, K', 2)
    m = masks.detach().cpu().numpy()
    out = np.zeros(len(m))
    for i in range(len(m)):
        h = _hull_mask(P[i], m.shape[-1])
        union = np.count_nonzero(h | m[i])
        out[i] = np.count_nonzero(h & m[i]) / union if union else 0.0
    return torch.from_numpy(out)


#: Elements of the largest tensors :func:`hull_agreement` builds at once (rows x pixels, rows x point pairs x points).
_HULL_CHUNK = 1 << 22


def _hull_edges(P: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The point pairs of ``P (M, K, 2)`` that are edges of their row's convex hull: every other point on one
    side of their line (to 1e-12 of the extent squared: a pair along a nearly straight stretch of the boundary
    counts too, and does no harm). Returns ``a, b (M, H)`` point indices and ``ok (M, H)`` bool (padding
    false), ``H`` the most edges of any row."""
    k = P.shape[1]
    i, j = torch.triu_indices(k, k, offset=1, device=P.device)
    d = P[:, j] - P[:, i]  # (M, E, 2)
    rel = P[:, None] - P[:, i, None]  # (M, E, K, 2)
    cross = d[..., None, 0] * rel[..., 1] - d[..., None, 1] * rel[..., 0]
    extent = (P - P[:, :1]).abs().amax((1, 2))
    eps = (1e-12 * extent * extent)[:, None, None]
    edge = (cross >= -eps).all(-1) | (cross <= eps).all(-1)  # (M, E)
    h = max(int(edge.sum(-1).max()), 1)
    order = torch.sort(edge.to(torch.int32), dim=-1, descending=True, stable=True).indices[:, :h]
    return i[order], j[order], edge.gather(-1, order)


def _hull_spans(P: torch.Tensor, size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """First and last pixel column inside the convex hull of ``P (M, K, 2)`` (x, y; float64) on each pixel row
    ``y = 0 .. size - 1``: ``(M, size)`` long each, ``first > last`` where the row misses the hull.

    A horizontal line meets the hull in the interval spanned by its crossings of the hull's edges
    (:func:`_hull_edges`); pixel centres on its boundary are inside, as in scikit-image's polygon fill."""
    a, b, ok = _hull_edges(P)
    rows = torch.arange(len(P), device=P.device)[:, None]
    xa, ya, xb, yb = (v[:, None] for v in (P[rows, a, 0], P[rows, a, 1], P[rows, b, 0], P[rows, b, 1]))  # (M, 1, H)
    y = torch.arange(size, dtype=P.dtype, device=P.device)[None, :, None]
    flat = ya == yb
    x = xa + (y - ya) * (xb - xa) / torch.where(flat, 1.0, yb - ya)
    x = torch.where(y == yb, xb, torch.where(y == ya, xa, x))  # an end exactly: a corner on a pixel centre is in
    meets = (torch.minimum(ya, yb) <= y) & (y <= torch.maximum(ya, yb)) & ok[:, None]
    inf = torch.tensor(float("inf"), dtype=P.dtype, device=P.device)
    left = torch.where(meets, torch.where(flat, torch.minimum(xa, xb), x), inf).amin(-1)
    right = torch.where(meets, torch.where(flat, torch.maximum(xa, xb), x), -inf).amax(-1)
    first = left.ceil().clamp(0, size).long()
    last = right.floor().clamp(-1, size - 1).long()
    return first, last


def _flat(P: torch.Tensor) -> torch.Tensor:
    """``(M,)`` bool: rows of ``P (M, K, 2)`` whose points are collinear (or coincident) to 1e-9 of their extent:
    scipy's hull refuses them (the reference then agrees 0); they are left to it."""
    d = P - P[:, :1]
    cross = d[:, :, None, 0] * d[:, None, :, 1] - d[:, :, None, 1] * d[:, None, :, 0]
    extent = d.abs().amax((1, 2))
    return cross.abs().amax((1, 2)) <= 1e-9 * extent * extent


def hull_agreement(shape: torch.Tensor, cams: ScaledOrthographic, masks: torch.Tensor) -> torch.Tensor:
    """Intersection over union of each mask and the convex hull of the projected ``shape``.

    Batched over the rows on the masks' device: each pixel row of the hull is one span of columns
    (:func:`_hull_spans`). The same counts as :func:`hull_agreement_reference` (scipy's hull, scikit-image's
    fill) but for a pixel centre within rounding of the hull's boundary (about 1e-16 of the coordinates:
    1e-13 pixels at a few hundred; a corner exactly on a pixel centre is in, as there).

    Args:
        shape: ``(K, 3)`` (NaN rows are left out); cams: ``M`` cameras; masks: ``(M, C, C)`` bool.

    Returns:
        ``(M,)`` float64 on the CPU, in ``[0, 1]`` (0 where the hull or the union is empty).
    """
    keep = torch.isfinite(shape).all(-1)
    out = torch.zeros(len(masks), dtype=torch.float64)
    if int(keep.sum()) < 3 or len(masks) == 0 or masks.shape[-1] == 0:
        return out
    P = cams.project(shape[keep].to(cams.R.dtype)).detach().to(masks.device, torch.float64)  # (M, K', 2)
    k, size = P.shape[1], masks.shape[-1]
    step = max(1, _HULL_CHUNK // max(size * size, size * k, k ** 3))
    for a in range(0, len(masks), step):
        out[a:a + step] = _span_iou(P[a:a + step], masks[a:a + step]).cpu()
    flat = _flat(P).cpu()
    if bool(flat.any()):
        rows = flat.nonzero().squeeze(1)
        out[rows] = hull_agreement_reference(shape, cams[rows], masks[rows.to(masks.device)])
    return out


def _span_iou(P: torch.Tensor, masks: torch.Tensor) -> torch.Tensor:
    """IoU of ``masks (M, C, C)`` and the hulls of ``P (M, K, 2)`` from the hull's spans per pixel row."""
    first, last = _hull_spans(P, masks.shape[-1])
    x = torch.arange(masks.shape[-1], device=masks.device)
    inside = (x >= first[..., None]) & (x <= last[..., None])  # (M, C, C)
    inter = (inside & masks).sum((1, 2))
    union = (last - first + 1).clamp(min=0).sum(-1) + masks.sum((1, 2)) - inter
    return torch.where(union > 0, inter.double() / union.clamp(min=1).double(), 0.0)


def keypoint_rms(shape: torch.Tensor, cams: ScaledOrthographic, keypoints: torch.Tensor,
                 visible: torch.Tensor) -> torch.Tensor:
    """``(M,)`` RMS distance (pixels) between the projected ``shape (K, 3)`` and the visible ``keypoints
    (M, K, 2)`` with a finite shape row; 0 for a row with none."""
    ok = (visible & torch.isfinite(shape).all(-1) & torch.isfinite(keypoints).all(-1)).to(cams.R.dtype)
    P = cams.project(torch.nan_to_num(shape).to(cams.R.dtype))
    d2 = ((P - torch.nan_to_num(keypoints).to(P.dtype)) ** 2).sum(-1) * ok
    return (d2.sum(-1) / ok.sum(-1).clamp(min=1)).sqrt()


def box_diagonal(masks: torch.Tensor) -> torch.Tensor:
    """``(M,)`` diagonal (pixels) of each mask's bounding box (1 for an empty mask)."""
    ys = torch.arange(masks.shape[1], device=masks.device, dtype=torch.float64)
    xs = torch.arange(masks.shape[2], device=masks.device, dtype=torch.float64)
    rows, cols = masks.any(2), masks.any(1)
    big = torch.tensor(float("inf"), dtype=torch.float64, device=masks.device)
    h = torch.where(rows, ys, -big).amax(-1) - torch.where(rows, ys, big).amin(-1) + 1
    w = torch.where(cols, xs, -big).amax(-1) - torch.where(cols, xs, big).amin(-1) + 1
    d = torch.hypot(h, w)
    return torch.where(torch.isfinite(d), d, torch.ones_like(d))


def choose_cameras(shape: torch.Tensor, sfm: ScaledOrthographic, refined: ScaledOrthographic,
                   keypoints: torch.Tensor, visible: torch.Tensor, masks: torch.Tensor) -> CameraChoice:
    """Score every row's SfM and refined cameras under ``shape (K, 3)`` and say which refined ones are suspect.

    Args:
        sfm, refined: ``M`` cameras each (canvas pixels); keypoints ``(M, K, 2)``; visible ``(M, K)``;
        masks ``(M, C, C)`` bool.
    """
    rms_s, rms_r = (keypoint_rms(shape, c, keypoints, visible).double().cpu() for c in (sfm, refined))
    diag = box_diagonal(masks).cpu()
    grew = rms_r - rms_s > KEYPOINT_GROWTH * diag
    hull_s = torch.full_like(rms_s, float("nan"))
    hull_r = hull_s.clone()
    idx = grew.nonzero().squeeze(1)  # the hulls only matter where the keypoint error grew (they cost ~1 ms a row)
    if idx.numel():
        on = idx.to(masks.device)
        hull_s[idx] = hull_agreement(shape, sfm[on], masks[on])
        hull_r[idx] = hull_agreement(shape, refined[on], masks[on])
    suspect = grew & (hull_r - hull_s < HULL_GAIN)
    return CameraChoice(suspect, rms_s, rms_r, hull_s, hull_r, diag)


def class_up(R: torch.Tensor) -> torch.Tensor | None:
    """The class's up direction ``(3,)`` in the object frame from cameras ``R (M, 3, 3)`` of level photographs:
    the unit vector most perpendicular to their image x axes (``R[:, 0]``), signed so that it points up in most
    images (image y points down); ``None`` when fewer than 3 cameras or the direction is not clear
    (:data:`UP_MARGIN`).

    Example:
        >>> import math
        >>> from carvi_torch.cameras import rotation_from_azimuth_elevation_roll
        >>> az = torch.linspace(0, 6, 12, dtype=torch.float64)
        >>> R = rotation_from_azimuth_elevation_roll(az, torch.full_like(az, 0.3), torch.zeros_like(az))
        >>> [round(float(v), 3) + 0.0 for v in class_up(R)]
        [0.0, 0.0, 1.0]
    """
    R = R.detach().double().cpu()
    R = R[torch.isfinite(R).flatten(1).all(1)]
    if len(R) < 3:
        return None
    x = R[:, 0]
    evals, evecs = torch.linalg.eigh(x.T @ x)
    if not float(evals[1]) > UP_MARGIN * max(float(evals[0]), 1e-12):
        return None
    up = evecs[:, 0]
    return -up if float((R[:, 1] @ up).median()) > 0 else up


def image_tilt(R: torch.Tensor, up: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The angle ``(M,)`` in degrees, ``[0, 180]``, between the image's up and the projection of ``up (3,)`` by
    cameras ``R (M, 3, 3)`` (0 upright, 180 upside down), and the projection's length ``(M,)`` (``cos`` of the
    elevation; the angle means little where it is short).

    Example:
        >>> R = torch.stack([torch.eye(3), torch.diag(torch.tensor([-1.0, -1.0, 1.0]))]).double()
        >>> tilt, length = image_tilt(R, torch.tensor([0.0, -1.0, 0.0], dtype=torch.float64))
        >>> tilt.tolist(), length.tolist()
        ([0.0, 180.0], [1.0, 1.0])
    """
    R = R.detach().double().cpu()
    u = up.double().cpu()
    x, y = R[:, 0] @ u, -(R[:, 1] @ u)
    return torch.rad2deg(torch.atan2(x, y)).abs(), torch.hypot(x, y)


def tilted(sfm: torch.Tensor, refined: torch.Tensor, has_sfm: torch.Tensor, max_tilt_deg: float) -> torch.Tensor:
    """``(M,)`` bool: the rows with an SfM camera (``has_sfm (M,)``) whose refined camera ``refined (M, 3, 3)``
    shows the class's up (:func:`class_up` of the SfM cameras ``sfm (M, 3, 3)``) tilted by more than
    ``max_tilt_deg`` and by more than :data:`TILT_MARGIN_DEG` beyond the SfM camera, where both cameras
    see the up at least :data:`MIN_UP_LENGTH` long (CPU)."""
    has = has_sfm.detach().cpu()
    none = torch.zeros_like(has)
    up = class_up(sfm.detach().cpu()[has]) if max_tilt_deg < 180 else None
    if up is None:
        return none
    (t_s, l_s), (t_r, l_r) = image_tilt(sfm, up), image_tilt(refined, up)
    seen = (l_s >= MIN_UP_LENGTH) & (l_r >= MIN_UP_LENGTH)
    return has & seen & (t_r > max_tilt_deg) & (t_r > t_s + TILT_MARGIN_DEG)


def kept_rows(suspect: torch.Tensor, has_sfm: torch.Tensor, how: CameraKeep,
              tilt: torch.Tensor | None = None) -> torch.Tensor:
    """``(M,)`` bool: the rows that keep their SfM camera, from the suspect rows ``(M,)`` among those with an
    SfM camera ``has_sfm (M,)`` and (``how`` ``class`` or ``objects``) the tilted rows ``tilt (M,)``.

    Example:
        >>> s, h = torch.tensor([True, True, False, False]), torch.tensor([True, True, True, False])
        >>> kept_rows(s, h, "objects").tolist(), kept_rows(s, h, "class").tolist()
        ([True, True, False, False], [True, True, True, False])
        >>> kept_rows(s & False, h, "class", tilt=torch.tensor([False, False, True, True])).tolist()
        [False, False, True, False]
    """
    suspect = suspect & has_sfm
    if how == "refined":
        return torch.zeros_like(suspect)
    tilt = torch.zeros_like(suspect) if tilt is None else tilt.to(suspect.device) & has_sfm
    if how == "objects":
        return suspect | tilt
    n = int(has_sfm.sum())
    whole = has_sfm.clone() if n and int(suspect.sum()) > CLASS_SUSPECT * n else torch.zeros_like(suspect)
    return whole | tilt
