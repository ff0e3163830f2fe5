"""What a benchmark record names beside its figures: the CPU model (shared by the scripts of scripts/)."""

from __future__ import annotations

import platform
from pathlib import Path


def cpu_model(default: str | None = None) -> str:
    """The `model name` /proc/cpuinfo gives, else `default`, else `platform.processor()` (or "unknown")."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return default if default is not None else (platform.processor() or "unknown")
