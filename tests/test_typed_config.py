"""A command's config is converted once, at the command's entry (`liedfl_cli/config/typed.py`), and
no module below the commands receives the raw config (docs/architecture.md, "How a config travels").

`RawConfigGuard` wraps every function and method defined in the packages below the commands and
records each call that gets an omegaconf `DictConfig` / `ListConfig` argument (or a list, tuple or
dict holding one); a tiny train, rollout, eval and `liedfl data` run in process under it, and the
negative test shows that it catches a raw config handed down.
"""

from __future__ import annotations

import functools
import importlib
import inspect
import pkgutil
import sys
from pathlib import Path

import pytest
from omegaconf import DictConfig, ListConfig, OmegaConf

import liedfl_cli
from helpers import SMOKE, compose_config, main_in_process, train_run

BELOW_COMMANDS = ("data", "evaluation", "files", "models", "solvers", "lie", "mechanics", "loggers", "display")
"""The packages that take typed objects only (the AST rule: tests/test_architecture.py)."""
KEPT_DUNDERS = ("__init__", "__post_init__", "__call__")


def _raw(value) -> bool:
    if isinstance(value, (DictConfig, ListConfig)):
        return True
    if isinstance(value, (list, tuple)):
        return any(isinstance(v, (DictConfig, ListConfig)) for v in value)
    if isinstance(value, dict):
        return any(isinstance(v, (DictConfig, ListConfig)) for v in value.values())
    return False


def _guarded_modules() -> list:
    mods = []
    for name in BELOW_COMMANDS:
        pkg = importlib.import_module(f"liedfl_cli.{name}")
        mods.append(pkg)
        for info in pkgutil.walk_packages(pkg.__path__, f"{pkg.__name__}."):
            mods.append(importlib.import_module(info.name))
    return mods


class RawConfigGuard:
    """Wraps the functions and methods of the packages below the commands (restored by monkeypatch);
    `calls` lists `module.function(argument)` for each call that received a raw config."""

    def __init__(self, monkeypatch):
        # every module of the package imported first: one imported while the guard is on would keep
        # a wrapper (a lazy `from x import f` binds what it finds) after the guard is gone
        for info in pkgutil.walk_packages(liedfl_cli.__path__, "liedfl_cli."):
            if not info.name.endswith("__main__"):  # (importing it runs the CLI)
                importlib.import_module(info.name)
        self.calls: list[str] = []
        self._mp = monkeypatch
        wrapped: dict[int, object] = {}  # id(original function) -> its wrapper
        for mod in _guarded_modules():
            for obj in list(vars(mod).values()):
                if inspect.isfunction(obj) and obj.__module__ == mod.__name__:
                    wrapped[id(obj)] = self._wrap(obj)
                elif inspect.isclass(obj) and obj.__module__ == mod.__name__:
                    self._wrap_class(obj)
        # every module namespace (and module-level registry dict) that refers to a wrapped function
        for mod in [m for n, m in list(sys.modules.items()) if n.startswith("liedfl_cli") and m is not None]:
            for name, obj in list(vars(mod).items()):
                if id(obj) in wrapped and inspect.isfunction(obj):
                    monkeypatch.setattr(mod, name, wrapped[id(obj)])
                elif isinstance(obj, dict):
                    for key, value in list(obj.items()):
                        if inspect.isfunction(value) and id(value) in wrapped:
                            monkeypatch.setitem(obj, key, wrapped[id(value)])

    def _wrap(self, fn):
        where = f"{fn.__module__}.{fn.__qualname__}"
        names = list(inspect.signature(fn).parameters)

        @functools.wraps(fn)
        def guarded(*args, **kwargs):
            for i, value in enumerate(args):
                if _raw(value):
                    self.calls.append(f"{where}({names[i] if i < len(names) else i})")
            for key, value in kwargs.items():
                if _raw(value):
                    self.calls.append(f"{where}({key})")
            return fn(*args, **kwargs)

        return guarded

    def _wrap_class(self, cls) -> None:
        for name, attr in list(vars(cls).items()):
            if name.startswith("__") and name not in KEPT_DUNDERS:
                continue
            if isinstance(attr, staticmethod):
                self._mp.setattr(cls, name, staticmethod(self._wrap(attr.__func__)))
            elif isinstance(attr, classmethod):
                self._mp.setattr(cls, name, classmethod(self._wrap(attr.__func__)))
            elif inspect.isfunction(attr):
                self._mp.setattr(cls, name, self._wrap(attr))


@pytest.fixture
def guard(monkeypatch):
    return RawConfigGuard(monkeypatch)


def test_no_module_below_the_commands_receives_a_raw_config(guard, tmp_path):
    """train (with its rollout and evaluation), rollout, eval and data, in process, under the guard."""
    run = train_run(tmp_path, *SMOKE, "train.epochs=1")
    data = str(tmp_path / "data")
    for args in (
        ("rollout", f"run={run}", "ui.progress=false", "eval.plots=false", f"paths.data_dir={data}"),
        ("eval", f"run={run}", "ui.progress=false", "eval.plots=false", f"paths.data_dir={data}"),
        ("data", "dataset=heavy_so3", "budget=smoke", f"paths.data_dir={data}"),
    ):
        code, trace = main_in_process(*args, cwd=tmp_path)
        assert code == 0, (args, trace)
    assert (run / "rollout.h5").is_file() and list((run / "rollouts").glob("*/eval.csv"))
    assert guard.calls == [], sorted(set(guard.calls))


def test_the_guard_catches_a_raw_config_handed_down(guard, tmp_path, monkeypatch):
    """The negative case: `liedfl data` with its conversion sabotaged (the dataset section passed on
    as the DictConfig) is caught, so the test above can fail."""
    import liedfl_cli.commands.data as data_command
    from liedfl_cli.config.typed import typed

    def leaky(cfg, command=None):
        run = typed(cfg, command)
        run.dataset = cfg.dataset  # the raw node, as before the conversion existed
        return run

    monkeypatch.setattr(data_command, "typed", leaky)
    cfg = compose_config("data", ("budget=smoke", f"paths.data_dir={tmp_path / 'data'}"))
    data_command.run_data(cfg)
    assert any(c.startswith("liedfl_cli.data.scenes.get_dataset(") for c in guard.calls), guard.calls


def test_typed_sections_are_dataclasses_built_once_from_the_config(tmp_path):
    from liedfl_cli.config.typed import RunConfig, TrainConfig, typed
    from liedfl_cli.data.dataset_config import DatasetConfig
    from liedfl_cli.solvers.options import SolverOptions
    from liedfl_cli.solvers.runtime import RuntimeOptions

    cfg = compose_config("train", (*SMOKE, "solver.tol=1e-7", "runtime.compile=false", "dataset.seed=3"))
    run = typed(cfg)
    assert isinstance(run, RunConfig) and run.command == "train"
    assert isinstance(run.train, TrainConfig) and run.train.epochs == cfg.train.epochs
    assert run.solver == SolverOptions(tol=1e-7, max_iter=cfg.solver.max_iter, max_halvings=cfg.solver.max_halvings)
    assert isinstance(run.runtime, RuntimeOptions) and run.runtime.compile == "false"
    assert isinstance(run.dataset, DatasetConfig) and run.dataset.seed == 3
    # the dataset section round-trips exactly (its cache name hashes these keys)
    assert run.dataset.as_dict() == OmegaConf.to_container(cfg.dataset, resolve=True)
    assert run.train.loss_options().w_del == cfg.train.w_del
    assert not any(isinstance(v, (DictConfig, ListConfig)) for v in vars(run).values())


def test_the_section_schemas_are_in_hydras_config_store():
    from hydra.core.config_store import ConfigStore

    from liedfl_cli.config.typed import SECTIONS

    stored = ConfigStore.instance().list("liedfl_schema")
    assert {f"{name}.yaml" for name in SECTIONS} <= set(stored)


def test_a_wrong_type_is_one_line_naming_the_key():
    from liedfl_cli.config.typed import TrainConfig, section
    from liedfl_cli.errors import ConfigError

    with pytest.raises(ConfigError) as e:
        section(TrainConfig, {"optimizer": {"lr": "fast"}}, "train")
    assert "train.optimizer.lr" in str(e.value) and "\n" not in str(e.value)


def test_the_layers_below_the_commands_never_see_a_dict_config_in_their_annotations():
    """Belt and braces for the AST rule: no source file below the commands names DictConfig."""
    root = Path(liedfl_cli.__file__).resolve().parent
    bad = [
        str(p.relative_to(root))
        for name in BELOW_COMMANDS
        for p in (root / name).rglob("*.py")
        if "DictConfig" in p.read_text() or "OmegaConf" in p.read_text()
    ]
    assert not bad, bad


def test_an_unresolved_or_null_output_dir_takes_the_default_outside_a_hydra_run():
    """A config composed by the compose API has no Hydra run folder: `${hydra:runtime.output_dir}`
    fails to resolve in a fresh process and resolves to None after an in-process Hydra run (the order
    CI runs the tests in); either way the typed `paths.output_dir` is the dataclass's default."""
    from liedfl_cli.config.typed import PathsConfig, typed

    for extra in ((), ("paths.output_dir=null",)):
        run = typed(compose_config("train", (*SMOKE, *extra)))
        assert run.paths.output_dir == PathsConfig().output_dir
