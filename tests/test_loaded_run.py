"""A loaded run's config is typed once, at load (`config/runs.py` `LoadedRun`): `liedfl rollout`,
`liedfl eval`, `liedfl export` and the Python API receive the run's `RunConfig` and never carry the
saved config raw beside it; the saved file format is unchanged."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest
import torch
from omegaconf import DictConfig, ListConfig

from helpers import SMOKE, train_run
from liedfl_cli import api
from liedfl_cli.config.runs import LoadedRun, load_run, load_run_checkpoint
from liedfl_cli.config.typed import RolloutConfig, RunConfig, TrainConfig
from liedfl_cli.data.dataset_config import DatasetConfig
from liedfl_cli.solvers.options import SolverOptions

PACKAGE = Path(__file__).resolve().parents[1] / "liedfl_cli"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("loaded")
    return train_run(root, *SMOKE, "train.epochs=2", "rollout.enabled=false")


def _raw(value) -> bool:
    if isinstance(value, (DictConfig, ListConfig)):
        return True
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return any(_raw(getattr(value, f.name)) for f in dataclasses.fields(value))
    if isinstance(value, dict):
        return any(_raw(v) for v in value.values())
    if isinstance(value, (list, tuple)):
        return any(_raw(v) for v in value)
    return False


def test_a_loaded_run_holds_its_config_typed(run):
    loaded = load_run_checkpoint(run, checkpoint="last")
    assert isinstance(loaded, LoadedRun) and isinstance(loaded.config, RunConfig)
    cfg = loaded.config
    assert isinstance(cfg.train, TrainConfig) and cfg.train.epochs == 2
    assert isinstance(cfg.rollout, RolloutConfig) and cfg.rollout.enabled is False
    assert isinstance(cfg.solver, SolverOptions) and isinstance(cfg.dataset, DatasetConfig)
    assert loaded.model_name == cfg.model["name"] == "liedflnn"
    assert not _raw(cfg)
    # the saved format is unchanged: the checkpoint holds the config as a plain mapping
    saved = torch.load(run / "checkpoints" / "last.pt", weights_only=True)["config"]
    assert isinstance(saved, dict) and saved["train"]["epochs"] == 2
    assert cfg.dataset.as_dict() == saved["dataset"]  # the section as saved (its cache name)
    # load_run's tuple and the API's Run carry the same typed config
    config, model, dataset, run_dir = load_run(run)
    assert isinstance(config, RunConfig) and config.train == cfg.train and run_dir == loaded.run_dir
    assert isinstance(api.load_run(run).config, RunConfig)


def _uses(tree: ast.AST, name: str) -> int:
    return sum(isinstance(n, ast.Name) and n.id == name for n in ast.walk(tree))


@pytest.mark.parametrize(
    ("path", "function"), [("commands/rollout.py", "run_rollout"), ("commands/evaluate.py", "run_eval")]
)
def test_rollout_and_eval_read_their_config_once(path, function):
    """The command's composed config is used once, to type it; everything after reads typed objects."""
    tree = ast.parse((PACKAGE / path).read_text())
    fn = next(n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == function)
    assert _uses(fn, "cfg") == 1, f"{path}: {function} reads its raw config more than once"


@pytest.mark.parametrize("path", ["commands/rollout.py", "commands/evaluate.py", "config/other_data.py", "api.py"])
def test_no_raw_run_config_in_rollout_eval_and_the_api(path):
    source = (PACKAGE / path).read_text()
    assert "OmegaConf" not in source, f"{path} handles a raw config"
