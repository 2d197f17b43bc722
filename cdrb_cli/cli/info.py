"""Commands that describe: inspect an artifact, the manifest schemas, the environments and methods, every
setting of a stage."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import (
    ListJsonOpt,
    app,
    check_outputs,
    choice,
    controller_registry,
    file_path,
    method_registry,
    registered,
)
from cdrb_cli.cli.options import MapOpt, MethodOpt, NetOpt, PresetOpt, env_spec
from cdrb_cli.errors import BadInput, CdrbError


# ------------------------------------------------------------------------------------------------ inspect
@app.command()
def inspect(
    file: Path = typer.Argument(..., help="Any cdrb artifact (.h5)."),
    as_json: bool = ListJsonOpt,
    plot: Path | None = typer.Option(
        None,
        "--plot",
        metavar="FILE",
        help="For a model: also draw its training curve (training and validation loss per step) to FILE (PNG).",
        parser=file_path,
    ),
    force: bool = typer.Option(False, "--force", help="Overwrite --plot if it exists (otherwise it is an error)."),
) -> None:
    """Validate an artifact and print its kind, version, provenance, summary and dataset shapes.

    Safe on any file: it never executes content and refuses hostile shapes before reading them."""
    from cdrb_cli.stages.inspect import describe, plot_training, render

    check_outputs(force, [file], plot=plot)
    info = describe(file)
    if plot is not None:
        ui.log(f"picture: {plot_training(file, plot)}")
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


@app.command()
def envs(
    as_json: bool = ListJsonOpt,
    maze_map: Path | None = MapOpt,
) -> None:
    """List the environments: family, dimensions, default plan horizon and stride, episode limit.

    A plan has HORIZON planned states, one every STRIDE environment steps, so it covers HORIZON x STRIDE steps."""
    from cdrb_cli.envs.registry import describe, list_envs

    rows = list_envs()
    if maze_map is not None:
        rows.append(describe(env_spec(None, maze_map), f"map file {maze_map}"))
    if as_json:
        ui.emit(rows, as_json=True)
        return
    ui.table(
        rows,
        [
            ("id", "id"),
            ("family", "family"),
            ("state", "obs_dim"),
            ("action", "action_dim"),
            ("goal", "goal_dim"),
            ("horizon", "horizon"),
            ("stride", "plan_stride"),
            ("limit", "episode_limit"),
            ("success r", "success_radius"),
            ("description", "description"),
        ],
    )


@app.command()
def methods(as_json: bool = ListJsonOpt) -> None:
    """List the methods `cdrb train --method` accepts: kind, samplers, networks, whether they need a buffer."""
    rows = [
        {
            "name": e.name,
            "kind": e.kind,
            "samplers": ",".join(e.samplers),
            "nets": ",".join(e.nets),
            "needs_buffer": e.needs_buffer,
            "description": e.description,
        }
        for e in method_registry().entries()
    ]
    if as_json:
        ui.emit(rows, as_json=True)
        return
    ui.table(
        rows,
        [
            ("method", "name"),
            ("kind", "kind"),
            ("samplers (default first)", "samplers"),
            ("nets (default first)", "nets"),
            ("buffer", "needs_buffer"),
            ("description", "description"),
        ],
    )


# ------------------------------------------------------------------------------------------------ config
@app.command("config")
def config_cmd(
    stage: str = typer.Argument(
        "train",
        parser=choice(lambda: ["train", "plan", "eval", "collect"], "stage"),
        metavar="train|plan|eval|collect",
        help="Which config.",
    ),
    method: str | None = MethodOpt,
    net: str | None = NetOpt,
    preset: str | None = PresetOpt,
    controller: str | None = typer.Option(
        None,
        "--controller",
        parser=registered(controller_registry, "controller"),
        metavar="NAME",
        help="eval: a controller.",
    ),
    fmt: str = typer.Option(
        "table",
        "--format",
        parser=choice(lambda: ["table", "json", "toml"], "format"),
        metavar="table|json|toml",
        help="table (keys, types, defaults, descriptions), or a json/toml template for --config.",
    ),
) -> None:
    """List every setting of a stage's config with its type, default and description.

    [cyan]cdrb config train --method cdrb --preset paper[/cyan] shows what [cyan]--set KEY=VALUE[/cyan] can change
    for that method and preset; [cyan]--format toml[/cyan] writes a template for [cyan]--config FILE[/cyan].
    Defaults that depend on the data (horizon, stride, features, CDRB's d_max) are filled in by `cdrb train`.
    [cyan]cdrb config plan[/cyan] and [cyan]cdrb config eval[/cyan] list every plan and eval knob (the sampler,
    avoidance, re-planning, the controllers' settings), [cyan]cdrb config collect[/cyan] the experts'."""
    from cdrb_cli.stages.show_config import config_template, render_template

    if stage != "train" and (method or net or preset):
        raise BadInput("--method/--net/--preset describe train settings", hint="use `cdrb config train ...`")
    if stage != "eval" and controller:
        raise BadInput("--controller describes eval settings", hint="use `cdrb config eval --controller ...`")
    if stage == "collect" and fmt != "table":
        raise BadInput(f"--format {fmt}: collect reads no --config file", hint="collect settings are --set keys")
    if stage in ("plan", "eval") and fmt == "json":
        raise BadInput(
            f"--format json: {stage} takes defaults from the model and its env, which a JSON file would override",
            hint=f"`cdrb config {stage} --format toml` writes a template with every key commented out",
        )
    template = config_template(
        stage, method=method, net=net, preset=preset, controller=controller, every_controller=fmt == "table"
    )
    sys.stdout.write(render_template(template, fmt, all_commented=stage in ("plan", "eval")))
