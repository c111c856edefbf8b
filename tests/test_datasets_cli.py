"""Tests of model loading, flip pairs, the COCO dataset writer and ``python -m carvi_torch.datasets``."""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from carvi_torch import datasets
from conftest import run_each_in_a_fresh_process
from carvi_torch.cameras import ScaledOrthographic
from carvi_torch.synthetic.meshes import (Model, harmonize_sides, infer_flip_pairs, load_cad_npz, load_models,
                                          side_disagreements, turned_models)
from carvi_torch.synthetic.render import (RENDER_VERSION, rasterize_triangles, read_render_info, render_dataset,
                                          render_info, render_mismatch)

ROOT = Path(__file__).resolve().parents[1]

# --------------------------------------------------------------------------- infer_flip_pairs


def test_infer_flip_pairs_naming_styles():
    names = ["left_wing", "right_wing", "noselanding", "body_back_left_lower", "body_back_right_lower",
             "L_WingTip", "R_WingTip", "Left_Wing_Base", "Right_Wing_Base", "wheel_l", "wheel_r",
             "mirror_left", "mirror_right", "leftcorner_windshield", "rightcorner_windshield", "l_eye", "r_eye",
             "rudder", "tail"]
    pairs = infer_flip_pairs(names)
    got = {(names[i], names[j]) for i, j in pairs}
    assert got == {("left_wing", "right_wing"), ("body_back_left_lower", "body_back_right_lower"),
                   ("L_WingTip", "R_WingTip"), ("Left_Wing_Base", "Right_Wing_Base"), ("wheel_l", "wheel_r"),
                   ("mirror_left", "mirror_right"), ("leftcorner_windshield", "rightcorner_windshield"),
                   ("l_eye", "r_eye")}
    assert all(i < j for i, j in pairs) and pairs == sorted(pairs)


def test_infer_flip_pairs_only_existing_counterparts():
    assert infer_flip_pairs(["left_wing", "tail", "rudder"]) == []
    assert infer_flip_pairs([]) == []
    # single letters swap only as whole name parts; case must match
    assert infer_flip_pairs(["rudder", "ludder", "L_x", "r_x"]) == []
    assert infer_flip_pairs(["upper_left_windshield", "upper_right_windshield"]) == [(0, 1)]


@pytest.mark.shared
def test_infer_flip_pairs_on_every_cad_class(shared_data):
    for path in sorted((shared_data / "pascal3d_cad").glob("*.npz")):
        names = [str(n) for n in np.load(path)["keypoint_names"]]
        pairs = infer_flip_pairs(names)
        sided = [n for n in names if "left" in n or "right" in n]
        # every keypoint naming a side is paired when its counterpart exists
        paired = {names[k] for p in pairs for k in p}
        for n in sided:
            other = n.replace("left", "\0").replace("right", "left").replace("\0", "right")
            assert (n in paired) == (other in names), (path.name, n)


# --------------------------------------------------------------------------- loaders


@pytest.mark.shared
def test_load_cad_models(shared_data):
    models = load_models(shared_data / "pascal3d_cad")
    assert len(models) == 73
    assert [m.name for m in models] == sorted(m.name for m in models)
    cats = {m.category for m in models}
    assert cats == {"aeroplane", "bicycle", "boat", "bottle", "bus", "car", "chair", "diningtable", "motorbike",
                    "sofa", "train", "tvmonitor"}
    car = next(m for m in models if m.name == "car01")
    raw = np.load(shared_data / "pascal3d_cad" / "car01.npz")
    assert car.category == "car" and car.source == "car01.npz"
    assert car.vertices.dtype == torch.float32 and car.faces.dtype == torch.long
    np.testing.assert_array_equal(car.vertices.numpy(), raw["vertices"])
    np.testing.assert_array_equal(car.faces.numpy(), raw["faces"])
    assert car.keypoint_names == [str(n) for n in raw["keypoint_names"]]
    # keypoint sets differ between models of a class: kept as they are
    assert len({len(m.keypoint_names) for m in models if m.category == "car"}) > 1


def _sided_model(name: str, xs: dict, width: float = 2.0, category: str = "thing") -> Model:
    """A model of ``category`` whose keypoints sit at x = ``xs[name]`` (y, z = 0), ``width`` wide."""
    box = torch.tensor([[-width / 2, 0.0, 0.0], [width / 2, 0.0, 0.0], [0.0, 1.0, 0.0]])
    pts = torch.tensor([[x, 0.0, 0.0] for x in xs.values()])
    return Model(name, category, box, torch.tensor([[0, 1, 2]]), list(xs), pts)


#: Left names at -x on both pairs; pair a named from the other side; both pairs turned (the model faces +y).
STD = {"left_a": -0.8, "right_a": 0.8, "left_b": -0.5, "right_b": 0.5, "nose": 0.0}
ODD = {"left_a": 0.7, "right_a": -0.7, "left_b": -0.6, "right_b": 0.6, "nose": 0.0}
TURNED = {"left_a": 0.8, "right_a": -0.8, "left_b": 0.5, "right_b": -0.5, "nose": 0.0}


def test_side_disagreements_needs_two_unanimous_others_and_a_clear_separation():
    assert side_disagreements([_sided_model("m0", STD), _sided_model("m1", STD), _sided_model("m2", ODD)]) == \
        [(2, ("left_a", "right_a"), 2)]
    # the names in another order on the model: the same pair
    rev = dict(reversed(list(ODD.items())))
    assert side_disagreements([_sided_model("m0", STD), _sided_model("m1", STD), _sided_model("m2", rev)]) == \
        [(2, ("left_a", "right_a"), 2)]
    # one other model only, a split class, or another class: nothing to go by
    assert side_disagreements([_sided_model("m0", STD), _sided_model("m1", ODD)]) == []
    assert side_disagreements([_sided_model("m0", STD), _sided_model("m1", ODD), _sided_model("m2", ODD),
                               _sided_model("m3", STD)]) == []
    assert side_disagreements([_sided_model("m0", STD, category="a"), _sided_model("m1", STD, category="a"),
                               _sided_model("m2", ODD, category="b")]) == []
    # pair a 0.1 apart votes on a model 0.9 wide, not on one 1.1 wide (the threshold is 10% of the width)
    near = {**STD, "left_a": 0.05, "right_a": -0.05}
    for width, found in [(0.9, [(2, ("left_a", "right_a"), 2)]), (1.1, [])]:
        assert side_disagreements([_sided_model("m0", STD), _sided_model("m1", STD),
                                   _sided_model("m2", near, width=width)]) == found, width
    # a model without vertices does not vote (nor is it judged)
    empty = Model("m3", "thing", torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.long), list(ODD),
                  torch.tensor([[x, 0.0, 0.0] for x in ODD.values()]))
    assert side_disagreements([_sided_model("m0", STD), _sided_model("m1", STD), empty]) == []


def test_harmonize_sides_renames_a_misnamed_pair_and_keeps_a_turned_model():
    models = [_sided_model("m0", STD), _sided_model("m1", STD), _sided_model("m2", ODD)]
    with pytest.warns(UserWarning, match="m2: 'left_a' and 'right_a' exchanged"):
        fixed = harmonize_sides(models)
    assert fixed[2].keypoint_names == ["right_a", "left_a", "left_b", "right_b", "nose"]
    assert fixed[2].side_swaps == [("left_a", "right_a")]
    torch.testing.assert_close(fixed[2].keypoints, models[2].keypoints)  # the points stay, their names move
    assert fixed[0] is models[0] and fixed[1] is models[1] and models[2].keypoint_names == list(ODD)
    assert side_disagreements(fixed) == []
    # every pair on the other side: a model turned in its frame keeps its names, with a warning
    turned = [_sided_model("m0", STD), _sided_model("m1", STD), _sided_model("m2", TURNED)]
    assert side_disagreements(turned) == [] and turned_models(turned) == [2]
    with pytest.warns(UserWarning, match="m2: every left/right pair lies on the other side"):
        kept = harmonize_sides(turned)
    assert kept[2] is turned[2]


@pytest.mark.shared
def test_load_models_names_motorbike01s_handles_like_the_other_motorbikes(shared_data):
    """PASCAL3D+'s motorbike01 puts ``left_handle_center`` at +x, where its left wheels are at -x and where the
    other three motorbikes put their right handle; loading renames that pair and nothing else."""
    with pytest.warns(UserWarning, match="motorbike01: 'left_handle_center' and 'right_handle_center' exchanged"):
        models = load_models(shared_data / "pascal3d_cad")
    given = load_models(shared_data / "pascal3d_cad", sides="as-given")
    changed = [m.name for m, g in zip(models, given) if m.keypoint_names != g.keypoint_names]
    assert changed == ["motorbike01"]
    for m in models:
        if m.category == "motorbike":
            x = dict(zip(m.keypoint_names, m.keypoints[:, 0].tolist()))
            assert x["left_handle_center"] < 0 < x["right_handle_center"], m.name
            assert x["left_back_wheel"] < x["right_back_wheel"], m.name
    assert side_disagreements(models) == [] and [m.side_swaps for m in given if m.side_swaps] == []
    with pytest.raises(ValueError, match="sides"):
        load_models(shared_data / "pascal3d_cad", sides="geometry")


def test_render_info_records_the_side_swaps(tmp_path):
    with pytest.warns(UserWarning, match="exchanged"):
        models = harmonize_sides([_sided_model("m0", STD), _sided_model("m1", STD), _sided_model("m2", ODD)])
    render_dataset(models, tmp_path / "r", views=1, progress=False, image_size=32)
    info = read_render_info(tmp_path / "r")
    assert info["side_swaps"] == {"m2": [["left_a", "right_a"]]} and info["views"] == 1
    gt = json.loads((tmp_path / "r" / "gt.json").read_text())["models"]["m2"]["keypoints"]
    assert gt["right_a"] == pytest.approx([0.7, 0.0, 0.0])
    assert read_render_info(tmp_path / "absent") is None
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "annotations.json").write_text('{"images": []}')
    assert read_render_info(tmp_path / "bad") is None


def test_render_mismatch_names_each_setting_that_differs(tmp_path):
    """A folder rendered with these arguments matches them (after the JSON round trip: tuples come back as
    lists); each setting, model list and left/right naming that differs gives its own one-line reason, and so
    does a record without the setting (an older version's) or without any record."""
    import inspect

    with pytest.warns(UserWarning, match="exchanged"):
        models = harmonize_sides([_sided_model("m0", STD), _sided_model("m1", STD), _sided_model("m2", ODD)])
    as_given = [_sided_model("m0", STD), _sided_model("m1", STD), _sided_model("m2", ODD)]
    cams = {"elevation_range_deg": (0.0, 50.0), "roll_sd_deg": 2.0}
    asked = dict(views=2, test_views=1, seed=3, image_size=32, keypoint_noise=0.5, boundary_noise=0.25,
                 camera_options=cams)
    render_dataset(models, tmp_path / "r", progress=False, **asked)
    info = read_render_info(tmp_path / "r")
    assert render_mismatch(info, models, **asked) is None
    assert info["camera_options"] == {"elevation_range_deg": [0.0, 50.0], "roll_sd_deg": 2.0}
    assert info["models"] == ["m0", "m1", "m2"] and info["image_size"] == [32, 32]

    def reason(models=models, **change):
        return render_mismatch(info, models, **dict(asked, **change))

    assert reason(views=3) == "views: 2 recorded, 3 wanted"
    assert reason(test_views=0) == "test_views: 1 recorded, 0 wanted"
    assert reason(seed=0) == "seed: 3 recorded, 0 wanted"
    assert reason(image_size=(32, 24)) == "image_size: [32, 32] recorded, [32, 24] wanted"
    assert reason(keypoint_noise=0.0) == "keypoint_noise: 0.5 recorded, 0.0 wanted"
    assert reason(boundary_noise=1) == "boundary_noise: 0.25 recorded, 1.0 wanted"
    assert reason(camera_options=None) == "camera_options elevation_range_deg: [0.0, 50.0] recorded, none wanted"
    assert reason(camera_options=dict(cams, roll_sd_deg=3.0)) == \
        "camera_options roll_sd_deg: 2.0 recorded, 3.0 wanted"
    assert reason(models=models[:2]) == "models: 3 recorded, 2 wanted; not wanted: m2"
    more = [Model(f"n{i}", m.category, m.vertices, m.faces, m.keypoint_names, m.keypoints)
            for i, m in enumerate(models + models)]
    assert reason(models=models + more) == "models: 3 recorded, 9 wanted; not recorded: n0, n1, n2 and 3 more"
    assert reason(models=models[::-1]) == "models: the same models in another order"
    assert reason(models=as_given) == \
        "other left/right names: m2: [['left_a', 'right_a']] recorded, none wanted"
    # the same names, other content: the mesh, a keypoint, the class
    m1 = models[1]
    bigger = Model(m1.name, m1.category, m1.vertices * 2, m1.faces, m1.keypoint_names, m1.keypoints)
    moved = Model(m1.name, m1.category, m1.vertices, m1.faces, m1.keypoint_names, m1.keypoints + 0.01)
    other = Model(m1.name, "other", m1.vertices, m1.faces, m1.keypoint_names, m1.keypoints)
    for changed in (bigger, moved, other):
        assert reason(models=[models[0], changed, models[2]]) == \
            "models changed since rendered (mesh, keypoints, class or source): m1"
    assert reason(models=[Model(m.name, m.category, m.vertices, m.faces, m.keypoint_names, m.keypoints,
                                side_swaps=m.side_swaps) for m in models]) is None  # the same content again
    assert render_mismatch(dict(info, render_version=0), models, **asked) == \
        f"rendered by renderer version 0, this is version {RENDER_VERSION}"
    for key in ("render_version", "seed", "camera_options", "models", "side_swaps", "model_hashes"):
        older = {k: v for k, v in info.items() if k != key}
        assert render_mismatch(older, models, **asked) == f"{key} not recorded (rendered by an older version)"
    assert render_mismatch(None, models, **asked).startswith("no render record")
    with pytest.raises(TypeError):
        render_mismatch(info, models, **asked, device="cpu")  # not a setting of the renders
    # its settings are render_dataset's, with render_dataset's defaults
    ours = inspect.signature(render_info).parameters
    theirs = inspect.signature(render_dataset).parameters
    assert {k: p.default for k, p in ours.items()} == {k: theirs[k].default for k in ours}


def test_render_dataset_records_numpy_and_torch_camera_options(tmp_path):
    """Camera options given as numpy numbers or torch dtypes are recorded in JSON form (numbers, the dtype's
    name), and the same options, in either form, match the record."""
    models = _toy_models()[2:3]
    cams = {"roll_sd_deg": np.float32(2.0), "elevation_range_deg": (np.float64(0.0), np.int64(50)),
            "dtype": torch.float64}
    render_dataset(models, tmp_path / "r", views=1, image_size=32, progress=False, camera_options=cams)
    info = read_render_info(tmp_path / "r")
    assert info["camera_options"] == {"roll_sd_deg": 2.0, "elevation_range_deg": [0.0, 50], "dtype": "torch.float64"}
    assert render_mismatch(info, models, views=1, image_size=32, camera_options=cams) is None
    assert render_mismatch(info, models, views=1, image_size=32, camera_options=dict(
        cams, roll_sd_deg=2.0, elevation_range_deg=(0.0, 50))) is None


def test_read_render_info_reads_a_long_block_and_refuses_a_broken_one(tmp_path):
    """An ``info`` block longer than the first read (10,000 model names) is read whole; one cut short is
    refused (``None``)."""
    names = [f"model{i:05d}" for i in range(10_000)]
    (tmp_path / "long").mkdir()
    (tmp_path / "long" / "annotations.json").write_text(json.dumps({"info": {"models": names}, "images": []}))
    assert read_render_info(tmp_path / "long") == {"models": names}
    (tmp_path / "cut").mkdir()
    (tmp_path / "cut" / "annotations.json").write_text(json.dumps({"info": {"models": names}})[:-2])
    assert read_render_info(tmp_path / "cut") is None


def test_load_mesh_with_json_and_messy_keypoints(tmp_path):
    box = trimesh.creation.box(extents=(1, 2, 3))
    for ext in ("ply", "obj", "off", "stl"):
        box.export(tmp_path / f"thing{ext}_1.{ext}")
        (tmp_path / f"thing{ext}_1.json").write_text(json.dumps(
            {"class": "thing", "keypoints": {"top": [0, 0, 1.5], "left_side": [-0.5, 0, 0], "gone": None,
                                             "bad": [float("nan"), 0, 0]}}))
    box.export(tmp_path / "orphan.ply")  # no json: skipped with a warning
    np.savez(tmp_path / "cup07.npz", vertices=box.vertices.astype(np.float32), faces=box.faces.astype(np.int32),
             keypoint_names=np.array(["rim", "rim", "base"]), keypoints=np.zeros((3, 3), np.float32))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        models = load_models(tmp_path)
    messages = " ".join(str(w.message) for w in caught)
    assert "orphan.ply" in messages and "non-finite" in messages and "repeated" in messages
    assert [m.name for m in models] == ["cup07", "thingobj_1", "thingoff_1", "thingply_1", "thingstl_1"]
    cup = models[0]
    assert cup.category == "cup" and cup.keypoint_names == ["rim", "base"]
    for m in models[1:]:
        assert m.category == "thing" and m.keypoint_names == ["top", "left_side"]
        # the same geometry whatever the format (obj / stl may reorder or duplicate vertices)
        tm = trimesh.Trimesh(m.vertices.double().numpy(), m.faces.numpy())
        assert abs(tm.volume - 6.0) < 1e-4, m.name
        torch.testing.assert_close(m.keypoints, torch.tensor([[0, 0, 1.5], [-0.5, 0, 0]]))


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_models(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="no models"):
        load_models(tmp_path)
    np.savez(tmp_path / "a1.npz", vertices=np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match="faces"):
        load_cad_npz(tmp_path / "a1.npz")
    with pytest.raises(ValueError, match="faces"):
        Model("x", "x", torch.zeros(3, 3), torch.tensor([[0, 1, 5]]))


# --------------------------------------------------------------------------- render_dataset


def _toy_models() -> list[Model]:
    """Two small classes, keypoint sets differing within a class, one model without keypoints."""
    box = trimesh.creation.box(extents=(0.6, 0.9, 0.4))
    ico = trimesh.creation.icosphere(subdivisions=2, radius=0.4)
    cyl = trimesh.creation.cylinder(radius=0.15, height=0.9)
    kb = {"left_front": [-0.3, -0.45, 0.2], "right_front": [0.3, -0.45, 0.2], "top": [0, 0, 0.2]}
    return [
        Model("crate01", "crate", box.vertices, box.faces, list(kb), list(kb.values()), source="crate01.ply"),
        Model("crate02", "crate", ico.vertices, ico.faces, ["top", "bottom"], [[0, 0, 0.4], [0, 0, -0.4]],
              source="crate02.ply"),
        Model("bottle01", "bottle", cyl.vertices, cyl.faces, ["mouth", "mouth_left", "mouth_right"],
              [[0, -0.15, 0.45], [-0.15, 0, 0.45], [0.15, 0, 0.45]], source="bottle01.ply"),
        Model("crate03", "crate", box.vertices, box.faces, [], torch.zeros(0, 3), source="crate03.ply"),
    ]


@pytest.fixture(scope="module")
def toy_dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("toy")
    summary = render_dataset(_toy_models(), out, views=4, test_views=1, seed=3, image_size=(96, 72), progress=False)
    return out, summary


def test_render_dataset_coco_loads_and_masks_match(toy_dataset):
    from pycocotools.coco import COCO

    out, summary = toy_dataset
    assert summary["images"] == 16 and summary["categories"] == ["bottle", "crate"]
    coco = COCO(str(out / "annotations.json"))
    data = json.loads((out / "annotations.json").read_text())
    gt = json.loads((out / "gt.json").read_text())
    cats = {c["name"]: c for c in data["categories"]}
    assert cats["crate"]["keypoints"] == ["bottom", "left_front", "right_front", "top"]  # sorted union
    assert cats["crate"]["flip_pairs"] == [[1, 2]]
    assert cats["bottle"]["flip_pairs"] == [[1, 2]] and cats["bottle"]["symmetry"] == "rotational"
    assert cats["crate"]["symmetry"] == "none" and cats["crate"]["articulated"] is False
    assert all(c["supercategory"] == "object" and c["skeleton"] == [] for c in data["categories"])
    models = {m.name: m for m in _toy_models()}
    for ann in data["annotations"]:
        img = coco.loadImgs(ann["image_id"])[0]
        assert (img["width"], img["height"]) == (96, 72)
        g = gt["annotations"][str(ann["id"])]
        model = models[g["model"]]
        assert img["file_name"].startswith(g["model"] + "_v") and img["file_name"].endswith(".png")
        assert ann["source"] == model.source and g["category"] == model.category
        assert g["mesh"] == f"meshes/{model.name}.ply" and (out / g["mesh"]).is_file()
        # the true camera reproduces the written mask exactly (pycocotools decodes it)
        cam = ScaledOrthographic.from_list([g])
        mask = rasterize_triangles(cam.project(model.vertices)[0], model.faces, 72, 96).numpy()
        decoded = coco.annToMask(ann).astype(bool)
        np.testing.assert_array_equal(decoded, mask)
        assert ann["area"] == mask.sum() and ann["iscrowd"] == 0
        ys, xs = np.nonzero(mask)
        assert ann["bbox"] == [xs.min(), ys.min(), xs.max() - xs.min() + 1, ys.max() - ys.min() + 1]
        # keypoints: projected where visible, zeros where occluded or absent on the model
        names = coco.loadCats(ann["category_id"])[0]["keypoints"]
        kp = np.array(ann["keypoints"], dtype=float).reshape(-1, 3)
        assert ann["num_keypoints"] == int((kp[:, 2] == 2).sum())
        for (x, y, v), n in zip(kp, names):
            if n not in model.keypoint_names:
                assert (x, y, v) == (0, 0, 0)
            elif v == 2:
                p = cam.project(model.keypoints[model.keypoint_names.index(n)][None])[0, 0]
                assert abs(x - p[0]) < 1e-3 and abs(y - p[1]) < 1e-3
            else:
                assert (x, y, v) == (0, 0, 0)
    # object ids: one per model; split: the first test_views renders of each model
    by_model: dict = {}
    for ann in data["annotations"]:
        by_model.setdefault(gt["annotations"][str(ann["id"])]["model"], []).append(ann)
    assert len({anns[0]["object_id"] for anns in by_model.values()}) == 4
    for anns in by_model.values():
        assert len({a["object_id"] for a in anns}) == 1
        assert [a["split"] for a in anns] == ["test", "pool", "pool", "pool"]
    # the 3-D keypoints travel in gt.json
    kp3 = gt["models"]["crate02"]["keypoints"]
    assert list(kp3) == ["top", "bottom"]
    np.testing.assert_allclose([kp3["top"], kp3["bottom"]], [[0, 0, 0.4], [0, 0, -0.4]], atol=1e-6)


def test_render_dataset_deterministic(toy_dataset, tmp_path):
    out, _ = toy_dataset
    render_dataset(_toy_models(), tmp_path / "same", views=4, test_views=1, seed=3, image_size=(96, 72),
                   progress=False)
    files = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(tmp_path / "same") for p in (tmp_path / "same").rglob("*") if p.is_file())
    for f in files:
        assert (out / f).read_bytes() == (tmp_path / "same" / f).read_bytes(), f
    render_dataset(_toy_models(), tmp_path / "other", views=4, test_views=1, seed=4, image_size=(96, 72),
                   progress=False)
    g1 = json.loads((out / "gt.json").read_text())["annotations"]
    g2 = json.loads((tmp_path / "other" / "gt.json").read_text())["annotations"]
    assert all(not np.allclose(g1[k]["R"], g2[k]["R"]) for k in g1)
    # a model's renders depend only on (seed, model name), not on the other models
    render_dataset(_toy_models()[2:3], tmp_path / "alone", views=4, seed=3, image_size=(96, 72), progress=False)
    g3 = json.loads((tmp_path / "alone" / "gt.json").read_text())["annotations"]
    bottle = [k for k in g1 if g1[k]["model"] == "bottle01"]
    assert [g1[k]["R"] for k in bottle] == [g3[k]["R"] for k in sorted(g3, key=int)]


def test_render_dataset_noise_and_errors(tmp_path):
    models = _toy_models()[:1]
    clean = render_dataset(models, tmp_path / "a", views=2, seed=1, image_size=96, progress=False)
    noisy = render_dataset(models, tmp_path / "b", views=2, seed=1, image_size=96, keypoint_noise=1.0,
                           boundary_noise=1.5, progress=False)
    a = json.loads(Path(clean["annotations"]).read_text())["annotations"]
    b = json.loads(Path(noisy["annotations"]).read_text())["annotations"]
    assert a[0]["segmentation"]["size"] == [96, 96]
    assert a[0]["segmentation"] != b[0]["segmentation"] and a[0]["keypoints"] != b[0]["keypoints"]
    with pytest.raises(ValueError, match="test_views"):
        render_dataset(models, tmp_path / "c", views=2, test_views=3, progress=False)
    with pytest.raises(ValueError, match="unique"):
        render_dataset(models + models, tmp_path / "c", views=1, progress=False)
    with pytest.raises(ValueError, match="views"):
        render_dataset(models, tmp_path / "c", views=0, progress=False)


def test_render_dataset_cut_short_leaves_no_record_of_its_files(tmp_path, monkeypatch):
    """``annotations.json`` marks a complete folder: a render into a folder of other renders removes it first
    and writes it last, so a render cut short (here while ``gt.json`` is written) leaves no record that passes
    for the files, and ``gt.json`` is never older than the record beside it."""
    from carvi_torch.io import outputs

    models, out = _toy_models()[2:3], tmp_path / "r"
    render_dataset(models, out, views=1, seed=0, image_size=32, progress=False)
    written = outputs.write_json

    def cut_short(path, obj, **kw):
        if Path(path).name == "gt.json":
            raise KeyboardInterrupt
        return written(path, obj, **kw)

    monkeypatch.setattr(outputs, "write_json", cut_short)
    with pytest.raises(KeyboardInterrupt):
        render_dataset(models, out, views=1, seed=1, image_size=32, progress=False)
    assert not (out / "annotations.json").exists() and read_render_info(out) is None
    monkeypatch.undo()
    render_dataset(models, out, views=1, seed=1, image_size=32, progress=False)
    render_dataset(models, tmp_path / "s1", views=1, seed=1, image_size=32, progress=False)
    assert render_mismatch(read_render_info(out), models, views=1, seed=1, image_size=32) is None
    assert (out / "gt.json").read_bytes() == (tmp_path / "s1" / "gt.json").read_bytes()


# --------------------------------------------------------------------------- CLI


@pytest.mark.parametrize("command", [[], ["synthetic"], ["procedural"], ["voc"]])
def test_cli_help(command, capsys):
    with pytest.raises(SystemExit) as e:
        datasets.main(command + ["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert "usage" in text
    if command == ["synthetic"]:
        assert "--meshes" in text and "--boundary-noise" in text and "--image-size" in text and "--canvas" in text
        from carvi_torch.synthetic.meshes import MESH_SUFFIXES

        words = " ".join(text.split())  # argparse wraps lines anywhere
        assert all(s in words for s in (".npz", *MESH_SUFFIXES)), words
        assert "meshes/ and images/ folders deleted first" in words and "replaced" in words
    if command == ["voc"]:
        assert "--keypoints" in text and "--masks" in text


def test_cli_synthetic_and_procedural(tmp_path, capsys):
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for m in _toy_models()[:3]:
        m.to_trimesh().export(meshes / f"{m.name}.ply")
        (meshes / f"{m.name}.json").write_text(json.dumps({"class": m.category, "keypoints": m.keypoint_dict()}))
    rc = datasets.main(["synthetic", "--meshes", str(meshes), "--out", str(tmp_path / "syn"), "--views", "3",
                        "--test-views", "1", "--seed", "2", "--canvas", "64", "--keypoint-noise", "0.5", "--quiet"])
    assert rc == 0
    data = json.loads((tmp_path / "syn" / "annotations.json").read_text())
    assert len(data["images"]) == 9 and {(i["width"], i["height"]) for i in data["images"]} == {(64, 64)}
    assert sum(a["split"] == "test" for a in data["annotations"]) == 3
    rc = datasets.main(["procedural", "--out", str(tmp_path / "proc"), "--instances", "1", "--classes", "car,bottle",
                        "--image-size", "80", "60", "--quiet"])
    assert rc == 0
    data = json.loads((tmp_path / "proc" / "annotations.json").read_text())
    assert [c["name"] for c in data["categories"]] == ["bottle", "car"]
    assert {(i["width"], i["height"]) for i in data["images"]} == {(80, 60)}
    assert "wrote 2 renders" in capsys.readouterr().out


def test_cli_procedural_writes_only_over_an_earlier_dataset(tmp_path, capsys):
    """``datasets procedural`` refuses a non-empty ``--out`` that is not an earlier dataset (one ``error:`` line,
    exit 2, nothing written) and replaces an earlier one whole: no mesh of the earlier models stays."""
    args = ["procedural", "--instances", "1", "--classes", "car", "--canvas", "32", "--quiet", "--out"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine")
    assert datasets.main([*args, str(other)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: --out {other}: not empty") and "'notes.txt'" in err[0], err
    assert [p.name for p in other.iterdir()] == ["notes.txt"]
    out = tmp_path / "proc"
    assert datasets.main([*args, str(out)]) == 0
    meshes = sorted(p.name for p in (out / "meshes").iterdir())
    (out / "meshes" / "car_stale.ply").write_bytes(b"an earlier model")
    (out / "images").mkdir()
    (out / "images" / "car_stale_v000.png").write_bytes(b"an earlier photograph")
    assert datasets.main([*args, str(out)]) == 0
    assert sorted(p.name for p in (out / "meshes").iterdir()) == meshes
    assert sorted(p.name for p in out.iterdir()) == ["annotations.json", "gt.json", "meshes"]


def test_cli_synthetic_names_sides_like_the_class_unless_told(tmp_path, capsys):
    """``datasets synthetic`` renders a model whose left/right pair is named from the other side with the class's
    names (recorded in the info block, and said on one ``warning:`` line), and with ``--sides as-given`` with its
    own."""
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for name, xs in [("thing1", STD), ("thing2", STD), ("thing3", ODD)]:
        m = _sided_model(name, xs)
        m.to_trimesh().export(meshes / f"{name}.ply")
        (meshes / f"{name}.json").write_text(json.dumps({"class": "thing", "keypoints": m.keypoint_dict()}))
    args = ["synthetic", "--meshes", str(meshes), "--views", "1", "--canvas", "32", "--quiet", "--out"]
    assert datasets.main([*args, str(tmp_path / "class")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == ["warning: thing3: 'left_a' and 'right_a' exchanged: the 2 other thing models that have them "
                   "name them from the other side"]
    assert datasets.main([*args, str(tmp_path / "given"), "--sides", "as-given"]) == 0
    assert capsys.readouterr().err == ""
    assert read_render_info(tmp_path / "class")["side_swaps"] == {"thing3": [["left_a", "right_a"]]}
    assert read_render_info(tmp_path / "given")["side_swaps"] == {}
    left = {d: json.loads((tmp_path / d / "gt.json").read_text())["models"]["thing3"]["keypoints"]["left_a"][0]
            for d in ("class", "given")}
    assert left["class"] == pytest.approx(-0.7) and left["given"] == pytest.approx(0.7)


def test_cli_bad_input(tmp_path, capsys):
    """A user error is one ``error:`` line and exit 2, and leaves no ``--out`` (nor its parents) behind."""
    out = str(tmp_path / "made" / "here" / "o")
    assert datasets.main(["synthetic", "--meshes", str(tmp_path / "none"), "--out", out]) == 2
    assert "no such directory" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "empty").mkdir()
    assert datasets.main(["synthetic", "--meshes", str(tmp_path / "empty"), "--out", out]) == 2
    assert datasets.main(["synthetic", "--meshes", str(tmp_path / "empty"), "--out", out, "--views", "2",
                          "--test-views", "3"]) == 2
    assert datasets.main(["procedural", "--out", out, "--classes", "ship"]) == 2
    assert datasets.main(["procedural", "--out", out, "--views", "1", "--test-views", "2"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 4 and all(line.startswith("error: ") for line in err), err
    assert "unknown classes ['ship']" in err[2] and "--test-views (2) exceeds --views (1)" in err[3]
    assert [p.name for p in tmp_path.iterdir()] == ["empty"]
    with pytest.raises(SystemExit):
        datasets.main(["synthetic", "--meshes", "x", "--out", "y", "--views", "0"])
    with pytest.raises(SystemExit):
        datasets.main(["synthetic", "--meshes", "x", "--out", "y", "--image-size", "3", "4", "--canvas", "5"])


def test_cli_voc_converts_fixtures(tmp_path, capsys):
    """The voc subcommand runs the converter: COCO JSON out, skipped objects named with reasons."""
    out = tmp_path / "a.json"
    rc = datasets.main(["voc", "--keypoints", str(ROOT / "tests" / "data" / "voc" / "keypoints"), "--out", str(out)])
    data = json.loads(out.read_text())
    assert rc == 0 and data["annotations"] and data["categories"]
    assert {s[0] if isinstance(s, list) else s["file"] for s in data["carvi_skipped"]}  # some fixtures are bad
    assert "skipped" in capsys.readouterr().out.lower()


def test_cli_module_entry_point():
    """``python -m carvi_torch.datasets synthetic --help`` (``runpy``, as ``-m`` runs it) in a fresh process
    whose environment holds an empty ``PATH`` (no external program is needed; the package is found through
    the fork server's path, as ``PYTHONPATH`` would put it)."""
    code = ("import runpy, sys; sys.argv = ['datasets', 'synthetic', '--help']; "
            "runpy.run_module('carvi_torch.datasets', run_name='__main__', alter_sys=True)")
    [(rc, out, err)] = run_each_in_a_fresh_process([code], cwd=ROOT, env={"PYTHONPATH": str(ROOT), "PATH": ""})
    assert rc == 0 and "--meshes" in out, err[-2000:]


def _models_folder(folder: Path, names=("thing1", "thing2")) -> dict[str, bytes]:
    """Good models (box + keypoint JSON) in ``folder``; returns every file's bytes."""
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        m = _sided_model(name, STD)
        m.to_trimesh().export(folder / f"{name}.ply")
        (folder / f"{name}.json").write_text(json.dumps({"class": "thing", "keypoints": m.keypoint_dict()}))
    return {p.name: p.read_bytes() for p in folder.iterdir()}


@pytest.mark.parametrize("out", ["{d}", "{d}/meshes", "{d}/meshes/o", "{link}"])
def test_cli_synthetic_refuses_an_out_that_holds_or_lies_in_its_models(out, tmp_path, capsys):
    """Models in D/meshes and ``--out D`` (which holds only ``meshes``, so looks like an earlier dataset) used to
    exit 0 with every keypoint file deleted and the meshes overwritten; overlapping folders (also through a link)
    are one ``error:`` line, exit 2, nothing written or removed."""
    d = tmp_path / "D"
    before = _models_folder(d / "meshes")
    (tmp_path / "link").symlink_to(d)
    out = out.format(d=d, link=tmp_path / "link")
    rc = datasets.main(["synthetic", "--meshes", str(d / "meshes"), "--out", out, "--views", "1", "--canvas", "32",
                        "--quiet"])
    err = capsys.readouterr().err.splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("error: --"), err
    assert {p.name: p.read_bytes() for p in (d / "meshes").iterdir()} == before
    assert sorted(p.name for p in d.iterdir()) == ["meshes"]


def test_cli_synthetic_skips_each_bad_model_with_a_warning_and_renders_the_rest(tmp_path, capsys):
    """Bad models used to stop the whole dataset (exit 2, a traceback, an error without the file's name) or
    render empty masks silently; each is now one ``warning:`` line naming its file, the good ones are rendered
    (exit 0, every annotation with a mask), and a folder of nothing but bad models is exit 2."""
    meshes = tmp_path / "meshes"
    _models_folder(meshes, ["thing1"])
    (meshes / "thing2.npz").write_bytes(b"PK\x03\x04 junk")
    (meshes / "thing3.ply").write_text("OBJ text, not PLY\n")
    (meshes / "thing4.obj").write_bytes(b"")
    (meshes / "thing5.json").write_text("[1, 2]")
    _sided_model("thing5", STD).to_trimesh().export(meshes / "thing5.ply")
    for n in ("thing3", "thing4"):
        (meshes / f"{n}.json").write_text(json.dumps({"keypoints": {"top": [0, 0, 0]}}))
    args = ["synthetic", "--meshes", str(meshes), "--views", "2", "--canvas", "32", "--quiet", "--out"]
    assert datasets.main([*args, str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err.splitlines()
    assert [line.split(":")[1].strip() for line in err] == [str(meshes / f) for f in
                                                           ("thing2.npz", "thing3.ply", "thing4.obj", "thing5.json")]
    assert all(line.startswith("warning: ") and line.endswith("skipped") for line in err), err
    data = json.loads((tmp_path / "out" / "annotations.json").read_text())
    assert {a["source"] for a in data["annotations"]} == {"thing1.ply"} and len(data["annotations"]) == 2
    assert all(a["area"] > 0 for a in data["annotations"])
    (meshes / "thing1.json").unlink()
    assert datasets.main([*args, str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 6 and err[-1].startswith("error: ") and "no usable models" in err[-1], err
    assert "Traceback" not in "".join(err) and not (tmp_path / "none").exists()


@pytest.mark.parametrize("option, value, said", [
    ("--seed", "-1", "expected an integer >= 0"), ("--seed", "x", "expected an integer >= 0"),
    ("--test-views", "abc", "expected an integer >= 0"), ("--keypoint-noise", "inf", "expected a finite number"),
    ("--keypoint-noise", "abc", "expected a finite number"), ("--boundary-noise", "nan", "expected a finite number"),
    ("--views", "two", "expected an integer >= 1")])
def test_cli_option_values_are_checked_by_argparse_naming_the_option(option, value, said, tmp_path, capsys):
    """``--seed -1`` used to fail mid-render with a traceback, ``--keypoint-noise inf`` to write null keypoints
    marked visible, and a bad value's message to name a function (``invalid _nonneg_float value``)."""
    with pytest.raises(SystemExit) as e:
        datasets.main(["synthetic", "--meshes", str(tmp_path), "--out", str(tmp_path / "o"), option, value])
    err = capsys.readouterr().err
    assert e.value.code == 2 and f"error: argument {option}: {said}" in err and "invalid" not in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("device", ["bogus", "cuda:7", "meta"])
def test_cli_device_is_checked_before_any_work(device, tmp_path, capsys):
    if device == "cuda:7" and torch.cuda.is_available() and torch.cuda.device_count() > 7:
        pytest.skip("this machine has a cuda:7")
    meshes = tmp_path / "meshes"
    _models_folder(meshes, ["thing1"])
    for command in (["synthetic", "--meshes", str(meshes)], ["procedural", "--instances", "1"]):
        assert datasets.main([*command, "--out", str(tmp_path / "o"), "--device", device, "--quiet"]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].startswith("error: --device ") and device in err[0], err
        assert sorted(p.name for p in tmp_path.iterdir()) == ["meshes"]


def test_cli_device_takes_a_runs_spellings_and_says_which_in_one_line(monkeypatch):
    """``--device`` takes what a run's ``device`` takes (``auto``: CUDA where the machine has it); another is refused
    in one line that says what the renders take, a CUDA device the machine lacks in one that says it has none."""
    from carvi_torch.cli import CommandError

    assert datasets._checked_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    assert datasets._checked_device("cpu") == torch.device("cpu")
    takes = "the renders run on cpu, cuda, cuda:N or auto"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for text in ("cuda", "cuda:1", "meta", "gpu"):
        with pytest.raises(CommandError) as e:
            datasets._checked_device(text)
        why = "this machine has no CUDA device (use --device cpu)" if text.startswith("cuda") else takes
        assert str(e.value) == f"--device {text!r}: {why}"
    assert datasets._checked_device("auto") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert datasets._checked_device("cuda:1") == torch.device("cuda:1")
    for text, said in (("meta", f"--device 'meta': {takes}"),
                       ("cuda:2", "--device cuda:2: this machine has 2 CUDA device(s), cuda:0 to cuda:1")):
        with pytest.raises(CommandError) as e:
            datasets._checked_device(text)
        assert str(e.value) == said


def test_cli_without_a_subcommand_is_a_usage_error(capsys):
    """It printed the help to stdout with exit status 2 and no ``error:`` line."""
    with pytest.raises(SystemExit) as e:
        datasets.main([])
    cap = capsys.readouterr()
    assert e.value.code == 2 and cap.out == ""
    assert "error: choose what to make: synthetic, procedural or voc" in cap.err.splitlines()[-1]
