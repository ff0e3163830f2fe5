"""The closing summary of `liedfl train` (issue 38): what was learned, in the data's units, beside
the truth where the dataset declares it; the validation figure against constant velocity and
constant acceleration (and the test rollout's); where the files are.

`closing_lines` and its helpers are pure: plain dicts in, lines of text out (tests call them
directly). `gather` reads a trained model and its dataset into those dicts (the one place that
touches tensors); `print_closing_summary` is what `run_train` calls."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

MAX_BODIES = 12  # bodies listed (a bigger tree: the rest in recovery.json); keeps a tree's summary ~25 lines
JOINT_DOF = {"free": 6, "ball": 3, "universal": 2, "hinge": 1, "weld": 0}
FILES = ("checkpoints/best.pt", "checkpoints/last.pt", "recovery.json", "summary.json", "eval.md", "rollout.h5",
         "train_metrics.csv", "train.log")  # fmt: skip
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


# ----------------------------------------------------------------------------- formatting (pure)
def num(x: Any) -> str:
    """A figure for the summary: 3 significant digits, `–` for None or a non-finite value."""
    if x is None or not isinstance(x, (int, float)) or not math.isfinite(float(x)):
        return "–"
    return f"{float(x):.3g}"


def vec(v: Sequence[float] | None) -> str:
    return "–" if v is None else "(" + ", ".join(num(x) for x in v) + ")"


def _beside(learned: str, true: str | None) -> str:
    return learned if true is None else f"{learned} [true {true}]"


def body_line(body: Mapping[str, Any], true: Mapping[str, Any] | None, units: Mapping[str, str]) -> str:
    """One body: `  link1 (ball joint to base): m 1.02 kg [true 1]  com (...) m [true (...)]  J 0.1 0.2 0.3 kg m² ...`.

    body: name, and any of joint, parent (a name), mass, com, moment (m·com of a body on a pivot),
    inertia (principal moments, ascending), damping (the mean of its joint's / body's damping
    coefficients); true: the same keys (None: no truth declared)."""
    t = true or {}
    head = f"  {body['name']}"
    if body.get("joint"):
        head += f" ({body['joint']}" + (f" joint to {body['parent']})" if body.get("parent") else ")")
    L = units.get("length", "m")
    parts = []
    if body.get("mass") is not None:
        parts.append("m " + _beside(f"{num(body['mass'])} kg", num(t["mass"]) if "mass" in t else None))
    if body.get("com") is not None:
        parts.append("com " + _beside(f"{vec(body['com'])} {L}", vec(t["com"]) if "com" in t else None))
    if body.get("moment") is not None:
        parts.append("m·com " + _beside(f"{vec(body['moment'])} kg {L}", vec(t["moment"]) if "moment" in t else None))
    if body.get("inertia") is not None:
        J = " ".join(num(x) for x in body["inertia"])
        true_J = " ".join(num(x) for x in t["inertia"]) if "inertia" in t else None
        parts.append("J " + _beside(f"{J} kg {L}²", true_J))
    if body.get("damping") is not None:
        damping = f"{num(body['damping'])} kg {L}²/s"
        parts.append("damping " + _beside(damping, num(t["damping"]) if "damping" in t else None))
    return head + ": " + "  ".join(parts) if parts else head


def physics_lines(physics: Mapping[str, Any] | None) -> list[str]:
    """What was learned: a heading (the model's kind, how the learned figures are scaled), one line
    per body (at most MAX_BODIES), gravity; [] when the model has no physical parameters.

    physics: kinetic ("per_body" / "articulated"), bodies (list of body dicts, see `body_line`),
    true_bodies (same length, or None), scaled ("true": learned figures put on the truth's common scale;
    "total_mass": dataset.total_mass fixed it; None: up to one common factor), units ({"length": "m"}),
    gravity ({"g", "up", "learned_up", "up_error_rad"} or None), errors (worst relative errors by name)."""
    if not physics or not physics.get("bodies"):
        return []
    kind = "articulated model" if physics.get("kinetic") == "articulated" else "per-body model"
    scale = {
        "true": "overall scale matched to the truth (the data fix only ratios)",
        "total_mass": "overall scale from dataset.total_mass",
    }.get(
        physics.get("scaled") or "", "up to one overall factor (the data fix only ratios; dataset.total_mass sets it)"
    )
    truth = "; [the truth the dataset declares]" if physics.get("true_bodies") else ""
    lines = [f"learned physics ({kind}; {scale}{truth}):"]
    bodies = list(physics["bodies"])
    trues = physics.get("true_bodies") or [None] * len(bodies)
    units = physics.get("units") or {}
    for body, true in list(zip(bodies, trues))[:MAX_BODIES]:
        lines.append(body_line(body, true, units))
    if len(bodies) > MAX_BODIES:
        lines.append(f"  … {len(bodies) - MAX_BODIES} more bodies in recovery.json")
    grav = physics.get("gravity")
    if grav:
        L = units.get("length", "m")
        text = f"  gravity {num(grav.get('g'))} {L}/s² along -{vec(grav.get('up'))}"
        if grav.get("learned_up"):
            text += " (direction learned" + (
                f", {math.degrees(grav['up_error_rad']):.2g}° from the truth)" if grav.get("up_error_rad") is not None
                else ")"
            )  # fmt: skip
        lines.append(text)
    errors = physics.get("errors") or {}
    if errors:
        lines.append("  worst relative errors: " + ", ".join(f"{k} {v:.1%}" for k, v in errors.items()))
    return lines


def validation_lines(val: Mapping[str, Any] | None, test: Mapping[str, Any] | None) -> list[str]:
    """The validation pass of the selected checkpoint (val: epoch, val_one_step_error,
    val_one_step_vs_cv, val_one_step_vs_ca, val_rollout_error) and the test rollout (test: trajectories,
    steps, one_step_vs_cv, one_step_vs_ca, rollout_vs_cv, rollout_vs_ca); ratios < 1 beat the reference."""
    lines = []
    if val and val.get("val_one_step_error") is not None:
        text = f"validation (epoch {val.get('epoch', '?')}): one step {val['val_one_step_error']:.3g}"
        ratios = [f"{num(val.get(k))}x {ref}" for k, ref in (("val_one_step_vs_cv", "CV"), ("val_one_step_vs_ca", "CA"))
                  if val.get(k) is not None]  # fmt: skip
        if ratios:
            text += " = " + ", ".join(ratios)
        if val.get("val_rollout_error") is not None:
            text += f"; rollout {val['val_rollout_error']:.3g}"
        lines.append(text)
    if test:
        parts = []
        for what in ("one_step", "rollout"):
            r = [f"{num(test.get(f'{what}_vs_{ref}'))}x {ref.upper()}" for ref in ("cv", "ca")
                 if test.get(f"{what}_vs_{ref}") is not None]  # fmt: skip
            if r:
                parts.append(f"{what.replace('_', ' ')} " + ", ".join(r))
        if parts:
            n = test.get("trajectories")
            size = f" ({n} trajector{'y' if n == 1 else 'ies'} x {test['steps']} steps)" if n else ""
            lines.append(f"test rollout{size}: " + "; ".join(parts))
    if lines:
        lines.append("  (CV: repeating the last increment, CA: constant acceleration; below 1x beats them)")
    return lines


def files_lines(run_dir: str | Path, present: Sequence[str]) -> list[str]:
    """Where the files are: the run folder, then the files of FILES that exist (`present`)."""
    names = [f for f in FILES if f in present]
    return [f"files in {run_dir}: " + ", ".join(names)] if names else [f"files in {run_dir}"]


def closing_lines(
    physics: Mapping[str, Any] | None,
    val: Mapping[str, Any] | None,
    test: Mapping[str, Any] | None,
    run_dir: str | Path,
    present: Sequence[str],
) -> list[str]:
    """The whole closing summary: a rule, what was learned, validation and test, files."""
    return [
        "── summary " + "─" * 40,
        *physics_lines(physics),
        *validation_lines(val, test),
        *files_lines(run_dir, present),
    ]


def selected_pass(history: Sequence[Mapping[str, Any]], best_epoch: int | None) -> dict | None:
    """The validation row of the selected checkpoint (`best_epoch`), else the last validation pass."""
    passes = [r for r in history if r.get("val_one_step_error") is not None]
    chosen = [r for r in passes if best_epoch is not None and r.get("epoch") == best_epoch]
    rows = chosen or passes[-1:]
    return dict(rows[0]) if rows else None


def test_figures(rows: Sequence[Mapping[str, Any]] | None) -> dict | None:
    """The test rollout's figures of the model (eval rows of `summary.json`: `model` "model", the
    references `model` constant_velocity / constant_acceleration)."""
    if not rows:
        return None
    model = next((r for r in rows if r.get("model") == "model"), None)
    if model is None:
        return None
    by = {r.get("model"): r for r in rows}
    out: dict[str, Any] = {"trajectories": model.get("rollout_trajectories"), "steps": model.get("rollout_steps")}
    for what, key in (("one_step", "one_step_rot_error_mean"), ("rollout", "geodesic_error_mean")):
        mine = model.get(key)
        for ref, name in (("cv", "constant_velocity"), ("ca", "constant_acceleration")):
            theirs = (by.get(name) or {}).get(key)
            if isinstance(mine, (int, float)) and isinstance(theirs, (int, float)) and theirs > 0:
                out[f"{what}_vs_{ref}"] = mine / theirs
    return out


# ----------------------------------------------------------------------------- reading a model
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
    J = Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=Jd.dtype) - Jd  # J = tr(J_d) I - J_d
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
    """The `physics` dict of `physics_lines` for a trained model (None: no physical parameters):
    learned figures put on the truth's scale where the data declare physics (`recovery`'s
    `scale_learned_over_true`), joints and parents of a tree, gravity, the worst relative errors."""
    import copy

    import torch

    from ..models.true_scheme import true_model

    inner = getattr(model, "inner", model)  # (a substeps wrapper)
    p = next(inner.parameters(), None)
    if p is not None and (p.device.type != "cpu" or p.dtype != torch.float64):
        inner = copy.deepcopy(inner).to(device="cpu", dtype=torch.float64)
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
    return out


def print_closing_summary(model, dataset, summary: Mapping[str, Any], history: Sequence[Mapping[str, Any]],
                          recovery: Mapping[str, Any] | None, out: Path) -> list[str]:  # fmt: skip
    """Print the closing summary of a finished `liedfl train` (also into train.log); returns its lines.
    A model whose parameters cannot be read this way gets the summary without them (a warning)."""
    from .ui import console, warning_line

    try:
        physics = gather(model, dataset, recovery)
    except (ValueError, RuntimeError, KeyError, IndexError, AttributeError, TypeError) as e:
        warning_line(f"closing summary: learned physics left out ({type(e).__name__}: {e})")
        physics = None
    best_epoch = (summary.get("validation") or {}).get("best_epoch")
    present = [f for f in FILES if (Path(out) / f).is_file()]
    lines = closing_lines(physics, selected_pass(history, best_epoch), test_figures(summary.get("eval")), out, present)
    for line in lines:
        console.print(line, highlight=False, markup=False, soft_wrap=True)
    return lines
