"""Reruns into one ``--out`` with other settings or inputs: what the summary records of how the finished objects
were made, which settings redo objects (the canvas) and which are taken care of object by object (the mesh
format), counts that add up, and class records that agree with the files.

Every test starts from a copy of one finished run of six procedural cars and six chairs.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import trimesh

from carvi_torch.config import Config
from carvi_torch.executors import run
from carvi_torch.io.layout import MESH_MEMBER, finished

SMALL = {"resolution": 16, "proposals": 3, "canvas_size": 48, "progress": False, "refine_iters": 20,
         "plane_size": 24, "preview": False, "report": False}


@pytest.fixture(scope="module")
def first(tmp_path_factory) -> tuple[Path, Path]:
    """``(data, out)``: annotations (with gt.json beside them) and a finished run of both classes on them."""
    from carvi_torch.synthetic import procedural

    d = tmp_path_factory.mktemp("data")
    procedural.write_default_collection(d, instances_per_class=6, categories=["car", "chair"], seed=1,
                                        progress=False)
    out = tmp_path_factory.mktemp("first") / "run"
    summary = run(_cfg(out, d / "annotations.json"), workers=0)
    assert [summary["classes"][c]["reconstructed"] for c in ("car", "chair")] == [6, 6]
    return d / "annotations.json", out


def _cfg(out: Path, data: Path, **extra) -> Config:
    return Config().override({**SMALL, "out": str(out), "data": str(data), **extra})


@pytest.fixture
def copy(first, tmp_path) -> tuple[Path, Path]:
    """``(data, out)``: a copy of the first run, for a test to rerun into."""
    data, out = first
    shutil.copytree(out, tmp_path / "run")
    return data, tmp_path / "run"


def _counts(summary: dict, cls: str = "car") -> tuple[int, int, int]:
    c = summary["classes"][cls]
    return c["reconstructed"], c["resumed"], c["skipped"]


def _adds_up(summary: dict) -> None:
    """Every class of the summary counts each of its objects once: reconstructed, resumed or skipped."""
    for name, c in summary["classes"].items():
        assert c["reconstructed"] + c["resumed"] + c["skipped"] == c["objects"], (name, c)


# --------------------------------------------------------------------------- the record of changed settings


def test_the_record_of_other_settings_stays_while_their_objects_do(copy, caplog):
    """The resumed objects were made at resolution 16: rerunning the same command at 24 again keeps saying so
    (it used to forget after one rerun, leaving config.yaml's 24 as the only record); back at 16, every object
    is one of 16 again and the record goes; overwrite redoes everything and records nothing."""
    data, out = copy
    once = run(_cfg(out, data, resolution=24), workers=0)
    assert once["resumed_from_other_settings"] == {"carve.resolution": [16, 24]}
    caplog.clear()
    again = run(_cfg(out, data, resolution=24), workers=0)
    assert _counts(again) == (0, 6, 0)
    assert again["resumed_from_other_settings"] == {"carve.resolution": [16, 24]}
    assert "other settings (carve.resolution: 16 -> 24)" in caplog.text
    assert "carve.resolution: [16, 24]" not in (out / "run.log").read_text()  # one line, the warning's
    back = run(_cfg(out, data), workers=0)
    assert "resumed_from_other_settings" not in back and _counts(back) == (0, 6, 0)
    fresh = run(_cfg(out, data, resolution=24, overwrite=True), workers=0)
    assert "resumed_from_other_settings" not in fresh and _counts(fresh) == (6, 0, 0)
    then = run(_cfg(out, data, resolution=24), workers=0)
    assert "resumed_from_other_settings" not in then and _counts(then) == (0, 6, 0)


def test_an_interrupted_overwrite_leaves_the_record_of_the_objects_it_did_not_redo(copy, monkeypatch):
    """Ctrl-C of an overwrite run with another resolution once the cars are redone: config.yaml says 24, but the
    chairs are still those made with 16. The record says so from the overwrite's start (it used to be left
    out, and a rerun resumed the objects of 16 under a config of 24 without a word); the rerun keeps it, and an
    overwrite that redoes every object drops it."""
    import carvi_torch.pipeline as P

    data, out = copy
    calls, carve = [], P.carve_and_select

    def interrupted(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:  # the chairs' first chunk: the cars (one chunk) are written
            raise KeyboardInterrupt
        return carve(*args, **kwargs)
    with monkeypatch.context() as m:
        m.setattr(P, "carve_and_select", interrupted)
        with pytest.raises(KeyboardInterrupt):
            run(_cfg(out, data, resolution=24, overwrite=True), workers=0)
    assert json.loads((out / "summary.json").read_text())["resumed_from_other_settings"] == {
        "carve.resolution": [16, 24, 24]}
    rerun = run(_cfg(out, data, resolution=24), workers=0)
    assert _counts(rerun) == (0, 6, 0) and _counts(rerun, "chair") == (0, 6, 0)
    assert rerun["resumed_from_other_settings"] == {"carve.resolution": [16, 24, 24]}
    redone = run(_cfg(out, data, resolution=24, overwrite=True), workers=0)
    assert _counts(redone) == (6, 0, 0) and "resumed_from_other_settings" not in redone


def test_an_overwrite_that_leaves_an_object_as_it_was_keeps_the_record(copy):
    """overwrite=true with cameras=gt and a gt.json without object 1: the car is skipped, its files made with
    resolution 16 stay, so the record of 16 stays too."""
    data, out = copy
    gt = json.loads((data.parent / "gt.json").read_text())
    del gt["annotations"]["1"]
    partial = out.parent / "gt_partial.json"
    partial.write_text(json.dumps(gt))
    summary = run(_cfg(out, data, resolution=24, overwrite=True, cameras="gt", gt=str(partial)), workers=0)
    assert _counts(summary) == (5, 0, 1) and (out / "car" / "voxels" / "1.npz").is_file()
    assert summary["resumed_from_other_settings"]["carve.resolution"] == [16, 24, 24]


def test_opening_a_rerun_reads_the_earlier_summary_once(copy, monkeypatch):
    """Opening a run into a folder with a ``summary.json`` reads that file once: the classes it keeps and the record
    of the settings its objects were made with both come from that one reading."""
    from carvi_torch.executors import common

    data, out = copy
    summary = json.loads((out / "summary.json").read_text())
    summary["resumed_from_other_settings"] = {"carve.resolution": [12, 16]}
    (out / "summary.json").write_text(json.dumps(summary))
    reads, real = [], Path.read_text

    def counted(self, *args, **kwargs):
        reads.append(self.name)
        return real(self, *args, **kwargs)
    monkeypatch.setattr(Path, "read_text", counted)
    setup = common.open_run(_cfg(out, data, resolution=24))
    setup.lock.release()
    assert reads.count("summary.json") == 1
    assert setup.changed == {"carve.resolution": (12, 24)} and sorted(setup.earlier) == ["car", "chair"]


def test_objects_made_with_two_earlier_values_are_both_recorded(copy):
    """Objects made at 16, then new objects at 24 (the chairs, redone by overwrite): a rerun at 20 says both."""
    data, out = copy
    run(_cfg(out, data, resolution=24, overwrite=True, classes="chair"), workers=0)
    mixed = run(_cfg(out, data, resolution=20), workers=0)
    assert mixed["resumed_from_other_settings"] == {"carve.resolution": [16, 24, 20]}
    assert run(_cfg(out, data, resolution=20), workers=0)["resumed_from_other_settings"] == {
        "carve.resolution": [16, 24, 20]}


def test_files_written_besides_the_objects_are_no_changed_setting(copy):
    """keep_all_scores and save_proposals add study files; the objects are made the same (README: what is
    written besides does not count)."""
    data, out = copy
    summary = run(_cfg(out, data, keep_all_scores=True, save_proposals=True), workers=0)
    assert "resumed_from_other_settings" not in summary and _counts(summary) == (0, 6, 0)


# --------------------------------------------------------------------------- the record each object keeps


def _held(out: Path, cls: str = "car") -> dict:
    """``{annotation id: carve.resolution}`` its voxels file records (``None``: no record)."""
    from carvi_torch.io.layout import file_settings

    return {int(p.stem): (file_settings(p) or {}).get("carve.resolution")
            for p in sorted((out / cls / "voxels").glob("*.npz"))}


def _drop_settings(paths) -> None:
    """The voxels files at ``paths`` as an older run wrote them: without the settings member."""
    from carvi_torch.io.layout import SETTINGS_MEMBER

    for path in paths:
        with np.load(path) as z:
            members = {k: z[k] for k in z.files if k != SETTINGS_MEMBER}
        np.savez(path, **members)


def _marked(store: Path, cls: str) -> dict:
    """``{annotation id: made_with_run_settings}`` of a class of an export."""
    import zarr

    g = zarr.open_group(str(store), mode="r")[cls]
    return dict(zip(g.attrs["annotation_ids"], g["made_with_run_settings"][:].tolist()))


def _export(out: Path, store: Path) -> dict:
    from carvi_torch.export import export

    return export(out, store, resolution=4, points=8, progress=False, workers=0)


def _two_cars_remade_at_24(copy) -> Path:
    """The copy's run folder after cars 2 and 5 were lost and a rerun at resolution 24 remade them (the other
    objects resumed, made at 16)."""
    data, out = copy
    assert set(_held(out).values()) == {16}
    for aid in (2, 5):
        (out / "car" / "voxels" / f"{aid}.npz").unlink()
    summary = run(_cfg(out, data, resolution=24), workers=0)
    assert _counts(summary) == (2, 4, 0)
    assert summary["resumed_from_other_settings"] == {"carve.resolution": [16, 24, 24]}
    return out


def test_each_object_records_its_settings_and_the_store_marks_those_made_otherwise(copy, tmp_path):
    """Two cars lost, then a rerun at resolution 24: each voxels file records the resolution its object was made
    with (24 for the two remade, 16 for the resumed), and the export marks exactly the resumed objects as not made
    with the run's settings (``made_with_run_settings``), its record of the other settings made from those
    objects; ``LiftedDataset`` gives the marks per item and as an array, and says how many in its warning."""
    from carvi_torch.training import LiftedDataset

    out = _two_cars_remade_at_24(copy)
    assert _held(out) == {1: 16, 2: 24, 3: 16, 4: 16, 5: 24, 6: 16} and set(_held(out, "chair").values()) == {16}
    index = _export(out, tmp_path / "store")
    assert _marked(tmp_path / "store", "car") == {1: False, 2: True, 3: False, 4: False, 5: True, 6: False}
    assert set(_marked(tmp_path / "store", "chair").values()) == {False}
    assert index["made_with_other_settings"] == {"carve.resolution": [16, 24, 24]}
    with pytest.warns(UserWarning, match="made_with_run_settings is false for 10 of its 12 objects"):
        ds = LiftedDataset(tmp_path / "store", classes=["car"], fields=["mask"])
        every = LiftedDataset(tmp_path / "store", classes=["car"])
    assert ds.made_with_run_settings.tolist() == [False, True, False, False, True, False]
    assert "made_with_run_settings" not in ds[1]  # a field like the others: an item has it where asked for
    assert [every[i]["made_with_run_settings"].item() for i in range(6)] == ds.made_with_run_settings.tolist()


def test_cmr_and_ucmr_files_mark_the_objects_made_otherwise_too(copy, tmp_path):
    """The CMR ``.mat`` and U-CMR ``.json`` files carry each object's ``made_with_run_settings`` (a 1 x N logical
    array beside ``annotation_ids``; a key of each image record) and the class's record of the other settings."""
    import scipy.io

    from carvi_torch.export.formats import export_format

    out = _two_cars_remade_at_24(copy)
    want = {1: False, 2: True, 3: False, 4: False, 5: True, 6: False}
    export_format(out, tmp_path / "ucmr", "ucmr", progress=False)
    car = json.loads((tmp_path / "ucmr" / "car.json").read_text())
    assert {r["annotation_id"]: r["made_with_run_settings"] for r in car["images"]} == want
    assert car["made_with_other_settings"] == {"carve.resolution": [16, 24, 24]}
    chair = json.loads((tmp_path / "ucmr" / "chair.json").read_text())
    assert chair["made_with_other_settings"] == {"carve.resolution": [16, 24]}
    export_format(out, tmp_path / "cmr", "cmr", progress=False)
    mat = scipy.io.loadmat(tmp_path / "cmr" / "car.mat", struct_as_record=False, squeeze_me=True)
    assert dict(zip(mat["annotation_ids"].astype(int).tolist(), mat["made_with_run_settings"].tolist())) == want
    assert json.loads(str(mat["made_with_other_settings"])) == {"carve.resolution": [16, 24, 24]}


def test_files_without_a_record_fall_back_on_the_folders(copy, tmp_path):
    """Voxels files written before objects recorded their settings: where the folder records no other settings,
    every object counts as made with the run's; where it does, an object without a record counts as not (unknown)
    and the store takes the folder's record, while an object that records the run's settings is still marked so."""
    from carvi_torch.io.layout import SETTINGS_MEMBER

    data, out = copy
    _drop_settings((out / "car" / "voxels").glob("*.npz"))
    _export(out, tmp_path / "alike")
    assert set(_marked(tmp_path / "alike", "car").values()) == {True}
    assert _store_record(tmp_path / "alike") == {}
    (out / "car" / "voxels" / "2.npz").unlink()
    run(_cfg(out, data, resolution=24), workers=0)  # the resumed cars record nothing, car 2 records 24
    with np.load(out / "car" / "voxels" / "1.npz") as z:
        assert SETTINGS_MEMBER not in z.files
    _export(out, tmp_path / "mixed")
    assert _marked(tmp_path / "mixed", "car") == {1: False, 2: True, 3: False, 4: False, 5: False, 6: False}
    assert _store_record(tmp_path / "mixed") == {"carve.resolution": [16, 24, 24]}


def _store_record(store: Path) -> dict:
    return json.loads((store / "zarr.json").read_text())["attributes"]["carvi_export"]["made_with_other_settings"]


def test_writer_processes_record_the_settings_too_and_a_converted_mesh_its_format(copy, tmp_path):
    """Objects written by writer processes (``workers=1``, as a Ray task's are: the same job) record their settings
    as the inline writer does; a rerun in another mesh format that converts the resumed objects' meshes records
    the new format in their voxels files, so the export finds them made with the run's settings."""
    from carvi_torch.config import object_settings
    from carvi_torch.io.layout import file_settings

    data, out = copy
    summary = run(_cfg(out, data, resolution=20, overwrite=True, classes="car"), workers=1)
    assert _counts(summary) == (6, 0, 0)
    want = object_settings(_cfg(out, data, resolution=20))
    assert all(file_settings(p) == want for p in (out / "car" / "voxels").glob("*.npz"))
    summary = run(_cfg(out, data, resolution=20, mesh_format="obj", classes="car"), workers=0)
    assert {file_settings(p)["mesh.format"] for p in (out / "car" / "voxels").glob("*.npz")} == {"obj"}
    assert summary["resumed_from_other_settings"]["carve.resolution"] == [16, 20, 20]  # the chairs, kept at 16
    _export(out, tmp_path / "store")
    assert set(_marked(tmp_path / "store", "car").values()) == {True}
    assert set(_marked(tmp_path / "store", "chair").values()) == {False}  # kept from the first run
    assert _store_record(tmp_path / "store") == {"carve.resolution": [16, 20, 20], "mesh.format": ["ply", "obj", "obj"]}


# --------------------------------------------------------------------------- the canvas


def test_another_canvas_redoes_every_object(copy):
    """canvas_size changes every object's canvas, which its voxels are carved and exported in: the objects are
    redone (and counted), not resumed next to a config.yaml that gives another canvas."""
    data, out = copy
    summary = run(_cfg(out, data, canvas_size=64), workers=0)
    for cls, ids in (("car", [1, 2, 3, 4, 5, 6]), ("chair", [7, 8, 9, 10, 11, 12])):
        assert _counts(summary, cls) == (6, 0, 0)
        assert summary["classes"][cls]["redone"] == {"count": 6, "canvas_changed": ids}
    assert "resumed_from_other_settings" not in summary
    margin = run(_cfg(out, data, canvas_size=64, canvas_margin=0.2, classes="car"), workers=0)
    assert margin["classes"]["car"]["redone"]["canvas_changed"] == [1, 2, 3, 4, 5, 6]
    # the chairs are left as they were: the record says so, and the export leaves them out rather than
    # misplace their grids on the canvas config.yaml now gives
    assert margin["classes_from_earlier_runs"] == ["chair"]
    assert margin["resumed_from_other_settings"] == {"input.canvas_margin": [0.1, 0.2, 0.2]}
    from carvi_torch.export import export

    index = export(out, out.parent / "export", resolution=4, points=8, progress=False, workers=0)
    assert sorted(s["annotation_id"] for s in index["samples"]) == [1, 2, 3, 4, 5, 6]
    assert {s["annotation_id"]: s["reason"].split(" (")[0] for s in index["skipped"]} == {
        i: "carved on another canvas than config.yaml's" for i in range(7, 13)}


# --------------------------------------------------------------------------- the mesh format


def test_another_mesh_format_resumes_the_objects_with_their_meshes_in_it(copy):
    """mesh_format=obj: the finished objects are resumed (nothing redone), each mesh made again from its voxels
    in the new format (its faces recorded in the voxels file) and the .ply removed; no setting is recorded as resumed
    otherwise. A mesh in another format
    beside one in the run's is named in the summary, not taken."""
    data, out = copy
    ply = {f.stem: trimesh.load(f, force="mesh", process=False) for f in (out / "car" / "meshes").glob("*.ply")}
    summary = run(_cfg(out, data, mesh_format="obj"), workers=0)
    assert _counts(summary) == (0, 6, 0) and "resumed_from_other_settings" not in summary
    assert summary["classes"]["car"]["meshes_converted"] == {"count": 6, "ply": [1, 2, 3, 4, 5, 6]}
    assert sorted(f.name for f in (out / "car" / "meshes").iterdir()) == [f"{i}.obj" for i in range(1, 7)]
    for stem, m in ply.items():
        obj = trimesh.load(out / "car" / "meshes" / f"{stem}.obj", force="mesh", process=False)
        assert np.allclose(obj.bounds, m.bounds, atol=1e-3) and abs(obj.volume - m.volume) < 1e-3 * abs(m.volume)
        assert finished(out / "car", int(stem), "obj") is True
        with np.load(out / "car" / "voxels" / f"{stem}.npz") as z:  # the record follows the converted file
            assert str(z[MESH_MEMBER]) == f"obj:{len(obj.faces)}"
    shutil.copy(out / "chair" / "meshes" / "7.obj", out / "chair" / "meshes" / "7.ply")
    again = run(_cfg(out, data, mesh_format="obj"), workers=0)
    assert _counts(again, "chair") == (0, 6, 0) and "meshes_converted" not in again["classes"]["chair"]
    assert again["classes"]["chair"]["other_format_meshes"] == {"count": 1, "files": ["7.ply"]}


def test_a_rerun_looks_up_each_objects_mesh_once(copy, monkeypatch):
    """A rerun in another mesh format looks up each object's mesh file once (the resume check's lookup, passed on to
    the conversion), and still converts every mesh."""
    from collections import Counter

    from carvi_torch.io import layout, results

    data, out = copy
    looked_up, real = Counter(), layout.object_mesh

    def counted(cdir, annotation_id, mesh_format):
        looked_up[(Path(cdir).name, annotation_id)] += 1
        return real(cdir, annotation_id, mesh_format)
    monkeypatch.setattr(layout, "object_mesh", counted)
    monkeypatch.setattr(results, "object_mesh", counted, raising=False)
    summary = run(_cfg(out, data, mesh_format="obj"), workers=0)
    assert [summary["classes"][c]["meshes_converted"]["count"] for c in ("car", "chair")] == [6, 6]
    assert len(looked_up) == 12 and set(looked_up.values()) == {1}, looked_up


# --------------------------------------------------------------------------- counts and class records


def test_an_object_without_a_camera_now_is_skipped_not_also_resumed(copy):
    """cameras=gt with a gt.json that lacks two objects: those are skipped, and counted there alone."""
    data, out = copy
    run(_cfg(out, data, cameras="gt", overwrite=True), workers=0)
    gt = json.loads((data.parent / "gt.json").read_text())
    for aid in ("1", "7"):
        del gt["annotations"][aid]
    partial = out.parent / "gt_partial.json"
    partial.write_text(json.dumps(gt))
    summary = run(_cfg(out, data, cameras="gt", gt=str(partial)), workers=0)
    _adds_up(summary)
    assert _counts(summary, "car") == (0, 5, 1) and _counts(summary, "chair") == (0, 5, 1)
    cams = json.loads((out / "car" / "cameras.json").read_text())["cameras"]
    assert cams["1"]["refined"] is None and cams["2"]["refined"] is not None


def test_overwrite_of_one_class_keeps_the_others_in_the_summary(copy):
    """overwrite=true classes=car redoes the cars; the chairs' files stay, and so does their summary entry (and
    the record that they were made with other settings)."""
    data, out = copy
    summary = run(_cfg(out, data, overwrite=True, classes="car", refine_iters=25), workers=0)
    assert sorted(summary["classes"]) == ["car", "chair"] and summary["classes_from_earlier_runs"] == ["chair"]
    assert _counts(summary) == (6, 0, 0) and summary["classes"]["chair"]["reconstructed"] == 6
    assert summary["resumed_from_other_settings"] == {"viewpoints.refine_iters": [20, 25, 25]}
    assert "data_changed" not in summary


def test_a_class_skipped_on_a_rerun_leaves_no_cameras_json_behind(copy):
    """Skipped on a rerun (fewer objects than min_instances), a class has no cameras from this run: the earlier
    cameras.json, which listed objects the run now leaves out, is moved aside (hidden) and the summary says so;
    the objects' files stay, and a rerun that reconstructs the class again resumes them, an object that was a
    puffball still recorded as one (only the earlier cameras.json knew it)."""
    data, out = copy
    cams = json.loads((out / "car" / "cameras.json").read_text())
    cams["cameras"]["1"]["surrogates_from"] = "puffball"
    (out / "car" / "cameras.json").write_text(json.dumps(cams))
    summary = run(_cfg(out, data, min_instances=7), workers=0)
    for cls in ("car", "chair"):
        assert summary["classes"][cls]["status"] == "skipped"
        assert not (out / cls / "cameras.json").exists() and (out / cls / ".cameras_earlier.json").is_file()
        assert any("cameras.json of an earlier run moved to" in w for w in summary["classes"][cls]["warnings"])
        assert len(list((out / cls / "voxels").glob("*.npz"))) == 6
    from carvi_torch.report import build_report

    build_report(out, out / "report")
    cards = (out / "report" / "cards.js").read_text()  # a card per object the report draws
    assert '"id": "1"' not in cards and '"mesh": "../car/meshes/1.ply"' not in cards
    back = run(_cfg(out, data), workers=0)
    assert _counts(back) == (0, 6, 0) and (out / "car" / "cameras.json").is_file()
    again = json.loads((out / "car" / "cameras.json").read_text())["cameras"]
    assert again["1"]["surrogates_from"] == "puffball" and again["2"]["surrogates_from"] != "puffball"


@pytest.mark.parametrize("car", [[6, 6], {"objects": 6, "reconstructed": "6", "resumed": None}])
def test_a_malformed_class_entry_of_the_earlier_summary_is_taken_as_unknown(copy, car, capsys):
    """An earlier summary.json whose car entry is no object, or holds counts that are no numbers: a rerun of the
    chairs ends with its table and exit status (it used to end in a traceback there), says so in one line, and
    leaves the car's entry out."""
    from carvi_torch.reconstruct import main as reconstruct_main

    data, out = copy
    summary = json.loads((out / "summary.json").read_text())
    summary["classes"]["car"] = car
    (out / "summary.json").write_text(json.dumps(summary))
    rc = reconstruct_main(["--data", str(data), "--out", str(out), "classes=chair",
                           *(f"{k}={v}" for k, v in SMALL.items())])
    err = capsys.readouterr().err
    assert rc == 0 and "Traceback" not in err
    assert [line for line in err.splitlines() if "malformed entries of class 'car'" in line]
    assert sorted(json.loads((out / "summary.json").read_text())["classes"]) == ["chair"]


# --------------------------------------------------------------------------- one run at a time


def test_a_second_run_into_a_folder_a_run_holds_is_refused_before_writing(copy, monkeypatch):
    """While a run holds ``--out`` (its lock), another run into it is a user error naming the holder's pid, and
    writes nothing there (``config.yaml`` and ``summary.json`` untouched); once the holder ends, a run goes on
    (the lock is released however the run ends)."""
    from carvi_torch.config import ConfigError
    from carvi_torch.runtime import FolderLock

    data, out = copy
    before = {p: p.read_bytes() for p in (out / "config.yaml", out / "summary.json")}
    with FolderLock(out):
        with pytest.raises(ConfigError, match=rf"--out {out}: another process \(pid \d+\) is writing into it"):
            run(_cfg(out, data, resolution=24), workers=0)
    assert {p: p.read_bytes() for p in before} == before

    def broken(*args, **kwargs):
        raise RuntimeError("stopped inside the run")
    with monkeypatch.context() as m:
        m.setattr("carvi_torch.executors.local._classes", broken)
        with pytest.raises(RuntimeError, match="stopped inside"):
            run(_cfg(out, data), workers=0)
    FolderLock(out).release()  # the failed run let it go
    summary = run(_cfg(out, data), workers=0)
    assert _counts(summary) == (0, 6, 0)
    FolderLock(out).release()


def _files(folder: Path) -> dict:
    """Every file under ``folder``: its content and modification time."""
    return {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_refused_run_leaves_the_embedded_collection_of_the_run_holding_the_folder(procedural_input, tmp_path):
    """Without ``--data`` a run generates the embedded collection into ``OUT/input``: a second run into a folder that
    another holds (here with another seed, which would generate it anew) is refused before it generates anything,
    so the holder's input stays byte for byte (it used to be replaced before the lock was asked for)."""
    from carvi_torch.config import ConfigError
    from carvi_torch.runtime import FolderLock

    out = tmp_path / "run"
    procedural_input(out)
    with FolderLock(out):
        before = _files(out)
        with pytest.raises(ConfigError, match="another process"):
            run(Config().override({**SMALL, "out": str(out), "procedural_instances": 2, "seed": 1}), workers=0)
        assert _files(out) == before


def test_a_read_only_class_folder_is_refused_before_any_work(copy, monkeypatch):
    """A class folder (or its meshes/ or voxels/) the run cannot write into: every object of the class would fail
    after its work, so the run stops first with one user error naming the folder, nothing written. (Simulated:
    the tests may run as root, whom file modes do not stop.)"""
    import os

    from carvi_torch.config import ConfigError
    from carvi_torch.executors import common

    data, out = copy
    real = os.access
    meshes = out / "car" / "meshes"
    monkeypatch.setattr(common.os, "access", lambda p, mode: False if Path(p) == meshes else real(p, mode))
    before = (out / "config.yaml").read_bytes()
    with pytest.raises(ConfigError, match=rf"--out {out}: {meshes} is not writable \(the run writes class 'car'"):
        run(_cfg(out, data, resolution=24), workers=0)
    assert (out / "config.yaml").read_bytes() == before


def test_the_lock_on_a_read_only_mount_and_on_nfs_read_only(tmp_path, monkeypatch, caplog):
    """A lock file on a read-only mount (EROFS) is opened read-only like another user's; where the file system
    locks only files open for writing (NFS: EBADF on a read-only descriptor), the folder runs unlocked with the
    warning of a file system without locks. EBADF on a descriptor open for writing is a fault: raised."""
    import errno
    import fcntl
    import os

    from carvi_torch import runtime
    from carvi_torch.runtime import FileLock, FolderLock

    real_open, real_flock = os.open, fcntl.flock

    def read_only_mount(path, flags, *mode):
        if str(path).endswith(FolderLock.NAME) and flags & os.O_RDWR:
            raise OSError(errno.EROFS, "Read-only file system", str(path))
        return real_open(path, flags, *mode)

    def nfs_flock(fd, op):
        if (fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_ACCMODE) == os.O_RDONLY:
            raise OSError(errno.EBADF, "Bad file descriptor")
        return real_flock(fd, op)
    (tmp_path / FolderLock.NAME).write_text("123")
    with monkeypatch.context() as m:
        m.setattr(runtime.os, "open", read_only_mount)
        with FileLock(tmp_path / FolderLock.NAME) as lock:
            assert lock.read_only and lock.lock()
        with pytest.raises(OSError) as raised:  # none to open read-only: the mount's error, not "no such file"
            FileLock(tmp_path / "none" / FolderLock.NAME)
        assert raised.value.errno == errno.EROFS
        m.setattr(fcntl, "flock", nfs_flock)
        caplog.clear()
        with caplog.at_level("WARNING", logger="carvi_torch"):
            FolderLock(tmp_path).release()
        assert "cannot lock it" in caplog.text
    with monkeypatch.context() as m:
        m.setattr(fcntl, "flock", lambda fd, op: (_ for _ in ()).throw(OSError(errno.EBADF, "Bad file descriptor")))
        with FileLock(tmp_path / "other") as lock, pytest.raises(OSError) as raised:
            lock.lock()
        assert raised.value.errno == errno.EBADF


def test_the_lock_works_on_another_users_file_and_without_file_system_locks(tmp_path, monkeypatch, caplog):
    """A lock file this process cannot open for writing (another user's, in a shared folder) is locked read-only;
    a file system without flock (ENOLCK, ENOSYS, EOPNOTSUPP) runs unlocked with a warning; any other error is
    raised."""
    import errno
    import fcntl
    import os

    from carvi_torch import runtime
    from carvi_torch.runtime import FolderBusy, FolderLock

    real_open = os.open

    def no_write(path, flags, *mode):
        if str(path).endswith(FolderLock.NAME) and flags & os.O_RDWR:
            raise PermissionError(errno.EACCES, "Permission denied", str(path))
        return real_open(path, flags, *mode)
    (tmp_path / FolderLock.NAME).write_text("123")
    with monkeypatch.context() as m:
        m.setattr(runtime.os, "open", no_write)
        with FolderLock(tmp_path):
            with pytest.raises(FolderBusy, match=r"pid 123\)"):  # read-only: the pid is the last holder's
                FolderLock(tmp_path)
    for code in (errno.ENOLCK, errno.ENOSYS, errno.EOPNOTSUPP, errno.EIO):
        def no_flock(fd, op, code=code):
            raise OSError(code, os.strerror(code))
        with monkeypatch.context() as m:
            m.setattr(fcntl, "flock", no_flock)
            if code == errno.EIO:
                with pytest.raises(OSError):
                    FolderLock(tmp_path)
            else:
                caplog.clear()
                with caplog.at_level("WARNING", logger="carvi_torch"):
                    FolderLock(tmp_path).release()
                assert "cannot lock it" in caplog.text


def test_a_resumed_objects_done_entry_must_name_its_meshs_format(tmp_path):
    """``_converted_mesh`` takes the format the resume check found (``ResumeCheck.done``): a bare truth value is refused
    before anything is written or removed, instead of rewriting the mesh and unlinking ``<id>.True``."""
    from carvi_torch.io.results import _converted_mesh

    mesh = tmp_path / "meshes" / "3.ply"
    mesh.parent.mkdir()
    mesh.write_bytes(b"kept")
    with pytest.raises(TypeError, match="object 3: its done entry must be the format"):
        _converted_mesh(3, {}, "obj", True)
    assert mesh.read_bytes() == b"kept" and sorted(p.name for p in mesh.parent.iterdir()) == ["3.ply"]
