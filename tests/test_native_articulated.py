"""The articulated model's native rollout (`models.articulated.engines.native`, the fused engine's step
in C++) against the fused engine in torch and the reference problem.

The native step must take the fused engine's Newton steps: the same poses to rounding (relative to
their magnitudes; rounding grows along a rollout), the same convergence flags and, but for steps that
end at the tolerance, the same iteration counts. Checked on trees with every joint type it serves
(free, ball, hinge, weld; world and parent rotations; free and pinned roots), with and without learned
gravity and per-DoF damping, on random topologies, on the true-parameter model of a MuJoCo-format tree
(declared gravity), and on failing steps; the models and settings it does not serve keep the torch
engines. Needs a C++ compiler (the one torch.compile uses); without one the module is skipped and the
routing test checks the fallback.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from test_articulated_joints import smooth_motion
from test_fused_articulated import _close, _random_tree
from test_fused_articulated import _tree as fused_tree

from liedfl_cli.lie import Pose, so3
from liedfl_cli.models.articulated.engines import native
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN
from liedfl_cli.solvers import compile as compile_cache
from liedfl_cli.solvers.execution import ExecutionPlan
from liedfl_cli.solvers.options import SolverOptions

F64 = torch.float64
H = 0.02
EAGER = ExecutionPlan(compile="false")  # the fused engine in torch: native code only under compile != false

needs_compiler = pytest.mark.skipif(compile_cache.cxx() is None, reason="no C++ compiler (g++/c++/clang++)")

# (tree of test_fused_articulated, potential parts, forces): the models the native step serves
CASES = {
    "ball-world damped": ("ball-world", ("uniform_gravity",), ("rayleigh",)),
    "ball-parent damped, no gravity": ("ball-parent", (), ("rayleigh",)),
    "hinge-world damped": ("hinge-world", ("uniform_gravity",), ("rayleigh",)),
    "hinge-parent": ("hinge-parent", ("uniform_gravity",), ()),
    "pinned-world damped": ("pinned-world", ("uniform_gravity",), ("rayleigh",)),
    "pinned-parent": ("pinned-parent", ("uniform_gravity",), ()),
    # undamped all-ball trees stay unreduced: the unknown moves the tree's own coordinates
    "ball-world unreduced": ("ball-world", ("uniform_gravity",), ()),
    "ball-parent unreduced": ("ball-parent", ("uniform_gravity",), ()),
}


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    """Every test builds into (or reads) one cache folder of this session, not the user's."""
    folder = tmp_path_factory.getbasetemp() / "native_cache"
    monkeypatch.setenv("LIEDFL_NATIVE_CACHE", str(folder))
    torch.set_num_threads(1)


def _model(case: str, seed: int = 5) -> tuple[ArticulatedLieDFLNN, Pose]:
    tree_name, potential, forces = CASES[case]
    tree = fused_tree(tree_name)
    torch.manual_seed(0)
    m = ArticulatedLieDFLNN(tree, H, potential=potential, forces=forces, init_jitter=0.3, seed=seed)
    with torch.no_grad():
        if m.dof_damper is not None:
            m.dof_damper.lam.copy_(0.3 + torch.rand(m.dof_damper.lam.shape, dtype=F64))
    m.requires_grad_(False)
    return m, smooth_motion(tree, 6, 3, H, seed=2)


def _pair(traj: Pose) -> tuple[Pose, Pose]:
    return traj.index((slice(None), 0)), traj.index((slice(None), 1))


def _eager(m: ArticulatedLieDFLNN) -> ArticulatedLieDFLNN:
    twin = m.with_path("fused")
    twin.set_plan(EAGER)
    return twin


def _native(m, g0, g1, steps, opts, progress=None):
    with torch.no_grad():  # as in `rollout_implicit`
        ro = m.with_path("fused").native_rollout(g0, g1, steps, opts, progress)
    assert ro is not None, native.applies(m)
    return ro


@needs_compiler
@pytest.mark.parametrize("case", list(CASES))
def test_native_rollouts_equal_the_fused_engine(case):
    m, traj = _model(case)
    assert native.applies(m) is None and m.reduced == ("unreduced" not in case)
    g0, g1 = _pair(traj)
    opts = SolverOptions(tol=1e-9)
    a = _native(m, g0, g1, 40, opts)
    b = _eager(m).rollout(g0, g1, 40, opts)
    assert bool(a.converged.all()) and torch.equal(a.converged, b.converged)
    assert _close(a.pose.R, b.pose.R, 1e-9) and _close(a.pose.p, b.pose.p, 1e-9)
    assert float((a.iterations == b.iterations).double().mean()) >= 0.95
    assert _close(a.residual_norm, b.residual_norm, 1e-6)
    assert float((a.pose.R[:, -1] - a.pose.R[:, 1]).abs().max()) > 1e-2  # the motion is not trivial
    # the observed pair is the rollout's start, as given
    assert torch.equal(a.pose.R[:, :2], torch.stack((g0.R, g1.R), 1))


@needs_compiler
@pytest.mark.parametrize("case", ["hinge-world damped", "pinned-parent"])
def test_native_rollouts_equal_the_reference_problem(case):
    """Against the reference problem too (autograd-free closed forms, but not the fused engine's code)."""
    m, traj = _model(case)
    g0, g1 = _pair(traj)
    opts = SolverOptions(tol=1e-9)
    a = _native(m, g0, g1, 25, opts)
    b = m.with_path("reference").rollout(g0, g1, 25, opts)
    assert torch.equal(a.converged, b.converged)
    assert _close(a.pose.R, b.pose.R, 1e-8) and _close(a.pose.p, b.pose.p, 1e-8)


@needs_compiler
@pytest.mark.parametrize("seed", range(8))
def test_random_trees_take_the_fused_steps(seed):
    """Random topologies, joint mixes (no universal joint: the native step does not serve it), roots and
    conventions: the native rollout equals the fused engine's."""
    tree = _random_tree(seed)
    kinds = ["ball" if k == "universal" else k for k in tree.joint_kinds]
    tree = type(tree).from_lists(
        tree.parents, tree.offsets, tree.rotations, tree.free_root, kinds, [list(map(list, a)) for a in tree.axes]
    )
    m = ArticulatedLieDFLNN(tree, H, potential=("uniform_gravity",), forces=("rayleigh",), init_jitter=0.3, seed=seed)
    m.requires_grad_(False)
    assert native.applies(m) is None, native.applies(m)
    g0, g1 = _pair(smooth_motion(tree, 4, 3, H, seed=seed))
    opts = SolverOptions(tol=1e-10)
    a, b = _native(m, g0, g1, 12, opts), _eager(m).rollout(g0, g1, 12, opts)
    assert torch.equal(a.converged, b.converged)
    assert _close(a.pose.R, b.pose.R, 1e-9) and _close(a.pose.p, b.pose.p, 1e-9)


@needs_compiler
def test_the_true_model_of_a_mujoco_tree_with_declared_gravity():
    """The benchmark's subject: the true-parameter scheme of a 5-body branched tree (declared gravity,
    per-DoF damping), 100 steps of h 0.05 from its recorded start, native against fused."""
    from liedfl_cli.data.mujoco_chain import chain_dataset
    from liedfl_cli.models.true_scheme import true_model

    ds = chain_dataset(parents="branched5", n_trajectories=3, steps=3, h=0.05, gravity=9.81, test_fraction=0.0)
    m = true_model(ds)
    assert m is not None and native.applies(m) is None
    m.requires_grad_(False)
    R, p = torch.as_tensor(ds.R), torch.as_tensor(ds.p)
    g0, g1 = Pose(R[:, 0], p[:, 0]), Pose(R[:, 1], p[:, 1])
    opts = SolverOptions()
    a, b = _native(m, g0, g1, 100, opts), _eager(m).rollout(g0, g1, 100, opts)
    assert bool(a.converged.all()) and torch.equal(a.converged, b.converged)
    assert _close(a.pose.R, b.pose.R, 1e-8) and _close(a.pose.p, b.pose.p, 1e-8)
    assert float((a.iterations == b.iterations).double().mean()) >= 0.95


@needs_compiler
@pytest.mark.parametrize("case", ["hinge-world damped", "ball-parent damped, no gravity"])
def test_chord_steps_equal_the_fused_engines_chord_steps(case):
    """solver=chord (the Jacobian of each step's first iterate, its factors reused): the same iterates as
    the torch engine's chord loop and the reference problem's, hence the same poses, flags and counts."""
    m, traj = _model(case)
    g0, g1 = _pair(traj)
    opts = SolverOptions(tol=1e-10, method="chord")
    a, b = _native(m, g0, g1, 30, opts), _eager(m).rollout(g0, g1, 30, opts)
    c = m.with_path("reference").rollout(g0, g1, 30, opts)
    assert bool(a.converged.all()) and torch.equal(a.converged, b.converged) and torch.equal(a.converged, c.converged)
    assert _close(a.pose.R, b.pose.R, 1e-9) and _close(a.pose.p, b.pose.p, 1e-9)
    assert _close(a.pose.R, c.pose.R, 1e-8) and _close(a.pose.p, c.pose.p, 1e-8)
    assert float((a.iterations == b.iterations).double().mean()) >= 0.95
    newton = _native(m, g0, g1, 30, SolverOptions(tol=1e-10))
    assert float(a.iterations.double().mean()) > float(newton.iterations.double().mean())  # chord, not Newton


@needs_compiler
def test_failures_are_flagged_as_the_fused_engine_flags_them():
    """One iteration per step cannot reach the tolerance: every step fails on both, with the same last
    iterates; a second pose no step of h explains fails on both with finite poses (backtracking)."""
    m, traj = _model("hinge-world damped")
    g0, g1 = _pair(traj)
    opts = SolverOptions(tol=1e-12, max_iter=1)
    a, b = _native(m, g0, g1, 5, opts), _eager(m).rollout(g0, g1, 5, opts)
    assert not bool(a.converged.any()) and torch.equal(a.converged, b.converged)
    assert torch.equal(a.iterations, b.iterations)
    assert _close(a.pose.R, b.pose.R, 1e-9) and _close(a.pose.p, b.pose.p, 1e-9)
    far = Pose(g1.R @ so3.exp(torch.full((6, 6, 3), 0.6, dtype=F64)), g1.p + 5.0)
    opts = SolverOptions(tol=1e-10, max_iter=4)
    a, b = _native(m, g0, far, 4, opts), _eager(m).rollout(g0, far, 4, opts)
    assert not bool(a.converged.any()) and not bool(b.converged.any())
    assert bool(torch.isfinite(a.pose.R).all()) and bool(torch.isfinite(a.pose.p).all())


@needs_compiler
def test_a_long_rollout_stays_on_the_group_and_the_joints():
    """2,000 steps: attitudes stay orthonormal (the Newton-Schulz advance), hinges stay hinges (each hinge
    body's relative rotation turns about its axis only) and every step converges."""
    m, traj = _model("hinge-parent")
    g0, g1 = _pair(traj)
    ro = _native(m, g0, g1, 2000, SolverOptions())
    assert bool(ro.converged.all())
    R = ro.pose.R
    eye = torch.eye(3, dtype=F64)
    assert float((R.transpose(-1, -2) @ R - eye).abs().max()) < 1e-12
    tree = m.tree
    for b, kind in enumerate(tree.joint_kinds):
        if kind != "hinge":
            continue
        axis = torch.tensor(tree.axes_array()[b][0], dtype=F64)
        # parent rotations: the stored attitude is the joint's; from the first pose it turns about the axis
        turn = so3.log(R[:, :1, b].transpose(-1, -2) @ R[:, :, b])
        off_axis = turn - (turn @ axis)[..., None] * axis
        assert float(off_axis.abs().max()) < 1e-9, b


@needs_compiler
def test_progress_is_reported_for_every_step(monkeypatch):
    from liedfl_cli.models.articulated import model as model_module

    monkeypatch.setattr(model_module, "NATIVE_CHUNK_ROW_STEPS", 12)  # chunks of 2 steps for 6 trajectories
    m, traj = _model("ball-world damped")
    g0, g1 = _pair(traj)
    seen: list[int] = []
    ro = m.with_path("fused").rollout(g0, g1, 9, SolverOptions(), progress=seen.append)
    assert seen == list(range(1, 9))
    assert ro.pose.R.shape[1] == 10 and ro.iterations.shape == (6, 8)
    b = _eager(m).rollout(g0, g1, 9, SolverOptions())
    assert _close(ro.pose.R, b.pose.R, 1e-9)


@needs_compiler
def test_the_rollout_routes_to_the_native_step_only_where_it_serves(monkeypatch):
    calls: list[int] = []
    real = native.NativeRollout.run

    def counting(self, *args, **kwargs):
        calls.append(1)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(native.NativeRollout, "run", counting)
    m, traj = _model("hinge-world damped")
    g0, g1 = _pair(traj)
    opts = SolverOptions()
    m.with_path("fused").rollout(g0, g1, 4, opts)
    assert calls, "a served model on the fused path rolls out natively"
    calls.clear()
    _eager(m).rollout(g0, g1, 4, opts)  # runtime.compile=false: torch only
    m.with_path("reference").rollout(g0, g1, 4, opts)
    m.with_path("fused").rollout(Pose(g0.R.float(), g0.p.float()), Pose(g1.R.float(), g1.p.float()), 4, opts)
    with torch.enable_grad():
        assert m.with_path("fused").native_rollout(g0, g1, 4, opts) is None
    unserved = ArticulatedLieDFLNN(m.tree, H, potential=("uniform_gravity",), forces=("rayleigh", "nn"), seed=1)
    assert native.applies(unserved) == "joint-space forces"
    unserved.requires_grad_(False)
    unserved.with_path("fused").rollout(g0, g1, 4, opts)
    assert not calls


def test_without_a_compiler_the_fused_engine_serves(monkeypatch, capsys):
    """No C++ compiler: no native rollout, one printed line, the same rollout from the torch engine."""
    monkeypatch.setattr(compile_cache, "cxx", lambda: None)
    monkeypatch.setattr(compile_cache, "_said", set())
    native.library.cache_clear()
    try:
        m, traj = _model("pinned-world damped")
        g0, g1 = _pair(traj)
        with torch.no_grad():
            assert m.with_path("fused").native_rollout(g0, g1, 4, SolverOptions()) is None
        assert "no C++ compiler" in capsys.readouterr().err
        ro = m.with_path("fused").rollout(g0, g1, 4, SolverOptions())
        assert bool(ro.converged.all())
    finally:
        native.library.cache_clear()


def test_a_failing_build_leaves_nothing_behind(tmp_path, monkeypatch, capsys):
    """A compiler that fails: None, one line naming the failure, and no library (not even a partial one)
    in the cache folder."""
    script = tmp_path / "badcxx"
    script.write_text("#!/bin/sh\necho 'error: no such thing' >&2\nexit 1\n")
    script.chmod(0o755)
    monkeypatch.setattr(compile_cache, "_said", set())
    folder = tmp_path / "cache"
    assert native.build(str(script), folder) is None
    assert "building the native articulated step failed (error: no such thing)" in capsys.readouterr().err
    assert not [p for p in folder.rglob("*") if p.is_file()]


@needs_compiler
def test_the_library_is_built_once_per_source_and_reused(tmp_path):
    folder = tmp_path / "cache"
    cxx = compile_cache.cxx()
    assert cxx is not None
    first = native.build(cxx, folder)
    assert first is not None and first.exists()
    stamp = first.stat().st_mtime_ns
    again = native.build(cxx, folder)
    assert again == first and again.stat().st_mtime_ns == stamp
    assert [p.name for p in Path(folder).iterdir()] == [first.name]
    assert os.access(first, os.R_OK)


@needs_compiler
def test_the_engine_kept_on_the_model_follows_its_parameters():
    """The native constants are kept on the model between rollouts (a short rollout does not read the
    parameters again), and an in-place change of a parameter (an optimiser step, a load, an edit through
    `.data`) rebuilds them:
    the rollout after the change equals the torch engine's with the new damping. The model stays
    deep-copyable with its engine attached."""
    import copy

    m, traj = _model("hinge-world damped")
    g0, g1 = _pair(traj)
    opts = SolverOptions(tol=1e-10)
    fused = m.with_path("fused")
    first = fused.rollout(g0, g1, 15, opts)
    engine = native.for_model(fused, g1.R)
    assert native.for_model(fused, g1.R) is engine  # kept
    with torch.no_grad():
        m.dof_damper.lam.mul_(3.0)
    assert native.for_model(fused, g1.R) is not engine  # rebuilt
    after = fused.rollout(g0, g1, 15, opts)
    b = _eager(m).rollout(g0, g1, 15, opts)
    assert _close(after.pose.R, b.pose.R, 1e-9) and _close(after.pose.p, b.pose.p, 1e-9)
    assert float((after.pose.R - first.pose.R).abs().max()) > 1e-6  # the change is seen
    engine = native.for_model(fused, g1.R)
    with torch.no_grad():
        m.dof_damper.lam.data.mul_(0.5)  # through .data: no version counter sees it
    assert native.for_model(fused, g1.R) is not engine
    edited = fused.rollout(g0, g1, 15, opts)
    c = _eager(m).rollout(g0, g1, 15, opts)
    assert _close(edited.pose.R, c.pose.R, 1e-9) and _close(edited.pose.p, c.pose.p, 1e-9)
    twin = copy.deepcopy(fused)
    again = twin.rollout(g0, g1, 15, opts)
    assert _close(again.pose.R, edited.pose.R, 1e-12)


@needs_compiler
def test_threads_split_the_rows_without_changing_a_bit():
    """`runtime.threads` 2: the rows are split over two threads; every row's result is the one thread's,
    bit for bit (rows are independent)."""
    m, traj = _model("pinned-world damped")
    g0, g1 = _pair(traj)
    g0 = Pose(g0.R.repeat(8, 1, 1, 1), g0.p.repeat(8, 1, 1))  # 48 rows: 24 per thread
    g1 = Pose(g1.R.repeat(8, 1, 1, 1), g1.p.repeat(8, 1, 1))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _native(m, g0, g1, 12, SolverOptions())
        torch.set_num_threads(2)
        two = _native(m, g0, g1, 12, SolverOptions())
    finally:
        torch.set_num_threads(before)
    assert torch.equal(one.pose.R, two.pose.R) and torch.equal(one.pose.p, two.pose.p)
    assert torch.equal(one.iterations, two.iterations) and torch.equal(one.residual_norm, two.residual_norm)


@needs_compiler
def test_a_non_finite_start_fails_its_row_alone():
    """A trajectory whose second pose is NaN: its steps are flagged (never converged, NaN residual), and
    the other rows are the torch engine's, untouched by it."""
    m, traj = _model("ball-world damped")
    g0, g1 = _pair(traj)
    R1 = g1.R.clone()
    R1[2] = float("nan")
    bad = Pose(R1, g1.p)
    ro = _native(m, g0, bad, 6, SolverOptions())
    assert not bool(ro.converged[2].any()) and bool(torch.isnan(ro.residual_norm[2]).all())
    keep = torch.tensor([0, 1, 3, 4, 5])
    b = _eager(m).rollout(g0.index(keep), g1.index(keep), 6, SolverOptions())
    assert bool(ro.converged[keep].all())
    assert _close(ro.pose.R[keep], b.pose.R, 1e-9) and _close(ro.pose.p[keep], b.pose.p, 1e-9)


@needs_compiler
def test_a_compiler_that_refuses_march_native_builds_the_portable_step(tmp_path, monkeypatch):
    """A compiler without -march=native (some clang): the portable flags build the library, and it is the
    one file in the cache."""
    cxx = compile_cache.cxx()
    script = tmp_path / "picky"
    script.write_text(
        "#!/bin/sh\n"
        'for a in "$@"; do [ "$a" = "-march=native" ] && { echo "error: unsupported" >&2; exit 1; }; done\n'
        f'exec {cxx} "$@"\n'
    )
    script.chmod(0o755)
    path = native.build(str(script), tmp_path / "cache")
    assert path is not None and path.exists()
    assert len([p for p in (tmp_path / "cache").rglob("*") if p.is_file()]) == 1


@needs_compiler
@pytest.mark.parametrize("joint, unit, heavy", [("hinge", "mm", True), ("ball", "mm", False), ("hinge", "m", True)])
def test_mujoco_trees_in_millimetres_with_heavy_roots(joint, unit, heavy):
    """What the generator of the tests above does not vary: MuJoCo-simulated trees in millimetres (positions
    in the hundreds, the rounding floor of the step test scaled with them), a 25 kg root over links of about
    0.5 kg,
    hinge joints with declared axes; the true model's native rollout equals the torch engine's, and every
    step converges."""
    from liedfl_cli.data.mujoco_chain import chain_dataset
    from liedfl_cli.models.true_scheme import true_model

    ds = chain_dataset(
        parents="branched5", joint=joint, unit=unit, heavy_root=heavy, root_mass=25.0 if heavy else 4.0,
        gravity=9.81, n_trajectories=3, steps=3, h=0.05, test_fraction=0.0, seed=3,
    )  # fmt: skip
    m = true_model(ds)
    assert m is not None and native.applies(m) is None
    m.requires_grad_(False)
    R, p = torch.as_tensor(ds.R), torch.as_tensor(ds.p)
    g0, g1 = Pose(R[:, 0], p[:, 0]), Pose(R[:, 1], p[:, 1])
    a, b = _native(m, g0, g1, 60, SolverOptions()), _eager(m).rollout(g0, g1, 60, SolverOptions())
    assert bool(a.converged.all()) and torch.equal(a.converged, b.converged)
    assert _close(a.pose.R, b.pose.R, 1e-8) and _close(a.pose.p, b.pose.p, 1e-8)
    if unit == "mm":
        assert float(a.pose.p.abs().max()) > 50.0  # the positions are in millimetres
