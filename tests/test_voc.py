"""Tests of carvi_torch.io.voc (Berkeley keypoints + SBD / VOC masks -> COCO keypoint JSON).

Hand-made fixtures live in tests/data/voc: keypoints/ (one file per branch, described in
FIXTURES below) and annotations/ (a VOC record). SBD ``.mat`` and VOC PNG masks are written
by the tests themselves. Coordinates in the fixture files are 1-based, as in the Berkeley
release; the converter's output is 0-based (file value - 1).
"""
from __future__ import annotations

import argparse
import itertools
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from carvi_torch.io.coco import MAX_IMAGE_PIXELS
from carvi_torch.io.voc import (
    InstanceMapTooLarge,
    VocFormatError,
    box_iou,
    category_entry,
    convert,
    encode_rle,
    find_mask_file,
    infer_flip_pairs,
    mask_boxes,
    match_instances,
    name_words,
    parse_keypoint_xml,
    parse_voc_record,
    rasterize_polygons,
    read_sbd_instances,
    read_voc_instances,
    rigid_keypoint_indices,
    run,
)
from carvi_torch.collection import keypoint_side, mirror_name
from carvi_torch.io.vocmeta import VOC_CLASSES, category_id, normalize_class_name

# pycocotools' decode trips a numpy 2 deprecation warning inside the library; not ours to fix.
pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")

DATA = Path(__file__).resolve().parent / "data" / "voc"
KP = DATA / "keypoints"

FIXTURES = {
    "valid": "2009_000010_1.xml",          # aeroplane, 4 visible + 1 not visible, rectangle polygon
    "malformed": "2009_000011_1.xml",      # mismatched tag on line 8
    "no_keypoints": "2009_000012_1.xml",   # no <keypoints> element
    "none_visible": "2009_000013_1.xml",   # empty <keypoints>
    "one_visible": "2009_000014_1.xml",    # 1 visible, 1 not visible
    "no_polygon": "2009_000015_1.xml",     # 3 visible, no polygon
    "boat": "2009_000016_1.xml",           # hull + mast + sail keypoints
    "cat": "2009_000017_1.xml",            # head/torso + limbs
    "bottle": "2009_000018_1.xml",
    "sbd_1": "2009_000020_1.xml",          # two aeroplanes of one image, no polygon
    "sbd_2": "2009_000020_2.xml",
}

# Real Berkeley names of a few classes (the voc2011_keypoints_Feb2012 name lists).
BIRD = ["Beak_Base", "Beak_Tip", "Left_Eye", "Left_Wing_Base", "Left_Wing_Tip", "Leg_Center",
        "Lower_Neck_Base", "Right_Eye", "Right_Wing_Base", "Right_Wing_Tip", "Tail_Tip", "Upper_Neck_Base"]
QUADRUPED = ["L_B_Elbow", "L_B_Paw", "L_EarBase", "L_Eye", "L_F_Elbow", "L_F_Paw", "Nose", "R_B_Elbow",
             "R_B_Paw", "R_EarBase", "R_Eye", "R_F_Elbow", "R_F_Paw", "TailBase", "Throat", "Withers"]
PERSON = ["B_Head", "HeadBack", "L_Ankle", "L_Ear", "L_Elbow", "L_Eye", "L_Foot", "L_Hip", "L_Knee",
          "L_Shoulder", "L_Toes", "L_Wrist", "Nose", "R_Ankle", "R_Ear", "R_Elbow", "R_Eye", "R_Foot",
          "R_Hip", "R_Knee", "R_Shoulder", "R_Toes", "R_Wrist"]
BOAT = ["Hull_Back_Bot", "Hull_Back_Top", "Hull_Front_Bot", "Hull_Front_Top", "Hull_Mid_Left_Bot",
        "Hull_Mid_Left_Top", "Hull_Mid_Right_Bot", "Hull_Mid_Right_Top", "Mast_Top", "Sail_Left", "Sail_Right"]
CHAIR = ["BackRest_Top_Left", "BackRest_Top_Right", "Leg_Left_Back", "Leg_Left_Front", "Leg_Right_Back",
         "Leg_Right_Front", "Seat_Left_Back", "Seat_Left_Front", "Seat_Right_Back", "Seat_Right_Front"]
TRAIN = ["Base_Back_Left", "Base_Back_Right", "Base_Front_Left", "Base_Front_Right", "Roof_Back_Left",
         "Roof_Back_Right", "Roof_Front_Middle"]


def keypoint_dir(tmp_path: Path, *keys: str) -> Path:
    """A folder holding copies of the named fixtures."""
    d = tmp_path / "kp"
    d.mkdir(exist_ok=True)
    for k in keys:
        shutil.copy(KP / FIXTURES[k], d / FIXTURES[k])
    return d


def load(path: Path) -> dict:
    return json.loads(Path(path).read_text())


def by_source(data: dict) -> dict:
    return {a["source"]: a for a in data["annotations"]}


def keypoint_dict(data: dict, ann: dict) -> dict:
    """name -> (x, y, v) of an output annotation."""
    cat = next(c for c in data["categories"] if c["id"] == ann["category_id"])
    k = np.asarray(ann["keypoints"], dtype=float).reshape(-1, 3)
    return {n: tuple(row) for n, row in zip(cat["keypoints"], k)}


# --------------------------------------------------------------------------- vocmeta


def test_vocmeta_names_and_ids():
    assert len(VOC_CLASSES) == 20 and len(set(VOC_CLASSES)) == 20
    assert category_id("aeroplane") == 1 and category_id("tvmonitor") == 20 and category_id("person") == 15
    assert normalize_class_name("Potted Plant") == "pottedplant"
    assert normalize_class_name("tv/monitor") == "tvmonitor"
    assert normalize_class_name("unicorn") is None and normalize_class_name(3) is None
    with pytest.raises(ValueError, match="unicorn"):
        category_id("unicorn")


# --------------------------------------------------------------------------- parse_keypoint_xml


def test_parse_valid_file_shifts_to_zero_based():
    obj = parse_keypoint_xml(KP / FIXTURES["valid"])
    assert obj.source == "2009_000010_1.xml" and obj.image == "2009_000010" and obj.voc_id == 1
    assert obj.category == "aeroplane" and obj.subcategory == "Propeller"
    assert obj.visible_bounds == (10.0, 10.0, 40.0, 20.0)
    assert list(obj.keypoints) == ["NoseTip", "L_WingTip", "R_WingTip", "Top_Rudder", "L_Stabilizer"]
    assert obj.keypoints["NoseTip"] == (50.0, 20.0, True)
    assert obj.keypoints["Top_Rudder"] == (12.25, 14.75, True)
    assert obj.keypoints["L_Stabilizer"] == (11.0, 24.0, False)
    assert obj.num_visible == 4
    np.testing.assert_array_equal(obj.polygon, [[10, 10], [50, 10], [50, 30], [10, 30]])
    assert len(obj.polygons) == 1
    np.testing.assert_array_equal(obj.box(), [10, 10, 50, 30])
    assert obj.extent() == (50.0, 30.0)


def test_parse_one_based_false_keeps_file_values():
    obj = parse_keypoint_xml(KP / FIXTURES["valid"], one_based=False)
    assert obj.keypoints["NoseTip"] == (51.0, 21.0, True)
    assert obj.visible_bounds == (11.0, 11.0, 40.0, 20.0)


def test_parse_malformed_names_file_and_position():
    with pytest.raises(VocFormatError) as e:
        parse_keypoint_xml(KP / FIXTURES["malformed"])
    msg = str(e.value)
    assert "2009_000011_1.xml" in msg and "line 8" in msg and "column" in msg
    assert e.value.path.name == "2009_000011_1.xml"


def test_parse_missing_keypoints():
    with pytest.raises(VocFormatError, match=r"2009_000012_1\.xml: missing <keypoints>"):
        parse_keypoint_xml(KP / FIXTURES["no_keypoints"])


def test_parse_empty_keypoints_and_no_polygon():
    obj = parse_keypoint_xml(KP / FIXTURES["none_visible"])
    assert obj.keypoints == {} and obj.num_visible == 0
    obj = parse_keypoint_xml(KP / FIXTURES["no_polygon"])
    assert obj.polygon is None and obj.polygons == () and obj.num_visible == 3


GOOD = """<annotation><image>im</image><voc_id>1</voc_id><category>cat</category>
<keypoints>{kps}</keypoints>{extra}</annotation>"""


@pytest.mark.parametrize("kps, extra, problem", [
    ('<keypoint name="Nose" visible="1" x="a" y="2"/>', "", "x of keypoint 'Nose' is not a number"),
    ('<keypoint name="Nose" visible="1" y="2"/>', "", "missing x of keypoint 'Nose'"),
    ('<keypoint visible="1" x="1" y="2"/>', "", "keypoint 0 has no name"),
    ('<keypoint name="Nose" visible="1" x="1" y="2"/><keypoint name="Nose" visible="1" x="1" y="2"/>', "",
     "appears twice"),
    ('<keypoint name="Nose" visible="1" x="nan" y="2"/>', "", "not finite"),
    ("", '<polylinesegments><segment name="foreground" x="1 2 3" y="1 2"/></polylinesegments>',
     "3 x and 2 y"),
    ("", '<polylinesegments><segment name="foreground" x="1 2" y="1 2"/></polylinesegments>',
     "at least 3"),
    ("", '<visible_bounds xmin="1" ymin="1" width="3"/>', "missing visible_bounds height"),
])
def test_parse_bad_fields(tmp_path, kps, extra, problem):
    p = tmp_path / "bad.xml"
    p.write_text(GOOD.format(kps=kps, extra=extra))
    with pytest.raises(VocFormatError, match=re.escape(problem)) as e:
        parse_keypoint_xml(p)
    assert "bad.xml" in str(e.value)


@pytest.mark.parametrize("text, problem", [
    ("<annotation><voc_id>1</voc_id><category>cat</category><keypoints/></annotation>", "missing <image>"),
    ("<annotation><image>a</image><voc_id>x</voc_id><category>cat</category><keypoints/></annotation>",
     "<voc_id> is not an integer"),
    ("<annotation><image>a</image><voc_id>1</voc_id><keypoints/></annotation>", "missing <category>"),
    ("<record><image>a</image></record>", "expected <annotation>"),
    ("", "malformed XML at line 1"),
])
def test_parse_missing_fields(tmp_path, text, problem):
    p = tmp_path / "f.xml"
    p.write_text(text)
    with pytest.raises(VocFormatError, match=re.escape(problem)):
        parse_keypoint_xml(p)


def test_parse_missing_file(tmp_path):
    with pytest.raises(VocFormatError, match="cannot read"):
        parse_keypoint_xml(tmp_path / "absent.xml")


def test_parse_voc_record():
    rec = parse_voc_record(DATA / "annotations" / "2009_000010.xml")
    assert (rec.width, rec.height) == (64, 48)
    assert rec.objects == ({"name": "aeroplane", "truncated": True, "occluded": False, "difficult": False},)


def test_parse_voc_record_without_size(tmp_path):
    p = tmp_path / "r.xml"
    p.write_text("<annotation><object><name>cat</name></object></annotation>")
    with pytest.raises(VocFormatError, match="missing <size>"):
        parse_voc_record(p)


@pytest.mark.parametrize("edit, problem", [
    (("<width>64</width>", "<width>1e12</width>"), "more than 200000000 pixels"),
    (("<truncated>1</truncated>", "<truncated>inf</truncated>"), "<truncated> is not 0/1"),
])
def test_parse_voc_record_refuses_sizes_beyond_memory_and_infinite_flags(tmp_path, edit, problem):
    """A size no mask of it could fit in memory, and a flag of ``inf`` (``int(inf)`` overflows): a VocFormatError
    naming the file (the converter warns and takes the size from elsewhere), never MemoryError or OverflowError."""
    p = tmp_path / "2009_000010.xml"
    p.write_text((DATA / "annotations" / "2009_000010.xml").read_text().replace(*edit))
    with pytest.raises(VocFormatError, match=re.escape(problem)) as err:
        parse_voc_record(p)
    assert str(p) in str(err.value)


def _edited_fixture(tmp_path: Path, old: str, new: str) -> Path:
    """The valid fixture with ``old`` replaced by ``new``, alone in a keypoint folder."""
    d = keypoint_dir(tmp_path, "valid")
    f = d / FIXTURES["valid"]
    text = f.read_text()
    assert old in text
    f.write_text(text.replace(old, new))
    return d


def test_convert_drops_a_keypoint_far_off_its_object_with_a_warning(tmp_path):
    """A mistyped coordinate (x 200001 for 51) would stretch the image size taken from the objects' extent and so
    look inside it; it is not visible, named in a warning, and the size is the one without it."""
    d = _edited_fixture(tmp_path, 'x="51.00" y="21.00"', 'x="200001.00" y="21.00"')
    report = convert(d, tmp_path / "out.json")
    data = load(tmp_path / "out.json")
    assert (data["images"][0]["width"], data["images"][0]["height"]) == (51, 31)
    assert keypoint_dict(data, data["annotations"][0])["NoseTip"] == (0, 0, 0)
    assert any(w.startswith(f"{FIXTURES['valid']}: keypoint(s) NoseTip lie far outside") for w in report.warnings)


def test_far_keypoints_band_is_the_outline_widened_by_half_its_larger_side():
    """The outline (a 10 x 6 polygon and ``visible_bounds`` inside it) widened by 5 each side, edges included: a
    visible keypoint on the edge stays, one a float step beyond, or NaN, is far; a hidden one never is, and
    without an outline nothing is."""
    from carvi_torch.io.voc import VocObject, far_keypoints
    poly = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 6.0], [0.0, 6.0]])
    kps = {"w": (-5.0, 3.0, True), "e": (15.0, 3.0, True), "n": (4.0, -5.0, True), "s": (4.0, 11.0, True),
           "w+": (np.nextafter(-5.0, -6.0), 3.0, True), "s+": (4.0, np.nextafter(11.0, 12.0), True),
           "nan": (float("nan"), 3.0, True), "hidden": (1e9, 3.0, False)}
    obj = VocObject("a.xml", "a", 1, "car", None, (1.0, 1.0, 2.0, 2.0), kps, poly, (poly,))
    assert far_keypoints(obj) == ("w+", "s+", "nan")
    assert far_keypoints(obj, tolerance=0.0) == ("w", "e", "n", "s", "w+", "s+", "nan")
    assert far_keypoints(VocObject("a.xml", "a", 1, "car", None, None, kps, None, ())) == ()
    assert far_keypoints(VocObject("a.xml", "a", 1, "car", None, None, {}, poly, (poly,))) == ()


def test_convert_skips_an_object_whose_extent_is_no_image_size(tmp_path):
    """A polygon vertex at 1e12 and no VOC record: the image size from the extent would be 1e12 pixels wide (a mask
    of terabytes); the object is skipped with the reason, nothing is allocated."""
    d = _edited_fixture(tmp_path, 'x="11.00 51.00 51.00 11.00 "', 'x="11.00 1e12 51.00 11.00 "')
    report = convert(d, tmp_path / "out.json")
    assert not report.written and report.counts == {}
    ((name, reason),) = report.skipped
    assert name == FIXTURES["valid"] and reason.startswith("no image size: no VOC record or instance map")


# --------------------------------------------------------------------------- names


def test_name_words():
    assert name_words("L_EarBase") == ["l", "ear", "base"]
    assert name_words("Bot_Rudder_Front") == ["bot", "rudder", "front"]
    assert name_words("leftEye") == ["left", "eye"]


def test_mirror_name_and_keypoint_side_follow_one_rule():
    """The Berkeley and PASCAL3D+ spellings swap (an involution), and the side a name gives is the one its swap
    leaves: one rule for the flip pairs the loader infers and the left the SfM frame takes from them."""
    cases = {"L_WingTip": "R_WingTip", "Left_Wing_Base": "Right_Wing_Base", "l_eye": "r_eye",
             "eye_left": "eye_right", "wheel_R": "wheel_L", "LEFT_EAR": "RIGHT_EAR", "leftEye": "rightEye",
             "Hull_Mid_Left_Bot": "Hull_Mid_Right_Bot", "NoseTip": "NoseTip", "Leftover": "Rightover",
             "leftcorner_windshield": "rightcorner_windshield", "Roof_Front_Middle": "Roof_Front_Middle",
             "R_F_Paw": "L_F_Paw", "mid1_left_top": "mid1_right_top", "LWing": "RWing", "L2": "R2",
             "wheel1L": "wheel1R", "XLeft": "XRight"}
    flip = {"left": "right", "right": "left", None: None}
    for name, swapped in cases.items():
        assert mirror_name(name) == swapped, name
        assert mirror_name(swapped) == name  # an involution
        assert keypoint_side(swapped) == flip[keypoint_side(name)], name
        assert (keypoint_side(name) is None) == (swapped == name), name


def test_every_real_keypoint_name_has_one_side_rule(shared_data):
    """Every keypoint name of the 73 PASCAL3D+ CAD models: its mirror swaps back (an involution), names the opposite
    side by :func:`keypoint_side`, and is a name of the same class wherever the name has a side (the flip pairs
    the loader infers are the pairs the SfM frame reads sides from)."""
    by_class: dict = {}
    for path in sorted((shared_data / "pascal3d_cad").glob("*.npz")):
        names = [str(n) for n in np.load(path)["keypoint_names"]]
        by_class.setdefault(re.sub(r"\d+$", "", path.stem), set()).update(names)
    flip = {"left": "right", "right": "left", None: None}
    sided = 0
    for cls, names in by_class.items():
        for name in names:
            mirrored = mirror_name(name)
            assert mirror_name(mirrored) == name and keypoint_side(mirrored) == flip[keypoint_side(name)], name
            if keypoint_side(name) is not None:
                sided += 1
                assert mirrored in names, (cls, name)
    assert len(by_class) == 12 and sided > 50


def _name_pairs(names, pairs):
    return {frozenset((names[i], names[j])) for i, j in pairs}


def test_infer_flip_pairs_berkeley_lists():
    assert _name_pairs(BIRD, infer_flip_pairs(BIRD)) == {
        frozenset(p) for p in [("Left_Eye", "Right_Eye"), ("Left_Wing_Base", "Right_Wing_Base"),
                               ("Left_Wing_Tip", "Right_Wing_Tip")]}
    assert _name_pairs(BOAT, infer_flip_pairs(BOAT)) == {
        frozenset(p) for p in [("Hull_Mid_Left_Bot", "Hull_Mid_Right_Bot"), ("Hull_Mid_Left_Top", "Hull_Mid_Right_Top"),
                               ("Sail_Left", "Sail_Right")]}
    chair = _name_pairs(CHAIR, infer_flip_pairs(CHAIR))
    assert len(chair) == 5 and frozenset(("Leg_Left_Back", "Leg_Right_Back")) in chair
    assert _name_pairs(TRAIN, infer_flip_pairs(TRAIN)) == {
        frozenset(p) for p in [("Base_Back_Left", "Base_Back_Right"), ("Base_Front_Left", "Base_Front_Right"),
                               ("Roof_Back_Left", "Roof_Back_Right")]}
    quad = infer_flip_pairs(QUADRUPED)
    expected = {frozenset((n, "R" + n[1:])) for n in QUADRUPED if n.startswith("L_")}
    assert _name_pairs(QUADRUPED, quad) == expected


def test_infer_flip_pairs_structure():
    pairs = infer_flip_pairs(PERSON)
    flat = [i for p in pairs for i in p]
    assert len(flat) == len(set(flat))  # each index at most once
    assert all(i < j for i, j in pairs) and pairs == sorted(pairs)
    assert len(pairs) == 10
    assert infer_flip_pairs([]) == [] and infer_flip_pairs(["NoseTip", "L_Eye"]) == []


def test_infer_flip_pairs_real_aeroplane_names(shared_data):
    kdir = shared_data / "pascal_voc_aeroplane" / "keypoints"
    names = sorted({n for p in kdir.glob("*.xml") for n in re.findall(r'<keypoint name="([^"]+)"', p.read_text())})
    assert _name_pairs(names, infer_flip_pairs(names)) == {
        frozenset(p) for p in [("L_WingTip", "R_WingTip"), ("Left_Wing_Base", "Right_Wing_Base"),
                               ("L_Stabilizer", "R_Stabilizer"), ("Left_Engine_Front", "Right_Engine_Front"),
                               ("Left_Engine_Back", "Right_Engine_Back")]}


def _rigid_names(cls, names):
    return {names[i] for i in rigid_keypoint_indices(cls, names)}


def test_rigid_keypoints_animals_boat_person():
    assert _rigid_names("cat", QUADRUPED) == {"L_EarBase", "L_Eye", "Nose", "R_EarBase", "R_Eye", "TailBase",
                                              "Throat", "Withers"}
    for cls in ("cow", "dog", "horse", "sheep"):
        assert _rigid_names(cls, QUADRUPED) == _rigid_names("cat", QUADRUPED)
    assert _rigid_names("bird", BIRD) == {"Beak_Base", "Beak_Tip", "Left_Eye", "Right_Eye", "Lower_Neck_Base",
                                          "Upper_Neck_Base"}
    assert _rigid_names("boat", BOAT) == {n for n in BOAT if n.startswith("Hull_")}
    assert _rigid_names("person", PERSON) == {"B_Head", "HeadBack", "L_Ear", "R_Ear", "L_Eye", "R_Eye", "Nose",
                                              "L_Shoulder", "R_Shoulder", "L_Hip", "R_Hip"}
    assert rigid_keypoint_indices("chair", CHAIR) == list(range(len(CHAIR)))


def test_rigid_keypoints_fallback_to_all():
    names = ["L_F_Paw", "R_F_Paw", "Nose", "L_Eye"]  # only 2 head names: too few for a rigid shape
    assert rigid_keypoint_indices("dog", names) == [0, 1, 2, 3]
    assert rigid_keypoint_indices("unicorn", names) == [0, 1, 2, 3]


def test_category_entry():
    c = category_entry("Boat", BOAT)
    assert c["id"] == 4 and c["name"] == "boat" and c["supercategory"] == "vehicle"
    assert c["keypoints"] == BOAT and c["skeleton"] == []
    assert c["symmetry"] == "none" and c["articulated"] is False
    assert c["rigid_keypoints"] == list(range(8))
    for cls in ("bottle", "diningtable", "pottedplant"):
        assert category_entry(cls, ["a"])["symmetry"] == "rotational"
    for cls in ("bird", "cat", "cow", "dog", "horse", "sheep", "person"):
        assert category_entry(cls, ["a"])["articulated"] is True
    with pytest.raises(ValueError, match="not a PASCAL VOC class"):
        category_entry("unicorn", ["a"])


# --------------------------------------------------------------------------- masks, boxes, matching


def test_rasterize_matches_matplotlib_pixel_centres():
    from matplotlib.path import Path as MplPath

    rng = np.random.default_rng(0)
    h, w = 40, 50
    yy, xx = np.mgrid[0:h, 0:w]
    centres = np.stack([xx.ravel(), yy.ravel()], 1).astype(float)
    for _ in range(5):
        # a random star-shaped (simple) polygon, reaching outside the image at times
        ang = np.sort(rng.uniform(0, 2 * np.pi, 12))
        rad = rng.uniform(5, 25, 12)
        c = rng.uniform(5, 45, 2)
        poly = c + np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1) + 0.123
        ref = MplPath(poly).contains_points(centres).reshape(h, w)
        np.testing.assert_array_equal(rasterize_polygons([poly], h, w), ref)


def test_rasterize_boundary_clipping_union_and_even_odd():
    sq = np.array([[1, 1], [3, 1], [3, 2], [1, 2]], float)  # centres on the boundary count
    m = rasterize_polygons([sq], 4, 5)
    expected = np.zeros((4, 5), bool)
    expected[1:3, 1:4] = True
    np.testing.assert_array_equal(m, expected)
    # clipped at the border, and a second polygon united
    big = np.array([[-5, -5], [2, -5], [2, 10], [-5, 10]], float)
    m = rasterize_polygons([sq, big], 4, 5)
    expected[:, :3] = True
    np.testing.assert_array_equal(m, expected)
    assert not rasterize_polygons([sq + 100], 4, 5).any()
    # pentagram: the centre has winding number 2, outside under the even-odd rule
    ang = np.pi / 2 + np.arange(5) * 4 * np.pi / 5
    star = np.stack([20 + 15 * np.cos(ang), 20 + 15 * np.sin(ang)], 1) + 0.3
    m = rasterize_polygons([star], 41, 41)
    assert not m[20, 20] and m[round(20 + 0.3 + 11 * np.sin(np.pi / 2)), 20]
    with pytest.raises(ValueError, match="polygons"):
        rasterize_polygons([np.zeros((2, 2))], 4, 5)
    with pytest.raises(ValueError, match="height, width"):
        rasterize_polygons([sq], 0, 5)


def test_rasterize_area_matches_shapely():
    import shapely

    rng = np.random.default_rng(1)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 30))
    rad = rng.uniform(60, 120, 30)
    poly = 150 + np.stack([rad * np.cos(ang), rad * np.sin(ang)], 1)
    area = shapely.Polygon(poly).area
    assert abs(rasterize_polygons([poly], 300, 300).sum() - area) / area < 0.01


def test_mask_boxes_vs_loop():
    rng = np.random.default_rng(2)
    masks = rng.random((6, 9, 11)) > 0.93
    masks[3] = False
    boxes = mask_boxes(masks)
    for b, m in zip(boxes, masks):
        ys, xs = np.nonzero(m)
        if len(xs) == 0:
            assert np.isnan(b).all()
        else:
            np.testing.assert_array_equal(b, [xs.min(), ys.min(), xs.max(), ys.max()])
    with pytest.raises(ValueError, match="masks"):
        mask_boxes(np.zeros((3, 3), bool))


def test_box_iou_vs_pixel_sets():
    rng = np.random.default_rng(3)

    def random_boxes(n):
        xs, ys = np.sort(rng.integers(0, 12, (n, 2)), 1), np.sort(rng.integers(0, 12, (n, 2)), 1)
        return np.stack([xs[:, 0], ys[:, 0], xs[:, 1], ys[:, 1]], 1)

    a, b = random_boxes(5), random_boxes(4)

    def pixels(box):
        x0, y0, x1, y1 = box
        return {(x, y) for x in range(x0, x1 + 1) for y in range(y0, y1 + 1)}

    iou = box_iou(a, b)
    for i, j in itertools.product(range(5), range(4)):
        pa, pb = pixels(a[i]), pixels(b[j])
        np.testing.assert_allclose(iou[i, j], len(pa & pb) / len(pa | pb), atol=1e-12)
    nan = box_iou(np.full((1, 4), np.nan), b)
    assert (nan == 0).all()


def test_match_instances_vs_brute_force():
    rng = np.random.default_rng(4)
    for _ in range(20):
        na, nb = int(rng.integers(0, 4)), int(rng.integers(0, 4))
        a = np.concatenate([rng.uniform(0, 20, (na, 2)), rng.uniform(20, 40, (na, 2))], 1)
        b = a[rng.integers(0, max(na, 1), nb)] + rng.normal(0, 3, (nb, 4)) if na else rng.uniform(0, 40, (nb, 4))
        ca, cb = rng.integers(0, 3, na), rng.integers(0, 3, nb)
        got = match_instances(a, ca, b, cb, min_iou=0.3)
        iou = box_iou(a, b)
        ok = ((ca[:, None] == 0) | (cb[None] == 0) | (ca[:, None] == cb[None])) & (iou >= 0.3)
        best = 0.0  # best total over every partial one-to-one assignment of valid pairs
        for perm in itertools.permutations(list(range(nb)) + [-1] * na, na):
            if all(j < 0 or ok[i, j] for i, j in enumerate(perm)):
                best = max(best, sum(iou[i, j] for i, j in enumerate(perm) if j >= 0))
        used = [j for j in got if j >= 0]
        assert len(used) == len(set(used))
        assert all(ok[i, j] for i, j in enumerate(got) if j >= 0)
        np.testing.assert_allclose(sum(iou[i, j] for i, j in enumerate(got) if j >= 0), best, atol=1e-9)


def test_match_instances_class_consistency_and_errors():
    obj = np.array([[0, 0, 10, 10]], float)
    inst = np.array([[0, 0, 10, 10], [0, 0, 9, 10]], float)
    assert match_instances(obj, [1], inst, [15, 1]).tolist() == [1]  # the person box is exact, but wrong class
    assert match_instances(obj, [1], inst, [0, 1]).tolist() == [0]  # unknown class is compatible
    assert match_instances(obj, [1], inst[:1], [15]).tolist() == [-1]
    assert match_instances(obj, [1], inst[:, :4] + 8, [1, 1], min_iou=0.5).tolist() == [-1]
    assert match_instances(obj, [1], np.zeros((0, 4)), []).tolist() == [-1]
    with pytest.raises(ValueError, match="object_classes"):
        match_instances(obj, [1, 2], inst, [1, 1])


def test_encode_rle_round_trip():
    from pycocotools import mask as mask_utils

    m = np.zeros((7, 9), bool)
    m[2:5, 3:8] = True
    m[6, 0] = True
    rle = encode_rle(m)
    assert isinstance(rle["counts"], str) and rle["size"] == [7, 9]
    json.dumps(rle)
    np.testing.assert_array_equal(mask_utils.decode(rle).astype(bool), m)


# --------------------------------------------------------------------------- instance files


def sbd_map() -> tuple[np.ndarray, np.ndarray]:
    """A 48x64 SBD-like instance map for image 2009_000020 and its categories.

    Instance 1 (person) covers exactly the box of object 1, instance 3 (aeroplane)
    most of it; instance 2 (aeroplane) lies on object 2.
    """
    seg = np.zeros((48, 64), np.uint8)
    seg[2:13, 2:23] = 1       # box [2, 2, 22, 12]: IoU 1 with object 1, but a person
    seg[3:13, 2:21] = 3       # aeroplane: IoU 190/231 with object 1
    seg[20:36, 30:56] = 2     # aeroplane on object 2 (box [30, 20, 55, 35])
    seg[25:28, 40:45] = 0     # a hole, so the mask is not just its box
    return seg, np.array([[15], [1], [1]], np.uint8)


def write_sbd(root: Path, image: str, seg: np.ndarray, cats: np.ndarray) -> Path:
    from scipy.io import savemat

    (root / "inst").mkdir(parents=True, exist_ok=True)
    p = root / "inst" / f"{image}.mat"
    savemat(p, {"GTinst": {"Segmentation": seg, "Categories": cats, "Boundaries": np.zeros((len(cats), 1))}})
    return p


def write_png(path: Path, arr: np.ndarray) -> Path:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    im = Image.fromarray(arr.astype(np.uint8), mode="P")
    im.putpalette([v for i in range(256) for v in ((i * 37) % 256, (i * 91) % 256, (i * 53) % 256)])
    im.save(path)
    return path


def voc_object_map() -> np.ndarray:
    """A 48x64 SegmentationObject map for image 2009_000020, 255 rings round the instances."""
    seg = np.zeros((48, 64), np.uint8)
    seg[19:37, 29:57] = 255
    seg[20:36, 30:56] = 1     # on object 2
    seg[1:14, 1:24] = 255
    seg[2:13, 2:23] = 2       # on object 1
    return seg


def test_read_sbd_instances(tmp_path):
    seg, cats = sbd_map()
    inst = read_sbd_instances(write_sbd(tmp_path, "2009_000020", seg, cats))
    assert inst.source == "sbd" and inst.shape == (48, 64)
    assert inst.ids.tolist() == [1, 2, 3] and inst.categories.tolist() == [15, 1, 1]
    masks = np.stack([inst.mask(j) for j in range(len(inst.ids))])
    for k, m in zip(inst.ids, masks):
        np.testing.assert_array_equal(m, seg == k)
    np.testing.assert_array_equal(inst.boxes, mask_boxes(masks))


def test_read_sbd_single_instance_and_errors(tmp_path):
    from scipy.io import savemat

    seg = np.zeros((5, 6), np.uint8)
    seg[1:3, 1:4] = 1
    inst = read_sbd_instances(write_sbd(tmp_path, "one", seg, np.array([[8]], np.uint8)))
    assert inst.categories.tolist() == [8] and inst.mask(0).sum() == 6
    savemat(tmp_path / "x.mat", {"other": np.zeros(3)})
    with pytest.raises(VocFormatError, match="no GTinst"):
        read_sbd_instances(tmp_path / "x.mat")
    (tmp_path / "y.mat").write_bytes(b"not a mat file")
    with pytest.raises(VocFormatError, match="y.mat"):
        read_sbd_instances(tmp_path / "y.mat")


def test_read_voc_instances_and_classes(tmp_path):
    seg = voc_object_map()
    p = write_png(tmp_path / "SegmentationObject" / "a.png", seg)
    inst = read_voc_instances(p)
    assert inst.source == "voc" and inst.ids.tolist() == [1, 2] and inst.categories.tolist() == [0, 0]
    masks = np.stack([inst.mask(j) for j in range(len(inst.ids))])
    for k, m in zip(inst.ids, masks):
        np.testing.assert_array_equal(m, seg == k)
    np.testing.assert_array_equal(inst.boxes, mask_boxes(masks))
    assert not (masks.any(0) & (seg == 255)).any()
    cls = np.where(seg == 1, 1, np.where(seg == 2, 15, np.where(seg == 255, 255, 0)))
    cls[20, 30] = 7  # a stray pixel does not outvote the rest
    c = write_png(tmp_path / "SegmentationClass" / "a.png", cls)
    assert read_voc_instances(p, c).categories.tolist() == [1, 15]
    assert find_mask_file(tmp_path, "a") == (p, c)
    assert find_mask_file(tmp_path, "b") is None
    from PIL import Image

    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tmp_path / "rgb.png")
    with pytest.raises(VocFormatError, match="RGB"):
        read_voc_instances(tmp_path / "rgb.png")


# --------------------------------------------------------------------------- convert


def test_convert_fixture_folder_accounts_for_every_file(tmp_path):
    kdir = keypoint_dir(tmp_path, *FIXTURES)
    out = tmp_path / "out.json"
    report = convert(kdir, out)
    data = load(out)
    reasons = dict(report.skipped)
    converted = set(by_source(data))
    assert converted | set(reasons) == set(FIXTURES.values()) and not converted & set(reasons)
    assert converted == {FIXTURES[k] for k in ("valid", "boat", "cat", "bottle")}
    assert reasons[FIXTURES["malformed"]].startswith("malformed file: malformed XML at line 8")
    assert reasons[FIXTURES["no_keypoints"]] == "malformed file: missing <keypoints>"
    assert reasons[FIXTURES["none_visible"]] == "too few visible keypoints: 0 visible, needs 2"
    assert reasons[FIXTURES["one_visible"]] == "too few visible keypoints: 1 visible, needs 2"
    for k in ("no_polygon", "sbd_1", "sbd_2"):
        assert reasons[FIXTURES[k]] == "no mask: no foreground polygon"
    assert report.counts == {"aeroplane": 1, "boat": 1, "bottle": 1, "cat": 1} and report.converted == 4
    assert report.num_files == len(FIXTURES) and report.num_images == 4
    assert data["carvi_skipped"] == [{"file": f, "reason": r} for f, r in sorted(reasons.items())]
    assert [c["id"] for c in data["categories"]] == [1, 4, 5, 8]


def test_convert_valid_object_fields(tmp_path):
    from pycocotools.coco import COCO

    out = tmp_path / "out.json"
    convert(keypoint_dir(tmp_path, "valid"), out)
    data = load(out)
    (img,) = data["images"]
    assert img == {"id": 1, "file_name": "2009_000010.jpg", "width": 51, "height": 31}  # ceil(max) + 1
    (cat,) = data["categories"]
    assert cat["keypoints"] == sorted(["NoseTip", "L_WingTip", "R_WingTip", "Top_Rudder", "L_Stabilizer"])
    assert _name_pairs(cat["keypoints"], cat["flip_pairs"]) == {frozenset(("L_WingTip", "R_WingTip"))}
    assert cat["rigid_keypoints"] == list(range(5)) and cat["symmetry"] == "none" and not cat["articulated"]
    (ann,) = data["annotations"]
    kp = keypoint_dict(data, ann)
    assert kp["NoseTip"] == (50.0, 20.0, 2) and kp["Top_Rudder"] == (12.25, 14.75, 2)
    assert kp["L_Stabilizer"] == (0, 0, 0)  # not visible
    assert ann["num_keypoints"] == 4 and ann["iscrowd"] == 0
    assert ann["source"] == "2009_000010_1.xml" and ann["voc_id"] == 1 and ann["object_id"] == 1
    assert ann["occluded"] is False and ann["truncated"] is False and ann["mask_source"] == "polygon"
    m = COCO(str(out)).annToMask(ann).astype(bool)
    expected = np.zeros((31, 51), bool)
    expected[10:31, 10:51] = True
    np.testing.assert_array_equal(m, expected)
    assert ann["area"] == 41 * 21 and ann["bbox"] == [10.0, 10.0, 41.0, 21.0]


def test_convert_size_and_flags_from_voc_record(tmp_path):
    from pycocotools.coco import COCO

    out = tmp_path / "out.json"
    convert(keypoint_dir(tmp_path, "valid"), out, annotations_dir=DATA / "annotations")
    data = load(out)
    assert (data["images"][0]["width"], data["images"][0]["height"]) == (64, 48)
    ann = data["annotations"][0]
    assert ann["truncated"] is True and ann["occluded"] is False
    assert COCO(str(out)).annToMask(ann).shape == (48, 64)


def test_convert_other_classes(tmp_path):
    out = tmp_path / "out.json"
    convert(keypoint_dir(tmp_path, "boat", "cat", "bottle"), out)
    cats = {c["name"]: c for c in load(out)["categories"]}
    boat, cat, bottle = cats["boat"], cats["cat"], cats["bottle"]
    assert {boat["keypoints"][i] for i in boat["rigid_keypoints"]} == {
        "Hull_Back_Bot", "Hull_Back_Top", "Hull_Front_Bot", "Hull_Front_Top", "Hull_Mid_Left_Top", "Hull_Mid_Right_Top"}
    assert not boat["articulated"] and boat["symmetry"] == "none"
    assert _name_pairs(boat["keypoints"], boat["flip_pairs"]) == {
        frozenset(("Hull_Mid_Left_Top", "Hull_Mid_Right_Top")), frozenset(("Sail_Left", "Sail_Right"))}
    assert cat["articulated"] and cat["symmetry"] == "none" and cat["supercategory"] == "animal"
    assert {cat["keypoints"][i] for i in cat["rigid_keypoints"]} == {
        "L_EarBase", "L_Eye", "Nose", "R_EarBase", "R_Eye", "TailBase", "Throat", "Withers"}
    assert bottle["symmetry"] == "rotational" and not bottle["articulated"]
    assert bottle["rigid_keypoints"] == list(range(6)) and len(bottle["flip_pairs"]) == 3


def test_convert_with_sbd_masks(tmp_path):
    from pycocotools.coco import COCO

    seg, cats = sbd_map()
    masks = tmp_path / "sbd"
    write_sbd(masks, "2009_000020", seg, cats)
    out = tmp_path / "out.json"
    report = convert(keypoint_dir(tmp_path, "sbd_1", "sbd_2", "valid"), out, masks_dir=masks)
    assert report.skipped == [] and report.mask_sources == {"polygon": 1, "sbd": 2}
    data = load(out)
    coco = COCO(str(out))
    anns = by_source(data)
    a1, a2 = anns["2009_000020_1.xml"], anns["2009_000020_2.xml"]
    np.testing.assert_array_equal(coco.annToMask(a1).astype(bool), seg == 3)  # not the person (1)
    np.testing.assert_array_equal(coco.annToMask(a2).astype(bool), seg == 2)
    assert a1["mask_source"] == "sbd" and a1["image_id"] == a2["image_id"]
    assert a1["object_id"] != a2["object_id"]
    img = next(i for i in data["images"] if i["id"] == a1["image_id"])
    assert (img["width"], img["height"]) == (64, 48)  # size from the instance map
    assert anns["2009_000010_1.xml"]["mask_source"] == "polygon"  # no instance file for its image


def test_convert_sbd_without_a_match_reports_no_mask(tmp_path):
    seg, cats = sbd_map()
    seg[seg == 2] = 0  # object 2 has no instance any more
    masks = tmp_path / "sbd"
    write_sbd(masks, "2009_000020", seg, cats)
    report = convert(keypoint_dir(tmp_path, "sbd_1", "sbd_2"), tmp_path / "o.json", masks_dir=masks)
    assert report.skipped == [("2009_000020_2.xml", "no mask: no foreground polygon and no matching instance mask")]


def test_convert_with_voc_png_masks(tmp_path):
    from pycocotools.coco import COCO

    seg = voc_object_map()
    root = tmp_path / "VOC2012"
    write_png(root / "SegmentationObject" / "2009_000020.png", seg)
    out = tmp_path / "out.json"
    report = convert(keypoint_dir(tmp_path, "sbd_1", "sbd_2"), out, masks_dir=root)
    assert report.skipped == [] and report.mask_sources == {"voc": 2}
    coco = COCO(str(out))
    anns = by_source(load(out))
    np.testing.assert_array_equal(coco.annToMask(anns["2009_000020_1.xml"]).astype(bool), seg == 2)
    np.testing.assert_array_equal(coco.annToMask(anns["2009_000020_2.xml"]).astype(bool), seg == 1)
    # with a class map saying instance 2 is a person, object 1 (an aeroplane) gets no mask
    cls = np.where(seg == 1, 1, np.where(seg == 2, 15, 0))
    write_png(root / "SegmentationClass" / "2009_000020.png", cls)
    report = convert(keypoint_dir(tmp_path, "sbd_1", "sbd_2"), out, masks_dir=root)
    assert [f for f, _ in report.skipped] == ["2009_000020_1.xml"] and report.converted == 1


def test_convert_mask_size_mismatch_falls_back_to_polygon(tmp_path):
    masks = tmp_path / "sbd"
    write_sbd(masks, "2009_000010", np.ones((10, 10), np.uint8), np.array([[1]], np.uint8))
    report = convert(keypoint_dir(tmp_path, "valid"), tmp_path / "o.json", masks_dir=masks,
                     annotations_dir=DATA / "annotations")
    assert report.mask_sources == {"polygon": 1} and len(report.warnings) == 2
    assert "10x10" in report.warnings[0] and "64x48" in report.warnings[0]
    assert report.warnings[1].startswith(f"no instance mask under {masks} matched an object")


def test_convert_classes_filter_and_errors(tmp_path):
    kdir = keypoint_dir(tmp_path, "valid", "cat", "boat")
    report = convert(kdir, tmp_path / "o.json", classes=["cat"])
    assert report.counts == {"cat": 1} and report.excluded == {"aeroplane": 1, "boat": 1}
    assert convert(kdir, tmp_path / "o.json", classes="cat,boat").counts == {"boat": 1, "cat": 1}
    with pytest.raises(ValueError, match="unicorn"):
        convert(kdir, tmp_path / "o.json", classes=["unicorn"])
    with pytest.raises(FileNotFoundError, match="keypoint_dir"):
        convert(tmp_path / "absent", tmp_path / "o.json")
    with pytest.raises(FileNotFoundError, match="masks_dir"):
        convert(kdir, tmp_path / "o.json", masks_dir=tmp_path / "absent")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match="no .xml files"):
        convert(tmp_path / "empty", tmp_path / "o.json")


def test_convert_unknown_category_and_deterministic(tmp_path):
    kdir = keypoint_dir(tmp_path, "valid", "cat")
    (kdir / "x_1.xml").write_text((KP / FIXTURES["valid"]).read_text().replace("aeroplane", "unicorn"))
    out1, out2 = tmp_path / "a.json", tmp_path / "b.json"
    report = convert(kdir, out1)
    assert dict(report.skipped)["x_1.xml"].startswith("unknown category: 'unicorn'")
    convert(kdir, out2)
    assert out1.read_bytes() == out2.read_bytes()


def test_run_prints_summary_and_writes_skipped(tmp_path, capsys):
    kdir = keypoint_dir(tmp_path, "valid", "malformed", "one_visible")
    out = tmp_path / "ann.json"
    args = argparse.Namespace(keypoints=str(kdir), masks=None, out=str(out))  # no .annotations attribute
    assert run(args) == 0
    text = capsys.readouterr().out
    assert "converted 1 objects" in text and "skipped 2" in text
    assert "2009_000011_1.xml" in text and "2009_000014_1.xml" in text
    data = load(out)
    assert [s["file"] for s in data["carvi_skipped"]] == ["2009_000011_1.xml", "2009_000014_1.xml"]


def test_run_exit_codes(tmp_path, capsys):
    kdir = keypoint_dir(tmp_path, "malformed")
    assert run(argparse.Namespace(keypoints=str(kdir), masks=None, out=str(tmp_path / "o.json"))) == 1
    assert not (tmp_path / "o.json").exists()  # nothing converted: nothing written
    first = capsys.readouterr()
    assert "nothing written" in first.out and "no object was converted" in first.err
    assert run(argparse.Namespace(keypoints=str(tmp_path / "absent"), masks=None, out=str(tmp_path / "o.json"))) == 2
    assert run(argparse.Namespace(out="x.json")) == 2
    err = capsys.readouterr().err
    assert f"--keypoints: {tmp_path / 'absent'} is not" in err
    assert "keypoint_dir" not in err  # the options, not convert()'s argument names


def test_run_names_the_options_and_writes_nothing_without_objects(tmp_path, capsys):
    kdir, out = keypoint_dir(tmp_path, "valid"), tmp_path / "o.json"
    # a VOC class no file has is a user error (exit 2, as procedural's unknown class), naming the files' classes
    assert run(argparse.Namespace(keypoints=str(kdir), out=str(out), classes="cat")) == 2
    assert capsys.readouterr().err == (f"error: voc: --classes: no object of cat in the .xml files of {kdir} "
                                       "(their classes: aeroplane)\n")
    assert run(argparse.Namespace(keypoints=str(kdir), out=str(out), masks=str(tmp_path / "no"))) == 2
    assert run(argparse.Namespace(keypoints=str(kdir), out=str(out), classes="unicorn")) == 2
    (tmp_path / "empty").mkdir()
    assert run(argparse.Namespace(keypoints=str(tmp_path / "empty"), out=str(out))) == 2
    err = capsys.readouterr().err.splitlines()
    assert [line.split(":")[2].strip() for line in err] == ["--masks", "--classes", "--keypoints"]
    assert not out.exists()


def test_run_warns_when_no_mask_of_masks_matched(tmp_path, capsys):
    """``--masks`` given but no mask file of it matched an object: a warning says every mask is a polygon."""
    kdir, out = keypoint_dir(tmp_path, "valid"), tmp_path / "o.json"
    (tmp_path / "masks").mkdir()
    assert run(argparse.Namespace(keypoints=str(kdir), out=str(out), masks=str(tmp_path / "masks"))) == 0
    text = capsys.readouterr().out
    assert f"warning: no instance mask under {tmp_path / 'masks'} matched an object" in text
    assert run(argparse.Namespace(keypoints=str(kdir), out=str(out))) == 0  # no --masks: nothing to say
    assert "warning" not in capsys.readouterr().out


def test_unreadable_mask_files_are_reasons_but_other_errors_propagate(tmp_path, monkeypatch):
    (tmp_path / "cut.png").write_bytes(write_png(tmp_path / "a.png", voc_object_map()).read_bytes()[:60])
    with pytest.raises(VocFormatError, match="cannot read the PNG"):
        read_voc_instances(tmp_path / "cut.png")
    from PIL import Image

    def broken(*args, **kwargs):
        raise RuntimeError("not a file problem")

    monkeypatch.setattr(Image, "open", broken)
    with pytest.raises(RuntimeError):
        read_voc_instances(tmp_path / "a.png")


# --------------------------------------------------------------------------- large instance maps


def write_blank_png(path: Path, width: int, height: int) -> Path:
    """A valid all-zero palette PNG of any size, streamed: 210 million pixels take 200 KB and under a second."""
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    z, row = zlib.compressobj(9), bytes(width + 1)  # filter byte 0, then the row's indices
    idat = b"".join([z.compress(row) for _ in range(height)] + [z.flush()])
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 3, 0, 0, 0))
                     + chunk(b"PLTE", bytes(768)) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
    return path


def test_an_instance_map_over_the_pixel_limit_is_not_decoded_and_its_objects_are_skipped(tmp_path, capsys):
    """A 205 KB palette PNG of 15000 x 14000 pixels (more than MAX_IMAGE_PIXELS) and no VOC record: refused from its
    header, before a byte of it is decoded; its image has no size, so its objects are skipped with the reason (in
    the output's carvi_skipped), one warning names the image, and the other images convert."""
    import tracemalloc

    masks = tmp_path / "masks"
    big = write_blank_png(masks / "SegmentationObject" / "2009_000020.png", 15000, 14000)
    assert big.stat().st_size < 300_000
    tracemalloc.start()
    with pytest.raises(InstanceMapTooLarge, match=f"is 15000x14000 pixels, more than {MAX_IMAGE_PIXELS}") as e:
        read_voc_instances(big)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert e.value.size == (15000, 14000) and peak < 1_000_000
    out = tmp_path / "o.json"
    kdir = keypoint_dir(tmp_path, "sbd_1", "sbd_2", "valid")
    assert run(argparse.Namespace(keypoints=str(kdir), masks=str(masks), out=str(out))) == 0
    why = f"no image size: 2009_000020.png: instance map is 15000x14000 pixels, more than {MAX_IMAGE_PIXELS}"
    assert load(out)["carvi_skipped"] == [{"file": FIXTURES[k], "reason": why} for k in ("sbd_1", "sbd_2")]
    assert list(by_source(load(out))) == [FIXTURES["valid"]]
    assert [line for line in capsys.readouterr().out.splitlines() if "2009_000020:" in line] == [
        f"warning: 2009_000020: {why}"]


def test_an_sbd_map_over_the_pixel_limit_or_a_mat_file_inflating_beyond_one_is_refused(tmp_path, monkeypatch):
    """The .mat path keeps the same bound: a Segmentation of more pixels, and a file whose compressed variables
    inflate to more bytes than such a map in doubles (measured by streaming, before scipy inflates them); a
    compressed file within it reads as the uncompressed one."""
    from scipy.io import savemat

    import carvi_torch.io.voc as voc

    seg, cats = sbd_map()
    plain = write_sbd(tmp_path / "plain", "2009_000020", seg, cats)
    packed = tmp_path / "packed.mat"
    savemat(packed, {"GTinst": {"Segmentation": seg, "Categories": cats}}, do_compression=True)
    a, b = read_sbd_instances(plain), read_sbd_instances(packed)
    assert a.ids.tolist() == b.ids.tolist() == [1, 2, 3] and np.array_equal(a.boxes, b.boxes)
    monkeypatch.setattr(voc, "_MAX_MAT_BYTES", 1000)
    with pytest.raises(InstanceMapTooLarge, match="inflates to more than 1000 bytes"):
        read_sbd_instances(packed)
    assert read_sbd_instances(plain).ids.tolist() == [1, 2, 3]  # nothing to inflate
    monkeypatch.setattr(voc, "MAX_IMAGE_PIXELS", 3000)
    with pytest.raises(InstanceMapTooLarge, match="instance map is 64x48 pixels, more than 3000") as e:
        read_sbd_instances(plain)
    assert e.value.size == (64, 48)
    report = convert(keypoint_dir(tmp_path, "sbd_1", "valid"), tmp_path / "o.json", masks_dir=tmp_path / "plain")
    assert report.skipped == [(FIXTURES["sbd_1"], "no image size: 2009_000020.mat: instance map is 64x48 pixels, "
                                                  "more than 3000")]
    assert report.counts == {"aeroplane": 1} and report.warnings[0].startswith("2009_000020: no image size")
    # a VOC record giving the image's size (within the bound): the map is only unusable, and the objects fall back
    # to their polygons
    records = tmp_path / "records"
    records.mkdir()
    record = (DATA / "annotations" / "2009_000010.xml").read_text().replace("<width>64", "<width>50")
    (records / "2009_000020.xml").write_text(record.replace("<height>48", "<height>40"))
    report = convert(keypoint_dir(tmp_path, "sbd_1", "valid"), tmp_path / "o.json", masks_dir=tmp_path / "plain",
                     annotations_dir=records)
    assert report.warnings[0] == (f"{plain}: instance map is 64x48 pixels, more than 3000; using polygons for "
                                  "2009_000020")
    assert report.skipped == [(FIXTURES["sbd_1"], "no mask: no foreground polygon and no matching instance mask")]


def test_splitting_a_large_map_holds_one_instance_mask_at_a_time(tmp_path):
    """254 instances on a 2000 x 2000 map: reading it with its class map, and making and encoding every instance's
    mask, each peak under 4 bytes per pixel of numpy and Python allocations (never an (instances, H, W) array),
    with the masks, boxes and classes of the map."""
    import tracemalloc

    from pycocotools import mask as mask_utils

    h, w = 2000, 2000
    seg = ((np.arange(h)[:, None] // 8 + np.arange(w)[None, :] // 250) % 254 + 1).astype(np.uint8)
    seg[:3] = 0
    seg[-3:, :] = 255
    p = write_png(tmp_path / "SegmentationObject" / "a.png", seg)
    c = write_png(tmp_path / "SegmentationClass" / "a.png", (seg % 20 + 1) * (seg < 255) + 255 * (seg == 255))
    tracemalloc.start()
    inst = read_voc_instances(p, c)
    read_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.reset_peak()
    rles = [encode_rle(inst.mask(j)) for j in range(len(inst.ids))]
    mask_peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert read_peak < 4 * h * w and mask_peak < 4 * h * w
    assert inst.ids.tolist() == list(range(1, 255)) and inst.categories.tolist() == [k % 20 + 1 for k in range(1, 255)]
    for k in (1, 77, 254):
        m = seg == k
        np.testing.assert_array_equal(mask_utils.decode(rles[k - 1]).astype(bool), m)
        np.testing.assert_array_equal(inst.boxes[k - 1], mask_boxes(m[None])[0])


def test_a_map_of_too_many_instance_values_a_class_map_of_another_size_and_memory_errors_are_unreadable(
        tmp_path, monkeypatch):
    import carvi_torch.io.voc as voc

    seg, cats = sbd_map()
    mat = write_sbd(tmp_path / "sbd", "2009_000020", seg, cats)
    monkeypatch.setattr(voc, "MAX_INSTANCES", 2)
    with pytest.raises(VocFormatError, match="holds more than 2 instance values: not an instance map"):
        read_sbd_instances(mat)
    monkeypatch.undo()
    p = write_png(tmp_path / "SegmentationObject" / "a.png", voc_object_map())
    c = write_blank_png(tmp_path / "SegmentationClass" / "a.png", 64, 47)
    with pytest.raises(VocFormatError, match=r"class map \(47, 64\) differs from instance map \(48, 64\)"):
        read_voc_instances(p, c)

    def claims_too_much(*args, **kwargs):
        raise MemoryError()  # what a header declaring a size beyond memory does

    monkeypatch.setattr("scipy.io.loadmat", claims_too_much)
    with pytest.raises(VocFormatError, match="cannot read the .mat file: it declares a size beyond memory"):
        read_sbd_instances(mat)


# --------------------------------------------------------------------------- real data


def test_real_aeroplanes(shared_data, tmp_path):
    import shapely
    from pycocotools.coco import COCO

    kdir = shared_data / "pascal_voc_aeroplane" / "keypoints"
    out = tmp_path / "aeroplane.json"
    report = convert(kdir, out)
    files = sorted(p.name for p in kdir.glob("*.xml"))
    data = load(out)
    anns = by_source(data)
    skipped = dict(report.skipped)
    assert set(anns) | set(skipped) == set(files) and not set(anns) & set(skipped)
    # independently of the parser: objects with fewer than 2 visible keypoints are the skipped ones
    nvis = {f: len(re.findall(r'<keypoint [^>]*visible="1"', (kdir / f).read_text())) for f in files}
    assert set(skipped) == {f for f, n in nvis.items() if n < 2}
    assert all(r.startswith("too few visible keypoints") for r in skipped.values())
    assert report.counts == {"aeroplane": len(files) - len(skipped)}

    coco = COCO(str(out))
    (cat,) = data["categories"]
    assert cat["name"] == "aeroplane" and len(cat["keypoints"]) == 16
    for f, ann in anns.items():
        text = (kdir / f).read_text()
        m = coco.annToMask(ann)
        assert m.any()
        seg = re.search(r'<segment name="foreground" x="([^"]*)" y="([^"]*)"', text)
        poly = shapely.make_valid(shapely.Polygon(np.stack([np.array(seg.group(i).split(), float) for i in (1, 2)], 1)))
        area = poly.area
        # pixel counts match the polygon area: within 3% for objects of 1000 px or more, and
        # within a quarter pixel per unit of perimeter for every object
        assert abs(m.sum() - area) <= 0.25 * poly.length, f
        if area >= 1000:
            assert abs(m.sum() - area) <= 0.03 * area, f
        # keypoints are the file values minus 1
        kp = keypoint_dict(data, ann)
        for name, x, y in re.findall(r'<keypoint name="([^"]+)" visible="1" x="([^"]+)" y="([^"]+)"', text):
            assert kp[name][:2] == pytest.approx((float(x) - 1, float(y) - 1), abs=1e-6) and kp[name][2] == 2
    nose = keypoint_dict(data, anns["2008_000037_1.xml"])["NoseTip"]
    assert nose == pytest.approx((370.44, 209.92, 2))
