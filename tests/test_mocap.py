"""Motion-capture import (scene cmu_cartwheel), Savitzky–Golay smoothing on SO(3), mocap metrics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation

from liedfl_cli.data import ConfigError, Dataset, DatasetError, config_hash, get_dataset, load_dataset, save_dataset
from liedfl_cli.data.bvh import read_bvh
from liedfl_cli.data.mocap import (
    ASF_UNIT_M,
    CMU_BODY_JOINTS,
    MOCAP_DIR,
    Z_UP,
    cmu_cartwheel,
    mocap_errors,
    moving_joints,
    recording_discrepancy,
    skeleton_points,
)
from liedfl_cli.data.smoothing import check_window, savgol_positions, savgol_rotations, savgol_table, smooth_pose
from liedfl_cli.lie import so3
from liedfl_cli.lie.product import Pose
from liedfl_cli.lie.tree import forward_kinematics

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "liedfl_cli" / "conf" / "dataset" / "cmu_cartwheel.yaml"


def cfg(**over) -> dict:
    """The scene's config as the CLI composes it: interpolations resolved (n_trajectories follows
    `files`, also when `over` replaces them), Hydra's defaults list dropped."""
    raw = OmegaConf.load(CONF)
    raw.pop("defaults", None)  # Hydra's defaults list (selects the group), consumed by composition
    if "files" in over:
        raw.files = over["files"]
    c = OmegaConf.to_container(raw, resolve=True)
    c.update(over)
    return c


def on_so3(R: np.ndarray, tol=1e-12):
    E = np.swapaxes(R, -1, -2) @ R - np.eye(3)
    assert np.sqrt((E * E).sum((-1, -2))).max() < tol
    assert np.abs(np.linalg.det(R) - 1.0).max() < tol


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    data_dir = tmp_path_factory.mktemp("data")
    ds, path = get_dataset(cfg(), data_dir)
    return ds, path


# ---------------------------------------------------------------------- smoothing
def test_savgol_positions_match_scipy_and_reproduce_polynomials():
    x = np.random.default_rng(0).standard_normal((150, 2, 3))
    np.testing.assert_allclose(
        savgol_positions(x, 51, 6), savgol_filter(x, 51, 6, axis=0, mode="interp"), atol=1e-6
    )  # scipy's own coefficients are only ~1e-7 accurate here
    t = np.linspace(-1.0, 2.0, 120)
    y = 3 * t**6 - t**3 + 2 * t - 1
    np.testing.assert_allclose(savgol_positions(y, 51, 6), y, atol=1e-11)
    T = savgol_table(51, 6)
    np.testing.assert_allclose(T.sum(1), 1.0, atol=1e-13)


def test_window_checks():
    with pytest.raises(ValueError, match="must be odd.*use 51"):
        check_window(50, 6)
    with pytest.raises(ValueError, match="order"):
        check_window(5, 5)
    with pytest.raises(ValueError, match="longer than the track"):
        savgol_positions(np.zeros(10), 11, 2)


def rotation_track(n=480, h=1 / 120, turns=3.0):
    """A smooth track turning `turns` full times about a slowly moving axis with varying speed."""
    t = h * np.arange(n)
    T = t[-1]
    yaw = 2 * np.pi * turns * (t / T) ** 2
    pitch = 0.6 * np.sin(2 * np.pi * t / T)
    roll = 0.4 * np.cos(3 * np.pi * t / T)
    return Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], -1)).as_matrix()


def test_smoothing_keeps_rotations_on_so3_through_full_turns():
    R = rotation_track()
    Rs = savgol_rotations(R, 51, 6)
    on_so3(Rs)
    d = so3.geodesic_distance(torch.from_numpy(Rs), torch.from_numpy(R)).numpy()
    assert d.max() < 1e-5  # a clean smooth track (3 full turns) is left almost unchanged
    # noise is reduced
    rng = np.random.default_rng(1)
    noisy = R @ so3.exp(torch.from_numpy(0.02 * rng.standard_normal((len(R), 3)))).numpy()
    dn = so3.geodesic_distance(torch.from_numpy(savgol_rotations(noisy, 51, 6)), torch.from_numpy(R)).numpy()
    d0 = so3.geodesic_distance(torch.from_numpy(noisy), torch.from_numpy(R)).numpy()
    assert dn.mean() < 0.45 * d0.mean()  # white-noise gain of the 51/6 filter is about 0.37


def test_smoothing_leaves_uniform_rotation_unchanged_and_is_equivariant():
    w = np.array([3.0, -2.0, 5.0])  # 6.2 rad/s: a full turn per second
    R = so3.exp(torch.from_numpy(w * np.arange(300)[:, None] / 120)).numpy()
    np.testing.assert_allclose(savgol_rotations(R, 51, 6), R, atol=1e-12)
    R = rotation_track(200)
    Q, P = Rotation.random(2, random_state=3).as_matrix()
    np.testing.assert_allclose(savgol_rotations(Q @ R @ P, 31, 4), Q @ savgol_rotations(R, 31, 4) @ P, atol=1e-12)


def test_smoothing_rejects_too_fast_rotations():
    R = so3.exp(torch.from_numpy(np.array([0.0, 0.0, 0.5]) * np.arange(100)[:, None])).numpy()
    with pytest.raises(ValueError, match="shorter window"):
        savgol_rotations(R, 21, 2)


def test_smoothing_real_recording_stays_on_so3():
    b = read_bvh(MOCAP_DIR / "49_07.bvh")
    names = ["Hips", *CMU_BODY_JOINTS]
    R = b.local_rotations([b.names.index(n) for n in names])[1:]
    Rs, ps = smooth_pose(R, b.local_translations([0])[1:], 51, 6)
    on_so3(Rs)
    assert ps.shape == (471, 1, 3)
    d = so3.geodesic_distance(torch.from_numpy(Rs), torch.from_numpy(R)).numpy()
    assert d.mean() < 0.02 and d.max() < 0.3


# ---------------------------------------------------------------------- metrics
def test_mocap_errors():
    g = torch.Generator().manual_seed(0)
    R = so3.random((3, 7, 4), generator=g)
    p = torch.randn(3, 7, 1, 3, generator=g, dtype=torch.float64)
    e = mocap_errors(Pose(R, p), Pose(R, p))
    assert all(float(v.abs().max()) == 0.0 for v in e.values())
    off = so3.exp(torch.tensor([0.0, 0.3, 0.0], dtype=torch.float64))
    R2 = R.clone()
    R2[..., 0, :, :] = R[..., 0, :, :] @ off
    R2[..., 2, :, :] = R[..., 2, :, :] @ off
    p2 = p + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    e = mocap_errors(Pose(R2, p2), Pose(R, p))
    assert e["root_rot"].shape == (3,) and e["root_rot_t"].shape == (3, 7) and e["joint_rot_per_joint"].shape == (3, 3)
    torch.testing.assert_close(e["root_rot"], torch.full((3,), 0.3, dtype=torch.float64))
    torch.testing.assert_close(e["joint_rot"], torch.full((3,), 0.1, dtype=torch.float64))
    torch.testing.assert_close(e["root_pos"], torch.full((3,), 2.0, dtype=torch.float64))
    e = mocap_errors(Pose(R2, p2), Pose(R, p), relative_position=True)
    torch.testing.assert_close(e["root_pos"], torch.zeros(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="shapes differ"):
        mocap_errors(Pose(R, p), Pose(R[:, :5], p[:, :5]))


# ---------------------------------------------------------------------- the scene
def test_cmu_cartwheel_dataset(imported):
    ds, path = imported
    assert path.name == f"cmu_cartwheel-{config_hash(cfg())}.h5"
    assert (ds.n_se3, ds.n_so3, ds.group.name) == (1, 22, "SE(3) x SO(3)^22")
    assert ds.body_names == ["Hips", *CMU_BODY_JOINTS] and ds.body_kinds == ["se3"] + ["so3"] * 22
    assert ds.R.shape == (2, 471, 23, 3, 3) and ds.p.shape == (2, 471, 1, 3)
    assert ds.h == pytest.approx(0.0083333)
    assert list(ds.train_idx) == [0, 1] and list(ds.test_idx) == [0, 1] and ds.params["split_overlap"] is True
    on_so3(ds.R)
    on_so3(ds.extras["R_raw"])
    src = ds.params["sources"]
    assert [s["frames_in_file"] for s in src] == [482, 472]
    assert [s["frames_after_skip"] for s in src] == [481, 471] and [s["frames_used"] for s in src] == [471, 471]
    assert ds.params["length_unit_m"] == pytest.approx(ASF_UNIT_M)
    assert ds.params["bodies"]["asf_names"][:3] == ["root", "lhipjoint", "lfemur"]
    assert "mocap.cs.cmu.edu" in ds.params["attribution"]


def test_t_pose_dropped_and_frames_converted(imported):
    """Raw sample 0 is the second motion line of 49_06 (the T-pose is skipped), turned to z up."""
    ds, _ = imported
    np.testing.assert_allclose(ds.extras["p_raw"][0, 0, 0], Z_UP @ [-2.4510, 16.5423, 42.9005], atol=1e-12)
    R_root = Rotation.from_euler("ZYX", [-175.2660, -6.5192, -165.3560], degrees=True).as_matrix()
    np.testing.assert_allclose(ds.extras["R_raw"][0, 0, 0], Z_UP @ R_root, atol=1e-12)
    j = ds.body_names.index("LeftUpLeg")  # channels 10-12 of the second motion line
    np.testing.assert_allclose(
        ds.extras["R_raw"][0, 0, j],
        Rotation.from_euler("ZYX", [-12.1131, -20.6462, -27.7235], degrees=True).as_matrix(),
        atol=1e-12,
    )
    assert ds.extras["p_raw"][0, 0, 0, 2] == pytest.approx(16.5423)  # hip height: z is up


def test_round_trip_and_cache(imported, tmp_path):
    ds, path = imported
    again, path2 = get_dataset(cfg(), path.parent)  # loads the cached file
    assert path2 == path
    out = save_dataset(again, tmp_path / "copy.h5")
    back = load_dataset(out)
    for a, b in ((ds, again), (ds, back)):
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.p, b.p)
        np.testing.assert_array_equal(a.extras["R_raw"], b.extras["R_raw"])
        assert (a.params, a.body_names, a.h) == (b.params, b.body_names, b.h)
        assert list(b.test_idx) == [0, 1]


def test_overlapping_split_needs_the_flag(imported, tmp_path):
    ds, _ = imported
    bad = Dataset(
        R=ds.R,
        p=ds.p,
        h=ds.h,
        scene="x",
        body_names=ds.body_names,
        body_kinds=ds.body_kinds,
        params={},
        split={"train": [0, 1], "test": [1]},
    )
    with pytest.raises(DatasetError, match="split_overlap"):
        save_dataset(bad, tmp_path / "bad.h5")
    bad.params = {"split_overlap": True}
    save_dataset(bad, tmp_path / "ok.h5")


def test_skeleton_points_reproduce_forward_kinematics(imported):
    ds, _ = imported
    b = read_bvh(MOCAP_DIR / "49_06.bvh")
    _, pw = b.world_poses()
    idx = [b.names.index(n) for n in ds.body_names]
    pts, edges = skeleton_points(ds.extras["R_raw"][0, :5], ds.extras["p_raw"][0, :5], ds.params["skeleton"])
    np.testing.assert_allclose(pts[:, :23], pw[1:6, idx] @ Z_UP.T, atol=1e-10)
    assert pts.shape[1] == 23 + len(ds.params["skeleton"]["points"]) and len(edges) == pts.shape[1] - 1
    toe = b.names.index("LeftToeBase")  # dropped joint, kept as a drawing point
    k = 23 + [p for p, _ in ds.params["skeleton"]["points"]].index(ds.body_names.index("LeftFoot"))
    np.testing.assert_allclose(pts[:, k], pw[1:6, toe] @ Z_UP.T, atol=1e-10)


@pytest.mark.parametrize("length_scale", [1.0, ASF_UNIT_M])
def test_the_tree_reproduces_the_bvh_joint_positions(imported, length_scale):
    """The dataset's tree (parents, joint offsets in the stored unit, rotations="parent"): forward
    kinematics of the stored coordinates gives the BVH joints' world poses (z up, scaled) to 1e-9."""
    ds, _ = imported
    if length_scale != 1.0:
        ds = cmu_cartwheel(cfg(smoothing=None, steps=8, train_steps=8, rollout_steps=8, length_scale=length_scale))
    tree = ds.tree
    assert tree is not None and tree.rotations == "parent" and tree.free_root
    assert list(tree.parents) == ds.params["skeleton"]["parents"] and tree.offsets[0] == (0.0, 0.0, 0.0)
    np.testing.assert_allclose(np.asarray(tree.offsets)[1:], np.asarray(ds.params["skeleton"]["offsets"])[1:])
    frames = [0, 3, 7]
    for i, name in enumerate(("49_06", "49_07")):
        b = read_bvh(MOCAP_DIR / f"{name}.bvh")
        Rw, pw = b.world_poses()
        idx = [b.names.index(n) for n in ds.body_names]
        R, p = ds.extras["R_raw"][i, frames], ds.extras["p_raw"][i, frames]
        world = forward_kinematics(tree, Pose(torch.as_tensor(R), torch.as_tensor(p)))
        ref_p = length_scale * pw[[k + 1 for k in frames]][:, idx] @ Z_UP.T  # + 1: the skipped T-pose
        ref_R = Z_UP @ Rw[[k + 1 for k in frames]][:, idx]
        scale = np.abs(ref_p).max()
        np.testing.assert_allclose(world.p.numpy(), ref_p, rtol=0, atol=1e-9 * scale)
        np.testing.assert_allclose(world.R.numpy(), ref_R, rtol=0, atol=1e-9)
        pts, _ = skeleton_points(R, p, ds.params["skeleton"])
        np.testing.assert_allclose(world.p.numpy(), pts[:, : ds.n_bodies], rtol=0, atol=1e-9 * scale)


def test_recording_discrepancy_numbers(imported):
    """The reference scale of Exp 4 (paper: 0.373 / 0.416 / 6.624), frame by frame over 471 frames."""
    ds, _ = imported
    d = recording_discrepancy(ds)
    assert d["root_rot"] == pytest.approx(1.535, abs=2e-3)
    assert d["joint_rot"] == pytest.approx(0.413, abs=2e-3)  # over the 18 moving joints (paper: 0.416)
    assert d["joint_rot_all"] == pytest.approx(0.338, abs=2e-3)  # over all 22 = 18/22 of it
    assert d["joint_rot_all"] == pytest.approx(d["joint_rot"] * 18 / 22, rel=1e-12)
    assert d["root_pos"] == pytest.approx(6.645, abs=5e-3)  # from each start position
    assert d["root_pos_m"] == pytest.approx(d["root_pos"] * ASF_UNIT_M)
    raw = recording_discrepancy(ds, raw=True)
    assert abs(raw["joint_rot"] - d["joint_rot"]) < 5e-3
    assert recording_discrepancy(ds, relative_position=False)["root_pos"] == pytest.approx(28.17, abs=0.02)


def test_moving_joints_are_derived_from_the_data(imported):
    """Four joints of the CMU cartwheels never rotate; the mean joint error runs over the other 18."""
    ds, _ = imported
    moving = moving_joints(ds)
    static = [n for j, n in enumerate(ds.body_names[1:]) if j not in moving]
    assert len(moving) == 18 and static == ["LHipJoint", "RHipJoint", "LeftShoulder", "RightShoulder"]
    # a joint that turns once, in one trajectory only, counts as moving
    R = ds.R.copy()
    j = ds.body_names.index("LHipJoint")
    R[1, 7, j] = so3.exp(torch.tensor([0.0, 0.0, 1e-6], dtype=torch.float64)).numpy()
    moved = type(ds)(R=R, p=ds.p, h=ds.h, scene=ds.scene, body_names=ds.body_names, body_kinds=ds.body_kinds)
    assert len(moving_joints(moved)) == 19
    # the mean over chosen joints, against a direct computation
    g = torch.Generator().manual_seed(1)
    Ra, Rb = so3.random((5, 4), generator=g), so3.random((5, 4), generator=g)
    p = torch.zeros(5, 1, 3, dtype=torch.float64)
    e = mocap_errors(Pose(Ra, p), Pose(Rb, p), joints=[0, 2])
    d = so3.geodesic_distance(Ra, Rb)
    torch.testing.assert_close(e["joint_rot"], d[:, [1, 3]].mean())
    torch.testing.assert_close(e["joint_rot_all"], d[:, 1:].mean())
    with pytest.raises(ValueError, match="subset"):
        mocap_errors(Pose(Ra, p), Pose(Rb, p), joints=[3])


def test_options_subsample_scale_crop_no_smoothing():
    ds = cmu_cartwheel(
        cfg(
            subsample=2,
            h=2 * 0.0083333,
            steps=100,
            train_steps=100,
            rollout_steps=100,
            length_scale=ASF_UNIT_M,
            z_up=False,
            smoothing=None,
            split="holdout",
            n_test=1,
        )
    )
    assert ds.R.shape == (2, 101, 23, 3, 3)
    assert list(ds.train_idx) == [0] and list(ds.test_idx) == [1] and ds.params["split_overlap"] is False
    b = read_bvh(MOCAP_DIR / "49_06.bvh")
    np.testing.assert_allclose(ds.p[0, :, 0], b.frames[1::2, :3][:101] * ASF_UNIT_M, atol=1e-12)  # y up, metres
    assert ds.params["length_unit_m"] == pytest.approx(1.0)
    np.testing.assert_array_equal(ds.R, ds.extras["R_raw"])


@pytest.mark.parametrize(
    "over,pattern",
    [
        ({"n_trajectories": 3}, "n_trajectories=3 must equal the number of dataset.files"),
        ({"smoothing": {"window": 50, "order": 6}}, "must be odd.*use 51"),
        (
            {"steps": 480, "train_steps": 480, "rollout_steps": 480, "smoothing": None},
            "49_07.bvh has 471 frames.*steps <= 470",
        ),
        ({"h": 0.01}, "dataset.h=0.01 does not match"),
        ({"joints": ["LeftLeg"]}, "BVH parent 'LeftUpLeg' of joint 'LeftLeg' is not selected"),
        ({"skip_frame": 1}, "unknown key"),
        ({"split": "random"}, "dataset.split"),
        ({"files": []}, "dataset.files"),
        ({"length_scale": 0}, "length_scale"),
        ({"import_version": 0}, "import_version=0"),
    ],
)
def test_config_errors(over, pattern):
    with pytest.raises(ConfigError, match=pattern):
        cmu_cartwheel(cfg(**over))


def test_file_errors(tmp_path):
    with pytest.raises(DatasetError, match="nope.bvh: BVH file not found") as e:
        cmu_cartwheel(cfg(files=["nope.bvh", "data/cmu_mocap/49_07.bvh"]))
    assert str(Path.cwd()) in str(e.value) and str(MOCAP_DIR) in str(e.value)  # where it looked, where they ship
    with pytest.raises(DatasetError, match=r"joint\(s\) \['Tail'\]"):
        cmu_cartwheel(cfg(joints=["Tail"], smoothing=None))
    bad = tmp_path / "bad.bvh"
    bad.write_text((MOCAP_DIR / "49_07.bvh").read_text().replace("Frames: 472", "Frames: 47"))
    with pytest.raises(DatasetError, match=f"{bad}: field 'Frames' declares 47 frames"):
        cmu_cartwheel(cfg(files=[str(MOCAP_DIR / "49_06.bvh"), str(bad)]))


def test_the_number_of_recordings_follows_the_files():
    """`dataset.files=[one.bvh]` alone gives one trajectory (no dataset.n_trajectories=1 needed)."""
    from helpers import compose_config

    one = compose_config("train", ["dataset=cmu_cartwheel", "dataset.files=[data/cmu_mocap/49_07.bvh]"])
    assert one.dataset.n_trajectories == 1
    assert compose_config("train", ["dataset=cmu_cartwheel"]).dataset.n_trajectories == 2
