"""The test of the redesign: a new environment family and new methods, declared in this file alone (nothing else
in the project edited), run through the real CLI: collect -> cluster -> train -> plan -> eval -> report. And a
method with two networks and two different optimizers trains, checkpoints and resumes bit for bit through the
generic training loop."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
import tomllib
from pydantic import Field

from cdrb_cli import artifacts
from cdrb_cli.cli import main
from cdrb_cli.envs.family import (
    Controller,
    ControllerConfig,
    ControllerEntry,
    EnvFamily,
    Episode,
    ExpertConfig,
    ExpertEntry,
    Scene,
)
from cdrb_cli.envs.registry import CONTROLLERS, EXPERTS, FAMILIES
from cdrb_cli.envs.spec import BoxObstacles, EnvSpec
from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import Planner, SampleResult
from cdrb_cli.methods.registry import METHODS, MethodEntry, MethodParams
from cdrb_cli.seeding import episode_seeds


# ------------------------------------------------------------------------------------------------ a toy family
class WallScene(Scene):
    """A point in a square with one wall in the middle."""

    family: Literal["toy-wall"] = "toy-wall"
    wall_half_height: float = 1.0


class PointEnv:
    """x' = x + 0.1 a, no simulator."""

    def __init__(self, spec: EnvSpec):
        self.spec = spec
        self.state = np.zeros(2)

    def reset(self, episode: Episode):
        self.state = np.array(episode.start, dtype=np.float64)
        return self.state.copy(), np.array(episode.goal, dtype=np.float64)

    def step(self, action):
        self.state = np.clip(self.state + 0.1 * np.clip(action, -1, 1), -3, 3)
        return self.state.copy()

    def close(self):
        pass


class DetourConfig(ExpertConfig):
    kind: Literal["toy-detour"] = "toy-detour"
    clearance: float = Field(0.4, description="how far above/below the wall the detour passes")


class DetourExpert:
    """Goes around the wall, above or below at random (so the data is multimodal), then to the goal."""

    def __init__(self, spec: EnvSpec, config: DetourConfig):
        self.h = spec.scene.wall_half_height + config.clearance
        self.waypoints: list[np.ndarray] = []

    def reset(self, state, goal, rng):
        side = self.h * (1 if rng.random() < 0.5 else -1)
        self.waypoints = [np.array([-0.4, side]), np.array([0.4, side]), np.asarray(goal, dtype=np.float64)]

    def act(self, state):
        while len(self.waypoints) > 1 and np.linalg.norm(self.waypoints[0] - state) < 0.05:
            self.waypoints.pop(0)
        return np.clip((self.waypoints[0] - state) / 0.1, -1, 1)

    def settled(self, state, goal):
        return bool(np.linalg.norm(state - goal) < 0.01)


class FollowConfig(ControllerConfig):
    name: Literal["toy-follow"] = "toy-follow"
    gain: float = Field(1.0, gt=0, le=10, description="how hard it steps toward the planned state (a plugin's knob)")


class Follow(Controller):
    """Steps toward the planned state of the current time."""

    def __init__(self, stride: int, gain: float = 1.0):
        self.stride, self.gain, self.plan = stride, gain, np.zeros((1, 2))

    def reset(self, plan):
        self.plan = np.asarray(plan)

    def act(self, state, t):
        target = self.plan[min(t // self.stride + 1, len(self.plan) - 1), :2]
        return np.clip(self.gain * (target - state) / 0.1, -1, 1)


class WallFamily(EnvFamily):
    name = "toy-wall"
    scene_type = WallScene
    experts = ("toy-detour",)
    controllers = ("toy-follow",)
    protocol = "left-start/right-goal"
    point_format = "x,y"

    def env_ids(self):
        return {"toy-wall": "a point, a wall, start on the left, goal on the right"}

    def make_spec(self, env_id):
        return EnvSpec(
            id=env_id,
            scene=WallScene(),
            obs_dim=2,
            action_dim=2,
            goal_dim=2,
            state_labels=["x", "y"],
            goal_dims=[0, 1],
            horizon=16,
            plan_stride=5,
            episode_limit=80,
            success_radius=0.1,
            dt=0.1,
            obstacles=BoxObstacles(
                dims=[0, 1], centers=[[0, 0]], half_sizes=[[0.2, 1.0]], inflate=0.05, low=[-3, -3], high=[3, 3]
            ),
        )

    def make_env(self, spec):
        return PointEnv(spec)

    def draw_episodes(self, spec, n, seed, stream):
        out = []
        for s in episode_seeds(seed, n, stream):
            rng = np.random.default_rng(int(s))
            out.append(Episode(int(s), (-2.0, float(rng.uniform(-1, 1))), (2.0, float(rng.uniform(-1, 1)))))
        return out


@pytest.fixture
def toy_family():
    with (
        FAMILIES.added(WallFamily()),
        EXPERTS.added(ExpertEntry(DetourConfig, DetourExpert, lambda policy: DetourConfig())),
        CONTROLLERS.added(ControllerEntry(FollowConfig, lambda spec, env, cfg, stride: Follow(stride, cfg.gain))),
    ):
        yield


# ------------------------------------------------------------------------------------------------ a toy method
class StraightParams(MethodParams):
    name: Literal["toy-straight"] = "toy-straight"
    sampler: Literal["straight"] = "straight"
    bend: float = Field(1.0, description="scale of the learned correction to the straight line")


class Straight(Planner):
    """The straight line from start to goal plus a learned correction (an MLP of the start and goal)."""

    def _line(self, start, goal):
        w = torch.linspace(0, 1, self.horizon, device=start.device)[None, :, None]
        return start[:, None] * (1 - w) + goal[:, None] * w

    def _plan(self, start, goal):
        return self.pin(self._line(start, goal) + self.config.method.bend * self.net(start, goal), start, goal)

    def loss(self, batch, rng):
        start, goal = self.ends(batch, self.obs_dim)
        return torch.mean((self._plan(start, goal) - batch) ** 2)

    def _sample(self, start, goal, rng, sampler, steps, keep_iterates):
        return SampleResult(plans=self._plan(start, goal))


STRAIGHT = MethodEntry(StraightParams, Straight, nets=("mlp",), presets={"quick": {"bend": 1.0}}, description="a test")


@pytest.fixture
def toy_method():
    with METHODS.added(STRAIGHT):
        yield


@pytest.fixture
def cdrb_in_process(capsys):
    """Run the CLI in this process (where the toys are registered): returns (exit code, stdout)."""

    def run(*args) -> tuple[int, str]:
        capsys.readouterr()
        code = main([str(a) for a in args])
        return code, capsys.readouterr().out

    return run


def test_a_new_family_and_method_run_through_the_cli(toy_family, toy_method, tmp_path, cdrb_in_process):
    _cdrb = cdrb_in_process
    demos, buffer, model = tmp_path / "demos.h5", tmp_path / "buffer.h5", tmp_path / "model.h5"
    code, out = _cdrb("envs", "--json")
    assert code == 0 and "toy-wall" in [row["id"] for row in json.loads(out)]
    code, out = _cdrb("methods", "--json")
    assert {"name": "toy-straight", "samplers": "straight"}.items() <= next(
        r for r in json.loads(out) if r["name"] == "toy-straight"
    ).items()

    assert _cdrb("collect", "toy-wall", "-n", "40", "--out", demos, "--plot", tmp_path / "d.png")[0] == 0
    d = artifacts.load(demos, "demos")
    assert d.manifest.env.family == "toy-wall" and d.manifest.config.expert.kind == "toy-detour"
    assert d.manifest.summary.success_rate == 1.0 and d.manifest.summary.states_in_walls == 0
    ys = [d.episode(e)[0][:, 1].max() for e in range(d.n_episodes)]
    assert min(ys) < 1.0 < max(ys)  # both detours (below and above the wall) are in the data

    # CDRB itself on the new family: the generic buffer and method code need nothing family-specific
    assert _cdrb("cluster", demos, "--k", "50", "--out", buffer)[0] == 0
    cdrb_model = tmp_path / "cdrb.h5"
    tiny = ["--set", "net.dim=8", "--set", "net.dim_mults=1,2", "--set", "method.diffusion_steps=4"]
    assert _cdrb("train", demos, "--buffer", buffer, "--steps", "20", *tiny, "--out", cdrb_model)[0] == 0

    # the new method, chosen by its registered name; the CLI's choices come from the registry
    code = _cdrb(
        "train", demos, "--method", "toy-straight", "--steps", "300", "--set", "net.hidden=32,32", "--out", model
    )[0]
    assert code == 0
    m = artifacts.load(model, "model")
    assert m.manifest.config.method == StraightParams(bend=1.0) and m.manifest.config.net.hidden == [32, 32]

    plans = tmp_path / "plans.h5"
    code = _cdrb(
        "plan",
        model,
        "--start",
        "-2,0.5",
        "--goal",
        "2,-0.5",
        "--num-plans",
        "2",
        "--out",
        plans,
        "--plot",
        tmp_path / "p.png",
    )[0]
    assert code == 0
    p = artifacts.load(plans, "plans")
    np.testing.assert_array_equal(p.plans[:, 0], [[-2, 0.5]] * 2)
    np.testing.assert_array_equal(p.plans[:, -1], [[2, -0.5]] * 2)
    loss = m.arrays["curve/loss"]
    assert loss[-1] < 0.5 * loss[0]  # it learned something (an average of the two detours: the MLP's weakness)
    assert _cdrb("plan", model, "--start", "0,0", "--goal", "2,0", "--out", tmp_path / "bad.h5")[0] == 2  # in the wall

    evals = []
    for name, path in (("straight", model), ("cdrb", cdrb_model)):
        ev = tmp_path / f"eval-{name}.h5"
        assert _cdrb("eval", path, "--seeds", "0,1", "--episodes", "5", "--out", ev)[0] == 0
        evals.append(ev)
    e = artifacts.load(evals[0], "eval")
    assert e.manifest.config.controller == FollowConfig() and e.manifest.config.protocol == "left-start/right-goal"
    assert e.manifest.summary.success_mean > 0.5
    code, out = _cdrb("report", *evals, "--format", "json")
    assert code == 0 and {r["method"] for r in json.loads(out)} == {"toy-straight", "cdrb"}


class InProcess:
    """A grid backend that runs each task's command in this process, where the toys are registered."""

    name = "in-process"

    def submit(self, payload):
        from concurrent.futures import Future

        for out in payload["outputs"]:
            Path(out).parent.mkdir(parents=True, exist_ok=True)
        fut = Future()
        fut.set_result({"rc": main(list(payload["argv"])), "seconds": 0.0, "stderr": []})
        return fut


def test_a_new_family_and_method_go_through_tune_select_test_and_report(toy_family, toy_method, tmp_path):
    """A study of the new family and method is data only: a tuning grid, `cdrb select`, a test grid that includes
    the selection, and `cdrb report`; no experiment code names either."""
    from cdrb_cli.orchestration.grid import load_grid, run_grid
    from cdrb_cli.orchestration.select import select

    common = (
        'envs = ["toy-wall"]\nmethods = ["toy-straight", "cdrb"]\ndemos = 40\nk = 30\neval_episodes = 3\n'
        '[[settings]]\nmethod = "cdrb"\n'
        'train = ["--set", "net.dim=8", "--set", "net.dim_mults=1,2", "--set", "method.diffusion_steps=4"]\n'
        '[[settings]]\nmethod = "toy-straight"\ntrain = ["--set", "net.hidden=32,32"]\n'
    )
    tune = tmp_path / "tune.toml"
    tune.write_text(
        'out = "tune"\nseeds = [0]\nsteps = 100\nsnapshot_at = [50]\neval_stream = "tune"\neval_seeds = [0, 1]\n'
        "report = false\n" + common + '[[variants]]\nname = "bent"\n'
        '[[variants]]\nname = "straighter"\nmethods = ["toy-straight"]\ntrain = ["--set", "method.bend=0.0"]\n'
    )
    run = run_grid(load_grid(tune), InProcess())
    assert {r.status for r in run.results} == {"done"}
    tuned = select(tune, tmp_path / "tuned.toml")
    text = tuned.read_text()
    assert 'method = "toy-straight"' in text and 'method = "cdrb"' in text
    assert all("steps" in s["train"] for s in tomllib.loads(text)["settings"])  # each at its chosen length

    test = tmp_path / "test.toml"
    test.write_text('include = ["tuned.toml"]\nout = "test"\nseeds = [0, 1]\n' + common)
    spec = load_grid(test)
    run = run_grid(spec, InProcess())
    assert {r.status for r in run.results} == {"done"}
    for r in run.results:
        if r.kind == "eval":
            assert artifacts.load(Path(r.outputs[0]), "eval").manifest.config.stream == "test"
    report = (spec.out / "report.md").read_text()
    assert "toy-straight" in report and "cdrb" in report


def test_after_the_fixtures_the_registries_are_as_shipped():
    assert "toy-wall" not in FAMILIES and "toy-straight" not in METHODS and "toy-detour" not in EXPERTS
    assert METHODS.names() == list(METHODS.builtins)


# ------------------------------------------------------------------------------------------------ two networks
class TwinParams(MethodParams):
    name: Literal["toy-twin"] = "toy-twin"
    sampler: Literal["actor"] = "actor"


class Twin(Planner):
    """An actor (the planner) and a critic that scores plans, with their own optimizers (Adam and SGD with
    momentum), the critic without an EMA: the shape of Diffusion-QL's checkpoint."""

    def build(self, buffer_points):
        super().build(buffer_points)
        d = self.feature_dim * self.horizon
        self.critic = torch.nn.Sequential(torch.nn.Linear(d, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1))

    def modules(self):
        return {"actor": self.net, "critic": self.critic}

    def ema_modules(self):
        return ("actor",)

    def make_optimizers(self):
        return {
            "actor": torch.optim.Adam(self.net.parameters(), lr=self.config.lr),
            "critic": torch.optim.SGD(self.critic.parameters(), lr=0.01, momentum=0.9),
        }

    def _plan(self, start, goal):
        return self.pin(self.net(start, goal), start, goal)

    def loss(self, batch, rng):
        start, goal = self.ends(batch, self.obs_dim)
        return torch.mean((self._plan(start, goal) - batch) ** 2)

    def update(self, batch, rng, optimizers):
        start, goal = self.ends(batch, self.obs_dim)
        target = -torch.mean((batch - batch.mean(0)) ** 2, dim=(1, 2))[:, None]
        critic_loss = torch.mean((self.critic(batch.flatten(1)) - target) ** 2)
        optimizers["critic"].zero_grad()
        critic_loss.backward()
        optimizers["critic"].step()
        plan = self._plan(start, goal)
        actor_loss = torch.mean((plan - batch) ** 2) - 0.01 * self.critic(plan.flatten(1)).mean()
        optimizers["actor"].zero_grad()
        actor_loss.backward()
        optimizers["actor"].step()
        return float(actor_loss.detach())

    def _sample(self, start, goal, rng, sampler, steps, keep_iterates):
        return SampleResult(plans=self._plan(start, goal))


@pytest.fixture
def twin():
    with METHODS.added(MethodEntry(TwinParams, Twin, nets=("mlp",))):
        yield


def test_two_networks_two_optimizers_resume_bit_for_bit(twin, small_data, tmp_path):
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train

    demos, _ = small_data
    settings = {"horizon": 16, "batch_size": 8, "net.hidden": [32], "checkpoint_every": 5}
    full = train(demos, None, train_config(demos, None, "toy-twin", {**settings, "steps": 20}), tmp_path / "a.h5")
    train(demos, None, train_config(demos, None, "toy-twin", {**settings, "steps": 10}), tmp_path / "b.h5")
    resumed = train(
        demos, None, train_config(demos, None, "toy-twin", {**settings, "steps": 20}), tmp_path / "b.h5", resume=True
    )
    keys = set(full.arrays)
    assert any(k.startswith("weights/critic/") for k in keys) and any(k.startswith("optim/critic/") for k in keys)
    assert any(k.endswith("/momentum_buffer") for k in keys) and not any(k.startswith("ema/critic/") for k in keys)
    assert keys == set(resumed.arrays)
    for k in keys:
        np.testing.assert_array_equal(full.arrays[k], resumed.arrays[k], err_msg=k)
    # the inference loader restores both: the actor from its EMA, the critic from its weights
    from cdrb_cli.methods.checkpoint import load_method

    method = load_method(full)
    w = full.tensors("weights/critic")
    np.testing.assert_array_equal(method.critic[0].weight.detach().numpy(), w["0.weight"])
    np.testing.assert_array_equal(method.net.net[0].weight.detach().numpy(), full.tensors("ema/actor")["net.0.weight"])


def test_a_plugins_eval_knob_is_one_config_field(toy_family, toy_method, tmp_path, cdrb_in_process):
    """The toy controller's ``gain`` is declared once, as a field of its config: --set, a grid variant's table,
    `cdrb select`'s output and the Python API reach it, with no CLI or grid code naming it."""
    from cdrb_cli import api
    from cdrb_cli.orchestration.grid import load_grid, run_grid
    from cdrb_cli.orchestration.select import select

    tune = tmp_path / "tune.toml"
    tune.write_text(
        'out = "tune"\nenvs = ["toy-wall"]\nmethods = ["toy-straight"]\nseeds = [0]\ndemos = 40\nsteps = 100\n'
        'eval_episodes = 3\neval_stream = "tune"\nreport = false\n'
        '[[settings]]\ntrain = ["--set", "net.hidden=32,32"]\n'
        '[[variants]]\nname = "soft"\neval = { controller = { gain = 0.05 } }\n'
        '[[variants]]\nname = "firm"\neval = { controller = { gain = 2.0 } }\n'
    )
    run = run_grid(load_grid(tune), InProcess())
    assert {r.status for r in run.results} == {"done"}
    evals = {r.id: Path(r.outputs[0]) for r in run.results if r.kind == "eval"}
    gains = {i: artifacts.load(p, "eval").manifest.config.controller.gain for i, p in evals.items()}
    assert sorted(gains.values()) == [0.05, 2.0]
    text = select(tune, tmp_path / "tuned.toml").read_text()
    (chosen,) = tomllib.loads(text)["settings"]
    assert chosen["eval"]["controller"]["gain"] in (0.05, 2.0)  # the chosen variant's knob, a table of settings

    model = next(Path(r.outputs[0]) for r in run.results if r.kind == "train")
    code, _ = cdrb_in_process(
        "eval", model, "--seeds", "0", "--episodes", "2", "--set", "controller.gain=0.5", "--out", tmp_path / "e.h5"
    )
    assert code == 0 and artifacts.load(tmp_path / "e.h5", "eval").manifest.config.controller.gain == 0.5
    summary = api.evaluate(model, tmp_path / "a.h5", episodes=2, seeds=[0], settings={"controller.gain": 0.25})
    assert artifacts.load(tmp_path / "a.h5", "eval").manifest.config.controller.gain == 0.25
    assert summary.per_seed[0].episodes == 2
    code, _ = cdrb_in_process("eval", model, "--set", "controller.gain=99", "--out", tmp_path / "bad.h5")
    assert code == 2 and not (tmp_path / "bad.h5").exists()
