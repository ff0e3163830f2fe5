"""Group axioms for every group (so3, se3, ProductGroup) and the ProductGroup layout helpers."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from liedfl_cli.lie import Pose, ProductGroup, se3, so3
from liedfl_cli.lie.tolerances import tol

DTYPES = (torch.float32, torch.float64)
BATCHES = ((), (5,), (2, 3))
MAX_ANGLE = math.pi - 1e-3
# Absolute tolerance of composite group identities (a handful of matmuls / exp / log).
ATOL = {torch.float64: 1e-12, torch.float32: 1e-5}

seeds = st.integers(0, 2**31 - 1)
# Scales the rotation angles so that the Taylor branches (tiny angles) are exercised too;
# "max" puts every angle at pi - 1e-3 exactly.
scales = st.sampled_from((0.0, 1e-9, 1e-4, 0.05, 0.3, 1.0, "max"))


def _rot_tangent(shape, dtype, gen, scale):
    """Rotation vectors of norm < scale * (pi - 1e-3) (= pi - 1e-3 for "max"), random directions."""
    d = torch.randn(*shape, 3, generator=gen, dtype=torch.float64)
    d = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    u = torch.rand(*shape, 1, generator=gen, dtype=torch.float64)
    ang = MAX_ANGLE * (torch.ones_like(u) if scale == "max" else u * scale)
    return (d * ang).to(dtype)


class SO3Module:
    name = "so3"

    def random(self, b, dtype, gen):
        return (so3.random(b, generator=gen, dtype=torch.float64).to(dtype),)

    def tangent(self, b, dtype, gen, scale):
        return _rot_tangent(b, dtype, gen, scale)

    def identity(self, b, dtype):
        return (so3.identity(b, dtype),)

    def compose(self, g, h):
        return (so3.compose(g[0], h[0]),)

    def inverse(self, g):
        return (so3.inverse(g[0]),)

    def exp(self, xi):
        return (so3.exp(xi),)

    def log(self, g):
        return so3.log(g[0])

    def rotations(self, g):
        return g[0]


class SE3Module:
    name = "se3"

    def random(self, b, dtype, gen):
        R = so3.random(b, generator=gen, dtype=torch.float64)
        return R.to(dtype), torch.randn(*b, 3, generator=gen, dtype=torch.float64).to(dtype)

    def tangent(self, b, dtype, gen, scale):
        w = _rot_tangent(b, dtype, gen, scale)
        return torch.cat((w, torch.randn(*b, 3, generator=gen, dtype=torch.float64).to(dtype)), -1)

    def identity(self, b, dtype):
        return se3.identity(b, dtype)

    def compose(self, g, h):
        return se3.compose(*g, *h)

    def inverse(self, g):
        return se3.inverse(*g)

    def exp(self, xi):
        return se3.exp(xi)

    def log(self, g):
        return se3.log(*g)

    def rotations(self, g):
        return g[0]


class Product:
    def __init__(self, m, n):
        self.G = ProductGroup(m, n)
        self.name = f"product({m},{n})"

    def random(self, b, dtype, gen):
        G = self.G
        R = so3.random((*b, G.n_bodies), generator=gen, dtype=torch.float64)
        p = torch.randn(*b, G.n_se3, 3, generator=gen, dtype=torch.float64)
        return Pose(R.to(dtype), p.to(dtype))

    def tangent(self, b, dtype, gen, scale):
        G = self.G
        w = _rot_tangent((*b, G.n_bodies), dtype, gen, scale)
        v = torch.randn(*b, G.n_se3, 3, generator=gen, dtype=torch.float64).to(dtype)
        return G.join(w, v)

    def identity(self, b, dtype):
        return self.G.identity(b, dtype)

    def compose(self, g, h):
        return self.G.compose(g, h)

    def inverse(self, g):
        return self.G.inverse(g)

    def exp(self, xi):
        return self.G.exp(xi)

    def log(self, g):
        return self.G.log(g)

    def rotations(self, g):
        return g.R


GROUPS = [SO3Module(), SE3Module(), Product(2, 3), Product(1, 22)]
group_param = pytest.mark.parametrize("grp", GROUPS, ids=lambda g: g.name)
dtype_param = pytest.mark.parametrize("dtype", DTYPES, ids=str)
batch_param = pytest.mark.parametrize("b", BATCHES, ids=str)


def assert_elem_close(g, h, atol):
    assert len(g) == len(h)
    for x, y in zip(g, h):
        assert x.shape == y.shape and x.dtype == y.dtype
        torch.testing.assert_close(x, y, atol=atol, rtol=0)


def assert_rotation(R):
    """Orthonormal with det +1, within the dtype's orthogonality threshold."""
    t = 10 * tol(R.dtype, "orthogonality")
    assert so3.orthogonality_error(R).max() < t
    torch.testing.assert_close(torch.linalg.det(R), torch.ones_like(R[..., 0, 0]), atol=t, rtol=0)


# ------------------------------------------------------------------------------- group axioms
@group_param
@dtype_param
@batch_param
@given(seed=seeds)
def test_associativity(grp, dtype, b, seed):
    gen = torch.Generator().manual_seed(seed)
    x, y, z = (grp.random(b, dtype, gen) for _ in range(3))
    lhs = grp.compose(grp.compose(x, y), z)
    rhs = grp.compose(x, grp.compose(y, z))
    assert_elem_close(lhs, rhs, 10 * ATOL[dtype])
    assert_rotation(grp.rotations(lhs))


@group_param
@dtype_param
@batch_param
@given(seed=seeds)
def test_identity_and_inverse(grp, dtype, b, seed):
    gen = torch.Generator().manual_seed(seed)
    g = grp.random(b, dtype, gen)
    e = grp.identity(b, dtype)
    assert_elem_close(grp.compose(e, g), g, 0)  # multiplying by exact identity is exact
    assert_elem_close(grp.compose(g, e), g, 0)
    assert_elem_close(grp.compose(g, grp.inverse(g)), e, ATOL[dtype])
    assert_elem_close(grp.compose(grp.inverse(g), g), e, ATOL[dtype])
    assert_elem_close(grp.inverse(grp.inverse(g)), g, ATOL[dtype])
    assert_elem_close(grp.exp(torch.zeros_like(grp.log(g))), e, 0)


@group_param
@dtype_param
@batch_param
@given(seed=seeds, scale=scales)
def test_log_exp_roundtrips(grp, dtype, b, seed, scale):
    """log(exp(xi)) = xi for rotation parts |w| < pi - 1e-3, and exp(log(g)) = g."""
    gen = torch.Generator().manual_seed(seed)
    xi = grp.tangent(b, dtype, gen, scale)
    g = grp.exp(xi)
    assert_rotation(grp.rotations(g))
    # Observed errors are a few ulp even at |w| = pi - 1e-3 (V^{-1} stays bounded up to 2 pi).
    torch.testing.assert_close(grp.log(g), xi, atol=ATOL[dtype], rtol=0)
    h = grp.random(b, dtype, gen)
    assert_elem_close(grp.exp(grp.log(h)), h, 10 * ATOL[dtype])


def _flat(x, b):
    return x.reshape(-1, *x.shape[len(b) :])


def _flat_elem(g, b):
    parts = [_flat(t, b) for t in g]
    return Pose(*parts) if isinstance(g, Pose) else tuple(parts)


@group_param
@dtype_param
@pytest.mark.parametrize("b", ((), (2, 3)), ids=str)
@given(seed=seeds, scale=scales)
def test_batched_equals_flattened(grp, dtype, b, seed, scale):
    gen = torch.Generator().manual_seed(seed)
    g, h = grp.random(b, dtype, gen), grp.random(b, dtype, gen)
    xi = grp.tangent(b, dtype, gen, scale)
    gf, hf = _flat_elem(g, b), _flat_elem(h, b)
    tight = 1e-14 if dtype == torch.float64 else 1e-6
    for batched, flat in (
        (grp.compose(g, h), grp.compose(gf, hf)),
        (grp.inverse(g), grp.inverse(gf)),
        (grp.exp(xi), grp.exp(_flat(xi, b))),
        ((grp.log(g),), (grp.log(gf),)),
    ):
        assert_elem_close(_flat_elem(batched, b), tuple(flat), tight)


# ------------------------------------------------------------------------ ProductGroup layout
LAYOUTS = [ProductGroup(0, 1), ProductGroup(1, 0), ProductGroup(2, 3), ProductGroup(1, 22), ProductGroup(3, 0)]
layout_param = pytest.mark.parametrize("G", LAYOUTS, ids=lambda G: G.name)


@layout_param
def test_split_join_roundtrip_and_body_slices(G):
    gen = torch.Generator().manual_seed(0)
    xi = torch.randn(4, G.dim, generator=gen, dtype=torch.float64)
    w, v = G.split(xi)
    assert w.shape == (4, G.n_bodies, 3) and v.shape == (4, G.n_se3, 3)
    assert torch.equal(G.join(w, v), xi)
    slices = G.body_slices()
    assert len(slices) == G.n_bodies and slices[0].start == 0 and slices[-1].stop == G.dim
    for i, s in enumerate(slices):
        block = xi[..., s]
        assert torch.equal(block[..., :3], w[..., i, :])  # rotation part first in every block
        if i < G.n_se3:
            assert block.shape[-1] == 6 and torch.equal(block[..., 3:], v[..., i, :])
        else:
            assert block.shape[-1] == 3


def test_split_is_body_by_body():
    G = ProductGroup(2, 1)
    xi = torch.arange(15.0, dtype=torch.float64)
    w, v = G.split(xi)
    assert w.tolist() == [[0, 1, 2], [6, 7, 8], [12, 13, 14]]
    assert v.tolist() == [[3, 4, 5], [9, 10, 11]]


@layout_param
def test_perturb_matches_retract_to_first_order(G):
    """d/ds perturb(g, s eta) = d/ds retract(g, s eta) at s = 0 (central differences)."""
    grp = Product(G.n_se3, G.n_so3)
    gen = torch.Generator().manual_seed(1)
    g = grp.random((2,), torch.float64, gen)
    eta = torch.randn(2, G.dim, generator=gen, dtype=torch.float64)
    h = 1e-5
    d_perturb = [(a - b) / (2 * h) for a, b in zip(G.perturb(g, h * eta), G.perturb(g, -h * eta))]
    d_retract = [(a - b) / (2 * h) for a, b in zip(G.retract(g, h * eta), G.retract(g, -h * eta))]
    for x, y in zip(d_perturb, d_retract):
        torch.testing.assert_close(x, y, atol=1e-8, rtol=0)
    assert_elem_close(G.perturb(g, 0 * eta), g, 0)
    assert_elem_close(G.retract(g, 0 * eta), g, 0)
    # Rotations agree exactly; translations differ at second order only (~ s^2).
    torch.testing.assert_close(G.perturb(g, eta).R, G.retract(g, eta).R, atol=1e-13, rtol=0)
    if G.n_se3:
        gap = [(G.perturb(g, s * eta).p - G.retract(g, s * eta).p).abs().max() for s in (1e-2, 1e-3)]
        assert 50 < gap[0] / gap[1] < 200


@layout_param
def test_increment_inverts_compose(G):
    grp = Product(G.n_se3, G.n_so3)
    gen = torch.Generator().manual_seed(2)
    g, h = grp.random((3,), torch.float64, gen), grp.random((3,), torch.float64, gen)
    assert_elem_close(G.increment(g, G.compose(g, h)), h, 1e-12)
    assert_elem_close(G.increment(g, g), G.identity((3,)), 1e-12)


@layout_param
def test_flatten_shape_and_content(G):
    g = Product(G.n_se3, G.n_so3).random((2, 3), torch.float64, torch.Generator().manual_seed(3))
    f = G.flatten(g)
    assert f.shape == (2, 3, 9 * G.n_bodies + 3 * G.n_se3)
    assert torch.equal(f[..., : 9 * G.n_bodies].reshape(2, 3, G.n_bodies, 3, 3), g.R)
    assert torch.equal(f[..., 9 * G.n_bodies :].reshape(2, 3, G.n_se3, 3), g.p)


def test_check_accepts_good_and_rejects_wrong_shapes():
    G = ProductGroup(2, 3)
    G.check(G.identity((4,)))
    G.check(G.identity())
    bad = [
        Pose(torch.zeros(4, 4, 3, 3), torch.zeros(4, 2, 3)),  # too few bodies
        Pose(torch.zeros(4, 5, 3, 3), torch.zeros(4, 3, 3)),  # p for every body
        Pose(torch.zeros(4, 5, 3, 3), torch.zeros(4, 2, 4)),  # 4-vectors
        Pose(torch.zeros(5, 9), torch.zeros(2, 3)),  # flattened rotations
        Pose(torch.zeros(4, 5, 3, 3), torch.zeros(2, 3)[..., :0]),
        Pose(torch.zeros(4, 5, 3, 3), torch.zeros(3, 2, 3)),  # batch shapes differ
        Pose(torch.zeros(4, 5, 3, 3), torch.zeros(2, 3)),  # p lacks the batch dimension
    ]
    for g in bad:
        with pytest.raises(ValueError):
            G.check(g)


def test_constructor_and_metadata():
    with pytest.raises(ValueError):
        ProductGroup(0, 0)
    with pytest.raises(ValueError):
        ProductGroup(-1, 2)
    G = ProductGroup(2, 3)
    assert (G.n_bodies, G.dim, G.name) == (5, 21, "SE(3)^2 x SO(3)^3")
    assert ProductGroup(1, 22).dim == 72


def test_orthogonality_error_is_max_over_bodies():
    G = ProductGroup(1, 2)
    g = G.identity((2,))
    R = g.R.clone()
    R[1, 2] *= 1.5
    err = G.orthogonality_error(Pose(R, g.p))
    assert err[0] == 0 and err[1] == pytest.approx(math.sqrt(3) * 1.25)
