"""HDF5 dataset format: round trip, atomic writes, validation errors, projection, caching, configs."""

from __future__ import annotations

import copy
import json
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from liedfl_cli.data import (
    SCENES,
    ConfigError,
    Dataset,
    DatasetError,
    config_hash,
    dataset_path,
    generate,
    get_dataset,
    load_dataset,
    save_dataset,
)
from liedfl_cli.data import scenes as scenes_mod
from liedfl_cli.data.files import SOURCE_SCENES
from liedfl_cli.data.mocap import REAL_DATA_SCENES
from liedfl_cli.lie import so3
from liedfl_cli.lie.product import ProductGroup
from liedfl_cli.lie.tree import Tree

CONF = Path(__file__).resolve().parents[1] / "liedfl_cli" / "conf" / "dataset"


def yaml_cfg(name: str) -> dict:
    c = OmegaConf.to_container(OmegaConf.load(CONF / f"{name}.yaml"))
    c.pop("defaults", None)  # Hydra's defaults list (selects the group), not a generator field
    return c


SIMULATED = sorted(set(SCENES) - set(REAL_DATA_SCENES) - set(SOURCE_SCENES))  # (file/import: test_own_data.py)


def tiny(name: str, **over) -> dict:
    c = yaml_cfg(name)
    c.update(n_trajectories=6, steps=6, train_steps=4, rollout_steps=6, n_test=None)
    c.update(over)
    return c


def smooth_rotations(shape, g: torch.Generator, step: float = 0.3) -> torch.Tensor:
    """(T, N+1, B, 3, 3): R_0 Haar-random, R_(k+1) = R_k exp(step * N(0, I))."""
    T, N1, B = shape
    R = [so3.random((T, B), generator=g)]
    for _ in range(N1 - 1):
        xi = step * torch.randn(T, B, 3, generator=g, dtype=torch.float64)
        R.append(R[-1] @ so3.exp(xi))
    return torch.stack(R, 1)


def multibody(T=5, N=4, seed=0) -> Dataset:
    """A hand-made SE(3) x SO(3)^2 dataset (random data, not physics): random initial attitudes, random
    per-step turns of about 0.3 rad (well-sampled motion: the load-time check rejects steps near pi)."""
    g = torch.Generator().manual_seed(seed)
    R = smooth_rotations((T, N + 1, 3), g).numpy()
    p = torch.randn(T, N + 1, 1, 3, generator=g, dtype=torch.float64).numpy()
    return Dataset(
        R=R,
        p=p,
        h=0.01,
        scene="custom",
        body_names=["root", "arm", "hand"],
        body_kinds=["se3", "so3", "so3"],
        params={"source": "test", "nested": {"a": [1, 2.5]}},
        seed=7,
        split={"train": np.array([0, 2, 3]), "test": np.array([1, 4])},
        extras={"omega": np.ones((T, N + 1, 3, 3)), "torque": np.zeros((T, N, 3, 3), np.float32)},
    )


@pytest.fixture
def saved(tmp_path):
    path = tmp_path / "data" / "ds.h5"
    save_dataset(multibody(), path)
    return path


def assert_same(a: Dataset, b: Dataset):
    for name in ("R", "p", "t"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert getattr(a, name).dtype == getattr(b, name).dtype
    assert (a.h, a.scene, a.body_names, a.body_kinds, a.params, a.seed) == (
        b.h,
        b.scene,
        b.body_names,
        b.body_kinds,
        b.params,
        b.seed,
    )
    assert a.split.keys() == b.split.keys()
    for k in a.split:
        np.testing.assert_array_equal(a.split[k], b.split[k])
    assert a.tree == b.tree
    assert a.extras.keys() == b.extras.keys()
    for k in a.extras:
        np.testing.assert_array_equal(a.extras[k], b.extras[k])
        assert a.extras[k].dtype == b.extras[k].dtype


# ------------------------------------------------------------------ round trip, atomicity
def test_round_trip_multibody_exact(saved):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = load_dataset(saved)
    assert_same(multibody(), back)
    assert back.group == ProductGroup(1, 2)
    assert (back.n_trajectories, back.n_steps) == (5, 4)
    with h5py.File(saved) as f:
        assert f.attrs["format_version"] == 1 and f.attrs["n_se3"] == 1 and f.attrs["n_so3"] == 2
        assert json.loads(f.attrs["body_kinds"]) == ["se3", "so3", "so3"]
        assert {"liedfl_version", "created", "params", "seed", "scene", "h"} <= set(f.attrs)


@pytest.mark.parametrize("rotations", ["world", "parent"])
def test_round_trip_with_tree_exact(tmp_path, rotations):
    """The optional tree fields (attributes parents, rotations; dataset joint_offsets) round-trip."""
    ds = multibody()
    ds.tree = Tree.from_lists([-1, 0, 0], [[0, 0, 0], [0.1, 0.2, 0.3], [-0.5, 0.0, 0.25]], rotations, free_root=True)
    path = save_dataset(ds, tmp_path / "tree.h5")
    back = load_dataset(path)
    assert_same(ds, back)
    assert back.tree is not None and back.tree.offsets[2] == (-0.5, 0.0, 0.25)
    with h5py.File(path) as f:
        assert json.loads(f.attrs["parents"]) == [-1, 0, 0] and f.attrs["rotations"] == rotations
    assert load_dataset(save_dataset(multibody(), tmp_path / "plain.h5")).tree is None


@pytest.mark.parametrize("name", SIMULATED)
def test_round_trip_generated_exact(tmp_path, name):
    ds = generate(tiny(name))
    path = save_dataset(ds, tmp_path / f"{name}.h5")
    assert_same(ds, load_dataset(path))


def test_atomic_write_leaves_no_tmp_and_keeps_old_file_on_failure(saved):
    assert not list(saved.parent.glob("*.tmp*"))
    assert sorted(p.name for p in saved.parent.iterdir()) == ["ds.h5"]
    bad = multibody(seed=1)
    bad.extras["obj"] = np.array([{"a": 1}] * 5, dtype=object)  # h5py cannot store object arrays
    with pytest.raises(TypeError):
        save_dataset(bad, saved)
    assert sorted(p.name for p in saved.parent.iterdir()) == ["ds.h5"]
    assert_same(multibody(), load_dataset(saved))


def test_pose_and_properties():
    ds = multibody()
    g = ds.pose()
    assert g.R.shape == (5, 5, 3, 3, 3) and g.p.shape == (5, 5, 1, 3) and g.R.dtype == torch.float64
    g1 = ds.pose(2, dtype=torch.float32)
    assert g1.R.shape == (5, 3, 3, 3) and g1.R.dtype == torch.float32
    gt = ds.pose("test")
    assert gt.R.shape[0] == 2
    torch.testing.assert_close(gt.R, torch.from_numpy(ds.R[[1, 4]]))
    ds.group.check(g)


# ------------------------------------------------------------------ validation errors
def edit(path, fn):
    with h5py.File(path, "r+") as f:
        fn(f)


def replace(f, name, data):
    del f[name]
    f.create_dataset(name, data=data)


def expect_error(path, *fragments):
    with pytest.raises(DatasetError) as info:
        load_dataset(path)
    msg = str(info.value)
    assert msg.startswith(str(path)), msg
    assert "\n" not in msg
    for frag in fragments:
        assert frag in msg, msg
    return msg


def test_missing_dataset(saved):
    edit(saved, lambda f: f.__delitem__("R"))
    expect_error(saved, "'R'", "missing")


def test_missing_positions_for_se3(saved):
    edit(saved, lambda f: f.__delitem__("p"))
    expect_error(saved, "'p'", "missing")


def test_missing_attribute(saved):
    edit(saved, lambda f: f.attrs.__delitem__("h"))
    expect_error(saved, "'h'", "missing")


def test_wrong_shape_R(saved):
    edit(saved, lambda f: replace(f, "R", f["R"][:, :, :2]))
    expect_error(saved, "'R'", "shape")


def test_wrong_shape_p(saved):
    edit(saved, lambda f: replace(f, "p", f["p"][:, :-1]))
    expect_error(saved, "'p'", "shape")


def test_wrong_length_t(saved):
    edit(saved, lambda f: replace(f, "t", f["t"][:-1]))
    expect_error(saved, "'t'", "shape")


def test_nan_reports_first_index(saved):
    def put_nan(f):
        R = f["R"][()]
        R[3, 2, 1, 0, 2] = np.nan
        R[4, 0, 0, 0, 0] = np.inf
        replace(f, "R", R)

    edit(saved, put_nan)
    expect_error(saved, "'R'", "non-finite", "(3, 2, 1, 0, 2)")


def test_nan_in_positions(saved):
    def put_nan(f):
        p = f["p"][()]
        p[1, 3, 0, 1] = np.nan
        replace(f, "p", p)

    edit(saved, put_nan)
    expect_error(saved, "'p'", "(1, 3, 0, 1)")


def test_gross_non_rotation(saved):
    def scale(f):
        R = f["R"][()]
        R[2, 1, 2] *= 1.1
        replace(f, "R", R)

    edit(saved, scale)
    expect_error(saved, "'R'", "not a rotation", "(2, 1, 2)")


def test_reflection_rejected(saved):
    def reflect(f):
        R = f["R"][()]
        R[0, 3, 1] = -R[0, 3, 1]  # orthogonal, det = -1
        replace(f, "R", R)

    edit(saved, reflect)
    expect_error(saved, "'R'", "(0, 3, 1)", "det R = -1")


def test_overlapping_split(saved):
    edit(saved, lambda f: replace(f, "split/test", np.array([1, 2])))
    expect_error(saved, "'split/test'", "2", "disjoint")


def test_split_out_of_range(saved):
    edit(saved, lambda f: replace(f, "split/train", np.array([0, 2, 9])))
    expect_error(saved, "'split/train'", "9", "position 2")


def test_not_hdf5(tmp_path):
    path = tmp_path / "fake.h5"
    path.write_text("R,p\n1,2\n")
    expect_error(path, "not an HDF5 file")


def test_missing_file(tmp_path):
    expect_error(tmp_path / "nope.h5", "does not exist")


def test_bad_body_kinds(saved):
    edit(saved, lambda f: f.attrs.__setitem__("body_kinds", json.dumps(["so3", "se3", "so3"])))
    expect_error(saved, "'body_kinds'")


def test_save_refuses_invalid_dataset(tmp_path):
    ds = multibody()
    ds.split["test"] = np.array([0])
    with pytest.raises(DatasetError, match="disjoint"):
        save_dataset(ds, tmp_path / "x.h5")
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------ projection of slightly-off rotations
def test_slightly_off_rotations_projected_with_one_warning(saved):
    rng = np.random.default_rng(0)
    spots = [(0, 0, 0), (1, 2, 1), (4, 4, 2)]

    def nudge(f):
        R = f["R"][()]
        for s in spots:
            R[s] += 1e-7 * rng.standard_normal((3, 3))
        replace(f, "R", R)

    edit(saved, nudge)
    with pytest.warns(UserWarning) as rec:
        ds = load_dataset(saved)
    msgs = [str(w.message) for w in rec if issubclass(w.category, UserWarning)]
    assert len(msgs) == 1 and "projected 3 of 75" in msgs[0] and str(saved) in msgs[0]
    err = so3.orthogonality_error(torch.from_numpy(ds.R))
    assert err.max() < 1e-13
    ref = multibody().R
    mask = np.ones(ref.shape[:3], bool)
    for s in spots:
        mask[s] = False
        np.testing.assert_allclose(ds.R[s], ref[s], atol=1e-6)
    np.testing.assert_array_equal(ds.R[mask], ref[mask])  # untouched rotations stay bit-exact


def test_user_written_minimal_float32_file(tmp_path):
    """The minimal file of docs/data_format.md: R, p, h, body_kinds; float32 uses the float32 tolerances."""
    path = tmp_path / "mine.h5"
    R = smooth_rotations((3, 10, 1), torch.Generator().manual_seed(1)).numpy().astype(np.float32)
    p = np.random.default_rng(0).standard_normal((3, 10, 1, 3)).astype(np.float32)
    with h5py.File(path, "w") as f:
        f.attrs["format_version"] = 1
        f.attrs["h"] = 1 / 120
        f.attrs["body_kinds"] = json.dumps(["se3"])
        f.create_dataset("R", data=R)
        f.create_dataset("p", data=p)
    with pytest.raises(DatasetError, match="group 'split' is missing"):  # training needs a split
        load_dataset(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # float32 rounding is below the float32 warn tolerance
        ds = load_dataset(path, require_split=False)
    assert ds.R.dtype == np.float64 and ds.scene == "mine" and ds.body_names == ["body0"]
    np.testing.assert_array_equal(ds.split["train"], np.arange(3))
    assert ds.split["test"].size == 0
    np.testing.assert_allclose(ds.t, np.arange(10) / 120)


# ------------------------------------------------------------------ generation, splits, caching
def test_split_sizes_and_determinism():
    a = generate(tiny("free_rigid_body", n_trajectories=12, n_test=3))
    assert a.split["test"].size == 3 and a.split["train"].size == 9
    assert np.intersect1d(a.split["test"], a.split["train"]).size == 0
    b = generate(tiny("heavy_so3", n_trajectories=20, test_fraction=0.1))
    assert b.split["test"].size == 2
    np.testing.assert_array_equal(a.R, generate(tiny("free_rigid_body", n_trajectories=12, n_test=3)).R)


def test_generated_layout_and_extras():
    ds = generate(tiny("heavy_se3"))
    T, N1 = 6, 7
    assert ds.R.shape == (T, N1, 1, 3, 3) and ds.p.shape == (T, N1, 1, 3) and ds.body_kinds == ["se3"]
    assert ds.extras["omega"].shape == (T, N1, 1, 3) and ds.extras["v"].shape == (T, N1, 1, 3)
    np.testing.assert_allclose(ds.t, 0.05 * np.arange(N1))
    ds3 = generate(tiny("heavy_so3"))
    assert ds3.p.shape == (T, N1, 0, 3) and ds3.extras["v"].shape == (T, N1, 0, 3)
    np.testing.assert_allclose(ds3.R[:, 0, 0], np.broadcast_to(np.eye(3), (T, 3, 3)))  # R0 = I


def test_get_dataset_caches(tmp_path, monkeypatch):
    cfg = tiny("heavy_so3")
    ds1, path1 = get_dataset(cfg, tmp_path)
    assert path1 == tmp_path / f"heavy_so3-{config_hash(cfg)}.h5" and path1.exists()
    assert len(config_hash(cfg)) == 10
    mtime = path1.stat().st_mtime_ns

    def boom(*a, **k):
        raise AssertionError("should have loaded from the cache")

    monkeypatch.setitem(SCENES, "heavy_so3", boom)
    ds2, path2 = get_dataset(OmegaConf.create(cfg), tmp_path)  # DictConfig gives the same hash
    assert path2 == path1 and path1.stat().st_mtime_ns == mtime
    assert_same(ds1, ds2)
    # train/rollout lengths do not change the data, so they share the file
    assert get_dataset(dict(cfg, train_steps=2), tmp_path)[1] == path1
    # 1 and 1.0 hash alike
    c_int = copy.deepcopy(cfg)
    c_int["initial"]["omega_scale"] = 1
    assert config_hash(c_int) == config_hash(cfg)
    monkeypatch.undo()
    _, path3 = get_dataset(dict(cfg, seed=1), tmp_path)
    assert path3 != path1 and path3.exists()
    c_phys = copy.deepcopy(cfg)
    c_phys["physics"]["D"] = [0.2, 0.1, 0.1]
    assert dataset_path(c_phys, tmp_path) not in (path1, path3)


def test_get_dataset_rejects_bad_config(tmp_path):
    with pytest.raises(ConfigError, match="not a registered scene"):
        get_dataset(dict(tiny("heavy_so3"), name="nope"), tmp_path)
    with pytest.raises(ConfigError, match="shorter than"):
        get_dataset(tiny("heavy_so3", rollout_steps=50), tmp_path)
    bad = tiny("heavy_se3")
    bad["physics"]["D"] = [0.1, 0.1, 0.1]
    with pytest.raises(ConfigError, match="physics.D"):
        get_dataset(bad, tmp_path)
    with pytest.raises(ConfigError, match="missing"):
        get_dataset({k: v for k, v in tiny("heavy_so3").items() if k != "seed"}, tmp_path)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("name", SIMULATED)
def test_yaml_configs_match_registry_and_fields(name):
    c = yaml_cfg(name)
    assert c["name"] == name
    assert list(c)[: len(scenes_mod.REQUIRED_KEYS)] == list(scenes_mod.REQUIRED_KEYS)
    assert set(c["physics"]) == {"J", "m", "rho", "g", "D"} and set(c["solver"]) == {"method", "rtol", "atol"}
    assert c["steps"] == max(c["train_steps"], c["rollout_steps"])
    assert isinstance(c["solver"]["rtol"], float) and c["solver"]["rtol"] == 1e-10
    # every scene has its file; `file` (a user's dataset file, not generated) is the one extra option
    assert {p.stem for p in CONF.glob("*.yaml")} == set(SCENES) | {scenes_mod.FILE_SCENE}
