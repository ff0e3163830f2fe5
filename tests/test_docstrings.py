"""Every public function of `liedfl_cli/lie/` states the shapes it works on.

Checked, for each module of the package: its public module-level functions and the public
methods (plain, static, class methods and properties) of its public classes, all defined in
that module. Each must
  1. be fully annotated (every parameter but self/cls, and the return), so that whether it
     takes or returns tensors is read from the signature rather than guessed; and
  2. have a docstring; and, when a Tensor or a Pose appears in its signature,
  3. have a shape annotation in that docstring: a parenthesised shape such as `(..., 3, 3)`,
     `(*batch_shape, 3, 3)`, `(3,` or `(B, ...)`, or the word "shape".
A new public function without a docstring, without annotations or without shapes fails here.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
import re

import pytest
import torch

import liedfl_cli.lie

SHAPE = re.compile(r"\((?:\.\.\.|\*\w+|\d+|[BNLT])\s*[,)]|\bshape\b")
TENSOR_TYPES = re.compile(r"\b(?:Tensor|Pose)\b")


def _modules():
    pkg = liedfl_cli.lie
    names = [pkg.__name__] + [f"{pkg.__name__}.{m.name}" for m in pkgutil.iter_modules(pkg.__path__)]
    return [importlib.import_module(n) for n in names]


def _public_callables():
    """(qualified name, function) for every public function and method defined in lie/."""
    out = []
    for mod in _modules():
        for name, obj in vars(mod).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != mod.__name__:
                continue
            if inspect.isfunction(obj):
                out.append((f"{mod.__name__}.{name}", obj))
            elif inspect.isclass(obj):
                for mname, member in vars(obj).items():
                    if mname.startswith("_"):
                        continue
                    if isinstance(member, (staticmethod, classmethod)):
                        member = member.__func__
                    elif isinstance(member, property):
                        member = member.fget
                    if inspect.isfunction(member) and member.__module__ == mod.__name__:
                        out.append((f"{mod.__name__}.{name}.{mname}", member))
    return out


PUBLIC = _public_callables()


def test_the_walk_finds_the_api():
    names = {n.rsplit(".", 2)[-2] + "." + n.rsplit(".", 1)[-1] for n, _ in PUBLIC}
    for expected in ("so3.exp", "so3.log", "se3.adjoint", "euler.from_matrix", "Pose.index", "ProductGroup.exp"):
        assert expected in names, expected


@pytest.mark.parametrize("name,fn", PUBLIC, ids=[n for n, _ in PUBLIC])
def test_public_function_states_shapes(name, fn):
    sig = inspect.signature(fn)
    params = [p for p in sig.parameters.values() if p.name not in ("self", "cls")]
    unannotated = [p.name for p in params if p.annotation is inspect.Parameter.empty]
    assert not unannotated, f"{name}: parameters without a type annotation: {unannotated}"
    assert sig.return_annotation is not inspect.Signature.empty, f"{name}: no return annotation"
    doc = inspect.getdoc(fn)
    assert doc, f"{name}: no docstring"
    annotations = [str(p.annotation) for p in params] + [str(sig.return_annotation)]
    if any(TENSOR_TYPES.search(a) for a in annotations):
        assert SHAPE.search(doc), f"{name}: takes or returns tensors but its docstring states no shape:\n{doc}"


def test_rule_rejects_an_undocumented_function():
    def f(x: torch.Tensor) -> torch.Tensor:
        """Does something to x."""
        return x

    doc = inspect.getdoc(f)
    assert TENSOR_TYPES.search(str(inspect.signature(f).return_annotation))
    assert not SHAPE.search(doc)
    assert SHAPE.search("(..., 3, 3) -> (..., 3)") and SHAPE.search("(B, 3)") and SHAPE.search("shape (...)")
    assert not SHAPE.search("(R, p) -> (w, v)")
