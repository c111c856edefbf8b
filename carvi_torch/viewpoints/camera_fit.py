"""Silhouette-based camera refinement, batched, and cameras for unseen images.

With the class's mean shape ``S (K, 3)`` fixed, every instance's scaled
orthographic camera is refined by minimising (paper, eq. "refinement")

    E_n = sum_{k visible} || p_nk - w_nk ||^2  +  lambda * sum_{k} rho_n(D_n(p_nk)),
    p_nk = s_n R_n[:2] S_k + t_n,

where ``w_nk`` are the instance's keypoints and ``D_n`` is the exact Euclidean
distance (pixels) to its mask, 0 inside (``carvi_torch.sdf.distance_to_mask``,
computed once by the caller). The paper penalises ``rho(D) = D^2``; here, by
default, ``rho_n`` is the robust Geman-McClure penalty
``rho_n(D) = delta_n^2 D^2 / (delta_n^2 + D^2)`` (:func:`silhouette_penalty`), equal
to ``D^2`` near the mask and bounded by ``delta_n^2`` far from it, with ``delta_n``
a fraction (:data:`ROBUST_FRACTION`, 0.2) of the larger side of the instance's mask
bounding box. Why: the mean shape is not the instance's shape, and with squared
distances one mean-shape point far outside the mask (a keypoint the instance does
not have, or one badly placed by SfM) outweighs every other term; on the PASCAL3D+
train renders (CAD models of very different lengths and keypoint layouts) the
squared penalty shrank and rotated every camera to pull such points in (median
error 14 -> 71 degrees), the robust one does not (14 -> 11);
``silhouette_robust=None`` gives the squared penalty back. ``D_n`` is sampled with ``grid_sample`` (bilinear,
``align_corners=True`` with ``x_norm = 2 x / (W - 1) - 1``, so pixel centres are exact
samples; ``padding_mode="border"``); a point outside the canvas gets the border value
plus its Euclidean distance to the canvas rectangle, so the penalty keeps growing
outside. All instances (and, for unseen images, all starts) are optimised at once.

Conventions (``carvi_torch.cameras``): image x right, y down, pixel centres at
integer coordinates, points ``(x, y)``; ``uv = s * X @ R[:2].T + t``.

Parameterisation and optimiser. Each camera is updated by a local increment
``(omega, sigma, tau)`` (6 numbers): ``R <- exp([omega]_x) R`` (rotation about the
camera axes, axis-angle), ``s <- s exp(sigma)``, ``t <- t + tau``; after each step the
first two rows are re-projected onto the nearest scaled rotation (removing floating
point drift), so every iterate is an exact scaled orthographic camera. The gradient
``dE/dp`` of the energy with respect to the projected points comes from autograd
(through ``grid_sample``), and is chained with the analytic Jacobian ``dp/d(omega,
sigma, tau)``. Steps are Levenberg-Marquardt steps ``-(H + mu (diag H + eps))^-1 g``
with ``H`` the Gauss-Newton matrix of both terms (the silhouette term through
``grad D``), one ``6x6`` solve per camera. Chosen over plain gradient descent on the
affine block ``M`` because its steps are scale-free (rotation in radians, scale in
log units, translation in pixels) and it converges in tens of iterations.

Monotonicity: a trial step is accepted for an instance only when it does not raise
that instance's energy; otherwise the instance keeps its camera and its damping
``mu`` grows (x4, a shorter step: per-instance backtracking), on acceptance ``mu``
shrinks (/3). Stopping rule, per instance: an accepted step lowered the energy by
at most ``tol`` times its value, or ``mu`` exceeded ``1e8`` (no descent step left),
or ``max_iters`` iterations.

Working set: a finished camera is no longer stepped. Once at most :data:`COMPACT_FRACTION` of
the rows the optimiser holds still has an active camera, the finished rows are written back
and dropped (their data with them), so the batch shrinks geometrically while a few slow
cameras run on. With no silhouette term every start is its own row. Each camera's arithmetic
is unchanged, so the results are those of stepping the whole batch to the end.

Compiled fit. Without a silhouette term, on the CPU, ``native=True`` (the mixture's EM, the pipeline's
``sfm_native``) runs the same steps per camera in a C++ kernel (``carvi_torch/kernels/camera_steps.h``),
equal to this code to rounding (:func:`_native_optimize`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import NamedTuple

import torch
import torch.nn.functional as F

from .. import native_library
from ..cameras import ScaledOrthographic, axis_angle_to_rotation, complete_rotation, scaled_stiefel
from ..runtime import cpu_single_thread
from ..sdf import distance_to_mask
from .choice import HULL_GAIN, hull_agreement

#: Default robust scale of the silhouette penalty, as a fraction of the mask's larger side.
ROBUST_FRACTION = 0.2
#: A planar twin's refined camera replaces the instance's own only when its energy is lower by
#: at least this fraction: nearly equal energies mean the data cannot tell the two apart, and
#: the branch SfM chose (jointly with every other instance) is kept.
TWIN_MARGIN = 0.02
#: Default of :func:`refine_cameras`' ``twin_hull``: within that margin (the twin's energy lower, but by less
#: than :data:`TWIN_MARGIN`) the twin still wins when the convex hull of the projected mean shape agrees clearly
#: better with the mask (:func:`twin_wins`): the energy's silhouette term is one-sided (it only pulls points into
#: the mask) and, for a flat object whose mean shape is deeper than it is, is dominated by the points that fall
#: outside the mask under either camera.
TWIN_HULL_TIEBREAK = True
#: Default of :func:`supported_shape`: a mean-shape keypoint shown by fewer than this fraction of
#: the instances being refined is left out of their refinement.
MIN_SUPPORT = 0.1
#: Visible keypoints whose bounding box is at most this many pixels wide and high "collapse to one
#: point": they fix no scale (the keypoint term is smallest at scale 0), so no camera is fitted to them.
COLLAPSE_PIXELS = 1.0
#: Why an instance whose visible keypoints collapse gets no camera (the summary's reason).
COLLAPSED_REASON = "visible keypoints collapse to one point (they fix no scale)"

__all__ = [
    "RefineResult",
    "silhouette_penalty",
    "robust_scales",
    "ROBUST_FRACTION",
    "TWIN_MARGIN",
    "TWIN_HULL_TIEBREAK",
    "twin_wins",
    "MIN_SUPPORT",
    "COLLAPSE_PIXELS",
    "COLLAPSED_REASON",
    "collapsed_keypoints",
    "supported_shape",
    "sample_distance",
    "refinement_energy",
    "refine_cameras",
    "planar_twin",
    "keypoint_thickness",
    "refine_keypoints_only",
    "refine_starts_keypoints_only",
    "estimate_camera",
    "mask_start_cameras",
    "sphere_rotations",
]


# --------------------------------------------------------------------------- primitives


class Fitted(NamedTuple):
    """What :func:`_optimize` gives: ``(N, B)`` cameras and energies of ``N`` rows from ``B`` starts each."""

    R: torch.Tensor
    s: torch.Tensor
    t: torch.Tensor
    E_before: torch.Tensor
    E: torch.Tensor
    E_kp: torch.Tensor
    E_sil: torch.Tensor
    iterations: int
    converged: torch.Tensor

    def first_start(self) -> "Fitted":
        """The same for start 0 alone: ``(N,)`` tensors."""
        return self.each(lambda x: x[:, 0])

    def at_start(self, start: torch.Tensor) -> "Fitted":
        """The same for start ``start[n]`` of row ``n`` alone (``start``: ``(N,)`` int64): ``(N,)`` tensors."""
        rows = torch.arange(start.shape[0], device=start.device)
        return self.each(lambda x: x[rows, start])

    def best_start(self) -> tuple["Fitted", torch.Tensor]:
        """Each row's start of the lowest energy ``E``: :meth:`at_start` of them, and their ``(N,)`` int64 index."""
        best = self.E.argmin(1)
        return self.at_start(best), best

    def each(self, op) -> "Fitted":
        """The same with ``op`` applied to every tensor (every field but ``iterations``)."""
        return self._replace(**{k: op(getattr(self, k)) for k in self._fields if k != "iterations"})

    @property
    def cameras(self) -> ScaledOrthographic:
        """``R, s, t`` as cameras, of a one-start result (:meth:`first_start`, :meth:`at_start`)."""
        return ScaledOrthographic(self.R, self.s, self.t)


@dataclass
class RefineResult:
    """Output of :func:`refine_cameras` / :func:`refine_keypoints_only`.

    Attributes:
        cameras: N refined cameras.
        energy_before: ``(N,)`` energy of the given cameras.
        energy_after: ``(N,)`` energy of the returned cameras (``<= energy_before``).
        iterations: iterations run (the largest over instances).
        converged: ``(N,)`` bool, the stopping rule fired before ``max_iters``.
        keypoint_energy: ``(N,)`` keypoint term of ``energy_after``.
        silhouette_energy: ``(N,)`` unweighted silhouette term ``sum_k rho(D(p_k))`` after.
        start: ``(N,)`` int64 index of the start that won (0 when there was one start).
    """

    cameras: ScaledOrthographic
    energy_before: torch.Tensor
    energy_after: torch.Tensor
    iterations: int
    converged: torch.Tensor
    keypoint_energy: torch.Tensor
    silhouette_energy: torch.Tensor
    start: torch.Tensor


# --------------------------------------------------------------------------- sampling


def sample_distance(dist_maps: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of distance maps, growing linearly outside the canvas.

    Args:
        dist_maps: ``(N, H, W)`` float, finite, pixel ``[i, j]`` at ``(x=j, y=i)``;
            ``H, W >= 2``.
        points: ``(N, P, 2)`` ``(x, y)`` pixels, one set per map.

    Returns:
        ``(N, P)``: ``grid_sample`` (bilinear, ``align_corners=True``, border padding)
        at the point clamped to the canvas, plus the point's Euclidean distance to
        the canvas rectangle ``[0, W-1] x [0, H-1]``. Differentiable in ``points``.

    Example:
        >>> D = torch.arange(4.0).expand(1, 2, 4)  # D = x
        >>> sample_distance(D, torch.tensor([[[1.5, 0.0], [5.0, 1.0]]]))
        tensor([[1.5000, 5.0000]])
    """
    n, h, w = dist_maps.shape
    x, y = points[..., 0], points[..., 1]
    xc, yc = x.clamp(0, w - 1), y.clamp(0, h - 1)  # what border padding samples
    # NaN survives the clamp and must never reach grid_sample (its CPU kernel reads out of bounds);
    # such a point's sample stays NaN through the outside term below
    grid = torch.stack([2.0 * xc / (w - 1) - 1.0, 2.0 * yc / (h - 1) - 1.0], dim=-1).nan_to_num(nan=0.0)[:, None]
    d = F.grid_sample(dist_maps[:, None].to(points.dtype), grid, mode="bilinear", padding_mode="border",
                      align_corners=True)[:, 0, 0]  # grid (N, 1, P, 2), finite, in [-1, 1]
    ox = x - xc
    oy = y - yc
    o2 = ox * ox + oy * oy
    out = torch.where(o2 == 0, torch.zeros_like(o2), o2.clamp(min=1e-30).sqrt())  # NaN stays NaN
    return d + out


def collapsed_keypoints(keypoints: torch.Tensor, visible: torch.Tensor,
                        shape: torch.Tensor | None = None) -> torch.Tensor:
    """Instances with at least 2 usable visible keypoints that all lie within :data:`COLLAPSE_PIXELS`
    (bounding box width and height) of each other: degenerate, no camera can be fitted to them.

    Args:
        keypoints: ``(N, K, 2)``; visible: ``(N, K)`` bool; shape: ``(K, 3)`` or None (then every
            keypoint counts; else only those with a finite shape row, as the fit uses them).

    Returns:
        ``(N,)`` bool.

    Example:
        >>> kp = torch.tensor([[[5.0, 5.0], [5.0, 5.0], [9.0, 1.0]], [[5.0, 5.0], [8.0, 5.0], [0.0, 0.0]]])
        >>> collapsed_keypoints(kp, torch.tensor([[True, True, False], [True, True, False]])).tolist()
        [True, False]
    """
    use = visible & torch.isfinite(keypoints).all(-1)
    if shape is not None:
        use = use & torch.isfinite(shape).all(-1)
    big = torch.finfo(keypoints.dtype).max
    kp = torch.nan_to_num(keypoints)
    extent = (torch.where(use[..., None], kp, -big).amax(1) - torch.where(use[..., None], kp, big).amin(1))
    return (use.sum(-1) >= 2) & (extent <= COLLAPSE_PIXELS).all(-1)


# --------------------------------------------------------------------------- checks


def _check(shape, keypoints, visible, dist_maps, n_cams=None):
    if not isinstance(shape, torch.Tensor) or shape.dim() != 2 or shape.shape[1] != 3:
        raise ValueError(f"shape must be a (K, 3) tensor, got {getattr(shape, 'shape', type(shape))}")
    k = shape.shape[0]
    if not isinstance(keypoints, torch.Tensor) or keypoints.dim() != 3 or keypoints.shape[1:] != (k, 2):
        raise ValueError(f"keypoints must be (N, {k}, 2) to match shape (K={k}), "
                         f"got {getattr(keypoints, 'shape', type(keypoints))}")
    n = keypoints.shape[0]
    if not isinstance(visible, torch.Tensor) or visible.shape != (n, k):
        raise ValueError(f"visible must be ({n}, {k}), got {getattr(visible, 'shape', type(visible))}")
    if dist_maps is not None:
        if not isinstance(dist_maps, torch.Tensor) or dist_maps.dim() != 3 or dist_maps.shape[0] != n:
            got = getattr(dist_maps, "shape", type(dist_maps))
            raise ValueError(f"dist_maps / masks must be ({n}, H, W), got {got}")
        if dist_maps.shape[1] < 2 or dist_maps.shape[2] < 2:
            raise ValueError(f"dist_maps must be at least 2x2 pixels, got {tuple(dist_maps.shape[1:])}")
    if n_cams is not None and n_cams != n:
        raise ValueError(f"cameras has {n_cams} entries but keypoints has N={n}")


def _finite_maps(maps: torch.Tensor) -> torch.Tensor:
    """``maps`` with non-finite values (empty masks) set to 0; copies only when needed."""
    bad = ~torch.isfinite(maps).flatten(1).all(1)
    if not bool(bad.any()):
        return maps
    maps = maps.clone()
    maps[bad] = torch.nan_to_num(maps[bad], nan=0.0, posinf=0.0, neginf=0.0)
    return maps


def _mask_valid(dist_maps: torch.Tensor, mask_valid) -> torch.Tensor:
    if mask_valid is None:
        return torch.isfinite(dist_maps).flatten(1).all(1)
    mv = torch.as_tensor(mask_valid, device=dist_maps.device).bool()
    if mv.shape != dist_maps.shape[:1]:
        raise ValueError(f"mask_valid must be ({dist_maps.shape[0]},), got {tuple(mv.shape)}")
    return mv


# --------------------------------------------------------------------------- energy


def refinement_energy(
    M: torch.Tensor,
    t: torch.Tensor,
    shape: torch.Tensor,
    keypoints: torch.Tensor,
    visible: torch.Tensor,
    dist_maps: torch.Tensor,
    silhouette_weight: float = 1.0,
    mask_valid: torch.Tensor | None = None,
    silhouette_robust: float | None = ROBUST_FRACTION,
) -> torch.Tensor:
    """The refinement energy of affine camera blocks, differentiable in ``M`` and ``t``.

    ``E_n = sum_{k visible} ||M_n S_k + t_n - w_nk||^2 + lambda sum_k rho_n(D_n(M_n S_k + t_n))``
    (NaN rows of ``shape`` are left out of both sums; ``lambda = 0`` where
    ``mask_valid`` is False; ``rho_n`` :func:`silhouette_penalty` with
    ``delta_n = silhouette_robust *`` the mask's larger side, ``D^2`` when None).

    Args:
        M: ``(N, 2, 3)`` (``s * R[:2]`` for a scaled orthographic camera).
        t: ``(N, 2)``.
        shape: ``(K, 3)``.
        keypoints: ``(N, K, 2)`` pixels; visible: ``(N, K)`` bool.
        dist_maps: ``(N, H, W)`` distance to the mask (0 inside).
        silhouette_weight: ``lambda``.
        mask_valid: ``(N,)`` bool; default: maps that are finite everywhere.
        silhouette_robust: robust scale as a fraction of the mask's larger side, or
            None for the squared distance.

    Returns:
        ``(N,)`` energies in ``M``'s dtype.
    """
    _check(shape, keypoints, visible, dist_maps)
    kmask = torch.isfinite(shape).all(-1)
    S = torch.nan_to_num(shape).to(M.dtype)
    lam = silhouette_weight * _mask_valid(dist_maps, mask_valid).to(M.dtype)
    maps = _finite_maps(dist_maps).to(M.dtype)
    P = S @ M.transpose(-1, -2) + t[:, None, :]  # (N, K, 2)
    wv = (visible & kmask & torch.isfinite(keypoints).all(-1)).to(M.dtype)
    r = (P - torch.nan_to_num(keypoints).to(M.dtype)) * wv[..., None]
    D = sample_distance(maps, P) * kmask.to(M.dtype)
    _check_robust(silhouette_robust)
    rscale = None if silhouette_robust is None else robust_scales(dist_maps, silhouette_robust).to(M.dtype)[:, None]
    return (r * r).sum((-1, -2)) + lam * silhouette_penalty(D, rscale).sum(-1)


def _terms(R, s, t, S, kmask, kp, wv, maps, lam, rscale=None):
    """Energy, gradient and Gauss-Newton matrix in the local camera coordinates.

    Args (``N`` maps, ``B`` cameras per map):
        R ``(N, B, 3, 3)``, s ``(N, B)``, t ``(N, B, 2)``, S ``(K, 3)`` (NaN-free),
        kmask ``(K,)`` float, kp ``(N, K, 2)``, wv ``(N, K)`` float keypoint weights,
        maps ``(N, H, W)`` or None, lam ``(N,)``, rscale ``(N,)`` robust scale of the
        silhouette penalty (:func:`silhouette_penalty`) or None (squared distance).

    Returns:
        ``E (N, B)``, ``E_kp (N, B)``, ``E_sil (N, B)`` (unweighted), ``g (N, B, 6)``,
        ``H (N, B, 6, 6)``.
    """
    n, b = s.shape
    k = S.shape[0]
    Y = S @ R.transpose(-1, -2)  # (N, B, K, 3), Y_k = R S_k
    P = s[..., None, None] * Y[..., :2] + t[..., None, :]  # (N, B, K, 2)
    r = P - kp[:, None]
    w = wv[:, None, :, None]
    E_kp = (w * r * r).sum((-1, -2))
    gP = 2.0 * w * r
    if maps is not None and bool((lam > 0).any()):
        with torch.enable_grad():
            Pd = P.detach().requires_grad_(True)
            D = sample_distance(maps, Pd.reshape(n, b * k, 2)).reshape(n, b, k) * kmask
            (gradD,) = torch.autograd.grad(D.sum(), Pd)  # dD/dp per point (points are independent)
        D, gradD = D.detach(), gradD.detach()
        rho, drho, wgn = _penalty_terms(D, None if rscale is None else rscale[:, None, None])
        E_sil = rho.sum(-1)
        g_sil = drho[..., None] * gradD
        gradD = wgn.sqrt()[..., None] * gradD  # Gauss-Newton (IRLS) weight folded in
        gP = gP + lam[:, None, None, None] * g_sil
    else:
        E_sil = torch.zeros_like(E_kp)
        gradD = None
    # Jacobian dp/d(omega, sigma, tau): (N, B, K, 2, 6)
    Y0, Y1, Y2 = Y.unbind(-1)
    z = torch.zeros_like(Y0)
    o = torch.ones_like(Y0)
    sc = s[..., None]
    nsc = -sc
    Q0, Q1 = (P - t[..., None, :]).unbind(-1)
    row_x = torch.stack([z, sc * Y2, nsc * Y1, Q0, o, z], dim=-1)
    row_y = torch.stack([nsc * Y2, z, sc * Y0, Q1, z, o], dim=-1)
    J = torch.stack([row_x, row_y], dim=-2)
    g = torch.einsum("nbkr,nbkrj->nbj", gP, J)
    H = 2.0 * torch.einsum("nk,nbkri,nbkrj->nbij", wv, J, J)
    if gradD is not None:
        JD = torch.einsum("nbkr,nbkrj->nbkj", gradD, J)  # (N, B, K, 6)
        H = H + 2.0 * lam[:, None, None, None] * torch.einsum("nbki,nbkj->nbij", JD, JD)
    E = E_kp + lam[:, None] * E_sil
    return E, E_kp, E_sil, g, H


def silhouette_penalty(D: torch.Tensor, delta: torch.Tensor | float | None = None) -> torch.Tensor:
    """Penalty of a projected shape point at distance ``D`` (pixels) outside the mask.

    ``delta = None``: ``D^2`` (the paper's). Otherwise Geman-McClure,
    ``rho(D) = delta^2 D^2 / (delta^2 + D^2)``: ``D^2`` near the mask (``D << delta``),
    bounded by ``delta^2`` far from it, so a shape point that the instance does not
    have (the mean shape is not the instance's shape, or one keypoint of the mean
    shape is badly placed) cannot drag the camera; its pull is largest at
    ``D = delta / sqrt(3)``.

    Args:
        D: ``(...)`` distances >= 0; delta: broadcastable to ``D`` (> 0) or None.

    Returns:
        ``(...)``, same shape.

    Example:
        >>> silhouette_penalty(torch.tensor([0.0, 1.0, 100.0]), 10.0)
        tensor([ 0.0000,  0.9901, 99.0099])
    """
    return _penalty_terms(D, delta)[0]


def _penalty_terms(D, delta):
    """``rho(D)``, ``rho'(D)`` and the IRLS Gauss-Newton weight ``rho'(D) / (2 D)``."""
    if delta is None:
        return D * D, 2.0 * D, torch.ones_like(D)
    d2 = torch.as_tensor(delta, dtype=D.dtype, device=D.device) ** 2
    q = d2 + D * D
    w = (d2 / q) ** 2
    return d2 * D * D / q, 2.0 * D * w, w


def _check_robust(silhouette_robust) -> None:
    if silhouette_robust is not None and not silhouette_robust > 0:
        raise ValueError(f"silhouette_robust must be > 0 or None (squared distance), got {silhouette_robust}")


def robust_scales(dist_maps: torch.Tensor, fraction: float) -> torch.Tensor:
    """Per-instance robust scale ``delta = fraction * `` (larger side of the mask's bounding box).

    Args:
        dist_maps: ``(N, H, W)`` distance to the mask (0 inside; non-finite for empty masks).
        fraction: > 0.

    Returns:
        ``(N,)`` pixels, in ``dist_maps``' dtype (1 for empty masks; their silhouette
        term is off anyway).
    """
    inside = dist_maps == 0
    h, w = dist_maps.shape[1:]
    ys = torch.arange(h, device=dist_maps.device, dtype=dist_maps.dtype)
    xs = torch.arange(w, device=dist_maps.device, dtype=dist_maps.dtype)
    big = torch.tensor(float("inf"), dtype=dist_maps.dtype, device=dist_maps.device)
    colany, rowany = inside.any(1), inside.any(2)
    bw = torch.where(colany, xs, -big).amax(-1) - torch.where(colany, xs, big).amin(-1) + 1
    bh = torch.where(rowany, ys, -big).amax(-1) - torch.where(rowany, ys, big).amin(-1) + 1
    size = torch.maximum(bw, bh)
    return torch.where(torch.isfinite(size) & (size > 0), fraction * size, torch.ones_like(size))


def _retract(R, s, t, delta):
    """Apply local increments ``delta (N, B, 6)`` and re-project onto scaled rotations."""
    Rn = axis_angle_to_rotation(delta[..., :3]) @ R
    rows = scaled_stiefel(Rn[..., :2, :])
    rows = rows / rows[..., :1, :].norm(dim=-1, keepdim=True)
    return complete_rotation(rows), s * torch.exp(delta[..., 3]), t + delta[..., 4:]


def _optimize(R, s, t, shape, keypoints, visible, maps, lam, max_iters, tol, rscale=None, native=False):
    """Levenberg-Marquardt over ``(N, B)`` cameras; see the module docstring.

    Runs single-threaded on the CPU (:func:`cpu_single_thread`), and without a silhouette term
    (``maps`` None or ``lam`` 0 everywhere: nothing needs autograd) under ``torch.inference_mode``
    (the same kernels, less dispatch per tensor op); the results are then cloned into ordinary tensors.
    ``native``: without a silhouette term, on the CPU, the compiled fit (:func:`_native_optimize`) where
    it applies.

    Returns :class:`Fitted`.
    """
    plain = maps is None or not bool((lam > 0).any())
    if native and plain:
        out = _native_optimize(R, s, t, shape, keypoints, visible, max_iters, tol)
        if out is not None:
            return out
    with cpu_single_thread(keypoints.device), torch.inference_mode(plain):
        out = _optimize_impl(R, s, t, shape, keypoints, visible, maps, lam, max_iters, tol, rscale)
    return out.each(torch.Tensor.clone) if plain else out


def _native_optimize(R, s, t, shape, keypoints, visible, max_iters, tol) -> Fitted | None:
    """:func:`_optimize_impl` without a silhouette term in the compiled kernel (``carvi_torch/kernels/camera_steps.h``,
    :mod:`carvi_torch.native_library`): every camera on its own, the same steps, equal to rounding (the torch
    code's sums run in another order); its :class:`Fitted`, or ``None`` where it does not apply (not on the CPU,
    not float32/64, no kernel) or declines (a retraction of rank < 2): the torch code then runs."""
    dt = keypoints.dtype
    ops = native_library.operators_on(keypoints.device) if dt in (torch.float32, torch.float64) else None
    if ops is None:
        return None
    n, b = s.shape
    kmask = torch.isfinite(shape).all(-1)
    S = torch.nan_to_num(shape).to(dt).contiguous()
    wv = (visible & kmask & torch.isfinite(keypoints).all(-1)).to(dt).repeat_interleave(b, 0).contiguous()
    kp = torch.nan_to_num(keypoints).repeat_interleave(b, 0).contiguous()
    Rf, sf, tf, E0, E, conv, it, ok = ops.fit_cameras(R.to(dt).reshape(n * b, 3, 3).contiguous(),
                                                     s.to(dt).reshape(n * b).contiguous(),
                                                     t.to(dt).reshape(n * b, 2).contiguous(), S, kp, wv, max_iters, tol)
    if not ok:
        return None
    E = E.reshape(n, b)
    return Fitted(R=Rf.reshape(n, b, 3, 3), s=sf.reshape(n, b), t=tf.reshape(n, b, 2), E_before=E0.reshape(n, b), E=E,
                  E_kp=E.clone(), E_sil=torch.zeros_like(E), iterations=it, converged=conv.reshape(n, b))


#: The optimiser works on a shrinking set of rows: once at most this fraction of the rows it
#: holds still has an active camera, the others are written back and dropped (module docstring).
COMPACT_FRACTION = 0.5


@dataclass(frozen=True)
class _LMState:
    """The per-camera state of :func:`_optimize_impl`'s Levenberg-Marquardt iterations, ``n`` rows of ``B``
    cameras each, every field row-aligned.

    Attributes:
        R: ``(n, B, 3, 3)`` the current rotations.
        s: ``(n, B)`` the current scales.
        t: ``(n, B, 2)`` the current translations.
        E: ``(n, B)`` the energy of the current cameras.
        E_kp: ``(n, B)`` its keypoint term.
        E_sil: ``(n, B)`` its unweighted silhouette term.
        g: ``(n, B, 6)`` the energy's gradient in the local coordinates ``(omega, sigma, tau)``.
        H: ``(n, B, 6, 6)`` its Gauss-Newton matrix in those coordinates.
        mu: ``(n, B)`` the damping of the next step.
        active: ``(n, B)`` bool, the camera still takes steps.
        converged: ``(n, B)`` bool, the stopping rule fired.
    """

    R: torch.Tensor
    s: torch.Tensor
    t: torch.Tensor
    E: torch.Tensor
    E_kp: torch.Tensor
    E_sil: torch.Tensor
    g: torch.Tensor
    H: torch.Tensor
    mu: torch.Tensor
    active: torch.Tensor
    converged: torch.Tensor

    def rows(self, keep: torch.Tensor) -> "_LMState":
        """The state of rows ``keep`` (``(m,)`` int64) alone."""
        return _LMState(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})

    def written_into(self, full: "_LMState", rows: torch.Tensor | None) -> "_LMState":
        """``full`` with this working set's tensors copied into its rows ``rows`` (``(n,)`` int64; None: this state is
        the full one, returned as it is)."""
        if rows is None:
            return self
        return _LMState(**{f.name: getattr(full, f.name).index_copy(0, rows, getattr(self, f.name))
                           for f in fields(self)})


@dataclass(frozen=True)
class _LMData:
    """What the energy of :func:`_optimize_impl`'s working set reads, row-aligned with its :class:`_LMState`.

    Attributes:
        keypoints: ``(n, K, 2)`` NaN-free keypoints.
        weights: ``(n, K)`` float keypoint weights (visible, finite keypoint and shape row).
        maps: ``(n, H, W)`` finite distance maps, or None (no silhouette term).
        lam: ``(n,)`` the silhouette weight ``lambda`` per row.
        rscale: ``(n,)`` robust scales of the silhouette penalty, or None (squared distances).
    """

    keypoints: torch.Tensor
    weights: torch.Tensor
    maps: torch.Tensor | None
    lam: torch.Tensor
    rscale: torch.Tensor | None

    def rows(self, keep: torch.Tensor) -> "_LMData":
        """The data of rows ``keep`` (``(m,)`` int64) alone."""
        return _LMData(**{f.name: None if getattr(self, f.name) is None else getattr(self, f.name)[keep]
                          for f in fields(self)})


def _optimize_impl(R, s, t, shape, keypoints, visible, maps, lam, max_iters, tol, rscale=None) -> Fitted:
    """:func:`_optimize`'s torch path: Levenberg-Marquardt steps (:func:`_lm_step`) on a working set of rows that
    shrinks as cameras finish (:data:`COMPACT_FRACTION`)."""
    dt = keypoints.dtype
    n, b = s.shape
    kmask = torch.isfinite(shape).all(-1)
    S = torch.nan_to_num(shape).to(dt)
    kmf = kmask.to(dt)
    wv = (visible & kmask & torch.isfinite(keypoints).all(-1)).to(dt)
    kp = torch.nan_to_num(keypoints)
    if maps is not None and not bool((lam > 0).any()):
        maps = None  # no silhouette term anywhere: the maps are never sampled
    if maps is not None:
        maps = _finite_maps(maps).to(dt)
    if rscale is not None:
        rscale = rscale.to(dt)
    flat = maps is None and b > 1
    if flat:
        # without maps every camera is its own row, so finished starts can be dropped one by one
        R, s, t = R.reshape(n * b, 1, 3, 3), s.reshape(n * b, 1), t.reshape(n * b, 1, 2)
        kp, wv, lam = kp.repeat_interleave(b, 0), wv.repeat_interleave(b, 0), lam.repeat_interleave(b, 0)
        rscale = None if rscale is None else rscale.repeat_interleave(b, 0)
    E, E_kp, E_sil, g, H = _terms(R, s, t, S, kmf, kp, wv, maps, lam, rscale)
    E_before = E.clone()
    active = torch.isfinite(E)
    # the working set: ``rows`` of the full state
    full = state = _LMState(R=R, s=s, t=t, E=E, E_kp=E_kp, E_sil=E_sil, g=g, H=H, mu=torch.full_like(E, 1e-3),
                            active=active, converged=torch.zeros_like(active))
    rows = None
    n_live = int(active.any(-1).sum())  # one host read per step: it also decides when to stop
    data = _LMData(keypoints=kp, weights=wv, maps=maps, lam=lam, rscale=rscale)
    it = 0
    for it in range(1, max_iters + 1):
        if n_live == 0:
            it -= 1
            break
        state = _lm_step(state, data, S, kmf, tol, dt)
        live = state.active.any(-1)
        n_live = int(live.sum())
        if 0 < n_live <= COMPACT_FRACTION * live.shape[0]:
            full = state.written_into(full, rows)
            keep = live.nonzero().squeeze(1)
            rows = keep if rows is None else rows[keep]
            state, data = state.rows(keep), data.rows(keep)
    full = state.written_into(full, rows)
    R, s, t, E, E_kp, E_sil, converged = full.R, full.s, full.t, full.E, full.E_kp, full.E_sil, full.converged
    if flat:
        R, s, t = R.reshape(n, b, 3, 3), s.reshape(n, b), t.reshape(n, b, 2)
        E_before, E, E_kp, E_sil, converged = (x.reshape(n, b) for x in (E_before, E, E_kp, E_sil, converged))
    return Fitted(R=R, s=s, t=t, E_before=E_before, E=E, E_kp=E_kp, E_sil=E_sil, iterations=it, converged=converged)


def _lm_step(state: _LMState, data: _LMData, S: torch.Tensor, kmf: torch.Tensor, tol: float,
             dt: torch.dtype) -> _LMState:
    """One Levenberg-Marquardt step of :func:`_optimize_impl` on its working set.

    ``state`` and ``data`` are row-aligned; ``dt`` is the working dtype (the keypoints'), in which the step is
    taken. Returns the new state. An active camera takes its step only where the energy does not rise (its damping
    is then divided by 3, else multiplied by 4); it stops when the relative decrease is at most ``tol`` or the
    damping passes 1e8.
    """
    st = state
    # damped 6x6 solves in float64: H can be rank-deficient (an instance with one
    # visible keypoint whose shape points all fall inside its mask has no
    # information about most directions); the relative ridge keeps A definite
    H64 = st.H.double()
    diagH = H64.diagonal(dim1=-2, dim2=-1)
    ridge = 1e-6 * diagH.mean(-1, keepdim=True) + 1e-12
    A = H64 + st.mu.double()[..., None, None] * torch.diag_embed(diagH + ridge)
    sol, info = torch.linalg.solve_ex(A, st.g.double().unsqueeze(-1))
    delta = (-sol.squeeze(-1)).to(dt)
    ok = st.active & (info == 0) & torch.isfinite(delta).all(-1)
    delta = torch.where(ok[..., None], delta, torch.zeros_like(delta))
    Rt, s_t, tt = _retract(st.R, st.s, st.t, delta)
    Et, Ekt, Est, gt, Ht = _terms(Rt, s_t, tt, S, kmf, data.keypoints, data.weights, data.maps, data.lam, data.rscale)
    accept = st.active & torch.isfinite(Et) & (Et <= st.E)
    small = accept & ((st.E - Et) <= tol * st.E)
    a2, a3 = accept[..., None], accept[..., None, None]
    mu = torch.where(accept, st.mu / 3.0, torch.where(st.active, st.mu * 4.0, st.mu))
    done = small | (mu > 1e8)
    return _LMState(R=torch.where(a3, Rt, st.R), s=torch.where(accept, s_t, st.s), t=torch.where(a2, tt, st.t),
                    E=torch.where(accept, Et, st.E), E_kp=torch.where(accept, Ekt, st.E_kp),
                    E_sil=torch.where(accept, Est, st.E_sil), g=torch.where(a2, gt, st.g),
                    H=torch.where(a3, Ht, st.H), mu=mu, active=st.active & ~done,
                    converged=st.converged | (st.active & done))


def _as_batched(cameras: ScaledOrthographic, dtype):
    return cameras.R.to(dtype)[:, None], cameras.s.to(dtype)[:, None], cameras.t.to(dtype)[:, None]


def planar_twin(shape: torch.Tensor, cameras: ScaledOrthographic,
                visible: torch.Tensor) -> tuple[ScaledOrthographic, torch.Tensor]:
    """The other camera under which the plane of an instance's visible keypoints projects the same.

    Orthographic views of a plane come in pairs: with ``n`` the unit normal of the plane
    (through ``c``) best fitting the instance's visible mean-shape points and
    ``H = I - 2 n n^T`` the reflection through it, the camera ``(D R H, s, t')``,
    ``D = diag(1, 1, -1)`` (a proper rotation), ``t' = t + 2 s (n . c) R[:2] n``, projects every
    point of that plane exactly where ``(R, s, t)`` does, and tilts the rest of the shape the
    other way. When the visible keypoints are (nearly) coplanar -- a monitor's four front
    corners -- keypoints cannot tell the two apart and SfM lands in either; the silhouette can.

    Args:
        shape: ``(K, 3)`` mean shape (NaN rows ignored).
        cameras: N cameras.
        visible: ``(N, K)`` bool.

    Returns:
        ``(twin, thickness)``: N cameras (float dtype of ``cameras``) and ``(N,)`` the
        thickness of the visible points, ``sqrt(l_min / l_mid)`` of their spread's eigenvalues
        (0 for exactly coplanar points, up to 1). An instance with fewer than 3 usable points
        gets its camera back unchanged and an infinite thickness.

    Example:
        >>> S = torch.tensor([[0., 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1]])
        >>> cam = ScaledOrthographic(axis_angle_to_rotation(torch.tensor([[0.3, 0.2, 0.1]])),
        ...                          torch.tensor([2.0]), torch.tensor([[5.0, 6.0]]))
        >>> vis = torch.tensor([[True, True, True, True, False]])
        >>> twin, thickness = planar_twin(S, cam, vis)
        >>> torch.allclose(twin.project(S)[:, :4], cam.project(S)[:, :4], atol=1e-5), float(thickness[0]) < 1e-3
        (True, True)
    """
    R, sc, t = cameras.R, cameras.s, cameras.t
    dt = R.dtype
    c, evals, evecs, cnt = _spread(shape.to(dt), visible)
    n = evecs[..., 0]  # (N, 3): the direction of least spread
    H = torch.eye(3, dtype=dt, device=R.device) - 2 * n[:, :, None] * n[:, None, :]
    D = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=dt, device=R.device))
    R2 = D @ R @ H
    t2 = t + 2 * (sc * (n * c).sum(-1))[:, None] * torch.einsum("nij,nj->ni", R[:, :2], n)
    ok = cnt >= 3
    twin = ScaledOrthographic(torch.where(ok[:, None, None], R2, R), sc, torch.where(ok[:, None], t2, t))
    return twin, _thickness(evals, ok)


def _spread(shape: torch.Tensor, visible: torch.Tensor):
    """Spread of each instance's visible, finite shape points: ``(centroid (N, 3), eigenvalues
    (N, 3) ascending, eigenvectors (N, 3, 3) as columns, point count (N,))`` in ``shape``'s dtype."""
    X = torch.nan_to_num(shape)
    w = (visible & torch.isfinite(shape).all(-1)).to(shape.dtype)  # (N, K)
    cnt = w.sum(1)
    c = (w @ X) / cnt.clamp(min=1)[:, None]  # (N, 3)
    Xc = X[None] - c[:, None]  # (N, K, 3)
    evals, evecs = torch.linalg.eigh(torch.einsum("nk,nki,nkj->nij", w, Xc, Xc))
    return c, evals, evecs, cnt


def _thickness(evals: torch.Tensor, ok: torch.Tensor) -> torch.Tensor:
    """Spread across the best plane over the smaller spread within it, ``sqrt(l_min / l_mid)``;
    ``inf`` where ``ok`` is False (fewer than 3 points)."""
    th = (evals[:, 0].clamp(min=0) / evals[:, 1].clamp(min=torch.finfo(evals.dtype).tiny)).sqrt()
    return torch.where(ok, th, torch.full_like(th, float("inf")))


def keypoint_thickness(shape: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
    """``(N,)`` thickness of each instance's visible shape points, as :func:`planar_twin` measures it:
    ``sqrt(l_min / l_mid)`` of their spread (0 for coplanar points, up to 1; ``inf`` for fewer than 3).

    Example:
        >>> S = torch.tensor([[0., 0, 0], [2, 0, 0], [0, 1, 0], [2, 1, 0], [1, 1, 1]])
        >>> keypoint_thickness(S, torch.tensor([[True] * 4 + [False], [True] * 5])).tolist()[0]
        0.0
    """
    _c, evals, _v, cnt = _spread(shape, visible)
    return _thickness(evals, cnt >= 3)


def supported_shape(shape: torch.Tensor, visible: torch.Tensor, min_support: float = MIN_SUPPORT) -> torch.Tensor:
    """The mean shape without the keypoints too few instances show (their rows set to NaN).

    SfM places a keypoint in 3D from the instances that show it; one that a handful of
    instances show is placed from a handful of views, and can be far off. The keypoint term
    uses it only for those instances, but the silhouette term pulls it into *every*
    instance's mask, so one badly placed point can turn every camera (on the PASCAL3D+ boat
    renders with three shape groups, a ``tail`` seen by 2 of a group's 28 objects sat at mid
    length, and refinement moved that group from 12 to 53 degrees). Rows whose support -- the
    fraction of ``visible``'s instances showing the keypoint -- is below ``min_support``
    become NaN, which the refinement leaves out of both terms.

    Args:
        shape: ``(K, 3)`` mean shape (NaN rows stay NaN).
        visible: ``(N, K)`` bool, the instances whose cameras will be refined with the shape
            (a class, or one shape group of it).
        min_support: in ``[0, 1]``; 0 keeps every row.

    Returns:
        ``(K, 3)``, a new tensor; ``shape`` itself when nothing is dropped or ``N == 0``.

    Example:
        >>> S = torch.arange(9.0).view(3, 3)
        >>> vis = torch.tensor([[True, True, False]] * 19 + [[True, True, True]])
        >>> supported_shape(S, vis, 0.1)[:, 0]
        tensor([0., 3., nan])
    """
    if not 0 <= min_support <= 1:
        raise ValueError(f"min_support must be in [0, 1], got {min_support}")
    if visible.dim() != 2 or shape.dim() != 2 or visible.shape[1] != shape.shape[0]:
        raise ValueError(f"need shape (K, 3) and visible (N, K), got {tuple(shape.shape)} and {tuple(visible.shape)}")
    if visible.shape[0] == 0 or min_support == 0:
        return shape
    weak = visible.float().mean(0) < min_support
    if not bool(weak.any()):
        return shape
    return torch.where(weak.to(shape.device)[:, None], torch.full_like(shape, float("nan")), shape)


# --------------------------------------------------------------------------- public


def refine_cameras(
    shape: torch.Tensor,
    cameras: ScaledOrthographic,
    keypoints: torch.Tensor,
    visible: torch.Tensor,
    dist_maps: torch.Tensor | None,
    *,
    silhouette_weight: float = 1.0,
    max_iters: int = 100,
    tol: float = 1e-6,
    mask_valid: torch.Tensor | None = None,
    silhouette_robust: float | None = ROBUST_FRACTION,
    twin_flatness: float = 0.0,
    twin_margin: float = TWIN_MARGIN,
    twin_hull: bool = TWIN_HULL_TIEBREAK,
) -> RefineResult:
    """Refine every instance's camera against its keypoints and silhouette, at once.

    Minimises the energy of the module docstring for each instance with the shape
    fixed; no instance's energy ever rises (rejected steps keep the camera).
    With ``twin_flatness > 0``, each instance whose visible keypoints are that flat (the
    thickness of :func:`planar_twin` below it; 1 takes every instance) is also refined from
    the planar twin of its camera; the twin's result is kept when its energy is lower than
    the other's by at least the fraction ``twin_margin``, or, with ``twin_hull``, lower by less and
    its projected hull's IoU with the mask higher by more than ``HULL_GAIN`` (:func:`twin_wins`; rows
    without a silhouette term are judged by the energy alone). ``start`` says which was kept.

    Args:
        shape: ``(K, 3)`` mean shape (NaN rows are ignored).
        cameras: N initial cameras (e.g. ``SfMResult.cameras``).
        keypoints: ``(N, K, 2)`` canvas pixels; visible: ``(N, K)`` bool.
        dist_maps: ``(N, H, W)`` ``distance_to_mask`` of the canvas masks (``inf``
            for empty masks), or ``None`` for the keypoint term alone.
        silhouette_weight: ``lambda`` of the silhouette term (pixels^2 per pixel^2).
        max_iters, tol: see the stopping rule in the module docstring.
        mask_valid: ``(N,)`` bool; instances with False (empty masks) use the
            keypoint term only. Default: maps that are finite everywhere.
        silhouette_robust: robust scale of the silhouette penalty as a fraction of
            each mask's larger side (module docstring); None: squared distance.
        twin_flatness: see above; 0 (the default): one start. The second start is run for
            the flat instances only.
        twin_margin: see above (:data:`TWIN_MARGIN`).
        twin_hull: see above (:data:`TWIN_HULL_TIEBREAK`).

    Returns:
        :class:`RefineResult` (``energy_before``: the given cameras').
    """
    _check(shape, keypoints, visible, dist_maps, len(cameras))
    _check_robust(silhouette_robust)
    if silhouette_weight < 0:
        raise ValueError(f"silhouette_weight must be >= 0, got {silhouette_weight}")
    if not twin_flatness >= 0 or not 0 <= twin_margin < 1:
        raise ValueError(f"need twin_flatness >= 0 and 0 <= twin_margin < 1, got {twin_flatness}, {twin_margin}")
    dt = keypoints.dtype
    if dist_maps is None:
        lam = torch.zeros(keypoints.shape[0], dtype=dt, device=keypoints.device)
    else:
        lam = silhouette_weight * _mask_valid(dist_maps, mask_valid).to(dt)
    rscale = None
    if dist_maps is not None and silhouette_robust is not None:
        rscale = robust_scales(dist_maps, silhouette_robust)
    energy = _Energy(shape=shape, keypoints=keypoints, visible=visible, dist_maps=dist_maps, lam=lam, rscale=rscale,
                     max_iters=max_iters, tol=tol)
    res = _result(energy.refine(cameras), torch.zeros(len(cameras), dtype=torch.long, device=keypoints.device))
    if twin_flatness > 0:  # the second start, for the flat instances only (instances are optimised independently)
        twin, thickness = planar_twin(shape, ScaledOrthographic(cameras.R.to(dt), cameras.s.to(dt),
                                                                cameras.t.to(dt)), visible)
        idx = (thickness < twin_flatness).nonzero().squeeze(1)
        if idx.numel():
            res = _twin_restart(res, twin[idx], idx, energy, twin_margin, twin_hull)
    return res


def _result(fit: Fitted, start: torch.Tensor) -> RefineResult:
    """``fit``, one start per row (``(N,)`` tensors), as a :class:`RefineResult` whose rows won ``start`` ``(N,)``."""
    return RefineResult(cameras=fit.cameras, energy_before=fit.E_before, energy_after=fit.E, iterations=fit.iterations,
                        converged=fit.converged, keypoint_energy=fit.E_kp, silhouette_energy=fit.E_sil, start=start)


@dataclass(frozen=True)
class _Energy:
    """:func:`refine_cameras`' energy of ``N`` rows and its stopping rule: ``shape (K, 3)``, ``keypoints (N, K, 2)``,
    ``visible (N, K)``, ``dist_maps (N, H, W)`` or ``None``, ``lam (N,)`` (``lambda`` per row), ``rscale (N,)``
    (the robust scales, :func:`robust_scales`) or ``None`` (squared distances), ``max_iters``, ``tol``."""

    shape: torch.Tensor
    keypoints: torch.Tensor
    visible: torch.Tensor
    dist_maps: torch.Tensor | None
    lam: torch.Tensor
    rscale: torch.Tensor | None
    max_iters: int
    tol: float

    def rows(self, idx: torch.Tensor) -> "_Energy":
        """The energy of rows ``idx`` (``(M,)`` int64) alone."""
        sub = lambda x: None if x is None else x[idx]  # noqa: E731
        return replace(self, keypoints=self.keypoints[idx], visible=self.visible[idx], dist_maps=sub(self.dist_maps),
                       lam=self.lam[idx], rscale=sub(self.rscale))

    def refine(self, cameras: ScaledOrthographic) -> Fitted:
        """``N`` cameras, one start each, refined (:func:`_optimize` in the keypoints' dtype): ``(N,)`` tensors."""
        R, s, t = _as_batched(cameras, self.keypoints.dtype)
        return _optimize(R, s, t, self.shape, self.keypoints, self.visible, self.dist_maps, self.lam, self.max_iters,
                         self.tol, self.rscale).first_start()


def _twin_restart(first: RefineResult, twin: ScaledOrthographic, idx: torch.Tensor, energy: _Energy,
                  twin_margin: float, twin_hull: bool) -> RefineResult:
    """:func:`refine_cameras`' second start: rows ``idx`` (``(M,)`` int64) refined from their planar ``twin`` cameras
    (``M``), each twin kept where :func:`twin_wins`. ``first``: the result of the first start over all ``N`` rows,
    returned with the winning twins' cameras, energies and stopping in their rows and ``start`` 1 there."""
    sub = energy.rows(idx)
    o2 = sub.refine(twin)
    # the hull judges only rows whose energy has a silhouette term (an empty mask: IoU 0 either way)
    masks = None
    if sub.dist_maps is not None and twin_hull:
        masks = (sub.dist_maps == 0) & (sub.lam > 0)[:, None, None]
    wins = twin_wins(energy.shape, first.cameras[idx], first.energy_after[idx], o2.cameras, o2.E, masks, twin_margin)
    win = idx[wins]
    put = lambda x, y: x.index_put((win,), y[wins])  # noqa: E731
    cams = first.cameras
    return replace(first, cameras=ScaledOrthographic(put(cams.R, o2.R), put(cams.s, o2.s), put(cams.t, o2.t)),
                   energy_after=put(first.energy_after, o2.E), iterations=max(first.iterations, o2.iterations),
                   converged=put(first.converged, o2.converged), keypoint_energy=put(first.keypoint_energy, o2.E_kp),
                   silhouette_energy=put(first.silhouette_energy, o2.E_sil),
                   start=first.start.index_put((win,), torch.ones_like(win)))


def twin_wins(shape: torch.Tensor, own: ScaledOrthographic, energy: torch.Tensor, twin: ScaledOrthographic,
              twin_energy: torch.Tensor, masks: torch.Tensor | None, margin: float = TWIN_MARGIN) -> torch.Tensor:
    """``(M,)`` bool: the rows whose refined planar twin replaces their own refined camera.

    The twin wins when its energy is lower by at least the fraction ``margin``, or (with ``masks``) when it is
    lower by less and the convex hull of the projected ``shape`` agrees clearly better with the mask under the
    twin: its IoU (:func:`~carvi_torch.viewpoints.choice.hull_agreement`, computed for those rows only) is higher
    by more than :data:`~carvi_torch.viewpoints.choice.HULL_GAIN`, the gain that also clears a refined camera
    of suspicion.

    Args:
        shape: ``(K, 3)``; own, twin: ``M`` cameras each; energy, twin_energy: ``(M,)``;
        masks: ``(M, H, W)`` bool or ``None`` (the energy alone).

    Example:
        >>> S = torch.tensor([[-4., -4, 0], [4, -4, 0], [4, 4, 0], [-4, 4, 0]])
        >>> big = ScaledOrthographic(torch.eye(3).expand(2, 3, 3), torch.full((2,), 2.0), torch.full((2, 2), 16.))
        >>> small = ScaledOrthographic(big.R, torch.ones(2), big.t)
        >>> mask = torch.zeros(2, 32, 32, dtype=torch.bool); mask[:, 8:25, 8:25] = True
        >>> twin_wins(S, small, torch.tensor([10.0, 10.0]), big, torch.tensor([9.9, 8.0]), mask).tolist()
        [True, True]
        >>> twin_wins(S, big, torch.tensor([10.0, 10.0]), small, torch.tensor([9.9, 8.0]), mask).tolist()
        [False, True]
    """
    wins = twin_energy < (1.0 - margin) * energy  # the twin must win clearly ...
    tie = ~wins & (twin_energy < energy)
    if masks is None or not bool(tie.any()):
        return wins
    at = tie.nonzero().squeeze(1)
    better = hull_agreement(shape, twin[at], masks[at]) > hull_agreement(shape, own[at], masks[at]) + HULL_GAIN
    return wins.index_put((at,), better.to(wins.device))  # ... or agree better with the mask


def mask_start_cameras(shape: torch.Tensor, masks: torch.Tensor | None, keypoints: torch.Tensor,
                       visible: torch.Tensor, rotations: torch.Tensor | None = None) -> ScaledOrthographic:
    """Cameras that put the shape on the mask: given rotation, mask centre, size from the mask.

    ``s`` = (larger side of the mask's bounding box) / (larger side of the shape's
    bounding box in the rotated image plane); ``t`` puts the shape's centroid on the
    mask's centroid. Instances with an empty (or no) mask use their visible
    keypoints' centroid and bounding box instead, and the canvas-free default
    ``s = 1, t = 0`` when they have none.

    Args:
        shape: ``(K, 3)``; masks: ``(N, H, W)`` bool or None; keypoints ``(N, K, 2)``;
        visible ``(N, K)``; rotations: ``(N, 3, 3)``, identity when None.

    Returns:
        N cameras in the keypoints' dtype.
    """
    n = keypoints.shape[0]
    dt, dev = keypoints.dtype, keypoints.device
    R = torch.eye(3, dtype=dt, device=dev).expand(n, 3, 3) if rotations is None else rotations.to(dt)
    S = shape[torch.isfinite(shape).all(-1)].to(dt)
    if S.shape[0] == 0:
        raise ValueError("shape has no finite row")
    proj = S @ R[:, :2, :].transpose(-1, -2)  # (N, K', 2)
    ext = (proj.amax(1) - proj.amin(1)).amax(-1).clamp(min=1e-12)  # (N,)
    c3 = S.mean(0)
    # keypoint fallback
    vk = visible & torch.isfinite(keypoints).all(-1)
    nk = vk.sum(-1)
    kp0 = torch.nan_to_num(keypoints)
    kc = (kp0 * vk[..., None]).sum(1) / nk.clamp(min=1)[:, None]
    big = torch.tensor(float("inf"), dtype=dt, device=dev)
    kmax = torch.where(vk[..., None], kp0, -big).amax(1)
    kmin = torch.where(vk[..., None], kp0, big).amin(1)
    ksize = torch.where(nk >= 2, (kmax - kmin).amax(-1), torch.zeros_like(ext))
    centre, size = kc, ksize
    if masks is not None:
        m = masks.bool()
        h, w = m.shape[1:]
        area = m.flatten(1).sum(-1)
        ys = torch.arange(h, dtype=dt, device=dev)
        xs = torch.arange(w, dtype=dt, device=dev)
        mf = m.to(dt)
        cx = (mf.sum(1) * xs).sum(-1) / area.clamp(min=1)
        cy = (mf.sum(2) * ys).sum(-1) / area.clamp(min=1)
        colany, rowany = m.any(1), m.any(2)
        bw = torch.where(colany, xs, -big).amax(-1) - torch.where(colany, xs, big).amin(-1) + 1
        bh = torch.where(rowany, ys, -big).amax(-1) - torch.where(rowany, ys, big).amin(-1) + 1
        has = area > 0
        centre = torch.where(has[:, None], torch.stack([cx, cy], -1), kc)
        size = torch.where(has, torch.maximum(bw, bh), ksize)
    s = torch.where(size > 0, size / ext, torch.ones_like(ext))
    t = centre - s[:, None] * (R[:, :2, :] @ c3)
    return ScaledOrthographic(R.contiguous(), s, t)


def refine_keypoints_only(
    shape: torch.Tensor,
    cameras: ScaledOrthographic,
    keypoints: torch.Tensor,
    visible: torch.Tensor,
    masks: torch.Tensor | None = None,
    *,
    max_iters: int = 100,
    tol: float = 1e-6,
) -> RefineResult:
    """Keypoint-only refinement from two starts per instance, keeping the better.

    Starts: (0) the given camera (e.g. SfM's); (1) identity rotation, the mask's
    centre and a scale from the mask size vs the shape extent
    (:func:`mask_start_cameras`; the visible keypoints stand in for a missing
    mask). Both are refined at once with ``lambda = 0``; ``start`` reports the winner.

    Args:
        shape: ``(K, 3)``; cameras: N; keypoints ``(N, K, 2)``; visible ``(N, K)``;
        masks: ``(N, H, W)`` bool or None.

    Returns:
        :class:`RefineResult` (``silhouette_energy`` is 0).
    """
    _check(shape, keypoints, visible, masks, len(cameras))
    dt = keypoints.dtype
    c1 = mask_start_cameras(shape, masks, keypoints, visible)
    R0, s0, t0 = _as_batched(cameras, dt)
    R = torch.cat([R0, c1.R[:, None]], 1)
    s = torch.cat([s0, c1.s[:, None]], 1)
    t = torch.cat([t0, c1.t[:, None]], 1)
    lam = torch.zeros(keypoints.shape[0], dtype=dt, device=keypoints.device)
    fit = _optimize(R, s, t, shape, keypoints, visible, None, lam, max_iters, tol)
    won, best = fit.best_start()
    return _result(won._replace(E_before=fit.E_before[:, 0]), best)


def refine_starts_keypoints_only(
    shape: torch.Tensor,
    R: torch.Tensor,
    s: torch.Tensor,
    t: torch.Tensor,
    keypoints: torch.Tensor,
    visible: torch.Tensor,
    *,
    max_iters: int = 100,
    tol: float = 1e-6,
    native: bool = False,
) -> tuple[ScaledOrthographic, torch.Tensor]:
    """Keypoint-only refinement of ``B`` given starts per instance, keeping each instance's best.

    Args:
        shape: ``(K, 3)``; R ``(N, B, 3, 3)``, s ``(N, B)``, t ``(N, B, 2)``: the starts;
        keypoints ``(N, K, 2)``; visible ``(N, K)``.
        native: on the CPU, the compiled fit (equal to rounding; the mixture's EM, ``sfm_native``).

    Returns:
        ``cameras`` (N) and ``energy (N,)`` (the squared keypoint residual of each).

    Example:
        >>> S = torch.randn(6, 3, generator=torch.Generator().manual_seed(0))
        >>> true = ScaledOrthographic(torch.eye(3)[None], torch.full((1,), 10.0), torch.zeros(1, 2))
        >>> start = axis_angle_to_rotation(torch.tensor([[[0.1, 0.0, 0.0]]]))
        >>> cams, e = refine_starts_keypoints_only(S, start, torch.full((1, 1), 9.0), torch.zeros(1, 1, 2),
        ...                                       true.project(S), torch.ones(1, 6, dtype=torch.bool))
        >>> bool(e[0] < 1e-6), bool(torch.allclose(cams.R, true.R, atol=1e-4))
        (True, True)
    """
    _check(shape, keypoints, visible, None, R.shape[0])
    lam = torch.zeros(keypoints.shape[0], dtype=keypoints.dtype, device=keypoints.device)
    dt = keypoints.dtype
    fit = _optimize(R.to(dt), s.to(dt), t.to(dt), shape, keypoints, visible, None, lam, max_iters, tol, native=native)
    won, _best = fit.best_start()
    return won.cameras, won.E


def sphere_rotations(n: int, dtype=torch.float32, device="cpu") -> torch.Tensor:
    """``n`` rotations whose viewing directions (third rows) cover the sphere evenly.

    Directions on a Fibonacci spiral (``z_i = 1 - (2 i + 1) / n``, golden-angle
    longitudes); each is completed to a proper rotation with an arbitrary in-plane
    roll (the refinement's starts solve the roll in closed form).

    Returns:
        ``(n, 3, 3)``.
    """
    i = torch.arange(n, dtype=torch.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    r = (1.0 - z * z).clamp(min=0).sqrt()
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    d = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    a = torch.where((d[:, 2].abs() < 0.9)[:, None], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64),
                    torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    r0 = torch.linalg.cross(a, d)
    r0 = r0 / r0.norm(dim=-1, keepdim=True)
    r1 = torch.linalg.cross(d, r0)
    return torch.stack([r0, r1, d], 1).to(dtype=dtype, device=device)


def _procrustes_starts(shape, keypoints, visible, R0, fallback: ScaledOrthographic):
    """Per image and start rotation, the best in-plane rotation, scale and translation.

    2-D similarity fit (proper rotation) of the projected shape ``S R0[:2]^T`` onto
    the visible keypoints, in closed form. Images with < 2 usable keypoints (or a
    degenerate projection) take ``fallback``'s scale and translation with ``R0``.

    Args:
        shape ``(K, 3)``; keypoints ``(M, K, 2)``; visible ``(M, K)``; R0 ``(B, 3, 3)``;
        fallback: M cameras (their ``s``, ``t`` are used).

    Returns:
        ``R (M, B, 3, 3)``, ``s (M, B)``, ``t (M, B, 2)``.
    """
    dt = keypoints.dtype
    m, b = keypoints.shape[0], R0.shape[0]
    kmask = torch.isfinite(shape).all(-1)
    S = torch.nan_to_num(shape).to(dt)
    w = (visible & kmask & torch.isfinite(keypoints).all(-1)).to(dt)  # (M, K)
    q = torch.nan_to_num(keypoints)
    p = torch.einsum("kj,bij->bki", S, R0[:, :2, :])  # (B, K, 2)
    wsum = w.sum(-1).clamp(min=1e-30)  # (M,)
    qc = (w[..., None] * q).sum(1) / wsum[:, None]  # (M, 2)
    pc = torch.einsum("mk,bki->mbi", w, p) / wsum[:, None, None]  # (M, B, 2)
    qd = q[:, None] - qc[:, None, None]  # (M, 1, K, 2)
    pd = p[None] - pc[:, :, None]  # (M, B, K, 2)
    C = torch.einsum("mk,mbki,mbkj->mbij", w, qd.expand(-1, b, -1, -1), pd)  # sum w q p^T
    theta = torch.atan2(C[..., 1, 0] - C[..., 0, 1], C[..., 0, 0] + C[..., 1, 1])
    c, sn = torch.cos(theta), torch.sin(theta)
    Rot = torch.stack([torch.stack([c, -sn], -1), torch.stack([sn, c], -1)], -2)  # (M, B, 2, 2)
    num = (Rot * C).sum((-1, -2))
    den = torch.einsum("mk,mbki->mb", w, pd * pd)
    ok = (w.sum(-1) >= 2)[:, None] & (den > 1e-12 * den.amax().clamp(min=1e-30)) & (num > 0)
    s = torch.where(ok, num / den.clamp(min=1e-30), fallback.s.to(dt)[:, None].expand(m, b))
    rows = Rot @ R0[None, :, :2, :]  # (M, B, 2, 3)
    R = complete_rotation(rows)
    R = torch.where(ok[..., None, None], R, R0[None].expand(m, b, 3, 3))
    t_fit = qc[:, None] - s[..., None] * (Rot @ pc[..., None]).squeeze(-1)
    # fallback translation: the shape centroid on the fallback camera's image of it
    c3 = S[kmask].mean(0) if bool(kmask.any()) else S.new_zeros(3)
    target = fallback.t.to(dt) + fallback.s.to(dt)[:, None] * (fallback.R.to(dt)[:, :2, :] @ c3)
    t_fb = target[:, None] - s[..., None] * (R[..., :2, :] @ c3)
    t = torch.where(ok[..., None], t_fit, t_fb)
    return R, s, t


def estimate_camera(
    shape: torch.Tensor,
    keypoints: torch.Tensor,
    visible: torch.Tensor,
    masks_or_dist_maps: torch.Tensor,
    *,
    n_starts: int = 16,
    silhouette_weight: float = 1.0,
    max_iters: int = 100,
    tol: float = 1e-6,
    mask_valid: torch.Tensor | None = None,
    silhouette_robust: float | None = ROBUST_FRACTION,
) -> tuple[ScaledOrthographic, torch.Tensor]:
    """Cameras of new, unseen images from their keypoints and masks.

    Starts per image (all refined at once, ``M x (n_starts + 1)`` cameras): the
    paper's identity rotation at the mask centre with a scale from the mask size
    (:func:`mask_start_cameras`), plus ``n_starts`` viewing directions spread over
    the sphere (:func:`sphere_rotations`; the object frame of an SfM shape has no
    known up, so directions are not tied to azimuth / elevation), each with its
    in-plane rotation, scale and translation solved in closed form from the
    visible keypoints. Every start is refined with :func:`refine_cameras`' energy;
    each image keeps its lowest-energy camera.

    Args:
        shape: ``(K, 3)``.
        keypoints: ``(M, K, 2)``; visible: ``(M, K)`` bool.
        masks_or_dist_maps: ``(M, H, W)``: bool masks (their distance maps are
            computed here) or float ``distance_to_mask`` maps.
        n_starts: number of rotated starts (besides the identity one).
        silhouette_weight, max_iters, tol, mask_valid, silhouette_robust: as in
            :func:`refine_cameras`.

    Returns:
        ``cameras`` (M) and ``energy (M,)``; an image whose visible keypoints collapse to one point
        (:func:`collapsed_keypoints`) gets a NaN camera and an infinite energy.
    """
    _check(shape, keypoints, visible, masks_or_dist_maps)
    if n_starts < 0:
        raise ValueError(f"n_starts must be >= 0, got {n_starts}")
    dt, dev = keypoints.dtype, keypoints.device
    if masks_or_dist_maps.dtype == torch.bool:
        masks = masks_or_dist_maps
        maps = distance_to_mask(masks)
    else:
        masks = None
        maps = masks_or_dist_maps
    valid = _mask_valid(maps, mask_valid)
    if masks is None:
        masks = (maps == 0) & valid[:, None, None]
    base = mask_start_cameras(shape, masks, keypoints, visible)
    Rs = [base.R[:, None]]
    ss = [base.s[:, None]]
    ts = [base.t[:, None]]
    if n_starts > 0:
        R0 = sphere_rotations(n_starts, dtype=dt, device=dev)
        R, s, t = _procrustes_starts(shape, keypoints, visible, R0, base)
        Rs.append(R)
        ss.append(s)
        ts.append(t)
    R, s, t = torch.cat(Rs, 1), torch.cat(ss, 1), torch.cat(ts, 1)
    lam = silhouette_weight * valid.to(dt)
    _check_robust(silhouette_robust)
    maps = maps.to(dev)
    rscale = None if silhouette_robust is None else robust_scales(maps, silhouette_robust)
    won, _best = _optimize(R, s, t, shape, keypoints, visible, maps, lam, max_iters, tol, rscale).best_start()
    return _without_collapsed(won.cameras, won.E, collapsed_keypoints(keypoints, visible, shape))


def _without_collapsed(cams: ScaledOrthographic, energy: torch.Tensor,
                       collapsed: torch.Tensor) -> tuple[ScaledOrthographic, torch.Tensor]:
    """``cams`` and ``energy`` with the ``collapsed (M,)`` rows made NaN and infinite (no camera)."""
    if not bool(collapsed.any()):
        return cams, energy
    nan = torch.tensor(float("nan"), dtype=cams.s.dtype, device=cams.s.device)
    R = torch.where(collapsed[:, None, None], nan, cams.R)
    s = torch.where(collapsed, nan, cams.s)
    t = torch.where(collapsed[:, None], nan, cams.t)
    return ScaledOrthographic(R, s, t), torch.where(collapsed, torch.full_like(energy, float("inf")), energy)
