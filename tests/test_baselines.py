"""Tests of carvi_torch.evaluation.baselines: Puffball and the SfM convex hull.

References: a brute-force numpy evaluation of the Puffball height formula, shapely
rasterisation of the mesh's projection, scipy's ConvexHull, and analytic disks/spheres.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch
import trimesh
from scipy import ndimage
from scipy.spatial import ConvexHull, cKDTree
from skimage import morphology

from carvi_torch.evaluation.baselines import medial_balls, puffball, puffball_height, sfm_convex_hull
from carvi_torch.cameras import ScaledOrthographic, random_rotations
from carvi_torch.evaluation.metrics import evaluate_reconstruction


def disk(size: int, cx: float, cy: float, r: float) -> torch.Tensor:
    yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    return (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r


def l_shape(size: int = 40) -> torch.Tensor:
    m = torch.zeros(size, size, dtype=torch.bool)
    m[5:35, 5:15] = True
    m[25:35, 5:35] = True
    return m


def projected_silhouette(mesh: trimesh.Trimesh, shape: tuple[int, int]) -> np.ndarray:
    """Pixels whose centre lies in the orthographic projection (x, y) of the mesh (shapely)."""
    tri = mesh.triangles[:, :, :2]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    keep = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) > 1e-12
    union = shapely.union_all(shapely.polygons(tri[keep]))
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return shapely.contains_xy(union, xx.ravel().astype(float), yy.ravel().astype(float)).reshape(shape)


def within_a_pixel(a: np.ndarray, b: np.ndarray) -> bool:
    """a and b differ only on pixels next to b's boundary (3x3 neighbourhood)."""
    st = np.ones((3, 3), bool)
    return bool(np.all(a <= ndimage.binary_dilation(b, st)) and np.all(ndimage.binary_erosion(b, st) <= a))


def single_camera(seed: int = 0, s: float = 30.0) -> ScaledOrthographic:
    R = random_rotations(1, torch.Generator().manual_seed(seed), dtype=torch.float64)
    f64 = dict(dtype=torch.float64)
    return ScaledOrthographic(R, torch.tensor([s], **f64), torch.tensor([[64.0, 60.0]], **f64))


# --------------------------------------------------------------------------- medial axis


class TestMedialBalls:
    def test_disk_centre_and_radius(self):
        c, r = medial_balls(disk(41, 20, 20, 12))
        i = int(r.argmax())  # digital medial axes need not hold the exact centre pixel
        assert float((c[i] - torch.tensor([20.0, 20.0])).norm()) <= 1.5 and float(r[i]) == pytest.approx(12.0, abs=1.5)
        assert c.dtype == torch.float32 and c.shape == (r.shape[0], 2)

    def test_balls_hold_foreground_only(self):
        m = l_shape()
        c, r = medial_balls(m)
        yy, xx = np.nonzero(~m.numpy())
        bg = np.stack([xx, yy], 1).astype(float)
        nearest_bg, _ = cKDTree(bg).query(c.numpy())
        np.testing.assert_allclose(nearest_bg, r.numpy(), rtol=1e-6)  # r = distance to the background

    def test_deterministic(self):
        m = l_shape()
        a, b = medial_balls(m), medial_balls(m)
        assert torch.equal(a[0], b[0]) and torch.equal(puffball_height(m), puffball_height(m))

    def test_empty_and_errors(self):
        c, r = medial_balls(torch.zeros(8, 8, dtype=torch.bool))
        assert c.shape == (0, 2) and r.shape == (0,)
        with pytest.raises(ValueError, match=r"\(H, W\)"):
            medial_balls(torch.zeros(2, 8, 8, dtype=torch.bool))


# --------------------------------------------------------------------------- height field


class TestPuffballHeight:
    def test_formula_vs_brute_force(self):
        m = l_shape(24)
        m[3:6, 15:20] = True  # a thin limb
        skel, dist = morphology.medial_axis(m.numpy(), return_distance=True, rng=0)  # the same tie-breaking
        qs = [(x, y, round(dist[y, x] ** 2)) for y, x in zip(*np.nonzero(skel))]  # integer r^2
        want = np.zeros(m.shape)
        for y, x in zip(*np.nonzero(m.numpy())):
            terms = [math.sqrt(r2 - (x - qx) ** 2 - (y - qy) ** 2) for qx, qy, r2 in qs
                     if (x - qx) ** 2 + (y - qy) ** 2 <= r2]
            want[y, x] = math.log(1 + sum(math.exp(t) for t in terms)) if terms else math.nan
        got = puffball_height(m, chunk_elems=50).numpy()  # tiny chunks
        covered = ~np.isnan(want)
        np.testing.assert_allclose(got[covered], want[covered], rtol=1e-5)
        assert np.all(got[~m.numpy()] == 0) and np.all(got[m.numpy()] >= math.log(2) - 1e-6)

    def test_disk_is_a_hemisphere(self):
        R = 15.0
        h = puffball_height(disk(41, 20, 20, R)).numpy()
        yy, xx = np.mgrid[0:41, 0:41]
        rho2 = (xx - 20.0) ** 2 + (yy - 20.0) ** 2
        inner = rho2 <= (R - 3) ** 2
        sphere = np.sqrt(np.maximum((R + 0.5) ** 2 - rho2, 0))
        # soft maximum of a few balls near the centre: within a pixel plus log(1 + #balls)
        nballs = int(medial_balls(disk(41, 20, 20, R))[0].shape[0])
        assert np.all(np.abs(h[inner] - sphere[inner]) <= 1.5 + math.log(1 + nballs))


# --------------------------------------------------------------------------- mesh


class TestPuffballMesh:
    @pytest.mark.parametrize("mask", [disk(41, 20, 19, 15), l_shape()], ids=["disk", "L"])
    def test_closed_symmetric_and_silhouette(self, mask):
        mesh = puffball(mask, depth_step=0.5)
        assert mesh.is_watertight and mesh.volume > 0
        v = mesh.vertices
        mirrored = v * np.array([1.0, 1.0, -1.0])
        gap, _ = cKDTree(v).query(mirrored)
        assert gap.max() < 1e-4  # symmetric about the image plane z = 0
        assert within_a_pixel(projected_silhouette(mesh, tuple(mask.shape)), mask.numpy())

    def test_disk_is_sphere_like(self):
        R = 15.0
        mesh = puffball(disk(41, 20, 20, R))
        r = np.linalg.norm(mesh.vertices - np.array([20.0, 20.0, 0.0]), axis=1)
        assert np.median(r) == pytest.approx(R + 0.5, abs=1.5)
        assert mesh.volume == pytest.approx(4 / 3 * math.pi * (R + 0.5) ** 3, rel=0.1)
        assert mesh.vertices[:, 2].max() == pytest.approx(R, abs=2.0)

    def test_evaluates_against_a_sphere(self):
        R = 15.0
        gt = trimesh.creation.icosphere(4, radius=R + 0.5)
        gt.apply_translation([20.0, 20.0, 7.0])  # another depth origin
        r = evaluate_reconstruction(puffball(disk(41, 20, 20, R)), gt)
        assert r["reason"] is None and r["error_percent"] < 2.0 and r["offset"] == pytest.approx(7.0, abs=0.5)

    def test_camera_empty_and_errors(self):
        m = disk(21, 10, 10, 6)
        a = puffball(m, single_camera())
        assert np.allclose(a.vertices, puffball(m).vertices)  # the camera does not move the mesh
        assert len(puffball(torch.zeros(9, 9, dtype=torch.bool)).faces) == 0
        two = ScaledOrthographic.cat([single_camera(0), single_camera(1)])
        with pytest.raises(ValueError, match="one camera"):
            puffball(m, two)
        with pytest.raises(ValueError, match="depth_step"):
            puffball(m, depth_step=0)


# --------------------------------------------------------------------------- SFMc


class TestSfmConvexHull:
    def test_hull_contains_all_points_and_matches_scipy(self):
        g = torch.Generator().manual_seed(0)
        S = torch.randn(14, 3, generator=g, dtype=torch.float64)
        S[3] = float("nan")
        S[7, 1] = float("nan")
        cam = single_camera(3)
        hull = sfm_convex_hull(S, cam)
        assert hull.is_watertight and hull.is_convex
        pts = cam.to_camera_frame(S[torch.isfinite(S).all(1)])[0].numpy()
        # every point is inside or on every face plane
        normals, origins = hull.face_normals, hull.triangles[:, 0]
        assert (np.einsum("fk,pfk->pf", normals, pts[:, None, :] - origins[None]) <= 1e-9).all()
        ref = ConvexHull(pts)
        assert hull.volume == pytest.approx(ref.volume, rel=1e-9)
        # hull vertices are mapped input points
        assert cKDTree(pts).query(hull.vertices)[0].max() < 1e-9

    def test_degenerate_gives_empty_mesh(self):
        cam = single_camera()
        three = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [float("nan"), 0, 0]], dtype=torch.float64)
        plane = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 3, 0]], dtype=torch.float64)
        for S in (three, plane):
            hull = sfm_convex_hull(S, cam)
            assert len(hull.faces) == 0
            assert "no faces" in evaluate_reconstruction(hull, trimesh.creation.box())["reason"]

    def test_errors(self):
        with pytest.raises(ValueError, match=r"\(K, 3\)"):
            sfm_convex_hull(torch.zeros(5, 2), single_camera())
        with pytest.raises(ValueError, match="one camera"):
            sfm_convex_hull(torch.zeros(5, 3), ScaledOrthographic.cat([single_camera(0), single_camera(1)]))
