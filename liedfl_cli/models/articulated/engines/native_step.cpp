// The articulated model's implicit DEL step in C++, one trajectory at a time (engines/native.py builds
// and loads it; engines/fused.py is the same step batched in torch and the module docstring there has
// the formulas). Each trajectory iterates on its own, so a row's Newton loop is the reference loop of
// solvers/newton.py (backtracking on ||f||_2, convergence on the full step's max norm) without batching.
//
// Shapes (row-major float64): B bodies, n DoF (the reduced tree's), dim = 6 m + 3 (B - m) the tree
// group's tangent dim, m = 1 with a free root else 0. Rotations of a pose in the tree's own coordinates
// (world or parent-relative attitudes, `world`), the free root's position.
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

#include "native_math.hpp"

namespace {

using namespace liedfl_native;

struct TreeSpec {
    int B, n, dim, m, world, joint_mode, reduced, max_iter, max_halvings, chord;
    double h, tol;
    const int64_t *parents, *kind, *col, *row;  // kind: 0 free, 1 ball, 2 hinge, 3 weld
    const double *axis, *offsets, *Jd, *mass, *rho, *rot_map;
    int gravity, damped;
    const double *gamma, *first_moment, *gmass, *damping, *S0pinv;
    std::vector<std::vector<int>> cols;  // per body: the columns its FK Jacobian can reach
};

inline double vinv_coeff(double t2) {
    static const double c[] = {1.0 / 12, 1.0 / 720, 1.0 / 30240, 1.0 / 1209600, 1.0 / 47900160};
    if (t2 < TAYLOR2) return poly(t2, c, 5);
    double half = 0.5 * std::sqrt(t2);
    return (1.0 - half * std::cos(half) / std::sin(half)) / t2;
}

// 3x3 helpers, row-major (the products: native_math.hpp)
inline void mv(const double *A, const double *x, double *y) {
    for (int i = 0; i < 3; ++i) y[i] = A[3 * i] * x[0] + A[3 * i + 1] * x[1] + A[3 * i + 2] * x[2];
}
inline void mtv(const double *A, const double *x, double *y) {
    for (int i = 0; i < 3; ++i) y[i] = A[i] * x[0] + A[3 + i] * x[1] + A[6 + i] * x[2];
}
inline void vee(const double *A, double *w) {  // vee of the skew part
    w[0] = 0.5 * (A[7] - A[5]);
    w[1] = 0.5 * (A[2] - A[6]);
    w[2] = 0.5 * (A[3] - A[1]);
}
inline void hat_sq(const double *w, double a, double b, double *M) {  // M = I + a hat(w) + b hat(w)^2
    double x = w[0], y = w[1], z = w[2];
    double H[9] = {0, -z, y, z, 0, -x, -y, x, 0};
    double H2[9];
    mm(H, H, H2);
    for (int k = 0; k < 9; ++k) M[k] = a * H[k] + b * H2[k];
    M[0] += 1.0, M[4] += 1.0, M[8] += 1.0;
}
inline void so3_exp(const double *w, double *R) {
    double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    hat_sq(w, sinc(t2), cosc(t2), R);
}
inline void V_matrix(const double *w, double *V) {
    double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    hat_sq(w, cosc(t2), sinc3(t2), V);
}
inline void V_inverse(const double *w, double *V) {
    double t2 = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];
    hat_sq(w, -0.5, vinv_coeff(t2), V);
}
// log through the unit quaternion (Shepperd's largest pivot), |w| <= pi: lie.so3.log
void so3_log(const double *r, double *w) {
    double tr = r[0] + r[4] + r[8];
    double piv[4] = {tr, r[0], r[4], r[8]};
    int c = 0;
    for (int k = 1; k < 4; ++k)
        if (piv[k] > piv[c]) c = k;
    double d21 = r[7] - r[5], d02 = r[2] - r[6], d10 = r[3] - r[1];
    double s01 = r[1] + r[3], s02 = r[2] + r[6], s12 = r[5] + r[7];
    double q[4], s;
    if (c == 0) {
        s = 2.0 * std::sqrt(std::fmax(1.0 + tr, 1e-12));
        q[0] = s / 4, q[1] = d21 / s, q[2] = d02 / s, q[3] = d10 / s;
    } else if (c == 1) {
        s = 2.0 * std::sqrt(std::fmax(1.0 + r[0] - r[4] - r[8], 1e-12));
        q[0] = d21 / s, q[1] = s / 4, q[2] = s01 / s, q[3] = s02 / s;
    } else if (c == 2) {
        s = 2.0 * std::sqrt(std::fmax(1.0 - r[0] + r[4] - r[8], 1e-12));
        q[0] = d02 / s, q[1] = s01 / s, q[2] = s / 4, q[3] = s12 / s;
    } else {
        s = 2.0 * std::sqrt(std::fmax(1.0 - r[0] - r[4] + r[8], 1e-12));
        q[0] = d10 / s, q[1] = s02 / s, q[2] = s12 / s, q[3] = s / 4;
    }
    double nq = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    double sg = q[0] < 0 ? -1.0 : 1.0;
    for (int k = 0; k < 4; ++k) q[k] = sg * q[k] / nq;
    double n2 = q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    double scale;
    if (n2 < TAYLOR2) {
        static const double cs[] = {1.0, -1.0 / 3, 1.0 / 5, -1.0 / 7, 1.0 / 9, -1.0 / 11, 1.0 / 13, -1.0 / 15};
        scale = (2.0 / q[0]) * poly(n2 / (q[0] * q[0]), cs, 8);
    } else {
        double nn = std::sqrt(n2);
        scale = 2.0 * std::atan2(nn, q[0]) / nn;
    }
    w[0] = scale * q[1], w[1] = scale * q[2], w[2] = scale * q[3];
}

// A pose of the tree in joint coordinates (parent-relative attitudes, the root's own pose), its forward
// kinematics and, once asked for, its FK Jacobian in the world frame (Theta, P) and the centres of mass'
// (Y), each (B, 3, n).
struct Frame {
    std::vector<double> R, Rw, pw, u, Th, P, Y;
    double p[3] = {0, 0, 0};
    bool jac = false, com = false;
    void init(const TreeSpec &t) {
        R.assign(9 * t.B, 0.0), Rw.assign(9 * t.B, 0.0), pw.assign(3 * t.B, 0.0), u.assign(3 * t.B, 0.0);
        Th.assign(3 * t.B * t.n, 0.0), P.assign(3 * t.B * t.n, 0.0), Y.assign(3 * t.B * t.n, 0.0);
    }
};

// rw_known: the world attitudes are the pose's own (a world-rotation tree's g), not recomputed. F.R holds the
// coordinates the unknown moves: parent-relative attitudes (joint_mode) or the world attitudes themselves
// (an unreduced world-rotation tree, every joint a ball)
void forward_kinematics(const TreeSpec &t, Frame &F, bool rw_known = false) {
    for (int b = 0; b < t.B; ++b) {
        int a = (int)t.parents[b];
        if (a < 0) {
            if (!rw_known) std::memcpy(&F.Rw[0], &F.R[0], 9 * sizeof(double));
            for (int i = 0; i < 3; ++i) F.u[i] = t.m ? F.p[i] : t.offsets[i];
            for (int i = 0; i < 3; ++i) F.pw[i] = F.u[i];
        } else {
            if (!rw_known && t.joint_mode) mm(&F.Rw[9 * a], &F.R[9 * b], &F.Rw[9 * b]);
            if (!rw_known && !t.joint_mode) std::memcpy(&F.Rw[9 * b], &F.R[9 * b], 9 * sizeof(double));
            mv(&F.Rw[9 * a], &t.offsets[3 * b], &F.u[3 * b]);
            for (int i = 0; i < 3; ++i) F.pw[3 * b + i] = F.pw[3 * a + i] + F.u[3 * b + i];
        }
    }
    F.jac = F.com = false;
}

// Theta_b = Theta_parent + Rw_b E_b (the joint's axes in the world; Rw_b E_b alone where the unknown moves
// world attitudes), P_b = P_parent + Theta_parent x u_b (the free root: its translation columns Rw_0)
void world_jacobian(const TreeSpec &t, Frame &F) {
    if (F.jac) return;
    const int n = t.n;
    for (int b = 0; b < t.B; ++b) {
        int a = (int)t.parents[b];
        double *Th = &F.Th[3 * n * b], *P = &F.P[3 * n * b];
        const double *Rw = &F.Rw[9 * b];
        for (int j : t.cols[b]) {
            for (int i = 0; i < 3; ++i) Th[i * n + j] = (a < 0 || !t.joint_mode) ? 0.0 : F.Th[3 * n * a + i * n + j];
            if (a < 0) {
                for (int i = 0; i < 3; ++i) P[i * n + j] = 0.0;
            } else {
                const double *Ta = &F.Th[3 * n * a], *Pa = &F.P[3 * n * a], *u = &F.u[3 * b];
                double t0 = Ta[j], t1 = Ta[n + j], t2 = Ta[2 * n + j];
                P[j] = Pa[j] + t1 * u[2] - t2 * u[1];
                P[n + j] = Pa[n + j] + t2 * u[0] - t0 * u[2];
                P[2 * n + j] = Pa[2 * n + j] + t0 * u[1] - t1 * u[0];
            }
        }
        int c = (int)t.col[b];
        switch (t.kind[b]) {
            case 0:  // free root: rotation columns c..c+2, translation columns c+3..c+5
                for (int i = 0; i < 3; ++i)
                    for (int k = 0; k < 3; ++k) {
                        Th[i * n + c + k] += Rw[3 * i + k];
                        P[i * n + c + 3 + k] = Rw[3 * i + k];
                    }
                break;
            case 1:
                for (int i = 0; i < 3; ++i)
                    for (int k = 0; k < 3; ++k) Th[i * n + c + k] += Rw[3 * i + k];
                break;
            case 2: {
                double ax[3];
                mv(Rw, &t.axis[3 * b], ax);
                for (int i = 0; i < 3; ++i) Th[i * n + c] += ax[i];
                break;
            }
            default:
                break;
        }
    }
    F.jac = true;
}

// Y_b = P_b + Theta_b x (Rw_b rho_b): the world velocity of body b's centre of mass per column
void com_jacobian(const TreeSpec &t, Frame &F) {
    if (F.com) return;
    world_jacobian(t, F);
    const int n = t.n;
    for (int b = 0; b < t.B; ++b) {
        double arm[3];
        mv(&F.Rw[9 * b], &t.rho[3 * b], arm);
        const double *Th = &F.Th[3 * n * b], *P = &F.P[3 * n * b];
        double *Y = &F.Y[3 * n * b];
        for (int j : t.cols[b]) {
            double a0 = Th[j], a1 = Th[n + j], a2 = Th[2 * n + j];
            Y[j] = P[j] + a1 * arm[2] - a2 * arm[1];
            Y[n + j] = P[n + j] + a2 * arm[0] - a0 * arm[2];
            Y[2 * n + j] = P[2 * n + j] + a0 * arm[1] - a1 * arm[0];
        }
    }
    F.com = true;
}

// r (n) += Theta^T (Rw c_w) + P^T (Rw c_v) over bodies, c (B, 6) body-frame covectors
void pair_add(const TreeSpec &t, const Frame &F, const double *c, double *r) {
    const int n = t.n;
    for (int b = 0; b < t.B; ++b) {
        double cw[3], cv[3];
        mv(&F.Rw[9 * b], &c[6 * b], cw);
        mv(&F.Rw[9 * b], &c[6 * b + 3], cv);
        const double *Th = &F.Th[3 * n * b], *P = &F.P[3 * n * b];
        for (int j : t.cols[b])
            r[j] += Th[j] * cw[0] + Th[n + j] * cw[1] + Th[2 * n + j] * cw[2] + P[j] * cv[0] + P[n + j] * cv[1] +
                    P[2 * n + j] * cv[2];
    }
}

// each body's world increment (W, z) = (Rw_a^T Rw_b, Rw_a^T (pw_b - pw_a))
inline void world_increment(const Frame &A, const Frame &Bf, int b, double *W, double *z) {
    mtm(&A.Rw[9 * b], &Bf.Rw[9 * b], W);
    double d[3] = {Bf.pw[3 * b] - A.pw[3 * b], Bf.pw[3 * b + 1] - A.pw[3 * b + 1], Bf.pw[3 * b + 2] - A.pw[3 * b + 2]};
    mtv(&A.Rw[9 * b], d, z);
}

// joint damping over the interval (qa, qb): r += (h/2) (-d . S0^+ nu), nu = the velocity estimate of
// the joint-coordinate increment (mechanics.kinetic.velocity_estimate)
void damping_add(const TreeSpec &t, const Frame &qa, const Frame &qb, double *r, std::vector<double> &nu) {
    if (!t.damped) return;
    for (int b = 0; b < t.B; ++b) {
        double W[9], w[3];
        mtm(&qa.R[9 * b], &qb.R[9 * b], W);
        vee(W, w);
        int r0 = (int)t.row[b];
        for (int i = 0; i < 3; ++i) nu[r0 + i] = w[i] / t.h;
        if (b < t.m) {
            double d[3] = {qb.p[0] - qa.p[0], qb.p[1] - qa.p[1], qb.p[2] - qa.p[2]}, z[3], wz[3];
            mtv(&qa.R[0], d, z);
            double wt[3] = {nu[r0], nu[r0 + 1], nu[r0 + 2]};
            cross(wt, z, wz);
            for (int i = 0; i < 3; ++i) nu[r0 + 3 + i] = (z[i] - 0.5 * t.h * wz[i]) / t.h;
        }
    }
    for (int j = 0; j < t.n; ++j) {
        const double *row = &t.S0pinv[j * t.dim];
        double red = 0.0;
        for (int k = 0; k < t.dim; ++k) red += row[k] * nu[k];
        r[j] += 0.5 * t.h * (-t.damping[j] * red);
    }
}

struct Work {
    std::vector<double> c, nu, J, HT, r, rc, delta, xi;
    std::vector<int> piv;
    void init(const TreeSpec &t) {
        c.assign(6 * t.B, 0.0), nu.assign(t.dim, 0.0), J.assign(t.n * t.n, 0.0), HT.assign(3 * t.n, 0.0);
        r.assign(t.n, 0.0), rc.assign(t.n, 0.0), delta.assign(t.n, 0.0), xi.assign(t.dim, 0.0);
        piv.assign(t.n, 0);
    }
};

// body b's kinetic covector (mechanics.kinetic.kinetic_d2 if `second`, else kinetic_d1) over its world
// increment fa -> fb, (w, v) in its frame at fa: c (6)
void kinetic_covector(const TreeSpec &t, const Frame &fa, const Frame &fb, int b, bool second, double *c) {
    double W[9], z[3], A[9], Bm[9], Wr[3], X[3], u[3], cu[3];
    world_increment(fa, fb, b, W, z);
    const double *Jd = &t.Jd[9 * b], *rho = &t.rho[3 * b];
    const double h = t.h, s = t.mass[b] / h;
    if (second) {  // vee(Jd W - W^T Jd) / h
        mm(Jd, W, A);
        mtm(W, Jd, Bm);
    } else {  // vee(Jd W^T - W Jd) / h
        mmt(Jd, W, A);
        mm(W, Jd, Bm);
    }
    for (int k = 0; k < 9; ++k) A[k] -= Bm[k];
    vee(A, c);
    for (int i = 0; i < 3; ++i) c[i] /= h;
    mv(W, rho, Wr);
    for (int i = 0; i < 3; ++i) X[i] = z[i] + Wr[i] - rho[i];  // X = z + (W - I) rho
    if (second) {  // w += s rho x W^T X, v = s W^T X
        mtv(W, X, u);
        cross(rho, u, cu);
        for (int i = 0; i < 3; ++i) c[i] += s * cu[i], c[3 + i] = s * u[i];
    } else {  // w += s X x (z + W rho), v = -s X
        for (int i = 0; i < 3; ++i) u[i] = z[i] + Wr[i];
        cross(X, u, cu);
        for (int i = 0; i < 3; ++i) c[i] += s * cu[i], c[3 + i] = -s * X[i];
    }
}

// D2 L_d(prev, cur) + gravity at cur + (h/2) damping of (prev, cur), on the DoF: (n)
void residual_const(const TreeSpec &t, const Frame &prev, Frame &cur, Work &w, double *out) {
    world_jacobian(t, cur);
    for (int b = 0; b < t.B; ++b) {
        double *c = &w.c[6 * b];
        kinetic_covector(t, prev, cur, b, true, c);
        if (t.gravity) {  // - h dV of the uniform field at cur
            double up[3], fu[3];
            mtv(&cur.Rw[9 * b], t.gamma, up);
            cross(&t.first_moment[3 * b], up, fu);
            for (int i = 0; i < 3; ++i) c[i] -= t.h * fu[i], c[3 + i] -= t.h * t.gmass[b] * up[i];
        }
    }
    for (int j = 0; j < t.n; ++j) out[j] = 0.0;
    pair_add(t, cur, w.c.data(), out);
    damping_add(t, prev, cur, out, w.nu);
}

// f(next) = const + D1 L_d(cur, next) on the DoF + (h/2) damping of (cur, next): (n)
void residual(const TreeSpec &t, const Frame &cur, const Frame &nxt, const double *cst, Work &w, double *r) {
    for (int b = 0; b < t.B; ++b) kinetic_covector(t, cur, nxt, b, false, &w.c[6 * b]);
    for (int j = 0; j < t.n; ++j) r[j] = cst[j];
    pair_add(t, cur, w.c.data(), r);
    damping_add(t, cur, nxt, r, w.nu);
}

// J = sum_b Theta_k^T Rk Hrot(W) Rn^T Theta_n - (m/h) Y_k^T Y_n, + the damping blocks
void jacobian(const TreeSpec &t, Frame &cur, Frame &nxt, Work &w) {
    com_jacobian(t, cur);
    com_jacobian(t, nxt);
    const int n = t.n;
    std::fill(w.J.begin(), w.J.end(), 0.0);
    for (int b = 0; b < t.B; ++b) {
        const double *Rk = &cur.Rw[9 * b], *Rn = &nxt.Rw[9 * b];
        double W[9], Hrot[9], T1[9], Hw[9];
        mtm(Rk, Rn, W);
        const double *map = &t.rot_map[81 * b];
        for (int l = 0; l < 9; ++l) {
            double acc = 0.0;
            for (int k = 0; k < 9; ++k) acc += W[k] * map[9 * k + l];
            Hrot[l] = acc;
        }
        mm(Rk, Hrot, T1);
        mmt(T1, Rn, Hw);
        const std::vector<int> &cols = t.cols[b];
        const double *Tn = &nxt.Th[3 * n * b], *Tk = &cur.Th[3 * n * b];
        const double *Yn = &nxt.Y[3 * n * b], *Yk = &cur.Y[3 * n * b];
        for (int j : cols)
            for (int i = 0; i < 3; ++i) w.HT[i * n + j] = Hw[3 * i] * Tn[j] + Hw[3 * i + 1] * Tn[n + j] + Hw[3 * i + 2] * Tn[2 * n + j];
        double s = t.mass[b] / t.h;
        for (int a : cols) {
            double k0 = Tk[a], k1 = Tk[n + a], k2 = Tk[2 * n + a];
            double y0 = s * Yk[a], y1 = s * Yk[n + a], y2 = s * Yk[2 * n + a];
            double *Jrow = &w.J[a * n];
            for (int j : cols)
                Jrow[j] += k0 * w.HT[j] + k1 * w.HT[n + j] + k2 * w.HT[2 * n + j] -
                           (y0 * Yn[j] + y1 * Yn[n + j] + y2 * Yn[2 * n + j]);
        }
    }
    if (!t.damped) return;
    // -(h/2) diag(d) times each rotational joint's (tr(W) I - W^T) / (2h) on its own DoF (fused.add_damping_jacobian)
    for (int b = 0; b < t.B; ++b) {
        int kind = (int)t.kind[b];
        if (kind == 3) continue;
        double W[9], blk[9];
        mtm(&cur.R[9 * b], &nxt.R[9 * b], W);
        double tr = W[0] + W[4] + W[8];
        for (int i = 0; i < 3; ++i)
            for (int j = 0; j < 3; ++j) blk[3 * i + j] = ((i == j ? tr : 0.0) - W[3 * j + i]) / (2 * t.h);
        int c = (int)t.col[b];
        if (kind == 2) {
            const double *ax = &t.axis[3 * b];
            double v = 0.0;
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j) v += ax[i] * blk[3 * i + j] * ax[j];
            w.J[c * n + c] += -0.5 * t.h * t.damping[c] * v;
        } else {
            for (int i = 0; i < 3; ++i)
                for (int j = 0; j < 3; ++j) w.J[(c + i) * n + c + j] += -0.5 * t.h * t.damping[c + i] * blk[3 * i + j];
        }
    }
}

// q' = the joints of q advanced by d (lie.joints.advance): ball R exp(d), hinge R exp(d a), the free root
// (R exp(w), p + R V(w) v); then its forward kinematics
void advance(const TreeSpec &t, const Frame &q, const double *d, Frame &out) {
    for (int b = 0; b < t.B; ++b) {
        int c = (int)t.col[b];
        double e[3] = {0, 0, 0}, E[9];
        switch (t.kind[b]) {
            case 0:
            case 1:
                e[0] = d[c], e[1] = d[c + 1], e[2] = d[c + 2];
                break;
            case 2:
                for (int i = 0; i < 3; ++i) e[i] = d[c] * t.axis[3 * b + i];
                break;
            default:
                std::memcpy(&out.R[9 * b], &q.R[9 * b], 9 * sizeof(double));
                continue;
        }
        so3_exp(e, E);
        mm(&q.R[9 * b], E, &out.R[9 * b]);
    }
    if (t.m) {
        const double *w = &d[t.col[0]], *v = &d[t.col[0] + 3];
        double V[9], Vv[3], RVv[3];
        V_matrix(w, V);
        mv(V, v, Vv);
        mv(&q.R[0], Vv, RVv);
        for (int i = 0; i < 3; ++i) out.p[i] = q.p[i] + RVv[i];
    }
    forward_kinematics(t, out);
}

// cur (prev^-1 cur) in the moving coordinates (the tree's own on an unreduced tree): the last increment
// applied at cur, as `ProductGroup.compose(g_k, inc)`
void compose_last(const TreeSpec &t, const Frame &prev, const Frame &cur, Frame &out) {
    for (int b = 0; b < t.B; ++b) {
        double W[9];
        mtm(&prev.R[9 * b], &cur.R[9 * b], W);
        mm(&cur.R[9 * b], W, &out.R[9 * b]);
    }
    if (t.m) {
        double dp[3] = {cur.p[0] - prev.p[0], cur.p[1] - prev.p[1], cur.p[2] - prev.p[2]}, z[3], Rz[3];
        mtv(&prev.R[0], dp, z);
        mv(&cur.R[0], z, Rz);
        for (int i = 0; i < 3; ++i) out.p[i] = cur.p[i] + Rz[i];
    }
}

// tree coordinates <-> joint coordinates
void load_pose(const TreeSpec &t, const double *R, const double *p, Frame &F) {
    if (t.world && !t.joint_mode) {
        std::memcpy(F.Rw.data(), R, 9 * t.B * sizeof(double));
        std::memcpy(F.R.data(), R, 9 * t.B * sizeof(double));
    } else if (t.world) {
        std::memcpy(F.Rw.data(), R, 9 * t.B * sizeof(double));
        for (int b = 0; b < t.B; ++b) {
            int a = (int)t.parents[b];
            if (a < 0)
                std::memcpy(&F.R[0], R, 9 * sizeof(double));
            else
                mtm(&R[9 * a], &R[9 * b], &F.R[9 * b]);
        }
    } else {
        std::memcpy(F.R.data(), R, 9 * t.B * sizeof(double));
    }
    if (t.m) std::memcpy(F.p, p, 3 * sizeof(double));
    forward_kinematics(t, F, t.world != 0);
}
inline const double *tree_R(const TreeSpec &t, const Frame &F) { return t.world ? F.Rw.data() : F.R.data(); }

// the joints' DoF of the increment qa -> qb: S0^+ log(qa^-1 qb) (mechanics.articulated.step_coordinates)
void step_coordinates(const TreeSpec &t, const Frame &qa, const Frame &qb, Work &w, double *dof) {
    for (int b = 0; b < t.B; ++b) {
        double W[9];
        mtm(&qa.R[9 * b], &qb.R[9 * b], W);
        int r0 = (int)t.row[b];
        so3_log(W, &w.xi[r0]);
        if (b < t.m) {
            double d[3] = {qb.p[0] - qa.p[0], qb.p[1] - qa.p[1], qb.p[2] - qa.p[2]}, z[3], Vi[9];
            mtv(&qa.R[0], d, z);
            V_inverse(&w.xi[r0], Vi);
            mv(Vi, z, &w.xi[r0 + 3]);
        }
    }
    for (int j = 0; j < t.n; ++j) {
        double acc = 0.0;
        for (int k = 0; k < t.dim; ++k) acc += t.S0pinv[j * t.dim + k] * w.xi[k];
        dof[j] = acc;
    }
}

inline double norm2(const std::vector<double> &v) {
    double s = 0.0;
    for (double x : v) s += x * x;
    return std::sqrt(s);
}

}  // namespace

extern "C" {

// Roll `count` steps of N trajectories on from their state, in place: (Rp, pp) g_{k-1} and (Rc, pc) g_k
// in tree coordinates (N, B, 3, 3) / (N, m, 3), dof (N, n) the last increment's DoF, dof_prev (N, n) the
// one before where has_prev (N) is 1; has_prev 2: a new rollout, dof computed here from the two poses
// (mechanics.articulated.step_coordinates). Writes the new poses (N, count, B, 3, 3) / (N, count, m, 3), and per
// step converged (N, count), Newton iterations (N, count) and the residual's max norm (N, count).
// chord: the Jacobian of a step's first iterate and its LU factors serve all its iterations
// (SolverOptions.method "chord"). `threads` > 1 splits the rows over that many threads (each row's result does not depend on it).
// Returns 0.
int liedfl_articulated_rollout(
    int64_t N, int64_t count, int64_t B, int64_t n, int64_t dim, int64_t m, int64_t world, int64_t joint_mode,
    int64_t reduced, const int64_t *parents,
    const int64_t *kind, const int64_t *col, const int64_t *row, const double *axis, const double *offsets,
    const double *Jd, const double *mass, const double *rho, const double *rot_map, int64_t gravity,
    const double *gamma, const double *first_moment, const double *gmass, int64_t damped, const double *damping,
    const double *S0pinv, double h, double tol, int64_t max_iter, int64_t max_halvings, int64_t chord, double *Rp, double *pp,
    double *Rc, double *pc, double *dof, double *dof_prev, uint8_t *has_prev, double *outR, double *outp,
    uint8_t *converged, int64_t *iterations, double *residual_norm, int64_t threads) {
    TreeSpec t{(int)B, (int)n, (int)dim, (int)m, (int)world, (int)joint_mode, (int)reduced, (int)max_iter, (int)max_halvings, (int)chord, h, tol,
               parents, kind, col, row, axis, offsets, Jd, mass, rho, rot_map, (int)gravity, (int)damped,
               gamma, first_moment, gmass, damping, S0pinv, {}};
    // the columns each body's Jacobian reaches: its own joint's and its ancestors'
    std::vector<int> ndof(B, 0);
    for (int b = 0; b < B; ++b) ndof[b] = (int)(b + 1 < B ? col[b + 1] : n) - (int)col[b];
    t.cols.resize(B);
    for (int b = 0; b < B; ++b) {
        for (int a = b; a >= 0; a = (int)parents[a])
            for (int k = 0; k < ndof[a]; ++k) t.cols[b].push_back((int)col[a] + k);
        std::sort(t.cols[b].begin(), t.cols[b].end());
    }
    const double eps = std::numeric_limits<double>::epsilon();
    const double big = std::numeric_limits<double>::max();
    // rows i0..i1-1, each with its own work space (rows are independent: any split gives the same bits)
    auto rows = [&](int64_t i0, int64_t i1) {
        Frame prev, cur, nxt, cand;
        prev.init(t), cur.init(t), nxt.init(t), cand.init(t);
        Work w;
        w.init(t);
        std::vector<double> cst(n), d(n), gR(9 * B);
        for (int64_t i = i0; i < i1; ++i) {
            double *rp = Rp + i * 9 * B, *rc_ = Rc + i * 9 * B, *ppi = pp + i * 3 * m, *pci = pc + i * 3 * m;
            double *dofi = dof + i * n, *dpi = dof_prev + i * n;
            load_pose(t, rp, ppi, prev);
            load_pose(t, rc_, pci, cur);
            if (has_prev[i] == 2) {  // a new rollout: the first increment's DoF from its two poses
                step_coordinates(t, prev, cur, w, dofi);
                has_prev[i] = 0;
            }
            for (int64_t k = 0; k < count; ++k) {
                residual_const(t, prev, cur, w, cst.data());
                // warm start: the last two increments' DoF extrapolated (2 d_k - d_{k-1}, where finite)
                bool fin = true;
                for (int j = 0; j < n; ++j) {
                    d[j] = has_prev[i] ? 2.0 * dofi[j] - dpi[j] : dofi[j];
                    fin = fin && std::isfinite(d[j]);
                }
                if (!fin)
                    for (int j = 0; j < n; ++j) d[j] = dofi[j];
                if (t.reduced) {
                    advance(t, cur, d.data(), nxt);
                } else {  // an unreduced tree: the last increment applied again, then moved by d - d_k
                    compose_last(t, prev, cur, cand);
                    for (int j = 0; j < n; ++j) d[j] = has_prev[i] ? d[j] - dofi[j] : 0.0;
                    advance(t, cand, d.data(), nxt);
                }
                residual(t, cur, nxt, cst.data(), w, w.r.data());
                double rn = norm2(w.r);
                bool conv = false, factor_singular = false;
                int it = 0;
                for (; it < t.max_iter && !conv; ++it) {
                    double scale = 0.0;
                    if (m) {
                        double dp[3] = {nxt.p[0] - cur.p[0], nxt.p[1] - cur.p[1], nxt.p[2] - cur.p[2]}, z[3];
                        mtv(&cur.R[0], dp, z);
                        for (int q = 0; q < 3; ++q) scale = std::fmax(scale, std::fabs(z[q]));
                    }
                    double step_tol = std::fmax(tol, 16.0 * eps * std::fmax(scale, 1.0));
                    // Newton: the Jacobian at every iterate; chord: at the step's first, its LU factors reused
                    if (!t.chord || it == 0) {
                        jacobian(t, cur, nxt, w);
                        factor_singular = !lu_factor(w.J.data(), (int)n, w.piv.data());
                    }
                    bool singular = factor_singular;
                    for (int j = 0; j < n; ++j) w.delta[j] = -w.r[j];
                    if (!singular) lu_solve(w.J.data(), (int)n, w.piv.data(), w.delta.data());
                    double full = 0.0;
                    bool finite = !singular;
                    for (int j = 0; j < n && finite; ++j) finite = std::isfinite(w.delta[j]);
                    if (!finite) {  // a singular Jacobian: no step on this iteration (the step fails)
                        singular = true;
                        std::fill(w.delta.begin(), w.delta.end(), 0.0);
                    }
                    for (int j = 0; j < n; ++j) full = std::fmax(full, std::fabs(w.delta[j]));
                    // backtracking on ||f||_2 (solvers.newton._careful_iteration); without a decrease the
                    // full step is taken where its residual is finite
                    double alpha = 1.0;
                    bool accepted = false;
                    for (int hh = 0; hh <= t.max_halvings; ++hh) {
                        for (int j = 0; j < n; ++j) d[j] = alpha * w.delta[j];
                        advance(t, nxt, d.data(), cand);
                        residual(t, cur, cand, cst.data(), w, w.rc.data());
                        double rcn = norm2(w.rc);
                        if (std::isfinite(rcn) && rcn <= std::fmin(rn * (1 - 1e-4 * alpha) + 1e-300, big)) {
                            accepted = true;
                            std::swap(nxt, cand);
                            std::swap(w.r, w.rc);
                            rn = rcn;
                            break;
                        }
                        alpha *= 0.5;
                    }
                    if (!accepted) {
                        advance(t, nxt, w.delta.data(), cand);
                        residual(t, cur, cand, cst.data(), w, w.rc.data());
                        double rcn = norm2(w.rc);
                        if (std::isfinite(rcn)) {
                            std::swap(nxt, cand);
                            std::swap(w.r, w.rc);
                            rn = rcn;
                        }
                    }
                    conv = !singular && full <= step_tol && std::isfinite(rn);
                }
                double rmax = 0.0;
                bool rnan = false;
                for (int j = 0; j < n; ++j) {
                    rmax = std::fmax(rmax, std::fabs(w.r[j]));
                    rnan = rnan || std::isnan(w.r[j]);
                }
                converged[i * count + k] = conv ? 1 : 0;
                iterations[i * count + k] = it;
                residual_norm[i * count + k] = rnan ? std::numeric_limits<double>::quiet_NaN() : rmax;
                // g_{k+1} = g_k inc with the increment's rotations re-orthonormalised by one Newton-Schulz
                // step (the model's implicit_advance), in the tree's coordinates
                const double *Rk = tree_R(t, cur), *Rn = tree_R(t, nxt);
                for (int b = 0; b < B; ++b) {
                    double W[9], WtW[9], M[9], Wn[9];
                    mtm(&Rk[9 * b], &Rn[9 * b], W);
                    mtm(W, W, WtW);
                    for (int q = 0; q < 9; ++q) M[q] = -WtW[q];
                    M[0] += 3.0, M[4] += 3.0, M[8] += 3.0;
                    mm(W, M, Wn);
                    for (int q = 0; q < 9; ++q) Wn[q] *= 0.5;
                    mm(&Rk[9 * b], Wn, &gR[9 * b]);
                }
                double gp[3] = {0, 0, 0};
                if (m) {
                    double dp[3] = {nxt.p[0] - cur.p[0], nxt.p[1] - cur.p[1], nxt.p[2] - cur.p[2]}, z[3], Rz[3];
                    mtv(&cur.R[0], dp, z);
                    mv(&cur.R[0], z, Rz);
                    for (int q = 0; q < 3; ++q) gp[q] = cur.p[q] + Rz[q];
                }
                std::memcpy(outR + (i * count + k) * 9 * B, gR.data(), 9 * B * sizeof(double));
                if (m) std::memcpy(outp + (i * count + k) * 3, gp, 3 * sizeof(double));
                load_pose(t, gR.data(), gp, nxt);
                std::memcpy(dpi, dofi, n * sizeof(double));
                step_coordinates(t, cur, nxt, w, dofi);
                has_prev[i] = 1;
                std::swap(prev, cur);
                std::swap(cur, nxt);
            }
            std::memcpy(rp, tree_R(t, prev), 9 * B * sizeof(double));
            std::memcpy(rc_, tree_R(t, cur), 9 * B * sizeof(double));
            if (m) std::memcpy(ppi, prev.p, 3 * sizeof(double)), std::memcpy(pci, cur.p, 3 * sizeof(double));
        }
    };
    split_rows(N, threads, rows);
    return 0;
}
}
