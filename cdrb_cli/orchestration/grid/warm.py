"""Warm task processes for the local pool: a small fork server (:mod:`cdrb_cli.cli.forkserver`) that imports cdrb and
its heavy libraries (torch, MuJoCo, Gymnasium-Robotics, h5py, scikit-learn) once, then forks one process per task;
this module is the grid's end of it.

A task of a grid is one `cdrb` command. Started as a fresh `python -m cdrb_cli` it pays 3-4 s of imports on these
cores before it does anything, which is most of the time of a small task (an eval of a few episodes, a clustering of
a small buffer, the tests' tiny trainings). A forked child starts with those imports done and runs the command in
the same `cdrb_cli.cli.main` a fresh process would, in the task's own folder, environment and thread count, with
its output in files; its exit code comes back to the grid.

The server speaks JSON lines on its stdin/stdout (plain data, nothing that could run code): a request ``{"id",
"argv", "env", "cwd", "stderr"}`` (and ``"stdout"``, a file for the task's stdout, else it is discarded) is
answered at once with ``{"id", "pid"}`` (the grid can signal the task itself) and, when the task ends, with
``{"id", "rc"}``. The server has one thread (it forks: no other thread may hold a
lock then), waits for requests and for its children in one ``select`` loop, starts with ``PYTHONSAFEPATH`` from an
empty folder (no module of the grid's folder is ever imported), and dies with the grid (Linux's parent-death
signal), as its children die with it.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

#: the server's module: on the command line's floor, as the tasks it runs are `cdrb` commands (the grid only names it)
SERVER = "cdrb_cli.cli.forkserver"


def parent_death_hook():
    """What a task's process runs before it starts (Linux): ask the kernel to send it SIGTERM when the thread that
    started it dies, so a grid killed with -9 leaves no training running and holding its output's lock. The
    function is looked up here, in the parent: the child only calls it."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    return lambda: prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def cold_only(argv: list[str]) -> bool:
    """Whether a command must start as a fresh process: one that records videos picks MuJoCo's GL back end before
    MuJoCo is imported, which the server has done already."""
    return any(a == "--video" or a.startswith("--video=") for a in argv)


# ------------------------------------------------------------------------------------------------ grid side
class WarmTask:
    """A task process the server forked, as the grid's stop logic sees a subprocess: ``poll``, ``terminate``,
    ``kill``, ``wait``."""

    def __init__(self, pid: int, done: threading.Event, result: dict):
        self.pid = pid
        self._done = done
        self._result = result

    @property
    def returncode(self) -> int | None:
        return self._result.get("rc")

    def poll(self) -> int | None:
        return self.returncode

    def _signal(self, sig: int) -> None:
        if not self._done.is_set():
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.pid, sig)

    def terminate(self) -> None:
        self._signal(signal.SIGTERM)

    def kill(self) -> None:
        self._signal(signal.SIGKILL)

    def wait(self, timeout: float | None = None) -> int:
        if not self._done.wait(timeout):
            raise subprocess.TimeoutExpired("cdrb task", timeout)
        return self.returncode


class WarmServer:
    """The grid's end of a fork server (started on first use, stopped by :meth:`close`)."""

    def __init__(self):
        self.started = time.time()  # the code the server imports is cdrb's as of now (see :meth:`stale`)
        self.home = tempfile.mkdtemp(prefix="cdrb-warm-")
        # TTY_COMPATIBLE=0: its consoles, made at import, draw for files (a task's log), not for a terminal
        env = dict(
            os.environ, PYTHONSAFEPATH="1", CDRB_WARM_PARENT=str(os.getpid()), CDRB_WARM_HOME=self.home,
            TTY_COMPATIBLE="0",
        )  # fmt: skip
        self.log = Path(self.home) / "server.log"
        with open(self.log, "w") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", SERVER],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log,
                cwd=self.home,  # an empty folder: nothing of the grid's folder is on its path
                env=env,
                preexec_fn=parent_death_hook(),
            )
        self._lock = threading.Lock()
        self._next = 0
        self._waiting: dict[int, tuple[threading.Event, threading.Event, dict]] = {}
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            reply = json.loads(line)
            with self._lock:
                entry = self._waiting.get(reply["id"])
            if entry is None:
                continue
            started, done, result = entry
            result.update(reply)
            (done if "rc" in reply else started).set()
        with self._lock:  # the server is gone: every task still waiting has failed
            for started, done, result in self._waiting.values():
                result.setdefault("rc", -signal.SIGKILL)
                started.set()
                done.set()

    def start(
        self, argv: list[str], env: dict, stderr: Path, cwd: Path | None = None, stdout: Path | None = None
    ) -> WarmTask:
        """Fork a task running ``cdrb argv`` with ``env`` in the folder ``cwd`` (default: this process's), its
        stderr into the file ``stderr`` and its stdout into the file ``stdout`` or nowhere (files that exist)."""
        started, done, result = threading.Event(), threading.Event(), {}
        with self._lock:
            self._next += 1
            rid = self._next
            self._waiting[rid] = (started, done, result)
            request = {"id": rid, "argv": argv, "env": env, "cwd": str(cwd or os.getcwd()), "stderr": str(stderr)}
            if stdout is not None:
                request["stdout"] = str(stdout)
            try:
                self.proc.stdin.write((json.dumps(request) + "\n").encode())
                self.proc.stdin.flush()
            except (BrokenPipeError, ValueError, OSError):
                result["rc"] = -signal.SIGKILL
                started.set()
                done.set()
        started.wait()
        return WarmTask(int(result.get("pid", 0)), done, result)

    def stale(self) -> bool:
        """Whether cdrb's code changed since the server imported it (a file of the package written since): a fork
        would run the old modules it holds beside new ones it imports later, so the grid starts a new server."""
        package = Path(__file__).resolve().parents[2]
        for path in package.rglob("*.py"):
            with contextlib.suppress(OSError):
                if path.stat().st_mtime > self.started - 1:
                    return True
        return False

    def retire(self) -> None:
        """Take no more tasks; the server ends by itself once the tasks it runs have ended."""
        with contextlib.suppress(OSError, ValueError):
            self.proc.stdin.close()

    def close(self) -> None:
        with contextlib.suppress(OSError, ValueError):
            self.proc.stdin.close()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        shutil.rmtree(self.home, ignore_errors=True)


def run_task(
    server: WarmServer, argv: list[str], env: dict, register, unregister, log: Path | None = None
) -> tuple[int, str, float]:
    """Run ``cdrb argv`` in a forked task, its stderr into the file ``log`` (kept) or a temp file (removed);
    ``register``/``unregister`` put its process where the grid's stop logic finds it. Returns (exit code, stderr,
    seconds)."""
    from cdrb_cli.orchestration.grid.memo import read_log

    if log is None:
        fd, name = tempfile.mkstemp(prefix="cdrb-task-", suffix=".err")
        os.close(fd)
    else:
        name = str(log)
    t = time.time()
    try:
        task = server.start(argv, env, Path(name))
        register(task)
        try:
            rc = task.wait()
        finally:
            unregister(task)
        return rc, read_log(name), time.time() - t
    finally:
        if log is None:
            with contextlib.suppress(OSError):
                os.unlink(name)
