"""The stock environments as gymnasium envs (`import cdrb_cli.gym`): every id `cdrb envs` lists can be made, reset
and stepped, and a cdrb plan executed in the gymnasium env does what `cdrb eval` measured on the same pair."""

from __future__ import annotations

import subprocess
import sys

import gymnasium
import numpy as np
import pytest

from cdrb_cli import artifacts


def test_every_stock_id_is_a_gymnasium_env():
    import cdrb_cli.gym as cg
    from cdrb_cli.envs.registry import FAMILIES

    ids = [i for fam in FAMILIES.entries() for i in fam.env_ids()]
    assert cg.register_envs() == [cg.gym_id(i) for i in ids] and len(ids) >= 14
    for env_id in ids:
        env = gymnasium.make(cg.gym_id(env_id))
        obs, info = env.reset(seed=3)
        spec = env.unwrapped.cdrb_spec
        assert spec.id == env_id and obs.shape == (spec.obs_dim,) and info["goal"].shape == (spec.goal_dim,)
        assert not env.unwrapped.collides(obs[None]).any()  # a protocol start is free
        again, _ = env.reset(seed=3)
        np.testing.assert_array_equal(obs, again)  # seeded resets repeat
        obs, reward, terminated, truncated, info = env.step(np.zeros(spec.action_dim))
        assert obs.shape == (spec.obs_dim,) and reward in (0.0, 1.0) and terminated == info["is_success"]
        env.close()
    # the module path form imports cdrb itself
    env = gymnasium.make("cdrb_cli.gym:cdrb/maze-v0")
    assert env.unwrapped.cdrb_spec.id == "maze"
    env.close()


@pytest.mark.parametrize("method", ["cdrb", "mlp"])
def test_a_plan_executed_in_the_gymnasium_env_matches_cdrb_eval(tiny_models, tmp_path, cdrb, method):
    from cdrb_cli.envs.registry import CONTROLLERS
    from cdrb_cli.gym import gym_id
    from cdrb_cli.seeding import EVAL_STREAMS

    model = tiny_models[method]
    r = cdrb("eval", model.path, "-n", "3", "--seeds", "1", "--out", tmp_path / "e.h5")
    assert r.returncode == 0, r.stderr
    ev = artifacts.load(tmp_path / "e.h5", "eval")
    cfg, spec = ev.manifest.config, model.manifest.env
    env = gymnasium.make(gym_id(spec.id)).unwrapped
    episodes = env.family.draw_protocol_episodes(spec, 3, 1, EVAL_STREAMS[cfg.stream], cfg.protocol)
    for e, episode in enumerate(episodes):
        obs, info = env.reset(options={"episode": episode})
        np.testing.assert_allclose(obs, ev.arrays["episodes/start"][e], atol=1e-6)  # stored as float32
        controller = CONTROLLERS.get(cfg.controller.name).build(spec, env.sim, cfg.controller,
                                                                model.manifest.config.stride)  # fmt: skip
        controller.reset(ev.arrays["plans"][e].astype(np.float64))
        success = False
        for t in range(spec.episode_limit + cfg.extra_steps):
            action = controller.act(obs, t)
            if controller.finished:
                break
            obs, _, terminated, _, info = env.step(action)
            success |= terminated
        assert success == bool(ev.arrays["episodes/success"][e])
        final = env.family.distance(spec, obs, info["goal"])
        assert final == pytest.approx(float(ev.arrays["episodes/final_distance"][e]), abs=1e-6)
    env.close()


def test_arguments_seeds_episodes_and_actions_are_checked():
    """The env's protocol is the family's protocol spec (success radius, episode limit as `cdrb eval --protocol`
    has them); an unknown protocol or stream, a seed outside 32 bits (gymnasium would fold it onto another seed's
    episode), an episode in a wall or of another kind, a wrong action and states of the wrong size are one-line
    BadInputs, never the simulator's assertion or a silent draw."""
    from cdrb_cli.envs.family import Episode
    from cdrb_cli.envs.registry import family_of, make_spec
    from cdrb_cli.errors import BadInput
    from cdrb_cli.gym import CdrbEnv

    base = make_spec("maze-tight")
    official = family_of(base).protocol_spec(base, "official-code")
    assert official.episode_limit != base.episode_limit  # the protocol changes what the env must follow
    env = CdrbEnv("maze-tight", protocol="official-code")
    assert env.unwrapped.cdrb_spec.episode_limit == official.episode_limit
    assert env.cdrb_spec.success_radius == official.success_radius
    for kw, needle in [({"protocol": "bogus"}, "not a protocol"), ({"protocol": 5}, "not a protocol"),
                       ({"stream": "bogus"}, "not a stream"), ({"render_mode": "human"}, "draws nothing")]:  # fmt: skip
        with pytest.raises(BadInput, match=needle):
            CdrbEnv("maze-tight", **kw)
    env = CdrbEnv("maze-tight")
    with pytest.raises(BadInput, match="before reset"):
        env.step(np.zeros(2))
    obs, info = env.reset(seed=7)
    again, _ = env.reset(seed=np.int64(7))
    np.testing.assert_array_equal(obs, again)  # a numpy seed is the same seed
    for seed in (2**32, -1, 2**63, 1.5, True, "3"):
        with pytest.raises(BadInput, match="not a seed"):
            env.reset(seed=seed)
    taken, _ = env.reset(options={"episode": info["episode"]})  # an episode drawn for this id is taken
    assert taken.shape == obs.shape
    wall = (0, 0)  # a maze episode names grid cells: the map's corner is wall
    assert base.scene.maze.rows[0][0] == "#"
    free_cell = info["episode"].start
    bad = [(Episode(0, wall, info["episode"].goal), "wall|inside an obstacle"),
           (Episode(0, free_cell, wall), "wall|inside an obstacle"),
           (5, "not an Episode"), (Episode(0, (99, 99), (1, 1)), "not an episode of this")]  # fmt: skip
    for episode, needle in bad:
        with pytest.raises(BadInput, match=needle):
            env.reset(options={"episode": episode})
    with pytest.raises(BadInput, match="not a dict"):
        env.reset(options=[1, 2])
    # without the simulator's assertions (python -O) the episode is still checked, by cdrb's own collision test
    code = (
        "from cdrb_cli.gym import CdrbEnv; from cdrb_cli.envs.family import Episode\n"
        "from cdrb_cli.errors import BadInput\n"
        "env = CdrbEnv('maze-tight'); _, info = env.reset(seed=7)\n"
        "for ep in (Episode(0, (0, 0), info['episode'].goal), Episode(0, info['episode'].start, (0, 0))):\n"
        "    try: env.reset(options={'episode': ep}); print('taken')\n"
        "    except BadInput as e: print(e.line())\n"
    )
    lines = subprocess.run([sys.executable, "-O", "-c", code], capture_output=True, text=True, check=True).stdout
    assert lines.count("inside an obstacle") == 2 and "its start" in lines and "its goal" in lines, lines
    env.reset(seed=1)
    for action in (0.0, np.zeros(3), np.zeros((1, 2)), [np.nan, 0.0], "up", None):
        with pytest.raises(BadInput):
            env.step(action)
    for states in ([[0.0, 0.0]], [[np.nan, 0, 0, 0]], None):
        with pytest.raises(BadInput):
            env.collides(states)
    with pytest.raises(BadInput, match="draws nothing"):
        env.render()
    env.close()
    with pytest.raises(BadInput, match="before reset"):
        env.step(np.zeros(2))
