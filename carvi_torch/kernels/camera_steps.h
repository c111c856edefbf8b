// The keypoint-only camera fit (carvi_torch.viewpoints.camera_fit._optimize_impl without a silhouette term) in
// plain C++: damped Gauss-Newton (Levenberg-Marquardt) over one scaled orthographic camera per row, rows
// independent. The same steps as the torch code, in the keypoints' float type T (float or double) with the
// 6 x 6 solves in double:
//
//   E = sum_k w_k |s R[:2] S_k + t - x_k|^2, local increments delta = (omega, log-scale, t) with
//   R <- retract(exp([omega]x) R), s <- s exp(sigma), t <- t + tau; a step is kept when E does not rise,
//   mu /= 3 then, else mu *= 4; a camera stops when the kept step lowers E by at most tol E or mu > 1e8.
//
// exp([omega]x) follows kornia's axis_angle_to_rotation_matrix (Rodrigues above theta^2 = 1e-6, its second-order
// series below); the retraction re-projects the first two rows onto a scaled Stiefel matrix
// (carvi_torch.cameras.scaled_stiefel), normalises them by the first row's norm and completes the rotation
// with their cross product. Agrees with the torch code to rounding, not bit for bit.
#pragma once

#include <cmath>
#include <cstdint>
#include <utility>

namespace carvi_fit {

template <typename T> void axis_angle(const T *w, T *R)
{
    const T theta2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    if (theta2 > T(1e-6)) {
        const T theta = std::sqrt(theta2);
        const T wx = w[0] / theta, wy = w[1] / theta, wz = w[2] / theta;
        const T c = std::cos(theta), s = std::sin(theta), omc = T(1) - c;
        R[0] = c + wx * wx * omc;
        R[1] = wx * wy * omc - wz * s;
        R[2] = wy * s + wx * wz * omc;
        R[3] = wz * s + wx * wy * omc;
        R[4] = c + wy * wy * omc;
        R[5] = -wx * s + wy * wz * omc;
        R[6] = -wy * s + wx * wz * omc;
        R[7] = wx * s + wy * wz * omc;
        R[8] = c + wz * wz * omc;
    } else {
        const T a = T(1) - theta2 / T(6), b = T(0.5) - theta2 / T(24);
        const T rx = w[0], ry = w[1], rz = w[2];
        R[0] = T(1) - b * (ry * ry + rz * rz);
        R[1] = -a * rz + b * (rx * ry);
        R[2] = a * ry + b * (rx * rz);
        R[3] = a * rz + b * (rx * ry);
        R[4] = T(1) - b * (rx * rx + rz * rz);
        R[5] = -a * rx + b * (ry * rz);
        R[6] = -a * ry + b * (rx * rz);
        R[7] = a * rx + b * (ry * rz);
        R[8] = T(1) - b * (rx * rx + ry * ry);
    }
}

// E, g (6) and H (6 x 6, row-major) of one camera.
template <typename T>
void terms(const T *R, T s, const T *t, const T *S, const T *kp, const T *wv, int64_t K, T &E, T *g, T *H)
{
    E = T(0);
    for (int i = 0; i < 6; ++i)
        g[i] = T(0);
    for (int i = 0; i < 36; ++i)
        H[i] = T(0);
    for (int64_t k = 0; k < K; ++k) {
        const T *X = S + 3 * k;
        T Y[3];
        for (int i = 0; i < 3; ++i)
            Y[i] = X[0] * R[3 * i] + X[1] * R[3 * i + 1] + X[2] * R[3 * i + 2];
        const T P0 = s * Y[0] + t[0], P1 = s * Y[1] + t[1];
        const T r0 = P0 - kp[2 * k], r1 = P1 - kp[2 * k + 1], w = wv[k];
        E += w * r0 * r0 + w * r1 * r1;
        const T g0 = T(2) * w * r0, g1 = T(2) * w * r1;
        const T Jx[6] = {T(0), s * Y[2], -s * Y[1], P0 - t[0], T(1), T(0)};
        const T Jy[6] = {-s * Y[2], T(0), s * Y[0], P1 - t[1], T(0), T(1)};
        for (int i = 0; i < 6; ++i) {
            g[i] += g0 * Jx[i] + g1 * Jy[i];
            for (int j = 0; j < 6; ++j)
                H[6 * i + j] += T(2) * w * (Jx[i] * Jx[j] + Jy[i] * Jy[j]);
        }
    }
}

// R <- rows of scaled_stiefel((exp([omega]x) R)[:2]) normalised and completed; false for a rank < 2 block.
template <typename T> bool retract_rotation(const T *R, const T *omega, T *out)
{
    T A[9], M[6];
    axis_angle(omega, A);
    for (int i = 0; i < 2; ++i)
        for (int j = 0; j < 3; ++j)
            M[3 * i + j] = A[3 * i] * R[j] + A[3 * i + 1] * R[3 + j] + A[3 * i + 2] * R[6 + j];
    const T a = M[0] * M[0] + M[1] * M[1] + M[2] * M[2];
    const T b = M[0] * M[3] + M[1] * M[4] + M[2] * M[5];
    const T d = M[3] * M[3] + M[4] * M[4] + M[5] * M[5];
    const T det = a * d - b * b;
    const T delta = std::sqrt(det > T(0) ? det : T(0));
    if (!(delta > T(1e-10) * (a + d)))
        return false;
    T rows[6];
    for (int j = 0; j < 3; ++j) {
        rows[j] = ((d + delta) * M[j] - b * M[3 + j]) / (T(2) * delta);
        rows[3 + j] = (-b * M[j] + (a + delta) * M[3 + j]) / (T(2) * delta);
    }
    const T n0 = std::sqrt(rows[0] * rows[0] + rows[1] * rows[1] + rows[2] * rows[2]);
    for (int j = 0; j < 6; ++j)
        out[j] = rows[j] / n0;
    out[6] = out[1] * out[5] - out[2] * out[4];
    out[7] = out[2] * out[3] - out[0] * out[5];
    out[8] = out[0] * out[4] - out[1] * out[3];
    return true;
}

// Solve the 6 x 6 system A x = b (double, partial pivoting); false on a zero pivot.
inline bool solve6(double *A, double *b)
{
    for (int c = 0; c < 6; ++c) {
        int p = c;
        for (int i = c + 1; i < 6; ++i)
            if (std::fabs(A[6 * i + c]) > std::fabs(A[6 * p + c]))
                p = i;
        if (!(A[6 * p + c] != 0.0))
            return false;
        if (p != c) {
            for (int j = 0; j < 6; ++j)
                std::swap(A[6 * c + j], A[6 * p + j]);
            std::swap(b[c], b[p]);
        }
        for (int i = c + 1; i < 6; ++i) {
            const double f = A[6 * i + c] / A[6 * c + c];
            for (int j = c; j < 6; ++j)
                A[6 * i + j] -= f * A[6 * c + j];
            b[i] -= f * b[c];
        }
    }
    for (int c = 5; c >= 0; --c) {
        double v = b[c];
        for (int j = c + 1; j < 6; ++j)
            v -= A[6 * c + j] * b[j];
        b[c] = v / A[6 * c + c];
    }
    return true;
}

// One camera's fit. R (9), s, t (2) updated; writes E_before, E, converged; returns the iterations in which
// it was active, or -1 where the torch code must run instead (a rank < 2 block in a retraction).
template <typename T>
int64_t fit_camera(T *R, T &s, T *t, const T *S, const T *kp, const T *wv, int64_t K, int64_t max_iters,
                   double tol, T &E_before, T &E_out, bool &converged)
{
    T E, g[6], H[36];
    terms(R, s, t, S, kp, wv, K, E, g, H);
    E_before = E;
    T mu = T(1e-3);
    bool active = std::isfinite(E);
    converged = false;
    int64_t last = 0;
    for (int64_t it = 1; it <= max_iters && active; ++it) {
        double A[36], x[6], mean = 0.0;
        for (int i = 0; i < 6; ++i)
            mean += (double)H[7 * i];
        const double ridge = 1e-6 * (mean / 6.0) + 1e-12;
        for (int i = 0; i < 36; ++i)
            A[i] = (double)H[i];
        for (int i = 0; i < 6; ++i) {
            A[7 * i] += (double)mu * ((double)H[7 * i] + ridge);
            x[i] = (double)g[i];
        }
        T delta[6] = {T(0), T(0), T(0), T(0), T(0), T(0)};
        if (solve6(A, x)) {
            bool finite = true;
            for (int i = 0; i < 6; ++i) {
                delta[i] = (T)(-x[i]);
                finite = finite && std::isfinite(delta[i]);
            }
            if (!finite)
                for (int i = 0; i < 6; ++i)
                    delta[i] = T(0);
        }
        T Rt[9], tt[2], Et, gt[6], Ht[36];
        if (!retract_rotation(R, delta, Rt))
            return -1;
        const T st = s * std::exp(delta[3]);
        tt[0] = t[0] + delta[4];
        tt[1] = t[1] + delta[5];
        terms(Rt, st, tt, S, kp, wv, K, Et, gt, Ht);
        const bool accept = std::isfinite(Et) && Et <= E;
        const bool small = accept && (E - Et) <= (T)tol * E;
        if (accept) {
            for (int i = 0; i < 9; ++i)
                R[i] = Rt[i];
            s = st;
            t[0] = tt[0];
            t[1] = tt[1];
            E = Et;
            for (int i = 0; i < 6; ++i)
                g[i] = gt[i];
            for (int i = 0; i < 36; ++i)
                H[i] = Ht[i];
        }
        mu = accept ? mu / T(3) : mu * T(4);
        last = it;
        if (small || mu > T(1e8)) {
            converged = true;
            active = false;
        }
    }
    E_out = E;
    return last;
}

} // namespace carvi_fit
