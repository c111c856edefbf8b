"""``python -m carvi_torch.export``: a sharded training dataset from a reconstruction directory.

For every reconstructed object the export writes, in shards of ``--shard-size`` objects, one
``.npy`` file per field (so a reader memory-maps them and never loads a whole shard), plus
``index.json`` describing fields, shapes, dtypes, axis order and every sample. The exact layout
is documented in ``docs/export.md``; :class:`carvi_torch.training.LiftedDataset` reads it.

Objects whose outputs are missing or unreadable (no voxels, no mesh, no camera, not in the
annotations) are reported by annotation id with the reason, in the console and in
``index.json["skipped"]``; the rest is exported.
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
import trimesh
from tqdm.auto import tqdm

from .cameras import ScaledOrthographic, Similarity2D
from .cli import add_common, split_classes
from .config import Config, read_run_config
from .io.coco import load_coco
from .io.layout import object_file
from .io.outputs import atomic_write, read_json, write_json
from .io.writer import INT64_RANGE
from .mesh import MESH_FORMATS

__all__ = ["export", "main", "FIELDS", "view_occupancy", "canonical_occupancy", "depth_map"]

FORMAT_VERSION = 1


@dataclass(frozen=True)
class FieldSpec:
    dtype: str
    shape: str  # symbolic, e.g. "(C, C)"
    doc: str


#: Every exported field: dtype, per-sample shape and meaning (also written to index.json).
FIELDS: dict[str, FieldSpec] = {
    "mask": FieldSpec("bool", "(C, C)", "canvas mask, [row = y, col = x], canvas pixels"),
    "keypoints": FieldSpec("float32", "(K, 2)", "canvas keypoints (x, y); 0 where not visible"),
    "visible": FieldSpec("bool", "(K,)", "keypoint visibility"),
    "crop_box": FieldSpec("float32", "(4,)", "image region of the canvas: x0, y0, x1, y1 (image pixels, "
                                             "centres of the canvas corner pixels)"),
    "canvas_scale": FieldSpec("float32", "()", "a in canvas = a * image + b"),
    "canvas_offset": FieldSpec("float32", "(2,)", "b in canvas = a * image + b"),
    "R": FieldSpec("float32", "(3, 3)", "camera rotation, rows = image x, image y (down), view direction, "
                                        "in the class frame"),
    "s": FieldSpec("float32", "()", "camera scale, image pixels per class-frame unit"),
    "t": FieldSpec("float32", "(2,)", "image position of the class-frame origin (image pixels)"),
    "viewpoint": FieldSpec("float32", "(3,)", "azimuth, elevation, roll (radians) in the class frame, as "
                                               "PASCAL3D+ defines them"),
    "occupancy_view": FieldSpec("bool", "(R, R, R)", "occupancy in the view frame, [depth, y, x]: the canvas "
                                                     "square in x, y and a depth range of the same size centred "
                                                     "on the object"),
    "occupancy_canonical": FieldSpec("bool", "(R, R, R)", "occupancy in the class frame, [z, y, x] of the class "
                                                          "frame over [-E, E]^3 (E = class_extent)"),
    "depth": FieldSpec("float32", "(C, C)", "depth of the mesh's first surface per canvas pixel, canvas pixels, "
                                            "relative to the object's depth centre; +inf where the ray misses"),
    "points": FieldSpec("float32", "(P, 3)", "surface points in the class frame (area-uniform samples)"),
    "normals": FieldSpec("float32", "(P, 3)", "outward unit normals at the points, class frame"),
    "annotation_id": FieldSpec("int64", "()", "COCO annotation id (-1 for a string id: see annotation_key)"),
    "image_id": FieldSpec("int64", "()", "COCO image id (-1 for a string id)"),
    "class_index": FieldSpec("int64", "()", "index into index.json['classes']"),
}


# =========================================================================== per-object computations


def _grid_points(res: int, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """``(res, res, res, 3)`` cell-centre points of the box ``[lo, hi]`` indexed ``[i2, i1, i0]`` -> ``(x0, x1, x2)``.

    Index order is (slowest..fastest) = (axis 2, axis 1, axis 0) of the coordinates, i.e. ``[z, y, x]``.
    """
    c = (torch.arange(res, dtype=torch.float64) + 0.5) / res
    axes = [lo[i] + (hi[i] - lo[i]) * c for i in range(3)]
    z, y, x = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    return torch.stack([x, y, z], dim=-1)


def _sample_occupancy(occ: np.ndarray, camera_to_voxel: np.ndarray, pts_cam: torch.Tensor) -> np.ndarray:
    """Occupancy of ``occ (D,H,W)`` at camera-frame points ``(..., 3)`` (outside = empty).

    Trilinear interpolation of the 0/1 grid thresholded just below 0.5: the same surface as the
    mesh (marching cubes at that level interpolates linearly along voxel edges), so the exported
    voxels agree with the exported mesh.
    """
    P = pts_cam.reshape(-1, 3).double()
    idx = P @ torch.from_numpy(camera_to_voxel[:3, :3]).T + torch.from_numpy(camera_to_voxel[:3, 3])  # (d, h, w)
    D, H, W = occ.shape
    g = torch.stack([2 * idx[:, 2] / max(W - 1, 1) - 1, 2 * idx[:, 1] / max(H - 1, 1) - 1,
                     2 * idx[:, 0] / max(D - 1, 1) - 1], dim=-1).float()
    vol = torch.from_numpy(occ.astype(np.float32))[None, None]
    out = F.grid_sample(vol, g.view(1, 1, 1, -1, 3), mode="bilinear", padding_mode="zeros", align_corners=True)
    return (out.view(pts_cam.shape[:-1]) > 0.5 - 1e-3).numpy()


def view_occupancy(occ: np.ndarray, voxel_to_canvas: np.ndarray, canvas_size: int, res: int,
                   depth_centre: float) -> np.ndarray:
    """Occupancy ``(res, res, res)`` ``[depth, y, x]`` over the canvas square and a cube of depth around the centre."""
    C = float(canvas_size)
    lo = torch.tensor([-0.5, -0.5, depth_centre - C / 2], dtype=torch.float64)
    hi = torch.tensor([C - 0.5, C - 0.5, depth_centre + C / 2], dtype=torch.float64)
    pts = _grid_points(res, lo, hi)  # [z, y, x] -> (x, y, z) canvas camera frame
    return _sample_occupancy(occ, np.linalg.inv(voxel_to_canvas), pts)


def canonical_occupancy(occ: np.ndarray, voxel_to_canvas: np.ndarray, camera: ScaledOrthographic, extent: float,
                        res: int) -> np.ndarray:
    """Occupancy ``(res, res, res)`` ``[z, y, x]`` of the class frame over ``[-extent, extent]^3``.

    ``camera`` is the object's canvas camera (class frame -> canvas pixels).
    """
    lo = torch.full((3,), -extent, dtype=torch.float64)
    pts = _grid_points(res, lo, -lo)  # class frame
    cam = camera.to(torch.float64)
    p_cam = cam.to_camera_frame(pts.reshape(1, -1, 3))[0].reshape(pts.shape)
    return _sample_occupancy(occ, np.linalg.inv(voxel_to_canvas), p_cam)


def depth_map(mesh_canvas: trimesh.Trimesh, canvas_size: int, depth_centre: float) -> np.ndarray:
    """First-surface depth of a canvas-frame mesh at every canvas pixel centre (z-buffer rasterisation)."""
    from .synthetic.render import rasterize_depth

    v = torch.from_numpy(np.asarray(mesh_canvas.vertices, dtype=np.float64))
    f = torch.from_numpy(np.asarray(mesh_canvas.faces, dtype=np.int64))
    z = rasterize_depth(v[:, :2], v[:, 2], f, canvas_size, canvas_size)
    return (z - depth_centre).numpy().astype(np.float32)


# =========================================================================== the export


def _recon_config(recon: Path) -> Config:
    p = recon / "config.yaml"
    if not p.is_file():
        raise FileNotFoundError(f"{recon}: no config.yaml (is this a reconstruction directory?)")
    return read_run_config(p)


def _data_path(recon: Path, cfg: Config) -> Path:
    """The annotations a run read: its summary's path (absolute), else its config's; a relative path
    is looked up beside the run, then from the current folder."""
    summ = recon / "summary.json"
    data = read_json(summ).get("data") if summ.is_file() else None
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


class _ShardWriter:
    """Accumulates samples and writes one folder of ``.npy`` files per shard (atomically per file).

    A shard holds one class only (``keypoints`` has the class's ``K``): :meth:`flush` is called at
    every class change.
    """

    def __init__(self, out: Path, shard_size: int):
        self.out, self.shard_size = out, shard_size
        self.buf: dict[str, list] = {k: [] for k in FIELDS}
        self.shards: list[dict] = []
        self.cls: str | None = None

    def add(self, sample: dict, cls: str):
        if cls != self.cls:
            self.flush()
            self.cls = cls
        for k in FIELDS:
            self.buf[k].append(sample[k])
        if len(self.buf["mask"]) >= self.shard_size:
            self.flush()

    def flush(self):
        n = len(self.buf["mask"])
        if n == 0:
            return
        name = f"shard_{len(self.shards):05d}"
        for k, spec in FIELDS.items():
            arr = np.stack([np.asarray(v) for v in self.buf[k]]).astype(spec.dtype)
            atomic_write(self.out / name / f"{k}.npy", lambda f, a=arr: np.save(f, a))
        self.shards.append({"name": name, "count": n, "class": self.cls})
        self.buf = {k: [] for k in FIELDS}


def export(recon: str | Path, out: str | Path, resolution: int = 32, points: int = 2048, shard_size: int = 256,
           seed: int = 0, progress: bool = True, classes=None) -> dict:
    """Export every reconstructed object of ``recon`` into a sharded dataset in ``out``; returns the index."""
    recon, out = Path(recon), Path(out)
    cfg = _recon_config(recon)
    data = _data_path(recon, cfg)
    canvas = cfg.input.canvas_size
    loaded = load_coco(data, canvas_size=canvas, margin=cfg.input.canvas_margin, classes=classes)
    class_names = sorted(c for c in loaded.collections if (recon / c).is_dir())
    writer = _ShardWriter(out, shard_size)
    skipped, samples = [], []
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    total = sum(len(loaded.collections[c]) for c in class_names)
    bar = tqdm(total=total, desc="export", disable=not progress)
    class_extent = {}
    for ci, cname in enumerate(class_names):
        coll = loaded.collections[cname]
        cdir = recon / cname
        try:
            cams = read_json(cdir / "cameras.json")
        except (FileNotFoundError, ValueError) as e:
            for aid in coll.annotation_ids:
                skipped.append({"annotation_id": aid, "class": cname, "reason": f"cameras.json unreadable: {e}"})
            bar.update(len(coll))
            continue
        shape = np.array([v for v in cams.get("mean_shape", {}).values() if v is not None], dtype=np.float64)
        extent = float(1.3 * np.linalg.norm(shape - shape.mean(0), axis=1).max()) if len(shape) else 1.0
        class_extent[cname] = extent
        for i, aid in enumerate(coll.annotation_ids):
            bar.update(1)
            reason = None
            cam_entry = cams.get("cameras", {}).get(str(aid), {})
            vox_p = object_file(cdir, "voxels", aid)
            mesh_p = next((p for p in (object_file(cdir, "meshes", aid, ext) for ext in MESH_FORMATS) if p.is_file()),
                          None)
            if cam_entry.get("refined") is None:
                reason = "no camera in cameras.json"
            elif not vox_p.is_file():
                reason = "no voxels (not reconstructed)"
            elif mesh_p is None:
                reason = "no mesh (not reconstructed)"
            if reason is None:
                try:
                    sample = _export_one(coll, i, cam_entry, vox_p, mesh_p, canvas, extent, resolution, points, rng)
                except Exception as e:  # partial/corrupt files: report and go on
                    reason = f"unreadable outputs: {type(e).__name__}: {e}"
            if reason is not None:
                skipped.append({"annotation_id": aid, "class": cname, "source": coll.sources[i], "reason": reason})
                continue
            sample["class_index"] = ci
            writer.add(sample, cname)
            samples.append({"annotation_id": aid, "image_id": coll.image_ids[i], "class": cname,
                            "source": coll.sources[i]})
    writer.flush()
    bar.close()
    for s in skipped:
        tqdm.write(f"export: {s['class']} annotation {s['annotation_id']} skipped: {s['reason']}")
    index = {
        "format_version": FORMAT_VERSION,
        "recon": str(recon), "data": str(data), "canvas_size": canvas, "resolution": resolution, "points": points,
        "classes": class_names, "class_extent": class_extent,
        "fields": {k: {"dtype": v.dtype, "shape": v.shape, "doc": v.doc} for k, v in FIELDS.items()},
        "shards": writer.shards, "samples": samples, "skipped": skipped,
        "seconds": round(time.perf_counter() - t0, 3),
    }
    write_json(out / "index.json", index, indent=None)
    return index


def _int_id(value) -> np.int64:
    """An id as the int64 field holds it: the id when it is an integer int64 holds, else -1 (``index.json``
    and :class:`~carvi_torch.training.LiftedDataset`'s ``annotation_key`` carry every id as given)."""
    lo, hi = INT64_RANGE
    return np.int64(value) if isinstance(value, int) and lo <= value <= hi else np.int64(-1)


def _export_one(coll, i, cam_entry, vox_p, mesh_p, canvas, extent, res, n_points, rng) -> dict:
    z = np.load(vox_p)
    occ = z["occupancy"].astype(bool)
    v2canvas = z["voxel_to_canvas"] if "voxel_to_canvas" in z else None
    a = float(coll.canvas_from_image.scale[i])
    b = coll.canvas_from_image.offset[i].double()
    image_to_canvas = np.diag([a, a, a, 1.0])
    image_to_canvas[:2, 3] = b.numpy()
    if v2canvas is None:
        v2canvas = image_to_canvas @ z["voxel_to_camera"]
    cam_img = ScaledOrthographic.from_list([cam_entry["refined"]], dtype=torch.float64)
    sim = Similarity2D(torch.tensor([a], dtype=torch.float64), b[None])
    cam_canvas = cam_img.compose_similarity(sim)
    m = trimesh.load(mesh_p, force="mesh", process=False)
    m_canvas = m.copy()
    m_canvas.apply_transform(image_to_canvas)
    depth_centre = float(np.asarray(m_canvas.vertices)[:, 2].mean()) if len(m_canvas.vertices) else 0.0
    pts, fidx = trimesh.sample.sample_surface(m_canvas, n_points, seed=int(rng.integers(2 ** 31)))
    normals_cam = np.asarray(m_canvas.face_normals)[fidx]
    # camera frame (canvas px) -> class frame: X = R^T [(u - t) / s, (v - t) / s, z / s]
    R = cam_canvas.R[0].numpy()
    s = float(cam_canvas.s[0])
    tt = cam_canvas.t[0].numpy()
    q = np.asarray(pts, dtype=np.float64).copy()
    q[:, :2] -= tt
    pts_class = (q / s) @ R
    normals_class = normals_cam @ R
    C = canvas
    x0y0 = (np.array([0.0, 0.0]) - b.numpy()) / a
    x1y1 = (np.array([C - 1.0, C - 1.0]) - b.numpy()) / a
    from .cameras import azimuth_elevation_roll_from_rotation

    az, el, ro = azimuth_elevation_roll_from_rotation(cam_img.R)
    return {
        "mask": coll.masks[i].cpu().numpy(),
        "keypoints": coll.keypoints[i].cpu().numpy(),
        "visible": coll.visible[i].cpu().numpy(),
        "crop_box": np.concatenate([x0y0, x1y1]).astype(np.float32),
        "canvas_scale": np.float32(a), "canvas_offset": b.numpy().astype(np.float32),
        "R": cam_img.R[0].numpy(), "s": np.float32(cam_img.s[0]), "t": cam_img.t[0].numpy(),
        "viewpoint": np.array([float(az[0]), float(el[0]), float(ro[0])], dtype=np.float32),
        "occupancy_view": view_occupancy(occ, v2canvas, canvas, res, depth_centre),
        "occupancy_canonical": canonical_occupancy(occ, v2canvas, cam_canvas, extent, res),
        "depth": depth_map(m_canvas, canvas, depth_centre),
        "points": pts_class.astype(np.float32), "normals": normals_class.astype(np.float32),
        "annotation_id": _int_id(coll.annotation_ids[i]), "image_id": _int_id(coll.image_ids[i]),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m carvi_torch.export",
                                 description="Export a reconstruction directory as a sharded dataset for PyTorch "
                                             "training (read it with carvi_torch.training.LiftedDataset; layout in "
                                             "docs/export.md).")
    ap.add_argument("--recon", required=True, help="output directory of carvi_torch.reconstruct")
    ap.add_argument("--out", required=True, help="dataset directory to write")
    ap.add_argument("--resolution", type=int, default=32, help="occupancy grid side (default 32)")
    ap.add_argument("--points", type=int, default=2048, help="surface points per object (default 2048)")
    ap.add_argument("--shard-size", type=int, default=256, help="objects per shard (default 256)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the surface sampling")
    add_common(ap)
    args = ap.parse_args(argv)
    try:
        idx = export(args.recon, args.out, args.resolution, args.points, args.shard_size, args.seed,
                     progress=not args.quiet, classes=split_classes(args.classes))
    except (FileNotFoundError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"exported {len(idx['samples'])} objects in {len(idx['shards'])} shard(s) to {args.out} "
          f"({idx['seconds']:.1f} s); skipped {len(idx['skipped'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
