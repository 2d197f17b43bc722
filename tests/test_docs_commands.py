"""The shell commands the docs show, checked against the repository and the CLI as they are.

Every line of a fenced ```bash block in README.md, docs/benchmarks.md, docs/cli.md and docs/tutorial.md is split
into commands (on ``&&``, ``||``, ``|``, ``;`` and parentheses, after dropping a leading ``$ `` and a trailing
``# comment``). For each command that starts with ``cdrb``:

* its command words (``cdrb grid``, ``cdrb import minari``) answer ``--help`` with exit code 0, and every long
  option it uses is named in that help text; ``cdrb plan`` and ``cdrb eval`` also accept the flags that docs/cli.md
  ("Plan and eval settings") lists as hidden from ``--help``;
* every file it names under experiments/, benchmarks/ or tests/ exists (an ``--out`` may name a file still to be
  written; everything under runs/ is output);
* a ``cdrb grid`` of an experiment file lists its tasks with ``--dry-run`` (the README's tour runs from a ``tour/``
  folder, so its ``../experiments/`` paths are read from there).

docs/benchmarks.md also gives commands inline, as code spans that start with ``cdrb grid``, ``cdrb select``, ``cdrb
report`` or ``python benchmarks/``: those are checked the same way.

A ``python benchmarks/X.py`` or ``bash benchmarks/X.sh`` command names a script that exists. The docs/notebook/
entries are a record of what was run then, not instructions, and are not checked.
"""

from __future__ import annotations

import re
import shlex
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ["README.md", "docs/benchmarks.md", "docs/cli.md", "docs/tutorial.md"]
#: a shell token that ends one command and may start another
SEPARATORS = {"&&", "||", "|", ";", "&", "(", ")"}
REDIRECTS = {">", ">>", "<", "&>"}
#: where a file a command names must exist (outputs go under runs/ or are named by --out)
CHECKED_DIRS = ("experiments/", "benchmarks/", "tests/")
#: wide help text, so that no option name is cut or wrapped
WIDE = {"COLUMNS": "250", "TERMINAL_WIDTH": "250"}


def _bash_lines(path: Path):
    """(line number, text) of every logical line in the file's ```bash blocks, continuation lines joined."""
    fenced, pending, start = False, "", 0
    for number, line in enumerate(path.read_text().splitlines(), 1):
        if line.startswith("```"):
            fenced = line.strip() == "```bash" if not fenced else False
            continue
        if not fenced:
            continue
        if not pending:
            start = number
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        yield start, pending + line
        pending = ""


#: the code spans of the results page that are commands (others name settings, labels or files)
INLINE = re.compile(r"`((?:cdrb (?:grid|select|report)|python benchmarks/)[^`]*)`")


def _inline_lines(path: Path):
    """(line number, text) of every command given as a code span outside the fenced blocks (one may wrap lines)."""
    text, fenced, kept = path.read_text(), False, []
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
            kept.append("")
            continue
        kept.append("" if fenced else line)
    prose = "\n".join(kept)
    for m in INLINE.finditer(prose):
        yield prose.count("\n", 0, m.start()) + 1, m.group(1).replace("\n", " ")


def _commands(text: str) -> list[list[str]]:
    """The simple commands of one shell line, as argument lists (redirections dropped)."""
    text = text.strip()
    text = text.removeprefix("$ ")
    lexer = shlex.shlex(text, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    commands, current, skip = [], [], False
    for token in lexer:  # shlex drops a `# comment` that starts a token
        if skip:
            skip = False
        elif token in SEPARATORS:
            commands.append(current)
            current = []
        elif token in REDIRECTS:
            skip = True
        else:
            current.append(token)
    commands.append(current)
    return [c for c in commands if c]


def _documented():
    """(where, argument list) of every command shown in a bash block of the checked docs."""
    for name in DOCS:
        inline = _inline_lines(ROOT / name) if name == "docs/benchmarks.md" else ()
        for number, line in [*_bash_lines(ROOT / name), *inline]:
            for argv in _commands(line):
                if argv[0] == "time" and len(argv) > 1:  # the shell's timer in front of the command
                    argv = argv[1:]
                yield f"{name}:{number}", argv


COMMANDS = list(_documented())
CDRB = [(where, argv) for where, argv in COMMANDS if argv[0] == "cdrb"]
SCRIPTS = [
    (where, argv)
    for where, argv in COMMANDS
    if argv[0] in ("python", "bash") and len(argv) > 1 and "benchmarks/" in argv[1]
]


def test_the_docs_show_commands():
    """The extraction finds what the docs hold (a broken fence would silently check nothing)."""
    shown = {where.split(":")[0] for where, _ in CDRB}
    assert shown == set(DOCS)
    assert len(CDRB) >= 60
    assert any(argv[:2] == ["cdrb", "grid"] for _, argv in CDRB)


@cache
def _hidden_flags() -> frozenset[str]:
    """The plan/eval flags docs/cli.md lists, in "Plan and eval settings", as accepted but hidden from --help."""
    text = (ROOT / "docs/cli.md").read_text()
    section = re.search(r"^## Plan and eval settings\n(.*?)^## ", text, re.S | re.M)
    assert section, "docs/cli.md has no 'Plan and eval settings' section"
    hidden = section.group(1).partition("hidden from `--help`")[2]  # the flags are listed after these words
    assert hidden, "docs/cli.md's 'Plan and eval settings' lists no flags hidden from --help"
    return frozenset(re.findall(r"`(--[a-z][a-z0-9-]*)", hidden)) - {"--help"}


_helps: dict[tuple[str, ...], str] = {}


def _help(cdrb, words: tuple[str, ...]) -> str:
    """`cdrb WORDS --help`, run once per command words."""
    if words not in _helps:
        result = cdrb(*words, "--help", env=WIDE)
        assert result.returncode == 0, f"`cdrb {' '.join(words)} --help` exited {result.returncode}: {result.stderr}"
        _helps[words] = result.stdout
    return _helps[words]


def _command_words(cdrb, args: list[str]) -> tuple[tuple[str, ...], list[str]]:
    """Split `cdrb`'s arguments into the command words (descending into groups such as `import`) and the rest."""
    words: list[str] = []
    while args and args[0].startswith("-"):  # cdrb's own options (-q, --debug) come before the command
        flag = args.pop(0)
        assert _names(_help(cdrb, ()), flag), f"cdrb has no option {flag}"
    while args:
        usage = re.search(r"Usage: cdrb[^\n]*", _help(cdrb, tuple(words)))
        if words and not (usage and "COMMAND" in usage.group(0)):
            break  # a command, not a group: the rest are its arguments
        words.append(args.pop(0))
    return tuple(words), args


def _names(help_text: str, flag: str) -> bool:
    """Whether a help text names the option (as a whole word: --seed is not --seeds)."""
    return re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", help_text) is not None


def _repo_path(token: str, where: str) -> Path | None:
    """The file a token names if it is one of the repository's own (experiments/, benchmarks/, tests/)."""
    if token.startswith("../experiments/") and where.startswith("README.md"):
        return (ROOT / "tour" / token).resolve()  # the README's tour runs from ./tour
    if token.startswith(CHECKED_DIRS) and not any(c in token for c in "*?[{$"):
        return ROOT / token
    return None


@pytest.mark.parametrize("where, argv", CDRB, ids=[f"{w}:{' '.join(a[:3])}" for w, a in CDRB])
def test_a_documented_cdrb_command_parses(cdrb, where, argv):
    """The command exists, takes the options the line gives it, names files that exist, and a grid of an
    experiment file lists its tasks."""
    words, args = _command_words(cdrb, list(argv[1:]))
    help_text = _help(cdrb, words)
    hidden = _hidden_flags() if words in {("plan",), ("eval",)} else frozenset()
    for token in args:
        flag = token.split("=", 1)[0]
        if flag.startswith("--") and flag != "--":
            assert _names(help_text, flag) or flag in hidden, f"{where}: `cdrb {' '.join(words)}` has no option {flag}"
    for before, token in zip(["", *args], args):
        path = _repo_path(token, where)
        if path is not None and before != "--out":
            assert path.exists(), f"{where}: {token} does not exist"
    grid_file = _repo_path(args[0], where) if words == ("grid",) and args else None
    if grid_file is not None and grid_file.suffix == ".toml" and "experiments" in grid_file.parts:
        _dry_run(cdrb, where, (str(grid_file), *args[1:]))


_dry_runs: set[tuple[str, ...]] = set()


def _dry_run(cdrb, where: str, args: tuple[str, ...]):
    """`cdrb grid ARGS --dry-run` from the repository root, once per distinct line."""
    if "--dry-run" not in args:
        args = (*args, "--dry-run")
    if args in _dry_runs:
        return
    result = cdrb("grid", *args, cwd=ROOT)
    assert result.returncode == 0, f"{where}: `cdrb grid {' '.join(args)}`: {result.stderr[-2000:]}"
    assert result.stdout.strip(), f"{where}: the dry run listed no task"
    _dry_runs.add(args)


def test_the_hidden_plan_and_eval_flags_exist():
    """What docs/cli.md lists as hidden-but-accepted is an option of `cdrb plan` or `cdrb eval`."""
    import typer.main

    from cdrb_cli.cli import app

    commands = typer.main.get_command(app).commands
    options = {opt for name in ("plan", "eval") for p in commands[name].params for opt in (*p.opts, *p.secondary_opts)}
    assert _hidden_flags()
    assert sorted(_hidden_flags() - options) == []


@pytest.mark.parametrize("where, argv", SCRIPTS, ids=[f"{w}:{a[1]}" for w, a in SCRIPTS])
def test_a_documented_benchmark_script_exists(where, argv):
    """`python benchmarks/X.py` and `bash benchmarks/X.sh` name scripts the repository has."""
    assert (ROOT / argv[1]).is_file(), f"{where}: {argv[1]} does not exist"
