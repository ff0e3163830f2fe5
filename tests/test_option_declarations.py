"""Each option is declared once, on its dataclass field (config/fields.py, config/typed.py): the
allowed values, bounds and the commands that need it come from there, and schema.py keeps no mirror
of them (docs/architecture.md, "Where an option is declared"): the optimiser's names (its registry is
built from them), a model's allowed values on its own `Options` fields (read for that model only), the
trainer's nested sections' bounds."""

from __future__ import annotations

import dataclasses

import pytest

from helpers import compose_config
from liedfl_cli.commands.export import EXPORTS
from liedfl_cli.commands.optimizers import OPTIMIZERS, SCHEDULES
from liedfl_cli.config import schema, typed
from liedfl_cli.config.fields import allowed, check_values, field_checks
from liedfl_cli.config.other_data import SPLITS
from liedfl_cli.config.typed import OptimizerConfig
from liedfl_cli.errors import ConfigError
from liedfl_cli.models.base import POTENTIAL_PARTS
from liedfl_cli.models.liedflnn.model import KINETIC_KINDS, KNOWN_PARTS, RESIDUAL_MODES, LieDFLNNOptions
from liedfl_cli.models.liedflnn.residual import FORMS
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
        (typed.OptimizerConfig, {"name": "sgd"}, "train.optimizer.name='sgd': choose one of soap, adam"),
        (typed.OptimizerConfig, {"lr": 0}, "train.optimizer.lr=0: must be a positive number"),
        (typed.EarlyStoppingConfig, {"min_delta": -1}, "train.early_stopping.min_delta=-1: must be a number >= 0"),
        (
            typed.EarlyStoppingConfig,
            {"patience": 0},
            "train.early_stopping.patience=0: must be a positive integer or null",
        ),
        (
            typed.OptimizerConfig,
            {"precondition_frequency": 0},
            "train.optimizer.precondition_frequency=0: must be a positive integer",
        ),
        (typed.RolloutLossConfig, {"horizon": 0}, "train.rollout_loss.horizon=0: must be a positive integer"),
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
    # what schema.py still lists: the runtime's two options (checked against solvers/runtime.py's lists)
    assert set(schema.CHOICES) == {("runtime", "device"), ("runtime", "dtype")}


def test_required_keys_are_derived_from_the_fields():
    """The keys each command reads, in the order a removed one is reported (as listed by hand before)."""
    solver = ("solver.tol", "solver.max_iter", "solver.max_halvings")
    assert schema.required("train") == (
        "seed",
        *(f"train.{k}" for k in ("epochs", "batch_size")),
        *(f"train.optimizer.{k}" for k in ("name", "lr", "weight_decay")),  # OptimizerConfig's own fields
        *(f"train.{k}" for k in ("w_del", "w_reg", "reg_points", "reg_form", "epsilon")),
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


def test_the_optimiser_registry_is_the_fields_names():
    assert tuple(OPTIMIZERS) == allowed(OptimizerConfig, "name")
    assert tuple(SCHEDULES) == allowed(OptimizerConfig, "schedule")
    assert all(callable(b) for b in (*OPTIMIZERS.values(), *SCHEDULES.values()))


def test_lieDFLNN_declares_its_values_on_its_options_fields():
    checks = field_checks(LieDFLNNOptions)
    assert checks["residual"].choices == RESIDUAL_MODES == tuple(FORMS)
    assert checks["kinetic"].choices == KINETIC_KINDS
    assert checks["known"].each_of == KNOWN_PARTS
    assert checks["potential"].each_of == POTENTIAL_PARTS and set(POTENTIAL_PARTS) < set(checks["potential"].choices)
    assert not any(path[0] == "model" for path in schema.CHOICES)  # no model list applied to every model


@pytest.mark.parametrize(
    "values, line",
    [
        ({"residual": "exact"}, "model.residual='exact': choose one of fast, generic"),
        ({"potential": ["mlp", "spring"]}, "model.potential=['mlp', 'spring']: unknown part 'spring'; choose from"),
        ({"potential": ["mlp", "mlp"]}, "model.potential=['mlp', 'mlp']: a part is given twice"),
        ({"known": ["mass"]}, "model.known=['mass']: unknown part 'mass'; choose from inertia, potential, damping"),
    ],
)
def test_a_bad_model_value_is_one_line_naming_the_key(values, line):
    with pytest.raises(ConfigError) as e:
        check_values(values, LieDFLNNOptions, "model")
    assert str(e.value).startswith(line)


def test_good_model_values_pass():
    check_values(
        {"residual": "generic", "potential": ["uniform_gravity", "mlp"], "known": []}, LieDFLNNOptions, "model"
    )
    check_values({"potential": "none", "kinetic": "articulated"}, LieDFLNNOptions, "model")


def test_the_schema_refuses_a_model_value_for_liedflnn_only():
    cfg = compose_config("train", ["model.residual=exact"])
    with pytest.raises(ConfigError, match="model.residual='exact': choose one of"):
        schema.validate(cfg, "train")
    schema.validate(compose_config("train", ["baseline=neural_ode"]), "train")  # other models: their own fields
