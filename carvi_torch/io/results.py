"""The run's reports and per-class JSON files: ``summary.json`` entries, ``cameras.json``, proposal scores.

Example:
    >>> r = ClassReport("car", objects=2)
    >>> r.skip("no usable camera", "viewpoints", annotation_id=7, source="a.xml")
    >>> r.to_dict()["skipped"], r.to_dict()["failures"][0]["reason"]
    (1, 'no usable camera')
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from .. import quality
from ..cameras import azimuth_elevation_roll_from_rotation
from ..mesh import occupancy_to_mesh, write_mesh
from .layout import MESH_MEMBER, SETTINGS_MEMBER, class_dir, held_settings, mesh_record, object_file, settings_text
from .outputs import numbers, read_json, shown, write_json, write_npz

__all__ = ["ROTATION_TOLERANCE", "numbers", "rotation_problem", "camera_record_problem", "shown", "ClassReport",
           "cameras_json", "mean_shape_problem", "cameras_part_problems", "cameras_file_problem", "scores_entry",
           "write_scores", "canonical_image_cameras", "resumed_objects", "drop_cameras", "quality_summary",
           "annotation_source", "same_object"]


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
    #: ``{str(annotation id): reconstruction_iou}`` of the objects written by this run (as the writers report
    #: it) and of those finished earlier (read from their files); not part of ``summary.json``.
    reconstruction_iou: dict = field(default_factory=dict)

    def skip(self, reason: str, stage: str, annotation_id=None, source=None):
        self.skipped.append({"annotation_id": annotation_id, "source": source, "stage": stage, "reason": reason})

    def skip_class(self, reasons: list[tuple]) -> "ClassReport":
        """The class is skipped (``status``), for ``reasons``: :meth:`skip`'s arguments, one tuple per entry.
        Returns this report."""
        self.status = "skipped"
        for reason in reasons:
            self.skip(*reason)
        return self

    def failures(self) -> list:
        """The skipped objects, class-level entries first, then by annotation id (the order in which
        writer processes finish must not change the report)."""
        return sorted(self.skipped, key=lambda f: (f["annotation_id"] is not None,
                                                   f["annotation_id"] if isinstance(f["annotation_id"], int) else 0))

    def to_dict(self) -> dict:
        return {"objects": self.objects, "reconstructed": self.reconstructed, "resumed": self.resumed,
                "skipped": len(self.skipped), "status": self.status, "failures": self.failures(),
                "warnings": self.warnings, "seconds": {k: round(v, 3) for k, v in self.seconds.items()},
                **self.info}

    def merge(self, part: "ClassReport") -> None:
        """Add the objects, failures, warnings and seconds of ``part``, the report of some of this class's
        objects (a chunk carved by another process)."""
        self.reconstructed += part.reconstructed
        self.skipped.extend(part.skipped)
        self.warnings.extend(part.warnings)
        self.reconstruction_iou.update(part.reconstruction_iou)
        for k, v in part.seconds.items():
            self.seconds[k] = self.seconds.get(k, 0.0) + v

    def book_write(self, out: dict, aid, src) -> None:
        """Book a writer's result (:func:`carvi_torch.io.write_worker.write_object`) for object ``aid``."""
        self.seconds["mesh"] = self.seconds.get("mesh", 0.0) + out["mesh_seconds"]
        self.seconds["write"] = self.seconds.get("write", 0.0) + out["write_seconds"]
        if out["ok"]:
            self.reconstructed += 1
            if out.get("reconstruction_iou") is not None:
                self.reconstruction_iou[str(aid)] = out["reconstruction_iou"]
        else:
            self.skip(out["reason"], "mesh", aid, src)


def annotation_source(ann: dict) -> str:
    """The ``source`` of a COCO annotation as :func:`carvi_torch.io.coco.load_coco` names the object (and
    ``cameras.json`` records it): the annotation's ``source``, else ``annotation <id>``."""
    return str(ann.get("source") or f"annotation {ann.get('id')}")


def same_object(cls: str, source: str | None, now_class: str | None, now_source: str) -> bool:
    """Whether an object a run recorded (its class key ``cls`` and ``cameras.json``'s ``source``, ``None``
    where the entry has none) is the one an annotation file now holds under its id (``now_class``, the class
    key of its category, and ``now_source``, :func:`annotation_source`): the readers of a run (evaluate,
    report) check it before they compare or draw the file's annotation with the run's outputs.

    Example:
        >>> same_object("car", "a.xml", "car", "a.xml"), same_object("car", None, "car", "annotation 3")
        (True, True)
        >>> same_object("car", "a.xml", "car", "b.xml"), same_object("car", "a.xml", "chair", "a.xml")
        (False, False)
    """
    return now_class == cls and (source is None or source == now_source)


def _camera_from(has_cam: bool, ground_truth: bool, sfm_ok: bool, unseen: int) -> str | None:
    if not has_cam:
        return None
    if ground_truth:
        return "ground_truth"
    if sfm_ok:
        return "sfm"
    # the unseen-image path: the mean shape's keypoints and the silhouette, or the silhouette alone
    return "mean_shape" if unseen > 0 else "silhouette"


def canonical_image_cameras(coll, vp, which: str = "cameras"):
    """The originals' cameras (``vp.cameras`` or ``vp.sfm_cameras``) in the canonical frame and image pixels."""
    n = len(coll)
    groups = vp.groups.labels if vp.groups.k > 1 else None
    cams = getattr(vp, which)[:n]
    cams = vp.frame.cameras(cams, groups) if vp.frame is not None else cams
    return cams.compose_similarity(coll.canvas_from_image.inverse())


def _angles(az, el, ro, has_cam: bool) -> dict:
    """``azimuth_deg``, ``elevation_deg``, ``roll_deg`` of a camera (``None`` for an object without one)."""
    return {k: math.degrees(float(v)) if has_cam else None
            for k, v in (("azimuth_deg", az), ("elevation_deg", el), ("roll_deg", ro))}


def resumed_objects(cdir: Path, coll, vp, done: list, mesh_format: str | None = None) -> dict:
    """The objects an earlier run finished (``done``, per original: the format of its mesh, else ``None``,
    :func:`~carvi_torch.io.layout.resume_check`), brought up to this run's cameras:
    each voxels file's ``voxel_to_object`` is rewritten from this run's camera where it differs (the cameras are
    fitted jointly, so a change to any object's input moves every camera, while a resumed object keeps its
    grid, which is in its image's frame: ``voxel_to_camera`` and every other member do not depend on the
    camera); ``NaN`` where the object has no camera now. With ``mesh_format``, a resumed object whose mesh is in
    another format only (an earlier run's ``mesh_format``) gets its mesh made again from its voxels (as the
    writers make it) in ``mesh_format``, and the other file is removed (:func:`_converted_mesh`). Returns
    ``{str(aid): reconstruction_iou}`` of them (read from the same files). A file that cannot be read is left
    alone (the object is redone anyway)."""
    ids = [i for i, d in enumerate(done) if d]
    if not ids:
        return {}
    to_object = canonical_image_cameras(coll, vp).camera_to_object_4x4().cpu()
    has_camera = vp.has_camera[:len(coll)].tolist()
    out = {}
    for i in ids:
        aid = coll.annotation_ids[i]
        path = object_file(cdir, "voxels", aid)
        try:
            with np.load(path) as z:
                members = {k: z[k] for k in z.files}
            v2img = torch.from_numpy(np.asarray(members["voxel_to_camera"], dtype=np.float64))
        except Exception:  # noqa: BLE001 - a damaged file (zipfile.BadZipFile...): its object is redone
            continue
        if "reconstruction_iou" in members:
            out[str(aid)] = float(members["reconstruction_iou"])
        v2o = (to_object[i] @ v2img).numpy() if has_camera[i] else np.full((4, 4), np.nan)
        converted = _converted_mesh(aid, members, mesh_format, done[i])
        record = {**_mesh_format_record(members, mesh_format),
                  **({MESH_MEMBER: mesh_record(mesh_format, len(converted.faces))} if converted is not None else {})}
        if record or not np.array_equal(members.get("voxel_to_object"), v2o, equal_nan=True):
            write_npz(path, sync=False, **{**members, "voxel_to_object": v2o, **record})
        if converted is not None:
            write_mesh(converted, object_file(cdir, "meshes", aid, mesh_format), sync=False)
            object_file(cdir, "meshes", aid, done[i]).unlink(missing_ok=True)
    return out


def _mesh_format_record(members: dict, mesh_format: str | None) -> dict:
    """``{SETTINGS_MEMBER: record}`` of a resumed object whose mesh is made again in ``mesh_format``
    (:func:`_converted_mesh`; ``None``: none is): its voxels file's settings record with that ``mesh.format``, the
    format its files are then in, written before the mesh (a stop between them leaves the mesh to convert, which
    the next run does); ``{}`` where the record says that format already, or there is no record.

    Example:
        >>> held = {SETTINGS_MEMBER: np.asarray('{"mesh.format":"ply"}')}
        >>> str(_mesh_format_record(held, "obj")[SETTINGS_MEMBER]), _mesh_format_record(held, "ply")
        ('{"mesh.format":"obj"}', {})
    """
    made = held_settings(members)
    if mesh_format is None or made is None or made.get("mesh.format", mesh_format) == mesh_format:
        return {}
    return {SETTINGS_MEMBER: np.asarray(settings_text({**made, "mesh.format": mesh_format}), dtype=str)}


def _converted_mesh(aid, members: dict, mesh_format: str | None, taken: str):
    """A resumed object's mesh (a ``trimesh.Trimesh``) to write in ``mesh_format`` where the one it is resumed with
    is in another format (``taken``, its ``done`` entry: the resume check found no mesh in ``mesh_format``), made
    from its voxels file's ``members`` as the writers make it (the occupancy is the written one, its largest
    component already taken); ``None`` where there is none to convert. The caller records its faces in the voxels
    file, writes it, then removes the other file (the same shape, in a format the run no longer writes): a stop
    before the mesh is written leaves the old file, checked as before (the record names the other format), and
    the next run converts it."""
    if not isinstance(taken, str):  # a truth value would name a file "<id>.True" and rewrite every resumed mesh
        raise TypeError(f"object {aid}: its done entry must be the format of the mesh it is resumed with "
                        f"(ResumeCheck.done), got {taken!r}")
    if mesh_format is None or taken == mesh_format:
        return None
    return occupancy_to_mesh(members["occupancy"], members["voxel_to_camera"])


def drop_cameras(out: Path | None, key: str, report: "ClassReport") -> None:
    """A class that stops before its cameras (skipped: too few instances, no true or SfM camera) has no
    ``cameras.json`` from this run: an earlier run's, which would list objects this run leaves out (and have the
    report draw them), is moved aside to :data:`EARLIER_CAMERAS`, with a warning (one that cannot be moved is named
    in it); the objects' meshes
    and voxels stay (finished work is never removed: a rerun that reconstructs the class resumes them). Nothing
    without ``out``."""
    path = class_dir(out, key) / "cameras.json" if out is not None else None
    if path is None or not path.is_file():
        return
    try:
        path.replace(path.with_name(EARLIER_CAMERAS))  # kept hidden: the puffball records (resumed_levels)
    except OSError as e:  # a folder the run cannot write: the class stays skipped, and the file is named
        report.warnings.append(f"cameras.json of an earlier run not removed ({e}): it lists objects this run "
                               "leaves out")
        return
    report.warnings.append(f"cameras.json of an earlier run moved to {EARLIER_CAMERAS} (this run skips the class; "
                           "the meshes and voxels of its objects stay, left out of the report and the export)")


#: Where :func:`drop_cameras` keeps a skipped class's earlier ``cameras.json`` (hidden: no reader lists it), so that
#: a later run resuming the class's objects still knows which were puffballs (:func:`resumed_levels`).
EARLIER_CAMERAS = ".cameras_earlier.json"


def quality_summary(cameras: dict) -> dict:
    """``summary.json``'s ``quality`` of a class: count, mean, quartiles and deciles of the objects' quality."""
    q = np.array([c["quality"] for c in cameras.values() if c.get("quality") is not None], dtype=np.float64)
    if len(q) == 0:
        return {"count": 0}
    pct = np.percentile(q, [10, 25, 50, 75, 90])
    return {"count": int(len(q)), "mean": round(float(q.mean()), 4),
            **{k: round(float(v), 4) for k, v in zip(("p10", "p25", "median", "p75", "p90"), pct)}}


def _quality(entry: dict, cam: dict, recon_iou: float | None) -> tuple[float | None, dict]:
    """An object's ``quality`` and the signals it combines (carvi_torch.quality)."""
    if entry["refined"] is None:
        return None, {}
    sig = {**cam, "camera_from": entry["camera_from"], "surrogates_from": entry["surrogates_from"],
           "reconstruction_iou": recon_iou}
    sig = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in sig.items() if v is not None}
    return round(quality.combine(sig), 4), sig


def _per_annotation(coll, vp, clusters, levels, recon: dict | None = None) -> dict:
    """``cameras.json``'s ``cameras``: per annotation id, SfM and final cameras in image pixels, canonical frame,
    and the object's ``quality`` with its ``quality_signals`` (``recon``: :func:`resumed_objects`)."""
    n = len(coll)
    mix = vp.groups
    group_of = mix.labels.tolist() if mix.k > 1 else None  # one host read
    sfm_img = canonical_image_cameras(coll, vp, "sfm_cameras").to_list()
    refined = canonical_image_cameras(coll, vp)
    ref_img = refined.to_list()
    az, el, ro = azimuth_elevation_roll_from_rotation(refined.R.double())
    sfm_ok, has_cam = vp.sfm_valid[:n].tolist(), vp.has_camera[:n].tolist()  # one host read each
    unseen = vp.unseen_keypoints[:n].tolist()
    kept = vp.kept_sfm[:n].tolist() if vp.kept_sfm is not None else None
    cam_sig = quality.camera_signals(coll, vp)
    recon = recon or {}
    per = {}
    for i, aid in enumerate(coll.annotation_ids):
        per[str(aid)] = {
            "source": coll.sources[i],
            "sfm": sfm_img[i] if sfm_ok[i] else None,
            "refined": ref_img[i] if has_cam[i] else None,
            "camera_from": _camera_from(has_cam[i], vp.source == "gt", sfm_ok[i], unseen[i]),
            **_angles(az[i], el[i], ro[i], has_cam[i]),
            "cluster": int(clusters.labels[i]) if clusters is not None else None,
            "surrogates_from": levels[i] if levels is not None else None,
        }
        if kept is not None:  # refine_keep class or objects: which of its two cameras the object keeps
            per[str(aid)]["camera_choice"] = ("sfm" if kept[i] else "refined") if sfm_ok[i] and has_cam[i] else None
        if group_of is not None:
            per[str(aid)]["shape_group"] = group_of[i]
        e = per[str(aid)]
        e["quality"], e["quality_signals"] = _quality(e, cam_sig[i], recon.get(str(aid)))
    return per


def _symmetry_plane(vp, frame, group: int) -> list | None:
    """The class's left-right reflection in the canonical frame (``None``: the class has none)."""
    if vp.reflection is None:
        return None
    P = frame.reflection(vp.reflection.cpu(), group) if frame is not None else vp.reflection
    return P.detach().double().cpu().tolist()


def cameras_json(coll, vp, axes: torch.Tensor | None, clusters, levels: list | None = None,
                 recon: dict | None = None) -> dict:
    """``cameras.json`` content of a class: per annotation id its cameras, then the mean shape,
    symmetry plane, principal directions and (with shape groups) every group's mean shape.

    Args:
        coll: the class; vp: its :class:`carvi_torch.viewpoints.Viewpoints`; axes: ``(3, 3)``
            principal directions; clusters: :class:`carvi_torch.surrogates.Clusters`; levels: per
            object, where its proposals come from (:data:`carvi_torch.surrogates.LEVELS`); recon: per
            annotation id, the reconstruction's quality signal (:func:`resumed_objects`, and the writers').
    """
    names = coll.meta.keypoint_names

    def named(S):
        S = S.detach().double().cpu()
        return {nm: (None if not torch.isfinite(S[k]).all() else S[k].tolist()) for k, nm in enumerate(names)}

    mix, frame, big = vp.groups, vp.frame, vp.groups.largest()
    canon = (lambda S, g=big: frame.points(S.cpu(), g)) if frame is not None else (lambda S, g=big: S)
    out = {
        "class": coll.name,
        "class_key": coll.meta.key,
        "frame": frame.kind if frame is not None else "sfm",
        "frame_info": frame.info if frame is not None else {"kind": "sfm"},
        "camera_convention": "image pixels of each annotation's image; R rows = image x, image y (down), view "
                             "direction, in the frame above; azimuth, elevation, roll as PASCAL3D+ defines them",
        "cameras": _per_annotation(coll, vp, clusters, levels, recon),
        "mean_shape": named(canon(vp.shape)),
        "symmetry_plane": _symmetry_plane(vp, frame, big),
        "principal_directions": None if axes is None else (
            frame.directions(axes.cpu(), big) if frame is not None else axes).detach().double().cpu().tolist(),
        "cluster_threshold_deg": float(clusters.threshold_deg) if clusters is not None else None,
    }
    if mix.k > 1:  # a mixture of rigid shapes: every group's mean shape, in the canonical frame
        sizes = mix.sizes()
        out["shape_groups"] = [{"objects": sizes[g], "mean_shape": named(canon(mix.shape(g), g))}
                               for g in range(mix.k)]
        out["mean_shape_group"] = big
    return out


def scores_entry(sel, j: int, surrogates: torch.Tensor | None, aid_of: list) -> dict:
    """``proposal_scores.json`` entry of reference ``j`` of a chunk's :class:`carvi_torch.select.Selection`."""
    return {
        "best": int(sel.best[j]),
        "scores": [None if not math.isfinite(v) else round(v, 6) for v in sel.scores[j].tolist()],
        "misses": [int(v) if v < 10 ** 6 else None for v in sel.misses[j].tolist()],
        "surrogates": ([[aid_of[s] if s >= 0 else None for s in pair] for pair in surrogates[j].tolist()]
                       if surrogates is not None else None),
    }


def write_scores(cdir: Path, annotation_ids: list, overwrite: bool) -> None:
    """``cdir/proposal_scores.json``: the per-object score files (``scores/<stem>.json``, written with
    each object, so a killed run keeps them) of ``annotation_ids``, merged (atomic). Objects without a
    score file keep the entry an earlier file had, unless ``overwrite``."""
    sp = cdir / "proposal_scores.json"
    merged = {}
    if sp.is_file() and not overwrite:
        try:
            merged = read_json(sp)
        except ValueError:
            merged = {}
    for aid in annotation_ids:
        p = object_file(cdir, "scores", aid)
        if p.is_file():
            try:
                merged[str(aid)] = read_json(p)
            except ValueError:
                pass  # a damaged score file: its object is redone only by overwrite; the earlier entry stays
    if merged:
        write_json(sp, merged, indent=None)


def resumed_levels(cdir: Path, coll, levels: list, done: list) -> list:
    """``levels`` with the puffball fallbacks of finished objects kept from the earlier run's cameras.json (or the
    one :func:`drop_cameras` moved aside; a puffball is decided after carving, which a resumed object does not
    repeat)."""
    previous: dict = {}
    for name in (EARLIER_CAMERAS, "cameras.json"):  # the later run's records last: they win
        try:
            previous.update(read_json(cdir / name).get("cameras", {}) if (cdir / name).is_file() else {})
        except (ValueError, AttributeError, TypeError):  # unreadable records: no puffball known from them
            pass
    return [("puffball" if d and (previous.get(str(a)) or {}).get("surrogates_from") == "puffball" else lv)
            for a, lv, d in zip(coll.annotation_ids, levels, done)]


# --------------------------------------------------------------------------- camera records read back


#: How far ``R R^T`` may be from the identity for ``R`` (of ``gt.json`` or of a run) to count as a rotation.
ROTATION_TOLERANCE = 1e-3


def rotation_problem(R) -> str | None:
    """Why ``R`` is no rotation matrix (3 x 3 finite numbers whose ``R R^T`` is the identity within
    :data:`ROTATION_TOLERANCE`, determinant +1); ``None`` when it is one.

    Example:
        >>> rotation_problem([[0, -1, 0], [1, 0, 0], [0, 0, 1]]) is None
        True
        >>> rotation_problem([[2, 0, 0], [0, 2, 0], [0, 0, 2]]), rotation_problem([[1, 0, 0], [0, 1, 0]])
        ('R is not a rotation', 'R is not 3 x 3 finite numbers')
    """
    if not numbers(R, (3, 3)):
        return "R is not 3 x 3 finite numbers"
    R = np.asarray(R, dtype=np.float64)
    if np.abs(R @ R.T - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        return "R is not a rotation"
    return None


def camera_record_problem(cam, finite: bool = True) -> str | None:
    """What makes a camera record unusable (``R``, ``s``, ``t``: an entry of ``cameras.json``'s ``sfm`` or
    ``refined``, or of ``gt.json``), ``None`` when nothing does: ``R`` a rotation (:func:`rotation_problem`), ``s``
    a positive number and ``t`` two numbers, all finite; with ``finite=False`` non-finite numbers (an estimate that
    failed) pass, ``R`` being a rotation where it is finite. The one check of the commands that read cameras back
    (evaluate, export).

    Example:
        >>> camera_record_problem({"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "s": 2.0, "t": [0, 1]}) is None
        True
        >>> camera_record_problem({"R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "s": None, "t": [0, 1]})
        's is None, not a finite positive number'
    """
    if not isinstance(cam, dict):
        return f"{shown(cam)} is not an object with R, s and t"
    R, s, t = cam.get("R"), cam.get("s"), cam.get("t")
    if not numbers(R, (3, 3), finite):
        return "R is not 3 x 3 finite numbers" if finite else "R is not 3 x 3 numbers"
    if numbers(R, (3, 3)) and rotation_problem(R):
        return rotation_problem(R)
    if finite and not (numbers(s, ()) and s > 0):
        return f"s is {shown(s)}, not a finite positive number"
    if not numbers(s, (), finite):
        return f"s is {shown(s)}, not a number"
    if not numbers(t, (2,), finite):
        return f"t is {shown(t)}, not 2 {'finite ' if finite else ''}numbers"
    return None


def mean_shape_problem(shape) -> str | None:
    """What makes a mean shape of ``cameras.json`` (its ``mean_shape``, or a shape group's) unusable: not an object
    of keypoint name -> 3 finite numbers or ``null`` (a keypoint the shape lacks); ``None`` when nothing does.

    Example:
        >>> mean_shape_problem({"nose": [0, 1, 2], "tail": None}) is None
        True
        >>> mean_shape_problem([1, 2])
        'mean_shape is [1, 2], not an object of keypoint name -> 3 numbers'
        >>> mean_shape_problem({"nose": [0, 1, "x"]})
        "mean_shape 'nose' is [0, 1, 'x'], not 3 finite numbers"
    """
    if not isinstance(shape, dict):
        return f"mean_shape is {shown(shape)}, not an object of keypoint name -> 3 numbers"
    bad = next((k for k, row in shape.items() if row is not None and not numbers(row, (3,))), None)
    return None if bad is None else f"mean_shape {shown(bad)} is {shown(shape[bad])}, not 3 finite numbers"


def cameras_part_problems(cams: dict) -> dict[str, str]:
    """Per part of a class's ``cameras.json`` (``cams``, a JSON object) that has the wrong type, what is wrong:
    ``cameras`` not an object of annotation id -> entry; ``mean_shape`` unusable (:func:`mean_shape_problem`);
    ``shape_groups`` not a list of objects whose ``mean_shape`` is usable. An absent or ``null`` part is none.

    Example:
        >>> cameras_part_problems({"cameras": {}, "shape_groups": [5]})
        {'shape_groups': "'shape_groups' is [5], not a list of objects with a mean_shape"}
    """
    out = {}
    if cams.get("cameras") is not None and not isinstance(cams["cameras"], dict):
        out["cameras"] = f"'cameras' is {shown(cams['cameras'])}, not an object of annotation id -> entry"
    if cams.get("mean_shape") is not None and (why := mean_shape_problem(cams["mean_shape"])):
        out["mean_shape"] = why
    groups = cams.get("shape_groups")
    if groups is not None and not (isinstance(groups, list) and all(isinstance(g, dict) for g in groups)):
        out["shape_groups"] = f"'shape_groups' is {shown(groups)}, not a list of objects with a mean_shape"
    elif groups is not None:
        bad = [(i, why) for i, g in enumerate(groups)
               if g.get("mean_shape") is not None and (why := mean_shape_problem(g["mean_shape"]))]
        if bad:
            out["shape_groups"] = f"shape group {bad[0][0]}'s {bad[0][1]}"
    return out


def cameras_file_problem(cams) -> str | None:
    """What makes a class's ``cameras.json`` (``cams``, its content) unusable as a whole: not a JSON object, its
    ``cameras`` not an object of annotation id -> entry, or its ``mean_shape`` unusable (:func:`mean_shape_problem`;
    either may be absent or ``null``); ``None`` when nothing does. The one check of the commands that read a
    class's cameras back whole (export, report: :func:`cameras_part_problems`, which this reads); a single entry's
    camera is :func:`camera_record_problem`'s.

    Example:
        >>> cameras_file_problem({"cameras": {}, "mean_shape": {"a": [0, 0, 1]}}) is None
        True
        >>> cameras_file_problem({"cameras": [1]}), cameras_file_problem([])
        ("'cameras' is [1], not an object of annotation id -> entry", 'not a JSON object')
    """
    if not isinstance(cams, dict):
        return "not a JSON object"
    problems = cameras_part_problems(cams)
    return problems.get("cameras") or problems.get("mean_shape")
