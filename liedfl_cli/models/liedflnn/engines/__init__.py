"""The fast paths of this model family: each must equal `../model.py` to rounding."""
