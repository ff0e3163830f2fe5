"""`liedfl data dataset=<scene>`: generate (or import) a dataset and print where it is."""

from __future__ import annotations

from omegaconf import DictConfig

from ..ui import console


def run_data(cfg: DictConfig):
    from .scenes import get_dataset

    ds, path = get_dataset(cfg.dataset, cfg.paths.data_dir)
    console.print(
        f"[bold]{cfg.dataset.name}[/]: {ds.n_trajectories} trajectories x {ds.n_steps} steps on "
        f"{ds.group.name}, h={ds.h} (train {len(ds.train_idx)}, test {len(ds.test_idx)}) -> {path}"
    )
    return path
