"""The `cdrb` commands a grid composes, as the grid reads them: for each option, its parameter, whether it takes a
value, the type of that value, whether it names a file the command reads, whether it changes what the command
makes or measures (``--out``, ``--device``, ``--force`` do not), and which setting it fills where it is one.

The command line describes its own commands and hands the description over (:func:`install`, done by
:mod:`cdrb_cli.cli` when it is imported); the grid reads only this data, never the command line's code, so the
grid sits below the command line that runs it and a new option needs no entry here.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from cdrb_cli.errors import RunFailed


@dataclass(frozen=True)
class OptionInfo:
    """One option of a command (every spelling of it maps to the same record)."""

    param: str  #: the parameter's name (``maze_map`` for ``--maze-map``)
    takes_value: bool  #: False for a flag
    flag_value: bool = True  #: what a flag sets: True, or False for its ``--no-`` form
    kind: type | None = None  #: the value's type (int, float, str, Path), where the command declares one
    reads_file: bool = False  #: the value names a file the command reads
    keyed: bool = True  #: it changes what the command makes or measures
    #: for an option that fills a setting (``--max-lag`` is ``controller.max_lag``): its value as typed (the text,
    #: or the flag's value) -> (the settings key, the value), as the command itself reads it; None for the others
    to_setting: Callable[[object], tuple[str, object]] | None = field(default=None, compare=False)
    #: the value as typed -> why the command refuses it (its range or choices), or None where it takes it
    check: Callable[[str], str | None] | None = field(default=None, compare=False)


#: command name -> option string -> its record
Catalogue = dict[str, dict[str, OptionInfo]]

_provider: Callable[[], Catalogue] | None = None
_catalogue: Catalogue | None = None


def install(provider: Callable[[], Catalogue]) -> None:
    """Hand over how to describe the commands (called once, when the description is first needed)."""
    global _provider, _catalogue
    _provider, _catalogue = provider, None


def options(command: str) -> dict[str, OptionInfo]:
    """``command``'s options by option string."""
    global _catalogue
    if _catalogue is None:
        if _provider is None:
            raise RunFailed(
                "the grid composes cdrb commands, and no description of them is installed",
                hint="import cdrb_cli.cli first (it installs the description of its commands)",
            )
        _catalogue = _provider()
    if command not in _catalogue:
        raise RunFailed(f"no cdrb command {command!r} is described", hint="a grid runs collect, cluster, train, eval")
    return _catalogue[command]


def keyed_params(command: str) -> set[str]:
    """The parameters of ``command`` that change what it makes or measures (not where it writes, on what hardware,
    how it reports, or what more it keeps)."""
    return {info.param for info in options(command).values() if info.keyed}


def _file_spans(flags: list[str], command: str):
    """(index, inline) for each value in ``flags`` that names a file the command reads: ``inline`` for
    ``--flag=FILE`` (the value after ``=`` at ``index``), else the value is the token at ``index``."""
    table = options(command)
    for i, token in enumerate(flags):
        name, eq, _ = token.partition("=")
        info = table.get(name)
        if info is None or not info.reads_file:
            continue
        if eq and name.startswith("--"):
            yield i, True
        elif not eq and i + 1 < len(flags):
            yield i + 1, False


def input_files(flags: list[str], command: str) -> list[Path]:
    """The files that ``command``'s options in ``flags`` name for it to read."""
    return [Path(flags[i].partition("=")[2] if inline else flags[i]) for i, inline in _file_spans(flags, command)]


def map_input_files(flags: list[str], command: str, change: Callable[[str], str]) -> list[str]:
    """``flags`` with every file value of an option that reads a file replaced by ``change(value)``."""
    out = list(flags)
    for i, inline in _file_spans(flags, command):
        if inline:
            name, _, value = out[i].partition("=")
            out[i] = f"{name}={change(value)}"
        else:
            out[i] = change(out[i])
    return out
