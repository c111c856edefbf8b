"""export/ + training.py: the zarr training store and its reader."""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from scipy import ndimage
from scipy.spatial import ConvexHull
from torch.utils.data import DataLoader

from carvi_torch.cameras import azimuth_elevation_roll_from_rotation
from carvi_torch.config import Config
from carvi_torch.executors import run
from carvi_torch.io.coco import load_coco
from carvi_torch.export import export, main as export_main
from carvi_torch.export.formats import export_format
from carvi_torch.export.objects import canonical_occupancy, splat_occupancy
from carvi_torch.training import LiftedDataset, collate_lifted

TINY = {"procedural_instances": 5, "resolution": 24, "proposals": 3, "canvas_size": 64, "progress": False,
        "refine_iters": 20, "plane_size": 32, "preview": False, "report": False, "classes": ["car", "chair"]}


@pytest.fixture(scope="module")
def recon(tmp_path_factory):
    out = tmp_path_factory.mktemp("recon")
    run(Config().override({**TINY, "out": str(out)}), workers=0)  # written inline: the same files, a second sooner
    return out


@pytest.fixture(scope="module")
def exported(recon, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "store"
    index = export(recon, out, resolution=16, points=256, shard_size=4, progress=False, workers=0, mesh=True)
    return out, index


def _canvas_mesh(recon, cls, aid, scale, offset):
    m = trimesh.load(recon / cls / "meshes" / f"{aid}.ply", force="mesh", process=False)
    T = np.diag([scale, scale, scale, 1.0])
    T[:2, 3] = offset
    m.apply_transform(T)
    return m


def test_store_opens_with_zarr_alone(exported):
    """Any zarr v3 reader gets the samples: one group per class, one compressed array per field,
    one chunk per sample, shards of --shard-size samples."""
    import zarr

    out, index = exported
    root = zarr.open_group(str(out), mode="r")
    attrs = root.attrs["carvi_export"]
    assert attrs["format_version"] == 3 and attrs["classes"] == ["car", "chair"]
    assert json.loads((out / "zarr.json").read_text())["zarr_format"] == 3
    for c in attrs["classes"]:
        g = root[c]
        n = g.attrs["count"]
        assert n == sum(1 for s in index["samples"] if s["class"] == c) == len(g.attrs["annotation_ids"])
        for name, spec in attrs["fields"].items():
            a = g[name]
            assert str(a.dtype) == spec["dtype"], name
            if name.startswith("mesh_"):
                continue
            assert a.shape[0] == n and a.chunks == (1, *a.shape[1:]) and a.shards == (4, *a.shape[1:]), name
            assert a.compressors, name
        assert g["occupancy_view"].shape[1:] == (16, 16, 16) and g["points"].shape[1:] == (256, 3)
        assert g["mask"][0].dtype == bool and g["mask"][0].shape == (64, 64)
    # a zarr store object works as well as a path (what remote stores are)
    ds = LiftedDataset(zarr.storage.LocalStore(str(out), read_only=True), fields=["mask"])
    assert len(ds) == len(index["samples"]) and torch.equal(ds[0]["mask"], torch.from_numpy(root["car"]["mask"][0]))
    # compression: the bool occupancies take far less than their raw size on disk
    occ_bytes = sum(f.stat().st_size for f in out.glob("*/occupancy_view/**/*") if f.is_file())
    assert occ_bytes < 0.5 * len(index["samples"]) * 16 ** 3


def test_round_trip_matches_reconstruction(recon, exported):
    """What the dataset returns equals what the reconstruction wrote, quality included (also summarised
    per class in summary.json)."""
    out, index = exported
    summary = json.loads((recon / "summary.json").read_text())["classes"]
    for c in ("car", "chair"):
        assert summary[c]["quality"]["count"] == summary[c]["reconstructed"]
        assert 0 <= summary[c]["quality"]["p10"] <= summary[c]["quality"]["median"] <= summary[c]["quality"]["p90"] <= 1
    ds = LiftedDataset(out)
    assert len(ds) == len(index["samples"]) >= 8
    for i in range(len(ds)):
        item = ds[i]
        cls, aid = item["class_key"], int(item["annotation_id"])
        assert item["annotation_key"] == str(aid)
        cams = json.loads((recon / cls / "cameras.json").read_text())["cameras"][str(aid)]
        assert np.allclose(item["R"].numpy(), cams["refined"]["R"], atol=1e-5)
        assert np.isclose(float(item["s"]), cams["refined"]["s"])
        # the angles are cameras.json's, in radians, and those of the stored R
        angles = [math.radians(cams[k]) for k in ("azimuth_deg", "elevation_deg", "roll_deg")]
        assert np.array_equal(item["viewpoint"].numpy(), np.array(angles, dtype=np.float32))
        R = torch.as_tensor(cams["refined"]["R"], dtype=torch.float64)
        assert np.allclose(torch.stack(azimuth_elevation_roll_from_rotation(R)).numpy(), angles, atol=1e-12)
        q = cams["quality"]  # every object with a camera has one, with the signals it combines
        assert 0.0 <= q <= 1.0 and np.isclose(float(item["quality"]), q) and "reconstruction_iou" in cams[
            "quality_signals"]
        z = np.load(recon / cls / "voxels" / f"{aid}.npz")
        assert np.isclose(float(item["canvas_scale"]), float(z["canvas_scale"]))
        assert item["points"].dtype == torch.float32 and item["depth"].dtype == torch.float32
        assert abs(float(torch.det(item["R"].double())) - 1) < 1e-4


def _mesh_cells(m, R, lo, size):
    """Cells ``[d, y, x]`` of an R^3 grid (origin ``lo``, cell ``size`` per axis x, y, z) whose centre is in ``m``."""
    c = (np.arange(R) + 0.5)[:, None] * np.broadcast_to(size, (3,))
    zz, yy, xx = np.meshgrid(lo[2] + c[:, 2], lo[1] + c[:, 1], lo[0] + c[:, 0], indexing="ij")
    return m.contains(np.stack([xx, yy, zz], -1).reshape(-1, 3)).reshape(R, R, R)


def test_view_occupancy_covers_the_mesh(recon, exported):
    """Every surface point of the mesh lies in the one-cell-dilated occupancy; the occupancy holds every
    cell whose centre is inside the mesh, and nothing farther than one cell from the mesh."""
    out, _ = exported
    ds = LiftedDataset(out, fields=["occupancy_view", "view_depth", "canvas_scale", "canvas_offset", "annotation_id"])
    cube = np.ones((3, 3, 3))
    checked_inside = 0
    for i in range(len(ds)):
        item = ds[i]
        m = _canvas_mesh(recon, item["class_key"], int(item["annotation_id"]), float(item["canvas_scale"]),
                         item["canvas_offset"].numpy())
        occ = item["occupancy_view"].numpy()
        R, C = occ.shape[0], 64.0
        zc, dz = item["view_depth"].tolist()
        pts = m.sample(4000, seed=i)
        cell = np.floor(np.stack([(pts[:, 2] - zc) / dz + R / 2, (pts[:, 1] + 0.5) * R / C,
                                  (pts[:, 0] + 0.5) * R / C], 1)).astype(int)
        assert ((cell >= 0) & (cell < R)).all(), i  # the whole mesh is inside the grid
        assert ndimage.binary_dilation(occ, cube)[cell[:, 0], cell[:, 1], cell[:, 2]].mean() >= 0.99, i
        near = np.zeros_like(occ)
        near[cell[:, 0], cell[:, 1], cell[:, 2]] = True
        if checked_inside < 2 and m.is_watertight:  # containment tests are slow: two objects
            ref = _mesh_cells(m, R, np.array([-0.5, -0.5, zc - R / 2 * dz]), np.array([C / R, C / R, dz]))
            assert (ref & occ).sum() >= 0.98 * ref.sum(), i
            near |= ref
            checked_inside += 1
        near |= ndimage.binary_fill_holes(near)
        assert not (occ & ~ndimage.binary_dilation(near, cube)).any(), i
    assert checked_inside == 2


def test_canonical_occupancy_covers_the_mesh(recon, exported):
    out, index = exported
    ds = LiftedDataset(out, fields=["occupancy_canonical", "mesh_vertices", "mesh_faces"])
    for i in range(len(ds)):
        item = ds[i]
        E = index["class_extent"][item["class_key"]]
        occ = item["occupancy_canonical"].numpy()
        R = occ.shape[0]
        m = trimesh.Trimesh(item["mesh_vertices"].numpy(), item["mesh_faces"].numpy(), process=False)
        pts = m.sample(2000, seed=i)
        cell = np.clip(np.floor((pts[:, ::-1] + E) * R / (2 * E)).astype(int), 0, R - 1)  # [z, y, x]
        dil = ndimage.binary_dilation(occ, structure=np.ones((3, 3, 3)))
        assert dil[cell[:, 0], cell[:, 1], cell[:, 2]].mean() >= 0.99, i


def _centre_sampled(occ, v2t, res):
    """What sampling cell centres gives (trilinear, level 0.5): the earlier export's occupancy."""
    c = np.arange(res) + 0.5
    pts = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    src = (pts - v2t[:3, 3]) @ np.linalg.inv(v2t[:3, :3]).T
    return (ndimage.map_coordinates(occ.astype(np.float32), src.T, order=1) >= 0.5).reshape(res, res, res)


def test_thin_parts_are_kept():
    """A rod and a plate one voxel thick, on a grid twice as fine as the export's and placed between its
    cell centres: sampling cell centres drops both; the supersampled occupancy keeps every cell holding
    one of their voxels' centres, and marks no cell their boxes do not overlap."""
    occ = np.zeros((40, 40, 40), bool)
    occ[8:32, 20, 20] = True  # a rod along depth; cell centres sit at odd voxel indices 2c + 1
    occ[10, 5:35, 5:35] = True  # a plate
    v2t = np.diag([0.5, 0.5, 0.5, 1.0])  # 20^3 cells, 2 voxels per cell
    assert not _centre_sampled(occ, v2t, 20).any()
    got = splat_occupancy(occ, v2t, 20)
    centres = np.zeros_like(got)  # analytic: voxel i has its centre in cell floor(i / 2)
    overlap = np.zeros_like(got)  # and its box [i - 0.5, i + 0.5] / 2 overlaps cells floor(i/2 -+ 1/4)
    for d, h, w in np.argwhere(occ):
        centres[d // 2, h // 2, w // 2] = True
        lo = np.floor((np.array([d, h, w]) - 0.5) / 2).astype(int)
        hi = np.floor((np.array([d, h, w]) + 0.5) / 2).astype(int)
        overlap[lo[0]:hi[0] + 1, lo[1]:hi[1] + 1, lo[2]:hi[2] + 1] = True
    assert got[centres].all() and not got[~overlap].any()
    assert got[5].sum() >= 15 * 15 and got[4:16, 10, 10].all()


def test_canonical_occupancy_of_a_thin_rotated_plate():
    """A plate one voxel thick, in a camera rotated 30 degrees about two axes: the canonical grid keeps it
    (at least 97% of the cells its mid-plane crosses), where cell-centre sampling keeps under half of them."""
    occ = np.zeros((48, 48, 48), bool)
    occ[24, 8:40, 8:40] = True  # depth 24: the plate z = 0 of the camera frame
    v2c = np.eye(4)
    v2c[:3, :3] = np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0]])  # (d, h, w) -> (x, y, z) = (w, h, d)
    v2c[:3, 3] = [-24, -24, -24]
    a, b = np.radians(30), np.radians(30)
    Rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    Ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    R = Rx @ Ry
    got = canonical_occupancy(occ, v2c, R, 1.0, np.zeros(2), extent=24.0, res=24)
    # cells crossed by the plate's mid-plane: dense samples of it, in the class frame X = R^T x
    u = np.linspace(8 - 23.5, 39 - 24 + 0.49, 400)
    g = np.stack(np.meshgrid(u, u, indexing="ij"), -1).reshape(-1, 2)
    X = np.concatenate([g, np.zeros((len(g), 1))], 1) @ R  # rows: R^T x
    cell = np.floor((X[:, ::-1] + 24.0) * 24 / 48).astype(int)
    want = np.zeros_like(got)
    want[cell[:, 0], cell[:, 1], cell[:, 2]] = True
    assert got[want].mean() >= 0.97  # slivers under the sub-sample spacing may be missed
    assert got.sum() <= 2.5 * want.sum()  # any-overlap, not a blanket
    # the same voxel -> canonical cell map for the centre sampler: [z, y, x] = (R^T x + E) res / (2 E)
    v2t_c = np.diag([0.5, 0.5, 0.5, 1.0])
    v2t_c[:3, :3] = 0.5 * np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0]]) @ R.T @ v2c[:3, :3]
    v2t_c[:3, 3] = 0.5 * (np.array([[0, 0, 1], [0, 1, 0], [1, 0, 0]]) @ R.T @ v2c[:3, 3]) + 12
    assert _centre_sampled(occ, v2t_c, 24)[want].mean() < 0.5


def test_depth_matches_ray_cast(recon, exported):
    out, _ = exported
    ds = LiftedDataset(out, fields=["depth", "view_depth", "canvas_scale", "canvas_offset", "annotation_id"])
    item = ds[1]
    m = _canvas_mesh(recon, item["class_key"], int(item["annotation_id"]), float(item["canvas_scale"]),
                     item["canvas_offset"].numpy())
    zc = float(item["view_depth"][0])
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
    # float16 keeps 11 significant bits: |depth| <= 32 canvas pixels -> within 2^-6 pixel
    assert np.abs(first[ok] - zc - depth[ys[pick], xs[pick]][ok]).max() < 2 ** -6 + 1e-3


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
    m = _canvas_mesh(recon, item["class_key"], int(item["annotation_id"]), a, item["canvas_offset"].numpy())
    _, dist, _ = trimesh.proximity.closest_point(m, uvz)
    # float16 class-frame points: 2^-11 relative, times s_c |X| (<= the canvas) -> under 0.05 canvas pixel
    assert dist.max() < 0.05
    assert np.allclose(np.linalg.norm(item["normals"].numpy(), axis=1), 1, atol=2e-3)
    # the normals point outwards: a step along them leaves the (watertight) mesh
    if m.is_watertight:
        n_c = item["normals"].numpy().astype(np.float64) @ R.T
        assert m.contains(uvz - 0.3 * n_c).mean() > 0.9 and m.contains(uvz + 0.3 * n_c).mean() < 0.1


def test_dataloader_two_workers(exported):
    out, index = exported
    ds = LiftedDataset(out, fields=["mask", "viewpoint", "occupancy_canonical", "mesh_vertices"])
    loader = DataLoader(ds, batch_size=3, num_workers=2, collate_fn=collate_lifted)
    seen = 0
    for batch in loader:
        assert batch["mask"].dtype == torch.bool and batch["viewpoint"].shape[1] == 3
        assert isinstance(batch["class_name"], list) and isinstance(batch["mesh_vertices"], list)
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


def test_class_field_and_quality_filters(recon, exported, tmp_path):
    out, _ = exported
    assert all(ds_item["class_key"] == "car" for ds_item in LiftedDataset(out, classes=["car"]))
    with pytest.raises(ValueError, match="unknown field"):
        LiftedDataset(out, fields=["nope"])
    with pytest.raises(ValueError, match="not in the export"):
        LiftedDataset(out, classes=["boat"])
    with pytest.raises((FileNotFoundError, ValueError)):  # a folder without a store: one clear error
        LiftedDataset(tmp_path)
    # min_quality keeps the objects whose cameras.json quality reaches it
    rec = tmp_path / "recon"
    shutil.copytree(recon, rec, ignore=shutil.ignore_patterns("voxels", "meshes"))
    for c in ("car", "chair"):
        shutil.copytree(recon / c / "voxels", rec / c / "voxels")
        shutil.copytree(recon / c / "meshes", rec / c / "meshes")
        cams = json.loads((rec / c / "cameras.json").read_text())
        for k, entry in enumerate(cams["cameras"].values()):
            entry["quality"] = k / 10
        (rec / c / "cameras.json").write_text(json.dumps(cams))
    export(rec, tmp_path / "q", resolution=4, points=8, progress=False, workers=0)
    ds = LiftedDataset(tmp_path / "q", min_quality=0.25, fields=["quality"])
    qs = sorted(float(ds[i]["quality"]) for i in range(len(ds)))
    assert len(ds) == 2 * 2 and min(qs) >= 0.25 - 1e-6  # 5 objects per class, qualities 0, .1, .2, .3, .4


def test_the_shard_layout_is_still_read_with_a_warning(tmp_path):
    """A format-1 export (index.json + shard_XXXXX/<field>.npy) reads, with a DeprecationWarning."""
    sh = tmp_path / "old" / "shard_00000"
    sh.mkdir(parents=True)
    masks = np.zeros((2, 4, 4), bool)
    masks[1, 1:3, 1:3] = True
    np.save(sh / "mask.npy", masks)
    np.save(sh / "s.npy", np.array([2.0, 3.0], np.float32))
    index = {"format_version": 1, "classes": ["car"], "fields": {"mask": {"dtype": "bool", "shape": "(C, C)"},
                                                                 "s": {"dtype": "float32", "shape": "()"}},
             "shards": [{"name": "shard_00000", "count": 2, "class": "car"}],
             "samples": [{"annotation_id": 5, "class": "car", "source": "a"},
                         {"annotation_id": "x7", "class": "car", "source": "b"}]}
    (tmp_path / "old" / "index.json").write_text(json.dumps(index))
    with pytest.warns(DeprecationWarning, match="deprecated and is read until carvi_torch 0.4"):
        ds = LiftedDataset(tmp_path / "old")
    assert len(ds) == 2 and ds[1]["mask"].sum() == 4 and float(ds[1]["s"]) == 3.0
    assert ds[1]["annotation_key"] == "x7"
    with pytest.warns(DeprecationWarning):
        assert len(LiftedDataset(tmp_path / "old", min_quality=0.0)) == 0  # no quality in format 1


def test_missing_and_partial_objects_reported(recon, tmp_path, capsys):
    broken = tmp_path / "recon"
    shutil.copytree(recon, broken)
    vox = sorted((broken / "car" / "voxels").glob("*.npz"))
    vox[0].unlink()  # missing
    mesh = broken / "car" / "meshes" / f"{vox[1].stem}.ply"
    mesh.write_bytes(mesh.read_bytes()[:50])  # partial file
    cams = json.loads((broken / "car" / "cameras.json").read_text())
    kept_angles = [math.radians(cams["cameras"][vox[2].stem][k]) for k in ("azimuth_deg", "elevation_deg", "roll_deg")]
    del cams["cameras"][vox[2].stem]["roll_deg"]  # no angles: they come from R
    del cams["cameras"][vox[3].stem]["roll_deg"]  # no angles and no readable R: skipped
    cams["cameras"][vox[3].stem]["refined"]["R"] = [[1.0, 0.0]]
    (broken / "car" / "cameras.json").write_text(json.dumps(cams))
    rc = export_main(["--recon", str(broken), "--out", str(tmp_path / "exp"), "--resolution", "8", "--points",
                      "16", "--workers", "0"])
    assert rc == 0
    import zarr

    attrs = zarr.open_group(str(tmp_path / "exp"), mode="r").attrs["carvi_export"]
    reasons = {s["annotation_id"]: s["reason"] for s in attrs["skipped"]}
    assert int(vox[0].stem) in reasons and "no voxels" in reasons[int(vox[0].stem)]
    assert int(vox[1].stem) in reasons and "unreadable" in reasons[int(vox[1].stem)]
    assert int(vox[2].stem) not in reasons
    assert "no readable azimuth/elevation/roll or R" in reasons[int(vox[3].stem)]
    ds = LiftedDataset(tmp_path / "exp", fields=["viewpoint", "annotation_id"])
    got = next(ds[i]["viewpoint"].numpy() for i in range(len(ds)) if int(ds[i]["annotation_id"]) == int(vox[2].stem))
    assert np.allclose(got, kept_angles, atol=1e-6)
    assert "skipped" in capsys.readouterr().out
    # an earlier export is replaced; a folder holding anything else is left alone (exit 2, nothing written)
    args = ["--recon", str(broken), "--resolution", "4", "--points", "8", "--workers", "0", "--classes", "chair"]
    assert export_main(args + ["--out", str(tmp_path / "exp")]) == 0
    assert zarr.open_group(str(tmp_path / "exp"), mode="r").attrs["carvi_export"]["classes"] == ["chair"]
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    assert export_main(args + ["--out", str(tmp_path / "mine")]) == 2
    assert [p.name for p in (tmp_path / "mine").iterdir()] == ["notes.txt"]


def test_cmr_and_ucmr_files_round_trip(recon, tmp_path):
    """The .mat reads as CMR reads it; every pose puts the normalised mean shape where our camera puts the
    mean shape (trans 1-based); conv_tri (1-based) closes the hull of S; the JSON's sfmpose is the same pose."""
    import scipy.io
    from scipy.spatial.transform import Rotation

    assert export_main(["--recon", str(recon), "--out", str(tmp_path / "cmr"), "--format", "cmr"]) == 0
    assert export_main(["--recon", str(recon), "--out", str(tmp_path / "ucmr"), "--format", "ucmr"]) == 0
    for c in ("car", "chair"):
        m = scipy.io.loadmat(tmp_path / "cmr" / f"{c}.mat", struct_as_record=False, squeeze_me=True)
        cams = json.loads((recon / c / "cameras.json").read_text())
        names = list(m["kp_names"])
        X = np.array([cams["mean_shape"][n] for n in names], dtype=np.float64)  # (K, 3), every row known here
        S = m["S"].T
        assert np.isclose(np.max(np.linalg.norm(S[:, None] - S[None], axis=-1)), 2.0) and np.allclose(S.mean(0), 0)
        hull = trimesh.Trimesh(S, m["conv_tri"].astype(int) - 1, process=False)
        assert hull.is_watertight and np.isclose(abs(hull.volume), ConvexHull(S).volume)
        js = json.loads((tmp_path / "ucmr" / f"{c}.json").read_text())
        assert len(m["sfm_anno"]) == len(js["images"]) == len(cams["cameras"])
        for a, aid, rec in zip(m["sfm_anno"], m["annotation_ids"], js["images"]):
            cam = cams["cameras"][str(aid)]["refined"]
            ours = cam["s"] * X @ np.array(cam["R"])[:2].T + np.array(cam["t"])
            theirs = a.scale * S @ a.rot[:2].T + a.trans - 1.0
            assert np.allclose(theirs, ours, atol=1e-6) and a.err_sfm_reproj >= 0
            s, t, q = rec["sfmpose"]
            assert str(rec["annotation_id"]) == str(aid) and np.isclose(s, a.scale) and np.allclose(t, a.trans)
            Rq = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()  # (w, x, y, z) -> scipy's (x, y, z, w)
            assert np.allclose(Rq, a.rot, atol=1e-6) and q[0] >= 0


# --------------------------------------------------------------------------- the fast paths against references


def _recon_meshes(recon, n=4):
    """Up to ``n`` (vertices in canvas pixels, faces) of the fixture's reconstruction."""
    from carvi_torch.mesh import read_mesh_arrays as load_mesh

    out = []
    for p in sorted(recon.glob("*/meshes/*.ply"))[:n]:
        v, f = load_mesh(p)
        z = np.load(p.parent.parent / "voxels" / f"{p.stem}.npz")
        out.append((v * float(z["canvas_scale"]) + np.r_[np.asarray(z["canvas_offset"], float).ravel()[:2], 0.0], f))
    return out


def test_numpy_zbuffer_equals_the_torch_rasteriser(recon):
    """The export's numpy z-buffer returns the torch rasteriser's depths bit for bit: on real meshes,
    and on triangle soups with pixel centres on edges (integer and half-integer vertices), degenerate,
    non-finite and off-image triangles."""
    from carvi_torch.export.raster import zbuffer
    from carvi_torch.synthetic.render import rasterize_depth

    cases = [(v[:, :2], v[:, 2], f, 64, 64) for v, f in _recon_meshes(recon, 2)]
    rng = np.random.default_rng(0)
    for _ in range(25):
        xy = rng.integers(-4, 26, (24, 2)) / rng.choice([1.0, 2.0, 3.0])
        xy[rng.integers(0, 24, 2)] = [[np.nan, 1.0], [np.inf, 2.0]][rng.integers(0, 2)]
        faces = rng.integers(0, 24, (30, 3))
        faces[:3, 2] = faces[:3, 1]  # degenerate
        cases.append((xy, rng.normal(size=24), faces, 18, 21))
    for xy, z, faces, h, w in cases:
        want = rasterize_depth(torch.from_numpy(xy), torch.from_numpy(z), torch.from_numpy(faces), h, w).numpy()
        got = zbuffer(xy, z, faces, h, w)
        assert got.dtype == np.float32 and np.array_equal(got, want, equal_nan=True)
    assert np.isfinite(got).any() and np.isinf(got).any()


def _centre_reference(occ, A, b, res):
    """Every cell whose centre's nearest voxel is occupied, testing every cell."""
    c = np.arange(res) + 0.5
    centres = np.stack(np.meshgrid(c, c, c, indexing="ij"), -1).reshape(-1, 3)
    src = np.rint((centres - b) @ np.linalg.inv(A).T).astype(np.int64)
    ok = ((src >= 0) & (src < np.array(occ.shape))).all(axis=1)
    out = np.zeros(len(src), bool)
    out[ok] = occ[tuple(src[ok].T)]
    return out.reshape(res, res, res)


def _splat_reference(occ, v2t, res):
    """The any-overlap occupancy written plainly: every cell centre's nearest voxel, every boundary box's
    sub-samples (the formulas of :func:`splat_occupancy`, with no restriction to the object's box)."""
    from carvi_torch.export.objects import MAX_SUBSAMPLES, surface_voxel_indices

    A, b = v2t[:3, :3], v2t[:3, 3]
    out = _centre_reference(occ, A, b, res)
    idx = surface_voxel_indices(occ)
    k = [int(min(MAX_SUBSAMPLES, max(1, np.ceil(2.0 * np.abs(A[:, j]).sum())))) for j in range(3)]
    subs = [(np.arange(n, dtype=np.float32) + 0.5) / n - 0.5 for n in k]
    offs = np.stack(np.meshgrid(*subs, indexing="ij"), -1).reshape(-1, 3)
    Af = A.astype(np.float32)
    cell = np.floor(((idx @ Af.T + b.astype(np.float32))[:, None] + (offs @ Af.T)[None]).reshape(-1, 3))
    cell = cell[((cell >= 0) & (cell < res)).all(axis=1)].astype(np.int64)
    out[tuple(cell.T)] = True
    return out


def test_occupancy_equals_the_plain_formulas(recon):
    """Testing only the cells around the object gives exactly the occupancy of testing every cell: on the
    fixture's grids (view and canonical maps of their own cameras) and on random blobs under random
    rotations, scales and shifts, some reaching past the target grid."""
    from scipy.spatial.transform import Rotation

    from carvi_torch.export.objects import _centre_hits

    rng = np.random.default_rng(1)
    grids = []
    for p in sorted(recon.glob("*/voxels/*.npz"))[:3]:
        z = np.load(p)
        grids.append((z["occupancy"].astype(bool), np.asarray(z["voxel_to_canvas"], float)))
    for _ in range(6):
        occ = ndimage.gaussian_filter(rng.random((20, 18, 22)), 2.0) > 0.52
        M = np.eye(4)
        M[:3, :3] = Rotation.random(random_state=rng).as_matrix() * rng.uniform(0.5, 3.0)
        M[:3, 3] = rng.uniform(-20, 60, 3)
        grids.append((occ, M))
    for occ, M in grids:
        lo, hi = np.argwhere(occ).min(axis=0).astype(float), np.argwhere(occ).max(axis=0).astype(float)
        for res in (8, 16):
            v2t = M * np.r_[[res / 64] * 3, 1.0][:, None]
            assert np.array_equal(splat_occupancy(occ, v2t, res), _splat_reference(occ, v2t, res))
            centres = np.zeros((res, res, res), bool)  # the centre test alone (the sub-samples hide its edges)
            _centre_hits(occ, v2t[:3, :3], v2t[:3, 3], res, lo, hi, centres)
            assert np.array_equal(centres, _centre_reference(occ, v2t[:3, :3], v2t[:3, 3], res))
    empty = np.zeros((5, 5, 5), bool)
    assert not splat_occupancy(empty, np.eye(4), 4).any()


def test_surface_samples_equal_numpys_cross_and_norm(recon):
    """The coordinate-major sampler returns what ``np.cross`` / ``np.linalg.norm`` give, bit for bit."""
    from carvi_torch.export.objects import sample_surface

    for v, f in _recon_meshes(recon, 2):
        tri = v[f]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        area2 = np.linalg.norm(cross, axis=1)
        rng = np.random.default_rng(5)
        cum = np.cumsum(area2)
        fidx = np.minimum(np.searchsorted(cum, rng.random(300) * cum[-1], side="right"), len(f) - 1)
        r1, r2 = np.sqrt(rng.random(300)), rng.random(300)
        w = np.stack([1 - r1, r1 * (1 - r2), r1 * r2], axis=1)
        want = (np.einsum("pk,pkc->pc", w, tri[fidx]), cross[fidx] / np.maximum(area2[fidx], 1e-300)[:, None])
        got = sample_surface(v, f, 300, np.random.default_rng(5))
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def test_worker_processes_write_the_same_store(recon, tmp_path):
    """With worker processes (one stream of jobs over both classes, written as the results come) the
    store holds the same samples in the same order as without, a broken object's reason in the same
    place; the workers' module imports neither torch nor kornia."""
    import zarr

    broken = tmp_path / "recon"
    shutil.copytree(recon, broken)
    mesh = sorted((broken / "car" / "meshes").glob("*.ply"))[1]
    mesh.write_bytes(mesh.read_bytes()[:60])  # a partial file: skipped by the worker, with its reason
    kw = dict(resolution=8, points=32, shard_size=2, progress=False, mesh=True)
    one = export(broken, tmp_path / "w0", workers=0, **kw)
    two = export(broken, tmp_path / "w2", workers=2, **kw)
    assert one["samples"] == two["samples"] and one["skipped"] == two["skipped"] and len(one["skipped"]) == 1
    a, b = zarr.open_group(str(tmp_path / "w0"), mode="r"), zarr.open_group(str(tmp_path / "w2"), mode="r")
    for c in one["classes"]:
        assert dict(a[c].attrs) == dict(b[c].attrs)
        for name in a[c].array_keys():
            assert np.array_equal(a[c][name][...], b[c][name][...], equal_nan=True), (c, name)
    code = ("import sys, carvi_torch.export.command as c, carvi_torch.export.objects as o; "
            "assert c.WORKER_MODULE == o.__name__; "
            "print(sorted(m for m in ('torch', 'kornia', 'zarr') if m in sys.modules))")
    # a real process (the fork server has torch imported already)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.returncode == 0 and res.stdout.strip() == "[]", res.stderr[-2000:]


@pytest.mark.parametrize("stored", ["abc", "xyz", np.array(["xyz"]), np.bytes_(b"xyz"), None],
                         ids=["same", "other", "a-list", "bytes", "none"])
def test_export_and_resume_read_a_voxels_fingerprint_by_one_rule(stored, tmp_path):
    """The export refuses an object exactly where a rerun of reconstruct would find other inputs: both read
    the fingerprint a voxels file holds the same way (one not written as the writers write it is none)."""
    from carvi_torch.export.objects import OtherInputs, export_object
    from carvi_torch.io.layout import INPUTS_CHANGED, finished, object_file

    members = {"occupancy": np.ones((2, 2, 2), bool), "voxel_to_camera": np.eye(4)}
    if stored is not None:
        members["input_fingerprint"] = np.asarray(stored, dtype=str) if isinstance(stored, str) else stored
    voxels = object_file(tmp_path, "voxels", 1)
    voxels.parent.mkdir()
    np.savez(voxels, **members)
    mesh = object_file(tmp_path, "meshes", 1, "ply")
    mesh.parent.mkdir()
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], process=False).export(mesh)
    try:
        export_object({"voxels": voxels, "fingerprint": "abc", "canvas_scale": 1.0, "canvas_offset": [0.0, 0.0]})
        refused = False
    except OtherInputs:
        refused = True
    except KeyError:  # past the check: the rest of the job is not given
        refused = False
    assert refused == (finished(tmp_path, 1, "ply", "abc") == INPUTS_CHANGED) == (isinstance(stored, str)
                                                                                   and stored == "xyz")


def _files(folder):
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_an_interrupted_export_leaves_the_earlier_one_intact(recon, tmp_path, monkeypatch, capsys):
    """Ctrl-C during a re-export (after some shards are written): exit 130, one line, and the earlier export
    byte for byte as it was, every sample readable; no hidden folder is left behind."""
    from carvi_torch.export import store

    out = tmp_path / "exp"
    args = ["--recon", str(recon), "--out", str(out), "--resolution", "4", "--points", "8", "--workers", "0",
            "--quiet"]
    assert export_main(args) == 0
    before = _files(out)
    n = len(LiftedDataset(out))
    added, real_add = [], store._ClassArrays.add

    def add(self, sample, meta):  # the interrupt arrives when two shards of one sample are written
        added.append(meta["annotation_id"])
        if len(added) == 3:
            raise KeyboardInterrupt
        real_add(self, sample, meta)

    monkeypatch.setattr(store._ClassArrays, "add", add)
    capsys.readouterr()
    assert export_main(args + ["--shard-size", "1", "--mesh"]) == 130
    assert capsys.readouterr().err.strip().splitlines() == [f"interrupted; {out} is as it was before the export"]
    assert _files(out) == before
    ds = LiftedDataset(out)
    assert len(ds) == n and float(ds[n - 1]["canvas_scale"]) > 0
    # interrupted into a new folder: the folder is not left behind
    added.clear()
    assert export_main(args[:2] + ["--out", str(tmp_path / "new" / "exp")] + args[4:]) == 130
    assert not (tmp_path / "new" / "exp").exists()


def test_ctrl_c_during_the_swap_says_the_new_store_is_complete(recon, tmp_path, monkeypatch, capsys):
    """Ctrl-C while the finished store is swapped in (held back until the swap is done): exit 130, the new
    store in place and readable, nothing removed, and the line says so rather than 'as it was'."""
    import signal
    import types

    from carvi_torch.export import store

    out = tmp_path / "exp"
    args = ["--recon", str(recon), "--out", str(out), "--points", "8", "--workers", "0", "--quiet"]
    assert export_main(args + ["--resolution", "4"]) == 0

    def rmtree(p, *a, **k):  # the last step of the swap removes the earlier store
        if store.OLD_PREFIX in str(p):
            signal.raise_signal(signal.SIGINT)
        return shutil.rmtree(p, *a, **k)

    monkeypatch.setattr(store, "shutil", types.SimpleNamespace(rmtree=rmtree))
    capsys.readouterr()
    assert export_main(args + ["--resolution", "6"]) == 130
    said = capsys.readouterr()
    err = said.err.strip().splitlines()
    assert said.out.startswith("exported ") and f" to {out} " in said.out, said.out
    assert err == [f"interrupted after the export finished; {out} holds the new store, complete"], err
    assert _store_attrs(out)["resolution"] == 6 and sorted(p.name for p in out.iterdir()) == ["car", "chair",
                                                                                               "zarr.json"]
    assert LiftedDataset(out)[0]["occupancy_view"].shape[-1] == 6


def test_ctrl_c_while_the_store_is_made_leaves_no_folder_behind(recon, tmp_path, monkeypatch, capsys):
    """Ctrl-C while the new store's group is made, and an export refused after ``--out`` was made: the folders
    the export made (``--out`` and its new parents) are gone, and those it did not make are kept."""
    import signal

    from carvi_torch.export import store

    real = store.zarr.open_group

    def open_group(*a, **k):
        group = real(*a, **k)
        signal.raise_signal(signal.SIGINT)
        return group

    args = ["--recon", str(recon), "--resolution", "4", "--points", "8", "--workers", "0", "--quiet"]
    (tmp_path / "kept").mkdir()
    assert export_main(args + ["--out", str(tmp_path / "kept" / "a" / "b"), "--classes", "nosuch"]) == 2
    monkeypatch.setattr(store.zarr, "open_group", open_group)
    assert export_main(args + ["--out", str(tmp_path / "kept" / "x" / "y")]) == 130
    assert list((tmp_path / "kept").iterdir()) == []


def test_camera_only_and_unfinished_runs_are_said_so(recon, tmp_path, capsys):
    """A camera-only run: one error line, exit 2, nothing written. An unfinished run (no totals in
    summary.json): its finished objects exported, the others in one warning line; --quiet prints no
    per-object line."""
    import yaml

    cams = tmp_path / "cams"
    shutil.copytree(recon, cams)
    cfg = yaml.safe_load((cams / "config.yaml").read_text())
    cfg["stage"] = "cameras"
    (cams / "config.yaml").write_text(yaml.safe_dump(cfg))
    args = ["--resolution", "4", "--points", "8", "--workers", "0", "--quiet"]
    capsys.readouterr()
    assert export_main(["--recon", str(cams), "--out", str(tmp_path / "e1")] + args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and "camera-only" in err[0]
    assert not (tmp_path / "e1").exists()

    part = tmp_path / "part"
    shutil.copytree(recon, part)
    summary = json.loads((part / "summary.json").read_text())
    del summary["total_seconds"]
    (part / "summary.json").write_text(json.dumps(summary))
    gone = sorted((part / "car" / "voxels").glob("*.npz"))[:2]
    for p in gone:
        p.unlink()
    assert export_main(["--recon", str(part), "--out", str(tmp_path / "e2")] + args) == 0
    cap = capsys.readouterr()
    warn = [line for line in cap.err.splitlines() if line.strip()]
    assert len(warn) == 1 and "unfinished run" in warn[0] and " 2 not reconstructed yet" in warn[0], cap.err
    assert "skipped:" not in cap.out
    attrs = json.loads((tmp_path / "e2" / "zarr.json").read_text())["attributes"]["carvi_export"]
    assert sorted(s["annotation_id"] for s in attrs["skipped"]) == sorted(int(p.stem) for p in gone)
    assert {s["reason"] for s in attrs["skipped"]} == {"not reconstructed yet (the run is unfinished)"}
    # nothing finished at all: an error, nothing written
    shutil.rmtree(part / "car")
    shutil.rmtree(part / "chair")
    assert export_main(["--recon", str(part), "--out", str(tmp_path / "e3")] + args) == 2
    assert "no object reconstructed yet" in capsys.readouterr().err
    assert not (tmp_path / "e3").exists()


def test_export_workers_ignore_ctrl_c():
    """Ctrl-C reaches the whole process group; an export worker ignores it (the export stops its pool and
    prints one line) instead of dying with a traceback of its own."""
    import multiprocessing as mp
    import os
    import signal
    import time

    from carvi_torch.export.objects import init_worker
    from carvi_torch.runtime import LeanProcessPool, start_method

    pool = LeanProcessPool(1, mp_context=mp.get_context(start_method()), initializer=init_worker,
                           initargs=(os.getpid(),))
    try:
        pid = pool.submit(os.getpid).result(timeout=60)
        os.kill(pid, signal.SIGINT)
        time.sleep(0.2)
        assert pool.submit(os.getpid).result(timeout=60) == pid
    finally:
        pool.shutdown()


#: A child process that exports ``argv[1]`` into ``argv[2]`` with two worker processes and stops for good at
#: the first sample it is to write (after touching ``argv[3]``): the workers are running by then.
_STALLED_EXPORT = """
import sys, time, pathlib
from carvi_torch.export import run as export_run

def stall(self, cls, sample, meta):
    pathlib.Path(sys.argv[3]).touch()
    time.sleep(600)

export_run.StoreWriter.add = stall
export_run.export(sys.argv[1], sys.argv[2], resolution=4, points=8, progress=False, workers=2)
"""


def test_a_killed_export_leaves_no_process_running(recon, tmp_path):
    """SIGKILL of the export while its worker processes are up: they (and the forkserver) notice and exit."""
    import os
    import signal
    import time
    import uuid

    from carvi_torch.runtime import gone_within, processes_marked

    marker, started = uuid.uuid4().hex, tmp_path / "started"
    proc = subprocess.Popen([sys.executable, "-c", _STALLED_EXPORT, str(recon), str(tmp_path / "out"), str(started)],
                            env=dict(os.environ, CARVI_TEST_MARKER=marker), stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while not started.exists() and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        ended = proc.poll() is not None
        assert started.exists(), f"the export never reached its first sample: {proc.stderr.read() if ended else ''}"
        assert len(processes_marked(marker)) >= 3  # the export, the forkserver, workers
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    left = gone_within(marker, 15.0)
    assert not left, f"processes of the killed export still running: {left}"


def _store_attrs(out) -> dict:
    return json.loads((out / "zarr.json").read_text())["attributes"]["carvi_export"]


def _run_copy(recon, dest, finished: bool = True):
    """A copy of ``recon`` that reads its own ``input/annotations.json`` (returned with the file's contents);
    ``finished=False``: as a run interrupted before its totals were written."""
    shutil.copytree(recon, dest)
    summary = json.loads((dest / "summary.json").read_text())
    summary["data"] = str(dest / "input" / "annotations.json")
    if not finished:
        del summary["total_seconds"]
    (dest / "summary.json").write_text(json.dumps(summary))
    return json.loads((dest / "input" / "annotations.json").read_text())


def test_an_unfinished_run_counts_every_object_it_has_not_reconstructed(recon, tmp_path, capsys):
    """A run killed after some car meshes and before chair started: every object of the run's classes without
    finished files is counted, per class, chair named as not started, and listed in the store (the
    annotation file's other classes, outside the run's ``classes``, are not)."""
    part = tmp_path / "part"
    data = _run_copy(recon, part, finished=False)
    shutil.rmtree(part / "chair")
    gone = sorted((part / "car" / "voxels").glob("*.npz"))[:2]
    for p in gone:
        p.unlink()
    cat_of = {c["id"]: c["name"] for c in data["categories"]}
    ids = {c: sorted(a["id"] for a in data["annotations"] if cat_of[a["category_id"]] == c) for c in ("car", "chair")}
    capsys.readouterr()
    assert export_main(["--recon", str(part), "--out", str(tmp_path / "e"), "--resolution", "4", "--points", "8",
                        "--workers", "0", "--quiet"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and "exported the 3 object(s) it finished; 7 not reconstructed yet are left out: car 2, " \
                              "chair 5 (not started)" in err[0], err
    attrs = _store_attrs(tmp_path / "e")
    assert attrs["classes"] == ["car", "chair"] and attrs["counts"] == {"car": len(ids["car"]) - 2, "chair": 0}
    assert {s["reason"] for s in attrs["skipped"]} == {"not reconstructed yet (the run is unfinished)"}
    assert sorted(s["annotation_id"] for s in attrs["skipped"] if s["class"] == "car") == [int(p.stem) for p in gone]
    assert sorted(s["annotation_id"] for s in attrs["skipped"] if s["class"] == "chair") == ids["chair"]
    assert LiftedDataset(tmp_path / "e", fields=["quality"]).class_names == ["car", "chair"]


def test_an_unknown_class_is_refused_and_nothing_written(recon, tmp_path, capsys):
    """``--classes`` naming a class the run does not have (a typo, another case, a class of the annotation file
    the run left out): one error line naming it and the run's classes, exit 2, nothing written."""
    args = ["--recon", str(recon), "--resolution", "4", "--points", "8", "--workers", "0", "--quiet"]
    capsys.readouterr()
    for i, (asked, fmt) in enumerate([("bogus", "zarr"), ("Car", "zarr"), ("car,bogus", "zarr"), ("bottle", "zarr"),
                                      ("bogus", "ucmr")]):
        out = tmp_path / f"e{i}"
        assert export_main(args + ["--out", str(out), "--classes", asked, "--format", fmt]) == 2, asked
        err = capsys.readouterr().err.strip().splitlines()
        wrong = asked.split(",")[-1]
        assert len(err) == 1 and err[0].startswith("error: --classes:") and repr(wrong) in err[0], err
        assert "(its classes: car, chair;" in err[0] and not out.exists()
    assert export_main(args + ["--out", str(tmp_path / "ok"), "--classes", "chair"]) == 0
    assert _store_attrs(tmp_path / "ok")["classes"] == ["chair"]


def test_objects_skipped_at_load_are_listed_with_their_reason(recon, tmp_path):
    """Objects the annotations no longer let through (flagged crowd, no visible keypoint) are in the store's
    ``skipped`` list with the reason the load gives (as summary.json's failures), beside those exported."""
    run = tmp_path / "run"
    data = _run_copy(recon, run)
    cars = [a for a in data["annotations"] if a["category_id"] == next(c["id"] for c in data["categories"]
                                                                       if c["name"] == "car")]
    cars[0]["iscrowd"] = 1
    cars[1]["keypoints"] = [0] * len(cars[1]["keypoints"])
    (run / "input" / "annotations.json").write_text(json.dumps(data))
    loaded = load_coco(run / "input" / "annotations.json", canvas_size=64, classes=["car", "chair"])
    expected = sorted((p.annotation_id, p.reason) for p in loaded.problems if p.fatal)
    assert [aid for aid, _ in expected] == sorted([cars[0]["id"], cars[1]["id"]])
    index = export(run, tmp_path / "e", resolution=4, points=8, progress=False, workers=0)
    assert sorted((s["annotation_id"], s["reason"]) for s in index["skipped"]) == expected
    assert {s["class"] for s in index["skipped"]} == {"car"} and len(index["samples"]) == 10 - 2


def _grid_to_canvas(step, origin):
    """``(4, 4)`` voxel ``(d, h, w)`` -> canvas ``(x, y, z)`` of a grid aligned with the camera (as carving's)."""
    M = np.zeros((4, 4))
    M[0, 2] = M[1, 1] = M[2, 0] = step
    M[:3, 3] = origin
    M[3, 3] = 1.0
    return M


def test_view_grid_holds_an_object_deeper_than_the_canvas():
    """A box seen end-on, 196 canvas pixels deep on a 128 canvas (cars seen from the front reach 207): every
    vertex and surface point of its mesh (the voxel boxes' outer faces) lies inside the view grid and in its
    occupied cells (one-cell dilated: a face on a cell boundary), the cells deepen only as much as needed
    (the end layers stay empty, every other layer is occupied),
    and the depth map stays within float16's 1/32 pixel. The cubic grid of the format's first release,
    centred on the mean vertex depth, leaves about a third of the vertices outside."""
    from carvi_torch.export.objects import depth_map, surface_voxel_indices, view_depth_frame, view_occupancy

    C, res, step = 128, 32, 3.5
    occ = np.zeros((60, 40, 40), bool)
    occ[2:58, 15:25, 17:23] = True  # 56 voxels deep (196 px), 10 x 6 across
    v2c = _grid_to_canvas(step, [64.0 - 20 * step, 64.0 - 20 * step, 40.0])
    lo, hi = np.array([2, 15, 17]) - 0.5, np.array([57, 24, 22]) + 0.5  # the box in voxel indices (d, h, w)
    corners = np.stack(np.meshgrid(*zip(lo, hi), indexing="ij"), -1).reshape(-1, 3)
    box = trimesh.convex.convex_hull(corners @ v2c[:3, :3].T + v2c[:3, 3])  # canvas (x, y, z)
    box = box.subdivide().subdivide()  # vertices along its faces, not only its corners
    pts = np.concatenate([box.vertices, box.sample(3000, seed=0)])
    zc, dz = view_depth_frame(surface_voxel_indices(occ), v2c, C, res)
    z0, z1 = box.vertices[:, 2].min(), box.vertices[:, 2].max()
    assert np.isclose(zc, (z0 + z1) / 2) and np.isclose(dz, (z1 - z0) / (res - 2))  # a cell to spare each end
    got = view_occupancy(occ, v2c, C, res, zc, cell_depth=dz)

    def cells(p, centre, cell):
        return np.floor(np.stack([(p[:, 2] - centre) / cell + res / 2, (p[:, 1] + 0.5) * res / C,
                                  (p[:, 0] + 0.5) * res / C], 1)).astype(int)

    c = cells(pts, zc, dz)
    assert ((c >= 0) & (c < res)).all()  # 100% of the mesh is inside the grid
    dil = ndimage.binary_dilation(got, np.ones((3, 3, 3)))
    assert dil[c[:, 0], c[:, 1], c[:, 2]].all()
    assert got[0].sum() == 0 and got[-1].sum() == 0 and got[1:-1].any(axis=(1, 2)).all()  # spans, whole
    old = cells(box.vertices, box.vertices[:, 2].mean(), C / res)  # the cubic grid on the mean vertex depth
    assert ((old[:, 0] < 0) | (old[:, 0] >= res)).mean() > 0.2
    depth = depth_map(box.vertices, box.faces, C, zc)
    hit = np.isfinite(depth)
    assert hit.sum() == 10 * 6 * step * step  # the box's end face, 35 x 21 pixel centres
    assert np.allclose(depth[hit], z0 - zc)  # the near face, 98 pixels before the centre
    assert 64 < abs(z0 - zc) < 128  # float16 spacing 2^-4 there: stored within 2^-5 pixel
    assert np.abs(depth[hit].astype(np.float16).astype(np.float64) - (z0 - zc)).max() <= 2.0 ** -5


def test_view_grid_cell_mapping_equals_a_brute_force_reference():
    """On a tiny grid whose voxel boxes meet the cell boundaries (2 voxels per cell in depth, 1 across), the
    view occupancy equals looping over every cell and every occupied voxel and testing whether their boxes
    overlap, each cell's box taken from the documented formula (x, y: ``[j C/res - 0.5, (j + 1) C/res -
    0.5)``; depth: ``[zc + (j - res/2) dz, zc + (j + 1 - res/2) dz)``)."""
    from carvi_torch.export.objects import view_occupancy

    C, res, zc, dz = 16, 8, 29.5, 6.0
    rng = np.random.default_rng(3)
    occ = rng.random((10, 7, 8)) < 0.15
    v2c = _grid_to_canvas(1.0, [0, 0, 0]) * np.r_[2.0, 2.0, 3.0, 1.0][:, None]  # x = 2w + 0.5, ...
    v2c[:3, 3] = [0.5, 0.5, 7.0]  # ... y = 2h + 0.5, z = 3d + 7
    want = np.zeros((res, res, res), bool)
    for d, h, w in np.argwhere(occ):
        vox = [(2 * w - 0.5, 2 * w + 1.5), (2 * h - 0.5, 2 * h + 1.5), (3 * d + 5.5, 3 * d + 8.5)]  # x, y, z
        for j0 in range(res):
            for j1 in range(res):
                for j2 in range(res):
                    cell = [(j2 * C / res - 0.5, (j2 + 1) * C / res - 0.5),
                            (j1 * C / res - 0.5, (j1 + 1) * C / res - 0.5),
                            (zc + (j0 - res / 2) * dz, zc + (j0 + 1 - res / 2) * dz)]
                    if all(min(a[1], b[1]) - max(a[0], b[0]) > 1e-9 for a, b in zip(vox, cell)):
                        want[j0, j1, j2] = True
    got = view_occupancy(occ, v2c, C, res, zc, cell_depth=dz)
    assert want.sum() > 10 and np.array_equal(got, want)
    assert not np.array_equal(view_occupancy(occ, v2c, C, res, zc), want)  # cubic cells map elsewhere


def test_a_run_done_in_parts_exports_every_part(recon, tmp_path, capsys):
    """A run made in parts into one ``--out`` (``classes=[chair]``, then ``classes=[car]``) keeps only the last
    part's setting in ``config.yaml``: the export still covers every class the run has cameras for, in the store
    and in the cmr files, and ``--classes chair`` is one of the run's classes."""
    run = tmp_path / "run"
    _run_copy(recon, run)
    cfg = run / "config.yaml"
    text = cfg.read_text()
    assert "classes: [car, chair]" in text
    cfg.write_text(text.replace("classes: [car, chair]", "classes: [car]"))
    args = ["--recon", str(run), "--resolution", "4", "--points", "8", "--workers", "0", "--quiet"]
    assert export_main(args + ["--out", str(tmp_path / "all")]) == 0
    assert _store_attrs(tmp_path / "all")["classes"] == ["car", "chair"]
    assert export_main(args + ["--out", str(tmp_path / "chair"), "--classes", "chair"]) == 0
    assert _store_attrs(tmp_path / "chair")["classes"] == ["chair"]
    assert export_main(args + ["--out", str(tmp_path / "cmr"), "--format", "cmr"]) == 0
    assert sorted(p.name for p in (tmp_path / "cmr").glob("*.mat")) == ["car.mat", "chair.mat"]


def test_a_leftover_folder_with_this_process_id_does_not_block_the_export(recon, tmp_path):
    """A killed export's hidden folders are removed by the next export into the same ``--out``, also where the
    next export runs under the same process id (a container's fixed pid): that folder cannot be its own yet."""
    import os

    from carvi_torch.export.store import OLD_PREFIX, PARTIAL_PREFIX

    out = tmp_path / "e"
    args = ["--recon", str(recon), "--resolution", "4", "--points", "8", "--workers", "0", "--quiet",
            "--classes", "car", "--out", str(out)]
    assert export_main(args) == 0
    for prefix in (OLD_PREFIX, PARTIAL_PREFIX):
        (out / f"{prefix}{os.getpid()}" / "car").mkdir(parents=True)
    assert export_main(args) == 0
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".carvi")) == []
    assert _store_attrs(out)["classes"] == ["car"]


def test_settings_out_of_range_are_refused_and_an_earlier_export_kept(recon, tmp_path, capsys):
    """A setting out of range (a negative seed, a grid of 0 or 3000 cells a side, no points, no shard, negative
    workers) is one ``error:`` line naming the option, exit 2, and the earlier export stays as it was."""
    out = tmp_path / "exp"
    base = ["--recon", str(recon), "--out", str(out), "--workers", "0", "--quiet", "--classes", "chair"]
    assert export_main(base + ["--resolution", "4", "--points", "8"]) == 0
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()
    for option, value in [("--seed", "-1"), ("--resolution", "0"), ("--resolution", "1"), ("--resolution", "3000"),
                          ("--points", "0"), ("--points", "-5"), ("--shard-size", "0"), ("--workers", "-1")]:
        args = base + ["--resolution", "4", "--points", "8", option, value]
        assert export_main(args) == 2, (option, value)
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"error: {option} must be ") and err[0].endswith(
            "(nothing was written)"), err
        assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before, (option, value)
    with pytest.raises(ValueError, match="points must be an integer >= 1"):
        export(recon, tmp_path / "api", points=0, progress=False, workers=0)
    assert not (tmp_path / "api").exists()


def test_a_run_with_no_exportable_object_keeps_the_earlier_export(recon, tmp_path, capsys):
    """When every object of the run fails (here: every mesh cut short), no empty store replaces the earlier
    export: one ``error:`` line with the first reason, exit 2."""
    broken = tmp_path / "recon"
    shutil.copytree(recon, broken)
    out = tmp_path / "exp"
    args = ["--recon", str(broken), "--out", str(out), "--resolution", "4", "--points", "8", "--workers", "0",
            "--quiet", "--classes", "chair"]
    assert export_main(args) == 0
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    for mesh in (broken / "chair" / "meshes").glob("*.ply"):
        mesh.write_bytes(mesh.read_bytes()[:50])
    capsys.readouterr()
    assert export_main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: none of the 5 object(s) could be exported") \
        and "unreadable outputs" in err[0] and err[0].endswith(f"{out} is as it was"), err
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_a_fault_of_the_export_itself_is_raised_not_reported_as_a_skip(recon, tmp_path, monkeypatch):
    """Only unreadable files make an object a skip; an error in the export's own computation surfaces."""
    from carvi_torch.export import objects

    def broken(*a, **k):
        raise TypeError("a fault in the export")

    monkeypatch.setattr(objects, "depth_map", broken)
    with pytest.raises(TypeError, match="a fault in the export"):
        export(recon, tmp_path / "e", resolution=4, points=8, progress=False, workers=0, classes=["chair"])
    assert not (tmp_path / "e").exists()


def test_items_carry_the_category_name_and_id_not_only_the_folder_key(recon, tmp_path):
    """A category whose name is no safe folder name ('my car 🚗') keeps its name and id through the export:
    the class group records them, and each item gives ``class_name`` (the name), ``class_key`` (the folder)
    and ``category_id``."""
    import zarr

    data = json.loads((recon / "input" / "annotations.json").read_text())
    keep = {c["id"] for c in data["categories"] if c["name"] == "car"}
    data["categories"] = [{**c, "name": "my car 🚗"} for c in data["categories"] if c["id"] in keep]
    data["annotations"] = [a for a in data["annotations"] if a["category_id"] in keep]
    ann = tmp_path / "ann.json"
    ann.write_text(json.dumps(data))
    run(Config().override({**TINY, "classes": None, "data": str(ann), "out": str(tmp_path / "r")}), workers=0)
    export(tmp_path / "r", tmp_path / "e", resolution=4, points=8, progress=False, workers=0)
    (cid,) = keep
    key = next(d.name for d in (tmp_path / "r").iterdir() if (d / "cameras.json").is_file())
    assert key != "my car 🚗"
    group = zarr.open_group(str(tmp_path / "e"), mode="r")[key]
    assert group.attrs["category_name"] == "my car 🚗" and group.attrs["category_id"] == cid
    ds = LiftedDataset(tmp_path / "e", fields=["quality"])
    assert len(ds) > 0 and ds.class_names == [key]
    assert {(it["class_name"], it["class_key"], it["category_id"]) for it in ds} == {("my car 🚗", key, str(cid))}
    batch = collate_lifted([ds[0], ds[0]])
    assert batch["class_name"] == ["my car 🚗"] * 2 and batch["category_id"] == [str(cid)] * 2


def test_export_help_gives_defaults_and_says_which_options_are_the_stores():
    """``--help`` names every default and marks the options that only the zarr store takes (``--format cmr`` and
    ``ucmr`` read ``--recon``, ``--out`` and ``--classes`` alone)."""
    from carvi_torch.export.command import parser

    ap = parser()
    text = " ".join(ap.format_help().split())
    assert "seed of the surface sampling (default 0)" in text
    for action in ap._actions:
        if action.dest in ("resolution", "points", "shard_size", "mesh", "workers", "seed"):
            assert action.help.startswith("zarr: "), action.dest
    assert "cmr" in next(a.help for a in ap._actions if a.dest == "out")


def test_cmr_says_it_ignores_the_zarr_stores_options(recon, tmp_path, capsys):
    """``--format cmr`` with options that only the zarr store takes (``--mesh``, ``--resolution``, ...) writes its
    files and says in one warning line which options it ignored, rather than dropping them unsaid."""
    out = tmp_path / "cmr"
    capsys.readouterr()
    assert export_main(["--recon", str(recon), "--out", str(out), "--format", "cmr", "--mesh", "--resolution", "64",
                        "--quiet"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["warning: --resolution, --mesh: for --format zarr only, ignored: --format cmr writes the cameras "
                   "and mean shape alone"]
    assert any(out.glob("*.mat"))
    assert export_main(["--recon", str(recon), "--out", str(tmp_path / "cmr2"), "--format", "cmr", "--quiet"]) == 0
    assert "warning" not in capsys.readouterr().err


def test_surface_voxels_equal_a_loop_over_the_neighbours():
    """The surface voxels (an empty or outside 6-neighbour) against a loop over every voxel, on random grids
    from sparse to full and one voxel thick."""
    from carvi_torch.export.objects import surface_voxel_indices

    rng = np.random.default_rng(3)
    steps = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    for p, shape in [(0.3, (6, 7, 5)), (0.8, (9, 9, 9)), (1.0, (4, 5, 6)), (0.7, (1, 6, 6))]:
        occ = rng.random(shape) < p
        want = []
        for d, h, w in np.argwhere(occ):
            around = [(d + a, h + b, w + c) for a, b, c in steps]
            if any(not all(0 <= i < n for i, n in zip(q, shape)) or not occ[q] for q in around):
                want.append((d, h, w))
        np.testing.assert_array_equal(surface_voxel_indices(occ), np.asarray(want, np.float32).reshape(-1, 3))


# --------------------------------------------------------------------------- bad inputs: skipped or refused, named

_SMALL = ["--resolution", "4", "--points", "8", "--workers", "0"]


def _reasons(out) -> dict:
    return {(s["class"], s["annotation_id"]): s["reason"] for s in _store_attrs(out)["skipped"]}


def _rewrite_npz(path, **members):
    z = dict(np.load(path))
    z.update(members)
    np.savez(path, **z)


def _ids(data, cls) -> list:
    cid = next(c["id"] for c in data["categories"] if c["name"] == cls)
    return sorted(a["id"] for a in data["annotations"] if a["category_id"] == cid)


def test_voxels_and_meshes_that_open_but_hold_bad_data_are_skipped_with_a_reason(recon, tmp_path, capsys):
    """A voxels file whose transform is cut to 3 x 3, whose occupancy is all empty or of zero size, and a mesh with
    a face index past its vertices: each object skipped with a one-line reason naming it, the rest exported."""
    from carvi_torch.mesh import read_mesh_arrays as load_mesh

    run = tmp_path / "run"
    _run_copy(recon, run)
    vox = sorted((run / "car" / "voxels").glob("*.npz"), key=lambda p: int(p.stem))
    _rewrite_npz(vox[0], voxel_to_canvas=np.load(vox[0])["voxel_to_canvas"][:3, :3])
    _rewrite_npz(vox[1], occupancy=np.zeros_like(np.load(vox[1])["occupancy"]))
    _rewrite_npz(vox[2], occupancy=np.zeros((0, 0, 0), bool))
    mesh = run / "car" / "meshes" / f"{vox[3].stem}.ply"
    m = trimesh.load(mesh, force="mesh", process=False)
    faces = m.faces.copy()
    faces[0, 0] = len(m.vertices) + 5
    mesh.write_bytes(trimesh.exchange.ply.export_ply(trimesh.Trimesh(m.vertices, faces, process=False)))
    capsys.readouterr()
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e")] + _SMALL) == 0
    said, reasons = capsys.readouterr().out, _reasons(tmp_path / "e")
    want = ["voxel_to_canvas of shape (3, 3) is not 4 x 4 finite numbers", "has no occupied voxel",
            "occupancy of shape (0, 0, 0) (bool) is not a 3-D grid", f"face index {len(m.vertices) + 5} is outside"]
    for p, why in zip(vox, want):
        reason = reasons[("car", int(p.stem))]
        assert reason.startswith("unreadable outputs: ") and why in reason, reason
        assert f"export: car annotation {p.stem} skipped: unreadable outputs" in said
    assert _store_attrs(tmp_path / "e")["counts"] == {"car": 1, "chair": 5}
    faces[0, 0] = -1  # a negative index wraps round in numpy: refused as well
    mesh.write_bytes(trimesh.exchange.ply.export_ply(trimesh.Trimesh(m.vertices, faces, process=False)))
    with pytest.raises(ValueError, match="face index -1 is outside"):
        load_mesh(mesh)


def test_each_voxels_file_is_opened_once_and_skips_keep_their_order(recon, tmp_path, monkeypatch):
    """Cars on another canvas, one without voxels and one with a cut mesh: the export opens each voxels file once
    (the worker checks the canvas as it reads the grid), and lists the class's skipped objects in annotation order:
    those skipped before any file is read (no voxels) first, then those a worker could not export (a cut mesh,
    another canvas); with worker processes too."""
    run = tmp_path / "run"
    _run_copy(recon, run)
    vox = sorted((run / "car" / "voxels").glob("*.npz"), key=lambda p: int(p.stem))
    mesh = run / "car" / "meshes" / f"{vox[0].stem}.ply"
    mesh.write_bytes(mesh.read_bytes()[:60])
    for p in (vox[1], vox[3]):
        _rewrite_npz(p, canvas_scale=np.load(p)["canvas_scale"] * 1.5)
    vox[2].unlink()
    opened, load = [], np.load
    monkeypatch.setattr(np, "load", lambda f, *a, **k: opened.append(str(f)) or load(f, *a, **k))
    one = export(run, tmp_path / "w0", resolution=4, points=8, progress=False, workers=0)
    monkeypatch.undo()
    assert sorted(opened) == sorted(str(p) for p in (vox[0], vox[1], vox[3], *vox[4:], *(run / "chair").glob(
        "voxels/*.npz"))), opened
    assert [(s["annotation_id"], s["reason"].split(" (")[0].split(":")[0]) for s in one["skipped"]] == [
        (int(vox[2].stem), "no voxels"), (int(vox[0].stem), "unreadable outputs"),
        (int(vox[1].stem), "carved on another canvas than config.yaml's"),
        (int(vox[3].stem), "carved on another canvas than config.yaml's")]
    two = export(run, tmp_path / "w2", resolution=4, points=8, progress=False, workers=2)
    assert two["skipped"] == one["skipped"] and two["samples"] == one["samples"] and len(one["samples"]) == 6


def test_an_unusable_camera_skips_its_object_naming_it_in_every_format(recon, tmp_path, capsys):
    """``R`` not 3 x 3, ``s`` a string or negative, ``t`` three numbers: the zarr store, cmr and ucmr skip that
    object with a reason naming it (class and annotation id) and export the rest."""
    import scipy.io

    run = tmp_path / "run"
    _run_copy(recon, run)
    path = run / "chair" / "cameras.json"
    cams = json.loads(path.read_text())
    ids = sorted(cams["cameras"], key=int)
    bad = {ids[0]: ("R", [[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]]), ids[1]: ("s", "abc"), ids[2]: ("s", -2.0),
           ids[3]: ("t", [1.0, 2.0, 3.0])}
    for aid, (key, value) in bad.items():
        cams["cameras"][aid]["refined"][key] = value
    path.write_text(json.dumps(cams))
    capsys.readouterr()
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e")] + _SMALL) == 0
    said, reasons = capsys.readouterr().out, _reasons(tmp_path / "e")
    for aid, (key, _) in bad.items():
        assert reasons[("chair", int(aid))].startswith(f"bad camera in cameras.json: {key} is "), reasons
        assert f"export: chair annotation {aid} skipped: bad camera in cameras.json: {key} is" in said
    assert _store_attrs(tmp_path / "e")["counts"] == {"car": 5, "chair": 1}
    for fmt in ("cmr", "ucmr"):
        assert export_main(["--recon", str(run), "--out", str(tmp_path / fmt), "--format", fmt]) == 0
        said = capsys.readouterr().out
        for aid, (key, _) in bad.items():
            assert f"export: chair annotation {aid} skipped: bad camera in cameras.json: {key} is" in said, said
        assert said.strip().splitlines()[-1].endswith("skipped 4")
    js = json.loads((tmp_path / "ucmr" / "chair.json").read_text())
    assert [str(r["annotation_id"]) for r in js["images"]] == [ids[4]]
    assert sorted(str(s["annotation_id"]) for s in js["skipped"]) == sorted(bad)
    mat = scipy.io.loadmat(tmp_path / "cmr" / "chair.mat", struct_as_record=False, squeeze_me=True)
    assert str(mat["annotation_ids"]) == ids[4] and sorted(mat["skipped_ids"]) == sorted(bad)


def test_a_re_export_refuses_a_folder_holding_the_users_own_files(recon, tmp_path, monkeypatch, capsys):
    """An earlier export with the user's files beside it (``NOTES.txt``, ``checkpoints/model.pt``) or inside a class
    group: refused with one error line naming the first, exit 2, everything kept; a file that appears while
    the export runs is kept too (the folder is checked again before the swap). The export alone is replaced."""
    from carvi_torch.export import store

    out = tmp_path / "exp"
    args = ["--recon", str(recon), "--out", str(out), "--quiet", "--classes", "chair"] + _SMALL
    assert export_main(args) == 0
    (out / "NOTES.txt").write_text("mine")
    (out / "checkpoints").mkdir()
    (out / "checkpoints" / "model.pt").write_bytes(b"weights")
    before = _files(out)
    capsys.readouterr()
    assert export_main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "'NOTES.txt' and 1 more" in err[0], err
    assert _files(out) == before
    (out / "NOTES.txt").unlink()
    shutil.rmtree(out / "checkpoints")
    (out / "chair" / "mine.txt").write_text("mine")
    assert export_main(args) == 2
    assert "'chair/mine.txt'" in capsys.readouterr().err and (out / "chair" / "mine.txt").read_text() == "mine"
    (out / "chair" / "mine.txt").unlink()
    real_add = store._ClassArrays.add

    def add(self, sample, meta):  # the user saves a file into --out while the export runs
        (out / "NOTES.txt").write_text("mine")
        real_add(self, sample, meta)

    monkeypatch.setattr(store._ClassArrays, "add", add)
    assert export_main(args) == 2
    assert "'NOTES.txt'" in capsys.readouterr().err and (out / "NOTES.txt").read_text() == "mine"
    assert sorted(p.name for p in out.iterdir()) == ["NOTES.txt", "chair", "zarr.json"]
    monkeypatch.undo()
    (out / "NOTES.txt").unlink()
    assert export_main(args) == 0 and len(LiftedDataset(out)) == 5


def test_a_finished_run_without_a_class_folder_lists_that_class_objects(recon, tmp_path, capsys):
    """``rm -r run/chair`` after the run finished: every chair object is listed as skipped with a reason (the zarr
    store and cmr), rather than the class vanishing; a class the run itself skipped gives summary.json's reason."""
    run = tmp_path / "run"
    data = _run_copy(recon, run)
    shutil.rmtree(run / "chair")
    capsys.readouterr()
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e")] + _SMALL) == 0
    said = capsys.readouterr().out
    reasons = _reasons(tmp_path / "e")
    assert sorted(aid for c, aid in reasons if c == "chair") == _ids(data, "chair")
    assert all(r == f"no cameras.json in {run / 'chair'} (the class folder was removed, or never written)"
               for (c, _), r in reasons.items() if c == "chair")
    assert said.strip().splitlines()[-1].endswith("skipped 5") and "export: chair annotation" in said
    assert _store_attrs(tmp_path / "e")["counts"] == {"car": 5}
    summary = json.loads((run / "summary.json").read_text())
    why = "class has 5 usable instance(s), fewer than min_instances=6"
    summary["classes"]["chair"].update(status="skipped", failures=[{"annotation_id": None, "source": None,
                                                                     "stage": "class", "reason": why}])
    (run / "summary.json").write_text(json.dumps(summary))
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e2"), "--quiet"] + _SMALL) == 0
    assert {r for (c, _), r in _reasons(tmp_path / "e2").items() if c == "chair"} == {
        f"the run skipped the class: {why}"}
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "cmr"), "--format", "cmr"]) == 0
    said = capsys.readouterr().out
    assert f"export: chair annotation {_ids(data, 'chair')[0]} skipped: the run skipped the class: {why}" in said
    assert said.strip().splitlines()[-1].endswith("skipped 5")


def test_cmr_and_ucmr_report_what_they_leave_out_and_box_the_annotation(recon, tmp_path, capsys):
    """The objects CMR and U-CMR files leave out (skipped at load, no camera) are reported as the zarr export
    reports them and listed in the files; the U-CMR ``bbox`` is the annotation's box (not the padded canvas),
    and ``err_sfm_reproj`` is normalised by that box's longer side, as the format documents."""
    import scipy.io

    run = tmp_path / "run"
    data = _run_copy(recon, run)
    cars = [a for a in data["annotations"] if a["id"] in _ids(data, "car")]
    cars[0]["iscrowd"] = 1
    (run / "input" / "annotations.json").write_text(json.dumps(data))
    cams = json.loads((run / "car" / "cameras.json").read_text())
    del cams["cameras"][str(cars[1]["id"])]
    (run / "car" / "cameras.json").write_text(json.dumps(cams))
    capsys.readouterr()
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "ucmr"), "--format", "ucmr"]) == 0
    said = capsys.readouterr().out
    assert f"export: car annotation {cars[0]['id']} skipped: " in said
    assert f"export: car annotation {cars[1]['id']} skipped: no camera in cameras.json" in said
    js = json.loads((tmp_path / "ucmr" / "car.json").read_text())
    assert sorted(s["annotation_id"] for s in js["skipped"]) == [cars[0]["id"], cars[1]["id"]]
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "cmr"), "--format", "cmr", "--quiet"]) == 0
    assert "export: 2 object(s) skipped" in capsys.readouterr().out
    m = scipy.io.loadmat(tmp_path / "cmr" / "car.mat", struct_as_record=False, squeeze_me=True)
    assert sorted(int(i) for i in m["skipped_ids"]) == [cars[0]["id"], cars[1]["id"]]
    coll = load_coco(run / "input" / "annotations.json", canvas_size=64, classes=["car"]).collections["car"]
    kp, vis = coll.keypoints_in_image().double().numpy(), coll.visible.numpy()
    by_id = {a["id"]: a for a in cars}
    assert len(js["images"]) == len(m["sfm_anno"]) == 3
    for rec, a, aid in zip(js["images"], m["sfm_anno"], m["annotation_ids"]):
        x, y, w, h = by_id[rec["annotation_id"]]["bbox"]
        assert rec["bbox"] == [x, y, x + w - 1, y + h - 1] and str(rec["annotation_id"]) == str(aid)
        i = coll.annotation_ids.index(rec["annotation_id"])
        proj = a.scale * m["S"].T @ a.rot[:2].T + a.trans - 1.0
        want = ((proj - kp[i]) ** 2).sum(axis=1)[vis[i]].sum() / (len(kp[i]) * max(w, h) ** 2)
        assert np.isclose(a.err_sfm_reproj, want, rtol=1e-9)


def test_camera_entries_of_no_annotated_object_are_reported(recon, tmp_path, capsys):
    """An entry of cameras.json whose id is no object of the annotation file: listed as skipped with the reason
    (store and U-CMR file), with one warning line counting such entries per class; the rest exported as before."""
    run = tmp_path / "run"
    _run_copy(recon, run)
    path = run / "car" / "cameras.json"
    cams = json.loads(path.read_text())
    cams["cameras"]["987654"] = next(iter(cams["cameras"].values()))
    path.write_text(json.dumps(cams))
    capsys.readouterr()
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e"), "--quiet"] + _SMALL) == 0
    err = capsys.readouterr().err.strip().splitlines()
    ann = run / "input" / "annotations.json"
    assert err == [f"warning: 1 camera(s) in cameras.json name no object of the annotation file {ann}: 1 of class "
                   "car (listed as skipped; was the run made from another file?)"], err
    assert _reasons(tmp_path / "e") == {
        ("car", 987654): f"in cameras.json but not an object of the annotation file {ann}"}
    assert _store_attrs(tmp_path / "e")["counts"] == {"car": 5, "chair": 5}
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "u"), "--format", "ucmr", "--quiet"]) == 0
    assert "1 of class car" in capsys.readouterr().err
    js = json.loads((tmp_path / "u" / "car.json").read_text())
    assert [s["annotation_id"] for s in js["skipped"]] == [987654] and len(js["images"]) == 5


def test_a_cameras_json_that_is_no_json_object_skips_its_class_in_every_format(recon, tmp_path, capsys):
    """A class whose ``cameras.json`` holds a JSON list: the zarr store and the ucmr files list every object of the
    class as skipped with the same reason naming the file, and export the other class."""
    run = tmp_path / "run"
    data = _run_copy(recon, run)
    path = run / "chair" / "cameras.json"
    path.write_text("[]")
    why = f"cameras.json unreadable: {path}: not a JSON object"
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e"), "--quiet"] + _SMALL) == 0
    assert _reasons(tmp_path / "e") == {("chair", aid): why for aid in _ids(data, "chair")}
    assert _store_attrs(tmp_path / "e")["counts"] == {"car": 5, "chair": 0}
    res = export_format(run, tmp_path / "u", "ucmr", progress=False)
    assert {(s["class"], s["annotation_id"]): s["reason"] for s in res["skipped"]} == _reasons(tmp_path / "e")
    assert [f.name for f in res["files"]] == ["car.json"] and res["objects"] == 5


def test_lifted_dataset_on_a_folder_without_a_store_says_what_to_do(recon, tmp_path):
    """A reconstruction run folder or an empty folder: a ValueError saying it is not a zarr export and how to
    write one (not zarr's GroupNotFoundError); a path that does not exist: FileNotFoundError, saying so."""
    (tmp_path / "empty").mkdir()
    for folder in (recon, tmp_path / "empty"):
        with pytest.raises(ValueError, match=r"not a zarr export .*write one with python -m carvi_torch.export"):
            LiftedDataset(folder)
    with pytest.raises(FileNotFoundError, match="no such export"):
        LiftedDataset(tmp_path / "nowhere")


def _as_older_files(run) -> None:
    """The voxels files of the run folder ``run`` as an older run wrote them: without the settings each object was
    made with (so the folder's record in summary.json stands for them)."""
    from carvi_torch.io.layout import SETTINGS_MEMBER

    for path in run.glob("*/voxels/*.npz"):
        with np.load(path) as z:
            members = {k: z[k] for k in z.files if k != SETTINGS_MEMBER}
        np.savez(path, **members)


def test_objects_made_with_other_settings_are_said_and_recorded_in_the_store(recon, tmp_path, capsys):
    """A run folder whose objects were made with other settings than its config.yaml's (summary.json's
    ``resumed_from_other_settings``), and whose voxels files do not record each object's (an older run's): the zarr
    export records the folder's record in the store's ``made_with_other_settings``, marks every object as not made
    with the run's settings, and every format warns in one line naming each setting's values; a folder without the
    record says nothing (tests/test_resume_settings.py: objects that record their settings)."""
    run = tmp_path / "run"
    _run_copy(recon, run)
    _as_older_files(run)
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "same"), "--quiet"] + _SMALL) == 0
    assert _store_attrs(tmp_path / "same")["made_with_other_settings"] == {}
    assert "other settings" not in capsys.readouterr().err
    assert LiftedDataset(tmp_path / "same").made_with_run_settings.all()
    summary = json.loads((run / "summary.json").read_text())
    summary["resumed_from_other_settings"] = {"carve.resolution": [16, 24], "selection.proposals": [5, 10, 10],
                                              "note": ["two\nlines", "one"]}  # a hand-edited record stays one line
    (run / "summary.json").write_text(json.dumps(summary))
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e"), "--quiet"] + _SMALL) == 0
    assert _store_attrs(tmp_path / "e")["made_with_other_settings"] == summary["resumed_from_other_settings"]
    with pytest.warns(UserWarning, match="carve.resolution 16 then 24; selection.proposals 5 then 10 then 10"):
        ds = LiftedDataset(tmp_path / "e")
    assert ds.attrs["made_with_other_settings"] == summary["resumed_from_other_settings"]
    assert len(ds) == 10 and not ds.made_with_run_settings.any()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert LiftedDataset(tmp_path / "same").attrs["made_with_other_settings"] == {}
    for args in ([], ["--format", "ucmr"]):
        if args:
            assert export_main(["--recon", str(run), "--out", str(tmp_path / "u"), "--quiet"] + args) == 0
        said = [line for line in capsys.readouterr().err.splitlines() if "other settings" in line]
        assert len(said) == 1 and ("carve.resolution 16 then 24; selection.proposals 5 then 10 then 10; note two lines "
                                   "then one") in said[0]


def test_a_hand_edited_settings_record_is_stored_and_said_safely(recon, tmp_path, capsys):
    """A summary.json record edited by hand (a name with a line break, NaN, a value nested 900 deep, a list of 40
    values, an empty list, a lone value): the export writes a store any JSON reader takes, warns on one line, and
    keeps only settings with two or more values, each plain or a short text."""
    from carvi_torch.io.layout import MOST_SETTINGS, settings_record

    deep: list = []
    for _ in range(900):
        deep = [deep]
    record = {"carve.resolution\nwarning: fake": [16, 24], "a": [float("nan"), 1], "b": [deep, 2],
              "c": list(range(40)), "d": [], "e": [24]}
    kept = settings_record(record)
    assert list(kept) == ["carve.resolution warning: fake", "a", "b", "c"]
    assert kept["a"] == ["nan", 1] and isinstance(kept["b"][0], str) and len(kept["b"][0]) <= 80
    assert len(kept["c"]) == MOST_SETTINGS and kept["c"][-1] == 39
    run = tmp_path / "run"
    _run_copy(recon, run)
    _as_older_files(run)
    summary = json.loads((run / "summary.json").read_text())
    (run / "summary.json").write_text(json.dumps({**summary, "resumed_from_other_settings": record}))
    capsys.readouterr()
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e"), "--quiet"] + _SMALL) == 0
    json.loads((tmp_path / "e" / "zarr.json").read_text(), parse_constant=lambda c: pytest.fail(f"{c} in zarr.json"))
    assert _store_attrs(tmp_path / "e")["made_with_other_settings"] == kept
    said = [line for line in capsys.readouterr().err.splitlines() if "other settings" in line or "fake" in line]
    assert len(said) == 1 and "carve.resolution warning: fake 16 then 24; a nan then 1" in said[0]


def _voxels_with_header(path, member: str | None = None, header_edit: tuple[bytes, bytes] = (b"", b"")) -> None:
    """A voxels file at ``path`` (grid, transform, canvas, fingerprint) whose ``member``'s ``.npy`` header has
    ``header_edit[0]`` replaced by ``header_edit[1]`` (stored uncompressed, so the zip's checksums still hold;
    ``member`` None: a sound file)."""
    import io
    import zipfile

    occ = np.zeros((4, 4, 4), bool)
    occ[1:3, 1:3, 1:3] = True
    buf = io.BytesIO()
    np.savez(buf, occupancy=occ, voxel_to_canvas=np.eye(4), canvas_scale=np.float64(0.5),
             canvas_offset=np.float64([3.0, 4.0]), input_fingerprint=np.asarray("abc", dtype=str))
    with zipfile.ZipFile(buf) as zin, zipfile.ZipFile(path, "w") as zout:
        for name in zin.namelist():
            data = zin.read(name)
            if name == f"{member}.npy":
                assert header_edit[0] in data[:128]
                data = data.replace(header_edit[0], header_edit[1], 1)
            zout.writestr(name, data)


#: A header edit that makes a member claim far more memory than any machine has.
_HUGE = (b"'shape': (4, 4, 4)", b"'shape': (10000000000000, 4, 4)")


def test_a_voxels_grid_whose_damaged_header_claims_any_size_is_unreadable_not_a_crash(tmp_path):
    """A damaged ``.npy`` header can declare any shape; reading it raises ``MemoryError`` (numpy allocates the array
    before reading it), which is the file's fault: the object is unreadable, the export goes on."""
    from carvi_torch.export.objects import UnreadableFiles, _read_voxels

    path = tmp_path / "3.npz"
    _voxels_with_header(path, "occupancy", _HUGE)
    with pytest.raises(UnreadableFiles, match="unreadable outputs: .*3.npz: .*MemoryError"):
        _read_voxels(path)


@pytest.mark.parametrize("damage", [(b"'descr': '<f8'", b"'descr': 'oops'"),
                                    (b"'shape': ()", b"'shape': (10000000000000,)")], ids=["bad dtype", "huge shape"])
def test_a_damaged_canvas_member_leaves_the_verdict_to_the_rest_of_the_read(tmp_path, damage):
    """A canvas member that cannot be read is no other canvas (the rest of the read judges the file: this one's
    grid and transform are sound, so it is read); a fault of the caller (no canvas to compare with) is raised,
    not taken for damage."""
    from carvi_torch.export.objects import _other_canvas, _read_voxels

    path = tmp_path / "3.npz"
    _voxels_with_header(path, "canvas_scale", damage)
    with np.load(path) as z:
        assert _other_canvas(z, (0.6, (3.0, 4.0)), "abc") is False
    assert _read_voxels(path, (0.6, (3.0, 4.0)), "abc")["occupancy"].sum() == 8
    _voxels_with_header(path)  # sound
    with np.load(path) as z, pytest.raises(TypeError):
        _other_canvas(z, None, "abc")


def test_the_viewpoint_of_an_entry_without_angles_comes_from_its_refined_R_or_is_none(monkeypatch):
    """Without readable angles the export computes them from ``refined.R``; every malformed entry or ``R`` gives
    None (the object's reason), while an error of the code computing them is raised, not taken for a bad R."""
    import carvi_torch.cameras
    from carvi_torch.export.run import _viewpoint_or_none

    eye = np.eye(3).tolist()
    assert np.allclose(_viewpoint_or_none({"refined": {"R": eye}}),
                       [float(a) for a in azimuth_elevation_roll_from_rotation(torch.eye(3, dtype=torch.float64))])
    for entry in ("oops", {}, {"refined": None}, {"refined": {"R": [[1.0, 0.0]]}}, {"refined": {"R": "oops"}},
                  {"refined": {"R": {"a": 1}}}, {"refined": {"R": [[10 ** 400] * 3] * 3}}):
        assert _viewpoint_or_none(entry) is None, entry

    def broken(R):
        raise RuntimeError("a fault of the code")

    monkeypatch.setattr(carvi_torch.cameras, "azimuth_elevation_roll_from_rotation", broken)
    with pytest.raises(RuntimeError, match="a fault of the code"):
        _viewpoint_or_none({"refined": {"R": eye}})


def _edit_cameras(run, cls: str, edit) -> Path:
    """Rewrite ``run/cls/cameras.json`` by ``edit(content)``; returns its path."""
    path = run / cls / "cameras.json"
    cams = json.loads(path.read_text())
    edit(cams)
    path.write_text(json.dumps(cams))
    return path


def _class_skipped_alone(run, tmp_path, capsys, cls: str, why: str) -> None:
    """The zarr store, cmr and ucmr each skip every object of ``cls`` with the reason ``why`` and export the other
    class of the run (exit 0, no traceback)."""
    data = json.loads((run / "input" / "annotations.json").read_text())
    other = "car" if cls == "chair" else "chair"
    capsys.readouterr()
    assert export_main(["--recon", str(run), "--out", str(tmp_path / "e"), "--quiet"] + _SMALL) == 0
    assert _reasons(tmp_path / "e") == {(cls, aid): why for aid in _ids(data, cls)}
    assert _store_attrs(tmp_path / "e")["counts"] == {other: 5, cls: 0}
    for fmt in ("cmr", "ucmr"):
        res = export_format(run, tmp_path / fmt, fmt, progress=False)
        assert [f.stem for f in res["files"]] == [other] and res["objects"] == 5
        assert {s["reason"] for s in res["skipped"]} == {why}
    assert "Traceback" not in "".join(capsys.readouterr())


def test_a_class_whose_mean_shape_collapses_to_one_point_is_skipped_alone(recon, tmp_path, capsys):
    """A class whose keypoints all lie at one point of its mean shape (duplicate keypoint names, a hand-edited
    file) has no scale for its canonical frame: its objects are skipped with one reason naming the file, in every
    format, and the other class is exported. A flat mean shape (every keypoint in one plane) still gives the
    CMR files a hull."""
    run = tmp_path / "run"
    _run_copy(recon, run)
    path = _edit_cameras(run, "chair", lambda c: c.update(mean_shape={n: [1.0, 2.0, 3.0] for n in c["mean_shape"]}))
    why = (f"cameras.json unusable: {path}: its mean_shape has no extent (its keypoints lie at one point), so the "
           "class has no scale for its canonical frame")
    _class_skipped_alone(run, tmp_path, capsys, "chair", why)
    _edit_cameras(run, "chair", lambda c: c.update(mean_shape={n: [float(i), float(i % 3), 0.0]
                                                               for i, n in enumerate(c["mean_shape"])}))
    res = export_format(run, tmp_path / "flat", "ucmr", progress=False)
    assert res["objects"] == 10 and json.loads((tmp_path / "flat" / "chair.json").read_text())["faces"]


@pytest.mark.parametrize("shape, why", [([1, 2], "mean_shape is [1, 2], not an object of keypoint name -> 3 numbers"),
                                        ({"seat": "x"}, "mean_shape 'seat' is 'x', not 3 finite numbers")])
def test_a_mistyped_mean_shape_skips_its_class_naming_the_file(recon, tmp_path, capsys, shape, why):
    """A hand-edited ``mean_shape`` (a list, a row that is no 3 numbers): that class is skipped with one reason
    naming its ``cameras.json``, in every format; the other class is exported."""
    run = tmp_path / "run"
    _run_copy(recon, run)
    path = _edit_cameras(run, "chair", lambda c: c.update(mean_shape=shape))
    _class_skipped_alone(run, tmp_path, capsys, "chair", f"cameras.json unusable: {path}: {why}")


def test_a_summary_whose_data_is_no_path_is_one_error_line(recon, tmp_path, capsys):
    """``summary.json``'s ``data`` (the annotation file the run read) of the wrong type: one ``error:`` line naming
    the file, exit 2, nothing written, in every format."""
    run = tmp_path / "run"
    _run_copy(recon, run)
    summary = json.loads((run / "summary.json").read_text())
    (run / "summary.json").write_text(json.dumps({**summary, "data": 5}))
    for fmt in ("zarr", "cmr", "ucmr"):
        capsys.readouterr()
        assert export_main(["--recon", str(run), "--out", str(tmp_path / fmt), "--format", fmt, "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [f"error: {run / 'summary.json'}: 'data' is 5, not the path of the annotation file the run "
                       "read (nothing was written)"], err
        assert not (tmp_path / fmt).exists()


def test_a_class_named_like_zarrs_metadata_file_is_skipped_and_the_store_still_reads(recon, tmp_path, capsys):
    """A category named ``zarr.json`` (its folder key too) cannot be a group of the store (the root's metadata file
    has that name): its objects are skipped with the reason, the other class is exported, and the store opens in
    LiftedDataset; ``--format ucmr`` exports that class."""
    data = json.loads((recon / "input" / "annotations.json").read_text())
    next(c for c in data["categories"] if c["name"] == "chair")["name"] = "zarr.json"
    (tmp_path / "ann.json").write_text(json.dumps(data))
    folder = tmp_path / "run"
    run_cfg = {**TINY, "out": str(folder), "data": str(tmp_path / "ann.json"), "classes": ["car", "zarr.json"]}
    run(Config().override(run_cfg), workers=0)
    why = ("the class key 'zarr.json' cannot name a group of the zarr store (the group's own metadata file is "
           "zarr.json); --format cmr or ucmr exports it")
    assert export_main(["--recon", str(folder), "--out", str(tmp_path / "e"), "--quiet"] + _SMALL) == 0
    assert set(_reasons(tmp_path / "e").values()) == {why}
    assert _store_attrs(tmp_path / "e")["counts"] == {"car": 5, "zarr.json": 0}
    ds = LiftedDataset(tmp_path / "e")
    assert len(ds) == 5 and {ds[i]["class_key"] for i in range(5)} == {"car"}
    assert export_main(["--recon", str(folder), "--out", str(tmp_path / "u"), "--format", "ucmr", "--quiet"]) == 0
    assert len(json.loads((tmp_path / "u" / "zarr.json.json").read_text())["images"]) == 5


def test_cmr_and_ucmr_replace_their_own_earlier_files_alone(recon, tmp_path, capsys):
    """A file in --out of the name cmr / ucmr would write that is not an earlier export's (a user's ``car.json``, a
    CMR ``.mat`` of CMR's own): one ``error:`` line naming it, exit 2, nothing written. Their own earlier files,
    marked or from before the marker, are replaced."""
    import scipy.io

    for fmt, ext in (("ucmr", "json"), ("cmr", "mat")):
        out = tmp_path / fmt
        out.mkdir()
        if fmt == "ucmr":
            (out / "car.json").write_text('{"my": "notes"}')
        else:
            scipy.io.savemat(out / "car.mat", {"sfm_anno": np.zeros((1, 2)), "S": np.zeros((3, 4))})
        mine = (out / f"car.{ext}").read_bytes()
        capsys.readouterr()
        assert export_main(["--recon", str(recon), "--out", str(out), "--format", fmt, "--quiet"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"error: --out {out}: 'car.{ext}' is not a file of an earlier "), err
        assert (out / f"car.{ext}").read_bytes() == mine and [p.name for p in out.iterdir()] == [f"car.{ext}"]
        (out / f"car.{ext}").unlink()
        assert export_main(["--recon", str(recon), "--out", str(out), "--format", fmt, "--quiet"]) == 0
        if fmt == "ucmr":  # as written before the marker
            js = json.loads((out / "car.json").read_text())
            assert js.pop("carvi_export") == "ucmr"
            (out / "car.json").write_text(json.dumps(js))
        else:
            mat = {k: v for k, v in scipy.io.loadmat(out / "car.mat").items() if not k.startswith("__")}
            assert str(mat.pop("carvi_export")[0]) == "cmr"
            scipy.io.savemat(out / "car.mat", mat)
        assert export_main(["--recon", str(recon), "--out", str(out), "--format", fmt, "--quiet"]) == 0
        assert sorted(p.name for p in out.iterdir()) == [f"car.{ext}", f"chair.{ext}"]
