"""export.py + training.py: the sharded training dataset and its reader."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
import trimesh
from torch.utils.data import DataLoader

from carvi_torch.config import Config
from carvi_torch.export import export, main as export_main
from carvi_torch.executors import run
from carvi_torch.training import LiftedDataset, collate_lifted

TINY = {"procedural_instances": 5, "resolution": 24, "proposals": 3, "canvas_size": 64, "progress": False,
        "refine_iters": 20, "plane_size": 32, "preview": False, "report": False, "classes": ["car", "chair"]}


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    out = tmp_path_factory.mktemp("recon")
    run(Config().override({**TINY, "out": str(out)}))
    return out


@pytest.fixture(scope="module")
def exported(recon, tmp_path_factory):
    out = tmp_path_factory.mktemp("export")
    index = export(recon, out, resolution=16, points=256, shard_size=4, progress=False)
    return out, index


def _canvas_mesh(recon, cls, aid, scale, offset):
    m = trimesh.load(recon / cls / "meshes" / f"{aid}.ply", force="mesh", process=False)
    T = np.diag([scale, scale, scale, 1.0])
    T[:2, 3] = offset
    m.apply_transform(T)
    return m


def test_index_and_shards(exported):
    out, index = exported
    n = len(index["samples"])
    per_class = {c: sum(1 for s in index["samples"] if s["class"] == c) for c in index["classes"]}
    assert n >= 8 and sum(s["count"] for s in index["shards"]) == n
    assert len(index["shards"]) == sum(-(-k // 4) for k in per_class.values())  # shards hold one class each
    for name, spec in index["fields"].items():
        arr = np.load(out / index["shards"][0]["name"] / f"{name}.npy", mmap_mode="r")
        assert str(arr.dtype) == spec["dtype"], name
    ds = LiftedDataset(out)
    item = ds[0]
    assert item["mask"].shape == (64, 64) and item["mask"].dtype == torch.bool
    assert item["occupancy_view"].shape == (16, 16, 16) and item["points"].shape == (256, 3)
    assert item["R"].shape == (3, 3) and abs(float(torch.det(item["R"].double())) - 1) < 1e-4


def test_round_trip_matches_reconstruction(recon, exported):
    """What the dataset returns equals what the reconstruction wrote."""
    out, index = exported
    ds = LiftedDataset(out)
    for i in range(len(ds)):
        item = ds[i]
        cls, aid = item["class_name"], int(item["annotation_id"])
        cams = json.loads((recon / cls / "cameras.json").read_text())["cameras"][str(aid)]["refined"]
        assert np.allclose(item["R"].numpy(), cams["R"], atol=1e-5) and np.isclose(float(item["s"]), cams["s"])
        z = np.load(recon / cls / "voxels" / f"{aid}.npz")
        assert np.isclose(float(item["canvas_scale"]), float(z["canvas_scale"]))


def test_occupancy_agrees_with_mesh(recon, exported):
    """Occupancy re-derived from the mesh agrees with the exported view-frame voxels (IoU >= 0.95)."""
    out, index = exported
    ds = LiftedDataset(out)
    ious = []
    for i in range(len(ds)):
        item = ds[i]
        m = _canvas_mesh(recon, item["class_name"], int(item["annotation_id"]), float(item["canvas_scale"]),
                         item["canvas_offset"].numpy())
        if not m.is_watertight:
            continue
        R = 16
        C = 64.0
        zc = float(np.asarray(m.vertices)[:, 2].mean())
        c = (np.arange(R) + 0.5) / R
        zz, yy, xx = np.meshgrid(zc - C / 2 + C * c, -0.5 + C * c, -0.5 + C * c, indexing="ij")
        pts = np.stack([xx, yy, zz], -1).reshape(-1, 3)
        inside = m.contains(pts).reshape(R, R, R)
        occ = item["occupancy_view"].numpy()
        ious.append((inside & occ).sum() / max((inside | occ).sum(), 1))
    assert ious and np.median(ious) >= 0.95, ious


def test_depth_matches_ray_cast(recon, exported):
    out, _ = exported
    ds = LiftedDataset(out, fields=["depth", "canvas_scale", "canvas_offset", "annotation_id"])
    item = ds[1]
    m = _canvas_mesh(recon, item["class_name"], int(item["annotation_id"]), float(item["canvas_scale"]),
                     item["canvas_offset"].numpy())
    zc = float(np.asarray(m.vertices)[:, 2].mean())
    depth = item["depth"].numpy()
    ys, xs = np.nonzero(np.isfinite(depth))
    pick = np.linspace(0, len(xs) - 1, 40).astype(int)
    origins = np.stack([xs[pick], ys[pick], np.full(len(pick), -1e4)], -1).astype(float)
    dirs = np.tile([0.0, 0.0, 1.0], (len(pick), 1))
    locs, ray_idx, _ = m.ray.intersects_location(origins, dirs)
    first = np.full(len(pick), np.inf)
    np.minimum.at(first, ray_idx, locs[:, 2])
    ok = np.isfinite(first)
    assert ok.mean() > 0.9
    assert np.abs(first[ok] - zc - depth[ys[pick], xs[pick]][ok]).max() < 1e-3


def test_points_on_surface(recon, exported):
    out, _ = exported
    ds = LiftedDataset(out, fields=["points", "normals", "R", "s", "t", "canvas_scale", "canvas_offset",
                                    "annotation_id"])
    item = ds[0]
    a = float(item["canvas_scale"])
    s_c = a * float(item["s"])
    t_c = a * item["t"].numpy() + item["canvas_offset"].numpy()
    X = item["points"].numpy().astype(np.float64)
    R = item["R"].numpy().astype(np.float64)
    uvz = s_c * X @ R.T
    uvz[:, :2] += t_c
    m = _canvas_mesh(recon, item["class_name"], int(item["annotation_id"]), a, item["canvas_offset"].numpy())
    _, dist, _ = trimesh.proximity.closest_point(m, uvz)
    assert dist.max() < 1e-2
    assert np.allclose(np.linalg.norm(item["normals"].numpy(), axis=1), 1, atol=1e-4)


def test_dataloader_two_workers(exported):
    out, index = exported
    ds = LiftedDataset(out, fields=["mask", "viewpoint", "occupancy_canonical"])
    loader = DataLoader(ds, batch_size=3, num_workers=2, collate_fn=collate_lifted)
    seen = 0
    for batch in loader:
        assert batch["mask"].dtype == torch.bool and batch["viewpoint"].shape[1] == 3
        assert isinstance(batch["class_name"], list)
        seen += batch["mask"].shape[0]
    assert seen == len(index["samples"])


def test_collate_pads_mixed_classes(exported):
    out, _ = exported
    ds = LiftedDataset(out, fields=["keypoints", "visible"])
    cars = [i for i in range(len(ds)) if ds[i]["class_name"] == "car"]
    chairs = [i for i in range(len(ds)) if ds[i]["class_name"] == "chair"]
    batch = collate_lifted([ds[cars[0]], ds[chairs[0]]])
    k_car, k_chair = ds[cars[0]]["keypoints"].shape[0], ds[chairs[0]]["keypoints"].shape[0]
    assert batch["keypoints"].shape == (2, max(k_car, k_chair), 2)
    assert not batch["visible"][1, k_chair:].any()


def test_class_and_field_filters(exported):
    out, _ = exported
    assert all(ds_item["class_name"] == "car" for ds_item in LiftedDataset(out, classes=["car"]))
    with pytest.raises(ValueError, match="unknown field"):
        LiftedDataset(out, fields=["nope"])
    with pytest.raises(ValueError, match="not in the export"):
        LiftedDataset(out, classes=["boat"])


def test_missing_and_partial_objects_reported(recon, tmp_path, capsys):
    broken = tmp_path / "recon"
    shutil.copytree(recon, broken)
    vox = sorted((broken / "car" / "voxels").glob("*.npz"))
    vox[0].unlink()  # missing
    mesh = broken / "car" / "meshes" / f"{vox[1].stem}.ply"
    mesh.write_bytes(mesh.read_bytes()[:50])  # partial file
    rc = export_main(["--recon", str(broken), "--out", str(tmp_path / "exp"), "--resolution", "8", "--points", "16"])
    assert rc == 0
    index = json.loads((tmp_path / "exp" / "index.json").read_text())
    reasons = {s["annotation_id"]: s["reason"] for s in index["skipped"]}
    assert int(vox[0].stem) in reasons and "no voxels" in reasons[int(vox[0].stem)]
    assert int(vox[1].stem) in reasons and "unreadable" in reasons[int(vox[1].stem)]
    assert "skipped" in capsys.readouterr().out
