"""Microbenchmarks behind the column layout (docs/benchmarks.md, "Column layout for a single SO(3) body").

    python scripts/bench_columns.py [--n 10000]

One torch thread, float64, best of 5 x 50 calls, microseconds per call: 3x3 products of n matrices as
`torch.matmul` on (n, 3, 3) against `fused_columns.matmul` on (3, 3, n); the 2-norm and cross product
along the first axis of (3, n) arrays, torch's kernels against the written-out ones.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from liedfl_cli.models.liedflnn.engines import columns as fused_columns


def best_us(fn, *args, repeats: int = 50) -> float:
    fn(*args)
    best = float("inf")
    for _ in range(5):
        t = time.perf_counter()
        for _ in range(repeats):
            fn(*args)
        best = min(best, (time.perf_counter() - t) / repeats)
    return best * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10000)
    n = ap.parse_args().n
    torch.set_num_threads(1)
    A, B = (torch.randn(n, 3, 3, dtype=torch.float64) for _ in range(2))
    Ac, Bc = (X.permute(1, 2, 0).contiguous() for X in (A, B))
    a, b = torch.randn(3, n, dtype=torch.float64), torch.randn(3, n, dtype=torch.float64)
    rows = {
        "matmul (n, 3, 3)": best_us(torch.matmul, A, B),
        "fused_columns.matmul (3, 3, n)": best_us(fused_columns.matmul, Ac, Bc),
        "linalg.vector_norm(dim=0) (3, n)": best_us(lambda x: torch.linalg.vector_norm(x, dim=0), a),
        "fused_columns.norm (3, n)": best_us(fused_columns.norm, a),
        "linalg.cross(dim=0) (3, n)": best_us(lambda x, y: torch.linalg.cross(x, y, dim=0), a, b),
        "sum of row crosses, fused_columns.row_cross_sum (9, n)": best_us(
            fused_columns.row_cross_sum, Ac.view(9, n), Bc.view(9, n)
        ),
    }
    for name, us in rows.items():
        print(f"{name:>58}: {us:9.1f} us")


if __name__ == "__main__":
    main()
