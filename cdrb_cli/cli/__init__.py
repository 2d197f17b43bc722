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
import errno
import os
import sys
from pathlib import Path

import typer

from cdrb_cli import PROG, envvars, interrupts, provenance, ui
from cdrb_cli.errors import (
    EXIT_BAD_INPUT,
    EXIT_BROKEN_PIPE,
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    BadInput,
    CdrbError,
    leave_record,
)

try:  # typer >= 0.20 vendors click; older versions use the click package
    from typer._click import exceptions as click_exc
except ImportError:  # pragma: no cover
    from click import exceptions as click_exc

from cdrb_cli.cli.common import app, readable_help  # noqa: F401  (app: the typer app; readable_help: tested)

# the command groups, imported for their registration on `app` (the order --help lists them in)
from cdrb_cli.cli import info, data, share, train, plan, evaluate, studies, grids  # noqa: E402, F401  isort: skip
from cdrb_cli.cli.catalogue import describe  # noqa: E402
from cdrb_cli.orchestration.grid import commands as _grid_commands  # noqa: E402

# the grid reads the commands it composes from their description, made when it first needs it
_grid_commands.install(lambda: describe(app))


# ------------------------------------------------------------------------------------------------ entry point
def _one_line(text: str) -> str:
    return " ".join(str(text).split()).replace("Value error, ", "")


def _error(text: str) -> None:
    sys.stderr.write(f"error: {ui.plain(_one_line(text))}\n")
    sys.stderr.flush()


def _refuse_empty_paths(command, args: list[str]) -> None:
    """Refuse an empty value of a path option (``--video ''``, ``--out=``): ``Path("")`` is the current folder, so
    a shell variable that was never set would write there."""
    cmd, rest = command, list(args)
    while rest and hasattr(cmd, "commands") and rest[0] in cmd.commands:
        cmd, rest = cmd.commands[rest[0]], rest[1:]
    paths, takes_value, path_args = set(), set(), []
    for param in getattr(cmd, "params", ()):
        described = getattr(param, "type_descriptor", None)
        is_path = getattr(described, "annotation", None) in (Path, list[Path])
        opts = [o for o in getattr(param, "opts", ()) if o.startswith("-")]
        if is_path:
            paths.update(opts)
        if opts and not getattr(param, "is_flag", False):
            takes_value.update(opts)
        if getattr(param, "param_type_name", None) == "argument":
            path_args.append(param.name.upper() if is_path else None)
    position = 0  # the positional arguments seen so far (an empty one, where a path goes, is refused too)
    for i, arg in enumerate(rest):
        if arg == "--":
            return
        flag, eq, value = arg.partition("=")
        if flag in paths and (value if eq else (rest[i + 1] if i + 1 < len(rest) else None)) == "":
            raise BadInput(f"{flag} '': an empty path (it would name the current folder)", hint="give a path")
        if (i and rest[i - 1] in takes_value) or arg.startswith("-"):  # an option's value, or an option
            continue
        name = path_args[min(position, len(path_args) - 1)] if path_args else None
        if arg == "" and name is not None:
            raise BadInput(f"{name} '': an empty path (it would name the current folder)", hint="give a path")
        position += 1


def _link_loop(exc: BaseException) -> str | None:
    """The path of a symbolic link loop that ``exc`` reports (Python's ``resolve`` raises RuntimeError for one
    before 3.13, OSError ELOOP from then on, as do the system calls), else None."""
    import errno

    if isinstance(exc, OSError) and exc.errno == errno.ELOOP:
        return str(exc.filename) if exc.filename is not None else "a path"
    prefix = "Symlink loop from "
    if isinstance(exc, RuntimeError) and str(exc).startswith(prefix):
        return str(exc)[len(prefix) :].strip("'\"")
    return None


def _stdout_failed(exc: BaseException) -> bool:
    """Whether ``exc`` was raised writing to stdout: the innermost Python frame's line writes to it, or the frame
    belongs to an object that prints to it (rich's console)."""
    import linecache

    tb = exc.__traceback__
    while tb is not None and tb.tb_next is not None:
        tb = tb.tb_next
    if tb is None:
        return False
    frame = tb.tb_frame
    if "stdout" in linecache.getline(frame.f_code.co_filename, tb.tb_lineno):
        return True
    me = frame.f_locals.get("self")
    return me is sys.stdout or (type(me).__name__ == "Console" and getattr(me, "file", None) is sys.stdout)


def _fail(message: str, hint: str | None, code: int) -> None:
    """Say a failure that is no :class:`CdrbError` (a usage error, a bug) on stderr, and leave its record too."""
    _error(f"{message} ({hint})" if hint else message)
    leave_record({"message": ui.plain(_one_line(message)), "hint": hint, "exit_code": code, "output_exists": None})


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
    for command in typer_app.registered_commands:
        command.help = reflow(command.help or (command.callback.__doc__ if command.callback else None))
    for group in typer_app.registered_groups:
        _reflow_commands(group.typer_instance)


_reflow_commands(app)


def _broken_pipe(exc: BaseException | None) -> bool:
    return isinstance(exc, BrokenPipeError) or (isinstance(exc, OSError) and exc.errno == errno.EPIPE)


def _stdout_to_devnull() -> None:
    """Point stdout at /dev/null, so that the interpreter's last flush finds no broken pipe to complain about."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError):  # stdout already closed or not a file
        pass


def main(argv: list[str] | None = None) -> int:
    """Run the CLI; returns the exit code (0 ok, 1 failed run, 2 bad input)."""
    args = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in args
    restore_signals = interrupts.install()
    try:
        command = typer.main.get_command(app)  # a second's work: a Ctrl-C during it is answered as one later
        envvars.check()  # a bad number in the environment stops the command before any work
        _refuse_empty_paths(command, args)
        with provenance.running([PROG, *args]) if argv is not None else contextlib.nullcontext():
            code = command.main(args=args, prog_name=PROG, standalone_mode=False)
        if code == EXIT_INTERRUPTED:  # typer turns KeyboardInterrupt into a returned exit code 130
            _interrupted(args)
        return code if isinstance(code, int) else 0
    except typer.Exit as exc:
        return exc.exit_code
    except SystemExit as exc:
        # click and rich end a command whose stdout reader went away (`cdrb inspect F | head -1`) with exit(1): the
        # end of the reader's interest, not a failed run; 141 = 128 + SIGPIPE, what a Unix tool stopped by it says
        if exc.code == 1 and _broken_pipe(exc.__context__):
            _stdout_to_devnull()
            return EXIT_BROKEN_PIPE
        raise
    except click_exc.UsageError as exc:
        if type(exc).__name__ == "NoArgsIsHelpError":  # the help text was the answer
            if exc.ctx is not None:
                sys.stdout.write(exc.ctx.get_help() + "\n")
            return EXIT_BAD_INPUT
        where = exc.ctx.command_path if exc.ctx else PROG
        _fail(f"{exc.format_message()}{_moved_flag(exc)}", f"see `{where} --help`", EXIT_BAD_INPUT)
        return EXIT_BAD_INPUT
    except click_exc.ClickException as exc:
        _fail(exc.format_message(), None, EXIT_BAD_INPUT)
        return EXIT_BAD_INPUT
    except typer.Abort:
        _error("aborted")
        return EXIT_INTERRUPTED
    except CdrbError as exc:
        leave_record(exc)
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
        loop = _link_loop(exc)
        if loop is not None:  # a path given through links that point at each other: the input is wrong, not cdrb
            _fail(f"{loop}: its symbolic links point at each other (a link loop)", "give a path that resolves",
                  EXIT_BAD_INPUT)  # fmt: skip
            return EXIT_BAD_INPUT
        if isinstance(exc, OSError) and _stdout_failed(exc):  # `cdrb inspect F > /dev/full`, a full disk
            _stdout_to_devnull()
            _fail(f"cannot write the output to stdout ({exc.strerror or exc})", "free space where stdout goes, "
                  "or send it elsewhere", EXIT_FAILED)  # fmt: skip
            return EXIT_FAILED
        _fail(f"{type(exc).__name__}: {_one_line(str(exc))[:300]}", "re-run with `cdrb --debug ...` for a traceback",
              EXIT_FAILED)  # fmt: skip
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
    if out.is_file():  # a finished model (or a file the next run will judge): nothing was lost to continue
        return f"; {out} is there: the same command again skips it if it is this run's finished model"
    return f"; no checkpoint of {out} was written yet: run the same command again to start over"
