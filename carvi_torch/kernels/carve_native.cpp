// carvi_torch's fused carving kernel (carve_core.h) as torch.library operators, in the namespace CARVI_NS
// (native.py names it after the build's key, carvi_<hex>: loading a second library that defines operators
// of a namespace already registered aborts the process, so two builds must never share one):
//
//   carvi::carve_labels(Tensor ext, Tensor views, Tensor scale, Tensor G, Tensor column_cost, int n,
//                       bool imprint, bool fma) -> (Tensor occ, Tensor columns, Tensor nonempty, Tensor samples)
//   carvi::sample(Tensor ext, int k, float scale, Tensor grid, bool fma) -> Tensor
//   carvi::line(Tensor ext, int k, float scale, float g0x, float g0y, float cx, float cy, int m, bool fma) -> Tensor
//   carvi::has_fma() -> bool
//   carvi::sfm_factorize(Tensor W, Tensor vis, Tensor Wf, Tensor S, Tensor M, bool have_prev, int first_it,
//                        float prev_rms, int max_outer, int inner, float tol, float reg, float scale)
//                        -> (Tensor M, Tensor t, Tensor S, Tensor Wf, Tensor history, int steps, int status)
//     (the rigid SfM's factorisation, sfm_steps.h; nothing to do with the carving but its build)
//   carvi::fit_cameras(Tensor R, Tensor s, Tensor t, Tensor S, Tensor kp, Tensor wv, int max_iters, float tol)
//                      -> (Tensor R, Tensor s, Tensor t, Tensor E_before, Tensor E, Tensor converged, int iters, bool ok)
//     (the keypoint-only camera fit, camera_steps.h)
//   carvi::joint_bundle(Tensor R, Tensor logs, Tensor t, Tensor X, Tensor w, Tensor v, int iters, float tol,
//                       float floor, float damping, float max_step, float max_damping, float diag_floor)
//                       -> (Tensor R, Tensor logs, Tensor t, Tensor X, Tensor history, int iterations, bool converged)
//     (the SfM's joint bundle adjustment, bundle_steps.h; float64)
//   carvi::splat_planes(Tensor(a!) out, Tensor occ, Tensor Ld, Tensor Lh, Tensor Lw, Tensor rows, int md, int mh,
//                       int mw, int G) -> ()
//     (the selection's projection of proposals onto the principal planes, splat_planes.h; grids in parallel)
//
// Every argument is checked here, at the operators' boundary: device, dtype, layout, contiguity, shapes,
// index ranges and sizes (the kernel reads raw pointers: it must never read outside its inputs, whatever
// they are). Proposals are carved in torch's intra-op thread pool (at::parallel_for: torch.set_num_threads
// governs it); the threads take proposals one at a time, heaviest first, from a shared counter, since
// proposals differ in cost by orders of magnitude.
#if defined(CARVI_FULL_HEADERS)
#include <torch/extension.h>
#else
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <torch/library.h>
#endif

#include <algorithm>
#include <atomic>
#include <cstring>
#include <numeric>
#include <tuple>
#include <vector>

#include "carve_core.h"
#include "sfm_steps.h"
#include "camera_steps.h"
#include "bundle_steps.h"
#include "splat_planes.h"

#ifndef CARVI_SCHEDULE
#define CARVI_SCHEDULE 2 // 0: parallel_for's own split; 1: weighted ranges, 4 per thread; 2: heaviest first
#endif

namespace {

void check_tensor(const at::Tensor &t, const char *name, at::ScalarType dtype, int64_t dim)
{
    TORCH_CHECK_VALUE(t.defined(), "carvi: ", name, " is undefined");
    TORCH_CHECK_VALUE(t.device().is_cpu(), "carvi: the kernels take CPU tensors; ", name, " is on ",
                      t.device());
    TORCH_CHECK_VALUE(t.layout() == at::kStrided, "carvi: ", name, " must be a strided (dense) tensor");
    TORCH_CHECK_TYPE(t.scalar_type() == dtype, "carvi: ", name, " must be ", dtype, ", got ", t.scalar_type());
    TORCH_CHECK_VALUE(t.dim() == dim, "carvi: ", name, " must have ", dim, " dimensions, got shape ", t.sizes());
    TORCH_CHECK_VALUE(t.is_contiguous(), "carvi: ", name, " must be contiguous");
    TORCH_CHECK_VALUE(!t.is_neg() && !t.is_conj(), "carvi: ", name, " must not be a negated or conjugated view");
    TORCH_CHECK_VALUE(t.numel() == 0 || t.has_storage(), "carvi: ", name, " has no storage");
}

// A new contiguous tensor holding a checked (contiguous) tensor's values (an empty one copies nothing).
at::Tensor copy_of(const at::Tensor &t)
{
    at::Tensor out = at::empty(t.sizes(), t.options());
    if (t.nbytes() > 0)
        std::memcpy(out.data_ptr(), t.data_ptr(), t.nbytes());
    return out;
}

// (K, Hp, Wp) float32 maps whose 32-bit pixel offsets cannot overflow.
void check_maps(const at::Tensor &ext)
{
    check_tensor(ext, "ext", at::kFloat, 3);
    const int64_t Hp = ext.size(1), Wp = ext.size(2);
    TORCH_CHECK_VALUE(Hp >= 1 && Wp >= 1, "carvi: maps must have at least one pixel, got ", ext.sizes());
    TORCH_CHECK_VALUE(Hp * Wp < (int64_t(1) << 31) - Wp, "carvi: maps of ", Hp, " x ", Wp,
                      " pixels are too large for the fused carving's 32-bit offsets");
}

// The maps, with one float after map `last` when it is the last one (the AVX2 sampler's 8-byte reads may
// touch it, with weight 0): ext itself, or a copy kept alive in `keep`.
const float *maps_with_spare(const at::Tensor &ext, bool uses_last, at::Tensor &keep)
{
    if (!uses_last)
        return ext.data_ptr<float>();
    keep = at::zeros({ext.numel() + 1}, ext.options());
    std::memcpy(keep.data_ptr<float>(), ext.data_ptr<float>(), sizeof(float) * ext.numel());
    return keep.data_ptr<float>();
}

void check_fma(bool fma)
{
    TORCH_CHECK_VALUE(!fma || carvi::has_fma(), "carvi: the fma variant needs a processor with AVX2 and FMA");
}

// Largest view index, after checking every one is in -1 .. K - 1.
int64_t check_views(const at::Tensor &views, int64_t K)
{
    const int64_t *v = views.data_ptr<int64_t>();
    int64_t lo = 0, hi = -1;
    for (int64_t i = 0; i < views.numel(); i++) {
        lo = std::min(lo, v[i]);
        hi = std::max(hi, v[i]);
    }
    TORCH_CHECK_VALUE(views.numel() == 0 || (lo >= -1 && hi < K), "carvi: views must index the ", K,
                      " maps of ext, or be -1 (unused), got ", lo, " .. ", hi);
    return hi;
}

void check_carve_inputs(const at::Tensor &ext, const at::Tensor &views, const at::Tensor &scale,
                        const at::Tensor &G, const at::Tensor &column_cost, int64_t n)
{
    check_maps(ext);
    check_tensor(views, "views", at::kLong, 2);
    const int64_t B = views.size(0), V = views.size(1);
    TORCH_CHECK_VALUE(V <= CARVI_MAX_VIEWS, "carvi: the fused carving takes at most ", CARVI_MAX_VIEWS,
                      " view slots, got ", V);
    TORCH_CHECK_VALUE(n >= 1 && n <= CARVI_MAX_RESOLUTION, "carvi: the fused carving takes resolutions 1 to ",
                      CARVI_MAX_RESOLUTION, ", got ", n);
    check_tensor(scale, "scale", at::kFloat, 2);
    check_tensor(G, "G", at::kFloat, 4);
    check_tensor(column_cost, "column_cost", at::kFloat, 2);
    const bool ok = scale.sizes() == at::IntArrayRef({B, V}) && G.sizes() == at::IntArrayRef({B, V, 2, 4}) &&
                    column_cost.sizes() == at::IntArrayRef({B, n * n});
    TORCH_CHECK_VALUE(ok, "carvi: scale, G, column_cost must be (", B, ", ", V, "), (", B, ", ", V, ", 2, 4), (", B,
                      ", ", n * n, "); got ", scale.sizes(), ", ", G.sizes(), ", ", column_cost.sizes());
}

// Estimated work per proposal: foreground columns times (used views + 1); interior voxels cost every
// view, exterior ones about one.
std::vector<int64_t> work_weights(const int64_t *views, const float *cc, int64_t B, int64_t V, int64_t HW)
{
    std::vector<int64_t> w(B);
    for (int64_t b = 0; b < B; b++) {
        int64_t fg = 0, used = 0;
        for (int64_t k = 0; k < HW; k++)
            fg += cc[b * HW + k] < 0.0f;
        for (int64_t j = 0; j < V; j++)
            used += views[b * V + j] >= 0;
        w[b] = fg * (used + 1);
    }
    return w;
}

// Runs carve_range(b0, b1) over all B proposals in torch's intra-op pool.
template <typename F>
void schedule(const std::vector<int64_t> &w, F carve_range)
{
    const int64_t B = (int64_t)w.size();
    const int64_t T = std::min<int64_t>(at::get_num_threads(), B);
    if (T <= 1 || at::in_parallel_region()) {
        carve_range(0, B);
        return;
    }
#if CARVI_SCHEDULE == 0
    at::parallel_for(0, B, 1, carve_range);
#elif CARVI_SCHEDULE == 1
    // 4 ranges per thread of about equal total weight, taken in turn (today's Python-pool split)
    const int64_t parts = 4 * T;
    const int64_t total = std::max<int64_t>(1, std::accumulate(w.begin(), w.end(), int64_t(0)));
    std::vector<int64_t> bounds{0};
    for (int64_t b = 0, acc = 0; b < B; b++) {
        acc += w[b];
        if (acc * parts >= total * (int64_t)bounds.size() && (int64_t)bounds.size() < parts)
            bounds.push_back(b + 1);
    }
    if (bounds.back() != B)
        bounds.push_back(B);
    std::atomic<int64_t> next{0};
    const int64_t R = (int64_t)bounds.size() - 1;
    at::parallel_for(0, T, 1, [&](int64_t, int64_t) {
        for (int64_t r; (r = next.fetch_add(1)) < R;)
            carve_range(bounds[r], bounds[r + 1]);
    });
#else
    // one proposal at a time, heaviest first, from a shared counter (longest-processing-time order)
    std::vector<int64_t> order(B);
    std::iota(order.begin(), order.end(), 0);
    std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) { return w[a] > w[b]; });
    std::atomic<int64_t> next{0};
    at::parallel_for(0, T, 1, [&](int64_t, int64_t) {
        for (int64_t i; (i = next.fetch_add(1)) < B;)
            carve_range(order[i], order[i] + 1);
    });
#endif
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor> carve_labels(
    const at::Tensor &ext, const at::Tensor &views, const at::Tensor &scale, const at::Tensor &G,
    const at::Tensor &column_cost, int64_t n, bool imprint, bool fma)
{
    check_carve_inputs(ext, views, scale, G, column_cost, n);
    check_fma(fma);
    const int64_t B = views.size(0), V = views.size(1), HW = n * n, Hp = ext.size(1), Wp = ext.size(2);
    const int64_t last = check_views(views, ext.size(0));
    at::Tensor spare;
    const float *maps = maps_with_spare(ext, last == ext.size(0) - 1, spare);
    auto u8 = ext.options().dtype(at::kByte);
    at::Tensor occ = at::zeros({B, n, HW}, u8), columns = at::zeros({B, HW}, u8), nonempty = at::zeros({B}, u8);
    at::Tensor samples = at::zeros({B}, ext.options().dtype(at::kLong));
    const int64_t *vp = views.data_ptr<int64_t>();
    const float *sp = scale.data_ptr<float>(), *gp = G.data_ptr<float>(), *cp = column_cost.data_ptr<float>();
    uint8_t *op = occ.data_ptr<uint8_t>(), *colp = columns.data_ptr<uint8_t>(), *np = nonempty.data_ptr<uint8_t>();
    int64_t *cntp = samples.data_ptr<int64_t>();
    auto fn = fma ? carvi::carve_fma : carvi::carve_plain;
    schedule(work_weights(vp, cp, B, V, HW), [&](int64_t b0, int64_t b1) {
        fn(maps, Hp, Wp, vp, sp, gp, cp, V, n, imprint, b0, b1, op, colp, np, cntp); // inputs checked: returns 0
    });
    return {occ.view(at::kBool), columns.view(at::kBool), nonempty.view(at::kBool), samples};
}

at::Tensor sample(const at::Tensor &ext, int64_t k, double scale, const at::Tensor &grid, bool fma)
{
    check_maps(ext);
    check_tensor(grid, "grid", at::kFloat, 2);
    TORCH_CHECK_VALUE(grid.size(1) == 2, "carvi: grid must be (m, 2), got ", grid.sizes());
    TORCH_CHECK_VALUE(k >= 0 && k < ext.size(0), "carvi: map ", k, " of ", ext.size(0), " maps");
    check_fma(fma);
    at::Tensor out = at::empty({grid.size(0)}, ext.options());
    auto fn = fma ? carvi::samples_fma : carvi::samples_plain;
    fn(ext.data_ptr<float>(), ext.size(1), ext.size(2), k, (float)scale, grid.data_ptr<float>(), grid.size(0),
       out.data_ptr<float>());
    return out;
}

at::Tensor line(const at::Tensor &ext, int64_t k, double scale, double g0x, double g0y, double cx, double cy,
                int64_t m, bool fma)
{
    check_maps(ext);
    TORCH_CHECK_VALUE(k >= 0 && k < ext.size(0), "carvi: map ", k, " of ", ext.size(0), " maps");
    TORCH_CHECK_VALUE(m >= 1 && m <= CARVI_MAX_RESOLUTION, "carvi: a line has 1 to ", CARVI_MAX_RESOLUTION,
                      " depths, got ", m);
    check_fma(fma);
    at::Tensor spare;
    const float *maps = maps_with_spare(ext, k == ext.size(0) - 1, spare);
    at::Tensor out = at::empty({m}, ext.options());
    auto fn = fma ? carvi::line_fma : carvi::line_plain;
    fn(maps, ext.size(1), ext.size(2), k, (float)scale, (float)g0x, (float)g0y, (float)cx, (float)cy, m,
       out.data_ptr<float>());
    return out;
}

bool has_fma() { return carvi::has_fma() != 0; }

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, int64_t, int64_t> sfm_factorize(
    const at::Tensor &W, const at::Tensor &vis, const at::Tensor &Wf, const at::Tensor &S, const at::Tensor &M,
    bool have_prev, int64_t first_it, double prev_rms, int64_t max_outer, int64_t inner, double tol, double reg,
    double scale)
{
    check_tensor(W, "W", at::kDouble, 3);
    check_tensor(vis, "vis", at::kDouble, 2);
    check_tensor(Wf, "Wf", at::kDouble, 3);
    check_tensor(S, "S", at::kDouble, 2);
    check_tensor(M, "M", at::kDouble, 3);
    const int64_t N = W.size(0), K = W.size(2), r = S.size(0);
    TORCH_CHECK_VALUE(W.size(1) == 2 && Wf.sizes() == W.sizes(), "carvi: W and Wf must be (N, 2, K), got ",
                      W.sizes(), " and ", Wf.sizes());
    TORCH_CHECK_VALUE(vis.size(0) == N && vis.size(1) == K, "carvi: vis must be (N, K) = (", N, ", ", K, "), got ",
                      vis.sizes());
    TORCH_CHECK_VALUE((r == 2 || r == 3) && S.size(1) == K, "carvi: S must be (2 or 3, K = ", K, "), got ", S.sizes());
    TORCH_CHECK_VALUE(M.size(0) == N && M.size(1) == 2 && M.size(2) == r, "carvi: M must be (N, 2, r) = (", N, ", 2, ",
                      r, "), got ", M.sizes());
    TORCH_CHECK_VALUE(max_outer >= 1 && inner >= 1 && first_it >= 1, "carvi: max_outer, inner and first_it must be "
                      ">= 1, got ", max_outer, ", ", inner, " and ", first_it);
    at::Tensor Wf_out = at::empty(Wf.sizes(), Wf.options()), S_out = at::empty(S.sizes(), S.options());
    at::Tensor M_out = at::empty(M.sizes(), M.options()), t = at::zeros({N, 2}, W.options());
    std::memcpy(Wf_out.data_ptr<double>(), Wf.data_ptr<double>(), sizeof(double) * N * 2 * K);
    std::memcpy(S_out.data_ptr<double>(), S.data_ptr<double>(), sizeof(double) * r * K);
    std::memcpy(M_out.data_ptr<double>(), M.data_ptr<double>(), sizeof(double) * N * 2 * r);
    at::Tensor history = at::zeros({max_outer >= first_it ? max_outer - first_it + 1 : 0}, W.options());
    int status = 0;
    const int64_t steps = carvi_sfm::factorize_loop(
        W.data_ptr<double>(), vis.data_ptr<double>(), Wf_out.data_ptr<double>(), N, K, S_out.data_ptr<double>(), (int)r,
        first_it, max_outer, inner, tol, reg, scale, prev_rms, have_prev, M_out.data_ptr<double>(), t.data_ptr<double>(),
        history.data_ptr<double>(), status);
    return {M_out, t, S_out, Wf_out, history, steps, (int64_t)status};
}

template <typename T>
void fit_cameras_typed(at::Tensor &R, at::Tensor &s, at::Tensor &t, const at::Tensor &S, const at::Tensor &kp,
                       const at::Tensor &wv, int64_t max_iters, double tol, at::Tensor &E0, at::Tensor &E,
                       at::Tensor &conv, int64_t &iters, bool &ok)
{
    const int64_t M = R.size(0), K = S.size(0);
    T *Rp = R.data_ptr<T>(), *sp = s.data_ptr<T>(), *tp = t.data_ptr<T>(), *E0p = E0.data_ptr<T>(), *Ep = E.data_ptr<T>();
    const T *Sp = S.data_ptr<T>(), *kpp = kp.data_ptr<T>(), *wvp = wv.data_ptr<T>();
    bool *cp = conv.data_ptr<bool>();
    iters = 0;
    ok = true;
    for (int64_t m = 0; m < M && ok; ++m) {
        bool c = false;
        const int64_t it = carvi_fit::fit_camera<T>(Rp + 9 * m, sp[m], tp + 2 * m, Sp, kpp + 2 * K * m, wvp + K * m, K,
                                                    max_iters, tol, E0p[m], Ep[m], c);
        cp[m] = c;
        ok = it >= 0;
        iters = it > iters ? it : iters;
    }
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, int64_t, bool> fit_cameras(
    const at::Tensor &R, const at::Tensor &s, const at::Tensor &t, const at::Tensor &S, const at::Tensor &kp,
    const at::Tensor &wv, int64_t max_iters, double tol)
{
    const at::ScalarType dt = kp.scalar_type();
    TORCH_CHECK_TYPE(dt == at::kFloat || dt == at::kDouble, "carvi: kp must be Float or Double, got ", dt);
    check_tensor(R, "R", dt, 3);
    check_tensor(s, "s", dt, 1);
    check_tensor(t, "t", dt, 2);
    check_tensor(S, "S", dt, 2);
    check_tensor(kp, "kp", dt, 3);
    check_tensor(wv, "wv", dt, 2);
    const int64_t M = R.size(0), K = S.size(0);
    TORCH_CHECK_VALUE(R.size(1) == 3 && R.size(2) == 3 && s.size(0) == M && t.size(0) == M && t.size(1) == 2,
                      "carvi: R, s, t must be (M, 3, 3), (M,), (M, 2), got ", R.sizes(), ", ", s.sizes(), ", ",
                      t.sizes());
    TORCH_CHECK_VALUE(S.size(1) == 3 && kp.size(0) == M && kp.size(1) == K && kp.size(2) == 2 && wv.size(0) == M &&
                          wv.size(1) == K,
                      "carvi: S, kp, wv must be (K, 3), (M, K, 2), (M, K), got ", S.sizes(), ", ", kp.sizes(), ", ",
                      wv.sizes());
    TORCH_CHECK_VALUE(max_iters >= 0, "carvi: max_iters must be >= 0, got ", max_iters);
    at::Tensor Ro = copy_of(R), so = copy_of(s), to = copy_of(t);
    at::Tensor E0 = at::zeros({M}, s.options()), E = at::zeros({M}, s.options());
    at::Tensor conv = at::zeros({M}, s.options().dtype(at::kBool));
    int64_t iters = 0;
    bool ok = true;
    if (dt == at::kFloat)
        fit_cameras_typed<float>(Ro, so, to, S, kp, wv, max_iters, tol, E0, E, conv, iters, ok);
    else
        fit_cameras_typed<double>(Ro, so, to, S, kp, wv, max_iters, tol, E0, E, conv, iters, ok);
    return {Ro, so, to, E0, E, conv, iters, ok};
}

std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor, int64_t, bool> joint_bundle(
    const at::Tensor &R, const at::Tensor &logs, const at::Tensor &t, const at::Tensor &X, const at::Tensor &w,
    const at::Tensor &v, int64_t iters, double tol, double floor, double damping, double max_step, double max_damping,
    double diag_floor)
{
    check_tensor(R, "R", at::kDouble, 3);
    check_tensor(logs, "logs", at::kDouble, 1);
    check_tensor(t, "t", at::kDouble, 2);
    check_tensor(X, "X", at::kDouble, 2);
    check_tensor(w, "w", at::kDouble, 3);
    check_tensor(v, "v", at::kDouble, 2);
    const int64_t N = R.size(0), K = X.size(0);
    TORCH_CHECK_VALUE(R.size(1) == 3 && R.size(2) == 3 && logs.size(0) == N && t.size(0) == N && t.size(1) == 2,
                      "carvi: R, logs, t must be (N, 3, 3), (N,), (N, 2), got ", R.sizes(), ", ", logs.sizes(), ", ",
                      t.sizes());
    TORCH_CHECK_VALUE(K >= 1 && X.size(1) == 3 && w.size(0) == N && w.size(1) == K && w.size(2) == 2 &&
                          v.size(0) == N && v.size(1) == K,
                      "carvi: X, w, v must be (K, 3), (N, K, 2), (N, K) with K >= 1, got ", X.sizes(), ", ", w.sizes(),
                      ", ", v.sizes());
    TORCH_CHECK_VALUE(iters >= 0 && damping > 0.0 && std::isfinite(damping), "carvi: iters must be >= 0 and damping "
                      "finite and positive, got ", iters, " and ", damping);
    at::Tensor Ro = copy_of(R), lo = copy_of(logs), to = copy_of(t), Xo = copy_of(X);
    std::vector<double> history;
    bool converged = false;
    const carvi_bundle::Problem p{N, K, w.data_ptr<double>(), v.data_ptr<double>()};
    const carvi_bundle::Settings cfg{iters, tol, floor, damping, max_step, max_damping, diag_floor};
    const int64_t it = carvi_bundle::adjust(p, Ro.data_ptr<double>(), lo.data_ptr<double>(), to.data_ptr<double>(),
                                            Xo.data_ptr<double>(), cfg, history, converged);
    at::Tensor h = at::empty({(int64_t)history.size()}, R.options());
    if (!history.empty())
        std::memcpy(h.data_ptr<double>(), history.data(), sizeof(double) * history.size());
    return {Ro, lo, to, Xo, h, it, converged};
}

void splat_planes(const at::Tensor &out, const at::Tensor &occ, const at::Tensor &Ld, const at::Tensor &Lh,
                  const at::Tensor &Lw, const at::Tensor &rows, int64_t md, int64_t mh, int64_t mw, int64_t G)
{
    check_tensor(out, "out", at::kBool, 1);
    check_tensor(occ, "occ", at::kBool, 4);
    check_tensor(rows, "rows", at::kLong, 1);
    TORCH_CHECK_VALUE(G >= 1 && G <= (int64_t(1) << 20) && md >= 1 && mh >= 1 && mw >= 1,
                      "carvi: G must be in 1 .. 2^20 and md, mh, mw >= 1, got ", G, ", ", md, ", ", mh, " and ", mw);
    const int64_t nb = rows.size(0), D = occ.size(1), H = occ.size(2), W = occ.size(3), plane = (G + 2) * (G + 2);
    const at::Tensor *tables[3] = {&Ld, &Lh, &Lw};
    const int64_t m[3] = {md, mh, mw}, size[3] = {D, H, W};
    const char *names[3] = {"Ld", "Lh", "Lw"};
    for (int a = 0; a < 3; ++a) {
        check_tensor(*tables[a], names[a], at::kFloat, 2);
        TORCH_CHECK_VALUE(tables[a]->size(0) == 3 * m[a] && tables[a]->size(1) == nb * size[a], "carvi: ", names[a],
                          " must be (3 * ", m[a], ", ", nb, " * ", size[a], "), got ", tables[a]->sizes());
    }
    TORCH_CHECK_VALUE(out.numel() % (3 * plane) == 0, "carvi: out must hold whole sets of three ", G + 2, " x ", G + 2,
                      " planes, got ", out.numel(), " samples");
    const int64_t B = out.numel() / (3 * plane);
    TORCH_CHECK_VALUE(occ.size(0) == B, "carvi: occ must hold the ", B, " grids of out, got ", occ.sizes());
    const int64_t *r = rows.data_ptr<int64_t>();
    std::vector<char> taken(B, 0);
    for (int64_t i = 0; i < nb; ++i) {  // distinct positions: the grids are splatted in parallel
        TORCH_CHECK_VALUE(r[i] >= 0 && r[i] < B && !taken[r[i]], "carvi: rows must be distinct positions in 0 .. ",
                          B - 1, ", got ", r[i], " at ", i);
        taken[r[i]] = 1;
    }
    const uint8_t *g = reinterpret_cast<const uint8_t *>(occ.data_ptr<bool>());
    uint8_t *o = reinterpret_cast<uint8_t *>(out.data_ptr<bool>());
    const float *ld = Ld.data_ptr<float>(), *lh = Lh.data_ptr<float>(), *lw = Lw.data_ptr<float>();
    at::parallel_for(0, nb, 1, [&](int64_t b0, int64_t b1) {
        for (int64_t b = b0; b < b1; ++b)
            carvi_splat::splat_grid(g + r[b] * D * H * W, b, D, H, W, ld, lh, lw, md, mh, mw, G, nb, o + r[b] * 3 * plane);
    });
}

} // namespace

#ifndef CARVI_NS
#define CARVI_NS carvi
#endif

TORCH_LIBRARY(CARVI_NS, m)
{
    m.def("carve_labels(Tensor ext, Tensor views, Tensor scale, Tensor G, Tensor column_cost, int n, bool imprint, "
          "bool fma) -> (Tensor, Tensor, Tensor, Tensor)");
    m.def("sample(Tensor ext, int k, float scale, Tensor grid, bool fma) -> Tensor");
    m.def("line(Tensor ext, int k, float scale, float g0x, float g0y, float cx, float cy, int m, bool fma) -> Tensor");
    m.def("has_fma() -> bool", &has_fma);
    m.def("sfm_factorize(Tensor W, Tensor vis, Tensor Wf, Tensor S, Tensor M, bool have_prev, int first_it, "
          "float prev_rms, int max_outer, int inner, float tol, float reg, float scale) -> "
          "(Tensor, Tensor, Tensor, Tensor, Tensor, int, int)");
    m.def("fit_cameras(Tensor R, Tensor s, Tensor t, Tensor S, Tensor kp, Tensor wv, int max_iters, float tol) -> "
          "(Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, int, bool)");
    m.def("joint_bundle(Tensor R, Tensor logs, Tensor t, Tensor X, Tensor w, Tensor v, int iters, float tol, "
          "float floor, float damping, float max_step, float max_damping, float diag_floor) -> "
          "(Tensor, Tensor, Tensor, Tensor, Tensor, int, bool)");
    m.def("splat_planes(Tensor(a!) out, Tensor occ, Tensor Ld, Tensor Lh, Tensor Lw, Tensor rows, int md, int mh, "
          "int mw, int G) -> ()");
}

// CompositeExplicitAutograd: one kernel for every device, so that a tensor on another device reaches the
// checks above (and gets their message) instead of the dispatcher's "could not run" error.
TORCH_LIBRARY_IMPL(CARVI_NS, CompositeExplicitAutograd, m)
{
    m.impl("carve_labels", &carve_labels);
    m.impl("sample", &sample);
    m.impl("line", &line);
    m.impl("sfm_factorize", &sfm_factorize);
    m.impl("fit_cameras", &fit_cameras);
    m.impl("joint_bundle", &joint_bundle);
    m.impl("splat_planes", &splat_planes);
}
