"""Reusable pieces of the benchmark studies: proposal ranking curves, shape distances, K-medoids.

* :func:`load_proposals` reads a ``<class>/proposals/<id>.npz`` file written by
  ``reconstruct save_proposals=true`` (every proposal's bit-packed occupancy).
* :func:`ranking_curves` turns per-proposal errors into the paper's ranking study: the error
  of the top-ranked, a random and the best available proposal among the first ``k`` of the
  pool, for every ``k`` at once.
* :func:`sample_points` and :func:`normalise_points` turn reconstructions of one class (each
  in its own reference camera frame, brought to the class's object frame with
  :meth:`carvi_torch.cameras.ScaledOrthographic.from_camera_frame`) into fixed-size, centred,
  scale-free point sets; :func:`chamfer_matrix` compares all pairs of them (batched).
* :func:`k_medoids` clusters a distance matrix (BUILD initialisation + PAM swaps, every
  candidate swap scored at once); :func:`order_clusters_by_size` orders the clusters.

Conventions: cameras are scaled orthographic in image pixels (``uv = s X R[:2]^T + t``,
``depth = s X R[2]``, docs/conventions.md); reconstructions are in the reference camera frame
``(u, v, depth)``, whose depth origin is arbitrary.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

__all__ = [
    "load_proposals",
    "ranking_curves",
    "sample_points",
    "normalise_points",
    "chamfer_matrix",
    "k_medoids",
    "medoid_cost",
    "order_clusters_by_size",
]


# --------------------------------------------------------------------------- proposals


def load_proposals(path: str | Path) -> dict:
    """Every proposal of one reference, as written by ``reconstruct save_proposals=true``.

    Returns:
        dict with ``occupancy (P, D, H, W)`` bool (unpacked from ``occupancy_bits``),
        ``voxel_to_camera (P, 4, 4)`` float64 (index -> reference camera frame, image pixels),
        ``valid (P,)`` bool, ``scores (P,)`` float, ``misses (P,)`` int, ``best`` int (the
        selected proposal) and ``surrogates (P, 2)`` annotation ids (``-1``: none).
    """
    path = Path(path)
    with np.load(path) as z:
        missing = {"occupancy_bits", "shape", "voxel_to_camera", "valid", "scores", "misses", "best"} - set(z.files)
        if missing:
            raise ValueError(f"{path}: not a proposals file, missing {sorted(missing)}")
        shape = tuple(int(v) for v in z["shape"])
        bits = z["occupancy_bits"]
        P = bits.shape[0]
        occ = np.unpackbits(bits, axis=1, count=int(np.prod(shape))).astype(bool).reshape(P, *shape)
        out = {"occupancy": occ, "voxel_to_camera": z["voxel_to_camera"].astype(np.float64),
               "valid": z["valid"].astype(bool), "scores": z["scores"].astype(np.float64),
               "misses": z["misses"].astype(np.int64), "best": int(z["best"]),
               "surrogates": z["surrogates"] if "surrogates" in z.files else np.full((P, 2), -1)}
    return out


def ranking_curves(errors: torch.Tensor, order: torch.Tensor) -> dict[str, torch.Tensor]:
    """Error of the top-ranked, a random and the best proposal among the first ``k``, for all ``k``.

    The ranking is a total order of each reference's proposals (``order``, e.g. from
    :func:`carvi_torch.select.rank_proposals`, best first); restricted to the first ``k``
    proposals it still orders them, so the top-ranked of the first ``k`` is the one of
    smallest rank among them (a running minimum over ``k``).

    * ``top[r, k-1]``: error of the top-ranked proposal among proposals ``0 .. k-1``;
    * ``random[r, k-1]``: the *expected* error of a proposal drawn uniformly among the
      finite-error ones of ``0 .. k-1`` (their mean; no draw, so no noise);
    * ``best[r, k-1]``: the smallest finite error among ``0 .. k-1`` (the best available).

    Entries are NaN while no proposal among the first ``k`` has a finite error (invalid
    proposals carry NaN errors and rank last).

    Args:
        errors: ``(R, P)`` float, error of every proposal, NaN where invalid or unevaluated.
        order: ``(R, P)`` long, proposal indices best first.

    Returns:
        dict of ``(R, P)`` float64 tensors ``top``, ``random``, ``best``.

    Example:
        >>> e = torch.tensor([[3.0, 1.0, 2.0]]); o = torch.tensor([[2, 0, 1]])
        >>> {k: v.tolist() for k, v in ranking_curves(e, o).items()}
        {'top': [[3.0, 3.0, 2.0]], 'random': [[3.0, 2.0, 2.0]], 'best': [[3.0, 1.0, 1.0]]}
    """
    if not isinstance(errors, torch.Tensor) or errors.dim() != 2:
        raise ValueError("errors must be a (R, P) tensor")
    if not isinstance(order, torch.Tensor) or order.shape != errors.shape:
        raise ValueError(f"order must be {tuple(errors.shape)} like errors")
    R, P = errors.shape
    e = errors.double()
    finite = torch.isfinite(e)
    rank = torch.empty_like(order)
    rank.scatter_(1, order, torch.arange(P, device=order.device).expand(R, P).contiguous())
    # invalid (non-finite) proposals never win while a finite one is available
    key = torch.where(finite, rank, rank + P)
    _, arg = torch.cummin(key, dim=1)
    top = e.gather(1, arg)
    top = torch.where(torch.cummax(finite.long(), dim=1).values.bool(), top, torch.full_like(top, math.nan))
    filled = torch.where(finite, e, torch.zeros_like(e))
    count = finite.double().cumsum(1)
    random = filled.cumsum(1) / count
    random = torch.where(count > 0, random, torch.full_like(random, math.nan))
    best = torch.cummin(torch.where(finite, e, torch.full_like(e, math.inf)), dim=1).values
    best = torch.where(torch.isinf(best), torch.full_like(best, math.nan), best)
    return {"top": top, "random": random, "best": best}


# --------------------------------------------------------------------------- shapes as point sets


def sample_points(mesh, count: int, seed: int = 0) -> torch.Tensor:
    """``count`` points drawn uniformly by area on a mesh's surface: ``(count, 3)`` float64.

    ``trimesh.sample.sample_surface`` with a fixed seed (same mesh, same seed, same points).
    """
    import trimesh

    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError("mesh must be a trimesh.Trimesh with faces")
    if int(count) < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    pts, _ = trimesh.sample.sample_surface(mesh, int(count), seed=int(seed))
    return torch.from_numpy(np.asarray(pts, dtype=np.float64))


def normalise_points(points: torch.Tensor, scale: bool = True) -> torch.Tensor:
    """Centre each point set at its centroid and (optionally) divide by its RMS radius.

    Centring also removes the arbitrary depth origin of a reconstruction brought back to the
    object frame (it is known up to a shift along its viewing direction).

    Args:
        points: ``(N, M, 3)``.
        scale: divide by ``sqrt(mean |p - centroid|^2)`` so that only shape is compared.

    Returns:
        ``(N, M, 3)``.
    """
    if points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError("points must be a (N, M, 3) tensor")
    c = points - points.mean(dim=1, keepdim=True)
    if scale:
        r = c.pow(2).sum(-1).mean(-1).sqrt().clamp_min(torch.finfo(c.dtype).tiny)
        c = c / r[:, None, None]
    return c


def chamfer_matrix(points: torch.Tensor, chunk_pairs: int = 64) -> torch.Tensor:
    """Symmetric RMS chamfer distance between every pair of point sets.

    ``D[i, j] = max(rms_{p in P_i} min_{q in P_j} |p - q|, rms_{q in P_j} min_{p in P_i} |p - q|)``:
    the paper's symmetric RMS mesh distance with each surface replaced by a point sample (so
    point-to-point rather than point-to-triangle distances). Pairs ``i < j`` are computed in
    batches of ``chunk_pairs`` with ``torch.cdist``; the matrix is symmetric with a zero diagonal.

    Args:
        points: ``(N, M, 3)`` float, ``M`` points per set.
        chunk_pairs: pairs per batch (bounds memory: ``chunk_pairs * M * M`` floats).

    Returns:
        ``(N, N)`` in ``points``' dtype and device.
    """
    if not isinstance(points, torch.Tensor) or points.dim() != 3 or points.shape[-1] != 3:
        raise ValueError("points must be a (N, M, 3) tensor")
    if int(chunk_pairs) < 1:
        raise ValueError(f"chunk_pairs must be >= 1, got {chunk_pairs}")
    N = points.shape[0]
    D = torch.zeros(N, N, dtype=points.dtype, device=points.device)
    ii, jj = torch.triu_indices(N, N, offset=1, device=points.device)
    for start in range(0, ii.numel(), int(chunk_pairs)):
        a, b = ii[start:start + chunk_pairs], jj[start:start + chunk_pairs]
        d2 = torch.cdist(points[a], points[b]).pow(2)  # (B, M, M)
        ab = d2.min(dim=2).values.mean(dim=1).sqrt()
        ba = d2.min(dim=1).values.mean(dim=1).sqrt()
        v = torch.maximum(ab, ba)
        D[a, b] = v
        D[b, a] = v
    return D


# --------------------------------------------------------------------------- K-medoids


def medoid_cost(D: torch.Tensor, medoids: torch.Tensor) -> torch.Tensor:
    """Total distance of every item to its nearest medoid: ``sum_i min_m D[i, m]`` (0-d tensor)."""
    return D[:, medoids].min(dim=1).values.sum()


def k_medoids(D: torch.Tensor, k: int, max_swaps: int = 1000) -> tuple[torch.Tensor, torch.Tensor, float]:
    """K-medoids of a distance matrix: PAM (BUILD, then best-improvement swaps).

    BUILD adds medoids greedily, each time the item that lowers the total cost
    ``sum_i min_m D[i, m]`` most (the first: the item of smallest distance sum). SWAP then
    scores every (medoid slot, non-medoid) exchange at once -- ``cost[j, c] =
    sum_i min(nearest medoid of i other than slot j, D[i, c])``, a ``(k, N, N)`` tensor --
    and applies the best one while it lowers the cost. Deterministic (ties: lowest index).
    The result is a local optimum under single swaps (exact on small, well-separated cases).

    Args:
        D: ``(N, N)`` symmetric, non-negative distances (zero diagonal).
        k: number of clusters, ``1 <= k <= N``.
        max_swaps: cap on the swap iterations.

    Returns:
        ``medoids (k,)`` long (item indices, in BUILD/SWAP slot order), ``labels (N,)`` long
        (the slot of each item's nearest medoid; a medoid gets its own slot) and the total cost.

    Example:
        >>> x = torch.tensor([0.0, 0.1, 5.0, 5.2, 9.0])
        >>> med, lab, cost = k_medoids((x[:, None] - x[None]).abs(), 3)
        >>> sorted(med.tolist()), round(cost, 6)
        ([0, 2, 4], 0.3)
    """
    if not isinstance(D, torch.Tensor) or D.dim() != 2 or D.shape[0] != D.shape[1]:
        raise ValueError("D must be a square (N, N) tensor")
    N = D.shape[0]
    if not 1 <= int(k) <= N:
        raise ValueError(f"k must be in [1, N={N}], got {k}")
    if not bool(torch.isfinite(D).all()):
        raise ValueError("D must be finite")
    k = int(k)
    D = D.double()
    # BUILD
    first = int(torch.argmin(D.sum(dim=0)))
    medoids = [first]
    nearest = D[:, first].clone()  # (N,) distance to the nearest chosen medoid
    for _ in range(1, k):
        gain = (nearest[:, None] - D).clamp_min(0).sum(dim=0)  # (N,) cost decrease if c is added
        gain[medoids] = -1.0
        c = int(torch.argmax(gain))
        medoids.append(c)
        nearest = torch.minimum(nearest, D[:, c])
    med = torch.tensor(medoids, dtype=torch.long, device=D.device)
    cost = medoid_cost(D, med)
    # SWAP
    for _ in range(int(max_swaps)):
        Dm = D[:, med]  # (N, k)
        # nearest medoid of every item once slot j is removed: (k, N) -- the nearest one, or
        # the second nearest where slot j was the nearest
        two = torch.topk(Dm, min(2, k), dim=1, largest=False)
        first_d, first_j = two.values[:, 0], two.indices[:, 0]
        second_d = two.values[:, 1] if k > 1 else torch.full_like(first_d, math.inf)
        slot = torch.arange(k, device=D.device)[:, None]
        excl = torch.where(first_j[None, :] == slot, second_d[None, :], first_d[None, :])
        cand = torch.minimum(excl[:, :, None], D[None, :, :]).sum(dim=1)  # (k, N): slot j -> candidate c
        cand[:, med] = math.inf  # medoids are no candidates
        best = torch.argmin(cand)
        j, c = divmod(int(best), N)
        if not float(cand[j, c]) < float(cost) - 1e-12 * max(1.0, abs(float(cost))):
            break
        med = med.clone()
        med[j] = c
        cost = cand[j, c]
    Dm = D[:, med]
    labels = Dm.argmin(dim=1)
    labels[med] = torch.arange(k, device=D.device)  # ties between coincident medoids
    return med, labels, float(cost)


def order_clusters_by_size(medoids: torch.Tensor,
                           labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Renumber clusters by decreasing size (ties: lower slot first).

    Returns:
        ``medoids (k,)`` reordered, ``labels (N,)`` renumbered, ``sizes (k,)`` long decreasing.
    """
    k = medoids.shape[0]
    sizes = torch.bincount(labels, minlength=k)
    order = sorted(range(k), key=lambda j: (-int(sizes[j]), j))
    perm = torch.tensor(order, dtype=torch.long, device=labels.device)
    new_label = torch.empty_like(perm)
    new_label[perm] = torch.arange(k, device=labels.device)
    return medoids[perm], new_label[labels], sizes[perm]
