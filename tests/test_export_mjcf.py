"""`liedfl export format=mjcf` and its writer `liedfl_cli/files/mjcf.py` (docs/export.md).

(a) A MuJoCo chain's declared physics written by `mjcf_text` and stepped by MuJoCo reproduces the
chain's own simulation (ball and hinge joints, free and pinned roots, gravity) to 1e-6 rad;
(b) universal and weld joints: MuJoCo composes two hinges as R_rel = exp(t1 a1) exp(t2 a2), keeps
a1^T R_rel a2 and a weld's R_rel constant; (c) end to end: a tiny articulated run exported, loaded
by MuJoCo, total mass 1 kg or dataset.total_mass; (d) one-line errors.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")

from liedfl_cli.data.hdf5 import save_dataset  # noqa: E402
from liedfl_cli.data.mujoco_chain import chain_dataset  # noqa: E402
from liedfl_cli.errors import ConfigError  # noqa: E402
from liedfl_cli.files.mjcf import (  # noqa: E402
    MjcfSpec,
    ball_damping_dropped,
    depth_first,
    load_model,
    mjcf_text,
    replay,
    spec_from_physics,
)
from liedfl_cli.lie import so3  # noqa: E402
from liedfl_cli.lie.tree import Tree  # noqa: E402

ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def _tree(ds):
    """The dataset's tree with its declared joints (from params["physics"] when the tree has none)."""
    physics = ds.params["physics"]
    if ds.tree.joints is not None:
        return ds.tree
    axes = physics.get("hinge_axes") or [None] * ds.tree.n_bodies
    return ds.tree.with_joints(physics["joints"], [[a or [0, 0, 0], [0, 0, 0]] for a in axes])


def _angle(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """The largest rotation angle between corresponding attitudes."""
    rel = torch.from_numpy(np.einsum("...ji,...jk->...ik", Ra, Rb))
    return float(so3.log(rel).norm(dim=-1).max())


# ----------------------------------------------------------------------------- (a) declared physics
@pytest.mark.parametrize("joint", ["ball", "hinge"])
@pytest.mark.parametrize("root", ["free", "pinned"])
def test_declared_physics_replays_the_chain(joint, root):
    ds = chain_dataset(
        links=3, joint=joint, root=root, gravity=9.81, n_trajectories=3, steps=50, h=0.02, speed=2.0, seed=1
    )
    tree = _tree(ds)
    xml = mjcf_text(spec_from_physics(tree, ds.params["physics"], ds.body_names))
    model = load_model(xml)
    assert model.nbody == tree.n_bodies + 1 and np.allclose(model.opt.gravity, [0, 0, -9.81])
    R, p = replay(xml, tree, ds.extras["qpos"][0, 0], ds.extras["qvel"][0, 0], ds.h, 50)
    assert R.shape == (51, tree.n_bodies, 3, 3)
    assert _angle(ds.extras["body_R_world"][0], R) < 1e-6
    assert np.abs(p - ds.extras["body_p_world"][0]).max() < 1e-6


def test_the_bodies_are_listed_depth_first():
    assert depth_first([-1, 0, 0, 1]) == [0, 1, 3, 2]
    tree = Tree.from_lists([-1, 0, 0, 1], np.eye(4, 3) * 0.3, free_root=False)
    spec = _spec(tree)
    model = load_model(mjcf_text(spec))
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, i) for i in range(1, 5)]
    assert names == ["b0", "b1", "b3", "b2"]


# ----------------------------------------------------------------------------- (b) universal, weld
def _spec(tree: Tree, damping: float = 0.02) -> MjcfSpec:
    B = tree.n_bodies
    dof = {"free": 6, "ball": 3, "universal": 2, "hinge": 1, "weld": 0}
    rng = np.random.default_rng(0)
    inertia = []
    for _ in range(B):
        Q = so3.exp(torch.from_numpy(rng.standard_normal(3))).numpy()
        inertia.append(Q @ np.diag(rng.uniform(0.02, 0.04, 3)) @ Q.T)
    return MjcfSpec(
        names=[f"b{b}" for b in range(B)],
        parents=list(tree.parents),
        offsets=np.asarray(tree.offsets),
        joints=list(tree.joint_kinds),
        axes=np.asarray(tree.axes_array()),
        mass=rng.uniform(1, 2, B),
        com=rng.uniform(-0.1, 0.1, (B, 3)),
        inertia=np.asarray(inertia),
        dof_damping=[[damping] * dof[k] for k in tree.joint_kinds],
        gravity=np.array([0.0, 0.0, -9.81]),
        timestep=1e-3,
    )


def test_universal_and_weld_joints():
    a1 = np.array([0.0, 0.6, 0.8])
    a2 = np.array([1.0, 0.0, 0.0])
    z = [0.0, 0.0, 0.0]
    tree = Tree.from_lists(
        [-1, 0, 1, 2],
        [[0, 0, 0], [0.3, 0, 0], [0.3, 0.1, 0], [0, 0.3, 0]],
        free_root=True,
        joints=["free", "universal", "weld", "ball"],
        axes=[[z, z], [a1, a2], [z, z], [z, z]],
    )
    xml = mjcf_text(_spec(tree))
    model = load_model(xml)
    assert model.njnt == 4 and model.nv == 6 + 2 + 3
    data = mujoco.MjData(model)
    # the composition: R_rel = exp(t1 a1) exp(t2 a2) (qpos: free 7, universal 2, ball 4)
    data.qpos[:7] = [0.1, 0.2, 0.3, 1, 0, 0, 0]
    data.qpos[7:9] = [0.7, -0.4]
    data.qpos[9:] = [1, 0, 0, 0]
    mujoco.mj_forward(model, data)
    ids = [b + 1 for b in range(4)]  # a serial chain: depth-first = index order
    Rw = data.xmat[ids].reshape(4, 3, 3)
    expect = so3.exp(torch.tensor(0.7 * a1)).numpy() @ so3.exp(torch.tensor(-0.4 * a2)).numpy()
    assert np.abs(Rw[0].T @ Rw[1] - expect).max() < 1e-12
    # stepping: a1^T R_rel a2 and the weld's R_rel stay constant
    rng = np.random.default_rng(1)
    data.qvel[:] = rng.standard_normal(model.nv)
    R, _ = replay(xml, tree, data.qpos.copy(), data.qvel.copy(), 0.01, 100)
    rel1 = np.einsum("kji,kjl->kil", R[:, 0], R[:, 1])
    assert np.abs(a1 @ rel1 @ a2 - a1 @ a2).max() < 1e-9
    assert np.abs(np.abs(rel1 - np.eye(3)).max()) > 0.05  # it moved
    weld = np.einsum("kji,kjl->kil", R[:, 1], R[:, 2])
    assert np.abs(weld - np.eye(3)).max() < 1e-9


def test_a_bad_body_is_refused_by_name():
    tree = Tree.from_lists([-1, 0], [[0, 0, 0], [0.3, 0, 0]], free_root=False)
    spec = _spec(tree)
    spec.mass[1] = 0.0
    with pytest.raises(ConfigError, match="body 'b1': mass"):
        mjcf_text(spec)
    spec = _spec(tree)
    spec.inertia[0] = np.diag([1.0, 1.0, 3.0])
    with pytest.raises(ConfigError, match="body 'b0'.*triangle"):
        mjcf_text(spec)
    spec = _spec(tree)
    spec.inertia[1] = np.diag([1.0, -1.0, 1.0])
    with pytest.raises(ConfigError, match="body 'b1'.*positive definite"):
        mjcf_text(spec)
    assert ball_damping_dropped([1.0, 1.0, 1.0]) == 0.0
    assert ball_damping_dropped([0.0, 0.0, 3.0]) == pytest.approx(4 / 3)


# ----------------------------------------------------------------------------- (c) end to end
def _liedfl(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "liedfl_cli", *args], cwd=cwd, env=ENV, capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope="module")
def hinge_run(tmp_path_factory) -> Path:
    tmp = tmp_path_factory.mktemp("export")
    ds = chain_dataset(
        links=2, joint="hinge", root="pinned", gravity=0.0, n_trajectories=3, steps=30, h=0.02, speed=2.0, seed=0
    )
    save_dataset(ds, tmp / "chain.h5")
    r = _liedfl(
        "train",
        "dataset=file",
        "dataset.path=chain.h5",
        "model.kinetic=articulated",
        "train.epochs=3",
        "eval.plots=false",
        "rollout.enabled=false",
        "paths.data_dir=data",
        "hydra.run.dir=run",
        cwd=tmp,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    return tmp


@pytest.mark.parametrize("mass", [None, 2.5])
def test_export_end_to_end(hinge_run, mass):
    out = f"model_{mass}.xml"
    extra = [] if mass is None else [f"dataset.total_mass={mass}"]
    r = _liedfl("export", "run=run", "format=mjcf", f"out={out}", "paths.data_dir=data", *extra, cwd=hinge_run)
    assert r.returncode == 0, r.stderr[-2000:]
    text = (hinge_run / out).read_text()
    model = mujoco.MjModel.from_xml_string(text)
    total = 1.0 if mass is None else mass
    assert model.body_mass[1:].sum() == pytest.approx(total, rel=1e-9)
    assert model.njnt == 2 and list(model.jnt_type) == [mujoco.mjtJoint.mjJNT_HINGE] * 2
    assert np.allclose(model.opt.gravity, 0) and model.opt.timestep == pytest.approx(0.02 / 20)
    assert (model.dof_damping > 0).all()
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, i) for i in (1, 2)]
    assert names == ["link0", "link1"]
    source = "not set" if mass is None else "from the command line"
    assert source in text and source in r.stdout
    assert not list(hinge_run.glob(f"{out}.tmp*"))  # written to a temporary file, then renamed


# ----------------------------------------------------------------------------- (d) one-line errors
def test_a_missing_run_is_one_line(tmp_path):
    r = _liedfl("export", "run=nowhere", "out=m.xml", cwd=tmp_path)
    assert r.returncode != 0 and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "run=nowhere" in lines[0], r.stderr
    assert not (tmp_path / "m.xml").exists()


def test_a_per_body_run_is_refused_in_one_line(tmp_path):
    r = _liedfl(
        "train",
        "dataset=heavy_so3",
        "budget=smoke",
        "train.epochs=1",
        "eval.plots=false",
        "rollout.enabled=false",
        "paths.data_dir=data",
        "hydra.run.dir=run",
        cwd=tmp_path,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    r = _liedfl("export", "run=run", "out=m.xml", "paths.data_dir=data", cwd=tmp_path)
    assert r.returncode != 0 and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "needs an articulated model (model.kinetic=articulated)" in lines[0], r.stderr
    assert not (tmp_path / "m.xml").exists()


def test_the_export_config_composes_and_passes_the_schema():
    from helpers import compose_config
    from liedfl_cli.cli import COMMANDS
    from liedfl_cli.config.schema import validate

    assert "export" in COMMANDS
    cfg = compose_config("export", ["run=x", "dataset.total_mass=2.5"])
    validate(cfg)
    assert cfg.task_name == "export" and cfg.dataset.total_mass == 2.5 and cfg.format == "mjcf"


def test_a_ball_model_with_gravity_in_process():
    """model_spec of an untrained articulated model: inertia J = tr(J_d) I - J_d about the COM, the
    total mass, -g u as gravity, one damping per ball joint (the mean, with a warning)."""
    from liedfl_cli.commands.export_model import model_spec
    from liedfl_cli.models.articulated import ArticulatedLieDFLNN

    tree = Tree.from_lists([-1, 0, 1], [[0, 0, 0], [0.3, 0, 0], [0.25, 0.05, 0]], free_root=True)
    model = ArticulatedLieDFLNN(tree, 0.02, potential=("uniform_gravity",), forces=("rayleigh",))
    assert model.dof_damper is not None
    d = torch.zeros(tree.n_dof, dtype=torch.float64)
    d[6:9] = torch.tensor([0.01, 0.02, 0.03])
    d[9:12] = 0.05
    model.dof_damper.set_coefficients(d)
    spec, notes, scale = model_spec(model, ["root", "upper", "lower"], 2.0)
    assert spec.mass.sum() == pytest.approx(2.0) and scale == pytest.approx(2.0 / float(model.mass().detach().sum()))
    assert np.allclose(spec.inertia, scale * model.inertia.J().detach().numpy())
    assert np.allclose(spec.gravity, [0, 0, -9.81])
    assert len([n for n in notes if "ball joint" in n]) == 1 and "'upper'" in notes[0]
    model_mj = load_model(mjcf_text(spec))
    assert list(model_mj.jnt_type) == [mujoco.mjtJoint.mjJNT_FREE] + [mujoco.mjtJoint.mjJNT_BALL] * 2
    assert np.allclose(model_mj.dof_damping, [0] * 6 + [scale * 0.02] * 3 + [scale * 0.05] * 3)
    assert model_mj.opt.timestep == pytest.approx(0.001)
