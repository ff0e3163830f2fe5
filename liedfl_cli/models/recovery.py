"""Parameter recovery of the DEL models: learned against true parameters of a synthetic scene,
after removing the common scale that the DEL residual cannot see. Reached through the model hook
`Model.parameter_recovery` (the pipeline calls `liedfl_cli.config.runs`-level code only through it)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

# The models call in here (their `parameter_recovery` hooks), so their classes are not imported:
# `model` and `ref` are a LieDFLNN pair or an ArticulatedLieDFLNN pair.


def _rayleigh(model):
    for f in model.force_terms():
        if getattr(f, "name", None) == "rayleigh":
            return f
    return None


def lie_recovery(model: Any, ref: Any, physics: Mapping[str, Any]) -> dict:
    """Learned vs true parameters after removing the common scale (divide by tr J_d).

    The residual is linear in (L_d, F), so only the regularity term fixes the overall scale;
    J_d, D and m (and the first moments m rho of pivot bodies under a uniform_gravity potential)
    are compared after normalising each side by its own tr J_d; rho is a length and compared as
    it is. Errors are max |entry difference| / max |true entry| over the compared arrays.
    `physics`: the scene's declared physics (params["physics"]). Both models on one device in one
    dtype (`liedfl_cli.config.recovery` compares them on the CPU in float64).
    """
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
            assert model.mass is not None and model.rho is not None  # set for SE(3) bodies
            assert ref.mass is not None and ref.rho is not None
            out["m_over_trace_rel_error"] = rel(model.mass() / s[: model.G.n_se3], ref.mass() / s_true[: model.G.n_se3])
            out["rho_max_abs_error"] = float((model.rho - ref.rho).abs().max())
            out["rho_max_rel_error"] = rel(model.rho, ref.rho)
        grav = _uniform_gravity(model)
        if grav is not None and model.G.n_so3 and "m" in physics:
            from ..mechanics.scene_physics import body_parameters

            _, masses, rhos, _ = body_parameters(model.G, dict(physics))
            m = model.G.n_se3
            true_c = (masses[m:, None] * rhos[m:]) / s_true[m:, None]
            out["pivot_moment_over_trace_rel_error"] = rel(grav.moment / s[m:, None], true_c)
        if grav is not None and grav.learn_direction:
            u = grav.direction()
            e3 = u.new_tensor([0.0, 0.0, 1.0])
            sin = torch.linalg.vector_norm(torch.linalg.cross(u, e3))
            out["gravity_direction_error_rad"] = float(torch.atan2(sin, u @ e3))
    return out


def _uniform_gravity(model):
    from ..mechanics.potentials import SumPotential, UniformGravityPotential

    V = model.potential
    terms = list(V.terms) if isinstance(V, SumPotential) else [V]
    return next((t for t in terms if isinstance(t, UniformGravityPotential)), None)


def articulated_recovery(model: Any, ref: Any) -> dict:
    """Per-body recovery of an articulated model: m_b, J_b (over the common scale, the total mass
    sum_b m_b of each side), rho_b as lengths, joint damping over the same scale. Each body's figures
    and the worst over bodies; errors are |learned - true| / max |true| per body."""
    with torch.no_grad():
        m, m_true = model.mass(), ref.mass()
        s, s_true = m.sum(), m_true.sum()
        J, J_true = model.inertia.J() / s, ref.inertia.J() / s_true
        rel = lambda a, b: float((a - b).abs().max() / b.abs().max().clamp_min(1e-300))
        bodies: list[dict[str, float | list[float]]] = []
        for b in range(model.tree.n_bodies):
            bodies.append(
                {
                    "mass_fraction_learned": float(m[b] / s),
                    "mass_fraction_true": float(m_true[b] / s_true),
                    "mass_fraction_rel_error": rel(m[b] / s, m_true[b] / s_true),
                    "com_learned": model.rho[b].tolist(),
                    "com_true": ref.rho[b].tolist(),
                    "com_abs_error": float((model.rho[b] - ref.rho[b]).norm()),
                    "inertia_over_total_mass_rel_error": rel(J[b], J_true[b]),
                }
            )
        out: dict = {
            "kinetic": "articulated",
            "scale_learned_over_true": float(s / s_true),
            "mass_fraction_max_rel_error": max(_floats(bodies, "mass_fraction_rel_error")),
            "com_max_abs_error": max(_floats(bodies, "com_abs_error")),
            "inertia_max_rel_error": max(_floats(bodies, "inertia_over_total_mass_rel_error")),
            "bodies": bodies,
        }
        if getattr(model, "start_report", None) is not None:
            # what the data determine: the regressor's rank; the rest is gauge (overall scale, a child's
            # mass sliding onto its parent; per-link masses are reported in that gauge)
            out["identifiability"] = model.start_report
        d, d_true = getattr(model, "dof_damper", None), getattr(ref, "dof_damper", None)
        if d is not None and d_true is not None and model.tree.n_dof == ref.tree.n_dof:
            dl, dt = d.coefficients() / s, d_true.coefficients() / s_true
            out["dof_damping_over_total_mass"] = {"learned": dl.tolist(), "true": dt.tolist()}
            out["dof_damping_max_rel_error"] = rel(dl, dt)
        f, f_true = _rayleigh(model), _rayleigh(ref)
        if f is not None and f_true is not None:
            D, D_true = f.D() / s, f_true.D() / s_true
            sl = model.G.body_slices()
            joints = [
                {
                    "body": b,
                    "learned": float(D[sl[b], sl[b]].diagonal().mean()),
                    "true": float(D_true[sl[b], sl[b]].diagonal().mean()),
                }
                for b in range(1, model.tree.n_bodies)
            ]
            out["joint_damping_over_total_mass"] = joints
            out["joint_damping_max_rel_error"] = max(
                abs(j["learned"] - j["true"]) / max(abs(j["true"]), 1e-300) for j in joints
            )
            out["damping_matrix_rel_error"] = rel(D, D_true)
    return out


def _floats(rows: list[dict], key: str) -> list[float]:
    return [float(r[key]) for r in rows]
