"""Real PASCAL VOC aeroplanes end to end: viewpoints vs PASCAL3D+, shapes vs the closest CAD model.

One command reproduces every number of ``docs/voc.md``::

    python tools/voc_study.py [--data ../shared/data] [--work outputs/voc] [--out WORK/voc_study.json]
                              [--figure WORK/voc_aeroplanes.png] [--seed 0] [--device cpu]
                              [--set KEY=VALUE ...] [--skip-reconstruct] [--no-shapes] [--no-diagnose]
    python tools/voc_study.py --cameras-only [--set KEY=VALUE ...]   # steps 1-3 alone, about 20 s

The record and the figure go under ``WORK`` unless ``--out`` and ``--figure`` name other files, so that a
plain run leaves the committed ones alone; docs/voc.md's command names ``docs/data/voc_study.json`` and
``docs/figures/voc_aeroplanes.png``.

Steps (each prints a table; everything lands in ``--out`` as JSON with the command line, the
per-object errors in ``WORK/per_object.json``):

1. **convert** every Berkeley keypoint file of ``DATA/pascal_voc_aeroplane/keypoints`` with
   :func:`carvi_torch.io.voc.convert` (the code of ``python -m carvi_torch.datasets voc``);
   skipped files are listed with their reasons.
2. **reconstruct** all converted objects with the command-line pipeline
   (``python -m carvi_torch.reconstruct --data WORK/annotations.json --out WORK/recon``,
   extra ``--set key=value`` overrides passed on); objects the pipeline skips are listed.
3. **viewpoints**: the SfM and the refined cameras of ``cameras.json`` against the
   PASCAL3D+ rotations of ``viewpoints_dev.json`` (``R``, our camera convention), after one
   global rotation aligning the SfM frame with the CAD frame
   (:func:`carvi_torch.evaluation.viewpoint_metrics.viewpoint_report`): median geodesic error,
   accuracy at 30 degrees, median azimuth / elevation errors; errors by ground-truth
   azimuth; the gross errors (> 30 degrees) by name. Beside them, the labels as written (the
   class's canonical frame, no fitted rotation) against ``ABSOLUTE_TARGETS``; then what keypoints allow
   (:func:`step_cad_floor`): the annotator's own CAD model and the pipeline's mean shape, each fitted to every
   object's keypoints from its ground-truth rotation, over all objects and per CAD model.
4. **unseen images**: a random third of the objects (``--seed``) is held aside; rigid SfM
   (with mirrors, the pipeline's settings) and refinement run on the rest; the held-aside
   cameras come from :func:`carvi_torch.viewpoints.camera_fit.estimate_camera` with the mean shape learned
   from the rest, once from keypoints alone (``silhouette_weight = 0``) and once with the
   silhouette term. The alignment ``G`` is fitted on the *training* objects with ground
   truth and applied unchanged (also reported: ``G`` fitted on the held-aside objects).
5. **shapes**: for every object with ground truth, the PASCAL3D+ CAD model named by its
   ``subtype`` is posed with the ground-truth rotation; its scale and image translation are
   fitted to the object's mask (area and centroid of the rendered CAD silhouette equal
   those of the mask; see :func:`fit_cad_to_mask`). The reconstruction is compared with it
   in the CAD frame: symmetric RMS error in percent of the CAD's bounding-box diagonal
   after the best depth shift along the viewing direction
   (:func:`carvi_torch.evaluation.metrics.evaluate_reconstruction`), and voxel IoU at the
   reconstruction's own voxel size after that shift (:func:`solid_iou`). The same for the
   Puffball and SfM-convex-hull baselines and, as a yardstick of how much aeroplanes differ,
   for the *other* seven CAD models posed the same way. The CAD model is only the closest
   of eight models, not the exact aeroplane of the photo.
6. **figure** ``--figure``: a dozen objects spread over the azimuths, each with its polygon
   mask, the projected reconstruction's silhouette, the annotated keypoints and the mean
   shape's keypoints seen by the refined camera, and two views of the mesh.

``--cameras-only``: the viewpoint check alone: convert, reconstruct with ``stage=cameras``
(into ``WORK/cameras``, settings of ``--set`` applied), the viewpoint tables of step 3; its
JSON (default ``WORK/cameras_only.json``) holds their summary. E.g. ``--cameras-only --set
silhouette_robust=0`` for the paper's squared silhouette penalty. ``--compare-set KEY=VALUE ...`` makes
a second set of cameras with those overrides (``WORK/cameras_compare``) and compares the two object by
object (:func:`paired_comparison`): at 165 objects a median moves by tenths of a degree with the sample,
so a difference of medians alone says little.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from carvi_torch.cameras import (
    ScaledOrthographic,
    azimuth_elevation_roll_from_rotation,
    rotation_from_azimuth_elevation_roll,
)
from carvi_torch.config import Config, read_run_config
from carvi_torch.evaluation import metrics
from carvi_torch.evaluation.viewpoint_metrics import (
    align_rotations,
    angle_errors,
    geodesic_errors,
    median_change,
    summarize,
    viewpoint_report,
)
from carvi_torch.io import coco, voc
from carvi_torch.io.layout import object_mesh
from carvi_torch.io.outputs import read_json, write_json
from carvi_torch.sdf import distance_to_mask
from carvi_torch.synthetic.render import rasterize_triangles
from carvi_torch.viewpoints import camera_fit, class_sfm, sfm
from carvi_torch.viewpoints.refine import refine_with_shape

ROOT = Path(__file__).resolve().parents[1]

CLASS = "aeroplane"

#: Berkeley keypoint name -> PASCAL3D+ CAD keypoint name. Berkeley ``L_`` is the pilot's left,
#: PASCAL3D+ ``left_`` the left of a viewer facing the nose: ``L_WingTip`` is ``right_wing``.
#: ``Bot_Rudder`` (the rear end of the fuselage under the fin) is the CAD ``tail``,
#: ``Bot_Rudder_Front`` (where the fin's leading edge meets the fuselage) is ``rudder_lower``.
BERKELEY_TO_PASCAL3D = {
    "L_WingTip": "right_wing", "R_WingTip": "left_wing",
    "L_Stabilizer": "right_elevator", "R_Stabilizer": "left_elevator",
    "NoseTip": "noselanding", "Top_Rudder": "rudder_upper",
    "Bot_Rudder": "tail", "Bot_Rudder_Front": "rudder_lower",
}

#: Targets of the task on the objects with ground truth (degrees, after refinement).
TARGETS = {"azimuth": 10.0, "elevation": 7.0, "geodesic": 15.0}
#: The written labels (canonical frame, no fitted rotation) on the 165 dev objects.
ABSOLUTE_TARGETS = {"geodesic": 12.0, "azimuth": 10.0, "elevation": 5.0}


# =========================================================================== small helpers


def gt_key(source: str) -> str:
    """``"2008_000033_1.xml"`` -> ``"2008_000033_1"`` (the key of ``viewpoints_dev.json``)."""
    return source[:-4] if source.endswith(".xml") else source


def _f(v, digits: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{digits}f}"


def print_table(title: str, header: list[str], rows: list[list]) -> None:
    """Plain fixed-width table on stdout."""
    cells = [[str(c) for c in header]] + [[c if isinstance(c, str) else _f(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    print(f"\n{title}")
    for j, r in enumerate(cells):
        print("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths))))
        if j == 0:
            print("  ".join("-" * w for w in widths))


def _summary_row(name: str, rep: dict) -> list:
    return [name, str(rep["n"]), rep["geodesic"]["median"], rep["geodesic"]["acc_at_30"],
            rep["azimuth"]["median"], rep["elevation"]["median"], "yes" if rep["mirrored"] else "no"]


VP_HEADER = ["cameras", "n", "geodesic med", "acc@30", "azimuth med", "elevation med", "mirrored"]


def _compact(rep: dict) -> dict:
    """A viewpoint report without its per-instance list."""
    return {k: v for k, v in rep.items() if k != "per_instance_geodesic"}


# =========================================================================== CAD models


def load_cad(path: str | Path) -> dict:
    """A PASCAL3D+ CAD model: ``vertices (V, 3) float64``, ``faces (F, 3) int64``, ``keypoints`` name -> (3,).

    Object frame: +z up, nose towards -y (the data README).
    """
    z = np.load(path)
    return {"name": Path(path).stem, "vertices": z["vertices"].astype(np.float64),
            "faces": z["faces"].astype(np.int64),
            "keypoints": {str(n): np.asarray(p, dtype=np.float64) for n, p in zip(z["keypoint_names"], z["keypoints"])}}


def pose_points(X: np.ndarray, R: np.ndarray, s: float, t: np.ndarray) -> np.ndarray:
    """Object-frame points ``X (P, 3)`` -> reference camera frame ``(u, v, depth)`` (image pixels)."""
    Y = s * X @ R.T
    Y[:, :2] += t
    return Y


def unpose_points(Y: np.ndarray, R: np.ndarray, s: float, t: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pose_points`: camera-frame points ``(P, 3)`` -> object frame."""
    Z = Y.astype(np.float64).copy()
    Z[:, :2] -= t
    return (Z / s) @ R


def fit_keypoints(P: np.ndarray, W: np.ndarray) -> tuple[float, np.ndarray, float]:
    """Scale ``s`` and translation ``t`` minimising ``sum ||s P_k + t - W_k||^2`` (rotation fixed).

    Args:
        P: ``(M, 2)`` projected model keypoints (``R[:2] X``); W: ``(M, 2)`` image keypoints; ``M >= 2``.

    Returns:
        ``s``, ``t (2,)`` and the RMS residual (pixels).
    """
    if len(P) < 2:
        raise ValueError(f"fit_keypoints needs 2 or more keypoints, got {len(P)}")
    pc, wc = P.mean(0), W.mean(0)
    den = float(((P - pc) ** 2).sum())
    s = float(((P - pc) * (W - wc)).sum()) / den if den > 0 else float("nan")
    t = wc - s * pc
    rms = float(np.sqrt(((s * P + t - W) ** 2).sum(-1).mean()))
    return s, t, rms


def silhouette(points2d: np.ndarray, faces: np.ndarray, origin: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Exact silhouette ``(H, W)`` bool of triangles, pixel ``[i, j]`` centred at ``origin + (j, i)``."""
    p = torch.from_numpy(points2d - origin)
    return rasterize_triangles(p, torch.from_numpy(faces), shape[0], shape[1]).numpy()


def mask_moments(mask: np.ndarray, origin=(0.0, 0.0)) -> tuple[float, np.ndarray]:
    """Area (pixels) and centroid ``(x, y)`` of a mask whose pixel ``[i, j]`` is at ``origin + (j, i)``."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return 0.0, np.full(2, np.nan)
    return float(len(xs)), np.array([xs.mean(), ys.mean()]) + np.asarray(origin, dtype=np.float64)


def fit_cad_to_mask(vertices: np.ndarray, faces: np.ndarray, R: np.ndarray, mask: np.ndarray,
                    render_size: int = 256) -> tuple[float, np.ndarray]:
    """Scale and image translation of a CAD model posed with rotation ``R`` so it covers the mask.

    The posed model's silhouette gets the mask's area and centroid. The silhouette of the
    model seen by ``R`` is rendered once (exactly, :func:`silhouette`) at scale ``s_0`` making
    its larger side ``render_size`` pixels; its area ``A_0`` and centroid ``c_0`` scale with the
    camera, so ``s = s_0 sqrt(A_mask / A_0)`` and ``t = c_mask - (s / s_0) c_0`` (``c_0``
    relative to the projected origin). Thin parts (wings seen edge-on) make ``A`` depend a
    little on the pixel size; at 256 pixels that changes ``s`` by well under 1%.

    Args:
        vertices: ``(V, 3)`` object frame; faces ``(F, 3)``; R: ``(3, 3)`` ground-truth rotation.
        mask: ``(H, W)`` bool image mask (pixel ``[i, j]`` at ``(x=j, y=i)``).

    Returns:
        ``s`` and ``t (2,)``: the model's image points are ``s R[:2] X + t``.
    """
    area_m, c_m = mask_moments(mask)
    if area_m == 0:
        raise ValueError("fit_cad_to_mask: empty mask")
    P = vertices @ R[:2].T
    lo = P.min(0)
    s0 = (render_size - 3) / float(np.ptp(P, axis=0).max())
    q = s0 * (P - lo) + 1.0
    shape = (int(np.ceil(q[:, 1].max())) + 2, int(np.ceil(q[:, 0].max())) + 2)
    area, c = mask_moments(silhouette(q, faces, np.zeros(2), shape))
    if area == 0:
        raise ValueError("fit_cad_to_mask: the posed model covers no pixel centre")
    c0 = (c - 1.0) / s0 + lo  # silhouette centroid at unit scale, relative to the projected origin
    s = math.sqrt(area_m / area) * s0
    return s, c_m - s * c0


def silhouette_iou(vertices, faces, R, s, t, mask) -> float:
    """IoU of the posed model's silhouette with ``mask (H, W)`` (both on one pixel grid)."""
    q = s * vertices @ R[:2].T + t
    lo = np.minimum(np.floor(q.min(0)) - 1, 0)
    hi = np.maximum(np.ceil(q.max(0)) + 1, [mask.shape[1] - 1, mask.shape[0] - 1])
    shape = (int(hi[1] - lo[1]) + 1, int(hi[0] - lo[0]) + 1)
    sil = silhouette(q, faces, lo, shape)
    big = np.zeros(shape, dtype=bool)
    oy, ox = int(-lo[1]), int(-lo[0])
    big[oy:oy + mask.shape[0], ox:ox + mask.shape[1]] = mask
    union = (sil | big).sum()
    return float((sil & big).sum() / union) if union else float("nan")


class VisualHull:
    """The visual hull of a mesh from ``views`` directions: a solid for meshes that are not watertight.

    PASCAL3D+ meshes have holes, so a flood fill of their surface voxels leaks (two of the
    eight aeroplanes). The hull is the set of points whose projection falls inside the
    mesh's silhouette in every one of ``views`` orthographic views spread over the sphere
    (:func:`carvi_torch.viewpoints.camera_fit.sphere_rotations`); it contains the solid and exceeds it only
    in concavities no view sees into (for aeroplanes: small wedges at the wing roots).

    Args:
        vertices: ``(V, 3)``; faces: ``(F, 3)``.
        views: number of directions; resolution: silhouette pixels across the bounding sphere.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, views: int = 32, resolution: int = 192):
        self.centre = (vertices.max(0) + vertices.min(0)) / 2
        self.radius = float(np.linalg.norm(vertices - self.centre, axis=1).max()) * 1.02
        self.pixel = 2 * self.radius / resolution
        self.resolution = resolution
        self.R = camera_fit.sphere_rotations(views, dtype=torch.float64).numpy()  # (B, 3, 3)
        X = vertices - self.centre
        sil = []
        for Rv in self.R:
            q = (X @ Rv[:2].T + self.radius) / self.pixel - 0.5  # pixel [i, j] covers [j, j+1) * pixel - radius
            sil.append(silhouette(q, faces, np.zeros(2), (resolution, resolution)))
        self.silhouettes = torch.from_numpy(np.stack(sil))  # (B, r, r)

    def contains(self, X: np.ndarray) -> np.ndarray:
        """``(P,)`` bool: points ``X (P, 3)`` (object frame) inside the hull."""
        Xc = torch.from_numpy(X - self.centre)
        R = torch.from_numpy(self.R)
        q = torch.einsum("bij,pj->bpi", R[:, :2], Xc)
        idx = torch.floor((q + self.radius) / self.pixel).long()  # (B, P, 2)
        ok = ((idx >= 0) & (idx < self.resolution)).all(-1)
        idx = idx.clamp(0, self.resolution - 1)
        b = torch.arange(len(R))[:, None].expand_as(idx[..., 0])
        inside = self.silhouettes[b, idx[..., 1], idx[..., 0]] & ok
        return inside.all(0).numpy()


@dataclass
class Solid:
    """A voxelised solid on the global lattice of side ``pitch`` (voxel centres at ``pitch * integers``).

    Attributes:
        occupancy: ``(D, H, W)`` bool, index ``(d, h, w)`` = ``(z, y, x)``.
        first: ``(3,)`` int64, the global ``(x, y, z)`` lattice index of voxel ``(0, 0, 0)``.
        pitch: voxel side.
    """

    occupancy: np.ndarray
    first: np.ndarray
    pitch: float

    def centres(self) -> np.ndarray:
        """``(D*H*W, 3)`` voxel centres ``(x, y, z)`` in ``occupancy``'s flattened order."""
        d, h, w = np.meshgrid(*(np.arange(k) for k in self.occupancy.shape), indexing="ij")
        return self.pitch * (self.first + np.stack([w.ravel(), h.ravel(), d.ravel()], 1))


def _lattice_box(lo: np.ndarray, hi: np.ndarray, pitch: float, margin: int = 2) -> tuple[np.ndarray, tuple]:
    """First global index ``(x, y, z)`` and ``(D, H, W)`` of the lattice block covering ``[lo, hi]``."""
    first = np.floor(lo / pitch).astype(np.int64) - margin
    last = np.ceil(hi / pitch).astype(np.int64) + margin
    n = last - first + 1
    return first, (int(n[2]), int(n[1]), int(n[0]))


def mesh_solid(vertices: np.ndarray, faces: np.ndarray, pitch: float, fill: bool = True,
               hull: VisualHull | None = None) -> Solid:
    """Solid voxelisation of a mesh on the global lattice.

    Surface voxels by :func:`carvi_torch.evaluation.metrics.voxelize_solid` (cavities filled when ``fill``:
    right for closed meshes such as the reconstructions); with ``hull``, united with the
    visual hull at the voxel centres (for CAD meshes with holes, ``fill=False``).
    """
    first, shape = _lattice_box(vertices.min(0), vertices.max(0), pitch)
    occ = metrics.voxelize_solid(torch.from_numpy(vertices), torch.from_numpy(np.asarray(faces, dtype=np.int64)),
                                 pitch, torch.from_numpy(first * pitch), shape, fill=fill).numpy()
    sol = Solid(occ, first, pitch)
    if hull is not None:
        sol.occupancy = occ | hull.contains(sol.centres()).reshape(shape)
    return sol


def similar_solid(src: Solid, scale: float, shift: np.ndarray, pitch: float) -> Solid:
    """``src`` mapped by ``X -> scale X + shift`` onto the lattice of side ``pitch`` (nearest voxel lookup)."""
    lo = scale * src.pitch * src.first + shift
    hi = scale * src.pitch * (src.first + np.array(src.occupancy.shape[::-1]) - 1) + shift
    first, shape = _lattice_box(lo, hi, pitch)
    out = Solid(np.zeros(shape, dtype=bool), first, pitch)
    X = (out.centres() - shift) / scale
    idx = np.rint(X / src.pitch).astype(np.int64) - src.first  # (P, 3) (x, y, z) into src
    ok = np.all((idx >= 0) & (idx < np.array(src.occupancy.shape[::-1])), axis=1)
    flat = np.zeros(len(X), dtype=bool)
    flat[ok] = src.occupancy[idx[ok, 2], idx[ok, 1], idx[ok, 0]]
    out.occupancy = flat.reshape(shape)
    return out


def solid_iou(a: Solid, b: Solid) -> float:
    """Intersection over union of two solids on the same lattice (``a.pitch == b.pitch``)."""
    if not math.isclose(a.pitch, b.pitch, rel_tol=1e-9):
        raise ValueError(f"solid_iou: lattices differ (pitch {a.pitch} vs {b.pitch})")
    na, nb = int(a.occupancy.sum()), int(b.occupancy.sum())
    lo = np.maximum(a.first, b.first)
    hi = np.minimum(a.first + np.array(a.occupancy.shape[::-1]), b.first + np.array(b.occupancy.shape[::-1]))
    inter = 0
    if np.all(hi > lo):
        sa = tuple(slice(int(l - f), int(h - f)) for l, h, f in zip(lo[::-1], hi[::-1], a.first[::-1]))
        sb = tuple(slice(int(l - f), int(h - f)) for l, h, f in zip(lo[::-1], hi[::-1], b.first[::-1]))
        inter = int((a.occupancy[sa] & b.occupancy[sb]).sum())
    union = na + nb - inter
    return inter / union if union else float("nan")


# =========================================================================== steps


def step_convert(data: Path, work: Path) -> dict:
    """Convert every keypoint file; returns counts and the skipped files with reasons."""
    ann = work / "annotations.json"
    rep = voc.convert(data / "pascal_voc_aeroplane" / "keypoints", ann)
    out = {"annotations": str(ann), "files": rep.num_files, "converted": rep.converted, "images": rep.num_images,
           "mask_sources": rep.mask_sources, "skipped": [{"file": f, "reason": r} for f, r in rep.skipped],
           "warnings": rep.warnings}
    print_table("conversion (python -m carvi_torch.datasets voc)", ["files", "converted", "images", "skipped"],
                [[str(rep.num_files), str(rep.converted), str(rep.num_images), str(len(rep.skipped))]])
    for s in out["skipped"]:
        print(f"  skipped {s['file']}: {s['reason']}")
    return out


def step_reconstruct(ann: Path, recon: Path, overrides: list[str], device: str) -> dict:
    """Run ``python -m carvi_torch.reconstruct`` (the study passes ``overwrite=true``: its record's stage times are
    a whole run's, never those of a resumed one; ``--skip-reconstruct`` reuses an existing run instead)."""
    cmd = [sys.executable, "-m", "carvi_torch.reconstruct", "--data", str(ann), "--out", str(recon),
           "progress=false", f"device={device}", *overrides]
    print("\n$ " + " ".join(shlex.quote(c) for c in cmd), flush=True)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=str(ROOT))
    wall = time.perf_counter() - t0
    summ = read_json(recon / "summary.json")
    c = summ["classes"][CLASS]
    out = {"command": cmd[1:], "wall_seconds_this_call": round(wall, 1), "objects": c["objects"],
           "reconstructed": c["reconstructed"], "resumed": c.get("resumed", 0), "failures": c["failures"],
           "warnings": c["warnings"], "seconds": c["seconds"], "total_seconds": summ.get("total_seconds"),
           "peak_rss_mb": summ.get("peak_rss_mb"), "sfm": c.get("sfm", {}).get("reflection"),
           "clusters": c.get("clusters")}
    meshes = len(list((recon / CLASS / "meshes").glob(f"*.{run_mesh_format(recon)}")))
    out["meshes"] = meshes
    print_table("reconstruction (python -m carvi_torch.reconstruct)",
                ["objects", "meshes", "skipped", "seconds (this run)"],
                [[str(c["objects"]), str(meshes), str(len(c["failures"])), _f(summ.get("total_seconds"), 1)]])
    for fl in c["failures"]:
        print(f"  skipped {fl.get('source')} (annotation {fl.get('annotation_id')}) at {fl['stage']}: {fl['reason']}")
    return out


def _gt_arrays(cams: dict, gt: dict, stage: str):
    keys, aids, R, Rg = [], [], [], []
    for aid, c in cams.items():
        k = gt_key(c["source"])
        if k in gt and c.get(stage):
            keys.append(k)
            aids.append(int(aid))
            R.append(c[stage]["R"])
            Rg.append(gt[k]["R"])
    return keys, aids, torch.tensor(R, dtype=torch.float64), torch.tensor(Rg, dtype=torch.float64)


def _refinement_change(cams: dict, gt: dict) -> dict:
    """:func:`~carvi_torch.evaluation.viewpoint_metrics.median_change` from the SfM to the refined cameras of the
    objects with both (each VOC annotation its own physical object)."""
    keys, _aids, R_sfm, Rg = _gt_arrays(cams, gt, "sfm")
    ref_keys, _a, R_ref, _g = _gt_arrays(cams, gt, "refined")
    at = {k: i for i, k in enumerate(ref_keys)}
    both = [i for i, k in enumerate(keys) if k in at]
    R_ref = R_ref[[at[keys[i]] for i in both]]
    return {k: round(v, 3) if isinstance(v, float) else v
            for k, v in median_change(R_sfm[both], R_ref, Rg[both], [keys[i] for i in both]).items()}


def azimuth_bins(R_est: torch.Tensor, R_gt: torch.Tensor, G: torch.Tensor, width: float = 30.0) -> list[dict]:
    """Errors per ground-truth azimuth bin: count, median |azimuth error|, signed median, median geodesic.

    The signed azimuth error (estimate minus truth) is wrapped to ``[-180, 180)``; azimuths follow
    PASCAL3D+ (``cameras.azimuth_elevation_roll_from_rotation``: 0 = seen from the front, 180 = from
    behind, 90 and 270 = from the sides).
    """
    signed = signed_azimuth_errors(R_est, R_gt, G)
    a_gt, _, _ = azimuth_elevation_roll_from_rotation(R_gt)
    geo = geodesic_errors(R_est, R_gt, G)
    az = torch.rad2deg(torch.remainder(a_gt, 2 * math.pi))
    out = []
    for lo in np.arange(0.0, 360.0, width):
        m = (az >= lo) & (az < lo + width)
        if not bool(m.any()):
            continue
        out.append({"azimuth_from": float(lo), "azimuth_to": float(lo + width), "n": int(m.sum()),
                    "median_abs_azimuth_error": float(np.median(signed[m].abs().numpy())),
                    "median_signed_azimuth_error": float(np.median(signed[m].numpy())),
                    "median_geodesic": float(np.median(geo[m].numpy()))})
    return out


def signed_azimuth_errors(R_est: torch.Tensor, R_gt: torch.Tensor, G: torch.Tensor) -> torch.Tensor:
    """``(N,)`` azimuth of ``R_est G`` minus that of ``R_gt`` (degrees, wrapped to ``[-180, 180)``)."""
    a_est, _, _ = azimuth_elevation_roll_from_rotation(R_est @ G)
    a_gt, _, _ = azimuth_elevation_roll_from_rotation(R_gt)
    return torch.rad2deg(torch.remainder(a_est - a_gt + math.pi, 2 * math.pi) - math.pi)


def toward_front(signed: np.ndarray, gt_azimuth: np.ndarray) -> np.ndarray:
    """Signed azimuth errors re-signed so that > 0 means the estimate is turned towards the front (azimuth 0).

    For a ground-truth azimuth in ``(0, 180)`` a smaller azimuth is nearer the front, in ``(180, 360)``
    a larger one.
    """
    return np.where(np.asarray(gt_azimuth) % 360.0 < 180.0, -np.asarray(signed), np.asarray(signed))


def side_view_bias(per: dict, subcategory: dict, gross: float = 45.0) -> dict:
    """Median toward-front azimuth error of side views (azimuth 60-120 or 240-300), per subcategory.

    Gross errors (``|azimuth error| >= gross``) are left out. ``per``: per-object dicts with
    ``signed_azimuth_error`` and ``gt_azimuth``; ``subcategory``: key -> Berkeley subcategory.
    """
    groups: dict[str, list[float]] = {}
    for k, v in per.items():
        az = v["gt_azimuth"] % 360.0
        if not (60.0 <= az < 120.0 or 240.0 <= az < 300.0) or abs(v["signed_azimuth_error"]) >= gross:
            continue
        e = float(toward_front(np.array([v["signed_azimuth_error"]]), np.array([az]))[0])
        for g in ("all", subcategory.get(k) or "unknown"):
            groups.setdefault(g, []).append(e)
    return {g: {"n": len(v), "median_toward_front": float(np.median(v)), "mean_toward_front": float(np.mean(v))}
            for g, v in sorted(groups.items())}


def paired_comparison(a: np.ndarray, b: np.ndarray, resamples: int = 4000, seed: int = 0) -> dict:
    """Two sets of errors of the same objects, ``a (n,)`` and ``b (n,)``, compared object by object.

    Returns ``{"median_a", "median_b", "difference"}`` (``median(a) - median(b)``), ``"interval_95"``: the
    2.5 and 97.5 percentiles of that difference over ``resamples`` bootstrap draws of the objects (the
    same draw for both, so each object's pair stays together), ``"a_lower"`` / ``"b_lower"``: the objects
    each puts closer (ties in neither), and ``"sign_test_p"``: the two-sided binomial sign test of those
    counts (``scipy.stats.binomtest``; 1.0 without a difference). Same seed, same interval.

    Example:
        >>> r = paired_comparison(np.array([1.0, 2.0, 3.0]), np.array([2.0, 3.0, 4.0]))
        >>> r["difference"], r["interval_95"], r["a_lower"], r["b_lower"]
        (-1.0, [-1.0, -1.0], 3, 0)
    """
    from scipy.stats import binomtest

    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    if a.shape != b.shape or a.ndim != 1 or not len(a):
        raise ValueError(f"paired_comparison needs two equal, non-empty 1-D arrays, got {a.shape} and {b.shape}")
    draws = np.random.default_rng(seed).integers(0, len(a), (resamples, len(a)))
    boot = np.median(a[draws], axis=1) - np.median(b[draws], axis=1)
    a_lower, b_lower = int((a < b).sum()), int((b < a).sum())
    p = binomtest(a_lower, a_lower + b_lower).pvalue if a_lower + b_lower else 1.0
    return {"median_a": float(np.median(a)), "median_b": float(np.median(b)),
            "difference": float(np.median(a) - np.median(b)),
            "interval_95": [float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))],
            "a_lower": a_lower, "b_lower": b_lower, "sign_test_p": float(p)}


def _aligned_errors(R: torch.Tensor, Rg: torch.Tensor) -> tuple[dict, torch.Tensor, torch.Tensor, dict]:
    """``(report, G, geodesic (n,), angle errors)`` of rotations ``R`` against ``Rg`` after the least-squares
    rotation ``G`` of :func:`viewpoint_report`."""
    rep = viewpoint_report(R, Rg)
    G = torch.tensor(rep["alignment"], dtype=torch.float64)
    return rep, G, geodesic_errors(R, Rg, G), angle_errors(R, Rg, G)


def step_compare(recon_a: Path, recon_b: Path, gt: dict, names: tuple[str, str]) -> dict:
    """The refined cameras of two reconstructions of the same objects, object by object (each after its own
    least-squares ``G``): per angle :func:`paired_comparison`, printed and returned."""
    per = []
    for recon in (recon_a, recon_b):
        keys, _aids, R, Rg = _gt_arrays(read_json(recon / CLASS / "cameras.json")["cameras"], gt, "refined")
        _rep, _G, geo, ang = _aligned_errors(R, Rg)
        per.append(dict(zip(keys, zip(geo.tolist(), ang["azimuth"].tolist(), ang["elevation"].tolist()))))
    both = sorted(set(per[0]) & set(per[1]))
    out = {"a": names[0], "b": names[1], "n": len(both)}
    for i, angle in enumerate(("geodesic", "azimuth", "elevation")):
        out[angle] = paired_comparison(np.array([per[0][k][i] for k in both]), np.array([per[1][k][i] for k in both]))
    rows = [[angle, r["median_a"], r["median_b"], f"{r['difference']:+.2f}",
             "[{:+.2f}, {:+.2f}]".format(*r["interval_95"]), str(r["a_lower"]), str(r["b_lower"]),
             f"{r['sign_test_p']:.2g}"] for angle, r in ((k, out[k]) for k in ("geodesic", "azimuth", "elevation"))]
    print_table(f"object by object, refined, least-squares G ({len(both)} objects; a = {names[0]}, b = {names[1]})",
                ["angle", "median a", "median b", "a - b", "95% (paired bootstrap)", "a closer", "b closer",
                 "sign test p"], rows)
    return out


def _pose_from(X: np.ndarray, W: np.ndarray, R0: np.ndarray, project, start, name: str):
    """The least-squares camera reached from ``R0``: a small rotation ``exp([w]x) R0`` and parameters ``q`` with
    ``project(X R^T, q) ~ W``, by scipy's ``least_squares`` from ``w = 0`` and ``q = start(s, t)`` (the scale
    and offset of :func:`fit_keypoints` at ``R0``). Returns ``R``, ``q`` and the RMS residual (pixels)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    if len(X) < 3:
        raise ValueError(f"{name} needs 3 or more points, got {len(X)}")
    s0, t0, _ = fit_keypoints(X @ R0[:2].T, W)

    def residual(p: np.ndarray) -> np.ndarray:
        return (project(X @ (Rotation.from_rotvec(p[:3]).as_matrix() @ R0).T, p[3:]) - W).ravel()

    sol = least_squares(residual, np.r_[0.0, 0.0, 0.0, start(s0, t0)])
    R = Rotation.from_rotvec(sol.x[:3]).as_matrix() @ R0
    return R, sol.x[3:].copy(), float(np.sqrt((sol.fun ** 2).reshape(-1, 2).sum(-1).mean()))


def fit_orthographic_pose(X: np.ndarray, W: np.ndarray, R0: np.ndarray) -> tuple[np.ndarray, float, np.ndarray, float]:
    """The scaled orthographic camera that best fits 3-D points to image points, reached from ``R0``.

    Minimises ``sum_k ||s R[:2] X_k + t - W_k||^2`` over ``R``, ``s`` and ``t`` by scipy's ``least_squares``
    from ``R0`` (a small rotation ``exp([w]x) R0``, the scale and offset of :func:`fit_keypoints` at ``R0``).

    Args:
        X: ``(M, 3)`` model points; W: ``(M, 2)`` image points, ``M >= 3``; R0: ``(3, 3)`` start.

    Returns:
        ``R (3, 3)``, ``s``, ``t (2,)`` and the RMS residual (pixels).
    """
    R, q, rms = _pose_from(X, W, R0, lambda Y, q: q[0] * Y[:, :2] + q[1:], lambda s, t: np.r_[s, t],
                           "fit_orthographic_pose")
    return R, float(q[0]), q[1:], rms


#: PASCAL3D+'s focal length in pixels (its tools' ``focal`` 1 times ``viewport`` 3000).
PASCAL3D_FOCAL = 3000.0


def fit_perspective_pose(X: np.ndarray, W: np.ndarray, R0: np.ndarray, focal: float = PASCAL3D_FOCAL
                         ) -> tuple[np.ndarray, float, np.ndarray, float]:
    """PASCAL3D+'s perspective camera that best fits 3-D points to image points, reached from ``R0``.

    As PASCAL3D+ poses its CAD models: the object's origin on the optical axis at distance ``d``, the image
    shifted by a principal point ``p``: ``uv = focal * Y[:2] / Y[2] + p`` with ``Y = R X + (0, 0, d)``.
    scipy's ``least_squares`` over ``R`` (a small rotation of ``R0``), ``d`` and ``p``, from ``R0``, the
    distance ``focal / s`` and ``p = t`` of :func:`fit_keypoints` at ``R0``.

    Args:
        X: ``(M, 3)`` model points; W: ``(M, 2)`` image points, ``M >= 3``; R0: ``(3, 3)`` start;
        focal: focal length in pixels.

    Returns:
        ``R (3, 3)``, ``d``, ``p (2,)`` and the RMS residual (pixels).
    """
    R, q, rms = _pose_from(X, W, R0, lambda Y, q: focal * Y[:, :2] / (Y[:, 2:] + q[0]) + q[1:],
                           lambda s, t: np.r_[focal / s, t], "fit_perspective_pose")
    return R, float(q[0]), q[1:], rms


def signed_elevation_errors(R_est: torch.Tensor, R_gt: torch.Tensor) -> np.ndarray:
    """``(N,)`` elevation of ``R_est`` minus that of ``R_gt`` (degrees; > 0: the estimate looks from higher)."""
    _, e_est, _ = azimuth_elevation_roll_from_rotation(R_est)
    _, e_gt, _ = azimuth_elevation_roll_from_rotation(R_gt.to(R_est))
    return torch.rad2deg(e_est - e_gt).numpy()


#: Fewest keypoint pairs for :func:`step_cad_floor`'s fits: 4 give 8 equations for the 6 unknowns of either
#: camera, so no fit is exact by construction.
CAD_FIT_MIN_POINTS = 4


def _cad_fit_rotations(ann: Path, data: Path, gt: dict, mean_shape: dict | None = None
                       ) -> tuple[list[str], list[int], dict, torch.Tensor]:
    """Keys, subtypes, rotations and ground truth of the objects whose annotator's CAD model names at least
    :data:`CAD_FIT_MIN_POINTS` of their visible keypoints. Rotations: ``{"orthographic", "perspective"}``, the
    CAD model fitted by :func:`fit_orthographic_pose` and :func:`fit_perspective_pose`, and with ``mean_shape``
    (Berkeley name -> ``(3,)``, the pipeline's in its written frame) ``"mean_shape"``: the orthographic fit of every
    visible keypoint it names. Every fit starts from the ground-truth rotation."""
    coll = read_json(ann)
    names = coll["categories"][0]["keypoints"]
    cads: dict[int, dict] = {}
    keys, subtypes, R_gt = [], [], []
    R_fit: dict[str, list] = {"orthographic": [], "perspective": []}
    if mean_shape:
        R_fit["mean_shape"] = []
    for a in coll["annotations"]:
        k = gt_key(a["source"])
        if k not in gt:
            continue
        sub = int(gt[k]["subtype"])
        if sub not in cads:
            cads[sub] = load_cad(data / "pascal3d_cad" / f"aeroplane{sub:02d}.npz")
        kp = np.asarray(a["keypoints"], dtype=np.float64).reshape(-1, 3)
        seen = {n: kp[i, :2] for i, n in enumerate(names) if kp[i, 2] > 0}
        X, W = _named_pairs(seen, {b: cads[sub]["keypoints"].get(p) for b, p in BERKELEY_TO_PASCAL3D.items()})
        if len(X) < CAD_FIT_MIN_POINTS:
            continue
        R0 = np.asarray(gt[k]["R"], dtype=np.float64)
        R_fit["orthographic"].append(fit_orthographic_pose(X, W, R0)[0])
        R_fit["perspective"].append(fit_perspective_pose(X, W, R0)[0])
        if mean_shape:
            R_fit["mean_shape"].append(fit_orthographic_pose(*_named_pairs(seen, mean_shape), R0)[0])
        R_gt.append(R0)
        keys.append(k)
        subtypes.append(sub)
    return keys, subtypes, {m: torch.tensor(np.array(R)) for m, R in R_fit.items()}, torch.tensor(np.array(R_gt))


def _named_pairs(seen: dict, model: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(X (M, 3), W (M, 2))``: the model points and image points of the names both give (``model``'s ``None``
    values count as absent)."""
    both = [n for n in seen if model.get(n) is not None]
    return (np.array([np.asarray(model[n], dtype=np.float64) for n in both]).reshape(-1, 3),
            np.array([seen[n] for n in both]).reshape(-1, 2))


def wing_station(shape: dict) -> float:
    """Where the wing tips sit along the fuselage: the mean over both tips of the projection of
    ``tip - NoseTip`` onto ``Bot_Rudder - NoseTip``, over that length (0 at the nose, 1 at the tail's foot).
    A swept wing's tips sit further back. ``shape``: Berkeley name -> ``(3,)``; NaN when it lacks one of the four.

    Example:
        >>> wing_station({"NoseTip": [0, -1, 0], "Bot_Rudder": [0, 1, 0], "L_WingTip": [1, 0.5, 0],
        ...               "R_WingTip": [-1, 0.5, 0]})
        0.75
    """
    if any(shape.get(n) is None for n in ("NoseTip", "Bot_Rudder", "L_WingTip", "R_WingTip")):
        return float("nan")
    nose, tail = (np.asarray(shape[n], dtype=np.float64) for n in ("NoseTip", "Bot_Rudder"))
    axis = tail - nose
    return float(np.mean([(np.asarray(shape[n], dtype=np.float64) - nose) @ axis / (axis @ axis)
                          for n in ("L_WingTip", "R_WingTip")]))


def _medians(R: torch.Tensor, R_gt: torch.Tensor, rows: np.ndarray | None = None) -> dict:
    """``{"n", "geodesic_median", "azimuth_median", "elevation_median"}`` of ``R`` against ``R_gt`` (no fitted
    rotation), over ``rows`` (a boolean mask) when given; rows whose ``R`` is not finite (no camera) left out."""
    keep = torch.isfinite(R).flatten(1).all(1)
    if rows is not None:
        keep &= torch.as_tensor(rows, dtype=torch.bool)
    R, R_gt = R[keep], R_gt[keep]
    geo, ang = geodesic_errors(R, R_gt).numpy(), angle_errors(R, R_gt)
    return {"n": len(R), "geodesic_median": float(np.median(geo)),
            "azimuth_median": float(np.median(ang["azimuth"].numpy())),
            "elevation_median": float(np.median(ang["elevation"].numpy()))}


def step_cad_floor(ann: Path, data: Path, gt: dict, vp: dict, written: dict | None = None,
                   subcategory: dict | None = None) -> dict:
    """How far the labels sit from the annotator's own CAD model, and from the pipeline's mean shape, fitted to
    each object's keypoints.

    For every object with ground truth whose PASCAL3D+ CAD model (its ``subtype``) names at least
    :data:`CAD_FIT_MIN_POINTS` of its visible keypoints, :func:`fit_orthographic_pose` and
    :func:`fit_perspective_pose` (PASCAL3D+'s own camera), each from the ground-truth rotation (the local optimum
    reached from it: a fit never crosses to a flipped view). These need no fitted ``G``: the CAD frame is the
    labels'. With ``written`` (the run's ``cameras.json``) its mean shape is fitted the same way, in the frame the
    run writes (the template's: the CAD frame to within the template's residual), beside the refined cameras as
    written: what one rigid shape lets keypoints reach from the truth, against what the pipeline reached. Then the
    refined cameras after the least-squares ``G`` fitted on all objects with ground truth (the headline
    alignment). Median errors over all objects and per subtype, the side views' azimuth bias per Berkeley
    ``subcategory`` (key -> name) of each fit (:func:`side_view_bias`) and the shapes' wing stations
    (:func:`wing_station`); printed and returned.
    """
    mean_shape = written["mean_shape"] if written else None
    keys, subtypes, R_fit, R_gt = _cad_fit_rotations(ann, data, gt, mean_shape)
    if written:
        R_fit["as_written"] = _written_rotations(written, keys)
    names = {"orthographic": "annotator_cad_fit", "perspective": "annotator_cad_perspective",
             "mean_shape": "mean_shape_fit", "as_written": "refined_as_written"}
    per = vp["refined"]["per_object"]
    sub = np.array(subtypes)
    out = {names[m]: _medians(R, R_gt) for m, R in R_fit.items()}
    out["refined"] = _refined_medians(per, keys, np.ones(len(keys), dtype=bool))
    out["by_subtype"] = {str(s): {**{names[m]: _medians(R, R_gt, sub == s) for m, R in R_fit.items()},
                                  "refined": _refined_medians(per, keys, sub == s)} for s in sorted(set(subtypes))}
    out["side_view_bias"] = {names[m]: side_view_bias(_signed_rows(keys, R, R_gt), subcategory or {})
                             for m, R in R_fit.items() if m != "perspective"}
    out["wing_station"] = _wing_stations(data, mean_shape)
    _print_floor(out)
    return out


def _written_rotations(written: dict, keys: list[str]) -> torch.Tensor:
    """``(len(keys), 3, 3)`` the refined rotations of ``cameras.json`` for ``keys`` (NaN where an object has none)."""
    by_key = {gt_key(c["source"]): c["refined"]["R"] for c in written["cameras"].values() if c.get("refined")}
    nan = [[float("nan")] * 3] * 3
    return torch.tensor([by_key.get(k, nan) for k in keys], dtype=torch.float64)


def _refined_medians(per: dict, keys: list[str], rows: np.ndarray) -> dict:
    """The medians of ``step_viewpoints``'s per-object refined errors (least-squares ``G``) over ``keys[rows]``."""
    sel = [per[k] for k, r in zip(keys, rows) if r and k in per]
    return {"n": len(sel), **{f"{a}_median": float(np.median([r[f] for r in sel])) for a, f in
                              (("geodesic", "geodesic"), ("azimuth", "azimuth_error"),
                               ("elevation", "elevation_error"))}}


def _signed_rows(keys: list[str], R: torch.Tensor, R_gt: torch.Tensor) -> dict:
    """Per key ``{"signed_azimuth_error", "gt_azimuth"}`` of ``R`` against ``R_gt`` (no fitted rotation; rows
    with a NaN rotation left out), as :func:`side_view_bias` reads them."""
    ok = torch.isfinite(R).flatten(1).all(1)
    signed = signed_azimuth_errors(R[ok], R_gt[ok], torch.eye(3, dtype=R.dtype))
    a_gt, _, _ = azimuth_elevation_roll_from_rotation(R_gt[ok])
    kept = [k for k, o in zip(keys, ok.tolist()) if o]
    return {k: {"signed_azimuth_error": float(e), "gt_azimuth": math.degrees(float(a)) % 360.0}
            for k, e, a in zip(kept, signed, a_gt)}


def _wing_stations(data: Path, mean_shape: dict | None) -> dict:
    """:func:`wing_station` of the mean shape (when given) and of every PASCAL3D+ aeroplane CAD model."""
    cads = {f.stem: load_cad(f)["keypoints"] for f in sorted((data / "pascal3d_cad").glob("aeroplane*.npz"))}
    return {**({"mean_shape": wing_station(mean_shape)} if mean_shape else {}),
            **{name: wing_station({b: kp.get(p) for b, p in BERKELEY_TO_PASCAL3D.items()})
               for name, kp in cads.items()}}


_FLOOR_ROWS = (("annotator_cad_fit", "annotator's CAD, orthographic fit"),
               ("annotator_cad_perspective", "annotator's CAD, PASCAL3D+'s camera"),
               ("mean_shape_fit", "the pipeline's mean shape, orthographic fit"),
               ("refined_as_written", "refined, as written (no G)"),
               ("refined", "refined (least-squares G)"))


def _print_floor(out: dict) -> None:
    """The tables of :func:`step_cad_floor`: all objects, azimuth / elevation medians per subtype (no fitted
    rotation), the side views' bias per subcategory, the wing stations."""
    print_table("the annotator's own CAD model and the pipeline's mean shape fitted near the truth, against the "
                "refined cameras on the same objects (median degrees)", ["cameras", "n", "geodesic", "azimuth",
                                                                         "elevation"],
                [[name, str(out[k]["n"]), out[k]["geodesic_median"], out[k]["azimuth_median"],
                  out[k]["elevation_median"]] for k, name in _FLOOR_ROWS if k in out])
    cols = [(k, name) for k, name in _FLOOR_ROWS if k in out and k not in ("annotator_cad_perspective", "refined")]
    print_table("the same by the annotator's CAD model (subtype): azimuth / elevation medians (degrees)",
                ["subtype", "n", *[name.split(",")[0] for _k, name in cols]],
                [[s, str(v["refined"]["n"]), *[f"{v[k]['azimuth_median']:.1f} / {v[k]['elevation_median']:.1f}"
                                               for k, _name in cols]] for s, v in out["by_subtype"].items()])
    bias = out["side_view_bias"]
    groups = sorted({g for b in bias.values() for g in b})
    print_table("side views (azimuth 60-120, 240-300; |azimuth error| < 45), no fitted rotation: median azimuth "
                "error towards the nose (degrees) by Berkeley subcategory", ["fit", *groups],
                [[k, *[f"{b[g]['median_toward_front']:+.1f} ({b[g]['n']})" if g in b else "-" for g in groups]]
                 for k, b in bias.items()])
    print("wing tips along the fuselage (0 nose, 1 tail): " + ", ".join(f"{k} {v:.2f}" for k, v in
                                                                         out["wing_station"].items()))


def step_viewpoints(recon: Path, gt: dict, subcategory: dict | None = None) -> dict:
    """SfM and refined cameras of the pipeline vs PASCAL3D+ (``subcategory``: key -> Berkeley subcategory)."""
    cams = read_json(recon / CLASS / "cameras.json")["cameras"]
    out, rows = {}, []
    for stage in ("sfm", "refined"):
        keys, aids, R, Rg = _gt_arrays(cams, gt, stage)
        rep, G, geo, ang = _aligned_errors(R, Rg)
        rob = viewpoint_report(R, Rg, robust=True)
        signed, signed_el = signed_azimuth_errors(R, Rg, G), signed_elevation_errors(R @ G, Rg)
        a_gt, e_gt, _ = azimuth_elevation_roll_from_rotation(Rg)
        per = {k: {"annotation_id": a, "geodesic": float(g), "azimuth_error": float(az), "elevation_error": float(el),
                   "signed_azimuth_error": float(sa), "signed_elevation_error": float(se),
                   "gt_azimuth": math.degrees(float(ag)) % 360.0, "gt_elevation": math.degrees(float(eg))}
               for k, a, g, az, el, sa, se, ag, eg in zip(keys, aids, geo, ang["azimuth"], ang["elevation"], signed,
                                                         signed_el, a_gt, e_gt)}
        gross = sorted(((k, v) for k, v in per.items() if v["geodesic"] > 30.0), key=lambda kv: -kv[1]["geodesic"])
        out[stage] = {"report": _compact(rep), "robust_alignment": _compact(rob), "by_azimuth": azimuth_bins(R, Rg, G),
                      "side_view_bias": side_view_bias(per, subcategory or {}),
                      "per_object": per, "gross_errors": [k for k, _ in gross]}
        rows.append(_summary_row("SfM" if stage == "sfm" else "refined", rep))
        rows.append(_summary_row(("SfM" if stage == "sfm" else "refined") + " (robust G)", rob))
        rows.append(_summary_row(("SfM" if stage == "sfm" else "refined") + " as written (no G)",
                                 {**rep, **rep["absolute"]}))
    print_table(f"viewpoints vs PASCAL3D+ ({out['refined']['report']['n']} objects with ground truth; degrees)",
                VP_HEADER, rows)
    out["refinement_change"] = _refinement_change(cams, gt)
    ch = out["refinement_change"]
    print(f"refined - SfM median geodesic on the {ch['objects']} objects with both: {ch['change']:+.2f} degrees, "
          f"95% interval over the objects [{ch['low']:+.2f}, {ch['high']:+.2f}] (viewpoint_metrics.median_change)")
    ref, sf = out["refined"]["report"], out["sfm"]["report"]
    checks = {}
    for name, target in TARGETS.items():
        checks[name] = {"refined": ref[name]["median"], "sfm": sf[name]["median"], "target": target,
                        "met": ref[name]["median"] <= target and ref[name]["median"] < sf[name]["median"]}
    out["acceptance"] = checks
    print_table("acceptance (refined median <= target and below SfM alone)",
                ["angle", "SfM", "refined", "target", "met"],
                [[k, v["sfm"], v["refined"], v["target"], "yes" if v["met"] else "NO"] for k, v in checks.items()])
    frame = read_json(recon / CLASS / "cameras.json").get("frame_info", {})
    absolute = {k: {"refined": ref["absolute"][k]["median"], "target": t, "met": ref["absolute"][k]["median"] <= t}
                for k, t in ABSOLUTE_TARGETS.items()}
    out["absolute"] = {"frame": frame, "checks": absolute}
    print_table(f"the labels as written, no fitted rotation (frame: {frame.get('kind')}, residual "
                f"{frame.get('residual')})", ["angle", "refined", "target", "met"],
                [[k, v["refined"], v["target"], "yes" if v["met"] else "NO"] for k, v in absolute.items()])
    print_table("refined cameras by ground-truth azimuth (degrees)",
                ["azimuth bin", "n", "|az err| med", "signed az err med", "geodesic med"],
                [[f"{b['azimuth_from']:.0f}-{b['azimuth_to']:.0f}", str(b["n"]), b["median_abs_azimuth_error"],
                  b["median_signed_azimuth_error"], b["median_geodesic"]] for b in out["refined"]["by_azimuth"]])
    print_table("side views (azimuth 60-120, 240-300; |azimuth error| < 45): azimuth error towards the front, "
                "by Berkeley subcategory (degrees; > 0 = estimate turned towards the nose)",
                ["subcategory", "n", "SfM median", "refined median", "refined mean"],
                [[g, str(v["n"]), out["sfm"]["side_view_bias"].get(g, {}).get("median_toward_front"),
                  v["median_toward_front"], v["mean_toward_front"]]
                 for g, v in out["refined"]["side_view_bias"].items()])
    print(f"  gross refined errors (> 30 deg): {len(out['refined']['gross_errors'])} of {ref['n']}")
    return out


_UNSEEN_NAMES = {"train_sfm": "training: SfM", "train_refined": "training: refined",
                 "unseen_keypoints_only": "unseen: keypoints only",
                 "unseen_keypoints_silhouette": "unseen: keypoints + silhouette",
                 "unseen_keypoints_only_self_aligned": "unseen: keypoints only (own G)",
                 "unseen_keypoints_silhouette_self_aligned": "unseen: kp + silhouette (own G)"}


def step_unseen(ann: Path, gt: dict, cfg: Config, seed: int, fraction: float, device: str,
                seen: dict | None = None) -> dict:
    """Cameras of a held-aside third from the mean shape learned on the other two thirds.

    ``seen``: the result of :func:`step_viewpoints`; its errors on the same held-aside objects
    (cameras of the full run, where they took part in SfM) are reported beside.
    """
    loaded = coco.load_coco(ann, canvas_size=cfg.input.canvas_size, margin=cfg.input.canvas_margin, device=device)
    coll = loaded.collections[CLASS]
    n = len(coll)
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(seed))
    n_test = int(round(fraction * n))
    test = perm[:n_test].sort().values
    train = perm[n_test:].sort().values
    tr, te = coll[train], coll[test]
    res, rr, est_kp, est_sil, seconds = _unseen_cameras(tr, te, cfg)
    n_tr = len(tr)
    R_tr_sfm, Rg_tr, _ = _with_gt(tr, res.cameras.R[:n_tr], gt)
    R_tr_ref, _, _ = _with_gt(tr, rr.cameras.R[:n_tr], gt)
    G = align_rotations(R_tr_ref, Rg_tr)
    R_kp, Rg_te, keys_te = _with_gt(te, est_kp.R, gt)
    R_sil, _, _ = _with_gt(te, est_sil.R, gt)
    reps = {
        "train_sfm": viewpoint_report(R_tr_sfm, Rg_tr),
        "train_refined": viewpoint_report(R_tr_ref, Rg_tr),
        "unseen_keypoints_only": viewpoint_report(R_kp, Rg_te, alignment=G),
        "unseen_keypoints_silhouette": viewpoint_report(R_sil, Rg_te, alignment=G),
        "unseen_keypoints_only_self_aligned": viewpoint_report(R_kp, Rg_te),
        "unseen_keypoints_silhouette_self_aligned": viewpoint_report(R_sil, Rg_te),
    }
    rows = [_summary_row(_UNSEEN_NAMES[k], v) for k, v in reps.items()]
    seen_rows = _same_objects_rows(seen, keys_te, rows) if seen is not None else {}
    print_table(f"unseen images: {n_test} held aside (seed {seed}), mean shape from the other {n - n_test}; "
                "G from the training objects unless 'own G'", VP_HEADER, rows)
    per = {k: {"keypoints_only": float(a), "keypoints_silhouette": float(b)}
           for k, a, b in zip(keys_te, reps["unseen_keypoints_only"]["per_instance_geodesic"],
                              reps["unseen_keypoints_silhouette"]["per_instance_geodesic"])}
    return {"seed": seed, "held_aside": n_test, "training": n - n_test,
            "held_aside_sources": [gt_key(s) for s in te.sources], "alignment_from_training": G.tolist(),
            "seconds": seconds, "reports": {k: _compact(v) for k, v in reps.items()},
            "same_objects_full_run": seen_rows, "per_object_geodesic": per}


def _unseen_cameras(tr, te, cfg: Config):
    """SfM and refinement on the training collection ``tr`` (with mirrors), then the held-aside ``te``'s cameras
    from its mean shape, from keypoints alone and with the silhouette; their seconds."""
    t0 = time.perf_counter()
    both = tr.with_mirrors()
    res = class_sfm(both, cfg.viewpoints)  # the pipeline's SfM (one shape)
    rr = refine_with_shape(res.shape, res.cameras, both, distance_to_mask(both.masks), cfg.viewpoints)
    t_train = time.perf_counter() - t0
    dist = distance_to_mask(te.masks)
    t0 = time.perf_counter()
    # the pipeline's unseen-image path: the keypoints the training instances show often enough
    vcfg = cfg.viewpoints
    shape = camera_fit.supported_shape(res.shape, both.visible, vcfg.refine_min_support)
    est_kp, _ = camera_fit.estimate_camera(shape, te.keypoints, te.visible, dist, silhouette_weight=0.0,
                                           max_iters=vcfg.refine_iters)
    est_sil, _ = camera_fit.estimate_camera(shape, te.keypoints, te.visible, dist,
                                            silhouette_weight=vcfg.silhouette_weight, max_iters=vcfg.refine_iters)
    t_test = time.perf_counter() - t0
    return res, rr, est_kp, est_sil, {"training_sfm_refine": round(t_train, 2),
                                      "estimate_camera_both_variants": round(t_test, 2)}


def _with_gt(c, R: torch.Tensor, gt: dict):
    """The rotations ``R (n, 3, 3)`` of the objects of collection ``c`` with ground truth (float64, CPU), theirs,
    and their keys."""
    keys = [gt_key(s) for s in c.sources]
    idx = [i for i, k in enumerate(keys) if k in gt]
    Rg = torch.tensor([gt[keys[i]]["R"] for i in idx], dtype=torch.float64)
    return R[idx].double().cpu(), Rg, [keys[i] for i in idx]


def _same_objects_rows(seen: dict, keys: list[str], rows: list) -> dict:
    """The full run's errors (SfM, refined) on the objects ``keys``, summarised; a table row each added to ``rows``."""
    seen_rows = {}
    for stage, label in (("sfm", "same objects, full run: SfM"), ("refined", "same objects, full run: refined")):
        per = [seen[stage]["per_object"][k] for k in keys if k in seen[stage]["per_object"]]
        seen_rows[stage] = {f: summarize(torch.tensor([p[f] for p in per], dtype=torch.float64))
                            for f in ("geodesic", "azimuth_error", "elevation_error")}
        v = seen_rows[stage]
        rows.append([label, str(v["geodesic"]["n"]), v["geodesic"]["median"], v["geodesic"]["acc_at_30"],
                     v["azimuth_error"]["median"], v["elevation_error"]["median"], "-"])
    return seen_rows


def camera_variant(coll, gt: dict, cfg: Config, *, mirrors: bool = True, rigid: list[int] | None = None,
                   silhouette_weight: float | None = None, refine_iters: int | None = None) -> dict:
    """SfM + refinement as the pipeline runs them with one shape (:func:`carvi_torch.viewpoints.class_sfm`,
    :func:`carvi_torch.viewpoints.refine.refine_with_shape`), scored against PASCAL3D+.

    Args:
        coll: the class collection (canvas tensors); gt: ``viewpoints_dev.json``.
        mirrors: add the flipped copies (the pipeline does).
        rigid: keypoint indices for SfM (default: the class's ``rigid_keypoints``).
        silhouette_weight, refine_iters: default the config's.

    Returns:
        ``{"sfm": report, "refined": report, "seconds": float}``.
    """
    t0 = time.perf_counter()
    both = coll.with_mirrors() if mirrors else coll
    meta = coll.meta
    opts = sfm.SfMOptions(max_outer=cfg.viewpoints.sfm_max_outer, inner=cfg.viewpoints.sfm_inner,
                          tol=cfg.viewpoints.sfm_tol, polish_iters=cfg.viewpoints.sfm_polish_iters,
                          polish=cfg.viewpoints.sfm_polish)
    res = sfm.rigid_sfm(both.keypoints, both.visible, opts,
                        rigid_keypoints=meta.rigid_keypoints if rigid is None else rigid,
                        keypoint_names=meta.keypoint_names, flip_pairs=meta.flip_pairs,
                        left_convention=meta.left_convention)
    vcfg = cfg.override({k: v for k, v in (("viewpoints.silhouette_weight", silhouette_weight),
                                           ("viewpoints.refine_iters", refine_iters)) if v is not None})
    rr = refine_with_shape(res.shape, res.cameras, both, distance_to_mask(both.masks), vcfg.viewpoints)
    n = len(coll)
    keys = [gt_key(s) for s in coll.sources]
    idx = [i for i, k in enumerate(keys) if k in gt]
    Rg = torch.tensor([gt[keys[i]]["R"] for i in idx], dtype=torch.float64)
    out = {"sfm": _compact(viewpoint_report(res.cameras.R[:n][idx].double().cpu(), Rg)),
           "refined": _compact(viewpoint_report(rr.cameras.R[:n][idx].double().cpu(), Rg)),
           "reflection": res.reflection_votes["decided_by"], "seconds": round(time.perf_counter() - t0, 1)}
    return out


def step_diagnose(data: Path, work: Path, gt: dict, cfg: Config, device: str) -> dict:
    """Viewpoint accuracy under the knobs the task names, one change at a time (cameras only, in-process).

    Baseline = the pipeline's settings. Variants: no mirrors; the keypoints' 1-based file
    coordinates kept (``one_based=False``); a 256-pixel canvas; SfM on a rigid subset
    without the engines; silhouette weights 0, 0.3, 3 and 10; 50 and 400 refinement steps.
    """
    ann = work / "annotations.json"
    ann_1 = work / "annotations_one_based.json"
    voc.convert(data / "pascal_voc_aeroplane" / "keypoints", ann_1, one_based=False)

    def load(path, canvas):
        return coco.load_coco(path, canvas_size=canvas, margin=cfg.input.canvas_margin,
                              device=device).collections[CLASS]

    coll = load(ann, cfg.input.canvas_size)
    names = coll.meta.keypoint_names
    no_engines = [i for i, nm in enumerate(names) if "engine" not in nm.lower()]
    variants = {
        "pipeline settings": lambda: camera_variant(coll, gt, cfg),
        "no mirrored copies": lambda: camera_variant(coll, gt, cfg, mirrors=False),
        "1-based coordinates kept": lambda: camera_variant(load(ann_1, cfg.input.canvas_size), gt, cfg),
        "canvas 256": lambda: camera_variant(load(ann, 256), gt, cfg),
        "rigid subset: no engines": lambda: camera_variant(coll, gt, cfg, rigid=no_engines),
        "silhouette weight 0": lambda: camera_variant(coll, gt, cfg, silhouette_weight=0.0),
        "silhouette weight 0.3": lambda: camera_variant(coll, gt, cfg, silhouette_weight=0.3),
        "silhouette weight 3": lambda: camera_variant(coll, gt, cfg, silhouette_weight=3.0),
        "silhouette weight 10": lambda: camera_variant(coll, gt, cfg, silhouette_weight=10.0),
        "refinement 50 steps": lambda: camera_variant(coll, gt, cfg, refine_iters=50),
        "refinement 400 steps": lambda: camera_variant(coll, gt, cfg, refine_iters=400),
    }
    out = {}
    for name, fn in variants.items():
        out[name] = fn()
        print(f"  diagnose: {name}: {out[name]['seconds']} s", flush=True)
    rows = []
    for name, v in out.items():
        sf, rf = v["sfm"], v["refined"]
        rows.append([name, sf["geodesic"]["median"], rf["geodesic"]["median"], sf["azimuth"]["median"],
                     rf["azimuth"]["median"], sf["elevation"]["median"], rf["elevation"]["median"],
                     rf["geodesic"]["acc_at_30"], "yes" if rf["mirrored"] else "no"])
    print_table("diagnosis: one change at a time (median errors in degrees, SfM -> refined)",
                ["variant", "geo SfM", "geo ref", "az SfM", "az ref", "el SfM", "el ref", "acc@30 ref", "mirrored"],
                rows)
    return out


def run_mesh_format(recon: Path) -> str:
    """The ``mesh.format`` the run ``recon`` wrote its meshes in (its ``config.yaml``; the default without one:
    :func:`~carvi_torch.io.layout.object_mesh` looks in the other formats too)."""
    cfg = recon / "config.yaml"
    return (read_run_config(cfg) if cfg.is_file() else Config()).mesh.format


def _recon_mesh(recon: Path, aid: int, mesh_format: str) -> trimesh.Trimesh | None:
    """Object ``aid``'s mesh of the run ``recon`` (:func:`~carvi_torch.io.layout.object_mesh`: in the run's
    ``mesh_format`` first), ``None`` without one."""
    p = object_mesh(recon / CLASS, aid, mesh_format)
    return trimesh.load(p, force="mesh", process=False) if p is not None else None


def _puffball_image(coll, i: int) -> trimesh.Trimesh:
    """Puffball of instance ``i``'s canvas mask, in image pixels."""
    from carvi_torch.evaluation.baselines import puffball

    m = puffball(coll.masks[i])
    a = float(coll.canvas_from_image.scale[i])
    b = coll.canvas_from_image.offset[i].double().cpu().numpy()
    V = np.asarray(m.vertices, dtype=np.float64).copy()
    V[:, :2] = (V[:, :2] - b) / a
    V[:, 2] /= a
    return trimesh.Trimesh(V, np.asarray(m.faces), process=False)


def _sfmc_image(cams_json: dict, aid: int) -> trimesh.Trimesh | None:
    from carvi_torch.evaluation.baselines import sfm_convex_hull

    cam = cams_json["cameras"].get(str(aid), {}).get("refined")
    if cam is None:
        return None
    S = torch.tensor([v for v in cams_json["mean_shape"].values() if v is not None], dtype=torch.float64)
    return sfm_convex_hull(S, ScaledOrthographic.from_list([cam], dtype=torch.float64))


#: Surface sampling step of the RMS error, as a fraction of the CAD diagonal. 1% rather than the
#: metric's default 0.5%: blobby reconstructions of thin aeroplanes put many samples far from the
#: CAD surface, where exact queries are slow; on the metric's benchmark (docs/tried.md: the retired
#: tools/bench_metrics.py) 1% and 0.5% agree within 0.02 points of percentage.
RMS_STEP = 0.01


def _rms(V_cad: np.ndarray, F: np.ndarray, R: np.ndarray, cad_eval) -> dict:
    """Symmetric RMS (% of the CAD diagonal) after the best shift along the viewing direction ``R[2]``."""
    m = trimesh.Trimesh(V_cad, F, process=False)
    r = metrics.evaluate_reconstruction(m, cad_eval, step=RMS_STEP * cad_eval.diag,
                                        axis=torch.from_numpy(R[2].copy()))
    ok = math.isfinite(r["error_percent"])
    return {"rms_percent": float(r["error_percent"]) if ok else None, "depth_offset": r["offset"] if ok else None,
            "reason": r["reason"]}


def score_mesh(mesh_img: trimesh.Trimesh | None, R, s, t, model: dict) -> dict:
    """RMS error and voxel IoU of an image-frame closed mesh against the posed CAD model ``model``.

    The mesh goes to the CAD frame (:func:`unpose_points` with the CAD's fitted ``s``, ``t``),
    is shifted along the viewing direction by the offset minimising the symmetric RMS, and
    is voxelised as a solid on the lattice of the CAD's :class:`Solid`.
    """
    if mesh_img is None or len(mesh_img.faces) == 0:
        return {"rms_percent": None, "iou": None, "reason": "no mesh"}
    F = np.asarray(mesh_img.faces, dtype=np.int64)
    Vc = unpose_points(np.asarray(mesh_img.vertices, dtype=np.float64), R, s, t)
    out = _rms(Vc, F, R, model["eval"])
    if out["rms_percent"] is not None:
        sol = mesh_solid(Vc + out["depth_offset"] * R[2], F, model["solid"].pitch, fill=True)
        out["iou"] = solid_iou(sol, model["solid"])
    return out


def score_other_cad(other: dict, R, s, t, s_o, t_o, model: dict) -> dict:
    """Another CAD model posed like the subtype (same ``R``, its own mask fit ``s_o``, ``t_o``) vs the subtype.

    In the subtype's frame the other model is ``k X + c`` with ``k = s_o / s`` and
    ``c = R^T (t_o - t, 0) / s``; its solid is its own :class:`Solid` mapped the same way.
    """
    k = s_o / s
    c = np.concatenate([t_o - t, [0.0]]) @ R / s
    out = _rms(k * other["cad"]["vertices"] + c, other["cad"]["faces"], R, model["eval"])
    if out["rms_percent"] is not None:
        sol = similar_solid(other["solid"], k, c + out["depth_offset"] * R[2], model["solid"].pitch)
        out["iou"] = solid_iou(sol, model["solid"])
    return out


def load_models(data: Path, cache: Path | None, iou_step: float = 0.01) -> dict:
    """The eight aeroplane CAD models with their evaluation meshes and solids (cached in ``cache``).

    ``solid``: surface voxels united with the 32-view :class:`VisualHull`, on a lattice of side
    ``iou_step`` times the model's bounding-box diagonal.
    """
    models = {}
    for k in range(1, 9):
        cad = load_cad(data / "pascal3d_cad" / f"{CLASS}0{k}.npz")
        ev = metrics.EvaluationMesh((torch.from_numpy(cad["vertices"]), torch.from_numpy(cad["faces"])),
                                    dtype=torch.float64, name=cad["name"])
        pitch = iou_step * ev.diag
        f = cache / f"{cad['name']}_solid_{iou_step:g}.npz" if cache is not None else None
        if f is not None and f.is_file():
            z = np.load(f)
            solid = Solid(z["occupancy"], z["first"], float(z["pitch"]))
        else:
            solid = mesh_solid(cad["vertices"], cad["faces"], pitch, fill=False,
                               hull=VisualHull(cad["vertices"], cad["faces"]))
            if f is not None:
                f.parent.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(f, occupancy=solid.occupancy, first=solid.first, pitch=solid.pitch)
        models[k] = {"cad": cad, "eval": ev, "solid": solid}
    return models


@dataclass
class _ShapeSources:
    """What every object's shape scores read: its annotations, the run's cameras and collection, the CAD models."""

    cc: object  # pycocotools COCO of the annotations
    cams_json: dict  # the run's cameras.json
    coll: object  # the loaded collection (the Puffball baseline's masks)
    row_of: dict  # annotation id -> row of coll
    models: dict  # subtype -> load_models' entry
    recon: Path
    mesh_format: str  # the run's mesh.format


def step_shapes(ann: Path, recon: Path, data: Path, work: Path, gt: dict, cfg: Config, other_cads: int) -> dict:
    """Reconstructions (and baselines) vs the posed closest CAD model, for the objects with ground truth."""
    from pycocotools.coco import COCO

    cc = COCO(str(ann))
    cams_json = read_json(recon / CLASS / "cameras.json")
    loaded = coco.load_coco(ann, canvas_size=cfg.input.canvas_size, margin=cfg.input.canvas_margin)
    coll = loaded.collections[CLASS]
    row_of = {int(a): i for i, a in enumerate(coll.annotation_ids)}
    t0 = time.perf_counter()
    models = load_models(data, work / "cad_solids")
    t_models = time.perf_counter() - t0
    src = _ShapeSources(cc, cams_json, coll, row_of, models, recon, run_mesh_format(recon))
    anns = [a for a in sorted(cc.anns.values(), key=lambda a: a["id"]) if gt_key(a["source"]) in gt]
    with_others = set(int(i) for i in np.linspace(0, len(anns) - 1, other_cads).round()) if other_cads > 0 else set()
    per = {}
    t0 = time.perf_counter()
    for j, ann_entry in enumerate(anns):
        key = gt_key(ann_entry["source"])
        per[key] = _shape_row(src, ann_entry, gt[key], j in with_others)
        if (j + 1) % 20 == 0 or j + 1 == len(anns):
            print(f"  shapes: {j + 1}/{len(anns)} objects, {time.perf_counter() - t0:.0f} s", flush=True)
    seconds = time.perf_counter() - t0
    table, fit = _shape_tables(per, bool(with_others))
    return {"table": table, "pose_fit": fit, "per_object": per,
            "seconds": {"cad_models": round(t_models, 1), "evaluation": round(seconds, 1)}}


def _shape_row(src: _ShapeSources, ann_entry: dict, g: dict, others: bool) -> dict:
    """One object's record: its ground-truth CAD model posed on its mask, the pose's keypoint check, the
    reconstruction's and baselines' scores (and with ``others`` the other CAD models')."""
    aid = int(ann_entry["id"])
    sub = int(g["subtype"])
    R = np.asarray(g["R"], dtype=np.float64)
    mask = src.cc.annToMask(ann_entry).astype(bool)
    model = src.models[sub]
    cad = model["cad"]
    s, t = fit_cad_to_mask(cad["vertices"], cad["faces"], R, mask)
    row = {"annotation_id": aid, "subtype": sub, "scale": s, "translation": t.tolist(),
           "cad_mask_iou": silhouette_iou(cad["vertices"], cad["faces"], R, s, t, mask)}
    row.update(_keypoint_check(src.cc, ann_entry, cad, R, s, t))
    row["reconstruction"] = score_mesh(_recon_mesh(src.recon, aid, src.mesh_format), R, s, t, model)
    if aid in src.row_of:
        row["puffball"] = score_mesh(_puffball_image(src.coll, src.row_of[aid]), R, s, t, model)
    row["sfm_hull"] = score_mesh(_sfmc_image(src.cams_json, aid), R, s, t, model)
    if others:
        row["other_cads"] = {}
        for k, other in src.models.items():
            if k != sub:
                s_o, t_o = fit_cad_to_mask(other["cad"]["vertices"], other["cad"]["faces"], R, mask)
                row["other_cads"][str(k)] = score_other_cad(other, R, s, t, s_o, t_o, model)
    return row


def _keypoint_check(cc, ann_entry: dict, cad: dict, R: np.ndarray, s: float, t: np.ndarray) -> dict:
    """Cross-check of a CAD pose ``(R, s, t)`` with the keypoints the annotation and the CAD model both name: the
    scale the keypoints give over ``s`` and their RMS misfit in % of the posed CAD's extent (none: fewer than 2)."""
    kp = np.asarray(ann_entry["keypoints"], dtype=np.float64).reshape(-1, 3)
    names = cc.cats[ann_entry["category_id"]]["keypoints"]
    pairs = [(kp[i, :2], cad["keypoints"][BERKELEY_TO_PASCAL3D[nm]]) for i, nm in enumerate(names)
             if kp[i, 2] > 0 and nm in BERKELEY_TO_PASCAL3D and BERKELEY_TO_PASCAL3D[nm] in cad["keypoints"]]
    if len(pairs) < 2:
        return {}
    W = np.stack([p[0] for p in pairs])
    P = np.stack([p[1] for p in pairs]) @ R[:2].T
    s_kp, _, _ = fit_keypoints(P, W)
    extent = s * float(np.ptp(cad["vertices"] @ R[:2].T, axis=0).max())
    rms = float(np.sqrt(((s * P + t - W) ** 2).sum(-1).mean()))
    return {"keypoint_scale_ratio": s_kp / s, "keypoint_rms_percent_of_extent": 100.0 * rms / extent}


def _agg(vals) -> dict:
    """Count, median and mean of the finite values of ``vals`` (``None``: skipped)."""
    vals = [v for v in vals if v is not None and math.isfinite(v)]
    return {"n": len(vals), "median": float(np.median(vals)) if vals else None,
            "mean": float(np.mean(vals)) if vals else None}


def _shape_tables(per: dict, with_others: bool) -> tuple[dict, dict]:
    """Print and return the shape errors per method (and against the other CAD models on their subset) and the
    quality of the CAD poses, over the objects' records ``per``."""
    methods = {"reconstruction": "reconstruction", "puffball": "Puffball", "sfm_hull": "SfM convex hull"}
    table = {m: {"rms_percent": _agg(r.get(m, {}).get("rms_percent") for r in per.values()),
                 "iou": _agg(r.get(m, {}).get("iou") for r in per.values())} for m in methods}
    if with_others:
        sub_rows = [r for r in per.values() if "other_cads" in r]

        def other(r, fn, field):
            v = [o[field] for o in r["other_cads"].values() if o.get(field) is not None]
            return float(fn(v)) if v else None

        table["reconstruction_on_subset"] = {"rms_percent": _agg(r["reconstruction"].get("rms_percent")
                                                                 for r in sub_rows),
                                             "iou": _agg(r["reconstruction"].get("iou") for r in sub_rows)}
        table["other_cad_median"] = {"rms_percent": _agg(other(r, np.median, "rms_percent") for r in sub_rows),
                                     "iou": _agg(other(r, np.median, "iou") for r in sub_rows)}
        table["other_cad_best"] = {"rms_percent": _agg(other(r, np.min, "rms_percent") for r in sub_rows),
                                   "iou": _agg(other(r, np.max, "iou") for r in sub_rows)}
        methods.update({"reconstruction_on_subset": f"reconstruction ({len(sub_rows)}-object subset)",
                        "other_cad_median": "another CAD model (median of 7, subset)",
                        "other_cad_best": "the closest other CAD model (subset)"})
    fit = {"cad_mask_iou": _agg(r["cad_mask_iou"] for r in per.values()),
           "keypoint_scale_ratio": _agg(r.get("keypoint_scale_ratio") for r in per.values()),
           "keypoint_rms_percent_of_extent": _agg(r.get("keypoint_rms_percent_of_extent") for r in per.values())}
    print_table(f"shapes vs the posed closest PASCAL3D+ CAD model ({len(per)} objects; RMS in % of the CAD "
                "diagonal, lower is better; voxel IoU at 1% of the diagonal, higher is better)",
                ["shape", "n", "RMS med", "RMS mean", "IoU med", "IoU mean"],
                [[methods[m], str(v["rms_percent"]["n"]), v["rms_percent"]["median"], v["rms_percent"]["mean"],
                  v["iou"]["median"], v["iou"]["mean"]] for m, v in table.items()])
    print_table("posing the CAD model (rotation = ground truth, scale + translation from the mask)",
                ["quantity", "n", "median", "mean"],
                [[k, str(v["n"]), v["median"], v["mean"]] for k, v in fit.items()])
    return table, fit


# =========================================================================== figure


def _render_mesh(ax, V: np.ndarray, F: np.ndarray, R: np.ndarray, title: str) -> None:
    """Flat-shaded orthographic view of a mesh (painter's algorithm) seen by rotation ``R``."""
    from matplotlib.collections import PolyCollection

    P = V @ R.T
    tri = P[F]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)
    light = np.array([-0.3, -0.5, -0.8])
    light /= np.linalg.norm(light)
    shade = 0.25 + 0.75 * np.abs(n @ light)
    order = np.argsort(-tri[:, :, 2].mean(1))  # far to near (depth grows into the scene)
    colors = np.clip(shade[order, None] * np.array([0.55, 0.7, 0.95]), 0, 1)
    ax.add_collection(PolyCollection(tri[order][:, :, :2], facecolors=colors, edgecolors="none"))
    lo, hi = P[:, :2].min(0), P[:, :2].max(0)
    c, r = (lo + hi) / 2, (hi - lo).max() / 2 * 1.08
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] + r, c[1] - r)
    ax.set_aspect("equal")
    ax.set_title(title, fontsize=8)


@dataclass
class _FigureSources:
    """What each object's panels read: the annotations, the run's cameras, the viewpoint and shape records."""

    cc: object  # pycocotools COCO of the annotations
    cams_json: dict  # the run's cameras.json
    per: dict  # step_viewpoints' refined per-object records
    S: np.ndarray  # (K, 3) the mean shape, NaN where a keypoint has none
    G: np.ndarray  # (3, 3) the alignment of the SfM frame with the CAD frame
    views: list  # (R (3, 3), label) of the mesh views
    recon: Path
    data: Path
    shapes: dict | None  # step_shapes' result
    mesh_format: str  # the run's mesh.format


def step_figure(path: Path, ann: Path, recon: Path, data: Path, gt: dict, vp: dict, shapes: dict | None,
                count: int = 12) -> dict:
    """A dozen objects: mask polygon + reconstruction silhouette + keypoints, and two views of the mesh."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from pycocotools.coco import COCO

    from carvi_torch.io.outputs import atomic_write

    cc = COCO(str(ann))
    cams_json = read_json(recon / CLASS / "cameras.json")
    G = np.asarray(vp["refined"]["report"]["alignment"], dtype=np.float64)
    per = vp["refined"]["per_object"]
    fmt = run_mesh_format(recon)
    keys = sorted((k for k in per if object_mesh(recon / CLASS, per[k]["annotation_id"], fmt) is not None),
                  key=lambda k: per[k]["gt_azimuth"])
    picks = [keys[int(i)] for i in np.linspace(0, len(keys) - 1, count).round()] if keys else []
    names = cc.cats[1]["keypoints"]
    S = np.array([cams_json["mean_shape"][nm] if cams_json["mean_shape"][nm] is not None else [np.nan] * 3
                  for nm in names], dtype=np.float64)
    cols = 3
    per_row = 3
    rows = int(math.ceil(len(picks) / per_row))
    fig, axes = plt.subplots(rows, cols * per_row, figsize=(2.2 * cols * per_row, 2.3 * rows), squeeze=False)
    for a in axes.ravel():
        a.set_xticks([])
        a.set_yticks([])
        a.axis("off")
    views = [(rotation_from_azimuth_elevation_roll(torch.tensor(math.radians(a), dtype=torch.float64),
                                                   torch.tensor(math.radians(e), dtype=torch.float64),
                                                   torch.tensor(0.0, dtype=torch.float64)).numpy(), lbl)
             for a, e, lbl in ((45.0, 20.0, "az 45, el 20"), (0.0, 80.0, "from above"))]
    src = _FigureSources(cc, cams_json, per, S, G, views, recon, data, shapes, fmt)
    for j, key in enumerate(picks):
        first = (j % per_row) * cols
        _draw_voc_object(src, key, axes[j // per_row, first],
                         [axes[j // per_row, first + 1 + k] for k in range(len(views))])
    fig.suptitle("PASCAL VOC aeroplanes: mask (polygon outline), reconstruction silhouette (green = both, red = mask "
                 "only, blue = reconstruction only), annotated keypoints (orange) and mean shape by the refined "
                 "camera (purple x); the mesh seen from two PASCAL3D+ viewpoints", fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda fh: fig.savefig(fh, format="png", dpi=90))
    plt.close(fig)
    print(f"\nwrote {path}")
    return {"figure": str(path), "objects": picks}


def _draw_voc_object(src: _FigureSources, key: str, a0, mesh_axes: list) -> None:
    """One object's panels: on ``a0`` its mask and polygons, the reconstruction's silhouette, the annotated keypoints
    and the mean shape by the refined camera; on ``mesh_axes`` the mesh in the CAD-aligned frame, one per view."""
    aid = src.per[key]["annotation_id"]
    ann_e = src.cc.anns[aid]
    mask = src.cc.annToMask(ann_e).astype(bool)
    mesh = _recon_mesh(src.recon, aid, src.mesh_format)
    V = np.asarray(mesh.vertices, dtype=np.float64)
    F = np.asarray(mesh.faces, dtype=np.int64)
    x0, x1, y0, y1 = _draw_overlap(a0, mask, silhouette(V[:, :2], F, np.zeros(2), mask.shape))
    obj = voc.parse_keypoint_xml(src.data / "pascal_voc_aeroplane" / "keypoints" / ann_e["source"])
    for poly in obj.polygons:
        p = np.vstack([poly, poly[:1]])
        a0.plot(p[:, 0], p[:, 1], "-", color="k", lw=0.6)
    kp = np.asarray(ann_e["keypoints"], dtype=np.float64).reshape(-1, 3)
    v = kp[:, 2] > 0
    a0.plot(kp[v, 0], kp[v, 1], "o", ms=3, color="orange", mec="k", mew=0.3)
    cam = src.cams_json["cameras"][str(aid)]["refined"]
    if cam is not None:
        c = ScaledOrthographic.from_list([cam], dtype=torch.float64)
        q = c.project(torch.from_numpy(src.S))[0].numpy()
        a0.plot(q[:, 0], q[:, 1], "x", ms=3.5, color="purple", mew=0.8)
    a0.set_xlim(x0 - 0.5, x1 - 0.5)
    a0.set_ylim(y1 - 0.5, y0 - 0.5)
    title = f"{key}  geo {src.per[key]['geodesic']:.0f} deg"
    if src.shapes and key in src.shapes["per_object"]:
        rr = src.shapes["per_object"][key]["reconstruction"]
        if rr.get("rms_percent") is not None:
            title += f"\nRMS {rr['rms_percent']:.1f}%  IoU {rr.get('iou', float('nan')):.2f}"
    a0.set_title(title, fontsize=7)
    # the mesh in the CAD-aligned object frame: X_sfm = R^T (v - t) / s, X_cad = G^T X_sfm
    if cam is not None:
        Rr = np.asarray(cam["R"], dtype=np.float64)
        X = unpose_points(V, Rr, float(cam["s"]), np.asarray(cam["t"], dtype=np.float64)) @ src.G
        for ax, (Rv, lbl) in zip(mesh_axes, src.views):
            _render_mesh(ax, X, F, Rv, lbl)


def _draw_overlap(ax, mask: np.ndarray, sil: np.ndarray) -> tuple[int, int, int, int]:
    """Show where the ``(H, W)`` mask and silhouette agree (green), the mask alone (red), the silhouette alone (blue),
    cropped to both with a margin; the crop ``x0, x1, y0, y1`` (ends excluded)."""
    ys, xs = np.nonzero(mask | sil)
    pad = 8
    y0, y1 = max(0, ys.min() - pad), min(mask.shape[0], ys.max() + pad + 1)
    x0, x1 = max(0, xs.min() - pad), min(mask.shape[1], xs.max() + pad + 1)
    rgb = np.ones(mask.shape + (3,))
    rgb[mask & sil] = (0.55, 0.85, 0.55)
    rgb[mask & ~sil] = (0.95, 0.55, 0.55)
    rgb[~mask & sil] = (0.55, 0.65, 0.95)
    ax.imshow(rgb[y0:y1, x0:x1], extent=(x0 - 0.5, x1 - 0.5, y1 - 0.5, y0 - 0.5))
    return x0, x1, y0, y1


# =========================================================================== main


def record_paths(args, work: Path) -> tuple[Path, Path | None]:
    """The record's and the figure's paths (``None``: no figure): ``--out`` and ``--figure``, by default
    ``WORK/voc_study.json`` and ``WORK/voc_aeroplanes.png`` (never the committed docs/ files unless named)."""
    out = Path(args.out).resolve() if args.out else work / "voc_study.json"
    figure = None if args.figure == "none" else Path(args.figure) if args.figure else work / "voc_aeroplanes.png"
    return out, figure


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(ROOT / ".." / "shared" / "data"),
                    help="folder with pascal_voc_aeroplane/ and pascal3d_cad/ (default ../shared/data)")
    ap.add_argument("--work", default=str(ROOT / "outputs" / "voc"),
                    help="working folder: annotations.json and the reconstruction (default outputs/voc)")
    ap.add_argument("--out", default=None,
                    help="JSON record (default WORK/voc_study.json, with --cameras-only WORK/cameras_only.json; "
                         "docs/voc.md's record: docs/data/voc_study.json)")
    ap.add_argument("--figure", default=None,
                    help="figure path (default WORK/voc_aeroplanes.png; docs/voc.md's: "
                         "docs/figures/voc_aeroplanes.png); 'none' for no figure")
    ap.add_argument("--seed", type=int, default=0, help="seed of the held-aside split (default 0)")
    ap.add_argument("--holdout", type=float, default=1 / 3, help="fraction held aside for unseen images (default 1/3)")
    ap.add_argument("--device", default="cpu", help="torch device (default cpu)")
    ap.add_argument("--threads", type=int, default=1,
                    help="torch CPU threads of this process's own steps (default 1: its many small tensor ops "
                         "ran 10-20x slower with 2 threads on a busy 2-core machine); the pipeline keeps its own")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="extra reconstruct config override (repeatable), e.g. --set silhouette_weight=3")
    ap.add_argument("--skip-reconstruct", action="store_true",
                    help="use the reconstruction already in WORK/recon (do not run the pipeline)")
    ap.add_argument("--other-cads", type=int, default=24, metavar="N",
                    help="compare N objects (spread over the list) also with the seven other CAD models, a "
                         "yardstick of how much aeroplanes differ (default 24; 0: skip)")
    ap.add_argument("--no-shapes", action="store_true", help="skip the shape comparison")
    ap.add_argument("--no-diagnose", action="store_true",
                    help="skip the viewpoint diagnosis (SfM + refinement under one change at a time)")
    ap.add_argument("--cameras-only", action="store_true",
                    help="convert, reconstruct with stage=cameras and print the viewpoint tables only")
    ap.add_argument("--compare-set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="--cameras-only: also make the cameras with these overrides (after --set's) into "
                         "WORK/cameras_compare and compare the two object by object: each angle's medians, the "
                         "paired bootstrap 95%% interval of their difference, the objects each puts closer and "
                         "the sign test")
    return ap


def cameras_only(args, data: Path, work: Path, command: str) -> dict:
    """``--cameras-only``: convert, ``stage=cameras``, the viewpoint tables (about 20 s)."""
    gt = json.loads((data / "pascal_voc_aeroplane" / "viewpoints_dev.json").read_text())
    conv = step_convert(data, work)
    ann = Path(conv["annotations"])
    recon = step_reconstruct(ann, work / "cameras", ["stage=cameras", "overwrite=true", *args.overrides], args.device)
    subcategory = {gt_key(a["source"]): a.get("subcategory") for a in read_json(ann)["annotations"]}
    vp = step_viewpoints(work / "cameras", gt, subcategory)
    floor = step_cad_floor(ann, data, gt, vp, read_json(work / "cameras" / CLASS / "cameras.json"), subcategory)
    summary = {stage: {"n": vp[stage]["report"]["n"],
                       **{f"{a}_median": vp[stage]["report"][a]["median"] for a in ("geodesic", "azimuth",
                                                                                    "elevation")},
                       "acc_at_30": vp[stage]["report"]["geodesic"]["acc_at_30"],
                       "mirrored": vp[stage]["report"]["mirrored"]} for stage in ("sfm", "refined")}
    out = Path(args.out) if args.out else work / "cameras_only.json"
    result = {"command": command, "objects": conv["converted"], **summary, "acceptance": vp["acceptance"],
              "cad_floor": floor, "cameras_seconds": recon["total_seconds"]}
    if args.compare_set:
        step_reconstruct(ann, work / "cameras_compare", ["stage=cameras", "overwrite=true", *args.overrides,
                                                          *args.compare_set], args.device)
        result["compared"] = step_compare(work / "cameras", work / "cameras_compare", gt,
                                          ("this run", " ".join(args.compare_set)))
    write_json(out, result)
    print(f"\nwrote {out}")
    return result


def main(argv=None) -> dict:
    args = build_parser().parse_args(argv)
    data, work = Path(args.data).resolve(), Path(args.work).resolve()
    src = data / "pascal_voc_aeroplane"
    if not (src / "keypoints").is_dir() or not (src / "viewpoints_dev.json").is_file():
        raise SystemExit(f"voc_study: {src} has no keypoints/ and viewpoints_dev.json (--data)")
    work.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(max(1, args.threads))
    command = "python tools/voc_study.py " + " ".join(shlex.quote(a) for a in (argv if argv is not None
                                                                             else sys.argv[1:]))
    if args.compare_set and not args.cameras_only:
        raise SystemExit("voc_study: --compare-set needs --cameras-only")
    if args.cameras_only:
        return cameras_only(args, data, work, command)
    out, figure = record_paths(args, work)
    load = os.getloadavg()
    print(f"voc_study: {command}\nload average at start: {load[0]:.2f} {load[1]:.2f} {load[2]:.2f}, "
          f"{os.cpu_count()} cores")
    t_start = time.perf_counter()
    gt = json.loads((data / "pascal_voc_aeroplane" / "viewpoints_dev.json").read_text())
    cfg = Config().override(args.overrides) if args.overrides else Config()

    result = {"command": command, "environment": {
        "torch": torch.__version__, "python": platform.python_version(), "cpu_count": os.cpu_count(),
        "load_average_start": [round(x, 2) for x in load], "device": args.device}}
    conv = step_convert(data, work)
    result["conversion"] = conv
    ann = Path(conv["annotations"])
    recon = work / "recon"
    result["reconstruction"] = _reused_reconstruction(recon) if args.skip_reconstruct else \
        step_reconstruct(ann, recon, ["overwrite=true", *args.overrides], args.device)
    subcategory = {gt_key(a["source"]): a.get("subcategory") for a in read_json(ann)["annotations"]}
    vp = step_viewpoints(recon, gt, subcategory)
    result["viewpoints"] = {k: ({kk: vv for kk, vv in v.items() if kk != "per_object"} if isinstance(v, dict)
                                and "per_object" in v else v) for k, v in vp.items()}
    result["cad_floor"] = step_cad_floor(ann, data, gt, vp, read_json(recon / CLASS / "cameras.json"), subcategory)
    result["unseen"] = step_unseen(ann, gt, cfg, args.seed, args.holdout, args.device, seen=vp)
    if not args.no_diagnose:
        result["diagnosis"] = step_diagnose(data, work, gt, cfg, args.device)
    shapes = None
    if not args.no_shapes:
        shapes = step_shapes(ann, recon, data, work, gt, cfg, other_cads=args.other_cads)
        result["shapes"] = {k: v for k, v in shapes.items() if k != "per_object"}
    if figure is not None:
        result["figure"] = step_figure(figure, ann, recon, data, gt, vp, shapes)
    result["total_seconds"] = round(time.perf_counter() - t_start, 1)
    load = os.getloadavg()
    result["environment"]["load_average_end"] = [round(x, 2) for x in load]
    write_json(out, result)
    write_json(work / "per_object.json", {"command": command, "objects": _per_object(vp, result["unseen"], shapes)})
    print(f"\nwrote {out} and {work / 'per_object.json'} in {result['total_seconds']:.0f} s "
          f"(load average at end {load[0]:.2f})")
    return result


def _reused_reconstruction(recon: Path) -> dict:
    """``--skip-reconstruct``: what the existing run's ``summary.json`` says of its aeroplanes."""
    if not (recon / CLASS / "cameras.json").is_file():
        raise SystemExit(f"voc_study: --skip-reconstruct but {recon}/{CLASS}/cameras.json is missing")
    summ = read_json(recon / "summary.json")
    c = summ["classes"][CLASS]
    return {"objects": c["objects"], "failures": c["failures"], "warnings": c["warnings"],
            "seconds": c["seconds"], "total_seconds": summ.get("total_seconds"),
            "note": "reused an existing reconstruction (--skip-reconstruct)"}


def _per_object(vp: dict, unseen: dict, shapes: dict | None) -> dict:
    """Every object with a refined camera: its SfM and refined errors, unseen-image error and shape record."""
    per_object = {}
    for k in vp["refined"]["per_object"]:
        row = {"sfm": vp["sfm"]["per_object"].get(k), "refined": vp["refined"]["per_object"][k]}
        if k in unseen["per_object_geodesic"]:
            row["unseen_geodesic"] = unseen["per_object_geodesic"][k]
        if shapes and k in shapes["per_object"]:
            row["shape"] = shapes["per_object"][k]
        per_object[k] = row
    return per_object


if __name__ == "__main__":
    main()
