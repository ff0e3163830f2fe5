"""Every experiment composed with every combination of the values it sweeps (`hydra.sweeper.params`),
at `budget=smoke` and at the default budget: the schema accepts each job's config and it types, so a
sweep cannot fail on a config error in job 17 after 16 jobs ran. (Running every experiment end to end
at a tiny budget: tests/test_configs.py and tests/test_exp4.py.)"""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import yaml

import liedfl_cli
from helpers import compose_config
from liedfl_cli.config.schema import validate
from liedfl_cli.config.typed import typed

CONF = Path(liedfl_cli.__file__).parent / "conf" / "experiment"
EXPERIMENTS = sorted(p.stem for p in CONF.glob("*.yaml"))


def _jobs(experiment: str) -> list[tuple[str, ...]]:
    with open(CONF / f"{experiment}.yaml") as f:
        params = ((yaml.safe_load(f).get("hydra") or {}).get("sweeper") or {}).get("params") or {}
    axes = [[f"{key}={v.strip()}" for v in str(values).split(",")] for key, values in params.items()]
    return [tuple(job) for job in itertools.product(*axes)]


def test_the_sweeps_are_found():
    assert {"exp1_euler_vs_lie", "exp2_discrete_vs_continuous", "exp3_manifold", "exp4_mocap"} <= set(EXPERIMENTS)
    assert len(_jobs("exp2_discrete_vs_continuous")) == 16 and len(_jobs("exp1_euler_vs_lie")) == 6


@pytest.mark.parametrize("budget", ["smoke", "default"])
@pytest.mark.parametrize("experiment", EXPERIMENTS)
def test_every_job_of_every_sweep_composes_and_types(experiment, budget, tmp_path):
    jobs = _jobs(experiment) or [()]
    for job in jobs:
        cfg = compose_config(
            "train",
            (f"experiment={experiment}", f"budget={budget}", *job, f"paths.output_dir={tmp_path}/run",
             f"paths.data_dir={tmp_path}/data"),
        )  # fmt: skip
        validate(cfg, "train")
        run = typed(cfg, "train")
        assert run.dataset is not None and run.train is not None, (experiment, job)
        for override in job:  # the swept value reached the job's config
            key, value = override.split("=", 1)
            if key == "baseline":
                continue  # a config group: its files set model/baseline sections
            got = cfg
            for part in key.split("."):
                got = got[part]
            assert str(got) == value or float(got) == float(value), (experiment, override, got)
