"""Keeping the better of an object's SfM and refined cameras (``viewpoints.choice``).

The scores are checked against independent references: the hull agreement against matplotlib's
point-in-polygon test of every pixel centre and, bit for bit, against scikit-image's polygon fill of scipy's
hull (``hull_agreement_reference``), the keypoint error against a loop over the points;
and the choice on constructed cameras whose outcome the rule fixes (``tests/test_pipeline.py`` checks
the run's cameras against the choice ``cameras.json`` reports).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest import requires_cuda
from carvi_torch.cameras import ScaledOrthographic, random_rotations, rotation_about_axis
from carvi_torch.viewpoints.choice import (HULL_GAIN, KEYPOINT_GROWTH, box_diagonal, choose_cameras,
                                           hull_agreement, hull_agreement_reference, keypoint_rms)


def _cams(R, s, t):
    return ScaledOrthographic(R.double(), torch.as_tensor(s, dtype=torch.float64),
                              torch.as_tensor(t, dtype=torch.float64))


def test_hull_agreement_matches_a_point_in_polygon_reference(generator):
    from matplotlib.path import Path as MPath
    from scipy.spatial import ConvexHull

    C = 48
    shape = torch.randn(7, 3, generator=generator, dtype=torch.float64) * 8
    R = torch.stack([rotation_about_axis(torch.tensor([0.3, 1.0, 0.2], dtype=torch.float64), a)
                     for a in (0.0, 0.7, 2.0)])
    cams = _cams(R, [1.0, 1.2, 0.8], [[24.0, 24.0], [20.0, 26.0], [30.0, 22.0]])
    yy, xx = np.mgrid[:C, :C]
    masks = torch.stack([torch.from_numpy((xx - 24) ** 2 / 100 + (yy - 24) ** 2 / 60 <= 1),
                         torch.from_numpy((abs(xx - 22) < 9) & (abs(yy - 25) < 12)),
                         torch.zeros(C, C, dtype=torch.bool)])
    masks[2, 10:30, 25:40] = True
    got = hull_agreement(shape, cams, masks).numpy()
    P = cams.project(shape).numpy()
    centres = np.stack([xx.ravel(), yy.ravel()], 1).astype(float)
    for i in range(3):
        inside = MPath(P[i][ConvexHull(P[i]).vertices]).contains_points(centres).reshape(C, C)
        m = masks[i].numpy()
        ref = (inside & m).sum() / (inside | m).sum()
        assert got[i] == pytest.approx(ref, abs=0.02)  # pixel centres on the hull's edge may go either way
    # NaN rows are left out, and fewer than 3 points have no area
    with_nan = torch.cat([shape, torch.full((1, 3), math.nan, dtype=torch.float64)])
    assert torch.equal(hull_agreement(with_nan, cams, masks), hull_agreement(shape, cams, masks))
    assert float(hull_agreement(shape[:2], cams[:1], masks[:1])[0]) == 0.0


@pytest.mark.parametrize("k, spread, seed", [(3, 20.0, 0), (7, 30.0, 1), (12, 40.0, 2), (15, 90.0, 3), (5, 2.0, 4)])
def test_hull_agreement_equals_its_reference_pixel_for_pixel(k, spread, seed):
    """The batched spans against scipy's hull filled by scikit-image (``hull_agreement_reference``): the same
    IoU, bit for bit, on random shapes and cameras (hulls inside, across and beyond the canvas edge, a hull of
    a few pixels) and masks of random blobs."""
    g = torch.Generator().manual_seed(seed)
    C, M = 64, 40
    shape = spread * torch.randn(k, 3, generator=g, dtype=torch.float64)
    cams = _cams(random_rotations(M, g, torch.float64), 0.2 + 0.6 * torch.rand(M, generator=g, dtype=torch.float64),
                 C * torch.rand(M, 2, generator=g, dtype=torch.float64))
    yy, xx = torch.meshgrid(torch.arange(C), torch.arange(C), indexing="ij")
    c = C * torch.rand(M, 2, 1, 1, generator=g)
    r = C / 6 + C / 3 * torch.rand(M, 1, 1, generator=g)
    masks = (xx - c[:, 0]) ** 2 + (yy - c[:, 1]) ** 2 <= r ** 2
    got, ref = hull_agreement(shape, cams, masks), hull_agreement_reference(shape, cams, masks)
    assert got.dtype == torch.float64 and got.shape == (M,)
    assert torch.equal(got, ref)
    assert int((ref > 0).sum()) >= M // 4  # the case is not all empty


@pytest.mark.parametrize("order", [(0, 1, 2), (2, 0, 1), (1, 2, 0), (2, 1, 0)])
def test_hull_agreement_keeps_a_corner_on_a_pixel_centre(order):
    """A hull corner exactly on a pixel centre (2, 8) is inside whatever the points' order: the crossing at an
    edge's end is the end itself (computed, it can land one unit in the last place outside and drop the pixel)."""
    pts = torch.tensor([[14.4, 1.3, 0.0], [8.6, 9.3, 0.0], [2.0, 8.0, 0.0]], dtype=torch.float64)[list(order)]
    cams = _cams(torch.eye(3)[None], [1.0], [[0.0, 0.0]])
    masks = torch.ones(1, 16, 16, dtype=torch.bool)
    ref = hull_agreement_reference(pts, cams, masks)
    assert float(ref[0]) == 30 / 256
    assert torch.equal(hull_agreement(pts, cams, masks), ref)


@requires_cuda
def test_hull_agreement_on_cuda_masks_equals_the_reference():
    """Masks on the GPU (a CUDA run's viewpoints on the device): the spans run there and give the reference's IoU
    on the CPU, bit for bit."""
    g = torch.Generator().manual_seed(5)
    C, M = 64, 30
    shape = 30.0 * torch.randn(9, 3, generator=g, dtype=torch.float64)
    cams = _cams(random_rotations(M, g, torch.float64), 0.2 + 0.6 * torch.rand(M, generator=g, dtype=torch.float64),
                 C * torch.rand(M, 2, generator=g, dtype=torch.float64))
    masks = torch.rand(M, C, C, generator=g) > 0.4
    ref = hull_agreement_reference(shape, cams, masks)
    dev = torch.device("cuda")
    got = hull_agreement(shape.to(dev), ScaledOrthographic(cams.R.to(dev), cams.s.to(dev), cams.t.to(dev)),
                         masks.to(dev))
    assert got.device.type == "cpu" and torch.equal(got, ref)


def test_hull_agreement_of_collinear_points_is_the_references():
    """Points on one line have no hull: agreement 0, as scipy's hull refusing them gives the reference."""
    shape = torch.tensor([[0.0, 0, 0], [5, 0, 0], [10, 0, 0], [-4, 0, 0]], dtype=torch.float64)
    cams = _cams(torch.eye(3)[None].expand(2, 3, 3), [1.0, 2.0], [[16.0, 16.0], [10.0, 20.5]])
    masks = torch.ones(2, 32, 32, dtype=torch.bool)
    assert torch.equal(hull_agreement(shape, cams, masks), hull_agreement_reference(shape, cams, masks))
    assert torch.equal(hull_agreement(shape, cams, masks), torch.zeros(2, dtype=torch.float64))


@pytest.mark.shared
def test_hull_agreement_equals_its_reference_on_the_real_aeroplanes(shared_data, tmp_path):
    """The real VOC aeroplanes and mirrors (654 masks at the default canvas) under their SfM cameras and mean
    shape: the batched IoU equals the reference's on every row."""
    from carvi_torch.config import Config
    from carvi_torch.io.coco import load_coco
    from carvi_torch.io.voc import convert
    from carvi_torch.viewpoints import class_sfm

    ann = tmp_path / "aeroplane.json"
    convert(shared_data / "pascal_voc_aeroplane" / "keypoints", ann)
    both = load_coco(ann, classes=["aeroplane"]).collections["aeroplane"].with_mirrors()
    res = class_sfm(both, Config().override({"progress": False}).viewpoints, polish_iters=0)
    rows = res.valid.nonzero().squeeze(1)
    got = hull_agreement(res.shape, res.cameras[rows], both.masks[rows])
    assert len(rows) > 600 and float(got.median()) > 0.3  # 0.42: eight keypoints outline an aeroplane roughly
    assert torch.equal(got, hull_agreement_reference(res.shape, res.cameras[rows], both.masks[rows]))


def test_keypoint_rms_and_box_diagonal_match_loops(generator):
    shape = torch.randn(6, 3, generator=generator, dtype=torch.float64)
    shape[4] = math.nan
    cams = _cams(torch.eye(3).expand(2, 3, 3), [10.0, 12.0], [[5.0, 5.0], [1.0, 2.0]])
    kp = torch.randn(2, 6, 2, generator=generator, dtype=torch.float64) * 10
    vis = torch.tensor([[1, 1, 0, 1, 1, 1], [0, 0, 0, 0, 1, 0]], dtype=torch.bool)
    got = keypoint_rms(shape, cams, kp, vis)
    P = cams.project(torch.nan_to_num(shape))
    for i in range(2):
        d = [float(((P[i, k] - kp[i, k]) ** 2).sum()) for k in range(6) if vis[i, k] and k != 4]
        ref = math.sqrt(sum(d) / len(d)) if d else 0.0
        assert float(got[i]) == pytest.approx(ref, rel=1e-9)
    masks = torch.zeros(2, 20, 20, dtype=torch.bool)
    masks[0, 3:7, 2:12] = True  # 4 rows, 10 columns
    assert box_diagonal(masks).tolist() == [pytest.approx(math.hypot(4, 10)), 1.0]


def test_choice_keeps_sfm_only_for_a_keypoint_loss_without_hull_gain():
    """A flat square seen face-on: the SfM camera fits its keypoints; a refined camera turned 40 degrees
    about the vertical loses them (growth over 1% of the diagonal) and covers less of the mask: the SfM
    camera is kept. A refined camera moved by a tenth of a pixel is kept."""
    S = torch.tensor([[-10.0, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0], [0, 0, 3]], dtype=torch.float64)
    eye = torch.eye(3, dtype=torch.float64)
    sfm = _cams(eye.expand(2, 3, 3), [1.0, 1.0], [[16.0, 16.0], [16.0, 16.0]])
    kp = sfm.project(S)
    vis = torch.ones(2, 5, dtype=torch.bool)
    masks = torch.zeros(2, 32, 32, dtype=torch.bool)
    masks[:, 6:27, 6:27] = True
    turned = rotation_about_axis(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), math.radians(40.0))
    refined = _cams(torch.stack([turned, eye]), [1.0, 1.0], [[16.0, 16.0], [16.1, 16.0]])
    c = choose_cameras(S, sfm, refined, kp, vis, masks)
    assert c.suspect.tolist() == [True, False]
    assert float(c.rms_refined[0] - c.rms_sfm[0]) > KEYPOINT_GROWTH * float(c.diagonal[0])
    assert float(c.hull_refined[0] - c.hull_sfm[0]) < HULL_GAIN


def test_kept_rows_per_object_and_per_class():
    """``class`` keeps the SfM cameras of every row with one only when more than a third of them are
    suspect; rows without an SfM camera never keep one."""
    from carvi_torch.viewpoints.choice import CLASS_SUSPECT, kept_rows

    has = torch.tensor([True] * 6 + [False, False])
    third = torch.tensor([True, True, False, False, False, False, True, True])
    assert CLASS_SUSPECT == 1 / 3
    assert kept_rows(third, has, "class").tolist() == [False] * 8  # 2 of 6: not more than a third
    more = third.clone()
    more[3] = True  # 3 of 6 (the CAD trains at 30 views: 45%)
    assert kept_rows(more, has, "class").tolist() == [True] * 6 + [False, False]
    assert kept_rows(more, has, "objects").tolist() == [True, True, False, True] + [False] * 4
    assert not kept_rows(more, has, "refined").any()
    assert not kept_rows(more, torch.zeros(8, dtype=torch.bool), "class").any()


def _level_cameras(n: int, roll_deg=None, elevation_deg: float = 15.0):
    from carvi_torch.cameras import rotation_from_azimuth_elevation_roll

    az = torch.linspace(0.0, 2 * math.pi, n + 1, dtype=torch.float64)[:n]
    el = torch.full_like(az, math.radians(elevation_deg))
    roll = torch.zeros_like(az) if roll_deg is None else torch.deg2rad(torch.as_tensor(roll_deg, dtype=torch.float64))
    return rotation_from_azimuth_elevation_roll(az, el, roll)


def test_image_tilt_is_the_roll_of_a_level_view_and_the_up_is_found_in_any_object_frame(generator):
    """At elevation 0 the tilt of the object's up (+z) is the camera's roll, by the angle convention of
    ``rotation_from_azimuth_elevation_roll``; ``class_up`` finds +z from level cameras in whatever frame
    the object is written (a random rotation G of the frame: cameras R G, up G^T z)."""
    from carvi_torch.cameras import random_rotations
    from carvi_torch.viewpoints.choice import class_up, image_tilt

    rolls = [0.0, 10.0, -35.0, 90.0, 150.0, -170.0, 5.0, 60.0]
    R = _level_cameras(8, rolls, elevation_deg=0.0)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    tilt, length = image_tilt(R, z)
    assert tilt.tolist() == pytest.approx([abs(r) for r in rolls], abs=1e-9)
    assert length.tolist() == pytest.approx([1.0] * 8, abs=1e-12)
    # the projected up shortens with the elevation: cos(elevation)
    assert image_tilt(_level_cameras(3, elevation_deg=50.0), z)[1].tolist() == pytest.approx(
        [math.cos(math.radians(50.0))] * 3, abs=1e-12)
    G = random_rotations(1, generator=generator, dtype=torch.float64)[0]
    level = _level_cameras(12, elevation_deg=20.0) @ G
    up = class_up(level)
    assert float(up @ (G.T @ z)) == pytest.approx(1.0, abs=1e-9)
    # cameras that all look down the up axis leave it unclear
    assert class_up(_level_cameras(12, elevation_deg=0.0)[:2]) is None


def test_a_tilted_refined_camera_keeps_its_sfm_camera_and_a_level_one_keeps_its_refinement():
    """A class of 12 level SfM cameras; refinement turns object 0 upside down (roll 160 degrees: a pose no
    photographer takes), object 1 by 8 degrees of azimuth and object 2 by a roll of 25 degrees (within
    ``refine_max_tilt_deg``): only object 0 keeps its SfM camera, under both ``class`` and ``objects``; the
    paper's ``refined`` keeps every refinement."""
    from carvi_torch.cameras import rotation_from_azimuth_elevation_roll
    from carvi_torch.viewpoints.choice import TILT_MARGIN_DEG, kept_rows, tilted

    sfm = _level_cameras(12, elevation_deg=15.0)
    refined = sfm.clone()
    a0, e0 = 0.0, math.radians(15.0)
    t = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    refined[0] = rotation_from_azimuth_elevation_roll(t(a0), t(e0), t(math.radians(160.0)))
    az1 = 2 * math.pi / 12
    refined[1] = rotation_from_azimuth_elevation_roll(t(az1 + math.radians(8.0)), t(e0), t(0.0))
    refined[2] = rotation_from_azimuth_elevation_roll(t(2 * az1), t(e0), t(math.radians(25.0)))
    has = torch.ones(12, dtype=torch.bool)
    tilt = tilted(sfm, refined, has, 30.0)
    assert tilt.tolist() == [True] + [False] * 11
    none = torch.zeros(12, dtype=torch.bool)
    for how in ("class", "objects"):
        assert kept_rows(none, has, how, tilt).tolist() == [True] + [False] * 11
    assert not kept_rows(none, has, "refined", tilt).any()
    # 180 switches the test off; a row without an SfM camera is never tilted
    assert not tilted(sfm, refined, has, 180.0).any()
    no_sfm = has.clone()
    no_sfm[0] = False
    assert not tilted(sfm, refined, no_sfm, 30.0)[0]
    # a refinement that turns an upside-down SfM camera (roll 170) upright is kept
    sfm_down = sfm.clone()
    sfm_down[3] = rotation_from_azimuth_elevation_roll(t(3 * az1), t(e0), t(math.radians(170.0)))
    assert not tilted(sfm_down, sfm, has, 30.0)[3]
    assert not kept_rows(none, has, "objects", tilted(sfm_down, sfm, has, 30.0))[3]
    # a camera looking nearly along the up (elevation 70: length cos 70 < MIN_UP_LENGTH) is not judged
    steep = refined.clone()
    steep[0] = rotation_from_azimuth_elevation_roll(t(a0), t(math.radians(70.0)), t(math.radians(160.0)))
    assert not tilted(sfm, steep, has, 30.0)[0]
    # an SfM camera already tilted by 150 degrees: a refined one at 160 is within the margin
    sfm_bad = sfm.clone()
    sfm_bad[0] = rotation_from_azimuth_elevation_roll(t(a0), t(e0), t(math.radians(160.0 - TILT_MARGIN_DEG + 10)))
    assert not tilted(sfm_bad, refined, has, 30.0)[0]


def test_the_pipeline_applies_the_tilt_test(tmp_path, procedural_input, monkeypatch):
    """``estimate_viewpoints`` wires the tilt test through: a row the test marks tilted ends with its SfM
    camera, its annotation id in ``refine.kept_sfm.tilted_ids``; the other rows keep the cameras they had."""
    import carvi_torch.viewpoints as vps
    from carvi_torch.config import Config
    from carvi_torch.io.coco import load_coco

    coll = next(iter(load_coco(procedural_input(tmp_path), classes=["car"]).collections.values()))
    cfg = Config().override({"progress": False, "refine_iters": 20}).viewpoints
    base = vps.estimate_viewpoints(coll, cfg)
    assert base.info["refine"]["kept_sfm"]["tilted_ids"] == []
    n = len(coll)
    free = (~base.kept_sfm[:n] & base.sfm_valid[:n]).nonzero().squeeze(1)
    assert len(free) > 0
    r = int(free[0])
    assert not torch.equal(base.cameras.R[r], base.sfm_cameras.R[r])

    def row_r_tilted(sfm_R, refined_R, has_sfm, max_deg):
        out = torch.zeros(len(sfm_R), dtype=torch.bool)
        out[r] = True
        return out

    monkeypatch.setattr(vps, "tilted", row_r_tilted)
    vp = vps.estimate_viewpoints(coll, cfg)
    assert vp.info["refine"]["kept_sfm"]["tilted_ids"] == [coll.annotation_ids[r]]
    assert torch.equal(vp.cameras.R[r], vp.sfm_cameras.R[r])
    others = torch.arange(len(vp.cameras.R)) != r
    assert torch.equal(vp.cameras.R[others], base.cameras.R[others])
