"""Parameter recovery of a trained run: the model's learned parameters against the true ones of
a synthetic scene (the comparison itself is the model's `parameter_recovery` hook)."""

from __future__ import annotations

import copy

import torch

from ..models.true_scheme import true_model


def parameter_recovery(model, dataset) -> dict | None:
    """The model's recovery figures against the scene's true-parameter model (`true_model`); None
    when the data declare no physics or the model has nothing comparable (`Model.parameter_recovery`)."""
    ref = true_model(dataset)
    if ref is None:
        return None
    p = next(model.parameters(), None)
    if p is not None and (p.device.type != "cpu" or p.dtype != torch.float64):  # compared on the CPU in float64
        model = copy.deepcopy(model).to(device="cpu", dtype=torch.float64)
    return model.parameter_recovery(ref, (dataset.params or {}).get("physics") or {})
