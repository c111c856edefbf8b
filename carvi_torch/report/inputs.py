"""What the report reads from a finished ``reconstruct --out`` folder, as typed records.

Nothing here writes anything. A class whose ``cameras.json`` is missing or unreadable keeps its
``summary.json`` entry and says why (``ClassInputs.problem``); an object keeps its entry whatever its
files look like (the card says what is wrong with them, :mod:`carvi_torch.report.cards`). An annotated
object that ``summary.json`` counts in its class but neither ``cameras.json`` nor the failures name gets an entry
too, with the problem (:data:`NO_CAMERA`). A part of ``summary.json`` (:data:`RUN_PARTS`, :data:`CLASS_PARTS`) or
of ``cameras.json`` (:func:`~carvi_torch.io.results.cameras_part_problems`) of the wrong type (a hand-edited file)
is read as absent, with one warning line naming the file (and the class panel says so).

Example:
    >>> _number({"quality": 0.5}, "quality"), _number({"quality": float("nan")}, "quality"), _number({}, "q")
    (0.5, None, None)
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.coco import class_keys, object_id
from ..io.layout import object_stem
from ..io.outputs import read_json, shown
from ..io.results import cameras_part_problems

__all__ = ["ReportError", "ObjectInputs", "ClassInputs", "RunInputs", "read_run", "NO_CAMERA", "RUN_PARTS",
           "CLASS_PARTS"]

log = logging.getLogger(__name__)
#: The parts of ``summary.json`` the report reads, with the type each has (a class's entry: :data:`CLASS_PARTS`);
#: a part of another type is read as absent (:func:`_typed`).
RUN_PARTS = {"input_problems": list}
CLASS_PARTS = {"failures": list, "warnings": list, "seconds": dict, "objects": (int, float),
               "reconstructed": (int, float), "resumed": (int, float), "skipped": (int, float)}
_WORDS = {list: "a list", dict: "an object"}


class ReportError(Exception):
    """The folder is not a finished run (no readable ``summary.json``): one line, no report."""


@dataclass
class ObjectInputs:
    """One object of a class: its ids, camera and scores (``None`` where the run has none)."""

    annotation_id: str
    """The annotation id as ``cameras.json`` spells it (a string)."""
    stem: str
    """Its file stem (``<class>/meshes/<stem>.<ext>``)."""
    source: str | None = None
    camera: dict | None = None
    """The final (refined) camera in image pixels: ``R (3, 3)``, ``s``, ``t (2,)``; ``None``: no camera."""
    sfm: dict | None = None
    """The SfM camera (before refinement), the same way; ``None``: SfM placed no camera."""
    shape_group: int = 0
    azimuth_deg: float | None = None
    elevation_deg: float | None = None
    camera_from: str | None = None
    surrogates_from: str | None = None
    quality: float | None = None
    """The run's quality score of the object when ``cameras.json`` has one (higher is better)."""
    score: float | None = None
    """The selected proposal's score (``proposal_scores.json``; a disagreement: lower is better)."""
    skipped: str | None = None
    """Why the run skipped the object (``summary.json``'s failures), else ``None``."""
    problem: str | None = None
    """What the run's records lack for the object (its camera is missing from ``cameras.json``), else ``None``."""


@dataclass
class ClassInputs:
    """One class: its ``summary.json`` entry, ``cameras.json`` content and objects."""

    key: str
    name: str
    summary: dict
    objects: list[ObjectInputs] = field(default_factory=list)
    keypoint_names: list[str] = field(default_factory=list)
    mean_shapes: list[np.ndarray] = field(default_factory=list)
    """Per shape group, ``(K, 3)`` float, the canonical-frame mean shape (NaN rows: not in it)."""
    frame: str | None = None
    problem: str | None = None
    """Why the class has no objects to show (``cameras.json`` missing or unreadable), or that ``cameras.json`` and
    the class's failures name fewer objects than ``summary.json`` counts, after the parts of its ``summary.json``
    entry and ``cameras.json`` read as absent for their wrong type, if any; else ``None``."""
    missing: int = 0
    """How many of the class's objects (``summary.json``'s count) neither ``cameras.json`` nor the failures name
    (``cameras.json`` lists every object of the class, chosen as a reference or not, with its camera or without)."""


@dataclass
class RunInputs:
    """The run: its folder, ``summary.json``, annotation file and classes."""

    recon: Path
    summary: dict
    classes: list[ClassInputs]
    data: Path | None
    mesh_format: str = "ply"


def _number(d: dict, key: str) -> float | None:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return None
    return float(v)


def _typed(record: dict, parts: dict, where: str) -> tuple[dict, list[str]]:
    """``record`` without those of its ``parts`` (name -> type) whose value is of another type (``null`` counts as
    absent), and a note for each (also a warning line; ``where``: the file, and the class, it is read from).

    Example:
        >>> _typed({"failures": 5, "objects": 6}, CLASS_PARTS, "summary.json")
        ({'objects': 6}, ["summary.json: 'failures' is 5, not a list; read as absent"])
    """
    bad = [k for k, t in parts.items()
           if record.get(k) is not None and (isinstance(record[k], bool) or not isinstance(record[k], t))]
    notes = [f"{where}: {k!r} is {shown(record[k])}, not {_WORDS.get(parts[k], 'a number')}; read as absent"
             for k in bad]
    for note in notes:
        log.warning(f"report: {note}")
    return {k: v for k, v in record.items() if k not in bad}, notes


def _usable_parts(cams: dict, key: str) -> tuple[dict, list[str]]:
    """A class's ``cameras.json`` content without its parts of the wrong type
    (:func:`~carvi_torch.io.results.cameras_part_problems`), and a note for each (also a warning line)."""
    problems = cameras_part_problems(cams)
    notes = [f"{key}/cameras.json: {why}; read as absent" for why in problems.values()]
    for note in notes:
        log.warning(f"report: {note}")
    return {k: v for k, v in cams.items() if k not in problems}, notes


def _mean_shapes(cams: dict, names: list[str]) -> list[np.ndarray]:
    def arr(named: dict) -> np.ndarray:
        return np.array([named.get(n) if named.get(n) is not None else [np.nan] * 3 for n in names], dtype=np.float64)

    groups = cams.get("shape_groups")
    if groups:
        return [arr(g.get("mean_shape") or {}) for g in groups]
    return [arr(cams.get("mean_shape") or {})]


def _chosen_scores(cdir: Path) -> dict:
    """Per annotation id, the selected proposal's score (``proposal_scores.json``), where the run kept them."""
    p = cdir / "proposal_scores.json"
    try:
        entries = read_json(p) if p.is_file() else {}
    except ValueError:
        return {}
    out = {}
    for aid, e in entries.items() if isinstance(entries, dict) else ():
        try:
            v = _number({"v": e["scores"][e["best"]]}, "v")
        except (KeyError, IndexError, TypeError):
            continue
        if v is not None:
            out[str(aid)] = v
    return out


def _objects(cams: dict, failures: dict, scores: dict) -> list[ObjectInputs]:
    out = []
    for aid, c in (cams.get("cameras") or {}).items():
        c = c if isinstance(c, dict) else {}
        g = c.get("shape_group")
        out.append(ObjectInputs(
            annotation_id=str(aid), stem=object_stem(aid), source=c.get("source"),
            camera=c.get("refined") if isinstance(c.get("refined"), dict) else None,
            sfm=c.get("sfm") if isinstance(c.get("sfm"), dict) else None,
            shape_group=g if isinstance(g, int) else 0,
            azimuth_deg=_number(c, "azimuth_deg"), elevation_deg=_number(c, "elevation_deg"),
            camera_from=c.get("camera_from"), surrogates_from=c.get("surrogates_from"),
            quality=_number(c, "quality"), score=scores.get(str(aid)), skipped=failures.pop(str(aid), None)))
    # skipped objects that cameras.json does not list (e.g. dropped at load) still get a card
    out += [ObjectInputs(annotation_id=aid, stem=object_stem(aid), skipped=reason) for aid, reason in failures.items()]
    return out


def _read_class(recon: Path, key: str, entry: dict, notes: list[str]) -> ClassInputs:
    """Class ``key`` of the run: its ``summary.json`` ``entry`` (typed: :func:`_typed`, whose ``notes`` the class's
    problem starts with) and ``cameras.json``."""
    notes = list(notes)
    failures = {str(f["annotation_id"]): f.get("reason", "skipped") for f in entry.get("failures", [])
                if isinstance(f, dict) and f.get("annotation_id") is not None}
    cls = ClassInputs(key=key, name=key, summary=entry)
    p = recon / key / "cameras.json"
    try:
        cams = read_json(p)
        if not isinstance(cams, dict):
            raise ValueError("not a JSON object")
    except FileNotFoundError:
        cams, cls.problem = {}, f"no {key}/cameras.json"
    except (ValueError, OSError) as e:
        cams, cls.problem = {}, f"{key}/cameras.json unreadable: {str(e).splitlines()[0][:120]}"
    cams, more = _usable_parts(cams, key)
    notes += more
    cls.name = str(cams.get("class", key))
    cls.frame = cams.get("frame")
    cls.keypoint_names = [str(n) for n in (cams.get("mean_shape") or {})]
    if cls.keypoint_names:
        cls.mean_shapes = _mean_shapes(cams, cls.keypoint_names)
    cls.objects = _objects(cams, failures, _chosen_scores(recon / key))
    known = len(cls.objects)  # cameras.json's entries (every object with or without a camera) and the failures
    counted = int(_number(entry, "objects") or 0)
    if cls.problem is None and counted > known:
        cls.missing = counted - known
        cls.problem = (f"{key}/cameras.json and the failures of the class name {known} of the {counted} objects "
                       "summary.json counts")
    cls.problem = "; ".join([*notes, *([cls.problem] if cls.problem else [])]) or None
    return cls


#: The card problem of an annotated object whose class's ``cameras.json`` lacks it (:func:`_add_unlisted`).
NO_CAMERA = "camera missing from cameras.json (summary.json counts the object in its class)"


def _add_unlisted(classes: list[ClassInputs], data: Path | None) -> None:
    """Give every class whose ``cameras.json`` lacks objects (``ClassInputs.missing``) an object for each
    annotation of its class in ``data`` that neither ``cameras.json`` nor the failures list, with the problem
    :data:`NO_CAMERA`. The file is read only then; unreadable, it adds nothing (the panel says how many)."""
    short = {c.key: c for c in classes if c.missing}
    if not short or data is None:
        return
    try:
        coco = read_json(data)
        key_of = class_keys(coco.get("categories") or [])
        anns = [a for a in coco.get("annotations") or [] if isinstance(a, dict)]
    except (OSError, ValueError, AttributeError, TypeError):
        return
    known = {c.key: {o.annotation_id for o in c.objects} for c in short.values()}
    for a in anns:
        aid, cls = object_id(a.get("id")), short.get(key_of.get(str(a.get("category_id"))))
        if aid is None or cls is None or str(aid) in known[cls.key]:
            continue
        known[cls.key].add(str(aid))
        source = a.get("source") if isinstance(a.get("source"), str) else None
        cls.objects.append(ObjectInputs(annotation_id=str(aid), stem=object_stem(aid), source=source,
                                        problem=NO_CAMERA))


def read_run(recon: str | Path) -> RunInputs:
    """Read ``recon/summary.json`` and every class's files it lists.

    Raises:
        ReportError: no readable ``summary.json`` with a ``classes`` mapping.
    """
    recon = Path(recon)
    try:
        summary = read_json(recon / "summary.json")
    except (OSError, ValueError) as e:
        raise ReportError(f"{recon} is not a finished run: summary.json unreadable ({type(e).__name__})") from e
    if not isinstance(summary, dict) or not isinstance(summary.get("classes"), dict):
        raise ReportError(f"{recon}/summary.json has no 'classes' mapping")
    summary = _typed(summary, RUN_PARTS, "summary.json")[0]
    typed = {str(k): _typed(v if isinstance(v, dict) else {}, CLASS_PARTS, f"summary.json class {k}")
             for k, v in summary["classes"].items()}
    summary["classes"] = {k: entry for k, (entry, _) in typed.items()}  # the page reads them typed too
    classes = [_read_class(recon, k, entry, notes) for k, (entry, notes) in typed.items()
               if (recon / k).resolve().parent == recon.resolve()]
    data = Path(summary["data"]) if isinstance(summary.get("data"), str) else None
    if (data is None or not data.is_file()) and (recon / "input" / "annotations.json").is_file():
        data = recon / "input" / "annotations.json"  # the embedded collection, in a run folder that moved
    _add_unlisted(classes, data)
    fmt = "ply"
    try:
        import yaml

        cfg = yaml.safe_load((recon / "config.yaml").read_text())
        fmt = str(((cfg or {}).get("mesh") or {}).get("format") or "ply")
    except Exception:  # noqa: BLE001 - no or damaged config: the default format
        pass
    return RunInputs(recon=recon, summary=summary, classes=classes, data=data, mesh_format=fmt)
