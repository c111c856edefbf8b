"""Tests of carvi_torch.evaluation.studies against independent references (brute force, loops, scipy)."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from carvi_torch.evaluation.studies import (chamfer_matrix, k_medoids, load_proposals, medoid_cost, normalise_points,
                                 order_clusters_by_size, ranking_curves, sample_points)


def _dist(x: torch.Tensor) -> torch.Tensor:
    return torch.cdist(x.double(), x.double())


def _brute_force_cost(D: torch.Tensor, k: int) -> float:
    N = D.shape[0]
    return min(float(D[:, list(c)].min(dim=1).values.sum()) for c in itertools.combinations(range(N), k))


# --------------------------------------------------------------------------- K-medoids


@pytest.mark.parametrize("seed", range(6))
def test_k_medoids_matches_brute_force_on_clustered_points(seed):
    g = torch.Generator().manual_seed(seed)
    centres = torch.randn(3, 2, generator=g, dtype=torch.float64) * 10
    x = torch.cat([c + 0.8 * torch.randn(3, 2, generator=g, dtype=torch.float64) for c in centres])  # N = 9
    D = _dist(x)
    med, labels, cost = k_medoids(D, 3)
    assert cost == pytest.approx(_brute_force_cost(D, 3), rel=1e-12, abs=1e-12)
    assert cost == pytest.approx(float(medoid_cost(D, med)), rel=1e-12)
    # labels: nearest medoid (loop reference)
    for i in range(D.shape[0]):
        assert float(D[i, med[labels[i]]]) == pytest.approx(min(float(D[i, m]) for m in med.tolist()))


@pytest.mark.parametrize("k", [1, 2, 4])
def test_k_medoids_exact_on_tiny_random_cases_and_locally_optimal(k):
    g = torch.Generator().manual_seed(10 + k)
    hits = 0
    for trial in range(8):
        D = _dist(torch.rand(7, 3, generator=g, dtype=torch.float64))
        med, labels, cost = k_medoids(D, k)
        assert len(set(med.tolist())) == k
        # no single swap improves (loop over every slot and non-medoid)
        for j in range(k):
            for c in range(7):
                if c in med.tolist():
                    continue
                m2 = med.clone()
                m2[j] = c
                assert float(medoid_cost(D, m2)) >= cost - 1e-12
        hits += abs(cost - _brute_force_cost(D, k)) < 1e-12
    assert hits >= 7  # PAM is a local search; on such tiny cases it should (nearly) always be exact


def test_k_medoids_k1_is_the_item_of_smallest_distance_sum():
    D = _dist(torch.tensor([[0.0], [1.0], [2.0], [10.0]]))
    med, labels, cost = k_medoids(D, 1)
    assert med.tolist() == [1] and labels.tolist() == [0, 0, 0, 0] and cost == pytest.approx(1 + 1 + 9)


def test_k_medoids_rejects_bad_input():
    with pytest.raises(ValueError, match="k must be"):
        k_medoids(torch.zeros(3, 3), 4)
    with pytest.raises(ValueError, match="square"):
        k_medoids(torch.zeros(3, 2), 1)
    with pytest.raises(ValueError, match="finite"):
        k_medoids(torch.full((2, 2), math.nan), 1)


def test_order_clusters_by_size():
    med = torch.tensor([7, 3, 5])
    labels = torch.tensor([0, 1, 1, 2, 1, 2, 0, 1])
    m, lab, sizes = order_clusters_by_size(med, labels)
    assert m.tolist() == [3, 7, 5] and sizes.tolist() == [4, 2, 2]
    assert lab.tolist() == [1, 0, 0, 2, 0, 2, 1, 0]


# --------------------------------------------------------------------------- distances


def test_chamfer_matrix_matches_a_loop_with_kd_trees():
    g = torch.Generator().manual_seed(1)
    pts = torch.randn(6, 40, 3, generator=g, dtype=torch.float64)
    pts[2] = pts[1] + 0.01  # a near-duplicate pair
    D = chamfer_matrix(pts, chunk_pairs=4)  # several chunks
    ref = np.zeros((6, 6))
    for i in range(6):
        for j in range(6):
            a, b = pts[i].numpy(), pts[j].numpy()
            dab = cKDTree(b).query(a)[0]
            dba = cKDTree(a).query(b)[0]
            ref[i, j] = max(np.sqrt((dab ** 2).mean()), np.sqrt((dba ** 2).mean()))
    np.testing.assert_allclose(D.numpy(), ref, rtol=1e-9, atol=1e-12)
    assert torch.equal(D, D.T) and float(D.diagonal().abs().max()) == 0.0
    assert float(D[1, 2]) == pytest.approx(0.01 * math.sqrt(3), rel=1e-6)


def test_normalise_points_removes_translation_and_scale():
    g = torch.Generator().manual_seed(3)
    X = torch.randn(1, 50, 3, generator=g, dtype=torch.float64)
    Y = 7.0 * X + torch.tensor([1.0, -2.0, 30.0])
    a, b = normalise_points(X), normalise_points(Y)
    torch.testing.assert_close(a, b)
    assert float(a.pow(2).sum(-1).mean()) == pytest.approx(1.0)
    assert float(normalise_points(Y, scale=False).mean(1).abs().max()) < 1e-12


def test_sample_points_is_deterministic_and_on_the_surface():
    box = trimesh.creation.box(extents=(2.0, 4.0, 6.0))
    p = sample_points(box, 500, seed=3)
    assert p.shape == (500, 3) and torch.equal(p, sample_points(box, 500, seed=3))
    # every point lies on a face of the box: one coordinate at +-half extent
    half = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    on_face = ((p.abs() - half).abs() < 1e-9).any(dim=1)
    assert bool(on_face.all())
    # area weighting: the two 2x4 faces hold 8/88 of the area
    frac = float(((p[:, 2].abs() - 3.0).abs() < 1e-9).double().mean())
    assert frac == pytest.approx(2 * 8 / 88, abs=0.04)


# --------------------------------------------------------------------------- ranking curves


def test_ranking_curves_match_a_loop():
    g = torch.Generator().manual_seed(4)
    R, P = 5, 9
    errors = torch.rand(R, P, generator=g, dtype=torch.float64) * 10
    errors[0, :3] = math.nan  # first proposals invalid
    errors[1, 4] = math.nan
    order = torch.stack([torch.randperm(P, generator=g) for _ in range(R)])
    out = ranking_curves(errors, order)
    for r in range(R):
        rank = {int(p): i for i, p in enumerate(order[r])}
        for k in range(1, P + 1):
            cand = [p for p in range(k) if math.isfinite(float(errors[r, p]))]
            if not cand:
                for key in ("top", "random", "best"):
                    assert math.isnan(float(out[key][r, k - 1]))
                continue
            top = min(cand, key=lambda p: rank[p])
            assert float(out["top"][r, k - 1]) == pytest.approx(float(errors[r, top]))
            assert float(out["random"][r, k - 1]) == pytest.approx(float(np.mean([float(errors[r, p]) for p in cand])))
            assert float(out["best"][r, k - 1]) == pytest.approx(min(float(errors[r, p]) for p in cand))


def test_ranking_curves_with_rank_proposals_order():
    from carvi_torch.select import rank_proposals

    scores = torch.tensor([[0.5, 0.2, 0.9, 0.1]])
    misses = torch.tensor([[0, 0, 0, 1]])
    valid = torch.tensor([[True, True, True, True]])
    order, best = rank_proposals(scores, misses, valid)
    errors = torch.tensor([[4.0, 2.0, 1.0, 3.0]])
    out = ranking_curves(errors, order)
    assert out["top"].tolist() == [[4.0, 2.0, 2.0, 2.0]]  # proposal 3 has a keypoint miss, ranks last
    assert out["best"].tolist() == [[4.0, 2.0, 1.0, 1.0]]


# --------------------------------------------------------------------------- proposal files


def test_load_proposals_round_trip(tmp_path):
    g = torch.Generator().manual_seed(5)
    occ = torch.rand(3, 4, 5, 6, generator=g) > 0.5
    P = occ.shape[0]
    np.savez(tmp_path / "7.npz", occupancy_bits=np.packbits(occ.numpy().reshape(P, -1), axis=1),
             shape=np.asarray(occ.shape[1:]), voxel_to_camera=np.tile(np.eye(4), (P, 1, 1)),
             valid=np.array([True, False, True]), scores=np.array([0.1, np.inf, 0.3]),
             misses=np.array([0, 10 ** 6, 1]), best=np.int64(2), surrogates=np.full((P, 2), -1))
    got = load_proposals(tmp_path / "7.npz")
    assert np.array_equal(got["occupancy"], occ.numpy())
    assert got["best"] == 2 and got["valid"].tolist() == [True, False, True]
    np.savez(tmp_path / "bad.npz", shape=np.zeros(3))
    with pytest.raises(ValueError, match="not a proposals file"):
        load_proposals(tmp_path / "bad.npz")
