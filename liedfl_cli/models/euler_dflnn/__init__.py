"""The Euler-angle DFLNN baseline: its meaning in `model.py`, its closed-form training path in
`engines/fused.py` (equal to autograd of `model.py`'s L_d to rounding: tests/test_fused_baselines.py)."""

from .model import EulerDFLNN

__all__ = ["EulerDFLNN"]
