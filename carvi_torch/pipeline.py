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
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from . import carve, mesh, refine, select, sfm, surrogates
from .cameras import ScaledOrthographic, azimuth_elevation_roll_from_rotation
from .collection import ClassCollection
from .config import Config
from .io import coco
from .io.outputs import is_done, read_json, write_json, write_npz
from .sdf import distance_to_mask, signed_distance

__all__ = ["run", "run_class", "ClassReport", "prepare_data"]

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

    def to_dict(self) -> dict:
        return {"objects": self.objects, "reconstructed": self.reconstructed, "resumed": self.resumed,
                "skipped": len(self.skipped), "status": self.status, "failures": self.skipped,
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


def _viewpoints(coll: ClassCollection, cfg: Config, report: ClassReport, device, gt_img: ScaledOrthographic | None):
    """Cameras for originals and mirrors (canvas pixels), the mean shape and the symmetry plane.

    Returns a dict with ``both`` (the 2N-instance collection), ``cams_sfm``, ``cams`` (2N), ``shape (K,3)``,
    ``reflection (3,3)``, ``has_camera (2N,) bool``.
    """
    n = len(coll)
    both = coll.with_mirrors()
    k = coll.meta.num_keypoints
    with _timed(report, "sfm", device):
        res = sfm.rigid_sfm(both.keypoints, both.visible, max_outer=cfg.sfm_max_outer, inner=cfg.sfm_inner,
                            tol=cfg.sfm_tol, rigid_keypoints=coll.meta.rigid_keypoints,
                            keypoint_names=coll.meta.keypoint_names, flip_pairs=coll.meta.flip_pairs,
                            left_convention=coll.meta.left_convention)
    for msg in res.problems:
        report.warnings.append(f"sfm: {msg}")
    shape = res.shape
    reflection = sfm.symmetry_plane(shape, coll.meta.flip_pairs)
    cams_sfm = res.cameras
    has_camera = res.valid.clone()
    report.info["sfm"] = res.summary()
    for i in (~res.valid[:n]).nonzero().squeeze(1).tolist():
        why = res.reasons[i] if i < len(res.reasons) and res.reasons[i] else "fewer than 2 visible keypoints"
        report.warnings.append(f"annotation {int(coll.annotation_ids[i])} ({coll.sources[i]}): no SfM camera: {why}")

    dist = distance_to_mask(both.masks)
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
            rr = refine.refine_cameras(shape, cams_sfm, both.keypoints, both.visible, dist,
                                       silhouette_weight=cfg.silhouette_weight, max_iters=cfg.refine_iters,
                                       silhouette_robust=cfg.silhouette_robust or None)
        cams = rr.cameras
        report.info["refine"] = {"median_energy_before": float(rr.energy_before[res.valid].median())
                                 if res.valid.any() else None,
                                 "median_energy_after": float(rr.energy_after[res.valid].median())
                                 if res.valid.any() else None}
    # instances without an SfM camera (fewer than 2 visible keypoints): the unseen-image path
    missing = ~has_camera
    if bool(missing.any()):
        with _timed(report, "refine", device):
            idx = missing.nonzero().squeeze(1)
            est, _energy = refine.estimate_camera(shape, both.keypoints[idx], both.visible[idx], dist[idx],
                                                   silhouette_robust=cfg.silhouette_robust or None)
        R, s, t = cams.R.clone(), cams.s.clone(), cams.t.clone()
        R[idx], s[idx], t[idx] = est.R, est.s, est.t
        cams = ScaledOrthographic(R, s, t)
        report.info["cameras_from_mean_shape"] = [int(coll.annotation_ids[i]) for i in idx.tolist() if i < n]
        has_camera = torch.ones_like(has_camera)
    finite = torch.isfinite(cams.R).flatten(1).all(1) & torch.isfinite(cams.s) & (cams.s > 0)
    has_camera &= finite
    return {"both": both, "cams_sfm": cams_sfm, "sfm_valid": res.valid, "cams": cams, "shape": shape,
            "reflection": reflection, "has_camera": has_camera, "dist": dist}


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
    inv = coll.canvas_from_image.inverse()
    sfm_img = vp["cams_sfm"][:n].compose_similarity(inv).to_list()
    ref_img = vp["cams"][:n].compose_similarity(inv).to_list()
    az, el, ro = azimuth_elevation_roll_from_rotation(vp["cams"].R[:n].double())
    per = {}
    for i, aid in enumerate(coll.annotation_ids.tolist()):
        per[str(aid)] = {
            "source": coll.sources[i],
            "sfm": sfm_img[i] if bool(vp["sfm_valid"][i]) else None,
            "refined": ref_img[i] if bool(vp["has_camera"][i]) else None,
            "azimuth_deg": math.degrees(float(az[i])), "elevation_deg": math.degrees(float(el[i])),
            "roll_deg": math.degrees(float(ro[i])),
            "cluster": int(clusters.labels[i]) if clusters is not None else None,
        }
    names = coll.meta.keypoint_names
    S = vp["shape"].detach().double().cpu()
    return {
        "class": coll.name,
        "frame": "image pixels of each annotation's image; R rows = image x, image y (down), view direction",
        "cameras": per,
        "mean_shape": {nm: (None if not torch.isfinite(S[k]).all() else S[k].tolist()) for k, nm in enumerate(names)},
        "symmetry_plane": vp["reflection"].detach().double().cpu().tolist(),
        "principal_directions": axes.detach().double().cpu().tolist() if axes is not None else None,
        "cluster_threshold_deg": float(clusters.threshold_deg) if clusters is not None else None,
    }


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


def run_class(coll: ClassCollection, cfg: Config, out: Path, gt: dict | None, device: torch.device,
              generator: torch.Generator) -> ClassReport:
    """Run every stage for one class; write ``out/<class>/``; return its report."""
    report = ClassReport(coll.name, objects=len(coll))
    cdir = out / coll.name
    if len(coll) < cfg.min_instances:
        report.status = "skipped"
        report.skip(f"class has {len(coll)} usable instance(s), fewer than min_instances={cfg.min_instances}",
                    "class")
        return report
    coll = coll.to(device)
    n = len(coll)
    gt_img = _gt_cameras(gt, coll)
    if cfg.cameras == "gt" and gt_img is None:
        report.status = "failed"
        report.skip("cameras=gt but gt.json has no camera for every annotation of this class", "viewpoints")
        return report

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
    write_json(cdir / "cameras.json", _cameras_json(coll, vp, axes, clusters))
    if cfg.stage == "cameras":
        report.reconstructed = 0
        report.status = "cameras"
        return report

    # ---- which references remain to do
    mesh_dir, vox_dir = cdir / "meshes", cdir / "voxels"
    aids = coll.annotation_ids.tolist()
    done = [not cfg.overwrite and is_done(mesh_dir / f"{a}.{cfg.mesh_format}", vox_dir / f"{a}.npz") for a in aids]
    report.resumed = sum(done)
    chosen = [cfg.references == "all" or coll.splits[i] == cfg.references for i in range(n)]
    todo = [i for i in range(n) if chosen[i] and not done[i] and bool(usable[i])]
    report.info["references"] = sum(chosen)
    for i in range(n):
        if chosen[i] and not bool(usable[i]):
            report.skip("no usable camera", "viewpoints", aids[i], coll.sources[i])

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
    sdf_maps = None
    with _timed(report, "sdf", device):
        sdf_maps = signed_distance(both.masks)
    avg = None
    with _timed(report, "select", device):
        centre = select.plane_centre(shape)
        extent = select.plane_extent(shape, centre=centre)
        avg, counts = select.average_masks(coll.masks, cams[:n], clusters.labels, axes, plane_size=cfg.plane_size,
                                           extent=extent, centre=centre)
    report.info["average_mask_members"] = [int(c) for c in counts.tolist()]

    chunk = max(1, cfg.max_batch_voxels // max(1, cfg.proposals * 5 * cfg.resolution ** 3))
    bar = tqdm(total=len(todo), desc=f"{coll.name}: carve+select", disable=not cfg.progress, leave=False)
    scores_out = {}
    for c0 in range(0, len(todo), chunk):
        ids = torch.tensor(todo[c0:c0 + chunk], device=device, dtype=torch.long)
        _reconstruct_chunk(ids, coll, both, cams, shape, axes, trip, sdf_maps, avg, counts, (extent, centre), cfg,
                           report,
                           symmetric, use_mirrors, cdir, scores_out, device)
        bar.update(len(ids))
    bar.close()
    if cfg.keep_all_scores and scores_out:
        prev = {}
        sp = cdir / "proposal_scores.json"
        if sp.is_file() and not cfg.overwrite:
            try:
                prev = read_json(sp)
            except ValueError:
                prev = {}
        prev.update(scores_out)
        write_json(sp, prev, indent=None)
    return report


def _reconstruct_chunk(ids, coll, both, cams, shape, axes, trip, sdf_maps, avg, counts, plane, cfg, report,
                       symmetric, use_mirrors, cdir, scores_out, device):
    """Carve, select and write the objects ``ids`` (indices of originals)."""
    n = len(coll)
    extent, centre = plane
    R = len(ids)
    if symmetric:
        # surrogates synthesised by rotating the reference camera about the symmetry axis
        with _timed(report, "surrogates", device):
            up = -cams.R[:n, 1, :].mean(dim=0)  # mean image-up direction in the object frame
            axis = surrogates.symmetry_axis(shape, up=up)
            if cfg.symmetric_axis_in_image:
                axis = surrogates.axis_in_image_plane(cams[ids], axis)
            extra = surrogates.symmetric_surrogates(cams[ids], axis, step_deg=cfg.symmetric_step_deg, centre=centre)
            m = len(extra) // R
            cams_all = ScaledOrthographic.cat([cams, extra])
            sdf_all = torch.cat([sdf_maps, sdf_maps[ids].repeat_interleave(m, dim=0)])
            base = 2 * n + torch.arange(R, device=device)[:, None] * m + torch.arange(m, device=device)[None]
            views = base[:, None, :]  # (R, 1, m): one proposal per reference
            valid = torch.ones(R, 1, dtype=torch.bool, device=device)
    else:
        cams_all, sdf_all = cams, sdf_maps
        sur = trip.surrogates[ids]  # (R, P, 2)
        valid = trip.valid[ids]
        views = _views_for_proposals(ids, sur.clamp(min=0), n, use_mirrors)
    P = views.shape[1]
    flat_ref = ids[:, None].expand(R, P).reshape(-1)
    flat_views = views.reshape(R * P, -1)
    flat_valid = valid.reshape(-1)
    keep = flat_valid.nonzero().squeeze(1)
    with _timed(report, "carve", device):
        grids = carve.carve_proposals(sdf_all, cams_all, flat_ref[keep], flat_views[keep], resolution=cfg.resolution,
                                      imprint=cfg.imprint, max_batch_voxels=cfg.max_batch_voxels)
    with _timed(report, "select", device):
        ref_cams = cams[flat_ref[keep]]
        proj = select.project_proposals(grids.occupancy, grids.voxel_to_camera, ref_cams, axes,
                                        plane_size=cfg.plane_size, extent=extent, centre=centre)
        sc = select.score_proposals(proj, avg, counts)
        miss = select.keypoint_misses(grids.occupancy, grids.voxel_to_camera, coll.keypoints[flat_ref[keep]],
                                      coll.visible[flat_ref[keep]])
        scores = torch.full((R * P,), float("inf"), device=device)
        misses = torch.full((R * P,), 10 ** 6, dtype=torch.long, device=device)
        empty = torch.ones(R * P, dtype=torch.bool, device=device)
        scores[keep], misses[keep], empty[keep] = sc, miss, grids.empty
        ok = flat_valid & ~empty
        order, best = select.rank_proposals(scores.view(R, P), misses.view(R, P), ok.view(R, P))
    # position of each proposal inside `keep`
    pos = torch.full((R * P,), -1, dtype=torch.long, device=device)
    pos[keep] = torch.arange(len(keep), device=device)
    t_mesh = t_write = 0.0
    for j, i in enumerate(ids.tolist()):
        aid = int(coll.annotation_ids[i])
        src = coll.sources[i]
        okj = ok.view(R, P)[j]
        if not bool(okj.any()):
            if bool(valid[j].any()):
                reason = "all proposals carved away (empty)"
            else:
                why = trip.reasons.get(i) if trip is not None else None
                reason = f"no valid surrogate triplet ({why or 'clusters too small'})"
            report.skip(reason, "carve", aid, src)
            continue
        t0 = time.perf_counter()
        b = j * P + int(best[j])
        p = int(pos[b])
        canvas_to_image = _canvas_to_image_4x4(coll.canvas_from_image.scale[i], coll.canvas_from_image.offset[i])
        v2c = grids.voxel_to_camera[p].double().cpu()
        v2img = canvas_to_image @ v2c
        occ_np = grids.occupancy[p].cpu().numpy()
        if cfg.largest_component:
            occ_np = mesh.largest_component(occ_np)
        m = mesh.occupancy_to_mesh(occ_np, v2img.numpy())
        t1 = time.perf_counter()
        t_mesh += t1 - t0
        if len(m.faces) == 0:
            report.skip("selected proposal has no surface", "mesh", aid, src)
            continue
        sur_ids = []
        if trip is not None:
            sur_ids = [int(coll.annotation_ids[int(s)]) for s in trip.surrogates[i, int(best[j])].tolist() if s >= 0]
        if cfg.save_proposals:
            _write_proposals(cdir / "proposals" / f"{aid}.npz", grids, pos[j * P:(j + 1) * P], canvas_to_image,
                             scores.view(R, P)[j], misses.view(R, P)[j], int(best[j]),
                             trip.surrogates[i] if trip is not None else None, coll)
        write_npz(cdir / "voxels" / f"{aid}.npz", occupancy=occ_np, voxel_to_camera=v2img.numpy(),
                  voxel_to_canvas=v2c.numpy(), canvas_scale=float(coll.canvas_from_image.scale[i]),
                  canvas_offset=coll.canvas_from_image.offset[i].cpu().numpy(),
                  surrogates=np.asarray(sur_ids, dtype=np.int64))
        mesh.write_mesh(m, cdir / "meshes" / f"{aid}.{cfg.mesh_format}")
        t_write += time.perf_counter() - t1
        report.reconstructed += 1
        if cfg.keep_all_scores:
            rows = scores.view(R, P)[j]
            scores_out[str(aid)] = {
                "best": int(best[j]),
                "scores": [None if not math.isfinite(v) else round(v, 6) for v in rows.tolist()],
                "misses": [int(v) if v < 10 ** 6 else None for v in misses.view(R, P)[j].tolist()],
                "surrogates": ([[int(coll.annotation_ids[int(s)]) if s >= 0 else None for s in pair]
                                for pair in trip.surrogates[i].tolist()] if trip is not None else None),
            }
    report.seconds["mesh"] = report.seconds.get("mesh", 0.0) + t_mesh
    report.seconds["write"] = report.seconds.get("write", 0.0) + t_write


def _write_proposals(path: Path, grids, positions: torch.Tensor, canvas_to_image: torch.Tensor, scores, misses,
                     best: int, surrogates, coll):
    """Every proposal of one reference (bit-packed occupancy, image-pixel transforms, scores) for studies."""
    P = len(positions)
    ok = positions >= 0
    idx = positions.clamp(min=0)
    occ = grids.occupancy[idx].cpu().numpy() & ok.cpu().numpy()[:, None, None, None]
    v2img = (canvas_to_image[None] @ grids.voxel_to_camera[idx].double().cpu()).numpy()
    sur = np.full((P, 2), -1, dtype=np.int64)
    if surrogates is not None:
        for k, pair in enumerate(surrogates.tolist()):
            sur[k] = [int(coll.annotation_ids[int(x)]) if x >= 0 else -1 for x in pair]
    write_npz(path, occupancy_bits=np.packbits(occ.reshape(P, -1), axis=1), shape=np.asarray(occ.shape[1:]),
              voxel_to_camera=v2img, valid=ok.cpu().numpy(), scores=scores.cpu().numpy(),
              misses=misses.cpu().numpy(), best=np.int64(best), surrogates=sur)


def _canvas_to_image_4x4(scale: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """4x4 map of camera-frame points from canvas pixels to image pixels (x, y shifted+scaled, z scaled)."""
    a = float(scale)
    T = torch.eye(4, dtype=torch.float64)
    T[0, 0] = T[1, 1] = T[2, 2] = 1.0 / a
    T[0, 3] = -float(offset[0]) / a
    T[1, 3] = -float(offset[1]) / a
    return T


# =========================================================================== whole run


def run(cfg: Config) -> dict:
    """Run every class; write ``config.yaml``, ``summary.json``, per-class outputs and ``preview.png``."""
    t_start = time.perf_counter()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    from .io.outputs import write_bytes

    write_bytes(out / "config.yaml", cfg.to_yaml().encode())
    device = cfg.resolve_device()
    torch.manual_seed(cfg.seed)
    data_path, gt_path = prepare_data(cfg)
    t0 = time.perf_counter()
    loaded = coco.load_coco(data_path, canvas_size=cfg.canvas_size, margin=cfg.canvas_margin, device=device,
                            classes=cfg.classes)
    load_s = time.perf_counter() - t0
    for p in loaded.problems:
        _log(p.message(), cfg)
    gt = read_json(gt_path) if gt_path is not None and Path(gt_path).is_file() else None
    summary = {"data": str(data_path), "gt": str(gt_path) if gt_path else None, "device": str(device),
               "torch_threads": torch.get_num_threads(), "load_seconds": round(load_s, 3),
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
            rep = run_class(coll, cfg, out, gt, device, g)
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
    if cfg.preview and cfg.stage == "all":
        try:
            from .preview import write_preview

            write_preview(out, summary)
        except Exception as e:  # a picture must never fail the run
            _log(f"preview.png not written: {e}", cfg)
    return summary


def _peak_rss_mb() -> float:
    """Peak resident memory of this process (MB)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _stable_hash(name: str) -> int:
    import zlib

    return zlib.crc32(name.encode()) % (2 ** 31)
