"""Viewpoint metrics: compare estimated cameras with ground-truth ones.

Estimated rotations are written in a class's canonical frame
(:mod:`carvi_torch.viewpoints.frame`), ground truth in its own (e.g. PASCAL3D+'s CAD frame:
+z up, front towards -y). :func:`viewpoint_report` compares them twice: ``absolute``, as
written (what a user training on the labels gets), and aligned, after one global rotation
``G`` with ``R_est G ~ R_gt`` (:func:`align_rotations`): the error of the cameras alone,
whatever the frame.
Camera convention (``carvi_torch.cameras``): rows of ``R`` = image x, image y (down),
viewing direction, in the object frame.

Orthographic SfM may also return the mirror image of the true frame (the Necker
ambiguity, when its reflection vote fails): then ``R_est = F R_true Q F`` with
``F = diag(1, 1, -1)`` and no proper ``G`` aligns the sets. :func:`viewpoint_report`
measures both hypotheses and *reports* a mirrored frame; it never silently fixes it.

:func:`compare_camera_runs` compares two runs of the same data instead (e.g. the CPU's cameras
with CUDA's): object by object, the angle between their refined rotations.

All angles returned are in degrees.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..cameras import (align_rotations, azimuth_elevation_roll_from_rotation, check_rotation_pairs,
                       finite_rotation_pairs, geodesic_angle, geodesic_errors)
from ..io.outputs import read_json

__all__ = [
    "align_rotations",
    "geodesic_errors",
    "angle_errors",
    "summarize",
    "viewpoint_report",
    "necker_mirror",
    "compare_camera_runs",
    "RUN_AGREEMENT_DEG",
    "RUN_TURNED_DEG",
    "aligned_median",
    "median_change",
    "fit_up_axis",
    "up_axis_errors",
]

#: Two runs of the same data agree when each class's median angle between their cameras is at most this
#: (degrees; the CPU against CUDA, docs/viewpoints.md, *CPU and CUDA*).
RUN_AGREEMENT_DEG = 0.5
#: An object whose two cameras are further apart than this (degrees) is listed by :func:`compare_camera_runs`
#: (``turned``): a median hides the few views that flip between near-equal solutions (views with few visible
#: keypoints: front and back exchanged, cameras from the silhouette or the mean shape alone).
RUN_TURNED_DEG = 1.0
#: Bootstrap resamples evaluated at once by :func:`median_change` (memory grows with it times the objects).
BOOTSTRAP_BATCH = 100


def necker_mirror(R: torch.Tensor) -> torch.Tensor:
    """The Necker-mirrored cameras ``F R F``, ``F = diag(1, 1, -1)``: ``(..., 3, 3)`` -> same.

    They see the mirrored object ``F S`` exactly as ``R`` sees ``S``, with depths negated.
    """
    f = torch.tensor([1.0, 1.0, -1.0], dtype=R.dtype, device=R.device)
    return f[:, None] * R * f[None, :]


def _wrap_deg(a: torch.Tensor) -> torch.Tensor:
    """Absolute angle difference wrapped to ``[0, 180]`` degrees, from radians."""
    return torch.rad2deg(torch.remainder(a + math.pi, 2 * math.pi) - math.pi).abs()


def angle_errors(R_est: torch.Tensor, R_gt: torch.Tensor, G: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Azimuth, elevation and roll errors (degrees, wrapped) of ``R_est G`` vs ``R_gt``.

    Angles follow PASCAL3D+ (``cameras.azimuth_elevation_roll_from_rotation``; the
    ground-truth object frame has +z up and its front towards -y).

    Returns:
        ``{"azimuth": (N,), "elevation": (N,), "roll": (N,)}``, each in ``[0, 180]``.
    """
    check_rotation_pairs(R_est, R_gt)
    Re = R_est if G is None else R_est @ G.to(R_est)
    a1, e1, r1 = azimuth_elevation_roll_from_rotation(Re)
    a2, e2, r2 = azimuth_elevation_roll_from_rotation(R_gt.to(Re))
    return {"azimuth": _wrap_deg(a1 - a2), "elevation": _wrap_deg(e1 - e2), "roll": _wrap_deg(r1 - r2)}


def fit_up_axis(R_est: torch.Tensor, R_gt: torch.Tensor) -> torch.Tensor:
    """The estimated frame's direction that best matches the ground truth's up (+z) in every camera.

    ``u`` maximises ``sum_n <R_est_n u, R_gt_n e_z>``: ``u = normalize(sum_n R_est_n^T R_gt_n e_z)``, the
    least-squares alignment of the up axes alone (a rotation about the up axis is left free, as it is for an
    object that looks the same from every azimuth). Pairs with a non-finite entry are ignored.

    Args:
        R_est, R_gt: ``(N, 3, 3)`` rotations.

    Returns:
        ``(3,)`` unit vector in the estimated object frame, in ``R_est``'s dtype.

    Example:
        >>> from carvi_torch.cameras import random_rotations
        >>> R = random_rotations(3, torch.Generator().manual_seed(0))
        >>> fit_up_axis(R, R).round(decimals=4).tolist()
        [0.0, 0.0, 1.0]
    """
    check_rotation_pairs(R_est, R_gt)
    ok = finite_rotation_pairs(R_est, R_gt)
    if not bool(ok.any()):
        raise ValueError("fit_up_axis: no pair of finite rotations")
    v = torch.einsum("nji,nj->i", R_est[ok].double(), R_gt[ok].double()[..., :, 2])
    return (v / v.norm().clamp(min=1e-300)).to(R_est.dtype)


def up_axis_errors(R_est: torch.Tensor, R_gt: torch.Tensor, align: bool = True,
                   axis: torch.Tensor | None = None) -> torch.Tensor:
    """Angle (degrees) between where two cameras see the object's up axis: the viewpoint error that ignores
    azimuth, for rotationally symmetric objects (bottles).

    The up axis is the ground truth's +z (PASCAL3D+'s CAD frame; a bottle's axis of symmetry). The
    angle between ``R_est_n u`` and ``R_gt_n e_z`` equals the smallest geodesic error of ``R_est_n`` over
    every rotation of the object about that axis: elevation and roll count, azimuth does not. ``u`` is
    :func:`fit_up_axis` with ``align`` (the aligned error), the estimate's own +z without (as written), or
    ``axis`` when given (e.g. ``G e_z`` of a global alignment ``G`` fitted elsewhere).

    Args:
        R_est, R_gt: ``(N, 3, 3)`` rotations.
        align: fit ``u`` (else ``u = e_z``).
        axis: ``(3,)`` unit ``u`` in the estimated frame; overrides ``align``.

    Returns:
        ``(N,)`` in ``[0, 180]``; NaN where an input is not finite.

    Example:
        >>> from carvi_torch.cameras import random_rotations, rotation_from_azimuth_elevation_roll
        >>> R = rotation_from_azimuth_elevation_roll(torch.tensor([0.0]), torch.tensor([0.3]), torch.tensor([0.0]))
        >>> turned = rotation_from_azimuth_elevation_roll(torch.tensor([2.0]), torch.tensor([0.3]), torch.tensor([0.0]))
        >>> up_axis_errors(turned, R, align=False).abs().item() < 1e-3  # an azimuth error alone
        True
    """
    check_rotation_pairs(R_est, R_gt)
    if axis is not None:
        u = torch.as_tensor(axis, dtype=R_est.dtype)
    else:
        u = fit_up_axis(R_est, R_gt) if align else torch.tensor([0.0, 0.0, 1.0], dtype=R_est.dtype)
    a = R_est.double() @ u.to(R_est.device).double()
    b = R_gt.to(R_est.device).double()[..., :, 2]
    cos = (a * b).sum(-1) / (a.norm(dim=-1) * b.norm(dim=-1))
    sin = torch.linalg.cross(a, b).norm(dim=-1) / (a.norm(dim=-1) * b.norm(dim=-1))
    return torch.rad2deg(torch.atan2(sin, cos)).to(R_est.dtype)


def summarize(errors: torch.Tensor, threshold: float = 30.0) -> dict:
    """Median, mean and accuracy of angular errors (degrees); NaNs are left out.

    The median of an even count is the mean of the two middle values (as numpy and
    MATLAB's ``median``, which PASCAL3D+'s MedErr uses), not ``torch.median``'s lower one.

    Returns:
        ``{"n": int, "median": float, "mean": float, "acc_at_30": float}`` where
        ``acc_at_30`` is the fraction of errors below ``threshold`` degrees
        (PASCAL3D+'s ``Acc_pi/6`` with the default). Empty input gives NaNs and ``n = 0``.

    Example:
        >>> summarize(torch.tensor([1.0, 2.0, 40.0]))["acc_at_30"]
        0.6666666865348816
    """
    e = torch.as_tensor(errors).flatten()
    e = e[torch.isfinite(e)]
    if e.numel() == 0:
        return {"n": 0, "median": float("nan"), "mean": float("nan"), "acc_at_30": float("nan")}
    return {
        "n": int(e.numel()),
        "median": float(torch.quantile(e.double(), 0.5)),
        "mean": float(e.mean()),
        "acc_at_30": float((e < threshold).float().mean()),
    }


def aligned_median(R_est: torch.Tensor, R_gt: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Median geodesic error (degrees) after the alignment :func:`align_rotations` fits, of weighted sets.

    Integer ``weights`` count each pair that many times: the result equals the plain median (as
    :func:`summarize` takes it) of the pairs repeated so, aligned again; that is what one bootstrap
    resample of :func:`median_change` measures.

    Args:
        R_est, R_gt: ``(N, 3, 3)`` finite rotations.
        weights: ``(N,)`` or ``(B, N)`` non-negative counts (default: ones), each row with a positive sum.

    Returns:
        ``()`` or ``(B,)`` float64 medians in degrees.

    Example:
        >>> from carvi_torch.cameras import random_rotations
        >>> R = random_rotations(4, torch.Generator().manual_seed(0)).double()
        >>> aligned_median(R, R, torch.tensor([[1.0, 0.0, 2.0, 1.0], [0.0, 0.0, 1.0, 0.0]])).abs().max() < 1e-6
        tensor(True)
    """
    w = torch.ones(len(R_est), dtype=torch.float64) if weights is None else torch.as_tensor(weights).double().cpu()
    if (w.shape[-1:] != (len(R_est),) or w.dim() > 2 or not bool((w >= 0).all()) or not bool((w == w.round()).all())
            or not bool((w.sum(-1) > 0).all())):
        raise ValueError(f"weights must be ({len(R_est)},) or (B, {len(R_est)}) non-negative integer counts, each row "
                         f"with a positive sum, got {tuple(w.shape)}")
    Re, Rg = R_est.double().cpu(), R_gt.double().cpu()
    G = align_rotations(Re, Rg, weights=w)  # (3, 3) or (B, 3, 3)
    err = torch.rad2deg(geodesic_angle(Re @ G[..., None, :, :], Rg))  # (N,) or (B, N)
    e, order = torch.sort(err, dim=-1)
    c = torch.cumsum(torch.gather(w.expand_as(err), -1, order), -1)
    total = c[..., -1:]
    # the two middle positions (0-based) of the repeated, sorted errors; equal for an odd count
    mid = [torch.floor((total - 1) / 2), torch.ceil((total - 1) / 2)]
    picks = [torch.gather(e, -1, torch.searchsorted(c, m + 0.5).clamp(max=e.shape[-1] - 1)) for m in mid]
    return (0.5 * (picks[0] + picks[1])).squeeze(-1)


def median_change(R_before: torch.Tensor, R_after: torch.Tensor, R_gt: torch.Tensor, clusters=None, *,
                  runs=None, resamples: int = 1000, level: float = 0.95, seed: int = 0) -> dict:
    """Change of the aligned median geodesic error from one set of cameras to another, with a bootstrap interval.

    ``change = aligned_median(R_after) - aligned_median(R_before)``, each set aligned with the ground truth by
    its own global rotation. The interval is the percentile bootstrap (``scipy.stats.bootstrap``) over
    ``clusters``: whole clusters (e.g. the views of one physical object, which share its shape) are drawn with
    replacement and both sets are aligned again on every resample. An interval that lies above 0 says the
    second set is worse beyond what another draw of the objects moves the medians. With ``runs`` (e.g. renders
    of the same objects from other cameras, each estimated on its own) every run is aligned on its own, the
    change is the mean of the runs' changes, and a drawn cluster counts in every run that holds it; a
    resample that draws none of a run's clusters takes the mean over the other runs.

    Args:
        R_before, R_after, R_gt: ``(N, 3, 3)`` finite rotations of the same N objects.
        clusters: ``N`` hashable labels, at least 2 distinct (default: every object its own cluster).
        runs: ``N`` hashable labels of the run each object belongs to (default: one run).
        resamples: bootstrap resamples.
        level: the interval's confidence level.
        seed: the resampling's seed (same seed, same interval).

    Returns:
        ``{"change", "low", "high"}`` (degrees) and ``"clusters"``, ``"objects"``, ``"runs"``, ``"resamples"``,
        ``"level"``.

    Example:
        >>> from carvi_torch.cameras import random_rotations
        >>> R = random_rotations(6, torch.Generator().manual_seed(1)).double()
        >>> median_change(R, R, R, resamples=50)["high"]
        0.0
    """
    from scipy.stats import bootstrap

    n = len(R_gt)
    if not (R_before.shape == R_after.shape == R_gt.shape == (n, 3, 3)) or n < 2:
        raise ValueError(f"median_change: need three (N, 3, 3) rotation sets of one N >= 2, got "
                         f"{tuple(R_before.shape)}, {tuple(R_after.shape)}, {tuple(R_gt.shape)}")
    labels = list(range(n)) if clusters is None else list(clusters)
    if len(labels) != n:
        raise ValueError(f"median_change: {len(labels)} cluster labels for {n} objects")
    index = {lab: i for i, lab in enumerate(dict.fromkeys(labels))}
    if len(index) < 2:
        raise ValueError("median_change: one cluster; the bootstrap needs at least 2")
    of = torch.tensor([index[lab] for lab in labels])
    run_of = [0] * n if runs is None else list(runs)
    if len(run_of) != n:
        raise ValueError(f"median_change: {len(run_of)} run labels for {n} objects")
    groups = [torch.tensor([i for i, r in enumerate(run_of) if r == g]) for g in dict.fromkeys(run_of)]

    def change(drawn, axis=-1) -> np.ndarray:  # drawn: (..., C) cluster indices, one resample per row
        d = torch.as_tensor(np.asarray(drawn), dtype=torch.long)
        counts = torch.zeros(*d.shape[:-1], len(index), dtype=torch.float64).scatter_add_(
            -1, d, torch.ones_like(d, dtype=torch.float64))
        parts = []
        for idx in groups:
            w = counts[..., of[idx]]
            empty = w.sum(-1) == 0  # a resample that draws none of this run's clusters leaves the run out
            w = torch.where(empty[..., None], torch.ones_like(w), w)
            c = aligned_median(R_after[idx], R_gt[idx], w) - aligned_median(R_before[idx], R_gt[idx], w)
            parts.append(torch.where(empty, torch.nan, c))
        return torch.nanmean(torch.stack(parts), 0).numpy()

    full = float(change(np.arange(len(index))))
    res = bootstrap((np.arange(len(index)),), change, vectorized=True, n_resamples=resamples, batch=BOOTSTRAP_BATCH,
                    confidence_level=level, method="percentile", rng=np.random.default_rng(seed))
    lo, hi = (float(x) for x in (res.confidence_interval.low, res.confidence_interval.high))
    return {"change": full, "low": lo, "high": hi, "clusters": len(index), "objects": n, "runs": len(groups),
            "resamples": resamples, "level": level}


def viewpoint_report(
    R_est: torch.Tensor,
    R_gt: torch.Tensor,
    *,
    valid: torch.Tensor | None = None,
    robust: bool = False,
    alignment: torch.Tensor | None = None,
) -> dict:
    """Everything about estimated vs ground-truth viewpoints, JSON-ready.

    Aligns the frames (:func:`align_rotations`, or the given ``alignment``), then reports geodesic, azimuth,
    elevation and roll error summaries. It also aligns the Necker-mirrored cameras
    (:func:`necker_mirror`) and sets ``"mirrored": True`` when they fit the ground
    truth better (median geodesic error): the estimated object frame is then the
    mirror image of the true one. The reported errors stay those of the cameras as
    given.

    Args:
        R_est, R_gt: ``(N, 3, 3)``.
        valid: ``(N,)`` bool, pairs to use (default: all finite).
        robust: robust alignment.
        alignment: ``(3, 3)`` a global rotation ``G`` (``R_est G ~ R_gt``) fitted elsewhere,
            e.g. on other instances of the same SfM frame (cameras of unseen images
            evaluated without fitting ``G`` to their own ground truth). ``None``: fit it
            here. The mirrored hypothesis is always fitted here.

    Returns:
        ``{"n", "alignment" (3x3 list), "geodesic", "azimuth", "elevation", "roll"
        (each a :func:`summarize` dict, after the alignment), "up_axis" (:func:`up_axis_errors`
        summarised: the error that ignores azimuth, for rotationally symmetric classes; the up axes
        aligned on their own, or by the given ``alignment``), "absolute" (the same five
        without any fitted rotation), "mirrored" (bool), "mirrored_geodesic" (summary of
        the mirrored hypothesis), "per_instance_geodesic" (list, NaN for unused pairs)}``.
    """
    check_rotation_pairs(R_est, R_gt)
    use = finite_rotation_pairs(R_est, R_gt)
    if valid is not None:
        v = torch.as_tensor(valid, device=R_est.device).bool()
        if v.shape != use.shape:
            raise ValueError(f"valid must be ({use.shape[0]},), got {tuple(v.shape)}")
        use = use & v
    if not bool(use.any()):
        raise ValueError("viewpoint_report: no valid pair of finite rotations")
    Re, Rg = R_est[use], R_gt[use]
    if alignment is None:
        G = align_rotations(Re, Rg, robust=robust)
    else:
        G = torch.as_tensor(alignment).to(Re)
        if G.shape != (3, 3) or not bool(torch.isfinite(G).all()):
            raise ValueError(f"alignment must be a finite (3, 3) rotation, got {tuple(G.shape)}")
    geo = geodesic_errors(Re, Rg, G)
    ang = angle_errors(Re, Rg, G)
    ang_abs = angle_errors(Re, Rg)
    Rm = necker_mirror(Re)
    Gm = align_rotations(Rm, Rg, robust=robust)
    geo_m = geodesic_errors(Rm, Rg, Gm)
    per = torch.full(use.shape, float("nan"), dtype=geo.dtype, device=geo.device)
    per[use] = geo
    report = {
        "n": int(use.sum()),
        "alignment": G.double().cpu().tolist(),
        "geodesic": summarize(geo),
        "azimuth": summarize(ang["azimuth"]),
        "elevation": summarize(ang["elevation"]),
        "roll": summarize(ang["roll"]),
        "up_axis": summarize(up_axis_errors(Re, Rg, axis=None if alignment is None else G[:, 2])),
        "absolute": {"geodesic": summarize(geodesic_errors(Re, Rg)),
                     **{k: summarize(ang_abs[k]) for k in ("azimuth", "elevation", "roll")},
                     "up_axis": summarize(up_axis_errors(Re, Rg, align=False))},
        "mirrored": bool(geo_m.median() < geo.median()),
        "mirrored_geodesic": summarize(geo_m),
        "per_instance_geodesic": per.double().cpu().tolist(),
    }
    return report


def _run_side(runs) -> tuple[dict, dict, int | None]:
    """One side of a comparison, one output folder or several (a run split across processes): every class of
    their ``summary.json`` files with the folder that holds it (the first one listed), and the torch threads of
    the first folder that says. A folder without ``summary.json`` (a run stopped before its first class) adds none.

    Returns:
        ``({class: summary entry}, {class: folder}, torch_threads or None)``.
    """
    folders = [Path(runs)] if isinstance(runs, (str, Path)) else [Path(r) for r in runs]
    entries, where, threads = {}, {}, None
    for f in folders:
        summary = read_json(f / "summary.json") if (f / "summary.json").is_file() else {}
        threads = threads if threads is not None else summary.get("torch_threads")
        for cls, entry in summary.get("classes", {}).items():
            if cls not in entries:
                entries[cls], where[cls] = entry, f
    return entries, where, threads


def _viewpoint_seconds(entry: dict) -> float:
    """A class's SfM (with the mixture's fit) and refinement seconds from its ``summary.json`` entry."""
    return round(sum(entry.get("seconds", {}).get(k, 0.0) for k in ("sfm", "refine")), 2)


def _class_agreement(cams: tuple[dict, dict], entries: tuple[dict, dict], labels: tuple[str, str]) -> dict | str:
    """One class of two runs: its agreement row, or why there is none.

    ``cams``: each run's ``cameras.json`` ``cameras`` (annotation id -> camera); ``entries``: each run's
    ``summary.json`` entry of the class.
    """
    a, b = cams
    both = [k for k, c in a.items() if c.get("refined") and (b.get(k) or {}).get("refined")]
    if not both:
        return "no object with a refined camera in both runs"
    R = [torch.tensor([side[k]["refined"]["R"] for k in both], dtype=torch.float64) for side in (a, b)]
    ang = torch.rad2deg(geodesic_angle(R[0], R[1]))
    return {"objects": entries[0].get("objects", len(a)), "compared": len(both),
            "median_deg": round(float(torch.quantile(ang, 0.5)), 3), "max_deg": round(float(ang.max()), 3),
            "turned": {k: round(float(x), 2) for x, k in sorted(zip(ang.tolist(), both), reverse=True)
                       if x > RUN_TURNED_DEG},
            "camera_choice_differs": sum(a[k].get("camera_choice") != b[k].get("camera_choice")
                                         for k in a.keys() & b.keys()),
            "missing": {labels[0]: len(b.keys() - a.keys()), labels[1]: len(a.keys() - b.keys())},
            "sfm_start": [e.get("sfm", {}).get("start", {}).get("kept") for e in entries],
            "shape_groups": [e.get("sfm_groups", {}).get("groups", 1) for e in entries],
            "viewpoint_seconds": {lab: _viewpoint_seconds(e) for lab, e in zip(labels, entries)}}


def compare_camera_runs(run_a, run_b, labels: tuple[str, str] = ("cpu", "cuda"),
                        tolerance_deg: float = RUN_AGREEMENT_DEG) -> dict:
    """Two runs' cameras of the same data (``reconstruct`` output folders), object by object.

    For every class in either run's ``summary.json``: the angle between the two refined rotations of each
    object that has one in both (:func:`carvi_torch.cameras.geodesic_angle`), its median and maximum, how many
    objects' ``camera_choice`` differs, the objects whose cameras are over :data:`RUN_TURNED_DEG` apart, which
    SfM start each run kept and how many shapes its mixture kept, and each run's SfM + refinement seconds. A
    class that one run has not finished (a run stopped at a time limit) lands in ``not_compared`` with the
    reason; it is not an error.

    Args:
        run_a, run_b: each an output folder (``summary.json``, ``<class>/cameras.json``), or a list of folders
            whose classes together make the run (one run split across processes).
        labels: the runs' names in the record (e.g. their devices).
        tolerance_deg: the largest median angle per class for the runs to agree.

    Returns:
        ``{"labels", "classes": {class: {"objects", "compared", "median_deg", "max_deg", "turned" (annotation id
        -> angle, largest first), "camera_choice_differs", "sfm_start": [a, b], "shape_groups": [a, b],
        "viewpoint_seconds": {label: s}}},
        "not_compared": {class: reason}, "viewpoint_seconds": {label: s} (the compared classes' sums),
        "torch_threads": {label: n}, "largest_median_deg" (``None`` without a compared class),
        "tolerance_deg", "agree"}`` (``agree``: a class was compared and every median is within tolerance).

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as d:
        ...     compare_camera_runs(Path(d), [Path(d), Path(d)])["not_compared"]
        {}
    """
    if len(labels) != 2 or labels[0] == labels[1]:
        raise ValueError(f"compare_camera_runs: labels must be two different names, got {list(labels)}")
    sides = [_run_side(run_a), _run_side(run_b)]
    rows, skipped = {}, {}
    for cls in sorted(set(sides[0][0]) | set(sides[1][0])):
        missing = [lab for lab, side in zip(labels, sides) if cls not in side[0]]
        files = [side[1][cls] / cls / "cameras.json" for side in sides] if not missing else []
        no_file = [lab for lab, f in zip(labels, files) if not f.is_file()]
        if missing or no_file:
            skipped[cls] = (f"not reached by the {missing[0]} run" if missing
                            else f"no cameras.json in the {no_file[0]} run")
            continue
        row = _class_agreement(tuple(read_json(f).get("cameras", {}) for f in files),
                               (sides[0][0][cls], sides[1][0][cls]), labels)
        if isinstance(row, str):
            skipped[cls] = row
        else:
            rows[cls] = row
    worst = max((r["median_deg"] for r in rows.values()), default=None)
    return {"labels": list(labels), "classes": rows, "not_compared": skipped,
            "viewpoint_seconds": {lab: round(sum(r["viewpoint_seconds"][lab] for r in rows.values()), 2)
                                  for lab in labels},
            "torch_threads": {lab: side[2] for lab, side in zip(labels, sides)},
            "largest_median_deg": worst, "tolerance_deg": tolerance_deg,
            "agree": worst is not None and worst <= tolerance_deg}
