"""Packaging: the configs and the CMU recordings (with their attribution) ship inside the package, so a
built wheel installed anywhere runs `liedfl train budget=smoke` and finds Exp 4's BVH files; `liedfl
--help` and the completion script name the program `liedfl`; LICENSE and CITATION.cff agree with
pyproject.toml."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("LIEDFL_DATA_DIR", "HYDRA_FULL_ERROR", "PYTHONPATH")}
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", MPLBACKEND="Agg", COLUMNS="120", **extra)
    return env


def test_wheel_ships_the_configs_and_runs_the_smoke_budget(tmp_path):
    # build from a copy of the sources (the build leaves build/ and *.egg-info next to them)
    src = tmp_path / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(ROOT / "liedfl_cli", src / "liedfl_cli", ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", str(src), "--no-deps", "--no-build-isolation", "-q", "-w", str(wheels)],
        check=True,
        capture_output=True,
        env=_env(),
        timeout=300,
    )
    (wheel,) = wheels.glob("liedfl-*.whl")
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        yamls = sorted(n for n in names if n.endswith(".yaml"))
        mocap = {n: z.read(n) for n in names if n.startswith("liedfl_cli/data/cmu_mocap/")}
    shipped = ROOT / "liedfl_cli" / "data" / "cmu_mocap"
    for name in ("49_06.bvh", "49_07.bvh", "ATTRIBUTION.md", "PROVENANCE.md"):  # byte for byte (sha256 in PROVENANCE)
        assert mocap.get(f"liedfl_cli/data/cmu_mocap/{name}") == (shipped / name).read_bytes(), name
    expected = sorted(
        f"liedfl_cli/conf/{p.relative_to(ROOT / 'liedfl_cli' / 'conf').as_posix()}"
        for p in (ROOT / "liedfl_cli" / "conf").rglob("*.yaml")
    )
    assert yamls == expected and "liedfl_cli/conf/train.yaml" in yamls and "liedfl_cli/conf/dataset/file.yaml" in yamls

    # install it on its own (dependencies: those already installed) and run it from elsewhere
    site = tmp_path / "site"
    subprocess.run(
        [sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--target", str(site), str(wheel)],
        check=True,
        capture_output=True,
        env=_env(),
        timeout=300,
    )
    work = tmp_path / "work"
    work.mkdir()
    env = _env(PYTHONPATH=str(site))
    # the installed copy, not the sources; Exp 4's config paths (data/cmu_mocap/*.bvh, relative) resolve to
    # the installed recordings; then the smoke budget trains (one interpreter for all three)
    where_found = (
        "import liedfl_cli; print(liedfl_cli.__file__)\n"
        "from liedfl_cli.data.mocap import _resolve; print(_resolve('data/cmu_mocap/49_07.bvh'), flush=True)\n"
    )
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            where_found + "from liedfl_cli.cli import main; main()",
            "train",
            "budget=smoke",
            "ui.progress=false",
            "eval.plots=false",
        ],  # (plots are not what the wheel is tested for)
        cwd=work,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    where, found = proc.stdout.splitlines()[:2]
    assert Path(where).is_relative_to(site), where
    assert Path(found).is_relative_to(site) and Path(found).stat().st_size > 100_000, found
    (run,) = (work / "outputs" / "runs").iterdir()
    assert (run / "eval.md").is_file() and (run / "train.log").is_file()
    assert "trained 2 epochs" in (run / "train.log").read_text()


def test_help_and_completion_name_liedfl(tmp_path):
    def liedfl(*args):
        cmd = [sys.executable, "-m", "liedfl_cli", *args]
        return subprocess.run(cmd, cwd=tmp_path, env=_env(PYTHONPATH=str(ROOT)), capture_output=True, text=True)

    out = liedfl("--help").stdout
    assert out.startswith("usage: liedfl {train,data,rollout,eval,report,export}") and "--completion" in out
    out = liedfl("train", "--help").stdout
    assert out.startswith("liedfl train: train and evaluate a model") and "liedfl-train" not in out
    script = liedfl("--completion", "bash").stdout
    assert "complete -o nospace -o default -F _liedfl_complete liedfl" in script
    assert liedfl("--completion", "fish").returncode == 2
    if shutil.which("bash") is None:
        return
    # the script completes the commands itself and the config keys through Hydra (`liedfl <cmd> -sc query=bash`)
    shim = tmp_path / "bin"
    shim.mkdir()
    (shim / "liedfl").write_text(f'#!/bin/sh\nexec "{sys.executable}" -m liedfl_cli "$@"\n')
    (shim / "liedfl").chmod(0o755)
    test = (
        script
        + '\nCOMP_WORDS=(liedfl tr); COMP_CWORD=1; COMP_LINE="liedfl tr"; _liedfl_complete; echo "A:${COMPREPLY[*]}"'
        + '\nCOMP_WORDS=(liedfl train dataset=he); COMP_CWORD=2; COMP_LINE="liedfl train dataset=he"; '
        + 'COMP_POINT=${#COMP_LINE}; _liedfl_complete; echo "B:${COMPREPLY[*]}"\n'
    )
    env = _env(PYTHONPATH=str(ROOT), PATH=f"{shim}{os.pathsep}{os.environ['PATH']}")
    out = subprocess.run(
        ["bash", "-c", test], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
    ).stdout
    assert "A:train" in out and "B:dataset=heavy_se3 dataset=heavy_so3" in out, out


def test_license_and_citation_match_the_project():
    import re

    pyproject = (ROOT / "pyproject.toml").read_text()  # (tomllib needs Python 3.11; liedfl supports 3.10)
    version = re.search(r'^version = "([^"]+)"', pyproject, re.M)
    assert version and re.search(r'^license = \{ text = "MIT" \}', pyproject, re.M)
    license_text = (ROOT / "LICENSE").read_text()
    assert license_text.startswith("MIT License") and "liedfl developers" in license_text
    cff = (ROOT / "CITATION.cff").read_text()
    assert "cff-version: 1.2.0" in cff and f'version: "{version.group(1)}"' in cff
    assert "2607.12627" in cff and "Learning Forced Multibody Dynamics on Lie Groups" in cff
    assert "https://arxiv.org/abs/2607.12627" in (ROOT / "README.md").read_text()
