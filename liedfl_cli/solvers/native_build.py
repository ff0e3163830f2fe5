"""Native code of the rollouts: a C++ source of the package built on first use with the C++ compiler
torch.compile uses (`solvers.compile.cxx`), once per source, compiler and CPU, and loaded with ctypes.

Built into `$LIEDFL_NATIVE_CACHE` (default `~/.cache/liedfl/native`) under a temporary name, then renamed,
so a failed or interrupted build never leaves a library behind; tuned for this CPU (`FLAGS`), else portable
(`PORTABLE_FLAGS`, for a compiler that refuses -march=native). No compiler, or a build that fails: None and
one printed line, and the caller keeps its torch engine. The users are the articulated model's native step
(`models.articulated.engines.native`) and a single SO(3) body's (`models.liedflnn.engines.native`).
"""

from __future__ import annotations

import ctypes
import hashlib
import itertools
import os
import platform
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from . import compile as compile_cache

FLAGS = ("-O3", "-march=native", "-shared", "-fPIC", "-std=c++17", "-pthread")
PORTABLE_FLAGS = tuple(f for f in FLAGS if f != "-march=native")
HEADERS = (Path(__file__).with_name("native_math.hpp"),)
"""What every native source includes (compiled with this folder on the include path, hashed into the keys)."""


def cpu_signature() -> str:
    """The CPU model and features (-march=native code is built per CPU)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
        lines = [ln for ln in text.splitlines() if ln.startswith(("model name", "flags"))][:2]
        return "\n".join(lines)
    except OSError:
        return platform.processor() or platform.machine()


def cache_dir() -> Path:
    return Path(os.environ.get("LIEDFL_NATIVE_CACHE") or Path.home() / ".cache" / "liedfl" / "native")


def build(source: Path, cxx: str, folder: Path, what: str) -> Path | None:
    """The shared library of `source` built by compiler `cxx` in `folder` (unless already cached there),
    named `<stem>_<key>.so` with key a hash of the source and `HEADERS`, the compiler's version, the flags and
    the CPU;
    None with one printed line naming `what` when the build fails (module docstring)."""
    text = b"\0".join([source.read_bytes(), *(h.read_bytes() for h in HEADERS)])
    try:
        version = subprocess.run([cxx, "--version"], capture_output=True, text=True, timeout=60).stdout
    except (OSError, subprocess.SubprocessError):
        version = ""
    last = "?"
    for flags in (FLAGS, PORTABLE_FLAGS):
        key = hashlib.sha256(b"\0".join([text, version.encode(), " ".join(flags).encode(), cpu_signature().encode()]))
        target = folder / f"{source.stem}_{key.hexdigest()[:16]}.so"
        if target.exists():
            return target
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=folder) as tmp:
                built = Path(tmp) / target.name
                cmd = [cxx, *flags, "-I", str(HEADERS[0].parent), str(source), "-o", str(built)]
                proc = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
                if proc.returncode == 0 and built.exists():
                    os.replace(built, target)
                    return target
                last = (proc.stderr.strip().splitlines() or [f"exit {proc.returncode}"])[-1]
        except (OSError, subprocess.SubprocessError) as e:
            last = str(e)
    compile_cache.say_once(f"runtime.compile: building {what} failed ({last})")
    return None


def load(source: Path, argtypes: dict[str, list], what: str) -> ctypes.CDLL | None:
    """`source` built (`build`) and loaded, each of its functions in `argtypes` (name -> ctypes argument types)
    declared with its types (a call with other arguments raises instead of reaching the C++) and an int
    result; None without a compiler or when the build fails (said once on stderr). Callers keep the result
    (an lru_cache)."""
    cxx = compile_cache.cxx()
    if cxx is None:
        compile_cache.say_once("runtime.compile: no C++ compiler found (g++/c++/clang++), running the fused paths")
        return None
    path = build(source, cxx, cache_dir(), what)
    if path is None:
        return None
    lib = ctypes.CDLL(str(path))
    for symbol, types in argtypes.items():
        fn = getattr(lib, symbol)
        fn.restype = ctypes.c_int
        fn.argtypes = types
    return lib


def kept_on_model(model, like: torch.Tensor, name: str, make: Callable[[Any, torch.Tensor], Any]) -> Any:
    """`make(model, like)` (a native engine's constants, read from the model's parameters), kept on the model
    under `name` while its step, parameters and buffers are unchanged, so a short rollout does not read the
    parameters again. Unchanged means equal values, not only the same tensors: an in-place edit through
    `.data` (which no version counter sees) rebuilds it too. The models served have few parameters, so the
    comparison costs microseconds."""
    owned = list(itertools.chain(model.parameters(), model.buffers()))
    tensors = [t.detach() for t in owned]
    key = (float(model.h), like.dtype, like.device, tuple(id(t) for t in owned))
    cached = model.__dict__.get(name)
    if (
        cached is not None
        and cached[0] == key
        and all(a.shape == b.shape and torch.equal(a, b) for a, b in zip(cached[2], tensors, strict=True))
    ):
        return cached[1]
    engine = make(model, like)
    model.__dict__[name] = (key, engine, [t.clone() for t in tensors])
    return engine


def run_in_chunks(run: Callable[[int], dict], rows: int, steps: int, row_steps: int, progress=None) -> list[dict]:
    """A native rollout's steps 1 .. steps-1 as calls `run(count)` of ~`row_steps` trajectory-steps each (for
    `rows` trajectories), so that progress is reported after each call, step by step, and signals are handled
    between calls: the calls' outputs, in order (empty without steps)."""
    chunks, k = [], 1
    per_call = max(1, row_steps // max(rows, 1))
    while k < steps:
        count = min(per_call, steps - k)
        chunks.append(run(count))
        if progress is not None:
            for j in range(k, k + count):
                progress(j)
        k += count
    return chunks
