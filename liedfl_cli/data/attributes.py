"""The root attributes of a dataset file, declared once and read through one typed door.

`ATTRIBUTES` is the table of docs/data_format.md ("Root attributes"): name, whether it is required,
the form it must take and what it means (a test keeps the two identical). `read_root_attributes`
reads every declared attribute of an open HDF5 file and returns plain Python values, or raises one
`DatasetError` line naming the file, the attribute, the expected form and what was found. Checks
that need more than one attribute or the arrays (counts against `body_kinds`, a tree's parents
against the bodies, joint types against the root) stay with the loader (data/hdf5.py).

What is accepted beside the canonical form (what liedfl writes): a list may be a JSON string or an
HDF5 1-D array (strings for names and kinds, integers for `parents`); a scalar may be a NumPy scalar
or a one-element array (MATLAB writes 1x1 attributes); bytes are UTF-8 text. Undeclared attributes
are ignored (room for the user's own metadata).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from datetime import datetime
from typing import Any

import numpy as np

from ..errors import DatasetError
from ..lie.tree import ROTATIONS

FORMAT_VERSION = 1
BODY_KINDS = ("se3", "so3")
SEED_MAX = 2**63 - 1  # stored as int64
TEXT_MAX = 200  # characters of a one-line text attribute (scene, version)


class _Bad(ValueError):
    """The raw value does not have the declared form; the message says what was found."""


@dataclass(frozen=True)
class Attribute:
    """One root attribute: `parse` turns the raw h5py value into the Python value or raises `_Bad`."""

    name: str
    required: bool
    form: str  # the expected form, as the error message and docs/data_format.md's "type" column say it
    parse: Callable[[Any], Any]
    meaning: str


# ---------------------------------------------------------------------- raw values
def _shown(v: Any) -> str:
    """A short description of a found value for an error message."""
    if isinstance(v, np.ndarray):
        return f"an HDF5 array of dtype {v.dtype} and shape {v.shape}"
    return f"{v!r:.80}"


def _text(v: Any) -> Any:
    if isinstance(v, bytes):
        try:
            return v.decode("utf-8")
        except UnicodeDecodeError:
            raise _Bad(f"bytes that are not UTF-8 text ({v!r:.40})") from None
    return v


def _scalar(raw: Any) -> Any:
    """A NumPy scalar or one-element array as a plain Python value; bytes decoded."""
    v = raw
    if isinstance(v, np.ndarray):
        if v.size != 1:
            raise _Bad(_shown(v))
        v = v.reshape(-1)[0]
    if isinstance(v, np.generic):
        v = v.item()
    return _text(v)


def _json(raw: Any) -> Any:
    """The JSON value of a text attribute."""
    v = _scalar(raw)
    if not isinstance(v, str):
        raise _Bad(f"{v!r:.80} (a {type(v).__name__}, not JSON text)")
    try:
        return json.loads(v)
    except json.JSONDecodeError as exc:
        raise _Bad(f"text that is not valid JSON ({exc.msg} at char {exc.pos})") from None
    except RecursionError:
        raise _Bad("JSON nested too deeply") from None


def _json_kind(v: Any) -> str:
    return {dict: "object", list: "list", str: "string", bool: "boolean", type(None): "null"}.get(type(v), "number")


# ---------------------------------------------------------------------- forms
def integer(lo: int, hi: int) -> Callable[[Any], int]:
    def parse(raw: Any) -> int:
        v = _scalar(raw)
        if isinstance(v, float) and v.is_integer() and abs(v) <= 2**53:  # written by a float-only tool
            v = int(v)
        if isinstance(v, bool) or not isinstance(v, int):
            raise _Bad(_shown(v))
        if not lo <= v <= hi:
            raise _Bad(f"{v} (outside {lo}..{hi})")
        return v

    return parse


def positive_number(raw: Any) -> float:
    v = _scalar(raw)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise _Bad(_shown(v))
    if not math.isfinite(v) or v <= 0:
        raise _Bad(repr(v))
    return float(v)


def text(raw: Any) -> str:
    v = _scalar(raw)
    if not isinstance(v, str):
        raise _Bad(_shown(v))
    if not v.strip() or len(v) > TEXT_MAX or any(c in v for c in "/\\") or not v.isprintable():
        raise _Bad(f"{v!r:.80}")
    return v


def choice(options: tuple[str, ...]) -> Callable[[Any], str]:
    def parse(raw: Any) -> str:
        v = _scalar(raw)
        if v not in options:
            raise _Bad(_shown(v))
        return v

    return parse


def timestamp(raw: Any) -> str:
    v = _scalar(raw)
    if not isinstance(v, str):
        raise _Bad(_shown(v))
    try:
        datetime.fromisoformat(v.replace("Z", "+00:00"))
    except ValueError:
        raise _Bad(f"{v!r:.80}") from None
    return v


def _list(raw: Any, item: Callable[[Any], bool], array_kinds: str) -> list:
    """A list from JSON text or an HDF5 1-D array whose dtype kind is in `array_kinds`."""
    if isinstance(raw, np.ndarray) and raw.dtype.kind in array_kinds:
        if raw.ndim != 1:
            raise _Bad(_shown(raw))
        v = [_text(x.item() if isinstance(x, np.generic) else x) for x in raw]
    elif isinstance(raw, np.ndarray) and raw.size != 1:
        raise _Bad(_shown(raw))
    else:
        v = _json(raw)
        if not isinstance(v, list):
            raise _Bad(f"a JSON {_json_kind(v)} ({json.dumps(v)[:80]})")
    bad = [i for i, x in enumerate(v) if not item(x)]
    if bad:
        raise _Bad(f"{v[bad[0]]!r:.40} at index {bad[0]}")
    return v


def _is_name(x: Any) -> bool:
    return isinstance(x, str) and bool(x.strip()) and x.isprintable() and len(x) <= TEXT_MAX


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def names(raw: Any) -> list[str]:
    v = _list(raw, _is_name, "OSU")
    seen: dict[str, int] = {}
    for i, x in enumerate(v):
        if x in seen:
            raise _Bad(f"{x!r:.40} twice (at {seen[x]} and {i})")
        seen[x] = i
    return v


def body_kinds(raw: Any) -> list[str]:
    v = _list(raw, lambda x: x in BODY_KINDS, "OSU")
    if not v:
        raise _Bad("an empty list (a dataset needs at least one body)")
    after = [i for i in range(1, len(v)) if v[i] == "se3" and v[i - 1] == "so3"]
    if after:
        raise _Bad(f"'se3' after 'so3' at index {after[0]} (SE(3) bodies come first)")
    return v


def int_list(raw: Any) -> list[int]:
    return _list(raw, _is_int, "iu")


def text_list(raw: Any) -> list[str]:
    return _list(raw, lambda x: isinstance(x, str), "OSU")


def json_object(raw: Any) -> dict:
    v = _json(raw)
    if not isinstance(v, dict):
        raise _Bad(f"a JSON {_json_kind(v)}")
    return v


# ---------------------------------------------------------------------- the table
LIST_OF_STR = "a JSON list of strings (or an HDF5 string array)"
ATTRIBUTES: tuple[Attribute, ...] = (
    Attribute(
        "format_version", True, f"an integer, 1..{FORMAT_VERSION}", integer(1, FORMAT_VERSION), "version of this format"
    ),
    Attribute("h", True, "a positive finite number", positive_number, "time step in seconds"),
    Attribute(
        "body_kinds",
        True,
        "a non-empty JSON list of 'se3'/'so3' (or an HDF5 string array), SE(3) first",
        body_kinds,
        "kind of each body, in the order of axis 2 of `R`",
    ),
    Attribute("body_names", False, f"{LIST_OF_STR}, unique names", names, "one name per body"),
    Attribute(
        "n_se3", False, "an integer >= 0", integer(0, 10**6), "number of SE(3) bodies (agrees with `body_kinds`)"
    ),
    Attribute(
        "n_so3", False, "an integer >= 0", integer(0, 10**6), "number of SO(3) bodies (agrees with `body_kinds`)"
    ),
    Attribute("scene", False, "one line of text without '/' or '\\'", text, "scene name (used in file names)"),
    Attribute("params", False, "a JSON object", json_object, "physics and generator parameters"),
    Attribute("seed", False, "an integer", integer(-1, SEED_MAX), "seed of the initial conditions"),
    Attribute(
        "parents",
        False,
        "a JSON list of integers (or an HDF5 integer array)",
        int_list,
        "parent of each body, -1 for the root",
    ),
    Attribute("rotations", False, f"one of {list(ROTATIONS)}", choice(tuple(ROTATIONS)), "what `R[..., b]` holds"),
    Attribute("joints", False, LIST_OF_STR, text_list, "joint type of each body"),
    Attribute(
        "liedfl_version", False, "one line of text without '/' or '\\'", text, "software version that wrote the file"
    ),
    Attribute("created", False, "an ISO-8601 time", timestamp, "time of writing"),
)
BY_NAME = {a.name: a for a in ATTRIBUTES}


def read_root_attributes(attrs: Mapping[str, Any], src: str) -> dict[str, Any]:
    """Every declared attribute of `attrs` (an h5py AttributeManager or a dict of raw values) parsed
    to its Python value; absent optional ones are None. Raises one `DatasetError` line:
    "<src>: attribute '<name>' must be <form>, got <found>" (or "... is missing")."""
    out: dict[str, Any] = {}
    for a in ATTRIBUTES:
        if a.name not in attrs:
            if a.required:
                raise DatasetError(f"{src}: attribute '{a.name}' is missing ({a.meaning}; {a.form})")
            out[a.name] = None
            continue
        try:
            raw = attrs[a.name]
        except (OSError, TypeError, ValueError, KeyError) as exc:  # an HDF5 type h5py cannot read
            raise DatasetError(f"{src}: attribute '{a.name}' cannot be read ({type(exc).__name__})") from None
        try:
            out[a.name] = a.parse(raw)
        except _Bad as bad:
            raise DatasetError(f"{src}: attribute '{a.name}' must be {a.form}, got {bad}") from None
    return out


__all__ = ["ATTRIBUTES", "Attribute", "BODY_KINDS", "FORMAT_VERSION", "read_root_attributes"]
