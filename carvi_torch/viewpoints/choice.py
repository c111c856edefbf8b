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
(the mean shape itself does not fit the class's silhouettes: the CAD trains at 8 views, 53-72% of their
rows, against at most 27% in any other class); ``"objects"`` keeps each suspect object's SfM camera.

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
           "MIN_UP_LENGTH", "CameraChoice", "kept_rows", "hull_agreement", "keypoint_rms", "box_diagonal",
           "choose_cameras", "class_up", "image_tilt", "tilted"]

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
CLASS_SUSPECT = 0.5
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


def _hull_vertices(points: np.ndarray) -> np.ndarray:
    """``(M, V, 2)`` float64 (x, y) vertices of the convex hull of each row's ``points (M, P, 2)``, in scipy's
    order; a row with fewer repeats its last vertex (zero-length edges), a row without area (fewer than 3
    points, collinear or coincident ones) is all NaN."""
    from scipy.spatial import ConvexHull, QhullError

    hulls = []
    for p in points:
        try:
            hulls.append(p[ConvexHull(p).vertices] if len(p) >= 3 else None)
        except (QhullError, ValueError):
            hulls.append(None)  # collinear or coincident points: no area
    V = max([len(h) for h in hulls if h is not None], default=1)
    out = np.full((len(points), V, 2), np.nan)
    for i, h in enumerate(hulls):
        if h is not None:
            out[i, :len(h)], out[i, len(h):] = h, h[-1]
    return out


def _scan_intervals(vertices: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of each scan line that ``skimage.draw.polygon``'s crossing test puts inside the convex polygon
    of ``vertices (M, V, 2)`` (x, y), but for pixel centres on a vertex (:func:`_vertex_hits`).

    The test counts the edges crossed by the rays from a pixel centre to +x and to -x: the centre is in when
    either count is odd. A convex polygon's scan line straddles two edges or none for each ray, so each gives
    one half-open interval ``[lo, hi)`` of x. An edge meets the line at ``x_c``; the test holds for every x on
    one side of it but the integer nearest to ``x_c``, where it is evaluated as scikit-image evaluates it.

    Returns:
        ``lo, hi`` ``(M, 2, size)`` int64 (the +x ray's interval, then the -x ray's; ``lo == hi``: empty) and
        ``odd (M,)`` bool: rows with a scan line that straddles more than two edges (a polygon convex only up
        to rounding), which these intervals do not describe.
    """
    xi, yi = vertices[..., 0, None], vertices[..., 1, None] - np.arange(size)  # (M, V, size): edge (i - 1, i)
    xj, yj = np.roll(xi, 1, axis=1), np.roll(yi, 1, axis=1)
    rays = np.stack([(yi > 0) != (yj > 0), (yi < 0) != (yj < 0)], axis=1)  # (M, 2, V, size)
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.where(rays.any(1), np.round(xi + yi / (yi - yj) * (xj - xi)), 0.0)  # nearest integer to x_c
        at_k = ((xi - k) * yj - (xj - k) * yi) / (yj - yi)  # scikit-image's test at it
    first = np.stack([k + (at_k > 0), k + 1 - (at_k < 0)], axis=1).clip(0, size)  # +x: x < first; -x: x >= first
    count = rays.sum(2)  # (M, 2, size)
    lo = np.where(count == 2, np.where(rays, first, np.inf).min(2), 0).astype(np.int64)
    hi = np.where(count == 2, np.where(rays, first, -np.inf).max(2), 0).astype(np.int64)
    return lo, hi, (count > 2).any((1, 2))


def _vertex_hits(vertices: np.ndarray, size: int) -> list[tuple[int, int, int]]:
    """``(row, y, x)`` of the pixel centres within scikit-image's tolerance (1e-12) of a vertex, once each."""
    near = np.round(vertices)
    new = (vertices != np.roll(vertices, 1, axis=1)).any(-1)  # not a repeat of the previous vertex
    hit = (np.abs(vertices - near) < 1e-12).all(-1) & (near >= 0).all(-1) & (near < size).all(-1) & new
    m, v = np.nonzero(hit)
    return sorted({(int(a), int(near[a, b, 1]), int(near[a, b, 0])) for a, b in zip(m, v)})


def _polygon_mask(vertices: np.ndarray, size: int) -> np.ndarray:
    """``(size, size)`` bool: ``skimage.draw.polygon`` of one row's ``vertices (V, 2)`` (x, y; NaN: empty)."""
    from skimage.draw import polygon

    out = np.zeros((size, size), dtype=bool)
    if np.isfinite(vertices).all():
        out[polygon(vertices[:, 1], vertices[:, 0], shape=(size, size))] = True
    return out


def polygon_masks(vertices: np.ndarray, size: int) -> np.ndarray:
    """``(M, size, size)`` bool: the pixels ``[y, x]`` whose centres lie in or on the convex polygon of each
    row's ``vertices (M, V, 2)`` float64 (x, y; NaN rows: empty), pixel for pixel what ``skimage.draw.polygon``
    draws (its crossing test, boundary and vertex tolerance included), every row at once.

    Example:
        >>> v = np.array([[[1.0, 1.0], [3.0, 1.0], [3.0, 2.0], [1.0, 2.0]]])
        >>> polygon_masks(v, 4)[0].astype(int).tolist()
        [[0, 0, 0, 0], [0, 1, 1, 1], [0, 1, 1, 1], [0, 0, 0, 0]]
    """
    lo, hi, odd = _scan_intervals(vertices, size)
    x = np.arange(size)
    out = ((lo[..., None] <= x) & (x < hi[..., None])).any(1)
    for m, y, x in _vertex_hits(vertices, size):
        out[m, y, x] = True
    for m in np.nonzero(odd)[0]:
        out[m] = _polygon_mask(vertices[m], size)
    return out


def _hull_counts(vertices: np.ndarray, masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(M,)`` int64 pixels of :func:`polygon_masks` of ``vertices (M, V, 2)``, and those of them in ``masks
    (M, C, C)`` bool, from its scan-line intervals and the masks' running sums along x (no hull pixels drawn)."""
    M, C = masks.shape[0], masks.shape[-1]
    lo, hi, odd = _scan_intervals(vertices, C)
    both = np.stack([lo.max(1), np.maximum(hi.min(1), lo.max(1))], axis=1)[:, :, None]  # (M, 2, 1, C)
    runs = np.zeros((M, C, C + 1), dtype=np.int32)
    np.cumsum(masks, axis=2, dtype=np.int32, out=runs[..., 1:])
    ends = np.concatenate([hi, both[:, 0]], axis=1).transpose(0, 2, 1)  # (M, C, 3): the counts added ...
    starts = np.concatenate([lo, both[:, 1]], axis=1).transpose(0, 2, 1)  # ... and those taken away
    pixels = (ends - starts).sum((1, 2), dtype=np.int64)
    inside = (np.take_along_axis(runs, ends, axis=2) - np.take_along_axis(runs, starts, axis=2)).sum((1, 2),
                                                                                                   dtype=np.int64)
    for m, y, x in _vertex_hits(vertices, C):
        if not ((lo[m, :, y] <= x) & (x < hi[m, :, y])).any():
            pixels[m] += 1
            inside[m] += masks[m, y, x]
    for m in np.nonzero(odd)[0]:
        h = _polygon_mask(vertices[m], C)
        pixels[m], inside[m] = np.count_nonzero(h), np.count_nonzero(h & masks[m])
    return pixels, inside


def hull_agreement(shape: torch.Tensor, cams: ScaledOrthographic, masks: torch.Tensor) -> torch.Tensor:
    """Intersection over union of each mask and the convex hull of the projected ``shape``.

    The hull of each row comes from scipy; its pixels are counted without drawing it (:func:`_hull_counts`,
    every row at once): the counts of :func:`polygon_masks`, which are scikit-image's.

    Args:
        shape: ``(K, 3)`` (NaN rows are left out); cams: ``M`` cameras; masks: ``(M, C, C)`` bool.

    Returns:
        ``(M,)`` float64 in ``[0, 1]`` (0 where the hull or the union is empty), on the host.
    """
    keep = torch.isfinite(shape).all(-1)
    P = cams.project(shape[keep].to(cams.R.dtype)).detach().double().cpu().numpy()  # (M, K', 2)
    m = masks.detach().cpu().numpy()
    pixels, inter = _hull_counts(_hull_vertices(P), m)
    union = pixels + np.count_nonzero(m, axis=(1, 2)) - inter
    return torch.from_numpy(np.where(union > 0, inter / np.maximum(union, 1), 0.0))


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
