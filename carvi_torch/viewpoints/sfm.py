"""Rigid structure from motion with missing data (Marques & Costeira 2008), batched.

Finds one mean shape ``S`` for a whole class and one scaled orthographic camera per
instance from the instances' 2-D keypoints, some of which are missing:

    minimise  sum_n sum_{k visible in n} || w_nk - (s_n R_n[:2] S_k + t_n) ||^2

Conventions (``carvi_torch.cameras``): image x right, y down, points ``(x, y)``;
``uv = s * X @ R[:2].T + t``, depth ``z = s * X @ R[2]`` (pixels, into the scene),
``R`` proper. Keypoints are in *canvas* pixels (every instance cropped and scaled into
one square canvas), so instances have comparable sizes.

The factorisation (:mod:`carvi_torch.viewpoints.factorization`) alternates filling the missing
entries of the measurement matrix ``W (2N, K)`` from the current model with power
factorisation steps whose ``2x3`` blocks are projected onto scaled rotations, with a
per-instance safeguard against depth-reversed poses, until the visible-entry residual
settles.

Before the factorisation, instances and keypoints are restricted to the largest
connected group of the visibility graph (an instance and a keypoint are linked when
the instance sees it): groups that share no keypoint have unrelated frames, so the
others are invalid, with the reason (PASCAL3D+'s diningtable: one CAD model's
table-top keypoints carry names no other model uses).

Then a **bundle polish** (``polish_iters`` rounds, the factorisation's stopping rule): alternate
every camera's constrained least-squares fit to the shape on its visible keypoints
(a few Levenberg-Marquardt steps on scaled rotations, ``refine.refine_cameras``
without the silhouette) and the shape's exact least-squares solve given the cameras;
or, with ``polish="joint"``, Levenberg-Marquardt over every camera and the shape at once
(:mod:`carvi_torch.viewpoints.bundle`), which settles in far fewer rounds.
Both steps lower the objective, which the factorisation's "solve unconstrained, then
project" steps do not guarantee on noisy data: on the 330 real PASCAL VOC aeroplanes
(with mirrors) the polish took the RMS residual from 8.0 to 5.9 canvas pixels and
the median viewpoint error against PASCAL3D+ from 18 to 12 degrees.

The camera's third row is the cross product of the first two, so ``R`` is proper.
Orthographic SfM cannot distinguish ``S`` from its mirror image (depths negated):
see :func:`rigid_sfm` for how this reflection (Necker) ambiguity is resolved.

All tensors of one call live on one device; the factorisation runs in float64
(the matrices are small: ``2N x K``) and results come back in the keypoints' dtype.
"""
from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np
import torch

from ..cameras import ScaledOrthographic, complete_rotation, geodesic_angle, scaled_stiefel
from ..collection import keypoint_side
from ..runtime import cpu_single_thread
from .bundle import joint_bundle_adjust
from .camera_fit import refine_cameras
from .factorization import factorize, planar_factorize, resect, visible_translation

__all__ = [
    "SfMResult",
    "SfMOptions",
    "rigid_sfm",
    "symmetry_plane",
    "mirror_width",
    "triangulate",
    "resect_cameras",
    "keypoint_side",
    "keypoint_end",
    "WARM_OUTER",
    "bundle_polish",
    "outside_main_component",
    "mirror_layout",
    "mirror_tie_angles",
    "MirrorLayout",
    "PolishMethod",
    "POLISH_METHODS",
]

#: How the bundle polish after the factorisation minimises (:func:`bundle_polish`): ``alternate`` (cameras,
#: then the shape, in turn) or ``joint`` (Levenberg-Marquardt over both at once, ``viewpoints.bundle``).
PolishMethod = Literal["alternate", "joint"]
POLISH_METHODS = typing.get_args(PolishMethod)

#: ``diag(1, 1, -1)``: the reflection that maps a solution onto its Necker mirror.
_FLIP_Z = (1.0, 1.0, -1.0)


# --------------------------------------------------------------------------- result


@dataclass
class SfMResult:
    """Output of :func:`rigid_sfm`.

    Attributes:
        shape: ``(K, 3)`` mean shape in the object frame, centred (mean of its finite
            rows is 0) and scaled so that the median camera scale of the valid
            instances is 1 (the shape is in canvas pixels of a typical instance).
            Rows of keypoints that could not be reconstructed are NaN.
        cameras: N scaled orthographic cameras (canvas pixels). Entries of invalid
            instances are placeholders: ``R = I``, ``s = 1``, ``t`` = mean of their
            visible keypoints (or 0).
        valid: ``(N,)`` bool, instances with >= 2 visible rigid keypoints in the
            largest connected group of the visibility graph (instances linked by shared
            keypoints) whose camera came out of the factorisation finite, with a
            non-zero scale. Every other instance has a reason in ``reasons``; no
            camera entry is ever NaN.
        residual: ``(N,)`` RMS reprojection error (pixels) of the visible keypoints
            used by the SfM (the rigid ones); NaN for invalid instances.
        residual_all: ``(N,)`` the same over all visible keypoints with a finite
            shape row (the non-rigid ones included).
        iterations: outer factorisation iterations run.
        polish_rounds: bundle-polish rounds run (0 for the planar model; ``polish="joint"``: accepted
            Levenberg-Marquardt steps).
        converged: whether the last stage's stopping rule fired before its limit.
        reflection_votes: how the reflection was decided: ``{"for": int, "against":
            int, "voters": int, "decided_by": "visibility" | "handedness" |
            "visibility (weak)" | "not applicable (planar)" | "none", "flipped": bool,
            "handedness": float | None}``
            (``for`` = instances whose visible keypoints are nearer the camera than
            their hidden ones in the returned frame).
        planar: whether the rigid keypoints were treated as coplanar.
        seen: ``(K,)`` int64, number of valid instances in which each keypoint is visible.
        never_visible: indices of keypoints visible in no instance (shape rows NaN).
        rigid_keypoints: the keypoint indices the factorisation used.
        reasons: per instance, ``""`` when valid, else why it has no camera.
        problems: human-readable messages for the class's summary.
        history: visible-entry RMS residual (pixels) after every outer iteration,
            then after every polish round.
        mirrors: empty when the instances hold no mirrored copies, else
            ``{"width": C, "tie_deg_median": float | None, "reseeded": bool, ...}``:
            the median angle between each copy's camera and its original's camera
            mirrored through the shape's symmetry plane (0 for a solution consistent
            with the object's symmetry), and whether the solution was re-seeded from
            the originals (with both residuals, ``rms_joint`` and ``rms_seeded``).
        filled: ``(K,)`` bool, the shape's rows taken from another shape rather than placed by this SfM (a
            shape group's rows its objects do not show, :func:`carvi_torch.viewpoints.mixture.fill_missing_rows`);
            ``None``: none.
    """

    shape: torch.Tensor
    cameras: ScaledOrthographic
    valid: torch.Tensor
    residual: torch.Tensor
    residual_all: torch.Tensor
    iterations: int
    polish_rounds: int
    converged: bool
    reflection_votes: dict
    planar: bool
    seen: torch.Tensor
    never_visible: list[int]
    rigid_keypoints: list[int]
    reasons: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    history: list[float] = field(default_factory=list)
    mirrors: dict = field(default_factory=dict)
    filled: torch.Tensor | None = None

    def summary(self) -> dict:
        """JSON-ready summary (counts, flags, messages) for ``summary.json``."""
        res = self.residual[self.valid]
        return {
            "instances": int(self.valid.numel()),
            "valid": int(self.valid.sum()),
            "iterations": int(self.iterations),
            "polish_rounds": int(self.polish_rounds),
            "converged": bool(self.converged),
            "planar": bool(self.planar),
            "median_residual_px": float(res.median()) if res.numel() else None,
            "reflection": dict(self.reflection_votes),
            "never_visible": list(self.never_visible),
            "rigid_keypoints": list(self.rigid_keypoints),
            "invalid": {int(i): r for i, r in enumerate(self.reasons) if r},
            "problems": list(self.problems),
            "mirrors": dict(self.mirrors),
        }


# --------------------------------------------------------------------------- names


_FRONT = ("front", "nose", "head")
_BACK = ("back", "tail", "rear")


def keypoint_end(name: str) -> str | None:
    """``"front"``, ``"back"`` or ``None`` from a keypoint name.

    Front: the lower-cased name contains ``front``, ``nose`` or ``head``
    (``headlight`` too); back: ``back``, ``tail`` or ``rear``. Both or neither: ``None``.

    Example:
        >>> keypoint_end("NoseTip"), keypoint_end("left_back_wheel"), keypoint_end("left_wing")
        ('front', 'back', None)
    """
    low = name.lower()
    f = any(w in low for w in _FRONT)
    b = any(w in low for w in _BACK)
    if f == b:
        return None
    return "front" if f else "back"


# --------------------------------------------------------------------------- helpers


def _check_inputs(keypoints: torch.Tensor, visible: torch.Tensor) -> None:
    if not isinstance(keypoints, torch.Tensor) or keypoints.dim() != 3 or keypoints.shape[-1] != 2:
        raise ValueError(f"keypoints must be a (N, K, 2) tensor, got {getattr(keypoints, 'shape', type(keypoints))}")
    if not keypoints.is_floating_point():
        raise ValueError(f"keypoints must be floating point, got {keypoints.dtype}")
    if not isinstance(visible, torch.Tensor) or visible.shape != keypoints.shape[:2]:
        raise ValueError(f"visible must be a (N, K) tensor matching keypoints {tuple(keypoints.shape[:2])}, "
                         f"got {getattr(visible, 'shape', type(visible))}")
    if keypoints.shape[0] == 0 or keypoints.shape[1] == 0:
        raise ValueError(f"keypoints must hold at least one instance and one keypoint, got {tuple(keypoints.shape)}")


def _flip_z(dtype, device) -> torch.Tensor:
    return torch.diag(torch.tensor(_FLIP_Z, dtype=dtype, device=device))


def outside_main_component(seen: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Instances and keypoints outside the largest connected group of the visibility graph.

    The graph links instance ``n`` and keypoint ``k`` when ``seen[n, k]``. Two groups
    that share no keypoint have unrelated frames (each could be rotated or reflected
    on its own), so one factorisation cannot place both. The main group is the
    component with the most instances (ties: the most keypoints, then the first).
    Instances and keypoints without any edge belong to no group and are not
    reported (other checks cover them).

    Args:
        seen: ``(N, K)`` bool.

    Returns:
        ``(N,)`` bool instances and ``(K,)`` bool keypoints that have an edge but lie
        outside the main component.

    Example:
        >>> seen = torch.tensor([[1, 1, 0, 0], [1, 1, 0, 0], [0, 0, 1, 1]], dtype=torch.bool)
        >>> [x.tolist() for x in outside_main_component(seen)]
        [[False, False, True], [False, False, True, True]]
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    n, k = seen.shape
    rows, cols = seen.nonzero(as_tuple=True)
    rows, cols = rows.cpu().numpy(), cols.cpu().numpy()
    graph = coo_matrix((np.ones(len(rows)), (rows, n + cols)), shape=(n + k, n + k))
    _, labels = connected_components(graph, directed=False)
    labels = torch.as_tensor(labels, device=seen.device)
    li, lk = labels[:n], labels[n:]
    has_i, has_k = seen.any(1), seen.any(0)
    if not bool(has_i.any()):
        return torch.zeros_like(has_i), torch.zeros_like(has_k)
    n_lab = int(labels.max()) + 1
    ci = torch.bincount(li[has_i], minlength=n_lab)
    ck = torch.bincount(lk[has_k], minlength=n_lab)
    main = int(torch.argmax(ci * (k + 1) + ck))  # most instances, then most keypoints, then first
    return has_i & (li != main), has_k & (lk != main)


def bundle_polish(M, t, S, W, vis, *, iters, tol, lm_iters=5, method: PolishMethod = "alternate",
                  native: bool = False):
    """Bundle polish of a rigid solution on the visible entries.

    ``method="alternate"`` (block coordinate descent) alternates (a) every camera's constrained
    least-squares fit to the current shape (:func:`carvi_torch.viewpoints.camera_fit.refine_cameras` with
    the keypoint term only: ``lm_iters`` Levenberg-Marquardt steps on scaled rotations, never raising an
    instance's residual) and (b) the shape's exact least-squares solve given the cameras
    (:func:`triangulate`); one round is (a) then (b). ``method="joint"``: Levenberg-Marquardt over every
    camera and the shape at once (:func:`carvi_torch.viewpoints.bundle.joint_bundle_adjust`); one round
    is one damped solve (``native``: on the CPU, in the compiled kernel, equal to rounding). Both lower the
    visible-entry residual, which the factorisation's "unconstrained solve, then project" steps do not
    guarantee on noisy data. Stops when the RMS residual changes by
    less than ``tol`` (relative), reaches the exact-fit floor, or after ``iters`` rounds. Degenerate
    blocks (:func:`_usable_blocks`) sit out and keep theirs.

    Args: ``M (N, 2, 3)``, ``t (N, 2)``, ``S (3, K)``, ``W (N, 2, K)``, ``vis (N, K)`` float.

    Returns ``M, t, S, history, converged`` (history: the RMS residual after every (accepted) round).
    """
    if method not in POLISH_METHODS:
        raise ValueError(f"method must be one of {POLISH_METHODS}, got {method!r}")
    kp = W.transpose(1, 2).contiguous()
    s = M[:, 0].norm(dim=-1)
    # degenerate blocks (zero scale: e.g. an instance whose visible keypoints coincide in
    # the shape) would turn into NaN cameras and, through the shape solve, NaN everywhere:
    # they sit out the polish and keep their block
    ok = _usable_blocks(M, t)
    vis = vis * ok[:, None]
    visb = vis > 0
    eye = torch.eye(3, dtype=M.dtype, device=M.device)
    R0 = torch.where(ok[:, None, None], complete_rotation(M / s.clamp(min=1e-300)[:, None, None]), eye)
    cams = ScaledOrthographic(R0, torch.where(ok, s, torch.ones_like(s)), torch.where(ok[:, None], t, 0.0))
    shape = S.T.contiguous()
    floor = 1e-5 * float(((W - (W * vis[:, None]).sum(-1, keepdim=True) / vis.sum(-1).clamp(min=1)[:, None, None])
                          .pow(2) * vis[:, None]).sum() / (2 * vis.sum()).clamp(min=1)) ** 0.5
    if method == "joint":
        res = joint_bundle_adjust(cams, shape, kp, visb, iters=iters, tol=tol, floor=floor, native=native)
        cams, shape, history, converged = res.cameras, res.shape, res.history, res.converged
    else:
        cams, shape, history, converged = _alternate(cams, shape, kp, visb, iters, tol, floor, lm_iters)
    M_out = torch.where(ok[:, None, None], cams.M, M)
    t_out = torch.where(ok[:, None], cams.t, t)
    return M_out, t_out, shape.T.contiguous(), history, converged


def _alternate(cams: ScaledOrthographic, shape, kp, visb, iters: int, tol: float, floor: float, lm_iters: int):
    """The alternation of :func:`bundle_polish` from ``cams`` and ``shape (K, 3)`` on ``kp (N, K, 2)``,
    ``visb (N, K)`` bool; returns ``cams, shape, history, converged``."""
    count = (2 * visb.sum()).clamp(min=1)

    def rms(c, X):
        e = torch.where(visb, ((c.project(X) - kp) ** 2).sum(-1), 0.0)
        return float((e.sum() / count).sqrt())

    history: list[float] = []
    prev = rms(cams, shape)
    converged = iters == 0
    for _ in range(iters):
        cams = refine_cameras(shape, cams, kp, visb, None, max_iters=lm_iters, tol=1e-12).cameras
        shape = triangulate(cams, kp, visb, min_views=1)
        cur = rms(cams, shape)
        history.append(cur)
        if cur <= floor or prev - cur <= tol * prev:
            converged = True
            break
        prev = cur
    return cams, shape, history, converged


def _usable_blocks(M: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``(N,)`` bool: camera blocks ``M (N, 2, 3)``, ``t (N, 2)`` that are finite with a scale above
    ``1e-6`` of the median finite scale (a zero block carries no rotation)."""
    s = M[:, 0].norm(dim=-1)
    fin = torch.isfinite(M).flatten(1).all(1) & torch.isfinite(t).all(1) & torch.isfinite(s)
    if not bool(fin.any()):
        return fin
    return fin & (s > 1e-6 * s[fin].median())


def mirror_width(keypoints: torch.Tensor, visible: torch.Tensor, flip_pairs: Sequence[Sequence[int]] | None,
                 atol: float = 1e-3) -> float | None:
    """Canvas width ``C`` when instances ``N/2..N-1`` are the mirrored copies of ``0..N/2-1``, else ``None``.

    The pipeline's mirrored copy of an instance (``ClassCollection.mirror``) has
    ``x' = C - 1 - x``, the same ``y``, and its keypoints relabelled along the flip
    pairs (and so its visibility). This checks exactly that layout on the visible
    entries (tolerance ``atol`` times ``1 +`` the largest coordinate) and returns ``C``.

    Args:
        keypoints: ``(N, K, 2)``; visible: ``(N, K)`` bool; flip_pairs: ``(i, j)`` pairs or None.

    Example:
        >>> kp = torch.tensor([[[1.0, 2.0], [5.0, 3.0]]]); vis = torch.ones(1, 2, dtype=torch.bool)
        >>> m = torch.stack([9.0 - kp[0, [1, 0], 0], kp[0, [1, 0], 1]], -1)[None]
        >>> mirror_width(torch.cat([kp, m]), torch.cat([vis, vis]), [(0, 1)])
        10.0
    """
    n, k = visible.shape
    if n < 2 or n % 2:
        return None
    h = n // 2
    perm = list(range(k))
    for i, j in flip_pairs or []:
        perm[int(i)], perm[int(j)] = int(j), int(i)
    perm_t = torch.tensor(perm, device=visible.device)
    v0, v1 = visible[:h], visible[h:]
    if not bool(v1.any()) or not torch.equal(v1, v0[:, perm_t]):
        return None
    a, b = keypoints[:h][:, perm_t], keypoints[h:]
    sx = (a[..., 0] + b[..., 0])[v1].double()
    dy = (a[..., 1] - b[..., 1])[v1].double()
    tol = atol * (1.0 + float(keypoints[visible].abs().max()))
    c = float(sx.median())
    if not math.isfinite(c) or float((sx - c).abs().max()) > tol or float(dy.abs().max()) > tol:
        return None
    return c + 1.0


@dataclass
class MirrorLayout:
    """Where each factorised row's mirrored copy is (rows = valid instances)."""

    partner: torch.Tensor  # (Nv,) long: row of the mirrored copy of an original (or of the original), -1: none
    original: torch.Tensor  # (Nv,) bool: rows of the first half
    width: float  # canvas width C (x' = C - 1 - x)
    pairs: list  # flip pairs as column positions of the factorised matrix


def mirror_layout(valid: torch.Tensor, width: float, flip_pairs, cols: list[int]) -> MirrorLayout:
    """Mirror pairing among the factorised rows (``valid (N,)`` bool, copy of ``i`` at ``i + N/2``)."""
    n = valid.shape[0]
    h = n // 2
    pos = torch.cumsum(valid.long(), 0) - 1
    idx = valid.nonzero().squeeze(1)
    other = torch.where(idx < h, idx + h, idx - h)
    partner = torch.where(valid[other], pos[other], torch.full_like(other, -1))
    where = {c: p for p, c in enumerate(cols)}
    pairs = [(where[int(i)], where[int(j)]) for i, j in (flip_pairs or []) if int(i) in where and int(j) in where]
    return MirrorLayout(partner, idx < h, float(width), pairs)


_FLIP_IMAGE_X = (-1.0, 1.0)


def _mirror_blocks(M: torch.Tensor, t: torch.Tensor, P: torch.Tensor, width: float):
    """Camera blocks of the mirrored images: ``M' = diag(-1, 1) M P``, ``t' = (C - 1 - t_x, t_y)``.

    As ``ScaledOrthographic.mirror(width, reflection=P)``: the mirrored image of an
    object with symmetry plane ``P (3, 3)`` seen by ``M (N, 2, 3)``, ``t (N, 2)``.
    """
    f = torch.tensor(_FLIP_IMAGE_X, dtype=M.dtype, device=M.device)
    tm = t.clone()
    tm[:, 0] = width - 1.0 - t[:, 0]
    return f[:, None] * (M @ P), tm


def mirror_tie_angles(M: torch.Tensor, S: torch.Tensor, mir: MirrorLayout) -> torch.Tensor | None:
    """Angles (degrees) between each mirrored copy's camera and its original's camera mirrored.

    A solution consistent with the object's bilateral symmetry has them equal (the
    copies are the originals' images flipped). ``None`` when no pair of symmetric
    keypoints defines the symmetry plane of ``S (3, Kc)``.

    Returns ``(P,)`` float64 for the originals whose copy is a row too.
    """

    has = mir.original & (mir.partner >= 0)
    if not bool(has.any()) or not mir.pairs:
        return None
    try:
        P = symmetry_plane(S.T, mir.pairs)
    except ValueError:
        return None
    Mo, _ = _mirror_blocks(M[has], torch.zeros_like(M[has, :, 0]), P, mir.width)
    Mm = M[mir.partner[has]]
    Ro = complete_rotation(Mo / Mo[:, 0].norm(dim=-1).clamp(min=1e-300)[:, None, None])
    Rm = complete_rotation(Mm / Mm[:, 0].norm(dim=-1).clamp(min=1e-300)[:, None, None])
    return torch.rad2deg(geodesic_angle(Ro, Rm))


def _seed_from_originals(Wv, vv, mir: MirrorLayout, M_joint, t_joint, polish_iters, polish_method, **kw):
    """Solve the originals alone, derive their copies' cameras by mirroring, polish all rows together.

    Returns ``M, t, S, history`` (history: originals' factorisation and polish, then the joint polish).
    """
    o = mir.original
    Mo, to, So, hist, _, _ = factorize(Wv[o], vv[o], rank=3, **kw)
    Mo, to, So, ph, _ = bundle_polish(Mo, to, So, Wv[o], vv[o], iters=polish_iters, tol=kw["tol"],
                                      method=polish_method, native=kw.get("native", False))
    seen = vv[o].sum(0)
    pairs = [(i, j) for i, j in mir.pairs if seen[i] >= 2 and seen[j] >= 2]
    M, t = M_joint.clone(), t_joint.clone()
    M[o], t[o] = Mo, to
    try:
        P = symmetry_plane(So.T, pairs)
    except ValueError:
        return None
    rows = o.nonzero().squeeze(1)
    has = mir.partner[rows] >= 0
    Mm, tm = _mirror_blocks(Mo[has], to[has], P, mir.width)
    M[mir.partner[rows[has]]] = Mm
    t[mir.partner[rows[has]]] = tm
    # every keypoint from every camera (a keypoint the originals never show is seen by their copies)
    s = M[:, 0].norm(dim=-1)
    cams = ScaledOrthographic(complete_rotation(M / s[:, None, None]), s, t)
    S = triangulate(cams, Wv.transpose(1, 2), vv > 0, min_views=1).T
    S = torch.where(torch.isfinite(S), S, So)
    M, t, S, ph2, _ = bundle_polish(M, t, S, Wv, vv, iters=polish_iters, tol=kw["tol"], method=polish_method,
                                    native=kw.get("native", False))
    return M, t, S, hist + ph + ph2


@dataclass
class _Fit:
    """The factorisation's solution on the valid instances and the keypoints ``cols``."""

    M: torch.Tensor  # (Nv, 2, 3)
    t: torch.Tensor  # (Nv, 2)
    S: torch.Tensor  # (3, Kc)
    history: list
    iterations: int
    polish_rounds: int
    converged: bool
    planar: bool
    mirrors: dict


#: Outer steps of a warm-started factorisation (``rigid_sfm(init_shape=...)``). From a near
#: solution the bundle polish converges in a few Gauss-Newton rounds, while the alternation's
#: slow tail (the missing entries' fill) would take about as many steps as a cold start: on the
#: 2,000-instance benchmark class, half of it started from the whole class's shape took 163
#: outer steps to stop, against 145 cold.
WARM_OUTER = 10


def _fit(Wv, vv, planar, planar_margin, polish_iters, mirrors: MirrorLayout | None = None, tie_deg: float = 5.0,
         S_init: torch.Tensor | None = None, polish_method: PolishMethod = "alternate", **kw):
    """Rigid (factorisation + polish) or planar solution; ``planar=None`` picks by residual.

    With ``mirrors`` (rows that are mirrored copies of others), a rigid solution whose
    copies' cameras are not their originals' mirrored (median angle above ``tie_deg``)
    fell into a minimum that breaks the object's symmetry; it is solved again from the
    originals alone (:func:`_seed_from_originals`) and the lower residual is kept.

    ``S_init (3, Kc)``: start of the rigid factorisation, which then runs at most
    :data:`WARM_OUTER` outer steps before the polish (the planar one and a re-seed start cold).

    Returns :class:`_Fit`.
    """
    report: dict = {}
    if planar is True:
        M, tv, Sc, history, iters, converged = planar_factorize(Wv, vv, **kw)
        return _Fit(M, tv, Sc, history, iters, 0, converged, True, report)
    kw3 = kw if S_init is None else dict(kw, max_outer=min(kw["max_outer"], WARM_OUTER))
    M, tv, Sc, history, iters, converged = factorize(Wv, vv, rank=3, S_init=S_init, **kw3)
    M, tv, Sc, phist, pconv = bundle_polish(M, tv, Sc, Wv, vv, iters=polish_iters, tol=kw["tol"],
                                            method=polish_method, native=kw.get("native", False))
    history = history + phist
    converged = pconv if polish_iters > 0 else converged
    if mirrors is not None:
        tie = mirror_tie_angles(M, Sc, mirrors)
        report = {"width": mirrors.width, "tie_deg_median": None if tie is None else float(tie.median()),
                  "reseeded": False}
        if tie is not None and float(tie.median()) > tie_deg and int(mirrors.original.sum()) >= 2:
            seeded = _seed_from_originals(Wv, vv, mirrors, M, tv, polish_iters, polish_method, **kw)
            report["rms_joint"] = history[-1]
            if seeded is not None:
                report["rms_seeded"] = seeded[3][-1]
                tie2 = mirror_tie_angles(seeded[0], seeded[2], mirrors)
                report["tie_deg_median_seeded"] = None if tie2 is None else float(tie2.median())
                if seeded[3][-1] < history[-1]:
                    M, tv, Sc = seeded[:3]
                    history = history + seeded[3]
                    phist = seeded[3]
                    report["reseeded"] = True
                    report["tie_deg_median_joint"] = report["tie_deg_median"]
                    report["tie_deg_median"] = report["tie_deg_median_seeded"]
    if planar is None:
        # a shorter planar fit decides; a planar winner is then run to the end
        max_outer = kw["max_outer"]
        short = dict(kw, max_outer=max(10, max_outer // 4))
        sol_p = planar_factorize(Wv, vv, **short)
        floor = 1e-5 * float(Wv.std())
        if sol_p[3][-1] <= history[-1] * (1.0 + planar_margin) + floor:
            if not sol_p[5] and short["max_outer"] < max_outer:
                sol_p = planar_factorize(Wv, vv, **kw)
            M, tv, Sc, history, iters, converged = sol_p
            return _Fit(M, tv, Sc, history, iters, 0, converged, True, {})
    return _Fit(M, tv, Sc, history, iters, len(phist), converged, False, report)


def resect_cameras(shape: torch.Tensor, keypoints: torch.Tensor, visible: torch.Tensor,
                   reg: float = 1e-6) -> tuple[ScaledOrthographic, torch.Tensor]:
    """Cameras of every instance from its keypoints and a known shape, in closed form.

    Per instance, the affine map ``[M t]`` (``2x3`` and ``2``) that best projects the shape's
    rows onto the visible keypoints (least squares, lightly pulled towards ``M = 0`` by the
    relative Tikhonov weight ``reg``, as the factorisation's per-instance resection), then ``M``
    projected onto the nearest scaled rotation (:func:`scaled_stiefel`) and the translation
    re-solved. Exact for noise-free projections of the shape seen at 4 or more non-coplanar
    keypoints; a start for an iterative fit otherwise (no search: one batched ``4x4`` solve).

    Args:
        shape: ``(K, 3)`` (NaN rows: keypoints it lacks, ignored).
        keypoints: ``(N, K, 2)`` pixels; visible: ``(N, K)`` bool (non-finite entries ignored).
        reg: relative Tikhonov weight.

    Returns:
        ``cameras`` (N, the keypoints' dtype) and ``ok (N,)`` bool: a finite camera with a
        positive scale (False, e.g., for instances with fewer than 2 usable keypoints; their
        camera is then an arbitrary placeholder).

    Example:
        >>> from carvi_torch.cameras import random_rotations
        >>> g = torch.Generator().manual_seed(0)
        >>> S = torch.randn(8, 3, generator=g); R = random_rotations(5, g)
        >>> kp = 30 * S @ R[:, :2].transpose(1, 2) + 64
        >>> cams, ok = resect_cameras(S, kp, torch.ones(5, 8, dtype=torch.bool))
        >>> bool(ok.all()), bool(torch.allclose(cams.R, R, atol=1e-4))
        (True, True)
    """
    dt, dev = keypoints.dtype, keypoints.device
    n = keypoints.shape[0]
    use = visible & torch.isfinite(shape).all(-1)[None] & torch.isfinite(keypoints).all(-1)
    S = torch.nan_to_num(shape.to(device=dev, dtype=torch.float64)).T.contiguous()  # (3, K)
    W = torch.nan_to_num(keypoints.double()).transpose(1, 2)  # (N, 2, K)
    enough = use.sum(-1) >= 2
    vis = torch.where(enough[:, None], use, torch.ones_like(use)).double()  # others: solved for nothing, not ok
    M, solved = resect(S, W, vis, torch.zeros(n, 2, 3, dtype=torch.float64, device=dev), reg, checked=True)
    enough = enough & solved
    M = scaled_stiefel(torch.where(enough[:, None, None], M, torch.zeros_like(M)))
    t, _ = visible_translation(M, S, W, vis)
    s = M[:, 0].norm(dim=-1)
    ok = torch.isfinite(M).flatten(1).all(-1) & torch.isfinite(t).all(-1) & (s > 1e-12) & enough
    eye = torch.eye(3, dtype=torch.float64, device=dev)
    R = torch.where(ok[:, None, None], complete_rotation(M / s.clamp(min=1e-12)[:, None, None]), eye)
    s = torch.where(ok, s, torch.ones_like(s))
    t = torch.where(ok[:, None], t, torch.zeros_like(t))
    return ScaledOrthographic(R.to(dt), s.to(dt), t.to(dt)), ok


def triangulate(cameras: ScaledOrthographic, keypoints: torch.Tensor, visible: torch.Tensor,
                min_views: int = 2, reg: float = 1e-9) -> torch.Tensor:
    """Least-squares 3-D points from scaled orthographic cameras.

    ``X_k = argmin sum_{n: visible[n, k]} || s_n R_n[:2] X - (w_nk - t_n) ||^2``: one
    ``3x3`` normal-equation solve per keypoint, batched (a tiny Tikhonov term,
    ``reg`` relative, keeps two-view solves defined).

    Args:
        cameras: N cameras.
        keypoints: ``(N, K, 2)`` pixels.
        visible: ``(N, K)`` bool.
        min_views: keypoints seen fewer times get NaN.

    Returns:
        ``(K, 3)`` in the keypoints' dtype; NaN rows where seen ``< min_views``.
    """
    dt = keypoints.dtype
    M = cameras.M.double()  # (N, 2, 3)
    w = keypoints.double() - cameras.t.double()[:, None, :]  # (N, K, 2)
    v = (visible & torch.isfinite(keypoints).all(-1)).double()
    A = torch.einsum("nk,nri,nrj->kij", v, M, M)  # (K, 3, 3)
    b = torch.einsum("nk,nri,nkr->ki", v, M, torch.nan_to_num(w))  # (K, 3)
    lam = reg * A.diagonal(dim1=1, dim2=2).sum(-1) / 3.0 + 1e-300
    X = torch.linalg.solve(A + lam[:, None, None] * torch.eye(3, dtype=A.dtype, device=A.device), b.unsqueeze(-1))
    X = X.squeeze(-1)
    X[v.sum(0) < min_views] = float("nan")
    return X.to(dt)


# --------------------------------------------------------------------------- reflection


def _visibility_votes(S: torch.Tensor, cams: ScaledOrthographic, visible: torch.Tensor) -> tuple[int, int]:
    """Count instances whose visible keypoints are nearer (``for``) or farther (``against``).

    ``S (K, 3)`` (NaN rows ignored), ``visible (N, K)`` bool for the given cameras.
    An instance votes when it has both a visible and a hidden keypoint with a finite
    shape row, and the two mean depths differ by more than ``1e-6`` of the shape's
    RMS radius (in pixels).
    """
    ok = torch.isfinite(S).all(-1)
    Sf = torch.nan_to_num(S)
    z = cams.depth(Sf)  # (N, K)
    vis = visible & ok
    hid = ~visible & ok
    nv, nh = vis.sum(-1), hid.sum(-1)
    zv = (z * vis).sum(-1) / nv.clamp(min=1)
    zh = (z * hid).sum(-1) / nh.clamp(min=1)
    radius = (Sf[ok] - Sf[ok].mean(0)).pow(2).sum(-1).mean().sqrt() if bool(ok.any()) else S.new_tensor(1.0)
    d = zh - zv
    can = (nv > 0) & (nh > 0) & (d.abs() > 1e-6 * radius * cams.s)
    return int((can & (d > 0)).sum()), int((can & (d < 0)).sum())


def _handedness(S: torch.Tensor, cams: ScaledOrthographic, keypoint_names, flip_pairs, left_convention):
    """Signed handedness ``det[left, up, front]`` of the current frame, or ``(None, why)``.

    ``left`` = mean over flip pairs of (left-named minus right-named) shape point,
    negated with ``left_convention="viewer"``; ``up`` = the image's up direction
    (``-R[1]``) lifted to the object frame and averaged over instances; ``front`` =
    mean of front-named keypoints minus mean of back-named ones. Each is normalised;
    the value is in ``[-1, 1]``; a correctly oriented object frame gives > 0 (for an
    object with its own left ``L``, up ``U`` and front ``F``, ``L = U x F``).
    """
    if keypoint_names is None or flip_pairs is None:
        return None, "no keypoint names / flip pairs given"
    names = list(keypoint_names)
    ok = torch.isfinite(S).all(-1)
    diffs = []
    for i, j in flip_pairs:
        i, j = int(i), int(j)
        si, sj = keypoint_side(names[i]), keypoint_side(names[j])
        if {si, sj} != {"left", "right"} or not (bool(ok[i]) and bool(ok[j])):
            continue
        li, ri = (i, j) if si == "left" else (j, i)
        diffs.append(S[li] - S[ri])
    if not diffs:
        return None, "no flip pair with left/right names and reconstructed points"
    left = torch.stack(diffs).mean(0)
    if left_convention == "viewer":
        left = -left
    ends = [keypoint_end(nm) for nm in names]
    fr = [k for k, e in enumerate(ends) if e == "front" and bool(ok[k])]
    bk = [k for k, e in enumerate(ends) if e == "back" and bool(ok[k])]
    if not fr or not bk:
        return None, "no front-named and back-named keypoints (front/nose/head vs back/tail/rear)"
    front = S[fr].mean(0) - S[bk].mean(0)
    up = (-cams.R[:, 1, :]).mean(0)
    if float(up.norm()) < 0.2:
        return None, f"image up directions disagree across instances (mean length {float(up.norm()):.2f} < 0.2)"
    vecs = [left, up, front]
    if any(float(x.norm()) == 0 for x in vecs):
        return None, "degenerate left/up/front vectors"
    L, U, F = (x / x.norm() for x in vecs)
    return float(torch.dot(L, torch.linalg.cross(U, F))), ""


def _flip_solution(S: torch.Tensor, cams: ScaledOrthographic) -> tuple[torch.Tensor, ScaledOrthographic]:
    """Necker mirror: ``S -> F S``, ``R -> F R F`` with ``F = diag(1, 1, -1)``.

    Projections are unchanged, depths are negated, ``R`` stays proper.
    """
    F = _flip_z(S.dtype, S.device)
    return S @ F, ScaledOrthographic(F @ cams.R @ F, cams.s, cams.t)


# --------------------------------------------------------------------------- main


@dataclass(frozen=True)
class SfMOptions:
    """Settings of :func:`rigid_sfm` (the algorithm's own; the class's keypoint metadata are arguments)."""

    max_outer: int = 200
    """Outer (fill / refill) iterations of the factorisation at most."""
    inner: int = 10
    """Power-factorisation steps per outer iteration."""
    tol: float = 1e-6
    """Relative change of the visible-entry RMS residual that stops the outer loop and the polish."""
    polish_iters: int = 30
    """Bundle-polish rounds after the factorisation (0: none)."""
    polish: PolishMethod = "alternate"
    """How the bundle polish minimises (:func:`bundle_polish`): ``alternate`` or ``joint``."""
    regularization: float = 1e-6
    """Relative Tikhonov weight of the shape and camera solves (keeps rank-deficient, e.g. planar
    or two-view, problems defined)."""
    planar: bool | None = None
    """``True`` forces the coplanar model, ``False`` forbids it, ``None`` fits both and keeps the
    planar one when its visible-entry RMS residual is at most ``(1 + planar_margin)`` times the
    rigid 3-D one (plus a float floor): the simpler model wins when it explains the data as well."""
    planar_margin: float = 0.02
    """See ``planar``."""
    vote_margin: float = 0.1
    """The visibility vote is too close, and the handedness rule decides (when applicable), when
    ``voters < min_voters`` or ``|for - against| <= max(vote_margin * voters, 3 sqrt(voters))``
    (the second bound: a margin that visibility unrelated to depth, a fair coin per voter, would
    reach by chance once in about 370 classes)."""
    min_voters: int = 5
    """See ``vote_margin``."""
    mirrors: bool | None = None
    """Whether instances ``N/2..N-1`` are the left-right mirrored copies of ``0..N/2-1``
    (``ClassCollection.with_mirrors()``); ``None`` detects it (:func:`mirror_width`), ``True``
    requires it, ``False`` treats every instance as independent ("Mirrored copies" in
    :func:`rigid_sfm`)."""
    mirror_tie_deg: float = 5.0
    """Median angle (degrees) between the copies' cameras and their originals' mirrored cameras
    above which the joint solution is re-seeded from the originals."""
    native: bool = True
    """On the CPU, run the factorisation's outer loop in the compiled kernel
    (:func:`~carvi_torch.viewpoints.factorization._native_steps`; float64, equal to the torch operators to rounding)
    where it builds; ``False``: torch operators only."""

    def check(self) -> None:
        """Raise ``ValueError`` for limits below 1 and an unknown polish method."""
        if self.max_outer < 1 or self.inner < 1:
            raise ValueError(f"max_outer and inner must be >= 1, got {self.max_outer} and {self.inner}")
        if self.polish not in POLISH_METHODS:
            raise ValueError(f"polish must be one of {POLISH_METHODS}, got {self.polish!r}")


@dataclass
class _Data:
    """The measurements :func:`rigid_sfm` factorises, and which instances and keypoints take part."""

    kp: torch.Tensor  # (N, K, 2) float64, non-finite entries zeroed
    vis: torch.Tensor  # (N, K) bool, visible and finite
    rigid: list  # the rigid keypoints asked for
    valid: torch.Tensor  # (N,) bool instances that take part
    reasons: list  # per instance, why it does not ("" when it does)
    cols: list  # the keypoints the factorisation uses
    excluded: set  # keypoints with no shape row from the factorisation or triangulation (never / few / lost)
    never: list  # keypoints visible in no instance
    seen: torch.Tensor  # (K,) valid instances that see each keypoint
    centroid: torch.Tensor  # (N, 2) mean visible keypoint of each instance
    problems: list


def _check_class(keypoints, visible, options, keypoint_names, flip_pairs, left_convention) -> None:
    _check_inputs(keypoints, visible)
    if left_convention not in ("object", "viewer"):
        raise ValueError(f"left_convention must be 'object' or 'viewer', got {left_convention!r}")
    options.check()
    k = keypoints.shape[1]
    if keypoint_names is not None and len(keypoint_names) != k:
        raise ValueError(f"keypoint_names must have K={k} entries, got {len(keypoint_names)}")
    for p in flip_pairs or ():
        if len(p) != 2 or not all(0 <= int(q) < k for q in p):
            raise ValueError(f"flip_pairs entries must be index pairs in [0, {k}), got {p}")


def _finite_visible(keypoints: torch.Tensor, visible: torch.Tensor, problems: list) -> torch.Tensor:
    """``visible`` without the entries whose coordinates are not finite (reported)."""
    vis = visible.to(device=keypoints.device, dtype=torch.bool)
    bad = vis & ~torch.isfinite(keypoints).all(-1)
    if bool(bad.any()):
        problems.append(f"{int(bad.sum())} visible keypoint entries have non-finite coordinates; "
                        "treated as not visible")
        vis = vis & ~bad
    return vis


def _main_component(vis, rigid, valid, reasons, keypoint_names, problems):
    """Restrict ``valid`` to the largest connected group of the visibility graph (reasons, problems
    updated); returns ``valid``, the rigid keypoints left in the group and those lost."""
    rigid_t = torch.tensor(rigid, device=vis.device, dtype=torch.long)
    outside, cols_out = outside_main_component(vis[:, rigid_t] & valid[:, None])
    if not bool(outside.any()):
        return valid, list(rigid), []
    lost = [rigid[j] for j in cols_out.nonzero().squeeze(1).tolist()]
    lost_names = [keypoint_names[j] for j in lost] if keypoint_names is not None else lost
    n_main = int((valid & ~outside).sum())
    for i in outside.nonzero().squeeze(1).tolist():
        reasons[i] = (f"its visible rigid keypoints share none with the {n_main} instances of the largest "
                      "connected group: SfM cannot place it in the class frame")
    problems.append(f"{int(outside.sum())} instance(s) see only keypoints {lost_names}, which no instance of "
                    f"the largest connected group ({n_main} instances) sees: those instances get no SfM camera "
                    "and those keypoints no shape row")
    return valid & ~outside, [r for r, o in zip(rigid, cols_out.tolist()) if not o], lost


def _select_data(keypoints, visible, rigid_keypoints, keypoint_names) -> _Data:
    """Step 1: the instances and keypoints that take part, with the reasons for those that do not."""
    n, k, _ = keypoints.shape
    problems: list[str] = []
    vis = _finite_visible(keypoints, visible, problems)
    kp = torch.nan_to_num(keypoints.double(), nan=0.0, posinf=0.0, neginf=0.0)
    rigid = list(range(k)) if rigid_keypoints is None else sorted({int(i) for i in rigid_keypoints})
    if any(not 0 <= i < k for i in rigid):
        raise ValueError(f"rigid_keypoints must be indices in [0, {k}), got {list(rigid_keypoints)}")
    if not rigid:
        raise ValueError("rigid_keypoints is empty")
    nvis_rigid = vis[:, torch.tensor(rigid, device=vis.device, dtype=torch.long)].sum(-1)
    valid = nvis_rigid >= 2
    reasons = ["" if bool(v) else f"only {int(c)} visible rigid keypoint(s); a camera needs 2"
               for v, c in zip(valid.tolist(), nvis_rigid.tolist())]
    # instances and keypoints linked to the largest group only through no shared keypoint
    # cannot be placed in its frame: SfM runs on the largest connected component
    valid, rigid_main, lost = _main_component(vis, rigid, valid, reasons, keypoint_names, problems)
    seen = (vis & valid[:, None]).sum(0)
    never = [i for i in range(k) if int(vis[:, i].sum()) == 0]
    if never:
        problems.append(f"keypoints {never} are never visible: excluded, shape rows NaN")
    cols = [i for i in rigid_main if int(seen[i]) >= 2]
    few = [i for i in rigid_main if 0 < int(seen[i]) < 2]
    if few:
        problems.append(f"rigid keypoints {few} are seen by fewer than 2 valid instances: excluded, shape rows NaN")
    centroid = (kp * vis[..., None]).sum(1) / vis.sum(1, keepdim=True).clamp(min=1)
    return _Data(kp, vis, rigid, valid, reasons, cols, set(never) | set(few) | set(lost), never, seen, centroid,
                 problems)


def _too_little(data: _Data) -> str | None:
    """Why SfM cannot run on ``data`` (``None``: it can)."""
    n_valid = int(data.valid.sum())
    if n_valid < 2:
        return f"only {n_valid} instance(s) with >= 2 visible rigid keypoints (need 2)"
    if len(data.cols) < 3:
        return f"only {len(data.cols)} rigid keypoint(s) seen by >= 2 valid instances (need 3)"
    return None


def _placeholder(data: _Data, why: str, dtype) -> SfMResult:
    """The result when SfM cannot run: every camera a placeholder, every instance invalid."""
    n, k = data.vis.shape
    dev = data.vis.device
    data.problems.append(f"SfM not run: {why}; all cameras are placeholders")
    reasons = [r if r else "SfM not run: " + why for r in data.reasons]
    R = torch.eye(3, dtype=dtype, device=dev).expand(n, 3, 3).clone()
    cams = ScaledOrthographic(R, torch.ones(n, dtype=dtype, device=dev), data.centroid.to(dtype))
    nan_n = torch.full((n,), float("nan"), dtype=dtype, device=dev)
    votes = {"for": 0, "against": 0, "voters": 0, "decided_by": "none", "flipped": False, "handedness": None}
    return SfMResult(torch.full((k, 3), float("nan"), dtype=dtype, device=dev), cams,
                     torch.zeros(n, dtype=torch.bool, device=dev), nan_n, nan_n.clone(), 0, 0, False, votes, False,
                     data.seen, data.never, data.rigid, reasons, data.problems, [])


def _coverage_problems(data: _Data) -> None:
    """Report instances whose keypoints leave their depth or rotation undetermined."""
    sub = data.vis[:, torch.tensor(data.cols, device=data.vis.device)].sum(-1)
    n_three = int((sub >= 3).sum())
    if n_three < 3:
        data.problems.append(f"only {n_three} instance(s) see 3 or more rigid keypoints: with fewer than 3 such "
                             "views the shape's depth is not determined (orthographic two-view ambiguity); cameras "
                             "unreliable")
    n_two = int((data.valid & (sub == 2)).sum())
    if n_two:
        data.problems.append(f"{n_two} instance(s) see only 2 rigid keypoints: their rotation is not determined by "
                             "the keypoints (only the silhouette refinement constrains it)")


def _warm_start(init_shape, k: int, cols: torch.Tensor, dev) -> torch.Tensor | None:
    """``init_shape (K, 3)`` as a start ``(3, Kc)`` of the factorisation, or ``None`` (too few finite rows)."""
    if init_shape.shape != (k, 3):
        raise ValueError(f"init_shape must be ({k}, 3), got {tuple(init_shape.shape)}")
    S_init = init_shape.to(device=dev, dtype=torch.float64)[cols]
    fin = torch.isfinite(S_init).all(-1)
    if int(fin.sum()) < 3:
        return None  # nothing to start from
    return torch.where(fin[:, None], S_init, S_init[fin].mean(0)).T.contiguous()


def _fit_problems(opts: SfMOptions, mirror_report: dict, converged: bool, history: list, problems: list) -> None:
    """Report a re-seeded or symmetry-breaking solution and iteration limits reached."""
    if mirror_report.get("reseeded"):
        joint = mirror_report['tie_deg_median_joint']
        problems.append(f"the joint solution broke the mirror symmetry (median {joint:.1f} "
                        "deg between copies' cameras and their mirrored originals): re-seeded from the originals")
    elif mirror_report.get("tie_deg_median") is not None and mirror_report["tie_deg_median"] > opts.mirror_tie_deg:
        problems.append(f"mirrored copies' cameras disagree with their mirrored originals (median "
                        f"{mirror_report['tie_deg_median']:.1f} deg) and re-seeding from the originals did not "
                        "lower the residual")
    if not converged:
        last = abs(history[-2] - history[-1]) / max(history[-2], 1e-300) if len(history) >= 2 else float("nan")
        problems.append(f"SfM stopped at its iteration limits (max_outer={opts.max_outer}, "
                        f"polish_iters={opts.polish_iters}) before the residual settled: last relative change "
                        f"{last:.1e} > tol={opts.tol:.0e} (RMS residual {history[-1]:.3g} px)")


def _fit_step(data: _Data, opts: SfMOptions, flip_pairs, init_shape, generator) -> _Fit:
    """Step 2: factorisation and bundle polish (rigid or planar) on the valid rows and ``cols``."""
    dev = data.vis.device
    cols = torch.tensor(data.cols, device=dev, dtype=torch.long)
    Wv = data.kp[data.valid][:, cols].transpose(1, 2).contiguous()  # (Nv, 2, Kc)
    vv = data.vis[data.valid][:, cols].double()
    layout = None
    if opts.mirrors is not False:
        width = mirror_width(data.kp, data.vis, flip_pairs)
        if width is None and opts.mirrors:
            raise ValueError("mirrors=True but instances N/2..N-1 are not the mirrored copies of 0..N/2-1 "
                             "(x' = C - 1 - x, same y, keypoints swapped along flip_pairs)")
        if width is not None:
            layout = mirror_layout(data.valid, width, flip_pairs, data.cols)
    planar, S_init = opts.planar, None
    if init_shape is not None:
        if planar is None:
            planar = False  # a warm start continues the rigid model: the planar one is not fitted
        S_init = _warm_start(init_shape, data.kp.shape[1], cols, dev)
    # no autograd anywhere in the fit: inference mode runs the same kernels with less dispatch per tensor
    # op; its results are cloned into ordinary tensors
    with cpu_single_thread(dev), torch.inference_mode():
        fit = _fit(Wv, vv, planar, opts.planar_margin, opts.polish_iters, mirrors=layout,
                   tie_deg=opts.mirror_tie_deg, S_init=S_init, polish_method=opts.polish, max_outer=opts.max_outer,
                   inner=opts.inner, native=opts.native,
                   tol=opts.tol, reg=opts.regularization, generator=generator)
    fit.M, fit.t, fit.S = fit.M.clone(), fit.t.clone(), fit.S.clone()
    _fit_problems(opts, fit.mirrors, fit.converged, fit.history, data.problems)
    return fit


def _assemble(data: _Data, fit: _Fit):
    """Step 3: cameras of every instance and the shape of every keypoint (float64), the valid
    instances' degenerate blocks made invalid and the other keypoints triangulated.

    Returns ``R (N, 3, 3)``, ``s (N,)``, ``t (N, 2)``, ``shape (K, 3)`` (NaN rows: no point).
    """
    n, k = data.vis.shape
    dev = data.vis.device
    M, tv = fit.M, fit.t
    # no NaN leaves SfM: a degenerate block (zero scale, non-finite) makes its instance invalid
    good = _usable_blocks(M, tv)
    if not bool(good.all()):
        idx_v = data.valid.nonzero().squeeze(1)
        for i in idx_v[~good].tolist():
            data.reasons[i] = ("SfM gave a degenerate camera (zero or non-finite scale): its visible rigid keypoints "
                               "coincide in the mean shape or carry no rotation")
        data.problems.append(f"{int((~good).sum())} instance(s) got a degenerate SfM camera and are marked invalid")
        sub = torch.zeros_like(data.valid)
        sub[idx_v[good]] = True
        data.valid = sub
        M, tv = M[good], tv[good]
    R = torch.eye(3, dtype=torch.float64, device=dev).expand(n, 3, 3).clone()
    s = torch.ones(n, dtype=torch.float64, device=dev)
    t = data.centroid.clone()
    sv = M[:, 0].norm(dim=-1)
    R[data.valid] = complete_rotation(M / sv[:, None, None])
    s[data.valid] = sv
    t[data.valid] = tv
    shape = torch.full((k, 3), float("nan"), dtype=torch.float64, device=dev)
    shape[torch.tensor(data.cols, device=dev, dtype=torch.long)] = fit.S.T
    _triangulate_others(data, ScaledOrthographic(R, s, t), shape)
    return R, s, t, shape


def _triangulate_others(data: _Data, cams64: ScaledOrthographic, shape: torch.Tensor) -> None:
    """Fill the shape rows of the keypoints the factorisation did not use, from the cameras (in place)."""
    k = shape.shape[0]
    others = [i for i in range(k) if i not in set(data.cols) | data.excluded]
    if not others:
        return
    o = torch.tensor(others, device=shape.device)
    X = triangulate(cams64[data.valid], data.kp[data.valid][:, o], data.vis[data.valid][:, o])
    shape[o] = X
    lost = [others[j] for j in range(len(others)) if not bool(torch.isfinite(X[j]).all())]
    if lost:
        data.problems.append(f"non-rigid keypoints {lost} are seen by fewer than 2 valid instances: shape rows NaN")


def _centre(shape, R, s, t):
    """Gauge, position: the shape's finite rows centred on 0, the translations absorbing it."""
    fin = torch.isfinite(shape).all(-1)
    c = shape[fin].mean(0)
    return shape - c, t + s[:, None] * (R[:, :2, :] @ c)


def _reflection_step(data, shape, cams64, is_planar, opts, keypoint_names, flip_pairs, left_convention):
    """Step 4: the reflection (Necker) decision of :func:`rigid_sfm`; returns ``shape, R, votes``."""
    v_for, v_against = _visibility_votes(shape, cams64[data.valid], data.vis[data.valid])
    voters = v_for + v_against
    votes = {"for": v_for, "against": v_against, "voters": voters, "decided_by": "none", "flipped": False,
             "handedness": None}
    close = voters < opts.min_voters or abs(v_for - v_against) <= max(opts.vote_margin * voters,
                                                                      3.0 * math.sqrt(voters))
    flip = v_against > v_for
    if is_planar:
        # the mirror of a plane is itself: the flip only reverses every camera's
        # (unobservable) tilt direction, so there is nothing to decide
        flip = False
        votes["decided_by"] = "not applicable (planar)"
    elif not close:
        votes["decided_by"] = "visibility"
    else:
        hand, why = _handedness(shape, cams64[data.valid], keypoint_names, flip_pairs, left_convention)
        votes["handedness"] = hand
        if hand is not None and abs(hand) >= 0.1:
            votes["decided_by"] = "handedness"
            flip = hand < 0
        else:
            why = why or f"left, up and front nearly coplanar (|det| = {abs(hand):.2f} < 0.1)"
            votes["decided_by"] = "visibility (weak)"
            data.problems.append(f"reflection ambiguous: visibility vote {v_for} for / {v_against} against is too "
                                 f"close and the handedness rule is not applicable ({why})")
    R = cams64.R
    if flip:
        shape, cams64 = _flip_solution(shape, cams64)
        R = cams64.R
        votes["for"], votes["against"] = v_against, v_for
        if votes["handedness"] is not None:
            votes["handedness"] = -votes["handedness"]
    votes["flipped"] = bool(flip)
    return shape, R, votes


def _scale_gauge(data: _Data, shape, R, s, t) -> tuple[torch.Tensor, ScaledOrthographic]:
    """Gauge, scale: the median camera scale of the valid instances is 1; placeholders for the others."""
    valid = data.valid
    med = s[valid].median()
    shape = shape * med
    s = s / med
    s = torch.where(valid, s, torch.ones_like(s))
    R = torch.where(valid[:, None, None], R, torch.eye(3, dtype=R.dtype, device=R.device))
    t = torch.where(valid[:, None], t, data.centroid)
    return shape, ScaledOrthographic(R, s, t)


def _report(data: _Data, fit: _Fit, shape, cams: ScaledOrthographic, votes: dict, dtype) -> SfMResult:
    """Step 5: residuals and the :class:`SfMResult` in the keypoints' dtype."""
    kp, vis, valid = data.kp, data.vis, data.valid

    def rms(cols_mask: torch.Tensor) -> torch.Tensor:
        P = cams.project(torch.nan_to_num(shape))
        m = vis & cols_mask[None, :]
        e = ((P - kp) ** 2).sum(-1) * m
        out = (e.sum(-1) / m.sum(-1).clamp(min=1)).sqrt()
        return torch.where(valid & (m.sum(-1) > 0), out, torch.full_like(out, float("nan")))

    cm = torch.zeros(shape.shape[0], dtype=torch.bool, device=shape.device)
    cm[torch.tensor(data.cols, device=shape.device, dtype=torch.long)] = True
    residual = rms(cm).to(dtype)
    residual_all = rms(torch.isfinite(shape).all(-1)).to(dtype)
    cams = ScaledOrthographic(cams.R.to(dtype), cams.s.to(dtype), cams.t.to(dtype))
    return SfMResult(shape.to(dtype), cams, valid, residual, residual_all, fit.iterations, fit.polish_rounds,
                     fit.converged, votes, fit.planar, data.seen, data.never, data.rigid, data.reasons,
                     data.problems, fit.history, fit.mirrors)


def rigid_sfm(
    keypoints: torch.Tensor,
    visible: torch.Tensor,
    options: SfMOptions | None = None,
    *,
    rigid_keypoints: Sequence[int] | None = None,
    keypoint_names: Sequence[str] | None = None,
    flip_pairs: Sequence[Sequence[int]] | None = None,
    left_convention: str = "object",
    generator: torch.Generator | None = None,
    init_shape: torch.Tensor | None = None,
    **overrides,
) -> SfMResult:
    """Mean shape and scaled orthographic cameras of a class from keypoints with missing data.

    Marques & Costeira's alternation (fill, factorise, project onto scaled rotations,
    re-solve the shape, refill), then a bundle polish; see the module docstring for
    the steps and the stopping rules.

    Args:
        keypoints: ``(N, K, 2)`` float, canvas pixels ``(x, y)``. Entries that are not
            visible are ignored (may be NaN). Visible entries with a non-finite
            coordinate are treated as not visible and reported in ``problems``.
        visible: ``(N, K)`` bool.
        options: :class:`SfMOptions` (iteration limits, tolerances, the planar and mirror
            rules, the reflection vote); ``**overrides`` replace single fields of it
            (``rigid_sfm(kp, vis, max_outer=30)``).
        rigid_keypoints: indices used by the factorisation (all when ``None``). The
            others are triangulated afterwards by least squares from the cameras
            (:func:`triangulate`), NaN when seen by fewer than 2 valid instances.
        keypoint_names: ``K`` names, for the reflection fallback.
        flip_pairs: ``(i, j)`` left/right index pairs, for the reflection fallback.
        left_convention: ``"object"`` when a keypoint named left lies on the object's
            own left (a person's left; Berkeley PASCAL keypoints: ``L_WingTip`` is the
            pilot's left), ``"viewer"`` when it lies on the left of a viewer facing
            the object's front (PASCAL3D+ CAD keypoints: ``left_wing`` is the pilot's right).
        generator: random source, only used to complete a rank-deficient initial
            shape (a fixed seed is used when ``None``, so results are deterministic).
        init_shape: ``(K, 3)`` a shape to start the rigid factorisation from instead of the
            rank-3 approximation of the filled measurements (e.g. the last round's shape of an
            alternation over sub-collections, :mod:`carvi_torch.viewpoints.mixture`). The missing
            entries are filled from the start's resected cameras, at most :data:`WARM_OUTER`
            outer steps are run and the bundle polish finishes. Any rotation, scale or
            translation of the solution serves; NaN rows start at the other rows' centroid.
            With ``planar=None`` the planar model is not fitted (``planar=False``): a warm
            start continues a rigid solution. Everything else is unchanged (the bundle polish
            runs to its own stopping rule: capped at 8 rounds it left the final groups' cameras
            less accurate, and the 15-render sofa test's median rose from 5.5 to 7.0 degrees).

    Returns:
        :class:`SfMResult`.

    Reflection (Necker) ambiguity. Orthographic SfM cannot tell ``S`` from its mirror
    ``diag(1,1,-1) S`` with cameras ``diag(1,1,-1) R diag(1,1,-1)`` (same projections,
    negated depths). Decided by, in order:

    1. *visibility vote*: every valid instance with both visible and hidden keypoints
       votes for the frame in which its visible keypoints are, on average, nearer
       the camera (smaller depth) than its hidden ones; the majority wins unless the
       vote is close (see ``vote_margin``, ``min_voters``);
    2. *handedness rule* (close votes): object left (mean left-minus-right flip-pair
       vector, by names; see ``left_convention``), image up averaged over the
       instances and lifted into the object frame, and object front (mean of
       front/nose/head-named minus back/tail/rear-named keypoints) must form a
       right-handed triple, ``left . (up x front) > 0``. Not applicable without names
       and flip pairs, without both front- and back-named keypoints, or when the
       instances' image up directions disagree (mean length < 0.2); the weak vote
       then decides and a problem is reported.

    Mirrored copies. A mirrored copy is a photograph of the object's mirror image, so
    for a bilaterally symmetric object its camera is its original's camera mirrored
    through the symmetry plane (``ScaledOrthographic.mirror``). The factorisation
    treats every row as independent, and with block-structured missing data (e.g.
    PASCAL3D+ cars: every keypoint in a left/right pair, CAD models annotated with
    12, 20 or 22 of the 22 names) the joint alternation can end in a minimum that
    breaks this tie (cars: median 122 degrees between copy and mirrored original,
    72 degrees of viewpoint error). When the median tie angle exceeds
    ``mirror_tie_deg``, the originals are solved alone, their copies' cameras are
    derived by mirroring, and all rows are polished together; the solution with the
    lower visible-entry residual is kept (``SfMResult.mirrors`` reports both).

    Planar keypoint sets (all rigid keypoints coplanar, e.g. PASCAL's bottle): the
    rank-3 factorisation is degenerate (the camera component along the plane normal
    is undetermined). The planar model factorises with rank 2 instead, leaving each
    ``2x2`` block free, because under scaled orthography *every* 2x2 linear map is a
    view of a plane; the result is therefore defined up to one affine map of the
    plane, fixed by making the blocks' average metric isotropic (exact for
    fronto-parallel views). Each block ``A`` is then completed to a camera
    ``[A | b]`` with ``b`` the unique (up to sign) column that makes its rows
    orthogonal and of equal norm: the camera images the plane exactly as ``A`` and
    is tilted out of it by ``acos(sigma_2 / sigma_1)``; the tilt's direction (the sign
    of ``b``) is not observable from a plane and is returned as ``+``. The in-plane
    part of every camera (rotation, scale, translation, foreshortening, which side
    of the plane it sees) is recovered; the shape has ``z = 0`` in the object frame.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> from carvi_torch.cameras import random_rotations
        >>> S = torch.randn(8, 3, generator=g); R = random_rotations(20, g)
        >>> kp = 50 * S @ R[:, :2].transpose(1, 2) + 64
        >>> res = rigid_sfm(kp, torch.ones(20, 8, dtype=torch.bool))
        >>> bool(res.residual.max() < 1e-3)
        True
    """
    opts = dataclasses.replace(options or SfMOptions(), **overrides)
    _check_class(keypoints, visible, opts, keypoint_names, flip_pairs, left_convention)
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    data = _select_data(keypoints, visible, rigid_keypoints, keypoint_names)
    why = _too_little(data)
    if why is not None:
        return _placeholder(data, why, keypoints.dtype)
    _coverage_problems(data)
    fit = _fit_step(data, opts, flip_pairs, init_shape, gen)
    R, s, t, shape = _assemble(data, fit)
    shape, t = _centre(shape, R, s, t)
    shape, R, votes = _reflection_step(data, shape, ScaledOrthographic(R, s, t), fit.planar, opts, keypoint_names,
                                       flip_pairs, left_convention)
    shape, cams = _scale_gauge(data, shape, R, s, t)
    return _report(data, fit, shape, cams, votes, keypoints.dtype)


def symmetry_plane(shape: torch.Tensor, flip_pairs: Sequence[Sequence[int]]) -> torch.Tensor:
    """Reflection ``P = I - 2 n n^T`` through the shape's left-right symmetry plane.

    ``n`` is the dominant direction of the left-minus-right pair differences
    (top eigenvector of ``sum d d^T``, so the order within each pair does not
    matter); pairs with a non-finite row are skipped. The pipeline mirrors cameras
    with ``ScaledOrthographic.mirror(width, reflection=P)``.

    Args:
        shape: ``(K, 3)`` float, may hold NaN rows.
        flip_pairs: ``(i, j)`` index pairs.

    Returns:
        ``(3, 3)`` symmetric orthogonal matrix with determinant -1, in ``shape``'s dtype.

    Example:
        >>> S = torch.tensor([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0]])
        >>> symmetry_plane(S, [(0, 1)])
        tensor([[-1.,  0.,  0.],
                [ 0.,  1.,  0.],
                [ 0.,  0.,  1.]])
    """
    if not isinstance(shape, torch.Tensor) or shape.dim() != 2 or shape.shape[1] != 3:
        raise ValueError(f"shape must be a (K, 3) tensor, got {getattr(shape, 'shape', type(shape))}")
    k = shape.shape[0]
    diffs = []
    for p in flip_pairs:
        if len(p) != 2 or not all(0 <= int(q) < k for q in p):
            raise ValueError(f"flip_pairs entries must be index pairs in [0, {k}), got {p}")
        d = shape[int(p[0])] - shape[int(p[1])]
        if bool(torch.isfinite(d).all()) and float(d.norm()) > 0:
            diffs.append(d)
    if not diffs:
        raise ValueError("flip_pairs: no pair with two distinct finite shape points to define the symmetry plane")
    D = torch.stack(diffs).double()
    _, vecs = torch.linalg.eigh(D.T @ D)
    nrm = vecs[:, -1]
    P = torch.eye(3, dtype=torch.float64, device=shape.device) - 2.0 * torch.outer(nrm, nrm)
    return P.to(shape.dtype)
