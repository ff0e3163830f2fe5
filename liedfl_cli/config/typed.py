"""A command's config as typed objects, converted once at the command's entry.

`typed(cfg)` turns a composed, validated `DictConfig` (`schema.validate` has run: unknown keys,
types and values are reported there, one line naming the key) into a `RunConfig`: one dataclass
per section, built with `OmegaConf.structured` / `OmegaConf.to_object` from the dataclasses below
(or the option classes of the layer that uses them: `SolverOptions`, `DatasetConfig`). The schemas
are registered with Hydra's `ConfigStore` under `liedfl_schema/<section>`. Below the commands
nothing sees the config library: `data/` gets a `DatasetConfig`, the solvers a `SolverOptions`,
the models their options as plain keywords and a `LossOptions`, the runtime a `RuntimeOptions`,
the scene evaluations a `SceneEvalOptions` (docs/architecture.md, "How a config travels").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from ..data.dataset_config import DatasetConfig
from ..errors import ConfigError
from ..evaluation.outputs import SceneEvalOptions
from ..files.checkpoint import CHECKPOINTS  # the checkpoint files' own list
from ..loggers import NAMES as LOGGERS  # the loggers' own list (loggers/__init__.py)
from ..models.base import LossOptions
from ..models.liedflnn.losses import LOSSES
from ..solvers.options import SolverOptions
from ..solvers.runtime import RuntimeOptions
from .fields import Check, Checked, check, option

TRAIN = ("train",)


@dataclass
class OptimizerConfig(Checked):
    section: ClassVar[str] = "train.optimizer"

    # the names are declared here only: commands/optimizers.py finds each one's builder (`build_<name>`)
    name: str = option("soap", choices_of=Literal["soap", "adam"], required=TRAIN)
    lr: float = option(3e-3, number="positive", required=TRAIN)
    weight_decay: float = option(0.0, number="nonnegative", required=TRAIN)
    schedule: str = option("constant", choices_of=Literal["constant", "cosine"])
    precondition_frequency: int = option(10, integer=1)  # SOAP: steps between eigenbasis updates
    max_precondition_dim: int = option(10000, integer=1)  # SOAP: larger dimensions are not preconditioned


@dataclass
class EarlyStoppingConfig(Checked):
    section: ClassVar[str] = "train.early_stopping"

    # validation passes without improvement before training stops; null = off
    patience: int | None = option(None, integer=1, nullable=True)
    min_delta: float = option(0.0, number="nonnegative")  # an improvement must exceed this


@dataclass
class RolloutLossConfig(Checked):  # train.loss=rollout: the fine-tuning stage (liedfl_cli/commands/finetune.py)
    section: ClassVar[str] = "train.rollout_loss"

    horizon: int = option(5, integer=1)  # k: steps rolled out per window of k + 2 true poses
    epochs: int = option(100, integer=1)  # fine-tuning epochs after train.epochs of the DEL loss
    lr: Any = option(None, number="positive", nullable=True)  # null: train.optimizer.lr


@dataclass
class TrainConfig(Checked):
    section: ClassVar[str] = "train"

    epochs: int = option(1000, integer=0, required=TRAIN)  # 0: the model's start only (train.start)
    batch_size: int = option(1024, integer=1, required=TRAIN)
    optimizer: OptimizerConfig = field(default_factory=OptimizerConfig)
    w_del: float = option(LossOptions.w_del, number="nonnegative", required=TRAIN)
    w_reg: float = option(LossOptions.w_reg, number="nonnegative", required=TRAIN)
    reg_points: int = option(LossOptions.reg_points, integer=0, required=TRAIN)
    reg_form: str = option(
        LossOptions.reg_form, choices_of=Literal["relu", "gaussian"], required=TRAIN
    )  # log-space penalties
    epsilon: float = option(LossOptions.epsilon, number="finite", required=TRAIN)
    # auto | positive int (None: auto)
    checkpoint_every: Any = option("auto", integer=1, auto=True, nullable=True, what="auto or a positive integer")
    full_batch: bool = False  # one optimiser step per epoch over every sample
    val_every: Any = option("auto", integer=1, auto=True, nullable=True, what="auto or a positive integer")
    val_horizon: int = option(20, integer=2)
    # which weights roll out: the best validation one-step error / rollout error, or the last (docs/validation.md)
    select: str = option("val_one_step", choices_of=Literal["val_one_step", "val_rollout", "last"])
    early_stopping: EarlyStoppingConfig = field(default_factory=EarlyStoppingConfig)
    loss: str = option(LossOptions.loss, choices_of=LOSSES)  # the training losses (models/liedflnn/losses.py)
    start: str = option("auto", choices_of=Literal["auto", "identify", "none"])  # a model's own start (articulated)
    rollout_loss: RolloutLossConfig = field(default_factory=RolloutLossConfig)

    def loss_options(self, solver: SolverOptions | None = None) -> LossOptions:
        """The settings `Model.loss` takes (solver: the rollout loss's Newton solves)."""
        return LossOptions(
            w_del=float(self.w_del),
            w_reg=float(self.w_reg),
            epsilon=float(self.epsilon),
            reg_form=str(self.reg_form),
            reg_points=int(self.reg_points),
            loss=str(self.loss),
            rollout_horizon=int(self.rollout_loss.horizon),
            solver=solver,
        )


RUNS = ("train", "rollout", "eval")  # the commands that roll out or evaluate a model


@dataclass
class RolloutConfig(Checked):
    section: ClassVar[str] = "rollout"

    enabled: bool = option(True, required=TRAIN)
    steps: int | None = option(None, integer=2, nullable=True, required=TRAIN)  # the given poses + >= 1 step
    max_trajectories: int | None = option(None, integer=1, nullable=True, required=("train", "rollout"))
    reference: bool = option(True, required=("train", "rollout"))


@dataclass
class EvalConfig(Checked):
    section: ClassVar[str] = "eval"

    plots: bool = option(True, required=RUNS)


@dataclass
class UiConfig(Checked):
    section: ClassVar[str] = "ui"

    progress: bool = option(True, required=(*RUNS, "data", "resume"))


@dataclass
class PathsConfig(Checked):
    section: ClassVar[str] = "paths"

    data_dir: str = option("outputs/data", required=(*RUNS, "data"))  # checked by schema._check_data_dir
    # Hydra's run folder (`${hydra:runtime.output_dir}`; "." outside a Hydra run)
    output_dir: str = option(".", required=TRAIN)


@dataclass(frozen=True)
class SolverConfig(SolverOptions, Checked):
    """The `solver` section: `SolverOptions` (the solvers' own dataclass declares the fields) with
    the checks of its values; `typed` hands the solvers a plain `SolverOptions`."""

    section: ClassVar[str] = "solver"
    checks: ClassVar[dict[str, Check]] = {
        "tol": check(number="positive", required=RUNS),
        "max_iter": check(integer=1, required=RUNS),
        "max_halvings": check(integer=0, required=RUNS),
    }


@dataclass
class RuntimeConfig:  # execution settings; checked and normalised by solvers/runtime.py `runtime_options`
    # the defaults are `RuntimeOptions`' own (solvers/runtime.py declares them and their values once)
    threads: Any = RuntimeOptions.threads  # auto | positive int
    fused: Any = RuntimeOptions.fused  # true | false (Any: "yes" is refused by RuntimeOptions, not read as true)
    compile: Any = RuntimeOptions.compile  # auto | true | false
    device: str = RuntimeOptions.device  # cpu | cuda | auto (availability checked when the job starts)
    dtype: str = RuntimeOptions.dtype  # float64 | float32


@dataclass
class LoggerConfig(Checked):  # the `logger` config group (liedfl_cli/loggers/)
    section: ClassVar[str] = "logger"

    name: str = option("csv", choices_of=LOGGERS)  # tensorboard: train_metrics.csv plus <run>/tensorboard/


@dataclass
class GroupConfig:
    n_se3: int = 0
    n_so3: int = 1


@dataclass
class TopKeys(Checked):
    """The commands' own top-level keys (`liedfl rollout run=... steps=... split=...`), checked here
    and kept as plain values in `RunConfig.top`; a key a command does not have is left out."""

    run: Any = option(None, required=("rollout", "eval"))
    checkpoint: str = option("best", choices_of=CHECKPOINTS)  # best.pt (else last.pt) | last.pt (files/checkpoint.py)
    steps: Any = option(None, integer=2, nullable=True, required=("rollout",))
    split: str = option("auto", choices_of=Literal["auto", "all", "train", "test"])  # config/other_data.py
    export: Any = option(None, choices_of=Literal["csv", "npz", None])  # predictions (commands/export.py) or none
    accept_changed_dataset: Any = None
    resume: Any = option(None, required=("resume",))
    epochs: Any = None
    sweep: Any = option(None, required=("report",))
    plots: Any = option(None, required=("report",))


SECTIONS: dict[str, Any] = {
    "train": TrainConfig,
    "rollout": RolloutConfig,
    "eval": EvalConfig,
    "ui": UiConfig,
    "paths": PathsConfig,
    "solver": SolverConfig,
    "group": GroupConfig,
    "runtime": RuntimeConfig,
    "logger": LoggerConfig,
}
"""Config section -> its dataclass (the types `schema.validate` checks and `typed` builds)."""


@dataclass
class RunConfig:
    """A command's config, typed. Sections a command's config does not have are None (`liedfl data`
    has no `train`; `liedfl eval` has no `rollout` section: there `rollout` is a file path, kept in
    `top`); `model` and `force` are plain mappings, checked by the model's `from_config` and
    `conf/force/<kind>.yaml`; `top` holds the command's own top-level keys (run, steps, checkpoint,
    split, export, accept_changed_dataset, resume, epochs, sweep, plots) as plain values."""

    command: str
    seed: int | None = None
    train: TrainConfig | None = None
    rollout: RolloutConfig | None = None
    eval: EvalConfig = field(default_factory=EvalConfig)
    ui: UiConfig = field(default_factory=UiConfig)
    paths: PathsConfig = field(default_factory=PathsConfig)
    solver: SolverOptions = field(default_factory=SolverOptions)
    runtime: RuntimeOptions = field(default_factory=RuntimeOptions)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    group: GroupConfig | None = None
    dataset: DatasetConfig | None = None
    model: dict[str, Any] | None = None
    force: dict[str, Any] = field(default_factory=dict)
    top: dict[str, Any] = field(default_factory=dict)

    def scene_eval_options(self) -> SceneEvalOptions:
        return SceneEvalOptions(plots=bool(self.eval.plots), solver=self.solver)


def _register() -> None:
    """The section schemas in Hydra's ConfigStore (group `liedfl_schema`), so a user's config can
    name them (`defaults: [liedfl_schema/train@train]`) and tools can list them."""
    try:
        from hydra.core.config_store import ConfigStore
    except ImportError:  # pragma: no cover (hydra is a dependency; the conversion does not need it)
        return
    cs = ConfigStore.instance()
    for name, schema in SECTIONS.items():
        cs.store(group="liedfl_schema", name=name, node=schema)


_register()


def _first_line(e: Exception) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


_KINDS = {"Float": "a number (e.g. 1e-3)", "Integer": "an integer", "Boolean": "true or false", "bool": "true or false",
          "String": "a string"}  # fmt: skip


def wrong_type_line(e: Exception, full_key: str) -> str | None:
    """OmegaConf's `Value 'abc' of type 'str' could not be converted to Float` in our words:
    `train.optimizer.lr=abc: must be a number (e.g. 1e-3)`; None for any other error."""
    import re

    line = _first_line(e)
    m = re.match(r"Value '(.*)' of type '\w+' could not be converted to (\w+)", line)
    m = m or re.match(r"Value '(.*)' is not a valid (\w+)", line)
    if m is None or not full_key:
        return None
    return f"{full_key}={m.group(1)}: must be {_KINDS.get(m.group(2), m.group(2))}"


def plain(node, where: str) -> Any:
    """A config subtree as plain Python (interpolations resolved); ConfigError naming `where`."""
    if isinstance(node, (DictConfig, ListConfig)):
        try:
            return OmegaConf.to_container(node, resolve=True)
        except OmegaConfBaseException as e:
            raise ConfigError(f"config key '{where}': {_first_line(e)}") from None
    return node


def section(schema: type, values: Any, where: str) -> Any:
    """`values` (a config node or plain mapping, None = the defaults) as an instance of the dataclass
    `schema`, through OmegaConf's structured configs (types converted and checked as in validate)."""
    values = plain(values, where)
    try:
        node = OmegaConf.merge(OmegaConf.structured(schema), values or {})
        return OmegaConf.to_object(node)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", None) or ""
        where_key = f" (key {where}.{key})" if key else ""
        ours = wrong_type_line(e, f"{where}.{key}" if key else "")
        raise ConfigError(ours or f"config section '{where}': {_first_line(e)}{where_key}") from None
    except ValueError as e:  # a schema's own __post_init__ check (e.g. SolverOptions.method), one line
        raise ConfigError(_first_line(e)) from None


def _resolvable(node: DictConfig) -> dict[str, Any]:
    """The keys of `node` whose values resolve to something: `paths.output_dir` names Hydra's run
    folder, which a config composed without a Hydra run (the compose API: tests, scripts) does not
    have; after an earlier Hydra run in the same process it resolves to None instead of failing."""
    out = {}
    for key in node:
        try:
            value = plain(node[key], str(key))
        except (ConfigError, OmegaConfBaseException, ValueError):
            continue
        if value is not None:
            out[str(key)] = value
    return out


def runtime_options(values: Any) -> RuntimeOptions:
    """The `runtime` section (a config node or plain mapping, None = the defaults) as the
    `RuntimeOptions` the solvers apply (values checked there: one-line ConfigError)."""
    return RuntimeOptions(**vars(section(RuntimeConfig, values, "runtime")))


def solver_options(values: Any) -> SolverOptions:
    """The `solver` section (a config node or plain mapping) as the `SolverOptions` the solvers
    take, its values checked (`SolverConfig`)."""
    return SolverOptions(**vars(section(SolverConfig, values, "solver")))


USER_FILES = ("file", "import")
"""The scenes that read a user's file (`dataset=file`, `dataset=import`)."""


def relaxed_dataset_config(d: dict) -> tuple[dict, bool]:
    """A rollout trains nothing, so `dataset.test_fraction=1.0` (every trajectory a test one, which a
    dataset refuses for training) asks for all trajectories: returns (the config to build the data with,
    whether all were asked)."""
    tf = d.get("test_fraction")
    if isinstance(tf, bool) or not isinstance(tf, (int, float)) or tf != 1.0:
        return d, False
    d = dict(d)
    if d.get("name") in USER_FILES:
        d.pop("test_fraction")  # the shipped default (data/files.py): the split is replaced anyway
    else:
        d["test_fraction"] = 0.0
    return d, True


def dataset_config(values: Any, rollout: bool = False) -> DatasetConfig:
    """The `dataset` section (a config node or plain mapping) as a `DatasetConfig`, checked once
    (`scenes.dataset_section`: one-line ConfigError naming the key). rollout: the section of
    `liedfl rollout dataset=...`, checked as `relaxed_dataset_config` reads it (`test_fraction=1.0`
    asks for every trajectory) and kept as configured."""
    from ..data.scenes import dataset_section

    d = plain(values, "dataset")
    return dataset_section(d, relaxed_dataset_config(d)[0] if rollout else None)


TOP_KEYS = tuple(f.name for f in dataclasses.fields(TopKeys))


def typed(cfg: DictConfig, command: str | None = None, check_dataset: bool = True) -> RunConfig:
    """The typed form of a composed config (validate it first: this reports only what the section
    dataclasses refuse). command: default `cfg.task_name`. check_dataset: false for a run's saved
    config, whose data are its recorded file (the section is checked where it generates data again:
    `scenes.get_dataset`)."""
    command = str(command or cfg.get("task_name") or "")
    out = RunConfig(command=command)
    if "seed" in cfg:
        out.seed = int(plain(cfg.seed, "seed"))
    for name, schema in SECTIONS.items():
        if name not in cfg or cfg.get(name) is None:
            continue
        if name == "rollout" and not isinstance(cfg.get(name), DictConfig):
            continue  # `liedfl eval rollout=<file>`: a path (in `top`)
        value: Any
        if name == "runtime":
            value = runtime_options(cfg[name])
        elif name == "solver":
            value = solver_options(cfg[name])
        elif name == "paths":
            value = section(schema, _resolvable(cfg[name]), name)
        else:
            value = section(schema, cfg[name], name)
        setattr(out, name, value)
    if cfg.get("dataset") is not None:
        if check_dataset:
            out.dataset = dataset_config(cfg.dataset, rollout=command == "rollout")
        else:
            out.dataset = DatasetConfig.from_mapping(plain(cfg.dataset, "dataset"))
    if cfg.get("model") is not None:
        out.model = dict(plain(cfg.model, "model"))
    if cfg.get("force") is not None:
        out.force = dict(plain(cfg.force, "force") or {})
    keys = set(cfg.keys())  # (`key in cfg` is false for a missing mandatory value such as `run: ???`)
    for key in TOP_KEYS:
        if key in keys:  # a missing value stays "???" (the commands name it)
            out.top[key] = "???" if OmegaConf.is_missing(cfg, key) else plain(cfg.get(key), key)
    if command == "eval" and "rollout" in cfg and not isinstance(cfg.get("rollout"), DictConfig):
        out.top["rollout"] = plain(cfg.get("rollout"), "rollout")
    return out


__all__ = [
    "SECTIONS",
    "DatasetConfig",
    "EarlyStoppingConfig",
    "EvalConfig",
    "GroupConfig",
    "LoggerConfig",
    "OptimizerConfig",
    "PathsConfig",
    "RolloutConfig",
    "RolloutLossConfig",
    "RunConfig",
    "RuntimeConfig",
    "SolverConfig",
    "TopKeys",
    "TrainConfig",
    "UiConfig",
    "dataset_config",
    "plain",
    "runtime_options",
    "solver_options",
    "section",
    "typed",
]
