"""Checkpoints load with the safe unpickler (weights_only=True) and store plain types only; resume
payloads (optimizer, scheduler, RNG states, epoch) round-trip; a pickle payload runs nothing."""

from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import pytest
import torch

from liedfl_cli.errors import CheckpointError
from liedfl_cli.files.checkpoint import (
    capture_rng_state,
    load_checkpoint,
    load_state,
    restore_rng_state,
    save_checkpoint,
    to_plain,
)


def _model() -> torch.nn.Module:
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Tanh(), torch.nn.Linear(4, 2)).double()


def _train_a_bit(model, opt, sched, steps=3):
    for _ in range(steps):
        opt.zero_grad()
        model(torch.randn(5, 3, dtype=torch.float64)).pow(2).sum().backward()
        opt.step()
        if sched is not None:
            sched.step()


def _raw_load(path):
    return torch.load(path, map_location="cpu", weights_only=True)


def test_versions_are_plain_strings_and_the_payload_loads_with_weights_only(tmp_path):
    path = tmp_path / "last.pt"
    config = {"seed": 0, "train": {"epochs": 2, "optimizer": {"lr": 3e-3}}, "dataset": {"J": [1.0, 2.0]}}
    extra = {
        "dataset_path": Path("/data/x.h5"),  # a Path is stored as str
        "timings": {"train_seconds": np.float64(1.5), "epochs": np.int64(2), "parameters": 15},
        "components": ["kinetic", "rayleigh"],
    }
    save_checkpoint(path, _model(), config, extra)
    payload = _raw_load(path)  # plain torch, no allow-list: must not raise
    assert type(payload["versions"]["torch"]) is str
    assert payload["versions"]["torch"] == str(torch.__version__)
    assert payload["dataset_path"] == "/data/x.h5" and type(payload["dataset_path"]) is str
    assert payload["timings"] == {"train_seconds": 1.5, "epochs": 2, "parameters": 15}
    assert type(payload["timings"]["epochs"]) is int
    assert payload["config"] == config
    back = load_checkpoint(path)
    m = _model()
    with torch.no_grad():
        for p in m.parameters():
            p.zero_()
    load_state(path, m, back)
    for a, b in zip(m.state_dict().values(), _model().state_dict().values()):
        assert torch.equal(a, b)


@pytest.mark.parametrize("opt_name", ["adam", "soap"])
def test_resume_payload_round_trips_under_weights_only(tmp_path, opt_name):
    """Optimizer and scheduler state dicts, RNG states and the epoch come back equal."""
    model = _model()
    if opt_name == "adam":
        opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    else:
        from pytorch_optimizer import SOAP

        opt = SOAP(model.parameters(), lr=1e-2)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=10)
    _train_a_bit(model, opt, sched)
    gen = torch.Generator().manual_seed(7)
    torch.randperm(10, generator=gen)
    extra = {
        "optimizer": opt.state_dict(),
        "scheduler": sched.state_dict(),
        "rng": capture_rng_state({"train": gen}),
        "epoch": 3,
    }
    path = tmp_path / "last.pt"
    save_checkpoint(path, model, {"seed": 0}, extra)
    back = load_checkpoint(path)
    assert back["epoch"] == 3

    # the optimizer and scheduler states load into fresh objects and continue identically
    model2 = _model()
    model2.load_state_dict(model.state_dict())
    if opt_name == "adam":
        opt2 = torch.optim.Adam(model2.parameters(), lr=1e-2)
    else:
        from pytorch_optimizer import SOAP

        opt2 = SOAP(model2.parameters(), lr=1e-2)
    sched2 = torch.optim.lr_scheduler.CosineAnnealingLR(opt2, T_max=10)
    opt2.load_state_dict(back["optimizer"])
    sched2.load_state_dict(back["scheduler"])
    assert sched2.get_last_lr() == sched.get_last_lr()
    torch.manual_seed(123)
    _train_a_bit(model, opt, sched, 2)
    torch.manual_seed(123)
    _train_a_bit(model2, opt2, sched2, 2)
    for a, b in zip(model.state_dict().values(), model2.state_dict().values()):
        assert torch.equal(a, b)


def test_rng_state_capture_and_restore_reproduce_every_stream():
    gen = torch.Generator().manual_seed(3)
    torch.manual_seed(1)
    np.random.seed(2)  # noqa: NPY002 (the global legacy stream is what resume restores)
    random.seed(3)
    np.random.standard_normal()  # noqa: NPY002 (leaves a cached gaussian in the legacy state)
    random.gauss(0, 1)
    state = capture_rng_state({"train": gen})
    # the state is weights_only-safe as it is
    assert to_plain(state) is not None

    def draw():
        return (
            torch.rand(3).tolist(),
            np.random.standard_normal(3).tolist(),  # noqa: NPY002
            [random.random(), random.gauss(0, 1)],
            torch.randint(0, 100, (4,), generator=gen).tolist(),
        )

    first = draw()
    restore_rng_state(state, {"train": gen})
    assert draw() == first


def test_restore_rng_state_refuses_a_malformed_state():
    with pytest.raises(CheckpointError, match="'rng'"):
        restore_rng_state({"torch": torch.get_rng_state()})


def test_save_refuses_objects_the_safe_loader_would_refuse(tmp_path):
    class Opaque:
        pass

    path = tmp_path / "last.pt"
    with pytest.raises(CheckpointError, match=r"'timings\.when'.*Opaque"):
        save_checkpoint(path, _model(), {"seed": 0}, {"timings": {"when": Opaque()}})
    with pytest.raises(CheckpointError, match="overwrite"):
        save_checkpoint(path, _model(), {"seed": 0}, {"config": {}})
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary file


class _Payload:
    """Unpickling this runs a shell command (what a malicious last.pt would do)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def _malicious_checkpoint(path: Path, marker: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(
        {"state_dict": {}, "config": {"x": _Payload(marker)}, "versions": {"liedfl": "0.1.0"}},
        path,
    )


def test_load_checkpoint_refuses_a_pickle_payload(tmp_path):
    ckpt, marker = tmp_path / "last.pt", tmp_path / "PWNED"
    _malicious_checkpoint(ckpt, marker)
    with pytest.raises(CheckpointError, match=r"refused.*posix\.system|refused.*system"):
        load_checkpoint(ckpt)
    assert not marker.exists()


def test_eval_refuses_a_pickle_payload_and_runs_nothing(tmp_path, run_main):
    """`liedfl eval run=<dir>` on a run whose last.pt would run `touch`: one-line error, no marker.
    In this process (`run_main`); test_hostile.py's `ckpt-pickle-payload-cli` refuses one in a new
    `liedfl` process (no allow-list state left by other tests)."""
    run, marker = tmp_path / "run", tmp_path / "PWNED"
    ckpt = run / "checkpoints" / "last.pt"
    _malicious_checkpoint(ckpt, marker)
    proc = run_main("eval", f"run={run}", "eval.plots=false", cwd=tmp_path)
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    assert str(ckpt) in lines[0] and "refused" in lines[0]
    assert not marker.exists(), "the pickle payload ran"
    assert sorted(p.name for p in run.rglob("*")) == ["checkpoints", "last.pt"]
