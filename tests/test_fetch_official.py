"""The official CDRB Fetch executor (`fetch-official`, the official-code protocol) against its definition: a step
budget per planned state, a 1 cm gate on the tracked point, the end of the episode when the plan runs out."""

from __future__ import annotations

import numpy as np
import pytest

from cdrb_cli.envs.fetch.official import OFFICIAL_STEPS, FetchOfficialController, official_steps
from cdrb_cli.envs.registry import CONTROLLERS, family_of, make_spec


def _drive(ctl, states):
    """Call the controller once per state (as the env loop does); the index it acts on after each call."""
    seen = []
    for t, s in enumerate(states):
        ctl.act(s, t)
        if ctl.finished:
            break
        seen.append(ctl.index)
    return seen


def test_official_budgets_per_task():
    assert {make_spec(i).id: official_steps(make_spec(i)) for i in ("fetch-reach", "fetch-reach-obstacle")} == {
        "fetch-reach": 1,
        "fetch-reach-obstacle": 13,
    }
    assert sorted(set(OFFICIAL_STEPS.values())) == [1, 2, 6, 9, 13]


@pytest.mark.parametrize("budget", [1, 2, 6, 9, 13])
def test_each_planned_state_gets_its_budget_when_never_reached(budget):
    """A tracked point that never comes within 1 cm: every planned state gets exactly ``budget`` steps, in
    order, then the executor is finished (no step after the plan)."""
    H = 7
    plan = np.zeros((H, 10))
    plan[:, :3] = np.linspace([1.0, 0.5, 0.5], [1.3, 0.9, 0.6], H)
    ctl = FetchOfficialController("reach", budget, 0.01)
    ctl.reset(plan)
    far = np.zeros(10)
    far[:3] = (5.0, 5.0, 5.0)
    seen = _drive(ctl, [far] * (H * budget + 5))
    assert seen == [i for i in range(H) for _ in range(budget)]
    assert ctl.finished


def test_a_state_within_the_gate_takes_no_step():
    """The tracked point within 1 cm of a planned state: the executor moves on before acting (just outside: it
    acts on it); the block's position is what is tracked when there is a block."""
    H = 5
    plan = np.zeros((H, 25))
    plan[:, 3:6] = np.linspace([1.2, 0.6, 0.425], [1.4, 0.9, 0.425], H)
    ctl = FetchOfficialController("pick-place", 2, 0.01)
    ctl.reset(plan)
    s = plan[2].copy()
    s[3:6] += (0.0099, 0, 0)  # within 1 cm of state 2: states 0, 1 are not, so each gets its 2 steps first
    s[:3] = s[3:6] + (0.0, 0.0, 0.3)
    away = s.copy()
    away[3:6] = (5.0, 5.0, 5.0)
    assert _drive(ctl, [away] * 4) == [0, 0, 1, 1]
    ctl.act(s, 4)  # at state 2 it is already within the gate: it goes on to state 3 without a step on 2
    assert ctl.index == 3
    ctl.reset(plan)
    s[3:6] = plan[2, 3:6] + (0.0101, 0, 0)
    _drive(ctl, [away] * 4)
    ctl.act(s, 4)
    assert ctl.index == 2


def test_push_reset_steps_do_not_count_and_end_after_fifty():
    """Push: steps spent resetting behind the block do not use a planned state's budget; after more than 50 reset
    steps in a row the executor moves on."""
    H = 3
    plan = np.zeros((H, 25))
    plan[:, 3:6] = np.linspace([1.2, 0.6, 0.425], [1.4, 0.9, 0.425], H)
    ctl = FetchOfficialController("push", 1, 0.01)
    ctl.reset(plan)
    s = np.zeros(25)
    s[3:6] = (1.25, 0.7, 0.425)
    s[:3] = s[3:6] + (0.0, 0.0, 0.3)  # far above the block: resetting (moving up, then over the approach point)
    s[6:9] = s[3:6] - s[:3]
    for t in range(51):
        ctl.act(s + (0.001 * t), t)  # the state moves: never "stuck"
        assert ctl.index == 0 and ctl.spent == 0
    # 51 reset steps in a row: the executor leaves state 0 at the next call, and state 1 gets one (reset) step
    ctl.act(s + 0.052, 51)
    assert ctl.index == 1 and ctl.spent == 0
    ctl.act(s + 0.053, 52)  # before it is left too
    assert ctl.index == 2


@pytest.mark.parametrize("env_id", ["fetch-reach-obstacle", "fetch-push", "fetch-pick-place"])
def test_official_protocol_executes_the_expert_plan_and_ends_with_the_plan(env_id):
    """Under the official-code protocol the executor ends the episode when the plan runs out, and executes the
    expert's own plan (cut to the horizon) to the goal on tasks the official budget covers."""
    from cdrb_cli.data import first_window
    from cdrb_cli.envs.registry import EXPERTS
    from cdrb_cli.seeding import STREAM_TUNE
    from cdrb_cli.stages.evaluate import run_episode

    spec = make_spec(env_id)
    fam = family_of(spec)
    run_spec = fam.protocol_spec(spec, "official-code")
    assert run_spec.episode_limit >= spec.horizon * official_steps(spec)
    if spec.scene.task != "reach":
        assert run_spec.pin_end_dims == [0, 1, 2, 3, 4, 5]  # gripper and block at the goal
    entry = EXPERTS.get(fam.experts[0])
    expert = entry.build(spec, entry.configure(None))
    c = CONTROLLERS.get("fetch-official")
    env = fam.make_env(spec)
    ctl = c.build(run_spec, env, c.config(), spec.plan_stride)
    ok = []
    try:
        for ep in fam.draw_episodes(spec, 4, 0, STREAM_TUNE):
            obs, goal = env.reset(ep)
            expert.reset(obs, goal, np.random.default_rng(ep.seed))
            demo = run_episode(env, spec, ep, lambda o, t: expert.act(o), spec.episode_limit)
            ctl.reset(first_window(demo.states, spec.horizon, spec.plan_stride))
            run = run_episode(env, run_spec, ep, ctl.act, run_spec.episode_limit, lambda: ctl.finished)
            assert run.success or ctl.finished
            assert len(run.states) - 1 <= spec.horizon * official_steps(spec) + 200
            ok.append(run.success)
    finally:
        env.close()
    assert np.mean(ok) >= 0.75
