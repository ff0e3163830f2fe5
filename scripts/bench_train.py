"""Training speed of LieDFLNN: seconds per epoch and per optimiser step on the paper's scenes.

    python scripts/bench_train.py [--epochs 3] [--data-dir outputs/data]

Builds each scene's dataset (cached), the model of the matching experiment (paper sizes), and
times `train.fit` for a few epochs at batch 1024 (fast path and generic autodiff path).
"""

import argparse
import time

import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from liedfl_cli.data.scenes import get_dataset
from liedfl_cli.factory import build_model
from liedfl_cli.train import fit, triplets

CASES = [
    ("free body SO(3) (Exp 2)", ["dataset=free_rigid_body"]),
    ("heavy body SO(3), MLP 64x3 (Exp 1)", ["dataset=heavy_so3", "model.potential=mlp"]),
    ("heavy body SE(3), MLP 32x3 (Exp 3)", ["dataset=heavy_se3", "model.mlp_width=32"]),
]


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--data-dir", default="outputs/data")
    args = ap.parse_args()
    import pathlib

    conf = str(pathlib.Path(__file__).resolve().parents[1] / "liedfl_cli" / "conf")
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    print("| scene / model | residual path | triplets | batches / epoch | s / epoch | ms / step |")
    print("|---|---|---|---|---|---|")
    for name, ov in CASES:
        for mode in ("fast", "generic"):
            with initialize_config_dir(config_dir=conf, version_base="1.3"):
                cfg = compose(
                    "train",
                    overrides=[
                        *ov,
                        f"model.residual={mode}",
                        f"paths.data_dir={args.data_dir}",
                        "paths.output_dir=/tmp/liedfl-bench",
                    ],
                )
            ds, _ = get_dataset(cfg.dataset, args.data_dir)
            model = build_model(cfg, ds)
            data = ds.pose(ds.train_idx)
            tcfg = OmegaConf.merge(cfg.train, {"epochs": args.epochs})
            n = triplets(data, int(cfg.dataset.train_steps))[0].R.shape[0]
            t = time.perf_counter()
            out = fit(model, data, tcfg, int(cfg.dataset.train_steps), show_progress=False, log_epochs=False)
            sec = (time.perf_counter() - t) / args.epochs
            print(
                f"| {name} | {mode} | {n} | {out['batches_per_epoch']} | {sec:.3f} | "
                f"{1e3 * sec / out['batches_per_epoch']:.1f} |"
            )


if __name__ == "__main__":
    main()
