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
and so does a run that stopped after the cameras (``stage=cameras``) without ``--viewpoints-only``;
an unknown ``--classes`` name, a ``--split`` that no annotation has, two ``--recon`` of one name, or a
reconstruction whose annotation ids name other objects in ``--data`` (another class or ``source``: it was
made from other data, or the file changed since the run), is an error (exit 2).

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

from .cli import add_common, positive_int, program, run_command, split_classes, writable_folder
from .config import Config, read_run_config
from .io.coco import CocoFormatError, class_keys, class_names, load_coco, object_id, select_classes
from .io.outputs import read_json, write_bytes, write_json
from .io.results import annotation_source, same_object
from .evaluation import reliability, viewpoint_metrics
from .evaluation.scoring import MAX_JOBS, POOL_FROM, ShapeScorer, default_jobs, posed_gt_mesh, score_shapes

__all__ = ["evaluate", "posed_gt_mesh", "format_shape_table", "format_viewpoint_table", "format_change", "main"]


def _read_cameras(rdir: Path, classes) -> dict[str, dict | None]:
    """Each class's ``cameras.json`` of the reconstruction ``rdir``, read once for every use: class -> its
    content (``None``: no file)."""
    return {cls: read_json(p) if (p := rdir / cls / "cameras.json").is_file() else None for cls in sorted(classes)}


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
            rep = viewpoint_metrics.viewpoint_report(torch.tensor(est, dtype=torch.float64),
                                                     torch.tensor(ref, dtype=torch.float64))
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

    Returns a dict with ``objects`` (per annotation id: class, and per method the error or the
    reason it is missing), ``classes`` (per class and method: mean and median error, count),
    ``viewpoints`` (per class and method: SfM and refined viewpoint reports) and
    ``classes_without_reconstruction`` (per class of the data in scope that some method has no folder
    for: those methods; without ``classes``, a class no method has is not evaluated). With
    ``shapes=False`` only the viewpoints are evaluated (e.g. after ``stage=cameras``). The shapes are scored
    with one torch thread per process, in this process or in ``jobs`` worker processes (default
    :func:`default_jobs`); the errors are the same either way.

    Raises:
        FileNotFoundError: no file ``data``, or no ground truth.
        ValueError: a ``split`` that no annotation of ``data`` has; a name in ``classes`` that is no class of
            ``data``; a reconstruction whose objects
            are not the ones of ``data`` (an annotation id of its ``cameras.json`` names another
            object there: another class or ``source``; or none of its ids is in ``data``).
    """
    data = Path(data)
    ann = _read_annotations(data, gt, split)
    classes = select_classes(classes, class_names(ann.categories), str(data)) if classes else None
    first = Path(next(iter(recons.values())))
    cfg = read_run_config(first / "config.yaml") if (first / "config.yaml").is_file() else Config()
    canvas_size = canvas_size or cfg.input.canvas_size
    coll_by_class = {}
    if baselines:
        loaded = load_coco(data, canvas_size=canvas_size, margin=cfg.input.canvas_margin,
                           classes=classes)
        coll_by_class = loaded.collections
    wanted = _wanted_classes(classes, recons, ann, data)
    cameras = {name: _read_cameras(Path(rdir), wanted) for name, rdir in recons.items()}  # method -> class -> file
    for name, rdir in recons.items():
        _check_same_objects(name, Path(rdir), cameras[name], ann.ann_class, ann.source_of, data)
    in_scope = [a for a, c in ann.ann_class.items()
                if str(a) in ann.gt_entries and (split is None or ann.split_of.get(a) == split) and c is not None]
    without = _classes_without_reconstruction(recons, [ann.ann_class[a] for a in in_scope], classes)
    targets = [a for a in in_scope if ann.ann_class[a] in wanted]
    targets.sort(key=_id_order)
    methods = list(recons) + (["Puffball", "SFMc"] if baselines and shapes else [])
    scorer = ShapeScorer(ann.gt_path.parent, recons, cameras, step_percent, baselines, coll_by_class)
    t0 = time.perf_counter()
    work = [(aid, ann.gt_entries[str(aid)], {"class": ann.ann_class[aid], "split": ann.split_of.get(aid, "")})
            for aid in targets]
    rows = score_shapes(scorer, work, default_jobs(len(work)) if jobs is None else jobs, progress) if shapes \
        else [row for _aid, _entry, row in work]
    objects: dict[str, dict] = {str(aid): row for aid, row in zip(targets, rows)}
    per_class = _class_errors(objects, methods)
    viewpoints = _class_viewpoints(list(per_class), objects, ann, cameras)
    means = {}
    for mth in methods:
        vals = [per_class[c][mth]["mean"] for c in per_class if per_class[c][mth]["mean"] is not None]
        means[mth] = float(np.mean(vals)) if vals else None
    res = {"data": str(data), "gt": str(ann.gt_path), "split": split, "step_percent": step_percent,
           "methods": methods, "recons": {k: str(v) for k, v in recons.items()}, "objects": objects,
           "classes": per_class, "mean_over_classes": means, "viewpoints": viewpoints,
           "classes_without_reconstruction": without}
    res["quality"] = reliability.quality_vs_error(res)
    res["seconds"] = round(time.perf_counter() - t0, 2)
    return res


@dataclasses.dataclass
class _Annotations:
    """What :func:`evaluate` reads of the annotation file and its ground truth; ids as strings."""

    gt_path: Path
    gt_entries: dict  # id -> its gt.json record
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
    gt_entries = gt_all.get("annotations", gt_all)
    dataset = read_json(data)
    anns = [a for a in dataset.get("annotations", []) if isinstance(a, dict) and object_id(a.get("id")) is not None]
    split_of = {str(a["id"]): a.get("split", "") for a in anns}
    if split is not None and split not in split_of.values():
        present = sorted({repr(s) if s else "none" for s in split_of.values()})
        raise ValueError(f"no annotation of {data} is in split {split!r} (its splits: {', '.join(present) or 'none'})")
    key_of = class_keys(dataset.get("categories", []))
    return _Annotations(gt_path=gt_path, gt_entries=gt_entries, categories=dataset.get("categories", []),
                        key_of=key_of, split_of=split_of,
                        ann_class={str(a["id"]): key_of.get(str(a.get("category_id"))) for a in anns},
                        original={str(a["id"]): a["id"] for a in anns},
                        source_of={str(a["id"]): annotation_source(a) for a in anns},
                        object_of={str(a["id"]): _physical_object(a) for a in anns})


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


def _class_errors(objects: dict, methods: list[str]) -> dict[str, dict]:
    """Per class (sorted) and method: mean, median, count and missing of the objects' finite ``error_percent``."""
    per_class: dict[str, dict] = {}
    for cls in sorted({r["class"] for r in objects.values()}):
        rows = [r for r in objects.values() if r["class"] == cls]
        per_class[cls] = {}
        for mth in methods:
            errs = [r[mth]["error_percent"] for r in rows if isinstance(r.get(mth), dict)
                    and r[mth].get("error_percent") is not None and math.isfinite(r[mth]["error_percent"])]
            per_class[cls][mth] = {"mean": float(np.mean(errs)) if errs else None,
                                   "median": float(np.median(errs)) if errs else None,
                                   "count": len(errs), "missing": len(rows) - len(errs)}
    return per_class


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
    """Markdown table in the shape of the paper's Table 1: per class mean error per method, and the mean."""
    methods = res["methods"]
    lines = ["| class | " + " | ".join(methods) + " |", "|---" * (len(methods) + 1) + "|"]
    for cls, row in sorted(res["classes"].items()):
        vals = [row[m]["mean"] for m in methods]
        finite = [v for v in vals if v is not None]
        best = min(finite) if finite else None
        cells = [f"**{_fmt(v)}**" if v is not None and v == best else _fmt(v) for v in vals]
        n = max(row[m]["count"] for m in methods)
        lines.append(f"| {cls} ({n}) | " + " | ".join(cells) + " |")
    means = [res["mean_over_classes"][m] for m in methods]
    lines.append("| **mean** | " + " | ".join(_fmt(v) for v in means) + " |")
    return "\n".join(lines)


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
                    help="reconstruction directory, or NAME=DIR to name the method; repeat to compare methods")
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
    recons = {}
    for item in args.recon:
        name, _, path = item.rpartition("=")
        name = name or ("Full" if not recons else Path(path).name)
        if name in recons:
            print(f"error: two --recon are named {name} ({recons[name]} and {path}): name them apart "
                  "(--recon NAME=DIR)", file=sys.stderr)
            return 2
        recons[name] = path
    for name, p in recons.items():
        if not Path(p).is_dir():
            print(f"error: reconstruction directory {p} ({name}) not found", file=sys.stderr)
            return 2
    made = bool(args.out) and not Path(args.out).exists()
    if args.out:
        writable_folder(args.out)  # before minutes of work, not after
    status = None
    try:
        status = _evaluate_and_write(args, recons)
    finally:
        if made and status != 0:  # the folder made by the check above, left empty: removed
            _remove_if_empty(Path(args.out))
    return status


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
    """The methods whose run stopped after the cameras (``stage: cameras`` in its ``config.yaml``): no shapes."""
    out = []
    for name, rdir in recons.items():
        try:
            if read_run_config(Path(rdir) / "config.yaml").stage == "cameras":
                out.append(name)
        except Exception:  # noqa: BLE001 - no or damaged config: nothing to say
            pass
    return out


def _remove_if_empty(folder: Path) -> None:
    try:
        folder.rmdir()
    except OSError:
        pass


def _evaluate_and_write(args, recons: dict) -> int:
    """The evaluation, its tables printed and, with ``--out``, written; the exit status."""
    try:
        res = evaluate(args.data, recons, gt=args.gt, split=args.split, baselines=args.baselines,
                       step_percent=args.step_percent, classes=split_classes(args.classes),
                       progress=not args.quiet, shapes=not args.viewpoints_only, jobs=args.jobs)
    except (FileNotFoundError, ValueError, CocoFormatError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    cams_only = [] if args.viewpoints_only else _camera_only(recons)
    if cams_only:
        print(f"note: {', '.join(cams_only)} stopped after the cameras (stage=cameras): no shapes to score; "
              "--viewpoints-only evaluates the viewpoints alone", file=sys.stderr)
    for cls, lacking in res["classes_without_reconstruction"].items():
        print(f"note: class {cls} has no reconstruction in {', '.join(lacking)}"
              + ("" if args.classes or len(lacking) < len(recons) else "; not evaluated"), file=sys.stderr)
    shapes, views = format_shape_table(res), format_viewpoint_table(res)
    if not args.viewpoints_only:
        print("Symmetric RMS error, % of the ground-truth bounding-box diagonal (objects per class in brackets)")
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
