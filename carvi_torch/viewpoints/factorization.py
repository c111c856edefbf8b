"""Rigid factorisation with missing data (Marques & Costeira 2008), batched: the core of
:func:`carvi_torch.viewpoints.sfm.rigid_sfm`.

Finds a shape ``S (rank, K)`` and one ``2 x rank`` block and translation per instance that
reproduce the visible entries of the measurement matrix ``W (N, 2, K)`` (instances' keypoints, in
canvas pixels; ``vis (N, K)`` 0/1). One *outer* iteration (:func:`factorize`):

1. **fill** the missing entries of ``W`` with the current model's predictions (first
   iteration: the instance's mean visible point);
2. **translations** = row means of the filled matrix; centre it;
3. ``inner`` iterations of power factorisation on the filled, centred matrix:
   ``M = W S^T (S S^T)^-1`` (all N blocks at once), project every ``2x3`` block onto
   the nearest scaled Stiefel matrix ``c U V^T`` (``cameras.nearest_scaled_rotation``),
   re-solve ``S = (sum M^T M)^-1 sum M^T W`` by least squares (both solves with a
   small Tikhonov term);
4. **per-instance safeguard** against the filling locking an instance into a wrong
   local minimum (typically its depth-reversed pose, whose filled entries are then
   self-consistent): each instance keeps, of (a) the block from step 3, (b) that block
   reflected through the shape's flattest principal plane, (c) an affine resection on
   its *visible* entries only projected onto scaled rotations and (d) its previous
   block, the one with the smallest visible-entry residual;
5. **refill** from the model and measure the RMS residual of the visible entries.

Stopping rule: stop after outer iteration ``i`` when the visible-entry RMS residual
``r_i`` satisfies ``|r_{i-1} - r_i| <= tol * r_{i-1}`` or ``r_i <= 1e-5 * (RMS of the
centred visible coordinates)`` (an exact fit at float32 precision), else after
``max_outer`` outer iterations. The reference implementation ran 200 outer x 10
inner iterations. On the CPU the outer steps run in a compiled kernel
(``carvi_torch/kernels/sfm_steps.h``) where it applies, equal to the torch steps to rounding.

``rank=2`` is the planar model (:func:`planar_factorize`): ``2x2`` blocks left free, then
gauge-fixed and completed to scaled orthographic cameras of the plane ``z = 0``.

Everything runs in float64 (the matrices are small: ``2N x K``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from .. import native_library
from ..cameras import scaled_stiefel

__all__ = ["factorize", "planar_factorize", "resect", "visible_translation"]


def visible_translation(M: torch.Tensor, S: torch.Tensor, W: torch.Tensor, vis: torch.Tensor,
                        counts: torch.Tensor | None = None):
    """Least-squares translation and residual on visible entries.

    Args:
        M: ``(N, 2, 3)``; S: ``(3, K)``; W: ``(N, 2, K)``; vis: ``(N, K)`` float (0/1).
        counts: ``(N, 1)`` ``vis.sum(-1).clamp(min=1)[:, None]`` when already computed (loops).

    Returns:
        ``t (N, 2)`` and the per-instance sum of squared visible residuals ``(N,)``.
    """
    D = W - M @ S  # (N, 2, K)
    v = vis[:, None]
    cnt = vis.sum(-1).clamp(min=1.0)[:, None] if counts is None else counts
    t = (D * v).sum(-1) / cnt
    r = ((D - t[..., None]) * v).pow(2).sum((1, 2))
    return t, r


def resect(S: torch.Tensor, W: torch.Tensor, vis: torch.Tensor, M_prev: torch.Tensor, reg: float,
           checked: bool = False):
    """Affine resection on visible entries, Tikhonov-pulled towards ``M_prev``.

    ``[M t] = argmin sum_k vis_k ||w_k - M S_k - t||^2 + mu ||M - M_prev||^2`` for every
    instance (``(N, r+1, r+1)`` batched solves), ``mu`` relative to the instance's
    visible-shape spread, so instances with 2 or 3 visible keypoints stay defined.

    Args:
        S: ``(r, K)``; W: ``(N, 2, K)``; vis: ``(N, K)`` float; M_prev: ``(N, 2, r)``.

    Returns ``M (N, 2, r)`` (not projected); with ``checked``, ``(M, solved (N,) bool)`` instead of
    raising on a singular system (its rows are then not to be used).
    """
    n, _, k = W.shape
    r = S.shape[0]
    X = torch.cat([S, torch.ones(1, k, dtype=S.dtype, device=S.device)], 0)  # (r+1, K)
    A = torch.einsum("nk,ik,jk->nij", vis, X, X)  # (N, r+1, r+1)
    b = torch.einsum("nk,nrk,jk->nrj", vis, W, X)  # (N, 2, r+1)
    spread = A[:, :r, :r].diagonal(dim1=1, dim2=2).sum(-1) / r
    scale = (S * S).sum() / (r * k)
    mu = reg * (spread + scale)  # (N,)
    D = torch.ones(r + 1, dtype=S.dtype, device=S.device)
    D[r] = 0.0
    L = mu[:, None, None] * torch.diag(D)
    prev = torch.cat([M_prev, torch.zeros(n, 2, 1, dtype=S.dtype, device=S.device)], 2)  # (N, 2, r+1)
    if checked:
        P, info = torch.linalg.solve_ex(A + L, (b + prev @ L).transpose(1, 2))
        return P.transpose(1, 2)[:, :, :r], info == 0
    P = torch.linalg.solve(A + L, (b + prev @ L).transpose(1, 2)).transpose(1, 2)
    return P[:, :, :r]


def _initial_shape(Wf: torch.Tensor, rank: int, generator: torch.Generator) -> torch.Tensor:
    """Shape ``(rank, K)`` from the SVD of the centred filled matrix ``(N, 2, K)``.

    Missing singular directions (too few instances or keypoints) are filled with a
    small random shape from ``generator`` so the first solves are well posed.
    """
    n, _, k = Wf.shape
    Wc = (Wf - Wf.mean(-1, keepdim=True)).reshape(2 * n, k)
    U, sv, Vh = torch.linalg.svd(Wc, full_matrices=False)
    S = torch.zeros(rank, k, dtype=Wf.dtype, device=Wf.device)
    r = min(rank, Vh.shape[0])
    S[:r] = Vh[:r] * sv[:r, None].sqrt() / math.sqrt(max(n, 1))
    ref = float(sv[0].sqrt()) / math.sqrt(max(n, 1)) if sv.numel() else 1.0
    ref = ref if ref > 0 else 1.0
    for i in range(r, rank):
        S[i] = 1e-3 * ref * torch.randn(k, generator=generator, dtype=torch.float64).to(S)
    # ranks dropped by the SVD itself (exactly degenerate data)
    weak = S[:rank].norm(dim=1) < 1e-9 * ref
    if bool(weak.any()):
        noise = 1e-3 * ref * torch.randn(rank, k, generator=generator, dtype=torch.float64).to(S)
        S[:rank] = torch.where(weak[:, None], noise, S[:rank])
    return S - S.mean(1, keepdim=True)


def _complete_planar(A: torch.Tensor) -> torch.Tensor:
    """Scaled Stiefel ``2x3`` blocks whose first two columns are ``A (N, 2, 2)``.

    With ``A = U diag(s1, s2) V^T``, ``[A | b]`` with ``b = sqrt(s1^2 - s2^2) U[:, 1]``
    has ``[A | b][A | b]^T = s1^2 I``: a scaled orthographic camera (scale ``s1``)
    that images the plane ``z = 0`` exactly as ``A`` does, tilted out of the plane
    by ``acos(s2 / s1)``. The sign of ``b`` (the tilt's direction) is not observable
    from a planar shape; ``+`` is returned.
    """
    U, sv, _ = torch.linalg.svd(A)
    b = (sv[:, 0] ** 2 - sv[:, 1] ** 2).clamp(min=0).sqrt()[:, None] * U[:, :, 1]
    return torch.cat([A, b[..., None]], dim=-1)


def _planar_gauge(A: torch.Tensor) -> torch.Tensor:
    """Affine gauge ``H (2, 2)`` of a planar factorisation: ``A_n -> A_n H``, ``S -> H^-1 S``.

    Every 2x2 block is a scaled orthographic view of a plane, so a planar
    factorisation is defined up to an affine map of the plane. ``H = G^(-1/2)``
    with ``G = sum_n A_n^T A_n / ||A_n||_2^2`` makes the blocks' average metric
    isotropic (exact when the views are fronto-parallel; unbiased for tilts spread
    evenly around the plane), scaled to ``det H = 1``.
    """
    top = torch.linalg.matrix_norm(A, ord=2)
    An = A / top.clamp(min=1e-300)[:, None, None]
    G = torch.einsum("nri,nrj->ij", An, An)
    ev, V = torch.linalg.eigh(G)
    H = V @ torch.diag(ev.clamp(min=1e-12 * float(ev.max())).rsqrt()) @ V.T
    return H / torch.det(H).abs().sqrt()


def _power_steps(Wc, S, eye, project, inner: int, reg: float, rank: int):
    """Step 3 of the alternation: ``inner`` power-factorisation steps on the centred filled matrix
    ``Wc (N, 2, K)`` from ``S (rank, K)``; returns the new ``S`` and the last blocks ``M (N, 2, rank)``.

    On the CPU the Tikhonov weights are host floats: the same double arithmetic as on 0-dim tensors,
    fewer tensor ops per step; on a GPU they stay on the device (a host float would wait for it twice
    per step)."""
    trace = (lambda X: float(X.diagonal().sum())) if Wc.device.type == "cpu" else (lambda X: X.diagonal().sum())
    Mi = None
    for _ in range(inner):
        A = S @ S.T
        lam = reg * trace(A) / rank + 1e-300
        Mi = project(Wc @ S.T @ torch.linalg.inv(A + lam * eye))
        B = torch.einsum("nri,nrj->ij", Mi, Mi)
        lamS = reg * trace(B) / rank + 1e-300
        S = torch.linalg.solve(B + lamS * eye, torch.einsum("nri,nrk->ik", Mi, Wc))
    return S, Mi


def factorize(W, vis, *, rank, max_outer, inner, tol, reg, generator, S_init=None, native=True):
    """Marques-Costeira alternation on ``W (N, 2, K)`` float64 with ``vis (N, K)`` float 0/1.

    ``rank=3``: blocks projected onto scaled Stiefel matrices after every solve (the
    rigid model). ``rank=2``: the planar model, ``2x2`` blocks left free (every
    ``2x2`` map is a scaled orthographic view of a plane), completed to ``2x3``
    cameras and gauge-fixed afterwards (:func:`_planar_gauge`, :func:`_complete_planar`).

    ``native``: the outer loop's steps in the compiled kernel on the CPU where it applies (:func:`_fill_loop`),
    else in torch operators.

    Returns ``M (N, 2, rank)``, ``t (N, 2)``, ``S (rank, K)``, ``history``,
    ``iterations``, ``converged``.
    """
    n, _, k = W.shape
    dev, dt = W.device, W.dtype
    eye = torch.eye(rank, dtype=dt, device=dev)
    project = scaled_stiefel if rank == 3 else (lambda x: x)
    v2 = vis[:, None, :]
    cnt = vis.sum(-1).clamp(min=1.0)
    centroid = (W * v2).sum(-1) / cnt[:, None]
    Wf = torch.where(v2 > 0, W, centroid[..., None])
    scale = float(((W - centroid[..., None]).pow(2) * v2).sum() / (2 * vis.sum()).clamp(min=1)) ** 0.5
    scale = scale if scale > 0 else 1.0

    if S_init is None:
        S = _initial_shape(Wf, rank, generator)
    else:
        # a warm start: the missing entries are filled from the start's own cameras, not from the
        # centroids (the fill is what the alternation is slow to correct)
        S = S_init.clone()
        M0, solved = resect(S, W, vis, torch.zeros(n, 2, rank, dtype=dt, device=dev), reg, checked=True)
        M0 = project(torch.where(solved[:, None, None], M0, torch.zeros_like(M0)))
        t0, _ = visible_translation(M0, S, W, vis)
        fill = M0 @ S + t0[..., None]
        ok = solved[:, None, None] & torch.isfinite(fill)
        Wf = torch.where(v2 > 0, W, torch.where(ok, fill, Wf))  # an unsolved row keeps the centroid fill
    return _fill_loop(W, vis, Wf, S, eye, project, max_outer=max_outer, inner=inner, tol=tol, reg=reg, scale=scale,
                      native=native)


@dataclass
class _FillState:
    """The outer loop's state: the filled matrix, the shape, the last step's blocks and translations, the RMS
    of every step run."""

    Wf: torch.Tensor  # (N, 2, K)
    S: torch.Tensor  # (rank, K)
    M: torch.Tensor | None = None  # (N, 2, rank)
    t: torch.Tensor | None = None  # (N, 2)
    history: list = field(default_factory=list)


def _fill_loop(W, vis, Wf, S, eye, project, *, max_outer, inner, tol, reg, scale, native=False):
    """The outer loop of :func:`factorize` from the filled matrix ``Wf (N, 2, K)`` and the shape ``S``:
    power steps, the best candidate block per instance, the refill, until the RMS settles (:func:`_fill_step`).

    ``native``: the steps run in the compiled kernel (:func:`_native_steps`) where it applies; a step it
    declines runs here, and the kernel goes on after it."""
    st = _FillState(Wf, S)
    ops = _native_ops(W, vis, Wf, S) if native else None
    W, vis = W.contiguous(), vis.contiguous()
    # loop invariants of the torch steps, computed once: counts, known entries, entries, row indices
    fixed = (vis.sum(-1).clamp(min=1.0)[:, None], vis[:, None, :] > 0, (2 * vis.sum()).clamp(min=1),
             torch.arange(W.shape[0], device=W.device))
    converged = False
    while len(st.history) < max_outer and not converged:
        if ops is not None:
            converged = _native_steps(ops, W, vis, st, max_outer=max_outer, inner=inner, tol=tol, reg=reg,
                                      scale=scale)
            if converged or len(st.history) >= max_outer:
                break
        _fill_step(W, vis, st, eye, project, inner, reg, fixed)
        h = st.history
        converged = h[-1] <= 1e-5 * scale or (len(h) >= 2 and abs(h[-2] - h[-1]) <= tol * h[-2])
    tv, _ = visible_translation(st.M, st.S, W, vis)
    return st.M, tv, st.S, st.history, len(st.history), converged


def _fill_step(W, vis, st: _FillState, eye, project, inner: int, reg: float, fixed) -> None:
    """One outer step in torch operators, updating ``st``: power steps, every instance's best candidate block
    (the power step's, the projected resection, for the rigid model the power step's reflected through the
    shape's plane, the last step's), the refill. ``fixed``: the loop's invariants (:func:`_fill_loop`)."""
    rank = st.S.shape[0]
    counts, known, entries, idx = fixed
    Wc = st.Wf - st.Wf.mean(-1)[..., None]
    S, Mi = _power_steps(Wc, st.S, eye, project, inner, reg, rank)
    cands = [Mi, project(resect(S, W, vis, Mi, reg))]
    if rank == 3:
        Sc = S - S.mean(1, keepdim=True)
        nrm = torch.linalg.svd(Sc, full_matrices=True)[0][:, 2]
        cands.append(Mi @ (eye - 2.0 * torch.outer(nrm, nrm)))
    if st.M is not None:
        cands.append(st.M)
    res = [visible_translation(c, S, W, vis, counts) for c in cands]
    r = torch.stack([x[1] for x in res])  # (C, N)
    best = r.argmin(0)
    st.M = torch.stack(cands)[best, idx]
    st.t = torch.stack([x[0] for x in res])[best, idx]
    st.S = S
    st.Wf = torch.where(known, W, st.M @ S + st.t[..., None])
    st.history.append(float((r[best, idx].sum() / entries).sqrt()))


def _native_ops(W, vis, Wf, S):
    """The compiled library's operators where the kernel applies (float64 on the CPU, the library loaded)."""
    if not all(x.dtype == torch.float64 for x in (W, vis, Wf, S)):
        return None
    return native_library.operators_on(W.device)


def _native_steps(ops, W, vis, st: _FillState, *, max_outer, inner, tol, reg, scale) -> bool:
    """Steps of :func:`_fill_loop` in the compiled kernel (``carvi_torch/kernels/sfm_steps.h``) from ``st``, until
    the RMS settles (returns True), ``max_outer`` steps or a step the kernel declines (a block of rank < 2, which
    the torch path projects through an SVD; a singular solve; a non-finite value: ``st`` is then the state before
    it). Equal to :func:`_fill_step` to rounding (its sums run in another order): one step is a few thousand flops
    instead of about two hundred tensor operators' dispatch."""
    n, rank = W.shape[0], st.S.shape[0]
    M = st.M if st.M is not None else W.new_zeros(n, 2, rank)
    prev = st.history[-1] if st.history else float("nan")
    M, t, S, Wf, hist, steps, status = ops.sfm_factorize(
        W, vis, st.Wf.contiguous(), st.S.contiguous(), M.contiguous(), st.M is not None, len(st.history) + 1, prev,
        max_outer, inner, tol, reg, scale)
    if steps > 0:
        st.M, st.t, st.S, st.Wf = M, t, S, Wf
        st.history += hist[:steps].tolist()
    return status == 1


def planar_factorize(W, vis, **kw):
    """Planar factorisation completed to cameras: ``M (N, 2, 3)``, ``t``, ``S (3, K)`` (z = 0), ..."""
    A, tv, S2, history, it, conv = factorize(W, vis, rank=2, **kw)
    H = _planar_gauge(A)
    A = A @ H
    S2 = torch.linalg.solve(H, S2)
    S2 = S2 - S2.mean(1, keepdim=True)
    M = _complete_planar(A)
    S = torch.cat([S2, torch.zeros_like(S2[:1])], 0)
    tv, _ = visible_translation(M, S, W, vis)
    return M, tv, S, history, it, conv
