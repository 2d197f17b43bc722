"""docs/tutorial.md's shell pipeline, run for real with tiny settings."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from cdrb_cli import artifacts

TUTORIAL = Path(__file__).resolve().parent.parent / "docs" / "tutorial.md"
TINY = {
    r"--episodes 1000": "--episodes 24",
    r"--k 1000": "--k 60",
    r"--steps 3000": "--steps 10 --set horizon=16 --set stride=10 --set net.dim=8 --set net.dim_mults=1,2 "
    "--set method.diffusion_steps=8",
    r"--seeds 0,1 --episodes 50": "--seeds 0 --episodes 2",
    r"-n 8 --show-steps 4": "-n 2 --show-steps 2",
}


@pytest.mark.slow
def test_tutorial_pipeline_runs(tmp_path):
    text = TUTORIAL.read_text()
    script = re.search(r"```bash\n(.*?)```", text, re.S).group(1)
    for pattern, tiny in TINY.items():
        assert re.search(pattern, script), pattern
        script = re.sub(pattern, tiny, script)
    bindir = Path(sys.executable).parent
    env = dict(os.environ, PATH=f"{bindir}{os.pathsep}{os.environ['PATH']}")
    proc = subprocess.run(["bash", "-c", script], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "| Maze Tight |" in proc.stdout
    for name, kind in [
        ("demos.h5", "demos"),
        ("buffer.h5", "buffer"),
        ("cdrb.h5", "model"),
        ("plans.h5", "plans"),
        ("eval-cdrb.h5", "eval"),
        ("eval-diffuser.h5", "eval"),
    ]:
        artifacts.load(tmp_path / name, kind)
    for name in ("demos.png", "plans.png", "results.png", "side-by-side.png"):
        assert (tmp_path / name).stat().st_size > 5000
