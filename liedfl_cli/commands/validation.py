"""Validation and model selection while training (docs/validation.md).

- `make_val_split`: held-out data taken from the train split at train time (the dataset file, its
  cache hash and its test split are untouched). With at least `TIME_SPLIT_BELOW` train trajectories a
  `dataset.val_fraction` share of them (drawn with the dataset's seed) is held out whole; with fewer
  (e.g. the two mocap recordings) the last `val_fraction` part in time of each train trajectory's
  training window is held out and training uses the part before it.
- `Validator`: every `train.val_every` epochs (and at the last epoch) the teacher-forced one-step
  error and a `train.val_horizon`-step rollout error on the validation data, under `torch.no_grad()`,
  in eval mode, on at most `MAX_VAL_TRAJECTORIES` trajectories / `MAX_ONE_STEP_PAIRS` one-step pairs;
  the constant-velocity and constant-acceleration one-step errors once, as the references (a model
  beats guessing only when `val_one_step_vs_best`, its error over the better of the two, is below 1).
- `Selection`: which pass is best (`train.select`), early stopping (`train.early_stopping`); its
  state travels in the checkpoint so that a resumed run selects as an uninterrupted one.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch

from ..config import fields
from ..config.typed import TrainConfig
from ..errors import ConfigError
from ..evaluation.metrics import geodesic_error, position_error
from ..lie import Pose
from ..solvers.one_step import (
    constant_acceleration_step,
    constant_velocity_one_step,
    constant_velocity_step,
    one_step_predictions,
)
from ..solvers.options import SolverOptions

DEFAULT_VAL_FRACTION = 0.1
TIME_SPLIT_BELOW = 5
"""Fewer train trajectories than this: the validation split is taken in time, not by trajectory."""
MIN_TRAIN_STEPS = 2
"""Steps a training window keeps at least after a time split (one pose triplet)."""
MAX_VAL_TRAJECTORIES = 64
MAX_ONE_STEP_PAIRS = 4096
AUTO_VAL_PASSES = 20
SELECT = fields.allowed(TrainConfig, "select")  # declared once, on the field
SELECT_COLUMN = {"val_one_step": "val_one_step_error", "val_rollout": "val_rollout_error"}
VAL_COLUMNS = (
    "val_one_step_error",
    "val_one_step_pos_error",
    "val_cv_one_step_error",
    "val_one_step_vs_cv",
    "val_ca_one_step_error",
    "val_one_step_vs_ca",
    "val_one_step_vs_best",
    "val_rollout_error",
    "val_rollout_pos_error",
    "val_seconds",
)
"""Columns of train_metrics.csv written by a validation pass (empty on epochs without one)."""


# ----------------------------------------------------------------------------- split
@dataclass(frozen=True)
class ValSplit:
    """Which data trains and which validates.

    kind: "none" (no validation), "trajectories" (val_idx held out whole) or "time" (the same
    trajectories; training uses steps 0..train_steps, validation the poses val_start..val_stop).
    """

    kind: str
    train_idx: np.ndarray
    val_idx: np.ndarray
    train_steps: int
    val_start: int = 0
    val_stop: int = 0

    def describe(self) -> str:
        if self.kind == "none":
            return "none (dataset.val_fraction=0)"
        n_poses = self.val_stop - self.val_start + 1
        if self.kind == "trajectories":
            return (
                f"{len(self.val_idx)} held-out train trajectories x {n_poses - 1} steps "
                f"(training on the other {len(self.train_idx)})"
            )
        return (
            f"in time: poses {self.val_start}..{self.val_stop} of each of the {len(self.val_idx)} train "
            f"trajectories (fewer than {TIME_SPLIT_BELOW}); training on steps 0..{self.train_steps}"
        )


def val_fraction(value) -> float:
    """`dataset.val_fraction`: a number in [0, 1) (ConfigError otherwise)."""
    if value is None:
        return DEFAULT_VAL_FRACTION
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (0 <= value < 1):
        raise ConfigError(f"dataset.val_fraction={value!r}: must be a number in [0, 1) (0: no validation)")
    return float(value)


def make_val_split(train_idx, train_steps: int, fraction: float, seed: int) -> ValSplit:
    """The validation split of the train trajectories `train_idx` (sorted indices), whose first
    `train_steps` steps train. Deterministic given `seed` (the dataset's). One-line ConfigError when
    the data is too small for the asked fraction."""
    train_idx = np.sort(np.asarray(train_idx, dtype=np.int64))
    n, L = len(train_idx), int(train_steps)
    fraction = val_fraction(fraction)
    if fraction == 0:
        return ValSplit("none", train_idx, np.zeros(0, np.int64), L)
    if L < MIN_TRAIN_STEPS:  # too short to train at all: the fault is the length, not the validation
        raise ConfigError(
            f"dataset.train_steps={L}: need at least {MIN_TRAIN_STEPS} steps to form a triplet (and more to validate)"
        )
    hint = "; lower dataset.val_fraction or set it to 0 (no validation)"
    if n >= TIME_SPLIT_BELOW:
        k = max(1, round(fraction * n))
        if k >= n:
            raise ConfigError(f"dataset.val_fraction={fraction}: holds out {k} of the {n} train trajectories" + hint)
        rng = np.random.default_rng(np.random.SeedSequence((abs(int(seed)), 0x7A1)))
        perm = rng.permutation(n)
        val = np.sort(train_idx[perm[:k]])
        return ValSplit("trajectories", np.sort(train_idx[perm[k:]]), val, L, 0, L)
    k = max(1, round(fraction * L))
    if L - k < MIN_TRAIN_STEPS:
        raise ConfigError(
            f"dataset.val_fraction={fraction}: with {n} train trajectories (fewer than {TIME_SPLIT_BELOW}) the last "
            f"{k} of their {L} training steps validate, leaving {L - k} (need {MIN_TRAIN_STEPS})" + hint
        )
    # validation poses L-k-1..L: the first pair (L-k-1, L-k) is the end of the training window, every
    # predicted pose (L-k+1..L) lies after it
    return ValSplit("time", train_idx, train_idx.copy(), L - k, L - k - 1, L)


def val_interval(value, epochs: int) -> int:
    """`train.val_every`: `auto` (about AUTO_VAL_PASSES passes per run) or a positive integer."""
    if value in (None, "auto"):
        return max(1, math.ceil(int(epochs) / AUTO_VAL_PASSES))
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"train.val_every={value!r}: must be auto or a positive integer")
    return int(value)


# ----------------------------------------------------------------------------- selection
@dataclass
class Selection:
    """Best validation pass and early stopping. metric: the train_metrics.csv column selected on (None:
    `select=last`, nothing is selected). A pass improves when its metric is finite and below the best
    by more than `min_delta`; `patience` passes in a row without improvement stop training."""

    metric: str | None
    patience: int | None = None
    min_delta: float = 0.0
    best: float | None = None
    best_epoch: int | None = None
    bad_passes: int = 0
    stopped: bool = False

    def update(self, epoch: int, row: dict) -> tuple[bool, bool]:
        """Record the pass of `epoch` (a row with the val columns) -> (improved, stop now)."""
        if self.metric is None:
            return False, False
        value = row.get(self.metric)
        value = float(value) if isinstance(value, (int, float)) else math.nan
        if math.isfinite(value) and (self.best is None or value < self.best - self.min_delta):
            self.best, self.best_epoch, self.bad_passes = value, int(epoch), 0
            return True, False
        self.bad_passes += 1
        self.stopped = self.patience is not None and self.bad_passes >= self.patience
        return False, self.stopped

    def state(self) -> dict:
        return {
            "metric": self.metric,
            "best": self.best,
            "best_epoch": self.best_epoch,
            "bad_passes": self.bad_passes,
            "stopped": self.stopped,
        }

    def restore(self, state: dict | None) -> None:
        if not state:
            return
        self.best = None if state.get("best") is None else float(state["best"])
        self.best_epoch = None if state.get("best_epoch") is None else int(state["best_epoch"])
        self.bad_passes = int(state.get("bad_passes", 0))
        self.stopped = bool(state.get("stopped", False))


def select_option(cfg_train: TrainConfig, split: ValSplit) -> tuple[str, list[str]]:
    """`train.select` checked against the split -> (select, notes)."""
    select = str(cfg_train.select)
    if select not in SELECT:
        raise ConfigError(f"train.select={select!r}: choose one of {', '.join(SELECT)}")
    es = cfg_train.early_stopping
    if split.kind == "none":
        notes = [] if select == "last" else [f"no validation split: train.select={select} -> last"]
        if es.patience is not None:
            notes.append("no validation split: train.early_stopping is off")
        return "last", notes
    if select == "last" and es.patience is not None:
        raise ConfigError(
            "train.early_stopping.patience needs a validation metric to watch: set train.select=val_one_step "
            "or val_rollout (or patience=null)"
        )
    return select, []


def make_selection(cfg_train: TrainConfig, select: str) -> Selection:
    es = cfg_train.early_stopping
    patience = es.patience
    if patience is not None and (isinstance(patience, bool) or not isinstance(patience, int) or patience < 1):
        raise ConfigError(f"train.early_stopping.patience={patience!r}: must be a positive integer or null")
    min_delta = es.min_delta or 0.0
    if isinstance(min_delta, bool) or not isinstance(min_delta, (int, float)) or not min_delta >= 0:
        raise ConfigError(f"train.early_stopping.min_delta={min_delta!r}: must be a number >= 0")
    if select == "last":
        return Selection(None)
    return Selection(SELECT_COLUMN[select], patience, float(min_delta))


# ----------------------------------------------------------------------------- measuring
def _picks(T: int, W: int, cap: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(trajectory, k) of the one-step pairs of T windows of W poses: every interior k, at most `cap`,
    evenly spread."""
    t = torch.arange(T).repeat_interleave(W - 2)
    k = torch.arange(1, W - 1).repeat(T)
    if len(t) > cap:
        pick = torch.linspace(0, len(t) - 1, cap).round().long()
        t, k = t[pick], k[pick]
    return t, k


def _one_step_windows(truth: Pose, cap: int) -> Pose:
    """Pose triplets (g_{k-1}, g_k, g_{k+1}) of truth (T, W, ...), at most `cap`, evenly spread:
    R (P, 3, B, 3, 3), p (P, 3, m, 3)."""
    T, W = truth.R.shape[:2]
    t, k = _picks(T, W, cap)
    t, k = t.to(truth.R.device), k.to(truth.R.device)
    stack = lambda x: torch.stack([x[t, k - 1], x[t, k], x[t, k + 1]], dim=1)
    return Pose(stack(truth.R), stack(truth.p))


def constant_acceleration_guesses(group, truth: Pose, cap: int) -> Pose:
    """The constant-acceleration guesses of g_{k+1} for the pairs of `_one_step_windows(truth, cap)`
    (same order): from (g_{k-2}, g_{k-1}, g_k) where k >= 2, the constant-velocity guess at k = 1 (only
    two poses before it). R (P, 1, B, 3, 3), p (P, 1, m, 3)."""
    T, W = truth.R.shape[:2]
    t, k = _picks(T, W, cap)
    t, k = t.to(truth.R.device), k.to(truth.R.device)
    at = lambda j: Pose(truth.R[t, j], truth.p[t, j])
    cv = constant_velocity_step(group, at(k - 1), at(k))
    ca = constant_acceleration_step(group, at((k - 2).clamp(min=0)), at(k - 1), at(k))
    first = (k == 1).view(-1, *([1] * (ca.R.dim() - 1)))
    R = torch.where(first, cv.R, ca.R)
    p = torch.where(first.view(-1, *([1] * (ca.p.dim() - 1))), cv.p, ca.p)
    return Pose(R[:, None], p[:, None])


def _errors(pred: Pose, true: Pose) -> tuple[float, float | None]:
    """(mean geodesic error over everything, mean position error or None without positions)."""
    rot = float(geodesic_error(pred.R, true.R).mean())
    pos = float(position_error(pred.p, true.p).mean()) if true.p.shape[-2] > 0 else None
    return rot, pos


def _reason(e: BaseException) -> str:
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}".rstrip(": ")


@dataclass
class Validator:
    """The validation passes of one training run (see the module docstring).

    truth: the validation window R (V, W, B, 3, 3), p (V, W, m, 3) on the model's device and dtype."""

    group: object
    truth: Pose
    solver: SolverOptions
    horizon: int
    every: int
    notes: list[str] = field(default_factory=list)
    _windows: Pose | None = None
    _cv: float | None = None
    _cv_pos: float | None = None
    _ca: float | None = None
    _failed: set[str] = field(default_factory=set)

    def __post_init__(self) -> None:
        self.truth = self.truth.index(slice(0, MAX_VAL_TRAJECTORIES))
        W = int(self.truth.R.shape[1])
        self.horizon = min(int(self.horizon), W - 1)
        self._windows = _one_step_windows(self.truth, MAX_ONE_STEP_PAIRS)
        cv = constant_velocity_one_step(self.group, self._windows)  # type: ignore[arg-type]
        self._cv, self._cv_pos = _errors(cv, self._windows.index((slice(None), slice(2, 3))))
        ca = constant_acceleration_guesses(self.group, self.truth, MAX_ONE_STEP_PAIRS)
        self._ca, _ = _errors(ca, self._windows.index((slice(None), slice(2, 3))))

    @property
    def cv_error(self) -> float:
        """The constant-velocity one-step error on the validation pairs (rad)."""
        return float(self._cv) if self._cv is not None else math.nan

    @property
    def n_pairs(self) -> int:
        assert self._windows is not None
        return int(self._windows.R.shape[0])

    def due(self, epoch: int, epochs: int) -> bool:
        return epoch % self.every == 0 or epoch == epochs

    def _note_once(self, what: str, model, e: BaseException) -> None:
        if what not in self._failed:
            self._failed.add(what)
            from ..display.ui import console

            console.print(
                f"[bold yellow]note:[/] {what} skipped for {type(model).__name__} ({_reason(e)})", highlight=False
            )

    def measure(self, model) -> dict:
        """One validation pass of `model` -> the VAL_COLUMNS (None where a metric does not apply,
        NaN where the model failed; a one-line note the first time)."""
        assert self._windows is not None
        t0 = time.perf_counter()
        row: dict = dict.fromkeys(VAL_COLUMNS)
        has_pos = self.truth.p.shape[-2] > 0
        was_training = model.training
        model.eval()
        try:
            with torch.no_grad(), torch.random.fork_rng(devices=[]):
                try:
                    pred, _ = one_step_predictions(model, self._windows, self.solver)
                    rot, pos = _errors(pred, self._windows.index((slice(None), slice(2, 3))))
                except (RuntimeError, ValueError, ArithmeticError, NotImplementedError) as e:
                    self._note_once("val_one_step_error", model, e)
                    rot, pos = math.nan, (math.nan if has_pos else None)
                row["val_one_step_error"], row["val_one_step_pos_error"] = rot, pos
                row["val_cv_one_step_error"] = self._cv
                row["val_one_step_vs_cv"] = rot / self._cv if self._cv else None
                row["val_ca_one_step_error"] = self._ca
                row["val_one_step_vs_ca"] = rot / self._ca if self._ca else None
                best = min(x for x in (self._cv, self._ca) if x is not None)
                row["val_one_step_vs_best"] = rot / best if best else None
                if self.horizon >= 2:
                    g0, g1 = self.truth.index((slice(None), 0)), self.truth.index((slice(None), 1))
                    try:
                        ro = model.rollout(g0, g1, self.horizon, self.solver)
                        span = (slice(None), slice(2, self.horizon + 1))
                        rot, pos = _errors(ro.pose.index(span), self.truth.index(span))
                    except (RuntimeError, ValueError, ArithmeticError, NotImplementedError) as e:
                        self._note_once("val_rollout_error", model, e)
                        rot, pos = math.nan, (math.nan if has_pos else None)
                    row["val_rollout_error"], row["val_rollout_pos_error"] = rot, pos
        finally:
            model.train(was_training)
        row["val_seconds"] = time.perf_counter() - t0
        return row


def format_pass(row: dict) -> str:
    """The progress-line text of a pass: `val 1.2e-04 (0.31x CV, 1.20x CA), roll 3.4e-03`."""
    one = row.get("val_one_step_error")
    if one is None:
        return ""
    text = f"val {one:.2e}"
    ratio = row.get("val_one_step_vs_cv")
    if ratio is not None:
        ca = row.get("val_one_step_vs_ca")
        text += f" ({ratio:.2f}x CV" + (f", {ca:.2f}x CA)" if ca is not None else ")")
    roll = row.get("val_rollout_error")
    if roll is not None:
        text += f", roll {roll:.2e}"
    return text
