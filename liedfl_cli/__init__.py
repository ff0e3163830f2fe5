"""liedfl: learning forced dynamics on Lie groups from positions only (LieDFLNN)."""

__version__ = "0.1.0"

from .resolvers import register as _register_resolvers

_register_resolvers()
