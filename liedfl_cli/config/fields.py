"""An option declared once: the dataclass field of its config section, with its check beside it.

A field of a section dataclass (`config/typed.py`) is written `name: type = option(default, ...)`:
the one place that says the option's type, default, allowed values (a `Literal` alias, read with
`typing.get_args`, or the tuple of the layer that implements it), bounds and the commands that
need it. `Checked.__post_init__` runs the checks, so `OmegaConf.to_object`, and any direct
construction, refuse a bad value as one `ConfigError` line naming the key (`train.loss='newtn':
choose one of del, newton, rollout`); `required_keys(schema, command)` lists the keys a command
needs (`schema.validate` reports one removed by an override). OmegaConf 2.3's structured configs
do not accept `Literal` annotations, so a field with choices is annotated `str` and its `Literal`
type is given to `option(choices_of=...)`; code that lists the values reads them from the field
(`allowed(TopKeys, "split")`).
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any, ClassVar

from ..errors import ConfigError

ALL_COMMANDS = ("train", "data", "rollout", "eval", "export", "report", "resume")


@dataclass(frozen=True)
class Check:
    """What one option accepts (None: no constraint of that kind) and which commands need it."""

    choices: tuple[Any, ...] | None = None  # allowed values (from a Literal alias)
    integer: int | None = None  # an integer >= this
    number: str | None = None  # "positive" | "nonnegative" | "finite"
    nullable: bool = False  # None is accepted
    auto: bool = False  # "auto" is accepted (an integer option)
    what: str | None = None  # the wording of the requirement, where the default one does not fit
    required: tuple[str, ...] = ()  # commands whose config must hold the key
    each_of: tuple[Any, ...] | None = None  # a list of distinct values, each one of these (or a scalar of choices)
    item: str = "value"  # what one value of such a list is called in the error ("part")

    def problem(self, v: Any) -> str | None:
        """The requirement `v` breaks, in words ("must be ...", "choose one of ..."), or None."""
        if v is None and self.nullable:
            return None
        if self.each_of is not None and isinstance(v, (list, tuple)):
            bad = [x for x in v if x not in self.each_of]
            if bad:
                return f"unknown {self.item} {bad[0]!r}; choose from {', '.join(str(c) for c in self.each_of)}"
            return f"a {self.item} is given twice" if len(set(map(str, v))) != len(v) else None
        if self.auto and v == "auto":
            return None
        if self.choices is not None:
            if v not in self.choices:
                return f"choose one of {', '.join(str(c) for c in self.choices)}"
            return None
        if self.integer is not None:
            if not (_is_int(v) and v >= self.integer):
                need = self.what or ("a positive integer" if self.integer == 1 else f"an integer >= {self.integer}")
                return f"must be {need}" + (" or null" if self.nullable and not self.what else "")
            return None
        if self.number is not None:
            ok = _is_number(v) and math.isfinite(v)
            ok = ok and not (self.number == "positive" and v <= 0) and not (self.number == "nonnegative" and v < 0)
            if not ok:
                words = {"positive": "a positive number", "nonnegative": "a number >= 0"}
                return f"must be {self.what or words.get(self.number, 'a finite number')}"
        return None


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def choices(alias: Any) -> tuple[Any, ...]:
    """The values of a `Literal[...]` alias, or of a tuple a lower layer declares (None inside it:
    the option may be null)."""
    values = alias if isinstance(alias, tuple) else typing.get_args(alias)
    return tuple(a for a in values if a is not None)


def check(
    *,
    choices_of: Any = None,
    integer: int | None = None,
    number: str | None = None,
    nullable: bool = False,
    auto: bool = False,
    what: str | None = None,
    required: tuple[str, ...] = (),
) -> Check:
    """A `Check` (for `option`, or for `Checked.checks` of fields inherited from another layer)."""
    if choices_of is not None:
        nullable = nullable or None in (choices_of if isinstance(choices_of, tuple) else typing.get_args(choices_of))
    allowed = choices(choices_of) if choices_of is not None else None
    return Check(allowed, integer, number, nullable, auto, what, required)


def option(default: Any = dataclasses.MISSING, *, default_factory: Any = dataclasses.MISSING, **kw: Any) -> Any:
    """A dataclass field with its check in the metadata (the keywords of `check`)."""
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata={"check": check(**kw)})
    return dataclasses.field(default=default, metadata={"check": check(**kw)})


def field_checks(schema: Any) -> dict[str, Check]:
    """Field name -> its `Check`: from the field's metadata, else from the class's `checks` (fields
    declared by a dataclass of another layer, e.g. `SolverOptions`). A layer below the config system
    (a model's `Options`, models/base.py) declares its values in plain metadata: `{"choices": (...)}`
    and / or `{"each_of": (...), "item": "part"}` (a list of distinct values)."""
    out = dict(getattr(schema, "checks", {}) or {})
    for f in dataclasses.fields(schema):
        c = f.metadata.get("check")
        if c is None and ("choices" in f.metadata or "each_of" in f.metadata):
            c = Check(
                choices=tuple(f.metadata["choices"]) if "choices" in f.metadata else None,
                each_of=tuple(f.metadata["each_of"]) if "each_of" in f.metadata else None,
                item=str(f.metadata.get("item", "value")),
            )
        if c is not None:
            out[f.name] = c
    return out


def check_values(values: Any, schema: Any, section: str) -> None:
    """`check_fields` on a plain mapping of a section's values (the keys it holds)."""
    for name, c in field_checks(schema).items():
        if isinstance(values, dict) and name in values:
            problem = c.problem(values[name])
            if problem is not None:
                raise ConfigError(f"{section}.{name}={shown(values[name])}: {problem}")


def allowed(schema: Any, name: str) -> tuple[Any, ...]:
    """The allowed values the field `name` of `schema` declares (for code that lists them)."""
    values = field_checks(schema)[name].choices
    assert values is not None, f"{schema.__name__}.{name} declares no choices"
    return values


def shown(v: Any) -> str:
    """A value as it was configured: a whole float given to a number field (`-1` read as `-1.0`)
    is shown as the integer the user typed."""
    if isinstance(v, float) and math.isfinite(v) and v.is_integer():
        return repr(int(v))
    return repr(v)


def check_fields(obj: Any, section: str) -> None:
    """Every field's check on `obj`; the first broken one as a ConfigError naming `section.field`."""
    for name, c in field_checks(type(obj)).items():
        v = getattr(obj, name)
        problem = c.problem(v)
        if problem is not None:
            key = f"{section}.{name}" if section else name
            raise ConfigError(f"{key}={shown(v)}: {problem}")


class Checked:
    """Mixin of a section dataclass whose fields carry their checks: `section` is the key prefix of
    its errors ("" for top-level keys), `checks` the checks of inherited fields."""

    section: ClassVar[str] = ""
    checks: ClassVar[dict[str, Check]] = {}

    def __post_init__(self) -> None:
        check_fields(self, self.section)


def required_keys(schema: Any, command: str, prefix: str) -> tuple[str, ...]:
    """The dotted keys of `schema`'s fields (nested dataclasses included) that `command` needs."""
    out: list[str] = []
    hints = typing.get_type_hints(schema)
    checks = field_checks(schema)
    for f in dataclasses.fields(schema):
        key = f"{prefix}.{f.name}" if prefix else f.name
        c = checks.get(f.name)
        if c is not None and command in c.required:
            out.append(key)
        sub = hints.get(f.name)
        if isinstance(sub, type) and dataclasses.is_dataclass(sub):
            out.extend(required_keys(sub, command, key))
    return tuple(out)


__all__ = [
    "ALL_COMMANDS",
    "Check",
    "allowed",
    "Checked",
    "check",
    "check_fields",
    "choices",
    "option",
    "required_keys",
    "shown",
]
