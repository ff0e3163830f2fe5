"""Kinematic trees in the data (parents, joint_offsets, rotations) and MuJoCo chains, the independent
engine they are tested against (liedfl_cli/data/mujoco_chain.py, scripts/mujoco_chain.py)."""

from __future__ import annotations

import itertools
import json
import math
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from liedfl_cli.data.hdf5 import Dataset, load_dataset, save_dataset
from liedfl_cli.data.scenes import get_dataset
from liedfl_cli.errors import DatasetError
from liedfl_cli.lie import so3
from liedfl_cli.lie.product import Pose
from liedfl_cli.lie.tree import Tree, coordinates, forward_kinematics

mujoco = pytest.importorskip("mujoco")

from liedfl_cli.data.mujoco_chain import (  # noqa: E402
    chain_dataset,
    chain_mjcf,
    chain_spec,
    declared_physics,
    step_rotations,
)

ROOT = Path(__file__).resolve().parents[1]
FILE = {
    "name": "file",
    "n_trajectories": None,
    "steps": None,
    "train_steps": None,
    "rollout_steps": None,
    "split": "auto",
    "test_fraction": 0.2,
    "n_test": None,
    "seed": 0,
    "noise": {"rotation": 0.0, "position": 0.0},
    "smoothing": None,
}


def small(**kw) -> Dataset:
    args = {"n_trajectories": 2, "steps": 20, "h": 0.02, "speed": 3.0, "max_step_rotation": 1.0, **kw}
    return chain_dataset(**args)


def fk(ds: Dataset) -> Pose:
    assert ds.tree is not None
    return forward_kinematics(ds.tree, ds.pose())


# ---------------------------------------------------------------------- chains: FK against MuJoCo
CASES = [
    dict(links=links, joint=joint, root=root, rotations=rot, gravity=g, joint_damping=d)
    for links, joint, root, rot, (g, d) in itertools.product(
        (2, 3, 5), ("ball", "hinge"), ("free", "pinned"), ("world", "parent"), ((0.0, 0.0), (9.81, 0.05))
    )
    if not (links == 5 and g == 0.0)  # keep the fast tier fast: 5 links only with gravity and damping
]


@pytest.mark.parametrize("kw", CASES, ids=lambda kw: "-".join(str(v) for v in kw.values()))
def test_forward_kinematics_reproduces_mujocos_bodies(tmp_path, kw):
    ds = small(seed=kw["links"], **kw)
    path = save_dataset(ds, tmp_path / "chain.h5")
    back = load_dataset(path)
    assert back.tree == ds.tree and back.tree is not None
    assert back.tree.rotations == kw["rotations"] and back.tree.free_root == (kw["root"] == "free")
    assert back.group.n_se3 == (1 if kw["root"] == "free" else 0) and back.n_bodies == kw["links"]
    world = fk(back)
    np.testing.assert_allclose(world.R.numpy(), back.extras["body_R_world"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(world.p.numpy(), back.extras["body_p_world"], rtol=0, atol=1e-9)
    # and back: the coordinates of the engine's world poses are the stored ones
    c = coordinates(back.tree, Pose(torch.as_tensor(back.extras["body_R_world"]), world.p))
    np.testing.assert_allclose(c.R.numpy(), back.R, atol=1e-12)
    phys = back.params["physics"]
    assert phys["kind"] == "articulated" and phys["g"] == kw["gravity"] and phys["integrator"] == "RK4"
    assert phys["joint_damping"] == [kw["joint_damping"]] * (kw["links"] - 1) and phys["root_damping"] == 0.0
    assert len(phys["bodies"]) == kw["links"] and phys["engine"].startswith("mujoco ")
    assert (back.params.get("potential") == "none") == (kw["gravity"] == 0)
    assert back.params["gravity"] == kw["gravity"]
    if kw["joint"] == "hinge":
        assert len(phys["hinge_axes"]) == kw["links"] and phys["hinge_axes"][1] is not None
    else:
        assert phys["hinge_axes"] is None


def test_resimulated_directly_in_the_test():
    """One chain re-simulated here from its MJCF and its recorded initial qpos/qvel: MuJoCo's bodies
    equal the forward kinematics of the stored coordinates (and a fresh simulation reproduces them)."""
    ds = small(links=4, joint="ball", root="free", rotations="parent", gravity=9.81, joint_damping=0.05, seed=3)
    model = mujoco.MjModel.from_xml_string(ds.params["mjcf"])
    data = mujoco.MjData(model)
    sub = ds.params["simulation"]["substeps_per_sample"]
    world = fk(ds)
    for i in range(ds.n_trajectories):
        data.qpos[:], data.qvel[:] = ds.extras["qpos"][i, 0], ds.extras["qvel"][i, 0]
        for k in range(ds.n_steps + 1):
            if k > 0:
                mujoco.mj_step(model, data, nstep=sub)
            mujoco.mj_forward(model, data)
            np.testing.assert_allclose(world.p[i, k].numpy(), data.xpos[1:], atol=1e-9)
            np.testing.assert_allclose(world.R[i, k].numpy(), data.xmat[1:].reshape(-1, 3, 3), atol=1e-9)


def test_conservation_without_damping_and_gravity():
    """Zero damping, zero gravity, free root: MuJoCo's energy and momenta are conserved (RK4 at dt=1e-3)."""
    ds = small(links=3, joint="ball", root="free", gravity=0.0, joint_damping=0.0, steps=40, seed=5)
    E = ds.extras["energy"]
    assert np.abs(E - E[:, :1]).max() < 1e-8 * np.abs(E).max()
    for name in ("linear_momentum", "angular_momentum"):
        L = ds.extras[name]
        assert np.abs(L - L[:, :1]).max() < 1e-8 * max(1.0, np.abs(L).max())
    damped = small(links=3, joint="ball", root="free", gravity=0.0, joint_damping=0.2, steps=40, seed=5)
    assert (damped.extras["energy"][:, -1] < damped.extras["energy"][:, 0] - 1e-4).all()  # damping dissipates
    L = damped.extras["angular_momentum"]  # joint damping is internal: momentum stays
    assert np.abs(L - L[:, :1]).max() < 1e-8 * max(1.0, np.abs(L).max())


def _kinetic_from_poses(ds: Dataset) -> np.ndarray:
    """Kinetic energy at samples 1..N-1 from central differences of the FK world poses and the
    declared physics: sum_b 1/2 m |c'|^2 + 1/2 w^T I w (w body frame, c the world COM)."""
    world = fk(ds)
    Rw, pw = world.R.numpy(), world.p.numpy()
    phys = ds.params["physics"]
    h = ds.h
    K = np.zeros((ds.n_trajectories, ds.n_steps - 1))
    for b, body in enumerate(phys["bodies"]):
        com = pw[:, :, b] + np.einsum("tkij,j->tki", Rw[:, :, b], np.asarray(body["com"]))
        v = (com[:, 2:] - com[:, :-2]) / (2 * h)
        dR = np.swapaxes(Rw[:, 1:-1, b], -1, -2) @ (Rw[:, 2:, b] - Rw[:, :-2, b]) / (2 * h)
        w = np.stack([dR[..., 2, 1] - dR[..., 1, 2], dR[..., 0, 2] - dR[..., 2, 0], dR[..., 1, 0] - dR[..., 0, 1]], -1)
        w /= 2
        Iw = np.einsum("ij,tkj->tki", np.asarray(body["inertia"]), w)
        K += 0.5 * body["mass"] * (v * v).sum(-1) + 0.5 * (w * Iw).sum(-1)
    return K


@pytest.mark.parametrize("root,gravity", [("free", 0.0), ("free", 9.81), ("pinned", 0.0)])
def test_declared_physics_recomputes_mujocos_kinetic_energy_to_second_order(root, gravity):
    """The declared masses, centres of mass and inertias (body frame) with central differences of the
    FK world poses give MuJoCo's kinetic energy up to O(h^2) over the same 0.2 s."""
    errors = []
    for h in (0.02, 0.01):
        ds = small(links=3, root=root, gravity=gravity, joint_damping=0.05, h=h, steps=round(0.2 / h), seed=2)
        K = _kinetic_from_poses(ds)
        ref = ds.extras["kinetic_energy"][:, 1:-1]
        errors.append(np.abs(K - ref).max() / np.abs(ref).max())
    assert errors[0] < 2e-3
    assert errors[1] < errors[0] / 3  # O(h^2): halving h divides the error by about 4


def test_declared_physics_is_mujocos_compiled_model():
    spec = chain_spec(links=3, seed=4)
    model = mujoco.MjModel.from_xml_string(chain_mjcf(spec))
    phys = declared_physics(spec, model)
    for link, body in zip(spec.links, phys["bodies"]):
        assert body["mass"] == pytest.approx(link.mass)
        np.testing.assert_allclose(body["com"], link.com, atol=1e-12)
        np.testing.assert_allclose(body["inertia"], link.inertia, atol=1e-10)
        I = np.asarray(body["inertia"])
        assert np.abs(I - np.diag(np.diag(I))).max() > 1e-4  # off-diagonal terms in the body frame
        assert np.linalg.eigvalsh(I).min() > 0
    assert all(np.linalg.norm(body["com"]) > 0.05 for body in phys["bodies"])  # centres of mass off the joint


def test_chain_is_deterministic_and_rotations_are_bounded():
    a, b = small(seed=7), small(seed=7)
    np.testing.assert_array_equal(a.R, b.R)
    np.testing.assert_array_equal(a.p, b.p)
    assert a.params["step_rotation"]["coordinates"] == pytest.approx(float(step_rotations(a.R).max()))
    assert a.params["step_rotation"]["coordinates"] < 1.0
    c = small(seed=8)
    assert not np.allclose(a.R, c.R)
    with pytest.raises(Exception, match="largest per-step rotation"):
        small(seed=7, max_step_rotation=1e-3)


def test_script_writes_a_file_that_dataset_file_reads_with_its_tree(tmp_path, capsys):
    """scripts/mujoco_chain.py's `main(argv)`, called in-process (its argument handling, output and file)."""
    import runpy

    main = runpy.run_path(str(ROOT / "scripts" / "mujoco_chain.py"), run_name="mujoco_chain_script")["main"]
    out = tmp_path / "chain.h5"
    argv = ["--links", "2", "--n-trajectories", "3", "--steps", "10", "--rotations", "parent", "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err
    stdout = capsys.readouterr().out
    assert "largest per-step rotation" in stdout and "SE(3) x SO(3)" in stdout
    ds, cached = get_dataset({**FILE, "path": str(out)}, tmp_path / "data")
    assert ds.tree is not None and ds.tree.rotations == "parent" and ds.tree == load_dataset(out).tree
    assert load_dataset(cached).tree == ds.tree
    capsys.readouterr()
    code = main(["--links", "7", "--out", str(tmp_path / "x.h5")])
    err = capsys.readouterr().err
    assert code == 2 and "links=7" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.h5").exists()


# ---------------------------------------------------------------------- the tree fields of the format
def tree_dataset(free: bool = True, rotations: str = "parent", B: int = 3) -> Dataset:
    g = torch.Generator().manual_seed(0)
    T, N1 = 2, 4
    R = so3.random((T, N1, B), generator=g).numpy()
    R[:, 1:] = R[:, :1]  # still data (the per-step check is not what is tested here)
    m = 1 if free else 0
    offsets = np.arange(3 * B, dtype=np.float64).reshape(B, 3) / 10
    if free:
        offsets[0] = 0.0
    return Dataset(
        R=R,
        p=np.zeros((T, N1, m, 3)),
        h=0.1,
        scene="tree",
        body_names=[f"b{i}" for i in range(B)],
        body_kinds=["se3"] * m + ["so3"] * (B - m),
        split={"train": np.array([0]), "test": np.array([1])},
        tree=Tree.from_lists([-1, 0, 1][:B] + [0] * (B - 3), offsets, rotations, free_root=free),
    )


@pytest.mark.parametrize("free", [True, False])
@pytest.mark.parametrize("rotations", ["world", "parent"])
def test_tree_fields_round_trip(tmp_path, free, rotations):
    ds = tree_dataset(free, rotations)
    path = save_dataset(ds, tmp_path / "t.h5")
    with h5py.File(path) as f:
        assert json.loads(f.attrs["parents"]) == [-1, 0, 1] and f.attrs["rotations"] == rotations
        assert f["joint_offsets"].dtype == np.float64 and f["joint_offsets"].shape == (3, 3)
    back = load_dataset(path)
    assert back.tree == ds.tree


def test_a_file_without_tree_has_none(tmp_path):
    ds = tree_dataset()
    ds.tree = None
    back = load_dataset(save_dataset(ds, tmp_path / "t.h5"))
    assert back.tree is None
    with h5py.File(tmp_path / "t.h5") as f:
        assert "parents" not in f.attrs and "joint_offsets" not in f


def _edit(path: Path, attrs=None, offsets=None, delete=()):
    with h5py.File(path, "a") as f:
        for k in delete:
            if k in f.attrs:
                del f.attrs[k]
            elif k in f:
                del f[k]
        for k, v in (attrs or {}).items():
            f.attrs[k] = v
        if offsets is not None:
            del f["joint_offsets"]
            f.create_dataset("joint_offsets", data=offsets)


BAD = [
    ({"attrs": {"parents": json.dumps([-1, 2, 0])}}, r"attribute 'parents' has parent 2 for body 1.*before"),
    ({"attrs": {"parents": json.dumps([0, 0, 1])}}, r"attribute 'parents' must start with -1"),
    ({"attrs": {"parents": json.dumps([-1, 0])}}, r"attribute 'parents' has 2 entries"),
    ({"attrs": {"parents": json.dumps([-1, "a", 0])}}, r"attribute 'parents' must be a JSON list of integers"),
    ({"offsets": np.zeros((3, 2))}, r"dataset 'joint_offsets' has shape \(3, 2\), expected \(3, 3\)"),
    ({"offsets": np.full((3, 3), np.nan)}, r"dataset 'joint_offsets' has non-finite value"),
    ({"offsets": np.ones((3, 3))}, r"dataset 'joint_offsets' row 0 .* must be zeros"),
    ({"attrs": {"rotations": "local"}}, r"attribute 'rotations' must be one of \['world', 'parent'\], got 'local'"),
    ({"delete": ["joint_offsets"]}, r"dataset 'joint_offsets' is missing"),
    ({"delete": ["parents"]}, r"attribute 'parents' is missing"),
    ({"delete": ["parents", "joint_offsets"]}, r"attribute 'rotations' is 'parent' but the file has no tree"),
    (
        {"attrs": {"body_kinds": json.dumps(["se3", "se3", "so3"]), "n_se3": 2, "n_so3": 1}},
        r"attribute 'parents' describes a tree but 'body_kinds' lists 2 SE\(3\) bodies",
    ),
]


@pytest.mark.parametrize("edit,pattern", BAD, ids=[p for _, p in BAD])
def test_malformed_tree_fields_are_one_line_errors(tmp_path, edit, pattern):
    path = save_dataset(tree_dataset(), tmp_path / "t.h5")
    if "body_kinds" in edit.get("attrs", {}):
        with h5py.File(path, "a") as f:
            p = f["p"][()]
            del f["p"]
            f.create_dataset("p", data=np.concatenate([p, p], 2))
    _edit(path, **edit)
    with pytest.raises(DatasetError, match=pattern) as e:
        load_dataset(path)
    msg = str(e.value)
    assert msg.startswith(str(path)) and "\n" not in msg


def test_save_refuses_a_tree_that_does_not_fit_the_bodies(tmp_path):
    ds = tree_dataset(free=True)
    ds.tree = Tree.from_lists([-1, 0, 1], np.zeros((3, 3)), "world", free_root=False)
    with pytest.raises(DatasetError, match="free_root=False"):
        save_dataset(ds, tmp_path / "t.h5")
    ds.tree = Tree.from_lists([-1, 0], np.zeros((2, 3)), "world")
    with pytest.raises(DatasetError, match="'parents' has 2 entries"):
        save_dataset(ds, tmp_path / "t.h5")


def test_build_context_carries_the_tree():
    from liedfl_cli.config.factory import build_context

    cfg = OmegaConf.create({"seed": 0, "train": {"epsilon": 10.0}, "force": None})
    ds = tree_dataset()
    assert build_context(cfg, ds).tree == ds.tree
    ds.tree = None
    assert build_context(cfg, ds).tree is None


def test_pinned_root_sits_at_its_offset():
    ds = small(links=2, root="pinned", seed=1)
    assert ds.tree is not None and not ds.tree.free_root
    np.testing.assert_allclose(ds.extras["body_p_world"][:, :, 0], np.broadcast_to(ds.tree.offsets[0], (2, 21, 3)))
    assert math.isclose(float(np.abs(fk(ds).p[:, :, 0].numpy() - np.asarray(ds.tree.offsets[0])).max()), 0.0)


def test_rolling_a_tree_model_out_on_other_data_needs_the_same_tree():
    from types import SimpleNamespace

    from liedfl_cli.config.other_data import check_model_fits_data
    from liedfl_cli.errors import ConfigError
    from liedfl_cli.lie.product import ProductGroup

    ds = tree_dataset()
    assert ds.tree is not None
    model = SimpleNamespace(G=ProductGroup(1, 2), h=0.1, tree=ds.tree)
    check_model_fits_data(model, ds, "run")
    check_model_fits_data(
        SimpleNamespace(G=ProductGroup(1, 2), h=0.1, tree=None), ds, "run"
    )  # a model without a tree (Model.tree)
    other = tree_dataset(rotations="world")
    with pytest.raises(ConfigError, match="other rotations"):
        check_model_fits_data(model, other, "run")
    other.tree = Tree.from_lists(ds.tree.parents, np.zeros((3, 3)), "parent")
    with pytest.raises(ConfigError, match="other offsets"):
        check_model_fits_data(model, other, "run")
    other.tree = None
    with pytest.raises(ConfigError, match="has none"):
        check_model_fits_data(model, other, "run")


# ---------------------------------------------------------------------- MuJoCo trees: every joint type
from liedfl_cli.data.mujoco_chain import JOINT_DOF, TREES, tree_spec  # noqa: E402
from liedfl_cli.errors import ConfigError  # noqa: E402
from liedfl_cli.lie.joint_constraints import joint_violation  # noqa: E402
from liedfl_cli.lie.joints import to_joint_coordinates  # noqa: E402

TREE_CASES = {
    "branched5-free-mixed-world": dict(parents="branched5", joints=["free", "hinge", "universal", "ball", "weld"]),
    "branched5-free-mixed-parent": dict(
        parents=[-1, 0, 0, 0, 1], joints=["free", "universal", "weld", "hinge", "hinge"], rotations="parent"
    ),
    "branched5-pinned-hinge-gravity": dict(
        parents="branched5",
        joints=["hinge", "ball", "hinge", "universal", "weld"],
        gravity=9.81,
        joint_damping=[0.0, 0.05, 0.02, [0.01, 0.08], 0.0],
        h=0.01,
        speed=2.0,
    ),
    "binary7-pinned-universal": dict(
        parents="binary7", joints=["universal", "hinge", "ball", "weld", "universal", "hinge", "ball"], h=0.02
    ),
    "branched7-pinned-ball-parent": dict(
        parents="branched7",
        joints=["ball", "hinge", "hinge", "universal", "ball", "weld", "hinge"],
        rotations="parent",
        gravity=9.81,
        h=0.02,
        speed=2.0,
    ),
    "chain4-heavy-root-mm": dict(
        parents=[-1, 0, 1, 2], joints=["free", "hinge", "universal", "ball"], heavy_root=True, unit="mm"
    ),
}


def tree(**kw) -> Dataset:
    args = {"n_trajectories": 2, "steps": 15, "h": 0.02, "speed": 3.0, "max_step_rotation": 1.0, "seed": 11, **kw}
    return chain_dataset(**args)


def joint_violations(ds: Dataset) -> list[float]:
    assert ds.tree is not None
    q = to_joint_coordinates(ds.tree, ds.pose())
    axes = torch.tensor(ds.tree.axes_array(), dtype=torch.float64)
    return [float(joint_violation(k, axes[b], q.R[:, :, b]).max()) for b, k in enumerate(ds.tree.joint_kinds)]


@pytest.mark.parametrize("kw", TREE_CASES.values(), ids=TREE_CASES.keys())
def test_trees_reproduce_mujocos_poses_and_obey_their_joints(tmp_path, kw):
    ds = tree(**kw)
    back = load_dataset(save_dataset(ds, tmp_path / "tree.h5"))  # the load-time joint check passes too
    assert back.tree == ds.tree and back.tree is not None
    parents = TREES[kw["parents"]] if isinstance(kw["parents"], str) else kw["parents"]
    assert list(back.tree.parents) == parents and back.tree.joints == tuple(kw["joints"])
    assert back.tree.free_root == (kw["joints"][0] == "free") and back.tree.rotations == kw.get("rotations", "world")
    world = fk(back)
    scale = 1000.0 if kw.get("unit") == "mm" else 1.0
    np.testing.assert_allclose(world.R.numpy(), back.extras["body_R_world"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(world.p.numpy(), back.extras["body_p_world"], rtol=0, atol=1e-9 * scale)
    violations = joint_violations(back)
    assert max(violations) < 1e-9, dict(zip(back.tree.joint_kinds, violations))
    # the joints really move: every hinge / universal / ball turns, a weld does not
    q = to_joint_coordinates(back.tree, back.pose()).R
    for b, k in enumerate(back.tree.joint_kinds):
        turn = float(so3.log(q[:, :1, b].transpose(-1, -2) @ q[:, :, b]).norm(dim=-1).max())
        assert (turn < 1e-9) if k == "weld" else (turn > 1e-2), (b, k, turn)
    phys = back.params["physics"]
    B = len(parents)
    assert phys["joints"] == kw["joints"] and np.asarray(phys["joint_axes"]).shape == (B, 2, 3)
    assert np.asarray(phys["joint_axes"]).tolist() == back.tree.axes_array()
    assert [len(d) for d in phys["dof_damping"]] == [JOINT_DOF[k] for k in kw["joints"]]
    assert len(phys["joint_damping"]) == B - 1 and phys["length_unit_m"] == back.params["length_unit_m"]
    assert back.params["length_unit_m"] == (1e-3 if kw.get("unit") == "mm" else 1.0)
    assert back.params["config"]["parents"] == parents and back.params["config"]["joints"] == kw["joints"]
    axes = np.asarray(back.tree.axes_array())
    for b, k in enumerate(kw["joints"]):
        if k == "universal":  # two axes well away from parallel (between pi/4 and 3pi/4)
            assert abs(axes[b, 0] @ axes[b, 1]) < np.cos(np.pi / 4)


def test_a_tree_resimulated_from_its_mjcf_matches_by_body_name():
    """MuJoCo numbers a tree's bodies depth first; the file's order is liedfl's: matched by name."""
    ds = tree(parents=[-1, 0, 0, 1, 2, 1], joints=["free", "universal", "hinge", "weld", "ball", "hinge"])
    model = mujoco.MjModel.from_xml_string(ds.params["mjcf"])
    data = mujoco.MjData(model)
    ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in ds.body_names]
    assert ids != sorted(ids)  # depth first: link3 (under link1) comes before link2
    assert model.nv == 6 + 2 + 1 + 0 + 3 + 1 and model.njnt == 1 + 2 + 1 + 1 + 1
    world = fk(ds)
    sub = ds.params["simulation"]["substeps_per_sample"]
    data.qpos[:], data.qvel[:] = ds.extras["qpos"][1, 0], ds.extras["qvel"][1, 0]
    for k in range(ds.n_steps + 1):
        if k > 0:
            mujoco.mj_step(model, data, nstep=sub)
        mujoco.mj_forward(model, data)
        np.testing.assert_allclose(world.p[1, k].numpy(), data.xpos[ids], atol=1e-9)
        np.testing.assert_allclose(world.R[1, k].numpy(), data.xmat[ids].reshape(-1, 3, 3), atol=1e-9)


def test_a_weld_is_exactly_constant_and_a_hinge_turns_about_its_axis_only():
    kw = dict(parents=[-1, 0, 1, 1], joints=["free", "hinge", "weld", "universal"])
    par = tree(rotations="parent", **kw)
    np.testing.assert_array_equal(par.R[:, :, 2], np.broadcast_to(np.eye(3), par.R[:, :, 2].shape))
    wor = tree(rotations="world", **kw)
    np.testing.assert_array_equal(wor.R[:, :, 2], wor.R[:, :, 1])  # world attitudes: the parent's, exactly
    rel = np.swapaxes(wor.R[:, :, 1], -1, -2) @ wor.R[:, :, 2]
    assert np.abs(rel - np.eye(3)).max() < 1e-14
    # hinge: R_rel = exp(t a) with a the declared axis (C = I: identity body quats)
    a = np.asarray(par.tree.axes[1][0])
    w = so3.log(torch.as_tensor(par.R[:, :, 1])).numpy()
    assert np.abs(w - (w @ a)[..., None] * a).max() < 1e-12
    # universal: R_rel a2 . a1 = a1 . a2 (C = I)
    a1, a2 = (np.asarray(x) for x in par.tree.axes[3])
    assert np.abs(np.einsum("i,tkij,j->tk", a1, par.R[:, :, 3], a2) - a1 @ a2).max() < 1e-12


def test_millimetres_are_the_metre_data_scaled():
    kw = dict(parents="branched5", joints=["free", "hinge", "ball", "universal", "ball"], gravity=9.81)
    kw.update(joint_damping=[0.0, 0.05, 0.03, [0.02, 0.06], 0.04], h=0.01, speed=2.0)
    m, mm = tree(**kw), tree(unit="mm", **kw)
    np.testing.assert_array_equal(mm.R, m.R)
    np.testing.assert_allclose(mm.p, 1000 * m.p, rtol=1e-15)
    np.testing.assert_allclose(mm.extras["body_p_world"], 1000 * m.extras["body_p_world"], rtol=1e-15)
    np.testing.assert_allclose(fk(mm).p.numpy(), mm.extras["body_p_world"], atol=1e-6)  # 1e-9 m in mm
    np.testing.assert_allclose(np.asarray(mm.tree.offsets), 1000 * np.asarray(m.tree.offsets), rtol=1e-15)
    np.testing.assert_allclose(mm.extras["energy"], 1e6 * m.extras["energy"], rtol=1e-12)
    pm, pmm = m.params["physics"], mm.params["physics"]
    for a, b in zip(pm["bodies"], pmm["bodies"]):
        assert a["mass"] == b["mass"]
        np.testing.assert_allclose(b["com"], 1000 * np.asarray(a["com"]), rtol=1e-15)
        np.testing.assert_allclose(b["inertia"], 1e6 * np.asarray(a["inertia"]), rtol=1e-15)
    assert pmm["g"] == pytest.approx(9810.0) and mm.params["gravity"] == pytest.approx(9810.0)
    np.testing.assert_allclose(pmm["dof_damping"][3], [2e4, 6e4])
    assert mm.params["length_unit_m"] == 1e-3 and m.params["length_unit_m"] == 1.0
    assert mm.params["mjcf"] == m.params["mjcf"]  # MuJoCo's scene stays in metres


def test_per_dof_damping_and_heavy_root_reach_mujoco():
    spec = tree_spec(
        [-1, 0, 1, 1], ["hinge", "universal", "ball", "weld"], joint_damping=[0.01, [0.02, 0.07], 0.03, 0.0], seed=3
    )
    model = mujoco.MjModel.from_xml_string(chain_mjcf(spec))
    phys = declared_physics(spec, model)
    assert phys["dof_damping"] == [[0.01], [0.02, 0.07], [0.03] * 3, []]
    assert phys["root_damping"] == 0.01 and phys["joint_damping"] == [pytest.approx(0.045), 0.03, 0.0]
    np.testing.assert_allclose(model.dof_damping, [0.01, 0.02, 0.07, 0.03, 0.03, 0.03])
    heavy = tree_spec([-1, 0, 0, 0, 1], ["free"] + ["ball"] * 4, heavy_root=True, seed=3)
    masses = [link.mass for link in heavy.links]
    assert masses[0] == 4.0 and all(0.5 <= m <= 0.7 for m in masses[1:])
    assert max(np.linalg.eigvalsh(link.inertia).max() for link in heavy.links[1:]) < 0.025
    assert tree_spec([-1, 0], ["free", "ball"], heavy_root=True, root_mass=10.0).links[0].mass == 10.0


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        (dict(parents=[-1, 0, 2], joints=["free", "ball", "ball"]), "every parent an earlier body"),
        (dict(parents=[-1, 0], joints=["free", "slider"]), "joints[1]='slider'"),
        (dict(parents=[-1, 0, 0], joints=["ball", "free", "ball"]), "joints[1]='free'"),
        (dict(parents=[-1, 0], joints=["weld", "weld"]), "nothing to move"),
        (dict(parents="star9", joints=None), "one of ['chain3'"),
        (dict(parents=[-1, 0], joints=["free", "universal"], joint_damping=[0.0, [0.1, 0.2, 0.3]]), "3 values"),
        (dict(parents=[-1, 0], joints=["free", "ball"], joint_damping=[0.1, 0.1]), "free root is undamped"),
        (dict(parents=[-1, 0], joints=["free", "ball"], unit="cm"), "unit='cm'"),
    ],
)
def test_bad_tree_options_are_config_errors(kw, message):
    with pytest.raises(ConfigError) as e:
        tree(**kw)
    assert message in str(e.value)


def test_script_makes_trees(tmp_path, capsys):
    import runpy

    main = runpy.run_path(str(ROOT / "scripts" / "mujoco_chain.py"), run_name="mujoco_chain_script")["main"]
    out = tmp_path / "tree.h5"
    argv = ["--parents", "0,0,0,1", "--joints", "hinge,universal,ball,weld", "--unit", "mm", "--heavy-root"]
    argv += ["--joint-damping", "0,0.05,0.02:0.08,0.05,0", "--n-trajectories", "2", "--steps", "5", "--out", str(out)]
    assert main(argv) == 0, capsys.readouterr().err
    ds = load_dataset(out)
    assert ds.tree is not None and list(ds.tree.parents) == [-1, 0, 0, 0, 1]
    assert ds.tree.joints == ("free", "hinge", "universal", "ball", "weld") and ds.params["length_unit_m"] == 1e-3
    assert ds.params["physics"]["dof_damping"][2] == pytest.approx([0.02e6, 0.08e6])
    assert "5 bodies" in capsys.readouterr().out
    out2 = tmp_path / "named.h5"
    argv = ["--tree", "binary7", "--root", "pinned", "--joint", "hinge", "--n-trajectories", "2", "--steps", "5"]
    assert main([*argv, "--h", "0.02", "--out", str(out2)]) == 0, capsys.readouterr().err
    named = load_dataset(out2)
    assert list(named.tree.parents) == TREES["binary7"] and named.tree.joints == ("hinge",) * 7
    assert main(["--tree", "binary7", "--parents", "0", "--out", str(tmp_path / "x.h5")]) == 2
    assert "not both" in capsys.readouterr().err
