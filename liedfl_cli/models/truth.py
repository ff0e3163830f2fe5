"""The discrete scheme with the scene's true parameters (J_d, m, rho, D and the known potential).

It is what a perfect LieDFLNN would learn: the yardstick for learned models ("true-parameter
discrete scheme") and the subject of the O(h^3)/O(h^2) consistency checks.
"""
from __future__ import annotations

import torch

from ..lie import ProductGroup
from ..mechanics.potentials import GravityPotential
from .liedflnn import LieDFLNN


def _per_body(value, n: int, shape: tuple[int, ...]) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64)
    return t.expand(n, *shape).clone() if t.shape == shape else t.reshape(n, *shape)


def physics_model(G: ProductGroup, h: float, physics: dict, residual: str = "fast") -> LieDFLNN:
    """LieDFLNN carrying the true rigid-body parameters of `physics`.

    physics: J (3 diagonal entries or 3x3, or one per body), m, rho (3 or per body), g, and
    D (length-dim diagonal or dim x dim). Bodies share J/m/rho when a single value is given.
    """
    B = G.n_bodies
    J = torch.as_tensor(physics["J"], dtype=torch.float64)
    if J.shape == (3,):
        J = torch.diag(J)
    J = _per_body(J, B, (3, 3))
    masses = _per_body(physics.get("m", 1.0), B, ())
    rhos = _per_body(physics.get("rho", [0.0, 0.0, 0.0]), B, (3,))
    D = torch.as_tensor(physics.get("D", [0.0] * G.dim), dtype=torch.float64)
    if D.ndim == 1:
        D = torch.diag(D)
    forces = ["rayleigh"] if torch.count_nonzero(D) else []
    model = LieDFLNN(G, h, potential="none", forces=forces, residual=residual, init_jitter=0.0)
    model.inertia.set_J(J)
    if G.n_se3:
        model.mass.set_value(masses[: G.n_se3])
        with torch.no_grad():
            model.rho.copy_(rhos[: G.n_se3])
    if forces:
        model.forces[0].D.set_matrix(D)
    gravity = float(physics.get("g", 0.0))
    if gravity != 0.0:
        model.potential = GravityPotential(G, masses, rhos, gravity)
    model.requires_grad_(False)
    return model


def true_model(dataset, residual: str = "fast") -> LieDFLNN | None:
    """The true-parameter scheme of a synthetic dataset, or None for real recordings."""
    physics = (dataset.params or {}).get("physics")
    if not physics or "J" not in physics:
        return None
    return physics_model(dataset.group, dataset.h, physics, residual)


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
        rel = lambda a, b: float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))  # noqa: E731
        out = {
            "Jd_over_trace_max_rel_error": rel(Jd / s[:, None, None], Jd_true / s_true[:, None, None]),
            "scale_learned_over_true": float((s / s_true).mean()),
        }
        if model.forces and ref.forces:
            D, D_true = model.forces[0].D(), ref.forces[0].D()
            out["D_over_trace_max_rel_error"] = rel(D / s[0], D_true / s_true[0])
            out["D_ratio_learned"] = float(D.diagonal()[:3].mean() / s[0])
            out["D_ratio_true"] = float(D_true.diagonal()[:3].mean() / s_true[0])
        if model.G.n_se3:
            out["m_over_trace_rel_error"] = rel(model.mass() / s[: model.G.n_se3], ref.mass() / s_true[: model.G.n_se3])
            out["rho_max_abs_error"] = float((model.rho - ref.rho).abs().max())
    return out
