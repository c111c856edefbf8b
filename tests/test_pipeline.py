"""End to end: reconstruct on a tiny embedded collection; outputs, resume, determinism, bad input."""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import yaml
from pycocotools.coco import COCO

from carvi_torch.config import Config
from carvi_torch.runtime import StageTimer
from carvi_torch.executors import run
from carvi_torch.reconstruct import main as reconstruct_main
from conftest import PIPELINE_TINY, requires_cuda, run_each_in_a_fresh_process

ROOT = Path(__file__).resolve().parents[1]
TINY = PIPELINE_TINY


def _cfg(out, **extra):
    """The settings ``TINY`` in ``out``. The runs of this file write inline (``run(..., workers=0)``: starting
    writer processes takes a second or more a run) unless the writers are part of what a test checks: the
    session's run (``tiny``) has them, the same files either way (checked by
    :func:`test_writers_chunks_threads_and_backend_do_not_change_outputs`)."""
    return Config().override({**TINY, "out": str(out), **extra})


@pytest.fixture(scope="module")
def tiny(pipeline_run):
    """A run without ``--data`` (settings ``TINY``): it took the embedded collection from ``out/input``; the
    session's run, which test_frame.py reads too."""
    return pipeline_run


def test_outputs_exist(tiny):
    out, summary = tiny
    assert (out / "config.yaml").is_file() and (out / "summary.json").is_file() and (out / "preview.png").is_file()
    assert set(summary["classes"]) == {"aeroplane", "bottle", "car", "chair"}
    for cls, rep in summary["classes"].items():
        assert rep["objects"] == 6 and rep["viewpoint_device"] == "cpu"
        assert rep["reconstructed"] + rep["skipped"] == 6, rep["failures"]
        assert rep["reconstructed"] >= 5, (cls, rep["failures"])
        cams = json.loads((out / cls / "cameras.json").read_text())
        assert len(cams["cameras"]) == 6 and len(cams["principal_directions"]) == 3
        for entry in cams["cameras"].values():
            R = np.array(entry["refined"]["R"])
            assert abs(np.linalg.det(R) - 1) < 1e-4
            assert entry["camera_from"] == ("sfm" if entry["sfm"] is not None else "mean_shape")
            # refine_keep=better: an object that keeps its SfM camera holds it as its final camera
            if entry["sfm"] is None:
                assert entry["camera_choice"] is None
            if entry["camera_choice"] == "sfm":
                np.testing.assert_allclose(R, np.array(entry["sfm"]["R"]), atol=1e-6)
        kept = [e for e in cams["cameras"].values() if e["camera_choice"] == "sfm"]
        assert rep["refine"]["kept_sfm"]["originals"] == len(kept)
        # a tilted refined camera (refine_max_tilt_deg) is one of the kept SfM cameras
        kept_ids = {k for k, e in cams["cameras"].items() if e["camera_choice"] == "sfm"}
        assert {str(i) for i in rep["refine"]["kept_sfm"]["tilted_ids"]} <= kept_ids
        assert {e["camera_choice"] for e in cams["cameras"].values() if e["sfm"] is not None} <= {"sfm", "refined"}
        for f in (out / cls / "voxels").glob("*.npz"):
            z = np.load(f)
            assert z["occupancy"].dtype == bool and z["occupancy"].any() and z["voxel_to_camera"].shape == (4, 4)
            m = trimesh.load(out / cls / "meshes" / f"{f.stem}.ply", force="mesh")
            assert len(m.faces) > 0


def test_resolved_config_saved(tiny):
    out, _ = tiny
    import yaml

    saved = yaml.safe_load((out / "config.yaml").read_text())
    assert saved["carve"]["resolution"] == 20 and saved["surrogates"]["proposals"] == 4 and saved["out"] == str(out)
    from carvi_torch.config import read_run_config

    assert read_run_config(out / "config.yaml") == _cfg(out)  # the saved file reads back as the run's settings


def test_meshes_overlay_their_masks(tiny):
    """Meshes are in the reference camera frame in image pixels: dropping z lands on the object's mask."""
    out, summary = tiny
    coco = COCO(summary["data"])
    ious = []
    for f in sorted((out / "car" / "voxels").glob("*.npz")) + sorted((out / "chair" / "voxels").glob("*.npz")):
        z = np.load(f)
        ann = coco.anns[int(f.stem)]
        mask = coco.annToMask(ann).astype(bool)
        d, h, w = np.nonzero(z["occupancy"])
        pts = z["voxel_to_camera"] @ np.stack([d, h, w, np.ones_like(d)])
        cols = np.zeros_like(mask)
        x = np.clip(np.round(pts[0]).astype(int), 0, mask.shape[1] - 1)
        y = np.clip(np.round(pts[1]).astype(int), 0, mask.shape[0] - 1)
        cols[y, x] = True
        # voxel centres are sparse at this resolution: compare bounding boxes and coverage of the centres
        inside = mask[y, x].mean()
        ys, xs = np.nonzero(mask)
        box = np.array([xs.min(), ys.min(), xs.max(), ys.max()])
        pbox = np.array([x.min(), y.min(), x.max(), y.max()])
        span = max(box[2] - box[0], box[3] - box[1])
        assert np.abs(pbox - box).max() < 0.15 * span, (f, box, pbox)
        ious.append(inside)
    assert np.median(ious) > 0.8


def test_rerun_skips_finished(tiny, tmp_path):
    out, summary = tiny
    before = {p: p.stat().st_mtime_ns for p in out.glob("*/meshes/*.ply")}
    cameras = {p: p.read_bytes() for p in out.glob("*/cameras.json")}
    again = run(_cfg(out, preview=False, sfm_group_threads=1, viewpoint_processes=1,
                     **{"viewpoints.device": "cpu", "viewpoints.gpu_min_objects": 5}), workers=0)
    complete = []
    for cls, rep in again["classes"].items():
        assert rep["resumed"] == summary["classes"][cls]["reconstructed"]
        assert rep["reconstructed"] == 0
        if summary["classes"][cls]["reconstructed"] == rep["objects"]:
            # nothing left to do: no silhouettes prepared, no average masks, no carving
            complete.append(cls)
            assert not {"carve", "select"} & set(rep["seconds"]), (cls, rep["seconds"])
            # the first run's qualities came from its writers' results, the rerun's from the voxels files
            assert (out / cls / "cameras.json").read_bytes() == cameras[out / cls / "cameras.json"], cls
    assert complete, "no class was complete after the first run: the check above did not run"
    assert before == {p: p.stat().st_mtime_ns for p in out.glob("*/meshes/*.ply")}
    assert "resumed_from_other_settings" not in again  # only `preview`, threads and devices differed: neutral


def test_cameras_json_quality_holds_the_voxels_files_reconstruction_iou(tiny):
    """The local run takes every object's reconstruction_iou from its writer's result instead of reading the
    voxels files again: cameras.json holds the files' value (rounded as before), for exactly the objects
    written, and each quality combines its signals."""
    from carvi_torch.quality import combine

    out, summary = tiny
    checked = 0
    for cls in summary["classes"]:
        cams = json.loads((out / cls / "cameras.json").read_text())["cameras"]
        files = {f.stem: float(np.load(f)["reconstruction_iou"]) for f in (out / cls / "voxels").glob("*.npz")}
        assert len(files) == summary["classes"][cls]["reconstructed"] > 0
        for aid, entry in cams.items():
            signals = entry["quality_signals"]
            if entry["refined"] is None:  # no camera: no quality, no reconstruction
                assert entry["quality"] is None and aid not in files
                continue
            assert signals.get("reconstruction_iou") == (round(files[aid], 6) if aid in files else None), (cls, aid)
            assert entry["quality"] == round(combine(signals), 4)
            checked += aid in files
    assert checked == sum(c["reconstructed"] for c in summary["classes"].values())


def test_rerun_with_other_settings_says_so(tiny, tmp_path, capsys):
    """Resuming finished objects made under other settings keeps them, and says which settings differ."""
    import shutil

    out, summary = tiny
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    capsys.readouterr()
    again = run(_cfg(copy, data=summary["data"], preview=False, refine_iters=7, classes=["car"]), workers=0)
    want = Config().override(TINY).viewpoints.refine_iters
    assert again["resumed_from_other_settings"] == {"viewpoints.refine_iters": [want, 7]}
    assert again["classes"]["car"]["resumed"] == summary["classes"]["car"]["reconstructed"]
    assert "other settings (viewpoints.refine_iters" in capsys.readouterr().err
    assert "other settings (viewpoints.refine_iters" in (copy / "run.log").read_text()
    fresh = run(_cfg(copy, data=summary["data"], preview=False, refine_iters=7, classes=["car"], overwrite=True),
                workers=0)
    assert fresh["classes"]["car"]["resumed"] == 0
    # the cars are made again with 7; the classes this run does not touch keep their objects, made with `want`
    assert fresh["classes_from_earlier_runs"] == ["aeroplane", "bottle", "chair"]
    assert fresh["resumed_from_other_settings"] == {"viewpoints.refine_iters": [want, 7, 7]}


@pytest.fixture(scope="module")
def car_again(tmp_path_factory):
    """The car class run again from scratch with the same seed (its input generated anew), written inline
    (no writer processes), one object per chunk, the torch carving and one torch thread: the folder, the
    run's summary and the caller's torch thread count before and after the run."""
    import carvi_torch.carve.chunks as chunks

    other = tmp_path_factory.mktemp("again")
    threads = torch.get_num_threads()
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(chunks, "CPU_CHUNK_OBJECTS", 1)
        res = run(_cfg(other, classes=["car"], preview=False, carve_backend="torch"), workers=0, threads=1)
    return other, res, (threads, torch.get_num_threads())


def test_same_seed_same_voxels(tiny, car_again):
    """Same seed, same voxels, even across the run's varying parts (writer processes or inline, fused
    native or torch carving, 2 threads or 1, chunks of any size): a seed that does not fix every draw fails
    here, and so does any of those parts that changes a label (tell them apart by rerunning with one varied)."""
    out, _ = tiny
    other, _res, _threads = car_again
    files = sorted((out / "car" / "voxels").glob("*.npz"))
    assert len(files) >= 5
    for f in files:
        a, b = np.load(f), np.load(other / "car" / "voxels" / f.name)
        assert np.array_equal(a["occupancy"], b["occupancy"])
        assert np.allclose(a["voxel_to_camera"], b["voxel_to_camera"])


def test_nearest_pixel_carving_stays_close_to_bilinear(tiny, tmp_path):
    """``carve_interpolation=nearest`` through the pipeline: the same objects reconstructed, on the
    same voxel grids, with labels that differ from the bilinear run's in some voxels, under 2% of
    them (the synthetic benchmark's error figures: docs/reconstruction.md, *Nearest-pixel reading*)."""
    out, summary = tiny
    other = tmp_path / "nearest"
    res = run(_cfg(other, data=summary["data"], classes=["car"], preview=False, carve_interpolation="nearest"),
              workers=0)
    assert res["classes"]["car"]["reconstructed"] == summary["classes"]["car"]["reconstructed"]
    assert yaml.safe_load((other / "config.yaml").read_text())["carve"]["interpolation"] == "nearest"
    differ, total = 0, 0
    for f in (out / "car" / "voxels").glob("*.npz"):
        a, b = np.load(f), np.load(other / "car" / "voxels" / f.name)
        assert np.allclose(a["voxel_to_camera"], b["voxel_to_camera"])
        differ += int((a["occupancy"] != b["occupancy"]).sum())
        total += a["occupancy"].size
    assert 0 < differ < 0.02 * total, (differ, total)


def test_stage_cameras_stops(tiny, tmp_path):
    summary = run(_cfg(tmp_path, data=tiny[1]["data"], stage="cameras", classes=["chair"]))
    assert (tmp_path / "chair" / "cameras.json").is_file()
    assert not (tmp_path / "chair" / "meshes").exists()
    assert summary["classes"]["chair"]["status"] == "cameras"


def test_oracle_cameras(tiny, tmp_path):
    data = Path(tiny[1]["data"])
    summary = run(_cfg(tmp_path, data=str(data), cameras="gt", classes=["car"], preview=False), workers=0)
    assert summary["classes"]["car"]["reconstructed"] >= 5
    gt = json.loads((data.parent / "gt.json").read_text())["annotations"]
    cams = json.loads((tmp_path / "car" / "cameras.json").read_text())["cameras"]
    for aid, entry in cams.items():
        assert np.allclose(entry["refined"]["R"], gt[aid]["R"], atol=1e-4)
        assert np.allclose(entry["refined"]["t"], gt[aid]["t"], atol=1e-2)
        assert entry["camera_from"] == "ground_truth"


def _write_small(path: Path, data: dict):
    path.write_text(json.dumps(data))
    return path


def test_bad_classes_reported(tiny, tmp_path):
    """A class with too few instances, and one whose instances have < 3 keypoints: reported, run goes on."""
    out, summary = tiny
    data = json.loads(Path(summary["data"]).read_text())
    cats = {c["name"]: c["id"] for c in data["categories"]}
    car_anns = [a for a in data["annotations"] if a["category_id"] == cats["car"]]
    chair_anns = [a for a in data["annotations"] if a["category_id"] == cats["chair"]][:2]  # too few
    bottle_anns = [a for a in data["annotations"] if a["category_id"] == cats["bottle"]]
    for a in bottle_anns:  # keep two visible keypoints at most
        kp = a["keypoints"]
        seen = 0
        for k in range(0, len(kp), 3):
            if kp[k + 2] == 2:
                seen += 1
                if seen > 2:
                    kp[k:k + 3] = [0, 0, 0]
    data["annotations"] = car_anns + chair_anns + bottle_anns
    src = Path(summary["data"]).parent
    dst = tmp_path / "data"
    dst.mkdir()
    _write_small(dst / "annotations.json", data)
    (dst / "gt.json").write_text((src / "gt.json").read_text())
    res = run(_cfg(tmp_path / "out", data=str(dst / "annotations.json"), preview=False), workers=0)
    chair = res["classes"]["chair"]
    assert chair["status"] == "skipped" and "min_instances" in chair["failures"][0]["reason"]
    assert res["classes"]["car"]["reconstructed"] >= 5
    bottle = res["classes"]["bottle"]
    assert bottle["reconstructed"] + bottle["skipped"] == len(bottle_anns)
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert saved["classes"]["chair"]["failures"]


def test_cli_malformed_json(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text('{"annotations": [')
    rc = reconstruct_main(["--data", str(bad), "--out", str(tmp_path / "o"), "progress=false"])
    err = capsys.readouterr().err
    assert rc == 2 and "bad.json" in err and "line 1" in err


def test_cli_bad_override(tmp_path, capsys):
    assert reconstruct_main(["--out", str(tmp_path), "resolution=abc"]) == 2
    assert "resolution" in capsys.readouterr().err


ENTRY_POINTS = ["reconstruct", "evaluate", "export", "datasets"]


@pytest.fixture(scope="module")
def helps() -> dict[str, tuple[int, str]]:
    """``python -m carvi_torch.<module> --help`` of every entry point (``runpy``, as ``-m`` runs it), each in a
    fresh process, the processes started at once: module -> (exit status, stdout)."""
    codes = [f"import runpy, sys; sys.argv = ['{m}', '--help']; runpy.run_module('carvi_torch.{m}', "
             "run_name='__main__', alter_sys=True)" for m in ENTRY_POINTS]
    res = run_each_in_a_fresh_process(codes, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    return {m: (rc, out) for m, (rc, out, _err) in zip(ENTRY_POINTS, res)}


@pytest.mark.parametrize("module", ENTRY_POINTS)
def test_help(module, helps):
    rc, out = helps[module]
    assert rc == 0 and "usage" in out.lower()


def test_reference_split_and_saved_proposals(tiny, tmp_path):
    """references=test reconstructs only test objects; save_proposals keeps every proposal, and the vote of
    the best-ranked ones is the output."""
    out, summary = tiny
    data = json.loads(Path(summary["data"]).read_text())
    cars = [a for a in data["annotations"] if a["category_id"] == next(c["id"] for c in data["categories"]
                                                                     if c["name"] == "car")]
    for a in cars[:2]:
        a["split"] = "test"
    dst = tmp_path / "data"
    dst.mkdir()
    (dst / "annotations.json").write_text(json.dumps(data))
    res = run(_cfg(tmp_path / "o", data=str(dst / "annotations.json"), classes=["car"], references="test",
                   save_proposals=True, preview=False))
    car = res["classes"]["car"]
    assert car["references"] == 2 and car["reconstructed"] + car["skipped"] == 2 and car["reconstructed"] >= 1
    assert len(list((tmp_path / "o" / "car" / "voxels").glob("*.npz"))) == car["reconstructed"]
    for a in cars[:2]:
        if not (tmp_path / "o" / "car" / "voxels" / f"{a['id']}.npz").is_file():
            continue
        z = np.load(tmp_path / "o" / "car" / "proposals" / f"{a['id']}.npz")
        vox = np.load(tmp_path / "o" / "car" / "voxels" / f"{a['id']}.npz")
        occ = np.unpackbits(z["occupancy_bits"], axis=1)[:, :int(np.prod(z["shape"]))].reshape(-1, *z["shape"])
        assert occ.shape[0] == TINY["proposals"]
        # the output is the vote of the best-ranked proposals (select.consensus), ranked from the saved scores
        from carvi_torch.config import SelectConfig
        from carvi_torch.select import rank_proposals, vote_proposals

        occ = torch.from_numpy(occ.astype(bool))
        ok = torch.from_numpy(z["valid"]).bool() & occ.flatten(1).any(1)
        order, best = rank_proposals(torch.from_numpy(z["scores"])[None].float(), torch.from_numpy(z["misses"])[None],
                                     ok[None])
        assert int(best[0]) == int(z["best"])
        top = order[:, :SelectConfig().consensus]
        voted, T = vote_proposals(occ, torch.from_numpy(z["voxel_to_camera"]),
                                  torch.where(ok[None].gather(1, top), top, torch.full_like(top, -1)))
        assert np.array_equal(voted[0].numpy(), vox["occupancy"])
        assert np.allclose(T[0].numpy(), vox["voxel_to_camera"])


def _files(root: Path, cls: str) -> dict:
    """Every output file of a class: voxels as arrays, meshes and scores as bytes."""
    out = {}
    for f in sorted((root / cls / "voxels").glob("*.npz")):
        z = np.load(f)
        out[f"voxels/{f.name}"] = {k: z[k] for k in z.files}
    for f in sorted((root / cls / "meshes").glob("*.ply")):
        out[f"meshes/{f.name}"] = f.read_bytes()
    out["proposal_scores.json"] = (root / cls / "proposal_scores.json").read_bytes()
    return out


def test_writers_chunks_threads_and_backend_do_not_change_outputs(tiny, car_again):
    """Inline writing vs writer processes, one object per chunk vs the default, the torch carving vs the
    default backend (the fused kernel where it builds): the same files, byte for byte; the torch thread
    count of the caller is restored; summary.json says which carving ran."""
    from carvi_torch.carve import native

    out, summary = tiny
    assert summary["writer_workers"] >= 1  # the fixture ran with writer processes
    assert summary["carve_backend"]["backend"] == ("fused" if native.available() else "torch")
    inline, res, (threads_before, threads_after) = car_again
    assert threads_after == threads_before
    assert res["writer_workers"] == 0 and res["torch_threads"] == 1
    assert res["carve_backend"] == {"backend": "torch", "variant": None, "reason": None}
    a, b = _files(out, "car"), _files(inline, "car")
    assert a.keys() == b.keys() and len(a) > 3
    for k in a:
        if k.startswith("voxels/"):
            assert a[k].keys() == b[k].keys()
            for name in a[k]:
                assert np.array_equal(a[k][name], b[k][name]), (k, name)
        else:
            assert a[k] == b[k], k
    for stage in ("carve", "select", "mesh", "write", "handoff"):
        assert res["classes"]["car"]["seconds"][stage] > 0


def _same_meshes_as_skimage(out: Path, cls: str) -> int:
    """Every mesh of ``out/cls`` equals scikit-image's mesh of its voxels (carvi_torch.mesh) within
    1e-5 voxel, with the same triangles; returns how many were checked."""
    from carvi_torch.mesh import occupancy_to_mesh
    from test_marching import VOXEL_TOL, assert_same_mesh

    files = sorted((out / cls / "voxels").glob("*.npz"))
    for f in files:
        z = np.load(f)
        ref = occupancy_to_mesh(z["occupancy"], z["voxel_to_camera"])
        m = trimesh.load(out / cls / "meshes" / f"{f.stem}.ply", force="mesh", process=False)
        tol = VOXEL_TOL * float(np.abs(z["voxel_to_camera"][:3, :3]).sum(1).max())
        assert_same_mesh(np.asarray(ref.vertices), np.asarray(ref.faces), np.asarray(m.vertices),
                         np.asarray(m.faces), tol)
    return len(files)


def test_torch_mesher_keeps_voxels_and_gives_scikit_image_meshes(tiny, tmp_path):
    """``mesher=torch`` (the CUDA default) run on the CPU, with ``largest_component``: the voxels are the
    writers' run's (largest component taken) byte for byte, and every mesh is scikit-image's mesh of its
    reconstructed grid within 1e-5 voxel with the same triangles; the meshing is booked in the run."""
    from carvi_torch.io.layout import SETTINGS_MEMBER, held_settings
    from carvi_torch.mesh import largest_component

    out, summary = tiny
    res = run(_cfg(tmp_path / "t", data=summary["data"], classes=["car"], preview=False, mesher="torch",
                   largest_component=True), workers=0)
    assert res["classes"]["car"]["reconstructed"] == summary["classes"]["car"]["reconstructed"]
    assert res["classes"]["car"]["seconds"]["mesh_device"] > 0
    for f in (out / "car" / "voxels").glob("*.npz"):
        a, b = np.load(f), np.load(tmp_path / "t" / "car" / "voxels" / f.name)
        assert np.array_equal(largest_component(a["occupancy"]), b["occupancy"])
        assert all(np.array_equal(a[k], b[k]) for k in a.files if k not in ("occupancy", SETTINGS_MEMBER))
        assert held_settings(b) == {**held_settings(a), "mesh.mesher": "torch", "mesh.largest_component": True}
    assert _same_meshes_as_skimage(tmp_path / "t", "car") >= 5


def _slow_job(job):
    time.sleep(job["sleep"])
    return dict(ok=True, i=job["i"])


def test_writer_books_back_pressure(monkeypatch):
    """Submitting more than ``4 * workers`` objects (or a larger ``backlog``) waits for the oldest (``blocked``
    counts that wait); results stay in submission order."""
    from carvi_torch.io import writer as W

    monkeypatch.setattr(W.Writer, "write", staticmethod(_slow_job))
    w = W.Writer(0)  # inline: no wait is ever needed
    got = []
    w.submit(dict(i=0, sleep=0.0), got.append)
    assert w.blocked == 0.0 and got == [dict(ok=True, i=0)]
    w = W.Writer(1)
    try:
        got = []
        for i in range(4):  # up to 4 * workers pending: never blocks
            w.submit(dict(i=i, sleep=0.0), got.append)
        assert w.blocked == 0.0 and len(w.pending) <= 4
        for i in range(4, 10):  # every further object first books the oldest
            w.submit(dict(i=i, sleep=0.05), got.append)
            assert len(w.pending) <= 4
        assert w.blocked > 0 and len(got) >= 6
        w.drain()
        blocked = w.blocked
        for i in range(10, 18):  # a chunk of 8 handed over at once may wait whole (backlog): never blocks
            w.submit(dict(i=i, sleep=0.05), got.append, backlog=8)
        assert w.blocked == blocked and len(w.pending) == 8
        w.submit(dict(i=18, sleep=0.0), got.append, backlog=8)  # the ninth waits for the oldest
        assert w.blocked > blocked and len(w.pending) == 8
        w.drain()
    finally:
        w.close()
    assert [g["i"] for g in got] == list(range(19))


def test_object_files_are_moved_into_place_unflushed_and_run_files_flushed(tmp_path, monkeypatch):
    """An object's voxels and mesh files are written whole and moved into place without an ``fsync`` (a damaged
    one is redone on resume: test_robustness); its proposals and scores (studies, which no resume check reads)
    and the run's own files with one."""
    import os

    from carvi_torch.io import write_worker
    from carvi_torch.io.outputs import write_json

    synced = []
    monkeypatch.setattr(os, "fsync", lambda fd: synced.append(fd))
    occ = np.zeros((8, 8, 8), bool)
    occ[2:6, 2:6, 2:6] = True
    job = dict(occupancy=occ, voxel_to_image=np.eye(4), voxel_to_canvas=np.eye(4), canvas_scale=1.0,
               canvas_offset=np.zeros(2, np.float32), surrogates=np.zeros(0, np.int64), largest_component=False,
               proposals={"x": np.ones(3)}, proposals_path=str(tmp_path / "p.npz"), scores={"a": 1},
               scores_path=str(tmp_path / "s.json"), voxel_path=str(tmp_path / "v.npz"),
               mesh_path=str(tmp_path / "m.ply"))
    assert write_worker.write_object(job)["ok"] and len(synced) == 2  # the proposals and the scores
    assert all((tmp_path / n).is_file() for n in ("p.npz", "s.json", "v.npz", "m.ply"))
    write_json(tmp_path / "summary.json", {"ok": True})
    assert len(synced) == 3


def test_writer_start_failure_surfaces_in_the_run(monkeypatch):
    """The writer processes start in a thread: a failure there is raised where the run first needs them
    (and a cancelling close, on an error's way out, does not raise it again)."""
    from carvi_torch.io import writer as W

    monkeypatch.setattr(W, "start_method", lambda: "no-such-start-method")
    w = W.Writer(1)
    for _ in range(2):  # and again on the next object: never written inline in the processes' place
        with pytest.raises(ValueError, match="no-such-start-method"):
            w.submit(dict(i=0), lambda res: None)
    w.close(cancel=True)
    w = W.Writer(1)
    with pytest.raises(ValueError, match="no-such-start-method"):
        w.close()


def test_writer_and_thread_rules(monkeypatch):
    from carvi_torch.io.writer import writer_workers
    from carvi_torch.runtime import intra_op_threads

    monkeypatch.setenv("CARVI_WRITERS", "3")
    monkeypatch.setenv("CARVI_THREADS", "2")
    assert writer_workers() == 3 and intra_op_threads(3) == 2
    monkeypatch.delenv("CARVI_WRITERS")
    monkeypatch.delenv("CARVI_THREADS")
    assert writer_workers("cameras") == 0
    cores = len(os.sched_getaffinity(0))
    assert writer_workers() == min(8, max(1, cores - 1))
    assert writer_workers("all", torch.device("cpu")) == min(8, max(1, cores - 1))
    assert writer_workers("all", torch.device("cuda")) == min(16, max(1, cores - 1))  # no device needed
    # the CPU: the cores less half the writers (who need about a quarter of the main process's CPU time);
    # a GPU: the cores less the writers
    assert intra_op_threads(writer_workers()) == max(1, cores - writer_workers() // 2)
    monkeypatch.setattr("carvi_torch.runtime.cores", lambda: 2)
    assert [intra_op_threads(1), intra_op_threads(1, torch.device("cuda")), intra_op_threads(1, "cuda:0")] == [2, 1, 1]
    monkeypatch.setattr("carvi_torch.runtime.cores", lambda: 16)
    assert [intra_op_threads(8), intra_op_threads(15, "cuda"), intra_op_threads(0, "cpu")] == [12, 1, 16]
    monkeypatch.setenv("CARVI_THREADS", "many")
    with pytest.raises(ValueError, match="CARVI_THREADS"):
        intra_op_threads(1)


@requires_cuda
@pytest.mark.parametrize("where", ["auto", "run"])
def test_cuda_run_matches_cpu(tiny, tmp_path, where):
    """device=cuda end to end: the same objects reconstructed; with the true cameras (no SfM or refinement
    differences) the voxels agree with the CPU run but for float rounding at a few voxels. ``auto`` makes this
    small class's viewpoint stage on the CPU, ``run`` on the GPU (the path of a class of gpu_min_objects)."""
    out, summary = tiny
    kw = dict(data=summary["data"], classes=["car"], preview=False, cameras="gt")
    cpu = run(_cfg(tmp_path / "cpu", **kw), workers=0)
    gpu = run(_cfg(tmp_path / "gpu", device="cuda", **{"viewpoints.device": where}, **kw))
    assert gpu["device"].startswith("cuda") and gpu["peak_cuda_mb"] > 0
    assert gpu["classes"]["car"]["viewpoint_device"].startswith("cpu" if where == "auto" else "cuda")
    assert cpu["classes"]["car"]["viewpoint_device"] == "cpu"
    assert gpu["classes"]["car"]["reconstructed"] == cpu["classes"]["car"]["reconstructed"] >= 5
    agree = []
    for f in (tmp_path / "cpu" / "car" / "voxels").glob("*.npz"):
        a, b = np.load(f)["occupancy"], np.load(tmp_path / "gpu" / "car" / "voxels" / f.name)["occupancy"]
        agree.append((a == b).mean() if a.shape == b.shape else 0.0)
    assert np.median(agree) > 0.999 and min(agree) > 0.95
    # on CUDA the meshes come from the batched torch marching cubes: scikit-image's within the tolerance
    assert gpu["classes"]["car"]["seconds"]["mesh_device"] > 0
    assert _same_meshes_as_skimage(tmp_path / "gpu", "car") >= 5


@requires_cuda
def test_cuda_run_with_viewpoints_on_the_cpu_matches_the_cpu_run(tiny, tmp_path):
    """``viewpoints.device=cpu`` in a CUDA run: the viewpoint stage runs on the CPU, as in a CPU run, so the
    cameras are the CPU run's (up to the threads' rounding) with the same choices, and the voxels agree but for
    float rounding at a few voxels."""
    from carvi_torch.cameras import geodesic_angle

    out, summary = tiny
    kw = dict(data=summary["data"], classes=["car"], preview=False)
    cpu = run(_cfg(tmp_path / "cpu", **kw), workers=0)
    gpu = run(_cfg(tmp_path / "gpu", device="cuda", **{"viewpoints.device": "cpu"}, **kw))
    assert gpu["device"].startswith("cuda") and gpu["classes"]["car"]["reconstructed"] >= 5
    assert gpu["classes"]["car"]["reconstructed"] == cpu["classes"]["car"]["reconstructed"]
    cams = [json.loads((tmp_path / d / "car" / "cameras.json").read_text())["cameras"] for d in ("cpu", "gpu")]
    assert cams[0].keys() == cams[1].keys()
    assert all(c.get("camera_choice") == cams[1][a].get("camera_choice") for a, c in cams[0].items())
    both = [a for a, c in cams[0].items() if c.get("refined") and cams[1][a].get("refined")]
    R = [torch.tensor([c[a]["refined"]["R"] for a in both], dtype=torch.float64) for c in cams]
    assert len(both) >= 5 and torch.rad2deg(geodesic_angle(*R)).max() < 0.1
    agree = []
    for f in (tmp_path / "cpu" / "car" / "voxels").glob("*.npz"):
        a, b = np.load(f)["occupancy"], np.load(tmp_path / "gpu" / "car" / "voxels" / f.name)["occupancy"]
        agree.append((a == b).mean() if a.shape == b.shape else 0.0)
    assert np.median(agree) > 0.999 and min(agree) > 0.95


@requires_cuda
def test_cuda_run_with_viewpoint_processes_matches_viewpoints_on_the_cpu(tiny, tmp_path):
    """``viewpoint_processes=2`` in a CUDA run: the classes' viewpoint stages made in worker processes on the CPU
    (with the run's thread count) give every class the cameras.json of a CUDA run with ``viewpoints.device=cpu``,
    byte for byte, and the same objects reconstructed."""
    out, summary = tiny
    kw = dict(data=summary["data"], classes=["aeroplane", "car", "chair"], preview=False, device="cuda")
    base = run(_cfg(tmp_path / "base", **{"viewpoints.device": "cpu"}, **kw))
    procs = run(_cfg(tmp_path / "procs", viewpoint_processes=2, **kw))
    for c in kw["classes"]:
        assert procs["classes"][c]["reconstructed"] == base["classes"][c]["reconstructed"] >= 5
        assert (tmp_path / "procs" / c / "cameras.json").read_bytes() == (
            tmp_path / "base" / c / "cameras.json").read_bytes()


@requires_cuda
def test_cuda_chunk_has_no_per_object_host_reads(tiny):
    """The device work of a chunk reads back from the GPU a fixed number of times, not once per object
    (a few more for a larger chunk are allowed: one per further group of equal sub-sampling in the
    selection's projections).

    Both chunks hold only references that have a surrogate triplet: a chunk with no valid
    proposal skips the carving and selection altogether, and would make a low baseline."""
    import warnings

    import carvi_torch.pipeline as P
    from carvi_torch.io import coco

    out, summary = tiny
    cfg = _cfg(out, data=summary["data"], device="cuda")
    loaded = coco.load_coco(summary["data"], canvas_size=cfg.input.canvas_size, margin=cfg.input.canvas_margin,
                            device=torch.device("cuda"), classes=["car"])
    plan, todo, report = P.prepare_class(loaded.collections["car"], cfg, torch.device("cuda"),
                                         torch.Generator().manual_seed(0))
    trip = plan.surrogates.triplets
    good = [i for i in todo if trip is None or i not in trip.reasons]
    counts = []
    for R in (1, len(good)):
        ids = torch.tensor(good[:R], device="cuda")
        torch.cuda.synchronize()
        torch.cuda.set_sync_debug_mode("warn")
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                P.carve_and_select(ids, plan, cfg, StageTimer("cuda"))
        finally:
            torch.cuda.set_sync_debug_mode(0)
        counts.append(len(caught))
    assert len(good) >= 4 and counts[0] > 0 and counts[1] <= counts[0] + 4, counts


def test_silhouette_robust_reaches_refinement(tiny, monkeypatch, tmp_path):
    """``silhouette_robust`` is handed to the refinement: 0 means the paper's squared penalty (None)."""
    from carvi_torch.viewpoints import camera_fit as Rf

    seen = []
    orig = Rf.refine_cameras

    def spy(*args, **kwargs):
        seen.append(kwargs.get("silhouette_robust", "missing"))
        return orig(*args, **kwargs)

    monkeypatch.setattr(Rf, "refine_cameras", spy)
    for value, expected in ((0.0, None), (0.3, 0.3)):
        run(_cfg(tmp_path / str(value), data=tiny[1]["data"], classes=["car"], stage="cameras",
                 silhouette_robust=value, preview=False))
        assert seen[-1] == expected


@pytest.mark.parametrize("workers", [0, 1])
def test_a_failing_write_is_booked_on_its_object(tiny, tmp_path, workers, monkeypatch):
    """An error while writing an object (here: a file stands where its meshes folder should be, as if made
    after the run's up-front check, which is skipped) is that object's failure, with its reason, in its own
    class; the run goes on and the writers are stopped."""
    from carvi_torch.executors import common
    monkeypatch.setattr(common, "_check_class_folders", lambda out, keys: None)
    for cls in ("car", "chair"):
        (tmp_path / cls).mkdir(parents=True)
        (tmp_path / cls / "meshes").write_text("not a folder")
    summary = run(_cfg(tmp_path, data=tiny[1]["data"], classes=["car", "chair"]), workers=workers)
    for cls in ("car", "chair"):
        rep = summary["classes"][cls]
        assert rep["status"] != "failed", rep
        assert rep["reconstructed"] == 0 and rep["skipped"] == 6, rep
        written = [f for f in rep["failures"] if "writing failed" in f["reason"]]
        assert len(written) >= 4 and all("FileExistsError" in f["reason"] for f in written), written
        assert all(f["stage"] == "carve" for f in rep["failures"] if f not in written)
        assert (tmp_path / cls / "meshes").read_text() == "not a folder"


def test_report_failures_do_not_depend_on_booking_order():
    from carvi_torch.io.results import ClassReport

    a, b = ClassReport("car"), ClassReport("car")
    entries = [("mesh", 7), ("carve", 3), ("class", None), ("carve", 12)]
    for stage, aid in entries:
        a.skip(f"{stage} failed", stage, aid)
    for stage, aid in reversed(entries):
        b.skip(f"{stage} failed", stage, aid)
    assert a.to_dict()["failures"] == b.to_dict()["failures"]
    assert [f["annotation_id"] for f in a.to_dict()["failures"]] == [None, 3, 7, 12]


def test_a_class_failing_midway_keeps_finished_objects_and_their_scores(tiny, monkeypatch, tmp_path):
    """An error after the first chunk: the class is reported failed, the run goes on, the objects of
    the first chunk are written with their proposal scores, and a rerun finishes the rest."""
    from carvi_torch import pipeline as P
    from carvi_torch.carve import chunks

    orig = P.carve_and_select
    calls = {"n": 0}

    def flaky(ids, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 2:
            raise RuntimeError("simulated failure in the second chunk")
        return orig(ids, *args, **kwargs)

    monkeypatch.setattr(P, "carve_and_select", flaky)
    monkeypatch.setattr(chunks, "CPU_CHUNK_OBJECTS", 3)
    data = tiny[1]["data"]
    summary = run(_cfg(tmp_path, data=data, classes=["car"]), workers=0)
    rep = summary["classes"]["car"]
    assert rep["status"] == "failed" and "simulated failure" in rep["failures"][0]["reason"]
    written = sorted(p.stem for p in (tmp_path / "car" / "meshes").glob("*.ply"))
    scored = sorted(p.stem for p in (tmp_path / "car" / "scores").glob("*.json"))  # one file per finished object
    assert 1 <= len(written) <= 3 and scored == written
    assert not (tmp_path / "car" / "proposal_scores.json").exists()  # merged only when a class ends
    monkeypatch.setattr(P, "carve_and_select", orig)
    again = run(_cfg(tmp_path, data=data, classes=["car"], preview=False), workers=0)["classes"]["car"]
    assert again["resumed"] == len(written) and again["resumed"] + again["reconstructed"] + again["skipped"] == 6
    merged = json.loads((tmp_path / "car" / "proposal_scores.json").read_text())
    assert set(written) <= set(merged) and len(merged) == again["resumed"] + again["reconstructed"]


def test_shape_groups_run_end_to_end(tmp_path, procedural_input):
    """``sfm_groups > 1`` through every stage: the fit is reported, cameras.json and meshes are written."""
    procedural_input(tmp_path)  # the embedded collection of the session (6 per class), where the run looks for it
    # the split kept on the keypoint rules alone; what is checked is that the per-group paths run and are
    # reported, not how far the SfM and the EM converge: 40 outer steps and 2 EM rounds (the defaults: 200, 6)
    summary = run(_cfg(tmp_path, classes=["car"], sfm_groups=2, sfm_group_min=2, sfm_group_misfit=0,
                       sfm_group_hull_gain=-1, sfm_max_outer=40, sfm_group_rounds=2, preview=False), workers=0)
    info = summary["classes"]["car"]["sfm_groups"]
    assert info["groups"] == 2 and sum(info["sizes"]) == 6  # this seed splits: the per-group paths run
    assert len(info["candidates"]) == 2 and all(c["k"] == 2 for c in info["candidates"])
    cams = json.loads((tmp_path / "car" / "cameras.json").read_text())
    assert len(cams["shape_groups"]) == 2 and {c["shape_group"] for c in cams["cameras"].values()} == {0, 1}
    assert summary["classes"]["car"]["reconstructed"] == 6


def test_local_run_records_the_executor_fields_a_ray_run_does(tiny):
    """README (*On a cluster*): ``summary.json["executor"]`` = ``{name, address, nodes, tasks, retries}`` on every
    executor; a local run: this machine, one task per class, no retries."""
    import platform

    out, summary = tiny
    on_disk = json.loads((out / "summary.json").read_text())["executor"]
    assert on_disk == summary["executor"] == {"name": "local", "address": None, "nodes": [platform.node()],
                                              "tasks": len(summary["classes"]), "retries": 0}


def test_a_rerun_with_other_procedural_settings_runs_on_the_collection_they_make(tmp_path):
    """The embedded default in ``OUT/input`` follows ``procedural_instances`` and ``seed`` on a rerun into the same
    ``--out`` (the run reconstructs the objects its config.yaml names, not those of the first run)."""
    def car_objects(**extra):
        run(_cfg(tmp_path, classes=["car"], preview=False, overwrite=True, **extra), workers=0)
        data = json.loads((tmp_path / "input" / "annotations.json").read_text())
        cams = json.loads((tmp_path / "car" / "cameras.json").read_text())["cameras"]
        return data, sorted(cams)

    data, cams = car_objects(procedural_instances=3, seed=0)
    car = next(c["id"] for c in data["categories"] if c["name"] == "car")
    assert len(cams) == 3 and data["info"]["seed"] == 0
    data, cams = car_objects(procedural_instances=4, seed=1)
    assert len(cams) == 4 and data["info"]["seed"] == 1
    assert len([a for a in data["annotations"] if a["category_id"] == car]) == 4
    assert yaml.safe_load((tmp_path / "config.yaml").read_text())["seed"] == 1


def test_resumed_objects_follow_the_refitted_cameras(tiny, tmp_path):
    """One object's keypoints edited: the cameras are refitted jointly (every camera moves), the other objects
    are resumed, and every voxels file's ``voxel_to_object`` is its grid mapped by the camera cameras.json now
    holds (the resumed ones included)."""
    import shutil

    out, summary = tiny
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    data = json.loads(Path(summary["data"]).read_text())
    car = next(c["id"] for c in data["categories"] if c["name"] == "car")
    ann = next(a for a in data["annotations"] if a["category_id"] == car)
    k = next(j for j in range(0, len(ann["keypoints"]), 3) if ann["keypoints"][j + 2] > 0)
    ann["keypoints"][k] += 4.0
    edited = tmp_path / "annotations.json"
    edited.write_text(json.dumps(data))
    before = json.loads((copy / "car" / "cameras.json").read_text())["cameras"]
    again = run(_cfg(copy, data=str(edited), preview=False, classes=["car"]), workers=0)
    assert again["classes"]["car"]["resumed"] == summary["classes"]["car"]["reconstructed"] - 1
    cams = json.loads((copy / "car" / "cameras.json").read_text())["cameras"]
    moved = 0
    for f in sorted((copy / "car" / "voxels").glob("*.npz")):
        cam = cams[f.stem]["refined"]
        R, s, t = np.array(cam["R"]), float(cam["s"]), np.array(cam["t"])
        to_object = np.eye(4)
        to_object[:3, :3], to_object[:3, 3] = R.T / s, -(R.T[:, :2] @ t) / s
        z = np.load(f)
        assert np.allclose(z["voxel_to_object"], to_object @ z["voxel_to_camera"], atol=1e-9), f.stem
        moved += f.stem != str(ann["id"]) and not np.allclose(before[f.stem]["refined"]["R"], R, atol=1e-9)
    assert moved > 0  # resumed objects whose camera the refit moved


def test_readme_names_every_member_of_a_voxels_file(tiny):
    """README's table of a run's files names every array a ``<class>/voxels/<id>.npz`` holds."""
    out, _ = tiny
    row = next(line for line in (ROOT / "README.md").read_text().splitlines()
               if line.startswith("| `<class>/voxels/<id>.npz` |"))
    members = set(np.load(next((out / "car" / "voxels").glob("*.npz"))).files)
    assert {"occupancy", "voxel_to_camera", "voxel_to_object", "input_fingerprint"} <= members
    assert [m for m in sorted(members) if f"`{m}" not in row] == []


@pytest.mark.parametrize("ending", ["reconstructed", "skipped", "failed", "no usable object"])
def test_files_of_objects_the_data_no_longer_holds_are_named(tmp_path, caplog, ending):
    """A rerun into an ``--out`` whose class folder holds files of objects that the data no longer has (other
    ``--data``, fewer ``procedural_instances``) keeps them but says so: one warning line and ``summary.json``'s
    ``other_objects``; the current objects' files are not counted. The same for every class of the run, however
    it ends: reconstructed, skipped (too few objects, no camera), failed, or asked for with no usable object."""
    import logging
    from types import SimpleNamespace

    from carvi_torch.executors.common import announce, book_class
    from carvi_torch.io.coco import LoadResult
    from carvi_torch.io.results import ClassReport

    cdir = tmp_path / "car"
    for kind, ext in (("meshes", "ply"), ("voxels", "npz")):
        (cdir / kind).mkdir(parents=True)
        for stem in ("2", "17", "9", "x-d6b96a97"):
            (cdir / kind / f"{stem}.{ext}").write_bytes(b"")
    (cdir / "voxels" / ".17.npz.abc.tmp").write_bytes(b"")  # a write cut short: no object's file
    usable = ending != "no usable object"
    coll = SimpleNamespace(annotation_ids=[2, 3], meta=SimpleNamespace(name="car", key="car"))
    loaded = LoadResult(collections={"car": coll} if usable else {},
                        dataset={"categories": [{"id": 1, "name": "car", "keypoints": ["a", "b", "c"]}]})
    setup = SimpleNamespace(loaded=loaded, summary={"classes": {}}, changed={}, out=tmp_path, earlier={},
                            cfg=SimpleNamespace(classes=["car"]))
    with caplog.at_level(logging.WARNING):
        announce(setup)
        if usable:
            status = "ok" if ending == "reconstructed" else ending
            book_class(setup, "car", ClassReport("car", objects=2, status=status))
    stems = ["9", "17", "x-d6b96a97"] if usable else ["2", "9", "17", "x-d6b96a97"]
    assert setup.summary["classes"]["car"]["other_objects"] == {"count": len(stems), "stems": stems}
    lines = [r.getMessage() for r in caplog.records if "no longer holds" in r.getMessage()]
    assert len(lines) == 1 and lines[0].startswith(f"  car: {len(stems)} object(s)") and ", ".join(stems) in lines[0]
    if usable:  # booked into summary.json as it stands
        assert json.loads((tmp_path / "summary.json").read_text())["classes"]["car"]["other_objects"]["stems"] == stems


def test_a_long_list_of_files_kept_names_five_and_counts_the_rest():
    """The warnings about files an earlier run left name the first five and say how many more there are."""
    from carvi_torch.io.layout import ResumeCheck

    stems = [str(i) for i in range(10, 17)]
    check = ResumeCheck(others=stems, other_formats=[f"{s}.ply" for s in stems[:5]])
    others, formats = check.lines("car")
    assert "(10, 11, 12, 13, 14 and 2 more); cameras.json" in others, others
    assert "(10.ply, 11.ply, 12.ply, 13.ply, 14.ply): not this run's" in formats, formats


def test_a_class_skipped_before_its_viewpoints_names_files_it_no_longer_holds(tmp_path):
    """A run whose every class has too few objects (skipped before the viewpoint stage) still names the files in a
    class's folder of objects the data does not hold, in ``summary.json``."""
    from carvi_torch.reconstruct import main

    out = tmp_path / "run"
    (out / "car" / "meshes").mkdir(parents=True)
    (out / "car" / "meshes" / "999.ply").write_bytes(b"")
    assert main(["--out", str(out), "--quiet", "procedural_instances=2", "preview=false", "report=false"]) == 1
    classes = json.loads((out / "summary.json").read_text())["classes"]
    assert classes["car"]["status"] == "skipped" and classes["car"]["other_objects"] == {"count": 1, "stems": ["999"]}
    assert [k for k, c in classes.items() if "other_objects" in c] == ["car"]


def test_a_class_asked_for_without_a_usable_object_is_reported_skipped(caplog):
    """A class of the data asked for with no usable object is a skipped class in the summary and a warning (a
    name that is no class of the data never gets here: the run refuses it, tests/test_cli.py)."""
    import logging
    from types import SimpleNamespace

    from carvi_torch.executors.common import announce
    from carvi_torch.io.coco import LoadResult

    data = {"categories": [{"id": 1, "name": "aeroplane"}, {"id": 2, "name": "chair"}]}
    setup = SimpleNamespace(loaded=LoadResult(collections={}, dataset=data), summary={"classes": {}}, changed={},
                            out=Path("run"), cfg=SimpleNamespace(classes=["chair"]))
    with caplog.at_level(logging.WARNING):
        announce(setup)
    assert setup.summary["classes"] == {"chair": {"status": "skipped", "objects": 0, "reconstructed": 0, "failures": [
        {"stage": "load", "reason": "no usable object of this class"}]}}
    assert "chair: no usable object of this class" in caplog.text


@pytest.mark.parametrize("fmt", ["obj", "off", "ply", "stl"])
@pytest.mark.parametrize("cut", ["line_end", "mid_line"])
def test_a_mesh_file_cut_short_is_not_finished_in_any_format(tmp_path, fmt, cut):
    """The voxels file records the faces of the mesh file as written (``io.layout.MESH_MEMBER``), so a mesh cut
    short is found where its format states no counts (OBJ; and an OFF file cut at a line end still parses): the
    resume check gives a reason and the object is redone. The whole file is a finished object's; a voxels file
    without the record (an older run's) keeps the check it had."""
    from carvi_torch.io import write_worker
    from carvi_torch.io.layout import MESH_MEMBER, finished

    occ = np.zeros((10, 10, 10), bool)
    occ[2:8, 3:7, 2:8] = True
    mesh_path, voxel_path = tmp_path / "meshes" / f"1.{fmt}", tmp_path / "voxels" / "1.npz"
    mesh_path.parent.mkdir()
    voxel_path.parent.mkdir()
    job = dict(occupancy=occ, voxel_to_image=np.eye(4), voxel_to_canvas=np.eye(4), canvas_scale=1.0,
               canvas_offset=np.zeros(2, np.float32), surrogates=np.zeros(0, np.int64), largest_component=False,
               voxel_path=str(voxel_path), mesh_path=str(mesh_path))
    assert write_worker.write_object(job)["ok"]
    assert finished(tmp_path, 1, fmt) is True
    whole = mesh_path.read_bytes()
    at = int(len(whole) * 0.8)
    if cut == "line_end" and fmt in ("obj", "off"):
        at = whole.rindex(b"\n", 0, at) + 1
    mesh_path.write_bytes(whole[:at])
    why = finished(tmp_path, 1, fmt)
    assert isinstance(why, str) and ("cut short" in why or "unreadable" in why), why
    with np.load(voxel_path) as z:  # an older run's voxels file: no record
        members = {k: z[k] for k in z.files if k != MESH_MEMBER}
    np.savez(voxel_path, **members)
    mesh_path.write_bytes(whole)
    assert finished(tmp_path, 1, fmt) is True
