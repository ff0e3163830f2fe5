"""torch.compile of the fused hot paths: whether this machine can, and the compiled functions built
once per key (a cache of code, not a setting: what to compile is the `ExecutionPlan`'s decision)."""

from __future__ import annotations

import functools
import os
import shutil
import sys
from collections.abc import Callable
from typing import Any

import torch


def cxx() -> str | None:
    """The C++ compiler here: `$CXX` when it is on PATH, else the first of g++, c++, clang++; None without
    one (torch.compile's CPU backend and the native articulated step build with it)."""
    env = os.environ.get("CXX")
    if env and shutil.which(env):
        return env
    return next((c for c in ("g++", "c++", "clang++") if shutil.which(c)), None)


@functools.lru_cache(maxsize=1)
def compiler_available() -> bool:
    """True when torch.compile's CPU backend can build code here (a C++ compiler on PATH)."""
    return cxx() is not None


_said: set[str] = set()


def say_once(message: str) -> None:
    """Print `warning: message` to stderr, once per process for the compile warnings."""
    if not _said:
        print(f"warning: {message}", file=sys.stderr, flush=True)
        _said.add(message)


_compiled: dict[Any, Callable] = {}


def compiled(fn: Callable, key: Any = None) -> Callable:
    """`torch.compile(fn)` (dynamic batch size), built once per key; falls back to `fn` with one
    printed line when compilation fails (e.g. a broken toolchain)."""
    key = key if key is not None else fn
    if key in _compiled:
        return _compiled[key]
    compiled_fn = torch.compile(fn, dynamic=True)

    def run(*args, **kwargs):
        try:
            return compiled_fn(*args, **kwargs)
        except Exception as e:  # compilation needs a working toolchain; eager is always correct
            say_once(f"runtime.compile: compilation failed ({type(e).__name__}), running uncompiled")
            _compiled[key] = fn
            return fn(*args, **kwargs)

    _compiled[key] = run
    return run
