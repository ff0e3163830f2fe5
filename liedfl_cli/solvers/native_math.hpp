// What the native steps share (models/articulated/engines/native_step.cpp, models/liedflnn/engines/native_body.cpp;
// solvers/native_build.py compiles them with this folder on the include path and hashes this file into their
// cache keys): the exp coefficients as functions of t^2 with their Taylor series below `taylor`, row-major 3x3
// products, LU with partial pivoting, and the rows of a batch split over threads.
#pragma once
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

namespace liedfl_native {

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

// 3x3 products, row-major
inline void mm(const double *A, const double *B, double *C) {  // C = A B
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[3 * i + j] = A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j];
}
inline void mtm(const double *A, const double *B, double *C) {  // C = A^T B
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) C[3 * i + j] = A[i] * B[j] + A[3 + i] * B[3 + j] + A[6 + i] * B[6 + j];
}
inline void mmt(const double *A, const double *B, double *C) {  // C = A B^T
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            C[3 * i + j] = A[3 * i] * B[3 * j] + A[3 * i + 1] * B[3 * j + 1] + A[3 * i + 2] * B[3 * j + 2];
}
inline void cross(const double *a, const double *b, double *c) {
    c[0] = a[1] * b[2] - a[2] * b[1];
    c[1] = a[2] * b[0] - a[0] * b[2];
    c[2] = a[0] * b[1] - a[1] * b[0];
}

// LU with partial pivoting of an n x n in place; false on an exactly zero pivot (LAPACK's info > 0)
inline bool lu_factor(double *A, int n, int *piv) {
    bool ok = true;
    for (int k = 0; k < n; ++k) {
        int p = k;
        double best = std::fabs(A[k * n + k]);
        for (int i = k + 1; i < n; ++i) {
            double v = std::fabs(A[i * n + k]);
            if (v > best) best = v, p = i;
        }
        piv[k] = p;
        if (p != k)
            for (int j = 0; j < n; ++j) std::swap(A[k * n + j], A[p * n + j]);
        double d = A[k * n + k];
        if (d == 0.0) {
            ok = false;
            continue;
        }
        double inv = 1.0 / d;
        for (int i = k + 1; i < n; ++i) {
            double l = A[i * n + k] * inv;
            A[i * n + k] = l;
            if (l != 0.0)
                for (int j = k + 1; j < n; ++j) A[i * n + j] -= l * A[k * n + j];
        }
    }
    return ok;
}
inline void lu_solve(const double *A, int n, const int *piv, double *x) {
    for (int k = 0; k < n; ++k)
        if (piv[k] != k) std::swap(x[k], x[piv[k]]);
    for (int i = 1; i < n; ++i)
        for (int k = 0; k < i; ++k) x[i] -= A[i * n + k] * x[k];
    for (int i = n - 1; i >= 0; --i) {
        for (int k = i + 1; k < n; ++k) x[i] -= A[i * n + k] * x[k];
        x[i] /= A[i * n + i];
    }
}

// rows(i0, i1) over [0, N) split over up to `threads` threads, at least 16 rows each (rows are independent:
// any split gives the same bits)
template <class Rows>
void split_rows(int64_t N, int64_t threads, Rows rows) {
    int64_t T = std::max<int64_t>(1, std::min<int64_t>(threads, N / 16));
    if (T == 1) {
        rows(int64_t(0), N);
        return;
    }
    std::vector<std::thread> pool;
    for (int64_t k = 1; k < T; ++k) pool.emplace_back(rows, N * k / T, N * (k + 1) / T);
    rows(int64_t(0), N / T);
    for (std::thread &th : pool) th.join();
}

}  // namespace liedfl_native
