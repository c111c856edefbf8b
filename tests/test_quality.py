"""quality.py: the per-object quality signals and their combination."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from carvi_torch.cameras import ScaledOrthographic, axis_angle_to_rotation, random_rotations
from carvi_torch.quality import camera_signals, combine, reconstruction_iou


def test_reconstruction_iou_against_a_pixel_loop():
    rng = np.random.default_rng(0)
    occ = rng.random((6, 9, 7)) < 0.2  # [d, h, w]
    A = np.zeros((4, 4))
    A[0, 2], A[1, 1], A[2, 0], A[3, 3] = 2.5, 3.0, 1.7, 1.0  # x = 2.5 w + 4, y = 3 h + 2, z = 1.7 d - 5
    A[:3, 3] = [4.0, 2.0, -5.0]
    mask = rng.random((32, 32)) < 0.4
    sil = occ.any(0)
    inter = union = 0
    for y in range(32):
        for x in range(32):
            h, w = (y - 2.0) / 3.0, (x - 4.0) / 2.5  # the nearest column, if any
            hi, wi = int(np.floor(h + 0.5)), int(np.floor(w + 0.5))
            p = 0 <= hi < 9 and 0 <= wi < 7 and sil[hi, wi]
            inter += p and mask[y, x]
            union += p or mask[y, x]
    assert reconstruction_iou(occ, A, mask) == pytest.approx(inter / union, abs=1e-12)
    tilted = A.copy()
    tilted[0, 0] = 0.5  # depth moves x: not a grid aligned with the rays
    with pytest.raises(ValueError, match="ray"):
        reconstruction_iou(occ, tilted, mask)


def test_grids_on_the_canvas_axes_take_the_general_projection_s_values():
    """The per-line projection of grids aligned with the canvas (the carving's) gives the general projection's
    silhouette pixel for pixel, with flipped axes, offsets off the canvas and voxels finer or coarser than pixels;
    a grid turned in the image plane takes the general path and matches a loop over the pixels."""
    from carvi_torch import quality

    rng = np.random.default_rng(4)
    for _ in range(40):
        sil = rng.random((int(rng.integers(3, 40)), int(rng.integers(3, 40)))) < 0.5
        sx, sy = rng.uniform(0.3, 4.0, 2) * rng.choice([-1.0, 1.0], 2)
        M, offset = np.array([[0.0, sx], [sy, 0.0]]), rng.uniform(-20.0, 60.0, 2)
        inv = np.linalg.inv(M)
        assert inv[0, 0] == 0 and inv[1, 1] == 0
        np.testing.assert_array_equal(quality._silhouette_on_canvas_axes(sil, inv, offset, 48),
                                      quality._silhouette_on_canvas(sil, inv, offset, 48))
    occ = rng.random((3, 8, 8)) < 0.4
    A = np.eye(4)[[2, 1, 0, 3]] * 1.0
    c, s_ = np.cos(0.4), np.sin(0.4)
    A[:2, 1:3] = [[1.5 * s_, 1.5 * c], [1.5 * c, -1.5 * s_]]  # (h, w) -> (x, y) turned by 0.4 rad
    A[:2, 3] = [12.0, 9.0]
    mask = rng.random((24, 24)) < 0.4
    sil, inv = occ.any(0), np.linalg.inv(A[:2, 1:3])
    inter = union = 0
    for y in range(24):
        for x in range(24):
            h, w = inv @ np.array([x - 12.0, y - 9.0])
            hi, wi = int(np.rint(h)), int(np.rint(w))
            p = 0 <= hi < 8 and 0 <= wi < 8 and sil[hi, wi]
            inter += p and mask[y, x]
            union += p or mask[y, x]
    assert reconstruction_iou(occ, A, mask) == pytest.approx(inter / union, abs=1e-12)


def test_combine_is_monotone_and_bounded():
    base = {"keypoint_residual": 0.01, "visible_keypoints": 6, "refinement_deg": 2.0, "mirror_deg": 5.0,
            "camera_from": "sfm", "reconstruction_iou": 0.9, "surrogates_from": "triplet"}
    q0 = combine(base)
    assert 0 < q0 < 1
    worse = [("keypoint_residual", 0.05), ("visible_keypoints", 3), ("refinement_deg", 10.0), ("mirror_deg", 40.0),
             ("camera_from", "silhouette"), ("reconstruction_iou", 0.5), ("surrogates_from", "puffball"),
             ("rotational", True)]
    for key, value in worse:
        assert combine({**base, key: value}) < q0, key
    assert combine({}) == 1.0 and combine({**base, "reconstruction_iou": 0.0}) >= 0.0
    assert combine({**base, "silhouette_inside": 0.0}) == q0  # recorded, not combined


def test_camera_signals_measure_residual_silhouette_and_mirror_disagreement():
    """Two objects: the first seen exactly (its keypoints on the projections, inside its mask, its mirrored
    copy's camera the mirror of its own, its SfM camera the same); the second with keypoints 3 px off, an
    empty mask, a mirrored camera turned 10 degrees and an SfM camera turned 7 degrees."""
    g = torch.Generator().manual_seed(1)
    S = torch.randn(4, 3, generator=g, dtype=torch.float64)
    S = torch.cat([S, S * torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)])  # left/right pairs
    P = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    R = random_rotations(2, generator=g, dtype=torch.float64)
    s = torch.tensor([8.0, 8.0], dtype=torch.float64)
    t = torch.tensor([[32.0, 32.0], [30.0, 34.0]], dtype=torch.float64)
    Rm = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64)) @ R @ P
    turn = axis_angle_to_rotation(torch.tensor([0.0, 0.0, math.radians(10.0)], dtype=torch.float64))
    Rm[1] = turn @ Rm[1]
    cams = ScaledOrthographic(torch.cat([R, Rm]), torch.cat([s, s]), torch.cat([t, 63 - t]))
    kp = ScaledOrthographic(R, s, t).project(S.expand(2, -1, -1)).clone()
    kp[1] += 3.0 / math.sqrt(2)
    masks = torch.zeros(2, 64, 64, dtype=torch.bool)
    masks[0] = True
    vis = torch.ones(2, 8, dtype=torch.bool)
    vis[1, :3] = False
    kp[1, :3] = 0.0
    coll = type("Coll", (), {"keypoints": kp, "visible": vis, "masks": masks, "meta": SimpleNamespace(symmetry="none"),
                             "__len__": lambda self: 2})()
    Rs = R.clone()
    Rs[1] = axis_angle_to_rotation(torch.tensor([math.radians(7.0), 0.0, 0.0], dtype=torch.float64)) @ R[1]
    sfm = ScaledOrthographic(torch.cat([Rs, Rm]), cams.s, cams.t)
    vp = SimpleNamespace(cameras=cams, sfm_cameras=sfm, sfm_valid=torch.ones(4, dtype=torch.bool),
                         groups=SimpleNamespace(k=1), shape=S, has_camera=torch.ones(4, dtype=torch.bool),
                         mirrored=True, reflection=P, source="estimate")
    sig = camera_signals(coll, vp)
    assert sig[0]["keypoint_residual"] == pytest.approx(0.0, abs=1e-12)
    assert sig[1]["keypoint_residual"] == pytest.approx(3.0 / 64, rel=1e-9)
    assert sig[0]["silhouette_inside"] == 1.0 and sig[1]["silhouette_inside"] == 0.0
    assert sig[0]["mirror_deg"] == pytest.approx(0.0, abs=1e-5)
    assert sig[1]["mirror_deg"] == pytest.approx(10.0, abs=1e-6)
    assert sig[0]["refinement_deg"] == pytest.approx(0.0, abs=1e-5)
    assert sig[1]["refinement_deg"] == pytest.approx(7.0, abs=1e-6)
    assert (sig[0]["visible_keypoints"], sig[1]["visible_keypoints"]) == (8, 5) and not sig[0]["rotational"]
    assert combine(sig[1]) < combine(sig[0])


def _signals_loop(coll, vp) -> list[tuple]:
    """The residual and inside fraction object by object (the reference for ``camera_signals``' batched form)."""
    n = len(coll)
    cams = vp.cameras
    R, s, t = cams.R[:n].double(), cams.s[:n].double(), cams.t[:n].double()
    labels = vp.groups.labels[:n].tolist() if vp.groups.k > 1 else [0] * n
    C = coll.masks.shape[-1]
    out = []
    for i in range(n):
        if not bool(vp.has_camera[i]):
            out.append((None, None))
            continue
        S = (vp.groups.shape(labels[i]) if vp.groups.k > 1 else vp.shape).double()
        ok = torch.isfinite(S).all(1)
        uv = s[i] * S[ok] @ R[i, :2].T + t[i]
        v = coll.visible[i] & ok
        res = None
        if bool(v.any()):
            d = s[i] * S[v] @ R[i, :2].T + t[i] - coll.keypoints[i, v].double()
            res = float(d.pow(2).sum(1).mean().sqrt()) / C
        px = uv.round().long()
        inb = (px >= 0).all(1) & (px < C).all(1)
        inside = torch.zeros(len(px), dtype=torch.bool)
        inside[inb] = coll.masks[i][px[inb, 1], px[inb, 0]]
        out.append((res, float(inside.float().mean()) if len(px) else None))
    return out


def test_camera_signals_match_an_object_by_object_loop(procedural_input, tmp_path):
    """On a real class's viewpoints (some cameras removed, a keypoint the shape lacks, a camera moved so that
    part of its points leave the mask): the batched residual and inside fraction equal the loop's."""
    from carvi_torch.config import Config
    from carvi_torch.io.coco import load_coco
    from carvi_torch.viewpoints import estimate_viewpoints

    cfg = Config()
    coll = load_coco(procedural_input(tmp_path), canvas_size=cfg.input.canvas_size, classes=["car"]).collections["car"]
    vp = estimate_viewpoints(coll, cfg.viewpoints)
    assert vp.groups.k == 1  # one shape: the (K, 3) rows below are its
    n = len(coll)
    vp.has_camera = vp.has_camera.clone()
    vp.has_camera[[1, 4]] = False
    vp.cameras.t[2] += 0.12 * coll.masks.shape[-1]
    vp.shape = vp.shape.clone()
    vp.shape[0] = float("nan")
    sig = camera_signals(coll, vp)
    ref = _signals_loop(coll, vp)
    assert len(sig) == n and sum(r[0] is None for r in ref) == 2
    for got, (res, inside) in zip(sig, ref):
        assert (got["keypoint_residual"] is None) == (res is None) and (got["silhouette_inside"] is None) == (
            inside is None)
        if res is not None:
            assert got["keypoint_residual"] == pytest.approx(res, rel=1e-12, abs=1e-15)
            assert got["silhouette_inside"] == inside  # counts of pixels: exactly the loop's
    assert 0 < sig[2]["silhouette_inside"] < 1
    # two shape groups: each object projected with its own group's shape (the second one a third larger)
    two = [vp.shape, vp.shape * 1.3]
    vp.groups = SimpleNamespace(k=2, labels=torch.tensor([0, 1] * n)[:2 * n], shape=lambda g: two[g])
    got = camera_signals(coll, vp)
    assert [g["keypoint_residual"] for g in got] != [g["keypoint_residual"] for g in sig]  # the groups count
    for g, (res, inside) in zip(got, _signals_loop(coll, vp)):
        assert g["silhouette_inside"] == inside
        assert (g["keypoint_residual"] is None) == (res is None)
        if res is not None:
            assert g["keypoint_residual"] == pytest.approx(res, rel=1e-12, abs=1e-15)


def test_an_empty_grid_on_the_canvas_axes_has_no_silhouette():
    """A grid with no column (zero rows or columns), aligned with the canvas: IoU 0, as the general projection
    gives, not an error."""
    A = np.eye(4)[[2, 1, 0, 3]] * 1.0
    mask = np.ones((8, 8), bool)
    assert reconstruction_iou(np.zeros((3, 0, 4), bool), A, mask) == 0.0
    assert reconstruction_iou(np.zeros((3, 4, 0), bool), A, mask) == 0.0
