"""Tests for carvi_torch.viewpoints.mixture: a mixture of rigid SfM shapes per class.

Per function: known values against scipy / analytic answers; the whole fit on a class made of
two rigid shapes seen by photo-like cameras (exact keypoints up to 0.2 px noise), where the
answer is known: two groups, the true split, and cameras far better than one shape gives.
"""
from __future__ import annotations

import copy
import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import render_cad_class
from carvi_torch.viewpoints import sfm, mixture as mix
from carvi_torch.cameras import Similarity2D
from carvi_torch.collection import ClassCollection, ClassMeta, infer_flip_pairs
from carvi_torch.sdf import distance_to_mask
from carvi_torch.synthetic.render import sample_cameras
from carvi_torch.evaluation.viewpoint_metrics import viewpoint_report
from carvi_torch.io.results import cameras_json
from carvi_torch.surrogates import cluster_instances
from carvi_torch.viewpoints import class_sfm, estimate_viewpoints
from carvi_torch.viewpoints.refine import cameras_from_mean_shape, refine_with_shape


# --------------------------------------------------------------------------- pieces


def test_group_rows_pairs_every_object_with_its_mirrored_copy():
    assert mix.group_rows(torch.tensor([0, 3]), 5).tolist() == [0, 3, 5, 8]


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


def test_top_up_never_takes_a_donor_below_the_bound():
    gen = torch.Generator().manual_seed(3)
    labels = torch.cat([torch.zeros(16, dtype=torch.long), torch.ones(30, dtype=torch.long)])
    cost = torch.rand(46, 3, generator=gen)
    cost[:16, 2] = -1.0  # group 0's objects are the cheapest to move into group 2
    out = mix.top_up(labels, cost, 3, 15)
    assert torch.bincount(out, minlength=3).tolist() == [15, 16, 15]


def test_kmeans_labels_separates_clear_clusters_and_is_deterministic():
    gen = torch.Generator().manual_seed(2)
    X = torch.cat([torch.randn(20, 4, generator=gen) * 0.1, torch.randn(15, 4, generator=gen) * 0.1 + 3.0])
    a, b = mix.kmeans_labels(X, 2, seed=5), mix.kmeans_labels(X, 2, seed=5)
    assert torch.equal(a, b)
    assert len(set(a[:20].tolist())) == 1 and len(set(a[20:].tolist())) == 1 and a[0] != a[-1]


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


def test_fill_missing_rows_poses_the_full_shape_onto_the_group_shape():
    gen = torch.Generator().manual_seed(8)
    S_full = torch.randn(10, 3, generator=gen, dtype=torch.float64)
    Q = torch.as_tensor(Rotation.from_rotvec([0.2, 0.9, -0.4]).as_matrix())
    exact = 1.7 * S_full @ Q + torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    S = exact.clone()
    S[[2, 7]] = float("nan")  # keypoints no member of the group shows
    S_full_nan = S_full.clone()
    S_full_nan[9] = float("nan")  # and one the class lacks too
    S[9] = float("nan")
    out = mix.fill_missing_rows(S, S_full_nan)
    assert torch.allclose(out[[2, 7]], exact[[2, 7]], atol=1e-10)
    assert torch.equal(out[:2], S[:2]) and bool(torch.isnan(out[9]).all())
    assert mix.fill_missing_rows(exact, S_full) is exact  # nothing missing: unchanged
    S[3:] = float("nan")  # 2 shared rows: no pose
    with pytest.raises(mix.SplitFailed, match="share 2"):
        mix.fill_missing_rows(S, S_full)


def _random_cameras(n, seed):
    from carvi_torch.cameras import ScaledOrthographic, random_rotations

    g = torch.Generator().manual_seed(seed)
    return ScaledOrthographic(random_rotations(n, g), 10 + 5 * torch.rand(n, generator=g),
                              60 + 5 * torch.randn(n, 2, generator=g))


def test_transfer_cameras_known_values():
    """Equal shapes give the cameras back; a similar copy ``c S Q0 + m`` is projected exactly as
    the original (every point); a rotated copy gives ``R Q0``. Independent: scipy's rotation."""
    g = torch.Generator().manual_seed(3)
    S = torch.randn(10, 3, generator=g, dtype=torch.float64)
    cams = _random_cameras(7, 0)
    cams = type(cams)(cams.R.double(), cams.s.double(), cams.t.double())
    same = mix.transfer_cameras(cams, S, S)
    assert torch.allclose(same.R, cams.R, atol=1e-10) and torch.allclose(same.s, cams.s)
    assert torch.allclose(same.t, cams.t, atol=1e-9)
    Q0 = torch.as_tensor(Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix())
    S2 = 2.5 * S @ Q0 + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    moved = mix.transfer_cameras(cams, S, S2)
    assert torch.allclose(moved.project(S2), cams.project(S), atol=1e-9)
    assert torch.allclose(moved.R, cams.R @ Q0, atol=1e-10) and torch.allclose(moved.s, cams.s / 2.5)
    # NaN rows are ignored for the alignment; they stay NaN when projected
    S3 = S2.clone()
    S3[[1, 4]] = float("nan")
    part = mix.transfer_cameras(cams, S, S3)
    assert torch.allclose(part.R, moved.R, atol=1e-9) and torch.allclose(part.t, moved.t, atol=1e-8)


def test_transfer_cameras_needs_three_shared_points():
    S = torch.randn(5, 3)
    T = S.clone()
    T[2:] = float("nan")
    with pytest.raises(ValueError, match="share 2"):
        mix.transfer_cameras(_random_cameras(3, 1), S, T)


def test_warm_and_cold_em_agree_on_two_shapes(two_shapes):
    """The warm-started EM (keypoint fits from the last round's cameras, SfM from the group's last
    shape) ends where the EM that searches the sphere and starts every SfM cold ends: same labels,
    keypoint costs within 2% per object, rotations within 0.5 degrees once the groups' frames
    (each SfM's own choice) are aligned."""
    coll, both, dist, R, truth, fitted = two_shapes
    n = len(coll)
    single = fitted.single  # the one-shape SfM of this class (_sfm(both)): the fit ran it
    cost1, cams1 = mix.keypoint_fit(single.shape, both, dist, n)
    start = truth.clone()
    start[:3] = 1 - start[:3]  # three objects start in the wrong group
    runs = {}
    for warm in (None, (single.shape, cams1)):
        runs[warm is not None] = mix.hard_em(both, n, dist, _shared_sfm, start, 2, 6, rounds=6, full_shape=single.shape,
                                             warm=warm)
    (lab_c, _g, cost_c, rot_c, _hist_c), (lab_w, _gw, cost_w, rot_w, hist_w) = runs[False], runs[True]
    assert torch.equal(lab_c, truth) and torch.equal(lab_w, truth)
    assert torch.allclose(cost_w, cost_c, rtol=0.02, atol=0.05), (cost_w - cost_c).abs().max()
    from carvi_torch.evaluation.viewpoint_metrics import geodesic_errors

    for Rc, Rw in zip(rot_c, rot_w):  # a group's frame is SfM's choice: the two differ by one rotation
        D = Rw.double().transpose(1, 2) @ Rc.double()
        assert float(geodesic_errors(D, D[:1].expand_as(D)).max()) < 0.5
    assert len(hist_w) >= 2  # the warm path ran at least one warm round


def test_a_warm_sfm_that_fails_is_run_cold(two_shapes):
    """A warm-started SfM that raises a linear-algebra error is a lost shortcut, not a lost split:
    the group's SfM is run again cold and the EM ends as it does with cold starts only."""
    coll, both, dist, R, truth, fitted = two_shapes
    n = len(coll)
    calls = []

    def flaky(sub, init_shape=None):
        calls.append(init_shape is not None)
        if init_shape is not None:
            raise torch.linalg.LinAlgError("singular")
        return _shared_sfm(sub)

    single = fitted.single  # _sfm(both), run by the fit
    _c, cams1 = mix.keypoint_fit(single.shape, both, dist, n)
    start = truth.clone()
    start[:3] = 1 - start[:3]  # a second round is needed, whose SfM starts warm
    lab, groups, *_ = mix.hard_em(both, n, dist, flaky, start, 2, 6, rounds=3, full_shape=single.shape,
                                  warm=(single.shape, cams1))
    assert torch.equal(lab, truth) and len(groups) == 2
    assert True in calls and calls.count(False) >= 3  # warm tries failed and were rerun cold


def test_warm_sfm_from_a_rotated_solution_matches_the_cold_one():
    """``rigid_sfm(init_shape=...)`` from the cold solution turned and scaled arbitrarily ends at
    the same fit: the same residuals and the same cameras up to the frame's rotation."""
    coll, _R, _truth = _two_shape_class(sizes=(20, 0), noise=0.3)
    cold = _sfm(coll)
    Q0 = torch.as_tensor(Rotation.from_rotvec([0.2, 0.9, -0.4]).as_matrix(), dtype=torch.float32)
    warm = _sfm(coll, init_shape=3.0 * cold.shape @ Q0 + 1.0)
    assert warm.iterations <= sfm.WARM_OUTER < cold.iterations
    assert torch.allclose(warm.residual, cold.residual, rtol=1e-3, atol=1e-3)
    Q = mix.rotation_onto(warm.shape, cold.shape)  # the two frames differ by a rotation at most
    from carvi_torch.evaluation.viewpoint_metrics import geodesic_errors

    assert float(geodesic_errors(warm.cameras.R.double() @ Q.double(), cold.cameras.R.double()).max()) < 0.05
    with pytest.raises(ValueError, match="init_shape"):
        _sfm(coll, init_shape=torch.zeros(5, 3))


# --------------------------------------------------------------------------- the whole fit


def _car(length: float, height: float, roof: float) -> tuple[torch.Tensor, list]:
    """12 keypoints of a box with a roof, PASCAL3D+ frame: +z up, front towards -y, the object's left +x."""
    pts, names = [], []
    for side, sx in (("left", 1), ("right", -1)):
        for end, sy in (("front", -1), ("back", 1)):
            for level, z in (("low", 0.0), ("high", height)):
                pts.append([0.9 * sx, sy * length, z])
                names.append(f"{side}_{end}_{level}")
            pts.append([0.63 * sx, sy * length * roof, 1.5 * height])
            names.append(f"{side}_{end}_roof")
    return torch.tensor(pts), names


def _two_shape_class(sizes=(12, 12), seed=0, noise=0.2, same_shape=False):
    """A class of ``sizes[0]`` long low cars and ``sizes[1]`` short tall ones, every keypoint visible.

    Returns the collection, the true rotations ``(n, 3, 3)`` and the true group of every object."""
    g = torch.Generator().manual_seed(seed)
    A, names = _car(2.0, 0.5, 0.4)
    B = A if same_shape else _car(1.2, 0.9, 0.8)[0]
    X = torch.cat([S.expand(m, -1, -1) for S, m in zip((A, B), sizes)])
    n, K = X.shape[:2]
    C = 128
    cam = sample_cameras(n, g, image_size=C, radius=2.3)
    kp = cam.project(X) + noise * torch.randn(n, K, 2, generator=g)
    yy, xx = torch.meshgrid(torch.arange(C), torch.arange(C), indexing="ij")
    lo, hi = kp.amin(1), kp.amax(1)
    masks = ((xx[None] >= lo[:, 0, None, None]) & (xx[None] <= hi[:, 0, None, None])
             & (yy[None] >= lo[:, 1, None, None]) & (yy[None] <= hi[:, 1, None, None]))  # boxes: sizes only
    coll = ClassCollection(ClassMeta("t", names, infer_flip_pairs(names)), masks, kp,
                           torch.ones(n, K, dtype=torch.bool), Similarity2D(torch.ones(n), torch.zeros(n, 2)),
                           torch.tensor([[C, C]] * n), list(range(n)), list(range(n)), list(range(n)),
                           torch.arange(n), torch.zeros(n, dtype=torch.bool))
    truth = torch.cat([torch.full((m,), i) for i, m in enumerate(sizes)])
    return coll, cam.R, truth


def _sfm(sub, init_shape=None, **options):
    m = sub.meta
    return sfm.rigid_sfm(sub.keypoints, sub.visible, keypoint_names=m.keypoint_names, flip_pairs=m.flip_pairs,
                         left_convention="object", init_shape=init_shape, **options)


_SFM_FITS: dict = {}


def _shared_sfm(sub, init_shape=None):
    """:func:`_sfm`, each sub-collection's fit computed once per module and handed out as a copy: the fits of
    the two-shape class that several tests repeat (the same groups of the same objects, the same start). The
    SfM is deterministic (same input, same result, bit for bit: checked by the thread test, whose two-thread
    fit runs :func:`_sfm` itself, as the tests of the SfM proper do), so a test gets what its own call would
    compute."""
    key = tuple(None if t is None else (tuple(t.shape), t.numpy().tobytes())
                for t in (sub.keypoints, sub.visible, init_shape))
    if key not in _SFM_FITS:
        _SFM_FITS[key] = _sfm(sub, init_shape)
    return copy.deepcopy(_SFM_FITS[key])


def _capped_sfm(max_outer: int):
    """:func:`_sfm` with at most ``max_outer`` outer steps, for tests whose check does not need the
    converged fit (what is recorded, which keypoints are kept or left out, the bookkeeping of a split)."""
    return lambda sub, init_shape=None: _sfm(sub, init_shape, max_outer=max_outer)


def _class_cameras(res: mix.MixtureResult) -> torch.Tensor:
    R = res.single.cameras.R.clone()
    for g in range(res.k):
        R[res.groups[g][0]] = res.cameras(g).R
    return R


#: The pipeline's default decision whether a class is one shape (``sfm_group_misfit``, ``sfm_group_hull_gain``).
GATE = {"min_misfit": 0.025, "hull_gain": 0.01}


@pytest.fixture(scope="module")
def two_shapes():
    coll, R, truth = _two_shape_class()
    both = coll.with_mirrors()
    dist = distance_to_mask(both.masks)
    fitted = mix.fit_mixture_of_shapes(both, dist, _shared_sfm, max_groups=2, min_size=6, **GATE)
    return coll, both, dist, R, truth, fitted


def test_gate_defaults_are_the_pipeline_defaults():
    from carvi_torch.config import ViewpointConfig

    cfg = ViewpointConfig()
    assert GATE == {"min_misfit": cfg.sfm_group_misfit, "hull_gain": cfg.sfm_group_hull_gain}


def test_misfit_against_a_loop():
    """Median over the rows with a camera of residual / mask-box diagonal, checked against numpy."""
    gen = torch.Generator().manual_seed(5)
    masks = torch.zeros(5, 20, 20, dtype=torch.bool)
    boxes = [(2, 9, 3, 15), (0, 20, 0, 20), (5, 6, 5, 8), (4, 12, 1, 3), (7, 17, 9, 18)]
    for m, (y0, y1, x0, x1) in zip(masks, boxes):
        m[y0:y1, x0:x1] = True
    res = type("R", (), {})()
    res.residual = torch.rand(5, generator=gen) * 3
    res.valid = torch.tensor([True, True, False, True, True])
    rel = sorted(float(res.residual[i]) / np.hypot(y1 - y0, x1 - x0)
                 for i, (y0, y1, x0, x1) in enumerate(boxes) if bool(res.valid[i]))
    want = rel[(len(rel) - 1) // 2]  # the lower median of an even count, as torch's
    assert mix.misfit(res, masks) == pytest.approx(want, abs=1e-6)
    res.valid[:] = False
    assert np.isnan(mix.misfit(res, masks))


def test_the_automatic_decision_splits_a_class_of_two_proportions(two_shapes):
    """Long low cars and short tall ones: one rigid shape misfits them (residual over 3% of the box
    diagonal), both starts of the two-group split raise the masks' agreement with the projected hulls
    by more than 0.01, so the default decision keeps two shapes, the true ones."""
    coll, both, dist, R, truth, fitted = two_shapes
    assert fitted.misfit >= GATE["min_misfit"] and fitted.note is None
    assert fitted.k == 2 and bool((fitted.labels == truth).all() or (fitted.labels == 1 - truth).all())
    assert len(fitted.candidates) == 2 and all(c["hull_gain"] >= GATE["hull_gain"] for c in fitted.candidates)
    # the recorded gain is the median over rows of the split's hull agreement minus one shape's
    one = mix.fit_mixture_of_shapes(both, dist, _sfm, max_groups=1, single=fitted.single)
    gain = (mix.hull_agreements(fitted, both.masks) - mix.hull_agreements(one, both.masks)).median()
    kept = next(c for c in fitted.candidates if c["kept"])
    assert kept["hull_gain"] == pytest.approx(float(gain), abs=1e-5)
    assert fitted.summary()["misfit"] == fitted.misfit


def test_group_shapes_are_centred_and_project_as_their_own_sfm(two_shapes):
    """In the class frame every group's shape is centred on the keypoints all groups placed (here every one),
    and its cameras project it where the group's own SfM cameras project the group's own shape. A group whose
    SfM put its origin elsewhere (its shape shifted, its cameras' translations with it: the same projections)
    gives the same class-frame shape and cameras, and a row filled from the class's shape (seen by none of the
    group's objects) does not move the origin however it was placed."""
    *_, fitted = two_shapes
    assert fitted.k == 2
    for g, (_rows, res) in enumerate(fitted.groups):
        S = fitted.shape(g)
        ok = torch.isfinite(S).all(-1)
        torch.testing.assert_close(S[ok].mean(0), torch.zeros(3, dtype=S.dtype), atol=1e-5, rtol=0)
        own = res.cameras.project(torch.nan_to_num(res.shape))[res.valid][:, ok]
        torch.testing.assert_close(fitted.cameras(g).project(torch.nan_to_num(S))[res.valid][:, ok], own,
                                   atol=1e-3, rtol=1e-5)
    rows, res = fitted.groups[1]
    d = torch.tensor([0.3, -0.2, 0.5], dtype=res.shape.dtype) * res.shape[torch.isfinite(res.shape).all(-1)].std()
    c = res.cameras
    shifted = type(c)(c.R, c.s, c.t - c.s[:, None] * (c.R[:, :2, :] @ d))
    moved = dataclasses.replace(res, shape=res.shape + d, cameras=shifted)
    off = dataclasses.replace(fitted, groups=[fitted.groups[0], (rows, moved)])
    torch.testing.assert_close(moved.cameras.project(torch.nan_to_num(moved.shape)),
                               c.project(torch.nan_to_num(res.shape)), atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(off.shape(1), fitted.shape(1), atol=1e-4, rtol=1e-5)
    torch.testing.assert_close(off.cameras(1).t, fitted.cameras(1).t, atol=1e-3, rtol=1e-5)
    mask = torch.zeros(len(res.shape), dtype=torch.bool)
    mask[0] = True
    filled = dataclasses.replace(res, shape=res.shape.clone(), filled=mask)
    filled.shape[0] += 5.0 * d
    far = dataclasses.replace(fitted, groups=[fitted.groups[0], (rows, filled)])
    kept = fitted.shape(1)[1:]  # every group's origin is now the centroid of rows 1.., the moved row's aside
    torch.testing.assert_close(far.shape(1)[1:], kept - kept.mean(0), atol=1e-3, rtol=1e-5)
    torch.testing.assert_close(far.shape(0)[1:].mean(0), torch.zeros(3, dtype=kept.dtype), atol=1e-5, rtol=0)
    own = res.cameras.project(torch.nan_to_num(res.shape))[res.valid][:, 1:]
    torch.testing.assert_close(far.cameras(1).project(far.shape(1))[res.valid][:, 1:], own, atol=1e-3, rtol=1e-5)


def test_a_keypoint_one_object_of_a_group_shows_is_filled_and_leaves_the_origin(two_shapes):
    """Through the real fill path: a keypoint shown by one object of a group only gets no row from the group's
    SfM (it needs two views), is filled from the class's shape and marked ``filled``; the groups' origin is the
    centroid of the keypoints both groups placed, so it leaves that keypoint out of every group."""
    _coll, both, _dist, _R, _truth, fitted = two_shapes
    n, g = len(both) // 2, 1
    members = (fitted.labels == g).nonzero().squeeze(1)
    vis = both.visible.clone()
    hide = torch.cat([members[1:], members + n])
    vis[hide, 0] = False  # keypoint 0: one object of group 1, in one view (not in the mirrored copies)
    sub = both.replace(visible=vis)
    rows, res = mix._group_sfm(sub, fitted.labels, g, n, _sfm, fitted.single.shape)
    assert bool(res.filled[0]) and not bool(res.filled[1:].any())
    _rows0, res0 = mix._group_sfm(sub, fitted.labels, 0, n, _sfm, fitted.single.shape)
    assert res0.filled is not None and not bool(res0.filled.any())
    two = dataclasses.replace(fitted, groups=[(_rows0, res0), (rows, res)])
    for h in range(2):
        S = two.shape(h)
        torch.testing.assert_close(S[1:].mean(0), torch.zeros(3, dtype=S.dtype), atol=1e-4, rtol=0)


def test_the_automatic_decision_keeps_one_shape_for_one_proportion():
    """One rigid shape (0.2 px noise): the one-shape fit leaves a residual far under 3% of the box
    diagonal, so no split is even tried (the mixture's cost is saved) and the class keeps one shape."""
    coll, _R, _truth = _two_shape_class(sizes=(12, 12), seed=1, same_shape=True)
    both = coll.with_mirrors()
    calls = []

    def counted(sub, init_shape=None):
        calls.append(len(sub))
        return _sfm(sub, init_shape)

    fitted = mix.fit_mixture_of_shapes(both, distance_to_mask(both.masks), counted, max_groups=3, min_size=6, **GATE)
    assert fitted.k == 1 and fitted.candidates == [] and calls == [48]  # the one-shape SfM only
    assert fitted.misfit < 0.01 and "fits" in fitted.note and fitted.summary()["misfit"] == fitted.misfit


def test_split_labels_splits_the_costliest_group_with_room_for_two():
    X = torch.tensor([[0.0], [0.1], [0.2], [5.0], [5.1], [9.0], [9.1], [9.2], [20.0], [20.1]])
    labels = torch.tensor([0, 0, 0, 1, 1, 1, 1, 1, 2, 2])
    cost = torch.zeros(10, 3)
    cost[:3, 0] = 1.0
    cost[3:8, 1] = 2.0
    cost[8:, 2] = 50.0  # the costliest group, but too small to split into two of 2
    out = mix.split_labels(labels, cost, X, 2, seed=0)
    # group 1 (sum 10) splits by its features: {5.0, 5.1} (the smaller part) becomes group 3
    assert out.tolist() == [0, 0, 0, 3, 3, 1, 1, 1, 2, 2]
    assert torch.equal(out, mix.split_labels(labels, cost, X, 2, seed=0))  # deterministic
    assert mix.split_labels(labels, cost, X, 3, seed=0) is None  # no group has 6 objects


def test_split_labels_of_equal_parts_moves_the_part_without_the_first_object(monkeypatch):
    """Equal parts: whichever k-means label the group's first object gets, its part keeps the group."""
    one, cost, X = torch.zeros(4, dtype=torch.long), torch.ones(4, 1), torch.zeros(4, 1)
    for parts in ([0, 0, 1, 1], [1, 1, 0, 0], [1, 0, 0, 1]):
        monkeypatch.setattr(mix, "kmeans_labels", lambda X_, k, seed, p=parts: torch.tensor(p))
        out = mix.split_labels(one, cost, X, 2, seed=0)
        assert out.tolist() == [0 if q == parts[0] else 1 for q in parts], parts


def test_split_labels_gives_up_on_a_group_k_means_cannot_split():
    """A group whose rows of ``X`` are all alike (objects without an SfM camera lift to zeros): k-means finds
    one part, so there is no split start (rather than an empty group that top-up fills arbitrarily)."""
    labels = torch.tensor([0] * 6 + [1] * 4)
    cost = torch.zeros(10, 2)
    cost[:6, 0] = 5.0
    with pytest.warns(UserWarning):  # scipy: one of the two clusters is empty
        assert mix.split_labels(labels, cost, torch.zeros(10, 3), 2, seed=0) is None
    cost[6:, 1] = 1.0
    assert mix.split_labels(labels, cost, torch.rand(10, 3, generator=torch.Generator().manual_seed(0)), 2,
                            seed=0) is not None


def test_the_next_k_also_starts_from_the_kept_groups_split_in_two(two_shapes, monkeypatch):
    """Three groups tried after the two true ones: besides the k-means and quantile starts, the EM starts
    from the kept two groups with one of them split in two (the kept split's costs decide which)."""
    coll, both, dist, R, truth, fitted = two_shapes
    starts, ends, em = [], [], mix.hard_em

    def recorded(both_, n, dist_, sfm_fn, labels, k, *args, **kwargs):
        starts.append((k, labels.clone()))
        ends.append(em(both_, n, dist_, sfm_fn, labels, k, *args, **kwargs))
        return ends[-1]

    monkeypatch.setattr(mix, "hard_em", recorded)
    three = mix.fit_mixture_of_shapes(both, dist, _shared_sfm, max_groups=3, min_size=6, single=fitted.single,
                                      rounds=1, threads=1)
    inits = [(c["k"], c["init"]) for c in three.candidates]
    assert inits == [(2, "lifted"), (2, "residual"), (3, "lifted"), (3, "residual"), (3, "split")]
    assert [k for k, _ in starts] == [2, 2, 3, 3, 3]
    kept = next(i for i, c in enumerate(three.candidates) if c["kept"] and c["k"] == 2)
    kept2, cost2 = ends[kept][0], ends[kept][2]
    split = starts[-1][1]
    moved = split == 2
    assert 6 <= int(moved.sum()) <= 12 and len(set(kept2[moved].tolist())) == 1  # one kept group split in two
    own = cost2.gather(1, kept2[:, None])[:, 0]
    sse = [float(own[kept2 == g].sum()) for g in range(2)]
    assert int(kept2[moved][0]) == max(range(2), key=sse.__getitem__)  # the costlier one
    assert torch.equal(split[~moved], kept2[~moved])


def test_fit_finds_the_two_shapes_and_their_cameras(two_shapes):
    coll, both, dist, R, truth, fitted = two_shapes
    n = len(coll)
    assert fitted.k == 2
    agree = (fitted.labels == truth).all() or (fitted.labels == 1 - truth).all()
    assert bool(agree), fitted.labels.tolist()
    kept = [c for c in fitted.candidates if c["kept"]]
    assert len(kept) == 1 and kept[0]["cut"] > 0.9 and kept[0]["agreement_deg"] < 60
    # the EM's record: rounds run, objects moved after each; below 400 objects settled means none moved
    for c in fitted.candidates:
        assert 1 <= c["rounds"] <= 7 and len(c["moved"]) == c["rounds"]
        assert c["settled"] == (c["moved"][-1] == 0)
    assert kept[0]["settled"]
    capped = mix.fit_mixture_of_shapes(both, dist, _shared_sfm, max_groups=2, min_size=6, rounds=0,
                                       single=fitted.single)
    assert all(c["rounds"] == 1 for c in capped.candidates)
    assert [c["settled"] for c in capped.candidates] == [c["moved"][0] == 0 for c in capped.candidates]
    one = mix.fit_mixture_of_shapes(both, dist, _sfm, max_groups=1, single=fitted.single)  # the one-shape SfM
    err_mix = viewpoint_report(_class_cameras(fitted)[:n].double(), R.double())
    err_one = viewpoint_report(_class_cameras(one)[:n].double(), R.double())
    assert not err_mix["mirrored"]
    # 0.2 px noise on 12 keypoints: the two-shape cameras are within 1 degree (median); one shape is not
    assert err_mix["geodesic"]["median"] < 1.0
    assert err_one["geodesic"]["median"] > 3.0
    # every group's shape in the class frame is its own box, up to scale: group shapes differ
    S0, S1 = fitted.shape(0), fitted.shape(1)
    assert S0.shape == S1.shape == (12, 3) and not torch.allclose(S0 / S0.norm(), S1 / S1.norm(), atol=0.05)


def test_fit_on_two_threads_equals_the_fit_on_one(two_shapes):
    """Each ``k``'s initialisations on two Python threads (the default, here with the class-size
    bound lowered to this small class): every label, candidate, shape and camera is the same as on
    one thread, bit for bit. The two-thread run really used two worker threads, and leaves the
    caller's intra-op thread count as it was. Below the bound the fit stays on the caller's thread, and
    is the fixture's fit again (the default ``threads=2``): the same seed gives the same fit, bit for bit
    (the fit is deterministic). That fit on the caller's thread is the one-thread reference (``threads=1``
    takes the same path: one worker). It takes the fixture's SfM fits (:func:`_shared_sfm`); the two-thread
    run computes its own, so an SfM that is not deterministic fails the last comparison."""
    import threading

    coll, both, dist, R, truth, fitted = two_shapes
    seen = set()
    sfm_fn = _shared_sfm

    def traced(sub, init_shape=None):
        seen.add(threading.get_ident())
        return sfm_fn(sub, init_shape)

    def assert_same_fit(a, b):
        assert a.k == b.k and torch.equal(a.labels, b.labels)
        assert a.candidates == b.candidates
        assert len(a.groups) == len(b.groups) and len(a.Q) == len(b.Q)
        for (ra, x), (rb, y) in zip(a.groups, b.groups):
            assert torch.equal(ra, rb) and torch.equal(x.shape, y.shape) and torch.equal(x.cameras.R, y.cameras.R)
        assert all(torch.equal(qa, qb) for qa, qb in zip(a.Q, b.Q))

    assert len(coll) < mix.THREADS_MIN_OBJECTS
    small = mix.fit_mixture_of_shapes(both, dist, traced, max_groups=2, min_size=6, threads=2, **GATE)
    assert seen == {threading.get_ident()}  # one thread: the caller's
    assert_same_fit(small, fitted)
    assert fitted.candidates and [c["init"] for c in fitted.candidates] == ["lifted", "residual"]  # in order
    seen.clear()
    sfm_fn = _sfm  # every SfM computed anew, on the worker threads
    lines = []
    before = torch.get_num_threads()
    again = mix.fit_mixture_of_shapes(both, dist, traced, max_groups=2, min_size=6, threads=2, log=lines.append,
                                      threads_min_objects=1, **GATE)
    assert torch.get_num_threads() == before
    assert len(seen - {threading.get_ident()}) == 2, seen  # both initialisations ran on worker threads
    assert [line.split("'")[1] for line in lines] == ["lifted", "residual"]  # logged in order
    assert_same_fit(again, small)


def test_an_error_on_a_worker_thread_reaches_the_caller(two_shapes):
    import threading

    coll, both, dist, R, truth, fitted = two_shapes

    def broken(sub, init_shape=None):
        if threading.current_thread() is not threading.main_thread():  # only on the workers
            raise RuntimeError("solver exploded")
        return _shared_sfm(sub, init_shape)

    with pytest.raises(RuntimeError, match="solver exploded"):
        mix.fit_mixture_of_shapes(both, dist, broken, max_groups=2, min_size=6, threads=2, threads_min_objects=1)


def test_fit_keeps_one_shape_when_the_frames_must_agree_closely(two_shapes):
    coll, both, dist, R, truth, fitted = two_shapes
    strict = mix.fit_mixture_of_shapes(both, dist, _shared_sfm, max_groups=2, min_size=6, agreement_deg=0.01,
                                       single=fitted.single)
    assert strict.k == 1 and not any(c["eligible"] or c["kept"] for c in strict.candidates)
    assert torch.equal(strict.shape(0), strict.single.shape)  # one group: the SfM shape itself


def test_fit_keeps_one_shape_for_one_rigid_shape():
    coll, R, _truth = _two_shape_class(sizes=(12, 12), seed=1, same_shape=True)
    both = coll.with_mirrors()
    # 40 outer steps: every candidate's cut is the converged fits' (0.10 and 0.08), the groups' residuals being the
    # bundle polish's
    fitted = mix.fit_mixture_of_shapes(both, distance_to_mask(both.masks), _capped_sfm(40), max_groups=2, min_size=6)
    assert fitted.k == 1 and (fitted.labels == 0).all()
    assert all(c["cut"] <= 0.3 for c in fitted.candidates)  # a second shape explains only noise


def test_shape_thickness_known_values():
    assert mix.shape_thickness(torch.tensor([[0.0, 0, 0], [2, 0, 0], [0, 1, 0], [2, 1, 0]])) == 0.0
    assert mix.shape_thickness(torch.zeros(2, 3)) == 0.0  # fewer than 3 points
    g = torch.Generator().manual_seed(0)
    S = torch.randn(9, 3, generator=g, dtype=torch.float64) * torch.tensor([3.0, 2.0, 0.5], dtype=torch.float64)
    S[4] = float("nan")  # ignored
    X = S[torch.isfinite(S).all(-1)].numpy()
    ev = np.linalg.eigvalsh(np.cov(X.T))  # independent: numpy, ascending
    assert mix.shape_thickness(S) == pytest.approx(float(np.sqrt(ev[0] / ev[1])), rel=1e-9)


def test_a_group_whose_keypoints_are_coplanar_is_not_usable(monkeypatch):
    """Objects of the second shape show only the 4 ground-level keypoints (one plane): a group of
    them alone cannot fix its cameras' tilt, so EM with that group stops the candidate (the fit
    records it and keeps fewer groups); mixed with 3D objects, the group is usable."""
    coll, _R, truth = _two_shape_class(seed=2)
    low = [i for i, name in enumerate(coll.meta.keypoint_names) if name.endswith("_low")]
    assert len(low) == 4
    coll.visible[truth == 1] = False
    coll.visible[(truth == 1).nonzero()[:, :1], torch.tensor(low)] = True
    both = coll.with_mirrors()
    dist = distance_to_mask(both.masks)
    n = len(coll)
    fit = _capped_sfm(40)  # the groups' thicknesses (0.008 planar, 0.38 mixed) are those of the converged fits
    full = fit(both).shape
    with pytest.raises(mix.SplitFailed, match="coplanar"):
        mix.hard_em(both, n, dist, fit, truth, 2, 6, rounds=0, full_shape=full)
    mixed = truth.clone()
    mixed[:3] = 1  # three objects that show every keypoint join the planar ones
    _lab, groups, _c, _r, _h = mix.hard_em(both, n, dist, fit, mixed, 2, 6, rounds=0, full_shape=full)
    assert all(mix.shape_thickness(res.shape) > 0.1 for _rows, res in groups)
    monkeypatch.setattr(mix, "PLANAR_THICKNESS", 0.0)  # the rule off: the planar group passes
    _lab, groups, _c, _r, _h = mix.hard_em(both, n, dist, fit, truth, 2, 6, rounds=0, full_shape=full)
    assert len(groups) == 2


def test_fit_small_class_runs_one_sfm_only():
    coll, _R, _truth = _two_shape_class(sizes=(5, 5))
    both = coll.with_mirrors()
    calls = []

    def counted(sub):
        calls.append(len(sub))
        return _sfm(sub)

    fitted = mix.fit_mixture_of_shapes(both, distance_to_mask(both.masks), counted, max_groups=3, min_size=6)
    assert fitted.k == 1 and calls == [20] and fitted.candidates == []
    assert "10 objects" in fitted.summary()["note"]


def test_fit_rejects_bad_arguments():
    coll, _R, _truth = _two_shape_class(sizes=(3, 3))
    both = coll.with_mirrors()
    with pytest.raises(ValueError, match="max_groups"):
        mix.fit_mixture_of_shapes(both, distance_to_mask(both.masks), _sfm, max_groups=0)
    with pytest.raises(ValueError, match="threads"):
        mix.fit_mixture_of_shapes(both, distance_to_mask(both.masks), _sfm, threads=0)


# --------------------------------------------------------------------------- in the pipeline


def test_pipeline_viewpoints_refine_every_group_with_its_own_shape(two_shapes, monkeypatch):
    """``sfm_groups=2``: the pipeline's cameras (SfM and refined) of the two-shape class, its
    ``cameras.json`` entries, and the one-shape default unchanged by the new code path. A group's
    cold SfM runs with :data:`~carvi_torch.viewpoints.mixture.COLD_GROUP_SFM` (the rigid model only),
    a warm one and the class's own SfM with the run's settings."""
    import carvi_torch.viewpoints as vpm
    from carvi_torch.config import Config

    coll, both, dist, R, truth, fitted = two_shapes
    n = len(coll)
    cfg = Config().override({"sfm_groups": 2, "sfm_group_min": 6, "progress": False, "silhouette_weight": 0.0})
    calls, plain = [], vpm.class_sfm

    def recorded(sub, cfg_, init_shape=None, **options):
        res = plain(sub, cfg_, init_shape, **options)
        calls.append((len(sub), init_shape is None, options, res.iterations, res.planar))
        return res

    monkeypatch.setattr(vpm, "class_sfm", recorded)
    vp = estimate_viewpoints(coll, cfg.viewpoints)
    monkeypatch.undo()
    cold = [c for c in calls if c[0] < 2 * n and c[1]]
    assert cold and all(c[2] == mix.COLD_GROUP_SFM and not c[4] for c in cold)
    assert any(not c[1] for c in calls) and all(c[2] == {} for c in calls if not (c[0] < 2 * n and c[1]))
    assert class_sfm(both, cfg.viewpoints, max_outer=3).iterations <= 3  # an option replaces the run's setting
    assert vp.groups.k == 2 and torch.equal(vp.groups.labels, fitted.labels)
    assert vp.info["sfm_groups"]["groups"] == 2 and vp.info["sfm_groups"]["sizes"] == [12, 12]
    for key in ("sfm_cameras", "cameras"):
        err = viewpoint_report(getattr(vp, key).R[:n].double(), R.double())
        assert err["geodesic"]["median"] < 1.0 and not err["mirrored"], key
    assert bool(vp.has_camera.all())
    big = fitted.largest()
    assert big == int(torch.bincount(fitted.labels).argmax())
    assert torch.allclose(vp.shape, fitted.shape(big), atol=0.01)  # the run's SfM settings differ slightly
    clusters = cluster_instances(vp.cameras.R[:n, 2, :], vp.has_camera[:n], torch.eye(3), cfg.surrogates)
    out = cameras_json(coll, vp, torch.eye(3), clusters)
    assert [g["objects"] for g in out["shape_groups"]] == [12, 12]
    assert {out["cameras"][str(i)]["shape_group"] for i in range(n)} == {0, 1}
    assert out["mean_shape"] == out["shape_groups"][out["mean_shape_group"]]["mean_shape"]

    # the one-group path is compared with the SfM and refinement run here, exactly: 40 outer steps do for that
    cfg1 = Config().override({"progress": False, "silhouette_weight": 0.0, "sfm_max_outer": 40, "sfm_groups": 1})
    one = estimate_viewpoints(coll, cfg1.viewpoints)
    assert one.groups.k == 1 and torch.equal(one.shape, one.groups.single.shape)
    # one group: exactly the one-shape SfM and its refinement, as before the mixture existed
    res = class_sfm(both, cfg1.viewpoints)
    ref = refine_with_shape(res.shape, res.cameras, both, dist, cfg1.viewpoints).cameras
    assert torch.equal(one.sfm_cameras.R, res.cameras.R) and torch.equal(one.cameras.R, ref.R)
    assert torch.equal(one.cameras.s, ref.s) and torch.equal(one.cameras.t, ref.t)
    assert "shape_groups" not in cameras_json(coll, one, torch.eye(3), clusters)
    assert viewpoint_report(one.cameras.R[:n].double(), R.double())["geodesic"]["median"] > 3.0


def test_pipeline_refines_without_keypoints_few_instances_show():
    """``refine_min_support``: the pipeline's refinement and unseen-image path drop the mean-shape
    rows too few of the refined instances show (``refine.supported_shape``), and only those."""
    from carvi_torch.viewpoints import camera_fit as refine
    from carvi_torch.config import Config

    coll, _R, _truth = _two_shape_class(seed=3)
    coll.visible[1:, [0, 6]] = False  # a left/right pair only object 0 shows: 2 of 48 rows with the mirrors
    both = coll.with_mirrors()
    dist = distance_to_mask(both.masks)
    res = _sfm(both, max_outer=40)  # the refinement is checked against its parts: any SfM fit does
    assert bool(torch.isfinite(res.shape).all())
    support = both.visible.float().mean(0)
    weak = support < 0.1
    assert weak.nonzero().squeeze(1).tolist() == [0, 6]
    on = Config().override({"progress": False, "refine_min_support": 0.1, "sfm_max_outer": 40, "sfm_groups": 1})
    off = on.override({"refine_min_support": 0.0})
    got = refine_with_shape(res.shape, res.cameras, both, dist, on.viewpoints)
    want = refine.refine_cameras(refine.supported_shape(res.shape, both.visible, 0.1), res.cameras, both.keypoints,
                                 both.visible, dist, silhouette_weight=on.viewpoints.silhouette_weight,
                                 max_iters=on.viewpoints.refine_iters,
                                 silhouette_robust=on.viewpoints.silhouette_robust,
                                 twin_flatness=on.viewpoints.refine_twin_flatness)
    assert torch.equal(got.cameras.R, want.cameras.R) and torch.equal(got.energy_after, want.energy_after)
    every = refine_with_shape(res.shape, res.cameras, both, dist, off.viewpoints)
    assert not torch.equal(every.energy_after, got.energy_after)
    # the unseen-image path takes the support over every row of the collection, not the few it estimates
    idx = torch.tensor([0, 30])  # row 0 shows the pair: over these rows alone it would be kept
    u_on = cameras_from_mean_shape(res.shape, res.cameras, idx, both, dist, on.viewpoints)
    est, _ = refine.estimate_camera(refine.supported_shape(res.shape, both.visible, 0.1), both.keypoints[idx],
                                    both.visible[idx], dist[idx], silhouette_robust=on.viewpoints.silhouette_robust)
    assert torch.equal(u_on.R[idx], est.R) and torch.equal(u_on.R[1:30], res.cameras.R[1:30])
    # the run says which keypoints its refinement left out (summary.json), and only when it does
    for cfg, want in ((on, {"0": ["left_front_low", "right_front_low"]}), (off, None)):
        vp = estimate_viewpoints(coll, cfg.viewpoints)
        assert vp.info["refine"].get("keypoints_left_out") == want


# --------------------------------------------------------------------------- real CAD models


def _cad_class(shared_data, tmp_path, prefix: str, count: int, views: int = 15):
    """The PASCAL3D+ CAD models named ``prefix*`` (``count`` of them) rendered ``views`` times each:
    ``(collection, true rotations (n, 3, 3) float64)``."""
    coll, R, models = render_cad_class(shared_data, tmp_path, prefix, views=views)
    assert len(models) == count
    return coll, R


def test_cad_sofas_fit_several_shapes_and_better_viewpoints(shared_data, tmp_path):
    """The six PASCAL3D+ sofa models (a long low couch, an armchair, ordinary sofas), 15 renders each.

    One rigid shape cannot fit them: its cameras are 19.7 deg off (median; the joint polish settles where the
    keypoints fit it best, the alternation's 30 rounds stop at 10.4). The default mixture splits them into
    groups of at least ``sfm_group_min`` whose frames agree and more than halves that error; the ground truth
    only scores. The hard EM's starts end in local optima that depend on the float rounding of the machine;
    the start from the kept three groups with one split in two (``split``) and 12 EM rounds find four groups
    near 5 degrees on every float path measured: 4.86 with the compiled kernels (``sfm_native``, the
    default), 5.63 with the torch operators on an AVX-512 processor (where the ``lifted`` start ends lower
    still), 4.50 with them on AVX2 (``ATEN_CPU_CAPABILITY=avx2``); with two starts and 6 rounds the kernels'
    EM ended at 8.2. The bound is the one the
    8-view benchmark holds sofa to."""
    from carvi_torch.config import Config

    coll, R = _cad_class(shared_data, tmp_path, "sofa", 6)
    n = len(coll)
    errors, default = {}, Config().viewpoints
    for groups in (1, default.sfm_groups):
        vp = estimate_viewpoints(coll, Config().override({"sfm_groups": groups, "progress": False}).viewpoints)
        img = vp.cameras[:n].compose_similarity(coll.canvas_from_image.inverse())
        errors[groups] = viewpoint_report(img.R.double(), R)["geodesic"]["median"]
        if groups > 1:
            info = vp.info["sfm_groups"]
            assert info["groups"] >= 3 and min(info["sizes"]) >= default.sfm_group_min
            assert info["frame_agreement_deg"] <= default.sfm_group_agreement_deg
    assert errors[1] > 9.0  # one shape: the target is missed
    assert errors[default.sfm_groups] < 8.0 and errors[default.sfm_groups] < 0.5 * errors[1], errors
    # one shape: the joint polish settles at a lower keypoint residual than the alternation's 30 rounds, with
    # cameras farther from the truth (they absorb the models' differences in proportions)
    both, rms, err = coll.with_mirrors(), {}, {}
    for method, rounds in (("alternate", 30), ("joint", 100)):
        cfg = Config().override({"sfm_groups": 1, "sfm_polish": method, "sfm_polish_iters": rounds}).viewpoints
        fit = class_sfm(both, cfg)
        rms[method] = float(fit.history[-1])
        img = fit.cameras[:n].compose_similarity(coll.canvas_from_image.inverse())
        err[method] = viewpoint_report(img.R.double(), R)["geodesic"]["median"]
    assert rms["joint"] < rms["alternate"] and err["joint"] > err["alternate"] + 5.0, (rms, err)


def test_cad_buses_just_under_the_old_gate_get_their_split(shared_data, tmp_path):
    """The six PASCAL3D+ bus models, 8 renders each (render seed 1 of the 8-view benchmark,
    docs/viewpoints.md). One rigid shape leaves 2.9% of the box diagonal, under the old gate of 3%: the
    mixture was not fitted and the cameras stayed 9.8 degrees off (median; refined from their true cameras
    under that one shape they end where they are, so no other start would help). With the default gate the
    mixture is fitted, its split passes the hull test, and the cameras land near 3.8 degrees."""
    from carvi_torch.config import ViewpointConfig

    coll, R, models = render_cad_class(shared_data, tmp_path, "bus", views=8, seed=1)
    assert len(models) == 6
    n = len(coll)
    errors, infos = {}, {}
    for gate in (0.03, ViewpointConfig().sfm_group_misfit):
        vp = estimate_viewpoints(coll, ViewpointConfig(sfm_group_misfit=gate), seed=1)
        ok = vp.sfm_valid[:n]
        errors[gate] = viewpoint_report(vp.cameras.R[:n][ok].double(), R[ok])["geodesic"]["median"]
        infos[gate] = vp.info["sfm_groups"]
    old, new = infos[0.03], infos[ViewpointConfig().sfm_group_misfit]
    assert ViewpointConfig().sfm_group_misfit <= old["misfit"] < 0.03  # the case the default gate is for
    assert old["groups"] == 1 and "note" in old and errors[0.03] > 8.0
    assert new["groups"] >= 2 and all(c["hull_gain"] >= 0.01 for c in new["candidates"] if c["kept"])
    assert errors[ViewpointConfig().sfm_group_misfit] < 5.0, errors


def test_cad_monitors_never_split_off_the_flat_fronted_models(shared_data, tmp_path):
    """The four PASCAL3D+ tvmonitor models, 15 renders each. Two carry only the four coplanar
    front corners, whose views fit any shape's front; a group of them alone cannot fix its
    cameras' tilt. With ``sfm_groups=3`` and every split tried (their keypoints fit one shape, so by
    default the mixture is not fitted at all) every candidate with such a group is recorded as not
    usable, every kept group has a 3-D shape, and the cameras meet the 8-degree target.

    (Without the rule and with the EM's keypoint fits searching the sphere every round, the fit
    kept a three-group split with such a group, at 7.9 degrees against 3.4 with the rule; with the
    warm starts the three-group candidates no longer win, so that contrast is not asserted here.
    The rule itself is checked against its own switch on synthetic objects above.)"""
    from carvi_torch.config import Config

    coll, R = _cad_class(shared_data, tmp_path, "tvmonitor", 4)
    n = len(coll)
    forced = {"sfm_groups": 3, "sfm_group_misfit": 0, "sfm_group_hull_gain": -1, "progress": False}  # every split tried
    vp = estimate_viewpoints(coll, Config().override(forced).viewpoints)
    img = vp.cameras[:n].compose_similarity(coll.canvas_from_image.inverse())
    info, err = vp.info["sfm_groups"], viewpoint_report(img.R.double(), R)["geodesic"]["median"]
    assert any("coplanar" in c.get("problem", "") for c in info["candidates"]), info["candidates"]
    assert not any(c["kept"] and "problem" in c for c in info["candidates"])
    assert info["groups"] < 3
    for g in range(info["groups"]):
        assert mix.shape_thickness(vp.groups.shape(g)) >= mix.PLANAR_THICKNESS
    assert err < 8.0, err


def test_rotation_onto_needs_three_shared_points():
    S = torch.randn(5, 3, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    T = S.clone()
    T[:3] = float("nan")  # two shared rows left
    with pytest.raises(ValueError, match="share 2"):
        mix.rotation_onto(T, S)
    with pytest.raises(ValueError, match="one line"):
        mix.rotation_onto(torch.ones(5, 3, dtype=torch.float64), S)
    line = torch.linspace(0, 1, 5, dtype=torch.float64)[:, None] * torch.tensor([1.0, 2.0, -1.0], dtype=torch.float64)
    with pytest.raises(ValueError, match="one line"):
        mix.rotation_onto(line, S)


def test_a_split_without_a_class_frame_is_not_kept(two_shapes, monkeypatch):
    """A group whose shape cannot be rotated into the class frame makes its split ineligible; one shape is kept."""
    coll, both, dist, R, truth, fitted = two_shapes

    def no_frame(groups):
        raise ValueError("the two shapes share 0 reconstructed keypoint(s); a rotation needs 3")

    monkeypatch.setattr(mix, "group_rotations", no_frame)
    lines = []
    out = mix.fit_mixture_of_shapes(both, dist, _shared_sfm, max_groups=2, min_size=6, log=lines.append,
                                    single=fitted.single)
    assert out.k == 1 and len(out.candidates) == 2
    assert all(not c["eligible"] and c["problem"].startswith("no class frame") for c in out.candidates)
    assert all("no class frame" in line for line in lines)


def test_a_group_without_cameras_makes_its_split_unusable_not_the_class():
    """Half the objects see one keypoint only (no SfM camera): they cost nothing under any shape. The
    residual-quantile start puts all of them in one group, whose SfM has no camera: that split is
    recorded as not usable (before, the class failed). The other start still splits the objects
    that have cameras by their true shape."""
    coll, _R, truth = _two_shape_class(sizes=(18, 18))
    bad = torch.cat([torch.arange(0, 9), torch.arange(18, 27)])
    coll.visible[bad] = False
    coll.visible[bad, 0] = True
    both = coll.with_mirrors()
    out = mix.fit_mixture_of_shapes(both, distance_to_mask(both.masks), _sfm, max_groups=2, min_size=6)
    by_init = {c["init"]: c for c in out.candidates}
    assert "no usable SfM shape" in by_init["residual"]["problem"] and not by_init["residual"]["eligible"]
    assert by_init["lifted"]["kept"] and out.k == 2
    good = torch.ones(36, dtype=torch.bool)
    good[bad] = False
    lab, tru = out.labels[good], truth[good]
    assert bool((lab == tru).all() or (lab == 1 - tru).all())
    assert all(bool(res.valid.any()) for _rows, res in out.groups)


def test_a_keypoint_no_object_shows_leaves_the_split_intact():
    """Bad input of the viewpoint issue, through the mixture: a keypoint never visible in the class is
    reported by the one-shape SfM and stays a NaN row of every group's shape (nothing to fill it
    from); the two true shapes are still found from the other keypoints. (Hidden with its left/right
    partner: a mirrored copy shows an original's keypoint under its partner's name.)"""
    coll, _R, truth = _two_shape_class(sizes=(12, 12), seed=3)
    names = coll.meta.keypoint_names
    hidden = [names.index("left_back_roof"), names.index("right_back_roof")]
    coll.visible[:, hidden] = False
    both = coll.with_mirrors()
    assert not bool(both.visible[:, hidden].any())
    # 40 outer steps: the same candidates, cuts and kept split as the converged fits
    out = mix.fit_mixture_of_shapes(both, distance_to_mask(both.masks), _capped_sfm(40), max_groups=2, min_size=6)
    assert any("never visible" in p for p in out.single.problems), out.single.problems
    assert out.k == 2 and bool((out.labels == truth).all() or (out.labels == 1 - truth).all())
    for g in range(2):
        fin = torch.isfinite(out.shape(g)).all(-1)
        assert fin.tolist() == [i not in hidden for i in range(len(names))]


@pytest.mark.parametrize("groups", [1, 2])
def test_pipeline_says_where_each_camera_came_from(groups):
    """Objects without an SfM camera take one from the unseen-image path. ``cameras.json`` says so
    per camera (``camera_from``); one whose visible keypoints all lack a mean-shape row is fitted to
    its silhouette alone, flagged ``silhouette`` and listed with a warning in the class report."""
    from carvi_torch.config import Config

    coll, _R, _truth = _two_shape_class(sizes=(20, 20), seed=4)
    names = coll.meta.keypoint_names
    pair = [names.index("left_back_roof"), names.index("right_back_roof")]
    coll.visible[:, pair] = False  # never seen by anyone: no shape row
    coll.visible[0] = False
    coll.visible[0, pair[0]] = True  # object 0: one keypoint, without a shape row -> silhouette only
    coll.visible[1] = False
    coll.visible[1, 0] = True  # object 1: one keypoint, with a shape row -> the mean shape helps
    # the split is kept on its keypoints (box masks here); what is checked is where each camera came from, not
    # how well the SfM and the EM converged: 30 outer steps and 2 EM rounds (the pipeline's: 200 and 6)
    cfg = Config().override({"sfm_groups": groups, "sfm_group_min": 6, "progress": False, "refine_iters": 20,
                             "sfm_group_hull_gain": -1, "sfm_max_outer": 30, "sfm_group_rounds": 2})
    vp = estimate_viewpoints(coll, cfg.viewpoints)
    assert vp.groups.k == groups
    aid = [int(a) for a in coll.annotation_ids]
    assert vp.info["cameras_from_mean_shape"] == [aid[0], aid[1]]
    assert vp.info["cameras_from_silhouette_only"] == [aid[0]]
    assert any("silhouette alone" in w and str(aid[0]) in w for w in vp.warnings)
    assert vp.unseen_keypoints[:2].tolist() == [0, 1] and bool((vp.unseen_keypoints[2:40] == -1).all())
    cams = cameras_json(coll, vp, None, None)["cameras"]
    assert [cams[str(a)]["camera_from"] for a in aid[:3]] == ["silhouette", "mean_shape", "sfm"]
    assert cams[str(aid[0])]["sfm"] is None and cams[str(aid[0])]["refined"] is not None


def test_a_class_under_the_misfit_gate_gets_the_one_shape_cameras_bit_for_bit():
    """The default ``sfm_groups`` (more than 1) on a class of one proportion (32 objects, enough for two groups): the
    one-shape residual is under the gate, no split is tried, and every camera, the mean shape and the SfM
    cameras equal those of ``sfm_groups=1`` exactly."""
    from carvi_torch.config import Config

    coll, _R, _truth = _two_shape_class(sizes=(16, 16), seed=2, same_shape=True)
    base = {"progress": False, "sfm_max_outer": 40, "refine_iters": 30}
    default = estimate_viewpoints(coll, Config().override(base).viewpoints)
    one = estimate_viewpoints(coll, Config().override({**base, "sfm_groups": 1}).viewpoints)
    assert Config().viewpoints.sfm_groups > 1 and default.groups.k == 1 and default.groups.candidates == []
    assert default.groups.misfit < GATE["min_misfit"] and "fits the keypoints" in default.groups.note
    for a, b in ((default.cameras, one.cameras), (default.sfm_cameras, one.sfm_cameras)):
        assert torch.equal(a.R, b.R) and torch.equal(a.s, b.s) and torch.equal(a.t, b.t)
    assert torch.equal(default.shape, one.shape)


def test_class_sfm_polishes_as_long_as_sfm_polish_iters_allows(two_shapes):
    """``viewpoints.sfm_polish_iters`` caps the bundle polish of the class's SfM: 1 round stops before the
    residual settles on this two-shape class (one shape cannot fit it exactly), enough rounds end at ``sfm_tol``
    with a residual no higher; 0 runs none; a negative count is refused."""
    from carvi_torch.config import Config, ConfigError

    _coll, both, _dist, _R, _truth, _fitted = two_shapes
    runs = {}
    for iters in (0, 1, 400):
        cfg = Config().override({"progress": False, "sfm_max_outer": 40, "sfm_polish_iters": iters})
        runs[iters] = class_sfm(both, cfg.viewpoints)
    assert runs[0].polish_rounds == 0
    assert runs[1].polish_rounds == 1 and not runs[1].converged
    assert 1 < runs[400].polish_rounds < 400 and runs[400].converged
    rms = {k: float(r.history[-1]) for k, r in runs.items()}  # the visible-entry RMS residual at the end
    assert rms[400] < rms[1] <= rms[0]
    with pytest.raises(ConfigError, match="sfm_polish_iters"):
        Config().override({"sfm_polish_iters": -1})
