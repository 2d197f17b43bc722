"""Terminal output: progress and logs on stderr, machine-usable results on stdout."""

from __future__ import annotations

import json
import os
import sys
import time
from contextlib import contextmanager
from typing import Any

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    Task,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text


def _width_if_unusable() -> int | None:
    """80 when COLUMNS says 0 (rich would then print nothing at all), else None: rich reads the terminal."""
    return 80 if os.environ.get("COLUMNS", "").strip() == "0" else None


#: the widest terminal taken from COLUMNS: rich lays a help page out for the width it is told, and 20,000,000
#: columns took it half a minute and gigabytes
MAX_COLUMNS = 1000


def _bound_columns() -> None:
    """Bound COLUMNS (read by rich, and by typer's help pages) to :data:`MAX_COLUMNS` for this process."""
    text = os.environ.get("COLUMNS", "").strip()
    if text.isdigit() and int(text) > MAX_COLUMNS:
        os.environ["COLUMNS"] = str(MAX_COLUMNS)


_bound_columns()
err = Console(stderr=True, highlight=False, soft_wrap=True, width=_width_if_unusable())

_quiet = False
_forward = None  # in a worker process (cdrb_cli.workers): the queue its progress and log lines go to


def set_quiet(value: bool) -> None:
    global _quiet
    _quiet = value


def forward_to(queue) -> None:
    """Send this process's progress and log lines to ``queue`` (a worker's; its parent draws them)."""
    global _forward
    _forward = queue


def plain(text: Any, limit: int | None = None) -> str:
    """Text safe for a terminal: control characters (ANSI escapes, carriage returns...) replaced by '?', optionally
    bounded. Every string that may come from a file or a path goes through it before it is printed."""
    out = "".join(ch if ch.isprintable() or ch == "\n" else "?" for ch in str(text))
    if limit is not None and len(out) > limit:
        out = out[:limit] + f"... ({len(out) - limit} more characters)"
    return out


def log(message: str) -> None:
    """A log line on stderr, printed as plain text (no markup is interpreted, control characters neutralized)."""
    if _forward is not None:
        _forward.put(("log", str(message)))
    elif not _quiet:
        err.print(Text(plain(message)))


def warn(message: str) -> None:
    if _forward is not None:
        _forward.put(("warn", str(message)))
        return
    err.print(Text("warning: ", style="yellow") + Text(plain(message)))


def stdout_console():
    """A console for human-readable results on stdout (tables); wide when stdout is not a terminal."""
    return Console(highlight=False, soft_wrap=True, width=_width_if_unusable() if sys.stdout.isatty() else 200)


def emit(result: Any, as_json: bool = False) -> None:
    """Write the command's result to stdout: a path (one line) or, with ``--json``, a JSON document."""
    if as_json:
        sys.stdout.write(json.dumps(result, indent=2, sort_keys=False, default=str) + "\n")
    else:
        sys.stdout.write(f"{result}\n")
    sys.stdout.flush()


#: seconds between the plain progress lines written when stderr is not a terminal (env CDRB_PROGRESS_SECONDS)
PROGRESS_SECONDS = 30.0


def shows_eta(task: Task) -> bool:
    """Whether a task's time left may be estimated from its rate: not for one added with ``eta=False``, a count of
    unlike items (a grid's tasks: an eval takes seconds, a training an hour), whose recent rate says nothing about
    the rest."""
    return task.fields.get("eta", True) is not False


class EtaColumn(TimeRemainingColumn):
    """``eta`` and the time left, or nothing for a task whose rate does not predict it (:func:`shows_eta`)."""

    def render(self, task: Task) -> Text:
        return Text.assemble("eta ", super().render(task)) if shows_eta(task) else Text("")


class LineProgress(Progress):
    """Progress for a stderr that is not a terminal (nohup, CI and SLURM logs): a live bar there is printed only when
    it ends, so each task instead gets one plain line every ``interval`` seconds and one when it completes."""

    def __init__(self, *columns, interval: float, **kwargs):
        super().__init__(*columns, **{**kwargs, "disable": True})
        self.interval = interval
        self._printed: dict = {}

    def update(self, task_id, **kwargs) -> None:
        super().update(task_id, **kwargs)
        self._line(task_id)

    def advance(self, task_id, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._line(task_id)

    def _line(self, task_id) -> None:
        task = self._tasks[task_id]
        done = task.total is not None and task.completed >= task.total
        now = time.monotonic()
        last = self._printed.setdefault(task_id, task.start_time or now)
        if last == "done" or (not done and now - last < self.interval):
            return
        self._printed[task_id] = "done" if done else now
        total = "?" if task.total is None else f"{task.total:g}"
        pct = f" ({100 * task.completed / task.total:.0f}%)" if task.total else ""
        elapsed = time.strftime("%H:%M:%S", time.gmtime(task.elapsed or 0))
        eta = (
            ""
            if done or not task.time_remaining or not shows_eta(task)
            else f", eta {time.strftime('%H:%M:%S', time.gmtime(task.time_remaining))}"
        )
        info = task.fields.get("info") or ""
        line = f"{task.description}: {task.completed:g}/{total}{pct}, {elapsed} elapsed{eta}" + (
            f", {info}" if info else ""
        )
        err.print(Text(plain(line)))


class ForwardedProgress:
    """The progress interface of a worker process: every call goes to its parent's display as a message."""

    def __init__(self, queue):
        self.queue = queue
        self.count = 0

    def add_task(self, description: str, total=None, completed=0, **fields):
        key = (os.getpid(), self.count)
        self.count += 1
        self.queue.put(("task", key, str(description), total, completed, {"info": "", **fields}))
        return key

    def update(self, task_id, **kwargs) -> None:
        self.queue.put(("update", task_id, kwargs))

    def advance(self, task_id, advance: float = 1) -> None:
        self.queue.put(("advance", task_id, advance))


@contextmanager
def progress(transient: bool = False):
    """A rich progress display on stderr (plain lines every ``CDRB_PROGRESS_SECONDS`` when stderr is not a terminal).
    Tasks may carry a ``info`` field shown after the bar. In a worker process, the parent's display."""
    if _forward is not None:
        yield ForwardedProgress(_forward)
        return
    columns = [
        SpinnerColumn(),
        TextColumn("{task.description}", markup=False, style="bold"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        EtaColumn(),
        TextColumn("{task.fields[info]}", markup=False),
    ]
    if not err.is_terminal and not _quiet:
        from cdrb_cli.envvars import progress_seconds

        interval = progress_seconds(PROGRESS_SECONDS)
        with LineProgress(*columns, console=err, interval=interval) as p:
            yield p
        return
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
    if isinstance(value, bool):
        return Text("yes" if value else "no")
    if isinstance(value, float):
        return Text(f"{value:g}")
    return Text("" if value is None else plain(value))
