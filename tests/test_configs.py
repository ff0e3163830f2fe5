"""Every config composes and passes the schema; group options match the registries in code.

Configs are discovered from liedfl_cli/conf/ at test time, so files added later (new datasets, forces,
baselines, experiments) are covered without editing this file.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from helpers import compose_config, model_file
from liedfl_cli.cli import COMMANDS, CONF_DIR
from liedfl_cli.config.schema import validate
from liedfl_cli.errors import ConfigError

PRIMARY = sorted(p.stem for p in CONF_DIR.glob("*.yaml"))
GROUPS = sorted(d.name for d in CONF_DIR.iterdir() if d.is_dir() and not d.name.startswith((".", "_")))
GROUP_OPTIONS = [(g, p.stem) for g in GROUPS for p in sorted((CONF_DIR / g).glob("*.yaml"))]
NEEDS_RUN = ("rollout", "eval")


def _paths(tmp: Path) -> list[str]:
    return [f"paths.output_dir={tmp / 'run'}", f"paths.data_dir={tmp / 'data'}"]


def _compose(name: str, overrides: list[str], conf_dir: Path = CONF_DIR):
    return compose_config(name, overrides, conf_dir)


def _check(cfg) -> None:
    """Schema-valid, and every interpolation resolves (hydra:... excluded by the path overrides)."""
    validate(cfg)
    OmegaConf.to_container(cfg, resolve=True)


# ----------------------------------------------------------------------------- discovery
def test_discovery_finds_the_configs():
    assert set(COMMANDS) <= set(PRIMARY), f"a command has no primary config: {set(COMMANDS) - set(PRIMARY)}"
    for g in ("dataset", "model", "force", "baseline", "solver", "budget", "experiment"):
        assert g in GROUPS, f"liedfl_cli/conf/{g}/ is missing"
    assert GROUP_OPTIONS


# ----------------------------------------------------------------------------- composition
@pytest.mark.parametrize("name", PRIMARY)
def test_primary_config_composes(name, tmp_path):
    bare = _compose(name, [])
    # mandatory command-line values (run=???, ...) get a dummy; paths only where the config has them
    overrides = [f"{k}=x" for k in bare if OmegaConf.is_missing(bare, k)]
    if name in NEEDS_RUN:
        assert "run=x" in overrides, f"liedfl_cli/conf/{name}.yaml should require run=<run dir>"
    if "paths" in bare:
        overrides += _paths(tmp_path)
    cfg = _compose(name, overrides)
    _check(cfg)
    assert cfg.task_name == name


def _own_data(group: str, option: str, tmp: Path) -> list[str]:
    """The file a scene that reads the user's data needs (dataset=file, dataset=import)."""
    from own_data import write_csv, write_h5

    if group != "dataset" or option not in ("file", "import"):
        return []
    if option == "file":
        return [f"dataset.path={write_h5(tmp / 'my.h5')}"]
    return [f"dataset.path={write_csv(tmp / 'log.csv')[0]}", "dataset.rotation=wxyz"]


@pytest.mark.parametrize("group,option", GROUP_OPTIONS, ids=[f"{g}={o}" for g, o in GROUP_OPTIONS])
def test_train_composes_with_every_group_option(group, option, tmp_path):
    own = _own_data(group, option, tmp_path)
    cfg = _compose("train", _paths(tmp_path) + [f"{group}={option}", *own])
    _check(cfg)
    if group in ("dataset", "model"):  # the option name is the `name` field the code dispatches on
        assert cfg[group].name == option, f"liedfl_cli/conf/{group}/{option}.yaml has name={cfg[group].name!r}"
    if group == "baseline":  # a baseline option only selects the model of the same name
        assert cfg.model.name == ("liedflnn" if option == "none" else option)
    # and the same option with the smoke budget (what CI and the CLI tests use)
    if group != "budget":
        _check(_compose("train", _paths(tmp_path) + [f"{group}={option}", *own, "budget=smoke"]))


def test_experiment_and_budget_files_are_global():
    """Override files must be `# @package _global_` (else their keys land under experiment./budget.)."""
    files = sorted((CONF_DIR / "experiment").glob("*.yaml")) + sorted((CONF_DIR / "budget").glob("*.yaml"))
    bad = [
        f"{p.relative_to(CONF_DIR)} starts with {p.read_text().lstrip(chr(0xFEFF)).splitlines()[:1]}"
        for p in files
        if p.read_text().lstrip("\ufeff").splitlines()[:1] != ["# @package _global_"]
    ]
    assert not bad, "; ".join(bad)


# ----------------------------------------------------------------------------- schema
@pytest.mark.parametrize(
    "override,key",
    [
        ("+train.epoch=3", "epoch"),
        ("+train.optimizer.lrate=0.1", "lrate"),
        ("+solver.maxiter=3", "maxiter"),
        ("+rollout.step=3", "step"),
        ("+model.mlp_widht=3", "mlp_widht"),
    ],
)
def test_misspelled_key_is_rejected(override, key, tmp_path):
    cfg = _compose("train", _paths(tmp_path) + [override])
    with pytest.raises(ConfigError, match=key):
        validate(cfg)


@pytest.mark.parametrize(
    "override,key",
    [
        ("train.epochs=many", "epochs"),
        ("train.optimizer.name=sgd", "train.optimizer.name"),
        ("train.reg_form=cubic", "train.reg_form"),
        ("model.residual=bogus", "model.residual"),
        ("model.potential=quadratic", "model.potential"),
        ("solver.method=broyden", "solver.method"),
    ],
)
def test_wrong_value_is_rejected(override, key, tmp_path):
    cfg = _compose("train", _paths(tmp_path) + [override])
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        validate(cfg)


def test_unknown_override_without_plus_is_a_hydra_error(tmp_path):
    with pytest.raises(Exception, match="epoch"):
        _compose("train", _paths(tmp_path) + ["train.epoch=3"])


def test_misspelled_key_in_an_experiment_file_is_caught(tmp_path):
    """An override file with a typo composes (Hydra merges it) but fails schema validation."""
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    (conf / "experiment" / "typo_test.yaml").write_text("# @package _global_\ntrain:\n  epoch: 3\n  batch_size: 32\n")
    cfg = _compose("train", _paths(tmp_path) + ["experiment=typo_test"], conf_dir=conf)
    assert cfg.train.epoch == 3
    with pytest.raises(ConfigError, match=r"epoch") as e:
        validate(cfg)
    assert "\n" not in str(e.value)
    # the same file without the typo is fine
    (conf / "experiment" / "typo_test.yaml").write_text("# @package _global_\ntrain:\n  epochs: 3\n  batch_size: 32\n")
    cfg = _compose("train", _paths(tmp_path) + ["experiment=typo_test"], conf_dir=conf)
    validate(cfg)
    assert cfg.train.epochs == 3


# ----------------------------------------------------------------------------- registries
def _options(group: str) -> set[str]:
    return {p.stem for p in (CONF_DIR / group).glob("*.yaml")}


def test_force_options_match_registry():
    from liedfl_cli.mechanics.forces import FORCES

    assert _options("force") == set(FORCES) | {"none"}


def test_model_configs_name_their_option_and_a_model_class():
    """liedfl_cli/conf/model/<name>.yaml has name: <name> and a _target_ that is a Model of this package;
    each baseline=<name> that exists selects exactly liedfl_cli/conf/model/<name>.yaml (none selects liedflnn)."""
    from liedfl_cli.config.factory import model_class

    for name in _options("model"):
        cfg = OmegaConf.load(CONF_DIR / "model" / f"{name}.yaml")
        assert cfg.name == name
        model_class(cfg._target_)
    # a baseline file is optional (it lists a model among the baselines): each one selects a model
    assert _options("baseline") <= _options("model") - {"liedflnn"} | {"none"}
    for name in _options("baseline"):
        text = (CONF_DIR / "baseline" / f"{name}.yaml").read_text()
        assert f"override /model: {'liedflnn' if name == 'none' else name}" in text


def test_every_model_owns_an_options_dataclass_matching_its_config_files():
    """Each model class of liedfl_cli/conf/model declares `Options`, a dataclass in its own file, and
    the keys of every config file of that class are its fields (so the schema checks their types)."""
    import dataclasses

    from liedfl_cli.config.factory import model_class

    for name in _options("model"):
        raw = model_file(name)  # with the files its defaults list names (articulated.yaml: liedflnn.yaml's)
        cls = model_class(raw._target_)
        assert cls.Options is not None and dataclasses.is_dataclass(cls.Options), name
        assert cls.Options.__module__ == cls.__module__, f"{name}: options not owned by the model's file"
        fields = {f.name: f for f in dataclasses.fields(cls.Options)}
        keys = {str(k) for k in raw} - {"_target_", "name"}
        assert keys <= set(fields), f"{name}: {sorted(keys - set(fields))} missing from {cls.Options.__name__}"
        assert "mlp_width" in keys and "mlp_depth" in keys  # a file that sets nothing would prove nothing here


def test_dataset_options_match_registry():
    from liedfl_cli.data.scenes import FILE_SCENE, SCENES

    assert _options("dataset") == set(SCENES) | {FILE_SCENE}  # file: a dataset file, not a generator
