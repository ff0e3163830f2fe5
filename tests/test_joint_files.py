"""Joints in files (attribute 'joints', dataset 'joint_axes') and MuJoCo trees with every joint type.

Round trip, the one-line errors, the refusal of motion that breaks a declared joint, and trees simulated
by MuJoCo (an engine nobody here wrote): branched, free and pinned roots, ball / hinge / universal / weld
joints, heavy root, millimetres, whose stored coordinates reproduce MuJoCo's world poses through liedfl's
forward kinematics and obey their joints to rounding error.
"""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest
import torch

from liedfl_cli.data.hdf5 import load_dataset, save_dataset
from liedfl_cli.errors import DatasetError
from liedfl_cli.lie import so3
from liedfl_cli.lie.joint_constraints import joint_violation
from liedfl_cli.lie.joints import to_joint_coordinates
from liedfl_cli.lie.tree import forward_kinematics

pytest.importorskip("mujoco")
from liedfl_cli.data.mujoco_chain import chain_dataset

MIXED = {"parents": [-1, 0, 0, 0, 1], "joints": ["free", "ball", "hinge", "universal", "weld"]}


@pytest.fixture(scope="module")
def mixed(tmp_path_factory):
    ds = chain_dataset(n_trajectories=4, steps=30, seed=5, **MIXED)
    path = tmp_path_factory.mktemp("joints") / "mixed.h5"
    save_dataset(ds, path)
    return ds, path


def test_joints_round_trip(mixed):
    ds, path = mixed
    back = load_dataset(path)
    assert back.tree == ds.tree and back.tree.joints == tuple(MIXED["joints"])
    assert back.tree.n_dof == 6 + 3 + 1 + 2 + 0


def _edited(src, tmp_path, edit):
    path = tmp_path / "edited.h5"
    path.write_bytes(src.read_bytes())
    with h5py.File(path, "r+") as f:
        edit(f)
    return path


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (lambda f: f.attrs.__setitem__("joints", json.dumps(["free", "ball"])), "'joints' has 2 entries"),
        (lambda f: f.attrs.__setitem__("joints", json.dumps("free")), "must be a JSON list"),
        (
            lambda f: f.attrs.__setitem__("joints", json.dumps(["ball", "ball", "hinge", "universal", "weld"])),
            "'ball' for the free (SE(3)) root",
        ),
        (
            lambda f: f.attrs.__setitem__("joints", json.dumps(["free", "slider", "hinge", "universal", "weld"])),
            "'slider' for body 1",
        ),
        (lambda f: f.__delitem__("joint_axes"), "'joint_axes' is missing (body 2 is a hinge"),
        (lambda f: f["joint_axes"].__setitem__((2, 0), [2.0, 0.0, 0.0]), "row [2, 0] of the hinge joint has norm 2"),
        (lambda f: f["joint_axes"].__setitem__((2, 0), [np.nan, 0.0, 0.0]), "'joint_axes' has non-finite"),
    ],
)
def test_bad_joint_fields_are_one_line_errors(mixed, tmp_path, edit, message):
    _, src = mixed
    with pytest.raises(DatasetError) as e:
        load_dataset(_edited(src, tmp_path, edit))
    assert message in str(e.value) and "\n" not in str(e.value)


def test_motion_that_breaks_a_declared_hinge_is_refused(mixed, tmp_path):
    _, src = mixed
    other = np.array([0.0, 0.0, 1.0])

    def wrong_axis(f):
        ax = f["joint_axes"][()]
        ax[2, 0] = other if abs(ax[2, 0] @ other) < 0.9 else np.array([1.0, 0.0, 0.0])
        f["joint_axes"][...] = ax

    with pytest.raises(DatasetError, match=r"body 2 \(link2\) is declared a hinge joint but trajectory \d violates"):
        load_dataset(_edited(src, tmp_path, wrong_axis))


@pytest.mark.parametrize(
    "kw",
    [
        {**MIXED, "rotations": "world"},
        {**MIXED, "rotations": "parent"},
        {
            "parents": [-1, 0, 1, 1],
            "joints": ["hinge", "hinge", "universal", "hinge"],
            "gravity": 9.81,
            "h": 0.02,
            "speed": 2.0,
        },
        {"parents": [-1, 0, 1, 2], "joints": ["universal", "ball", "weld", "hinge"], "h": 0.02, "speed": 2.0},
    ],
)
def test_mujoco_trees_obey_their_joints_and_match_mujocos_poses(kw):
    ds = chain_dataset(n_trajectories=3, steps=20, seed=2, **{"h": 0.05, **kw})
    truth = ds.pose()
    world = forward_kinematics(ds.tree, truth)
    assert np.abs(world.R.numpy() - ds.extras["body_R_world"]).max() < 1e-10
    assert np.abs(world.p.numpy() - ds.extras["body_p_world"]).max() < 1e-10
    q = to_joint_coordinates(ds.tree, truth)
    axes = torch.tensor(ds.tree.axes_array(), dtype=torch.float64)
    for b, kind in enumerate(ds.tree.joint_kinds):
        assert float(joint_violation(kind, axes[b], q.R[:, :, b]).max()) < 1e-9, (b, kind)


def test_the_same_tree_in_millimetres_is_the_metre_tree_scaled():
    kw = {"parents": [-1, 0, 1, 2], "joints": ["free", "ball", "hinge", "ball"], "heavy_root": True}
    m = chain_dataset(n_trajectories=2, steps=10, seed=4, **kw)
    mm = chain_dataset(n_trajectories=2, steps=10, seed=4, unit="mm", **kw)
    assert np.allclose(mm.R, m.R, atol=0) and np.allclose(mm.p, 1000 * m.p, rtol=1e-12)
    assert np.allclose(np.asarray(mm.tree.offsets), 1000 * np.asarray(m.tree.offsets))
    bm, bmm = m.params["physics"]["bodies"], mm.params["physics"]["bodies"]
    assert bm[0]["mass"] == 4.0 and all(0.5 <= b["mass"] <= 0.7 for b in bm[1:])
    assert np.allclose(bmm[1]["inertia"], 1e6 * np.asarray(bm[1]["inertia"]))
    assert mm.params["length_unit_m"] == 1e-3


# ---------------------------------------------------------------------- joint_violation on hand-built motion
def _exp(w) -> torch.Tensor:
    return so3.exp(torch.as_tensor(np.asarray(w, dtype=np.float64)))


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


A = _unit([0.3, -0.5, 0.8])
A2 = _unit([0.9, 0.2, -0.1])
C = _exp([0.4, 0.1, -0.7])
THETA = np.linspace(-2.0, 2.5, 30)  # ~0.16 rad per step


def _axes(a1=A, a2=None) -> torch.Tensor:
    return torch.tensor(np.stack([a1, np.zeros(3) if a2 is None else a2]))


def test_violation_of_exact_joint_motion_is_rounding_error():
    hinge = C @ _exp(THETA[:, None] * A)  # (N+1, 3, 3): C exp(t a)
    universal = _exp(THETA[:, None] * A2) @ C @ _exp(np.cos(THETA)[:, None] * A)  # exp(t1 a1) C exp(t2 a2)
    weld = C.expand(5, 3, 3)
    assert float(joint_violation("hinge", _axes(A), hinge)) < 1e-12
    assert float(joint_violation("universal", _axes(A2, A), universal)) < 1e-12
    assert float(joint_violation("weld", _axes(), weld)) == 0.0
    free = so3.exp(torch.randn(30, 3, dtype=torch.float64))
    for kind in ("ball", "free"):
        assert float(joint_violation(kind, _axes(), free)) == 0.0
    # batched: (T, N+1, 3, 3) -> (T,)
    assert joint_violation("hinge", _axes(A), torch.stack([hinge, hinge])).shape == (2,)
    with pytest.raises(ValueError, match="unknown joint type 'slider'"):
        joint_violation("slider", _axes(), hinge)


def test_violation_measures_the_wobble_in_radians():
    eps = 1e-3
    off = _unit(np.cross(A, [1.0, 0.0, 0.0]))  # perpendicular to the axis
    # the axis itself (C a in the parent frame) tilted by eps after the first sample
    tilted = C @ _exp(THETA[:, None] * A)
    tilted[1:] = _exp(eps * _unit(np.cross(C.numpy() @ A, [1.0, 0.0, 0.0]))) @ tilted[1:]
    assert float(joint_violation("hinge", _axes(A), tilted)) == pytest.approx(eps, rel=2e-2)
    # an increment with an off-axis part eps (in the body frame) but the axis back in place
    wobble = C @ _exp(THETA[:, None] * A)
    wobble[10] = wobble[10] @ _exp(eps * off)
    v = float(joint_violation("hinge", _axes(A), wobble))
    assert eps * 0.99 < v < 1.01 * eps
    # universal: a1^T R a2 drifts by sin(eps) -> eps as an angle
    uni = _exp(THETA[:, None] * A2) @ C @ _exp(THETA[:, None] * A)
    n = _unit(np.cross(A2, (C.numpy() @ A)))
    uni[5:] = _exp(THETA[5:, None] * A2) @ _exp(eps * n) @ C @ _exp(THETA[5:, None] * A)
    assert float(joint_violation("universal", _axes(A2, A), uni)) == pytest.approx(eps, rel=1e-2)
    # weld: the geodesic distance to the first sample
    weld = C.expand(4, 3, 3).clone()
    weld[3] = weld[3] @ _exp(2 * eps * A)
    assert float(joint_violation("weld", _axes(), weld)) == pytest.approx(2 * eps, rel=1e-9)


# ---------------------------------------------------------------------- more of the file's one-line errors
def test_joints_as_an_hdf5_string_array_are_read(mixed, tmp_path):
    ds, src = mixed
    path = _edited(src, tmp_path, lambda f: f.attrs.__setitem__("joints", np.array(MIXED["joints"], dtype="S")))
    assert load_dataset(path).tree.joints == tuple(MIXED["joints"])
    strs = h5py.string_dtype()
    path = _edited(src, tmp_path, lambda f: f.attrs.create("joints", MIXED["joints"], dtype=strs))
    assert load_dataset(path).tree == ds.tree


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (
            lambda f: f.attrs.__setitem__("joints", "hinge"),
            "'joints' must be a JSON list of strings (or an HDF5 string array), got text that is not valid JSON",
        ),
        (lambda f: f.attrs.__setitem__("joints", json.dumps("hingeball")), 'got a JSON string ("hingeball")'),
        (
            lambda f: f.attrs.__setitem__("joints", json.dumps(["free", "ball", "free", "universal", "weld"])),
            "'free' for body 2 ('free' is only the free root's, body 0)",
        ),
        (
            lambda f: (f.__delitem__("joint_axes"), f.create_dataset("joint_axes", data=np.zeros((5, 3)))),
            "'joint_axes' has shape (5, 3), expected (5, 2, 3)",
        ),
        (lambda f: f.attrs.__delitem__("joints"), "'joint_axes' is given but attribute 'joints' is missing"),
        (
            lambda f: f["joint_axes"].__setitem__((3, 1), [0.0, 0.6, 0.8 + 2e-6]),
            "row [3, 1] of the universal joint has norm 1",
        ),
    ],
)
def test_more_bad_joint_fields(mixed, tmp_path, edit, message):
    _, src = mixed
    path = _edited(src, tmp_path, edit)
    with pytest.raises(DatasetError) as e:
        load_dataset(path)
    assert message in str(e.value) and "\n" not in str(e.value) and str(path) in str(e.value)


def test_joints_without_a_tree_and_a_pinned_root_declared_free_are_refused(tmp_path):
    ds = chain_dataset(n_trajectories=2, steps=6, seed=1, parents=[-1, 0, 1], joints=["hinge", "ball", "weld"])
    path = save_dataset(ds, tmp_path / "pinned.h5")
    assert load_dataset(path).tree.joints == ("hinge", "ball", "weld")
    bad = _edited(path, tmp_path, lambda f: f.attrs.__setitem__("joints", json.dumps(["free", "ball", "weld"])))
    with pytest.raises(DatasetError, match=r"has 'free' for body 0 \('free' is only the free root's"):
        load_dataset(bad)

    def no_tree(f):
        del f.attrs["parents"], f["joint_offsets"]

    with pytest.raises(DatasetError, match="attribute 'joints' needs a tree"):
        load_dataset(_edited(path, tmp_path, no_tree))


def test_a_wobbling_hinge_is_refused_naming_body_trajectory_and_violation(mixed, tmp_path):
    """The stored motion of the hinge (body 2) made to wobble off its axis in trajectory 1 by 1e-3 rad."""
    ds, src = mixed
    axis = np.asarray(ds.tree.axes[2][0])
    off = _unit(np.cross(axis, [0.0, 0.0, 1.0]))

    def wobble(f):
        R = f["R"][()]  # world rotations: turning body 2's world attitude turns its R_rel as much
        R[1, 7:, 2] = R[1, 7:, 2] @ _exp(1e-3 * off).numpy()
        f["R"][...] = R

    with pytest.raises(DatasetError) as e:
        load_dataset(_edited(src, tmp_path, wobble))
    msg = str(e.value)
    assert "body 2 (link2) is declared a hinge joint but trajectory 1 violates it by 0.001 rad (> 1e-06)" in msg
    assert str(src.name) != msg and "edited.h5" in msg and "\n" not in msg

    # 1e-8 rad of wobble (float rounding of a careful recording) is accepted
    def tiny(f):
        R = f["R"][()]
        R[1, 7:, 2] = R[1, 7:, 2] @ _exp(1e-8 * off).numpy()
        f["R"][...] = R

    load_dataset(_edited(src, tmp_path, tiny))


def test_a_weld_that_moves_and_a_universal_that_bends_are_refused(mixed, tmp_path):
    ds, src = mixed

    def turn(body, angle):
        def edit(f):
            R = f["R"][()]
            R[2, 3:, body] = R[2, 3:, body] @ _exp(angle * _unit([1.0, 2.0, 3.0])).numpy()
            f["R"][...] = R

        return edit

    with pytest.raises(DatasetError, match=r"body 4 \(link4\) is declared a weld joint but trajectory 2 violates"):
        load_dataset(_edited(src, tmp_path, turn(4, 1e-4)))
    with pytest.raises(DatasetError, match=r"body 3 \(link3\) is declared a universal joint but trajectory 2"):
        load_dataset(_edited(src, tmp_path, turn(3, 1e-2)))
