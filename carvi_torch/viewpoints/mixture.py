"""SfM stage, optional: a mixture of rigid shapes per class (``sfm_groups > 1``).

One rigid mean shape cannot fit a class whose members differ in proportions (sofas: a long low
couch, an armchair and ordinary sofas); the cameras then absorb the shape differences and the
viewpoints suffer. This stage splits a class into at most ``max_groups`` groups, each with its own
rigid SfM (:func:`carvi_torch.viewpoints.sfm.rigid_sfm`), by hard EM over the groups, without any ground
truth, and puts every group in one class frame.

First a gate (``min_misfit``, the pipeline's ``sfm_group_misfit``): when the one-shape SfM already fits
the keypoints (:func:`misfit`: residual over the mask's box diagonal, median over the objects, below the
gate) no split is tried and the class keeps one shape at no further cost.

The fit, for ``k = 2, 3, ...`` while a split is accepted:

1. Initial labellings: ``lifted`` = k-means (``scipy.cluster.vq.kmeans2``, k-means++, best of
   10 restarts) of every object's one-shape reprojection residuals lifted into the object frame
   (``R[:2]^T r / s``; the object and its mirrored copy side by side, unit norm);
   ``residual`` = quantiles of every object's one-shape keypoint residual; from ``k = 3``,
   ``split`` = the kept ``k - 1`` groups with the one of the largest residual that has room for two
   groups split in two by k-means of its objects' lifted residuals (:func:`split_labels`). The EM
   ends in another local optimum from each; ``split`` carries the groups already found forward
   (on the 15-render CAD sofas with the compiled kernels the kept four-group residual 6,237 px^2 ->
   3,054, 8.2 -> 4.9 degrees; the three float paths measured now agree within 1.2 degrees).
2. Alternation (at most ``rounds``): rigid SfM of every group (its objects with their mirrored
   copies); a keypoint-only camera of every object under every group's shape
   (:func:`carvi_torch.viewpoints.camera_fit.estimate_camera`); every object moves to the group with the lowest
   squared pixel residual (object + mirrored copy). A group below ``min_size`` objects takes the
   objects that cost least to move.
   A keypoint no member of a group shows is left NaN by the group's SfM; it is filled from the
   whole class's shape posed onto the group's (:func:`fill_missing_rows`), so that every group is
   scored on the same keypoints (a shape lacking keypoints would otherwise look cheaper).
   Warm starts (``warm_start=True``, the default): the keypoint-only cameras are searched over the
   sphere once, under the one-shape SfM; every round then refines, per object and group, that
   camera carried onto the group's shape (:func:`transfer_cameras`; later rounds: the object's
   last cameras under the group and under its own group), the group's SfM camera (first round)
   and the closed-form resection of the object onto the shape
   (:func:`carvi_torch.viewpoints.sfm.resect_cameras`). Every group's SfM after the first round starts from
   its last shape (``init_shape``). On the 2,000-instance benchmark class this cut the fit from
   459 s to 25 s; on the CAD renders it keeps as many groups as the search did in 11 of 12
   classes (boat: three instead of two; docs/viewpoints.md).
   The initialisations of a ``k`` are independent: on a class of at least
   :data:`THREADS_MIN_OBJECTS` objects they run side by side on ``threads`` Python threads (same
   result as one after the other; with two starts per ``k``, 1.43x faster on 2 cores for a
   2,000-instance class that splits in three, 1.47x for one that does not).
3. One class frame: every group's shape is rotated onto group 0's (a proper rotation on their
   shared keypoints, centred and scaled, :func:`rotation_onto`), and its cameras with it.
4. Acceptance: among the candidates whose groups' frames agree within ``agreement_deg``
   (:func:`frame_agreement`: the median, over the objects with an SfM camera, of the angle
   between an object's rotations under two groups' rotated shapes), the one with the lower
   residual is taken when it cuts the residual of ``k - 1`` groups by more than ``gain``.
   Otherwise the fit stops at ``k - 1``. A candidate with a group that has no usable SfM shape
   (fewer than 3 keypoints, no camera, or only keypoints on one plane: :data:`PLANAR_THICKNESS`),
   or whose shapes share too few keypoints for one frame,
   is recorded with its problem and never kept: the class falls back to fewer groups, never fails.
   With ``hull_gain`` (the pipeline's ``sfm_group_hull_gain``) a ``k`` is eligible only when every
   usable start raises the median agreement of the masks with the projected group shapes' hulls
   (:func:`hull_agreements`) by at least that much over one shape: a silhouette test the keypoint-only
   EM does not optimise. On the 8-view CAD renders it separates sofa, bus and aeroplane (0.014-0.033)
   from boat and motorbike (at most 0.000 and -0.003), which the residual cut does not.

Limitations: planar classes (every keypoint on one plane) have a two-fold tilt ambiguity per
group that the agreement check reads as disagreeing frames, so they keep one shape; a class's
``rigid_keypoints`` subset is not used here (every reconstructed keypoint counts).

Every object and its mirrored copy belong to one group. Objects without an SfM camera (fewer
than 2 visible keypoints) cost the same in every group; they end up in group 0 unless a group
needs them to reach ``min_size``.

The acceptance rule and its thresholds (``gain = 0.3``, ``agreement_deg = 60``, and the pipeline's
``sfm_group_misfit = 0.025``, ``sfm_group_hull_gain = 0.01``) were set on the renders of the PASCAL3D+
CAD models (docs/viewpoints.md); they are not tuned on any other data. The pipeline's defaults ask for more,
smaller groups (``sfm_groups=4``, ``sfm_group_min=10``, ``sfm_group_gain=0.25``), which with the joint
bundle adjustment put every small CAD class within its viewpoint bound (docs/viewpoints.md, *The joint
bundle adjustment*).

Example:
    >>> import torch
    >>> from carvi_torch.viewpoints.mixture import top_up
    >>> top_up(torch.tensor([0, 0, 0, 1]), torch.tensor([[0., 3.], [0., 1.], [0., 2.], [5., 0.]]), 2, 2).tolist()
    [0, 1, 0, 1]
"""
from __future__ import annotations

import dataclasses
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from scipy.cluster.vq import kmeans2
from scipy.spatial.transform import Rotation

from ..cameras import ScaledOrthographic, geodesic_errors
from ..runtime import cpu_single_thread
from . import camera_fit
from .choice import box_diagonal, hull_agreement
from .sfm import SfMResult, resect_cameras

__all__ = ["MixtureResult", "fit_mixture_of_shapes", "shape_thickness", "PLANAR_THICKNESS", "group_rows",
           "keypoint_fit", "transfer_cameras", "lifted_residuals", "kmeans_labels", "split_labels", "top_up",
           "hard_em", "rotation_onto", "group_rotations", "frame_agreement", "EM_SETTLED",
           "THREADS_MIN_OBJECTS", "misfit", "hull_agreements", "COLD_GROUP_SFM"]

#: The EM stops when at most this fraction of the objects (rounded down: none below 400 objects)
#: changed group in a round. On large classes a few objects near two shapes' boundary keep
#: trading places for the last rounds (the 2,000-instance class of ``tools/bench_viewpoints.py
#: --shapes 3 --groups 3``: its four candidates' last rounds moved 3, 5, 2 and 3 objects, the
#: rounds before those 8, 37, 15 and 106; each candidate's ``"moved"``).
EM_SETTLED = 0.0025

#: The fit runs a ``k``'s initialisations on two threads only for classes of at least this many
#: objects. The solvers are chains of small tensor ops; torch releases the interpreter lock inside
#: each, but on a small class the ops are so short that the two threads mostly wait for the lock
#: and for each other's wake-ups. Measured (2 cores, 1 intra-op thread each, three proportions,
#: ``sfm_groups=3``; ``tools/bench_viewpoints.py --threads-min-objects 0``, docs/viewpoints.md):
#: 150 objects 1.21x slower on two threads, 400 1.07x slower, 700 1.10x faster, 2,000 1.43-1.47x
#: faster; the CAD sofa renders (180 objects, a scratch run) 1.14-1.25x slower.
THREADS_MIN_OBJECTS = 500

#: What the pipeline's SfM of a group runs with when it starts cold (the first EM round, or a warm start
#: that failed): :class:`carvi_torch.viewpoints.sfm.SfMOptions` fields replacing the run's. ``planar=False``:
#: the rigid model alone, without the planar model's trial fit, which only matters where the plane wins,
#: and a group whose keypoints lie on one plane is refused by :data:`PLANAR_THICKNESS` either way (on the
#: CAD renders at 8 and 30 views every group's cameras are the same bit for bit, for 4% less CPU).
COLD_GROUP_SFM = {"planar": False}

#: ``(ClassCollection, init_shape=None) -> SfMResult``: the rigid SfM of a collection with the run's
#: settings; ``init_shape`` (``(K, 3)`` or None) is passed on to :func:`carvi_torch.viewpoints.sfm.rigid_sfm`
#: (a warm start). Called with the collection alone when there is no start.
SfMFn = Callable[..., SfMResult]


def group_rows(idx: torch.Tensor, n: int) -> torch.Tensor:
    """Rows of the ``2n`` originals + mirrors collection for objects ``idx (m,)``: ``(2m,)``, originals first."""
    return torch.cat([idx, idx + n])


def keypoint_fit(shape: torch.Tensor, both, dist: torch.Tensor, n: int, *, n_starts: int = 16,
                 starts: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None, native: bool = False
                 ) -> tuple[torch.Tensor, ScaledOrthographic]:
    """Keypoint-only cameras of every row of ``both`` under ``shape``, and what they cost.

    Args:
        shape: ``(K, 3)`` a mean shape (NaN rows: keypoints it lacks).
        both: the ``2n`` collection (originals, then mirrored copies).
        dist: ``(2n, H, W)`` distance maps of its masks (only the starts' mask centres use them: no
            silhouette term).
        n: number of originals.
        n_starts: rotated starts of the search over the sphere
            (:func:`carvi_torch.viewpoints.camera_fit.estimate_camera`), when ``starts`` is None.
        starts: ``R (2n, B, 3, 3)``, ``s (2n, B)``, ``t (2n, B, 2)``: refine these starts instead of
            searching the sphere (a warm start), plus the closed-form resection of every row
            (:func:`carvi_torch.viewpoints.sfm.resect_cameras`); every row keeps its best. The resection
            finds the basins that the warm starts miss (on the sofa renders, warm starts alone
            ended worse than the search for up to 11% of the objects under a group's shape,
            with the resection for none).
        native: the warm starts' refinement in the compiled fit on the CPU (equal to rounding;
            :func:`carvi_torch.viewpoints.camera_fit.refine_starts_keypoints_only`).

    Returns:
        ``cost (n,)`` squared pixel residual of every object plus its mirrored copy, and the ``2n``
        cameras.
    """
    if starts is None:
        cams, _ = camera_fit.estimate_camera(shape, both.keypoints, both.visible, dist, silhouette_weight=0.0,
                                         n_starts=n_starts)
    else:
        R, s, t = starts
        rc, ok = resect_cameras(shape, both.keypoints, both.visible)  # rows without one repeat their first start
        R = torch.cat([R, torch.where(ok[:, None, None], rc.R.to(R), R[:, 0])[:, None]], 1)
        s = torch.cat([s, torch.where(ok, rc.s.to(s), s[:, 0])[:, None]], 1)
        t = torch.cat([t, torch.where(ok[:, None], rc.t.to(t), t[:, 0])[:, None]], 1)
        cams, _ = camera_fit.refine_starts_keypoints_only(shape, R, s, t, both.keypoints, both.visible, native=native)
    P = cams.project(torch.nan_to_num(shape).to(cams.R))
    vis = both.visible & torch.isfinite(shape).all(-1)[None] & torch.isfinite(both.keypoints).all(-1)
    r = ((P - torch.nan_to_num(both.keypoints)).pow(2).sum(-1) * vis).sum(-1)
    return r[:n] + r[n:], cams


def transfer_cameras(cams: ScaledOrthographic, S_from: torch.Tensor, S_to: torch.Tensor) -> ScaledOrthographic:
    """Cameras that show ``S_to`` as ``cams`` show ``S_from``, once the two shapes are aligned.

    With ``(S_to - m_to) Q ~ c (S_from - m_from)`` (:func:`rotation_onto`, least-squares ``c``,
    centroids ``m`` over the rows finite in both), a point ``x`` of ``S_to`` stands for
    ``Q^T (x - m_to) / c + m_from`` of ``S_from``, so ``R' = R Q^T``, ``s' = s / c`` and
    ``t' = t + s R[:2] m_from - s' R'[:2] m_to``. Equal shapes give the cameras back; a rotated
    copy ``S_to = S_from Q0`` gives ``R Q0``. Used to carry cameras from one shape to the next
    (a warm start); the result is only as good as the two shapes are alike.

    Args:
        cams: N cameras; S_from, S_to: ``(K, 3)``, NaN rows ignored.

    Raises:
        ValueError: the shapes share fewer than 3 keypoints, or only collinear ones.

    Example:
        >>> S = torch.tensor([[0., 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]])
        >>> c = ScaledOrthographic(torch.eye(3)[None], torch.ones(1), torch.zeros(1, 2))
        >>> d = transfer_cameras(c, S, 2 * S + 1)
        >>> torch.allclose(d.project(2 * S + 1), c.project(S), atol=1e-5)
        True
    """
    Q = rotation_onto(S_to, S_from).to(cams.R)
    ok = torch.isfinite(S_to).all(-1) & torch.isfinite(S_from).all(-1)
    A, B = S_to[ok].to(cams.R), S_from[ok].to(cams.R)
    m_to, m_from = A.mean(0), B.mean(0)
    A, B = A - m_to, B - m_from
    c = ((A @ Q) * B).sum() / (B * B).sum()
    R = cams.R @ Q.T
    s = cams.s / c
    t = cams.t + cams.s[..., None] * (cams.R[..., :2, :] @ m_from) - s[..., None] * (R[..., :2, :] @ m_to)
    return ScaledOrthographic(R, s, t)


def lifted_residuals(res: SfMResult, keypoints: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """``(M, 3K)`` reprojection residuals of SfM rows lifted into the object frame (``R[:2]^T r / s``).

    Args:
        res: the SfM of ``M`` rows; keypoints ``(M, K, 2)``, visible ``(M, K)`` of those rows.
    """
    c = res.cameras
    P = c.project(torch.nan_to_num(res.shape))
    vis = visible & torch.isfinite(res.shape).all(-1)[None] & res.valid[:, None] & torch.isfinite(keypoints).all(-1)
    r = (torch.nan_to_num(keypoints) - P) * vis[..., None]
    return (torch.einsum("mki,mij->mkj", r, c.R[:, :2, :]) / c.s[:, None, None]).flatten(1)


def kmeans_labels(X: torch.Tensor, k: int, seed: int, restarts: int = 10) -> torch.Tensor:
    """``(n,)`` labels of the best of ``restarts`` k-means++ runs (scipy) of ``X (n, d)``, by
    within-cluster sum of squares. Same seed, same labels."""
    data = X.detach().double().cpu().numpy()
    best, best_cost = None, np.inf
    for r in range(restarts):
        centres, labels = kmeans2(data, k, minit="++", seed=np.random.default_rng(seed + r))
        cost = float(((data - centres[labels]) ** 2).sum())
        if cost < best_cost:
            best, best_cost = labels, cost
    return torch.as_tensor(best, dtype=torch.long, device=X.device)


def split_labels(labels: torch.Tensor, cost: torch.Tensor, X: torch.Tensor, min_size: int,
                 seed: int) -> torch.Tensor | None:
    """``(n,)`` labels of ``k + 1`` groups: ``k`` groups with the one of the largest summed cost among those
    of at least ``2 * min_size`` objects split in two by :func:`kmeans_labels` of its rows of ``X``; the
    part with fewer objects takes label ``k`` (of equal parts, the one without the group's first object).

    Args:
        labels: ``(n,)`` long groups ``0 .. k - 1``; cost: ``(n, k)`` every object's cost in every group;
        X: ``(n, d)`` features to split by (the lifted residuals).

    Returns:
        The new labels, or None when no group has ``2 * min_size`` objects or k-means finds one part
        only (the group's rows of ``X`` all alike, e.g. objects without an SfM camera).

    Example:
        >>> X = torch.tensor([[0.], [0.1], [5.], [5.1], [9.], [9.1]])
        >>> cost = torch.tensor([[1., 9.], [1., 9.], [9., 4.], [9., 4.], [9., 4.], [9., 4.]])
        >>> split_labels(torch.tensor([0, 0, 1, 1, 1, 1]), cost, X, 2, 0).tolist()
        [0, 0, 1, 1, 2, 2]
    """
    k = cost.shape[1]
    own = cost.gather(1, labels[:, None])[:, 0].double()
    sse = torch.zeros(k, dtype=torch.float64, device=own.device).index_add_(0, labels, own)
    room = torch.bincount(labels, minlength=k) >= 2 * min_size
    if not bool(room.any()):
        return None
    worst = int(torch.where(room, torch.nan_to_num(sse, nan=-1.0), float("-inf")).argmax())  # costs are >= 0
    members = (labels == worst).nonzero()[:, 0]
    part = kmeans_labels(X[members], 2, seed)
    ones = int(part.sum())
    if ones in (0, len(part)):
        return None
    moving = 1 - int(part[0]) if 2 * ones == len(part) else int(2 * ones < len(part))
    out = labels.clone()
    out[members[part == moving]] = k
    return out


def top_up(labels: torch.Tensor, cost: torch.Tensor, k: int, min_size: int) -> torch.Tensor:
    """Groups below ``min_size`` take the objects of larger groups that cost least to move.

    Args:
        labels: ``(n,)`` long group of every object; cost: ``(n, k)`` cost of every object in every group.

    Returns:
        New ``(n,)`` labels; no donor group is taken below ``min_size``.
    """
    labels = labels.clone()
    cost = cost.to(labels.device)
    for g in range(k):
        while int((labels == g).sum()) < min_size:  # one object at a time: no donor drops below the bound
            sizes = torch.bincount(labels, minlength=k)
            extra = torch.nan_to_num(cost[:, g] - cost.gather(1, labels[:, None])[:, 0], nan=float("inf"))
            extra[(labels == g) | (sizes[labels] <= min_size)] = float("inf")
            best = int(extra.argmin())
            if not bool(torch.isfinite(extra[best])):
                break  # no group can give an object away
            labels[best] = g
    return labels


class SplitFailed(ValueError):
    """A candidate split cannot be used (a group without a usable shape); the fit keeps fewer groups."""


#: A group whose own SfM shape (the keypoints its members show) is flatter than this is not usable:
#: coplanar keypoints leave the tilt of every camera of the group undetermined (a planar twin per
#: view, :func:`carvi_torch.viewpoints.camera_fit.planar_twin`), so its cameras are arbitrary along one rotation.
#: (The SfM's own ``planar`` flag does not catch it: on such a group the rigid model fits the plane
#: as well as the planar model does, and a nearly flat rigid shape comes back.)
PLANAR_THICKNESS = 0.1


def shape_thickness(S: torch.Tensor) -> float:
    """:func:`carvi_torch.viewpoints.camera_fit.keypoint_thickness` of the finite rows of ``S (K, 3)`` (in float64):
    0 for coplanar points, up to 1; ``0`` for fewer than 3 finite rows (no shape to speak of).

    Example:
        >>> shape_thickness(torch.tensor([[0., 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]))
        0.0
    """
    every = torch.ones(1, S.shape[0], dtype=torch.bool, device=S.device)
    th = float(camera_fit.keypoint_thickness(S.double(), every)[0])
    return th if math.isfinite(th) else 0.0


def fill_missing_rows(S: torch.Tensor, S_full: torch.Tensor) -> torch.Tensor:
    """``S`` with the rows it lacks (NaN) and ``S_full`` has, taken from ``S_full`` posed onto ``S``.

    The pose is the similarity (proper rotation :func:`rotation_onto`, scale, translation) that
    fits ``S_full`` onto ``S`` on their shared rows. A group's SfM leaves a keypoint NaN when no
    member of the group shows it; filled from the class's shape, every group's shape has the
    same keypoints, so keypoint costs under different groups' shapes count the same keypoints.

    Args:
        S: ``(K, 3)`` a group's shape; S_full: ``(K, 3)`` the whole class's shape.

    Raises:
        SplitFailed: fewer than 3 shared rows (no pose).
    """
    missing = ~torch.isfinite(S).all(-1) & torch.isfinite(S_full).all(-1)
    if not bool(missing.any()):
        return S
    shared = torch.isfinite(S).all(-1) & torch.isfinite(S_full).all(-1)
    try:
        Q = rotation_onto(S_full, S)  # S_full Q ~ c S
    except ValueError as e:
        raise SplitFailed(f"a group's shape cannot be completed from the class's: {e}") from None
    A, B = S_full[shared].to(S), S[shared]
    ma, mb = A.mean(0), B.mean(0)
    c = (B - mb).norm() / (A - ma).norm()
    out = S.clone()
    out[missing] = c * (S_full[missing].to(S) - ma) @ Q.to(S) + mb
    return out


def _group_sfm(both, labels: torch.Tensor, g: int, n: int, sfm_fn: SfMFn, full_shape: torch.Tensor | None,
               init: torch.Tensor | None = None):
    """``(rows, SfMResult)`` of group ``g`` (its SfM started from ``init`` when given), its shape
    completed from ``full_shape``; raises :class:`SplitFailed`."""
    rows = group_rows((labels == g).nonzero().squeeze(1), n)
    res = None
    if init is not None:
        try:
            res = sfm_fn(both[rows], init_shape=init)
        except torch.linalg.LinAlgError:  # a warm start is a shortcut only: start cold instead
            res = None
    if res is None:
        res = sfm_fn(both[rows])
    if int(torch.isfinite(res.shape).all(-1).sum()) < 3 or not bool(res.valid.any()):
        raise SplitFailed(f"group {g} ({len(rows) // 2} objects) has no usable SfM shape "
                          f"({int(res.valid.sum())} cameras, {int(torch.isfinite(res.shape).all(-1).sum())} keypoints)")
    thickness = shape_thickness(res.shape)
    if thickness < PLANAR_THICKNESS:
        raise SplitFailed(f"group {g} ({len(rows) // 2} objects) shows only (nearly) coplanar keypoints (thickness "
                          f"{thickness:.3f} < {PLANAR_THICKNESS}): the tilt of its cameras is undetermined")
    if full_shape is not None:
        placed = torch.isfinite(res.shape).all(-1)
        res = dataclasses.replace(res, shape=fill_missing_rows(res.shape, full_shape))
        res = dataclasses.replace(res, filled=torch.isfinite(res.shape).all(-1) & ~placed)
    return rows, res


def _warm_starts(groups, labels: torch.Tensor, prev, prior) -> list:
    """Per group, the starts of its keypoint fit: ``(R, s, t)`` batched ``(2n, B, ...)``, or None
    (search the sphere: the shapes could not be aligned).

    ``prev``: last round's ``(shapes, cameras)`` per group; starts under group ``g`` are its own last
    cameras and every row's camera under its assigned group, both carried onto the new shape.
    First round (``prev`` None): ``prior = (shape, cameras)`` carried onto every group's shape, and
    the group's SfM cameras for its own rows.
    """
    lab2 = labels.repeat(2)
    out = []
    for g, (rows, res) in enumerate(groups):
        try:
            if prev is None:
                first = transfer_cameras(prior[1], prior[0], res.shape)
                second = ScaledOrthographic(first.R.clone(), first.s.clone(), first.t.clone())
                c = res.cameras
                use = res.valid & torch.isfinite(c.R).flatten(1).all(-1) & torch.isfinite(c.t).all(-1) & (c.s > 0)
                r = rows[use]
                second.R[r], second.s[r], second.t[r] = c.R[use].to(first.R), c.s[use].to(first.s), c.t[use].to(first.t)
            else:
                shapes, cams = prev
                moved = [transfer_cameras(cams[h], shapes[h], res.shape) for h in range(len(groups))]
                first = moved[g]
                pick = lambda x: torch.stack(x)[lab2, torch.arange(len(lab2), device=lab2.device)]  # noqa: E731
                second = ScaledOrthographic(pick([m.R for m in moved]), pick([m.s for m in moved]),
                                            pick([m.t for m in moved]))
        except ValueError:
            out.append(None)
            continue
        out.append((torch.stack([first.R, second.R], 1), torch.stack([first.s, second.s], 1),
                    torch.stack([first.t, second.t], 1)))
    return out


def hard_em(both, n: int, dist: torch.Tensor, sfm_fn: SfMFn, labels: torch.Tensor, k: int, min_size: int,
            rounds: int = 6, full_shape: torch.Tensor | None = None,
            warm: tuple[torch.Tensor, ScaledOrthographic] | None = None, native: bool = False):
    """Hard EM over ``k`` rigid shapes from ``labels (n,)``.

    Args:
        full_shape: the whole class's SfM shape; rows a group's shape lacks are filled from it
            (:func:`fill_missing_rows`), so every group is scored on the same keypoints.
        warm: ``(shape, cameras)``: every row's keypoint-only camera under ``shape`` (the ``2n``
            rows; e.g. the one-shape fit). Given, the keypoint fits are warm-started
            (:func:`transfer_cameras`): the first round's from these cameras and the group's
            SfM cameras, later rounds' from the last round's cameras, each with the row's
            closed-form resection (:func:`keypoint_fit`; three starts per row and group instead
            of the search over the sphere). The groups' SfM runs cold in the first round (started
            from the class's shape, the sofa renders' groups stayed near it: 8.0 against 5.8
            degrees on 15 renders) and from the group's last shape later (``sfm_fn``'s
            ``init_shape``). ``None``: every round searches the sphere and every SfM starts cold.

    Returns:
        ``(labels, groups, cost, rotations, history)``: final labels; per group ``(rows, SfMResult)``
        (rows of ``both``, :func:`group_rows`); ``cost (n, k)``; per group ``(n, 3, 3)`` every object's
        keypoint-only rotation under the group's shape; per round the sizes and RMS pixel residual.

    Raises:
        SplitFailed: a group without a usable shape (too few cameras or keypoints).
    """
    ok_kp = torch.isfinite(both.keypoints).all(-1)
    nvis = ((both.visible & ok_kp)[:n].sum(-1) + (both.visible & ok_kp)[n:].sum(-1)).sum().clamp(min=1)
    history = []
    prev = None
    for it in range(rounds + 1):
        if warm is None:
            inits = [None] * k
        else:  # the first round's SfM starts cold, later ones from the group's last shape
            inits = [None] * k if prev is None else prev[0]
        groups = [_group_sfm(both, labels, g, n, sfm_fn, full_shape, inits[g]) for g in range(k)]
        starts = [None] * k if warm is None else _warm_starts(groups, labels, prev, warm)
        fits = [keypoint_fit(res.shape, both, dist, n, starts=st, native=native)
                for (_rows, res), st in zip(groups, starts)]
        prev = ([res.shape for _rows, res in groups], [c for _cost, c in fits])
        cost = torch.stack([c for c, _cams in fits], 1)
        new = top_up(cost.argmin(1), cost, k, min_size)
        moved = int((new != labels).sum())
        history.append({"round": it, "sizes": torch.bincount(labels, minlength=k).tolist(),
                        "rms_px": float(cost.gather(1, labels[:, None]).sum() / nvis) ** 0.5, "moved": moved})
        if it == rounds or moved <= int(EM_SETTLED * n):
            return labels, groups, cost, [cams.R[:n] for _c, cams in fits], history
        labels = new


def _map_candidates(fn, items: list, threads: int, device, stop: Callable | None = None) -> list:
    """``[fn(*item) for item in items]``, on at most ``threads`` Python threads, in order; with ``stop``,
    the list ends at the first result for which ``stop(result)`` is true (on one thread the items after
    it are not run; on several they ran and are dropped, so the list is the same either way).

    On the CPU the whole map runs with one intra-op thread (:func:`carvi_torch.runtime.cpu_single_thread`,
    set once here, on one thread or on several, so every op runs the same way in both cases: the
    solvers inside already run on one, and the few other ops would otherwise split their sums
    over the intra-op threads on one thread and not on several). Worker threads start with the
    caller's count. An exception in one item is raised here once all have finished.
    """
    with cpu_single_thread(device):
        if threads == 1 or len(items) < 2:
            out = []
            for item in items:
                out.append(fn(*item))
                if stop is not None and stop(out[-1]):
                    break
            return out
        with ThreadPoolExecutor(min(threads, len(items))) as pool:
            futures = [pool.submit(fn, *item) for item in items]
            out = [f.result() for f in futures]
    ends = [i for i, r in enumerate(out) if stop is not None and stop(r)]
    return out[:ends[0] + 1] if ends else out


def rotation_onto(S: torch.Tensor, S0: torch.Tensor) -> torch.Tensor:
    """Proper rotation ``Q (3, 3)`` with ``S Q ~ c S0`` on the rows finite in both (centred, unit norm).

    Args:
        S, S0: ``(K, 3)`` shapes; NaN rows are ignored.

    Returns:
        ``(3, 3)`` with det +1 (a mirror image is matched by a rotation, never a reflection), on
        ``S``'s device and dtype.

    Raises:
        ValueError: fewer than 3 rows finite in both shapes, or all of them on one line.
    """
    ok = torch.isfinite(S).all(-1) & torch.isfinite(S0).all(-1)
    if int(ok.sum()) < 3:
        raise ValueError(f"the two shapes share {int(ok.sum())} reconstructed keypoint(s); a rotation needs 3")
    A, B = S[ok].detach().double().cpu(), S0[ok].detach().double().cpu()
    A, B = A - A.mean(0), B - B.mean(0)
    for X in (A, B):  # collinear points leave the rotation about their line undetermined
        sv = torch.linalg.svdvals(X)
        if float(sv[0]) == 0 or float(sv[1]) <= 1e-6 * float(sv[0]):
            raise ValueError("a shape's shared keypoints all lie on one line; no rotation between the shapes")
    A, B = A / A.norm(), B / B.norm()
    rot, _ = Rotation.align_vectors(B.numpy(), A.numpy())  # rot maps rows of A onto rows of B
    return torch.as_tensor(rot.as_matrix().T, dtype=S.dtype, device=S.device)


def group_rotations(groups) -> list[torch.Tensor]:
    """``Q_g`` rotating every group's mean shape onto group 0's (the identity for one group)."""
    S0 = groups[0][1].shape
    return [torch.eye(3, dtype=S0.dtype, device=S0.device) if len(groups) == 1 else rotation_onto(res.shape, S0)
            for _r, res in groups]


def frame_agreement(rotations: list[torch.Tensor], Q: list[torch.Tensor], valid: torch.Tensor | None = None) -> float:
    """How well the groups' frames agree after the shape alignment (degrees; no ground truth).

    Every object has a keypoint-only camera ``R`` under every group's mean shape (from the EM);
    under the rotated shape ``S Q`` that camera is ``R Q``. If the frames agree, an object's
    rotations under two groups' shapes differ only by what the shape difference costs.

    Args:
        rotations: per group, ``(n, 3, 3)`` the objects' rotations under the group's shape.
        Q: per group, the rotation of its shape into the common frame (:func:`group_rotations`).
        valid: ``(n,)`` bool, the objects that count (those with an SfM camera: an object with
            fewer than 2 visible keypoints has an arbitrary rotation); default all.

    Returns:
        The largest, over pairs of groups, of the median angle between the two rotations over
        all objects (0 for one group; ``inf`` when a pair has no finite angle).
    """
    Rs = [R.double() @ q.to(R.device).double() for R, q in zip(rotations, Q)]
    if valid is not None:
        Rs = [R[valid.to(R.device)] for R in Rs]
    worst = 0.0
    for a in range(len(Rs)):
        for b in range(a + 1, len(Rs)):
            e = geodesic_errors(Rs[a], Rs[b])
            e = e[torch.isfinite(e)]
            worst = max(worst, float(e.median()) if len(e) else float("inf"))  # no camera pair: no agreement
    return worst


@dataclass
class MixtureResult:
    """Output of :func:`fit_mixture_of_shapes`.

    Attributes:
        k: groups kept (1: one rigid shape, as without the mixture).
        labels: ``(n,)`` long group of every object (its mirrored copy shares it).
        groups: per group ``(rows, SfMResult)``: rows of the ``2n`` collection (:func:`group_rows`)
            and the group's own SfM, in its own frame.
        Q: per group ``(3, 3)``: the rotation of its shape (and cameras) into the class frame (group 0's).
        agreement_deg: :func:`frame_agreement` of the kept groups (0 for one group).
        candidates: every split tried: ``{"k", "init", "sizes", "sse_px2", "cut", "agreement_deg",
            "eligible", "kept"}``, and once its EM ran, ``"rounds"`` (EM rounds run, each a fit of
            every group and a re-assignment; the last one scores the final labels, so at most
            ``rounds + 1`` of :func:`fit_mixture_of_shapes`'s ``rounds``), ``"moved"`` (objects
            that changed group after each round) and ``"settled"`` (whether the last round moved
            at most :data:`EM_SETTLED` of the objects; False: stopped at the cap).
        single: the one-shape SfM of the whole class (always run first).
        note: why no split was tried (``None`` when one was, or with ``max_groups = 1``).
        misfit: :func:`misfit` of the one-shape SfM (``None`` when not measured).
        cost: ``(n, k)`` every object's squared keypoint residual under every group's shape, from the
            EM's last round (``None`` for one shape); the next ``k``'s ``split`` start reads it.
    """

    k: int
    labels: torch.Tensor
    groups: list
    Q: list
    agreement_deg: float
    single: SfMResult
    candidates: list = field(default_factory=list)
    note: str | None = None
    misfit: float | None = None
    cost: torch.Tensor | None = None

    def shape(self, g: int) -> torch.Tensor:
        """``(K, 3)`` mean shape of group ``g`` in the class frame, centred on the keypoints every group's own
        SfM placed (one group: the SfM shape itself).

        A group's SfM centres its shape on the keypoints its own objects show, and the rows it lacks are filled
        from the class's shape afterwards (:func:`fill_missing_rows`), so its origin is not the same point of the
        object as another group's: a surrogate of one group would be carved into a reference of another that
        far off. Centred on the same named keypoints in every group, every group's cameras place one point of
        the object.
        """
        S = self.groups[g][1].shape
        if self.k == 1:
            return S
        S = S @ self.Q[g].to(S)
        return S - self._origin(g).to(S)

    def cameras(self, g: int) -> ScaledOrthographic:
        """SfM cameras of group ``g``'s rows (``groups[g][0]``) in the class frame, for :meth:`shape` (its
        projections are those of the group's own SfM shape and cameras)."""
        c = self.groups[g][1].cameras
        R = c.R @ self.Q[g].to(c.R)
        if self.k == 1:
            return ScaledOrthographic(R, c.s, c.t)
        return ScaledOrthographic(R, c.s, c.t + c.s[:, None] * (R[:, :2, :] @ self._origin(g).to(R)))

    def _origin(self, g: int) -> torch.Tensor:
        """``(3,)`` group ``g``'s centroid of the keypoints every group's own SfM placed (not filled from the
        class's shape: ``SfMResult.filled``), in the class frame; of all its finite rows where the groups share no
        such keypoint."""
        S = self.groups[g][1].shape
        S = S @ self.Q[g].to(S)
        common = torch.ones(S.shape[0], dtype=torch.bool, device=S.device)
        for _rows, res in self.groups:
            common &= torch.isfinite(res.shape).all(-1).to(common.device)
            if res.filled is not None:
                common &= ~res.filled.to(common.device)
        if not bool(common.any()):
            common = torch.isfinite(S).all(-1)
        return S[common].mean(0)

    def sizes(self) -> list[int]:
        """Objects per group (host ints)."""
        return torch.bincount(self.labels, minlength=self.k).tolist()

    def largest(self) -> int:
        """The group with the most objects (the first of equals)."""
        sizes = self.sizes()
        return sizes.index(max(sizes))

    def summary(self) -> dict:
        """JSON-ready: groups kept, their sizes, the frame agreement, every candidate (and a note
        when no split was tried)."""
        out = {"groups": self.k, "sizes": self.sizes(), "frame_agreement_deg": self.agreement_deg,
               "candidates": self.candidates}
        if self.note:
            out["note"] = self.note
        if self.misfit is not None:
            out["misfit"] = self.misfit
        return out


def misfit(res: SfMResult, masks: torch.Tensor) -> float:
    """How badly one rigid shape fits a class: the median (torch's: the lower middle value of an even
    count), over the rows with an SfM camera, of each row's keypoint RMS residual over the diagonal of its
    mask's box (0 for an exact fit; NaN without a row).

    Args:
        res: the one-shape SfM of ``M`` rows; masks: ``(M, H, W)`` bool, their masks.

    Example:
        >>> from types import SimpleNamespace
        >>> masks = torch.zeros(2, 8, 8, dtype=torch.bool); masks[:, 1:4, 1:5] = True  # 3 x 4 boxes: diagonal 5
        >>> res = SimpleNamespace(residual=torch.tensor([0.5, float("nan")]), valid=torch.tensor([True, False]))
        >>> misfit(res, masks)
        0.1
    """
    ok = res.valid.to(masks.device) & torch.isfinite(res.residual).to(masks.device)
    if not bool(ok.any()):
        return float("nan")
    rel = res.residual.to(masks.device, torch.float64)[ok] / box_diagonal(masks[ok])
    return round(float(rel.median()), 6)


def hull_agreements(mix: "MixtureResult", masks: torch.Tensor) -> torch.Tensor:
    """``(2n,)`` float64: every row's agreement (IoU) of its mask with the convex hull of its group's mean
    shape projected by its SfM camera (:func:`carvi_torch.viewpoints.choice.hull_agreement`); NaN for the
    rows without an SfM camera. A silhouette measure the keypoint-only EM does not optimise."""
    out = torch.full((masks.shape[0],), float("nan"), dtype=torch.float64)
    for g in range(mix.k):
        rows, res = mix.groups[g]
        on = rows[res.valid.to(rows.device)]
        if on.numel():
            cams = mix.cameras(g)[res.valid.nonzero().squeeze(1)]
            out[on.cpu()] = hull_agreement(mix.shape(g), cams, masks[on.to(masks.device)])
    return out


def _hull_gain(hull: torch.Tensor, hull1: torch.Tensor) -> float:
    """Median, over the rows with both, of a split's hull agreement minus the one shape's (NaN: no row)."""
    d = hull - hull1
    d = d[torch.isfinite(d)]
    return round(float(d.median()), 6) if d.numel() else float("nan")


def fit_mixture_of_shapes(both, dist: torch.Tensor, sfm_fn: SfMFn, *, max_groups: int = 3, min_size: int = 15,
                          gain: float = 0.3, agreement_deg: float = 60.0, rounds: int = 6, seed: int = 0,
                          single: SfMResult | None = None, log: Callable[[str], None] | None = None,
                          warm_start: bool = True, threads: int = 2,
                          threads_min_objects: int = THREADS_MIN_OBJECTS, min_misfit: float = 0.0,
                          hull_gain: float | None = None, native: bool = False) -> MixtureResult:
    """Fit at most ``max_groups`` rigid shapes to a class (see the module docstring for the rule).

    Args:
        both: the class with its mirrored copies (``2n`` instances, copy ``i + n`` mirrors ``i``).
        dist: ``(2n, H, W)`` distance maps of its masks (:func:`carvi_torch.sdf.distance_to_mask`).
        sfm_fn: rigid SfM of a sub-collection with the run's settings.
        max_groups: most groups (``1``: the one-shape SfM only).
        min_size: fewest objects per group; a class with fewer than ``2 * min_size`` objects keeps one shape.
        gain: a split is kept when it cuts the residual of one group fewer by more than this fraction.
        agreement_deg: a split is only eligible when its groups' frames agree within this (degrees).
        rounds: most EM rounds per candidate.
        seed: seed of the k-means starts.
        single: the one-shape SfM of ``both`` when already computed.
        log: called with a line per candidate.
        warm_start: the EM's keypoint fits start from the one-shape fit and then from the last
            round (:func:`hard_em`'s ``warm``); False: every fit searches the sphere (slower).
        threads: Python threads that run a ``k``'s initialisations side by side (1: one after
            the other), on classes of at least ``threads_min_objects`` objects (smaller ones
            run on one). The result is the same either way (each EM is the same sequence of tensor
            ops, each on one intra-op thread); on the CPU the two share the cores, on a GPU the
            launches interleave.
        threads_min_objects: class size from which ``threads`` apply (default :data:`THREADS_MIN_OBJECTS`;
            0: always, as the benchmark does to measure small classes).
        min_misfit: no split is tried when the one-shape SfM's :func:`misfit` is below this (one rigid
            shape fits the class; the mixture's cost is saved). 0: always try.
        hull_gain: a ``k`` is only eligible when each of its usable starts raises the median hull
            agreement of the rows (:func:`hull_agreements`, under each row's group shape and SfM
            camera) by at least this over one shape; the starts after one that fails are not recorded
            (on one thread not run). ``None``: not measured, no such test.
        native: the EM's keypoint-only camera fits in the compiled kernel on the CPU (:func:`keypoint_fit`; the
            pipeline's ``sfm_native``).

    Returns:
        :class:`MixtureResult`.
    """
    if max_groups < 1 or min_size < 1:
        raise ValueError(f"max_groups and min_size must be >= 1, got {max_groups} and {min_size}")
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    n = len(both) // 2
    best = _one_shape(both, sfm_fn(both) if single is None else single)
    if not _split_gate(best, both, n, max_groups, min_size, min_misfit):
        return best
    ctx = _em_context(best, both, dist, n, sfm_fn, rounds=rounds, min_size=min_size, agreement_deg=agreement_deg,
                      warm_start=warm_start, native=native, hull_gain=hull_gain)
    workers = threads if n >= threads_min_objects else 1
    sse_prev = float(ctx.cost1.sum())
    for k in range(2, max_groups + 1):
        if n < k * min_size:
            break
        inits = _initial_labels(ctx, best, k, seed)
        cands = _run_starts(ctx, best, k, inits, sse_prev, workers, log)
        ok = [c for c in cands if c[0]["eligible"]]
        if not ok:
            break
        row, res = min(ok, key=lambda c: c[0]["sse_px2"])
        if row["cut"] <= gain:
            break
        row["kept"] = True
        res.candidates = best.candidates
        best, sse_prev = res, row["sse_px2"]
    return best


def _one_shape(both, res1: SfMResult) -> MixtureResult:
    """The one-shape :class:`MixtureResult` of ``both`` from its SfM ``res1``."""
    n = len(both) // 2
    eye = torch.eye(3, dtype=res1.shape.dtype, device=res1.shape.device)
    labels1 = torch.zeros(n, dtype=torch.long, device=both.keypoints.device)
    return MixtureResult(1, labels1, [(torch.arange(2 * n, device=both.keypoints.device), res1)], [eye], 0.0, res1)


def _split_gate(best: MixtureResult, both, n: int, max_groups: int, min_size: int, min_misfit: float) -> bool:
    """Sets ``best.misfit`` (with ``max_groups > 1`` and at least ``2 * min_size`` objects) and, when no split is
    to be tried with ``max_groups > 1``, ``best.note`` saying why; returns whether :func:`fit_mixture_of_shapes`
    tries one."""
    if max_groups == 1:
        return False
    if n < 2 * min_size:
        best.note = f"one shape: {n} objects, fewer than twice the smallest group ({min_size})"
        return False
    best.misfit = misfit(best.single, both.masks)
    if min_misfit > 0 and not best.misfit >= min_misfit:
        best.note = (f"one shape: it fits the keypoints (residual {best.misfit:.4f} of the box diagonal, "
                     f"under {min_misfit})")
        return False
    return True


@dataclass(frozen=True, eq=False)
class _EMContext:
    """What every start of one class's EM shares (read only, also by worker threads): the class, its one-shape
    fit and the rule's settings."""

    both: object  # the 2n collection (originals, then mirrored copies), as fit_mixture_of_shapes's ``both``
    n: int
    dist: torch.Tensor
    sfm_fn: SfMFn
    res1: SfMResult
    cost1: torch.Tensor  # (n,) each object's keypoint cost under the one shape
    cams1: ScaledOrthographic  # the one shape's keypoint fit (the EM's warm start)
    lifted: torch.Tensor  # (n, 6K) unit rows: the object's lifted residuals (3K), then its mirrored copy's
    nvis_obj: torch.Tensor  # (n,) visible keypoints of each object and its copy (at least 1)
    rounds: int
    min_size: int
    agreement_deg: float
    warm_start: bool
    native: bool
    hull_gain: float | None
    hull1: torch.Tensor | None  # the rows' hull agreements under one shape (None: no hull test)


def _em_context(best: MixtureResult, both, dist, n, sfm_fn, *, rounds, min_size, agreement_deg, warm_start, native,
                hull_gain) -> _EMContext:
    """The one-shape measures every start reads: hull agreements, the keypoint fit over the sphere, the
    lifted residuals (unit rows) and the visible counts."""
    res1 = best.single
    hull1 = hull_agreements(best, both.masks) if hull_gain is not None else None
    cost1, cams1 = keypoint_fit(res1.shape, both, dist, n)  # the one search over the sphere
    seen = both.visible & torch.isfinite(both.keypoints).all(-1)
    lifted = lifted_residuals(res1, both.keypoints, both.visible)
    lifted = torch.cat([lifted[:n], lifted[n:]], 1)
    return _EMContext(both=both, n=n, dist=dist, sfm_fn=sfm_fn, res1=res1, cost1=cost1, cams1=cams1,
                      lifted=lifted / lifted.norm(dim=1, keepdim=True).clamp(min=1e-9),
                      nvis_obj=(seen[:n].sum(-1) + seen[n:].sum(-1)).clamp(min=1), rounds=rounds, min_size=min_size,
                      agreement_deg=agreement_deg, warm_start=warm_start, native=native, hull_gain=hull_gain,
                      hull1=hull1)


def _initial_labels(ctx: _EMContext, best: MixtureResult, k: int, seed: int) -> dict[str, torch.Tensor]:
    """The EM's starting labels for ``k`` groups: k-means of the lifted residuals, bands of the one-shape
    residual and, from the kept ``k - 1`` groups, the costliest one split in two (when it can be)."""
    n = ctx.n
    inits = {"lifted": kmeans_labels(ctx.lifted, k, seed),
             "residual": ((ctx.cost1 / ctx.nvis_obj).argsort(stable=True).argsort(stable=True) * k // n)
             .clamp(max=k - 1)}
    split = None if best.cost is None else split_labels(best.labels, best.cost, ctx.lifted, ctx.min_size, seed)
    if split is not None:
        inits["split"] = split
    return inits


def _run_starts(ctx: _EMContext, best: MixtureResult, k: int, inits: dict, sse_prev: float, workers: int,
                log: Callable[[str], None] | None) -> list:
    """Every start's EM for ``k`` groups, side by side on ``workers`` threads (:func:`_map_candidates`; with
    the hull test the starts after the first that fails it are not recorded, and on one thread not run):
    ``[(row, MixtureResult)]`` of the usable ones, each row also appended to ``best.candidates`` and
    logged, each row's ``eligible`` set."""
    cands = []
    fails = None if ctx.hull1 is None else (lambda r: not r[0].get("hull_gain", ctx.hull_gain) >= ctx.hull_gain)
    items = [(ctx, best.misfit, name, lab0, k, sse_prev) for name, lab0 in inits.items()]
    for row, res, line in _map_candidates(_candidate, items, workers, ctx.both.keypoints.device, stop=fails):
        best.candidates.append(row)
        if res is not None:
            cands.append((row, res))
        if log is not None:
            log(line)
    if ctx.hull1 is not None:  # every usable start of this k must raise the hull agreement enough
        gains = [c[0]["hull_gain"] for c in cands]
        floor = min(gains) if gains and all(math.isfinite(g) for g in gains) else float("nan")
        for row, _res in cands:
            row["eligible"] = bool(row["eligible"] and floor >= ctx.hull_gain)
    return cands


def _candidate(ctx: _EMContext, misfit1: float | None, name: str, lab0: torch.Tensor, k: int, sse_prev: float):
    """``(row, MixtureResult or None, log line)`` of the EM from one start.

    Args:
        ctx: the class's shared measures; misfit1: the one-shape :func:`misfit`, copied into the result.
        name: the start's name (``row["init"]``); lab0: ``(n,)`` its labels, topped up to ``min_size`` here.
        k: groups; sse_prev: the residual of the best ``k - 1`` groups, against which ``row["cut"]`` is taken.
    """
    n = ctx.n
    lab0 = top_up(lab0, torch.zeros(n, k, device=lab0.device), k, ctx.min_size)
    row = {"k": k, "init": name, "sizes": None, "sse_px2": float("inf"), "cut": float("-inf"),
           "agreement_deg": float("inf"), "eligible": False, "kept": False}
    try:
        lab, groups, cost, rotations, hist = hard_em(ctx.both, n, ctx.dist, ctx.sfm_fn, lab0, k, ctx.min_size,
                                                      ctx.rounds, full_shape=ctx.res1.shape,
                                                      warm=(ctx.res1.shape, ctx.cams1) if ctx.warm_start else None,
                                                      native=ctx.native)
    except SplitFailed as e:
        row["problem"] = str(e)
        return row, None, f"{k} shapes from '{name}': not usable: {e}"
    sse = float(cost.gather(1, lab[:, None]).sum())
    row.update(sizes=torch.bincount(lab, minlength=k).tolist(), sse_px2=sse, cut=1 - sse / max(sse_prev, 1e-12),
               rounds=len(hist), moved=[h["moved"] for h in hist], settled=hist[-1]["moved"] <= int(EM_SETTLED * n))
    try:
        Q = group_rotations(groups)
    except ValueError as e:  # a group's shape cannot be put in the class frame: not a usable split
        row["problem"] = f"no class frame: {e}"
        return row, None, f"{k} shapes from '{name}': sizes {row['sizes']}, {row['problem']}"
    row["agreement_deg"] = frame_agreement(rotations, Q, valid=ctx.res1.valid[:n])
    row["eligible"] = bool(row["agreement_deg"] <= ctx.agreement_deg and math.isfinite(sse))
    out = MixtureResult(k, lab, groups, Q, row["agreement_deg"], ctx.res1, misfit=misfit1, cost=cost)
    line = (f"{k} shapes from '{name}': sizes {row['sizes']}, residual cut {row['cut']:.0%}, "
            f"frames agree within {row['agreement_deg']:.0f} deg")
    if ctx.hull1 is not None:
        row["hull_gain"] = _hull_gain(hull_agreements(out, ctx.both.masks), ctx.hull1)
        line += f", hull agreement {row['hull_gain']:+.3f}"
    return row, out, line
