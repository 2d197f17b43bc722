"""The ``cdrb`` command line: one thin command per stage (parse -> validate -> stage function -> artifact).

Conventions shared by every command: ``--seed`` for determinism, ``--out`` for the artifact written, ``--force`` to
overwrite it, ``--json`` for a machine-readable result. stdout carries only the result (the path written, or
JSON); progress and logs go to stderr. Exit codes: 0 ok, 1 the run failed, 2 bad input. Errors are one line;
``cdrb --debug ...`` shows tracebacks.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import typer

try:  # typer >= 0.20 vendors click; older versions use the click package
    from typer._click import exceptions as click_exc
except ImportError:  # pragma: no cover
    from click import exceptions as click_exc

from cdrb_cli import __version__, ui
from cdrb_cli.errors import EXIT_BAD_INPUT, EXIT_FAILED, BadInput, CdrbError

app = typer.Typer(
    name="cdrb",
    help="Cold Diffusion on the Replay Buffer: plan robot trajectories through states the robot has visited.\n\n"
    "Pipeline: collect -> cluster -> train -> plan / eval -> report. Every stage writes a versioned HDF5 "
    "artifact (inspect any of them with `cdrb inspect FILE`). `cdrb quickstart` runs the whole pipeline.",
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
    context_settings={"help_option_names": ["-h", "--help"]},
)

_state = {"debug": False}

SeedOpt = typer.Option(0, "--seed", help="Random seed; the same seed and inputs give the same artifact.")
ForceOpt = typer.Option(False, "--force", help="Overwrite --out if it exists (otherwise an existing file is an error).")
JsonOpt = typer.Option(False, "--json", help="Print a JSON result on stdout instead of the path.")


def _version(value: bool) -> None:
    if value:
        typer.echo(f"cdrb {__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks for errors."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or logs on stderr."),
) -> None:
    _state["debug"] = debug
    ui.set_quiet(quiet)


# ------------------------------------------------------------------------------------------------ inspect
@app.command()
def inspect(
    file: Path = typer.Argument(..., help="Any cdrb artifact (.h5)."),
    as_json: bool = JsonOpt,
) -> None:
    """Validate an artifact and print its kind, version, provenance, summary and dataset shapes.

    Safe on any file: it never executes content and refuses hostile shapes before reading them."""
    from cdrb_cli.stages.inspect import describe, render

    info = describe(file)
    if as_json:
        ui.emit(info, as_json=True)
    else:
        render(info)


# ------------------------------------------------------------------------------------------------ schema
schema_app = typer.Typer(help="JSON Schemas of the artifact manifests.", no_args_is_help=True)
app.add_typer(schema_app, name="schema")


@schema_app.command("export")
def schema_export(
    folder: Path = typer.Argument(Path("schemas"), help="Folder to write <kind>.v<major>.schema.json into."),
):
    """Export one JSON Schema per artifact kind and major version (the files committed under schemas/)."""
    from cdrb_cli.artifacts.schema import export

    for path in export(folder):
        ui.emit(path)


@schema_app.command("check")
def schema_check(folder: Path = typer.Argument(Path("schemas"), help="Folder holding the committed schema files.")):
    """Exit 1 if the schema files in FOLDER differ from the pydantic models (run `cdrb schema export`)."""
    from cdrb_cli.artifacts.schema import drift

    stale = drift(folder)
    if stale:
        raise CdrbError(f"{folder}: schemas out of date: {', '.join(stale)}", hint=f"run `cdrb schema export {folder}`")
    ui.log(f"{folder}: schemas match the models")


# ------------------------------------------------------------------------------------------------ envs
EnvArg = typer.Argument(None, help="Environment id (see `cdrb envs`); omit it with --maze-map.")
MapOpt = typer.Option(None, "--maze-map", help="A maze map text file: rows of # wall, . free, S start, G goal, C both.")


def _spec(env: str | None, maze_map: Path | None):
    from cdrb_cli.envs.registry import make_spec

    return make_spec(env, maze_map)


@app.command()
def envs(
    as_json: bool = JsonOpt,
    maze_map: Path | None = MapOpt,
) -> None:
    """List the environments: dimensions, default plan horizon and stride, episode limit.

    A plan has HORIZON planned states, one every STRIDE environment steps, so it covers HORIZON x STRIDE steps."""
    from cdrb_cli.envs.registry import list_envs

    rows = list_envs()
    if maze_map is not None:
        spec = _spec(None, maze_map)
        rows.append(
            {
                "id": spec.id,
                "description": f"map file {maze_map}",
                "obs_dim": spec.obs_dim,
                "action_dim": spec.action_dim,
                "goal_dim": spec.goal_dim,
                "horizon": spec.horizon,
                "plan_stride": spec.plan_stride,
                "plan_env_steps": spec.plan_env_steps,
                "episode_limit": spec.episode_limit,
                "success_radius": spec.success_radius,
            }
        )
    if as_json:
        ui.emit(rows, as_json=True)
        return
    from rich.table import Table

    table = Table(
        "id",
        "state",
        "action",
        "goal",
        "horizon",
        "stride",
        "limit",
        "success r",
        "description",
        header_style="bold",
        box=None,
    )
    for r in rows:
        table.add_row(
            r["id"],
            str(r["obs_dim"]),
            str(r["action_dim"]),
            str(r["goal_dim"]),
            str(r["horizon"]),
            str(r["plan_stride"]),
            str(r["episode_limit"]),
            f"{r['success_radius']:g}",
            r["description"],
        )
    ui.stdout_console().print(table)


# ------------------------------------------------------------------------------------------------ collect
@app.command()
def collect(
    env: str | None = EnvArg,
    episodes: int = typer.Option(1000, "--episodes", "-n", min=1, help="Number of demonstrations."),
    expert: str = typer.Option("planner", "--expert", help="planner (scripted, default) or sac (needs --policy)."),
    policy: Path | None = typer.Option(None, "--policy", help="SB3 SAC zip from `cdrb expert train` (--expert sac)."),
    valid_fraction: float = typer.Option(
        0.1, "--valid-fraction", min=0.0, max=0.9, help="Episodes held out for validation."
    ),
    maze_map: Path | None = MapOpt,
    out: Path = typer.Option(Path("demos.h5"), "--out", "-o", help="Demos artifact to write."),
    plot: Path | None = typer.Option(None, "--plot", help="Also draw the maze and a sample of demos to this PNG."),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Roll out an expert and write a [bold]demos[/bold] artifact (train/valid split, per-episode seeds, success).

    The scripted planner expert takes a random shortest grid route (both gaps next to a goal get used), smooths it
    and comes to rest at the goal. Example: [cyan]cdrb collect maze-tight -n 1000 --plot demos.png[/cyan]"""
    from cdrb_cli.artifacts import produce
    from cdrb_cli.stages.collect import collect as run_collect
    from cdrb_cli.stages.collect import collect_config

    if expert not in ("planner", "sac"):
        raise BadInput(f"--expert {expert!r}: unknown expert", hint="use planner or sac")
    spec = _spec(env, maze_map)
    config = collect_config(spec, episodes, seed=seed, expert=expert, policy=policy, valid_fraction=valid_fraction)
    demos = produce(out, "demos", force, config, lambda: run_collect(spec, config, out), env=spec)
    s = demos.manifest.summary
    ui.log(
        f"{spec.id}: {s.episodes} episodes ({s.train_episodes} train / {s.valid_episodes} valid), "
        f"success {s.success_rate:.1%}, mean length {s.mean_length:.0f} steps (max {s.max_length}), "
        f"states inside walls: {s.states_in_walls}, {s.wall_time_s:.1f}s"
    )
    if s.success_rate < 0.99:
        ui.warn(f"expert success {s.success_rate:.1%} is below 99%")
    if plot is not None:
        from cdrb_cli.envs.render import plot_demos

        plot_demos(demos, plot, seed=seed)
        ui.log(f"picture: {plot}")
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
    out: Path = typer.Option(Path("expert.zip"), "--out", "-o", help="SB3 zip to write."),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
) -> None:
    """Train a goal-conditioned SAC(+HER) expert. About 11-15 ms per step on 2 CPU cores: 1M steps take 3-4 hours."""
    from cdrb_cli.artifacts import check_output
    from cdrb_cli.experts.sac import train_sac

    spec = _spec(env, maze_map)
    check_output(out, force)
    train_sac(spec, steps, seed, out, her=her)
    ui.emit(out)


# ------------------------------------------------------------------------------------------------ cluster
def _load(path: Path, kind: str):
    from cdrb_cli.artifacts import load

    return load(path, kind)


@app.command()
def cluster(
    demos: Path = typer.Argument(..., help="Demos artifact from `cdrb collect`."),
    k: int = typer.Option(1000, "--k", min=0, help="k-means clusters; 0 keeps the full buffer."),
    features: str = typer.Option("state", "--features", help="state, or state-action (actions joined to states)."),
    split: str = typer.Option("train", "--split", help="Episodes whose states form the buffer: train or all."),
    out: Path = typer.Option(Path("buffer.h5"), "--out", "-o", help="Buffer artifact to write."),
    plot: Path | None = typer.Option(None, "--plot", help="Also draw the buffer states on the map to this PNG."),
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

    if features not in ("state", "state-action"):
        raise BadInput(f"--features {features!r}: unknown", hint="use state or state-action")
    if split not in ("train", "all"):
        raise BadInput(f"--split {split!r}: unknown", hint="use train or all")
    d = _load(demos, "demos")
    config = ClusterConfig(k=k, features=features, split=split, seed=seed)
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


# ------------------------------------------------------------------------------------------------ train
@app.command()
def train(
    demos: Path = typer.Argument(..., help="Demos artifact from `cdrb collect`."),
    buffer: Path | None = typer.Option(None, "--buffer", help="Buffer artifact (required for --method cdrb)."),
    method: str = typer.Option("cdrb", "--method", help="cdrb, diffuser (Gaussian DDPM baseline) or mlp."),
    net: str | None = typer.Option(None, "--net", help="unet (default) or transformer; mlp for --method mlp."),
    preset: str = typer.Option("quick", "--preset", help="quick (minutes on CPU) or paper (reference settings)."),
    steps: int | None = typer.Option(None, "--steps", help="Gradient steps (preset: quick 3000, paper 20000)."),
    horizon: int | None = typer.Option(None, "--horizon", help="Planned states per plan (env default: 168)."),
    stride: int | None = typer.Option(None, "--stride", help="Env steps per planned state (env default: 2)."),
    diffusion_steps: int | None = typer.Option(None, "--diffusion-steps", help="T (preset: quick 32, paper 128)."),
    schedule: str = typer.Option("linear", "--schedule", help="CDRB ball radius schedule: linear, log, sqrt, sigmoid."),
    d_max: float | None = typer.Option(None, "--d-max", help="CDRB largest radius (default: buffer diameter)."),
    features: str | None = typer.Option(None, "--features", help="state or state-action (CDRB: the buffer's)."),
    dim: int | None = typer.Option(None, "--dim", help="U-Net base width (preset: quick 16, paper 32)."),
    dim_mults: str | None = typer.Option(None, "--dim-mults", help="U-Net width multipliers, e.g. 1,4,8."),
    residual: bool | None = typer.Option(
        None, "--residual/--no-residual", help="U-Net output = input + correction (preset: quick on, paper off)."
    ),
    loss_weight_power: float | None = typer.Option(
        None, "--loss-weight-power", help="CDRB: weight samples by (eps_1/eps_k)^p (preset: quick 1, paper 0)."
    ),
    batch_size: int | None = typer.Option(None, "--batch-size", help="Windows per step (preset)."),
    lr: float | None = typer.Option(None, "--lr", help="Adam learning rate (preset)."),
    checkpoint_every: int | None = typer.Option(None, "--checkpoint-every", help="Save a checkpoint every N steps."),
    start_fraction: float | None = typer.Option(
        None, "--start-fraction", help="Share of windows starting at an episode's start (default 0.9)."
    ),
    device: str = typer.Option("auto", "--device", help="auto (CUDA when present), cpu or cuda."),
    out: Path = typer.Option(Path("model.h5"), "--out", "-o", help="Model artifact to write (also the checkpoint)."),
    resume: bool = typer.Option(False, "--resume", help="Continue the checkpoint in --out (same flags and inputs)."),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Train a planner on demonstration windows and write a [bold]model[/bold] artifact.

    CDRB learns R(tau_k, k) ~ tau_0 where tau_k replaces each state by a random buffer state within radius eps_k.
    Windows are HORIZON states every STRIDE env steps, padded with the demo's final (resting) state; start and goal
    are pinned. The model is checkpointed into --out every --checkpoint-every steps: after a crash,
    [cyan]--resume[/cyan] continues to exactly the result of an uninterrupted run.
    Example: [cyan]cdrb train demos.h5 --buffer buffer.h5 --method cdrb --preset quick[/cyan]"""
    from cdrb_cli.artifacts import find_up_to_date
    from cdrb_cli.presets import PRESETS
    from cdrb_cli.stages.train import resolve_config
    from cdrb_cli.stages.train import train as run_train
    from cdrb_cli.torch_utils import setup_torch

    if preset not in PRESETS:
        raise BadInput(f"--preset {preset!r}: unknown", hint="use quick or paper")
    if method not in ("cdrb", "diffuser", "mlp"):
        raise BadInput(f"--method {method!r}: unknown", hint="use cdrb, diffuser or mlp")
    if net is not None and net not in ("unet", "transformer", "mlp"):
        raise BadInput(f"--net {net!r}: unknown", hint="use unet or transformer")
    if schedule not in ("linear", "log", "sqrt", "sigmoid"):
        raise BadInput(f"--schedule {schedule!r}: unknown", hint="use linear, log, sqrt or sigmoid")
    if features is not None and features not in ("state", "state-action"):
        raise BadInput(f"--features {features!r}: unknown", hint="use state or state-action")
    for flag, value in (
        ("--horizon", horizon),
        ("--stride", stride),
        ("--steps", steps),
        ("--batch-size", batch_size),
        ("--checkpoint-every", checkpoint_every),
    ):
        if value is not None and value <= 0:
            raise BadInput(f"{flag} {value}: must be a positive integer", hint=f"pass {flag} N with N > 0")
    if d_max is not None and not d_max > 0:
        raise BadInput(f"--d-max {d_max}: must be positive", hint="omit it to use the buffer diameter")
    mults = None
    if dim_mults is not None:
        try:
            mults = [int(v) for v in dim_mults.split(",") if v.strip()]
        except ValueError:
            raise BadInput(f"--dim-mults {dim_mults!r}: not a list of integers", hint="e.g. 1,4,8") from None
        if not mults:
            raise BadInput("--dim-mults is empty", hint="e.g. 1,4,8")
    d = _load(demos, "demos")
    b = _load(buffer, "buffer") if buffer is not None else None
    config = resolve_config(
        d,
        b,
        method,
        preset=preset,
        net=net,
        features=features,
        horizon=horizon,
        stride=stride,
        diffusion=diffusion_steps,
        schedule=schedule,
        d_max=d_max,
        seed=seed,
        steps=steps,
        dim=dim,
        dim_mults=mults,
        start_fraction=start_fraction,
        residual=residual,
        loss_weight_power=loss_weight_power,
        batch_size=batch_size,
        lr=lr,
        checkpoint_every=checkpoint_every,
    )
    parents = [d] + ([b] if b is not None else [])
    if out.exists() and not force and not resume:
        model = find_up_to_date(out, "model", config, parents)
        if model is not None:
            ui.log(f"[green]{out}[/green] is up to date (same config and inputs): skipped; --force redoes it")
            ui.emit({"path": str(out), "state": model.manifest.state.model_dump()} if as_json else out, as_json=as_json)
            return
        raise BadInput(f"--out {out}: file exists", hint="pass --resume to continue it, --force to overwrite it")
    if resume and force:
        raise BadInput("--resume and --force together", hint="--resume continues --out; --force starts over")
    from cdrb_cli.artifacts import check_output

    check_output(out, force=True)
    dev = setup_torch(device)
    model = run_train(d, b, config, out, resume=resume, device=dev)
    st = model.manifest.state
    ui.log(
        f"{method}: {st.step} steps, loss {st.loss:.4f}"
        + (f", valid {st.valid_loss:.4f}" if st.valid_loss is not None else "")
        + f", {st.parameters:,} parameters, {st.wall_time_s:.0f}s"
    )
    ui.emit({"path": str(out), "state": st.model_dump()} if as_json else out, as_json=as_json)


# ------------------------------------------------------------------------------------------------ plan
@app.command()
def plan(
    model: Path = typer.Argument(..., help="Model artifact from `cdrb train`."),
    start: list[str] = typer.Option([], "--start", help="Start x,y (at rest) or x,y,vx,vy; repeat for several."),
    goal: list[str] = typer.Option([], "--goal", help="Goal x,y; one per --start (or one for all)."),
    pairs: int = typer.Option(0, "--pairs", min=0, help="Instead: N start/goal pairs drawn by the eval protocol."),
    n: int = typer.Option(1, "--n", min=1, help="Plans per start/goal pair."),
    sampler: str | None = typer.Option(None, "--sampler", help="cdrb: alg1 (default) or alg2; diffuser: ddpm, ddim."),
    sample_steps: int | None = typer.Option(None, "--sample-steps", help="Fewer denoising steps (default: all)."),
    raw_weights: bool = typer.Option(False, "--raw-weights", help="Plan with the raw weights instead of the EMA."),
    show_steps: int = typer.Option(0, "--show-steps", min=0, help="Keep N intermediate iterates (drawn by --plot)."),
    batch_size: int = typer.Option(256, "--batch-size", min=1, help="Plans sampled together."),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda."),
    out: Path = typer.Option(Path("plans.h5"), "--out", "-o", help="Plans artifact to write."),
    plot: Path | None = typer.Option(None, "--plot", help="Draw the maze and the plans to this PNG."),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Plan from start to goal and write a [bold]plans[/bold] artifact (start and goal held exactly).

    CDRB (Algorithm 1): start from random buffer states, then repeatedly restore and re-degrade with shrinking
    balls. Example: [cyan]cdrb plan model.h5 --start 0,0 --goal 6,6 --n 8 --plot plans.png --show-steps 4[/cyan]"""
    from cdrb_cli.artifacts import produce
    from cdrb_cli.configs import PlanConfig
    from cdrb_cli.envs.protocol import draw_pairs, goal_state, pair_states
    from cdrb_cli.seeding import STREAM_PLAN
    from cdrb_cli.stages.plan import check_state, make_plans, parse_state
    from cdrb_cli.torch_utils import setup_torch

    m = _load(model, "model")
    spec = m.manifest.env
    if pairs:
        if start or goal:
            raise BadInput("--pairs with --start/--goal", hint="give either explicit points or --pairs N")
        s_arr, g_xy = pair_states(spec, draw_pairs(spec, pairs, seed, STREAM_PLAN))
        g_arr = goal_state(spec, g_xy)
    else:
        if not start or not goal:
            raise BadInput("no start/goal given", hint="pass --start X,Y --goal X,Y (or --pairs N)")
        if len(goal) == 1 and len(start) > 1:
            goal = goal * len(start)
        if len(goal) != len(start):
            raise BadInput(f"{len(start)} --start but {len(goal)} --goal", hint="give one goal per start, or one")
        s_arr = np.array([parse_state(t, "--start", spec) for t in start])
        g_arr = np.array([parse_state(t, "--goal", spec) for t in goal])
        for st_ in s_arr:
            check_state(st_, "--start", spec)
        for gl_ in g_arr:
            check_state(gl_, "--goal", spec)
    cfg_method = m.manifest.config.method
    chosen = sampler or getattr(cfg_method, "sampler", "direct")
    allowed = {"cdrb": ("alg1", "alg2"), "diffuser": ("ddpm", "ddim"), "mlp": ("direct",)}[cfg_method.name]
    if chosen not in allowed:
        raise BadInput(f"--sampler {chosen}: {cfg_method.name} models use {', '.join(allowed)}")
    if sample_steps is not None and sample_steps < 1:
        raise BadInput(f"--sample-steps {sample_steps}: must be positive")
    config = PlanConfig(
        sampler=chosen, n=n, sample_steps=sample_steps, use_ema=not raw_weights, keep_iterates=show_steps, seed=seed
    )
    result = produce(
        out,
        "plans",
        force,
        config,
        lambda: make_plans(m, s_arr, g_arr, config, out, device=setup_torch(device), batch_size=batch_size),
        parents=[m],
    )
    sm = result.manifest.summary
    ui.log(
        f"{sm.plans} plans for {sm.pairs} pairs: {sm.in_wall_fraction:.2%} of planned states inside walls "
        f"({sm.plans_with_wall_states} plans touch a wall), {sm.seconds_per_plan * 1000:.1f} ms/plan"
    )
    if plot is not None:
        from cdrb_cli.envs.render import plot_plans

        a = result.arrays
        plot_plans(
            spec,
            a["plans"],
            plot,
            starts=a["starts"],
            goals=a["goals"],
            in_wall=a["in_wall"],
            title=f"{result.manifest.method}: {sm.plans} plans, {sm.in_wall_fraction:.1%} states in walls",
            iterates=a.get("iterates"),
            iterate_steps=a.get("iterate_steps"),
        )
        ui.log(f"picture: {plot}")
    ui.emit({"path": str(out), "summary": sm.model_dump()} if as_json else out, as_json=as_json)


# ------------------------------------------------------------------------------------------------ eval
def _int_list(text: str, flag: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise BadInput(f"{flag} {text!r}: not a comma-separated list of integers", hint="e.g. 0,1,2,3,4") from None
    if not values:
        raise BadInput(f"{flag} is empty", hint="e.g. 0,1,2,3,4")
    if len(set(values)) != len(values):
        raise BadInput(f"{flag} {text!r}: repeated values", hint="list each seed once")
    return values


@app.command("eval")
def eval_cmd(
    model: Path = typer.Argument(..., help="Model artifact from `cdrb train`."),
    episodes: int = typer.Option(100, "--episodes", "-n", min=1, help="Episodes per evaluation seed."),
    seeds: str = typer.Option("0,1,2,3,4", "--seeds", help="Evaluation seeds (each draws its own start/goal pairs)."),
    controller: str = typer.Option("pd", "--controller", help="pd (kp 10, kd 1) or inverse-dynamics."),
    max_lag: float | None = typer.Option(
        None,  # configs.DEFAULT_MAX_LAG, resolved below so that start-up does not import the configs
        "--max-lag",
        min=0.0,
        show_default=False,
        help="Pause the plan's clock while the ball lags more than this many metres behind it (default 0.6); 0: "
        "follow the plan on the environment's clock.",
    ),
    sampler: str | None = typer.Option(None, "--sampler", help="Override the model's sampler (alg1/alg2, ddpm/ddim)."),
    sample_steps: int | None = typer.Option(None, "--sample-steps", help="Fewer denoising steps (default: all)."),
    raw_weights: bool = typer.Option(False, "--raw-weights", help="Plan with raw instead of EMA weights."),
    video: Path | None = typer.Option(None, "--video", help="Write rollout GIFs of the first episodes to this folder."),
    videos: int = typer.Option(3, "--videos", min=1, help="How many rollout GIFs with --video."),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda."),
    out: Path = typer.Option(Path("eval.h5"), "--out", "-o", help="Eval artifact to write."),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Plan once per episode, execute the plan in MuJoCo with a controller, and write an [bold]eval[/bold] artifact.

    Start/goal pairs follow one protocol (starts in the map's start cells, goals in its goal cells, the stock
    reset noise; for the paper's mazes: centre starts, corner goals) and are identical across methods for the same
    seeds. Per episode: success within the env's success radius at any step, steps, final distance, planned states
    inside walls, executed collisions, path length relative to the expert, planning time.
    Example: [cyan]cdrb eval model.h5 --seeds 0,1,2,3,4 --episodes 100 --video gifs/[/cyan]"""
    if video is not None:
        from cdrb_cli.envs.render import choose_gl_backend

        choose_gl_backend()  # before MuJoCo is imported
    from cdrb_cli.artifacts import produce
    from cdrb_cli.configs import DEFAULT_MAX_LAG, EvalConfig
    from cdrb_cli.stages.evaluate import evaluate
    from cdrb_cli.torch_utils import setup_torch

    if controller not in ("pd", "inverse-dynamics"):
        raise BadInput(f"--controller {controller!r}: unknown", hint="use pd or inverse-dynamics")
    seed_list = _int_list(seeds, "--seeds")
    m = _load(model, "model")
    cfg_method = m.manifest.config.method
    chosen = sampler or getattr(cfg_method, "sampler", "direct")
    allowed = {"cdrb": ("alg1", "alg2"), "diffuser": ("ddpm", "ddim"), "mlp": ("direct",)}[cfg_method.name]
    if chosen not in allowed:
        raise BadInput(f"--sampler {chosen}: {cfg_method.name} models use {', '.join(allowed)}")
    if sample_steps is not None and sample_steps < 1:
        raise BadInput(f"--sample-steps {sample_steps}: must be positive")
    if video is not None and video.exists() and not video.is_dir():
        raise BadInput(f"--video {video}: exists and is not a folder", hint="pass a folder path")
    config = EvalConfig(
        episodes=episodes,
        seeds=seed_list,
        controller=controller,
        max_lag=(DEFAULT_MAX_LAG if max_lag is None else max_lag) or None,
        sampler=chosen,
        sample_steps=sample_steps,
        use_ema=not raw_weights,
        seed=seed,
    )
    n_videos = videos if video is not None else 0
    ev = produce(
        out,
        "eval",
        force,
        config,
        lambda: evaluate(m, config, out, device=setup_torch(device), video_dir=video, videos=n_videos),
        parents=[m],
    )
    s = ev.manifest.summary
    ui.log(
        f"{s.method} on {m.manifest.env.id}: success {100 * s.success_mean:.1f} ± {100 * s.success_std:.1f}% "
        f"over {len(seed_list)} seeds x {episodes} episodes; planned states in walls "
        f"{100 * s.in_wall_mean:.2f}%; executed collisions {100 * s.executed_collision_mean:.1f}%; "
        f"plan {1000 * s.plan_seconds_mean:.1f} ms"
    )
    if video is not None:
        ui.log(f"rollout GIFs: {video}/")
    ui.emit({"path": str(out), "summary": s.model_dump()} if as_json else out, as_json=as_json)


# ------------------------------------------------------------------------------------------------ report
@app.command()
def report(
    evals: list[Path] = typer.Argument(
        ..., help="Eval artifacts (any number; rows = environments, columns = methods)."
    ),
    fmt: str = typer.Option("table", "--format", help="table, markdown, csv or json."),
    paper: bool = typer.Option(False, "--paper", help="Add the paper's Table 1 figures under ours."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Write the report to this file (else stdout)."),
    plot: Path | None = typer.Option(None, "--plot", help="Bar chart of success and planned-in-wall rates (PNG)."),
    plans_plot: Path | None = typer.Option(None, "--plans-plot", help="Every method's plans for the same pairs (PNG)."),
) -> None:
    """Compare eval artifacts in a Table-1-style report (success mean ± std over seeds, plus planned states in
    walls, executed collisions, path length and planning time), with optional pictures.

    Evals of one environment must share a protocol (seeds, episodes, controller); mixing is an error."""
    from cdrb_cli.stages.report import collect_rows, plot_bars, plot_side_by_side, render

    if fmt not in ("table", "markdown", "csv", "json"):
        raise BadInput(f"--format {fmt!r}: unknown", hint="use table, markdown, csv or json")
    arts = [_load(p, "eval") for p in evals]
    rows = collect_rows(arts)
    text = render(rows, fmt, paper=paper)
    if plot is not None:
        plot_bars(rows, plot)
        ui.log(f"picture: {plot}")
    if plans_plot is not None:
        plot_side_by_side(arts, plans_plot)
        ui.log(f"picture: {plans_plot}")
    if out is not None:
        from cdrb_cli.artifacts import atomic_path

        with atomic_path(out) as tmp:
            tmp.write_text(text)
        ui.emit(out)
    else:
        sys.stdout.write(text)


# ------------------------------------------------------------------------------------------------ quickstart
@app.command()
def quickstart(
    out: Path = typer.Option(Path("runs/quickstart"), "--out", "-o", help="Folder for every artifact and picture."),
    env: str = typer.Option("maze-tight", "--env", help="Environment id."),
    episodes: int = typer.Option(1000, "--episodes", min=2, help="Demonstrations to collect."),
    k: int = typer.Option(1000, "--k", min=0, help="Buffer size after k-means (0 = full buffer)."),
    methods: str = typer.Option("cdrb,diffuser", "--methods", help="Methods to train and compare."),
    seeds: str = typer.Option("0,1", "--seeds", help="Evaluation seeds."),
    eval_episodes: int = typer.Option(50, "--eval-episodes", min=1, help="Episodes per evaluation seed."),
    steps: int | None = typer.Option(None, "--steps", help="Training steps per method (quick preset: 3000)."),
    videos: int = typer.Option(0, "--videos", min=0, help="Rollout GIFs per method (0: none)."),
    device: str = typer.Option("auto", "--device", help="auto, cpu or cuda."),
    seed: int = SeedOpt,
) -> None:
    """Run the whole pipeline on Maze Tight: collect -> cluster -> train CDRB and Diffuser (quick) -> eval ->
    report. About 10 minutes on 2 CPU cores. Re-running skips every stage that is up to date; an interrupted run
    resumes where it stopped. Prints the results table and the paths of the pictures."""
    if videos:
        from cdrb_cli.envs.render import choose_gl_backend

        choose_gl_backend()
    from cdrb_cli.stages.pipeline import quickstart as run_quickstart
    from cdrb_cli.torch_utils import setup_torch

    method_list = tuple(m.strip() for m in methods.split(",") if m.strip())
    for m in method_list:
        if m not in ("cdrb", "diffuser", "mlp"):
            raise BadInput(f"--methods: unknown method {m!r}", hint="use cdrb, diffuser, mlp")
    if not method_list or len(set(method_list)) != len(method_list):
        raise BadInput(f"--methods {methods!r}: give each method once", hint="e.g. cdrb,diffuser")
    from cdrb_cli.envs.registry import make_spec

    make_spec(env)
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out}: exists and is not a folder", hint="pass a folder path")
    if steps is not None and steps <= 0:
        raise BadInput(f"--steps {steps}: must be positive")
    dev = setup_torch(device)
    res = run_quickstart(
        out,
        env=env,
        episodes=episodes,
        k=k,
        methods=method_list,
        seeds=tuple(_int_list(seeds, "--seeds")),
        eval_episodes=eval_episodes,
        steps=steps,
        seed=seed,
        device=dev,
        videos=videos,
    )
    ui.log(f"done in {res.seconds / 60:.1f} min; artifacts in {res.folder}/")
    sys.stdout.write(res.report)
    sys.stdout.write("\n" + "\n".join(str(p) for p in res.pictures) + "\n")


# ------------------------------------------------------------------------------------------------ entry point
def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _error(text: str) -> None:
    sys.stderr.write(f"error: {_one_line(text)}\n")
    sys.stderr.flush()


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 failed run, 2 bad input)."""
    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args
    command = typer.main.get_command(app)
    try:
        command.main(args=args, prog_name="cdrb", standalone_mode=False)
        return 0
    except typer.Exit as exc:
        return exc.exit_code
    except click_exc.UsageError as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":  # the help text was the answer
            if exc.ctx is not None:
                sys.stdout.write(exc.ctx.get_help() + "\n")
            return EXIT_BAD_INPUT
        where = exc.ctx.command_path if exc.ctx else "cdrb"
        _error(f"{exc.format_message()} (see `{where} --help`)")
        return EXIT_BAD_INPUT
    except click_exc.ClickException as exc:
        _error(exc.format_message())
        return EXIT_BAD_INPUT
    except typer.Abort:
        _error("aborted")
        return 130
    except CdrbError as exc:
        if debug:
            raise
        _error(exc.line())
        return exc.exit_code
    except KeyboardInterrupt:
        _error("interrupted; artifacts already written are intact")
        return 130
    except Exception as exc:  # a bug or an environment failure: still one line unless --debug
        if debug:
            raise
        _error(f"{type(exc).__name__}: {_one_line(str(exc))[:300]} (re-run with `cdrb --debug ...` for a traceback)")
        return EXIT_FAILED


if __name__ == "__main__":
    sys.exit(main())
