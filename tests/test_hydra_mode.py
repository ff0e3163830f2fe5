"""`config.hydra_mode`: Hydra's first composition (`Hydra.get_mode`, only to read `hydra.mode`) is skipped
where no config file and no argument can set hydra.mode, and kept everywhere else."""

from __future__ import annotations

import shutil

import pytest
from hydra import compose, initialize_config_dir
from hydra._internal.hydra import Hydra
from hydra.core.global_hydra import GlobalHydra

from liedfl_cli.cli import CONF_DIR
from liedfl_cli.config.hydra_mode import mode_is_default, without_mode_composition

PRIMARY = sorted(p.stem for p in CONF_DIR.glob("*.yaml"))


def test_no_packaged_config_file_has_a_mode_key():
    assert mode_is_default(CONF_DIR, [])


@pytest.mark.parametrize("command", PRIMARY)
def test_every_primary_config_composes_with_hydra_mode_none(command):
    """The premise, checked by Hydra itself: what the skipped composition would have returned."""
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name=command, return_hydra_config=True)
    GlobalHydra.instance().clear()
    assert cfg.hydra.mode is None


@pytest.mark.parametrize(
    "args",
    [
        ["hydra.mode=MULTIRUN"],
        ["++hydra.mode=RUN"],
        ["~hydra.mode"],
        ["hydra.searchpath=[file:///elsewhere]"],
        ["hydra/launcher=joblib"],
        ["-cd", "/elsewhere"],
        ["--config-dir=/elsewhere"],
        ["-cn", "other"],
        ["--config-path", "x"],
    ],
)
def test_an_argument_that_can_set_the_mode_keeps_hydras_get_mode(args):
    assert not mode_is_default(CONF_DIR, ["budget=smoke", *args])


@pytest.mark.parametrize("args", [[], ["-m", "dataset.seed=1,2"], ["hydra.run.dir=x", "hydra.job.chdir=false"]])
def test_other_arguments_skip_it(args):
    assert mode_is_default(CONF_DIR, ["budget=smoke", *args])


@pytest.mark.parametrize(
    "text", ["hydra:\n  mode: MULTIRUN\n", "# @package _global_\nhydra.mode: MULTIRUN\n", "  mode : RUN\n"]
)
def test_a_config_file_with_a_mode_key_keeps_hydras_get_mode(tmp_path, text):
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    assert mode_is_default(conf, [])
    (conf / "experiment" / "my_sweep.yaml").write_text(text)
    assert not mode_is_default(conf, [])


def test_the_shortcut_returns_none_without_composing_and_restores_hydra(monkeypatch):
    original = Hydra.get_mode
    calls = []
    monkeypatch.setattr(Hydra, "compose_config", lambda self, *a, **k: calls.append(a) or 1 / 0)
    with without_mode_composition(CONF_DIR, ["budget=smoke"]) as skipped:
        assert skipped and Hydra.get_mode is not original
        assert Hydra.get_mode(object.__new__(Hydra), config_name="train", overrides=[]) is None
    assert Hydra.get_mode is original and not calls
    with without_mode_composition(CONF_DIR, ["hydra.mode=MULTIRUN"]) as skipped:
        assert not skipped and Hydra.get_mode is original


@pytest.mark.parametrize(("extra", "compositions"), [((), 1), (("hydra.mode=RUN",), 2)])
def test_a_command_composes_once_unless_the_mode_may_be_set(tmp_path, monkeypatch, run_main, extra, compositions):
    """End to end in this process: `liedfl data` composes its config once; with a hydra.mode override,
    twice (Hydra's get_mode), and both write the same dataset."""
    calls = []
    compose = Hydra.compose_config

    def counted(self, *a, **k):
        calls.append(1)
        return compose(self, *a, **k)

    monkeypatch.setattr(Hydra, "compose_config", counted)
    run_main("data", "budget=smoke", "ui.progress=false", *extra, cwd=tmp_path, ok=True)
    assert len(calls) == compositions
    assert len(list((tmp_path / "outputs" / "data").glob("*.h5"))) == 1
    assert Hydra.compose_config is counted  # the shortcut patched get_mode only
