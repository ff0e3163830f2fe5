"""Multibody figures (issue 38): every body gets its own panel (or heat-map row), the learned model is
labelled with its kind, the tree's skeleton is drawn, and `liedfl eval` of an articulated run writes
them. Structure only: no pixels are compared."""

from __future__ import annotations

import numpy as np
import pytest

from helpers import train_run
from liedfl_cli.display import plots


def _poses(T=2, S=12, B=4, m=4, seed=0, noise=0.0) -> plots.ArrayPose:
    """Random rotations (T, S, B, 3, 3) and positions (T, S, m, 3), optionally perturbed."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    R = Rotation.from_rotvec(rng.normal(size=(T * S * B, 3))).as_matrix().reshape(T, S, B, 3, 3)
    p = rng.normal(size=(T, S, m, 3))
    if noise:
        R = R @ Rotation.from_rotvec(noise * rng.normal(size=(T * S * B, 3))).as_matrix().reshape(T, S, B, 3, 3)
        p = p + noise * rng.normal(size=p.shape)
    return plots.ArrayPose(R, p)


def _errors(B: int, m: int):
    truth = _poses(B=B, m=m)
    preds = {"model": _poses(B=B, m=m, noise=1e-3), "true_scheme": _poses(B=B, m=m, noise=1e-4)}
    return truth, preds, {k: plots.body_errors(truth, v) for k, v in preds.items()}


def _names(kind: str, B: int) -> dict[str, str]:
    return {**plots.display_names(["model", "true_scheme"]), "model": plots.model_label("liedflnn", kind, B)}


def test_model_label_names_the_kind_on_multibody_data_only():
    assert plots.model_label("liedflnn", "articulated", 4) == "LieDFLNN (articulated)"
    assert plots.model_label("liedflnn", "per_body", 3) == "LieDFLNN (per-body)"
    assert plots.model_label("liedflnn", "per_body", 1) == "liedflnn"
    assert plots.model_label("glnn_rk4", "per_body", 3) == "glnn_rk4"


def test_body_errors_are_per_body_and_skip_non_finite_samples():
    truth, preds, errors = _errors(B=4, m=1)
    e = errors["model"]
    assert e["geodesic_error"].shape == (4, 12) and e["position_error"].shape == (1, 12)
    assert np.allclose(plots.body_errors(truth, truth)["geodesic_error"], 0.0, atol=1e-6)
    bad = plots.ArrayPose(preds["model"].R.copy(), preds["model"].p)
    bad.R[0, 5:, 2] = np.nan  # trajectory 0 fails at sample 5 on body 2: the mean is over trajectory 1 there
    g = plots.body_errors(truth, bad)["geodesic_error"]
    assert np.isfinite(g).all()


@pytest.mark.parametrize("kind", ["articulated", "per_body"])
def test_small_multiples_have_one_panel_per_body_and_the_kind_in_the_legend(kind):
    _, _, errors = _errors(B=5, m=5)
    names = _names(kind, 5)
    body_names = [f"link{b}" for b in range(5)]
    fig = plots.draw_body_errors(errors, 0.05, body_names, names=names)
    panels = [ax for ax in fig.axes if ax.get_visible()]
    assert len(panels) == 5
    assert [ax.get_title() for ax in panels] == [f"body {b}: link{b}" for b in range(5)]
    labels = [t.get_text() for leg in fig.legends for t in leg.get_texts()]
    assert names["model"] in labels and "true scheme" in labels
    assert all(ax.get_xlabel() in ("", "time [s]") for ax in panels)
    assert "[rad]" in panels[0].get_ylabel()
    fig = plots.draw_body_errors(errors, 0.05, body_names, "position_error", names, length_unit="mm")
    assert len([ax for ax in fig.axes if ax.get_visible()]) == 5 and "[mm]" in fig.axes[0].get_ylabel()
    plots.plt.close("all")


def test_many_bodies_give_a_heat_map_with_one_row_per_body():
    B = plots.HEATMAP_ABOVE + 4
    _, _, errors = _errors(B=B, m=1)
    names = _names("per_body", B)
    fig = plots.draw_body_errors(errors, 0.05, [f"joint{b}" for b in range(B)], names=names)
    maps = [ax for ax in fig.axes if ax.images]
    assert [ax.get_title() for ax in maps] == ["LieDFLNN (per-body)", "true scheme"]
    for ax in maps:
        assert ax.images[0].get_array().shape[0] == B
        assert [t.get_text() for t in ax.get_yticklabels()] == [f"{b} joint{b}" for b in range(B)]
    assert any("[rad]" in ax.get_ylabel() for ax in fig.axes)  # the colour bar's unit
    plots.plt.close("all")


def test_skeleton_joins_every_body_to_its_parent_in_3d_and_two_projections():
    parents = (-1, 0, 1, 1, 3)
    truth, preds, _ = _errors(B=5, m=5)
    names = _names("articulated", 5)
    fig = plots.draw_skeleton(truth.p, {k: v.p for k, v in preds.items()}, parents, 0.05, names=names)
    ax3, ax_xy, ax_xz = fig.axes
    # per drawn skeleton (recorded + 2 models) one line per body: the root's point and a bone per child
    assert len(ax_xy.lines) == len(ax_xz.lines) == len(ax3.lines) == 3 * len(parents)
    labels = [t.get_text() for t in ax3.get_legend().get_texts()]
    assert labels[0] == "recorded" and labels[1].startswith("LieDFLNN (articulated)")
    assert ax_xy.get_xlabel() == "x [m]" and ax_xz.get_ylabel() == "z [m]"
    # a prediction that failed after sample 7: the frame shown is the last one every skeleton has
    bad = preds["model"].p.copy()
    bad[0, 8:] = np.nan
    assert plots.skeleton_frame(truth.p, {"model": bad}) == 7
    plots.plt.close("all")


@pytest.fixture(scope="module")
def chain_run(tmp_path_factory):
    pytest.importorskip("mujoco")
    from liedfl_cli.data.hdf5 import save_dataset
    from liedfl_cli.data.mujoco_chain import chain_dataset
    from liedfl_cli.solvers import runtime

    root = tmp_path_factory.mktemp("chain")
    save_dataset(chain_dataset(n_trajectories=10, steps=12, seed=3, links=3, h=0.05), root / "chain.h5")
    settings = runtime._current
    try:
        return train_run(
            root, "dataset=file", f"dataset.path={root / 'chain.h5'}", "model.kinetic=articulated", "train.epochs=2",
            "ui.progress=false", "runtime.threads=1",
        )  # fmt: skip
    finally:
        runtime._current = settings  # run_train configures the runtime: restore it


def test_eval_of_an_articulated_run_draws_every_body_and_the_skeleton(chain_run):
    for name in ("error_per_body.png", "position_error_per_body.png", "skeleton.png", "error_vs_step.png"):
        assert (chain_run / "plots" / name).is_file(), name
