"""liedfl: learning forced dynamics on Lie groups from positions only (LieDFLNN)."""

__version__ = "0.1.0"
