"""Tests of carvi_torch.carve: imprinted visual hulls, batched and one at a time.

References: brute-force per-voxel loops in float64 (tiny grids), analytic silhouettes
and visual hulls of ellipsoids and boxes (shapely for polygons), the true solids, and
rendered real CAD models (PASCAL3D+, ``shared_data``).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import shapely
import torch
from skimage.draw import polygon as draw_polygon

from carvi_torch.cameras import ScaledOrthographic, random_rotations, rotation_from_azimuth_elevation_roll
from carvi_torch.carve import (
    BIG,
    PAD,
    ProposalGrids,
    VoxelGrid,
    carve_proposals,
    carve_proposals_loop,
    extend_maps,
    imprinted_visual_hull,
    mask_geometry,
    prepare_maps,
)
from carvi_torch.sdf import signed_distance
from conftest import requires_cuda


# --------------------------------------------------------------------------- helpers


def cameras_from_angles(angles_deg, s, t) -> ScaledOrthographic:
    """Cameras from (azimuth, elevation, roll) in degrees, one scale and image centre each."""
    a = torch.tensor(angles_deg, dtype=torch.float64) * math.pi / 180
    R = rotation_from_azimuth_elevation_roll(a[:, 0], a[:, 1], a[:, 2]).float()
    n = len(angles_deg)
    return ScaledOrthographic(R, torch.as_tensor(s, dtype=torch.float32).expand(n).clone(),
                              torch.as_tensor(t, dtype=torch.float32).expand(n, 2).clone())


def pixel_centres(size: int) -> torch.Tensor:
    """(size, size, 2) float64 (x, y) pixel centres."""
    ys, xs = torch.meshgrid(torch.arange(size, dtype=torch.float64), torch.arange(size, dtype=torch.float64),
                            indexing="ij")
    return torch.stack([xs, ys], dim=-1)


def ellipse_inside(cams: ScaledOrthographic, sigma: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Is image point u (V, ..., 2) inside the silhouette of the ellipsoid X^T sigma^-1 X <= 1 in each view."""
    M = cams.M.double()
    C = M @ sigma.double() @ M.transpose(1, 2)  # (V, 2, 2) projected covariance
    d = u.double() - cams.t.double().view(-1, *([1] * (u.dim() - 2)), 2)
    Ci = torch.linalg.inv(C).view(-1, *([1] * (u.dim() - 2)), 2, 2)
    q = (d[..., None, :] @ Ci @ d[..., :, None])[..., 0, 0]
    return q <= 1.0


def ellipsoid_masks(cams, sigma, size) -> torch.Tensor:
    u = pixel_centres(size)[None].expand(len(cams), size, size, 2)
    return ellipse_inside(cams, sigma, u)


def near_boundary(inside_fn, u: torch.Tensor, radius: float, n_dir: int = 16) -> torch.Tensor:
    """True where the disk of ``radius`` around u (..., 2) holds points of both labels of inside_fn."""
    ang = torch.arange(n_dir, dtype=torch.float64) * 2 * math.pi / n_dir
    ring = torch.stack([torch.cos(ang), torch.sin(ang)], -1) * radius
    here = inside_fn(u)
    out = torch.zeros_like(here)
    for r in (0.5, 1.0):
        for off in ring:
            out |= inside_fn(u + r * off) != here
    return out


def voxel_centres(grid_T: torch.Tensor, n: int) -> torch.Tensor:
    """(n, n, n, 3) float64 camera-frame centres of a grid."""
    d, h, w = torch.meshgrid(*(torch.arange(n, dtype=torch.float64),) * 3, indexing="ij")
    idx = torch.stack([d, h, w, torch.ones_like(d)], -1)
    return (idx @ grid_T.double().T)[..., :3]


def to_views(cams: ScaledOrthographic, reference: int, p: torch.Tensor) -> torch.Tensor:
    """Camera-frame points p (..., 3) of the reference to pixels of every view: (V, ..., 2)."""
    c64 = cams.to(dtype=torch.float64)
    X = c64[reference].from_camera_frame(p.reshape(1, -1, 3))[0]
    return c64.project(X).reshape(len(cams), *p.shape[:-1], 2)


def blob_masks(n: int, size: int, gen: torch.Generator) -> torch.Tensor:
    """Random unions of ellipses, some touching the canvas border."""
    u = pixel_centres(size)
    masks = torch.zeros(n, size, size, dtype=torch.bool)
    for i in range(n):
        for _ in range(3):
            c = torch.rand(2, generator=gen, dtype=torch.float64) * size * 0.6 + size * 0.2
            ax = torch.rand(2, generator=gen, dtype=torch.float64) * size * 0.25 + 2
            th = float(torch.rand(1, generator=gen)) * math.pi
            rot = torch.tensor([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]], dtype=torch.float64)
            d = (u - c) @ rot
            masks[i] |= ((d / ax) ** 2).sum(-1) <= 1
    masks[1, :, : size // 3] = True  # touches the left border
    return masks


def random_cameras(n: int, size: int, gen: torch.Generator) -> ScaledOrthographic:
    R = random_rotations(n, gen)
    s = 0.5 * size * (0.7 + 0.6 * torch.rand(n, generator=gen))
    t = size / 2 + size * 0.1 * torch.randn(n, 2, generator=gen)
    return ScaledOrthographic(R, s, t)


# --------------------------------------------------------------------------- brute force


def brute_force(sdf: torch.Tensor, cams: ScaledOrthographic, T: torch.Tensor, reference: int, views: list[int],
                n: int, imprint: bool = True, nearest: bool = False, nudge: float = 0.0):
    """Per-voxel float64 loop: C = max_m (s_r / s_m) bilinear(extended sdf_m, u_m) (``nearest``: the
    extended map at the nearest pixel of ``u_m + nudge``); labels; imprinting."""
    S = sdf.double().clamp(-BIG, BIG).numpy()
    _, H, W = S.shape
    c64 = cams.to(dtype=torch.float64)

    def value(m, qx, qy):  # extended map at an integer pixel
        cx, cy = min(max(qx, 0), W - 1), min(max(qy, 0), H - 1)
        return S[m, cy, cx] + math.hypot(qx - cx, qy - cy)

    def bilinear(m, x, y):
        x = min(max(x, -PAD), W - 1 + PAD)
        y = min(max(y, -PAD), H - 1 + PAD)
        if nearest:
            return value(m, round(x + nudge), round(y + nudge))
        x0, y0 = math.floor(x), math.floor(y)
        fx, fy = x - x0, y - y0
        return ((1 - fx) * (1 - fy) * value(m, x0, y0) + fx * (1 - fy) * value(m, x0 + 1, y0)
                + (1 - fx) * fy * value(m, x0, y0 + 1) + fx * fy * value(m, x0 + 1, y0 + 1))

    Td = T.double()
    sr = float(c64.s[reference])
    C = np.zeros((n, n, n))
    col = np.zeros((n, n))
    for d in range(n):
        for h in range(n):
            for w in range(n):
                p = Td @ torch.tensor([d, h, w, 1.0], dtype=torch.float64)
                X = c64[reference].from_camera_frame(p[None, None, :3])
                best = -math.inf
                for m in [reference] + views:
                    u = c64[m].project(X)[0, 0]
                    best = max(best, bilinear(m, float(u[0]), float(u[1])) * sr / float(c64.s[m]))
                C[d, h, w] = best
                if d == 0:
                    col[h, w] = bilinear(reference, float(p[0]), float(p[1]))
    occ = C < 0
    if imprint:
        for h in range(n):
            for w in range(n):
                if col[h, w] < 0 and not occ[:, h, w].any():
                    occ[int(np.argmin(C[:, h, w])), h, w] = True
    return occ, C, col


# --------------------------------------------------------------------------- maps and geometry


def test_extend_maps_band_values_brute_force():
    gen = torch.Generator().manual_seed(1)
    sdf = torch.randn(2, 5, 7, generator=gen)
    ext = extend_maps(sdf, pad=3)
    assert ext.shape == (2, 11, 13) and ext.dtype == torch.float32
    assert torch.equal(ext[:, 3:-3, 3:-3], sdf)
    for i in range(11):
        for j in range(13):
            y, x = i - 3, j - 3
            cy, cx = min(max(y, 0), 4), min(max(x, 0), 6)
            expect = sdf[:, cy, cx] + math.hypot(x - cx, y - cy)
            assert torch.allclose(ext[:, i, j], expect, atol=1e-6)


def test_extend_maps_mask_touching_border_is_outside_beyond_half_pixel():
    m = torch.zeros(1, 6, 6, dtype=torch.bool)
    m[0, :, :3] = True  # touches the left, top and bottom borders
    ext = extend_maps(signed_distance(m))
    assert float(ext[0, PAD + 2, PAD]) == pytest.approx(-0.5)  # border pixel, foreground
    assert (ext[0, :, :PAD] > 0).all() and (ext[0, :PAD] > 0).all()  # every band pixel is outside


def test_mask_geometry_against_numpy():
    gen = torch.Generator().manual_seed(2)
    masks = blob_masks(4, 24, gen)
    masks[3] = False
    t = torch.tensor([[3.0, 4.0], [12.0, 12.0], [0.0, 23.0], [5.0, 5.0]])
    box, nonempty, radius = mask_geometry(signed_distance(masks), t)
    assert nonempty.tolist() == [True, True, True, False]
    for i in range(3):
        ys, xs = np.nonzero(masks[i].numpy())
        assert box[i].tolist() == [xs.min() - 0.5, xs.max() + 0.5, ys.min() - 0.5, ys.max() + 0.5]
        far = np.hypot(xs - float(t[i, 0]), ys - float(t[i, 1])).max()
        assert float(radius[i]) == pytest.approx(far + math.sqrt(2), abs=1e-9)
    assert float(radius[3]) == 0.0


# --------------------------------------------------------------------------- exactness


def test_single_silhouette_matches_brute_force_cylinder():
    gen = torch.Generator().manual_seed(3)
    masks = blob_masks(2, 20, gen)[:1]
    cams = random_cameras(1, 20, gen)
    n = 8
    out = carve_proposals(signed_distance(masks), cams, torch.tensor([0]), torch.zeros(1, 0, dtype=torch.long),
                          resolution=n, return_cost=True)
    occ_bf, C_bf, col_bf = brute_force(signed_distance(masks), cams, out.voxel_to_camera[0], 0, [], n)
    assert np.allclose(out.cost[0].numpy(), C_bf, atol=1e-4)
    assert np.allclose(out.column_cost[0].numpy(), col_bf, atol=1e-4)
    assert np.array_equal(out.occupancy[0].numpy(), occ_bf)
    # A cylinder: every depth slice is the reference columns.
    assert torch.equal(out.occupancy[0], out.reference_columns[0].expand(n, n, n))


def test_single_silhouette_equals_mask_lookup_away_from_boundary():
    gen = torch.Generator().manual_seed(4)
    masks = blob_masks(2, 48, gen)[:1]
    cams = random_cameras(1, 48, gen)
    n = 40
    out = carve_proposals(signed_distance(masks), cams, torch.tensor([0]), torch.zeros(1, 0, dtype=torch.long),
                          resolution=n)
    pts = voxel_centres(out.voxel_to_camera[0], n)[0, ..., :2].reshape(-1, 2).numpy()  # column centres (x, y)
    m = masks[0].numpy()
    lookup = m[np.clip(np.round(pts[:, 1]).astype(int), 0, 47), np.clip(np.round(pts[:, 0]).astype(int), 0, 47)]
    lookup &= (pts >= -0.5).all(1) & (pts <= 47.5).all(1)
    got = out.occupancy[0, n // 2].reshape(-1).numpy()
    assert out.occupancy[0].any(0).equal(out.occupancy[0].all(0))  # constant along depth
    bad = np.nonzero(got != lookup)[0]
    assert len(bad) < 0.05 * (n * n)
    ys, xs = np.nonzero(m)
    bys, bxs = np.nonzero(~m)
    for i in bad:  # within half a pixel of a pixel of the other label
        x, y = pts[i]
        oy, ox = (bys, bxs) if lookup[i] else (ys, xs)
        dist = np.hypot(np.maximum(np.abs(x - ox) - 0.5, 0), np.maximum(np.abs(y - oy) - 0.5, 0)).min()
        assert dist <= 0.5 + 1e-6


def test_three_views_match_brute_force_with_imprinting():
    gen = torch.Generator().manual_seed(5)
    masks = blob_masks(3, 20, gen)
    cams = random_cameras(3, 20, gen)
    n = 7
    sdf = signed_distance(masks)
    for imprint in (True, False):
        out = carve_proposals(sdf, cams, torch.tensor([1]), torch.tensor([[0, 2]]), resolution=n, imprint=imprint,
                              return_cost=True)
        occ_bf, C_bf, _ = brute_force(sdf, cams, out.voxel_to_camera[0], 1, [0, 2], n, imprint=imprint)
        assert np.allclose(out.cost[0].numpy(), C_bf, atol=1e-4)
        sure = np.abs(C_bf) > 1e-4
        assert np.array_equal(out.occupancy[0].numpy()[sure], occ_bf[sure])


# --------------------------------------------------------------------------- known solids


def test_ellipsoid_three_views_matches_analytic_visual_hull():
    size, n = 64, 40
    sigma = torch.diag(torch.tensor([0.9, 0.5, 0.35]) ** 2)
    cams = cameras_from_angles([[30, 20, 0], [110, 10, 5], [200, 60, 0]], 30.0, [31.5, 31.5])
    masks = ellipsoid_masks(cams, sigma, size)
    grid = imprinted_visual_hull(masks, cams, reference=0, resolution=n)
    p = voxel_centres(grid.voxel_to_camera, n)
    u = to_views(cams, 0, p)  # (3, n, n, n, 2)
    analytic = ellipse_inside(cams, sigma, u).all(0)
    occ = grid.occupancy
    iou = (occ & analytic).sum() / (occ | analytic).sum()
    assert iou > 0.95
    bad = occ != analytic
    near = near_boundary(lambda q: ellipse_inside(cams, sigma, q), u[:, bad], 1.0).any(0)
    assert near.all()  # every disagreement is within a pixel of a silhouette boundary
    # The solid lies inside the hull (away from its surface by more than a pixel).
    X = cams.to(dtype=torch.float64)[0].from_camera_frame(p.reshape(1, -1, 3))[0]
    r = torch.sqrt((X @ torch.linalg.inv(sigma.double()) * X).sum(-1)).reshape(n, n, n)
    deep = r < 1 - 1.5 / 30.0
    assert deep.sum() > 1000 and occ[deep].all()
    # The grid encloses the hull: its outer layer is empty.
    assert not (occ[[0, -1]].any() or occ[:, [0, -1]].any() or occ[:, :, [0, -1]].any())


def test_box_generic_views_match_polygon_visual_hull():
    size, n = 64, 36
    half = torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64)
    corners = torch.tensor([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=torch.float64) * half
    cams = cameras_from_angles([[20, 15, 0], [100, 30, 0], [250, 70, 10]], 28.0, [31.5, 31.5])
    polys = [shapely.convex_hull(shapely.MultiPoint(cams.to(dtype=torch.float64)[i].project(corners)[0].numpy()))
             for i in range(3)]
    px = pixel_centres(size).reshape(-1, 2).numpy()
    masks = torch.stack([torch.from_numpy(shapely.contains_xy(P, px[:, 0], px[:, 1]).reshape(size, size))
                         for P in polys])
    grid = imprinted_visual_hull(masks, cams, reference=0, resolution=n)
    u = to_views(cams, 0, voxel_centres(grid.voxel_to_camera, n)).reshape(3, -1, 2).numpy()
    analytic = np.stack([shapely.contains_xy(P, u[i, :, 0], u[i, :, 1]) for i, P in enumerate(polys)]).all(0)
    occ = grid.occupancy.reshape(-1).numpy()
    assert (occ & analytic).sum() / (occ | analytic).sum() > 0.93
    bad = np.nonzero(occ != analytic)[0]
    dist = np.stack([shapely.distance(P.boundary, shapely.points(u[i, bad])) for i, P in enumerate(polys)]).min(0)
    assert (dist <= 1.0).all()


def test_box_axis_views_recover_the_box():
    size, n = 64, 40
    # front (looks along +y), side (along -x), top (along -z): the hull of these is the box
    cams = cameras_from_angles([[0, 0, 0], [90, 0, 0], [0, 90, 0]], 30.0, [31.5, 31.5])
    half = torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64)
    corners = torch.tensor([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], dtype=torch.float64) * half
    px = pixel_centres(size).numpy()
    masks = []
    for i in range(3):
        q = cams.to(dtype=torch.float64)[i].project(corners)[0].numpy()
        lo, hi = q.min(0), q.max(0)
        masks.append(torch.from_numpy(((px >= lo) & (px <= hi)).all(-1)))
    masks = torch.stack(masks)
    grid = imprinted_visual_hull(masks, cams, reference=0, resolution=n)
    X = cams.to(dtype=torch.float64)[0].from_camera_frame(voxel_centres(grid.voxel_to_camera, n).reshape(1, -1, 3))[0]
    solid = (X.abs() <= half).all(-1).reshape(n, n, n)
    occ = grid.occupancy
    assert (occ & solid).sum() / (occ | solid).sum() > 0.9
    # disagreements lie within a voxel (plus the masks' pixelisation) of the box surface
    margin = (X.abs() - half).abs().min(-1).values.reshape(n, n, n)
    step = grid.voxel_to_camera[:3, :3].abs().amax() / 30.0 + 1.0 / 30.0
    assert (margin[occ != solid] <= step).all()
    true_volume = float(torch.prod(2 * half)) * 30.0 ** 3
    assert grid.volume() == pytest.approx(true_volume, rel=0.08)


# --------------------------------------------------------------------------- batched vs loop


def random_proposals(gen, M=8, B=12, V=4, size=32):
    masks = blob_masks(M, size, gen)
    masks[5] = False  # an empty mask, used as a view and as a reference
    cams = random_cameras(M, size, gen)
    reference = torch.randint(0, M, (B,), generator=gen)
    reference[3] = 5
    views = torch.randint(0, M, (B, V), generator=gen)
    views[torch.rand(B, V, generator=gen) < 0.25] = -1
    views[4] = -1  # a proposal with no further view
    views[6, 0] = 5
    return signed_distance(masks), cams, reference, views


@pytest.mark.parametrize("imprint, n", [(True, 14), (False, 14), (True, 11)])
def test_batched_equals_loop_voxel_for_voxel(imprint, n):
    gen = torch.Generator().manual_seed(6)
    sdf, cams, reference, views = random_proposals(gen)
    loop = carve_proposals_loop(sdf, cams, reference, views, resolution=n, imprint=imprint)
    # "auto" runs the fused CPU kernel where it applies and builds (labels only), else torch
    for mbv, return_cost, backend in [(n ** 3, False, "torch"), (10 ** 9, False, "torch"), (n ** 3, False, "auto"),
                                      (n ** 3, True, "auto"), (10 ** 9, True, "auto")]:
        out = carve_proposals(sdf, cams, reference, views, resolution=n, imprint=imprint, max_batch_voxels=mbv,
                              return_cost=return_cost, backend=backend)
        assert torch.equal(out.occupancy, loop.occupancy)
        assert torch.equal(out.voxel_to_camera, loop.voxel_to_camera)
        assert torch.equal(out.empty, loop.empty)
        assert torch.equal(out.reference_columns, loop.reference_columns)
        assert torch.equal(out.column_cost, loop.column_cost)
        if return_cost:
            assert torch.equal(out.cost, loop.cost)
    assert bool(loop.empty[3]) and not loop.occupancy[3].any()  # empty reference
    assert loop.occupancy.any() and (~loop.empty).sum() >= len(reference) // 2


def test_nearest_interpolation_batched_equals_loop_and_brute_force():
    """``interpolation="nearest"``: the batched carving equals the loop voxel for voxel (every
    chunking, with and without imprinting), its costs equal a per-voxel float64 loop that reads the
    nearest pixel, and its labels differ from the bilinear ones only in a thin layer."""
    gen = torch.Generator().manual_seed(6)
    sdf, cams, reference, views = random_proposals(gen)
    n = 14
    for imprint in (True, False):
        loop = carve_proposals_loop(sdf, cams, reference, views, resolution=n, imprint=imprint, interpolation="nearest")
        for mbv in (n ** 3, 10 ** 9):
            out = carve_proposals(sdf, cams, reference, views, resolution=n, imprint=imprint, max_batch_voxels=mbv,
                                  return_cost=True, interpolation="nearest")
            assert torch.equal(out.occupancy, loop.occupancy) and torch.equal(out.cost, loop.cost)
            assert torch.equal(out.column_cost, loop.column_cost)
    bil = carve_proposals(sdf, cams, reference, views, resolution=n)
    near = carve_proposals(sdf, cams, reference, views, resolution=n, interpolation="nearest")
    differ = (bil.occupancy != near.occupancy).float().mean()
    assert 0 < differ < 0.05, differ  # not the same computation, but close to it
    gen = torch.Generator().manual_seed(5)
    masks = blob_masks(3, 20, gen)
    cams3 = random_cameras(3, 20, gen)
    sdf3 = signed_distance(masks)
    out = carve_proposals(sdf3, cams3, torch.tensor([1]), torch.tensor([[0, 2]]), resolution=7, return_cost=True,
                          interpolation="nearest")
    # a projection on a pixel edge (the grid is aligned with the reference, whose voxels can project
    # exactly between two pixels) picks either pixel, whichever float rounding gives: the voxels
    # whose cost does not depend on that are compared exactly
    T = out.voxel_to_camera[0]
    occ_lo, C_lo, _ = brute_force(sdf3, cams3, T, 1, [0, 2], 7, imprint=False, nearest=True, nudge=-1e-5)
    occ_hi, C_hi, _ = brute_force(sdf3, cams3, T, 1, [0, 2], 7, imprint=False, nearest=True, nudge=1e-5)
    clear = np.isclose(C_lo, C_hi, atol=1e-9)
    assert clear.mean() > 0.5
    assert np.allclose(out.cost[0].numpy()[clear], C_lo[clear], atol=1e-4)
    ambiguous = ~clear  # there, one of the two readings
    got = out.cost[0].numpy()[ambiguous]
    assert (np.isclose(got, C_lo[ambiguous], atol=1e-4) | np.isclose(got, C_hi[ambiguous], atol=1e-4)).all()


def test_unknown_interpolation_is_refused():
    sdf = signed_distance(blob_masks(2, 16, torch.Generator().manual_seed(0)))
    cams = random_cameras(2, 16, torch.Generator().manual_seed(0))
    args = (sdf, cams, torch.tensor([0]), torch.tensor([[1]]))
    with pytest.raises(ValueError, match="interpolation"):
        carve_proposals(*args, resolution=8, interpolation="bicubic")
    with pytest.raises(ValueError, match="interpolation"):
        carve_proposals_loop(*args, resolution=8, interpolation="bicubic")


def test_unused_slot_is_the_same_as_leaving_the_view_out():
    gen = torch.Generator().manual_seed(7)
    sdf, cams, _, _ = random_proposals(gen)
    a = carve_proposals(sdf, cams, torch.tensor([0, 0]), torch.tensor([[1, -1, 2], [1, 2, -1]]), resolution=12)
    b = carve_proposals(sdf, cams, torch.tensor([0]), torch.tensor([[2, 1]]), resolution=12)
    assert torch.equal(a.occupancy[0], b.occupancy[0]) and torch.equal(a.occupancy[1], b.occupancy[0])


# --------------------------------------------------------------------------- imprinting


def test_imprinting_fills_every_foreground_column():
    gen = torch.Generator().manual_seed(8)
    sdf, cams, reference, views = random_proposals(gen, M=10, B=16)
    n = 16
    with_imprint = carve_proposals(sdf, cams, reference, views, resolution=n, return_cost=True)
    without = carve_proposals(sdf, cams, reference, views, resolution=n, imprint=False)
    filled = with_imprint.occupancy.any(dim=1)  # (B, H, W) columns with an interior voxel
    assert (filled | ~with_imprint.reference_columns).all()
    assert (with_imprint.occupancy | ~without.occupancy).all()  # imprinting only adds voxels
    added = with_imprint.occupancy & ~without.occupancy
    # at most one voxel per column, in columns without any interior voxel, at the argmin of C
    assert (added.sum(dim=1) <= 1).all()
    cols = added.any(dim=1)
    assert not (without.occupancy.any(dim=1) & cols).any()
    b, h, w = cols.nonzero(as_tuple=True)
    argmin = with_imprint.cost[b, :, h, w].argmin(dim=1)
    assert torch.equal(added[b, :, h, w].int().argmax(dim=1), argmin)


def test_imprinting_repairs_inconsistent_surrogates():
    # reference: spread wings seen from the front; surrogates: closed wings seen from the side
    size, n = 48, 24
    ref = torch.zeros(size, size, dtype=torch.bool)
    ref[20:28, 4:44] = True  # wide
    narrow = torch.zeros(size, size, dtype=torch.bool)
    narrow[20:28, 20:28] = True
    masks = torch.stack([ref, narrow, narrow])
    cams = cameras_from_angles([[0, 0, 0], [45, 0, 0], [-45, 0, 0]], 20.0, [23.5, 23.5])
    sdf = signed_distance(masks)
    without = carve_proposals(sdf, cams, torch.tensor([0]), torch.tensor([[1, 2]]), resolution=n, imprint=False)
    fg = without.reference_columns[0]
    missed = fg & ~without.occupancy[0].any(0)
    assert missed.sum() > 0.3 * fg.sum()  # plain hull misses the wing tips
    grid = imprinted_visual_hull(masks, cams, reference=0, resolution=n)
    assert (grid.occupancy.any(0) | ~fg).all()


# --------------------------------------------------------------------------- contract, meshes, devices


def test_imprinted_visual_hull_contract_and_voxel_grid():
    size, n = 48, 20
    sigma = torch.diag(torch.tensor([0.9, 0.6, 0.4]) ** 2)
    cams = cameras_from_angles([[10, 10, 0], [100, 20, 0]], 20.0, [23.5, 23.5])
    masks = ellipsoid_masks(cams, sigma, size)
    grid = imprinted_visual_hull(masks, cams, reference=1, resolution=n)
    assert isinstance(grid, VoxelGrid)
    assert grid.occupancy.shape == (n, n, n) and grid.occupancy.dtype == torch.bool
    assert grid.voxel_to_camera.shape == (4, 4) and grid.cost.shape == (n, n, n)
    T = grid.voxel_to_camera.double()
    assert grid.volume() == pytest.approx(float(grid.occupancy.sum()) * abs(float(torch.linalg.det(T[:3, :3]))))
    pts = grid.camera_points()
    assert pts.shape == (int(grid.occupancy.sum()), 3)
    idx = grid.occupancy.nonzero().double()
    assert torch.allclose(pts.double(), idx @ T[:3, :3].T + T[:3, 3], atol=1e-4)
    # occupied voxel centres project inside the reference mask (within half a pixel)
    m = masks[1]
    xi, yi = pts[:, 0].round().long().clamp(0, size - 1), pts[:, 1].round().long().clamp(0, size - 1)
    assert m[yi, xi].float().mean() > 0.97
    assert grid.to("cpu").occupancy.equal(grid.occupancy)
    # carving the same silhouettes directly gives the same grid
    out = carve_proposals(signed_distance(masks), cams, torch.tensor([1]), torch.tensor([[0]]), resolution=n)
    assert torch.equal(out.occupancy[0], grid.occupancy) and isinstance(out, ProposalGrids)
    assert torch.equal(out[0].occupancy, grid.occupancy) and len(out) == 1
    assert torch.allclose(out.volumes(), torch.tensor([grid.volume()], dtype=torch.float64))


def test_grid_bounds_enclose_the_object_depth():
    size, n = 64, 30
    sigma = torch.diag(torch.tensor([0.9, 0.5, 0.35]) ** 2)
    cams = cameras_from_angles([[30, 20, 0], [120, 10, 0], [200, 60, 0]], 30.0, [31.5, 31.5])
    masks = ellipsoid_masks(cams, sigma, size)
    grid = imprinted_visual_hull(masks, cams, resolution=n)
    T = grid.voxel_to_camera.double()
    view = cams.R[0, 2].double()
    z_extent = 30.0 * math.sqrt(float(view @ sigma.double() @ view))  # analytic half depth of the ellipsoid
    z_first, z_last = float(T[2, 3]), float(T[2, 0] * (n - 1) + T[2, 3])
    assert z_first < -z_extent and z_last > z_extent
    assert z_last - z_first < 4 * z_extent  # and the bound is not loose
    ys, xs = np.nonzero(masks[0].numpy())
    assert float(T[0, 3] + T[0, 2] * 0.5) == pytest.approx(xs.min() - 0.5, abs=1e-4)  # cell edge on the extent
    assert float(T[1, 3] + T[1, 1] * (n - 1.5)) == pytest.approx(ys.max() + 0.5, abs=1e-4)


def test_mesh_of_a_carving_is_watertight_and_covers_the_reference():
    size, n = 48, 24
    sigma = torch.diag(torch.tensor([0.9, 0.5, 0.35]) ** 2)
    cams = cameras_from_angles([[30, 20, 0], [110, 10, 5], [200, 60, 0]], 22.0, [23.5, 23.5])
    masks = ellipsoid_masks(cams, sigma, size)
    masks[0, 22:26, 2:10] = True  # a thin part only the reference has: imprinted
    grid = imprinted_visual_hull(masks, cams, resolution=n)
    mesh = grid.to_mesh()
    assert mesh.is_watertight and mesh.volume > 0
    assert mesh.volume == pytest.approx(grid.volume(), rel=0.25)
    tris = mesh.vertices[mesh.faces][:, :, :2]
    shadow = shapely.union_all(shapely.polygons(tris)).buffer(1e-6)
    cols = voxel_centres(grid.voxel_to_camera, n)[0, ..., :2][grid.occupancy.any(0)].numpy()
    assert shapely.contains_xy(shadow, cols[:, 0], cols[:, 1]).all()  # every filled column is covered
    ys, xs = np.nonzero(masks[0].numpy())
    assert shapely.contains_xy(shadow, xs, ys).mean() > 0.9  # and so is the reference mask
    big = grid.to_mesh(largest_component=True)
    assert big.is_watertight and 0 < big.volume <= mesh.volume + 1e-6


def test_empty_reference_gives_an_empty_grid_and_mesh():
    masks = torch.zeros(2, 16, 16, dtype=torch.bool)
    masks[1, 4:10, 4:10] = True
    cams = cameras_from_angles([[0, 0, 0], [90, 0, 0]], 8.0, [7.5, 7.5])
    grid = imprinted_visual_hull(masks, cams, resolution=10)
    assert not grid.occupancy.any() and grid.volume() == 0.0
    assert torch.isfinite(grid.voxel_to_camera).all()
    assert len(grid.to_mesh().vertices) == 0
    out = carve_proposals(signed_distance(masks), cams, torch.tensor([0, 1]), torch.tensor([[1], [0]]), resolution=10)
    assert out.empty.tolist() == [True, False]
    # the empty view carves everything away; imprinting leaves one voxel per foreground column
    assert torch.equal(out.occupancy[1].sum(0), out.reference_columns[1].long())
    out = carve_proposals(signed_distance(masks), cams, torch.tensor([1]), torch.tensor([[0]]), resolution=10,
                          imprint=False)
    assert out.empty.tolist() == [True]
    out = carve_proposals(signed_distance(masks), cams, torch.tensor([1]), torch.zeros(1, 0, dtype=torch.long),
                          resolution=10)
    assert out.empty.tolist() == [False]
    none = carve_proposals(signed_distance(masks), cams, torch.zeros(0, dtype=torch.long),
                           torch.zeros(0, 1, dtype=torch.long), resolution=10)
    assert none.occupancy.shape == (0, 10, 10, 10)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(sdf=torch.zeros(3, 8)), "sdf"),
        (dict(sdf=torch.full((3, 8, 8), float("nan"))), "NaN"),
        (dict(reference=torch.tensor([3])), "reference"),
        (dict(reference=torch.tensor([0.0])), "reference"),
        (dict(views=torch.tensor([[0, -2]])), "views"),
        (dict(views=torch.tensor([0, 1])), "views"),
        (dict(resolution=3), "resolution"),
        (dict(max_batch_voxels=0), "max_batch_voxels"),
    ],
)
def test_bad_input_raises(kwargs, match):
    args = dict(sdf=torch.ones(3, 8, 8), reference=torch.tensor([0]), views=torch.tensor([[1, 2]]), resolution=8)
    args.update(kwargs)
    cams = cameras_from_angles([[0, 0, 0]] * 3, 4.0, [3.5, 3.5])
    with pytest.raises(ValueError, match=match):
        carve_proposals(args.pop("sdf"), cams, args.pop("reference"), args.pop("views"), **args)


def test_bad_cameras_and_masks_raise():
    cams = cameras_from_angles([[0, 0, 0]] * 2, 4.0, [3.5, 3.5])
    with pytest.raises(ValueError, match="cameras"):
        carve_proposals(torch.ones(3, 8, 8), cams, torch.tensor([0]), torch.tensor([[1]]))
    with pytest.raises(ValueError, match="reference"):
        imprinted_visual_hull(torch.ones(2, 8, 8, dtype=torch.bool), cams, reference=2)
    with pytest.raises(ValueError, match="masks"):
        imprinted_visual_hull(torch.ones(8, 8, dtype=torch.bool), cams)


@requires_cuda
def test_cuda_column_indices_are_exact():
    """The column rows and columns on CUDA (a tensor-by-scalar division there multiplies by the
    reciprocal) at widths where a plain ``floor(c / width)`` would be off by one."""
    from carvi_torch.carve.geometry import column_hw
    for width in (41, 47, 61, 2047):
        c = torch.arange(width * width, device="cuda")
        h, w = column_hw(c, width)
        assert torch.equal(h.long().cpu(), torch.arange(width * width) // width)
        assert torch.equal(w.long().cpu(), torch.arange(width * width) % width)


@requires_cuda
@pytest.mark.parametrize("n", [16, 41])
def test_cuda_matches_cpu(n):
    gen = torch.Generator().manual_seed(9)
    sdf, cams, reference, views = random_proposals(gen)
    cpu = carve_proposals(sdf, cams, reference, views, resolution=n, return_cost=True)
    gpu = carve_proposals(sdf.cuda(), cams.to("cuda"), reference.cuda(), views.cuda(), resolution=n,
                          return_cost=True)
    assert torch.allclose(gpu.column_cost.cpu(), cpu.column_cost, atol=1e-3, rtol=1e-5)
    assert gpu.occupancy.is_cuda
    assert torch.allclose(gpu.cost.cpu(), cpu.cost, atol=1e-3, rtol=1e-5)
    sure = cpu.cost.abs() > 1e-3
    assert torch.equal(gpu.occupancy.cpu()[sure], cpu.occupancy[sure])
    assert (gpu.occupancy.cpu() != cpu.occupancy).float().mean() < 1e-3
    loop = carve_proposals_loop(sdf.cuda(), cams.to("cuda"), reference.cuda(), views.cuda(), resolution=n)
    assert torch.equal(loop.occupancy, gpu.occupancy)
    masks = sdf < 0
    grid = imprinted_visual_hull(masks.cuda(), cams.to("cuda"), reference=0, resolution=n)
    assert grid.occupancy.is_cuda and grid.to_mesh().is_watertight


@requires_cuda
def test_cuda_nearest_matches_its_loop_and_the_cpu():
    """``interpolation="nearest"`` on CUDA: batched equals the CUDA loop voxel for voxel, and the CPU
    result except where a projection sits on a pixel edge (either pixel is a valid reading)."""
    gen = torch.Generator().manual_seed(9)
    sdf, cams, reference, views = random_proposals(gen)
    args = (sdf.cuda(), cams.to("cuda"), reference.cuda(), views.cuda())
    gpu = carve_proposals(*args, resolution=16, interpolation="nearest")
    loop = carve_proposals_loop(*args, resolution=16, interpolation="nearest")
    assert gpu.occupancy.is_cuda and torch.equal(loop.occupancy, gpu.occupancy)
    cpu = carve_proposals(sdf, cams, reference, views, resolution=16, interpolation="nearest")
    assert (gpu.occupancy.cpu() != cpu.occupancy).float().mean() < 1e-2


# --------------------------------------------------------------------------- real data


def render_mask(vertices: np.ndarray, faces: np.ndarray, cam: ScaledOrthographic, size: int) -> torch.Tensor:
    """Silhouette of a triangle mesh: union of its projected triangles (skimage polygon fill)."""
    uv = cam.project(torch.from_numpy(vertices).float())[0].numpy()
    mask = np.zeros((size, size), dtype=bool)
    for f in faces:
        rr, cc = draw_polygon(uv[f, 1], uv[f, 0], shape=mask.shape)
        mask[rr, cc] = True
    return torch.from_numpy(mask)


def test_real_cad_chair_hull_contains_the_model(shared_data):
    model = np.load(shared_data / "pascal3d_cad" / "chair04.npz")
    V, Fc = model["vertices"].astype(np.float32), model["faces"].astype(np.int64)
    size, n = 64, 32
    cams = cameras_from_angles([[30, 15, 0], [120, 10, 0], [250, 50, 0]], 50.0, [31.5, 31.5])
    masks = torch.stack([render_mask(V, Fc, cams[i], size) for i in range(3)])
    assert masks.flatten(1).any(1).all()
    grid = imprinted_visual_hull(masks, cams, reference=0, resolution=n)
    # CAD vertices in the reference camera frame, as voxel indices
    p = cams[0].to_camera_frame(torch.from_numpy(V))[0].double()
    T = grid.voxel_to_camera.double()
    idx = (p - T[:3, 3]) @ torch.linalg.inv(T[:3, :3]).T
    assert (idx > 0).all() and (idx < n - 1).all()  # the grid encloses the model
    near = torch.nn.functional.max_pool3d(grid.occupancy[None, None].float(), 3, 1, 1)[0, 0].bool()  # +-1 voxel
    inside = near[tuple(idx.round().long().T)]
    assert inside.float().mean() > 0.97
    # imprinting: every foreground column of the reference holds a voxel
    out = carve_proposals(signed_distance(masks), cams, torch.tensor([0]), torch.tensor([[1, 2]]), resolution=n)
    assert (out.occupancy[0].any(0) | ~out.reference_columns[0]).all()
    assert grid.to_mesh().is_watertight


# --------------------------------------------------------------------------- prepared maps


def test_prepared_maps_give_the_same_grids_bit_for_bit():
    gen = torch.Generator().manual_seed(11)
    sdf, cams, reference, views = random_proposals(gen, M=9, B=14, V=5, size=28)
    plain = carve_proposals(sdf, cams, reference, views, resolution=12)
    maps = prepare_maps(sdf, cams)
    assert len(maps) == 9 and maps.ext.shape == (10, 28 + 2 * PAD, 28 + 2 * PAD)
    torch.testing.assert_close(maps.sdf(torch.arange(9)), sdf.clamp(-BIG, BIG), rtol=0, atol=0)
    for kw in ({}, dict(max_batch_voxels=12 ** 3), dict(backend="torch")):
        got = carve_proposals(maps, None, reference, views, resolution=12, **kw)
        assert torch.equal(got.occupancy, plain.occupancy), kw
        assert torch.equal(got.voxel_to_camera, plain.voxel_to_camera) and torch.equal(got.empty, plain.empty)
        assert torch.equal(got.columns, got.occupancy.any(dim=1)), kw
    # maps given a chunk at a time by a function: the same maps
    chunked = prepare_maps(lambda a, b: sdf[a:b], cams, count=9)
    assert torch.equal(chunked.ext, maps.ext) and torch.equal(chunked.box, maps.box)
    # the loop takes prepared maps too
    loop = carve_proposals_loop(maps, None, reference, views, resolution=12)
    assert torch.equal(loop.occupancy, plain.occupancy)
    with pytest.raises(ValueError, match="cameras=None"):
        carve_proposals(maps, cams, reference, views, resolution=12)
    with pytest.raises(ValueError, match="reference"):
        carve_proposals(maps, None, torch.tensor([9]), views[:1], resolution=12)
    with pytest.raises(ValueError, match="count"):
        prepare_maps(lambda a, b: sdf[a:b], cams)


def test_entries_sharing_a_map_equal_copies_of_it():
    """with_entries (e.g. rotated cameras of one reference) carves like copying the map per camera."""
    gen = torch.Generator().manual_seed(12)
    sdf, cams, reference, views = random_proposals(gen, M=8, B=8, V=2, size=24)
    extra = random_cameras(4, 24, gen)
    which = torch.tensor([0, 0, 2, 3])
    maps = prepare_maps(sdf, cams).with_entries(which, extra)
    copied = torch.cat([sdf, sdf[which]])
    cams_all = ScaledOrthographic.cat([cams, extra])
    ref = torch.tensor([0, 2, 3, 1])
    vw = torch.tensor([[8, 9], [10, -1], [11, 1], [8, 11]])
    a = carve_proposals(maps, None, ref, vw, resolution=11)
    b = carve_proposals(copied, cams_all, ref, vw, resolution=11)
    assert torch.equal(a.occupancy, b.occupancy) and torch.equal(a.voxel_to_camera, b.voxel_to_camera)
    with pytest.raises(ValueError, match="map indices"):
        prepare_maps(sdf, cams).with_entries(torch.tensor([8]), extra[:1])


@pytest.mark.parametrize("imprint", [True, False])
def test_loop_structures_agree_voxel_for_voxel(imprint):
    """The benchmark's ladder of loops: distance maps computed per proposal from the masks,
    the reference sampled at every voxel, maps given, maps prepared once: same labels and cost."""
    gen = torch.Generator().manual_seed(21)
    sdf, cams, reference, views = random_proposals(gen, M=8, B=10, V=4, size=28)
    masks = sdf < 0
    n = 12
    given = carve_proposals_loop(sdf, cams, reference, views, resolution=n, imprint=imprint)
    naive = carve_proposals_loop(masks, cams, reference, views, resolution=n, imprint=imprint,
                                 reference_every_voxel=True)
    prepared = carve_proposals_loop(prepare_maps(sdf, cams), None, reference, views, resolution=n, imprint=imprint)
    batched = carve_proposals(sdf, cams, reference, views, resolution=n, imprint=imprint)
    for other in (naive, prepared, batched):
        assert torch.equal(other.occupancy, given.occupancy)
        assert torch.equal(other.voxel_to_camera, given.voxel_to_camera)
        assert torch.equal(other.empty, given.empty)
    assert torch.equal(naive.cost, given.cost) and torch.equal(prepared.cost, given.cost)
    assert bool(given.occupancy.any()) and bool(given.empty.any())  # the case is not trivial


def test_loop_from_masks_with_no_proposal():
    gen = torch.Generator().manual_seed(23)
    sdf, cams, _, _ = random_proposals(gen, M=8, B=8, V=2, size=16)
    out = carve_proposals_loop(sdf < 0, cams, torch.zeros(0, dtype=torch.long), torch.zeros(0, 2, dtype=torch.long),
                               resolution=8)
    assert out.occupancy.shape == (0, 8, 8, 8)


def test_loop_from_masks_rejects_bad_masks():
    gen = torch.Generator().manual_seed(22)
    sdf, cams, reference, views = random_proposals(gen, M=8, B=8, V=2, size=16)
    with pytest.raises(ValueError, match="masks must be a"):
        carve_proposals_loop((sdf < 0)[None], cams, reference, views, resolution=8)
    with pytest.raises(ValueError, match="cameras must be"):
        carve_proposals_loop(sdf < 0, cams[:4], reference, views, resolution=8)


def test_foreground_first_is_the_stable_argsort():
    from carvi_torch.carve.torch_backend import foreground_first
    gen = torch.Generator().manual_seed(3)
    fg = torch.rand(9, 37, generator=gen) < 0.5
    fg[0] = True  # every column foreground
    fg[1] = False  # none
    fg[2, :5] = True
    fg[2, 5:] = False
    got = foreground_first(fg)
    want = torch.from_numpy(np.argsort((~fg).numpy(), axis=1, kind="stable"))
    assert torch.equal(got, want)
    # a permutation of every row, foreground first, each part ascending
    count = fg.sum(1)
    for b in range(fg.shape[0]):
        k = int(count[b])
        assert sorted(got[b].tolist()) == list(range(37))
        assert bool(fg[b, got[b, :k]].all()) and not bool(fg[b, got[b, k:]].any())
        for part in (got[b, :k], got[b, k:]):
            assert bool((part[1:] > part[:-1]).all())


def test_default_batch_voxels_scales_with_threads_and_is_bounded():
    from carvi_torch.carve import default_batch_voxels
    before = torch.get_num_threads()
    try:
        seen = {}
        for t in (1, 2, 3, 64):
            torch.set_num_threads(t)
            seen[t] = default_batch_voxels("cpu")
    finally:
        torch.set_num_threads(before)
    assert seen[1] == 2 ** 19 and seen[2] == 2 ** 20 and seen[3] == 3 * 2 ** 19 and seen[64] == 2 ** 21
    assert default_batch_voxels("cuda") == default_batch_voxels(torch.device("cuda", 0)) == 2 ** 25
    # the chunking never changes the labels (cf. test_batched_equals_loop_voxel_for_voxel)
    gen = torch.Generator().manual_seed(8)
    sdf, cams, reference, views = random_proposals(gen)
    a = carve_proposals(sdf, cams, reference, views, resolution=12)
    b = carve_proposals(sdf, cams, reference, views, resolution=12, max_batch_voxels=12 ** 2)
    assert torch.equal(a.occupancy, b.occupancy) and torch.equal(a.columns, b.columns)


@pytest.mark.parametrize("threads", [2, 3])
def test_chunks_hold_a_multiple_of_the_threads_within_the_budget(threads, monkeypatch):
    """The CPU ``grid_sample`` shares work among threads by batch entry: every chunk but the
    last of a call holds a multiple of the thread count, none exceeds the voxel budget, and
    the labels are those of one thread and one proposal per chunk (the torch backend's chunks)."""
    from carvi_torch.carve import torch_backend
    gen = torch.Generator().manual_seed(8)
    sdf, cams, reference, views = random_proposals(gen, B=23)
    n = 12
    sizes = []
    plan = torch_backend.plan_chunks

    def spy(*args, **kwargs):
        for idx, k, slots in plan(*args, **kwargs):
            sizes.append(len(idx))
            yield idx, k, slots

    monkeypatch.setattr(torch_backend, "plan_chunks", spy)
    fg_cols = carve_proposals(sdf, cams, reference, views, resolution=n, max_batch_voxels=1).reference_columns
    count = fg_cols.flatten(1).sum(1)
    budget = 7 * int(count.max()) * n  # 7 proposals of the largest count: 6 with 2 or 3 threads
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = carve_proposals(sdf, cams, reference, views, resolution=n, max_batch_voxels=n, backend="torch")
        torch.set_num_threads(threads)
        sizes.clear()
        out = carve_proposals(sdf, cams, reference, views, resolution=n, max_batch_voxels=budget, backend="torch")
        assert torch_backend.chunk_multiple(torch.device("cpu")) == threads
    finally:
        torch.set_num_threads(before)
    assert torch_backend.chunk_multiple(torch.device("cuda")) == 1
    got = list(sizes)  # chunks led by an empty reference are skipped, and empty ones come last
    assert int((count > 0).sum()) <= sum(got) <= len(count) and len(got) >= 3
    assert all(s % threads == 0 for s in got[:-1]), got
    order = torch.argsort(count, descending=True, stable=True)
    start = 0
    for s in got:  # proposals of the chunk: at most the budget's voxels of foreground columns
        assert s * int(count[order[start]]) * n <= budget
        start += s
    assert torch.equal(out.occupancy, one.occupancy) and torch.equal(out.columns, one.columns)
    assert torch.equal(out.empty, one.empty)
    loop = carve_proposals_loop(sdf, cams, reference, views, resolution=n)
    assert torch.equal(out.occupancy, loop.occupancy)
    # a budget of fewer proposals than threads: chunks of whatever fits (here one), not of zero
    try:
        torch.set_num_threads(threads)
        sizes.clear()
        small = carve_proposals(sdf, cams, reference, views, resolution=n, max_batch_voxels=int(count.max()) * n,
                                return_cost=True)
    finally:
        torch.set_num_threads(before)
    assert sizes and set(sizes) == {1}
    assert torch.equal(small.occupancy, loop.occupancy) and torch.equal(small.cost, loop.cost)


@pytest.mark.parametrize("width", [4, 11, 41, 60, 61, 517, 2047, 2048])
def test_column_hw_is_exact_integer_division(width):
    from carvi_torch.carve.geometry import column_hw
    c = torch.arange(width * width)
    h, w = column_hw(c, width)
    assert h.dtype == w.dtype == torch.float32
    assert torch.equal(h.long(), torch.div(c, width, rounding_mode="floor")) and torch.equal(w.long(), c % width)


def test_column_hw_rule_is_exact_under_a_reciprocal_multiply_too():
    """CUDA divides a tensor by a scalar as a multiply by the float32 reciprocal: the rule of
    ``_column_hw`` must hold for that division too, at every width up to the bound (the quotient
    grows with ``c``, so each row's first and last column decide)."""
    for width in range(4, 2049):
        h = torch.arange(width, dtype=torch.float32)
        ends = torch.cat([h * width, h * width + (width - 1)])
        inv = torch.tensor(1.0, dtype=torch.float32) / torch.tensor(float(width), dtype=torch.float32)
        for q in ((ends + 0.5) / width, (ends + 0.5) * inv):
            assert torch.equal(torch.floor(q), torch.cat([h, h])), width


def test_resolution_above_the_exact_column_bound_is_refused():
    gen = torch.Generator().manual_seed(2)
    sdf, cams, reference, views = random_proposals(gen)
    with pytest.raises(ValueError, match=r"resolution must be an int in \[4, 2048\]"):
        carve_proposals(sdf, cams, reference, views, resolution=2049)


