"""Loading models that cannot be rendered: each is skipped with one reason naming its file, the rest are read.

(The loaders' good paths, PASCAL3D+ models and left/right names are tested in test_datasets_cli.py.)
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from carvi_torch.synthetic.meshes import BadModelFile, Model, load_cad_npz, load_model, load_models

BOX = trimesh.creation.box()  # 1 x 1 x 1 about the origin
KP = {"left_front": [-0.5, -0.5, 0.5], "right_front": [0.5, -0.5, 0.5], "top": [0.0, 0.0, 0.5]}
GOOD = {"class": "thing", "keypoints": KP}
NPZ = dict(vertices=BOX.vertices.astype(np.float32), faces=BOX.faces, keypoint_names=np.array(list(KP)),
           keypoints=np.array(list(KP.values()), np.float32))


def _write(folder: Path, name: str, content) -> None:
    path = folder / name
    if isinstance(content, trimesh.Trimesh):
        content.export(path)
    elif isinstance(content, bytes):
        path.write_bytes(content)
    elif isinstance(content, str):
        path.write_text(content)
    elif name.endswith(".npz"):
        np.savez(path, **content)
    else:
        path.write_text(json.dumps(content))


def _scaled(vertices_scale: float = 1.0, faces=None) -> trimesh.Trimesh:
    return trimesh.Trimesh(BOX.vertices * vertices_scale, BOX.faces if faces is None else faces, process=False)


def _nan_box() -> trimesh.Trimesh:
    v = BOX.vertices.copy()
    v[0] = np.nan
    return trimesh.Trimesh(v, BOX.faces, process=False)


#: name -> (files of the bad model ``thing2``, words its reason holds). Each was rendered with empty masks, read
#: wrongly, or stopped the whole command (exit 2 or a traceback) before.
BAD = {
    "empty_obj": ({"thing2.obj": b"", "thing2.json": GOOD}, "thing2.obj: no faces"),
    "random_stl": ({"thing2.stl": bytes(range(256)) * 2, "thing2.json": GOOD}, "thing2.stl: no faces"),
    "no_faces": ({"thing2.ply": _scaled(faces=np.zeros((0, 3), int)), "thing2.json": GOOD}, "thing2.ply: no faces"),
    "all_zero": ({"thing2.ply": _scaled(0.0), "thing2.json": {"class": "thing", "keypoints": {"a": [0, 0, 0]}}},
                 "thing2.ply: every vertex of its faces lies at one point"),
    "nan_vertex": ({"thing2.ply": _nan_box(), "thing2.json": GOOD}, "thing2.ply: vertices hold non-finite"),
    "keypoints_in_mm": ({"thing2.ply": BOX, "thing2.json": {"class": "thing", "keypoints": {
        k: [1000 * c for c in v] for k, v in KP.items()}}}, "thing2.ply: keypoint(s) 'left_front', 'right_front', "
                                                            "'top' lie far outside the mesh"),
    "text_as_ply": ({"thing2.ply": "hello, not a mesh\n", "thing2.json": GOOD},
                    "thing2.ply: not a readable .ply mesh"),
    "obj_as_ply": ({"thing2.ply": BOX.export(file_type="obj"), "thing2.json": GOOD},
                   "thing2.ply: not a readable .ply mesh"),
    "malformed_json": ({"thing2.ply": BOX, "thing2.json": '{"class": "thing", "keypoints": {'},
                       "thing2.json: malformed JSON at line 1"),
    "json_not_utf8": ({"thing2.ply": BOX, "thing2.json": b'{"class": "th\xefng"}'}, "thing2.json: not UTF-8 text"),
    "json_too_deep": ({"thing2.ply": BOX, "thing2.json": "[" * 100_000 + "]" * 100_000},
                      "thing2.json: JSON nested too deeply"),
    "json_array": ({"thing2.ply": BOX, "thing2.json": [1, 2]}, "thing2.json: expected a JSON object"),
    "keypoint_2d": ({"thing2.ply": BOX, "thing2.json": {"keypoints": {"a": [0, 0]}}},
                    "thing2.json: keypoint 'a' is not three numbers"),
    "keypoint_text": ({"thing2.ply": BOX, "thing2.json": {"keypoints": {"a": ["0", "0", "0"]}}},
                      "thing2.json: keypoint 'a' is not three numbers"),
    "keypoint_list": ({"thing2.ply": BOX, "thing2.json": {"keypoints": [[0, 0, 0]]}},
                      "thing2.json: 'keypoints' must be an object"),
    "no_keypoints": ({"thing2.ply": BOX, "thing2.json": {"class": "thing", "keypoints": {}}},
                     "thing2.ply: no keypoints"),
    "class_number": ({"thing2.ply": BOX, "thing2.json": {"class": 5, "keypoints": KP}}, "thing2.json: 'class'"),
    "junk_npz": ({"thing2.npz": b"PK\x03\x04garbage"}, "thing2.npz: not a readable .npz"),
    "object_npz": ({"thing2.npz": {**NPZ, "keypoint_names": np.array([{"a": 1}] * 3, dtype=object)}},
                   "thing2.npz: array 'keypoint_names' cannot be read"),
    "npz_no_keypoints": ({"thing2.npz": {"vertices": NPZ["vertices"], "faces": NPZ["faces"]}},
                         "thing2.npz: missing array(s) ['keypoint_names', 'keypoints']"),
    "npz_keypoints_transposed": ({"thing2.npz": {**NPZ, "keypoint_names": np.array(["a", "b", "c", "d"]),
                                                 "keypoints": np.zeros((3, 4), np.float32)}},
                                 "thing2.npz: keypoints must be (K, 3)"),
    "npz_fractional_faces": ({"thing2.npz": {**NPZ, "faces": NPZ["faces"] + 0.7}}, "thing2.npz: faces must be integer"),
    "npz_faces_one_based": ({"thing2.npz": {**NPZ, "faces": NPZ["faces"] + 1}}, "thing2.npz: faces index outside"),
    "npz_no_class_name": ({"123.npz": NPZ}, "123.npz: model file stem '123'"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_a_model_that_cannot_be_rendered_is_skipped_with_one_line_naming_it(case, tmp_path):
    files, reason = BAD[case]
    _write(tmp_path, "thing1.ply", BOX)
    _write(tmp_path, "thing1.json", GOOD)
    for name, content in files.items():
        _write(tmp_path, name, content)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        models = load_models(tmp_path)
    assert [m.name for m in models] == ["thing1"]
    lines = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert len(lines) == 1 and "\n" not in lines[0], lines
    assert lines[0].startswith(str(tmp_path)) and reason in lines[0] and lines[0].endswith("skipped"), lines[0]
    bad = tmp_path / next(n for n in files if not n.endswith(".json"))
    with pytest.raises(BadModelFile, match=r"\A" + str(tmp_path)):  # alone: the same reason, as an error
        load_model(bad)


def test_no_usable_model_is_an_error_after_the_reasons(tmp_path):
    _write(tmp_path, "thing1.ply", BOX)
    _write(tmp_path, "thing1.json", [1, 2])
    _write(tmp_path, "thing2.npz", b"junk")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with pytest.raises(ValueError, match="no usable models"):
            load_models(tmp_path)
    assert [str(w.message).split(":")[0] for w in caught] == [str(tmp_path / "thing1.json"),
                                                            str(tmp_path / "thing2.npz")]


def test_files_sharing_a_model_name_are_skipped_and_the_rest_read(tmp_path):
    for name in ("thing1.ply", "thing1.obj", "thing2.ply"):
        _write(tmp_path, name, BOX)
    for name in ("thing1.json", "thing2.json"):
        _write(tmp_path, name, GOOD)
    with pytest.warns(UserWarning, match="thing1.obj, thing1.ply share the model name 'thing1'"):
        assert [m.name for m in load_models(tmp_path)] == ["thing2"]


def test_a_key_given_twice_keeps_the_first_value_with_a_warning(tmp_path):
    """The module promises the first of repeated keypoint names; JSON's own parser kept the last."""
    _write(tmp_path, "thing1.ply", BOX)
    _write(tmp_path, "thing1.json", '{"class": "thing", "class": "other", '
                                    '"keypoints": {"top": [0, 0, 0.5], "left": [-0.5, 0, 0], "top": [9, 9, 9]}}')
    with pytest.warns(UserWarning) as caught:
        [model] = load_models(tmp_path)
    assert model.category == "thing" and model.keypoint_names == ["top", "left"]
    torch.testing.assert_close(model.keypoints, torch.tensor([[0, 0, 0.5], [-0.5, 0, 0]]))
    said = sorted(str(w.message) for w in caught)
    assert said == [f"{tmp_path / 'thing1.json'}: key 'class' given more than once; keeping the first",
                    f"{tmp_path / 'thing1.json'}: key 'top' given more than once; keeping the first"]


def test_npz_keypoints_must_be_k_by_3(tmp_path):
    """(3, 4) with 4 names used to be reshaped into 4 scrambled points."""
    np.savez(tmp_path / "thing1.npz", **{**NPZ, "keypoint_names": np.array(list("abcd")),
                                         "keypoints": np.arange(12, dtype=np.float32).reshape(3, 4)})
    with pytest.raises(BadModelFile, match=r"thing1.npz: keypoints must be \(K, 3\).*\(3, 4\)"):
        load_cad_npz(tmp_path / "thing1.npz")


def test_model_refuses_non_finite_coordinates_and_misshapen_keypoints():
    faces = torch.tensor([[0, 1, 2]])
    v = torch.eye(3)
    with pytest.raises(ValueError, match="m: vertices hold non-finite"):
        Model("m", "m", torch.tensor([[0.0, 0, 0], [1, 0, 0], [float("nan"), 1, 0]]), faces)
    with pytest.raises(ValueError, match="m: vertices hold non-finite"):  # beyond float32
        Model("m", "m", torch.tensor([[0.0, 0, 0], [1, 0, 0], [1e300, 1, 0]], dtype=torch.float64), faces)
    with pytest.raises(ValueError, match="m: keypoints hold non-finite"):
        Model("m", "m", v, faces, ["a"], [[float("inf"), 0, 0]])
    with pytest.raises(ValueError, match=r"m: keypoints must be \(K, 3\)"):
        Model("m", "m", v, faces, list("abcd"), torch.zeros(3, 4))
    with pytest.raises(ValueError, match="m: faces must be integer"):
        Model("m", "m", v, torch.tensor([[0.0, 1.5, 2.0]]))
    assert Model("m", "m", v, torch.tensor([[0.0, 1.0, 2.0]])).faces.dtype == torch.long  # whole numbers: fine
    assert Model("m", "m", v, faces, [], []).keypoints.shape == (0, 3)


def test_a_mesh_in_any_unit_loads(tmp_path):
    """Sizes are judged relative to the mesh: a box 1e-12 or 1e12 wide, keypoints alike, is a model."""
    for name, scale in [("tiny1", 1e-12), ("huge1", 1e12)]:
        _write(tmp_path, f"{name}.ply", _scaled(scale))
        _write(tmp_path, f"{name}.json", {"class": "thing", "keypoints": {k: [scale * c for c in p]
                                                                           for k, p in KP.items()}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        models = load_models(tmp_path)
    assert [m.name for m in models] == ["huge1", "tiny1"]


def test_strict_raises_where_a_model_would_be_skipped(tmp_path):
    """The benchmarks read a fixed set of CAD models: ``strict`` makes a broken one an error (it used to be one
    before models were skipped), not a run on fewer models."""
    _write(tmp_path, "thing1.ply", BOX)
    _write(tmp_path, "thing1.json", GOOD)
    assert [m.name for m in load_models(tmp_path, strict=True)] == ["thing1"]
    _write(tmp_path, "thing2.npz", b"junk")
    with pytest.raises(ValueError, match=r"thing2\.npz"):
        load_models(tmp_path, strict=True)
    (tmp_path / "thing2.npz").unlink()
    _write(tmp_path, "thing1.obj", BOX)
    with pytest.raises(ValueError, match="share a model name"):
        load_models(tmp_path, strict=True)
