"""Training: fit a discrete model to pose triplets of the train split.

loss = w_DEL * mean ||r_k||^2 + w_reg * mean penalty(log|det H|) over `reg_points` random pairs.
Triplets are batched tensors (no Python loop over samples).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from .checkpoint import save_checkpoint
from .errors import ConfigError
from .factory import loss_options
from .io_utils import write_csv, write_json
from .lie import Pose
from .ui import console, progress_bar


def make_optimizer(params, cfg_opt) -> torch.optim.Optimizer:
    name = cfg_opt.name
    if name == "soap":
        from pytorch_optimizer import SOAP

        return SOAP(params, lr=cfg_opt.lr, weight_decay=cfg_opt.weight_decay)
    if name == "adam":
        return torch.optim.Adam(params, lr=cfg_opt.lr, weight_decay=cfg_opt.weight_decay)
    raise ConfigError(f"train.optimizer.name must be 'soap' or 'adam', got {name!r}")


def make_schedule(opt, name: str, epochs: int):
    """Per-epoch learning-rate schedule: constant (paper) or cosine decay to 1% of lr."""
    if name == "constant":
        return None
    if name == "cosine":
        return torch.optim.lr_scheduler.CosineAnnealingLR(
            opt, T_max=max(epochs, 1), eta_min=0.01 * opt.param_groups[0]["lr"]
        )
    raise ConfigError(f"train.optimizer.schedule must be 'constant' or 'cosine', got {name!r}")


def fit(
    model,
    data: Pose,
    cfg_train: DictConfig,
    steps: int,
    seed: int = 0,
    show_progress: bool = True,
    log_epochs: bool = True,
) -> dict:
    """Train `model` on the first `steps` steps of `data` (T, N+1, ...).

    The model says what a sample is (`model.training_set`: pose triplets or whole windows);
    each epoch visits the samples in shuffled mini-batches (plus `reg_points` random pairs per
    batch for models with a regularity term). Returns history and timings.
    """
    opts = loss_options(cfg_train)
    samples = model.training_set(data, int(steps))
    n = samples.n
    bs = min(int(cfg_train.batch_size), n)
    n_batches = math.ceil(n / bs)
    gen = torch.Generator().manual_seed(seed)
    params = [p for p in model.parameters() if p.requires_grad]
    if not params:
        raise ConfigError("the model has no trainable parameters")
    opt = make_optimizer(params, cfg_train.optimizer)
    epochs = int(cfg_train.epochs)
    sched = make_schedule(opt, cfg_train.optimizer.get("schedule", "constant"), epochs)
    history = []
    t0 = time.perf_counter()
    with progress_bar(show_progress) as bar:
        task = bar.add_task("train", total=epochs, loss=float("nan"))
        for epoch in range(1, epochs + 1):
            perm = torch.randperm(n, generator=gen)
            sums: dict[str, float] = {}
            for b in range(n_batches):
                idx = perm[b * bs : (b + 1) * bs]
                opt.zero_grad(set_to_none=True)
                loss, parts = model.loss(samples.batch(idx, gen, opts.reg_points), opts)
                if not torch.isfinite(loss):
                    raise FloatingPointError(f"training loss became {loss.item()} at epoch {epoch}, batch {b}")
                loss.backward()
                opt.step()
                for k, v in {"loss": loss, **parts}.items():
                    sums[k] = sums.get(k, 0.0) + float(v.detach()) / n_batches
            if sched is not None:
                sched.step()
            history.append({"epoch": epoch, **sums, "seconds": time.perf_counter() - t0})
            bar.update(task, advance=1, loss=sums["loss"])
            if log_epochs and not show_progress and (epoch % max(1, epochs // 10) == 0 or epoch == epochs):
                console.print(
                    f"epoch {epoch}/{epochs}  "
                    + "  ".join(f"{k} {v:.3e}" for k, v in sums.items())
                    + f"  ({time.perf_counter() - t0:.1f} s)",
                    highlight=False,
                )
    wall = time.perf_counter() - t0
    return {
        "history": history,
        "train_seconds": wall,
        "seconds_per_epoch": wall / max(epochs, 1),
        "n_samples": n,
        "batches_per_epoch": n_batches,
    }


def count_parameters(model) -> int:
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def run_train(cfg: DictConfig) -> dict:
    """`liedfl train`: data -> model -> fit -> checkpoint -> rollout -> eval. Returns a summary."""
    from .data.scenes import get_dataset
    from .evaluate import run_eval_from_objects
    from .factory import build_model
    from .rollout import rollout_and_save

    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(int(cfg.seed))
    dataset, data_path = get_dataset(cfg.dataset, cfg.paths.data_dir)
    model = build_model(cfg, dataset)
    n_params = count_parameters(model)
    comps = model.components()
    console.print(
        f"[bold]model[/] {type(model).__name__} on {dataset.group.name}, h={dataset.h}: "
        f"components {', '.join(comps)}; {n_params} trainable parameters"
    )
    write_json(out / "components.json", {"model": type(model).__name__, "components": comps, "parameters": n_params})

    train_data = dataset.pose(dataset.train_idx)
    result = fit(
        model, train_data, cfg.train, int(cfg.dataset.train_steps), seed=int(cfg.seed), show_progress=cfg.ui.progress
    )
    write_csv(out / "train_metrics.csv", result["history"])
    timings = {
        "train_seconds": result["train_seconds"],
        "seconds_per_epoch": result["seconds_per_epoch"],
        "epochs": int(cfg.train.epochs),
        "n_samples": result["n_samples"],
        "parameters": n_params,
    }
    from .recovery import parameter_recovery

    recovery = parameter_recovery(model, dataset)
    if recovery is not None:
        write_json(out / "recovery.json", recovery)
    config = OmegaConf.to_container(cfg, resolve=True)
    save_checkpoint(
        out / "checkpoints" / "last.pt",
        model,
        config,
        {"dataset_path": str(Path(data_path).resolve()), "timings": timings, "components": comps},
    )
    console.print(
        f"trained {cfg.train.epochs} epochs in {result['train_seconds']:.1f} s "
        f"(final loss {result['history'][-1]['loss']:.3e}); checkpoint {out / 'checkpoints' / 'last.pt'}"
    )
    summary = {
        "run_dir": str(out),
        "dataset_path": str(Path(data_path).resolve()),
        "timings": timings,
        "final_loss": result["history"][-1]["loss"],
    }
    if cfg.rollout.enabled:
        ro = rollout_and_save(cfg, model, dataset, out / "rollout.h5", steps=cfg.rollout.steps)
        summary["rollout"] = ro
        summary["eval"] = run_eval_from_objects(cfg, dataset, out, timings)
        from .extras import run_extra_evals

        extra = run_extra_evals(cfg, model, dataset, out)
        if extra is not None:
            summary["extra_eval"] = extra
    write_json(out / "summary.json", summary)
    return summary
