"""Flag lists of a grid file checked against the commands they extend, and command lines read as what they ask
for (the option table of a command, its options by parameter name)."""

from __future__ import annotations

import json
from pathlib import Path

from cdrb_cli.errors import BadInput
from cdrb_cli.orchestration.grid.commands import OptionInfo, options
from cdrb_cli.orchestration.grid.spec import GridSpec
from cdrb_cli.settings import clip

#: the options the grid sets itself from its own keys (data_seed, demos, preset, seeds, eval_stream, eval_episodes,
#: device, out...), which settings and variants therefore may not pass: a repeated option's last value wins, so
#: ``train = ["--method", "diffuser"]`` would file a Diffuser under the grid's MLP name
GRID_OPTIONS = {
    "collect": {"episodes", "seed", "out"},
    "cluster": {"seed", "out"},
    "train": {"method", "preset", "seed", "buffer", "snapshot_at", "out", "device", "log_dir"},
    "eval": {"seeds", "stream", "episodes", "out", "device"},
}
#: the options by which the grid runs its tasks (it resumes a training whose model is there, replaces only its own
#: out-of-date artifacts, and lists its commands with its own ``--dry-run``): in a flag list they would make a task
#: overwrite a user's file, fail on a fresh start, or be recorded done without its artifact
RUN_OPTIONS = {"force", "resume", "own", "dry_run"}
#: the settings (``--set KEY``) behind those options
GRID_SETTINGS = {"train": {"method", "method.name", "preset", "seed"}, "eval": {"episodes", "seeds", "stream", "seed"}}


def _check_flag_list(flags: list[str], command: str, where: str, out: Path) -> None:
    """One settings or variant flag list for ``cdrb command``: every option exists, is not one the grid sets, has
    its value, and an integer or number value parses; a controller is a known one; a file it reads exists (or
    lies under ``out``, where the grid writes). A
    mistake is one line when the grid is read, not a failure of every task hours later."""
    from cdrb_cli.envs.registry import CONTROLLERS

    table = options(command)
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
        pname = entry.param
        if pname in RUN_OPTIONS:
            raise BadInput(
                f"{where}: {clip(repr(token), 60)}: the grid decides this for each task itself",
                hint="drop it: the grid resumes trainings, replaces only its own out-of-date artifacts, and "
                "`cdrb grid --dry-run` lists its commands",
            )
        if pname in GRID_OPTIONS.get(command, ()):
            raise BadInput(
                f"{where}: {clip(repr(token), 60)}: the grid sets this `cdrb {command}` option itself",
                hint="use the grid's own key (seeds, eval_seeds, eval_stream, eval_episodes, demos, data_seed, preset, "
                "device, out, tensorboard, or a variant's stream)",
            )
        if not entry.takes_value:
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
        base = entry.kind
        if base in (int, float):
            try:
                base(inline)
            except ValueError:
                what = "an integer" if base is int else "a number"
                raise BadInput(f"{where}: {token} {clip(repr(inline), 40)}: not {what}",
                               hint=f"`cdrb {command} --help` says what it takes") from None  # fmt: skip
        if pname == "controller":
            CONTROLLERS.get(inline, f"{where}: --controller")
        problem = entry.check(inline) if entry.check is not None else None
        if problem:
            raise BadInput(f"{where}: {token.partition('=')[0]} {clip(repr(inline), 40)}: {problem}",
                           hint=f"`cdrb {command} --help` says what it takes")  # fmt: skip
        option = token.partition("=")[0]
        if entry.reads_file and not Path(inline).exists() and not Path(inline).resolve().is_relative_to(out.resolve()):
            raise BadInput(f"{where}: {option} {clip(inline, 300)}: no such file", hint="fix the path (relative to the "
                           "file that names it)")  # fmt: skip
        if entry.reads_file and Path(inline).exists() and not Path(inline).is_file():  # a folder, a device
            raise BadInput(f"{where}: {option} {clip(inline, 300)}: not a regular file",
                           hint="name the file itself")  # fmt: skip


def check_flags(spec: GridSpec, path: Path) -> None:
    """Every flag list of the grid's settings and variants, by :func:`_check_flag_list`."""
    items = [("settings", i, s) for i, s in enumerate(spec.settings)] + [
        ("variants", i, v) for i, v in enumerate(spec.variants)
    ]
    for kind, i, item in items:
        for command in ("collect", "cluster", "train", "eval"):
            _check_flag_list(getattr(item, command, []), command, f"{path}: {kind}[{i}].{command}", spec.out)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def walk_options(tokens: list[str], table: dict[str, OptionInfo]):
    """Walk a command line's tokens (the command's name left off) over its options (:func:`~cdrb_cli.orchestration.
    grid.commands.options`):
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
        elif not entry.takes_value:
            yield token, entry, None
        elif eq and name.startswith("--"):
            yield token, entry, inline
        else:
            yield token, entry, tokens[i] if i < len(tokens) else None
            i += 1


def last_value_wins(flags: list[str], command: str) -> list[str]:
    """``flags`` of ``cdrb command`` with each option that takes one value kept once, at its first place, with the
    value given last (as the command itself reads a repeated option); flags, arguments and ``--set`` (a repeatable
    option) are kept as they are. A grid whose included files both name ``--features`` thus writes one flag, and the
    same clustering gets the same command line, whichever files declared it."""
    groups: list[list[str]] = []
    last: dict[str, list[str]] = {}
    for token, entry, value in walk_options(flags, options(command)):
        if entry is not None and entry.takes_value and value is not None:
            # one spelling for one value: ``--x=y`` as ``--x y`` (the command reads both alike)
            group = [token.partition("=")[0] if token.startswith("--") else token, value]
        else:
            group = [token]
        if entry is None or not entry.takes_value or entry.param == "sets":
            groups.append(group)
        elif entry.param in last:
            last[entry.param][:] = group
        else:
            last[entry.param] = group
            groups.append(group)
    return [t for g in groups for t in g]


def parse_command(
    argv: list[str], file_key=str, fold: bool = True
) -> tuple[list[str], dict[str, object], list[tuple[str, str]]]:
    """A command line as what it asks for, independent of how its flags are spelled: (its arguments, its options
    that are not settings by parameter name with the last value winning as on the command line, its settings as
    (key, value as JSON) pairs). An option that fills a setting counts as that setting (``--max-lag 0.6`` is
    ``--set controller.max_lag=0.6``, ``--steps 4000`` is ``--set steps=4000``) and a ``--set`` value counts as
    what it parses to (``0.60`` is ``0.6``); a setting given again later replaces all the earlier one set, and the
    pairs are sorted unless one key lies inside another. Every argument and file value goes through ``file_key``
    (a file's stand-in: its sha256, the task that wrote it, its name). ``fold=False`` keeps each option and each
    ``--set`` value as typed (for messages that quote the user)."""
    from cdrb_cli.settings import parse_value

    positional, given, sets = [], {}, []
    for token, entry, value in walk_options(argv[1:], options(argv[0])):
        if entry is None:
            positional.append(file_key(token))
            continue
        pname = entry.param
        value = ("" if value is None else value) if entry.takes_value else entry.flag_value
        if entry.reads_file and isinstance(value, str):
            value = file_key(value)
        if pname == "sets":
            k, _, v = str(value).partition("=")
            sets.append((k.strip(), _canonical(lambda v=v: parse_value(v.strip()), v.strip()) if fold else v.strip()))
            continue
        setting = _as_setting(entry, value) if fold else None
        if setting is not None:
            sets.append(setting)
        elif entry.to_setting is None or not fold:
            given[pname] = file_key(value) if isinstance(value, str) and not entry.reads_file else value
    # a later setting of the same key replaces all an earlier one set, whatever came between: the earlier is moot;
    # the order of the rest matters only where one key lies inside another (net= then net.dim=): sorted, a key
    # comes before the keys inside it, so the sorted order is the same command unless one came after them
    sets = [kv for j, kv in enumerate(sets) if all(kv[0] != later[0] for later in sets[j + 1 :])]
    if not any(b.startswith(a + ".") for j, (b, _) in enumerate(sets) for a, _ in sets[j + 1 :]):
        sets.sort()
    return positional, given, sets


def _canonical(value_of, text: str) -> str:
    """A setting's value as JSON (keys sorted), or its text where it does not parse (the command then says why)."""
    try:
        return json.dumps(value_of(), sort_keys=True)
    except Exception:  # a value the command refuses: keyed by its text
        return text


def _as_setting(entry: OptionInfo, value) -> tuple[str, str] | None:
    """The (key, value as JSON) of an option that fills a setting, as the command reads it; None for another
    option, or one given as not set (a moved flag's default)."""
    if entry.to_setting is None:
        return None
    try:
        pair = entry.to_setting(value)
    except Exception:  # a value the command refuses: keyed by its text under the option's own name
        return (f"--{entry.param}", str(value))
    return None if pair is None else (pair[0], _canonical(lambda: pair[1], str(pair[1])))


def nested(a: str, b: str) -> bool:
    """Whether one dotted settings key lies inside the other (``net`` and ``net.dim``)."""
    return a.startswith(b + ".") or b.startswith(a + ".")


def as_table(flags: list[str], command: str) -> dict | None:
    """``flags`` of ``command`` as the table of settings they set (as a grid file or a settings file writes them;
    null settings listed under ``null``), or None where they hold more than settings: an argument, an option that
    is not a setting (``--scene FILE``), a file (anchored at the file that names it only as a flag), or one key
    inside another (whose order matters)."""
    from cdrb_cli.settings import NULL_KEY

    table = options(command)
    if any(entry is None or entry.reads_file for _, entry, _ in walk_options(flags, table)):
        return None
    positional, given, sets = parse_command([command, *flags])
    if positional or given or any(nested(a, b) for j, (a, _) in enumerate(sets) for b, _ in sets[j + 1 :]):
        return None
    out: dict = {}
    nulls = []
    for key, text in sets:
        try:
            value = json.loads(text)
        except ValueError:
            return None
        if value is None:
            nulls.append(key)
            continue
        *parents, leaf = key.split(".")
        node = out
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    if nulls:
        out[NULL_KEY] = nulls
    return out


def without_setting(flags: list[str], command: str, key: str) -> list[str]:
    """``flags`` without what sets ``key``: its option (``--steps N``) and its ``--set key=...`` (the caller sets
    it itself, and `cdrb train` refuses a setting given both ways)."""
    out: list[str] = []
    table = options(command)
    for token, entry, value in walk_options(flags, table):
        if entry is None:
            out.append(token)
            continue
        if entry.param == "sets" and str(value).partition("=")[0].strip().replace("-", "_") == key:
            continue
        if (_as_setting(entry, value) or ("",))[0] == key:
            continue
        out += [token] if "=" in token or not entry.takes_value else [token, "" if value is None else value]
    return out
