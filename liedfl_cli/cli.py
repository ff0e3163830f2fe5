"""`liedfl <command> [hydra overrides]`: a thin dispatcher over one @hydra.main per command.

Hydra has no subcommands; the first word picks the primary config (liedfl_cli/conf/<command>.yaml) and
the plain function that does the work (`run_train`, ...), which tests call directly.
"""

from __future__ import annotations

import contextlib
import os
import sys
from pathlib import Path
from typing import NoReturn

from .config import resolvers  # noqa: F401  (registers the config resolvers)
from .config.preflight import DIR_ARGS, classify, preflight, preflight_or_fail  # noqa: F401 (re-exported)

CONF_DIR = Path(__file__).resolve().parent / "conf"
COMMANDS = {
    "train": "train and evaluate a model (generates the dataset if needed)",
    "data": "only generate (or import) a dataset",
    "rollout": "roll a trained run out: liedfl rollout run=<run dir>|latest [steps=N] [split=all] [export=csv|npz]",
    "eval": "metrics table and plots of a run: liedfl eval run=<run dir>|latest",
    "report": "one table and figures over a sweep: liedfl report sweep=<multirun dir>",
    "export": "the identified articulated model as MJCF: liedfl export run=<run dir>|latest out=model.xml",
}
USAGE = (
    "usage: liedfl {"
    + ",".join(COMMANDS)
    + "} [key=value ...] [-m] [--cfg job] [--help]\n\n"
    + "\n".join(f"  {k:<8} {v}" for k, v in COMMANDS.items())
    + "\n\n  liedfl <command> --help         the command's config groups and keys"
    + "\n  liedfl train resume=<run>       continue a run (run=latest, resume=latest: the newest one in outputs/runs/)"
    + "\n  liedfl --version                liedfl's version (also -V, and after a command)"
    + '\n  liedfl --completion bash|zsh    shell completion: eval "$(liedfl --completion bash)" in ~/.bashrc'
)
COMPLETION = r"""# liedfl shell completion: commands, then config groups and keys through Hydra (liedfl <cmd> -sc).
# bash: eval "$(liedfl --completion bash)" in ~/.bashrc; zsh: eval "$(liedfl --completion zsh)" in ~/.zshrc
_liedfl_complete() {
    local cur="${COMP_WORDS[COMP_CWORD]}"
    if (( COMP_CWORD <= 1 )); then
        COMPREPLY=($(compgen -W "COMMANDS --help --version --completion" -- "$cur"))
        return
    fi
    local cmd="${COMP_WORDS[1]}"
    case "$cmd" in
        COMMANDS_CASE) ;;
        *) return ;;
    esac
    local rest="${COMP_LINE#*${cmd}}"
    local choices
    choices=$(COMP_POINT=$COMP_POINT COMP_LINE="liedfl${rest}" liedfl "$cmd" -sc query=bash 2>/dev/null)
    COMPREPLY=($(compgen -o nospace -o default -W "$choices" -- "$cur"))
}
COMP_WORDBREAKS=${COMP_WORDBREAKS//=}
complete -o nospace -o default -F _liedfl_complete liedfl
""".replace("COMMANDS_CASE", "|".join(COMMANDS)).replace("COMMANDS", " ".join(COMMANDS))


def completion_script(shell: str) -> str:
    """The completion script for `shell` (bash, or zsh through bashcompinit), registered for `liedfl`."""
    if shell == "bash":
        return COMPLETION
    if shell == "zsh":
        return "autoload -U +X compinit && compinit\nautoload -U +X bashcompinit && bashcompinit\n" + COMPLETION
    raise ValueError(shell)


def _dispatch(command: str, cfg):
    if command == "train":
        from .commands.train import run_train

        return run_train(cfg)
    if command == "resume":
        from .commands.train import run_resume

        return run_resume(cfg)
    if command == "data":
        from .commands.data import run_data
        from .files.signals import set_phase

        set_phase("data generation", "nothing written")
        return run_data(cfg)
    if command == "rollout":
        from .commands.rollout import run_rollout

        return run_rollout(cfg)
    if command == "eval":
        from .commands.evaluate import run_eval
        from .config.runs import check_run_files

        check_run_files(cfg.run)
        return run_eval(cfg)
    if command == "report":
        from .commands.report import run_report

        return run_report(cfg)
    if command == "export":
        from .commands.export_model import run_export

        return run_export(cfg)
    raise AssertionError(command)


def _job_context(command: str, cfg) -> tuple[bool, Path | None, Path | None]:
    """(multirun?, the folder that gets status.json, Hydra's run folder) of the running job."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return False, None, None
    hc = HydraConfig.get()
    hydra_dir = Path(str(hc.runtime.output_dir))
    if hc.mode == RunMode.MULTIRUN:
        return True, hydra_dir, hydra_dir
    if command == "resume":  # the run continues in its own folder: status.json says "ok" once it finishes
        return False, Path(str(cfg.resume)), hydra_dir  # (a failed resume leaves the run's status as it was)
    if command != "train":  # eval/rollout/report/data write into existing folders: no status file
        return False, None, hydra_dir
    try:
        out = Path(str(cfg.paths.output_dir))
    except Exception:  # an unresolvable path: fall back to Hydra's folder
        out = hydra_dir
    return False, out, hydra_dir


def _has_content(d: Path) -> bool:
    return d.is_dir() and any(e.name != ".hydra" and e.suffix != ".log" for e in d.iterdir())


def _record_failure(multirun: bool, status_dir, hydra_dir, message: str, code: int, status: str) -> None:
    from .commands.status import remove_unused_run_dir, write_status
    from .files.signals import phase

    if not multirun and hydra_dir is not None:
        remove_unused_run_dir(hydra_dir)
    if status_dir is None or not status_dir.is_dir():
        return
    extra = {"phase": phase()} if status == "interrupted" and phase() else {}
    if multirun or _has_content(status_dir):
        with contextlib.suppress(OSError):
            write_status(status_dir, status, code, error=message, **extra)


def _log_file(command: str, cfg) -> Path | None:
    """The run's `train.log`: `liedfl train` (the run folder, each job's in a sweep) and `liedfl train
    resume=<run>` (appended to the resumed run's); None for the other commands."""
    if command == "train":
        _, status_dir, _ = _job_context(command, cfg)
        return status_dir / "train.log" if status_dir is not None and status_dir.is_dir() else None
    if command == "resume":
        run = Path(str(cfg.get("resume") or ""))
        return run / "train.log" if str(run) not in ("", ".", "???") and run.is_dir() else None
    return None


def _lock_folder(command: str, cfg) -> Path | None:
    """The run folder the job writes into, which it locks (`locks.py`): the new run's (train, each job of
    a sweep), the resumed run's, the run rolled out or evaluated; None for data and report."""
    if command == "train":
        _, status_dir, _ = _job_context(command, cfg)
        return status_dir if status_dir is not None and status_dir.is_dir() else None
    key = {"resume": "resume", "rollout": "run", "eval": "run"}.get(command)
    if key is None:
        return None
    value = str(cfg.get(key) or "")
    return Path(value) if value not in ("", ".", "???") and Path(value).is_dir() else None


def _run(command: str, cfg):
    """One job (`_run_job`) holding its run folder's lock, with SIGTERM raised as an exception
    (`signals.py`) and everything it prints mirrored to the run's train.log."""
    from .config.preflight import classify
    from .display.ui import fail
    from .files.locks import RunLocked, acquire, release_folder
    from .files.signals import terminate_as_exception

    with terminate_as_exception():
        folder = None
        try:
            folder = _lock_folder(command, cfg)
            if folder is not None:
                acquire(folder, command)
            log = _log_file(command, cfg)
            if log is None:
                return _run_job(command, cfg)
            from .display.ui import log_to

            with log_to(log):
                return _run_job(command, cfg)
        except (RunLocked, KeyboardInterrupt) as e:  # (the job's own errors are handled in _run_job)
            known = classify(e)
            assert known is not None
            fail(*known)
        finally:
            if folder is not None:
                release_folder(folder)


def _run_job(command: str, cfg):
    """One job: preflight, the command, status.json. In a multirun a failing job records its status
    and returns (the sweep goes on; `main` reports the count); in a single run it exits non-zero."""
    import time

    from .commands.status import write_status
    from .display.ui import error_line, fail

    _one_line_warnings()  # (also in launcher worker processes, which do not run `main`)
    _no_collection_at_exit()
    multirun, status_dir, hydra_dir = _job_context(command, cfg)
    failure_dir = None if command == "resume" and not multirun else status_dir
    t0 = time.perf_counter()
    try:
        preflight(command, cfg)
        result = _dispatch(command, cfg)
    except SystemExit:
        raise
    except BaseException as e:
        known = classify(e)
        if known is None:  # a bug: keep its traceback, but record the failure first
            _record_failure(multirun, failure_dir, hydra_dir, f"internal error: {type(e).__name__}: {e}", 1, "failed")
            if multirun and isinstance(e, Exception):
                import traceback

                traceback.print_exc()
                return None
            raise
        message, code = known
        interrupted = isinstance(e, KeyboardInterrupt) or code in (130, 143)
        if interrupted and command == "resume":  # the run went on training: say that it stopped, and where
            failure_dir = status_dir
        _record_failure(multirun, failure_dir, hydra_dir, message, code, "interrupted" if interrupted else "failed")
        if multirun and not interrupted:
            assert status_dir is not None  # a multirun job's status folder is Hydra's job folder
            error_line(f"[job {status_dir.name}] {message}")
            return None
        fail(message, code)
    if status_dir is not None:
        write_status(status_dir, "ok", 0, seconds=round(time.perf_counter() - t0, 3), **_threads())
    return result


def _threads() -> dict:
    """torch's intra-op threads in the job, for status.json (one per job when jobs share a machine)."""
    torch = sys.modules.get("torch")
    return {} if torch is None else {"threads": int(torch.get_num_threads())}


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


RUNS_DIR = Path("outputs") / "runs"


def version() -> str:
    """`liedfl <version>`: the installed distribution's version (the package's when not installed)."""
    try:
        from importlib.metadata import version as dist_version

        return f"liedfl {dist_version('liedfl')}"
    except Exception:  # not installed (e.g. run from a source tree)
        from . import __version__

        return f"liedfl {__version__}"


def latest_run(root: Path = RUNS_DIR) -> Path | None:
    """The run folder under `root` whose checkpoints/last.pt was modified last (None if there is none)."""
    best: tuple[float, Path] | None = None
    if root.is_dir():
        for d in root.iterdir():
            try:
                mtime = (d / "checkpoints" / "last.pt").stat().st_mtime
            except OSError:
                continue
            if best is None or mtime > best[0]:
                best = (mtime, d)
    return None if best is None else best[1]


def _resolve_latest(command: str, args: list[str]) -> list[str]:
    """`run=latest` (rollout, eval) and `resume=latest` (train): the newest run under outputs/runs/."""
    key = {"rollout": "run", "eval": "run", "export": "run", "resume": "resume"}.get(command)
    if key is None or f"{key}=latest" not in args:
        return args
    run = latest_run()
    if run is None:
        print(
            f"error: {key}=latest: no run under {RUNS_DIR}/ (no run folder with checkpoints/last.pt)", file=sys.stderr
        )
        raise SystemExit(2)
    return [f"{key}={run}" if a == f"{key}=latest" else a for a in args]


def main() -> None:
    """`liedfl ...`; output cut short by a closed pipe (`liedfl train --help | head -1`) ends quietly with
    exit code 141 (128 + SIGPIPE, as for other commands killed by a closed pipe)."""
    try:
        try:
            _main()
        finally:
            from .files.locks import release_all

            release_all()  # (the job releases its lock; this covers a lock taken before the job ran)
            sys.stdout.flush()
    except BrokenPipeError:
        # Python would complain again when it flushes stdout at exit: point stdout at /dev/null
        with contextlib.suppress(OSError, ValueError):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        raise SystemExit(141) from None


def _main() -> None:
    argv = sys.argv[1:]
    if argv and argv[0] in ("-V", "--version"):
        print(version())
        raise SystemExit(0)
    if not argv or argv[0] in ("-h", "--help", "help"):
        print(USAGE)
        raise SystemExit(0 if argv else 2)
    if argv[0] == "--completion":
        shell = argv[1] if len(argv) > 1 else "bash"
        if shell not in ("bash", "zsh"):
            print(f"error: --completion {shell}: choose bash or zsh", file=sys.stderr)
            raise SystemExit(2)
        print(completion_script(shell), end="")
        raise SystemExit(0)
    command = argv[0]
    if command == "train" and any(a.startswith("resume=") for a in argv[1:]):
        command = "resume"  # `liedfl train resume=<run dir>` has its own primary config (liedfl_cli/conf/resume.yaml)
    if command not in COMMANDS and command != "resume":
        print(f"error: unknown command {command!r}{_did_you_mean(command)}\n\n{USAGE}", file=sys.stderr)
        raise SystemExit(2)
    if any(a in ("--version", "-V") for a in argv[1:]):  # liedfl's version, not Hydra's
        print(version())
        raise SystemExit(0)
    argv = [argv[0], *_resolve_latest(command, argv[1:])]
    if not (CONF_DIR / f"{command}.yaml").is_file():
        print(
            f"error: config directory {CONF_DIR} not found; reinstall liedfl (`pip install .`)",
            file=sys.stderr,
        )
        raise SystemExit(2)
    if command in DIR_ARGS:
        _check_dir_arg(command, argv[1:])
    _check_flags(command, argv[1:])
    _check_dataset_choice(argv[1:])
    _one_line_warnings()
    _no_collection_at_exit()
    from .commands.status import reset

    reset()
    import hydra

    @hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=command)
    def _hydra_main(cfg):
        try:
            return _run(command, cfg)
        except Exception as e:  # e.g. train.log cannot be opened: one line here, not Hydra's extra line
            known = classify(e)
            if known is None:
                raise
            from .display.ui import fail

            fail(*known)

    sys.argv = [f"liedfl-{command}", *_with_help_overrides(command, argv[1:])]
    # Hydra prints its own errors over several lines and exits; with HYDRA_FULL_ERROR it raises them
    # instead, so that they can be reduced to one line here (the user's HYDRA_FULL_ERROR=1 keeps
    # Hydra's full text).
    user_full_error = os.environ.get("HYDRA_FULL_ERROR")
    os.environ["HYDRA_FULL_ERROR"] = "1"
    launcher_error = None
    from .config.hydra_mode import without_mode_composition

    try:
        with without_mode_composition(CONF_DIR, sys.argv[1:]):  # one composition instead of two
            _hydra_main()
    except KeyboardInterrupt:
        _interrupted_sweep()
        raise
    except Exception as e:
        if user_full_error == "1":
            raise
        launcher_error = _launcher_failure(e)
        if launcher_error is None:
            _hydra_failure(command, e)
    finally:
        if user_full_error is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = user_full_error
    _sweep_exit(launcher_error)


def _interrupted_sweep() -> None:
    """Ctrl-C in the process that waits for the jobs of a submitit sweep: one line (the jobs run in
    processes of their own; on a cluster they go on)."""
    from .commands.status import jobs_ran_elsewhere, sweep_dir
    from .display.ui import fail

    sd = sweep_dir()
    if sd is not None and jobs_ran_elsewhere():
        fail(
            f"interrupted: stopped waiting for the jobs of {sd} (jobs that were not interrupted go on;"
            f" `liedfl report sweep={sd}` lists them once they are done)",
            130,
        )


def _launcher_failure(e: Exception) -> str | None:
    """One line for an error of the sweep's launcher (None for anything else). submitit raises in the
    launching process when a job died without returning (killed, out of memory, past its time limit,
    interrupted) or could not be submitted; the jobs' own failures are recorded in their folders."""
    from .commands.status import sweep_dir

    if sweep_dir() is None or type(e).__module__.split(".")[0] != "submitit":
        return None
    lines = [ln.strip() for ln in str(e).splitlines() if ln.strip() and not set(ln.strip()) <= set("-=")]
    text = type(e).__name__ if not lines else lines[0] if len(lines) == 1 else f"{lines[0]} ... {lines[-1]}"
    return f"{type(e).__name__}: {text}" if not text.startswith(type(e).__name__) else text


def _with_help_overrides(command: str, args: list[str]) -> list[str]:
    """`args` with `_help_overrides` inserted next to the user's own overrides: argparse takes the
    overrides as one run of positional words, so `dataset=import --help <ours>` would be refused."""
    extra = _help_overrides(command, args)
    if not extra:
        return list(args)
    i = next((i for i, a in enumerate(args) if not a.startswith("-") and "=" in a), len(args))
    return [*args[:i], *extra, *args[i:]]


def _help_overrides(command: str, args: list[str]) -> list[str]:
    """With --help: Hydra's help names the program `liedfl <command>` (not the entry point's name)."""
    if not any(a in ("--help", "-h") for a in args):
        return []
    what = COMMANDS.get(command, "continue an interrupted run: liedfl train resume=<run dir>")
    return [
        f"hydra.help.app_name='liedfl {command}'",
        f"hydra.help.header='liedfl {command}: {what}. Usage: liedfl {command} [key=value ...] [-m] [--cfg job]'",
    ]


def _did_you_mean(command: str) -> str:
    """` (did you mean train?)` for a misspelt command, "" when nothing is close."""
    import difflib

    close = difflib.get_close_matches(command, list(COMMANDS), n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""


RECORDING_SUFFIXES = (".csv", ".txt", ".npz")
DATASET_SUFFIXES = (".h5", ".hdf5", ".hdf")


def _check_dataset_choice(args: list[str]) -> None:
    """`dataset=chain.h5` names a file where the dataset group wants a scene (`dataset=file` / `import`):
    one line with the overrides that read it, before Hydra says it cannot find `dataset/chain.h5`."""
    for a in args:
        key, sep, value = a.partition("=")
        if not sep or key.lstrip("+~") != "dataset":
            continue
        suffix = Path(value).suffix.lower()
        if suffix in DATASET_SUFFIXES:
            hint = f"dataset=file dataset.path={value}"
        elif suffix in RECORDING_SUFFIXES:
            hint = f"dataset=import dataset.path={value} dataset.rotation=wxyz (or xyzw, matrix)"
        else:
            continue
        print(f"error: {a}: dataset= takes a scene name, not a file; for this file: {hint}", file=sys.stderr)
        raise SystemExit(2)


def _check_flags(command: str, args: list[str]) -> None:
    """Hydra's command-line parser, with its errors (an unknown flag, a flag without its value) as
    one line instead of argparse's usage block; so is Hydra's refusal of two modes at once (e.g.
    `-m ... --cfg job`: Hydra either runs a sweep or prints one composed config)."""
    if "--version" in args:
        return
    try:
        from hydra._internal.utils import get_args_parser
    except ImportError:  # pragma: no cover (another Hydra layout: Hydra reports it itself)
        return
    parser = get_args_parser()

    def error(message: str) -> NoReturn:
        print(f"error: {message} (usage: liedfl {command} [key=value ...] [-m] [--cfg job] [--help])", file=sys.stderr)
        raise SystemExit(2)

    parser.error = error  # type: ignore[method-assign]  # replaces Hydra's parser's method on purpose
    parsed = parser.parse_args(args)
    modes = [
        name
        for name, on in (
            ("-m/--multirun", parsed.multirun),
            ("-r/--run", parsed.run),
            (f"--cfg {parsed.cfg}", parsed.cfg is not None),
            ("--info", parsed.info is not None),
            ("--shell-completion", parsed.shell_completion),
        )
        if on
    ]
    if len(modes) > 1 and not (parsed.help or parsed.hydra_help):
        print(
            f"error: {' and '.join(modes)} cannot be combined (Hydra runs one of them); to see a job's"
            f" composed config, give one value per swept key without -m: liedfl {command} --cfg job key=value ...",
            file=sys.stderr,
        )
        raise SystemExit(2)


def _no_collection_at_exit() -> None:
    """Freeze every object (`gc.freeze`) when the interpreter exits, before its last garbage collections:
    they then skip the millions of objects torch and its dependencies allocate, which took ~1 s of every
    `liedfl` process's end at load 6 (0.2 s frozen). Nothing waits on a collection at exit: files are
    closed (and renamed) where they are written, and atexit handlers run as before. Registered once per
    process, also in launcher worker processes."""
    import atexit
    import gc

    if not _EXIT_FREEZE:
        _EXIT_FREEZE.append(True)
        atexit.register(gc.freeze)


_EXIT_FREEZE: list[bool] = []


def _one_line_warnings() -> None:
    """liedfl's own warnings (data projected, coarse sampling, ...) as one `warning: ...` line."""
    import warnings

    from .errors import LiedflWarning

    shown = warnings.showwarning
    if getattr(shown, "_liedfl", False):
        return

    def show(message, category, filename, lineno, file=None, line=None):
        if isinstance(category, type) and issubclass(category, LiedflWarning):
            from .display.ui import warning_line

            warning_line(str(message))
        else:
            shown(message, category, filename, lineno, file, line)

    show._liedfl = True  # type: ignore[attr-defined]  # a function attribute: marks the hook as installed
    warnings.showwarning = show


def _sweep_exit(launcher_error: str | None = None) -> None:
    """After a multirun: one summary line, exit code = number of failed jobs (capped at 100).

    The summary is read from the job folders (status.json), whichever process ran the jobs. Jobs that
    ran elsewhere (submitit) printed their errors into their logs: their error lines are repeated
    here. launcher_error: the launcher stopped the sweep (the exit code is then at least 1)."""
    from .commands.status import jobs_ran_elsewhere, sweep_dir, sweep_summary
    from .display.ui import console, error_line, fail

    sd = sweep_dir()
    if sd is None or not Path(sd).is_dir():
        if launcher_error is not None:
            fail(f"launcher: {launcher_error}")
        return
    failed, total, failures = sweep_summary(sd)
    if jobs_ran_elsewhere():
        for d, message in failures:
            error_line(f"[job {d.name}] {message}")
    if failed:
        error_line(f"{failed} of {total} jobs failed: {', '.join(str(d) for d, _ in failures)}")
    if launcher_error is not None:
        error_line(
            f"launcher: {launcher_error} (jobs still running go on; `liedfl report sweep={sd}` lists them"
            f" once they are done; job logs: {Path(sd) / '.submitit'})"
        )
    if failed or launcher_error is not None:
        raise SystemExit(min(max(failed, 1), 100))
    console.print(f"all {total} jobs finished: {sd}", highlight=False, soft_wrap=True)


def _hydra_failure(command: str, e: Exception) -> None:
    """Hydra's own errors (override grammar, composition, a missing option) as one line plus a hint;
    anything else goes on up with its traceback."""
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from .display.ui import fail

    if isinstance(e, OSError) and e.filename:  # e.g. a run folder that cannot be created
        from .config.preflight import os_error_line

        fail(os_error_line(e))
    yaml_error = _yaml_error(e)
    if yaml_error is not None:
        fail(yaml_error)
    if not isinstance(e, (HydraException, OmegaConfBaseException)):
        raise e
    unknown = unknown_key_message(command, e)
    if unknown is not None:
        fail(unknown)
    message = hydra_message(command, e)
    if "hydra/launcher/submitit" in message:  # the plugin's configs exist only once it is installed
        message += ' (the submitit launchers need hydra-submitit-launcher: pip install -e ".[cluster]")'
    fail(message + " (HYDRA_FULL_ERROR=1 shows Hydra's full message)")


def _yaml_error(e: BaseException) -> str | None:
    """One line for a YAML syntax error in a config file (an experiment, a `--config-dir` file):
    the file, line and column, and what the parser found; None for other errors."""
    import yaml

    while e is not None and not isinstance(e, yaml.YAMLError):
        e = e.__cause__ or e.__context__  # type: ignore[assignment]
    if e is None:
        return None
    mark = getattr(e, "problem_mark", None) or getattr(e, "context_mark", None)
    problem = getattr(e, "problem", None) or str(e).splitlines()[0]
    context = getattr(e, "context", None)
    where = f"{mark.name}: line {mark.line + 1}, column {mark.column + 1}" if mark is not None else "a config file"
    return f"{where}: YAML syntax error: {problem}" + (f" ({context})" if context else "")


def hydra_message(command: str, e: BaseException) -> str:
    """One line from a (multi-line) Hydra exception: its first line, the informative next lines, the
    available options of a missing config and, for an unknown key, the closest existing one."""
    import re

    text = str(e)
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    options: list[str] = []
    rest: list[str] = []
    in_options = False
    for ln in lines[1:]:
        if ln.startswith("Available options"):
            in_options = True
            continue
        if in_options and re.fullmatch(r"[\w.\-/]+", ln):
            options.append(ln)
            continue
        in_options = False
        if ln.startswith(
            ("See http", "full_key:", "object_type", "reference_type", "Set the environment", "Config search path")
        ) or ln.startswith("provider="):
            continue
        rest.append(ln.rstrip("."))
    msg = (lines[0] if lines else type(e).__name__).rstrip(".")
    override = getattr(e, "override", None)
    if override is not None:
        msg = f"cannot parse override '{override}': {msg}"
    if rest:
        msg += ": " + "; ".join(rest)
    cause = e.__cause__
    if cause is not None and str(cause).strip():
        first = str(cause).strip().splitlines()[0].rstrip(".")
        if first not in msg:
            msg += f" ({first})"
    if options:
        msg += f" (available: {', '.join(options)})"
    m = re.search(r"Could not (?:override|append to|delete) '([^']+)'", text)
    if m:
        msg += _closest_existing_key(command, m.group(1))
    return msg


def _user_overrides(dotted: str) -> list[str]:
    """The overrides on the command line (sys.argv, as `main` hands it to Hydra) other than the ones
    of `dotted` and of hydra.*: the config the user asked for, without the failing key."""
    out = []
    for a in sys.argv[1:]:
        if a.startswith("-") or "=" not in a:
            continue
        key = a.split("=", 1)[0].lstrip("+~")
        if key != dotted and not key.startswith("hydra."):
            out.append(a)
    return out


def _parent_node(command: str, dotted: str):
    """The config node that would hold `dotted`, composed with the user's other overrides (e.g.
    dataset=file, whose `path` a misspelt `dataset.pth` is close to); without the sweeps when they do
    not compose, then without any. None when there is no such node."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import DictConfig, OmegaConf

    overrides = _user_overrides(dotted)
    attempts = [overrides, [o for o in overrides if "," not in o.split("=", 1)[1]], []]
    base = None
    for attempt in attempts:
        try:
            GlobalHydra.instance().clear()
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                base = compose(config_name=command, overrides=attempt)
            break
        except Exception:
            continue
    if base is None:
        return None
    parent = dotted.rpartition(".")[0]
    node = OmegaConf.select(base, parent) if parent else base
    return node if isinstance(node, DictConfig) else None


def _closest_existing_key(command: str, dotted: str) -> str:
    """' (did you mean X?)' (the closest key of the node `dotted` would be in; a looser match when
    none is close); '' when nothing is."""
    import difflib

    try:
        node = _parent_node(command, dotted)
    except Exception:  # a hint only
        return ""
    if node is None:
        return ""
    parent, _, key = dotted.rpartition(".")
    keys = sorted(str(k) for k in node if k != "hydra")
    match = difflib.get_close_matches(key, keys, n=1, cutoff=0.6) or difflib.get_close_matches(key, keys, cutoff=0.4)
    return f" (did you mean '{parent + '.' if parent else ''}{match[0]}'?)" if match else ""


def unknown_key_message(command: str, e: BaseException) -> str | None:
    """Hydra's refusal of an override of a key that does not exist (`dataset.pth=3`: "Could not
    override 'dataset.pth' ... Key 'pth' is not in struct") as the schema's one line for a misspelt
    key: "unknown config key 'dataset.pth' for scene 'file' (did you mean 'dataset.path'?)"."""
    import re

    text = str(e) + " " + str(e.__cause__ or "")
    m = re.search(r"Could not override '([^']+)'", text)
    if m is None or "not in struct" not in text:
        return None
    dotted = m.group(1)
    try:
        node = _parent_node(command, dotted)
    except Exception:  # a hint only
        node = None
    if node is None:
        return None
    from .config.schema import closest

    parent, _, key = dotted.rpartition(".")
    hint = _closest_existing_key(command, dotted)
    if not hint:
        hint = closest(key, [str(k) for k in node if k != "hydra"])
    where = f" for scene '{node.get('name')}'" if parent == "dataset" and node.get("name") else ""
    return f"unknown config key '{dotted}'{where}{hint}"


if __name__ == "__main__":
    main()
