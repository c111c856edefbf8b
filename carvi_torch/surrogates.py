"""Principal directions of a class, viewpoint clusters and surrogate triplets.

The surrogate stage (:mod:`carvi_torch.pipeline`; paper, "Sampling shape surrogates"):

1. :func:`principal_directions` — PCA axes of the SfM mean shape ``S``.
2. :func:`cluster_by_direction` — instances seen (front or back) within a threshold of a
   principal axis form that axis' cluster; the threshold widens while too few
   instances are clustered.
3. :func:`sample_triplets` — per reference instance, ``P`` triplets = the reference +
   one surrogate from each of two *different* clusters, clusters drawn with probability
   proportional to their size.
4. Rotationally symmetric classes (bottle-like) replace surrogates by the reference seen
   from cameras rotated about the symmetry axis: :func:`symmetry_axis`,
   :func:`symmetric_surrogates`.

Conventions: the object frame is the frame of the mean shape ``S (K, 3)``; a camera's
viewing direction in that frame is ``R[2]`` (:attr:`ScaledOrthographic.view_direction`).
Rows of ``S`` holding NaN (keypoints SfM never saw) are ignored everywhere.
Randomness only through the ``torch.Generator`` passed in.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch

from .cameras import ScaledOrthographic, rotation_about_axis

if TYPE_CHECKING:
    from .config import SurrogateConfig

__all__ = [
    "Clusters",
    "check_axes",
    "Triplets",
    "principal_components",
    "principal_directions",
    "cluster_by_direction",
    "cluster_weights",
    "members_per_object",
    "object_share",
    "sample_triplets",
    "symmetry_axis",
    "symmetric_surrogates",
    "axis_through_silhouettes",
    "axis_in_image_plane",
    "cluster_instances",
    "SurrogatePlan",
    "rotated_cameras",
    "plan_proposals",
    "LEVELS",
]


# --------------------------------------------------------------------------- PCA


def _finite_rows(S: torch.Tensor, name: str = "S") -> torch.Tensor:
    """Rows of ``S (K, 3)`` without NaN/inf; ``ValueError`` if the shape is wrong."""
    if not isinstance(S, torch.Tensor) or S.dim() != 2 or S.shape[-1] != 3:
        shape = tuple(S.shape) if isinstance(S, torch.Tensor) else type(S).__name__
        raise ValueError(f"{name} must be a (K, 3) tensor, got {shape}")
    return S[torch.isfinite(S).all(dim=-1)]


def principal_components(S: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """PCA of a mean shape: axes and variances, by decreasing variance.

    Rows of ``S`` with a non-finite entry are ignored. The covariance of the centred
    finite rows is eigen-decomposed in float64 (``torch.linalg.eigh``).

    Sign convention (the eigenvectors' signs are arbitrary): the first two axes are
    flipped so that their component of largest magnitude is positive; the third is
    their cross product, so ``axes`` is a proper rotation (right-handed, ``det = +1``).

    Args:
        S: ``(K, 3)`` float, object frame; may hold NaN rows.

    Returns:
        ``axes (3, 3)`` (rows = unit axes, decreasing variance) and ``variances (3,)``
        (population variance of the finite rows along each axis), both in ``S``'s dtype
        and device.

    Raises:
        ValueError: ``S`` is not ``(K, 3)`` or has fewer than 3 finite rows.

    Example:
        >>> S = torch.tensor([[3.0, 0, 0], [-3.0, 0, 0], [0, 1.0, 0], [0, -1.0, 0], [0, 0, .5]])
        >>> axes, var = principal_components(S)
        >>> axes.abs().round()
        tensor([[1., 0., 0.],
                [0., 1., 0.],
                [0., 0., 1.]])
    """
    X = _finite_rows(S)
    if X.shape[0] < 3:
        raise ValueError(f"S needs at least 3 finite rows for a PCA, got {X.shape[0]}")
    X = X.double()
    Xc = X - X.mean(dim=0, keepdim=True)
    cov = Xc.T @ Xc / X.shape[0]
    evals, evecs = torch.linalg.eigh(cov)  # ascending; columns are eigenvectors
    order = torch.arange(2, -1, -1, device=S.device)
    evals = evals[order].clamp_min(0.0)
    axes = evecs[:, order].T.contiguous()  # rows
    idx = axes[:2].abs().argmax(dim=-1)  # (2,)
    sign = torch.sign(axes[:2].gather(1, idx[:, None]))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    first_two = axes[:2] * sign
    third = torch.linalg.cross(first_two[0], first_two[1], dim=-1)
    axes = torch.cat([first_two, third[None]], dim=0)
    return axes.to(S.dtype), evals.to(S.dtype)


def principal_directions(S: torch.Tensor) -> torch.Tensor:
    """Principal directions of a class: PCA axes of its centred mean shape.

    See :func:`principal_components` for NaN handling and the sign convention.

    Args:
        S: ``(K, 3)`` float mean shape (object frame); NaN rows are ignored.

    Returns:
        ``(3, 3)``: rows = unit axes by decreasing variance; a proper rotation.
    """
    return principal_components(S)[0]


# --------------------------------------------------------------------------- clusters


@dataclass
class Clusters:
    """Instances grouped by the principal direction they are seen along.

    Attributes:
        labels: ``(N,)`` long in ``{-1, 0, 1, 2}``: the axis whose cluster the instance
            joined, ``-1`` for none.
        threshold_deg: the angular threshold finally used (degrees).
        sizes: ``(3,)`` long, members per axis.
        log: human-readable notes, one per widening of the threshold (each starting with
            ``"widened"``) and one if the maximum was reached without success.
        angle_deg: ``(N,)`` float, angle (degrees, in ``[0, 90]``) between each
            instance's viewing direction and its nearest principal axis (front or back).
    """

    labels: torch.Tensor
    threshold_deg: float
    sizes: torch.Tensor
    log: list[str] = field(default_factory=list)
    angle_deg: torch.Tensor | None = None


def check_axes(axes: torch.Tensor) -> None:
    """``ValueError`` unless ``axes`` is a ``(3, 3)`` tensor (rows: principal axes)."""
    if not isinstance(axes, torch.Tensor) or axes.shape != (3, 3):
        shape = tuple(axes.shape) if isinstance(axes, torch.Tensor) else type(axes).__name__
        raise ValueError(f"axes must be a (3, 3) tensor (rows = principal axes), got {shape}")


def _check_clustering(view_dirs, axes, threshold_deg, widen_step_deg, max_threshold_deg, min_second, groups) -> None:
    """:func:`cluster_by_direction`'s argument checks (``ValueError`` naming the argument)."""
    if not isinstance(view_dirs, torch.Tensor) or view_dirs.dim() != 2 or view_dirs.shape[-1] != 3:
        shape = tuple(view_dirs.shape) if isinstance(view_dirs, torch.Tensor) else type(view_dirs).__name__
        raise ValueError(f"view_dirs must be a (N, 3) tensor, got {shape}")
    check_axes(axes)
    if not threshold_deg > 0:
        raise ValueError(f"threshold_deg must be > 0, got {threshold_deg}")
    if not widen_step_deg > 0:
        raise ValueError(f"widen_step_deg must be > 0, got {widen_step_deg}")
    if not threshold_deg <= max_threshold_deg <= 45.0:
        raise ValueError(
            f"max_threshold_deg must lie in [threshold_deg={threshold_deg}, 45], got {max_threshold_deg}"
        )
    if min_second < 0:
        raise ValueError(f"min_second must be >= 0, got {min_second}")
    if groups is not None and (not isinstance(groups, torch.Tensor) or groups.shape != (view_dirs.shape[0],)):
        raise ValueError(f"groups must be None or a ({view_dirs.shape[0]},) tensor")


def _nearest_axis(view_dirs: torch.Tensor, axes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(angle_deg, nearest)`` ``(N,)``: each direction's angle (float64 degrees) to its nearest axis, front or
    back (``+axes[j]`` or ``-axes[j]``), and that axis's index; a non-finite row gets a NaN angle."""
    v = view_dirs.double()
    v = v / v.norm(dim=-1, keepdim=True)
    a = axes.to(device=view_dirs.device, dtype=torch.float64)
    a = a / a.norm(dim=-1, keepdim=True)
    best_cos, nearest = (v @ a.T).abs().clamp(max=1.0).max(dim=-1)
    return torch.rad2deg(torch.acos(best_cos)), nearest


def cluster_by_direction(
    view_dirs: torch.Tensor,
    axes: torch.Tensor,
    threshold_deg: float = 15.0,
    widen_step_deg: float = 5.0,
    max_threshold_deg: float = 45.0,
    min_second: int = 2,
    groups: torch.Tensor | None = None,
) -> Clusters:
    """Cluster instances around the principal directions by their viewing direction.

    Instance ``n`` joins the cluster of axis ``j`` when the angle between its viewing
    direction and ``+axes[j]`` or ``-axes[j]`` (front or back view) is strictly below
    the threshold. The axes being orthogonal and the threshold at most 45 degrees, an
    instance is near at most one axis: it is tested against its nearest axis only.

    Widening: while the second-smallest cluster has fewer than ``min_second`` members
    (so fewer than two clusters can provide surrogates), the threshold grows by
    ``widen_step_deg`` (the last step clipped to ``max_threshold_deg``), each widening
    noted in ``log``. With ``groups`` (physical objects, e.g. one per CAD model rendered many
    times) a cluster's members are counted as distinct objects: a cluster holding views of one
    object only gives every reference the same surrogate shape (and the same average mask).

    Args:
        view_dirs: ``(N, 3)`` viewing directions in the object frame
            (``cameras.R[:, 2]``); normalised here; a non-finite row joins no cluster.
        axes: ``(3, 3)`` principal axes (rows), e.g. from :func:`principal_directions`.
        threshold_deg: initial threshold (degrees, ``> 0``).
        widen_step_deg: widening step (degrees, ``> 0``).
        max_threshold_deg: largest threshold (degrees, ``threshold_deg <= . <= 45``).
        min_second: members the second-smallest cluster should have (``>= 0``).
        groups: optional ``(N,)`` long physical-object ids (default: every instance its own).

    Returns:
        :class:`Clusters` on the device of ``view_dirs``.

    Example:
        >>> v = torch.tensor([[0.0, 0, 1], [0, 0, -1], [1, 0, 0], [1, 1, 0]])
        >>> cluster_by_direction(v, torch.eye(3), min_second=1).labels
        tensor([ 2,  2,  0, -1])
    """
    _check_clustering(view_dirs, axes, threshold_deg, widen_step_deg, max_threshold_deg, min_second, groups)
    dev = view_dirs.device
    angle, nearest = _nearest_axis(view_dirs, axes)
    what = "members" if groups is None else "objects"
    log: list[str] = []
    thr = float(threshold_deg)
    while True:
        labels = torch.where(angle < thr, nearest, torch.full_like(nearest, -1))
        sizes = torch.bincount(labels[labels >= 0], minlength=3)[:3]
        counted = sizes if groups is None else _objects_per_cluster(labels, groups.to(dev))
        second = int(counted.sort().values[1])
        if second >= min_second:
            break
        if thr >= max_threshold_deg:
            log.append(
                f"second-smallest principal-direction cluster still has {second} < {min_second} {what} "
                f"at the maximum threshold {thr:g} deg (sizes {sizes.tolist()})"
            )
            break
        new = min(thr + widen_step_deg, float(max_threshold_deg))
        log.append(
            f"widened principal-direction threshold from {thr:g} to {new:g} deg: second-smallest cluster "
            f"has {second} < {min_second} {what} (sizes {sizes.tolist()})"
        )
        thr = new
    return Clusters(labels=labels, threshold_deg=thr, sizes=sizes, log=log, angle_deg=angle.to(view_dirs.dtype))


def members_per_object(labels: torch.Tensor, object_ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Members of each cluster that are views of each physical object.

    Args:
        labels: ``(N,)`` long cluster labels in ``{-1, 0, 1, 2}`` (-1: unclustered, counted nowhere).
        object_ids: ``(N,)`` integer physical-object ids.

    Returns:
        ``counts (G, 3)`` long, members of cluster ``j`` whose object is the ``g``-th distinct id (ascending),
        and ``group (N,)`` long, the row of ``counts`` of each instance.

    Example:
        >>> counts, group = members_per_object(torch.tensor([0, 0, 2, -1]), torch.tensor([7, 7, 3, 3]))
        >>> counts.tolist(), group.tolist()
        ([[0, 0, 1], [2, 0, 0]], [1, 1, 0, 0])
    """
    ids, group = torch.unique(object_ids, return_inverse=True)
    inside = labels >= 0
    counts = torch.zeros(ids.shape[0], 3, dtype=torch.long, device=labels.device)
    counts.index_put_((group[inside], labels[inside].long()), torch.ones_like(group[inside]), accumulate=True)
    return counts, group


def _objects_per_cluster(labels: torch.Tensor, groups: torch.Tensor) -> torch.Tensor:
    """``(3,)`` long: distinct ``groups`` among each cluster's members (``labels (N,)``, ``groups (N,)``)."""
    counts, _ = members_per_object(labels, groups)
    return (counts > 0).sum(dim=0)


# --------------------------------------------------------------------------- triplets


@dataclass
class Triplets:
    """Sampled surrogate pairs: reference ``r``'s proposal ``p`` carves
    ``references[r], surrogates[r, p, 0], surrogates[r, p, 1]``.

    Attributes:
        surrogates: ``(R, P, 2)`` long instance indices, ``-1`` where the proposal is
            invalid (no usable pair, or a duplicate of an earlier proposal).
        valid: ``(R, P)`` bool, ``valid == (surrogates >= 0).all(-1)``.
        reasons: ``{instance index of the reference: why}`` for every reference with no
            valid proposal at all.
        clusters: ``(R, P, 2)`` long, the principal direction each surrogate came from
            (``-1`` where invalid).
    """

    surrogates: torch.Tensor
    valid: torch.Tensor
    reasons: dict[int, str]
    clusters: torch.Tensor


def cluster_weights(
    labels: torch.Tensor,
    object_ids: torch.Tensor,
    references: torch.Tensor,
    own_cluster_weight: float = 0.1,
    floor: float = 0.2,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Unnormalised probabilities of drawing each cluster for each reference.

    ``w[r, j] = max(sizes[j] / sizes.sum(), floor)``; the reference's own cluster gets
    ``own_cluster_weight`` instead; a cluster with no member eligible for the reference
    (members not sharing its ``object_id``, hence never the reference itself) gets 0.

    Args:
        labels: ``(N,)`` long cluster labels in ``{-1, 0, 1, 2}``.
        object_ids: ``(N,)`` long physical-object ids.
        references: ``(R,)`` long instance indices.
        own_cluster_weight, floor: as above.

    Returns:
        ``weights (R, 3)`` float64 and ``eligible (R, 3)`` long, the number of members of
        each cluster eligible as surrogates of each reference.
    """
    counts = torch.bincount(labels[labels >= 0], minlength=3)[:3]
    sizes = counts.double()
    total = sizes.sum().clamp_min(1.0)
    base = torch.clamp(sizes / total, min=floor)  # (3,)
    # eligible[r, j] = #{n : labels[n] == j, object_ids[n] != object_ids[ref_r]}
    #               = sizes[j] - #{n : labels[n] == j, object_ids[n] == object_ids[ref_r]}
    # (members per object id and cluster: O(N) memory, not a reference x instance matrix)
    per_object, group = members_per_object(labels, object_ids)
    eligible = counts[None, :] - per_object[group[references]]  # (R, 3)
    w = base[None, :].expand(references.shape[0], 3).clone()
    own = labels[references]
    has_own = own >= 0
    w[has_own.nonzero().squeeze(-1), own[has_own]] = float(own_cluster_weight)
    w = torch.where(eligible > 0, w, torch.zeros_like(w))
    return w, eligible


#: Member weights (references x 3 x instances) built at once by :func:`sample_triplets`.
_TRIPLET_CHUNK_ELEMS = 1 << 24


def object_share(labels: torch.Tensor, object_ids: torch.Tensor) -> torch.Tensor:
    """``(N,)`` float: 1 / (members of the same cluster that are views of the same physical object).

    Weighting cluster members by it gives every physical object of a cluster the same total weight,
    however many views of it the cluster holds. Unclustered instances (label -1) get 1.

    Args:
        labels: ``(N,)`` long in ``{-1, 0, 1, 2}``; object_ids: ``(N,)`` long.

    Example:
        >>> object_share(torch.tensor([0, 0, 0, 1, -1]), torch.tensor([7, 7, 8, 7, 7])).tolist()
        [0.5, 0.5, 1.0, 1.0, 1.0]
    """
    counts, group = members_per_object(labels, object_ids)
    share = 1.0 / counts[group, labels.long().clamp(min=0)].clamp(min=1).to(torch.float32)
    return torch.where(labels >= 0, share, torch.ones_like(share))


def _member_draws(labels: torch.Tensor, object_ids: torch.Tensor, references: torch.Tensor, eligible: torch.Tensor,
                  samples: int, generator: torch.Generator | None) -> torch.Tensor:
    """``(3 r, samples)`` uniform draws (with replacement) among each cluster's eligible members.

    Row ``3 i + j``: members of cluster ``j`` not sharing ``object_ids[references[i]]``; a cluster
    without any (``eligible[i, j] == 0``) draws among all instances (a placeholder, never used).
    The weights are the cluster indicators with the reference's own object zeroed (one copy
    and a scatter, not an elementwise comparison of every reference with every instance).
    """
    n = labels.shape[0]
    r = references.shape[0]
    dev = labels.device
    probs = (labels[None, :] == torch.arange(3, device=dev)[:, None]).float()[None].expand(r, 3, n).clone()
    # instances sharing each reference's object id: (reference row, instance) pairs
    order = torch.argsort(object_ids, stable=True)
    sorted_ids = object_ids[order]
    first = torch.searchsorted(sorted_ids, object_ids[references])
    last = torch.searchsorted(sorted_ids, object_ids[references], right=True)
    size = last - first
    row = torch.repeat_interleave(torch.arange(r, device=dev), size)
    rank = torch.arange(row.shape[0], device=dev) - torch.repeat_interleave(torch.cumsum(size, 0) - size, size)
    inst = order[first[row] + rank]
    clustered = labels[inst] >= 0
    probs[row[clustered], labels[inst[clustered]], inst[clustered]] = 0.0
    probs[eligible <= 0] = 1.0  # placeholders for empty rows
    return torch.multinomial(probs.reshape(-1, n), samples, replacement=True, generator=generator)


def sample_triplets(
    labels: torch.Tensor,
    object_ids: torch.Tensor,
    references: torch.Tensor,
    proposals: int = 20,
    generator: torch.Generator | None = None,
    own_cluster_weight: float = 0.1,
    floor: float = 0.2,
) -> Triplets:
    """Sample ``proposals`` surrogate pairs for every reference instance.

    Per reference and proposal: two *different* principal-direction clusters are drawn
    without replacement (``torch.multinomial`` on the weights of
    :func:`cluster_weights`: proportional to cluster size, floored at ``floor``, the
    reference's own cluster at ``own_cluster_weight``, clusters without an eligible
    member at 0); then one surrogate uniformly from the eligible members of each (a
    masked categorical, ``torch.multinomial`` over instances). A surrogate never is the
    reference nor shares its ``object_id`` (annotations without a known object must
    carry unique ids). A proposal repeating an earlier proposal's unordered pair is
    marked invalid (first occurrence kept). A reference with fewer than two clusters of
    positive weight gets no valid proposal and a reason.

    Sampling runs on ``generator.device`` (CPU when ``generator`` is None, using the
    global RNG), so a CPU generator gives the same triplets for CPU and CUDA inputs;
    results are returned on the device of ``labels``. The same generator state gives the
    same triplets.

    Args:
        labels: ``(N,)`` long in ``{-1, 0, 1, 2}`` (:attr:`Clusters.labels`).
        object_ids: ``(N,)`` long.
        references: ``(R,)`` long instance indices in ``[0, N)``.
        proposals: ``P >= 1`` proposals per reference.
        generator: ``torch.Generator``.
        own_cluster_weight: weight of the reference's own cluster (``>= 0``).
        floor: lower bound of a non-empty cluster's normalised size (``>= 0``).

    Returns:
        :class:`Triplets`.

    Example:
        >>> labels = torch.tensor([0, 0, 1, 1, 2, 2])
        >>> t = sample_triplets(labels, torch.arange(6), torch.tensor([0]), 4, torch.Generator().manual_seed(0))
        >>> t.surrogates.shape, bool(t.valid.any())
        (torch.Size([1, 4, 2]), True)
    """
    _check_triplet_args(labels, object_ids, references, proposals, own_cluster_weight, floor)
    out_dev = labels.device
    dev = generator.device if generator is not None else torch.device("cpu")
    labels = labels.to(dev).long()
    object_ids = object_ids.to(dev).long()
    references = references.to(dev).long()
    P = int(proposals)

    w, eligible = cluster_weights(labels, object_ids, references, own_cluster_weight, floor)  # (R, 3)
    usable = (w > 0).sum(dim=-1) >= 2  # (R,)
    pick = _cluster_pairs(w, usable, P, generator)
    surrogates = _members_of_pairs(labels, object_ids, references, eligible, pick, generator)
    surrogates, valid, clusters = _drop_repeated_pairs(surrogates, pick, usable, labels.shape[0])
    reasons = _no_pair_reasons(labels, references, usable, eligible, w)
    return Triplets(
        surrogates=surrogates.to(out_dev), valid=valid.to(out_dev), reasons=reasons, clusters=clusters.to(out_dev)
    )


def _check_triplet_args(labels: torch.Tensor, object_ids: torch.Tensor, references: torch.Tensor, proposals: int,
                        own_cluster_weight: float, floor: float) -> None:
    """``ValueError`` unless the arguments are as :func:`sample_triplets` documents them."""
    for name, x in (("labels", labels), ("object_ids", object_ids), ("references", references)):
        if not isinstance(x, torch.Tensor) or x.dim() != 1:
            raise ValueError(f"{name} must be a 1-D tensor")
        if x.dtype.is_floating_point or x.dtype == torch.bool:
            raise ValueError(f"{name} must hold integers, got {x.dtype}")
    n = labels.shape[0]
    if object_ids.shape[0] != n:
        raise ValueError(f"object_ids must have N={n} entries like labels, got {object_ids.shape[0]}")
    if labels.numel() and (labels.min() < -1 or labels.max() > 2):
        raise ValueError("labels must lie in {-1, 0, 1, 2}")
    if references.numel() and (references.min() < 0 or references.max() >= n):
        raise ValueError(f"references must be instance indices in [0, {n})")
    if int(proposals) < 1:
        raise ValueError(f"proposals must be >= 1, got {proposals}")
    if own_cluster_weight < 0 or floor < 0:
        raise ValueError(f"own_cluster_weight and floor must be >= 0, got {own_cluster_weight}, {floor}")


def _cluster_pairs(w: torch.Tensor, usable: torch.Tensor, P: int, generator: torch.Generator | None) -> torch.Tensor:
    """Two different clusters per proposal: ``(R, P, 2)`` long drawn with weights ``w (R, 3)``
    (rows not ``usable (R,)`` draw from placeholder weights)."""
    R, dev = w.shape[0], w.device
    w_draw = torch.where(usable[:, None], w, torch.ones_like(w))  # placeholder rows keep multinomial happy
    w_draw = w_draw[:, None, :].expand(R, P, 3).reshape(R * P, 3)
    if R * P:
        return torch.multinomial(w_draw, 2, replacement=False, generator=generator).reshape(R, P, 2)
    return torch.zeros(R, P, 2, dtype=torch.long, device=dev)


def _members_of_pairs(labels: torch.Tensor, object_ids: torch.Tensor, references: torch.Tensor,
                      eligible: torch.Tensor, pick: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """One eligible member of each picked cluster: ``(R, P, 2)`` instance indices (``-1`` when there are none).

    One member of every cluster is drawn per slot, then the chosen cluster's kept. The ``(references, 3, N)``
    member weights are built a chunk of references at a time (bounded memory for large classes);
    multinomial draws row by row, so chunks give the same draws."""
    (R, P, _), n = pick.shape, labels.shape[0]
    if not (R * P and n):
        return torch.full((R, P, 2), -1, dtype=torch.long, device=pick.device)
    per = max(1, _TRIPLET_CHUNK_ELEMS // (3 * n))
    draws = torch.cat([_member_draws(labels, object_ids, references[r:r + per], eligible[r:r + per], 2 * P,
                                     generator) for r in range(0, R, per)])
    draws = draws.reshape(R, 3, P, 2)
    return draws.permute(0, 2, 3, 1).gather(-1, pick[..., None]).squeeze(-1)  # (R, P, 2)


def _drop_repeated_pairs(surrogates: torch.Tensor, pick: torch.Tensor, usable: torch.Tensor, n: int
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``surrogates``, ``valid (R, P)`` and ``clusters`` with the rows not ``usable`` and every repeat of an
    earlier proposal's unordered pair marked invalid (``-1``); ``surrogates``, ``pick``: ``(R, P, 2)``."""
    R, P, _ = surrogates.shape
    valid = usable[:, None].expand(R, P).clone()
    key = surrogates.min(dim=-1).values * max(n, 1) + surrogates.max(dim=-1).values  # (R, P)
    same = key[:, :, None] == key[:, None, :]  # (R, P, P): [r, p, q]
    earlier = torch.ones(P, P, dtype=torch.bool, device=surrogates.device).tril(diagonal=-1)  # q < p
    dup = (same & earlier).any(dim=-1)
    valid &= ~dup
    surrogates = torch.where(valid[..., None], surrogates, torch.full_like(surrogates, -1))
    clusters = torch.where(valid[..., None], pick, torch.full_like(pick, -1))
    return surrogates, valid, clusters


def _no_pair_reasons(labels: torch.Tensor, references: torch.Tensor, usable: torch.Tensor, eligible: torch.Tensor,
                     w: torch.Tensor) -> dict[int, str]:
    """Why each reference not ``usable (R,)`` gets no pair: ``{instance index: reason}`` from its ``eligible``
    members and weights ``w`` (both ``(R, 3)``)."""
    reasons: dict[int, str] = {}
    if references.shape[0] and not bool(usable.all()):
        sizes = torch.bincount(labels[labels >= 0], minlength=3)[:3].tolist()
        for r in (~usable).nonzero().squeeze(-1).tolist():  # only the failing references
            ref = int(references[r])
            own = int(labels[ref])
            reasons[ref] = (
                f"fewer than two principal-direction clusters can give a surrogate: eligible members per "
                f"direction {eligible[r].tolist()} (cluster sizes {sizes}, own cluster {own}, weights "
                f"{[round(x, 3) for x in w[r].tolist()]}); members sharing the reference's object_id are excluded"
            )
    return reasons


# --------------------------------------------------------------------------- rotational symmetry


def symmetry_axis(S: torch.Tensor, choice: int | None = None, up: torch.Tensor | None = None,
                  planar_ratio: float = 1e-3) -> torch.Tensor:
    """Axis of rotational symmetry of a (roughly) rotationally symmetric class.

    Among the PCA axes (:func:`principal_components`, variances ``l0 >= l1 >= l2``) the
    symmetry axis is the one whose variance stands apart from the two others, which are
    about equal for a solid of revolution: the first axis when
    ``log(l0 / l1) > log(l1 / l2)`` (elongated, e.g. a bottle), else the third (flat, e.g.
    a round table). The middle axis never stands apart by this measure. ``choice`` picks
    PCA axis 0, 1 or 2 explicitly instead.

    Planar keypoint sets (``l2 < planar_ratio * l0``; e.g. PASCAL's view-dependent bottle
    keypoints, which lie on the silhouette) say nothing about the third direction: the
    third PCA axis is then the normal of the keypoint plane, roughly the viewing direction,
    never a symmetry axis. The axis is then the in-plane PCA axis (0 or 1) closest to
    ``up`` when given (e.g. the mean image-up direction of the class's cameras: bottles and
    tables stand upright in photos), else axis 0.

    Args:
        S: ``(K, 3)`` mean shape (object frame), NaN rows ignored.
        choice: ``None`` (automatic) or a PCA axis index in ``{0, 1, 2}``.
        up: optional ``(3,)`` direction (object frame) used for planar keypoint sets.
        planar_ratio: variance ratio below which the keypoints count as planar.

    Returns:
        ``(3,)`` unit axis in the object frame.

    Example:
        >>> S = torch.tensor([[0, 0, 5.0], [0, 0, -5], [1, 0, 0], [-1, 0, 0], [0, 1.1, 0], [0, -1.1, 0]])
        >>> symmetry_axis(S).abs()
        tensor([0., 0., 1.])
    """
    axes, var = principal_components(S)
    if choice is not None:
        if choice not in (0, 1, 2):
            raise ValueError(f"choice must be None or a PCA axis index in {{0, 1, 2}}, got {choice}")
        return axes[choice]
    v = var.double().clamp_min(torch.finfo(torch.float64).tiny)
    if float(v[2] / v[0]) < planar_ratio:
        if up is None:
            return axes[0]
        u = up.to(axes)
        return axes[0] if bool((axes[0] @ u).abs() >= (axes[1] @ u).abs()) else axes[1]
    top = torch.log(v[0] / v[1])
    bottom = torch.log(v[1] / v[2])
    return axes[0] if bool(top > bottom) else axes[2]


def axis_in_image_plane(cameras: ScaledOrthographic, axis: torch.Tensor) -> torch.Tensor:
    """Per camera, the symmetry axis turned into the camera's image plane.

    Photos of rotationally symmetric objects (bottles, pots) are mostly taken from the side,
    and with view-dependent, coplanar keypoints the out-of-plane tilt of an SfM camera is
    not determined by the data. This keeps the axis' direction *in the image* (the
    projection ``R[:2] @ axis``) and drops its depth component, so the reference is assumed
    to be seen perpendicular to its axis.

    Args:
        cameras: ``N`` cameras.
        axis: ``(3,)`` symmetry axis in the object frame.

    Returns:
        ``(N, 3)`` unit axes in the object frame (``R^T [a_x, a_y, 0]`` normalised). A camera
        looking exactly along the axis keeps the original axis.

    Example:
        >>> cam = ScaledOrthographic(torch.eye(3)[None], torch.ones(1), torch.zeros(1, 2))
        >>> axis_in_image_plane(cam, torch.tensor([0.0, 0.6, 0.8]))
        tensor([[0., 1., 0.]])
    """
    a = axis.to(cameras.R) / axis.norm()
    cam = cameras.R @ a  # (N, 3) in camera coordinates
    flat = torch.cat([cam[:, :2], torch.zeros_like(cam[:, 2:])], dim=-1)
    norm = flat.norm(dim=-1, keepdim=True)
    ok = norm > 1e-6
    out = (cameras.R.transpose(-1, -2) @ (flat / norm.clamp_min(1e-12)).unsqueeze(-1)).squeeze(-1)
    return torch.where(ok, out, a.expand_as(out))


def axis_through_silhouettes(cameras: ScaledOrthographic, masks: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """Per reference, the point ``centre`` moved within the reference's image plane onto its silhouette's centroid.

    A solid of revolution seen from the side has a silhouette symmetric about the projected axis, so the
    centroid of the silhouette lies on it; the class mean shape's centroid (the default rotation centre)
    projects wherever the keypoints and the camera put it, and an axis off the silhouette's middle by
    ``d`` pixels makes the reference's rotated copies carve ``2 d`` off its width. The depth of the
    point along the reference's viewing ray stays that of ``centre`` (it only moves the hull along the ray).

    Args:
        cameras: ``N`` reference cameras; masks: ``(N, H, W)`` bool their silhouettes (same pixels);
            centre: ``(3,)`` object-frame point.

    Returns:
        ``(N, 3)`` object-frame points projecting onto each silhouette's centroid (``centre`` for an
        empty mask).

    Example:
        >>> cam = ScaledOrthographic(torch.eye(3)[None], torch.full((1,), 2.0), torch.zeros(1, 2))
        >>> m = torch.zeros(1, 5, 9, dtype=torch.bool); m[0, 1:4, 5:8] = True   # centroid (x, y) = (6, 2)
        >>> axis_through_silhouettes(cam, m, torch.tensor([0.0, 0.0, 7.0]))
        tensor([[3., 1., 7.]])
    """
    if not isinstance(masks, torch.Tensor) or masks.dim() != 3 or masks.shape[0] != len(cameras):
        raise ValueError(f"masks must be a ({len(cameras)}, H, W) tensor like the cameras")
    m = masks.to(torch.float64)
    area = m.sum(dim=(1, 2))
    ys = torch.arange(m.shape[1], dtype=torch.float64, device=m.device)
    xs = torch.arange(m.shape[2], dtype=torch.float64, device=m.device)
    cx = (m.sum(dim=1) * xs).sum(dim=1) / area.clamp_min(1.0)
    cy = (m.sum(dim=2) * ys).sum(dim=1) / area.clamp_min(1.0)
    R, s, t = cameras.R.to(m), cameras.s.to(m), cameras.t.to(m)
    c = centre.to(m)
    seen = s[:, None] * (R[:, :2] @ c) + t  # (N, 2) where the reference sees ``centre``
    move = (torch.stack([cx, cy], dim=1) - seen) / s[:, None]
    move = torch.where((area > 0)[:, None], move, torch.zeros_like(move))
    out = c + (R[:, :2].transpose(-1, -2) @ move[..., None])[..., 0]
    return out.to(centre.dtype)


def symmetric_surrogates(
    camera: ScaledOrthographic, axis: torch.Tensor, step_deg: float = 90.0, centre: torch.Tensor | None = None
) -> ScaledOrthographic:
    """Cameras that stand in for surrogates of rotationally symmetric references.

    For each reference camera, camera ``k`` is ``R_k = R @ Rot(axis, k * step)`` for
    ``k = 1 .. 360/step - 1`` with the reference's ``s`` and ``t`` (``Rot`` right-handed,
    :func:`rotation_about_axis`). Seen from camera ``k``, a point ``X`` lands where the
    reference camera sees ``Rot(axis, k step) X``; carving the reference mask from all
    these cameras intersects the reference's visual cone with its rotated copies, i.e.
    assumes the object is a solid of revolution about ``axis`` through the object-frame
    origin. With ``centre = c`` the axis passes through ``c`` instead: the point seen is
    ``Rot (X - c) + c``, so ``t_k = t + s (R (c - Rot c))[:2]``.
    (The paper rotated every 45 degrees; the default here is 90.)

    Args:
        camera: ``ScaledOrthographic`` of ``N >= 1`` reference cameras.
        axis: ``(3,)`` symmetry axis in the object frame (:func:`symmetry_axis`), or ``(N, 3)`` one
            per reference (e.g. :func:`axis_in_image_plane`).
        step_deg: rotation step in degrees; ``360 / step_deg`` must be an integer ``>= 2``.
        centre: optional ``(3,)`` point of the axis (object frame), or ``(N, 3)`` one per reference
            (e.g. :func:`axis_through_silhouettes`); default the origin.

    Returns:
        ``ScaledOrthographic`` of length ``N * (360 / step_deg - 1)`` on the camera's device,
        reference-major: entries ``[i * m, (i + 1) * m)`` belong to reference ``i``.

    Example:
        >>> cam = ScaledOrthographic(torch.eye(3)[None], torch.ones(1), torch.zeros(1, 2))
        >>> len(symmetric_surrogates(cam, torch.tensor([0.0, 0, 1]), 45.0))
        7
    """
    if not isinstance(camera, ScaledOrthographic) or len(camera) < 1:
        raise ValueError("camera must be a non-empty ScaledOrthographic")
    if not isinstance(axis, torch.Tensor) or axis.shape not in ((3,), (len(camera), 3)):
        raise ValueError(f"axis must be a (3,) or ({len(camera)}, 3) tensor")
    if not bool(torch.isfinite(axis).all()) or float(axis.norm(dim=-1).min()) == 0.0:
        raise ValueError("axis must be finite and non-zero")
    if not step_deg > 0:
        raise ValueError(f"step_deg must be > 0, got {step_deg}")
    count = 360.0 / step_deg
    n = int(round(count))
    if abs(count - n) > 1e-6 or n < 2:
        raise ValueError(f"step_deg must divide 360 into at least 2 steps, got {step_deg}")
    N, m = len(camera), n - 1
    R0 = camera.R.double()  # (N, 3, 3)
    k = torch.arange(1, n, dtype=torch.float64, device=R0.device)
    angles = torch.deg2rad(k * float(step_deg))
    ax = axis.to(device=R0.device, dtype=torch.float64).reshape(-1, 1, 3).expand(N, m, 3)
    rot = rotation_about_axis(ax, angles.expand(N, m))  # (N, m, 3, 3)
    R = R0[:, None] @ rot  # (N, m, 3, 3)
    t = camera.t.double()[:, None, :].expand(N, m, 2).clone()
    if centre is not None:
        if not isinstance(centre, torch.Tensor) or centre.shape not in ((3,), (N, 3)):
            raise ValueError(f"centre must be None or a (3,) or ({N}, 3) tensor")
        c = centre.to(device=R0.device, dtype=torch.float64).reshape(-1, 1, 3, 1).expand(N, m, 3, 1)
        shift = (R0[:, None, :2] @ c - R[:, :, :2, :] @ c)[..., 0]  # (N, m, 2): R (c - Rot c), image rows
        t = t + camera.s.double()[:, None, None] * shift
    s_rep = camera.s[:, None].expand(N, m).reshape(-1).clone()
    return ScaledOrthographic(R.reshape(-1, 3, 3).to(camera.R.dtype), s_rep, t.reshape(-1, 2).to(camera.t.dtype))


# --------------------------------------------------------------------------- class plan


def cluster_instances(view_dirs: torch.Tensor, usable: torch.Tensor, axes: torch.Tensor,
                      cfg: SurrogateConfig, groups: torch.Tensor | None = None) -> Clusters:
    """:func:`cluster_by_direction` of the instances that have a camera, with the configured
    thresholds; the others get label ``-1`` (never surrogates).

    Args:
        view_dirs: ``(N, 3)`` viewing directions; usable: ``(N,)`` bool; axes: ``(3, 3)``;
        groups: optional ``(N,)`` long physical objects, counted instead of members with
        ``cfg.cluster_count_objects``.
    """
    labels = torch.full((len(view_dirs),), -1, dtype=torch.long, device=view_dirs.device)
    if not bool(usable.any()):
        return Clusters(labels, cfg.cluster_threshold_deg, torch.zeros(3, dtype=torch.long), ["no usable camera"])
    sub = cluster_by_direction(view_dirs[usable], axes, threshold_deg=cfg.cluster_threshold_deg,
                               widen_step_deg=cfg.cluster_widen_step_deg,
                               max_threshold_deg=cfg.cluster_max_threshold_deg,
                               groups=groups[usable] if groups is not None and cfg.cluster_count_objects else None)
    labels[usable] = sub.labels.to(labels.device)
    return Clusters(labels, float(sub.threshold_deg), sub.sizes, list(sub.log))


@dataclass
class SurrogatePlan:
    """Which silhouettes every proposal of a class carves.

    Views are *entries* of the class's prepared maps (:class:`carvi_torch.carve.CarveMaps`):
    rows ``0 .. 2N - 1`` are the originals and their mirrored copies; for a rotationally
    symmetric class, entries ``2N + k m + j`` are the ``m`` rotated cameras of the ``k``-th
    reference in ``todo``.

    Attributes:
        n: instances of the class (originals).
        axes: ``(3, 3)`` principal directions (rows).
        clusters: the instances' :class:`Clusters`.
        triplets: sampled :class:`Triplets` of every original (``None`` for a symmetric class).
        mirrors: whether proposals also carve the mirrored silhouettes.
        todo: the originals to reconstruct (host ints, in order); chunks are consecutive runs of it.
        rotated: rotated cameras per reference in ``todo`` (symmetric classes; 0 otherwise).
        levels: per original, where its proposals come from (:data:`LEVELS`; ``None``: no camera).
    """

    n: int
    axes: torch.Tensor
    clusters: Clusters
    triplets: Triplets | None
    mirrors: bool
    todo: list = field(default_factory=list)
    rotated: int = 0
    levels: list = field(default_factory=list)

    def __post_init__(self):
        self.set_todo(self.todo)

    def set_todo(self, todo: list) -> None:
        """The originals to reconstruct (host ints, in order)."""
        self.todo = list(todo)
        self._pos = {i: k for k, i in enumerate(self.todo)}

    def proposal_views(self, ids: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Views ``(R, P, V)`` long (entries of the maps) and validity ``(R, P)`` bool of the proposals
        of the references ``ids (R,)`` (a consecutive run of ``todo``)."""
        R = len(ids)
        if self.triplets is None:
            # one proposal per reference: its rotated cameras
            k = self._pos[int(ids[0])] + torch.arange(R, device=ids.device)
            views = 2 * self.n + k[:, None, None] * self.rotated + torch.arange(self.rotated, device=ids.device)
            return views, torch.ones(R, 1, dtype=torch.bool, device=ids.device)
        sur = self.triplets.surrogates[ids]  # (R, P, 2), -1: no surrogate in that slot (unused view)
        if not self.mirrors:
            return sur, self.triplets.valid[ids]
        r = ids[:, None, None].expand(-1, sur.shape[1], 1)
        mirrored = torch.where(sur >= 0, sur + self.n, torch.full_like(sur, -1))
        return torch.cat([sur, r + self.n, mirrored], dim=-1), self.triplets.valid[ids]

    def surrogates_of(self, ids: torch.Tensor) -> torch.Tensor | None:
        """``(R, P, 2)`` long surrogate originals of each proposal (``-1`` invalid), or ``None`` (symmetric)."""
        return None if self.triplets is None else self.triplets.surrogates[ids]

    def reason(self, i: int) -> str:
        """Why reference ``i`` has no valid proposal."""
        why = self.triplets.reasons.get(i) if self.triplets is not None else None
        return f"no valid surrogate triplet ({why or 'clusters too small'})"


#: Where a reference's proposals come from, most to least informed: two surrogates from two clusters
#: (a rotationally symmetric class: the reference seen from rotated cameras); the same from clusters
#: widened to every instance's nearest principal direction; one surrogate; the reference and its
#: mirrored copy alone; a puffball of the reference's silhouette (also for a reference whose every
#: proposal carved away to nothing).
LEVELS = ("triplet", "rotated_views", "widened_clusters", "surrogate_pair", "own_mirror", "puffball")


def _nearest_axis_labels(view_dirs: torch.Tensor, usable: torch.Tensor, axes: torch.Tensor) -> torch.Tensor:
    """Every usable instance in the cluster of its nearest principal direction (front or back)."""
    v = view_dirs.double() / view_dirs.double().norm(dim=-1, keepdim=True)
    nearest = (v @ axes.to(v).T).abs().argmax(dim=-1)
    return torch.where(usable, nearest, torch.full_like(nearest, -1))


def _pairs(groups: torch.Tensor, usable: torch.Tensor, refs: list, P: int, generator) -> torch.Tensor:
    """``(len(refs), P, 2)``: one surrogate per proposal (second slot -1), drawn without repetition
    among the usable instances of other physical objects; -1 rows where there is none."""
    out = torch.full((len(refs), P, 2), -1, dtype=torch.long)
    for k, r in enumerate(refs):
        cand = (usable & (groups != groups[r])).nonzero().squeeze(1).cpu()
        if len(cand):
            pick = cand[torch.randperm(len(cand), generator=generator)[:P]]
            out[k, :len(pick), 0] = pick
    return out


def plan_proposals(clusters: Clusters, groups: torch.Tensor, usable: torch.Tensor, view_dirs: torch.Tensor,
                   axes: torch.Tensor, proposals: int, mirrors: bool,
                   generator: torch.Generator) -> tuple[Triplets, list]:
    """Triplets of every original, and a fallback for every reference that has none (:data:`LEVELS`).

    Args:
        clusters: the instances' :class:`Clusters`; groups: ``(N,)`` long physical objects;
        usable: ``(N,)`` bool instances with a camera; view_dirs: ``(N, 3)``; axes: ``(3, 3)``.
        proposals: ``P``; mirrors: whether the mirrored silhouettes are carved too.
        generator: the class's random source (triplets first, then the fallbacks).

    Returns:
        :class:`Triplets` (``N`` rows; a pair has its second surrogate -1, ``own_mirror`` both) and the
        level of every original (``None`` for one without a camera).
    """
    n, dev = len(usable), usable.device
    trip = sample_triplets(clusters.labels, groups, torch.arange(n, device=dev), proposals=proposals,
                           generator=generator)
    has = trip.valid.any(dim=1)
    levels = [("triplet" if h else None) if u else None for h, u in zip(has.tolist(), usable.tolist())]
    failing = [i for i, lv in enumerate(levels) if lv is None and bool(usable[i])]
    if not failing:
        return trip, levels
    idx = torch.tensor(failing, device=dev)
    wide = sample_triplets(_nearest_axis_labels(view_dirs, usable, axes), groups, idx, proposals=proposals,
                           generator=generator)
    sur, valid = trip.surrogates.clone(), trip.valid.clone()
    sur[idx], valid[idx] = wide.surrogates, wide.valid
    rest = [i for i, ok in zip(failing, wide.valid.any(dim=1).tolist()) if not ok]
    for i in failing:
        levels[i] = "widened_clusters"
    pairs = _pairs(groups.cpu(), usable.cpu(), rest, proposals, generator).to(dev)
    for k, i in enumerate(rest):
        if bool((pairs[k, :, 0] >= 0).any()):
            sur[i], valid[i], levels[i] = pairs[k], pairs[k, :, 0] >= 0, "surrogate_pair"
        elif mirrors:
            sur[i, 0], valid[i, 0], levels[i] = -1, True, "own_mirror"
        else:
            levels[i] = "puffball"
    return Triplets(sur, valid, trip.reasons, trip.clusters), levels


def rotated_cameras(cams: ScaledOrthographic, shape: torch.Tensor, todo: torch.Tensor, centre: torch.Tensor,
                    cfg: SurrogateConfig, masks: torch.Tensor | None = None) -> tuple[ScaledOrthographic, int]:
    """A rotationally symmetric class's synthetic surrogates: every reference in ``todo`` seen from
    cameras rotated about the symmetry axis (:func:`symmetric_surrogates`).

    Args:
        cams: the class's ``(2N)`` cameras (originals first); shape: ``(K, 3)`` mean shape;
        todo: ``(T,)`` long references; centre: ``(3,)`` rotation centre; masks: the originals'
        ``(N, H, W)`` bool silhouettes, needed with ``cfg.symmetric_axis_through_silhouette``
        (:func:`axis_through_silhouettes`).

    Returns:
        the cameras, reference-major (``T * m``), and ``m`` per reference.
    """
    n = len(cams) // 2
    up = -cams.R[:n, 1, :].mean(dim=0)  # mean image-up direction in the object frame
    axis = symmetry_axis(shape, up=up)
    if cfg.symmetric_axis_in_image:
        axis = axis_in_image_plane(cams[todo], axis)
    if cfg.symmetric_axis_through_silhouette:
        if masks is None:
            raise ValueError("symmetric_axis_through_silhouette needs the references' masks")
        centre = axis_through_silhouettes(cams[todo], masks[todo], centre)
    extra = symmetric_surrogates(cams[todo], axis, step_deg=cfg.symmetric_step_deg, centre=centre)
    return extra, len(extra) // len(todo)
