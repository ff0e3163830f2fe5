"""The closing summary of `liedfl train` (issue 38): what was learned, in the data's units, beside
the truth where the dataset declares it; the validation figure against constant velocity and
constant acceleration (and the test rollout's); where the files are.

`closing_lines` and its helpers are pure: plain dicts in, lines of text out (tests call them
directly). `models.learned_physics.gather` reads a trained model and its dataset into those dicts
(the one place that touches the model); `print_closing_summary` is what `run_train` calls."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeGuard

MAX_BODIES = 12  # bodies listed (a bigger tree: the rest in recovery.json); keeps a tree's summary ~25 lines
FILES = ("checkpoints/best.pt", "checkpoints/last.pt", "recovery.json", "summary.json", "eval.md", "rollout.h5",
         "train_metrics.csv", "train.log")  # fmt: skip


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
    gravity ({"g", "up", "learned_up", "up_error_rad"} or None), errors (worst relative errors by name),
    gauge ({"invisible", "parameters"}: how many parameter combinations the data cannot see, or None)."""
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
    gauge = physics.get("gauge")
    if gauge:  # per-link figures along combinations the data cannot see (the identification's gauge)
        k, n = int(gauge["invisible"]), int(gauge["parameters"])
        lines.append(
            f"  the data determine {n - k} of the {n} parameter combinations: per-link values can differ from the "
            f"truth along the other {k} without changing any prediction (docs/identification.md)"
        )
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
    notes: Sequence[str] = (),
) -> list[str]:
    """The whole closing summary: a rule, what was learned, validation and test, `notes` (`start_notes`),
    files."""
    return [
        "── summary " + "─" * 40,
        *physics_lines(physics),
        *validation_lines(val, test),
        *notes,
        *files_lines(run_dir, present),
    ]


def start_notes(history: Sequence[Mapping[str, Any]], best_epoch: int | None) -> list[str]:
    """A hint when the start (validation pass at epoch 0) stayed the selected checkpoint although epochs
    followed: they improved nothing on the validation data, and the run could have ended there."""
    later = [int(r.get("epoch") or 0) for r in history if r.get("val_one_step_error") is not None]
    later = [e for e in later if e > 0]
    if best_epoch != 0 or not later:
        return []
    return [
        f"  the start (epoch 0) stayed the best: the {max(later)} epochs after it did not improve the validation "
        "error; train.epochs=0 (the start only) or train.early_stopping.patience=N end such runs early"
    ]


def selected_pass(
    history: Sequence[Mapping[str, Any]], best_epoch: int | None, validation: Mapping[str, Any] | None = None
) -> dict | None:
    """The validation row of the selected checkpoint (`best_epoch`); where the history has no row for it
    (the start's pass, epoch 0, is not a training epoch) the figure `validation` (summary.json's section:
    metric, best) records for it; else the last validation pass."""
    passes = [r for r in history if r.get("val_one_step_error") is not None]
    chosen = [r for r in passes if best_epoch is not None and r.get("epoch") == best_epoch]
    if not chosen and best_epoch is not None and validation and validation.get("best") is not None:
        return {"epoch": best_epoch, str(validation.get("metric") or "val_one_step_error"): validation["best"]}
    rows = chosen or passes[-1:]
    return dict(rows[0]) if rows else None


def test_figures(rows: Sequence[Mapping[str, Any]] | None) -> dict | None:
    """The test rollout's figures of the model (eval rows of `summary.json`: `model` "model", the
    references `model` constant_velocity / constant_acceleration), each ratio over the same samples on
    both sides: constant velocity's from the row's own columns (`one_step_vs_cv`, `rollout_vs_cv`: over
    the model's valid samples); constant acceleration's from the two rows' errors, only where those cover
    the same samples (no Newton failure) and, for the rollout, where the reference predicts a sample at
    all (it starts from three true poses: a rollout of 2 steps or fewer has no sample of its own)."""
    if not rows:
        return None
    model = next((r for r in rows if r.get("model") == "model"), None)
    if model is None:
        return None
    ca = next((r for r in rows if r.get("model") == "constant_acceleration"), {})
    steps = model.get("rollout_steps")
    out: dict[str, Any] = {"trajectories": model.get("rollout_trajectories"), "steps": steps}
    same_samples = not model.get("newton_failures")
    for what, key in (("one_step", "one_step_rot_error_mean"), ("rollout", "geodesic_error_mean")):
        cv = model.get(f"{what}_vs_cv")
        if isinstance(cv, (int, float)) and math.isfinite(cv):
            out[f"{what}_vs_cv"] = cv
        mine, theirs = model.get(key), ca.get(key)
        predicts = what == "one_step" or not isinstance(steps, int) or steps >= 3
        if same_samples and predicts and _positive(mine) and _positive(theirs):
            out[f"{what}_vs_ca"] = mine / theirs
    return out


def _positive(x: Any) -> TypeGuard[float]:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def print_closing_summary(physics: Mapping[str, Any] | None, summary: Mapping[str, Any],
                          history: Sequence[Mapping[str, Any]], out: Path) -> list[str]:  # fmt: skip
    """Print the closing summary of a finished `liedfl train` (also into train.log); returns its lines.
    physics: what `models.learned_physics.gather` read from the model (None: left out)."""
    from .ui import console

    best_epoch = (summary.get("validation") or {}).get("best_epoch")
    present = [f for f in FILES if (Path(out) / f).is_file()]
    val, test = selected_pass(history, best_epoch, summary.get("validation")), test_figures(summary.get("eval"))
    lines = closing_lines(physics, val, test, out, present, start_notes(history, best_epoch))
    for line in lines:
        console.print(line, highlight=False, markup=False, soft_wrap=True)
    return lines
