"""io/coco.py: COCO keypoint JSON in and out, validation per object."""
from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from pycocotools.coco import COCO

from carvi_torch.io.coco import (CocoFormatError, decode_counts, decode_segmentation, encode_mask, load_coco,
                                 make_annotation, make_category, rle_counts, write_coco)

NAMES = ["left_wing", "right_wing", "nose", "tail"]


def _ellipse(h, w, cx, cy, rx, ry):
    yy, xx = np.mgrid[:h, :w]
    return ((xx - cx) / rx) ** 2 + ((yy - cy) / ry) ** 2 <= 1


def _dataset(tmp_path, extra_anns=(), n=4):
    images, anns = [], []
    rng = np.random.default_rng(0)
    for i in range(n):
        w, h = 160 + 10 * i, 120
        images.append({"id": i + 1, "file_name": f"im{i}.jpg", "width": w, "height": h})
        m = _ellipse(h, w, 70 + i, 60, 40, 20)
        kp = np.array([[40.0, 60], [100, 60], [70 + i, 45], [70, 75]]) + rng.normal(0, 1, (4, 2))
        vis = np.array([True, True, True, i % 2 == 0])
        anns.append(make_annotation(i + 1, i + 1, 1, m, kp, vis, object_id=100 + i, source=f"im{i}.xml"))
    anns += list(extra_anns)
    cats = [make_category(1, "plane", NAMES)]
    path = tmp_path / "ann.json"
    write_coco(path, images, anns, cats)
    return path, images, anns


class TestEncodeDecode:
    def test_round_trip_pycocotools(self, tmp_path):
        path, images, anns = _dataset(tmp_path)
        coco = COCO(str(path))
        for a in anns:
            im = images[a["image_id"] - 1]
            m = _ellipse(im["height"], im["width"], 70 + a["image_id"] - 1, 60, 40, 20)
            assert np.array_equal(coco.annToMask(coco.anns[a["id"]]).astype(bool), m)
            assert np.array_equal(decode_segmentation(a["segmentation"], im["height"], im["width"]), m)

    def test_polygon(self):
        poly = [[2.0, 2.0, 12.0, 2.0, 12.0, 8.0, 2.0, 8.0]]
        m = decode_segmentation(poly, 10, 15)
        assert m.shape == (10, 15) and 50 <= m.sum() <= 80

    def test_uncompressed_rle(self):
        m = np.zeros((4, 5), bool)
        m[1:3, 1:4] = True
        counts = []  # column-major run lengths, starting with zeros
        flat = m.flatten(order="F")
        cur, run = False, 0
        for v in flat:
            if v == cur:
                run += 1
            else:
                counts.append(run)
                cur, run = v, 1
        counts.append(run)
        assert np.array_equal(decode_segmentation({"size": [4, 5], "counts": counts}, 4, 5), m)

    def test_bad_segmentation(self):
        with pytest.raises(ValueError):
            decode_segmentation({"size": [3, 3], "counts": "x"}, 4, 5)
        with pytest.raises(ValueError):
            decode_segmentation([[1.0, 2.0]], 4, 5)

    @staticmethod
    def _runs(m: np.ndarray) -> list[int]:
        """Column-major run lengths of a mask, background first, by a loop over the pixels."""
        runs, cur, n = [], False, 0
        for v in m.flatten(order="F"):
            if v == cur:
                n += 1
            else:
                runs.append(n)
                cur, n = v, 1
        return runs + [n]

    def test_compressed_counts_are_the_run_lengths(self):
        """rle_counts against a pixel loop on random masks (empty, full, sparse, dense; runs long enough to take
        several 5-bit groups and negative differences); decode_counts is pycocotools' decode, order included."""
        from pycocotools import mask as mask_utils
        rng = np.random.default_rng(3)
        for t in range(120):
            h, w = (int(v) for v in rng.integers(1, 70, 2))
            m = rng.random((h, w)) < [0.0, 1.0, 0.02, 0.5, 0.98][t % 5]
            rle = mask_utils.encode(np.asfortranarray(m.astype(np.uint8)))
            counts = rle_counts(rle["counts"])
            assert counts.tolist() == self._runs(m)
            ref = mask_utils.decode(rle).astype(bool)
            out = decode_counts(counts, h, w)
            assert np.array_equal(out, ref) and out.flags.f_contiguous == ref.flags.f_contiguous
        big = np.zeros((1500, 2000), dtype=np.uint8, order="F")
        big[10:1400, 3:1990] = 1
        assert rle_counts(mask_utils.encode(big)["counts"]).tolist() == [10 + 3 * 1500] + [1390, 110] * 1986 + [
            1390, 100 + 10 * 1500]

    @pytest.mark.parametrize("counts, reason", [
        ("", "sum to 0, not"), ("0d", "end inside a run"), ("  ", "outside the compressed alphabet"),
        ("PPPPPPPP0", "too long"), ("1O", "negative run")])
    def test_short_or_broken_compressed_counts_are_refused(self, counts, reason):
        """pycocotools decodes counts that stop short of H x W into a mask whose rest is unset memory; such counts,
        and any other string that is not a compressed RLE, are a ValueError naming why."""
        with pytest.raises(ValueError, match=reason):
            decode_segmentation({"size": [20, 30], "counts": counts}, 20, 30)

    def test_counts_cut_after_a_run_are_refused(self):
        m = _ellipse(20, 30, 15, 10, 9, 6)
        text = encode_mask(m)["counts"]
        assert decode_segmentation({"size": [20, 30], "counts": text}, 20, 30).tolist() == m.tolist()
        cut = max(k for k in range(1, len(text) // 2) if ord(text[k - 1]) - 48 < 32)  # ends on a whole run
        with pytest.raises(ValueError, match=r"sum to \d+, not width x height = 30 x 20 = 600"):
            decode_segmentation({"size": [20, 30], "counts": text[:cut]}, 20, 30)

    def test_a_list_holding_an_rle_says_so(self):
        rle = encode_mask(np.ones((4, 5), bool))
        with pytest.raises(ValueError, match="list holding an RLE object"):
            decode_segmentation([rle], 4, 5)

    def test_a_far_polygon_vertex_is_cut_before_rasterising(self, monkeypatch):
        """pycocotools rasterises a polygon at five samples per pixel of its edges: a vertex at 1e8 costs
        gigabytes and one at 1e12 crashes the process, so what reaches it stays within the image's box."""
        from carvi_torch.io import coco
        real = coco.mask_utils.frPyObjects

        def rasterise(polys, h, w):  # checks before pycocotools sees them (a crash would take pytest along)
            pts = np.concatenate([np.reshape(p, (-1, 2)) for p in polys])
            assert pts.min() >= -50 and (pts.max(0) <= [100, 80]).all()
            return real(polys, h, w)
        monkeypatch.setattr(coco.mask_utils, "frPyObjects", rasterise)
        m = decode_segmentation([[0, 0, 1e12, 0, 1e12, 1e12], [2, 2, 8, 2, 8, 8, 2, 8]], 40, 50)
        ys, xs = np.mgrid[:40, :50]
        away = (xs > 9) | (ys > 9)  # off the small square
        assert m[away & (ys < xs - 1)].all() and not m[away & (ys > xs + 1)].any()  # the triangle: below y = x

    def test_a_polygon_vertex_at_1e12_does_not_crash_the_process(self):
        import subprocess
        import sys
        code = ("from carvi_torch.io.coco import decode_segmentation as d; "
                "print(int(d([[0, 0, 1e12, 0, 1e12, 1e12]], 30, 40).sum()))")
        done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, done.stderr[-400:]
        assert 500 < int(done.stdout) < 800  # about the 30 x 40 image's part below y = x: 30 * 40 - 30 * 30 / 2

    def test_polygons_inside_the_box_are_rasterised_as_given(self):
        from pycocotools import mask as mask_utils
        rng = np.random.default_rng(1)
        for _ in range(50):
            poly = rng.uniform([-40, -30], [80, 60], (6, 2)).ravel()  # within [-W, 2W] x [-H, 2H]
            want = mask_utils.decode(mask_utils.merge(mask_utils.frPyObjects([poly.tolist()], 30, 40))).astype(bool)
            assert np.array_equal(decode_segmentation([poly.tolist()], 30, 40), want)

    def test_a_polygon_entirely_outside_the_box_is_an_empty_mask(self):
        assert not decode_segmentation([[1e9, 1e9, 2e9, 1e9, 2e9, 2e9]], 30, 40).any()


def _shoelace(flat: np.ndarray) -> float:
    x, y = np.reshape(flat, (-1, 2)).T
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def test_a_keypoint_on_the_edge_of_the_image_band_stays_visible():
    """The band a visible keypoint may lie in is the image widened by OUTSIDE_TOLERANCE of its larger side
    (160 pixels for 320 x 240) past the pixel centres, edges included: on the edge each side the keypoint stays,
    one float step beyond it goes, with one warning naming it."""
    from carvi_torch.io.coco import OUTSIDE_TOLERANCE, _parse_keypoints
    tol = OUTSIDE_TOLERANCE * 320
    edge = np.array([[-tol, 100.0], [319 + tol, 100.0], [100.0, -tol], [100.0, 239 + tol]])
    outward = np.array([[-np.inf, 100.0], [np.inf, 100.0], [100.0, -np.inf], [100.0, np.inf]])
    for i in range(5):
        xy = edge.copy()
        if i < 4:
            xy[i] = np.nextafter(edge[i], outward[i])
        warnings = []
        kp = np.concatenate([xy, np.full((4, 1), 2.0)], axis=1).ravel().tolist()
        _, visible = _parse_keypoints({"keypoints": kp}, 4, 320, 240, warnings.append)
        assert visible.tolist() == [j != i for j in range(4)]
        assert warnings == ([] if i == 4 else [f"keypoint(s) [{i}] lie far outside the 320x240 image; "
                                               "treated as not visible"])


def test_far_outside_is_the_box_widened_by_the_tolerance():
    from carvi_torch.io.coco import far_outside
    xy = np.array([[-2.5, 0.0], [np.nextafter(-2.5, -3), 0.0], [0.0, 12.5], [0.0, np.nextafter(12.5, 13)],
                   [np.nan, 1.0], [3.0, 4.0]])
    assert far_outside(xy, (0, 2), (5, 10), 5).tolist() == [False, True, False, True, True, False]
    assert far_outside(xy, (0, 2), (5, 10), 5, tolerance=0.0).tolist() == [True, True, True, True, True, False]
    assert far_outside(np.zeros((0, 2)), (0, 0), (1, 1), 1).shape == (0,)


def test_clip_polygon_is_the_intersection_with_the_box():
    """The cut polygon covers what shapely's intersection with ``[-W, 2W] x [-H, 2H]`` covers (simple
    polygons: the cut's area is the intersection's; the edges the cut adds along the box cancel)."""
    shapely = pytest.importorskip("shapely")
    from carvi_torch.io.coco import clip_polygon
    rng = np.random.default_rng(0)
    h, w = 30, 40
    box = shapely.box(-w, -h, 2 * w, 2 * h)
    done = 0
    for scale in (1, 10, 1e6, 1e300):
        for _ in range(60):
            n = int(rng.integers(3, 9))  # a star-shaped polygon: simple, often not convex
            angle, radius = np.sort(rng.uniform(0, 2 * np.pi, n)), rng.uniform(0.2, 1, n) * scale * w
            pts = np.stack([np.cos(angle), np.sin(angle)], 1) * radius[:, None] + rng.uniform(-1, 1, 2) * scale * w
            poly = shapely.Polygon(pts)
            if not poly.is_valid:
                continue
            cut = clip_polygon(pts.ravel(), h, w)
            assert np.isfinite(cut).all()
            if scale < 1e100:
                want = poly.intersection(box).area
            else:  # beyond shapely's range: the box is all in or all out (shapely on the polygon scaled down)
                want = box.area if shapely.Polygon(pts / scale).contains(shapely.Point(0, 0)) else 0.0
            got = _shoelace(cut) if len(cut) >= 6 else 0.0
            assert got == pytest.approx(want, rel=1e-9, abs=1e-6)
            if 0 < want and scale < 1e100:
                assert shapely.Polygon(np.reshape(cut, (-1, 2))).buffer(1e-6).covers(poly.intersection(box))
            done += 1
    assert done > 200


class TestLoad:
    def test_collection(self, tmp_path):
        path, images, anns = _dataset(tmp_path)
        res = load_coco(path, canvas_size=64)
        c = res.collections["plane"]
        assert len(c) == 4 and c.masks.shape == (4, 64, 64) and c.keypoints.shape == (4, 4, 2)
        assert c.meta.flip_pairs == [(0, 1)] and c.object_ids == [100, 101, 102, 103]
        assert c.object_groups.tolist() == [0, 1, 2, 3]
        assert c.visible[:, 3].tolist() == [True, False, True, False]
        # keypoints map back to the image exactly
        img = torch.tensor([[a["keypoints"][3 * k], a["keypoints"][3 * k + 1]] for a in anns for k in range(4)],
                           dtype=torch.float32).reshape(4, 4, 2)
        back = c.keypoints_in_image()
        assert torch.allclose(back[c.visible], img[c.visible], atol=2e-3)
        # canvas mask area ~ image area * scale^2
        area_img = torch.tensor([a["area"] for a in anns])
        ratio = c.masks.flatten(1).sum(1) / (area_img * c.canvas_from_image.scale ** 2)
        assert ((ratio - 1).abs() < 0.05).all()
        # the object is centred in the canvas with the margin
        assert c.masks[:, :5].sum() == 0 and c.masks[:, :, :5].sum() == 0

    def test_problems_per_object(self, tmp_path):
        good = make_annotation(0, 1, 1, _ellipse(120, 160, 70, 60, 40, 20),
                               np.array([[40.0, 60], [100, 60], [70, 45], [70, 75]]), np.ones(4, bool))
        bad = []

        def variant(aid, **changes):
            a = json.loads(json.dumps(good))
            a["id"] = aid
            for k, v in changes.items():
                if v is None:
                    a.pop(k)
                else:
                    a[k] = v
            bad.append(a)

        variant(50, segmentation=None)  # missing mask
        variant(51, segmentation=encode_mask(np.zeros((120, 160), bool)))  # empty mask
        variant(52, keypoints=[1, 2, 2] * 3)  # keypoint count
        variant(53, keypoints=[0, 0, 0] * 4)  # nothing visible
        variant(54, category_id=9)  # unknown category
        variant(1)  # duplicate id (1 exists)
        variant(55, image_id=77)  # unknown image
        variant(56, keypoints=[float("nan"), 1, 2, 100, 60, 2, 70, 45, 2, 70, 75, 2])  # NaN -> warning
        variant(57, keypoints=[5000, 60, 2, 100, 60, 2, 70, 45, 2, 70, 75, 2])  # far outside -> warning
        variant(58, occluded=True)
        variant(59, segmentation={"size": [120, 160], "counts": "garbage!!"})
        path, _, _ = _dataset(tmp_path, bad)
        res = load_coco(path, canvas_size=32)
        reasons = {p.annotation_id: p for p in res.problems}
        assert "missing mask" in reasons[50].reason and "empty mask" in reasons[51].reason
        assert "keypoint values" in reasons[52].reason and "no visible keypoint" in reasons[53].reason
        assert "unknown category" in reasons[54].reason and "duplicate" in reasons[1].reason
        assert "unknown image" in reasons[55].reason
        assert "NaN" in reasons[56].reason and not reasons[56].fatal
        assert "far outside" in reasons[57].reason and not reasons[57].fatal
        assert "occluded" in reasons[58].reason and "malformed segmentation" in reasons[59].reason
        c = res.collections["plane"]
        ids = c.annotation_ids
        assert ids == [1, 2, 3, 4, 56, 57]  # good objects and the two warned ones go on
        assert c.visible[4].tolist() == [False, True, True, True] and c.visible[5].tolist() == [False, True, True, True]
        for p in res.problems:
            assert str(p.annotation_id) in p.message()

    def test_chunks_of_the_load_change_no_bit(self, tmp_path, monkeypatch):
        """The load resamples and hashes masks a chunk at a time (its memory bound): chunks of 3 and of 2 give
        the collection of one chunk, canvases, similarities, keypoints and fingerprints to the bit."""
        from carvi_torch.io import coco
        path, _, _ = _dataset(tmp_path, n=7)
        runs = []
        for chunk in (10 ** 6, 3, 2):
            monkeypatch.setattr(coco._Canvases, "CHUNK", chunk)
            runs.append(load_coco(path, canvas_size=32).collections["plane"])
        one = runs[0]
        for c in runs[1:]:
            assert torch.equal(c.masks, one.masks) and torch.equal(c.keypoints, one.keypoints)
            assert torch.equal(c.canvas_from_image.scale, one.canvas_from_image.scale)
            assert torch.equal(c.canvas_from_image.offset, one.canvas_from_image.offset)
            assert c.fingerprints == one.fingerprints and c.annotation_ids == one.annotation_ids
        assert len(set(one.fingerprints)) == 7 and one.masks.any(dim=(1, 2)).all()

    def test_malformed_json(self, tmp_path):
        p = tmp_path / "bad.json"
        p.write_text('{"images": [], "annotations": [1, 2,, 3]}')
        with pytest.raises(CocoFormatError, match=r"bad\.json.*line 1, column"):
            load_coco(p)
        p.write_text('{"images": []}')
        with pytest.raises(CocoFormatError, match="annotations"):
            load_coco(p)
        with pytest.raises(CocoFormatError, match="no such file"):
            load_coco(tmp_path / "missing.json")

    def test_unreadable_files_name_the_file(self, tmp_path):
        """`images` not a list, nesting beyond the parser's recursion, bytes that are not UTF-8: one
        CocoFormatError (a user error) naming the file, never a TypeError or RecursionError."""
        path, _, _ = _dataset(tmp_path, n=2)
        data = json.loads(path.read_text())
        bad = tmp_path / "bad.json"
        bad.write_text(json.dumps({**data, "images": 5}))
        with pytest.raises(CocoFormatError, match=r"bad\.json: 'images' is an integer \(5\), not a list"):
            load_coco(bad)
        bad.write_text(json.dumps(data)[:-1] + ', "info": ' + "[" * 100_000 + "]" * 100_000 + "}")
        with pytest.raises(CocoFormatError, match=r"bad\.json: JSON nested too deeply"):
            load_coco(bad)
        bad.write_bytes(json.dumps({**data, "info": "caf\u00e9"}, ensure_ascii=False).encode("latin-1"))
        with pytest.raises(CocoFormatError, match=r"bad\.json: not UTF-8 text \(byte 0xe9"):
            load_coco(bad)

    def test_a_byte_order_mark_is_accepted(self, tmp_path):
        path, _, _ = _dataset(tmp_path, n=2)
        path.write_bytes(b"\xef\xbb\xbf" + path.read_bytes())
        assert len(load_coco(path, canvas_size=32).collections["plane"]) == 2

    def test_class_filter_and_extras(self, tmp_path):
        path, images, anns = _dataset(tmp_path)
        data = json.loads(path.read_text())
        data["categories"][0].update({"rigid_keypoints": [0, 1, 2], "symmetry": "rotational", "articulated": True,
                                      "flip_pairs": [[0, 1]], "left_convention": "viewer"})
        path.write_text(json.dumps(data))
        c = load_coco(path, canvas_size=32).collections["plane"]
        assert c.meta.rigid_keypoints == [0, 1, 2] and c.meta.symmetry == "rotational" and c.meta.articulated
        assert c.meta.left_convention == "viewer"
        assert load_coco(path, classes=["car"]).collections == {}

    def test_keypoints_3d_of_finite_numbers_and_nulls_are_kept(self, tmp_path):
        path, _, _ = _dataset(tmp_path)
        data = json.loads(path.read_text())
        pts = [[0, 0, 1], None, [-1e299, 2, 3.5], [10 ** 20, 0.0, -7]]
        data["categories"][0]["keypoints_3d"] = pts
        path.write_text(json.dumps(data))
        res = load_coco(path, canvas_size=32)
        assert res.collections["plane"].meta.keypoints_3d == pts and res.problems == []

    @pytest.mark.parametrize("field, value", [
        ("flip_pairs", [[0, 1], [0, 2]]), ("flip_pairs", [[1, 1]]), ("flip_pairs", ["01"]),
        ("flip_pairs", [[10 ** 400, 1]]), ("flip_pairs", [[float("inf"), 1]]), ("flip_pairs", [[0.5, 1]]),
        ("rigid_keypoints", [0.5, 1.7, 2.2]), ("rigid_keypoints", "012"), ("rigid_keypoints", [0, 1, float("inf")]),
        ("rigid_keypoints", [0, 1, True]), ("keypoints_3d", [[1, 2, 10 ** 400], None, None, None]),
        ("keypoints_3d", [[1, 2, 1e301], None, None, None]), ("keypoints_3d", [[1, 2, False], None, None, None]),
        ("keypoints_3d", [[1, 2], None, None, None])])
    def test_a_bad_category_field_is_a_warning_not_a_crash(self, tmp_path, field, value):
        """Overlapping or self pairs (the mirror would not be a permutation), strings, fractions, integers beyond
        float64, infinities, booleans, 3-D coordinates beyond 1e300: one warning naming the field, the field's
        default, every object loaded."""
        path, _, _ = _dataset(tmp_path)
        data = json.loads(path.read_text())
        data["categories"][0][field] = value
        path.write_text(json.dumps(data))
        res = load_coco(path, canvas_size=32)
        c = res.collections["plane"]
        assert len(c) == 4 and [p.fatal for p in res.problems] == [False]
        assert field in res.problems[0].reason and len(res.problems[0].message()) < 300
        assert c.meta.flip_pairs == [(0, 1)] and c.meta.rigid_keypoints is None and c.meta.keypoints_3d is None

    @pytest.mark.parametrize("names, said", [
        (["x", "x", "x", "x"], "'x'"), (["left_wing", "left_wing", "nose", "tail"], "'left_wing'"),
        ([1, "1", "nose", "tail"], "'1'"), (["a", "b", "a", "b"], "'a', 'b'")])
    def test_a_category_whose_keypoint_names_repeat_is_skipped_with_one_reason(self, tmp_path, names, said):
        """Keypoints are found by name (mean shape, templates, flips), so two sharing one would collapse into one
        point: the category is an input problem naming it and the repeated names; the other classes load."""
        path, images, anns = _dataset(tmp_path)
        data = json.loads(path.read_text())
        data["categories"][0]["keypoints"] = names
        data["categories"].append(make_category(2, "kite", NAMES))
        data["annotations"].append({**anns[0], "id": 50, "category_id": 2})
        path.write_text(json.dumps(data))
        res = load_coco(path, canvas_size=32)
        assert list(res.collections) == ["kite"] and len(res.collections["kite"]) == 1
        (p,) = res.problems
        assert p.fatal and p.category == "plane" and p.annotation_id is None and "\n" not in p.message()
        assert p.reason == f"keypoint names repeat: {said}; each keypoint needs its own name"

    def test_keypoints_beyond_float64_skip_their_object(self, tmp_path):
        bad = make_annotation(9, 1, 1, _ellipse(120, 160, 70, 60, 40, 20), np.ones((4, 2)), np.ones(4, bool))
        bad["keypoints"][0] = 10 ** 400
        path, _, _ = _dataset(tmp_path, [bad])
        res = load_coco(path, canvas_size=32)
        assert [(p.annotation_id, p.fatal) for p in res.problems] == [(9, True)]
        assert "beyond floating point" in res.problems[0].reason and len(res.collections["plane"]) == 4

    def test_ids_that_name_the_same_files_keep_the_first_and_say_what_became_of_it(self, tmp_path):
        """An id is the object's file name (``object_stem``): a second annotation with the same id, or with an id
        spelled alike there (``"a/b"`` is written as ``a_b-<hash>``), is skipped with a reason
        naming the first, whose fate (kept or why not) the reason tells; ids that differ in letter case only are
        two objects; the rule does not depend on ``classes``."""
        from carvi_torch.io.layout import object_stem
        ell = _ellipse(120, 160, 70, 60, 40, 20)
        kp = np.array([[40.0, 60], [100, 60], [70, 45], [70, 75]])

        def ann(aid, cat=1, **extra):
            return {**make_annotation(0, 1, cat, ell, kp, np.ones(4, bool)), "id": aid, **extra}
        stem = object_stem("a/b")
        extra = [ann("a/b"), ann(stem), ann("Obj-A"), ann("obj-a"), ann(77, segmentation=None), ann(77),
                 ann(3, cat=2)]
        path, _, _ = _dataset(tmp_path, extra)
        data = json.loads(path.read_text())
        data["categories"].append(make_category(2, "other", NAMES))
        path.write_text(json.dumps(data))
        for classes in (None, ["other"]):
            res = load_coco(path, canvas_size=32, classes=classes)
            why = {(p.annotation_id, p.reason) for p in res.problems}
            if classes is None:
                assert res.collections["plane"].annotation_ids == [1, 2, 3, 4, "a/b", "Obj-A", "obj-a"]
                assert (stem, f"annotation id {stem!r} and the earlier 'a/b' name the same output files "
                              f"({stem!r}); keeping the first") in why
                assert (77, "duplicate annotation id 77; the first is not reconstructed either: missing mask "
                            "(no segmentation)") in why
            assert "other" not in res.collections  # id 3 is a plane's first, whichever classes are run
            assert any(a == 3 and r.startswith("duplicate annotation id 3;") for a, r in why)


class TestInterrupts:
    """Ctrl-C during loading stops the load; only what bad input raises becomes a one-line reason."""

    def _with_garbage(self, tmp_path):
        anns = [{"id": 50, "image_id": 1, "category_id": 1, "keypoints": [40, 60, 2] * 4,
                 "segmentation": {"counts": 5, "size": [120, 160]}},          # pycocotools: TypeError
                {"id": 51, "image_id": 1, "category_id": 1, "keypoints": [40, 60, 2] * 4,
                 "segmentation": [["a", "b", "c", "d", "e", "f"]]}]           # numpy: ValueError
        return _dataset(tmp_path, anns, n=2)[0]

    def test_malformed_segmentations_are_one_line_reasons(self, tmp_path):
        res = load_coco(self._with_garbage(tmp_path))
        reasons = {p.annotation_id: p.message() for p in res.problems}
        assert set(reasons) == {50, 51} and len(res.collections["plane"]) == 2
        assert all("malformed segmentation" in m and "\n" not in m for m in reasons.values())

    def test_an_interrupt_that_the_decoder_turns_into_a_type_error_propagates(self, tmp_path, monkeypatch):
        # seen once: a Ctrl-C during loading came out of pycocotools' decoding as numpy's TypeError about an
        # old-style __array__, and the run went on with a bad-mask reason. The load must stop instead
        import signal

        from carvi_torch.io import coco

        real, calls = coco.decode_segmentation, []

        def decoder(seg, height, width):
            calls.append(1)
            if len(calls) == 2:
                try:
                    signal.raise_signal(signal.SIGINT)
                    sum(range(100))  # the Python-level handler runs at a bytecode boundary
                except KeyboardInterrupt:
                    raise TypeError("__array__() got an unexpected keyword argument 'copy'") from None
            return real(seg, height, width)

        monkeypatch.setattr(coco, "decode_segmentation", decoder)
        path = _dataset(tmp_path, n=3)[0]
        with pytest.raises(KeyboardInterrupt):
            load_coco(path)
        assert len(calls) == 2 and signal.getsignal(signal.SIGINT) is signal.default_int_handler

    @pytest.mark.parametrize("error", [KeyboardInterrupt, RuntimeError, MemoryError])
    def test_what_bad_input_does_not_raise_is_not_a_reason(self, tmp_path, monkeypatch, error):
        from carvi_torch.io import coco

        def decoder(seg, height, width):
            raise error("not an input problem")

        monkeypatch.setattr(coco, "decode_segmentation", decoder)
        with pytest.raises(error):
            load_coco(_dataset(tmp_path, n=2)[0])


@pytest.mark.parametrize("size", [128, 64])
def test_real_aeroplanes_canvases_are_the_per_object_references(shared_data, tmp_path, size):
    """The VOC aeroplanes (real masks, photos of many sizes): loading's batched canvases are the per-object
    reference's (``collection.resample_to_canvas``) bit for bit."""
    from carvi_torch.collection import resample_to_canvas
    from carvi_torch.io.voc import convert

    ann = tmp_path / "aeroplane.json"
    convert(shared_data / "pascal_voc_aeroplane" / "keypoints", ann)
    (coll,) = load_coco(ann, canvas_size=size).collections.values()
    data = json.loads(ann.read_text())
    images = {im["id"]: im for im in data["images"]}
    anns = {a["id"]: a for a in data["annotations"]}
    sim = coll.canvas_from_image
    ref = []
    for i, aid in enumerate(coll.annotation_ids):
        im = images[anns[aid]["image_id"]]
        mask = torch.from_numpy(decode_segmentation(anns[aid]["segmentation"], im["height"], im["width"]))
        ref.append(resample_to_canvas(mask, float(sim.scale[i]), sim.offset[i], size))
    assert len(ref) > 300 and len({tuple(wh) for wh in coll.image_size.tolist()}) > 10  # photos of many sizes
    assert torch.equal(coll.masks, torch.stack(ref))
