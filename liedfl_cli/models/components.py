"""What a model shows of itself: its components with parameter counts, its interpretable force parameters."""

from __future__ import annotations

import torch
from torch import nn


def component_tagger():
    """tag(label, *modules) -> "label (n trainable)" | "label (shared)" | "label (known, frozen)", counting
    parameters shared between parts (uniform_gravity's m, rho) once across the calls of one tagger."""
    seen: set[int] = set()

    def tag(label: str, *modules) -> str:
        params = [p for m in modules if m is not None for p in (m.parameters() if isinstance(m, nn.Module) else [m])]
        own = [p for p in params if id(p) not in seen]
        seen.update(id(p) for p in params)
        n = sum(p.numel() for p in own if p.requires_grad)
        if params and not own:
            return f"{label} (shared)"
        if params and n == 0 or not params:
            return f"{label} (known, frozen)"
        return f"{label} ({n:,})"

    return tag


def force_parameters(forces) -> dict[str, torch.Tensor]:
    """`D` of a constant Rayleigh damping and `C` of a learned control among `forces` (no grad)."""
    out: dict[str, torch.Tensor] = {}
    for f in forces:
        kind = getattr(f, "name", "")
        if kind == "rayleigh" and callable(getattr(f, "D", None)):
            out["D"] = f.D().detach()
        elif kind == "control" and callable(getattr(f, "C", None)):
            out["C"] = f.C().detach()
    return out
