"""docs/architecture.md, "Adding a model": one model file plus one config file, nothing else.

A toy model (a learned multiple of the last increment, `g_{k+1} = g_k exp(s log(g_{k-1}^-1 g_k))`)
is written into a temporary folder as `liedfl_cli.models.toy_velocity` (the only package whose
models configs may name) and its config into a temporary config folder added to Hydra's search
path; then `liedfl train`, `rollout` and `eval` run on it in-process, with no other file touched.
"""

from __future__ import annotations

import importlib.util
import sys

import pytest

MODEL_FILE = '''
import torch
from torch import nn

from liedfl_cli.models.base import ExplicitModel, config_options


class ToyVelocity(ExplicitModel):
    """g_{k+1} = g_k exp(s xi), xi = log(g_{k-1}^-1 g_k): constant velocity times a learned s."""

    window = "triplet"
    OPTIONS = ("init",)

    def __init__(self, G, h, init=0.5):
        super().__init__()
        self.G, self.h = G, h
        self.s = nn.Parameter(torch.tensor(float(init), dtype=torch.float64))

    @classmethod
    def from_config(cls, ctx, **options):
        return cls(ctx.group, ctx.h, **config_options(cls, options, cls.OPTIONS))

    def _next(self, prev, cur):
        xi = self.G.log(self.G.increment(prev, cur))
        return self.G.retract(cur, self.s * xi)

    def loss(self, batch, opts):
        prev, cur, nxt = batch.poses()
        err = self.G.log(self.G.increment(self._next(prev, cur), nxt))
        loss = (err**2).sum(-1).mean()
        return loss, {"toy_loss": loss.detach()}

    def initial_state(self, g0, g1):
        return (g0, g1)

    def state_pose(self, state):
        return state[0]

    def step(self, state, opts):
        prev, cur = state
        return (cur, self._next(prev, cur)), None

    def components(self):
        return [f"s ({float(self.s.detach()):.3f})"]
'''

CONFIG_FILE = """_target_: liedfl_cli.models.toy_velocity.ToyVelocity
name: toy_velocity
init: 0.5
"""


@pytest.fixture
def toy_model(tmp_path, monkeypatch):
    """The model file imported as liedfl_cli.models.toy_velocity, its config in <tmp>/conf/model/."""
    src = tmp_path / "toy_velocity.py"
    src.write_text(MODEL_FILE)
    spec = importlib.util.spec_from_file_location("liedfl_cli.models.toy_velocity", src)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "liedfl_cli.models.toy_velocity", module)
    spec.loader.exec_module(module)
    conf = tmp_path / "conf" / "model"
    conf.mkdir(parents=True)
    (conf / "toy_velocity.yaml").write_text(CONFIG_FILE)
    return tmp_path / "conf"


def test_one_model_file_and_one_config_file_train_roll_out_and_evaluate(toy_model, tmp_path, run_main):
    import csv
    import json

    run = tmp_path / "run"
    common = ["ui.progress=false", "runtime.threads=1", f"hydra.searchpath=[file://{toy_model}]"]
    run_main(
        "train",
        "model=toy_velocity",
        "budget=smoke",
        "train.epochs=30",
        "eval.plots=false",
        f"paths.data_dir={tmp_path / 'data'}",
        f"hydra.run.dir={run}",
        *common,
        cwd=tmp_path,
        ok=True,
    )
    components = json.loads((run / "components.json").read_text())
    assert any(c.startswith("s (") for c in components["components"]), components
    rows = list(csv.DictReader((run / "train_metrics.csv").open()))
    assert rows and "toy_loss" in rows[0]
    # trained: the learned multiple of the last increment moved from 0.5 towards constant velocity's 1
    from liedfl_cli import api

    s = float(api.load_run(run).model.s)
    assert 0.55 < s < 1.5, s
    run_main("rollout", f"run={run}", "steps=6", "eval.plots=false", *common, cwd=tmp_path, ok=True)
    assert len(list((run / "rollouts").glob("*/rollout.h5"))) == 1
    run_main("eval", f"run={run}", "eval.plots=false", *common, cwd=tmp_path, ok=True)
    table = list(csv.DictReader((run / "eval.csv").open()))
    assert {r["name"] for r in table} >= {"toy_velocity", "constant velocity"}, table
