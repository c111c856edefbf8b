"""Tests of carvi_torch.evaluation.metrics: sampling, exact distances, RMS errors, depth offset, IoU.

References are independent of the code under test: a float64 numpy point-triangle
distance written differently (projection test + edge distances), brute force over all
triangles, trimesh's closest point, analytic solids and dense numerical integration.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from carvi_torch.evaluation.metrics import (
    EvaluationMesh,
    MeshDistanceIndex,
    barycentric_grid,
    best_depth_offset,
    bounding_box_diagonal,
    evaluate_reconstruction,
    mesh_tensors,
    occupancy_iou,
    point_to_mesh_distance,
    point_triangle_distance,
    rms_distance,
    sample_surface,
    symmetric_rms,
    symmetric_rms_percent,
    triangle_areas,
    voxel_iou,
    voxelize_solid,
)
from tests.conftest import requires_cuda


# --------------------------------------------------------------------------- references


def ref_point_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[float, str]:
    """float64 distance from p to triangle abc, and the feature it is closest to.

    Projection on the plane when it falls inside (face), else the nearest of the three
    segments (edge interior, or vertex when the segment parameter is clamped).
    """
    n = np.cross(b - a, c - a)
    nn = n @ n
    if nn > 1e-300:
        q = p - ((p - a) @ n) / nn * n
        signs = [np.cross(v1 - q, v2 - q) @ n for v1, v2 in ((a, b), (b, c), (c, a))]
        if min(signs) >= 0:
            return float(np.linalg.norm(p - q)), "face"
    best, feature = math.inf, None
    for (u, v), name in (((a, b), "ab"), ((b, c), "bc"), ((c, a), "ca")):
        e = v - u
        ee = e @ e
        t = 0.0 if ee == 0 else float(np.clip((p - u) @ e / ee, 0.0, 1.0))
        d = float(np.linalg.norm(p - (u + t * e)))
        if d < best:
            best = d
            feature = f"vertex-{name[0]}" if t == 0.0 else f"vertex-{name[1]}" if t == 1.0 else f"edge-{name}"
    return best, feature


def ref_point_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Brute force over every triangle with :func:`ref_point_triangle`."""
    tri = vertices[faces]
    return np.array([min(ref_point_triangle(p, *t)[0] for t in tri) for p in points])


def random_soup(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of sizes from 1e-3 to 1, slivers and a few degenerate ones, in a unit box."""
    centre = rng.uniform(-1, 1, (n, 1, 3))
    size = 10 ** rng.uniform(-3, 0, (n, 1, 1))
    tri = centre + size * rng.normal(size=(n, 3, 3))
    tri[: n // 10, 2] = tri[: n // 10, 0] + 1e-4 * (tri[: n // 10, 1] - tri[: n // 10, 0])  # slivers
    tri[n // 10: n // 10 + 2, 2] = 0.3 * tri[n // 10: n // 10 + 2, 0] + 0.7 * tri[n // 10: n // 10 + 2, 1]  # collinear
    tri[n // 10 + 2, 1] = tri[n // 10 + 2, 0]  # two coincident vertices
    return tri.reshape(-1, 3), np.arange(3 * n).reshape(n, 3)


def box_surface_distance(p: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Exact distance from points (P, 3) to the surface of the box [lo, hi]."""
    outside = np.linalg.norm(p - np.clip(p, lo, hi), axis=1)
    inside = np.minimum(p - lo, hi - p).min(axis=1)
    return np.where(outside > 0, outside, inside)


def box_face_grid(lo: np.ndarray, hi: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint-rule points and weights (n x n per face) on the surface of a box."""
    pts, wts = [], []
    ext = hi - lo
    g = (np.arange(n) + 0.5) / n
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        for side in (lo[axis], hi[axis]):
            P = np.zeros((n * n, 3))
            P[:, axis] = side
            P[:, u] = lo[u] + np.repeat(g, n) * ext[u]
            P[:, v] = lo[v] + np.tile(g, n) * ext[v]
            pts.append(P)
            wts.append(np.full(n * n, ext[u] * ext[v] / (n * n)))
    return np.concatenate(pts), np.concatenate(wts)


def box_mesh(lo, hi) -> trimesh.Trimesh:
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def load_cad(shared_data, name: str) -> trimesh.Trimesh:
    d = np.load(shared_data / "pascal3d_cad" / f"{name}.npz")
    return trimesh.Trimesh(d["vertices"].astype(np.float64), d["faces"].astype(np.int64), process=False)


# --------------------------------------------------------------------------- mesh input


class TestMeshInput:
    def test_trimesh_and_pair_agree(self):
        box = trimesh.creation.box()
        v1, f1 = mesh_tensors(box)
        v2, f2 = mesh_tensors((np.asarray(box.vertices), np.asarray(box.faces)), dtype=torch.float64)
        assert v1.shape == (8, 3) and f1.dtype == torch.int64 and v1.dtype == torch.float32
        assert torch.allclose(v1.double(), v2) and torch.equal(f1, f2)

    @pytest.mark.parametrize("mesh, msg", [
        ((torch.zeros(4, 2), torch.zeros(1, 3, dtype=torch.long)), "vertices must be"),
        ((torch.zeros(4, 3), torch.zeros(1, 4, dtype=torch.long)), "faces must be"),
        ((torch.zeros(4, 3), torch.tensor([[0, 1, 4]])), "face indices"),
        ("not a mesh", "trimesh.Trimesh or a"),
    ])
    def test_errors(self, mesh, msg):
        with pytest.raises(ValueError, match=msg):
            mesh_tensors(mesh)

    def test_diagonal_ignores_unreferenced_vertices(self):
        v = torch.tensor([[0.0, 0, 0], [3, 0, 0], [0, 4, 0], [100, 100, 100]])
        assert bounding_box_diagonal(v, torch.tensor([[0, 1, 2]])) == pytest.approx(5.0)
        assert bounding_box_diagonal(v) == pytest.approx(math.sqrt(3) * 100)

    def test_triangle_areas_vs_trimesh(self):
        mesh = trimesh.creation.icosphere(2)
        v, f = mesh_tensors(mesh, dtype=torch.float64)
        np.testing.assert_allclose(triangle_areas(v, f).numpy(), mesh.area_faces, rtol=1e-12)


# --------------------------------------------------------------------------- sampling


class TestBarycentricGrid:
    @pytest.mark.parametrize("n", [1, 2, 3, 7])
    def test_matches_enumeration(self, n):
        face, u, v = barycentric_grid(torch.tensor([n]))
        got = sorted(zip(np.round(u.numpy() * 3 * n).astype(int), np.round(v.numpy() * 3 * n).astype(int)))
        want = sorted([(3 * i + 1, 3 * j + 1) for i in range(n) for j in range(n - i)]
                      + [(3 * i + 2, 3 * j + 2) for i in range(n) for j in range(n - 1 - i)])
        assert got == want and face.tolist() == [0] * n * n

    def test_ragged_and_random_points_inside(self, generator):
        n = torch.tensor([1, 4, 2, 9])
        face, u, v = barycentric_grid(n, generator)
        assert torch.equal(torch.bincount(face), n * n)
        assert bool((u >= 0).all() and (v >= 0).all() and (u + v <= 1 + 1e-12).all())
        # every random point lies in its own sub-triangle: rows/cols of the grid agree
        nn = n[face].double()
        assert bool((torch.floor(u * nn) + torch.floor(v * nn) <= nn - 1).all())

    def test_errors(self):
        with pytest.raises(ValueError, match=">= 1"):
            barycentric_grid(torch.tensor([1, 0]))
        with pytest.raises(ValueError, match=r"\(F,\)"):
            barycentric_grid(torch.ones(2, 2, dtype=torch.long))


class TestSampleSurface:
    def test_weights_sum_to_area(self, generator):
        mesh = trimesh.creation.icosphere(3, radius=2.0)
        v, f = mesh_tensors(mesh, dtype=torch.float64)
        for kw in ({}, {"generator": generator}, {"merge_small": False}):
            for step in (0.05, 0.5, 3.0):  # fine, coarse, coarser than every triangle
                p, w = sample_surface(v, f, step, **kw)
                assert p.shape == (w.shape[0], 3)
                assert float(w.sum()) == pytest.approx(mesh.area, rel=1e-10)

    def test_density_follows_step(self):
        square = (torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]), torch.tensor([[0, 1, 2], [0, 2, 3]]))
        for step in (0.1, 0.02, 0.01):
            p, w = sample_surface(*square, step)
            assert p.shape[0] == pytest.approx(1 / step ** 2, rel=0.05)
        # many small triangles: the systematic sampling keeps the density
        fine = trimesh.creation.icosphere(5)  # 20480 faces of area ~6e-4
        v, f = mesh_tensors(fine)
        for step in (0.05, 0.1):
            p, _ = sample_surface(v, f, step)
            assert p.shape[0] == pytest.approx(fine.area / step ** 2, rel=0.05)
            assert p.shape[0] < f.shape[0]
        p, _ = sample_surface(v, f, 0.1, merge_small=False)
        assert p.shape[0] == f.shape[0]  # one point per triangle

    def test_points_on_surface(self, generator):
        mesh = trimesh.creation.icosphere(2)
        v, f = mesh_tensors(mesh, dtype=torch.float64)
        p, _ = sample_surface(v, f, 0.07, generator=generator)
        _, dist, _ = trimesh.proximity.closest_point(mesh, p.numpy()[::10])
        assert dist.max() < 1e-9

    def test_linear_integrand_exact(self):
        # a triangle with n >= 1 everywhere: the midpoint rule integrates x exactly
        v = torch.tensor([[0.0, 0, 0], [2, 0, 0], [0.5, 1.5, 0]], dtype=torch.float64)
        f = torch.tensor([[0, 1, 2]])
        p, w = sample_surface(v, f, 0.11)
        assert float((w * p[:, 0]).sum()) == pytest.approx(float(triangle_areas(v, f)) * float(v[:, 0].mean()),
                                                           rel=1e-12)

    def test_quadrature_converges(self):
        # integral of x^2 over the unit square = 1/3
        square = (torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], dtype=torch.float64),
                  torch.tensor([[0, 1, 2], [0, 2, 3]]))
        errs = []
        for step in (0.1, 0.05, 0.025):
            p, w = sample_surface(*square, step)
            errs.append(abs(float((w * p[:, 0] ** 2).sum()) - 1 / 3))
        assert errs[2] < errs[0] / 8 and errs[2] < 1e-4

    def test_deterministic_and_seeded(self):
        v, f = mesh_tensors(trimesh.creation.icosphere(2))
        a = sample_surface(v, f, 0.1)[0]
        assert torch.equal(a, sample_surface(v, f, 0.1)[0])
        r1 = sample_surface(v, f, 0.1, generator=torch.Generator().manual_seed(1))[0]
        r2 = sample_surface(v, f, 0.1, generator=torch.Generator().manual_seed(1))[0]
        r3 = sample_surface(v, f, 0.1, generator=torch.Generator().manual_seed(2))[0]
        assert torch.equal(r1, r2) and not torch.equal(r1, r3)

    def test_errors(self):
        v, f = mesh_tensors(trimesh.creation.box())
        for bad in (0.0, -1.0, float("nan")):
            with pytest.raises(ValueError, match="step"):
                sample_surface(v, f, bad)
        with pytest.raises(ValueError, match="max_points"):
            sample_surface(v, f, 1e-4, max_points=1000)


# --------------------------------------------------------------------------- exact distances


class TestPointTriangleDistance:
    def test_every_voronoi_region_vs_reference(self):
        rng = np.random.default_rng(0)
        tris = rng.normal(size=(40, 3, 3))
        points, expected, regions = [], [], set()
        for a, b, c in tris:
            n = np.cross(b - a, c - a)
            n /= np.linalg.norm(n)
            cen = (a + b + c) / 3
            probes = [cen + 0.3 * n]  # face
            for v in (a, b, c):  # vertex regions: outwards from the centroid
                probes.append(v + 0.5 * (v - cen) + 0.2 * n)
            for u, v in ((a, b), (b, c), (c, a)):  # edge regions: outwards from the edge midpoint
                m = (u + v) / 2
                probes.append(m + 0.3 * (m - cen) - 0.1 * n)
            probes += list(cen + rng.normal(size=(5, 3)))
            for p in probes:
                d, feat = ref_point_triangle(p, a, b, c)
                points.append(np.concatenate([p, a, b, c]))
                expected.append(d)
                regions.add(feat)
        assert regions == {"face", "vertex-a", "vertex-b", "vertex-c", "edge-ab", "edge-bc", "edge-ca"}
        X = torch.tensor(np.array(points))
        got = point_triangle_distance(X[:, :3], X[:, 3:6], X[:, 6:9], X[:, 9:])
        np.testing.assert_allclose(got.numpy(), expected, rtol=1e-10, atol=1e-12)
        got32 = point_triangle_distance(*(X.float()[:, 3 * i:3 * i + 3] for i in range(4)))
        np.testing.assert_allclose(got32.numpy(), expected, rtol=1e-4, atol=1e-5)

    def test_degenerate_triangles(self):
        rng = np.random.default_rng(1)
        a, b = rng.normal(size=3), rng.normal(size=3)
        tris = [(a, b, 0.25 * a + 0.75 * b), (a, a, b), (a, a, a), (a, 0.5 * (a + b), b)]
        for tri in tris:
            for p in rng.normal(size=(20, 3)):
                got = point_triangle_distance(*(torch.tensor(x) for x in (p, *tri)))
                assert float(got) == pytest.approx(ref_point_triangle(p, *tri)[0], rel=1e-9, abs=1e-12)

    def test_broadcast_and_squared(self):
        tri = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
        p = torch.tensor([[[0.25, 0.25, 2.0]], [[2.0, 0.0, 0.0]]])  # (2, 1, 3)
        d2 = point_triangle_distance(p, tri[0], tri[1], tri[2], squared=True)
        assert d2.shape == (2, 1) and torch.allclose(d2, torch.tensor([[4.0], [1.0]]))
        with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
            point_triangle_distance(torch.zeros(2), tri[0], tri[1], tri[2])


class TestPointToMeshDistance:
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_brute_force_on_random_soups(self, seed):
        rng = np.random.default_rng(seed)
        v, f = random_soup(rng, 60)
        near = v[rng.integers(0, len(v), 80)] + 10 ** rng.uniform(-4, -1, (80, 1)) * rng.normal(size=(80, 3))
        points = np.concatenate([near, rng.uniform(-3, 3, (40, 3)), 10 * rng.normal(size=(5, 3))])
        want = ref_point_mesh(points, v, f)
        V, F, P = torch.tensor(v), torch.tensor(f), torch.tensor(points)
        # defaults, and a deep hierarchy with tiny pieces, few seeds and tiny chunks
        for kw in ({}, {"size": 0.05, "width": 2, "grid": 2, "chunk": 7}, {"width": 5, "grid": 200}):
            got = MeshDistanceIndex(V, F, **kw).distance(P)
            np.testing.assert_allclose(got.numpy(), want, rtol=1e-9, atol=1e-12)
        got32 = point_to_mesh_distance(P.float(), V.float(), F)
        np.testing.assert_allclose(got32.numpy(), want, rtol=1e-4, atol=1e-5)

    def test_vs_trimesh_closest_point(self):
        mesh = trimesh.creation.torus(1.0, 0.3, major_sections=48, minor_sections=24)
        rng = np.random.default_rng(3)
        points = rng.uniform(-1.6, 1.6, (300, 3))
        closest_t, dist_t, _ = trimesh.proximity.closest_point(mesh, points)
        V, F = mesh_tensors(mesh, dtype=torch.float64)
        index = MeshDistanceIndex(V, F)
        dist, closest, face = index.closest(torch.tensor(points))
        np.testing.assert_allclose(dist.numpy(), dist_t, rtol=1e-5, atol=1e-9)
        # the closest point is on the mesh, at that distance from the point
        np.testing.assert_allclose(np.linalg.norm(points - closest.numpy(), axis=1), dist_t, rtol=1e-5, atol=1e-9)
        on = point_triangle_distance(closest, *V[F[face]].unbind(1))
        assert float(on.max()) < 1e-9

    def test_real_cad_vs_trimesh(self, shared_data):
        mesh = load_cad(shared_data, "aeroplane03")  # 7106 faces, slivers and tiny triangles
        rng = np.random.default_rng(4)
        points = mesh.sample(150, seed=4) + 0.02 * rng.normal(size=(150, 3))
        points = np.concatenate([points, rng.uniform(-0.5, 0.5, (50, 3))])
        _, dist_t, _ = trimesh.proximity.closest_point(mesh, points)
        V, F = mesh_tensors(mesh, dtype=torch.float64)
        np.testing.assert_allclose(point_to_mesh_distance(torch.tensor(points), V, F).numpy(), dist_t,
                                   rtol=1e-5, atol=1e-9)
        d32 = point_to_mesh_distance(torch.tensor(points).float(), V.float(), F)
        np.testing.assert_allclose(d32.numpy(), dist_t, rtol=1e-4, atol=1e-6)

    def test_errors(self):
        V, F = mesh_tensors(trimesh.creation.box())
        with pytest.raises(ValueError, match="F >= 1"):
            MeshDistanceIndex(V, F[:0])
        with pytest.raises(ValueError, match="finite"):
            MeshDistanceIndex(V, F).distance(torch.tensor([[0.0, float("nan"), 0.0]]))
        with pytest.raises(ValueError, match=r"\(P, 3\)"):
            MeshDistanceIndex(V, F).distance(torch.zeros(3))
        V2 = V.clone()
        V2[0, 0] = float("inf")
        with pytest.raises(ValueError, match="finite"):
            MeshDistanceIndex(V2, F)

    @requires_cuda
    def test_cuda_matches_cpu(self):
        rng = np.random.default_rng(5)
        v, f = random_soup(rng, 200)
        P = torch.tensor(rng.uniform(-1.5, 1.5, (500, 3)))
        cpu = point_to_mesh_distance(P, torch.tensor(v), torch.tensor(f))
        gpu = point_to_mesh_distance(P.cuda(), torch.tensor(v).cuda(), torch.tensor(f).cuda())
        assert gpu.is_cuda
        torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-9, atol=1e-12)


# --------------------------------------------------------------------------- RMS errors


class TestRms:
    def test_concentric_spheres(self):
        # faceted spheres: vertices on the sphere, faces up to the sagitta inside it
        r1, r2 = 1.0, 1.5
        inner, outer = trimesh.creation.icosphere(4, radius=r1), trimesh.creation.icosphere(4, radius=r2)
        edge = outer.edges_unique_length.max()
        sagitta = edge ** 2 / (8 * r1)  # the most a face of either sphere dips inside its sphere
        e = symmetric_rms(inner, outer, step=0.05)
        assert e == pytest.approx(r2 - r1, abs=2 * sagitta)  # tessellation tolerance 2 sagitta ~ 2.6e-3
        assert 100 * e / (2 * r2 * math.sqrt(3)) == pytest.approx(symmetric_rms_percent(inner, outer, step=0.05),
                                                                   rel=1e-12)

    @pytest.mark.parametrize("delta", [0.1, 0.35])
    def test_shifted_box_vs_numerical_integration(self, delta):
        lo, hi = np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.6, 0.4])
        shift = np.array([delta, 0.0, 0.0])
        a, b = box_mesh(lo, hi), box_mesh(lo + shift, hi + shift)
        pts, wts = box_face_grid(lo, hi, 200)  # dense midpoint rule, independent of sample_surface
        ref = math.sqrt((wts * box_surface_distance(pts, lo + shift, hi + shift) ** 2).sum() / wts.sum())
        step = 0.005 * math.sqrt(1.0 ** 2 + 0.6 ** 2 + 0.4 ** 2)
        assert rms_distance(a, b, step) == pytest.approx(ref, rel=0.01)
        assert symmetric_rms(a, b) == pytest.approx(ref, rel=0.01)  # the two directions agree by symmetry

    def test_identical_meshes(self, shared_data):
        mesh = load_cad(shared_data, "aeroplane03")  # float32 boxes, float64 exact distances
        assert symmetric_rms(mesh, mesh) < 1e-6 * mesh.scale

    def test_identical_procedural(self):
        mesh = trimesh.creation.capsule(1.0, 0.4)
        assert symmetric_rms(mesh, mesh) < 1e-6

    def test_degenerate_inputs_raise(self):
        box = trimesh.creation.box()
        flat = (torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), torch.tensor([[0, 1, 2]]))
        with pytest.raises(ValueError, match="zero surface area"):
            symmetric_rms(flat, box)
        with pytest.raises(ValueError, match="no faces"):
            rms_distance(box, (torch.zeros(0, 3), torch.zeros(0, 3, dtype=torch.long)), 0.1)


# --------------------------------------------------------------------------- depth offset


class TestDepthOffset:
    def test_recovers_known_shift(self, shared_data):
        gt = load_cad(shared_data, "chair05")  # not symmetric in depth: legs, back
        recon = gt.copy()
        recon.apply_translation([0.0, 0.0, 0.123])
        r = best_depth_offset(recon, gt, step=0.01 * gt.scale)
        assert r.offset == pytest.approx(-0.123, abs=1e-3 * gt.scale)
        assert r.error < 1e-6
        offset, error = r
        assert offset == r.offset and error == r.error

    def test_minimum_vs_dense_scan(self):
        # an asymmetric pair whose mean-depth guess is wrong: a partial, shifted copy
        gt = trimesh.creation.capsule(1.0, 0.5, count=[24, 24])
        gt.apply_transform(trimesh.transformations.rotation_matrix(0.6, [1, 0, 0]))
        recon = gt.copy()
        keep = recon.triangles_center[:, 2] < 0.2
        recon = trimesh.Trimesh(recon.vertices, recon.faces[keep])
        recon.apply_translation([0, 0, 0.4])
        gtm, rm = EvaluationMesh(gt), EvaluationMesh(recon)
        step = 0.02 * gtm.diag
        r = best_depth_offset(rm, gtm, step=step, search_step=step, xatol=1e-3)
        zs = r.initial_offset + np.linspace(-0.3, 0.3, 41)
        scan = [max(rms_distance(rm, gtm, r.step, shift=[0, 0, z]), rms_distance(gtm, rm, r.step, shift=[0, 0, -z]))
                for z in zs]
        assert abs(r.initial_offset - zs[int(np.argmin(scan))]) > 0.02  # the start is not the answer
        assert r.error <= min(scan) + 1e-3 * gtm.diag
        assert r.evaluations <= 15

    def test_object_frame_with_view_direction(self):
        # the same evaluation in the camera frame (axis z) and in the object frame (axis R[2])
        from carvi_torch.cameras import ScaledOrthographic, random_rotations

        gt = trimesh.creation.capsule(1.0, 0.4, count=[16, 16])
        gt.apply_transform(trimesh.transformations.rotation_matrix(0.5, [0, 1, 0]))
        recon = trimesh.creation.box(extents=[0.8, 0.8, 1.6])
        R = random_rotations(1, torch.Generator().manual_seed(3), dtype=torch.float64)
        f64 = dict(dtype=torch.float64)
        cam = ScaledOrthographic(R, torch.tensor([40.0], **f64), torch.tensor([[64.0, 64.0]], **f64))

        def to_cam(m):
            return cam.to_camera_frame(torch.tensor(m.vertices))[0], torch.tensor(m.faces)

        diag = float(np.linalg.norm(gt.extents))
        shift = torch.tensor([0.0, 0.0, 17.0], dtype=torch.float64)
        rv, rf = to_cam(recon)
        in_cam = evaluate_reconstruction((rv + shift, rf), to_cam(gt), diag=40.0 * diag, step=0.01 * 40 * diag)
        in_obj = evaluate_reconstruction(recon, gt, diag=diag, axis=R[0, 2], step=0.01 * diag)
        assert in_cam["diag"] == pytest.approx(40 * diag) and in_obj["diag"] == pytest.approx(diag)
        assert in_cam["error_percent"] == pytest.approx(in_obj["error_percent"], rel=0.02)
        assert in_cam["offset"] == pytest.approx(40 * in_obj["offset"] - 17.0, abs=0.01 * 40 * diag)

    def test_errors(self):
        box = trimesh.creation.box()
        for bad in (3, [0.0, 0.0, 0.0], [1.0, 2.0]):
            with pytest.raises(ValueError, match="axis"):
                best_depth_offset(box, box, axis=bad)
        with pytest.raises(ValueError, match="diag"):
            evaluate_reconstruction(box, box, diag=-1.0)
        with pytest.raises(ValueError, match="xatol"):
            best_depth_offset(box, box, xatol=0)


# --------------------------------------------------------------------------- evaluation


class TestEvaluateReconstruction:
    def test_result_fields(self):
        gt = trimesh.creation.icosphere(3, radius=10.0)
        recon = trimesh.creation.icosphere(3, radius=9.0)
        recon.apply_translation([0, 0, 5.0])
        r = evaluate_reconstruction(recon, gt)
        assert set(r) == {"error_percent", "offset", "rms_ab", "rms_ba", "diag", "step", "evaluations", "reason"}
        assert r["reason"] is None and r["diag"] == pytest.approx(20 * math.sqrt(3), rel=1e-3)
        assert r["offset"] == pytest.approx(-5.0, abs=0.05)
        assert r["error_percent"] == pytest.approx(100 * max(r["rms_ab"], r["rms_ba"]) / r["diag"])
        assert r["rms_ab"] == pytest.approx(1.0, abs=0.05) and r["rms_ba"] == pytest.approx(1.0, abs=0.05)
        fixed = evaluate_reconstruction(recon, gt, optimise_offset=False)
        assert fixed["offset"] == 0.0 and fixed["error_percent"] > r["error_percent"]

    @pytest.mark.parametrize("recon, reason", [
        ((np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)), "no faces"),
        ((np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2]]), np.array([[0, 1, 2]])), "zero surface area"),
        ((np.array([[0.0, 0, 0], [1, 0, 0], [np.nan, 1, 0]]), np.array([[0, 1, 2]])), "non-finite"),
        ((np.zeros((3, 2)), np.array([[0, 1, 2]])), "invalid reconstruction"),
    ])
    def test_degenerate_recon_gives_nan_and_reason(self, recon, reason):
        r = evaluate_reconstruction(recon, trimesh.creation.box())
        assert math.isnan(r["error_percent"]) and reason in r["reason"]

    def test_invalid_gt_raises(self):
        with pytest.raises(ValueError, match="gt has no faces"):
            evaluate_reconstruction(trimesh.creation.box(), (np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)))

    def test_prepared_gt_is_reused(self):
        gt = EvaluationMesh(trimesh.creation.icosphere(3))
        r1 = evaluate_reconstruction(trimesh.creation.icosphere(2, radius=0.9), gt)
        index = gt.index
        r2 = evaluate_reconstruction(trimesh.creation.icosphere(2, radius=0.9), gt)
        assert gt.index is index and r1["error_percent"] == r2["error_percent"]


# --------------------------------------------------------------------------- occupancy


class TestOccupancy:
    def test_occupancy_iou(self):
        a = torch.zeros(2, 3, 3, 3, dtype=torch.bool)
        b = torch.zeros(2, 3, 3, 3, dtype=torch.bool)
        a[0, :2], b[0, 1:] = True, True
        iou = occupancy_iou(a, b)
        assert iou.shape == (2,) and float(iou[0]) == pytest.approx(1 / 3) and math.isnan(float(iou[1]))
        with pytest.raises(ValueError, match="3 dimensions"):
            occupancy_iou(torch.ones(3, 3, dtype=torch.bool), torch.ones(3, 3, dtype=torch.bool))

    def test_voxelize_sphere_volume_and_convention(self):
        sphere = trimesh.creation.icosphere(4, radius=1.0)
        V, F = mesh_tensors(sphere)
        pitch = 0.05
        origin = torch.tensor([-1.2, -1.2, -1.0])
        occ = voxelize_solid(V, F, pitch, origin, (41, 49, 49))
        assert occ.shape == (41, 49, 49) and occ.dtype == torch.bool
        # shell voxels count as occupied: the volume grows by up to area * pitch
        assert sphere.volume < float(occ.sum()) * pitch ** 3 < sphere.volume + sphere.area * pitch
        d, h, w = (occ.nonzero().double().mean(0))  # centroid back in (x, y, z) = origin + pitch (w, h, d)
        assert [float(origin[0] + pitch * w), float(origin[1] + pitch * h), float(origin[2] + pitch * d)] == \
            pytest.approx([0.0, 0.0, 0.0], abs=0.02)

    def test_voxel_iou_boxes(self):
        a = box_mesh([0, 0, 0], [1.0, 1.0, 1.0])
        b = box_mesh([0.5, 0, 0], [1.5, 1.0, 1.0])
        assert voxel_iou(a, b, 0.02) == pytest.approx(1 / 3, abs=0.03)
        assert voxel_iou(a, a, 0.05) == pytest.approx(1.0)
        assert voxel_iou(a, box_mesh([3, 3, 3], [4, 4, 4]), 0.1) == 0.0
        # shells: the overlap is four 0.5 x 1 faces (area 2) out of 6 + 6 - 2
        assert voxel_iou(a, b, 0.02, fill=False) == pytest.approx(0.2, abs=0.03)
