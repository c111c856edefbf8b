"""The export: a training dataset (a zarr v3 store) from a reconstruction directory.

For every reconstructed object the export writes one sample into a zarr v3 store: one group per
class, one compressed array per field, one chunk per sample (:mod:`carvi_torch.export.store`;
layout and fields in ``docs/export.md``). :class:`carvi_torch.training.LiftedDataset` reads it,
and so does zarr alone. ``--format cmr`` / ``--format ucmr`` write the annotation files of
category-specific mesh reconstruction codebases instead (:mod:`carvi_torch.export.formats`).

Objects whose outputs are missing or unreadable (no voxels, no mesh, files holding unusable data, no camera,
an unusable camera or no readable angles, a finished run's class folder missing), those the annotations' reader
skips, and the ``cameras.json`` entries that name no object of the annotations are reported by annotation id
with the reason, in the console and in the root group's ``skipped`` attribute; the rest is exported. The
per-object work runs in ``--workers`` processes (default: one per core), fed one stream of jobs over
every class; the main process writes the results in order as they come
(:mod:`carvi_torch.export.command` is the command line).
"""
from __future__ import annotations

import math
import multiprocessing as mp
import os
import time
from collections import Counter, deque
from itertools import islice
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np
from tqdm.auto import tqdm

from ..io.coco import load_coco
from ..io.layout import object_file, object_mesh, other_settings, other_settings_text
from ..io.writer import INT64_RANGE, start_method
from ..runtime import LeanProcessPool, cores, stable_hash, torch_threads
from .source import (NOT_YET, NOT_IN_ANNOTATIONS, SettingsTally, camera_entry, camera_problem, class_cameras,
                     class_categories, class_extent, class_scope, data_path, load_skips, missing_class_reason,
                     recon_config, run_classes, skip_all, unfinished)
from .objects import (canonical_occupancy, depth_map, init_worker, safe_export_object,
                      safe_export_objects, view_occupancy)
from .settings import settings_problem
from .store import (ATTRS_KEY, DEFAULT_FIELDS, FIELDS, FORMAT_VERSION, MESH_FIELDS, InterruptedAfterSwap, StoreWriter,
                    group_name_problem)

__all__ = ["export", "report_skipped", "FIELDS", "DEFAULT_FIELDS", "view_occupancy", "canonical_occupancy",
           "depth_map", "ATTRS_KEY", "FORMAT_VERSION"]

#: Objects per task handed to a worker process (fewer round trips than one object per task).
TASK_OBJECTS = 4
#: Tasks queued per worker process at most (bounds the memory of queued jobs and of results not yet written).
TASKS_PER_WORKER = 4


def _int_id(value) -> np.int64:
    """An id as the int64 field holds it: the id when it is an integer int64 holds, else -1 (the class
    group's ``annotation_ids`` and :class:`~carvi_torch.training.LiftedDataset`'s ``annotation_key`` carry
    every id as given)."""
    lo, hi = INT64_RANGE
    return np.int64(value) if isinstance(value, int) and lo <= value <= hi else np.int64(-1)


# =========================================================================== the export (main process)


#: The angles of a ``cameras.json`` entry, in the order of the store's ``viewpoint`` field.
_ANGLE_KEYS = ("azimuth_deg", "elevation_deg", "roll_deg")


def _viewpoint_or_none(entry: dict) -> list[float] | None:
    """Azimuth, elevation, roll (radians) of a ``cameras.json`` entry: the angles the run wrote (from its final
    camera's ``R``), or, where a file from elsewhere has none, computed from ``refined.R``; None where neither
    is readable (the object is then skipped with a reason). Only what a malformed entry raises means that."""
    try:
        angles = [math.radians(float(entry[k])) for k in _ANGLE_KEYS]
        if all(math.isfinite(a) for a in angles):
            return angles
    except (KeyError, TypeError, ValueError):
        pass
    try:
        import torch  # the main process has it loaded already (the annotations)

        from ..cameras import azimuth_elevation_roll_from_rotation

        R = torch.as_tensor(np.asarray(entry["refined"]["R"], dtype=np.float64).reshape(3, 3))
        return [float(x) for x in azimuth_elevation_roll_from_rotation(R)]
    except (KeyError, TypeError, ValueError, OverflowError):  # no R, not 3 x 3 numbers, a number beyond float
        return None


def _jobs(coll, cname: str, ci: int, cdir: Path, cams: dict, settings: dict, skipped: list,
          no_files: str = "no voxels (not reconstructed)"):
    """The jobs of a class's objects that have a usable camera, voxels and a mesh (the others go to ``skipped``
    with their reason; ``no_files``: that of an object without voxels)."""
    jobs = []
    for i, aid in enumerate(coll.annotation_ids):
        entry = camera_entry(cams, aid)
        vox = object_file(cdir, "voxels", aid)
        mesh = object_mesh(cdir, aid, settings["mesh_format"])  # the run's own format first
        viewpoint = _viewpoint_or_none(entry)
        reason = ("no camera in cameras.json" if entry.get("refined") is None else
                  "no readable azimuth/elevation/roll or R in cameras.json" if viewpoint is None else
                  camera_problem(entry))
        if reason is None:
            reason = no_files if not vox.is_file() else "no mesh (not reconstructed)" if mesh is None else None
        if reason is not None:
            skipped.append({"annotation_id": aid, "class": cname, "source": coll.sources[i], "reason": reason})
            continue
        q = entry.get("quality")
        jobs.append({**settings, "class": cname, "class_index": ci, "annotation_id": aid,
                     "viewpoint": viewpoint, "image_id": coll.image_ids[i],
                     "source": coll.sources[i],
                     "seed": [settings["seed"], stable_hash(cname), i],
                     "mask": coll.masks[i].cpu().numpy(), "keypoints": coll.keypoints[i].cpu().numpy(),
                     "visible": coll.visible[i].cpu().numpy(),
                     "canvas_scale": float(coll.canvas_from_image.scale[i]),
                     "canvas_offset": coll.canvas_from_image.offset[i].double().numpy(), "camera": entry["refined"],
                     "quality": float(q) if q is not None else float("nan"), "voxels": str(vox), "mesh": str(mesh),
                     "fingerprint": coll.fingerprints[i]})
    return jobs


def _class_jobs(loaded, recon: Path, class_names: list, settings: dict, writer: StoreWriter, skipped: dict, bar,
                no_files: str, data: Path):
    """The jobs of every class, class by class, read lazily (a class's ``cameras.json`` when its first job is
    asked for); objects that cannot be exported go to ``skipped[class]`` with their reason, and so do the
    entries of ``cameras.json`` that name no object of the annotation file ``data``."""
    for ci, cname in enumerate(class_names):
        coll, cdir = loaded.collections.get(cname), recon / cname
        if coll is None:  # every object of the class skipped at load
            continue
        if (why := group_name_problem(cname)) is not None:
            skipped[cname].extend(skip_all(coll, cname, f"the class key {cname!r} cannot name a group of the zarr "
                                                        f"store ({why}); --format cmr or ucmr exports it"))
            bar.update(len(coll))
            continue
        cams = class_cameras(coll, cname, recon, skipped[cname], no_files == NOT_YET, data)
        if cams is None:
            bar.update(len(coll))
            continue
        writer.extent[cname] = class_extent(cams)
        jobs = _jobs(coll, cname, ci, cdir, cams, {**settings, "extent": writer.extent[cname]}, skipped[cname],
                     no_files)
        bar.update(len(coll) - len(jobs))
        yield from jobs


def _stream(jobs: Iterable[dict], pool, workers: int) -> Iterator[tuple[dict, dict | None, str | None]]:
    """``(job, sample, reason)`` for every job, in job order: one stream over every class, tasks of
    :data:`TASK_OBJECTS` objects, at most :data:`TASKS_PER_WORKER` tasks per worker in flight (no barrier:
    a worker takes the next task as soon as it is free, and results are handed on as they come, in order)."""
    if pool is None:
        for job in jobs:
            yield (job, *safe_export_object(job))
        return
    source, pending = iter(jobs), deque()

    def submit() -> bool:
        task = list(islice(source, TASK_OBJECTS))
        if task:
            pending.append((task, pool.submit(safe_export_objects, task)))
        return bool(task)

    while len(pending) < TASKS_PER_WORKER * workers and submit():
        pass
    while pending:
        task, future = pending.popleft()
        submit()
        for job, result in zip(task, future.result()):
            yield (job, *result)


def _skipped_in_order(class_names: list, skipped: dict) -> list:
    return [s for c in class_names for s in skipped[c]]


def report_skipped(recon: Path, skipped_list: list, exported: int, pending: bool, progress: bool, data: Path,
                   where: str = "reasons in the store's 'skipped' attribute",
                   tally: SettingsTally | None = None) -> None:
    """The skipped objects, one line each (a count alone when ``progress`` is off; ``where``: where the reasons
    are); one warning line counting, per class, the ``cameras.json`` entries that name no object of the
    annotation file ``data``; an unfinished run's objects not reconstructed yet in one line, counted per class,
    with the classes it has not started; one warning line where the exported objects were made with other
    settings than the run's ``config.yaml``'s (``tally``: :class:`~carvi_torch.export.source.SettingsTally`; without
    one, the folder's record: :func:`~carvi_torch.io.layout.other_settings`)."""
    import sys

    other = [s for s in skipped_list if s["reason"] != NOT_YET]
    for s in other if progress else ():
        tqdm.write(f"export: {s['class']} annotation {s['annotation_id']} skipped: {s['reason']}")
    if other and not progress:
        print(f"export: {len(other)} object(s) skipped ({where})")
    extra = Counter(s["class"] for s in other if s["reason"].startswith(NOT_IN_ANNOTATIONS))
    if extra:
        print(f"warning: {sum(extra.values())} camera(s) in cameras.json name no object of the annotation file "
              f"{data}: {', '.join(f'{n} of class {c}' for c, n in extra.items())} (listed as skipped; was the run "
              "made from another file?)", file=sys.stderr)
    made = tally.line() if tally is not None else other_settings_text(other_settings(recon))
    if made:
        print(f"warning: {recon} holds objects made with other settings than its config.yaml's: {made}; the "
              "export's made_with_run_settings says which; reconstruct with overwrite=true makes them alike",
              file=sys.stderr)
    if pending:
        print(f"warning: {recon} is an unfinished run (interrupted or still running): exported the {exported} "
              f"object(s) it finished; {_not_yet(recon, skipped_list)} (rerun reconstruct to finish it)",
              file=sys.stderr)


def _not_yet(recon: Path, skipped_list: list) -> str:
    """``N not reconstructed yet are left out: car 28, chair 40 (not started)``."""
    per_class = Counter(s["class"] for s in skipped_list if s["reason"] == NOT_YET)
    parts = [f"{c} {n}" + ("" if (recon / c / "cameras.json").is_file() else " (not started)")
             for c, n in per_class.items()]
    return f"{sum(per_class.values())} not reconstructed yet are left out" + (": " + ", ".join(parts) if parts else "")


def _check_exportable(recon: Path, cfg) -> None:
    if cfg.stage == "cameras":
        raise ValueError(f"{recon} is a camera-only run (stage=cameras): it has no shapes for the zarr store "
                         "(export --format cmr or ucmr takes its cameras; nothing was written)")


def _load(recon: Path, cfg, data: Path, classes, pending: bool):
    """The annotations of the classes to export (those of the run's that ``classes`` asks for; ``ValueError``
    naming an unknown one), the classes' names in store order: every class of the run's input when the run
    is unfinished (a class not started yet included), else those the run wrote cameras for; and the classes of
    a finished run without a ``cameras.json`` (skipped by the run, or their folder removed: their objects are
    reported)."""
    covered = run_classes(cfg.classes, recon)
    with torch_threads(1):
        loaded = load_coco(data, canvas_size=cfg.input.canvas_size, margin=cfg.input.canvas_margin,
                           classes=classes or covered)
    scope = class_scope(loaded.dataset["categories"], covered, classes, recon)
    present = [c for c in scope if pending or (recon / c / "cameras.json").is_file()]
    return loaded, present, [c for c in scope if c not in present]


def _missing_class_skips(loaded, recon: Path, missing: list) -> dict[str, list]:
    """``{class: [skipped objects]}`` of the classes of a finished run that have no folder: the objects skipped at
    load and every other object of the class, with the reason
    (:func:`~carvi_torch.export.source.missing_class_reason`)."""
    out = load_skips(loaded.problems, missing)
    for c in missing:
        coll = loaded.collections.get(c)
        out[c].extend(skip_all(coll, c, missing_class_reason(recon, c)) if coll is not None else ())
    return out


def _none_exported(skipped_list: list, out: Path) -> str:
    """The line of an export that had objects and exported none of them (the first reason quoted)."""
    first = skipped_list[0]
    return (f"none of the {len(skipped_list)} object(s) could be exported (the first, {first['class']} annotation "
            f"{first['annotation_id']}: {first['reason']}); {out} is as it was")


def export(recon: str | Path, out: str | Path, resolution: int = 32, points: int = 2048, shard_size: int = 256,
           seed: int = 0, progress: bool = True, classes=None, workers: int | None = None,
           mesh: bool = False) -> dict:
    """Export every reconstructed object of ``recon`` into a zarr v3 store at ``out``.

    The store is swapped in at ``out`` when complete: an export that raises (Ctrl-C included) leaves ``out`` as
    it was, except :class:`~carvi_torch.export.store.InterruptedAfterSwap` (Ctrl-C during the swap: the new store
    is in place, and its ``result`` is what this returns). A camera-only run (``stage=cameras``), or an
    unfinished one with no object finished, raises ``ValueError`` (nothing written); an unfinished run's
    finished objects are exported, with one warning line.

    Returns the root group's description (its ``carvi_export`` attribute) plus ``samples``: one entry
    (class, annotation_id, image_id, source) per exported sample, in store order.
    """
    problem = settings_problem(resolution, points, shard_size, seed, workers, options=False)
    if problem is not None:
        raise ValueError(f"{problem} (nothing was written)")
    recon, out = Path(recon), Path(out)
    cfg = recon_config(recon)
    _check_exportable(recon, cfg)
    pending = unfinished(recon)
    data = data_path(recon, cfg)
    canvas = cfg.input.canvas_size
    workers = cores() if workers is None else int(workers)
    t0 = time.perf_counter()
    writer = StoreWriter(out, shard_size, DEFAULT_FIELDS + (MESH_FIELDS if mesh else []))  # --out checked first
    settings = {"canvas": canvas, "resolution": resolution, "points": points, "seed": seed, "mesh_field": mesh,
                "mesh_format": cfg.mesh.format}  # the run's own meshes first, where another format's are left
    tally = SettingsTally.of(recon, cfg)
    try:
        loaded, class_names, missing = _load(recon, cfg, data, classes, pending)
        writer.categories = class_categories(loaded.dataset["categories"], class_names)
        skipped = load_skips(loaded.problems, class_names)
        samples = _write_samples(loaded, recon, class_names, settings, writer, skipped, progress, workers,
                                 NOT_YET if pending else "no voxels (not reconstructed)", data, tally)
        if pending and not samples:
            raise ValueError(f"{recon} is an unfinished run with no object reconstructed yet: nothing to export "
                             "(nothing was written)")
        skipped.update(_missing_class_skips(loaded, recon, missing))
        skipped_list = _skipped_in_order([*class_names, *missing], skipped)
        if not samples and skipped_list:  # an empty store would replace an earlier, good one
            raise ValueError(_none_exported(skipped_list, out))
        attrs = {"recon": str(recon), "data": str(data), "canvas_size": canvas, "resolution": resolution,
                 "points": points, "seed": seed, "classes": class_names,
                 "class_extent": {c: writer.extent[c] for c in class_names if c in writer.extent},
                 "categories": writer.categories,
                 "skipped": skipped_list, "made_with_other_settings": tally.record(),
                 "seconds": round(time.perf_counter() - t0, 3)}
        desc = writer.close(attrs)
    except InterruptedAfterSwap as e:  # Ctrl-C during the swap: the new store is complete, nothing to undo
        e.result = {**e.result, "samples": samples}
        raise
    except BaseException:
        writer.abort()
        raise
    report_skipped(recon, skipped_list, len(samples), pending, progress, data, tally=tally)
    return {**desc, "samples": samples}


def _write_samples(loaded, recon: Path, class_names: list, settings: dict, writer: StoreWriter, skipped: dict,
                   progress: bool, workers: int, no_files: str, data: Path, tally: SettingsTally) -> list:
    """Compute every object (in ``workers`` processes, or here) and add it to ``writer``, its
    ``made_with_run_settings`` from the settings its voxels file records (counted in ``tally``); returns the
    samples' entries (class, annotation_id, image_id, source) in store order."""
    samples = []
    bar = tqdm(total=sum(len(loaded.collections.get(c, ())) for c in class_names), desc="export",
               disable=not progress)
    ctx = mp.get_context(start_method())
    if workers > 0 and start_method() == "forkserver":  # workers fork from a server that imported them once
        ctx.set_forkserver_preload([safe_export_objects.__module__])
    pool = (LeanProcessPool(workers, mp_context=ctx, initializer=init_worker, initargs=(os.getpid(),))
            if workers > 0 else None)
    try:
        with torch_threads(1):
            jobs = _class_jobs(loaded, recon, class_names, settings, writer, skipped, bar, no_files, data)
            current = None
            for job, sample, reason in _stream(jobs, pool, workers):
                bar.update(1)
                if job["class"] != current and current is not None:
                    writer.finish(current)  # a class is complete: written while the workers go on
                current = job["class"]
                if reason is not None:  # after the objects skipped before the export: both in annotation order
                    skipped[current].append({k: job[k] for k in ("annotation_id", "class", "source")}
                                            | {"reason": reason})
                    continue
                sample["annotation_id"], sample["image_id"] = _int_id(job["annotation_id"]), _int_id(job["image_id"])
                sample["made_with_run_settings"] = np.bool_(tally.add(sample.pop("settings")))
                writer.add(job["class"], sample, job)
                samples.append({k: job[k] for k in ("class", "annotation_id", "image_id", "source")})
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
        bar.close()
    return samples
