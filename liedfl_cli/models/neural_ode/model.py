"""Neural ODE baseline (paper Exp 3): a second-order MLP vector field on the raw entries
x = flatten(g) of the configuration (9 per body for R, then 3 per SE(3) body for p):

    x' = v,   v' = f_theta(x, v)   (MLP, GELU, width x depth),

integrated with torchdiffeq (`method`, rtol / atol); with `method: dopri5` on the fused path (the
default, `runtime.fused`) the same dopri5 runs as one autograd node per solve (`solvers.dopri5`, field
`models.neural_ode.engines.fused`), same numbers to rounding. No geometric structure: predicted R are
not orthogonal, and the drift is the result. Training unrolls the ODE over each window from
x_0 with v_0 = (x_1 - x_0)/h and minimises the mean squared error of the predicted positions
x_1..x_L (window "trajectory": the whole training window of each trajectory; "triplet": each
3-pose window of the train split as a length-2 trajectory). Rollout from (g0, g1): the same
start, the ODE solution sampled every h, with g0, g1 in front. Works for any product group.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

import torch

from ...errors import ConfigError
from ...lie import Pose, ProductGroup
from ...mechanics.mlp import MLP
from ...solvers import dopri5
from .. import mlp_derivatives
from ..base import Batch, BuildContext, ExplicitModel, LossOptions, LossParts, config_options
from .engines.fused import MLPField

ADAPTIVE_METHODS = ("dopri5", "dopri8", "bosh3", "fehlberg2", "adaptive_heun")


# rollout state: (x (N, n), v (N, n))
State = tuple[torch.Tensor, torch.Tensor]


@dataclass
class NeuralODEOptions:
    """The Neural ODE's config options (conf/model/neural_ode.yaml): the schema `config/schema.py` checks the
    `model` section's keys and types against (`Model.Options`); `from_config` checks the values."""

    window: str = "trajectory"  # trajectory | triplet
    mlp_width: int = 64
    mlp_depth: int = 3
    method: str = "dopri5"  # any torchdiffeq method
    rtol: float = 1e-7
    atol: float = 1e-9
    max_num_steps: int = 100000
    potential: Any = "auto"  # auto | mlp (the vector field's MLP holds any potential)


class NeuralODE(ExplicitModel):
    """x'' = f_theta(x, v) on the raw entries x (..., n) of a pose, n = 9 B + 3 m."""

    adaptive = True  # torchdiffeq integrates the whole time grid (any method)

    def __init__(
        self,
        G: ProductGroup,
        h: float,
        window: str = "trajectory",
        mlp_width: int = 64,
        mlp_depth: int = 3,
        method: str = "dopri5",
        rtol: float = 1e-7,
        atol: float = 1e-9,
        max_num_steps: int = 100000,
        seed: int = 0,
    ):
        super().__init__()
        self.G, self.h, self.window = G, float(h), window
        self.method, self.rtol, self.atol, self.max_num_steps = method, float(rtol), float(atol), int(max_num_steps)
        self.n = 9 * G.n_bodies + 3 * G.n_se3
        with torch.random.fork_rng():  # seeded nn.Linear initialisation, global RNG untouched
            torch.manual_seed(int(seed))
            self.field = MLP(2 * self.n, self.n, mlp_width, mlp_depth)

    Options = NeuralODEOptions
    OPTIONS = tuple(f.name for f in fields(NeuralODEOptions))

    @classmethod
    def from_config(cls, ctx: BuildContext, **options) -> NeuralODE:
        """`potential` (set for every model of a sweep by the experiment files) may only be auto or mlp:
        the vector field is one MLP, which holds any potential force implicitly."""
        opt = config_options(cls, options, cls.OPTIONS)
        if opt.pop("potential", "auto") not in ("auto", "mlp"):
            raise ConfigError(
                "model=neural_ode: its vector field is one MLP (any potential is in it); "
                "model.potential must be auto or mlp"
            )
        if opt.get("window", "trajectory") not in ("triplet", "trajectory"):
            raise ConfigError(f"model.window={opt['window']!r}: choose one of triplet, trajectory")
        return cls(ctx.group, ctx.h, seed=ctx.seed, **opt)

    def components(self) -> list[str]:
        """["f:MLP(2n->n)", "integrator:<method>"]."""
        return [f"f:MLP({2 * self.n}->{self.n})", f"integrator:{self.method}"]

    def to_x(self, g: Pose) -> torch.Tensor:
        """Pose R (..., B, 3, 3), p (..., m, 3) -> x (..., n) (`ProductGroup.flatten`)."""
        return self.G.flatten(g)

    def from_x(self, x: torch.Tensor) -> Pose:
        """Inverse of `to_x`: x (..., n) -> Pose R (..., B, 3, 3), p (..., m, 3) (R not orthogonalised)."""
        lead, B, m = x.shape[:-1], self.G.n_bodies, self.G.n_se3
        return Pose(x[..., : 9 * B].reshape(*lead, B, 3, 3), x[..., 9 * B :].reshape(*lead, m, 3))

    def integrate_x(self, x0: torch.Tensor, v0: torch.Tensor, steps: int) -> torch.Tensor:
        """(N, n), (N, n) -> x at t = 0, h, ..., steps h: (N, steps+1, n)."""
        from torchdiffeq import odeint

        n = self.n

        def f(t, y):
            return torch.cat((y[:, n:], self.field(y)), -1)

        t = self.h * torch.arange(steps + 1, dtype=x0.dtype, device=x0.device)
        if self.fused_solve():  # the whole solve as one autograd node (solvers/dopri5.py)
            ys = dopri5.odeint(
                MLPField(self.field, n),
                torch.cat((x0, v0), -1),
                t.tolist(),
                MLPField.params_of(self.field),
                self.rtol,
                self.atol,
                self.max_num_steps,
            )
            return ys[..., :n].transpose(0, 1)
        opts = {"max_num_steps": self.max_num_steps} if self.method in ADAPTIVE_METHODS else {}
        ys = odeint(
            f, torch.cat((x0, v0), -1), t, rtol=self.rtol, atol=self.atol, method=self.method, options=opts or None
        )
        return ys[..., :n].transpose(0, 1)

    def fused_solve(self) -> bool:
        """Whether `integrate_x` runs `solvers.dopri5` (one autograd node per solve): the model's path is
        "fused", its method dopri5 and its field a plain MLP; otherwise torchdiffeq (any method)."""
        return self.path == "fused" and self.method == "dopri5" and mlp_derivatives.layers(self.field) is not None

    def loss(self, batch: Batch, opts: LossOptions) -> tuple[torch.Tensor, LossParts]:
        """Unroll each window from (x_0, (x_1 - x_0)/h) -> (mean squared error of the predicted
        x_1..x_L, {"mse": ...}); a triplet is a length-2 window.

        batch: windows R (N, L+1, B, 3, 3), p (N, L+1, m, 3) (`as_sequence`) -> (scalar (), {"mse": scalar ()}).
        """
        x = self.to_x(batch.as_sequence())
        pred = self.integrate_x(x[:, 0], (x[:, 1] - x[:, 0]) / self.h, x.shape[1] - 1)
        mse = ((pred[:, 1:] - x[:, 1:]) ** 2).mean()
        return mse, {"mse": mse}

    # ------------------------------------------------------------------ rollout (solvers.rollout_explicit)
    def initial_state(self, g0: Pose, g1: Pose) -> State:
        """g0, g1 (leading shape (N,)) -> (x0 (N, n), v0 = (x1 - x0)/h (N, n))."""
        x0, x1 = self.to_x(g0), self.to_x(g1)
        return x0, (x1 - x0) / self.h

    def state_pose(self, state: State) -> Pose:
        """(x (N, n), v) -> Pose R (N, B, 3, 3), p (N, m, 3)."""
        return self.from_x(state[0])

    def integrate(self, state: State, steps: int) -> Pose:
        """(x0 (N, n), v0 (N, n)) -> Pose at t = 0, h, ..., steps h: R (N, steps+1, B, 3, 3), p (N, steps+1, m, 3)."""
        return self.from_x(self.integrate_x(state[0], state[1], steps))
