"""LieDFLNN's forced DEL residual, one object per derivative mode, chosen once when the model is built
(`model.residual: fast | generic` -> `LieDFLNN.residual_form`; theseus's habit: a cost function whose
derivatives are fixed at construction, not a mode string re-tested in every method).

    r(g_prev, g, g_next) = const(g_prev, g) + var(g, g_next)
    const = D2 L_d(g_prev, g) + F^+(g_prev, g)  (+ the potential's covector on the closed-form path)
    var   = D1 L_d(g, g_next) + F^-(g, g_next)  (the generic path keeps the potential inside D1 L_d)

`ClosedForm` ("fast", the default): the kinetic terms and the mixed Hessian's blocks in closed form
(`mechanics.kinetic`), the forces' Jacobian by `force_jacobian_xi`. `Autodiff` ("generic"): every
derivative of `model.lagrangian` by autodiff: the independent reference the closed forms are tested
against (tests/test_residual.py). Both take the model as their first argument and hold no state.
"""

from __future__ import annotations

from typing import cast

import torch
from torch.func import grad

from ...lie import Pose
from ...mechanics import kinetic
from ...mechanics.forces import force_jacobian_xi
from ...solvers.newton import jacobian


class ClosedForm:
    """The closed-form residual ("fast")."""

    mode = "fast"

    def const(self, model, g_prev: Pose, g: Pose) -> torch.Tensor:
        """D2 L_d(g_prev, g) + F^+ + the potential's covector, (..., dim)."""
        Jd, m, rho = model._params()
        d2 = kinetic.kinetic_d2(model.G, model.G.increment(g_prev, g), Jd, m, rho, model.h)
        return d2 + model.half_force(g_prev, g) + model.potential_covector(g)

    def var(self, model, g: Pose, g_next: Pose) -> torch.Tensor:
        """D1 L_d(g, g_next) + F^- (the potential is in `const`), (..., dim)."""
        Jd, m, rho = model._params()
        d1 = kinetic.kinetic_d1(model.G, model.G.increment(g, g_next), Jd, m, rho, model.h)
        return d1 + model.half_force(g, g_next)

    def jacobian_var(self, model, g: Pose, inc: Pose) -> torch.Tensor:
        """d var(g, g inc exp(delta)) / d delta at 0, (..., dim, dim): the kinetic mixed Hessian (block
        diagonal over bodies) plus (h/2) dF/d xi~ . d xi~/d delta for each force."""
        G = model.G
        Jd, m, rho = model._params()
        blocks = kinetic.mixed_hessian_blocks(G, inc, Jd, m, rho, model.h)
        J = inc.R.new_zeros(*inc.R.shape[:-3], G.dim, G.dim)
        for s, b in zip(G.body_slices(), blocks):
            J[..., s, s] = b
        if len(model.forces):
            xi = kinetic.velocity_estimate(G, inc, model.h)
            dxi = kinetic.velocity_estimate_jacobian(G, inc, model.h)
            # a Tensor, not the int 0 that sum() gives for no forces (there is at least one)
            dF = cast(torch.Tensor, sum(force_jacobian_xi(f, g, xi) for f in model.forces))
            J = J + 0.5 * model.h * (dF @ dxi)
        return J

    def hessian_blocks(self, model, g: Pose, g_next: Pose) -> list[torch.Tensor]:
        """Each body's diagonal block H_b of the mixed Hessian at (g, g_next), (..., n_b, n_b)."""
        Jd, m, rho = model._params()
        return kinetic.mixed_hessian_blocks(model.G, model.G.increment(g, g_next), Jd, m, rho, model.h)


class Autodiff:
    """The generic residual ("generic"): derivatives of `model.lagrangian` by autodiff."""

    mode = "generic"

    def const(self, model, g_prev: Pose, g: Pose) -> torch.Tensor:
        eta = g.R.new_zeros(*g.R.shape[:-3], model.G.dim)
        d2 = grad(lambda e: model.lagrangian(g_prev, model.G.perturb(g, e)).sum())(eta)
        return d2 + model.half_force(g_prev, g)

    def var(self, model, g: Pose, g_next: Pose) -> torch.Tensor:
        eta = g.R.new_zeros(*g.R.shape[:-3], model.G.dim)
        d1 = grad(lambda e: model.lagrangian(model.G.perturb(g, e), g_next).sum())(eta)
        return d1 + model.half_force(g, g_next)

    def jacobian_var(self, model, g: Pose, inc: Pose) -> torch.Tensor:
        G = model.G
        zero = inc.R.new_zeros(*inc.R.shape[:-3], G.dim)
        return jacobian(lambda d: self.var(model, g, G.compose(g, G.retract(inc, d))), zero)

    def hessian_blocks(self, model, g: Pose, g_next: Pose) -> list[torch.Tensor]:
        H = model.mixed_hessian_autodiff(g, g_next)
        return [H[..., s, s] for s in model.G.body_slices()]


FORMS: dict[str, ClosedForm | Autodiff] = {"fast": ClosedForm(), "generic": Autodiff()}
"""`model.residual` option -> its residual object (the option names are these keys)."""


def residual_form(mode: str) -> ClosedForm | Autodiff:
    """The residual object of `model.residual=mode` (ValueError naming the choices otherwise)."""
    if mode not in FORMS:
        raise ValueError(f"residual must be one of {', '.join(FORMS)}, got {mode!r}")
    return FORMS[mode]
