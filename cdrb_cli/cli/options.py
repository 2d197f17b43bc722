"""Options more than one command declares, each once: scenes and maps, the settings of plan and eval (and the
flags they replaced), and the training choices."""

from __future__ import annotations

import functools
import inspect
import typing
from collections.abc import Callable
from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import choice, method_registry, net_names, parse_seeds, preset_names, registered

# ------------------------------------------------------------------------------------------------ envs, methods
EnvArg = typer.Argument(None, help="Environment id (see `cdrb envs`); omit it with --maze-map.")
MapOpt = typer.Option(None, "--maze-map", help="A maze map text file: rows of # wall, . free, S start, G goal, C both.")


#: the names of the scene option of plan and eval (:data:`SceneMapOpt`, ``evaluate.SceneOpt``), the first the one
#: their help shows
SCENE_FLAGS = ("--scene", "--maze-map")


def typed_flag(names: tuple[str, ...]) -> str:
    """Which of an option's ``names`` the command line used (its last use, the one that counts), so that an error
    names the flag as the user typed it; the first name when none of them is there."""
    from cdrb_cli.provenance import command_line

    typed = [a.split("=", 1)[0] for a in command_line()[1:]]
    used = [a for a in typed if a in names]
    return used[-1] if used else names[0]


SceneMapOpt = typer.Option(
    None,
    *SCENE_FLAGS,
    metavar="FILE",
    help="Plan among obstacles the data never saw, the model not retrained: for a maze, a map file (the training "
    "map with walls added, same size and cell size); for Fetch, a TOML file of \\[\\[boxes]] (center, half) put down. "
    "Plans then avoid them with the settings chosen for new obstacles (`--set avoid=plain`: as the model is).",
)

#: flags of plan and eval that now live in the configs: flag -> (config key, its type, the value a bare flag sets,
#: typer's bounds). They keep working, hidden from --help, each with a one-line note naming the key
#: (:func:`moved_flags` adds them to a command).
MOVED_FLAGS: dict[str, tuple[str, type, object, dict]] = {
    "--mask-buffer": ("avoid.mask_buffer", bool, True, {}),
    "--best-of": ("avoid.best_of", int, None, {"min": 1, "max": 64}),
    "--guide-scale": ("avoid.guide_scale", float, None, {"min": 0.0, "max": 1e6}),
    "--route-k": ("avoid.route_k", int, None, {"min": 1}),
    "--route-clearance": ("avoid.route_clearance", float, None, {"min": 0.0, "max": 1000.0}),
    "--route-buffer": ("avoid.route_buffer", Path, None, {}),
    "--sampler": ("sampler", str, None, {}),
    "--sample-steps": ("sample_steps", int, None, {}),
    "--raw-weights": ("use_ema", bool, False, {}),
    "--show-steps": ("keep_iterates", int, None, {"min": 0}),
    "--controller": ("controller.name", str, None, {}),
    "--max-lag": ("controller.max_lag", float, None, {"min": 0.0}),
    "--repair-k": ("replan.repair_k", int, None, {}),
    "--repair-steps": ("replan.repair_steps", int, None, {}),
}


#: the moved flags each command still takes
AVOID_MOVED = ("--mask-buffer", "--best-of", "--route-k", "--route-clearance", "--route-buffer", "--guide-scale")
PLAN_MOVED = ("--sampler", "--sample-steps", "--raw-weights", "--show-steps", *AVOID_MOVED)
EVAL_MOVED = ("--controller", "--max-lag", "--repair-k", "--repair-steps", *AVOID_MOVED, "--sampler", "--sample-steps",
              "--raw-weights")  # fmt: skip


def moved_name(flag: str) -> str:
    """The parameter a moved flag fills (its own name, as when it was a declared option: grid memo keys use it)."""
    return flag[2:].replace("-", "_")


def moved_flags(*flags: str) -> Callable:
    """A command decorator: the hidden options ``flags`` (of :data:`MOVED_FLAGS`) join the command's signature, and
    the command receives what was given of them as ``moved`` (flag -> value; None or False: not given)."""

    def decorate(fn: Callable) -> Callable:
        sig = inspect.signature(fn)
        extra = []
        for flag in flags:
            key, kind, _, bounds = MOVED_FLAGS[flag]
            option = typer.Option(
                False if kind is bool else None, flag, hidden=True, help=f"Moved: --set {key}=VALUE.", **bounds
            )
            annotation = bool if kind is bool else typing.Optional[kind]  # noqa: UP045  (typer reads Optional)
            extra.append(inspect.Parameter(moved_name(flag), inspect.Parameter.KEYWORD_ONLY, default=option,
                                           annotation=annotation))  # fmt: skip
        kept = [p for p in sig.parameters.values() if p.name != "moved"]
        hints = typing.get_type_hints(fn)

        @functools.wraps(fn)
        def command(**kwargs):
            moved = {flag: kwargs.pop(moved_name(flag)) for flag in flags}
            return fn(**kwargs, moved=moved)

        params = [p.replace(annotation=hints.get(p.name, p.annotation)) for p in kept] + extra
        command.__signature__ = sig.replace(parameters=params)
        command.__annotations__ = {p.name: p.annotation for p in params}  # resolved types, for typer and the grid
        return command

    return decorate


RunSetOpt = typer.Option(
    [],
    "--set",
    metavar="KEY=VALUE",
    help="Set any config field, e.g. --set avoid.best_of=8 --set controller.look_ahead=2 (repeatable; `cdrb config "
    "plan|eval` lists them with their defaults).",
)
RunConfigOpt = typer.Option(
    None,
    "--config",
    help="A TOML or JSON file of settings (`cdrb config plan|eval --format toml` writes a template), or a file "
    "`cdrb select` wrote (experiments/tuned/*.toml): the settings it chose for the model's environment and method.",
)


def run_settings(config_file: Path | None, sets: list[str], flags: list[tuple[str, str, object]], moved: dict):
    """The settings of a plan or an eval in priority order: the ``--config`` file, the flags, then ``--set``
    (a field given both by a flag and by ``--set`` is refused, in any spelling). ``flags``: (source text, key,
    value) of the everyday flags given; ``moved``: moved flag -> value given (None: not given), each noted once."""
    from cdrb_cli.settings import Setting, parse_set, read_config_file
    from cdrb_cli.stages.configure import each_field_once, given_once_anyhow

    items = read_config_file(config_file) if config_file is not None else []
    given = [Setting(tuple(key.split(".")), value, source) for source, key, value in flags]
    given += moved_settings(moved)
    sets_ = parse_set(sets)
    each_field_once(items)  # a file has no order to let one key win; a repeated --set keeps its last value
    given_once_anyhow(given, sets_)
    return items + given + sets_


def moved_settings(moved: dict, warn: bool = True) -> list:
    """The settings of the moved flags given (flag -> value; None or False: not given), each noted once as
    deprecated when ``warn``."""
    from cdrb_cli.settings import Setting

    out = []
    for flag, value in moved.items():
        if value is None or value is False:
            continue
        key, _, fixed, _ = MOVED_FLAGS[flag]
        value = fixed if fixed is not None else value
        value = str(value) if isinstance(value, Path) else value
        if flag == "--max-lag" and value == 0:
            value = None  # 0 meant: follow the plan on the environment's clock
        shown = "null" if value is None else str(value).lower() if isinstance(value, bool) else value
        if warn:
            ui.warn(f"{flag} is deprecated: write --set {key}={shown} (or put it in a --config file)")
        out.append(Setting(tuple(key.split(".")), value, flag if isinstance(value, bool) else f"{flag} {value}"))
    return out


#: the settings `cdrb eval` keeps an everyday flag for
EVERYDAY = ("episodes", "seeds", "stream", "protocol", "replan")


def everyday_flags(values: dict) -> list[tuple[str, str, object]]:
    """The everyday flags given, as (how the user typed it, settings key, value) for :func:`run_settings`."""
    parse = {"episodes": int, "seeds": lambda text: parse_seeds(text, "--seeds")}
    return [(f"--{key} {value}", key, parse.get(key, str)(value)) for key, value in values.items() if value is not None]


def env_spec(env: str | None, maze_map: Path | None):
    from cdrb_cli.envs.registry import make_spec

    return make_spec(env, maze_map)


# ------------------------------------------------------------------------------------------------ train
SetOpt = typer.Option(
    [],
    "--set",
    metavar="KEY=VALUE",
    help="Set any config field, e.g. --set net.dim=32 --set method.schedule=log (repeatable; `cdrb config` lists "
    "them).",
)
ConfigOpt = typer.Option(
    None,
    "--config",
    help="A TOML or JSON file of settings (`cdrb config --format toml`), or a file `cdrb select` wrote "
    "(experiments/tuned/*.toml): what it chose for the demos' environment and the method, recorded in the model so "
    "that its plans and evals start from the eval settings chosen with it.",
)
MethodOpt = typer.Option(
    None,
    "--method",
    parser=registered(method_registry, "method"),
    metavar="METHOD",
    help="The method to train (default: CDRB; `cdrb methods` lists them).",
)
NetOpt = typer.Option(
    None,
    "--net",
    parser=choice(net_names, "network"),
    metavar="NET",
    help="The network: unet, transformer, mlp, sieve or a plugin's (default: the method's; `cdrb methods` lists "
    "the networks of each method).",
)
PresetOpt = typer.Option(
    None,
    "--preset",
    parser=choice(preset_names, "preset"),
    metavar="PRESET",
    help="quick (minutes on CPU, the default) or paper (the reference settings).",
)
