"""Declared physics is validated at load (issue 18, item 5): a file whose `params.physics` is malformed
(either schema), whose `params` is not a JSON object or whose `seed` is not an integer fails in
`load_dataset` with one line naming the field (and the body), before anything is trained; a generated
scene's `dataset.physics.*` overrides get the same checks (`data/checks.py::check_physics`)."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
from own_data import motion, write_h5
from test_cli import FAST

from liedfl_cli.data.hdf5 import Dataset, load_dataset, save_dataset
from liedfl_cli.errors import ConfigError, DatasetError
from liedfl_cli.lie.tree import Tree

GOOD = {"J": [1.0, 2.0, 2.5], "m": 0.5, "rho": [0.0, 0.0, 0.1], "g": 9.81, "D": [0.1] * 6}
BOX = [[2.0, 0.1, 0.0], [0.1, 2.5, 0.0], [0.0, 0.0, 3.0]]
ARTICULATED = {
    "kind": "articulated",
    "g": 9.81,
    "bodies": [{"name": f"l{b}", "mass": 1.5, "com": [0.0, 0.0, 0.2], "inertia": BOX} for b in range(2)],
    "joint_damping": [0.1],
    "root_damping": 0.0,
}


def _set(path: Path, **attrs) -> Path:
    with h5py.File(path, "r+") as f:
        for k, v in attrs.items():
            f.attrs[k] = v
    return path


def _rigid(path: Path, physics) -> Path:
    """The SE(3) recording of own_data (one body, dim 6) declaring `physics`."""
    return _set(write_h5(path), params=json.dumps({"physics": physics}))


def _chain(path: Path, physics, tree: bool = True) -> Path:
    """Two SO(3) bodies (a pinned chain when `tree`) declaring `physics`."""
    _, R0, _ = motion(4, 21, seed=0)
    _, R1, _ = motion(4, 21, seed=1)
    ds = Dataset(
        R=np.stack([R0, R1], axis=2),
        p=np.zeros((4, 21, 0, 3)),
        h=0.05,
        scene="chain",
        body_names=["l0", "l1"],
        body_kinds=["so3", "so3"],
        params={"physics": physics},
        split={"train": np.arange(1, 4), "test": np.array([0])},
        tree=Tree.from_lists([-1, 0], np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.4]]), "world", False) if tree else None,
    )
    return save_dataset(ds, path)


def _edit(physics: dict, **changes) -> dict:
    out = json.loads(json.dumps(physics))
    for k, v in changes.items():
        out[k] = v
    return out


def _body(b: int, **changes) -> dict:
    out = json.loads(json.dumps(ARTICULATED))
    out["bodies"][b].update(changes)
    return out


RIGID_BAD = [
    ("J-string", _edit(GOOD, J="heavy"), "params.physics.J must be a number"),
    ("J-triangle", _edit(GOOD, J=[1, 1, 5]), "params.physics.J violates the triangle inequality"),
    ("J-not-positive", _edit(GOOD, J=[1, 0, 1]), "params.physics.J must be positive definite"),
    ("J-shape", _edit(GOOD, J=[1, 2]), "params.physics.J has shape (2,)"),
    ("J-missing", {k: v for k, v in GOOD.items() if k != "J"}, "params.physics.J is missing"),
    ("m-negative", _edit(GOOD, m=-1), "params.physics.m must be positive"),
    ("m-count", _edit(GOOD, m=[1, 2]), "params.physics.m has shape (2,)"),
    ("rho-shape", _edit(GOOD, rho=[0, 1]), "params.physics.rho has shape (2,)"),
    ("g-text", _edit(GOOD, g="down"), "params.physics.g must be a number"),
    ("D-size", _edit(GOOD, D=[0.1, 0.1, 0.1]), "params.physics.D has shape (3,); expected (6,) or (6, 6)"),
    ("D-negative", _edit(GOOD, D=[0.1, -0.1, 0, 0, 0, 0]), "params.physics.D must be non-negative"),
    ("D-not-psd", _edit(GOOD, D=(np.eye(6) - 2 * np.eye(6)[::-1]).tolist()), "params.physics.D must be positive semi"),
    ("D-nan", _edit(GOOD, D=[float("nan")] * 6), "params.physics.D has a non-finite value"),
    ("interaction-bodies", _edit(GOOD, interaction={"kind": "gravity", "mu": 1.0}), "interaction.bodies must be 2"),
    ("control-R_f", _edit(GOOD, control={"R_f": [0, 1], "K_R": 1, "K_w": 1}), "params.physics.control.R_f must be"),
    ("kind-unknown", _edit(GOOD, kind="soft"), "params.physics.kind is 'soft'"),
    ("not-an-object", [1, 2, 3], "params.physics must be a JSON object"),
]
ARTICULATED_BAD = [
    ("mass-zero", _body(1, mass=0.0), "params.physics.bodies[1].mass must be one positive number"),
    ("com-size", _body(0, com=[0, 0]), "params.physics.bodies[0].com must be 3 numbers"),
    ("inertia-shape", _body(1, inertia=[1, 1, 1]), "params.physics.bodies[1].inertia has shape (3,)"),
    ("inertia-asymmetric", _body(1, inertia=[[2, 1, 0], [0, 2, 0], [0, 0, 3]]), "bodies[1].inertia must be symmetric"),
    ("inertia-indefinite", _body(0, inertia=np.diag([1, -1, 1]).tolist()), "bodies[0].inertia must be positive def"),
    ("inertia-triangle", _body(1, inertia=np.diag([1, 1, 5]).tolist()), "bodies[1].inertia violates the triangle"),
    ("inertia-text", _body(1, inertia="I"), "params.physics.bodies[1].inertia must be a number"),
    ("body-missing-key", _body(0, mass=None), "params.physics.bodies[0].mass must be a number"),
    ("bodies-count", _edit(ARTICULATED, bodies=ARTICULATED["bodies"][:1]), "params.physics.bodies must list 2"),
    ("joint-damping-count", _edit(ARTICULATED, joint_damping=[0.1, 0.2]), "joint_damping must have 1 entries"),
    (
        "joint-damping-negative",
        _edit(ARTICULATED, joint_damping=[-0.1]),
        "params.physics.joint_damping[0] must be >= 0",
    ),
    ("root-damping-negative", _edit(ARTICULATED, root_damping=-1), "params.physics.root_damping must be >= 0"),
]


def _one_line(exc: pytest.ExceptionInfo, path: Path, needle: str) -> None:
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith(f"{path}: "), msg
    assert needle in msg, msg


@pytest.mark.parametrize("physics,needle", [c[1:] for c in RIGID_BAD], ids=[c[0] for c in RIGID_BAD])
def test_per_body_physics_is_checked_at_load(tmp_path, physics, needle):
    path = _rigid(tmp_path / "bad.h5", physics)
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    _one_line(exc, path, needle)


@pytest.mark.parametrize("physics,needle", [c[1:] for c in ARTICULATED_BAD], ids=[c[0] for c in ARTICULATED_BAD])
def test_articulated_physics_is_checked_at_load(tmp_path, physics, needle):
    path = _chain(tmp_path / "bad.h5", physics)
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    _one_line(exc, path, needle)


def test_articulated_physics_needs_the_files_tree(tmp_path):
    path = _chain(tmp_path / "bad.h5", ARTICULATED, tree=False)
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    _one_line(exc, path, "params.physics.kind is 'articulated' but the file has no kinematic tree")


def test_well_formed_physics_loads(tmp_path):
    assert load_dataset(_rigid(tmp_path / "a.h5", GOOD)).params["physics"] == GOOD
    full = _edit(GOOD, J=BOX, D=np.diag([0.1] * 6).tolist(), m=[2.0], rho=[[0, 0, 0.1]])
    assert load_dataset(_rigid(tmp_path / "b.h5", full)).params["physics"] == full
    assert load_dataset(_chain(tmp_path / "c.h5", ARTICULATED)).params["physics"]["kind"] == "articulated"
    assert load_dataset(_chain(tmp_path / "d.h5", _edit(ARTICULATED, joint_damping=None))).tree is not None


@pytest.mark.parametrize(
    "attrs,needle",
    [
        ({"params": json.dumps([1, 2])}, "attribute 'params' must be a JSON object, got a JSON list"),
        ({"params": json.dumps("x")}, "attribute 'params' must be a JSON object, got a JSON str"),
        ({"seed": "abc"}, "attribute 'seed' must be an integer, got 'abc'"),
        ({"seed": 1.5}, "attribute 'seed' must be an integer, got 1.5"),
        ({"seed": True}, "attribute 'seed' must be an integer"),
    ],
    ids=["params-list", "params-string", "seed-text", "seed-float", "seed-bool"],
)
def test_params_and_seed_are_checked_at_load(tmp_path, attrs, needle):
    path = _set(write_h5(tmp_path / "bad.h5"), **attrs)
    with pytest.raises(DatasetError) as exc:
        load_dataset(path)
    _one_line(exc, path, needle)


def test_an_integral_float_seed_loads(tmp_path):
    assert load_dataset(_set(write_h5(tmp_path / "a.h5"), seed=3.0)).seed == 3


def test_the_scene_config_check_shares_the_rules():
    from liedfl_cli.data.checks import check_physics

    with pytest.raises(ConfigError, match=r"^dataset\.physics\.J violates the triangle inequality"):
        check_physics({"J": [1, 1, 5]}, 1, 3, prefix="dataset.physics", error=ConfigError)


@pytest.fixture
def liedfl(run_main):
    """The command run in-process (`run_main`): these tests are about the check, not the process."""
    return run_main


def _no_run(cwd: Path) -> None:
    runs = cwd / "outputs" / "runs"
    assert not runs.exists() or not any(p.is_file() for p in runs.rglob("*")), sorted(runs.rglob("*"))


@pytest.mark.parametrize(
    "make,needle",
    [
        (lambda p: _rigid(p, _edit(GOOD, J="heavy")), "params.physics.J must be a number"),
        (lambda p: _chain(p, _body(1, inertia=np.diag([1, 1, 5]).tolist())), "bodies[1].inertia violates the"),
        (lambda p: _set(write_h5(p), params=json.dumps([1])), "attribute 'params' must be a JSON object"),
        (lambda p: _set(write_h5(p), seed="abc"), "attribute 'seed' must be an integer"),
    ],
    ids=["J-string", "articulated-triangle", "params-list", "seed-text"],
)
def test_train_on_a_bad_file_stops_in_one_line_before_training(tmp_path, make, needle, liedfl):
    make(tmp_path / "bad.h5")
    proc = liedfl("train", "dataset=file", "dataset.path=bad.h5", *FAST, "runtime.threads=1", cwd=tmp_path, ok=False)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert lines[0].startswith("error: ") and "bad.h5: " in lines[0] and needle in lines[0], lines[0]
    _no_run(tmp_path)


def test_a_non_physical_inertia_override_stops_before_generation(tmp_path, liedfl):
    proc = liedfl("train", *FAST, "runtime.threads=1", "dataset.physics.J=[1,1,5]", cwd=tmp_path, ok=False)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "dataset.physics.J violates the triangle inequality" in lines[0], lines[0]
    assert not (tmp_path / "outputs" / "data").exists() or not any((tmp_path / "outputs" / "data").glob("*.h5"))
    _no_run(tmp_path)
