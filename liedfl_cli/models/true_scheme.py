"""The discrete scheme with the scene's true parameters (J_d, m, rho, D, the known potential and
known forces such as a PD control).

It is what a perfect LieDFLNN would learn: the yardstick for learned models ("true-parameter
discrete scheme") and the subject of the O(h^3)/O(h^2) consistency checks.
"""

from __future__ import annotations

import torch

from ..lie import ProductGroup
from ..mechanics.forces import RayleighForce
from ..mechanics.scene_physics import body_parameters, true_control, true_potential
from .base import ImplicitModel
from .liedflnn.model import DEFAULT_RESIDUAL, LieDFLNN


def physics_model(G: ProductGroup, h: float, physics: dict, residual: str = DEFAULT_RESIDUAL) -> LieDFLNN:
    """LieDFLNN carrying the true parameters of `physics` (every part frozen).

    Bodies share J/m/rho when a single value is given. Parameters set: J (B, 3, 3), masses (m,)
    and rho (m, 3) of the SE(3) bodies, D (dim, dim) when nonzero, plus the scene's potential and
    control. Its DEL residual vanishes on exact trajectories up to O(h^3) per step.
    """
    J, masses, rhos, D = body_parameters(G, physics)
    forces = ["rayleigh"] if torch.count_nonzero(D) else []
    model = LieDFLNN(G, h, potential="none", forces=forces, residual=residual, init_jitter=0.0)
    model.inertia.set_J(J)
    if G.n_se3:
        assert model.mass is not None and model.rho is not None  # set for SE(3) bodies
        model.mass.set_value(masses[: G.n_se3])
        with torch.no_grad():
            model.rho.copy_(rhos[: G.n_se3])
    if forces:
        rayleigh = model.forces[0]
        assert isinstance(rayleigh, RayleighForce)  # forces == ["rayleigh"]
        rayleigh.D.set_matrix(D)
    model.potential = true_potential(G, physics)
    ctrl = true_control(G, physics)
    if ctrl is not None:
        model.forces.append(ctrl)
    model.requires_grad_(False)
    return model


def true_model(dataset, residual: str = DEFAULT_RESIDUAL) -> ImplicitModel | None:
    """The true-parameter scheme of a synthetic dataset (`physics_model` of its params["physics"]
    on the dataset's group and h; for articulated physics declared with the data's kinematic tree,
    `articulated_true_model`), or None for real recordings.

    `dataset`: a `data.hdf5.Dataset` (read through .params, .group, .h, .tree only; not imported
    here, since models/ may not import data/)."""
    physics = (dataset.params or {}).get("physics")
    if not physics:
        return None
    tree = getattr(dataset, "tree", None)
    if physics.get("kind") == "articulated":
        if tree is None:
            return None
        from .articulated.model import articulated_true_model

        return articulated_true_model(tree, dataset.h, physics, residual)
    if "J" not in physics:
        return None
    return physics_model(dataset.group, dataset.h, physics, residual)
