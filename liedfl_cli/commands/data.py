"""`liedfl data dataset=<scene>`: generate (or import) a dataset and print where it is."""

from __future__ import annotations

from omegaconf import DictConfig

from ..config.typed import typed
from ..data.scenes import get_dataset
from ..display.ui import console, err_console


def run_data(cfg: DictConfig):
    run = typed(cfg, "data")
    assert run.dataset is not None, "validated: `liedfl data` has a dataset"
    ds, path = get_dataset(run.dataset, run.paths.data_dir, console=err_console)
    split = (ds.params or {}).get("split_source")
    console.print(
        f"[bold]{run.dataset.name}[/]: {ds.n_trajectories} trajectories x {ds.n_steps} steps on "
        f"{ds.group.name}, h={ds.h} (train {len(ds.train_idx)}, test {len(ds.test_idx)}"
        + (f", {split}" if split else "")
        + f") -> {path}",
        soft_wrap=True,
    )
    if run.dataset.name == "import":
        console.print(
            f"train on it: liedfl train dataset=file dataset.path={path}  (or liedfl train with the same "
            "dataset options)",
            highlight=False,
            markup=False,
            soft_wrap=True,
        )
    return path
