"""The discrete scheme with the scene's true parameters (J_d, m, rho, D, the known potential and
known forces such as a PD control).

It is what a perfect LieDFLNN would learn: the yardstick for learned models ("true-parameter
discrete scheme") and the subject of the O(h^3)/O(h^2) consistency checks. The same helpers
give the frozen components of a model with a known Lagrangian (`model.known`).

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

from ..lie import ProductGroup, so3
from ..mechanics.forces import PDControl
from ..mechanics.potentials import GravityPotential, InteractionPotential, SumPotential
from .liedflnn import LieDFLNN


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
    terms = []
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


def physics_model(G: ProductGroup, h: float, physics: dict, residual: str = "fast") -> LieDFLNN:
    """LieDFLNN carrying the true parameters of `physics` (every part frozen).

    Bodies share J/m/rho when a single value is given.
    """
    J, masses, rhos, D = body_parameters(G, physics)
    forces = ["rayleigh"] if torch.count_nonzero(D) else []
    model = LieDFLNN(G, h, potential="none", forces=forces, residual=residual, init_jitter=0.0)
    model.inertia.set_J(J)
    if G.n_se3:
        model.mass.set_value(masses[: G.n_se3])
        with torch.no_grad():
            model.rho.copy_(rhos[: G.n_se3])
    if forces:
        model.forces[0].D.set_matrix(D)
    model.potential = true_potential(G, physics)
    ctrl = true_control(G, physics)
    if ctrl is not None:
        model.forces.append(ctrl)
    model.requires_grad_(False)
    return model


def true_model(dataset, residual: str = "fast") -> LieDFLNN | None:
    """The true-parameter scheme of a synthetic dataset, or None for real recordings."""
    physics = (dataset.params or {}).get("physics")
    if not physics or "J" not in physics:
        return None
    return physics_model(dataset.group, dataset.h, physics, residual)


def _rayleigh(model):
    for f in getattr(model, "forces", ()):
        if getattr(f, "name", None) == "rayleigh":
            return f
    return None


def parameter_recovery(model, dataset) -> dict | None:
    """Learned vs true parameters after removing the common scale (divide by tr J_d).

    The residual is linear in (L_d, F), so only the regularity term fixes the overall scale;
    J_d, D and m are compared after normalising each side by its own tr J_d. Errors are
    max |entry difference| / max |true entry| over the compared arrays.
    """
    ref = true_model(dataset)
    if ref is None or not isinstance(model, LieDFLNN):
        return None
    with torch.no_grad():
        Jd, Jd_true = model.inertia.Jd(), ref.inertia.Jd()
        s, s_true = Jd.diagonal(dim1=-2, dim2=-1).sum(-1), Jd_true.diagonal(dim1=-2, dim2=-1).sum(-1)
        rel = lambda a, b: float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))
        out = {
            "Jd_over_trace_max_rel_error": rel(Jd / s[:, None, None], Jd_true / s_true[:, None, None]),
            "scale_learned_over_true": float((s / s_true).mean()),
        }
        f, f_true = _rayleigh(model), _rayleigh(ref)
        if f is not None and f_true is not None:
            D, D_true = f.D(), f_true.D()
            out["D_over_trace_max_rel_error"] = rel(D / s[0], D_true / s_true[0])
            out["D_ratio_learned"] = float(D.diagonal()[:3].mean() / s[0])
            out["D_ratio_true"] = float(D_true.diagonal()[:3].mean() / s_true[0])
        if model.G.n_se3:
            out["m_over_trace_rel_error"] = rel(model.mass() / s[: model.G.n_se3], ref.mass() / s_true[: model.G.n_se3])
            out["rho_max_abs_error"] = float((model.rho - ref.rho).abs().max())
    return out
