"""Damping recovery: a free rigid body (the default scene: 128 trajectories, h = 0.1, training length 100,
batch 1024, SOAP lr 3e-3, epsilon 10) with a NON-diagonal true damping matrix

    D = [[0.05, 0.02, 0.01], [0.02, 0.06, -0.015], [0.01, -0.015, 0.04]]

learned with the current initialisation of D = L L^T + diag(lambda^2) (L = c I: every entry gets gradient)
and with the previous one (L = 0: the gradient of every entry of L is zero, so D stays diagonal).

python scripts/damping_recovery.py [--epochs 500] [--out outputs/damping_recovery]
                                   [--figure docs/img/damping_recovery.png]

Prints the final errors (D / tr J_d against the truth: max entry error over max true entry) and the
learned matrices; writes <out>/summary.json and the figure (error against epoch, both starts).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch
from omegaconf import OmegaConf

from liedfl_cli.cli import CONF_DIR
from liedfl_cli.commands.callbacks import LoggerCallback
from liedfl_cli.commands.train import fit
from liedfl_cli.config.recovery import parameter_recovery
from liedfl_cli.data.scenes import get_dataset
from liedfl_cli.models.liedflnn.model import LieDFLNN

ROOT = Path(__file__).resolve().parents[1]
D_TRUE = [[0.05, 0.02, 0.01], [0.02, 0.06, -0.015], [0.01, -0.015, 0.04]]


def train(ds, start: str, epochs: int) -> dict:
    model = LieDFLNN(ds.group, ds.h, forces=("rayleigh",), epsilon=10.0, seed=0)
    D = model.forces[0].D
    if start == "L = 0 (before)":
        with torch.no_grad():
            d0 = float(D().diagonal()[0])
            D.L_entries.zero_()
            D.lam.fill_(d0**0.5)
    cfg = OmegaConf.load(CONF_DIR / "train.yaml").train
    cfg.epochs = epochs
    curve = []

    def on_epoch(row):
        rec = parameter_recovery(model, ds)
        curve.append((row["epoch"], rec["D_over_trace_max_rel_error"], rec["Jd_over_trace_max_rel_error"]))

    fit(model, ds.pose(ds.train_idx), cfg, 100, seed=0, callbacks=[LoggerCallback(on_epoch)])
    rec = parameter_recovery(model, ds)
    s = float(model.inertia.Jd()[0].trace().detach())
    s_true = sum((1.521, 1.362, 1.211)) / 2
    return {
        "start": start,
        "curve": curve,
        "recovery": rec,
        "D_learned_rescaled": (model.forces[0].D() * s_true / s).detach().tolist(),
    }


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=500)
    ap.add_argument("--out", type=Path, default=Path("outputs/damping_recovery"))
    ap.add_argument("--figure", type=Path, default=ROOT / "docs" / "img" / "damping_recovery.png")
    ap.add_argument("--data-dir", default="outputs/data")
    args = ap.parse_args()
    c = OmegaConf.load(CONF_DIR / "dataset" / "free_rigid_body.yaml")
    c.pop("defaults")
    c.physics.D = D_TRUE
    ds, _ = get_dataset(c, args.data_dir)
    results = [train(ds, s, args.epochs) for s in ("L = c I (now)", "L = 0 (before)")]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "summary.json").write_text(json.dumps({"D_true": D_TRUE, "runs": results}, indent=1))
    for r in results:
        rec = r["recovery"]
        print(
            f"{r['start']}: D error {rec['D_over_trace_max_rel_error']:.4f}, J_d error "
            f"{rec['Jd_over_trace_max_rel_error']:.2e}; D learned (rescaled to the true tr J_d):"
        )
        for row in r["D_learned_rescaled"]:
            print("   ", "  ".join(f"{x:+.5f}" for x in row))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    for r, style in zip(results, ("-", "--")):
        e = [x[0] for x in r["curve"]]
        ax.semilogy(e, [x[1] for x in r["curve"]], style, label=f"D, start {r['start']}")
        ax.semilogy(e, [x[2] for x in r["curve"]], style, alpha=0.5, label=f"J_d, start {r['start']}")
    ax.axhline(0.02, color="0.5", linestyle=":", label="2 %")
    ax.set_xlabel("epoch")
    ax.set_ylabel("max relative error (after / tr J_d)")
    ax.set_title("Non-diagonal damping: recovery against epoch", fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7)
    fig.tight_layout()
    args.figure.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.figure, dpi=110)
    print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
