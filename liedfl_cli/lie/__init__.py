"""Lie groups on plain batched tensors: one module per group with the same function names."""

from . import se3, so3
from .product import SE3, SO3, Pose, ProductGroup

__all__ = ["so3", "se3", "Pose", "ProductGroup", "SO3", "SE3"]
