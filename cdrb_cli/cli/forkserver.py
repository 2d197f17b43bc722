"""The warm task server of the grid's local pool (started by :class:`cdrb_cli.orchestration.grid.warm.WarmServer`
as ``python -m cdrb_cli.cli.forkserver``): it imports cdrb and its heavy libraries once, then forks one process per
task, which runs the task's `cdrb` command in :func:`cdrb_cli.cli.main`. The protocol and the guarantees are in
:mod:`cdrb_cli.orchestration.grid.warm`."""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import select
import signal
import sys

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

#: what the server imports before it forks the first task of a command: torch.optim imports torch._dynamo on its
#: first call (~2.5 s a process), which only trainings make, so a grid pays it once, and only if it trains
BEFORE_FIRST = {"train": ("torch._dynamo",)}


def serve() -> None:
    """The server: its loop, then its scratch folder (``CDRB_WARM_HOME``) removed however it ends, also when the
    grid was killed with -9 and the kernel's SIGTERM ends the server."""
    home = os.environ.get("CDRB_WARM_HOME")
    signal.signal(signal.SIGTERM, _terminated)
    try:
        _loop()
    finally:
        if home:
            import shutil

            shutil.rmtree(home, ignore_errors=True)


def _terminated(signum, frame) -> None:
    raise SystemExit(128 + signum)


def _loop() -> None:
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
                for name in BEFORE_FIRST.get(request["argv"][0] if request["argv"] else "", ()):
                    with contextlib.suppress(ImportError):
                        importlib.import_module(name)  # a no-op once imported
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
        from cdrb_cli.files import regular_fd

        err = regular_fd(request["stderr"], os.O_WRONLY | os.O_APPEND)  # the task's log, made by the grid
        # stdout: discarded (a grid's tasks name their outputs), or into the file the request names (it exists)
        out = regular_fd(request["stdout"], os.O_WRONLY | os.O_APPEND) if request.get("stdout") else null
        os.dup2(null, 0)
        os.dup2(out, 1)
        os.dup2(err, 2)
        for fd in {null, out, err}:
            os.close(fd)
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


if __name__ == "__main__":
    serve()
