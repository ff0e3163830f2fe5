"""Fused hot paths of LieDFLNN, part 6 (see `models.liedflnn.engines.core`): the rollout of a single SO(3) or SE(3)
body, or of any product of bodies SE(3)^m x SO(3)^n (constant Rayleigh damping, a learned force), in native code.

The step of `engines.scalar` / `engines.columns` (one SO(3) body) and of the row layout's `FusedStep` (every
other product) written in C++ (`native_body.cpp`), one trajectory at a time, each with the reference Newton
loop of `solvers.newton` (backtracking on ||r||_2, convergence on the full step's max norm, a failed step kept
and flagged): no Python and no tensor operation per step, so a step costs its arithmetic (~1.4 µs at batch 1
with a 10 x 2 MLP potential on SO(3), ~2.7 µs on SE(3)) where the Python floats of `engines.scalar` pay
~60 µs and the row layout 0.4-1.8 ms. Built on first use (`solvers.native_build`, the articulated step's
machinery) and kept per machine.

Serves (`applies`) the fused path of a LieDFLNN of one body or a product of bodies with constant Rayleigh
damping and at most one learned force (`NNForce`, GELU or tanh layers; batches up to `FORCE_ROWS`), a
potential that is none, an MLP of Linear layers with exact GELU or tanh
activations, gravity (declared or learned, `GravityPotential` / `UniformGravityPotential`) or a sum of those
with at most one MLP (a single SO(3) body with an MLP: batches up to the size where the column layout's
batched products overtake it, `MLP_ROWS`); float64 poses on the CPU (a rollout records no gradient on any
engine), a plan that allows native code (`ExecutionPlan.wants_native`: not under `runtime.compile=false`),
and a C++ compiler that builds it. Otherwise the torch engines (`engines/choose.py`): interaction
potentials, control forces and configuration-dependent damping, float32, GPUs.

One difference from the other engines, in no converging step: an exactly singular Jacobian takes no step
(the step is flagged as failed) where the reference takes a least-squares step.

    applies(model, g0)                       whether a rollout takes this path
    rollout(model, g0, g1, steps, opts)      `solvers.rollout.rollout_implicit` for those models
"""

from __future__ import annotations

import ctypes
import functools
import math
import time
from pathlib import Path
from typing import Literal

import torch

from ....lie import Pose
from ....lie.batched import HISTORY
from ....mechanics.forces import NNForce, RayleighForce
from ....mechanics.potentials import GravityPotential, MLPPotential, SumPotential, UniformGravityPotential
from ....solvers import native_build, newton
from ....solvers.options import SolverOptions
from ....solvers.rollout import Rollout
from ... import mlp_derivatives
from . import columns as fused_columns
from .rollout import rollout_maps
from .scalar import activation_name

SOURCE = Path(__file__).with_name("native_body.cpp")
_I, _D, _P = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
_POTENTIAL = [_I, _P, _P, _P, _P, _P, _P, _I, _P, _P, _P]  # `_NativePotential.args`
_DIAGNOSTICS = [_P, _P, _P, _I]  # converged, iterations, residual norm, threads
ARGTYPES = {  # ... the pose(s), hist, hist_len, the output pose(s), _DIAGNOSTICS
    "liedfl_so3_rollout": [_I, _I, _P, _P, _P, *_POTENTIAL, _D, _I, _I, _P, _P, _P, _P, *_DIAGNOSTICS],
    "liedfl_product_rollout": [_I, _I, _I, _I, _P, _P, _P, _P, _P, _P, _I, _P, _D, *_POTENTIAL]
    + [_I, _P, _P, _P, _P, _P, _P, _P, _D]  # the learned force's network (`_NativeForce.args`)
    + [_D, _I, _I, _P, _P, _P, _P, _P, _P, _P, _P, *_DIAGNOSTICS],
}
"""The C signatures (native_body.cpp): N and count, the body's maps, the potential, the tolerance, max_iter and
max_halvings, the state and outputs, threads."""
ACTIVATIONS = {"gelu": 0, "tanh": 1}
MLP_ROWS = 2000
MLP_WEIGHTS = 200
"""With an MLP potential the native step computes the network for one trajectory at a time, where the column
layout of an SO(3) body (`engines.columns`) multiplies whole batches at once: past some batch size the columns
are faster. The native step serves an SO(3) body up to MLP_ROWS x sqrt(MLP_WEIGHTS / weights) x threads
trajectories: measured crossovers (idle, µs per trajectory-step, native / columns; docs/benchmarks.md "The
native rigid-body step", record docs/bench/native_body_2026-12-07.json): one thread, 10 x 2 (200 weights)
0.66 / 0.85 at 1,000 and 0.66 / 0.61 at 2,000, 32 x 3 (2,368) 1.89 / 6.02 at 100 and 1.87 / 1.39 at 1,000,
64 x 3 (8,832) 3.96 / 6.88 at 100 and 3.96 / 2.33 at 1,000; two threads, 10 x 2 0.34 / 0.35 at 8,000, 32 x 3
0.96 / 1.46 at 1,000 and 0.95 / 0.92 at 2,000. Without an MLP, and for every other group (whose torch engine
is the row layout), it serves every batch (1.2-780x the torch engine from 1 to 16,000 trajectories)."""
FORCE_ROWS = 300
FORCE_WEIGHTS = 2500
"""With a learned force (`NNForce`) every Newton iteration evaluates the network and its Jacobian in xi~ (forward
mode, dim columns) one trajectory at a time, where the row layout multiplies whole batches: the native step
serves up to FORCE_ROWS x sqrt(FORCE_WEIGHTS / weights) x threads trajectories (measured, idle, one thread, a
32 x 3 force, µs per trajectory-step native / rows: SO(3) 11.3 / 19.0 at 100 and 11.2 / 10.6 at 300, SE(3)
21.3 / 40.6 and 21.1 / 21.4, SE(3) x SO(3) 22.9 / 50.4 and 22.6 / 29.6; at batch 1 93-110x; record
docs/bench/native_body_nn_2026-12-07.json)."""
CHUNK_ROW_STEPS = 400_000
"""Trajectory-steps per call into the native code (~0.5 s): progress is reported and signals are handled
between calls."""


def _potential_terms(potential) -> tuple[list | None, list] | None:
    """(the MLP's layers or None, the gravity terms) of a potential the native step computes, else None."""
    terms = list(potential.terms) if isinstance(potential, SumPotential) else [] if potential is None else [potential]
    layers, gravity = None, []
    for term in terms:
        if isinstance(term, MLPPotential) and layers is None:
            layers = mlp_derivatives.layers(term.net)
            if layers is None or any(activation_name(act) is None for _, act in layers[:-1]):
                return None
        elif isinstance(term, (GravityPotential, UniformGravityPotential)):
            gravity.append(term)
        else:
            return None
    return layers, gravity


def applies(model, g0: Pose) -> bool:
    """Whether `model`'s rollout from g0 takes this path (module docstring); builds the native step on the
    first call that needs it."""
    return (
        (fused_columns.single_linear_so3(model, g0) or _product(model, g0))
        and g0.R.dtype.is_floating_point
        and torch.finfo(g0.R.dtype).bits == 64
        and g0.R.device.type == "cpu"
        and model.plan.wants_native()
        and _serves_batch(model, g0)
        and library() is not None
    )


def _product(model, g0: Pose) -> bool:
    """A LieDFLNN on the fused path of any product of bodies (one SE(3) body, SE(3) x SO(3)^n, SO(3)^n, ...)
    with constant Rayleigh damping and at most one learned force (`NNForce` with GELU or tanh layers), poses
    (T, B, 3, 3) / (T, m, 3)."""
    return model._fused() and g0.R.dim() == 4 and _force_layers(model) is not False


def _force_layers(model) -> list | None | Literal[False]:
    """The layers of the model's one `NNForce` (None without one; False where a force is neither that nor
    constant Rayleigh damping, or there are two)."""
    nets = [f for f in model.forces if isinstance(f, NNForce)]
    if len(nets) > 1 or any(not isinstance(f, (RayleighForce, NNForce)) for f in model.forces):
        return False
    if not nets:
        return None
    layers = mlp_derivatives.layers(nets[0].net)
    if layers is None or len(layers) < 2 or any(activation_name(act) is None for _, act in layers[:-1]):
        return False
    return layers


def _serves_batch(model, g0: Pose) -> bool:
    """Whether the potential is one the native step computes and g0's trajectories are few enough for it
    (`MLP_ROWS`, `FORCE_ROWS`)."""
    terms = _potential_terms(model.potential)
    if terms is None:
        return False
    force = _force_layers(model)
    if isinstance(force, list):  # a learned force: its Jacobian per trajectory against the row layout's batches
        weights = sum(lin.weight.numel() for lin, _ in force)
        return g0.R.shape[0] <= FORCE_ROWS * math.sqrt(FORCE_WEIGHTS / weights) * torch.get_num_threads()
    if terms[0] is None or not fused_columns.single_linear_so3(model, g0):
        return True  # (without a column layout the torch engine is the row layout: slower at any batch)
    rows = g0.R.shape[0]
    weights = sum(lin.weight.numel() for lin, _ in terms[0])
    limit = MLP_ROWS * math.sqrt(MLP_WEIGHTS / weights) * torch.get_num_threads()
    return rows <= limit


@functools.lru_cache(maxsize=1)
def library() -> ctypes.CDLL | None:
    """The compiled step, built on first use, or None without a compiler or when the build fails (said once
    on stderr): the torch engines then serve."""
    return native_build.load(SOURCE, ARGTYPES, "the native rigid-body step")


def _ptr(t: torch.Tensor) -> ctypes.c_void_p:
    return ctypes.c_void_p(t.data_ptr())


class _NativePotential:
    """The potential's constants for the native step: the MLP's hidden layers (weights, the same transposed,
    biases, activations; input widths[0] = the pose's 9 or 12 entries) and output weights times -h, and the
    gravity terms -h dV = (a x (R^T f), m R^T f) (the potentials' `left_gradient`; m on SE(3) only)."""

    def __init__(self, model, dt: torch.dtype):
        terms = _potential_terms(model.potential)
        assert terms is not None  # `applies`
        layers, gravity = terms
        h, i64 = float(model.h), torch.int64
        zero = torch.zeros(1, dtype=dt)
        hidden = layers[:-1] if layers else []
        self.layers = len(hidden)
        inputs = 9 * model.G.n_bodies + 3 * model.G.n_se3  # the MLP reads flatten(g): rotations, then positions
        self.width = torch.tensor([inputs] + [lin.out_features for lin, _ in hidden], dtype=i64)
        flat = lambda ts: torch.cat([t.detach().to(dt).reshape(-1) for t in ts]) if ts else zero
        self.weights = flat([lin.weight for lin, _ in hidden])
        self.weights_t = flat([lin.weight.T for lin, _ in hidden])
        self.biases = flat([zero.new_zeros(lin.out_features) if lin.bias is None else lin.bias for lin, _ in hidden])
        self.act = torch.tensor([ACTIVATIONS[activation_name(act) or ""] for _, act in hidden] or [0], dtype=i64)
        self.out = (-h * layers[-1][0].weight.detach().to(dt)[0]).contiguous() if layers else zero
        B, m = model.G.n_bodies, model.G.n_se3
        a_, f_, m_ = [], [], []
        for term in gravity:  # per body b: a_b (first moment) and, on SE(3), m_b; along f
            if isinstance(term, GravityPotential):
                masses = term.gravity * term.masses
                a, f = masses[:, None] * term.rhos, torch.tensor([0.0, 0.0, 1.0], dtype=dt)
            else:
                masses = torch.cat((term.mass(), term.gravity.new_zeros(B - m))) if m else term.gravity.new_zeros(B)
                a, f = term.first_moments(), term.field()
            masses = torch.where(torch.arange(B) < m, masses, torch.zeros_like(masses))  # SO(3) bodies: no v part
            a_.append(-h * a.detach().to(dt).reshape(B, 3))
            f_.append(f.detach().to(dt))
            m_.append(-h * masses.detach().to(dt).reshape(B))
        self.n_grav = len(a_)
        self.grav_a = torch.stack(a_).contiguous() if a_ else zero.new_zeros(1, B, 3)
        self.grav_f = torch.stack(f_).contiguous() if f_ else zero.new_zeros(1, 3)
        self.grav_m = torch.stack(m_).contiguous() if m_ else zero.new_zeros(1, B)

    def args(self) -> list:
        """Its arguments of the C functions, from `layers` to `grav_m`."""
        return [
            self.layers, _ptr(self.width), _ptr(self.weights), _ptr(self.weights_t), _ptr(self.biases),
            _ptr(self.act), _ptr(self.out), self.n_grav, _ptr(self.grav_a), _ptr(self.grav_f), _ptr(self.grav_m),
        ]  # fmt: skip


def _outputs(like: torch.Tensor, N: int, count: int, B: int, m: int | None) -> dict:
    """The native step's outputs for `count` steps of N trajectories of B bodies (m SE(3): positions; None: an
    SO(3) body's step, no positions)."""
    out = {
        "R": like.new_empty(N, count, B, 3, 3),
        "converged": like.new_empty(N, count, dtype=torch.uint8),
        "iterations": like.new_empty(N, count, dtype=torch.int64),
        "residual_norm": like.new_empty(N, count),
    }
    if m is not None:
        out["p"] = like.new_empty(N, count, m, 3)
    return out


def _state_and_output_args(state: dict, out: dict) -> list:
    poses = [_ptr(state["R"])] + ([_ptr(state["p"])] if "p" in out else [])
    results = [_ptr(out["R"])] + ([_ptr(out["p"])] if "p" in out else [])
    diagnostics = [_ptr(out["converged"]), _ptr(out["iterations"]), _ptr(out["residual_norm"])]
    return [*poses, _ptr(state["hist"]), _ptr(state["hist_len"]), *results, *diagnostics, torch.get_num_threads()]


class NativeSO3:
    """The constants of one SO(3) model's native rollout (its parameters read once, detached) and the call."""

    product = False  # (the linear SO(3) step: no positions, no g_{k-1})

    def __init__(self, model, like: torch.Tensor):
        dt = like.dtype
        maps = rollout_maps(model)
        assert maps.linear is not None  # `applies`: a linear residual
        # rows applied to W.flatten(): residual (3, 9), Jacobian (9, 9), constant part (3, 9)
        self.F, self.JT, self.C = (m.detach().to(dt).T.contiguous() for m in maps.linear)
        self.potential = _NativePotential(model, dt)

    def run(self, state: dict, count: int, opts: SolverOptions) -> dict:
        """`count` steps from `state` (updated in place; `rollout`) -> this chunk's rotations (N, count, 3, 3)
        and per-step diagnostics, with `opts`' tolerance, iterations and halvings."""
        out = _outputs(self.F, state["R"].shape[0], count, 1, None)
        lib = library()  # (not kept on the engine: a model that holds it stays deep-copyable)
        assert lib is not None
        step_tol = max(opts.tol, newton.ROUNDING_ULPS * torch.finfo(self.F.dtype).eps)  # rotations: entries <= 1
        rc = lib.liedfl_so3_rollout(
            state["R"].shape[0], count, _ptr(self.F), _ptr(self.JT), _ptr(self.C), *self.potential.args(),
            step_tol, opts.max_iter, opts.max_halvings, *_state_and_output_args(state, out),
        )  # fmt: skip
        if rc != 0:
            raise RuntimeError(f"native SO(3) rollout returned {rc}")
        return out


class _NativeForce:
    """The learned force's network for the native step (`Net` in native_body.cpp): hidden layers as
    `_NativePotential`'s (input flatten(g) then xi~), the output layer's weights (dim, width) and bias, the
    force's scale; no layers (0) without one."""

    def __init__(self, model, dt: torch.dtype):
        layers = _force_layers(model)
        zero = torch.zeros(1, dtype=dt)
        self.layers, self.scale = 0, 0.0
        self.width = torch.zeros(1, dtype=torch.int64)
        self.weights = self.weights_t = self.biases = self.out_w = self.out_b = zero
        self.act = self.width
        if not isinstance(layers, list):  # (no learned force: `applies` refused a False)
            return
        force = next(f for f in model.forces if isinstance(f, NNForce))
        hidden, (last, _) = layers[:-1], layers[-1]
        self.layers, self.scale = len(hidden), float(force.scale)
        widths = [hidden[0][0].in_features] + [lin.out_features for lin, _ in hidden]
        self.width = torch.tensor(widths, dtype=torch.int64)
        flat = lambda ts: torch.cat([t.detach().to(dt).reshape(-1) for t in ts])
        self.weights = flat([lin.weight for lin, _ in hidden])
        self.weights_t = flat([lin.weight.T for lin, _ in hidden])
        self.biases = flat([zero.new_zeros(lin.out_features) if lin.bias is None else lin.bias for lin, _ in hidden])
        self.act = torch.tensor([ACTIVATIONS[activation_name(act) or ""] for _, act in hidden], dtype=torch.int64)
        self.out_w = last.weight.detach().to(dt).contiguous()
        self.out_b = zero.new_zeros(last.out_features) if last.bias is None else last.bias.detach().to(dt).contiguous()

    def args(self) -> list:
        return [
            self.layers, _ptr(self.width), _ptr(self.weights), _ptr(self.weights_t), _ptr(self.biases),
            _ptr(self.act), _ptr(self.out_w), _ptr(self.out_b), self.scale,
        ]  # fmt: skip


class NativeProduct:
    """The constants of the native rollout of a product of bodies SE(3)^m x SO(3)^(B-m) (one SE(3) body
    included; its parameters read once, detached) and the call."""

    product = True  # (the product step: positions (possibly none) and g_{k-1})

    def __init__(self, model, like: torch.Tensor):
        dt = like.dtype
        G, maps = model.G, rollout_maps(model)
        self.B, self.m = G.n_bodies, G.n_se3
        # rows applied to W_b.flatten(): the kinetic d1 and d2 rotational parts (B, 3, 9), the rotational Hessian
        # blocks (B, 9, 9), the SE(3) bodies' kinetic blocks (m, 36, 9)
        maps_ = (maps.d1, maps.d2, maps.hess)
        self.d1, self.d2, self.hess = (t.detach().to(dt).transpose(1, 2).contiguous() for t in maps_)
        P = maps.P
        zero = self.d1.new_zeros(1)
        block = maps.se3_block
        self.se3_block = block.detach().to(dt).transpose(1, 2).contiguous() if block is not None else zero
        self.rho = P.rho.detach().to(dt).contiguous() if self.m else zero
        self.s = (P.mass.detach().to(dt) / float(model.h)).contiguous() if self.m else zero
        self.h = float(model.h)
        self.damped = P.D is not None
        self.D = P.D.detach().to(dt).contiguous() if P.D is not None else zero
        self.potential = _NativePotential(model, dt)
        self.force = _NativeForce(model, dt)

    def run(self, state: dict, count: int, opts: SolverOptions) -> dict:
        """`count` steps from `state` (updated in place; `rollout`) -> this chunk's rotations (N, count, B, 3, 3),
        positions (N, count, m, 3) and per-step diagnostics; the step tolerance is scaled by each iterate's
        translations in the C++ (`solvers.newton.step_tolerance`)."""
        out = _outputs(self.d1, state["R"].shape[0], count, self.B, self.m)
        lib = library()
        assert lib is not None
        rc = lib.liedfl_product_rollout(
            state["R"].shape[0], count, self.B, self.m, _ptr(self.d1), _ptr(self.d2), _ptr(self.hess),
            _ptr(self.se3_block), _ptr(self.rho), _ptr(self.s), int(self.damped), _ptr(self.D), self.h,
            *self.potential.args(), *self.force.args(), opts.tol, opts.max_iter, opts.max_halvings,
            _ptr(state["R_prev"]), _ptr(state["p_prev"]), *_state_and_output_args(state, out),
        )  # fmt: skip
        if rc != 0:
            raise RuntimeError(f"native product rollout returned {rc}")
        return out


def for_model(model, like: torch.Tensor) -> NativeSO3 | NativeProduct:
    """`model`'s native engine, kept on the model while its step, parameters and buffers are unchanged
    (`solvers.native_build.kept_on_model`)."""
    # one SO(3) body with a linear residual (no learned force): the linear step; else the product's
    single = model.G.n_bodies == 1 and not model.G.n_se3 and _force_layers(model) is None
    make = NativeSO3 if single else NativeProduct
    return native_build.kept_on_model(model, like, "_native_body", make)


@torch.no_grad()
def rollout(model, g0: Pose, g1: Pose, steps: int, opts: SolverOptions, progress=None) -> Rollout:
    """`rollout_implicit(model, ...)` in native code (`applies(model, g0)` must hold)."""
    t0 = time.perf_counter()
    N = g0.R.shape[0]
    like = g0.R
    engine = for_model(model, like)
    B, m = model.G.n_bodies, model.G.n_se3
    inc = model.G.increment(g0, g1)
    hist = like.new_zeros(N, HISTORY, 9 * B + 3 * m)  # increments: rotations, then the SE(3) translations
    hist[:, 0, : 9 * B] = inc.R.reshape(N, 9 * B)
    hist[:, 0, 9 * B :] = inc.p.reshape(N, 3 * m)
    hist_len = like.new_ones(N, dtype=torch.int64)
    state = {"R": g1.R.reshape(N, 9 * B).contiguous().clone(), "hist": hist, "hist_len": hist_len}
    if engine.product:  # positions, and g_{k-1} for a learned force
        state["p"] = g1.p.reshape(N, 3 * m).contiguous().clone()
        state["R_prev"] = g0.R.reshape(N, 9 * B).contiguous().clone()
        state["p_prev"] = g0.p.reshape(N, 3 * m).contiguous().clone()
    run = lambda count: engine.run(state, count, opts)
    chunks = native_build.run_in_chunks(run, N, steps, CHUNK_ROW_STEPS, progress)
    cat = _outputs(like, N, 0, B, m if engine.product else None)
    if chunks:
        cat = {key: torch.cat([c[key] for c in chunks], 1) for key in chunks[0]}
    R = torch.cat((g0.R[:, None], g1.R[:, None], cat["R"]), 1)  # (N, steps + 1, B, 3, 3)
    p = (
        torch.cat((g0.p[:, None], g1.p[:, None], cat["p"]), 1)
        if engine.product
        else g0.p.new_zeros(N, R.shape[1], 0, 3)
    )
    return Rollout(
        Pose(R, p), cat["converged"].bool(), cat["iterations"], cat["residual_norm"], time.perf_counter() - t0
    )
