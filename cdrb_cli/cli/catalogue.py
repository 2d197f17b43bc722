"""The description of the commands a grid composes (:mod:`cdrb_cli.orchestration.grid.commands`), read from the
commands themselves: their options, value types and which options read files or only say where and how a command
runs."""

from __future__ import annotations

import dataclasses
import typing
from collections.abc import Callable
from pathlib import Path

import typer

from cdrb_cli.orchestration.grid.commands import Catalogue, OptionInfo
from cdrb_cli.settings import Setting

#: the commands a grid runs or whose command lines it reads back (an eval's manifest records its command)
GRID_COMMANDS = ("collect", "cluster", "train", "eval", "plan", "report")
#: parameters that name a file the command writes
OUTPUTS = frozenset({"out", "plot", "plans_plot", "replan_plot", "video", "docs", "log_dir"})
#: parameters that say on what hardware a command runs, how it reports, whether it may overwrite or resume, and
#: what more it keeps: never part of what it makes or measures
BOOKKEEPING = frozenset({"device", "force", "resume", "as_json", "workers", "videos", "keep_plans", "dry_run"})


def _value_type(hint):
    """``int`` for ``int | None``: the type a value is parsed as."""
    return next((t for t in typing.get_args(hint) if t is not type(None)), hint)


def _one(settings: list[Setting]) -> tuple[str, object] | None:
    return (settings[0].key, settings[0].value) if settings else None


def setting_options() -> dict[str, dict[str, Callable[[object], tuple[str, object] | None]]]:
    """For each command, its options that fill a setting (parameter -> the value as typed -> (key, value)), read as
    the command reads them: the everyday flags of eval and train and the flags that moved into the configs. A grid
    then keys ``--max-lag 0.6`` and ``--set controller.max_lag=0.6`` as the one setting they are."""
    from cdrb_cli.cli.options import (
        EVAL_MOVED,
        EVERYDAY,
        MOVED_FLAGS,
        PLAN_MOVED,
        everyday_flags,
        moved_name,
        moved_settings,
    )
    from cdrb_cli.methods.config import user_settings

    def everyday(name: str):
        return lambda text: next(((k, v) for _, k, v in everyday_flags({name: text})), None)

    def moved(flag: str):
        kind = MOVED_FLAGS[flag][1]
        return lambda value: _one(moved_settings({flag: True if kind is bool else kind(value)}, warn=False))

    def train_flag(name: str):
        return lambda text: _one(user_settings(**{name: int(text) if name == "steps" else text}))

    def moved_table(flags) -> dict:
        return {moved_name(f): moved(f) for f in flags}

    return {
        "eval": {name: everyday(name) for name in EVERYDAY} | moved_table(EVAL_MOVED),
        "plan": moved_table(PLAN_MOVED),
        "train": {name: train_flag(name) for name in ("method", "net", "preset", "steps")},
    }


def _checker(command, param) -> Callable[[str], str | None]:
    """Why ``command`` refuses a value of ``param`` as typed (its type, range or choices: the option's own
    parser), or None."""

    def check(text: str) -> str | None:
        try:
            param.process_value(command.context_class(command), text)
        except Exception as exc:  # the parser's refusal, whatever its class
            return str(getattr(exc, "message", exc)).splitlines()[0]
        return None

    return check


def describe(app: typer.Typer) -> Catalogue:
    """The options of :data:`GRID_COMMANDS` in ``app``, as the grid reads them."""
    group = typer.main.get_command(app)
    catalogue: Catalogue = {}
    settings = setting_options()
    for name in GRID_COMMANDS:
        command = group.commands[name]
        hints = typing.get_type_hints(command.callback)
        table: dict[str, OptionInfo] = {}
        for p in command.params:
            if p.param_type_name != "option":
                continue
            kind = _value_type(hints.get(p.name))
            info = OptionInfo(
                param=p.name,
                takes_value=not getattr(p, "is_flag", False),
                kind=kind,
                reads_file=kind is Path and p.name not in OUTPUTS,
                keyed=p.name not in OUTPUTS | BOOKKEEPING,
                to_setting=settings.get(name, {}).get(p.name),
            )
            if info.takes_value and not info.reads_file and p.name not in OUTPUTS and not p.multiple:
                info = dataclasses.replace(info, check=_checker(command, p))
            table.update(dict.fromkeys(p.opts, info))
            table.update(dict.fromkeys(p.secondary_opts, dataclasses.replace(info, flag_value=False)))
        catalogue[name] = table
    return catalogue
