"""PointMaze pictures: the maze drawn with matplotlib, and top-down MuJoCo frames of the ball."""

from __future__ import annotations

import numpy as np

from cdrb_cli.envs.geometry import box_arrays
from cdrb_cli.envs.pointmaze.maze import MazeGeometry
from cdrb_cli.envs.spec import EnvSpec


def draw_maze(ax, spec: EnvSpec, show_cells: bool = True) -> None:
    """Walls as grey boxes (their true extent), start cells green, goal cells red, agent-radius outline dotted;
    walls the training map did not have in orange."""
    from matplotlib.patches import Rectangle

    ob = spec.obstacles
    centers, halves = box_arrays(ob)
    if show_cells:
        g = MazeGeometry(spec.scene.maze)
        s = g.s
        for cells, colour in ((g.start_cells, "#d8f3dc"), (g.goal_cells, "#ffd6d6")):
            for c in cells:
                x, y = g.cell_to_xy(c)
                ax.add_patch(Rectangle((x - s / 2, y - s / 2), s, s, color=colour, lw=0, zorder=0))
    for c, h in zip(centers, halves):
        ax.add_patch(Rectangle(c - h, 2 * h[0], 2 * h[1], color="#555555", lw=0, zorder=1))
    if spec.scene.trained_maze is not None:  # walls the training data never saw, in their own colour
        from cdrb_cli.envs.render import NEW_WALL

        g, before = MazeGeometry(spec.scene.maze), MazeGeometry(spec.scene.trained_maze)
        for cell in np.argwhere(~g.free & before.free):
            x, y = g.cell_to_xy(cell)
            ax.add_patch(Rectangle((x - g.s / 2, y - g.s / 2), g.s, g.s, color=NEW_WALL, lw=0, zorder=1.5))
        r = ob.inflate
        if r > 0:
            ax.add_patch(
                Rectangle(c - h - r, 2 * (h[0] + r), 2 * (h[1] + r), fill=False, ls=":", lw=0.4, ec="#999999", zorder=1)
            )
    ax.set_xlim(ob.low[0], ob.high[0])
    ax.set_ylim(ob.low[1], ob.high[1])
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def mujoco_frames(
    spec: EnvSpec, states: np.ndarray, goal, every: int, size: int = 480, plan: np.ndarray | None = None
) -> list[np.ndarray]:
    """Top-down MuJoCo frames of the ball following ``states``, the ``plan`` drawn as a blue line on the floor
    and the path so far as a red one (raises when no GL context can be made)."""
    import mujoco

    from cdrb_cli.envs.pointmaze.env import PointMaze
    from cdrb_cli.envs.render import draw_rollout_in_scene

    env = PointMaze(spec)
    env.env.goal = np.asarray(goal, dtype=np.float64)
    env.env.update_target_site_pos()
    model, data = env.env.point_env.model, env.env.point_env.data
    renderer = mujoco.Renderer(model, size, size)
    cam = mujoco.MjvCamera()
    cam.lookat[:] = [0.0, 0.0, 0.0]
    extent = max(np.abs(spec.obstacles.low).max(), np.abs(spec.obstacles.high).max())
    cam.distance, cam.elevation, cam.azimuth = 2.9 * extent, -90.0, 90.0
    frames = []
    lift = lambda xy: np.column_stack([np.asarray(xy)[:, :2], np.full(len(xy), 0.05)])  # noqa: E731
    width = 0.04 * spec.scene.maze.cell_size
    try:
        for i in range(0, len(states), every):
            env.set_state(states[i])
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=cam)
            draw_rollout_in_scene(renderer.scene, None if plan is None else lift(plan), lift(states[: i + 1]), width)
            frames.append(renderer.render().copy())
    finally:
        renderer.close()
        env.close()
    return frames
