"""`liedfl export format=mjcf` and its writer `liedfl_cli/files/mjcf.py` (docs/export.md).

(a) A MuJoCo chain's declared physics written by `mjcf_text` compiles to the chain's own model (masses,
inertias, centres of mass, joints, axes, damping to 1e-9) and, stepped by MuJoCo from the recorded state,
reproduces the chain's simulation (ball, hinge, universal, weld joints, free and pinned roots, gravity) to
1e-6 rad, < 0.1 x constant velocity's error; from the poses alone (`initial_state_from_poses`) too;
(b) universal and weld joints: MuJoCo composes two hinges as R_rel = exp(t1 a1) exp(t2 a2), keeps
a1^T R_rel a2 and a weld's R_rel constant; (c) end to end: a tiny articulated run exported, loaded
by MuJoCo, total mass 1 kg or dataset.total_mass; (d) one-line errors.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco")

from helpers import main_in_process  # noqa: E402
from liedfl_cli.data.hdf5 import save_dataset  # noqa: E402
from liedfl_cli.data.mujoco_chain import chain_dataset  # noqa: E402
from liedfl_cli.errors import ConfigError  # noqa: E402
from liedfl_cli.files.mjcf import (  # noqa: E402
    MjcfSpec,
    ball_damping_dropped,
    depth_first,
    initial_state_from_poses,
    load_model,
    mjcf_text,
    replay,
    spec_from_physics,
    write_mjcf,
)
from liedfl_cli.lie import so3  # noqa: E402
from liedfl_cli.lie.tree import Tree  # noqa: E402


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
SCENES = {
    "ball-free": dict(links=3, joint="ball", root="free"),
    "ball-pinned": dict(links=3, joint="ball", root="pinned"),
    "hinge-free": dict(links=3, joint="hinge", root="free"),
    "hinge-pinned": dict(links=3, joint="hinge", root="pinned"),
    "branched-universal-weld": dict(parents="branched5", joints=["free", "universal", "weld", "hinge", "ball"]),
}


def _full_inertia(model, b: int) -> np.ndarray:
    """Body b's inertia about its COM in the body frame, (3, 3), from MuJoCo's principal form."""
    Q = np.zeros(9)
    mujoco.mju_quat2Mat(Q, model.body_iquat[b])
    Q = Q.reshape(3, 3)
    return Q @ np.diag(model.body_inertia[b]) @ Q.T


def _assert_same_model(src, ours, names) -> None:
    """The compiled MJCFs agree body by body (matched by name) to 1e-9."""
    assert ours.nbody == src.nbody and ours.njnt == src.njnt and ours.nq == src.nq and ours.nv == src.nv
    assert np.allclose(ours.opt.gravity, src.opt.gravity, atol=1e-12) and ours.opt.timestep == src.opt.timestep
    for name in names:
        a = mujoco.mj_name2id(src, mujoco.mjtObj.mjOBJ_BODY, name)
        b = mujoco.mj_name2id(ours, mujoco.mjtObj.mjOBJ_BODY, name)
        assert a >= 1 and b >= 1, name
        assert abs(src.body_mass[a] - ours.body_mass[b]) < 1e-9, name
        assert np.abs(src.body_ipos[a] - ours.body_ipos[b]).max() < 1e-9, name
        assert np.abs(_full_inertia(src, a) - _full_inertia(ours, b)).max() < 1e-9, name
        assert np.abs(src.body_pos[a] - ours.body_pos[b]).max() < 1e-9, name
        assert np.abs(src.body_quat[a] - ours.body_quat[b]).max() < 1e-12, name
        ja = [j for j in range(src.njnt) if src.jnt_bodyid[j] == a]
        jb = [j for j in range(ours.njnt) if ours.jnt_bodyid[j] == b]
        assert [int(src.jnt_type[j]) for j in ja] == [int(ours.jnt_type[j]) for j in jb], name
        for j, k in zip(ja, jb):
            assert np.abs(src.jnt_axis[j] - ours.jnt_axis[k]).max() < 1e-9, name
            da, db = src.jnt_dofadr[j], ours.jnt_dofadr[k]
            n = {0: 6, 1: 3}.get(int(src.jnt_type[j]), 1)
            if int(src.jnt_type[j]) != 0:  # (a free joint's damping is not written)
                assert np.abs(src.dof_damping[da : da + n] - ours.dof_damping[db : db + n]).max() < 1e-9, name


def _mean_errors(ds, tree, i: int, R_world: np.ndarray, k0: int = 0) -> tuple[float, float]:
    """(mean geodesic error of R_world (S+1, B, 3, 3) against the recorded world attitudes from
    sample k0, that of constant velocity from the true samples k0, k0 + 1), over S+1 samples, rad."""
    from liedfl_cli.evaluation.metrics import geodesic_error
    from liedfl_cli.lie import Pose
    from liedfl_cli.lie.tree import forward_kinematics
    from liedfl_cli.solvers.one_step import constant_velocity_rollout

    S = R_world.shape[0] - 1
    true_R = torch.as_tensor(ds.extras["body_R_world"][i, k0 : k0 + S + 1])
    err = float(geodesic_error(torch.as_tensor(R_world), true_R).mean())
    truth = ds.pose([i])
    cv = constant_velocity_rollout(ds.group, truth.index((slice(0, 1), k0)), truth.index((slice(0, 1), k0 + 1)), S)
    cv_world = forward_kinematics(tree, Pose(cv.R[0], cv.p[0]))
    return err, float(geodesic_error(cv_world.R, true_R).mean())


@pytest.mark.parametrize("scene", list(SCENES))
def test_declared_physics_replays_the_chain(scene):
    ds = chain_dataset(gravity=9.81, n_trajectories=4, steps=60, h=0.02, speed=2.0, seed=1, **SCENES[scene])
    tree = _tree(ds)
    xml = mjcf_text(spec_from_physics(tree, ds.params["physics"], ds.body_names))
    model = load_model(xml)
    assert model.nbody == tree.n_bodies + 1 and np.allclose(model.opt.gravity, [0, 0, -9.81])
    _assert_same_model(mujoco.MjModel.from_xml_string(ds.params["mjcf"]), model, ds.body_names)
    i = int(ds.test_idx[0])
    R, p = replay(xml, tree, ds.extras["qpos"][i, 0], ds.extras["qvel"][i, 0], ds.h, 50)
    assert R.shape == (51, tree.n_bodies, 3, 3)
    assert _angle(ds.extras["body_R_world"][i, :51], R) < 1e-6
    assert np.abs(p - ds.extras["body_p_world"][i, :51]).max() < 1e-6
    err, cv = _mean_errors(ds, tree, i, R)
    assert err < 0.1 * cv and err < 1e-8
    # without the engine's state: (qpos, qvel) at sample 1 from the poses 0, 1, 2 (second order)
    qpos, qvel, k0 = initial_state_from_poses(tree, ds.R[i], ds.p[i], ds.h)
    assert k0 == 1 and qpos.shape == (model.nq,) and qvel.shape == (model.nv,)
    R1, _ = replay(xml, tree, qpos, qvel, ds.h, 50)
    assert _angle(ds.extras["body_R_world"][i, 1], R1[:1]) < 1e-9  # the poses are the configuration
    err_poses, cv1 = _mean_errors(ds, tree, i, R1, k0=1)
    assert err_poses < 0.1 * cv1
    print(f"\n{scene}: replay {err:.3g} rad, from poses {err_poses:.3g} rad, constant velocity {cv:.3g} rad")


def test_initial_state_orders():
    """Central differences (sample 1) are second order, forward ones (sample 0) first order: halving h
    divides the velocity error by about 4 and 2."""
    errors: dict[str, list[float]] = {"central": [], "forward": []}
    for h in (0.02, 0.01):
        ds = chain_dataset(
            links=2, joint="ball", root="free", gravity=9.81, n_trajectories=2, steps=4, h=h, speed=2.0, seed=3
        )
        for method in errors:
            qpos, qvel, k0 = initial_state_from_poses(ds.tree, ds.R[0], ds.p[0], h, method=method)
            assert np.abs(qpos[:3] - ds.extras["qpos"][0, k0, :3]).max() < 1e-12
            errors[method].append(float(np.abs(qvel - ds.extras["qvel"][0, k0]).max()))
    assert 3.0 < errors["central"][0] / errors["central"][1] < 5.0
    assert 1.6 < errors["forward"][0] / errors["forward"][1] < 2.4
    assert errors["central"][0] < 0.1 * errors["forward"][0]


def test_initial_state_refuses_a_hinge_off_its_axis():
    tree = Tree.from_lists(
        [-1, 0],
        [[0, 0, 0], [0.3, 0, 0]],
        free_root=False,
        joints=["ball", "hinge"],
        axes=[[[0] * 3] * 2] + [[[0, 0, 1], [0, 0, 0]]],
    )
    R = np.tile(np.eye(3), (3, 2, 1, 1))
    R[:, 1] = so3.exp(torch.tensor([0.3, 0.0, 0.0])).numpy()  # about x, not the hinge's z
    with pytest.raises(ConfigError, match="body 1: its hinge rotation is 0.3 rad off"):
        initial_state_from_poses(tree, R, np.zeros((3, 0, 3)), 0.01)
    with pytest.raises(ConfigError, match="T >= 3"):
        initial_state_from_poses(tree, R[:2], np.zeros((2, 0, 3)), 0.01)


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
# The commands run in this process (`helpers.run_main`, the entry point's `main()`): what is tested
# is each command's behaviour and its one-line errors, not the process boundary.
@pytest.fixture
def _liedfl(run_main):
    def run(*args, cwd: Path) -> subprocess.CompletedProcess:
        return run_main(*args, cwd=cwd)

    return run


@pytest.fixture(scope="module")
def ball_run(tmp_path_factory) -> Path:
    """A ball chain on a free root under gravity, trained 3 epochs with model.kinetic=articulated."""
    tmp = tmp_path_factory.mktemp("export")
    ds = chain_dataset(
        links=2, joint="ball", root="free", gravity=9.81, n_trajectories=3, steps=30, h=0.02, speed=2.0, seed=0
    )
    save_dataset(ds, tmp / "chain.h5")
    with pytest.MonkeyPatch.context() as mp:
        for key in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR"):
            mp.delenv(key, raising=False)
        mp.setenv("MPLBACKEND", "Agg")
        code, tb = main_in_process(
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
    assert code == 0, tb[-2000:]
    return tmp


@pytest.mark.parametrize("mass", [None, 2.5])
def test_export_end_to_end(ball_run, mass, _liedfl):
    from liedfl_cli.data.hdf5 import load_dataset

    out = f"model_{mass}.xml"
    extra = [] if mass is None else [f"dataset.total_mass={mass}"]
    r = _liedfl("export", "run=run", "format=mjcf", f"out={out}", "paths.data_dir=data", *extra, cwd=ball_run)
    assert r.returncode == 0, r.stderr[-2000:]
    text = (ball_run / out).read_text()
    model = mujoco.MjModel.from_xml_string(text)
    total = 1.0 if mass is None else mass
    assert model.body_mass[1:].sum() == pytest.approx(total, rel=1e-9)
    assert list(model.jnt_type) == [mujoco.mjtJoint.mjJNT_FREE, mujoco.mjtJoint.mjJNT_BALL]
    assert np.allclose(model.opt.gravity, [0, 0, -9.81]) and model.opt.timestep == pytest.approx(0.02 / 50)
    assert (model.dof_damping[6:] >= 0).all()
    names = [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, i) for i in (1, 2)]
    assert names == ["link0", "link1"]
    source = "not set" if mass is None else "from the command line"
    assert source in text and source in r.stdout and "lengths in m" in text and "h/50" in text
    assert f"wrote {out}" in r.stdout
    assert not list(ball_run.glob(f"{out}.tmp*")) and not list(ball_run.glob(".*tmp*"))
    # the exported model, replayed by MuJoCo from the true states, follows the data (the scale is a gauge)
    ds = load_dataset(ball_run / "chain.h5")
    for i in range(len(ds.R)):
        R, _ = replay(text, ds.tree, ds.extras["qpos"][i, 0], ds.extras["qvel"][i, 0], ds.h, 30)
        err, cv = _mean_errors(ds, ds.tree, i, R)
        assert err < 0.1 * cv, (i, err, cv)


# ----------------------------------------------------------------------------- (d) one-line errors
def _one_line_failure(r: subprocess.CompletedProcess, *needles: str) -> None:
    assert r.returncode != 0 and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and all(n in lines[0] for n in needles), r.stderr


def test_a_missing_run_is_one_line(tmp_path, _liedfl):
    r = _liedfl("export", "run=nowhere", "out=m.xml", cwd=tmp_path)
    _one_line_failure(r, "run=nowhere")
    assert not (tmp_path / "m.xml").exists()


@pytest.mark.parametrize(
    "args, needles",
    [
        (["out=/proc/m.xml"], ["/proc/m.xml"]),  # not writable (even as root)
        (["out=."], ["out=.", "is a directory"]),
        (["out=nofolder/m.xml"], ["does not exist"]),
        (["format=urdf"], ["format='urdf'", "mjcf"]),
        (["dataset.total_mass=-1"], ["dataset.total_mass=-1"]),
    ],
)
def test_bad_arguments_are_one_line(ball_run, args, needles, _liedfl):
    r = _liedfl("export", "run=run", "paths.data_dir=data", *args, cwd=ball_run)
    _one_line_failure(r, *needles)


def test_a_per_body_run_is_refused_in_one_line(tmp_path, _liedfl):
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
    _one_line_failure(r, "needs an articulated model (model.kinetic=articulated)")
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
    from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN

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
    assert model_mj.opt.timestep == pytest.approx(0.02 / 50)


def test_write_mjcf_is_atomic(tmp_path):
    tree = Tree.from_lists([-1, 0], [[0, 0, 0], [0.3, 0, 0]], free_root=False)
    out = tmp_path / "m.xml"
    out.write_text("old")
    spec = _spec(tree)
    spec.mass[1] = -1.0
    with pytest.raises(ConfigError, match="body 'b1': mass"):
        write_mjcf(out, spec)
    assert out.read_text() == "old"  # a refused spec leaves the file as it was
    assert write_mjcf(out, _spec(tree)) == out and load_model(out.read_text()).nbody == 3
    assert [f.name for f in tmp_path.iterdir()] == ["m.xml"]


def test_rayleigh_damping_and_gravity_direction():
    """A joint-space Rayleigh D (group tangent layout) is written as the diagonal of S^T D S per DoF,
    with the dropped share; a learned gravity direction within 1e-3 rad of -e3 is written as -e3."""
    from liedfl_cli.commands.export_model import gravity_vector, rayleigh_dof_damping

    a = np.array([0.0, 0.6, 0.8])
    tree = Tree.from_lists(
        [-1, 0, 1],
        [[0, 0, 0], [0.3, 0, 0], [0.3, 0, 0]],
        free_root=True,
        joints=["free", "ball", "hinge"],
        axes=[[[0] * 3] * 2, [[0] * 3] * 2, [list(a), [0, 0, 0]]],
    )
    D = np.diag(np.arange(1.0, 13.0))  # dim 6 + 3 + 3
    d, off, root = rayleigh_dof_damping(tree, D)
    assert np.allclose(d, [0] * 6 + [7, 8, 9] + [a @ np.diag([10, 11, 12]) @ a]) and off == 0
    assert root == pytest.approx(np.linalg.norm(np.arange(1.0, 7.0)) / np.linalg.norm(np.arange(1.0, 13.0)))
    D[6, 7] = D[7, 6] = 1.0
    _, off, _ = rayleigh_dof_damping(tree, D)
    assert 0 < off < 1
    with pytest.raises(ConfigError, match="shape"):
        rayleigh_dof_damping(tree, np.eye(9))
    g, phrase = gravity_vector(np.array([1e-4, 0.0, -9.81]))
    assert g[0] == g[1] == 0 and g[2] == pytest.approx(-9.81) and "along -e3" in phrase
    tilted = 9.81 * np.array([np.sin(0.1), 0.0, -np.cos(0.1)])
    g, phrase = gravity_vector(tilted)
    assert np.allclose(g, tilted) and "learned direction" in phrase and "0.1 rad" in phrase
    assert gravity_vector(np.zeros(3))[1] == "none"
