"""``python -m carvi_torch.evaluate``: shape and viewpoint errors of reconstructions against ground truth.

Shapes: the symmetric RMS mesh distance of the paper (``carvi_torch.evaluation.metrics``), in percent of
the ground-truth bounding-box diagonal, in the reference camera frame (the ground-truth mesh
posed by its true camera, image pixels) after the best depth offset. Viewpoints: geodesic,
azimuth, elevation and roll errors after one global rotation aligning the class frame with
the ground-truth frame (``carvi_torch.evaluation.viewpoint_metrics``), for SfM and refined cameras;
the up-axis error that ignores azimuth (``up_axis``, for rotationally symmetric classes such as
bottles); and refinement's change of the median from SfM with a 95% bootstrap interval over the
physical objects (``change_from_sfm``, whose ``object_id`` groups the views of one object): an
interval above 0 says refinement made the class worse beyond what another draw of objects moves it.

Several reconstruction directories (e.g. Full, -CRef, -SImp, oracle) are compared in one run,
so every ground-truth mesh is sampled and indexed once; the baselines Puffball and SFMc are
computed on the fly (``--baselines``).

Cost: nearly all of it is the shape error of each object (the depth-offset search and the exact
distances of ``metrics.best_depth_offset``), whose surface samples grow as ``1 / step^2``; a progress
bar counts the objects (``--quiet`` hides it). The objects are scored in worker processes, one per core
(at most 8; ``--jobs``), each with one torch thread, or in this process below 16 objects; the errors are
the same either way. The default run's 40 chairs took 32 s at the default ``--step-percent 0.5`` and 12 s
at 2 (wall clock, the interpreter's start included) on the 2-core development host, the class mean 3.04
at both steps; in this process alone (``--jobs 1``) 55-63 s and 14-16 s::

    python -m carvi_torch.reconstruct --out D --classes chair
    python -m carvi_torch.evaluate --data D/input/annotations.json --recon D --quiet --step-percent S

One process with two torch threads instead (the code of commit 6febb78) took 49-53 s and 12 s there, and
its threads, which spin while they wait for each other, slow down by an order of magnitude on a busy host:
two such evaluations side by side at step 2 took 102 s, against 19 s with the worker processes.
``--viewpoints-only`` takes seconds.

Only what matches is scored, and what does not is said: a class of ``--data`` that a reconstruction
has no folder for gets a ``note:`` line (and ``classes_without_reconstruction`` in ``results.json``),
and so does a run that stopped after the cameras (``stage=cameras``) without ``--viewpoints-only``, and
an unfinished run (``unfinished``); an unknown ``--classes`` name, a ``--split`` that no annotation has, two
``--recon`` of one name, a ``gt.json`` or ``--data`` that is not a JSON object, or a reconstruction whose
annotation ids name other objects in ``--data`` (another class or ``source``: it was made from other data, or
the file changed since the run), or a first run's ``config.yaml`` that cannot be read, is an error (exit 2); another
method's folder may hold another tool's ``config.yaml`` (a note names it).

Bad input leaves out what it touches, with a one-line reason on stderr that names the object, and the rest is
evaluated: an object that ``gt.json`` has no entry for, or whose entry is unusable (``R`` not a rotation within
1e-3, ``s`` not a positive number, a mesh file that cannot be read, ...), is skipped for every method (its
``reason`` in ``results.json``'s ``objects``); a method's mesh that cannot be read, that the metric cannot score
(no surface area, ...), or that the run skipped, leaves that method without the object's shape error (the reason
naming the file, the metric's, or the run's reason, each on its own line); an unusable
camera of a run's ``cameras.json`` (or an unusable file) leaves its viewpoint out (``camera_problems``).

Methods are compared on the same objects: a class's row of the shape table is, for every method, the mean over
the objects that every method (the baselines included) has an error for (``compared``; ``car (4 of 6)`` where
some method misses some), the best in bold, and the table's mean is over the classes with such objects
(``mean_over_classes_compared``); a class without any such object shows each method's mean over its own
objects with their number, and bolds none. A ``note:`` line says per class how many objects each method misses
and why (``missing_reasons``: the kinds of reason, with the objects' ids), and how many have no usable refined
camera, and why, or too few for a viewpoint report (``viewpoint_coverage``: the global alignment needs two).
``classes`` keeps each method's ``mean``, ``median`` and ``count`` over its own objects, and
``mean_over_classes`` their mean over its classes.

Examples:
    python -m carvi_torch.evaluate --data renders/annotations.json --recon runs/full
    python -m carvi_torch.evaluate --data renders/annotations.json --recon Full=runs/full \\
        --recon -CRef=runs/nocref --baselines --split test --out results/
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from .cli import (CommandError, add_common, nonempty_paths, positive_int, program, run_command, split_classes,
                  writable_folder)
from .config import Config, ConfigError, read_run_config
from .io.coco import CocoFormatError, class_keys, class_names, load_coco, object_id, select_classes
from .io.layout import NOT_YET, objects_made_otherwise, objects_text, other_settings, other_settings_text, unfinished
from .io.outputs import read_json, shown_names, write_bytes, write_json
from .io.results import annotation_source, same_object
from .evaluation import reliability, viewpoint_metrics
from .evaluation.scoring import (MAX_JOBS, POOL_FROM, Reason, ReasonKind, ShapeScorer, camera_problem, default_jobs,
                                 gt_problem, numbers, posed_gt_mesh, score_shapes)
from .runtime import folders_to_make, remove_empty

__all__ = ["evaluate", "posed_gt_mesh", "format_shape_table", "format_viewpoint_table", "format_change", "main",
           "NO_GROUND_TRUTH", "NOT_YET"]

#: The reason of an object in scope that ``gt.json`` has no entry for.
NO_GROUND_TRUTH = "no ground truth: gt.json has no entry for it"
#: The kind of an object's problem that concerns its SfM camera alone: it does not explain a missing refined camera.
UNUSABLE_SFM_CAMERA: ReasonKind = "unusable sfm camera in cameras.json"


def _read_cameras(rdir: Path, classes) -> tuple[dict[str, dict | None], dict[str, dict]]:
    """Each class's ``cameras.json`` of the reconstruction ``rdir``, read once for every use: class -> its
    content (``None``: no file) made safe to read (:func:`_usable_cameras`), and class -> what was unusable in it
    (``{"file": why the file is, or None, "objects": {annotation id: why its camera is, a Reason}}``; classes
    without any left out)."""
    contents, problems = {}, {}
    for cls in sorted(classes):
        p = rdir / cls / "cameras.json"
        if not p.is_file():
            contents[cls] = None
            continue
        try:
            content = read_json(p)
        except (OSError, ValueError) as e:
            contents[cls], problems[cls] = {"cameras": {}}, {"file": str(e), "objects": {}}
            continue
        contents[cls], problem = _usable_cameras(p, content)
        if problem:
            problems[cls] = problem
    return contents, problems


def _usable_cameras(path: Path, content) -> tuple[dict, dict]:
    """``cameras.json`` (``content``, read from ``path``) with what cannot be used taken out, and what that was:
    a file that is not an object with a ``cameras`` object becomes one without cameras; an entry that is not an
    object an empty one; an ``sfm`` or ``refined`` camera that :func:`~carvi_torch.evaluation.scoring.camera_problem`
    finds unusable ``None``. Problems as :func:`_read_cameras`'s (``{}``: none).

    Example:
        >>> content, problems = _usable_cameras(Path("c.json"), {"cameras": {"3": "oops"}})
        >>> content, problems["objects"]["3"].text
        ({'cameras': {'3': {}}}, "its cameras.json entry is 'oops', not an object")
    """
    if not isinstance(content, dict) or not isinstance(content.get("cameras"), dict):
        what = "not a JSON object" if not isinstance(content, dict) else "its 'cameras' is not an object"
        return {"cameras": {}}, {"file": f"{path}: {what}", "objects": {}}
    bad = {}
    for aid, entry in content["cameras"].items():
        if not isinstance(entry, dict):
            content["cameras"][aid] = {}
            bad[aid] = Reason("cameras.json entry not an object",
                              f"its cameras.json entry is {entry!r:.40}, not an object")
            continue
        for stage, kind in (("sfm", UNUSABLE_SFM_CAMERA), ("refined", "unusable refined camera in cameras.json")):
            why = camera_problem(entry[stage]) if entry.get(stage) is not None else None
            if why:
                entry[stage] = None
                bad[aid] = Reason.of(kind, why)
    return content, ({"file": None, "objects": bad} if bad else {})


def _viewpoints(cameras: dict | None, gt_entries: dict, aids: list, object_of: dict | None = None) -> dict | None:
    """Viewpoint reports of one class: ``sfm`` (objects with an SfM camera), ``refined`` (every
    object with a final camera) and, when ``refined`` holds objects without an SfM camera,
    ``refined_with_sfm``: the refined cameras of the objects that also have an SfM camera.
    Objects without an SfM camera get theirs from the unseen-image path, not from refinement;
    ``refined_with_sfm`` is the before/after comparison of the refinement itself, and its report (or
    ``refined``'s, when the objects are the same) carries ``change_from_sfm``: the change of the median with a
    bootstrap interval over the physical objects (:func:`_refinement_change`). Each report is
    aligned with its own global rotation. ``cameras``: the class's ``cameras.json`` (``None``: none);
    ``object_of``: annotation id (str) -> physical object (default: every annotation its own)."""
    if cameras is None:
        return None
    cams = cameras.get("cameras", {})
    out = {}
    has_sfm = {a for a in aids if cams.get(str(a), {}).get("sfm") is not None}
    for stage, source, among in (("sfm", "sfm", None), ("refined", "refined", None),
                                 ("refined_with_sfm", "refined", has_sfm)):
        est, ref, used = [], [], []
        for a in aids:
            c = cams.get(str(a), {}).get(source)
            g = gt_entries.get(str(a))
            if c is None or g is None or (among is not None and a not in among):
                continue
            est.append(c["R"])
            ref.append(g["R"])
            used.append(a)
        if among is not None and "refined" in out and used == out["refined"]["annotation_ids"]:
            continue  # the same objects: the refined report already is the comparison
        if len(est) >= 2:
            try:
                rep = viewpoint_metrics.viewpoint_report(torch.tensor(est, dtype=torch.float64),
                                                         torch.tensor(ref, dtype=torch.float64))
            except ValueError:  # no pair of finite rotations: nothing to report (viewpoint_coverage says why)
                continue
            rep["annotation_ids"] = used  # aligned with rep["per_instance_geodesic"]
            out[stage] = rep
    same = out.get("refined_with_sfm", out.get("refined"))
    if same is not None and "sfm" in out:
        same["change_from_sfm"] = _refinement_change(cams, gt_entries, same["annotation_ids"], object_of or {})
    return out or None


def _refinement_change(cams: dict, gt_entries: dict, aids: list, object_of: dict) -> dict | None:
    """:func:`~carvi_torch.evaluation.viewpoint_metrics.median_change` from the SfM to the refined cameras of the
    objects ``aids`` (each with both), resampling physical objects (the views of one object share its shape);
    objects with a non-finite camera are left out; ``None`` with fewer than 2 physical objects left."""
    pairs = [a for a in aids if cams[str(a)].get("sfm") is not None]
    rot = lambda rows: torch.tensor([r["R"] for r in rows], dtype=torch.float64).reshape(-1, 3, 3)  # noqa: E731
    sets = [rot(cams[str(a)]["sfm"] for a in pairs), rot(cams[str(a)]["refined"] for a in pairs),
            rot(gt_entries[str(a)] for a in pairs)]
    ok = torch.stack([torch.isfinite(R).flatten(1).all(1) for R in sets]).all(0)
    labels = [object_of.get(str(a), ("annotation", str(a))) for a, k in zip(pairs, ok.tolist()) if k]
    if len(set(labels)) < 2:
        return None
    res = viewpoint_metrics.median_change(*(R[ok] for R in sets), labels)
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in res.items()}


def evaluate(data: str | Path, recons: dict[str, str | Path], *, gt: str | Path | None = None,
             split: str | None = None, baselines: bool = False, step_percent: float = 0.5,
             classes=None, progress: bool = True, canvas_size: int | None = None, shapes: bool = True,
             jobs: int | None = None) -> dict:
    """Evaluate reconstruction directories ``recons`` (method name -> directory) against ``gt.json``.

    Returns a dict with ``objects`` (per annotation id in scope: class, and per method the error or the
    reason it is missing with the reason's ``kind``, :class:`~carvi_torch.evaluation.scoring.Reason`; or, for an
    object without usable ground truth, the ``reason`` alone), ``classes`` (per class and method: mean and median
    error, count, over the method's own objects; ``missing`` and ``missing_reasons``, the objects with usable
    ground truth it has no error for, and their ids per kind of reason; ``compared_mean`` and
    ``compared_median`` over the objects every method has an error for), ``compared`` (per class: its
    ``objects`` in scope, those ``without_ground_truth``, and the ids ``compared``), ``mean_over_classes`` and
    ``mean_over_classes_compared``, ``viewpoints`` (per class and method: SfM and refined viewpoint reports),
    ``viewpoint_coverage`` (per class and method with cameras: the objects with a refined camera to score, why
    the others have none, and their ids per kind of reason), ``camera_problems`` (per method and class: what of
    its ``cameras.json`` was unusable), ``unfinished`` (the methods whose run has not finished) and
    ``classes_without_reconstruction`` (per class of the data in scope that some method has no folder for: those
    methods; without ``classes``, a class no method has is not evaluated), ``unread_configs`` (per method
    folder that is no run of this package and holds a ``config.yaml`` it cannot read: why) and
    ``made_with_other_settings`` (per method whose folder holds objects made with other settings than its
    ``config.yaml``'s: :func:`~carvi_torch.io.layout.other_settings`). With ``shapes=False``
    only the viewpoints are evaluated (e.g. after ``stage=cameras``). The shapes are scored with one torch thread per
    process, in this process or in ``jobs`` worker processes (default :func:`default_jobs`); the errors are the
    same either way.

    Raises:
        FileNotFoundError: no file ``data``, or no ground truth.
        ValueError: a ``data`` or ``gt.json`` that is not a JSON object of the expected kind; a ``split`` that no
            annotation of ``data`` has; a name in ``classes`` that is no class of ``data``; a reconstruction whose
            objects are not the ones of ``data`` (an annotation id of its ``cameras.json`` names another
            object there: another class or ``source``; or a run of this package (the first method, or any folder
            with a ``summary.json``) whose ``config.yaml`` cannot be read (:class:`~carvi_torch.config.ConfigError`:
            the first run's canvas loads the masks, a run's ``mesh_format`` says which of its meshes are its own).
            Another method's folder without ``summary.json`` may hold another tool's ``config.yaml``: it is listed in
            ``unread_configs`` and its meshes are found in the default ``mesh_format`` first.
    """
    data = Path(data)
    ann = _read_annotations(data, gt, split)
    classes = select_classes(classes, class_names(ann.categories), str(data)) if classes else None
    configs, unread_configs = _run_configs(recons)
    cfg = next(iter(configs.values()))
    coll_by_class = load_coco(data, canvas_size=canvas_size or cfg.input.canvas_size, margin=cfg.input.canvas_margin,
                              classes=classes).collections if baselines else {}
    wanted = _wanted_classes(classes, recons, ann, data)
    read = {name: _read_cameras(Path(rdir), wanted) for name, rdir in recons.items()}
    cameras = {name: got[0] for name, got in read.items()}  # method -> class -> cameras.json (None: none)
    for name, rdir in recons.items():
        _check_same_objects(name, Path(rdir), cameras[name], ann.ann_class, ann.source_of, data)
    in_scope = [a for a, c in ann.ann_class.items()
                if (split is None or ann.split_of.get(a) == split) and c is not None]
    without = _classes_without_reconstruction(recons, [ann.ann_class[a] for a in in_scope], classes)
    targets = sorted((a for a in in_scope if ann.ann_class[a] in wanted), key=_id_order)
    methods = list(recons) + (["Puffball", "SFMc"] if baselines and shapes else [])
    unfinished = [name for name, rdir in recons.items() if _unfinished(Path(rdir))]
    problems = _scoped({name: got[1] for name, got in read.items()}, set(targets))
    scorer = ShapeScorer(ann.gt_path.parent, recons, cameras, {name: c.mesh.format for name, c in configs.items()},
                         step_percent, baselines, coll_by_class,
                         missing=_missing_reasons(recons, problems, unfinished))
    t0 = time.perf_counter()
    objects = _score_objects(scorer, targets, ann, shapes, jobs, progress)
    per_class, compared = _class_errors(objects, methods)
    res = {"data": str(data), "gt": str(ann.gt_path), "split": split, "step_percent": step_percent,
           "methods": methods, "recons": {k: str(v) for k, v in recons.items()}, "objects": objects,
           "classes": per_class, "compared": compared,
           "mean_over_classes": mean_over_classes(per_class, methods, "mean"),
           "mean_over_classes_compared": mean_over_classes(per_class, methods, "compared_mean"),
           "viewpoints": _class_viewpoints(list(per_class), objects, ann, cameras),
           "viewpoint_coverage": _viewpoint_coverage(objects, ann, cameras, problems),
           "camera_problems": _problem_texts(problems), "unfinished": unfinished,
           "classes_without_reconstruction": without, "unread_configs": unread_configs,
           "made_with_other_settings": {name: made for name, rdir in recons.items() if (made := other_settings(rdir))}}
    res["quality"] = reliability.quality_vs_error(res, cameras)
    res["seconds"] = round(time.perf_counter() - t0, 2)
    return res


def _run_config(rdir: Path) -> Config:
    """The configuration of the run in ``rdir`` (its ``config.yaml``; the defaults without one: a folder of meshes,
    another method's). :class:`~carvi_torch.config.ConfigError` for a file that cannot be read as one."""
    return read_run_config(rdir / "config.yaml") if (rdir / "config.yaml").is_file() else Config()


def _run_configs(recons: dict) -> tuple[dict, dict]:
    """Each method's run configuration (:func:`_run_config`) and, per method whose ``config.yaml`` could not be
    read, why: the first method's must be read (its canvas loads the baselines' masks), and so must a run's of this
    package (a folder with ``summary.json``: its ``mesh_format`` says which of its meshes are its own); another
    folder may hold another tool's file, and the defaults stand in (its ``mesh_format`` only orders the formats its
    meshes are looked up in)."""
    configs, unread = {}, {}
    for k, (name, rdir) in enumerate(recons.items()):
        try:
            configs[name] = _run_config(Path(rdir))
        except ConfigError as e:
            if k == 0 or (Path(rdir) / "summary.json").is_file():
                raise
            configs[name], unread[name] = Config(), " ".join(str(e).split())
    return configs, unread


def _score_objects(scorer: ShapeScorer, targets: list, ann: "_Annotations", shapes: bool, jobs: int | None,
                   progress: bool) -> dict[str, dict]:
    """Each object of ``targets``'s row: ``class``, ``split`` and, with ``shapes``, every method's error or why
    there is none (:func:`score_shapes`); an object without usable ground truth gets its ``reason`` instead and is
    not scored."""
    rows = {aid: {"class": ann.ann_class[aid], "split": ann.split_of.get(aid, "")} for aid in targets}
    for aid, row in rows.items():
        if aid in ann.gt_problems:
            row["reason"] = ann.gt_problems[aid]
    work = [(aid, ann.gt_entries[aid], row) for aid, row in rows.items() if "reason" not in row]
    if shapes and work:
        scored = score_shapes(scorer, work, default_jobs(len(work)) if jobs is None else jobs, progress)
        rows.update({aid: row for (aid, _entry, _row), row in zip(work, scored)})
    return rows


def mean_over_classes(per_class: dict, methods: list[str], key: str) -> dict:
    """Per method: the mean over classes of its class means ``key`` (``mean`` or ``compared_mean``), the classes
    without one (or from an older ``results.json``, without the key) left out (``None``: none has one)."""
    vals = {m: [row[m][key] for row in per_class.values() if row[m].get(key) is not None] for m in methods}
    return {m: float(np.mean(v)) if v else None for m, v in vals.items()}


def _scoped(problems: dict, objects: set) -> dict:
    """:func:`_read_cameras`'s problems per method, of the objects in scope (``objects``) only; methods and classes
    without any left out."""
    out = {}
    for name, per in problems.items():
        for cls, p in per.items():
            kept = {a: why for a, why in p["objects"].items() if a in objects}
            if p["file"] or kept:
                out.setdefault(name, {})[cls] = {"file": p["file"], "objects": kept}
    return out


def _problem_texts(problems: dict) -> dict:
    """:func:`_scoped`'s problems with each object's :class:`~carvi_torch.evaluation.scoring.Reason` as its text
    (``results.json``'s ``camera_problems``)."""
    return {name: {cls: {"file": p["file"], "objects": {a: why.text for a, why in p["objects"].items()}}
                   for cls, p in per.items()} for name, per in problems.items()}


def _unfinished(rdir: Path) -> bool:
    """Whether ``rdir`` holds a reconstruction run that has not finished (interrupted, or still running): a class's
    ``cameras.json``, but no ``summary.json`` with ``total_seconds`` (which a run writes when its last class is
    done). A folder of meshes without ``cameras.json`` (another method's) is no such run."""
    return any(rdir.glob("*/cameras.json")) and unfinished(rdir)


def _run_failures(rdir: Path) -> list[tuple[str, str, str]]:
    """``(class, annotation id, reason)`` of each object the run in ``rdir`` skipped, as its ``summary.json`` books
    them (none without a readable one)."""
    try:
        summary = read_json(rdir / "summary.json")
    except (OSError, ValueError):
        return []
    classes = summary.get("classes") if isinstance(summary, dict) else None
    out = []
    for cls, entry in classes.items() if isinstance(classes, dict) else ():
        failures = entry.get("failures") if isinstance(entry, dict) else None
        for f in failures if isinstance(failures, list) else ():
            if isinstance(f, dict) and f.get("annotation_id") is not None and isinstance(f.get("reason"), str):
                out.append((cls, str(f["annotation_id"]), f["reason"]))
    return out


def _missing_reasons(recons: dict, problems: dict, unfinished: list) -> dict:
    """:class:`ShapeScorer`'s ``missing``: per method, why an object has no mesh where more is known than that
    there is none: the run skipped it (its ``summary.json``, with the run's reason), its class's ``cameras.json``
    is unusable, or the run is unfinished."""
    out = {}
    for name, rdir in recons.items():
        why = {(None, None): Reason("not reconstructed yet", NOT_YET)} if name in unfinished else {}
        for cls, p in problems.get(name, {}).items():
            if p["file"]:
                why[(cls, None)] = Reason.of("unusable cameras.json", p["file"])
        for cls, aid, reason in _run_failures(Path(rdir)):
            why[(cls, aid)] = Reason.of("skipped by the run", reason)
        out[name] = why
    return out


@dataclasses.dataclass
class _Annotations:
    """What :func:`evaluate` reads of the annotation file and its ground truth; ids as strings."""

    gt_path: Path
    gt_entries: dict  # id -> its gt.json record, the usable ones (gt_problem finds nothing wrong)
    gt_problems: dict  # id -> why the annotation has no usable ground truth (the annotations of the file only)
    categories: list  # the file's categories
    key_of: dict  # category id -> class folder
    split_of: dict  # id -> split ("" without one)
    ann_class: dict  # id -> class folder (None: an unknown category)
    original: dict  # id -> the id as the file gives it (int or str)
    source_of: dict  # id -> the annotation's source
    object_of: dict  # id -> its physical object ("object_id", else the annotation itself)


def _read_annotations(data: Path, gt, split: str | None) -> _Annotations:
    """Read ``data`` and its ground truth (``gt``, default ``gt.json`` beside it); errors as :func:`evaluate`'s."""
    if not data.is_file():
        raise FileNotFoundError(f"{data}: no such annotation file")
    gt_path = Path(gt) if gt else data.with_name("gt.json")
    if not gt_path.is_file():
        raise FileNotFoundError(f"{gt_path}: no ground truth (gt.json beside the annotations)")
    gt_all = read_json(gt_path)
    gt_entries = gt_all.get("annotations", gt_all) if isinstance(gt_all, dict) else gt_all
    if not isinstance(gt_entries, dict):
        raise ValueError(f"{gt_path}: expected a JSON object of annotation id -> ground truth (or one under "
                         f"'annotations'), got {_json_kind(gt_entries)}")
    dataset = read_json(data)
    if not isinstance(dataset, dict):
        raise ValueError(f"{data}: expected a COCO JSON object (images, annotations, categories), got "
                         f"{_json_kind(dataset)}")
    if not isinstance(dataset.get("annotations", []), list):
        raise ValueError(f"{data}: its 'annotations' is {_json_kind(dataset['annotations'])}, not a list")
    anns = [a for a in dataset.get("annotations", []) if isinstance(a, dict) and object_id(a.get("id")) is not None]
    split_of = {str(a["id"]): a.get("split", "") for a in anns}
    if split is not None and split not in split_of.values():
        present = sorted({repr(s) if s else "none" for s in split_of.values()})
        raise ValueError(f"no annotation of {data} is in split {split!r} (its splits: {', '.join(present) or 'none'})")
    key_of = class_keys(dataset.get("categories", []))
    gt_problems = {str(a["id"]): _gt_problem(gt_entries, str(a["id"])) for a in anns}
    return _Annotations(gt_path=gt_path, gt_problems={a: why for a, why in gt_problems.items() if why},
                        gt_entries={a: gt_entries[a] for a, why in gt_problems.items() if not why},
                        categories=dataset.get("categories", []),
                        key_of=key_of, split_of=split_of,
                        ann_class={str(a["id"]): key_of.get(str(a.get("category_id"))) for a in anns},
                        original={str(a["id"]): a["id"] for a in anns},
                        source_of={str(a["id"]): annotation_source(a) for a in anns},
                        object_of={str(a["id"]): _physical_object(a) for a in anns})


def _gt_problem(gt_entries: dict, aid: str) -> str | None:
    """Why annotation ``aid`` has no usable ground truth in ``gt_entries`` (``gt.json``'s records), ``None`` when it
    has (:func:`~carvi_torch.evaluation.scoring.gt_problem`).

    Example:
        >>> _gt_problem({"3": {"mesh": "m.ply", "R": [[2, 0, 0], [0, 2, 0], [0, 0, 2]], "s": 1, "t": [0, 0]}}, "3")
        'ground truth unusable: R is not a rotation'
        >>> _gt_problem({}, "3")
        'no ground truth: gt.json has no entry for it'
    """
    if aid not in gt_entries:
        return NO_GROUND_TRUTH
    why = gt_problem(gt_entries[aid])
    return f"ground truth unusable: {why}" if why else None


def _json_kind(value) -> str:
    """What kind of JSON value ``value`` is, with its article (``a list``, ``a string``, ``null``, ...).

    Example:
        >>> _json_kind([1]), _json_kind(None), _json_kind(2.5)
        ('a list', 'null', 'a number')
    """
    if value is None:
        return "null"
    kinds = ((bool, "a boolean"), ((int, float), "a number"), (str, "a string"), (list, "a list"), (dict, "an object"))
    return next(name for kind, name in kinds if isinstance(value, kind))


def _physical_object(a: dict) -> tuple:
    """The physical object of annotation ``a``: its ``object_id`` within its category, else the annotation."""
    oid = object_id(a.get("object_id"))
    return ("annotation", str(a["id"])) if oid is None else ("object", str(a.get("category_id")), str(oid))


def _wanted_classes(classes: list[str] | None, recons: dict, ann: _Annotations, data: Path) -> set[str]:
    """The classes to evaluate: ``classes``, by default those some reconstruction has a folder for (``ValueError``:
    none)."""
    wanted = set(classes) if classes else {c for r in recons.values() for c in ann.ann_class.values()
                                           if c is not None and (Path(r) / c).is_dir()}
    if not wanted:
        raise ValueError(f"no class of {data} ({', '.join(sorted(set(ann.key_of.values()))) or 'none'}) has a folder "
                         f"in {' or '.join(map(str, recons.values()))}")
    return wanted


def _class_errors(objects: dict, methods: list[str]) -> tuple[dict[str, dict], dict[str, dict]]:
    """Per class (sorted) and method (:func:`_method_errors`), and per class what the methods are compared on:
    ``objects`` (in scope), ``without_ground_truth`` (those with a ``reason``, scored for no method) and
    ``compared``, the ids of the objects every method has a finite ``error_percent`` for."""
    per_class: dict[str, dict] = {}
    compared: dict[str, dict] = {}
    for cls in sorted({r["class"] for r in objects.values()}):
        rows = {a: r for a, r in objects.items() if r["class"] == cls}
        usable = {a: r for a, r in rows.items() if "reason" not in r}
        errs = {m: {a: e for a, r in usable.items() if (e := _error(r, m)) is not None} for m in methods}
        common = [a for a in usable if all(a in errs[m] for m in methods)]
        per_class[cls] = {m: _method_errors(usable, m, errs[m], common) for m in methods}
        compared[cls] = {"objects": len(rows), "without_ground_truth": len(rows) - len(usable), "compared": common}
    return per_class, compared


def _error(row: dict, method: str) -> float | None:
    """``method``'s finite ``error_percent`` in an object's ``row`` (``None``: none)."""
    e = row[method].get("error_percent") if isinstance(row.get(method), dict) else None
    return e if e is not None and math.isfinite(e) else None


def _method_errors(usable: dict, method: str, errs: dict, common: list) -> dict:
    """One method's entry of a class: ``mean``, ``median`` and ``count`` of its errors ``errs`` (id -> error);
    ``missing``, the objects of ``usable`` (those with usable ground truth) it has none for, and
    ``missing_reasons``, their ids per kind of reason (the entry's ``kind``: the reason itself, such as the file, is
    the object's in ``objects``; ``not scored`` without an entry); ``compared_mean`` and ``compared_median`` over
    the objects ``common`` to every method.

    Example:
        >>> usable = {"1": {"A": {"error_percent": 2.0}}, "2": {"A": Reason.of("unreadable mesh", "m.ply").entry()}}
        >>> e = _method_errors(usable, "A", {"1": 2.0}, ["1"])
        >>> e["count"], e["missing"], e["missing_reasons"], e["compared_mean"]
        (1, 1, {'unreadable mesh': ['2']}, 2.0)
    """
    vals, both = list(errs.values()), [errs[a] for a in common]
    reasons: dict[str, list] = {}
    for a, r in usable.items():
        if a not in errs:
            reasons.setdefault(r[method]["kind"] if method in r else "not scored", []).append(a)
    return {"mean": float(np.mean(vals)) if vals else None, "median": float(np.median(vals)) if vals else None,
            "count": len(vals), "missing": len(usable) - len(vals), "missing_reasons": reasons,
            "compared_mean": float(np.mean(both)) if both else None,
            "compared_median": float(np.median(both)) if both else None}


def _viewpoint_coverage(objects: dict, ann: "_Annotations", cameras: dict, problems: dict) -> dict[str, dict]:
    """Per class and method with a ``cameras.json``: ``objects``, how many of the class's objects with usable ground
    truth have a refined camera to score; ``missing``, why each of the others has none (annotation id -> reason:
    :func:`_no_refined_camera`, ``problems`` as :func:`_scoped` gives them); and ``missing_reasons``, their ids per
    kind of reason."""
    out: dict[str, dict] = {}
    for name, per in cameras.items():
        for cls, content in per.items():
            aids = [a for a, r in objects.items() if r["class"] == cls and a in ann.gt_entries]
            if content is None or not aids:
                continue
            bad = problems.get(name, {}).get(cls, {"file": None, "objects": {}})
            missing = {a: why for a in aids if (why := _no_refined_camera(content["cameras"].get(a), bad, a))}
            kinds: dict[str, list] = {}
            for a, why in missing.items():
                kinds.setdefault(why.kind, []).append(a)
            out.setdefault(cls, {})[name] = {"objects": len(aids) - len(missing),
                                             "missing": {a: why.text for a, why in missing.items()},
                                             "missing_reasons": kinds}
    return out


def _no_refined_camera(cam: dict | None, bad: dict, aid: str) -> Reason | None:
    """Why object ``aid`` has no refined camera to score (``None``: it has one): its class's ``cameras.json`` or its
    entry or refined camera there is unusable (``bad``: the class's problems, as :func:`_scoped` gives them; an
    unusable SfM camera is no reason), it is not in the file (``cam``: its entry, made safe to read, ``None``:
    none), the entry has no refined camera, or a non-finite one.

    Example:
        >>> fine = {"file": None, "objects": {}}
        >>> _no_refined_camera(None, fine, "3").text, _no_refined_camera({"refined": None}, fine, "3").kind
        ('not in cameras.json', 'no refined camera')
        >>> sfm_only = {"file": None, "objects": {"3": Reason.of(UNUSABLE_SFM_CAMERA, "R is not a rotation")}}
        >>> _no_refined_camera({"sfm": None, "refined": None}, sfm_only, "3").text
        'no refined camera'
    """
    refined = cam.get("refined") if cam is not None else None
    if bad["file"]:
        return Reason.of("unusable cameras.json", bad["file"])
    problem = bad["objects"].get(aid)
    if refined is None and problem is not None and problem.kind != UNUSABLE_SFM_CAMERA:
        return problem
    if refined is None:
        return Reason.of("not in cameras.json" if cam is None else "no refined camera")
    return None if numbers(refined["R"], (3, 3)) else Reason.of("non-finite refined camera")


def _class_viewpoints(classes: list[str], objects: dict, ann: _Annotations, cameras: dict) -> dict[str, dict]:
    """Per class and method with cameras: the :func:`_viewpoints` reports of the class's objects."""
    viewpoints = {}
    for cls in classes:
        aids = [ann.original[a] for a, r in objects.items() if r["class"] == cls]
        vp = {}
        for name in cameras:
            rep = _viewpoints(cameras[name][cls], ann.gt_entries, aids, ann.object_of)
            if rep:
                vp[name] = rep
        viewpoints[cls] = vp
    return viewpoints


def _classes_without_reconstruction(recons: dict, classes_in_scope: list, asked) -> dict[str, list[str]]:
    """``{class: [methods without a folder for it]}`` over the data's classes in scope (those asked for)."""
    out = {}
    for cls in sorted(set(classes_in_scope)):
        if asked is None or cls in asked:
            lacking = [name for name, rdir in recons.items() if not (Path(rdir) / cls).is_dir()]
            if lacking:
                out[cls] = lacking
    return out


def _check_same_objects(name: str, rdir: Path, cameras: dict, ann_class: dict, source_of: dict, data: Path) -> None:
    """``ValueError`` when the reconstruction ``rdir`` was made from other data than ``data``: an annotation
    id of a ``cameras.json`` (``cameras``: class -> its content, ``None`` where there is none) names another
    object in ``data`` (another class, or another ``source``), or no id of it is in ``data`` at all. Ids that
    ``data`` lacks are allowed (a subset of the objects)."""
    seen, found = 0, 0
    for cls in sorted(cameras):
        cams = cameras[cls].get("cameras") if cameras[cls] is not None else None
        for aid, cam in (cams if isinstance(cams, dict) else {}).items():
            seen += 1
            if aid not in ann_class:
                continue
            found += 1
            src = cam.get("source") if isinstance(cam, dict) else None
            if not same_object(cls, src, ann_class[aid], source_of[aid]):
                raise ValueError(f"{_not_made_from(name, rdir, data)}: its {cls} annotation {aid} is "
                                 f"{src or 'unnamed'}, in {data.name} it is {ann_class[aid]} {source_of[aid]}")
    if seen and not found:
        raise ValueError(f"{_not_made_from(name, rdir, data)}: none of its {seen} annotation ids is in {data.name}")


def _not_made_from(name: str, rdir: Path, data: Path) -> str:
    """How a reconstruction differs from ``data``: made from another file (named where the run's ``summary.json``
    records it), or from ``data`` itself, which changed since the run."""
    p = rdir / "summary.json"
    try:
        made = read_json(p).get("data") if p.is_file() else None
    except (ValueError, AttributeError):
        made = None
    if not isinstance(made, str) or not made:
        return f"--recon {name}={rdir} was not made from {data}"
    try:
        same = Path(made).resolve() == data.resolve() or Path(made).samefile(data)
    except OSError:
        same = False
    if same:
        return (f"--recon {name}={rdir} was made from {data}, but its objects differ from the file's current "
                "contents (the file changed since the run)")
    return f"--recon {name}={rdir} was not made from {data} (it was made from {made})"


def _id_order(aid: str):
    """Sort key of ids as strings: integers by value first, then the others as text."""
    return (0, int(aid), "") if aid.lstrip("-").isdigit() else (1, 0, aid)


# --------------------------------------------------------------------------- tables


def _fmt(v, digits=2):
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}f}"


def format_shape_table(res: dict) -> str:
    """Markdown table in the shape of the paper's Table 1: per class every method's mean error over the objects
    that every method has an error for (``compared``), the best in bold, and their mean over the classes with such
    objects; the objects compared in brackets, ``4 of 6`` where some method misses some of the class's objects in
    scope. A class without an object every method has shows each method's mean over its own objects, with their
    number, and bolds none (:func:`_shape_row`). A ``res`` without ``compared`` (an older ``results.json``) shows
    each method's own means.

    Example:
        >>> res = {"methods": ["A", "B"], "compared": {"car": {"objects": 3, "compared": ["1", "2"]}},
        ...        "classes": {"car": {"A": {"mean": 3.0, "count": 3, "compared_mean": 2.0},
        ...                            "B": {"mean": 2.5, "count": 2, "compared_mean": 2.5}}},
        ...        "mean_over_classes": {"A": 3.0, "B": 2.5}, "mean_over_classes_compared": {"A": 2.0, "B": 2.5}}
        >>> print(format_shape_table(res))
        | class | A | B |
        |---|---|---|
        | car (2 of 3) | **2.00** | 2.50 |
        | **mean** | 2.00 | 2.50 |
    """
    methods, compared = res["methods"], res.get("compared")
    lines = ["| class | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for cls, row in sorted(res["classes"].items()):
        lines.append(_shape_row(cls, row, methods, None if compared is None else compared.get(cls)))
    means = res["mean_over_classes"] if compared is None else res["mean_over_classes_compared"]
    scored = [c for c in (compared or {}).values() if c["objects"] > c.get("without_ground_truth", 0)]
    used = sum(1 for c in scored if c["compared"])
    label = "**mean**" if compared is None or used == len(scored) else f"**mean** ({used} of {len(scored)} classes)"
    lines.append(f"| {label} | " + " | ".join(_fmt(means[m]) for m in methods) + " |")
    return "\n".join(lines)


def _shape_row(cls: str, row: dict, methods: list[str], compared: dict | None) -> str:
    """One class's row of :func:`format_shape_table` (``compared``: the class's entry of ``res["compared"]``,
    ``None`` for each method's own objects)."""
    n = len(compared["compared"]) if compared else 0
    no_gt = compared.get("without_ground_truth", 0) if compared else 0
    scored = compared["objects"] - no_gt if compared else 0  # the objects with usable ground truth
    apart = compared is not None and not n and scored > 0  # none every method has: each its own, not ranked
    vals = [row[m]["compared_mean" if n else "mean"] for m in methods]
    if compared is None:
        label = f"{cls} ({max(row[m]['count'] for m in methods)})"
    elif not scored:
        label = f"{cls} (no ground truth for its {compared['objects']})"
    elif n == compared["objects"]:
        label = f"{cls} ({n})"
    else:
        label = f"{cls} ({n or ('none' if len(methods) > 1 else 0)} of {compared['objects']}" \
                + (" in common" if apart and len(methods) > 1 else "") \
                + (f"; {no_gt} without ground truth)" if no_gt else ")")
    finite = [v for v in vals if v is not None]
    best = min(finite) if finite and not apart else None
    cells = [f"**{_fmt(v)}**" if v is not None and v == best else _fmt(v) for v in vals]
    if apart:
        cells = [c if v is None else f"{c} ({row[m]['count']})" for c, v, m in zip(cells, vals, methods)]
    return f"| {label} | " + " | ".join(cells) + " |"


def format_viewpoint_table(res: dict) -> str:
    """Per class and method: median geodesic / azimuth / elevation error as written (absolute: the
    labels a user trains on) and after one fitted global rotation (aligned: the cameras alone), the up axis
    error that ignores azimuth (rotationally symmetric classes, ``viewpoint_metrics.up_axis_errors``), the
    accuracy at 30 degrees of each, and on the refinement's before/after row the change of the aligned
    median from SfM with its 95% interval over the physical objects (``change_from_sfm``)."""
    lines = ["| class | method | stage | n | geodesic abs / aligned | azimuth abs / aligned | "
             "elevation abs / aligned | up axis abs / aligned | acc@30 abs / aligned | mirrored | "
             "refined - SfM median [95% over objects] |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for cls, per in sorted(res["viewpoints"].items()):
        for mth, stages in per.items():
            for stage, rep in stages.items():
                ab = rep.get("absolute", {})

                def pair(key, stat="median", nd=1):
                    return f"{_fmt(ab.get(key, {}).get(stat), nd)} / {_fmt(rep.get(key, {}).get(stat), nd)}"

                lines.append(f"| {cls} | {mth} | {stage} | {rep.get('geodesic', {}).get('n', '-')} | "
                             f"{pair('geodesic')} | {pair('azimuth')} | {pair('elevation')} | {pair('up_axis')} | "
                             f"{pair('geodesic', 'acc_at_30', 2)} | {rep.get('mirrored', False)} | "
                             f"{format_change(rep.get('change_from_sfm'))} |")
    return "\n".join(lines)


def format_change(change: dict | None) -> str:
    """``change_from_sfm`` as ``+0.3 [-0.5, +1.9]`` (degrees), ``-`` for none.

    >>> format_change({"change": 0.283, "low": -0.512, "high": 1.857})
    '+0.3 [-0.5, +1.9]'
    """
    if not change:
        return "-"
    c, lo, hi = (round(change[k], 1) + 0.0 for k in ("change", "low", "high"))  # + 0.0: no "-0.0"
    return f"{c:+.1f} [{lo:+.1f}, {hi:+.1f}]"


#: The line of an evaluation interrupted by Ctrl-C.
INTERRUPTED = "interrupted; nothing was written"


def main(argv=None) -> int:
    """Exit status: 0 evaluated; 2 a user error or an ``--out`` that cannot be written (one ``error:`` line,
    checked before the work); 130 interrupted by Ctrl-C (one line)."""
    return run_command(lambda: _main(argv), INTERRUPTED)


def _main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog=program("carvi_torch.evaluate"), description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="COCO keypoint JSON the reconstruction ran on (gt.json beside it)")
    ap.add_argument("--recon", required=True, action="append",
                    help="reconstruction directory, or NAME=DIR to name the method (an existing directory whose "
                         "path holds '=' is that directory); repeat to compare methods")
    ap.add_argument("--out", help="directory for results.json, shapes.md (not with --viewpoints-only), viewpoints.md "
                                  "and, where the runs score their objects' quality, quality.md (default: none, "
                                  "the tables are printed only)")
    ap.add_argument("--gt", help="ground truth file (default: gt.json beside --data)")
    ap.add_argument("--split", help="evaluate only annotations of this split (e.g. test)")
    ap.add_argument("--baselines", action="store_true", help="also evaluate Puffball and SFMc")
    ap.add_argument("--step-percent", type=_positive_finite, default=0.5,
                    help="surface sampling step in percent of the GT bounding-box diagonal (default 0.5; the tables "
                         "in docs/ say which step they used, mostly 1 to 3). A coarser step trades a little accuracy "
                         "for time: on the default run's chairs 0.8 s per object at 0.5, 0.3 s at 2 (wall clock, "
                         "2 cores, the interpreter's start included), the errors moving by hundredths of a "
                         "percentage point (the samples fall as 1/step^2; the time less)")
    ap.add_argument("--viewpoints-only", action="store_true", help="skip the shapes (e.g. after stage=cameras)")
    ap.add_argument("--jobs", type=positive_int, default=None,
                    help="processes that score the shapes, one torch thread each (default: one per core, at most "
                         f"{MAX_JOBS}; this process alone below {POOL_FROM} objects). 1: this process; the errors "
                         "are the same for every count")
    add_common(ap)
    args = ap.parse_args(argv)
    nonempty_paths(args, "--data", "--recon", "--out", "--gt")
    recons = _parse_recons(args.recon)
    # the folders the check below makes (--out and the parents it lacks, deepest first): removed on failure
    made = folders_to_make(args.out) if args.out else []
    if args.out:
        writable_folder(args.out)  # before minutes of work, not after
    status = None
    try:
        status = _evaluate_and_write(args, recons)
    finally:
        if status != 0:
            remove_empty(made)
    return status


def _parse_recons(items: list[str]) -> dict[str, str]:
    """``--recon``'s values as method name -> directory: an existing directory is itself (whatever its path
    holds: ``runs/a=b``), else ``NAME=DIR`` (split at the first ``=``), else a directory; unnamed, the first is
    ``Full`` and the others their folder's name. :class:`~carvi_torch.cli.CommandError` for two of one name or
    a directory that is not there."""
    recons: dict[str, str] = {}
    for item in items:
        name, sep, path = ("", "", item) if Path(item).is_dir() else item.partition("=")
        if not sep:
            name, path = "", item
        if not path:
            raise CommandError(f"--recon {item}: the directory is empty; give a path ('.' for the current folder)")
        name = name or ("Full" if not recons else Path(path).name)
        if name in recons:
            raise CommandError(f"two --recon are named {name} ({recons[name]} and {path}): name them apart "
                               "(--recon NAME=DIR)")
        recons[name] = path
    for name, p in recons.items():
        if not Path(p).is_dir():
            raise CommandError(f"reconstruction directory {p} ({name}) not found")
    return recons


def _positive_finite(text: str) -> float:
    """``--step-percent``'s type: a finite number above 0 (argparse says what is wrong, exit 2)."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"expected a finite number > 0, got {text}")
    return v


def _camera_only(recons: dict) -> list[str]:
    """The methods whose run stopped after the cameras (``stage: cameras`` in its ``config.yaml``): no shapes. A
    missing or unreadable ``config.yaml`` (:class:`~carvi_torch.config.ConfigError`) says nothing."""
    out = []
    for name, rdir in recons.items():
        try:
            if read_run_config(Path(rdir) / "config.yaml").stage == "cameras":
                out.append(name)
        except ConfigError:  # no or damaged config: nothing to say
            pass
    return out


def _print_notes(args, recons: dict, res: dict) -> None:
    """On stderr: what was left out (:func:`_left_out_lines`), then notes on the runs (one that stopped after
    the cameras, an unfinished one), the classes some method has no folder for, and per class each method's
    misses (:func:`_miss_notes`)."""
    lines = _left_out_lines(res, not args.viewpoints_only)
    cams_only = [] if args.viewpoints_only else _camera_only(recons)
    if cams_only:
        lines.append(f"note: {', '.join(cams_only)} stopped after the cameras (stage=cameras): no shapes to score; "
                     "--viewpoints-only evaluates the viewpoints alone")
    for name, why in res.get("unread_configs", {}).items():
        lines.append(f"note: {name} is no run of this package and its config.yaml could not be read as one "
                     f"({why[:120]}): its meshes are looked up as {Config().mesh.format} first, then in the other "
                     "formats")
    for name, made in res.get("made_with_other_settings", {}).items():
        counted = objects_text(objects_made_otherwise(recons[name]))
        lines.append(f"note: {name} ({recons[name]}) holds objects made with other settings than its config.yaml's: "
                     + other_settings_text(made)
                     + f" (oldest first, then the run's{'; ' + counted if counted else ''}): its errors mix them")
    for name in res["unfinished"]:
        lines.append(f"note: {name} ({recons[name]}) is an unfinished run (interrupted or still running): the "
                     "objects it has not reconstructed yet count as missing")
    for cls, lacking in res["classes_without_reconstruction"].items():
        lines.append(f"note: class {cls} has no reconstruction in {', '.join(lacking)}"
                     + ("" if args.classes or len(lacking) < len(recons) else "; not evaluated"))
    lines += _miss_notes(res, not args.viewpoints_only)
    for line in lines:
        print(line, file=sys.stderr)


#: The kinds of reason a method has no shape error for whose text says what of the object itself failed (its mesh
#: file, the run's reason, what the metric found): each such object gets a line of its own.
OWN_LINE_KINDS = frozenset({"skipped by the run", "unreadable mesh", "unscorable mesh"})


def _left_out_lines(res: dict, shapes: bool) -> list[str]:
    """One line per object left out for a reason that names it: without usable ground truth (for every method);
    a method's mesh whose reason is of a kind in :data:`OWN_LINE_KINDS` (``shapes``); a method's unusable
    ``cameras.json`` (one line) or camera."""
    lines = []
    for aid, row in res["objects"].items():
        if "reason" in row:
            lines.append(f"evaluate: {row['class']} annotation {aid} skipped: {row['reason']}")
        for m in res["methods"] if shapes else ():
            entry = row.get(m) if _error(row, m) is None else None
            if isinstance(entry, dict) and entry.get("kind") in OWN_LINE_KINDS:
                lines.append(f"evaluate: {row['class']} annotation {aid}: {m} has no shape error: {entry['reason']}")
    for name, per in res["camera_problems"].items():
        for cls, p in per.items():
            if p["file"]:
                lines.append(f"evaluate: {cls}: {name}'s cameras.json is unusable, its objects left out: {p['file']}")
            lines += [f"evaluate: {cls} annotation {aid}: {name}: {why}" for aid, why in p["objects"].items()]
    return lines


def _miss_notes(res: dict, shapes: bool) -> list[str]:
    """Per class: a note per method with objects it has no shape error for (``shapes``), with the reasons and the
    objects, saying what the shape table compares; a note per method with objects without a usable refined camera,
    and one where a method has too few for a viewpoint report."""
    lines = []
    for cls, row in res["classes"].items():
        comp = res["compared"][cls]
        usable, n = comp["objects"] - comp["without_ground_truth"], len(comp["compared"])
        for m in res["methods"] if shapes else ():
            if row[m]["missing"]:
                table = (f"the shape table compares {cls} on the {n} objects every method has" if n else
                         f"no {cls} object has every method's: the shape table shows each method's own mean, unranked")
                lines.append(f"note: {cls}: {m} has no shape error for {row[m]['missing']} of {usable} objects "
                             f"({_grouped(row[m]['missing_reasons'])}); {table}")
        for m, cov in res["viewpoint_coverage"].get(cls, {}).items():
            if cov["missing"]:
                lines.append(f"note: {cls}: {m} has no usable refined camera for {len(cov['missing'])} of {usable} "
                             f"objects ({_grouped(cov['missing_reasons'])}); its viewpoint rows count the others")
            if cov["objects"] < 2:
                lines.append(f"note: {cls}: no viewpoint report for {m}: {cov['objects']} object(s) with a refined "
                             "camera and ground truth (the global alignment needs at least 2)")
    return lines


def _grouped(groups: dict, most: int = 10) -> str:
    """Reasons with their objects' ids, the first ``most`` of each.

    Example:
        >>> _grouped({"no reconstruction": ["3", "4"], "unreadable mesh": [str(i) for i in range(12)]})
        'no reconstruction: 3, 4; unreadable mesh: 0, 1, 2, 3, 4, 5, 6, 7, 8, 9 and 2 more'
    """
    return "; ".join(f"{why}: {shown_names(ids, most)}" for why, ids in groups.items())


def _evaluate_and_write(args, recons: dict) -> int:
    """The evaluation, its tables printed and, with ``--out``, written; the exit status."""
    try:
        res = evaluate(args.data, recons, gt=args.gt, split=args.split, baselines=args.baselines,
                       step_percent=args.step_percent, classes=split_classes(args.classes),
                       progress=not args.quiet, shapes=not args.viewpoints_only, jobs=args.jobs)
    except (FileNotFoundError, ValueError, CocoFormatError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    _print_notes(args, recons, res)
    shapes, views = format_shape_table(res), format_viewpoint_table(res)
    if not args.viewpoints_only:
        print("Symmetric RMS error, % of the ground-truth bounding-box diagonal (per class the objects every method "
              "is compared on in brackets, of those in scope)")
        print(shapes)
        print()
    print("Viewpoint errors (degrees) after global alignment")
    print(views)
    quality = reliability.format_quality_table(res["quality"]) if res["quality"] else ""
    if quality:
        print("\nHow the objects' quality ranks their errors (Spearman rho; negative: higher quality, lower error)")
        print(quality)
    if args.out:
        out = Path(args.out)
        tables = {"shapes.md": None if args.viewpoints_only else shapes, "viewpoints.md": views,
                  "quality.md": quality or None}
        write_json(out / "results.json", res)
        for name, text in tables.items():
            if text is not None:
                write_bytes(out / name, (text + "\n").encode())
        print(f"wrote {out}/results.json, " + ", ".join(n for n, t in tables.items() if t is not None))
    return 0


if __name__ == "__main__":
    sys.exit(main())
