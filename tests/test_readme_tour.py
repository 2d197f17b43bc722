"""The README's tour, extracted and run as written in a fresh folder, with only its sizes made small."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from cdrb_cli import artifacts
from tests.factories import run_doc_block

ROOT = Path(__file__).resolve().parent.parent
#: the sizes the test shrinks (each must occur in the tour: a tour edited away from them fails here, not silently)
SMALL = {
    r"-n 1000 ": "-n 40 ",
    r"--k 1000 ": "--k 60 ",
    r"--steps 3000 ": "--steps 10 --set horizon=16 --set stride=10 --set net.dim=8 --set net.dim_mults=1,2 "
    "--set method.diffusion_steps=8 ",
    r"--seeds 0,1,2,3,4 --episodes 100 ": "--seeds 0 --episodes 2 ",
    r"-n 8 --set keep_iterates=4 ": "-n 2 --set keep_iterates=2 ",
}


@pytest.mark.slow
def test_the_readme_tour_runs_as_written_in_a_fresh_folder(tmp_path):
    (tmp_path / "experiments").symlink_to(ROOT / "experiments")  # the tour runs beside the repository's files
    env = {"MINARI_DATASETS_PATH": str(tmp_path / "minari"), "MPLBACKEND": "Agg"}
    proc = run_doc_block((ROOT / "README.md").read_text(), r"## A tour\n", SMALL, tmp_path, env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    folder = tmp_path / "tour"
    for name, kind in [
        ("demos.h5", "demos"),
        ("buffer.h5", "buffer"),
        ("cdrb.h5", "model"),
        ("plans.h5", "plans"),
        ("eval-cdrb.h5", "eval"),
        ("imported.h5", "demos"),
    ]:
        artifacts.load(folder / name, kind)
    for name in ("demos.png", "buffer.png", "plans.png", "results.png", "eval-plans.png", "curve.png"):
        assert (folder / name).stat().st_size > 5000, name
    assert any((folder / "gifs").glob("*.gif"))
    exported = artifacts.load(folder / "demos.h5", "demos").arrays["steps/observations"]
    assert artifacts.load(folder / "imported.h5", "demos").arrays["steps/observations"].shape == exported.shape
    assert "| Maze Tight |" in proc.stdout  # the report's table on stdout


def test_a_doc_scripts_cdrb_gives_its_output_exit_code_and_folder(tmp_path):
    """The `cdrb` the doc scripts run (a warm fork on Linux) behaves as the installed one: stdout where the script
    sends it, the one-line error on stderr, the exit code, the script's folder and environment."""
    block = (
        "## S\n```bash\nmkdir -p sub && cd sub\ncdrb envs > envs.txt\n"
        'if cdrb inspect "$WHAT" 2> err.txt; then exit 9; else echo "rc=$?"; fi\n'
        'echo "out=$(cdrb inspect "$WHAT" 2>&1 || true)"\necho "which=$(command -v cdrb)"\n```\n'
    )
    proc = run_doc_block(block, r"## S\n", {}, tmp_path, {"WHAT": "nothing.h5"})
    assert proc.returncode == 0, proc.stderr
    assert "maze-tight" in (tmp_path / "sub" / "envs.txt").read_text()
    assert (tmp_path / "sub" / "err.txt").read_text().strip() == "error: nothing.h5: no such file (check the path)"
    lines = proc.stdout.splitlines()
    assert lines[:2] == ["rc=2", "out=error: nothing.h5: no such file (check the path)"]
    assert ("/cdrb-shell-" in lines[2]) == sys.platform.startswith("linux")  # the warm `cdrb` was the one run
