"""interop.py: our cameras in PyTorch3D's and kornia's conventions, checked by projecting points both ways.

PyTorch3D itself is not installed: its documented transforms are written out below as the 4x4
row-vector matrices of ``pytorch3d.renderer.cameras`` (world -> view ``X R + T``; the orthographic
``K``; ``get_ndc_camera_transform`` for screen-space cameras; ``get_ndc_to_screen_transform`` with
the x/y flip of ``transform_points_screen``), independently of carvi_torch.interop.
"""
from __future__ import annotations

import torch

from carvi_torch.cameras import ScaledOrthographic, random_rotations
from carvi_torch.interop import from_pytorch3d, to_kornia, to_kornia_pinhole, to_pytorch3d


def _cameras(n=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    R = random_rotations(n, generator=g, dtype=torch.float64)
    s = 0.5 + 3 * torch.rand(n, generator=g, dtype=torch.float64)
    t = torch.rand(n, 2, generator=g, dtype=torch.float64) * torch.tensor([300.0, 200.0], dtype=torch.float64)
    X = torch.randn(n, 50, 3, generator=g, dtype=torch.float64) * 10
    return ScaledOrthographic(R, s, t), X


def _row(M):  # a Transform3d's matrix: points @ M
    return M.transpose(-1, -2)


def _p3d_screen(X, R, T, focal, pp, hw, in_ndc):
    """PyTorch3D's ``OrthographicCameras(...).transform_points_screen(X)`` from its documented matrices."""
    n = X.shape[0]
    H, W = hw[:, 0], hw[:, 1]
    Xh = torch.cat([X, torch.ones_like(X[..., :1])], -1)
    world_to_view = torch.zeros(n, 4, 4, dtype=X.dtype)  # Rotate(R).compose(Translate(T))
    world_to_view[:, :3, :3], world_to_view[:, 3, :3], world_to_view[:, 3, 3] = R, T, 1.0
    K = torch.zeros(n, 4, 4, dtype=X.dtype)  # _get_sfm_calibration_matrix(orthographic=True)
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 3], K[:, 1, 3], K[:, 2, 2], K[:, 3, 3] = (
        focal[:, 0], focal[:, 1], pp[:, 0], pp[:, 1], 1.0, 1.0)
    scale = torch.minimum(H, W) / 2.0
    N2S = torch.zeros(n, 4, 4, dtype=X.dtype)  # get_ndc_to_screen_transform (before the flip)
    N2S[:, 0, 0], N2S[:, 1, 1], N2S[:, 0, 3], N2S[:, 1, 3], N2S[:, 2, 2], N2S[:, 3, 3] = (
        scale, scale, -W / 2.0, -H / 2.0, 1.0, 1.0)
    M = world_to_view @ _row(K)
    if not in_ndc:  # get_ndc_camera_transform: principal point fix, then screen -> ndc
        fix = torch.eye(4, dtype=X.dtype).repeat(n, 1, 1)
        fix[:, :2, 3] = -2.0 * pp
        M = M @ _row(fix) @ torch.linalg.inv(_row(N2S))
    flip = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=X.dtype))
    out = Xh @ M @ _row(N2S) @ flip
    return out[..., :2] / out[..., 3:]


def test_pytorch3d_screen_and_ndc_cameras_project_like_ours():
    cams, X = _cameras()
    hw = torch.tensor([[240.0, 320.0]], dtype=torch.float64).expand(5, 2)
    ours = cams.project(X)  # pixel centres at integers
    for in_ndc in (False, True):
        p = to_pytorch3d(cams, (240, 320), in_ndc=in_ndc, depth=100.0)
        assert torch.allclose(torch.det(p["R"]), torch.ones(5, dtype=torch.float64))
        scr = _p3d_screen(X, p["R"], p["T"], p["focal_length"], p["principal_point"], hw, in_ndc)
        assert torch.allclose(scr - 0.5, ours, atol=1e-9), in_ndc  # screen: pixel j's centre at j + 0.5
        back = from_pytorch3d(p["R"], p["focal_length"], p["principal_point"], p["T"], (240, 320), in_ndc)
        assert torch.allclose(back.R, cams.R) and torch.allclose(back.s, cams.s) and torch.allclose(back.t, cams.t)
    # the view frame: +X left, +Y up, +Z into the scene (a point right of the origin's image has view x < 0)
    p = to_pytorch3d(cams, (240, 320))
    view = X @ p["R"]
    assert torch.allclose(view[..., 0], -(X @ cams.R[:, 0, :, None])[..., 0])
    assert torch.allclose(view[..., 2], cams.depth(X) / cams.s[:, None])


def test_from_pytorch3d_moves_a_view_shift_into_t():
    cams, X = _cameras(3, seed=1)
    p = to_pytorch3d(cams, (100, 100))
    T = torch.tensor([[1.5, -2.0, 7.0]], dtype=torch.float64).expand(3, 3)
    hw = torch.tensor([[100.0, 100.0]], dtype=torch.float64).expand(3, 2)
    scr = _p3d_screen(X, p["R"], T, p["focal_length"], p["principal_point"], hw, False)
    back = from_pytorch3d(p["R"], p["focal_length"], p["principal_point"], T)
    assert torch.allclose(back.project(X), scr - 0.5, atol=1e-9)


def test_kornia_orthographic_projects_and_unprojects_like_ours():
    from kornia.geometry.vector import Vector2, Vector3
    from kornia.sensors.camera import CameraModel, CameraModelType

    cams, X = _cameras()
    model, E = to_kornia(cams, (240, 320), depth=50.0)
    Xc = X @ E[:, None, :3, :3].transpose(-1, -2).squeeze(1) + E[:, None, :3, 3]  # world -> camera
    assert model.params.shape == (5, 4)
    for i in range(5):  # one camera's parameter row per point batch
        m = CameraModel(model.image_size, CameraModelType.ORTHOGRAPHIC, model.params[i])
        uv = m.project(Vector3(Xc[i])).data
        assert torch.allclose(uv, cams.project(X)[i], atol=1e-9)
        back = m.unproject(Vector2(uv), Xc[i, :, 2]).data  # the camera-frame point, given its depth
        Xw = (back - E[i, :3, 3]) @ E[i, :3, :3]  # camera -> world (R^T)
        assert torch.allclose(Xw, X[i], atol=1e-8)


def test_kornia_pinhole_is_the_weak_perspective_limit():
    cams, X = _cameras()
    err = []
    for distance in (1e3, 1e5):
        pin = to_kornia_pinhole(cams, (240, 320), distance)
        uv = pin.project(X)  # (N, P, 3) world points -> (N, P, 2) pixels
        err.append(float((uv - cams.project(X)).abs().max()))
        # and back: the pinhole's unprojection at the true camera depth recovers the points
        depth = (X @ cams.R[:, 2, :, None])[..., 0] + distance
        back = pin.unproject(uv, depth[..., None])
        assert torch.allclose(back, X, atol=1e-6 * distance)
    # |error| ~ s |x - t| |z| / distance: shrinks with the distance (100x farther: about 100x smaller)
    assert err[1] < 0.05 and err[1] < err[0] / 50
