"""docs/tutorial.md's shell pipeline, run for real with tiny settings."""

from __future__ import annotations

from pathlib import Path

import pytest

from cdrb_cli import artifacts
from tests.factories import run_doc_block

TUTORIAL = Path(__file__).resolve().parent.parent / "docs" / "tutorial.md"
TINY = {
    r"--episodes 1000": "--episodes 24",
    r"--k 1000": "--k 60",
    r"--steps 3000": "--steps 10 --set horizon=16 --set stride=10 --set net.dim=8 --set net.dim_mults=1,2 "
    "--set method.diffusion_steps=8",
    r"--seeds 0,1 --episodes 50": "--seeds 0 --episodes 2",
    r"-n 8 --set keep_iterates=4": "-n 2 --set keep_iterates=2",
}


@pytest.mark.slow
def test_tutorial_pipeline_runs(tmp_path):
    proc = run_doc_block(TUTORIAL.read_text(), "", TINY, tmp_path, timeout=600)
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
