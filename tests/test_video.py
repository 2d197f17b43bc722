"""Rollout videos rendered by MuJoCo: the plan is drawn into the scene. Rendering runs in a fresh
process, since MUJOCO_GL must be chosen before MuJoCo is first imported."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

SCRIPT = """
import sys
import numpy as np
from cdrb_cli.envs.render import choose_gl_backend
choose_gl_backend()
from cdrb_cli.envs.registry import family_of, make_spec
spec = make_spec(sys.argv[1])
fam = family_of(spec)
states = np.zeros((4, spec.obs_dim))
if spec.family == "pointmaze":
    states[:, :2] = [[-5.0, 0.0], [-5.0, 1.0], [-5.0, 2.0], [-5.0, 3.0]]
    goal = np.array([5.0, 5.0])
else:
    states[:, :6] = [1.3, 0.6, 0.45, 1.25, 0.65, 0.425]
    goal = np.array([1.3, 0.9, 0.425])
plan = states.copy()
plan[:, spec.goal_dims[:2]] += np.linspace(0.0, 0.3, 4)[:, None]
try:
    bare = fam.render_frames(spec, states, goal, every=1)
except Exception as exc:
    print("NO-GL", exc)
    sys.exit(0)
drawn = fam.render_frames(spec, states, goal, every=1, plan=plan)
np.savez(sys.argv[2], bare=np.stack(bare), drawn=np.stack(drawn))
"""


@pytest.mark.parametrize("env", ["maze-tight", "fetch-push-obstacle"])
def test_mujoco_frames_draw_the_plan_into_the_scene(tmp_path, env):
    out = tmp_path / "frames.npz"
    proc = subprocess.run([sys.executable, "-c", SCRIPT, env, out], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    if proc.stdout.startswith("NO-GL"):
        pytest.skip(f"MuJoCo cannot render on this machine: {proc.stdout.strip()}")
    frames = np.load(out)
    bare, drawn = frames["bare"], frames["drawn"]
    assert bare.shape == drawn.shape and len(bare) == 4
    differs = np.abs(drawn[-1].astype(int) - bare[-1].astype(int)).sum(-1) > 30
    assert differs.sum() > 50, "the plan's line is not in the picture"
    changed = drawn[-1][differs]
    assert (changed[:, 2] > changed[:, 0]).mean() > 0.5  # in the plan's colour (blue)


def test_a_second_run_into_the_same_folder_replaces_its_labels_gifs_and_nothing_else(tmp_path, monkeypatch):
    """GIFs are named <label>_<episode>_<outcome>.gif: a run that wrote episode 0 as a failure, then one where it
    succeeds, would leave both files (and episode 5 of a longer run) looking like the second run's. The earlier
    run's GIFs of that label go; other labels' and other files stay."""
    from cdrb_cli.envs import render
    from cdrb_cli.envs.registry import family_of, make_spec

    spec = make_spec("maze-tight")
    monkeypatch.setattr(type(family_of(spec)), "render_frames", lambda *a, **k: 1 / 0)  # matplotlib frames: quick
    folder = tmp_path / "gifs"
    folder.mkdir()
    stale = [folder / "cdrb_00_fail.gif", folder / "cdrb_05_success.gif", folder / "cdrb_100_fail.gif"]
    kept = [folder / "cdrbx_00_fail.gif", folder / "diffuser_00_fail.gif", folder / "cdrb_00_fail.gif.txt"]
    for path in stale + kept:
        path.write_bytes(b"earlier")
    states = np.array([[-1.0, -1.0, 0, 0], [-0.5, -1.0, 0, 0], [0.0, -1.0, 0, 0]])
    written = render.rollout_gifs(spec, [(states, states, np.array([0.0, -1.0]), True)], folder, label="cdrb")
    assert written == [folder / "cdrb_00_success.gif"] and written[0].read_bytes()[:3] == b"GIF"
    assert not any(p.exists() for p in stale)
    assert all(p.read_bytes() == b"earlier" for p in kept)
