"""Nothing lost, nothing escapes: valid objects are reconstructed, bad input gets a per-object reason,
user errors one line, and nothing is written outside ``--out``.

Each test builds its input from a small procedural collection (two classes of six objects) by
editing the COCO file as a user's file could be.
"""
from __future__ import annotations

import copy
import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from carvi_torch.config import Config, ConfigError
from carvi_torch.executors import exit_status, run
from carvi_torch.io.coco import load_coco
from carvi_torch.reconstruct import main as reconstruct_main
from carvi_torch.runtime import gone_within, processes_marked
from conftest import run_each_in_a_fresh_process

ROOT = Path(__file__).resolve().parents[1]
SMALL = {"resolution": 16, "proposals": 3, "canvas_size": 48, "progress": False, "refine_iters": 20,
         "plane_size": 24, "preview": False, "report": False}


@pytest.fixture(scope="module")
def base_dir(tmp_path_factory) -> Path:
    """Six procedural cars and six chairs: annotations.json, gt.json and the meshes."""
    from carvi_torch.synthetic import procedural

    d = tmp_path_factory.mktemp("base")
    procedural.write_default_collection(d, instances_per_class=6, categories=["car", "chair"], seed=1,
                                        progress=False)
    return d


@pytest.fixture(scope="module")
def base(base_dir) -> dict:
    """COCO data of six procedural cars and six chairs."""
    return json.loads((base_dir / "annotations.json").read_text())


def _write(tmp: Path, data: dict, name="ann.json") -> Path:
    p = tmp / name
    p.write_text(json.dumps(data))
    return p


def _cfg(out: Path, data: Path, **extra) -> Config:
    return Config().override({**SMALL, "out": str(out), "data": str(data), **extra})


def _problems(summary: dict) -> dict:
    return {str(p["annotation_id"]): p for p in summary["input_problems"]}


# --------------------------------------------------------------------------- 1. fallbacks


def test_every_object_of_a_tiny_class_is_reconstructed(base, tmp_path):
    """Six objects per class is too few for two principal-direction clusters each: every object still
    gets a reconstruction, and cameras.json / summary.json say which fallback made it."""
    out = tmp_path / "run"
    s = run(_cfg(out, _write(tmp_path, base)), workers=0)
    for key in ("car", "chair"):
        c = s["classes"][key]
        assert c["reconstructed"] == c["objects"] == 6 and c["skipped"] == 0, c["failures"]
        cams = json.loads((out / key / "cameras.json").read_text())["cameras"]
        levels = [e["surrogates_from"] for e in cams.values()]
        assert set(levels) <= {"triplet", "widened_clusters", "surrogate_pair", "own_mirror", "puffball"}
        assert c["surrogates_from"]["counts"] == {lv: levels.count(lv) for lv in c["surrogates_from"]["counts"]}
    fallbacks = {lv for key in ("car", "chair") for lv in s["classes"][key]["surrogates_from"]["fallbacks"]}
    assert fallbacks, "this collection is small enough to need a fallback somewhere"


def test_a_class_of_one_physical_object_without_mirrors_gets_puffballs(base, tmp_path):
    """Every car is a view of one physical object and mirrors are off: no proposal at all, so every car is a
    puffball, written with its voxels file (a grid with the mask's silhouette) and its mesh."""
    data = copy.deepcopy(base)
    car = next(c["id"] for c in data["categories"] if c["name"] == "car")
    data["annotations"] = [dict(a, object_id=7) for a in data["annotations"] if a["category_id"] == car]
    data["categories"] = [c for c in data["categories"] if c["id"] == car]
    out = tmp_path / "run"
    s = run(_cfg(out, _write(tmp_path, data), mirrors=False, mesher="torch"), workers=0)
    c = s["classes"]["car"]
    assert c["reconstructed"] == 6 and c["surrogates_from"]["counts"] == {"puffball": 6}, c["failures"]
    files = sorted((out / "car" / "voxels").glob("*.npz"))
    assert len(files) == 6
    for f in files:
        assert np.load(f)["occupancy"].any() and (out / "car" / "meshes" / f"{f.stem}.ply").stat().st_size > 0


def test_fallback_levels_in_order():
    """One cluster only: widened clusters when the widening finds two; else a single surrogate; else (one
    physical object) the own mirrored copy; without mirrors, a puffball."""
    from carvi_torch.surrogates import Clusters, plan_proposals

    axes = torch.eye(3)
    # every instance seen along +z except two along x and y, just outside the 15 degree clusters
    view = torch.tensor([[0.0, 0, 1]] * 6 + [[1.0, 0, 0.5], [0, 1.0, 0.5]])
    n = len(view)
    labels = torch.tensor([2] * 6 + [-1, -1])
    cl = Clusters(labels, 15.0, torch.bincount(labels[labels >= 0], minlength=3))
    usable = torch.ones(n, dtype=torch.bool)
    g = torch.Generator().manual_seed(0)
    trip, levels = plan_proposals(cl, torch.arange(n), usable, view, axes, 4, True, g)
    assert set(levels) == {"widened_clusters"} and bool(trip.valid.any(dim=1).all())
    # all seen along one axis: no second cluster even widened -> one surrogate each
    trip, levels = plan_proposals(cl, torch.arange(n), usable, torch.tensor([[0.0, 0, 1]] * n), axes, 4, True, g)
    assert set(levels) == {"surrogate_pair"} and bool((trip.surrogates[..., 1][trip.valid] == -1).all())
    # one physical object: no surrogate at all -> the reference and its mirror; without mirrors a puffball
    one = torch.zeros(n, dtype=torch.long)
    trip, levels = plan_proposals(cl, one, usable, torch.tensor([[0.0, 0, 1]] * n), axes, 4, True, g)
    assert set(levels) == {"own_mirror"} and bool(trip.valid[:, 0].all()) and not trip.valid[:, 1:].any()
    _trip, levels = plan_proposals(cl, one, usable, torch.tensor([[0.0, 0, 1]] * n), axes, 4, False, g)
    assert set(levels) == {"puffball"}


def test_puffball_grid_matches_the_puffball_mesh():
    """The voxelised puffball has the volume of the baseline's marching-cubes mesh of the same height field."""
    from carvi_torch.carve.puffball import puffball_grids
    from carvi_torch.evaluation.baselines import puffball

    yy, xx = torch.meshgrid(torch.arange(48), torch.arange(48), indexing="ij")
    mask = ((xx - 24) ** 2 / 18 ** 2 + (yy - 22) ** 2 / 10 ** 2) <= 1
    grids = puffball_grids(mask[None], resolution=48)
    mesh = puffball(mask)
    assert float(grids.volumes()[0]) == pytest.approx(mesh.volume, rel=0.06)
    # the grid's silhouette is the mask: the same area, and no occupied column farther than a pixel from it
    from scipy import ndimage

    T = grids.voxel_to_camera[0].double()
    hw = grids.columns[0].nonzero().double()
    x, y = T[0, 2] * hw[:, 1] + T[0, 3], T[1, 1] * hw[:, 0] + T[1, 3]
    area = len(hw) * float(T[0, 2] * T[1, 1])
    assert area == pytest.approx(float(mask.sum()), rel=0.08)
    outside = ndimage.distance_transform_edt(~mask.numpy())
    assert outside[y.round().long().numpy(), x.round().long().numpy()].max() <= 1.0


# --------------------------------------------------------------------------- 2, 3, 4. ids and names


def _string_ids(data: dict) -> dict:
    d = copy.deepcopy(data)
    cat = {c["id"]: f"cat-{c['name']}" for c in d["categories"]}
    img = {i["id"]: f"img/{i['id']}" for i in d["images"]}
    for c in d["categories"]:
        c["id"] = cat[c["id"]]
    for i in d["images"]:
        i["id"] = img[i["id"]]
    for a in d["annotations"]:
        a["category_id"], a["image_id"] = cat[a["category_id"]], img[a["image_id"]]
        a["object_id"] = f"plane {a['id']}"
        a["id"] = f"obj/{a['id']}"
    return d


def test_string_ids_are_carried_to_every_output(base, tmp_path):
    out = tmp_path / "run"
    s = run(_cfg(out, _write(tmp_path, _string_ids(base)), classes="car"), workers=0)
    c = s["classes"]["car"]
    assert c["reconstructed"] == 6 and not s["input_problems"]
    cams = json.loads((out / "car" / "cameras.json").read_text())["cameras"]
    assert sorted(cams) == sorted(a["id"] for a in _string_ids(base)["annotations"] if a["category_id"] == "cat-car")
    files = sorted(p.name for p in (out / "car" / "meshes").iterdir())
    assert len(files) == 6 and all("/" not in f and not f.startswith(".") for f in files)
    from carvi_torch.io.layout import object_file

    assert all(object_file(out / "car", "meshes", a, "ply").is_file() for a in cams)


def test_an_integer_id_beyond_64_bits_is_kept_as_written(base, tmp_path):
    """Annotation id 10**30 (no int64 holds it): the object is made, its files and cameras.json
    carry its digits, and the arrays that hold ids fall back to strings instead of overflowing."""
    from carvi_torch.export.run import _int_id
    from carvi_torch.io.layout import object_file
    from carvi_torch.io.writer import id_array

    huge = 10 ** 30
    d = copy.deepcopy(base)
    next(a for a in d["annotations"] if a["id"] == 3)["id"] = huge
    out = tmp_path / "run"
    c = run(_cfg(out, _write(tmp_path, d), classes="car"), workers=0)["classes"]["car"]
    assert c["status"] != "failed" and c["reconstructed"] == 6, c["failures"]
    assert str(huge) in json.loads((out / "car" / "cameras.json").read_text())["cameras"]
    assert object_file(out / "car", "meshes", huge, "ply").is_file()
    assert id_array([huge, 2, -1]).tolist() == [str(huge), "2", ""] and id_array([2 ** 63 - 1]).dtype == np.int64
    assert _int_id(huge) == -1 and _int_id(-5) == -5


@pytest.mark.parametrize("bad, why", [(None, "null"), (3.5, "a float"), (True, "a boolean"), ("", "")])
def test_unusable_ids_skip_their_object(base, tmp_path, bad, why):
    d = copy.deepcopy(base)
    d["annotations"][0]["id"] = bad
    d["annotations"][1]["id"] = d["annotations"][2]["id"]  # a duplicate
    res = load_coco(_write(tmp_path, d), canvas_size=48)
    reasons = [p.reason for p in res.problems]
    assert any("not an integer or a string" in r and why in r for r in reasons), reasons
    assert any("duplicate annotation id" in r for r in reasons)
    assert sum(len(c) for c in res.collections.values()) == len(d["annotations"]) - 2


def test_two_categories_of_one_name_are_two_classes(base, tmp_path):
    d = copy.deepcopy(base)
    chair = next(c for c in d["categories"] if c["name"] == "chair")
    chair["name"] = "car"
    out = tmp_path / "run"
    s = run(_cfg(out, _write(tmp_path, d)), workers=0)
    assert len(s["classes"]) == 2 and sum(c["reconstructed"] for c in s["classes"].values()) == 12
    names = sorted(json.loads((out / k / "cameras.json").read_text())["class"] for k in s["classes"])
    assert names == ["car", "car"] and sorted(s["classes"])[0] == "car"


@pytest.mark.parametrize("name", ["../../evil", "/abs/path", "a/b", ".", "", "..", "~root"])
def test_category_names_never_leave_the_output_folder(base, tmp_path, name):
    d = copy.deepcopy(base)
    d["categories"][0]["name"] = name
    d["annotations"] = [a for a in d["annotations"] if a["category_id"] == d["categories"][0]["id"]]
    root = tmp_path / "root"
    out = root / "deep" / "out"
    out.parent.mkdir(parents=True)
    before = sorted(p for p in tmp_path.rglob("*"))
    s = run(_cfg(out, _write(root, d)), workers=0)
    (key,) = s["classes"]
    assert s["classes"][key]["reconstructed"] == 6
    assert (out / key / "cameras.json").is_file() and (out / key).resolve().parent == out.resolve()
    assert json.loads((out / key / "cameras.json").read_text())["class"] == name
    new = [p for p in tmp_path.rglob("*") if p not in before]
    assert all(p == out or out in p.parents or p == root / "ann.json" for p in new), new
    assert not Path("/abs/path").exists()


def test_classes_named_like_the_runs_own_files_get_other_folders(base, tmp_path):
    """Categories named summary.json and Config.YAML (any case) do not collide with the run's files: their
    folders get other safe names, their names stay in summary.json and cameras.json."""
    from carvi_torch.io.layout import RUN_NAMES, class_dir

    d = copy.deepcopy(base)
    d["categories"][0]["name"], d["categories"][1]["name"] = "summary.json", "Config.YAML"
    out = tmp_path / "run"
    s = run(_cfg(out, _write(tmp_path, d)), workers=0)
    assert sorted(s["classes"]) == ["Config.YAML-2", "summary.json-1"]
    assert all(c["reconstructed"] == 6 for c in s["classes"].values()), s["classes"]
    assert json.loads((out / "summary.json").read_text())["classes"] == s["classes"]
    assert sorted(json.loads((out / k / "cameras.json").read_text())["class"] for k in s["classes"]) == [
        "Config.YAML", "summary.json"]
    for name in RUN_NAMES:
        with pytest.raises(ValueError, match="run's own names"):
            class_dir(out, name)


# --------------------------------------------------------------------------- 6, 7. sizes and masks


def test_a_huge_image_is_skipped_not_a_crash(base, tmp_path):
    d = copy.deepcopy(base)
    a = d["annotations"][0]
    im = next(i for i in d["images"] if i["id"] == a["image_id"])
    im["width"] = im["height"] = 100000
    a["segmentation"] = [[10.0, 10.0, 90000.0, 10.0, 90000.0, 90000.0]]
    res = load_coco(_write(tmp_path, d), canvas_size=48)
    p = next(p for p in res.problems if p.annotation_id == a["id"])
    assert "100000x100000" in p.reason and "max_image_pixels" in p.reason
    with pytest.raises(ConfigError, match="canvas_size"):
        Config().override({"canvas_size": 5000})


def test_uncompressed_rle_counts_must_cover_the_image(base, tmp_path):
    d = copy.deepcopy(base)
    a = d["annotations"][0]
    im = next(i for i in d["images"] if i["id"] == a["image_id"])
    a["segmentation"] = {"size": [im["height"], im["width"]], "counts": [10, 20, 30]}
    res = load_coco(_write(tmp_path, d), canvas_size=48)
    p = next(p for p in res.problems if p.annotation_id == a["id"])
    assert "sum to 60" in p.reason and p.fatal


@pytest.mark.parametrize("value, skipped", [("no", False), ("false", False), (0, False), ("yes", True),
                                            (True, True), ("maybe", True)])
def test_yes_no_flags(base, tmp_path, value, skipped):
    d = copy.deepcopy(base)
    d["annotations"][0]["truncated"] = value
    res = load_coco(_write(tmp_path, d), canvas_size=48)
    hit = [p for p in res.problems if p.annotation_id == d["annotations"][0]["id"]]
    assert bool(hit) == skipped, hit


def test_an_object_whose_keypoints_collapse_is_skipped_alone(base, tmp_path):
    """Every visible keypoint of one object on one pixel: no camera fits it (its fit used to reach
    grid_sample with NaN and crash the process); it is skipped with the reason, the others are made."""
    d = copy.deepcopy(base)
    a = next(a for a in d["annotations"] if a["id"] == 2)
    kp = a["keypoints"]
    for i in range(0, len(kp), 3):
        if kp[i + 2] == 2:
            kp[i:i + 2] = [250.0, 150.0]
    out = tmp_path / "run"
    c = run(_cfg(out, _write(tmp_path, d), classes="car"), workers=0)["classes"]["car"]
    assert [(f["annotation_id"], f["reason"]) for f in c["failures"]] == [
        (2, "visible keypoints collapse to one point (they fix no scale)")]
    assert c["reconstructed"] == 5 and c["status"] != "failed"
    cams = json.loads((out / "car" / "cameras.json").read_text())["cameras"]
    assert cams["2"]["refined"] is None and cams["2"]["azimuth_deg"] is None and cams["1"]["refined"] is not None


def test_objects_skipped_at_load_count_in_their_class_and_get_report_cards(base, tmp_path):
    """Objects dropped at load (an unknown image, a polygon of no area, every keypoint far off the image) are
    their class's objects and skipped ones (summary, the closing table), with the load reason as their
    failure, and each gets a report card giving it; ``input_problems`` still lists them."""
    from carvi_torch.reconstruct import format_table
    from carvi_torch.report import build_report

    d = copy.deepcopy(base)
    anns = {a["id"]: a for a in d["annotations"]}
    anns[1]["image_id"] = 999
    anns[2]["segmentation"] = [[10.0, 10.0, 20.0, 20.0, 30.0, 30.0]]  # three points on a line
    anns[4]["keypoints"] = [v if i % 3 == 2 else -5000.0 for i, v in enumerate(anns[4]["keypoints"])]
    out = tmp_path / "run"
    s = run(_cfg(out, _write(tmp_path, d), classes="car"), workers=0)
    c = s["classes"]["car"]
    why = {1: "unknown image id 999", 2: "empty mask", 4: "no visible keypoint"}
    assert (c["objects"], c["reconstructed"], c["skipped"]) == (6, 3, 3)
    assert {f["annotation_id"]: (f["stage"], f["reason"]) for f in c["failures"]} == {
        k: ("load", v) for k, v in why.items()}
    assert {p["annotation_id"] for p in s["input_problems"] if p["skipped"]} == set(why)
    row = next(line.split() for line in format_table(s).splitlines() if line.startswith("car "))
    assert row[1:5] == ["6", "3", "0", "3"]  # objects, reconstructed, resumed, skipped
    build_report(out, out / "report")
    text = (out / "report" / "cards.js").read_text()
    cards = json.loads(text[text.index("\n[") + 1:text.rindex(");")])
    assert {int(k["id"]): k["skipped"] for k in cards if k.get("skipped")} == why
    assert not any(k.get("problems") for k in cards)  # the reason is the card's, not an unreadable mask


# --------------------------------------------------------------------------- categories without left/right pairs


@pytest.mark.parametrize("change", [{"keypoints": [f"k{i}" for i in range(10)]}, {"flip_pairs": []}],
                         ids=["names k0..k9", "flip_pairs []"])
def test_a_class_without_left_right_pairs_runs_without_mirrors(base, tmp_path, change):
    """No flip pairs (none to infer from the names, or none given): the class runs without mirrored
    copies and symmetry plane (it used to fail in symmetry_plane), and says so."""
    from carvi_torch.viewpoints import NO_MIRRORS

    d = copy.deepcopy(base)
    chair = next(c for c in d["categories"] if c["name"] == "chair")
    chair.pop("flip_pairs", None)
    chair.update(change)
    out = tmp_path / "run"
    c = run(_cfg(out, _write(tmp_path, d), classes="chair"), workers=0)["classes"]["chair"]
    assert c["reconstructed"] == 6 and c["status"] != "failed", c["failures"]
    assert NO_MIRRORS in c["warnings"] and "own_mirror" not in c["surrogates_from"]["counts"]
    assert json.loads((out / "chair" / "cameras.json").read_text())["symmetry_plane"] is None


def test_a_class_of_one_keypoint_is_skipped_with_its_reason(base, tmp_path):
    """A single keypoint places no object in SfM: the class is skipped (not failed) with one reason."""
    d = copy.deepcopy(base)
    chair = next(c for c in d["categories"] if c["name"] == "chair")
    chair.update(keypoints=["center"], flip_pairs=[])
    for a in d["annotations"]:
        if a["category_id"] == chair["id"]:
            a["keypoints"] = next(a["keypoints"][i:i + 3] for i in range(0, len(a["keypoints"]), 3)
                                  if a["keypoints"][i + 2] == 2)
    s = run(_cfg(tmp_path / "run", _write(tmp_path, d)), workers=0)
    c = s["classes"]["chair"]
    assert c["status"] == "skipped" and len(c["failures"]) == 1 and c["failures"][0]["annotation_id"] is None
    assert "no mean shape" in c["failures"][0]["reason"] and "a camera needs 2" in c["failures"][0]["reason"]
    assert s["classes"]["car"]["reconstructed"] == 6 and exit_status(s) == 0


# --------------------------------------------------------------------------- ground truth beside the data


@pytest.mark.parametrize("content, warned", [
    (b"<html>404 Not Found</html>", True), (b"[]", False),
    (json.dumps({"annotations": {"1": {"R": "junk", "s": 1, "t": [0, 0]}}}).encode(), False)],
    ids=["not JSON", "a list", "junk cameras"])
def test_a_broken_gt_json_does_not_stop_a_run_that_does_not_need_it(base, tmp_path, content, warned):
    """Ground truth is only used with cameras=gt: an unreadable gt.json is one warning, a junk one nothing."""
    (tmp_path / "gt.json").write_bytes(content)
    s = run(_cfg(tmp_path / "run", _write(tmp_path, base), classes="car"), workers=0)
    assert s["classes"]["car"]["reconstructed"] == 6
    gt = [p for p in s["input_problems"] if p["stage"] == "gt"]
    assert len(gt) == warned and s["gt"] == (None if warned else str(tmp_path / "gt.json"))
    assert all("gt.json: malformed JSON" in p["reason"] and not p["skipped"] for p in gt)
    assert ("gt.json: malformed JSON" in (tmp_path / "run" / "run.log").read_text()) == warned


def test_cameras_gt_needs_a_readable_gt_json(base, tmp_path, capsys):
    data = _write(tmp_path, base)
    out = tmp_path / "run"
    for content in (None, b"<html>404 Not Found</html>"):
        if content is not None:
            (tmp_path / "gt.json").write_bytes(content)
        rc = reconstruct_main(["--data", str(data), "--out", str(out), "--quiet", "cameras=gt"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and err[0].startswith("error: cameras=gt") and "gt.json" in err[0], err
        assert not out.exists()


def test_cameras_gt_skips_the_objects_without_a_usable_true_camera(base, base_dir, tmp_path):
    gt = json.loads((base_dir / "gt.json").read_text())
    gt["annotations"]["2"]["R"] = "junk"
    gt["annotations"]["3"]["R"] = [[2, 0, 0], [0, 1, 0], [0, 0, 1]]
    del gt["annotations"]["4"]
    (tmp_path / "gt.json").write_text(json.dumps(gt))
    out = tmp_path / "run"
    c = run(_cfg(out, _write(tmp_path, base), classes="car", cameras="gt"), workers=0)["classes"]["car"]
    assert {f["annotation_id"]: f["reason"] for f in c["failures"]} == {
        2: "cameras=gt: gt.json camera: R must be 3x3 numbers, s a number, t 2 numbers",
        3: "cameras=gt: gt.json camera: R is not a rotation", 4: "cameras=gt: no camera in gt.json"}
    assert c["reconstructed"] == 3
    cams = json.loads((out / "car" / "cameras.json").read_text())["cameras"]
    assert cams["1"]["camera_from"] == "ground_truth" and cams["2"]["camera_from"] is None


# --------------------------------------------------------------------------- 8, 10, 11. resume


def test_resume_redoes_damaged_outputs_and_merges_partial_runs(base, tmp_path):
    data = _write(tmp_path, base)
    out = tmp_path / "run"
    first = run(_cfg(out, data, classes="car"), workers=0)
    assert list(first["classes"]) == ["car"]
    meshes = sorted((out / "car" / "meshes").glob("*.ply"))
    voxels = sorted((out / "car" / "voxels").glob("*.npz"))
    meshes[0].write_bytes(meshes[0].read_bytes()[:300])
    voxels[1].write_bytes(voxels[1].read_bytes()[:200])
    # what a machine crash can leave of files moved into place unflushed (an object's files are not fsynced)
    meshes[2].write_bytes(b"")
    voxels[3].write_bytes(bytes(voxels[3].stat().st_size))
    whole = meshes[4].read_bytes()  # the right size, its last half never written: zeros
    meshes[4].write_bytes(whole[:len(whole) // 2] + bytes(len(whole) - len(whole) // 2))
    second = run(_cfg(out, data, classes="chair"), workers=0)
    assert sorted(second["classes"]) == ["car", "chair"]  # the earlier run's class is kept
    assert second["classes_from_earlier_runs"] == ["car"]
    again = run(_cfg(out, data, classes="car"), workers=0)["classes"]["car"]
    assert again["resumed"] == 1 and again["reconstructed"] == 5
    for m, v in zip(meshes[:5], voxels[:5]):
        assert len(trimesh.load(m, force="mesh").faces) > 0 and np.load(v)["occupancy"].any()


def _files(out: Path, cls: str = "car") -> dict:
    """``{annotation id: (mesh bytes, voxels mtime)}`` of a class's finished objects."""
    return {m.stem: (m.read_bytes(), (out / cls / "voxels" / f"{m.stem}.npz").stat().st_mtime_ns)
            for m in (out / cls / "meshes").glob("*.ply")}


def _grids(out: Path, cls: str = "car") -> dict:
    """``{annotation id: (occupancy bytes, voxel_to_camera bytes, input fingerprint)}`` of a class's voxels files."""
    grids = {}
    for f in (out / cls / "voxels").glob("*.npz"):
        with np.load(f) as z:
            grids[f.stem] = (z["occupancy"].tobytes(), z["voxel_to_camera"].tobytes(), str(z["input_fingerprint"]))
    return grids


def test_resume_keeps_an_object_only_while_its_inputs_are_unchanged(base, tmp_path):
    """A rerun resumes an object only when its own inputs are those it was made from (the fingerprint in its
    voxels file), whatever file they come from: a copy of the annotations elsewhere resumes all; an edited
    mask redoes exactly that object (its reconstruction_iou renewed); a file whose objects are others under
    the same ids redoes them all; files without a fingerprint (an older run's) are redone and counted."""
    from carvi_torch.io.coco import decode_segmentation, encode_mask

    out, data = tmp_path / "run", _write(tmp_path, base)
    assert run(_cfg(out, data, classes="car"), workers=0)["classes"]["car"]["reconstructed"] == 6
    first = _files(out)
    (tmp_path / "elsewhere").mkdir()
    grids = _grids(out)
    copied = run(_cfg(out, _write(tmp_path / "elsewhere", base), classes="car"), workers=0)
    c = copied["classes"]["car"]
    assert (c["resumed"], c["reconstructed"]) == (6, 0) and "redone" not in c and _files(out) == first
    assert copied["data_changed"]["previous"] == str(data.resolve())
    # one object's mask edited: the left 40% of its columns taken away
    edited = copy.deepcopy(base)
    ann = next(a for a in edited["annotations"] if a["id"] == 3)
    im = next(i for i in edited["images"] if i["id"] == ann["image_id"])
    mask = decode_segmentation(ann["segmentation"], im["height"], im["width"])
    cols = np.flatnonzero(mask.any(axis=0))
    mask[:, :cols[0] + int(0.4 * len(cols))] = False
    ann["segmentation"] = encode_mask(mask)
    again = run(_cfg(out, _write(tmp_path, edited, "edited.json"), classes="car"), workers=0)["classes"]["car"]
    assert (again["resumed"], again["reconstructed"]) == (5, 1)
    assert again["redone"] == {"count": 1, "inputs_changed": [3]}
    now = _files(out)
    # the others are resumed: their meshes and grids kept (their voxels files are rewritten only in
    # voxel_to_object, which follows the cameras, refitted jointly with the edited object's)
    assert now["3"][0] != first["3"][0] and {k: v[0] for k, v in now.items() if k != "3"} == {
        k: v[0] for k, v in first.items() if k != "3"}
    assert {k: v for k, v in _grids(out).items() if k != "3"} == {k: v for k, v in grids.items() if k != "3"}
    cams = json.loads((out / "car" / "cameras.json").read_text())["cameras"]
    iou = float(np.load(out / "car" / "voxels" / "3.npz")["reconstruction_iou"])
    assert cams["3"]["quality_signals"]["reconstruction_iou"] == round(iou, 6)
    # other objects under the same ids: the chairs, their category renamed car
    car = next(c for c in base["categories"] if c["name"] == "car")
    chair = next(c for c in base["categories"] if c["name"] == "chair")
    car_ids = sorted(a["id"] for a in base["annotations"] if a["category_id"] == car["id"])
    chairs = sorted((a for a in base["annotations"] if a["category_id"] == chair["id"]), key=lambda a: a["id"])
    others = {"images": base["images"], "categories": [{**chair, "id": car["id"], "name": "car"}],
              "annotations": [{**a, "id": i, "category_id": car["id"]} for a, i in zip(chairs, car_ids)]}
    swapped = run(_cfg(out, _write(tmp_path, others, "others.json"), classes="car"), workers=0)["classes"]["car"]
    assert (swapped["resumed"], swapped["reconstructed"]) == (0, 6)
    assert swapped["redone"] == {"count": 6, "inputs_changed": car_ids}
    # an older run's files, without a fingerprint: redone, and said so
    vox = out / "car" / "voxels" / "2.npz"
    with np.load(vox) as z:
        members = {k: z[k] for k in z.files if k != "input_fingerprint"}
    np.savez(vox, **members)
    older = run(_cfg(out, tmp_path / "others.json", classes="car"), workers=0)["classes"]["car"]
    assert (older["resumed"], older["reconstructed"]) == (5, 1)
    assert older["redone"] == {"count": 1, "no_input_record": [2]}
    # the annotations edited after the run: export leaves out the object whose files no longer match them
    from carvi_torch.export import export

    others["annotations"][0]["segmentation"] = encode_mask(mask)
    _write(tmp_path, others, "others.json")
    index = export(out, tmp_path / "export", resolution=4, points=8, progress=False, workers=0)
    assert len(index["samples"]) == 5 and [(s["annotation_id"], s["reason"]) for s in index["skipped"]] == [
        (car_ids[0], "its files were made from other inputs than the annotation file's (rerun reconstruct)")]


def test_a_killed_run_leaves_no_process_running(base, tmp_path):
    """SIGKILL of the main process while its writer processes work: they notice and exit."""
    marker = uuid.uuid4().hex
    code = ("import sys, json; from carvi_torch.config import Config; from carvi_torch.executors import run; "
            "run(Config().override(json.loads(sys.argv[3]) | {'out': sys.argv[1], 'data': sys.argv[2]}), workers=2)")
    settings = json.dumps({**SMALL, "resolution": 40, "proposals": 20})
    env = dict(os.environ, CARVI_TEST_MARKER=marker)
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "run"), str(_write(tmp_path, base)),
                             settings], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def marked() -> list[int]:
        return processes_marked(marker)

    for _ in range(600):  # wait for the writer processes (the main process plus at least two)
        if len(marked()) >= 3 or proc.poll() is not None:
            break
        time.sleep(0.1)
    assert proc.poll() is None and len(marked()) >= 3, "the run ended before its writers were seen"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    left = gone_within(marker, 10.0)
    assert not left, f"processes of the killed run still running: {left}"


def test_ctrl_c_is_one_line_and_exit_130(tmp_path, capsys, monkeypatch):
    """Ctrl-C during a run: one line, exit status 130, no traceback (the finished objects stay for a rerun)."""
    import carvi_torch.executors as executors
    from carvi_torch.reconstruct import INTERRUPTED

    def interrupted(cfg):
        raise KeyboardInterrupt

    monkeypatch.setattr(executors, "run", interrupted)
    rc = reconstruct_main(["--out", str(tmp_path / "out"), "--quiet"])
    captured = capsys.readouterr()
    assert rc == 130 and captured.err.splitlines() == [INTERRUPTED] and "Traceback" not in captured.out


def test_writer_processes_ignore_ctrl_c():
    """Ctrl-C reaches the whole process group; a writer process ignores it (the run stops the writers)
    instead of dying with a KeyboardInterrupt traceback."""
    from carvi_torch.io import write_worker
    from carvi_torch.io.writer import Writer

    w = Writer(1)
    try:
        pid = w.pool.submit(write_worker.start_worker).result(timeout=30)
        os.kill(pid, signal.SIGINT)
        time.sleep(0.2)
        assert w.pool.submit(write_worker.start_worker).result(timeout=30) == pid
    finally:
        w.close()


WRITERS_SCRIPT = """
import json, multiprocessing, sys
import numpy as np
import torch  # the run's main module imports torch (carvi_torch.reconstruct does)
from carvi_torch.io import write_worker
from carvi_torch.io.writer import Writer

def main(out):
    w = Writer(2)
    try:
        occ = np.zeros((20, 20, 20), bool); occ[5:15, 5:15, 5:15] = True
        job = dict(occupancy=occ, voxel_to_image=np.eye(4), voxel_to_canvas=np.eye(4)[[2, 1, 0, 3]], canvas_scale=1.0,
                   canvas_offset=np.zeros(2, np.float32), surrogates=np.zeros(2, np.int64), largest_component=True,
                   proposals=None, scores=None, mask=np.ones((64, 64), bool), voxel_path=out + "/v.npz",
                   mesh_path=out + "/m.ply")
        jobs = [w.pool.submit(write_worker.write_object_safe, job) for _ in range(4)]
        ok = all(f.result(timeout=60)["ok"] for f in jobs)
        pids = sorted(p.pid for p in multiprocessing.active_children())  # every writer process the pool started
        torch_in = [("libtorch" in open(f"/proc/{p}/maps").read()) for p in pids]
        print(json.dumps({"pids": pids, "ok": ok, "torch": torch_in}))
    finally:
        w.close()

if __name__ == "__main__":
    main(sys.argv[1])
"""


@pytest.mark.skipif(not Path("/proc/self/maps").is_file(), reason="reads /proc/<pid>/maps (Linux)")
def test_writer_processes_start_without_torch(tmp_path):
    """The writers neither re-import the run's main module (which imports torch) nor import torch to write an
    object: each is a small process (about 80 MB against 270 with torch) that starts in a fraction of a second."""
    script = tmp_path / "run_main.py"
    script.write_text(WRITERS_SCRIPT)
    res = subprocess.run([sys.executable, str(script), str(tmp_path)], capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr[-2000:]
    got = json.loads(res.stdout.strip().splitlines()[-1])
    assert got["ok"] and (tmp_path / "m.ply").is_file() and got["pids"]
    assert got["torch"] == [False] * len(got["pids"])


# --------------------------------------------------------------------------- 12, 13. errors and exit status


@pytest.mark.parametrize("args, why", [(["device=tpu"], "device"), (["device=banana"], "device"),
                                       (["device=mps"], "device"), (["--data", "missing.json"], "no such file"),
                                       (["silhouette_weight=nan"], "silhouette_weight"),
                                       (["resolutoin=40"], "did you mean 'resolution'")])
def test_user_errors_are_one_line_and_write_nothing(tmp_path, capsys, args, why):
    out = tmp_path / "out"
    rc = reconstruct_main(["--out", str(out), "--quiet", *args])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error:") and why in err[0], err
    assert not out.exists()


def test_an_output_folder_that_is_a_file_or_under_one(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("x")
    for out in (f, f / "sub"):
        assert reconstruct_main(["--out", str(out), "--quiet"]) == 2
        assert "is a file" in capsys.readouterr().err
    assert f.read_text() == "x"


@pytest.mark.parametrize("link", ["car", "car/meshes", "run.log", "report", "report/assets", "input"])
def test_a_symbolic_link_where_the_run_writes_is_refused_with_nothing_written(base_dir, tmp_path, capsys, link):
    """A link under --out would carry the run's files (or run.log's lines) outside --out: one error line,
    exit 2, before any work; the link's target and --out are as they were."""
    out, outside = tmp_path / "out", tmp_path / "outside"
    outside.mkdir()
    (outside / "kept.txt").write_text("mine")
    (out / link).parent.mkdir(parents=True, exist_ok=True)
    (out / link).symlink_to(outside / "kept.txt" if link == "run.log" else outside)
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))
    rc = reconstruct_main(["--data", str(base_dir / "annotations.json"), "--out", str(out), "--quiet",
                           *(f"{k}={v}" for k, v in SMALL.items())])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error:") and "symbolic link" in err[0], err
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before
    assert (outside / "kept.txt").read_text() == "mine"


@pytest.mark.parametrize("where", ["car", "car/meshes", "chair/voxels"])
def test_a_file_where_a_class_folder_goes_is_refused_before_the_work(base_dir, tmp_path, capsys, monkeypatch, where):
    """Found once the classes are loaded, before the viewpoints: one error line, exit 2, the file kept."""
    from carvi_torch.executors import local
    out = tmp_path / "out"
    (out / where).parent.mkdir(parents=True, exist_ok=True)
    (out / where).write_text("mine")
    monkeypatch.setattr(local, "_classes", lambda *a: pytest.fail("the classes ran"))
    rc = reconstruct_main(["--data", str(base_dir / "annotations.json"), "--out", str(out), "--quiet",
                           *(f"{k}={v}" for k, v in SMALL.items())])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error:") and f"{where} is a file" in err[0], err
    assert (out / where).read_text() == "mine"


@pytest.mark.parametrize("finished", ["car/meshes/1.ply", "chair/voxels/7.npz"])
def test_stage_cameras_into_a_folder_with_finished_objects_is_refused(tmp_path, capsys, finished):
    """A camera-only run would rewrite config.yaml, cameras.json and the class's summary entry beside shapes
    made with other cameras: one error line, exit 2, the folder as it was."""
    out = tmp_path / "out"
    (out / finished).parent.mkdir(parents=True)
    (out / finished).write_text("shape")
    (out / "summary.json").write_text('{"classes": {"car": {"status": "ok", "reconstructed": 1}}}')
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    rc = reconstruct_main(["--out", str(out), "--quiet", "stage=cameras", *(f"{k}={v}" for k, v in SMALL.items())])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error:") and "stage=cameras" in err[0], err
    assert "another --out" in err[0] and finished.rsplit("/", 1)[0] in err[0]
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_stage_cameras_into_an_empty_or_camera_only_folder_runs(base_dir, tmp_path):
    """Empty (or holding only empty per-object folders) and camera-only folders take a camera-only run."""
    out = tmp_path / "out"
    (out / "car" / "meshes").mkdir(parents=True)
    args = ["--data", str(base_dir / "annotations.json"), "--out", str(out), "--quiet", "--classes", "car",
            "stage=cameras", *(f"{k}={v}" for k, v in SMALL.items())]
    for _ in range(2):  # the second into the first's camera-only folder
        assert reconstruct_main(args) == 0
        assert json.loads((out / "summary.json").read_text())["classes"]["car"]["status"] == "cameras"
        assert (out / "car" / "cameras.json").is_file() and not any((out / "car" / "meshes").iterdir())


def test_references_of_a_split_no_object_has_is_a_user_error(base, tmp_path, capsys):
    """Else the run reconstructs nothing, says ok per class and exits 1 without a reason."""
    d = copy.deepcopy(base)
    for i, a in enumerate(d["annotations"]):
        a["split"] = "test" if i % 2 else "pool"
    out = tmp_path / "out"
    rc = reconstruct_main(["--data", str(_write(tmp_path, d)), "--out", str(out), "--quiet", "references=tset",
                           *(f"{k}={v}" for k, v in SMALL.items())])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error:"), err
    assert "references=tset" in err[0] and "'pool', 'test'" in err[0]
    assert not out.exists()


def test_run_log_is_not_opened_through_a_link(tmp_path):
    from carvi_torch.runtime import log, log_to_file
    target = tmp_path / "target.log"
    target.write_text("mine")
    (tmp_path / "run.log").symlink_to(target)
    with pytest.raises(OSError):
        with log_to_file(tmp_path / "run.log"):
            log.info("a line")
    assert target.read_text() == "mine"


def test_exit_status_says_when_nothing_came_out(base, tmp_path):
    d = copy.deepcopy(base)
    for a in d["annotations"]:
        a["truncated"] = True
    data = _write(tmp_path, d)
    rc = reconstruct_main(["--data", str(data), "--out", str(tmp_path / "o"), "--quiet", "preview=false",
                          "report=false"])
    assert rc == 1
    assert exit_status({"classes": {"car": {"reconstructed": 0, "resumed": 3}}}) == 0
    assert exit_status({"classes": {"car": {"reconstructed": 5, "status": "failed"}}}) == 1


def test_files_take_the_umask(base, tmp_path):
    code = ("import os, sys; os.umask(0o022); from carvi_torch.io.outputs import write_json; "
            f"path = {str(tmp_path / 'x.json')!r}; write_json(path, {{'a': 1}}); "
            "print(oct(os.stat(path).st_mode & 0o777))")
    [(rc, out, err)] = run_each_in_a_fresh_process([code])  # the umask is the process's own
    assert rc == 0 and out.strip() == "0o644", err


def test_export_finds_the_runs_data_and_names_a_broken_chunk(base, tmp_path, monkeypatch):
    from carvi_torch.export import export
    from carvi_torch.training import LiftedDataset

    work = tmp_path / "work"
    work.mkdir()
    _write(work, base)
    monkeypatch.chdir(work)
    s = run(_cfg(work / "run", Path("ann.json"), classes="car"), workers=0)
    assert Path(s["data"]).is_absolute()
    monkeypatch.chdir(tmp_path)  # another folder: the relative path must not be read from here
    index = export(work / "run", tmp_path / "export", resolution=8, points=32, progress=False, workers=0)
    assert len(index["samples"]) == 6
    shard = next(p for p in (tmp_path / "export" / "car" / "mask").rglob("*") if p.is_file())
    shard.write_bytes(b"broken")
    with pytest.raises(OSError, match="car/mask"):
        LiftedDataset(tmp_path / "export")[0]


# --------------------------------------------------------------------------- 14, 15. CLI and logging


def _carvi_in_process(argv: list[str], capsys) -> tuple[int, str, str]:
    """``carvi ARGV`` through ``carvi_torch.cli.main`` in this process: (exit status, stdout, stderr)."""
    from carvi_torch.cli import main

    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as e:  # a command's own --help ends its parser with SystemExit, as in a process
        rc = e.code or 0
    out, err = capsys.readouterr()
    return rc, out, err


def test_one_cli_and_a_log(base, tmp_path, capsys):
    # the version and every command's help, through the same main as the command line below (in this process:
    # each fresh process spends seconds importing torch; `python -m carvi_torch.X --help` of every module
    # runs in processes of its own in test_pipeline.py)
    said = {cmd: _carvi_in_process([cmd, "--help"] if cmd else ["--version"], capsys)
            for cmd in ("", "reconstruct", "evaluate", "export", "datasets")}
    assert said[""][0] == 0 and said[""][1].startswith("carvi_torch ")
    for cmd in ("reconstruct", "evaluate", "export", "datasets"):
        rc, out, err = said[cmd]
        assert rc == 0 and "usage:" in out and (cmd == "datasets" or "--classes" in out), (cmd, err)
    data = _write(tmp_path, base)
    out = tmp_path / "run"
    argv = ["carvi", "reconstruct", "--data", str(data), "--out", str(out), "--classes", "car", "sfm_max_outer=2",
            "sfm_polish_iters=1", "resolution=16", "proposals=3", "canvas_size=48", "preview=false", "report=false"]
    # `python -m carvi_torch.cli reconstruct ...` in a process of its own (runpy, as -m runs it); written inline
    # (CARVI_WRITERS=0): what is checked is where the messages go, and a fresh process's writers take seconds
    # to start (the writer processes of a command-line run: tools/stress_inputs.py's check in test_tools.py)
    [(rc, stdout, stderr)] = run_each_in_a_fresh_process(
        [f"import runpy, sys; sys.argv = {argv!r}; runpy.run_module('carvi_torch.cli', run_name='__main__', "
         "alter_sys=True)"], env={**os.environ, "CARVI_WRITERS": "0"})
    assert rc == 0, stderr[-2000:]
    # a warning that reaches summary.json also reaches the terminal, the log and the table
    assert "SfM stopped at its iteration limits" in stderr
    assert "SfM stopped at its iteration limits" in (out / "run.log").read_text()
    assert "warnings" in stdout.splitlines()[0] and "warning: sfm:" in stdout


def test_a_duplicate_id_leaves_the_first_objects_card_alone(base, tmp_path):
    """A copy of annotation 2 with the same id: the copy is an input problem, while the object with that id
    (the first) is reconstructed, not listed among the class's failures, and its report card has its mesh."""
    from carvi_torch.export.source import load_skips

    d = copy.deepcopy(base)
    first = next(a for a in d["annotations"] if a["id"] == 2)
    d["annotations"].append({**copy.deepcopy(first), "source": "the copy"})
    out = tmp_path / "run"
    s = run(_cfg(out, _write(tmp_path, d), classes="car", report=True), workers=0)
    c = s["classes"]["car"]
    assert any("duplicate annotation id" in p["reason"] for p in s["input_problems"])
    assert c["reconstructed"] == 6 and not c["failures"], c["failures"]
    text = (out / "report" / "cards.js").read_text()
    cards = json.loads(text[text.index("\n[") + 1:text.rindex("]") + 1])
    card = next(c for c in cards if c["id"] == "2")
    assert "skipped" not in card and card.get("mesh"), card
    assert load_skips(load_coco(_write(tmp_path, d), canvas_size=48).problems, ["car"]) == {"car": []}
