"""The articulated model's forced DEL residual, one object per derivative mode, chosen once when the model
is built (`model.residual: fast | generic` -> `ArticulatedLieDFLNN.residual_form`), as LieDFLNN's is
(`models/liedflnn/residual.py`): the model's methods delegate, none re-tests a mode string.

    r(g_prev, g, g_next) = const(g_prev, g) + var(g, g_next)     (in the tree's coordinates, (..., dim))
    const = A(g)^T D2 K(FK(g_prev), FK(g)) - h dV + (h/2) C(g)^T F(g_prev, g)
    var   = A(g)^T D1 K(FK(g), FK(g_next)) + (h/2) C(g)^T F(g, g_next)

`ClosedForm` ("fast", the default): every body's SE(3) kinetic derivatives in closed form on FK's world
increments, taken to the coordinates by the FK Jacobian A (`mechanics.articulated`), the Newton Jacobian
A_k^T blockdiag(H_b) A_{k+1} plus the forces'. `Autodiff` ("generic"): autodiff of `model.lagrangian`
through FK, the reference the closed forms are tested against (tests/test_articulated.py). Both hold no
state; `step_terms` gives a rollout step's residual part and Jacobian with what is fixed over the step's
Newton iterations computed once (full coordinates; the model reduces them on a tree with hinges).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch.func import grad

from ...lie import Pose
from ...lie.tree import forward_kinematics
from ...mechanics import articulated as art
from ...mechanics import kinetic
from ...solvers.newton import jacobian

StepTerms = tuple[Callable[[Pose], torch.Tensor], Callable[[Pose], torch.Tensor]]


class ClosedForm:
    """The closed-form residual ("fast"): also what the least-squares start and the increment-stored
    training triplets (`ArticulatedTriplets`) are written for (`closed_form`)."""

    mode = "fast"
    closed_form = True

    def const(self, model, g_prev: Pose, g: Pose, fk: tuple[Pose, torch.Tensor] | None = None) -> torch.Tensor:
        """D2 L_d(g_prev, g) + F^+ + the potential, (..., dim); fk: (FK(g), A(g)) when already known."""
        Gw = art.world_group(model.tree)
        world, A = art.fk_and_jacobian(model.tree, g) if fk is None else fk
        inc_w = Gw.increment(forward_kinematics(model.tree, g_prev), world)
        Jd, m, rho = model._params()
        d2 = kinetic.kinetic_d2(Gw, inc_w, Jd, m, rho, model.h)
        return art.to_coordinates(A, d2) + model.potential_covector(g, world, A) + model.half_force(g_prev, g, at=g)

    def var(self, model, g: Pose, g_next: Pose) -> torch.Tensor:
        """D1 L_d(g, g_next) + F^-, (..., dim)."""
        Gw = art.world_group(model.tree)
        world, A = art.fk_and_jacobian(model.tree, g)
        inc_w = Gw.increment(world, forward_kinematics(model.tree, g_next))
        Jd, m, rho = model._params()
        d1 = kinetic.kinetic_d1(Gw, inc_w, Jd, m, rho, model.h)
        return art.to_coordinates(A, d1) + model.half_force(g, g_next, at=g)

    def jacobian_var(self, model, g: Pose, inc: Pose) -> torch.Tensor:
        """d var(g, g inc exp(delta)) / d delta at 0 in full coordinates, (..., dim, dim):
        A_k^T blockdiag(H_b) A_{k+1} plus the forces'."""
        Gw = art.world_group(model.tree)
        world, A = art.fk_and_jacobian(model.tree, g)
        w_next, A_next = art.fk_and_jacobian(model.tree, model.G.compose(g, inc))
        Jd, m, rho = model._params()
        J = art.newton_jacobian(A, Gw.increment(world, w_next), A_next, Jd, m, rho, model.h)
        Jf = model._force_jacobian(g, inc)
        return J if Jf is None else J + Jf

    def step_terms(self, model, g: Pose, world: Pose, A: torch.Tensor) -> StepTerms:
        """(var(x), its full Jacobian(x)) of a rollout step at g for the increment x, with the parameters
        (detached), g's joint coordinates and joint-velocity map computed once for the step's iterations."""
        tree, G, Gw, h = model.tree, model.G, art.world_group(model.tree), model.h
        with torch.no_grad():
            Jd, m, rho = (t.detach() for t in model._params())
        # joint coordinates and velocity map of g: only the joint-space forces read them
        q, C = (art.joint_coordinates(tree, g), art.joint_velocity_map(tree, g)) if len(model.forces) else (g, None)

        def var(x: Pose) -> torch.Tensor:
            g_next = G.compose(g, x)
            d1 = kinetic.kinetic_d1(Gw, Gw.increment(world, forward_kinematics(tree, g_next)), Jd, m, rho, h)
            r = art.to_coordinates(A, d1)
            if not len(model.forces):
                return r
            tau = model.joint_torque(g, g_next, q=q).detach()
            return r + 0.5 * h * (tau if C is None else (C.transpose(-1, -2) @ tau[..., None])[..., 0])

        def jac(x: Pose) -> torch.Tensor:
            w_next, A_next = art.fk_and_jacobian(tree, G.compose(g, x))
            J = art.newton_jacobian(A, Gw.increment(world, w_next), A_next, Jd, m, rho, h)
            Jf = model._force_jacobian(g, x, fixed=(q, C))
            return J if Jf is None else J + Jf.detach()

        return var, jac


class Autodiff:
    """Autodiff of L_d through FK ("generic"): the reference."""

    mode = "generic"
    closed_form = False

    @staticmethod
    def _d(model, which: int, a: Pose, b: Pose) -> torch.Tensor:
        """Autodiff of L_d(a, b) under the left perturbation of argument `which` (1 or 2)."""
        x = b if which == 2 else a
        eta = x.R.new_zeros(*x.R.shape[:-3], model.G.dim)
        if which == 2:
            return grad(lambda e: model.lagrangian(a, model.G.perturb(b, e)).sum())(eta)
        return grad(lambda e: model.lagrangian(model.G.perturb(a, e), b).sum())(eta)

    def const(self, model, g_prev: Pose, g: Pose, fk: tuple[Pose, torch.Tensor] | None = None) -> torch.Tensor:
        """D2 L_d(g_prev, g) (the potential inside L_d) + F^+, (..., dim); fk is not used."""
        return self._d(model, 2, g_prev, g) + model.half_force(g_prev, g, at=g)

    def var(self, model, g: Pose, g_next: Pose) -> torch.Tensor:
        """D1 L_d(g, g_next) + F^-, (..., dim)."""
        return self._d(model, 1, g, g_next) + model.half_force(g, g_next, at=g)

    def jacobian_var(self, model, g: Pose, inc: Pose) -> torch.Tensor:
        """d var(g, g inc exp(delta)) / d delta at 0 in full coordinates by autodiff, (..., dim, dim)."""
        G = model.G
        zero = inc.R.new_zeros(*inc.R.shape[:-3], G.dim)
        return jacobian(lambda d: self.var(model, g, G.compose(g, G.retract(inc, d))), zero)

    def step_terms(self, model, g: Pose, world: Pose, A: torch.Tensor) -> StepTerms:
        """(var(x), its full Jacobian(x)) of a rollout step at g by autodiff (world, A not used)."""
        G = model.G

        def var(x: Pose) -> torch.Tensor:
            with torch.enable_grad():
                return self.var(model, g, G.compose(g, x))

        def jac(x: Pose) -> torch.Tensor:
            with torch.enable_grad():
                return self.jacobian_var(model, g, x)

        return var, jac


FORMS: dict[str, ClosedForm | Autodiff] = {"fast": ClosedForm(), "generic": Autodiff()}


def residual_form(mode: str) -> ClosedForm | Autodiff:
    """The residual object of `model.residual` (checked by `check_options` before)."""
    return FORMS[mode]
