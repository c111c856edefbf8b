"""Tests for the pure pieces of tools/sfm_mixture_study.py (the study itself needs the CAD renders)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import sfm_mixture_study as mix  # noqa: E402


def test_rotation_onto_recovers_a_known_rotation():
    gen = torch.Generator().manual_seed(0)
    S0 = torch.randn(9, 3, generator=gen, dtype=torch.float64)
    Rt = torch.as_tensor(Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix())
    S = 2.5 * S0 @ Rt + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)  # rotated, scaled, shifted
    S[4] = float("nan")  # a keypoint one shape lacks: ignored
    Q = mix.rotation_onto(S, S0)
    assert torch.allclose(Q, Rt.T, atol=1e-8)
    assert float(torch.det(Q)) == pytest.approx(1.0, abs=1e-10)


def test_rotation_onto_is_proper_for_a_mirror_image():
    """A mirrored shape has no proper rotation onto the original: still a rotation (det +1), never a reflection."""
    gen = torch.Generator().manual_seed(1)
    S0 = torch.randn(8, 3, generator=gen, dtype=torch.float64)
    Q = mix.rotation_onto(S0 * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64), S0)
    assert float(torch.det(Q)) == pytest.approx(1.0, abs=1e-10)
    assert torch.allclose(Q @ Q.T, torch.eye(3, dtype=torch.float64), atol=1e-10)


def test_top_up_moves_the_cheapest_objects_into_small_groups():
    labels = torch.tensor([0, 0, 0, 0, 0, 0, 1])
    cost = torch.tensor([[0.0, 5.0], [0.0, 1.0], [0.0, 9.0], [0.0, 2.0], [0.0, 7.0], [0.0, 3.0], [4.0, 0.0]])
    out = mix.top_up(labels, cost, 2, 3)
    assert out.tolist() == [0, 1, 0, 1, 0, 0, 1]  # objects 1 and 3 cost least to move
    assert mix.top_up(labels, cost, 2, 1).tolist() == labels.tolist()  # already large enough


def test_kmeans_labels_separates_clear_clusters_and_is_deterministic():
    gen = torch.Generator().manual_seed(2)
    X = torch.cat([torch.randn(20, 4, generator=gen) * 0.1, torch.randn(15, 4, generator=gen) * 0.1 + 3.0])
    a, b = mix.kmeans_labels(X, 2, seed=5), mix.kmeans_labels(X, 2, seed=5)
    assert torch.equal(a, b)
    assert len(set(a[:20].tolist())) == 1 and len(set(a[20:].tolist())) == 1 and a[0] != a[-1]


def _entry(sse):
    return {str(k): {"chosen": "x", "candidates": [{"init": "x", "sse_px2": v, "sfm": 1.0 + k, "refined": 2.0 + k}]}
            for k, v in sse.items()}


@pytest.mark.parametrize("sse, expected", [({1: 100.0, 2: 60.0, 3: 30.0}, 3),  # 40% then 50%
                                           ({1: 100.0, 2: 60.0, 3: 50.0}, 2),  # 40% then 17%
                                           ({1: 100.0, 2: 80.0, 3: 10.0}, 1),  # 20%: stop at once
                                           ({1: 100.0, 2: 50.0, 3: 70.0}, 2)])  # k=3 worse than k=2
def test_rule_accepts_one_more_group_per_clear_cut(sse, expected):
    k, chosen = mix.pick(_entry(sse), 0.3)
    assert k == expected and chosen[k]["sse_px2"] == sse[k]
    assert f"| {expected} |" in mix.table({"c": _entry(sse)}, 0.3)


def test_rule_with_frame_agreement_skips_disagreeing_splits():
    entry = {"1": {"chosen": "single", "candidates": [{"init": "single", "sse_px2": 100.0, "sfm": 1, "refined": 1}]},
             "2": {"chosen": "a", "candidates": [
                 {"init": "a", "sse_px2": 40.0, "frame_agreement_deg": 120.0, "sfm": 2, "refined": 2},
                 {"init": "b", "sse_px2": 50.0, "frame_agreement_deg": 20.0, "sfm": 3, "refined": 3}]},
             "3": {"chosen": "a", "candidates": [
                 {"init": "a", "sse_px2": 10.0, "frame_agreement_deg": 90.0, "sfm": 4, "refined": 4}]}}
    k, chosen = mix.pick(entry, 0.3)
    assert k == 3 and chosen[2]["init"] == "a"  # without the check: the lowest residual
    k, chosen = mix.pick(entry, 0.3, agreement=60.0)
    assert k == 2 and chosen[2]["init"] == "b" and 3 not in chosen  # the agreeing split only
    assert "frames within 60 deg" in mix.table({"c": entry}, 0.3, 60.0)


def test_top_up_never_takes_a_donor_below_the_bound():
    gen = torch.Generator().manual_seed(3)
    labels = torch.cat([torch.zeros(16, dtype=torch.long), torch.ones(30, dtype=torch.long)])
    cost = torch.rand(46, 3, generator=gen)
    cost[:16, 2] = -1.0  # group 0's objects are the cheapest to move into group 2
    out = mix.top_up(labels, cost, 3, 15)
    assert torch.bincount(out, minlength=3).tolist() == [15, 16, 15]


def test_frame_agreement_measures_the_angle_between_group_frames():
    R = torch.as_tensor(Rotation.random(40, random_state=4).as_matrix())
    I = torch.eye(3, dtype=torch.float64)
    Q = torch.as_tensor(Rotation.from_rotvec([0.0, 0.0, 0.5]).as_matrix())  # 28.6 degrees
    assert mix.frame_agreement([R], [I]) == 0.0
    assert mix.frame_agreement([R, R], [I, I]) == pytest.approx(0.0, abs=1e-5)
    assert mix.frame_agreement([R, R], [I, Q]) == pytest.approx(28.65, abs=0.01)
    # a group whose cameras are already off by Q^T is brought back by its rotation Q
    assert mix.frame_agreement([R, R @ Q.T], [I, Q]) == pytest.approx(0.0, abs=1e-5)
    assert mix.frame_agreement([R, torch.full_like(R, float("nan"))], [I, I]) == float("inf")
