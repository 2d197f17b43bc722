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
