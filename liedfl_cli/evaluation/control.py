"""Exp 5 evaluation: the learned control torque along the observed trajectory vs the true one.

Listed as SCENE_EVALS["pd_control"] in `liedfl_cli.evaluation` and run by `liedfl train`,
`liedfl rollout` and `liedfl eval` after the standard evaluation. For every trajectory of each split, at k = 0..N-1:

  learned   tau_theta(R_k, w~_k): the rotational part of the sum of the model's forces, with
            w~_k = vee(W_k - W_k^T)/(2h) from the data increment W_k = R_k^T R_{k+1} (what the
            model sees: positions only);
  true      tau(R_k, w_k) from `extras/tau_ext` (the simulator's non-conservative torque at the
            true angular velocity; equal to the PD torque `extras/tau_control` when D = 0, the
            Exp 5 setting);
  law@w~    the true PD law evaluated at (R_k, w~_k) (the true-parameter scheme's force), which
            separates identification error from the O(h) error of the velocity estimate.

Relative error per step ||tau_theta - tau|| / ||tau||; summary mean and max over steps and the
aggregate ||tau_theta - tau||_2 / ||tau||_2 over all steps. Files (computed here, written by the
command: `commands.outputs.write_outputs`), next to the rollout file:
control_eval.json, control_eval.md, plots/torque.png (torque components learned vs true, relative
error, and the rollout's body axis R e3 on the sphere; from the rollout file when present).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ..display.plots import COLORS, display_names, draw_unit_sphere, plt
from ..files.io_utils import markdown_table
from ..files.rollout_file import FILE_NAME, load_rollout
from ..lie import Pose
from ..mechanics.kinetic import velocity_estimate
from ..models.base import tensor_placement
from .outputs import EvalOutputs, SceneEvalOptions

if TYPE_CHECKING:
    from matplotlib.figure import Figure


@torch.no_grad()
def force_torques(model, traj: Pose, h: float) -> np.ndarray:
    """Rotational part of sum_F F(g_k, xi~_k) along trajectories (T, N+1, ...) -> (T, N, B, 3), computed
    on the model's device and in its dtype, returned in float64."""
    G = model.G
    traj = traj.to(**tensor_placement(model))
    g = traj.index((slice(None), slice(0, -1)))
    inc = G.increment(g, traj.index((slice(None), slice(1, None))))
    xi = velocity_estimate(G, inc, h)
    total = torch.zeros_like(xi)
    for f in model.force_terms():
        total = total + f(g, xi)
    w, _ = G.split(total)
    return w.to(device="cpu", dtype=torch.float64).numpy()


def torque_errors(learned: np.ndarray, true: np.ndarray) -> dict:
    """Relative errors over (T, N, B, 3) arrays: per-step curve (mean over trajectories) and scalars."""
    T, N = learned.shape[:2]
    d = (learned - true).reshape(T, N, -1)
    t = true.reshape(T, N, -1)
    per_step = np.linalg.norm(d, axis=-1) / np.maximum(np.linalg.norm(t, axis=-1), 1e-300)
    return {
        "curve": per_step.mean(0),
        "rel_error_mean": float(per_step.mean()),
        "rel_error_max": float(per_step.max()),
        "rel_error_aggregate": float(np.linalg.norm(d) / max(np.linalg.norm(t), 1e-300)),
    }


def evaluate_control(opts: SceneEvalOptions, model, dataset, run_dir, rollout_path=None) -> EvalOutputs | None:
    """Exp 5 torque recovery, computed, neither written nor printed: the summary, files and console
    lines (for a model without forces: an empty summary and the line saying the evaluation is skipped).

    rollout_path: the rollout file drawn in the plot (default `<run_dir>/rollout.h5`; the plot goes
    without it when it does not exist); the files go next to it."""
    from ..models.true_scheme import true_model

    path = Path(rollout_path) if rollout_path is not None else Path(run_dir) / FILE_NAME
    out_dir = path.parent
    if not model.force_terms():
        skipped = EvalOutputs({}, out_dir)
        skipped.say("[yellow]control eval skipped:[/] the model has no force components")
        return skipped
    h = dataset.h
    ref = true_model(dataset)
    rows, curves = [], {}
    for split in ("train", "test"):
        idx = np.asarray(dataset.split[split])
        if idx.size == 0:
            continue
        traj = dataset.pose(idx)
        learned = force_torques(model, traj, h)
        N = learned.shape[1]
        true = np.asarray(dataset.extras["tau_ext"])[idx][:, :N]
        err = torque_errors(learned, true)
        row = {
            "split": split,
            "trajectories": int(idx.size),
            "steps": int(N),
            "rel_error_mean": err["rel_error_mean"],
            "rel_error_max": err["rel_error_max"],
            "rel_error_aggregate": err["rel_error_aggregate"],
        }
        if ref is not None and ref.force_terms():
            law = force_torques(ref, traj, h)
            e2 = torque_errors(learned, law)
            row.update(
                {
                    "vs_law_at_w_tilde_mean": e2["rel_error_mean"],
                    "vs_law_at_w_tilde_max": e2["rel_error_max"],
                    "law_at_w_tilde_vs_true_mean": torque_errors(law, true)["rel_error_mean"],
                }
            )
        rows.append(row)
        curves[split] = {"learned": learned[0], "true": true[0], "rel_error": err["curve"]}
    if not rows:
        return None
    summary = {"rows": rows, "reference": "extras/tau_ext (true non-conservative torque at the true angular velocity)"}
    out = EvalOutputs(summary, out_dir)
    out.add("control_eval.json", summary)
    out.add("control_eval.md", control_markdown(rows))
    for r in rows:
        out.say(
            f"control recovery ({r['split']}): relative torque error mean {r['rel_error_mean']:.3e}, "
            f"max {r['rel_error_max']:.3e}, aggregate {r['rel_error_aggregate']:.3e}"
        )
    if opts.plots:
        key = "test" if "test" in curves else "train"
        out.add("plots/torque.png", plot_torque(curves[key], h, _rollout_R(path, dataset), key))
    return out


def control_markdown(rows: list[dict]) -> str:
    """The content of control_eval.md: the rows of `evaluate_control` as a table."""
    md = (
        "# Control recovery (learned torque along the observed trajectories)\n\n"
        "Relative error ||tau_theta(R_k, w~_k) - tau(R_k, w_k)|| / ||tau(R_k, w_k)|| per step (mean, max), "
        "and aggregated over all steps; `vs_law_at_w_tilde`: against the true PD law evaluated at the "
        "same velocity estimate w~_k.\n\n"
    )
    return md + markdown_table(rows, list(rows[0]))


def _rollout_R(path: Path, dataset) -> dict:
    """{name: R (S+1, B, 3, 3)} of the first rolled-out trajectory (truth included, over the steps it
    has, and the constant-velocity rollout from its true first pair), from a rollout file ({} when
    there is none)."""
    if not path.is_file():
        return {}
    from ..solvers.one_step import constant_velocity_rollout

    rf = load_rollout(path, dataset)
    i = int(rf.traj_index[0])
    out = {name: e.R[0] for name, e in rf.models.items()}
    truth = dataset.pose([i])
    first = (truth.index((slice(None), 0)), truth.index((slice(None), 1)))
    out["constant_velocity"] = constant_velocity_rollout(dataset.group, *first, rf.steps).R[0].numpy()
    out["truth"] = dataset.R[i, : rf.steps + 1]
    out["_index"] = i
    return out


def plot_torque(curve: dict, h: float, rollouts: dict, split: str) -> Figure:
    """Torque components learned vs true, relative error, rollout on the sphere and its rotation error."""
    learned, true = curve["learned"], curve["true"]  # (N, B, 3)
    N = learned.shape[0]
    t = np.arange(N) * h
    fig = plt.figure(figsize=(15, 8))
    for j in range(3):
        ax = fig.add_subplot(2, 3, j + 1)
        ax.plot(t, true[:, 0, j], "--", color="black", label="true")
        ax.plot(t, learned[:, 0, j], color="tab:blue", label="learned")
        ax.set_title(f"torque component {j + 1} ({split} trajectory)")
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"tau_{j + 1} [N m]")
        ax.grid(alpha=0.3)
        if j == 0:
            ax.legend()
    ax = fig.add_subplot(2, 3, 4)
    ax.semilogy(t, np.maximum(curve["rel_error"], 1e-17), color="tab:blue")
    ax.set_title("relative torque error ||tau_theta - tau|| / ||tau||")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("relative torque error [dimensionless]")
    ax.grid(alpha=0.3)
    rollouts = dict(rollouts)
    index = rollouts.pop("_index", None)
    labels = {**display_names([k for k in rollouts if k != "truth"]), "truth": "truth"}
    if rollouts:
        ax3 = fig.add_subplot(2, 3, 5, projection="3d")
        draw_unit_sphere(ax3)
        for name, R in rollouts.items():
            if name == "constant_velocity":
                continue  # an error reference, drawn in the error panel only
            ax3.plot(
                *R[:, 0, :, 2].T,
                "-" if name == "truth" else "--",
                color=COLORS.get(name),
                linewidth=1.0,
                label=labels.get(name, name),
            )
        ax3.legend(loc="upper left", fontsize=8)
        ax3.set_title(f"rollout: body axis R e3 (trajectory {index})")
        ax = fig.add_subplot(2, 3, 6)
        truth = rollouts["truth"]
        for name, R in rollouts.items():
            if name == "truth":
                continue
            S = min(len(R), len(truth))
            err = np.linalg.norm(R[:S] - truth[:S], axis=(-2, -1)).mean(-1) / np.sqrt(3.0)
            ax.semilogy(
                np.arange(S) * h,
                np.maximum(err, 1e-17),
                "--" if name == "constant_velocity" else "-",
                color=COLORS.get(name),
                label=labels.get(name, name),
            )
        ax.set_title("rollout relative rotation error ||R^ - R||_F / ||R||_F")
        ax.set_xlabel("time [s]")
        ax.set_ylabel("relative rotation error [dimensionless]")
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    return fig


__all__ = ["force_torques", "torque_errors", "evaluate_control", "control_markdown", "plot_torque"]
