"""Process-wide execution settings of the numerical engine (`runtime` config section): threads,
fused paths, compilation, device and dtype.

    runtime.threads   auto | N   torch intra-op threads (auto: 1, measured fastest here; 1 per job
                                 under the joblib launcher whatever N says)
    runtime.fused     true | false   the path of the models built while it is in force (false: the
                                 reference paths, for comparison); read once per model, at its
                                 construction (`models.base.ImplicitModel.path`)
    runtime.compile   auto | true | false   torch.compile (CPU inductor) of the fused hot paths;
                                 auto compiles only work large enough to repay the compilation
                                 (docs/benchmarks.md); without a C++ compiler it falls back to
                                 eager, saying so once.
    runtime.device    cpu | cuda | auto   where models and data live (auto: cuda when torch sees a
                                 CUDA device, else cpu; cuda without one: one-line ConfigError)
    runtime.dtype     float64 | float32   floating-point type of models and data (float32: poses are
                                 re-orthonormalised every rollout step, README "Runtime settings")

The models and solvers read `current()` for threads, compilation and, when a model is built, its path: the device
and dtype are the pipeline's (`placement()`, used by `factory.build_model` and the commands), and
models and solvers take them from their inputs. The pipeline calls `configure(cfg.runtime)` once per
command (`factory.configure_runtime`, which knows about Hydra's launchers; this module does not).
`using(...)` switches settings temporarily (tests, benchmarks).
"""

from __future__ import annotations

import contextlib
import functools
import os
import shutil
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from typing import Any

import torch

from ..errors import ConfigError

COMPILE_CHOICES = ("auto", "true", "false")
DEVICE_CHOICES = ("cpu", "cuda", "auto")
DTYPES = {"float64": torch.float64, "float32": torch.float32}
"""`runtime.dtype` names -> torch dtypes (the one place below the pipeline that names them)."""
DEFAULT_THREADS = 1
"""Threads for `runtime.threads: auto` (docs/benchmarks.md: on the 2-core machine one thread was
as fast as two on an idle machine at the batch sizes used here and several times faster when
other work shares the cores)."""

COMPILE_MIN_WORK = {"rollout": 5.0e7, "train": 1.0e5}
"""`compile: auto` compiles a hot path only for work large enough to repay the one-off compilation
(tens of seconds on 2 cores, docs/benchmarks.md): a rollout of trajectories x steps row-steps, a
training run of optimiser steps."""


@dataclass(frozen=True)
class RuntimeOptions:
    threads: int | str = "auto"
    fused: bool = True
    compile: str = "auto"
    device: str = "cpu"
    dtype: str = "float64"

    def __post_init__(self) -> None:
        """Check the values (one-line ConfigError naming the key); `compile` given as a boolean
        (`runtime.compile=true`) becomes "true" / "false"."""
        threads = self.threads
        if not (threads == "auto" or (isinstance(threads, int) and not isinstance(threads, bool) and threads >= 1)):
            raise ConfigError(f"runtime.threads={threads!r}: choose auto or a positive integer")
        comp = self.compile
        comp = {True: "true", False: "false"}.get(comp, comp) if isinstance(comp, bool) else str(comp)
        if comp not in COMPILE_CHOICES:
            raise ConfigError(f"runtime.compile={self.compile!r}: choose one of {', '.join(COMPILE_CHOICES)}")
        object.__setattr__(self, "compile", comp)
        if not isinstance(self.fused, bool):
            raise ConfigError(f"runtime.fused={self.fused!r}: choose true or false")
        if self.device not in DEVICE_CHOICES:
            raise ConfigError(f"runtime.device={self.device!r}: choose one of {', '.join(DEVICE_CHOICES)}")
        if self.dtype not in DTYPES:
            raise ConfigError(f"runtime.dtype={self.dtype!r}: choose one of {', '.join(DTYPES)}")


_current = RuntimeOptions()


def current() -> RuntimeOptions:
    return _current


def resolve_threads(threads: int | str, parallel_job: bool = False) -> int:
    """Threads to use: a number as given (capped at the cores), auto -> DEFAULT_THREADS; 1 in a
    parallel sweep job (the jobs already share the cores)."""
    if parallel_job:
        return 1
    if threads == "auto":
        return DEFAULT_THREADS
    return max(1, min(int(threads), os.cpu_count() or 1))


def configure(opts: RuntimeOptions | None = None, parallel_job: bool = False) -> RuntimeOptions:
    """Apply the runtime settings for this process (None: the defaults); returns the options in
    force. `parallel_job`: this process is one of several sweep jobs run side by side (joblib)."""
    global _current
    opts = opts if opts is not None else RuntimeOptions()
    resolve_device(opts.device)  # cuda without a CUDA device: fail before any work
    torch.set_num_threads(resolve_threads(opts.threads, parallel_job))
    _current = opts
    return opts


def resolve_device(name: str) -> torch.device:
    """`runtime.device` -> the torch device: cpu; cuda (ConfigError when torch sees no CUDA device);
    auto: cuda when torch sees one, else cpu."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError(
            f"runtime.device=cuda: no CUDA device is available (torch {torch.__version__}, "
            f"CUDA build {torch.version.cuda or 'none'}); use runtime.device=cpu or auto"
        )
    if name not in DEVICE_CHOICES:
        raise ConfigError(f"runtime.device={name!r}: choose one of {', '.join(DEVICE_CHOICES)}")
    return torch.device(name)


def placement() -> tuple[torch.device, torch.dtype]:
    """(device, dtype) of the current settings, for the pipeline: models are built, then moved there
    (`factory.build_model`); datasets are converted there after loading."""
    opts = current()
    return resolve_device(opts.device), DTYPES[opts.dtype]


@contextlib.contextmanager
def using(**changes: Any) -> Iterator[RuntimeOptions]:
    """Temporarily replace some settings (threads are left as they are)."""
    global _current
    before = _current
    _current = replace(before, **changes)
    try:
        yield _current
    finally:
        _current = before


# ---------------------------------------------------------------------------- compilation
@functools.lru_cache(maxsize=1)
def compiler_available() -> bool:
    """True when torch.compile's CPU backend can build code here (a C++ compiler on PATH)."""
    cxx = os.environ.get("CXX")
    if cxx and shutil.which(cxx):
        return True
    return any(shutil.which(c) for c in ("g++", "c++", "clang++"))


_said_no_compiler = False


def _say_once(message: str) -> None:
    global _said_no_compiler
    if not _said_no_compiler:
        print(f"warning: {message}", file=sys.stderr, flush=True)
        _said_no_compiler = True


_planned: dict[str, float] = {}


def plan(kind: str, work: float) -> None:
    """Announce the size of the coming hot-path work ("rollout": row-steps, "train": optimiser
    steps), which `compile: auto` weighs against the compilation time."""
    _planned[kind] = float(work)


def want_compile(kind: str) -> bool:
    """Whether to compile the hot path `kind` ("rollout" | "train") under `runtime.compile` (asked by
    the fused paths only: a model built with `runtime.fused=false` never reaches it)."""
    opts = current()
    if opts.compile == "false":
        return False
    if opts.compile == "auto" and _planned.get(kind, 0.0) < COMPILE_MIN_WORK[kind]:
        return False
    if not compiler_available():
        _say_once("runtime.compile: no C++ compiler found (g++/c++/clang++), running the fused paths uncompiled")
        return False
    return True


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
            _say_once(f"runtime.compile: compilation failed ({type(e).__name__}), running uncompiled")
            _compiled[key] = fn
            return fn(*args, **kwargs)

    _compiled[key] = run
    return run
