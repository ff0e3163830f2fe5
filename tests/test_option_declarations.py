"""Each option is declared once, on its dataclass field (config/fields.py, config/typed.py): the
allowed values, bounds and the commands that need it come from there, and schema.py keeps no mirror
of them (only the options other owners are restructuring: docs/architecture.md, "Where an option is
declared")."""

from __future__ import annotations

import dataclasses

import pytest

from liedfl_cli.commands.export import EXPORTS
from liedfl_cli.config import schema, typed
from liedfl_cli.config.fields import field_checks
from liedfl_cli.config.other_data import SPLITS
from liedfl_cli.errors import ConfigError
from liedfl_cli.solvers.options import SolverOptions


@pytest.mark.parametrize(
    ("schema_cls", "values", "message"),
    [
        (typed.TrainConfig, {"loss": "newtn"}, "train.loss='newtn': choose one of del, newton, rollout"),
        (typed.TrainConfig, {"select": "best"}, "train.select='best': choose one of val_one_step, val_rollout, last"),
        (typed.TrainConfig, {"reg_form": "abs"}, "train.reg_form='abs': choose one of relu, gaussian"),
        (typed.TrainConfig, {"start": "x"}, "train.start='x': choose one of auto, identify, none"),
        (typed.TrainConfig, {"epochs": -1}, "train.epochs=-1: must be an integer >= 0"),
        (typed.TrainConfig, {"batch_size": 0}, "train.batch_size=0: must be a positive integer"),
        (typed.TrainConfig, {"w_del": -1}, "train.w_del=-1: must be a number >= 0"),
        (typed.TrainConfig, {"epsilon": float("inf")}, "train.epsilon=inf: must be a finite number"),
        (typed.TrainConfig, {"val_every": 0}, "train.val_every=0: must be auto or a positive integer"),
        (typed.TrainConfig, {"val_horizon": 1}, "train.val_horizon=1: must be an integer >= 2"),
        (typed.RolloutConfig, {"steps": 1}, "rollout.steps=1: must be an integer >= 2 or null"),
        (
            typed.RolloutConfig,
            {"max_trajectories": 0},
            "rollout.max_trajectories=0: must be a positive integer or null",
        ),
        (typed.LoggerConfig, {"name": "wandb"}, "logger.name='wandb': choose one of csv, tensorboard"),
        (typed.SolverConfig, {"tol": 0}, "solver.tol=0: must be a positive number"),
        (typed.SolverConfig, {"max_iter": 0}, "solver.max_iter=0: must be a positive integer"),
        (typed.TopKeys, {"split": "valid"}, "split='valid': choose one of auto, all, train, test"),
        (typed.TopKeys, {"export": "xls"}, "export='xls': choose one of csv, npz"),
        (typed.TopKeys, {"checkpoint": "newest"}, "checkpoint='newest': choose one of best, last"),
    ],
)
def test_a_bad_value_is_refused_by_its_field(schema_cls, values, message):
    """The one-line error comes from the field's declaration, both when the section is built from a
    config (`typed.section`, what `schema.validate` does) and when the dataclass is built directly."""
    with pytest.raises(ConfigError) as built:
        typed.section(schema_cls, values, schema_cls.section)
    assert str(built.value) == message
    with pytest.raises(ConfigError) as direct:
        schema_cls(**values)
    assert str(direct.value) == message


def test_defaults_pass_their_own_checks():
    for cls in (typed.TrainConfig, typed.RolloutConfig, typed.EvalConfig, typed.UiConfig, typed.PathsConfig):
        assert dataclasses.is_dataclass(cls())
    assert typed.solver_options(None) == SolverOptions()  # the solvers get their own plain dataclass
    assert type(typed.solver_options({"tol": 1e-3})) is SolverOptions


def test_value_lists_are_read_from_the_fields():
    assert SPLITS == ("auto", "all", "train", "test") == field_checks(typed.TopKeys)["split"].choices
    assert EXPORTS == ("csv", "npz") == field_checks(typed.TopKeys)["export"].choices
    # what schema.py still lists: the options other owners are restructuring (models, runtime, optimiser)
    assert {path[0] for path in schema.CHOICES} == {"model", "runtime", "train"}
    assert {path[:2] for path in schema.CHOICES if path[0] == "train"} == {("train", "optimizer")}


def test_required_keys_are_derived_from_the_fields():
    """The keys each command reads, in the order a removed one is reported (as listed by hand before)."""
    solver = ("solver.tol", "solver.max_iter", "solver.max_halvings")
    assert schema.required("train") == (
        "seed",
        *(f"train.{k}" for k in ("epochs", "batch_size", "w_del", "w_reg", "reg_points", "reg_form", "epsilon")),
        *(f"train.optimizer.{k}" for k in ("name", "lr", "weight_decay")),
        *(f"rollout.{k}" for k in ("enabled", "steps", "max_trajectories", "reference")),
        *("eval.plots", "ui.progress", "paths.data_dir", "paths.output_dir"),
        *("dataset", "model", "force", "model.name"),
        *solver,
    )
    assert schema.required("data") == ("ui.progress", "paths.data_dir", "dataset")
    assert schema.required("rollout") == (
        *("run", "steps", "rollout.max_trajectories", "rollout.reference", "eval.plots", "ui.progress"),
        *("paths.data_dir", *solver),
    )
    assert schema.required("eval") == ("run", "eval.plots", "ui.progress", "paths.data_dir", *solver)
    assert schema.required("report") == ("sweep", "plots")
    assert schema.required("resume") == ("resume", "ui.progress")
    assert schema.required("export") == ()
