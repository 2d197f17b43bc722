"""Terminal output: progress and logs on stderr, machine-usable results on stdout."""

from __future__ import annotations

import json
import sys
from contextlib import contextmanager
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

err = Console(stderr=True, highlight=False, soft_wrap=True)

_quiet = False


def set_quiet(value: bool) -> None:
    global _quiet
    _quiet = value


def log(message: str) -> None:
    """A log line on stderr (rich markup allowed)."""
    if not _quiet:
        err.print(message)


def warn(message: str) -> None:
    err.print(f"[yellow]warning:[/yellow] {message}")


def stdout_console():
    """A console for human-readable results on stdout (tables); wide when stdout is not a terminal."""
    return Console(highlight=False, soft_wrap=True, width=None if sys.stdout.isatty() else 200)


def emit(result: Any, as_json: bool = False) -> None:
    """Write the command's result to stdout: a path (one line) or, with ``--json``, a JSON document."""
    if as_json:
        sys.stdout.write(json.dumps(result, indent=2, sort_keys=False, default=str) + "\n")
    else:
        sys.stdout.write(f"{result}\n")
    sys.stdout.flush()


@contextmanager
def progress(transient: bool = False):
    """A rich progress display on stderr. Tasks may carry a ``info`` field shown after the bar."""
    columns = [
        SpinnerColumn(),
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TextColumn("eta"),
        TimeRemainingColumn(),
        TextColumn("{task.fields[info]}"),
    ]
    with Progress(*columns, console=err, transient=transient, disable=_quiet) as p:
        yield p


def table(rows: list[dict], columns: list[tuple[str, str]]) -> None:
    """Print ``rows`` as a table on stdout: ``columns`` = [(header, key)]."""
    from rich.table import Table

    t = Table(*[header for header, _ in columns], header_style="bold", box=None)
    for r in rows:
        t.add_row(*[_cell(r.get(key)) for _, key in columns])
    stdout_console().print(t)


def _cell(value: Any):
    from rich.text import Text

    if isinstance(value, bool):
        return Text("yes" if value else "no")
    if isinstance(value, float):
        return Text(f"{value:g}")
    return Text("" if value is None else str(value))
