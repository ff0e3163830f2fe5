"""Job status, sweep summaries and clean failure paths of the CLI.

- Every `liedfl train` run folder and every job folder of a `-m` sweep gets a `status.json`:
  `{"status": "ok", "exit_code": 0, ...}` or `{"status": "failed", "error": "<one line>", "exit_code": N}`
  (`"interrupted"` for Ctrl-C). A failing sweep job records its status and the sweep goes on;
  `sweep_summary` counts the failures afterwards (the CLI's exit code).
- `LiedflCallback` (registered under `hydra.callbacks` in every primary config) validates the config
  in `on_run_start`, i.e. before Hydra creates the run directory, and records which directories the
  run is about to create, so that `remove_unused_run_dir` can take back a run folder that holds
  nothing but Hydra's own files when a single run fails. In a multirun it records, in the process
  that launches the sweep, the sweep folder and the launcher: the summary is read from the job
  folders afterwards, so it does not matter which process (or machine: submitit) ran each job.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback

from ..files.io_utils import write_json

STATUS_FILE = "status.json"
HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")

SUBMITIT_PLUGIN = "hydra_plugins.hydra_submitit_launcher"

_state: dict[str, Any] = {"run_dir": None, "keep_from": None, "sweep_dir": None, "launcher": None}


def reset() -> None:
    """Forget the run / sweep folders of a previous command (the CLI calls it first)."""
    _state.update(run_dir=None, keep_from=None, sweep_dir=None, launcher=None)


# ----------------------------------------------------------------------------- status files
def write_status(run_dir, status: str, exit_code: int, error: str | None = None, **extra) -> Path:
    """Write `<run_dir>/status.json` atomically."""
    obj: dict[str, Any] = {"status": status, "exit_code": int(exit_code)}
    if error is not None:
        obj["error"] = error
    obj.update(extra)
    path = Path(run_dir) / STATUS_FILE
    write_json(path, obj)
    return path


def mark_interrupted(folder, message: str, exit_code: int, phase: str) -> Path:
    """Record in `<folder>/status.json` that `phase` (e.g. an evaluation of the folder) was interrupted,
    keeping the status it had under "previous" (`clear_interruption` restores it)."""
    previous = read_status(folder)
    if previous is not None and previous.get("status") == "interrupted" and previous.get("phase") == phase:
        previous = previous.get("previous")
    return write_status(folder, "interrupted", exit_code, error=message, phase=phase, previous=previous)


def clear_interruption(folder, phase: str) -> None:
    """After `phase` completed in `folder`: its earlier interruption mark (`mark_interrupted`) is
    replaced by the status it hid (or removed if there was none)."""
    st = read_status(folder)
    if st is None or st.get("status") != "interrupted" or st.get("phase") != phase or "previous" not in st:
        return
    previous = st["previous"]
    path = Path(folder) / STATUS_FILE
    if isinstance(previous, dict):
        write_json(path, previous)
    else:
        path.unlink(missing_ok=True)


def read_status(run_dir) -> dict | None:
    """The run's status.json as a dict; None when absent; a `failed` status when unreadable."""
    path = Path(run_dir) / STATUS_FILE
    if not path.is_file():
        return None
    try:
        obj = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        return {"status": "failed", "error": f"{path}: unreadable status file ({type(e).__name__})", "exit_code": -1}
    if not isinstance(obj, dict) or "status" not in obj:
        return {"status": "failed", "error": f"{path}: not a status object", "exit_code": -1}
    return obj


# ----------------------------------------------------------------------------- sweeps
def job_dirs(sweep_dir) -> list[Path]:
    """Job folders of a sweep: folders holding a status.json or a .hydra/ folder (any depth)."""
    sweep_dir = Path(sweep_dir)
    found = {p.parent for p in sweep_dir.rglob(STATUS_FILE)} | {p.parent for p in sweep_dir.rglob(".hydra")}
    return sorted((d for d in found if d != sweep_dir), key=lambda d: _natural(d.relative_to(sweep_dir)))


def _natural(rel: Path):
    return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in rel.parts]


def failed_runs(sweep_dir) -> list[tuple[Path, str]]:
    """(job dir, error line) of every job whose status is not ok; a job without status.json (nor eval.csv)
    did not finish."""
    out = []
    for d in job_dirs(sweep_dir):
        st = read_status(d)
        if st is None:
            if not (d / "eval.csv").is_file():  # (runs of liedfl versions before status.json have eval.csv)
                out.append((d, "no status.json: the job did not finish"))
        elif st.get("status") != "ok":
            out.append((d, str(st.get("error") or st.get("status"))))
    return out


def sweep_summary(sweep_dir) -> tuple[int, int, list[tuple[Path, str]]]:
    """(failed, total, failures) over the jobs of a sweep."""
    jobs = job_dirs(sweep_dir)
    failures = failed_runs(sweep_dir)
    return len(failures), len(jobs), failures


def sweep_dir() -> str | None:
    """The sweep folder of the multirun this process launched (set by the callback)."""
    return _state["sweep_dir"]


def jobs_ran_elsewhere() -> bool:
    """True when the jobs of this process's multirun wrote their output somewhere other than this
    console: the submitit launchers run each job in its own process with stdout/stderr in
    `<sweep>/.submitit/<job id>/`."""
    return str(_state["launcher"] or "").startswith(SUBMITIT_PLUGIN)


def check_launcher(config) -> None:
    """One line, before anything is created, for a submitit launcher that cannot work here: the plugin
    is not installed (`hydra/launcher=liedfl_local` names the plugin's class), or a SLURM launcher on
    a machine without SLURM (submitit needs `srun`)."""
    import importlib.util
    import shutil

    from omegaconf import OmegaConf

    from ..display.ui import fail

    target = str(OmegaConf.select(config, "hydra.launcher._target_", default="") or "")
    if not target.startswith(SUBMITIT_PLUGIN):
        return
    choices = OmegaConf.select(config, "hydra.runtime.choices", default=None) or {}
    choice = f"hydra/launcher={choices.get('hydra/launcher', target)}"
    if importlib.util.find_spec(SUBMITIT_PLUGIN) is None or importlib.util.find_spec("submitit") is None:
        fail(f'{choice}: hydra-submitit-launcher is not installed (pip install -e ".[cluster]")')
    if target.endswith(".SlurmLauncher") and shutil.which("srun") is None:
        fail(f"{choice}: SLURM's srun is not on PATH: submit the sweep from a machine of the cluster")


# ----------------------------------------------------------------------------- failed single runs
def remove_unused_run_dir(run_dir) -> bool:
    """Remove a run folder this process created that holds nothing but Hydra's files (`.hydra/` with
    its three yaml files, an empty or Hydra-written `*.log`), then the empty parents it created.
    Returns True when the folder was removed. Never removes anything else: files are deleted by
    name and folders with `rmdir`, which fails on a non-empty folder."""
    run_dir = Path(run_dir).absolute()
    recorded = _state["run_dir"]
    if recorded is None or Path(recorded).absolute() != run_dir or not run_dir.is_dir():
        return False
    keep_from = Path(_state["keep_from"]).absolute()
    if keep_from == run_dir:  # the folder existed before this run: leave it
        return False
    from ..files.locks import LOCK_FILE, release_folder

    entries = [e for e in run_dir.iterdir() if e.name != LOCK_FILE]  # (this process's lock: released below)
    hydra = run_dir / ".hydra"
    if any(e != hydra and not (e.suffix == ".log" and e.is_file()) for e in entries):
        return False
    if hydra.exists() and (
        not hydra.is_dir() or any(p.name not in HYDRA_FILES or not p.is_file() for p in hydra.iterdir())
    ):
        return False
    release_folder(run_dir)
    try:
        for name in HYDRA_FILES:
            (hydra / name).unlink(missing_ok=True)
        if hydra.exists():
            hydra.rmdir()
        for e in entries:
            if e.suffix == ".log":
                e.unlink(missing_ok=True)
        run_dir.rmdir()
        parent = run_dir.parent
        while parent != keep_from and keep_from in parent.parents:
            parent.rmdir()  # raises OSError when not empty: stop there
            parent = parent.parent
    except OSError:
        pass
    return not run_dir.exists()


def discard_new_run_outputs(run_dir) -> bool:
    """Remove what a single run wrote into the run folder it created (everything but Hydra's
    `.hydra/`, the `*.log` files and the lock), so that `remove_unused_run_dir` can take the folder
    back after a config or data error found once the data were loaded. A folder that existed before
    the run, a multirun's job folder or a run outside the CLI is left alone. Returns True when
    something was removed."""
    import shutil

    from ..files.locks import LOCK_FILE

    run_dir = Path(run_dir).absolute()
    recorded, keep_from = _state["run_dir"], _state["keep_from"]
    if recorded is None or keep_from is None or Path(recorded).absolute() != run_dir or not run_dir.is_dir():
        return False
    if Path(keep_from).absolute() == run_dir:  # the user's existing folder: leave it as it is
        return False
    removed = False
    for e in run_dir.iterdir():
        if e.name in (".hydra", LOCK_FILE) or (e.suffix == ".log" and e.is_file()):
            continue
        if e.is_dir() and not e.is_symlink():
            shutil.rmtree(e, ignore_errors=True)
        else:
            e.unlink(missing_ok=True)
        removed = True
    return removed


def _deepest_existing(path: Path) -> Path:
    path = path.absolute()
    while not path.exists():
        path = path.parent
    return path


def _lock_new_run(run_dir: Path) -> None:
    """Take the run folder's lock before Hydra writes its `.hydra/` files there (a second
    `liedfl train hydra.run.dir=<dir>` must not overwrite the first one's config); the job keeps it."""
    from ..config.preflight import os_error_line
    from ..display.ui import fail
    from ..files.locks import RunLocked, acquire

    try:  # (an exception here would reach the user as Hydra's two-line callback warning first)
        run_dir.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        fail(f"hydra.run.dir={run_dir}: cannot create the run folder: {os_error_line(e)}")
    try:
        acquire(run_dir, "train")
    except RunLocked as e:
        fail(str(e))


class LiedflCallback(Callback):
    """Hydra callback: validate before the run folder exists, remember what the run creates, and
    remember the sweep folder of a multirun."""

    def on_run_start(self, config, **kwargs) -> None:
        from omegaconf import OmegaConf

        from ..config.preflight import preflight_or_fail

        run_dir = OmegaConf.select(config, "hydra.run.dir", default=None)
        if run_dir is not None:
            run_dir = Path(str(run_dir))
            _state["run_dir"] = str(run_dir.absolute())
            _state["keep_from"] = str(_deepest_existing(run_dir))
        # SystemExit on a bad config: Hydra turns a callback's exceptions into warnings, not exits
        preflight_or_fail(str(config.get("task_name")), config)
        if run_dir is not None and str(config.get("task_name")) == "train":
            _lock_new_run(run_dir)

    def on_multirun_start(self, config, **kwargs) -> None:
        from omegaconf import OmegaConf

        d = OmegaConf.select(config, "hydra.sweep.dir", default=None)
        _state["sweep_dir"] = None if d is None else str(d)
        _state["launcher"] = OmegaConf.select(config, "hydra.launcher._target_", default=None)
        check_launcher(config)  # (before the launcher is instantiated and the sweep folder created)


__all__ = [
    "STATUS_FILE",
    "LiedflCallback",
    "write_status",
    "read_status",
    "mark_interrupted",
    "clear_interruption",
    "job_dirs",
    "failed_runs",
    "sweep_summary",
    "sweep_dir",
    "jobs_ran_elsewhere",
    "check_launcher",
    "remove_unused_run_dir",
    "discard_new_run_outputs",
]
