"""The identification's regressor (`models.articulated.fit.regressor`): d r / d pi of the articulated
residual, built from ten coloured forward-mode directions and the FK Jacobian, against the plain
forward-mode Jacobian of the residual in all P directions (`torch.func.jacfwd`), on trees with every
joint type, learned gravity or none, per-DoF damping or none, an MLP potential and learned forces
(which do not depend on pi and must not leak into it)."""

from __future__ import annotations

import pytest
import torch
from test_articulated_joints import mixed_tree, smooth_motion
from test_fused_articulated import _tree

from liedfl_cli.models.articulated.fit import pack, regressor, unpack
from liedfl_cli.models.articulated.model import ArticulatedLieDFLNN

F64 = torch.float64
H = 0.02

CASES = {
    "free root, ball joints, gravity": (lambda: _tree("ball-world"), ("uniform_gravity",), ()),
    "ball joints, parent attitudes, mlp + nn": (lambda: _tree("ball-parent"), ("uniform_gravity", "mlp"), ("nn",)),
    "hinges and a weld, damped": (lambda: _tree("hinge-world"), ("uniform_gravity",), ("rayleigh",)),
    "universal joints, pinned, damped, no gravity": (lambda: mixed_tree("parent", free_root=False), (), ("rayleigh",)),
}


@pytest.mark.parametrize("case", list(CASES))
def test_the_coloured_regressor_equals_the_full_forward_mode_jacobian(case):
    make, potential, forces = CASES[case]
    tree = make()
    m = ArticulatedLieDFLNN(
        tree, H, potential=potential, forces=forces, init_jitter=0.3, seed=5, mlp_width=8, mlp_depth=2
    )
    m.requires_grad_(False)
    samples = m.training_set(smooth_motion(tree, 3, 6, H, seed=4), 6)
    samples.enable_jacobian()
    batch = samples.batch(torch.arange(samples.n), torch.Generator().manual_seed(0), 0)
    with torch.no_grad():
        Jd, mass, rho = (t.detach() for t in m._params())
        d = None if m.dof_damper is None else m.dof_damper.coefficients().detach()
    pi0 = pack(Jd, mass, rho, d)

    def residual(pi):
        return m._batch_residual(batch, unpack(pi, tree.n_bodies)).reshape(-1)

    full = torch.func.jacfwd(residual)(pi0)
    Y = regressor(m, batch, pi0)
    assert Y.shape == full.shape
    scale = float(full.abs().max())
    assert scale > 0 and float((Y - full).abs().max()) <= 1e-10 * scale
    # and it is the residual's linear part: r(pi) = r(pi0) + Y (pi - pi0) for another pi
    with torch.no_grad():
        pi1 = pi0 * (1.0 + 0.1 * torch.linspace(-1.0, 1.0, pi0.shape[0], dtype=F64))
        lhs, rhs = residual(pi1), residual(pi0) + Y @ (pi1 - pi0)
    assert float((lhs - rhs).abs().max()) <= 1e-9 * max(1.0, float(lhs.abs().max()))
