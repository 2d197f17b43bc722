"""The stock environments as gymnasium envs (`import cdrb_cli.gym`): every id `cdrb envs` lists can be made, reset
and stepped, and a cdrb plan executed in the gymnasium env does what `cdrb eval` measured on the same pair."""

from __future__ import annotations

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
