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


# ----------------------------------------------------------------------------- a family with a fast engine
FAMILY_INIT = """from .model import ToyFamily

__all__ = ["ToyFamily"]
"""

FAMILY_MODEL = '''
import torch
from torch import nn

from liedfl_cli.models.base import ExplicitModel, config_options

from .engines import fast


class ToyFamily(ExplicitModel):
    """g_{k+1} = g_k exp(s xi), xi = log(g_{k-1}^-1 g_k) (the toy above), its loss computed by the
    family's own fast engine on the fused path and by the group's generic maps on the reference one."""

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
        if self.path == "fused" and fast.applies(self):
            loss = fast.loss(self.G, self.s, prev, cur, nxt)
        else:
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

FAMILY_ENGINE = '''
"""The toy family's fast loss: the same numbers as `model.py`'s reference loss, by SO(3) closed forms."""
import torch

from liedfl_cli.lie import so3

CALLS = [0]


def applies(model) -> bool:
    return model.G.n_se3 == 0


def loss(G, s, prev, cur, nxt):
    CALLS[0] += 1
    xi = so3.log(prev.R.transpose(-1, -2) @ cur.R)  # (N, B, 3)
    pred = cur.R @ so3.exp(s * xi)
    err = so3.log(pred.transpose(-1, -2) @ nxt.R)
    return (err**2).sum((-1, -2)).mean()
'''

FAMILY_CONFIG = """_target_: liedfl_cli.models.toy_family.ToyFamily
name: toy_family
init: 0.5
"""


@pytest.fixture
def toy_family(tmp_path, monkeypatch):
    """The family package written outside the source tree and imported as liedfl_cli.models.toy_family."""
    pkg = tmp_path / "toy_family"
    (pkg / "engines").mkdir(parents=True)
    (pkg / "__init__.py").write_text(FAMILY_INIT)
    (pkg / "model.py").write_text(FAMILY_MODEL)
    (pkg / "engines" / "__init__.py").write_text("")
    (pkg / "engines" / "fast.py").write_text(FAMILY_ENGINE)
    import liedfl_cli.models

    monkeypatch.setattr(liedfl_cli.models, "__path__", [*liedfl_cli.models.__path__, str(tmp_path)])
    for name in [n for n in sys.modules if n.startswith("liedfl_cli.models.toy_family")]:
        monkeypatch.delitem(sys.modules, name)
    conf = tmp_path / "conf" / "model"
    conf.mkdir(parents=True)
    (conf / "toy_family.yaml").write_text(FAMILY_CONFIG)
    yield tmp_path / "conf"
    for name in [n for n in sys.modules if n.startswith("liedfl_cli.models.toy_family")]:
        del sys.modules[name]


def test_a_model_family_with_a_fast_engine_is_its_package_plus_one_config(toy_family, tmp_path, run_main):
    """The package (model.py, engines/fast.py) and one config file, from outside the source tree: `liedfl
    train` runs it on the plan the command builds (`runtime.fused`): its engine serves the fused run only,
    and both paths end with the same weight."""
    from liedfl_cli import api

    common = ["ui.progress=false", "runtime.threads=1", f"hydra.searchpath=[file://{toy_family}]"]
    learned = {}
    for fused in ("true", "false"):
        import liedfl_cli.models.toy_family.engines.fast as fast

        before = fast.CALLS[0]
        run = tmp_path / f"run_{fused}"
        run_main(
            "train",
            "model=toy_family",
            "budget=smoke",
            "train.epochs=20",
            "eval.plots=false",
            "rollout.enabled=false",
            f"runtime.fused={fused}",
            f"paths.data_dir={tmp_path / 'data'}",
            f"hydra.run.dir={run}",
            *common,
            cwd=tmp_path,
            ok=True,
        )
        calls = fast.CALLS[0] - before
        assert (calls > 0) == (fused == "true"), (fused, calls)
        learned[fused] = float(api.load_run(run).model.s)
    assert 0.55 < learned["true"] < 1.5, learned
    assert abs(learned["true"] - learned["false"]) <= 1e-9 * abs(learned["false"]), learned
