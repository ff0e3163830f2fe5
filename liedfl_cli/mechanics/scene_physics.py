"""A scene's true physics as model parts: per-body J, m, rho, the Rayleigh D, the gravity and
interaction potential and a known control, read from a synthetic dataset's params["physics"].

Used for the true-parameter discrete scheme (`models.true_scheme`) and for the frozen parts of a
model with a partly known Lagrangian (`model.known`).

`physics` (a scene's `dataset.params["physics"]`) holds
  J    3 diagonal entries, a 3x3 matrix, B lists of 3 diagonal entries or B 3x3 matrices
       (a 3x3 array is always read as one full matrix shared by every body)
  m    one mass or B masses;  rho  one (3,) centre of mass or B of them
  g    gravitational acceleration (gravity potential m g e3.(o + R rho), o = p or the pivot 0)
  D    length-dim diagonal or dim x dim Rayleigh damping on the flat tangent layout
  interaction (optional)  {kind, mu, r1, r2, moment1, moment2}, see mechanics.potentials
  control (optional)      {R_f (rotation vector), K_R, K_w, feedforward}, see forces.PDControl
"""

from __future__ import annotations

import torch
from torch import nn

from ..lie import ProductGroup, so3
from .forces import PDControl
from .potentials import GravityPotential, InteractionPotential, SumPotential


def _per_body(value, n: int, shape: tuple[int, ...]) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64)
    return t.expand(n, *shape).clone() if t.shape == shape else t.reshape(n, *shape)


def body_parameters(G: ProductGroup, physics: dict):
    """-> J (B, 3, 3), masses (B,), rhos (B, 3), D (dim, dim) from a physics dict."""
    B = G.n_bodies
    J = torch.as_tensor(physics["J"], dtype=torch.float64)
    if J.shape == (3,):
        J = torch.diag(J)
    elif J.ndim == 2 and J.shape == (B, 3) and J.shape != (3, 3):
        J = torch.diag_embed(J)
    J = _per_body(J, B, (3, 3))
    masses = _per_body(physics.get("m", 1.0), B, ())
    rhos = _per_body(physics.get("rho", [0.0, 0.0, 0.0]), B, (3,))
    D = torch.as_tensor(physics.get("D", [0.0] * G.dim), dtype=torch.float64)
    if D.ndim == 1:
        D = torch.diag(D)
    if D.shape != (G.dim, G.dim):
        raise ValueError(
            f"physics.D has shape {tuple(D.shape)}, expected ({G.dim},) or ({G.dim}, {G.dim}) for {G.name}"
        )
    return J, masses, rhos, D


def true_potential(G: ProductGroup, physics: dict):
    """Gravity (+ interaction) potential of a scene as a module without parameters, or None."""
    _, masses, rhos, _ = body_parameters(G, physics)
    terms: list[nn.Module] = []
    gravity = float(physics.get("g", 0.0))
    if gravity != 0.0:
        terms.append(GravityPotential(G, masses, rhos, gravity))
    inter = physics.get("interaction")
    if inter:
        a, b = (int(i) for i in inter.get("bodies", (0, 1)))
        kw = {k: inter[k] for k in ("r1", "r2", "moment1", "moment2") if k in inter}
        terms.append(
            InteractionPotential(
                G, inter["kind"], float(inter["mu"]), masses=masses[[a, b]], rhos=rhos[[a, b]], bodies=(a, b), **kw
            )
        )
    if not terms:
        return None
    return terms[0] if len(terms) == 1 else SumPotential(terms)


def true_control(G: ProductGroup, physics: dict):
    """The scene's known control force (PDControl), or None."""
    ctrl = physics.get("control")
    if not ctrl:
        return None
    _, masses, rhos, _ = body_parameters(G, physics)
    R_f = so3.exp(torch.as_tensor(ctrl["R_f"], dtype=torch.float64))
    return PDControl(
        G,
        ctrl["K_R"],
        ctrl["K_w"],
        R_f,
        bool(ctrl.get("feedforward", False)),
        m=float(masses[0]),
        rho=rhos[0],
        g=float(physics.get("g", 0.0)),
    )
