"""evaluate.py: shape errors against posed ground truth, baselines, viewpoint reports, tables."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from carvi_torch.config import Config, ConfigError
from carvi_torch.evaluate import evaluate, format_shape_table, format_viewpoint_table, main, posed_gt_mesh
from carvi_torch.executors import run
from conftest import record_settings

TINY = {"procedural_instances": 6, "resolution": 20, "proposals": 3, "canvas_size": 64, "progress": False,
        "refine_iters": 20, "plane_size": 32, "preview": False, "report": False, "classes": ["car"]}


@pytest.fixture(scope="module")
def recon(tmp_path_factory, procedural_input):
    out = tmp_path_factory.mktemp("recon")
    procedural_input(out)  # the embedded collection, generated once per session, where the run looks for it
    run(Config().override({**TINY, "out": str(out)}), workers=0)  # written inline: the same files, a second sooner
    return out


def _gt(recon):
    data = recon / "input" / "annotations.json"
    gt = json.loads((recon / "input" / "gt.json").read_text())["annotations"]
    return data, {a: e for a, e in gt.items() if e["category"] == "car"}


def test_posed_gt_projects_onto_mask(recon):
    from pycocotools.coco import COCO

    data, gt = _gt(recon)
    coco = COCO(str(data))
    aid = next(iter(gt))
    mesh, diag = posed_gt_mesh(gt[aid], data.parent)
    mask = coco.annToMask(coco.anns[int(aid)]).astype(bool)
    xy = np.round(np.asarray(mesh.vertices)[:, :2]).astype(int)
    ok = (xy[:, 0] >= 0) & (xy[:, 1] >= 0) & (xy[:, 0] < mask.shape[1]) & (xy[:, 1] < mask.shape[0])
    assert ok.all() and mask[xy[:, 1], xy[:, 0]].mean() > 0.9
    assert diag > 0


def test_perfect_and_shifted_reconstructions(recon, tmp_path):
    """The posed GT mesh as a 'reconstruction' scores ~0, also shifted in depth; a scaled one does not."""
    data, gt = _gt(recon)
    fake = {name: tmp_path / name for name in ("same", "shifted", "scaled")}
    for name, d in fake.items():
        (d / "car" / "meshes").mkdir(parents=True)
        shutil.copy(recon / "config.yaml", d / "config.yaml")
        for aid, entry in gt.items():
            mesh, _ = posed_gt_mesh(entry, data.parent)
            if name == "shifted":
                mesh.apply_translation([0, 0, 25.0])
            if name == "scaled":
                c = mesh.vertices.mean(0)
                mesh.apply_translation(-c)
                mesh.apply_scale(1.2)
                mesh.apply_translation(c)
            mesh.export(d / "car" / "meshes" / f"{aid}.ply")
    res = evaluate(data, fake, step_percent=2.0, progress=False)
    for row in res["objects"].values():
        assert row["same"]["error_percent"] < 0.05
        assert row["shifted"]["error_percent"] < 0.3
        assert row["scaled"]["error_percent"] > 2.0
    assert res["classes"]["car"]["same"]["count"] == len(gt)


def test_real_run_with_baselines(recon, tmp_path, capsys, monkeypatch):
    """The command line on a real run with the baselines: every method scores every object, the viewpoint
    report, the tables. The objects' check, their meshes, the viewpoints, the SfM baseline and the quality study
    share one reading of a class's ``cameras.json`` (it grows with the objects)."""
    from carvi_torch import evaluate as module
    from carvi_torch.evaluation import reliability

    data, gt = _gt(recon)
    reads, read = [], module.read_json
    for reader in (module, reliability):
        monkeypatch.setattr(reader, "read_json", lambda p: reads.append(p.name) or read(p))
    rc = main(["--data", str(data), "--recon", f"Full={recon}", "--baselines", "--step-percent", "2",
               "--out", str(tmp_path / "ev"), "--quiet"])
    assert rc == 0
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["methods"] == ["Full", "Puffball", "SFMc"]
    car = res["classes"]["car"]
    for m in res["methods"]:
        assert car[m]["count"] + car[m]["missing"] == len(gt) and car[m]["count"] >= len(gt) - 1
        assert 0 < car[m]["mean"] < 50
    vp = res["viewpoints"]["car"]["Full"]
    assert set(vp) == {"sfm", "refined"} and vp["refined"]["geodesic"]["median"] < 20
    # per-instance errors are tied to their objects
    ids = vp["refined"]["annotation_ids"]
    assert len(ids) == len(vp["refined"]["per_instance_geodesic"]) and set(ids) <= {int(k) for k in gt}
    text = capsys.readouterr().out
    assert f"| car ({len(gt)}) |" in text and "refined" in text
    assert (tmp_path / "ev" / "shapes.md").read_text().startswith("| class |")
    assert format_shape_table(res).count("\n") == 3 and "refined" in format_viewpoint_table(res)
    assert reads.count("cameras.json") == 1 and res["quality"]["Full"]["car"]["viewpoint_deg"]["quality"]["n"] > 0


def test_the_quality_study_of_results_alone_reads_the_cameras_it_is_not_given(recon):
    """``quality_vs_error`` on results alone (e.g. merged from ``results.json`` files) reads each run's
    ``cameras.json`` and finds what the evaluation found with the cameras it had read."""
    from carvi_torch.evaluation.reliability import quality_vs_error

    data, _gt_entries = _gt(recon)
    res = evaluate(data, {"Full": recon}, classes=["car"], shapes=False, progress=False)
    assert res["quality"]["Full"]["car"]["viewpoint_deg"]["quality"]["n"] > 0
    assert quality_vs_error(json.loads(json.dumps(res))) == res["quality"]


def test_missing_reconstruction_reported(recon, tmp_path):
    data, gt = _gt(recon)
    partial = tmp_path / "partial"
    shutil.copytree(recon, partial)
    first = sorted((partial / "car" / "meshes").glob("*.ply"))[0]
    first.unlink()
    res = evaluate(data, {"Full": partial}, step_percent=2.0, progress=False)
    assert res["objects"][first.stem]["Full"]["reason"] == "no reconstruction"
    before = len(gt) - len(list((recon / "car" / "meshes").glob("*.ply")))
    assert res["classes"]["car"]["Full"]["missing"] == before + 1



def test_a_mesh_left_from_other_inputs_is_not_scored(recon, tmp_path):
    """An object the run's latest input dropped (gone from ``cameras.json``) keeps the mesh an earlier run made;
    that mesh is not the run's, so the object counts as having no reconstruction."""
    data, _gt_entries = _gt(recon)
    run = tmp_path / "run"
    shutil.copytree(recon, run)
    stale = sorted((run / "car" / "meshes").glob("*.ply"))[0]
    cams = json.loads((run / "car" / "cameras.json").read_text())
    del cams["cameras"][stale.stem]
    (run / "car" / "cameras.json").write_text(json.dumps(cams))
    res = evaluate(data, {"Full": run}, step_percent=2.0, progress=False, classes=["car"])
    assert stale.is_file() and res["objects"][stale.stem]["Full"]["reason"] == "no reconstruction"
    kept = [k for k, r in res["objects"].items() if k != stale.stem and "error_percent" in r["Full"]]
    assert kept, "the other objects are still scored"


def test_the_mesh_scored_is_the_one_of_the_runs_mesh_format(recon, tmp_path):
    """A run whose ``mesh_format`` changed keeps the other format's meshes beside its own: evaluate scores the file
    the export takes (the run's format), not the first format it knows of."""
    from carvi_torch.config import read_run_config
    from carvi_torch.io.layout import object_mesh

    data, gt = _gt(recon)
    run = tmp_path / "run"
    shutil.copytree(recon, run)
    (run / "config.yaml").write_text(read_run_config(run / "config.yaml").override(["mesh_format=obj"]).to_yaml())
    leftover = sorted((run / "car" / "meshes").glob("*.ply"))[0]
    current = leftover.with_suffix(".obj")
    posed_gt_mesh(gt[leftover.stem], data.parent)[0].export(current)  # the run's mesh: the ground truth itself
    assert object_mesh(run / "car", leftover.stem, "obj") == current
    res = evaluate(data, {"Full": run, "ply": recon}, classes=["car"], step_percent=2.0, progress=False)
    assert res["objects"][leftover.stem]["Full"]["error_percent"] < 0.05
    assert res["objects"][leftover.stem]["ply"]["error_percent"] > 0.5  # the leftover .ply: the run's old carving


def test_another_tools_config_yaml_beside_a_methods_meshes_is_noted_not_fatal(recon, tmp_path, capsys):
    """A method's folder holding another tool's ``config.yaml`` is evaluated (its meshes looked up in the default
    format first) and named in a note; a run of this package (a folder with ``summary.json``) and the first method
    (its canvas loads the masks) must have a readable one, so a foreign one there is an error."""
    data, _ = _gt(recon)
    other = tmp_path / "other"
    shutil.copytree(recon, other)
    (other / "config.yaml").write_text("seed: 42\ndata:\n  root: /x\n")
    with pytest.raises(ConfigError, match="expected text, got a mapping"):  # a run of this package: its own
        evaluate(data, {"Full": recon, "Other": other}, classes=["car"], step_percent=2.0, progress=False)
    (other / "summary.json").unlink()  # another tool's folder of meshes and cameras
    res = evaluate(data, {"Full": recon, "Other": other}, classes=["car"], step_percent=2.0, progress=False)
    assert list(res["unread_configs"]) == ["Other"] and "data" in res["unread_configs"]["Other"]
    scored = [r["Other"]["error_percent"] for r in res["objects"].values() if "Other" in r]
    assert scored and all(e is not None for e in scored)
    assert scored == [r["Full"]["error_percent"] for r in res["objects"].values() if "Full" in r]
    capsys.readouterr()
    assert main(["--data", str(data), "--recon", f"Full={recon}", "--recon", f"Other={other}", "--classes", "car",
                 "--step-percent", "2", "--viewpoints-only"]) == 0
    assert "note: Other is no run of this package and its config.yaml could not be read" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="expected text, got a mapping"):
        evaluate(data, {"Other": other, "Full": recon}, classes=["car"], step_percent=2.0, progress=False)


def test_a_run_made_with_other_settings_is_noted(recon, tmp_path, capsys):
    """A method's folder whose objects were made with other settings than its config.yaml's: evaluate lists it in
    ``made_with_other_settings`` and says so in a note naming each setting's values and how many objects their
    voxels files say were made so; a folder without the record is not listed."""
    data, _ = _gt(recon)
    run = tmp_path / "run"
    shutil.copytree(recon, run)
    summary = json.loads((run / "summary.json").read_text())
    summary["resumed_from_other_settings"] = {"carve.resolution": [16, 24]}
    (run / "summary.json").write_text(json.dumps(summary))
    capsys.readouterr()
    assert main(["--data", str(data), "--recon", f"Mixed={run}", "--recon", f"Full={recon}", "--classes", "car",
                 "--viewpoints-only", "--out", str(tmp_path / "ev")]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "other settings" in line]
    assert len(notes) == 1 and notes[0].startswith("note: Mixed (") and "carve.resolution 16 then 24" in notes[0]
    assert "0 of its 6 objects by their voxels files" in notes[0]  # each records the run's settings
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["made_with_other_settings"] == {"Mixed": {"carve.resolution": [16, 24]}}
    record_settings(sorted((run / "car" / "voxels").glob("*.npz"))[:2], carve__resolution=16)
    assert main(["--data", str(data), "--recon", f"Mixed={run}", "--classes", "car", "--viewpoints-only",
                 "--out", str(tmp_path / "ev2")]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "other settings" in line]
    assert len(notes) == 1 and "(oldest first, then the run's; 2 of its 6 objects by their voxels files)" in notes[0]


def test_an_object_whose_ground_truth_fails_gets_a_reason_and_no_scores(recon, tmp_path):
    """A ground-truth mesh that cannot be read leaves its object unscored, with the reason, for every method and
    baseline; the class's other objects are scored."""
    data, gt = _gt(recon)
    inputs = tmp_path / "input"
    shutil.copytree(data.parent, inputs)
    gt_all = json.loads((inputs / "gt.json").read_text())
    broken = sorted(gt)[0]
    gt_all["annotations"][broken]["mesh"] = "meshes/missing.ply"
    (inputs / "gt.json").write_text(json.dumps(gt_all))
    res = evaluate(inputs / "annotations.json", {"Full": recon}, baselines=True, step_percent=5.0, progress=False,
                   classes=["car"])
    row = res["objects"][broken]
    assert row["reason"].startswith("ground truth unusable:") and "missing.ply" in row["reason"]
    assert not {"Full", "Puffball", "SFMc"} & set(row)
    # not a miss of the methods: the class counts it among its objects without ground truth, compared on the others
    car = res["compared"]["car"]
    assert car["without_ground_truth"] == 1 and broken not in car["compared"]
    assert res["classes"]["car"]["Full"]["count"] >= 1

def test_cli_errors(tmp_path, capsys):
    assert main(["--data", str(tmp_path / "a.json"), "--recon", str(tmp_path / "none")]) == 2
    assert "not found" in capsys.readouterr().err
    # a missing --data is said as such (not as a missing gt.json beside it)
    assert main(["--data", str(tmp_path / "a.json"), "--recon", str(tmp_path), "--quiet"]) == 2
    assert capsys.readouterr().err == f"error: {tmp_path / 'a.json'}: no such annotation file\n"
    # two --recon of one method name would overwrite each other's results
    (tmp_path / "b").mkdir()
    assert main(["--data", "x.json", "--recon", f"M={tmp_path}", "--recon", f"M={tmp_path / 'b'}"]) == 2
    assert capsys.readouterr().err.startswith("error: two --recon are named M (")
    assert main(["--data", "x.json", "--recon", str(tmp_path), "--recon", str(tmp_path / "b"),
                 "--recon", f"{tmp_path}/x/../b"]) == 2
    assert "two --recon are named b" in capsys.readouterr().err
    for bad in ("0", "-1", "nan", "inf"):
        with pytest.raises(SystemExit) as e:
            main(["--data", "x.json", "--recon", str(tmp_path), "--step-percent", bad])
        assert e.value.code == 2 and "--step-percent" in capsys.readouterr().err


def test_viewpoints_only(recon, tmp_path, capsys):
    data, gt = _gt(recon)
    rc = main(["--data", str(data), "--recon", str(recon), "--viewpoints-only", "--quiet", "--out", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 0 and "Symmetric RMS" not in out and "| car | Full | refined |" in out
    assert not (tmp_path / "shapes.md").exists() and (tmp_path / "viewpoints.md").is_file()  # no empty table
    assert f"wrote {tmp_path}/results.json, viewpoints.md" in out and "shapes.md" not in out


def test_a_camera_only_run_gets_a_note(recon, tmp_path, capsys):
    """A run that stopped after the cameras, evaluated without --viewpoints-only, gets a note suggesting it."""
    cams = tmp_path / "cams"
    shutil.copytree(recon, cams, ignore=shutil.ignore_patterns("meshes", "voxels"))
    cfg = cams / "config.yaml"
    cfg.write_text(cfg.read_text().replace("stage: all", "stage: cameras"))
    data, gt = _gt(recon)
    assert main(["--data", str(data), "--recon", str(cams), "--classes", "car", "--step-percent", "5", "--quiet"]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if "stage=cameras" in line]
    assert notes and notes[0].startswith("note: Full stopped after the cameras") and "--viewpoints-only" in notes[0]
    assert main(["--data", str(data), "--recon", str(cams), "--classes", "car", "--viewpoints-only", "--quiet"]) == 0
    assert "stage=cameras" not in capsys.readouterr().err


def test_a_split_no_annotation_has_is_refused(recon, capsys):
    data, gt = _gt(recon)
    splits = sorted({a.get("split", "") for a in json.loads(data.read_text())["annotations"]})
    assert main(["--data", str(data), "--recon", str(recon), "--split", "tset", "--viewpoints-only", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: no annotation of") and "split 'tset'" in err and "\n" == err[-1]
    assert all((repr(s) if s else "none") in err for s in splits), (splits, err)


def _with_first_car_camera_edited(recon, tmp_path, gt, edit):
    """A copy of the run whose first car with ground truth has its ``cameras.json`` entry changed by ``edit``:
    the copy, that annotation id and the edited ``cameras.json``."""
    part = tmp_path / "part"
    shutil.copytree(recon, part)
    p = part / "car" / "cameras.json"
    cj = json.loads(p.read_text())
    first = sorted(int(a) for a in cj["cameras"] if str(a) in gt)[0]
    edit(cj["cameras"][str(first)])
    p.write_text(json.dumps(cj))
    return part, first, cj


def test_refinement_is_compared_on_the_objects_with_an_sfm_camera(recon, tmp_path):
    """An object without an SfM camera (its camera came from the unseen-image path) counts in
    ``refined`` but not in ``sfm``; ``refined_with_sfm`` scores the refined cameras of exactly the
    ``sfm`` objects, each set with its own global alignment (checked against viewpoint_report)."""
    import torch

    from carvi_torch.evaluation.viewpoint_metrics import viewpoint_report

    data, gt = _gt(recon)
    part, dropped, cj = _with_first_car_camera_edited(recon, tmp_path, gt, lambda c: c.update(sfm=None))
    vp = evaluate(data, {"Full": part}, shapes=False, progress=False)["viewpoints"]["car"]["Full"]
    assert set(vp) == {"sfm", "refined", "refined_with_sfm"}
    assert dropped in vp["refined"]["annotation_ids"] and dropped not in vp["sfm"]["annotation_ids"]
    assert vp["refined_with_sfm"]["annotation_ids"] == vp["sfm"]["annotation_ids"]
    keep = vp["sfm"]["annotation_ids"]
    want = viewpoint_report(torch.tensor([cj["cameras"][str(a)]["refined"]["R"] for a in keep], dtype=torch.float64),
                            torch.tensor([gt[str(a)]["R"] for a in keep], dtype=torch.float64))
    assert vp["refined_with_sfm"]["geodesic"]["median"] == pytest.approx(want["geodesic"]["median"], abs=1e-9)
    assert vp["refined_with_sfm"]["geodesic"]["n"] == vp["refined"]["geodesic"]["n"] - 1


def test_the_refinement_change_resamples_physical_objects(recon, tmp_path):
    """``change_from_sfm`` is the refined median minus the SfM median of the same objects (the two reports
    of evaluate, each aligned on its own); its interval resamples whole ``object_id``s: with the views
    given pairwise to one object, half as many clusters; with none, one per view."""
    from carvi_torch.evaluate import format_change

    data, _gt_car = _gt(recon)
    vp = evaluate(data, {"Full": recon}, shapes=False, progress=False)["viewpoints"]["car"]["Full"]
    ch = vp["refined"]["change_from_sfm"]
    assert ch["change"] == pytest.approx(vp["refined"]["geodesic"]["median"] - vp["sfm"]["geodesic"]["median"],
                                         abs=2e-3)  # rounded to 3 decimals
    assert ch["low"] <= ch["change"] <= ch["high"] and ch["objects"] == vp["sfm"]["geodesic"]["n"]
    assert "change_from_sfm" not in vp["sfm"] and format_change(ch) in format_viewpoint_table(
        {"viewpoints": {"car": {"Full": vp}}})
    doc = json.loads(data.read_text())
    cars = sorted((a for a in doc["annotations"] if str(a["id"]) in _gt_car), key=lambda a: a["id"])
    for i, a in enumerate(cars):
        a["object_id"] = f"pair{i // 2}"
    paired = tmp_path / "input" / "annotations.json"
    shutil.copytree(data.parent, paired.parent)
    paired.write_text(json.dumps(doc))
    ch2 = evaluate(paired, {"Full": recon}, shapes=False, progress=False)["viewpoints"]["car"]["Full"]["refined"]
    assert ch2["change_from_sfm"]["clusters"] == (ch["objects"] + 1) // 2 and ch["clusters"] == ch["objects"]
    assert ch2["change_from_sfm"]["change"] == ch["change"]
    for a in cars:
        a["object_id"] = "one"  # one physical object: no interval, and no error
    paired.write_text(json.dumps(doc))
    one = evaluate(paired, {"Full": recon}, shapes=False, progress=False)["viewpoints"]["car"]["Full"]["refined"]
    assert one["change_from_sfm"] is None and one["geodesic"]["median"] == vp["refined"]["geodesic"]["median"]


def test_a_non_finite_camera_leaves_the_refinement_change_to_the_others(recon, tmp_path):
    data, gt = _gt(recon)
    part, _aid, _cj = _with_first_car_camera_edited(recon, tmp_path, gt,
                                                   lambda c: c["refined"].update(R=[[float("nan")] * 3] * 3))
    vp = evaluate(data, {"Full": part}, shapes=False, progress=False)["viewpoints"]["car"]["Full"]
    ch = vp["refined"]["change_from_sfm"]
    assert ch is not None and ch["objects"] == vp["sfm"]["geodesic"]["n"] - 1


def test_classes_without_reconstruction_are_named(recon, tmp_path, capsys):
    data, gt = _gt(recon)
    cats = {c["name"] for c in json.loads(data.read_text())["categories"]}
    assert "car" in cats and len(cats) > 1  # the run reconstructed car only
    rc = main(["--data", str(data), "--recon", str(recon), "--viewpoints-only", "--quiet", "--out", str(tmp_path)])
    notes = [line for line in capsys.readouterr().err.splitlines() if line.startswith("note:")]
    res = json.loads((tmp_path / "results.json").read_text())
    assert rc == 0 and res["classes_without_reconstruction"] == {c: ["Full"] for c in sorted(cats - {"car"})}
    assert notes == [f"note: class {c} has no reconstruction in Full; not evaluated" for c in sorted(cats - {"car"})]
    assert set(res["viewpoints"]) == {"car"}
    # asked for by name, such a class is evaluated (every object missing) and still named
    res = evaluate(data, {"Full": recon}, classes=["car", "chair"], step_percent=5.0, progress=False)
    assert res["classes_without_reconstruction"] == {"chair": ["Full"]}
    assert res["classes"]["chair"]["Full"]["count"] == 0 and res["classes"]["chair"]["Full"]["missing"] > 0


def test_unknown_classes_and_foreign_reconstructions_are_refused(recon, tmp_path, capsys):
    data, gt = _gt(recon)
    assert main(["--data", str(data), "--recon", str(recon), "--classes", "car,nosuch", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "'nosuch'" in err and "car" in err
    dataset = json.loads(data.read_text())
    gt_file = data.parent / "gt.json"
    # the same ids naming other objects (another source), then ids the data does not have
    for change in ({"source": "elsewhere.xml"}, {"id": None}):
        other = json.loads(json.dumps(dataset))
        for i, a in enumerate(other["annotations"]):
            a.update({k: (v if v is not None else f"x{i}") for k, v in change.items()})
        path = tmp_path / "other.json"
        path.write_text(json.dumps(other))
        assert main(["--data", str(path), "--recon", str(recon), "--gt", str(gt_file), "--viewpoints-only",
                     "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert "\n" not in err and "was not made from" in err and str(recon / "input" / "annotations.json") in err
    # the data it was made from passes
    assert main(["--data", str(data), "--recon", str(recon), "--viewpoints-only", "--quiet"]) == 0
    capsys.readouterr()
    # the file the run was made from, changed since: said so, not "not made from X (it was made from X)"
    moved = tmp_path / "moved"
    shutil.copytree(recon, moved, ignore=shutil.ignore_patterns("meshes", "voxels", "report"))
    summary = json.loads((moved / "summary.json").read_text())
    summary["data"] = str(moved / "input" / "annotations.json")
    (moved / "summary.json").write_text(json.dumps(summary))
    changed = json.loads(json.dumps(dataset))
    for a in changed["annotations"]:
        a["source"] = "elsewhere.xml"
    (moved / "input" / "annotations.json").write_text(json.dumps(changed))
    assert main(["--data", str(moved / "input" / "annotations.json"), "--recon", str(moved), "--gt", str(gt_file),
                 "--viewpoints-only", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "but its objects differ from the file's current contents" in err
    assert "(the file changed since the run)" in err and "was not made from" not in err


def test_a_progress_bar_counts_the_objects_unless_quiet(recon, capsys):
    data, gt = _gt(recon)
    assert main(["--data", str(data), "--recon", str(recon), "--classes", "car", "--step-percent", "5"]) == 0
    err = capsys.readouterr().err
    assert "evaluate: 100%" in err and f"{len(gt)}/{len(gt)}" in err  # worker processes: the command's test below
    assert main(["--data", str(data), "--recon", str(recon), "--classes", "car", "--step-percent", "5", "--quiet"]) == 0
    assert "evaluate" not in capsys.readouterr().err


def test_help_says_what_the_step_costs(capsys):
    """--help's costs hold: the seconds per object that --step-percent quotes are the measured totals of the
    default run that the description gives, over its objects; and the surface samples, whose number the
    cost follows, fall as 1/step^2."""
    import inspect
    import re

    import torch
    import trimesh

    from carvi_torch.evaluation.metrics import sample_surface

    with pytest.raises(SystemExit):
        main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "progress bar counts the objects" in text
    run = re.search(r"default run's (\d+) chairs took (\d+) s at the default `*--step-percent ([\d.]+)`* and (\d+) s "
                    r"at ([\d.]+)", text)
    quoted = re.search(r"on the default run's chairs ([\d.]+) s per object at ([\d.]+), ([\d.]+) s at ([\d.]+) ",
                       text)
    assert run and quoted, text
    objects, fine_s, fine, coarse_s, coarse = (float(g) for g in run.groups())
    default = inspect.signature(evaluate).parameters["step_percent"].default
    assert (quoted[2], quoted[4]) == (run[3], run[5]) and fine == default  # the steps timed: the default, and 2
    for per_object, total in ((quoted[1], fine_s), (quoted[3], coarse_s)):
        digits = len(per_object.partition(".")[2])
        assert float(per_object) == round(total / objects, digits), (per_object, total, objects)
    assert "1/step^2" in text
    sphere = trimesh.creation.icosphere(subdivisions=6)  # many small faces, as the ground truth's CAD meshes
    V, F = torch.tensor(sphere.vertices, dtype=torch.float64), torch.tensor(sphere.faces)
    diag = float(np.linalg.norm(sphere.extents))  # the steps are percent of the bounding-box diagonal
    counts = [len(sample_surface(V, F, percent / 100 * diag)[0]) for percent in (fine, coarse)]
    assert counts[0] / counts[1] == pytest.approx((coarse / fine) ** 2, rel=0.05)


def test_help_says_what_happens_without_out(capsys):
    """--out is optional: --help says that without it the tables are printed and no file is written."""
    with pytest.raises(SystemExit):
        main(["--help"])
    assert "(default: none, the tables are printed only)" in " ".join(capsys.readouterr().out.split())


def test_workers_that_cannot_start_leave_the_scoring_to_this_process(recon, monkeypatch, caplog):
    """The scorer the workers would get pickles, the baselines' collections with it; and where no process
    starts, this process scores every object with the same errors."""
    import pickle

    from carvi_torch.evaluation import scoring

    handed = []

    def no_processes(*args, initargs=(), **kwargs):
        handed.append(pickle.loads(pickle.dumps(initargs)))
        raise OSError("no processes here")

    data, _ = _gt(recon)
    want = evaluate(data, {"Full": recon}, step_percent=10.0, progress=False, baselines=True, jobs=1)["objects"]
    monkeypatch.setattr(scoring, "LeanProcessPool", no_processes)
    with caplog.at_level("WARNING", logger=scoring.__name__):
        got = evaluate(data, {"Full": recon}, step_percent=10.0, progress=False, baselines=True, jobs=2)["objects"]
    assert got == want
    assert "worker processes failed (OSError: no processes here); scoring here" in caplog.text
    (scorer,), = handed
    assert scorer.baselines and len(scorer.collections["car"]) >= 2


def test_default_jobs_follow_the_cores_and_the_object_count(monkeypatch):
    from carvi_torch.evaluation import scoring

    for n_cores, n_objects, want in ((4, 100, 4), (4, scoring.POOL_FROM - 1, 1), (1, 100, 1),
                                     (64, 100, scoring.MAX_JOBS), (2, scoring.POOL_FROM, 2)):
        monkeypatch.setattr(scoring, "cores", lambda n=n_cores: n)
        assert scoring.default_jobs(n_objects) == want, (n_cores, n_objects)


def test_jobs_must_be_a_whole_number_of_at_least_one(tmp_path, capsys):
    for bad in ("0", "-2", "1.5", "two"):
        with pytest.raises(SystemExit) as e:
            main(["--data", "x.json", "--recon", str(tmp_path), "--jobs", bad])
        assert e.value.code == 2 and "--jobs: expected an integer >= 1" in capsys.readouterr().err


def test_the_command_scores_in_worker_processes(recon, tmp_path):
    """``python -m carvi_torch.evaluate --jobs 2``, where the command's module is ``__main__``: its workers get what
    they run from an importable module, give every object and method the errors of the in-process scoring, to
    the bit (one torch thread each way), and the progress bar counts the objects."""
    import subprocess
    import sys

    data, gt = _gt(recon)
    argv = [sys.executable, "-m", "carvi_torch.evaluate", "--data", str(data), "--recon", f"Full={recon}",
            "--step-percent", "10", "--jobs", "2", "--out", str(tmp_path / "ev")]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0 and "worker processes failed" not in done.stderr, done.stderr[-2000:]
    assert "evaluate: 100%" in done.stderr and f"{len(gt)}/{len(gt)}" in done.stderr
    got = json.loads((tmp_path / "ev" / "results.json").read_text())["objects"]
    want = evaluate(data, {"Full": recon}, step_percent=10.0, progress=False, jobs=1)["objects"]
    assert len(want) == len(gt) >= 2 and got == want
    errors = [r["Full"]["error_percent"] for r in want.values()]
    assert None not in errors and len(set(errors)) == len(errors)  # every object scored, and apart


# --------------------------------------------------------------------------- bad input: the object, not the run


def _inputs_with(recon, tmp_path, edit):
    """A copy of the run's input folder whose ``gt.json`` records (annotation id -> record) ``edit`` changed: its
    annotation file, and the car ids with ground truth, sorted."""
    data, gt = _gt(recon)
    inputs = tmp_path / "input"
    shutil.copytree(data.parent, inputs)
    gt_all = json.loads((inputs / "gt.json").read_text())
    edit(gt_all["annotations"], sorted(gt, key=int))
    (inputs / "gt.json").write_text(json.dumps(gt_all))
    return inputs / "annotations.json", sorted(gt, key=int)


def _err_lines(capsys):
    return capsys.readouterr().err.splitlines()


def test_objects_without_ground_truth_are_reported(recon, tmp_path, capsys):
    """An object in scope that gt.json has no entry for is not dropped silently: one line naming it, its reason in
    results.json, and the table counts it among the class's objects."""
    data, cars = _inputs_with(recon, tmp_path, lambda g, cars: g.pop(cars[1]))
    assert main(["--data", str(data), "--recon", str(recon), "--classes", "car", "--step-percent", "5", "--quiet",
                 "--out", str(tmp_path / "ev")]) == 0
    assert f"evaluate: car annotation {cars[1]} skipped: no ground truth: gt.json has no entry for it" in \
        _err_lines(capsys)
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["objects"][cars[1]] == {"class": "car", "split": res["objects"][cars[1]]["split"],
                                       "reason": "no ground truth: gt.json has no entry for it"}
    assert res["compared"]["car"]["objects"] == len(cars) and res["compared"]["car"]["without_ground_truth"] == 1
    assert f"| car ({len(res['compared']['car']['compared'])} of {len(cars)}; 1 without ground truth) |" in \
        (tmp_path / "ev" / "shapes.md").read_text()


def test_malformed_ground_truth_skips_its_objects_and_evaluates_the_rest(recon, tmp_path, capsys):
    """A gt.json record that is not an object, has no usable s, an R that is not 3 x 3, or an R that is no rotation
    (scaled, or a reflection: det -1) leaves out its object with one line naming it; the other objects are scored,
    shapes and viewpoints. A gt.json that is not an object is one error line (exit 2)."""
    import numpy as np

    def edit(g, cars):
        g[cars[0]] = "oops"
        g[cars[1]]["s"] = None
        g[cars[2]]["R"] = g[cars[2]]["R"][:2]
        g[cars[3]]["R"] = (2 * np.asarray(g[cars[3]]["R"])).tolist()
        g[cars[4]]["R"] = (-np.asarray(g[cars[4]]["R"])).tolist()

    data, cars = _inputs_with(recon, tmp_path, edit)
    assert len(cars) >= 6, "one object left to score beside the five broken ones"
    assert main(["--data", str(data), "--recon", str(recon), "--classes", "car", "--step-percent", "5", "--quiet",
                 "--out", str(tmp_path / "ev")]) == 0
    err = _err_lines(capsys)
    want = {cars[0]: "its entry is 'oops', not an object", cars[1]: "s is None, not a finite positive number",
            cars[2]: "R is not 3 x 3 finite numbers", cars[3]: "R is not a rotation", cars[4]: "R is not a rotation"}
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    for aid, why in want.items():
        assert f"evaluate: car annotation {aid} skipped: ground truth unusable: {why}" in err, err
        assert res["objects"][aid]["reason"] == f"ground truth unusable: {why}" and "Full" not in res["objects"][aid]
    scored = [a for a in cars if a not in want and res["objects"][a]["Full"]["error_percent"] is not None]
    assert scored and set(res["compared"]["car"]["compared"]) == set(scored)
    coverage = res["viewpoint_coverage"]["car"]["Full"]  # the objects the viewpoint report may score
    assert coverage["objects"] == len(scored) and not set(coverage["missing"]) & set(want), coverage
    # a gt.json that is not an object of records: one error line
    (data.parent / "gt.json").write_text("[1, 2]")
    assert main(["--data", str(data), "--recon", str(recon), "--quiet", "--viewpoints-only"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"error: {data.parent / 'gt.json'}: expected a JSON object")


def _run_copy_cameras(recon, tmp_path):
    """``(data, part, path, content, ids)``: a copy ``part`` of the run, its car ``cameras.json`` (``path``, its
    ``content`` to edit and write back) and the ids there that have ground truth, in order."""
    data, gt = _gt(recon)
    part = tmp_path / "part"
    shutil.copytree(recon, part)
    p = part / "car" / "cameras.json"
    cj = json.loads(p.read_text())
    return data, part, p, cj, sorted((a for a in cj["cameras"] if a in gt), key=int)


def test_malformed_cameras_of_a_run_leave_out_their_viewpoints(recon, tmp_path, capsys):
    """A run's cameras.json entry that is not an object, or whose refined R is not 3 x 3, is one line naming the
    object and method; the viewpoints are scored on the others and the meshes still count."""
    data, part, p, cj, ids = _run_copy_cameras(recon, tmp_path)
    cj["cameras"][ids[0]]["refined"]["R"] = cj["cameras"][ids[0]]["refined"]["R"][:2]
    cj["cameras"][ids[1]] = "oops"
    p.write_text(json.dumps(cj))
    assert main(["--data", str(data), "--recon", str(part), "--viewpoints-only", "--quiet", "--out",
                 str(tmp_path / "ev")]) == 0
    err = _err_lines(capsys)
    assert f"evaluate: car annotation {ids[0]}: Full: unusable refined camera in cameras.json: R is not 3 x 3 " \
           "numbers" in err
    assert f"evaluate: car annotation {ids[1]}: Full: its cameras.json entry is 'oops', not an object" in err
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    refined = {str(a) for a in res["viewpoints"]["car"]["Full"]["refined"]["annotation_ids"]}
    assert ids[0] not in refined and ids[1] not in refined and len(refined) == len(ids) - 2
    assert set(res["viewpoint_coverage"]["car"]["Full"]["missing"]) == {ids[0], ids[1]}


def test_missing_refined_cameras_are_grouped_by_the_kind_of_their_reason(recon, tmp_path, capsys):
    """The note on the objects without a usable refined camera groups them by the kind of their reason, whatever
    its text holds (an entry quoted with a colon in it), as ``viewpoint_coverage``'s ``missing_reasons`` does."""
    data, part, p, cj, ids = _run_copy_cameras(recon, tmp_path)
    cj["cameras"][ids[0]] = "oops: no camera"
    cj["cameras"][ids[1]]["refined"] = None
    p.write_text(json.dumps(cj))
    assert main(["--data", str(data), "--recon", str(part), "--viewpoints-only", "--quiet", "--out",
                 str(tmp_path / "ev")]) == 0
    note = next(line for line in _err_lines(capsys) if "has no usable refined camera" in line)
    assert f"(cameras.json entry not an object: {ids[0]}; no refined camera: {ids[1]})" in note, note
    coverage = json.loads((tmp_path / "ev" / "results.json").read_text())["viewpoint_coverage"]["car"]["Full"]
    assert coverage["missing_reasons"] == {"cameras.json entry not an object": [ids[0]], "no refined camera": [ids[1]]}
    assert coverage["missing"][ids[0]] == "its cameras.json entry is 'oops: no camera', not an object"


def test_a_mesh_the_metric_cannot_score_is_named_and_grouped_by_kind(recon, tmp_path, capsys):
    """A run's mesh without surface (its faces flat to lines) leaves that method without the object's error: a line
    names the object and what the metric found, and the note and ``missing_reasons`` count it as an unscorable
    mesh."""
    import trimesh

    data, gt = _gt(recon)
    flat = tmp_path / "flat"
    shutil.copytree(recon, flat)
    ply = sorted((flat / "car" / "meshes").glob("*.ply"), key=lambda q: int(q.stem))[0]
    trimesh.Trimesh([[0, 0, 0], [1, 1, 1], [2, 2, 2]], [[0, 1, 2]], process=False).export(ply)
    assert main(["--data", str(data), "--recon", f"A={recon}", "--recon", f"B={flat}", "--classes", "car",
                 "--step-percent", "5", "--quiet", "--out", str(tmp_path / "ev")]) == 0
    err = _err_lines(capsys)
    assert f"evaluate: car annotation {ply.stem}: B has no shape error: recon has zero surface area" in err, err
    assert any(line.startswith(f"note: car: B has no shape error for 1 of {len(gt)} objects (unscorable mesh: "
                               f"{ply.stem})") for line in err), err
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["classes"]["car"]["B"]["missing_reasons"] == {"unscorable mesh": [ply.stem]}
    assert res["objects"][ply.stem]["B"]["kind"] == "unscorable mesh"


def test_unreadable_meshes_skip_their_object_with_the_file_named(recon, tmp_path, capsys):
    """A ground-truth mesh trimesh cannot read (an .npz) skips its object for every method; a run's truncated .ply
    leaves that method without the object's error: each reason names the file, and the rest is evaluated."""
    def edit(g, cars):
        g[cars[0]]["mesh"] = "gt.npz"

    data, cars = _inputs_with(recon, tmp_path, edit)
    np.savez(data.parent / "gt.npz", a=np.zeros(3))
    bad = tmp_path / "bad"
    shutil.copytree(recon, bad)
    ply = bad / "car" / "meshes" / f"{cars[1]}.ply"
    assert ply.is_file()
    ply.write_bytes(ply.read_bytes()[:len(ply.read_bytes()) // 2])
    assert main(["--data", str(data), "--recon", f"A={recon}", "--recon", f"B={bad}", "--classes", "car",
                 "--step-percent", "5", "--quiet", "--out", str(tmp_path / "ev")]) == 0
    err = _err_lines(capsys)
    assert any(line.startswith(f"evaluate: car annotation {cars[0]} skipped: ground truth unusable: cannot read ")
               and "gt.npz" in line for line in err), err
    assert any(line.startswith(f"evaluate: car annotation {cars[1]}: B has no shape error: unreadable mesh: ")
               and str(ply) in line for line in err), err
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["objects"][cars[1]]["A"]["error_percent"] is not None
    assert res["classes"]["car"]["B"]["missing_reasons"] == {"unreadable mesh": [cars[1]]}


def test_methods_are_compared_on_the_objects_every_one_has(recon, tmp_path, capsys):
    """A method that failed on some objects (a mesh gone, a camera entry gone: the run skipped them) is not ranked
    on fewer objects: the class's row compares every method on the objects they all have (here the same meshes,
    so the same means, both in bold), a note says what each method misses and why; a class no object of which
    every method has shows each method's own mean, unranked."""
    data, gt = _gt(recon)
    fail = tmp_path / "fail"
    shutil.copytree(recon, fail)
    meshes = sorted((fail / "car" / "meshes").glob("*.ply"), key=lambda q: int(q.stem))
    gone, skipped = meshes[0].stem, meshes[1].stem
    meshes[0].unlink()
    meshes[1].unlink()
    cj = json.loads((fail / "car" / "cameras.json").read_text())
    del cj["cameras"][skipped]
    (fail / "car" / "cameras.json").write_text(json.dumps(cj))
    summary = json.loads((fail / "summary.json").read_text())
    summary["classes"]["car"]["failures"].append({"annotation_id": int(skipped), "reason": "no usable camera"})
    (fail / "summary.json").write_text(json.dumps(summary))
    assert main(["--data", str(data), "--recon", f"A={recon}", "--recon", f"B={fail}", "--classes", "car",
                 "--step-percent", "5", "--quiet", "--out", str(tmp_path / "ev")]) == 0
    err = _err_lines(capsys)
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    car, common = res["classes"]["car"], res["compared"]["car"]["compared"]
    assert gone not in common and skipped not in common and len(common) == car["B"]["count"]
    assert car["A"]["compared_mean"] == pytest.approx(car["B"]["compared_mean"])
    assert car["B"]["missing_reasons"] == {"no reconstruction": [gone], "skipped by the run": [skipped]}
    row = next(line for line in (tmp_path / "ev" / "shapes.md").read_text().splitlines() if line.startswith("| car"))
    mean = f"{car['A']['compared_mean']:.2f}"
    assert row == f"| car ({len(common)} of {len(gt)}) | **{mean}** | **{mean}** |"  # a tie: both in bold
    assert any(line.startswith(f"note: car: B has no shape error for 2 of {len(gt)} objects (no reconstruction: "
                               f"{gone}; skipped by the run: {skipped}); the shape table compares car on the "
                               f"{len(common)} objects every method has") for line in err), err
    assert f"evaluate: car annotation {skipped}: B has no shape error: skipped by the run: no usable camera" in err
    # nothing in common: each method's own mean with its count, none in bold, the mean row says what it covers
    for m in (fail / "car" / "meshes").glob("*.ply"):
        m.unlink()
    res = evaluate(data, {"A": recon, "B": fail}, classes=["car"], step_percent=5.0, progress=False)
    text = format_shape_table(res)
    assert f"| car (none of {len(gt)} in common) | {res['classes']['car']['A']['mean']:.2f} " \
           f"({res['classes']['car']['A']['count']}) | - |" in text
    assert "**" not in text.replace("**mean**", "") and "| **mean** (0 of 1 classes) | - | - |" in text


def test_an_unfinished_run_is_named_and_its_missing_objects_say_why(recon, tmp_path, capsys):
    data, gt = _gt(recon)
    unf = tmp_path / "unf"
    shutil.copytree(recon, unf)
    (unf / "summary.json").unlink()
    first = sorted((unf / "car" / "meshes").glob("*.ply"))[0]
    first.unlink()
    assert main(["--data", str(data), "--recon", str(unf), "--classes", "car", "--step-percent", "5", "--quiet"]) == 0
    err = _err_lines(capsys)
    assert f"note: Full ({unf}) is an unfinished run (interrupted or still running): the objects it has not " \
           "reconstructed yet count as missing" in err
    res = evaluate(data, {"Full": unf}, classes=["car"], step_percent=5.0, progress=False)
    assert res["unfinished"] == ["Full"]
    assert res["objects"][first.stem]["Full"]["reason"] == "not reconstructed yet (the run is unfinished)"


def test_a_class_with_one_object_says_why_it_has_no_viewpoint_report(recon, tmp_path, capsys):
    data, gt = _gt(recon)
    doc = json.loads(data.read_text())
    one = sorted(gt, key=int)[0]
    for a in doc["annotations"]:
        a["split"] = "test" if str(a["id"]) == one else "pool"
    inputs = tmp_path / "input"
    shutil.copytree(data.parent, inputs)
    (inputs / "annotations.json").write_text(json.dumps(doc))
    assert main(["--data", str(inputs / "annotations.json"), "--recon", str(recon), "--split", "test",
                 "--viewpoints-only", "--quiet"]) == 0
    assert "note: car: no viewpoint report for Full: 1 object(s) with a refined camera and ground truth (the global " \
           "alignment needs at least 2)" in _err_lines(capsys)


def test_a_failed_evaluation_leaves_no_folder_it_made(recon, tmp_path, capsys):
    data, _ = _gt(recon)
    out = tmp_path / "newp" / "a" / "b"
    assert main(["--data", str(data), "--recon", str(recon), "--split", "nosuch", "--quiet", "--out", str(out)]) == 2
    assert capsys.readouterr().err.startswith("error: ") and not (tmp_path / "newp").exists()
    (tmp_path / "kept").mkdir()  # a folder that was there stays
    assert main(["--data", str(data), "--recon", str(recon), "--split", "nosuch", "--quiet", "--out",
                 str(tmp_path / "kept" / "a")]) == 2
    assert (tmp_path / "kept").is_dir() and not (tmp_path / "kept" / "a").exists()


def test_a_recon_folder_whose_path_holds_an_equals_sign(recon, tmp_path, capsys):
    """An existing folder is taken whole, ``=`` in its path or not; otherwise NAME=DIR splits at the first ``=``."""
    data, _ = _gt(recon)
    odd = tmp_path / "x=y" / "run"
    shutil.copytree(recon, odd, ignore=shutil.ignore_patterns("meshes", "voxels", "input"))
    assert main(["--data", str(data), "--recon", str(odd), "--viewpoints-only", "--quiet"]) == 0
    assert "| car | Full | refined |" in capsys.readouterr().out
    assert main(["--data", str(data), "--recon", f"M={odd}", "--viewpoints-only", "--quiet"]) == 0
    assert "| car | M | refined |" in capsys.readouterr().out


def test_a_class_without_ground_truth_is_labelled_so_and_left_out_of_the_mean_count():
    """No method misses anything where the ground truth is absent: the row says so, and the mean's class count
    leaves that class out (it read "none of 6 in common" and "1 of 2 classes")."""
    from carvi_torch.evaluate import format_shape_table

    res = {"methods": ["A", "B"],
           "compared": {"car": {"objects": 3, "without_ground_truth": 0, "compared": ["1", "2", "3"]},
                        "chair": {"objects": 6, "without_ground_truth": 6, "compared": []}},
           "classes": {"car": {"A": {"mean": 3.0, "count": 3, "compared_mean": 3.0},
                               "B": {"mean": 2.5, "count": 3, "compared_mean": 2.5}},
                       "chair": {"A": {"mean": None, "count": 0, "compared_mean": None},
                                 "B": {"mean": None, "count": 0, "compared_mean": None}}},
           "mean_over_classes": {"A": 3.0, "B": 2.5}, "mean_over_classes_compared": {"A": 3.0, "B": 2.5}}
    table = format_shape_table(res)
    assert "| chair (no ground truth for its 6) | - | - |" in table
    assert "| **mean** | 3.00 | 2.50 |" in table and "in common" not in table


def test_a_missing_refined_camera_is_not_blamed_on_an_unusable_sfm_camera(recon, tmp_path, capsys):
    """An object whose SfM camera is unusable and whose refined camera is absent has no refined camera because
    there is none, not because of its SfM camera; an unusable refined camera beside an unusable SfM one is the
    refined camera's problem; an unusable SfM camera beside a good refined one leaves the object's viewpoint
    scored. The SfM problem is still a line of its own."""
    data, part, p, cj, ids = _run_copy_cameras(recon, tmp_path)
    for a in ids[:3]:
        cj["cameras"][a]["sfm"]["R"] = cj["cameras"][a]["sfm"]["R"][:2]
    cj["cameras"][ids[0]]["refined"] = None
    cj["cameras"][ids[1]]["refined"]["R"] = cj["cameras"][ids[1]]["refined"]["R"][:2]
    p.write_text(json.dumps(cj))
    assert main(["--data", str(data), "--recon", str(part), "--viewpoints-only", "--quiet", "--out",
                 str(tmp_path / "ev")]) == 0
    err = _err_lines(capsys)
    assert f"evaluate: car annotation {ids[0]}: Full: unusable sfm camera in cameras.json: R is not 3 x 3 " \
           "numbers" in err
    coverage = json.loads((tmp_path / "ev" / "results.json").read_text())["viewpoint_coverage"]["car"]["Full"]
    assert coverage["missing"] == {ids[0]: "no refined camera",
                                   ids[1]: "unusable refined camera in cameras.json: R is not 3 x 3 numbers"}
    assert coverage["missing_reasons"] == {"no refined camera": [ids[0]],
                                           "unusable refined camera in cameras.json": [ids[1]]}
    assert coverage["objects"] == len(ids) - 2


def test_runs_that_stopped_after_the_cameras_are_told_by_their_config(tmp_path, monkeypatch):
    """``_camera_only`` names the runs whose ``config.yaml`` says ``stage: cameras``; a missing or damaged one says
    nothing, and a fault of the code reading it is raised, not taken for a damaged file."""
    import carvi_torch.evaluate as ev

    runs = {name: tmp_path / name for name in ("cams", "full", "none", "bad")}
    for rdir in runs.values():
        rdir.mkdir()
    (runs["cams"] / "config.yaml").write_text("stage: cameras\n")
    (runs["full"] / "config.yaml").write_text("stage: all\n")
    (runs["bad"] / "config.yaml").write_text("stage: [cameras\n")
    assert ev._camera_only(runs) == ["cams"]

    def broken(path):
        raise RuntimeError("a fault of the code")

    monkeypatch.setattr(ev, "read_run_config", broken)
    with pytest.raises(RuntimeError, match="a fault of the code"):
        ev._camera_only(runs)
