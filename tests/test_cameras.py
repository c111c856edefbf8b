"""cameras.py: per function smoke / shapes / known values / references / gradcheck / exceptions."""
from __future__ import annotations

import math

import numpy as np
import pycolmap
import pytest
import torch

from carvi_torch import cameras as C

TOL = {torch.float32: 1e-5, torch.float64: 1e-10}


def _near_identity(n, g, eps=1e-4, dtype=torch.float64):
    v = torch.randn(n, 3, generator=g, dtype=dtype) * eps
    return C.axis_angle_to_rotation(v)


def _near_pi(n, g, eps=1e-4, dtype=torch.float64):
    axis = torch.randn(n, 3, generator=g, dtype=dtype)
    axis = axis / axis.norm(dim=-1, keepdim=True)
    ang = math.pi - eps * torch.rand(n, generator=g, dtype=dtype)
    return C.axis_angle_to_rotation(axis * ang[:, None])


@pytest.fixture(params=["random", "identity", "pi"])
def rotations(request, generator):
    g = generator
    if request.param == "random":
        return C.random_rotations(200, g, dtype=torch.float64)
    if request.param == "identity":
        return _near_identity(50, g)
    return _near_pi(50, g)


# ----------------------------------------------------------------------------- quaternions


class TestQuaternion:
    def test_against_pycolmap(self, rotations):
        q = C.rotation_to_quaternion(rotations)  # (w, x, y, z)
        for R, qi in zip(rotations.numpy(), q.numpy()):
            ref = pycolmap.Rotation3d(R).quat  # (x, y, z, w)
            ref = np.array([ref[3], ref[0], ref[1], ref[2]])
            if ref[0] < 0 or (abs(ref[0]) < 1e-12 and np.dot(ref, qi) < 0):
                ref = -ref
            if np.dot(ref, qi) < 0:  # w ~ 0: either sign is the same rotation
                ref = -ref
            np.testing.assert_allclose(qi, ref, atol=1e-6)

    def test_round_trip(self, rotations):
        back = C.quaternion_to_rotation(C.rotation_to_quaternion(rotations))
        assert torch.allclose(back, rotations, atol=1e-9)

    def test_quaternion_from_pycolmap(self, generator):
        q_xyzw = torch.randn(20, 4, generator=generator, dtype=torch.float64)
        q_xyzw = q_xyzw / q_xyzw.norm(dim=-1, keepdim=True)
        R = C.quaternion_to_rotation(q_xyzw[:, [3, 0, 1, 2]])
        for Ri, qi in zip(R.numpy(), q_xyzw.numpy()):
            np.testing.assert_allclose(Ri, pycolmap.Rotation3d(qi).matrix(), atol=1e-9)

    def test_shapes_broadcast(self):
        R = torch.eye(3).expand(2, 5, 3, 3)
        assert C.rotation_to_quaternion(R).shape == (2, 5, 4)
        assert C.quaternion_to_rotation(torch.tensor([1.0, 0, 0, 0]).expand(2, 5, 4)).shape == (2, 5, 3, 3)

    def test_gradient_finite_at_identity(self):
        R = torch.eye(3, dtype=torch.float64)[None].requires_grad_()
        C.rotation_to_quaternion(R).sum().backward()
        assert torch.isfinite(R.grad).all()


# ----------------------------------------------------------------------------- angles


class TestGeodesic:
    def test_against_pycolmap(self, rotations, generator):
        other = C.random_rotations(len(rotations), generator, dtype=torch.float64)
        ang = C.geodesic_angle(rotations, other)
        for a, R1, R2 in zip(ang.numpy(), rotations.numpy(), other.numpy()):
            ref = pycolmap.Rotation3d(R1).angle_to(pycolmap.Rotation3d(R2))
            assert abs(a - ref) < 1e-6

    def test_self_angle_and_magnitude(self, rotations):
        ang = C.geodesic_angle(rotations, torch.eye(3, dtype=torch.float64))
        for a, R in zip(ang.numpy(), rotations.numpy()):
            assert abs(a - pycolmap.Rotation3d(R).angle()) < 1e-6
        assert C.geodesic_angle(rotations, rotations).abs().max() < 1e-6

    def test_known_value(self):
        R = C.rotation_about_axis(torch.tensor([0.0, 0, 1], dtype=torch.float64), 0.7)
        assert abs(float(C.geodesic_angle(R, torch.eye(3, dtype=torch.float64))) - 0.7) < 1e-12

    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_float32_matches_float64(self, generator, dtype):
        a = C.random_rotations(100, generator, dtype=torch.float64)
        b = C.random_rotations(100, generator, dtype=torch.float64)
        ref = C.geodesic_angle(a, b)
        got = C.geodesic_angle(a.to(dtype), b.to(dtype)).double()
        assert (got - ref).abs().max() < (1e-3 if dtype == torch.float32 else 1e-12)


class TestAzimuthElevationRoll:
    def test_round_trip_float64(self, generator):
        az = (torch.rand(500, generator=generator, dtype=torch.float64) * 2 - 1) * math.pi * 0.999
        el = (torch.rand(500, generator=generator, dtype=torch.float64) * 2 - 1) * math.pi / 2 * 0.99
        ro = (torch.rand(500, generator=generator, dtype=torch.float64) * 2 - 1) * math.pi * 0.999
        R = C.rotation_from_azimuth_elevation_roll(az, el, ro)
        a2, e2, r2 = C.azimuth_elevation_roll_from_rotation(R)
        assert torch.allclose(a2, az, atol=1e-9) and torch.allclose(e2, el, atol=1e-9)
        assert torch.allclose(r2, ro, atol=1e-9)
        assert torch.allclose(torch.det(R), torch.ones(500, dtype=torch.float64))

    def test_matrix_round_trip_random(self, generator):
        R = C.random_rotations(300, generator, dtype=torch.float64)
        back = C.rotation_from_azimuth_elevation_roll(*C.azimuth_elevation_roll_from_rotation(R))
        assert torch.allclose(back, R, atol=1e-9)

    def test_frontal_view(self):
        z = torch.tensor(0.0, dtype=torch.float64)
        R = C.rotation_from_azimuth_elevation_roll(z, z, z)
        # image x = object x, image y (down) = -object z (up), looking along +y (front faces -y)
        assert torch.allclose(R, torch.tensor([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]], dtype=torch.float64))

    def test_elevation_looks_down(self):
        R = C.rotation_from_azimuth_elevation_roll(torch.tensor(0.0), torch.tensor(0.5), torch.tensor(0.0))
        assert R[2, 2] < 0  # viewing direction points downwards (-z) when the camera is raised

    def test_float32_against_float64(self, generator):
        R = C.random_rotations(100, generator, dtype=torch.float64)
        a64 = C.azimuth_elevation_roll_from_rotation(R)
        a32 = C.azimuth_elevation_roll_from_rotation(R.float())
        for x, y in zip(a32, a64):
            d = torch.remainder(x.double() - y + math.pi, 2 * math.pi) - math.pi
            assert d.abs().max() < 1e-3

    def test_pascal3d_viewpoints(self, shared_data):
        """The PASCAL3D+ file's R and euler angles agree with our convention."""
        import json

        d = json.loads((shared_data / "pascal_voc_aeroplane" / "viewpoints_dev.json").read_text())
        E = torch.tensor([v["euler"] for v in d.values()], dtype=torch.float64)
        R = torch.tensor([v["R"] for v in d.values()], dtype=torch.float64)
        ours = C.rotation_from_azimuth_elevation_roll(E[:, 2], E[:, 1], E[:, 0])
        assert (ours - R).abs().max() < 1e-7
        # and PASCAL3D+'s own rotation matrix: rot^T = Rz(theta) Rx(elevation - pi/2) Rz(-azimuth), R = F rot^T
        rot = torch.tensor([v["rot"] for v in d.values()], dtype=torch.float64)
        F = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
        assert (F @ rot.transpose(1, 2) - R).abs().max() < 1e-7
        a, e, r = C.azimuth_elevation_roll_from_rotation(R)
        wrap = lambda x: torch.remainder(x + math.pi, 2 * math.pi) - math.pi  # noqa: E731
        assert wrap(e - E[:, 1]).abs().max() < 1e-6
        free = E[:, 1].abs() < math.radians(89.9)  # 4 objects seen from straight below: az and roll not separable
        assert int((~free).sum()) == 4
        assert wrap(a - E[:, 2])[free].abs().max() < 1e-6 and wrap(r - E[:, 0])[free].abs().max() < 1e-6


# ----------------------------------------------------------------------------- stiefel


class TestNearestScaledRotation:
    def test_recovers_scaled_rotation(self, generator):
        R = C.random_rotations(50, generator, dtype=torch.float64)
        s = torch.rand(50, generator=generator, dtype=torch.float64) * 5 + 0.1
        R2, s2 = C.nearest_scaled_rotation(s[:, None, None] * R[:, :2])
        assert torch.allclose(R2, R, atol=1e-10) and torch.allclose(s2, s, atol=1e-10)

    def test_is_nearest(self, generator):
        """Against a brute-force search over rotations (small perturbation of the optimum)."""
        M = torch.randn(1, 2, 3, generator=generator, dtype=torch.float64)
        R, s = C.nearest_scaled_rotation(M)
        best = ((s[:, None, None] * R[:, :2] - M) ** 2).sum()
        for _ in range(500):
            dR = C.axis_angle_to_rotation(torch.randn(3, generator=generator, dtype=torch.float64) * 0.05)
            ds = 1 + 0.05 * torch.randn((), generator=generator, dtype=torch.float64)
            cand = ((s * ds) * (R[0] @ dR)[:2] - M[0]) ** 2
            assert cand.sum() >= best - 1e-12

    def test_proper(self, generator):
        R, _ = C.nearest_scaled_rotation(torch.randn(100, 2, 3, generator=generator))
        assert torch.allclose(torch.det(R), torch.ones(100), atol=1e-5)


# ----------------------------------------------------------------------------- camera


def _random_cameras(n, g, dtype=torch.float64):
    R = C.random_rotations(n, g, dtype=dtype)
    s = torch.rand(n, generator=g, dtype=dtype) * 100 + 10
    t = torch.rand(n, 2, generator=g, dtype=dtype) * 300
    return C.ScaledOrthographic(R, s, t)


class TestScaledOrthographic:
    def test_project_depth_loop(self, generator):
        cam = _random_cameras(4, generator)
        X = torch.randn(7, 3, generator=generator, dtype=torch.float64)
        uv, z = cam.project(X), cam.depth(X)
        assert uv.shape == (4, 7, 2) and z.shape == (4, 7)
        for n in range(4):
            for p in range(7):
                ref = cam.s[n] * (cam.R[n] @ X[p])
                assert torch.allclose(uv[n, p], ref[:2] + cam.t[n]) and torch.allclose(z[n, p], ref[2])

    def test_camera_frame_round_trip(self, generator):
        cam = _random_cameras(3, generator)
        X = torch.randn(3, 5, 3, generator=generator, dtype=torch.float64)
        assert torch.allclose(cam.from_camera_frame(cam.to_camera_frame(X)), X, atol=1e-10)

    def test_compose_similarity(self, generator):
        cam = _random_cameras(5, generator)
        sim = C.Similarity2D(torch.rand(5, generator=generator, dtype=torch.float64) + 0.2,
                             torch.randn(5, 2, generator=generator, dtype=torch.float64) * 10)
        X = torch.randn(9, 3, generator=generator, dtype=torch.float64)
        assert torch.allclose(cam.compose_similarity(sim).project(X), sim.apply(cam.project(X)))
        back = cam.compose_similarity(sim).compose_similarity(sim.inverse())
        assert torch.allclose(back.project(X), cam.project(X))

    def test_mirror_twice_identity(self, generator):
        cam = _random_cameras(5, generator)
        P = torch.eye(3, dtype=torch.float64) - 2 * torch.outer(*(2 * [torch.tensor([0.6, 0.8, 0.0],
                                                                               dtype=torch.float64)]))
        twice = cam.mirror(320.0, P).mirror(320.0, P)
        assert torch.allclose(twice.R, cam.R) and torch.allclose(twice.t, cam.t) and torch.allclose(twice.s, cam.s)

    def test_mirror_sees_symmetric_object(self, generator):
        """A flipped image of a symmetric object equals projecting the mirrored (swapped) points."""
        cam = _random_cameras(3, generator)
        X = torch.randn(6, 3, generator=generator, dtype=torch.float64)
        P = torch.diag(torch.tensor([-1.0, 1, 1], dtype=torch.float64))
        W = 400.0
        uv = cam.project(X)
        flipped = torch.stack([W - 1 - uv[..., 0], uv[..., 1]], dim=-1)
        mirrored = cam.mirror(W, P)
        assert torch.allclose(mirrored.project(X @ P.T), flipped)
        assert torch.allclose(torch.det(mirrored.R), torch.ones(3, dtype=torch.float64))

    def test_serialisation(self, generator):
        cam = _random_cameras(3, generator)
        back = C.ScaledOrthographic.from_list(cam.to_list(), dtype=torch.float64)
        assert torch.equal(back.R, cam.R) and torch.equal(back.s, cam.s) and torch.equal(back.t, cam.t)

    def test_exceptions(self):
        with pytest.raises(ValueError):
            C.ScaledOrthographic(torch.eye(3), torch.ones(1), torch.zeros(1, 2))
        with pytest.raises(ValueError):
            C.ScaledOrthographic(torch.eye(3)[None], torch.ones(2), torch.zeros(1, 2))

    def test_from_affine_gradcheck(self, generator):
        M = torch.randn(2, 2, 3, generator=generator, dtype=torch.float64, requires_grad=True)
        t = torch.randn(2, 2, generator=generator, dtype=torch.float64)
        X = torch.randn(4, 3, generator=generator, dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda m: C.ScaledOrthographic.from_affine(m, t).project(X), (M,))
