"""`cdrb eval`: plans executed in the simulator, to an eval artifact."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import (
    DeviceOpt,
    ForceOpt,
    JsonOpt,
    SeedOpt,
    app,
    check_outputs,
    check_video_folder,
    choice,
    file_path,
    gif_count,
    report_gifs,
    trained_model,
)
from cdrb_cli.cli.options import (
    EVAL_MOVED,
    SCENE_FLAGS,
    RunConfigOpt,
    RunSetOpt,
    everyday_flags,
    moved_flags,
    run_settings,
    typed_flag,
)
from cdrb_cli.cli.tuned import read_selection, selection_settings
from cdrb_cli.errors import BadInput

# ------------------------------------------------------------------------------------------------ eval
EpisodesOpt = typer.Option(
    None, "--episodes", "-n", min=1, max=100_000, help="Episodes per evaluation seed (default 100)."
)
SeedsOpt = typer.Option(
    None, "--seeds", help="Evaluation seeds, each drawing its own start/goal pairs (default 0,1,2,3,4)."
)
StreamOpt = typer.Option(
    None,
    "--stream",
    parser=choice(lambda: ["test", "tune"], "stream"),
    metavar="test|tune",
    help="Which start/goal pairs: 'tune' to choose settings on, 'test' (never used for choosing) for reported "
    "tables (default test).",
)
ProtocolOpt = typer.Option(
    None,
    "--protocol",
    metavar="NAME",
    help="The evaluation protocol (default: the environment's; `cdrb envs --json` lists them). 'official-code' "
    "evaluates as the official CDRB code; 'detour' (with --scene) keeps the pairs the new obstacles lengthen; "
    "'anywhere' starts anywhere, with the settings chosen for plans from anywhere (mazes: the best of 16 plans).",
)
ReplanOpt = typer.Option(
    None,
    "--replan",
    metavar="never|every:N|deviation:D",
    help="Planners, closed loop: plan again from the current state every N env steps, or when the state is "
    "farther than D (metres, in the obstacle dimensions) from where the plan has it now (default: never, one "
    "plan per episode as in the paper), with the settings chosen for re-planning. Repairs: --set "
    "replan.repair_k=K.",
)
SceneOpt = typer.Option(
    None,
    *SCENE_FLAGS,
    metavar="FILE",
    help="Evaluate among obstacles the data never saw, the model not retrained: for a maze, a map file (the "
    "training map with walls added); for Fetch, a TOML file of \\[\\[boxes]] (center, half) put down. Plans avoid "
    "them with the settings chosen for new obstacles (`--set avoid=plain`: as the model is).",
)
VideoOpt = typer.Option(None, "--video", help="Write rollout GIFs of the first episodes to this folder.")
EvalOutOpt = typer.Option(Path("eval.h5"), "--out", "-o", help="Eval artifact to write.", parser=file_path)
VideosOpt = typer.Option(
    None, "--videos", min=1, max=100, hidden=True, help="How many rollout GIFs with --video (default 3)."
)
KeepPlansOpt = typer.Option(
    True, "--plans/--no-plans", hidden=True, help="Keep each episode's (first) plan in the eval artifact."
)
ReplanPlotOpt = typer.Option(
    None, "--replan-plot", hidden=True, help="With --replan: the first episode's successive plans (PNG)."
)
AllowPartialOpt = typer.Option(False, "--allow-partial", hidden=True, help="Accept an unfinished model.")


@app.command("eval")
@moved_flags(*EVAL_MOVED)
def eval_cmd(
    model: Path = typer.Argument(..., help="Model artifact from `cdrb train`."),
    episodes: int | None = EpisodesOpt,
    seeds: str | None = SeedsOpt,
    stream: str | None = StreamOpt,
    protocol: str | None = ProtocolOpt,
    replan: str | None = ReplanOpt,
    maze_map: Path | None = SceneOpt,
    sets: list[str] = RunSetOpt,
    config_file: Path | None = RunConfigOpt,
    video: Path | None = VideoOpt,
    device: str = DeviceOpt,
    out: Path = EvalOutOpt,
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
    videos: int | None = VideosOpt,
    keep_plans: bool = KeepPlansOpt,
    replan_plot: Path | None = ReplanPlotOpt,
    allow_partial: bool = AllowPartialOpt,
    moved: dict | None = None,
) -> None:
    """Plan once per episode, execute the plan with a controller in the simulator, write an [bold]eval[/bold]
    artifact.

    Start/goal pairs follow the environment's protocol (for the paper's mazes: centre starts, corner goals, the
    stock reset noise) and are identical across methods for the same seeds. Per episode: success at any step,
    steps, final distance, planned states inside obstacles, executed collisions, path length relative to the
    expert, planning time. Example: [cyan]cdrb eval model.h5 --seeds 0,1,2,3,4 --episodes 100 --video gifs/[/cyan]

    Every other knob is a setting ([cyan]cdrb config eval[/cyan] lists them; [cyan]--set KEY=VALUE[/cyan] or
    [cyan]--config FILE[/cyan]): the controller and its gains ([cyan]controller.*[/cyan]), re-planning and repairs
    ([cyan]replan.*[/cyan]), avoidance ([cyan]avoid.*[/cyan]), the sampler and its steps. Closed loop (planners):
    [cyan]--replan every:20[/cyan] plans again every 20 steps from the current state; [cyan]--replan
    deviation:0.5 --set replan.repair_k=4[/cyan] repairs the plan when the agent is 0.5 m off it. New obstacles,
    no retraining: [cyan]--scene closed.txt --protocol detour[/cyan] evaluates on the pairs the new walls lengthen,
    avoiding them with the settings chosen for new obstacles. Also: [cyan]--videos N[/cyan] (GIFs with --video,
    default 3), [cyan]--no-plans[/cyan] (a smaller file without the plans), [cyan]--replan-plot PNG[/cyan] (one
    closed-loop episode's plans), [cyan]--allow-partial[/cyan] (an unfinished model)."""
    if video is not None:
        from cdrb_cli.envs.render import choose_gl_backend

        choose_gl_backend()  # before MuJoCo is imported
    from cdrb_cli.stages.configure import eval_config, route_buffer_path
    from cdrb_cli.stages.evaluate import eval_artifact, summary_line
    from cdrb_cli.torch_utils import setup_torch

    everyday = dict(episodes=episodes, seeds=seeds, stream=stream, protocol=protocol, replan=replan)
    selection = read_selection(config_file)
    settings = run_settings(None if selection else config_file, sets, everyday_flags(everyday), moved)
    if video is not None:
        check_video_folder(video, out)
    m = trained_model(model, allow_partial)
    if selection is not None:  # the choice of `cdrb select` for this model, under what this command line sets
        settings = selection_settings(selection, config_file, m) + settings
    route_buffer = route_buffer_path(settings)
    read = [model, *(p for p in (config_file, maze_map, route_buffer) if p is not None)]
    check_outputs(force, read, out=out, replan_plot=replan_plot)
    from cdrb_cli.stages.avoid import load_route_buffer
    from cdrb_cli.stages.plan import scene_spec
    from cdrb_cli.stages.plan_warnings import off_scene_warning

    scene = scene_spec(m, maze_map, typed_flag(SCENE_FLAGS))
    config = eval_config(m, settings, seed=seed, scene_file=maze_map, scene=scene)
    if replan_plot is not None and config.replan.mode == "never":
        raise BadInput("--replan-plot draws the plans of a closed-loop episode", hint="add --replan every:N")
    route_art = load_route_buffer(route_buffer)
    if config.avoid.label() != "plain":
        ui.log(f"avoiding obstacles: {config.avoid.label()}")
    started = time.time()
    outputs = dict(keep_plans=keep_plans, video_dir=video, videos=gif_count(video, videos), replan_plot=replan_plot)
    ev = eval_artifact(m, config, out, force=force, device=setup_torch(device), scene=scene, route_buffer=route_art,
                       **outputs)  # fmt: skip
    s = ev.manifest.summary
    if s.masked is not None and s.masked.warning():
        ui.warn(s.masked.warning())
    jumps = ev.arrays.get("episodes/plan_max_jump")  # each episode's largest planned step, every plan it made
    warning = (
        None if jumps is None else off_scene_warning(ev.manifest.env, jumps, m.manifest.config.stride, config.avoid)
    )
    if warning:
        ui.warn(warning)
    ui.log(summary_line(s, config, ev.manifest.env.id))
    if video is not None:
        report_gifs(video, started, out)
    if replan_plot is not None and replan_plot.exists():
        ui.log(f"picture: {replan_plot}")
    ui.emit({"path": str(out), "summary": s.model_dump()} if as_json else out, as_json=as_json)
