"""Tests of carvi_torch.select: average masks, proposal projections, scores, keypoint misses, ranking."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from carvi_torch.cameras import ScaledOrthographic, random_rotations
from carvi_torch.surrogates import object_share
from carvi_torch.select import (
    average_masks,
    keypoint_misses,
    plane_axes,
    plane_centre,
    plane_extent,
    plane_points,
    project_proposals,
    rank_proposals,
    score_proposals,
)
from conftest import requires_cuda

HALF = (0.9, 0.6, 0.4)  # box half-sizes along axes[0], axes[1], axes[2]
CANVAS = 64


# --------------------------------------------------------------------------- helpers (independent references)


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    return float((a & b).sum() / max(1, (a | b).sum()))


def _view_along(axes: torch.Tensor, j: int, sign: float, roll: float) -> torch.Tensor:
    """Rotation whose viewing direction is ``sign * axes[j]``, rolled by ``roll`` in the image."""
    d = sign * axes[j]
    u = math.cos(roll) * axes[(j + 1) % 3] + math.sin(roll) * axes[(j + 2) % 3]
    v = torch.linalg.cross(d, u, dim=-1)
    return torch.stack([u, v, d])


def _render_box(R, s, t, axes, half, size=CANVAS) -> np.ndarray:
    """Silhouette of the box ``{X : |axes[i] . X| <= half[i]}`` by exact ray/slab intersection.

    A pixel ``(x, y)`` sees the ray ``X(l) = p0 R[0] + p1 R[1] + l R[2]`` with
    ``p = ((x, y) - t) / s``; it is foreground when the ray meets the box.
    """
    R, axes = np.asarray(R, np.float64), np.asarray(axes, np.float64)
    ys, xs = np.mgrid[0:size, 0:size].astype(np.float64)
    p0, p1 = (xs - t[0]) / s, (ys - t[1]) / s
    lo = np.full(xs.shape, -np.inf)
    hi = np.full(xs.shape, np.inf)
    ok = np.ones(xs.shape, bool)
    for i in range(3):
        alpha = p0 * (axes[i] @ R[0]) + p1 * (axes[i] @ R[1])
        beta = axes[i] @ R[2]
        if abs(beta) < 1e-12:
            ok &= np.abs(alpha) <= half[i]
        else:
            l1, l2 = (-half[i] - alpha) / beta, (half[i] - alpha) / beta
            lo = np.maximum(lo, np.minimum(l1, l2))
            hi = np.minimum(hi, np.maximum(l1, l2))
    return ok & (lo <= hi)


def _plane_rect(j, G, extent, half=HALF) -> np.ndarray:
    """Analytic projection of the box on plane ``j``: ``|a| <= half[j+1]``, ``|b| <= half[j+2]``."""
    g = np.linspace(-extent, extent, G)
    ha, hb = half[(j + 1) % 3], half[(j + 2) % 3]
    return (np.abs(g)[None, :] <= ha) & (np.abs(g)[:, None] <= hb)


def _voxelise_box(cam: ScaledOrthographic, axes, half, step, pad=2):
    """Occupancy + voxel_to_camera of the box in ``cam``'s camera frame (grid aligned with it)."""
    signs = torch.tensor([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], dtype=torch.float64)
    corners = (signs * torch.tensor(half, dtype=torch.float64)) @ axes.double()
    pc = cam.to(dtype=torch.float64).to_camera_frame(corners)[0]  # (8, 3) = x, y, z
    lo = torch.floor(pc.min(0).values) - pad * step
    n = torch.ceil((pc.max(0).values + pad * step - lo) / step).long() + 1  # per x, y, z
    T = torch.zeros(4, 4, dtype=torch.float64)
    T[0, 2] = T[1, 1] = T[2, 0] = step
    T[:3, 3] = lo
    T[3, 3] = 1.0
    D, H, W = int(n[2]), int(n[1]), int(n[0])
    idx = torch.stack(torch.meshgrid(torch.arange(D), torch.arange(H), torch.arange(W), indexing="ij"), -1)
    hom = torch.cat([idx.reshape(-1, 3).double(), torch.ones(D * H * W, 1, dtype=torch.float64)], 1)
    pcam = (hom @ T.T)[:, :3]
    X = cam.to(dtype=torch.float64).from_camera_frame(pcam[None])[0]
    c = X @ axes.double().T
    occ = (c.abs() <= torch.tensor(half, dtype=torch.float64)).all(-1).reshape(D, H, W)
    return occ, T


def _box_class(axes, rolls=(0.3, 2.0), jitter=((0.0, 0.0), (1.5, -2.0))):
    """Masks and cameras of identical boxes seen exactly along +-each axis."""
    Rs, ss, ts, labels, signs = [], [], [], [], []
    for j in range(3):
        for sign in (1.0, -1.0):
            for roll, (dx, dy) in zip(rolls, jitter):
                Rs.append(_view_along(axes, j, sign, roll))
                ss.append(18.0 + dx)
                ts.append([32.0 + dx, 31.0 + dy])
                labels.append(j)
                signs.append(sign)
    cams = ScaledOrthographic(torch.stack(Rs), torch.tensor(ss), torch.tensor(ts))
    masks = torch.stack([
        torch.from_numpy(_render_box(cams.R[n], float(cams.s[n]), cams.t[n].tolist(), axes, HALF))
        for n in range(len(cams))
    ])
    return masks, cams, torch.tensor(labels), torch.tensor(signs)


@pytest.fixture
def axes(generator):
    return random_rotations(1, generator)[0]


# --------------------------------------------------------------------------- planes


class TestPlanes:
    def test_plane_axes_cyclic_right_handed(self, axes):
        pa = plane_axes(axes)
        for j in range(3):
            torch.testing.assert_close(torch.linalg.cross(pa[j, 0], pa[j, 1], dim=-1), axes[j], atol=1e-6, rtol=0)

    def test_plane_points(self, axes):
        pts = plane_points(axes, 5, 2.0, centre=torch.tensor([1.0, 2.0, 3.0]))
        assert pts.shape == (3, 5, 5, 3)
        # [j, i, k] = centre + a_k e_a + b_i e_b, a/b = linspace(-2, 2, 5)
        j, i, k = 1, 4, 0
        expected = torch.tensor([1.0, 2.0, 3.0]) + (-2.0) * axes[2] + 2.0 * axes[0]
        torch.testing.assert_close(pts[j, i, k], expected)

    def test_extent_and_centre(self):
        S = torch.tensor([[1.0, 0, 0], [3.0, 0, 0], [2.0, 2.0, 0], [float("nan"), 0, 0]])
        torch.testing.assert_close(plane_centre(S), torch.tensor([2.0, 2.0 / 3, 0.0]))
        expected = 1.3 * max(math.dist(p, (2.0, 2.0 / 3, 0.0)) for p in [(1, 0, 0), (3, 0, 0), (2, 2, 0)])
        assert plane_extent(S) == pytest.approx(expected)
        assert plane_extent(S, factor=1.0, centre=torch.zeros(3)) == pytest.approx(3.0)
        with pytest.raises(ValueError, match="factor"):
            plane_extent(S, factor=0.0)


# --------------------------------------------------------------------------- average_masks


class TestAverageMasks:
    def test_boxes_seen_along_axes_give_the_rectangle(self, axes):
        masks, cams, labels, _ = _box_class(axes)
        ext = 1.3 * math.sqrt(sum(h * h for h in HALF))
        avg, counts = average_masks(masks, cams, labels, axes, plane_size=64, extent=torch.tensor(ext))
        assert avg.shape == (3, 64, 64) and avg.dtype == torch.float32
        assert counts.tolist() == [4, 4, 4]
        assert float(avg.min()) >= 0 and float(avg.max()) <= 1
        for j in range(3):
            iou = _iou(avg[j].numpy() > 0.5, _plane_rect(j, 64, ext))
            assert iou > 0.9, (j, iou)

    def test_back_views_agree_with_front_views(self, axes):
        masks, cams, labels, signs = _box_class(axes)
        ext = 1.3
        front, _ = average_masks(masks, cams, torch.where(signs > 0, labels, -1), axes, 48, ext)
        back, _ = average_masks(masks, cams, torch.where(signs < 0, labels, -1), axes, 48, ext)
        for j in range(3):
            assert _iou(front[j] > 0.5, back[j] > 0.5) > 0.95
            assert float((front[j] - back[j]).abs().mean()) < 0.03

    def test_vs_brute_force_nearest(self, generator):
        n, H, W, G, ext = 6, 40, 50, 16, 1.2
        R = random_rotations(n, generator)
        s = 10 + 5 * torch.rand(n, generator=generator)
        t = torch.tensor([[25.0, 20.0]]) + 3 * torch.randn(n, 2, generator=generator)
        cams = ScaledOrthographic(R, s, t)
        masks = torch.rand(n, H, W, generator=generator) > 0.5
        labels = torch.tensor([0, 2, 2, -1, 0, 2])
        axes = random_rotations(1, generator)[0]
        avg, counts = average_masks(masks, cams, labels, axes, G, ext, mode="nearest")
        g = np.linspace(-ext, ext, G)
        expected = np.zeros((3, G, G))
        ax = axes.double().numpy()
        for m in range(n):
            j = int(labels[m])
            if j < 0:
                continue
            ea, eb = ax[(j + 1) % 3], ax[(j + 2) % 3]
            Rm, sm, tm = R[m].double().numpy(), float(s[m]), t[m].double().numpy()
            for i in range(G):
                for k in range(G):
                    X = g[k] * ea + g[i] * eb
                    x, y = sm * (Rm[:2] @ X) + tm
                    xi, yi = int(np.floor(x + 0.5)), int(np.floor(y + 0.5))
                    if 0 <= xi < W and 0 <= yi < H and masks[m, yi, xi]:
                        expected[j, i, k] += 1
        expected /= np.maximum(np.bincount(labels[labels >= 0].numpy(), minlength=3), 1)[:, None, None]
        assert counts.tolist() == [2, 0, 3]
        assert bool((avg[1] == 0).all())  # no members -> no average
        mismatch = np.abs(avg.numpy() - expected) > 1e-5
        assert mismatch.mean() < 0.01, mismatch.sum()

    def test_object_weights_vs_one_member_at_a_time(self, generator):
        """Each physical object counts once: the weighted average equals the mean over objects of each
        object's mean aligned mask (brute force: one member at a time); unit weights change nothing."""
        n, H, W, G, ext = 7, 30, 36, 12, 1.1
        cams = ScaledOrthographic(random_rotations(n, generator), 9 + 3 * torch.rand(n, generator=generator),
                                  torch.tensor([[18.0, 15.0]]) + 2 * torch.randn(n, 2, generator=generator))
        masks = torch.rand(n, H, W, generator=generator) > 0.4
        labels = torch.tensor([0, 0, 0, 0, 2, 2, -1])
        objects = torch.tensor([5, 5, 5, 6, 5, 7, 6])  # cluster 0: three views of 5 and one of 6
        axes = random_rotations(1, generator)[0]
        weights = object_share(labels, objects)
        avg, counts = average_masks(masks, cams, labels, axes, G, ext, weights=weights)
        one = [average_masks(masks, cams, torch.where(torch.arange(n) == m, labels, -1), axes, G, ext)[0]
               for m in range(n)]
        for j in (0, 2):
            per_object = {}
            for m in range(n):
                if int(labels[m]) == j:
                    per_object.setdefault(int(objects[m]), []).append(one[m][j])
            expected = torch.stack([torch.stack(v).mean(0) for v in per_object.values()]).mean(0)
            torch.testing.assert_close(avg[j], expected, atol=1e-5, rtol=0)
        assert counts.tolist() == [4, 0, 2] and bool((avg[1] == 0).all())
        plain, _ = average_masks(masks, cams, labels, axes, G, ext)
        assert torch.equal(average_masks(masks, cams, labels, axes, G, ext, weights=torch.ones(n))[0], plain)
        assert not torch.allclose(avg[0], plain[0])  # the rule did something where an object repeats

    def test_exceptions(self, axes):
        cams = ScaledOrthographic(torch.eye(3)[None], torch.ones(1), torch.zeros(1, 2))
        with pytest.raises(ValueError, match="cameras"):
            average_masks(torch.zeros(2, 8, 8, dtype=torch.bool), cams, torch.zeros(2, dtype=torch.long), axes)
        with pytest.raises(ValueError, match="labels"):
            average_masks(torch.zeros(1, 8, 8, dtype=torch.bool), cams, torch.zeros(2, dtype=torch.long), axes)
        with pytest.raises(ValueError, match="mode"):
            average_masks(torch.zeros(1, 8, 8, dtype=torch.bool), cams, torch.zeros(1, dtype=torch.long), axes,
                          mode="x")
        with pytest.raises(ValueError, match="extent"):
            average_masks(torch.zeros(1, 8, 8, dtype=torch.bool), cams, torch.zeros(1, dtype=torch.long), axes,
                          extent=0.0)


# --------------------------------------------------------------------------- project_proposals


def _ref_cameras(generator, b):
    R = random_rotations(b, generator)
    return ScaledOrthographic(R, torch.full((b,), 20.0), torch.tensor([[32.0, 30.0]]).expand(b, 2).clone())


def _stack_grids(grids):
    """Pad voxel grids to a common (D, H, W) (padding is empty, so transforms stay valid)."""
    D = max(o.shape[0] for o, _ in grids)
    H = max(o.shape[1] for o, _ in grids)
    W = max(o.shape[2] for o, _ in grids)
    occ = torch.zeros(len(grids), D, H, W, dtype=torch.bool)
    for b, (o, _) in enumerate(grids):
        occ[b, : o.shape[0], : o.shape[1], : o.shape[2]] = o
    return occ, torch.stack([T for _, T in grids])


class TestProjectProposals:
    def test_box_along_each_axis(self, generator, axes):
        cams = _ref_cameras(generator, 2)
        step = 1.0  # pixels; s = 20 -> 0.05 object units
        occ, T = _stack_grids([_voxelise_box(cams[b], axes, HALF, step=step) for b in range(2)])
        ext, G = 1.3, 64
        proj = project_proposals(occ, T, cams, axes, G, ext)
        assert proj.shape == (2, 3, G, G) and proj.dtype == torch.bool
        # The voxelised box's shadow lies within sqrt(3) v / 2 of the true box's (v = voxel edge),
        # and a set sample within half a spacing c / 2 of the shadow.
        v, c = step / 20.0, 2 * ext / (G - 1)
        r = math.sqrt(3) * v / 2
        for b in range(2):
            for j in range(3):
                got = proj[b, j].numpy()
                inner = _plane_rect(j, G, ext, tuple(h - r for h in HALF))
                outer = _plane_rect(j, G, ext, tuple(h + r + c / 2 + 1e-6 for h in HALF))
                assert got[inner].all() and not got[~outer].any(), (b, j)
                iou = _iou(got, _plane_rect(j, G, ext))
                assert iou > 0.8, (b, j, iou)

    def test_coarse_voxels_leave_no_holes(self, generator, axes):
        cams = _ref_cameras(generator, 1)
        step = 2.0  # 0.1 object units per voxel vs a plane spacing of 2.6 / 63 ~ 0.041
        occ, T = _voxelise_box(cams[0], axes, HALF, step=step)
        ext, G = 1.3, 64
        margin = math.sqrt(3) * step / 20.0  # voxel diagonal, object units
        inner = [_plane_rect(j, G, ext, tuple(h - margin for h in HALF)) for j in range(3)]
        auto = project_proposals(occ[None], T[None], cams, axes, G, ext)
        single = project_proposals(occ[None], T[None], cams, axes, G, ext, supersample=1)
        c = 2 * ext / (G - 1)
        for j in range(3):
            assert bool(auto[0, j].numpy()[inner[j]].all()), j  # every interior sample is set
            outer = _plane_rect(j, G, ext, tuple(h + margin / 2 + c / 2 + 1e-6 for h in HALF))
            assert not bool(auto[0, j].numpy()[~outer].any()), j
        # centres alone leave holes: the footprint sampling is what fills them
        assert sum(int((~single[0, j].numpy())[inner[j]].sum()) for j in range(3)) > 50

    @pytest.mark.parametrize("native", [False, None])
    @pytest.mark.parametrize("m", [1, 2])
    def test_vs_brute_force(self, generator, m, native):
        B, D, H, W, G, ext = 2, 5, 6, 7, 12, 1.0
        occ = torch.rand(B, D, H, W, generator=generator) > 0.7
        cams = ScaledOrthographic(random_rotations(B, generator), torch.tensor([9.0, 12.0]),
                                  torch.tensor([[3.0, 4.0], [5.0, 2.0]]))
        T = torch.zeros(B, 4, 4, dtype=torch.float64)
        T[:, 0, 2] = T[:, 1, 1] = T[:, 2, 0] = torch.tensor([1.3, 0.9], dtype=torch.float64)
        T[:, :3, 3] = torch.randn(B, 3, generator=generator, dtype=torch.float64)
        T[:, 3, 3] = 1
        axes = random_rotations(1, generator)[0]
        centre = torch.tensor([0.05, -0.1, 0.02])
        got = project_proposals(occ, T, cams, axes, G, ext, centre=centre, supersample=m, native=native)
        expected = np.zeros((B, 3, G, G), bool)
        ax = axes.double().numpy()
        o = (np.arange(m) + 0.5) / m - 0.5
        for b in range(B):
            Rb, sb, tb = cams.R[b].double().numpy(), float(cams.s[b]), cams.t[b].double().numpy()
            for d, h, w in occ[b].nonzero().tolist():
                for od in o:
                    for oh in o:
                        for ow in o:
                            p = T[b].numpy() @ np.array([d + od, h + oh, w + ow, 1.0])
                            q = np.array([p[0] - tb[0], p[1] - tb[1], p[2]]) / sb
                            X = Rb.T @ q - centre.double().numpy()
                            for j in range(3):
                                a, bb = ax[(j + 1) % 3] @ X, ax[(j + 2) % 3] @ X
                                k = int(np.floor((a + ext) * (G - 1) / (2 * ext) + 0.5))
                                i = int(np.floor((bb + ext) * (G - 1) / (2 * ext) + 0.5))
                                if 0 <= k < G and 0 <= i < G:
                                    expected[b, j, i, k] = True
        assert expected.sum() > 20
        assert int((got.numpy() != expected).sum()) <= 2  # rounding ties at most

    def test_boundary_vs_scipy_erosion(self, generator):
        """Boundary voxels = occupied minus the 26-neighbourhood erosion (outside the grid counts as empty)."""
        from scipy import ndimage

        from carvi_torch.select import boundary_voxels

        occ = torch.rand(3, 7, 9, 8, generator=generator) > 0.35
        occ[1] = True  # full grid: only its outer layer is boundary
        got = boundary_voxels(occ)
        st = np.ones((3, 3, 3), bool)
        for b in range(3):
            o = occ[b].numpy()
            expected = o & ~ndimage.binary_erosion(o, structure=st, border_value=0)
            assert np.array_equal(got[b].numpy(), expected), b
        assert got[1].sum() == 7 * 9 * 8 - 5 * 7 * 6

    def test_each_grid_alone_equals_in_a_batch(self, generator, axes):
        """Per-grid sub-sampling: a projection does not depend on its batch mates or on the chunking."""
        cams = _ref_cameras(generator, 3)
        grids = [_voxelise_box(cams[0], axes, HALF, step=0.6), _voxelise_box(cams[1], axes, HALF, step=2.5),
                 _voxelise_box(cams[2], axes, HALF, step=1.2)]
        occ, T = _stack_grids(grids)
        full = project_proposals(occ, T, cams, axes, 48, 1.3)
        for b in range(3):
            alone = project_proposals(occ[b:b + 1], T[b:b + 1], cams[b:b + 1], axes, 48, 1.3)
            assert torch.equal(alone[0], full[b]), b
        small = project_proposals(occ, T, cams, axes, 48, 1.3, chunk_points=100, chunk_voxels=1)
        assert torch.equal(small, full)
        # the coarse grid needs more sub-samples than the fine one: the rule is per grid
        from carvi_torch.select import supersampling

        A = torch.zeros(3, 3, 4, dtype=torch.float64)
        A[:, :, :3] = torch.diag_embed(torch.tensor([[0.1, 0.1, 0.1], [1.0, 0.1, 0.1], [0.1, 0.1, 2.0]],
                                                    dtype=torch.float64))
        assert supersampling(A, 0.2, None).tolist() == [[1, 1, 1], [8, 1, 1], [1, 1, 8]]

    def test_empty_and_exceptions(self, generator, axes):
        cams = _ref_cameras(generator, 2)
        occ = torch.zeros(2, 3, 3, 3, dtype=torch.bool)
        T = torch.eye(4).expand(2, 4, 4)
        assert not bool(project_proposals(occ, T, cams, axes, 8, 1.0).any())
        with pytest.raises(ValueError, match="voxel_to_camera"):
            project_proposals(occ, torch.eye(4)[None], cams, axes, 8, 1.0)
        with pytest.raises(ValueError, match="ref_cameras"):
            project_proposals(occ, T, cams[0], axes, 8, 1.0)
        with pytest.raises(ValueError, match="plane_size"):
            project_proposals(occ, T, cams, axes, 1, 1.0)
        with pytest.raises(ValueError, match="extent is required"):
            project_proposals(occ, T, cams, axes, 8)
        with pytest.raises(ValueError, match="supersample"):
            project_proposals(occ, T, cams, axes, 8, 1.0, supersample=0)


def _library():
    from carvi_torch import native_library

    ops = native_library.library_operators()
    if ops is None:
        pytest.skip(f"the compiled library is not available here: {native_library.load()['reason']}")
    return ops


class TestNativeSplat:
    """The compiled splat (``carvi_torch/kernels/splat_planes.h``) against the torch operators, bit for bit."""

    @pytest.mark.parametrize("supersample", [None, 1, 2, 3])
    def test_equals_the_torch_operators(self, generator, supersample):
        _library()
        B, D, H, W = 5, 9, 7, 11
        occ = torch.rand(B, D, H, W, generator=generator) > 0.45
        occ[1] = True  # full: only its outer layer is boundary
        occ[2] = False  # empty
        occ[3, :, :, -1] = True  # touching the grid's edge
        cams = _ref_cameras(generator, B)
        T = torch.zeros(B, 4, 4, dtype=torch.float64)
        T[:, :3, :3] = torch.diag_embed(torch.rand(B, 3, generator=generator, dtype=torch.float64) * 3 + 0.2)
        T[:, :3, 3] = torch.randn(B, 3, generator=generator, dtype=torch.float64) * 5
        T[:, 3, 3] = 1
        axes = random_rotations(1, generator)[0]
        for ext in (1.0, 0.3):  # 0.3: many points fall off the planes (clamped to the border)
            a = project_proposals(occ, T, cams, axes, 24, ext, supersample=supersample, native=False)
            b = project_proposals(occ, T, cams, axes, 24, ext, supersample=supersample, native=True)
            assert torch.equal(a, b), ext
            assert bool(a.any()) and not bool(a[2].any())

    def test_default_uses_the_kernel_on_the_cpu_and_falls_back(self, generator, axes, monkeypatch):
        from carvi_torch import native_library

        ops = _library()
        occ = torch.rand(2, 6, 6, 6, generator=generator) > 0.5
        T = torch.eye(4, dtype=torch.float64).expand(2, 4, 4) * 0.1
        T = T.clone()
        T[:, 3, 3] = 1
        cams = _ref_cameras(generator, 2)
        calls = []

        class Spy:
            def splat_planes(self, *args):
                calls.append(args[0].shape)
                return ops.splat_planes(*args)

        monkeypatch.setattr(native_library, "library_operators", lambda: Spy())
        got = project_proposals(occ, T, cams, axes, 16, 1.0)
        assert calls, "the default did not take the kernel on the CPU"
        monkeypatch.setattr(native_library, "library_operators", lambda: None)
        monkeypatch.setattr(native_library, "load", lambda: {"reason": "no compiler"})
        assert torch.equal(project_proposals(occ, T, cams, axes, 16, 1.0), got)  # the torch operators
        with pytest.raises(RuntimeError, match="no compiler"):
            project_proposals(occ, T, cams, axes, 16, 1.0, native=True)

    def test_sum_order_and_ties_of_the_torch_code(self):
        """One voxel, one sub-voxel point, crafted tables: coordinate 0 is (0.5 + 2^-25) + 2^-25 = 0.5 in float32 (the
        torch code's order; 0.5 + (2^-25 + 2^-25) would be 0.5 + 2^-24), which rounds to 0; coordinates 1 and 2 are
        the ties 2.5 and 1.5, which round to the even 2."""
        ops = _library()
        G, Gp = 4, 6
        out = torch.zeros(3 * Gp * Gp, dtype=torch.bool)
        tiny = 2.0 ** -25
        Ld = torch.tensor([[0.5], [2.5], [1.5]])
        Lh = torch.tensor([[tiny], [0.0], [0.0]])
        one = torch.ones(1, 1, 1, 1, dtype=torch.bool)
        ops.splat_planes(out, one, Ld, Lh, Lh.clone(), torch.tensor([0]), 1, 1, 1, G)
        k = (0, 2, 2)
        expected = torch.zeros(3, Gp, Gp, dtype=torch.bool)
        for j in range(3):  # plane j: (a, b) = (k[(j + 1) % 3], k[(j + 2) % 3]) at [b + 1, a + 1]
            expected[j, k[(j + 2) % 3] + 1, k[(j + 1) % 3] + 1] = True
        assert torch.equal(out.view(3, Gp, Gp), expected)

    def test_small_chunks_and_non_finite_maps(self, generator, axes):
        _library()
        cams = _ref_cameras(generator, 3)
        occ = torch.rand(3, 8, 8, 8, generator=generator) > 0.4
        T = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1) * 0.2
        T[:, 3, 3] = 1
        full = project_proposals(occ, T, cams, axes, 20, 1.0, native=False)
        assert torch.equal(project_proposals(occ, T, cams, axes, 20, 1.0, native=True, chunk_voxels=1), full)
        T[1, 0, 0] = float("nan")
        for native in (False, True):
            with pytest.raises(ValueError, match="finite"):
                project_proposals(occ, T, cams, axes, 20, 1.0, native=native)

    def test_operator_checks_its_arguments(self):
        ops = _library()
        G, Gp = 4, 6
        out = torch.zeros(2 * 3 * Gp * Gp, dtype=torch.bool)
        occ = torch.ones(2, 2, 3, 4, dtype=torch.bool)
        Ld, Lh, Lw = torch.zeros(3, 4), torch.zeros(3, 6), torch.zeros(3, 8)
        rows = torch.tensor([0, 1])
        ops.splat_planes(out, occ, Ld, Lh, Lw, rows, 1, 1, 1, G)
        assert bool(out.view(2, 3, Gp, Gp)[:, :, 1, 1].all())  # every point at coordinate 0 -> sample (0, 0)
        with pytest.raises(ValueError, match="distinct"):
            ops.splat_planes(out, occ, Ld, Lh, Lw, torch.tensor([1, 1]), 1, 1, 1, G)
        with pytest.raises(ValueError, match="distinct"):
            ops.splat_planes(out, occ, Ld, Lh, Lw, torch.tensor([0, 2]), 1, 1, 1, G)
        with pytest.raises(ValueError, match="Lh must be"):
            ops.splat_planes(out, occ, Ld, torch.zeros(3, 5), Lw, rows, 1, 1, 1, G)
        with pytest.raises(ValueError, match="occ must hold the 2 grids"):
            one = [x[:, :n].clone() for x, n in ((Ld, 2), (Lh, 3), (Lw, 4))]  # tables of one grid
            ops.splat_planes(out, occ[:1], *one, rows[:1], 1, 1, 1, G)
        with pytest.raises(ValueError, match="whole sets"):
            ops.splat_planes(out[:-1], occ, Ld, Lh, Lw, rows, 1, 1, 1, G)
        with pytest.raises(TypeError, match="occ must be Bool"):
            ops.splat_planes(out, occ.float(), Ld, Lh, Lw, rows, 1, 1, 1, G)
        with pytest.raises(ValueError, match=">= 1"):
            ops.splat_planes(out, occ, Ld, Lh, Lw, rows, 0, 1, 1, G)
        with pytest.raises(ValueError, match="2\\^20"):
            ops.splat_planes(out, occ, Ld, Lh, Lw, rows, 1, 1, 1, 1 << 40)


# --------------------------------------------------------------------------- score_proposals


class TestScoreProposals:
    def test_known_values(self):
        G = 4
        proj = torch.zeros(2, 3, G, G, dtype=torch.bool)
        proj[0] = True
        avg = torch.stack([torch.full((G, G), 0.25), torch.full((G, G), 0.5), torch.zeros(G, G)])
        avg[2, :2] = 1.0
        counts = torch.tensor([3, 0, 2])
        score = score_proposals(proj, avg, counts)
        # direction 1 has no members and is ignored
        assert score.tolist() == pytest.approx([0.75 + 0.5, 0.25 + 0.5])

    def test_true_shape_beats_distorted(self, generator, axes):
        masks, cams, labels, _ = _box_class(axes)
        ext, G = 1.3, 48
        avg, counts = average_masks(masks, cams, labels, axes, G, ext)
        ref = _ref_cameras(generator, 1)
        shapes = [HALF, (HALF[0] * 1.4, HALF[1], HALF[2]), (HALF[0], HALF[1] * 0.6, HALF[2]), (0.7, 0.7, 0.7)]
        occ, T = _stack_grids([_voxelise_box(ref[0], axes, h, step=1.0) for h in shapes])
        refs = ScaledOrthographic.cat([ref] * len(shapes))
        score = score_proposals(project_proposals(occ, T, refs, axes, G, ext), avg, counts)
        assert int(score.argmin()) == 0 and bool((score[1:] > score[0] + 0.01).all()), score

    def test_exceptions(self):
        with pytest.raises(ValueError, match="averages"):
            score_proposals(torch.zeros(1, 3, 4, 4), torch.zeros(3, 5, 5), torch.ones(3))
        with pytest.raises(ValueError, match="counts"):
            score_proposals(torch.zeros(1, 3, 4, 4), torch.zeros(3, 4, 4), torch.ones(2))


# --------------------------------------------------------------------------- keypoint_misses


class TestKeypointMisses:
    def test_vs_brute_force(self, generator):
        B, D, H, W, K = 3, 4, 9, 11, 15
        occ = torch.rand(B, D, H, W, generator=generator) > 0.85
        step = torch.tensor([1.0, 1.5, 0.75], dtype=torch.float64)
        T = torch.zeros(B, 4, 4, dtype=torch.float64)
        T[:, 0, 2] = step
        T[:, 1, 1] = step
        T[:, 2, 0] = step
        T[:, :3, 3] = torch.tensor([[2.0, 3.0, -5.0], [-1.0, 0.5, 0.0], [4.0, 4.0, 1.0]], dtype=torch.float64)
        T[:, 3, 3] = 1
        kp = torch.rand(B, K, 2, generator=generator) * 20 - 2
        vis = torch.rand(B, K, generator=generator) > 0.3
        got = keypoint_misses(occ, T, kp, vis)
        assert got.dtype == torch.long and got.shape == (B,)
        expected = []
        for b in range(B):
            pts = [(T[b].numpy() @ np.array([d, h, w, 1.0]))[:2] for d, h, w in occ[b].nonzero().tolist()]
            half = float(step[b]) / 2
            miss = 0
            for k in range(K):
                if not vis[b, k]:
                    continue
                x, y = kp[b, k].double().tolist()
                covered = any(abs(px - x) <= half and abs(py - y) <= half for px, py in pts)
                miss += not covered
            expected.append(miss)
        assert got.tolist() == expected
        assert max(expected) > 0 and min(expected) < int(vis.sum(-1).min())  # neither trivial case

    def test_known_columns_give_the_same_misses(self, generator):
        B, D, H, W, K = 3, 4, 9, 11, 15
        occ = torch.rand(B, D, H, W, generator=generator) > 0.85
        T = torch.zeros(B, 4, 4, dtype=torch.float64)
        T[:, 0, 2] = T[:, 1, 1] = T[:, 2, 0] = 1.0
        T[:, 3, 3] = 1
        kp = torch.rand(B, K, 2, generator=generator) * 12
        vis = torch.ones(B, K, dtype=torch.bool)
        plain = keypoint_misses(occ, T, kp, vis)
        assert torch.equal(keypoint_misses(occ, T, kp, vis, columns=occ.any(dim=1)), plain)
        assert not torch.equal(keypoint_misses(occ, T, kp, vis, columns=torch.zeros(B, H, W, dtype=torch.bool)),
                               plain)
        with pytest.raises(ValueError, match="columns"):
            keypoint_misses(occ, T, kp, vis, columns=occ.any(dim=2))

    def test_rotated_in_plane_grid(self, generator):
        # a grid turned in the image plane: columns are found through the 2x2 inverse
        c, s_ = math.cos(0.4), math.sin(0.4)
        T = torch.eye(4, dtype=torch.float64)
        T[:3, :3] = torch.tensor([[0.0, -s_, c], [0.0, c, s_], [1.0, 0.0, 0.0]], dtype=torch.float64)
        T[:2, 3] = torch.tensor([5.0, 5.0], dtype=torch.float64)
        occ = torch.zeros(1, 2, 4, 4, dtype=torch.bool)
        occ[0, 1, 2, 3] = True
        centre = (T @ torch.tensor([1.0, 2.0, 3.0, 1.0], dtype=torch.float64))[:2]
        kp = torch.stack([centre + 0.3, centre + 1.0]).float()[None]
        assert keypoint_misses(occ, T[None], kp, torch.ones(1, 2, dtype=torch.bool)).tolist() == [1]

    def test_exceptions(self):
        occ = torch.zeros(1, 2, 3, 3, dtype=torch.bool)
        T = torch.eye(4)[None].clone()
        with pytest.raises(ValueError, match="keypoints"):
            keypoint_misses(occ, T, torch.zeros(1, 2, 3), torch.ones(1, 2, dtype=torch.bool))
        with pytest.raises(ValueError, match="visible"):
            keypoint_misses(occ, T, torch.zeros(1, 2, 2), torch.ones(1, 3, dtype=torch.bool))
        T[0, 0, 0] = 1.0  # the depth index moves the image x: not aligned with the reference camera
        T[0, 0, 2] = 1.0
        with pytest.raises(ValueError, match="viewing ray"):
            keypoint_misses(occ, T, torch.zeros(1, 2, 2), torch.ones(1, 2, dtype=torch.bool))


# --------------------------------------------------------------------------- rank_proposals


class TestRankProposals:
    def test_vs_python_sort(self, generator):
        R, P = 30, 12
        scores = torch.rand(R, P, generator=generator).round(decimals=1)  # many ties
        scores[torch.rand(R, P, generator=generator) < 0.05] = float("nan")
        misses = torch.randint(0, 3, (R, P), generator=generator)
        valid = torch.rand(R, P, generator=generator) > 0.3
        valid[0] = False
        order, best = rank_proposals(scores, misses, valid)
        for r in range(R):
            def key(p, r=r):
                nan = math.isnan(float(scores[r, p]))
                return not bool(valid[r, p]), int(misses[r, p]), nan, 0.0 if nan else float(scores[r, p]), p

            assert order[r].tolist() == sorted(range(P), key=key)
            assert int(best[r]) == (order[r, 0].item() if bool(valid[r].any()) else -1)
        assert int(best[0]) == -1

    def test_exceptions(self):
        with pytest.raises(ValueError, match="misses"):
            rank_proposals(torch.zeros(2, 3), torch.zeros(2, 2), torch.ones(2, 3, dtype=torch.bool))


# --------------------------------------------------------------------------- device


@requires_cuda
def test_cuda_matches_cpu(generator, axes):
    masks, cams, labels, _ = _box_class(axes)
    avg_c, cnt_c = average_masks(masks, cams, labels, axes, 32, 1.3)
    avg_g, cnt_g = average_masks(masks.cuda(), cams.to("cuda"), labels.cuda(), axes.cuda(), 32, 1.3)
    assert avg_g.is_cuda
    torch.testing.assert_close(avg_g.cpu(), avg_c, atol=1e-4, rtol=0)
    torch.testing.assert_close(cnt_g.cpu(), cnt_c)
    ref = _ref_cameras(generator, 2)
    occ, T = _stack_grids([_voxelise_box(ref[b], axes, HALF, step=1.5) for b in range(2)])
    p_c = project_proposals(occ, T, ref, axes, 32, 1.3)
    p_g = project_proposals(occ.cuda(), T.cuda(), ref.to("cuda"), axes.cuda(), 32, 1.3)
    assert p_g.is_cuda and int((p_g.cpu() != p_c).sum()) <= 2
    s_c = score_proposals(p_c, avg_c, cnt_c)
    s_g = score_proposals(p_g, avg_g, cnt_g)
    torch.testing.assert_close(s_g.cpu(), s_c, atol=1e-3, rtol=0)
    kp = torch.rand(2, 6, 2, generator=generator) * 60
    vis = torch.ones(2, 6, dtype=torch.bool)
    want = keypoint_misses(occ, T, kp, vis).tolist()
    assert keypoint_misses(occ.cuda(), T.cuda(), kp.cuda(), vis.cuda()).cpu().tolist() == want
    o_c, b_c = rank_proposals(s_c[None], torch.zeros(1, 2, dtype=torch.long), torch.ones(1, 2, dtype=torch.bool))
    o_g, b_g = rank_proposals(s_g[None], torch.zeros(1, 2, dtype=torch.long, device="cuda"),
                              torch.ones(1, 2, dtype=torch.bool, device="cuda"))
    assert o_g.is_cuda and o_g.cpu().tolist() == o_c.tolist()


class TestVoteProposals:
    def test_vote_against_a_loop_over_voxels(self, generator):
        """The majority vote on the common depth grid equals a plain loop: every voxel's camera depth read
        in each proposal at its nearest depth index; a column the vote empties keeps the first proposal's."""
        from carvi_torch.select import vote_proposals

        B, D, H, W = 5, 7, 3, 4
        occ = torch.rand(B, D, H, W, generator=generator) < 0.5
        occ[3, :, 0, 0] = False
        occ[3, 6, 0, 0] = True  # the first voted proposal of row 1 fills a column the others leave empty
        occ[[1, 2], :, 0, 0] = False
        T = torch.eye(4, dtype=torch.float64).repeat(B, 1, 1)
        T[:, 0, 2], T[:, 1, 1] = 2.0, 2.0
        T[:, 2, 0] = torch.tensor([1.0, 0.5, 1.5, 2.0, 0.8], dtype=torch.float64)
        T[:, 2, 3] = torch.tensor([0.0, 1.0, -2.0, 3.0, 0.4], dtype=torch.float64)
        rows = torch.tensor([[0, 1, 2, 4], [3, 1, 2, -1]])
        out, T_out = vote_proposals(occ, T, rows)
        for r in range(2):
            used = [int(b) for b in rows[r] if b >= 0]
            ends = [float(T[b, 2, 3] + T[b, 2, 0] * k) for b in used for k in (0, D - 1)]
            lo, hi = min(ends), max(ends)
            assert float(T_out[r, 2, 3]) == pytest.approx(lo)
            assert float(T_out[r, 2, 0]) == pytest.approx((hi - lo) / (D - 1))
            zs = [lo + (hi - lo) * d / (D - 1) for d in range(D)]

            def read(b, z, h, w):
                k = round((z - float(T[b, 2, 3])) / float(T[b, 2, 0]))
                return 0 <= k < D and bool(occ[b, k, h, w])

            for h in range(H):
                for w in range(W):
                    col = [2 * sum(read(b, z, h, w) for b in used) > len(used) for z in zs]
                    if not any(col):  # the vote leaves the column empty: the first proposal's column
                        col = [read(used[0], z, h, w) for z in zs]
                    assert out[r, :, h, w].tolist() == col, (r, h, w)
        assert bool(out[1, :, 0, 0].any())
        # one proposal: itself, voxel for voxel
        one, T_one = vote_proposals(occ, T, torch.tensor([[2], [4]]))
        assert torch.equal(one, occ[[2, 4]]) and torch.allclose(T_one, T[[2, 4]])
