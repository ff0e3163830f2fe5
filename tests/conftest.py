"""Shared test configuration.

The default torch dtype is deliberately left alone: every Lie-group test states its dtype.
A modest hypothesis profile keeps the property tests fast (select another one with
HYPOTHESIS_PROFILE=<name>, e.g. `thorough`).
"""

from __future__ import annotations

import os

from hypothesis import HealthCheck, settings

settings.register_profile(
    "default-liedfl",
    deadline=None,
    max_examples=12,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("thorough", deadline=None, max_examples=300)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default-liedfl"))
