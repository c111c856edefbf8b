"""Where an export reads from: a reconstruction directory's configuration and the annotations it ran on."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import Config, object_settings, read_run_config
from ..io.coco import class_keys, class_names, select_classes, skipped_at_load
from ..io.layout import NOT_YET, unfinished  # noqa: F401 - the export's names for them
from ..io.layout import objects_record, other_settings, other_settings_text, other_values
from ..io.outputs import read_json, shown
from ..io.results import camera_record_problem, cameras_file_problem

__all__ = ["recon_config", "data_path", "unfinished", "class_scope", "run_classes", "class_categories",
           "camera_problem", "camera_entry", "load_skips", "missing_class_reason", "extra_cameras", "skip_all",
           "class_cameras", "class_extent", "NOT_YET", "NOT_IN_ANNOTATIONS", "SettingsTally"]

#: How the reason of a ``cameras.json`` entry that names no object of the annotation file begins.
NOT_IN_ANNOTATIONS = "in cameras.json but not an object of the annotation file"


def recon_config(recon: Path) -> Config:
    """The resolved configuration of a reconstruction directory (its ``config.yaml``)."""
    p = recon / "config.yaml"
    if not p.is_file():
        raise FileNotFoundError(f"{recon}: no config.yaml (is this a reconstruction directory?)")
    return read_run_config(p)


def load_skips(problems: list, class_names: list) -> dict[str, list]:
    """``{class: [skipped objects]}``, each class's list started with its objects skipped when the annotations
    were read (:func:`~carvi_torch.io.coco.skipped_at_load`, as ``summary.json`` books them), with their reason."""
    return {c: [{**s, "class": c} for s in skipped_at_load(problems, c)] for c in class_names}



def data_path(recon: Path, cfg: Config) -> Path:
    """The annotations a run read: its summary's path (absolute), else its config's; a relative path
    is looked up beside the run, then from the current folder. ``ValueError`` naming ``summary.json`` where its
    ``data`` is not a path (a string)."""
    summ = recon / "summary.json"
    summary = read_json(summ) if summ.is_file() else {}
    data = summary.get("data") if isinstance(summary, dict) else None
    if data is not None and not isinstance(data, str):
        raise ValueError(f"{summ}: 'data' is {shown(data)}, not the path of the annotation file the run read "
                         "(nothing was written)")
    data = data or cfg.data
    if not data:
        return recon / "input" / "annotations.json"
    p = Path(data)
    if p.is_absolute():
        return p
    for base in (recon, recon.parent):
        if (base / p).is_file():
            return base / p
    return p


def run_classes(setting, recon: Path) -> list[str] | None:
    """The classes a run covered: its ``classes`` setting (``None``: every class) and every class folder with
    cameras that an earlier part of the run left in ``recon`` (a run done in parts, ``classes=[car]`` then
    ``classes=[chair]`` into one ``--out``, keeps only the last part's setting).

    Example:
        >>> run_classes(None, Path("no/such/run")) is None, run_classes(["car"], Path("no/such/run"))
        (True, ['car'])
    """
    if not setting:
        return None
    parts = [d.name for d in recon.iterdir() if (d / "cameras.json").is_file()] if recon.is_dir() else []
    return sorted(set(setting) | set(parts))


def class_scope(categories: list, run_classes, asked, recon: Path) -> list[str]:
    """The class folders an export covers: the annotation file's classes that the run covered (its ``classes``
    setting, names or folder names; all without one), those of ``asked`` (``--classes``) alone when given.
    ``ValueError`` naming any ``asked`` class that is not one of them, and the run's classes.

    Example:
        >>> cats = [{"id": 1, "name": "car", "keypoints": ["a"]}, {"id": 2, "name": "chair", "keypoints": ["a"]}]
        >>> class_scope(cats, None, ["chair"], Path("runA"))
        ['chair']
        >>> class_scope(cats, ["car"], ["chair"], Path("runA"))
        Traceback (most recent call last):
        ...
        ValueError: --classes: 'chair' is not a class of the run runA (its classes: car; names are case-sensitive)
    """
    names = class_names(categories)
    if run_classes:
        in_run = {k for n in run_classes for k in names.get(n, ())}
        names = {n: [k for k in ks if k in in_run] for n, ks in names.items() if set(ks) & in_run}
    if not asked:
        return sorted({k for ks in names.values() for k in ks})
    return select_classes(asked, names, f"the run {recon}")


def class_categories(categories: list, class_names: list) -> dict[str, dict]:
    """``{class key: {"name": category name, "id": category id}}`` of ``class_names`` (folder keys): the category
    each key stands for, its name and id as the annotation file gives them (a key is a safe, unique spelling of
    the name, which may differ from it).

    Example:
        >>> cats = [{"id": 7, "name": "my car", "keypoints": ["a"]}, {"id": 2, "name": "car", "keypoints": ["a"]}]
        >>> class_keys(cats)["7"], class_categories(cats, list(class_keys(cats).values()))[class_keys(cats)["7"]]
        ('my_car-47602f1b', {'name': 'my car', 'id': 7})
    """
    keys = class_keys(categories)
    out = {}
    for cat in categories:
        key = keys.get(str(cat.get("id"))) if isinstance(cat, dict) else None
        if key in class_names:
            out[key] = {"name": str(cat.get("name")), "id": cat.get("id")}
    return out


def camera_problem(entry: dict) -> str | None:
    """What makes a ``cameras.json`` entry's camera unusable (``refined``: ``R`` 3 x 3 finite numbers, a rotation
    within 1e-3; ``s`` a finite positive number; ``t`` two finite numbers; ``quality``, where given, a number),
    None when nothing does.

    Example:
        >>> camera_problem({"refined": {"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "s": 2.0, "t": [1, 2]}}) is None
        True
        >>> camera_problem({"refined": {"R": [[1, 0, 0], [0, 1, 0]], "s": 2.0, "t": [1, 2]}})
        'bad camera in cameras.json: R is not 3 x 3 finite numbers'
    """
    cam = entry.get("refined")
    if not isinstance(cam, dict):
        return "bad camera in cameras.json: 'refined' is not an object with R, s and t"
    why = camera_record_problem(cam)
    if why is not None:
        return f"bad camera in cameras.json: {why}"
    q = entry.get("quality")
    if q is not None and (isinstance(q, bool) or not isinstance(q, (int, float))):
        return f"bad quality in cameras.json: {shown(q)} is not a number"
    return None


def camera_entry(cams, aid) -> dict:
    """The ``cameras.json`` entry of annotation ``aid`` (``{}`` where there is none, or it is not an object)."""
    entry = cams.get("cameras") if isinstance(cams, dict) else None
    entry = entry.get(str(aid)) if isinstance(entry, dict) else None
    return entry if isinstance(entry, dict) else {}


def missing_class_reason(recon: Path, key: str) -> str:
    """Why the objects of class ``key`` of a finished run have no outputs, its folder (or its ``cameras.json``)
    being missing: the run skipped the class (``summary.json``'s status, with its first reason), or the folder
    was removed (or never written)."""
    try:
        entry = read_json(recon / "summary.json")["classes"][key]
        if entry.get("status") == "skipped":
            why = next((f["reason"] for f in entry.get("failures") or () if isinstance(f, dict)), None)
            return "the run skipped the class" + (f": {why}" if why else "")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        pass
    return f"no cameras.json in {recon / key} (the class folder was removed, or never written)"


def _as_given(key: str):
    """A ``cameras.json`` key as the annotation id it names: an int where it spells one, else the string."""
    try:
        return int(key) if str(int(key)) == key else key
    except ValueError:
        return key


def extra_cameras(cams, cname: str, known, data: Path) -> list[dict]:
    """The entries of a class's ``cameras.json`` that are not objects of the annotation file (``known``: the
    annotation ids, as strings, the export read or skipped at load), as skipped objects with their reason."""
    entries = cams.get("cameras") if isinstance(cams, dict) else None
    out = []
    for k, entry in (entries.items() if isinstance(entries, dict) else ()):
        if k not in known:
            source = entry.get("source") if isinstance(entry, dict) else None
            out.append({"annotation_id": _as_given(k), "class": cname, "source": source,
                        "reason": f"{NOT_IN_ANNOTATIONS} {data}"})
    return out


def skip_all(coll, cname: str, reason: str) -> list[dict]:
    """Every object of a class's collection as a skipped object with ``reason``."""
    return [{"annotation_id": aid, "class": cname, "source": src, "reason": reason}
            for aid, src in zip(coll.annotation_ids, coll.sources)]


def class_extent(cams: dict) -> float:
    """Half-side ``E`` of the canonical occupancy cube: 1.3 x the largest keypoint radius of the class's
    mean shape (1.0 without one; 0 where its keypoints lie at one point: no scale, :func:`class_cameras` skips
    such a class)."""
    shape = np.array([v for v in (cams.get("mean_shape") or {}).values() if v is not None], dtype=np.float64)
    return float(1.3 * np.linalg.norm(shape - shape.mean(0), axis=1).max()) if len(shape) else 1.0


def _read_cameras(path: Path) -> tuple[dict | None, str | None]:
    """A class's ``cameras.json`` at ``path`` and ``None``, or ``None`` and why it cannot be used: unreadable, not
    a JSON object, its ``cameras`` or ``mean_shape`` of the wrong type
    (:func:`~carvi_torch.io.results.cameras_file_problem`: a mean shape row that is not 3 finite numbers included),
    or a mean shape of no extent (its keypoints at one point: the class has no scale for the canonical frame, nor
    for CMR's normalised shape)."""
    try:
        cams = read_json(path)
        if not isinstance(cams, dict):
            raise ValueError(f"{path}: not a JSON object")
    except (FileNotFoundError, ValueError) as e:
        return None, f"cameras.json unreadable: {e}"
    why = cameras_file_problem(cams)
    if why is None and not (math.isfinite(extent := class_extent(cams)) and extent > 0):
        why = "its mean_shape has no extent (its keypoints lie at one point), so the class has no scale for its " \
              "canonical frame"
    return (cams, None) if why is None else (None, f"cameras.json unusable: {path}: {why}")


def class_cameras(coll, cname: str, recon: Path, skipped: list, pending: bool, data: Path) -> dict | None:
    """The ``cameras.json`` of class ``cname`` of the run ``recon``, its entries that name no object of the
    annotation file ``data`` added to ``skipped`` (:func:`extra_cameras`; ``skipped`` holds the class's objects
    skipped so far, those skipped at load among them). None, with every object of ``coll`` added to ``skipped``,
    where the file is missing (the reason: :data:`NOT_YET` in an unfinished run, ``pending``, else
    :func:`missing_class_reason`), or unusable (:func:`_read_cameras`)."""
    path = recon / cname / "cameras.json"
    if not path.is_file():
        cams, reason = None, NOT_YET if pending else missing_class_reason(recon, cname)
    else:
        cams, reason = _read_cameras(path)
    if reason is not None:
        skipped.extend(skip_all(coll, cname, reason))
        return None
    known = {str(a) for a in coll.annotation_ids} | {str(s["annotation_id"]) for s in skipped}
    skipped.extend(extra_cameras(cams, cname, known, data))
    return cams


@dataclass
class SettingsTally:
    """The settings the objects an export writes were made with, object by object: ``run`` (the run's,
    :func:`~carvi_torch.config.object_settings` of its ``config.yaml``), ``folder`` (the run folder's record,
    :func:`~carvi_torch.io.layout.other_settings`, which stands for an object whose voxels file records none: an
    older run's) and, per object added, its :func:`~carvi_torch.io.layout.other_values` (``None``: unknown).

    Example:
        >>> tally = SettingsTally({"carve.resolution": 24}, {})
        >>> tally.add({"carve.resolution": 24}), tally.add({"carve.resolution": 16}), tally.add(None)
        (True, False, True)
        >>> tally.record()
        {'carve.resolution': [16, 24, 24]}
    """

    run: dict
    folder: dict
    others: list = field(default_factory=list)

    @classmethod
    def of(cls, recon: Path, cfg: Config) -> "SettingsTally":
        """The tally of the run folder ``recon`` whose configuration is ``cfg``."""
        return cls(object_settings(cfg), other_settings(recon))

    def add(self, held: dict | None) -> bool:
        """Count an object whose voxels file holds ``held`` (:func:`~carvi_torch.io.layout.held_settings`);
        returns whether it was made with the run's settings (the store's ``made_with_run_settings``): its record
        says so, or, without one, the folder records no other settings."""
        other = other_values(held, self.run) if held is not None else None
        self.others.append(other)
        return not other if other is not None else not self.folder

    def record(self) -> dict:
        """The objects' mixed-settings record (:func:`~carvi_torch.io.layout.objects_record`): the store's
        ``made_with_other_settings``, ``{}`` where all were made with the run's settings."""
        return objects_record(self.others, self.run, self.folder)

    def line(self) -> str:
        """The record and how many of the objects were made otherwise on one line, ``""`` where none was.

        Example:
            >>> made, count = SettingsTally({"a": 2}, {"a": [1, 2]}, [{"a": 1}, {}, None]).line().split("; ")
            >>> made
            "a 1 then 2 then 2 (oldest first, then the run's)"
            >>> count
            "2 of the 3 exported objects (1 of them by the folder's record: its file records no settings)"
        """
        made = self.record()
        if not made:
            return ""
        unknown = sum(o is None for o in self.others) if self.folder else 0
        other = sum(bool(o) for o in self.others if o is not None) + unknown
        why = f" ({unknown} of them by the folder's record: its file records no settings)" if unknown else ""
        return (other_settings_text(made) + f" (oldest first, then the run's); {other} of the {len(self.others)} "
                f"exported objects{why}")
