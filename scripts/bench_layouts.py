"""Layouts of the articulated engine's small products, timed side by side (issue 34: where the time of a
5-body step goes and what another layout would buy).

    python scripts/bench_layouts.py [--repeats 200] [--compile] [--json FILE]

Shapes are those of a 5-body tree at batch 1,000 (N 1,000, B 5, n 18 unknown columns), float64, one
thread; milliseconds per call, best of three rounds of `repeats` calls, each row with its error against the
first row of its group. Groups:

- `product3`: 5,000 3x3 products A B: `torch.bmm` (N B, 3, 3) (what the engine does); the same batch-first
  by columns (three broadcast multiply-adds); broadcast-and-sum; and planes (3, 3, N B) with the batch last
  (three broadcast multiply-adds over contiguous planes: a structure-of-arrays layout).
- `cross_columns`: a x v for every column of a (N, B, 3, n): the stacked form (the engine before
  2026-12-07) and rows written into one buffer (after).
- `jacobian`: the Newton Jacobian's sum Theta_k^T H Theta_n - (m/h) Y_k^T Y_n (N, n, n) from (N, 3B, n)
  factors: one product of concatenated factors (before), two products into one buffer (after).
- with `--compile` (tens of seconds of `torch.compile`): the chain R_k (R_k^T R_n + H) R_n^T of 3x3
  matrices eager batch-first, compiled batch-first and compiled batch-last, and the Jacobian's sum compiled
  batch-last: what a compiled structure-of-arrays engine would be made of.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

from machine_info import cpu_model

from liedfl_cli.files.io_utils import write_json

N, B, n = 1000, 5, 18


def best_ms(fn, repeats: int) -> float:
    fn()
    best = float("inf")
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(repeats):
            fn()
        best = min(best, (time.perf_counter() - t) / repeats * 1e3)
    return best


def group(rows: dict, repeats: int) -> dict:
    """name -> (fn, how to compare its output with the first row's) -> {ms, max_abs_error}."""
    out, ref = {}, None
    for name, (fn, to_ref) in rows.items():
        value = to_ref(fn())
        ref = value if ref is None else ref
        out[name] = {"ms": best_ms(fn, repeats), "max_abs_error": float((value - ref).abs().max())}
    return out


def same(x):
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=200)
    ap.add_argument("--compile", action="store_true", help="also the compiled layouts (tens of seconds)")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()
    torch.set_num_threads(1)
    gen = torch.Generator().manual_seed(0)

    def rnd(*shape):
        return torch.randn(*shape, generator=gen, dtype=torch.float64)

    load_start = os.getloadavg()[0]
    M = N * B
    A, Bm = rnd(M, 3, 3), rnd(M, 3, 3)
    Ap, Bp = A.permute(1, 2, 0).contiguous(), Bm.permute(1, 2, 0).contiguous()

    def columns(a, b):
        out = torch.mul(a[..., :, 0:1], b[..., 0:1, :])
        out.addcmul_(a[..., :, 1:2], b[..., 1:2, :])
        return out.addcmul_(a[..., :, 2:3], b[..., 2:3, :])

    def planes(a, b):  # (3, 3, M): row i of a times row k of b, the batch innermost
        out = torch.mul(a[:, 0:1], b[0:1])
        out.addcmul_(a[:, 1:2], b[1:2])
        return out.addcmul_(a[:, 2:3], b[2:3])

    def from_planes(x):
        return x.permute(2, 0, 1)

    figures: dict = {
        "product3": group(
            {
                "bmm batch-first (engine)": (lambda: torch.bmm(A, Bm), same),
                "columns batch-first": (lambda: columns(A, Bm), same),
                "broadcast-and-sum batch-first": (lambda: (A[..., :, :, None] * Bm[..., None, :, :]).sum(-2), same),
                "planes batch-last": (lambda: planes(Ap, Bp), from_planes),
            },
            args.repeats,
        )
    }
    a, v = rnd(N, B, 3, n), rnd(N, B, 3)
    from liedfl_cli.models.articulated.engines.fused import _cross_columns

    def stacked_cross(a, v):
        a0, a1, a2 = a.unbind(-2)
        v0, v1, v2 = (x[..., None] for x in v.unbind(-1))
        return torch.stack((a1 * v2 - a2 * v1, a2 * v0 - a0 * v2, a0 * v1 - a1 * v0), -2)

    figures["cross_columns"] = group(
        {
            "stacked (before)": (lambda: stacked_cross(a, v), same),
            "rows into one buffer (after)": (lambda: _cross_columns(a, v), same),
        },
        args.repeats,
    )
    Tk, HT, Yk, Yn = (rnd(N, 3 * B, n) for _ in range(4))

    def concatenated():
        left = torch.cat((Tk, Yk), 1).transpose(1, 2)
        return torch.bmm(left, torch.cat((HT, Yn.neg()), 1))

    def two_products():
        return torch.baddbmm(torch.bmm(Tk.mT, HT), Yk.mT, Yn, alpha=-1)

    jac_rows = {"concatenated factors (before)": (concatenated, same), "two products (after)": (two_products, same)}
    if args.compile:
        tk, ht, yk, yn = (x.movedim(0, -1).contiguous() for x in (Tk, HT, Yk, Yn))

        def jac_last(tk, ht, yk, yn):  # (3B, n, N) factors -> (n, n, N)
            return (tk[:, :, None] * ht[:, None]).sum(0) - (yk[:, :, None] * yn[:, None]).sum(0)

        t = time.perf_counter()
        cj = torch.compile(jac_last, dynamic=False)
        cj(tk, ht, yk, yn)
        figures["compile_s_jacobian"] = time.perf_counter() - t
        jac_rows["compiled batch-last"] = (lambda: cj(tk, ht, yk, yn), lambda x: x.movedim(-1, 0))
    figures["jacobian"] = group(jac_rows, max(1, args.repeats // 10))
    if args.compile:
        Rk, Rn, H = rnd(N, B, 3, 3), rnd(N, B, 3, 3), rnd(N, B, 3, 3)
        rk, rn, hh = (x.movedim(0, -1).contiguous() for x in (Rk, Rn, H))

        def chain_first(Rk, Rn, H):
            return Rk @ (Rk.mT @ Rn + H) @ Rn.mT

        def mm_last(x, y):  # (B, 3, 3, N) products, the batch last
            return (x[:, :, :, None] * y[:, None]).sum(2)

        def chain_last(rk, rn, hh):
            return mm_last(mm_last(rk, mm_last(rk.transpose(1, 2), rn) + hh), rn.transpose(1, 2))

        t = time.perf_counter()
        c_first, c_last = torch.compile(chain_first, dynamic=False), torch.compile(chain_last, dynamic=False)
        c_first(Rk, Rn, H)
        c_last(rk, rn, hh)
        figures["compile_s_chains"] = time.perf_counter() - t
        figures["chain3"] = group(
            {
                "eager batch-first (engine)": (lambda: chain_first(Rk, Rn, H), same),
                "compiled batch-first": (lambda: c_first(Rk, Rn, H), same),
                "compiled batch-last": (lambda: c_last(rk, rn, hh), lambda x: x.movedim(-1, 0)),
            },
            args.repeats,
        )
    out = {
        "cpu": cpu_model(),
        "threads": 1,
        "shapes": {"N": N, "B": B, "n": n},
        "repeats": args.repeats,
        "load_1min_start": load_start,
        "load_1min_end": os.getloadavg()[0],
        "ms_per_call": figures,
    }
    for name, rows in figures.items():
        if isinstance(rows, dict):
            first = next(iter(rows.values()))["ms"]
            for row, fig in rows.items():
                ratio, err = first / fig["ms"], fig["max_abs_error"]
                print(f"{name:14s} {row:32s} {fig['ms']:8.3f} ms  {ratio:5.2f}x  error {err:.1e}")
        else:
            print(f"{name}: {rows:.1f} s")
    print(f"CPU {out['cpu']}, one thread, load {load_start:.2f} -> {out['load_1min_end']:.2f}")
    if args.json:
        write_json(args.json, out)  # write then rename: a killed run never leaves half a record


if __name__ == "__main__":
    main()
