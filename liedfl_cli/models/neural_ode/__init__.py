"""The Neural ODE baseline: its meaning in `model.py`, the fused training path (its MLP field with
hand-written derivatives, one autograd node per solve) in `engines/fused.py`."""

from .model import NeuralODE

__all__ = ["NeuralODE"]
