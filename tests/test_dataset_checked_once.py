"""The dataset section is checked once per conversion, at the door (`typed.dataset_config` ->
`scenes.dataset_section`), and the data layer takes the checked `DatasetConfig` without checking it
again (docs/architecture.md, "Where an option is declared")."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from helpers import compose_config
from liedfl_cli.config import schema
from liedfl_cli.config.typed import dataset_config, typed
from liedfl_cli.data import scenes
from liedfl_cli.data.dataset_config import DatasetConfig
from liedfl_cli.errors import ConfigError


@pytest.fixture
def count_checks(monkeypatch):
    """How many times the scenes' common fields are checked (`scene_common.check_config`)."""
    calls = []
    real = scenes.check_config

    def counted(c, registry=None):
        calls.append(c.get("name"))
        return real(c, registry)

    monkeypatch.setattr(scenes, "check_config", counted)
    return calls


def test_a_typed_dataset_is_checked_once_and_not_again_by_the_data_layer(tmp_path, count_checks):
    cfg = compose_config("data", ("budget=smoke", "ui.progress=false", f"paths.data_dir={tmp_path}"))
    run = typed(cfg)
    assert isinstance(run.dataset, DatasetConfig) and run.dataset.checked is not None
    assert count_checks == [run.dataset.name]  # the door
    ds, path = scenes.get_dataset(run.dataset, tmp_path)
    assert scenes.dataset_path(run.dataset, tmp_path) == path and path.is_file()
    assert count_checks == [run.dataset.name]  # generate, cache name, save: no second check
    # the section is kept as configured (its cache name hashes these keys)
    assert run.dataset.as_dict() == OmegaConf.to_container(cfg.dataset, resolve=True)
    # a plain mapping (the Python API, scripts) is still checked where it is used
    scenes.dataset_path(run.dataset.as_dict(), tmp_path)
    assert len(count_checks) == 2


def test_validate_and_the_conversion_share_the_one_check(tmp_path, count_checks):
    cfg = compose_config("data", ("budget=smoke", "ui.progress=false", f"paths.data_dir={tmp_path}"))
    schema.validate(cfg, "data")
    assert count_checks == [cfg.dataset.name]


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"val_fraction": 1.0}, r"dataset.val_fraction=1.0: must be a number in \[0, 1\)"),
        ({"h": -1}, r"dataset.h must be positive, got -1"),
        ({"name": "nowhere"}, r"dataset.name='nowhere' is not a registered scene"),
    ],
)
def test_a_bad_dataset_section_is_one_line_at_the_door(section, message):
    d = {**OmegaConf.to_container(compose_config("data", ("budget=smoke",)).dataset, resolve=True), **section}
    with pytest.raises(ConfigError, match=message):
        dataset_config(d)


def test_a_rollout_section_is_checked_as_relaxed_and_kept_as_configured():
    d = {
        **OmegaConf.to_container(compose_config("data", ("budget=smoke",)).dataset, resolve=True),
        "test_fraction": 1.0,
    }
    with pytest.raises(ConfigError, match="test_fraction"):
        dataset_config(d)  # training refuses every trajectory as a test one
    ds = dataset_config(d, rollout=True)  # a rollout asks for all of them
    assert ds.test_fraction == 1.0 and ds.as_dict()["test_fraction"] == 1.0
    assert ds.checked is not None and ds.checked["test_fraction"] == 0.0
