"""The GLNN baselines (RK4, Lie-Heun, Lie-Midpoint): their meaning in `model.py`, the fused training
path (the vector field with hand-written derivatives, one autograd node per solve) in `engines/fused.py`."""

from .model import GLNN

__all__ = ["GLNN"]
