"""BVH reader: the shipped CMU files, line endings, Euler conventions, forward kinematics, bad files."""

from __future__ import annotations

import hashlib
import itertools
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from liedfl_cli.data.bvh import axis_rotation, euler_to_matrix, forward_kinematics, parse_bvh, read_bvh
from liedfl_cli.errors import DatasetError

DATA = Path(__file__).resolve().parents[1] / "data" / "cmu_mocap"
FILES = {"49_06.bvh": 482, "49_07.bvh": 472}
SHA256 = {
    "49_06.bvh": "96c742ccc9f412d0d2b3f9d7bb11e6672d99db6c35b093f875fb4b82efa476ce",
    "49_07.bvh": "2dfd53f94480217bce5f292a24a308323ed53d6ef4a460c595bbc774700e5ada",
}
HIERARCHY_ORDER = [
    "Hips",
    "LHipJoint",
    "LeftUpLeg",
    "LeftLeg",
    "LeftFoot",
    "LeftToeBase",
    "RHipJoint",
    "RightUpLeg",
    "RightLeg",
    "RightFoot",
    "RightToeBase",
    "LowerBack",
    "Spine",
    "Spine1",
    "Neck",
    "Neck1",
    "Head",
    "LeftShoulder",
    "LeftArm",
    "LeftForeArm",
    "LeftHand",
    "LeftFingerBase",
    "LeftHandIndex1",
    "LThumb",
    "RightShoulder",
    "RightArm",
    "RightForeArm",
    "RightHand",
    "RightFingerBase",
    "RightHandIndex1",
    "RThumb",
]


@pytest.fixture(scope="module")
def real():
    return {name: read_bvh(DATA / name) for name in FILES}


def tiny_bvh(
    channels="Zrotation Yrotation Xrotation",
    frames=("0 0 0 0 0 0 10 20 30", "1 2 3 4 5 6 7 8 9"),
    declared=None,
    eol="\n",
    motion=True,
) -> str:
    """Root with 6 channels and one child joint with the given channels (and an End Site)."""
    lines = [
        "HIERARCHY",
        "ROOT Hips",
        "{",
        "\tOFFSET 0 0 0",
        "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation",
        "\tJOINT Arm",
        "\t{",
        "\t\tOFFSET 1 2 3",
        f"\t\tCHANNELS {len(channels.split())} {channels}",
        "\t\tEnd Site",
        "\t\t{",
        "\t\t\tOFFSET 0 0 1",
        "\t\t}",
        "\t}",
        "}",
    ]
    if motion:
        lines += ["MOTION", f"Frames: {len(frames) if declared is None else declared}", "Frame Time: 0.01", *frames]
    return eol.join(lines) + eol


# ---------------------------------------------------------------------- shipped files
@pytest.mark.parametrize("name", sorted(FILES))
def test_shipped_files_are_byte_identical_to_provenance(name):
    assert hashlib.sha256((DATA / name).read_bytes()).hexdigest() == SHA256[name]
    provenance = (DATA / "PROVENANCE.md").read_text()
    assert SHA256[name] in provenance
    assert "NSF EIA-0196217" in (DATA / "ATTRIBUTION.md").read_text()


@pytest.mark.parametrize("name", sorted(FILES))
def test_real_files_parse(real, name):
    b = real[name]
    assert b.n_frames == FILES[name]
    assert b.n_channels == 96 and b.frames.shape == (FILES[name], 96)
    assert b.n_joints == 31 and b.names == HIERARCHY_ORDER
    assert b.frame_time == pytest.approx(0.0083333)
    assert b.channels[0] == ("Xposition", "Yposition", "Zposition", "Zrotation", "Yrotation", "Xrotation")
    assert all(c == ("Zrotation", "Yrotation", "Xrotation") for c in b.channels[1:])
    assert b.parents[:6] == [-1, 0, 1, 2, 3, 4] and b.parents[b.names.index("LeftArm")] == b.names.index("LeftShoulder")
    assert len(b.end_sites) == 7
    np.testing.assert_allclose(b.offsets[b.names.index("LeftUpLeg")], [1.62067, -1.77917, 0.70989])
    assert np.isfinite(b.frames).all()


def test_first_frame_is_the_converter_t_pose(real):
    """Line 1 of MOTION: integer angles that put the rest skeleton in a T-pose (legs down, arms out)."""
    b = real["49_06.bvh"]
    t_pose = b.frames[0]
    assert np.array_equal(t_pose[6:], np.round(t_pose[6:]))  # integer angles (-21, 21, -16, 11, -8, 8)
    assert not np.array_equal(b.frames[1][6:], np.round(b.frames[1][6:]))
    np.testing.assert_allclose(t_pose[:3], b.frames[1][:3], atol=1e-3)  # same root position as frame 1
    _, p = b.world_poses()
    n = b.names

    def angle(a, c, ref):
        v = p[0, n.index(c)] - p[0, n.index(a)]
        return np.degrees(np.arccos(abs(v @ np.asarray(ref, float)) / np.linalg.norm(v)))

    for side in ("Left", "Right"):
        assert angle(f"{side}UpLeg", f"{side}Foot", [0, 1, 0]) < 2.0  # leg vertical (y is up in BVH)
        assert angle(f"{side}Arm", f"{side}Hand", [1, 0, 0]) < 10.0  # arm sideways (8 deg below horizontal)
    assert angle("Hips", "Head", [0, 1, 0]) < 6.0


@pytest.mark.parametrize("name", sorted(FILES))
def test_bone_lengths_constant_under_forward_kinematics(real, name):
    b = real[name]
    L = b.bone_lengths()
    expected = np.linalg.norm(b.offsets, axis=-1)
    expected[0] = 0.0
    np.testing.assert_allclose(L, np.broadcast_to(expected, L.shape), atol=1e-10)
    R, _ = b.world_poses()
    E = np.swapaxes(R, -1, -2) @ R - np.eye(3)
    assert np.abs(E).max() < 1e-12 and np.abs(np.linalg.det(R) - 1).max() < 1e-12


def test_convention_keeps_the_body_on_the_floor(real):
    """With R = Rz Ry Rx the lowest point of the body (joints and End Sites) stays at floor level through
    the whole cartwheel (hands and feet take turns); the reversed product Rx Ry Rz floats the body up to
    ~13 units (0.7 m) above the floor. This pins the Euler order convention on real data."""
    b = real["49_06.bvh"]

    def lowest(order):
        R = np.stack([euler_to_matrix(b.euler_angles(j), order) for j in range(b.n_joints)], 1)
        Rw, pw = forward_kinematics(b.parents, b.local_translations(), R)
        pts = np.concatenate([pw, b.end_site_positions(Rw, pw)], axis=1)
        return pts[1:, :, 1].min(axis=1)

    good, bad = lowest("ZYX"), lowest("XYZ")
    assert good.min() > -0.5 and good.max() < 4.0 and good.std() < 1.5
    assert bad.max() > 8.0


# ---------------------------------------------------------------------- conventions
@pytest.mark.parametrize("order", ["".join(p) for p in itertools.permutations("XYZ")] + ["ZX", "Y", "XYX"])
def test_euler_matches_scipy_intrinsic(order):
    angles = np.random.default_rng(len(order)).uniform(-400, 400, size=(50, len(order)))
    expected = Rotation.from_euler(order.upper(), angles, degrees=True).as_matrix()
    np.testing.assert_allclose(euler_to_matrix(angles, order), expected, atol=1e-14)


def test_axis_rotation_is_right_handed():
    np.testing.assert_allclose(axis_rotation("Z", np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(axis_rotation("X", np.pi / 2) @ [0, 1, 0], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(axis_rotation("Y", np.pi / 2) @ [0, 0, 1], [1, 0, 0], atol=1e-15)
    assert euler_to_matrix(np.zeros((4, 0)), "").shape == (4, 3, 3)


@pytest.mark.parametrize(
    "channels",
    [
        "Xrotation Zrotation Yrotation",
        "Yrotation Xrotation Zrotation",
        "Xposition Zrotation Xrotation Yrotation",
        "Zrotation Xrotation",
    ],
)
def test_declared_channel_order_is_used(channels):
    n = len(channels.split())
    rng = np.random.default_rng(n)
    vals = rng.uniform(-180, 180, size=(3, 6 + n))
    b = parse_bvh(tiny_bvh(channels, frames=[" ".join(f"{v:.6f}" for v in row) for row in vals]))
    order = "".join(c[0] for c in channels.split() if c.endswith("rotation"))
    assert b.rotation_order(1) == order
    rot_cols = [6 + i for i, c in enumerate(channels.split()) if c.endswith("rotation")]
    expected = Rotation.from_euler(order, np.round(vals[:, rot_cols], 6), degrees=True).as_matrix()
    np.testing.assert_allclose(b.local_rotations([1])[:, 0], expected, atol=1e-13)
    root = Rotation.from_euler("ZYX", np.round(vals[:, 3:6], 6), degrees=True).as_matrix()
    np.testing.assert_allclose(b.local_rotations([0])[:, 0], root, atol=1e-13)


def test_forward_kinematics_by_hand():
    frames = ["1 2 3 90 0 0 0 0 0", "0 0 0 0 0 0 90 0 0"]  # root Zrot 90; then child Zrot 90
    b = parse_bvh(tiny_bvh(frames=frames))
    R, p = b.world_poses()
    # frame 0: root at (1,2,3) turned 90 deg about z; child offset (1,2,3) -> Rz(90)(1,2,3) = (-2,1,3)
    np.testing.assert_allclose(p[0, 0], [1, 2, 3], atol=1e-14)
    np.testing.assert_allclose(p[0, 1], [1 - 2, 2 + 1, 3 + 3], atol=1e-14)
    # frame 1: root at origin, unrotated; child rotated: its position is the offset, its End Site turns
    np.testing.assert_allclose(p[1, 1], [1, 2, 3], atol=1e-14)
    np.testing.assert_allclose(b.end_site_positions(R, p)[1, 0], [1, 2, 4], atol=1e-14)
    np.testing.assert_allclose(b.end_site_positions(R, p)[0, 0], [-1, 3, 7], atol=1e-14)
    with pytest.raises(ValueError, match="does not precede"):
        forward_kinematics([1, -1], np.zeros((2, 3)), np.tile(np.eye(3), (2, 1, 1)))


def test_position_channels_add_to_offset():
    b = parse_bvh(
        tiny_bvh("Xposition Yposition Zposition Zrotation Yrotation Xrotation", frames=["0 0 0 0 0 0 10 20 30 0 0 0"])
    )
    np.testing.assert_allclose(b.local_translations()[0, 1], [11, 22, 33])


@pytest.mark.parametrize("eol", ["\n", "\r\n", "\r"])
def test_line_endings(eol):
    ref = parse_bvh(tiny_bvh())
    b = parse_bvh(tiny_bvh(eol=eol))
    np.testing.assert_array_equal(b.frames, ref.frames)
    assert b.names == ref.names == ["Hips", "Arm"]


def test_real_file_with_normalised_line_endings(real):
    text = (DATA / "49_07.bvh").read_bytes().decode()
    assert "\r\n" in text and re.search(r"[^\r]\n", text)  # mixed, as PROVENANCE says
    b = parse_bvh(text.replace("\r\n", "\n"), "lf")
    np.testing.assert_array_equal(b.frames, real["49_07.bvh"].frames)


# ---------------------------------------------------------------------- bad files
def write(tmp_path, text, name="bad.bvh") -> Path:
    path = tmp_path / name
    path.write_text(text, newline="")
    return path


def expect_error(path, *patterns):
    with pytest.raises(DatasetError) as info:
        read_bvh(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert msg.startswith(str(path))
    for pat in patterns:
        assert re.search(pat, msg), msg
    return msg


def test_unknown_channel_name(tmp_path):
    path = write(tmp_path, tiny_bvh("Zrotation Wrotation Xrotation"))
    expect_error(path, r"line 9:", r"joint 'Arm'", r"unknown channel name 'Wrotation'")


def test_repeated_channel_is_a_bad_order(tmp_path):
    path = write(tmp_path, tiny_bvh("Zrotation Zrotation Xrotation"))
    expect_error(path, r"line 9:", r"channel order Zrotation Zrotation", r"repeats 'Zrotation'")


def test_bad_channel_count(tmp_path):
    path = write(tmp_path, tiny_bvh().replace("CHANNELS 3", "CHANNELS x"))
    expect_error(path, r"line 9:", r"CHANNELS count 'x'")


@pytest.mark.parametrize("declared,hint", [(3, "truncated"), (1, "")])
def test_frame_count_mismatch(tmp_path, declared, hint):
    path = write(tmp_path, tiny_bvh(declared=declared))
    msg = expect_error(path, rf"field 'Frames' declares {declared} frames but the MOTION section has 2 lines")
    assert (hint in msg) if hint else ("truncated" not in msg)


def test_wrong_number_of_values_names_the_line(tmp_path):
    path = write(tmp_path, tiny_bvh(frames=("0 0 0 0 0 0 1 2 3", "0 0 0 0 0 0 1 2", "0 0 0 0 0 0 1 2 3")))
    expect_error(path, r"line 20 \(frame 1\): 8 values, but the hierarchy declares 9 channels")


def test_non_numeric_value_names_line_and_column(tmp_path):
    path = write(tmp_path, tiny_bvh(frames=("0 0 0 0 0 0 1 2 3", "0 0 0 0 0 0 1 abc 3")))
    expect_error(path, r"line 20 \(frame 1\), column 8 \(channel Arm.Yrotation\): 'abc' is not a number")
    path = write(tmp_path, tiny_bvh(frames=("0 0 nan 0 0 0 1 2 3",)), "nan.bvh")
    expect_error(path, r"line 19 \(frame 0\), column 3 \(channel Hips.Zposition\): 'nan' is not finite")


def test_non_numeric_value_in_real_file(tmp_path):
    lines = (DATA / "49_06.bvh").read_bytes().decode().splitlines(keepends=True)
    assert lines[187].startswith("-2.451 16.5423 42.9005 0 0 0")  # line 188: T-pose = frame 0
    vals = lines[299].split()
    vals[40] = "1.2.3"
    lines[299] = " ".join(vals) + "\r\n"
    path = write(tmp_path, "".join(lines), "49_06_bad.bvh")
    expect_error(path, r"line 300 \(frame 112\), column 41 \(channel Spine.Yrotation\): '1.2.3' is not a number")


def test_truncated_file(tmp_path):
    text = tiny_bvh()
    expect_error(write(tmp_path, text[: text.index("End Site")], "cut1.bvh"), r"truncated")
    expect_error(write(tmp_path, text[: text.index("Frame Time")], "cut2.bvh"), r"truncated", r"Frame Time")
    # cut in the middle of the last motion line
    real_text = (DATA / "49_07.bvh").read_bytes()
    path = tmp_path / "49_07_cut.bvh"
    path.write_bytes(real_text[: len(real_text) - 300])
    expect_error(
        path, r"line 659 \(frame 471\): \d+ values, but the hierarchy declares 96 channels \(file truncated\?\)"
    )


def test_missing_motion_section(tmp_path):
    expect_error(write(tmp_path, tiny_bvh(motion=False)), r"MOTION section is missing")
    text = tiny_bvh().replace("MOTION", "MOTON")
    expect_error(write(tmp_path, text, "typo.bvh"), r"line 16: expected 'MOTION'")


def test_other_structural_errors(tmp_path):
    expect_error(write(tmp_path, "", "empty.bvh"), r"empty")
    expect_error(write(tmp_path, "HIERARCH\n", "h.bvh"), r"line 1: expected 'HIERARCHY'")
    expect_error(
        write(tmp_path, tiny_bvh().replace("Frame Time: 0.01", "Frame Time: fast"), "ft.bvh"),
        r"line 18: field 'Frame Time' must be a number",
    )
    expect_error(
        write(tmp_path, tiny_bvh().replace("OFFSET 1 2 3", "OFFSET 1 x 3"), "off.bvh"),
        r"line 8: OFFSET Y of joint 'Arm' 'x' is not a number",
    )
    expect_error(write(tmp_path, tiny_bvh().replace("JOINT Arm", "JOINT Hips"), "dup.bvh"), r"used twice")
    expect_error(tmp_path / "missing.bvh", r"does not exist")
