"""The stages in order, per class: load -> mirror -> SfM -> refine -> surrogates -> carve -> select -> mesh.

Data flows one way through the stage modules::

    io.coco          annotations  -> ClassCollection (canvas tensors)
    collection       mirrored copies
    sfm              mean shape S + cameras            (keypoints only)
    refine           cameras refined by silhouettes    (+ unseen-image cameras)
    surrogates       principal directions, clusters, triplets
    carve            imprinted visual hull of every proposal
    select           average masks, proposal scores, best proposal
    mesh             marching cubes, files

:func:`run` drives a whole run (every class), :func:`run_class` one class. Both only
orchestrate: the numerical work lives in the stage modules. Outputs are written
atomically and a rerun skips objects whose mesh and voxels already exist.
"""
from __future__ import annotations

import math
import os
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import yaml
from tqdm.auto import tqdm

from . import carve, mesh, refine, select, sfm, sfm_mixture, surrogates
from .cameras import ScaledOrthographic, azimuth_elevation_roll_from_rotation
from .collection import ClassCollection
from .config import Config
from .io import coco
from .io.outputs import is_done, read_json, write_json, write_npz
from .sdf import distance_to_mask, signed_distance

__all__ = ["run", "run_class", "prepare_class", "proposals_of", "ClassReport", "prepare_data", "writer_workers",
           "torch_threads"]

#: Reflection of the ground-truth object frames (PASCAL3D+ and procedural: left/right along x).
GT_REFLECTION = torch.diag(torch.tensor([-1.0, 1.0, 1.0]))


@dataclass
class ClassReport:
    """What happened to one class (becomes its entry in ``summary.json``)."""

    name: str
    objects: int = 0
    reconstructed: int = 0
    resumed: int = 0
    skipped: list = field(default_factory=list)  # dicts: annotation_id, source, stage, reason
    warnings: list = field(default_factory=list)
    seconds: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)
    status: str = "ok"

    def skip(self, reason: str, stage: str, annotation_id=None, source=None):
        self.skipped.append({"annotation_id": annotation_id, "source": source, "stage": stage, "reason": reason})

    def failures(self) -> list:
        """The skipped objects, class-level entries first, then by annotation id (the order in which
        writer processes finish must not change the report)."""
        return sorted(self.skipped, key=lambda f: (f["annotation_id"] is not None,
                                                   f["annotation_id"] if isinstance(f["annotation_id"], int) else 0))

    def to_dict(self) -> dict:
        return {"objects": self.objects, "reconstructed": self.reconstructed, "resumed": self.resumed,
                "skipped": len(self.skipped), "status": self.status, "failures": self.failures(),
                "warnings": self.warnings, "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
                **self.info}


@contextmanager
def _timed(report: ClassReport, stage: str, device: torch.device):
    t0 = time.perf_counter()
    yield
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    report.seconds[stage] = report.seconds.get(stage, 0.0) + time.perf_counter() - t0


def _log(msg: str, cfg: Config):
    tqdm.write(msg) if cfg.progress else print(msg)


# =========================================================================== data


def prepare_data(cfg: Config) -> tuple[Path, Path | None]:
    """The annotation file (and ``gt.json`` if any) to run on; generates the embedded default when needed."""
    if cfg.data:
        data = Path(cfg.data)
        gt = Path(cfg.gt) if cfg.gt else data.with_name("gt.json")
        return data, (gt if gt.is_file() else None)
    from .synthetic import procedural

    target = Path(cfg.out) / "input"
    ann = target / "annotations.json"
    if not is_done(ann, target / "gt.json"):
        _log(f"generating the embedded procedural collection ({cfg.procedural_instances} instances per class) "
             f"in {target}", cfg)
        procedural.write_default_collection(target, instances_per_class=cfg.procedural_instances, seed=cfg.seed,
                                            progress=cfg.progress)
    return ann, target / "gt.json"


def _gt_cameras(gt: dict | None, coll: ClassCollection) -> ScaledOrthographic | None:
    """Image-pixel ground-truth cameras of the collection's instances (None if any is missing)."""
    if gt is None:
        return None
    entries = gt.get("annotations", gt)
    items = []
    for aid in coll.annotation_ids.tolist():
        e = entries.get(str(aid))
        if e is None or "R" not in e:
            return None
        items.append(e)
    return ScaledOrthographic.from_list(items, device=coll.device)


# =========================================================================== viewpoints


def class_sfm(both: ClassCollection, cfg: Config, init_shape: torch.Tensor | None = None) -> sfm.SfMResult:
    """Rigid SfM of a collection (originals and mirrored copies) with the config's settings and
    the category's rigid keypoints, keypoint names, flip pairs and left/right convention
    (``init_shape``: a start for the factorisation, see :func:`carvi_torch.sfm.rigid_sfm`)."""
    m = both.meta
    return sfm.rigid_sfm(both.keypoints, both.visible, max_outer=cfg.sfm_max_outer, inner=cfg.sfm_inner,
                         tol=cfg.sfm_tol, rigid_keypoints=m.rigid_keypoints, keypoint_names=m.keypoint_names,
                         flip_pairs=m.flip_pairs, left_convention=m.left_convention,
                         init_shape=init_shape)


def class_refine(shape: torch.Tensor, cams: ScaledOrthographic, both: ClassCollection, dist: torch.Tensor,
                 cfg: Config) -> refine.RefineResult:
    """Silhouette refinement of every camera of ``both`` with the mean shape fixed, as configured
    (without the keypoints fewer than ``refine_min_support`` of ``both`` show)."""
    shape = refine.supported_shape(shape, both.visible, cfg.refine_min_support)
    return refine.refine_cameras(shape, cams, both.keypoints, both.visible, dist, silhouette_weight=cfg.silhouette_weight,
                                 max_iters=cfg.refine_iters, silhouette_robust=cfg.silhouette_robust or None,
                                 twin_flatness=cfg.refine_twin_flatness)


def _unseen_shape(shape: torch.Tensor, both: ClassCollection, cfg: Config) -> torch.Tensor:
    """The mean shape the unseen-image path fits to ``both``'s rows: without the keypoints fewer than
    ``refine_min_support`` of them show (:func:`carvi_torch.refine.supported_shape`, support over all of ``both``)."""
    return refine.supported_shape(shape, both.visible, cfg.refine_min_support)


def cameras_from_mean_shape(shape: torch.Tensor, cams: ScaledOrthographic, idx: torch.Tensor, both: ClassCollection,
                            dist: torch.Tensor, cfg: Config) -> ScaledOrthographic:
    """``cams`` with the cameras of rows ``idx`` replaced by the unseen-image estimate from ``shape``."""
    if idx.numel() == 0:
        return cams
    shape = _unseen_shape(shape, both, cfg)
    est, _energy = refine.estimate_camera(shape, both.keypoints[idx], both.visible[idx], dist[idx],
                                          silhouette_robust=cfg.silhouette_robust or None)
    R, s, t = cams.R.clone(), cams.s.clone(), cams.t.clone()
    R[idx], s[idx], t[idx] = est.R, est.s, est.t
    return ScaledOrthographic(R, s, t)


def _shape_groups(both: ClassCollection, dist: torch.Tensor, res: sfm.SfMResult, cfg: Config,
                  report: ClassReport) -> sfm_mixture.MixtureResult:
    """One rigid shape (``sfm_groups=1``) or the mixture of :mod:`carvi_torch.sfm_mixture`."""
    if cfg.sfm_groups == 1 or cfg.cameras != "estimate":
        return sfm_mixture.fit_mixture_of_shapes(both, dist, None, max_groups=1, single=res)
    log = []
    mix = sfm_mixture.fit_mixture_of_shapes(
        both, dist, lambda sub, init_shape=None: class_sfm(sub, cfg, init_shape), max_groups=cfg.sfm_groups, min_size=cfg.sfm_group_min,
        gain=cfg.sfm_group_gain, agreement_deg=cfg.sfm_group_agreement_deg, rounds=cfg.sfm_group_rounds,
        seed=cfg.seed, single=res, log=log.append, threads=cfg.sfm_group_threads)
    for line in log:
        _log(f"  {both.name}: {line}", cfg)
    report.info["sfm_groups"] = mix.summary()
    return mix


def _per_group(mix: sfm_mixture.MixtureResult, base: ScaledOrthographic, fn) -> ScaledOrthographic:
    """``base`` with the rows of every shape group replaced by ``fn(g, rows_g)``.

    ``rows_g`` are group ``g``'s rows of the ``2N`` collection, or ``None`` for one group (then
    ``fn(0, None)`` gets every row and returns all of them).
    """
    if mix.k == 1:
        return fn(0, None)
    R, s, t = base.R.clone(), base.s.clone(), base.t.clone()
    for g, (rows, _res) in enumerate(mix.groups):
        c = fn(g, rows)
        R[rows], s[rows], t[rows] = c.R, c.s, c.t
    return ScaledOrthographic(R, s, t)


def _rows(x, rows):
    """``x`` restricted to ``rows`` (``None``: all of it)."""
    return x if rows is None else x[rows]


def group_sfm_cameras(mix: sfm_mixture.MixtureResult) -> tuple[ScaledOrthographic, torch.Tensor]:
    """Every group's SfM cameras in the class frame, gathered into the ``2N`` rows; and ``valid (2N,)``."""
    single = mix.single
    if mix.k == 1:
        return single.cameras, single.valid.clone()
    valid = single.valid.clone()
    for rows, res in mix.groups:
        valid[rows] = res.valid
    return _per_group(mix, single.cameras, lambda g, _rows: mix.cameras(g)), valid


def refine_groups(mix: sfm_mixture.MixtureResult, cams_sfm: ScaledOrthographic, both: ClassCollection,
                  dist: torch.Tensor, cfg: Config) -> tuple[ScaledOrthographic, torch.Tensor]:
    """Silhouette refinement of every group with its own mean shape; returns the cameras and
    ``energy (2, 2N)`` (before, after)."""
    energy = torch.zeros((2, len(both)), dtype=cams_sfm.s.dtype, device=cams_sfm.s.device)

    def refine_group(g, rows):
        rr = class_refine(mix.shape(g), _rows(cams_sfm, rows), _rows(both, rows), _rows(dist, rows), cfg)
        at = slice(None) if rows is None else rows
        energy[0, at], energy[1, at] = rr.energy_before, rr.energy_after
        return rr.cameras

    return _per_group(mix, cams_sfm, refine_group), energy


def keypoints_left_out(mix: sfm_mixture.MixtureResult, both: ClassCollection, cfg: Config) -> dict[str, list[str]]:
    """Per shape group (``"0"``, ``"1"``...), the names of the keypoints its refinement leaves out
    (:func:`carvi_torch.refine.supported_shape` with ``refine_min_support``); groups that keep
    every keypoint are not listed."""
    out = {}
    for g in range(mix.k):
        rows = None if mix.k == 1 else mix.groups[g][0]
        S = mix.shape(g)
        kept = refine.supported_shape(S, _rows(both, rows).visible, cfg.refine_min_support)
        dropped = (torch.isfinite(S).all(-1) & ~torch.isfinite(kept).all(-1)).nonzero().squeeze(1).tolist()
        if dropped:
            out[str(g)] = [both.meta.keypoint_names[k] for k in dropped]
    return out


def unseen_keypoints(mix: sfm_mixture.MixtureResult, missing: torch.Tensor, both: ClassCollection,
                     cfg: Config) -> torch.Tensor:
    """``(2N,)`` long: for the rows ``missing`` (the unseen-image path), how many of their visible
    keypoints have a row in the mean shape the path fits (its group's, :func:`_unseen_shape`);
    -1 elsewhere. 0 means the camera is fitted to the silhouette alone."""
    count = torch.full((len(both),), -1, dtype=torch.long, device=missing.device)
    for g in range(mix.k):
        rows = None if mix.k == 1 else mix.groups[g][0]
        sub = _rows(both, rows)
        S = _unseen_shape(mix.shape(g), sub, cfg)
        seen = (sub.visible & torch.isfinite(sub.keypoints).all(-1) & torch.isfinite(S).all(-1)).sum(-1)
        if rows is None:
            count = torch.where(missing, seen, count)
        else:
            count[rows] = torch.where(missing[rows], seen, count[rows])
    return count


def unseen_per_group(mix: sfm_mixture.MixtureResult, cams: ScaledOrthographic, missing: torch.Tensor,
                     both: ClassCollection, dist: torch.Tensor, cfg: Config) -> ScaledOrthographic:
    """``cams`` with the rows ``missing (2N,) bool`` estimated from their group's mean shape (unseen-image path)."""
    return _per_group(mix, cams, lambda g, rows: cameras_from_mean_shape(
        mix.shape(g), _rows(cams, rows), _rows(missing, rows).nonzero().squeeze(1), _rows(both, rows), _rows(dist, rows), cfg))


def _viewpoints(coll: ClassCollection, cfg: Config, report: ClassReport, device, gt_img: ScaledOrthographic | None):
    """Cameras for originals and mirrors (canvas pixels), the mean shape and the symmetry plane.

    Returns a dict with ``both`` (the 2N-instance collection), ``cams_sfm``, ``cams`` (2N), ``shape (K,3)``
    (with several shape groups: the largest group's, in the class frame), ``reflection (3,3)``,
    ``has_camera (2N,) bool``, ``groups`` (:class:`carvi_torch.sfm_mixture.MixtureResult`).
    """
    n = len(coll)
    both = coll.with_mirrors()
    with _timed(report, "sfm", device):
        res = class_sfm(both, cfg)
    for msg in res.problems:
        report.warnings.append(f"sfm: {msg}")
    report.info["sfm"] = res.summary()
    for i in (~res.valid[:n]).nonzero().squeeze(1).tolist():
        why = res.reasons[i] if i < len(res.reasons) and res.reasons[i] else "fewer than 2 visible keypoints"
        report.warnings.append(f"annotation {int(coll.annotation_ids[i])} ({coll.sources[i]}): no SfM camera: {why}")

    with _timed(report, "sdf", device):
        dist = distance_to_mask(both.masks)
    with _timed(report, "sfm", device):
        mix = _shape_groups(both, dist, res, cfg, report)
    cams_sfm, sfm_valid = group_sfm_cameras(mix)
    shape = mix.shape(mix.largest())
    reflection = sfm.symmetry_plane(shape, coll.meta.flip_pairs)
    has_camera = sfm_valid.clone()

    cams = cams_sfm
    if cfg.cameras == "gt":
        if gt_img is None:
            raise RuntimeError("cameras=gt needs gt.json with a camera for every annotation")
        w = coll.image_size[:, 0].to(gt_img.t.dtype)
        mirrored = gt_img.mirror(w, GT_REFLECTION.to(gt_img.R))
        cams = ScaledOrthographic.cat([gt_img.compose_similarity(coll.canvas_from_image),
                                       mirrored.compose_similarity(both.canvas_from_image[n:])])
        has_camera = torch.ones(2 * n, dtype=torch.bool, device=device)
        # express the mean shape in the ground-truth frame, so clusters/selection use the same frame
        from .viewpoint_metrics import align_rotations

        ok = res.valid
        G = align_rotations(cams_sfm.R[ok], cams.R[ok])  # R_sfm G ~ R_gt
        ratio = (cams.s[ok] / cams_sfm.s[ok]).median()
        shape = (shape @ G) / ratio
        reflection = GT_REFLECTION.to(shape)
    elif cfg.refine:
        with _timed(report, "refine", device):
            cams, energy = refine_groups(mix, cams_sfm, both, dist, cfg)
        ok = sfm_valid
        report.info["refine"] = {"median_energy_before": float(energy[0][ok].median()) if ok.any() else None,
                                 "median_energy_after": float(energy[1][ok].median()) if ok.any() else None}
        left_out = keypoints_left_out(mix, both, cfg)
        if left_out:
            report.info["refine"]["keypoints_left_out"] = left_out
            _log(f"  {coll.name}: refinement leaves out keypoints shown by fewer than "
                 f"{cfg.refine_min_support:.0%} of the instances: "
                 + "; ".join(f"group {g}: {', '.join(v)}" for g, v in left_out.items()), cfg)
    # instances without an SfM camera (fewer than 2 visible keypoints): the unseen-image path
    missing = ~has_camera
    if bool(missing.any()):
        with _timed(report, "refine", device):
            cams = unseen_per_group(mix, cams, missing, both, dist, cfg)
        idx = missing.nonzero().squeeze(1)
        report.info["cameras_from_mean_shape"] = [int(coll.annotation_ids[i]) for i in idx.tolist() if i < n]
        unseen_kp = unseen_keypoints(mix, missing, both, cfg)
        blind = [int(coll.annotation_ids[i]) for i in (unseen_kp[:n] == 0).nonzero().squeeze(1).tolist()]
        if blind:
            report.info["cameras_from_silhouette_only"] = blind
            report.warnings.append(
                f"{len(blind)} annotation(s) without an SfM camera got one from the silhouette alone (none of "
                f"their visible keypoints has a row in the mean shape): unreliable, a silhouette often fits "
                f"several viewpoints (cameras.json: camera_from 'silhouette'); ids {blind[:20]}"
                + (" ..." if len(blind) > 20 else ""))
        has_camera = torch.ones_like(has_camera)
    else:
        unseen_kp = torch.full((len(both),), -1, dtype=torch.long, device=missing.device)
    finite = torch.isfinite(cams.R).flatten(1).all(1) & torch.isfinite(cams.s) & (cams.s > 0)
    has_camera &= finite
    return {"both": both, "cams_sfm": cams_sfm, "sfm_valid": sfm_valid, "cams": cams, "shape": shape,
            "reflection": reflection, "has_camera": has_camera, "dist": dist, "groups": mix,
            "unseen_keypoints": unseen_kp, "ground_truth_cameras": cfg.cameras == "gt"}


@dataclass
class _Clusters:
    labels: torch.Tensor
    threshold_deg: float
    sizes: torch.Tensor
    log: list


def _clusters(view_dirs: torch.Tensor, usable: torch.Tensor, axes: torch.Tensor, cfg: Config) -> _Clusters:
    """Cluster the instances that have a camera; the others get label -1 (never surrogates)."""
    labels = torch.full((len(view_dirs),), -1, dtype=torch.long, device=view_dirs.device)
    if not bool(usable.any()):
        return _Clusters(labels, cfg.cluster_threshold_deg, torch.zeros(3, dtype=torch.long), ["no usable camera"])
    sub = surrogates.cluster_by_direction(view_dirs[usable], axes, threshold_deg=cfg.cluster_threshold_deg,
                                          widen_step_deg=cfg.cluster_widen_step_deg,
                                          max_threshold_deg=cfg.cluster_max_threshold_deg)
    labels[usable] = sub.labels.to(labels.device)
    return _Clusters(labels, float(sub.threshold_deg), sub.sizes, list(sub.log))


def _jsonable(x):
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().tolist()
    return x


def _cameras_json(coll: ClassCollection, vp: dict, axes: torch.Tensor | None, clusters) -> dict:
    """``cameras.json`` content: per annotation id, SfM and refined cameras in image pixels."""
    n = len(coll)
    mix = vp["groups"]
    group_of = mix.labels.tolist() if mix.k > 1 else None  # one host read
    inv = coll.canvas_from_image.inverse()
    sfm_img = vp["cams_sfm"][:n].compose_similarity(inv).to_list()
    ref_img = vp["cams"][:n].compose_similarity(inv).to_list()
    az, el, ro = azimuth_elevation_roll_from_rotation(vp["cams"].R[:n].double())
    sfm_ok, has_cam = vp["sfm_valid"][:n].tolist(), vp["has_camera"][:n].tolist()  # one host read each
    unseen = vp["unseen_keypoints"][:n].tolist() if "unseen_keypoints" in vp else [-1] * n
    per = {}
    for i, aid in enumerate(coll.annotation_ids.tolist()):
        if not has_cam[i]:
            camera_from = None
        elif vp.get("ground_truth_cameras"):
            camera_from = "ground_truth"
        elif sfm_ok[i]:
            camera_from = "sfm"
        else:  # the unseen-image path: the mean shape's keypoints and the silhouette, or the silhouette alone
            camera_from = "mean_shape" if unseen[i] > 0 else "silhouette"
        per[str(aid)] = {
            "source": coll.sources[i],
            "sfm": sfm_img[i] if sfm_ok[i] else None,
            "refined": ref_img[i] if has_cam[i] else None,
            "camera_from": camera_from,
            "azimuth_deg": math.degrees(float(az[i])), "elevation_deg": math.degrees(float(el[i])),
            "roll_deg": math.degrees(float(ro[i])),
            "cluster": int(clusters.labels[i]) if clusters is not None else None,
        }
        if group_of is not None:
            per[str(aid)]["shape_group"] = group_of[i]
    names = coll.meta.keypoint_names

    def named(S):
        S = S.detach().double().cpu()
        return {nm: (None if not torch.isfinite(S[k]).all() else S[k].tolist()) for k, nm in enumerate(names)}

    out = {
        "class": coll.name,
        "frame": "image pixels of each annotation's image; R rows = image x, image y (down), view direction",
        "cameras": per,
        "mean_shape": named(vp["shape"]),
        "symmetry_plane": vp["reflection"].detach().double().cpu().tolist(),
        "principal_directions": axes.detach().double().cpu().tolist() if axes is not None else None,
        "cluster_threshold_deg": float(clusters.threshold_deg) if clusters is not None else None,
    }
    if mix.k > 1:  # a mixture of rigid shapes: every group's mean shape, in the same class frame
        sizes = mix.sizes()
        out["shape_groups"] = [{"objects": sizes[g], "mean_shape": named(mix.shape(g))} for g in range(mix.k)]
        out["mean_shape_group"] = mix.largest()
    return out


# =========================================================================== reconstruction


def _views_for_proposals(refs: torch.Tensor, sur: torch.Tensor, n: int, use_mirrors: bool) -> torch.Tensor:
    """Further views of every proposal (indices into the 2N-instance arrays).

    Args:
        refs: ``(R,)`` reference indices (originals, ``< n``).
        sur: ``(R, P, 2)`` surrogate indices (originals).
    Returns:
        ``(R, P, V)`` long: the two surrogates, and with mirrors also the mirrored reference and the
        mirrored surrogates (index ``+ n``).
    """
    r = refs[:, None, None].expand(-1, sur.shape[1], 1)
    if not use_mirrors:
        return sur
    return torch.cat([sur, r + n, sur + n], dim=-1)


def prepare_class(coll: ClassCollection, cfg: Config, device: torch.device, generator: torch.Generator,
                  gt: dict | None = None, out: Path | None = None, report: ClassReport | None = None):
    """Every stage of one class up to carving: cameras, clusters, triplets, prepared silhouettes.

    Writes ``out/<class>/cameras.json`` when ``out`` is given. Used by :func:`run_class` and
    by the benchmark (which carves the same proposals on its own).

    Returns:
        ``(plan, todo, report)``: the :class:`_ClassPlan` (``None`` when the class stops
        before carving: too few instances, missing ground truth, ``stage=cameras``), the
        original indices to reconstruct, and the class report so far.
    """
    report = ClassReport(coll.name, objects=len(coll)) if report is None else report
    cdir = (Path(out) if out is not None else Path(".")) / coll.name
    if len(coll) < cfg.min_instances:
        report.status = "skipped"
        report.skip(f"class has {len(coll)} usable instance(s), fewer than min_instances={cfg.min_instances}",
                    "class")
        return None, [], report
    coll = coll.to(device)
    n = len(coll)
    gt_img = _gt_cameras(gt, coll)
    if cfg.cameras == "gt" and gt_img is None:
        report.status = "failed"
        report.skip("cameras=gt but gt.json has no camera for every annotation of this class", "viewpoints")
        return None, [], report

    vp = _viewpoints(coll, cfg, report, device, gt_img)
    both, cams, shape = vp["both"], vp["cams"], vp["shape"]

    # ---- principal directions and clusters (originals only)
    with _timed(report, "surrogates", device):
        axes = surrogates.principal_directions(shape)
        usable = vp["has_camera"][:n]
        clusters = _clusters(cams.R[:n, 2, :], usable, axes, cfg)
    for line in clusters.log:
        _log(f"  {coll.name}: {line}", cfg)
        report.warnings.append(f"clusters: {line}")
    report.info["clusters"] = {"threshold_deg": float(clusters.threshold_deg),
                               "sizes": [int(v) for v in clusters.sizes.tolist()]}
    if out is not None:
        write_json(cdir / "cameras.json", _cameras_json(coll, vp, axes, clusters))
    if cfg.stage == "cameras":
        report.reconstructed = 0
        report.status = "cameras"
        return None, [], report

    # ---- which references remain to do
    mesh_dir, vox_dir = cdir / "meshes", cdir / "voxels"
    aids = coll.annotation_ids.tolist()
    usable_h = usable.tolist()
    done = [out is not None and not cfg.overwrite and is_done(mesh_dir / f"{a}.{cfg.mesh_format}",
                                                             vox_dir / f"{a}.npz") for a in aids]
    report.resumed = sum(done)
    chosen = [cfg.references == "all" or coll.splits[i] == cfg.references for i in range(n)]
    todo = [i for i in range(n) if chosen[i] and not done[i] and usable_h[i]]
    report.info["references"] = sum(chosen)
    for i in range(n):
        if chosen[i] and not usable_h[i]:
            report.skip("no usable camera", "viewpoints", aids[i], coll.sources[i])
    if not todo:  # everything done already (a resumed run) or nothing usable: no maps to prepare
        return None, [], report

    # ---- surrogates for every reference (all of them, so a resumed run samples the same triplets)
    symmetric = coll.meta.symmetry == "rotational"
    use_mirrors = cfg.mirrors and not coll.meta.articulated
    refs_all = torch.arange(n, device=device)
    with _timed(report, "surrogates", device):
        if symmetric:
            trip = None
        else:
            trip = surrogates.sample_triplets(clusters.labels, coll.object_ids, refs_all, proposals=cfg.proposals,
                                              generator=generator)
    # ---- the silhouettes, prepared once for every carving of the class (the outside distances are reused)
    with _timed(report, "sdf", device):
        dist = vp.pop("dist")
        maps = carve.prepare_maps(lambda a, b: signed_distance(both.masks[a:b], outside=dist[a:b]), cams,
                                  count=len(both))
        del dist
    with _timed(report, "select", device):
        centre = select.plane_centre(shape)
        extent = select.plane_extent(shape, centre=centre)
        avg, counts = select.average_masks(coll.masks, cams[:n], clusters.labels, axes, plane_size=cfg.plane_size,
                                           extent=extent, centre=centre)
    report.info["average_mask_members"] = [int(c) for c in counts.tolist()]
    todo_t = torch.tensor(todo, dtype=torch.long, device=device)
    if symmetric and todo:
        # surrogates synthesised by rotating the reference camera about the symmetry axis: further
        # entries that reuse the reference's own map (no map is copied)
        with _timed(report, "surrogates", device):
            up = -cams.R[:n, 1, :].mean(dim=0)  # mean image-up direction in the object frame
            axis = surrogates.symmetry_axis(shape, up=up)
            if cfg.symmetric_axis_in_image:
                axis = surrogates.axis_in_image_plane(cams[todo_t], axis)
            extra = surrogates.symmetric_surrogates(cams[todo_t], axis, step_deg=cfg.symmetric_step_deg,
                                                    centre=centre)
            per_ref = len(extra) // len(todo)
            maps = maps.with_entries(maps.entry_map[todo_t].repeat_interleave(per_ref), extra)

    plan = _ClassPlan(coll=coll, cams=cams, axes=axes, trip=trip, maps=maps, avg=avg, counts=counts, extent=extent,
                      centre=centre, symmetric=symmetric, use_mirrors=use_mirrors, cdir=cdir,
                      aids=aids, todo_pos={i: k for k, i in enumerate(todo)})
    return plan, todo, report


def proposals_of(plan: "_ClassPlan", ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The proposals of references ``ids`` (original indices, a consecutive run of ``todo``).

    Returns:
        ``reference (R * P,)`` long, ``views (R * P, V)`` long entries of ``plan.maps`` and
        ``valid (R * P,)`` bool, reference-major.
    """
    views, valid = _proposal_views(ids, plan)
    R, P = valid.shape
    return ids[:, None].expand(R, P).reshape(-1), views.reshape(R * P, -1), valid.reshape(-1)


def run_class(coll: ClassCollection, cfg: Config, out: Path, gt: dict | None, device: torch.device,
              generator: torch.Generator, writer: "_Writer | None" = None) -> ClassReport:
    """Run every stage for one class; write ``out/<class>/``; return its report.

    ``writer`` meshes and writes the objects (worker processes, see :func:`run`); by default
    they are written inline.
    """
    plan, todo, report = prepare_class(coll, cfg, device, generator, gt=gt, out=out)
    if plan is None:
        return report
    cdir = plan.cdir
    todo_t = torch.tensor(todo, dtype=torch.long, device=device)
    chunk = _chunk_objects(cfg, device)
    own_writer = writer is None
    if own_writer:
        writer = _Writer(0)
    bar = tqdm(total=len(todo), desc=f"{coll.name}: carve+select", disable=not cfg.progress, leave=False)
    scores_out = {}
    try:
        for c0 in range(0, len(todo), chunk):
            ids = todo_t[c0:c0 + chunk]
            result = _carve_and_select(ids, plan, cfg, report, device)
            # handing the chunk to the writers; the time spent blocked on busy writers is booked
            # as waiting for them, the rest as hand-off (host-side bookkeeping per object)
            t0, b0 = time.perf_counter(), writer.blocked
            _submit_chunk(result, ids, plan, cfg, report, writer, scores_out)
            waited = writer.blocked - b0
            report.seconds["handoff"] = report.seconds.get("handoff", 0.0) + time.perf_counter() - t0 - waited
            report.seconds["write_wait"] = report.seconds.get("write_wait", 0.0) + waited
            del result  # the next chunk's grids must not sit beside this one's
            bar.update(len(ids))
        bar.close()
        with _timed(report, "write_wait", device):
            writer.drain()
    except BaseException as e:
        # this class's pending objects are finished (their files written) before the error
        # leaves, so they are not booked into the next class; an interrupt drops them
        if own_writer:
            writer.close(cancel=True)
        elif not isinstance(e, KeyboardInterrupt):
            writer.drain()
        try:  # the scores of the objects handed to the writer so far are kept too
            _write_scores(cdir, cfg, scores_out)
        except Exception:  # noqa: BLE001 - the original error is the one to report
            pass
        raise
    if own_writer:
        writer.close()
    _write_scores(cdir, cfg, scores_out)
    return report


def _write_scores(cdir: Path, cfg: Config, scores_out: dict) -> None:
    """Merge this run's proposal scores into ``cdir/proposal_scores.json`` (atomic)."""
    if not (cfg.keep_all_scores and scores_out):
        return
    prev = {}
    sp = cdir / "proposal_scores.json"
    if sp.is_file() and not cfg.overwrite:
        try:
            prev = read_json(sp)
        except ValueError:
            prev = {}
    prev.update(scores_out)
    write_json(sp, prev, indent=None)


@dataclass
class _ClassPlan:
    """What carving and selection need for every chunk of one class (built once per class)."""

    coll: ClassCollection
    cams: ScaledOrthographic  # (2N) canvas cameras of originals and mirrors
    axes: torch.Tensor
    trip: object  # surrogates.Triplets or None (rotationally symmetric class)
    maps: carve.CarveMaps  # entries: 2N silhouettes (+ rotated reference cameras, symmetric classes)
    avg: torch.Tensor
    counts: torch.Tensor
    extent: float
    centre: torch.Tensor
    symmetric: bool
    use_mirrors: bool
    cdir: Path
    aids: list  # annotation ids of the originals (host ints)
    todo_pos: dict  # original index -> position among the references to reconstruct
    canvas_scale: torch.Tensor | None = None  # (N,) float64 host copy of canvas_from_image.scale
    canvas_offset: torch.Tensor | None = None  # (N, 2) float64 host copy of canvas_from_image.offset

    def __post_init__(self):
        sim = self.coll.canvas_from_image
        self.canvas_scale = sim.scale.detach().double().cpu()
        self.canvas_offset = sim.offset.detach().double().cpu()


#: Objects per pipeline chunk on the CPU: small enough that a chunk's grids stay in the
#: caches between carving and selection, large enough that per-chunk overheads vanish.
_CPU_CHUNK_OBJECTS = 4
#: Fraction of the free CUDA memory a pipeline chunk may take (grids, costs, projections).
_CUDA_CHUNK_FRACTION = 0.25
#: Bytes per voxel of one proposal held during a chunk on CUDA (occupancy, boundary, sampling temporaries).
_CUDA_BYTES_PER_VOXEL = 16


def _chunk_objects(cfg: Config, device: torch.device) -> int:
    """References carved and selected together (one pipeline chunk).

    CPU: a few (:data:`_CPU_CHUNK_OBJECTS`), the carving and selection chunk further for their
    caches. CUDA: as many as a quarter of the free device memory holds, so that kernels are
    few and large.
    """
    per_object = max(1, cfg.proposals) * cfg.resolution ** 3
    if device.type == "cuda":
        free, _total = torch.cuda.mem_get_info(device)
        return max(1, int(free * _CUDA_CHUNK_FRACTION) // (per_object * _CUDA_BYTES_PER_VOXEL))
    return _CPU_CHUNK_OBJECTS


def _carve_batch_voxels(cfg: Config, device: torch.device) -> int:
    """Voxels per carving chunk: the config's bound, and at most the device default of the carving."""
    best = carve.default_batch_voxels(device)
    return max(1, min(int(cfg.max_batch_voxels), best))


@dataclass
class _ChunkResult:
    """Carving and selection of one chunk of ``R`` references, ``P`` proposals each (host tensors
    except ``grids``)."""

    grids: carve.ProposalGrids  # the kept proposals (device)
    pos: torch.Tensor  # (R * P,) long position of each proposal in ``grids`` (-1: not carved)
    scores: torch.Tensor  # (R, P) float
    misses: torch.Tensor  # (R, P) long
    ok: torch.Tensor  # (R, P) bool: valid and not empty
    valid: torch.Tensor  # (R, P) bool: a valid triplet
    best: torch.Tensor  # (R,) long
    best_occupancy: torch.Tensor  # (R, D, H, W) bool: the best proposal of every reference (host)
    best_transform: torch.Tensor  # (R, 4, 4) float64 voxel -> canvas of the best proposal (host)
    surrogates: torch.Tensor | None  # (R, P, 2) long original indices (host), -1 invalid


def _proposal_views(ids: torch.Tensor, plan: _ClassPlan) -> tuple[torch.Tensor, torch.Tensor]:
    """Further views ``(R, P, V)`` (entries of ``plan.maps``) and validity ``(R, P)`` of the chunk's proposals."""
    n = len(plan.coll)
    R = len(ids)
    if plan.symmetric:
        # one proposal per reference: its rotated cameras, entries 2N + k * m + j (k its rank in ``todo``)
        m = (len(plan.maps) - 2 * n) // max(1, len(plan.todo_pos))
        first = plan.todo_pos[int(ids[0])]  # chunks are consecutive runs of ``todo``
        k = first + torch.arange(R, device=ids.device)
        views = 2 * n + k[:, None, None] * m + torch.arange(m, device=ids.device)
        return views, torch.ones(R, 1, dtype=torch.bool, device=ids.device)
    sur = plan.trip.surrogates[ids]  # (R, P, 2)
    return _views_for_proposals(ids, sur.clamp(min=0), n, plan.use_mirrors), plan.trip.valid[ids]


def _carve_and_select(ids: torch.Tensor, plan: _ClassPlan, cfg: Config, report: ClassReport,
                      device: torch.device) -> _ChunkResult:
    """Carve every proposal of the references ``ids`` (indices of originals), score and rank them.

    All device work of a chunk; the few tensors the writer needs come back to the host at
    the end, in one transfer each.
    """
    coll = plan.coll
    R = len(ids)
    with _timed(report, "surrogates", device):
        views, valid = _proposal_views(ids, plan)
    P = views.shape[1]
    flat_ref = ids[:, None].expand(R, P).reshape(-1)
    flat_views = views.reshape(R * P, -1)
    flat_valid = valid.reshape(-1)
    keep = flat_valid.nonzero().squeeze(1)
    with _timed(report, "carve", device):
        grids = carve.carve_proposals(plan.maps, None, flat_ref[keep], flat_views[keep], resolution=cfg.resolution,
                                      imprint=cfg.imprint, max_batch_voxels=_carve_batch_voxels(cfg, device),
                                      interpolation=cfg.carve_interpolation, backend=cfg.carve_backend)
    with _timed(report, "select", device):
        kept_ref = flat_ref[keep]
        ref_cams = plan.cams[kept_ref]
        proj = select.project_proposals(grids.occupancy, grids.voxel_to_camera, ref_cams, plan.axes,
                                        plane_size=cfg.plane_size, extent=plan.extent, centre=plan.centre)
        sc = select.score_proposals(proj, plan.avg, plan.counts)
        miss = select.keypoint_misses(grids.occupancy, grids.voxel_to_camera, coll.keypoints[kept_ref],
                                      coll.visible[kept_ref], columns=grids.columns)
        scores = torch.full((R * P,), float("inf"), device=device)
        misses = torch.full((R * P,), 10 ** 6, dtype=torch.long, device=device)
        empty = torch.ones(R * P, dtype=torch.bool, device=device)
        scores[keep], misses[keep], empty[keep] = sc, miss, grids.empty
        ok = flat_valid & ~empty
        _order, best = select.rank_proposals(scores.view(R, P), misses.view(R, P), ok.view(R, P))
        # position of each proposal inside `keep`; the best one of each reference
        pos = torch.full((R * P,), -1, dtype=torch.long, device=device)
        pos[keep] = torch.arange(len(keep), device=device)
        if len(keep):
            best_pos = pos.view(R, P).gather(1, best.clamp(min=0)[:, None])[:, 0].clamp(min=0)
            best_occ = grids.occupancy[best_pos].cpu()
            best_T = grids.voxel_to_camera[best_pos].double().cpu()
        else:  # no valid proposal in the chunk: nothing will be written
            n = cfg.resolution
            best_occ = torch.zeros(R, n, n, n, dtype=torch.bool)
            best_T = torch.zeros(R, 4, 4, dtype=torch.float64)
    return _ChunkResult(grids=grids, pos=pos.cpu(), scores=scores.view(R, P).cpu(), misses=misses.view(R, P).cpu(),
                        ok=ok.view(R, P).cpu(), valid=valid.cpu(), best=best.cpu(), best_occupancy=best_occ,
                        best_transform=best_T,
                        surrogates=None if plan.trip is None else plan.trip.surrogates[ids].cpu())


def _submit_chunk(res: _ChunkResult, ids: torch.Tensor, plan: _ClassPlan, cfg: Config, report: ClassReport,
                  writer: "_Writer", scores_out: dict) -> None:
    """Hand every reconstructed reference of a chunk to the writer; note the failures (host data only)."""
    coll = plan.coll
    R, P = res.scores.shape
    scale, offset = plan.canvas_scale, plan.canvas_offset
    ids_h = ids.tolist()
    any_ok = res.ok.any(dim=1).tolist()
    any_valid = res.valid.any(dim=1).tolist()
    best = res.best.tolist()
    aid_of = plan.aids
    for j, i in enumerate(ids_h):
        aid, src = aid_of[i], coll.sources[i]
        if not any_ok[j]:
            if any_valid[j]:
                reason = "all proposals carved away (empty)"
            else:
                why = plan.trip.reasons.get(i) if plan.trip is not None else None
                reason = f"no valid surrogate triplet ({why or 'clusters too small'})"
            report.skip(reason, "carve", aid, src)
            continue
        canvas_to_image = _canvas_to_image_4x4(scale[i], offset[i])
        v2c = res.best_transform[j]
        v2img = canvas_to_image @ v2c
        sur_ids = []
        if res.surrogates is not None:
            sur_ids = [aid_of[s] for s in res.surrogates[j, best[j]].tolist() if s >= 0]
        proposals = None
        if cfg.save_proposals:
            proposals = _proposals_payload(res, j, canvas_to_image, best[j], aid_of)
        job = dict(aid=aid, occupancy=res.best_occupancy[j].numpy(), voxel_to_canvas=v2c.numpy(),
                   voxel_to_image=v2img.numpy(), canvas_scale=float(scale[i]),
                   canvas_offset=offset[i].float().numpy(), surrogates=np.asarray(sur_ids, dtype=np.int64),
                   voxel_path=str(plan.cdir / "voxels" / f"{aid}.npz"),
                   mesh_path=str(plan.cdir / "meshes" / f"{aid}.{cfg.mesh_format}"),
                   proposals_path=str(plan.cdir / "proposals" / f"{aid}.npz"), proposals=proposals,
                   largest_component=cfg.largest_component)
        writer.submit(job, lambda out, aid=aid, src=src: _account(out, aid, src, report))
        if cfg.keep_all_scores:
            rows = res.scores[j].tolist()
            scores_out[str(aid)] = {
                "best": int(best[j]),
                "scores": [None if not math.isfinite(v) else round(v, 6) for v in rows],
                "misses": [int(v) if v < 10 ** 6 else None for v in res.misses[j].tolist()],
                "surrogates": ([[aid_of[s] if s >= 0 else None for s in pair] for pair in res.surrogates[j].tolist()]
                               if res.surrogates is not None else None),
            }


def _account(out: dict, aid: int, src: str, report: ClassReport) -> None:
    """Book a finished write into the class report."""
    report.seconds["mesh"] = report.seconds.get("mesh", 0.0) + out["mesh_seconds"]
    report.seconds["write"] = report.seconds.get("write", 0.0) + out["write_seconds"]
    if out["ok"]:
        report.reconstructed += 1
    else:
        report.skip(out["reason"], "mesh", aid, src)


def _proposals_payload(res: _ChunkResult, j: int, canvas_to_image: torch.Tensor, best: int, aid_of: list) -> dict:
    """Every proposal of reference ``j`` of a chunk (bit-packed occupancy, image-pixel transforms, scores)."""
    R, P = res.scores.shape
    positions = res.pos[j * P:(j + 1) * P]
    ok = positions >= 0
    idx = positions.clamp(min=0).to(res.grids.occupancy.device)
    occ = res.grids.occupancy[idx].cpu().numpy() & ok.numpy()[:, None, None, None]
    v2img = (canvas_to_image[None] @ res.grids.voxel_to_camera[idx].double().cpu()).numpy()
    sur = np.full((P, 2), -1, dtype=np.int64)
    if res.surrogates is not None:
        for k, pair in enumerate(res.surrogates[j].tolist()):
            sur[k] = [aid_of[x] if x >= 0 else -1 for x in pair]
    return dict(occupancy_bits=np.packbits(occ.reshape(P, -1), axis=1), shape=np.asarray(occ.shape[1:]),
                voxel_to_camera=v2img, valid=ok.numpy(), scores=res.scores[j].numpy(),
                misses=res.misses[j].numpy(), best=np.int64(best), surrogates=sur)


def _write_object(job: dict) -> dict:
    """Mesh and files of one reconstructed object (runs in a writer process, or inline).

    Takes host (numpy) data only. Returns ``ok``, ``reason``, ``mesh_seconds``, ``write_seconds``.
    """
    t0 = time.perf_counter()
    occ = job["occupancy"]
    v2img = job["voxel_to_image"]
    if job["largest_component"]:
        occ = mesh.largest_component(occ)
    m = mesh.occupancy_to_mesh(occ, v2img)
    t1 = time.perf_counter()
    if len(m.faces) == 0:
        return dict(ok=False, reason="selected proposal has no surface", mesh_seconds=t1 - t0, write_seconds=0.0)
    if job["proposals"] is not None:
        write_npz(job["proposals_path"], **job["proposals"])
    write_npz(job["voxel_path"], occupancy=occ, voxel_to_camera=v2img, voxel_to_canvas=job["voxel_to_canvas"],
              canvas_scale=job["canvas_scale"], canvas_offset=job["canvas_offset"], surrogates=job["surrogates"])
    mesh.write_mesh(m, job["mesh_path"])
    return dict(ok=True, reason=None, mesh_seconds=t1 - t0, write_seconds=time.perf_counter() - t1)


def _write_object_safe(job: dict) -> dict:
    """:func:`_write_object`, with any error of this object booked as its own failure (reason)
    instead of surfacing later, at some other object's turn (or in another class)."""
    try:
        return _write_object(job)
    except Exception as e:  # noqa: BLE001 - reported per object, the run goes on
        return dict(ok=False, reason=f"writing failed: {type(e).__name__}: {e}", mesh_seconds=0.0, write_seconds=0.0)


def _start_worker() -> int:
    """No-op run by each writer process once, so that all of them start (fork) early."""
    return os.getpid()


class _Writer:
    """Meshes and files of reconstructed objects, in worker processes or inline.

    Results are booked in submission order (deterministic reports). At most
    ``4 * workers`` objects wait at once, which bounds the memory of pending grids.
    With ``workers == 0`` every object is written at once, in this process.
    ``blocked``: seconds :meth:`submit` spent waiting for a writer to finish (back-pressure:
    the writers, not the device work, are then what limits the run).
    """

    def __init__(self, workers: int):
        self.workers = int(workers)
        self.pool = None
        self.pending: deque = deque()
        self.blocked = 0.0
        if self.workers > 0:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # fork (Linux): workers share the parent's imports and start in milliseconds; they only
            # run numpy/scikit-image/trimesh code. They are started here, before the data are loaded.
            method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
            self.pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context(method))
            for f in [self.pool.submit(_start_worker) for _ in range(self.workers)]:
                f.result()

    def submit(self, job: dict, done) -> None:
        if self.pool is None:
            done(_write_object_safe(job))
            return
        self.pending.append((self.pool.submit(_write_object_safe, job), done))
        if len(self.pending) > 4 * self.workers:
            t0 = time.perf_counter()
            while len(self.pending) > 4 * self.workers:
                self._finish_one()
            self.blocked += time.perf_counter() - t0

    def _finish_one(self) -> None:
        future, done = self.pending.popleft()
        try:
            out = future.result()
        except Exception as e:  # noqa: BLE001 - a writer process died (BrokenProcessPool, ...)
            out = dict(ok=False, reason=f"writer process failed: {type(e).__name__}: {e}", mesh_seconds=0.0,
                       write_seconds=0.0)
        done(out)

    def drain(self) -> None:
        """Wait for every submitted object and book it."""
        while self.pending:
            self._finish_one()

    def close(self, cancel: bool = False) -> None:
        """Book what is pending (or, with ``cancel``, drop it: an error or Ctrl-C is on its way
        out) and stop the processes."""
        try:
            if not cancel:
                self.drain()
        finally:
            self.pending.clear()
            if self.pool is not None:
                self.pool.shutdown(wait=True, cancel_futures=True)
                self.pool = None


def _canvas_to_image_4x4(scale: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """4x4 map of camera-frame points from canvas pixels to image pixels (x, y shifted+scaled, z scaled)."""
    a = float(scale)
    T = torch.eye(4, dtype=torch.float64)
    T[0, 0] = T[1, 1] = T[2, 2] = 1.0 / a
    T[0, 3] = -float(offset[0]) / a
    T[1, 3] = -float(offset[1]) / a
    return T


# =========================================================================== whole run


def _env_count(name: str, minimum: int) -> int | None:
    """The integer environment variable ``name`` (at least ``minimum``), or None when unset."""
    env = os.environ.get(name)
    if env is None:
        return None
    try:
        return max(minimum, int(env))
    except ValueError:
        raise ValueError(f"{name} must be an integer, got {env!r}") from None


def _cores() -> int:
    """CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def writer_workers(cfg: Config, device: torch.device | None = None) -> int:
    """Writer processes of a run: ``CARVI_WRITERS`` if set, else ``cores - 1`` (at least 1; at
    most 8 on the CPU, 16 with ``device`` a GPU; none for ``stage=cameras``).

    Meshing and writing an object takes ~10-25 ms of CPU; in worker processes it overlaps the
    carving of the next objects (``0``: everything inline). On the CPU the carving needs the
    cores too; with a GPU the main process mostly waits on the device, and the writers are
    what limits a run (on an H100 with 16 cores, 9,087 objects: 62 s with 8 writers, 48 s with
    15; docs/benchmarks/README.md).
    """
    env = _env_count("CARVI_WRITERS", 0)
    if env is not None:
        return env
    if cfg.stage != "all":
        return 0
    cap = 16 if device is not None and device.type == "cuda" else 8
    return min(cap, max(1, _cores() - 1))


def torch_threads(workers: int) -> int:
    """Intra-op threads of this process during a run: ``CARVI_THREADS`` if set, else the CPU
    cores left to it beside ``workers`` writer processes (at least one).

    The carving and selection are chains of many medium-sized tensor operations; on a machine
    whose cores are busy with other work (the writers), extra OpenMP threads of each operation
    mostly wait for one another.
    """
    env = _env_count("CARVI_THREADS", 1)
    return env if env is not None else max(1, _cores() - workers)


@contextmanager
def _torch_threads(n: int):
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def run(cfg: Config, workers: int | None = None, threads: int | None = None) -> dict:
    """Run every class; write ``config.yaml``, ``summary.json``, per-class outputs and ``preview.png``.

    ``workers``: writer processes for meshes and files (default :func:`writer_workers`);
    ``threads``: torch intra-op threads of this process during the run (default
    :func:`torch_threads`; restored afterwards).
    """
    t_start = time.perf_counter()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    from .io.outputs import write_bytes

    changed = _settings_changed(out / "config.yaml", cfg)
    if changed:
        _log(f"{out} holds a run made with other settings ("
             + ", ".join(f"{k}: {a!r} -> {b!r}" for k, (a, b) in changed.items())
             + "); its finished objects are kept as they are (resumed), so pass overwrite=true to redo them", cfg)
    write_bytes(out / "config.yaml", cfg.to_yaml().encode())
    device = cfg.resolve_device()
    torch.manual_seed(cfg.seed)
    # writer processes start first, while this process is small
    writer = _Writer(writer_workers(cfg, device) if workers is None else workers)
    try:
        with _torch_threads(torch_threads(writer.workers) if threads is None else max(1, int(threads))):
            summary = _run(cfg, out, device, writer, t_start)
    except BaseException:
        writer.close(cancel=True)  # an error or Ctrl-C: stop the writers without waiting for them
        raise
    writer.close()
    if changed:
        summary["resumed_from_other_settings"] = {k: list(v) for k, v in changed.items()}
    summary["peak_rss_workers_mb"] = round(_peak_rss_mb(children=True), 1) if writer.workers else 0.0
    summary["writer_workers"] = writer.workers
    write_json(out / "summary.json", summary)
    if cfg.preview and cfg.stage == "all":
        try:
            from .preview import write_preview

            write_preview(out, summary)
        except Exception as e:  # a picture must never fail the run
            _log(f"preview.png not written: {e}", cfg)
    return summary


#: Settings that do not change how an object is reconstructed (a rerun may differ in them freely;
#: the input files are the user's choice, and resumed objects are matched by annotation id).
_NEUTRAL_SETTINGS = {"out", "data", "gt", "progress", "preview", "overwrite", "classes", "stage", "device",
                     "sfm_group_threads",  # the mixture fit's result is the same on any number of threads
                     "carve_backend"}  # every carving backend gives the same labels voxel for voxel


def _settings_changed(previous: Path, cfg: Config) -> dict:
    """``{key: (old, new)}`` of the settings in which ``cfg`` differs from the run saved at
    ``previous`` (its ``config.yaml``), when that run's finished objects would be resumed
    (no ``overwrite``); empty otherwise, or when the file is missing or unreadable."""
    if cfg.overwrite or cfg.stage != "all" or not previous.is_file():
        return {}
    try:
        old = yaml.safe_load(previous.read_text()) or {}
    except (OSError, yaml.YAMLError):
        return {}
    new = yaml.safe_load(cfg.to_yaml())
    # a key the old file lacks (a setting added since) counts as changed: that run predates it
    return {k: (old.get(k), v) for k, v in new.items() if k not in _NEUTRAL_SETTINGS and old.get(k) != v}


def _run(cfg: Config, out: Path, device: torch.device, writer: "_Writer", t_start: float) -> dict:
    """:func:`run` once the writer is up: load, every class, ``summary.json``."""
    data_path, gt_path = prepare_data(cfg)
    t0 = time.perf_counter()
    loaded = coco.load_coco(data_path, canvas_size=cfg.canvas_size, margin=cfg.canvas_margin, device=device,
                            classes=cfg.classes)
    load_s = time.perf_counter() - t0
    for p in loaded.problems:
        _log(p.message(), cfg)
    gt = read_json(gt_path) if gt_path is not None and Path(gt_path).is_file() else None
    summary = {"data": str(data_path), "gt": str(gt_path) if gt_path else None, "device": str(device),
               "torch_threads": torch.get_num_threads(),
               "carve_backend": carve.resolve_backend(cfg.carve_backend, device, cfg.carve_interpolation),
               "load_seconds": round(load_s, 3),
               "input_problems": [p.to_dict() for p in loaded.problems], "classes": {}}
    names = sorted(loaded.collections)
    if cfg.classes:
        for c in cfg.classes:
            if c not in loaded.collections:
                summary["classes"][c] = {"status": "skipped", "objects": 0, "reconstructed": 0,
                                         "failures": [{"stage": "load", "reason": "no usable object of this class"}]}
    for name in names:
        coll = loaded.collections[name]
        g = torch.Generator(device="cpu").manual_seed(cfg.seed + _stable_hash(name))
        _log(f"{name}: {len(coll)} objects", cfg)
        try:
            rep = run_class(coll, cfg, out, gt, device, g, writer)
        except Exception as e:  # one broken class must not stop the others
            import traceback

            rep = ClassReport(name, objects=len(coll), status="failed")
            rep.skip(f"{type(e).__name__}: {e}", "class")
            _log(traceback.format_exc(), cfg)
        summary["classes"][name] = rep.to_dict()
        for s in rep.skipped:
            _log(f"  {name}: annotation {s['annotation_id']} ({s['source']}) skipped at {s['stage']}: {s['reason']}",
                 cfg)
        write_json(out / "summary.json", summary)
    summary["total_seconds"] = round(time.perf_counter() - t_start, 3)
    summary["peak_rss_mb"] = round(_peak_rss_mb(), 1)
    if device.type == "cuda":
        summary["peak_cuda_mb"] = round(torch.cuda.max_memory_allocated(device) / 2 ** 20, 1)
    write_json(out / "summary.json", summary)
    return summary


def _peak_rss_mb(children: bool = False) -> float:
    """Peak resident memory (MB) of this process, or of its largest finished child process."""
    import resource

    who = resource.RUSAGE_CHILDREN if children else resource.RUSAGE_SELF
    return resource.getrusage(who).ru_maxrss / 1024.0


def _stable_hash(name: str) -> int:
    import zlib

    return zlib.crc32(name.encode()) % (2 ** 31)
