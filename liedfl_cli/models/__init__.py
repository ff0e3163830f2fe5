"""Models: every model follows the contract of `models.base` and has one config file; a model family
is a package whose `model.py` is its one meaning and whose `engines/` hold the fast paths that must
equal it (docs/architecture.md, "Model families and their engines").

| config (conf/model/)           | class (package/file)                          | kind     | trained on   |
|--------------------------------|-----------------------------------------------|----------|--------------|
| liedflnn                       | LieDFLNN (liedflnn/model.py)                  | implicit | triplets     |
| euler_dflnn                    | EulerDFLNN (euler_dflnn/model.py)             | implicit | triplets     |
| euclidean_dflnn                | EuclideanDFLNN (euclidean_dflnn/model.py)     | implicit | triplets     |
| glnn_rk4 / _lie_heun / _midpoint | GLNN (glnn/model.py) | explicit | trajectories (midpoint: triplets) |
| neural_ode                     | NeuralODE (neural_ode/model.py)               | explicit | trajectories |
| articulated (or liedflnn, kinetic=articulated) | ArticulatedLieDFLNN (articulated/model.py) | implicit | triplets |
| liedflnn, substeps or order    | SubstepModel (liedflnn/substeps.py)           | implicit | triplets     |

Groups: LieDFLNN any product group (the articulated model a kinematic tree); Euler-angle DFLNN and GLNN
SO(3); Euclidean DFLNN SO(3) or SE(3); Neural ODE any; the sub-step wrapper as the model it wraps.

`liedfl_cli.config.factory.build_model(cfg, dataset)` builds the one a config names (asking the class's
`variant_for` first: LieDFLNN on a declared kinematic tree is the articulated model) and gives it the
command's `ExecutionPlan`. Shared by the families: the true-parameter scheme of a synthetic dataset
(true_scheme.py), what a trained model learned for the closing summary (learned_physics.py), the
closed-form MLP derivatives the engines use (mlp_derivatives.py), the DEL loss (del_loss.py), damping
stiffness (stiffness.py) and parameter recovery (recovery.py).
"""
