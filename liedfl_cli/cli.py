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
    "rollout": "roll a trained run out: liedfl rollout run=<run dir> [steps=N]",
    "eval": "metrics table and plots of a run: liedfl eval run=<run dir>",
}
USAGE = "usage: liedfl {" + ",".join(COMMANDS) + "} [key=value ...] [-m] [--cfg job] [--help]\n\n" + "\n".join(
    f"  {k:<8} {v}" for k, v in COMMANDS.items()
)


def _run(command: str, cfg):
    from .data.errors import LiedflError
    from .schema import validate
    from .ui import fail

    try:
        validate(cfg)
        if command == "train":
            from .train import run_train

            return run_train(cfg)
        if command == "data":
            from .data.command import run_data

            return run_data(cfg)
        if command == "rollout":
            from .rollout import run_rollout

            return run_rollout(cfg)
        if command == "eval":
            from .evaluate import run_eval

            return run_eval(cfg)
    except LiedflError as e:
        fail(str(e))
    except FloatingPointError as e:
        fail(f"numerical failure: {e}")
    except KeyboardInterrupt:
        fail("interrupted", code=130)


def main() -> None:
    argv = sys.argv[1:]
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        raise SystemExit(0 if argv else 2)
    command = argv[0]
    if command not in COMMANDS:
        print(f"error: unknown command {command!r}\n\n{USAGE}", file=sys.stderr)
        raise SystemExit(2)
    if not (CONF_DIR / f"{command}.yaml").is_file():
        print(f"error: config directory {CONF_DIR} not found; install liedfl with `pip install -e .` from a clone",
              file=sys.stderr)
        raise SystemExit(2)
    import hydra

    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=command)
    def _hydra_main(cfg):
        return _run(command, cfg)

    sys.argv = [f"liedfl-{command}", *argv[1:]]
    _hydra_main()


if __name__ == "__main__":
    main()
