"""Keeping the better of an object's SfM and refined cameras (``viewpoints.choice``).

The scores are checked against independent references: the hull agreement against matplotlib's
point-in-polygon test of every pixel centre, the keypoint error against a loop over the points;
and the choice on constructed cameras whose outcome the rule fixes (``tests/test_pipeline.py`` checks
the run's cameras against the choice ``cameras.json`` reports).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from carvi_torch.cameras import ScaledOrthographic, rotation_about_axis
from carvi_torch.viewpoints.choice import (HULL_GAIN, KEYPOINT_GROWTH, box_diagonal, choose_cameras,
                                           hull_agreement, keypoint_rms)


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
    """``class`` keeps the SfM cameras of every row with one only when more than half of them are suspect;
    rows without an SfM camera never keep one."""
    from carvi_torch.viewpoints.choice import CLASS_SUSPECT, kept_rows

    has = torch.tensor([True] * 6 + [False, False])
    half = torch.tensor([True, True, True, False, False, False, True, True])
    assert CLASS_SUSPECT == 0.5
    assert kept_rows(half, has, "class").tolist() == [False] * 8  # 3 of 6: not more than half
    more = half.clone()
    more[3] = True
    assert kept_rows(more, has, "class").tolist() == [True] * 6 + [False, False]
    assert kept_rows(more, has, "objects").tolist() == [True] * 4 + [False] * 4
    assert not kept_rows(more, has, "refined").any()
    assert not kept_rows(more, torch.zeros(8, dtype=torch.bool), "class").any()
