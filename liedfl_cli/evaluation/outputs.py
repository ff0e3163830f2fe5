"""What a scene evaluation hands back: its summary, the files it wants written, not yet written, and
what it wants shown on the console, not yet printed.

The evaluation functions compute; the commands write (`commands.outputs.write_outputs`, the one
place that turns an `EvalOutputs` into files) and print (`commands.outputs.show`). `files` maps a
path relative to `out_dir` to its content, by suffix: ".json" any JSON-able object, ".csv" a list
of row dicts (the columns of the first row), ".md" text, ".png" a matplotlib Figure (drawn, not saved;
the writer closes it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..solvers.options import SolverOptions

SUFFIXES = (".json", ".csv", ".md", ".png")


@dataclass(frozen=True)
class SceneEvalOptions:
    """What a scene evaluation takes from the run's config (built by liedfl_cli/config/typed.py):
    plots: draw the figures (`eval.plots`); solver: the Newton settings of its one-step solves."""

    plots: bool = True
    solver: SolverOptions = field(default_factory=SolverOptions)


@dataclass
class EvalOutputs:
    """summary: the dict the evaluation returns (also the content of its JSON file); out_dir: the
    folder of the rollout file, where the files belong; files: relative path -> content (see above);
    messages: what the command prints on the console, in order: (text or a rich renderable, `Console.print` options)."""

    summary: dict
    out_dir: Path
    files: dict[str, Any] = field(default_factory=dict)
    messages: list[tuple[Any, dict[str, Any]]] = field(default_factory=list)

    def say(self, what: Any, **options: Any) -> None:
        """Ask the command to print `what` (text with rich markup, or a rich renderable such as a
        Table) with `Console.print` options, after the entries already asked for."""
        self.messages.append((what, options))

    def add(self, name: str, content: Any) -> None:
        if Path(name).suffix not in SUFFIXES:
            raise ValueError(f"evaluation output {name!r}: suffix must be one of {', '.join(SUFFIXES)}")
        self.files[name] = content

    def table(self, name: str) -> list[dict]:
        """The rows of the CSV file `name` (KeyError when there is none)."""
        return self.files[name]

    def figures(self) -> dict[str, Any]:
        return {k: v for k, v in self.files.items() if k.endswith(".png")}


__all__ = ["EvalOutputs", "SceneEvalOptions"]
