"""Shared test configuration.

The default torch dtype is deliberately left alone: every Lie-group test states its dtype.
A modest hypothesis profile keeps the property tests fast (select another one with
HYPOTHESIS_PROFILE=<name>, e.g. `thorough`).

Every test starts from the same engine state, whatever ran before it (`_fresh_runtime`): the default
`runtime` settings, no planned work, one torch thread (`runtime.threads: auto`), and `runtime.compile:
auto` never compiling in this process (a test that trains longer than the smoke budget must not pay
tens of seconds of compilation by accident; `@pytest.mark.compile_auto` keeps the real threshold, and
`runtime.compile=true` still compiles). Subprocesses are not covered: pass `runtime.compile=false`.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import pytest
import torch
from hypothesis import HealthCheck, settings

# Under pytest-xdist (`-n 2`) the worker processes start with COLUMNS=80 and LINES=24 in their
# environment (seen with pytest-xdist 3.8, execnet 2.1), which a single-process run does not have: the
# console (`display.ui`, imported below) would then wrap its lines at 80 columns instead of 160, and
# every `liedfl` subprocess would inherit them. Drop them so that a worker sees the environment of the
# plain `python -m pytest` run.
if "PYTEST_XDIST_WORKER" in os.environ:
    for _name in ("COLUMNS", "LINES"):
        os.environ.pop(_name, None)

import helpers
import liedfl_cli.config.resolvers  # noqa: F401  (the configs the tests compose use its resolvers)
from liedfl_cli.solvers import execution, runtime

settings.register_profile(
    "default-liedfl",
    deadline=None,
    max_examples=12,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("thorough", deadline=None, max_examples=300)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default-liedfl"))
helpers.cache_yaml_parses()  # each config file's YAML parsed once per session (helpers.py says why)


# ----------------------------------------------------------------------------- parallel runs
# `python -m pytest -n 2` (pytest-xdist, the README's command): two worker processes on two cores. Every
# thread pool of a worker then gets one thread, not one per core, so that the pools of the two workers
# (OpenMP in torch, OpenBLAS in numpy/scipy) do not oversubscribe the cores; that covers what runs
# outside a test's `_fresh_runtime` too (module- and session-scoped fixtures start before it, with torch's
# default of one thread per core).
def pytest_configure(config) -> None:
    if getattr(config.option, "numprocesses", None) and "PYTEST_XDIST_WORKER" not in os.environ:
        for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(name, "1")  # inherited by the workers this process starts


if "PYTEST_XDIST_WORKER" in os.environ:
    torch.set_num_threads(runtime.DEFAULT_THREADS)

# The two workers end together only if no long test starts last: `--dist worksteal` hands each worker
# half of the collection and moves tests from the end of one queue to the other, so a 20-30 s test near
# the end of the collection (test_tutorial.py sorts late) can leave one core idle for most of it. These
# modules go first, whole (their module fixtures still set up once), in this order; every test still runs.
LONG_FIRST = ("test_tutorial.py", "test_substeps.py")


def pytest_collection_modifyitems(config, items) -> None:
    def rank(item) -> int:
        name = item.path.name
        return LONG_FIRST.index(name) if name in LONG_FIRST else len(LONG_FIRST)

    items.sort(key=rank)  # stable: every other test keeps its place


# ----------------------------------------------------------------------------- engine state
@pytest.fixture(autouse=True)
def _fresh_runtime(request):
    """The default engine state before each test, restored after it (see the module docstring)."""
    threads, min_work = torch.get_num_threads(), dict(execution.COMPILE_MIN_WORK)

    def reset() -> None:
        runtime._current = runtime.RuntimeOptions()

    reset()
    torch.set_num_threads(runtime.DEFAULT_THREADS)
    if request.node.get_closest_marker("compile_auto") is None:
        execution.COMPILE_MIN_WORK.update(dict.fromkeys(execution.COMPILE_MIN_WORK, math.inf))
    try:
        yield
    finally:
        execution.COMPILE_MIN_WORK.update(min_work)
        reset()
        torch.set_num_threads(threads)


# ----------------------------------------------------------------------------- shared fixtures
# Config composition, the CLI runner and a tiny dataset (implemented in tests/helpers.py, which
# modules may also import directly). Each fixture returns a plain function so module-scoped
# fixtures can use it.


@pytest.fixture(scope="session")
def compose_cfg():
    """compose_cfg(name="train", overrides=()) -> the composed config of conf/<name>.yaml."""
    return helpers.compose_config


@pytest.fixture(scope="session")
def smoke_cfg():
    """smoke_cfg(tmp, run, *overrides) -> a `train` config on the smoke budget writing to tmp/run,
    with datasets cached in tmp/data."""

    def make(tmp: Path, run: str = "run", *overrides: str):
        paths = (f"paths.data_dir={tmp}/data", f"paths.output_dir={tmp}/{run}")
        return helpers.compose_config("train", (*helpers.SMOKE, *paths, *overrides))

    return make


@pytest.fixture(scope="session")
def run_cli():
    """run_cli(*args, cwd, ok=False) -> CompletedProcess of the `liedfl` command in a subprocess
    (ok=True asserts exit 0 and no traceback)."""
    return helpers.run_cli


@pytest.fixture
def run_main(capfd, monkeypatch):
    """run_main(*args, cwd, ok=False) -> CompletedProcess of `liedfl *args` run in this process
    (`helpers.run_main`: the entry point's `main()`, without a new interpreter per call)."""

    def run(*args: str, cwd: Path, ok: bool = False):
        return helpers.run_main(*args, cwd=cwd, capfd=capfd, monkeypatch=monkeypatch, ok=ok)

    return run


@pytest.fixture(scope="session")
def free_body_dataset():
    """A tiny damped free rigid body (6 trajectories x 12 steps), generated in memory once."""
    from liedfl_cli.data.scenes import generate

    cfg = helpers.compose_config("train", ["budget=smoke", "paths.data_dir=unused", "paths.output_dir=unused"])
    return generate(cfg.dataset)
