"""The articulated LieDFLNN (a kinematic tree of rigid bodies, SE(3) x SO(3)^n): its meaning in
`model.py`, the second-order start of a fit in `fit.py` and `identification.py`, and in `engines/`
the fused rollout engine that must equal `model.py`'s reference problem to rounding
(tests/test_fused_articulated.py)."""

from .model import ArticulatedLieDFLNN

__all__ = ["ArticulatedLieDFLNN"]
