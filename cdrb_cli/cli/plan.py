"""`cdrb plan`: plans from start to goal, to a plans artifact."""

from __future__ import annotations

from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import (
    DeviceOpt,
    ForceOpt,
    JsonOpt,
    PartialOpt,
    SeedOpt,
    app,
    check_outputs,
    file_path,
    trained_model,
)
from cdrb_cli.cli.options import (
    PLAN_MOVED,
    SCENE_FLAGS,
    RunConfigOpt,
    RunSetOpt,
    SceneMapOpt,
    moved_flags,
    run_settings,
    typed_flag,
)
from cdrb_cli.cli.tuned import plan_part, read_selection, selection_settings


@app.command()
@moved_flags(*PLAN_MOVED)
def plan(
    model: Path = typer.Argument(..., help="Model artifact from `cdrb train`."),
    start: list[str] = typer.Option(
        [], "--start", help="A start state (mazes: x,y at rest, or x,y,vx,vy); repeatable."
    ),
    goal: list[str] = typer.Option([], "--goal", help="A goal (mazes: x,y); one per --start, or one for all."),
    pairs: int = typer.Option(
        0, "--pairs", min=0, max=100_000, help="Instead: N start/goal pairs drawn by the eval protocol."
    ),
    n: int | None = typer.Option(None, "--num-plans", "-n", min=1, max=10_000, help="Plans per start/goal pair."),
    maze_map: Path | None = SceneMapOpt,
    plot: Path | None = typer.Option(
        None, "--plot", help="Draw the scene and the plans to this PNG.", parser=file_path
    ),
    sets: list[str] = RunSetOpt,
    config_file: Path | None = RunConfigOpt,
    allow_partial: bool = PartialOpt,
    device: str = DeviceOpt,
    out: Path = typer.Option(Path("plans.h5"), "--out", "-o", help="Plans artifact to write.", parser=file_path),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
    batch_size: int | None = typer.Option(
        None, "--batch-size", min=1, max=100_000, hidden=True, help="Plans sampled together (setting `batch`)."
    ),
    moved: dict | None = None,
) -> None:
    """Plan from start to goal and write a [bold]plans[/bold] artifact (start and goal held exactly).

    CDRB (the paper's sampling algorithm): start from random buffer states, then repeatedly restore and
    re-degrade with shrinking balls.
    Example: [cyan]cdrb plan model.h5 --start 0,0 --goal 6,6 -n 8 --plot plans.png --set keep_iterates=4[/cyan]

    Every other knob is a setting ([cyan]cdrb config plan[/cyan] lists them): the sampler and its steps, the raw
    weights, kept iterates, and how plans keep out of obstacles ([cyan]avoid.*[/cyan]). New obstacles, no
    retraining: [cyan]--scene closed.txt[/cyan] plans in the training map with walls added, avoiding them with
    the settings chosen for new obstacles (CDRB: masked buffer, a buffer route repaired from k = 8, best of 4);
    a start away from the demonstrations' starts keeps the best of several plans by the collision test (the
    setting chosen for plans from anywhere; mazes: 16; CDRB tries a pair whose every plan crosses a wall again
    from a buffer route); [cyan]--set avoid=plain[/cyan] plans as the model is.
    Also: [cyan]--batch-size N[/cyan], the setting [cyan]batch[/cyan] (plans sampled together, default 256;
    each batch has a random stream of its own, so another size gives other plans)."""
    from cdrb_cli.artifacts import produce
    from cdrb_cli.stages.avoid import load_route_buffer
    from cdrb_cli.stages.configure import check_plan_count, plan_config, route_buffer_path
    from cdrb_cli.stages.plan import make_plans, plan_points, scene_spec
    from cdrb_cli.torch_utils import check_device_name, setup_torch

    flags = [] if n is None else [(f"--num-plans {n}", "n", n)]
    flags += [] if batch_size is None else [(f"--batch-size {batch_size}", "batch", batch_size)]
    selection = read_selection(config_file)
    settings = run_settings(None if selection else config_file, sets, flags, moved)
    m = trained_model(model, allow_partial)
    if selection is not None:  # the choice of `cdrb select` for this model, under what this command line sets
        settings = plan_part(selection_settings(selection, config_file, m)) + settings
    rb_path = route_buffer_path(settings)
    read = [model, *(p for p in (config_file, maze_map, rb_path) if p is not None)]
    check_outputs(force, read, out=out, plot=plot)
    check_device_name(device)  # before an up-to-date output returns without planning
    spec = scene_spec(m, maze_map, typed_flag(SCENE_FLAGS))
    # the settings and the plan count are checked before any pair is drawn (--pairs 100000 takes a while)
    check_plan_count(m, pairs or len(start), plan_config(m, settings, seed=seed, scene_file=maze_map))
    s_arr, g_arr = plan_points(spec, start, goal, pairs, seed)
    config = plan_config(m, settings, seed=seed, scene_file=maze_map, starts=s_arr)
    route_art = load_route_buffer(rb_path)
    result = produce(
        out,
        "plans",
        force,
        config,
        lambda: make_plans(
            m,
            s_arr,
            g_arr,
            config,
            out,
            device=setup_torch(device),
            spec=spec,
            route_buffer=route_art,
        ),
        parents=[m] if route_art is None else [m, route_art],
        env=spec,
        inputs={"starts": s_arr, "goals": g_arr},
    )
    _tell(result, spec, m, config, plot)
    summary = result.manifest.summary.model_dump()
    ui.emit({"path": str(out), "summary": summary} if as_json else out, as_json=as_json)


def _tell(result, spec, model, config, plot: Path | None) -> None:
    """What `cdrb plan` says on stderr about the plans it wrote (their safety, a masked buffer, a first step or a
    jump out of the scene), and the picture ``plot``."""
    from cdrb_cli.envs.geometry import largest_jump
    from cdrb_cli.stages.plan import draw_plans
    from cdrb_cli.stages.plan_warnings import disconnected_warning, off_scene_warning

    if config.avoid.label() != "plain":
        ui.log(f"avoiding obstacles: {config.avoid.label()}")
    sm = result.manifest.summary
    ui.log(
        f"{sm.plans} plans for {sm.pairs} pairs: {sm.in_wall_fraction:.2%} of planned states inside obstacles "
        f"({sm.plans_with_wall_states} plans touch one), {sm.seconds_per_plan * 1000:.1f} ms/plan"
    )
    if sm.masked is not None:
        ui.log(
            f"masked buffer: {sm.masked.removed} of {sm.masked.buffer_states} buffer states removed, "
            f"{sm.masked.redrawn} restored state(s) re-drawn"
        )
        if sm.masked.warning():
            ui.warn(sm.masked.warning())
    plans = result.arrays["plans"]
    jumps = largest_jump(plans[..., : spec.obs_dim], spec.obstacles.dims)
    # a plan out of the scene is the one thing to say: its first step is then off too
    warning = off_scene_warning(spec, jumps, model.manifest.config.stride, config.avoid) or disconnected_warning(
        spec, plans, model.manifest.config.stride, config.avoid
    )
    if warning:
        ui.warn(warning)
    if plot is not None:
        draw_plans(result, spec, plot)
        ui.log(f"picture: {plot}")
