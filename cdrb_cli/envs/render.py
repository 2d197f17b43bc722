"""Pictures of demonstrations, buffers, plans and rollouts (matplotlib, headless), for any environment family:
the family draws its scene (:meth:`~cdrb_cli.envs.family.EnvFamily.draw_scene`) and maps states to picture
coordinates (:meth:`~cdrb_cli.envs.family.EnvFamily.xy`); everything else here is generic.

Public helpers for other pictures: :func:`pyplot` (headless matplotlib), :func:`save_figure` (atomic write),
:data:`COLOURS`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cdrb_cli.envs.registry import family_of
from cdrb_cli.envs.spec import EnvSpec

COLOURS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf"]


def pyplot():
    """matplotlib.pyplot on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path) -> Path:
    """Write a figure atomically (format from the suffix, PNG by default) and close it."""
    from cdrb_cli.files import atomic_path

    path = Path(path)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".") or "png", bbox_inches="tight")
    pyplot().close(fig)
    return path


def label(text: str) -> str:
    """Text from a file or a path, safe in a picture: no control characters, no mathtext ($)."""
    from cdrb_cli.ui import plain

    return plain(text).replace("$", r"\$")


def set_title(ax, text: str, fontsize: float = 10) -> None:
    ax.set_title(label(text), fontsize=fontsize)


def draw_scene(ax, spec: EnvSpec) -> None:
    """The environment's scene (its family draws it)."""
    family_of(spec).draw_scene(ax, spec)


def draw_plans(ax, spec: EnvSpec, plans: np.ndarray, in_wall: np.ndarray | None = None, markers: bool = True) -> None:
    """Plans (P, H, D) on the scene, one colour each; states inside obstacles as red crosses."""
    xy = family_of(spec).xy(spec, plans)
    for i, tr in enumerate(xy):
        colour = COLOURS[i % len(COLOURS)]
        ax.plot(tr[:, 0], tr[:, 1], "-", lw=0.9, alpha=0.8, color=colour, zorder=2)
        if markers:
            ax.plot(tr[:, 0], tr[:, 1], ".", ms=1.5, alpha=0.6, color=colour, zorder=2)
    if in_wall is not None and in_wall.any():
        bad = xy[in_wall]
        ax.plot(bad[:, 0], bad[:, 1], "x", color="red", ms=4, mew=1.0, zorder=5)


def draw_ends(ax, spec: EnvSpec, starts: np.ndarray | None, goals: np.ndarray | None) -> None:
    fam = family_of(spec)
    if starts is not None:
        s = fam.xy(spec, starts)
        ax.plot(s[:, 0], s[:, 1], "o", ms=5, mfc="white", mec="black", zorder=4)
    if goals is not None:
        g = fam.xy(spec, goals)
        ax.plot(g[:, 0], g[:, 1], "*", ms=10, mfc="gold", mec="black", zorder=4)


#: the colour of obstacles added after training (`--maze-map` at plan/eval time)
NEW_WALL = "#c0641a"


def plan_legend(target, in_wall: bool = True, bodies: bool = False, new_walls: bool = False, **kwargs) -> None:
    """The key of every plans picture (one colour per plan, start circle, goal star, red cross = planned state in an
    obstacle; ``bodies``: Fetch's thin gripper and thick block paths; ``new_walls``: walls added after training) on
    an axes or a figure."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    handles = [Line2D([], [], color="0.35", lw=1.0, label="a plan (one colour each)")]
    if bodies:
        handles = [
            Line2D([], [], color="0.35", lw=0.8, label="gripper path (thin)"),
            Line2D([], [], color="0.35", lw=2.6, label="block path (thick)"),
        ]
    handles += [
        Line2D([], [], ls="", marker="o", ms=5, mfc="white", mec="black", label="start"),
        Line2D([], [], ls="", marker="*", ms=10, mfc="gold", mec="black", label="goal"),
    ]
    if in_wall:
        handles.append(
            Line2D([], [], ls="", marker="x", ms=5, mew=1.0, color="red", label="planned state in an obstacle")
        )
    if new_walls:
        handles.append(Patch(color=NEW_WALL, label="obstacle added after training"))
    kwargs.setdefault("fontsize", 7)
    kwargs.setdefault("framealpha", 0.85)
    target.legend(handles=handles, **kwargs)


def plot_demos(demos, path: str | Path, n: int = 60, seed: int = 0) -> Path:
    """A sample of demonstrations on the scene, coloured by goal region."""
    spec = demos.manifest.env
    fam = family_of(spec)
    own = fam.plot_demos(demos, Path(path), n, seed)
    if own is not None:
        return own
    plt = pyplot()
    rng = np.random.default_rng(seed)
    ids = rng.choice(demos.n_episodes, size=min(n, demos.n_episodes), replace=False)
    fig, ax = plt.subplots(figsize=(6, 6))
    draw_scene(ax, spec)
    for e in ids:
        obs, _ = demos.episode(int(e))
        colour = COLOURS[fam.goal_group(spec, obs[-1, spec.goal_dims]) % len(COLOURS)]
        xy = fam.xy(spec, obs)
        ax.plot(xy[:, 0], xy[:, 1], "-", lw=0.8, alpha=0.7, color=colour, zorder=2)
        ax.plot(xy[0, 0], xy[0, 1], "o", ms=2.5, color=colour, zorder=3)
    s = demos.manifest.summary
    set_title(ax, f"{spec.id}: {len(ids)} of {s.episodes} demos (success {s.success_rate:.1%})")
    return save_figure(fig, path)


def plot_buffer(buffer, path: str | Path) -> Path:
    """The buffer's states on the scene, coloured by speed where the family gives one, and its transition graph
    (the states consecutive demonstration states join, which geodesic balls measure along) as thin grey lines."""
    plt = pyplot()
    spec = buffer.manifest.env
    low, high = buffer.low, buffer.high
    raw = (buffer.points + 1) / 2 * (high - low) + low
    fig, ax = plt.subplots(figsize=(6, 6))
    draw_scene(ax, spec)
    fam = family_of(spec)
    xy = fam.xy(spec, raw[:, : spec.obs_dim])
    edges = buffer.arrays.get("graph/edges")
    if edges is not None and len(edges):
        from matplotlib.collections import LineCollection

        ax.add_collection(LineCollection(xy[edges], colors="0.55", linewidths=0.4, alpha=0.6, zorder=1))
    speed = fam.speed(spec, raw[:, : spec.obs_dim])
    sc = ax.scatter(xy[:, 0], xy[:, 1], s=4, c=speed, cmap="viridis", zorder=2)
    if speed is not None:
        fig.colorbar(sc, ax=ax, shrink=0.7, label="speed")
    set_title(ax, f"{spec.id}: replay buffer, {len(raw)} states")
    return save_figure(fig, path)


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
    """Plans (P, H, D) on the scene; states inside obstacles marked with red crosses. With ``iterates``
    (P, S, H, D), one panel per kept intermediate iterate shows the denoising at work."""
    if iterates is None:  # a family may draw its plans its own way (Fetch: top and side views)
        own = family_of(spec).plot_plans(spec, plans, Path(path), starts, goals, in_wall, title or "plans")
        if own is not None:
            return own
    plt = pyplot()
    panels = 1 + (iterates.shape[1] if iterates is not None else 0)
    fig, axes = plt.subplots(1, panels, figsize=(5 * panels, 5), squeeze=False)
    axes = axes[0]

    def draw(ax, trajs, title_, wall=None):
        draw_scene(ax, spec)
        draw_plans(ax, spec, trajs, wall)
        draw_ends(ax, spec, starts, goals)
        set_title(ax, title_, fontsize=9)

    if iterates is not None:
        for j in range(iterates.shape[1]):
            step = iterate_steps[j] if iterate_steps is not None else j
            draw(axes[j], iterates[:, j], f"iterate k={step}")
    draw(axes[-1], plans, title or "plans", in_wall)
    changed = family_of(spec).scene_changed(spec)
    plan_legend(fig, loc="upper center", ncol=5 if changed else 4, bbox_to_anchor=(0.5, 0.02), new_walls=changed)
    return save_figure(fig, path)


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


#: MuJoCo rollout frames: the plan in blue, the executed path so far in red
PLAN_RGBA, PATH_RGBA = (0.12, 0.47, 0.71, 0.9), (0.84, 0.15, 0.16, 0.9)


def draw_rollout_in_scene(scene, plan_points: np.ndarray | None, path_points: np.ndarray, width: float) -> None:
    """The plan (when given) and the executed path so far, both (n, 3) points, into a MuJoCo scene."""
    if plan_points is not None:
        draw_path_in_scene(scene, plan_points, PLAN_RGBA, width)
    draw_path_in_scene(scene, path_points, PATH_RGBA, width)


def draw_path_in_scene(scene, points: np.ndarray, rgba, width: float) -> None:
    """Add a polyline through ``points`` (n, 3) to a MuJoCo ``MjvScene`` as capsules (after ``update_scene``, so
    it is drawn in the next render); points that do not fit the scene's geom buffer are left out."""
    import mujoco

    pts = np.asarray(points, dtype=np.float64)
    rgba = np.asarray(rgba, dtype=np.float32)
    for a, b in zip(pts[:-1], pts[1:]):
        if scene.ngeom >= scene.maxgeom or np.allclose(a, b):
            continue
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), np.eye(3).ravel(), rgba)
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, width, a, b)
        scene.ngeom += 1


def _matplotlib_frames(spec: EnvSpec, plan, states, goal, every: int) -> list[np.ndarray]:
    plt = pyplot()
    fam = family_of(spec)
    fig, ax = plt.subplots(figsize=(5, 5), dpi=96)
    draw_scene(ax, spec)
    p, s = fam.xy(spec, plan), fam.xy(spec, states)
    g = fam.xy(spec, fam.goal_state(spec, goal))[0]
    ax.plot(p[:, 0], p[:, 1], "-", color="#1f77b4", lw=1.2, alpha=0.8, label="plan")
    ax.plot(g[0], g[1], "*", ms=12, mfc="gold", mec="black")
    (trail,) = ax.plot([], [], "-", color="#d62728", lw=1.2, label="executed")
    (agent,) = ax.plot([], [], "o", ms=6, color="#d62728")
    ax.legend(loc="upper center", fontsize=7, ncol=2, frameon=False)
    fig.tight_layout()
    frames = []
    for t in range(0, len(states), every):
        trail.set_data(s[: t + 1, 0], s[: t + 1, 1])
        agent.set_data([s[t, 0]], [s[t, 1]])
        fig.canvas.draw()
        frames.append(np.asarray(fig.canvas.buffer_rgba())[..., :3].copy())
    plt.close(fig)
    return frames


#: rollout GIFs: milliseconds per frame (each frame is ``every`` environment steps) and how long the last frame stays
GIF_FRAME_MS, GIF_HOLD_MS = 100, 1500


def _captioned(frame: np.ndarray, text: str):
    """A frame with a caption band under it (what the viewer is looking at: method, episode, step, outcome)."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(frame)
    band = 22
    out = Image.new("RGB", (img.width, img.height + band), "white")
    out.paste(img, (0, 0))
    ImageDraw.Draw(out).text((6, img.height + 5), text, fill=(20, 20, 20))
    return out


def earlier_gifs(folder: Path, name: str) -> list[Path]:
    """The GIFs :func:`rollout_gifs` names ``<name>_<episode>_<outcome>.gif`` already in ``folder``."""
    import re

    pattern = re.compile(re.escape(name) + r"_\d{2,}_(success|fail)\.gif")
    return sorted(p for p in Path(folder).glob("*.gif") if pattern.fullmatch(p.name) and p.is_file())


def rollout_gifs(spec: EnvSpec, episodes, folder, label: str = "", every: int = 4) -> list[Path]:
    """One GIF per executed episode ``(plan, states, goal, success)``: simulator frames where offscreen rendering
    works, otherwise (with a message saying why) matplotlib frames of the plan and the executed path. Each frame
    carries a caption (label, episode, environment step, outcome); frames play at :data:`GIF_FRAME_MS` and the last
    one stays :data:`GIF_HOLD_MS`. A progress bar counts the episodes drawn."""
    from cdrb_cli import ui
    from cdrb_cli.files import atomic_path, new_folder

    fam = family_of(spec)
    folder = Path(folder)
    use_simulator = True
    written = []
    episodes = list(episodes)
    with new_folder(folder), ui.progress() as bar:
        name = label or "rollout"
        earlier = earlier_gifs(folder, name)  # this label's GIFs of an earlier run
        task = bar.add_task("rollout GIFs", total=len(episodes), info="")
        for i, (plan, states, goal, ok) in enumerate(episodes):
            frames = None
            if use_simulator:
                try:
                    frames = fam.render_frames(spec, states, goal, every, plan=plan)
                except Exception as exc:  # no GL context on this machine, or a family without simulator frames
                    import os

                    use_simulator = False
                    gl = os.environ.get("MUJOCO_GL")
                    ui.warn(
                        f"simulator frames are unavailable ({type(exc).__name__}"
                        + (f", MUJOCO_GL={gl}" if gl else "")
                        + "); drawing the rollouts with matplotlib instead "
                        "(MuJoCo renders offscreen with libosmesa6 installed, or on a machine with EGL)"
                    )
            if frames is None:
                frames = _matplotlib_frames(spec, plan, states, goal, every)
            outcome = "success" if ok else "failure"
            total = len(states) - 1
            images = [
                _captioned(
                    f, f"{name}  episode {i}  step {min(j * every, total)}/{total}  {outcome}  (blue plan, red path)"
                )
                for j, f in enumerate(frames)
            ]
            path = folder / f"{name}_{i:02d}_{'success' if ok else 'fail'}.gif"
            durations = [GIF_FRAME_MS] * (len(images) - 1) + [GIF_HOLD_MS]
            with atomic_path(path) as tmp:
                images[0].save(tmp, format="GIF", save_all=True, append_images=images[1:], duration=durations, loop=0)
            written.append(path)
            bar.update(task, advance=1)
        for path in set(earlier) - set(written):  # once this run's are written: none of them left mixed in
            path.unlink(missing_ok=True)
        if earlier:
            ui.log(f"replaced {len(earlier)} {name} GIF(s) of an earlier run in {folder}/")
    if written:
        import os

        how = f"MuJoCo (MUJOCO_GL={os.environ.get('MUJOCO_GL', 'default')})" if use_simulator else "matplotlib"
        ui.log(f"{len(written)} GIF(s) drawn with {how}")
    return written


def plot_replans(spec: EnvSpec, plans, plan_steps, states, goal, path, label: str, replan) -> Path:
    """One closed-loop episode: every plan it made (purple to yellow in the order they were made, each from the state
    it was made at) over the executed path (black), with the goal."""
    plt = pyplot()
    fam = family_of(spec)
    fig, ax = plt.subplots(figsize=(5, 5), dpi=110)
    draw_scene(ax, spec)
    colours = plt.get_cmap("viridis")(np.linspace(0.15, 0.95, len(plans)))
    for i, (plan, step) in enumerate(zip(plans, plan_steps)):
        p = fam.xy(spec, np.asarray(plan)[:, : spec.obs_dim])
        ax.plot(p[:, 0], p[:, 1], "-", color=colours[i], lw=1.0, alpha=0.85, label="first plan" if i == 0 else None)
        ax.plot(p[0, 0], p[0, 1], "o", ms=3, color=colours[i])
        if len(plans) <= 12:  # the env step each plan was made at
            ax.annotate(str(step), p[0], fontsize=6, color=colours[i], xytext=(3, 3), textcoords="offset points")
    s = fam.xy(spec, states)
    ax.plot(s[:, 0], s[:, 1], "-", color="black", lw=1.6, label="executed")
    g = fam.xy(spec, fam.goal_state(spec, goal))[0]
    ax.plot(g[0], g[1], "*", ms=14, mfc="gold", mec="black", label="goal")
    ax.legend(loc="upper center", fontsize=7, ncol=3, frameon=False)
    set_title(ax, f"{label}: {len(plans)} plans ({replan.label()}; purple first, yellow last)", fontsize=9)
    return save_figure(fig, path)


def demo_gifs(demos, folder: Path, count: int) -> None:
    """GIFs of the first ``count`` demonstrations of a demos artifact, in ``folder``."""
    shown = []
    for e in range(min(count, demos.n_episodes)):
        states, _ = demos.episode(e)
        goal = demos.desired_goals[int(demos.episode_start[e])]
        shown.append((states, states, goal, bool(demos.episode_success[e])))
    rollout_gifs(demos.manifest.env, shown, folder, label="demo", every=2)
