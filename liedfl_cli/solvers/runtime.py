"""Process-wide execution settings of the numerical engine (`runtime` config section): threads,
fused paths, compilation, device and dtype.

    runtime.threads   auto | N   torch intra-op threads (auto: 1, measured fastest here; 1 per job
                                 under the joblib launcher whatever N says)
    runtime.fused     true | false   the path of the models the command builds (false: the reference
                                 paths, for comparison): their `ExecutionPlan.path`
    runtime.compile   auto | true | false   torch.compile (CPU inductor) of the fused hot paths;
                                 auto compiles only work large enough to repay the compilation
                                 (docs/benchmarks.md); without a C++ compiler it falls back to
                                 eager, saying so once.
    runtime.device    cpu | cuda | auto   where models and data live (auto: cuda when torch sees a
                                 CUDA device, else cpu; cuda without one: one-line ConfigError)
    runtime.dtype     float64 | float32   floating-point type of models and data (float32: poses are
                                 re-orthonormalised every rollout step, README "Runtime settings")

Nothing below the pipeline reads these settings. Threads are set for the process (`configure`); the
device and dtype are the pipeline's (`placement()`, used by `factory.build_model` and the commands),
and models and solvers take them from their inputs; `fused` and `compile` become each model's
`solvers.execution.ExecutionPlan` when the pipeline builds it (`ExecutionPlan.from_runtime`). The
pipeline calls `configure(cfg.runtime)` once per command (`factory.configure_runtime`, which knows
about Hydra's launchers; this module does not). `using(...)` switches settings temporarily (tests).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from dataclasses import dataclass, replace
from typing import Any

import torch

from ..errors import ConfigError
from .execution import COMPILE_CHOICES

DEVICE_CHOICES = ("cpu", "cuda", "auto")
DTYPES = {"float64": torch.float64, "float32": torch.float32}
"""`runtime.dtype` names -> torch dtypes (the one place below the pipeline that names them)."""
DEFAULT_THREADS = 1
"""Threads for `runtime.threads: auto` (docs/benchmarks.md: on the 2-core machine one thread was
as fast as two on an idle machine at the batch sizes used here and several times faster when
other work shares the cores)."""


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
