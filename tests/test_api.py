"""The Python API (`liedfl_cli.api`): input checks, poses of every group, predict / rollout / parameters on
a trained run, and the code of docs/api.md run as written."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from own_data import write_csv

from liedfl_cli import api
from liedfl_cli.errors import InputError
from liedfl_cli.lie import ProductGroup

DOC = Path(__file__).resolve().parents[1] / "docs" / "api.md"


def _rotations(shape, seed=0) -> np.ndarray:
    from liedfl_cli.lie import so3

    g = torch.Generator().manual_seed(seed)
    return so3.random(shape, generator=g).numpy()


# ----------------------------------------------------------------------------- groups and poses
@pytest.mark.parametrize(
    "spec,expected",
    [
        ("SO(3)", (0, 1)),
        ("se3", (1, 0)),
        ("SE(3) x SO(3)^22", (1, 22)),
        ("SE(3)^2 x SO(3)", (2, 1)),
        ((1, 3), (1, 3)),
        (ProductGroup(2, 0), (2, 0)),
    ],
)
def test_group_from_names_and_pairs(spec, expected):
    G = api.group(spec)
    assert (G.n_se3, G.n_so3) == expected


def test_group_rejects_nonsense():
    for bad in ("SU(2)", "", (0, 0), 3):
        with pytest.raises(InputError, match="group="):
            api.group(bad)


@pytest.mark.parametrize("group", ["SO(3)", "SE(3)", "SO(3)^3", "SE(3) x SO(3)^2"])
def test_make_pose_for_every_kind_of_group(group):
    G = api.group(group)
    B, m = G.n_bodies, G.n_se3
    R = _rotations((5, B))
    p = np.random.default_rng(0).normal(size=(5, m, 3)) if m else None
    g = api.make_pose(G, R=R, p=p)
    assert g.R.shape == (5, B, 3, 3) and g.p.shape == (5, m, 3) and g.R.dtype == torch.float64
    q = api.rotations_to_quaternions(R, scalar_first=True)
    gq = api.make_pose(G, quaternions=q, scalar_first=True, p=p)
    assert torch.allclose(gq.R, g.R, atol=1e-12)
    q_last = api.rotations_to_quaternions(R, scalar_first=False)
    assert np.allclose(q_last[..., 3], q[..., 0])
    assert torch.allclose(api.make_pose(G, quaternions=q_last, scalar_first=False, p=p).R, g.R, atol=1e-12)


def test_one_bare_pose_of_a_one_body_group():
    R = _rotations(())
    g = api.make_pose("SE(3)", R=R, p=[1.0, 2.0, 3.0])
    assert g.R.shape == (1, 3, 3) and g.p.shape == (1, 3)
    g = api.make_pose("SO(3)", quaternions=[1.0, 0.0, 0.0, 0.0], scalar_first=True)
    assert g.R.shape == (1, 3, 3) and g.p.shape == (0, 3) and torch.allclose(g.R[0], torch.eye(3, dtype=torch.float64))


def test_float32_is_converted_and_projected():
    R = _rotations((4, 1)).astype(np.float32)
    g = api.make_pose("SO(3)", R=R)
    assert g.R.dtype == torch.float64
    err = (g.R.transpose(-1, -2) @ g.R - torch.eye(3, dtype=torch.float64)).abs().max()
    assert err < 1e-14
    g = api.make_pose("SO(3)", R=torch.from_numpy(R))  # torch tensors too
    assert g.R.dtype == torch.float64


@pytest.mark.parametrize(
    "kwargs,message",
    [
        ({"group": "SE(3)", "R": np.eye(3)[None, None]}, r"p: SE\(3\) needs the positions of its 1 SE\(3\) body"),
        ({"group": "SO(3)", "R": np.eye(3)[None, None], "p": np.zeros((1, 1, 3))}, r"p: SO\(3\) has no positions"),
        ({"group": "SE(3)", "R": np.eye(3)[None, None], "p": np.zeros((2, 3))}, r"p: shape \(2, 3\); need \(1, 1, 3\)"),
        ({"group": "SO(3)^2", "R": np.eye(3)}, r"R: shape \(3, 3\); need \(\.\.\., 2, 3, 3\) for SO\(3\)\^2"),
        ({"group": "SO(3)", "R": 2 * np.eye(3)}, r"R: not a rotation matrix at index \(\): .*det R = 8"),
        ({"group": "SO(3)", "R": np.full((3, 3), np.nan)}, r"R: non-finite value at index \(0, 0\)"),
        ({"group": "SO(3)", "R": np.eye(3).astype(np.float16)}, r"R: dtype float16 has too few digits"),
        ({"group": "SO(3)", "R": np.eye(3).astype(complex)}, r"R: dtype complex128 is not supported"),
        ({"group": "SO(3)", "R": [["a"] * 3] * 3}, r"R: dtype <U1 is not supported"),
        ({"group": "SO(3)", "quaternions": [1.0, 0, 0, 0]}, r"quaternions need scalar_first=True"),
        ({"group": "SO(3)", "quaternions": [2.0, 0, 0, 0], "scalar_first": True}, r"quaternions: norm 2 at index"),
        ({"group": "SO(3)", "quaternions": [1.0, 0, 0], "scalar_first": True}, r"quaternions: shape \(3,\); need"),
        ({"group": "SO(3)"}, r"give the rotations either as R="),
    ],
)
def test_bad_inputs_are_one_clear_line(kwargs, message):
    kwargs = dict(kwargs)
    group = kwargs.pop("group")
    with pytest.raises(InputError, match=message) as e:
        api.make_pose(group, **kwargs)
    assert "\n" not in str(e.value) and isinstance(e.value, ValueError)


# ----------------------------------------------------------------------------- a trained run
@pytest.fixture(scope="module")
def run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api")
    return api.train(
        "budget=smoke", "dataset=heavy_se3", "eval.plots=false", output_dir=tmp / "run", data_dir=tmp / "data"
    )


def test_train_and_load(run):
    assert run.name == "liedflnn" and run.group.name == "SE(3)" and run.h == 0.05
    again = api.load_run(run.run_dir)
    assert again.name == run.name and (run.run_dir / "train_metrics.csv").is_file()
    assert "SE(3)" in repr(again)


def test_predict_and_rollout_match_the_models_own_rollout(run):
    R, p = run.trajectory(0)
    g0, g1 = api.make_pose(run.group, R[0], p[0]), api.make_pose(run.group, R[1], p[1])
    traj = api.rollout(run, g0, g1, 6)
    assert traj.R.shape == (7, 1, 3, 3) and traj.p.shape == (7, 1, 3) and traj.converged.shape == (5,)
    assert np.allclose(traj.t, 0.05 * np.arange(7))
    np.testing.assert_array_equal(traj.R[:2], R[:2])
    nxt = api.predict(run, g0, g1)
    assert np.allclose(nxt.R.numpy(), traj.R[2]) and np.allclose(nxt.p.numpy(), traj.p[2])
    ref = run.model.rollout(
        api.make_pose(run.group, R[None, 0], p[None, 0]), api.make_pose(run.group, R[None, 1], p[None, 1]), 6
    )
    assert np.allclose(ref.pose.R[0].numpy(), traj.R)
    # a batch of starts, and (R, p) pairs instead of poses
    idx = run.dataset.test_idx
    Rt, pt = run.dataset.R[idx], run.dataset.p[idx]
    batch = api.rollout(run, (Rt[:, 0], pt[:, 0]), (Rt[:, 1], pt[:, 1]), 4, solver={"tol": 1e-8, "max_iter": 20})
    assert batch.R.shape == (len(idx), 5, 1, 3, 3)


def test_rollout_input_errors(run):
    R, p = run.trajectory(0)
    g0 = api.make_pose(run.group, R[0], p[0])
    with pytest.raises(InputError, match=r"steps=1: must be an integer >= 2"):
        api.rollout(run, g0, g0, 1)
    with pytest.raises(InputError, match=r"g1: p: SE\(3\) needs the positions"):
        api.rollout(run, g0, (R[1], None), 3)
    with pytest.raises(InputError, match=r"g0 and g1 differ in shape"):
        api.rollout(run, g0, api.make_pose(run.group, R[None, 1], p[None, 1]), 3)
    with pytest.raises(InputError, match=r"R: shape \(1, 3, 3\); need \(\.\.\., 2, 3, 3\) for SE\(3\) x SO\(3\)"):
        api.make_pose("SE(3) x SO(3)", R=R[0], p=p[0])
    with pytest.raises(InputError, match="expected a Run"):
        api.rollout("not a run", g0, g0, 3)
    with pytest.raises(InputError, match="solver"):
        api.rollout(run, g0, g0, 3, solver=5)
    with pytest.raises(InputError, match=r"solver\.method='broyden': choose one of newton, chord"):
        api.rollout(run, g0, g0, 3, solver={"method": "broyden"})
    chord = api.rollout(run, g0, api.make_pose(run.group, R[1], p[1]), 4, solver={"method": "chord", "tol": 1e-10})
    newton = api.rollout(run, g0, api.make_pose(run.group, R[1], p[1]), 4, solver={"tol": 1e-10})
    assert np.abs(chord.R - newton.R).max() < 1e-8 and chord.converged.all()


def test_parameters(run):
    params = api.parameters(run)
    assert params["J_d"].shape == (1, 3, 3) and params["m"].shape == (1,) and params["rho_COM"].shape == (1, 3)
    assert params["D"].shape == (6, 6) and np.allclose(params["D"], params["D"].T)
    assert all(isinstance(v, np.ndarray) for v in params["weights"].values())
    assert set(params["weights"]) == set(run.model.state_dict())


# ----------------------------------------------------------------------------- docs/api.md
def test_the_documented_example_runs(tmp_path, monkeypatch):
    """Every ```python block of docs/api.md, in order, in one namespace, in a folder holding log.csv."""
    blocks = re.findall(r"```python\n(.*?)```", DOC.read_text(), flags=re.S)
    assert len(blocks) >= 2
    write_csv(tmp_path / "log.csv", n_traj=4, rotation="xyzw")
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MPLBACKEND", "Agg")
    monkeypatch.delenv("LIEDFL_DATA_DIR", raising=False)
    namespace: dict = {"__name__": "__main__"}
    for code in blocks:
        exec(compile(code, str(DOC), "exec"), namespace)  # (our own documentation)
    assert (tmp_path / "rollout_error.png").stat().st_size > 1000
    assert namespace["traj"].R.shape[0] == namespace["steps"] + 1
    assert os.path.isdir(namespace["run_dir"])


def test_so3_poses_from_torch_tensors_and_their_own_pose():
    """An SO(3) pose given as torch tensors (R, and the empty p of a Pose) is accepted (issue 21, item 1:
    np.size of a torch tensor is a method, so the empty positions were taken for real ones)."""
    from liedfl_cli import api
    from liedfl_cli.lie import SO3, so3

    R = so3.exp(torch.tensor([[0.1, 0.2, 0.3]], dtype=torch.float64))
    g = api.make_pose(SO3, R=R[0])
    assert g.R.shape == (1, 3, 3) and g.p.shape == (0, 3)
    again = api._pose(g, SO3, "g0")  # a Pose whose p is an empty torch tensor
    torch.testing.assert_close(again.R, g.R)
    with pytest.raises(api.InputError, match="no positions"):
        api.make_pose(SO3, R=R[0], p=torch.zeros(1, 3, dtype=torch.float64))
