"""Tests for carvi_torch.evaluation.viewpoint_metrics against scipy's rotation tools."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from carvi_torch.cameras import random_rotations, rotation_from_azimuth_elevation_roll
from carvi_torch.evaluation.viewpoint_metrics import (
    align_rotations,
    aligned_median,
    angle_errors,
    compare_camera_runs,
    fit_up_axis,
    geodesic_errors,
    median_change,
    necker_mirror,
    summarize,
    up_axis_errors,
    viewpoint_report,
)


def test_align_rotations_matches_scipy_chordal_mean(generator):
    R_gt = random_rotations(50, generator, dtype=torch.float64)
    G_true = random_rotations(1, generator, dtype=torch.float64)[0]
    noise = Rotation.from_rotvec(np.random.default_rng(0).normal(scale=0.05, size=(50, 3))).as_matrix()
    R_est = torch.from_numpy(noise) @ R_gt @ G_true.T
    G = align_rotations(R_est, R_gt)
    # R_est G ~ R_gt  <=>  G ~ R_est^T R_gt: the chordal L2 mean of those (scipy's Rotation.mean)
    B = np.einsum("nji,njk->nik", R_est.numpy(), R_gt.numpy())
    ref = Rotation.from_matrix(B).mean().as_matrix()
    np.testing.assert_allclose(G.numpy(), ref, atol=1e-8)
    assert abs(float(torch.det(G)) - 1.0) < 1e-10
    exact = align_rotations(R_gt @ G_true.T, R_gt)
    assert torch.allclose(exact, G_true, atol=1e-10)


def test_align_rotations_with_a_batch_of_weightings_equals_one_at_a_time(generator):
    R_gt = random_rotations(12, generator, dtype=torch.float64)
    R_est = torch.from_numpy(Rotation.from_rotvec(np.random.default_rng(1).normal(scale=0.3, size=(12, 3)))
                             .as_matrix()) @ R_gt
    W = torch.from_numpy(np.random.default_rng(2).integers(0, 4, size=(5, 12))).double()
    W[:, 0] += 1  # every weighting has a positive sum
    G = align_rotations(R_est, R_gt, weights=W)
    assert G.shape == (5, 3, 3)
    for b in range(5):
        torch.testing.assert_close(G[b], align_rotations(R_est, R_gt, weights=W[b]), atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="not with robust"):
        align_rotations(R_est, R_gt, weights=W, robust=True)
    with pytest.raises(ValueError, match="weights must be"):
        align_rotations(R_est, R_gt, weights=W[:, :5])


def _turned(R_gt: torch.Tensor, rotvecs: np.ndarray) -> torch.Tensor:
    """``R_gt_n Q_n``: each camera turned in its object frame by the rotation vector ``rotvecs[n]``."""
    return R_gt @ torch.from_numpy(Rotation.from_rotvec(rotvecs).as_matrix())


def test_aligned_median_of_counts_is_the_median_of_the_repeated_set(generator):
    """Brute force: weights 0-3 against the pairs repeated that many times, aligned and summarised again."""
    rng = np.random.default_rng(3)
    R_gt = random_rotations(9, generator, dtype=torch.float64)
    R_est = _turned(R_gt, rng.normal(scale=0.2, size=(9, 3)))
    W = torch.from_numpy(rng.integers(0, 4, size=(20, 9))).double()
    W[W.sum(1) == 0, 0] = 1
    got = aligned_median(R_est, R_gt, W)
    for w, m in zip(W, got):
        rep = torch.repeat_interleave(torch.arange(9), w.long())
        want = viewpoint_report(R_est[rep], R_gt[rep])["geodesic"]["median"]  # numpy's median of an even count
        assert float(m) == pytest.approx(want, abs=1e-9)
    assert float(aligned_median(R_est, R_gt)) == pytest.approx(viewpoint_report(R_est, R_gt)["geodesic"]["median"],
                                                               abs=1e-9)
    with pytest.raises(ValueError, match="positive sum"):
        aligned_median(R_est, R_gt, torch.zeros(9))
    with pytest.raises(ValueError, match="integer counts"):
        aligned_median(R_est, R_gt, torch.full((9,), 0.5))


def test_median_change_resamples_whole_clusters(generator):
    """Analytic: each cluster holds the six turns by ``c`` about +-x, +-y, +-z, so any draw of whole clusters
    aligns with the identity and every error is ``c``: change ``c``, interval ``[c, c]``. Drawing single
    views breaks the symmetry and the interval widens."""
    c = math.radians(4.0)
    turns = np.concatenate([np.eye(3), -np.eye(3)]) * c
    R_gt = random_rotations(30, generator, dtype=torch.float64)
    R_after = _turned(R_gt, np.tile(turns, (5, 1)))
    clusters = [f"object{i // 6}" for i in range(30)]
    res = median_change(R_gt, R_after, R_gt, clusters, resamples=200)
    assert (res["clusters"], res["objects"]) == (5, 30)
    for key in ("change", "low", "high"):
        assert res[key] == pytest.approx(4.0, abs=1e-9)
    views = median_change(R_gt, R_after, R_gt, resamples=200)
    assert views["change"] == pytest.approx(4.0, abs=1e-9) and views["high"] - views["low"] > 0.05
    assert median_change(R_after, R_after, R_gt, clusters, resamples=50)["high"] == 0.0


def test_median_change_interval_is_seeded_and_brackets_a_real_change(generator):
    rng = np.random.default_rng(4)
    R_gt = random_rotations(40, generator, dtype=torch.float64)
    before = _turned(R_gt, rng.normal(scale=math.radians(2), size=(40, 3)))
    after = _turned(R_gt, rng.normal(scale=math.radians(6), size=(40, 3)))
    a = median_change(before, after, R_gt, seed=7)
    assert a == median_change(before, after, R_gt, seed=7)
    assert a != median_change(before, after, R_gt, seed=8)
    assert 0 < a["low"] <= a["change"] <= a["high"]  # three times the noise: worse beyond the interval
    b = median_change(after, before, R_gt, seed=7)
    assert b["change"] == pytest.approx(-a["change"]) and b["high"] < 0


def test_median_change_over_runs_aligns_each_run_and_draws_clusters_across_them(generator):
    """Two runs of the same objects: the same run twice gives the one run's change and interval (a drawn cluster
    counts in both); a run written in a turned frame changes nothing (each run is aligned on its own), while
    pooling its objects into one run does."""
    rng = np.random.default_rng(9)
    R_gt = random_rotations(24, generator, dtype=torch.float64)
    before = _turned(R_gt, rng.normal(scale=math.radians(3), size=(24, 3)))
    after = _turned(R_gt, rng.normal(scale=math.radians(4), size=(24, 3)))
    clusters = [f"model{i % 6}" for i in range(24)]
    one = median_change(before, after, R_gt, clusters, resamples=300)
    twice = median_change(torch.cat([before, before]), torch.cat([after, after]), torch.cat([R_gt, R_gt]),
                          clusters * 2, runs=[0] * 24 + [1] * 24, resamples=300)
    assert twice["runs"] == 2 and twice["clusters"] == 6
    for k in ("change", "low", "high"):
        assert twice[k] == pytest.approx(one[k], abs=1e-9)
    G = torch.from_numpy(Rotation.from_euler("xyz", [30, -50, 70], degrees=True).as_matrix())
    turned = median_change(torch.cat([before, before @ G]), torch.cat([after, after @ G]), torch.cat([R_gt, R_gt]),
                           clusters * 2, runs=[0] * 24 + [1] * 24, resamples=300)
    for k in ("change", "low", "high"):
        assert turned[k] == pytest.approx(one[k], abs=1e-6)
    pooled = median_change(torch.cat([before, before @ G]), torch.cat([after, after @ G]), torch.cat([R_gt, R_gt]),
                           clusters * 2, resamples=300)
    assert abs(pooled["change"] - one["change"]) > 0.01 or abs(pooled["high"] - one["high"]) > 0.01
    only0 = [0, 6, 12, 18]  # a second run holding model0 alone: a third of the resamples draw none of it
    part = median_change(torch.cat([before, before[only0]]), torch.cat([after, after[only0]]),
                         torch.cat([R_gt, R_gt[only0]]), clusters + ["model0"] * 4, runs=[0] * 24 + [1] * 4,
                         resamples=300)
    assert all(math.isfinite(part[k]) for k in ("change", "low", "high")) and part["low"] <= part["high"]
    alone = median_change(before[only0], after[only0], R_gt[only0], resamples=50)["change"]
    assert part["change"] == pytest.approx((one["change"] + alone) / 2, abs=1e-9)  # the mean of the runs' changes


def test_median_change_checks_its_input(generator):
    R = random_rotations(4, generator, dtype=torch.float64)
    with pytest.raises(ValueError, match="rotation sets"):
        median_change(R, R[:3], R)
    with pytest.raises(ValueError, match="3 cluster labels for 4 objects"):
        median_change(R, R, R, ["a", "b", "c"])
    with pytest.raises(ValueError, match="one cluster"):
        median_change(R, R, R, ["a"] * 4)
    with pytest.raises(ValueError, match="3 run labels for 4 objects"):
        median_change(R, R, R, runs=[0, 0, 1])


def _rz(phi: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(Rotation.from_euler("z", np.asarray(phi)[:, None]).as_matrix())


def test_up_axis_errors_ignore_azimuth_and_equal_the_best_turn_about_the_axis(generator):
    """Known values: a turn about the object's up axis costs nothing, a tilt by t costs t. Brute force: the
    error equals the smallest geodesic error over a 0.05-degree grid of turns about +z (scipy's angles)."""
    rng = np.random.default_rng(5)
    R_gt = random_rotations(30, generator, dtype=torch.float64)
    spun = R_gt @ _rz(rng.uniform(-np.pi, np.pi, 30))  # the object turned about its up axis
    assert float(up_axis_errors(spun, R_gt, align=False).max()) < 1e-6
    assert float(geodesic_errors(spun, R_gt).median()) > 30
    tilt = torch.from_numpy(Rotation.from_euler("x", np.full((30, 1), 7.0), degrees=True).as_matrix())
    torch.testing.assert_close(up_axis_errors(R_gt @ tilt, R_gt, align=False), torch.full((30,), 7.0,
                                                                                           dtype=torch.float64))
    R_est = _turned(R_gt, rng.normal(scale=0.3, size=(30, 3)))[:6]
    grid = np.deg2rad(np.arange(0, 360, 0.05))
    for Re, Rg in zip(R_est.numpy(), R_gt[:6].numpy()):
        best = (Rotation.from_matrix(Re[None] @ Rotation.from_euler("z", grid[:, None]).as_matrix()).inv()
                * Rotation.from_matrix(Rg)).magnitude().min()
        got = float(up_axis_errors(torch.from_numpy(Re[None]), torch.from_numpy(Rg[None]), align=False)[0])
        assert got == pytest.approx(np.rad2deg(best), abs=0.03)


def test_up_axis_alignment_finds_the_up_of_a_turned_frame(generator):
    """An estimate written in a frame turned by G0 and spun about the true up per object: the aligned
    error is 0 and the fitted axis is the true up in the estimate's frame; as written the error is the
    frame's tilt."""
    rng = np.random.default_rng(6)
    R_gt = random_rotations(25, generator, dtype=torch.float64)
    G0 = torch.from_numpy(Rotation.from_euler("x", 20, degrees=True).as_matrix())
    R_est = R_gt @ _rz(rng.uniform(-np.pi, np.pi, 25)) @ G0.T  # R_est G0 = R_gt Rz(phi_n)
    assert float(up_axis_errors(R_est, R_gt).max()) < 1e-6
    torch.testing.assert_close(fit_up_axis(R_est, R_gt), G0[:, 2], atol=1e-9, rtol=0)  # R_est^T R_gt e_z = G0 e_z
    torch.testing.assert_close(up_axis_errors(R_est, R_gt, align=False), torch.full((25,), 20.0, dtype=torch.float64))
    R_est[3] = float("nan")
    assert torch.isnan(up_axis_errors(R_est, R_gt)[3]) and float(up_axis_errors(R_est, R_gt)[:3].max()) < 1e-6
    rep = viewpoint_report(R_est, R_gt)
    assert rep["up_axis"]["median"] < 1e-6 and rep["absolute"]["up_axis"]["median"] == pytest.approx(20.0)
    # a global alignment fitted elsewhere gives the axis (G e_z), as it gives the other errors
    assert viewpoint_report(R_est, R_gt, alignment=G0)["up_axis"]["median"] < 1e-6
    assert viewpoint_report(R_est, R_gt, alignment=torch.eye(3, dtype=torch.float64))["up_axis"]["median"] == \
        pytest.approx(20.0)


def test_robust_alignment_resists_outliers(generator):
    R_gt = random_rotations(100, generator, dtype=torch.float64)
    G_true = random_rotations(1, generator, dtype=torch.float64)[0]
    noise = Rotation.from_rotvec(np.random.default_rng(1).normal(scale=0.02, size=(100, 3))).as_matrix()
    R_est = torch.from_numpy(noise) @ R_gt @ G_true.T
    R_est[:30] = random_rotations(30, generator, dtype=torch.float64)  # 30% gross errors
    err = lambda G: math.degrees(Rotation.from_matrix((G @ G_true.T).numpy()).magnitude())  # noqa: E731
    plain = align_rotations(R_est, R_gt)
    robust = align_rotations(R_est, R_gt, robust=True)
    assert err(robust) < 1.0 and err(robust) < err(plain)


def test_align_rotations_ignores_nan_and_checks_input(generator):
    R = random_rotations(5, generator, dtype=torch.float64)
    R_est = R.clone()
    R_est[0] = float("nan")
    assert torch.allclose(align_rotations(R_est, R), torch.eye(3, dtype=torch.float64), atol=1e-10)
    with pytest.raises(ValueError, match="R_est"):
        align_rotations(torch.zeros(3, 3), R)
    with pytest.raises(ValueError, match="same number"):
        align_rotations(R[:2], R)
    with pytest.raises(ValueError, match="no pair"):
        align_rotations(torch.full((2, 3, 3), float("nan")), R[:2])


def test_geodesic_errors_match_scipy(generator):
    A = random_rotations(40, generator, dtype=torch.float64)
    B = random_rotations(40, generator, dtype=torch.float64)
    got = geodesic_errors(A, B)
    ref = np.degrees(Rotation.from_matrix(np.einsum("nij,nkj->nik", A.numpy(), B.numpy())).magnitude())
    np.testing.assert_allclose(got.numpy(), ref, atol=1e-7)
    G = random_rotations(1, generator, dtype=torch.float64)[0]
    assert float(geodesic_errors(B @ G.T, B, G).max()) < 1e-5


def test_angle_errors_known_offsets_and_wrapping():
    az = torch.tensor([math.radians(10.0), math.radians(170.0), 0.3], dtype=torch.float64)
    el = torch.tensor([0.2, 0.1, -0.3], dtype=torch.float64)
    roll = torch.tensor([0.0, 0.05, 3.0], dtype=torch.float64)
    R_gt = rotation_from_azimuth_elevation_roll(az, el, roll)
    R_est = rotation_from_azimuth_elevation_roll(az - math.radians(20.0), el + math.radians(5.0),
                                                 roll + math.radians(7.0))
    e = angle_errors(R_est, R_gt)
    np.testing.assert_allclose(e["azimuth"].numpy(), [20.0] * 3, atol=1e-6)
    np.testing.assert_allclose(e["elevation"].numpy(), [5.0] * 3, atol=1e-6)
    np.testing.assert_allclose(e["roll"].numpy(), [7.0] * 3, atol=1e-6)
    # across the +-180 seam: 175 vs -175 is 10 degrees, not 350
    a = rotation_from_azimuth_elevation_roll(torch.tensor(math.radians(175.0)), torch.tensor(0.1), torch.tensor(0.0))
    b = rotation_from_azimuth_elevation_roll(torch.tensor(math.radians(-175.0)), torch.tensor(0.1), torch.tensor(0.0))
    assert float(angle_errors(a[None], b[None])["azimuth"][0]) == pytest.approx(10.0, abs=1e-3)


def test_summarize_values():
    s = summarize(torch.tensor([1.0, 3.0, 50.0, float("nan"), 20.0]))
    # even count: the mean of the two middle values (numpy's median), not torch.median's lower one
    assert s == {"n": 4, "median": float(np.median([1.0, 3.0, 50.0, 20.0])), "mean": pytest.approx(18.5),
                 "acc_at_30": 0.75}
    assert s["median"] == 11.5
    assert summarize(torch.tensor([4.0, 1.0, 9.0]))["median"] == 4.0
    assert summarize(torch.tensor([]))["n"] == 0
    assert math.isnan(summarize(torch.tensor([float("nan")]))["median"])


def test_report_flags_a_mirrored_frame(generator):
    R_gt = random_rotations(60, generator, dtype=torch.float64)
    Q = random_rotations(1, generator, dtype=torch.float64)[0]
    good = R_gt @ Q.T
    rep = viewpoint_report(good, R_gt)
    assert rep["n"] == 60 and not rep["mirrored"]
    assert rep["geodesic"]["median"] < 1e-5 and rep["geodesic"]["acc_at_30"] == 1.0
    assert rep["azimuth"]["median"] < 1e-4
    json.dumps(rep)
    # the Necker-mirrored solution of the same cameras: reported, not fixed
    bad = necker_mirror(good)
    rep_m = viewpoint_report(bad, R_gt)
    assert rep_m["mirrored"]
    assert rep_m["geodesic"]["median"] > 10.0 and rep_m["mirrored_geodesic"]["median"] < 1e-5
    # proper matrices, and mirroring twice is the identity
    assert torch.allclose(torch.det(bad), torch.ones(60, dtype=torch.float64))
    assert torch.allclose(necker_mirror(bad), good)


def test_report_valid_mask_and_errors(generator):
    R_gt = random_rotations(10, generator, dtype=torch.float64)
    R_est = R_gt.clone()
    R_est[:3] = random_rotations(3, generator, dtype=torch.float64)
    valid = torch.ones(10, dtype=torch.bool)
    valid[:3] = False
    rep = viewpoint_report(R_est, R_gt, valid=valid)
    assert rep["n"] == 7 and rep["geodesic"]["median"] < 1e-5
    assert all(math.isnan(x) for x in rep["per_instance_geodesic"][:3])
    with pytest.raises(ValueError, match="valid"):
        viewpoint_report(R_est, R_gt, valid=torch.ones(4, dtype=torch.bool))
    with pytest.raises(ValueError, match="no valid"):
        viewpoint_report(R_est, R_gt, valid=torch.zeros(10, dtype=torch.bool))


def test_report_gives_the_absolute_error_beside_the_aligned_one():
    """Labels off by one known rotation about the up axis: aligned errors vanish, absolute ones are
    the rotation's angle (geodesic and azimuth), and elevation is untouched."""
    g = torch.Generator().manual_seed(3)
    az = torch.rand(25, generator=g, dtype=torch.float64) * 2 * math.pi
    el = torch.deg2rad(torch.rand(25, generator=g, dtype=torch.float64) * 40)
    R_gt = rotation_from_azimuth_elevation_roll(az, el, torch.zeros(25, dtype=torch.float64))
    R_est = rotation_from_azimuth_elevation_roll(az + math.radians(20), el, torch.zeros(25, dtype=torch.float64))
    rep = viewpoint_report(R_est, R_gt)
    assert rep["geodesic"]["median"] < 1e-5 and rep["azimuth"]["median"] < 1e-5
    ab = rep["absolute"]
    assert ab["geodesic"]["median"] == pytest.approx(20.0, abs=1e-6)
    assert ab["azimuth"]["median"] == pytest.approx(20.0, abs=1e-6) and ab["elevation"]["mean"] < 1e-6


def test_report_with_a_given_alignment(generator):
    """A G fitted on other instances is applied as given, not refitted."""
    R_gt = random_rotations(40, generator, dtype=torch.float64)
    G_true = random_rotations(1, generator, dtype=torch.float64)[0]
    noise = torch.from_numpy(Rotation.from_rotvec(np.random.default_rng(2).normal(scale=0.05, size=(40, 3)))
                             .as_matrix())
    R_est = noise @ R_gt @ G_true.T
    G_train = align_rotations(R_est[:30], R_gt[:30])
    rep = viewpoint_report(R_est[30:], R_gt[30:], alignment=G_train)
    assert torch.allclose(torch.tensor(rep["alignment"], dtype=torch.float64), G_train, atol=1e-12)
    ref = geodesic_errors(R_est[30:], R_gt[30:], G_train)
    assert rep["geodesic"]["median"] == pytest.approx(float(np.median(ref.numpy())), abs=1e-9)
    assert rep["per_instance_geodesic"] == pytest.approx(ref.tolist(), abs=1e-9)
    # the identity as alignment: every error is the angle of G_true (up to the noise)
    rep_id = viewpoint_report(R_est, R_gt, alignment=torch.eye(3, dtype=torch.float64))
    angle = math.degrees(Rotation.from_matrix(G_true.numpy()).magnitude())
    assert rep_id["geodesic"]["median"] == pytest.approx(angle, abs=8.0)
    assert rep_id["geodesic"]["median"] > viewpoint_report(R_est, R_gt)["geodesic"]["median"] + 5.0
    with pytest.raises(ValueError, match="alignment"):
        viewpoint_report(R_est, R_gt, alignment=torch.eye(2))


# --------------------------------------------------------------------------- real data


def _camera_run(run, classes: dict, groups: int = 1, seconds: float = 1.0, choice: str = "refined") -> None:
    """A hand-made ``reconstruct`` output folder: ``classes`` = {class: {annotation id: refined R (3x3) or None}},
    every object's ``camera_choice`` ``choice``; ``summary.json`` names every class, with its SfM start, shapes
    kept and seconds."""
    entries = {}
    for cls, cams in classes.items():
        (run / cls).mkdir(parents=True)
        doc = {str(k): ({"refined": {"R": np.asarray(R).tolist()}, "camera_choice": choice} if R is not None
                        else {"camera_choice": "none"}) for k, R in cams.items()}
        (run / cls / "cameras.json").write_text(json.dumps({"class": cls, "cameras": doc}))
        entries[cls] = {"objects": len(cams), "seconds": {"sfm": seconds, "refine": seconds / 2, "carve": 9.0},
                        "sfm": {"start": {"kept": "cold"}}, "sfm_groups": {"groups": groups}}
    (run / "summary.json").write_text(json.dumps({"torch_threads": 2, "classes": entries}))


def test_compare_camera_runs_identical_runs_agree_at_zero(tmp_path):
    rots = Rotation.random(6, random_state=1).as_matrix()
    classes = {"car": {i: rots[i] for i in range(3)}, "bus": {i + 3: rots[i + 3] for i in range(3)}}
    _camera_run(tmp_path / "a", classes)
    _camera_run(tmp_path / "b", classes)
    rec = compare_camera_runs(tmp_path / "a", tmp_path / "b")
    assert set(rec["classes"]) == {"bus", "car"} and rec["not_compared"] == {}
    for row in rec["classes"].values():
        assert row["compared"] == 3 and row["median_deg"] == 0.0 and row["max_deg"] == 0.0 and row["turned"] == {}
        assert row["camera_choice_differs"] == 0 and row["sfm_start"] == ["cold", "cold"]
        assert row["viewpoint_seconds"] == {"cpu": 1.5, "cuda": 1.5}  # SfM + refinement, not carving
    assert rec["largest_median_deg"] == 0.0 and rec["agree"] is True
    assert rec["viewpoint_seconds"] == {"cpu": 3.0, "cuda": 3.0} and rec["torch_threads"] == {"cpu": 2, "cuda": 2}


def test_compare_camera_runs_measures_known_turns_against_scipy(tmp_path):
    """Every object of the second run turned about its own random axis by a known angle: the median and the
    largest angle are scipy's (the relative rotation's magnitude) and the nominal ones."""
    turns = np.array([0.0, 0.3, 12.5, 37.0])
    rots = Rotation.random(4, random_state=2)
    axes = Rotation.random(4, random_state=3).apply([1.0, 0.0, 0.0])
    turned = Rotation.from_rotvec(axes * np.radians(turns)[:, None]) * rots
    _camera_run(tmp_path / "a", {"car": dict(enumerate(rots.as_matrix()))})
    _camera_run(tmp_path / "b", {"car": dict(enumerate(turned.as_matrix()))}, groups=2)
    row = compare_camera_runs(tmp_path / "a", tmp_path / "b", labels=("x", "y"), tolerance_deg=5.0)["classes"]["car"]
    ref = np.degrees((rots * turned.inv()).magnitude())
    np.testing.assert_allclose(ref, turns, atol=1e-9)  # the reference sees the nominal turns
    assert row["median_deg"] == pytest.approx(float(np.median(ref)), abs=1e-3)  # 6.4: mean of the middle two
    assert row["max_deg"] == pytest.approx(37.0, abs=1e-3)
    assert list(row["turned"]) == ["3", "2"]  # over RUN_TURNED_DEG (1 degree), largest first; 0.3 is not
    np.testing.assert_allclose(list(row["turned"].values()), ref[[3, 2]], atol=0.01)
    assert row["shape_groups"] == [1, 2] and set(row["viewpoint_seconds"]) == {"x", "y"}
    rec = compare_camera_runs(tmp_path / "a", tmp_path / "b")
    assert rec["agree"] is False and rec["largest_median_deg"] == pytest.approx(6.4, abs=1e-3)


def test_compare_camera_runs_reports_classes_one_run_lacks(tmp_path):
    """A class the second run never reached, one whose cameras.json is missing, one without a refined camera on
    one side: each named with its reason, the rest compared; no class at all does not agree."""
    R = Rotation.random(3, random_state=4).as_matrix()
    _camera_run(tmp_path / "a", {"car": {1: R[0], 5: R[1]}, "sofa": {2: R[1]}, "train": {3: R[2]}, "tv": {4: R[0]}})
    _camera_run(tmp_path / "b", {"car": {1: R[0]}, "train": {3: R[2]}, "tv": {4: None}}, choice="sfm")
    (tmp_path / "b" / "train" / "cameras.json").unlink()
    rec = compare_camera_runs(tmp_path / "a", tmp_path / "b")
    assert set(rec["classes"]) == {"car"} and rec["agree"] is True
    assert rec["not_compared"] == {"sofa": "not reached by the cuda run", "train": "no cameras.json in the cuda run",
                                   "tv": "no object with a refined camera in both runs"}
    # car's object 5 is only in the first run: missing from the second, not a differing choice
    assert rec["classes"]["car"]["compared"] == 1 and rec["classes"]["car"]["camera_choice_differs"] == 1
    assert rec["classes"]["car"]["missing"] == {"cpu": 0, "cuda": 1}
    empty = compare_camera_runs(tmp_path / "a", tmp_path / "nothing")
    assert empty["classes"] == {} and empty["agree"] is False and empty["largest_median_deg"] is None
    assert empty["not_compared"]["car"] == "not reached by the cuda run"
    with pytest.raises(ValueError, match="two different names"):
        compare_camera_runs(tmp_path / "a", tmp_path / "b", labels=("cpu", "cpu"))


def test_compare_camera_runs_merges_a_run_split_across_folders(tmp_path):
    """One side made by two processes (a folder each): their classes together are compared with the other side;
    a class both folders hold is read from the first; a folder without summary.json adds nothing."""
    rots = Rotation.random(4, random_state=5)
    turned = Rotation.from_rotvec([0.0, 0.0, np.radians(20.0)]) * rots
    _camera_run(tmp_path / "a", {"car": dict(enumerate(rots.as_matrix()[:2])), "bus": {2: rots.as_matrix()[2]}})
    _camera_run(tmp_path / "b1", {"car": dict(enumerate(rots.as_matrix()[:2]))})
    _camera_run(tmp_path / "b2", {"bus": {2: turned.as_matrix()[2]}, "car": dict(enumerate(turned.as_matrix()[:2]))})
    (tmp_path / "b3").mkdir()
    rec = compare_camera_runs(tmp_path / "a", [tmp_path / "b1", tmp_path / "b2", tmp_path / "b3"])
    assert set(rec["classes"]) == {"bus", "car"} and rec["not_compared"] == {}
    assert rec["classes"]["car"]["max_deg"] == 0.0  # from b1, listed first
    assert rec["classes"]["bus"]["median_deg"] == pytest.approx(20.0, abs=1e-3)
    assert rec["torch_threads"] == {"cpu": 2, "cuda": 2}


def _voc_aeroplanes(root, canvas=128):
    """Berkeley keypoints + figure-ground polygons of the VOC aeroplanes, in canvas pixels.

    Each object is scaled so its polygon's larger side spans 80% of the canvas and
    centred; masks are the polygons rasterised by skimage. Objects without a
    polygon keep an empty mask.
    """
    import xml.etree.ElementTree as ET

    from skimage.draw import polygon2mask

    files = sorted((root / "pascal_voc_aeroplane" / "keypoints").glob("*.xml"))
    recs, names = [], []
    for f in files:
        a = ET.parse(f).getroot()
        kps = {k.get("name"): (float(k.get("x")), float(k.get("y")), k.get("visible") == "1")
               for k in a.iter("keypoint")}
        names += [n for n in kps if n not in names]
        seg = [s for s in a.iter("segment") if s.get("name") == "foreground"]
        poly = None
        if seg:
            poly = np.stack([np.array(seg[0].get("x").split(), float), np.array(seg[0].get("y").split(), float)], 1)
        recs.append((f.stem, kps, poly))
    n, k = len(recs), len(names)
    kp = np.zeros((n, k, 2))
    vis = np.zeros((n, k), bool)
    masks = np.zeros((n, canvas, canvas), bool)
    for i, (_, kps, poly) in enumerate(recs):
        pts = poly if poly is not None else np.array([v[:2] for v in kps.values() if v[2]] or [[0.0, 0.0]])
        lo, hi = pts.min(0), pts.max(0)
        scale = 0.8 * canvas / max(float((hi - lo).max()), 1e-6)
        off = canvas / 2 - scale * (lo + hi) / 2
        for j, name in enumerate(names):
            if name in kps and kps[name][2]:
                kp[i, j] = scale * np.array(kps[name][:2]) + off
                vis[i, j] = True
        if poly is not None:
            masks[i] = polygon2mask((canvas, canvas), (scale * poly + off)[:, ::-1])
    return [r[0] for r in recs], names, torch.tensor(kp, dtype=torch.float32), torch.tensor(vis), torch.tensor(masks)


@pytest.mark.shared
def test_viewpoints_of_real_voc_aeroplanes(shared_data):
    """SfM + refinement on the 330 VOC aeroplanes (with mirrors) vs PASCAL3D+ viewpoints."""
    from carvi_torch.viewpoints.camera_fit import refine_cameras
    from carvi_torch.sdf import distance_to_mask
    from carvi_torch.viewpoints.sfm import keypoint_side, rigid_sfm

    ids, names, kp, vis, masks = _voc_aeroplanes(shared_data)
    canvas = masks.shape[-1]
    # flip pairs from the Berkeley names (L_WingTip / R_WingTip, Left_Engine_Front / Right_...)
    def key(nm):
        return nm.lower().replace("left", "").replace("right", "").replace("l_", "").replace("r_", "")

    pairs = [(i, j) for i, a in enumerate(names) for j, b in enumerate(names)
             if keypoint_side(a) == "left" and keypoint_side(b) == "right" and key(a) == key(b)]
    assert len(pairs) == 5
    perm = list(range(len(names)))
    for i, j in pairs:
        perm[i], perm[j] = j, i
    kp_m = kp[:, perm].clone()
    kp_m[..., 0] = canvas - 1 - kp_m[..., 0]
    KP, VIS = torch.cat([kp, kp_m]), torch.cat([vis, vis[:, perm]])
    MS = torch.cat([masks, masks.flip(-1)])
    sfm = rigid_sfm(KP, VIS, keypoint_names=names, flip_pairs=pairs, left_convention="object")
    assert not sfm.planar
    assert sfm.reflection_votes["decided_by"] == "visibility"
    # objects with no visible keypoint are reported, not dropped silently
    assert (~sfm.valid).sum() > 0 and all(sfm.reasons[i] for i in torch.nonzero(~sfm.valid)[:, 0].tolist())
    ref = refine_cameras(sfm.shape, sfm.cameras, KP, VIS, distance_to_mask(MS))
    assert bool((ref.energy_after <= ref.energy_before).all())

    gt = json.loads((shared_data / "pascal_voc_aeroplane" / "viewpoints_dev.json").read_text())
    idx = [i for i, r in enumerate(ids) if r in gt]
    R_gt = torch.tensor([gt[ids[i]]["R"] for i in idx], dtype=torch.float64)
    rep_sfm = viewpoint_report(sfm.cameras.R[idx].double(), R_gt, valid=sfm.valid[idx])
    rep_ref = viewpoint_report(ref.cameras.R[idx].double(), R_gt, valid=sfm.valid[idx])
    assert rep_sfm["n"] >= 150
    assert not rep_sfm["mirrored"] and not rep_ref["mirrored"]
    # measured: SfM 12.0 deg, refined 11.5 deg median geodesic error (azimuth 9.8, elevation 3.5)
    assert rep_sfm["geodesic"]["median"] < 15.0
    assert rep_ref["geodesic"]["median"] < 15.0
    assert rep_ref["geodesic"]["median"] <= rep_sfm["geodesic"]["median"] + 0.5
    assert rep_ref["elevation"]["median"] < 6.0

    # written in the canonical frame (shipped aeroplane template, Berkeley names through the aliases), the
    # labels need no fitted rotation: measured geodesic 11.3, azimuth 9.6, elevation 3.6 degrees
    from carvi_torch.viewpoints.frame import canonical_frame
    from carvi_torch.viewpoints.sfm import symmetry_plane

    n = len(ids)
    seen = sfm.valid[:n]
    frame = canonical_frame("best", "aeroplane", names, [sfm.shape], sfm.shape, symmetry_plane(sfm.shape, pairs),
                            ref.cameras.R[:n][seen])
    assert frame.kind == "template" and frame.info["matched_keypoints"] >= 8
    R_canon = frame.cameras(ref.cameras[:n]).R[idx].double()
    absolute = viewpoint_report(R_canon, R_gt, valid=seen[idx])["absolute"]
    assert absolute["geodesic"]["median"] <= 12.0
    assert absolute["azimuth"]["median"] <= 10.0
    assert absolute["elevation"]["median"] <= 5.0

    # the handedness rule alone (Berkeley names: L_ is the aeroplane's own left) agrees
    hand = rigid_sfm(KP, VIS, keypoint_names=names, flip_pairs=pairs, left_convention="object",
                     vote_margin=1.0, polish_iters=5)
    assert hand.reflection_votes["decided_by"] == "handedness"
    assert not viewpoint_report(hand.cameras.R[idx].double(), R_gt, valid=hand.valid[idx])["mirrored"]
