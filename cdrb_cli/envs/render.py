"""Pictures of mazes, demonstrations, buffers and plans (matplotlib, headless)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cdrb_cli.envs.maze import MazeGeometry
from cdrb_cli.envs.spec import EnvSpec

GOAL_COLOURS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf"]


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def draw_maze(ax, spec: EnvSpec, show_cells: bool = True) -> None:
    """Walls as grey boxes (their true extent), start cells green, goal cells red, agent-radius outline dashed."""
    from matplotlib.patches import Rectangle

    ob = spec.obstacles
    centers = np.asarray(ob.centers).reshape(-1, 2)
    halves = np.asarray(ob.half_sizes).reshape(-1, 2)
    if show_cells and spec.maze is not None:
        g = MazeGeometry(spec.maze)
        s = g.s
        for cells, colour in ((g.start_cells, "#d8f3dc"), (g.goal_cells, "#ffd6d6")):
            for c in cells:
                x, y = g.cell_to_xy(c)
                ax.add_patch(Rectangle((x - s / 2, y - s / 2), s, s, color=colour, lw=0, zorder=0))
    for c, h in zip(centers, halves):
        ax.add_patch(Rectangle(c - h, 2 * h[0], 2 * h[1], color="#555555", lw=0, zorder=1))
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


def _goal_colour(goal_xy, goals: np.ndarray) -> str:
    i = int(np.argmin(np.linalg.norm(goals - np.asarray(goal_xy)[None], axis=1)))
    return GOAL_COLOURS[i % len(GOAL_COLOURS)]


def plot_demos(demos, path: str | Path, n: int = 60, seed: int = 0) -> Path:
    """A sample of demonstrations over the maze, coloured by goal cell."""
    plt = _plt()
    spec = demos.manifest.env
    g = MazeGeometry(spec.maze)
    goals_xy = g.cell_to_xy(g.goal_cells)
    rng = np.random.default_rng(seed)
    ids = rng.choice(demos.n_episodes, size=min(n, demos.n_episodes), replace=False)
    fig, ax = plt.subplots(figsize=(6, 6))
    draw_maze(ax, spec)
    for e in ids:
        obs, _ = demos.episode(int(e))
        colour = _goal_colour(obs[-1, :2], goals_xy)
        ax.plot(obs[:, 0], obs[:, 1], "-", lw=0.8, alpha=0.7, color=colour, zorder=2)
        ax.plot(obs[0, 0], obs[0, 1], "o", ms=2.5, color=colour, zorder=3)
    s = demos.manifest.summary
    ax.set_title(f"{spec.id}: {len(ids)} of {s.episodes} demos (success {s.success_rate:.1%})", fontsize=10)
    return _save(fig, path)


def plot_buffer(buffer, path: str | Path) -> Path:
    plt = _plt()
    spec = buffer.manifest.env
    low, high = buffer.low, buffer.high
    raw = (buffer.points + 1) / 2 * (high - low) + low
    fig, ax = plt.subplots(figsize=(6, 6))
    draw_maze(ax, spec)
    speed = np.linalg.norm(raw[:, 2:4], axis=1) if raw.shape[1] >= 4 else None
    sc = ax.scatter(raw[:, 0], raw[:, 1], s=4, c=speed, cmap="viridis", zorder=2)
    if speed is not None:
        fig.colorbar(sc, ax=ax, shrink=0.7, label="speed (m/s)")
    ax.set_title(f"{spec.id}: replay buffer, {len(raw)} states", fontsize=10)
    return _save(fig, path)


def plot_plans(
    spec: EnvSpec,
    plans: np.ndarray,
    path: str | Path,
    starts: np.ndarray | None = None,
    goals: np.ndarray | None = None,
    in_wall: np.ndarray | None = None,
    title: str = "",
    iterates: np.ndarray | None = None,
    iterate_steps: Sequence[int] | None = None,
) -> Path:
    """Plans (P, H, D) over the maze; states inside walls marked with red crosses. With ``iterates``
    (P, S, H, D), one panel per kept intermediate iterate shows cold diffusion at work."""
    plt = _plt()
    panels = 1 + (iterates.shape[1] if iterates is not None else 0)
    fig, axes = plt.subplots(1, panels, figsize=(5 * panels, 5), squeeze=False)
    axes = axes[0]

    def draw(ax, trajs, label):
        draw_maze(ax, spec)
        for i, tr in enumerate(trajs):
            colour = GOAL_COLOURS[i % len(GOAL_COLOURS)]
            ax.plot(tr[:, 0], tr[:, 1], "-", lw=0.9, alpha=0.8, color=colour, zorder=2)
            ax.plot(tr[:, 0], tr[:, 1], ".", ms=1.5, alpha=0.6, color=colour, zorder=2)
        if starts is not None:
            ax.plot(starts[:, 0], starts[:, 1], "o", ms=5, mfc="white", mec="black", zorder=4)
        if goals is not None:
            ax.plot(goals[:, 0], goals[:, 1], "*", ms=10, mfc="gold", mec="black", zorder=4)
        ax.set_title(label, fontsize=9)

    if iterates is not None:
        for j in range(iterates.shape[1]):
            step = iterate_steps[j] if iterate_steps is not None else j
            draw(axes[j], iterates[:, j], f"iterate k={step}")
    draw(axes[-1], plans, title or "plans")
    if in_wall is not None and in_wall.any():
        bad = plans[in_wall]
        axes[-1].plot(bad[:, 0], bad[:, 1], "x", color="red", ms=4, mew=1.0, zorder=5)
    return _save(fig, path)


def _save(fig, path: str | Path) -> Path:
    from cdrb_cli.artifacts import atomic_path

    path = Path(path)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".") or "png")
    _plt().close(fig)
    return path


# ------------------------------------------------------------------------------------------------ rollouts
def choose_gl_backend() -> str:
    """Pick MUJOCO_GL before MuJoCo is first imported: the user's choice, else OSMesa when its library is
    installed (software rendering, works headless), else EGL (GPU machines)."""
    import ctypes.util
    import os

    if "MUJOCO_GL" not in os.environ:
        os.environ["MUJOCO_GL"] = "osmesa" if ctypes.util.find_library("OSMesa") else "egl"
        if os.environ["MUJOCO_GL"] == "osmesa":
            os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
    return os.environ["MUJOCO_GL"]


def _mujoco_frames(spec: EnvSpec, states: np.ndarray, goal, every: int, size: int = 360) -> list[np.ndarray]:
    """Top-down MuJoCo frames of the ball following ``states`` (raises when no GL context can be made)."""
    import mujoco

    from cdrb_cli.envs.pointmaze import PointMaze

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
    try:
        for s in states[::every]:
            env.set_state(s)
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera=cam)
            frames.append(renderer.render().copy())
    finally:
        renderer.close()
        env.close()
    return frames


def _matplotlib_frames(spec: EnvSpec, plan, states, goal, every: int) -> list[np.ndarray]:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4, 4), dpi=80)
    draw_maze(ax, spec)
    ax.plot(plan[:, 0], plan[:, 1], "-", color="#1f77b4", lw=1.2, alpha=0.8, label="plan")
    ax.plot(goal[0], goal[1], "*", ms=12, mfc="gold", mec="black")
    (trail,) = ax.plot([], [], "-", color="#d62728", lw=1.2, label="executed")
    (ball,) = ax.plot([], [], "o", ms=6, color="#d62728")
    ax.legend(loc="upper center", fontsize=7, ncol=2, frameon=False)
    fig.tight_layout()
    frames = []
    for t in range(0, len(states), every):
        trail.set_data(states[: t + 1, 0], states[: t + 1, 1])
        ball.set_data([states[t, 0]], [states[t, 1]])
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    return frames


def rollout_gifs(spec: EnvSpec, episodes, folder, label: str = "", every: int = 4) -> list[Path]:
    """One GIF per executed episode ``(plan, states, goal, success)``: MuJoCo frames where offscreen rendering
    works, otherwise (with a message saying why) matplotlib frames of the plan and the executed path."""
    from PIL import Image

    from cdrb_cli import ui
    from cdrb_cli.artifacts import atomic_path

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    use_mujoco = True
    written = []
    for i, (plan, states, goal, ok) in enumerate(episodes):
        frames = None
        if use_mujoco:
            try:
                frames = _mujoco_frames(spec, states, goal, every)
            except Exception as exc:  # no GL context on this machine
                import os

                use_mujoco = False
                ui.warn(
                    f"MuJoCo offscreen rendering is unavailable (MUJOCO_GL={os.environ.get('MUJOCO_GL')}: "
                    f"{type(exc).__name__}); drawing the rollouts with matplotlib instead "
                    "(install libosmesa6, or use a machine with EGL, for MuJoCo frames)"
                )
        if frames is None:
            frames = _matplotlib_frames(spec, plan, states, goal, every)
        path = folder / f"{label or 'rollout'}_{i:02d}_{'success' if ok else 'fail'}.gif"
        images = [Image.fromarray(f) for f in frames]
        with atomic_path(path) as tmp:
            images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=40, loop=0)
        written.append(path)
    return written
