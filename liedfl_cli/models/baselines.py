"""Baselines of the paper, selected with `baseline=<name>` (registry keys = config option names).

`BASELINES[name](cfg, dataset) -> model`; every model follows LieDFLNN's protocol (`window`, `G`,
`h`, `loss`, `rollout`, `components`). Hyper-parameters live in conf/baseline/<name>.yaml; an
unknown key there, or a dataset group the baseline does not model, is a ConfigError.

| name              | model (file)                    | groups          | window (loss)                          |
|-------------------|---------------------------------|-----------------|----------------------------------------|
| glnn_rk4          | GLNN, dopri5 (glnn.py)          | SO(3)           | trajectory (MSE of R entries)          |
| glnn_lie_midpoint | GLNN, implicit Lie midpoint     | SO(3)           | triplet (two-step MSE of R entries)    |
| glnn_lie_heun     | GLNN, explicit Lie-Heun         | SO(3)           | trajectory (MSE of R entries)          |
| euler_dflnn       | DFLNN in ZYX Euler angles       | SO(3)           | triplet (DEL residual + regularity)    |
| euclidean_dflnn   | DFLNN on the entries of (R, p)  | SO(3) or SE(3)  | triplet (DEL residual + regularity)    |
| neural_ode        | 2nd-order MLP field, torchdiffeq| any             | trajectory (MSE of x entries)          |
"""

from __future__ import annotations

from ..errors import ConfigError
from .baseline_common import options, single_so3, use_damping, use_potential

BASELINES: dict = {}


def register(name: str):
    def deco(fn):
        BASELINES[name] = fn
        return fn

    return deco


_GLNN_COMMON = {
    "window": None,
    "potential": "auto",
    "damping": "auto",
    "mlp_width": 64,
    "mlp_depth": 3,
    "init_jitter": 0.1,
}
_GLNN = {
    "glnn_rk4": ("dopri5", "trajectory", {"rtol": 1e-7, "atol": 1e-9, "max_num_steps": 100000}),
    "glnn_lie_midpoint": ("midpoint", "triplet", {"train_newton_iters": 4}),
    "glnn_lie_heun": ("heun", "trajectory", {}),
}


def _glnn_builder(name: str):
    integrator, window, extra = _GLNN[name]

    def build(cfg, dataset):
        from .glnn import GLNN

        single_so3(dataset.group, name)
        opt = options(cfg, {**_GLNN_COMMON, **extra})
        return GLNN(
            dataset.group,
            dataset.h,
            integrator=integrator,
            window=opt.pop("window") or window,
            potential=use_potential(opt, dataset),
            damping=use_damping(opt, cfg),
            **{k: v for k, v in opt.items() if k not in ("potential", "damping")},
            seed=int(cfg.seed),
        )

    return build


for _name in _GLNN:
    register(_name)(_glnn_builder(_name))

_DFLNN = {"potential": "auto", "damping": "auto", "mlp_width": 64, "mlp_depth": 3, "init_jitter": 0.1}


@register("euler_dflnn")
def _euler(cfg, dataset):
    from .euler_dflnn import EulerDFLNN

    single_so3(dataset.group, "euler_dflnn")
    opt = options(cfg, _DFLNN)
    return EulerDFLNN(
        dataset.group,
        dataset.h,
        potential=use_potential(opt, dataset),
        damping=use_damping(opt, cfg),
        mlp_width=opt["mlp_width"],
        mlp_depth=opt["mlp_depth"],
        init_jitter=opt["init_jitter"],
        epsilon=float(cfg.train.epsilon),
        seed=int(cfg.seed),
    )


@register("euclidean_dflnn")
def _euclidean(cfg, dataset):
    from .euclidean_dflnn import EuclideanDFLNN

    G = dataset.group
    if G.n_bodies != 1:
        raise ConfigError(
            f"baseline=euclidean_dflnn models a single rigid body (SO(3) or SE(3)); this dataset's group is {G.name}"
        )
    opt = options(cfg, {**_DFLNN, "potential": "mlp"})
    return EuclideanDFLNN(
        G,
        dataset.h,
        potential=use_potential(opt, dataset),
        damping=use_damping(opt, cfg),
        mlp_width=opt["mlp_width"],
        mlp_depth=opt["mlp_depth"],
        init_jitter=opt["init_jitter"],
        epsilon=float(cfg.train.epsilon),
        seed=int(cfg.seed),
    )


@register("neural_ode")
def _neural_ode(cfg, dataset):
    from .neural_ode import NeuralODE

    opt = options(
        cfg,
        {
            "window": "trajectory",
            "mlp_width": 64,
            "mlp_depth": 3,
            "method": "dopri5",
            "rtol": 1e-7,
            "atol": 1e-9,
            "max_num_steps": 100000,
        },
    )
    return NeuralODE(dataset.group, dataset.h, seed=int(cfg.seed), **opt)


def build_baseline(cfg, dataset):
    name = cfg.baseline.name
    if name not in BASELINES:
        raise ConfigError(f"baseline={name!r} is not available; choose none or one of {sorted(BASELINES) or '[]'}")
    return BASELINES[name](cfg, dataset)
