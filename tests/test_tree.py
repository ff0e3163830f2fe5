"""Forward kinematics of kinematic trees (`lie.tree`) against an independent reference (4x4
homogeneous transforms chained body by body with scipy rotations) and its Jacobian against central
finite differences of the exact group perturbation."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from liedfl_cli.lie import Pose, so3
from liedfl_cli.lie.tree import Tree, coordinates, fk_jacobian, forward_kinematics

TREES = {
    "chain4": [-1, 0, 1, 2],
    "branching": [-1, 0, 0, 1, 1, 2, 5],
}


def _tree(name: str, rotations: str, free_root: bool, seed: int = 0) -> Tree:
    parents = TREES[name]
    rng = np.random.default_rng(seed)
    offsets = rng.normal(size=(len(parents), 3))
    if free_root:
        offsets[0] = 0.0
    return Tree.from_lists(parents, offsets, rotations, free_root)


def _random_coordinates(tree: Tree, batch: tuple[int, ...], seed: int = 1) -> Pose:
    gen = torch.Generator().manual_seed(seed)
    R = so3.exp(2.0 * torch.randn(*batch, tree.n_bodies, 3, generator=gen, dtype=torch.float64))
    m = 1 if tree.free_root else 0
    p = torch.randn(*batch, m, 3, generator=gen, dtype=torch.float64)
    return Pose(R, p)


def _reference_fk(tree: Tree, R: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World 4x4 transforms body by body: T_b = T_parent @ [[R_rel, o_b], [0, 1]] (parent mode) or
    [[R_parent^T R_b, o_b], ...] (world mode), with plain numpy and scipy."""
    B = tree.n_bodies
    T = [None] * B
    for b in range(B):
        M = np.eye(4)
        if b == 0:
            M[:3, :3] = R[0]
            M[:3, 3] = p[0] if tree.free_root else np.asarray(tree.offsets[0])
            T[0] = M
            continue
        q = tree.parents[b]
        Tq = T[q]
        R_rel = R[b] if tree.rotations == "parent" else Tq[:3, :3].T @ R[b]
        M[:3, :3] = Rotation.from_matrix(R_rel).as_matrix()
        M[:3, 3] = tree.offsets[b]
        T[b] = Tq @ M
    return np.stack([t[:3, :3] for t in T]), np.stack([t[:3, 3] for t in T])


@pytest.mark.parametrize("name", list(TREES))
@pytest.mark.parametrize("rotations", ["world", "parent"])
@pytest.mark.parametrize("free_root", [True, False])
def test_forward_kinematics_matches_homogeneous_transforms(name, rotations, free_root):
    tree = _tree(name, rotations, free_root)
    g = _random_coordinates(tree, (5, 2))
    world = forward_kinematics(tree, g)
    assert world.R.shape == (5, 2, tree.n_bodies, 3, 3) and world.p.shape == (5, 2, tree.n_bodies, 3)
    for i in range(5):
        for j in range(2):
            Rr, pr = _reference_fk(tree, g.R[i, j].numpy(), g.p[i, j].numpy())
            np.testing.assert_allclose(world.R[i, j].numpy(), Rr, atol=1e-12)
            np.testing.assert_allclose(world.p[i, j].numpy(), pr, atol=1e-12)
    # coordinates() inverts it
    back = coordinates(tree, world)
    torch.testing.assert_close(back.R, g.R, atol=1e-12, rtol=0)
    torch.testing.assert_close(back.p, g.p, atol=1e-12, rtol=0)


@pytest.mark.parametrize("name", list(TREES))
@pytest.mark.parametrize("rotations", ["world", "parent"])
@pytest.mark.parametrize("free_root", [True, False])
def test_fk_jacobian_matches_finite_differences(name, rotations, free_root):
    tree = _tree(name, rotations, free_root, seed=3)
    G = tree.group
    g = _random_coordinates(tree, (3,), seed=4)
    A = fk_jacobian(tree, g)
    assert A.shape == (3, tree.n_bodies, 6, G.dim)
    world = forward_kinematics(tree, g)
    eps = 1e-6
    for i in range(G.dim):
        e = torch.zeros(3, G.dim, dtype=torch.float64)
        e[:, i] = eps
        cols = []
        for sgn in (1.0, -1.0):
            w2 = forward_kinematics(tree, G.retract(g, sgn * e))  # exact exp: first order is all that counts
            dw = so3.log(world.R.transpose(-1, -2) @ w2.R)
            dv = so3.act(world.R.transpose(-1, -2), w2.p - world.p)
            cols.append(torch.cat((dw, dv), -1))
        fd = (cols[0] - cols[1]) / (2 * eps)  # (3, B, 6)
        torch.testing.assert_close(A[..., i], fd, atol=1e-8, rtol=0)


def test_tree_rejects_bad_structure():
    with pytest.raises(ValueError, match="parents\\[0\\]"):
        Tree.from_lists([0, 0], np.zeros((2, 3)))
    with pytest.raises(ValueError, match="parents\\[2\\]"):
        Tree.from_lists([-1, 0, 3, 0], np.zeros((4, 3)))
    with pytest.raises(ValueError, match="offsets"):
        Tree.from_lists([-1, 0], np.zeros((3, 3)))
    with pytest.raises(ValueError, match="rotations"):
        Tree.from_lists([-1, 0], np.zeros((2, 3)), rotations="local")
