// The rigid SfM factorisation's outer loop (carvi_torch.viewpoints.factorization._fill_loop) in plain C++: the power
// steps (_power_steps), the candidate blocks, the refill and the stopping test.
//
// Each power step, on the centred filled measurement matrix Wc (N blocks of 2 x K) and the shape S (r x K),
// r = 2 (planar: blocks left free) or 3 (rigid: blocks projected onto scaled Stiefel matrices):
//
//   lam  = reg tr(S S^T) / r + 1e-300         M_n = project(Wc_n S^T (S S^T + lam I)^-1)
//   lamS = reg tr(sum M_n^T M_n) / r + 1e-300  S   = (sum M_n^T M_n + lamS I)^-1 sum M_n^T Wc_n
//
// project(M) = c U V^T, the nearest scaled Stiefel matrix, in the closed form of
// carvi_torch.cameras.scaled_stiefel: adj(M M^T + delta I) M / (2 delta), delta = sqrt(det M M^T).
// The torch path runs the same arithmetic in float64 as torch operators (one to two dozen per step,
// each a few microseconds of dispatch on these tiny matrices); here a step is a few hundred flops.
// The results agree with the torch path to rounding (the r x r solves are Gaussian eliminations
// with partial pivoting, the products are summed in a different order), not bit for bit.
//
// A block of rank < 2 (delta <= 1e-10 tr, where scaled_stiefel falls back to an SVD) or a non-finite
// value makes factorize_loop return 0; the caller then runs the torch path from the same inputs.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace carvi_sfm {

// Solve A X = B in place for an r x r matrix A (row-major, r <= 3) and m right-hand sides B (r x m,
// row-major) by Gaussian elimination with partial pivoting. Returns false on a zero pivot.
inline bool solve_small(double *A, int r, double *B, int64_t m)
{
    for (int c = 0; c < r; ++c) {
        int p = c;
        for (int i = c + 1; i < r; ++i)
            if (std::fabs(A[i * r + c]) > std::fabs(A[p * r + c]))
                p = i;
        if (!(A[p * r + c] != 0.0))
            return false;
        if (p != c) {
            for (int j = 0; j < r; ++j)
                std::swap(A[c * r + j], A[p * r + j]);
            for (int64_t j = 0; j < m; ++j)
                std::swap(B[c * m + j], B[p * m + j]);
        }
        for (int i = c + 1; i < r; ++i) {
            const double f = A[i * r + c] / A[c * r + c];
            for (int j = c; j < r; ++j)
                A[i * r + j] -= f * A[c * r + j];
            for (int64_t j = 0; j < m; ++j)
                B[i * m + j] -= f * B[c * m + j];
        }
    }
    for (int c = r - 1; c >= 0; --c) {
        for (int64_t j = 0; j < m; ++j) {
            double v = B[c * m + j];
            for (int i = c + 1; i < r; ++i)
                v -= A[c * r + i] * B[i * m + j];
            B[c * m + j] = v / A[c * r + c];
        }
    }
    return true;
}

// Nearest scaled Stiefel matrix of one 2 x 3 block, in place. False for a block of rank < 2.
inline bool scaled_stiefel_block(double *M)
{
    const double *m1 = M, *m2 = M + 3;
    const double a = m1[0] * m1[0] + m1[1] * m1[1] + m1[2] * m1[2];
    const double b = m1[0] * m2[0] + m1[1] * m2[1] + m1[2] * m2[2];
    const double d = m2[0] * m2[0] + m2[1] * m2[1] + m2[2] * m2[2];
    const double tr = a + d;
    const double det = a * d - b * b;
    const double delta = std::sqrt(det > 0.0 ? det : 0.0);
    if (!(delta > 1e-10 * tr))
        return false;
    const double inv = 1.0 / (2.0 * delta);
    double out[6];
    for (int j = 0; j < 3; ++j) {
        out[j] = ((d + delta) * m1[j] - b * m2[j]) * inv;
        out[3 + j] = (-b * m1[j] + (a + delta) * m2[j]) * inv;
    }
    for (int j = 0; j < 6; ++j)
        M[j] = out[j];
    return true;
}

// A + (reg tr(A) / r + 1e-300) I for an r x r matrix A, in place: the power steps' relative Tikhonov weight.
inline void add_relative_ridge(double *A, int r, double reg)
{
    double trace = 0.0;
    for (int i = 0; i < r; ++i)
        trace += A[i * r + i];
    const double lam = reg * trace / r + 1e-300;
    for (int i = 0; i < r; ++i)
        A[i * r + i] += lam;
}

// `inner` power steps. Wc: (N, 2, K) row-major; S: (r, K), updated in place; M: (N, 2, r), the last
// step's blocks. False (S and M then unspecified) on a rank < 2 block, a singular solve or a
// non-finite value.
inline bool power_steps(const double *Wc, int64_t N, int64_t K, double *S, int r, int64_t inner, double reg,
                        bool stiefel, double *M)
{
    std::vector<double> C(r * K);
    for (int64_t step = 0; step < inner; ++step) {
        // G = S S^T + lam I; P = S^T G^-1, i.e. G P^T = S (G symmetric): solve with S as r x K right-hand sides
        double G[9] = {0};
        for (int i = 0; i < r; ++i)
            for (int j = 0; j < r; ++j) {
                double v = 0.0;
                for (int64_t k = 0; k < K; ++k)
                    v += S[i * K + k] * S[j * K + k];
                G[i * r + j] = v;
            }
        add_relative_ridge(G, r, reg);
        std::vector<double> PT(S, S + r * K); // P^T (r x K)
        if (!solve_small(G, r, PT.data(), K))
            return false;
        // M_n = Wc_n P, projected; B = sum M_n^T M_n; C = sum M_n^T Wc_n
        double B[9] = {0};
        for (int64_t i = 0; i < r * K; ++i)
            C[i] = 0.0;
        for (int64_t n = 0; n < N; ++n) {
            const double *w = Wc + n * 2 * K;
            double *mn = M + n * 2 * r;
            for (int row = 0; row < 2; ++row)
                for (int c = 0; c < r; ++c) {
                    double v = 0.0;
                    for (int64_t k = 0; k < K; ++k)
                        v += w[row * K + k] * PT[c * K + k];
                    mn[row * r + c] = v;
                }
            if (stiefel && !scaled_stiefel_block(mn))
                return false;
            for (int i = 0; i < r; ++i)
                for (int j = 0; j < r; ++j)
                    B[i * r + j] += mn[i] * mn[j] + mn[r + i] * mn[r + j];
            for (int i = 0; i < r; ++i)
                for (int64_t k = 0; k < K; ++k)
                    C[i * K + k] += mn[i] * w[k] + mn[r + i] * w[K + k];
        }
        add_relative_ridge(B, r, reg);
        if (!solve_small(B, r, C.data(), K))
            return false;
        for (int64_t i = 0; i < r * K; ++i) {
            if (!std::isfinite(C[i]))
                return false;
            S[i] = C[i];
        }
    }
    for (int64_t i = 0; i < N * 2 * r; ++i)
        if (!std::isfinite(M[i]))
            return false;
    return true;
}

// Unit eigenvector of the smallest eigenvalue of a symmetric 3 x 3 matrix C (row-major), by cyclic Jacobi
// rotations. Its sign is arbitrary (the caller uses n n^T only).
inline void smallest_eigenvector(const double *C, double *out)
{
    double a[3][3], v[3][3] = {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            a[i][j] = C[i * 3 + j];
    for (int sweep = 0; sweep < 50; ++sweep) {
        const double off = a[0][1] * a[0][1] + a[0][2] * a[0][2] + a[1][2] * a[1][2];
        const double diag = a[0][0] * a[0][0] + a[1][1] * a[1][1] + a[2][2] * a[2][2];
        if (!(off > 1e-30 * diag))
            break;
        for (int p = 0; p < 2; ++p)
            for (int q = p + 1; q < 3; ++q) {
                if (a[p][q] == 0.0)
                    continue;
                const double theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
                const double t = (theta >= 0 ? 1.0 : -1.0) / (std::fabs(theta) + std::sqrt(theta * theta + 1.0));
                const double c = 1.0 / std::sqrt(t * t + 1.0), sn = t * c;
                for (int k = 0; k < 3; ++k) { // a <- a J (columns p, q)
                    const double akp = a[k][p], akq = a[k][q];
                    a[k][p] = c * akp - sn * akq;
                    a[k][q] = sn * akp + c * akq;
                }
                for (int k = 0; k < 3; ++k) { // a <- J^T a (rows p, q)
                    const double apk = a[p][k], aqk = a[q][k];
                    a[p][k] = c * apk - sn * aqk;
                    a[q][k] = sn * apk + c * aqk;
                }
                for (int k = 0; k < 3; ++k) {
                    const double vkp = v[k][p], vkq = v[k][q];
                    v[k][p] = c * vkp - sn * vkq;
                    v[k][q] = sn * vkp + c * vkq;
                }
            }
    }
    int m = 0;
    for (int i = 1; i < 3; ++i)
        if (a[i][i] < a[m][m])
            m = i;
    for (int k = 0; k < 3; ++k)
        out[k] = v[k][m];
}

// Visible-entry translation t (2) and squared residual of one block M (2 x r) against W_n (2 x K).
inline double visible_residual(const double *M, int r, const double *S, const double *w, const double *vis,
                               int64_t K, double count, double *t)
{
    double sum[2] = {0.0, 0.0};
    for (int row = 0; row < 2; ++row)
        for (int64_t k = 0; k < K; ++k) {
            double p = 0.0;
            for (int c = 0; c < r; ++c)
                p += M[row * r + c] * S[c * K + k];
            sum[row] += (w[row * K + k] - p) * vis[k];
        }
    t[0] = sum[0] / count;
    t[1] = sum[1] / count;
    double res = 0.0;
    for (int row = 0; row < 2; ++row)
        for (int64_t k = 0; k < K; ++k) {
            double p = 0.0;
            for (int c = 0; c < r; ++c)
                p += M[row * r + c] * S[c * K + k];
            const double e = (w[row * K + k] - p - t[row]) * vis[k];
            res += e * e;
        }
    return res;
}

// The affine resection of one instance (carvi_torch.viewpoints.factorization.resect): [M t] minimising the visible
// residual plus mu ||M - M_prev||^2, mu = reg (spread + scale_S). Writes M (2 x r); false on a zero pivot.
inline bool resect_block(const double *S, int r, int64_t K, const double *w, const double *vis, const double *Mprev,
                         double reg, double scale_S, double *M)
{
    const int q = r + 1;
    double A[16] = {0}, B[8] = {0}; // A: q x q; B: q x 2 (the transposed right-hand side)
    for (int64_t k = 0; k < K; ++k) {
        if (vis[k] == 0.0)
            continue;
        double x[4];
        for (int c = 0; c < r; ++c)
            x[c] = S[c * K + k];
        x[r] = 1.0;
        for (int i = 0; i < q; ++i) {
            for (int j = 0; j < q; ++j)
                A[i * q + j] += vis[k] * x[i] * x[j];
            B[i * 2 + 0] += vis[k] * w[k] * x[i];
            B[i * 2 + 1] += vis[k] * w[K + k] * x[i];
        }
    }
    double spread = 0.0;
    for (int c = 0; c < r; ++c)
        spread += A[c * q + c];
    const double mu = reg * (spread / r + scale_S);
    for (int c = 0; c < r; ++c) {
        A[c * q + c] += mu;
        B[c * 2 + 0] += mu * Mprev[c];
        B[c * 2 + 1] += mu * Mprev[r + c];
    }
    if (!solve_small(A, q, B, 2))
        return false;
    for (int c = 0; c < r; ++c) {
        M[c] = B[c * 2 + 0];
        M[r + c] = B[c * 2 + 1];
    }
    return true;
}

// The reflection through the plane of the centred shape's two largest directions: H = I - 2 n n^T (3 x 3).
inline void shape_reflection(const double *S, int64_t K, double *H)
{
    double C[9] = {0}, mean[3] = {0, 0, 0}, nrm[3];
    for (int c = 0; c < 3; ++c) {
        for (int64_t k = 0; k < K; ++k)
            mean[c] += S[c * K + k];
        mean[c] /= (double)K;
    }
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            for (int64_t k = 0; k < K; ++k)
                C[i * 3 + j] += (S[i * K + k] - mean[i]) * (S[j * K + k] - mean[j]);
    smallest_eigenvector(C, nrm);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            H[i * 3 + j] = (i == j ? 1.0 : 0.0) - 2.0 * nrm[i] * nrm[j];
}

// One instance's best candidate block (the power step's Mi, the projected resection, for r = 3 Mi reflected by H,
// the last step's Mprev when given) by visible residual, the first on ties. Writes M (2 x r), t (2) and the
// residual; false where the torch path must run (singular resection, rank < 2 block, non-finite residual).
inline bool best_block(const double *S, int r, int64_t K, const double *w, const double *v, const double *Mi,
                       const double *Mprev, const double *H, double reg, double scale_S, double count, double *M,
                       double *t, double &res)
{
    double cand[4][6], tc[4][2], rc[4];
    int C = 0;
    std::copy(Mi, Mi + 2 * r, cand[C++]);
    if (!resect_block(S, r, K, w, v, Mi, reg, scale_S, cand[C]) || (r == 3 && !scaled_stiefel_block(cand[C])))
        return false;
    ++C;
    if (r == 3) {
        for (int row = 0; row < 2; ++row)
            for (int j = 0; j < 3; ++j) {
                double x = 0.0;
                for (int i = 0; i < 3; ++i)
                    x += cand[0][row * 3 + i] * H[i * 3 + j];
                cand[C][row * 3 + j] = x;
            }
        ++C;
    }
    if (Mprev != nullptr)
        std::copy(Mprev, Mprev + 2 * r, cand[C++]);
    int best = 0;
    for (int c = 0; c < C; ++c) {
        rc[c] = visible_residual(cand[c], r, S, w, v, K, count, tc[c]);
        if (!std::isfinite(rc[c]))
            return false;
        if (rc[c] < rc[best])
            best = c;
    }
    std::copy(cand[best], cand[best] + 2 * r, M);
    t[0] = tc[best][0];
    t[1] = tc[best][1];
    res = rc[best];
    return true;
}

// Wc = Wf minus each row's mean (N x 2 rows of K).
inline void centre_rows(const double *Wf, int64_t rows, int64_t K, double *Wc)
{
    for (int64_t i = 0; i < rows; ++i) {
        double mean = 0.0;
        for (int64_t k = 0; k < K; ++k)
            mean += Wf[i * K + k];
        mean /= (double)K;
        for (int64_t k = 0; k < K; ++k)
            Wc[i * K + k] = Wf[i * K + k] - mean;
    }
}

// The hidden entries of Wf refilled from the blocks: M S + t.
inline void refill(const double *vis, const double *S, const double *M, const double *t, int64_t N, int64_t K, int r,
                   double *Wf)
{
    for (int64_t n = 0; n < N; ++n)
        for (int row = 0; row < 2; ++row)
            for (int64_t k = 0; k < K; ++k) {
                if (vis[n * K + k] > 0.0)
                    continue;
                double p = t[n * 2 + row];
                for (int c = 0; c < r; ++c)
                    p += M[n * 2 * r + row * r + c] * S[c * K + k];
                Wf[(n * 2 + row) * K + k] = p;
            }
}

enum { RAN_OUT = 0, CONVERGED = 1, DECLINED = 2 };

// Steps first_it.. of the outer loop of carvi_torch.viewpoints.factorization.factorize from the filled matrix
// Wf (N, 2, K), the shape S (r x K) and, with have_prev, the last step's blocks M (N, 2, r) (its RMS prev_rms): per
// step the
// power steps, every instance's best candidate block, the refill, the convergence test. Updates Wf, S, M, t (N, 2)
// and writes each step's RMS to history[step - first_it]. Returns the steps run; status: CONVERGED, RAN_OUT (at
// max_outer), or DECLINED: the next step needs the torch path (see power_steps, best_block), and Wf, S, M, t are
// those after the steps run.
inline int64_t factorize_loop(const double *W, const double *vis, double *Wf, int64_t N, int64_t K, double *S, int r,
                              int64_t first_it, int64_t max_outer, int64_t inner, double tol, double reg,
                              double scale, double prev_rms, bool have_prev, double *M, double *t, double *history,
                              int &status)
{
    std::vector<double> Wc(N * 2 * K), Mi(N * 2 * r), counts(N), S0(S, S + r * K), Mn(N * 2 * r), tn(N * 2);
    double entries = 0.0;
    for (int64_t n = 0; n < N; ++n) {
        double c = 0.0;
        for (int64_t k = 0; k < K; ++k)
            c += vis[n * K + k];
        entries += 2.0 * c;
        counts[n] = c < 1.0 ? 1.0 : c;
    }
    entries = entries < 1.0 ? 1.0 : entries;
    double last = prev_rms;
    status = RAN_OUT;
    for (int64_t it = first_it; it <= max_outer; ++it) {
        std::copy(S, S + r * K, S0.begin());
        centre_rows(Wf, N * 2, K, Wc.data());
        double H[9] = {0}, scale_S = 0.0, total = 0.0;
        bool ok = power_steps(Wc.data(), N, K, S, r, inner, reg, r == 3, Mi.data());
        for (int64_t i = 0; ok && i < r * K; ++i)
            scale_S += S[i] * S[i];
        scale_S /= (double)(r * K);
        if (ok && r == 3)
            shape_reflection(S, K, H);
        for (int64_t n = 0; ok && n < N; ++n) {
            double res = 0.0;
            ok = best_block(S, r, K, W + n * 2 * K, vis + n * K, Mi.data() + n * 2 * r,
                            have_prev ? M + n * 2 * r : nullptr, H, reg, scale_S, counts[n], Mn.data() + n * 2 * r,
                            tn.data() + n * 2, res);
            total += res;
        }
        if (!ok) {
            std::copy(S0.begin(), S0.end(), S);
            status = DECLINED;
            return it - first_it;
        }
        std::copy(Mn.begin(), Mn.end(), M);
        std::copy(tn.begin(), tn.end(), t);
        have_prev = true;
        refill(vis, S, M, t, N, K, r, Wf);
        const double rms = std::sqrt(total / entries);
        history[it - first_it] = rms;
        const bool settled = it > 1 && std::fabs(last - rms) <= tol * last;
        last = rms;
        if (rms <= 1e-5 * scale || settled) {
            status = CONVERGED;
            return it - first_it + 1;
        }
    }
    return max_outer >= first_it ? max_outer - first_it + 1 : 0;
}

} // namespace carvi_sfm
