"""Exp 4 evaluation: the paper's mocap table (reproduction errors vs the ground-truth discrepancy).

Listed as SCENE_EVALS["cmu_cartwheel"] in `liedfl_cli.evaluation` and run by `liedfl train`,
`liedfl rollout` and `liedfl eval` after the standard evaluation. From a rollout file (group `model`,
one rollout per test sequence started from its true first pair; read and checked against the dataset
by `rollout_file.load_rollout`) and the dataset:

  per sequence   mean over the rollout of: root rotation geodesic error |log(R^_0^T R_0)| (rad), the
                 joint rotation geodesic error averaged over the MOVING joints (rad; the joints that
                 rotate somewhere in the data, `data.mocap.moving_joints`: 18 of the 22 in the CMU
                 cartwheels, whose LHipJoint, RHipJoint, LeftShoulder and RightShoulder channels are
                 constant; a constant joint has zero error and discrepancy, so averaging over all 22
                 scales both by 18/22), the same over all joints (`joint_rot_all`), and the root position
                 error |p^_0 - p_0|, in CMU ASF units (the file unit of the CMU BVH files, 1/0.45 inch
                 = 0.0564 m; the paper's unit) and in metres (params.length_unit_m). The mean runs over
                 the predicted samples k = 2..S; samples 0 and 1 are the given initial pair (zero error).
  discrepancy    the same three numbers between the two ground-truth recordings, frame by frame over
                 their common (cropped) length, root positions measured from each recording's start
                 (`data.mocap.recording_discrepancy`, the paper's reference scale).
  span           errors where ground truth exists: samples 0..min(S, N) of a rollout of S steps over a
                 dataset of N steps; the Newton and non-finite diagnostics cover the whole rollout.
  paper          the numbers of the paper's table next to ours, and a verdict line saying whether
                 every one of our errors is below the corresponding discrepancy (ours and the paper's).
                 The verdict is given only when the rollout covers the whole recording (every recorded
                 step); a shorter rollout (a smoke run, `steps=` below the recording) says so instead.
  Newton         the rollout's non-converged implicit steps (`model/converged` of the rollout file).
  constant vel.  the same three errors of the constant-velocity rollout g_{k+1} = g_k exp(log(g_{k-1}^-1 g_k))
                 from each sequence's true first pair over the same samples (rows "Constant velocity,
                 sequence i"; no verdict for them): a model that does not beat it has learned nothing.
  diagnostics    per sequence and metric, the time until the per-timestep error first exceeds the
                 per-timestep discrepancy; and teacher-forced one-step errors (g_{k+1} from the true
                 (g_{k-1}, g_k); the rollout file's `model/one_step` predictions, else one batched
                 two-step rollout here) next to constant velocity's, which separate the model's local
                 error from the compounding of the rollout.

Files (computed here, written by the command: `commands.outputs.write_outputs`), next to the rollout
file: mocap_eval.csv, mocap_eval.md, mocap_eval.json and, with eval.plots,
plots/mocap_errors.png
(per-timestep errors, discrepancy in grey, constant velocity dashed), plots/mocap_skeleton_seq<i>.png
(skeletons at uniform intervals by forward kinematics from the BVH offsets in params.skeleton: truth
green/red, prediction blue), plots/mocap_root_trajectory.png (root path and frames in 3-D) and
plots/mocap_joint_axes_seq<i>.png (bone directions of selected joints on the unit sphere).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from rich.markup import escape
from rich.table import Table

from ..data.mocap import ASF_UNIT_M, mocap_errors, moving_joints, recording_discrepancy, skeleton_points
from ..display.plots import draw_unit_sphere, plt
from ..files.io_utils import fmt, markdown_table
from ..files.rollout_file import FILE_NAME, RolloutEntry, load_rollout
from ..lie import Pose
from ..models.base import Model, tensor_placement
from .outputs import EvalOutputs, SceneEvalOptions

if TYPE_CHECKING:
    from matplotlib.figure import Figure

PAPER: dict[str, Any] = {
    "sequences": [
        {"root_rot": 0.193, "joint_rot": 0.186, "root_pos": 0.887},
        {"root_rot": 0.188, "joint_rot": 0.233, "root_pos": 1.409},
    ],
    "discrepancy": {"root_rot": 0.373, "joint_rot": 0.416, "root_pos": 6.624},
}
"""The paper's Exp 4 table (root position in CMU ASF units, the unit of the BVH files)."""

METRICS = ("root_rot", "joint_rot", "root_pos")
LABELS = {
    "root_rot": "root rot. [rad]",
    "joint_rot": "mean joint rot. (moving joints) [rad]",
    "root_pos": "root pos. [ASF units]",
}
SEQ_COLORS = ("tab:green", "tab:red")
CV_COLORS = ("#0b4d1a", "#7a0000")
"""Constant velocity of sequence 1, 2: darker than SEQ_COLORS and dashed, visible on top of a model curve."""
PRED_COLOR = "tab:blue"
AXIS_JOINTS = ("LeftUpLeg", "RightUpLeg", "LeftArm", "RightArm", "LeftLeg", "RightLeg")
"""Joints whose bone direction (R_j times the unit offset of its child) is drawn on the sphere."""


# --------------------------------------------------------------------------- helpers
def _asf_per_unit(dataset) -> float:
    """CMU ASF units per stored length unit (1.0 for length_scale 1)."""
    return float(dataset.params.get("length_unit_m", ASF_UNIT_M)) / ASF_UNIT_M


def recording_steps(dataset) -> int:
    """Steps of the whole (common) recording: the shortest source's frames after the import's
    skip/subsample minus one (params["sources"]), else the dataset's own length. A dataset cropped
    shorter (budget=smoke, a smaller dataset.steps) does not cover the recording."""
    avail = [s.get("frames_available") for s in dataset.params.get("sources") or []]
    avail = [int(a) for a in avail if a is not None]
    return min(avail) - 1 if avail else int(dataset.n_steps)


def _sequence_name(dataset, i: int) -> str:
    src = dataset.params.get("sources") or []
    return Path(src[i]["file"]).stem if i < len(src) else f"trajectory {i}"


# --------------------------------------------------------------------------- numbers
def sequence_errors(pred_R, pred_p, true_R, true_p, joints=None) -> dict:
    """Per-sequence errors over the predicted samples k >= 2: scalars and per-step curves (numpy).
    joints: the joints of the mean joint error (None: all); `joint_rot_all` is over all joints."""
    e = mocap_errors(
        Pose(torch.as_tensor(pred_R), torch.as_tensor(pred_p)),
        Pose(torch.as_tensor(true_R), torch.as_tensor(true_p)),
        joints=joints,
    )
    out = {}
    for k in (*METRICS, "joint_rot_all"):
        curve = e[k + "_t"].numpy()  # (T, S+1)
        out[k + "_t"] = curve
        out[k] = curve[:, 2:].mean(-1) if curve.shape[-1] > 2 else curve.mean(-1)
    out["joint_rot_per_joint"] = e["joint_rot_per_joint"].numpy()
    return out


def discrepancy(dataset, joints="moving") -> dict | None:
    """Ground-truth discrepancy between recordings 0 and 1 (scalars and curves), None with < 2.
    joints: as in `data.mocap.recording_discrepancy` (default: the moving joints)."""
    if dataset.n_trajectories < 2:
        return None
    if isinstance(joints, str) and joints == "moving":
        joints = moving_joints(dataset)
    d: dict[str, Any] = recording_discrepancy(dataset, joints=joints)  # scalars, then the curves
    e = mocap_errors(dataset.pose([0]).index(0), dataset.pose([1]).index(0), relative_position=True, joints=joints)
    d.update({k + "_t": e[k + "_t"].numpy() for k in (*METRICS, "joint_rot_all")})
    return d


def below_until(err: dict, disc: dict | None, h: float) -> list[dict]:
    """Per rolled-out sequence and metric: the time (s) of the last predicted sample before the
    per-timestep error first exceeds the per-timestep discrepancy (None: never exceeds it)."""
    out = []
    for n in range(err["root_rot"].shape[0]):
        row: dict[str, float | None] = {}
        for k in METRICS:
            if disc is None:
                row[k] = None
                continue
            e = err[k + "_t"][n]
            S = min(len(e), len(disc[k + "_t"]))
            over = np.nonzero(~(e[2:S] <= disc[k + "_t"][2:S]))[0]
            row[k] = None if not len(over) else float((over[0] + 1) * h)
        out.append(row)
    return out


@torch.no_grad()
def one_step_errors(model, truth_R, truth_p, solver, joints=None, stored=None, group=None) -> dict | None:
    """Teacher-forced one-step predictions: g_{k+1} from the true (g_{k-1}, g_k) for every k, batched.

    Separates the model's local error from the compounding of the rollout. Returns per-sequence means
    of the three errors for the model and for the references (`ONE_STEP_REFERENCES`): constant velocity
    g_k exp(log(g_{k-1}^-1 g_k)) (the last increment repeated), constant acceleration R_k exp(2 w_k - w_{k-1}),
    p_k + 2 dp_k - dp_{k-1}, and constant velocity with Euclidean positions (`solvers.one_step`), and the Newton
    convergence count. `stored`: the rollout file's `model/one_step` predictions (`rollout_file.OneStep`)
    of the same samples, used when present; otherwise the model predicts them here
    (`solvers.one_step.one_step_predictions`). "model" is None (and the counts 0) for a model without
    a `rollout(g0, g1, steps, solver)` method when nothing is stored. `group`: the data's group
    (default the model's). None for fewer than 3 poses.
    """
    from ..solvers.one_step import (
        constant_acceleration_one_step,
        constant_velocity_one_step,
        euclidean_velocity_one_step,
        one_step_predictions,
    )

    truth = Pose(torch.as_tensor(truth_R), torch.as_tensor(truth_p))
    T, K = truth.R.shape[0], truth.R.shape[1] - 2
    G = group if group is not None else (model.G if isinstance(model, Model) else None)
    if K < 1 or G is None:
        return None
    true = truth.index((slice(None), slice(2, None)))
    pred, conv = None, None
    if stored is not None and stored.R.shape[:2] == (T, K):
        pred, conv = stored.pose, torch.from_numpy(stored.converged)
    elif isinstance(model, Model):
        was_training = model.training
        model.eval()
        try:
            pred, conv = one_step_predictions(model, truth.to(**tensor_placement(model)), solver)
        finally:
            model.train(was_training)
        pred = pred.to(device="cpu", dtype=torch.float64)
    guesses = {
        "const_velocity": constant_velocity_one_step(G, truth),
        "const_acceleration": constant_acceleration_one_step(G, truth),
        "euclid_velocity": euclidean_velocity_one_step(G, truth),
    }
    refs = {}
    for who, guess in guesses.items():
        e = mocap_errors(guess, true, joints=joints)
        refs[who] = {k: e[k].numpy() for k in METRICS}
    em = mocap_errors(pred, true, joints=joints) if pred is not None else None
    return {
        "model": None if em is None else {k: em[k].numpy() for k in METRICS},
        **refs,
        "converged": 0 if conv is None else int(conv.sum()),
        "solves": 0 if conv is None else int(conv.numel()),
        "from_rollout_file": stored is not None and pred is not None and stored.R.shape[:2] == (T, K),
    }


def constant_velocity_errors(dataset, tR, tp, joints=None) -> dict:
    """`sequence_errors` of the constant-velocity rollout (`solvers.one_step.constant_velocity_rollout`)
    from each sequence's true first pair over the same samples as the truth tR (T, S+1, B, 3, 3)."""
    from ..solvers.one_step import constant_velocity_rollout

    truth = Pose(torch.as_tensor(tR), torch.as_tensor(tp))
    S = truth.R.shape[1] - 1
    cv = constant_velocity_rollout(dataset.group, truth.index((slice(None), 0)), truth.index((slice(None), 1)), S)
    return sequence_errors(cv.R.numpy(), cv.p.numpy(), tR, tp, joints=joints)


def constant_acceleration_errors(dataset, tR, tp, joints=None) -> dict:
    """`sequence_errors` of the constant-acceleration rollout (`solvers.one_step.constant_acceleration_rollout`)
    from each sequence's true first three poses over the same samples as the truth tR (T, S+1, B, 3, 3)
    (its sample 2 is the data's: it starts from one true pose more than a model)."""
    from ..solvers.one_step import constant_acceleration_rollout

    truth = Pose(torch.as_tensor(tR), torch.as_tensor(tp))
    S = truth.R.shape[1] - 1
    if S < 2:
        return constant_velocity_errors(dataset, tR, tp, joints=joints)
    g0, g1, g2 = (truth.index((slice(None), k)) for k in range(3))
    ca = constant_acceleration_rollout(g0, g1, g2, S)
    return sequence_errors(ca.R.numpy(), ca.p.numpy(), tR, tp, joints=joints)


def _finite(x) -> bool:
    return x is not None and isinstance(x, (int, float)) and math.isfinite(x)


ONE_STEP_REFERENCES = ("const_velocity", "const_acceleration", "euclid_velocity")
"""The zero-parameter one-step references of `one_step_errors`; a model beats guessing on a metric only
when it beats the best of them (`best_reference_ratios`)."""


def best_reference_ratios(onestep: dict) -> dict[str, list[float]] | None:
    """Per metric, per sequence: the model's one-step error over the smallest reference error (< 1: the
    model beats every zero-parameter guess). None without the model's predictions."""
    if onestep is None or onestep.get("model") is None:
        return None
    out = {}
    for k in METRICS:
        best = np.min(
            np.stack([np.asarray(onestep[w][k], dtype=float) for w in ONE_STEP_REFERENCES if w in onestep]), 0
        )
        out[k] = [float(a / b) if b > 0 else math.nan for a, b in zip(np.asarray(onestep["model"][k], float), best)]
    return out


CV_ROW = "Constant velocity, sequence"
"""Start of the constant-velocity rows' names (they are no predictions: verdicts skip them)."""
CA_ROW = "Constant acceleration, sequence"
"""Start of the constant-acceleration rows' names (no predictions either)."""


def build_rows(
    err: dict,
    disc: dict | None,
    idx: np.ndarray,
    dataset,
    ro: RolloutEntry,
    asf: float,
    unit_m: float,
    steps: int,
    cv: dict | None = None,
    ca: dict | None = None,
) -> list[dict]:
    """Table rows: one per rolled-out sequence (errors over `steps` steps, Newton failures over the whole
    rollout), then, with `cv` (`constant_velocity_errors`) and `ca` (`constant_acceleration_errors`), the
    constant-velocity and constant-acceleration rollouts of each sequence, then the ground-truth
    discrepancy."""
    rows = []
    for n, i in enumerate(idx):
        paper = PAPER["sequences"][i] if i < len(PAPER["sequences"]) else {}
        fails = int((~ro.converged[n]).sum())
        row = {
            "row": f"Sequence {i + 1} ({_sequence_name(dataset, i)}) prediction",
            "steps": steps,
            "root_rot": float(err["root_rot"][n]),
            "root_rot_paper": paper.get("root_rot"),
            "joint_rot": float(err["joint_rot"][n]),
            "joint_rot_paper": paper.get("joint_rot"),
            "joint_rot_all": float(err["joint_rot_all"][n]),
            "root_pos_asf": float(err["root_pos"][n]) * asf,
            "root_pos_m": float(err["root_pos"][n]) * unit_m,
            "root_pos_paper_asf": paper.get("root_pos"),
            "newton_failures": fails,
        }
        if disc is not None:
            for k, key in (("root_rot", "root_rot"), ("joint_rot", "joint_rot"), ("root_pos", "root_pos_asf")):
                ours = row[key]
                row[f"{k}_below_discrepancy"] = bool(_finite(ours) and ours < disc[k] * (asf if k == "root_pos" else 1))
        rows.append(row)
    for label, ref in ((CV_ROW, cv), (CA_ROW, ca)):
        for n, i in enumerate(idx if ref is not None else []):
            assert ref is not None
            rows.append(
                {
                    "row": f"{label} {i + 1} ({_sequence_name(dataset, i)})",
                    "steps": steps,
                    "root_rot": float(ref["root_rot"][n]),
                    "joint_rot": float(ref["joint_rot"][n]),
                    "joint_rot_all": float(ref["joint_rot_all"][n]),
                    "root_pos_asf": float(ref["root_pos"][n]) * asf,
                    "root_pos_m": float(ref["root_pos"][n]) * unit_m,
                    "newton_failures": None,
                }
            )
    if disc is not None:
        p = PAPER["discrepancy"]
        rows.append(
            {
                "row": f"Ground truth discrepancy ({_sequence_name(dataset, 0)} vs {_sequence_name(dataset, 1)})",
                "steps": int(dataset.n_steps),
                "root_rot": disc["root_rot"],
                "root_rot_paper": p["root_rot"],
                "joint_rot": disc["joint_rot"],
                "joint_rot_paper": p["joint_rot"],
                "joint_rot_all": disc["joint_rot_all"],
                "root_pos_asf": disc["root_pos"] * asf,
                "root_pos_m": disc["root_pos"] * unit_m,
                "root_pos_paper_asf": p["root_pos"],
                "newton_failures": None,
            }
        )
    return rows


def verdict(rows: list[dict], disc: dict | None, asf: float, full: bool = True) -> dict:
    """Is every one of our errors below the discrepancy (ours, and the paper's numbers)?

    full: the rollout covers the whole recording. Otherwise no verdict is given: both entries are
    {"given": False, "reason": ...} (a 12-step smoke rollout says nothing about the paper's claim)."""
    seq = [r for r in rows if r["row"].startswith("Sequence")]
    out: dict[str, dict[str, Any] | None] = {}
    paper = PAPER["discrepancy"]
    for name, ref in (
        (
            "measured",
            None
            if disc is None
            else {"root_rot": disc["root_rot"], "joint_rot": disc["joint_rot"], "root_pos_asf": disc["root_pos"] * asf},
        ),
        ("paper", {"root_rot": paper["root_rot"], "joint_rot": paper["joint_rot"], "root_pos_asf": paper["root_pos"]}),
    ):
        if ref is None:
            out[name] = None
            continue
        if not full:
            steps = seq[0]["steps"] if seq else 0
            out[name] = {"given": False, "reason": f"the rollout covers {steps} steps, not the whole recording"}
            continue
        fails = [f"{r['row'].split(' (')[0]} {k}" for r in seq for k in ref if not (_finite(r[k]) and r[k] < ref[k])]
        out[name] = {"given": True, "all_below": not fails, "not_below": fails}
    return out


# --------------------------------------------------------------------------- entry point
@dataclass
class MocapNumbers:
    """Everything the table, the summary and the plots of one rollout are made of (see the module
    docstring). Arrays: tR, tp, pR, pp (T, n_err+1, B, 3, 3) / (T, n_err+1, B, 3) truth and prediction
    over the samples with ground truth; err, cv (`sequence_errors`), disc (`discrepancy`)."""

    ro: RolloutEntry
    idx: np.ndarray
    n_err: int
    tR: np.ndarray
    tp: np.ndarray
    pR: np.ndarray
    pp: np.ndarray
    joints: list[int]
    err: dict
    cv: dict
    disc: dict | None
    full: bool
    asf: float
    unit_m: float
    rows: list[dict]
    verdict: dict
    nonfinite: list[int]
    until: list[dict]
    onestep: dict | None
    per_joint: dict[str, float]


def mocap_numbers(opts: SceneEvalOptions, model, dataset, path: Path) -> MocapNumbers:
    """Read the rollout file `path` and compute the errors, rows and verdicts (writes nothing)."""
    rf = load_rollout(path, dataset)
    ro, idx = rf.model, rf.traj_index
    n_err = min(ro.steps, dataset.n_steps)  # errors where ground truth exists; Newton over the whole rollout
    truth = dataset.pose(idx)
    tR, tp = truth.R.numpy()[:, : n_err + 1], truth.p.numpy()[:, : n_err + 1]
    pR, pp = ro.R[:, : n_err + 1], ro.p[:, : n_err + 1]
    joints = moving_joints(dataset)
    err = sequence_errors(pR, pp, tR, tp, joints=joints)
    cv_err = constant_velocity_errors(dataset, tR, tp, joints=joints)
    disc = discrepancy(dataset, joints=joints)
    full = n_err >= recording_steps(dataset)
    asf = _asf_per_unit(dataset)
    unit_m = float(dataset.params.get("length_unit_m", float("nan")))
    ca_err = constant_acceleration_errors(dataset, tR, tp, joints=joints)
    rows = build_rows(err, disc, idx, dataset, ro, asf, unit_m, n_err, cv=cv_err, ca=ca_err)
    onestep = one_step_errors(model, tR, tp, opts.solver, joints=joints, stored=ro.one_step, group=dataset.group)
    per_joint = {
        name: float(v)
        for name, v in zip(dataset.body_names[dataset.n_se3 :], np.nanmean(err["joint_rot_per_joint"], 0))
    }
    return MocapNumbers(
        ro=ro,
        idx=idx,
        n_err=n_err,
        tR=tR,
        tp=tp,
        pR=pR,
        pp=pp,
        joints=joints,
        err=err,
        cv=cv_err,
        disc=disc,
        full=full,
        asf=asf,
        unit_m=unit_m,
        rows=rows,
        verdict=verdict(rows, disc, asf, full=full),
        nonfinite=[
            int(i) for n, i in enumerate(idx) if not (np.isfinite(ro.R[n]).all() and np.isfinite(ro.p[n]).all())
        ],
        until=below_until(err, disc, dataset.h),
        onestep=onestep,
        per_joint=per_joint,
    )


def verdict_lines(m: MocapNumbers, dataset) -> list[str]:
    """The two verdict lines and the Newton line of the report."""
    ro, S = m.ro, m.ro.steps

    def verdict_line(key: str, what: str) -> str:
        v = m.verdict.get(key)
        if v is None:
            return f"{what}: not available (needs two recordings)"
        if not v["given"]:
            return f"{what}: no verdict ({v['reason']} of {recording_steps(dataset)})"
        if v["all_below"]:
            return f"{what}: YES, every one of our errors is below it"
        return f"{what}: NO; not below for {', '.join(v['not_below'])}"

    n_fail, first_fail = ro.n_failed, ro.first_failure
    newton_line = (
        f"Newton (whole rollout, samples 2..{S}): {n_fail} non-converged implicit step(s) out of "
        f"{ro.converged.size} ({'first at sample ' + str(first_fail) if n_fail else 'none'}); "
        f"mean iterations {ro.mean_iterations:.2f}"
    )
    if m.nonfinite:
        newton_line += f"; NON-FINITE rollout for trajectory(ies) {m.nonfinite}"
    return [
        verdict_line("measured", "Below the ground-truth discrepancy measured on this data"),
        verdict_line("paper", "Below the paper's discrepancy numbers (0.373 / 0.416 / 6.624)"),
        newton_line,
    ]


def mocap_summary(m: MocapNumbers, dataset) -> dict:
    """The content of mocap_eval.json (also what `evaluate_mocap` returns as its summary)."""
    ro, idx, onestep, asf, joints = m.ro, m.idx, m.onestep, m.asf, m.joints
    sps = ro.seconds_per_step
    return {
        "rows": m.rows,
        "verdict": m.verdict,
        "newton_failures": ro.n_failed,
        "first_failure_sample": ro.first_failure,
        "nonfinite_trajectories": m.nonfinite,
        "rollout_steps": ro.steps,
        "error_steps": m.n_err,
        "rollout_seconds_per_step": float(sps) if sps is not None else None,
        "joint_rot_per_joint": m.per_joint,
        "moving_joints": [dataset.body_names[dataset.n_se3 + j] for j in joints],
        "static_joints": [name for j, name in enumerate(dataset.body_names[dataset.n_se3 :]) if j not in set(joints)],
        "verdict_given": m.full,
        "below_discrepancy_until_s": {_sequence_name(dataset, i): u for i, u in zip(idx, m.until)},
        "one_step": None
        if onestep is None
        else {
            "converged": onestep["converged"],
            "solves": onestep["solves"],
            **{
                f"{who}_{k}": {
                    _sequence_name(dataset, i): float(onestep[who][k][n] * (asf if k == "root_pos" else 1))
                    for n, i in enumerate(idx)
                }
                for who in ("model", *ONE_STEP_REFERENCES)
                if onestep.get(who) is not None
                for k in METRICS
            },
            "model_vs_best_reference": best_reference_ratios(onestep),
            "from_rollout_file": onestep["from_rollout_file"],
        },
        "discrepancy_common_frames": int(dataset.n_steps) + 1,
        "length_unit_m": m.unit_m,
        "asf_units_per_stored_unit": asf,
        "paper": PAPER,
    }


TABLE_COLUMNS = [
    "row",
    "steps",
    "root_rot",
    "root_rot_paper",
    "joint_rot",
    "joint_rot_paper",
    "joint_rot_all",
    "root_pos_asf",
    "root_pos_m",
    "root_pos_paper_asf",
    "newton_failures",
]
"""Columns of the table in mocap_eval.md."""


def mocap_markdown(m: MocapNumbers, summary: dict, dataset) -> str:
    """The content of mocap_eval.md: the table, the verdicts, the time below the discrepancy, the
    one-step errors and the per-joint errors."""
    ro, idx, onestep, asf, S = m.ro, m.idx, m.onestep, m.asf, m.ro.steps
    static = summary["static_joints"]
    md = (
        f"# Exp 4: cartwheel reproduction errors ({dataset.scene}, h={dataset.h}, rollout of {S} steps from the "
        f"true first pair)\n\n"
        f"Means over the predicted samples k = 2..{m.n_err} (where the recording has ground truth): root rotation "
        f"geodesic error (rad), joint rotation geodesic error averaged over the {len(m.joints)} moving joints "
        f"(`joint_rot`, rad; the joints that never rotate in these recordings have zero error and discrepancy: "
        f"{', '.join(static) if static else 'none'}) and over all {dataset.n_so3} joints (`joint_rot_all`), "
        "root position error "
        "|p^ - p| in CMU ASF units (the file unit of the CMU BVH files and the paper's unit; "
        "1 ASF unit = 1/0.45 inch = 0.0564 m) and in metres. "
        f"Ground truth discrepancy: the same numbers between the two recordings over their common "
        f"{int(dataset.n_steps) + 1} frames, root positions measured from each recording's start. "
        "`*_paper`: the paper's table.\n\n"
    )
    md += markdown_table(m.rows, TABLE_COLUMNS)
    md += "\n" + "\n".join(f"- {x}" for x in verdict_lines(m, dataset))
    sps = ro.seconds_per_step
    if sps is not None:
        md += f"\n- Rollout: {float(sps):.4g} s per step ({S} steps, {len(idx)} sequence(s) batched)"
    if m.disc is not None:
        md += "\n\n## Time until the per-timestep error first exceeds the per-timestep discrepancy (s; '–': never)\n\n"
        md += markdown_table(
            [{"sequence": _sequence_name(dataset, i), **u} for i, u in zip(idx, m.until)], ["sequence", *METRICS]
        )
    if onestep is not None:
        md += (
            "\n## One-step (teacher-forced) errors: g_{k+1} from the true (g_{k-1}, g_k), mean over k\n\n"
            "`const_velocity`: g_k exp(log(g_{k-1}^-1 g_k)), the last increment repeated; `const_acceleration`: "
            "R_k exp(2 w_k - w_{k-1}), p_k + 2 dp_k - dp_{k-1} (constant velocity's guess at k = 1); "
            "`euclid_velocity`: rotations as constant velocity, root position p_k + dp_k. A model beats guessing "
            "only where it beats the best of the three (`model_vs_best_reference` in mocap_eval.json). "
            + (
                f"Newton converged on {onestep['converged']} of {onestep['solves']} solves"
                + (" (predictions stored in the rollout file)" if onestep["from_rollout_file"] else "")
                + ".\n\n"
                if onestep["model"] is not None
                else "The model's one-step predictions are not available.\n\n"
            )
        )
        orows = [
            {
                "sequence": _sequence_name(dataset, i),
                "predictor": who,
                **{LABELS[k]: float(onestep[who][k][n] * (asf if k == "root_pos" else 1)) for k in METRICS},
            }
            for n, i in enumerate(idx)
            for who in ("model", *ONE_STEP_REFERENCES)
            if onestep.get(who) is not None
        ]
        md += markdown_table(orows, list(orows[0]))
        ratios = best_reference_ratios(onestep)
        if ratios is not None:
            md += "\n\nModel over the best reference (< 1: better than every zero-parameter guess): " + "; ".join(
                f"{_sequence_name(dataset, i)}: " + ", ".join(f"{k} {fmt(ratios[k][n])}" for k in METRICS)
                for n, i in enumerate(idx)
            )
            md += "\n"
    md += "\n\n## Mean joint rotation error per joint (rad, mean over the rolled-out sequences)\n\n"
    md += markdown_table([m.per_joint], list(m.per_joint))
    return md


def mocap_console(m: MocapNumbers, dataset) -> list[tuple[Any, dict[str, Any]]]:
    """The table and the verdict lines for the console ((renderable, print options), `EvalOutputs.say`)."""
    table = Table(
        title=f"Exp 4 mocap reproduction ({m.ro.steps} steps); ours vs paper; joint rot over {len(m.joints)} "
        "moving joints"
    )
    for c in (
        "",
        "root rot [rad]",
        "paper",
        "joint rot [rad]",
        "paper",
        f"all {dataset.n_so3} joints",
        "root pos [ASF]",
        "root pos [m]",
        "paper [ASF]",
        "Newton fail",
    ):
        table.add_column(escape(c), overflow="fold")
    for r in m.rows:
        table.add_row(
            r["row"],
            fmt(r["root_rot"]),
            fmt(r.get("root_rot_paper")),
            fmt(r["joint_rot"]),
            fmt(r.get("joint_rot_paper")),
            fmt(r.get("joint_rot_all")),
            fmt(r["root_pos_asf"]),
            fmt(r["root_pos_m"]),
            fmt(r.get("root_pos_paper_asf")),
            fmt(r["newton_failures"]),
        )
    shown: list[tuple[Any, dict[str, Any]]] = [(table, {})]
    extra = []
    if m.onestep is not None:
        mo, c = m.onestep["model"], m.onestep["const_velocity"]
        extra.append(
            "one-step (teacher-forced) mean joint rot. error: "
            + ("model " + ", ".join(f"{float(v):.3e}" for v in mo["joint_rot"]) + " vs " if mo is not None else "")
            + "constant velocity "
            + ", ".join(f"{float(v):.3e}" for v in c["joint_rot"])
            + ", constant acceleration "
            + ", ".join(f"{float(v):.3e}" for v in m.onestep["const_acceleration"]["joint_rot"])
            + " rad (per sequence)"
        )
    shown += [(escape(x), {"highlight": False}) for x in verdict_lines(m, dataset) + extra]
    return shown


def mocap_figures(m: MocapNumbers, dataset) -> dict[str, Any]:
    """{path under the output folder: Figure} of the four kinds of plots (drawn, not saved)."""
    figs: dict[str, Any] = {"plots/mocap_errors.png": plot_errors(m.err, m.disc, m.idx, dataset, m.asf, cv=m.cv)}
    for n, i in enumerate(m.idx):
        sk = _skeleton_for(dataset, i)
        figs[f"plots/mocap_skeleton_seq{i + 1}.png"] = plot_skeletons(
            m.tR[n], m.tp[n], m.pR[n], m.pp[n], sk, dataset.h, i
        )
        axes = plot_joint_axes(m.tR[n], m.pR[n], sk, dataset.body_names, i)
        if axes is not None:
            figs[f"plots/mocap_joint_axes_seq{i + 1}.png"] = axes
    figs["plots/mocap_root_trajectory.png"] = plot_root_trajectory(m.tR, m.tp, m.pR, m.pp, m.idx, dataset)
    return figs


def evaluate_mocap(opts: SceneEvalOptions, model, dataset, run_dir, rollout_path=None) -> EvalOutputs:
    """Exp 4 table, files and plots of a rollout (see the module docstring), computed, not written:
    the files of the returned `EvalOutputs` go next to the rollout file.

    rollout_path: the rollout file (default `<run_dir>/rollout.h5`)."""
    path = Path(rollout_path) if rollout_path is not None else Path(run_dir) / FILE_NAME
    m = mocap_numbers(opts, model, dataset, path)
    summary = mocap_summary(m, dataset)
    out = EvalOutputs(summary, path.parent)
    out.add("mocap_eval.json", summary)
    out.add("mocap_eval.csv", m.rows)
    out.add("mocap_eval.md", mocap_markdown(m, summary, dataset))
    for what, options in mocap_console(m, dataset):
        out.say(what, **options)
    if opts.plots:
        for name, fig in mocap_figures(m, dataset).items():
            out.add(name, fig)
    return out


# --------------------------------------------------------------------------- plots
def _skeleton_for(dataset, i: int) -> dict:
    sk = dict(dataset.params["skeleton"])
    per_file = sk.get("per_file_offsets") or {}
    if str(i) in per_file:
        sk["offsets"] = per_file[str(i)]
    return sk


def plot_errors(err: dict, disc: dict | None, idx, dataset, asf: float, cv: dict | None = None) -> Figure:
    """Per-timestep errors of each sequence (3 panels) with the ground-truth discrepancy in grey and,
    with `cv` (`constant_velocity_errors`), the constant-velocity rollout of each sequence dashed."""

    h = dataset.h
    fig, axes = plt.subplots(1, 3, figsize=(14, 3.6))
    for ax, k in zip(axes, METRICS):
        scale = asf if k == "root_pos" else 1.0
        # a diverged root position (many orders above the discrepancy) on a linear axis would
        # flatten everything else to 0: that panel goes to a log axis
        if k == "root_pos" and disc is not None:
            errs = np.concatenate([np.asarray(e)[2:] for d in (err, cv or {}) for e in d.get(k + "_t", [])])
            top = np.max(errs[np.isfinite(errs)], initial=0.0)
            if top > 1e3 * np.max(disc[k + "_t"]) > 0:
                ax.set_yscale("log")
        if disc is not None:
            y = disc[k + "_t"] * scale
            ax.fill_between(np.arange(len(y)) * h, 0, y, color="0.85", label="ground-truth discrepancy")
            ax.plot(np.arange(len(y)) * h, y, color="0.55", linewidth=0.8)
        for n, i in enumerate(idx):
            y = err[k + "_t"][n] * scale
            ax.plot(
                np.arange(2, len(y)) * h,
                y[2:],
                color=SEQ_COLORS[i % 2] if i < 2 else None,
                label=f"sequence {i + 1} ({_sequence_name(dataset, i)})",
            )
            if cv is not None:
                y = cv[k + "_t"][n] * scale
                ax.plot(
                    np.arange(2, len(y)) * h,
                    y[2:],
                    "--",
                    color=CV_COLORS[i % 2] if i < 2 else None,
                    linewidth=1.2,
                    zorder=3,
                    label=f"constant velocity, sequence {i + 1}",
                )
        ax.set_title(LABELS[k])
        ax.set_xlabel("time [s]")
        ax.set_ylabel(LABELS[k])
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle(
        "Exp 4: per-timestep reproduction error (rollout from the true first pair"
        + ("; dashed: constant velocity from the same pair)" if cv is not None else ")"),
        y=1.02,
    )
    return fig


def _limits(ax, pts: np.ndarray) -> None:
    pts = pts[np.isfinite(pts).all(-1)]
    if not len(pts):
        return
    c = 0.5 * (pts.max(0) + pts.min(0))
    r = 0.5 * float((pts.max(0) - pts.min(0)).max()) or 1.0
    ax.set_xlim(c[0] - r, c[0] + r)
    ax.set_ylim(c[1] - r, c[1] + r)
    ax.set_zlim(c[2] - r, c[2] + r)
    ax.set_box_aspect((1, 1, 1))


def plot_skeletons(tR, tp, pR, pp, skeleton: dict, h: float, i: int, n_frames: int = 8) -> Figure:
    """Skeletons (forward kinematics) at uniform intervals: truth (green/red) vs prediction (blue)."""

    S = tR.shape[0] - 1
    frames = np.unique(np.linspace(0, S, min(n_frames, S + 1)).round().astype(int))
    P_true, edges = skeleton_points(tR[frames], tp[frames], skeleton)
    P_pred, _ = skeleton_points(pR[frames], pp[frames], skeleton)
    fig = plt.figure(figsize=(2.6 * len(frames), 3.4))
    color = SEQ_COLORS[i % 2] if i < 2 else "black"
    for c, k in enumerate(frames):
        ax = fig.add_subplot(1, len(frames), c + 1, projection="3d")
        for P, col, lw, lab in ((P_true[c], color, 1.8, "truth"), (P_pred[c], PRED_COLOR, 1.2, "prediction")):
            for a, b in edges:
                ax.plot(*np.stack([P[a], P[b]]).T, color=col, linewidth=lw, label=lab if (a, b) == edges[0] else None)
        _limits(ax, np.concatenate([P_true[c], P_pred[c]]))
        ax.view_init(elev=10, azim=-60)
        ax.set_title(f"t = {k * h:.3f} s", fontsize=9)
        ax.set_xticklabels([]), ax.set_yticklabels([]), ax.set_zticklabels([])
        if c == 0:
            ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Sequence {i + 1}: skeleton at uniform intervals (truth vs prediction; world frame, z up)")
    return fig


def plot_root_trajectory(tR, tp, pR, pp, idx, dataset, n_frames: int = 8) -> Figure:
    """Root position path in 3-D with the root frame (axes) at uniform intervals, truth vs prediction."""

    fig = plt.figure(figsize=(5.2 * len(idx), 5))
    for n, i in enumerate(idx):
        ax = fig.add_subplot(1, len(idx), n + 1, projection="3d")
        color = SEQ_COLORS[i % 2] if i < 2 else "black"
        pts = np.concatenate([tp[n, :, 0], pp[n, :, 0]])
        fin = pts[np.isfinite(pts).all(-1)]
        span = float((fin.max(0) - fin.min(0)).max()) if len(fin) else 1.0
        ell = 0.08 * (span or 1.0)
        S = tR.shape[1] - 1
        frames = np.unique(np.linspace(0, S, min(n_frames, S + 1)).round().astype(int))
        for R, p, col, style, lab in (
            (tR[n], tp[n], color, "-", "truth"),
            (pR[n], pp[n], PRED_COLOR, "--", "prediction"),
        ):
            ax.plot(*p[:, 0].T, style, color=col, linewidth=1.5, label=lab)
            for k in frames:
                for a, ac in zip(range(3), ("r", "g", "b")):
                    seg = np.stack([p[k, 0], p[k, 0] + ell * R[k, 0, :, a]])
                    ax.plot(*seg.T, style, color=ac, linewidth=0.9, alpha=0.8)
        _limits(ax, pts)
        ax.set_title(f"Sequence {i + 1} ({_sequence_name(dataset, i)}): root in SE(3)")
        unit = "ASF units" if abs(_asf_per_unit(dataset) - 1.0) < 1e-4 else f"x {dataset.params['length_unit_m']:.4g} m"
        for setter, name in ((ax.set_xlabel, "x"), (ax.set_ylabel, "y"), (ax.set_zlabel, "z")):
            setter(f"{name} [{unit}]", fontsize=8)
        ax.legend(fontsize=8, loc="upper left")
    return fig


def _bone_axes(skeleton: dict, names: list[str]) -> list[tuple[int, str, np.ndarray]]:
    """(body, name, unit offset of its first child in its frame) for the AXIS_JOINTS present."""
    parents, offsets = skeleton["parents"], np.asarray(skeleton["offsets"], dtype=np.float64)
    out = []
    for name in AXIS_JOINTS:
        if name not in names:
            continue
        j = names.index(name)
        kids = [c for c, q in enumerate(parents) if q == j and np.linalg.norm(offsets[c]) > 0]
        if kids:
            out.append((j, name, offsets[kids[0]] / np.linalg.norm(offsets[kids[0]])))
    return out


def plot_joint_axes(tR, pR, skeleton: dict, names: list[str], i: int) -> Figure | None:
    """Bone direction R_j d_j (d_j: unit offset of the child in joint j's frame) on the unit sphere."""

    axes_list = _bone_axes(skeleton, names)
    if not axes_list:
        return None
    fig = plt.figure(figsize=(3.4 * len(axes_list), 3.6))
    color = SEQ_COLORS[i % 2] if i < 2 else "black"
    for c, (j, name, d) in enumerate(axes_list):
        ax = fig.add_subplot(1, len(axes_list), c + 1, projection="3d")
        draw_unit_sphere(ax)
        ax.plot(*(tR[:, j] @ d).T, color=color, linewidth=1.6, label="truth")
        ax.plot(*(pR[:, j] @ d).T, "--", color=PRED_COLOR, linewidth=1.2, label="prediction")
        ax.set_title(name, fontsize=9)
        ax.set_xticklabels([]), ax.set_yticklabels([]), ax.set_zticklabels([])
        if c == 0:
            ax.legend(fontsize=7, loc="upper left")
    fig.suptitle(f"Sequence {i + 1}: selected joint rotations (bone direction in the parent frame) on S^2")
    return fig


__all__ = [
    "PAPER",
    "evaluate_mocap",
    "mocap_numbers",
    "mocap_summary",
    "mocap_markdown",
    "mocap_figures",
    "sequence_errors",
    "discrepancy",
    "verdict",
    "below_until",
    "one_step_errors",
    "constant_velocity_errors",
    "constant_acceleration_errors",
    "plot_errors",
    "plot_skeletons",
    "plot_root_trajectory",
    "plot_joint_axes",
]
