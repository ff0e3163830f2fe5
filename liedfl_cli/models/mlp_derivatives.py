"""Closed-form derivatives of the project's MLPs (`mechanics.mlp.MLP`: Linear layers with an
activation between them) for the fused rollout: one forward pass that also gives what Newton needs,
with no autograd graph.

    value_and_gradient(net, x)      scalar networks (potentials): V and dV/dx        (..., ), (..., n)
    gradient_and_hvp(net, x, v)     also the Hessian-vector product (d^2V/dx^2) v    (..., n)
    value_and_jacobian(net, z1, E)  vector networks (forces) from the first layer's pre-activation z1
                                    (..., width) and its derivative E (..., width, k) with respect to k
                                    inputs: F and dF/d(inputs)                       (..., out), (..., out, k)
    left_covector(G, g, dx)         d f(g exp(eta))/d eta at 0 from df/dflatten(g)   (..., dim)
    potential_covector(model, g)    -h dV(g exp(eta))/d eta at 0 of an MLP potential (None: not an MLP)
    gradient_feature_major(lys, x)  dV/dx without a graph, feature major (n, T): one wide product per
                                    layer; rotation_potential_covector(lys, G, R, h) builds on it (rollouts);
                                    gradient_columns(lys, a) the same from a feature-major input a (n, T)

The backward pass of every activation is ATen's own (`gelu_backward`, `tanh_backward`, ...), the
kernels autograd runs, so the gradient is autograd's to rounding; without a graph an exact GELU's value
and slope come from one erf and one exp (ATen's formulas, equal to rounding). Under autograd (training: the
parameters need gradients through the input gradient) `value_and_gradient` runs feature major and makes each
activation's value and slope one autograd node (`_ActAndSlope`, whose backward uses act'' kept from the
forward), so the loss's backward is one pass with no double backward; while `torch.compile` traces, the
slope is the plain tensor expression (`_act_slope`), which inductor fuses.

Activations: GELU (exact or tanh form), Tanh, Softplus, SiLU; `layers(net)` is None for anything
else, and the callers then use autograd.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from ..lie import Pose, ProductGroup
from ..mechanics.mlp import activation_slope

Layer = tuple[nn.Linear, nn.Module | None]

_INV_SQRT2 = 1.0 / math.sqrt(2.0)
_INV_SQRT2PI = 1.0 / math.sqrt(2.0 * math.pi)
_SUPPORTED = (nn.GELU, nn.Tanh, nn.Softplus, nn.SiLU)


def layers(net: nn.Module) -> list[Layer] | None:
    """[(Linear, activation after it or None)] of a Sequential of Linear layers and supported
    activations ending in a Linear layer; None for anything else."""
    if not isinstance(net, nn.Sequential) or not len(net):
        return None
    out: list[Layer] = []
    for m in net:
        if isinstance(m, nn.Linear):
            out.append((m, None))
        elif isinstance(m, _SUPPORTED) and out and out[-1][1] is None:
            out[-1] = (out[-1][0], m)
        else:
            return None
    return out if out[-1][1] is None else None


def _act(act: nn.Module, z: torch.Tensor) -> torch.Tensor:
    return act(z)


def _act_backward(act: nn.Module, g: torch.Tensor, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """g * act'(z) (a = act(z)), with ATen's backward kernels."""
    aten = torch.ops.aten
    if isinstance(act, nn.GELU):
        return aten.gelu_backward(g, z, approximate=act.approximate)
    if isinstance(act, nn.Tanh):
        return aten.tanh_backward(g, a)
    if isinstance(act, nn.Softplus):
        return aten.softplus_backward(g, z, act.beta, act.threshold)
    return aten.silu_backward(g, z)


_act_slope = activation_slope  # act'(z) as a differentiable expression (`mechanics.mlp`)


def _act_curvature(act: nn.Module, z: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """act''(z)."""
    if isinstance(act, nn.GELU) and act.approximate == "none":
        return torch.exp(-0.5 * z * z) * _INV_SQRT2PI * (2.0 - z * z)
    if isinstance(act, nn.Tanh):
        return -2.0 * a * (1.0 - a * a)
    if isinstance(act, nn.Softplus):
        bz = act.beta * z
        s = torch.sigmoid(bz)
        return torch.where(bz > act.threshold, torch.zeros_like(z), act.beta * s * (1.0 - s))
    if isinstance(act, nn.SiLU):
        s = torch.sigmoid(z)
        return s * (1.0 - s) * (2.0 + z * (1.0 - 2.0 * s))
    c, k = math.sqrt(2.0 / math.pi), 0.044715
    t = torch.tanh(c * (z + k * z * z * z))
    du = c * (1.0 + 3 * k * z * z)
    d2u = c * 6 * k * z
    sech2 = 1.0 - t * t
    return sech2 * du + 0.5 * z * (-2.0 * t * sech2 * du * du + sech2 * d2u)


def _forward(lys: list[Layer], x: torch.Tensor) -> tuple[torch.Tensor, list[tuple[torch.Tensor, torch.Tensor]]]:
    """Output and the (pre-activation, activation) of every hidden layer."""
    saved = []
    a = x
    for lin, act in lys[:-1]:
        z = nn.functional.linear(a, lin.weight, lin.bias)
        assert act is not None
        a = _act(act, z)
        saved.append((z, a))
    last = lys[-1][0]
    return nn.functional.linear(a, last.weight, last.bias), saved


class _ActAndSlope(torch.autograd.Function):
    """(act(z), act'(z)) as one autograd node: the forward from `_act_and_slope` (exact GELU: one erf and
    one exp), the backward d/dz = grad_a act'(z) + grad_s act''(z) (`_act_curvature`). Autograd of the
    same formulas written as tensor expressions records ~10 nodes per layer whose backward passes cost
    1.8x as much (MLP 64 x 3 at 2048 points, docs/benchmarks.md round 8). Once differentiable: a second
    backward through it raises instead of returning zeros."""

    @staticmethod
    def forward(ctx, z: torch.Tensor, act: nn.Module) -> tuple[torch.Tensor, torch.Tensor]:
        if isinstance(act, nn.GELU) and act.approximate == "none":
            # act'' = phi(z) (2 - z^2) from the same exp as act', kept for the backward
            a, s, e = _gelu_value_slope_gauss(z)
            curv = torch.mul(z, z).mul_(-_INV_SQRT2PI).add_(2.0 * _INV_SQRT2PI).mul_(e)
        else:
            a, s = _act_and_slope(act, z)
            curv = _act_curvature(act, z, a)
        ctx.save_for_backward(s, curv)
        return a, s

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_a: torch.Tensor | None, grad_s: torch.Tensor | None):
        s, curv = ctx.saved_tensors
        if grad_a is None:
            return None if grad_s is None else grad_s * curv, None
        out = grad_a * s
        return out if grad_s is None else out.addcmul_(grad_s, curv), None


def _act_and_slope_differentiable(act: nn.Module, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(act(z), act'(z)) under autograd: one `_ActAndSlope` node, or the plain expressions while
    `torch.compile` traces (inductor fuses those itself) and under torch.func transforms (vmap, jacrev:
    the reference path's Newton Jacobian, `losses.autodiff_jacobian_var`, differentiates through the
    slope twice, which the once-differentiable node cannot)."""
    if torch.compiler.is_compiling() or torch._C._are_functorch_transforms_active():
        a = act(z)
        return a, _act_slope(act, z, a)
    out = _ActAndSlope.apply(z, act)
    return out[0], out[1]


def value_and_gradient(net: nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(net(x)[..., 0] (...,), d sum(net(x)[..., 0]) / dx (..., n)) of a network with one output;
    None when `layers(net)` is None."""
    lys = layers(net)
    if lys is None:
        return None
    g = lys[-1][0].weight[0]  # broadcast against the batch by the first product below
    differentiable = torch.is_grad_enabled() and (x.requires_grad or any(p.requires_grad for p in net.parameters()))
    if differentiable and len(lys) > 1:
        # feature major (width, T): each layer one wide product, as in `gradient_columns`
        slopes = []
        a = x.reshape(-1, x.shape[-1]).T
        for lin, act in lys[:-1]:
            assert act is not None
            z = lin.weight @ a if lin.bias is None else torch.addmm(lin.bias[:, None], lin.weight, a)
            a, s = _act_and_slope_differentiable(act, z)
            slopes.append(s)
        last = lys[-1][0]
        out = last.weight[:1] @ a if last.bias is None else torch.addmm(last.bias[:1, None], last.weight[:1], a)
        g = g[:, None]
        for (lin, _), s in zip(reversed(lys[:-1]), reversed(slopes)):
            g = lin.weight.T @ (g * s)
        return out[0].reshape(x.shape[:-1]), g.T.reshape(x.shape)
    out, saved = _forward(lys, x)
    for (lin, act), (z, a) in zip(reversed(lys[:-1]), reversed(saved)):
        assert act is not None
        g = _act_backward(act, g, z, a) @ lin.weight
    return out[..., 0], g.expand(*x.shape[:-1], -1)


def gradient_and_hvp(net: nn.Module, x: torch.Tensor, v: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(dV/dx, (d^2 V/dx^2) v), both (..., n), of a network with one output V = net(x)[..., 0]:
    reverse mode for the gradient and its directional derivative along v carried alongside
    (forward over reverse, by hand). None when `layers(net)` is None."""
    lys = layers(net)
    if lys is None:
        return None
    saved = []
    a, da = x, v
    for lin, act in lys[:-1]:
        assert act is not None
        z = nn.functional.linear(a, lin.weight, lin.bias)
        dz = da @ lin.weight.T
        a = act(z)
        s = _act_slope(act, z, a)
        saved.append((z, a, dz, s))
        da = s * dz
    g = lys[-1][0].weight[0].expand(*x.shape[:-1], -1)
    dg = torch.zeros_like(g)
    for (lin, act), (z, a, dz, s) in zip(reversed(lys[:-1]), reversed(saved)):
        assert act is not None
        c = _act_curvature(act, z, a)
        g, dg = g * s, dg * s + g * c * dz
        g, dg = g @ lin.weight, dg @ lin.weight
    return g, dg


def _needs_graph(net: nn.Module, x: torch.Tensor) -> bool:
    return torch.is_grad_enabled() and (x.requires_grad or any(p.requires_grad for p in net.parameters()))


def _gelu_value_slope_gauss(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Exact GELU's (z Phi(z), Phi(z) + z phi(z), e = exp(-z^2/2)), phi = e / sqrt(2 pi), from one erf and
    one exp (ATen's `gelu` and `gelu_backward` would evaluate erf twice), no graph, written in place:
    nine passes over z where eleven were."""
    u = z * _INV_SQRT2
    cdf = torch.erf(u).mul_(0.5).add_(0.5)  # Phi(z)
    e = torch.mul(u, u).neg_().exp_()
    return z * cdf, torch.addcmul(cdf, e, z, value=_INV_SQRT2PI), e


def _act_and_slope(act: nn.Module, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(act(z), act'(z)), no graph; exact GELU from one erf and one exp (ATen's formulas for
    `gelu` and `gelu_backward`, which would evaluate erf twice), written in place."""
    if isinstance(act, nn.GELU) and act.approximate == "none":
        a, s, _ = _gelu_value_slope_gauss(z)
        return a, s
    a = act(z)
    return a, _act_backward(act, torch.ones_like(z), z, a)


def gradient_feature_major(lys: list[Layer], x: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """scale * d net(x)[:, 0] / dx of a scalar network (no graph), computed and returned feature
    major: x (T, n) -> (n, T). Every layer is then one wide product (width x T), several times
    faster on CPU than the batch-major (T x width) one at these widths."""
    return gradient_columns(lys, x.T, scale)


def gradient_columns(lys: list[Layer], a: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """`gradient_feature_major` from the input already feature major: a (n, T) -> (n, T)."""
    slopes = []
    for lin, act in lys[:-1]:
        assert act is not None
        z = lin.weight @ a if lin.bias is None else torch.addmm(lin.bias[:, None], lin.weight, a)
        a, s = _act_and_slope(act, z)
        slopes.append(s)
    g = (scale * lys[-1][0].weight[0])[:, None]
    for (lin, _), s in zip(reversed(lys[:-1]), reversed(slopes)):
        g = lin.weight.T @ s.mul_(g)
    return g


def rotation_potential_covector(lys: list[Layer], G: ProductGroup, R: torch.Tensor, h: float) -> torch.Tensor:
    """-h dV(R exp(eta))/d eta at 0, (T, 3 B), of an MLP potential V = net(R.flatten()) with layers
    `lys` on a rotation-only group, R (T, B, 3, 3) (rank 4: one batch axis), without a graph."""
    return _rotation_covector(G, R, gradient_feature_major(lys, R.flatten(-3), -h))


def _rotation_covector(G: ProductGroup, R: torch.Tensor, dx_t: torch.Tensor) -> torch.Tensor:
    """`left_covector` of a rotation-only group from the feature-major dx_t (9 B, T): (T, 3 B)."""
    T, B = R.shape[0], G.n_bodies
    dR = dx_t.T.reshape(T, B, 3, 3)
    c = torch.linalg.cross(dR, R, dim=-1)
    return (c[..., 0, :] + c[..., 1, :] + c[..., 2, :]).reshape(T, 3 * B)


def first_layer(net: nn.Module) -> nn.Linear:
    """The first Linear layer of a network `layers` accepts."""
    first = next(iter(net.children()))
    assert isinstance(first, nn.Linear)
    return first


def value_and_jacobian(net: nn.Module, z1: torch.Tensor, E: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Output (..., out) and its Jacobian (..., out, k) of a network whose first pre-activation z1
    (..., width) is given together with its derivative E (..., width, k) (or (width, k)) with
    respect to k inputs (forward mode through the hidden layers). Needs `layers(net)`."""
    lys = layers(net)
    assert lys is not None
    if len(lys) == 1:  # a single Linear layer: z1 is the output
        return z1, E.expand(*z1.shape[:-1], *E.shape[-2:])
    z, J = z1, E
    for i, (_, act) in enumerate(lys[:-1]):
        assert act is not None
        a = act(z)
        s = _act_slope(act, z, a)
        J = s[..., None] * J
        nxt = lys[i + 1][0]
        z = nn.functional.linear(a, nxt.weight, nxt.bias)
        J = nxt.weight @ J
    return z, J


# ---------------------------------------------------------------------------- on the group
def left_covector(G: ProductGroup, g: Pose, dx: torch.Tensor) -> torch.Tensor:
    """d f(g exp(eta)) / d eta at 0, (..., dim), from dx = df/dflatten(g) (..., 9 B + 3 m).

    Per body the rotational part is vee(A - A^T) with A = R^T dR, i.e. sum_k dR_k x R_k over the
    rows k (A - A^T = hat(sum_k dR_k x R_k)); the translational part of an SE(3) body is R^T dp."""
    lead = g.R.shape[:-3]
    B, m = G.n_bodies, G.n_se3
    dR = dx[..., : 9 * B].reshape(*lead, B, 3, 3)
    c = torch.linalg.cross(dR, g.R, dim=-1)
    w = c[..., 0, :] + c[..., 1, :] + c[..., 2, :]  # two adds: faster than a sum over the middle axis
    if not m:
        return w.reshape(*lead, 3 * B)
    dp = dx[..., 9 * B :].reshape(*lead, m, 3)
    v = (g.R[..., :m, :, :] * dp[..., :, None]).sum(-2)
    return G.join(w, v)


def potential_covector(model, g: Pose) -> torch.Tensor | None:
    """-h dV(g exp(eta))/d eta at 0 (..., dim) of a model whose potential is an `MLPPotential`
    of a supported network; None otherwise."""
    return mlp_potential_covector(model.potential, model.G, g, float(model.h))


def mlp_potential_covector(V, G: ProductGroup, g: Pose, h: float) -> torch.Tensor | None:
    """-h dV(g exp(eta))/d eta at 0 (..., dim) for V an `MLPPotential` on G of a supported network,
    in closed form (differentiable in the parameters and in g); None for any other V."""
    from ..mechanics.potentials import MLPPotential

    if not isinstance(V, MLPPotential):
        return None
    x = g.R.flatten(-3) if not G.n_se3 else G.flatten(g)  # no copy for rotation-only groups
    if x.dim() == 2 and not G.n_se3 and not _needs_graph(V.net, x):
        lys = layers(V.net)
        if lys is not None:
            return rotation_potential_covector(lys, G, g.R, h)
    got = value_and_gradient(V.net, x)
    if got is None:
        return None
    return -h * left_covector(G, g, got[1])


class ForcesAt:
    """The per-iteration ("generic") forces of a Newton solve at a fixed g: their sum F(g, xi~) and
    dF/d xi~ (..., dim, dim). An `NNForce` with a supported network is evaluated in closed form
    (value and Jacobian in one pass, the part of its first layer fixed by g computed once); other
    forces by calling them and `force_jacobian_xi` (autodiff). The Jacobian computed with a value
    is kept for the next `jacobian` call at the same xi~ (Newton asks for it at the accepted iterate)."""

    def __init__(self, G: ProductGroup, forces: list[nn.Module], g: Pose):
        from ..mechanics.forces import NNForce

        self.G, self.g = G, g
        self.closed: list[tuple[nn.Module, torch.Tensor, torch.Tensor, torch.Tensor]] = []
        self.other: list[nn.Module] = []
        for f in forces:
            if isinstance(f, NNForce) and layers(f.net) is not None and not torch.is_grad_enabled():
                lin = first_layer(f.net)
                n_g = lin.in_features - G.dim
                z0 = nn.functional.linear(G.flatten(g), lin.weight[:, :n_g], lin.bias)
                self.closed.append((f.net, torch.as_tensor(f.scale), z0, lin.weight[:, n_g:]))
            else:
                self.other.append(f)
        self._kept: tuple[object, torch.Tensor] | None = None

    def _closed(self, xi: torch.Tensor, jac: bool) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        F = J = None
        for net, scale, z0, Wxi in self.closed:
            z1 = torch.addmm(z0, xi, Wxi.T) if xi.dim() == 2 else z0 + xi @ Wxi.T
            Fi, Ji = value_and_jacobian(net, z1, Wxi)
            F = scale * Fi if F is None else F + scale * Fi
            if jac:
                J = scale * Ji if J is None else J + scale * Ji
        return F, J

    def value(self, xi: torch.Tensor, key: object = None) -> torch.Tensor:
        """Sum of the forces at xi~ (..., dim); the closed-form forces' Jacobian is kept under
        `key` (the iterate xi~ was computed from)."""
        F, J = self._closed(xi, True)
        out = torch.zeros_like(xi) if F is None else F
        for f in self.other:
            out = out + f(self.g, xi)
        self._kept = None if J is None or key is None else (key, J)
        return out

    def jacobian(self, xi: torch.Tensor, key: object = None) -> torch.Tensor:
        """Sum of dF/d xi~ at xi~, (..., dim, dim) (the one kept by `value` under the same `key`)."""
        from ..mechanics.forces import force_jacobian_xi

        if key is not None and self._kept is not None and self._kept[0] is key:
            J: torch.Tensor | None = self._kept[1]
        else:
            J = self._closed(xi, True)[1]
        for f in self.other:
            Jf = force_jacobian_xi(f, self.g, xi).detach()
            J = Jf if J is None else J + Jf
        assert J is not None
        return J

    def restrict(self, rows: torch.Tensor) -> ForcesAt:
        """The same forces on the rows `rows` of the batch."""
        sub = ForcesAt.__new__(ForcesAt)
        sub.G, sub._kept, sub.other = self.G, None, self.other
        sub.g = Pose(self.g.R.index_select(0, rows), self.g.p.index_select(0, rows))
        sub.closed = [(net, s, z0.index_select(0, rows), W) for net, s, z0, W in self.closed]
        return sub


def potential_input_gradient(net: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
    """dV/dx (..., n) of an MLP potential V = net(x)[..., 0], differentiable in the parameters:
    closed form where `mlp_derivatives` supports the network, else autograd."""
    vg = value_and_gradient(net, x)
    if vg is not None:
        return vg[1]
    with torch.enable_grad():
        xg = x.detach().requires_grad_(True) if not x.requires_grad else x
        (g,) = torch.autograd.grad(net(xg)[..., 0].sum(), xg, create_graph=True)
    return g
