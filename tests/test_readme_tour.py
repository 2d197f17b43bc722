"""The README's tour, extracted and run as written in a fresh folder, with only its sizes made small."""

from __future__ import annotations

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
