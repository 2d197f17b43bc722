"""The ``cdrb`` command line: one thin command per stage (parse -> validate -> stage function -> artifact).

Conventions shared by every command: ``--seed`` for determinism, ``--out`` for the artifact written, ``--force`` to
overwrite it, ``--json`` for a machine-readable result. stdout carries only the result (the path written, or
JSON); progress and logs go to stderr. Exit codes: 0 ok, 1 the run failed, 2 bad input. Errors are one line;
``cdrb --debug ...`` shows tracebacks.
"""

from __future__ import annotations

import sys
from pathlib import Path

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
    policy: Path | None = typer.Option(
        None, "--policy", help="SB3 SAC zip from `cdrb expert train` (--expert sac)."
    ),
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
    from cdrb_cli.artifacts import prepare_output
    from cdrb_cli.stages.collect import collect as run_collect
    from cdrb_cli.stages.collect import collect_config

    if expert not in ("planner", "sac"):
        raise BadInput(f"--expert {expert!r}: unknown expert", hint="use planner or sac")
    spec = _spec(env, maze_map)
    config = collect_config(spec, episodes, seed=seed, expert=expert, policy=policy, valid_fraction=valid_fraction)
    if prepare_output(out, "demos", force, config, env=spec):
        demos = run_collect(spec, config, out)
    else:
        from cdrb_cli.artifacts import load

        demos = load(out, "demos")
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


# ------------------------------------------------------------------------------------------------ not yet built
def _not_built(name: str, issue: int):
    def command(ctx: typer.Context) -> None:
        raise BadInput(f"`cdrb {name}` is not built yet", hint=f"it arrives with issue #{issue}")

    command.__doc__ = f"(not built yet: arrives with issue #{issue})"
    return command


for _name, _issue in (
    ("cluster", 4),
    ("train", 4),
    ("plan", 4),
    ("eval", 6),
    ("report", 6),
    ("quickstart", 6),
):
    app.command(_name, context_settings={"allow_extra_args": True, "ignore_unknown_options": True})(
        _not_built(_name, _issue)
    )


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
