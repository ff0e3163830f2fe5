"""A fuzzer of the documented dataset format with an oracle: every generated file is known valid or
known invalid before it is loaded.

tests/test_fuzz_loaders.py mutates files blindly and can only check "clean load or one-line error";
it cannot see a file that should have been refused but loaded (a `body_names` JSON string split into
letters). Here each mutation is drawn from a table of the format (docs/data_format.md): a root
attribute or an array written in one of its accepted forms (the loaded value must equal the intended
one) or in a form the format refuses (the load must end in one `DatasetError` line naming the file
and the attribute or array). One to three mutations per file, on a single SE(3) body or a three-body
tree.

Fast tier: 300 files through `load_dataset` and 8 through `liedfl data`; slow tier: 3,000 files
(`LIEDFL_FUZZ_SEED=<int>` draws another sample).
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from fuzz_strategies import FAST, check_outcome
from hypothesis import HealthCheck, given, seed, settings
from hypothesis import strategies as st
from own_data import H, motion
from test_fuzz_loaders import _rigid_dataset  # the SE(3) body with declared physics

from helpers import main_in_process
from liedfl_cli.data.hdf5 import Dataset, load_dataset, save_dataset
from liedfl_cli.errors import DatasetError
from liedfl_cli.lie.tree import Tree

STR = h5py.string_dtype()
FAST_FILES, SLOW_FILES, CLI_FILES = 300, 3000, 8


@dataclass(frozen=True)
class Case:
    """One mutation: `key` (what it touches, h and t together; two of one key are never combined), `apply`
    (edits the open file), valid or not, and for a valid one `check(ds)` of the loaded dataset, for
    an invalid one the names one of which the error must mention."""

    key: str
    label: str
    apply: Callable[[h5py.File], None]
    valid: bool
    check: Callable[[Dataset], bool] | None = None
    names: tuple[str, ...] = ()


def _attr(name: str, value: Any) -> Callable[[h5py.File], None]:
    def apply(f: h5py.File) -> None:
        f.attrs[name] = value

    return apply


def ok(key: str, value: Any, check: Callable[[Dataset], bool], label: str = "") -> Case:
    return Case(key, label or f"{key}={value!r:.40}", _attr(key, value), True, check)


def bad(key: str, value: Any, *also: str, label: str = "") -> Case:
    return Case(key, label or f"{key}={value!r:.40}", _attr(key, value), False, names=(f"'{key}'", *also))


def _array(name: str, edit: Callable[[np.ndarray], np.ndarray]) -> Callable[[h5py.File], None]:
    def apply(f: h5py.File) -> None:
        a = edit(f[name][()])
        del f[name]
        f.create_dataset(name, data=a)

    return apply


def _set_h(value: Any, n: int) -> Callable[[h5py.File], None]:
    """h and t together (t must be spaced by h)."""

    def apply(f: h5py.File) -> None:
        f.attrs["h"] = value
        del f["t"]
        f.create_dataset("t", data=float(np.asarray(value).reshape(-1)[0]) * np.arange(n))

    return apply


def _joints_and_axes(axes: np.ndarray) -> Callable[[h5py.File], None]:
    """Ball joints declared with the dataset `joint_axes` (optional for ball joints, checked when given)."""

    def apply(f: h5py.File) -> None:
        f.attrs["joints"] = json.dumps(["ball"] * 3)
        f.create_dataset("joint_axes", data=axes)

    return apply


# ----------------------------------------------------------------------------- the two bases
def _chain() -> Dataset:
    _, R, _ = motion(4, 10)
    Rs = np.stack([R, np.swapaxes(R, -1, -2), R @ R], axis=2)  # three bodies, parent-relative
    tree = Tree.from_lists([-1, 0, 1], np.array([[0, 0, 1.0], [0, 0, 1.0], [0, 0, 1.0]]), "parent", free_root=False)
    return Dataset(
        R=Rs,
        p=np.zeros(Rs.shape[:2] + (0, 3)),
        h=H,
        scene="chain",
        body_names=["a", "b", "c"],
        body_kinds=["so3"] * 3,
        params={"note": "fuzz"},
        seed=0,
        split={"train": np.array([0, 1, 2]), "test": np.array([3])},
        tree=tree,
    )


def _common_cases(names: list[str], kinds: list[str], n: int) -> list[Case]:
    B = len(kinds)
    other = [f"{x}_2" for x in names]
    return [
        # format_version
        ok("format_version", np.int32(1), lambda d: True),
        ok("format_version", 1.0, lambda d: True),
        bad("format_version", 2),
        bad("format_version", "1"),
        bad("format_version", True),
        # h (with t)
        Case("t", "h=0.02", _set_h(0.02, n), True, lambda d: d.h == 0.02),
        Case("t", "h=np.float32", _set_h(np.float32(0.25), n), True, lambda d: d.h == 0.25),
        Case("t", "h=[0.1]", _set_h(np.array([0.1]), n), True, lambda d: d.h == 0.1),
        Case("t", "h=" + repr(0.0), _attr("h", 0.0), False, names=("'h'",)),
        Case("t", "h=" + repr(-0.05), _attr("h", -0.05), False, names=("'h'",)),
        Case("t", "h=" + repr(np.nan), _attr("h", np.nan), False, names=("'h'",)),
        Case("t", "h=" + repr(np.inf), _attr("h", np.inf), False, names=("'h'",)),
        Case("t", "h=" + repr("0.05"), _attr("h", "0.05"), False, names=("'h'",)),
        Case("t", "h=" + repr(np.array([0.05, 0.05])), _attr("h", np.array([0.05, 0.05])), False, names=("'h'",)),
        Case("t", "h=" + repr(True), _attr("h", True), False, names=("'h'",)),
        # body_names
        ok("body_names", json.dumps(other), lambda d: d.body_names == other),
        ok("body_names", np.array(other, dtype=STR), lambda d: d.body_names == other),
        ok("body_names", np.array([x.encode() for x in other]), lambda d: d.body_names == other),
        bad("body_names", json.dumps("abc")),
        bad("body_names", json.dumps({"a": 1, "b": 2, "c": 3})),
        bad("body_names", "5"),
        bad("body_names", 5),
        bad("body_names", "box"),
        bad("body_names", json.dumps(other + ["extra"])),
        bad("body_names", json.dumps([""] * B)),
        bad("body_names", json.dumps(["same"] * (B + 1))),
        bad("body_names", json.dumps([1] * B)),
        bad("body_names", np.array([[x] for x in other], dtype=STR)),
        bad("body_names", np.arange(B)),
        # body_kinds
        ok("body_kinds", np.array(kinds, dtype=STR), lambda d: d.body_kinds == kinds),
        bad("body_kinds", json.dumps([])),
        bad("body_kinds", json.dumps(kinds[0])),
        bad("body_kinds", kinds[0]),
        bad("body_kinds", json.dumps(["xyz"] + kinds[1:])),
        bad("body_kinds", json.dumps({k: 1 for k in kinds})),
        bad("body_kinds", json.dumps(["so3"] + ["se3"] * (B - 1) if B > 1 else ["so3"]), "'p'", "'R'", "n_s"),
        # counts
        ok("n_so3", float(kinds.count("so3")), lambda d: True),
        bad("n_se3", kinds.count("se3") + 1),
        bad("n_so3", "1"),
        bad("n_se3", -1),
        bad("n_so3", np.array([1, 2])),
        # scene
        ok("scene", "a scene: 49 (take 2)", lambda d: d.scene == "a scene: 49 (take 2)"),
        ok("scene", np.bytes_(b"bytes_scene"), lambda d: d.scene == "bytes_scene"),
        bad("scene", np.array([1, 2])),
        bad("scene", 5),
        bad("scene", ""),
        bad("scene", "a/b"),
        bad("scene", "two\nlines"),
        bad("scene", "x" * 300),
        bad("scene", np.bytes_(b"\xff\xfe")),
        # params
        bad("params", json.dumps([1, 2])),
        bad("params", json.dumps("x")),
        bad("params", "{not json"),
        bad("params", 5),
        bad("params", json.dumps(None)),
        # seed
        ok("seed", 7, lambda d: d.seed == 7),
        ok("seed", np.int64(2**63 - 1), lambda d: d.seed == 2**63 - 1),
        ok("seed", -1, lambda d: d.seed == -1),
        ok("seed", 12.0, lambda d: d.seed == 12),
        bad("seed", 1e300),
        bad("seed", -5),
        bad("seed", -2.0),
        bad("seed", 1.5),
        bad("seed", "abc"),
        bad("seed", True),
        bad("seed", np.nan),
        bad("seed", np.uint64(2**64 - 1)),
        bad("seed", np.array([1, 2])),
        # created / version / own metadata
        ok("created", "2026-11-28T10:00:00+00:00", lambda d: True),
        ok("created", "2026-11-28T10:00:00Z", lambda d: True),
        bad("created", 5),
        bad("created", "yesterday"),
        bad("created", np.array([1.0, 2.0])),
        ok("liedfl_version", "0.9.1", lambda d: True),
        bad("liedfl_version", 3),
        ok("my_note", np.array([[1, 2], [3, 4]]), lambda d: True, label="undeclared attribute"),
        # arrays
        Case(
            "R",
            "R NaN",
            _array("R", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 7, np.nan, a)),
            False,
            names=("'R'",),
        ),  # fmt: skip
        Case("R", "R huge", _array("R", lambda a: a * 1e200), False, names=("'R'",)),
        Case("R", "R float16", _array("R", lambda a: a.astype(np.float16)), False, names=("'R'",)),
        Case("R", "R one pose", _array("R", lambda a: a[:, :1]), False, names=("'R'",)),
        Case("R", "R float32", _array("R", lambda a: a.astype(np.float32)), True, lambda d: d.R.dtype == np.float64),
        Case(
            "t",
            "t jitter",
            _array("t", lambda a: a + np.where(np.arange(a.size) == 3, 1e-3, 0.0)),
            False,
            names=("'t'",),
        ),  # fmt: skip
        Case("t", "t short", _array("t", lambda a: a[:-1]), False, names=("'t'",)),
        Case("split", "test index out of range", _array("split/test", lambda a: a + 100), False, names=("split/test",)),
        Case("split", "train empty", _array("split/train", lambda a: a[:0]), False, names=("split/train",)),
        Case("split", "train 2-D", _array("split/train", lambda a: a[None]), False, names=("split/train",)),
        Case("split", "train floats", _array("split/train", lambda a: a.astype(float)), False, names=("split/train",)),
        Case("split", "overlap", _array("split/test", lambda a: np.array([1])), False, names=("split/test",)),
    ]


def _rigid_cases(n: int) -> list[Case]:
    return [
        Case("p", "p dropped", lambda f: f.__delitem__("p"), False, names=("'p'",)),
        Case("p", "p inf", _array("p", lambda a: a + np.inf), False, names=("'p'",)),
        Case("p", "p wrong shape", _array("p", lambda a: a[..., :2]), False, names=("'p'",)),
        bad("parents", json.dumps([-1]), "joint_offsets"),
        ok("n_se3", 1, lambda d: d.n_se3 == 1),
    ]


def _chain_cases(n: int) -> list[Case]:
    def tree(check: Callable[[Tree], bool]) -> Callable[[Dataset], bool]:
        return lambda d: d.tree is not None and check(d.tree)

    return [
        ok("parents", np.array([-1, 0, 1]), tree(lambda t: list(t.parents) == [-1, 0, 1]), "parents int64 array"),
        ok("parents", np.array([-1, 0, 1], dtype=np.int32), tree(lambda t: list(t.parents) == [-1, 0, 1])),
        ok("parents", json.dumps([-1, 0, 0]), tree(lambda t: list(t.parents) == [-1, 0, 0])),
        bad("parents", json.dumps([-1, 0])),
        bad("parents", json.dumps([0, 0, 1])),
        bad("parents", json.dumps([-1, 2, 1])),
        bad("parents", json.dumps([-1, 0.5, 1])),
        bad("parents", json.dumps([-1, True, 1])),
        bad("parents", np.array([-1.0, 0.0, 1.0])),
        bad("parents", np.array([[-1, 0, 1]])),
        bad("parents", "abc"),
        bad("parents", json.dumps([])),
        ok("rotations", np.bytes_(b"parent"), tree(lambda t: t.rotations == "parent")),
        ok("rotations", np.array(["parent"], dtype=STR), tree(lambda t: t.rotations == "parent")),
        bad("rotations", "local"),
        bad("rotations", 5),
        ok("joints", json.dumps(["ball"] * 3), tree(lambda t: list(t.joints or []) == ["ball"] * 3)),
        ok("joints", np.array(["ball"] * 3, dtype=STR), tree(lambda t: list(t.joints or []) == ["ball"] * 3)),
        bad("joints", json.dumps(["hinge"] * 3), "joint_axes"),
        bad("joints", json.dumps(["free"] * 3)),
        bad("joints", json.dumps("ball")),
        bad("joints", json.dumps(["ball"] * 2)),
        bad("joints", 5),
        Case(
            "joints",
            "ball joints with axes",
            _joints_and_axes(np.tile([[1.0, 0, 0], [0, 1.0, 0]], (3, 1, 1))),
            True,
            tree(lambda t: list(t.joints or []) == ["ball"] * 3),
        ),  # fmt: skip
        Case("joints", "axes of the wrong shape", _joints_and_axes(np.ones((3, 3))), False, names=("joint_axes",)),
        Case("joints", "axes NaN", _joints_and_axes(np.full((3, 2, 3), np.nan)), False, names=("joint_axes",)),
        Case(
            "joints",
            "axes as integers",
            _joints_and_axes(np.ones((3, 2, 3), dtype=np.int64)),
            False,
            names=("joint_axes",),
        ),  # fmt: skip
        Case("offsets", "offsets NaN", _array("joint_offsets", lambda a: a * np.nan), False, names=("joint_offsets",)),
        Case("offsets", "offsets dropped", lambda f: f.__delitem__("joint_offsets"), False, names=("joint_offsets",)),
        bad("body_kinds", json.dumps(["se3", "so3", "se3"])),
    ]


@pytest.fixture(scope="module")
def bases(tmp_path_factory) -> tuple[Path, list[tuple[Path, list[Case]]]]:
    root = tmp_path_factory.mktemp("fuzz_format")
    out = []
    for name, ds, extra in (("rigid", _rigid_dataset(), _rigid_cases), ("chain", _chain(), _chain_cases)):
        path = save_dataset(ds, root / f"{name}.h5")
        load_dataset(path)  # the base itself is valid
        n = ds.R.shape[1]
        out.append((path, _common_cases(ds.body_names, ds.body_kinds, n) + extra(n)))
    return root, out


def _mutations(draw, cases: list[Case]) -> list[Case]:
    picked = draw(st.lists(st.sampled_from(cases), min_size=1, max_size=3, unique_by=lambda c: c.key))
    return picked


def _write_case(root: Path, base: Path, picked: list[Case]) -> Path:
    path = root / f"case_{uuid.uuid4().hex[:10]}.h5"
    shutil.copyfile(base, path)
    with h5py.File(path, "r+") as f:
        for c in picked:
            c.apply(f)
    return path


def _property(bases, which: int, data) -> None:
    root, all_bases = bases
    base, cases = all_bases[which]
    picked = _mutations(data.draw, cases)
    path = _write_case(root, base, picked)
    try:
        ds = check_outcome(lambda: load_dataset(path), path)
        labels = [c.label for c in picked]
        if all(c.valid for c in picked):
            assert ds is not None, f"a valid file was refused: {labels}"
            failed = [c.label for c in picked if c.check is not None and not c.check(ds)]
            assert not failed, f"loaded but wrong: {failed}"
        else:
            assert ds is None, f"an invalid file loaded: {[c.label for c in picked if not c.valid]}"
    finally:
        path.unlink(missing_ok=True)


def _refusal_names_the_field(bases, which: int, data) -> None:
    """An invalid file's error names one of its invalid fields (drawn alone: the one field to name)."""
    root, all_bases = bases
    base, cases = all_bases[which]
    c = data.draw(st.sampled_from([c for c in cases if not c.valid]))
    path = _write_case(root, base, [c])
    try:
        with pytest.raises(DatasetError) as exc:
            load_dataset(path)
        msg = str(exc.value)
        assert msg.startswith(f"{path}: ") and "\n" not in msg, msg
        assert any(n in msg for n in c.names), f"{c.label}: {msg}"
    finally:
        path.unlink(missing_ok=True)


@settings(FAST, max_examples=FAST_FILES)
@given(which=st.integers(0, 1), data=st.data())
def test_fuzz_format_with_an_oracle(bases, which, data):
    _property(bases, which, data)


@settings(FAST, max_examples=120)
@given(which=st.integers(0, 1), data=st.data())
def test_fuzz_a_refusal_names_the_field(bases, which, data):
    _refusal_names_the_field(bases, which, data)


def test_every_case_alone(bases):
    """Every mutation of the table on its own: the valid ones load with the intended value, the
    invalid ones are one line naming the field (the table's coverage does not rest on the sample)."""
    root, all_bases = bases
    counts = {"valid": 0, "invalid": 0}
    for base, cases in all_bases:
        for c in cases:
            path = _write_case(root, base, [c])
            try:
                if c.valid:
                    ds = load_dataset(path)
                    assert c.check is None or c.check(ds), c.label
                else:
                    with pytest.raises(DatasetError) as exc:
                        load_dataset(path)
                    msg = str(exc.value)
                    assert msg.startswith(f"{path}: ") and "\n" not in msg, msg
                    assert any(n in msg for n in c.names), f"{c.label}: {msg}"
                counts["valid" if c.valid else "invalid"] += 1
            finally:
                path.unlink(missing_ok=True)
    assert counts["valid"] >= 30 and counts["invalid"] >= 100, counts


@settings(
    FAST,
    max_examples=CLI_FILES,
    suppress_health_check=[*FAST.suppress_health_check, HealthCheck.function_scoped_fixture],
)
@given(which=st.integers(0, 1), data=st.data())
def test_fuzz_format_through_the_data_command(bases, which, data, tmp_path_factory, capfd):
    """`liedfl data dataset=file`: exit 0 exactly for valid files; an invalid one is one error line
    naming the file and a non-zero exit, never a traceback."""
    root, all_bases = bases
    base, cases = all_bases[which]
    picked = _mutations(data.draw, cases)
    path = _write_case(root, base, picked)
    work = tmp_path_factory.mktemp("cli")
    try:
        capfd.readouterr()
        code, tb = main_in_process(
            "data", "dataset=file", f"dataset.path={path}", f"paths.data_dir={work / 'data'}", cwd=work
        )
        _, err = capfd.readouterr()
        assert not tb, tb
        if all(c.valid for c in picked):
            assert code == 0, err
        else:
            assert code != 0
            lines = [x for x in err.splitlines() if x.strip()]
            assert len(lines) == 1 and path.name in lines[0], err
    finally:
        path.unlink(missing_ok=True)
        shutil.rmtree(work, ignore_errors=True)


@pytest.mark.slow
def test_fuzz_format_slow(bases):
    count = [0]

    def counted(which, data):
        count[0] += 1
        _property(bases, which, data)

    test = given(which=st.integers(0, 1), data=st.data())(counted)
    other = os.environ.get("LIEDFL_FUZZ_SEED")
    if other:
        test = seed(int(other))(settings(FAST, max_examples=SLOW_FILES, derandomize=False)(test))
    else:
        test = settings(FAST, max_examples=SLOW_FILES)(test)
    test()
    assert count[0] >= SLOW_FILES
