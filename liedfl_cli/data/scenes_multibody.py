"""Multibody and controlled scenes (two bodies on SE(3) x SO(3), PD-controlled heavy body).

Registered into `scenes.SCENES` on import (see the end of scenes.py)."""
