"""Commands that make data: collect demonstrations, import and export Minari datasets, train an RL expert,
cluster the replay buffer."""

from __future__ import annotations

from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import (
    ForceOpt,
    JsonOpt,
    SeedOpt,
    app,
    check_import_out,
    check_outputs,
    check_video_folder,
    choice,
    expert_registry,
    file_path,
    gif_count,
    literal_values,
    load_artifact,
    registered,
    share_below_one,
)
from cdrb_cli.cli.options import EnvArg, MapOpt, env_spec


# ------------------------------------------------------------------------------------------------ collect
@app.command()
def collect(
    env: str | None = EnvArg,
    episodes: int = typer.Option(1000, "--episodes", "-n", min=1, max=1_000_000, help="Number of demonstrations."),
    expert: str | None = typer.Option(
        None,
        "--expert",
        parser=registered(expert_registry, "expert"),
        metavar="EXPERT",
        help="The demonstrator (default: the environment's scripted expert; `sac` needs --policy).",
    ),
    policy: Path | None = typer.Option(None, "--policy", help="A policy file for experts that need one (SB3 SAC zip)."),
    valid_fraction: float | None = typer.Option(
        None,
        "--valid-fraction",
        parser=share_below_one,
        metavar="SHARE",
        help="Share of episodes held out for validation, in [0, 1) (default 0.1).",
    ),
    starts: str = typer.Option(
        "protocol",
        "--starts",
        metavar="WHERE",
        help="Where demonstrations start: protocol (the environment's start region) or anywhere (mazes: any free "
        "cell; Fetch: the gripper anywhere in the workspace), so plans can start wherever the robot is; "
        "protocol+anywhere alternates between the two.",
    ),
    maze_map: Path | None = MapOpt,
    out: Path = typer.Option(Path("demos.h5"), "--out", "-o", help="Demos artifact to write.", parser=file_path),
    plot: Path | None = typer.Option(
        None,
        "--plot",
        help="Also draw a sample of demos on the scene to this PNG (Fetch: top and side views).",
        parser=file_path,
    ),
    video: Path | None = typer.Option(None, "--video", help="Write GIFs of the first demos to this folder."),
    videos: int | None = typer.Option(
        None, "--videos", min=1, max=100, help="How many demo GIFs with --video (default 3)."
    ),
    workers: int | None = typer.Option(
        None,
        "--workers",
        min=1,
        max=256,
        help="Processes rolling out episodes (default: one per core, at least 100 episodes each). The demos are the "
        "same array for array whatever the number.",
    ),
    sets: list[str] = typer.Option(
        [],
        "--set",
        metavar="KEY=VALUE",
        help="Set a field of the expert's config, e.g. --set 'expert.routes=[\"over\"]' (repeatable; recorded in "
        "the artifact).",
    ),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Roll out an expert and write a [bold]demos[/bold] artifact (train/valid split, per-episode seeds, success).

    The scripted maze expert takes a random shortest grid route (both gaps next to a goal get used), smooths it
    and comes to rest at the goal; the scripted Fetch experts go over or around the walls, at random where both
    work (`--set 'expert.routes=["over"]'` keeps one kind where it exists; `--set expert.clearance=0.05`,
    `expert.gain`, `expert.reach_tolerance` are the other fields). `summary.routes` counts the routes. Examples:
    [cyan]cdrb collect maze-tight -n 1000 --plot demos.png[/cyan],
    [cyan]cdrb collect fetch-push-obstacle -n 1000 --plot push.png --video gifs/[/cyan] (GIFs are MuJoCo frames
    where an offscreen GL context can be made, matplotlib drawings otherwise; the command says which)."""
    from cdrb_cli.artifacts import produce
    from cdrb_cli.stages.collect import check_workers, collect_config
    from cdrb_cli.stages.collect import collect as run_collect

    gifs = gif_count(video, videos)  # --videos without --video: refused before any work
    if video is not None:
        from cdrb_cli.envs.render import choose_gl_backend

        choose_gl_backend()  # before MuJoCo is imported
        check_video_folder(video, out)
    check_outputs(force, [maze_map, policy], out=out, plot=plot)
    check_workers(workers)
    spec = env_spec(env, maze_map)
    from cdrb_cli.settings import parse_set

    config = collect_config(
        spec,
        episodes,
        seed=seed,
        expert=expert,
        policy=policy,
        valid_fraction=valid_fraction,
        settings=parse_set(sets),
        starts=starts,
    )
    demos = produce(out, "demos", force, config, lambda: run_collect(spec, config, out, workers=workers), env=spec)
    s = demos.manifest.summary
    _log_demos(spec.id, s)
    if plot is not None:
        from cdrb_cli.envs.render import plot_demos

        plot_demos(demos, plot, seed=seed)
        ui.log(f"picture: {plot}")
    if video is not None:
        from cdrb_cli.envs.render import demo_gifs

        demo_gifs(demos, video, gifs)
        ui.log(f"demo GIFs: {video}/")
    ui.emit({"path": str(out), "summary": s.model_dump()} if as_json else out, as_json=as_json)


def _log_demos(env_id: str, s) -> None:
    """What a collection made, for the log: episodes, expert success and lengths, routes; a warning for an expert
    that failed more than 1% of its episodes."""
    from cdrb_cli.stages.collect import route_shares

    ui.log(
        f"{env_id}: {s.episodes} episodes ({s.train_episodes} train / {s.valid_episodes} valid), "
        f"success {s.success_rate:.1%}, mean length {s.mean_length:.0f} steps (max {s.max_length}), "
        f"states inside obstacles: {s.states_in_walls}, {s.wall_time_s:.1f}s"
    )
    if s.routes:
        ui.log(f"routes: {route_shares(s.routes)}")
    if s.success_rate < 0.99:
        ui.warn(f"expert success {s.success_rate:.1%} is below 99%")


# ------------------------------------------------------------------------------------------------ minari
import_app = typer.Typer(help="Bring outside datasets and model folders in as cdrb artifacts.", no_args_is_help=True)
app.add_typer(import_app, name="import")


@import_app.command("minari")
def import_minari(
    dataset: str = typer.Argument(
        ..., help="A Minari dataset id found in MINARI_DATASETS_PATH (default ~/.minari/datasets), or its folder."
    ),
    env: str | None = typer.Option(
        None, "--env", help="The cdrb environment (default: from the dataset's env_spec; `cdrb envs`)."
    ),
    valid_fraction: float = typer.Option(
        0.1,
        "--valid-fraction",
        parser=share_below_one,
        metavar="SHARE",
        help="Share held out for validation, in [0, 1).",
    ),
    out: Path = typer.Option(Path("demos.h5"), "--out", "-o", help="Demos artifact to write.", parser=file_path),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Import a Minari dataset (already on disk: cdrb never downloads) as a [bold]demos[/bold] artifact.

    PointMaze datasets map to the maze family (a stock maze when the walls match, else the dataset's own map),
    Fetch Reach/Push/PickAndPlace to the Fetch tasks. The artifact records the dataset id, the Minari version and
    the sha256 of its files; success is cdrb's own test on the states. Example: [cyan]cdrb import minari
    D4RL/pointmaze/umaze-v2 --out umaze.h5[/cyan], then cluster and train as usual."""
    from cdrb_cli.stages.minari_io import import_minari as run_import

    check_import_out(force, out, Path(dataset) if Path(dataset).exists() else None)
    demos = run_import(dataset, out, env=env, valid_fraction=valid_fraction, seed=seed)
    s = demos.manifest.summary
    ui.log(
        f"{demos.manifest.env.id}: {s.episodes} episodes ({s.train_episodes} train / {s.valid_episodes} valid), "
        f"{s.steps} steps, success {s.success_rate:.1%}, states inside obstacles: {s.states_in_walls}"
    )
    ui.emit({"path": str(out), "summary": s.model_dump()} if as_json else out, as_json=as_json)


@import_app.command("npz")
def import_npz(
    file: Path = typer.Argument(..., help="A dataset file, e.g. OGBench's pointmaze-medium-navigate-v0.npz."),
    env: str | None = typer.Option(None, "--env", help="The cdrb environment (default: from the file's name)."),
    valid_fraction: float = typer.Option(
        0.1, "--valid-fraction", parser=share_below_one, metavar="SHARE", help="Share held out, in [0, 1)."
    ),
    out: Path = typer.Option(Path("demos.h5"), "--out", "-o", help="Demos artifact to write.", parser=file_path),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Import a dataset file (.npz, on disk) as a [bold]demos[/bold] artifact: OGBench's PointMaze files (each
    episode's goal is its last state: the files hold none). Example: [cyan]cdrb import npz
    pointmaze-medium-navigate-v0.npz --out demos.h5[/cyan]"""
    from cdrb_cli.stages.dataset_files import import_file as run_import

    check_import_out(force, out, file)
    s = run_import(file, out, env=env, valid_fraction=valid_fraction, seed=seed).manifest.summary
    ui.log(f"{file.name}: {s.episodes} episodes, {s.steps} steps, states inside obstacles: {s.states_in_walls}")
    ui.emit({"path": str(out), "summary": s.model_dump()} if as_json else out, as_json=as_json)


# ------------------------------------------------------------------------------------------------ expert
expert_app = typer.Typer(
    help="Train stable-baselines3 experts (SAC + HER) for `cdrb collect --expert sac`.", no_args_is_help=True
)
app.add_typer(expert_app, name="expert")


@expert_app.command("train")
def expert_train(
    env: str | None = EnvArg,
    steps: int = typer.Option(
        100_000, "--steps", min=1, help="Environment steps (the paper used 1M: hours on 2 cores)."
    ),
    her: bool = typer.Option(True, "--her/--no-her", help="Hindsight experience replay (future strategy, 4 goals)."),
    maze_map: Path | None = MapOpt,
    out: Path = typer.Option(Path("expert.zip"), "--out", "-o", help="SB3 zip to write.", parser=file_path),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
) -> None:
    """Train a goal-conditioned SAC(+HER) expert. About 11-15 ms per step on 2 CPU cores: 1M steps take 3-4 hours."""
    from cdrb_cli.artifacts import claim_output
    from cdrb_cli.experts.sac import train_sac

    spec = env_spec(env, maze_map)
    with claim_output(out, force):
        train_sac(spec, steps, seed, out, her=her)
    ui.emit(out)


# ------------------------------------------------------------------------------------------------ cluster
@app.command()
def cluster(
    demos: Path = typer.Argument(..., help="Demos artifact from `cdrb collect`."),
    k: int | None = typer.Option(
        None,
        "--k",
        min=0,
        help="k-means clusters (default 1000, or every state where the demos hold fewer); 0 keeps the full buffer.",
    ),
    features: str = typer.Option(
        "state",
        "--features",
        parser=choice(literal_values("ClusterConfig", "features"), "feature space"),
        metavar="state|state-action",
        help="state, or state-action (actions joined to states).",
    ),
    split: str = typer.Option(
        "train",
        "--split",
        parser=choice(literal_values("ClusterConfig", "split"), "split"),
        metavar="train|all",
        help="Episodes whose states form the buffer: train or all.",
    ),
    graph_join: str = typer.Option(
        "features",
        "--graph-join",
        parser=choice(literal_values("ClusterConfig", "graph_join"), "graph join"),
        metavar="features|position",
        help="How demo states join the transition graph geodesic balls measure along: at the nearest buffer state "
        "by every feature, or by position alone.",
    ),
    out: Path = typer.Option(Path("buffer.h5"), "--out", "-o", help="Buffer artifact to write.", parser=file_path),
    plot: Path | None = typer.Option(
        None, "--plot", help="Also draw the buffer states on the scene to this PNG.", parser=file_path
    ),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Build the [bold]replay buffer[/bold] CDRB diffuses through (writes a buffer artifact).

    Features are normalized to [-1, 1] per dimension (min/max over the training demos); k-means (scikit-learn)
    picks K representatives and each centroid is snapped to its nearest real demo state, so every buffer state
    is a known good state. Example: [cyan]cdrb cluster demos.h5 --k 1000 --plot buffer.png[/cyan]"""
    from cdrb_cli.artifacts import produce
    from cdrb_cli.configs import ClusterConfig
    from cdrb_cli.stages.cluster import cluster as run_cluster
    from cdrb_cli.stages.cluster import fit_default_k

    check_outputs(force, [demos], out=out, plot=plot)
    d = load_artifact(demos, "demos")
    config = ClusterConfig(
        features=features, split=split, graph_join=graph_join, seed=seed, **({"k": k} if k is not None else {})
    )
    config = fit_default_k(d, config)
    buf = produce(out, "buffer", force, config, lambda: run_cluster(d, config, out), parents=[d])
    sm = buf.manifest.summary
    ui.log(
        f"buffer: {sm.points} states from {sm.source_states} ({features}), diameter {sm.diameter:.3f}, "
        f"{sm.wall_time_s:.1f}s"
    )
    if plot is not None:
        from cdrb_cli.envs.render import plot_buffer

        plot_buffer(buf, plot)
        ui.log(f"picture: {plot}")
    ui.emit({"path": str(out), "summary": sm.model_dump()} if as_json else out, as_json=as_json)
