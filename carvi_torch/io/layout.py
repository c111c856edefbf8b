"""Where a run's files lie in its output folder: one place for every reader and writer.

::

    OUT/config.yaml, OUT/summary.json, OUT/run.log, OUT/preview.png, OUT/report/index.html
    OUT/<class key>/cameras.json
    OUT/<class key>/meshes/<object stem>.<format>
    OUT/<class key>/voxels/<object stem>.npz
    OUT/<class key>/proposals/<object stem>.npz         (studies)
    OUT/<class key>/scores/<object stem>.json           (studies: every proposal's score)
    OUT/<class key>/proposal_scores.json                (studies: the scores merged at the end of the class)

The class key is the category's name when that is a safe folder name and none of the run's own
names (:data:`RUN_NAMES`), else a safe spelling of it (``ClassMeta.key``); an object's stem is its
annotation id when that is a safe file name, else a safe spelling of it
(:func:`~carvi_torch.io.outputs.safe_name`). Neither can point outside ``OUT``: no separator, no
leading dot.

Example:
    >>> object_file(Path("out/car"), "meshes", "../x", "ply").as_posix()
    'out/car/meshes/x-d6b96a97.ply'
"""
from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .outputs import first_link, read_json, safe_name, shown_names

__all__ = ["unfinished", "NOT_YET",
           "class_dir", "object_stem", "object_file", "object_mesh", "finished", "KINDS", "RUN_NAMES", "reserved",
           "INPUTS_CHANGED", "NO_INPUT_RECORD", "CANVAS_CHANGED", "PER_OBJECT_SETTINGS", "ResumeCheck", "resume_check",
           "same_canvas", "other_objects", "held_fingerprint", "linked_path", "other_settings", "other_settings_text",
           "settings_record", "MOST_SETTINGS", "SETTINGS_MEMBER", "settings_text", "held_settings", "file_settings",
           "other_values", "objects_record", "objects_made_otherwise", "objects_text", "MESH_MEMBER", "mesh_record",
           "held_mesh_faces"]

#: Per-object file kinds and their extension (``None``: the mesh format).
KINDS = {"meshes": None, "voxels": "npz", "proposals": "npz", "scores": "json"}
#: The run's own files and folders in ``OUT`` (``input``: the embedded default collection; ``report``: the
#: HTML report); no class
#: folder takes one of these names, in any case.
RUN_NAMES = ("config.yaml", "summary.json", "run.log", "preview.png", "input", "report")


def reserved(key: str) -> bool:
    """Whether ``key`` is one of the run's own names in ``OUT`` (:data:`RUN_NAMES`, case-insensitively).

    Example:
        >>> reserved("Summary.JSON"), reserved("car")
        (True, False)
    """
    return key.lower() in RUN_NAMES


def class_dir(out: str | Path, key: str) -> Path:
    """The folder of a class (``key``: ``ClassMeta.key``, already safe and not reserved; checked again here)."""
    if safe_name(key) != key or reserved(key):
        raise ValueError(f"class key {key!r} is not a safe folder name or is one of the run's own names")
    return Path(out) / key


def linked_path(out: str | Path, keys=()) -> Path | None:
    """The first path a run writes under ``out`` that is a symbolic link, or ``None``: a run writes only
    inside ``out``, and a link would carry its files (or run.log's lines) elsewhere. Looked at: the run's
    own names (:data:`RUN_NAMES`), everything below ``input/`` and ``report/``, and per class key the
    class folder and its per-object folders (:data:`KINDS`). Files written whole replace a link rather than
    follow it; these are the folders written into and the files appended to.

    Example:
        >>> linked_path("no/such/folder", ["car"]) is None
        True
    """
    out = Path(out)
    for name in RUN_NAMES:
        if (out / name).is_symlink():
            return out / name
    linked = first_link(out, ("input", "report"))
    if linked is not None:
        return linked
    for key in keys:
        for path in (out / key, *(out / key / kind for kind in KINDS)):
            if path.is_symlink():
                return path
    return None


def other_settings(recon: str | Path) -> dict:
    """The settings the run folder's finished objects were made with where they are not its ``config.yaml``'s
    (``summary.json``'s ``resumed_from_other_settings``: per setting, the values the objects were made with, oldest
    first, then the run's); ``{}`` where there are none, or no readable record.

    Example:
        >>> other_settings(Path("no/such/run"))
        {}
    """
    try:
        record = read_json(Path(recon) / "summary.json").get("resumed_from_other_settings")
    except (OSError, ValueError, AttributeError):
        return {}
    return settings_record(record)


#: The most settings, and values per setting, a mixed-settings record keeps (the run's value always among them).
MOST_SETTINGS = 16


def settings_record(record) -> dict:
    """A mixed-settings record (``resumed_from_other_settings``, or the export's ``made_with_other_settings``) as
    safe to store and print: per setting (its name on one line, at most 80 characters), two or more values, each a
    plain JSON value (text, a whole number, a finite float, a truth value, ``null``); any other value, or text over
    80 characters, becomes a short text; at most :data:`MOST_SETTINGS` settings and values (the last, the run's,
    kept). Anything else, or a setting with fewer than two values, is left out.

    Example:
        >>> settings_record({"carve.resolution": [16, 24], "x": [24], "y": "no list", "z": [float("nan"), [1, 2]]})
        {'carve.resolution': [16, 24], 'z': ['nan', '[1, 2]']}
    """
    if not isinstance(record, dict):
        return {}
    out = {}
    for k, values in list(record.items())[:MOST_SETTINGS]:
        if isinstance(values, list) and len(values) >= 2:
            kept = values[:MOST_SETTINGS - 1] + values[-1:] if len(values) > MOST_SETTINGS else values
            out[" ".join(str(k).split())[:80]] = [_plain(v) for v in kept]
    return out


def _plain(value):
    """``value`` where it is a plain JSON value (text of at most 80 characters), else a short text of it."""
    if value is None or isinstance(value, (bool, int)) or (isinstance(value, float) and math.isfinite(value)):
        return value
    if isinstance(value, str) and len(value) <= 80:
        return value
    try:
        text = " ".join(repr(value).split()) if not isinstance(value, str) else value
    except RecursionError:
        text = "(too deeply nested)"
    return text if len(text) <= 80 else text[:77] + "..."


def other_settings_text(made: dict) -> str:
    """:func:`other_settings`' record on one line: each setting with its values, oldest first (a value's own line
    breaks and runs of spaces shown as one space).

    Example:
        >>> other_settings_text({"carve.resolution": [16, 24], "note": ["a\\nb", None]})
        'carve.resolution 16 then 24; note a b then None'
    """
    return "; ".join(" ".join(str(k).split()) + " " + " then ".join(" ".join(str(v).split()) for v in values)
                     for k, values in made.items())


def object_stem(annotation_id) -> str:
    """The file stem of an object: its annotation id, or a safe spelling of it."""
    return safe_name(annotation_id)


def object_file(cdir: str | Path, kind: str, annotation_id, ext: str | None = None) -> Path:
    """``cdir/<kind>/<stem>.<ext>``; ``ext`` defaults to the kind's (``npz``); meshes need their format."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {list(KINDS)}, got {kind!r}")
    ext = ext or KINDS[kind]
    if ext is None:
        raise ValueError("meshes need their format as ext (ply, obj, ...)")
    return Path(cdir) / kind / f"{object_stem(annotation_id)}.{ext}"


def object_mesh(cdir: str | Path, annotation_id, mesh_format: str) -> Path | None:
    """The mesh file of an object: in ``mesh_format``, else in another format a run writes (an earlier run's with
    another ``mesh_format``: :func:`finished` takes it, and the resumed object's mesh is written again in the run's
    format), else ``None``.

    Example:
        >>> object_mesh("no/such/run/car", 3, "obj") is None
        True
    """
    from ..mesh import MESH_FORMATS

    for ext in (mesh_format, *(f for f in MESH_FORMATS if f != mesh_format)):
        path = object_file(cdir, "meshes", annotation_id, ext)
        if path.is_file():
            return path
    return None


#: Why a finished object is redone although its files are sound: :func:`finished`'s reasons a run counts
#: (``summary.json``: ``redone``) rather than logging each object's.
INPUTS_CHANGED = "its inputs differ from those it was made from"
NO_INPUT_RECORD = "its files hold no record of its inputs (an older run's)"
CANVAS_CHANGED = "it was carved on another canvas (canvas_size or canvas_margin changed since)"
#: The settings whose change a rerun takes care of object by object, so that no object it resumes was made with
#: another value: a canvas setting changes every object's canvas (:data:`CANVAS_CHANGED`: the object is redone),
#: and a resumed object whose mesh is in another format gets its mesh written again in the run's. Only the
#: classes a run does not touch (kept from an earlier run) can hold objects made with another value.
PER_OBJECT_SETTINGS = ("input.canvas_size", "input.canvas_margin", "mesh.format")


def held_fingerprint(voxels) -> str | None:
    """The input fingerprint an object's voxels hold (``voxels``: the opened ``npz`` file, or its members in a
    dict): the string the writers store (a 0-d unicode array), or ``None`` where there is none or it is of
    another kind (an older run's file, or a foreign one).

    Example:
        >>> held_fingerprint({"input_fingerprint": np.asarray("3f2a", dtype=str)}), held_fingerprint({})
        ('3f2a', None)
    """
    fp = voxels["input_fingerprint"] if "input_fingerprint" in voxels else None
    return str(fp) if fp is not None and fp.dtype.kind == "U" and fp.ndim == 0 else None


#: The member of an object's voxels file that records the settings the object was made with
#: (:func:`~carvi_torch.config.object_settings`, as compact JSON text: :func:`settings_text`; a 0-d unicode array,
#: like ``input_fingerprint``). An older run's file has none: how its object was made is unknown.
SETTINGS_MEMBER = "settings"


def settings_text(settings: dict) -> str:
    """``settings`` (``{dotted key: value}``: :func:`~carvi_torch.config.object_settings`) as a voxels file records
    them (:data:`SETTINGS_MEMBER`): compact JSON, in the given order.

    Example:
        >>> settings_text({"carve.resolution": 16, "mesh.format": "ply"})
        '{"carve.resolution":16,"mesh.format":"ply"}'
    """
    return json.dumps(settings, separators=(",", ":"))


def held_settings(voxels) -> dict | None:
    """The settings an object's voxels hold (``voxels``: the opened ``npz`` file, or its members in a dict):
    ``{dotted key: value}`` as :func:`settings_text` wrote them, or ``None`` where there are none (an older run's
    file) or they are of another kind or unreadable (a foreign file).

    Example:
        >>> held_settings({SETTINGS_MEMBER: np.asarray('{"carve.resolution":16}', dtype=str)}), held_settings({})
        ({'carve.resolution': 16}, None)
    """
    text = voxels[SETTINGS_MEMBER] if SETTINGS_MEMBER in voxels else None
    if text is None or text.dtype.kind != "U" or text.ndim != 0:
        return None
    try:
        made = json.loads(str(text))
    except (ValueError, RecursionError):
        return None
    return made if isinstance(made, dict) else None


#: The voxels file's member recording the object's mesh file as written: ``"<format>:<faces>"``
#: (:func:`mesh_record`), so that a mesh file cut short is found whatever its format (an OBJ or OFF file cut at a
#: line end still parses). Faces alone: a format may store the vertices otherwise (STL repeats them per face),
#: and a file cut among its vertices has lost every face.
MESH_MEMBER = "mesh"


def mesh_record(mesh_format: str, faces: int) -> np.ndarray:
    """The :data:`MESH_MEMBER` of an object whose mesh file is in ``mesh_format`` with ``faces`` triangles.

    Example:
        >>> str(mesh_record("obj", 12))
        'obj:12'
    """
    return np.asarray(f"{mesh_format}:{int(faces)}", dtype=str)


def held_mesh_faces(voxels, mesh_format: str) -> int | None:
    """The faces the voxels (the opened ``npz`` file, or its members in a dict) record for the object's
    mesh file in ``mesh_format`` (:func:`mesh_record`); ``None`` where they record none (an older run's file), one
    of another format (a mesh being converted: the file found is checked as before) or one of another kind.

    Example:
        >>> held_mesh_faces({MESH_MEMBER: mesh_record("obj", 12)}, "obj"), held_mesh_faces({}, "obj")
        (12, None)
    """
    text = voxels[MESH_MEMBER] if MESH_MEMBER in voxels else None
    if text is None or text.dtype.kind != "U" or text.ndim != 0:
        return None
    fmt, _, faces = str(text).partition(":")
    return int(faces) if fmt == mesh_format and faces.isdigit() else None


def file_settings(path: str | Path) -> dict | None:
    """:func:`held_settings` of the voxels file at ``path``; ``None`` also where it is missing or cannot be read.

    Example:
        >>> file_settings("no/such/run/car/voxels/3.npz") is None
        True
    """
    try:
        with np.load(path) as z:
            return held_settings(z)
    except Exception:  # noqa: BLE001 - a missing or damaged file: its object's settings are unknown
        return None


def other_values(held: dict, run: dict) -> dict:
    """``{dotted key: value}`` of the settings an object was made with (``held``: :func:`held_settings`) that are
    not the run's (``run``: :func:`~carvi_torch.config.object_settings` of its ``config.yaml``; compared as JSON
    holds them, a tuple as a list); a setting one of them lacks (added or removed since) counts, as ``None``.
    ``{}``: the object was made with the run's settings.

    Example:
        >>> other_values({"carve.resolution": 16, "seed": 0}, {"carve.resolution": 24, "seed": 0, "new": (1, 2)})
        {'carve.resolution': 16, 'new': None}
    """
    run = json.loads(settings_text(run))
    return {k: held.get(k) for k in {**held, **run} if held.get(k) != run.get(k)}


def objects_record(others: list, run: dict, folder: dict) -> dict:
    """The mixed-settings record of a set of objects (the form of ``summary.json``'s ``resumed_from_other_settings``:
    per setting, the values the objects were made with, then the run's; :func:`settings_record`) from each object's
    :func:`other_values` (``None``: unknown, an older run's file without :data:`SETTINGS_MEMBER`): the values the
    objects were made with, in the order of the folder's record (``folder``: :func:`other_settings`) where it has
    them, and the folder's values too where an object's are unknown; then the run's value (``run``: its settings;
    the folder's for a setting it does not know).

    Example:
        >>> run = {"carve.resolution": 24}
        >>> objects_record([{}, {"carve.resolution": 16}], run, {}), objects_record([{}, {}], run, {"x": [1, 2]})
        ({'carve.resolution': [16, 24, 24]}, {})
        >>> objects_record([{}, None], run, {"carve.resolution": [20, 24]})
        {'carve.resolution': [20, 24, 24]}
    """
    known, run = [o for o in others if o is not None], json.loads(settings_text(run))
    made = {k: list(v[:-1]) for k, v in folder.items()} if len(known) < len(others) else {}
    for k, v in ((k, v) for o in known for k, v in o.items()):
        made.setdefault(k, []).append(v)
    out = {}
    for k, values in made.items():
        now = run[k] if k in run else folder.get(k, [None])[-1]  # a setting the run does not know: the folder's
        values += [now] if any(k not in o for o in known) else []  # objects made with the run's value
        order = folder.get(k, [])[:-1]
        values = sorted((v for i, v in enumerate(values) if v not in values[:i]),
                        key=lambda v: order.index(v) if v in order else len(order))
        out[k] = values + [now]
    return settings_record(out)


def objects_made_otherwise(recon: str | Path) -> tuple[int, int, int]:
    """``(other, recorded, objects)``: how many objects of the run folder ``recon`` (its voxels files) record
    settings other than its ``config.yaml``'s (:func:`other_values`), how many record theirs at all
    (:data:`SETTINGS_MEMBER`), and how many there are; ``(0, 0, 0)`` without a readable ``config.yaml``.

    Example:
        >>> objects_made_otherwise("no/such/run")
        (0, 0, 0)
    """
    from ..config import ConfigError, object_settings, read_run_config

    try:
        run = object_settings(read_run_config(Path(recon) / "config.yaml"))
    except (ConfigError, OSError):
        return 0, 0, 0
    other = recorded = objects = 0
    for path in Path(recon).glob("*/voxels/*.npz"):
        objects += 1
        held = file_settings(path)
        recorded += held is not None
        other += bool(held is not None and other_values(held, run))
    return other, recorded, objects


def objects_text(counts: tuple[int, int, int]) -> str:
    """:func:`objects_made_otherwise`'s counts in a few words, ``""`` where no object records its settings.

    Example:
        >>> objects_text((2, 10, 12)), objects_text((0, 0, 12))
        ('2 of its 12 objects by their voxels files, 2 of which record none', '')
    """
    other, recorded, objects = counts
    if not recorded:
        return ""
    return f"{other} of its {objects} objects by their voxels files" + (
        f", {objects - recorded} of which record none" if recorded < objects else "")


def _voxels_state(path: Path) -> tuple[str | None, dict]:
    """``(why a voxels file is not a finished object's or None, its members)``."""
    try:
        with np.load(path) as z:
            members = {k: z[k] for k in z.files}  # every member read: the zip's checksums cover each
            occ, T = members["occupancy"], members["voxel_to_camera"]
    except Exception as e:  # noqa: BLE001 - any damage means: redo the object
        return f"unreadable voxels ({type(e).__name__})", {}
    if occ.dtype != bool or occ.ndim != 3 or T.shape != (4, 4) or not np.isfinite(T).all():
        return f"voxels of the wrong kind (occupancy {occ.dtype} {occ.shape}, transform {T.shape})", {}
    return None, members


def same_canvas(members: dict, canvas) -> bool | None:
    """Whether a voxels file's ``canvas_scale`` and ``canvas_offset`` are ``canvas`` (``(scale, (x, y))``, the
    object's canvas now: ``ClassCollection.canvas_from_image``), to rounding; ``None`` where the file holds none.

    Example:
        >>> same_canvas({"canvas_scale": np.float64(0.5), "canvas_offset": np.float32([3, 4])}, (0.5, (3.0, 4.0)))
        True
        >>> same_canvas({"canvas_scale": np.float64(0.5), "canvas_offset": np.float32([3, 4])}, (0.6, (3.0, 4.0)))
        False
    """
    try:
        scale, offset = float(members["canvas_scale"]), np.asarray(members["canvas_offset"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        return None
    return bool(offset.shape == (2,) and np.isclose(scale, canvas[0], rtol=1e-5, atol=0)
                and np.allclose(offset, canvas[1], rtol=1e-5, atol=1e-3))


def _mesh_ok(path: Path, members: dict | None = None) -> str | None:
    """Why a mesh file is not a finished object's (``None``: it is one): it cannot be read, holds no usable mesh
    (:func:`~carvi_torch.mesh.read_mesh_arrays`), a face names a vertex twice, which no written face does
    (zeros where a file's tail never reached the disk do), or it holds other counts of vertices and faces than
    its voxels file's ``members`` record for it (:func:`held_mesh_faces`: a file cut short)."""
    from ..mesh import read_mesh_arrays

    try:
        _, faces = read_mesh_arrays(path)
    except Exception as e:  # noqa: BLE001 - any damage: the object is redone
        return f"unreadable mesh ({type(e).__name__}: {' '.join(str(e).split())[:80]})"
    if ((faces[:, 0] == faces[:, 1]) | (faces[:, 1] == faces[:, 2]) | (faces[:, 0] == faces[:, 2])).any():
        return "mesh with broken faces (a face names one vertex twice)"
    held = held_mesh_faces(members or {}, path.suffix[1:].lower())
    if held is not None and held != len(faces):
        return f"mesh cut short ({len(faces)} faces where {held} were written)"
    return None


def finished(cdir: str | Path, annotation_id, mesh_format: str, fingerprint: str | None = None,
             canvas: tuple | None = None) -> str | bool:
    """Whether an earlier run finished an object: ``True``, ``False`` (no files), or the reason its files
    cannot be trusted (the object is redone): a truncated or damaged mesh or voxels file, or, when its
    current input ``fingerprint`` is given (``ClassCollection.fingerprints``), files made from other
    inputs (:data:`INPUTS_CHANGED`) or holding no fingerprint (:data:`NO_INPUT_RECORD`), or, when its current
    ``canvas`` is given (``(scale, (x, y))`` of ``ClassCollection.canvas_from_image``), voxels carved on another
    canvas (:data:`CANVAS_CHANGED`; none recorded: :data:`NO_INPUT_RECORD`). The mesh may be in another format
    than ``mesh_format`` (:func:`object_mesh`).

    Example:
        >>> finished("no/such/run/car", 3, "ply")
        False
    """
    return _finished(object_mesh(cdir, annotation_id, mesh_format), object_file(cdir, "voxels", annotation_id),
                     fingerprint, canvas)


def _finished(mesh: Path | None, voxels: Path, fingerprint: str | None, canvas: tuple | None) -> str | bool:
    """:func:`finished` of an object whose mesh file is ``mesh`` (:func:`object_mesh`, looked up by the caller) and
    whose voxels file is ``voxels``."""
    if mesh is None or not voxels.is_file():
        return False
    why, members = _voxels_state(voxels)
    if why is None and fingerprint:
        held = held_fingerprint(members)
        why = None if held == fingerprint else (INPUTS_CHANGED if held else NO_INPUT_RECORD)
    if why is None and canvas is not None:
        same = same_canvas(members, canvas)
        why = None if same else NO_INPUT_RECORD if same is None else CANVAS_CHANGED
    return why or _mesh_ok(mesh, members) or True


#: ``summary.json`` names of the reasons a sound finished object is redone (per class: ``redone``).
REDONE = {INPUTS_CHANGED: "inputs_changed", NO_INPUT_RECORD: "no_input_record", CANVAS_CHANGED: "canvas_changed"}


@dataclass
class ResumeCheck:
    """What an earlier run left of a class's objects: ``done`` per object (the format of the mesh file of a
    finished object, which is resumed with that file; ``None``: none to resume), ``damaged``
    (``{annotation id: reason}``: files that cannot be trusted), ``redone`` (``{reason name:
    [annotation ids]}``: sound files made from other inputs or canvases, or without a record of them),
    ``others`` (:func:`other_objects`: the stems of mesh or voxels files of objects the data no longer holds),
    ``converted`` (``{format: [annotation ids]}``: finished objects whose mesh is in that format only, another
    than the run's: resumed, their mesh written again in the run's format and that file removed) and
    ``other_formats`` (the file names of meshes of the class's objects in another format that stay: an object
    redone, or with a mesh in the run's format too)."""

    done: list = field(default_factory=list)
    damaged: dict = field(default_factory=dict)
    redone: dict = field(default_factory=dict)
    others: list = field(default_factory=list)
    converted: dict = field(default_factory=dict)
    other_formats: list = field(default_factory=list)

    def lines(self, key: str) -> list[str]:
        """The run's warning lines for class ``key``: each damaged object, then the redone and the others'
        counts, the converted meshes and those in another format that stay.

        Example:
            >>> ResumeCheck(others=["17", "18"]).lines("car")[0][:60]
            '  car: 2 object(s) of an earlier run that the data no longer'
            >>> ResumeCheck(converted={"ply": [1, 2]}).lines("car")[0][:72]
            '  car: 2 finished object(s) have their mesh in another format (ply): res'
        """
        out = [f"  {key}: annotation {a}: {why}; reconstructing it again" for a, why in self.damaged.items()]
        if self.redone:
            out.append(f"  {key}: {self.line()}")
        if self.others:
            out.append(f"  {key}: {len(self.others)} object(s) of an earlier run that the data no longer holds keep "
                       f"their files in meshes/ and voxels/ ({shown_names(self.others, 5)}); cameras.json, the report "
                       "and the export leave them out")
        if self.converted:
            n, formats = sum(len(v) for v in self.converted.values()), ", ".join(sorted(self.converted))
            out.append(f"  {key}: {n} finished object(s) have their mesh in another format ({formats}): resumed, "
                       f"their meshes written again in this run's format from their voxels (the {formats} files "
                       "removed)")
        if self.other_formats:
            out.append(f"  {key}: {len(self.other_formats)} mesh file(s) of an earlier run in another format than "
                       f"this run's stay in meshes/ ({shown_names(self.other_formats, 5)}): not this run's meshes of "
                       "their objects; remove them if they are not wanted")
        return out

    def info(self) -> dict:
        """``summary.json``'s entries of the class, where there are any: ``redone``, ``other_objects`` (``count``,
        ``stems``), ``meshes_converted`` (``count``, and the ids per earlier format) and ``other_format_meshes``
        (``count``, ``files``)."""
        out = ({"redone": self.summary()} if self.redone else {}) | (
            {"other_objects": {"count": len(self.others), "stems": self.others}} if self.others else {})
        if self.converted:
            out["meshes_converted"] = {"count": sum(len(v) for v in self.converted.values()),
                                       **dict(sorted(self.converted.items()))}
        if self.other_formats:
            out["other_format_meshes"] = {"count": len(self.other_formats), "files": self.other_formats}
        return out

    def summary(self) -> dict:
        """``summary.json``'s ``redone`` of the class: ``count`` and the ids per reason."""
        return {"count": sum(len(v) for v in self.redone.values()), **dict(sorted(self.redone.items()))}

    def line(self) -> str:
        """One line: how many finished objects are redone, and why.

        Example:
            >>> ResumeCheck(redone={"inputs_changed": [1, 2]}).line()
            'redoing 2 finished object(s): 2 whose inputs changed since they were made'
        """
        why = {"inputs_changed": "whose inputs changed since they were made",
               "canvas_changed": "carved on another canvas (canvas_size or canvas_margin changed since)",
               "no_input_record": "made by an older run that recorded no inputs"}
        return (f"redoing {self.summary()['count']} finished object(s): "
                + "; ".join(f"{len(ids)} {why[k]}" for k, ids in sorted(self.redone.items())))


def other_objects(cdir: str | Path, annotation_ids: list) -> list[str]:
    """The stems of the mesh and voxels files in class folder ``cdir`` that belong to none of ``annotation_ids``
    (an earlier run's objects that the data no longer holds), shorter first (numeric ids in order).

    Example:
        >>> other_objects("no/such/run/car", [1, 2])
        []
    """
    ours = {object_stem(a) for a in annotation_ids}
    stems = {f.stem for kind in ("meshes", "voxels") if (Path(cdir) / kind).is_dir()
             for f in (Path(cdir) / kind).iterdir() if f.is_file() and not f.name.startswith(".")}
    return sorted(stems - ours, key=lambda s: (len(s), s))


def resume_check(cdir: str | Path, annotation_ids: list, fingerprints: list, mesh_format: str,
                 canvases=None) -> ResumeCheck:
    """:func:`finished` for every object of a class (``fingerprints``: their current input fingerprints;
    ``canvases``: their current canvases, ``ClassCollection.canvas_from_image``, ``.scale (N,)`` and ``.offset
    (N, 2)``), and the meshes of its objects in other formats than ``mesh_format`` (``ResumeCheck.converted``,
    ``ResumeCheck.other_formats``). Each object's mesh file is looked up once (:func:`object_mesh`): its format is
    the object's ``ResumeCheck.done``."""
    check = ResumeCheck()
    formats = _mesh_formats(cdir, mesh_format)
    canvases = ([None] * len(annotation_ids) if canvases is None
                else list(zip(canvases.scale.tolist(), canvases.offset.tolist())))
    for a, fp, canvas in zip(annotation_ids, fingerprints, canvases):
        mesh = object_mesh(cdir, a, mesh_format)
        state = _finished(mesh, object_file(cdir, "voxels", a), fp, canvas)
        if state in REDONE:
            check.redone.setdefault(REDONE[state], []).append(a)
        elif isinstance(state, str):
            check.damaged[a] = state
        taken = mesh.suffix[1:] if state is True else None  # the format of the mesh the object is resumed with
        check.done.append(taken)
        stem = object_stem(a)
        others = [f for f in formats.get(stem, []) if f != mesh_format]
        if taken is not None and taken != mesh_format:  # converted (results.resumed_objects)
            check.converted.setdefault(taken, []).append(a)
            others.remove(taken)
        check.other_formats += [f"{stem}.{f}" for f in others]
    return check


def _mesh_formats(cdir: str | Path, mesh_format: str) -> dict[str, list[str]]:
    """``{stem: [formats]}`` of the mesh files in class folder ``cdir`` (one listing of ``meshes/``), each object's
    formats in :func:`object_mesh`'s order."""
    from ..mesh import MESH_FORMATS

    order = (mesh_format, *(f for f in MESH_FORMATS if f != mesh_format))
    folder, out = Path(cdir) / "meshes", {}
    if not folder.is_dir():
        return out
    for f in folder.iterdir():
        stem, _, ext = f.name.rpartition(".")
        if ext in order and stem and not f.name.startswith(".") and f.is_file():
            out.setdefault(stem, []).append(ext)
    return {stem: sorted(exts, key=order.index) for stem, exts in out.items()}


#: The reason of an object that an unfinished run (:func:`unfinished`) has not reconstructed yet.
NOT_YET = "not reconstructed yet (the run is unfinished)"


def unfinished(recon: Path) -> bool:
    """Whether the run in ``recon`` has not finished (interrupted, or still running): its ``summary.json`` is
    missing, unreadable, or has no ``total_seconds`` (which a run writes when its last class is done)."""
    try:
        summary = read_json(Path(recon) / "summary.json")
    except (OSError, ValueError):
        return True
    return not isinstance(summary, dict) or "total_seconds" not in summary
