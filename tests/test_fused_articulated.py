"""The articulated model's fused rollout engine (`models.articulated.engines.fused`) against the reference problem.

The engine must take the reference's Newton steps: the same residual, Jacobian, warm start and
retraction at the same iterate (to rounding, relative to their magnitudes), hence the same rollouts,
convergence flags and iteration counts. Checked on trees with every joint type the engine serves (free,
ball, hinge, weld; world and parent rotations; free and pinned roots; reduced and unreduced), with
learned gravity, an MLP potential, per-DoF damping and learned joint-space forces; the models it does
not serve (universal joints, the generic residual, a recorded gradient) keep the reference problem.
"""

from __future__ import annotations

import pytest
import torch
from test_articulated_joints import _unit, mixed_tree, smooth_motion

from liedfl_cli.lie import Pose, so3
from liedfl_cli.lie.tree import Tree
from liedfl_cli.mechanics.articulated import extrapolate
from liedfl_cli.mechanics.forces import NNForce, RayleighNonlinearForce
from liedfl_cli.models.articulated.engines import fused as fa
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN, ArticulatedState
from liedfl_cli.solvers import newton
from liedfl_cli.solvers.execution import ExecutionPlan
from liedfl_cli.solvers.options import SolverOptions

F64 = torch.float64
H = 0.02


@pytest.fixture(autouse=True)
def _torch_engine_only(monkeypatch):
    """These tests are of the fused engine in torch: rollouts never go to the native step (tested
    against this engine in tests/test_native_articulated.py)."""
    monkeypatch.setattr(ExecutionPlan, "wants_native", lambda self: False)


def _tree(name: str) -> Tree:
    if name.startswith("universal"):  # test_articulated_joints' tree: universal, hinge, ball, weld joints
        return mixed_tree(name.split("-")[1], free_root=not name.endswith("pinned"))
    z = [0.0, 0.0, 0.0]
    parents = [-1, 0, 0, 2, 1, 4]
    offsets = [z, [0.4, 0.0, 0.1], [0.0, 0.3, 0.0], [0.2, 0.2, 0.0], [0.0, 0.0, 0.5], [0.1, -0.3, 0.2]]
    a1, a2, a3 = _unit([1.0, 2.0, -0.5]), _unit([0.2, 1.0, 0.1]), _unit([0.0, 0.0, 1.0])
    if name.startswith("ball"):
        rotations = name.split("-")[1]
        return Tree.from_lists(parents, offsets, rotations, True, ["free"] + ["ball"] * 5)
    if name.startswith("hinge"):  # free root, hinges, a ball and a weld
        rotations = name.split("-")[1]
        kinds = ["free", "hinge", "hinge", "ball", "weld", "hinge"]
        axes = [[z, z], [a1, z], [a2, z], [z, z], [z, z], [a3, z]]
        return Tree.from_lists(parents, offsets, rotations, True, kinds, axes)
    # pinned root on a hinge, then a ball, hinges and a weld (a robot arm on a table)
    offsets = [[0.1, 0.2, 0.3]] + offsets[1:]
    kinds = ["hinge", "ball", "hinge", "weld", "hinge", "ball"]
    axes = [[a3, z], [z, z], [a1, z], [z, z], [a2, z], [z, z]]
    return Tree.from_lists(parents, offsets, name.split("-")[1], False, kinds, axes)


# (tree, potential parts, forces): every joint type and both attitude conventions; damping ("rayleigh"
# becomes per-DoF damping, which makes a tree reduced), learned forces, an MLP potential
CASES = {
    "ball-world unreduced": ("ball-world", ("uniform_gravity",), ()),
    "ball-parent unreduced, forces": ("ball-parent", ("uniform_gravity", "mlp"), ("nn", "rayleigh_nonlinear")),
    "ball-world damped": ("ball-world", ("uniform_gravity",), ("rayleigh",)),
    "hinge-world damped, nn": ("hinge-world", ("uniform_gravity",), ("rayleigh", "nn")),
    "hinge-parent damped, mlp, forces": ("hinge-parent", ("uniform_gravity", "mlp"), ("rayleigh", "nn")),
    "pinned-world damped": ("pinned-world", ("uniform_gravity",), ("rayleigh",)),
    "pinned-parent, mlp": ("pinned-parent", ("mlp",), ()),
    "universal-world damped, nn": ("universal-world", ("uniform_gravity",), ("rayleigh", "nn")),
    "universal-parent pinned, damped": ("universal-parent-pinned", ("uniform_gravity", "mlp"), ("rayleigh",)),
}


def _model(case: str) -> tuple[ArticulatedLieDFLNN, Pose]:
    tree_name, potential, forces = CASES[case]
    tree = _tree(tree_name)
    torch.manual_seed(0)
    m = ArticulatedLieDFLNN(
        tree, H, potential=potential, forces=forces, init_jitter=0.3, seed=5, mlp_width=8, mlp_depth=2
    )
    with torch.no_grad():
        if m.dof_damper is not None:
            m.dof_damper.lam.copy_(0.3 + torch.rand(m.dof_damper.lam.shape, dtype=F64))
        for f in m.forces:  # learned forces of a visible size (the untrained MLPs start near zero)
            for p in f.parameters():
                p.mul_(3.0)
    m.requires_grad_(False)
    return m, smooth_motion(tree, 5, 3, H, seed=2)


def _close(a: torch.Tensor, b: torch.Tensor, rel: float = 1e-10) -> bool:
    if b.numel() == 0:
        return a.shape == b.shape
    a, b = a.detach(), b.detach()
    scale = max(1.0, float(b.abs().max()))
    return float((a - b).abs().max()) <= rel * scale


@pytest.mark.parametrize("case", list(CASES))
def test_the_engine_serves_the_case(case):
    m, _ = _model(case)
    assert fa.applies(m) is None
    assert m.reduced == ("damped" in case or not case.startswith("ball"))


@pytest.mark.parametrize("case", list(CASES))
def test_residual_jacobian_warm_start_and_retraction_equal_the_reference(case):
    m, traj = _model(case)
    g0, g1 = traj.index((slice(None), 0)), traj.index((slice(None), 1))
    with torch.no_grad():
        ref = m.with_path("reference")
        p_ref = ref.implicit_problem(ref.implicit_start(g0, g1))
        state = m.with_path("fused").implicit_start(g0, g1)
        assert isinstance(state, fa.FusedArticulatedState)
        p_fused = m.implicit_problem(state)
        assert _close(p_fused.x0.R, p_ref.x0.R) and _close(p_fused.x0.p, p_ref.x0.p)
        x = p_ref.x0
        for _ in range(2):  # at the warm start and at a moved iterate
            r = p_ref.f(x)
            assert _close(p_fused.f(x), r), float((p_fused.f(x) - r).abs().max())
            J = p_ref.jac(x)
            assert _close(p_fused.jac(x), J), float((p_fused.jac(x) - J).abs().max())
            delta = 0.01 * torch.linspace(-1.0, 1.0, r.shape[-1], dtype=F64).expand_as(r)
            xr, xf = p_ref.retract(x, delta), p_fused.retract(x, delta)
            assert _close(xf.R, xr.R) and _close(xf.p, xr.p)
            x = xr


@pytest.mark.parametrize(
    "case",
    ["ball-world damped", "hinge-parent damped, mlp, forces", "pinned-world damped", "universal-world damped, nn"],
)
def test_rollouts_equal_the_reference_to_rounding(case):
    m, traj = _model(case)
    g0, g1 = traj.index((slice(None), 0)), traj.index((slice(None), 1))
    opts = SolverOptions(tol=1e-9)
    a = m.with_path("fused").rollout(g0, g1, 30, opts)
    b = m.with_path("reference").rollout(g0, g1, 30, opts)
    assert bool(a.converged.all()) and bool(b.converged.all())
    # rounding grows along a rollout; 1e-8 of the magnitudes after 30 steps is ~1e4 ulps
    assert _close(a.pose.R, b.pose.R, 1e-8) and _close(a.pose.p, b.pose.p, 1e-8)
    # integer counts from float tests: a step at the tolerance could flip under rounding
    assert float((a.iterations == b.iterations).double().mean()) >= 0.95
    # the motion is not trivial: the rollout moves away from its start
    assert float((a.pose.R[:, -1] - a.pose.R[:, 1]).abs().max()) > 1e-2


@pytest.mark.parametrize("case", ["ball-world unreduced", "hinge-parent damped, mlp, forces"])
def test_chord_rollouts_equal_the_reference_and_newtons_solution(case):
    """`solver.method=chord` (one Jacobian per step): the fused engine and the reference loop take the
    same chord steps, and at a tight tolerance both land on Newton's solution."""
    m, traj = _model(case)
    g0, g1 = traj.index((slice(None), 0)), traj.index((slice(None), 1))
    chord = SolverOptions(tol=1e-11, method="chord", max_iter=30)
    a = m.with_path("fused").rollout(g0, g1, 20, chord)
    b = m.with_path("reference").rollout(g0, g1, 20, chord)
    assert bool(a.converged.all()) and bool(b.converged.all())
    assert _close(a.pose.R, b.pose.R, 1e-8) and _close(a.pose.p, b.pose.p, 1e-8)
    assert float((a.iterations == b.iterations).double().mean()) >= 0.95
    n = m.with_path("fused").rollout(g0, g1, 20, SolverOptions(tol=1e-11))
    # both solve the same equations to ~1e-11 per step: the rollouts agree far below the motion's size
    assert _close(a.pose.R, n.pose.R, 1e-8) and _close(a.pose.p, n.pose.p, 1e-8)
    assert float((a.pose.R[:, -1] - a.pose.R[:, 1]).abs().max()) > 1e-2
    # linear convergence: chord needs at least Newton's iterations, here strictly more on some step
    assert bool((a.iterations >= n.iterations).all()) and bool((a.iterations > n.iterations).any())


def _guess_errors(case: str, h: float, steps: int) -> tuple[float, float]:
    """Max distance of the warm start (2 d_k - d_{k-1}) and of the last increment alone to the solved
    increment over steps 2..steps of a reference rollout at step h: (extrapolated, last increment)."""
    tree_name, potential, forces = CASES[case]
    torch.manual_seed(0)
    m = ArticulatedLieDFLNN(
        _tree(tree_name), h, potential=potential, forces=forces, init_jitter=0.3, seed=5, mlp_width=8, mlp_depth=2
    ).with_path("reference")
    m.requires_grad_(False)
    traj = smooth_motion(m.tree, 3, 1, h, seed=2)
    G = m.tree.group
    state = m.implicit_start(traj.index((slice(None), 0)), traj.index((slice(None), 1)))
    errs = [0.0, 0.0]
    with torch.no_grad():
        for k in range(steps):
            problem = m.implicit_problem(state)
            sol = newton.solve(problem, SolverOptions(tol=1e-13, max_iter=30))
            assert bool(sol.converged.all())
            if k >= 1:
                assert state.dof_prev is not None
                for i, guess in enumerate((problem.x0, state.inc)):
                    errs[i] = max(errs[i], float(G.log(G.increment(guess, sol.x)).abs().max()))
            state, _ = m.implicit_advance(state, sol.x)
    return errs[0], errs[1]


@pytest.mark.parametrize("case", ["ball-world unreduced", "hinge-world damped, nn"])
def test_the_warm_start_extrapolates_to_third_order(case):
    """The Newton start 2 d_k - d_{k-1} (`ArticulatedLieDFLNN.warm_start`) is off by O(h^3) over a fixed
    time, the last increment by O(h^2): halving h divides their errors by about 8 and 4."""
    ext, last = _guess_errors(case, 0.02, 10)
    ext2, last2 = _guess_errors(case, 0.01, 20)
    assert ext < last and ext2 < 0.3 * last2
    assert 6.0 < ext / ext2 < 10.0, ext / ext2
    assert 3.0 < last / last2 < 5.0, last / last2


def test_a_failed_step_does_not_seed_the_next_guess():
    d = torch.tensor([[0.1, 0.2], [0.3, 0.4]], dtype=F64)
    prev = torch.tensor([[0.0, 0.1], [float("nan"), 0.0]], dtype=F64)
    pred = extrapolate(d, prev)
    torch.testing.assert_close(pred[0], torch.tensor([0.2, 0.3], dtype=F64))
    torch.testing.assert_close(pred[1], d[1])


def test_rows_that_converge_early_leave_the_batch_without_changing_the_others(monkeypatch):
    """At 64+ rows the loop continues on the rows still iterating (`restrict`) once at most a quarter
    is left: a batch that mixes slow rows with fast ones gives every row the result it has alone."""
    m, traj = _model("hinge-world damped, nn")
    g0, g1 = traj.index((slice(None), 0)), traj.index((slice(None), 1))
    big0 = Pose(g0.R.repeat(16, 1, 1, 1), g0.p.repeat(16, 1, 1))
    big1 = Pose(g1.R.repeat(16, 1, 1, 1), g1.p.repeat(16, 1, 1))
    start = Pose(big0.R.clone(), big0.p.clone())  # rows 0..69 start at rest and converge first
    start.R[70:], start.p[70:] = big1.R[70:], big1.p[70:]
    restricted = []
    index = fa.FusedArticulatedState.index
    monkeypatch.setattr(
        fa.FusedArticulatedState, "index", lambda s, rows: restricted.append(len(rows)) or index(s, rows)
    )
    opts = SolverOptions(tol=1e-9)
    mf = m.with_path("fused")
    together = mf.rollout(big0, start, 6, opts)
    assert restricted and min(restricted) <= 20  # the moving rows were iterated apart
    alone = mf.rollout(big0.index(slice(70, None)), start.index(slice(70, None)), 6, opts)
    assert _close(together.pose.R[70:], alone.pose.R, 1e-12) and _close(together.pose.p[70:], alone.pose.p, 1e-12)


def test_models_the_engine_does_not_serve_keep_the_reference_problem():
    world_forces = ArticulatedLieDFLNN(_tree("ball-world"), H, forces=("nn",))
    assert "forces" in (fa.applies(world_forces) or "")
    generic = ArticulatedLieDFLNN(_tree("ball-world"), H, residual="generic", forces=())
    assert fa.applies(generic) == "residual=generic"
    m, traj = _model("ball-world damped")
    g0, g1 = traj.index((slice(None), 0)), traj.index((slice(None), 1))
    with torch.no_grad():
        pair = smooth_motion(world_forces.tree, 2, 1, H)
        start = world_forces.with_path("fused").implicit_start(
            pair.index((slice(None), 0)), pair.index((slice(None), 1))
        )
        assert isinstance(start, ArticulatedState)
        assert isinstance(m.with_path("reference").implicit_start(g0, g1), ArticulatedState)
    # a recorded gradient: the engine reads the parameters detached, so the reference problem serves
    with torch.enable_grad():
        assert isinstance(m.with_path("fused").implicit_start(g0, g1), ArticulatedState)


@pytest.mark.parametrize("force_cls", [NNForce, RayleighNonlinearForce])
def test_force_jacobians_in_closed_form_equal_autodiff(force_cls):
    """The closed-form dF/d xi~ the engine (and the reference's Jacobian) uses, against one reverse
    pass per tangent direction."""
    tree = _tree("hinge-parent")
    G = tree.group
    f = force_cls(G, 2.0, width=16, depth=2)
    with torch.no_grad():
        for p in f.parameters():
            p.mul_(3.0)
    g = smooth_motion(tree, 4, 1, H).index((slice(None), 1))
    xi = torch.randn(4, G.dim, dtype=F64, generator=torch.Generator().manual_seed(1))
    J = f.jacobian_xi(g, xi)
    x = xi.clone().requires_grad_(True)
    F = f(g, x)
    rows = [torch.autograd.grad(F[:, i].sum(), x, retain_graph=True)[0] for i in range(G.dim)]
    J_auto = torch.stack(rows, -2)
    assert float(J_auto.abs().max()) > 1e-3
    assert _close(J, J_auto, 1e-12)


def test_a_newton_failure_is_flagged_as_the_reference_flags_it():
    """One iteration per step cannot reach the tolerance: both paths flag every step as failed and keep
    the same last iterates; a second pose far off the first (0.6 rad on every attitude, 5 units on the
    root: a start no step of h explains) fails on both, with finite poses (the careful iterations)."""
    m, traj = _model("hinge-world damped, nn")
    g0, g1 = traj.index((slice(None), 0)), traj.index((slice(None), 1))
    opts = SolverOptions(tol=1e-12, max_iter=1)
    a = m.with_path("fused").rollout(g0, g1, 5, opts)
    b = m.with_path("reference").rollout(g0, g1, 5, opts)
    assert not bool(a.converged.any()) and torch.equal(a.converged, b.converged)
    assert _close(a.pose.R, b.pose.R, 1e-9) and _close(a.pose.p, b.pose.p, 1e-9)
    fast = m.with_path("fused")
    far = Pose(g1.R @ so3.exp(torch.full((5, 6, 3), 0.6, dtype=F64)), g1.p + 5.0)
    opts = SolverOptions(tol=1e-10, max_iter=4)
    a, b = fast.rollout(g0, far, 4, opts), m.with_path("reference").rollout(g0, far, 4, opts)
    assert not bool(a.converged.any()) and not bool(b.converged.any())
    assert bool(torch.isfinite(a.pose.R).all()) and bool(torch.isfinite(a.pose.p).all())


def _random_tree(seed: int) -> Tree:
    """A random topology (2-7 bodies, each parent any earlier body), joint kinds, unit axes, offsets,
    attitude convention and root."""
    gen = torch.Generator().manual_seed(seed)
    B = int(torch.randint(2, 8, (1,), generator=gen))
    parents = [-1] + [int(torch.randint(0, b, (1,), generator=gen)) for b in range(1, B)]
    free = bool(torch.rand(1, generator=gen) < 0.5)
    kinds = ["free" if free else ["ball", "universal", "hinge"][int(torch.randint(0, 3, (1,), generator=gen))]]
    kinds += [
        ["ball", "universal", "hinge", "weld"][int(torch.randint(0, 4, (1,), generator=gen))] for _ in range(1, B)
    ]
    axes = [[_unit(torch.randn(3, generator=gen, dtype=F64).tolist()) for _ in range(2)] for _ in range(B)]
    offsets = (0.3 * torch.randn(B, 3, generator=gen, dtype=F64)).tolist()
    if free:
        offsets[0] = [0.0, 0.0, 0.0]
    rotations = "world" if bool(torch.rand(1, generator=gen) < 0.5) else "parent"
    return Tree.from_lists(parents, offsets, rotations, free, kinds, axes)


@pytest.mark.parametrize("seed", range(12))
def test_random_trees_take_the_reference_steps(seed):
    """Topologies, joint mixes and conventions the scenes above do not cover: the engine's residual and
    Jacobian at the reference's warm start, and two rollout steps, equal the reference's."""
    tree = _random_tree(seed)
    forces = ("rayleigh", "nn") if seed % 3 else ("rayleigh",)
    m = ArticulatedLieDFLNN(tree, H, potential=("uniform_gravity",), forces=forces, init_jitter=0.3, seed=seed)
    with torch.no_grad():
        if m.dof_damper is not None:
            m.dof_damper.lam.copy_(0.3 + torch.rand(m.dof_damper.lam.shape, dtype=F64))
    m.requires_grad_(False)
    assert fa.applies(m) is None, fa.applies(m)
    traj = smooth_motion(tree, 4, 3, H, seed=seed)
    g0, g1 = traj.index((slice(None), 0)), traj.index((slice(None), 1))
    with torch.no_grad():
        ref = m.with_path("reference")
        p_ref = ref.implicit_problem(ref.implicit_start(g0, g1))
        p_fused = m.with_path("fused").implicit_problem(m.with_path("fused").implicit_start(g0, g1))
        x = p_ref.x0
        assert _close(p_fused.x0.R, x.R) and _close(p_fused.x0.p, x.p)
        assert _close(p_fused.f(x), p_ref.f(x)) and _close(p_fused.jac(x), p_ref.jac(x))
    opts = SolverOptions(tol=1e-10)
    a, b = m.with_path("fused").rollout(g0, g1, 4, opts), m.with_path("reference").rollout(g0, g1, 4, opts)
    assert torch.equal(a.converged, b.converged)
    assert _close(a.pose.R, b.pose.R, 1e-9) and _close(a.pose.p, b.pose.p, 1e-9)
