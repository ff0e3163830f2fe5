"""The fine-tuning stage of `train.loss=rollout`: after `train.fit` has trained with the DEL loss for
`train.epochs`, train `train.rollout_loss.epochs` more epochs on the k-step rollout error of windows of
k + 2 true poses (`models.liedflnn.losses.rollout_window_loss`, gradients by the implicit function theorem).

A fresh optimiser of the `train.optimizer` kind (learning rate `train.rollout_loss.lr`, or the
optimiser's when null), mini-batches of `train.batch_size` windows, the run's `solver` settings for
the Newton solves. Each epoch's row goes to `finetune_metrics.csv`; the stage is not checkpointed on
its own (an interrupted run resumes at its DEL stage and fine-tunes again).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable

import torch

from ..config.typed import TrainConfig
from ..display.ui import console, progress_bar
from ..lie import Pose
from ..models.liedflnn.losses import WindowSet, check_loss, rollout_window_loss
from ..solvers.options import SolverOptions
from .optimizers import make_optimizer


def finetune(
    model,
    data: Pose,
    cfg_train: TrainConfig,
    steps: int,
    solver: SolverOptions,
    seed: int = 0,
    show_progress: bool = True,
    on_epoch: Callable[[dict], None] | None = None,
) -> dict:
    """Fine-tune `model` on rollout windows of the first `steps` steps of `data` -> {history, seconds};
    the optimiser is `train.optimizer`'s (`optimizers.make_optimizer`)."""
    check_loss(model, "rollout")
    opts = dataclasses.replace(cfg_train.loss_options(solver), loss="rollout")
    cfg_rl = cfg_train.rollout_loss
    epochs = int(cfg_rl.epochs)
    windows = WindowSet(data, int(steps), opts.rollout_horizon)
    n = windows.n
    bs = n if cfg_train.full_batch else min(int(cfg_train.batch_size), n)
    n_batches = math.ceil(n / bs)
    gen = torch.Generator().manual_seed(seed + 1)
    params = [p for p in model.parameters() if p.requires_grad]
    cfg_opt = cfg_train.optimizer
    if cfg_rl.lr is not None:
        cfg_opt = dataclasses.replace(cfg_opt, lr=float(cfg_rl.lr))
    opt = make_optimizer(params, cfg_opt)
    history: list[dict] = []
    t0 = time.perf_counter()
    with progress_bar(show_progress) as bar:
        task = bar.add_task("fine-tune", total=epochs, completed=0, loss=float("nan"))
        for epoch in range(1, epochs + 1):
            perm = torch.randperm(n, generator=gen)
            sums: dict[str, float] = {}
            for b in range(n_batches):
                opt.zero_grad(set_to_none=True)
                loss, parts = rollout_window_loss(
                    model, windows.batch(perm[b * bs : (b + 1) * bs], gen, 0), opts, solver
                )
                if not torch.isfinite(loss):
                    raise FloatingPointError(
                        f"rollout loss became {loss.item()} at fine-tuning epoch {epoch}, batch {b}"
                    )
                loss.backward()
                opt.step()
                for k, v in {"loss": loss, **parts}.items():
                    sums[k] = sums.get(k, 0.0) + float(v.detach()) / n_batches
            row = {"epoch": epoch, **sums, "seconds": time.perf_counter() - t0}
            history.append(row)
            if on_epoch is not None:
                on_epoch(row)
            bar.update(task, advance=1, loss=sums["loss"])
            if not show_progress and (epoch % max(1, epochs // 10) == 0 or epoch == epochs):
                console.print(
                    f"fine-tune {epoch}/{epochs}  " + "  ".join(f"{k} {v:.3e}" for k, v in sums.items()),
                    highlight=False,
                )
    return {"history": history, "seconds": time.perf_counter() - t0, "windows": n, "epochs": epochs}
