"""Hostile inputs, table-driven: bad config values and overrides, misspelled keys, Hydra errors, broken
datasets, BVH files, run folders, checkpoints, sweep folders and interruptions.

Every case asserts the exit code, exactly one non-empty stderr line `error: ...` naming the file or
config field, no Python traceback, and that nothing was created, changed or left behind in the
case's folder (a snapshot of every file, before and after).

Most cases call `liedfl_cli.cli.main` in-process (the CLI keeps no state between calls: it resets its
run/sweep bookkeeping and Hydra clears its global state), which keeps the ~100 cases in well under a
minute; the cases marked `proc` go through a real `liedfl` process (signals, the entry point, the
pickle payload). Validation errors fail before any data is generated; the cases that need data share
one tiny smoke dataset and one trained smoke run (module fixtures).

Run: `python -m pytest tests/test_hostile.py -q` (`-k <case id>` for one case).
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from helpers import main_in_process, train_run
from liedfl_cli.cli import CONF_DIR

FAST = ("budget=smoke", "ui.progress=false", "eval.plots=false")
REPO = Path(__file__).resolve().parents[1]
CMU = REPO / "data" / "cmu_mocap" / "49_06.bvh"


# ----------------------------------------------------------------------------- shared data
@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """One finished smoke run (trained in-process); its dataset is the smoke cache file."""
    return train_run(tmp_path_factory.mktemp("hostile_run"), *FAST)


@pytest.fixture(scope="module")
def pristine(trained) -> Path:
    """The cached smoke dataset: where `liedfl train budget=smoke` looks for it (same config hash)."""
    (path,) = (trained.parent / "data").glob("*.h5")
    return path


class Ctx:
    """What a case's setup creates: `tmp` (the working directory) and named paths for the arguments."""

    def __init__(self, tmp: Path, trained: Path, pristine: Path, monkeypatch):
        self.tmp, self.trained, self.pristine, self.monkeypatch = tmp, trained, pristine, monkeypatch
        self.vars: dict[str, str] = {"tmp": str(tmp)}

    # --- run folders and checkpoints
    def run(self, edit: Callable[[Path], None] | None = None) -> Path:
        run = self.tmp / "run"
        shutil.copytree(self.trained, run)
        self.vars["run"] = str(run)
        self.vars["ckpt"] = str(run / "checkpoints" / "last.pt")
        if edit:
            edit(run)
        return run

    # --- the cached dataset, edited
    def dataset(self, edit: Callable[[h5py.File], None] | None = None, raw: bytes | None = None) -> Path:
        data = self.tmp / "outputs" / "data" / self.pristine.name
        data.parent.mkdir(parents=True)
        if raw is not None:
            data.write_bytes(raw)
        else:
            shutil.copy(self.pristine, data)
            if edit:
                with h5py.File(data, "r+") as f:
                    edit(f)
        self.vars["data"] = str(Path("outputs") / "data" / data.name)
        return data

    def file(self, name: str, text: str | bytes) -> Path:
        path = self.tmp / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(text, bytes):
            path.write_bytes(text)
        else:
            path.write_text(text, newline="")
        self.vars[name.replace(".", "_").replace("/", "_")] = str(path)
        return path

    def sweep(self, edit: Callable[[Path], None] | None = None) -> Path:
        sweep = self.tmp / "sweep"
        job = sweep / "0"
        shutil.copytree(self.trained, job)
        (job / ".hydra").mkdir(exist_ok=True)
        cfg = json.loads(json.dumps(_run_config(self.trained)))
        import yaml

        (job / ".hydra" / "config.yaml").write_text(yaml.safe_dump(cfg))
        (job / ".hydra" / "overrides.yaml").write_text("- seed=0\n")
        self.vars["sweep"] = str(sweep)
        self.vars["job"] = str(job)
        if edit:
            edit(job)
        return sweep


def _run_config(run: Path) -> dict:
    return torch.load(run / "checkpoints" / "last.pt", map_location="cpu", weights_only=True)["config"]


@dataclass(frozen=True)
class Case:
    id: str
    args: tuple[str, ...]
    needles: tuple[str, ...]  # substrings of the error line ({name} placeholders from the setup)
    setup: Callable[[Ctx], None] | None = None
    code: int = 2
    proc: bool = False  # through a real `liedfl` process
    python: str | None = None  # proc: code run before main() (e.g. to send a signal at a given moment)
    allowed: tuple[str, ...] = field(default=())  # files that may appear (e.g. a dataset completed before a signal)


# ----------------------------------------------------------------------------- setups
def _ckpt_edit(fn, replace: bool = False):
    """Edit the run's checkpoint payload in place (or replace it by fn's result)."""

    def setup(ctx: Ctx):
        def edit(run: Path):
            path = run / "checkpoints" / "last.pt"
            payload = torch.load(path, map_location="cpu", weights_only=True)
            out = fn(payload)
            torch.save(out if replace else payload, path)

        ctx.run(edit)

    return setup


def _ckpt_bytes(data: bytes):
    return lambda ctx: ctx.run(lambda run: (run / "checkpoints" / "last.pt").write_bytes(data))


class _Payload:
    def __init__(self, marker: str):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _pickle_payload(ctx: Ctx):
    def edit(run: Path):
        path = run / "checkpoints" / "last.pt"
        payload = torch.load(path, map_location="cpu", weights_only=True)
        payload["timings"] = _Payload(str(ctx.tmp / "PWNED"))
        torch.save(payload, path)

    ctx.run(edit)


def _run_file(name: str, content: str | bytes):
    def setup(ctx: Ctx):
        def edit(run: Path):
            p = run / name
            p.write_bytes(content) if isinstance(content, bytes) else p.write_text(content)

        ctx.run(edit)

    return setup


def _replace(f: h5py.File, name: str, data) -> None:
    del f[name]
    f.create_dataset(name, data=data)


def _edit_R(fn):
    def edit(f):
        R = f["R"][...]
        out = fn(R)
        _replace(f, "R", R if out is None else out)

    return lambda ctx: ctx.dataset(edit)


def _edit(fn):
    return lambda ctx: ctx.dataset(fn)


def _reflect(R):
    R[0, 3, 0] = -R[0, 3, 0]


def _turn_too_far(R):
    """The increment of trajectory 1, step 4 -> 5 becomes a turn by 0.95 pi (ambiguous); the later
    increments are unchanged (the rest of the trajectory is rotated along)."""
    from liedfl_cli.lie import so3

    W = so3.exp(torch.tensor([0.0, 0.0, 0.95 * np.pi], dtype=torch.float64)).numpy()
    M = R[1, 4, 0] @ W @ R[1, 5, 0].T  # R_5 -> R_4 W
    R[1, 5:, 0] = M @ R[1, 5:, 0]


def _t_uneven(f):
    t = f["t"][...]
    t[5] += 0.01
    _replace(f, "t", t)


def _set_attr(name, value):
    return _edit(lambda f: f.attrs.__setitem__(name, value))


def _del(name):
    return _edit(lambda f: f.__delitem__(name))


def _physics(**changes):
    """Change entries of the cached dataset's declared physics (params["physics"])."""

    def edit(f):
        params = json.loads(f.attrs["params"])
        params["physics"].update(changes)
        f.attrs["params"] = json.dumps(params, sort_keys=True)

    return _edit(edit)


def _conf_with_typo(ctx: Ctx):
    conf = ctx.tmp / "conf" / "dataset"
    conf.mkdir(parents=True)
    text = (CONF_DIR / "dataset" / "free_rigid_body.yaml").read_text()
    (conf / "typo.yaml").write_text(text.replace("n_trajectories: 128", "n_trajectoriez: 128"))
    ctx.vars["conf"] = str(ctx.tmp / "conf")


def _tiny_bvh(
    frames=("0 0 0 0 0 0 10 20 30", "1 2 3 4 5 6 7 8 9"), declared=None, channels="Zrotation Yrotation Xrotation"
):
    lines = ["HIERARCHY", "ROOT Hips", "{", "\tOFFSET 0 0 0",
             "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation", "\tJOINT Arm", "\t{",
             "\t\tOFFSET 1 2 3", f"\t\tCHANNELS {len(channels.split())} {channels}", "\t\tEnd Site", "\t\t{",
             "\t\t\tOFFSET 0 0 1", "\t\t}", "\t}", "}", "MOTION",
             f"Frames: {len(frames) if declared is None else declared}", "Frame Time: 0.01", *frames]  # fmt: skip
    return "\n".join(lines) + "\n"


def _bvh(text: str | bytes):
    return lambda ctx: ctx.file("bad.bvh", text)


def _real_bvh(edit: Callable[[list[str]], None]):
    def setup(ctx: Ctx):
        lines = CMU.read_bytes().decode().splitlines(keepends=True)
        edit(lines)
        ctx.file("bad.bvh", "".join(lines))

    return setup


def _set_value(line_no: int, col: int, value: str):
    def edit(lines):
        vals = lines[line_no - 1].split()
        vals[col - 1] = value
        lines[line_no - 1] = " ".join(vals) + "\r\n"

    return edit


BVH_ARGS = (
    "data",
    "dataset=cmu_cartwheel",
    "dataset.files=[{bad_bvh}]",
    "dataset.n_trajectories=1",
    "ui.progress=false",
)


def _sweep_edit(fn):
    return lambda ctx: ctx.sweep(fn)


def _interrupt_generation(ctx: Ctx):
    """Ctrl-C while the scene is being simulated (before anything is written)."""
    from liedfl_cli.data import scenes

    def interrupted(cfg, progress=None):
        raise KeyboardInterrupt

    ctx.monkeypatch.setitem(scenes.SCENES, "free_rigid_body", interrupted)


_SIGNAL_DURING_WRITE = textwrap.dedent(
    """
    import os, signal, h5py
    _real = h5py.Group.create_dataset
    def _create(self, *a, **k):  # the signal arrives while the dataset file is being written
        os.kill(os.getpid(), signal.SIGINT)
        return _real(self, *a, **k)
    h5py.Group.create_dataset = _create
    """
)


# --- locks/signals setups (issue 18 items 2-4)
def _locked(host: str | None = None, dead: bool = False):
    """The run, locked by another process: a live one of this host (the test runner's parent), or one of
    another host (its pid, dead or not, means nothing here)."""

    def setup(ctx: Ctx):
        from liedfl_cli.files import locks
        from liedfl_cli.files.io_utils import host_id

        run = ctx.run()
        pid = _gone_pid() if dead else os.getppid()
        record = {"host": host or host_id(), "hostname": host or "thishost", "pid": pid,
                  "start": "" if host else locks.process_start(pid), "since": "2026-01-01T00:00:00+00:00",
                  "command": "train", "token": "e" * 16}  # fmt: skip
        (run / locks.LOCK_FILE).write_text(json.dumps(record))

    return setup


# --- setups of the values block (issue 18 items 6, 7, 9, 10)
RUN_FOLDER = ("outputs", "outputs/runs", "outputs/runs/*")  # a failed train keeps its run folder (status.json)


def _bad_yaml(group: str, text: str):
    def setup(ctx: Ctx):
        d = ctx.tmp / "conf" / group
        d.mkdir(parents=True)
        (d / "bad.yaml").write_text(text)
        ctx.vars["conf"] = str(ctx.tmp / "conf")

    return setup


def _gone_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _signal_hook(target: str, *sigs: str) -> str:
    """Python run before main(): `target` ('module:attribute') first sends `sigs` to the process."""
    module, attr = target.split(":")
    kills = "".join(f"    os.kill(os.getpid(), signal.{s})\n" for s in sigs)
    return (
        f"import os, signal, importlib\n_m = importlib.import_module({module!r})\n_real = _m.{attr}\n"
        f"def _hooked(*a, **k):\n{kills}    return _real(*a, **k)\n_m.{attr} = _hooked\n"
    )


def _run_and_outside_rollout(ctx: Ctx):
    run = ctx.run()
    (ctx.tmp / "elsewhere").mkdir()
    shutil.copy(run / "rollout.h5", ctx.tmp / "elsewhere" / "rollout.h5")
    ctx.vars["elsewhere"] = str(ctx.tmp / "elsewhere")


_IGNORE_SIGINT = "import signal\nsignal.signal(signal.SIGINT, signal.SIG_IGN)  # as if inherited (nohup)\n"
_RO = ("ui.progress=false", "eval.plots=false")


def _scaled_weights(factor: float):
    """Both checkpoints' weights times `factor`: finite, but the model's predictions are not."""

    def setup(ctx: Ctx):
        def edit(run: Path):
            for name in ("last.pt", "best.pt"):
                path = run / "checkpoints" / name
                if path.is_file():
                    payload = torch.load(path, map_location="cpu", weights_only=True)
                    for v in payload["state_dict"].values():
                        if v.is_floating_point():
                            v.mul_(factor)
                    torch.save(payload, path)

        ctx.run(edit)

    return setup


def _enospc(filename=None) -> OSError:
    import errno

    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), *([str(filename)] if filename is not None else []))


def _disk_full_torch_save(ctx: Ctx):
    """The disk fills while a checkpoint is written: torch.save fails on the temporary file."""
    ctx.dataset()

    def save(obj, f, *a, **k):
        Path(f).write_bytes(b"half")  # a partial temporary file, which must not stay
        raise _enospc(f)

    ctx.monkeypatch.setattr(torch, "save", save)


def _disk_full_h5(ctx: Ctx):
    """The disk fills while the dataset is written (h5py's errors name no file)."""

    def create(self, *a, **k):
        raise _enospc()

    ctx.monkeypatch.setattr(h5py.Group, "create_dataset", create)


def _disk_full_json(ctx: Ctx):
    ctx.dataset()
    real = Path.write_text

    def write_text(self, *a, **k):
        if ".tmp" in self.name:
            real(self, "{", encoding="utf-8")
            raise _enospc(self)
        return real(self, *a, **k)

    ctx.monkeypatch.setattr(Path, "write_text", write_text)


# ----------------------------------------------------------------------------- the table
# --- setups of the import / export / logger block (the features of the usability round)
def _import_csv(edit: Callable[[list[str]], list[str]] | None = None, name: str = "log.csv"):
    """A valid two-recording CSV log (tests/own_data.py), its lines edited by `edit`."""

    def setup(ctx: Ctx):
        from own_data import write_csv

        path, _, _ = write_csv(ctx.tmp / name, n_traj=2, n_samples=21, rotation="wxyz")
        if edit is not None:
            path.write_text("\n".join(edit(path.read_text().splitlines())) + "\n")

    return setup


def _cell(row: int, col: int, value: str):
    """Line `row` (0 = the header) with field `col` replaced."""

    def edit(lines: list[str]) -> list[str]:
        cells = lines[row].split(",")
        cells[col] = value
        return [*lines[:row], ",".join(cells), *lines[row + 1 :]]

    return edit


def _swap(a: int, b: int):
    def edit(lines: list[str]) -> list[str]:
        lines = list(lines)
        lines[a], lines[b] = lines[b], lines[a]
        return lines

    return edit


def _npz_without_q(ctx: Ctx):
    np.savez(ctx.tmp / "log.npz", t=np.arange(5.0))


IMP = ("data", "dataset=import", "dataset.path=log.csv", "dataset.rotation=wxyz")


T = "train"
CASES: list[Case] = [
    # --- config values (fail before any folder or data exists)
    Case("epochs-minus-one", (T, *FAST, "train.epochs=-1"), ("train.epochs=-1", "integer >= 0")),
    Case("epochs-negative", (T, *FAST, "train.epochs=-5"), ("train.epochs=-5",)),
    Case("epochs-text", (T, *FAST, "train.epochs=many"), ("train.epochs", "many")),
    Case("batch-zero", (T, *FAST, "train.batch_size=0"), ("train.batch_size=0",)),
    Case("batch-negative", (T, *FAST, "train.batch_size=-3"), ("train.batch_size=-3",)),
    Case("lr-negative", (T, *FAST, "train.optimizer.lr=-1"), ("train.optimizer.lr=-1", "positive")),
    Case("lr-zero", (T, *FAST, "train.optimizer.lr=0"), ("train.optimizer.lr=0",)),
    Case("lr-nan", (T, *FAST, "train.optimizer.lr=nan"), ("train.optimizer.lr=nan",)),
    Case("optimizer-unknown", (T, *FAST, "train.optimizer.name=sgd"), ("train.optimizer.name", "sgd")),
    Case("schedule-unknown", (T, *FAST, "train.optimizer.schedule=linear"), ("train.optimizer.schedule",)),
    Case("weight-decay-negative", (T, *FAST, "train.optimizer.weight_decay=-0.1"), ("train.optimizer.weight_decay",)),
    Case("reg-form-unknown", (T, *FAST, "train.reg_form=cubic"), ("train.reg_form", "cubic")),
    Case("w-del-negative", (T, *FAST, "train.w_del=-1"), ("train.w_del=-1",)),
    Case("reg-points-negative", (T, *FAST, "train.reg_points=-2"), ("train.reg_points=-2",)),
    Case("seed-text", (T, *FAST, "seed=abc"), ("seed='abc'", "integer")),
    Case("seed-float", (T, *FAST, "seed=1.5"), ("seed=1.5",)),
    Case("seed-negative", (T, *FAST, "seed=-3"), ("seed=-3",)),
    Case("epoch-scale-zero", (T, *FAST, "epoch_scale=0"), ("epoch_scale=0",)),
    Case("epoch-scale-text", (T, *FAST, "epoch_scale=abc"), ("epoch_scale='abc'",)),
    Case("data-dir-under-a-file", (T, *FAST, "paths.data_dir=/dev/null/x"), ("paths.data_dir=/dev/null/x",)),
    Case(
        "data-dir-is-a-file",
        (T, *FAST, "paths.data_dir={afile}"),
        ("paths.data_dir=", "not a directory"),
        setup=lambda ctx: ctx.vars.update(afile=str(ctx.file("afile", "x"))),
    ),
    Case("target-builtin", (T, *FAST, "model._target_=builtins.print"), ("model._target_", "builtins.print")),
    Case("target-os-system", (T, *FAST, "model._target_=os.system"), ("model._target_", "os.system")),
    Case("target-own-function", (T, *FAST, "model._target_=liedfl_cli.files.io_utils.write_text"), ("model._target_",)),
    Case("target-missing-class", (T, *FAST, "model._target_=liedfl_cli.models.Nope"), ("model._target_",)),
    Case("residual-unknown", (T, *FAST, "model.residual=bogus"), ("model.residual", "bogus")),
    Case("potential-unknown", (T, *FAST, "model.potential=quadratic"), ("model.potential",)),
    Case("known-part-unknown", (T, *FAST, "model.known=[mass]"), ("model.known", "mass")),
    Case("rollout-steps-zero", (T, *FAST, "rollout.steps=0"), ("rollout.steps=0",)),
    Case("rollout-max-traj-zero", (T, *FAST, "rollout.max_trajectories=0"), ("rollout.max_trajectories=0",)),
    Case("solver-tol-zero", (T, *FAST, "solver.tol=0"), ("solver.tol=0",)),
    Case("solver-max-iter-zero", (T, *FAST, "solver.max_iter=0"), ("solver.max_iter=0",)),
    Case("empty-train-split", (T, *FAST, "dataset.n_test=6"), ("dataset.n_test=6", "no training")),
    Case("empty-test-split", (T, *FAST, "dataset.n_test=0"), ("dataset.n_test=0", "empty test split")),
    Case("h-negative", (T, *FAST, "dataset.h=-1"), ("dataset.h", "-1")),
    Case("steps-too-short", (T, *FAST, "dataset.steps=3"), ("dataset.steps=3",)),
    Case("test-fraction-too-big", (T, *FAST, "dataset.test_fraction=1.5"), ("dataset.test_fraction",)),
    Case("ode-method-unknown", (T, *FAST, "dataset.solver.method=Euler"), ("solver.method", "Euler")),
    Case("section-removed", (T, *FAST, "~train"), ("train.epochs", "missing")),
    Case("dataset-key-removed", (T, *FAST, "~dataset.h"), ("dataset", "'h'")),
    # --- unknown keys, with the closest valid one
    Case("typo-dataset", (T, *FAST, "+dataset.n_trajectoriez=3"), ("dataset.n_trajectoriez", "dataset.n_trajectories")),
    Case("typo-top-level", (T, *FAST, "+foo=1"), ("'foo'",)),
    Case("typo-top-level-empty", (T, *FAST, "+foo="), ("'foo'",)),
    Case("typo-train", (T, *FAST, "+train.epoch=3"), ("train.epoch", "train.epochs")),
    Case("typo-optimizer", (T, *FAST, "+train.optimizer.lrate=0.1"), ("train.optimizer.lrate",)),
    Case("typo-solver", (T, *FAST, "+solver.maxiter=3"), ("solver.maxiter", "solver.max_iter")),
    Case("typo-model", (T, *FAST, "+model.mlp_widht=3"), ("model.mlp_widht", "model.mlp_width")),
    Case("typo-physics", (T, *FAST, "+dataset.physics.JJ=1"), ("dataset.physics.JJ", "dataset.physics.J")),
    Case("typo-initial", (T, *FAST, "+dataset.initial.omega_sd=1"), ("dataset.initial.omega_sd", "omega_std")),
    Case("typo-force-option", (T, *FAST, "+force.rayleigh.init=1"), ("force.rayleigh.init", "init_diag")),
    Case("force-unknown", (T, *FAST, "+force.magnet.k=1"), ("force.magnet",)),
    Case("typo-model-option", (T, *FAST, "baseline=glnn_rk4", "+model.rtoll=1"), ("model.rtoll", "model.rtol")),
    Case("typo-rollout", (T, *FAST, "+rollout.step=3"), ("rollout.step", "rollout.steps")),
    Case("typo-paths", (T, *FAST, "+paths.dta_dir=x"), ("paths.dta_dir", "paths.data_dir")),
    Case("typo-ui", (T, *FAST, "+ui.progres=false"), ("ui.progres", "ui.progress")),
    Case(
        "typo-mocap", ("data", "dataset=cmu_cartwheel", "+dataset.skipframes=2"), ("dataset.skipframes", "skip_frames")
    ),
    Case(
        "typo-in-dataset-yaml",
        (T, "--config-dir", "{conf}", *FAST, "dataset=typo"),
        ("dataset.n_trajectoriez", "dataset.n_trajectories"),
        setup=_conf_with_typo,
    ),
    # --- Hydra's own errors, one line with a hint
    Case("hydra-missing-option", (T, "dataset=nosuch"), ("dataset/nosuch", "free_rigid_body", "HYDRA_FULL_ERROR")),
    Case("hydra-missing-baseline", (T, "baseline=nosuch"), ("baseline/nosuch", "glnn_rk4")),
    Case("hydra-override-without-plus", (T, "train.epoch=3"), ("train.epoch", "train.epochs")),
    Case(
        "hydra-override-without-plus-scene",
        (T, "dataset=file", "dataset.pth=x.h5"),
        ("unknown config key 'dataset.pth' for scene 'file'", "did you mean 'dataset.path'?"),
    ),
    Case("hydra-grammar", (T, "a=b=c"), ("a=b=c",)),
    Case("hydra-unclosed-list", (T, "seed=[1,2"), ("seed=[1,2",)),
    Case("hydra-delete-missing", (T, "~nosuchkey"), ("nosuchkey",)),
    Case("unknown-flag", (T, "--epochs", "3"), ("unrecognized arguments: --epochs",)),
    Case("flag-without-value", (T, "--cfg"), ("--cfg",)),
    Case("multirun-with-cfg", (T, "-m", *FAST, "train.epochs=1,2", "--cfg", "job"), ("--cfg", "-m", "one value")),
    Case("multirun-with-info", (T, "--multirun", "--info"), ("--info", "--multirun")),
    # --- rollout / eval / report arguments
    Case("eval-run-missing", ("eval", "run={tmp}/nope"), ("run=", "no such run directory")),
    Case("eval-run-not-given", ("eval",), ("run=<run dir> is required",)),
    Case("report-sweep-missing", ("report", "sweep={tmp}/nope"), ("sweep=", "no such")),
    Case(
        "report-sweep-empty",
        ("report", "sweep={tmp}/empty"),
        ("no finished runs",),
        setup=lambda ctx: (ctx.tmp / "empty").mkdir(),
    ),
    Case("rollout-steps-arg-zero", ("rollout", "run={run}", "steps=0"), ("steps=0",), setup=lambda c: c.run()),
    Case("rollout-steps-arg-text", ("rollout", "run={run}", "steps=abc"), ("steps", "abc"), setup=lambda c: c.run()),
    Case("rollout-steps-arg-negative", ("rollout", "run={run}", "steps=-3"), ("steps=-3",), setup=lambda c: c.run()),
    Case("eval-typo", ("eval", "run={run}", "+rollot=x"), ("rollot", "rollout"), setup=lambda c: c.run()),
    Case("rollout-latest-no-runs", ("rollout", "run=latest"), ("run=latest", "no run under outputs/runs/")),
    Case("resume-latest-no-runs", (T, "resume=latest"), ("resume=latest", "no run under outputs/runs/")),
    # --- run folders and checkpoints
    Case(
        "ckpt-missing",
        ("eval", "run={run}"),
        ("{ckpt}", "not found"),
        setup=lambda c: c.run(lambda r: shutil.rmtree(r / "checkpoints")),
    ),
    Case(
        "ckpt-random-bytes",
        ("eval", "run={run}"),
        ("{ckpt}", "not a readable checkpoint"),
        setup=_ckpt_bytes(np.random.default_rng(0).bytes(4096)),
    ),
    Case("ckpt-empty-file", ("eval", "run={run}"), ("{ckpt}", "not a readable checkpoint"), setup=_ckpt_bytes(b"")),
    Case("ckpt-pickle-payload", ("eval", "run={run}"), ("{ckpt}", "refused"), setup=_pickle_payload),
    Case("ckpt-pickle-payload-cli", ("eval", "run={run}"), ("{ckpt}", "refused"), setup=_pickle_payload, proc=True),
    Case(
        "ckpt-not-a-dict",
        ("eval", "run={run}"),
        ("{ckpt}", "not a dict"),
        setup=_ckpt_edit(lambda p: [1, 2], replace=True),
    ),
    Case("ckpt-no-config", ("eval", "run={run}"), ("{ckpt}", "'config'"), setup=_ckpt_edit(lambda p: p.pop("config"))),
    Case(
        "ckpt-config-not-mapping",
        ("eval", "run={run}"),
        ("{ckpt}", "'config'"),
        setup=_ckpt_edit(lambda p: p.__setitem__("config", "x")),
    ),
    Case(
        "ckpt-wrong-shape",
        ("eval", "run={run}"),
        ("{ckpt}", "state_dict.", "(7, 5)"),
        setup=_ckpt_edit(lambda p: p["state_dict"].__setitem__(next(iter(p["state_dict"])), torch.zeros(7, 5))),
    ),
    Case(
        "ckpt-non-finite",
        ("eval", "run={run}"),
        ("{ckpt}", "non-finite"),
        setup=_ckpt_edit(lambda p: next(iter(p["state_dict"].values())).fill_(float("nan"))),
    ),
    Case(
        "ckpt-extra-key",
        ("eval", "run={run}"),
        ("{ckpt}", "unexpected key 'bogus'"),
        setup=_ckpt_edit(lambda p: p["state_dict"].__setitem__("bogus", torch.zeros(1))),
    ),
    Case(
        "ckpt-is-a-folder",
        ("eval", "run={run}"),
        ("{ckpt}", "not found"),
        setup=lambda c: c.run(
            lambda r: ((r / "checkpoints" / "last.pt").unlink(), (r / "checkpoints" / "last.pt").mkdir())
        ),
    ),
    Case(
        "metrics-not-numbers",
        ("eval", "run={run}"),
        ("train_metrics.csv", "line 3", "'loss'"),
        setup=_run_file("train_metrics.csv", "epoch,loss\n1,0.5\n2,lots\n"),
    ),
    Case(
        "metrics-binary",
        ("eval", "run={run}"),
        ("train_metrics.csv",),
        setup=_run_file("train_metrics.csv", b"\xff\xfe\x00garbage"),
    ),
    Case(
        "metrics-no-loss-column",
        ("eval", "run={run}"),
        ("train_metrics.csv", "'loss'"),
        setup=_run_file("train_metrics.csv", "epoch,other\n1,2\n"),
    ),
    Case(
        "metrics-ragged",
        ("eval", "run={run}"),
        ("train_metrics.csv", "line 2", "more fields"),
        setup=_run_file("train_metrics.csv", "epoch,loss\n1,0.5,7\n"),
    ),
    Case(
        "recovery-garbled",
        ("eval", "run={run}"),
        ("recovery.json", "not valid JSON"),
        setup=_run_file("recovery.json", "{oops"),
    ),
    Case(
        "recovery-not-object",
        ("eval", "run={run}"),
        ("recovery.json", "JSON object"),
        setup=_run_file("recovery.json", "[1, 2]"),
    ),
    Case(
        "report-eval-csv-binary",
        ("report", "sweep={sweep}", "plots=false"),
        ("eval.csv",),
        setup=_sweep_edit(lambda j: (j / "eval.csv").write_bytes(b"\xff\xfe\x00\x01")),
    ),
    Case(
        "report-eval-csv-text-number",
        ("report", "sweep={sweep}", "plots=false"),
        ("eval.csv", "rel_rot_error_mean"),
        setup=_sweep_edit(lambda j: (j / "eval.csv").write_text("model,rel_rot_error_mean\nmodel,high\n")),
    ),
    Case(
        "report-summary-garbled",
        ("report", "sweep={sweep}", "plots=false"),
        ("summary.json", "not valid JSON"),
        setup=_sweep_edit(lambda j: (j / "summary.json").write_text("{")),
    ),
    Case(
        "report-config-garbled",
        ("report", "sweep={sweep}", "plots=false"),
        ("config.yaml",),
        setup=_sweep_edit(lambda j: (j / ".hydra" / "config.yaml").write_text("a: [unclosed\n")),
    ),
    Case(
        "report-config-not-train",
        ("report", "sweep={sweep}", "plots=false"),
        ("config.yaml", "'dataset'"),
        setup=_sweep_edit(lambda j: (j / ".hydra" / "config.yaml").write_text("seed: 0\n")),
    ),
    # --- datasets (the cached file of `liedfl train budget=smoke`, broken; fails at load, no run folder left)
    Case(
        "data-nan",
        (T, *FAST),
        ("{data}", "'R'", "non-finite", "(1, 3, 0, 0, 0)"),
        setup=_edit_R(lambda R: R.__setitem__((1, 3, 0, 0, 0), np.nan)),
    ),
    Case(
        "data-not-rotation",
        (T, *FAST),
        ("{data}", "not a rotation", "(0, 2, 0)"),
        setup=_edit_R(lambda R: R.__setitem__((0, 2, 0), 2 * R[0, 2, 0])),
    ),
    Case("data-reflection", (T, *FAST), ("{data}", "det R = -1", "(0, 3, 0)"), setup=_edit_R(_reflect)),
    Case(
        "data-ambiguous-steps",
        (T, *FAST),
        ("{data}", "turns too far", "trajectory 1, step 4 -> 5"),
        setup=_edit_R(_turn_too_far),
    ),
    Case("data-R-wrong-shape", (T, *FAST), ("{data}", "'R'", "shape"), setup=_edit_R(lambda R: R[:, :, :, :2])),
    Case(
        "data-R-integers", (T, *FAST), ("{data}", "'R'", "floating-point"), setup=_edit_R(lambda R: R.astype(np.int64))
    ),
    Case("data-R-float16", (T, *FAST), ("{data}", "'R'", "float16"), setup=_edit_R(lambda R: R.astype(np.float16))),
    Case("data-R-missing", (T, *FAST), ("{data}", "'R'", "missing"), setup=_del("R")),
    Case("data-params-list", (T, *FAST), ("{data}", "'params'", "JSON object"), setup=_set_attr("params", "[1, 2]")),
    Case("data-seed-text", (T, *FAST), ("{data}", "'seed'", "integer"), setup=_set_attr("seed", "abc")),
    Case("data-physics-J-text", (T, *FAST), ("{data}", "params.physics.J", "number"), setup=_physics(J="heavy")),
    Case(
        "data-physics-J-triangle", (T, *FAST), ("{data}", "params.physics.J", "triangle"), setup=_physics(J=[1, 1, 5])
    ),
    Case("data-physics-D-size", (T, *FAST), ("{data}", "params.physics.D", "shape (2,)"), setup=_physics(D=[0, 0])),
    Case("override-physics-J-triangle", (T, *FAST, "dataset.physics.J=[1,1,5]"), ("dataset.physics.J", "triangle")),
    Case("data-no-split", (T, *FAST), ("{data}", "group 'split' is missing"), setup=_del("split")),
    Case(
        "data-empty-train",
        (T, *FAST),
        ("{data}", "'split/train' is empty"),
        setup=_edit(lambda f: _replace(f, "split/train", np.zeros(0, dtype=np.int64))),
    ),
    Case(
        "data-split-out-of-range",
        (T, *FAST),
        ("{data}", "'split/train'", "out of range"),
        setup=_edit(lambda f: _replace(f, "split/train", np.array([0, 99]))),
    ),
    Case(
        "data-split-overlap",
        (T, *FAST),
        ("{data}", "'split/test'", "disjoint"),
        setup=_edit(lambda f: _replace(f, "split/test", f["split/train"][:1])),
    ),
    Case(
        "data-split-floats",
        (T, *FAST),
        ("{data}", "'split/train'", "integers"),
        setup=_edit(lambda f: _replace(f, "split/train", f["split/train"][...].astype(float))),
    ),
    Case("data-h-missing", (T, *FAST), ("{data}", "'h'", "missing"), setup=_edit(lambda f: f.attrs.__delitem__("h"))),
    Case("data-h-negative", (T, *FAST), ("{data}", "'h'"), setup=_set_attr("h", -0.1)),
    Case(
        "data-format-version", (T, *FAST), ("{data}", "'format_version'", "99"), setup=_set_attr("format_version", 99)
    ),
    Case("data-body-kinds-json", (T, *FAST), ("{data}", "'body_kinds'", "JSON"), setup=_set_attr("body_kinds", "[so3")),
    Case(
        "data-body-kinds-unknown",
        (T, *FAST),
        ("{data}", "'body_kinds'", "'se2'"),
        setup=_edit(lambda f: (f.attrs.__delitem__("n_so3"), f.attrs.__setitem__("body_kinds", '["se2"]'))),
    ),
    Case("data-t-uneven", (T, *FAST), ("{data}", "'t'", "evenly spaced"), setup=_edit(_t_uneven)),
    Case(
        "data-extras-wrong-length",
        (T, *FAST),
        ("{data}", "extras/omega"),
        setup=_edit(lambda f: _replace(f, "extras/omega", f["extras/omega"][:1])),
    ),
    Case("data-not-hdf5", (T, *FAST), ("{data}", "not an HDF5 file"), setup=lambda c: c.dataset(raw=b"R,p\n1,2\n")),
    Case(  # (in-process: ckpt-pickle-payload-cli and the signal cases take `liedfl` through a process)
        "data-inf",
        (T, *FAST),
        ("{data}", "non-finite"),
        setup=_edit_R(lambda R: R.__setitem__((0, 1, 0, 2, 2), np.inf)),
    ),
    # --- BVH files (imported through the cmu_cartwheel scene)
    Case(
        "bvh-missing", (*BVH_ARGS[:2], "dataset.files=[{tmp}/none.bvh]", *BVH_ARGS[3:]), ("none.bvh", "does not exist")
    ),
    Case("bvh-empty", BVH_ARGS, ("bad.bvh", "empty"), setup=_bvh("")),
    Case("bvh-binary", BVH_ARGS, ("bad.bvh",), setup=_bvh(b"\x00\xff\xfe garbage \x00")),
    Case(
        "bvh-unknown-channel",
        BVH_ARGS,
        ("bad.bvh", "line 9", "Wrotation"),
        setup=_bvh(_tiny_bvh(channels="Zrotation Wrotation Xrotation")),
    ),
    Case("bvh-frame-count", BVH_ARGS, ("bad.bvh", "'Frames'", "declares 5"), setup=_bvh(_tiny_bvh(declared=5))),
    Case(
        "bvh-short-line",
        BVH_ARGS,
        ("bad.bvh", "line 20", "8 values"),
        setup=_bvh(_tiny_bvh(frames=("0 0 0 0 0 0 1 2 3", "0 0 0 0 0 0 1 2"))),
    ),
    Case("bvh-no-motion", BVH_ARGS, ("bad.bvh", "MOTION"), setup=_bvh(_tiny_bvh().split("MOTION")[0])),
    Case("bvh-missing-joints", BVH_ARGS, ("bad.bvh", "LHipJoint", "not in the hierarchy"), setup=_bvh(_tiny_bvh())),
    Case(
        "bvh-real-not-a-number",
        BVH_ARGS,
        ("bad.bvh", "line 300", "'1.2.3'"),
        setup=_real_bvh(_set_value(300, 41, "1.2.3")),
    ),
    Case(
        "bvh-real-infinite", BVH_ARGS, ("bad.bvh", "line 250", "not finite"), setup=_real_bvh(_set_value(250, 5, "inf"))
    ),
    Case(
        "bvh-real-truncated",
        BVH_ARGS,
        ("bad.bvh", "truncated"),
        setup=_real_bvh(lambda lines: lines.__delitem__(slice(100, None))),
    ),
    Case(
        "bvh-wrong-frame-time",
        (*BVH_ARGS, "dataset.h=0.5"),
        ("dataset.h=0.5", "Frame Time"),
        setup=lambda c: c.file("bad.bvh", CMU.read_bytes()),
    ),
    # --- interruptions
    Case(
        "ctrl-c-during-generation",
        ("data", "budget=smoke", "ui.progress=false"),
        ("interrupted",),
        code=130,
        setup=_interrupt_generation,
    ),
    Case(
        "ctrl-c-during-dataset-write",
        ("data", "budget=smoke", "ui.progress=false"),
        ("interrupted",),
        code=130,
        proc=True,
        python=_SIGNAL_DURING_WRITE,
        allowed=("outputs", "outputs/data", "outputs/data/*.h5"),
    ),
    Case(
        "ctrl-c-during-train-data-write",
        (T, *FAST),
        ("interrupted",),
        code=130,
        proc=True,
        python=_SIGNAL_DURING_WRITE,
        allowed=("outputs", "outputs/data", "outputs/data/*.h5"),
    ),
    # --- locks/signals (issue 18 items 2-4)
    Case("lock-held-eval", ("eval", "run={run}", *_RO), ("run folder {run}", "in use", "pid"), setup=_locked()),
    Case("lock-held-rollout", ("rollout", "run={run}", *_RO), ("run folder {run}", "in use"), setup=_locked()),
    Case("lock-held-resume", (T, "resume={run}", "ui.progress=false"), ("run folder {run}", "in use"), setup=_locked()),
    Case(
        "lock-held-train-same-dir", (T, *FAST, "hydra.run.dir={run}"), ("run folder {run}", "in use"), setup=_locked()
    ),
    Case("lock-held-eval-cli", ("eval", "run={run}", *_RO), ("run folder {run}", "in use"), setup=_locked(), proc=True),
    Case(
        "lock-other-host-eval",
        ("eval", "run={run}", *_RO),
        ("{run}", "another machine", "othernode", "LIEDFL_RUN_LOCK=break"),
        setup=_locked("othernode"),
    ),
    Case(
        "lock-other-host-dead-pid-rollout",
        ("rollout", "run={run}", *_RO),
        ("{run}", "another machine", "LIEDFL_RUN_LOCK=break"),
        setup=_locked("othernode", dead=True),
    ),
    Case(
        "lock-other-host-dead-pid-resume",
        (T, "resume={run}", "ui.progress=false"),
        ("{run}", "another machine"),
        setup=_locked("othernode", dead=True),
        proc=True,
    ),
    # (SIGTERM / SIGINT during data generation, a rollout, an evaluation: test_signals_phases.py)
    Case(
        "sigterm-during-rollout-eval",
        ("rollout", "run={run}", "steps=12", *_RO),
        ("SIGTERM: interrupted during evaluation", "nothing kept"),
        setup=lambda c: c.run(),
        code=143,
        proc=True,
        python=_signal_hook("liedfl_cli.commands.evaluate:run_eval_from_objects", "SIGTERM"),
    ),
    Case(
        "sigterm-during-report",
        ("report", "sweep={sweep}", "plots=false"),
        ("SIGTERM: interrupted during report",),
        setup=lambda c: c.sweep(),
        code=143,
        proc=True,
        python=_signal_hook("liedfl_cli.commands.report:collect", "SIGTERM"),
    ),
    Case(
        "sigint-ignored-then-sigterm-during-rollout",
        ("rollout", "run={run}", "steps=12", *_RO),
        ("SIGTERM: interrupted during rollout",),
        setup=lambda c: c.run(),
        code=143,
        proc=True,
        python=_IGNORE_SIGINT + _signal_hook("liedfl_cli.commands.rollout:_roll", "SIGINT", "SIGTERM"),
    ),
    # --- values (issue 18 items 6,7,9,10) ---
    Case(
        "lr-diverges-soap",
        (T, *FAST, "train.optimizer.lr=1e300"),
        ("training diverged", "learning rate diverged", "train.optimizer.lr=1e+300"),
        setup=lambda c: c.dataset(),
        allowed=RUN_FOLDER,
    ),
    Case(
        "lr-diverges-adam",
        (T, *FAST, "train.optimizer.lr=1e6", "train.optimizer.name=adam"),
        ("training diverged", "learning rate diverged", "adam"),
        setup=lambda c: c.dataset(),
        allowed=RUN_FOLDER,
    ),
    Case("seed-past-64-bits", (T, *FAST, "seed=18446744073709551616"), ("seed=18446744073709551616", "2**63 - 1")),
    Case("seed-2-to-the-63", (T, *FAST, "seed=9223372036854775808"), ("seed=9223372036854775808",)),
    Case("target-abstract-model", (T, *FAST, "model._target_=liedfl_cli.models.base.Model"), ("abstract",)),
    Case(
        "target-abstract-implicit",
        (T, *FAST, "model._target_=liedfl_cli.models.base.ImplicitModel"),
        ("model._target_", "abstract"),
    ),
    Case(
        "yaml-syntax-config-dir",
        (T, "--config-dir", "{conf}", *FAST, "dataset=bad"),
        ("bad.yaml: line 4, column 1", "YAML syntax error"),
        setup=_bad_yaml("dataset", "name: free_rigid_body\nh: 0.1\nn_trajectories: [1,\n"),
    ),
    Case(
        "yaml-syntax-experiment",
        (T, "--config-dir", "{conf}", *FAST, "+experiment=bad"),
        ("bad.yaml: line 4", "YAML syntax error", "mapping values are not allowed"),
        setup=_bad_yaml("experiment", "# @package _global_\ntrain:\n  epochs: 3\n   lr: 2\n"),
    ),
    Case(
        "size-trajectories",
        (T, *FAST, "dataset.n_trajectories=1000000000000"),
        ("dataset.n_trajectories=1000000000000", "memory", "this machine's"),
    ),
    Case(
        "size-trajectories-float",
        ("data", "budget=smoke", "dataset.n_trajectories=1e12"),
        ("dataset.n_trajectories", "memory"),
    ),
    Case(
        "size-steps",
        (T, *FAST, "dataset.steps=100000000000000", "dataset.n_trajectories=100"),
        ("dataset.steps=100000000000000", "memory"),
    ),
    Case("size-mlp-width", (T, *FAST, "model.mlp_width=1000000000"), ("model.mlp_width=1000000000", "memory")),
    Case(
        "size-mlp-width-ode",
        (T, *FAST, "baseline=neural_ode", "model.mlp_width=100000000"),
        ("model.mlp_width=100000000", "memory"),
    ),
    Case("rollout-huge-weights", ("rollout", "run={run}"), ("non-finite", "unusable"), setup=_scaled_weights(1e300)),
    Case(
        "rollout-huge-weights-last",
        ("rollout", "run={run}", "checkpoint=last"),
        ("{ckpt}", "non-finite", "largest |weight|"),
        setup=_scaled_weights(1e300),
    ),
    Case("eval-huge-weights", ("eval", "run={run}"), ("non-finite", "unusable"), setup=_scaled_weights(1e300)),
    Case(
        "data-split-2d",
        (T, *FAST),
        ("{data}", "'split/train'", "1-D", "(2, 2)"),
        setup=_edit(lambda f: _replace(f, "split/train", f["split/train"][...][:4].reshape(2, 2))),
    ),
    Case(
        "data-split-2d-test",
        (T, *FAST),
        ("{data}", "'split/test'", "1-D"),
        setup=_edit(lambda f: _replace(f, "split/test", f["split/test"][...].reshape(1, -1))),
    ),
    Case(
        "dataset-changed-rollout",
        ("rollout", "run={run}"),
        ("changed since", "accept_changed_dataset=true"),
        setup=_ckpt_edit(lambda p: p.__setitem__("dataset_sha256", "0" * 64)),
    ),
    Case(
        "dataset-changed-eval",
        ("eval", "run={run}"),
        ("changed since", "accept_changed_dataset=true"),
        setup=_ckpt_edit(lambda p: p.__setitem__("dataset_sha256", "0" * 64)),
    ),
    Case(
        "accept-changed-dataset-not-bool",
        ("eval", "run={run}", "accept_changed_dataset=maybe"),
        ("accept_changed_dataset='maybe'", "true or false"),
        setup=lambda c: c.run(),
    ),
    Case(
        "ckpt-plain-pickle",
        ("eval", "run={run}"),
        ("{ckpt}", "not a readable checkpoint"),
        setup=_ckpt_bytes(__import__("pickle").dumps({"state_dict": {}, "x": list(range(3))}, protocol=4)),
    ),
    Case(
        "ckpt-plain-pickle-protocol5",
        ("eval", "run={run}"),
        ("{ckpt}", "not a readable checkpoint"),
        setup=_ckpt_bytes(__import__("pickle").dumps({"state_dict": {}}, protocol=5)),
    ),
    Case(
        "disk-full-checkpoint",
        (T, *FAST),
        ("checkpoints/best.pt: No space left on device",),
        setup=_disk_full_torch_save,
        allowed=RUN_FOLDER,
    ),
    Case(
        "disk-full-dataset-no-filename",
        ("data", "budget=smoke", "ui.progress=false"),
        ("No space left on device",),
        setup=_disk_full_h5,
        allowed=("outputs", "outputs/data"),
    ),
    Case(
        "disk-full-json",
        (T, *FAST),
        ("components.json: No space left on device",),
        setup=_disk_full_json,
        allowed=RUN_FOLDER,
    ),
    # --- import / export / logger (the usability round's new keys and files)
    Case("import-time-unit-unknown", (*IMP, "dataset.time_unit=hours"), ("dataset.time_unit='hours'", "s, ms or us")),
    Case("import-gravity-text", (*IMP, "dataset.gravity=down"), ("dataset.gravity='down'",), setup=_import_csv()),
    Case("import-gravity-2-vector", (*IMP, "dataset.gravity=[0,9.81]"), ("dataset.gravity=[0, 9.81]",)),
    Case(
        "import-columns-no-such-column",
        (*IMP, "dataset.columns={{q0:qa}}"),
        ("log.csv", "dataset.columns.q0=qa", "no such column"),
        setup=_import_csv(),
    ),
    Case("import-columns-list-too-short", (*IMP, "dataset.columns=[a,b]"), ("dataset.columns=['a', 'b']",)),
    Case(
        "import-time-column-missing",
        (*IMP, "dataset.time_column=time"),
        ("log.csv", "column 'time' is missing", "dataset.columns"),
        setup=_import_csv(),
    ),
    Case(
        "import-rotation-unknown", (*IMP[:3], "dataset.rotation=zyx"), ("dataset.rotation='zyx'", "wxyz, xyzw, matrix")
    ),
    Case("import-length-scale-negative", (*IMP, "dataset.length_scale=-1"), ("dataset.length_scale=-1", "positive")),
    Case("import-chunk-steps-zero", (*IMP, "dataset.chunk_steps=0"), ("dataset.chunk_steps=0", ">= 2")),
    Case("import-time-scale-zero", (*IMP, "dataset.time_scale=0"), ("dataset.time_scale=0", "positive")),
    Case(
        "import-csv-nan-cell", IMP, ("log.csv", "line 6", "'q0'", "not finite"), setup=_import_csv(_cell(5, 2, "nan"))
    ),
    Case(
        "import-csv-text-cell",
        IMP,
        ("log.csv", "line 6", "'q1'", "not a number"),
        setup=_import_csv(_cell(5, 3, "abc")),
    ),
    Case(
        "import-csv-zero-quaternion",
        IMP,
        ("log.csv", "quaternion norm 0", "not a unit quaternion"),
        setup=_import_csv(lambda ls: _cell(5, 2, "0")(_cell(5, 3, "0")(_cell(5, 4, "0")(_cell(5, 5, "0")(ls))))),
    ),
    Case("import-csv-time-backwards", IMP, ("log.csv", "not increasing at sample 5"), setup=_import_csv(_swap(5, 6))),
    Case(
        "import-csv-header-only",
        IMP,
        ("log.csv", "header line and at least 2 rows"),
        setup=_import_csv(lambda ls: ls[:1]),
    ),
    Case("import-csv-empty", IMP, ("log.csv", "found 0 line(s)"), setup=_import_csv(lambda ls: [])),
    Case(
        "import-csv-ragged",
        IMP,
        ("log.csv", "line 8 has 10 fields", "header has 9"),
        setup=_import_csv(lambda ls: [*ls[:7], ls[7] + ",1", *ls[8:]]),
    ),
    Case(
        "import-npz-no-quaternions",
        ("data", "dataset=import", "dataset.path=log.npz", "dataset.rotation=wxyz"),
        ("log.npz", "array 'q' is missing"),
        setup=_npz_without_q,
    ),
    Case(
        "rollout-split-unknown",
        ("rollout", "run={run}", "split=some"),
        ("split='some'", "auto, all, train, test"),
        setup=lambda c: c.run(),
    ),  # fmt: skip
    Case(
        "rollout-export-unknown",
        ("rollout", "run={run}", "export=xls"),
        ("export='xls'", "csv, npz"),
        setup=lambda c: c.run(),
    ),  # fmt: skip
    Case(
        "rollout-checkpoint-unknown",
        ("rollout", "run={run}", "checkpoint=middle"),
        ("checkpoint='middle'", "best, last"),
        setup=lambda c: c.run(),
    ),  # fmt: skip
    Case(
        "eval-rollout-not-hdf5",
        ("eval", "run={run}", "rollout=junk.h5"),
        ("junk.h5", "not an HDF5 file"),
        setup=lambda c: (c.run(), c.file("junk.h5", b"\x89 not hdf5 " * 20)),
    ),
    Case(
        "eval-rollout-missing",
        ("eval", "run={run}", "rollout=nothere.h5"),
        ("rollout=nothere.h5", "no such rollout file"),
        setup=lambda c: c.run(),
    ),  # fmt: skip
    Case("logger-unknown", (T, *FAST, "logger=wandb"), ("logger/wandb", "csv, tensorboard")),
    Case("logger-key-unknown", (T, *FAST, "+logger.flush_secs=3"), ("logger.flush_secs",)),
]


# ----------------------------------------------------------------------------- running
def _snapshot(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        out[rel] = "dir" if p.is_dir() else hashlib.sha1(p.read_bytes()).hexdigest()
    return out


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR")}
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg", COLUMNS="200")
    return env


def _in_process(args: list[str], capfd) -> tuple[int, str]:
    capfd.readouterr()
    code, extra = main_in_process(*args, cwd=Path.cwd())
    return code, capfd.readouterr().err + extra


def _subprocess(args: list[str], cwd: Path, python: str | None) -> tuple[int, str]:
    code = (
        python or ""
    ) + "\nimport sys\nfrom liedfl_cli.cli import main\nsys.argv = ['liedfl', *sys.argv[1:]]\nmain()\n"
    proc = subprocess.run(
        [sys.executable, "-c", code, *args],
        cwd=cwd,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=_default_signals,
    )
    return proc.returncode, proc.stderr


def _default_signals() -> None:
    """In the child before exec: SIGINT and SIGTERM at their defaults, as from a terminal. Under `nohup` or
    as a background job of a script the tests inherit SIGINT ignored, and liedfl (like Python) then keeps
    ignoring it (README, "Interruptions and resume"): the Ctrl-C cases need a process that takes it."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def _allowed(rel: str, patterns: tuple[str, ...]) -> bool:
    from fnmatch import fnmatch

    return any(fnmatch(rel, p) for p in patterns)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_hostile_input(case: Case, trained, pristine, tmp_path, monkeypatch, capfd):
    monkeypatch.delenv("LIEDFL_DATA_DIR", raising=False)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    ctx = Ctx(tmp_path, trained, pristine, monkeypatch)
    if case.setup:
        case.setup(ctx)
    before = _snapshot(tmp_path)
    args = [a.format(**ctx.vars) for a in case.args]
    if case.proc:
        code, err = _subprocess(args, tmp_path, case.python)
    else:
        monkeypatch.chdir(tmp_path)
        code, err = _in_process(args, capfd)

    assert "Traceback" not in err, err
    assert code == case.code, f"exit code {code}, expected {case.code}\n{err}"
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one line on stderr, got {len(lines)}:\n{err}"
    line = lines[0]
    assert line.startswith("error: "), line
    for needle in case.needles:
        n = needle.format(**ctx.vars)
        assert n in line, f"{n!r} not in {line!r}"

    after = _snapshot(tmp_path)
    changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
    unexpected = [k for k in changed if not (k not in before and _allowed(k, case.allowed))]
    assert not unexpected, f"files created, changed or removed: {unexpected}"
    assert not [k for k in after if ".tmp" in Path(k).name], "temporary files left behind"


def test_the_table_is_large_and_ids_are_unique():
    assert len(CASES) >= 200  # issue 18: at least 200 hostile cases
    assert len({c.id for c in CASES}) == len(CASES)
