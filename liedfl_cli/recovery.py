"""Parameter recovery: learned against true parameters of a synthetic scene, after removing
the common scale that the DEL residual cannot see."""

from __future__ import annotations

import torch

from .models.liedflnn import LieDFLNN
from .models.true_scheme import true_model


def _rayleigh(model):
    for f in getattr(model, "forces", ()):
        if getattr(f, "name", None) == "rayleigh":
            return f
    return None


def parameter_recovery(model, dataset) -> dict | None:
    """Learned vs true parameters after removing the common scale (divide by tr J_d).

    The residual is linear in (L_d, F), so only the regularity term fixes the overall scale;
    J_d, D and m (and the first moments m rho of pivot bodies under a uniform_gravity potential)
    are compared after normalising each side by its own tr J_d; rho is a length and compared as
    it is. Errors are max |entry difference| / max |true entry| over the compared arrays.
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
            out["rho_max_rel_error"] = rel(model.rho, ref.rho)
        grav = _uniform_gravity(model)
        physics = (dataset.params or {}).get("physics") or {}
        if grav is not None and model.G.n_so3 and "m" in physics:
            from .mechanics.scene_physics import body_parameters

            _, masses, rhos, _ = body_parameters(model.G, physics)
            m = model.G.n_se3
            true_c = (masses[m:, None] * rhos[m:]) / s_true[m:, None]
            out["pivot_moment_over_trace_rel_error"] = rel(grav.moment / s[m:, None], true_c)
        if grav is not None and grav.learn_direction:
            u, e3 = grav.direction(), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
            sin = torch.linalg.vector_norm(torch.linalg.cross(u, e3))
            out["gravity_direction_error_rad"] = float(torch.atan2(sin, u @ e3))
    return out


def _uniform_gravity(model):
    from .mechanics.potentials import SumPotential, UniformGravityPotential

    V = getattr(model, "potential", None)
    terms = list(V.terms) if isinstance(V, SumPotential) else [V]
    return next((t for t in terms if isinstance(t, UniformGravityPotential)), None)
