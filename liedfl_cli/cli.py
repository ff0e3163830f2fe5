"""`liedfl <command> [hydra overrides]`: a thin dispatcher over one @hydra.main per command.

Hydra has no subcommands; the first word picks the primary config (conf/<command>.yaml) and
the plain function that does the work (`run_train`, ...), which tests call directly.
"""

from __future__ import annotations

import sys
from pathlib import Path

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
COMMANDS = {
    "train": "train and evaluate a model (generates the dataset if needed)",
    "data": "only generate (or import) a dataset",
    "rollout": "roll a trained run out into <run>/rollouts/<name>/: liedfl rollout run=<run dir> [steps=N]",
    "eval": "metrics table and plots of a run: liedfl eval run=<run dir> [rollout=<rollout file>]",
    "report": "one table and figures over a sweep: liedfl report sweep=<multirun dir>",
}
# commands whose Hydra run dir is `${<key>}`, an existing directory named on the command line
DIR_ARGS = {
    "rollout": ("run", "run dir", "run directory", "a directory written by `liedfl train`"),
    "eval": ("run", "run dir", "run directory", "a directory written by `liedfl train`"),
    "resume": ("resume", "run dir", "run directory", "a directory written by `liedfl train`"),
    "report": ("sweep", "multirun dir", "multirun directory", "a directory written by `liedfl train -m`"),
}
USAGE = (
    "usage: liedfl {"
    + ",".join(COMMANDS)
    + "} [key=value ...] [-m] [--cfg job] [--help]\n\n"
    + "\n".join(f"  {k:<8} {v}" for k, v in COMMANDS.items())
)


def _run(command: str, cfg):
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from .errors import ConfigError, LiedflError
    from .schema import validate
    from .ui import fail

    try:
        if command in DIR_ARGS and OmegaConf.is_missing(cfg, DIR_ARGS[command][0]):
            key, what, _, hint = DIR_ARGS[command]
            raise ConfigError(f"{key}=<{what}> is required ({hint})")
        validate(cfg)
        if command == "train":
            from .train import run_train

            return run_train(cfg)
        if command == "resume":
            from .train import run_resume

            return run_resume(cfg)
        if command == "data":
            from .data.command import run_data

            return run_data(cfg)
        if command == "rollout":
            from .rollout import run_rollout

            return run_rollout(cfg)
        if command == "eval":
            from .evaluate import run_eval

            return run_eval(cfg)
        if command == "report":
            from .report import run_report

            return run_report(cfg)
    except LiedflError as e:
        fail(str(e), code=getattr(e, "exit_code", 2))
    except FloatingPointError as e:
        fail(f"numerical failure: {e}")
    except OmegaConfBaseException as e:  # e.g. a broken interpolation in an override file
        key = getattr(e, "full_key", None)
        fail(
            f"config error: {str(e).splitlines()[0] if str(e) else type(e).__name__}" + (f" (key {key})" if key else "")
        )
    except KeyboardInterrupt:
        fail("interrupted", code=130)


def _check_dir_arg(command: str, args: list[str]) -> None:
    """`run=<dir>` (rollout, eval) / `sweep=<dir>` (report), checked before Hydra starts: Hydra's run
    dir is `${run}` / `${sweep}`, so Hydra would otherwise create a mistyped directory (and crash
    with a traceback when the value is missing). Skipped for flags (-m, --cfg, --help, ...) and
    for values Hydra has to interpret (sweeps, ${...})."""
    import re

    key, what, noun, hint = DIR_ARGS[command]
    if any(a.startswith("-") for a in args):
        return
    value = None
    for a in args:
        m = re.fullmatch(r"\+{0,2}" + key + r"=(.*)", a, flags=re.S)
        if m:
            value = m.group(1).strip()
    if value is not None and len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
        value = value[1:-1]
    if value in (None, "", "???", "null"):
        print(f"error: {key}=<{what}> is required ({hint})", file=sys.stderr)
        raise SystemExit(2)
    if any(c in value for c in ",${}[]()") or value.startswith(("glob", "range", "choice")):
        return
    if not Path(value).is_dir():
        print(f"error: {key}={value}: no such {noun}", file=sys.stderr)
        raise SystemExit(2)


def main() -> None:
    argv = sys.argv[1:]
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        raise SystemExit(0 if argv else 2)
    command = argv[0]
    if command == "train" and any(a.startswith("resume=") for a in argv[1:]):
        command = "resume"  # `liedfl train resume=<run dir>` has its own primary config
    if command not in COMMANDS and command != "resume":
        print(f"error: unknown command {command!r}\n\n{USAGE}", file=sys.stderr)
        raise SystemExit(2)
    if not (CONF_DIR / f"{command}.yaml").is_file():
        print(
            f"error: config directory {CONF_DIR} not found; install liedfl with `pip install -e .` from a clone",
            file=sys.stderr,
        )
        raise SystemExit(2)
    if command in DIR_ARGS:
        _check_dir_arg(command, argv[1:])
    import hydra

    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=command)
    def _hydra_main(cfg):
        return _run(command, cfg)

    sys.argv = [f"liedfl-{command}", *argv[1:]]
    _hydra_main()


if __name__ == "__main__":
    main()
