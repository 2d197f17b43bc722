"""Flag lists of a grid file checked against the commands they extend, and command lines read as what they ask
for (the option table of a command, its options by parameter name)."""

from __future__ import annotations

import functools
import json
from pathlib import Path

from cdrb_cli.errors import BadInput
from cdrb_cli.orchestration.grid.spec import GridSpec
from cdrb_cli.settings import clip

GRID_OPTIONS = {
    "collect": {"episodes", "seed", "out"},
    "cluster": {"out"},
    "train": {"method", "preset", "seed", "buffer", "snapshot_at", "out", "device"},
    "eval": {"seeds", "stream", "episodes", "out", "device"},
}
#: the settings (``--set KEY``) behind those options
GRID_SETTINGS = {"train": {"method", "method.name", "preset", "seed"}, "eval": {"episodes", "seeds", "stream", "seed"}}
#: files a grid's flags name that no grid writes: missing, every task that reads one would fail
INPUT_FILE_FLAGS = ("--maze-map", "--scene", "--policy", "--config", "--paper-figures")


def _check_flag_list(flags: list[str], command: str, where: str) -> None:
    """One settings or variant flag list for ``cdrb command``: every option exists, is not one the grid sets, has
    its value, and an integer or number value parses; a controller is a known one; a file it names exists. A
    mistake is one line when the grid is read, not a failure of every task hours later."""
    import typing

    from cdrb_cli.envs.registry import CONTROLLERS

    table = option_table(command)
    hints = typing.get_type_hints(_command(command).callback)
    for token, entry, inline in walk_options(flags, table):
        if entry is None:
            if token.startswith("-") and not _is_number(token):
                raise BadInput(f"{where}: {clip(repr(token), 60)} is not a `cdrb {command}` option",
                               hint=f"`cdrb {command} --help` lists them")  # fmt: skip
            raise BadInput(
                f"{where}: {clip(repr(token), 60)} is not the value of an option (the grid names the command's "
                "files itself)",
                hint='give each value right after its option, e.g. ["--steps", "4000"]',
            )
        pname, takes_value, _ = entry
        if pname in GRID_OPTIONS.get(command, ()):
            raise BadInput(
                f"{where}: {clip(repr(token), 60)}: the grid sets this `cdrb {command}` option itself",
                hint="use the grid's own key (seeds, eval_seeds, eval_stream, eval_episodes, demos, data_seed, preset, "
                "device, out, or a variant's stream)",
            )
        if not takes_value:
            continue
        key = (inline or "").partition("=")[0].strip().replace("-", "_")
        if pname == "sets" and key in GRID_SETTINGS.get(command, ()):
            raise BadInput(
                f"{where}: --set {clip(inline, 60)}: the grid sets {key} of `cdrb {command}` itself",
                hint="use the grid's own key (seeds, eval_seeds, eval_stream, eval_episodes, preset, or a variant's "
                "stream)",
            )
        if inline is None or ("=" not in token and inline.startswith("-") and inline in table):
            raise BadInput(f"{where}: {clip(repr(token), 60)} has no value",
                           hint=f"give it one: [{json.dumps(token)}, VALUE]")  # fmt: skip
        kind = hints.get(pname)
        base = next((t for t in typing.get_args(kind) if t is not type(None)), kind)
        if base in (int, float):
            try:
                base(inline)
            except ValueError:
                what = "an integer" if base is int else "a number"
                raise BadInput(f"{where}: {token} {clip(repr(inline), 40)}: not {what}",
                               hint=f"`cdrb {command} --help` says what it takes") from None  # fmt: skip
        if pname == "controller":
            CONTROLLERS.get(inline, f"{where}: --controller")
        option = token.partition("=")[0]
        if option in INPUT_FILE_FLAGS and not Path(inline).exists():
            raise BadInput(f"{where}: {option} {clip(inline, 300)}: no such file", hint="fix the path (relative to the "
                           "file that names it)")  # fmt: skip


@functools.cache
def _command(command: str):
    import typer

    from cdrb_cli.cli import app

    return typer.main.get_command(app).commands[command]


def check_flags(spec: GridSpec, path: Path) -> None:
    """Every flag list of the grid's settings and variants, by :func:`_check_flag_list`."""
    items = [("settings", i, s) for i, s in enumerate(spec.settings)] + [
        ("variants", i, v) for i, v in enumerate(spec.variants)
    ]
    for kind, i, item in items:
        for command in ("collect", "cluster", "train", "eval"):
            _check_flag_list(getattr(item, command, []), command, f"{path}: {kind}[{i}].{command}")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


@functools.cache
def option_table(command: str) -> dict[str, tuple[str, bool, bool]]:
    """``command``'s options, from the CLI itself: option string -> (parameter name, takes a value, the value a
    flag sets: True, or False for its ``--no-`` form)."""
    cmd = _command(command)
    table: dict[str, tuple[str, bool, bool]] = {}
    for p in cmd.params:
        if p.param_type_name != "option":
            continue
        flag = bool(getattr(p, "is_flag", False))
        for o in p.opts:
            table[o] = (p.name, not flag, True)
        for o in p.secondary_opts:
            table[o] = (p.name, False, False)
    return table


def walk_options(tokens: list[str], table: dict[str, tuple[str, bool, bool]]):
    """Walk a command line's tokens (the command's name left off) over its option table (:func:`option_table`):
    yield (token, entry, value) for each option, in the ``--x=y`` or the ``--x y`` form, with ``value`` its value
    (None where the line ends before it; an option without one yields None), and (token, None, token) for each token
    that is not an option."""
    i = 0
    while i < len(tokens):
        token = tokens[i]
        name, eq, inline = token.partition("=")
        entry = table.get(name if eq and name.startswith("--") else token)
        i += 1
        if entry is None:
            yield token, None, token
        elif not entry[1]:
            yield token, entry, None
        elif eq and name.startswith("--"):
            yield token, entry, inline
        else:
            yield token, entry, tokens[i] if i < len(tokens) else None
            i += 1


def parse_command(argv: list[str], file_key=str) -> tuple[list[str], dict[str, object], list[tuple[str, str]]]:
    """A command line as what it asks for, independent of how its flags are spelled: (its arguments, its options by
    parameter name with the last value winning as on the command line, its ``--set``s with each one overridden later
    by the same key dropped, sorted unless one key lies inside another). Every argument and option value goes
    through ``file_key`` (a file's stand-in: its sha256, the task that wrote it, its name)."""
    positional, options, sets = [], {}, []
    for token, entry, value in walk_options(argv[1:], option_table(argv[0])):
        if entry is None:
            positional.append(file_key(token))
            continue
        pname, takes_value, flag_value = entry
        value = ("" if value is None else value) if takes_value else flag_value
        if pname == "sets":
            k, _, v = str(value).partition("=")
            sets.append((k.strip(), v.strip()))
        else:
            options[pname] = file_key(value) if isinstance(value, str) else value
    # a later --set of the same key replaces all an earlier one set, whatever came between: the earlier is moot;
    # the order of the rest matters only where one key lies inside another (net= then net.dim=)
    sets = [kv for j, kv in enumerate(sets) if all(kv[0] != later[0] for later in sets[j + 1 :])]
    if not any(nested(a, b) for j, (a, _) in enumerate(sets) for b, _ in sets[j + 1 :]):
        sets.sort()
    return positional, options, sets


def nested(a: str, b: str) -> bool:
    """Whether one dotted settings key lies inside the other (``net`` and ``net.dim``)."""
    return a.startswith(b + ".") or b.startswith(a + ".")
