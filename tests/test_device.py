"""`runtime.device` / `runtime.dtype` (issue "scale up: the same runs on a GPU"), tested on the CPU.

- The source below the pipeline (lie/, mechanics/, solvers/, models/) hard-codes no device and no
  dtype: `test_no_hard_coded_device_or_dtype_below_the_pipeline` scans it by the rules in `RULES`.
- `runtime.device=cpu` and `auto` (no CUDA) give the same run as the defaults, bit for bit.
- `runtime.dtype=float32` trains and rolls out end to end; its rollouts stay on SO(3).
- `runtime.device=cuda` without CUDA is a one-line error; `auto` follows `torch.cuda.is_available`.
- Checkpoints load with `map_location` (the "meta" device stands in for a GPU).
"""

from __future__ import annotations

import ast
import csv
from pathlib import Path

import pytest
import torch

from liedfl_cli.errors import ConfigError
from liedfl_cli.lie import so3, tolerances
from liedfl_cli.solvers import runtime

PKG = Path(__file__).resolve().parents[1] / "liedfl_cli"
BELOW_PIPELINE = ("lie", "mechanics", "solvers", "models")

RULES = """\
Below the pipeline (liedfl_cli/lie, mechanics, solvers, models) tensors take their device and
dtype from the inputs (`x.new_zeros`, `torch.zeros_like`, `dtype=x.dtype, device=x.device`):

1. never `.cuda()`, `.cpu()`, `.double()`, `.float()`, `.half()`, `.bfloat16()`, `torch.device(...)`,
   `torch.set_default_dtype/device/tensor_type`, and no device name ("cpu", "cuda", "cuda:N", "mps",
   "meta") except as the other side of a comparison with `<x>.device.type`;
2. a floating dtype by name (`torch.float64`, `double`, `float32`, `float`, `float16`, `half`,
   `bfloat16`) only
   a. in lie/tolerances.py (the tables per dtype) and solvers/runtime.py (the names of
      `runtime.dtype`; the settings module, read for device and dtype by the pipeline only),
   b. as the default value of a function parameter (`dtype: torch.dtype = torch.float64`),
   c. in construction code: `__init__` methods, mechanics/scene_physics.py (the scene's true physics
      built as modules) and potentials._vec3 (an `__init__` helper). Parameters and buffers are
      created on the CPU in float64 (the same initial values from the seed whatever the runtime);
      the pipeline then moves the module (`factory.place`),
   d. in fused_maps._exp_coefficients_scalar (Python-float arithmetic is float64 whatever the tensors);
3. outside construction code (2c) a tensor factory (torch.zeros, ones, empty, full, eye, arange,
   linspace, logspace, tensor, as_tensor, rand, randn, randint, randperm, normal) passes `device=`
   (or `**options`), unless it draws from a `generator=` (whose device decides), and every factory
   but the integer ones (arange, randint, randperm) passes `dtype=` too;
4. nothing below the pipeline but solvers/runtime.py uses `placement`, `resolve_device` or `DTYPES`
   (the device and dtype are decided in the pipeline).
"""

DEVICE_NAMES = ("cpu", "cuda", "mps", "meta")
FORBIDDEN_METHODS = ("cuda", "cpu", "double", "float", "half", "bfloat16")
FLOAT_DTYPES = ("float64", "double", "float32", "float", "float16", "half", "bfloat16")
FACTORIES = (
    "zeros",
    "ones",
    "empty",
    "full",
    "eye",
    "arange",
    "linspace",
    "logspace",
    "tensor",
    "as_tensor",
    "rand",
    "randn",
    "randint",
    "randperm",
    "normal",
)
INTEGER_FACTORIES = ("arange", "randint", "randperm")
SETTINGS_MODULES = ("lie/tolerances.py", "solvers/runtime.py")  # rule 2a (runtime.py: rules 1 and 4 too)
CONSTRUCTION_MODULES = ("mechanics/scene_physics.py",)  # rule 2c
CONSTRUCTION_FUNCTIONS = {  # rule 2c
    ("mechanics/potentials.py", "_vec3"),
    # the articulated model's declared truth and starting geometry, read when it is built
    ("models/articulated/model.py", "articulated_parameters"),
    ("models/articulated/model.py", "joint_damping_matrix"),
    ("models/articulated/model.py", "geometric_start"),
    ("models/articulated/model.py", "true_dof_damping"),
}
PYTHON_FLOAT_FUNCTIONS = {("models/liedflnn/engines/maps.py", "_exp_coefficients_scalar")}  # rule 2d


def _is_torch_attr(node: ast.AST, names) -> bool:
    return (
        isinstance(node, ast.Attribute)
        and node.attr in names
        and isinstance(node.value, ast.Name)
        and node.value.id == "torch"
    )


def _is_device_name(value) -> bool:
    return isinstance(value, str) and (value in DEVICE_NAMES or value.startswith("cuda:"))


def _is_device_type(node: ast.AST) -> bool:
    """`<x>.device.type` (or `<x>.type`): what a device name may be compared with."""
    return isinstance(node, ast.Attribute) and node.attr == "type"


def violations(source: str, rel: str) -> list[str]:
    """The places in `source` (a module at `rel` under liedfl_cli/) that break `RULES`."""
    tree = ast.parse(source)
    out: list[str] = []
    allowed: set[int] = set()  # ids of nodes a rule allows

    # rule 1: device names compared with <x>.device.type; rule 2b: parameter defaults
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            if any(_is_device_type(s) for s in sides):
                allowed.update(id(s) for s in sides if isinstance(s, ast.Constant))
                allowed.update(id(e) for s in sides if isinstance(s, (ast.Tuple, ast.List, ast.Set)) for e in s.elts)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            args = node.args
            for d in [*args.defaults, *[d for d in args.kw_defaults if d is not None]]:
                allowed.update(id(n) for n in ast.walk(d))

    settings = rel in SETTINGS_MODULES
    whole_module_construction = rel in CONSTRUCTION_MODULES

    def visit(node: ast.AST, func: str | None, construction: bool) -> None:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            func = node.name
            construction = (
                construction
                or node.name == "__init__"
                or whole_module_construction
                or (rel, node.name) in CONSTRUCTION_FUNCTIONS
            )
        where = f"{rel}:{getattr(node, 'lineno', '?')}"
        python_floats = (rel, func) in PYTHON_FLOAT_FUNCTIONS
        if isinstance(node, ast.Call):
            f = node.func
            method = isinstance(f, ast.Attribute) and f.attr in FORBIDDEN_METHODS and not node.args
            if method and not node.keywords and not _is_torch_attr(f, FLOAT_DTYPES):  # (torch.float(...))
                out.append(f"{where}: .{f.attr}() (rule 1)")
            defaults = ("device", "set_default_dtype", "set_default_device", "set_default_tensor_type")
            if _is_torch_attr(f, defaults) and rel != "solvers/runtime.py":
                out.append(f"{where}: torch.{f.attr}(...) (rule 1)")
            if _is_torch_attr(f, FACTORIES) and not construction:
                kw = {k.arg for k in node.keywords}
                spread = None in kw  # **options
                if "device" not in kw and not spread and "generator" not in kw:
                    out.append(f"{where}: torch.{f.attr}(...) without device= (rule 3)")
                if f.attr not in INTEGER_FACTORIES and "dtype" not in kw and not spread:
                    out.append(f"{where}: torch.{f.attr}(...) without dtype= (rule 3)")
        device_name = isinstance(node, ast.Constant) and _is_device_name(node.value)
        if device_name and id(node) not in allowed and rel != "solvers/runtime.py":
            out.append(f"{where}: device name {node.value!r} (rule 1)")
        dtype_name = _is_torch_attr(node, FLOAT_DTYPES) and id(node) not in allowed
        if dtype_name and not (settings or construction or python_floats):
            out.append(f"{where}: torch.{node.attr} (rule 2)")
        names = [a.name for a in node.names] if isinstance(node, ast.ImportFrom) else []
        names += [node.id] if isinstance(node, ast.Name) else [node.attr] if isinstance(node, ast.Attribute) else []
        for name in names:
            if name in ("placement", "resolve_device", "DTYPES") and rel != "solvers/runtime.py":
                out.append(f"{where}: {name} (rule 4)")
        for child in ast.iter_child_nodes(node):
            visit(child, func, construction)

    visit(tree, None, False)
    return out


def _sources():
    for layer in BELOW_PIPELINE:
        for path in sorted((PKG / layer).rglob("*.py")):
            yield path.relative_to(PKG).as_posix(), path.read_text()


def test_no_hard_coded_device_or_dtype_below_the_pipeline():
    found = [v for rel, src in _sources() for v in violations(src, rel)]
    assert not found, "hard-coded device or dtype below the pipeline:\n  " + "\n  ".join(found) + "\n\n" + RULES


@pytest.mark.parametrize(
    "snippet",
    [
        "def f(x):\n    return x.double()",
        "def f(x):\n    return x.cuda()",
        "def f(x):\n    return x.to('cuda')",
        "def f(x):\n    return x.to(device='cpu')",
        "def f(x):\n    return torch.device('cuda:0')",
        "def f(x):\n    return x.to(torch.float64)",
        "def f(x):\n    return torch.zeros(3, dtype=x.dtype)",
        "def f(x):\n    return torch.eye(3, device=x.device)",
        "def f(n):\n    return torch.arange(n)",
        "def f(x):\n    return torch.tensor([1.0, 2.0], dtype=torch.float32, device=x.device)",
        "def f(x):\n    torch.set_default_dtype(torch.float64)",
        "from liedfl_cli.solvers.runtime import placement",
    ],
)
def test_the_scan_finds_each_kind_of_hard_coding(snippet):
    assert violations("import torch\n" + snippet + "\n", "models/example.py")


@pytest.mark.parametrize(
    "snippet",
    [
        "def f(x):\n    return torch.zeros(3, dtype=x.dtype, device=x.device)",
        "def f(x, **opts):\n    return torch.tensor([1.0], **opts)",
        "def f(n, g):\n    return torch.randint(0, n, (3,), generator=g)",
        "def f(x):\n    return x.new_zeros(3) + torch.zeros_like(x)",
        "def f(x):\n    return x.device.type == 'cpu'",
        "def f(shape, dtype: torch.dtype = torch.float64, device=None):\n"
        "    return torch.zeros(shape, dtype=dtype, device=device)",
        "class M:\n    def __init__(self, n):\n        self.w = torch.randn(n, dtype=torch.float64)",
    ],
)
def test_the_scan_allows_what_the_rules_allow(snippet):
    assert violations("import torch\n" + snippet + "\n", "models/example.py") == []


# ----------------------------------------------------------------------------- settings
@pytest.fixture
def restore_runtime(monkeypatch):
    """In-process commands call runtime.configure: start from the defaults (not from whatever an earlier
    test left) and put the settings back afterwards."""
    monkeypatch.setattr(runtime, "_current", runtime.RuntimeOptions())
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_device_and_dtype_settings_are_checked(restore_runtime, monkeypatch):
    from liedfl_cli.config.typed import runtime_options

    opts = runtime_options({"device": "auto", "dtype": "float32"})
    assert (opts.device, opts.dtype) == ("auto", "float32")
    assert runtime.RuntimeOptions() == runtime_options({"device": "cpu", "dtype": "float64"})
    for bad, key in (({"device": "gpu"}, "runtime.device='gpu'"), ({"dtype": "float16"}, "runtime.dtype='float16'")):
        with pytest.raises(ConfigError, match=key):
            runtime_options(bad)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    runtime.configure(runtime.RuntimeOptions(device="auto", dtype="float32"))
    assert runtime.placement() == (torch.device("cpu"), torch.float32)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)  # (nothing is allocated)
    assert runtime.resolve_device("auto") == torch.device("cuda")
    assert runtime.resolve_device("cuda") == torch.device("cuda")
    assert runtime.resolve_device("cpu") == torch.device("cpu")


def test_schema_knows_device_and_dtype(compose_cfg, tmp_path):
    from liedfl_cli.config.schema import validate

    for name in ("train", "rollout", "eval"):
        base = [f"paths.data_dir={tmp_path}"] + (["run=x"] if name != "train" else [])
        validate(compose_cfg(name, [*base, "runtime.device=auto", "runtime.dtype=float32"]), name)
        for bad in ("runtime.device=gpu", "runtime.dtype=float16"):
            with pytest.raises(ConfigError, match=bad.split("=")[0]):
                validate(compose_cfg(name, [*base, bad]), name)


def test_cuda_without_a_gpu_is_a_one_line_config_error(restore_runtime, monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ConfigError) as e:
        runtime.configure(runtime.RuntimeOptions(device="cuda"))
    assert str(e.value).startswith("runtime.device=cuda: no CUDA device") and "\n" not in str(e.value)
    assert runtime.current() == runtime.RuntimeOptions()  # nothing applied


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_cli_cuda_without_a_gpu_fails_before_anything_is_written(run_main, tmp_path):
    proc = run_main("train", "budget=smoke", "runtime.device=cuda", f"paths.data_dir={tmp_path}/data", cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: runtime.device=cuda: no CUDA device"), proc.stderr
    assert not (tmp_path / "outputs").exists() and not (tmp_path / "data").exists()


# ----------------------------------------------------------------------------- runs
def _figures(run: Path) -> list[dict]:
    """eval.csv without its timing columns."""
    with open(run / "eval.csv") as f:
        return [{k: v for k, v in r.items() if "s_per" not in k and "seconds" not in k} for r in csv.DictReader(f)]


def _state(run: Path) -> dict:
    return torch.load(run / "checkpoints" / "last.pt", weights_only=True)["state_dict"]


def test_cpu_and_auto_runs_equal_the_default_run_bit_for_bit(smoke_cfg, tmp_path, restore_runtime, monkeypatch):
    import h5py

    from liedfl_cli.commands.train import run_train

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # auto -> cpu even on a GPU machine
    runs = {"default": (), "cpu": ("runtime.device=cpu",), "auto": ("runtime.device=auto", "runtime.dtype=float64")}
    for name, overrides in runs.items():
        run_train(smoke_cfg(tmp_path, name, *overrides))
    base = tmp_path / "default"
    for name in ("cpu", "auto"):
        run = tmp_path / name
        assert _figures(run) == _figures(base)
        a, b = _state(run), _state(base)
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
        with h5py.File(run / "rollout.h5") as f, h5py.File(base / "rollout.h5") as g:
            assert (f["model/R"][()] == g["model/R"][()]).all() and f["model/R"].dtype == "float64"


def test_placing_a_model_on_the_cpu_in_float64_moves_nothing(free_body_dataset, compose_cfg, restore_runtime):
    from liedfl_cli.config.factory import build_model, place

    cfg = compose_cfg("train", ["budget=smoke", "paths.data_dir=unused", "paths.output_dir=unused"])
    model = build_model(cfg, free_body_dataset)
    before = [p.data_ptr() for p in model.parameters()]
    assert [p.data_ptr() for p in place(model).parameters()] == before
    assert all(p.dtype == torch.float64 and p.device.type == "cpu" for p in model.parameters())


def test_float32_run_trains_rolls_out_and_evaluates(smoke_cfg, tmp_path, restore_runtime, monkeypatch):
    import h5py

    from liedfl_cli.commands.train import run_train
    from liedfl_cli.config import runs

    summary = run_train(smoke_cfg(tmp_path, "run", "runtime.dtype=float32"))
    run = tmp_path / "run"
    assert all(v.dtype == torch.float32 for v in _state(run).values() if v.is_floating_point())
    assert summary["rollout"]["model"]["n_failed"] == 0
    with h5py.File(run / "rollout.h5") as f:  # the file format stays float64
        R = torch.from_numpy(f["model/R"][()])
    assert R.dtype == torch.float64
    assert float(so3.orthogonality_error(R).max()) <= tolerances.tol(torch.float32, "orthogonality")
    rows = {r["model"]: r for r in summary["eval"]}
    assert float(rows["model"]["max_orth_drift"]) <= tolerances.tol(torch.float32, "orthogonality")
    # a float32 checkpoint reloads in the command's dtype (here the default float64) ...
    load, where = runs.load_checkpoint, []
    monkeypatch.setattr(
        runs, "load_checkpoint", lambda p, map_location: where.append(map_location) or load(p, map_location)
    )
    runtime.configure(runtime.RuntimeOptions())
    _, model, _, _ = runs.load_run(run)
    assert all(p.dtype == torch.float64 for p in model.parameters())
    # ... or in float32, its tensors loaded straight onto the runtime's device (map_location)
    runtime.configure(runtime.RuntimeOptions(dtype="float32"))
    _, model, _, _ = runs.load_run(run)
    assert all(p.dtype == torch.float32 for p in model.parameters())
    assert where == [torch.device("cpu")] * 4  # each load_run reads last.pt (config, checks) and best.pt (weights)


@pytest.mark.parametrize("fused", [True, False], ids=["fused", "reference"])
def test_float32_rollouts_stay_on_so3(free_body_dataset, fused, monkeypatch):
    """Only the increment re-orthonormalised, float32 poses drift off SO(3) step by step (~4e-6 in 200
    steps with the extrapolated warm start's one Newton iteration a step, ~1e-5 with the last increment's
    two; ~2.5e-4 in 2000: scripts/float32_cost.py); with every pose projected (runtime.dtype=float32
    today) they stay at rounding level (~3e-7, a few float32 epsilons)."""
    from liedfl_cli.models.true_scheme import true_model

    model = true_model(free_body_dataset).to(dtype=torch.float32)
    g = free_body_dataset.pose().to(dtype=torch.float32)
    # the reference path (Python steps, its time grows with the batch) on 2 of the 6 trajectories: increment
    # only, 83 float32 epsilons after 200 steps (90 over all 6); projected, 3.1 (3.1)
    n = 6 if fused else 2
    g0, g1 = g.index((slice(0, n), 0)), g.index((slice(0, n), 1))
    steps = 200

    def drift() -> float:
        ro = model.with_path("fused" if fused else "reference").rollout(g0, g1, steps)
        assert ro.pose.R.dtype == torch.float32 and ro.n_failed == 0
        return float(so3.orthogonality_error(ro.pose.R).max())

    projected = drift()
    monkeypatch.setitem(tolerances.PROJECT_POSES, torch.float32, False)
    increment_only = drift()
    eps = torch.finfo(torch.float32).eps
    assert projected <= 10 * eps and increment_only >= 15 * eps  # measured 29-34 eps (one Intel CPU): 2x margin


def test_float64_rollouts_are_not_projected():
    assert not tolerances.projects_poses(torch.float64) and tolerances.projects_poses(torch.float32)


# ----------------------------------------------------------------------------- checkpoints
def test_checkpoint_loads_with_map_location(tmp_path, free_body_dataset, compose_cfg, restore_runtime):
    from liedfl_cli.config.factory import build_model
    from liedfl_cli.files.checkpoint import load_checkpoint, load_state, save_checkpoint

    cfg = compose_cfg("train", ["budget=smoke", "paths.data_dir=unused", "paths.output_dir=unused"])
    model = build_model(cfg, free_body_dataset)
    path = tmp_path / "last.pt"
    save_checkpoint(path, model, {"seed": 0})
    meta = load_checkpoint(path, map_location="meta")  # "meta" stands in for a GPU
    assert all(v.device.type == "meta" for v in meta["state_dict"].values())
    payload = load_checkpoint(path, map_location=torch.device("cpu"))
    other = build_model(cfg, free_body_dataset)
    load_state(path, other, payload)
    assert all(torch.equal(a, b) for a, b in zip(model.state_dict().values(), other.state_dict().values()))
