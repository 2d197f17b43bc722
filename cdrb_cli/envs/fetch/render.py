"""Pictures of the Fetch scenes: top (x-y) and side (x-z) views of the table, the walls and the paths of the
gripper and the block; MuJoCo frames where an offscreen GL context can be made."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cdrb_cli.envs.fetch.geometry import TABLE_TOP, TABLE_XY
from cdrb_cli.envs.spec import EnvSpec

WALL = "#c0504d"
TABLE = "#e9e3d5"
#: (horizontal axis, vertical axis) of each view, as state-position indices (x=0, y=1, z=2)
VIEWS = {"top": (0, 1), "side": (0, 2)}
LIMITS = {0: (1.0, 1.6), 1: (0.35, 1.15), 2: (0.38, 1.0)}


def draw_view(ax, spec: EnvSpec, view: str = "top") -> None:
    """The table and the walls in one view (metres)."""
    from matplotlib.patches import Rectangle

    h, v = VIEWS[view]
    (x0, x1), (y0, y1) = TABLE_XY
    if view == "top":
        ax.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, color=TABLE, lw=0, zorder=0))
    else:
        ax.add_patch(Rectangle((x0, LIMITS[2][0]), x1 - x0, TABLE_TOP - LIMITS[2][0], color=TABLE, lw=0, zorder=0))
        ax.axhline(TABLE_TOP, color="#8c7b5a", lw=0.8, zorder=0)
    from cdrb_cli.envs.render import NEW_WALL

    n_walls = len(spec.scene.walls)
    for i, w in enumerate(spec.scene.solid):  # boxes put down after training in the new-wall colour
        lo, hi, colour = w.low, w.high, WALL if i < n_walls else NEW_WALL
        ax.add_patch(Rectangle((lo[h], lo[v]), hi[h] - lo[h], hi[v] - lo[v], color=colour, alpha=0.85, lw=0, zorder=1))
    ax.set_xlim(*LIMITS[h])
    ax.set_ylim(*LIMITS[v])
    ax.set_aspect("equal")
    ax.set_xlabel("xyz"[h] + " (m)", fontsize=8)
    ax.set_ylabel("xyz"[v] + " (m)", fontsize=8)
    ax.tick_params(labelsize=7)


def fit_side(ax, spec: EnvSpec, z: np.ndarray) -> None:
    """Crop a side view to what it shows: from below the table top to 5 cm over the highest drawn point or wall
    (at least 20 cm over the table), instead of the whole reachable height."""
    tops = [float(np.max(z))] if np.size(z) else []
    tops += [w.high[2] for w in spec.scene.solid]
    top = max([TABLE_TOP + 0.2, *(t + 0.05 for t in tops)])
    ax.set_ylim(LIMITS[2][0], min(top, LIMITS[2][1]))


def draw_top(ax, spec: EnvSpec) -> None:
    draw_view(ax, spec, "top")


def _bodies(spec: EnvSpec) -> list[tuple[slice, float, float]]:
    """(state dims, line width, alpha) of each body drawn: the gripper thin, the block (if any) thick."""
    out = [(slice(0, 3), 0.7, 0.55)]
    if spec.scene.task != "reach":
        out.append((slice(3, 6), 1.8, 0.9))
    return out


def _draw_paths(ax, view: str, states: np.ndarray, bodies, colour) -> None:
    """One path (T, D) in ``view``, each body with its own line."""
    h, v = VIEWS[view]
    for dims, lw, alpha in bodies:
        p = states[:, dims]
        ax.plot(p[:, h], p[:, v], "-", lw=lw, alpha=alpha, color=colour, zorder=2)


def plot_demos(demos, path: str | Path, n: int = 40, seed: int = 0) -> Path:
    """Top and side views of a sample of demonstrations: gripper paths thin, block paths thick, coloured by
    the side of the wall the goal is on; starts as circles, goals as stars."""
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.envs.render import COLOURS, plan_legend, pyplot, save_figure, set_title

    plt = pyplot()
    spec = demos.manifest.env
    fam = family_of(spec)
    rng = np.random.default_rng(seed)
    ids = rng.choice(demos.n_episodes, size=min(n, demos.n_episodes), replace=False)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2))
    bodies = _bodies(spec)
    for ax, view in zip(axes, VIEWS):
        draw_view(ax, spec, view)
        h, v = VIEWS[view]
        for e in ids:
            obs, _ = demos.episode(int(e))
            goal = demos.desired_goals[int(demos.episode_start[e])]
            colour = COLOURS[fam.goal_group(spec, goal) % len(COLOURS)]
            _draw_paths(ax, view, obs, bodies, colour)
            p = obs[0, spec.goal_dims]
            ax.plot(p[h], p[v], "o", ms=3, mfc="white", mec=colour, zorder=3)
            ax.plot(goal[h], goal[v], "*", ms=6, mfc="gold", mec="black", mew=0.4, zorder=4)
        set_title(ax, f"{view} view", fontsize=9)
        if view == "side":
            fit_side(
                ax, spec, np.concatenate([demos.episode(int(e))[0][:, [2, 5][: len(bodies)]].ravel() for e in ids])
            )
    s = demos.manifest.summary
    what = "gripper" if spec.scene.task == "reach" else "gripper (thin) and block (thick)"
    fig.suptitle(
        f"{spec.id}: {len(ids)} of {s.episodes} demos, {what}, one colour per goal region; success "
        f"{s.success_rate:.1%}, {s.states_in_walls} states in obstacles",
        fontsize=10,
    )
    plan_legend(fig, in_wall=False, bodies=spec.scene.task != "reach", loc="upper center", ncol=4,
                bbox_to_anchor=(0.5, 0.02))  # fmt: skip
    return save_figure(fig, path)


def plot_plans(spec: EnvSpec, plans, path: str | Path, starts, goals, in_wall, title: str) -> Path:
    """Top and side views of plans (P, H, D): gripper paths thin, block paths thick, one colour per plan; planned
    states in an obstacle as red crosses (at the block when there is one), starts as circles, goals as stars."""
    from cdrb_cli.envs.render import COLOURS, plan_legend, pyplot, save_figure, set_title

    plt = pyplot()
    plans = np.asarray(plans)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5.2))
    bodies = _bodies(spec)
    ends = bodies[-1][0]  # the block's dims when there is one, else the gripper's
    for ax, view in zip(axes, VIEWS):
        draw_view(ax, spec, view)
        h, v = VIEWS[view]
        for i, plan in enumerate(plans):
            _draw_paths(ax, view, plan, bodies, COLOURS[i % len(COLOURS)])
        if in_wall is not None and np.asarray(in_wall).any():
            bad = plans[np.asarray(in_wall)][:, ends]
            ax.plot(bad[:, h], bad[:, v], "x", color="red", ms=4, mew=1.0, zorder=5)
        if starts is not None:
            s = np.asarray(starts)[:, ends]
            ax.plot(s[:, h], s[:, v], "o", ms=5, mfc="white", mec="black", zorder=4)
        if goals is not None:
            g = np.asarray(goals)[:, spec.goal_dims]
            ax.plot(g[:, h], g[:, v], "*", ms=10, mfc="gold", mec="black", zorder=4)
        set_title(ax, f"{view} view", fontsize=9)
        if view == "side":
            fit_side(ax, spec, plans[..., [2, 5][: len(bodies)]])
    fig.suptitle(f"{spec.id}: {title}", fontsize=10)
    changed = bool(spec.scene.extra_boxes)
    plan_legend(
        fig,
        bodies=spec.scene.task != "reach",
        new_walls=changed,
        loc="upper center",
        ncol=6 if changed else 5,
        bbox_to_anchor=(0.5, 0.02),
    )
    return save_figure(fig, path)


def mujoco_frames(
    spec: EnvSpec, states: np.ndarray, goal, every: int, size: int = 480, plan: np.ndarray | None = None
) -> list[np.ndarray]:
    """MuJoCo frames of a Fetch path (raises when no GL context can be made). The arm is driven kinematically
    through the grip positions by the mocap (a picture of the path, not a re-simulation); the block is placed at
    its recorded position. The ``plan``'s goal dims (the block's path; Reach: the gripper's) are drawn as a blue
    line, the executed ones so far as a red one."""
    import mujoco

    from cdrb_cli.envs.fetch.env import FetchEnv
    from cdrb_cli.envs.render import draw_rollout_in_scene

    env = FetchEnv(spec)
    u = env.env
    u.goal = np.asarray(goal, dtype=np.float64)
    u._render_callback()
    renderer = mujoco.Renderer(u.model, size, size)
    cam = mujoco.MjvCamera()
    cam.lookat[:] = [1.3, 0.75, 0.5]
    cam.distance, cam.elevation, cam.azimuth = 1.6, -25.0, 150.0
    frames = []
    states = np.asarray(states)
    dims = spec.goal_dims
    try:
        for i in range(0, len(states), every):
            s = states[i]
            u._utils.set_mocap_pos(u.model, u.data, "robot0:mocap", s[:3])
            if u.has_object:
                u.place_object(s[3:5], z=float(s[5]))
            mujoco.mj_step(u.model, u.data, nstep=u.n_substeps)
            renderer.update_scene(u.data, camera=cam)
            planned = None if plan is None else np.asarray(plan)[:, dims]
            draw_rollout_in_scene(renderer.scene, planned, states[: i + 1, dims], 0.006)
            frames.append(renderer.render().copy())
    finally:
        renderer.close()
        env.close()
    return frames
