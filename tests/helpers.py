"""Test helpers shared by the test modules (and by the fixtures of conftest.py): config
composition, the `liedfl` command in a subprocess and its environment."""

from __future__ import annotations

import ast
import os
import pickle
import shutil
import subprocess
import sys
import traceback
from pathlib import Path

from liedfl_cli.cli import CONF_DIR

SMOKE = ("budget=smoke", "ui.progress=false", "eval.plots=false")


def compose_config(name: str = "train", overrides=(), conf_dir: Path = CONF_DIR):
    """The config conf/<name>.yaml composed with `overrides`, as the CLI composes it."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(conf_dir), version_base="1.3"):
        return compose(config_name=name, overrides=list(overrides))


def model_file(name: str, conf_dir: Path = CONF_DIR):
    """conf/model/<name>.yaml with the files its defaults list names merged under it (as Hydra does)."""
    from omegaconf import OmegaConf

    raw = OmegaConf.load(conf_dir / "model" / f"{name}.yaml")
    defaults = list(raw.pop("defaults", []))
    out = OmegaConf.create({})
    for d in defaults:
        out = OmegaConf.merge(out, raw if d == "_self_" else model_file(str(d), conf_dir))
    return out if "_self_" in defaults else OmegaConf.merge(out, raw)


def single_body_models(conf_dir: Path = CONF_DIR) -> list[str]:
    """The model configs other than LieDFLNN's that any dataset can train (not those needing a tree):
    the baselines the generic tests train on a free body."""
    from liedfl_cli.config.factory import model_class

    names = sorted(p.stem for p in (conf_dir / "model").glob("*.yaml") if p.stem != "liedflnn")
    return [n for n in names if not model_class(model_file(n, conf_dir)._target_).needs_tree]


def train_run(root: Path, *overrides: str, name: str = "run") -> Path:
    """`run_train` of the train config with `overrides`, output in root/name, data in root/data (in
    this process): the run folder. For module fixtures that need one finished run."""
    from hydra.core.global_hydra import GlobalHydra

    from liedfl_cli.commands.train import run_train

    run_train(
        compose_config("train", (*overrides, f"paths.output_dir={root / name}", f"paths.data_dir={root / 'data'}"))
    )
    GlobalHydra.instance().clear()
    return root / name


def cli_command() -> list[str]:
    exe = shutil.which("liedfl", path=str(Path(sys.executable).parent)) or shutil.which("liedfl")
    return [exe] if exe else [sys.executable, "-c", "from liedfl_cli.cli import main; main()"]


def cli_env() -> dict:
    """The environment of a CLI subprocess: one thread, no user data dir, no full Hydra errors."""
    env = {k: v for k, v in os.environ.items() if k not in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR")}
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg", COLUMNS="200")
    return env


def run_cli(*args: str, cwd: Path, ok: bool = False, timeout: int = 300) -> subprocess.CompletedProcess:
    """`liedfl *args` in a subprocess (cwd, `cli_env()`); ok=True asserts exit 0 and no traceback."""
    proc = subprocess.run([*cli_command(), *args], cwd=cwd, env=cli_env(), capture_output=True, text=True,
                          timeout=timeout)  # fmt: skip
    if ok:
        assert proc.returncode == 0, f"liedfl {' '.join(args)} -> {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
        assert "Traceback" not in proc.stderr, proc.stderr
    return proc


def main_in_process(*args: str, cwd: Path) -> tuple[int, str]:
    """`liedfl_cli.cli.main` with argv `liedfl *args`, run in this process in `cwd`: (exit code, the
    traceback of an escaping exception or ""; such an exception counts as exit 1, as in a process).
    Restores argv, the working directory, Hydra's global state and the runtime settings; captures
    nothing (`run_main` does, with capfd)."""
    from hydra.core.global_hydra import GlobalHydra

    from liedfl_cli.cli import main
    from liedfl_cli.solvers import runtime

    argv, here, settings = sys.argv, os.getcwd(), runtime._current
    sys.argv = ["liedfl", *args]
    os.chdir(cwd)
    extra = ""
    try:
        main()
        code = 0
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    except BaseException:  # what the process would print as a traceback
        code, extra = 1, traceback.format_exc()
    finally:
        sys.argv, runtime._current = argv, settings
        os.chdir(here)
        GlobalHydra.instance().clear()
    return code, extra


def run_main(*args: str, cwd: Path, capfd, monkeypatch, ok: bool = False) -> subprocess.CompletedProcess:
    """`liedfl *args` as `liedfl_cli.cli.main` called in this process (what the `liedfl` entry point runs),
    in cwd, with the environment of `cli_env()`; returns a CompletedProcess like `run_cli` (returncode
    from SystemExit; an escaping exception: returncode 1 and its traceback appended to stderr). Saves
    the seconds of a new interpreter per call, for tests of a command's behaviour; tests of the process
    boundary (signals, the installed script, exit on a closed pipe) keep `run_cli`."""
    for key in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR"):
        monkeypatch.delenv(key, raising=False)
    for key, value in (("MPLBACKEND", "Agg"), ("COLUMNS", "200")):
        monkeypatch.setenv(key, value)
    capfd.readouterr()
    code, extra = main_in_process(*args, cwd=cwd)
    out, err = capfd.readouterr()
    proc = subprocess.CompletedProcess(["liedfl", *args], code, out, err + extra)
    if ok:
        assert proc.returncode == 0, f"liedfl {' '.join(args)} -> {proc.returncode}\n{proc.stdout}\n{proc.stderr}"
        assert "Traceback" not in proc.stderr, proc.stderr
    return proc


class _ParsedYaml:
    """Stands in for the `yaml` module inside omegaconf (see `cache_yaml_parses`); any other attribute
    is yaml's own."""

    def __init__(self, yaml_module) -> None:
        self._yaml, self._parsed = yaml_module, {}

    def __getattr__(self, name: str):
        return getattr(self._yaml, name)

    def load(self, stream, Loader):
        if Loader.__name__ != "OmegaConfLoader" or not hasattr(stream, "seek"):
            return self._yaml.load(stream, Loader=Loader)
        start = stream.tell()
        text = stream.read()
        if text not in self._parsed:
            stream.seek(start)  # parsed from the file itself: its errors name the file, as before
            self._parsed[text] = pickle.dumps(self._yaml.load(stream, Loader=Loader))
        return pickle.loads(self._parsed[text])  # a fresh copy (pickle: faster than deepcopy)


def cache_yaml_parses() -> None:
    """Every Hydra composition re-reads and re-parses ~16 YAML files (about a fifth of its ~0.08 s),
    and the fast tier composes ~800 times (in-process `liedfl` runs and `compose_config`): in the test
    process, omegaconf's YAML parse of a file's text is done once and each load gets a fresh copy of
    the parsed data (plain dicts, lists and scalars), so nothing one load does reaches another. Keyed
    by the text itself, so an edited file parses afresh; a file that fails to parse is not stored."""
    import yaml
    from omegaconf import omegaconf

    if not isinstance(omegaconf.yaml, _ParsedYaml):
        omegaconf.yaml = _ParsedYaml(yaml)  # type: ignore[assignment]


def modules_in_fresh_interpreter(code: str, roots: tuple[str, ...]) -> list[str]:
    """Run `code` (Python source) in a new interpreter from the repository root and return the
    sorted top-level names among `roots` that it left in `sys.modules` (what an import loads)."""
    probe = f"{code}\nimport sys\nprint(sorted({{m.split('.')[0] for m in sys.modules}} & {set(roots)!r}))"
    out = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        cwd=Path(__file__).resolve().parents[1],
        check=True,
    )
    return ast.literal_eval(out.stdout.strip().splitlines()[-1])


def write_model_rollout(path: Path, ds, idx, R, p, converged=None) -> None:
    """Write poses R (T, S+1, B, 3, 3), p (T, S+1, m, 3) as the rollout.h5 of a "model" on trajectories
    `idx` of `ds` (2 Newton iterations a step; `converged` (T, S-1) bool, all True by default), for the
    evaluation tests."""
    import numpy as np

    from liedfl_cli.files.rollout_file import RolloutEntry, write_rollout

    T, S = R.shape[0], R.shape[1] - 1
    conv = np.ones((T, S - 1), bool) if converged is None else converged
    fails = np.flatnonzero((~conv).any(0))
    ent = RolloutEntry(
        R=R,
        p=p,
        converged=conv,
        iterations=np.full((T, S - 1), 2),
        residual_norm=np.zeros((T, S - 1)),
        attrs={"seconds": 1.0, "seconds_per_step": 0.1, "n_failed": int((~conv).sum()),
               "first_failure": int(fails[0]) + 2 if len(fails) else -1, "n_trajectories": T},
    )  # fmt: skip
    write_rollout(path, steps=S, h=ds.h, scene=ds.scene, traj_index=idx, rollouts={"model": ent})
