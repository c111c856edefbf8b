"""The compiled factorisation (``sfm_native``) against the torch operators' (``carvi_torch.viewpoints.sfm``).

Tolerance: the two run the same float64 arithmetic in different summation orders, so they agree to rounding:
cameras, translations and shapes within 1e-9 (in pixels and shape units of order 1-100), the RMS history
within 1e-12 relative, the same number of outer steps on these problems.
"""
from __future__ import annotations

import pytest
import torch

from carvi_torch.cameras import random_rotations
from carvi_torch import native_library
from carvi_torch.viewpoints import factorization, sfm

needs_library = pytest.mark.skipif(native_library.library_operators() is None,
                                   reason=f"no compiled kernel here: {native_library.load()['reason']}")

KW = dict(max_outer=200, inner=10, tol=1e-7, reg=1e-6)


def _problem(n: int, k: int, seed: int, planar: bool = False, missing: float = 0.3, thin: float = 1.0):
    """``W (n, 2, k)`` float64 pixels of a random rigid (or planar; ``thin``: its third axis scaled so) shape
    under scaled orthographic cameras, with 0.5 px noise, and ``vis (n, k)`` 0/1 with ``missing`` of the
    entries hidden."""
    g = torch.Generator().manual_seed(seed)
    S = 20 * torch.randn(3, k, generator=g, dtype=torch.float64)
    S[2] *= 0.0 if planar else thin
    R = random_rotations(n, generator=g).double()
    s = 1 + torch.rand(n, generator=g, dtype=torch.float64)
    W = s[:, None, None] * R[:, :2] @ S + 100 * torch.rand(n, 2, 1, generator=g, dtype=torch.float64)
    W = W + 0.5 * torch.randn(W.shape, generator=g, dtype=torch.float64)
    vis = (torch.rand(n, k, generator=g) > missing).double()
    vis[:, :3] = 1.0  # every instance sees three keypoints
    return W, vis


def _both(W, vis, rank: int, S_init=None):
    out = []
    for use in (False, True):
        with torch.inference_mode():
            out.append(factorization.factorize(W, vis, rank=rank, generator=torch.Generator().manual_seed(3),
                                      S_init=S_init, native=use, **KW))
    return out


@needs_library
@pytest.mark.parametrize("rank,planar", [(3, False), (2, True)])
@pytest.mark.parametrize("warm", [False, True])
@pytest.mark.parametrize("seed", [0, 1])
def test_native_factorisation_equals_the_torch_one(rank, planar, warm, seed):
    W, vis = _problem(40, 12, seed, planar=planar)
    S_init = None
    if warm:
        S_init = torch.randn(rank, 12, generator=torch.Generator().manual_seed(seed + 7), dtype=torch.float64)
    (M0, t0, S0, h0, it0, c0), (M1, t1, S1, h1, it1, c1) = _both(W, vis, rank, S_init)
    assert M1.shape == M0.shape == (40, 2, rank) and S1.shape == S0.shape == (rank, 12)
    assert (it1, c1) == (it0, c0) and len(h1) == len(h0) == it0
    torch.testing.assert_close(M1, M0, rtol=0, atol=1e-9)
    torch.testing.assert_close(t1, t0, rtol=0, atol=1e-9)
    torch.testing.assert_close(S1, S0, rtol=0, atol=1e-9)
    torch.testing.assert_close(torch.tensor(h1), torch.tensor(h0), rtol=1e-12, atol=0)


@needs_library
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_native_factorisation_equals_the_torch_one_on_thin_shapes(seed):
    """A thin shape (its third axis a tenth of the others) nearly has a tilt ambiguity: the candidate block
    reflected through the shape's plane wins for some instances and steps. Unsettled after 200 steps, the
    two paths still agree to 1e-8 (thinner shapes, a thirtieth, can part ways: near a tie of the
    reflection, rounding picks the candidate)."""
    W, vis = _problem(40, 12, seed, thin=0.1)
    (M0, t0, S0, h0, it0, c0), (M1, t1, S1, h1, it1, c1) = _both(W, vis, 3)
    assert (it1, c1) == (it0, c0)
    torch.testing.assert_close(M1, M0, rtol=0, atol=1e-8)
    torch.testing.assert_close(S1, S0, rtol=0, atol=1e-8)


@needs_library
def test_native_factorisation_fits_an_exact_rigid_class():
    """No noise, nothing hidden: the factorisation reproduces the measurements (an analytic solution)."""
    g = torch.Generator().manual_seed(5)
    S = torch.randn(3, 10, generator=g, dtype=torch.float64)
    R = random_rotations(30, generator=g).double()
    W = R[:, :2] @ S + torch.randn(30, 2, 1, generator=g, dtype=torch.float64)
    vis = torch.ones(30, 10, dtype=torch.float64)
    with torch.inference_mode():
        M, t, Sh, hist, _, converged = factorization.factorize(W, vis, rank=3, native=True, **KW,
                                                               generator=torch.Generator().manual_seed(0))
    assert converged and hist[-1] < 1e-6
    torch.testing.assert_close(M @ Sh + t[..., None], W, rtol=0, atol=1e-5)
    # the exact-fit floor (RMS <= 1e-5 of the data's scale) stops both paths at the same step
    with torch.inference_mode():
        ref = factorization.factorize(W, vis, rank=3, generator=torch.Generator().manual_seed(0), native=False, **KW)
    assert (len(hist), converged) == (len(ref[3]), ref[5]) and len(hist) < 5


def _kernel_once(W, vis, S, **kw):
    """One call of the kernel from the centroid-filled matrix and ``S``: ``(steps, status)``."""
    ops = native_library.library_operators()
    n, rank = W.shape[0], S.shape[0]
    cnt = vis.sum(-1).clamp(min=1.0)
    Wf = torch.where(vis[:, None] > 0, W, ((W * vis[:, None]).sum(-1) / cnt[:, None])[..., None])
    out = ops.sfm_factorize(W, vis, Wf.contiguous(), S, torch.zeros(n, 2, rank, dtype=torch.float64), False, 1,
                            float("nan"), kw["max_outer"], kw["inner"], kw["tol"], kw["reg"], 1.0)
    return out[5], out[6]


@needs_library
@pytest.mark.parametrize("max_outer", [3, 200])
def test_native_keeps_the_first_candidate_on_ties(max_outer):
    """An instance with one visible keypoint fits it exactly with every candidate block (residual 0): both
    paths keep the first (the power step's block), not the previous step's."""
    W, vis = _problem(40, 12, 0)
    vis[5] = 0.0
    vis[5, 4] = 1.0
    kw = dict(KW, max_outer=max_outer)
    out = []
    with torch.inference_mode():
        for use in (False, True):
            out.append(factorization.factorize(W, vis, rank=2, generator=torch.Generator().manual_seed(3), native=use,
                                               **kw))
        S = torch.randn(2, 12, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        assert _kernel_once(W, vis, S, **kw)[0] > 0  # the kernel runs its steps
    assert out[0][4] == out[1][4]
    torch.testing.assert_close(out[1][0], out[0][0], rtol=0, atol=1e-11)


@needs_library
def test_native_declines_a_rank_deficient_block_and_the_torch_path_runs_that_step():
    """An instance whose visible keypoints lie on one image line starts with a rank-1 block, which the torch
    path's projection takes through an SVD: the kernel declines the first step (no step run), the torch path
    runs it, and the kernel goes on from there: the torch path's result to rounding, in as many steps."""
    W, vis = _problem(20, 8, 2)
    vis[4] = 0.0
    vis[4, :3] = 1.0
    W[4, 1] = 0.5 * W[4, 0] + 3.0
    with torch.inference_mode():
        S = torch.randn(3, 8, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        assert _kernel_once(W, vis, S, **KW) == (0, 2)
        a, b = _both(W, vis, 3)
    assert (a[4], a[5]) == (b[4], b[5])
    for x, y in zip(a[:3], b[:3]):
        torch.testing.assert_close(y, x, rtol=0, atol=1e-9)


def _centroid_filled(W, vis):
    cnt = vis.sum(-1).clamp(min=1.0)
    return torch.where(vis[:, None] > 0, W, ((W * vis[:, None]).sum(-1) / cnt[:, None])[..., None]).contiguous()


@needs_library
def test_a_declined_step_hands_back_the_state_before_it():
    """The kernel's power steps update the shape in place before a block is declined: the declined call hands
    back the shape, the blocks and the filled matrix it was given (the torch path runs that step from them),
    also when it resumes (``first_it`` > 1, the last step's blocks given)."""
    ops = native_library.library_operators()
    W, vis = _problem(20, 8, 2)
    vis[4] = 0.0
    vis[4, :3] = 1.0
    W[4, 1] = 0.5 * W[4, 0] + 3.0
    Wf = _centroid_filled(W, vis)
    S = torch.randn(3, 8, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    M = torch.randn(20, 2, 3, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    for have_prev, first_it in ((False, 1), (True, 5)):
        M_out, _t, S_out, Wf_out, hist, steps, status = ops.sfm_factorize(
            W, vis, Wf, S, M, have_prev, first_it, 1.0, 200, 10, 1e-7, 1e-6, 1.0)
        assert (steps, status) == (0, 2) and hist.shape == (200 - first_it + 1,)
        assert torch.equal(S_out, S) and torch.equal(M_out, M) and torch.equal(Wf_out, Wf)


@needs_library
def test_a_resumed_kernel_call_tests_convergence_against_the_last_rms_given():
    """Resuming at step 2 (after a step run elsewhere), the kernel compares step 2's RMS with ``prev_rms``: equal
    to it, the loop has settled at step 2; the first step's RMS, it goes on."""
    ops = native_library.library_operators()
    W, vis = _problem(30, 10, 0)
    Wf = _centroid_filled(W, vis)
    S = torch.randn(3, 10, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    M0 = torch.zeros(30, 2, 3, dtype=torch.float64)
    args = (10, 1e-7, 1e-6, 1.0)
    _, _, _, _, h, steps, status = ops.sfm_factorize(W, vis, Wf, S, M0, False, 1, float("nan"), 2, *args)
    assert (steps, status) == (2, 0) and abs(h[0] - h[1]) > 1e-7 * h[0]  # two steps, not settled
    M1, _t, S1, Wf1, _, steps, status = ops.sfm_factorize(W, vis, Wf, S, M0, False, 1, float("nan"), 1, *args)
    assert (steps, status) == (1, 0)
    for prev, settled in ((float(h[1]), True), (float(h[0]), False)):
        _, _, _, _, h2, steps, status = ops.sfm_factorize(W, vis, Wf1, S1, M1, True, 2, prev, 3, *args)
        assert h2[0] == h[1]  # the same step 2
        assert (steps, status) == ((1, 1) if settled else (2, 0))


@needs_library
def test_native_does_not_apply_to_float32_or_other_devices():
    W, vis = _problem(10, 6, 0)
    S = torch.randn(3, 6, dtype=torch.float64)
    assert factorization._native_ops(W, vis, W, S) is not None
    assert factorization._native_ops(W.float(), vis, W.float(), S) is None
    assert factorization._native_ops(W.to("meta"), vis.to("meta"), W.to("meta"), S.to("meta")) is None


@needs_library
def test_native_operator_checks_its_arguments():
    ops = native_library.library_operators()
    W, vis = _problem(10, 6, 0)
    S = torch.randn(3, 6, dtype=torch.float64)
    M = torch.zeros(10, 2, 3, dtype=torch.float64)
    state = (False, 1, float("nan"))
    args = (200, 10, 1e-7, 1e-6, 1.0)
    ops.sfm_factorize(W, vis, W, S, M, *state, *args)
    with pytest.raises(ValueError, match="vis must be"):
        ops.sfm_factorize(W, vis[:, :5].contiguous(), W, S, M, *state, *args)
    with pytest.raises(ValueError, match="S must be"):
        ops.sfm_factorize(W, vis, W, torch.randn(4, 6, dtype=torch.float64), M, *state, *args)
    with pytest.raises(ValueError, match="M must be"):
        ops.sfm_factorize(W, vis, W, S, M[:, :, :2].contiguous(), *state, *args)
    with pytest.raises(TypeError, match="must be Double"):
        ops.sfm_factorize(W.float(), vis, W, S, M, *state, *args)
    with pytest.raises(ValueError, match="contiguous"):
        ops.sfm_factorize(W.transpose(0, 2), vis, W, S, M, *state, *args)
    with pytest.raises(ValueError, match="max_outer, inner and first_it"):
        ops.sfm_factorize(W, vis, W, S, M, *state, 0, 10, 1e-7, 1e-6, 1.0)
    with pytest.raises(ValueError, match="max_outer, inner and first_it"):
        ops.sfm_factorize(W, vis, W, S, M, False, 0, float("nan"), *args)


@needs_library
def test_rigid_sfm_cameras_agree_with_and_without_the_kernel():
    """The whole SfM (mirrored copies, the polish, the planar test) on a class with hidden keypoints."""
    W, vis = _problem(30, 10, 4)
    kp, visible = W.transpose(1, 2).float(), vis > 0
    res = [sfm.rigid_sfm(kp, visible, sfm.SfMOptions(native=use, polish="joint", polish_iters=100)) for use in
           (False, True)]
    assert bool(res[0].valid.all()) and torch.equal(res[0].valid, res[1].valid)
    torch.testing.assert_close(res[1].cameras.R, res[0].cameras.R, rtol=0, atol=1e-5)
    torch.testing.assert_close(res[1].cameras.s, res[0].cameras.s, rtol=1e-5, atol=0)
    torch.testing.assert_close(res[1].shape, res[0].shape, rtol=0, atol=1e-4)


@needs_library
def test_the_setting_reaches_the_factorisation(monkeypatch):
    """``viewpoints.sfm_native=false`` never calls the kernel; the default does."""
    from types import SimpleNamespace

    from carvi_torch.config import Config
    from carvi_torch.viewpoints import class_sfm

    calls = []
    real = factorization._native_steps
    monkeypatch.setattr(factorization, "_native_steps", lambda ops, W, vis, st, **k: (
        lambda n0, out: calls.append(len(st.history) > n0) or out)(len(st.history), real(ops, W, vis, st, **k)))
    W, vis = _problem(20, 8, 6)
    meta = SimpleNamespace(rigid_keypoints=None, keypoint_names=None, flip_pairs=None, left_convention="object")
    coll = SimpleNamespace(keypoints=W.transpose(1, 2).float(), visible=vis > 0, meta=meta)
    class_sfm(coll, Config().override({"sfm_native": False}).viewpoints)
    assert calls == []
    class_sfm(coll, Config().viewpoints)
    assert calls and all(calls)  # called, and the kernel ran steps (float64 inputs on the CPU)


@needs_library
def test_an_instance_with_two_visible_keypoints_costs_a_cold_rigid_start_one_torch_step(monkeypatch):
    """Its centred, centroid-filled rows are proportional: the first power step's block has rank 1, so the kernel
    declines the first step of a cold rigid factorisation; the torch path runs that one and the kernel the rest
    (docs/viewpoints.md), to the torch path's result."""
    W, vis = _problem(40, 12, 0)
    vis[5] = 0.0
    vis[5, [4, 8]] = 1.0
    torch_steps = []
    real = factorization._fill_step
    monkeypatch.setattr(factorization, "_fill_step", lambda *a, **k: torch_steps.append(1) or real(*a, **k))
    a, b = _both(W, vis, 3)
    assert len(torch_steps) == a[4] + 1  # every step of the torch run, then the kernel's one declined step
    assert (a[4], a[5]) == (b[4], b[5])
    for x, y in zip(a[:3], b[:3]):  # the two-keypoint instance's block is underdetermined: 1e-7 relative
        torch.testing.assert_close(y, x, rtol=1e-7, atol=1e-9)


# --------------------------------------------------------------------------- the keypoint-only camera fit


def _camera_problem(n: int, b: int, k: int, seed: int, dtype):
    """A shape with one unknown (NaN) keypoint, ``n`` instances seen by random cameras (0.5 px noise, 30% hidden)
    and ``b`` starts each, every start within about 20 degrees of its instance's camera."""
    from carvi_torch.cameras import axis_angle_to_rotation

    g = torch.Generator().manual_seed(seed)
    S = 10 * torch.randn(k, 3, generator=g, dtype=dtype)
    S[3] = float("nan")
    R = random_rotations(n, generator=g).to(dtype)
    kp = (20 * R[:, :2] @ torch.nan_to_num(S).T).transpose(1, 2) + 64
    kp = kp + 0.5 * torch.randn(kp.shape, generator=g, dtype=dtype)
    visible = torch.rand(n, k, generator=g) > 0.3
    visible[:, :4] = True
    turn = axis_angle_to_rotation(0.2 * torch.randn(n, b, 3, generator=g, dtype=dtype))
    R0 = turn @ R[:, None]
    s0 = 20 * (1 + 0.1 * torch.randn(n, b, generator=g, dtype=dtype))
    t0 = 64 + 2 * torch.randn(n, b, 2, generator=g, dtype=dtype)
    return S, kp, visible, R0, s0, t0


@needs_library
@pytest.mark.parametrize("dtype,atol", [(torch.float64, 1e-7), (torch.float32, 2e-3)])
def test_native_camera_fit_equals_the_torch_one(dtype, atol):
    """Levenberg-Marquardt from starts near the truth: the same cameras, energies and stopping (rotations within
    ``atol``; float32's tolerance covers its rounding over some forty steps, and its last camera may stop one
    step apart)."""
    from carvi_torch.viewpoints import camera_fit as cf

    S, kp, visible, R0, s0, t0 = _camera_problem(40, 3, 12, 0, dtype)
    lam = torch.zeros(40, dtype=dtype)
    a = cf._optimize(R0, s0, t0, S, kp, visible, None, lam, 100, 1e-6)
    b = cf._optimize(R0, s0, t0, S, kp, visible, None, lam, 100, 1e-6, native=True)
    assert abs(b.iterations - a.iterations) <= (1 if dtype == torch.float32 else 0)
    assert torch.equal(b.converged, a.converged) and bool(a.converged.all())
    torch.testing.assert_close(b.R, a.R, rtol=0, atol=atol)
    torch.testing.assert_close(b.s, a.s, rtol=1e-5 if dtype == torch.float32 else 1e-10, atol=0)
    torch.testing.assert_close(b.E, a.E, rtol=1e-4 if dtype == torch.float32 else 1e-9, atol=1e-6)
    torch.testing.assert_close(b.E_before, a.E_before, rtol=1e-6 if dtype == torch.float32 else 1e-12, atol=0)
    assert torch.equal(b.E_sil, torch.zeros_like(b.E_sil)) and torch.equal(b.E_kp, b.E)


@needs_library
def test_native_camera_fit_recovers_exact_cameras():
    """No noise, every keypoint seen: the fit lands on the true cameras (an analytic solution)."""
    from carvi_torch.viewpoints import camera_fit as cf

    g = torch.Generator().manual_seed(3)
    S = torch.randn(8, 3, generator=g, dtype=torch.float64)
    R = random_rotations(6, generator=g).double()
    kp = (10 * R[:, :2] @ S.T).transpose(1, 2) + 5
    visible = torch.ones(6, 8, dtype=torch.bool)
    from carvi_torch.cameras import axis_angle_to_rotation
    R0 = (axis_angle_to_rotation(0.1 * torch.randn(6, 3, generator=g, dtype=torch.float64)) @ R)[:, None]
    cams, E = cf.refine_starts_keypoints_only(S, R0, torch.full((6, 1), 9.0, dtype=torch.float64),
                                              torch.full((6, 1, 2), 5.0, dtype=torch.float64), kp, visible,
                                              native=True, tol=1e-12)
    assert bool((E < 1e-12).all())
    torch.testing.assert_close(cams.R, R, rtol=0, atol=1e-6)
    torch.testing.assert_close(cams.s, torch.full((6,), 10.0, dtype=torch.float64), rtol=1e-6, atol=0)


@needs_library
def test_native_camera_fit_operator_checks_its_arguments():
    ops = native_library.library_operators()
    S, kp, visible, R0, s0, t0 = _camera_problem(4, 1, 6, 1, torch.float64)
    S = torch.nan_to_num(S)
    wv = visible.double()
    args = (R0[:, 0].contiguous(), s0[:, 0].contiguous(), t0[:, 0].contiguous(), S, kp.contiguous(), wv)
    ops.fit_cameras(*args, 10, 1e-6)
    with pytest.raises(TypeError, match="Float or Double"):
        ops.fit_cameras(*args[:4], kp.half(), wv, 10, 1e-6)
    with pytest.raises(TypeError, match="must be Double"):
        ops.fit_cameras(args[0].float(), *args[1:], 10, 1e-6)
    with pytest.raises(ValueError, match="S, kp, wv must be"):
        ops.fit_cameras(*args[:3], S[:5].contiguous(), args[4], wv, 10, 1e-6)
    with pytest.raises(ValueError, match="max_iters"):
        ops.fit_cameras(*args, -1, 1e-6)


@needs_library
def test_the_setting_reaches_the_mixtures_camera_fits(monkeypatch):
    """The mixture's keypoint fits use the compiled fit with ``native=True`` (the pipeline passes ``sfm_native``)
    and never without."""
    from carvi_torch.viewpoints import camera_fit as cf
    from carvi_torch.viewpoints import mixture

    calls = []
    real = cf._native_optimize
    monkeypatch.setattr(cf, "_native_optimize", lambda *a, **k: calls.append(1) or real(*a, **k))
    S, kp, visible, R0, s0, t0 = _camera_problem(6, 2, 8, 2, torch.float32)
    both = __import__("types").SimpleNamespace(keypoints=kp, visible=visible)
    for native in (False, True):
        calls.clear()
        mixture.keypoint_fit(S, both, torch.zeros(6, 4, 4), 3, starts=(R0, s0, t0), native=native)
        assert bool(calls) == native


def test_without_the_library_both_fits_run_in_torch(monkeypatch):
    """No compiler (``library_operators`` None): ``native=True`` gives the torch paths' results bit for bit."""
    from carvi_torch.viewpoints import camera_fit as cf

    W, vis = _problem(30, 10, 5)
    with torch.inference_mode():
        a = factorization.factorize(W, vis, rank=3, generator=torch.Generator().manual_seed(3), native=False, **KW)
    S, kp, visible, R0, s0, t0 = _camera_problem(10, 2, 8, 4, torch.float32)
    lam = torch.zeros(10)
    c = cf._optimize(R0, s0, t0, S, kp, visible, None, lam, 100, 1e-6)
    monkeypatch.setattr(native_library, "library_operators", lambda: None)
    with torch.inference_mode():
        b = factorization.factorize(W, vis, rank=3, generator=torch.Generator().manual_seed(3), native=True, **KW)
    d = cf._optimize(R0, s0, t0, S, kp, visible, None, lam, 100, 1e-6, native=True)
    assert all(torch.equal(x, y) for x, y in zip(a[:3], b[:3])) and a[3:] == b[3:]
    assert c.iterations == d.iterations
    assert all(torch.equal(getattr(c, k), getattr(d, k)) for k in c._fields if k != "iterations")


def test_operators_on_serves_cpu_tensors_only(monkeypatch):
    """The one gate every compiled stage asks (SfM, the camera fit, the selection's splat)."""
    from carvi_torch import native_library

    assert native_library.operators_on("meta") is None
    with pytest.raises(ValueError, match="CPU tensors"):
        native_library.operators_on("meta", required=True)
    monkeypatch.setattr(native_library, "library_operators", lambda: None)
    monkeypatch.setattr(native_library, "load", lambda: {"reason": "no compiler found"})
    assert native_library.operators_on("cpu") is None
    with pytest.raises(RuntimeError, match="no compiler found"):
        native_library.operators_on(torch.device("cpu"), required=True)
    sentinel = object()
    monkeypatch.setattr(native_library, "library_operators", lambda: sentinel)
    assert native_library.operators_on("cpu", required=True) is sentinel
