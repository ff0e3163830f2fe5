"""`liedfl export run=<run dir>|latest format=mjcf out=model.xml [dataset.total_mass=M]`: the identified
articulated model of a run as a MuJoCo MJCF file (docs/export.md; the writer: `files/mjcf.py`).

What is written: the run's kinematic tree (the joints and axes it trained with), each body's learned
mass m_b, centre of mass rho_b and inertia J_b = tr(J_d) I - J_d about the centre of mass (from the
discrete inertia J_d = tr(J)/2 I - J), the learned joint damping per degree of freedom, and the
gravity of a `uniform_gravity` potential (g u, acting along -u; none otherwise). The learned model
has one arbitrary overall scale: masses, inertias and damping are scaled so that the total mass is
`dataset.total_mass` (the command line's, else the run's config), else 1 kg; the XML's comment and
the console line say which. Body names: the dataset's. Time step h/50 (`timestep=` to change it),
MuJoCo's RK4, contacts disabled. Damping: the model's per-DoF joint damping (`multibody()`), else the
diagonal of a joint-space Rayleigh matrix D (`physical_parameters()["D"]`, projected on each joint's
axes), with a warning saying which share of D the diagonal drops. Gravity: exactly -g e3 when the
learned "up" direction is within 1e-3 rad of e3, else the learned direction. The file is checked by
compiling it with MuJoCo when mujoco is installed, and written to a temporary file then renamed.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from ..config.typed import RunConfig
from ..display.ui import console, warning_line
from ..errors import ConfigError
from ..files.mjcf import MjcfSpec, ball_damping_dropped, load_model, mjcf_text, unique_names, write_mjcf

FORMATS = ("mjcf",)
SUBSTEPS = 50  # MuJoCo steps per sample interval h (RK4): the default timestep h/50
GRAVITY_SNAP = 1e-3  # rad: a learned gravity direction this close to -e3 is written as -e3
NOT_ARTICULATED = "export format=mjcf needs an articulated model (model.kinetic=articulated)"


def _positive_mass(value, where: str) -> float | None:
    if value is None:
        return None
    try:
        m = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"dataset.total_mass={value!r}{where}: a positive number (kg) or null") from None
    if isinstance(value, bool) or not (m > 0 and math.isfinite(m)):
        raise ConfigError(f"dataset.total_mass={value!r}{where}: a positive number (kg) or null")
    return m


def total_mass_choice(cfg: DictConfig, run_cfg: RunConfig) -> tuple[float, str]:
    """(total mass in kg, where it comes from): the command line's dataset.total_mass, else the run's
    config's, else 1 kg."""
    given = OmegaConf.select(cfg, "dataset.total_mass", default=None)
    m = _positive_mass(given, "")
    if m is not None:
        return m, "dataset.total_mass from the command line"
    saved = run_cfg.dataset.total_mass if run_cfg.dataset is not None else None
    m = _positive_mass(saved, " in the run's config")
    if m is not None:
        return m, "dataset.total_mass from the run's config"
    return 1.0, "dataset.total_mass not set: the learned scale is arbitrary"


def _numpy(t) -> np.ndarray:
    return t.detach().cpu().double().numpy()


def rayleigh_dof_damping(tree, D: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Per-DoF damping (n,) (root first, `lie.joints.joint_slices`) from a joint-space Rayleigh matrix D
    (dim, dim) in the layout of `tree.group`'s tangent (a free root's 6 entries (w, v), then 3 per body):
    the diagonal of S^T D S with S each joint's axes (ball: I_3, hinge: a, universal: [a1, a2] at
    R_rel = I, weld: none; a free root's 6 DoF are not exported: 0). Returns (damping, the share of
    D's off-diagonal terms that a per-DoF damping drops: |offdiag(S^T D S)|_F / |S^T D S|_F, the share
    of |D|_F on a free root's DoF, which MJCF joint damping cannot carry)."""
    from ..lie.joints import joint_slices

    D = np.asarray(D, dtype=np.float64)
    dim = tree.group.dim
    if D.shape != (dim, dim):
        raise ConfigError(f"joint-space damping D has shape {D.shape}, expected ({dim}, {dim}) for this tree")
    rows = tree.group.body_slices()
    axes = np.asarray(tree.axes_array(), dtype=np.float64)
    cols = joint_slices(tree)
    S = np.zeros((dim, tree.n_dof))  # each joint's motion basis at R_rel = I (universal: [a1, a2])
    for b, kind in enumerate(tree.joint_kinds):
        r, c = rows[b].start, cols[b].start
        if kind in ("free", "ball"):
            n = 6 if kind == "free" else 3
            S[r : r + n, c : c + n] = np.eye(n)
        elif kind == "hinge":
            S[r : r + 3, c] = axes[b, 0]
        elif kind == "universal":
            S[r : r + 3, c] = axes[b, 0]
            S[r : r + 3, c + 1] = axes[b, 1]
    Dr = S.T @ D @ S
    total = float(np.linalg.norm(Dr))
    off = 0.0 if total == 0 else float(np.linalg.norm(Dr - np.diag(np.diag(Dr)))) / total
    d = np.diag(Dr).copy()
    root_share = 0.0
    if tree.free_root:
        d[cols[0]] = 0.0
        norm_D = float(np.linalg.norm(D))
        root_share = 0.0 if norm_D == 0 else float(np.linalg.norm(D[rows[0], :])) / norm_D
    return d, off, root_share


def gravity_vector(gravity: np.ndarray) -> tuple[np.ndarray, str]:
    """(the MJCF gravity vector (3,), a phrase for the comment): a field within GRAVITY_SNAP rad of -e3
    written as exactly (0, 0, -g), else the learned direction as it is."""
    g = float(np.linalg.norm(gravity))
    if g == 0:
        return np.zeros(3), "none"
    angle = float(np.arccos(np.clip(-float(gravity[2]) / g, -1.0, 1.0)))
    if angle < GRAVITY_SNAP:
        return np.array([0.0, 0.0, -g]), f"{g:.6g} along -e3 (learned direction {angle:.2g} rad from -e3)"
    return np.asarray(gravity, dtype=np.float64), (
        f"{g:.6g} along the learned direction ({', '.join(f'{x:.6g}' for x in gravity / g)}), {angle:.4g} rad from -e3"
    )


def model_spec(model, names, total_mass: float, timestep: float | None = None) -> tuple[MjcfSpec, list[str], float]:
    """The MJCF spec of a trained `ArticulatedLieDFLNN` with masses, inertias and damping scaled to
    `total_mass` (kg); returns (spec, warnings: what the file cannot carry, scale factor).

    From `model.multibody()`: mass (B,), COM (B, 3), inertia about the COM (B, 3, 3) = tr(J_d) I - J_d,
    per-DoF damping (n,), gravity (3,); when the model damps through a joint-space Rayleigh force
    instead, the diagonal of its D (`physical_parameters()["D"]`, `rayleigh_dof_damping`)."""
    from ..lie.joints import joint_slices

    mb = model.multibody()
    if mb is None:
        raise ConfigError(NOT_ARTICULATED)
    tree = mb["tree"]
    B = tree.n_bodies
    mass, rho, J = _numpy(mb["mass"]), _numpy(mb["com"]), _numpy(mb["inertia"])
    scale = total_mass / float(mass.sum())
    damping = _numpy(mb["dof_damping"])
    names = unique_names(names, B)
    notes: list[str] = []
    unexported = list(mb["unexported"])
    D = model.physical_parameters().get("D")
    if D is not None and not np.any(damping):
        damping, off, root_share = rayleigh_dof_damping(tree, _numpy(D))
        unexported = [u for u in unexported if "'rayleigh'" not in u]
        if off > 1e-3:
            notes.append(
                f"the joint damping matrix D is not diagonal: wrote its diagonal per DoF "
                f"({100 * off:.1f}% of D, the off-diagonal terms, dropped)"
            )
        if root_share > 1e-3:
            notes.append(f"the free root's damping ({100 * root_share:.1f}% of D) has no MJCF form: not exported")
    per_body = []
    for b, (kind, cols) in enumerate(zip(tree.joint_kinds, joint_slices(tree))):
        values = [scale * float(x) for x in damping[cols]]
        if kind == "ball":
            dropped = ball_damping_dropped(values)
            if dropped > 1e-3:
                notes.append(
                    f"body {names[b]!r}: MuJoCo has one damping per ball joint: wrote the mean "
                    f"{float(np.mean(values)):.4g} of {', '.join(f'{x:.4g}' for x in values)} "
                    f"({100 * dropped:.1f}% of the damping dropped)"
                )
        per_body.append(values)
    gravity, _ = gravity_vector(_numpy(mb["gravity"]))
    notes += [f"{part} has no MJCF form: not exported" for part in unexported]
    spec = MjcfSpec(
        names=names,
        parents=list(tree.parents),
        offsets=np.asarray(tree.offsets, dtype=np.float64),
        joints=list(tree.joint_kinds),
        axes=np.asarray(tree.axes_array(), dtype=np.float64),
        mass=scale * mass,
        com=rho,
        inertia=scale * J,
        dof_damping=per_body,
        gravity=gravity,
        timestep=float(timestep) if timestep is not None else float(model.h) / SUBSTEPS,
    )
    return spec, notes, scale


def length_unit(dataset) -> str:
    """The data's length unit: "m" unless params["length_unit_m"] says another."""
    unit = (getattr(dataset, "params", None) or {}).get("length_unit_m")
    if unit is None or abs(float(unit) - 1.0) < 1e-9:
        return "m"
    if abs(float(unit) - 1e-3) < 1e-12:
        return "mm"
    return f"({float(unit):.6g} m)"


def _out_path(value) -> Path:
    if value in (None, "", "???"):
        raise ConfigError("out=<file> is required (e.g. out=model.xml)")
    out = Path(str(value))
    if out.is_dir():
        raise ConfigError(f"out={out}: is a directory (give a file name, e.g. {out / 'model.xml'})")
    if not out.parent.is_dir():
        raise ConfigError(f"out={out}: folder {out.parent} does not exist")
    return out


def _timestep(value) -> float | None:
    if value is None:
        return None
    try:
        dt = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"timestep={value!r}: a positive number (s) or null (h/{SUBSTEPS})") from None
    if isinstance(value, bool) or not (dt > 0 and math.isfinite(dt)):
        raise ConfigError(f"timestep={value!r}: a positive number (s) or null (h/{SUBSTEPS})")
    return dt


def run_export(cfg: DictConfig) -> Path:
    """`liedfl export`: load the run's checkpoint, write its articulated model as MJCF to `out`
    (module docstring). Returns the path written."""
    from ..config.factory import configure_runtime
    from ..config.runs import load_run_checkpoint
    from ..config.typed import runtime_options
    from ..files.checkpoint import describe_checkpoint
    from ..files.dataset_identity import accept_option
    from ..models.articulated.model import joint_summary

    if OmegaConf.is_missing(cfg, "run") or cfg.get("run") in (None, ""):
        raise ConfigError("run=<run dir> is required (a directory written by `liedfl train`)")
    fmt = cfg.get("format")
    if fmt not in FORMATS:
        raise ConfigError(f"format={fmt!r}: choose one of {', '.join(FORMATS)}")
    out = _out_path(None if OmegaConf.is_missing(cfg, "out") else cfg.get("out"))
    timestep = _timestep(cfg.get("timestep"))
    _positive_mass(OmegaConf.select(cfg, "dataset.total_mass", default=None), "")  # before loading the run
    configure_runtime(runtime_options(cfg.get("runtime")))
    loaded = load_run_checkpoint(
        str(cfg.run),
        OmegaConf.select(cfg, "paths.data_dir", default=None),
        str(cfg.get("checkpoint") or "best"),
        accept_option(cfg.get("accept_changed_dataset")),
    )
    model, dataset, run_dir, used = loaded.model, loaded.dataset, loaded.run_dir, loaded.checkpoint
    if model.multibody() is None:
        raise ConfigError(NOT_ARTICULATED)
    console.print(describe_checkpoint(used), highlight=False)
    total_mass, source = total_mass_choice(cfg, loaded.config)
    spec, notes, scale = model_spec(model, list(dataset.body_names or []), total_mass, timestep)
    checkpoint = describe_checkpoint(used).removeprefix("checkpoint: ")
    h = float(model.h)
    unit = length_unit(dataset)
    _, gravity_phrase = gravity_vector(_numpy(model.multibody()["gravity"]))
    spec.comment = "\n".join(
        [
            f"liedfl export of run {Path(run_dir).resolve()} ({checkpoint})",
            f"joints: {joint_summary(model.tree)}",
            f"total mass {total_mass:g} kg ({source}): learned masses, inertias and damping x {scale:.6g}",
            f"units: lengths in {unit} (the data's), mass kg, inertia kg {unit}^2, damping kg {unit}^2/s, "
            f"gravity {unit}/s^2",
            f"gravity: {gravity_phrase}",
            f"timestep h/{h / spec.timestep:.4g} = {spec.timestep!r} s (h = {h!r} s, the data's sample interval); "
            "MuJoCo's RK4; contacts disabled",
            "inertial: mass, centre of mass (body frame, from the joint), inertia about it (body frame)",
            *notes,
        ]
    )
    text = mjcf_text(spec)
    try:
        load_model(text)  # MuJoCo compiles it (a check; skipped without mujoco)
    except ConfigError as e:
        if "mujoco package" not in str(e):
            raise
        notes.append("mujoco is not installed: the file was not compiled as a check")
    for note in notes:
        warning_line(note)
    write_mjcf(out, spec)
    g = np.linalg.norm(spec.gravity)
    console.print(
        f"wrote {out}: MJCF of {model.tree.n_bodies} bodies ({joint_summary(model.tree)}), total mass "
        f"{total_mass:g} kg ({source}; learned values x {scale:.4g}), gravity "
        f"{'none' if g == 0 else f'{g:.4g} {unit}/s^2'}, timestep {spec.timestep:.4g} s",
        highlight=False,
    )
    return out


__all__ = [
    "FORMATS",
    "NOT_ARTICULATED",
    "SUBSTEPS",
    "gravity_vector",
    "length_unit",
    "model_spec",
    "rayleigh_dof_damping",
    "run_export",
    "total_mass_choice",
]
