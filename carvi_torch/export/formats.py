"""Annotation files of category-specific mesh reconstruction codebases, one per class.

``--format cmr`` writes ``<out>/<class>.mat`` the way CMR (Kanazawa et al. 2018) reads its SfM
annotations (``scipy.io.loadmat(path, struct_as_record=False, squeeze_me=True)``):

- ``sfm_anno``: a 1 x N struct array, one element per object that has a usable camera, with ``rot``
  (3 x 3: rows image x, image y (down), viewing direction, as ours), ``scale`` (scalar),
  ``trans`` (2, image pixels, **1-based** as MATLAB's), ``err_sfm_reproj`` (sum over the K
  keypoints of the squared reprojection error of the visible ones, divided by
  ``K * box_scale^2``, ``box_scale`` = the longer side of the object's box in image pixels, the
  normalisation of CMR's ``pascal_sfm.m``; the box is the annotation's, :func:`annotation_boxes`, not the
  padded canvas around it); a keypoint ``X`` (a column of ``S``) projects to
  ``scale * rot[:2] @ X + trans``.
- ``S``: 3 x K mean shape in the class's canonical frame, centred on its mean and scaled so that
  its largest pairwise keypoint distance is 2 (CMR's normalisation); keypoints the mean shape
  lacks are placed at the centre.
- ``conv_tri``: F x 3 triangles of the convex hull of ``S`` (``scipy.spatial.ConvexHull``),
  **1-based** (CMR subtracts 1 when it loads them).
- ``annotation_ids``, ``image_ids``, ``sources``, ``kp_names``: which object each element is;
  ``skipped_ids``, ``skipped_reasons``: the class's objects left out, and why.
- ``made_with_run_settings`` (1 x N logical): per element, whether the object's shape (its voxels and mesh in the
  run folder) was made with the run's settings, as the zarr store's field of that name says;
  ``made_with_other_settings``: the class's objects' record of the other settings, as JSON text (``{}``: none).

``--format ucmr`` writes ``<out>/<class>.json`` with one record per object: ``annotation_id``,
``image_id``, ``source``, ``bbox`` (the annotation's box, x0, y0, x1, y1: its extreme pixel centres, image
pixels, 0-based), ``quality`` and
``sfmpose = [s, [tx, ty], [qw, qx, qy, qz]]``: CMR's pose of the same object (``trans`` 1-based,
the quaternion of ``rot``, scalar first as CMR's ``quaternion_from_matrix`` gives it) and
``made_with_run_settings`` (as the ``.mat``'s); plus the mean shape ``S`` (K x 3), ``faces`` (0-based),
``skipped`` (the class's objects left out, with the reason) and ``made_with_other_settings`` (the record, a dict).

Objects left out (skipped when the annotations were read, without a usable camera, of a class whose
``cameras.json`` is missing, and the entries of ``cameras.json`` that name no object of the annotation file)
are reported as the zarr export reports its own.

Each file carries :data:`MARKER` (a key of the JSON, a variable of the ``.mat``) = its format: an export replaces
its own earlier files alone, and refuses, before it writes anything, an ``--out`` where a file it would write
is someone else's (a user's ``car.json``, a run's ``summary.json``).

Example:
    >>> import numpy as np
    >>> S = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [0, 0, 3]], float)
    >>> Sn, centre, k = normalised_shape(S)
    >>> round(float(np.linalg.norm(Sn[1] - Sn[3])), 6), bool(np.allclose(Sn.mean(0), 0))
    (2.0, True)
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import scipy.io
from scipy.spatial import ConvexHull, QhullError, distance

from ..io.coco import load_coco, object_id
from ..io.layout import file_settings, object_file, settings_text
from ..io.outputs import atomic_write, read_json, write_json
from .source import (SettingsTally, camera_entry, camera_problem, class_cameras, class_scope, data_path, load_skips,
                     recon_config, run_classes, unfinished)

__all__ = ["normalised_shape", "cmr_pose", "export_format", "class_records", "quaternion_wxyz", "annotation_boxes",
           "MARKER"]

#: The key (``ucmr`` JSON) or variable (``cmr`` ``.mat``) that marks a file as this export's; its value is the format.
MARKER = "carvi_export"
#: The U-CMR file's ``convention`` (also how a file written before :data:`MARKER` is recognised).
CONVENTION = ("sfmpose = [s, [tx, ty], [qw, qx, qy, qz]]: keypoint X of S projects to s * R(q)[:2] @ X + t in image "
              "pixels, 1-based (CMR's); R rows = image x, image y (down), viewing direction")


def normalised_shape(S: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """``(S - c) * k`` with ``c`` the mean of ``S (K, 3)`` and ``k`` making its diameter 2; returns it, ``c``, ``k``."""
    c = S.mean(axis=0)
    d = distance.pdist(S).max() if len(S) > 1 else 0.0
    k = 2.0 / d if d > 0 else 1.0
    return (S - c) * k, c, k


def cmr_pose(R: np.ndarray, s: float, t: np.ndarray, centre: np.ndarray, k: float) -> tuple[float, np.ndarray]:
    """CMR's ``scale`` and 0-based ``trans`` of our camera ``(R, s, t)`` for the normalised shape
    ``S' = (X - centre) k``: ``s R[:2] X + t = (s / k) R[:2] S' + (t + s R[:2] centre)``."""
    return s / k, t + s * R[:2] @ centre


def quaternion_wxyz(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation, ``w >= 0``."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def _outward_hull(S: np.ndarray) -> np.ndarray:
    """Triangles ``(F, 3)`` of the convex hull of ``S (K, 3)``, wound counter-clockwise seen from outside; of a
    flat ``S`` (its keypoints in one plane or on one line), the hull of a joggled copy (Qhull's ``QJ``): both
    sides of the flat shape."""
    if len(S) < 4:
        return np.zeros((0, 3), dtype=np.int64)
    try:
        h = ConvexHull(S)
    except QhullError:  # flat: no 3-D hull
        h = ConvexHull(S, qhull_options="QJ")
    f = h.simplices.copy()
    n = np.cross(S[f[:, 1]] - S[f[:, 0]], S[f[:, 2]] - S[f[:, 0]])
    inward = (n * (S[f[:, 0]] - S[h.vertices].mean(axis=0))).sum(axis=1) < 0
    f[inward] = f[inward][:, ::-1]
    return f


def _mean_shape(cams: dict, names: list) -> np.ndarray:
    """``(K, 3)`` mean shape in keypoint order; a keypoint without a row goes to the others' centre."""
    rows = [(cams.get("mean_shape") or {}).get(n) for n in names]
    known = np.array([r for r in rows if r is not None], dtype=np.float64)
    c = known.mean(axis=0) if len(known) else np.zeros(3)
    return np.array([r if r is not None else c for r in rows], dtype=np.float64)


def annotation_boxes(annotations: list) -> dict[str, list[float]]:
    """``{str(annotation id): [x0, y0, x1, y1]}``: the box of each annotation with a usable COCO ``bbox``
    (``[x, y, w, h]``, ``w, h > 0``, finite) as the extreme pixel centres it spans, ``[x, y, x + w - 1, y + h - 1]``
    (0-based, inclusive: CMR's ``bbox`` less 1); the first annotation of a repeated id, as the loader keeps it.

    Example:
        >>> annotation_boxes([{"id": 3, "bbox": [10, 20, 5, 8]}, {"id": 4, "bbox": [0, 0, 0, 1]},
        ...                   {"id": 4, "bbox": [1, 1, 5, 5]}])
        {'3': [10.0, 20.0, 14.0, 27.0]}
    """
    out: dict[str, list[float] | None] = {}
    for ann in annotations:
        aid, box = object_id(ann.get("id")) if isinstance(ann, dict) else None, None
        if aid is None or str(aid) in out:  # a later annotation of a repeated id is not the object
            continue
        try:
            x, y, w, h = (float(v) for v in ann["bbox"])
            box = [x, y, x + w - 1.0, y + h - 1.0] if w > 0 and h > 0 and np.isfinite([x, y, w, h]).all() else None
        except (KeyError, TypeError, ValueError):
            pass
        out[str(aid)] = box
    return {a: b for a, b in out.items() if b is not None}


def _mask_box(coll, i: int) -> np.ndarray:
    """The image box ``(x0, y0, x1, y1)`` of object ``i``'s canvas mask (its extreme pixel centres, mapped back
    to the image: within a canvas pixel of the mask's own box), for an annotation without a usable ``bbox``."""
    a = float(coll.canvas_from_image.scale[i])
    b = coll.canvas_from_image.offset[i].double().cpu().numpy()
    m = coll.masks[i].cpu().numpy()
    ys, xs = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
    lo, hi = (np.array([xs[0], ys[0]]), np.array([xs[-1], ys[-1]])) if len(xs) else (0.0, m.shape[-1] - 1.0)
    return np.concatenate([(lo - b) / a, (hi - b) / a])


def class_records(cams: dict, cname: str, coll, boxes: dict, skipped: list) -> tuple[list[dict], np.ndarray,
                                                                                      np.ndarray]:
    """Per object with a usable camera: ids, CMR pose, reprojection error, box (``boxes``:
    :func:`annotation_boxes`; the mask's box for an object without one) and quality; the normalised mean shape
    ``(K, 3)``; its convex hull triangles ``(F, 3)`` (0-based). The objects without a camera, or with one that
    is not usable (:func:`~carvi_torch.export.source.camera_problem`), go to ``skipped`` with their reason."""
    names = list(coll.meta.keypoint_names)
    S, centre, k = normalised_shape(_mean_shape(cams, names))
    hull = _outward_hull(S)
    kp_img = coll.keypoints_in_image().double().cpu().numpy()
    vis = coll.visible.cpu().numpy()
    out = []
    for i, aid in enumerate(coll.annotation_ids):
        entry = camera_entry(cams, aid)
        reason = "no camera in cameras.json" if entry.get("refined") is None else camera_problem(entry)
        if reason is not None:
            skipped.append({"annotation_id": aid, "class": cname, "source": coll.sources[i], "reason": reason})
            continue
        cam = entry["refined"]
        R, s, t = np.asarray(cam["R"], dtype=np.float64), float(cam["s"]), np.asarray(cam["t"], dtype=np.float64)
        scale, trans = cmr_pose(R, s, t, centre, k)
        proj = (scale * S @ R[:2].T) + trans
        box = np.asarray(boxes[str(aid)]) if str(aid) in boxes else _mask_box(coll, i)
        box_scale = float(max(box[2] - box[0], box[3] - box[1])) + 1.0  # the box's longer side, in pixels
        err = float(((proj - kp_img[i]) ** 2).sum(axis=1)[vis[i]].sum()) / (len(names) * box_scale ** 2)
        out.append({"annotation_id": aid, "image_id": coll.image_ids[i], "source": coll.sources[i], "rot": R,
                    "scale": scale, "trans": trans, "err_sfm_reproj": err, "bbox": box.tolist(),
                    "quality": entry.get("quality")})
    return out, S, hull


def _write_cmr(path: Path, recs: list, S: np.ndarray, hull: np.ndarray, names: list, skipped: list,
               made: dict) -> None:
    anno = np.zeros((1, len(recs)), dtype=[("rot", object), ("scale", object), ("trans", object),
                                           ("err_sfm_reproj", object)])
    for j, r in enumerate(recs):
        anno[0, j] = (r["rot"], float(r["scale"]), r["trans"] + 1.0, float(r["err_sfm_reproj"]))
    ids = np.array([str(r["annotation_id"]) for r in recs], dtype=object)
    data = {MARKER: "cmr", "sfm_anno": anno, "S": S.T.copy(), "conv_tri": (hull + 1).astype(np.float64),
            "annotation_ids": ids, "image_ids": np.array([str(r["image_id"]) for r in recs], dtype=object),
            "sources": np.array([r["source"] or "" for r in recs], dtype=object),
            "kp_names": np.array(names, dtype=object),
            "skipped_ids": np.array([str(r["annotation_id"]) for r in skipped], dtype=object),
            "skipped_reasons": np.array([r["reason"] for r in skipped], dtype=object),
            "made_with_run_settings": np.array([[r["made_with_run_settings"] for r in recs]], dtype=bool),
            "made_with_other_settings": settings_text(made)}
    atomic_write(path, lambda f: scipy.io.savemat(f, data, do_compression=True))


def _write_ucmr(path: Path, cname: str, recs: list, S: np.ndarray, hull: np.ndarray, names: list,
                skipped: list, made: dict) -> None:
    items = [{"annotation_id": r["annotation_id"], "image_id": r["image_id"], "source": r["source"],
              "bbox": r["bbox"], "quality": r["quality"], "made_with_run_settings": r["made_with_run_settings"],
              "sfmpose": [float(r["scale"]), (r["trans"] + 1.0).tolist(), quaternion_wxyz(r["rot"]).tolist()]}
             for r in recs]
    write_json(path, {MARKER: "ucmr", "class": cname, "keypoint_names": names, "S": S.tolist(),
                      "faces": hull.tolist(), "convention": CONVENTION, "images": items,
                      "skipped": [{k: r.get(k) for k in ("annotation_id", "source", "reason")} for r in skipped],
                      "made_with_other_settings": made})


def _ours(path: Path, fmt: str) -> bool:
    """Whether the file at ``path`` is one an earlier ``fmt`` export wrote: it carries :data:`MARKER` = ``fmt``, or,
    written before the marker, the U-CMR :data:`CONVENTION` / the ``.mat``'s ``kp_names`` and ``skipped_reasons``
    beside ``sfm_anno`` (CMR's own files have neither)."""
    try:
        if fmt == "ucmr":
            js = read_json(path)
            return isinstance(js, dict) and (js.get(MARKER) == fmt or js.get("convention") == CONVENTION)
        names = {n for n, _, _ in scipy.io.whosmat(path)}
        if MARKER in names:
            return str(scipy.io.loadmat(path, variable_names=[MARKER], squeeze_me=True)[MARKER]) == fmt
        return {"sfm_anno", "kp_names", "skipped_reasons"} <= names
    except (OSError, ValueError, TypeError, scipy.io.matlab.MatReadError):
        return False


def _check_replaceable(paths: list, out: Path, fmt: str) -> None:
    """``ValueError`` naming the first of ``paths`` (the files the export is to write) that stands in ``out`` and
    is not an earlier ``fmt`` export's (:func:`_ours`): it is never replaced."""
    for path in paths:
        if (path.exists() or path.is_symlink()) and not _ours(path, fmt):
            raise ValueError(f"--out {out}: {path.name!r} is not a file of an earlier --format {fmt} export (no "
                             f"{MARKER!r} marker): it is never replaced; choose another --out (nothing "
                             "was written)")


def _class_skips(loaded, recon: Path, cname: str, data: Path, pending: bool) -> tuple[dict | None, list]:
    """A class's ``cameras.json`` (None where it has none, or it cannot be read) and its skipped objects so far:
    those skipped at load, every other one where there are no cameras, and the entries of ``cameras.json`` that
    name no object of the annotation file ``data`` (:func:`~carvi_torch.export.source.class_cameras`; ``pending``:
    the run is unfinished)."""
    skipped = load_skips(loaded.problems, [cname])[cname]
    coll = loaded.collections.get(cname)
    cams = class_cameras(coll, cname, recon, skipped, pending, data) if coll is not None else None
    return cams, skipped


def _settings_of(recs: list, cdir: Path, tally: SettingsTally) -> dict:
    """Each record's ``made_with_run_settings`` from the settings its object's voxels file in the class folder
    ``cdir`` records (none, or no file: the folder's record counts), each counted in ``tally`` too; returns the
    class's own record (:meth:`~carvi_torch.export.source.SettingsTally.record`)."""
    mine = SettingsTally(tally.run, tally.folder)
    for r in recs:
        r["made_with_run_settings"] = mine.add(file_settings(object_file(cdir, "voxels", r["annotation_id"])))
    tally.others += mine.others
    return mine.record()


def export_format(recon: str | Path, out: str | Path, fmt: str, classes=None, progress: bool = True) -> dict:
    """Write one ``cmr`` ``.mat`` or ``ucmr`` ``.json`` file per reconstructed class of ``recon`` into ``out``;
    returns ``{"files": [the files written], "objects": how many they hold, "skipped": [objects not written, with
    their reason]}``: the objects skipped at load, those without a usable camera (their class's ``cameras.json``
    missing included), and the entries of ``cameras.json`` that name no object of the annotation file. Each file
    lists its class's in ``skipped``, and they are reported as the zarr export reports its own
    (:func:`~carvi_torch.export.run.report_skipped`; one line each, a count alone when ``progress`` is off).
    ``ValueError``, nothing written, where a file to write stands in ``out`` and is not this export's
    (:func:`_check_replaceable`)."""
    from .run import report_skipped

    recon, out = Path(recon), Path(out)
    cfg = recon_config(recon)
    covered = run_classes(cfg.classes, recon)
    data = data_path(recon, cfg)
    loaded = load_coco(data, canvas_size=cfg.input.canvas_size, margin=cfg.input.canvas_margin,
                       classes=classes or covered)
    scope = class_scope(loaded.dataset["categories"], covered, classes, recon)  # an unknown class: ValueError
    boxes = annotation_boxes(loaded.dataset["annotations"])
    skipped, pending, files = [], unfinished(recon), []
    tally = SettingsTally.of(recon, cfg)
    for cname in scope:  # every file's content first: the files in --out are checked before any is written
        cams, class_skipped = _class_skips(loaded, recon, cname, data, pending)
        if cams is not None:
            coll = loaded.collections[cname]
            recs, S, hull = class_records(cams, cname, coll, boxes, class_skipped)
            made = _settings_of(recs, recon / cname, tally)
            files.append((out / f"{cname}.{'mat' if fmt == 'cmr' else 'json'}", cname, recs, S, hull,
                          list(coll.meta.keypoint_names), class_skipped, made))
        skipped += class_skipped
    _check_replaceable([f[0] for f in files], out, fmt)
    for path, cname, recs, S, hull, names, class_skipped, made in files:
        if fmt == "cmr":
            _write_cmr(path, recs, S, hull, names, class_skipped, made)
        else:
            _write_ucmr(path, cname, recs, S, hull, names, class_skipped, made)
    objects = sum(len(f[2]) for f in files)
    report_skipped(recon, skipped, objects, pending, progress, data,
                   where="without --quiet each is listed with its reason", tally=tally)
    return {"files": [f[0] for f in files], "objects": objects, "skipped": skipped}
