"""Shared test configuration.

The default torch dtype is deliberately left alone: every Lie-group test states its dtype.
A modest hypothesis profile keeps the property tests fast (select another one with
HYPOTHESIS_PROFILE=<name>, e.g. `thorough`).
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

import helpers
import liedfl_cli.resolvers  # noqa: F401  (the configs the tests compose use its resolvers)

settings.register_profile(
    "default-liedfl",
    deadline=None,
    max_examples=12,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("thorough", deadline=None, max_examples=300)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default-liedfl"))


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


@pytest.fixture(scope="session")
def free_body_dataset():
    """A tiny damped free rigid body (6 trajectories x 12 steps), generated in memory once."""
    from liedfl_cli.data.scenes import generate

    cfg = helpers.compose_config("train", ["budget=smoke", "paths.data_dir=unused", "paths.output_dir=unused"])
    return generate(cfg.dataset)
