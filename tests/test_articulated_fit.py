"""The articulated model's least-squares start (`models.articulated.fit`): the residual is affine in the
physical parameters (so the autodiff regressor is exact), the start is the same in metres and in
millimetres, it lifts a heavy-root chain from worse than constant velocity to far better, and what it
writes is physically consistent."""

from __future__ import annotations

import pytest
import torch

from liedfl_cli.evaluation.metrics import geodesic_error
from liedfl_cli.models.articulated.fit import consistent, least_squares_start, pack, unpack
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN, ArticulatedTriplets
from liedfl_cli.solvers.one_step import constant_velocity_one_step, one_step_predictions
from liedfl_cli.solvers.options import SolverOptions

pytest.importorskip("mujoco")
from liedfl_cli.data.mujoco_chain import chain_dataset

F64 = torch.float64
HEAVY = {"parents": [-1, 0, 1, 2], "joints": ["free", "ball", "ball", "ball"], "heavy_root": True}


def _ratio(model, truth) -> float:
    pred, conv = one_step_predictions(model, truth, SolverOptions())
    assert bool(conv.all())
    cv = constant_velocity_one_step(model.G, truth)
    target = truth.index((slice(None), slice(2, None)))
    return float(geodesic_error(pred.R, target.R).mean() / geodesic_error(cv.R, target.R).mean())


def _fit(unit: str):
    ds = chain_dataset(n_trajectories=20, steps=60, seed=31, unit=unit, **HEAVY)
    truth = ds.pose()
    train, test = truth.index(slice(0, 16)), truth.index(slice(16, 20))
    model = ArticulatedLieDFLNN(ds.tree, ds.h, forces=("rayleigh",))
    before = _ratio(model, test)
    report = least_squares_start(model, ArticulatedTriplets(model, train, 60), epsilon=10.0)
    return model, before, _ratio(model, test), report


def test_pack_unpack_and_consistency():
    gen = torch.Generator().manual_seed(0)
    m = 0.5 + torch.rand(4, generator=gen, dtype=F64)
    rho = torch.randn(4, 3, generator=gen, dtype=F64)
    A = torch.randn(4, 3, 3, generator=gen, dtype=F64)
    Jd = A @ A.transpose(-1, -2)
    d = torch.rand(5, generator=gen, dtype=F64)
    back = unpack(pack(Jd, m, rho, d), 4)
    for a, b in zip(back, (Jd, m, rho, d)):
        assert torch.allclose(a, b, atol=1e-12)
    bad = -Jd  # nothing physical about it
    J, m2, changed = consistent(bad, -m)
    lam = torch.linalg.eigvalsh(J)
    assert (lam > 0).all() and (lam[:, 2] <= lam[:, 0] + lam[:, 1]).all() and (m2 > 0).all()
    assert changed == [0, 1, 2, 3]


def test_the_residual_is_affine_in_the_physical_parameters():
    ds = chain_dataset(n_trajectories=3, steps=12, seed=3, gravity=9.81, **HEAVY)
    model = ArticulatedLieDFLNN(ds.tree, ds.h, potential=("uniform_gravity",), forces=("rayleigh",), init_jitter=0.3)
    trip = ArticulatedTriplets(model, ds.pose(), 12)
    b = trip.batch(torch.arange(trip.n), torch.Generator().manual_seed(0), 0)
    with torch.no_grad():
        Jd, m, rho = (t.detach() for t in model._params())
        d = model.dof_damper.coefficients().detach()
        # the model's own parameters give the model's own residual
        assert torch.allclose(model._batch_residual(b, (Jd, m, rho, d)), model._batch_residual(b), atol=1e-12)
    gen = torch.Generator().manual_seed(1)
    pi1 = pack(Jd, m, rho, d)
    pi2 = pi1 * (1 + 0.3 * torch.rand(pi1.shape, generator=gen, dtype=F64))
    r = lambda pi: model._batch_residual(b, unpack(pi, 4)).detach()
    a = 0.3
    mixed = r(a * pi1 + (1 - a) * pi2)
    assert torch.allclose(mixed, a * r(pi1) + (1 - a) * r(pi2), atol=1e-10 * float(mixed.abs().max()))


def test_the_start_is_unit_free_and_beats_constant_velocity_on_a_heavy_root():
    model_m, before_m, after_m, rep = _fit("m")
    model_mm, before_mm, after_mm, _ = _fit("mm")
    assert before_m > 0.5 and before_mm > 0.5  # the geometric start: no better than constant velocity
    assert after_m < 0.1 and after_mm < 0.1, (after_m, after_mm)  # measured 0.01-0.02
    assert abs(after_m - after_mm) < 0.1 * after_m  # the same fit in millimetres
    # what was written is consistent (the model's parameterisation could not hold anything else)
    J = model_mm.inertia.J().detach()
    lam = torch.linalg.eigvalsh(J)
    assert (lam > 0).all() and (model_mm.mass() > 0).all()
    assert rep.passes == 3 and rep.weighted_rms[-1] < rep.weighted_rms[0]
