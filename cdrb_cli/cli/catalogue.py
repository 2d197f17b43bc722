"""The description of the commands a grid composes (:mod:`cdrb_cli.orchestration.grid.commands`), read from the
commands themselves: their options, value types and which options read files or only say where and how a command
runs."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import typer

from cdrb_cli.orchestration.grid.commands import Catalogue, OptionInfo

#: the commands a grid runs or whose command lines it reads back (an eval's manifest records its command)
GRID_COMMANDS = ("collect", "cluster", "train", "eval", "plan", "report")
#: parameters that name a file the command writes
OUTPUTS = frozenset({"out", "plot", "plans_plot", "replan_plot", "video", "docs"})
#: parameters that say on what hardware a command runs, how it reports, whether it may overwrite or resume, and
#: what more it keeps: never part of what it makes or measures
BOOKKEEPING = frozenset({"device", "force", "resume", "as_json", "workers", "videos", "keep_plans", "dry_run"})


def _value_type(hint):
    """``int`` for ``int | None``: the type a value is parsed as."""
    return next((t for t in typing.get_args(hint) if t is not type(None)), hint)


def describe(app: typer.Typer) -> Catalogue:
    """The options of :data:`GRID_COMMANDS` in ``app``, as the grid reads them."""
    group = typer.main.get_command(app)
    catalogue: Catalogue = {}
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
            )
            table.update(dict.fromkeys(p.opts, info))
            table.update(dict.fromkeys(p.secondary_opts, dataclasses.replace(info, flag_value=False)))
        catalogue[name] = table
    return catalogue
