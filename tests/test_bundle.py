"""Tests for carvi_torch.viewpoints.bundle: the joint Levenberg-Marquardt bundle adjustment."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares

from carvi_torch import native_library
from carvi_torch.cameras import ScaledOrthographic, axis_angle_to_rotation, random_rotations
from carvi_torch.config import Config, ConfigError
from carvi_torch.viewpoints import bundle, class_sfm, sfm
from carvi_torch.viewpoints.bundle import jacobians, joint_bundle_adjust, residuals

F64 = torch.float64


def problem(seed, n=12, k=8, missing=0.0, noise=0.0):
    """Cameras, shape and keypoints of a random rigid scene; ``missing``: fraction of hidden entries (every
    instance keeps at least 3, every keypoint at least 2 views)."""
    g = torch.Generator().manual_seed(seed)
    X = 20.0 * torch.randn(k, 3, generator=g, dtype=F64)
    cams = ScaledOrthographic(random_rotations(n, g, F64), 1.0 + 0.5 * torch.rand(n, generator=g, dtype=F64),
                              64.0 + 5.0 * torch.randn(n, 2, generator=g, dtype=F64))
    w = cams.project(X) + noise * torch.randn(n, k, 2, generator=g, dtype=F64)
    vis = torch.rand(n, k, generator=g) >= missing
    vis[:, :3] = True
    vis[:2] = True
    return cams, X, w, vis, g


def perturbed(cams, X, g, deg=5.0, shape_noise=1.0):
    """A start near ``cams``, ``X``: rotations turned by about ``deg`` degrees, scales, translations and shape moved."""
    n = len(cams)
    turn = axis_angle_to_rotation(np.deg2rad(deg) * torch.randn(n, 3, generator=g, dtype=F64) / 3 ** 0.5)
    start = ScaledOrthographic(turn @ cams.R, cams.s * (1 + 0.05 * torch.randn(n, generator=g, dtype=F64)),
                               cams.t + torch.randn(n, 2, generator=g, dtype=F64))
    return start, X + shape_noise * torch.randn(X.shape, generator=g, dtype=F64)


def rms(cams, X, w, vis):
    e = ((cams.project(X) - w) ** 2).sum(-1)[vis]
    return float((e.sum() / (2 * vis.sum())).sqrt())


# --------------------------------------------------------------------------- independent references


def test_final_cost_matches_scipy_least_squares():
    """On a small noisy problem with missing entries, scipy's LM on the same parameters (absolute axis-angle
    of the rotation relative to the start, log-scale, translation, shape) ends at the same cost (relative
    1e-8); both start from the same perturbed solution."""
    cams, X, w, vis, g = problem(1, n=6, k=7, missing=0.3, noise=0.5)
    start, X0 = perturbed(cams, X, g)
    n, k = vis.shape
    v = vis.double()

    def fun(p):
        p = torch.from_numpy(p)
        Rn = axis_angle_to_rotation(p[:3 * n].reshape(n, 3)) @ start.R
        s = start.s.log().add(p[3 * n:4 * n]).exp()
        t = p[4 * n:6 * n].reshape(n, 2)
        r, _ = residuals(Rn, s, t, p[6 * n:].reshape(k, 3), w, v)
        return r[vis].reshape(-1).numpy()

    p0 = np.concatenate([np.zeros(4 * n), start.t.reshape(-1).numpy(), X0.reshape(-1).numpy()])
    ref = least_squares(fun, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=20000)
    assert ref.success
    ours = joint_bundle_adjust(start, X0, w, vis, iters=200, tol=1e-12)
    cost = rms(ours.cameras, ours.shape, w, vis) ** 2 * 2 * int(vis.sum())
    assert ours.converged
    assert cost == pytest.approx(float(ref.fun @ ref.fun), rel=1e-8)
    assert cost < 0.9 * rms(start, X0, w, vis) ** 2 * 2 * int(vis.sum())  # it moved: the test can tell


def test_analytic_jacobian_matches_autograd():
    """``jacobians`` equals ``torch.autograd.functional.jacobian`` of the masked residuals with respect to the
    increments ``(omega, rho, tau)`` per camera and ``xi`` per shape point, at zero (float64)."""
    cams, X, w, vis, _ = problem(2, n=4, k=5, missing=0.3)
    v = vis.double()
    n, k = vis.shape

    def f(dc, dx):
        R = axis_angle_to_rotation(dc[:, :3]) @ cams.R
        return residuals(R, cams.s * dc[:, 3].exp(), cams.t + dc[:, 4:], X + dx, w, v)[0]

    Jc, Jx = torch.autograd.functional.jacobian(f, (torch.zeros(n, 6, dtype=F64), torch.zeros(k, 3, dtype=F64)))
    _, Y = residuals(cams.R, cams.s, cams.t, X, w, v)
    A, B = jacobians(cams.R, cams.s, Y, v)
    idx = torch.arange(n)
    kdx = torch.arange(k)
    # Jc (N, K, 2, N, 6): only the residual's own camera; Jx (N, K, 2, K, 3): only its own point
    torch.testing.assert_close(Jc[idx, :, :, idx], A, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(Jx[:, kdx, :, kdx].permute(1, 0, 2, 3), B, rtol=1e-10, atol=1e-10)
    assert float(Jc.abs().sum()) == pytest.approx(float(A.abs().sum()))  # nothing off the blocks
    assert float(Jx.abs().sum()) == pytest.approx(float(B.abs().sum()))
    assert bool((A[~vis] == 0).all()) and float(A[vis].abs().sum()) > 0


# --------------------------------------------------------------------------- recovery


def _relative_rotations(R):
    return R[:, None] @ R[None].transpose(-1, -2)


@pytest.mark.parametrize("missing", [0.0, 0.4])
def test_noise_free_recovery_up_to_the_gauge(missing):
    """Noise-free keypoints (all, or 40% missing): the residual falls to the float floor and the cameras
    are the true ones up to one global similarity: equal relative rotations ``R_n R_m^T``, scale ratios."""
    cams, X, w, vis, g = problem(3, n=15, k=10, missing=missing)
    start, X0 = perturbed(cams, X, g, deg=10.0, shape_noise=2.0)
    assert rms(start, X0, w, vis) > 1.0
    res = joint_bundle_adjust(start, X0, w, vis, iters=100, tol=0.0, floor=1e-9)
    assert res.converged and res.history[-1] <= 1e-9
    torch.testing.assert_close(_relative_rotations(res.cameras.R), _relative_rotations(cams.R), atol=1e-8, rtol=0)
    ratio = res.cameras.s / cams.s
    assert float((ratio.max() - ratio.min()) / ratio.mean()) < 1e-8
    assert res.iterations < 30  # Gauss-Newton from near the solution: a handful of steps


def test_an_unseen_keypoint_stays_where_it_is():
    """A keypoint no instance sees has no residual: it keeps its start, finite (the damping's floor)."""
    cams, X, w, vis, g = problem(4, n=10, k=6)
    vis[:, 5] = False
    start, X0 = perturbed(cams, X, g)
    res = joint_bundle_adjust(start, X0, w, vis, iters=50, tol=1e-12)
    torch.testing.assert_close(res.shape[5], X0[5], rtol=0, atol=1e-9)
    assert res.history[-1] < 1e-6


# --------------------------------------------------------------------------- the iteration


def test_cost_never_rises_and_rejected_steps_keep_the_solution():
    """From a far start with almost no damping, Gauss-Newton steps overshoot: some are rejected (more solves
    than accepted steps), and the RMS residual never rises from the start through every accepted step."""
    cams, X, w, vis, g = problem(5, n=10, k=8, missing=0.3, noise=1.0)
    start, X0 = perturbed(cams, X, g, deg=60.0, shape_noise=10.0)
    res = joint_bundle_adjust(start, X0, w, vis, iters=60, tol=1e-12, damping=1e-12)
    seq = [rms(start, X0, w, vis)] + res.history
    assert res.iterations > len(res.history)  # some steps were rejected
    assert all(b <= a for a, b in zip(seq, seq[1:]))
    assert rms(res.cameras, res.shape, w, vis) == pytest.approx(res.history[-1], rel=1e-12)


def test_stopping_rule_and_cap():
    """``tol`` stops after the first accepted step whose relative gain is below it; ``iters`` caps the
    solves and then ``converged`` is False; ``iters=0`` returns the start."""
    cams, X, w, vis, g = problem(6, missing=0.2, noise=1.0)
    start, X0 = perturbed(cams, X, g, deg=20.0)
    loose = joint_bundle_adjust(start, X0, w, vis, iters=100, tol=0.5)
    tight = joint_bundle_adjust(start, X0, w, vis, iters=100, tol=1e-10)
    capped = joint_bundle_adjust(start, X0, w, vis, iters=2, tol=1e-10)
    assert loose.converged and tight.converged and not capped.converged
    assert len(loose.history) < len(tight.history) and capped.iterations == 2
    none = joint_bundle_adjust(start, X0, w, vis, iters=0)
    assert none.converged and none.iterations == 0 and torch.equal(none.shape, X0)


def test_deterministic():
    cams, X, w, vis, g = problem(7, missing=0.3, noise=1.0)
    start, X0 = perturbed(cams, X, g)
    a = joint_bundle_adjust(start, X0, w, vis, iters=40)
    b = joint_bundle_adjust(start, X0, w, vis, iters=40)
    assert torch.equal(a.cameras.R, b.cameras.R) and torch.equal(a.shape, b.shape) and a.history == b.history


@pytest.mark.parametrize("change, match", [
    (lambda a: a.update(shape=a["shape"][:, :2]), "shape must be"),
    (lambda a: a.update(shape=a["shape"][:0]), "shape must be"),
    (lambda a: a.update(keypoints=a["keypoints"][:, :-1]), "keypoints must be"),
    (lambda a: a.update(visible=a["visible"].double()), "visible must be"),
    (lambda a: a.update(visible=a["visible"][:-1]), "visible must be"),
    (lambda a: a.update(cameras=ScaledOrthographic(a["cameras"].R, 0 * a["cameras"].s, a["cameras"].t)),
     "scales must be"),
    (lambda a: a["shape"].__setitem__((1, 2), float("nan")), "must be finite"),
    (lambda a: a.update(shape=a["shape"][0, 0]), "shape must be"),
    (lambda a: a.update(damping=0.0), "damping must be"),
    (lambda a: a.update(damping=-1e-3), "damping must be"),
    (lambda a: a.update(damping=float("nan")), "damping must be"),
    (lambda a: a.update(iters=-1), "iters must be"),
])
def test_bad_inputs_raise(change, match):
    cams, X, w, vis, _ = problem(8, n=5, k=4)
    args = {"cameras": cams, "shape": X.clone(), "keypoints": w, "visible": vis}
    change(args)
    with pytest.raises(ValueError, match=match):
        joint_bundle_adjust(**args)


# --------------------------------------------------------------------------- as the SfM's polish


def _blocks(cams, X, w, vis):
    return cams.M.clone(), cams.t.clone(), X.T.contiguous(), w.transpose(1, 2).contiguous(), vis.double()


def test_polish_joint_reaches_the_alternations_end_in_fewer_rounds():
    """``bundle_polish(method="joint")`` ends at the residual the alternation reaches with no round cap (within
    1e-6 relative), in fewer rounds, from a noisy start."""
    cams, X, w, vis, g = problem(9, n=40, k=12, missing=0.4, noise=1.0)
    start, X0 = perturbed(cams, X, g, deg=15.0, shape_noise=3.0)
    M, t, S, W, v = _blocks(start, X0, w, vis)
    alt = sfm.bundle_polish(M, t, S, W, v, iters=2000, tol=1e-12, method="alternate")
    joint = sfm.bundle_polish(M, t, S, W, v, iters=2000, tol=1e-12, method="joint")
    assert alt[4] and joint[4]
    assert joint[3][-1] == pytest.approx(alt[3][-1], rel=1e-6)
    assert len(joint[3]) < len(alt[3])


def test_polish_joint_leaves_a_degenerate_block_out():
    """A zero camera block sits out of the joint polish (as of the alternation): it keeps its block, the others
    fit the data and nothing turns NaN."""
    cams, X, w, vis, g = problem(10, n=10, k=8, noise=0.5)
    start, X0 = perturbed(cams, X, g)
    M, t, S, W, v = _blocks(start, X0, w, vis)
    M[3] = 0.0
    M2, t2, S2, hist, conv = sfm.bundle_polish(M, t, S, W, v, iters=100, tol=1e-10, method="joint")
    assert torch.equal(M2[3], M[3]) and torch.equal(t2[3], t[3])
    assert bool(torch.isfinite(M2).all() & torch.isfinite(S2).all()) and conv
    keep = torch.arange(10) != 3
    assert rms(ScaledOrthographic.from_affine(M2[keep], t2[keep]), S2.T, w[keep], vis[keep]) < 0.6
    with pytest.raises(ValueError, match="method must be"):
        sfm.bundle_polish(M, t, S, W, v, iters=1, tol=0.0, method="both")


def test_rigid_sfm_polishes_jointly_when_asked(monkeypatch):
    """``SfMOptions(polish="joint")`` runs the joint solver (and only then); an unknown method is refused."""
    cams, X, w, vis, _ = problem(11, n=30, k=10, missing=0.3, noise=0.5)
    calls = []
    plain = sfm.joint_bundle_adjust
    monkeypatch.setattr(sfm, "joint_bundle_adjust", lambda *a, **k: calls.append(1) or plain(*a, **k))
    opts = sfm.SfMOptions(max_outer=20, polish_iters=50, planar=False, mirrors=False)
    a = sfm.rigid_sfm(w, vis, opts)
    assert not calls
    b = sfm.rigid_sfm(w, vis, sfm.SfMOptions(**{**opts.__dict__, "polish": "joint"}))
    assert calls and b.converged
    assert float(b.residual.median()) == pytest.approx(float(a.residual.median()), rel=0.05)
    with pytest.raises(ValueError, match="polish must be"):
        sfm.rigid_sfm(w, vis, sfm.SfMOptions(polish="both"))


def test_config_passes_sfm_polish_to_the_class_sfm(monkeypatch):
    """``viewpoints.sfm_polish`` reaches ``SfMOptions.polish`` through ``class_sfm``; bad values are refused."""
    seen = []
    monkeypatch.setattr(sfm, "rigid_sfm", lambda kp, vis, opts, **k: seen.append(opts.polish))
    meta = SimpleNamespace(rigid_keypoints=None, keypoint_names=None, flip_pairs=None, left_convention="object")
    both = SimpleNamespace(meta=meta, keypoints=None, visible=None)
    for method in ("joint", "alternate"):
        class_sfm(both, Config().override({"sfm_polish": method}).viewpoints)
    assert seen == ["joint", "alternate"]
    assert Config().viewpoints.sfm_polish == "joint"
    with pytest.raises(ConfigError, match="sfm_polish"):
        Config().override({"sfm_polish": "both"})



def test_a_step_without_predicted_gain_is_taken(monkeypatch):
    """A step that lowers the cost while the linear model predicts no gain (rounding near a minimum) is
    accepted, the damping update bounded (a gain ratio of ``1 / 1e-300`` would overflow the cube)."""
    cams, X, w, vis, g = problem(12, n=8, k=6, noise=0.5)
    start, X0 = perturbed(cams, X, g)
    real_ne, real_solve, grads = bundle._normal_equations, bundle._solve, {}

    def no_gradient(A, B, r):
        U, W, V, gc, gx = real_ne(A, B, r)
        grads["g"] = (gc, gx)
        return U, W, V, torch.zeros_like(gc), torch.zeros_like(gx)  # what the gain prediction sees

    def undamped(U, W, V, gc, gx, lam):
        dc, dx, Dc, Dx = real_solve(U, W, V, *grads["g"], lam)
        return dc, dx, 0 * Dc, 0 * Dx

    monkeypatch.setattr(bundle, "_normal_equations", no_gradient)
    monkeypatch.setattr(bundle, "_solve", undamped)
    res = joint_bundle_adjust(start, X0, w, vis, iters=5, tol=0.0)
    assert len(res.history) >= 2 and res.history[-1] < rms(start, X0, w, vis)


@pytest.mark.shared
def test_real_aeroplanes_keep_every_camera(shared_data, tmp_path):
    """The 327 real PASCAL VOC aeroplanes (and mirrors) polished jointly: no camera degenerates and the polish
    settles below the alternation's residual. Without the step bound (``MAX_STEP``) one joint step turned an
    aeroplane that shows only its nose and rudder points by thousands of radians (the others' gain lowered the
    total) and its scale then collapsed to 0: two objects lost their SfM camera."""
    from carvi_torch.io.coco import load_coco
    from carvi_torch.io.voc import convert

    ann = tmp_path / "aeroplane.json"
    convert(shared_data / "pascal_voc_aeroplane" / "keypoints", ann)
    both = load_coco(ann, classes=["aeroplane"]).collections["aeroplane"].with_mirrors()
    cfg = Config().override({"sfm_polish": "joint", "progress": False}).viewpoints
    res = class_sfm(both, cfg, polish_iters=100)
    assert not [p for p in res.problems if "degenerate" in p]
    assert res.converged and int(res.valid.sum()) == len(both)
    assert res.history[-1] < 5.9  # the alternation's 30 rounds end at 5.9 px RMS (docs/viewpoints.md)


def test_no_step_turns_a_camera_by_more_than_max_step():
    """The trust bound is on a camera's rotation angle ``|omega|``: a camera started 0.7 rad away about the
    diagonal axis (0.40 rad per component, each below ``MAX_STEP``) is reached in accepted steps of at most
    ``MAX_STEP`` each (the runs with 1, 2, ... solves are the prefixes of one run). A bound on each component
    alone accepted a first step of about 0.6 rad."""
    g = torch.Generator().manual_seed(0)
    n, k = 8, 10
    X = 20.0 * torch.randn(k, 3, generator=g, dtype=F64)
    cams = ScaledOrthographic(random_rotations(n, g, F64), torch.ones(n, dtype=F64), torch.zeros(n, 2, dtype=F64))
    turn = torch.eye(3, dtype=F64).repeat(n, 1, 1)
    turn[0] = axis_angle_to_rotation(torch.full((1, 3), 0.7 / 3 ** 0.5, dtype=F64))[0]
    start = ScaledOrthographic(turn @ cams.R, cams.s, cams.t)
    w, vis = cams.project(X), torch.ones(n, k, dtype=torch.bool)
    prev, turns = start.R, []
    for iters in range(1, 16):
        res = joint_bundle_adjust(start, X, w, vis, iters=iters, tol=1e-12)
        cos = (((res.cameras.R @ prev.transpose(-1, -2)).diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
        turns.append(float(torch.arccos(cos).max()))
        prev = res.cameras.R
    assert res.history[-1] < 1e-8 and sum(t > 0.05 for t in turns) >= 2
    assert max(turns) <= bundle.MAX_STEP + 1e-9


def test_results_come_back_in_the_callers_dtype():
    """float32 cameras, shape and keypoints: the solve runs in float64 (the same solution as from float64 inputs
    rounded to float32) and the cameras and shape come back in float32."""
    cams, X, w, vis, g = problem(13, n=8, k=6, noise=0.5)
    start, X0 = perturbed(cams, X, g)
    f32 = ScaledOrthographic(start.R.float(), start.s.float(), start.t.float())
    res = joint_bundle_adjust(f32, X0.float(), w.float(), vis, iters=50)
    ref = joint_bundle_adjust(ScaledOrthographic(f32.R.double(), f32.s.double(), f32.t.double()), X0.float().double(),
                              w.float().double(), vis, iters=50)
    assert {res.shape.dtype, res.cameras.R.dtype, res.cameras.s.dtype, res.cameras.t.dtype} == {torch.float32}
    torch.testing.assert_close(res.shape, ref.shape.float())
    assert res.history == ref.history


def test_one_read_back_to_the_host_per_solve():
    """Each damped solve reads one tensor back to the host (the step's length, cost and predicted gain
    together): on a GPU every read waits for the device. Counted as calls of ``item``, ``tolist``, ``float``,
    ``bool`` and ``int`` on tensors, 20 solves against 10."""
    from torch.overrides import TorchFunctionMode

    reads_of = {torch.Tensor.item, torch.Tensor.tolist, torch.Tensor.__bool__, torch.Tensor.__float__,
                torch.Tensor.__int__, torch.Tensor.__index__}

    class Reads(TorchFunctionMode):
        count = 0

        def __torch_function__(self, func, types, args=(), kwargs=None):
            self.count += func in reads_of
            return func(*args, **(kwargs or {}))

    cams, X, w, vis, g = problem(14, n=8, k=10, noise=0.3)
    start, X0 = perturbed(cams, X, g, deg=20.0)
    counts = []
    for iters in (10, 20):
        with Reads() as reads:
            res = joint_bundle_adjust(start, X0, w, vis, iters=iters, tol=0.0)
        assert res.iterations == iters
        counts.append(reads.count)
    assert counts[1] - counts[0] == 10


def test_a_failed_factorisation_is_a_rejected_step(monkeypatch):
    """A damped system that is not positive definite gives a NaN step (``_solve``); the iteration rejects it
    like a step that raises the cost (the damping grows) and goes on from the same solution."""
    U = -torch.eye(6, dtype=F64)[None].repeat(2, 1, 1)
    dc, dx, _, _ = bundle._solve(U, torch.zeros(2, 6, 3, dtype=F64), torch.eye(3, dtype=F64)[None],
                                 torch.ones(2, 6, dtype=F64), torch.ones(1, 3, dtype=F64), 1e-3)
    assert bool(dc.isnan().all() & dx.isnan().all())
    cams, X, w, vis, g = problem(15, n=8, k=6, noise=0.5)
    start, X0 = perturbed(cams, X, g)
    real, calls = bundle._solve, []

    def first_fails(U, W, V, gc, gx, lam):
        calls.append(lam)
        step = real(U, W, V, gc, gx, lam)
        return (step[0] * float("nan"), step[1] * float("nan"), *step[2:]) if len(calls) == 1 else step

    monkeypatch.setattr(bundle, "_solve", first_fails)
    res = joint_bundle_adjust(start, X0, w, vis, iters=30)
    assert calls[1] == 2 * calls[0] and res.converged
    assert res.iterations == len(res.history) + 1 and res.history[-1] < rms(start, X0, w, vis)


def test_schur_step_equals_the_dense_damped_solve():
    """``_solve``'s step (cameras eliminated, shape solved, cameras back-substituted) equals the dense solve of
    ``(J^T J + D) d = -J^T r`` with ``J`` assembled from the blocks, a camera that sees nothing included: a sign or
    transpose in the elimination changes the step, which the final-cost comparison with scipy would not see."""
    cams, X, w, vis, _ = problem(16, n=5, k=6, missing=0.3, noise=0.5)
    vis[4] = False
    n, k = vis.shape
    v = vis.double()
    r, Y = residuals(cams.R, cams.s, cams.t, X, w, v)
    A, B = jacobians(cams.R, cams.s, Y, v)
    dc, dx, Dc, Dx = bundle._solve(*bundle._normal_equations(A, B, r), 0.1)
    J = torch.zeros(n, k, 2, 6 * n + 3 * k, dtype=F64)
    for i in range(n):
        J[i, :, :, 6 * i:6 * i + 6] = A[i]
    for j in range(k):
        J[:, j, :, 6 * n + 3 * j:6 * n + 3 * j + 3] = B[:, j]
    J = J.reshape(-1, 6 * n + 3 * k)
    d = torch.linalg.solve(J.T @ J + torch.diag(torch.cat([Dc.reshape(-1), Dx])), -J.T @ r.reshape(-1))
    torch.testing.assert_close(torch.cat([dc.reshape(-1), dx]), d, rtol=1e-9, atol=1e-12)
    assert float(d.abs().max()) > 1e-3 and bool((dc[4] == 0).all())


# --------------------------------------------------------------------------- the compiled kernel

needs_library = pytest.mark.skipif(native_library.library_operators() is None,
                                   reason=f"no compiled kernel here: {native_library.load()['reason']}")


def _both_paths(start, X0, w, vis, **kw):
    return [joint_bundle_adjust(start, X0, w, vis, native=use, **kw) for use in (False, True)]


@needs_library
@pytest.mark.parametrize("seed, n, k, missing, deg, damping", [
    (20, 12, 8, 0.0, 5.0, 1e-3),
    (21, 40, 12, 0.4, 15.0, 1e-3),
    (22, 96, 10, 0.3, 10.0, 1e-3),
    (23, 10, 8, 0.3, 60.0, 1e-12),  # a far start with almost no damping: rejected steps and the step bound
])
def test_native_matches_the_torch_operators(seed, n, k, missing, deg, damping):
    """The compiled loop (``bundle_steps.h``) against the torch operators from the same noisy start: the same
    damped solves and accepted steps, every RMS of the history within 1e-10 relative, cameras (rotations,
    scales, translations in pixels) and shape within 1e-8: the same float64 steps summed in another order."""
    cams, X, w, vis, g = problem(seed, n=n, k=k, missing=missing, noise=1.0)
    w = torch.where(vis[..., None], w, float("nan"))  # hidden entries are read as unseen whatever they hold
    start, X0 = perturbed(cams, X, g, deg=deg, shape_noise=3.0)
    ref, nat = _both_paths(start, X0, w, vis, iters=60, tol=1e-9, damping=damping)
    assert nat.iterations == ref.iterations and nat.converged == ref.converged
    assert len(nat.history) == len(ref.history) >= 2
    torch.testing.assert_close(torch.tensor(nat.history), torch.tensor(ref.history), rtol=1e-10, atol=0)
    for a, b in [(nat.cameras.R, ref.cameras.R), (nat.cameras.s, ref.cameras.s), (nat.cameras.t, ref.cameras.t),
                 (nat.shape, ref.shape)]:
        torch.testing.assert_close(a, b, rtol=0, atol=1e-8)
    if damping < 1e-6:
        assert nat.iterations > len(nat.history)  # the case does reject steps


@needs_library
def test_native_keeps_float32_and_the_start_with_no_iterations():
    """A float32 problem comes back in float32 (solved in float64); ``iters=0`` returns the start."""
    cams, X, w, vis, g = problem(24, n=8, k=6, noise=0.5)
    start, X0 = perturbed(cams, X, g)
    s32 = ScaledOrthographic(start.R.float(), start.s.float(), start.t.float())
    ref, nat = _both_paths(s32, X0.float(), w.float(), vis, iters=30)
    assert nat.shape.dtype == torch.float32 and nat.cameras.R.dtype == torch.float32
    torch.testing.assert_close(nat.shape, ref.shape, rtol=0, atol=1e-4)
    none = joint_bundle_adjust(start, X0, w, vis, iters=0, native=True)
    assert none.iterations == 0 and none.converged and torch.equal(none.shape, X0) and none.history == []


@needs_library
@pytest.mark.parametrize("change, error", [
    (lambda a: a.__setitem__(0, a[0].float()), TypeError),
    (lambda a: a.__setitem__(1, a[1][:-1]), ValueError),
    (lambda a: a.__setitem__(3, a[3][:, :2].contiguous()), ValueError),
    (lambda a: a.__setitem__(4, a[4].transpose(0, 1)), ValueError),
    (lambda a: a.__setitem__(6, -1), ValueError),
    (lambda a: a.__setitem__(9, 0.0), ValueError),
])
def test_native_operator_checks_its_inputs(change, error):
    """The operator refuses wrong dtypes, shapes, layouts, a negative ``iters`` and a non-positive damping
    (it reads raw pointers: nothing may reach it that it could read outside of)."""
    cams, X, w, vis, _ = problem(25, n=5, k=4)
    args = [cams.R.contiguous(), cams.s.log(), cams.t.contiguous(), X.contiguous(), w.contiguous(), vis.double(),
            10, 1e-7, 0.0, 1e-3, bundle.MAX_STEP, bundle.MAX_DAMPING, bundle.DIAG_FLOOR]
    native_library.library_operators().joint_bundle(*args)  # the unchanged arguments run
    change(args)
    with pytest.raises(error):
        native_library.library_operators().joint_bundle(*args)


@needs_library
def test_rigid_sfm_native_polish_matches_the_torch_polish():
    """``rigid_sfm`` with the joint polish, the compiled factorisation on both sides, the polish compiled or in
    torch: the same cameras within 1e-7 and the same residuals within 1e-9 px."""
    cams, X, w, vis, _ = problem(26, n=30, k=10, missing=0.3, noise=0.5)
    opts = sfm.SfMOptions(max_outer=50, polish_iters=100, planar=False, mirrors=False, polish="joint")
    calls = []
    plain = sfm.joint_bundle_adjust

    def polish(*a, native_as=None, **kw):
        calls.append(kw["native"])
        return plain(*a, **{**kw, "native": native_as})

    out = []
    for native in (False, True):
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(sfm, "joint_bundle_adjust", lambda *a, **kw: polish(*a, native_as=native, **kw))
            out.append(sfm.rigid_sfm(w, vis, opts))
    assert calls and all(calls)  # the SfM asks for the compiled polish by default (SfMOptions.native)
    torch.testing.assert_close(out[1].cameras.R, out[0].cameras.R, rtol=0, atol=1e-7)
    torch.testing.assert_close(out[1].residual, out[0].residual, rtol=0, atol=1e-9)


@pytest.mark.shared
@needs_library
def test_real_aeroplanes_native_polish_matches_torch(shared_data, tmp_path):
    """The real VOC aeroplanes and mirrors (654 rows, missing keypoints): the joint adjustment from the
    factorisation's cameras, compiled against torch operators: the same steps, RMS within 1e-9 relative,
    rotations within 1e-6."""
    from carvi_torch.io.coco import load_coco
    from carvi_torch.io.voc import convert

    ann = tmp_path / "aeroplane.json"
    convert(shared_data / "pascal_voc_aeroplane" / "keypoints", ann)
    both = load_coco(ann, classes=["aeroplane"]).collections["aeroplane"].with_mirrors()
    start = class_sfm(both, Config().override({"progress": False}).viewpoints, polish_iters=0)
    v = start.valid
    cams = ScaledOrthographic(start.cameras.R[v], start.cameras.s[v], start.cameras.t[v])
    shape = torch.nan_to_num(start.shape)
    ref, nat = _both_paths(cams, shape, both.keypoints[v], both.visible[v], iters=20, tol=1e-9)
    assert nat.iterations == ref.iterations and len(nat.history) == len(ref.history) >= 2
    torch.testing.assert_close(torch.tensor(nat.history), torch.tensor(ref.history), rtol=1e-9, atol=0)
    torch.testing.assert_close(nat.cameras.R, ref.cameras.R, rtol=0, atol=1e-6)
