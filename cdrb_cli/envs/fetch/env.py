"""gymnasium-robotics' Fetch environments with real MuJoCo walls, and cdrb's small episode API over them.

:func:`fetch_class` subclasses the stock env (``MujocoFetchReachEnv``, ``MujocoFetchPushEnv``,
``MujocoFetchPickAndPlaceEnv``) and changes only the model it builds and where it starts:

* the walls are added to the stock model with ``mujoco.MjSpec`` as box geoms that collide with the arm and the
  block (they are physics, not a check after the fact);
* every official wall runs through the stock start pose, so during the stock settling steps the walls do not
  collide and the gripper is then driven to the scene's *home* (the stock start, or above the wall), clear of
  every wall; the home is where every episode starts;
* objects and goals are placed from the family's draw (:mod:`cdrb_cli.envs.fetch.tasks`), around the stock
  sampling centre, never overlapping a wall; an episode drawn from anywhere also drives the gripper to its start
  the same way (walls passable while it moves; the family keeps only starts where the arm then touches none).

Success is measured by cdrb (within ``spec.success_radius`` at any step); episodes never end early.
"""

from __future__ import annotations

import contextlib

import numpy as np

from cdrb_cli.envs.family import Episode
from cdrb_cli.envs.fetch.tasks import FetchScene, draw_task, split_start
from cdrb_cli.envs.pointmaze.env import import_gymnasium_robotics
from cdrb_cli.envs.spec import EnvSpec

_SETTLE_STEPS = 20  # env steps (x 20 substeps) per correction while driving the gripper home during setup


def _stock_class(task: str):
    import_gymnasium_robotics()
    if task == "reach":
        from gymnasium_robotics.envs.fetch.reach import MujocoFetchReachEnv as cls
    elif task == "push":
        from gymnasium_robotics.envs.fetch.push import MujocoFetchPushEnv as cls
    else:
        from gymnasium_robotics.envs.fetch.pick_and_place import MujocoFetchPickAndPlaceEnv as cls
    return cls


class _JointAddresses:
    """gymnasium-robotics' ``mujoco_utils`` for one env, with ``robot_get_obs`` reading the robot joints' qpos and
    qvel addresses once instead of looking each joint up by name at every step (a fifth of a Fetch step's time);
    the same arrays. Everything else is the module's own."""

    def __init__(self, utils):
        self._utils = utils
        self._index: dict = {}

    def __getattr__(self, name):
        return getattr(self._utils, name)

    def robot_get_obs(self, model, data, joint_names):
        if data.qpos is None or not joint_names:
            return self._utils.robot_get_obs(model, data, joint_names)
        key = (id(model), tuple(joint_names))
        if key not in self._index:
            import mujoco

            ids = [mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, n) for n in joint_names if n.startswith("robot")]
            scalar = (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
            ok = all(i >= 0 and model.jnt_type[i] in scalar for i in ids)  # one value per joint: plain gathers
            qpos, qvel = np.array([model.jnt_qposadr[i] for i in ids]), np.array([model.jnt_dofadr[i] for i in ids])
            self._index[key] = (qpos, qvel) if ok else None
        index = self._index[key]
        if index is None:
            return self._utils.robot_get_obs(model, data, joint_names)
        return np.squeeze(data.qpos[index[0]][:, None]), np.squeeze(data.qvel[index[1]][:, None])


def fetch_class(scene: FetchScene):
    """The stock Fetch env class of ``scene.task`` with the scene's walls, home and start/goal draws."""
    import mujoco

    base = _stock_class(scene.task)

    class FetchWithWalls(base):
        cdrb_scene = scene

        def _initialize_simulation(self):
            if not isinstance(self._utils, _JointAddresses):
                self._utils = _JointAddresses(self._utils)
            spec = mujoco.MjSpec.from_file(self.fullpath)
            n_walls = len(scene.walls)
            for i, wall in enumerate(scene.solid):  # the task's walls, then the boxes put down after training
                body = spec.worldbody.add_body(name=f"cdrb_wall{i}", pos=list(wall.center))
                body.add_geom(
                    name=f"cdrb_wall{i}",
                    type=mujoco.mjtGeom.mjGEOM_BOX,
                    size=list(wall.half),
                    rgba=[0.85, 0.45, 0.40, 1.0] if i < n_walls else [0.75, 0.39, 0.10, 1.0],
                )
            self.model = spec.compile()
            self.data = mujoco.MjData(self.model)
            self._model_names = self._utils.MujocoModelNames(self.model)
            self.model.vis.global_.offwidth = self.width
            self.model.vis.global_.offheight = self.height
            geom = mujoco.mjtObj.mjOBJ_GEOM
            self._wall_geoms = [mujoco.mj_name2id(self.model, geom, f"cdrb_wall{i}") for i in range(len(scene.solid))]
            self._env_setup(initial_qpos=self.initial_qpos)
            self.initial_time = self.data.time
            self.initial_qpos = np.copy(self.data.qpos)
            self.initial_qvel = np.copy(self.data.qvel)

        def _env_setup(self, initial_qpos):
            with self._walls_passable():
                super()._env_setup(initial_qpos)  # the stock settling
                self.cdrb_stock_start = self.initial_gripper_xpos.copy()
                self._drive_grip(scene.home)
            self.initial_gripper_xpos = self._utils.get_site_xpos(self.model, self.data, "robot0:grip").copy()

        @contextlib.contextmanager
        def _walls_passable(self):
            walls = self._wall_geoms
            saved = self.model.geom_contype[walls].copy(), self.model.geom_conaffinity[walls].copy()
            self.model.geom_contype[walls] = 0
            self.model.geom_conaffinity[walls] = 0
            try:
                yield
            finally:
                self.model.geom_contype[walls], self.model.geom_conaffinity[walls] = saved
                self._mujoco.mj_forward(self.model, self.data)

        def _drive_grip(self, at) -> None:
            at = np.asarray(at, dtype=np.float64)
            target = at.copy()
            for _ in range(3):  # the weld holds the grip site a little off the mocap: correct for it
                self._utils.set_mocap_pos(self.model, self.data, "robot0:mocap", target)
                for _ in range(_SETTLE_STEPS):
                    self._mujoco.mj_step(self.model, self.data, nstep=self.n_substeps)
                target += at - self._utils.get_site_xpos(self.model, self.data, "robot0:grip")

        def move_grip(self, at) -> None:
            """Drive the grip site to ``at`` (walls passable on the way, as at setup) and let the arm settle there:
            where an episode from anywhere starts. Whether the arm then touches a wall is the caller's to check
            (:meth:`FetchEnv.robot_contacts`)."""
            with self._walls_passable():
                self._drive_grip(at)

        #: draw the block and goal at every reset (the training env's gymnasium resets); FetchEnv turns it off:
        #: it places each episode's own block and goal right after the reset
        cdrb_draws = True

        def _reset_sim(self):
            ok = super()._reset_sim()
            self.cdrb_episode = draw_task(scene, self.np_random) if self.cdrb_draws else None
            if self.cdrb_episode is not None and self.has_object:
                self.place_object(self.cdrb_episode[0])
            return ok

        def _sample_goal(self):
            episode = getattr(self, "cdrb_episode", None)
            if episode is None:
                if not self.cdrb_draws:
                    return np.zeros(3)  # FetchEnv.reset sets the episode's goal next
                episode = draw_task(scene, self.np_random)
            return np.asarray(episode[1], dtype=np.float64).copy()

        def place_object(self, xy, z: float | None = None) -> None:
            qpos = self._utils.get_joint_qpos(self.model, self.data, "object0:joint").copy()
            qpos[:2] = xy
            qpos[2] = self.height_offset if z is None else z
            qpos[3:] = (1.0, 0.0, 0.0, 0.0)
            self._utils.set_joint_qpos(self.model, self.data, "object0:joint", qpos)
            self._utils.set_joint_qvel(self.model, self.data, "object0:joint", np.zeros(6))
            self._mujoco.mj_forward(self.model, self.data)

    FetchWithWalls.__name__ = f"Fetch{scene.task.title().replace('-', '')}WithWalls"
    return FetchWithWalls


class FetchEnv:
    """One Fetch instance: ``reset(episode)`` places the block and the goal of the episode; ``step(action)``."""

    def __init__(self, spec: EnvSpec, render_mode: str | None = None):
        cls = fetch_class(spec.scene)
        kwargs = {"render_mode": render_mode} if render_mode else {}
        self.spec = spec
        self.env = cls(**kwargs)
        self.env.cdrb_draws = False  # reset() places each episode's block and goal itself
        self.goal = np.zeros(3)

    @property
    def home(self) -> np.ndarray:
        """Where the grip site starts every episode (after the setup drove it home)."""
        return np.asarray(self.env.initial_gripper_xpos, dtype=np.float64).copy()

    def reset(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        u = self.env
        u.reset(seed=int(episode.seed))
        block, grip = split_start(self.spec.scene.task, tuple(episode.start))
        if grip is not None:
            u.move_grip(grip)
        if u.has_object:
            u.place_object(np.asarray(block, dtype=np.float64))
        self.goal = np.asarray(episode.goal, dtype=np.float64).copy()
        u.goal = self.goal.copy()
        u._render_callback()
        return self.observe(), self.goal.copy()

    def observe(self) -> np.ndarray:
        return np.array(self.env._get_obs()["observation"], dtype=np.float64)

    def step(self, action) -> np.ndarray:
        obs, *_ = self.env.step(np.clip(np.asarray(action, dtype=np.float32), -1.0, 1.0))
        return np.array(obs["observation"], dtype=np.float64)

    def render(self):
        return self.env.render()

    def robot_contacts(self) -> list[tuple[int, str]]:
        """(index into ``scene.solid``, robot body) of every box the robot penetrates now, over its whole arm (the
        collision test of states models only the gripper)."""
        import mujoco

        u = self.env
        mujoco.mj_forward(u.model, u.data)
        solid = {g: i for i, g in enumerate(u._wall_geoms)}
        out = []
        for c in u.data.contact[: u.data.ncon]:
            for box, other in ((c.geom1, c.geom2), (c.geom2, c.geom1)):
                body = mujoco.mj_id2name(u.model, mujoco.mjtObj.mjOBJ_BODY, int(u.model.geom_bodyid[other]))
                if box in solid and c.dist < 0 and (body or "").startswith("robot0:"):
                    out.append((solid[box], body))
        return sorted(set(out))

    def close(self) -> None:
        self.env.close()


def training_env(spec: EnvSpec, seed: int):
    """The goal-conditioned gymnasium env RL experts train on: the walls, the family's draws, sparse reward, a time
    limit of the spec's episode length."""
    from gymnasium.wrappers import TimeLimit

    env = TimeLimit(fetch_class(spec.scene)(reward_type="sparse"), max_episode_steps=spec.episode_limit)
    env.reset(seed=seed)
    return env
