"""The typed reader of a dataset file's root attributes (liedfl_cli/data/attributes.py): its
declaration is docs/data_format.md's table, and the round-3 trust findings are each a case."""

from __future__ import annotations

import json
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
from own_data import write_h5

from liedfl_cli.data.attributes import ATTRIBUTES, read_root_attributes
from liedfl_cli.data.hdf5 import load_dataset
from liedfl_cli.errors import DatasetError

DOC = Path(__file__).resolve().parents[1] / "docs" / "data_format.md"
VALID = {"format_version": 1, "h": 0.1, "body_kinds": json.dumps(["so3"])}


def _table_rows() -> dict[str, tuple[str, str]]:
    text = DOC.read_text()
    start = text.index("| attribute | form | required | meaning |")
    rows = {}
    for line in text[start:].splitlines()[2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split(" | ")]
        rows[cells[0].strip("`")] = (cells[1], cells[2])
    return rows


def test_the_docs_table_is_the_declaration():
    rows = _table_rows()
    assert list(rows) == [a.name for a in ATTRIBUTES]
    for a in ATTRIBUTES:
        form, required = rows[a.name]
        assert form == a.form, a.name
        assert required.startswith("yes" if a.required else "no"), a.name


@pytest.mark.parametrize(
    "attrs, needle",
    [
        ({"body_names": json.dumps("abc")}, "'body_names' must be a JSON list of strings"),
        ({"body_names": json.dumps({"a": 1})}, "got a JSON object"),
        ({"body_names": "5"}, "got a JSON number"),
        ({"body_kinds": json.dumps([])}, "got an empty list"),
        ({"seed": 1e300}, "'seed' must be an integer, got 1e+300"),
        ({"seed": -3.0}, "'seed' must be an integer, got -3 (outside -1..9223372036854775807)"),
        ({"scene": np.array([1, 2])}, "'scene' must be one line of text without '/' or '\\', got an HDF5 array"),
        ({"created": 5}, "'created' must be an ISO-8601 time, got 5"),
        ({"parents": np.array([-1.0, 0.0])}, "'parents' must be a JSON list of integers"),
    ],
)
def test_round3_findings_are_one_line(attrs, needle):
    with pytest.raises(DatasetError) as exc:
        read_root_attributes({**VALID, **attrs}, "d.h5")
    msg = str(exc.value)
    assert msg.startswith("d.h5: attribute '") and "\n" not in msg
    assert needle in msg, msg


def test_native_hdf5_forms_are_accepted():
    got = read_root_attributes(
        {
            "format_version": np.array([1]),  # MATLAB's 1x1
            "h": np.float32(0.5),
            "body_kinds": np.array([b"se3", b"so3"]),
            "body_names": np.array(["root", "arm"], dtype=h5py.string_dtype()),
            "parents": np.array([-1, 0], dtype=np.int32),  # the natural h5py way
            "seed": 4.0,
        },
        "d.h5",
    )
    assert got["format_version"] == 1 and got["h"] == 0.5 and got["seed"] == 4
    assert got["body_kinds"] == ["se3", "so3"] and got["body_names"] == ["root", "arm"]
    assert got["parents"] == [-1, 0] and all(type(q) is int for q in got["parents"])


def test_a_tree_without_bodies_and_a_misordered_file_with_physics_name_body_kinds(tmp_path):
    path = write_h5(tmp_path / "d.h5")
    with h5py.File(path, "r+") as f:
        f.attrs["body_kinds"] = json.dumps([])
        f.attrs["parents"] = json.dumps([])
    with pytest.raises(DatasetError, match=re.escape(f"{path}: attribute 'body_kinds' must be a non-empty")):
        load_dataset(path)
    with h5py.File(path, "r+") as f:  # physics declared, bodies misordered: the order is named, not physics
        f.attrs["body_kinds"] = json.dumps(["so3", "se3"])
        f.attrs["params"] = json.dumps({"physics": {"J": [1, 1, 1], "D": [1, 2]}})
        del f.attrs["parents"]
    with pytest.raises(DatasetError, match="attribute 'body_kinds' .* got 'se3' after 'so3' at index 1"):
        load_dataset(path)
