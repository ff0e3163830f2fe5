"""The articulated model's rollout in native code: the fused engine's implicit DEL step
(`engines.fused`: the same residual, Jacobian, warm start, retraction and Newton-Schulz advance) written
in C++ (`native_step.cpp`), one trajectory at a time, each with the reference Newton loop of
`solvers.newton` (backtracking on ||f||_2, convergence on the full step's max norm, a failed step kept
and flagged). A step costs no Python and no tensor operation: at batch 1 it is the arithmetic of the
step, where the fused engine pays for ~1,800 tensor operations.

Built on first use with the C++ compiler torch.compile uses (`$CXX`, g++, c++ or clang++), once per
source, compiler and CPU, into `$LIEDFL_NATIVE_CACHE` (default `~/.cache/liedfl/native`; written to a
temporary name, then renamed), and loaded with ctypes (`solvers.native_build`, shared with the rigid bodies'
native step, `models.liedflnn.engines.native`). The model uses it (`ArticulatedLieDFLNN.
native_rollout`) on the fused path when `runtime.compile` is not false, no gradient is recorded, the
data are float64 on the CPU, the method is Newton or chord and the model is one it serves (`applies`:
free, ball, hinge and weld joints, gravity, joint damping; reduced or not); otherwise the fused engine.
No compiler, or a build that fails: the fused engine, with one printed line.

Differences from the batched loop, none of them in the results of a converging step: rows never wait
for each other; a singular Jacobian (an exactly zero pivot) ends the row's iteration as a failure
instead of a least-squares step; the poses of g_{k+1} are the ones the fused engine computes, to
rounding (tests/test_native_articulated.py).
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import torch

from ....lie import Pose
from ....lie.joints import _maps as joint_maps
from ....lie.joints import joint_slices
from ....solvers import native_build
from ....solvers.options import SolverOptions
from . import fused

SOURCE = Path(__file__).with_name("native_step.cpp")
_I, _D, _P = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
ARGTYPES = [_I] * 9 + [_P] * 10 + [_I] + [_P] * 3 + [_I] + [_P] * 2 + [_D, _D] + [_I] * 3 + [_P] * 12 + [_I]
"""The C signature of `liedfl_articulated_rollout` (native_step.cpp): 6 sizes, 3 flags, the tree's and the model's
arrays, gravity, damping, h and tol, max_iter / max_halvings / chord, the state and outputs, threads."""
KINDS = {"free": 0, "ball": 1, "hinge": 2, "weld": 3}


def applies(model) -> str | None:
    """None when the native step serves `model` (an `ArticulatedLieDFLNN`), else why not (one line)."""
    why = fused.applies(model)
    if why is not None:
        return why
    if len(model.forces):
        return "joint-space forces"
    if model.potential_coord is not None:
        return "a potential of the coordinates"
    bad = [k for k in model.tree.joint_kinds if k not in KINDS]
    if bad:
        return f"{bad[0]} joints"
    return None


def cache_dir() -> Path:
    return native_build.cache_dir()


def build(cxx: str, folder: Path) -> Path | None:
    """The compiled step for compiler `cxx` in `folder` (built there unless already cached), or None with
    one printed line when the build fails (`solvers.native_build.build`)."""
    return native_build.build(SOURCE, cxx, folder, "the native articulated step")


@functools.lru_cache(maxsize=1)
def library() -> ctypes.CDLL | None:
    """The compiled step, built on first use (module docstring), or None without a compiler or when
    the build fails (said once on stderr): the fused engine then serves."""
    return native_build.load(SOURCE, {"liedfl_articulated_rollout": ARGTYPES}, "the native articulated step")


def _ptr(t: torch.Tensor) -> ctypes.c_void_p:
    return ctypes.c_void_p(t.data_ptr())


class NativeRollout:
    """The constants of one model's native rollout (its parameters read once, detached) and the call."""

    def __init__(self, model, like: torch.Tensor):
        maps = fused.build_maps(model, like)
        tree = model.tree
        dt, dev = like.dtype, like.device  # float64 on the CPU (`usable`)
        self.dtype, self.device = dt, dev
        i64 = torch.int64
        G = tree.group
        self.B, self.n, self.dim, self.m = tree.n_bodies, tree.n_dof, G.dim, G.n_se3
        self.world = int(tree.rotations == "world")
        self.joint_mode, self.reduced = int(maps.joint_mode), int(maps.reduced)
        self.parents = torch.tensor(tree.parents, dtype=i64)
        self.kind = torch.tensor([KINDS[k] for k in tree.joint_kinds], dtype=i64)
        self.col = torch.tensor([s.start for s in joint_slices(tree)], dtype=i64)
        self.row = torch.tensor([s.start for s in G.body_slices()], dtype=i64)
        self.axis = torch.tensor(tree.axes_array(), dtype=dt)[:, 0].contiguous()
        self.offsets = maps.offsets.to(dt).contiguous()
        self.Jd, self.mass, self.rho = (t.to(dt).contiguous() for t in (maps.Jd, maps.mass, maps.rho))
        self.rot_map = maps.rot_map.to(dt).contiguous()
        B = self.B
        self.gravity = int(maps.gamma is not None)
        zeros3 = torch.zeros(3, dtype=dt)
        self.gamma = zeros3 if maps.gamma is None else maps.gamma.to(dt).contiguous()
        self.first_moment = torch.zeros(B, 3, dtype=dt) if maps.first_moment is None else maps.first_moment.to(dt)
        self.first_moment = self.first_moment.contiguous()
        self.gmass = torch.zeros(B, dtype=dt) if maps.gmass is None else maps.gmass.to(dt).contiguous()
        self.damped = int(maps.damping is not None)
        self.damping = torch.zeros(self.n, dtype=dt) if maps.damping is None else maps.damping.to(dt).contiguous()
        self.S0pinv = joint_maps(tree, dt, dev)["S0_pinv"].contiguous()
        self.h = float(model.h)

    def run(self, state: dict, count: int, opts: SolverOptions) -> dict:
        """`count` steps from `state` (updated in place; `start`) -> this chunk's poses and diagnostics, with
        `opts`' tolerance, iterations, halvings and method (newton, or chord: one Jacobian per step)."""
        N, B, m = state["Rc"].shape[0], self.B, self.m
        dt, dev = self.dtype, self.device
        out = {
            "R": torch.empty(N, count, B, 3, 3, dtype=dt, device=dev),
            "p": torch.empty(N, count, m, 3, dtype=dt, device=dev),
            "converged": torch.empty(N, count, dtype=torch.uint8, device=dev),
            "iterations": torch.empty(N, count, dtype=torch.int64, device=dev),
            "residual_norm": torch.empty(N, count, dtype=dt, device=dev),
        }
        lib = library()  # (not kept on the engine: a model that holds it stays deep-copyable)
        assert lib is not None
        rc = lib.liedfl_articulated_rollout(
            ctypes.c_int64(N), ctypes.c_int64(count), ctypes.c_int64(B), ctypes.c_int64(self.n),
            ctypes.c_int64(self.dim), ctypes.c_int64(m), ctypes.c_int64(self.world),
            ctypes.c_int64(self.joint_mode), ctypes.c_int64(self.reduced),
            _ptr(self.parents), _ptr(self.kind), _ptr(self.col), _ptr(self.row), _ptr(self.axis), _ptr(self.offsets),
            _ptr(self.Jd), _ptr(self.mass), _ptr(self.rho), _ptr(self.rot_map), ctypes.c_int64(self.gravity),
            _ptr(self.gamma), _ptr(self.first_moment), _ptr(self.gmass), ctypes.c_int64(self.damped),
            _ptr(self.damping), _ptr(self.S0pinv), ctypes.c_double(self.h), ctypes.c_double(opts.tol),
            ctypes.c_int64(opts.max_iter), ctypes.c_int64(opts.max_halvings), ctypes.c_int64(opts.method == "chord"),
            _ptr(state["Rp"]), _ptr(state["pp"]), _ptr(state["Rc"]), _ptr(state["pc"]), _ptr(state["dof"]),
            _ptr(state["dof_prev"]), _ptr(state["has_prev"]),
            _ptr(out["R"]), _ptr(out["p"]), _ptr(out["converged"]), _ptr(out["iterations"]), _ptr(out["residual_norm"]),
            ctypes.c_int64(torch.get_num_threads()),
        )  # fmt: skip
        if rc != 0:
            raise RuntimeError(f"native articulated rollout returned {rc}")
        return out

    def start(self, g0: Pose, g1: Pose) -> dict:
        """The state of the first step: (g0, g1); the first increment's DoF are computed natively on the
        first call (`has_prev` 2: `mechanics.articulated.step_coordinates`, as `ArticulatedLieDFLNN.
        increment_coordinates`), and there is no previous increment yet."""
        N, n = g0.R.shape[0], self.n
        return {
            "Rp": g0.R.contiguous().clone(),
            "pp": g0.p.contiguous().clone(),
            "Rc": g1.R.contiguous().clone(),
            "pc": g1.p.contiguous().clone(),
            "dof": torch.zeros(N, n, dtype=self.dtype, device=self.device),
            "dof_prev": torch.zeros(N, n, dtype=self.dtype, device=self.device),
            "has_prev": torch.full((N,), 2, dtype=torch.uint8, device=self.device),
        }


def for_model(model, like: torch.Tensor) -> NativeRollout:
    """`model`'s NativeRollout, kept on the model while its step, parameters and buffers are unchanged
    (`solvers.native_build.kept_on_model`): a short rollout does not pay for reading the parameters again
    (~1 ms)."""
    return native_build.kept_on_model(model, like, "_native_rollout", NativeRollout)


def available() -> bool:
    """Whether the native step can run here (a compiler that builds it); builds it on first call."""
    return library() is not None


def usable(model, g: Pose) -> bool:
    """Whether a rollout of `model` from poses like `g` runs natively (module docstring)."""
    return (
        g.R.dtype.is_floating_point
        and torch.finfo(g.R.dtype).bits == 64  # float64: the C++ step's type
        and g.R.device.type == "cpu"
        and not torch.is_grad_enabled()
        and applies(model) is None
        and available()
    )
