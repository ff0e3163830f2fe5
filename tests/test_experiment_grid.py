"""The whole grid of `scripts/reproduce_paper.sh` at `budget=smoke`: every experiment file
(`conf/experiment/*.yaml`) with every combination of the values it sweeps (`hydra.sweeper.params`), plus
the single runs of `scripts/paper_plan.py`'s `EXTRA_JOBS`, taken through what `liedfl train` does
before its first epoch: composed by Hydra from the package's config dir, validated (`schema.validate`),
typed once (`typed`), its dataset got as `run_train` gets it (the config checked and hashed by
`data.scenes.get_dataset`; a tiny smoke dataset, generated once per distinct dataset into a module's
folder), the validation split set up, the model built (`factory.build_model`) and its loss checked.
Nothing trains. Each job then asserts that what its sweep value says reached the job: the model's
`_target_` and class, the scene and its group, every swept key in the typed config.

The grid is listed by `paper_plan.sweep_params` (the script's own expansion, imported, not copied);
`test_the_grid_follows_the_experiment_files` checks it against the sweep lists read independently
with `yaml.safe_load`, and that a value added to an experiment file is picked up. (Composing and typing
every job at the default budget too: tests/test_experiment_sweeps.py. The plan script itself:
tests/test_paper_plan.py.) The `slow` test runs every job for real at `budget=smoke`.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml
from test_paper_plan import _plan_module  # scripts/paper_plan.py as the module `paper_plan`

import liedfl_cli.cli
from helpers import SMOKE, compose_config, train_run
from liedfl_cli.cli import CONF_DIR
from liedfl_cli.config.factory import build_model, configure_runtime
from liedfl_cli.config.schema import validate
from liedfl_cli.config.typed import typed
from liedfl_cli.data.files import complete_steps
from liedfl_cli.data.scenes import get_dataset
from liedfl_cli.errors import LiedflError
from liedfl_cli.models.liedflnn.losses import check_loss, check_rollout_horizon

ROOT = Path(__file__).resolve().parent.parent
EXPERIMENTS = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))
BUDGET = "budget=smoke"
ARTICULATED_CLASS = "ArticulatedLieDFLNN"
"""`model.kinetic=articulated` turns LieDFLNN's config into this class (`factory.build_model`)."""


@dataclass(frozen=True)
class GridJob:
    """One `liedfl train` job of the reproduction: its experiment and its own overrides."""

    experiment: str
    overrides: tuple[str, ...]

    @property
    def id(self) -> str:
        """`exp2[baseline=glnn_rk4,dataset.train_steps=10]`; a job without overrides: its experiment."""
        short = self.experiment.split("_")[0] if re.fullmatch(r"exp\d+_.*", self.experiment) else self.experiment
        return f"{short}[{','.join(self.overrides)}]" if self.overrides else short


def grid(experiments: list[str]) -> list[GridJob]:
    """Every job of `experiments` at `budget=smoke`, as paper_plan.py expands them (its sweeps'
    cartesian product, then its EXTRA_JOBS), composed from `liedfl_cli.cli.CONF_DIR`."""
    plan = _plan_module()
    out = []
    with plan._Composer() as compose:
        for exp in experiments:
            out += [GridJob(exp, tuple(ov)) for ov in plan.sweep_params(compose, exp, [BUDGET])]
            out += [GridJob(exp, tuple(ov)) for _folder, ov in plan.EXTRA_JOBS.get(exp, [])]
    return out


GRID = grid(EXPERIMENTS)


# ----------------------------------------------------------------------------- the files, read apart
def _yaml(path: Path) -> dict:
    with open(path) as f:
        return yaml.safe_load(f) or {}


def _sweep_lists(experiment: str, conf_dir: Path = CONF_DIR) -> dict[str, list[str]]:
    """An experiment's `hydra.sweeper.params`, each value list split, straight from its file."""
    params = ((_yaml(conf_dir / "experiment" / f"{experiment}.yaml").get("hydra") or {}).get("sweeper") or {}).get(
        "params"
    ) or {}
    return {key: [v.strip() for v in str(values).split(",")] for key, values in params.items()}


def _override_in_defaults(path: Path, group: str) -> str | None:
    """The option a config file's defaults list selects for `group` (`- group: option`,
    `- override /group: option`, `- override /group@_global_.group: option`)."""
    for entry in _yaml(path).get("defaults") or []:
        if isinstance(entry, dict):
            for key, value in entry.items():
                if key.replace("override ", "").strip().lstrip("/") in (group, f"{group}@_global_.{group}"):
                    return str(value)
    return None


def _expected_model(job: GridJob) -> str:
    """The model file (conf/model/<name>.yaml) the job asks for: its `model=` override, else its
    `baseline=` value, the name of a model file by the convention of conf/baseline/ (`none`: the
    train config's default model)."""
    own = dict(ov.split("=", 1) for ov in job.overrides)
    if "model" in own:
        return own["model"]
    baseline = own.get("baseline", "none")
    if baseline != "none":
        return baseline
    default = _override_in_defaults(CONF_DIR / "train.yaml", "model")
    assert default is not None, "conf/train.yaml's defaults name no model"
    return default


def _expected_class(job: GridJob) -> str:
    """The class name of the job's model: its config file's `_target_`, or the articulated model
    where the job sets `model.kinetic=articulated`."""
    if "model.kinetic=articulated" in job.overrides:
        return ARTICULATED_CLASS
    return str(_yaml(CONF_DIR / "model" / f"{_expected_model(job)}.yaml")["_target_"]).rsplit(".", 1)[1]


def _typed_value(run, key: str):
    """`key` (dotted) read from the typed config: dataclass fields, then a dataset's scene keys
    (`DatasetConfig.scene`), then mapping keys."""
    got = run
    for part in key.split("."):
        if isinstance(got, dict):
            got = got[part]
        elif hasattr(got, part):
            got = getattr(got, part)
        else:
            got = got.scene[part]
    return got


# ----------------------------------------------------------------------------- what train does first
@dataclass
class Prepared:
    """A job taken up to its first epoch: its composed and typed configs, dataset and its file, model."""

    cfg: object
    run: object
    dataset: object
    data_path: Path
    model: object


def prepare(job: GridJob, root: Path, data_dir: Path) -> Prepared:
    """What `run_train` does with the job's config before training (commands/train.py, `_run_train`):
    compose, validate, type once, apply the runtime, get the dataset (cached in `data_dir`), fill its
    null steps, set up the validation split, check a rollout loss's horizon, build the model and
    check its loss. Raises what the command raises."""
    from liedfl_cli.commands.train import validation_setup

    paths = (f"paths.output_dir={root / 'run'}", f"paths.data_dir={data_dir}")
    cfg = compose_config("train", (f"experiment={job.experiment}", BUDGET, *job.overrides, *paths))
    validate(cfg, "train")
    run = typed(cfg, "train")
    assert run.train is not None and run.dataset is not None
    configure_runtime(run.runtime)
    dataset, data_path = get_dataset(run.dataset, run.paths.data_dir)
    complete_steps(run.dataset, dataset)
    validation_setup(run, dataset, None)
    if run.train.loss == "rollout":
        check_rollout_horizon(run.train.rollout_loss.horizon, int(run.dataset.train_steps or 0))
    model = build_model(run, dataset)
    check_loss(model, run.train.loss)
    return Prepared(cfg, run, dataset, Path(data_path), model)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    """The jobs' datasets, shared by the module: each distinct smoke dataset is generated once."""
    return tmp_path_factory.mktemp("grid_data")


# ----------------------------------------------------------------------------- the grid
def test_the_grid_follows_the_experiment_files(tmp_path, monkeypatch):
    """The grid holds, per experiment, the product of its sweep lists' lengths (read with
    yaml.safe_load, not from paper_plan) plus its EXTRA_JOBS, each combination once; a value added
    to an experiment file's sweep adds its jobs."""
    plan = _plan_module()
    for exp in EXPERIMENTS:
        lists = _sweep_lists(exp)
        jobs = [j for j in GRID if j.experiment == exp]
        extra = [tuple(ov) for _folder, ov in plan.EXTRA_JOBS.get(exp, [])]
        assert len(jobs) == math.prod(len(v) for v in lists.values()) + len(extra), exp
        swept = {tuple(f"{k}={v}" for k, v in zip(lists, combo)) for combo in itertools.product(*lists.values())}
        assert {j.overrides for j in jobs} == swept | set(extra), exp
    assert len({j.id for j in GRID}) == len(GRID), "two jobs with one test id"
    assert "exp2[baseline=glnn_rk4,dataset.train_steps=10]" in {j.id for j in GRID}

    # a copy of the configs with one more training length in Exp 2's sweep: 4 more jobs
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    exp2 = conf / "experiment" / "exp2_discrete_vs_continuous.yaml"
    text = exp2.read_text()
    assert "dataset.train_steps: 10,40,70,100\n" in text
    exp2.write_text(text.replace("dataset.train_steps: 10,40,70,100\n", "dataset.train_steps: 10,40,70,100,130\n"))
    monkeypatch.setattr(liedfl_cli.cli, "CONF_DIR", conf)  # where paper_plan's composer reads the configs
    grown = grid(["exp2_discrete_vs_continuous"])
    lists = _sweep_lists("exp2_discrete_vs_continuous", conf)
    assert lists["dataset.train_steps"] == ["10", "40", "70", "100", "130"]
    assert len(grown) == math.prod(len(v) for v in lists.values()) == len(_sweep_lists(exp2.stem)["baseline"]) * 5
    assert ("baseline=glnn_rk4", "dataset.train_steps=130") in {j.overrides for j in grown}


@pytest.mark.parametrize("job", GRID, ids=[j.id for j in GRID])
def test_every_job_composes_validates_and_builds_its_model(job, data_dir, tmp_path):
    p = prepare(job, tmp_path, data_dir)
    run = p.run

    # the model the sweep value names: its config file's target, and that class built
    name = _expected_model(job)
    target = _yaml(CONF_DIR / "model" / f"{name}.yaml")["_target_"]
    assert p.cfg.model._target_ == target and p.cfg.model.name == name
    assert type(p.model).__name__ == _expected_class(job)
    assert p.model.name == name

    # the experiment's scene, its group, and the dataset got for it
    scene = _override_in_defaults(CONF_DIR / "experiment" / f"{job.experiment}.yaml", "dataset")
    assert run.dataset.name == scene and p.dataset.scene == scene
    assert p.data_path.parent == data_dir and p.data_path.name.startswith(f"{scene}-")
    group = _override_in_defaults(CONF_DIR / "dataset" / f"{scene}.yaml", "group")
    assert group is not None and run.group.n_se3 == _yaml(CONF_DIR / "group" / f"{group}.yaml")["n_se3"]
    assert (p.dataset.group.n_se3, p.dataset.group.n_so3) == (run.group.n_se3, run.group.n_so3)

    # every swept value, as the typed config holds it (config groups: checked above)
    for override in job.overrides:
        key, value = override.split("=", 1)
        if key in ("baseline", "model"):
            continue
        want = yaml.safe_load(value)
        got = _typed_value(run, key)
        assert got == want and type(got) is type(want), (override, got)
    if any(ov.startswith("dataset.train_steps=") for ov in job.overrides):
        assert p.dataset.n_steps >= run.dataset.train_steps  # the smoke data covers the swept length

    # the budget: smoke's epochs, not the experiment's
    assert run.train.epochs == _yaml(CONF_DIR / "budget" / "smoke.yaml")["train"]["epochs"]


def _values(case) -> tuple:
    return tuple(case.values) if hasattr(case, "values") else case


INVALID = [
    ("exp2_discrete_vs_continuous", ("baseline=glnn_rk5", "dataset.train_steps=10"), "glnn_rk5"),
    ("exp2_discrete_vs_continuous", ("baseline=glnn_rk4", "dataset.train_steps=-10"), "train_steps"),
    ("exp4_mocap", ("model.kinetic=articulate",), "kinetic"),
    # a scene's `initial` block: its numbers are checked by the scene's generator (`scene_common.section`)
    ("exp1_euler_vs_lie", ("baseline=euler_dflnn", "dataset.initial.omega_scale=fast"), "omega_scale"),
]


@pytest.mark.parametrize("experiment,overrides,named", INVALID, ids=[GridJob(*_values(c)[:2]).id for c in INVALID])
def test_an_invalid_sweep_value_fails_naming_it(experiment, overrides, named, data_dir, tmp_path):
    """A sweep value no config or check accepts fails before training, and the error names it."""
    with pytest.raises(Exception) as err:
        prepare(GridJob(experiment, overrides), tmp_path, data_dir)
    assert named in str(err.value), str(err.value)
    if not named.startswith("glnn"):  # (an unknown config option is Hydra's error)
        assert isinstance(err.value, LiedflError) and "\n" not in str(err.value).strip()


@pytest.mark.slow
def test_every_job_trains_at_smoke_budget(tmp_path_factory):
    """Every job of the grid run for real by `run_train` at `budget=smoke` (two epochs, rollout,
        evaluation without plots; about 30 s for the 30 jobs): each trains smoke's epochs to a finite loss,
    builds the model its sweep value names and writes its rollout."""
    from liedfl_cli.files.checkpoint import load_checkpoint

    root = tmp_path_factory.mktemp("grid_runs")
    epochs = _yaml(CONF_DIR / "budget" / "smoke.yaml")["train"]["epochs"]
    for i, job in enumerate(GRID):
        out = train_run(root, f"experiment={job.experiment}", *SMOKE, *job.overrides, name=f"job{i}")
        assert (out / "checkpoints" / "last.pt").is_file(), job.id
        payload = load_checkpoint(out / "checkpoints" / "last.pt")
        losses = [row["loss"] for row in payload["history"]]
        assert len(losses) == epochs and all(math.isfinite(x) for x in losses), (job.id, losses)
        assert json.loads((out / "components.json").read_text())["model"] == _expected_class(job), job.id
        assert (out / "rollout.h5").is_file(), job.id
