"""Tests for carvi_torch.viewpoints.camera_fit: silhouette refinement, keypoint-only refinement, unseen images."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import ndimage
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation
from skimage.draw import polygon2mask

from carvi_torch.cameras import ScaledOrthographic, axis_angle_to_rotation, random_rotations, rotation_about_axis
from carvi_torch.viewpoints.camera_fit import (
    TWIN_MARGIN,
    Fitted,
    RefineResult,
    _terms,
    collapsed_keypoints,
    estimate_camera,
    keypoint_thickness,
    mask_start_cameras,
    planar_twin,
    refine_cameras,
    refine_keypoints_only,
    refine_starts_keypoints_only,
    refinement_energy,
    sample_distance,
    sphere_rotations,
    supported_shape,
    twin_wins,
)
from carvi_torch.sdf import distance_to_mask
from carvi_torch.viewpoints.choice import HULL_GAIN
import carvi_torch.viewpoints.camera_fit as refine_module
from carvi_torch.viewpoints.sfm import rigid_sfm

CANVAS = 96


# --------------------------------------------------------------------------- helpers


def hull_masks(points: torch.Tensor, size: int = CANVAS) -> torch.Tensor:
    """Filled convex hulls of ``points (N, P, 2)`` rasterised by skimage (``(N, size, size)`` bool)."""
    out = np.zeros((points.shape[0], size, size), dtype=bool)
    for i, p in enumerate(points.detach().double().numpy()):
        v = p[ConvexHull(p).vertices]
        out[i] = polygon2mask((size, size), v[:, ::-1])
    return torch.from_numpy(out)


def make_scene(seed, n=60, k=12, deform=0.0, hidden=0.4, size=CANVAS):
    """Instances of a class: mean shape + per-instance deformation, random views.

    Keypoints are the true instance's projections; the farthest ``hidden`` fraction
    is hidden (self-occlusion); masks are the convex hulls of every projected point.
    """
    g = torch.Generator().manual_seed(seed)
    S0 = torch.randn(k, 3, generator=g) * torch.tensor([1.0, 0.7, 0.5])
    S0 = S0 - S0.mean(0)
    Sn = S0 + deform * torch.randn(n, k, 3, generator=g)
    R = random_rotations(n, g)
    s = size / 5.0 * (1.0 + 0.1 * torch.rand(n, generator=g))
    t = size / 2.0 + 2.0 * torch.randn(n, 2, generator=g)
    cams = ScaledOrthographic(R, s, t)
    kp = cams.project(Sn)
    z = cams.depth(Sn)
    rank = (-z).argsort(1).argsort(1)
    vis = rank >= round(hidden * k)
    masks = hull_masks(kp, size)
    return {"S0": S0, "Sn": Sn, "cams": cams, "kp": kp, "vis": vis, "masks": masks}


def rot_err_deg(R1, R2):
    R1 = np.asarray(R1, dtype=np.float64)
    R2 = np.asarray(R2, dtype=np.float64)
    return np.degrees(Rotation.from_matrix(np.einsum("nij,nkj->nik", R1, R2)).magnitude())


def mask_sides(D):
    """Larger side of each mask's bounding box (pixels), from the zeros of its distance map, by numpy."""
    out = []
    for m in np.asarray(D) == 0:
        ys, xs = np.nonzero(m)
        out.append(max(xs.max() - xs.min() + 1, ys.max() - ys.min() + 1))
    return np.array(out, dtype=np.float64)


def brute_energy(M, t, S, kp, vis, D, lam, robust=None):
    """Per-instance loop with scipy's order-1 map_coordinates (independent of grid_sample).

    ``robust``: None for the squared distance, else the Geman-McClure scale as a fraction of
    the mask's larger side."""
    n, h, w = D.shape
    sides = mask_sides(D)
    out = []
    for i in range(n):
        e = 0.0
        for k in range(S.shape[0]):
            p = M[i] @ S[k] + t[i]
            if vis[i, k]:
                e += float(((p - kp[i, k]) ** 2).sum())
            x, y = float(p[0]), float(p[1])
            cx, cy = min(max(x, 0.0), w - 1.0), min(max(y, 0.0), h - 1.0)
            d = ndimage.map_coordinates(D[i], [[cy], [cx]], order=1)[0]
            d += math.hypot(x - cx, y - cy)
            if robust is None:
                e += lam * d * d
            else:
                c2 = (robust * sides[i]) ** 2
                e += lam * c2 * d * d / (c2 + d * d)
        out.append(e)
    return np.array(out)


# --------------------------------------------------------------------------- sampling and energy


def test_sample_distance_inside_matches_scipy_and_grows_outside(generator):
    D = torch.rand(3, 7, 9, generator=generator, dtype=torch.float64) * 5
    pts = torch.rand(3, 20, 2, generator=generator, dtype=torch.float64) * torch.tensor([8.0, 6.0], dtype=torch.float64)
    got = sample_distance(D, pts)
    for i in range(3):
        ref = ndimage.map_coordinates(D[i].numpy(), [pts[i, :, 1].numpy(), pts[i, :, 0].numpy()], order=1)
        np.testing.assert_allclose(got[i].numpy(), ref, atol=1e-10)
    # pixel centres are exact samples (align_corners=True)
    assert float(sample_distance(D, torch.tensor([[[3.0, 2.0]]] * 3, dtype=torch.float64))[1, 0]) == pytest.approx(
        float(D[1, 2, 3]))
    # outside: border value plus the distance to the canvas, strictly increasing outward
    xs = torch.tensor([8.0, 9.0, 12.0, 20.0], dtype=torch.float64)
    far = torch.stack([xs, torch.full_like(xs, 3.0)], -1)[None].expand(3, -1, -1)
    v = sample_distance(D, far)
    np.testing.assert_allclose(v[0].numpy(), D[0, 3, 8].item() + np.array([0.0, 1.0, 4.0, 12.0]), atol=1e-10)
    assert bool((v[:, 1:] > v[:, :-1]).all())


@pytest.mark.parametrize("robust", [None, 0.2, 0.05])
def test_energy_matches_brute_force_loop(generator, robust):
    d = make_scene(1, n=4, k=6)
    dm = distance_to_mask(d["masks"]).double()
    M = d["cams"].M.double() * 1.05
    t = d["cams"].t.double() + 1.5
    S = d["S0"].double()
    E = refinement_energy(M, t, S, d["kp"].double(), d["vis"], dm, silhouette_weight=0.7, silhouette_robust=robust)
    ref = brute_energy(M.numpy(), t.numpy(), S.numpy(), d["kp"].double().numpy(), d["vis"].numpy(), dm.numpy(), 0.7,
                       robust)
    np.testing.assert_allclose(E.numpy(), ref, rtol=1e-10)
    # NaN shape rows drop out of both sums; an invalid mask drops the silhouette term
    S2 = S.clone()
    S2[2] = float("nan")
    keep = [0, 1, 3, 4, 5]
    E2 = refinement_energy(M, t, S2, d["kp"].double(), d["vis"], dm, 0.7, mask_valid=torch.tensor([1, 0, 1, 1]).bool(),
                           silhouette_robust=robust)
    ref2 = brute_energy(M.numpy(), t.numpy(), S.numpy()[keep], d["kp"].double().numpy()[:, keep],
                        d["vis"].numpy()[:, keep], dm.numpy(), 0.7, robust)
    ref2[1] = brute_energy(M.numpy()[1:2], t.numpy()[1:2], S.numpy()[keep], d["kp"].double().numpy()[1:2, keep],
                           d["vis"].numpy()[1:2, keep], dm.numpy()[1:2], 0.0)[0]
    np.testing.assert_allclose(E2.numpy(), ref2, rtol=1e-10)
    if robust is not None:  # the default is the robust penalty at ROBUST_FRACTION
        from carvi_torch.viewpoints.camera_fit import ROBUST_FRACTION

        Ed = refinement_energy(M, t, S, d["kp"].double(), d["vis"], dm, silhouette_weight=0.7)
        refd = brute_energy(M.numpy(), t.numpy(), S.numpy(), d["kp"].double().numpy(), d["vis"].numpy(), dm.numpy(),
                            0.7, ROBUST_FRACTION)
        np.testing.assert_allclose(Ed.numpy(), refd, rtol=1e-10)


def test_silhouette_penalty_and_robust_scales():
    from carvi_torch.viewpoints.camera_fit import robust_scales, silhouette_penalty

    D = torch.tensor([0.0, 0.5, 3.0, 40.0, 1e4], dtype=torch.float64)
    np.testing.assert_allclose(silhouette_penalty(D).numpy(), (D * D).numpy())
    c = 4.0
    ref = c * c * D * D / (c * c + D * D)
    np.testing.assert_allclose(silhouette_penalty(D, c).numpy(), ref.numpy(), rtol=1e-12)
    # quadratic near the mask, bounded by delta^2 far from it
    assert float(silhouette_penalty(torch.tensor(0.1, dtype=torch.float64), c)) == pytest.approx(0.01, rel=1e-3)
    assert float(silhouette_penalty(torch.tensor(1e6, dtype=torch.float64), c)) == pytest.approx(c * c, rel=1e-9)
    masks = torch.zeros(3, 20, 30, dtype=torch.bool)
    masks[0, 2:5, 3:10] = True   # 3 x 7
    masks[1, 1:19, 10:12] = True  # 18 x 2
    dm = distance_to_mask(masks)
    np.testing.assert_allclose(robust_scales(dm[:2], 0.25).numpy(), [0.25 * 7, 0.25 * 18])
    assert float(robust_scales(dm, 0.25)[2]) == 1.0  # empty mask


def test_robust_penalty_ignores_a_misplaced_shape_point():
    """One mean-shape point far from where the instances have it (a keypoint placed badly by SfM, or
    one the instance lacks): the squared penalty drags every camera off to pull it into the mask, the
    robust one leaves the cameras near the truth."""
    d = make_scene(11, n=40, k=10, hidden=0.3)
    dm = distance_to_mask(d["masks"])
    S = d["S0"].clone()
    S[3] = S[3] + torch.tensor([6.0, -5.0, 0.0])  # far outside every silhouette
    vis = d["vis"].clone()
    vis[:, 3] = False
    errs = {}
    for robust in (None, 0.2):
        res = refine_cameras(S, d["cams"], d["kp"], vis, dm, max_iters=100, silhouette_robust=robust)
        errs[robust] = np.median(rot_err_deg(res.cameras.R, d["cams"].R))
    assert errs[0.2] < 2.0 and errs[None] > 5.0 * errs[0.2]


def test_energy_gradcheck_float64():
    d = make_scene(2, n=3, k=5)
    dm = distance_to_mask(d["masks"]).double()
    M = (d["cams"].M.double() * 1.1).requires_grad_(True)
    t = (d["cams"].t.double() + 2.3).requires_grad_(True)

    def f(M_, t_):
        return refinement_energy(M_, t_, d["S0"].double(), d["kp"].double(), d["vis"], dm, 1.0)

    assert torch.autograd.gradcheck(f, (M, t), eps=1e-6, atol=1e-5)


@pytest.mark.parametrize("robust", [False, True])
def test_local_gradient_and_gauss_newton_match_finite_differences(robust):
    d = make_scene(3, n=3, k=6)
    dm = distance_to_mask(d["masks"]).double()
    cams = d["cams"]
    R = cams.R.double()[:, None] @ rotation_about_axis(torch.tensor([1.0, 2, 3], dtype=torch.float64), 0.2)
    s = cams.s.double()[:, None] * 1.1
    t = cams.t.double()[:, None] + 1.7
    S = d["S0"].double()
    kmask = torch.ones(S.shape[0], dtype=torch.float64)
    wv = d["vis"].double()
    lam = torch.full((3,), 0.5, dtype=torch.float64)
    rscale = torch.tensor([3.0, 5.0, 8.0], dtype=torch.float64) if robust else None
    E, _, _, g, H = _terms(R, s, t, S, kmask, d["kp"].double(), wv, dm, lam, rscale)
    from carvi_torch.cameras import axis_angle_to_rotation

    def energy(delta):
        Rn = axis_angle_to_rotation(delta[..., :3]) @ R
        return _terms(Rn, s * torch.exp(delta[..., 3]), t + delta[..., 4:], S, kmask, d["kp"].double(), wv, dm, lam,
                      rscale)[0]

    eps = 1e-6
    fd = torch.zeros_like(g)
    for j in range(6):
        e = torch.zeros(3, 1, 6, dtype=torch.float64)
        e[..., j] = eps
        fd[..., j] = (energy(e) - energy(-e)) / (2 * eps)
    assert torch.allclose(g, fd, rtol=1e-5, atol=1e-5 * float(g.abs().max()))
    # H is symmetric positive semi-definite
    assert torch.allclose(H, H.transpose(-1, -2))
    assert float(torch.linalg.eigvalsh(H).min()) > -1e-8 * float(H.abs().max())


# --------------------------------------------------------------------------- refine_cameras


def test_refinement_never_raises_energy_and_reports_it():
    d = make_scene(4, n=80, k=10, deform=0.2)
    g = torch.Generator().manual_seed(4)
    axis = torch.randn(80, 3, generator=g)
    R0 = rotation_about_axis(axis, torch.deg2rad(torch.rand(80, generator=g) * 90)) @ d["cams"].R
    start = ScaledOrthographic(R0, d["cams"].s * (0.7 + 0.6 * torch.rand(80, generator=g)),
                               d["cams"].t + 8 * torch.randn(80, 2, generator=g))
    kp = d["kp"] + 1.5 * torch.randn(d["kp"].shape, generator=g)
    dm = distance_to_mask(d["masks"])
    res = refine_cameras(d["S0"], start, kp, d["vis"], dm, silhouette_weight=2.0, max_iters=60)
    assert isinstance(res, RefineResult)
    assert bool((res.energy_after <= res.energy_before).all())
    assert float(res.energy_after.sum()) < 0.5 * float(res.energy_before.sum())
    # reported energies are those of the cameras, recomputed independently
    E0 = refinement_energy(start.M, start.t, d["S0"], kp, d["vis"], dm, 2.0)
    E1 = refinement_energy(res.cameras.M, res.cameras.t, d["S0"], kp, d["vis"], dm, 2.0)
    assert torch.allclose(E0, res.energy_before, rtol=1e-4)
    assert torch.allclose(E1, res.energy_after, rtol=1e-3, atol=1e-3)
    assert torch.allclose(res.keypoint_energy + 2.0 * res.silhouette_energy, res.energy_after, rtol=1e-4)
    R = res.cameras.R.double()
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(80, 3, 3), atol=1e-5)
    assert torch.allclose(torch.det(R), torch.ones(80, dtype=torch.float64), atol=1e-5)


def test_refinement_fixes_cameras_when_the_true_shape_differs_from_the_mean():
    d = make_scene(5, n=150, k=12, deform=0.15, hidden=0.4)
    sfm = rigid_sfm(d["kp"], d["vis"])
    assert sfm.reflection_votes["decided_by"] == "visibility"
    dm = distance_to_mask(d["masks"])
    # one global rotation between the SfM frame and the true frame (from SfM's own cameras)
    B = np.einsum("nji,njk->nik", sfm.cameras.R.double().numpy(), d["cams"].R.double().numpy())
    G = torch.from_numpy(Rotation.from_matrix(B).mean().as_matrix())
    err_sfm = rot_err_deg(sfm.cameras.R.double() @ G, d["cams"].R)
    kp_only = refine_keypoints_only(sfm.shape, sfm.cameras, d["kp"], d["vis"], d["masks"])
    sil = refine_cameras(sfm.shape, sfm.cameras, d["kp"], d["vis"], dm, silhouette_weight=1.0)
    err_kp = rot_err_deg(kp_only.cameras.R.double() @ G, d["cams"].R)
    err_sil = rot_err_deg(sil.cameras.R.double() @ G, d["cams"].R)
    assert np.median(err_sil) < 0.85 * np.median(err_sfm), (np.median(err_sfm), np.median(err_sil))
    assert np.median(err_sil) < np.median(err_kp)
    assert np.mean(err_sil) < np.mean(err_sfm)


# --------------------------------------------------------------------------- supported shape


def test_supported_shape_known_values():
    S = torch.arange(12.0).view(4, 3)
    S[2] = float("nan")
    vis = torch.zeros(20, 4, dtype=torch.bool)
    vis[:, 0] = True  # support 1
    vis[:2, 1] = True  # support 0.1: at the threshold, kept
    vis[:1, 3] = True  # support 0.05: dropped
    out = supported_shape(S, vis, 0.1)
    assert torch.equal(out[[0, 1]], S[[0, 1]])
    assert bool(torch.isnan(out[[2, 3]]).all())
    assert out is not S and not bool(torch.isnan(S[3]).any())  # a new tensor; the input is untouched
    # nothing to drop, no instances, or the rule off: the shape itself
    assert supported_shape(S, vis, 0.0) is S
    assert supported_shape(S, vis[:0], 0.5) is S
    assert supported_shape(S, vis[:, [0, 0, 0, 0]], 0.5) is S
    # the row count threshold by brute force over thresholds
    for frac in (0.0, 0.04, 0.05, 0.06, 0.1, 0.11, 1.0):
        got = torch.isnan(supported_shape(S, vis, frac)[:, 0])
        want = [bool(torch.isnan(S[k, 0])) or (frac > 0 and vis[:, k].float().mean().item() < frac) for k in range(4)]
        assert got.tolist() == want, frac


@pytest.mark.parametrize("args, match", [
    ((torch.zeros(3, 3), torch.ones(4, 3, dtype=torch.bool), 1.5), "min_support"),
    ((torch.zeros(3, 3), torch.ones(4, 3, dtype=torch.bool), -0.1), "min_support"),
    ((torch.zeros(3, 3), torch.ones(4, 2, dtype=torch.bool), 0.1), "need shape"),
    ((torch.zeros(3, 3), torch.ones(3, dtype=torch.bool), 0.1), "need shape"),
])
def test_supported_shape_bad_arguments(args, match):
    with pytest.raises(ValueError, match=match):
        supported_shape(*args)


def test_a_keypoint_few_instances_show_does_not_turn_every_camera():
    """A mean-shape point SfM placed badly from the 2 of 60 instances that show it: refining with
    it pulls the point into every mask and turns the cameras; without it (support below 10%) the
    cameras stay at the truth, exactly as if the row were absent."""
    d = make_scene(22, n=60, k=10, hidden=0.3)
    dm = distance_to_mask(d["masks"])
    S = d["S0"].clone()
    S[3] = S[3] + torch.tensor([0.0, 0.0, 1.5])
    vis = d["vis"].clone()
    seen = vis[:, 3].nonzero()[:2, 0]
    vis[:, 3] = False
    vis[seen, 3] = True
    errs = {}
    for name, shape in (("all", S), ("supported", supported_shape(S, vis, 0.1))):
        res = refine_cameras(shape, d["cams"], d["kp"], vis, dm, max_iters=100)
        errs[name] = float(np.median(rot_err_deg(res.cameras.R, d["cams"].R)))
    absent = S.clone()
    absent[3] = float("nan")
    ref = refine_cameras(absent, d["cams"], d["kp"], vis, dm, max_iters=100)
    assert errs["supported"] == pytest.approx(float(np.median(rot_err_deg(ref.cameras.R, d["cams"].R))), abs=1e-6)
    assert errs["supported"] < 1.5 and errs["all"] > 2.5 * errs["supported"], errs


# --------------------------------------------------------------------------- planar twin


def _monitor(seed, n=80, size=CANVAS):
    """A monitor-like class: 4 coplanar front corners (the only keypoints, all visible) on a
    plane off the origin with a tilted normal, and a smaller box behind them (in the mean shape
    and the masks, never a keypoint)."""
    g = torch.Generator().manual_seed(seed)
    front = torch.tensor([[-1.0, -0.6, 0.0], [1.0, -0.6, 0.0], [1.0, 0.6, 0.0], [-1.0, 0.6, 0.0]], dtype=torch.float64)
    back = torch.tensor([[x, y, -0.7] for x in (-0.5, 0.5) for y in (-0.3, 0.3)], dtype=torch.float64)
    Q = rotation_about_axis(torch.tensor([[0.3, 1.0, 0.2]], dtype=torch.float64), torch.tensor([0.5],
                            dtype=torch.float64))[0]
    S = torch.cat([front, back]) @ Q.T + torch.tensor([0.2, -0.1, 0.3], dtype=torch.float64)
    # views from the front half-sphere, tilted 20-60 degrees (a frontal view is ambiguous for the silhouette too)
    axis = torch.randn(n, 3, generator=g, dtype=torch.float64)
    axis[:, 2] = 0
    tilt = torch.deg2rad(20 + 40 * torch.rand(n, generator=g, dtype=torch.float64))
    R = rotation_about_axis(axis, tilt) @ Q.T
    cams = ScaledOrthographic(R, torch.full((n,), size / 4.0, dtype=torch.float64),
                              size / 2.0 + torch.zeros(n, 2, dtype=torch.float64))
    kp = cams.project(S)
    vis = torch.zeros(n, 8, dtype=torch.bool)
    vis[:, :4] = True
    return S, cams, kp, vis, hull_masks(kp, size)


def test_keypoint_thickness_matches_a_numpy_loop():
    g = torch.Generator().manual_seed(3)
    S = torch.randn(7, 3, generator=g, dtype=torch.float64) * torch.tensor([2.0, 1.0, 0.3], dtype=torch.float64)
    S[5] = float("nan")
    vis = torch.rand(6, 7, generator=g) > 0.3
    vis[0] = False
    vis[0, :2] = True  # two points: no plane
    got = keypoint_thickness(S, vis)
    for i in range(6):
        X = S.numpy()[vis[i].numpy() & np.isfinite(S.numpy()).all(1)]
        if len(X) < 3:
            assert math.isinf(float(got[i]))
            continue
        ev = np.linalg.eigvalsh(np.cov(X.T, bias=True))
        want = float(np.sqrt(max(ev[0], 0) / ev[1]))
        assert float(got[i]) == pytest.approx(want, rel=1e-9, abs=1e-6)  # 3 points: 0 up to rounding


def test_planar_twin_projects_the_plane_alike():
    S, cams, kp, vis, _ = _monitor(0, n=20)
    twin, thick = planar_twin(S, cams, vis)
    assert torch.allclose(thick, torch.zeros(20, dtype=torch.float64), atol=1e-6)
    R = twin.R
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(20, 3, 3), atol=1e-10)
    assert torch.allclose(torch.det(R), torch.ones(20, dtype=torch.float64), atol=1e-10)
    P0, P1 = cams.project(S), twin.project(S)
    assert torch.allclose(P1[:, :4], P0[:, :4], atol=1e-9)  # the plane projects alike
    assert ((P1[:, 4:] - P0[:, 4:]).norm(dim=-1) > 1.0).all()  # the rest tilts the other way
    assert (rot_err_deg(twin.R, cams.R) > 30).all()  # 2x the 20-60 degree tilt
    # the twin of the twin is the camera itself
    back, _ = planar_twin(S, twin, vis)
    assert torch.allclose(back.R, cams.R, atol=1e-9) and torch.allclose(back.t, cams.t, atol=1e-9)
    # a non-flat visible set is thick; fewer than 3 usable points: unchanged, infinite thickness
    vis2 = vis.clone()
    vis2[:, 4] = True
    assert (planar_twin(S, cams, vis2)[1] > 0.3).all()
    vis3 = torch.zeros_like(vis)
    vis3[:, :2] = True
    S_nan = S.clone()
    S_nan[2] = float("nan")
    vis3[:, 2] = True  # its shape row is NaN: not usable
    tw3, th3 = planar_twin(S_nan, cams, vis3)
    assert torch.equal(tw3.R, cams.R) and torch.equal(tw3.t, cams.t) and torch.isinf(th3).all()


def test_twin_start_recovers_the_other_branch_of_a_plane():
    """Started on the wrong branch (keypoints fit exactly), the silhouette refinement alone stays
    there; with the twin start every instance comes back to its true camera."""
    S, cams, kp, vis, masks = _monitor(1)
    S, kp = S.float(), kp.float()
    cams = ScaledOrthographic(cams.R.float(), cams.s.float(), cams.t.float())
    wrong, _ = planar_twin(S, cams, vis)
    dm = distance_to_mask(masks)
    plain = refine_cameras(S, wrong, kp, vis, dm, max_iters=100)
    twin = refine_cameras(S, wrong, kp, vis, dm, max_iters=100, twin_flatness=0.1)
    e_plain, e_twin = rot_err_deg(plain.cameras.R, cams.R), rot_err_deg(twin.cameras.R, cams.R)
    # where the back box projects inside the front's outline, the two branches have (nearly) the
    # same silhouette and nothing decides; judge the views whose two silhouettes differ
    differ = (hull_masks(wrong.project(S)) ^ masks).flatten(1).sum(1) > 20
    assert differ.float().mean() > 0.3
    assert np.median(e_plain[differ]) > 20, np.median(e_plain)
    assert np.median(e_twin[differ]) < 2 and (twin.start[differ] == 1).float().mean() > 0.9, e_twin[differ]
    assert bool((twin.energy_after <= twin.energy_before).all())
    assert bool((twin.energy_after <= plain.energy_after).all())
    # the reported energy is that of the kept camera
    E = refinement_energy(twin.cameras.M, twin.cameras.t, S, kp, vis, dm, 1.0)
    assert torch.allclose(E, twin.energy_after, rtol=1e-3, atol=1e-3)


def test_twin_start_off_or_unused_changes_nothing():
    d = make_scene(6, n=40, k=10, deform=0.2)
    dm = distance_to_mask(d["masks"])
    sfm = rigid_sfm(d["kp"], d["vis"])
    base = refine_cameras(sfm.shape, sfm.cameras, d["kp"], d["vis"], dm, max_iters=40)
    assert (base.start == 0).all()
    # no instance this flat: the second start repeats the first, and the result is the same
    none_flat = refine_cameras(sfm.shape, sfm.cameras, d["kp"], d["vis"], dm, max_iters=40, twin_flatness=1e-9)
    # every instance tried, but the twin must lower the energy by 99.9% (no tie-break by the hull): never kept here
    strict = refine_cameras(sfm.shape, sfm.cameras, d["kp"], d["vis"], dm, max_iters=40, twin_flatness=1.0,
                            twin_margin=0.999, twin_hull=False)
    for r in (none_flat, strict):
        assert (r.start == 0).all()
        assert torch.allclose(r.cameras.R, base.cameras.R, atol=1e-6)
        assert torch.allclose(r.energy_after, base.energy_after, rtol=1e-6)
    assert 0 < TWIN_MARGIN < 0.1
    with pytest.raises(ValueError, match="twin"):
        refine_cameras(sfm.shape, sfm.cameras, d["kp"], d["vis"], dm, twin_flatness=-1.0)
    with pytest.raises(ValueError, match="twin"):
        refine_cameras(sfm.shape, sfm.cameras, d["kp"], d["vis"], dm, twin_flatness=0.1, twin_margin=1.0)


def _iou_by_point_in_hull(points: np.ndarray, mask: np.ndarray) -> float:
    """IoU of ``mask`` and the convex hull of ``points (P, 2)``, by testing every pixel centre against the hull's
    half-planes (independent of the package's polygon fill)."""
    eq = ConvexHull(points).equations  # inside: n . x + c <= 0 for every facet
    ys, xs = np.mgrid[:mask.shape[0], :mask.shape[1]]
    inside = ((np.stack([xs.ravel(), ys.ravel()], 1) @ eq[:, :2].T + eq[:, 2]) <= 1e-9).all(1).reshape(mask.shape)
    return float((inside & mask).sum() / (inside | mask).sum())


def test_twin_wins_by_energy_or_by_hull_agreement_within_the_margin():
    """A twin clearly lower in energy wins, a higher one never does; within the margin it wins when its projected
    hull agrees better with the mask by more than HULL_GAIN (the reference IoU by half-plane tests of every pixel
    centre)."""
    g = torch.Generator().manual_seed(3)
    n = 48
    S = torch.randn(7, 3, generator=g, dtype=torch.float64)
    truth = ScaledOrthographic(random_rotations(n, g).double(), torch.full((n,), 14.0, dtype=torch.float64),
                               CANVAS / 2 + 3 * torch.randn(n, 2, generator=g, dtype=torch.float64))

    def near(scale):  # cameras up to ``scale`` radians and 15 * scale % of scale away from the truth
        turn = axis_angle_to_rotation(scale * torch.randn(n, 3, generator=g, dtype=torch.float64))
        return ScaledOrthographic(turn @ truth.R, truth.s * (1 + 0.5 * scale * torch.randn(n, generator=g)), truth.t)

    own, twin = near(0.3), near(0.3)
    slightly = torch.arange(n) % 8 == 5  # a twin barely larger than its own camera: a small hull gain, if any
    twin = ScaledOrthographic(torch.where(slightly[:, None, None], own.R, twin.R),
                              torch.where(slightly, own.s * 1.04, twin.s), twin.t)
    masks = hull_masks(truth.project(S))
    E = torch.full((n,), 100.0, dtype=torch.float64)
    band = torch.arange(n) % 4  # 0: clearly lower, 1: lower within the margin, 2: equal, 3: higher
    Et = torch.stack([E * 0.9, E * 0.99, E, E * 1.01]).gather(0, band[None])[0]
    wins = twin_wins(S, own, E, twin, Et, masks, margin=0.02)
    P_own, P_twin = own.project(S).numpy(), twin.project(S).numpy()
    iou = np.array([[_iou_by_point_in_hull(P[i], masks[i].numpy()) for i in range(n)] for P in (P_own, P_twin)])
    tie = band.numpy() == 1
    gain = iou[1] - iou[0] - HULL_GAIN  # the twin must agree better by more than HULL_GAIN
    clear = np.abs(gain) > 0.02  # pixels on a hull edge may fall either way
    assert wins[band == 0].all() and not wins[band >= 2].any()
    assert (tie & clear & (gain > 0)).sum() >= 3 and (tie & clear & (gain < 0) & (iou[1] > iou[0])).sum() >= 1
    assert (tie & clear & (gain < 0)).sum() >= 3
    assert np.array_equal(wins.numpy()[tie & clear], (gain > 0)[tie & clear])
    # without masks, the energy alone: only the clear winners
    assert torch.equal(twin_wins(S, own, E, twin, Et, None, margin=0.02), band == 0)


def test_empty_masks_use_keypoints_only():
    d = make_scene(6, n=20, k=8)
    masks = d["masks"].clone()
    masks[:5] = False
    dm = distance_to_mask(masks)
    assert bool(torch.isinf(dm[:5]).all())
    start = ScaledOrthographic(rotation_about_axis(torch.tensor([0.0, 1.0, 0.0]), 0.3) @ d["cams"].R,
                               d["cams"].s, d["cams"].t + 2)
    a = refine_cameras(d["S0"], start, d["kp"], d["vis"], dm)
    b = refine_cameras(d["S0"], start[:5], d["kp"][:5], d["vis"][:5], dm[:5], silhouette_weight=0.0)
    assert bool(torch.isfinite(a.energy_after).all())
    assert torch.allclose(a.cameras.R[:5], b.cameras.R, atol=1e-4)
    assert bool((a.silhouette_energy[5:] >= 0).all())
    # mask_valid given explicitly overrides the default
    c = refine_cameras(d["S0"], start, d["kp"], d["vis"], distance_to_mask(d["masks"]),
                       mask_valid=torch.zeros(20, dtype=torch.bool))
    e = refine_cameras(d["S0"], start, d["kp"], d["vis"], distance_to_mask(d["masks"]), silhouette_weight=0.0)
    assert torch.allclose(c.energy_after, e.energy_after)


def test_refine_keypoints_only_two_starts():
    d = make_scene(7, n=30, k=10, hidden=0.2)
    flipped = ScaledOrthographic(rotation_about_axis(torch.tensor([0.0, 1.0, 0.0]), math.pi) @ d["cams"].R,
                                 d["cams"].s, d["cams"].t)
    res = refine_keypoints_only(d["S0"], flipped, d["kp"], d["vis"], d["masks"])
    # each instance keeps the better of its two refined starts
    one = refine_cameras(d["S0"], flipped, d["kp"], d["vis"], distance_to_mask(d["masks"]), silhouette_weight=0.0)
    assert bool((res.energy_after <= one.energy_after + 1e-3).all())
    assert bool((res.start == 1).any())
    err = rot_err_deg(res.cameras.R, d["cams"].R)
    assert np.median(err) < 0.5
    assert float(res.silhouette_energy.abs().max()) == 0.0


def test_refine_starts_keypoints_only_keeps_each_instances_best_start():
    """Two starts per instance, a near one and one turned by 150 degrees: the result is, per
    instance, the better of the two refined alone (the same energy), and the near start recovers
    the true camera of noise-free keypoints."""
    d = make_scene(11, n=25, k=10, hidden=0.3)
    c = d["cams"]
    near = axis_angle_to_rotation(0.05 * torch.randn(25, 3, generator=torch.Generator().manual_seed(1))) @ c.R
    far = rotation_about_axis(torch.tensor([0.3, 1.0, 0.2]), math.radians(150.0)).to(c.R) @ c.R
    R = torch.stack([far, near], 1)
    s = torch.stack([c.s, c.s * 0.95], 1)
    t = torch.stack([c.t, c.t + 1.0], 1)
    cams, e = refine_starts_keypoints_only(d["S0"], R, s, t, d["kp"], d["vis"])
    alone = [refine_starts_keypoints_only(d["S0"], R[:, b:b + 1], s[:, b:b + 1], t[:, b:b + 1], d["kp"], d["vis"])[1]
             for b in range(2)]
    assert torch.allclose(e, torch.minimum(*alone), rtol=1e-5, atol=1e-6)
    assert float(rot_err_deg(cams.R, c.R).max()) < 0.1 and float(e.max()) < 1e-4
    with pytest.raises(ValueError):
        refine_starts_keypoints_only(d["S0"], R[:3], s[:3], t[:3], d["kp"], d["vis"])


def test_fitted_takes_every_field_from_each_rows_best_start():
    """``Fitted.best_start``: per row the start of the lowest energy, every tensor from that start (none mixed), the
    iteration count kept; ``first_start`` is start 0 alike, and ``cameras`` gives that start's ``R, s, t``."""
    g = torch.Generator().manual_seed(0)
    n, b = 4, 3
    E = torch.tensor([[3.0, 1.0, 2.0], [0.5, 4.0, 1.0], [2.0, 2.5, 0.1], [1.0, 1.0, 9.0]])
    mark = torch.arange(n * b, dtype=torch.float64).reshape(n, b)  # row n, start j -> n * b + j
    R = random_rotations(n * b, generator=g).reshape(n, b, 3, 3)
    fit = Fitted(R=R, s=mark + 1, t=torch.stack([mark, -mark], -1),
                 E_before=mark + 100, E=E, E_kp=mark + 200, E_sil=mark + 300, iterations=7, converged=(mark % 2) == 0)
    won, best = fit.best_start()
    assert best.tolist() == [1, 0, 2, 0] and won.iterations == 7
    rows = torch.arange(n)
    picked = rows * b + best
    assert won.s.tolist() == (picked + 1).tolist() and won.E_kp.tolist() == (picked + 200).tolist()
    assert won.E_before.tolist() == (picked + 100).tolist() and won.E_sil.tolist() == (picked + 300).tolist()
    assert won.E.tolist() == E[rows, best].tolist() and won.converged.tolist() == (picked % 2 == 0).tolist()
    assert torch.equal(won.cameras.R, fit.R[rows, best]) and torch.equal(won.cameras.t[:, 1], -picked.double())
    first = fit.first_start()
    assert first.s.tolist() == (rows * b + 1).tolist() and first.iterations == 7
    assert torch.equal(first.cameras.R, fit.R[:, 0]) and first.E.tolist() == E[:, 0].tolist()


def test_mask_start_cameras_centre_and_scale():
    masks = torch.zeros(2, 40, 50, dtype=torch.bool)
    masks[0, 10:20, 5:25] = True  # 20 wide, 10 high, centre (14.5, 14.5)
    shape = torch.tensor([[-1.0, -0.5, 0.0], [1.0, 0.5, 0.0], [0.0, 0.0, 3.0]])
    kp = torch.tensor([[[0.0, 0.0]] * 3, [[10.0, 10.0], [30.0, 20.0], [0.0, 0.0]]])
    vis = torch.tensor([[False] * 3, [True, True, False]])
    cams = mask_start_cameras(shape, masks, kp, vis)
    assert torch.allclose(cams.R, torch.eye(3).expand(2, 3, 3))
    centroid = shape.mean(0)
    assert torch.allclose(cams.project(centroid[None])[0, 0], torch.tensor([14.5, 14.5]))
    assert float(cams.s[0]) == pytest.approx(20.0 / 2.0)  # mask 20 px vs shape extent 2 in x
    # empty mask: visible keypoints' centre (20, 15) and extent 20
    assert torch.allclose(cams.project(centroid[None])[1, 0], torch.tensor([20.0, 15.0]))
    assert float(cams.s[1]) == pytest.approx(10.0)


# --------------------------------------------------------------------------- unseen images


def test_sphere_rotations_cover_the_sphere():
    R = sphere_rotations(64, dtype=torch.float64)
    assert torch.allclose(R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(64, 3, 3), atol=1e-12)
    assert torch.allclose(torch.det(R), torch.ones(64, dtype=torch.float64))
    d = R[:, 2]
    probe = torch.nn.functional.normalize(torch.randn(2000, 3, generator=torch.Generator().manual_seed(0),
                                                      dtype=torch.float64), dim=1)
    worst = torch.rad2deg(torch.arccos((probe @ d.T).amax(1).clamp(-1, 1))).max()
    assert float(worst) < 20.0  # 64 evenly spread directions: every direction within 20 deg


def test_estimate_camera_for_unseen_images():
    d = make_scene(8, n=40, k=12, hidden=0.3)
    cams, energy = estimate_camera(d["S0"], d["kp"], d["vis"], d["masks"])
    assert len(cams) == 40 and energy.shape == (40,)
    err = rot_err_deg(cams.R, d["cams"].R)
    assert np.median(err) < 0.5 and (err < 5).mean() >= 0.9, np.sort(err)[-5:]
    # scales within 4%: the hull vertices lie on the mask's edge, where the distance to
    # the nearest foreground pixel centre is up to half a pixel, so the silhouette
    # term shrinks the projection by a fraction of a pixel (scale ~20 px per unit)
    assert torch.allclose(cams.s, d["cams"].s, rtol=4e-2)
    # float distance maps give the same cameras as bool masks
    cams2, energy2 = estimate_camera(d["S0"], d["kp"], d["vis"], distance_to_mask(d["masks"]))
    assert torch.allclose(energy, energy2, rtol=1e-4, atol=1e-4)
    # energies are those of the returned cameras
    E = refinement_energy(cams.M, cams.t, d["S0"], d["kp"], d["vis"], distance_to_mask(d["masks"]))
    assert torch.allclose(E, energy, rtol=1e-3, atol=1e-3)
    # more starts never do worse than the identity start alone
    _, e0 = estimate_camera(d["S0"], d["kp"], d["vis"], d["masks"], n_starts=0)
    assert bool((energy <= e0 + 1e-3).all())


@pytest.mark.parametrize("silhouette_weight", [0.0, 1.0])
def test_dropping_finished_rows_changes_no_result(monkeypatch, silhouette_weight):
    """The optimiser's shrinking working set gives the cameras of the full batch run to the end.

    ``COMPACT_FRACTION = 0`` never drops a row (every camera is stepped, finished or not, as before
    the working set existed); the default drops finished rows. Per-camera arithmetic is the same,
    so the results agree to float32 rounding; with keypoints only, each start is its own row.
    """
    d = make_scene(21, n=30, k=12, hidden=0.3)
    dist = distance_to_mask(d["masks"])
    noisy = ScaledOrthographic(d["cams"].R, d["cams"].s * 1.1, d["cams"].t + 2.0)
    runs = {}
    for frac in (0.0, refine_module.COMPACT_FRACTION):
        monkeypatch.setattr(refine_module, "COMPACT_FRACTION", frac)
        cams, e = estimate_camera(d["S0"], d["kp"], d["vis"], dist, silhouette_weight=silhouette_weight)
        ref = refine_cameras(d["S0"], noisy, d["kp"], d["vis"], dist, silhouette_weight=silhouette_weight)
        runs[frac] = (cams, e, ref)
    (c0, e0, r0), (c1, e1, r1) = runs.values()
    assert torch.allclose(e0, e1, rtol=1e-5, atol=1e-5)
    assert torch.allclose(c0.R, c1.R, atol=1e-5) and torch.allclose(c0.t, c1.t, atol=1e-4)
    assert torch.allclose(r0.energy_after, r1.energy_after, rtol=1e-5, atol=1e-5)
    assert torch.allclose(r0.cameras.R, r1.cameras.R, atol=1e-5)
    assert r0.iterations == r1.iterations and torch.equal(r0.converged, r1.converged)


def test_degenerate_instances_stay_finite():
    d = make_scene(10, n=6, k=8)
    vis = d["vis"].clone()
    masks = d["masks"].clone()
    vis[0] = False  # no keypoint, mask only
    vis[1] = False
    vis[1, 0] = True  # one keypoint, mask
    masks[2] = False  # keypoints only
    vis[3] = False
    masks[3] = False  # nothing at all
    cams, energy = estimate_camera(d["S0"], d["kp"], vis, masks)
    assert bool(torch.isfinite(cams.R).all() and torch.isfinite(cams.t).all() and torch.isfinite(energy).all())
    assert float(energy[3]) == 0.0
    res = refine_cameras(d["S0"], d["cams"], d["kp"], vis, distance_to_mask(masks))
    assert bool(torch.isfinite(res.cameras.R).all()) and bool((res.energy_after <= res.energy_before).all())


def test_non_finite_points_never_reach_grid_sample(monkeypatch):
    """NaN and infinite points (a degenerate fit's trial step) give non-finite samples, and
    ``grid_sample`` only ever sees a finite grid inside [-1, 1] (its CPU kernel can crash on NaN)."""
    seen = []
    real = refine_module.F.grid_sample

    def spy(inp, grid, **kw):
        seen.append(grid.clone())
        return real(inp, grid, **kw)

    monkeypatch.setattr(refine_module.F, "grid_sample", spy)
    D = torch.arange(8.0).expand(1, 6, 8)
    pts = torch.tensor([[[float("nan"), 1.0], [float("inf"), 2.0], [2.0, -float("inf")], [3.0, 2.0]]])
    got = sample_distance(D, pts)
    assert seen and bool(torch.isfinite(seen[0]).all()) and float(seen[0].abs().max()) <= 1.0
    assert not bool(torch.isfinite(got[0, :3]).any()) and float(got[0, 3]) == 3.0


def test_collapsed_keypoints_get_no_camera():
    """An image whose visible keypoints all lie on one pixel fixes no scale: it gets a NaN camera and
    an infinite energy; the other images of the batch keep their fits."""
    d = make_scene(11, n=4, k=8, hidden=0.2)
    kp = d["kp"].clone()
    kp[1] = torch.tensor([40.0, 50.0])  # every keypoint of image 1 at one pixel
    kp[2, :, 0] = 30.0 + 0.1 * torch.arange(8)  # spread over less than a pixel
    kp[2, :, 1] = 20.0
    flags = collapsed_keypoints(kp, d["vis"])
    assert flags.tolist() == [False, True, True, False]
    one = d["vis"].clone()
    one[0] = False
    one[0, 0] = True  # a single visible keypoint is no collapse
    assert not bool(collapsed_keypoints(kp, one)[0])
    cams, energy = estimate_camera(d["S0"], kp, d["vis"], d["masks"], max_iters=30)
    assert bool(torch.isnan(cams.s[1:3]).all()) and bool(torch.isinf(energy[1:3]).all())
    assert bool(torch.isfinite(cams.R[[0, 3]]).all()) and bool((cams.s[[0, 3]] > 1).all())


# --------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    "which,value,match",
    [
        ("shape", torch.zeros(5, 2), "shape"),
        ("keypoints", torch.zeros(3, 4, 2), "keypoints"),
        ("visible", torch.ones(3, 4, dtype=torch.bool), "visible"),
        ("dist_maps", torch.zeros(3, 8), "dist_maps"),
        ("dist_maps", torch.zeros(3, 1, 8), "2x2"),
    ],
)
def test_bad_arguments_raise(which, value, match):
    args = {"shape": torch.zeros(5, 3), "keypoints": torch.zeros(3, 5, 2),
            "visible": torch.ones(3, 5, dtype=torch.bool), "dist_maps": torch.zeros(3, 8, 8)}
    args[which] = value
    cams = ScaledOrthographic(torch.eye(3).expand(3, 3, 3), torch.ones(3), torch.zeros(3, 2))
    with pytest.raises(ValueError, match=match):
        refine_cameras(args["shape"], cams, args["keypoints"], args["visible"], args["dist_maps"])


def test_camera_count_mismatch_and_negative_weight():
    cams = ScaledOrthographic(torch.eye(3).expand(2, 3, 3), torch.ones(2), torch.zeros(2, 2))
    with pytest.raises(ValueError, match="cameras"):
        refine_cameras(torch.zeros(5, 3), cams, torch.zeros(3, 5, 2), torch.ones(3, 5, dtype=torch.bool),
                       torch.zeros(3, 8, 8))
    with pytest.raises(ValueError, match="silhouette_weight"):
        refine_cameras(torch.zeros(5, 3), cams, torch.zeros(2, 5, 2), torch.ones(2, 5, dtype=torch.bool),
                       torch.zeros(2, 8, 8), silhouette_weight=-1.0)


# --------------------------------------------------------------------------- device


@pytest.mark.cuda
def test_cuda_matches_cpu():
    d = make_scene(9, n=30, k=10, deform=0.1)
    dm = distance_to_mask(d["masks"])
    start = ScaledOrthographic(rotation_about_axis(torch.tensor([1.0, 0.0, 0.0]), 0.2) @ d["cams"].R,
                               d["cams"].s, d["cams"].t)
    a = refine_cameras(d["S0"], start, d["kp"], d["vis"], dm)
    b = refine_cameras(d["S0"].cuda(), start.to("cuda"), d["kp"].cuda(), d["vis"].cuda(), dm.cuda())
    assert b.cameras.R.device.type == "cuda"
    assert torch.allclose(a.energy_after, b.energy_after.cpu(), rtol=1e-3, atol=1e-2)
    c, e = estimate_camera(d["S0"].cuda(), d["kp"].cuda(), d["vis"].cuda(), d["masks"].cuda())
    assert c.R.device.type == "cuda" and bool(torch.isfinite(e).all())


def test_refine_cameras_hands_the_masks_to_the_twin_rule_and_keeps_its_choice(monkeypatch):
    """``refine_cameras`` asks :func:`twin_wins` about the flat rows with their masks (``dist == 0``) under
    ``twin_hull`` and none without it, rows without a silhouette term get empty masks, and ``start`` is the rule's
    answer: a spy that always picks the twin makes every tried row start 1."""
    d = make_scene(6, n=12, k=10, deform=0.2)
    dm = distance_to_mask(d["masks"])
    sfm = rigid_sfm(d["kp"], d["vis"])
    seen = []

    def spy(shape, own, energy, twin, twin_energy, masks, margin):
        seen.append(masks)
        return torch.ones_like(energy, dtype=torch.bool)

    monkeypatch.setattr(refine_module, "twin_wins", spy)
    valid = torch.ones(12, dtype=torch.bool)
    valid[3] = False
    for hull in (True, False):
        r = refine_cameras(sfm.shape, sfm.cameras, d["kp"], d["vis"], dm, max_iters=5, twin_flatness=1.0,
                           twin_hull=hull, mask_valid=valid)
        assert (r.start == 1).all()
    assert seen[1] is None
    expected = d["masks"].clone()
    expected[3] = False
    assert torch.equal(seen[0], expected)
