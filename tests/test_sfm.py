"""Tests for carvi_torch.viewpoints.sfm: rigid factorisation with missing data, reflection, planar sets."""
from __future__ import annotations

import contextlib
import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial import procrustes
from scipy.spatial.transform import Rotation

from conftest import render_cad_class
from carvi_torch.cameras import ScaledOrthographic, nearest_scaled_rotation, random_rotations, rotation_about_axis
from carvi_torch.viewpoints.camera_fit import refine_cameras
from carvi_torch.viewpoints.sfm import (
    SfMResult,
    keypoint_end,
    keypoint_side,
    resect_cameras,
    rigid_sfm,
    scaled_stiefel,
    symmetry_plane,
    triangulate,
)

F = np.diag([1.0, 1.0, -1.0])


# --------------------------------------------------------------------------- helpers


def make_class(seed, n=200, k=12, missing=0.4, noise=0.0, visibility="random", axes=(1.0, 0.8, 0.6),
               shape=None, rotations=None):
    """A rigid shape seen by ``n`` random scaled orthographic cameras (canvas-like pixels).

    ``missing``: fraction of keypoints hidden in every instance; ``visibility``:
    ``"random"`` (no depth cue), ``"depth"`` (the farthest are hidden: self-occlusion)
    or ``"reversed"`` (the nearest are hidden). ``noise``: Gaussian std per coordinate
    as a fraction of the instance's projected extent (larger bounding-box side).
    """
    g = torch.Generator().manual_seed(seed)
    if shape is None:
        S = torch.randn(k, 3, generator=g, dtype=torch.float64) * torch.tensor(axes, dtype=torch.float64)
        S = S - S.mean(0)
    else:
        S = shape.double()
        k = S.shape[0]
    R = random_rotations(n, g, dtype=torch.float64) if rotations is None else rotations.double()
    s = 40.0 + 10.0 * torch.rand(n, generator=g, dtype=torch.float64)
    t = 64.0 + 5.0 * torch.randn(n, 2, generator=g, dtype=torch.float64)
    cams = ScaledOrthographic(R, s, t)
    kp = cams.project(S)
    extent = (kp.amax(1) - kp.amin(1)).amax(-1)
    kp = kp + noise * extent[:, None, None] * torch.randn(kp.shape, generator=g, dtype=torch.float64)
    m = round(missing * k)
    if visibility == "random":
        rank = torch.rand(n, k, generator=g).argsort(1).argsort(1)
    elif visibility in ("depth", "reversed"):
        z = cams.depth(S)
        z = z if visibility == "depth" else -z
        rank = (-z).argsort(1).argsort(1)  # 0 = farthest
    else:
        raise ValueError(visibility)
    vis = rank >= m
    return {"S": S, "R": R, "s": s, "t": t, "kp": kp.float(), "vis": vis}


def scipy_alignment(R_est, R_gt):
    """Errors (deg) after the best global rotation, by scipy's chordal mean of R_est^T R_gt."""
    Re = np.asarray(R_est, dtype=np.float64)
    Rg = np.asarray(R_gt, dtype=np.float64)
    B = np.einsum("nji,njk->nik", Re, Rg)
    G = Rotation.from_matrix(B).mean().as_matrix()
    err = Rotation.from_matrix(np.einsum("nij,jk,nlk->nil", Re, G, Rg)).magnitude()
    return np.degrees(err), G


def errors_any_reflection(R_est, R_gt):
    """Errors of the better of the frame and its Necker mirror (random visibility cannot tell)."""
    e1, _ = scipy_alignment(R_est, R_gt)
    e2, _ = scipy_alignment(F @ np.asarray(R_est, dtype=np.float64) @ F, R_gt)
    return e1 if np.median(e1) <= np.median(e2) else e2


def assert_cameras_proper(cams: ScaledOrthographic, atol=1e-4):
    R = cams.R.double()
    eye = torch.eye(3, dtype=torch.float64).expand_as(R)
    assert torch.allclose(R @ R.transpose(1, 2), eye, atol=atol)
    assert torch.allclose(torch.det(R), torch.ones(len(cams), dtype=torch.float64), atol=atol)
    assert bool((cams.s > 0).all())


# --------------------------------------------------------------------------- scaled_stiefel


def test_scaled_stiefel_matches_svd_projection(generator):
    M = torch.randn(500, 2, 3, generator=generator, dtype=torch.float64)
    M[0, 1] = 2.0 * M[0, 0]  # rank 1: SVD fallback
    out = scaled_stiefel(M)
    # independent reference: numpy SVD, c U V^T with c the mean singular value
    U, sv, Vt = np.linalg.svd(M.numpy(), full_matrices=False)
    ref = sv.mean(-1)[:, None, None] * (U @ Vt)
    np.testing.assert_allclose(out[1:].numpy(), ref[1:], atol=1e-9)
    # rank-1 block: rows orthogonal with equal norms (the projection is not unique)
    G = out[0] @ out[0].T
    assert abs(float(G[0, 1])) < 1e-9 and abs(float(G[0, 0] - G[1, 1])) < 1e-9
    R, s = nearest_scaled_rotation(M[1:])
    assert torch.allclose(out[1:], s[:, None, None] * R[:, :2], atol=1e-9)


def test_scaled_stiefel_is_differentiable():
    M = torch.randn(4, 2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(scaled_stiefel, (M,))


# --------------------------------------------------------------------------- names


@pytest.mark.parametrize(
    "name,side,end",
    [
        ("L_WingTip", "left", None),
        ("Left_Wing_Base", "left", None),
        ("R_Stabilizer", "right", None),
        ("right_front_wheel", "right", "front"),
        ("leftcorner_windshield", "left", None),
        ("NoseTip", None, "front"),
        ("noselanding", None, "front"),
        ("tail", None, "back"),
        ("left_back_wheel", "left", "back"),
        ("headlight_center", None, "front"),
        ("Top_Rudder", None, None),
        ("rear_left", "left", "back"),
        ("front_back", None, None),
    ],
)
def test_keypoint_side_and_end(name, side, end):
    assert keypoint_side(name) == side
    assert keypoint_end(name) == end


# --------------------------------------------------------------------------- accuracy


def test_missing_data_noise_free_recovers_every_camera():
    d = make_class(0, n=200, k=12, missing=0.4)
    res = rigid_sfm(d["kp"], d["vis"])
    assert isinstance(res, SfMResult)
    assert bool(res.valid.all()) and res.shape.shape == (12, 3)
    assert float(res.residual.max()) < 1e-2
    err = errors_any_reflection(res.cameras.R, d["R"])
    assert err.max() < 0.5, f"max camera error {err.max():.3f} deg"
    assert_cameras_proper(res.cameras)
    # shape up to similarity (scipy's Procrustes allows a reflection)
    _, _, disparity = procrustes(d["S"].numpy(), res.shape.double().numpy())
    assert disparity < 1e-8
    # translations and scales reproduce the keypoints, including the hidden ones
    P = res.cameras.project(res.shape).double()
    true = ScaledOrthographic(d["R"], d["s"], d["t"]).project(d["S"])
    assert float((P - true).norm(dim=-1).max()) < 0.05


def test_missing_data_with_noise_median_within_two_degrees():
    d = make_class(1, n=200, k=12, missing=0.4, noise=0.01)
    res = rigid_sfm(d["kp"], d["vis"])
    err = errors_any_reflection(res.cameras.R, d["R"])
    assert np.median(err) < 2.0, f"median {np.median(err):.2f} deg"
    # the residual is at the noise level (std 1% of extents of ~100-200 px per coordinate)
    assert 0.3 < float(res.residual.median()) < 3.0


def test_visibility_vote_gives_the_true_frame():
    d = make_class(2, n=150, k=12, missing=0.35, visibility="depth")
    res = rigid_sfm(d["kp"], d["vis"])
    assert res.reflection_votes["decided_by"] == "visibility"
    assert res.reflection_votes["for"] > res.reflection_votes["against"]
    err, G = scipy_alignment(res.cameras.R, d["R"])  # proper alignment only
    assert err.max() < 0.5
    # the mirrored hypothesis fits badly: the frame is not a mirror image
    err_m, _ = scipy_alignment(F @ res.cameras.R.double().numpy() @ F, d["R"])
    assert np.median(err_m) > 10.0


def test_visibility_vote_follows_the_cue():
    # hiding the *nearest* keypoints is a wrong cue: the vote must then pick the mirror
    d = make_class(2, n=150, k=12, missing=0.35, visibility="reversed")
    res = rigid_sfm(d["kp"], d["vis"])
    assert res.reflection_votes["decided_by"] == "visibility"
    err_m, _ = scipy_alignment(F @ res.cameras.R.double().numpy() @ F, d["R"])
    assert err_m.max() < 0.5


def _named_class(seed, left_convention_truth="object"):
    """A bilaterally symmetric object: +z up, front towards -y; its own left is +x.

    (With up = +z and front = -y, a person's left is up x front = +x.)
    """
    g = torch.Generator().manual_seed(seed)
    half = torch.tensor([[0.6, -0.8, 0.1], [0.5, 0.7, 0.3], [0.3, 0.0, -0.4], [0.7, 0.4, 0.2]], dtype=torch.float64)
    half = half + 0.05 * torch.randn(half.shape, generator=g, dtype=torch.float64)
    mid = torch.tensor([[0.0, -1.0, 0.0], [0.0, 1.0, 0.2], [0.0, 0.2, 0.6]], dtype=torch.float64)
    left = half
    right = half * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)
    S = torch.cat([left, right, mid])
    names = ["left_front_wheel", "left_back_door", "left_side", "left_mirror",
             "right_front_wheel", "right_back_door", "right_side", "right_mirror",
             "nose", "tail", "roof"]
    if left_convention_truth == "viewer":
        names = [n.replace("left", "TMP").replace("right", "left").replace("TMP", "right") for n in names]
    pairs = [(0, 4), (1, 5), (2, 6), (3, 7)]
    # upright photos: azimuth anywhere, elevation 0..40 deg, small roll
    n = 120
    az = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    el = torch.rand(n, generator=g, dtype=torch.float64) * math.radians(40)
    roll = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * math.radians(20)
    from carvi_torch.cameras import rotation_from_azimuth_elevation_roll

    R = rotation_from_azimuth_elevation_roll(az, el, roll)
    return S, names, pairs, R


@pytest.mark.parametrize("convention", ["object", "viewer"])
def test_handedness_rule_decides_a_close_vote(convention):
    S, names, pairs, R = _named_class(3, convention)
    d = make_class(3, n=R.shape[0], shape=S, rotations=R, missing=0.3, visibility="random")
    res = rigid_sfm(d["kp"], d["vis"], keypoint_names=names, flip_pairs=pairs, left_convention=convention)
    assert res.reflection_votes["decided_by"] == "handedness"
    assert res.reflection_votes["handedness"] > 0
    err, _ = scipy_alignment(res.cameras.R, d["R"])
    assert err.max() < 0.5
    # the wrong convention must give the mirror image
    other = "viewer" if convention == "object" else "object"
    res2 = rigid_sfm(d["kp"], d["vis"], keypoint_names=names, flip_pairs=pairs, left_convention=other)
    err2, _ = scipy_alignment(F @ res2.cameras.R.double().numpy() @ F, d["R"])
    assert err2.max() < 0.5


def test_close_vote_without_names_is_reported():
    d = make_class(4, n=30, k=10, missing=0.3, visibility="random")
    res = rigid_sfm(d["kp"], d["vis"])
    assert res.reflection_votes["decided_by"] == "visibility (weak)"
    assert any("reflection ambiguous" in p for p in res.problems)


def test_mirrored_copies_are_consistent_with_symmetry_plane():
    S, names, pairs, R = _named_class(5)
    width = 128.0
    d = make_class(5, n=R.shape[0], shape=S, rotations=R, missing=0.3, visibility="depth")
    kp, vis = d["kp"], d["vis"]
    # the pipeline's mirrored copies: x' = W - 1 - x and left/right labels swapped
    perm = list(range(S.shape[0]))
    for i, j in pairs:
        perm[i], perm[j] = j, i
    kp_m = kp[:, perm].clone()
    kp_m[..., 0] = width - 1 - kp_m[..., 0]
    vis_m = vis[:, perm]
    res = rigid_sfm(torch.cat([kp, kp_m]), torch.cat([vis, vis_m]), keypoint_names=names, flip_pairs=pairs)
    n = kp.shape[0]
    assert float(res.residual.max()) < 1e-2
    P = symmetry_plane(res.shape, pairs)
    mirrored = res.cameras[:n].mirror(width, reflection=P)
    # the mirror of each original camera is the camera SfM found for its flipped copy
    ang = torch.rad2deg(torch.arccos(((mirrored.R * res.cameras.R[n:]).sum((1, 2)) - 1).clamp(-2, 2) / 2))
    assert float(ang.max()) < 0.5
    assert torch.allclose(mirrored.t, res.cameras.t[n:], atol=1e-2)


# --------------------------------------------------------------------------- planar


def _planar_class(seed, tilt_deg, n=100, k=8, missing=0.25):
    g = torch.Generator().manual_seed(seed)
    S = torch.randn(k, 3, generator=g, dtype=torch.float64)
    S[:, 2] = 0.0
    S = S - S.mean(0)
    roll = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2 * math.pi
    axis = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axis[:, 2] = 0.0
    tilt = torch.deg2rad(tilt_deg * torch.rand(n, generator=g, dtype=torch.float64))
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(n, 3)
    R = rotation_about_axis(z, roll) @ rotation_about_axis(axis, tilt)
    return make_class(seed, n=n, shape=S, rotations=R, missing=missing)


@pytest.mark.parametrize("tilt", [0.0, 30.0])
def test_planar_keypoints_no_nan_and_in_plane_cameras(tilt):
    d = _planar_class(6, tilt)
    res = rigid_sfm(d["kp"], d["vis"])
    assert res.planar
    assert bool(torch.isfinite(res.shape).all()) and bool(torch.isfinite(res.cameras.R).all())
    assert_cameras_proper(res.cameras)
    assert float(res.shape[:, 2].abs().max()) < 1e-6
    # every keypoint, hidden ones included, lands where the true camera puts it
    P = res.cameras.project(res.shape).double()
    true = ScaledOrthographic(d["R"], d["s"], d["t"]).project(d["S"])
    assert float((P - true).norm(dim=-1).max()) < 0.05
    # in-plane blocks A_n = M_n B (2x2) equal the true ones up to one global 2x2 map
    A_est = res.cameras.M.double()[:, :, :2]
    A_true = d["s"][:, None, None] * d["R"][:, :2, :2]
    X = torch.linalg.lstsq(A_est.reshape(-1, 2), A_true.reshape(-1, 2)).solution
    assert float((A_est @ X - A_true).abs().max()) < 1e-3 * float(d["s"].mean())
    if tilt == 0.0:
        # fronto-parallel views: the gauge is a similarity and every roll is exact
        sv = torch.linalg.svdvals(X)
        assert float(sv[0] / sv[1]) < 1.0 + 1e-4
        roll_est = torch.atan2(A_est[:, 1, 0], A_est[:, 0, 0])
        roll_true = torch.atan2(A_true[:, 1, 0], A_true[:, 0, 0])
        diff = torch.remainder(roll_est - roll_true + math.pi, 2 * math.pi) - math.pi
        diff = torch.rad2deg(torch.remainder(diff - diff[0] + math.pi, 2 * math.pi) - math.pi)
        assert float(diff.abs().max()) < 0.5


def test_planar_forced_off_does_not_crash():
    d = _planar_class(7, 20.0)
    res = rigid_sfm(d["kp"], d["vis"], planar=False, max_outer=30)
    assert not res.planar
    assert bool(torch.isfinite(res.cameras.R).all()) and bool(torch.isfinite(res.shape).all())


def test_non_planar_class_is_not_called_planar():
    d = make_class(8, n=100, k=10, missing=0.3, noise=0.01)
    assert not rigid_sfm(d["kp"], d["vis"]).planar


# --------------------------------------------------------------------------- rigid subset, triangulation


def test_rigid_subset_and_triangulated_rest():
    d = make_class(9, n=80, k=12, missing=0.3)
    vis = d["vis"].clone()
    vis[:, 11] = False
    vis[0, 11] = True  # keypoint 11 seen once: cannot be triangulated
    rigid = list(range(8))
    res = rigid_sfm(d["kp"], vis, rigid_keypoints=rigid)
    assert res.rigid_keypoints == rigid
    assert bool(torch.isnan(res.shape[11]).all())
    assert any("[11]" in p for p in res.problems)
    # keypoints 8..10 were triangulated: the whole shape matches the truth up to similarity
    _, _, disp = procrustes(d["S"][:11].numpy(), res.shape[:11].double().numpy())
    assert disp < 1e-8


def test_fit_under_inference_mode_gives_ordinary_tensors_equal_to_a_grad_mode_fit(monkeypatch):
    """The factorisation, the bundle polish and keypoint-only camera fits run under inference mode (less
    dispatch per tensor op). Their results must be ordinary tensors (later code writes into them and
    differentiates through them) and the same bit for bit as the fit with inference mode off."""
    d = make_class(3, n=60, k=10, missing=0.3, noise=1.0)
    res = rigid_sfm(d["kp"], d["vis"])

    def parts(r):
        f = refine_cameras(r.shape, r.cameras, d["kp"], d["vis"], None, max_iters=5)
        return [r.shape, r.cameras.R, r.cameras.s, r.cameras.t, r.residual, f.cameras.R, f.energy_after]

    outs = parts(res)
    assert not any(x.is_inference() for x in outs)
    res.cameras.t[0] += 0.0  # an in-place write outside inference mode raises on an inference tensor
    S = res.shape.clone().requires_grad_(True)
    (S * res.cameras.s[:1]).sum().backward()
    assert S.grad is not None
    monkeypatch.setattr(torch, "inference_mode", lambda mode=True: contextlib.nullcontext())
    res2 = rigid_sfm(d["kp"], d["vis"])
    assert all(torch.equal(a, b) for a, b in zip(outs, parts(res2)))
    assert res.history == res2.history and len(res.history) > 2


def test_triangulate_known_points(generator):
    X = torch.randn(5, 3, generator=generator, dtype=torch.float64)
    cams = ScaledOrthographic(random_rotations(6, generator, dtype=torch.float64),
                              torch.rand(6, generator=generator, dtype=torch.float64) + 1.0,
                              torch.randn(6, 2, generator=generator, dtype=torch.float64))
    kp = cams.project(X)
    vis = torch.ones(6, 5, dtype=torch.bool)
    vis[:, 4] = False
    vis[2, 4] = True
    out = triangulate(cams, kp, vis)
    assert torch.allclose(out[:4], X[:4], atol=1e-8)
    assert bool(torch.isnan(out[4]).all())


def test_resect_cameras_recovers_noise_free_cameras():
    """Known shape, 40% of keypoints hidden (7 of 12 visible), noise-free: every camera exactly;
    NaN shape rows and non-finite coordinates are ignored."""
    d = make_class(4, n=50, k=12, missing=0.4)
    S = d["S"].clone()
    kp = d["kp"].double().clone()
    S[3] = float("nan")  # a keypoint the shape lacks
    kp[0, d["vis"][0].nonzero()[0, 0]] = float("nan")  # a visible entry without coordinates
    cams, ok = resect_cameras(S, kp, d["vis"])
    assert bool(ok.all())
    # float32 keypoints and the 1e-6 relative pull towards M = 0: 1e-4 of a unit rotation entry
    assert torch.allclose(cams.R, d["R"], atol=1e-4) and torch.allclose(cams.s, d["s"], rtol=1e-4)
    assert torch.allclose(cams.t, d["t"], atol=1e-2)
    assert cams.R.dtype == torch.float64


def test_resect_cameras_with_noise_is_a_close_start():
    """With 1% noise the closed form is a start, not the optimum (the affine fit is projected onto
    scaled rotations afterwards): median within 2.5 degrees of the true camera, all within 10."""
    from carvi_torch.evaluation.viewpoint_metrics import geodesic_errors

    d = make_class(5, n=200, k=12, missing=0.3, noise=0.01)
    cams, ok = resect_cameras(d["S"], d["kp"], d["vis"])
    err = geodesic_errors(cams.R.double(), d["R"])
    assert bool(ok.all()) and float(err.median()) < 2.5 and float(err.max()) < 10.0, err.sort().values[-10:]


def test_resect_cameras_without_enough_keypoints_says_so():
    d = make_class(6, n=4, k=8, missing=0.0)
    vis = d["vis"].clone()
    vis[1] = False
    vis[2, 1:] = False  # one keypoint
    cams, ok = resect_cameras(d["S"], d["kp"], vis)
    assert ok.tolist() == [True, False, False, True]
    assert bool(torch.isfinite(cams.R).all() and torch.isfinite(cams.t).all() and (cams.s > 0).all())
    # a shape with no extent leaves every system singular: no camera, no exception
    cams0, ok0 = resect_cameras(torch.zeros(8, 3), d["kp"], d["vis"])
    assert not bool(ok0.any()) and bool(torch.isfinite(cams0.R).all())


# --------------------------------------------------------------------------- bad input


def test_all_instances_with_two_keypoints():
    d = make_class(10, n=40, k=8, missing=0.75)  # 2 visible each
    res = rigid_sfm(d["kp"], d["vis"])
    assert bool(res.valid.all())
    assert any("3 or more" in p for p in res.problems)
    assert any("40 instance(s) see only 2" in p for p in res.problems)
    assert bool(torch.isfinite(res.cameras.R).all())


def test_all_instances_with_one_keypoint():
    d = make_class(11, n=10, k=6, missing=5 / 6)
    res = rigid_sfm(d["kp"], d["vis"])
    assert not bool(res.valid.any())
    assert all("only 1 visible" in r for r in res.reasons)
    assert any("SfM not run" in p for p in res.problems)
    assert bool(torch.isnan(res.shape).all())
    assert bool(torch.isnan(res.residual).all())
    json.dumps(res.summary())


def test_two_instances_only():
    d = make_class(12, n=2, k=10, missing=0.0)
    res = rigid_sfm(d["kp"], d["vis"])
    assert bool(res.valid.all())
    assert any("depth is not determined" in p for p in res.problems)
    assert bool(torch.isfinite(res.shape).all()) and bool(torch.isfinite(res.cameras.R).all())
    assert float(res.residual.max()) < 1e-2


def test_never_visible_keypoint_and_invalid_instance():
    d = make_class(13, n=60, k=10, missing=0.2)
    vis = d["vis"].clone()
    vis[:, 3] = False
    vis[5] = False
    vis[5, 0] = True
    res = rigid_sfm(d["kp"], vis)
    assert res.never_visible == [3]
    assert bool(torch.isnan(res.shape[3]).all())
    assert not bool(res.valid[5]) and "only 1 visible" in res.reasons[5]
    assert bool(res.valid.sum() == 59)
    assert any("never visible" in p for p in res.problems)
    keep = torch.ones(60, dtype=torch.bool)
    keep[5] = False
    err = errors_any_reflection(res.cameras.R[keep], d["R"][keep])
    assert err.max() < 0.5
    s = res.summary()
    assert s["never_visible"] == [3] and "5" in json.loads(json.dumps(s))["invalid"]


def test_nan_coordinates_of_visible_keypoints_are_reported():
    d = make_class(14, n=40, k=8, missing=0.2)
    kp = d["kp"].clone()
    kp[0, 0] = float("nan")
    vis = d["vis"].clone()
    vis[0, 0] = True
    res = rigid_sfm(kp, vis)
    assert any("non-finite" in p for p in res.problems)
    assert bool(torch.isfinite(res.shape).all())


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"keypoints": torch.zeros(3, 4)}, "keypoints"),
        ({"visible": torch.ones(3, 5, dtype=torch.bool)}, "visible"),
        ({"rigid_keypoints": [0, 9]}, "rigid_keypoints"),
        ({"flip_pairs": [(0, 7)]}, "flip_pairs"),
        ({"keypoint_names": ["a"]}, "keypoint_names"),
        ({"left_convention": "mine"}, "left_convention"),
    ],
)
def test_bad_arguments_raise(kwargs, match):
    args = {"keypoints": torch.zeros(3, 4, 2), "visible": torch.ones(3, 4, dtype=torch.bool)}
    args.update(kwargs)
    kp, vis = args.pop("keypoints"), args.pop("visible")
    with pytest.raises(ValueError, match=match):
        rigid_sfm(kp, vis, **args)


def test_deterministic_and_summary_is_json():
    d = make_class(15, n=50, k=10, missing=0.3)
    a = rigid_sfm(d["kp"], d["vis"])
    b = rigid_sfm(d["kp"], d["vis"])
    assert torch.equal(a.shape, b.shape) and torch.equal(a.cameras.R, b.cameras.R)
    s = json.loads(json.dumps(a.summary()))
    assert s["valid"] == 50 and s["reflection"]["decided_by"] in ("visibility", "visibility (weak)")


# --------------------------------------------------------------------------- symmetry plane


def test_symmetry_plane_of_a_reflected_shape(generator):
    half = torch.randn(4, 3, generator=generator, dtype=torch.float64)
    n = torch.nn.functional.normalize(torch.randn(3, generator=generator, dtype=torch.float64), dim=0)
    # independent reference: a Householder matrix built in numpy
    H = np.eye(3) - 2.0 * np.outer(n.numpy(), n.numpy())
    other = half @ torch.from_numpy(H)
    S = torch.cat([half, other, torch.full((1, 3), float("nan"), dtype=torch.float64)])
    pairs = [(0, 4), (5, 1), (2, 6), (3, 7), (0, 8)]  # mixed order, one pair with a NaN row
    P = symmetry_plane(S, pairs)
    np.testing.assert_allclose(P.numpy(), H, atol=1e-10)
    assert abs(float(torch.det(P)) + 1.0) < 1e-10
    with pytest.raises(ValueError, match="flip_pairs"):
        symmetry_plane(S, [(0, 8)])
    with pytest.raises(ValueError, match="shape"):
        symmetry_plane(torch.zeros(3, 2), [(0, 1)])


# --------------------------------------------------------------------------- device


@pytest.mark.cuda
@pytest.mark.parametrize("visibility", ["depth", "random"])
def test_cuda_matches_cpu(visibility):
    """CUDA and CPU give the same solution.

    With ``visibility="depth"`` (self-occlusion) the reflection is decided by the visibility
    vote, so both devices must return the same frame. With ``"random"`` visibility the vote
    ties (no depth cue): either frame is a valid answer, and the two devices may return the two
    Necker mirrors of one solution, which must then be equal up to ``diag(1, 1, -1)``.
    """
    d = make_class(16, n=100, k=12, missing=0.3, noise=0.005, visibility=visibility)
    a = rigid_sfm(d["kp"], d["vis"])
    b = rigid_sfm(d["kp"].cuda(), d["vis"].cuda())
    assert b.shape.device.type == "cuda" and b.cameras.R.device.type == "cuda"
    # The object frame is fixed only up to one rotation (the factorisation's gauge comes from
    # an SVD, whose signs and bases may differ between backends): compare what does not depend
    # on it -- the reprojected mean shape of every instance and the relative rotations.
    assert torch.equal(a.valid, b.valid.cpu())
    Pa = a.cameras.project(torch.nan_to_num(a.shape))[a.valid]
    Pb = b.cameras.to("cpu").project(torch.nan_to_num(b.shape.cpu()))[a.valid]
    torch.testing.assert_close(Pa, Pb, atol=1e-2, rtol=0)  # canvas pixels
    Ra, Rb = a.cameras.R[a.valid], b.cameras.R.cpu()[a.valid]
    rel_a, rel_b = Ra @ Ra[:1].transpose(1, 2), Rb @ Rb[:1].transpose(1, 2)
    if visibility == "depth":
        assert a.reflection_votes["decided_by"] == b.reflection_votes["decided_by"] == "visibility"
        torch.testing.assert_close(rel_a, rel_b, atol=1e-3, rtol=0)
    else:
        assert a.reflection_votes["for"] == a.reflection_votes["against"]  # a tie: no depth cue
        F = torch.diag(torch.tensor([1.0, 1.0, -1.0]))
        same = (rel_a - rel_b).abs().amax() < 1e-3
        assert same or (rel_a - F @ rel_b @ F).abs().amax() < 1e-3


# --------------------------------------------------------------------------- disconnected groups, degenerate blocks


def _two_groups(seed=21):
    """Group A: 8 non-planar keypoints, 40 instances; group B: 4 other, coplanar keypoints, 12
    instances (4 of them see only 2): no instance sees keypoints of both groups (the PASCAL3D+
    diningtable models: one model's table-top keypoints are named differently from the others')."""
    g = torch.Generator().manual_seed(seed)
    S = torch.randn(12, 3, generator=g, dtype=torch.float64)
    S[8:, 2] = 0.0
    R = random_rotations(52, g, dtype=torch.float64)
    d = make_class(seed, n=52, shape=S, rotations=R, missing=0.0)
    vis = torch.zeros(52, 12, dtype=torch.bool)
    vis[:40, :8] = True
    vis[40:, 8:] = True
    vis[40:44, 10:] = False
    return d, vis


def test_disconnected_groups_no_nan_and_reasons():
    d, vis = _two_groups()
    res = rigid_sfm(d["kp"], vis)
    assert bool(torch.isfinite(res.cameras.R).all()) and bool(torch.isfinite(res.cameras.s).all())
    assert bool(res.valid[:40].all()) and not bool(res.valid[40:].any())
    assert all("largest connected group" in r for r in res.reasons[40:])
    assert any("no shape row" in p for p in res.problems)
    assert bool(torch.isfinite(res.shape[:8]).all()) and bool(torch.isnan(res.shape[8:]).all())
    # the main group is reconstructed as if the other were absent (noise-free: exact)
    err = errors_any_reflection(res.cameras.R[:40], d["R"][:40])
    assert err.max() < 0.5


def test_outside_main_component_picks_most_instances():
    from carvi_torch.viewpoints.sfm import outside_main_component

    seen = torch.zeros(6, 5, dtype=torch.bool)
    seen[:2, :3] = True   # 2 instances, 3 keypoints
    seen[2:5, 3:] = True  # 3 instances, 2 keypoints: the main group
    inst, kps = outside_main_component(seen)
    assert inst.tolist() == [True, True, False, False, False, False]  # instance 5 has no edge
    assert kps.tolist() == [True, True, True, False, False]


def test_polish_keeps_degenerate_blocks_out_of_the_shape():
    from carvi_torch.viewpoints.sfm import bundle_polish

    d = make_class(22, n=30, k=8, missing=0.2)
    W = d["kp"].double().transpose(1, 2).contiguous()
    vis = d["vis"].double()
    cams = ScaledOrthographic(d["R"], d["s"], d["t"])
    M, t = cams.M.clone(), cams.t.clone()
    M[3] = 0.0  # a zero block: no rotation, would be a NaN camera
    M[4] = float("nan")
    M2, t2, S2, hist, _ = bundle_polish(M, t, d["S"].T.contiguous(), W, vis, iters=3, tol=1e-9)
    assert bool(torch.isfinite(S2).all()) and all(math.isfinite(h) for h in hist)
    assert hist[-1] < 1e-4
    assert torch.equal(M2[3], M[3]) and bool(torch.isfinite(M2[torch.arange(30) != 4]).all())


# --------------------------------------------------------------------------- mirrored copies


def _with_mirrors(kp, vis, pairs, width=128.0):
    """The pipeline's mirrored copies appended: x' = W - 1 - x, labels swapped along ``pairs``."""
    perm = list(range(kp.shape[1]))
    for i, j in pairs:
        perm[i], perm[j] = j, i
    kp_m = kp[:, perm].clone()
    kp_m[..., 0] = width - 1 - kp_m[..., 0]
    return torch.cat([kp, kp_m]), torch.cat([vis, vis[:, perm]])


def test_mirror_width_detects_the_layout_only():
    from carvi_torch.viewpoints.sfm import mirror_width

    S, names, pairs, R = _named_class(5)
    d = make_class(5, n=R.shape[0], shape=S, rotations=R, missing=0.3, visibility="depth")
    kp, vis = _with_mirrors(d["kp"], d["vis"], pairs, width=100.0)
    assert mirror_width(kp, vis, pairs) == pytest.approx(100.0, abs=1e-4)
    # not a mirror layout: wrong pairs, a moved keypoint, an odd count, unrelated halves
    assert mirror_width(kp, vis, pairs[1:]) is None
    kp2 = kp.clone()
    kp2[-1, vis[-1].nonzero()[0, 0], 0] += 0.5
    assert mirror_width(kp2, vis, pairs) is None
    assert mirror_width(kp[1:], vis[1:], pairs) is None
    assert mirror_width(d["kp"], d["vis"], pairs) is None
    with pytest.raises(ValueError, match="mirrors=True"):
        rigid_sfm(d["kp"], d["vis"], flip_pairs=pairs, mirrors=True)


def test_mirror_tie_angle_is_zero_for_the_truth_and_large_when_broken():
    from carvi_torch.viewpoints.sfm import mirror_layout, mirror_tie_angles, mirror_width

    S, names, pairs, R = _named_class(6)
    d = make_class(6, n=R.shape[0], shape=S, rotations=R, missing=0.0)
    kp, vis = _with_mirrors(d["kp"], d["vis"], pairs)
    n = R.shape[0]
    cams = ScaledOrthographic(d["R"], d["s"], d["t"])
    P = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    both = ScaledOrthographic.cat([cams, cams.mirror(128.0, reflection=P)])
    layout = mirror_layout(torch.ones(2 * n, dtype=torch.bool), mirror_width(kp, vis, pairs), pairs,
                            list(range(S.shape[0])))
    tie = mirror_tie_angles(both.M, S.T, layout)
    assert tie.shape == (n,) and float(tie.max()) < 1e-6
    # copies seen from the originals' viewpoints (not mirrored): angles far from 0
    broken = ScaledOrthographic.cat([cams, cams])
    assert float(mirror_tie_angles(broken.M, S.T, layout).median()) > 20.0


@pytest.fixture(scope="module")
def cad_cars(shared_data, tmp_path_factory):
    """The 5 PASCAL3D+ car models rendered from 30 views each (keypoints with self-occlusion)."""
    coll, R, _ = render_cad_class(shared_data, tmp_path_factory.mktemp("cars"), "car", views=30)
    return coll, R


def test_cad_cars_with_mirrors_are_reseeded_from_the_originals(cad_cars):
    """PASCAL3D+ cars: every keypoint in a left/right pair, models annotated with 12, 20 or 22 names.

    The joint factorisation over originals and mirrored copies ends in a minimum that breaks the
    mirror tie (72 deg median error); re-seeding from the originals recovers the viewpoints."""
    from carvi_torch.evaluation.viewpoint_metrics import viewpoint_report

    coll, R = cad_cars
    both = coll.with_mirrors()
    kw = dict(keypoint_names=coll.meta.keypoint_names, flip_pairs=coll.meta.flip_pairs,
              left_convention=coll.meta.left_convention)
    n = len(coll)
    plain = rigid_sfm(both.keypoints, both.visible, mirrors=False, **kw)
    res = rigid_sfm(both.keypoints, both.visible, **kw)
    assert res.mirrors["width"] == pytest.approx(coll.canvas_size, abs=1e-3)
    assert res.mirrors["reseeded"] and res.mirrors["tie_deg_median"] < 1.0
    assert res.mirrors["rms_seeded"] < res.mirrors["rms_joint"]
    assert any("re-seeded" in p for p in res.problems)
    err = viewpoint_report(res.cameras.R[:n].double(), R)["geodesic"]["median"]
    err_plain = viewpoint_report(plain.cameras.R[:n].double(), R)["geodesic"]["median"]
    assert err < 8.0 < err_plain
    assert res.reflection_votes["against"] <= 0.05 * res.reflection_votes["voters"]
