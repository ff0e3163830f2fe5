// A single SO(3) body's implicit DEL step in C++, one trajectory at a time (engines/native.py builds and
// loads it). The step is `engines/scalar.py`'s, term by term: the residual const + F W.flatten() and its
// Jacobian JT W.flatten() from the linear maps of `RolloutMaps.linear` (a body with no force or constant
// Rayleigh damping has a residual linear in the increment W), the constant part C W_prev + the
// potential's covector -h dV at g_k (an MLP of R's entries with exact GELU or tanh layers, and uniform
// gravity terms a x (R^T f)), the 3x3 solve from the adjugate, the retraction W exp(hat(delta)) in closed
// form, the warm start from the last three increments (`lie.batched.extrapolate_increments`), one
// Newton-Schulz step and g_{k+1} = g_k W. The Newton loop is the reference loop of solvers/newton.py
// (backtracking on ||r||_2, convergence on the full step's max norm, a failed step kept and flagged), with
// one difference: an exactly singular Jacobian takes no step (the row's iteration fails) instead of a
// least-squares step.
//
// Row-major float64; a pose or increment is its 9 rotation entries.
#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

namespace {

constexpr double TRUST = 0.5;  // lie.batched.TRUST
constexpr int HISTORY = 3;     // lie.batched.HISTORY
const double INV_SQRT2 = 1.0 / std::sqrt(2.0);
const double INV_SQRT2PI = 1.0 / std::sqrt(2.0 * M_PI);

struct Spec {
    const double *F, *JT, *C;  // (3, 9), (9, 9), (3, 9): rows applied to W.flatten()
    int layers;                // hidden layers of the MLP potential (0: none)
    const int64_t *width;      // (layers + 1): 9, then each hidden layer's width
    const double *weights, *weights_t, *biases, *out;  // the hidden layers' (out, in) weights, the same
                                                       // transposed (in, out), biases, concatenated;
                                           // the output layer's weights times -h
    const int64_t *act;                    // per hidden layer: 0 GELU (exact), 1 tanh
    int n_grav;
    const double *grav_a, *grav_f;  // (n_grav, 3) each: covector += a x (R^T f)
    double step_tol;
    int max_iter, max_halvings;
};

inline void mul3(const double *A, const double *B, double *C) {  // C = A B
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}
inline void mul3_tn(const double *A, const double *B, double *C) {  // C = A^T B
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[3 * i + j] = A[i] * B[j] + A[3 + i] * B[3 + j] + A[6 + i] * B[6 + j];
}
inline void mul3_nt(const double *A, const double *B, double *C) {  // C = A B^T
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[3 * i] * B[3 * j] + A[3 * i + 1] * B[3 * j + 1] + A[3 * i + 2] * B[3 * j + 2];
}
// y (k) = M (k, 9) x (9), each entry summed left to right from 0 (`scalar._apply`)
inline void apply(const double *M, int k, const double *x, double *y) {
    for (int i = 0; i < k; ++i) {
        double s = 0.0;
        for (int j = 0; j < 9; ++j) s += M[9 * i + j] * x[j];
        y[i] = s;
    }
}

// -h dV(R exp(eta))/d eta at 0 of the potential (`scalar._Potential.covector` + the gravity terms), c (3)
void covector(const Spec &s, const double *R, std::vector<double> &a, std::vector<double> &z,
              std::vector<double> &slopes, std::vector<double> &gr, double *c) {
    c[0] = c[1] = c[2] = 0.0;
    if (s.layers) {
        // forward: the activations of every hidden layer, keeping each one's slope
        const double *W = s.weights, *b = s.biases;
        std::memcpy(a.data(), R, 9 * sizeof(double));
        int in = 9, off = 0;
        for (int l = 0; l < s.layers; ++l) {
            int out = (int)s.width[l + 1];
            // z_i = sum_j W_ij a_j summed over j in order, for all i at once (the transposed weights: the
            // inner loop runs over i, contiguous and independent, so it vectorises with the same sums)
            const double *Wt = s.weights_t + (W - s.weights);
            std::fill(z.begin(), z.begin() + out, 0.0);
            for (int j = 0; j < in; ++j) {
                const double aj = a[j], *row = &Wt[j * out];
                for (int i = 0; i < out; ++i) z[i] += row[i] * aj;
            }
            for (int i = 0; i < out; ++i) z[i] += b[i];
            double *sl = &slopes[off];
            for (int i = 0; i < out; ++i) {
                double v = z[i];
                if (s.act[l] == 0) {
                    double cdf = 0.5 * std::erf(v * INV_SQRT2) + 0.5;
                    a[i] = v * cdf;
                    sl[i] = cdf + v * std::exp(-0.5 * v * v) * INV_SQRT2PI;
                } else {
                    double t = std::tanh(v);
                    a[i] = t;
                    sl[i] = 1.0 - t * t;
                }
            }
            W += out * in, b += out, off += out, in = out;
        }
        // backward: d(-h V)/d(R entries) through the layers in reverse
        std::memcpy(gr.data(), s.out, in * sizeof(double));
        for (int l = s.layers - 1; l >= 0; --l) {
            int out = (int)s.width[l + 1], inl = (int)s.width[l];
            off -= out;
            W -= out * inl;
            const double *sl = &slopes[off];
            for (int i = 0; i < out; ++i) z[i] = sl[i] * gr[i];
            // gr_j = sum_i W_ij z_i summed over i in order, for all j at once (rows of W, contiguous)
            std::fill(gr.begin(), gr.begin() + inl, 0.0);
            for (int i = 0; i < out; ++i) {
                const double zi = z[i], *row = &W[i * inl];
                for (int j = 0; j < inl; ++j) gr[j] += row[j] * zi;
            }
        }
        // sum over rows k of dR_k x R_k
        for (int k = 0; k < 3; ++k) {
            const double *d = &gr[3 * k], *r = &R[3 * k];
            c[0] += d[1] * r[2] - d[2] * r[1];
            c[1] += d[2] * r[0] - d[0] * r[2];
            c[2] += d[0] * r[1] - d[1] * r[0];
        }
    }
    for (int j = 0; j < s.n_grav; ++j) {
        const double *av = &s.grav_a[3 * j], *f = &s.grav_f[3 * j];
        double u[3] = {R[0] * f[0] + R[3] * f[1] + R[6] * f[2], R[1] * f[0] + R[4] * f[1] + R[7] * f[2],
                       R[2] * f[0] + R[5] * f[1] + R[8] * f[2]};  // R^T f
        c[0] += av[1] * u[2] - av[2] * u[1];
        c[1] += av[2] * u[0] - av[0] * u[2];
        c[2] += av[0] * u[1] - av[1] * u[0];
    }
}

// W exp(hat(d)) (`scalar._retract`)
inline void retract(const double *W, const double *d, double *out) {
    double t = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    t = std::max(t, DBL_MIN);
    double sinc = std::sin(t) / t, sh = std::sin(0.5 * t) / t, cosc = 2.0 * sh * sh, c = std::cos(t);
    double x = d[0], y = d[1], z = d[2];
    double E[9] = {c + cosc * x * x,        cosc * x * y - sinc * z, cosc * x * z + sinc * y,
                   cosc * y * x + sinc * z, c + cosc * y * y,        cosc * y * z - sinc * x,
                   cosc * z * x - sinc * y, cosc * z * y + sinc * x, c + cosc * z * z};
    mul3(W, E, out);
}

// the warm start from the last L increments, oldest first (`scalar._extrapolate`)
void extrapolate(const double *hist, int L, double *out) {
    const double *W = &hist[9 * (L - 1)];
    if (L == 1) {
        std::memcpy(out, W, 9 * sizeof(double));
        return;
    }
    double E[9], D[9], T[9], E3[9];
    mul3_nt(W, &hist[9 * (L - 2)], E);
    if (L == 3) {  // E D'^T E with D' = W_1 W_2^T
        mul3_nt(&hist[9], &hist[0], D);
        mul3_nt(E, D, T);
        mul3(T, E, E3);
        std::memcpy(E, E3, sizeof E);
    }
    bool ok = 3.0 - (E[0] + E[4] + E[8]) <= TRUST * TRUST * (3.0 - (W[0] + W[4] + W[8]));  // NaN: false
    if (ok)
        mul3(E, W, out);
    else
        std::memcpy(out, W, 9 * sizeof(double));
}

inline double norm3(const double *r) { return std::sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]); }

}  // namespace

extern "C" {

// Roll `count` steps of N trajectories on from their state, in place: R (N, 9) the pose g_k, hist (N, 3, 9)
// the last increments g_{j}^{-1} g_{j+1}, oldest first, hist_len (N) how many (1 to 3; the last one is
// g_{k-1}^{-1} g_k). Writes the poses g_{k+1}... (N, count, 9) and per step converged (N, count), Newton
// iterations (N, count) and the residual's max norm (N, count). `threads` > 1 splits the rows over that
// many threads (each row's result does not depend on it). Returns 0.
int liedfl_so3_rollout(int64_t N, int64_t count, const double *F, const double *JT, const double *C, int64_t layers,
                       const int64_t *width, const double *weights, const double *weights_t, const double *biases, const int64_t *act,
                       const double *out_w, int64_t n_grav, const double *grav_a, const double *grav_f,
                       double step_tol, int64_t max_iter, int64_t max_halvings, double *R, double *hist,
                       int64_t *hist_len, double *outR, uint8_t *converged, int64_t *iterations,
                       double *residual_norm, int64_t threads) {
    Spec s{F,     JT,     C,    (int)layers, width, weights, weights_t, biases, out_w, act, (int)n_grav, grav_a, grav_f,
           step_tol, (int)max_iter, (int)max_halvings};
    int wmax = 9;
    int total = 0;
    for (int l = 0; l < layers; ++l) wmax = std::max(wmax, (int)width[l + 1]), total += (int)width[l + 1];
    const double big = std::numeric_limits<double>::max();
    auto rows = [&](int64_t i0, int64_t i1) {
        std::vector<double> a(wmax), z(wmax), slopes(std::max(total, 1)), gr(wmax);
        for (int64_t i = i0; i < i1; ++i) {
            double *g = R + 9 * i, *hi = hist + 27 * i;
            int L = (int)hist_len[i];
            for (int64_t k = 0; k < count; ++k) {
                double cov[3], cst[3], W[9], r[3], J[9], cand[9], rc[3], delta[3], dd[3];
                covector(s, g, a, z, slopes, gr, cov);
                apply(s.C, 3, &hi[9 * (L - 1)], cst);
                for (int q = 0; q < 3; ++q) cst[q] += cov[q];
                extrapolate(hi, L, W);
                apply(s.F, 3, W, r);
                for (int q = 0; q < 3; ++q) r[q] += cst[q];
                double rn = norm3(r);
                bool conv = false;
                int it = 0;
                for (; it < s.max_iter && !conv; ++it) {
                    apply(s.JT, 9, W, J);
                    const double *ra = &J[0], *rb = &J[3], *rcw = &J[6];
                    double adj[9] = {
                        rb[1] * rcw[2] - rb[2] * rcw[1], rb[2] * rcw[0] - rb[0] * rcw[2], rb[0] * rcw[1] - rb[1] * rcw[0],
                        rcw[1] * ra[2] - rcw[2] * ra[1], rcw[2] * ra[0] - rcw[0] * ra[2], rcw[0] * ra[1] - rcw[1] * ra[0],
                        ra[1] * rb[2] - ra[2] * rb[1],   ra[2] * rb[0] - ra[0] * rb[2],   ra[0] * rb[1] - ra[1] * rb[0]};
                    double det = ra[0] * adj[0] + ra[1] * adj[1] + ra[2] * adj[2];
                    bool singular = det == 0.0;
                    for (int q = 0; q < 3; ++q)
                        delta[q] = singular ? 0.0 : -(adj[q] * r[0] + adj[3 + q] * r[1] + adj[6 + q] * r[2]) / det;
                    if (!(std::isfinite(delta[0]) && std::isfinite(delta[1]) && std::isfinite(delta[2]))) {
                        singular = true;  // no step on this iteration (the step fails)
                        delta[0] = delta[1] = delta[2] = 0.0;
                    }
                    double full = std::max(std::fabs(delta[0]), std::max(std::fabs(delta[1]), std::fabs(delta[2])));
                    // backtracking on ||r||_2 (solvers.newton._careful_iteration); without a decrease the full
                    // step is taken where its residual is finite
                    double alpha = 1.0;
                    bool accepted = false;
                    for (int hh = 0; hh <= s.max_halvings; ++hh) {
                        for (int q = 0; q < 3; ++q) dd[q] = alpha * delta[q];
                        retract(W, dd, cand);
                        apply(s.F, 3, cand, rc);
                        for (int q = 0; q < 3; ++q) rc[q] += cst[q];
                        double rcn = norm3(rc);
                        if (std::isfinite(rcn) && rcn <= std::fmin(rn * (1 - 1e-4 * alpha) + 1e-300, big)) {
                            accepted = true;
                            std::memcpy(W, cand, sizeof W);
                            std::memcpy(r, rc, sizeof r);
                            rn = rcn;
                            break;
                        }
                        alpha *= 0.5;
                    }
                    if (!accepted) {
                        retract(W, delta, cand);
                        apply(s.F, 3, cand, rc);
                        for (int q = 0; q < 3; ++q) rc[q] += cst[q];
                        double rcn = norm3(rc);
                        if (std::isfinite(rcn)) {
                            std::memcpy(W, cand, sizeof W);
                            std::memcpy(r, rc, sizeof r);
                            rn = rcn;
                        }
                    }
                    conv = !singular && full <= s.step_tol && std::isfinite(rn);
                }
                double rmax = 0.0;
                bool rnan = false;
                for (int q = 0; q < 3; ++q) rmax = std::fmax(rmax, std::fabs(r[q])), rnan = rnan || std::isnan(r[q]);
                converged[i * count + k] = conv ? 1 : 0;
                iterations[i * count + k] = it;
                residual_norm[i * count + k] = rnan ? std::numeric_limits<double>::quiet_NaN() : rmax;
                // the increment re-orthonormalised by one Newton-Schulz step, g_{k+1} = g_k W
                double M[9], Wn[9], gn[9];
                mul3_tn(W, W, M);
                for (int q = 0; q < 9; ++q) M[q] = (q % 4 == 0 ? 3.0 : 0.0) - M[q];
                mul3(W, M, Wn);
                for (int q = 0; q < 9; ++q) Wn[q] *= 0.5;
                mul3(g, Wn, gn);
                std::memcpy(g, gn, sizeof gn);
                std::memcpy(outR + (i * count + k) * 9, gn, sizeof gn);
                if (L == HISTORY) {
                    std::memmove(hi, hi + 9, 9 * (HISTORY - 1) * sizeof(double));
                    --L;
                }
                std::memcpy(&hi[9 * L], Wn, sizeof Wn);
                ++L;
            }
            hist_len[i] = L;
        }
    };
    int64_t T = std::max<int64_t>(1, std::min<int64_t>(threads, N / 16));  // >= 16 rows per thread
    if (T == 1) {
        rows(0, N);
        return 0;
    }
    std::vector<std::thread> pool;
    for (int64_t k = 1; k < T; ++k) pool.emplace_back(rows, N * k / T, N * (k + 1) / T);
    rows(0, N / T);
    for (std::thread &th : pool) th.join();
    return 0;
}
}
