"""The canonical object frame (carvi_torch.viewpoints.frame): similarity fits, templates, the
automatic symmetry+up frame, fall-backs, and the frame of every written output."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from carvi_torch.cameras import (ScaledOrthographic, azimuth_elevation_roll_from_rotation, geodesic_angle,
                                 random_rotations, rotation_from_azimuth_elevation_roll)
from carvi_torch.viewpoints.frame import (MAX_TEMPLATE_RESIDUAL, CanonicalFrame, FrameFit,
                                          build_templates, canonical_frame, fit_similarity, load_templates,
                                          symmetry_up_frame, template_points)
from conftest import cad_models

D = torch.float64


def _deg(A, B):
    return math.degrees(float(geodesic_angle(A.double()[None], B.double()[None])[0]))


def _car_template():
    """A box-like 'car' in the PASCAL3D+ frame (+z up, front -y): wheels low, roof high, front at -y."""
    names, pts = [], []
    for side, x in (("left", -0.4), ("right", 0.4)):
        for end, y in (("front", -1.0), ("back", 1.0)):
            names += [f"{side}_{end}_wheel", f"{side}_{end}_light", f"{side}_{end}_roof"]
            pts += [[x, 0.8 * y, 0.0], [x, y, 0.35], [0.8 * x, 0.5 * y, 0.7]]
    return names, torch.tensor(pts, dtype=D)


# --------------------------------------------------------------------------- fit_similarity


def test_fit_similarity_recovers_an_exact_similarity(generator):
    S = torch.randn(12, 3, generator=generator, dtype=D)
    Q = random_rotations(1, generator, dtype=D)[0]
    fit = fit_similarity(S, 1.7 * S @ Q.T + torch.tensor([0.3, -2.0, 5.0], dtype=D))
    assert torch.allclose(fit.Q, Q, atol=1e-9) and abs(fit.c - 1.7) < 1e-9
    assert torch.allclose(fit.tau, torch.tensor([0.3, -2.0, 5.0], dtype=D), atol=1e-9)
    assert fit.residual < 1e-9 and fit.matched == 12


def test_fit_similarity_matches_scipy_on_noisy_points(generator):
    """Without outliers the rotation is the least-squares one: scipy's Kabsch agrees."""
    S = torch.randn(30, 3, generator=generator, dtype=D)
    Q = random_rotations(1, generator, dtype=D)[0]
    T = S @ Q.T + 0.02 * torch.randn(30, 3, generator=generator, dtype=D)
    fit = fit_similarity(S, T, iters=1)  # one pass: plain (unweighted) Umeyama
    ref, _ = Rotation.align_vectors((T - T.mean(0)).numpy(), (S - S.mean(0)).numpy())
    assert _deg(fit.Q, torch.tensor(ref.as_matrix())) < 1e-6


def test_fit_similarity_never_returns_a_reflection(generator):
    """A car whose left keypoints sit on its right (a mirror image) has no proper fit: refused."""
    _, T = _car_template()
    Q = random_rotations(1, generator, dtype=D)[0]
    fit = fit_similarity((T * torch.tensor([-1.0, 1, 1], dtype=D)) @ Q.T, T)
    assert abs(float(torch.det(fit.Q)) - 1) < 1e-9 and fit.residual > MAX_TEMPLATE_RESIDUAL
    assert fit_similarity(T @ Q.T, T).residual < 1e-9


def test_fit_similarity_shrugs_off_one_wrong_keypoint(generator):
    S = torch.randn(10, 3, generator=generator, dtype=D)
    Q = random_rotations(1, generator, dtype=D)[0]
    T = S @ Q.T
    T[3] += torch.tensor([5.0, -4.0, 3.0], dtype=D)
    assert _deg(fit_similarity(S, T).Q, Q) < 0.5
    assert _deg(fit_similarity(S, T, iters=1).Q, Q) > 2.0  # the reweighting is what does it


def test_fit_similarity_partial_and_planar_and_too_few(generator):
    S = torch.randn(8, 3, generator=generator, dtype=D)
    S[:, 2] = 0.0  # a planar class (e.g. a tv screen's corners and a stand in one plane)
    Q = random_rotations(1, generator, dtype=D)[0]
    T = S @ Q.T
    T[[1, 5]] = math.nan  # keypoints the template does not know
    S2 = S.clone()
    S2[6] = math.nan  # a keypoint the SfM shape never saw
    fit = fit_similarity(S2, T)
    assert fit.matched == 5 and _deg(fit.Q, Q) < 1e-6  # a plane of points fixes a rotation (not a reflection)
    T[[0, 2, 3, 4]] = math.nan
    with pytest.raises(ValueError, match="3 shared points"):
        fit_similarity(S2, T)


def test_residual_forgives_proportions_not_shape(generator):
    """A longer object of the same kind fits its template; a scrambled one does not."""
    names, T = _car_template()
    longer = T * torch.tensor([1.0, 1.4, 0.8], dtype=D)
    assert fit_similarity(longer, T).residual < 0.02
    scrambled = T[torch.randperm(len(T), generator=generator)]
    assert fit_similarity(scrambled, T).residual > MAX_TEMPLATE_RESIDUAL


# --------------------------------------------------------------------------- templates


def test_template_points_by_name_alias_and_own():
    templates = {"classes": {"aeroplane": {"keypoints": {"left_wing": [1, 0, 0], "right_wing": [-1, 0, 0],
                                                         "noselanding": [0, -1, 0], "tail": [0, 1, 0.2]}}},
                 "aliases": {"aeroplane": {"L_WingTip": "right_wing", "R_WingTip": "left_wing",
                                           "NoseTip": "noselanding", "Bot_Rudder": "tail"}}}
    T, src = template_points("Aeroplane", ["L_WingTip", "R_WingTip", "NoseTip", "Bot_Rudder", "Other"], templates)
    assert "aeroplane" in src and T[0].tolist() == [-1, 0, 0] and T[1].tolist() == [1, 0, 0]
    assert torch.isnan(T[4]).all()
    assert template_points("aeroplane", ["L_WingTip", "R_WingTip", "Other"], templates) is None  # 2 < 4 known
    assert template_points("horse", ["a", "b", "c", "d"], templates) is None
    own = [[0, 0, 0], None, [1, 0, 0], [0, 1, 0], [0, 0, 1]]
    T, src = template_points("horse", list("abcde"), templates, own=own)
    assert src == "category keypoints_3d" and torch.isnan(T[1]).all() and T[4].tolist() == [0, 0, 1]


def test_shipped_templates_cover_the_pascal_classes():
    t = load_templates()
    assert len(t["classes"]) == 12 and "+z up" in t["frame"]
    car = t["classes"]["car"]["keypoints"]  # the PASCAL3D+ frame: up is +z, the front towards -y
    assert car["left_front_light"][1] < car["left_back_light"][1]
    assert car["left_window_up"][2] > car["left_front_wheel"][2]
    for cls, e in t["classes"].items():
        pts = torch.tensor(list(e["keypoints"].values()), dtype=D)
        assert pts.norm(dim=-1).max() <= 0.5 + 1e-6, cls  # inside the unit-diagonal box
        assert e["models"] >= 1 and set(e["counts"]) == set(e["keypoints"])


@pytest.mark.shared
def test_shipped_templates_are_the_cad_models_averaged(shared_data):
    """templates.json is what build_templates makes of ../shared/data/pascal3d_cad, and its frame is
    PASCAL3D+'s: every class's front keypoints lie at lower y than its back ones, tops above bottoms."""
    built = build_templates(cad_models(shared_data))
    shipped = load_templates()["classes"]
    assert built.keys() == shipped.keys()
    for cls in built:
        assert built[cls]["counts"] == shipped[cls]["counts"]
        for k, p in built[cls]["keypoints"].items():
            assert np.allclose(p, shipped[cls]["keypoints"][k], atol=2e-6), (cls, k)
    car = shipped["car"]["keypoints"]
    front = np.mean([v for k, v in car.items() if "front" in k], 0)
    back = np.mean([v for k, v in car.items() if "rear" in k or "back" in k], 0)
    assert front[1] < back[1]
    plane = shipped["aeroplane"]["keypoints"]
    assert plane["noselanding"][1] < plane["tail"][1] and plane["rudder_upper"][2] > plane["noselanding"][2]


# --------------------------------------------------------------------------- the automatic frame


def _photo_cameras(n, generator, elev_sd=12.0, roll_sd=3.0):
    az = torch.rand(n, generator=generator, dtype=D) * 2 * math.pi
    el = torch.deg2rad(12.0 + elev_sd * torch.randn(n, generator=generator, dtype=D)).clamp(-0.3, 1.2)
    ro = torch.deg2rad(roll_sd * torch.randn(n, generator=generator, dtype=D))
    return rotation_from_azimuth_elevation_roll(az, el, ro)


def test_symmetry_up_frame_finds_up_and_front_in_a_rotated_sfm_frame(generator):
    """Cameras like photographs of a car, seen through an arbitrary SfM frame ``X_sfm = G X``: the frame
    found undoes ``G`` (up, front and the symmetry normal), to the accuracy of the camera statistics."""
    names, T = _car_template()
    G = random_rotations(1, generator, dtype=D)[0]
    R_true = _photo_cameras(200, generator)
    R_sfm = R_true @ G.T  # the same cameras, object frame rotated by G
    P = torch.diag(torch.tensor([-1.0, 1, 1], dtype=D))  # the car's mirror plane x = 0
    fit, info = symmetry_up_frame(G @ P @ G.T, R_sfm, T @ G.T, names)
    assert info["front"] == "names" and info["up_margin"] > 5
    QG = fit.Q @ G  # true frame -> canonical frame: the identity when all is found
    assert math.degrees(math.acos(min(1.0, float(QG[2, 2])))) < 3.0  # up
    assert _deg(QG, torch.eye(3, dtype=D)) < 3.0  # and everything else
    assert abs(info["roll_rms_deg"] - 3.0) < 1.0 and 10 < info["elevation_rms_deg"] < 25


def test_symmetry_up_frame_says_when_the_front_is_unknown(generator):
    names, T = _car_template()
    anonymous = [f"k{i}" for i in range(len(names))]
    fit, info = symmetry_up_frame(torch.diag(torch.tensor([-1.0, 1, 1], dtype=D)), _photo_cameras(50, generator),
                                  T, anonymous)
    assert info["front"] == "ambiguous"
    assert abs(float(fit.Q[2, 2])) > 0.99  # up is still found
    assert abs(float(torch.det(fit.Q)) - 1) < 1e-9


# --------------------------------------------------------------------------- canonical_frame and its fall-backs


def _templates_for(names, T):
    return {"classes": {"car": {"keypoints": {n: p.tolist() for n, p in zip(names, T)}}}, "aliases": {}}


def test_template_frame_of_shape_groups_is_one_rotation(generator):
    """Shape groups share the SfM class frame: one rotation takes them all to the template (their
    cameras stay consistent), each group keeps its own scale and offset and its own residual."""
    names, T = _car_template()
    G = random_rotations(1, generator, dtype=D)[0]
    shapes = [T @ G.T * 2.0 + 1.0, (T * torch.tensor([1.0, 1.2, 0.9], dtype=D)) @ G.T * 0.5]
    shapes[1][3] = math.nan  # a keypoint one group never saw
    R = _photo_cameras(20, generator)
    frame = canonical_frame("best", "car", names, shapes, shapes[0], None, R, templates=_templates_for(names, T))
    assert frame.kind == "template" and len(frame.fits) == 2 and len(frame.info["residual_per_group"]) == 2
    assert _deg(frame.fits[0].Q, G.T) < 1e-6 and torch.equal(frame.fits[0].Q, frame.fits[1].Q)
    assert abs(frame.fits[0].c - 0.5) < 1e-6 and 1.6 < frame.fits[1].c < 2.4  # least squares over the proportions
    assert max(frame.info["residual_per_group"]) < 1e-6 and frame.info["matched_keypoints"] == 11
    # groups a few degrees apart (the frames SfM found agree only roughly): the rotation is their compromise
    tilt = torch.tensor(Rotation.from_rotvec([0.0, 0.0, math.radians(6)]).as_matrix())
    frame = canonical_frame("best", "car", names, [T @ G.T, T @ (tilt @ G).T], T, None, R,
                            templates=_templates_for(names, T))
    assert 2.0 < _deg(frame.fits[0].Q, G.T) < 4.0 and 2.0 < _deg(frame.fits[0].Q, (tilt @ G).T) < 4.0


def test_a_template_the_data_disagree_with_falls_back_and_says_why(generator):
    names, T = _car_template()
    wrong = T[torch.randperm(len(T), generator=generator)]
    P = torch.diag(torch.tensor([-1.0, 1, 1], dtype=D))
    R = _photo_cameras(40, generator)
    frame = canonical_frame("best", "car", names, [T], T, P, R, templates=_templates_for(names, wrong))
    assert frame.kind == "symmetry+up" and "fits the mean shape badly" in frame.info["fallback"]
    frame = canonical_frame("best", "car", names, [T], T, None, R, templates=_templates_for(names, wrong))
    assert frame.kind == "sfm" and "no left/right keypoint pairs" in frame.info["fallback"]
    frame = canonical_frame("sfm", "car", names, [T], T, P, R, templates=_templates_for(names, T))
    assert frame.kind == "sfm" and "fallback" not in frame.info


def test_canonical_cameras_see_canonical_points_where_sfm_cameras_saw_sfm_points(generator):
    """``R' = R Q^T, s' = s / c, t' = t - s' R'[:2] tau`` leaves every projection unchanged, per group."""
    fits = [FrameFit(random_rotations(1, generator, dtype=D)[0], 1.5, torch.tensor([0.1, 0.2, -0.3], dtype=D)),
            FrameFit(random_rotations(1, generator, dtype=D)[0], 0.7, torch.tensor([-1.0, 0.0, 2.0], dtype=D))]
    frame = CanonicalFrame("template", fits)
    cams = ScaledOrthographic(random_rotations(6, generator, dtype=D), torch.rand(6, generator=generator, dtype=D) + 1,
                              torch.randn(6, 2, generator=generator, dtype=D))
    groups = torch.tensor([0, 1, 0, 1, 1, 0])
    X = torch.randn(6, 5, 3, generator=generator, dtype=D)
    canon = frame.cameras(cams, groups)
    for i in range(6):
        Xc = frame.points(X[i], int(groups[i]))
        assert torch.allclose(canon[i:i + 1].project(Xc[None]), cams[i:i + 1].project(X[i][None]), atol=1e-9)
    one = CanonicalFrame("symmetry+up", fits[:1])  # one fit shared by every group
    assert torch.allclose(one.cameras(cams, groups).R, cams.R @ fits[0].Q.T)


def test_camera_to_object_inverts_the_projection(generator):
    cams = ScaledOrthographic(random_rotations(4, generator, dtype=D), torch.rand(4, generator=generator, dtype=D) + 1,
                              torch.randn(4, 2, generator=generator, dtype=D))
    X = torch.randn(4, 7, 3, generator=generator, dtype=D)
    uv = cams.project(X)
    depth = cams.s[:, None] * (X @ cams.R[:, 2, :, None])[..., 0]
    hom = torch.cat([uv, depth[..., None], torch.ones(4, 7, 1, dtype=D)], -1)
    back = (cams.camera_to_object_4x4() @ hom.transpose(1, 2)).transpose(1, 2)[..., :3]
    assert torch.allclose(back, X, atol=1e-9)


# --------------------------------------------------------------------------- end to end


def test_outputs_are_written_in_the_pascal3d_frame(pipeline_run):
    """Procedural objects are built in the PASCAL3D+ frame: with the shipped templates the written cameras
    need no fitted rotation (absolute ~ aligned error), azimuth/elevation are PASCAL3D+'s, and the voxel
    grids' ``voxel_to_object`` put each object upright (its largest extent along y for a car). Read from the
    session's tiny run (conftest's ``pipeline_run``: resolution 20, six procedural objects per class)."""
    from carvi_torch.evaluation.viewpoint_metrics import viewpoint_report

    tmp_path, summary = pipeline_run
    assert summary["classes"]["car"]["frame"]["kind"] == "template"
    cams = json.loads((tmp_path / "car" / "cameras.json").read_text())
    assert cams["frame"] == "template" and cams["frame_info"]["residual"] < MAX_TEMPLATE_RESIDUAL
    gt = json.loads(open(summary["gt"]).read())
    gt = gt.get("annotations", gt)
    ids = [a for a, e in cams["cameras"].items() if e["refined"] is not None and a in gt]
    R = torch.tensor([cams["cameras"][a]["refined"]["R"] for a in ids], dtype=D)
    Rg = torch.tensor([gt[a]["R"] for a in ids], dtype=D)
    rep = viewpoint_report(R, Rg)
    assert rep["absolute"]["geodesic"]["median"] < rep["geodesic"]["median"] + 3.0
    assert rep["absolute"]["geodesic"]["median"] < 10.0
    az, el, _ = azimuth_elevation_roll_from_rotation(R)
    e = cams["cameras"][ids[0]]
    assert abs(e["azimuth_deg"] - math.degrees(float(az[0]))) < 1e-3
    assert abs(e["elevation_deg"] - math.degrees(float(el[0]))) < 1e-3
    for f in sorted((tmp_path / "car" / "voxels").glob("*.npz"))[:3]:
        z = np.load(f)
        n = z["occupancy"].shape[0]
        ijk = np.argwhere(z["occupancy"]).astype(np.float64)
        pts = (z["voxel_to_object"] @ np.c_[ijk, np.ones(len(ijk))].T).T[:, :3]
        ext = pts.max(0) - pts.min(0)
        assert ext[1] > ext[0] and ext[1] > ext[2], ext  # a car is longest front to back
        assert n == 20 and np.isfinite(z["voxel_to_object"]).all()
