"""Closed forms of the rigid-body kinetic discrete Lagrangian on SE(3)^m x SO(3)^n.

Per body, with increment (W, z) = g_k^{-1} g_{k+1} and X = z + (W - I) rho:
    K = (tr J_d - tr(W J_d)) / h  [+ m |X|^2 / (2h) for SE(3) bodies]
`d1` is dK/d(eta) for the left perturbation g_k exp(eta) of the first argument and `d2`
for the left perturbation g_{k+1} exp(eta) of the second; both return flat tangent
covectors (..., dim) in the layout of `ProductGroup`. Derivations in docs/math.md; each is
tested against autodiff of `kinetic_lagrangian`.

Shapes: W (..., B, 3, 3), z (..., m, 3), Jd (B, 3, 3), mass (m,), rho (m, 3).
"""

from __future__ import annotations

import torch

from ..lie import Pose, ProductGroup, so3


def _trace(A: torch.Tensor) -> torch.Tensor:
    return A.diagonal(dim1=-2, dim2=-1).sum(-1)


def kinetic_lagrangian(G: ProductGroup, inc: Pose, Jd, mass, rho, h: float) -> torch.Tensor:
    """Sum over bodies of K(W, z), shape (...)."""
    W, z = inc.R, inc.p
    K = ((_trace(Jd) - _trace(W @ Jd)) / h).sum(-1)
    m = G.n_se3
    if m:
        eye = torch.eye(3, dtype=W.dtype, device=W.device)
        X = z + so3.act(W[..., :m, :, :] - eye, rho)
        K = K + (0.5 * mass / h * (X * X).sum(-1)).sum(-1)
    return K


def kinetic_d1(G: ProductGroup, inc: Pose, Jd, mass, rho, h: float) -> torch.Tensor:
    """dK/d(eta) at 0 for (g exp(eta))^{-1} g' : (..., dim)."""
    W, z = inc.R, inc.p
    w = so3.vee(Jd @ W.transpose(-1, -2) - W @ Jd) / h
    m = G.n_se3
    if m:
        eye = torch.eye(3, dtype=W.dtype, device=W.device)
        Wm = W[..., :m, :, :]
        X = z + so3.act(Wm - eye, rho)
        a = z + so3.act(Wm, rho)
        scale = (mass / h)[..., None]
        w = torch.cat((w[..., :m, :] + scale * torch.cross(X, a, dim=-1), w[..., m:, :]), -2)
        v = -scale * X
    else:
        v = z[..., :0, :]
    return G.join(w, v)


def kinetic_d2(G: ProductGroup, inc: Pose, Jd, mass, rho, h: float) -> torch.Tensor:
    """dK/d(eta) at 0 for g^{-1} (g' exp(eta)) : (..., dim)."""
    W, z = inc.R, inc.p
    w = so3.vee(Jd @ W - W.transpose(-1, -2) @ Jd) / h
    m = G.n_se3
    if m:
        eye = torch.eye(3, dtype=W.dtype, device=W.device)
        Wm = W[..., :m, :, :]
        X = z + so3.act(Wm - eye, rho)
        WtX = so3.act(Wm.transpose(-1, -2), X)
        scale = (mass / h)[..., None]
        rho_b = rho.expand_as(WtX)
        w = torch.cat((w[..., :m, :] + scale * torch.cross(rho_b, WtX, dim=-1), w[..., m:, :]), -2)
        v = scale * WtX
    else:
        v = z[..., :0, :]
    return G.join(w, v)


def velocity_estimate(G: ProductGroup, inc: Pose, h: float) -> torch.Tensor:
    """(w~, v~) = (vee(W - W^T)/(2h), (I - h/2 hat(w~)) z / h): the paper's first-order log(W, z)/h."""
    W, z = inc.R, inc.p
    w = so3.vee(W) / h
    m = G.n_se3
    wm = w[..., :m, :]
    v = (z - 0.5 * h * torch.cross(wm, z, dim=-1)) / h
    return G.join(w, v)


def _generators(dtype, device) -> torch.Tensor:
    """hat(e_i) stacked: (3, 3, 3)."""
    return so3.hat(torch.eye(3, dtype=dtype, device=device))


def se3_mixed_hessian(W: torch.Tensor, Jd, mass, rho, h: float) -> torch.Tensor:
    """The SE(3) blocks of `mixed_hessian_blocks` for n bodies at once, (..., n, 6, 6):
    [[H_rot + s P W P, -s P W], [s W P, -s W]], P = hat(rho), s = m / h, rows (a_w, a_v), columns
    (b_w, b_v). W (..., n, 3, 3); Jd (n, 3, 3), mass (n,), rho (n, 3)."""
    E = _generators(W.dtype, W.device)
    Hrot = torch.einsum("iab,...kbc,jcd,kda->...kij", E, W, E, Jd) / h
    P = so3.hat(rho)
    s = (mass / h)[:, None, None]
    PW = P @ W
    top = torch.cat((Hrot + s * (PW @ P), -s * PW), -1)
    bottom = torch.cat((s * (W @ P), -s * W), -1)
    return torch.cat((top, bottom), -2)


def mixed_hessian_blocks(G: ProductGroup, inc: Pose, Jd, mass, rho, h: float) -> list[torch.Tensor]:
    """Per-body blocks of H = d^2 K(exp(-a) (W, z) exp(b)) / da db at 0 (closed form).

    Rotational block: H_ij = tr(hat(e_i) W hat(e_j) J_d) / h. SE(3) bodies add, with rows
    (a_w, a_v) and columns (b_w, b_v), (m/h) [[hat(rho) W hat(rho), -hat(rho) W], [W hat(rho), -W]].
    Returns a list of (..., 3, 3) or (..., 6, 6) tensors, one per body.
    """
    W, m = inc.R, G.n_se3
    blocks = list(se3_mixed_hessian(W[..., :m, :, :], Jd[:m], mass, rho, h).unbind(-3)) if m else []
    if G.n_so3:
        E = _generators(W.dtype, W.device)
        Hrot = torch.einsum("iab,...kbc,jcd,kda->...kij", E, W[..., m:, :, :], E, Jd[m:]) / h  # (..., n, 3, 3)
        blocks += list(Hrot.unbind(-3))
    return blocks


def velocity_estimate_jacobian(G: ProductGroup, inc: Pose, h: float) -> torch.Tensor:
    """d xi~ / d delta for the right perturbation inc exp(delta), shape (..., dim, dim), block diagonal.

    d w~/d delta_w = (tr(W) I - W^T) / (2h);  d v~/d delta_v = (I - h/2 hat(w~)) W / h;
    d v~/d delta_w = hat(z)/2 d w~/d delta_w.
    """
    W, z = inc.R, inc.p
    eye = torch.eye(3, dtype=W.dtype, device=W.device)
    dw = (_trace(W)[..., None, None] * eye - W.transpose(-1, -2)) / (2 * h)  # (..., B, 3, 3)
    lead = W.shape[:-3]
    out = W.new_zeros(*lead, G.dim, G.dim)
    for i, s in enumerate(G.body_slices()):
        out[..., s.start : s.start + 3, s.start : s.start + 3] = dw[..., i, :, :]
        if i < G.n_se3:
            w_t = so3.vee(W[..., i, :, :]) / h
            out[..., s.start + 3 : s.stop, s.start + 3 : s.stop] = (eye - 0.5 * h * so3.hat(w_t)) @ W[..., i, :, :] / h
            out[..., s.start + 3 : s.stop, s.start : s.start + 3] = 0.5 * so3.hat(z[..., i, :]) @ dw[..., i, :, :]
    return out
