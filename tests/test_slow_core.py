"""Slow tier: the issue's full-budget runs (minutes each). Run with `pytest -m slow`."""

import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from liedfl_cli.commands.train import run_train

CONF = str(Path(__file__).resolve().parents[1] / "liedfl_cli" / "conf")
pytestmark = pytest.mark.slow


def _run(tmp_path, overrides):
    with initialize_config_dir(config_dir=CONF, version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[
                *overrides,
                "ui.progress=false",
                f"paths.data_dir={tmp_path}/data",
                f"paths.output_dir={tmp_path}/run",
            ],
        )
    return run_train(cfg)


def _rows(summary):
    return {r["model"]: r for r in summary["eval"]}


def test_free_rigid_body_default_run_recovers_parameters(tmp_path):
    s = _run(tmp_path, [])
    rows = _rows(s)
    rec = json.loads((tmp_path / "run" / "recovery.json").read_text())
    assert rec["Jd_over_trace_max_rel_error"] < 5e-3
    assert rec["D_over_trace_max_rel_error"] < 5e-2
    assert rows["model"]["newton_failures"] == 0
    assert rows["model"]["max_orth_drift"] < 1e-12
    assert rows["model"]["rel_rot_error_mean"] < 1.25 * rows["true_scheme"]["rel_rot_error_mean"]


def test_heavy_se3_run_stays_on_group(tmp_path):
    s = _run(tmp_path, ["dataset=heavy_se3", "model.mlp_width=32", "train.epochs=300"])
    rows = _rows(s)
    assert rows["model"]["newton_failures"] == 0
    assert rows["model"]["max_orth_drift"] < 1e-12 and rows["model"]["max_det_drift"] < 1e-12
    assert rows["model"]["rel_rot_error_mean"] < 0.5
