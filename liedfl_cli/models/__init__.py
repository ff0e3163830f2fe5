"""Models: every model follows the contract of `models.base` and has one config file.

| config (conf/model/)   | class (file)                      | kind     | groups         | trained on |
|------------------------|-----------------------------------|----------|----------------|------------|
| liedflnn               | LieDFLNN (liedflnn.py)            | implicit | any product    | triplets   |
| euler_dflnn            | EulerDFLNN (euler_dflnn.py)       | implicit | SO(3)          | triplets   |
| euclidean_dflnn        | EuclideanDFLNN (euclidean_dflnn.py)| implicit| SO(3) or SE(3) | triplets   |
| glnn_rk4 / _lie_heun / _lie_midpoint | GLNN (glnn.py)      | explicit | SO(3)          | trajectories / triplets |
| neural_ode             | NeuralODE (neural_ode.py)         | explicit | any product    | trajectories |
| liedflnn, model.kinetic=articulated | ArticulatedLieDFLNN (articulated.py) | implicit | a kinematic tree | triplets |
| liedflnn, model.substeps or order | SubstepModel (substeps.py), wraps either | implicit | as wrapped | triplets |

`liedfl_cli.config.factory.build_model(cfg, dataset)` builds the one a config names. Beside them: the
true-parameter scheme of a synthetic dataset (true_scheme.py), the second-order start of an articulated
fit (articulated_fit.py, identification.py), what a trained model learned for the closing summary
(learned_physics.py), and the fused engines (fused_*.py) that must equal the reference paths.
"""
