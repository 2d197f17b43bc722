"""Warm task processes for the local pool: a small fork server that imports cdrb and its heavy libraries (torch,
MuJoCo, Gymnasium-Robotics, h5py, scikit-learn) once, then forks one process per task.

A task of a grid is one `cdrb` command. Started as a fresh `python -m cdrb_cli` it pays 3-4 s of imports on these
cores before it does anything, which is most of the time of a small task (an eval of a few episodes, a clustering of
a small buffer, the tests' tiny trainings). A forked child starts with those imports done and runs the command in
the same `cdrb_cli.cli.main` a fresh process would, in the task's own folder, environment and thread count, with
its output in files; its exit code comes back to the grid.

The server speaks JSON lines on its stdin/stdout (plain data, nothing that could run code): a request ``{"id",
"argv", "env", "cwd", "stderr"}`` is answered at once with ``{"id", "pid"}`` (the grid can signal the task itself)
and, when the task ends, with ``{"id", "rc"}``. The server has one thread (it forks: no other thread may hold a
lock then), waits for requests and for its children in one ``select`` loop, starts with ``PYTHONSAFEPATH`` from an
empty folder (no module of the grid's folder is ever imported), and dies with the grid (Linux's parent-death
signal), as its children die with it.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

#: what the server imports before it forks: what every kind of task would import first
PRELOAD = (
    "numpy",
    "torch",
    "h5py",
    "scipy.spatial",
    "sklearn.cluster",
    "threadpoolctl",
    "cdrb_cli.cli",
    "cdrb_cli.stages.collect",
    "cdrb_cli.stages.cluster",
    "cdrb_cli.stages.train",
    "cdrb_cli.stages.evaluate",
    "cdrb_cli.stages.report",
    "cdrb_cli.methods.cdrb",
    "cdrb_cli.methods.diffuser",
    "cdrb_cli.envs.pointmaze.env",
    "cdrb_cli.envs.fetch.env",
)


def cold_only(argv: list[str]) -> bool:
    """Whether a command must start as a fresh process: one that records videos picks MuJoCo's GL back end before
    MuJoCo is imported, which the server has done already."""
    return any(a == "--video" or a.startswith("--video=") for a in argv)


# ------------------------------------------------------------------------------------------------ server side
def serve() -> None:
    """The server's loop (``python -m cdrb_cli.orchestration.grid.warm``)."""
    from cdrb_cli.envs.pointmaze.env import import_gymnasium_robotics
    from cdrb_cli.workers import die_with_parent

    die_with_parent(int(os.environ.get("CDRB_WARM_PARENT", "0")) or None)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the grid, which stops the tasks itself
    for name in PRELOAD:
        with contextlib.suppress(ImportError):
            importlib.import_module(name)
    with contextlib.suppress(ImportError):
        import_gymnasium_robotics()
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # a child ended: the wake-up byte ends the select
    requests = sys.stdin.buffer
    replies = os.fdopen(os.dup(sys.stdout.fileno()), "w", buffering=1)
    children: dict[int, object] = {}
    pending = b""
    open_ = True
    while open_ or children:
        readable, _, _ = select.select([requests, wake_r] if open_ else [wake_r], [], [], 1.0)
        if wake_r in readable:
            os.read(wake_r, 512)
        while children:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                break
            if pid == 0:
                break
            rid = children.pop(pid, None)
            if rid is not None:
                replies.write(json.dumps({"id": rid, "rc": os.waitstatus_to_exitcode(status)}) + "\n")
        if open_ and requests in readable:
            chunk = os.read(requests.fileno(), 1 << 16)
            if not chunk:  # the grid closed the pipe (finished or gone): no more tasks
                open_ = False
                continue
            pending += chunk
            while b"\n" in pending:
                line, pending = pending.split(b"\n", 1)
                request = json.loads(line)
                pid = os.fork()
                if pid == 0:
                    _child(request, wake_r, wake_w)  # never returns
                children[pid] = request["id"]
                replies.write(json.dumps({"id": request["id"], "pid": pid}) + "\n")


def _child(request: dict, *fds: int) -> None:
    """In the forked child: become the task's process, run its command, exit with its code."""
    code = 1
    try:
        signal.set_wakeup_fd(-1)
        for fd in fds:
            os.close(fd)
        for sig in (signal.SIGCHLD, signal.SIGTERM):
            signal.signal(sig, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        from cdrb_cli.workers import die_with_parent

        die_with_parent(os.getppid())
        _name(f"cdrb-{request['argv'][0] if request['argv'] else 'task'}")
        null = os.open(os.devnull, os.O_RDWR)
        err = os.open(request["stderr"], os.O_WRONLY | os.O_APPEND)
        os.dup2(null, 0)
        os.dup2(null, 1)
        os.dup2(err, 2)
        os.close(null)
        os.close(err)
        sys.stdin = open(0, closefd=False)  # new file objects: none of the server's locks come along
        sys.stdout = open(1, "w", buffering=1, closefd=False)
        sys.stderr = open(2, "w", buffering=1, closefd=False)
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        threads = os.environ.get("OMP_NUM_THREADS", "").strip()
        if threads.isdigit() and int(threads) > 0:  # the libraries read it when they were loaded, in the server
            from threadpoolctl import threadpool_limits

            threadpool_limits(int(threads))
        from cdrb_cli.cli import main

        code = main(list(request["argv"]))
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    except BaseException:
        import traceback

        traceback.print_exc()
        code = 1
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def _name(name: str) -> None:
    """The process's name as `top` and `ps -o comm` show it (Linux: 15 bytes), so a task is told from the server."""
    if sys.platform.startswith("linux"):
        import ctypes

        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(15, name.encode()[:15], 0, 0, 0)  # PR_SET_NAME


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
        from cdrb_cli.orchestration.grid.run import _die_with_parent

        self.started = time.time()  # the code the server imports is cdrb's as of now (see :meth:`stale`)
        self.home = tempfile.mkdtemp(prefix="cdrb-warm-")
        env = dict(os.environ, PYTHONSAFEPATH="1", CDRB_WARM_PARENT=str(os.getpid()))
        self.log = Path(self.home) / "server.log"
        with open(self.log, "w") as log:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "cdrb_cli.orchestration.grid.warm"],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=log,
                cwd=self.home,  # an empty folder: nothing of the grid's folder is on its path
                env=env,
                preexec_fn=_die_with_parent(),
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

    def start(self, argv: list[str], env: dict, stderr: Path) -> WarmTask:
        """Fork a task running ``cdrb argv`` with ``env`` in this process's current folder, its stderr into the
        file ``stderr`` (which exists)."""
        started, done, result = threading.Event(), threading.Event(), {}
        with self._lock:
            self._next += 1
            rid = self._next
            self._waiting[rid] = (started, done, result)
            request = {"id": rid, "argv": argv, "env": env, "cwd": os.getcwd(), "stderr": str(stderr)}
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


def run_task(server: WarmServer, argv: list[str], env: dict, register, unregister) -> tuple[int, str, float]:
    """Run ``cdrb argv`` in a forked task; ``register``/``unregister`` put its process where the grid's stop logic
    finds it. Returns (exit code, stderr, seconds)."""
    fd, name = tempfile.mkstemp(prefix="cdrb-task-", suffix=".err")
    os.close(fd)
    t = time.time()
    try:
        task = server.start(argv, env, Path(name))
        register(task)
        try:
            rc = task.wait()
        finally:
            unregister(task)
        return rc, Path(name).read_text(errors="replace"), time.time() - t
    finally:
        with contextlib.suppress(OSError):
            os.unlink(name)


if __name__ == "__main__":
    serve()
