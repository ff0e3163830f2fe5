"""Real recordings: BVH motion capture imported onto SE(3) x SO(3)^n.

Registered into `scenes.SCENES` on import (see the end of scenes.py)."""
