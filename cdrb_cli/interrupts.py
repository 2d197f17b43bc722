"""Ctrl-C and SIGTERM, made reliable.

Python raises ``KeyboardInterrupt`` wherever the main thread happens to be when a signal arrives. When that is a
finalizer or a weakref callback (the garbage collector runs them at any allocation), the exception is printed as
"Exception ignored in ..." and dropped, and the run goes on as if nothing had been asked. Loops that run many short
steps (training) therefore ask for the interrupt to be *polled*: inside :func:`polled` the signal only raises a flag,
and the loop calls :func:`check` between steps, where raising is always safe (and never lands inside a checkpoint
write). Everywhere else the signal raises at once, as Python's own handler does.
"""

from __future__ import annotations

import signal
from contextlib import contextmanager

_requested = False
_polling = 0
_delivered = 0
#: the signals :func:`install` routes through the handler (while installed)
_routed: tuple[int, ...] = ()


def delivered() -> int:
    """How many SIGINT/SIGTERM the handler has received: a ``KeyboardInterrupt`` raised while this did not move
    came from code, not from the user (e.g. a plugin raising it)."""
    return _delivered


def _handler(signum, frame) -> None:
    global _requested, _delivered
    _delivered += 1
    if not _polling:
        raise KeyboardInterrupt  # raised now, so nothing is left to answer later
    _requested = True


def install():
    """Route SIGTERM, and SIGINT unless the process was started with it ignored (a background job), through the
    handler; returns a function that restores the previous handlers."""
    global _requested, _routed
    _requested = False
    previous = {signal.SIGTERM: signal.signal(signal.SIGTERM, _handler)}
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, _handler)
    outer, _routed = _routed, tuple(previous)

    def restore() -> None:
        global _routed
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        _routed = outer

    return restore


def reinstall() -> None:
    """Route the signals :func:`install` routes through the handler again, after a library replaced the handler
    (``ray.init`` sets its own SIGTERM handler, which exits with code 15 and a C++ stack dump instead of the
    interrupt's clean stop). Nothing when :func:`install` is not in force (cdrb used as a library), or off the main
    thread (where no handler can be set)."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    for sig in _routed:
        signal.signal(sig, _handler)


@contextmanager
def polled():
    """Within this block a signal is only recorded; the block calls :func:`check` often enough to answer it."""
    global _polling
    _polling += 1
    try:
        check()
        yield
    finally:
        _polling -= 1
    check()


def check() -> None:
    """Raise ``KeyboardInterrupt`` if Ctrl-C or SIGTERM arrived (and was not yet answered)."""
    global _requested
    if _requested:
        _requested = False
        raise KeyboardInterrupt
