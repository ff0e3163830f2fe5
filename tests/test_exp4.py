"""Exp 4 (mocap cartwheels): the experiment config, a smoke training run end to end with the mocap
table and plots (liedfl_cli/evaluation/mocap.py), and the mocap metrics against the recordings."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

import liedfl_cli  # noqa: F401  (registers the ${scaled:...} resolvers)
from helpers import compose_config

ROOT = Path(__file__).resolve().parents[1]
PLOTS = (
    "mocap_errors.png",
    "mocap_skeleton_seq1.png",
    "mocap_skeleton_seq2.png",
    "mocap_root_trajectory.png",
    "mocap_joint_axes_seq1.png",
    "mocap_joint_axes_seq2.png",
)


def _compose(overrides: list[str]):
    return compose_config("train", overrides)


def _figures_as_stubs(monkeypatch) -> None:
    """`write_outputs` writes each figure as a few bytes instead of rendering it: the tests below check
    which files the writer writes (names, tables' bytes), and the smoke run of the fixture already
    rendered every figure for real (`test_exp4_smoke_run_end_to_end` checks them). Rendering the
    figures again (3-D skeletons, ~5 s per test) checked nothing more."""
    from liedfl_cli.commands import outputs
    from liedfl_cli.display.plots import plt

    def stub(fig, path: Path, dpi: int = 120) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"figure")
        plt.close(fig)

    monkeypatch.setattr(outputs, "save_figure", stub)


def test_exp4_config_matches_the_paper(tmp_path):
    cfg = _compose(["experiment=exp4_mocap", f"paths.data_dir={tmp_path}/data", f"paths.output_dir={tmp_path}/run"])
    c = OmegaConf.to_container(cfg, resolve=True)
    assert c["dataset"]["name"] == "cmu_cartwheel" and c["dataset"]["split"] == "reproduce"
    assert list(c["force"]) == ["rayleigh", "rayleigh_nonlinear", "nn"]  # F = F_D + F_NL + F_NN
    assert c["force"]["rayleigh"]["coupling"] == c["force"]["rayleigh_nonlinear"]["coupling"] == "per_body"
    assert all((f["width"], f["depth"]) == (32, 3) for k, f in c["force"].items() if k != "rayleigh")
    assert c["train"]["epsilon"] == pytest.approx(math.log(1e5))  # the table's 100.000 as |det H| >= 1e5
    assert (c["model"]["potential"], c["model"]["mlp_width"], c["model"]["mlp_depth"]) == ("mlp", 32, 3)
    assert (c["train"]["batch_size"], c["train"]["epochs"], c["train"]["reg_points"]) == (63, 10000, 10)
    assert c["rollout"]["reference"] is False and c["rollout"]["steps"] == c["dataset"]["steps"] == 470
    assert (c["group"]["n_se3"], c["group"]["n_so3"]) == (1, 22)
    reduced = _compose(
        [
            "experiment=exp4_mocap",
            "budget=reduced",
            f"paths.data_dir={tmp_path}/data",
            f"paths.output_dir={tmp_path}/run",
        ]
    )
    assert reduced.train.epochs == 1000


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    from liedfl_cli.commands.train import run_train

    tmp = tmp_path_factory.mktemp("exp4")
    cfg = _compose(
        [
            "experiment=exp4_mocap",
            "budget=smoke",
            "ui.progress=false",
            "eval.plots=true",
            f"paths.data_dir={tmp}/data",
            f"paths.output_dir={tmp}/run",
        ]
    )
    summary = run_train(cfg)
    return cfg, summary, tmp / "run", tmp / "data"


def test_exp4_smoke_run_end_to_end(smoke_run):
    cfg, summary, run, _ = smoke_run
    # budget=smoke asks for 6 trajectories: the import caps at the 2 recordings (dataset.cap_trajectories)
    assert cfg.dataset.n_trajectories == 6 and cfg.dataset.cap_trajectories is True
    comps = json.loads((run / "components.json").read_text())["components"]
    assert any(c.startswith("F:rayleigh_nonlinear") for c in comps) and any(c.startswith("F:nn") for c in comps)
    assert any(c.startswith("V:MLP 32x3") for c in comps)
    assert "extra_eval" in summary and set(summary["rollout"]) == {"model"}  # no reference scheme
    for name in ("mocap_eval.csv", "mocap_eval.md", "mocap_eval.json"):
        assert (run / name).is_file(), name
    with open(run / "mocap_eval.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["row"].split(" (")[0] for r in rows] == [
        "Sequence 1",
        "Sequence 2",
        "Constant velocity, sequence 1",
        "Constant velocity, sequence 2",
        "Constant acceleration, sequence 1",
        "Constant acceleration, sequence 2",
        "Ground truth discrepancy",
    ]
    for r in rows:
        for k in ("root_rot", "joint_rot", "root_pos_asf", "root_pos_m"):
            assert math.isfinite(float(r[k])), (r["row"], k, r[k])
    assert [r["root_rot_paper"] for r in rows] == ["0.193", "0.188", "", "", "", "", "0.373"]
    from liedfl_cli.data.mocap import ASF_UNIT_M

    for r in rows:
        assert float(r["root_pos_m"]) == pytest.approx(float(r["root_pos_asf"]) * ASF_UNIT_M)
    md = (run / "mocap_eval.md").read_text()
    assert "ASF" in md and "Below the ground-truth discrepancy" in md and "Newton" in md
    ev = json.loads((run / "mocap_eval.json").read_text())
    assert ev["newton_failures"] == 0 and ev["nonfinite_trajectories"] == []
    # a 12-step smoke rollout (of a 12-step crop) does not cover the 470-step recording: no verdict
    assert ev["verdict_given"] is False
    assert ev["verdict"]["measured"]["given"] is False and ev["verdict"]["paper"]["given"] is False
    assert "no verdict (the rollout covers 12 steps, not the whole recording of 470)" in md
    assert len(ev["moving_joints"]) + len(ev["static_joints"]) == 22
    assert ev["one_step"]["solves"] == 2 * 11 and set(ev["below_discrepancy_until_s"]) == {"49_06", "49_07"}
    assert all(math.isfinite(v) for v in ev["one_step"]["model_joint_rot"].values())
    assert ev["one_step"]["from_rollout_file"] is True  # the model's one-step predictions stored at rollout time
    with h5py.File(run / "rollout.h5") as f:
        assert f["model/one_step/R"].shape == (2, 11, 23, 3, 3) and f["model/one_step/p"].shape == (2, 11, 1, 3)
    # the constant-velocity rollout of the mocap rows is the general evaluation's constant_velocity row
    with open(run / "eval.csv") as f:
        cv = next(r for r in csv.DictReader(f) if r["model"] == "constant_velocity")
    seq_cv = [r for r in rows if r["row"].startswith("Constant velocity")]
    # eval.csv averages samples 0..12 (0 and 1 exact), the mocap table the predicted samples 2..12
    mocap_mean = np.mean([float(r["root_pos_asf"]) for r in seq_cv]) * 11 / 13 / ev["asf_units_per_stored_unit"]
    assert float(cv["position_error_mean"]) == pytest.approx(mocap_mean, rel=1e-9) and mocap_mean > 0
    for name in PLOTS:
        path = run / "plots" / name
        assert path.is_file() and path.stat().st_size > 5000, name
    assert not list(run.glob(".*tmp*")) and not list((run / "plots").glob(".*tmp*"))


def test_evaluate_mocap_writes_nothing_and_returns_what_is_written(smoke_run, tmp_path, monkeypatch, capsys):
    """The mocap evaluation computes (summary, rows, markdown, figures, console table) and neither
    writes nor prints; the command's writer then writes exactly the files the run holds (same bytes
    for the tables) and `show` prints the table."""
    from liedfl_cli.commands.outputs import show, write_outputs
    from liedfl_cli.config.runs import load_run
    from liedfl_cli.config.typed import typed
    from liedfl_cli.evaluation.mocap import evaluate_mocap

    cfg, _, run, data = smoke_run
    _, model, dataset, _ = load_run(run, data)

    def tree(root):
        return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}

    before = tree(run)
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    out = evaluate_mocap(typed(cfg).scene_eval_options(), model, dataset, run)
    assert tree(run) == before and tree(tmp_path) == {}
    assert capsys.readouterr() == ("", "")
    show(out)
    assert "Exp 4 mocap reproduction" in capsys.readouterr().out
    _figures_as_stubs(monkeypatch)
    assert out.out_dir == run and set(out.files) == {"mocap_eval.json", "mocap_eval.csv", "mocap_eval.md"} | {
        f"plots/{n}" for n in PLOTS
    }
    assert out.table("mocap_eval.csv") is out.summary["rows"] and len(out.summary["rows"]) == 7
    written = write_outputs(out, tmp_path / "again")
    assert sorted(p.relative_to(tmp_path / "again").as_posix() for p in written) == sorted(out.files)
    for name in ("mocap_eval.json", "mocap_eval.csv", "mocap_eval.md"):
        assert (tmp_path / "again" / name).read_bytes() == (run / name).read_bytes(), name
    with open(tmp_path / "again" / "mocap_eval.csv") as f:
        assert [r["row"] for r in csv.DictReader(f)] == [r["row"] for r in out.summary["rows"]]


def test_compute_eval_writes_nothing_and_returns_what_is_written(smoke_run, tmp_path, monkeypatch, capsys):
    """The general evaluation of `liedfl eval` computes its rows, eval.md, figures and console notes
    without writing or printing; `run_eval_from_objects` prints and writes them (the run's eval.csv
    holds the same rows)."""
    from liedfl_cli.commands.evaluate import compute_eval
    from liedfl_cli.commands.outputs import write_outputs
    from liedfl_cli.config.runs import load_run
    from liedfl_cli.config.typed import typed

    cfg, _, run, data = smoke_run
    _, _, dataset, _ = load_run(run, data)
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*")}
    monkeypatch.chdir(tmp_path)
    capsys.readouterr()
    out = compute_eval(typed(cfg), dataset, run)
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*")} == before and not list(tmp_path.iterdir())
    assert capsys.readouterr() == ("", "")
    assert str(out.messages[0][0]).startswith("columns: rel err")
    assert out.summary["title"].startswith(f"{dataset.scene}: test rollout (")
    assert {"eval.csv", "eval.md", "eval_curves.json", "plots/error_vs_step.png"} <= set(out.files)
    rows = out.table("eval.csv")
    _figures_as_stubs(monkeypatch)
    assert rows is out.summary["rows"] and {r["model"] for r in rows} == {
        "model",
        "constant_velocity",
        "constant_acceleration",
        "constant_velocity_euclidean",
    }
    write_outputs(out, tmp_path / "again")
    with open(tmp_path / "again" / "eval.csv") as f, open(run / "eval.csv") as g:
        mine, theirs = list(csv.DictReader(f)), list(csv.DictReader(g))
    assert [r["model"] for r in mine] == [r["model"] for r in rows] == [r["model"] for r in theirs]
    for a, b in zip(mine, theirs):  # the run's own eval.csv has the train timings of the run, not given here
        assert a["geodesic_error_mean"] == b["geodesic_error_mean"]


def test_mocap_errors_truth_and_discrepancy(smoke_run):
    """Truth against itself is zero; recording 0 against recording 1 is `recording_discrepancy`."""
    from liedfl_cli.data.mocap import mocap_errors, moving_joints, recording_discrepancy
    from liedfl_cli.data.scenes import get_dataset
    from liedfl_cli.evaluation.mocap import discrepancy

    cfg, _, _, data_dir = smoke_run
    ds, _ = get_dataset(cfg.dataset, data_dir)
    assert ds.n_trajectories == 2 and ds.R.shape == (2, 13, 23, 3, 3)
    truth = ds.pose()
    e = mocap_errors(truth, truth)
    assert all(float(v.abs().max()) == 0.0 for v in e.values())
    e = mocap_errors(truth.index(0), truth.index(1), relative_position=True, joints=moving_joints(ds))
    d = recording_discrepancy(ds)
    for k in ("root_rot", "joint_rot", "root_pos"):
        assert float(e[k]) == pytest.approx(d[k], rel=1e-12)
        assert d[k] > 0
    ours = discrepancy(ds)
    for k in ("root_rot", "joint_rot", "root_pos"):
        assert ours[k] == d[k]
        np.testing.assert_allclose(ours[k + "_t"].mean(), d[k], rtol=1e-12)


def test_cap_trajectories_is_opt_in():
    from liedfl_cli.data.mocap import cmu_cartwheel
    from liedfl_cli.errors import ConfigError

    c = OmegaConf.to_container(OmegaConf.load(ROOT / "liedfl_cli" / "conf" / "dataset" / "cmu_cartwheel.yaml"))
    c.pop("defaults", None)
    c.update(steps=5, train_steps=5, rollout_steps=5, n_trajectories=6)
    with pytest.raises(ConfigError, match="must equal the number of dataset.files"):
        cmu_cartwheel(c)
    ds = cmu_cartwheel({**c, "cap_trajectories": True})
    assert ds.R.shape[:2] == (2, 6) and list(ds.test_idx) == [0, 1]
    one = cmu_cartwheel({**c, "cap_trajectories": True, "n_trajectories": 1})
    assert one.R.shape[:2] == (1, 6)
    torch.testing.assert_close(torch.as_tensor(one.R[0]), torch.as_tensor(ds.R[0]))
    with pytest.raises(ConfigError, match="leave no train or no test"):
        cmu_cartwheel({**c, "cap_trajectories": True, "split": "holdout", "n_test": 2})
