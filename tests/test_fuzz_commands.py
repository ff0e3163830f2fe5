"""Mutated checkpoints through the commands and the API that read them: `liedfl rollout`, `liedfl
eval`, `liedfl train resume=` and `api.load_run`. tests/test_fuzz_loaders.py fuzzes the loader they
share; this checks the property where users meet it: exit 0, or a non-zero exit with one error line
(never a traceback, never a run folder left in a state the next command cannot read).

Mutations (tests/test_fuzz_loaders.py's payload mutations, plus truncation, a foreign file and
non-finite or reshaped weights) are drawn by hypothesis, derandomized. Fast tier: 3 files per
command; slow tier: 40 per command.
"""

from __future__ import annotations

import shutil
import uuid
from pathlib import Path

import numpy as np
import pytest
import torch
from fuzz_strategies import FAST, check_outcome
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_fuzz_loaders import _mutate_payload, payload_mutation

from helpers import SMOKE, main_in_process, train_run

COMMANDS = ("rollout", "eval", "resume", "api")
FAST_PER_COMMAND, SLOW_PER_COMMAND = 3, 40


def _weights(kind: str):
    """A mutation of every floating weight tensor: non-finite, reshaped, or another dtype."""

    def edit(payload: dict) -> dict:
        state = payload.get("model_state") or payload.get("state_dict") or {}
        for k, v in list(state.items()):
            if isinstance(v, torch.Tensor) and v.is_floating_point():
                if kind == "nan":
                    state[k] = torch.full_like(v, float("nan"))
                elif kind == "inf":
                    state[k] = v * float("inf")
                elif kind == "reshape":
                    state[k] = v.reshape(-1)[:-1] if v.numel() > 1 else v.reshape(1, 1)
                elif kind == "float32":
                    state[k] = v.float()
                break
        return payload

    return edit


whole_file = st.sampled_from(["truncated", "foreign", "empty", "nan", "inf", "reshape", "float32"])
case = st.one_of(
    st.tuples(st.just("payload"), st.lists(payload_mutation, min_size=1, max_size=2)),
    st.tuples(st.just("file"), whole_file),
)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("fuzz_commands")
    return train_run(root, *SMOKE)


def _broken_copy(run: Path, mutation) -> Path:
    copy = run.parent / f"case_{uuid.uuid4().hex[:8]}"
    shutil.copytree(run, copy)
    path = copy / "checkpoints" / "last.pt"
    (copy / "checkpoints" / "best.pt").unlink(missing_ok=True)
    kind, what = mutation
    if kind == "payload":
        payload = torch.load(path, weights_only=True)
        for m in what:
            payload = _mutate_payload(payload, m) if isinstance(payload, dict) else payload
        torch.save(payload, path)
    elif what == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 2])
    elif what == "foreign":
        np.save(path.with_suffix(".npy"), np.zeros(3))
        path.with_suffix(".npy").replace(path)
    elif what == "empty":
        path.write_bytes(b"")
    else:
        torch.save(_weights(what)(torch.load(path, weights_only=True)), path)
    return copy


def _command_property(trained: Path, command: str, mutation, capfd) -> int:
    """Run `command` on a broken copy of the run; return its exit code (api: 0 loaded, 2 refused)."""
    run = _broken_copy(trained, mutation)
    try:
        if command == "api":
            from liedfl_cli import api

            got = check_outcome(
                lambda: api.load_run(run, checkpoint="last"), run / "checkpoints" / "last.pt", (str(run),)
            )
            return 0 if got is not None else 2
        args = {"rollout": ("rollout", f"run={run}"), "eval": ("eval", f"run={run}"),
                "resume": ("train", f"resume={run}", "epochs=3")}[command]  # fmt: skip
        capfd.readouterr()
        code, tb = main_in_process(*args, "ui.progress=false", cwd=run.parent)
        _, err = capfd.readouterr()
        assert not tb and "Traceback" not in err, tb or err
        if code != 0:
            errors = [x for x in err.splitlines() if x.startswith("error:")]
            assert len(errors) == 1 and str(run) in errors[0], err
        return code
    finally:
        shutil.rmtree(run, ignore_errors=True)


SETTINGS = settings(FAST, suppress_health_check=[*FAST.suppress_health_check, HealthCheck.function_scoped_fixture])


@pytest.mark.parametrize("command", COMMANDS)
def test_fuzz_checkpoints_through_the_commands(trained, command, capfd):
    @settings(SETTINGS, max_examples=FAST_PER_COMMAND)
    @given(mutation=case)
    def run(mutation):
        _command_property(trained, command, mutation, capfd)

    run()


@pytest.mark.parametrize("what", ["truncated", "foreign", "nan", "reshape"])
def test_each_broken_file_through_rollout(trained, what, capfd):
    """The whole-file mutations each once (the sample above may miss one): each is refused."""
    assert _command_property(trained, "rollout", ("file", what), capfd) == 2


@pytest.mark.slow
@pytest.mark.parametrize("command", COMMANDS)
def test_fuzz_checkpoints_through_the_commands_slow(trained, command, capfd):
    count = [0]

    @settings(SETTINGS, max_examples=SLOW_PER_COMMAND)
    @given(mutation=case)
    def run(mutation):
        count[0] += 1
        _command_property(trained, command, mutation, capfd)

    run()
    assert count[0] >= SLOW_PER_COMMAND


# ----------------------------------------------------------------------------- config values that name paths
def _paths_cases(run: Path, tmp: Path) -> dict[str, tuple[tuple[str, ...], bool]]:
    """name -> (argv, works?): paths through symlinks work as their targets; a path that names the
    wrong kind of thing (a file for a folder, a folder for a file, a dangling link) is one line."""
    link = tmp / "link_to_run"
    link.symlink_to(run, target_is_directory=True)
    dangling = tmp / "dangling.h5"
    dangling.symlink_to(tmp / "nowhere.h5")
    a_file = tmp / "a_file"
    a_file.write_text("not a folder")
    data = next((run.parent / "data").glob("*.h5"))
    data_link = tmp / "data_link.h5"
    data_link.symlink_to(data)
    return {
        "rollout through a symlinked run": (("rollout", f"run={link}", "steps=3"), True),
        "eval through a symlinked run": (("eval", f"run={link}"), True),
        "rollout of a run that is a file": (("rollout", f"run={a_file}"), False),
        "eval of a rollout file of another kind": (("eval", f"run={run}", f"rollout={a_file}"), False),
        "dataset.path through a symlink": (
            ("data", "dataset=file", f"dataset.path={data_link}", f"paths.data_dir={tmp / 'cache'}"),
            True,
        ),  # fmt: skip
        "dataset.path a dangling symlink": (("data", "dataset=file", f"dataset.path={dangling}"), False),
        "dataset.path a folder": (("data", "dataset=file", f"dataset.path={tmp}"), False),
        "paths.data_dir a file": (("data", "dataset=heavy_so3", "budget=smoke", f"paths.data_dir={a_file}"), False),
        "resume of a run that is a file": (("train", f"resume={a_file}"), False),
    }


CASE_NAMES = [  # the keys of _paths_cases (built per test: the symlinks live in tmp_path)
    "rollout through a symlinked run", "eval through a symlinked run", "rollout of a run that is a file",
    "eval of a rollout file of another kind", "dataset.path through a symlink", "dataset.path a dangling symlink",
    "dataset.path a folder", "paths.data_dir a file", "resume of a run that is a file",
]  # fmt: skip


@pytest.mark.parametrize("name", CASE_NAMES)
def test_config_values_that_name_paths(trained, name, tmp_path, capfd):
    cases = _paths_cases(trained, tmp_path)
    assert list(cases) == CASE_NAMES
    argv, works = cases[name]
    capfd.readouterr()
    code, tb = main_in_process(*argv, "ui.progress=false", cwd=tmp_path)
    _, err = capfd.readouterr()
    assert not tb and "Traceback" not in err, tb or err
    if works:
        assert code == 0, err
    else:
        errors = [x for x in err.splitlines() if x.startswith("error:")]
        assert code == 2 and len(errors) == 1, err


ONE_STEP = "1 step per trajectory; a rollout needs at least 2 to compare with"


@pytest.mark.parametrize("steps", [None, "5"])
def test_a_one_step_file_in_rollout_names_the_file(trained, steps, tmp_path, capfd):
    """Round 3: `rollout steps=1: need at least 2` without the file, and with steps=5 a StopIteration
    traceback."""
    from liedfl_cli.data.hdf5 import load_dataset, save_dataset

    ds = load_dataset(next((trained.parent / "data").glob("*.h5")))
    ds.R, ds.p, ds.t = ds.R[:, :2], ds.p[:, :2], None
    path = save_dataset(ds, tmp_path / "one_step.h5")
    capfd.readouterr()
    args = ("rollout", f"run={trained}", "dataset=file", f"dataset.path={path}", f"paths.data_dir={tmp_path / 'c'}")
    code, tb = main_in_process(*args, *([f"steps={steps}"] if steps else []), cwd=tmp_path)
    _, err = capfd.readouterr()
    assert not tb and code == 2, tb or err
    assert err.strip().splitlines()[-1] == f"error: {path}: {ONE_STEP}", err


def test_a_checkpoint_config_without_its_rollout_section_is_one_line(trained, capfd):
    """The slow fuzz's find (one payload byte of the checkpoint changed so that its stored config has no
    rollout section): `liedfl rollout` refuses it in one line naming the run, no traceback."""
    assert _command_property(trained, "rollout", ("payload", [("set", 38, ":")]), capfd) == 2
