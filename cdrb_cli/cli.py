"""The ``cdrb`` command line: one thin command per stage (parse -> validate -> stage function -> artifact).

Conventions shared by every command: ``--seed`` for determinism, ``--out`` for the artifact written, ``--force`` to
overwrite it, ``--json`` for a machine-readable result. stdout carries only the result (the path written, or
JSON); progress and logs go to stderr. Exit codes: 0 ok, 1 the run failed, 2 bad input. Errors are one line;
``cdrb --debug ...`` shows tracebacks.

Names of environments, methods, samplers, experts and controllers are never spelled here: they come from the
registries (:mod:`cdrb_cli.envs.registry`, :mod:`cdrb_cli.methods.registry`), looked up when a command runs, so a
registered plugin is a valid choice too. Training hyper-parameters come from the config's own fields
(``--set KEY=VALUE``, ``--config FILE``; ``cdrb config train`` lists them).
"""

from __future__ import annotations

import contextlib
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import typer

try:  # typer >= 0.20 vendors click; older versions use the click package
    from typer._click import exceptions as click_exc
except ImportError:  # pragma: no cover
    from click import exceptions as click_exc

from cdrb_cli import PROG, __version__, interrupts, provenance, ui
from cdrb_cli.errors import EXIT_BAD_INPUT, EXIT_FAILED, EXIT_INTERRUPTED, BadInput, CdrbError

#: what `--help` shows for a value of each Python type typer names (a flag shows nothing)
_READABLE = {"bool": "", "int": "N", "float": "X", "str": "TEXT", "path": "FILE", "file": "FILE", "directory": "DIR"}


def _readable_help() -> None:
    """Help that names values as a person reads them (N, X, FILE, TEXT, DEMOS) instead of Python types (``<int>``,
    ``<list[str]>``, ``{demos}``). Typer has no hook for its type labels, so its two label methods are wrapped."""
    import re

    from typer import core

    base = getattr(core, "_TyperParameter", None)
    if base is None or not hasattr(core, "TyperArgument"):  # another typer layout: keep its own labels
        return
    label = base.display_type

    def display_type(self, ctx) -> str:
        text = label(self, ctx)
        m = re.fullmatch(r"<(list\[)?(\w+)(?: range)?\]?>", text)
        if m is None:
            return text
        word = _READABLE.get(m.group(2).lower(), m.group(2).upper())
        return f"{word}..." if m.group(1) and word else word

    def usage_name(self) -> str:
        name = (self.metavar or self.name or "").upper()
        name = name if self.required else f"[{name}]"
        return name + ("..." if self.nargs != 1 else "")

    base.display_type = display_type
    core.TyperArgument._usage_display_name = usage_name


_readable_help()

app = typer.Typer(
    name=PROG,
    help="Cold Diffusion on the Replay Buffer: plan robot trajectories through states the robot has visited.\n\n"
    "Pipeline: collect -> cluster -> train -> plan / eval -> report. Every stage writes a versioned HDF5 "
    "artifact (inspect any of them with `cdrb inspect FILE`). `cdrb quickstart` runs the whole pipeline.",
    add_completion=True,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
    context_settings={"help_option_names": ["-h", "--help"]},
)

SeedOpt = typer.Option(
    0, "--seed", min=0, max=2**32 - 1, help="Random seed (32-bit); the same seed and inputs give the same artifact."
)
ForceOpt = typer.Option(False, "--force", help="Overwrite --out if it exists (otherwise an existing file is an error).")
JsonOpt = typer.Option(False, "--json", help="Print a JSON result on stdout instead of the path.")
ListJsonOpt = typer.Option(False, "--json", help="Print JSON on stdout instead of the table.")
GridSetOpt = typer.Option(
    [],
    "--set",
    metavar="KEY=VALUE",
    help="Replace a top-level key of the grid file, e.g. --set demos=40 --set 'seeds=[0]' --set out=runs/small "
    "(VALUE is read as TOML; `out` is then relative to the current folder). Repeatable; `cdrb select` takes the "
    "same --set as the `cdrb grid` run that made the evals.",
)
GridIncludeOpt = typer.Option(
    [],
    "--include",
    metavar="FILE",
    help="A settings file applied after the grid's own settings (e.g. smaller nets for a smoke run). Repeatable.",
)
DeviceOpt = typer.Option("auto", "--device", help="auto (CUDA when present), cpu or cuda.")


# ------------------------------------------------------------------------------------------------ choices
def _choice(values: Callable[[], list[str]], what: str) -> Callable[[str], str]:
    """A typer ``parser`` accepting the strings ``values()`` gives when the option is parsed (not at start-up)."""

    def parse(value: str) -> str:
        allowed = values()
        if value not in allowed:
            raise ValueError(f"{value!r} is not a known {what} (choose one of {', '.join(allowed)})")
        return value

    return parse


def _registered(registry: Callable, what: str) -> Callable[[str], str]:
    """A typer ``parser`` accepting the names of a registry (plugins included)."""
    return _choice(lambda: registry().names(), what)


def _methods():
    from cdrb_cli.methods.registry import METHODS

    return METHODS


def _experts():
    from cdrb_cli.envs.registry import EXPERTS

    return EXPERTS


def _controllers():
    from cdrb_cli.envs.registry import CONTROLLERS

    return CONTROLLERS


def _nets() -> list[str]:
    from cdrb_cli.configs import net_kinds

    return net_kinds()


def _presets() -> list[str]:
    from cdrb_cli.presets import PRESETS

    return list(PRESETS)


def _literal(model: str, field: str) -> Callable[[], list[str]]:
    """The values of a ``Literal`` field of a config record (``configs.<model>.<field>``)."""

    def values() -> list[str]:
        import typing

        from cdrb_cli import configs

        annotation = getattr(configs, model).model_fields[field].annotation
        return list(typing.get_args(annotation))

    return values


def _version(value: bool) -> None:
    if value:
        typer.echo(f"{PROG} {__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks for errors."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or logs on stderr."),
) -> None:
    ui.set_quiet(quiet)


def _load(path: Path, kind: str):
    from cdrb_cli.artifacts import load

    return load(path, kind)


def _ints(text: str, flag: str, what: str, example: str) -> list[int]:
    """A non-empty comma-separated list of integers (``what`` and ``example`` word the errors)."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise BadInput(f"{flag} {text!r}: not a comma-separated list of {what}", hint=f"e.g. {example}") from None
    if not values:
        raise BadInput(f"{flag} is empty", hint=f"e.g. {example}")
    return values


def _int_list(text: str, flag: str) -> list[int]:
    values = _ints(text, flag, "integers", "0,1,2,3,4")
    if len(set(values)) != len(values):
        raise BadInput(f"{flag} {text!r}: repeated values", hint="list each seed once")
    if any(not 0 <= v < 2**32 for v in values):
        raise BadInput(f"{flag} {text!r}: seeds are 32-bit (0 to 4294967295)", hint="e.g. 0,1,2,3,4")
    return values


PICTURES = (".png", ".pdf", ".svg")


def _check_outputs(force: bool, inputs=(), **outputs: Path | None) -> None:
    """Every output path of a command (``out=..., plot=...``), before any work: the rule of
    :func:`cdrb_cli.artifacts.check_output`, pictures with a picture suffix, and no two outputs the same."""
    from cdrb_cli.artifacts import check_output
    from cdrb_cli.artifacts.outputs import distinct_outputs

    distinct_outputs(**outputs)
    for name, path in outputs.items():
        # --out is checked (and locked) by the stage that writes it; --docs is rewritten in place, not created
        if path is not None and name not in ("out", "docs"):
            check_output(Path(path), force, "--" + name.replace("_", "-"), inputs, suffixes=PICTURES)


def _check_positive(flag: str, value) -> None:
    if value is not None and value <= 0:
        raise BadInput(f"{flag} {value}: must be positive", hint=f"pass {flag} N with N > 0")


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
    ),
    force: bool = ForceOpt,
) -> None:
    """Validate an artifact and print its kind, version, provenance, summary and dataset shapes.

    Safe on any file: it never executes content and refuses hostile shapes before reading them."""
    from cdrb_cli.stages.inspect import describe, plot_training, render

    _check_outputs(force, [file], plot=plot)
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


# ------------------------------------------------------------------------------------------------ envs, methods
EnvArg = typer.Argument(None, help="Environment id (see `cdrb envs`); omit it with --maze-map.")
MapOpt = typer.Option(None, "--maze-map", help="A maze map text file: rows of # wall, . free, S start, G goal, C both.")


SceneMapOpt = typer.Option(
    None,
    "--scene",
    "--maze-map",
    metavar="FILE",
    help="Plan among obstacles the data never saw, the model not retrained: for a maze, a map file (the training "
    "map with walls added, same size and cell size); for Fetch, a TOML file of \\[\\[boxes]] (center, half) put down. "
    "Plans then avoid them with the settings chosen for new obstacles (`--set avoid=plain`: as the model is).",
)

#: flags of plan and eval that now live in the configs: flag -> (config key, how a value is shown); they keep
#: working, hidden from --help, with a one-line note naming the key
MOVED_FLAGS = {
    "--mask-buffer": ("avoid.mask_buffer", None),
    "--best-of": ("avoid.best_of", None),
    "--guide-scale": ("avoid.guide_scale", None),
    "--route-k": ("avoid.route_k", None),
    "--route-clearance": ("avoid.route_clearance", None),
    "--route-buffer": ("avoid.route_buffer", None),
    "--sampler": ("sampler", None),
    "--sample-steps": ("sample_steps", None),
    "--raw-weights": ("use_ema", False),
    "--show-steps": ("keep_iterates", None),
    "--controller": ("controller.name", None),
    "--max-lag": ("controller.max_lag", None),
    "--repair-k": ("replan.repair_k", None),
    "--repair-steps": ("replan.repair_steps", None),
}


def _moved(flag: str, default=None, **kw):
    return typer.Option(default, flag, hidden=True, help=f"Moved: --set {MOVED_FLAGS[flag][0]}=VALUE.", **kw)


RunSetOpt = typer.Option(
    [],
    "--set",
    metavar="KEY=VALUE",
    help="Set any config field, e.g. --set avoid.best_of=8 --set controller.look_ahead=2 (repeatable; `cdrb config "
    "plan|eval` lists them with their defaults).",
)
RunConfigOpt = typer.Option(
    None, "--config", help="A TOML or JSON file of settings (`cdrb config plan|eval --format toml` writes a template)."
)


def _run_settings(config_file: Path | None, sets: list[str], flags: list[tuple[str, str, object]], moved: dict):
    """The settings of a plan or an eval in priority order: the ``--config`` file, the flags, then ``--set``
    (a field given both by a flag and by ``--set`` is refused). ``flags``: (source text, key, value) of the
    everyday flags given; ``moved``: moved flag -> value given (None: not given), each noted once."""
    from cdrb_cli.settings import Setting, lookup, parse_set, read_config_file

    items = read_config_file(config_file) if config_file is not None else []
    given = [Setting(tuple(key.split(".")), value, source) for source, key, value in flags]
    for flag, value in moved.items():
        if value is None or value is False:
            continue
        key, fixed = MOVED_FLAGS[flag]
        value = fixed if fixed is not None else value
        value = str(value) if isinstance(value, Path) else value
        if flag == "--max-lag" and value == 0:
            value = None  # 0 meant: follow the plan on the environment's clock
        shown = "null" if value is None else str(value).lower() if isinstance(value, bool) else value
        ui.warn(f"{flag} is deprecated: write --set {key}={shown} (or put it in a --config file)")
        given.append(Setting(tuple(key.split(".")), value, flag if isinstance(value, bool) else f"{flag} {value}"))
    sets_ = parse_set(sets)
    for s in sets_:
        clash = lookup(given, s.path)
        if clash is not None:
            raise BadInput(f"{clash.source} with {s.source}", hint="give it once")
    return items + given + sets_


def _spec(env: str | None, maze_map: Path | None):
    from cdrb_cli.envs.registry import make_spec

    return make_spec(env, maze_map)


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
        rows.append(describe(_spec(None, maze_map), f"map file {maze_map}"))
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
        for e in _methods().entries()
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


def _check_video_folder(video: Path, out: Path | None = None) -> None:
    """--video names a folder (made if missing), checked before any work: not an existing file, under a folder
    that can be made and written (not under a file), and not the folder of the run's own --out (a GIF could take
    the artifact's name)."""
    if video.exists() and not video.is_dir():
        raise BadInput(f"--video {video}: exists and is not a folder", hint="pass a folder path")
    first = video
    while not first.exists() and first != first.parent:
        first = first.parent
    if not first.is_dir() or not os.access(first, os.W_OK | os.X_OK):
        what = "is not a folder" if not first.is_dir() else "is not writable"
        raise BadInput(f"--video {video}: {first} {what}", hint="pass a folder that can be made and written")
    if out is not None and Path(out).resolve().parent == video.resolve():
        raise BadInput(
            f"--out {out}: inside the --video folder {video}", hint="keep the artifact outside the GIFs' folder"
        )


def _report_gifs(video: Path, since: float, out: Path) -> None:
    """Say where the GIFs went, or that none were written (an up-to-date artifact is not re-run)."""
    written = [p for p in video.glob("*.gif") if p.stat().st_mtime >= since - 1] if video.is_dir() else []
    if written:
        ui.log(f"{len(written)} GIF(s) in {video}/")
    else:
        ui.log(f"no GIFs written: {out} is up to date, so nothing ran (--force re-runs it with --video)")


# ------------------------------------------------------------------------------------------------ collect
@app.command()
def collect(
    env: str | None = EnvArg,
    episodes: int = typer.Option(1000, "--episodes", "-n", min=1, max=1_000_000, help="Number of demonstrations."),
    expert: str | None = typer.Option(
        None,
        "--expert",
        parser=_registered(_experts, "expert"),
        metavar="EXPERT",
        help="The demonstrator (default: the environment's scripted expert; `sac` needs --policy).",
    ),
    policy: Path | None = typer.Option(None, "--policy", help="A policy file for experts that need one (SB3 SAC zip)."),
    valid_fraction: float | None = typer.Option(
        None, "--valid-fraction", min=0.0, max=0.9, help="Share of episodes held out for validation (default 0.1)."
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
    out: Path = typer.Option(Path("demos.h5"), "--out", "-o", help="Demos artifact to write."),
    plot: Path | None = typer.Option(
        None, "--plot", help="Also draw a sample of demos on the scene to this PNG (Fetch: top and side views)."
    ),
    video: Path | None = typer.Option(None, "--video", help="Write GIFs of the first demos to this folder."),
    videos: int = typer.Option(3, "--videos", min=1, max=100, help="How many demo GIFs with --video."),
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
    from cdrb_cli.stages.collect import collect as run_collect
    from cdrb_cli.stages.collect import collect_config, route_shares

    if video is not None:
        from cdrb_cli.envs.render import choose_gl_backend

        choose_gl_backend()  # before MuJoCo is imported
        _check_video_folder(video, out)
    _check_outputs(force, out=out, plot=plot)
    cores = os.cpu_count() or 1
    if workers is not None and workers > 2 * cores:
        raise BadInput(
            f"--workers {workers}: more than twice this machine's {cores} cores (each worker holds an environment "
            "and about 120 MB)",
            hint=f"use at most {2 * cores}, or leave --workers out (one per core)",
        )
    spec = _spec(env, maze_map)
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
    ui.log(
        f"{spec.id}: {s.episodes} episodes ({s.train_episodes} train / {s.valid_episodes} valid), "
        f"success {s.success_rate:.1%}, mean length {s.mean_length:.0f} steps (max {s.max_length}), "
        f"states inside obstacles: {s.states_in_walls}, {s.wall_time_s:.1f}s"
    )
    if s.routes:
        ui.log(f"routes: {route_shares(s.routes)}")
    if s.success_rate < 0.99:
        ui.warn(f"expert success {s.success_rate:.1%} is below 99%")
    if plot is not None:
        from cdrb_cli.envs.render import plot_demos

        plot_demos(demos, plot, seed=seed)
        ui.log(f"picture: {plot}")
    if video is not None:
        from cdrb_cli.envs.render import rollout_gifs

        shown = []
        for e in range(min(videos, demos.n_episodes)):
            states, _ = demos.episode(e)
            goal = demos.desired_goals[int(demos.episode_start[e])]
            shown.append((states, states, goal, bool(demos.episode_success[e])))
        rollout_gifs(spec, shown, video, label="demo", every=2)
        ui.log(f"demo GIFs: {video}/")
    ui.emit({"path": str(out), "summary": s.model_dump()} if as_json else out, as_json=as_json)


# ------------------------------------------------------------------------------------------------ minari
import_app = typer.Typer(help="Bring outside datasets in as cdrb artifacts.", no_args_is_help=True)
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
        0.1, "--valid-fraction", min=0.0, max=0.9, help="Share of episodes held out for validation."
    ),
    out: Path = typer.Option(Path("demos.h5"), "--out", "-o", help="Demos artifact to write."),
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

    _check_outputs(force, out=out)
    demos = run_import(dataset, out, env=env, valid_fraction=valid_fraction, seed=seed)
    s = demos.manifest.summary
    ui.log(
        f"{demos.manifest.env.id}: {s.episodes} episodes ({s.train_episodes} train / {s.valid_episodes} valid), "
        f"{s.steps} steps, success {s.success_rate:.1%}, states inside obstacles: {s.states_in_walls}"
    )
    ui.emit({"path": str(out), "summary": s.model_dump()} if as_json else out, as_json=as_json)


@app.command("export")
def export_cmd(
    demos: Path = typer.Argument(..., help="A demos artifact."),
    minari: str = typer.Option(
        ..., "--minari", help="Dataset name, [namespace/]name[-vN] (-v0 is added), e.g. cdrb/maze-tight-expert."
    ),
    root: Path | None = typer.Option(
        None, "--root", help="Datasets folder (default: MINARI_DATASETS_PATH, else ~/.minari/datasets)."
    ),
    force: bool = typer.Option(False, "--force", help="Replace a dataset of the same name."),
) -> None:
    """Export a [bold]demos[/bold] artifact as a Minari dataset that `minari.load_dataset(NAME)` opens.

    Observations are goal dicts (observation, achieved_goal, desired_goal), the reward is cdrb's success test (as
    a sparse reward) and infos["success"] has it per step; the env_spec is the gymnasium equivalent of the
    environment where one exists (PointMaze with this map, Fetch without walls). Prints the dataset's folder."""
    from cdrb_cli.stages.minari_io import dataset_id_for, export_minari

    art = _load(demos, "demos")
    folder = export_minari(art, minari, root=root, force=force)
    ui.log(f"{art.n_episodes} episodes written as Minari dataset {dataset_id_for(minari)}")
    ui.emit(folder)


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
    from cdrb_cli.artifacts import claim_output
    from cdrb_cli.experts.sac import train_sac

    spec = _spec(env, maze_map)
    with claim_output(out, force):
        train_sac(spec, steps, seed, out, her=her)
    ui.emit(out)


# ------------------------------------------------------------------------------------------------ cluster
@app.command()
def cluster(
    demos: Path = typer.Argument(..., help="Demos artifact from `cdrb collect`."),
    k: int | None = typer.Option(None, "--k", min=0, help="k-means clusters (default 1000); 0 keeps the full buffer."),
    features: str = typer.Option(
        "state",
        "--features",
        parser=_choice(_literal("ClusterConfig", "features"), "feature space"),
        metavar="state|state-action",
        help="state, or state-action (actions joined to states).",
    ),
    split: str = typer.Option(
        "train",
        "--split",
        parser=_choice(_literal("ClusterConfig", "split"), "split"),
        metavar="train|all",
        help="Episodes whose states form the buffer: train or all.",
    ),
    out: Path = typer.Option(Path("buffer.h5"), "--out", "-o", help="Buffer artifact to write."),
    plot: Path | None = typer.Option(None, "--plot", help="Also draw the buffer states on the scene to this PNG."),
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

    _check_outputs(force, [demos], out=out, plot=plot)
    d = _load(demos, "demos")
    config = ClusterConfig(features=features, split=split, seed=seed, **({"k": k} if k is not None else {}))
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
SetOpt = typer.Option(
    [],
    "--set",
    metavar="KEY=VALUE",
    help="Set any config field, e.g. --set net.dim=32 --set method.schedule=log (repeatable; `cdrb config` lists "
    "them).",
)
ConfigOpt = typer.Option(None, "--config", help="A TOML or JSON file of settings (`cdrb config --format toml`).")
MethodOpt = typer.Option(
    None,
    "--method",
    parser=_registered(_methods, "method"),
    metavar="METHOD",
    help="The method to train (default: CDRB; `cdrb methods` lists them).",
)
NetOpt = typer.Option(
    None,
    "--net",
    parser=_choice(_nets, "network"),
    metavar="NET",
    help="The network: unet, transformer or mlp (default: the method's).",
)
PresetOpt = typer.Option(
    None,
    "--preset",
    parser=_choice(_presets, "preset"),
    metavar="PRESET",
    help="quick (minutes on CPU, the default) or paper (the reference settings).",
)


@app.command()
def train(
    demos: Path = typer.Argument(..., help="Demos artifact from `cdrb collect`."),
    buffer: Path | None = typer.Option(
        None, "--buffer", help="Buffer artifact (for methods that diffuse through one)."
    ),
    method: str | None = MethodOpt,
    net: str | None = NetOpt,
    preset: str | None = PresetOpt,
    steps: int | None = typer.Option(
        None, "--steps", help="Gradient steps (default: the preset's; `cdrb config train`)."
    ),
    sets: list[str] = SetOpt,
    config_file: Path | None = ConfigOpt,
    dry_run: bool = typer.Option(False, "--dry-run", help="Print the resolved config as JSON and exit."),
    device: str = DeviceOpt,
    out: Path = typer.Option(Path("model.h5"), "--out", "-o", help="Model artifact to write (also the checkpoint)."),
    resume: bool = typer.Option(False, "--resume", help="Continue the checkpoint in --out (same settings and inputs)."),
    snapshot_at: str | None = typer.Option(
        None,
        "--snapshot-at",
        metavar="STEPS",
        help="Also write the model after these steps (e.g. 1000,3000) to OUT.step<N>.h5, each exactly what "
        "`--steps N` writes: a learning curve from one run.",
    ),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Train a method on demonstration windows and write a [bold]model[/bold] artifact.

    CDRB learns R(tau_k, k) ~ tau_0 where tau_k replaces each state by a random buffer state within radius eps_k.
    Windows are HORIZON states every STRIDE env steps, padded with the demo's final (resting) state; start and goal
    are pinned. Every hyper-parameter is a config field: [cyan]--set KEY=VALUE[/cyan] or [cyan]--config FILE[/cyan]
    ([cyan]cdrb config train --method M[/cyan] lists them with their defaults); [cyan]--dry-run[/cyan] shows the
    resolved config. The model is checkpointed into --out: after a crash, [cyan]--resume[/cyan] continues to
    exactly the result of an uninterrupted run.
    Example: [cyan]cdrb train demos.h5 --buffer buffer.h5 --set horizon=128 --set net.dim=32[/cyan]"""
    from cdrb_cli.methods.config import buffer_info, resolve_train_config, user_settings
    from cdrb_cli.stages.train import train_or_resume
    from cdrb_cli.torch_utils import setup_torch

    _check_positive("--steps", steps)
    settings = user_settings(method, net, preset, steps, config_file, sets)
    d = _load(demos, "demos")
    b = _load(buffer, "buffer") if buffer is not None else None
    config = resolve_train_config(d.manifest.env, buffer_info(b), settings, seed=seed)
    from cdrb_cli.stages.train import TRAIN_BYTES_PER_PARAMETER, check_size

    n_params = check_size(d, b, config)
    if dry_run:
        ui.log(f"{n_params:,} parameters (about {n_params * TRAIN_BYTES_PER_PARAMETER / 2**20:,.0f} MiB to train)")
        ui.emit(config.model_dump(mode="json"), as_json=True)
        return
    snapshots = _ints(snapshot_at, "--snapshot-at", "step counts", "1000,3000") if snapshot_at else []
    model, done = train_or_resume(
        d, b, config, out, force=force, resume=resume, device=setup_torch(device), snapshots=snapshots
    )
    if done == "up to date":
        ui.log(f"{out} is up to date (same config and inputs): skipped; --force redoes it")
        from cdrb_cli.stages.train import snapshot_path

        missing = [s for s in snapshots if not snapshot_path(out, s).exists()]
        if missing:
            ui.log(f"warning: --snapshot-at {','.join(map(str, missing))}: not written (nothing was trained)")
    st = model.manifest.state
    ui.log(
        f"{config.method.name}: {st.step} steps, loss {st.loss:.4f}"
        + (f", valid {st.valid_loss:.4f}" if st.valid_loss is not None else "")
        + f", {st.parameters:,} parameters, {st.wall_time_s:.0f}s"
    )
    ui.emit({"path": str(out), "state": st.model_dump()} if as_json else out, as_json=as_json)


# ------------------------------------------------------------------------------------------------ config
@app.command("config")
def config_cmd(
    stage: str = typer.Argument(
        "train",
        parser=_choice(lambda: ["train", "plan", "eval", "collect"], "stage"),
        metavar="train|plan|eval|collect",
        help="Which config.",
    ),
    method: str | None = MethodOpt,
    net: str | None = NetOpt,
    preset: str | None = PresetOpt,
    controller: str | None = typer.Option(
        None, "--controller", parser=_registered(_controllers, "controller"), metavar="NAME", help="eval: a controller."
    ),
    fmt: str = typer.Option(
        "table",
        "--format",
        parser=_choice(lambda: ["table", "json", "toml"], "format"),
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
    template = config_template(stage, method=method, net=net, preset=preset, controller=controller)
    sys.stdout.write(render_template(template, fmt))


# ------------------------------------------------------------------------------------------------ plan
PartialOpt = typer.Option(
    False, "--allow-partial", help="Accept a model whose training did not finish (an interrupted checkpoint)."
)


def _trained_model(path: Path, allow_partial: bool):
    m = _load(path, "model")
    st = m.manifest.state
    if not st.finished and not allow_partial:
        raise BadInput(
            f"{path}: training stopped at step {st.step} of {m.manifest.config.steps} (an unfinished checkpoint)",
            hint="finish it with `cdrb train ... --resume`, or pass --allow-partial",
        )
    return m


@app.command()
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
    plot: Path | None = typer.Option(None, "--plot", help="Draw the scene and the plans to this PNG."),
    sets: list[str] = RunSetOpt,
    config_file: Path | None = RunConfigOpt,
    allow_partial: bool = PartialOpt,
    device: str = DeviceOpt,
    out: Path = typer.Option(Path("plans.h5"), "--out", "-o", help="Plans artifact to write."),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
    batch_size: int = typer.Option(256, "--batch-size", min=1, hidden=True, help="Plans sampled together."),
    sampler: str | None = _moved("--sampler"),
    sample_steps: int | None = _moved("--sample-steps"),
    raw_weights: bool = _moved("--raw-weights", False),
    show_steps: int | None = _moved("--show-steps", min=0),
    mask_buffer: bool = _moved("--mask-buffer", False),
    best_of: int | None = _moved("--best-of", min=1, max=64),
    route_k: int | None = _moved("--route-k", min=1),
    route_clearance: float | None = _moved("--route-clearance", min=0.0, max=1000.0),
    route_buffer: Path | None = _moved("--route-buffer"),
    guide_scale: float | None = _moved("--guide-scale", min=0.0, max=1e6),
) -> None:
    """Plan from start to goal and write a [bold]plans[/bold] artifact (start and goal held exactly).

    CDRB (the paper's sampling algorithm): start from random buffer states, then repeatedly restore and
    re-degrade with shrinking balls.
    Example: [cyan]cdrb plan model.h5 --start 0,0 --goal 6,6 -n 8 --plot plans.png --set keep_iterates=4[/cyan]

    Every other knob is a setting ([cyan]cdrb config plan[/cyan] lists them): the sampler and its steps, the raw
    weights, kept iterates, and how plans keep out of obstacles ([cyan]avoid.*[/cyan]). New obstacles, no
    retraining: [cyan]--scene closed.txt[/cyan] plans in the training map with walls added, avoiding them with
    the settings chosen for new obstacles (CDRB: masked buffer, a buffer route repaired from k = 8, best of 4);
    [cyan]--set avoid=plain[/cyan] plans as the model is. Also: [cyan]--batch-size N[/cyan] (plans sampled
    together, default 256)."""
    from cdrb_cli.artifacts import produce
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.seeding import STREAM_PLAN
    from cdrb_cli.stages.configure import plan_config, route_buffer_path
    from cdrb_cli.stages.plan import load_route_buffer, make_plans, scene_spec
    from cdrb_cli.torch_utils import setup_torch

    flags = [] if n is None else [(f"--num-plans {n}", "n", n)]
    moved = {
        "--sampler": sampler,
        "--sample-steps": sample_steps,
        "--raw-weights": raw_weights,
        "--show-steps": show_steps,
        "--mask-buffer": mask_buffer,
        "--best-of": best_of,
        "--route-k": route_k,
        "--route-clearance": route_clearance,
        "--route-buffer": route_buffer,
        "--guide-scale": guide_scale,
    }
    settings = _run_settings(config_file, sets, flags, moved)
    rb_path = route_buffer_path(settings)
    read = [model, *(p for p in (config_file, maze_map, rb_path) if p is not None)]
    _check_outputs(force, read, out=out, plot=plot)
    m = _trained_model(model, allow_partial)
    spec = scene_spec(m, maze_map)
    config = plan_config(m, settings, seed=seed, scene_file=maze_map)
    route_art = load_route_buffer(rb_path)
    family = family_of(spec)
    if pairs:
        if start or goal:
            raise BadInput("--pairs with --start/--goal", hint="give either explicit points or --pairs N")
        s_arr, g = family.reset_states(spec, family.draw_episodes(spec, pairs, seed, STREAM_PLAN))
        g_arr = family.goal_state(spec, g)
    else:
        if not start or not goal:
            raise BadInput("no start/goal given", hint=f"pass --start and --goal ({family.point_format}), or --pairs N")
        if len(goal) == 1 and len(start) > 1:
            goal = goal * len(start)
        if len(goal) != len(start):
            raise BadInput(f"{len(start)} --start but {len(goal)} --goal", hint="give one goal per start, or one")
        s_arr = np.array([family.parse_point(spec, t, "--start") for t in start])
        g_arr = np.array([family.parse_point(spec, t, "--goal") for t in goal])
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
            batch_size=batch_size,
            spec=spec,
            route_buffer=route_art,
        ),
        parents=[m] if route_art is None else [m, route_art],
        env=spec,
    )
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
    from cdrb_cli.stages.plan import disconnected_warning

    warning = disconnected_warning(spec, result.arrays["plans"], m.manifest.config.stride, config.avoid)
    if warning:
        ui.warn(warning)
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
            title=f"{result.manifest.method}: {sm.plans} plans, {sm.in_wall_fraction:.1%} states in obstacles",
            iterates=a.get("iterates"),
            iterate_steps=a.get("iterate_steps"),
        )
        ui.log(f"picture: {plot}")
    ui.emit({"path": str(out), "summary": sm.model_dump()} if as_json else out, as_json=as_json)


# ------------------------------------------------------------------------------------------------ eval
@app.command("eval")
def eval_cmd(
    model: Path = typer.Argument(..., help="Model artifact from `cdrb train`."),
    episodes: int | None = typer.Option(
        None, "--episodes", "-n", min=1, max=100_000, help="Episodes per evaluation seed (default 100)."
    ),
    seeds: str | None = typer.Option(
        None, "--seeds", help="Evaluation seeds, each drawing its own start/goal pairs (default 0,1,2,3,4)."
    ),
    stream: str | None = typer.Option(
        None,
        "--stream",
        parser=_choice(lambda: ["test", "tune"], "stream"),
        metavar="test|tune",
        help="Which start/goal pairs: 'tune' to choose settings on, 'test' (never used for choosing) for reported "
        "tables (default test).",
    ),
    protocol: str | None = typer.Option(
        None,
        "--protocol",
        metavar="NAME",
        help="The evaluation protocol (default: the environment's; `cdrb envs` lists them). 'official-code' "
        "evaluates as the official CDRB code; 'detour' (with --scene) keeps the pairs the new obstacles lengthen; "
        "'anywhere' starts anywhere.",
    ),
    replan: str | None = typer.Option(
        None,
        "--replan",
        metavar="never|every:N|deviation:D",
        help="Planners, closed loop: plan again from the current state every N env steps, or when the state is "
        "farther than D (metres, in the obstacle dimensions) from where the plan has it now (default: never, one "
        "plan per episode as in the paper). Repairs: --set replan.repair_k=K.",
    ),
    maze_map: Path | None = typer.Option(
        None,
        "--scene",
        "--maze-map",
        metavar="FILE",
        help="Evaluate among obstacles the data never saw, the model not retrained: for a maze, a map file (the "
        "training map with walls added); for Fetch, a TOML file of \\[\\[boxes]] (center, half) put down. Plans avoid "
        "them with the settings chosen for new obstacles (`--set avoid=plain`: as the model is).",
    ),
    sets: list[str] = RunSetOpt,
    config_file: Path | None = RunConfigOpt,
    video: Path | None = typer.Option(None, "--video", help="Write rollout GIFs of the first episodes to this folder."),
    device: str = DeviceOpt,
    out: Path = typer.Option(Path("eval.h5"), "--out", "-o", help="Eval artifact to write."),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
    videos: int = typer.Option(3, "--videos", min=1, hidden=True, help="How many rollout GIFs with --video."),
    keep_plans: bool = typer.Option(
        True, "--plans/--no-plans", hidden=True, help="Keep each episode's (first) plan in the eval artifact."
    ),
    replan_plot: Path | None = typer.Option(
        None, "--replan-plot", hidden=True, help="With --replan: the first episode's successive plans (PNG)."
    ),
    allow_partial: bool = typer.Option(False, "--allow-partial", hidden=True, help="Accept an unfinished model."),
    controller: str | None = _moved("--controller"),
    max_lag: float | None = _moved("--max-lag", min=0.0, show_default=False),
    repair_k: int | None = _moved("--repair-k"),
    repair_steps: int | None = _moved("--repair-steps"),
    mask_buffer: bool = _moved("--mask-buffer", False),
    best_of: int | None = _moved("--best-of", min=1, max=64),
    route_k: int | None = _moved("--route-k", min=1),
    route_clearance: float | None = _moved("--route-clearance", min=0.0, max=1000.0),
    route_buffer: Path | None = _moved("--route-buffer"),
    guide_scale: float | None = _moved("--guide-scale", min=0.0, max=1e6),
    sampler: str | None = _moved("--sampler"),
    sample_steps: int | None = _moved("--sample-steps"),
    raw_weights: bool = _moved("--raw-weights", False),
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
    from cdrb_cli.artifacts import produce
    from cdrb_cli.stages.configure import eval_config, route_buffer_path
    from cdrb_cli.stages.evaluate import evaluate
    from cdrb_cli.stages.report import failure_text
    from cdrb_cli.torch_utils import setup_torch

    flags = [
        (f"{flag} {value}", key, parse(value))
        for flag, key, value, parse in (
            ("--episodes", "episodes", episodes, int),
            ("--seeds", "seeds", seeds, lambda text: _int_list(text, "--seeds")),
            ("--stream", "stream", stream, str),
            ("--protocol", "protocol", protocol, str),
            ("--replan", "replan", replan, str),
        )
        if value is not None
    ]
    moved = {
        "--controller": controller,
        "--max-lag": max_lag,
        "--repair-k": repair_k,
        "--repair-steps": repair_steps,
        "--mask-buffer": mask_buffer,
        "--best-of": best_of,
        "--route-k": route_k,
        "--route-clearance": route_clearance,
        "--route-buffer": route_buffer,
        "--guide-scale": guide_scale,
        "--sampler": sampler,
        "--sample-steps": sample_steps,
        "--raw-weights": raw_weights,
    }
    settings = _run_settings(config_file, sets, flags, moved)
    if video is not None:
        _check_video_folder(video, out)
    route_buffer = route_buffer_path(settings)
    read = [model, *(p for p in (config_file, maze_map, route_buffer) if p is not None)]
    _check_outputs(force, read, out=out, replan_plot=replan_plot)
    m = _trained_model(model, allow_partial)
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.stages.plan import load_route_buffer, scene_spec

    scene = scene_spec(m, maze_map)
    config = eval_config(m, settings, seed=seed, scene_file=maze_map, scene=scene)
    if replan_plot is not None and config.replan.mode == "never":
        raise BadInput("--replan-plot draws the plans of a closed-loop episode", hint="add --replan every:N")
    stream, seed_list, episodes = config.stream, config.seeds, config.episodes
    eval_spec = family_of(m.manifest.env).protocol_spec(scene, config.protocol)
    route_art = load_route_buffer(route_buffer)
    n_videos = videos if video is not None else 0
    if config.avoid.label() != "plain":
        ui.log(f"avoiding obstacles: {config.avoid.label()}")
    started = time.time()
    ev = produce(
        out,
        "eval",
        force,
        config,
        lambda: evaluate(
            m,
            config,
            out,
            device=setup_torch(device),
            keep_plans=keep_plans,
            video_dir=video,
            videos=n_videos,
            replan_plot=replan_plot,
            spec=eval_spec,
            route_buffer=route_art,
        ),
        parents=[m] if route_art is None else [m, route_art],
        env=eval_spec,
    )
    s = ev.manifest.summary
    crossing = "" if s.plan_crossing_mean is None else f"; plans through obstacles {100 * s.plan_crossing_mean:.1f}%"
    if s.masked is not None and s.masked.warning():
        ui.warn(s.masked.warning())
    ui.log(
        f"{s.method} on {ui.plain(ev.manifest.env.id)} ({stream} pairs): success {100 * s.success_mean:.1f} ± "
        f"{100 * s.success_std:.1f}% over {len(seed_list)} seeds x {episodes} episodes; "
        + (
            f"planned states in obstacles {100 * s.in_wall_mean:.2f}%{crossing}; "
            if s.in_wall_mean is not None
            else "closed loop (no plans); "
        )
        + f"executed collisions {100 * s.executed_collision_mean:.1f}%; "
        + (f"plan {1000 * s.plan_seconds_mean:.1f} ms" if s.in_wall_mean is not None else "")
        + (
            f" ({s.replans_mean:.1f} re-plans, {1000 * s.planning_seconds_mean:.0f} ms planning per episode: "
            f"{config.replan.label()})"
            if config.replan.mode != "never" and s.replans_mean is not None
            else ""
        )
        + (f"{1000 * s.plan_seconds_mean:.2f} ms per episode step" if s.in_wall_mean is None else "")
        + (f"; failed episodes by cause: {failure_text(s.failures)}" if s.failures and any(s.failures.values()) else "")
    )
    if video is not None:
        _report_gifs(video, started, out)
    if replan_plot is not None and replan_plot.exists():
        ui.log(f"picture: {replan_plot}")
    ui.emit({"path": str(out), "summary": s.model_dump()} if as_json else out, as_json=as_json)


# ------------------------------------------------------------------------------------------------ report
@app.command()
def report(
    evals: list[Path] = typer.Argument(
        ..., help="Eval artifacts (any number; rows = environments, columns = methods)."
    ),
    fmt: str = typer.Option(
        "table",
        "--format",
        parser=_choice(lambda: ["table", "markdown", "summary", "csv", "json"], "format"),
        metavar="table|markdown|summary|csv|json",
        help="table, markdown, summary (markdown, a line per environment: the straight line's success as the floor, "
        "each method's success and weighted success, marked where it does not beat the floor), csv or json.",
    ),
    paper: bool = typer.Option(False, "--paper", help="Add the paper's Table 1 figures under ours."),
    paper_figures: Path | None = typer.Option(
        None, "--paper-figures", metavar="FILE", help="With --paper: read the figures from FILE (TOML) instead."
    ),
    per_seed: bool = typer.Option(
        False, "--per-seed", help="One row per eval file and evaluation seed instead of one per environment x method."
    ),
    docs: Path | None = typer.Option(
        None,
        "--docs",
        metavar="FILE",
        help="Write the markdown report into FILE between <!-- BLOCK:begin --> and <!-- BLOCK:end --> (with --block).",
    ),
    block: str | None = typer.Option(None, "--block", metavar="NAME", help="The marked block of --docs to replace."),
    out: Path | None = typer.Option(None, "--out", "-o", help="Write the report to this file (else stdout)."),
    plot: Path | None = typer.Option(None, "--plot", help="Bar chart of success and planned-in-obstacle rates (PNG)."),
    plans_plot: Path | None = typer.Option(None, "--plans-plot", help="Every method's plans for the same pairs (PNG)."),
    force: bool = ForceOpt,
) -> None:
    """Compare eval artifacts in a Table-1-style report (success mean ± std over seeds, plus planned states in
    obstacles, executed collisions, path length and planning time), with optional pictures.

    Evals of one environment must share a protocol (seeds, episodes, controller); mixing is an error."""
    from cdrb_cli.stages import report as rep

    if (docs is None) != (block is None):
        raise BadInput(
            "--docs and --block go together", hint="e.g. --docs docs/benchmarks.md --block table1-maze-tight"
        )
    if docs is not None and fmt not in ("markdown", "table", "summary"):
        raise BadInput(f"--docs writes markdown, not --format {fmt}", hint="drop --format or write it with --out")
    if paper_figures is not None and not paper:
        raise BadInput("--paper-figures goes with --paper", hint="add --paper, or drop --paper-figures")
    _check_outputs(force, evals, docs=docs, out=out, plot=plot, plans_plot=plans_plot)
    if out is not None:
        from cdrb_cli.artifacts import check_output

        check_output(out, force, "--out", evals)
    figures = rep.paper_figures(paper_figures) if paper else False
    arts = [_load(p, "eval") for p in evals]
    # per-seed rows list every file as it is; the grouped rows (and their bar chart) need one protocol per env
    rows = rep.collect_rows(arts) if not per_seed or plot is not None else []
    if per_seed:
        if fmt == "summary":
            raise BadInput("--per-seed has no summary format", hint="use --format table, markdown, csv or json")
        text = rep.render_seed_rows(rep.seed_rows(arts), fmt)
    elif fmt == "summary":
        text = rep.render_summary(rows, paper=figures)
    else:
        text = rep.render(rows, "markdown" if docs is not None else fmt, paper=figures)
    # every check before the first file is written: a bad --docs block or evals without plans leave nothing behind
    if plans_plot is not None:
        rep.with_plans(arts)
    if docs is not None:
        rep.check_docs_block(docs, block, text, evals)
    if plot is not None:
        rep.plot_bars(rows, plot)
        ui.log(f"picture: {plot}")
    if plans_plot is not None:
        rep.plot_side_by_side(arts, plans_plot)
        ui.log(f"picture: {plans_plot}")
    if docs is not None:
        rep.write_docs_block(docs, block, text, evals)
    if out is not None:
        from cdrb_cli.artifacts import atomic_path, claim_output

        with claim_output(out, force, "--out", evals), atomic_path(out) as tmp:
            tmp.write_text(text)
        ui.emit(out)
    elif docs is not None:
        ui.emit(docs)
    else:
        sys.stdout.write(text)


# ------------------------------------------------------------------------------------------------ quickstart
@app.command()
def quickstart(
    out: Path = typer.Option(Path("runs/quickstart"), "--out", "-o", help="Folder for every artifact and picture."),
    env: str | None = typer.Option(None, "--env", help="Environment id (default: Maze Tight; `cdrb envs`)."),
    episodes: int = typer.Option(1000, "--episodes", min=2, help="Demonstrations to collect."),
    k: int | None = typer.Option(None, "--k", min=0, help="Buffer size after k-means (default 1000; 0 = full)."),
    methods: str | None = typer.Option(
        None, "--methods", help="Methods to train and compare, comma-separated (default: CDRB and Diffuser)."
    ),
    seeds: str = typer.Option(
        "5,6,7",
        "--seeds",
        help="Evaluation seeds of the test stream (default 5,6,7: pairs no setting was chosen on; Table 1 uses 0-4).",
    ),
    eval_episodes: int = typer.Option(50, "--eval-episodes", min=1, help="Episodes per evaluation seed."),
    steps: int | None = typer.Option(None, "--steps", help="Training steps per method (quick preset: 3000)."),
    videos: int = typer.Option(0, "--videos", min=0, help="Rollout GIFs per method (0: none)."),
    device: str = DeviceOpt,
    seed: int = SeedOpt,
) -> None:
    """Run the whole pipeline on Maze Tight: collect -> cluster -> train CDRB and Diffuser (quick) -> eval ->
    report. 5-9 minutes on 2 CPU cores. Re-running skips every stage that is up to date; an interrupted run
    resumes where it stopped. Prints the results table and the paths of the pictures."""
    if videos:
        from cdrb_cli.envs.render import choose_gl_backend

        choose_gl_backend()
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.stages.quickstart import DEFAULT_ENV, DEFAULT_METHODS, check_methods
    from cdrb_cli.stages.quickstart import quickstart as run_quickstart
    from cdrb_cli.torch_utils import setup_torch

    method_list = tuple(m.strip() for m in methods.split(",") if m.strip()) if methods else DEFAULT_METHODS
    check_methods(method_list, "--methods")
    make_spec(env or DEFAULT_ENV)
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out}: exists and is not a folder", hint="pass a folder path")
    _check_positive("--steps", steps)
    res = run_quickstart(
        out,
        env=env or DEFAULT_ENV,
        episodes=episodes,
        k=k,
        methods=method_list,
        seeds=tuple(_int_list(seeds, "--seeds")),
        eval_episodes=eval_episodes,
        steps=steps,
        seed=seed,
        device=setup_torch(device),
        videos=videos,
    )
    ui.log(f"done in {res.seconds / 60:.1f} min; artifacts in {res.folder}/")
    sys.stdout.write(res.report)
    sys.stdout.write("\n" + "\n".join(str(p) for p in res.pictures) + "\n")


# ------------------------------------------------------------------------------------------------ select
@app.command()
def select(
    grid_file: Path = typer.Argument(..., help="A tuning grid (TOML) whose evals `cdrb grid` has run."),
    out: Path = typer.Option(
        ..., "--out", "-o", metavar="FILE", help="The settings file to write (TOML), for test grids to include."
    ),
    table: Path | None = typer.Option(
        None,
        "--table",
        metavar="FILE",
        help="Also write every candidate's scores: CSV (.csv) or a markdown table (other names).",
    ),
    curves: Path | None = typer.Option(
        None,
        "--curves",
        metavar="FILE",
        help="Also write the learning curves as CSV: one row per candidate, training length and training seed "
        "(success, weighted success, success without collision, plans through an obstacle, collisions; per cent).",
    ),
    docs: Path | None = typer.Option(
        None,
        "--docs",
        metavar="FILE",
        help="Also write what was chosen (one line per environment, a column per method: tuning success ± std, "
        "training length, plans through an obstacle) into FILE between <!-- BLOCK:begin --> and "
        "<!-- BLOCK:end --> (with --block).",
    ),
    block: str | None = typer.Option(None, "--block", metavar="NAME", help="The marked block of --docs to replace."),
    overrides: list[str] = GridSetOpt,
    includes: list[Path] = GridIncludeOpt,
    force: bool = ForceOpt,
) -> None:
    """Choose each method's settings on the tuning stream from a tuning grid's evals, and write them as a settings
    file that test grids `include`.

    Candidates are the grid's variants (training settings, or eval-only knobs on one model) at each training length
    of its learning curves (`snapshot_at`). The rule, per environment x method: highest tuning success, then fewest
    plans through an obstacle, then fewest executed collisions, then the grid's variant order, then fewest training
    steps. Prints the path of the settings file."""
    from cdrb_cli.stages.select import select as run_select

    if (docs is None) != (block is None):
        raise BadInput("--docs and --block go together", hint="e.g. --docs README.md --block tuning-fetch")
    options = dict(force=force, table=table, curves=curves, overrides=overrides, includes=includes)
    ui.emit(run_select(grid_file, out, docs=docs, block=block, **options))


# ------------------------------------------------------------------------------------------------ grid
@app.command()
def grid(
    grid_file: Path = typer.Argument(..., help="Grid file (TOML): envs x methods x seeds (x variants)."),
    backend: str = typer.Option(
        "auto",
        "--backend",
        parser=_choice(lambda: ["auto", "ray", "pool"], "backend"),
        help='Where tasks run: ray (needs `pip install "cdrb-cli\\[ray]"`), pool (local processes), auto (Ray '
        "when installed).",
    ),
    workers: int | None = typer.Option(
        None, "--workers", "-j", min=1, help="Local pool: parallel tasks; local Ray: CPUs it may use (default: all)."
    ),
    address: str | None = typer.Option(
        None, "--address", help="A running Ray cluster, e.g. ray://head:10001 (default: start Ray on this machine)."
    ),
    retries: int = typer.Option(1, "--retries", min=0, help="Re-runs of a failed task before it is reported."),
    dry_run: bool = typer.Option(
        False, "--dry-run", help="Print the tasks' commands (one per line; with --json a list of tasks) and stop."
    ),
    overrides: list[str] = GridSetOpt,
    includes: list[Path] = GridIncludeOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Run a grid of experiments: collect -> cluster -> train -> eval -> report for every environment, method,
    seed and variant of GRID_FILE, in parallel on Ray or a local pool.

    Tasks whose artifacts are up to date are not run again, so a grid stopped half-way continues where it
    stopped; a failed task is retried (a training resumes from its checkpoint) and then reported, while the
    others go on. Prints the path of the summary (OUT/grid.json). Format and examples: docs/cli.md.
    """
    from cdrb_cli.stages.grid import grid as run_grid_file

    res = run_grid_file(
        grid_file,
        backend=backend,
        workers=workers,
        address=address,
        retries=retries,
        dry_run=dry_run,
        overrides=overrides,
        includes=includes,
    )
    if dry_run:
        import shlex

        if as_json:  # one object per task: what it is, its command, what it writes, the tasks it waits for
            rows = [
                {
                    "id": t.id,
                    "kind": t.kind,
                    "argv": t.argv,
                    "outputs": [str(p) for p in t.outputs],
                    "deps": t.deps,
                }
                for t in res
            ]
            ui.emit(rows, as_json=True)
            return
        for task in res:
            sys.stdout.write("cdrb " + shlex.join(task.argv) + "\n")
        return
    ui.log(
        f"grid finished in {res.seconds / 60:.1f} min: {res.count('done')} run, {res.count('up to date')} up to date"
    )
    if as_json:
        import json

        ui.emit(json.loads(res.summary.read_text()), as_json=True)
    else:
        ui.emit(res.summary)


# ------------------------------------------------------------------------------------------------ entry point
def _one_line(text: str) -> str:
    return " ".join(str(text).split()).replace("Value error, ", "")


def _error(text: str) -> None:
    sys.stderr.write(f"error: {ui.plain(_one_line(text))}\n")
    sys.stderr.flush()


def _moved_flag(exc) -> str:
    """For an unknown option of `cdrb train` that names a config field: how to set it now."""
    name = getattr(exc, "option_name", "") or ""
    if not name.startswith("--") or exc.ctx is None or exc.ctx.command.name != "train":
        return ""
    key = name[2:].replace("-", "_")
    from cdrb_cli.stages.show_config import settable_keys

    for full in settable_keys():
        if full == key or full.endswith("." + key):
            return f"; it is a config field now: --set {full}=VALUE"
    return ""


def reflow(doc: str | None) -> str | None:
    """A docstring as help text: each paragraph one line (the terminal wraps it at its own width, 80 or 200
    columns alike), bullet and numbered items kept on lines of their own, blank lines between paragraphs kept."""
    import inspect as _inspect
    import re

    if not doc:
        return doc
    paragraphs = []
    for para in _inspect.cleandoc(doc).split("\n\n"):
        lines: list[str] = []
        for line in (ln.strip() for ln in para.splitlines()):
            if lines and not re.match(r"^([*\-]|\d+[.)])\s", line):
                lines[-1] += " " + line
            else:
                lines.append(line)
        paragraphs.append("\n".join(lines))
    return "\n\n".join(paragraphs)


def _reflow_commands(typer_app: typer.Typer) -> None:
    """Every command's help from its docstring, reflowed (hard-wrapped docstrings render with ragged breaks)."""
    for info in typer_app.registered_commands:
        info.help = reflow(info.help or (info.callback.__doc__ if info.callback else None))
    for group in typer_app.registered_groups:
        _reflow_commands(group.typer_instance)


_reflow_commands(app)


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 failed run, 2 bad input)."""
    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args
    command = typer.main.get_command(app)
    restore_signals = interrupts.install()
    try:
        with provenance.running([PROG, *args]) if argv is not None else contextlib.nullcontext():
            code = command.main(args=args, prog_name=PROG, standalone_mode=False)
        if code == EXIT_INTERRUPTED:  # typer turns KeyboardInterrupt into a returned exit code 130
            _interrupted(args)
        return code if isinstance(code, int) else 0
    except typer.Exit as exc:
        return exc.exit_code
    except click_exc.UsageError as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":  # the help text was the answer
            if exc.ctx is not None:
                sys.stdout.write(exc.ctx.get_help() + "\n")
            return EXIT_BAD_INPUT
        where = exc.ctx.command_path if exc.ctx else PROG
        _error(f"{exc.format_message()}{_moved_flag(exc)} (see `{where} --help`)")
        return EXIT_BAD_INPUT
    except click_exc.ClickException as exc:
        _error(exc.format_message())
        return EXIT_BAD_INPUT
    except typer.Abort:
        _error("aborted")
        return EXIT_INTERRUPTED
    except CdrbError as exc:
        if debug:
            raise
        _error(exc.line())
        return exc.exit_code
    except KeyboardInterrupt:
        _interrupted(args)
        return EXIT_INTERRUPTED
    except Exception as exc:  # a bug or an environment failure: still one line unless --debug
        if debug:
            raise
        _error(f"{type(exc).__name__}: {_one_line(str(exc))[:300]} (re-run with `cdrb --debug ...` for a traceback)")
        return EXIT_FAILED
    finally:
        restore_signals()


def _interrupted(args: list[str]) -> None:
    _error(f"interrupted; artifacts already written are intact{_how_to_continue(args)}")


def _how_to_continue(args: list[str]) -> str:
    """What to run after an interrupt: ``--resume`` only where a training left a checkpoint to continue."""
    if "quickstart" in args:
        return "; run the same command again to continue where it stopped"
    if "train" not in args:
        return ""
    out = Path("model.h5")
    for i, a in enumerate(args):
        if a in ("--out", "-o") and i + 1 < len(args):
            out = Path(args[i + 1])
        elif a.startswith("--out="):
            out = Path(a.split("=", 1)[1])
    from cdrb_cli.artifacts import unfinished_model

    if unfinished_model(out):
        return "; continue the training with --resume"
    return f"; no checkpoint of {out} was written yet: run the same command again to start over"


if __name__ == "__main__":
    sys.exit(main())
