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

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .outputs import safe_name

__all__ = ["class_dir", "object_stem", "object_file", "finished", "KINDS", "RUN_NAMES", "reserved", "INPUTS_CHANGED",
           "NO_INPUT_RECORD", "ResumeCheck", "resume_check", "other_objects", "held_fingerprint", "linked_path"]

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
    for tree in ("input", "report"):
        for top, dirs, files in os.walk(out / tree):  # not into linked folders: those are reported
            for name in sorted(dirs + files):
                if os.path.islink(os.path.join(top, name)):
                    return Path(top) / name
    for key in keys:
        for path in (out / key, *(out / key / kind for kind in KINDS)):
            if path.is_symlink():
                return path
    return None


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


#: Why a finished object is redone although its files are sound: :func:`finished`'s reasons a run counts
#: (``summary.json``: ``redone``) rather than logging each object's.
INPUTS_CHANGED = "its inputs differ from those it was made from"
NO_INPUT_RECORD = "its files hold no record of its inputs (an older run's)"


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


def _voxels_state(path: Path) -> tuple[str | None, str | None]:
    """``(why a voxels file is not a finished object's or None, the input fingerprint it holds or None)``."""
    try:
        with np.load(path) as z:
            members = {k: z[k] for k in z.files}  # every member read: the zip's checksums cover each
            occ, T = members["occupancy"], members["voxel_to_camera"]
    except Exception as e:  # noqa: BLE001 - any damage means: redo the object
        return f"unreadable voxels ({type(e).__name__})", None
    if occ.dtype != bool or occ.ndim != 3 or T.shape != (4, 4) or not np.isfinite(T).all():
        return f"voxels of the wrong kind (occupancy {occ.dtype} {occ.shape}, transform {T.shape})", None
    return None, held_fingerprint(members)


def _mesh_ok(path: Path) -> str | None:
    """Why a mesh file is not a finished object's (``None``: it is one)."""
    import trimesh

    try:
        m = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001
        return f"unreadable mesh ({type(e).__name__})"
    faces = np.asarray(getattr(m, "faces", np.zeros((0, 3))))
    if len(faces) == 0:
        return "mesh without faces"
    # a written mesh names three distinct vertices per face: zeros where a file's tail never reached the disk do not
    if (faces.min() < 0 or faces.max() >= len(m.vertices) or (faces[:, 0] == faces[:, 1]).any()
            or (faces[:, 1] == faces[:, 2]).any() or (faces[:, 0] == faces[:, 2]).any()):
        return "mesh with broken faces"
    return None


def finished(cdir: str | Path, annotation_id, mesh_format: str, fingerprint: str | None = None) -> str | bool:
    """Whether an earlier run finished an object: ``True``, ``False`` (no files), or the reason its files
    cannot be trusted (the object is redone): a truncated or damaged mesh or voxels file, or, when its
    current input ``fingerprint`` is given (``ClassCollection.fingerprints``), files made from other
    inputs (:data:`INPUTS_CHANGED`) or holding no fingerprint (:data:`NO_INPUT_RECORD`).

    Example:
        >>> finished("no/such/run/car", 3, "ply")
        False
    """
    mesh, voxels = object_file(cdir, "meshes", annotation_id, mesh_format), object_file(cdir, "voxels", annotation_id)
    if not (mesh.is_file() and voxels.is_file()):
        return False
    why, held = _voxels_state(voxels)
    if why is None and fingerprint:
        why = None if held == fingerprint else (INPUTS_CHANGED if held else NO_INPUT_RECORD)
    return why or _mesh_ok(mesh) or True


#: ``summary.json`` names of the reasons a sound finished object is redone (per class: ``redone``).
REDONE = {INPUTS_CHANGED: "inputs_changed", NO_INPUT_RECORD: "no_input_record"}


@dataclass
class ResumeCheck:
    """What an earlier run left of a class's objects: ``done`` per object (resume it), ``damaged``
    (``{annotation id: reason}``: files that cannot be trusted), ``redone`` (``{reason name:
    [annotation ids]}``: sound files made from other inputs, or without a record of them) and ``others``
    (:func:`other_objects`: the stems of mesh or voxels files of objects the data no longer holds)."""

    done: list = field(default_factory=list)
    damaged: dict = field(default_factory=dict)
    redone: dict = field(default_factory=dict)
    others: list = field(default_factory=list)

    def lines(self, key: str) -> list[str]:
        """The run's warning lines for class ``key``: each damaged object, then the redone and the others'
        counts.

        Example:
            >>> ResumeCheck(others=["17", "18"]).lines("car")[0][:60]
            '  car: 2 object(s) of an earlier run that the data no longer'
        """
        out = [f"  {key}: annotation {a}: {why}; reconstructing it again" for a, why in self.damaged.items()]
        if self.redone:
            out.append(f"  {key}: {self.line()}")
        if self.others:
            shown = ", ".join(self.others[:5]) + (", ..." if len(self.others) > 5 else "")
            out.append(f"  {key}: {len(self.others)} object(s) of an earlier run that the data no longer holds keep "
                       f"their files in meshes/ and voxels/ ({shown}); cameras.json, the report and the export "
                       "leave them out")
        return out

    def info(self) -> dict:
        """``summary.json``'s entries of the class: ``redone`` and ``other_objects`` (``count``, ``stems``), where
        there are any."""
        return ({"redone": self.summary()} if self.redone else {}) | (
            {"other_objects": {"count": len(self.others), "stems": self.others}} if self.others else {})

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


def resume_check(cdir: str | Path, annotation_ids: list, fingerprints: list, mesh_format: str) -> ResumeCheck:
    """:func:`finished` for every object of a class (``fingerprints``: their current input fingerprints)."""
    check = ResumeCheck()
    for a, fp in zip(annotation_ids, fingerprints):
        state = finished(cdir, a, mesh_format, fp)
        if state in REDONE:
            check.redone.setdefault(REDONE[state], []).append(a)
        elif isinstance(state, str):
            check.damaged[a] = state
        check.done.append(state is True)
    return check
