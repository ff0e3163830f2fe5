"""Hypothesis strategies for tests/test_fuzz_loaders.py: mutations of a valid file of each kind.

A mutation is a plain tuple (so that a failing case can be kept as an explicit `@example`); its target
is a name or an index into the sorted names the file has (taken modulo their number), so one
strategy serves every file. Kinds:

- HDF5 trees (datasets, rollout files): `Tree` holds root/group attributes, datasets and empty
  groups; `tree_mutations` drops, renames, retypes, reshapes and poisons them (NaN/inf, huge,
  negative values), turns datasets into groups and back, and writes JSON and unicode junk into
  attributes.
- array dicts (NPZ archives, checkpoint payloads): `array_mutations`.
- text (CSV, BVH): `text_mutations` deletes, duplicates and swaps lines, replaces tokens with
  junk, truncates, and appends invalid UTF-8.
- bytes (any file): `byte_mutations` truncates, overwrites bytes or replaces the whole file.

`check_outcome` states the property: a loader either returns (the caller checks the result's
invariants) or raises the CLI's one-line error type (`LiedflError`) whose message names the file.
"""

from __future__ import annotations

import contextlib
import json
import os
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from hypothesis import HealthCheck, Phase, settings
from hypothesis import strategies as st

from liedfl_cli.errors import LiedflError, LiedflWarning

# fast tier: a small reproducible sample per loader (derandomized: CI sees the same files every run);
# slow tier: >= 1,000 generated files per loader. database=None: no .hypothesis folder in the repo.
FAST = settings(
    max_examples=40,
    deadline=None,
    derandomize=True,
    database=None,
    # no shrinking: a failing file is reported as generated (shrinking a mutated file takes minutes)
    phases=[Phase.explicit, Phase.reuse, Phase.generate],
    report_multiple_bugs=True,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much, HealthCheck.data_too_large],
)
SLOW_EXAMPLES = 1000
SLOW = settings(FAST, max_examples=SLOW_EXAMPLES)

# ----------------------------------------------------------------------------- junk values
JUNK_NUMBERS = [0.0, -0.0, -1.0, 1e-308, 1e308, -1e308, float("nan"), float("inf"), float("-inf"), 2.0**63, 0.5]
JUNK_TEXT = [
    "",
    " ",
    "nan",
    "inf",
    "-inf",
    "1e400",
    "-1e308",
    "abc",
    "ü",
    "\U0001f600",
    "0x10",
    "1,5",
    "NaN",
    "1e-400",
    "-0",
    "99999999999999999999999",
    "{",
    "[]",
    "{}",
    "null",
    "[1, 2]",
    '["se3", "so3"]',
    '["so3", "se3"]',
    '["xyz"]',
    '"se3"',
    '{"physics": {"J": "abc"}}',
    '{"physics": [1, 2]}',
    '{"physics": {"J": [1, 1, 5]}}',
    '{"physics": {"J": [1, 1, 1], "D": [1, 2]}}',
    '{"split_overlap": true}',
    "[-1, 0, 1]",
    "[-1, 5, 0]",
    '[0, "a"]',
    "world",
    "parent",
    "true",
]
# no surrogates and no NUL: HDF5 strings cannot hold them (what a file can hold is what is fuzzed)
text_chars = st.characters(blacklist_categories=("Cs",), blacklist_characters="\x00")
junk_text = st.one_of(st.sampled_from(JUNK_TEXT), st.text(text_chars, max_size=12))
junk_scalar = st.one_of(
    st.sampled_from(JUNK_NUMBERS),
    st.sampled_from([0, 1, -1, -5, 2, 3, 2**31, 2**62, -(2**63), True, False]),
    junk_text,
)
index = st.integers(0, 10_000)


# ----------------------------------------------------------------------------- arrays
array_mutation = st.one_of(
    st.tuples(
        st.just("dtype"),
        st.sampled_from(["int64", "int8", "uint8", "bool", "float16", "float32", "complex128", "str", ">f8"]),
    ),
    st.tuples(
        st.just("shape"), st.sampled_from(["ravel", "slice", "none", "empty", "scalar", "grow", "transpose"]), index
    ),
    st.tuples(st.just("poke"), index, st.sampled_from(JUNK_NUMBERS)),
    st.tuples(st.just("scale"), st.sampled_from([-1.0, 0.0, 1e300, 1e-300, float("nan"), 1.001, 3.0])),
    st.tuples(st.just("random"), st.integers(0, 2**32 - 1)),
)


def mutate_array(a, m: tuple):
    """`a` (any numpy array or scalar) changed by one `array_mutation`."""
    a = np.array(a)
    kind = m[0]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kind == "dtype":
            if m[1] == "str":
                return np.array([str(x) for x in a.reshape(-1)[:8]], dtype=h5py.string_dtype())
            if a.dtype.kind in "fc" and np.dtype(m[1]).kind in "iub":
                a = np.nan_to_num(a.real)
            if a.dtype.kind in "SUO":
                return np.zeros(a.shape, dtype=m[1])
            return a.astype(m[1])
        if kind == "shape":
            how, i = m[1], m[2]
            if how == "ravel":
                return a.reshape(-1)
            if how == "slice" and a.ndim:
                ax = i % a.ndim
                return np.take(a, range(max(a.shape[ax] - 1 - i % 3, 0)), axis=ax)
            if how == "none":
                return a[None]
            if how == "empty":
                return np.zeros((0,) + a.shape[1:], dtype=a.dtype)
            if how == "scalar":
                return a.reshape(-1)[0] if a.size else np.float64(1.0)
            if how == "grow" and a.ndim:
                return np.concatenate([a, a], axis=i % a.ndim)
            if how == "transpose":
                return a.T
            return a
        if a.dtype.kind not in "fciub" or a.size == 0:
            return a
        if kind == "poke":
            out = a.astype(np.float64) if a.dtype.kind != "c" else a.copy()
            out.reshape(-1)[m[1] % out.size] = m[2]
            return out.astype(a.dtype) if a.dtype.kind in "fc" else out
        if kind == "scale":
            return (a * m[1]).astype(a.dtype) if a.dtype.kind in "fc" else a * m[1]
        if kind == "random":
            rng = np.random.default_rng(m[1])
            return rng.normal(size=a.shape) * 10.0 ** rng.integers(-3, 4)
    return a


# ----------------------------------------------------------------------------- HDF5 trees
@dataclass
class Tree:
    """An HDF5 file as data: attributes {(group, name): value}, datasets {path: array}, empty groups."""

    attrs: dict[tuple[str, str], Any] = field(default_factory=dict)
    datasets: dict[str, Any] = field(default_factory=dict)
    groups: set[str] = field(default_factory=set)

    @classmethod
    def read(cls, path) -> Tree:
        t = cls()
        with h5py.File(path, "r") as f:
            for k, v in f.attrs.items():
                t.attrs[("/", k)] = v

            def visit(name, obj):
                if isinstance(obj, h5py.Dataset):
                    t.datasets[name] = obj[()]
                else:
                    t.groups.add(name)
                    for k, v in obj.attrs.items():
                        t.attrs[(name, k)] = v

            f.visititems(visit)
        return t

    def copy(self) -> Tree:
        return Tree(dict(self.attrs), dict(self.datasets), set(self.groups))

    def write(self, path) -> None:
        with h5py.File(path, "w") as f:
            for g in sorted(self.groups):
                if g not in f:
                    with contextlib.suppress(TypeError, ValueError):  # a dataset is in the way
                        f.require_group(g)
            for name, v in sorted(self.datasets.items()):
                try:
                    if name in f:
                        del f[name]
                    f.create_dataset(name, data=v)
                except (TypeError, ValueError):  # a dataset's parent became a dataset, or an odd dtype
                    pass
            for (g, k), v in sorted(self.attrs.items(), key=lambda kv: kv[0]):
                if g in f:
                    with contextlib.suppress(TypeError, ValueError):  # a value HDF5 cannot hold
                        f[g].attrs[k] = v


tree_mutation = st.one_of(
    st.tuples(st.just("drop"), index),
    st.tuples(st.just("rename"), index, st.sampled_from(["_x", "X", " ", "/..", "\u00e9"])),
    st.tuples(st.just("attr"), index, junk_scalar),
    st.tuples(st.just("attr_array"), index, st.sampled_from(["floats", "strings", "empty", "ints"])),
    st.tuples(st.just("json"), index, index, junk_scalar),
    st.tuples(st.just("array"), index, array_mutation),
    st.tuples(st.just("to_group"), index),
    st.tuples(st.just("to_dataset"), index, st.sampled_from(JUNK_NUMBERS)),
    st.tuples(st.just("add"), st.sampled_from(["extras/junk", "junk", "split/val", "model2/R", "one"]), index),
)


def _pick(names: list, target):
    if not names:
        return None
    if isinstance(target, str):
        return target if target in names else None
    return sorted(names, key=str)[target % len(names)]


def _json_mutate(obj, where: int, value):
    """`obj` (parsed JSON) with one leaf (the where-th, modulo) replaced by `value`, or an entry dropped."""
    leaves: list[tuple[Any, Any]] = []

    def walk(o):
        if isinstance(o, dict):
            for k in list(o):
                leaves.append((o, k))
                walk(o[k])
        elif isinstance(o, list):
            for i in range(len(o)):
                leaves.append((o, i))
                walk(o[i])

    walk(obj)
    if not leaves:
        return value
    parent, key = leaves[where % len(leaves)]
    if where % 5 == 0:  # drop the entry
        del parent[key]
    else:
        parent[key] = value if not isinstance(value, float) or np.isfinite(value) else str(value)
    return obj


def apply_tree_mutation(t: Tree, m: tuple) -> Tree:
    t = t.copy()
    kind = m[0]
    if kind == "drop":
        everything = [("a", k) for k in t.attrs] + [("d", k) for k in t.datasets] + [("g", k) for k in t.groups]
        hit = _pick(everything, m[1])
        if hit is not None:
            what, k = hit
            if what == "a":
                del t.attrs[k]
            elif what == "d":
                del t.datasets[k]
            else:
                t.groups.discard(k)
                t.datasets = {n: v for n, v in t.datasets.items() if not n.startswith(k + "/")}
    elif kind == "rename":
        hit = _pick(list(t.attrs) + list(t.datasets), m[1])
        if isinstance(hit, tuple):
            t.attrs[(hit[0], hit[1] + m[2])] = t.attrs.pop(hit)
        elif hit is not None:
            t.datasets[hit + m[2]] = t.datasets.pop(hit)
    elif kind == "attr":
        k = _pick(list(t.attrs), m[1])
        if k is not None:
            t.attrs[k] = m[2]
    elif kind == "attr_array":
        k = _pick(list(t.attrs), m[1])
        if k is not None:
            t.attrs[k] = {
                "floats": np.array([1.0, float("nan"), 3.0]),
                "strings": np.array(["se3", "so3"], dtype=h5py.string_dtype()),
                "empty": np.zeros(0),
                "ints": np.array([-1, 0, 7]),
            }[m[2]]
    elif kind == "json":
        k = _pick(list(t.attrs), m[1])
        if k is not None:
            v = t.attrs[k]
            v = v.decode() if isinstance(v, bytes) else v
            try:
                obj = json.loads(v) if isinstance(v, str) else None
            except ValueError:
                obj = None
            if obj is not None:
                t.attrs[k] = json.dumps(_json_mutate(obj, m[2], m[3]))
    elif kind == "array":
        k = _pick(list(t.datasets), m[1])
        if k is not None:
            t.datasets[k] = mutate_array(t.datasets[k], m[2])
    elif kind == "to_group":
        k = _pick(list(t.datasets), m[1])
        if k is not None:
            del t.datasets[k]
            t.groups.add(k)
    elif kind == "to_dataset":
        k = _pick(sorted(t.groups), m[1])
        if k is not None:
            t.groups.discard(k)
            t.datasets = {n: v for n, v in t.datasets.items() if not n.startswith(k + "/")}
            t.attrs = {a: v for a, v in t.attrs.items() if a[0] != k}
            t.datasets[k] = np.full(3, m[2])
    elif kind == "add":
        t.datasets[m[1]] = np.arange(m[2] % 7, dtype=np.float64)
    return t


# ----------------------------------------------------------------------------- array dicts (NPZ)
dict_mutation = st.one_of(
    st.tuples(st.just("drop"), index),
    st.tuples(st.just("rename"), index, st.sampled_from(["_x", "X", "q", "R", "t"])),
    st.tuples(st.just("array"), index, array_mutation),
    st.tuples(st.just("set"), index, junk_scalar),
    st.tuples(st.just("add"), st.sampled_from(["q", "R", "p", "t", "body_names", "junk"]), array_mutation),
)


def apply_dict_mutation(d: dict, m: tuple) -> dict:
    d = dict(d)
    k = _pick(list(d), m[1]) if m[0] != "add" else None
    if m[0] == "drop" and k is not None:
        del d[k]
    elif m[0] == "rename" and k is not None:
        d[m[2] if m[2] not in d else k + m[2]] = d.pop(k)
    elif m[0] == "array" and k is not None:
        d[k] = mutate_array(d[k], m[2])
    elif m[0] == "set" and k is not None:
        d[k] = np.array(m[2])
    elif m[0] == "add":
        base = next(iter(d.values())) if d else np.zeros(3)
        d[m[1]] = mutate_array(base, m[2])
    return d


# ----------------------------------------------------------------------------- text (CSV, BVH)
text_mutation = st.one_of(
    st.tuples(st.just("delete"), index),
    st.tuples(st.just("duplicate"), index),
    st.tuples(st.just("swap"), index, index),
    st.tuples(st.just("token"), index, index, junk_text),
    st.tuples(st.just("header"), index, junk_text),
    st.tuples(st.just("insert"), index, st.text(text_chars, max_size=30)),
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("newlines"), st.sampled_from(["\r", "\r\n", "\n\n"])),
    st.tuples(st.just("tail"), st.binary(min_size=1, max_size=20)),
)


def apply_text_mutation(data: bytes, m: tuple, sep: str | None) -> bytes:
    """`data` (UTF-8 text) with one text mutation; `sep`: the token separator (None: whitespace)."""
    kind = m[0]
    if kind == "tail":
        return data + m[1]
    if kind == "truncate":
        return data[: int(m[1] * len(data))]
    text = data.decode("utf-8", "replace")
    lines = text.split("\n")
    n = len(lines)
    if kind == "delete":
        del lines[m[1] % n]
    elif kind == "duplicate":
        i = m[1] % n
        lines.insert(i, lines[i])
    elif kind == "swap":
        i, j = m[1] % n, m[2] % n
        lines[i], lines[j] = lines[j], lines[i]
    elif kind in ("token", "header"):
        i = 0 if kind == "header" else m[1] % n
        j, junk = (m[1], m[2]) if kind == "header" else (m[2], m[3])
        toks = lines[i].split(sep)
        if toks:
            toks[j % len(toks)] = junk
            lines[i] = (sep if sep is not None else " ").join(toks)
    elif kind == "insert":
        lines.insert(m[1] % (n + 1), m[2])
    elif kind == "newlines":
        return m[1].join(lines).encode()
    return "\n".join(lines).encode()


# ----------------------------------------------------------------------------- bytes (any file)
byte_mutation = st.one_of(
    st.tuples(st.just("truncate"), st.floats(0.0, 1.0)),
    st.tuples(st.just("flip"), st.floats(0.0, 1.0), st.binary(min_size=1, max_size=16)),
    st.tuples(st.just("replace"), st.binary(max_size=64)),
)


def apply_byte_mutation(data: bytes, m: tuple) -> bytes:
    if m[0] == "truncate":
        return data[: int(m[1] * len(data))]
    if m[0] == "flip":
        i = min(int(m[1] * len(data)), max(len(data) - 1, 0))
        return data[:i] + m[2] + data[i + len(m[2]) :]
    return m[1]


# ----------------------------------------------------------------------------- the property
def check_outcome(load, path: Path, names: tuple[str, ...] = ()):
    """Run `load()`: return its result, or None after a clean refusal. A clean refusal is a
    `LiedflError` whose message is one line naming `path` (or one of `names`); anything else (another
    exception, a multi-line message, a message naming no file, a warning other than liedfl's own)
    fails the test."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        e = None
        try:
            result = load()
        except LiedflError as err:
            e = err
            msg = str(e)
            assert "\n" not in msg.strip(), f"multi-line error: {msg!r}"
            assert any(str(n) in msg for n in (str(path), *names)), f"error names no file: {msg!r}"
            result = None
    log = os.environ.get("LIEDFL_FUZZ_LOG")  # outcome tally of a run (which checks the sample reached)
    if log:
        with open(log, "a") as f:
            f.write(("loaded" if result is not None else str(e).replace(str(path), "<file>")[:90]) + "\n")
    foreign = [w for w in caught if not issubclass(w.category, LiedflWarning)]
    assert not foreign, f"a warning other than liedfl's own: {foreign[0].category.__name__}: {foreign[0].message}"
    return result
