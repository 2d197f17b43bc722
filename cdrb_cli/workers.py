"""Independent pieces of one command, run side by side in worker processes, each with its share of the cores.

Small networks use two CPU cores poorly inside one run: a quick-preset U-Net trains only ~1.3x faster on two
threads than on one, while two runs of one thread each go nearly twice as fast as one run alone
(docs/benchmarks.md §11). So a command with several independent trainings or evaluations (``cdrb quickstart``) runs
them at once. Workers are spawned processes that start with one job each and a fixed thread count; their progress
bars and log lines come back through a queue and are drawn by this process's own display, and an error a user
caused comes back as its one-line message, re-raised here with the same type.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing import get_context
from typing import Any

from cdrb_cli import ui
from cdrb_cli.errors import BadInput, CdrbError, RunFailed


def die_with_parent(parent: int | None = None) -> None:
    """In a worker process, on Linux: the kernel's promise to SIGTERM it when its parent dies, so a command killed
    with -9 leaves no worker running (nor the resource tracker a pool keeps)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes
    import signal

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if parent is not None and os.getppid() != parent:  # the parent died before the promise was made
        os._exit(1)


@contextmanager
def sigint_ignored() -> Iterator[None]:
    """Ignore Ctrl-C while worker processes are spawned here: a spawned interpreter starts with the dispositions it
    inherits, so a worker whose SIGINT is ignored from its first instruction cannot be stopped by a Ctrl-C halfway
    through its imports (a traceback each). The parent takes the Ctrl-C and ends the pool; the window in which the
    parent itself ignores it is the fork and exec of the workers, milliseconds. Off the main thread (no handler can
    be set there): nothing."""
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous is None:  # None: set outside Python,
        yield  # so it could not be put back
        return
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def plan(jobs: int, device: str = "cpu") -> tuple[int, int]:
    """(processes, torch threads each) for ``jobs`` independent jobs: on a CPU, the cores free now
    (:func:`cdrb_cli.torch_utils.cpu_threads`, or ``OMP_NUM_THREADS``) shared out, one process per job while
    cores last; on a GPU, one process (the jobs share the device one after another)."""
    from cdrb_cli.torch_utils import cpu_threads

    cores = cpu_threads()
    if jobs <= 1 or str(device) != "cpu" or cores < 2:
        return 1, cores
    processes = min(jobs, cores)
    return processes, max(1, cores // processes)


_stop = None  # in a worker: the parent's event, set when the parent was interrupted
_takes_sigint = False  # in a worker: whether Ctrl-C is to reach its jobs (not in a background job)
_running = False  # in a worker: whether a job runs, with the handlers in place


def _init(queue, threads: int, parent: int, stop, takes_sigint: bool) -> None:
    global _stop, _takes_sigint
    die_with_parent(parent)
    os.environ["OMP_NUM_THREADS"] = str(threads)  # cdrb's own set-up reads it; torch is not imported yet
    _stop, _takes_sigint = stop, takes_sigint
    threading.Thread(target=_answer_stop, daemon=True).start()
    ui.forward_to(queue)


def _answer_stop() -> None:
    """In a worker: once the parent was interrupted, stop the job running here as a SIGTERM does (between two
    training steps), unless a signal already reached it (the user's Ctrl-C to the whole group)."""
    from cdrb_cli import interrupts

    _stop.wait()
    if _running and not interrupts.delivered():  # an idle worker checks `_stop` when its next job comes
        os.kill(os.getpid(), signal.SIGTERM)


def _call(fn: Callable[[Any], Any], payload: Any) -> tuple[str, Any]:
    """In a worker, a job, once ``fn``'s module is imported (unpickling the job imported it, with Ctrl-C ignored).
    While it runs, Ctrl-C and SIGTERM stop a training between two steps (:mod:`cdrb_cli.interrupts`); between jobs
    Ctrl-C is ignored again. A Ctrl-C that came while it was ignored reached the parent, which sets ``_stop``: a job
    not begun does not begin, and a thread here stops the one running (the parent waits for its workers)."""
    global _running
    from cdrb_cli import interrupts

    if _takes_sigint:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    restore = interrupts.install()
    _running = True  # before the check: the thread either sees it and signals, or the check sees `_stop`
    try:
        if _stop is not None and _stop.is_set():
            raise KeyboardInterrupt
        return "ok", fn(payload)
    except CdrbError as exc:  # the user's error: its one line, not a traceback
        return ("bad" if isinstance(exc, BadInput) else "failed"), (exc.message, exc.hint)
    finally:
        _running = False
        restore()
        if _takes_sigint:
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def run(fn: Callable[[Any], Any], payloads: Sequence[Any], processes: int, threads: int) -> list[Any]:
    """``[fn(p) for p in payloads]``, ``processes`` at a time in spawned workers with ``threads`` torch threads
    each (``processes`` <= 1: here, in order). ``fn`` must be a module-level function; payloads and results
    small plain values (paths, settings, names). The first error is raised once every job has ended."""
    if processes <= 1 or len(payloads) <= 1:
        return [fn(p) for p in payloads]
    ctx = get_context("spawn")
    queue, stop = ctx.Queue(), ctx.Event()
    takes_sigint = signal.getsignal(signal.SIGINT) is not signal.SIG_IGN  # not when run as a background job
    with ui.progress() as bar:
        relay = threading.Thread(target=_relay, args=(queue, bar), daemon=True)
        relay.start()
        try:
            init = (queue, threads, os.getpid(), stop, takes_sigint)
            with ProcessPoolExecutor(processes, mp_context=ctx, initializer=_init, initargs=init) as pool:
                with sigint_ignored():  # the workers spawn here, at the first submits
                    futures = [pool.submit(_call, fn, p) for p in payloads]
                try:
                    outcomes = [f.result() for f in futures]
                except KeyboardInterrupt:
                    stop.set()  # the jobs running stop, those not begun do not begin
                    raise
        finally:
            queue.put(None)
            relay.join(timeout=5)
    for status, value in outcomes:
        if status != "ok":
            message, hint = value
            raise (BadInput if status == "bad" else RunFailed)(message, hint=hint)
    return [value for _, value in outcomes]


def _relay(queue, bar) -> None:
    """Draw what the workers send (tasks, their progress, log lines) on this process's display, until None."""
    tasks: dict[tuple, Any] = {}
    while True:
        message = queue.get()
        if message is None:
            return
        kind, *rest = message
        if kind == "task":
            key, description, total, completed, fields = rest
            tasks[key] = bar.add_task(description, total=total, completed=completed, **fields)
        elif kind == "update" and rest[0] in tasks:
            bar.update(tasks[rest[0]], **rest[1])
        elif kind == "advance" and rest[0] in tasks:
            bar.advance(tasks[rest[0]], rest[1])
        elif kind == "log":
            ui.log(rest[0])
        elif kind == "warn":
            ui.warn(rest[0])
