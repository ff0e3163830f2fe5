"""The closing summary of `liedfl train` (issue 38): the pure formatting of what was learned (beside
the truth), the validation and test figures against constant velocity / acceleration and the files;
then a single body and an articulated tree end to end."""

from __future__ import annotations

import pytest

from liedfl_cli.display import closing_summary as cs

TREE = {
    "kinetic": "articulated",
    "scaled": "true",
    "units": {"length": "mm"},
    "bodies": [
        {"name": "base", "joint": "free", "mass": 2.0, "com": [0.0, 0.1, 0.0], "inertia": [0.1, 0.2, 0.3]},
        {
            "name": "arm",
            "joint": "hinge",
            "parent": "base",
            "mass": 1.0,
            "com": [0.0, 0.0, 0.5],
            "inertia": [0.01, 0.02, 0.02],
            "damping": 0.05,
        },
    ],  # fmt: skip
    "true_bodies": [
        {"mass": 2.1, "com": [0.0, 0.1, 0.0], "inertia": [0.1, 0.2, 0.31]},
        {"mass": 0.9, "com": [0.0, 0.0, 0.5], "inertia": [0.01, 0.02, 0.02], "damping": 0.05},
    ],
    "gravity": {"g": 9810.0, "up": [0.0, 0.0, 1.0], "learned_up": False},
    "errors": {"J": 0.032, "m": 0.1},
}
VAL = {"epoch": 40, "val_one_step_error": 1.2e-4, "val_one_step_vs_cv": 0.31, "val_one_step_vs_ca": 1.2}
TEST = {"trajectories": 13, "steps": 99, "one_step_vs_cv": 0.02, "one_step_vs_ca": 0.05, "rollout_vs_cv": 0.1}


def test_a_tree_per_body_and_joint_beside_the_truth():
    lines = cs.closing_lines(TREE, VAL, TEST, "/runs/chain", ["summary.json", "recovery.json", "train.log"])
    text = "\n".join(lines)
    assert len(lines) <= 25
    assert "articulated model" in lines[1] and "[the truth the dataset declares]" in lines[1]
    assert "  base (free): m 2 kg [true 2.1]  com (0, 0.1, 0) mm [true (0, 0.1, 0)]" in text
    assert "  arm (hinge joint to base): m 1 kg [true 0.9]" in text and "damping 0.05 kg mm²/s [true 0.05]" in text
    assert "J 0.1 0.2 0.3 kg mm² [true 0.1 0.2 0.31]" in text
    assert "gravity 9.81e+03 mm/s² along -(0, 0, 1)" in text and "worst relative errors: J 3.2%, m 10.0%" in text
    assert "validation (epoch 40): one step 0.00012 = 0.31x CV, 1.2x CA" in text
    assert "test rollout (13 trajectories x 99 steps): one step 0.02x CV, 0.05x CA; rollout 0.1x CV" in text
    assert lines[-1] == "files in /runs/chain: recovery.json, summary.json, train.log"


def test_without_truth_or_physics():
    body = {"kinetic": "per_body", "bodies": [{"name": "body0", "inertia": [1.0, 2.0, 3.0]}], "true_bodies": None}
    lines = cs.physics_lines(body)
    assert "up to one overall factor" in lines[0] and "[" not in lines[1] and lines[1].endswith("J 1 2 3 kg m²")
    assert cs.physics_lines(None) == [] and cs.validation_lines(None, None) == []
    assert cs.closing_lines(None, None, None, "/r", []) == [
        cs.closing_lines(None, None, None, "/r", [])[0],
        "files in /r",
    ]


def test_a_big_tree_stays_compact():
    tree = {**TREE, "bodies": [dict(TREE["bodies"][1], name=f"b{i}") for i in range(30)], "true_bodies": None}
    lines = cs.closing_lines(tree, VAL, TEST, "/r", [])
    assert len(lines) <= 25 and "18 more bodies in recovery.json" in "\n".join(lines)


def test_selected_pass_and_test_figures():
    history = [{"epoch": 1, "val_one_step_error": 2.0}, {"epoch": 2, "val_one_step_error": None},
               {"epoch": 3, "val_one_step_error": 1.0}]  # fmt: skip
    assert cs.selected_pass(history, 1)["epoch"] == 1 and cs.selected_pass(history, None)["epoch"] == 3
    assert cs.selected_pass([], 1) is None
    model = {"model": "model", "one_step_rot_error_mean": 1.0, "geodesic_error_mean": 2.0, "rollout_trajectories": 2,
             "rollout_steps": 12, "newton_failures": 0, "one_step_vs_cv": 0.25, "rollout_vs_cv": 0.5}  # fmt: skip
    rows = [
        model,
        {"model": "constant_velocity", "one_step_rot_error_mean": 4.0, "geodesic_error_mean": 4.0},
        {"model": "constant_acceleration", "one_step_rot_error_mean": 2.0, "geodesic_error_mean": 8.0},
    ]
    t = cs.test_figures(rows)
    assert t is not None
    assert (t["one_step_vs_cv"], t["rollout_vs_cv"], t["one_step_vs_ca"], t["rollout_vs_ca"]) == (0.25, 0.5, 0.5, 0.25)
    assert cs.test_figures(None) is None


def test_test_figures_compare_only_the_same_samples():
    """A rollout cut at a Newton failure: constant velocity's ratio is the row's (over the valid samples),
    constant acceleration's is left out (its row covers every step); a rollout of 2 steps: constant
    acceleration predicts no sample of its own (its sample 2 is the data's), so no rollout ratio to it."""
    model = {"model": "model", "one_step_rot_error_mean": 1.0, "geodesic_error_mean": 2.0, "rollout_steps": 12,
             "newton_failures": 3, "one_step_vs_cv": 0.25, "rollout_vs_cv": 0.7}  # fmt: skip
    ca = {"model": "constant_acceleration", "one_step_rot_error_mean": 2.0, "geodesic_error_mean": 1e-17}
    cut = cs.test_figures([model, ca])
    assert (
        cut is not None and cut["rollout_vs_cv"] == 0.7 and "rollout_vs_ca" not in cut and "one_step_vs_ca" not in cut
    )
    short = cs.test_figures([{**model, "newton_failures": 0, "rollout_steps": 2}, ca])
    assert short is not None and "rollout_vs_ca" not in short and short["one_step_vs_ca"] == 0.5
    nan = cs.test_figures([{**model, "rollout_vs_cv": float("nan")}, ca])
    assert nan is not None and "rollout_vs_cv" not in nan


def test_a_single_body_run_ends_with_the_summary(tmp_path, run_main):
    proc = run_main(
        "train", "budget=smoke", "eval.plots=false", "ui.progress=false",
        f"paths.output_dir={tmp_path / 'run'}", f"paths.data_dir={tmp_path / 'data'}", cwd=tmp_path, ok=True,
    )  # fmt: skip
    tail = proc.stdout[proc.stdout.index("── summary") :]
    assert "learned physics (per-body model; overall scale matched to the truth" in tail
    assert "kg m² [true " in tail and "damping " in tail and "worst relative errors: J " in tail
    assert "x CV, " in tail and "x CA" in tail and "test rollout (2 trajectories x 12 steps)" in tail
    assert f"files in {tmp_path / 'run'}: checkpoints/best.pt" in tail and "recovery.json" in tail


def test_an_articulated_run_lists_bodies_and_joints(tmp_path, run_main):
    pytest.importorskip("mujoco")
    from liedfl_cli.data.hdf5 import save_dataset
    from liedfl_cli.data.mujoco_chain import chain_dataset

    save_dataset(chain_dataset(n_trajectories=10, steps=12, seed=3, links=3, h=0.05), tmp_path / "chain.h5")
    proc = run_main(
        "train", "dataset=file", f"dataset.path={tmp_path / 'chain.h5'}", "model.kinetic=articulated",
        "train.epochs=2", "ui.progress=false", "eval.plots=false", f"paths.output_dir={tmp_path / 'run'}",
        cwd=tmp_path, ok=True,
    )  # fmt: skip
    tail = proc.stdout[proc.stdout.index("── summary") :].splitlines()
    assert "articulated model" in tail[1], tail
    bodies = [x for x in tail if x.startswith("  ") and ": m " in x]
    assert len(bodies) == 3 and "(free)" in bodies[0] and "joint to " in bodies[1], tail
    assert all("[true " in x and " kg m² " in x for x in bodies)
    assert len(tail) <= 25


def test_a_start_that_stayed_the_best_says_the_epochs_added_nothing():
    history = [
        {"epoch": 0, "val_one_step_error": 1.0e-4},
        {"epoch": 500, "val_one_step_error": 1.1e-4},
        {"epoch": 1000, "val_one_step_error": 1.2e-4},
    ]
    notes = cs.start_notes(history, 0)
    assert len(notes) == 1 and "1000 epochs" in notes[0] and "train.epochs=0" in notes[0]
    assert cs.start_notes(history, 500) == []  # the epochs helped: no hint
    assert cs.start_notes(history[:1], 0) == []  # nothing after the start (train.epochs=0)
    lines = cs.closing_lines(None, history[0], None, "/runs/x", [], notes)
    assert notes[0] in lines


def test_the_start_selected_shows_its_own_figure_not_the_last_pass():
    """The start's validation pass (epoch 0) is not in the epochs' history: the summary takes its figure
    from summary.json's validation section instead of showing the last pass as if it were selected."""
    history = [{"epoch": 20, "val_one_step_error": 3.0e-5}, {"epoch": 40, "val_one_step_error": 1.5e-5}]
    validation = {"metric": "val_one_step_error", "best": 5.8e-6, "best_epoch": 0}
    row = cs.selected_pass(history, 0, validation)
    assert row == {"epoch": 0, "val_one_step_error": 5.8e-6}
    text = "\n".join(cs.validation_lines(row, None))
    assert "validation (epoch 0): one step 5.8e-06" in text
    assert cs.selected_pass(history, 40, validation)["val_one_step_error"] == 1.5e-5


def test_a_tree_with_invisible_combinations_says_so_beside_its_errors():
    lines = cs.physics_lines({**TREE, "gauge": {"invisible": 6, "parameters": 38}})
    text = "\n".join(lines)
    assert "determine 32 of the 38 parameter combinations" in text and "other 6" in text
    assert "determine" not in "\n".join(cs.physics_lines(TREE))  # none declared: no line
