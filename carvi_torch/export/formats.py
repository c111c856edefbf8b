"""Annotation files of category-specific mesh reconstruction codebases, one per class.

``--format cmr`` writes ``<out>/<class>.mat`` the way CMR (Kanazawa et al. 2018) reads its SfM
annotations (``scipy.io.loadmat(path, struct_as_record=False, squeeze_me=True)``):

- ``sfm_anno``: a 1 x N struct array, one element per object that has a camera, with ``rot``
  (3 x 3: rows image x, image y (down), viewing direction, as ours), ``scale`` (scalar),
  ``trans`` (2, image pixels, **1-based** as MATLAB's), ``err_sfm_reproj`` (sum over the K
  keypoints of the squared reprojection error of the visible ones, divided by
  ``K * box_scale^2``, ``box_scale`` = the longer side of the object's box in image pixels, the
  normalisation of CMR's ``pascal_sfm.m``); a keypoint ``X`` (a column of ``S``) projects to
  ``scale * rot[:2] @ X + trans``.
- ``S``: 3 x K mean shape in the class's canonical frame, centred on its mean and scaled so that
  its largest pairwise keypoint distance is 2 (CMR's normalisation); keypoints the mean shape
  lacks are placed at the centre.
- ``conv_tri``: F x 3 triangles of the convex hull of ``S`` (``scipy.spatial.ConvexHull``),
  **1-based** (CMR subtracts 1 when it loads them).
- ``annotation_ids``, ``image_ids``, ``sources``, ``kp_names``: which object each element is.

``--format ucmr`` writes ``<out>/<class>.json`` with one record per object: ``annotation_id``,
``image_id``, ``source``, ``bbox`` (x0, y0, x1, y1, image pixels, 0-based), ``quality`` and
``sfmpose = [s, [tx, ty], [qw, qx, qy, qz]]``: CMR's pose of the same object (``trans`` 1-based,
the quaternion of ``rot``, scalar first as CMR's ``quaternion_from_matrix`` gives it); plus the
mean shape ``S`` (K x 3) and ``faces`` (0-based).

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
from scipy.spatial import ConvexHull, distance

from ..io.coco import load_coco
from ..io.outputs import atomic_write, read_json, write_json
from .source import class_scope, data_path, recon_config, run_classes

__all__ = ["normalised_shape", "cmr_pose", "export_format", "class_records", "quaternion_wxyz"]


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
    """Triangles ``(F, 3)`` of the convex hull of ``S (K, 3)``, wound counter-clockwise seen from outside."""
    if len(S) < 4:
        return np.zeros((0, 3), dtype=np.int64)
    h = ConvexHull(S)
    f = h.simplices.copy()
    n = np.cross(S[f[:, 1]] - S[f[:, 0]], S[f[:, 2]] - S[f[:, 0]])
    inward = (n * (S[f[:, 0]] - S[h.vertices].mean(axis=0))).sum(axis=1) < 0
    f[inward] = f[inward][:, ::-1]
    return f


def _mean_shape(cams: dict, names: list) -> np.ndarray:
    """``(K, 3)`` mean shape in keypoint order; a keypoint without a row goes to the others' centre."""
    rows = [cams.get("mean_shape", {}).get(n) for n in names]
    known = np.array([r for r in rows if r is not None], dtype=np.float64)
    c = known.mean(axis=0) if len(known) else np.zeros(3)
    return np.array([r if r is not None else c for r in rows], dtype=np.float64)


def class_records(recon: Path, cname: str, coll) -> tuple[list[dict], np.ndarray, np.ndarray]:
    """Per object with a camera: ids, CMR pose, reprojection error, box and quality; the normalised mean
    shape ``(K, 3)``; its convex hull triangles ``(F, 3)`` (0-based)."""
    cams = read_json(recon / cname / "cameras.json")
    names = list(coll.meta.keypoint_names)
    S, centre, k = normalised_shape(_mean_shape(cams, names))
    hull = _outward_hull(S)
    kp_img = coll.keypoints_in_image().double().cpu().numpy()
    vis = coll.visible.cpu().numpy()
    C = coll.masks.shape[-1]
    out = []
    for i, aid in enumerate(coll.annotation_ids):
        entry = cams.get("cameras", {}).get(str(aid)) or {}
        cam = entry.get("refined")
        if cam is None:
            continue
        R, s, t = np.asarray(cam["R"]), float(cam["s"]), np.asarray(cam["t"], dtype=np.float64)
        scale, trans = cmr_pose(R, s, t, centre, k)
        proj = (scale * S @ R[:2].T) + trans
        a = float(coll.canvas_from_image.scale[i])
        b = coll.canvas_from_image.offset[i].double().cpu().numpy()
        box = np.concatenate([-b / a, (C - 1.0 - b) / a])
        box_scale = float(max(box[2] - box[0], box[3] - box[1]))  # the canvas's side in image pixels
        err = float(((proj - kp_img[i]) ** 2).sum(axis=1)[vis[i]].sum()) / (len(names) * box_scale ** 2)
        out.append({"annotation_id": aid, "image_id": coll.image_ids[i], "source": coll.sources[i], "rot": R,
                    "scale": scale, "trans": trans, "err_sfm_reproj": err, "bbox": box.tolist(),
                    "quality": entry.get("quality")})
    return out, S, hull


def _write_cmr(path: Path, recs: list, S: np.ndarray, hull: np.ndarray, names: list) -> None:
    anno = np.zeros((1, len(recs)), dtype=[("rot", object), ("scale", object), ("trans", object),
                                           ("err_sfm_reproj", object)])
    for j, r in enumerate(recs):
        anno[0, j] = (r["rot"], float(r["scale"]), r["trans"] + 1.0, float(r["err_sfm_reproj"]))
    ids = np.array([str(r["annotation_id"]) for r in recs], dtype=object)
    data = {"sfm_anno": anno, "S": S.T.copy(), "conv_tri": (hull + 1).astype(np.float64),
            "annotation_ids": ids, "image_ids": np.array([str(r["image_id"]) for r in recs], dtype=object),
            "sources": np.array([r["source"] or "" for r in recs], dtype=object),
            "kp_names": np.array(names, dtype=object)}
    atomic_write(path, lambda f: scipy.io.savemat(f, data, do_compression=True))


def _write_ucmr(path: Path, cname: str, recs: list, S: np.ndarray, hull: np.ndarray, names: list) -> None:
    items = [{"annotation_id": r["annotation_id"], "image_id": r["image_id"], "source": r["source"],
              "bbox": r["bbox"], "quality": r["quality"],
              "sfmpose": [float(r["scale"]), (r["trans"] + 1.0).tolist(), quaternion_wxyz(r["rot"]).tolist()]}
             for r in recs]
    write_json(path, {"class": cname, "keypoint_names": names, "S": S.tolist(), "faces": hull.tolist(),
                      "convention": "sfmpose = [s, [tx, ty], [qw, qx, qy, qz]]: keypoint X of S projects to "
                                    "s * R(q)[:2] @ X + t in image pixels, 1-based (CMR's); R rows = image x, "
                                    "image y (down), viewing direction",
                      "images": items})


def export_format(recon: str | Path, out: str | Path, fmt: str, classes=None) -> list[Path]:
    """Write one ``cmr`` ``.mat`` or ``ucmr`` ``.json`` file per reconstructed class of ``recon`` into
    ``out``; returns the files written."""
    recon, out = Path(recon), Path(out)
    cfg = recon_config(recon)
    covered = run_classes(cfg.classes, recon)
    loaded = load_coco(data_path(recon, cfg), canvas_size=cfg.input.canvas_size, margin=cfg.input.canvas_margin,
                       classes=classes or covered)
    scope = class_scope(loaded.dataset["categories"], covered, classes, recon)  # an unknown class: ValueError
    written = []
    for cname in (c for c in scope if c in loaded.collections and (recon / c / "cameras.json").is_file()):
        coll = loaded.collections[cname]
        recs, S, hull = class_records(recon, cname, coll)
        names = list(coll.meta.keypoint_names)
        path = out / f"{cname}.{'mat' if fmt == 'cmr' else 'json'}"
        if fmt == "cmr":
            _write_cmr(path, recs, S, hull, names)
        else:
            _write_ucmr(path, cname, recs, S, hull, names)
        written.append(path)
    return written
