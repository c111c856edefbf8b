"""Tests of carvi_torch.synthetic.render: rasteriser, z-buffer, keypoint visibility, cameras, views."""
from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch

from carvi_torch.cameras import (ScaledOrthographic, azimuth_elevation_roll_from_rotation,
                                 rotation_from_azimuth_elevation_roll)
from carvi_torch.synthetic.meshes import load_cad_npz
from carvi_torch.synthetic.render import (
    VISIBILITY_EPS_REL,
    keypoint_visibility,
    parse_image_size,
    perturb_boundary,
    rasterize_depth,
    rasterize_triangles,
    render_dataset,
    render_view,
    sample_cameras,
    seed_generator,
)

# --------------------------------------------------------------------------- helpers


def brute_force_raster(points: np.ndarray, faces: np.ndarray, h: int, w: int) -> np.ndarray:
    """Per-pixel loop with exact rational arithmetic: centre inside or on a non-degenerate triangle."""
    out = np.zeros((h, w), dtype=bool)
    tris = []
    for f in faces:
        a, b, c = ([Fraction(float(v)) for v in points[i]] for i in f)
        area = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])
        if area != 0:
            tris.append((a, b, c, 1 if area > 0 else -1))
    for i in range(h):
        for j in range(w):
            p = (Fraction(j), Fraction(i))
            for a, b, c, sgn in tris:
                e = [sgn * ((v[0] - u[0]) * (p[1] - u[1]) - (v[1] - u[1]) * (p[0] - u[0]))
                     for u, v in ((a, b), (b, c), (c, a))]
                if min(e) >= 0:
                    out[i, j] = True
                    break
    return out


def cube_mesh(half: float = 0.5):
    import trimesh

    m = trimesh.creation.box(extents=(2 * half,) * 3)
    return torch.tensor(m.vertices, dtype=torch.float32), torch.tensor(m.faces, dtype=torch.long)


def camera(az_deg, el_deg, roll_deg=0.0, s=100.0, t=(160.0, 120.0)) -> ScaledOrthographic:
    R = rotation_from_azimuth_elevation_roll(torch.tensor(math.radians(az_deg)), torch.tensor(math.radians(el_deg)),
                                             torch.tensor(math.radians(roll_deg)))
    return ScaledOrthographic(R[None].float(), torch.tensor([float(s)]), torch.tensor([list(t)]))


# --------------------------------------------------------------------------- rasterize_triangles


def test_rasterize_single_triangle_matches_brute_force(generator):
    for _ in range(20):
        pts = torch.rand(3, 2, generator=generator) * torch.tensor([14.0, 11.0]) - 1.0
        faces = torch.tensor([[0, 1, 2]])
        got = rasterize_triangles(pts, faces, 10, 12).numpy()
        ref = brute_force_raster(pts.numpy(), faces.numpy(), 10, 12)
        np.testing.assert_array_equal(got, ref)


def test_rasterize_pixels_on_edges_and_vertices_are_inside():
    # right triangle with integer vertices: the hypotenuse x + y = 4 passes through pixel centres
    pts = torch.tensor([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]])
    got = rasterize_triangles(pts, torch.tensor([[0, 1, 2]]), 6, 6)
    ii, jj = torch.meshgrid(torch.arange(6), torch.arange(6), indexing="ij")
    np.testing.assert_array_equal(got.numpy(), (ii + jj <= 4).numpy())
    # clockwise order gives the same pixels
    got_cw = rasterize_triangles(pts, torch.tensor([[0, 2, 1]]), 6, 6)
    assert torch.equal(got, got_cw)


def test_rasterize_shared_edge_and_degenerate_ignored():
    # a square split into two triangles covers its closed pixel set exactly once
    pts = torch.tensor([[1.0, 1.0], [5.0, 1.0], [5.0, 4.0], [1.0, 4.0], [7.0, 7.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3], [4, 4, 4], [0, 1, 1]])  # two degenerate
    got = rasterize_triangles(pts, faces, 8, 8)
    ref = torch.zeros(8, 8, dtype=torch.bool)
    ref[1:5, 1:6] = True
    assert torch.equal(got, ref)
    # a line (zero area) alone draws nothing
    line = torch.tensor([[0.0, 0.0], [3.0, 3.0], [6.0, 6.0]])
    assert not rasterize_triangles(line, torch.tensor([[0, 1, 2]]), 8, 8).any()


def test_rasterize_random_soup_matches_brute_force_with_chunks(generator):
    pts = torch.rand(30, 2, generator=generator) * torch.tensor([20.0, 16.0]) - 2.0
    faces = torch.randint(0, 30, (25, 3), generator=generator)
    ref = brute_force_raster(pts.numpy(), faces.numpy(), 14, 18)
    for chunk in (1, 7, 1 << 22):
        got = rasterize_triangles(pts, faces, 14, 18, chunk=chunk).numpy()
        np.testing.assert_array_equal(got, ref)


def test_rasterize_clipping_and_offscreen():
    pts = torch.tensor([[-50.0, -50.0], [100.0, -50.0], [-50.0, 100.0], [200.0, 200.0], [210.0, 200.0], [200.0, 210.0]])
    got = rasterize_triangles(pts, torch.tensor([[0, 1, 2], [3, 4, 5]]), 5, 7)
    assert got.all()  # the big triangle covers the whole image; the far one nothing


def test_rasterize_errors():
    pts = torch.zeros(3, 2)
    with pytest.raises(ValueError, match="points2d"):
        rasterize_triangles(torch.zeros(3, 3), torch.tensor([[0, 1, 2]]), 4, 4)
    with pytest.raises(ValueError, match="faces"):
        rasterize_triangles(pts, torch.tensor([[0, 1, 3]]), 4, 4)
    with pytest.raises(ValueError, match="faces"):
        rasterize_triangles(pts, torch.tensor([[0.0, 1.0, 2.0]]), 4, 4)
    with pytest.raises(ValueError, match="height"):
        rasterize_triangles(pts, torch.tensor([[0, 1, 2]]), 0, 4)


def test_rasterize_depth_plane_and_min():
    # two overlapping squares at constant depths 5 and 2, plus a sloped triangle
    pts = torch.tensor([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [0.0, 6.0]])
    faces = torch.tensor([[0, 1, 2], [0, 2, 3]])
    pts2 = torch.cat([pts, pts + 3.0])
    faces2 = torch.cat([faces, faces + 4])
    depth = torch.tensor([5.0] * 4 + [2.0] * 4)
    z = rasterize_depth(pts2, depth, faces2, 12, 12)
    mask = rasterize_triangles(pts2, faces2, 12, 12)
    assert torch.equal(torch.isfinite(z), mask)
    assert z[1, 1] == 5.0 and z[4, 4] == 2.0 and z[8, 8] == 2.0
    # an affine depth z = x + 2y is reproduced at every covered pixel centre
    tri = torch.tensor([[0.5, 0.2], [9.3, 1.1], [2.2, 8.7]])
    d = tri[:, 0] + 2 * tri[:, 1]
    z = rasterize_depth(tri, d, torch.tensor([[0, 1, 2]]), 10, 10)
    ii, jj = torch.meshgrid(torch.arange(10.0), torch.arange(10.0), indexing="ij")
    cov = torch.isfinite(z)
    assert cov.sum() > 20
    torch.testing.assert_close(z[cov], (jj + 2 * ii)[cov], atol=1e-4, rtol=0)


@pytest.mark.shared
def test_silhouette_area_matches_shapely_on_cad_models(shared_data):
    """Pixel count vs the exact area of the union of projected triangles (shapely), within 1%."""
    shapely = pytest.importorskip("shapely")
    names = ["chair01", "sofa03", "tvmonitor03", "diningtable05", "bottle01", "car04", "bus02"]
    errors = []
    for k, name in enumerate(names):
        m = load_cad_npz(shared_data / "pascal3d_cad" / f"{name}.npz")
        cams = sample_cameras(2, seed_generator(11, name), (320, 240), radius=m.bounding_radius, fill=(0.8, 0.85))
        for c in range(2):
            uv = cams[c].project(m.vertices)[0]
            mask = rasterize_triangles(uv, m.faces, 240, 320)
            tri = uv.double().numpy()[m.faces.numpy()]
            polys = shapely.polygons(np.concatenate([tri, tri[:, :1]], axis=1))
            polys = polys[shapely.area(polys) > 0]
            area = shapely.area(shapely.union_all(shapely.make_valid(polys)))
            errors.append(abs(int(mask.sum()) - area) / area)
    print("relative area errors", [round(e, 5) for e in errors])
    assert max(errors) < 0.01, errors


# --------------------------------------------------------------------------- keypoint_visibility


def test_visibility_cube_faces(generator):
    V, F = cube_mesh(0.5)
    normals = torch.tensor([[0, 0, 1.0], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]])
    kp = 0.5 * normals + torch.tensor([0.13, -0.07, 0.21]) * (1 - normals.abs())  # off-centre points of each face
    # frontal camera: azimuth 0, elevation 10 looks along about +y and down: -y face and top seen
    vis = keypoint_visibility(V, F, kp, camera(0, 10).R[0])
    assert vis.tolist() == [True, False, False, False, False, True]
    # in general: a face point is visible iff the face's normal points towards the camera
    for _ in range(20):
        u = torch.rand(2, generator=generator)
        az, el = (u * torch.tensor([360.0, 160.0]) - torch.tensor([0.0, 80.0])).tolist()
        R = camera(az, el).R[0]
        expected = (normals @ -R[2]) > 0
        assert torch.equal(keypoint_visibility(V, F, kp, R), expected)
    # a point 0.1 inside the top face (eps = 2% of the diagonal = 0.035) is hidden; 0.01 inside is not
    deep = torch.tensor([[0.1, 0.1, 0.4], [0.1, 0.1, 0.49]])
    assert keypoint_visibility(V, F, deep, camera(0, 90).R[0]).tolist() == [False, True]
    # an explicit eps overrides the relative one
    assert keypoint_visibility(V, F, deep, camera(0, 90).R[0], eps=0.2).tolist() == [True, True]


def test_visibility_corners_by_brute_force(generator):
    """Cube corners: visible iff the corner lies on a face whose normal points to the camera."""
    V, F = cube_mesh(0.5)
    corners = torch.tensor([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    for _ in range(20):
        R = torch.linalg.qr(torch.randn(3, 3, generator=generator))[0]
        R = R * torch.sign(torch.det(R))
        toward = -R[2]  # direction to the camera in the object frame
        vis = keypoint_visibility(V, F, corners, R)
        # a corner c is hidden iff the ray c + t*toward enters the cube: -sign(c_i) * toward_i > 0 for all i
        hidden = ((-torch.sign(corners) * toward) > 1e-6).all(dim=1)
        assert torch.equal(vis, ~hidden)


def test_visibility_empty_and_errors():
    V, F = cube_mesh()
    assert keypoint_visibility(V, F, torch.zeros(0, 3), torch.eye(3)).shape == (0,)
    assert keypoint_visibility(V, F[:0], torch.zeros(2, 3), torch.eye(3)).all()
    with pytest.raises(ValueError, match="keypoints"):
        keypoint_visibility(V, F, torch.zeros(2, 2), torch.eye(3))
    with pytest.raises(ValueError, match="R"):
        keypoint_visibility(V, F, torch.zeros(2, 3), torch.eye(2))
    with pytest.raises(ValueError, match="eps"):
        keypoint_visibility(V, F, torch.zeros(2, 3), torch.eye(3), eps=-1.0)


@pytest.mark.shared
def test_visibility_agrees_with_trimesh_rays(shared_data):
    """Every keypoint of a sample of renders: same answer as trimesh's ray-triangle intersector."""
    import trimesh
    from trimesh.ray.ray_triangle import RayMeshIntersector

    names = ["aeroplane03", "car03", "chair01", "bottle02", "bus02", "motorbike03", "sofa02", "bicycle04"]
    checked = 0
    for name in names:
        m = load_cad_npz(shared_data / "pascal3d_cad" / f"{name}.npz")
        tm = trimesh.Trimesh(m.vertices.double().numpy(), m.faces.numpy(), process=False)
        eps = VISIBILITY_EPS_REL * float(np.linalg.norm(tm.bounds[1] - tm.bounds[0]))
        intersector = RayMeshIntersector(tm)
        cams = sample_cameras(4, seed_generator(5, name), radius=m.bounding_radius)
        for c in range(4):
            R = cams.R[c]
            vis = keypoint_visibility(m.vertices, m.faces, m.keypoints, R)
            origins = m.keypoints.double().numpy()
            dirs = np.repeat(-R[2].double().numpy()[None], len(origins), axis=0)
            loc, ray, _tri = intersector.intersects_location(origins, dirs, multiple_hits=True)
            dist = ((loc - origins[ray]) * dirs[ray]).sum(axis=1)
            ref = np.ones(len(origins), dtype=bool)
            ref[ray[dist > eps]] = False
            np.testing.assert_array_equal(vis.numpy(), ref, err_msg=f"{name} camera {c}")
            checked += len(origins)
    assert checked > 200


# --------------------------------------------------------------------------- sample_cameras


def test_sample_cameras_distribution():
    n = 4000
    cams = sample_cameras(n, torch.Generator().manual_seed(3), (320, 240), radius=0.5)
    assert cams.R.shape == (n, 3, 3) and cams.s.shape == (n,) and cams.t.shape == (n, 2)
    torch.testing.assert_close(cams.R @ cams.R.transpose(1, 2), torch.eye(3).expand(n, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.det(cams.R), torch.ones(n), atol=1e-5, rtol=0)
    az, el, roll = (torch.rad2deg(a) for a in azimuth_elevation_roll_from_rotation(cams.R.double()))
    from scipy import stats

    assert stats.kstest(torch.remainder(az, 360).numpy() / 360.0, "uniform").pvalue > 1e-3
    frac_0_40 = ((el >= 0) & (el <= 40)).double().mean().item()
    assert frac_0_40 > 0.75
    assert 0.05 < (el < 0).double().mean().item() < 0.3  # a few below the horizon
    assert el.min() >= -20 - 1e-6 and el.max() <= 75 + 1e-6
    assert 2.5 < roll.std().item() < 3.5 and roll.abs().max() <= 9.0 + 1e-6
    fill = 2 * cams.s * 0.5 / 240
    assert fill.min() >= 0.4 - 1e-6 and fill.max() <= 0.85 + 1e-6
    assert fill.min() < 0.45 and fill.max() > 0.8
    # the bounding disc stays inside the image
    rho = cams.s * 0.5
    assert (cams.t[:, 0] - rho >= -1e-4).all() and (cams.t[:, 0] + rho <= 319 + 1e-4).all()
    assert (cams.t[:, 1] - rho >= -1e-4).all() and (cams.t[:, 1] + rho <= 239 + 1e-4).all()


def test_sample_cameras_determinism_and_square_canvas():
    a = sample_cameras(5, torch.Generator().manual_seed(1), 128)
    b = sample_cameras(5, torch.Generator().manual_seed(1), (128, 128))
    c = sample_cameras(5, torch.Generator().manual_seed(2), 128)
    assert torch.equal(a.R, b.R) and torch.equal(a.t, b.t)
    assert not torch.equal(a.R, c.R)
    assert parse_image_size(64) == (64, 64)
    with pytest.raises(ValueError, match="fill"):
        sample_cameras(2, None, fill=(0.5, 1.5))
    with pytest.raises(ValueError, match="radius"):
        sample_cameras(2, None, radius=0.0)
    with pytest.raises(ValueError, match="image_size"):
        sample_cameras(2, None, image_size=(1, 2, 3))


@pytest.mark.shared
def test_sampled_views_keep_cad_models_inside(shared_data):
    for name in ["aeroplane01", "train01", "diningtable02"]:
        m = load_cad_npz(shared_data / "pascal3d_cad" / f"{name}.npz")
        cams = sample_cameras(50, seed_generator(0, name), (320, 240), radius=m.bounding_radius)
        uv = cams.project(m.vertices)
        assert uv[..., 0].min() >= 0 and uv[..., 0].max() <= 319
        assert uv[..., 1].min() >= 0 and uv[..., 1].max() <= 239


# --------------------------------------------------------------------------- render_view


def test_render_view_cube_front():
    V, F = cube_mesh(0.5)
    kp = torch.tensor([[0, -0.5, 0], [0, 0.5, 0], [0.5, -0.5, 0.5]])
    out = render_view(V, F, kp, torch.tensor([True, True, False]), camera(0, 0, s=40, t=(50, 30)), (100, 60))
    assert out["mask"].shape == (60, 100) and out["mask"].dtype == torch.bool
    # the front face spans x in [30, 70], y in [10, 50] (pixel centres, edges included)
    ref = torch.zeros(60, 100, dtype=torch.bool)
    ref[10:51, 30:71] = True
    assert torch.equal(out["mask"], ref)
    torch.testing.assert_close(out["keypoints"], torch.tensor([[50.0, 30.0], [50.0, 30.0], [70.0, 10.0]]))
    assert out["visible"].tolist() == [True, False, False]  # back face hidden; third not on the model


def test_render_view_keypoint_noise_and_outside_image():
    V, F = cube_mesh(0.5)
    kp = torch.tensor([[0, -0.5, 0]]).repeat(2000, 1)
    cam = camera(0, 0, s=40, t=(50, 30))
    out = render_view(V, F, kp, None, cam, (100, 60), generator=torch.Generator().manual_seed(0), keypoint_noise=2.0)
    d = out["keypoints"] - torch.tensor([50.0, 30.0])
    assert out["visible"].all()
    assert abs(d.std().item() - 2.0) < 0.1 and abs(d.mean().item()) < 0.1
    # a keypoint projecting outside the image is not visible
    far = render_view(V, F, torch.tensor([[0, -0.5, 0]]), None, camera(0, 0, s=40, t=(150, 30)), (100, 60))
    assert not far["visible"].any()
    with pytest.raises(ValueError, match="single camera"):
        render_view(V, F, kp[:1], None, ScaledOrthographic.cat([cam, cam]), (100, 60))
    with pytest.raises(ValueError, match="noise"):
        render_view(V, F, kp[:1], None, cam, (100, 60), keypoint_noise=-1.0)


def test_perturb_boundary_moves_boundary_by_about_sigma():
    ii, jj = torch.meshgrid(torch.arange(200.0), torch.arange(200.0), indexing="ij")
    disc = (ii - 100) ** 2 + (jj - 100) ** 2 <= 60**2
    assert torch.equal(perturb_boundary(disc, 0.0), disc)
    noisy = perturb_boundary(disc, 2.0, torch.Generator().manual_seed(0))
    changed = (noisy ^ disc).sum().item()
    # the symmetric difference per unit of boundary length is E|delta| = sigma * sqrt(2 / pi) for a normal delta
    per_length = changed / (2 * math.pi * 60)
    assert 0.8 < per_length < 2.5, per_length
    # far from the boundary nothing changes
    assert noisy[100, 100] and not noisy[5, 5]
    again = perturb_boundary(disc, 2.0, torch.Generator().manual_seed(0))
    assert torch.equal(noisy, again)
    with pytest.raises(ValueError, match="sigma"):
        perturb_boundary(disc, -1.0)


# --------------------------------------------------------------------------- CUDA


@pytest.mark.cuda
def test_render_on_cuda_matches_cpu(generator):
    V, F = cube_mesh(0.5)
    V = V + 0.01 * torch.randn(V.shape, generator=generator)
    kp = torch.tensor([[0, -0.5, 0], [0, 0.5, 0], [0.5, 0.1, 0.2]])
    cams = sample_cameras(4, generator, (64, 48), radius=0.9)
    for c in range(4):
        cpu = render_view(V, F, kp, None, cams[c], (64, 48))
        gpu = render_view(V.cuda(), F.cuda(), kp.cuda(), None, cams[c], (64, 48))
        assert gpu["mask"].is_cuda
        assert torch.equal(cpu["mask"], gpu["mask"].cpu())
        assert torch.equal(cpu["visible"], gpu["visible"].cpu())
        torch.testing.assert_close(cpu["keypoints"], gpu["keypoints"].cpu())
        uv = cams[c].project(V)[0]
        z = cams[c].depth(V)[0]
        torch.testing.assert_close(rasterize_depth(uv.cuda(), z.cuda(), F.cuda(), 48, 64).cpu(),
                                   rasterize_depth(uv, z, F, 48, 64))
    noisy = perturb_boundary(cpu["mask"].cuda(), 1.5, torch.Generator().manual_seed(0))
    assert noisy.is_cuda and noisy.shape == (48, 64)


# --------------------------------------------------------------------------- render_dataset: degenerate models


def _box_model(name: str = "box1", scale: float = 1.0):
    from carvi_torch.synthetic.meshes import Model

    V, F = cube_mesh(0.5)
    kp = torch.tensor([[-0.5, -0.5, 0.5], [0.5, -0.5, 0.5], [0.0, 0.0, 0.5]])
    return Model(name, "thing", V.double() * scale, F, ["left_front", "right_front", "top"], kp.double() * scale)


def test_render_dataset_masks_are_the_same_in_any_unit(tmp_path):
    """The cameras frame the model by its own size: a box 1e-12 or 1e12 wide renders as the unit box does (no
    absolute size floor, which made a 1e-12 box an empty mask with visible keypoints)."""
    import json

    anns = {}
    for scale in (1.0, 1e-12, 1e12):
        render_dataset([_box_model(scale=scale)], tmp_path / str(scale), views=3, seed=1, image_size=48,
                       progress=False)
        anns[scale] = json.loads((tmp_path / str(scale) / "annotations.json").read_text())["annotations"]
    for scale in (1e-12, 1e12):
        assert [a["area"] for a in anns[scale]] == [a["area"] for a in anns[1.0]], scale
        for a, b in zip(anns[scale], anns[1.0]):
            assert a["area"] > 0 and a["segmentation"] == b["segmentation"]
            np.testing.assert_allclose(a["keypoints"], b["keypoints"], atol=1e-3)


def test_render_dataset_leaves_out_views_with_an_empty_mask(tmp_path):
    """A flat model seen edge-on (a horizontal square, cameras at elevation 0) covers no pixel: no image and no
    annotation for those views (they had area 0 and visible keypoints), counted in the summary."""
    import json

    from carvi_torch.synthetic.meshes import Model

    flat = Model("flat1", "thing", [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]],
                 ["a", "b"], [[-1, -1, 0], [1, 1, 0]])
    summary = render_dataset([_box_model(), flat], tmp_path / "r", views=3, seed=0, image_size=48, progress=False,
                             camera_options={"elevation_deg": (0.0, 0.0), "roll_sd_deg": 0.0})
    data = json.loads((tmp_path / "r" / "annotations.json").read_text())
    gt = json.loads((tmp_path / "r" / "gt.json").read_text())
    assert summary["images"] == 3 and summary["empty_views"] == {"flat1": 3}
    assert [a["id"] for a in data["annotations"]] == [i["id"] for i in data["images"]] == [1, 2, 3]
    assert all(a["area"] > 0 for a in data["annotations"])
    assert {g["model"] for g in gt["annotations"].values()} == {"box1"} and "flat1" in gt["models"]


def test_render_dataset_refuses_a_model_with_nothing_to_render_before_writing(tmp_path):
    from carvi_torch.synthetic.meshes import Model

    point = Model("point1", "thing", torch.zeros(4, 3), [[0, 1, 2]], ["a"], [[0.0, 0, 0]], source="point1.ply")
    with pytest.raises(ValueError, match="point1.ply: nothing to render"):
        render_dataset([_box_model(), point], tmp_path / "r", views=1, image_size=32, progress=False)
    assert not (tmp_path / "r").exists()
