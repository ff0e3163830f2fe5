"""The one place where an evaluation's computed outputs become files, and console text.

`liedfl_cli.evaluation` computes (summaries, row tables, drawn figures, console lines: `EvalOutputs`)
and neither writes nor prints; the commands (train, rollout, eval, report) hand its result to `show`,
which prints what it asked for, and to `write_outputs`, which writes each file atomically (write then
rename) by its suffix.
"""

from __future__ import annotations

from pathlib import Path

from ..display.plots import plt, save_figure
from ..display.ui import console
from ..evaluation import EvalOutputs, SceneEvalOptions, run_extra_evals
from ..files.io_utils import write_csv, write_json, write_text


def write_outputs(result: EvalOutputs, out_dir: str | Path | None = None) -> list[Path]:
    """Write every file of `result` under `out_dir` (default `result.out_dir`); returns their paths.
    Figures are closed, also the ones not reached when a write fails."""
    root = Path(out_dir) if out_dir is not None else result.out_dir
    written = []
    try:
        for name, content in result.files.items():
            path = root / name
            suffix = path.suffix
            if suffix == ".json":
                write_json(path, content)
            elif suffix == ".csv":
                write_csv(path, content)
            elif suffix == ".md":
                write_text(path, content)
            elif suffix == ".png":
                save_figure(content, path)
            else:  # EvalOutputs.add refuses other suffixes; a dict filled by hand may not
                raise ValueError(f"evaluation output {name!r}: no writer for suffix {suffix!r}")
            written.append(path)
    finally:
        for content in result.figures().values():
            plt.close(content)
    return written


def show(result: EvalOutputs) -> None:
    """Print what `result` asked to show (`EvalOutputs.say`), in order."""
    for what, options in result.messages:
        console.print(what, **options)


def run_scene_eval(opts: SceneEvalOptions, model, dataset, run_dir, rollout_path=None) -> dict | None:
    """The dataset scene's evaluation (`evaluation.run_extra_evals`), shown and written next to the
    rollout file; returns its summary (None when the scene has none or the evaluation was skipped)."""
    result = run_extra_evals(opts, model, dataset, run_dir, rollout_path=rollout_path)
    if result is None:
        return None
    show(result)
    write_outputs(result)
    return result.summary or None


__all__ = ["write_outputs", "show", "run_scene_eval"]
