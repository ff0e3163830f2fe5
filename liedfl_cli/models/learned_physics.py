"""What a trained model learned, read into plain dicts for the closing summary of `liedfl train`
(`display.closing_summary` formats them): per body mass, centre of mass, principal inertia, damping
(or m·com of a body on a pivot), joints and parents of a tree, gravity, put on the truth's scale where
the data declare physics, the worst relative errors of `recovery.json`.

`dataset`: a `data.hdf5.Dataset`, read through .body_names and .params only (models/ may not import
data/)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

JOINT_DOF = {"free": 6, "ball": 3, "universal": 2, "hinge": 1, "weld": 0}
LENGTH_UNITS = {1.0: "m", 1e-2: "cm", 1e-3: "mm"}
ERROR_KEYS = (  # recovery.json's worst relative errors, by what they are about (the first found of each)
    ("Jd_over_trace_max_rel_error", "J"),
    ("inertia_max_rel_error", "J"),
    ("m_over_trace_rel_error", "m"),
    ("mass_fraction_max_rel_error", "m"),
    ("rho_max_rel_error", "com"),
    ("D_over_trace_max_rel_error", "damping"),
    ("dof_damping_max_rel_error", "damping"),
    ("joint_damping_max_rel_error", "damping"),
)


def _principal(J) -> list[float]:
    import torch

    return [float(x) for x in torch.linalg.eigvalsh(J)]


def _bodies_of(model, params: dict, scale: float, names: list[str], joints: list[str] | None,
               parents: list[int] | None) -> list[dict]:  # fmt: skip
    """Per-body dicts (see `body_line`) of a model's `physical_parameters`, divided by `scale`."""
    import torch

    Jd = params.get("J_d")
    if Jd is None:
        return []
    B = int(Jd.shape[0])
    J = (
        Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=Jd.dtype, device=Jd.device) - Jd
    )  # J = tr(J_d) I - J_d
    m, rho = params.get("m"), params.get("rho_COM")
    n_m = int(m.shape[0]) if m is not None else 0
    damping = _damping_per_body(model, params, B, joints)
    grav = _gravity(model)
    moments = grav.moment if grav is not None and getattr(grav, "moment", None) is not None else None
    out = []
    for b in range(B):
        d: dict[str, Any] = {"name": names[b] if b < len(names) else f"body{b}"}
        if joints is not None and b < len(joints):
            d["joint"] = joints[b]
            if parents is not None and parents[b] >= 0:
                d["parent"] = names[parents[b]] if parents[b] < len(names) else f"body{parents[b]}"
        if b < n_m:
            assert m is not None and rho is not None
            d["mass"] = float(m[b]) / scale
            d["com"] = [float(x) for x in rho[b]]
        elif moments is not None and b - n_m < moments.shape[0]:
            d["moment"] = [float(x) / scale for x in moments[b - n_m].detach()]
        d["inertia"] = [x / scale for x in _principal(J[b])]
        c = damping[b] if damping is not None else None
        if c is not None:
            d["damping"] = c / scale
        out.append(d)
    return out


def _damping_per_body(model, params: dict, B: int, joints: list[str] | None) -> list[float | None] | None:
    """The mean damping coefficient of each body's joint (`dof_damping`, by the joints' DoF; a free root's
    undamped DoF left out; a weld: none) or of the rotational diagonal of its block of a constant Rayleigh `D`."""
    coeffs = params.get("dof_damping")
    if coeffs is not None and joints is not None:
        out: list[float | None] = []
        k = 0
        for kind in joints[:B]:
            n = JOINT_DOF.get(kind, 3)
            block = coeffs[k : k + n]
            k += n
            values = [float(x) for x in block]
            if kind == "free":  # a free root: only its damped DoF, if any
                values = [x for x in values if x != 0.0]
            out.append(sum(values) / len(values) if values else None)
        return out
    D = params.get("D")
    G = getattr(model, "G", None)
    if D is None or G is None:
        return None
    slices = G.body_slices()
    if len(slices) != B:
        return None
    return [float(D[s, s].diagonal()[:3].mean()) for s in slices]  # the rotational part


def _gravity(model):
    from ..mechanics.potentials import SumPotential, UniformGravityPotential

    for V in (getattr(model, "potential", None), getattr(model, "potential_world", None)):
        if V is None or not hasattr(V, "parameters"):
            continue
        terms = list(V.terms) if isinstance(V, SumPotential) else [V]
        found = next((t for t in terms if isinstance(t, UniformGravityPotential)), None)
        if found is not None:
            return found
    return None


def _true_moments(model, dataset, bodies: list[dict], true_bodies: list[dict]) -> None:
    """m·com of pivot (SO(3)) bodies under gravity from the declared physics (the true scheme's potential
    has no learnable moment to read), beside the learned ones."""
    physics = (getattr(dataset, "params", None) or {}).get("physics") or {}
    G = getattr(model, "G", None)
    if G is None or "m" not in physics or not any("moment" in b for b in bodies):
        return
    from ..mechanics.scene_physics import body_parameters

    _, masses, rhos, _ = body_parameters(G, dict(physics))
    for b, (body, true) in enumerate(zip(bodies, true_bodies)):
        if "moment" in body and "moment" not in true and b < len(masses):
            true["moment"] = [float(masses[b]) * float(x) for x in rhos[b]]


def gather(model, dataset, recovery: Mapping[str, Any] | None) -> dict | None:
    """The `physics` dict of `physics_lines` for a trained model (None: no physical parameters), read
    where the model lives (the caller moves a GPU or float32 model to the CPU in float64 first):
    learned figures put on the truth's scale where the data declare physics (`recovery`'s
    `scale_learned_over_true`), joints and parents of a tree, gravity, the worst relative errors."""
    from ..models.true_scheme import true_model

    inner = getattr(model, "inner", model)  # (a substeps wrapper)
    params = inner.physical_parameters()
    if not params or "J_d" not in params:
        return None
    tree = getattr(inner, "tree", None)
    kinetic = "articulated" if tree is not None else "per_body"
    names = list(getattr(dataset, "body_names", []) or [])
    joints = parents = None
    if tree is not None:
        record = inner.joint_record() if hasattr(inner, "joint_record") else None
        joints = list((record or {}).get("kinds") or tree.joints or [])
        joints = joints or ["free" if tree.free_root else "ball"] + ["ball"] * (len(tree.parents) - 1)
        parents = list(tree.parents)
    scale, scaled = 1.0, None
    if recovery and recovery.get("scale_learned_over_true"):
        scale, scaled = float(recovery["scale_learned_over_true"]), "true"
    elif kinetic == "articulated" and getattr(inner, "total_mass", None):
        scaled = "total_mass"
    bodies = _bodies_of(inner, params, scale, names, joints, parents)
    true_bodies = None
    ref = true_model(dataset) if recovery else None
    if ref is not None and type(getattr(ref, "inner", ref)) is type(inner):
        ref = getattr(ref, "inner", ref)
        truth = _bodies_of(ref, ref.physical_parameters(), 1.0, names, joints, parents)
        true_bodies = [{k: v for k, v in t.items() if k not in ("name", "joint", "parent")} for t in truth]
        if len(true_bodies) != len(bodies):
            true_bodies = None
        else:
            _true_moments(inner, dataset, bodies, true_bodies)
    unit = float((getattr(dataset, "params", None) or {}).get("length_unit_m", 1.0) or 1.0)
    out: dict[str, Any] = {"kinetic": kinetic, "bodies": bodies, "true_bodies": true_bodies, "scaled": scaled,
                           "units": {"length": LENGTH_UNITS.get(unit, f"({unit:g} m)")}}  # fmt: skip
    grav = _gravity(inner)
    if grav is not None:
        out["gravity"] = {"g": float(grav.gravity), "up": [float(x) for x in grav.direction().detach()],
                          "learned_up": bool(grav.learn_direction),
                          "up_error_rad": (recovery or {}).get("gravity_direction_error_rad")}  # fmt: skip
    errors = {}
    for key, label in ERROR_KEYS:
        v = (recovery or {}).get(key)
        if isinstance(v, (int, float)) and math.isfinite(v) and label not in errors:
            errors[label] = float(v)
    if errors:
        out["errors"] = errors
    ident = (recovery or {}).get("identifiability") or {}
    gauge, n_par = ident.get("gauge_dimension"), ident.get("parameters")
    if isinstance(gauge, int) and isinstance(n_par, int) and gauge > 0:
        out["gauge"] = {"invisible": gauge, "parameters": n_par}
    return out


__all__ = ["gather"]
