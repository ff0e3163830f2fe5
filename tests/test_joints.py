"""lie.joints: motion subspaces, the exact joint retraction and the coordinate basis T = C^{-1} S,
against autodiff of the retraction and the joint constraints."""

from __future__ import annotations

import pytest
import torch

from liedfl_cli.lie import Pose, so3
from liedfl_cli.lie import joints as jt
from liedfl_cli.lie.tree import Tree
from liedfl_cli.mechanics.articulated import joint_velocity_map

F64 = torch.float64


def _unit(v):
    v = torch.as_tensor(v, dtype=torch.float64)
    return (v / v.norm()).tolist()


def mixed_tree(rotations: str, free_root: bool = True) -> Tree:
    """Five bodies, a branched tree: root, hinge, universal (non-orthogonal axes), ball, weld."""
    z = [0.0, 0.0, 0.0]
    kinds = ["free" if free_root else "hinge", "hinge", "universal", "ball", "weld"]
    axes = [
        [_unit([0.3, -0.2, 1.0]) if not free_root else z, z],
        [_unit([1.0, 2.0, -0.5]), z],
        [_unit([0.2, 1.0, 0.1]), _unit([1.0, 0.3, 0.4])],
        [z, z],
        [z, z],
    ]
    offsets = [
        [0.0, 0.0, 0.0] if free_root else [0.1, 0.2, 0.3],
        [0.4, 0.0, 0.1],
        [0.0, 0.3, 0.0],
        [0.2, 0.2, 0.0],
        [0.0, 0.0, 0.5],
    ]
    return Tree.from_lists([-1, 0, 0, 2, 1], offsets, rotations, free_root, kinds, axes)


def on_manifold(tree: Tree, batch: int, gen: torch.Generator) -> Pose:
    """Random coordinates whose joints obey the tree (advance from reference rotations C)."""
    G = tree.group
    C = so3.exp(0.7 * torch.randn(tree.n_bodies, 3, generator=gen, dtype=F64))
    q0 = Pose(C.expand(batch, -1, -1, -1).clone(), torch.randn(batch, G.n_se3, 3, generator=gen, dtype=F64))
    q = jt.advance(tree, q0, torch.randn(batch, tree.n_dof, generator=gen, dtype=F64))
    return jt.from_joint_coordinates(tree, q)


@pytest.mark.parametrize("rotations", ["world", "parent"])
@pytest.mark.parametrize("free_root", [True, False])
def test_retract_derivative_is_the_coordinate_basis(rotations, free_root):
    tree = mixed_tree(rotations, free_root)
    G = tree.group
    gen = torch.Generator().manual_seed(1)
    g = on_manifold(tree, 4, gen)
    g_next = on_manifold(tree, 4, gen)
    x = G.increment(g, g_next)
    T = jt.coordinate_basis(tree, g_next)
    assert T.shape == (4, G.dim, tree.n_dof)

    def moved(d):  # left-trivialised displacement of g x' from g x
        x2 = jt.retract(tree, g, x, d)
        return G.log(G.increment(g_next, G.compose(g, x2)))

    d0 = torch.zeros(4, tree.n_dof, dtype=F64)
    Jac = torch.func.jacfwd(moved)(d0)  # (4, dim, 4, n)
    Jac = torch.stack([Jac[i, :, i, :] for i in range(4)])
    assert torch.allclose(Jac, T, atol=1e-10)
    assert torch.linalg.matrix_rank(T).eq(tree.n_dof).all()


@pytest.mark.parametrize("rotations", ["world", "parent"])
def test_joints_stay_on_their_manifolds(rotations):
    tree = mixed_tree(rotations)
    gen = torch.Generator().manual_seed(2)
    g = on_manifold(tree, 3, gen)
    q0 = jt.to_joint_coordinates(tree, g)
    x = tree.group.increment(g, g)
    for _ in range(200):  # many large steps
        x = jt.retract(tree, g, x, 0.5 * torch.randn(3, tree.n_dof, generator=gen, dtype=F64))
    q = jt.to_joint_coordinates(tree, tree.group.compose(g, x))
    ax = torch.tensor(tree.axes_array(), dtype=F64)
    # hinge (body 1): the axis is fixed in the parent frame
    assert torch.allclose(q.R[:, 1] @ ax[1, 0], q0.R[:, 1] @ ax[1, 0], atol=1e-12)
    # universal (body 2): a1^T R_rel a2 constant
    c0 = torch.einsum("i,bij,j->b", ax[2, 0], q0.R[:, 2], ax[2, 1])
    c = torch.einsum("i,bij,j->b", ax[2, 0], q.R[:, 2], ax[2, 1])
    assert torch.allclose(c, c0, atol=1e-12)
    assert not torch.allclose(q.R[:, 2], q0.R[:, 2], atol=1e-3)  # it did move
    # weld (body 4): R_rel constant
    assert torch.allclose(q.R[:, 4], q0.R[:, 4], atol=1e-12)


def test_all_ball_basis_is_the_inverse_joint_map():
    tree = Tree.from_lists([-1, 0, 1], [[0, 0, 0], [0.3, 0, 0], [0.3, 0, 0]], "world")
    gen = torch.Generator().manual_seed(3)
    g = on_manifold(tree, 2, gen)
    C = joint_velocity_map(tree, g)
    assert C is not None
    T = jt.coordinate_basis(tree, g)
    assert torch.allclose(C @ T, torch.eye(tree.group.dim, dtype=F64).expand(2, -1, -1), atol=1e-12)


def test_reduce_recovers_admissible_velocities():
    tree = mixed_tree("world")
    gen = torch.Generator().manual_seed(4)
    g = on_manifold(tree, 3, gen)
    T = jt.coordinate_basis(tree, g)
    d = torch.randn(3, tree.n_dof, generator=gen, dtype=F64)
    assert torch.allclose(jt.reduce(T, (T @ d[..., None])[..., 0]), d, atol=1e-10)
