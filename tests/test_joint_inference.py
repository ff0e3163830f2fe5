"""Joint inference from poses (liedfl_cli/mechanics/joint_inference.py): synthetic motions of every joint
kind with random axes and smooth random angles (sums of sines), noiseless and with rotation noise, in
both rotation conventions, on a free and a pinned root; the CMU cartwheels (scripts/infer_joints.py)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
import torch

from liedfl_cli.lie import so3
from liedfl_cli.lie.tree import Tree
from liedfl_cli.mechanics.joint_inference import (
    axis_drift,
    format_inference,
    infer_joints,
    universal_fit,
)

ROOT = Path(__file__).resolve().parents[1]
F64 = torch.float64


def unit(g: torch.Generator) -> torch.Tensor:
    v = torch.randn(3, generator=g, dtype=F64)
    return v / v.norm()


def sines(g: torch.Generator, t: torch.Tensor, amp: float, dim: tuple[int, ...] = (), k: int = 3) -> torch.Tensor:
    """A smooth random signal (t.shape + dim): k sines of amplitude amp * U(0.5, 1.5), 1-5 rad/s."""
    out = torch.zeros(*t.shape, *dim, dtype=F64)
    tt = t.reshape(*t.shape, *([1] * len(dim)))
    for _ in range(k):
        A = amp * (0.5 + torch.rand(dim, generator=g, dtype=F64))
        w = 1.0 + 4.0 * torch.rand(dim, generator=g, dtype=F64)
        p = 2 * math.pi * torch.rand(dim, generator=g, dtype=F64)
        out = out + A * torch.sin(w * tt + p)
    return out


def non_orthogonal_pair(g: torch.Generator, angle: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Two unit vectors `angle` rad apart (a1 in the parent frame, a2 in the body frame, C = identity)."""
    a1 = unit(g)
    n = torch.linalg.cross(a1, unit(g), dim=-1)
    n = n / n.norm()
    return a1, so3.exp(angle * n) @ a1


def relative_motion(kind: str, g: torch.Generator, t: torch.Tensor, amp: float = 0.6, axes=None):
    """R_rel (T, N+1, 3, 3) of one joint and its true axes (None, a, or (a1, a2))."""
    C = so3.exp(torch.randn(3, generator=g, dtype=F64))
    if kind == "weld":
        return C.expand(*t.shape, 3, 3).clone(), None
    if kind == "hinge":
        a = unit(g) if axes is None else axes
        return C @ so3.exp(sines(g, t, amp)[..., None] * a), a
    if kind == "universal":
        a1, a2 = (unit(g), unit(g)) if axes is None else axes
        if axes is not None:
            C = torch.eye(3, dtype=F64)  # the pair's angle as given
        t1, t2 = sines(g, t, amp), sines(g, t, amp)
        return so3.exp(t1[..., None] * a1) @ C @ so3.exp(t2[..., None] * a2), (a1, a2)
    if kind in ("ball", "free"):
        return C @ so3.exp(sines(g, t, amp, (3,))), None
    raise ValueError(kind)


def chain(rels: list[torch.Tensor], rotations: str, free_root: bool, noise: float, g: torch.Generator):
    """A serial chain's tree and coordinates R (T, N+1, B, 3, 3) from relative rotations, with noise
    R exp(n), n ~ N(0, noise^2 I), on the stored coordinates."""
    Rrel = torch.stack(rels, 2)
    B = Rrel.shape[2]
    parents = [-1] + list(range(B - 1))
    Rw = [Rrel[:, :, 0]]
    for b in range(1, B):
        Rw.append(Rw[parents[b]] @ Rrel[:, :, b])
    R = torch.stack(Rw, 2) if rotations == "world" else Rrel
    if noise:
        R = R @ so3.exp(noise * torch.randn(*R.shape[:-2], 3, generator=g, dtype=F64))
    root = [0.0, 0.0, 0.0] if free_root else [0.0, 0.0, 1.0]
    tree = Tree.from_lists(parents, [root] + [[0.3, 0.0, 0.0]] * (B - 1), rotations, free_root)
    return tree, R


def times(T: int = 2, N: int = 400, h: float = 0.01) -> torch.Tensor:
    return (torch.arange(N + 1, dtype=F64) * h).expand(T, N + 1)


def same_axis(found, true: torch.Tensor) -> float:
    """Distance between a found unit axis and the true one, up to sign."""
    f = torch.tensor(found, dtype=F64)
    return float(min((f - true).norm(), (f + true).norm()))


@pytest.mark.parametrize("noise", [0.0, 1e-4])
@pytest.mark.parametrize("free_root", [True, False])
@pytest.mark.parametrize("rotations", ["world", "parent"])
def test_every_kind_is_recognised(rotations, free_root, noise):
    g = torch.Generator().manual_seed(7 + 2 * int(free_root) + int(noise > 0))
    t = times()
    root = "free" if free_root else "universal"
    kinds = [root, "weld", "hinge", "universal", "ball", "hinge", "universal", "weld"]
    special = {6: non_orthogonal_pair(g, math.radians(55.0))}  # a universal joint with axes 55 deg apart
    rels, truth = [], []
    for b, k in enumerate(kinds):
        R, ax = relative_motion(k, g, t, axes=special.get(b))
        rels.append(R)
        truth.append(ax)
    tree, R = chain(rels, rotations, free_root, noise, g)
    result = infer_joints(tree, R)
    assert result.kinds == tuple(kinds), format_inference(result)
    assert result.tree.joints == tuple(kinds)
    assert result.noise_source == "estimated"
    tol_axis = 1e-6 if noise == 0 else 1e-3
    tol_universal = 1e-6 if noise == 0 else 3e-3
    for b, (k, ax) in enumerate(zip(kinds, truth)):
        j = result.joints[b]
        if k == "hinge":
            assert same_axis(j.axes[0], ax) < tol_axis
            assert j.axes[1] == (0.0, 0.0, 0.0)
        elif k == "universal":
            assert same_axis(j.axes[0], ax[0]) < tol_universal
            assert same_axis(j.axes[1], ax[1]) < tol_universal
            assert j.universal_residual <= j.tol_universal
        else:
            assert j.axes == ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
        if k != "free":
            assert j.margin > 1.0
    # noise: the estimate sees it (world attitudes: a relative rotation carries two samples' noise)
    if noise:
        for j in result.joints:
            assert 0.7 * noise < j.noise < (2.0 if rotations == "world" else 1.4) * noise
    else:
        assert all(j.noise < 1e-4 for j in result.joints)


def test_the_universal_joints_increments_span_three_dimensions():
    """Why the rank alone cannot tell a universal joint from a ball: its increments are 3-D."""
    g = torch.Generator().manual_seed(3)
    R, _ = relative_motion("universal", g, times(1))
    tree, Rc = chain([R], "parent", False, 0.0, g)
    j = infer_joints(tree, Rc).joints[0]
    assert j.kind == "universal" and j.rank == 3
    assert j.increment_sv[2] > 100 * j.tol_increment


@pytest.mark.parametrize("rotations", ["world", "parent"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_tiny_hinge_at_noise_is_a_hinge(rotations, seed):
    """A hinge moving 1e-3 rad (amplitude) under 1e-4 rad of noise: its increments (~1e-5 per step) are
    below the noise; its displacement from the mean pose is not."""
    g = torch.Generator().manual_seed(seed)
    t = times()
    a = unit(g)
    w = 2 * math.pi * (0.7 + 0.6 * torch.rand((), generator=g, dtype=F64))
    tiny = so3.exp(torch.randn(3, generator=g, dtype=F64)) @ so3.exp((1e-3 * torch.sin(w * t))[..., None] * a)
    root, _ = relative_motion("hinge", g, t)
    weld, _ = relative_motion("weld", g, t)
    tree, R = chain([root, tiny, weld], rotations, False, 1e-4, g)
    result = infer_joints(tree, R)
    assert result.kinds == ("hinge", "hinge", "weld"), format_inference(result)
    j = result.joints[1]
    assert j.increment_sv[0] < j.tol_increment  # the increments alone would call it a weld
    assert same_axis(j.axes[0], a) < 0.1


@pytest.mark.parametrize("rotations", ["world", "parent"])
def test_a_ball_that_moves_in_a_plane_for_a_while_stays_a_ball(rotations):
    """First half: a slow rotation about one fixed axis (a hinge's motion); second half: all three."""
    g = torch.Generator().manual_seed(11)
    t = times(1, 600)
    half = t.shape[1] // 2
    a = unit(g)
    slow = so3.exp((0.2 * torch.sin(0.8 * t))[..., None] * a)
    free = so3.exp(sines(g, t - t[:, half : half + 1], 0.4, (3,)))
    R = slow.clone()
    R[:, half:] = slow[:, half : half + 1] @ free[:, half:]
    root, _ = relative_motion("free", g, t)
    tree, Rc = chain([root, R], rotations, True, 1e-4, g)
    result = infer_joints(tree, Rc)
    assert result.kinds == ("free", "ball"), format_inference(result)
    # the planar half alone is a hinge
    part = infer_joints(tree, Rc[:, : half - 10])
    assert part.kinds[1] == "hinge"
    assert same_axis(part.joints[1].axes[0], a) < 1e-2


def test_sign_convention():
    """Hinge axes and each universal axis: the largest |component| positive, whatever the truth's sign."""
    g = torch.Generator().manual_seed(5)
    t = times(1)
    a = torch.tensor([0.2, -0.9, 0.3], dtype=F64)
    a = a / a.norm()
    a1 = torch.tensor([-0.8, 0.1, 0.2], dtype=F64)
    a2 = torch.tensor([0.1, 0.3, -0.7], dtype=F64)
    hinge, _ = relative_motion("hinge", g, t, axes=a)
    uni, _ = relative_motion("universal", g, t, axes=(a1 / a1.norm(), a2 / a2.norm()))
    tree, R = chain([hinge, uni], "parent", False, 0.0, g)
    result = infer_joints(tree, R)
    assert result.kinds == ("hinge", "universal")
    assert torch.allclose(torch.tensor(result.joints[0].axes[0], dtype=F64), -a, atol=1e-9)
    assert torch.allclose(torch.tensor(result.joints[1].axes[0], dtype=F64), -a1 / a1.norm(), atol=1e-9)
    assert torch.allclose(torch.tensor(result.joints[1].axes[1], dtype=F64), -a2 / a2.norm(), atol=1e-9)
    for row in (result.joints[0].axes[0], *result.joints[1].axes):
        v = torch.tensor(row, dtype=F64)
        assert v[v.abs().argmax()] > 0


def test_given_noise_overrides_the_estimate():
    g = torch.Generator().manual_seed(2)
    t = times(1)
    rels = [relative_motion(k, g, t, amp=0.05)[0] for k in ("hinge", "weld", "universal")]
    tree, R = chain(rels, "parent", False, 1e-4, g)
    assert infer_joints(tree, R).kinds == ("hinge", "weld", "universal")
    # 1 rad of noise hides every motion; 1e-7 rad makes the noise itself three motion directions
    big = infer_joints(tree, R, noise=1.0)
    assert big.kinds == ("weld", "weld", "weld") and big.noise_source == "given"
    assert big.joints[0].noise == 1.0 and big.joints[0].tol_increment == pytest.approx(3 * math.sqrt(2))
    assert infer_joints(tree, R, noise=1e-7).kinds == ("ball", "ball", "ball")


def test_exact_weld_and_the_helpers():
    g = torch.Generator().manual_seed(4)
    t = times(1)
    weld, _ = relative_motion("weld", g, t)
    hinge, a = relative_motion("hinge", g, t)
    ball, _ = relative_motion("ball", g, t)
    tree, R = chain([weld, hinge, ball], "parent", False, 0.0, g)
    result = infer_joints(tree, R)
    assert result.kinds == ("weld", "hinge", "ball")
    assert result.joints[0].increment_sv == (0.0, 0.0, 0.0) and result.joints[0].margin > 1e6
    flat = hinge.reshape(-1, 3, 3)
    assert axis_drift(flat, a) < 1e-12
    assert axis_drift(ball.reshape(-1, 3, 3), a) > 0.05
    a1, a2, res = universal_fit(ball.reshape(-1, 3, 3))
    assert res > 0.01 and abs(float(a1.norm()) - 1) < 1e-12 and abs(float(a2.norm()) - 1) < 1e-12


def test_input_checks_and_one_trajectory():
    g = torch.Generator().manual_seed(1)
    t = times(1, 20)
    tree, R = chain([relative_motion("hinge", g, t)[0]], "world", False, 0.0, g)
    assert infer_joints(tree, R[0]).kinds == ("hinge",)  # (N+1, B, 3, 3): one trajectory
    assert infer_joints(tree, R.numpy()).kinds == ("hinge",)
    with pytest.raises(ValueError, match="shape"):
        infer_joints(tree, R[..., :2, :])
    with pytest.raises(ValueError, match="at least 4"):
        infer_joints(tree, R[:, :3])
    assert infer_joints(tree, R[:, :3], noise=1e-6).kinds == ("hinge",)
    with pytest.raises(ValueError, match="noise"):
        infer_joints(tree, R, noise=-1.0)


def test_format_inference_one_line_per_body():
    g = torch.Generator().manual_seed(9)
    t = times(1, 60)
    rels = [relative_motion(k, g, t)[0] for k in ("free", "weld", "hinge", "universal", "ball")]
    tree, R = chain(rels, "world", True, 0.0, g)
    result = infer_joints(tree, R)
    names = ["pelvis", "a", "knee", "ankle", "hip"]
    text = format_inference(result, names)
    lines = text.splitlines()
    assert len(lines) == 2 + len(names)
    for line, name, kind in zip(lines[2:], names, result.kinds):
        assert line.split()[:2] == [name, kind]
    assert "[" in lines[4] and ";" in lines[5]  # the hinge's axis, the universal joint's two
    assert format_inference(result).splitlines()[2].startswith("body 0")


def test_cmu_cartwheels():
    """The Exp 4 recordings after the experiment's smoothing: 4 joints never move, knees, elbows and
    wrists are hinges; the feet are 2-DoF joints (universal on the raw data, where their fit residual
    is at the channels' rounding) but the smoothing moves them 1.2e-3 rad off that constraint, above
    the smoothed data's own noise floor, so they come out as balls (docs/joints.md)."""
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        from infer_joints import cmu_dataset
    finally:
        sys.path.pop(0)
    ds = cmu_dataset({"window": 51, "order": 6})
    assert ds.tree is not None
    result = infer_joints(ds.tree, torch.as_tensor(ds.R))
    by = dict(zip(ds.body_names, result.kinds))
    assert [n for n, k in by.items() if k == "weld"] == ["LHipJoint", "RHipJoint", "LeftShoulder", "RightShoulder"]
    hinges = ["LeftLeg", "RightLeg", "LeftForeArm", "LeftHand", "RightForeArm", "RightHand"]
    assert [n for n, k in by.items() if k == "hinge"] == hinges
    for foot in ("LeftFoot", "RightFoot"):
        j = result.joints[ds.body_names.index(foot)]
        assert j.kind == "ball" and 5e-4 < j.universal_residual < 3e-3
    assert [k for n, k in by.items() if "Foot" in n] == ["ball", "ball"]
    with_noise = infer_joints(ds.tree, torch.as_tensor(ds.R), noise=1e-3)
    assert [n for n, k in zip(ds.body_names, with_noise.kinds) if k == "universal"] == ["LeftFoot", "RightFoot"]


@pytest.mark.parametrize("rotations", ["world", "parent"])
def test_mujoco_tree_without_declared_joints(rotations):
    """An independent engine's data (RK4, gravity, damping), its joints left out of the file: every kind
    found, the axes MuJoCo's (up to sign)."""
    pytest.importorskip("mujoco")
    from liedfl_cli.data.mujoco_chain import chain_dataset

    kinds = ["free", "hinge", "universal", "weld", "ball", "hinge", "universal"]
    ds = chain_dataset(
        rotations=rotations,
        parents="branched7",
        joints=kinds,
        gravity=9.81,
        n_trajectories=4,
        steps=60,
        seed=3,
        declare_joints=False,
    )
    assert ds.tree is not None and ds.tree.joints is None
    result = infer_joints(ds.tree, torch.as_tensor(ds.R))
    assert list(result.kinds) == ds.params["physics"]["joints"] == kinds, format_inference(result)
    truth = torch.tensor(ds.params["physics"]["joint_axes"], dtype=F64)  # (B, 2, 3), Tree.axes layout
    checked = 0
    for b, kind in enumerate(kinds):
        for row in {"hinge": (0,), "universal": (0, 1)}.get(kind, ()):
            assert same_axis(result.joints[b].axes[row], truth[b, row]) < 1e-6
            checked += 1
    assert checked == 6
