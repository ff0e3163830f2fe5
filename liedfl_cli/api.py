"""Python API: trained liedfl models in a notebook or a script (docs/api.md).

    from liedfl_cli import api

    run = api.load_run("outputs/runs/<run>")            # a run written by `liedfl train`
    R, p = run.trajectory(0, split="test")              # numpy: R (N+1, B, 3, 3), p (N+1, m, 3)
    g0 = api.make_pose(run.group, R=R[0], p=p[0])       # or quaternions=..., scalar_first=...
    g1 = api.make_pose(run.group, R=R[1], p=p[1])
    g2 = api.predict(run, g0, g1)                       # one step
    traj = api.rollout(run, g0, g1, steps=100)          # numpy arrays, Newton diagnostics
    params = api.parameters(run)                        # learned parameters as a dict of arrays

Inputs are numpy arrays (or torch tensors) of real numbers; they are checked before anything runs and
every problem is one `InputError` line naming the argument, its shape and what was expected. Arrays
are used in float64: float32 (and integer) inputs are converted, rotations that are off SO(3) by
more than 1e-9 (float32 rounding) but less than 1e-3 are projected back by SVD, anything further off
is refused, and so are complex, boolean, float16 and non-finite inputs.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .config import resolvers  # noqa: F401  (registers the config resolvers)
from .errors import ConfigError, InputError
from .lie import Pose, ProductGroup, so3
from .models.base import Model
from .solvers.options import SolverOptions

ArrayLike = Any


# --------------------------------------------------------------------------- groups
def group(spec) -> ProductGroup:
    """A product group from `ProductGroup`, (n_se3, n_so3), a Dataset/Run, or a name: "SO(3)", "SE(3)",
    "SE(3) x SO(3)^22", "so3", "se3", "se3_so3n:22" (SE(3) x SO(3)^22)."""
    if isinstance(spec, ProductGroup):
        return spec
    if hasattr(spec, "group") and isinstance(spec.group, ProductGroup):
        return spec.group
    if isinstance(spec, (tuple, list)) and len(spec) == 2 and all(isinstance(x, int) for x in spec):
        try:
            return ProductGroup(int(spec[0]), int(spec[1]))
        except ValueError as e:
            raise InputError(f"group={tuple(spec)}: {e}") from None
    if isinstance(spec, str):
        s = spec.replace(" ", "").lower()
        if s in ("so3", "so(3)"):
            return ProductGroup(0, 1)
        if s in ("se3", "se(3)"):
            return ProductGroup(1, 0)
        n_se3 = n_so3 = 0
        ok = bool(s)
        for part in s.split("x"):
            base, _, power = part.partition("^")
            try:
                k = int(power) if power else 1
            except ValueError:
                ok = False
                break
            if base in ("se(3)", "se3"):
                n_se3 += k
            elif base in ("so(3)", "so3"):
                n_so3 += k
            else:
                ok = False
                break
        if ok and n_se3 + n_so3 > 0:
            return ProductGroup(n_se3, n_so3)
    raise InputError(
        f"group={spec!r}: not a group; give a ProductGroup, (n_se3, n_so3), a run, or a name such as "
        "'SO(3)', 'SE(3)' or 'SE(3) x SO(3)^22'"
    )


# --------------------------------------------------------------------------- input checks
def _array(x: ArrayLike, name: str) -> np.ndarray:
    """x as a float64 numpy array (InputError for non-real, float16, object arrays or non-finite values)."""
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    try:
        a = np.asarray(x)
    except (TypeError, ValueError) as e:
        raise InputError(f"{name}: not an array ({type(e).__name__}: {e})") from None
    if a.dtype == np.bool_ or not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise InputError(f"{name}: dtype {a.dtype} is not supported; give real numbers (float64, or float32)")
    if a.dtype.itemsize < 4 and np.issubdtype(a.dtype, np.floating):
        raise InputError(f"{name}: dtype {a.dtype} has too few digits for poses; give float64 (or float32)")
    a = a.astype(np.float64)
    bad = ~np.isfinite(a)
    if bad.any():
        raise InputError(f"{name}: non-finite value at index {tuple(int(i) for i in np.argwhere(bad)[0])}")
    return a


def _rotations(R: np.ndarray, name: str) -> np.ndarray:
    """Check rotation matrices (..., 3, 3); project the slightly-off ones (float32 rounding)."""
    E = np.swapaxes(R, -1, -2) @ R - np.eye(3)
    err = np.sqrt((E * E).sum((-1, -2)))
    det = np.linalg.det(R) if R.size else np.zeros(R.shape[:-2])
    worst = np.maximum(err, np.abs(det - 1.0))
    if (worst > 1e-3).any():
        i = tuple(int(k) for k in np.argwhere(worst > 1e-3)[0])
        raise InputError(
            f"{name}: not a rotation matrix at index {i}: ||R^T R - I||_F = {err[i]:.3g}, det R = {det[i]:.6g}"
        )
    off = worst > 1e-9
    if off.any():
        R = R.copy()
        R[off] = so3.project(torch.from_numpy(np.ascontiguousarray(R[off]))).numpy()
    return R


def quaternions_to_rotations(q: ArrayLike, scalar_first: bool) -> np.ndarray:
    """Unit quaternions (..., 4) -> rotation matrices (..., 3, 3). scalar_first: True for (w, x, y, z),
    False for (x, y, z, w); required, because both conventions are common and a wrong guess silently
    gives another motion. Norms may be off 1 by up to 1e-2 (they are normalised)."""
    if not isinstance(scalar_first, bool):
        raise InputError(
            "scalar_first must be True (quaternions (w, x, y, z)) or False ((x, y, z, w)); "
            f"got {scalar_first!r}: the convention is not guessed"
        )
    a = _array(q, "quaternions")
    if a.ndim < 1 or a.shape[-1] != 4:
        raise InputError(f"quaternions: shape {a.shape}; need (..., 4)")
    norm = np.linalg.norm(a, axis=-1)
    bad = np.abs(norm - 1.0) > 1e-2
    if bad.any():
        i = tuple(int(k) for k in np.argwhere(bad)[0])
        raise InputError(f"quaternions: norm {norm[i]:.4g} at index {i} is not 1 (tolerance 1e-2)")
    wxyz = a if scalar_first else a[..., [3, 0, 1, 2]]
    return so3.from_quaternion(torch.from_numpy(np.ascontiguousarray(wxyz))).numpy()


def rotations_to_quaternions(R: ArrayLike, scalar_first: bool) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> unit quaternions (..., 4) with a non-negative scalar part,
    (w, x, y, z) if scalar_first else (x, y, z, w)."""
    if not isinstance(scalar_first, bool):
        raise InputError(f"scalar_first must be True or False, got {scalar_first!r}")
    a = _array(R, "R")
    if a.ndim < 2 or a.shape[-2:] != (3, 3):
        raise InputError(f"R: shape {a.shape}; need (..., 3, 3)")
    q = so3.to_quaternion(torch.from_numpy(_rotations(a, "R"))).numpy()
    return q if scalar_first else q[..., [1, 2, 3, 0]]


def make_pose(
    group_spec,
    R: ArrayLike | None = None,
    p: ArrayLike | None = None,
    *,
    quaternions: ArrayLike | None = None,
    scalar_first: bool | None = None,
) -> Pose:
    """A pose (or a batch, or a sequence of poses) of the group, as a float64 torch `Pose`.

    group_spec: see `group` (B bodies, the m SE(3) bodies first). Rotations: `R` of shape (..., B, 3, 3),
    body to world; or `quaternions` (..., B, 4) with `scalar_first` stated (True: (w, x, y, z), False:
    (x, y, z, w)). Positions: `p` (..., m, 3) of the SE(3) bodies; leave it out for SO(3)^n groups.
    The leading dimensions (...) are free: none for one pose, (T,) for T trajectories, (T, K) for
    sequences. One bare pose of a one-body group may drop the body axis: R (3, 3), quaternions (4,),
    p (3,).
    """
    G = group(group_spec)
    B, m = G.n_bodies, G.n_se3
    if (R is None) == (quaternions is None):
        raise InputError("make_pose: give the rotations either as R=(..., B, 3, 3) or as quaternions=(..., B, 4)")
    if quaternions is not None:
        if scalar_first is None:
            raise InputError(
                "make_pose: quaternions need scalar_first=True (w, x, y, z) or scalar_first=False (x, y, z, w)"
            )
        shape = np.shape(quaternions)
        Rm = quaternions_to_rotations(quaternions, scalar_first)
        need = f"quaternions: shape {shape}; need (..., {B}, 4)" + (" or (4,)" if B == 1 else "")
    else:
        Rm = _array(R, "R")
        shape = Rm.shape
        need = f"R: shape {shape}; need (..., {B}, 3, 3)" + (" or (3, 3)" if B == 1 else "")
        if Rm.ndim >= 2 and Rm.shape[-2:] == (3, 3):
            Rm = _rotations(Rm, "R")
    if B == 1 and Rm.ndim == 2 and Rm.shape == (3, 3):
        Rm = Rm[None]  # one bare pose of a one-body group
    if Rm.ndim < 3 or Rm.shape[-3:] != (B, 3, 3):
        raise InputError(f"{need} for {G.name} (the body axis B = {B} is required)")
    lead = Rm.shape[:-3]
    if m == 0:
        if p is not None and _size(p):
            raise InputError(f"p: {G.name} has no positions (no SE(3) body); leave p out (got shape {np.shape(p)})")
        pm = np.zeros((*lead, 0, 3))
    else:
        if p is None:
            raise InputError(f"p: {G.name} needs the positions of its {m} SE(3) bod{'y' if m == 1 else 'ies'}")
        pm = _array(p, "p")
        if m == 1 and not lead and pm.shape == (3,):
            pm = pm[None]
        if pm.shape != (*lead, m, 3):
            raise InputError(f"p: shape {pm.shape}; need {(*lead, m, 3)} (the rotations have leading shape {lead})")
    return Pose(torch.from_numpy(np.ascontiguousarray(Rm)), torch.from_numpy(np.ascontiguousarray(pm)))


def _size(x) -> int:
    """Number of entries of an array or tensor (np.size of a torch tensor is its bound `size` method)."""
    return int(x.numel()) if isinstance(x, torch.Tensor) else int(np.size(x))


def _pose(x, G: ProductGroup, name: str) -> Pose:
    """A Pose / (R, p) pair / dict as a float64 Pose on G (checked)."""
    R: Any
    p: Any
    if isinstance(x, Pose):
        R, p = x.R, x.p
    elif isinstance(x, Mapping) and "R" in x:
        R, p = x["R"], x.get("p")
    elif isinstance(x, Sequence) and len(x) == 2 and not isinstance(x, str):
        R, p = x
    else:
        raise InputError(f"{name}: expected a pose (api.make_pose(...), or a pair (R, p)), got {type(x).__name__}")
    try:
        return make_pose(G, R=R, p=p if (p is not None and _size(p)) else None)
    except InputError as e:
        raise InputError(f"{name}: {e}") from None


def _pair(run_or_model, g0, g1) -> tuple[Any, Pose, Pose, bool]:
    model = getattr(run_or_model, "model", run_or_model)
    if not isinstance(model, Model):
        raise InputError(f"expected a Run (api.load_run) or a liedfl model, got {type(run_or_model).__name__}")
    G = model.G
    a, b = _pose(g0, G, "g0"), _pose(g1, G, "g1")
    if a.R.shape != b.R.shape:
        raise InputError(f"g0 and g1 differ in shape: R {tuple(a.R.shape)} vs {tuple(b.R.shape)}")
    lead = a.R.shape[:-3]
    if len(lead) > 1:
        raise InputError(f"g0, g1: leading shape {tuple(lead)}; give one pose or a batch (T, ...) of poses")
    single = len(lead) == 0
    if single:
        a, b = Pose(a.R[None], a.p[None]), Pose(b.R[None], b.p[None])
    return model, a, b, single


# --------------------------------------------------------------------------- runs
@dataclass
class Run:
    """A trained run: its config (typed: `config.typed.RunConfig`), model (trained weights, eval
    mode), dataset and folder."""

    config: Any
    model: Any
    dataset: Any
    run_dir: Path
    checkpoint: dict = field(default_factory=dict)  # which checkpoint was loaded (file, epoch, selection)

    @property
    def name(self) -> str:
        return self.model.name or type(self.model).__name__

    @property
    def group(self) -> ProductGroup:
        return self.model.G

    @property
    def h(self) -> float:
        return float(self.model.h)

    def trajectory(self, i: int = 0, split: str = "test") -> tuple[np.ndarray, np.ndarray]:
        """The i-th trajectory of a split ("train", "test") or of the whole dataset (split=None):
        (R (N+1, B, 3, 3), p (N+1, m, 3)) as numpy arrays."""
        idx = np.arange(self.dataset.n_trajectories) if split is None else self.dataset.split.get(split)
        if idx is None:
            raise InputError(f"split={split!r}: choose 'train', 'test' or None")
        if not 0 <= i < len(idx):
            raise InputError(f"trajectory {i}: the {split or 'dataset'} has {len(idx)} trajectories")
        j = int(idx[i])
        return self.dataset.R[j].copy(), self.dataset.p[j].copy()

    def __repr__(self) -> str:
        ds = self.dataset
        return (
            f"Run({self.run_dir}, model={self.name}, group={self.group.name}, h={self.h}, "
            f"dataset={ds.scene}: {ds.n_trajectories} x {ds.n_steps} steps, train {len(ds.train_idx)}, "
            f"test {len(ds.test_idx)})"
        )


def load_run(run_dir, data_dir=None, checkpoint: str = "best") -> Run:
    """Load a run written by `liedfl train` (its checkpoint, config and dataset). checkpoint: `best`
    (checkpoints/best.pt, the model selected on the validation split, when the run has one; else
    last.pt) or `last`; `Run.checkpoint` says which was loaded."""
    from .config.runs import load_run_checkpoint

    loaded = load_run_checkpoint(run_dir, data_dir, checkpoint)
    loaded.model.eval()
    return Run(loaded.config, loaded.model, loaded.dataset, Path(loaded.run_dir), loaded.checkpoint)


def train(*overrides: str, output_dir=None, data_dir=None, progress: bool = False) -> Run:
    """`liedfl train <overrides>` from Python: compose the train config with the overrides (e.g.
    "dataset=import", "dataset.path=log.csv", "dataset.rotation=wxyz", "budget=smoke"), validate it,
    train, roll out and evaluate into `output_dir` (default outputs/runs/<date>_<time>_api) and
    return the run."""
    from datetime import datetime

    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from .cli import CONF_DIR
    from .commands.train import run_train
    from .config.schema import validate

    if output_dir is None:
        output_dir = Path("outputs/runs") / datetime.now().strftime("%Y-%m-%d_%H-%M-%S-%f_api")
    extra = [f"paths.output_dir={Path(output_dir).absolute()}", f"ui.progress={str(bool(progress)).lower()}"]
    if data_dir is not None:
        extra.append(f"paths.data_dir={Path(data_dir).absolute()}")
    GlobalHydra.instance().clear()
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose(config_name="train", overrides=[*overrides, *extra])
    validate(cfg, "train")
    from .files.locks import run_lock

    Path(output_dir).mkdir(parents=True, exist_ok=True)
    with run_lock(output_dir, "train"):  # one process per run folder, as for `liedfl train` (locks.RunLocked)
        run_train(cfg)
    return load_run(output_dir)


# --------------------------------------------------------------------------- prediction
@dataclass
class Trajectory:
    """A rollout as numpy arrays: R (T, S+1, B, 3, 3), p (T, S+1, m, 3) (no T for a single start),
    the Newton flags of the solves that produced samples 2..S, the time step and wall time."""

    R: np.ndarray
    p: np.ndarray
    converged: np.ndarray
    iterations: np.ndarray
    h: float
    seconds: float

    @property
    def t(self) -> np.ndarray:
        """Sample times 0, h, ..., S h (s)."""
        return self.h * np.arange(self.R.shape[-4])

    @property
    def pose(self) -> Pose:
        return Pose(torch.from_numpy(self.R), torch.from_numpy(self.p))


def _solver(solver) -> SolverOptions:
    if solver is None:
        return SolverOptions()
    if isinstance(solver, SolverOptions):
        return solver
    if isinstance(solver, Mapping):
        from .config.typed import section

        try:  # the `solver` section's schema: unknown keys and wrong types refused
            return section(SolverOptions, dict(solver), "solver")
        except ConfigError as e:
            raise InputError(f"solver={dict(solver)}: {e}") from None
    raise InputError(f"solver: give a mapping such as {{'tol': 1e-5, 'max_iter': 10}}, got {type(solver).__name__}")


def rollout(run_or_model, g0, g1, steps: int, solver=None) -> Trajectory:
    """Predict g_2..g_steps from the two poses g0, g1 (one pose each, or batches (T, ...)): the model's
    own rollout (Newton on the DEL equations for LieDFLNN). solver: SolverOptions or a mapping of
    `tol`, `max_iter`, `max_halvings` (default: the CLI's)."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 2:
        raise InputError(f"steps={steps!r}: must be an integer >= 2 (the two given poses and at least one prediction)")
    model, a, b, single = _pair(run_or_model, g0, g1)
    was_training = model.training
    model.eval()
    try:
        ro = model.rollout(a, b, int(steps), _solver(solver))
    finally:
        model.train(was_training)
    out = Trajectory(
        R=ro.pose.R.detach().cpu().numpy(),
        p=ro.pose.p.detach().cpu().numpy(),
        converged=ro.converged.detach().cpu().numpy().astype(bool),
        iterations=ro.iterations.detach().cpu().numpy(),
        h=float(model.h),
        seconds=float(ro.seconds),
    )
    if single:
        out.R, out.p, out.converged, out.iterations = out.R[0], out.p[0], out.converged[0], out.iterations[0]
    return out


def predict(run_or_model, g0, g1, solver=None) -> Pose:
    """The pose after g1 (one step of the model) as a float64 torch `Pose`; batches work as in `rollout`.
    (An implicit step whose Newton solve did not converge still returns its last iterate; `rollout(run,
    g0, g1, 2).converged` has the flag.)"""
    tr = rollout(run_or_model, g0, g1, 2, solver)
    return Pose(torch.from_numpy(tr.R[..., -1, :, :, :].copy()), torch.from_numpy(tr.p[..., -1, :, :].copy()))


def geodesic_error(R_pred: ArrayLike, R_true: ArrayLike) -> np.ndarray:
    """Geodesic distance |log(R_pred^T R_true)| (rad) of two rotation arrays of the same shape (..., 3, 3)."""
    a, b = _array(R_pred, "R_pred"), _array(R_true, "R_true")
    if a.shape != b.shape or a.shape[-2:] != (3, 3):
        raise InputError(f"geodesic_error: shapes {a.shape} and {b.shape}; need the same (..., 3, 3)")
    return so3.geodesic_distance(torch.from_numpy(a), torch.from_numpy(b)).numpy()


# --------------------------------------------------------------------------- parameters
def parameters(run_or_model) -> dict[str, Any]:
    """The learned parameters as numpy arrays.

    Interpretable parts where the model has them (LieDFLNN): `J_d` (B, 3, 3) the discrete inertia of
    each body, `m` (m,) and `rho_COM` (m, 3) of the SE(3) bodies, `D` (dim, dim) a constant Rayleigh
    damping, `C` (3, k) a learned control's input matrix; and under `weights` every parameter tensor
    by its state-dict name (networks included)."""
    model = getattr(run_or_model, "model", run_or_model)
    if not isinstance(model, Model):
        raise InputError(f"expected a Run (api.load_run) or a liedfl model, got {type(run_or_model).__name__}")
    out: dict[str, Any] = {k: v.cpu().numpy() for k, v in model.physical_parameters().items()}
    with torch.no_grad():
        out["weights"] = {k: v.detach().cpu().numpy().copy() for k, v in model.state_dict().items()}
    return out


__all__ = [
    "InputError",
    "Run",
    "Trajectory",
    "group",
    "make_pose",
    "quaternions_to_rotations",
    "rotations_to_quaternions",
    "load_run",
    "train",
    "rollout",
    "predict",
    "geodesic_error",
    "parameters",
]
