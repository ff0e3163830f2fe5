"""LieDFLNN, the paper's model: its one meaning in `model.py` (parameters, L_d, forces, the forced DEL
residual and the reference Newton problem), the sub-step / fourth-order wrapper in `substeps.py`, and
in `engines/` the fast paths that must equal `model.py` to rounding (tests/test_fused*.py):
`core` (the engines' entry: samples as increments, the fused loss and Newton step), `maps` (closed
forms), `training` (the fused DEL residual and hand-written gradient), `gradient` (the fused
optimiser's loss-and-gradient), `rollout` (the implicit step on the increment), `columns` and
`scalar` (single-body SO(3) rollouts in column layout and in Python floats)."""

from .model import LieDFLNN

__all__ = ["LieDFLNN"]
