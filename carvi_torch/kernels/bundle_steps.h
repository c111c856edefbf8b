// The joint bundle adjustment (carvi_torch.viewpoints.bundle.joint_bundle_adjust) in plain C++: Levenberg-Marquardt
// over every scaled orthographic camera and one shape at once, in double, the same steps as the torch code:
//
//   cost = sum_n sum_k v_nk |s_n R_n[:2] X_k + t_n - w_nk|^2; per camera (omega, rho, tau) with
//   R <- exp([omega]x) R, log s <- log s + rho, t <- t + tau; the shape X <- X + xi.
//
// Normal equations U (6 x 6 per camera), W (6 x 3K per camera), V (3 x 3 per keypoint), gradients gc, gx; Marquardt's
// damping lambda * max(diag, floor * mean diag) per block family; the cameras eliminated (Schur complement), the
// 3K x 3K system solved by Cholesky, the cameras back-substituted. A step is kept when the cost falls and no camera
// turns or rescales by more than max_step; lambda follows Nielsen's rule. Stops as the torch code does: a kept step
// lowering the RMS residual by at most tol of it, the RMS at or below floor, lambda above max_damping, or iters
// damped solves. exp([omega]x) is camera_steps.h's (kornia's Rodrigues and its series). Agrees with the torch code
// to rounding, not bit for bit (its sums run in another order).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "camera_steps.h"

namespace carvi_bundle {

// In-place Cholesky factor (lower triangle, row-major m x m) of a symmetric matrix, reading only its lower triangle;
// false when a pivot is not positive (NaN included), as torch.linalg.cholesky_ex's info != 0.
inline bool cholesky(double *A, int64_t m)
{
    for (int64_t j = 0; j < m; ++j) {
        double d = A[j * m + j];
        for (int64_t k = 0; k < j; ++k)
            d -= A[j * m + k] * A[j * m + k];
        if (!(d > 0.0))
            return false;
        const double l = std::sqrt(d);
        A[j * m + j] = l;
        for (int64_t i = j + 1; i < m; ++i) {
            double s = A[i * m + j];
            for (int64_t k = 0; k < j; ++k)
                s -= A[i * m + k] * A[j * m + k];
            A[i * m + j] = s / l;
        }
    }
    return true;
}

// Solve L L^T x = b in place (x overwrites b, stride between entries `stride`).
inline void cholesky_solve(const double *L, int64_t m, double *b, int64_t stride)
{
    for (int64_t i = 0; i < m; ++i) {
        double s = b[i * stride];
        for (int64_t k = 0; k < i; ++k)
            s -= L[i * m + k] * b[k * stride];
        b[i * stride] = s / L[i * m + i];
    }
    for (int64_t i = m - 1; i >= 0; --i) {
        double s = b[i * stride];
        for (int64_t k = i + 1; k < m; ++k)
            s -= L[k * m + i] * b[k * stride];
        b[i * stride] = s / L[i * m + i];
    }
}

struct Problem {
    int64_t N, K;
    const double *w; // (N, K, 2), zero where not visible
    const double *v; // (N, K), 0 or 1
};

// Residuals r (N, K, 2), rotated points Y (N, K, 3); returns the cost.
inline double residuals(const Problem &p, const double *R, const double *logs, const double *t, const double *X,
                        double *r, double *Y)
{
    double cost = 0.0;
    for (int64_t n = 0; n < p.N; ++n) {
        const double *Rn = R + 9 * n, s = std::exp(logs[n]);
        for (int64_t k = 0; k < p.K; ++k) {
            const double *x = X + 3 * k;
            double *y = Y + 3 * (n * p.K + k);
            for (int i = 0; i < 3; ++i)
                y[i] = Rn[3 * i] * x[0] + Rn[3 * i + 1] * x[1] + Rn[3 * i + 2] * x[2];
            const double vv = p.v[n * p.K + k];
            double *rr = r + 2 * (n * p.K + k);
            const double *ww = p.w + 2 * (n * p.K + k);
            rr[0] = (s * y[0] + t[2 * n] - ww[0]) * vv;
            rr[1] = (s * y[1] + t[2 * n + 1] - ww[1]) * vv;
            cost += rr[0] * rr[0] + rr[1] * rr[1];
        }
    }
    return cost;
}

// The normal equations' blocks at the current point: U (N, 6, 6), W (N, 6, 3K), V (K, 3, 3), gc (N, 6), gx (K, 3).
struct Normal {
    std::vector<double> U, W, V, gc, gx;
};

inline void normal_equations(const Problem &p, const double *R, const double *logs, const double *Y, const double *r,
                             Normal &ne)
{
    const int64_t N = p.N, K = p.K, m = 3 * K;
    std::fill(ne.U.begin(), ne.U.end(), 0.0);
    std::fill(ne.W.begin(), ne.W.end(), 0.0);
    std::fill(ne.V.begin(), ne.V.end(), 0.0);
    std::fill(ne.gc.begin(), ne.gc.end(), 0.0);
    std::fill(ne.gx.begin(), ne.gx.end(), 0.0);
    for (int64_t n = 0; n < N; ++n) {
        const double s = std::exp(logs[n]), *Rn = R + 9 * n;
        double *U = ne.U.data() + 36 * n, *W = ne.W.data() + 6 * m * n, *gc = ne.gc.data() + 6 * n;
        for (int64_t k = 0; k < K; ++k) {
            const double vv = p.v[n * K + k];
            if (vv == 0.0)
                continue; // a masked entry's rows of the Jacobian are zero
            const double *y = Y + 3 * (n * K + k), *rr = r + 2 * (n * K + k), sv = s * vv;
            const double A[2][6] = {{0.0, y[2] * sv, -y[1] * sv, y[0] * sv, vv, 0.0},
                                    {-y[2] * sv, 0.0, y[0] * sv, y[1] * sv, 0.0, vv}};
            double B[2][3];
            for (int j = 0; j < 3; ++j) {
                B[0][j] = s * Rn[j] * vv;
                B[1][j] = s * Rn[3 + j] * vv;
            }
            for (int a = 0; a < 6; ++a) {
                for (int b = 0; b < 6; ++b)
                    U[6 * a + b] += A[0][a] * A[0][b] + A[1][a] * A[1][b];
                for (int j = 0; j < 3; ++j)
                    W[m * a + 3 * k + j] += A[0][a] * B[0][j] + A[1][a] * B[1][j];
                gc[a] += A[0][a] * rr[0] + A[1][a] * rr[1];
            }
            double *V = ne.V.data() + 9 * k, *gx = ne.gx.data() + 3 * k;
            for (int i = 0; i < 3; ++i) {
                for (int j = 0; j < 3; ++j)
                    V[3 * i + j] += B[0][i] * B[0][j] + B[1][i] * B[1][j];
                gx[i] += B[0][i] * rr[0] + B[1][i] * rr[1];
            }
        }
    }
}

// lam * max(diag, diag_floor * mean diag + 1e-300) of `count` square blocks of size b (stored one after another).
inline void damping(const double *H, int64_t count, int b, double lam, double diag_floor, double *D)
{
    double sum = 0.0;
    for (int64_t c = 0; c < count; ++c)
        for (int i = 0; i < b; ++i)
            sum += H[c * b * b + i * b + i];
    const double lo = diag_floor * (sum / double(count * b)) + 1e-300;
    for (int64_t c = 0; c < count; ++c)
        for (int i = 0; i < b; ++i) {
            const double d = H[c * b * b + i * b + i];
            D[c * b + i] = lam * (std::isnan(d) ? d : std::max(d, lo));
        }
}

// The damped step by the Schur complement: dc (N, 6), dx (3K), the dampings Dc, Dx; false when a damped system is
// not positive definite.
struct Step {
    std::vector<double> dc, dx, Dc, Dx, Ud, UiW, S;
};

inline bool solve(const Problem &p, const Normal &ne, double lam, double diag_floor, Step &st)
{
    const int64_t N = p.N, K = p.K, m = 3 * K, c = m + 1;
    damping(ne.U.data(), N, 6, lam, diag_floor, st.Dc.data());
    damping(ne.V.data(), K, 3, lam, diag_floor, st.Dx.data());
    std::fill(st.S.begin(), st.S.end(), 0.0);
    for (int64_t k = 0; k < K; ++k)
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                st.S[(3 * k + i) * m + 3 * k + j] = ne.V[9 * k + 3 * i + j] + (i == j ? st.Dx[3 * k + i] : 0.0);
    std::vector<double> rhs(m);
    for (int64_t i = 0; i < m; ++i)
        rhs[i] = -ne.gx[i];
    for (int64_t n = 0; n < N; ++n) {
        double *L = st.Ud.data(), *X = st.UiW.data() + 6 * c * n;
        const double *W = ne.W.data() + 6 * m * n;
        for (int a = 0; a < 36; ++a)
            L[a] = ne.U[36 * n + a] + (a % 7 == 0 ? st.Dc[6 * n + a / 7] : 0.0);
        if (!cholesky(L, 6))
            return false;
        for (int a = 0; a < 6; ++a) {
            for (int64_t j = 0; j < m; ++j)
                X[c * a + j] = W[m * a + j];
            X[c * a + m] = ne.gc[6 * n + a];
        }
        for (int64_t j = 0; j < c; ++j)
            cholesky_solve(L, 6, X + j, c);
        for (int a = 0; a < 6; ++a) { // S -= W^T (U^-1 W) (its lower triangle: all cholesky reads), rhs += W^T (U^-1 gc)
            const double *Wa = W + m * a, *Xa = X + c * a;
            for (int64_t i = 0; i < m; ++i) {
                const double wi = Wa[i];
                if (wi == 0.0)
                    continue;
                double *Si = st.S.data() + i * m;
                for (int64_t j = 0; j <= i; ++j)
                    Si[j] -= wi * Xa[j];
                rhs[i] += wi * Xa[m];
            }
        }
    }
    if (!cholesky(st.S.data(), m))
        return false;
    cholesky_solve(st.S.data(), m, rhs.data(), 1);
    for (int64_t i = 0; i < m; ++i)
        st.dx[i] = rhs[i];
    for (int64_t n = 0; n < N; ++n) {
        const double *X = st.UiW.data() + 6 * c * n;
        for (int a = 0; a < 6; ++a) {
            double d = -X[c * a + m];
            for (int64_t j = 0; j < m; ++j)
                d -= X[c * a + j] * st.dx[j];
            st.dc[6 * n + a] = d;
        }
    }
    return true;
}

// The parameters after the step (R <- exp([omega]x) R, log s += rho, t += tau, X += dx).
inline void apply(int64_t N, int64_t K, const double *R, const double *logs, const double *t, const double *X,
                  const Step &st, double *R2, double *logs2, double *t2, double *X2)
{
    for (int64_t n = 0; n < N; ++n) {
        const double *d = st.dc.data() + 6 * n, *Rn = R + 9 * n;
        double E[9];
        carvi_fit::axis_angle<double>(d, E);
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j)
                R2[9 * n + 3 * i + j] = E[3 * i] * Rn[j] + E[3 * i + 1] * Rn[3 + j] + E[3 * i + 2] * Rn[6 + j];
        logs2[n] = logs[n] + d[3];
        t2[2 * n] = t[2 * n] + d[4];
        t2[2 * n + 1] = t[2 * n + 1] + d[5];
    }
    for (int64_t i = 0; i < 3 * K; ++i)
        X2[i] = X[i] + st.dx[i];
}

// The longest move of any camera: its rotation angle |omega| or its log-scale change |rho| (NaN for a NaN step).
inline double step_length(int64_t N, const double *dc)
{
    double longest = 0.0;
    for (int64_t n = 0; n < N; ++n) {
        const double *d = dc + 6 * n;
        const double a = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]), b = std::fabs(d[3]);
        if (std::isnan(a) || std::isnan(b))
            return std::nan("");
        longest = std::max(longest, std::max(a, b));
    }
    return longest;
}

struct Settings {
    int64_t iters;
    double tol, floor, damping, max_step, max_damping, diag_floor;
};

// The run, in place on R (N, 9), logs (N), t (N, 2), X (K, 3). Appends the kept steps' RMS residuals to history;
// returns the damped solves run and sets converged.
inline int64_t adjust(const Problem &p, double *R, double *logs, double *t, double *X, const Settings &cfg,
                      std::vector<double> &history, bool &converged)
{
    const int64_t N = p.N, K = p.K, m = 3 * K;
    double vis = 0.0;
    for (int64_t i = 0; i < N * K; ++i)
        vis += p.v[i];
    const double entries = std::max(2.0 * vis, 1.0);
    std::vector<double> r(2 * N * K), Y(3 * N * K), r2(2 * N * K), Y2(3 * N * K);
    std::vector<double> R2(9 * N), logs2(N), t2(2 * N), X2(3 * K);
    Normal ne{std::vector<double>(36 * N), std::vector<double>(6 * m * N), std::vector<double>(9 * K),
              std::vector<double>(6 * N), std::vector<double>(m)};
    Step st{std::vector<double>(6 * N), std::vector<double>(m), std::vector<double>(6 * N), std::vector<double>(m),
            std::vector<double>(36), std::vector<double>(6 * (m + 1) * N), std::vector<double>(m * m)};
    double cost = residuals(p, R, logs, t, X, r.data(), Y.data());
    double lam = cfg.damping, nu = 2.0;
    int64_t it = 0;
    converged = cfg.iters == 0 || std::sqrt(cost / entries) <= cfg.floor;
    while (it < cfg.iters && !converged) {
        ++it;
        normal_equations(p, R, logs, Y.data(), r.data(), ne);
        const bool ok = solve(p, ne, lam, cfg.diag_floor, st);
        double length = std::nan(""), cost_new = std::nan(""), pred = 0.0;
        if (ok) {
            apply(N, K, R, logs, t, X, st, R2.data(), logs2.data(), t2.data(), X2.data());
            cost_new = residuals(p, R2.data(), logs2.data(), t2.data(), X2.data(), r2.data(), Y2.data());
            for (int64_t i = 0; i < 6 * N; ++i)
                pred += st.dc[i] * (st.Dc[i] * st.dc[i] - ne.gc[i]);
            for (int64_t i = 0; i < m; ++i)
                pred += st.dx[i] * (st.Dx[i] * st.dx[i] - ne.gx[i]);
            length = step_length(N, st.dc.data());
        }
        if (!(length <= cfg.max_step && cost_new < cost)) {
            lam *= nu;
            nu *= 2.0;
            converged = lam > cfg.max_damping;
            continue;
        }
        const double rho = std::min((cost - cost_new) / std::max(pred, 1e-300), 1.0);
        const double q = 2.0 * rho - 1.0;
        lam *= std::max(1.0 / 3.0, 1.0 - q * q * q);
        nu = 2.0;
        const double prev = std::sqrt(cost / entries);
        std::copy(R2.begin(), R2.end(), R);
        std::copy(logs2.begin(), logs2.end(), logs);
        std::copy(t2.begin(), t2.end(), t);
        std::copy(X2.begin(), X2.end(), X);
        r.swap(r2);
        Y.swap(Y2);
        cost = cost_new;
        const double cur = std::sqrt(cost / entries);
        history.push_back(cur);
        converged = cur <= cfg.floor || prev - cur <= cfg.tol * prev;
    }
    return it;
}

} // namespace carvi_bundle
