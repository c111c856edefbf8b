"""Tests of carvi_torch.surrogates: PCA axes, clusters, triplet sampling, symmetric surrogates."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.spatial.transform import Rotation

from carvi_torch.cameras import ScaledOrthographic, random_rotations
from carvi_torch.surrogates import (
    object_share,
    Clusters,
    Triplets,
    cluster_by_direction,
    cluster_weights,
    members_per_object,
    principal_components,
    principal_directions,
    sample_triplets,
    symmetric_surrogates,
    symmetry_axis,
)
from conftest import requires_cuda


def _anisotropic_shape(generator, k=40, sigmas=(3.0, 1.5, 0.5)):
    """Random points with distinct variances along the axes of a random rotation Q (rows)."""
    Q = random_rotations(1, generator, dtype=torch.float64)[0]
    X = torch.randn(k, 3, generator=generator, dtype=torch.float64) * torch.tensor(sigmas, dtype=torch.float64)
    return X @ Q + torch.tensor([0.3, -2.0, 1.0], dtype=torch.float64), Q


# --------------------------------------------------------------------------- principal_directions


class TestPrincipalDirections:
    def test_smoke_shapes(self, generator):
        S, _ = _anisotropic_shape(generator)
        axes = principal_directions(S.float())
        assert axes.shape == (3, 3) and axes.dtype == torch.float32

    def test_vs_numpy_eigh(self, generator):
        S, _ = _anisotropic_shape(generator)
        axes, var = principal_components(S)
        X = S.numpy() - S.numpy().mean(axis=0)
        w, V = np.linalg.eigh(np.cov(X.T, bias=True))
        w, V = w[::-1], V[:, ::-1]
        np.testing.assert_allclose(var.numpy(), w, rtol=1e-10, atol=1e-12)
        # same axes up to sign
        np.testing.assert_allclose(np.abs(np.sum(axes.numpy() * V.T, axis=1)), 1.0, atol=1e-10)

    def test_orthonormal_right_handed_sign_convention(self, generator):
        for _ in range(5):
            S, _ = _anisotropic_shape(generator)
            axes = principal_directions(S)
            torch.testing.assert_close(axes @ axes.T, torch.eye(3, dtype=S.dtype), atol=1e-10, rtol=0)
            assert torch.linalg.det(axes) == pytest.approx(1.0, abs=1e-10)
            for row in axes[:2]:
                assert row[row.abs().argmax()] > 0

    def test_recovers_generating_axes(self, generator):
        S, Q = _anisotropic_shape(generator, k=4000)
        axes = principal_directions(S)
        assert torch.all((axes * Q).sum(-1).abs() > 0.99)

    def test_nan_rows_ignored(self, generator):
        S, _ = _anisotropic_shape(generator)
        S_nan = S.clone()
        S_nan[[2, 7, 11]] = float("nan")
        S_nan[5, 1] = float("nan")
        keep = torch.ones(len(S), dtype=torch.bool)
        keep[[2, 5, 7, 11]] = False
        torch.testing.assert_close(principal_directions(S_nan), principal_directions(S[keep]))

    def test_rotation_equivariance(self, generator):
        S, _ = _anisotropic_shape(generator)
        Q = random_rotations(1, generator, dtype=torch.float64)[0]
        a1 = principal_directions(S)
        a2 = principal_directions(S @ Q.T)
        assert torch.all(((a1 @ Q.T) * a2).sum(-1).abs() > 1 - 1e-9)

    def test_exceptions(self):
        with pytest.raises(ValueError, match="S must be"):
            principal_directions(torch.zeros(5, 2))
        with pytest.raises(ValueError, match="at least 3 finite rows"):
            principal_directions(torch.tensor([[0.0, 0, 0], [1, 0, 0], [float("nan"), 0, 0]]))

    def test_real_cad_cars(self, shared_data):
        # PASCAL3D+ frame: front towards -y, +z up: cars are longest along y, then x, then z.
        for f in sorted((shared_data / "pascal3d_cad").glob("car*.npz")):
            S = torch.tensor(np.load(f)["keypoints"])
            axes = principal_directions(S)
            assert abs(float(axes[0, 1])) > 0.98, f.name
            assert abs(float(axes[1, 0])) > 0.98, f.name
            assert abs(float(axes[2, 2])) > 0.98, f.name


# --------------------------------------------------------------------------- cluster_by_direction


def _brute_labels(view_dirs, axes, thr):
    out = []
    for v in view_dirs.double().tolist():
        v = np.asarray(v) / np.linalg.norm(v)
        lab = -1
        for j in range(3):
            a = axes[j].double().numpy()
            ang = math.degrees(math.acos(min(1.0, abs(float(v @ a)) / np.linalg.norm(a))))
            if ang < thr:
                lab = j
        out.append(lab)
    return torch.tensor(out)


def _tilted(axes, j, k, deg, sign=1.0):
    """Unit direction ``deg`` degrees from ``sign * axes[j]`` towards ``axes[k]``."""
    t = math.radians(deg)
    return sign * math.cos(t) * axes[j] + math.sin(t) * axes[k]


class TestClusterByDirection:
    def test_vs_brute_force(self, generator):
        axes = random_rotations(1, generator)[0]
        # views concentrated near the axes so all clusters fill
        base = axes[torch.randint(0, 3, (300,), generator=generator)]
        base = base * torch.where(torch.rand(300, 1, generator=generator) < 0.5, -1.0, 1.0)
        v = base + 0.3 * torch.randn(300, 3, generator=generator)
        for thr in (5.0, 15.0, 30.0):
            cl = cluster_by_direction(v, axes, threshold_deg=thr, max_threshold_deg=max(thr, 45.0), min_second=0)
            assert isinstance(cl, Clusters)
            assert cl.threshold_deg == thr and cl.log == []
            torch.testing.assert_close(cl.labels, _brute_labels(v, axes, thr))
            torch.testing.assert_close(cl.sizes, torch.bincount(cl.labels[cl.labels >= 0], minlength=3))
            assert cl.labels.dtype == torch.long and cl.angle_deg.shape == (300,)

    def test_front_and_back(self):
        axes = torch.eye(3)
        v = torch.stack([_tilted(axes, 0, 1, 10), _tilted(axes, 0, 1, 10, -1.0), _tilted(axes, 2, 0, 14, -1.0)])
        cl = cluster_by_direction(v, axes, min_second=0)
        assert cl.labels.tolist() == [0, 0, 2]

    def test_widening_exactly_when_needed(self):
        axes = random_rotations(1, torch.Generator().manual_seed(3))[0]
        # axis 0: 5 tight members; axis 1: members at 17 and 23 degrees; axis 2: none
        v = [_tilted(axes, 0, 1, d) for d in (1, 2, 3, 4, 5)] + [_tilted(axes, 1, 2, 17), _tilted(axes, 1, 0, 23, -1.0)]
        v = torch.stack(v)
        cl = cluster_by_direction(v, axes, threshold_deg=15.0, min_second=2)
        # 15: sizes (5,0,0) -> widen; 20: (5,1,0) -> widen; 25: (5,2,0) -> stop
        assert cl.threshold_deg == 25.0
        assert len(cl.log) == 2 and all(m.startswith("widened") for m in cl.log)
        assert "15 to 20" in cl.log[0] and "20 to 25" in cl.log[1]
        assert cl.sizes.tolist() == [5, 2, 0]
        torch.testing.assert_close(cl.labels, _brute_labels(v, axes, 25.0))
        # every threshold tried before the final one had a too-small second cluster
        for thr in (15.0, 20.0):
            lab = _brute_labels(v, axes, thr)
            sizes = torch.bincount(lab[lab >= 0], minlength=3)
            assert int(sizes.sort().values[1]) < 2
        # no widening when the second-smallest cluster is large enough (one empty cluster is fine)
        cl2 = cluster_by_direction(v, axes, threshold_deg=25.0, min_second=2)
        assert cl2.log == [] and cl2.threshold_deg == 25.0
        cl3 = cluster_by_direction(v, axes, threshold_deg=15.0, min_second=1)
        assert cl3.threshold_deg == 20.0 and len(cl3.log) == 1

    def test_widening_counts_objects_when_given(self):
        """With physical objects, a cluster holding views of one object counts once: the threshold widens
        until the second-smallest cluster holds two objects (brute-force count at every threshold)."""
        axes = random_rotations(1, torch.Generator().manual_seed(3))[0]
        # axis 0: 5 views of objects 0-4; axis 1: two views of object 7 at 3 and 6 degrees, object 8 at 23
        v = [_tilted(axes, 0, 1, d) for d in (1, 2, 3, 4, 5)] + [_tilted(axes, 1, 2, 3), _tilted(axes, 1, 2, 6),
                                                                  _tilted(axes, 1, 0, 23, -1.0)]
        v, groups = torch.stack(v), torch.tensor([0, 1, 2, 3, 4, 7, 7, 8])
        assert cluster_by_direction(v, axes, threshold_deg=15.0, min_second=2).threshold_deg == 15.0
        cl = cluster_by_direction(v, axes, threshold_deg=15.0, min_second=2, groups=groups)
        assert cl.threshold_deg == 25.0 and cl.sizes.tolist() == [5, 3, 0]
        assert "1 < 2 objects" in cl.log[0]
        for thr, enough in ((15.0, False), (20.0, False), (25.0, True)):
            lab = _brute_labels(v, axes, thr)
            objects = [len({int(g) for g, l in zip(groups, lab) if l == j}) for j in range(3)]
            assert (sorted(objects)[1] >= 2) == enough, (thr, objects)
        with pytest.raises(ValueError, match="groups"):
            cluster_by_direction(v, axes, groups=groups[:3])

    def test_widening_stops_at_maximum(self):
        axes = torch.eye(3)
        v = torch.stack([_tilted(axes, 0, 1, d) for d in (1, 2, 3)])
        cl = cluster_by_direction(v, axes, threshold_deg=15.0, widen_step_deg=10.0, max_threshold_deg=40.0)
        # 15 -> 25 -> 35 -> 40 (clipped), then a final note
        assert cl.threshold_deg == 40.0
        assert sum(m.startswith("widened") for m in cl.log) == 3
        assert "35 to 40" in cl.log[2] and "maximum" in cl.log[-1]
        assert cl.sizes.tolist() == [3, 0, 0]

    def test_nan_view_joins_nothing(self):
        v = torch.tensor([[0.0, 0, 1], [float("nan"), 0, 0]])
        assert cluster_by_direction(v, torch.eye(3), min_second=0).labels.tolist() == [2, -1]

    def test_exceptions(self):
        with pytest.raises(ValueError, match="view_dirs"):
            cluster_by_direction(torch.zeros(3, 2), torch.eye(3))
        with pytest.raises(ValueError, match="axes"):
            cluster_by_direction(torch.zeros(3, 3), torch.eye(2))
        with pytest.raises(ValueError, match="threshold_deg"):
            cluster_by_direction(torch.zeros(3, 3), torch.eye(3), threshold_deg=0.0)
        with pytest.raises(ValueError, match="max_threshold_deg"):
            cluster_by_direction(torch.zeros(3, 3), torch.eye(3), max_threshold_deg=50.0)
        with pytest.raises(ValueError, match="widen_step_deg"):
            cluster_by_direction(torch.zeros(3, 3), torch.eye(3), widen_step_deg=-1.0)


# --------------------------------------------------------------------------- sample_triplets


def _random_class(generator, n=60):
    labels = torch.randint(-1, 3, (n,), generator=generator)
    object_ids = torch.randint(0, n // 3, (n,), generator=generator)  # ~3 views per physical object
    return labels, object_ids


def _check_invariants(t: Triplets, labels, object_ids, references):
    R, P, _ = t.surrogates.shape
    assert t.valid.shape == (R, P) and t.clusters.shape == (R, P, 2)
    torch.testing.assert_close(t.valid, (t.surrogates >= 0).all(-1))
    assert bool(((t.surrogates >= 0) == t.valid[..., None]).all())
    for r in range(R):
        ref = int(references[r])
        seen = set()
        for p in range(P):
            if not t.valid[r, p]:
                continue
            a, b = t.surrogates[r, p].tolist()
            assert ref not in (a, b)
            assert object_ids[a] != object_ids[ref] and object_ids[b] != object_ids[ref]
            ca, cb = int(labels[a]), int(labels[b])
            assert ca >= 0 and cb >= 0 and ca != cb
            assert [ca, cb] == t.clusters[r, p].tolist()
            pair = frozenset((a, b))
            assert pair not in seen
            seen.add(pair)
        if ref in t.reasons:
            assert not bool(t.valid[r].any())


class TestSampleTriplets:
    def test_invariants_random_class(self, generator):
        labels, object_ids = _random_class(generator)
        refs = torch.arange(60)
        t = sample_triplets(labels, object_ids, refs, 20, generator)
        _check_invariants(t, labels, object_ids, refs)
        assert int(t.valid.sum()) > 0.8 * 60 * 20 * 0.5  # most proposals survive
        # some duplicates among small clusters are removed, never all
        for r in range(60):
            if int(refs[r]) not in t.reasons:
                assert bool(t.valid[r].any())

    def test_deterministic_under_seed(self, generator):
        labels, object_ids = _random_class(generator)
        refs = torch.arange(0, 60, 3)
        a = sample_triplets(labels, object_ids, refs, 20, torch.Generator().manual_seed(7))
        b = sample_triplets(labels, object_ids, refs, 20, torch.Generator().manual_seed(7))
        c = sample_triplets(labels, object_ids, refs, 20, torch.Generator().manual_seed(8))
        torch.testing.assert_close(a.surrogates, b.surrogates)
        assert a.reasons == b.reasons
        assert not torch.equal(a.surrogates, c.surrogates)

    def test_chunked_member_weights_give_the_same_draws(self, generator, monkeypatch):
        """The member weights are built a chunk of references at a time: same triplets, and the
        same as the reference x instance matrix of the stated rule (brute force)."""
        import carvi_torch.surrogates as S

        labels, object_ids = _random_class(generator)
        object_ids[::4] = object_ids[1::4][: len(object_ids[::4])]  # some physical objects seen twice
        refs = torch.arange(len(labels))
        whole = sample_triplets(labels, object_ids, refs, 12, torch.Generator().manual_seed(5))
        monkeypatch.setattr(S, "_TRIPLET_CHUNK_ELEMS", 3 * len(labels) * 7)  # chunks of 7 references
        chunked = sample_triplets(labels, object_ids, refs, 12, torch.Generator().manual_seed(5))
        assert torch.equal(whole.surrogates, chunked.surrogates) and whole.reasons == chunked.reasons
        # brute force: eligible members counted pair by pair
        w, elig = cluster_weights(labels, object_ids, refs)
        brute = [[sum(int(labels[m]) == j and int(object_ids[m]) != int(object_ids[r]) for m in range(len(labels)))
                  for j in range(3)] for r in refs.tolist()]
        assert elig.tolist() == brute

    def test_object_share_vs_brute_force(self, generator):
        labels = torch.randint(-1, 3, (40,), generator=generator)
        objects = torch.randint(0, 6, (40,), generator=generator)
        lab, obj = labels.tolist(), objects.tolist()
        brute = [1.0 if lab[i] < 0 else 1.0 / sum(lab[k] == lab[i] and obj[k] == obj[i] for k in range(40))
                 for i in range(40)]
        torch.testing.assert_close(object_share(labels, objects), torch.tensor(brute), atol=1e-7, rtol=0)
        assert torch.equal(object_share(labels, torch.arange(40)), torch.ones(40))  # no repeated object: all 1

    def test_members_per_object_vs_brute_force(self, generator):
        """The one count behind the weights, shares and object counts: members of cluster j viewing object g,
        counted by a loop over every (object, cluster) pair; the objects per cluster follow from it."""
        from carvi_torch.surrogates import _objects_per_cluster

        labels = torch.randint(-1, 3, (30,), generator=generator)
        objects = torch.randint(0, 8, (30,), generator=generator) * 5 - 7  # sparse, some negative ids
        counts, group = members_per_object(labels, objects)
        distinct = sorted(set(objects.tolist()))
        lab, obj = labels.tolist(), objects.tolist()
        brute = [[sum(lab[n] == j and obj[n] == g for n in range(30)) for j in range(3)] for g in distinct]
        assert counts.tolist() == brute
        assert [distinct[k] for k in group.tolist()] == obj
        seen = [len({obj[n] for n in range(30) if lab[n] == j}) for j in range(3)]
        assert _objects_per_cluster(labels, objects).tolist() == seen
        assert _objects_per_cluster(torch.full((4,), -1), torch.arange(4)).tolist() == [0, 0, 0]

    def test_cluster_weights_stated_rule(self):
        labels = torch.tensor([0] * 30 + [1] * 10 + [2] * 5 + [-1])
        object_ids = torch.arange(46)
        object_ids[40:45] = 99  # cluster 2 is one physical object
        refs = torch.tensor([45, 0, 40])
        w, elig = cluster_weights(labels, object_ids, refs)
        assert elig.tolist() == [[30, 10, 5], [29, 10, 5], [30, 10, 0]]
        p = torch.tensor([30, 10, 5], dtype=torch.float64) / 45
        expected = torch.stack([
            p.clamp_min(0.2),
            torch.tensor([0.1, float(p[1]), 0.2], dtype=torch.float64),  # own cluster 0
            torch.tensor([float(p[0]), float(p[1]), 0.0], dtype=torch.float64),  # cluster 2 all share its id
        ])
        torch.testing.assert_close(w, expected)

    @pytest.mark.parametrize("ref_label", [-1, 0])
    def test_cluster_frequencies(self, ref_label):
        labels = torch.tensor([0] * 30 + [1] * 10 + [2] * 5 + [-1])
        object_ids = torch.arange(46)
        ref = 45 if ref_label == -1 else 0
        draws = 20000
        g = torch.Generator().manual_seed(11)
        # one proposal per (repeated) reference: no duplicate removal biases the counts
        t = sample_triplets(labels, object_ids, torch.full((draws,), ref), 1, g)
        assert bool(t.valid.all())
        w = cluster_weights(labels, object_ids, torch.tensor([ref]))[0][0].tolist()
        W = sum(w)
        pairs = [(0, 1), (0, 2), (1, 2)]
        # successive sampling without replacement
        expected = np.array([w[i] / W * w[j] / (W - w[i]) + w[j] / W * w[i] / (W - w[j]) for i, j in pairs])
        got = t.clusters[:, 0].sort(dim=-1).values
        observed = np.array([int(((got[:, 0] == i) & (got[:, 1] == j)).sum()) for i, j in pairs])
        chi2 = stats.chisquare(observed, expected * draws)
        assert chi2.pvalue > 1e-3, (observed, expected * draws)
        # members are uniform within a cluster (cluster 0 has 30 eligible, or 29 without the reference)
        sur = t.surrogates[:, 0][t.clusters[:, 0] == 0]
        members = [n for n in range(30) if n != ref]
        counts = np.array([int((sur == n).sum()) for n in members])
        assert stats.chisquare(counts).pvalue > 1e-3
        assert ref not in sur.tolist()

    def test_no_valid_surrogate_reason(self, generator):
        labels = torch.tensor([0, 0, 1, 1, 2, 2, -1])
        # instance 6 (unclustered) is the same physical object as everything in clusters 1 and 2
        object_ids = torch.tensor([0, 1, 5, 5, 5, 5, 5])
        t = sample_triplets(labels, object_ids, torch.tensor([6, 0]), 5, generator)
        assert 6 in t.reasons and "[2, 0, 0]" in t.reasons[6]
        assert not bool(t.valid[0].any())
        assert bool(t.valid[1].any()) and 0 not in t.reasons
        _check_invariants(t, labels, object_ids, torch.tensor([6, 0]))

    def test_empty_clusters(self, generator):
        # one empty direction: every proposal uses the two others
        labels = torch.tensor([0] * 4 + [2] * 4 + [-1] * 2)
        object_ids = torch.arange(10)
        refs = torch.arange(10)
        t = sample_triplets(labels, object_ids, refs, 20, generator)
        _check_invariants(t, labels, object_ids, refs)
        assert t.reasons == {}
        assert set(t.clusters[t.valid].flatten().tolist()) == {0, 2}
        # with 4 x 4 pairs at most 16 distinct pairs: duplicates among 20 proposals are removed
        assert int(t.valid[8].sum()) <= 16
        # two empty directions: nobody gets a proposal, everybody a reason
        labels2 = torch.tensor([1] * 6 + [-1] * 2)
        t2 = sample_triplets(labels2, torch.arange(8), torch.arange(8), 20, generator)
        assert not bool(t2.valid.any()) and sorted(t2.reasons) == list(range(8))
        assert bool((t2.surrogates == -1).all()) and bool((t2.clusters == -1).all())
        # nothing clustered at all
        t3 = sample_triplets(torch.full((4,), -1), torch.arange(4), torch.arange(4), 3, generator)
        assert sorted(t3.reasons) == [0, 1, 2, 3]

    def test_no_references(self, generator):
        t = sample_triplets(torch.tensor([0, 1, 2]), torch.arange(3), torch.zeros(0, dtype=torch.long), 5, generator)
        assert t.surrogates.shape == (0, 5, 2) and t.reasons == {}

    def test_exceptions(self, generator):
        labels, ids = torch.tensor([0, 1, 2]), torch.arange(3)
        with pytest.raises(ValueError, match="labels must lie"):
            sample_triplets(torch.tensor([0, 3, 1]), ids, torch.tensor([0]), 2, generator)
        with pytest.raises(ValueError, match="object_ids"):
            sample_triplets(labels, torch.arange(4), torch.tensor([0]), 2, generator)
        with pytest.raises(ValueError, match="references"):
            sample_triplets(labels, ids, torch.tensor([3]), 2, generator)
        with pytest.raises(ValueError, match="proposals"):
            sample_triplets(labels, ids, torch.tensor([0]), 0, generator)
        with pytest.raises(ValueError, match="integers"):
            sample_triplets(labels.float(), ids, torch.tensor([0]), 2, generator)

    @requires_cuda
    def test_cuda_matches_cpu(self):
        labels, ids = _random_class(torch.Generator().manual_seed(1))
        refs = torch.arange(60)
        a = sample_triplets(labels, ids, refs, 20, torch.Generator().manual_seed(2))
        b = sample_triplets(labels.cuda(), ids.cuda(), refs.cuda(), 20, torch.Generator().manual_seed(2))
        assert b.surrogates.is_cuda
        torch.testing.assert_close(a.surrogates, b.surrogates.cpu())
        c = sample_triplets(labels.cuda(), ids.cuda(), refs.cuda(), 20, torch.Generator("cuda").manual_seed(2))
        _check_invariants(
            Triplets(c.surrogates.cpu(), c.valid.cpu(), c.reasons, c.clusters.cpu()), labels, ids, refs
        )


# --------------------------------------------------------------------------- symmetric surrogates


class TestSymmetry:
    def test_symmetry_axis_elongated_and_flat(self, generator):
        Q = random_rotations(1, generator, dtype=torch.float64)[0]
        ang = torch.rand(200, generator=generator, dtype=torch.float64) * 2 * math.pi
        h = torch.rand(200, generator=generator, dtype=torch.float64) * 2 - 1
        ring = torch.stack([torch.cos(ang), torch.sin(ang), torch.zeros_like(ang)], -1)
        bottle = ring * 0.3 + h[:, None] * torch.tensor([0, 0, 2.0], dtype=torch.float64)
        table = ring * torch.rand(200, 1, generator=generator, dtype=torch.float64) + h[:, None] * torch.tensor(
            [0, 0, 0.1], dtype=torch.float64
        )
        for S in (bottle, table):
            axis = symmetry_axis(S @ Q.T)
            assert abs(float(axis @ Q[:, 2])) > 0.99  # Q maps z to Q[:, 2]
            assert float(axis.norm()) == pytest.approx(1.0)

    def test_explicit_choice(self, generator):
        S, _ = _anisotropic_shape(generator)
        for j in range(3):
            torch.testing.assert_close(symmetry_axis(S, choice=j), principal_directions(S)[j])
        with pytest.raises(ValueError, match="choice"):
            symmetry_axis(S, choice=3)

    def test_real_cad_bottles(self, shared_data):
        for f in sorted((shared_data / "pascal3d_cad").glob("bottle*.npz")):
            axis = symmetry_axis(torch.tensor(np.load(f)["keypoints"]))
            assert abs(float(axis[2])) > 0.98, f.name  # bottles stand along +z

    @pytest.mark.parametrize("step", [90.0, 45.0, 120.0])
    def test_symmetric_surrogates_vs_scipy(self, generator, step):
        R0 = random_rotations(1, generator, dtype=torch.float64)
        f64 = dict(dtype=torch.float64)
        cam = ScaledOrthographic(R0, torch.tensor([3.0], **f64), torch.tensor([[10.0, -4.0]], **f64))
        axis = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
        out = symmetric_surrogates(cam, axis, step)
        n = int(round(360 / step))
        assert len(out) == n - 1
        unit = axis.numpy() / np.linalg.norm(axis.numpy())
        for k in range(1, n):
            rot = Rotation.from_rotvec(unit * math.radians(k * step)).as_matrix()
            np.testing.assert_allclose(out.R[k - 1].numpy(), R0[0].numpy() @ rot, atol=1e-10)
        torch.testing.assert_close(out.s, cam.s.expand(n - 1))
        torch.testing.assert_close(out.t, cam.t.expand(n - 1, 2))
        assert torch.allclose(torch.linalg.det(out.R), torch.ones(n - 1, dtype=torch.float64))
        # points on the axis project where the reference camera sees them
        X = torch.stack([axis * 0.7, -axis * 2.0])
        torch.testing.assert_close(out.project(X), cam.project(X).expand(n - 1, 2, 2))

    def test_symmetric_surrogates_with_centre(self, generator):
        R0 = random_rotations(1, generator)
        cam = ScaledOrthographic(R0, torch.tensor([2.0]), torch.tensor([[5.0, 6.0]]))
        axis, c = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, -2.0, 0.5])
        out = symmetric_surrogates(cam, axis, 90.0, centre=c)
        # points on the axis line through c are fixed; others rotate about it
        X = torch.stack([c, c + 3 * axis])
        torch.testing.assert_close(out.project(X), cam.project(X).expand(3, 2, 2), atol=1e-5, rtol=0)
        P = torch.tensor([[2.0, -2.0, 0.5]])  # one unit from the axis along +x
        rotated = torch.tensor([[1.0, -1.0, 0.5]])  # P turned by +90 degrees about z through c
        torch.testing.assert_close(out[0].project(P), cam.project(rotated), atol=1e-5, rtol=0)

    def test_exceptions(self):
        cam = ScaledOrthographic(torch.eye(3)[None], torch.ones(1), torch.zeros(1, 2))
        with pytest.raises(ValueError, match="step_deg"):
            symmetric_surrogates(cam, torch.tensor([0.0, 0, 1]), 70.0)
        with pytest.raises(ValueError, match="step_deg"):
            symmetric_surrogates(cam, torch.tensor([0.0, 0, 1]), 360.0)
        with pytest.raises(ValueError, match="axis"):
            symmetric_surrogates(cam, torch.zeros(3), 90.0)
        with pytest.raises(ValueError, match="non-empty"):
            symmetric_surrogates(cam[0:0], torch.tensor([0.0, 0, 1]))

    def test_axis_in_image_plane(self, generator):
        from carvi_torch.cameras import random_rotations
        from carvi_torch.surrogates import axis_in_image_plane

        cams = ScaledOrthographic(random_rotations(6, generator), torch.ones(6), torch.zeros(6, 2))
        axis = torch.tensor([0.3, -0.2, 0.9])
        out = axis_in_image_plane(cams, axis)
        in_cam = (cams.R @ out.unsqueeze(-1)).squeeze(-1)
        torch.testing.assert_close(in_cam[:, 2], torch.zeros(6), atol=1e-6, rtol=0)  # no depth component
        torch.testing.assert_close(out.norm(dim=-1), torch.ones(6))
        proj = (cams.R[:, :2] @ axis)  # same direction in the image as the original axis
        cos = (in_cam[:, :2] * proj).sum(-1) / proj.norm(dim=-1)
        torch.testing.assert_close(cos, torch.ones(6), atol=1e-5, rtol=0)

    def test_per_reference_axes(self, generator):
        from carvi_torch.cameras import random_rotations

        cams = ScaledOrthographic(random_rotations(3, generator), torch.ones(3), torch.zeros(3, 2))
        axes = torch.nn.functional.normalize(torch.randn(3, 3, generator=generator), dim=-1)
        out = symmetric_surrogates(cams, axes, 90.0)
        for i in range(3):
            one = symmetric_surrogates(cams[i:i + 1], axes[i], 90.0)
            torch.testing.assert_close(out.R[3 * i:3 * i + 3], one.R)

    def test_planar_keypoints(self):
        """Coplanar keypoints (a bottle's silhouette points in the x-z plane): the axis lies in the plane."""
        S = torch.tensor([[0, 0, 2.0], [0.3, 0, 1.0], [-0.3, 0, 1.0], [0.5, 0, -1.5], [-0.5, 0, -1.5], [0, 0, -2.0]])
        assert symmetry_axis(S).abs().argmax() == 2  # the long in-plane axis, not the plane normal (y)
        wide = S * torch.tensor([4.0, 1.0, 0.5])  # wider than tall: 'up' decides
        assert symmetry_axis(wide, up=torch.tensor([0.1, 0.0, -1.0])).abs().argmax() == 2
        assert symmetry_axis(wide).abs().argmax() == 0

    def test_axis_through_silhouettes(self, generator):
        """Each reference's rotation centre moves in its image plane onto its silhouette's centroid (against
        scipy's centre of mass); the half-turned camera then mirrors the silhouette about its own middle."""
        from scipy import ndimage

        from carvi_torch.cameras import random_rotations
        from carvi_torch.surrogates import axis_in_image_plane, axis_through_silhouettes

        f64 = dict(dtype=torch.float64)
        cams = ScaledOrthographic(random_rotations(3, generator, dtype=torch.float64),
                                  torch.tensor([2.0, 3.0, 1.5], **f64),
                                  torch.tensor([[20.0, 18.0], [25.0, 22.0], [30.0, 15.0]], **f64))
        masks = torch.zeros(3, 40, 50, dtype=torch.bool)
        masks[0, 5:30, 10:17] = True
        masks[1, 12:35, 30:41] = True
        masks[2, 3:9, 4:44] = True
        masks[2, 20:22, 20:23] = True  # not symmetric: the centroid still
        c = torch.tensor([0.4, -0.3, 0.2], **f64)
        out = axis_through_silhouettes(cams, masks, c)
        com = torch.tensor([ndimage.center_of_mass(m.numpy())[::-1] for m in masks], **f64)  # (x, y)
        seen = cams.s[:, None] * (cams.R[:, :2] @ out[..., None])[..., 0] + cams.t
        torch.testing.assert_close(seen, com)
        torch.testing.assert_close((cams.R[:, 2] * (out - c)).sum(-1), torch.zeros(3, **f64))  # same depth
        # the image's vertical through the centroid as the axis: half a turn mirrors x about the centroid
        axis = axis_in_image_plane(cams, cams.R[0, 1])  # camera 0's vertical, turned into each image plane
        assert float((axis[0] - cams.R[0, 1]).abs().max()) < 1e-12
        for i in range(3):
            half = symmetric_surrogates(cams[i:i + 1], cams.R[i, 1], 180.0, centre=out[i])
            X = out[i] + 5.0 * cams.R[i, 0] + 2.0 * cams.R[i, 1] + 4.0 * cams.R[i, 2]
            u_ref, u_half = cams[i:i + 1].project(X[None])[0, 0], half.project(X[None])[0, 0]
            torch.testing.assert_close(u_half[0] - com[i, 0], -(u_ref[0] - com[i, 0]))
            torch.testing.assert_close(u_half[1], u_ref[1])
        # per-reference centres: each reference as if alone
        both = symmetric_surrogates(cams, axis, 90.0, centre=out)
        for i in range(3):
            one = symmetric_surrogates(cams[i:i + 1], axis[i], 90.0, centre=out[i])
            torch.testing.assert_close(both.t[3 * i:3 * i + 3], one.t)
        empty = axis_through_silhouettes(cams[:1], torch.zeros(1, 40, 50, dtype=torch.bool), c)
        torch.testing.assert_close(empty[0], c)

    def test_batched_equals_one_by_one(self, generator):
        from carvi_torch.cameras import random_rotations

        cams = ScaledOrthographic(random_rotations(4, generator), torch.rand(4, generator=generator) + 1,
                                  torch.rand(4, 2, generator=generator) * 50)
        axis, c = torch.tensor([0.2, 0.1, 1.0]), torch.tensor([0.3, -0.2, 0.1])
        out = symmetric_surrogates(cams, axis, 45.0, centre=c)
        assert len(out) == 4 * 7
        for i in range(4):
            one = symmetric_surrogates(cams[i:i + 1], axis, 45.0, centre=c)
            torch.testing.assert_close(out.R[7 * i:7 * (i + 1)], one.R)
            torch.testing.assert_close(out.t[7 * i:7 * (i + 1)], one.t)
