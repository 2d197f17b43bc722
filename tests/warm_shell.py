"""A `cdrb` for shell scripts under test whose commands run as forks of a warm server (the grid's
:class:`~cdrb_cli.orchestration.grid.warm.WarmServer`): the same `cdrb_cli.cli.main` with the script's arguments,
folder, environment, stdout, stderr and exit code, without a fresh interpreter's 3-4 s of imports per command.

The script's `cdrb` is a small bash program first on its PATH. It writes one call's arguments, environment and
folder into a fresh folder, names that folder on a FIFO this process reads, and waits on a FIFO of its own for the
exit code; then it prints the call's stdout and stderr where the script expects them. A command that must start
fresh (:func:`~cdrb_cli.orchestration.grid.warm.cold_only`: it records videos) runs the installed `cdrb` instead, so
every script still calls the real entry point too.
"""

from __future__ import annotations

import contextlib
import os
import shlex
import shutil
import sys
import tempfile
import threading
from pathlib import Path

SHIM = """#!/usr/bin/env bash
# the test's cdrb: the command runs as a fork of a warm server (tests/warm_shell.py)
d=$(mktemp -d {relay}/call.XXXXXX) || exit 1
printf '%s\\0' "$@" > "$d/argv"; env -0 > "$d/env"; printf '%s' "$PWD" > "$d/cwd"; mkfifo "$d/rc"
printf '%s\\n' "$d" > {relay}/requests
read -r rc < "$d/rc"
if [ "$rc" = cold ]; then rm -rf "$d"; exec {real} "$@"; fi  # a command that must start fresh
cat "$d/out"; cat "$d/err" >&2
rm -rf "$d"
exit "$rc"
"""


def _fields(path: Path) -> list[str]:
    return path.read_bytes().decode().split("\0")[:-1]


def _serve_call(server, folder: Path) -> None:
    """Run one call the shim handed over; its exit code goes back on the call's FIFO (-1 if it could not start),
    or ``cold`` for a command that must start fresh, which the shim then runs itself."""
    from cdrb_cli.orchestration.grid.warm import cold_only

    rc = -1
    try:
        argv = _fields(folder / "argv")
        if cold_only(argv):
            rc = "cold"
            return
        env = dict(item.split("=", 1) for item in _fields(folder / "env") if "=" in item)
        out, err = folder / "out", folder / "err"
        out.touch()
        err.touch()
        rc = server.start(argv, env, err, cwd=Path((folder / "cwd").read_text()), stdout=out).wait()
    finally:
        with open(folder / "rc", "w") as fh:  # the shim is reading it: opening does not block for long
            fh.write(f"{rc}\n")


@contextlib.contextmanager
def warm_cdrb():
    """Yields a folder to put first on a script's PATH: its `cdrb` runs each command as a warm fork (Linux)."""
    from cdrb_cli.orchestration.grid.warm import WarmServer

    home = Path(tempfile.mkdtemp(prefix="cdrb-shell-"))
    requests = home / "requests"
    os.mkfifo(requests)
    shim = home / "bin" / "cdrb"
    shim.parent.mkdir()
    real = Path(sys.executable).parent / "cdrb"
    shim.write_text(SHIM.format(real=shlex.quote(str(real)), relay=shlex.quote(str(home))))
    shim.chmod(0o755)
    server = WarmServer()
    stop = threading.Event()

    def relay() -> None:
        while not stop.is_set():
            with open(requests) as fh:  # blocks until a shim (or the stop below) opens it for writing
                for line in fh:
                    if line.strip() and not stop.is_set():
                        threading.Thread(target=_serve_call, args=(server, Path(line.strip())), daemon=True).start()

    thread = threading.Thread(target=relay, daemon=True)
    thread.start()
    try:
        yield shim.parent
    finally:
        stop.set()
        with contextlib.suppress(OSError):  # wakes the relay's open, if it is in one (no reader: ENXIO)
            fd = os.open(requests, os.O_WRONLY | os.O_NONBLOCK)
            os.write(fd, b"\n")
            os.close(fd)
        thread.join(timeout=5)
        server.close()
        shutil.rmtree(home, ignore_errors=True)
