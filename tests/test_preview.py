"""``preview.png``: one row per object of the run found in its data, string annotation ids included."""
from __future__ import annotations

import json
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

from carvi_torch.io.coco import make_annotation, make_category, write_coco
from carvi_torch.io.layout import object_file
from carvi_torch.io.outputs import write_npz
from carvi_torch.preview import PREVIEW_ROW_INCHES, write_preview


def _run_folder(tmp_path, ids):
    """A run folder of class ``car`` with a voxels file per id in ``ids`` and data holding the annotations of
    ``ids`` but the last (a file of the folder that the data does not name)."""
    mask = np.zeros((40, 40), bool)
    mask[10:30, 12:28] = True
    anns = []
    for i, aid in enumerate(ids[:-1]):
        ann = make_annotation(1, i + 1, 1, mask, np.array([[15.0, 15.0], [25.0, 25.0]]), np.array([True, True]))
        anns.append({**ann, "id": aid})
    images = [{"id": i + 1, "width": 40, "height": 40, "file_name": f"{i}.png"} for i in range(len(ids))]
    data = write_coco(tmp_path / "ann.json", images, anns, [make_category(1, "car", ["left_a", "right_a"])])
    occ = np.zeros((4, 40, 40), bool)
    occ[:, 10:30, 12:28] = True
    for aid in ids:
        write_npz(object_file(tmp_path / "run" / "car", "voxels", aid), occupancy=occ,
                  voxel_to_camera=np.eye(4)[[2, 1, 0, 3]])
    return tmp_path / "run", {"data": str(data), "classes": {"car": {}}}


def test_string_ids_get_their_rows(tmp_path):
    """String ids (one that is no safe file name) are drawn, a row each; a file the data lacks is passed over."""
    out, summary = _run_folder(tmp_path, ["obj-7", "../x", "orphan"])
    assert write_preview(out, summary) is not None
    assert plt.imread(out / "preview.png").shape[0] == round(2 * PREVIEW_ROW_INCHES * 80)


def test_ids_the_run_rejects_take_no_row(tmp_path):
    """An annotation whose id the loader rejects (a boolean) is no object of the run, even where its spelling is a
    file's stem (``True``, a string id of the run)."""
    out, summary = _run_folder(tmp_path, ["True", "orphan"])
    data = json.loads(Path(summary["data"]).read_text())
    # a boolean id, first, on an image the data lacks: drawing it would fail (no image to size its mask)
    data["annotations"].insert(0, {**data["annotations"][0], "id": True, "image_id": 99})
    Path(summary["data"]).write_text(json.dumps(data))
    assert write_preview(out, summary) == out / "preview.png"
    assert plt.imread(out / "preview.png").shape[0] == round(PREVIEW_ROW_INCHES * 80)  # the string id's row alone


def test_an_id_equal_to_a_rejected_one_keeps_its_row(tmp_path):
    """A boolean id ``true`` before the integer id 1 (one key in pycocotools' index, which keeps the boolean):
    object 1 is the run's and gets its row."""
    out, summary = _run_folder(tmp_path, [1, "orphan"])
    data = json.loads(Path(summary["data"]).read_text())
    data["annotations"].insert(0, {**data["annotations"][0], "id": True, "image_id": 99})
    Path(summary["data"]).write_text(json.dumps(data))
    assert write_preview(out, summary) == out / "preview.png"
    assert plt.imread(out / "preview.png").shape[0] == round(PREVIEW_ROW_INCHES * 80)


def test_nothing_drawn_without_objects_in_the_data(tmp_path):
    """No voxels file of the run names an annotation of its data: no preview."""
    out, summary = _run_folder(tmp_path, ["only-in-the-folder"])
    assert write_preview(out, summary) is None and not (out / "preview.png").exists()
