"""Compute apart from writing and printing (issue 19, item 4), checked on the source: the evaluations
(`liedfl_cli/evaluation/`) neither print nor write (they return `EvalOutputs`: files and console lines;
`commands.outputs` writes and shows them), and `display/` draws figures without saving them (one
writer, `save_figure`, used by `commands.outputs.write_outputs`). What the functions do when run is
tested next to them (tests/test_control.py, tests/test_exp4.py: nothing printed, nothing written)."""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "liedfl_cli"

PRINTING = {"print", "console", "err_console", "warning_line", "print_table", "fail"}
WRITING = {"savefig", "save_figure", "write_text", "write_bytes", "write_csv", "write_json", "atomic_path", "mkdir"}


def _names(tree: ast.AST) -> set[str]:
    """Every name and attribute used or imported in `tree`."""
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            out.add(node.id)
        elif isinstance(node, ast.Attribute):
            out.add(node.attr)
        elif isinstance(node, ast.ImportFrom):
            out.update(a.asname or a.name for a in node.names)
    return out


def test_the_evaluations_neither_print_nor_write():
    files = sorted((PKG / "evaluation").glob("*.py"))
    assert {f.name for f in files} >= {"control.py", "mocap.py", "metrics.py", "outputs.py"}
    for f in files:
        used = _names(ast.parse(f.read_text()))
        assert not used & PRINTING, (f.name, sorted(used & PRINTING))
        assert not used & WRITING, (f.name, sorted(used & WRITING))


def test_display_figures_are_drawn_not_saved_except_by_the_one_writer():
    for f in ("plots.py", "speed_figure.py"):
        tree = ast.parse((PKG / "display" / f).read_text())
        for node in tree.body:
            if isinstance(node, ast.FunctionDef) and node.name != "save_figure":
                args = {a.arg for a in node.args.args + node.args.kwonlyargs}
                assert not args & {"path", "out", "dst", "filename"}, (f, node.name)
                assert not _names(node) & WRITING, (f, node.name)
