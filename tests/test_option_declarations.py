"""Options declared once (issue 35 item 3): the optimiser's names on their config field (the registry is
built from them), a model's allowed values on its own `Options` fields (read by the schema for that model
only), the bounds of the trainer's nested sections on their fields."""

from __future__ import annotations

import pytest

from helpers import compose_config
from liedfl_cli.commands.optimizers import OPTIMIZERS, SCHEDULES
from liedfl_cli.config import schema
from liedfl_cli.config.fields import allowed, check_values, field_checks
from liedfl_cli.config.typed import EarlyStoppingConfig, OptimizerConfig, RolloutLossConfig
from liedfl_cli.errors import ConfigError
from liedfl_cli.models.base import POTENTIAL_PARTS
from liedfl_cli.models.liedflnn.model import KINETIC_KINDS, KNOWN_PARTS, RESIDUAL_MODES, LieDFLNNOptions
from liedfl_cli.models.liedflnn.residual import FORMS


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


@pytest.mark.parametrize(
    "build, line",
    [
        (lambda: OptimizerConfig(lr=0.0), "train.optimizer.lr=0: must be a positive number"),
        (lambda: OptimizerConfig(precondition_frequency=0), "train.optimizer.precondition_frequency=0: must be"),
        (lambda: EarlyStoppingConfig(patience=0), "train.early_stopping.patience=0: must be a positive integer"),
        (lambda: RolloutLossConfig(horizon=0), "train.rollout_loss.horizon=0: must be a positive integer"),
    ],
)
def test_the_trainer_sections_check_their_own_fields(build, line):
    with pytest.raises(ConfigError) as e:
        build()
    assert str(e.value).startswith(line)


def test_the_schema_refuses_a_model_value_for_liedflnn_only():
    cfg = compose_config("train", ["model.residual=exact"])
    with pytest.raises(ConfigError, match="model.residual='exact': choose one of"):
        schema.validate(cfg, "train")
    schema.validate(compose_config("train", ["baseline=neural_ode"]), "train")  # other models: their own fields
