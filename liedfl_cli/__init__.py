"""liedfl: learning forced dynamics on Lie groups from positions only (LieDFLNN).

Importing the package or its core (`lie`, `mechanics`, `solvers`, `models`) loads no config system;
the config resolvers are registered by the modules that read configs (`liedfl_cli.config.resolvers`)."""

__version__ = "0.1.0"
