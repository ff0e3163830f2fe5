"""What a `liedfl` process pays at its start and its end (docs/benchmarks.md, "Fast tier of the tests").

The modules of the commands that draw nothing load neither matplotlib nor scipy at import
(test_architecture.py checks it in a fresh interpreter); the pyplot they load when they draw is the Agg
one; the process skips the garbage collections of the interpreter's exit (`gc.freeze` at exit,
registered once)."""

from __future__ import annotations

import atexit
import gc

from liedfl_cli import cli


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
