"""docs/tutorial_robot.md runs as written: every ```bash block of the page, in order, in an empty folder,
at a tiny budget (10 trajectories of 24 steps instead of 32 of 100, 2 epochs instead of 300), must exit 0
and leave the files the page talks about. The commands are read from the page, so the page and the
program cannot drift apart. Needs mujoco (the test extra)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from helpers import cli_env

REPO = Path(__file__).resolve().parents[1]
PAGE = REPO / "docs" / "tutorial_robot.md"
TINY = {  # what the page says -> what the test runs
    "--n-trajectories 32": "--n-trajectories 10 --steps 24",
    "train.epochs=300": "train.epochs=2 ui.progress=false runtime.threads=1",
    "python scripts/": f"{sys.executable} {REPO / 'scripts'}/",
    "python - <<": f"{sys.executable} - <<",
}


def bash_blocks(text: str) -> list[str]:
    """The ```bash blocks of a markdown text, in order."""
    return re.findall(r"^```bash\n(.*?)^```", text, flags=re.S | re.M)


def tiny(block: str) -> str:
    for old, new in TINY.items():
        block = block.replace(old, new)
    return block


def test_the_page_has_the_five_steps():
    blocks = bash_blocks(PAGE.read_text())
    text = "\n".join(blocks)
    for command in (
        "scripts/mujoco_chain.py",
        "infer_joints.py",
        "liedfl train",
        "liedfl export",
        "format=mjcf",
        "replay(",
    ):
        assert command in text, command
    for old in TINY:
        assert old in text, f"the page no longer says {old!r}: update TINY"


def test_every_command_of_the_tutorial_runs(tmp_path):
    pytest.importorskip("mujoco")
    env = cli_env()
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])])
    env["LIEDFL_DATA_DIR"] = str(tmp_path / "data")
    bin_dir = Path(sys.executable).parent  # the `liedfl` of this interpreter first
    env["PATH"] = os.pathsep.join([str(bin_dir), env.get("PATH", "")])
    for block in bash_blocks(PAGE.read_text()):
        script = tiny(block)
        proc = subprocess.run(["bash", "-euo", "pipefail", "-c", script], cwd=tmp_path, env=env,
                              capture_output=True, text=True, timeout=300)  # fmt: skip
        assert proc.returncode == 0, f"{script}\n-> {proc.returncode}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
        assert "Traceback" not in proc.stderr, proc.stderr
    for f in ("arm.h5", "my_arm.h5", "arm.xml", "arm_run/joints.json", "arm_run/recovery.json",
              "arm_run/plots/error_per_body.png", "arm_run/plots/skeleton.png"):  # fmt: skip
        assert (tmp_path / f).is_file(), f
    assert "<mujoco" in (tmp_path / "arm.xml").read_text()
    assert "MuJoCo replay of" in proc.stdout
