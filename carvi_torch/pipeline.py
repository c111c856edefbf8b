"""The stages in order, per class: load -> viewpoints -> surrogates -> carve -> select -> mesh and files.

Data flows one way through the stage modules::

    io.coco          annotations  -> ClassCollection (canvas tensors)
    viewpoints       SfM, mixture of shapes, refinement  -> Viewpoints (cameras of originals and mirrors)
    surrogates       principal directions, clusters, triplets  -> SurrogatePlan
    carve            imprinted visual hull of every proposal  -> ProposalGrids
    select           average masks, proposal scores, the best proposal  -> Selection
    io.writer        marching cubes, files (worker processes; on CUDA the meshes come from marching)

:func:`run_class` runs one class; an executor (:mod:`carvi_torch.executors`) runs the classes of a
run. The pipeline only orders the stages and keeps the books (resume, the report); the numerical work
lives in the stage modules.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import torch
from tqdm.auto import tqdm

from . import carve, select, surrogates
from .carve import CarveMaps
from .carve.puffball import puffball_grids
from .collection import ClassCollection
from .config import Config, object_settings
from .io.layout import ResumeCheck, class_dir, object_file, resume_check, settings_text
from .io.outputs import write_json
from .io.results import (ClassReport, cameras_json, canonical_image_cameras, drop_cameras, quality_summary,
                         resumed_levels, resumed_objects, scores_entry, write_scores)
from .io.writer import Writer, canvas_to_image_4x4, id_array, mesh_jobs, proposals_payload
from .marching import resolve_mesher
from .runtime import StageTimer, log
from .sdf import signed_distance
from .viewpoints import NoMeanShape, Viewpoints, estimate_viewpoints, ground_truth_cameras

__all__ = ["run_class", "viewpoint_stage", "class_viewpoints", "prepare_class", "carve_and_select",
           "ClassPlan", "ClassViewpoints", "PreparedClass", "finished_objects", "reconstruct_chunk", "finish_class"]


@dataclass
class ClassPlan:
    """What carving and selection need for every chunk of one class (built once per class); ``aids`` to
    ``object_from_camera`` are host copies of what the hand-off reads per object (``object_from_camera``:
    ``(N, 4, 4)`` camera frame in image pixels -> canonical frame)."""

    coll: ClassCollection
    viewpoints: Viewpoints
    surrogates: surrogates.SurrogatePlan
    maps: CarveMaps  # entries: 2N silhouettes (+ rotated reference cameras, symmetric classes)
    selection: select.SelectionReference
    cdir: Path
    aids: list = field(init=False)
    canvas_scale: torch.Tensor = field(init=False)
    canvas_offset: torch.Tensor = field(init=False)
    object_from_camera: torch.Tensor = field(init=False)

    def __post_init__(self):
        sim = self.coll.canvas_from_image
        self.aids = list(self.coll.annotation_ids)
        self.canvas_scale = sim.scale.detach().double().cpu()
        self.canvas_offset = sim.offset.detach().double().cpu()
        self.object_from_camera = canonical_image_cameras(self.coll, self.viewpoints).camera_to_object_4x4().cpu()

    def proposals(self, ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The proposals of references ``ids`` (a consecutive run of ``todo``), reference-major:
        ``reference (R * P,)`` long, ``views (R * P, V)`` long entries of :attr:`maps`, ``valid (R * P,)`` bool."""
        views, valid = self.surrogates.proposal_views(ids)
        R, P = valid.shape
        return ids[:, None].expand(R, P).reshape(-1), views.reshape(R * P, -1), valid.reshape(-1)


class ClassViewpoints(NamedTuple):
    """:func:`class_viewpoints`' result (``viewpoints`` and ``surrogates`` ``None``: the class stops there)."""

    coll: ClassCollection
    viewpoints: Viewpoints | None
    surrogates: surrogates.SurrogatePlan | None
    report: ClassReport


class PreparedClass(NamedTuple):
    """:func:`prepare_class`' result: the plan (``None``: no carving), the originals to reconstruct, the report."""

    plan: ClassPlan | None
    todo: list[int]
    report: ClassReport


def finished_objects(coll: ClassCollection, cfg: Config, out: Path | None, report: ClassReport) -> list[str | None]:
    """Per original: the format of its mesh where an earlier run into ``out`` finished it from its current inputs
    and canvas, else ``None`` (always with ``overwrite``): :func:`~carvi_torch.io.layout.resume_check`. Damaged
    files are logged per object, those made from other inputs or canvases in one line and ``report.info["redone"]``
    (files of objects the data no longer holds: :func:`carvi_torch.executors.common.book_class`)."""
    if out is None:
        return [None] * len(coll)
    cdir = class_dir(out, coll.meta.key)
    check = (ResumeCheck(done=[None] * len(coll)) if cfg.overwrite
             else resume_check(cdir, coll.annotation_ids, coll.fingerprints, cfg.mesh.format, coll.canvas_from_image))
    for line in check.lines(coll.meta.key):
        log.warning(line)
    report.info.update(check.info())
    return check.done


def _todo(coll: ClassCollection, vp: Viewpoints, done: list, cfg: Config, report: ClassReport) -> list[int]:
    """The originals to reconstruct: chosen (``references``), with a usable camera, not finished (resume)."""
    aids, usable = coll.annotation_ids, vp.has_camera[:len(coll)].tolist()
    report.resumed = sum(u for d, u in zip(done, usable) if d)  # a finished object without a camera: skipped
    chosen = [cfg.references == "all" or coll.splits[i] == cfg.references for i in range(len(coll))]
    report.info["references"] = sum(chosen)
    for i in range(len(coll)):
        if chosen[i] and not usable[i]:
            report.skip(vp.no_camera.get(i, "no usable camera"), "viewpoints", aids[i], coll.sources[i])
    return [i for i in range(len(coll)) if chosen[i] and not done[i] and usable[i]]


def _maps(vp: Viewpoints, plan: surrogates.SurrogatePlan, todo: list[int], sel: select.SelectionReference,
          cfg: Config, timer: StageTimer) -> CarveMaps:
    """The class's silhouettes prepared for carving (the outside distances reused), and for a
    rotationally symmetric class the rotated reference cameras as further entries (no map copied)."""
    with timer("sdf"):
        dist = vp.take_distances()
        maps = carve.prepare_maps(lambda a, b: signed_distance(vp.both.masks[a:b], outside=dist[a:b]), vp.cameras,
                                  count=len(vp.both))
    if plan.triplets is None and todo:
        with timer("surrogates"):
            todo_t = torch.tensor(todo, dtype=torch.long, device=maps.device)
            extra, plan.rotated = surrogates.rotated_cameras(vp.cameras, vp.shape, todo_t, sel.centre, cfg.surrogates,
                                                              masks=vp.both.masks)
            maps = maps.with_entries(maps.entry_map[todo_t].repeat_interleave(plan.rotated), extra)
    return maps


def _surrogate_plan(coll, vp: Viewpoints, cfg: Config, generator, timer, report) -> surrogates.SurrogatePlan:
    """Principal directions, clusters, and the triplets (or fallbacks) of every original: all of them,
    so that a resumed run samples the same ones."""
    n, usable = len(coll), vp.has_camera[:len(coll)]
    mirrors = cfg.surrogates.mirrors and not coll.meta.articulated and vp.mirrored
    with timer("surrogates"):
        axes = surrogates.principal_directions(vp.shape)
        views = vp.cameras.view_direction[:n]
        clusters = surrogates.cluster_instances(views, usable, axes, cfg.surrogates, groups=coll.object_groups)
        if coll.meta.symmetry == "rotational":
            trip, levels = None, ["rotated_views" if u else None for u in usable.tolist()]
        else:
            trip, levels = surrogates.plan_proposals(clusters, coll.object_groups, usable, views, axes,
                                                     cfg.surrogates.proposals, mirrors, generator)
    report.warnings += [f"clusters: {line}" for line in clusters.log]  # logged with the class's other warnings
    report.info["clusters"] = {"threshold_deg": float(clusters.threshold_deg),
                               "sizes": [int(v) for v in clusters.sizes.tolist()]}
    return surrogates.SurrogatePlan(n, axes, clusters, trip, mirrors, levels=levels)


def viewpoint_stage(coll: ClassCollection, cfg: Config, gt: dict | None = None,
                    report: ClassReport | None = None) -> tuple[Viewpoints | None, ClassReport]:
    """The viewpoint stage of one class on its collection's device, reading and writing no file (a worker
    process may run it): ``(vp, report)``; ``vp.log`` is the caller's to log. With ``cameras=gt`` the true
    cameras, the objects without a usable one in ``gt.json`` skipped with the reason. ``vp`` is ``None``
    (the class skipped, the reason in ``report``): too few instances, no object with a true camera, or
    SfM placed none."""
    report = ClassReport(coll.meta.key, objects=len(coll)) if report is None else report
    if len(coll) < cfg.input.min_instances:
        why = f"class has {len(coll)} usable instance(s), fewer than min_instances={cfg.input.min_instances}"
        return None, report.skip_class([(why, "class", None, None)])
    gt_img, gt_why = ground_truth_cameras(gt, coll) if cfg.study.cameras == "gt" else (None, [])
    if cfg.study.cameras == "gt" and gt_img is None:
        return None, report.skip_class([(f"cameras=gt: {why}", "viewpoints", aid, src)
                                        for aid, src, why in zip(coll.annotation_ids, coll.sources, gt_why)])
    try:
        vp = estimate_viewpoints(coll, cfg.viewpoints, source=cfg.study.cameras, gt_cameras=gt_img, seed=cfg.seed,
                                 timer=StageTimer(coll.device, report.seconds))
    except NoMeanShape as e:
        return None, report.skip_class([(str(e), "viewpoints", None, None)])
    vp.no_camera.update({i: f"cameras=gt: {why}" for i, why in enumerate(gt_why) if why})
    report.warnings.extend(vp.warnings)
    report.info.update(vp.info)
    return vp, report


def class_viewpoints(coll: ClassCollection, cfg: Config, device: torch.device, generator: torch.Generator,
                     gt: dict | None = None, report: ClassReport | None = None,
                     made: tuple | None = None) -> ClassViewpoints:
    """The part of :func:`prepare_class` that reads and writes no file (an executor may run it ahead, on another
    thread): the class on ``device``, its viewpoints and surrogate plan, both ``None`` when the class stops there
    (too few instances, no true or SfM cameras). ``made``: the result of :func:`viewpoint_stage` on this class
    made elsewhere (a worker process), on the CPU."""
    vdev = cfg.viewpoint_device(device, len(coll))
    vcoll = coll.to(vdev) if made is None else coll
    vp, report = viewpoint_stage(vcoll, cfg, gt, report) if made is None else made
    report.info["viewpoint_device"] = str(vdev)
    if vp is None:
        return ClassViewpoints(coll, None, None, report)
    for line in vp.log:
        log.info(line)
    vp, timer = (vp if vdev == device else vp.to(device)), StageTimer(device, report.seconds)
    coll = vcoll if vcoll.device == device else coll.to(device)
    return ClassViewpoints(coll, vp, _surrogate_plan(coll, vp, cfg, generator, timer, report), report)


def prepare_class(coll: ClassCollection, cfg: Config, device: torch.device, generator: torch.Generator,
                  gt: dict | None = None, out: Path | None = None, report: ClassReport | None = None,
                  done: list[str | None] | None = None, ahead: ClassViewpoints | None = None) -> PreparedClass:
    """Every stage of one class up to carving: viewpoints, clusters, triplets, prepared silhouettes.

    Writes ``out/<class>/cameras.json`` when ``out`` is given (an earlier run's removed if the class stops first:
    :func:`~carvi_torch.io.results.drop_cameras`). ``done``: per original, the format of the mesh of an object an
    earlier run finished, else ``None`` (default :func:`finished_objects`; an executor that may run this twice
    passes it, so that both runs plan the same objects). ``ahead``: :func:`class_viewpoints`'s result, made first.

    Returns:
        :class:`PreparedClass`: the plan is ``None`` when the class stops before carving (too few instances,
        missing ground truth, ``stage=cameras``, nothing to do).
    """
    coll, vp, plan, report = class_viewpoints(coll, cfg, device, generator, gt, report) if ahead is None else ahead
    if vp is None:
        drop_cameras(out, coll.meta.key, report)
        return PreparedClass(None, [], report)
    timer, n = StageTimer(device, report.seconds), len(coll)
    cdir = class_dir(out if out is not None else ".", coll.meta.key)
    done = finished_objects(coll, cfg, out, report) if done is None else list(done)
    if out is not None:
        with timer("class_files"):
            plan.levels = resumed_levels(cdir, coll, plan.levels, done)
            report.reconstruction_iou.update(resumed_objects(cdir, coll, vp, done, cfg.mesh.format))
            cams = cameras_json(coll, vp, plan.axes, plan.clusters, plan.levels, report.reconstruction_iou)
            write_json(cdir / "cameras.json", cams)
        report.info["quality"] = quality_summary(cams["cameras"])
    if cfg.stage == "cameras":
        report.status = "cameras"
        return PreparedClass(None, [], report)
    todo = _todo(coll, vp, done, cfg, report)
    if not todo:  # everything done already (a resumed run) or nothing usable: no maps to prepare
        return PreparedClass(None, [], report)
    plan.set_todo(todo)
    with timer("select"):
        sel = select.class_reference(vp.shape, coll.masks, vp.cameras[:n], plan.clusters.labels, plan.axes,
                                     cfg.select.plane_size, coll.object_groups if cfg.select.balance_objects else None)
    report.info["average_mask_members"] = [int(c) for c in sel.counts.tolist()]
    maps = _maps(vp, plan, todo, sel, cfg, timer)
    return PreparedClass(ClassPlan(coll, vp, plan, maps, sel, cdir), todo, report)


def carve_and_select(ids: torch.Tensor, plan: ClassPlan, cfg: Config, timer: StageTimer) -> select.Selection:
    """Carve, score and rank every proposal of the originals ``ids`` (a run of ``todo``): a chunk's device work."""
    with timer("surrogates"):
        flat_ref, views, flat_valid = plan.proposals(ids)
    valid, keep = flat_valid.view(len(ids), -1), flat_valid.nonzero().squeeze(1)
    kept_ref = flat_ref[keep]
    with timer("carve"):
        grids = carve.carve_proposals(plan.maps, None, kept_ref, views[keep],
                                      resolution=cfg.carve.resolution, imprint=cfg.carve.imprint,
                                      interpolation=cfg.carve.interpolation, backend=cfg.carve.backend)
    with timer("select"):
        coll = plan.coll
        return select.select_proposals(grids, keep, valid, plan.viewpoints.cameras[kept_ref],
                                       coll.keypoints[kept_ref], coll.visible[kept_ref], plan.selection,
                                       consensus=cfg.select.consensus)


def _job(sel: select.Selection, occupancy: torch.Tensor, masks: torch.Tensor, j: int, i: int, sur, plan: ClassPlan,
         cfg: Config) -> dict:
    """The writer's job for reference ``j`` (original ``i``) of a chunk, of host data (grids and masks read once)."""
    scale, offset, aid_of, aid = plan.canvas_scale[i], plan.canvas_offset[i], plan.aids, plan.aids[i]
    canvas_to_image, v2c, best = canvas_to_image_4x4(scale, offset), sel.best_transform[j], int(sel.best[j])
    sur_ids = [] if sur is None or best < 0 else [aid_of[s] for s in sur[j, best].tolist() if s >= 0]
    v2img = canvas_to_image @ v2c
    return dict(aid=aid, occupancy=occupancy[j].numpy(), voxel_to_canvas=v2c.numpy(),
                voxel_to_image=v2img.numpy(), voxel_to_object=(plan.object_from_camera[i] @ v2img).numpy(),
                canvas_scale=float(scale), canvas_offset=offset.float().numpy(), surrogates=id_array(sur_ids),
                voxel_path=str(object_file(plan.cdir, "voxels", aid)),
                mesh_path=str(object_file(plan.cdir, "meshes", aid, cfg.mesh.format)),
                proposals_path=str(object_file(plan.cdir, "proposals", aid)),
                proposals=(proposals_payload(sel, j, sur, canvas_to_image, aid_of)
                           if cfg.study.save_proposals and best >= 0 else None),
                largest_component=cfg.mesh.largest_component, mask=masks[j].numpy(),
                input_fingerprint=plan.coll.fingerprints[i], settings=settings_text(object_settings(cfg)))


def _submit(sel: select.Selection, ids: torch.Tensor, plan: ClassPlan, cfg: Config, report: ClassReport,
            writer: Writer, timer: StageTimer) -> None:
    """Hand a chunk's references to the writer (puffballs where no proposal is left; meshed first: mesher=torch)."""
    sur = None if (sur := plan.surrogates.surrogates_of(ids)) is None else sur.cpu()
    puffed = _puffballs(sel, ids, plan, cfg)
    aid_of, occupancy = plan.aids, sel.best_occupancy.cpu()  # the selected grids (R, D, H, W), to the host once
    masks = plan.coll.masks[ids].cpu()  # and the references' masks (R, S, S)
    jobs = [_job(sel, occupancy, masks, j, i, None if j in puffed else sur, plan, cfg)
            for j, i in enumerate(ids.tolist())]
    if resolve_mesher(cfg.mesh.mesher, ids.device) == "torch":
        with timer("mesh_device"):
            mesh_jobs(sel.best_occupancy, occupancy, jobs, cfg.mesh.largest_component, cfg.mesh.format)
    for j, (i, job) in enumerate(zip(ids.tolist(), jobs)):
        aid, src = aid_of[i], plan.coll.sources[i]
        if cfg.study.keep_all_scores and j not in puffed:
            job["scores"], job["scores_path"] = scores_entry(sel, j, sur, aid_of), str(
                object_file(plan.cdir, "scores", aid))
        # a chunk's objects may all wait: the next chunk's device work overlaps their writing
        writer.submit(job, lambda res, aid=aid, src=src: report.book_write(res, aid, src), backlog=len(jobs))


def _puffballs(sel: select.Selection, ids: torch.Tensor, plan: ClassPlan, cfg: Config) -> set[int]:
    """The chunk's references without a non-empty proposal get a puffball instead (their level becomes
    ``puffball``); returns their positions in the chunk."""
    none = [j for j, ok in enumerate(sel.ok.any(dim=1).tolist()) if not ok]
    if not none:
        return set()
    sel.take_grids(none, puffball_grids(plan.coll.masks[ids[torch.tensor(none, device=ids.device)]],
                                        cfg.carve.resolution))
    for j in none:
        plan.surrogates.levels[int(ids[j])] = "puffball"
    return set(none)


def run_class(coll: ClassCollection, cfg: Config, out: Path, gt: dict | None, device: torch.device,
              generator: torch.Generator, writer: Writer | None = None,
              ahead: ClassViewpoints | None = None) -> ClassReport:
    """Run every stage for one class; write ``out/<class>/``; return its report.

    ``writer`` meshes and writes the objects (worker processes, see :func:`carvi_torch.executors.local.run`); by default
    they are written inline. ``ahead``: :func:`class_viewpoints`'s result, made beforehand.
    """
    plan, todo, report = prepare_class(coll, cfg, device, generator, gt=gt, out=out, ahead=ahead)
    if plan is None:
        return report
    own_writer = writer is None
    writer = Writer(0) if own_writer else writer
    bar = tqdm(total=len(todo), desc=f"{coll.meta.key}: carve+select", disable=not cfg.progress, leave=False)
    try:
        _carve_chunks(plan, todo, cfg, report, writer, bar.update)
        bar.close()
    except BaseException as e:
        # this class's pending objects are finished (their files written) before the error
        # leaves, so they are not booked into the next class; an interrupt drops them
        if own_writer:
            writer.close(cancel=True)
        elif not isinstance(e, KeyboardInterrupt):
            writer.drain()
        raise
    if own_writer:
        writer.close()
    finish_class(plan, cfg, report)
    return report


def _carve_chunks(plan: ClassPlan, todo: list[int], cfg: Config, report: ClassReport, writer: Writer,
                  progress=None) -> None:
    """Carve, select and hand to ``writer`` the originals ``todo`` (a consecutive run of the plan's),
    :func:`carvi_torch.carve.chunk_objects` at a time; wait for the writer at the end."""
    device = plan.maps.device
    timer = StageTimer(device, report.seconds)
    todo_t = torch.tensor(todo, dtype=torch.long, device=device)
    chunk = carve.chunk_objects(cfg.surrogates.proposals, cfg.carve.resolution, device)
    for c0 in range(0, len(todo), chunk):
        ids = todo_t[c0:c0 + chunk]
        sel = carve_and_select(ids, plan, cfg, timer)
        # time blocked on busy writers is booked as waiting for them, the device's meshing as mesh_device
        t0, b0, m0 = time.perf_counter(), writer.blocked, timer.seconds.get("mesh_device", 0.0)
        _submit(sel, ids, plan, cfg, report, writer, timer)
        timer.add("handoff", time.perf_counter() - t0 - writer.blocked + b0 - timer.seconds.get("mesh_device", 0) + m0)
        timer.add("write_wait", writer.blocked - b0)
        del sel  # the next chunk's grids must not sit beside this one's
        if progress is not None:
            progress(len(ids))
    with timer("write_wait"):
        writer.drain()


def reconstruct_chunk(plan: ClassPlan, ids: list[int], cfg: Config) -> tuple[ClassReport, list[int]]:
    """Carve, select, mesh and write here the originals ``ids`` (a consecutive run of the class's ``todo``): a
    distributed executor's task, on a :func:`prepare_class` plan (the files :func:`run_class` writes for them).
    Returns the report of these objects and the originals of ``ids`` that became puffballs."""
    report = ClassReport(plan.coll.meta.key, objects=0)
    _carve_chunks(plan, list(ids), cfg, report, Writer(0))
    return report, [i for i in ids if plan.surrogates.levels[i] == "puffball"]


def finish_class(plan: ClassPlan, cfg: Config, report: ClassReport, puffballs: list[int] = ()) -> None:
    """The end of a class whose objects are written: ``puffballs`` (originals that became puffballs in chunks
    carved elsewhere) marked; where every object's proposals came from (summary); cameras.json again with every
    object's quality (its reconstruction is known now: ``report.reconstruction_iou``, the writers' results merged
    over the chunks and the objects of earlier runs); the merged proposal scores."""
    for i in puffballs:
        plan.surrogates.levels[i] = "puffball"
    levels = plan.surrogates.levels
    used = [lv for lv in surrogates.LEVELS if lv in levels]
    report.info["surrogates_from"] = {
        "counts": {lv: levels.count(lv) for lv in used},
        "fallbacks": {lv: [a for a, x in zip(plan.aids, levels) if x == lv] for lv in used
                      if lv not in ("triplet", "rotated_views")}}
    vp, sp = plan.viewpoints, plan.surrogates
    with StageTimer("cpu", report.seconds)("class_files"):  # host work: nothing to wait for on the device
        cams = cameras_json(plan.coll, vp, sp.axes, sp.clusters, levels, report.reconstruction_iou)
        write_json(plan.cdir / "cameras.json", cams)
        if cfg.study.keep_all_scores:
            write_scores(plan.cdir, plan.aids, cfg.overwrite)
    report.info["quality"] = quality_summary(cams["cameras"])
