"""Import defaults that do not mislead (issue 21, item 4): `model.potential=auto` builds no learned
potential when the data declare nothing (and says how to get one), `dataset.gravity` declares it,
`dataset.time_unit` and the milliseconds warning, `dataset.columns` and the common headers."""

from __future__ import annotations

import csv
import warnings

import numpy as np
import pytest
import torch
from own_data import H, motion, write_csv

from liedfl_cli.data.files import import_recording
from liedfl_cli.errors import ConfigError, DatasetError, DataWarning
from liedfl_cli.lie import so3
from liedfl_cli.mechanics.potentials import UniformGravityPotential
from liedfl_cli.models.base import BuildContext
from liedfl_cli.models.liedflnn.model import LieDFLNN


def _import(path, **kw):
    return import_recording({"name": "import", "path": str(path), "rotation": "wxyz", **kw})


def _rewrite(src, dst, rename: dict[str, str], scale_t: float = 1.0) -> None:
    """A copy of CSV `src` with its header renamed (and its time stamps multiplied by scale_t)."""
    with open(src, newline="") as f:
        rows = list(csv.reader(f))
    header = [rename.get(h, h) for h in rows[0]]
    ti = rows[0].index("t")
    body = [[(repr(float(v) * scale_t) if j == ti else v) for j, v in enumerate(r)] for r in rows[1:]]
    with open(dst, "w", newline="") as f:
        csv.writer(f).writerows([header, *body])


def _model(ds) -> LieDFLNN:
    ctx = BuildContext(ds.group, ds.h, physics=None, metadata=ds.params, forces={"rayleigh": {}})
    return LieDFLNN.from_config(ctx, potential="auto", mlp_width=8)


# ----------------------------------------------------------------------------- potential and gravity
def test_auto_learns_no_potential_on_an_import_that_declares_nothing(tmp_path):
    path, _, _ = write_csv(tmp_path / "log.csv")
    m = _model(_import(path))
    assert m.potential is None
    (note,) = m.notes  # one line, naming the overrides
    assert "\n" not in note and "auto: none" in note and "model.potential=mlp" in note and "dataset.gravity" in note
    ctx = BuildContext(m.G, H, metadata=_import(path).params, forces={"rayleigh": {}})
    assert LieDFLNN.from_config(ctx, potential="mlp", mlp_width=8).potential is not None  # the override


@pytest.mark.parametrize(
    ("gravity", "up", "parts"),
    [
        (9.81, [0.0, 0.0, 1.0], ["uniform_gravity"]),
        ([0.0, -3.7, 0.0], [0.0, 1.0, 0.0], ["uniform_gravity"]),  # y up: the acceleration along -y
        ([0.0, 0.0, -9.81], [0.0, 0.0, 1.0], ["uniform_gravity"]),
        ("none", None, []),
        (0, None, []),
    ],
)
def test_dataset_gravity_is_the_declared_potential(tmp_path, gravity, up, parts):
    path, _, _ = write_csv(tmp_path / "log.csv")
    ds = _import(path, gravity=gravity)
    m = _model(ds)
    if not parts:
        assert m.potential is None and ds.params["gravity"] == 0.0 and "g = 0" in m.notes[0]
        return
    assert isinstance(m.potential, UniformGravityPotential)
    g = float(np.linalg.norm(gravity)) if isinstance(gravity, list) else gravity
    assert float(m.potential.gravity) == pytest.approx(g, rel=1e-12)
    assert np.allclose(m.potential.direction().detach().numpy(), up, atol=1e-12)
    assert "\n" not in m.notes[0] and f"g = {g:g}" in m.notes[0]


@pytest.mark.parametrize("bad", ["heavy", [0.0, 9.81], -1.0, True, [0.0, "a", 1.0], float("nan")])
def test_bad_gravity_is_a_one_line_error_naming_the_key(tmp_path, bad):
    path, _, _ = write_csv(tmp_path / "log.csv")
    with pytest.raises(ConfigError, match=r"dataset\.gravity=") as e:
        _import(path, gravity=bad)
    assert "\n" not in str(e.value)


# ----------------------------------------------------------------------------- time unit
def _ms_csv(path, step_ms: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """One recording stamped in integer milliseconds; returns its (R, p)."""
    _, R, p = motion(1, 21, h=step_ms / 1000)
    q = so3.to_quaternion(torch.from_numpy(R[0])).numpy()
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t", "q0", "q1", "q2", "q3", "x", "y", "z"])
        for k in range(21):
            w.writerow([str(step_ms * k), *(repr(float(v)) for v in (*q[k], *p[0, k]))])
    return R, p


def test_time_unit_converts_stamps_and_milliseconds_read_as_seconds_warn(tmp_path):
    R, _ = _ms_csv(tmp_path / "ms.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no warning once the unit is given
        ds = _import(tmp_path / "ms.csv", time_unit="ms")
        assert ds.h == pytest.approx(0.05, rel=1e-12)
        assert np.abs(ds.R[0, :, 0] - R[0]).max() < 1e-12
        assert _import(tmp_path / "ms.csv", time_unit="s").h == pytest.approx(50.0)  # seconds, confirmed
    with pytest.warns(DataWarning, match=r"h = 50 s .*looks like milliseconds.*dataset\.time_unit=ms"):
        assert _import(tmp_path / "ms.csv").h == pytest.approx(50.0)
    _, _, _ = write_csv(tmp_path / "s.csv")  # fractional seconds: no warning
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _import(tmp_path / "s.csv")
    us = tmp_path / "us.csv"
    _rewrite(tmp_path / "ms.csv", us, {}, scale_t=1000.0)
    assert _import(us, time_unit="us").h == pytest.approx(0.05, rel=1e-12)
    with pytest.raises(ConfigError, match=r"dataset\.time_unit='min'"):
        _import(us, time_unit="min")


# ----------------------------------------------------------------------------- columns
QW = {"q0": "qw", "q1": "qx", "q2": "qy", "q3": "qz", "x": "px", "y": "py", "z": "pz", "t": "time"}


@pytest.mark.parametrize(
    "rename",
    [
        QW,
        {"q0": "w", "q1": "x", "q2": "y", "q3": "z", "x": "pos_x", "y": "pos_y", "z": "pos_z", "t": "timestamp"},
        {"q0": "quat_w", "q1": "quat_x", "q2": "quat_y", "q3": "quat_z", "t": "Time"},
        {"q0": "QW", "q1": "QX", "q2": "QY", "q3": "QZ", "x": "position_x", "y": "position_y", "z": "position_z"},
    ],
)
def test_common_headers_are_recognised(tmp_path, rename):
    path, R, p = write_csv(tmp_path / "log.csv")
    _rewrite(path, tmp_path / "named.csv", rename)
    for rotation in ("wxyz", "xyzw"):  # named components: the order convention cannot swap them
        ds = import_recording({"name": "import", "path": str(tmp_path / "named.csv"), "rotation": rotation})
        assert np.abs(ds.R[:, :, 0] - R).max() < 1e-9
        if "x" in rename:
            assert ds.body_kinds == ["se3"] and np.abs(ds.p[:, :, 0] - p).max() < 1e-9
        assert ds.params["columns"]["q0" if rotation == "wxyz" else "q3"] == rename["q0"]


def test_a_column_mapping_or_list(tmp_path):
    path, R, p = write_csv(tmp_path / "log.csv")
    odd = {"q0": "a", "q1": "b", "q2": "c", "q3": "d", "x": "e", "y": "f", "z": "g", "t": "clock"}
    _rewrite(path, tmp_path / "odd.csv", odd)
    with pytest.raises(DatasetError, match=r"column 'q0' is missing .*dataset\.columns"):
        _import(tmp_path / "odd.csv", columns={"t": "clock"})
    ds = _import(tmp_path / "odd.csv", columns=odd)
    assert np.abs(ds.R[:, :, 0] - R).max() < 1e-9 and np.abs(ds.p[:, :, 0] - p).max() < 1e-9
    ds = _import(tmp_path / "odd.csv", columns=["a", "b", "c", "d", "e", "f", "g"], time_column="clock")
    assert np.abs(ds.R[:, :, 0] - R).max() < 1e-9 and ds.body_kinds == ["se3"]
    ds = _import(tmp_path / "odd.csv", columns=["a", "b", "c", "d"], time_column="clock")
    assert ds.body_kinds == ["so3"]  # the positions' columns are not recognised names: a rotating body
    for bad, match in (
        ({"q9": "a"}, r"dataset\.columns\.q9: unknown column"),
        ({"q0": 3}, r"dataset\.columns\.q0=3"),
        (["a", "b"], r"dataset\.columns=\['a', 'b'\]"),
        ("a,b", r"dataset\.columns='a,b'"),
    ):
        with pytest.raises(ConfigError, match=match) as e:
            _import(tmp_path / "odd.csv", columns=bad)
        assert "\n" not in str(e.value)
    with pytest.raises(DatasetError, match=r"dataset\.columns\.q0=nope: no such column"):
        _import(tmp_path / "odd.csv", columns={**odd, "q0": "nope"})


def test_npz_arrays_renamed_by_columns(tmp_path):
    t, R, p = motion(2, 11)
    q = so3.to_quaternion(torch.from_numpy(R)).numpy()
    np.savez(tmp_path / "rec.npz", time=np.tile(t, (2, 1)), quat=q, pos=p)
    ds = _import(tmp_path / "rec.npz", columns={"t": "time", "q": "quat", "p": "pos"})
    assert ds.n_trajectories == 2 and np.abs(ds.R[:, :, 0] - R).max() < 1e-12
    with pytest.raises(DatasetError, match=r"dataset\.columns\.q=quaternion: no such array"):
        _import(tmp_path / "rec.npz", columns={"t": "time", "q": "quaternion"})
