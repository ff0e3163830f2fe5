"""The articulated model's own config (`model=articulated`, conf/model/articulated.yaml: LieDFLNN's options
read from liedflnn.yaml, its own `_target_` and `Options`): it builds the same model as `model.kinetic=
articulated`, trains end to end from the CLI, refuses per_body and data without a tree in one line."""

from __future__ import annotations

import pytest
import torch

from helpers import SMOKE, compose_config, model_file, train_run
from liedfl_cli.config import schema
from liedfl_cli.config.factory import build_model, model_class
from liedfl_cli.config.runs import load_run
from liedfl_cli.errors import ConfigError
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN, ArticulatedOptions
from liedfl_cli.models.liedflnn.model import LieDFLNNOptions


@pytest.fixture(scope="module")
def chain_file(tmp_path_factory):
    pytest.importorskip("mujoco")
    from liedfl_cli.data.hdf5 import save_dataset
    from liedfl_cli.data.mujoco_chain import chain_dataset

    root = tmp_path_factory.mktemp("chain")
    save_dataset(chain_dataset(n_trajectories=6, steps=10, seed=5, links=3, h=0.05), root / "chain.h5")
    return root / "chain.h5"


def _cfg(tmp_path, chain_file, *extra):
    paths = (f"paths.data_dir={tmp_path}/data", f"paths.output_dir={tmp_path}/run")
    return compose_config(
        "train", ("dataset=file", f"dataset.path={chain_file}", *SMOKE, *paths, "runtime.threads=1", *extra)
    )


def test_the_file_reads_liedflnns_options_and_names_its_own_class():
    art, base = model_file("articulated"), model_file("liedflnn")
    assert model_class(art._target_) is ArticulatedLieDFLNN and art.name == "articulated"
    assert art.kinetic == "articulated"
    assert {k: v for k, v in art.items() if k not in ("_target_", "name", "kinetic")} == {
        k: v for k, v in base.items() if k not in ("_target_", "name", "kinetic")
    }
    assert issubclass(ArticulatedOptions, LieDFLNNOptions) and ArticulatedLieDFLNN.Options is ArticulatedOptions


def test_model_articulated_is_the_model_kinetic_articulated_builds(tmp_path, chain_file):
    from liedfl_cli.data.hdf5 import load_dataset

    ds = load_dataset(chain_file)
    a = build_model(_cfg(tmp_path, chain_file, "model=articulated"), ds)
    b = build_model(_cfg(tmp_path, chain_file, "model.kinetic=articulated"), ds)
    assert type(a) is type(b) is ArticulatedLieDFLNN and a.name == "articulated" and b.name == "liedflnn"
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)


def test_model_articulated_trains_and_reloads(tmp_path, chain_file):
    from liedfl_cli.solvers import runtime

    settings = runtime._current
    try:
        run = train_run(
            tmp_path, "dataset=file", f"dataset.path={chain_file}", "model=articulated", "train.epochs=2", *SMOKE[1:]
        )  # (no figures: this test reads none; budget=smoke would ask the 10-step file for 12 steps)
    finally:
        runtime._current = settings  # run_train configures the runtime: restore it
    import csv
    import math

    rows = {r["model"]: r for r in csv.DictReader((run / "eval.csv").open())}
    assert math.isfinite(float(rows["model"]["rel_rot_error_mean"]))
    assert "constant_velocity" in rows and "constant_acceleration" in rows  # the guesses beside it
    _, model, _, _ = load_run(run)
    assert isinstance(model, ArticulatedLieDFLNN) and model.name == "articulated"


def test_per_body_and_data_without_a_tree_are_one_line_errors(tmp_path, chain_file):
    from liedfl_cli.data.hdf5 import load_dataset

    with pytest.raises(ConfigError, match="model=articulated with model.kinetic=per_body") as e:
        build_model(_cfg(tmp_path, chain_file, "model=articulated", "model.kinetic=per_body"), load_dataset(chain_file))
    assert "\n" not in str(e.value)
    cfg = compose_config("train", ("model=articulated", *SMOKE, f"paths.data_dir={tmp_path}/data"))
    schema.validate(cfg, "train")  # the keys are LieDFLNN's: valid; the data decide at build time
    from liedfl_cli.data.scenes import get_dataset

    free, _ = get_dataset(cfg.dataset, data_dir=str(tmp_path / "data"))  # the default scene: one free body
    with pytest.raises(ConfigError, match="needs a kinematic tree"):
        build_model(cfg, free)
    with pytest.raises(ConfigError, match="model.residual='x'"):
        schema.validate(compose_config("train", ("model=articulated", "model.residual=x")), "train")
