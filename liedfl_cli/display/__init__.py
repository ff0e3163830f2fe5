"""What the user sees: terminal output (rich) and figures (matplotlib)."""
