"""The import rules of docs/architecture.md, checked on the source (every import counts, also
one inside a function: a lazy import still makes a dependency)."""

from __future__ import annotations

import ast
import functools
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "liedfl_cli"
CORE = ("lie", "mechanics", "models", "solvers")  # the math layers: no config system below the pipeline
BELOW_COMMANDS = (*CORE, "data", "evaluation", "files", "loggers", "display")
"""Layers that receive typed objects only (config/typed.py converts a command's config at its entry)."""
CONFIG_LIBS = ("hydra", "omegaconf")


def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


@functools.cache
def _tree(path: Path) -> ast.Module:
    """The parsed source of `path`, once per process and only when a test asks (not at collection:
    every pytest-xdist worker collects this module, and parsing the package takes ~1 s)."""
    return ast.parse(path.read_text(), filename=str(path))


@functools.cache
def _imports(path: Path) -> frozenset[str]:
    """Absolute names of every module imported by `path` (relative imports resolved)."""
    mod = _module_name(path)
    package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
    out = set()
    for node in ast.walk(_tree(path)):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)]
                prefix = ".".join(base + ([node.module] if node.module else []))
            else:
                prefix = node.module or ""
            out.add(prefix)
            out.update(f"{prefix}.{a.name}" for a in node.names)  # `from . import x` imports module x
    return frozenset(out)


MODULES = {_module_name(p): p for p in sorted(PKG.rglob("*.py"))}


@functools.cache
def _graph() -> dict[str, set[str]]:
    """module -> the package's modules it imports (not itself, not its own parent packages)."""
    return {
        m: {i for i in _imports(p) if i in MODULES and i != m and not m.startswith(i + ".")} for m, p in MODULES.items()
    }


def _layer(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and (PKG / parts[1]).is_dir()) else "pipeline"


def test_no_layer_below_the_commands_imports_the_config_system():
    """hydra / omegaconf only in config/, commands/ and the entry points (imports inside functions
    count: `_imports` walks the whole tree); tests/test_typed_config.py checks the calls at run time."""
    bad = [
        f"{m} imports {i}"
        for m, p in MODULES.items()
        if _layer(m) in BELOW_COMMANDS
        for i in _imports(p)
        if i.split(".")[0] in CONFIG_LIBS
    ]
    assert not bad, bad
    assert {_layer(m) for m in MODULES} >= set(BELOW_COMMANDS)  # the scan covers real folders


# docs/architecture.md's layer table: each layer imports only the layers listed (the package root
# `liedfl_cli`, which holds only the version, and `liedfl_cli.errors` are importable from everywhere).
ALLOWED = {
    "lie": set(),
    "mechanics": {"lie"},
    "solvers": {"lie"},
    "models": {"lie", "mechanics", "solvers"},
    "files": {"lie"},
    "display": {"files"},
    "data": {"lie", "mechanics", "files", "display"},
    "evaluation": {"lie", "mechanics", "solvers", "models", "data", "files", "display"},
    "loggers": {"files", "display"},
    "config": {"lie", "mechanics", "solvers", "models", "data", "files", "display", "evaluation", "loggers"},
    "commands": {
        "lie",
        "mechanics",
        "solvers",
        "models",
        "data",
        "files",
        "display",
        "evaluation",
        "loggers",
        "config",
    },
}
TOP = {"liedfl_cli", "liedfl_cli.__main__", "liedfl_cli.api", "liedfl_cli.cli", "liedfl_cli.errors"}


def test_every_module_is_in_a_layer_of_the_table():
    """At most 6 modules at the top of the package (the entry points and the error types); every
    other module lives in a folder that is a layer of the table."""
    top = {m for m in MODULES if _layer(m) == "pipeline"}
    assert top == TOP, sorted(top ^ TOP)
    assert len(TOP - {"liedfl_cli"}) <= 6
    assert {_layer(m) for m in MODULES} - {"pipeline"} == set(ALLOWED)


def test_each_layer_imports_only_the_layers_below_it():
    """No whitelist: every import of a module in a layer goes to its own layer or one listed."""
    bad = []
    graph = _graph()
    for m in MODULES:
        layer = _layer(m)
        if layer not in ALLOWED:
            continue
        for i in graph[m]:
            if i in ("liedfl_cli", "liedfl_cli.errors"):
                continue
            if _layer(i) != layer and _layer(i) not in ALLOWED[layer]:
                bad.append(f"{m} imports {i}")
    assert not bad, bad


def test_there_are_no_import_cycles():
    """Tarjan's strongly connected components of the module graph: all of size one."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []
    counter = [0]
    graph = _graph()

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_the_graph_is_not_trivially_empty():
    """Guards the checks above against a broken parser: known edges must be seen."""
    graph = _graph()
    assert "liedfl_cli.models.base" in graph["liedfl_cli.models.liedflnn.model"]
    assert "liedfl_cli.solvers.newton" in graph["liedfl_cli.solvers.rollout"]
    assert (
        _layer("liedfl_cli.cli") == "pipeline"
        and _layer("liedfl_cli.commands.train") == "commands"
        and _layer("liedfl_cli.lie.so3") == "lie"
    )


def _concrete_model_classes() -> set[str]:
    """Names of the classes defined under models/ except the abstract contract (`models.base`)."""
    names = set()
    for m, p in MODULES.items():
        if _layer(m) == "models" and m != "liedfl_cli.models.base":
            names |= {n.name for n in ast.walk(_tree(p)) if isinstance(n, ast.ClassDef)}
    return names


def test_no_code_outside_models_tests_a_concrete_model_class_or_probes_its_attributes():
    """The model contract (`models.base.Model`) has hooks for what the pipeline needs (notes, tree,
    force terms, physical parameters, parameter recovery, damping stiffness): outside models/ nothing
    asks which model it holds (isinstance on a concrete class) or probes a model's attributes."""
    concrete = _concrete_model_classes()
    bad = []
    for m, p in MODULES.items():
        if _layer(m) == "models":
            continue
        for node in ast.walk(_tree(p)):
            if not isinstance(node, ast.Call) or not isinstance(node.func, ast.Name) or len(node.args) < 2:
                continue
            first, second = node.args[0], node.args[1]
            if node.func.id == "isinstance":
                names = second.elts if isinstance(second, ast.Tuple) else [second]
                hit = [n.id for n in names if isinstance(n, ast.Name) and n.id in concrete]
                if hit:
                    bad.append(f"{m}:{node.lineno} isinstance(..., {hit[0]})")
            elif node.func.id in ("getattr", "hasattr"):
                target = ast.unparse(first)
                if target in ("model", "self.model", "ref"):
                    bad.append(f"{m}:{node.lineno} {node.func.id}({target}, ...)")
    assert not bad, bad


def test_importing_the_core_loads_no_config_system():
    """`import liedfl_cli.lie` (or mechanics, solvers, models, data, evaluation, files, loggers,
    display) in a fresh interpreter loads neither
    hydra nor omegaconf: the package root registers nothing (the config modules import
    `liedfl_cli.config.resolvers`)."""
    from helpers import modules_in_fresh_interpreter

    code = (
        "import liedfl_cli.lie, liedfl_cli.mechanics, liedfl_cli.solvers, liedfl_cli.models.liedflnn.model, "
        "liedfl_cli.models.articulated.model, liedfl_cli.data.scenes, liedfl_cli.evaluation, "
        "liedfl_cli.files.checkpoint, liedfl_cli.loggers, liedfl_cli.display.plots"
    )
    assert modules_in_fresh_interpreter(code, ("hydra", "omegaconf")) == []


def _family(mod: str) -> str:
    """The model family package of a module under models/ (`liedfl_cli.models.liedflnn.engines.core` ->
    `liedfl_cli.models.liedflnn`); a shared module of models/ is its own family; '' outside models/."""
    parts = mod.split(".")
    if len(parts) < 3 or parts[1] != "models":
        return ""
    return ".".join(parts[:3])


def _class_families() -> dict[str, set[str]]:
    """Class name -> the families defining a class of that name (concrete models and engine types)."""
    out: dict[str, set[str]] = {}
    for m, p in MODULES.items():
        if _layer(m) == "models" and m != "liedfl_cli.models.base":
            for n in ast.walk(_tree(p)):
                if isinstance(n, ast.ClassDef):
                    out.setdefault(n.name, set()).add(_family(m))
    return out


def _type_tests(tree: ast.Module):
    """(line, isinstance | issubclass, class name) of every type test naming a class by name or attribute."""
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and len(node.args) == 2):
            continue
        if node.func.id in ("isinstance", "issubclass"):
            second = node.args[1]
            for n in second.elts if isinstance(second, ast.Tuple) else [second]:
                if isinstance(n, ast.Name):
                    yield node.lineno, node.func.id, n.id
                elif isinstance(n, ast.Attribute):
                    yield node.lineno, node.func.id, n.attr


def test_no_type_test_on_a_concrete_model_or_engine_type_outside_its_family():
    """Which model or engine a caller holds is asked only inside that model's family package
    (`models/<family>/`): elsewhere (the pipeline, another family, the shared model modules) the
    contract's hooks answer (`Model.variant_for`, `value_and_grad`, `set_plan`, ...). Covers
    `isinstance` and `issubclass`, by plain name and by attribute (`fused.IncrementBatch`)."""
    families = _class_families()
    bad = []
    for m, p in MODULES.items():
        own = _family(m)
        for line, kind, name in _type_tests(_tree(p)):
            where = families.get(name)
            if where is not None and own not in where:
                bad.append(f"{m}:{line} {kind}(..., {name}) (defined in {sorted(where)})")
    assert not bad, bad


def test_the_type_test_scan_sees_the_families_own_checks():
    """Guards the check above: the LieDFLNN family's own checks of its engine types are found."""
    seen = {(name, _family(m)) for m, p in MODULES.items() for _, _, name in _type_tests(_tree(p))}
    assert ("IncrementBatch", "liedfl_cli.models.liedflnn") in seen


def test_no_model_reads_the_process_runtime():
    """Models and their engines are told how to run (`solvers.execution.ExecutionPlan`, held by the
    model): no module under models/ imports `solvers.runtime` (threads, device, dtype, the command's
    settings), so nothing there reads a process-global setting."""
    bad = [m for m, p in MODULES.items() if _layer(m) == "models" and "liedfl_cli.solvers.runtime" in _imports(p)]
    assert not bad, bad
    assert "liedfl_cli.solvers.runtime" in _imports(MODULES["liedfl_cli.config.factory"])  # the scan sees imports
