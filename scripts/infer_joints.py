"""Infer every joint of a recording (weld / hinge / universal / ball) and print the evidence table.

python scripts/infer_joints.py <file.h5 | cmu> [--noise RAD] [--raw] [--window 51 --order 6]

file.h5: a dataset file with a kinematic tree (`parents`, `joint_offsets`; docs/data_format.md), all
its trajectories. cmu: the CMU cartwheels of Exp 4 (liedfl_cli/conf/dataset/cmu_cartwheel.yaml,
imported by `liedfl_cli.data.mocap.cmu_cartwheel`) with the experiment's Savitzky-Golay smoothing
(window 51, order 6; --window/--order to change it, --raw for none). --noise: the rotation noise per
sample and axis (rad) instead of the per-joint estimate. Method: liedfl_cli/mechanics/joint_inference.py,
docs/joints.md. Takes seconds.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path

import torch

from liedfl_cli.mechanics.joint_inference import format_inference, infer_joints

CONF = Path(__file__).resolve().parents[1] / "liedfl_cli" / "conf" / "dataset" / "cmu_cartwheel.yaml"


def cmu_dataset(smoothing: dict | None):
    """The cmu_cartwheel scene's Dataset as its config builds it, with `smoothing` ({window, order} or None)."""
    from omegaconf import OmegaConf

    import liedfl_cli.config.resolvers  # noqa: F401  (registers ${len_or:...})
    from liedfl_cli.data.mocap import cmu_cartwheel

    raw = OmegaConf.load(CONF)
    raw.pop("defaults", None)
    c = OmegaConf.to_container(raw, resolve=True)
    assert isinstance(c, dict)
    c["smoothing"] = smoothing
    return cmu_cartwheel(c)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data", help="a dataset file (.h5) with a kinematic tree, or 'cmu'")
    ap.add_argument("--noise", type=float, default=None, help="rotation noise per sample (rad); default: estimated")
    ap.add_argument("--raw", action="store_true", help="cmu: no smoothing")
    ap.add_argument("--window", type=int, default=51, help="cmu: Savitzky-Golay window (odd)")
    ap.add_argument("--order", type=int, default=6, help="cmu: Savitzky-Golay order")
    a = ap.parse_args(argv)
    if a.data == "cmu":
        ds = cmu_dataset(None if a.raw else {"window": a.window, "order": a.order})
        what = "CMU cartwheels 49_06 + 49_07, " + ("raw" if a.raw else f"Savitzky-Golay {a.window}/{a.order}")
    else:
        from liedfl_cli.data.hdf5 import load_dataset

        ds = load_dataset(a.data, require_split=False)
        what = a.data
    if ds.tree is None:
        print(f"{what}: the data have no kinematic tree (parents, joint_offsets)", file=sys.stderr)
        return 2
    R = torch.as_tensor(ds.R, dtype=torch.float64)
    result = infer_joints(ds.tree, R, noise=a.noise)
    T, N1 = R.shape[:2]
    print(f"{what}: {T} trajectories x {N1} samples, {ds.tree.n_bodies} bodies, rotations={ds.tree.rotations}")
    print(format_inference(result, ds.body_names))
    counts = Counter(result.kinds)
    print(
        "summary: "
        + ", ".join(f"{k} {counts[k]}" for k in ("free", "weld", "hinge", "universal", "ball") if k in counts)
    )
    for kind in ("weld", "hinge", "universal", "ball"):
        names = [n for n, k in zip(ds.body_names, result.kinds) if k == kind]
        if names:
            print(f"  {kind}: {', '.join(names)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
