// A rigid body's or a product of bodies' implicit DEL step in C++, one trajectory at a time (engines/native.py
// builds and loads it): one SO(3) body (`liedfl_so3_rollout`) and SE(3)^m x SO(3)^(B-m)
// (`liedfl_product_rollout`, one SE(3) body included).
//
// SO(3): the step of `engines/scalar.py`, term by term: the residual const + F W.flatten() and its Jacobian
// JT W.flatten() from the linear maps of `RolloutMaps.linear` (a body with no force or constant Rayleigh
// damping has a residual linear in the increment W), the constant part C W_prev + the potential's covector
// -h dV at g_k, the 3x3 solve from the adjugate, the retraction W exp(hat(delta)) in closed form.
// Products: the fused row step of `engines/rollout.py` (`FusedStep`, a learned force's value and Jacobian at every
// iteration as its `ForcesAt`): the kinetic
// d1 / d2 terms (rotational parts from their linear maps), constant Rayleigh damping on the velocity estimate,
// the kinetic blocks of the Jacobian linear in W, an LU solve, the retraction x exp(delta) body by body.
// Both: the potential's covector from an MLP of the pose's entries (exact GELU or tanh layers) and uniform
// gravity terms; the warm start from the last three increments (`lie.batched.extrapolate_increments`); one
// Newton-Schulz step of the increment's rotation and g_{k+1} = g_k inc. The Newton loop is the reference loop
// of solvers/newton.py (backtracking on ||r||_2, convergence on the full step's max norm, a failed step kept
// and flagged), with one difference: an exactly singular Jacobian takes no step (the row's iteration fails)
// instead of a least-squares step.
//
// Row-major float64; a rotation is its 9 entries, a product's pose or increment its bodies' rotation entries
// then its SE(3) bodies' translations.
#include <algorithm>
#include <cfloat>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

#include "native_math.hpp"

namespace {

using namespace liedfl_native;

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
    const double *grav_a, *grav_f, *grav_m;  // (n_grav, B, 3), (n_grav, 3), (n_grav, B): per body b the covector
                                             // += (a_b x (R_b^T f), m_b R_b^T f) (the second part on SE(3) only)
    double step_tol;
    int max_iter, max_halvings;
};

// y (k) = M (k, 9) x (9), each entry summed left to right from 0 (`scalar._apply`)
inline void apply(const double *M, int k, const double *x, double *y) {
    for (int i = 0; i < k; ++i) {
        double s = 0.0;
        for (int j = 0; j < 9; ++j) s += M[9 * i + j] * x[j];
        y[i] = s;
    }
}

// a (out) = act(z) for the hidden layer `l`'s activation (0 GELU, exact; 1 tanh), sl (out) its slope act'(z)
inline void activate(int64_t act, const double *z, int out, double *a, double *sl) {
    for (int i = 0; i < out; ++i) {
        double v = z[i];
        if (act == 0) {
            double cdf = 0.5 * std::erf(v * INV_SQRT2) + 0.5;
            a[i] = v * cdf;
            sl[i] = cdf + v * std::exp(-0.5 * v * v) * INV_SQRT2PI;
        } else {
            double t = std::tanh(v);
            a[i] = t;
            sl[i] = 1.0 - t * t;
        }
    }
}

// z (out) += Wt^T a, Wt (in, out) a layer's transposed weights: each z_i summed over j in order, for all i at once
// (the inner loop runs over i, contiguous and independent, so it vectorises with the same sums)
inline void accumulate(const double *Wt, const double *a, int in, int out, double *z) {
    for (int j = 0; j < in; ++j) {
        const double aj = a[j], *row = &Wt[j * out];
        for (int i = 0; i < out; ++i) z[i] += row[i] * aj;
    }
}

// -h dV(g exp(eta))/d eta at 0 of the potential (`scalar._Potential.covector`, `mlp_derivatives.left_covector`
// and the gravity terms' `left_gradient`) for B bodies, the first m of them SE(3): R (9 B), p (3 m); c (dim) in
// the group's tangent layout (per body w, then v for an SE(3) body); the MLP's input is (R, p)
void covector(const Spec &s, int B, int m, const double *R, const double *p, std::vector<double> &a,
              std::vector<double> &z, std::vector<double> &slopes, std::vector<double> &gr, double *c) {
    const int dim = 6 * m + 3 * (B - m);
    auto at = [m](int b) { return b < m ? 6 * b : 6 * m + 3 * (b - m); };  // a body's first tangent entry
    for (int q = 0; q < dim; ++q) c[q] = 0.0;
    if (s.layers) {
        // forward: the activations of every hidden layer, keeping each one's slope
        const double *W = s.weights, *b = s.biases;
        std::memcpy(a.data(), R, 9 * B * sizeof(double));
        if (m) std::memcpy(&a[9 * B], p, 3 * m * sizeof(double));
        int in = (int)s.width[0], off = 0;
        for (int l = 0; l < s.layers; ++l) {
            int out = (int)s.width[l + 1];
            std::fill(z.begin(), z.begin() + out, 0.0);
            accumulate(s.weights_t + (W - s.weights), a.data(), in, out, z.data());
            for (int i = 0; i < out; ++i) z[i] += b[i];
            activate(s.act[l], z.data(), out, a.data(), &slopes[off]);
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
        // per body the sum over rows k of dR_k x R_k; an SE(3) body's R^T dp
        for (int b = 0; b < B; ++b) {
            double *cb = &c[at(b)];
            for (int k = 0; k < 3; ++k) {
                const double *d = &gr[9 * b + 3 * k], *r = &R[9 * b + 3 * k];
                cb[0] += d[1] * r[2] - d[2] * r[1];
                cb[1] += d[2] * r[0] - d[0] * r[2];
                cb[2] += d[0] * r[1] - d[1] * r[0];
            }
            if (b < m) {
                const double *Rb = &R[9 * b], *dp = &gr[9 * B + 3 * b];
                for (int i = 0; i < 3; ++i) cb[3 + i] = Rb[i] * dp[0] + Rb[3 + i] * dp[1] + Rb[6 + i] * dp[2];
            }
        }
    }
    for (int j = 0; j < s.n_grav; ++j) {
        const double *f = &s.grav_f[3 * j];
        for (int b = 0; b < B; ++b) {
            const double *Rb = &R[9 * b], *av = &s.grav_a[3 * (j * B + b)];
            double u[3] = {Rb[0] * f[0] + Rb[3] * f[1] + Rb[6] * f[2], Rb[1] * f[0] + Rb[4] * f[1] + Rb[7] * f[2],
                           Rb[2] * f[0] + Rb[5] * f[1] + Rb[8] * f[2]};  // R^T f
            double *cb = &c[at(b)];
            cb[0] += av[1] * u[2] - av[2] * u[1];
            cb[1] += av[2] * u[0] - av[0] * u[2];
            cb[2] += av[0] * u[1] - av[1] * u[0];
            if (b < m)
                for (int i = 0; i < 3; ++i) cb[3 + i] += s.grav_m[j * B + b] * u[i];
        }
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
    mm(W, E, out);
}

// the warm start from the last L increments, oldest first (`scalar._extrapolate`)
void extrapolate(const double *hist, int L, double *out) {
    const double *W = &hist[9 * (L - 1)];
    if (L == 1) {
        std::memcpy(out, W, 9 * sizeof(double));
        return;
    }
    double E[9], D[9], T[9], E3[9];
    mmt(W, &hist[9 * (L - 2)], E);
    if (L == 3) {  // E D'^T E with D' = W_1 W_2^T
        mmt(&hist[9], &hist[0], D);
        mmt(E, D, T);
        mm(T, E, E3);
        std::memcpy(E, E3, sizeof E);
    }
    bool ok = 3.0 - (E[0] + E[4] + E[8]) <= TRUST * TRUST * (3.0 - (W[0] + W[4] + W[8]));  // NaN: false
    if (ok)
        mm(E, W, out);
    else
        std::memcpy(out, W, 9 * sizeof(double));
}

inline double norm3(const double *r) { return std::sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]); }

// ---------------------------------------------------------------------------- a product of bodies
// A learned force F(g, xi~) = scale (W_out a + b_out) of an MLP of (flatten(g), xi~) (`mechanics.forces.NNForce`):
// hidden layers of exact GELU or tanh, weights as for the potential (`Spec`); nq = 9 B + 3 m inputs from g, then
// the dim inputs of xi~, dim outputs.
struct Net {
    int layers, nq, dim;
    const int64_t *width, *act;  // width (layers + 1): nq + dim, then each hidden layer's width
    const double *weights, *weights_t, *biases, *out_w, *out_b;  // out_w (dim, width[layers]), out_b (dim)
    double scale;
};

// Net's work space and its first layer's part fixed by g (`fix`), for values at (g, xi) and dF/dxi~ there
struct NetEval {
    const Net *net = nullptr;
    std::vector<double> zq, a, z, slopes, J, J2;
    void init(const Net *n) {
        net = n;
        if (!n) return;
        int wmax = 1, total = 0;
        for (int l = 0; l < n->layers; ++l) wmax = std::max(wmax, (int)n->width[l + 1]), total += (int)n->width[l + 1];
        zq.assign(wmax, 0.0), a.assign(std::max(wmax, n->nq + n->dim), 0.0), z.assign(wmax, 0.0);
        slopes.assign(std::max(total, 1), 0.0), J.assign(wmax * n->dim, 0.0), J2.assign(wmax * n->dim, 0.0);
    }
    // zq = the first layer's weights on g's inputs times flatten(g) (R: 9 B, p: 3 m)
    void fix(const double *R, const double *p, int B, int m) {
        const Net &n = *net;
        const int w1 = (int)n.width[1];
        std::memcpy(a.data(), R, 9 * B * sizeof(double));
        if (m) std::memcpy(&a[9 * B], p, 3 * m * sizeof(double));
        std::fill(zq.begin(), zq.begin() + w1, 0.0);
        accumulate(n.weights_t, a.data(), n.nq, w1, zq.data());
    }
    // F (dim) at (the fixed g, xi); with dF (dim x dim, row-major) its Jacobian in xi by forward mode
    void eval(const double *xi, double *F, double *dF) {
        const Net &n = *net;
        const int d = n.dim, in0 = n.nq + d;
        const double *W = n.weights, *Wt = n.weights_t, *b = n.biases;
        int in = in0, off = 0;
        for (int l = 0; l < n.layers; ++l) {
            const int out = (int)n.width[l + 1];
            if (l == 0) {
                for (int i = 0; i < out; ++i) z[i] = zq[i];
                accumulate(Wt + n.nq * out, xi, d, out, z.data());
                if (dF)  // J (out x d) = the first layer's xi columns
                    for (int i = 0; i < out; ++i)
                        for (int j = 0; j < d; ++j) J[i * d + j] = W[i * in + n.nq + j];
            } else {
                std::fill(z.begin(), z.begin() + out, 0.0);
                accumulate(Wt, a.data(), in, out, z.data());
                if (dF) {  // J <- W_l J
                    std::fill(J2.begin(), J2.begin() + out * d, 0.0);
                    for (int i = 0; i < out; ++i)
                        for (int k = 0; k < in; ++k) {
                            const double wik = W[i * in + k], *src = &J[k * d];
                            double *dst = &J2[i * d];
                            for (int j = 0; j < d; ++j) dst[j] += wik * src[j];
                        }
                    std::swap(J, J2);
                }
            }
            for (int i = 0; i < out; ++i) z[i] += b[i];
            double *sl = &slopes[off];
            activate(n.act[l], z.data(), out, a.data(), sl);
            if (dF)
                for (int i = 0; i < out; ++i)
                    for (int j = 0; j < d; ++j) J[i * d + j] *= sl[i];
            W += out * in, Wt += out * in, b += out, off += out, in = out;
        }
        for (int i = 0; i < d; ++i) {
            double acc = 0.0;
            const double *row = &n.out_w[i * in];
            for (int k = 0; k < in; ++k) acc += row[k] * a[k];
            F[i] = n.scale * (acc + n.out_b[i]);
        }
        if (dF)
            for (int i = 0; i < d; ++i)
                for (int j = 0; j < d; ++j) {
                    double acc = 0.0;
                    for (int k = 0; k < in; ++k) acc += n.out_w[i * in + k] * J[k * d + j];
                    dF[i * d + j] = n.scale * acc;
                }
    }
};

// `engines/rollout.py`'s fused step of a product of bodies (`FusedStep` without per-iteration forces): r = const
// + kinetic_d1(x) + (h/2) (-D xi~(x)), J = the kinetic blocks (linear in each W, `RolloutMaps.hess` /
// `se3_block`) + (h/2) (-D) dxi~/d delta, const = kinetic_d2(x_prev) + (h/2) (-D xi~(x_prev)) + the potential's
// covector at g_k. A product of B bodies, the first m of them SE(3) (`lie.ProductGroup`): an increment x is its rotations W_b
// (9 B) then the SE(3) bodies' translations z_i (3 m); the tangent layout gives body b its entries at `at(b)`:
// w, then v for an SE(3) body.
struct Product {
    int B, m, dim, nx;
    const double *d1, *d2, *hess, *se3, *rho, *s, *D;  // rows applied to W_b.flatten(): d1, d2 (B, 3, 9), the
                                                       // rotational Hessian blocks (B, 9, 9), the SE(3) bodies'
                                                       // kinetic blocks (m, 36, 9); rho (m, 3), mass / h (m);
                                                       // D (dim, dim) or null
    double h;
    int at(int b) const { return b < m ? 6 * b : 6 * m + 3 * (b - m); }
};

// kinetic_d1 (second = false) or kinetic_d2 of the increment x: c (dim) (`engines.rollout.kinetic_d1/d2`)
void kinetic(const Product &P, const double *x, bool second, double *c) {
    for (int b = 0; b < P.B; ++b) {
        const double *W = &x[9 * b];
        double *cb = &c[P.at(b)];
        apply((second ? P.d2 : P.d1) + 27 * b, 3, W, cb);
        if (b >= P.m) continue;
        const double *z = &x[9 * P.B + 3 * b], *rho = &P.rho[3 * b];
        const double s = P.s[b];
        double Wr[3], X[3], u[3], cu[3];
        for (int i = 0; i < 3; ++i) Wr[i] = W[3 * i] * rho[0] + W[3 * i + 1] * rho[1] + W[3 * i + 2] * rho[2];
        for (int i = 0; i < 3; ++i) X[i] = z[i] + Wr[i] - rho[i];
        if (second) {  // w += s rho x W^T X, v = s W^T X
            for (int i = 0; i < 3; ++i) u[i] = W[i] * X[0] + W[3 + i] * X[1] + W[6 + i] * X[2];
            cross(rho, u, cu);
            for (int i = 0; i < 3; ++i) cb[i] += s * cu[i], cb[3 + i] = s * u[i];
        } else {  // w += s X x (z + W rho), v = -s X
            for (int i = 0; i < 3; ++i) u[i] = z[i] + Wr[i];
            cross(X, u, cu);
            for (int i = 0; i < 3; ++i) cb[i] += s * cu[i], cb[3 + i] = -s * X[i];
        }
    }
}

// xi~ (dim) of the increment x, per body (vee(W) / h, (z - h/2 w~ x z) / h) (`kinetic.velocity_estimate`)
void velocity(const Product &P, const double *x, double *xi) {
    const double h = P.h;
    for (int b = 0; b < P.B; ++b) {
        const double *W = &x[9 * b];
        double *w = &xi[P.at(b)];
        w[0] = 0.5 * (W[7] - W[5]) / h, w[1] = 0.5 * (W[2] - W[6]) / h, w[2] = 0.5 * (W[3] - W[1]) / h;
        if (b < P.m) {
            const double *z = &x[9 * P.B + 3 * b];
            double wz[3];
            cross(w, z, wz);
            for (int i = 0; i < 3; ++i) w[3 + i] = (z[i] - 0.5 * h * wz[i]) / h;
        }
    }
}

// r (dim) += (h/2) (-D xi~(x) + F_nn(g, xi~(x))) with `nn`'s g fixed (`NetEval::fix`; none: null); xi, F scratch
void forces_add(const Product &P, NetEval *nn, const double *x, double *r, double *xi, double *F) {
    if (!P.D && !nn) return;
    velocity(P, x, xi);
    if (P.D)
        for (int i = 0; i < P.dim; ++i) {
            double acc = 0.0;
            for (int j = 0; j < P.dim; ++j) acc += P.D[P.dim * i + j] * xi[j];
            r[i] += 0.5 * P.h * -acc;
        }
    if (nn) {
        nn->eval(xi, F, nullptr);
        for (int i = 0; i < P.dim; ++i) r[i] += 0.5 * P.h * F[i];
    }
}

// J (dim x dim) = blockdiag(the kinetic blocks at x) + (h/2) (-D) blockdiag(dxi~/d delta) (`rollout.step_jacobian`;
// `velocity_jacobian_blocks`: dw = (tr W I - W^T) / (2h), an SE(3) body's [[dw, 0], [hat(z) dw / 2, (I - h/2
// hat(w~)) W / h]]), plus (h/2) dF_nn/dxi~ blockdiag(dxi~/d delta) with `nn`'s g fixed; A, dF (dim x dim), xi, F
// scratch
void jacobian(const Product &P, NetEval *nn, const double *x, double *J, double *A, double *dF, double *xi, double *F) {
    const int n = P.dim;
    const double h = P.h;
    std::fill(J, J + n * n, 0.0);
    for (int b = 0; b < P.B; ++b) {
        const double *W = &x[9 * b];
        const int o = P.at(b), k = b < P.m ? 6 : 3;
        double blk[36];
        if (b < P.m)
            apply(P.se3 + 324 * b, 36, W, blk);
        else
            apply(P.hess + 81 * b, 9, W, blk);
        for (int i = 0; i < k; ++i)
            for (int j = 0; j < k; ++j) J[n * (o + i) + o + j] = blk[k * i + j];
    }
    if (!P.D && !nn) return;
    std::fill(A, A + n * n, 0.0);
    for (int b = 0; b < P.B; ++b) {
        const double *W = &x[9 * b];
        const int o = P.at(b);
        const double tr = W[0] + W[4] + W[8];
        double dw[9];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) dw[3 * i + j] = ((i == j ? tr : 0.0) - W[3 * j + i]) / (2 * h);
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) A[n * (o + i) + o + j] = dw[3 * i + j];
        if (b >= P.m) continue;
        const double *z = &x[9 * P.B + 3 * b];
        double w[3] = {0.5 * (W[7] - W[5]) / h, 0.5 * (W[2] - W[6]) / h, 0.5 * (W[3] - W[1]) / h};
        double Hz[9] = {0, -z[2], z[1], z[2], 0, -z[0], -z[1], z[0], 0};
        double M[9] = {1, 0.5 * h * w[2], -0.5 * h * w[1], -0.5 * h * w[2], 1, 0.5 * h * w[0],
                       0.5 * h * w[1], -0.5 * h * w[0], 1};  // I - h/2 hat(w)
        double dvw[9], dvv[9];
        mm(Hz, dw, dvw);
        mm(M, W, dvv);
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) {
                A[n * (o + 3 + i) + o + j] = 0.5 * dvw[3 * i + j];
                A[n * (o + 3 + i) + o + 3 + j] = dvv[3 * i + j] / h;
            }
    }
    // dF (the forces' Jacobian in xi~): -D, plus the network's
    for (int q = 0; q < n * n; ++q) dF[q] = P.D ? -P.D[q] : 0.0;
    if (nn) {
        velocity(P, x, xi);
        nn->eval(xi, F, A + n * n);  // (A's second half: scratch for the network's Jacobian)
        for (int q = 0; q < n * n; ++q) dF[q] += A[n * n + q];
    }
    for (int i = 0; i < n; ++i)
        for (int j = 0; j < n; ++j) {
            double acc = 0.0;
            for (int q = 0; q < n; ++q) acc += dF[n * i + q] * A[n * q + j];
            J[n * i + j] += 0.5 * h * acc;
        }
}

// x exp(delta) body by body: W exp(w), and an SE(3) body's z + W V(w) v (`lie.batched.group_retract`)
void retract(const Product &P, const double *x, const double *d, double *out) {
    for (int b = 0; b < P.B; ++b) {
        const double *w = &d[P.at(b)], *W = &x[9 * b];
        double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
        double c0 = sinc(t2), c1 = cosc(t2);
        double H[9] = {0, -w[2], w[1], w[2], 0, -w[0], -w[1], w[0], 0}, H2[9], E[9];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) H2[3 * i + j] = w[i] * w[j] - (i == j ? t2 : 0.0);  // hat(w)^2
        for (int q = 0; q < 9; ++q) E[q] = (q % 4 == 0 ? 1.0 : 0.0) + c0 * H[q] + c1 * H2[q];
        mm(W, E, &out[9 * b]);
        if (b >= P.m) continue;
        const double *v = w + 3, *z = &x[9 * P.B + 3 * b];
        double c2 = sinc3(t2), V[9], Vv[3];
        for (int q = 0; q < 9; ++q) V[q] = (q % 4 == 0 ? 1.0 : 0.0) + c1 * H[q] + c2 * H2[q];
        for (int i = 0; i < 3; ++i) Vv[i] = V[3 * i] * v[0] + V[3 * i + 1] * v[1] + V[3 * i + 2] * v[2];
        double *zo = &out[9 * P.B + 3 * b];
        for (int i = 0; i < 3; ++i) zo[i] = z[i] + W[3 * i] * Vv[0] + W[3 * i + 1] * Vv[1] + W[3 * i + 2] * Vv[2];
    }
}

// a b and a^-1 of product poses (rotations, then the SE(3) bodies' translations)
void pose_mul(const Product &P, const double *a, const double *b, double *c) {
    for (int q = 0; q < P.B; ++q) mm(&a[9 * q], &b[9 * q], &c[9 * q]);
    for (int q = 0; q < P.m; ++q) {
        const double *R = &a[9 * q], *pa = &a[9 * P.B + 3 * q], *pb = &b[9 * P.B + 3 * q];
        for (int i = 0; i < 3; ++i) c[9 * P.B + 3 * q + i] = pa[i] + R[3 * i] * pb[0] + R[3 * i + 1] * pb[1] + R[3 * i + 2] * pb[2];
    }
}
void pose_inv(const Product &P, const double *a, double *c) {
    for (int q = 0; q < P.B; ++q)
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) c[9 * q + 3 * i + j] = a[9 * q + 3 * j + i];
    for (int q = 0; q < P.m; ++q) {
        const double *R = &a[9 * q], *p = &a[9 * P.B + 3 * q];
        for (int i = 0; i < 3; ++i) c[9 * P.B + 3 * q + i] = -(R[i] * p[0] + R[3 + i] * p[1] + R[6 + i] * p[2]);
    }
}

// the warm start from the last L increments, oldest first (`lie.batched.extrapolate_increments`); t scratch
// (3 nx)
void extrapolate(const Product &P, const double *hist, int L, double *out, double *t) {
    const int nx = P.nx;
    const double *last = &hist[nx * (L - 1)];
    if (L == 1) {
        std::memcpy(out, last, nx * sizeof(double));
        return;
    }
    double *inv = t, *E = t + nx, *T = t + 2 * nx;
    pose_inv(P, &hist[nx * (L - 2)], inv);
    pose_mul(P, last, inv, E);
    if (L == 3) {  // E D'^-1 E with D' = inc_1 inc_2^-1
        pose_inv(P, &hist[0], inv);
        pose_mul(P, &hist[nx], inv, T);  // D'
        pose_inv(P, T, inv);
        pose_mul(P, E, inv, T);
        pose_mul(P, T, E, inv);
        std::memcpy(E, inv, nx * sizeof(double));
    }
    pose_mul(P, E, last, out);
    double trE = 0.0, trW = 0.0, dp2 = 0.0, p2 = 0.0;
    for (int b = 0; b < P.B; ++b) trE += E[9 * b] + E[9 * b + 4] + E[9 * b + 8], trW += last[9 * b] + last[9 * b + 4] + last[9 * b + 8];
    for (int q = 9 * P.B; q < nx; ++q) dp2 += (out[q] - last[q]) * (out[q] - last[q]), p2 += last[q] * last[q];
    const double t2 = TRUST * TRUST;
    bool ok = 3.0 * P.B - trE <= t2 * (3.0 * P.B - trW);  // NaN compares false
    if (P.m) ok = ok && dp2 <= t2 * p2;
    if (!ok) std::memcpy(out, last, nx * sizeof(double));
}

inline double norm(const double *r, int n) {
    double s = 0.0;
    for (int q = 0; q < n; ++q) s += r[q] * r[q];
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
                covector(s, 1, 0, g, nullptr, a, z, slopes, gr, cov);
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
                mtm(W, W, M);
                for (int q = 0; q < 9; ++q) M[q] = (q % 4 == 0 ? 3.0 : 0.0) - M[q];
                mm(W, M, Wn);
                for (int q = 0; q < 9; ++q) Wn[q] *= 0.5;
                mm(g, Wn, gn);
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
    split_rows(N, threads, rows);
    return 0;
}

// Roll `count` steps of N trajectories of a product of B bodies (the first m SE(3)) on from their state, in
// place: R (N, B, 9), p (N, m, 3) the pose g_k, hist (N, 3, nx) the last increments (x: rotations, then the
// SE(3) translations), oldest first, hist_len (N) how many, and Rprev, Pprev the pose g_{k-1} (read by a learned
// force). Writes the poses (N, count, B, 9) / (N, count, m, 3)
// and per step converged, Newton iterations and the residual's max norm (N, count). The bodies: d1, d2
// (B, 3, 9), hess (B, 9, 9), se3 (m, 36, 9), rho (m, 3), s = mass / h (m), D (dim, dim) when damped; the
// potential as for `liedfl_so3_rollout` (the MLP's input (R, p), 9 B + 3 m wide; gravity per body); a learned
// force `Net` when f_layers > 0. `threads` as there. Returns 0.
int liedfl_product_rollout(int64_t N, int64_t count, int64_t B, int64_t m, const double *d1, const double *d2,
                           const double *hess, const double *se3, const double *rho, const double *s_mass,
                           int64_t damped, const double *D, double h, int64_t layers, const int64_t *width,
                           const double *weights, const double *weights_t, const double *biases,
                           const int64_t *act, const double *out_w, int64_t n_grav, const double *grav_a,
                           const double *grav_f, const double *grav_m, int64_t f_layers, const int64_t *f_width,
                           const double *f_weights, const double *f_weights_t, const double *f_biases,
                           const int64_t *f_act, const double *f_out_w, const double *f_out_b, double f_scale,
                           double tol, int64_t max_iter, int64_t max_halvings, double *Rprev, double *Pprev,
                           double *R, double *Pp, double *hist, int64_t *hist_len,
                           double *outR, double *outp, uint8_t *converged, int64_t *iterations,
                           double *residual_norm, int64_t threads) {
    Spec s{nullptr,     nullptr, nullptr, (int)layers, width, weights,        weights_t,          biases, out_w, act,
           (int)n_grav, grav_a,  grav_f,  grav_m,      tol,   (int)max_iter, (int)max_halvings};
    const int dim = (int)(6 * m + 3 * (B - m)), nx = (int)(9 * B + 3 * m);
    Product P{(int)B, (int)m, dim, nx, d1, d2, hess, se3, rho, s_mass, damped ? D : nullptr, h};
    Net net{(int)f_layers, nx, dim, f_width, f_act, f_weights, f_weights_t, f_biases, f_out_w, f_out_b, f_scale};
    const Net *force = f_layers > 0 ? &net : nullptr;  // a learned force (`NNForce`), or none
    int wmax = nx, total = 0;
    for (int l = 0; l < layers; ++l) wmax = std::max(wmax, (int)width[l + 1]), total += (int)width[l + 1];
    const double big = std::numeric_limits<double>::max(), eps = std::numeric_limits<double>::epsilon();
    auto rows = [&](int64_t i0, int64_t i1) {
        std::vector<double> a(wmax), z(wmax), slopes(std::max(total, 1)), gr(wmax);
        std::vector<double> cst(dim), r(dim), rc(dim), delta(dim), dd(dim), xi(dim), Fs(dim), J(dim * dim);
        std::vector<double> A(2 * dim * dim), dF(dim * dim), x(nx), cand(nx), t(3 * nx), gk(nx), gn(nx), inc(nx);
        std::vector<int> piv(dim);
        NetEval eval;
        eval.init(force);
        NetEval *nn = force ? &eval : nullptr;
        for (int64_t i = i0; i < i1; ++i) {
            double *g = R + 9 * B * i, *gp = Pp + 3 * m * i, *hi = hist + 3 * nx * i;
            double *g0 = Rprev + 9 * B * i, *gp0 = Pprev + 3 * m * i;
            int L = (int)hist_len[i];
            for (int64_t k = 0; k < count; ++k) {
                const double *prev = &hi[nx * (L - 1)];
                kinetic(P, prev, true, cst.data());
                if (nn) nn->fix(g0, gp0, (int)B, (int)m);  // the forces of the interval before g_k, at g_{k-1}
                forces_add(P, nn, prev, cst.data(), xi.data(), Fs.data());
                if (nn) nn->fix(g, gp, (int)B, (int)m);  // ... and of the interval after it, at g_k
                covector(s, (int)B, (int)m, g, gp, a, z, slopes, gr, rc.data());
                for (int q = 0; q < dim; ++q) cst[q] += rc[q];
                extrapolate(P, hi, L, x.data(), t.data());
                auto residual = [&](const double *y, double *out) {
                    kinetic(P, y, false, out);
                    for (int q = 0; q < dim; ++q) out[q] += cst[q];
                    forces_add(P, nn, y, out, xi.data(), Fs.data());
                };
                residual(x.data(), r.data());
                double rn = norm(r.data(), dim);
                bool conv = false;
                int it = 0;
                for (; it < s.max_iter && !conv; ++it) {
                    double scale = 0.0;  // newton.step_tolerance: the largest translation of the iterate
                    for (int q = 9 * (int)B; q < nx; ++q) scale = std::fmax(scale, std::fabs(x[q]));
                    double step_tol = m ? std::fmax(tol, 16.0 * eps * std::fmax(scale, 1.0)) : std::fmax(tol, 16.0 * eps);
                    jacobian(P, nn, x.data(), J.data(), A.data(), dF.data(), xi.data(), Fs.data());
                    bool singular = !lu_factor(J.data(), dim, piv.data());
                    for (int q = 0; q < dim; ++q) delta[q] = -r[q];
                    if (!singular) lu_solve(J.data(), dim, piv.data(), delta.data());
                    bool finite = !singular;
                    for (int q = 0; q < dim && finite; ++q) finite = std::isfinite(delta[q]);
                    if (!finite) {  // no step on this iteration (the step fails)
                        singular = true;
                        std::fill(delta.begin(), delta.end(), 0.0);
                    }
                    double full = 0.0;
                    for (int q = 0; q < dim; ++q) full = std::fmax(full, std::fabs(delta[q]));
                    // backtracking on ||r||_2 (solvers.newton._careful_iteration); without a decrease the full
                    // step is taken where its residual is finite
                    double alpha = 1.0;
                    bool accepted = false;
                    for (int hh = 0; hh <= s.max_halvings; ++hh) {
                        for (int q = 0; q < dim; ++q) dd[q] = alpha * delta[q];
                        retract(P, x.data(), dd.data(), cand.data());
                        residual(cand.data(), rc.data());
                        double rcn = norm(rc.data(), dim);
                        if (std::isfinite(rcn) && rcn <= std::fmin(rn * (1 - 1e-4 * alpha) + 1e-300, big)) {
                            accepted = true;
                            std::swap(x, cand);
                            std::swap(r, rc);
                            rn = rcn;
                            break;
                        }
                        alpha *= 0.5;
                    }
                    if (!accepted) {
                        retract(P, x.data(), delta.data(), cand.data());
                        residual(cand.data(), rc.data());
                        double rcn = norm(rc.data(), dim);
                        if (std::isfinite(rcn)) {
                            std::swap(x, cand);
                            std::swap(r, rc);
                            rn = rcn;
                        }
                    }
                    conv = !singular && full <= step_tol && std::isfinite(rn);
                }
                double rmax = 0.0;
                bool rnan = false;
                for (int q = 0; q < dim; ++q) rmax = std::fmax(rmax, std::fabs(r[q])), rnan = rnan || std::isnan(r[q]);
                converged[i * count + k] = conv ? 1 : 0;
                iterations[i * count + k] = it;
                residual_norm[i * count + k] = rnan ? std::numeric_limits<double>::quiet_NaN() : rmax;
                // each rotation of the increment re-orthonormalised (one Newton-Schulz step), g_{k+1} = g_k inc
                for (int b = 0; b < B; ++b) {
                    double M[9];
                    const double *W = &x[9 * b];
                    mtm(W, W, M);
                    for (int q = 0; q < 9; ++q) M[q] = (q % 4 == 0 ? 3.0 : 0.0) - M[q];
                    mm(W, M, &inc[9 * b]);
                    for (int q = 0; q < 9; ++q) inc[9 * b + q] *= 0.5;
                }
                std::copy(x.begin() + 9 * B, x.end(), inc.begin() + 9 * B);
                std::memcpy(gk.data(), g, 9 * B * sizeof(double));
                if (m) std::memcpy(gk.data() + 9 * B, gp, 3 * m * sizeof(double));  // (no positions: maybe null)
                std::memcpy(g0, g, 9 * B * sizeof(double));  // g_k becomes the next step's g_{k-1}
                if (m) std::memcpy(gp0, gp, 3 * m * sizeof(double));
                pose_mul(P, gk.data(), inc.data(), gn.data());
                std::memcpy(g, gn.data(), 9 * B * sizeof(double));
                std::memcpy(outR + (i * count + k) * 9 * B, gn.data(), 9 * B * sizeof(double));
                if (m) {
                    std::memcpy(gp, gn.data() + 9 * B, 3 * m * sizeof(double));
                    std::memcpy(outp + (i * count + k) * 3 * m, gn.data() + 9 * B, 3 * m * sizeof(double));
                }
                if (L == HISTORY) {
                    std::memmove(hi, hi + nx, nx * (HISTORY - 1) * sizeof(double));
                    --L;
                }
                std::memcpy(&hi[nx * L], inc.data(), nx * sizeof(double));
                ++L;
            }
            hist_len[i] = L;
        }
    };
    split_rows(N, threads, rows);
    return 0;
}
}
