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
