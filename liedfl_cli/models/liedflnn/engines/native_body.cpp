// A single rigid body's implicit DEL step in C++, one trajectory at a time (engines/native.py builds and
// loads it), on SO(3) (`liedfl_so3_rollout`) and on SE(3) (`liedfl_se3_rollout`).
//
// SO(3): the step of `engines/scalar.py`, term by term: the residual const + F W.flatten() and its Jacobian
// JT W.flatten() from the linear maps of `RolloutMaps.linear` (a body with no force or constant Rayleigh
// damping has a residual linear in the increment W), the constant part C W_prev + the potential's covector
// -h dV at g_k, the 3x3 solve from the adjugate, the retraction W exp(hat(delta)) in closed form.
// SE(3): the fused row step of `engines/rollout.py` (`FusedStep` without per-iteration forces): the kinetic
// d1 / d2 terms (rotational parts from their linear maps), constant Rayleigh damping on the velocity estimate,
// the kinetic block of the Jacobian linear in W, a 6x6 LU solve, the retraction (W, z) exp(delta).
// Both: the potential's covector from an MLP of the pose's entries (exact GELU or tanh layers) and uniform
// gravity terms; the warm start from the last three increments (`lie.batched.extrapolate_increments`); one
// Newton-Schulz step of the increment's rotation and g_{k+1} = g_k inc. The Newton loop is the reference loop
// of solvers/newton.py (backtracking on ||r||_2, convergence on the full step's max norm, a failed step kept
// and flagged), with one difference: an exactly singular Jacobian takes no step (the row's iteration fails)
// instead of a least-squares step.
//
// Row-major float64; a rotation is its 9 entries, an SE(3) pose or increment its 9 rotation entries then its
// 3 translation entries.
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
    const double *grav_a, *grav_f, *grav_m;  // (n_grav, 3), (n_grav, 3), (n_grav,): covector += (a x (R^T f),
                                             // m R^T f) (the translational part on SE(3) only)
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

// -h dV(g exp(eta))/d eta at 0 of the potential (`scalar._Potential.covector`, `mlp_derivatives.left_covector`
// and the gravity terms' `left_gradient`), c (3) on SO(3) (p null), (6) on SE(3) (the MLP's input then (R, p))
void covector(const Spec &s, const double *R, const double *p, std::vector<double> &a, std::vector<double> &z,
              std::vector<double> &slopes, std::vector<double> &gr, double *c) {
    const int dim = p ? 6 : 3;
    for (int q = 0; q < dim; ++q) c[q] = 0.0;
    if (s.layers) {
        // forward: the activations of every hidden layer, keeping each one's slope
        const double *W = s.weights, *b = s.biases;
        std::memcpy(a.data(), R, 9 * sizeof(double));
        if (p) std::memcpy(&a[9], p, 3 * sizeof(double));
        int in = (int)s.width[0], off = 0;
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
        // sum over rows k of dR_k x R_k; on SE(3) R^T dp
        for (int k = 0; k < 3; ++k) {
            const double *d = &gr[3 * k], *r = &R[3 * k];
            c[0] += d[1] * r[2] - d[2] * r[1];
            c[1] += d[2] * r[0] - d[0] * r[2];
            c[2] += d[0] * r[1] - d[1] * r[0];
        }
        if (p)
            for (int i = 0; i < 3; ++i) c[3 + i] = R[i] * gr[9] + R[3 + i] * gr[10] + R[6 + i] * gr[11];
    }
    for (int j = 0; j < s.n_grav; ++j) {
        const double *av = &s.grav_a[3 * j], *f = &s.grav_f[3 * j];
        double u[3] = {R[0] * f[0] + R[3] * f[1] + R[6] * f[2], R[1] * f[0] + R[4] * f[1] + R[7] * f[2],
                       R[2] * f[0] + R[5] * f[1] + R[8] * f[2]};  // R^T f
        c[0] += av[1] * u[2] - av[2] * u[1];
        c[1] += av[2] * u[0] - av[0] * u[2];
        c[2] += av[0] * u[1] - av[1] * u[0];
        if (p)
            for (int i = 0; i < 3; ++i) c[3 + i] += s.grav_m[j] * u[i];
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

// ---------------------------------------------------------------------------- a single SE(3) body
constexpr double TAYLOR2 = 1e-2;  // (lie.tolerances float64 "taylor" = 0.1)^2: series below it

inline double poly(double x, const double *c, int k) {
    double out = c[k - 1];
    for (int i = k - 2; i >= 0; --i) out = out * x + c[i];
    return out;
}
// sin(t)/t, 2 sin^2(t/2)/t^2, (t - sin t)/t^3 of t^2 (`lie.batched.exp_coefficients`)
inline double sinc(double t2) {
    static const double c[] = {1.0, -1.0 / 6, 1.0 / 120, -1.0 / 5040, 1.0 / 362880};
    if (t2 < TAYLOR2) return poly(t2, c, 5);
    double t = std::sqrt(t2);
    return std::sin(t) / t;
}
inline double cosc(double t2) {
    static const double c[] = {0.5, -1.0 / 24, 1.0 / 720, -1.0 / 40320, 1.0 / 3628800};
    if (t2 < TAYLOR2) return poly(t2, c, 5);
    double s = std::sin(0.5 * std::sqrt(t2));
    return 2.0 * s * s / t2;
}
inline double sinc3(double t2) {
    static const double c[] = {1.0 / 6, -1.0 / 120, 1.0 / 5040, -1.0 / 362880, 1.0 / 39916800};
    if (t2 < TAYLOR2) return poly(t2, c, 5);
    double t = std::sqrt(t2);
    return (t - std::sin(t)) / (t2 * t);
}
// `engines/rollout.py`'s fused step of one SE(3) body (no linear maps: the residual is not linear in the
// increment x = (W, z)): r = const + kinetic_d1(x) + (h/2) (-D xi~(x)), J = the kinetic block (linear in W,
// `RolloutMaps.se3_block`) + (h/2) (-D) dxi~/d delta, const = kinetic_d2(x_prev) + (h/2) (-D xi~(x_prev)) + the
// potential's covector at g_k.
struct Body {
    const double *d1, *d2, *hess, *rho, *D;  // (3, 9), (3, 9), (36, 9) rows applied to W.flatten(); (3); (6, 6) or null
    double s, h;                            // m / h, h
};

inline void cross3(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

// kinetic_d1 (second = false) or kinetic_d2 of the increment (W, z): c (6)
void se3_kinetic(const Body &b, const double *W, const double *z, bool second, double *c) {
    double Wr[3], X[3], u[3], cu[3];
    apply(second ? b.d2 : b.d1, 3, W, c);
    for (int i = 0; i < 3; ++i) Wr[i] = W[3 * i] * b.rho[0] + W[3 * i + 1] * b.rho[1] + W[3 * i + 2] * b.rho[2];
    for (int i = 0; i < 3; ++i) X[i] = z[i] + Wr[i] - b.rho[i];
    if (second) {  // w += s rho x W^T X, v = s W^T X
        for (int i = 0; i < 3; ++i) u[i] = W[i] * X[0] + W[3 + i] * X[1] + W[6 + i] * X[2];
        cross3(b.rho, u, cu);
        for (int i = 0; i < 3; ++i) c[i] += b.s * cu[i], c[3 + i] = b.s * u[i];
    } else {  // w += s X x (z + W rho), v = -s X
        for (int i = 0; i < 3; ++i) u[i] = z[i] + Wr[i];
        cross3(X, u, cu);
        for (int i = 0; i < 3; ++i) c[i] += b.s * cu[i], c[3 + i] = -b.s * X[i];
    }
}

// r (6) += (h/2) (-D xi~(W, z)), xi~ = (vee(W) / h, (z - h/2 w~ x z) / h) (`kinetic.velocity_estimate`)
void se3_damping_add(const Body &b, const double *W, const double *z, double *r) {
    if (!b.D) return;
    double xi[6], wz[3];
    xi[0] = 0.5 * (W[7] - W[5]) / b.h, xi[1] = 0.5 * (W[2] - W[6]) / b.h, xi[2] = 0.5 * (W[3] - W[1]) / b.h;
    cross3(xi, z, wz);
    for (int i = 0; i < 3; ++i) xi[3 + i] = (z[i] - 0.5 * b.h * wz[i]) / b.h;
    for (int i = 0; i < 6; ++i) {
        double acc = 0.0;
        for (int j = 0; j < 6; ++j) acc += b.D[6 * i + j] * xi[j];
        r[i] += 0.5 * b.h * -acc;
    }
}

// J (6x6) = the kinetic block at W + (h/2) (-D) dxi~/d delta (`rollout.step_jacobian`,
// `velocity_jacobian_blocks`: [[dw, 0], [hat(z) dw / 2, (I - h/2 hat(w~)) W / h]], dw = (tr W I - W^T) / (2h))
void se3_jacobian(const Body &b, const double *W, const double *z, double *J) {
    apply(b.hess, 36, W, J);
    if (!b.D) return;
    const double h = b.h, tr = W[0] + W[4] + W[8];
    double dw[9], A[36] = {0};
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) dw[3 * i + j] = ((i == j ? tr : 0.0) - W[3 * j + i]) / (2 * h);
    double w[3] = {0.5 * (W[7] - W[5]) / h, 0.5 * (W[2] - W[6]) / h, 0.5 * (W[3] - W[1]) / h};
    double Hz[9] = {0, -z[2], z[1], z[2], 0, -z[0], -z[1], z[0], 0};
    double M[9] = {1, 0.5 * h * w[2], -0.5 * h * w[1], -0.5 * h * w[2], 1, 0.5 * h * w[0],
                   0.5 * h * w[1], -0.5 * h * w[0], 1};  // I - h/2 hat(w)
    double dvw[9], dvv[9];
    mul3(Hz, dw, dvw);
    mul3(M, W, dvv);
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            A[6 * i + j] = dw[3 * i + j];
            A[6 * (3 + i) + j] = 0.5 * dvw[3 * i + j];
            A[6 * (3 + i) + 3 + j] = dvv[3 * i + j] / h;
        }
    for (int i = 0; i < 6; ++i)
        for (int j = 0; j < 6; ++j) {
            double acc = 0.0;
            for (int k = 0; k < 6; ++k) acc += b.D[6 * i + k] * A[6 * k + j];
            J[6 * i + j] += 0.5 * h * -acc;
        }
}

// (W, z) exp(delta): W exp(w), z + W V(w) v (`lie.batched.group_retract`)
void se3_retract(const double *W, const double *z, const double *d, double *Wo, double *zo) {
    const double *w = d, *v = d + 3;
    double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    double c0 = sinc(t2), c1 = cosc(t2), c2 = sinc3(t2);
    double H[9] = {0, -w[2], w[1], w[2], 0, -w[0], -w[1], w[0], 0}, H2[9], E[9], V[9], Vv[3];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) H2[3 * i + j] = w[i] * w[j] - (i == j ? t2 : 0.0);  // hat(w)^2
    for (int k = 0; k < 9; ++k) {
        double I = (k % 4 == 0) ? 1.0 : 0.0;
        E[k] = I + c0 * H[k] + c1 * H2[k];
        V[k] = I + c1 * H[k] + c2 * H2[k];
    }
    for (int i = 0; i < 3; ++i) Vv[i] = V[3 * i] * v[0] + V[3 * i + 1] * v[1] + V[3 * i + 2] * v[2];
    mul3(W, E, Wo);
    for (int i = 0; i < 3; ++i) zo[i] = z[i] + W[3 * i] * Vv[0] + W[3 * i + 1] * Vv[1] + W[3 * i + 2] * Vv[2];
}

// a b and a^-1 of poses (R 9, p 3) as one array of 12
inline void pose_mul(const double *a, const double *b, double *c) {
    mul3(a, b, c);
    for (int i = 0; i < 3; ++i) c[9 + i] = a[9 + i] + a[3 * i] * b[9] + a[3 * i + 1] * b[10] + a[3 * i + 2] * b[11];
}
inline void pose_inv(const double *a, double *c) {
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) c[3 * i + j] = a[3 * j + i];
    for (int i = 0; i < 3; ++i) c[9 + i] = -(a[i] * a[9] + a[3 + i] * a[10] + a[6 + i] * a[11]);
}

// the warm start from the last L increments (R, z) of 12, oldest first (`lie.batched.extrapolate_increments`)
void se3_extrapolate(const double *hist, int L, double *out) {
    const double *last = &hist[12 * (L - 1)];
    if (L == 1) {
        std::memcpy(out, last, 12 * sizeof(double));
        return;
    }
    double inv[12], E[12], Dp[12], T[12], guess[12];
    pose_inv(&hist[12 * (L - 2)], inv);
    pose_mul(last, inv, E);
    if (L == 3) {
        pose_inv(&hist[0], inv);
        pose_mul(&hist[12], inv, Dp);
        pose_inv(Dp, inv);
        pose_mul(E, inv, T);
        pose_mul(T, E, Dp);
        std::memcpy(E, Dp, sizeof E);
    }
    pose_mul(E, last, guess);
    const double t2 = TRUST * TRUST;
    bool ok = 3.0 - (E[0] + E[4] + E[8]) <= t2 * (3.0 - (last[0] + last[4] + last[8]));
    double dp2 = 0.0, p2 = 0.0;
    for (int i = 0; i < 3; ++i) dp2 += (guess[9 + i] - last[9 + i]) * (guess[9 + i] - last[9 + i]), p2 += last[9 + i] * last[9 + i];
    ok = ok && dp2 <= t2 * p2;  // NaN: false
    std::memcpy(out, ok ? guess : last, 12 * sizeof(double));
}

// LU with partial pivoting of a 6x6 in place; false on an exactly zero pivot
bool lu6(double *A, int *piv) {
    bool ok = true;
    for (int k = 0; k < 6; ++k) {
        int p = k;
        double best = std::fabs(A[6 * k + k]);
        for (int i = k + 1; i < 6; ++i)
            if (std::fabs(A[6 * i + k]) > best) best = std::fabs(A[6 * i + k]), p = i;
        piv[k] = p;
        if (p != k)
            for (int j = 0; j < 6; ++j) std::swap(A[6 * k + j], A[6 * p + j]);
        if (A[6 * k + k] == 0.0) {
            ok = false;
            continue;
        }
        for (int i = k + 1; i < 6; ++i) {
            double l = A[6 * i + k] / A[6 * k + k];
            A[6 * i + k] = l;
            for (int j = k + 1; j < 6; ++j) A[6 * i + j] -= l * A[6 * k + j];
        }
    }
    return ok;
}
void lu6_solve(const double *A, const int *piv, double *x) {
    for (int k = 0; k < 6; ++k)
        if (piv[k] != k) std::swap(x[k], x[piv[k]]);
    for (int i = 1; i < 6; ++i)
        for (int k = 0; k < i; ++k) x[i] -= A[6 * i + k] * x[k];
    for (int i = 5; i >= 0; --i) {
        for (int k = i + 1; k < 6; ++k) x[i] -= A[6 * i + k] * x[k];
        x[i] /= A[6 * i + i];
    }
}

inline double norm6(const double *r) {
    double s = 0.0;
    for (int q = 0; q < 6; ++q) s += r[q] * r[q];
    return std::sqrt(s);
}

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
                       const double *grav_m, double step_tol, int64_t max_iter, int64_t max_halvings, double *R, double *hist,
                       int64_t *hist_len, double *outR, uint8_t *converged, int64_t *iterations,
                       double *residual_norm, int64_t threads) {
    Spec s{F,     JT,     C,        (int)layers, width,         weights,           weights_t, biases, out_w, act,
           (int)n_grav, grav_a, grav_f, grav_m, step_tol, (int)max_iter, (int)max_halvings};
    int wmax = 12;
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
                covector(s, g, nullptr, a, z, slopes, gr, cov);
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
// Roll `count` steps of N trajectories of one SE(3) body on from their state, in place: R (N, 9), p (N, 3) the
// pose g_k, hist (N, 3, 12) the last increments (W, z), oldest first, hist_len (N) how many. Writes the poses
// (N, count, 9) / (N, count, 3) and per step converged, Newton iterations and the residual's max norm
// (N, count). The body: d1, d2 (3, 9), hess (36, 9), rho (3), mass, D (6, 6) when damped; the potential as for
// `liedfl_so3_rollout` (the MLP's input (R, p), 12 wide). `threads` as there. Returns 0.
int liedfl_se3_rollout(int64_t N, int64_t count, const double *d1, const double *d2, const double *hess,
                       const double *rho, double mass, int64_t damped, const double *D, double h, int64_t layers,
                       const int64_t *width, const double *weights, const double *weights_t, const double *biases,
                       const int64_t *act, const double *out_w, int64_t n_grav, const double *grav_a,
                       const double *grav_f, const double *grav_m, double tol, int64_t max_iter,
                       int64_t max_halvings, double *R, double *P, double *hist, int64_t *hist_len, double *outR,
                       double *outp, uint8_t *converged, int64_t *iterations, double *residual_norm,
                       int64_t threads) {
    Spec s{nullptr,     nullptr, nullptr, (int)layers, width, weights,        weights_t,          biases, out_w, act,
           (int)n_grav, grav_a,  grav_f,  grav_m,      tol,   (int)max_iter, (int)max_halvings};
    Body b{d1, d2, hess, rho, damped ? D : nullptr, mass / h, h};
    int wmax = 12, total = 0;
    for (int l = 0; l < layers; ++l) wmax = std::max(wmax, (int)width[l + 1]), total += (int)width[l + 1];
    const double big = std::numeric_limits<double>::max(), eps = std::numeric_limits<double>::epsilon();
    auto rows = [&](int64_t i0, int64_t i1) {
        std::vector<double> a(wmax), z(wmax), slopes(std::max(total, 1)), gr(wmax);
        for (int64_t i = i0; i < i1; ++i) {
            double *g = R + 9 * i, *gp = P + 3 * i, *hi = hist + 36 * i;
            int L = (int)hist_len[i];
            for (int64_t k = 0; k < count; ++k) {
                double cst[6], x[12], r[6], J[36], cand[12], rc[6], delta[6], dd[6];
                int piv[6];
                const double *prev = &hi[12 * (L - 1)];
                se3_kinetic(b, prev, prev + 9, true, cst);
                se3_damping_add(b, prev, prev + 9, cst);
                double cov[6];
                covector(s, g, gp, a, z, slopes, gr, cov);
                for (int q = 0; q < 6; ++q) cst[q] += cov[q];
                se3_extrapolate(hi, L, x);
                auto residual = [&](const double *y, double *out) {
                    se3_kinetic(b, y, y + 9, false, out);
                    for (int q = 0; q < 6; ++q) out[q] += cst[q];
                    se3_damping_add(b, y, y + 9, out);
                };
                residual(x, r);
                double rn = norm6(r);
                bool conv = false;
                int it = 0;
                for (; it < s.max_iter && !conv; ++it) {
                    double scale = std::max(std::fabs(x[9]), std::max(std::fabs(x[10]), std::fabs(x[11])));
                    double step_tol = std::fmax(tol, 16.0 * eps * std::fmax(scale, 1.0));  // newton.step_tolerance
                    se3_jacobian(b, x, x + 9, J);
                    bool singular = !lu6(J, piv);
                    for (int q = 0; q < 6; ++q) delta[q] = -r[q];
                    if (!singular) lu6_solve(J, piv, delta);
                    bool finite = !singular;
                    for (int q = 0; q < 6 && finite; ++q) finite = std::isfinite(delta[q]);
                    if (!finite) {  // no step on this iteration (the step fails)
                        singular = true;
                        std::fill(delta, delta + 6, 0.0);
                    }
                    double full = 0.0;
                    for (int q = 0; q < 6; ++q) full = std::fmax(full, std::fabs(delta[q]));
                    double alpha = 1.0;
                    bool accepted = false;
                    for (int hh = 0; hh <= s.max_halvings; ++hh) {
                        for (int q = 0; q < 6; ++q) dd[q] = alpha * delta[q];
                        se3_retract(x, x + 9, dd, cand, cand + 9);
                        residual(cand, rc);
                        double rcn = norm6(rc);
                        if (std::isfinite(rcn) && rcn <= std::fmin(rn * (1 - 1e-4 * alpha) + 1e-300, big)) {
                            accepted = true;
                            std::memcpy(x, cand, sizeof x);
                            std::memcpy(r, rc, sizeof r);
                            rn = rcn;
                            break;
                        }
                        alpha *= 0.5;
                    }
                    if (!accepted) {
                        se3_retract(x, x + 9, delta, cand, cand + 9);
                        residual(cand, rc);
                        double rcn = norm6(rc);
                        if (std::isfinite(rcn)) {
                            std::memcpy(x, cand, sizeof x);
                            std::memcpy(r, rc, sizeof r);
                            rn = rcn;
                        }
                    }
                    conv = !singular && full <= step_tol && std::isfinite(rn);
                }
                double rmax = 0.0;
                bool rnan = false;
                for (int q = 0; q < 6; ++q) rmax = std::fmax(rmax, std::fabs(r[q])), rnan = rnan || std::isnan(r[q]);
                converged[i * count + k] = conv ? 1 : 0;
                iterations[i * count + k] = it;
                residual_norm[i * count + k] = rnan ? std::numeric_limits<double>::quiet_NaN() : rmax;
                // the increment's rotation re-orthonormalised (one Newton-Schulz step), g_{k+1} = g_k (W, z)
                double M[9], inc[12], gn[12], gk[12];
                mul3_tn(x, x, M);
                for (int q = 0; q < 9; ++q) M[q] = (q % 4 == 0 ? 3.0 : 0.0) - M[q];
                mul3(x, M, inc);
                for (int q = 0; q < 9; ++q) inc[q] *= 0.5;
                std::memcpy(inc + 9, x + 9, 3 * sizeof(double));
                std::memcpy(gk, g, 9 * sizeof(double));
                std::memcpy(gk + 9, gp, 3 * sizeof(double));
                pose_mul(gk, inc, gn);
                std::memcpy(g, gn, 9 * sizeof(double));
                std::memcpy(gp, gn + 9, 3 * sizeof(double));
                std::memcpy(outR + (i * count + k) * 9, gn, 9 * sizeof(double));
                std::memcpy(outp + (i * count + k) * 3, gn + 9, 3 * sizeof(double));
                if (L == HISTORY) {
                    std::memmove(hi, hi + 12, 12 * (HISTORY - 1) * sizeof(double));
                    --L;
                }
                std::memcpy(&hi[12 * L], inc, sizeof inc);
                ++L;
            }
            hist_len[i] = L;
        }
    };
    int64_t T = std::max<int64_t>(1, std::min<int64_t>(threads, N / 16));
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
