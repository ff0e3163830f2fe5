"""System identification of the articulated model (`models.articulated.identification`): the residual and the Newton
Jacobian are linear in the ten inertial parameters per body and the damping (so the autodiff regressor is
exact), the log-Cholesky map gives only physical bodies and round-trips, the data determine the base
parameters (true parameters fit, identify() recovers them), metres and millimetres give the same fit, and
a heavy-root chain ends far better than constant velocity."""

from __future__ import annotations

import pytest
import torch

from liedfl_cli.models.articulated import identification as idf
from liedfl_cli.models.articulated.model import (
    ArticulatedLieDFLNN,
    ArticulatedTriplets,
    articulated_parameters,
    true_dof_damping,
)

pytest.importorskip("mujoco")
from liedfl_cli.data.mujoco_chain import chain_dataset

F64 = torch.float64
HEAVY = {"parents": [-1, 0, 1, 2], "joints": ["free", "ball", "ball", "ball"], "heavy_root": True}


def _true_pi(ds, prob) -> torch.Tensor:
    phys = ds.params["physics"]
    t = articulated_parameters(phys, ds.tree.n_bodies)
    J = t["J"]
    Jd = J.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] / 2 * torch.eye(3, dtype=F64) - J
    pi = idf.to_pi(Jd, t["mass"], t["rho"]).reshape(-1)
    d = true_dof_damping(ds.tree, phys)
    return pi if prob.damped is None else torch.cat((pi, d[prob.damped]))


def test_log_cholesky_gives_only_physical_bodies_and_round_trips():
    gen = torch.Generator().manual_seed(0)
    theta = 2.0 * torch.randn(50, 10, generator=gen, dtype=F64)
    pi = idf.log_cholesky_to_pi(theta)
    assert (torch.linalg.eigvalsh(idf.pseudo_inertia(pi)) > 0).all()
    Jd, m, rho = idf.from_pi(pi)
    J = Jd.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None, None] * torch.eye(3, dtype=F64) - Jd
    lam = torch.linalg.eigvalsh(J)
    assert (m > 0).all() and (lam > 0).all() and (lam[:, 2] < lam[:, 0] + lam[:, 1]).all()  # a rigid body
    back = idf.pi_to_log_cholesky(pi)
    assert torch.allclose(back, theta, atol=1e-9)
    assert torch.allclose(idf.to_pi(Jd, m, rho), pi, atol=1e-12 * float(pi.abs().max()))
    # an unphysical body is projected onto the consistent set
    bad = pi.clone()
    bad[:, 0] = -bad[:, 0]
    proj, changed = idf.project_consistent(bad[:5] / bad[:5].abs().amax(-1, keepdim=True))
    assert changed == [0, 1, 2, 3, 4] and (torch.linalg.eigvalsh(idf.pseudo_inertia(proj)) > 0).all()


def test_residual_and_newton_jacobian_are_linear_in_the_parameters():
    ds = chain_dataset(n_trajectories=3, steps=12, seed=3, gravity=9.81, **HEAVY)
    model = ArticulatedLieDFLNN(ds.tree, ds.h, potential=("uniform_gravity",), forces=("rayleigh",), init_jitter=0.3)
    trip = ArticulatedTriplets(model, ds.pose(), 12)
    prob, pi0 = idf.linear_problem(model, trip)
    b = trip.batch(torch.arange(trip.n), torch.Generator().manual_seed(0), 0)
    with torch.no_grad():
        r_model, H_model = model._batch_residual(b), model.newton_jacobian_batch(b)
    # Y pi + r0 and H0 + Hb pi reproduce the model's own residual and Newton Jacobian
    assert torch.allclose(prob.residual(pi0), r_model, rtol=0, atol=1e-10 * float(r_model.abs().max()))
    assert torch.allclose(prob.jacobian(pi0), H_model, rtol=0, atol=1e-10 * float(H_model.abs().max()))
    assert float(prob.r0.abs().max()) < 1e-10 * float(r_model.abs().max())  # nothing else in this model
    gen = torch.Generator().manual_seed(1)
    pi1 = pi0 * (1 + 0.3 * torch.rand(pi0.shape, generator=gen, dtype=F64))
    pi2 = pi0 * (1 + 0.3 * torch.rand(pi0.shape, generator=gen, dtype=F64))

    def r(pi):
        Jd, m, rho, d = prob.split(pi)
        return model._batch_residual(b, (Jd, m, rho, d)).detach()

    def H(pi):
        Jd, m, rho, d = prob.split(pi)
        with idf.explicit_parameters(model, Jd, m, rho, d):
            return model.newton_jacobian_batch(b).detach()

    a, c = 0.7, -1.9  # r(a pi1 + c pi2) = a r(pi1) + c r(pi2): linear, not only affine
    for fn in (r, H):
        mixed = fn(a * pi1 + c * pi2)
        assert torch.allclose(mixed, a * fn(pi1) + c * fn(pi2), rtol=0, atol=1e-10 * float(mixed.abs().max()))
    assert torch.allclose(prob.residual(pi1), r(pi1), rtol=0, atol=1e-10 * float(r(pi1).abs().max()))
    assert torch.allclose(prob.jacobian(pi2), H(pi2), rtol=0, atol=1e-10 * float(H(pi2).abs().max()))
    with torch.no_grad():  # the context manager restored the model
        assert torch.equal(model.newton_jacobian_batch(b), H_model)


def test_true_parameters_fit_and_identify_recovers_the_base_parameters():
    ds = chain_dataset(links=3, joint="ball", n_trajectories=12, steps=60, h=0.02, speed=3.0, seed=7)
    truth = ds.pose()
    model = ArticulatedLieDFLNN(ds.tree, ds.h, forces=("rayleigh",))
    trip = ArticulatedTriplets(model, truth, 60)
    prob, pi0 = idf.linear_problem(model, trip, max_triplets=600)
    pit = _true_pi(ds, prob)
    x_true, x_start = (float(prob.prediction_error(p).pow(2).mean().sqrt()) for p in (pit, pi0))
    assert x_true < 0.01 * x_start, (x_true, x_start)
    info = idf.identifiability(model, trip, prob=prob)
    assert info["rank"] == info["expected_rank"] == prob.P - (ds.tree.n_bodies - 1)
    assert all(g["relative_residual"] < 1e-12 for g in info["ball_gauge_in_null_space"])
    M = float(pit[0 : 10 * prob.B : 10].sum())
    res = idf.identify(model, trip, total_mass=M, max_triplets=600, log=None)
    assert res.lm_rms[-1] <= x_true * 1.0001
    Jd_t, m_t, rho_t, _ = prob.split(pit)
    with torch.no_grad():
        Jd, m, rho = (t.detach() for t in model._params())
    fit, true = idf.base_parameters(ds.tree, Jd, m, rho), idf.base_parameters(ds.tree, Jd_t, m_t, rho_t)
    for key in ("first_moment", "inertia_about_joint"):
        err = float((fit[key] - true[key]).abs().max() / true[key].abs().max())
        assert err < 3e-3, (key, err)
    assert abs(float(fit["subtree_mass"][0]) - M) < 1e-9 * M
    # per-link masses are gauge: not asserted (they need not match)


def _heavy(unit: str):
    ds = chain_dataset(n_trajectories=20, steps=60, seed=31, unit=unit, **HEAVY)
    truth = ds.pose()
    train, test = truth.index(slice(0, 16)), truth.index(slice(16, 20))
    model = ArticulatedLieDFLNN(ds.tree, ds.h, forces=("rayleigh",))
    before = idf.one_step_ratio(model, test)
    # 300 of the 944 training triplets (a strided subset, as identify() takes them): the fit and the
    # comparison hold with margin (2026-11-29: after 0.034 in both units, asserted <= 0.1; m and mm
    # 4.5e-8 apart, asserted <= 1e-6; base parameters 5e-9 apart, asserted <= 1e-6) at 60 % of the time
    # of 600 triplets (after 0.029, 1.6e-7 apart)
    res = idf.identify(model, ArticulatedTriplets(model, train, 60), max_triplets=300, log=None)
    return model, before, idf.one_step_ratio(model, test, tol=1e-12), res


def test_metres_and_millimetres_give_the_same_fit_and_a_heavy_root_beats_constant_velocity():
    model_m, before_m, after_m, res_m = _heavy("m")
    model_mm, before_mm, after_mm, res_mm = _heavy("mm")
    assert before_m > 0.5 and before_mm > 0.5  # the equal-mass start: no better than constant velocity
    assert after_m <= 0.1 and after_mm <= 0.1, (after_m, after_mm)
    assert abs(after_m - after_mm) <= 1e-6 * after_m, (after_m, after_mm)
    with torch.no_grad():
        # per-link masses are gauge (where each fit ends along the null directions depends on its start):
        # compare the base parameters over the total mass, in the tree's length unit
        def base(mod, L):
            Jd, m, rho = (t.detach() for t in mod._params())
            b = idf.base_parameters(mod.tree, Jd, m, rho)
            M = float(m.sum())
            return b["first_moment"] / (M * L), b["inertia_about_joint"] / (M * L * L)

        for a, c in zip(base(model_m, 1.0), base(model_mm, 1e3)):
            assert torch.allclose(a, c, rtol=0, atol=1e-6 * float(a.abs().max())), float((a - c).abs().max())
    assert res_m.rank == res_mm.rank == res_m.n_params - 3
