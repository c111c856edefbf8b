"""The viewpoint stage: a camera for every instance of a class and the class's mean shape.

Modules, in the order data flows through them:

* :mod:`~carvi_torch.viewpoints.camera_fit`: fitting scaled orthographic cameras to a fixed
  shape (keypoints and silhouettes; Levenberg-Marquardt on scaled rotations), the shared maths;
* :mod:`~carvi_torch.viewpoints.sfm`: rigid structure from motion with missing data;
* :mod:`~carvi_torch.viewpoints.factorization`: SfM's missing-data factorisation (the alternation of filling
  and power steps, its compiled kernel on the CPU);
* :mod:`~carvi_torch.viewpoints.bundle`: SfM's joint bundle adjustment of all cameras and the shape
  (``sfm_polish=joint``);
* :mod:`~carvi_torch.viewpoints.mixture`: optionally several rigid shapes per class;
* :mod:`~carvi_torch.viewpoints.refine`: silhouette refinement per shape group, and cameras for
  the instances SfM could not place (the unseen-image path).
* :mod:`~carvi_torch.viewpoints.choice`: each object's SfM or refined camera, judged without ground
  truth (``refine_keep``);
* :mod:`~carvi_torch.viewpoints.frame`: the class's canonical frame (a template of 3-D keypoints,
  ``templates.json``, or the automatic frame), in which the cameras and the mean shape are written.

:func:`estimate_viewpoints` runs them in order on a class and its mirrored copies and returns
a :class:`Viewpoints`. Cameras are in canvas pixels (``carvi_torch.cameras`` conventions).

Example:
    >>> from carvi_torch.synthetic import procedural
    >>> from carvi_torch.io.coco import load_coco
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> _ = procedural.write_default_collection(d, instances_per_class=8, categories=["car"], seed=0, progress=False)
    >>> coll = load_coco(d / "annotations.json").collections["car"]
    >>> from carvi_torch.config import ViewpointConfig
    >>> vp = estimate_viewpoints(coll, ViewpointConfig())
    >>> len(vp.cameras) == 2 * len(coll), tuple(vp.shape.shape[1:])
    (True, (3,))
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np
import torch

from ..cameras import FLIP_X, ScaledOrthographic, align_rotations
from ..io.outputs import shown_names
from ..collection import ClassCollection
from ..runtime import StageTimer, fields_to_device
from ..sdf import distance_to_mask
from . import camera_fit, mixture, sfm
from .choice import kept_rows, tilted
from .frame import CanonicalFrame, FrameFit, canonical_frame, load_templates, template_points
from .refine import (choose_per_group, group_sfm_cameras, keypoints_left_out, refine_groups, unseen_keypoints,
                     unseen_per_group)

if TYPE_CHECKING:
    from ..config import ViewpointConfig

__all__ = ["Viewpoints", "CameraSource", "estimate_viewpoints", "class_sfm", "started_sfm", "TEMPLATE_START_MARGIN",
           "GT_REFLECTION", "ground_truth_cameras", "true_canvas_cameras",
           "NoMeanShape", "symmetry_plane_or_none", "NO_MIRRORS"]

#: Where a run's cameras come from: ``estimate`` (SfM and refinement) or ``gt`` (the true cameras, a study).
CameraSource = Literal["estimate", "gt"]

#: Reflection of the ground-truth object frames (PASCAL3D+ and procedural: left/right along x).
GT_REFLECTION = FLIP_X


@dataclass
class Viewpoints:
    """Cameras of a class's originals and mirrored copies (``2N`` rows, canvas pixels) and its mean shape.

    Attributes:
        both: the class with its mirrored copies (row ``i + N`` mirrors row ``i``).
        sfm_cameras: ``ScaledOrthographic (2N)``: the SfM cameras in the class frame.
        sfm_valid: ``(2N,)`` bool: rows with an SfM camera.
        cameras: ``ScaledOrthographic (2N)``: the final cameras (refined, unseen-image or ground truth).
        has_camera: ``(2N,)`` bool: rows whose final camera is usable (finite, positive scale).
        shape: ``(K, 3)`` mean shape (with shape groups: the largest group's) in the class frame.
        reflection: ``(3, 3)`` reflection through the shape's left-right symmetry plane (``None`` when no
            flip pair defines one).
        groups: the shape groups (:class:`~carvi_torch.viewpoints.mixture.MixtureResult`).
        unseen_keypoints: ``(2N,)`` long: for rows of the unseen-image path, their visible keypoints
            with a mean-shape row (0: the silhouette alone); -1 elsewhere.
        source: :data:`CameraSource`.
        frame: the canonical object frame the outputs are written in (:mod:`~carvi_torch.viewpoints.frame`;
            the cameras and shapes here stay in the SfM frame).
        mirrored: whether rows ``N..2N-1`` are the originals' mirrored copies with their keypoints; False
            for a class without flip pairs (no way to relabel a flipped image's keypoints): those rows hold
            no keypoints and get no camera, and nothing uses them.
        no_camera: ``{row: reason}`` for the rows without a usable camera (after :func:`estimate_viewpoints`).
        kept_sfm: ``(2N,)`` bool: rows whose SfM camera was kept over its refined one
            (``refine_keep`` ``class`` or ``objects``, :mod:`~carvi_torch.viewpoints.choice`); else ``None``.
        distances: ``(2N, H, W)`` exact distances to the masks (:func:`carvi_torch.sdf.distance_to_mask`),
            kept for the carving's signed distances; :meth:`take_distances` hands them over once.
        info: entries for the class's summary (``sfm``, ``sfm_groups``, ``refine``,
            ``cameras_from_mean_shape``, ``cameras_from_silhouette_only``), in that order.
        warnings: messages for the class's summary.
        log: lines for the terminal.
    """

    both: ClassCollection
    sfm_cameras: ScaledOrthographic
    sfm_valid: torch.Tensor
    cameras: ScaledOrthographic
    has_camera: torch.Tensor
    shape: torch.Tensor
    reflection: torch.Tensor | None
    groups: mixture.MixtureResult
    unseen_keypoints: torch.Tensor
    source: str = "estimate"
    mirrored: bool = True
    distances: torch.Tensor | None = None
    frame: CanonicalFrame | None = None
    no_camera: dict = field(default_factory=dict)
    kept_sfm: torch.Tensor | None = None
    info: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)
    log: list = field(default_factory=list)

    def to(self, device) -> "Viewpoints":
        """These viewpoints with their tensors on ``device``, but the canonical frame: it is made from host
        copies and read on the host (``cameras.json``) in every run, so it stays there."""
        return fields_to_device(self, device, keep=("frame",))

    def take_distances(self) -> torch.Tensor:
        """The distance maps, released from this object (the carving needs them once)."""
        dist, self.distances = self.distances, None
        if dist is None:
            raise RuntimeError("the distance maps were already taken")
        return dist


def class_sfm(both: ClassCollection, cfg: ViewpointConfig, init_shape: torch.Tensor | None = None,
              **options) -> sfm.SfMResult:
    """Rigid SfM of a collection with the configured limits and the category's rigid keypoints, names,
    flip pairs and left/right convention (``init_shape``: a start, :func:`~carvi_torch.viewpoints.sfm.rigid_sfm`;
    ``options``: :class:`~carvi_torch.viewpoints.sfm.SfMOptions` fields that replace the configured ones)."""
    m = both.meta
    opts = sfm.SfMOptions(max_outer=cfg.sfm_max_outer, inner=cfg.sfm_inner, tol=cfg.sfm_tol,
                          polish_iters=cfg.sfm_polish_iters, polish=cfg.sfm_polish, native=cfg.sfm_native)
    opts = dataclasses.replace(opts, **options)
    return sfm.rigid_sfm(both.keypoints, both.visible, opts, rigid_keypoints=m.rigid_keypoints,
                         keypoint_names=m.keypoint_names, flip_pairs=m.flip_pairs, left_convention=m.left_convention,
                         init_shape=init_shape)


#: The template start's SfM solution replaces the cold start's when its visible-keypoint RMS residual
#: is lower by more than this fraction (``sfm_template_start``). On the CAD renders at 8 views per model
#: the trains' rescues cut it by 52% and 75%; the 10-20% cuts of boat and sofa changed their cameras
#: both ways (sofa 10.9 -> 9.4 and 11.7 -> 14.9 degrees), so only a clear cut counts.
TEMPLATE_START_MARGIN = 0.25


def _template_start(both: ClassCollection) -> torch.Tensor | None:
    """``(K, 3)`` start shape of the class's SfM from its template of 3-D keypoints (NaN rows: not in the
    template), scaled to the canvas width; ``None`` without a template (:func:`~carvi_torch.viewpoints.frame.
    template_points`)."""
    m = both.meta
    found = template_points(m.name, m.keypoint_names, load_templates(), own=m.keypoints_3d)
    if found is None:
        return None
    T, _source = found
    return (T * float(both.masks.shape[-1])).to(both.keypoints.dtype)


def _rms(res: sfm.SfMResult) -> float:
    """Visible-keypoint RMS residual (pixels) of an SfM solution over its placed instances."""
    r = res.residual[res.valid]
    return float((r * r).mean().sqrt()) if r.numel() else math.inf


def started_sfm(both: ClassCollection, cfg: ViewpointConfig) -> tuple[sfm.SfMResult, dict | None]:
    """:func:`class_sfm` from a cold start and (``sfm_template_start``, a class with a template that is not
    rotationally symmetric) from its template; the template start's solution is kept when it places as many
    instances with an RMS residual lower by more than :data:`TEMPLATE_START_MARGIN`. Returns the solution
    and, when there were two starts, ``{"kept": "cold" | "template", "rms_cold_px", "rms_template_px"}``
    (the summary's ``sfm.start``).

    A class whose models disagree on what some keypoints mean (the CAD trains) can lead the cold
    factorisation into a poor local solution; the template's rough proportions start it near a good one.
    A rotationally symmetric class (bottles) is left out: its keypoints depend on the view (the sides of
    the silhouette), a rigid fit with a lower residual says nothing of the cameras (CAD bottles: median
    error 29 -> 49 degrees from the template start).
    """
    res = class_sfm(both, cfg)
    T = _template_start(both) if cfg.sfm_template_start and both.meta.symmetry != "rotational" else None
    if T is None:
        return res, None
    alt = class_sfm(both, cfg, T)
    cold, warm = _rms(res), _rms(alt)
    keep = int(alt.valid.sum()) >= int(res.valid.sum()) and warm < (1.0 - TEMPLATE_START_MARGIN) * cold
    return (alt if keep else res), {"kept": "template" if keep else "cold", "rms_cold_px": round(cold, 3),
                                    "rms_template_px": round(warm, 3)}


def _sfm_notes(coll: ClassCollection, res: sfm.SfMResult, vp_info: dict, warnings: list) -> None:
    """The SfM's problems and the originals it could not place, for the summary."""
    n = len(coll)
    for msg in res.problems:
        warnings.append(f"sfm: {msg}")
    vp_info["sfm"] = res.summary()
    for i in (~res.valid[:n]).nonzero().squeeze(1).tolist():
        why = res.reasons[i] if i < len(res.reasons) and res.reasons[i] else "fewer than 2 visible keypoints"
        warnings.append(f"annotation {coll.annotation_ids[i]} ({coll.sources[i]}): no SfM camera: {why}")


class NoMeanShape(ValueError):
    """SfM placed no instance of a class (e.g. its category has a single keypoint): the class has no mean
    shape and cannot be reconstructed (a reason for the whole class, not an error of the program)."""


def _check_placed(coll: ClassCollection, res: sfm.SfMResult) -> None:
    """Raise :class:`NoMeanShape` when SfM placed no instance (naming the first instance's reason)."""
    if bool(res.valid.any()):
        return
    why = next((r for r in res.reasons if r), "no reason given")
    raise NoMeanShape(f"SfM placed no object, so the class has no mean shape (annotation {coll.annotation_ids[0]}: "
                      f"{why})")


def _shape_groups(both, dist, res, cfg: ViewpointConfig, source: str, seed: int, info: dict, log: list):
    """One rigid shape (``sfm_groups=1``) or the mixture of :mod:`carvi_torch.viewpoints.mixture`."""
    if cfg.sfm_groups == 1 or source != "estimate":
        return mixture.fit_mixture_of_shapes(both, dist, None, max_groups=1, single=res)
    lines = []
    mix = mixture.fit_mixture_of_shapes(
        both, dist, lambda sub, init_shape=None: class_sfm(sub, cfg, init_shape,
                                                           **(mixture.COLD_GROUP_SFM if init_shape is None else {})),
        max_groups=cfg.sfm_groups,
        min_size=cfg.sfm_group_min, gain=cfg.sfm_group_gain, agreement_deg=cfg.sfm_group_agreement_deg,
        rounds=cfg.sfm_group_rounds, seed=seed, single=res, log=lines.append, threads=cfg.sfm_group_threads,
        min_misfit=cfg.sfm_group_misfit, hull_gain=None if cfg.sfm_group_hull_gain <= -1 else cfg.sfm_group_hull_gain,
        native=cfg.sfm_native)
    log.extend(f"  {both.name}: {line}" for line in lines)
    info["sfm_groups"] = mix.summary()
    return mix


def true_canvas_cameras(coll: ClassCollection, both: ClassCollection, gt_img: ScaledOrthographic) -> ScaledOrthographic:
    """The true cameras ``gt_img`` (``N``, image pixels; :func:`ground_truth_cameras`) in canvas pixels, the
    mirrored copies' after them (``2N``, the rows of ``both``: the class with its mirrored copies)."""
    n = len(coll)
    w = coll.image_size[:, 0].to(gt_img.t.dtype)
    mirrored = gt_img.mirror(w, GT_REFLECTION.to(gt_img.R))
    return ScaledOrthographic.cat([gt_img.compose_similarity(coll.canvas_from_image),
                                   mirrored.compose_similarity(both.canvas_from_image[n:])])


def _ground_truth(coll: ClassCollection, both: ClassCollection, gt_img: ScaledOrthographic, vp: Viewpoints) -> None:
    """Replace the cameras by the true ones (in canvas pixels, mirrors included) and express the mean
    shape in the ground-truth frame, so that clusters and selection use that frame (a study)."""
    vp.cameras = true_canvas_cameras(coll, both, gt_img)
    known = torch.isfinite(gt_img.s).to(both.keypoints.device)  # instances without a true camera get none
    vp.has_camera = torch.cat([known, known])
    ok = vp.groups.single.valid & vp.has_camera
    if not bool(ok.any()):
        return
    G = align_rotations(vp.sfm_cameras.R[ok], vp.cameras.R[ok])  # R_sfm G ~ R_gt
    ratio = (vp.cameras.s[ok] / vp.sfm_cameras.s[ok]).median()
    vp.shape = (vp.shape @ G) / ratio
    vp.reflection = GT_REFLECTION.to(vp.shape)


def _refine_step(vp: Viewpoints, dist: torch.Tensor, cfg: ViewpointConfig) -> None:
    """Silhouette refinement of every shape group's cameras (the summary's ``refine`` entry)."""
    cams, energy = refine_groups(vp.groups, vp.sfm_cameras, vp.both, dist, cfg)
    vp.cameras = cams
    ok = vp.sfm_valid
    vp.info["refine"] = {"median_energy_before": float(energy[0][ok].median()) if ok.any() else None,
                         "median_energy_after": float(energy[1][ok].median()) if ok.any() else None}
    if cfg.refine_keep != "refined":
        _keep_better(vp, cfg)
    left_out = keypoints_left_out(vp.groups, vp.both, cfg)
    if left_out:
        vp.info["refine"]["keypoints_left_out"] = left_out
        vp.log.append(f"  {vp.both.name}: refinement leaves out keypoints shown by fewer than "
                      f"{cfg.refine_min_support:.0%} of the instances: "
                      + "; ".join(f"group {g}: {', '.join(v)}" for g, v in left_out.items()))


def _keep_better(vp: Viewpoints, cfg: ViewpointConfig) -> None:
    """Keep the SfM cameras where the refined ones are suspect, per object or for the whole class
    (``refine_keep``), and where a refined camera is tilted (``refine_max_tilt_deg``;
    :mod:`~carvi_torch.viewpoints.choice`); the summary's ``refine.kept_sfm`` counts the suspect and tilted
    rows and the originals that keep their SfM camera, with their annotation ids."""
    choice = choose_per_group(vp.groups, vp.sfm_cameras, vp.cameras, vp.both, cfg)
    suspect = choice.suspect.to(vp.sfm_valid.device) & vp.sfm_valid
    tilt = tilted(vp.sfm_cameras.R, vp.cameras.R, vp.sfm_valid, cfg.refine_max_tilt_deg).to(suspect.device)
    keep = kept_rows(suspect, vp.sfm_valid, cfg.refine_keep, tilt)
    sfm, ref = vp.sfm_cameras, vp.cameras
    vp.cameras = ScaledOrthographic(torch.where(keep[:, None, None], sfm.R, ref.R), torch.where(keep, sfm.s, ref.s),
                                    torch.where(keep[:, None], sfm.t, ref.t))
    vp.kept_sfm = keep
    n = len(vp.both) // 2
    ids = [vp.both.annotation_ids[i] for i in keep[:n].nonzero().squeeze(1).tolist()]
    tilted_ids = [vp.both.annotation_ids[i] for i in tilt[:n].nonzero().squeeze(1).tolist()]
    vp.info["refine"]["kept_sfm"] = {"how": cfg.refine_keep, "suspect": int(suspect.sum()),
                                     "tilted": int(tilt.sum()), "tilted_ids": tilted_ids,
                                     "with_sfm": int(vp.sfm_valid.sum()), "originals": len(ids),
                                     "mirrored_copies": int(keep[n:].sum()), "ids": ids}


def _unseen_step(coll: ClassCollection, vp: Viewpoints, missing: torch.Tensor, dist: torch.Tensor,
                 cfg: ViewpointConfig) -> None:
    """Cameras for the rows ``missing (2N,)`` without one (fewer than 2 visible keypoints): the
    unseen-image path."""
    n = len(coll)
    vp.cameras = unseen_per_group(vp.groups, vp.cameras, missing, vp.both, dist, cfg)
    idx = missing.nonzero().squeeze(1)
    vp.info["cameras_from_mean_shape"] = [coll.annotation_ids[i] for i in idx.tolist() if i < n]
    vp.unseen_keypoints = unseen_keypoints(vp.groups, missing, vp.both, cfg)
    blind = [coll.annotation_ids[i] for i in (vp.unseen_keypoints[:n] == 0).nonzero().squeeze(1).tolist()]
    if blind:
        vp.info["cameras_from_silhouette_only"] = blind
        vp.warnings.append(
            f"{len(blind)} annotation(s) without an SfM camera got one from the silhouette alone (none of "
            f"their visible keypoints has a row in the mean shape): unreliable, a silhouette often fits "
            f"several viewpoints (cameras.json: camera_from 'silhouette'); ids {shown_names(blind, 20)}")
    vp.has_camera = vp.has_camera | missing


def ground_truth_cameras(gt, coll: ClassCollection) -> tuple[ScaledOrthographic | None, list]:
    """Image-pixel ground-truth cameras of the collection's instances from ``gt.json``'s content.

    Returns:
        ``ScaledOrthographic (N)`` with NaN rows for the instances without a usable entry (``None``
        when no instance has one), and per instance why it has none (``None``: it has one).

    Example:
        >>> from types import SimpleNamespace
        >>> entry = {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "s": 2.0, "t": [0, 0]}
        >>> coll = SimpleNamespace(annotation_ids=[1, 2], device="cpu")
        >>> cams, why = ground_truth_cameras({"annotations": {"1": entry, "2": {"R": "junk"}}}, coll)
        >>> cams.s.tolist()[0], why
        (2.0, [None, 'gt.json camera: R must be 3x3 numbers, s a number, t 2 numbers'])
    """
    entries = gt.get("annotations", gt) if isinstance(gt, dict) else gt
    if not isinstance(entries, dict):
        why = "gt.json holds no object of annotation ids" if gt is not None else "no gt.json"
        return None, [why] * len(coll.annotation_ids)
    parsed = [_gt_camera(entries.get(str(aid))) for aid in coll.annotation_ids]
    why = [p if isinstance(p, str) else None for p in parsed]
    if all(isinstance(p, str) for p in parsed):
        return None, why
    nan = (np.full((3, 3), np.nan), np.nan, np.full(2, np.nan))
    cams = [nan if isinstance(p, str) else p for p in parsed]
    R, s, t = (torch.tensor(np.stack([c[j] for c in cams]), dtype=torch.float32, device=coll.device) for j in range(3))
    return ScaledOrthographic(R, s, t), why


def _gt_camera(entry) -> tuple[np.ndarray, float, np.ndarray] | str:
    """``(R (3, 3), s, t (2,))`` of one ``gt.json`` entry, or why it has no usable camera."""
    if entry is None:
        return "no camera in gt.json"
    try:
        R = np.asarray(entry["R"], dtype=np.float64)
        s = float(entry["s"])
        t = np.asarray(entry["t"], dtype=np.float64)
    except (KeyError, TypeError, ValueError, IndexError):
        R = s = t = None
    if R is None or R.shape != (3, 3) or t.shape != (2,):
        return "gt.json camera: R must be 3x3 numbers, s a number, t 2 numbers"
    if not (np.isfinite(R).all() and np.isfinite(t).all() and math.isfinite(s) and s > 0):
        return "gt.json camera: R, s and t must be finite, s positive"
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) <= 0:
        return "gt.json camera: R is not a rotation"
    return R, s, t


def estimate_viewpoints(coll: ClassCollection, cfg: ViewpointConfig, *, source: str = "estimate",
                        gt_cameras: ScaledOrthographic | None = None, seed: int = 0,
                        timer: StageTimer | None = None) -> Viewpoints:
    """Cameras of a class (originals and mirrored copies) and its mean shape and symmetry plane.

    SfM, the optional mixture of shapes, then (``source="estimate"``) silhouette refinement or
    (``"gt"``) the true cameras, and the unseen-image path for rows without a camera.

    Args:
        coll: the class (``N`` instances) on its device.
        cfg: the viewpoint settings (:class:`carvi_torch.config.ViewpointConfig`).
        source: :data:`CameraSource`.
        gt_cameras: ``ScaledOrthographic (N)`` true cameras in image pixels (``source="gt"``).
        seed: seed of the mixture's k-means starts.
        timer: books ``sfm``, ``sdf`` and ``refine`` seconds.

    Returns:
        :class:`Viewpoints` with ``2N`` rows.

    Raises:
        NoMeanShape: SfM placed no instance (the class cannot be reconstructed).
    """
    if source == "gt" and gt_cameras is None:
        raise ValueError("source='gt' needs the true cameras of every annotation (gt_cameras)")
    timer = timer if timer is not None else StageTimer(coll.device)
    both, mirrored = _mirrored_rows(coll)
    info, warnings, log = {}, [] if mirrored else [NO_MIRRORS], []
    with timer("sfm"):
        res, start = started_sfm(both, cfg)
    _sfm_notes(coll, res, info, warnings)
    if start is not None:
        info["sfm"]["start"] = start
    _check_placed(coll, res)
    with timer("sdf"):
        dist = distance_to_mask(both.masks)
    with timer("sfm"):
        mix = _shape_groups(both, dist, res, cfg, source, seed, info, log)
    cams_sfm, sfm_valid = group_sfm_cameras(mix)
    shape = mix.shape(mix.largest())
    vp = Viewpoints(both, cams_sfm, sfm_valid, cams_sfm, sfm_valid.clone(), shape,
                    symmetry_plane_or_none(shape, coll.meta.flip_pairs), mix, None, source=source, mirrored=mirrored,
                    distances=dist, info=info, warnings=warnings, log=log)
    if source == "gt":
        _ground_truth(coll, both, gt_cameras, vp)
    elif cfg.refine:
        with timer("refine"):
            _refine_step(vp, dist, cfg)
    missing = ~vp.has_camera if mirrored else ~vp.has_camera & ~both.is_mirror
    if source != "gt" and bool(missing.any()):
        with timer("refine"):
            _unseen_step(coll, vp, missing, dist, cfg)
    else:
        vp.unseen_keypoints = torch.full((len(both),), -1, dtype=torch.long, device=vp.has_camera.device)
    finite = torch.isfinite(vp.cameras.R).flatten(1).all(1) & torch.isfinite(vp.cameras.s) & (vp.cameras.s > 0)
    vp.has_camera = vp.has_camera & finite
    vp.no_camera = _no_camera_reasons(vp)
    vp.cameras = _with_placeholders(vp.cameras, vp.has_camera)
    vp.frame = _frame(coll, vp, cfg)
    vp.info["frame"] = vp.frame.info
    if "fallback" in vp.frame.info and cfg.frame in ("best", "template"):
        vp.warnings.append(f"frame: {vp.frame.kind} ({vp.frame.info['fallback']})")
    return vp


#: The class warning of a class without left/right keypoint pairs.
NO_MIRRORS = ("no left/right keypoint pairs (flip_pairs): no mirrored copies and no symmetry plane; each object "
              "is carved from its own and its surrogates' silhouettes")


def _mirrored_rows(coll: ClassCollection) -> tuple[ClassCollection, bool]:
    """The class with its mirrored copies (``2N`` rows), and whether the copies carry keypoints: a class
    without flip pairs cannot relabel a flipped image's keypoints (a left one would keep its name on the
    right), so its copies' keypoints are hidden and the copies take no part (:attr:`Viewpoints.mirrored`)."""
    both = coll.with_mirrors()
    if coll.meta.flip_pairs:
        return both, True
    return both.replace(visible=both.visible & ~both.is_mirror[:, None]), False


def symmetry_plane_or_none(shape: torch.Tensor, flip_pairs) -> torch.Tensor | None:
    """:func:`~carvi_torch.viewpoints.sfm.symmetry_plane` of ``shape (K, 3)``, or ``None`` when no flip
    pair has two distinct finite points (a class without left/right keypoints)."""
    if not flip_pairs:
        return None
    try:
        return sfm.symmetry_plane(shape, flip_pairs)
    except ValueError:
        return None


def _no_camera_reasons(vp: Viewpoints) -> dict[int, str]:
    """``{row: reason}`` for the rows without a usable camera."""
    missing = (~vp.has_camera).nonzero().squeeze(1).tolist()
    if not missing:
        return {}
    collapsed = camera_fit.collapsed_keypoints(vp.both.keypoints, vp.both.visible).tolist()
    return {i: camera_fit.COLLAPSED_REASON if collapsed[i] else "no usable camera" for i in missing}


def _with_placeholders(cams: ScaledOrthographic, has_camera: torch.Tensor) -> ScaledOrthographic:
    """``cams`` with the rows without a usable camera (``has_camera (2N,)`` False) set to a finite
    placeholder (identity rotation, unit scale, no shift), so that the batched later stages never meet
    a NaN camera; ``has_camera`` keeps them out of every result."""
    if bool(has_camera.all()):
        return cams
    keep = has_camera.to(cams.R.device)
    eye = torch.eye(3, dtype=cams.R.dtype, device=cams.R.device)
    return ScaledOrthographic(torch.where(keep[:, None, None], cams.R, eye), torch.where(keep, cams.s, 1.0),
                              torch.where(keep[:, None], cams.t, 0.0))


def _frame(coll: ClassCollection, vp: Viewpoints, cfg: ViewpointConfig) -> CanonicalFrame:
    """The class's canonical frame (ground-truth cameras are in theirs already)."""
    if vp.source == "gt":
        return CanonicalFrame("ground_truth", [FrameFit(torch.eye(3, dtype=torch.float64))], {"kind": "ground_truth"})
    n = len(coll)
    mix = vp.groups
    reflection = symmetry_plane_or_none(vp.shape, coll.meta.flip_pairs)
    seen = vp.has_camera[:n]
    return canonical_frame(cfg.frame, coll.meta.name, coll.meta.keypoint_names,
                           [mix.shape(g).cpu() for g in range(mix.k)], vp.shape.cpu(),
                           None if reflection is None else reflection.cpu(), vp.cameras.R[:n][seen].cpu(),
                           own_template=coll.meta.keypoints_3d)

