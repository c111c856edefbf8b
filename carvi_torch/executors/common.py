"""What every executor does around the classes: check the request, load the data, keep the summary.

A run is: :func:`open_run` (user errors first, with nothing written: the device, the output
folder, the annotation file), the classes (the executor's business), then :func:`finish_run`
(``summary.json`` merged with an earlier run's classes, ``preview.png``) and :func:`exit_status`.
"""
from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from .. import carve
from ..config import Config, ConfigError, settings_changed
from ..io import coco
from ..io.layout import (KINDS, PER_OBJECT_SETTINGS, RUN_NAMES, ResumeCheck, class_dir, linked_path, object_file,
                         other_objects)
from ..io.outputs import read_json, write_bytes, write_json
from ..io.results import ClassReport, drop_cameras
from ..runtime import FolderBusy, FolderLock, log, peak_rss_mb, stable_hash, unwritable_above

__all__ = ["RunSetup", "check_request", "open_run", "finish_run", "exit_status", "class_generator",
           "prepare_data", "read_ground_truth", "book_class"]


@dataclass
class RunSetup:
    """A checked run: where it writes, its device, its data and the summary so far."""

    cfg: Config
    out: Path
    device: torch.device
    loaded: coco.LoadResult
    gt: dict | None
    summary: dict
    changed: dict = field(default_factory=dict)  # {setting: (values finished objects were made with, ..., now)}
    t_start: float = field(default_factory=time.perf_counter)
    started_ns: int = field(default_factory=time.time_ns)  # files older than this are an earlier run's
    earlier: dict = field(default_factory=dict)  # classes an earlier run into the same folder reported
    lock: FolderLock | None = None  # held on ``out`` until the run ends (the executor releases it)
    kept: list = field(default_factory=list)  # those of them, with objects, that this run does not touch


def _check_out(out: Path) -> None:
    """The output folder must be a folder this process can create and write (nothing is created here)."""
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file, not a folder")
    why = unwritable_above(out / "summary.json")  # the folder itself where it exists, else the nearest above
    if why:
        raise ConfigError(f"--out {out}: {why}")
    _check_links(out)


def _check_links(out: Path, keys=()) -> None:
    """No path the run writes under ``out`` is a symbolic link (:func:`~carvi_torch.io.layout.linked_path`)."""
    link = linked_path(out, keys)
    if link is not None:
        raise ConfigError(f"--out {out}: {link} is a symbolic link, and a run writes nothing outside --out; "
                          "remove the link or choose another --out")


def _check_references(references: str, collections: dict) -> None:
    """``references`` names a split that some loaded object has (else the run would reconstruct nothing and
    say nothing of why)."""
    present = {s for c in collections.values() for s in c.splits}
    if references != "all" and references not in present:
        named = ", ".join(repr(s) for s in sorted(present - {""}))
        raise ConfigError(f"references={references}: no loaded object has that split; "
                          + (f"the splits present are {named} (or all)" if named else
                             "no object has a split (references=all)"))


def _check_class_folders(out: Path, keys) -> None:
    """Once the classes are known, before any work: no link where the run writes (:func:`_check_links`), no
    file where a class's folder or one of its per-object folders goes, and none of those folders read-only (the
    class would fail after all its work)."""
    _check_links(out, keys)
    for key in keys:
        for path in (out / key, *(out / key / kind for kind in KINDS)):
            if path.exists() and not path.is_dir():
                raise ConfigError(f"--out {out}: {path} is a file where the run writes a folder of class "
                                  f"{key!r}; move it or choose another --out")
            if path.is_dir() and not os.access(path, os.W_OK | os.X_OK):  # every object of the class would fail
                raise ConfigError(f"--out {out}: {path} is not writable (the run writes class {key!r} there); "
                                  "give yourself write access or choose another --out")


def _check_cameras_only(out: Path) -> None:
    """``stage=cameras`` writes no shapes but would rewrite ``config.yaml``, the classes' ``cameras.json`` and
    their summary entries: into a folder that holds finished objects (meshes or voxels of any class) it would
    leave those objects next to cameras and a record they were not made with, so it is refused."""
    if not out.is_dir():
        return
    for cdir in sorted(out.iterdir()):
        if cdir.name in RUN_NAMES or not cdir.is_dir() or cdir.is_symlink():
            continue
        for kind in ("meshes", "voxels"):
            folder = cdir / kind
            if folder.is_dir() and not folder.is_symlink() and any(folder.iterdir()):
                raise ConfigError(f"--out {out} holds finished objects ({folder}), and stage=cameras would replace "
                                  "their run's cameras and record; choose another --out for a camera-only run")


def check_request(cfg: Config) -> torch.device:
    """The user errors a run can have before it starts, as :class:`ConfigError` (nothing is written):
    an unknown or absent device, an output folder that is a file or not writable (or, for ``stage=cameras``,
    one that holds finished objects), annotations that do not exist, a ``classes`` name that is no class of the
    embedded collection (without ``data``; those of a file are checked once it is read). Returns the device."""
    device = cfg.resolve_device()
    _check_out(Path(cfg.out))
    if cfg.stage == "cameras":
        _check_cameras_only(Path(cfg.out))
    if cfg.data is not None and not Path(cfg.data).is_file():
        raise ConfigError(f"--data {cfg.data}: no such file")
    if cfg.gt is not None and not Path(cfg.gt).is_file():
        raise ConfigError(f"gt={cfg.gt}: no such file")
    if cfg.data is None and cfg.classes:  # the embedded collection's classes, known before it is generated
        from ..synthetic.procedural import CATEGORIES

        _check_classes(cfg.classes, {c: [c] for c in CATEGORIES}, "the embedded collection")
    return device


def _check_classes(asked, names: dict, where: str) -> None:
    """Every name of ``classes`` is a class of the data (:func:`~carvi_torch.io.coco.select_classes`, the check of
    every command's ``--classes``): else a user error naming the unknown ones and the data's classes."""
    if asked:
        try:
            coco.select_classes(asked, names, where)
        except ValueError as e:
            raise ConfigError(str(e)) from None


def prepare_data(cfg: Config) -> tuple[Path, Path | None]:
    """The annotation file (and ``gt.json`` if any) to run on; generates the embedded default when needed."""
    if cfg.data:
        data = Path(cfg.data)
        gt = Path(cfg.gt) if cfg.gt else data.with_name("gt.json")
        return data, (gt if gt.is_file() else None)
    from ..synthetic import procedural

    return procedural.default_collection(Path(cfg.out) / "input", cfg.input.procedural_instances, cfg.seed,
                                         cfg.progress, log=log.info)


def open_run(cfg: Config) -> RunSetup:
    """Check the request, read the annotations, then create the output folder and ``config.yaml``.

    Raises :class:`ConfigError` or :class:`~carvi_torch.io.coco.CocoFormatError` for a user error,
    before anything is written (the embedded default collection is generated into ``OUT/input``, once the
    run holds the folder's lock: a run refused because another holds it writes nothing there).
    """
    device = check_request(cfg)
    out = Path(cfg.out)
    lock = _lock(out) if cfg.data is None else None  # the embedded default is generated into OUT/input
    try:
        data_path, gt_path, loaded, gt, load_s = _read_input(cfg, device)
        lock = lock or _lock(out)
        previous = _earlier_summary(out)
        earlier, earlier_data = _earlier_classes(previous, cfg)
        changed = settings_changed(out / "config.yaml", cfg, previous)
        write_bytes(out / "config.yaml", cfg.to_yaml().encode())
    except BaseException:
        if lock is not None:
            lock.release()
        raise
    summary = {"data": str(Path(data_path).resolve()), "gt": str(Path(gt_path).resolve()) if gt_path else None,
               "device": str(device), "torch_threads": torch.get_num_threads(),
               "carve_backend": carve.resolve_backend(cfg.carve.backend, device, cfg.carve.interpolation),
               "load_seconds": round(load_s, 3), "input_problems": [p.to_dict() for p in loaded.problems],
               "classes": {}}
    if earlier_data is not None and earlier_data != summary["data"]:
        summary["data_changed"] = {"previous": earlier_data, "now": summary["data"]}
    return RunSetup(cfg, out, device, loaded, gt, summary, changed, earlier=earlier, lock=lock)


def _read_input(cfg: Config, device: torch.device) -> tuple:
    """``(data_path, gt_path, loaded, gt, load_seconds)``: the annotations (:func:`prepare_data`) and ground truth
    read and checked against the request (classes, references, the class folders under ``--out``); user errors
    as :func:`open_run` says."""
    data_path, gt_path = prepare_data(cfg)  # reads only, unless it generates the embedded default
    t0 = time.perf_counter()
    loaded = coco.load_coco(data_path, canvas_size=cfg.input.canvas_size, margin=cfg.input.canvas_margin,
                            device=device, classes=cfg.classes, max_image_pixels=cfg.input.max_image_pixels)
    load_s = time.perf_counter() - t0
    _check_classes(cfg.classes, coco.class_names(loaded.dataset["categories"]), f"--data {data_path}")
    gt, gt_problem = read_ground_truth(gt_path, cfg.study.cameras == "gt")
    if gt_problem is not None:
        loaded.problems.append(gt_problem)
        gt_path = None
    _check_references(cfg.references, loaded.collections)
    _check_class_folders(Path(cfg.out), loaded.collections)
    return data_path, gt_path, loaded, gt, load_s


def _lock(out: Path) -> FolderLock:
    """``out`` made and locked for this run (:class:`~carvi_torch.runtime.FolderLock`): a second run into it while
    this one lives is a user error, before it writes anything."""
    out.mkdir(parents=True, exist_ok=True)
    try:
        return FolderLock(out)
    except FolderBusy as e:
        raise ConfigError(f"--out {e}; wait for that run to end or choose another --out") from None


def read_ground_truth(path: Path | None, needed: bool) -> tuple[dict | None, coco.Problem | None]:
    """``gt.json``'s content (``None`` when there is none) and the problem of an unreadable one.

    ``needed`` (``cameras=gt``): a missing or unreadable file is a user error (:class:`ConfigError`);
    otherwise an unreadable file is a warning and the run goes on without ground truth.
    """
    if path is None:
        if needed:
            raise ConfigError("cameras=gt needs ground truth: no gt.json beside --data (or pass gt=FILE)")
        return None, None
    try:
        return read_json(path), None
    except (OSError, ValueError) as e:
        if needed:
            raise ConfigError(f"cameras=gt: {e}") from None
        return None, coco.Problem(f"ground truth unreadable, going on without it: {e}", stage="gt", fatal=False)


def announce(setup: RunSetup) -> None:
    """Log the input problems (those of a whole file or class as warnings, an object's warnings as info:
    there may be thousands), the classes asked for that have no usable object, and changed settings
    (:func:`_settings_record`)."""
    for p in setup.loaded.problems:
        (log.warning if p.fatal or p.annotation_id is None else log.info)(p.message())
    moved = setup.summary.get("data_changed")
    if moved:
        log.warning(f"{setup.out} holds a run on other annotations ({moved['previous']}); its finished objects "
                    "are resumed only where an object's own inputs are unchanged, the others are redone")
    _skipped_classes(setup)
    _settings_record(setup)


def _skipped_classes(setup: RunSetup) -> None:
    """The classes asked for that have no usable object: skipped, into the summary and the log (an earlier run's
    ``cameras.json`` of one removed: :func:`~carvi_torch.io.results.drop_cameras`)."""
    names = {c.meta.name for c in setup.loaded.collections.values()} | set(setup.loaded.collections)
    keys = coco.class_names(setup.loaded.dataset.get("categories", []))
    for c in setup.cfg.classes or []:  # each a class of the data (open_run refuses any other name)
        if c not in names:
            why = "no usable object of this class"
            report = ClassReport(c)
            for key in keys.get(c, [c]):
                drop_cameras(setup.out, key, report)
            setup.summary["classes"][c] = {"status": "skipped", "objects": 0, "reconstructed": 0,
                                           "failures": [{"stage": "load", "reason": why}],
                                           **({"warnings": report.warnings} if report.warnings else {}),
                                           **_other_objects(setup, c, keys.get(c, [c]))}
            log.warning(f"{c}: {why}")
            for w in report.warnings:
                log.warning(f"  {c}: {w}")


def _settings_record(setup: RunSetup) -> None:
    """The settings finished objects in the folder were made with, other than this run's (``setup.changed``, from
    :func:`~carvi_torch.config.settings_changed`), kept where such objects can stay (never for
    :data:`~carvi_torch.io.layout.PER_OBJECT_SETTINGS`, which the resume check handles object by object, unless for
    the classes with objects that the run does not touch, ``setup.kept``: an earlier run's classes that it leaves).
    With ``overwrite`` too: the run redoes those objects, but until it has (a run stopped on the way leaves some),
    they are in the folder. Logged in one line (with ``overwrite`` alone as info: the run redoes them all) and put
    into the summary (``resumed_from_other_settings``, :func:`_settings_entry`), which is written at once: a run
    stopped before its first class still carries the record on (:func:`_settings_at_end` drops it where no such
    object is left)."""
    if not setup.changed:
        return
    ours = set(setup.loaded.collections) | set(setup.summary["classes"])
    setup.kept = sorted(k for k, v in setup.earlier.items() if k not in ours and isinstance(v, dict)
                        and (v.get("reconstructed") or v.get("resumed")))
    setup.changed = {k: v for k, v in setup.changed.items() if setup.kept or k not in PER_OBJECT_SETTINGS}
    if not setup.changed:
        return
    where = []
    if set(setup.changed) - set(PER_OBJECT_SETTINGS):
        where.append(("overwrite=true redoes those of the classes it runs, and summary.json names these settings "
                      "until it has") if setup.cfg.overwrite else ("its finished objects whose inputs are unchanged "
                     "are kept as they are (resumed), so pass overwrite=true to redo them"))
    if setup.kept:
        where.append(f"the classes this run does not touch keep their objects as they are ({', '.join(setup.kept)})")
    (log.info if setup.cfg.overwrite and not setup.kept else log.warning)(
        f"{setup.out} holds finished objects made with other settings ("
        + ", ".join(f"{k}: {_made_with(v)}" for k, v in setup.changed.items()) + "); " + "; ".join(where))
    setup.summary["resumed_from_other_settings"] = _settings_entry(setup.changed, wrote=True)
    write_summary(setup)


def _made_with(values: tuple) -> str:
    """``16, 20 -> 24``: the values other than this run's, then this run's (``values``: a ``setup.changed`` entry).

    Example:
        >>> _made_with((16, 24, 24)), _made_with(("ply", "obj"))
        ('16 -> 24', "'ply' -> 'obj'")
    """
    return ", ".join(repr(v) for v in values[:-1] if v != values[-1]) + f" -> {values[-1]!r}"


def _settings_entry(changed: dict, wrote: bool) -> dict:
    """``summary.json``'s ``resumed_from_other_settings``: per setting, the values finished objects in the folder
    were made with, oldest first, then this run's (``[16, 24]``: made with 16, this run's 24; ``[16, 24, 24]``:
    made with 16 and 24). ``wrote``: this run made objects (with its value, then among those they were made with).

    Example:
        >>> _settings_entry({"carve.resolution": (16, 24)}, wrote=True), _settings_entry({"a": (1, 2)}, wrote=False)
        ({'carve.resolution': [16, 24, 24]}, {'a': [1, 2]})
    """
    out = {}
    for k, values in changed.items():
        made, now = list(values[:-1]), values[-1]
        out[k] = made + ([now] if wrote and now not in made else []) + [now]
    return out


def _other_objects(setup: RunSetup, name: str, keys: list[str]) -> dict:
    """``summary.json``'s ``other_objects`` of class ``name`` (folders ``keys``): the mesh and voxels files there
    of objects that are none of the class's usable objects in this run's data
    (:func:`~carvi_torch.io.layout.other_objects`), with their warning line. Every class this run reports gets
    it, whatever became of the class (reconstructed, skipped, failed, or without a usable object)."""
    stems: set[str] = set()
    for key in keys:
        coll = setup.loaded.collections.get(key)
        stems.update(other_objects(class_dir(setup.out, key), coll.annotation_ids if coll is not None else []))
    check = ResumeCheck(others=sorted(stems, key=lambda s: (len(s), s)))
    for line in check.lines(name):
        log.warning(line)
    return check.info()


def class_generator(cfg: Config, key: str) -> torch.Generator:
    """The random source of one class (same seed, same class: same triplets on any executor)."""
    return torch.Generator(device="cpu").manual_seed(cfg.seed + stable_hash(key))


def _earlier_summary(out: Path) -> dict:
    """The ``summary.json`` an earlier run into ``out`` wrote, read once per run (``{}`` where there is none, or
    it cannot be read or holds no JSON object), its malformed class entries left out (:func:`_class_entry_ok`,
    logged in one line): this run knows nothing of those classes, as if the file did not name them."""
    path = out / "summary.json"
    if not path.is_file():
        return {}
    try:
        earlier = read_json(path)
    except (ValueError, OSError):
        return {}
    if not isinstance(earlier, dict):
        return {}
    classes = earlier.get("classes", {})
    if not isinstance(classes, dict):
        log.warning(f"{path}: its classes are no JSON object; taken as unknown (left out of this run's summary)")
        classes = {}
    kept = {k: v for k, v in classes.items() if _class_entry_ok(v)}
    bad = [k for k in classes if k not in kept]
    if bad:
        more = f" and {len(bad) - 5} more" if len(bad) > 5 else ""
        log.warning(f"{path}: malformed entries of class {', '.join(map(repr, bad[:5]))}{more}; taken as unknown "
                    "(left out of this run's summary)")
    return {**earlier, "classes": kept}


#: The counts of a class entry of ``summary.json`` (whole numbers, none negative).
_COUNTS = ("objects", "reconstructed", "resumed", "skipped")


def _class_entry_ok(entry) -> bool:
    """A class entry of ``summary.json`` as a run writes it, as far as a run reads it: an object whose counts
    (:data:`_COUNTS`) are whole numbers of at least 0, ``status`` text, ``failures`` a list of objects, ``warnings``
    a list, ``seconds`` an object of numbers (each where present).

    Example:
        >>> _class_entry_ok({"objects": 6, "reconstructed": 6, "seconds": {"sfm": 0.5}, "failures": []})
        True
        >>> [_class_entry_ok(e) for e in ([6], {"reconstructed": "6"}, {"resumed": None}, {"failures": [1]})]
        [False, False, False, False]
    """
    if not isinstance(entry, dict):
        return False
    failures, seconds = entry.get("failures", []), entry.get("seconds", {})
    return (all(type(entry.get(k, 0)) is int and entry.get(k, 0) >= 0 for k in _COUNTS)
            and isinstance(entry.get("status", ""), str) and isinstance(entry.get("warnings", []), list)
            and isinstance(failures, list) and all(isinstance(f, dict) for f in failures)
            and isinstance(seconds, dict) and all(type(v) in (int, float) for v in seconds.values()))


def _earlier_classes(earlier: dict, cfg: Config) -> tuple[dict, str | None]:
    """The classes an earlier run reported (``earlier``: its ``summary.json``, :func:`_earlier_summary`) and the
    annotation file it read (the file ``None`` with ``overwrite``, which resumes nothing): a dataset can be
    processed in parts, and the summary keeps every part (with ``overwrite`` too: it redoes the classes it runs,
    and those it does not touch keep their files).

    Example:
        >>> _earlier_classes({"classes": {"car": {}}, "data": "a.json"}, Config()), _earlier_classes({}, Config())
        (({'car': {}}, 'a.json'), ({}, None))
    """
    classes, data = earlier.get("classes", {}), earlier.get("data")
    data = data if isinstance(data, str) and not cfg.overwrite else None
    return (classes if isinstance(classes, dict) else {}), data


def write_summary(setup: RunSetup) -> None:
    """``summary.json`` as it stands (atomically, after every class): this run's classes, and those of
    an earlier run into the same folder that this run did not touch."""
    s = dict(setup.summary)
    kept = {k: v for k, v in setup.earlier.items() if k not in s["classes"]}
    if kept:
        s["classes"] = dict(sorted({**s["classes"], **kept}.items()))
        s["classes_from_earlier_runs"] = sorted(kept)
    write_json(setup.out / "summary.json", s)


def book_class(setup: RunSetup, key: str, rep) -> None:
    """A finished class into the summary (classes in name order, whichever finished first), with the
    objects of it skipped at load (:func:`~carvi_torch.io.coco.skipped_at_load`) and the files in its folder of
    objects the data no longer holds (:func:`_other_objects`, however the class ended), its skipped objects and
    warnings into the log (those skipped at load were logged already), and ``summary.json`` written."""
    at_load = coco.skipped_at_load(setup.loaded.problems, key)
    whole = replace(rep, objects=rep.objects + len(at_load), skipped=rep.skipped + at_load) if at_load else rep
    setup.summary["classes"][key] = whole.to_dict() | _other_objects(setup, key, [key])
    setup.summary["classes"] = dict(sorted(setup.summary["classes"].items()))
    for s in rep.skipped:
        log.info(f"  {key}: annotation {s['annotation_id']} ({s['source']}) skipped at {s['stage']}: "
                 f"{s['reason']}")
    for w in rep.warnings:
        log.warning(f"  {key}: {w}")
    write_summary(setup)


def finish_run(setup: RunSetup, writer_workers: int, workers_mb: float | None = None, pool=None) -> dict:
    """Totals, the earlier run's other classes, ``summary.json``, ``preview.png`` and ``report/``; returns the summary.

    ``workers_mb``: the largest writer process's peak memory (as the writers report it). ``pool``: the run's
    writer processes, idle by now: they make the report's mesh scripts (the decimation, most of the report's time)
    while this process draws the preview and the rest of the report (:func:`~carvi_torch.report.build.start_report`).
    """
    s = setup.summary
    s["total_seconds"] = round(time.perf_counter() - setup.t_start, 3)
    peak = peak_rss_mb()
    s["peak_rss_mb"] = round(peak, 1) if peak is not None else None
    s["peak_rss_workers_mb"] = round(workers_mb, 1) if writer_workers and workers_mb is not None else 0.0
    if setup.device.type == "cuda":
        s["peak_cuda_mb"] = round(torch.cuda.max_memory_allocated(setup.device) / 2 ** 20, 1)
    _settings_at_end(setup)
    s["writer_workers"] = writer_workers
    write_summary(setup)
    report = None
    if setup.cfg.report and setup.cfg.stage == "all":
        try:
            from ..report.build import start_report

            report = start_report(setup.out, setup.out / "report", pool=pool)
        except Exception as e:  # noqa: BLE001 - the report must never fail the run
            log.warning(f"report/index.html not written: {e}")
    if setup.cfg.preview and setup.cfg.stage == "all":
        try:
            from ..preview import write_preview

            write_preview(setup.out, read_json(setup.out / "summary.json"))
        except Exception as e:  # noqa: BLE001 - a picture must never fail the run
            log.warning(f"preview.png not written: {e}")
    if report is not None:
        try:
            report.finish()
        except Exception as e:  # noqa: BLE001 - the report must never fail the run
            log.warning(f"report/index.html not written: {e}")
    return read_json(setup.out / "summary.json")


def _settings_at_end(setup: RunSetup) -> None:
    """``resumed_from_other_settings`` as the run leaves the folder (:func:`_settings_record` wrote it as if the run
    made objects): gone where no finished object made otherwise can be left (the run resumed none, no class is
    kept from an earlier run, and with ``overwrite`` no object of its classes keeps files from before it,
    :func:`_left_from_before`), and without this run's value among those objects were made with where it made
    none."""
    s = setup.summary
    if not setup.changed:
        return
    if not setup.kept and not any(c.get("resumed") for c in s["classes"].values()) and not _left_from_before(setup):
        s.pop("resumed_from_other_settings", None)
        return
    s["resumed_from_other_settings"] = _settings_entry(setup.changed, any(c.get("reconstructed")
                                                                          for c in s["classes"].values()))


def _left_from_before(setup: RunSetup) -> bool:
    """An ``overwrite`` run left an object of its classes with the voxels file of an earlier run (not redone: not
    chosen by ``references``, skipped now, its class failed), which :func:`_settings_record` may record as made
    with other settings. Without ``overwrite`` such objects are the resumed ones, counted in the summary."""
    if not setup.cfg.overwrite:
        return False
    for key, coll in setup.loaded.collections.items():
        for aid in coll.annotation_ids:
            with contextlib.suppress(OSError):
                if object_file(class_dir(setup.out, key), "voxels", aid).stat().st_mtime_ns < setup.started_ns:
                    return True
    return False


def exit_status(summary: dict, stage: str = "all") -> int:
    """0: the run made what it was asked for; 1: a class failed, or no object (no camera with
    ``stage=cameras``) came out of it."""
    classes = summary.get("classes", {}).values()
    if any(c.get("status") == "failed" for c in classes):
        return 1
    if stage == "cameras":
        return 0 if any(c.get("status") == "cameras" for c in classes) else 1
    return 0 if any(c.get("reconstructed", 0) + c.get("resumed", 0) > 0 for c in classes) else 1
