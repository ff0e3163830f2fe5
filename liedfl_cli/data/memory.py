"""Memory estimates checked before allocating: an impossible size (`dataset.n_trajectories=1e12`,
`model.mlp_width=1000000000`) is refused with the estimate and the machine's memory instead of
failing deep inside numpy or torch (or being killed by the kernel)."""

from __future__ import annotations

import os

from ..errors import ConfigError


def machine_memory() -> int | None:
    """Physical memory of this machine in bytes (None where the OS does not say)."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE")) * int(os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return None


def human_bytes(n: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.3g} {unit}"
        n /= 1024
    return f"{n:.3g} PiB"  # pragma: no cover


def check_fits(what: str, nbytes: float) -> None:
    """ConfigError when `nbytes` (an estimate, a lower bound) exceeds the machine's memory; `what`
    names the config values, e.g. "dataset.n_trajectories=... x dataset.steps=..."."""
    total = machine_memory()
    if total is not None and nbytes > total:
        raise ConfigError(
            f"{what}: needs at least {human_bytes(nbytes)} of memory, more than this machine's "
            f"{human_bytes(total)}; choose smaller values"
        )
