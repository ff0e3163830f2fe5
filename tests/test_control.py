"""Learned control (Exp 5): C with unit-norm columns, the true PD force, known (frozen) Lagrangian
parts, the pd_control scene, the torque evaluation and an end-to-end smoke run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from liedfl_cli.commands.outputs import run_scene_eval, show, write_outputs
from liedfl_cli.commands.train import count_parameters
from liedfl_cli.data import generate
from liedfl_cli.data.scenes_multibody import pd_torque
from liedfl_cli.evaluation import EvalOutputs, SceneEvalOptions
from liedfl_cli.evaluation.control import evaluate_control, force_torques, plot_torque, torque_errors
from liedfl_cli.lie import SO3, Pose, ProductGroup, so3
from liedfl_cli.mechanics.forces import ControlForce
from liedfl_cli.models.liedflnn.model import LieDFLNN
from liedfl_cli.models.true_scheme import physics_model, true_model

ROOT = Path(__file__).resolve().parents[1]


def pd_config(**over) -> dict:
    c = OmegaConf.to_container(OmegaConf.load(ROOT / "liedfl_cli" / "conf" / "dataset" / "pd_control.yaml"))
    c.pop("defaults", None)
    c.update(n_trajectories=2, steps=40, train_steps=40, rollout_steps=40, n_test=1)
    c.update(over)
    return c


@pytest.fixture(scope="module")
def pd_data():
    return generate(pd_config())


@pytest.mark.parametrize("G,n_inputs", [(ProductGroup(0, 1), 3), (ProductGroup(1, 2), 4), (ProductGroup(0, 1), 5)])
def test_control_matrix_has_unit_norm_columns(G, n_inputs):
    f = ControlForce(G, n_inputs=n_inputs, width=8, depth=1)
    opt = torch.optim.Adam(f.parameters(), lr=0.5)
    g = Pose(so3.random((7, G.n_bodies)), torch.randn(7, G.n_se3, 3, dtype=torch.float64))
    xi = torch.randn(7, G.dim, dtype=torch.float64)
    for _ in range(3):
        with torch.no_grad():
            f.C_raw.mul_(torch.rand_like(f.C_raw) * 5 + 0.1)
        C = f.C()
        assert C.shape == (3 * G.n_bodies, n_inputs)
        torch.testing.assert_close(torch.linalg.vector_norm(C, dim=0), torch.ones(n_inputs, dtype=torch.float64))
        opt.zero_grad()
        f(g, xi).square().sum().backward()
        opt.step()
    out = f(g, xi)
    _, v = G.split(out)
    assert (v == 0).all()  # no control force on translations


def test_pd_control_scene(pd_data):
    ds = pd_data
    assert ds.body_kinds == ["so3"] and ds.R.shape == (2, 41, 1, 3, 3)
    np.testing.assert_array_equal(ds.R[0], ds.R[1])  # perturb = 0: the test trajectory copies the training one
    assert set(ds.split["train"]) | set(ds.split["test"]) == {0, 1}
    ctrl = ds.params["physics"]["control"]
    J_bar = (1.521 + 1.362 + 1.211) / 9
    assert ctrl["K_R"] == pytest.approx(5 * J_bar) and ctrl["K_w"] == pytest.approx(J_bar)
    assert ctrl["feedforward"] is False
    # D = 0: the non-conservative torque is the PD torque
    np.testing.assert_allclose(ds.extras["tau_ext"], ds.extras["tau_control"], atol=1e-15)
    # the PD law written out by hand at one sample
    R, w = ds.R[0, 7, 0], ds.extras["omega"][0, 7, 0]
    Rf = so3.exp(torch.tensor(ctrl["R_f"], dtype=torch.float64)).numpy()
    E = Rf.T @ R - R.T @ Rf
    e_R = 0.5 * np.array([E[2, 1], E[0, 2], E[1, 0]])
    np.testing.assert_allclose(ds.extras["tau_control"][0, 7, 0], -ctrl["K_R"] * e_R - ctrl["K_w"] * w, atol=1e-13)


def test_feedforward_cancels_gravity():
    ph = {"J": [1.521, 1.362, 1.211], "m": 0.5, "rho": [0.0, 0.5, 1.0], "g": 9.81}
    ctrl = {"R_f": [0.0, 0.0, 0.0], "K_R": 0.0, "K_w": 0.0, "feedforward": True}
    R = so3.random((5,)).numpy()
    tau = pd_torque(R, np.zeros((5, 3)), ctrl, ph["m"], ph["rho"], ph["g"])
    from liedfl_cli.data.physics import RigidBodySO3

    np.testing.assert_allclose(
        tau, -RigidBodySO3(J=ph["J"], m=0.5, rho=ph["rho"], g=9.81).gravity_torque(R), atol=1e-14
    )


def test_true_pd_force_matches_the_scene(pd_data):
    """The true-parameter scheme carries the PD law as a force; at the true velocity it is the
    scene's torque, and the scheme's residual on the data is small (O(h^3))."""
    ds = pd_data
    ref = true_model(ds)
    names = [f.name for f in ref.forces]
    assert names == ["pd_control"] and ref.potential is not None
    R = torch.from_numpy(ds.R[0, :, :])
    w = torch.from_numpy(ds.extras["omega"][0])
    tau = ref.forces[0](Pose(R, torch.zeros(41, 0, 3, dtype=torch.float64)), w.reshape(41, 3))
    np.testing.assert_allclose(tau.numpy(), ds.extras["tau_control"][0, :, 0], atol=1e-13)
    traj = ds.pose([0])
    args = (
        traj.index((slice(None), slice(0, -2))),
        traj.index((slice(None), slice(1, -1))),
        traj.index((slice(None), slice(2, None))),
    )
    r = ref.residual(*args)
    ctrl = ref.forces.pop(0)
    r_uncontrolled = ref.residual(*args)
    ref.forces.append(ctrl)
    assert r.abs().max() < 0.05 * r_uncontrolled.abs().max()


def test_known_lagrangian_is_true_and_frozen(pd_data):
    ds = pd_data
    ph = ds.params["physics"]
    model = LieDFLNN(
        SO3,
        ds.h,
        potential="none",
        forces={"control": {"width": 16, "depth": 2}},
        known=["inertia", "potential"],
        physics=ph,
    )
    ref = true_model(ds)
    torch.testing.assert_close(model.inertia.Jd(), ref.inertia.Jd())
    assert not any(p.requires_grad for p in model.inertia.parameters())
    assert count_parameters(model) == sum(p.numel() for p in model.forces.parameters())
    comps = model.components()
    assert comps[0] == "J_d (known, frozen)" and comps[1] == "V:gravity (known, frozen)"
    assert comps[2].startswith("F:control")
    # with the PD law in place of the learned control the model is the true-parameter scheme
    model.forces[0] = ref.forces[0]
    traj = ds.pose([0])
    args = (
        traj.index((slice(None), slice(0, -2))),
        traj.index((slice(None), slice(1, -1))),
        traj.index((slice(None), slice(2, None))),
    )
    torch.testing.assert_close(model.residual(*args), ref.residual(*args), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="known"):
        LieDFLNN(SO3, ds.h, forces=[], known=["inertia"], physics=None)
    with pytest.raises(ValueError, match="unknown part"):
        LieDFLNN(SO3, ds.h, forces=[], known=["mass"], physics=ph)


def test_torque_evaluation_of_the_true_law(pd_data, tmp_path):
    """The true law at the velocity estimate w~ differs from the true torque only by O(h)."""
    ds = pd_data
    ref = true_model(ds)
    learned = force_torques(ref, ds.pose([0]), ds.h)
    assert learned.shape == (1, 40, 1, 3)
    err = torque_errors(learned, ds.extras["tau_ext"][[0], :40])
    assert err["rel_error_mean"] < 0.05 and err["rel_error_max"] < 0.2
    assert torque_errors(learned, learned)["rel_error_max"] == 0.0
    path = tmp_path / "plots" / "torque.png"
    fig = plot_torque(
        {"learned": learned[0], "true": ds.extras["tau_ext"][0, :40], "rel_error": err["curve"]},
        ds.h,
        {"truth": ds.R[0], "model": ds.R[0], "_index": 0},
        "test",
    )
    assert not path.parent.exists()  # drawn, not written: the command's writer saves it
    write_outputs(EvalOutputs({}, tmp_path, {"plots/torque.png": fig}))
    assert path.is_file() and path.stat().st_size > 1000
    assert not list(path.parent.glob(".*tmp*"))


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


def test_evaluate_control_writes_nothing_and_returns_what_is_written(pd_data, tmp_path, monkeypatch, capsys):
    """The evaluation computes (summary, rows, figure, console lines) and neither writes nor prints; only
    `commands.outputs.write_outputs` writes and `commands.outputs.show` prints."""
    ds = pd_data
    cwd, run = tmp_path / "cwd", tmp_path / "run"
    cwd.mkdir(), run.mkdir()
    monkeypatch.chdir(cwd)
    capsys.readouterr()
    out = evaluate_control(SceneEvalOptions(plots=True), true_model(ds), ds, run)
    assert _tree(cwd) == {} and _tree(run) == {}
    assert capsys.readouterr() == ("", "")
    assert out is not None
    show(out)
    printed = capsys.readouterr().out
    assert [x.split(":")[0] for x in printed.splitlines()] == [f"control recovery ({s})" for s in ("train", "test")]
    assert out is not None and out.out_dir == run
    assert set(out.files) == {"control_eval.json", "control_eval.md", "plots/torque.png"}
    rows = out.summary["rows"]
    assert [r["split"] for r in rows] == ["train", "test"] and out.files["control_eval.json"] is out.summary
    written = write_outputs(out)
    assert sorted(p.relative_to(run).as_posix() for p in written) == sorted(out.files)
    assert json.loads((run / "control_eval.json").read_text())["rows"] == json.loads(json.dumps(rows))
    md = (run / "control_eval.md").read_text()
    assert all(f"| {r['split']} |" in md for r in rows)
    assert (run / "plots" / "torque.png").stat().st_size > 1000 and _tree(cwd) == {}


def test_control_eval_of_a_model_without_forces_is_skipped_saying_so_in_the_command(
    pd_data, tmp_path, monkeypatch, capsys
):
    ds = pd_data
    monkeypatch.chdir(tmp_path)
    opts = SceneEvalOptions(plots=True)
    model = LieDFLNN(ds.group, ds.h, forces=[])
    capsys.readouterr()
    out = evaluate_control(opts, model, ds, tmp_path / "run")
    assert capsys.readouterr() == ("", "") and not list(tmp_path.iterdir())
    assert out is not None and out.summary == {} and out.files == {}
    assert run_scene_eval(opts, model, ds, tmp_path / "run") is None  # the command: shown, nothing written
    assert capsys.readouterr().out.startswith("control eval skipped: the model has no force components")
    assert not list(tmp_path.iterdir())


def test_exp5_smoke_run_end_to_end(tmp_path):
    from liedfl_cli.commands.train import run_train

    with initialize_config_dir(config_dir=str(ROOT / "liedfl_cli" / "conf"), version_base="1.3"):
        cfg = compose(
            config_name="train",
            overrides=[
                "experiment=exp5_control",
                "budget=smoke",
                f"paths.data_dir={tmp_path}",
                f"paths.output_dir={tmp_path}/run",
                "ui.progress=false",
                "eval.plots=false",
            ],
        )
    assert cfg.train.w_reg == 0 and cfg.train.w_del == 1 and list(cfg.model.known) == ["inertia", "potential"]
    summary = run_train(cfg)
    run = tmp_path / "run"
    comps = json.loads((run / "components.json").read_text())
    assert comps["components"][:2] == ["J_d (known, frozen)", "V:gravity (known, frozen)"]
    assert comps["parameters"] == 9356  # C (3x3) + u: MLP 64x3 from (R, w~) in R^12 to R^3
    ce = json.loads((run / "control_eval.json").read_text())
    assert {r["split"] for r in ce["rows"]} == {"train", "test"}
    assert all(np.isfinite(r["rel_error_mean"]) for r in ce["rows"])
    assert (run / "control_eval.md").is_file() and "extra_eval" in summary
    assert summary["rollout"]["model"]["n_failed"] == 0
    # the frozen known parts are saved and restored with the checkpoint
    from liedfl_cli.config.runs import load_run

    _, model, _, _ = load_run(run, tmp_path)
    torch.testing.assert_close(model.inertia.Jd(), physics_model(SO3, 0.05, model_physics(cfg, tmp_path)).inertia.Jd())


def model_physics(cfg, data_dir):
    from liedfl_cli.data.scenes import get_dataset

    return get_dataset(cfg.dataset, data_dir)[0].params["physics"]
