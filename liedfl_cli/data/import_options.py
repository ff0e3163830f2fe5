"""Options of `dataset=import` that say what a recording means: its time unit (`time_unit`), which of
its columns hold what (`columns`, and the common headers recognised without it) and the gravity the
user declares for it (`gravity`). `files.py` reads the recording; this module only interprets names,
units and declarations (one-line ConfigError / DatasetError naming the key or the file).

Canonical CSV columns: `t`, `trajectory`, `q0..q3` (in the order `dataset.rotation` says),
`r00..r22`, `x y z`; with `bodies: [a, b]` each body's columns are prefixed (`a.q0`, `a.x`).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from ..errors import ConfigError, DatasetError, DataWarning

TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}
"""Seconds per unit of the time stamps (`dataset.time_unit`; null = seconds, unconfirmed)."""

QUAT_NAMES = {"wxyz": ("w", "x", "y", "z"), "xyzw": ("x", "y", "z", "w")}
"""Component held by q0..q3 for each quaternion order."""
_QUAT_ALIASES = ("q{c}", "q_{c}", "quat_{c}", "quat.{c}", "quaternion_{c}", "orientation_{c}", "rot_{c}")
_POS_ALIASES = ("p{c}", "p_{c}", "pos_{c}", "pos.{c}", "position_{c}")
_TIME_ALIASES = ("time", "timestamp", "time_s", "stamp")
NPZ_ARRAYS = ("t", "q", "R", "p", "body_names")


def canonical_columns(rotation: str, prefix: str = "") -> tuple[str, ...]:
    rot = tuple(f"r{i}{j}" for i in range(3) for j in range(3)) if rotation == "matrix" else ("q0", "q1", "q2", "q3")
    return tuple(prefix + k for k in (*rot, "x", "y", "z"))


# --------------------------------------------------------------------------- time
def check_time_unit(c: dict) -> float:
    """Seconds per stamp unit of `dataset.time_unit` (null: 1.0)."""
    unit = c.get("time_unit")
    if unit is None:
        return 1.0
    if not isinstance(unit, str) or unit not in TIME_UNITS:
        raise ConfigError(f"dataset.time_unit={unit!r}: choose s, ms or us (or null for seconds)")
    return TIME_UNITS[unit]


def warn_if_milliseconds(c: dict, h: float, stamps: list[np.ndarray], where: str) -> None:
    """One DataWarning when seconds were assumed (time_unit null, time_scale 1) but the step is 1 s or
    more between integer time stamps: the look of milliseconds (a 20 ms step read as 20 s)."""
    if c.get("time_unit") is not None or float(c.get("time_scale", 1.0)) != 1.0 or h < 1.0:
        return
    if all(np.all(s == np.round(s)) for s in stamps):
        warnings.warn(
            f"{where}: step h = {h:g} s between integer time stamps looks like milliseconds; "
            "set dataset.time_unit=ms (or dataset.time_unit=s to keep seconds and silence this)",
            DataWarning,
            stacklevel=3,
        )


# --------------------------------------------------------------------------- gravity
def gravity_params(c: dict) -> dict:
    """`dataset.gravity` as the dataset's declaration (params fields read by `model.potential=auto`):
    null -> {} (nothing declared); none / 0 / false -> {"gravity": 0.0} (no gravity); a number g > 0
    -> {"gravity": g} (along -e3); a 3-vector a (the acceleration, world frame) -> {"gravity": |a|,
    "gravity_up": -a / |a|}."""
    v = c.get("gravity")
    if v is None:
        return {}
    if v is False or (isinstance(v, str) and v.strip().lower() == "none"):
        return {"gravity": 0.0}
    bad = ConfigError(
        f"dataset.gravity={v!r}: null (undeclared), none (no gravity), a magnitude g >= 0 along -e3 "
        "(e.g. 9.81) or the acceleration vector in the world frame (e.g. [0,0,-9.81])"
    )
    if isinstance(v, bool):
        raise bad
    if isinstance(v, (int, float)):
        if not math.isfinite(v) or v < 0:
            raise bad
        return {"gravity": float(v)}
    if isinstance(v, (list, tuple)):
        if len(v) != 3 or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v):
            raise bad
        a = np.asarray(v, dtype=np.float64)
        g = float(np.linalg.norm(a))
        if not math.isfinite(g):
            raise bad
        if g == 0.0:
            return {"gravity": 0.0}
        up = [float(x) for x in -a / g]
        return (
            {"gravity": g} if np.allclose(up, [0.0, 0.0, 1.0], rtol=0, atol=1e-12) else {"gravity": g, "gravity_up": up}
        )
    raise bad


# --------------------------------------------------------------------------- columns
def check_columns(c: dict) -> dict[str, str]:
    """`dataset.columns` as {canonical name: the file's column} ({} when null). A list names the
    rotation columns (q0..q3 or r00..r22) and optionally x, y, z, in that order (one body)."""
    raw = c.get("columns")
    if raw is None:
        return {}
    rotation = c.get("rotation")
    canon = canonical_columns(str(rotation)) if rotation in ("wxyz", "xyzw", "matrix") else ()
    if isinstance(raw, (list, tuple)):
        n_rot = len(canon) - 3
        if not canon or len(raw) not in (n_rot, n_rot + 3) or c.get("bodies") is not None:
            raise ConfigError(
                f"dataset.columns={list(raw)!r}: a list names the {n_rot or 4} rotation columns (q0..q3, or r00..r22 "
                "with rotation=matrix) and optionally x, y, z, in that order, for one body; otherwise a mapping "
                "{q0: qw, ...}"
            )
        raw = dict(zip(canon, raw))
    if not isinstance(raw, dict):
        raise ConfigError(f"dataset.columns={raw!r}: a mapping {{canonical: file column}} (e.g. {{q0: qw}}) or a list")
    names = set(canonical_columns("wxyz")) | set(canonical_columns("matrix")) | {"t", "trajectory"} | set(NPZ_ARRAYS)
    bodies = c.get("bodies") or []
    out = {}
    for k, v in raw.items():
        base = str(k).split(".", 1)[1] if "." in str(k) and str(k).split(".", 1)[0] in bodies else str(k)
        if base not in names:
            raise ConfigError(
                f"dataset.columns.{k}: unknown column (map t, trajectory, q0..q3, r00..r22, x, y, z, "
                "with bodies <body>.q0 ..., or the NPZ arrays t, q, R, p, body_names)"
            )
        if not isinstance(v, str) or not v.strip():
            raise ConfigError(f"dataset.columns.{k}={v!r}: must be a column name of the file")
        out[str(k)] = v.strip()
    return out


class ColumnFinder:
    """Finds the canonical columns in a CSV header: `dataset.columns` first, then the exact name, then
    the common spellings (case-insensitive): time `time`, `timestamp`; quaternion components `qw`,
    `q_w`, `quat_w`, ... (matched by the component's name, so their order does not matter) or bare
    `w, x, y, z` when the header has a `w` column; positions `px`, `pos_x`, `position_x`, ...
    `used` records which file column each canonical name came from."""

    def __init__(self, header: list[str], c: dict, path):
        self.header, self.path, self.rotation = header, path, c["rotation"]
        self.mapping = check_columns(c)
        self.exact = {h: i for i, h in enumerate(header)}
        self.lower: dict[str, int] = {}
        for i, h in enumerate(header):
            self.lower.setdefault(h.lower(), i)
        self.used: dict[str, str] = {}
        self.taken: set[int] = set()

    def _mapped(self, name: str) -> int | None:
        if name not in self.mapping:
            return None
        col = self.mapping[name]
        if col not in self.exact:
            raise DatasetError(
                f"{self.path}: dataset.columns.{name}={col}: no such column (header: {', '.join(self.header)})"
            )
        return self.exact[col]

    def _take(self, name: str, i: int) -> int:
        self.used[name] = self.header[i]
        self.taken.add(i)
        return i

    def find(self, name: str, aliases: tuple[str, ...] = ()) -> int | None:
        """The column of canonical `name` (None if absent)."""
        i = self._mapped(name)
        if i is None and name in self.exact and self.exact[name] not in self.taken:
            i = self.exact[name]
        if i is None:
            i = next(
                (self.lower[a.lower()] for a in aliases if self.lower.get(a.lower()) not in (None, *self.taken)), None
            )
        return None if i is None else self._take(name, i)

    def need(self, name: str, aliases: tuple[str, ...] = ()) -> int:
        i = self.find(name, aliases)
        if i is None:
            hint = " or map it with dataset.columns" if name != "t" else " (or set dataset.time_column)"
            raise DatasetError(f"{self.path}: column '{name}' is missing (header: {', '.join(self.header)}){hint}")
        return i

    def time(self, name: str) -> int:
        """The time column: `dataset.columns.t`, else `dataset.time_column` (default `t`: also `time`, ...)."""
        i = self._mapped("t")
        return self._take("t", i) if i is not None else self.need(name, _TIME_ALIASES if name == "t" else ())

    def trajectory(self, name: str) -> int | None:
        i = self._mapped("trajectory")
        return self._take("trajectory", i) if i is not None else self.find(name)

    def rotation_columns(self, prefix: str) -> list[int]:
        if self.rotation == "matrix":
            return [self.need(f"{prefix}r{i}{j}") for i in range(3) for j in range(3)]
        comps = QUAT_NAMES[self.rotation]
        bare_w = f"{prefix}w".lower() in self.lower and not any(f"{prefix}q{k}" in self.exact for k in range(4))
        out = []
        for k, comp in enumerate(comps):
            aliases = tuple(prefix + a.format(c=comp) for a in _QUAT_ALIASES) + ((prefix + comp,) if bare_w else ())
            out.append(self.need(f"{prefix}q{k}", aliases))
        return out

    def position_columns(self, prefix: str) -> list[int | None]:
        return [self.find(prefix + comp, tuple(prefix + a.format(c=comp) for a in _POS_ALIASES)) for comp in "xyz"]


__all__ = [
    "TIME_UNITS",
    "check_time_unit",
    "warn_if_milliseconds",
    "gravity_params",
    "check_columns",
    "ColumnFinder",
    "canonical_columns",
]
