"""Skip Hydra's first composition of the config where its result is known.

`@hydra.main` composes the whole config twice per command: once in `Hydra.get_mode`, only to read
`hydra.mode`, and again to run the job (0.15–0.3 s each on the 2-core VM, of a command that reaches
its first line of work in ~3 s). `hydra.mode` is None (Hydra's default) unless a config file or an
override sets it, and None is also what `get_mode` returns when that first composition fails (the
second reports the error). So where nothing can set it, `get_mode` may return None without
composing, and Hydra goes on exactly as before (`-m` still selects a sweep: Hydra adds
`hydra.mode=MULTIRUN` itself when the mode is None).

Nothing can set it when no YAML file of the config directory has a `mode:` key at any level (a
textual scan: conservative, a comment is not a key) and no argument can bring one in: an override
of `hydra.mode`, `hydra.searchpath` or a `hydra/...` group, or a flag that adds or swaps config
files (`-cn/-cp/-cd`). Anything else keeps Hydra's own `get_mode`.
"""

from __future__ import annotations

import contextlib
import re
from collections.abc import Iterator, Sequence
from pathlib import Path

MODE_KEY = re.compile(r"^[ \t]*(hydra\.)?mode[ \t]*:", re.MULTILINE)
CONFIG_FLAGS = ("-cn", "-cp", "-cd", "--config-name", "--config-path", "--config-dir")
MODE_SOURCES = ("hydra.mode", "hydra.searchpath", "hydra/")


def _override_key(arg: str) -> str:
    """`hydra.mode` of `++hydra.mode=RUN`, `hydra/launcher` of `hydra/launcher=joblib`, `~hydra.mode`."""
    return arg.lstrip("+~").split("=", 1)[0].strip()


def mode_is_default(conf_dir: Path, args: Sequence[str]) -> bool:
    """Whether `hydra.mode` is certainly None for `liedfl <command> *args` with configs in `conf_dir`."""
    for arg in args:
        if arg.split("=", 1)[0] in CONFIG_FLAGS:
            return False
        key = _override_key(arg)
        if key == "hydra" or key.startswith(MODE_SOURCES):
            return False
    for path in conf_dir.rglob("*.yaml"):
        try:
            text = path.read_text(encoding="utf-8", errors="replace")
        except OSError:
            return False
        if MODE_KEY.search(text):
            return False
    return True


@contextlib.contextmanager
def without_mode_composition(conf_dir: Path, args: Sequence[str]) -> Iterator[bool]:
    """Within the block, Hydra's `get_mode` returns None without composing when `mode_is_default`
    (yields whether it does); otherwise, and after the block, it is Hydra's own."""
    try:
        from hydra._internal.hydra import Hydra
    except ImportError:  # pragma: no cover (another Hydra layout: keep Hydra's behaviour)
        yield False
        return
    original = getattr(Hydra, "get_mode", None)
    if original is None or not mode_is_default(conf_dir, args):
        yield False
        return

    def get_mode(self, config_name=None, overrides=()):
        return None

    Hydra.get_mode = get_mode  # type: ignore[method-assign]
    try:
        yield True
    finally:
        Hydra.get_mode = original  # type: ignore[method-assign]
