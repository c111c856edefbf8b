"""Joint Levenberg-Marquardt bundle adjustment of scaled orthographic cameras and one shape.

Minimises, over every camera and the shape at once,

    cost = sum_n sum_{k visible in n} || s_n R_n[:2] X_k + t_n - w_nk ||^2

(the rigid SfM objective of :mod:`carvi_torch.viewpoints.sfm` on its visible entries).

Conventions (``carvi_torch.cameras``): image x right, y down, points ``(x, y)``;
``uv = s * X @ R[:2].T + t``; ``R`` proper, rows = image x, image y, viewing direction.
Shapes: cameras ``R (N, 3, 3)``, ``s (N,)``, ``t (N, 2)``; shape ``X (K, 3)``; keypoints
``w (N, K, 2)``; ``visible (N, K)`` bool. Everything runs in float64, batched over the
instances (no Python loop over them), on the tensors' device; the results come back in the shape's dtype.

Parameters of one step: per camera 6 numbers ``(omega, rho, tau)`` -- ``R <- exp([omega]_x) R``
(a rotation about the camera axes), ``s <- s exp(rho)``, ``t <- t + tau`` -- and the shape's
``3K`` coordinates ``X <- X + xi``. The Gauss-Newton matrix has a block-diagonal camera part
(``6x6`` per camera), so the cameras are eliminated (Schur complement) and one ``3K x 3K``
system is solved for the shape (``K`` is a class's keypoint count, about 10-20), then the
cameras are back-substituted. The damping is Marquardt's (``lambda`` times the matrix's
diagonal, floored), updated by Nielsen's rule; it also keeps the 7 gauge directions (a global
rotation, scale and 3-D translation of the solution) defined, and a step is accepted only
where the cost falls (and no camera's rotation or log-scale moves by more than :data:`MAX_STEP`), so the
cost never rises. Stopping rule, as the alternation's
(``sfm.bundle_polish``): an accepted step lowered the RMS residual by at most ``tol`` of it,
or the RMS residual is at most ``floor``, or the damping exceeds :data:`MAX_DAMPING` (no
descent step is left at float precision); else after ``iters`` damped solves.

The gauge of the result is that of the start moved by the (damped) steps; callers fix it
(``sfm._centre``, ``sfm._scale_gauge``).

Example (a noise-free problem solved from a perturbed start):

    >>> from carvi_torch.cameras import ScaledOrthographic, random_rotations
    >>> g = torch.Generator().manual_seed(0)
    >>> X = torch.randn(8, 3, generator=g, dtype=torch.float64)
    >>> cams = ScaledOrthographic(random_rotations(6, g, torch.float64), torch.ones(6, dtype=torch.float64),
    ...                           torch.zeros(6, 2, dtype=torch.float64))
    >>> w = cams.project(X)
    >>> start = ScaledOrthographic(cams.R, cams.s * 1.05, cams.t + 0.1)
    >>> res = joint_bundle_adjust(start, X + 0.05, w, torch.ones(6, 8, dtype=torch.bool), iters=50, tol=1e-12)
    >>> res.converged, res.history[-1] < 1e-8
    (True, True)
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from .. import native_library
from ..cameras import ScaledOrthographic, axis_angle_to_rotation

__all__ = ["BundleResult", "joint_bundle_adjust", "residuals", "jacobians", "MAX_DAMPING", "MAX_STEP"]

#: Damping above which no descent step is left (the step is at float precision's noise): converged.
MAX_DAMPING = 1e12
#: Longest step of any camera's rotation (radians) or log-scale: a longer one is rejected as a failed step
#: (the damping grows). A camera whose visible keypoints are nearly collinear has a nearly unobservable
#: rotation; without the bound one joint step turned such a camera (a real PASCAL VOC aeroplane showing its
#: nose and rudder points) by thousands of radians while the other cameras' gain lowered the total, and its
#: scale then collapsed to 0.
MAX_STEP = 0.5
#: Marquardt's damping: ``lambda * max(diag, DIAG_FLOOR * mean diag)`` per parameter block (cameras,
#: shape), so unobserved parameters (a keypoint no camera sees) stay defined.
DIAG_FLOOR = 1e-9


@dataclass
class BundleResult:
    """Output of :func:`joint_bundle_adjust`.

    Attributes:
        cameras: N adjusted cameras (the start shape's dtype).
        shape: ``(K, 3)`` (the start shape's dtype).
        history: RMS residual (pixels, over the visible entries) after every accepted step.
        converged: the stopping rule (not the iteration cap) ended the run.
        iterations: damped solves run (accepted and rejected steps).
    """

    cameras: ScaledOrthographic
    shape: torch.Tensor
    history: list
    converged: bool
    iterations: int


def residuals(R: torch.Tensor, s: torch.Tensor, t: torch.Tensor, X: torch.Tensor, w: torch.Tensor,
              v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Masked residuals ``r (N, K, 2) = v * (s R[:2] X + t - w)`` and the rotated points ``Y (N, K, 3) = R X``.

    ``R (N, 3, 3)``, ``s (N,)``, ``t (N, 2)``, ``X (K, 3)``, ``w (N, K, 2)``, ``v (N, K)`` float 0/1.
    """
    Y = torch.einsum("nij,kj->nki", R, X)
    r = (s[:, None, None] * Y[..., :2] + t[:, None, :] - w) * v[..., None]
    return r, Y


def jacobians(R: torch.Tensor, s: torch.Tensor, Y: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Analytic Jacobians of the masked residuals at the current parameters.

    Returns ``A (N, K, 2, 6)``: with respect to the camera's ``(omega, rho, tau)`` (rotation increment
    ``exp([omega]_x) R``, log-scale, translation), and ``B (N, K, 2, 3)``: with respect to ``X_k``.
    ``d(R X)/d omega = -[Y]_x``, whose first two rows are ``[[0, Y3, -Y2], [-Y3, 0, Y1]]``.
    """
    n, k = v.shape
    Y1, Y2, Y3 = Y.unbind(-1)
    z = torch.zeros_like(Y1)
    one = torch.ones_like(Y1)
    sv = s[:, None] * v
    rot = torch.stack([torch.stack([z, Y3, -Y2], -1), torch.stack([-Y3, z, Y1], -1)], -2) * sv[..., None, None]
    scale = (Y[..., :2] * sv[..., None])[..., None]
    trans = torch.stack([torch.stack([one, z], -1), torch.stack([z, one], -1)], -2) * v[..., None, None]
    A = torch.cat([rot, scale, trans], -1)
    B = (s[:, None, None] * R[:, :2, :])[:, None] * v[..., None, None]
    return A, B.expand(n, k, 2, 3)


def _normal_equations(A, B, r):
    """Blocks of ``J^T J`` and ``J^T r``: ``U (N, 6, 6)``, ``W (N, 6, 3K)``, ``V (K, 3, 3)``,
    ``gc (N, 6)``, ``gx (K, 3)``."""
    n, k = A.shape[:2]
    U = torch.einsum("nkra,nkrb->nab", A, A)
    W = torch.einsum("nkra,nkrb->nakb", A, B).reshape(n, 6, 3 * k)
    V = torch.einsum("nkra,nkrb->kab", B, B)
    gc = torch.einsum("nkra,nkr->na", A, r)
    gx = torch.einsum("nkra,nkr->ka", B, r)
    return U, W, V, gc, gx


def _damping(H: torch.Tensor, lam: float) -> torch.Tensor:
    """The damping added to the diagonal of square blocks ``H (..., m, m)``: ``lam * max(diag H, DIAG_FLOOR *
    mean diag)``, shape ``(..., m)``."""
    d = H.diagonal(dim1=-2, dim2=-1)
    return lam * d.clamp(min=DIAG_FLOOR * d.mean() + 1e-300)  # a tensor bound: no read-back to the host


def _solve(U, W, V, gc, gx, lam: float):
    """The damped step by the Schur complement (cameras eliminated): ``dc (N, 6)``, ``dx (3K,)`` and the
    damping added to the diagonals, ``Dc (N, 6)``, ``Dx (3K,)``; ``dc`` and ``dx`` are NaN when a damped system
    is not positive definite (the caller reads that with the step's cost, in one read-back)."""
    Dc, Dx = _damping(U, lam), _damping(V, lam).reshape(-1)
    L, info = torch.linalg.cholesky_ex(U + torch.diag_embed(Dc))
    UiW = torch.cholesky_solve(torch.cat([W, gc[..., None]], -1), L)  # (N, 6, 3K + 1)
    S = torch.block_diag(*V.unbind(0)) + torch.diag(Dx) - torch.einsum("nai,naj->ij", W, UiW[..., :-1])
    rhs = torch.einsum("nai,na->i", W, UiW[..., -1]) - gx.reshape(-1)
    Ls, info_s = torch.linalg.cholesky_ex(S)
    dx = torch.cholesky_solve(rhs[:, None], Ls)[:, 0]
    dc = -UiW[..., -1] - torch.einsum("naj,j->na", UiW[..., :-1], dx)
    failed = (info != 0).any() | (info_s != 0)
    return dc.masked_fill(failed, float("nan")), dx.masked_fill(failed, float("nan")), Dc, Dx


def _step_length(dc: torch.Tensor) -> torch.Tensor:
    """The longest move of any camera in ``dc (N, 6)`` (0-d): its rotation's angle ``|omega|`` (radians: the
    rotation ``exp([omega]_x)`` turns by ``|omega|`` whatever the axis) or its log-scale change ``|rho|``; NaN
    for a NaN step."""
    return torch.maximum(dc[:, :3].norm(dim=-1), dc[:, 3].abs()).max()


def _apply(R, logs, t, X, dc, dx):
    """Parameters after the step: ``R <- exp([omega]_x) R``, ``log s <- log s + rho``, ``t <- t + tau``."""
    return axis_angle_to_rotation(dc[:, :3]) @ R, logs + dc[:, 3], t + dc[:, 4:], X + dx


def _native_adjust(ops, problem: tuple, dtype: torch.dtype, iters: int, tol: float, floor: float,
                   damping: float) -> BundleResult:
    """:func:`joint_bundle_adjust`'s loop in the compiled kernel (``carvi_torch/kernels/bundle_steps.h``): the same
    steps in float64, its sums in another order. ``problem``: ``R, log s, t, X, w, v`` in float64 (``w`` with
    non-finite entries zeroed, ``v`` the 0/1 mask)."""
    R, logs, t, X, w, v = (x.contiguous() for x in problem)
    R, logs, t, X, hist, it, converged = ops.joint_bundle(R, logs, t, X, w, v, iters, tol, floor, damping, MAX_STEP,
                                                          MAX_DAMPING, DIAG_FLOOR)
    cams = ScaledOrthographic(R.to(dtype), logs.exp().to(dtype), t.to(dtype))
    return BundleResult(cams, X.to(dtype), hist.tolist(), bool(converged), int(it))


def _check(cameras: ScaledOrthographic, shape: torch.Tensor, keypoints: torch.Tensor, visible: torch.Tensor,
           iters: int, damping: float):
    """Raise ``ValueError`` for inconsistent shapes, a non-bool mask, non-positive scales, a non-finite start,
    a negative ``iters`` or a damping that is not finite and positive (``lambda`` only ever multiplies: from 0 no
    rejected step would raise it, and every damped solve would fail the same way)."""
    if not 0.0 < damping < float("inf"):
        raise ValueError(f"damping must be finite and positive, got {damping}")
    if iters < 0:
        raise ValueError(f"iters must be at least 0, got {iters}")
    if shape.dim() != 2 or shape.shape[1] != 3 or shape.shape[0] == 0:
        raise ValueError(f"shape must be (K, 3), got {tuple(shape.shape)}")
    n, k = len(cameras), shape.shape[0]
    if keypoints.shape != (n, k, 2):
        raise ValueError(f"keypoints must be ({n}, {k}, 2) for {n} cameras and {k} shape points, "
                         f"got {tuple(keypoints.shape)}")
    if visible.shape != (n, k) or visible.dtype != torch.bool:
        raise ValueError(f"visible must be ({n}, {k}) bool, got {tuple(visible.shape)} {visible.dtype}")
    if bool((cameras.s <= 0).any()) or not bool(torch.isfinite(cameras.s).all()):
        raise ValueError("camera scales must be finite and positive (degenerate blocks sit out: leave them out)")
    if not all(bool(torch.isfinite(x).all()) for x in (shape, cameras.R, cameras.t)):
        raise ValueError("the start (shape, rotations, translations) must be finite")


def joint_bundle_adjust(cameras: ScaledOrthographic, shape: torch.Tensor, keypoints: torch.Tensor,
                        visible: torch.Tensor, *, iters: int = 100, tol: float = 1e-7, floor: float = 0.0,
                        damping: float = 1e-3, native: bool = False) -> BundleResult:
    """Joint LM over every camera and the shape (module docstring), the cost never rising.

    Args:
        cameras: N cameras with finite, positive scales (the start).
        shape: ``(K, 3)`` finite start shape.
        keypoints: ``(N, K, 2)`` pixels; entries that are not visible (or not finite) are ignored.
        visible: ``(N, K)`` bool.
        iters: damped solves at most (0: the start is returned).
        tol: relative change of the RMS residual that stops the run.
        floor: RMS residual (pixels) at or below which the run stops (an exact fit).
        damping: initial Marquardt ``lambda`` (finite, positive).
        native: on the CPU, run the same steps in the compiled kernel (:func:`_native_adjust`; equal to this
            code to rounding, not bit for bit); elsewhere, or where the library did not build, this code.

    Returns:
        :class:`BundleResult` (in ``shape``'s dtype; the history holds the accepted steps' RMS residuals).
    """
    _check(cameras, shape, keypoints, visible, iters, damping)
    f64 = torch.float64
    v = (visible & torch.isfinite(keypoints).all(-1)).to(f64)
    w = torch.nan_to_num(keypoints.to(f64))
    R, logs, t, X = cameras.R.to(f64), cameras.s.to(f64).log(), cameras.t.to(f64), shape.to(f64)
    entries = max(2.0 * float(v.sum()), 1.0)
    if native and (ops := native_library.operators_on(shape.device)) is not None:
        return _native_adjust(ops, (R, logs, t, X, w, v), shape.dtype, iters, tol, floor, damping)
    r, Y = residuals(R, logs.exp(), t, X, w, v)
    cost = float((r * r).sum())
    history: list[float] = []
    lam, nu, it, converged = damping, 2.0, 0, iters == 0 or (cost / entries) ** 0.5 <= floor
    while it < iters and not converged:
        it += 1
        A, B = jacobians(R, logs.exp(), Y, v)
        U, W, V, gc, gx = _normal_equations(A, B, r)
        dc, dx, Dc, Dx = _solve(U, W, V, gc, gx, lam)
        new = _apply(R, logs, t, X, dc, dx.reshape(-1, 3))
        r_new, Y_new = residuals(new[0], new[1].exp(), new[2], new[3], w, v)
        pred = (dc * (Dc * dc - gc)).sum() + (dx * (Dx * dx - gx.reshape(-1))).sum()
        # the iteration's one read-back: a failed solve is NaN, and NaN compares False
        length, cost_new, pred = torch.stack([_step_length(dc), (r_new * r_new).sum(), pred]).tolist()
        # a step outside the trust region of the linearised rotations and scales is a failed one
        if not (length <= MAX_STEP and cost_new < cost):
            lam, nu = lam * nu, nu * 2.0
            converged = lam > MAX_DAMPING
            continue
        rho = min((cost - cost_new) / max(pred, 1e-300), 1.0)  # gain ratio; above 1 the factor is 1/3 anyway
        lam, nu = lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 2.0
        prev = (cost / entries) ** 0.5
        (R, logs, t, X), r, Y, cost = new, r_new, Y_new, cost_new
        cur = (cost / entries) ** 0.5
        history.append(cur)
        converged = cur <= floor or prev - cur <= tol * prev
    dt = shape.dtype
    return BundleResult(ScaledOrthographic(R.to(dt), logs.exp().to(dt), t.to(dt)), X.to(dt), history, converged, it)
