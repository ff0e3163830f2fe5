"""What a `liedfl` process pays at its start and its end (docs/benchmarks.md, "Fast tier of the tests").

The modules of the commands that draw nothing (train and eval with eval.plots=false, rollout, data) load
neither matplotlib nor scipy at import (checked in a fresh interpreter); the pyplot they load when they
draw is the Agg one; the process skips the garbage collections of the interpreter's exit (`gc.freeze` at exit,
registered once)."""

from __future__ import annotations

import atexit
import gc
from pathlib import Path

from helpers import modules_in_fresh_interpreter
from liedfl_cli import cli

PKG = Path(__file__).resolve().parents[1] / "liedfl_cli"


def test_commands_that_draw_nothing_load_no_matplotlib_or_scipy():
    # every module of the commands, the evaluations and the data layer (what `liedfl` may import to run)
    code = (
        "import importlib, pathlib, pkgutil, liedfl_cli.cli\n"
        "for pkg in ('commands', 'evaluation', 'data'):\n"
        "    path = [str(pathlib.Path(liedfl_cli.cli.__file__).parent / pkg)]\n"
        "    for m in pkgutil.iter_modules(path):\n"
        "        importlib.import_module(f'liedfl_cli.{pkg}.{m.name}')"
    )
    assert modules_in_fresh_interpreter(code, ("matplotlib", "scipy")) == []


def test_plotting_still_loads_pyplot_on_the_agg_backend():
    """The lazy `plots.plt` is pyplot itself once touched, on the non-interactive Agg backend."""
    import matplotlib

    from liedfl_cli.display import plots

    fig = plots.plt.figure()
    try:
        assert matplotlib.get_backend().lower() == "agg"
        assert plots.plt.gcf() is fig
    finally:
        plots.plt.close(fig)


def test_the_exit_freeze_is_registered_once_per_process(monkeypatch):
    registered = []
    monkeypatch.setattr(cli, "_EXIT_FREEZE", [])
    monkeypatch.setattr(atexit, "register", registered.append)
    cli._no_collection_at_exit()
    cli._no_collection_at_exit()
    assert registered == [gc.freeze]
