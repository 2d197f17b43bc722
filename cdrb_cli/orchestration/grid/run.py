"""Running a grid: tasks as processes of their own on a local pool (forks of a warm server) or on Ray (`python -m
cdrb_cli` processes), retried once, with progress, a summary and the report."""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import json
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from cdrb_cli import artifacts, interrupts, ui
from cdrb_cli.errors import ERROR_FILE, EXIT_BAD_INPUT, BadInput, RunFailed
from cdrb_cli.orchestration.grid.expansion import expand
from cdrb_cli.orchestration.grid.load import load_grid
from cdrb_cli.orchestration.grid.memo import (
    check_outputs,
    fresh_log,
    is_done,
    last_line,
    log_path,
    open_log,
    read_log,
    up_to_date,
    write_memo,
    written_here,
)
from cdrb_cli.orchestration.grid.reuse import REUSABLE, regular_sha
from cdrb_cli.orchestration.grid.spec import STDERR_LINES, GridSpec, Task, read_small
from cdrb_cli.settings import clip

# ------------------------------------------------------------------------------------------------ execution
#: `cdrb train`'s hidden option for a model file the grid wrote itself: resume it if it is this run, else start over
OWN_MODEL = "--continue-or-replace"


def execute(payload: dict, server=None) -> dict:
    """Run one task's `cdrb` command in a process of its own (on this machine or a Ray worker): forked by the local
    pool's warm ``server`` (:mod:`~cdrb_cli.orchestration.grid.warm`) where there is one, else a fresh `python -m
    cdrb_cli`. A training whose model file is there is continued with ``--resume``: a checkpoint an earlier attempt
    left unfinished, or a finished shorter run of the same settings that the grid now trains longer (a curve
    extended to more steps); the command itself refuses a file of other settings, unless the grid wrote that file
    itself (:data:`OWN_MODEL`: then a run of other settings or data is out of date and trained over)."""
    argv = list(payload["argv"])
    if payload["kind"] == "train" and Path(payload["outputs"][0]).is_file() and OWN_MODEL not in argv:
        argv.append("--resume")
    for out in payload["outputs"]:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
    # PYTHONSAFEPATH: the task's `python -m` must not import modules from the current folder (a `typer.py` beside
    # the grid would run in every task); cdrb is imported from where it is installed
    # TTY_COMPATIBLE=0: a task's stderr is a file or a pipe, never a terminal, whatever FORCE_COLOR says, so its
    # progress is plain lines (a live bar's redraws would grow its log by megabytes an hour)
    env = dict(os.environ, OMP_NUM_THREADS=str(max(1, int(payload["cpus"]))), PYTHONSAFEPATH="1", TTY_COMPATIBLE="0")
    log = Path(payload["log"]) if payload.get("log") else None  # the grid's log of the task (local pool), made by it
    with _error_record(env, log) as error:
        rc, stderr, seconds = _run(server, argv, env, log)
    tail = [ln for ln in stderr.splitlines() if ln.strip()][-STDERR_LINES:]
    return {"rc": rc, "seconds": seconds, "stderr": tail, "error": error if rc else None}


@contextlib.contextmanager
def _error_record(env: dict, log: Path | None):
    """Name a file in ``env`` where the task's command leaves its failure as data (:data:`ERROR_FILE`): beside the
    task's log where it has one, else a fresh name in the temporary folder, made only by a command that fails (a
    grid killed mid-task leaves no file behind); yields a dict that holds that record after the block (empty when
    the command left none), and removes the file."""
    path = (
        f"{log}.error.json"
        if log is not None
        else os.path.join(tempfile.gettempdir(), f"cdrb-task-error-{uuid.uuid4().hex}.json")
    )
    with contextlib.suppress(OSError):
        os.unlink(path)  # an earlier attempt's
    env[ERROR_FILE] = path
    record: dict = {}
    try:
        yield record
    finally:
        text = read_small(Path(path))
        with contextlib.suppress(OSError):
            os.unlink(path)
        with contextlib.suppress(ValueError, RecursionError, TypeError):
            found = json.loads(text or "")
            record.update(found if isinstance(found, dict) else {})


def _run(server, argv: list[str], env: dict, log: Path | None) -> tuple[int, str, float]:
    """The command's exit code, stderr and seconds: forked by the warm ``server``, else a fresh process."""
    from cdrb_cli.orchestration.grid.warm import cold_only, parent_death_hook, run_task

    if server is not None and not cold_only(argv):
        return run_task(server, argv, env, _register, _unregister, log)
    t = time.time()
    fd = open_log(log) if log is not None else None
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "cdrb_cli", *argv],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE if fd is None else fd,
            text=True,
            env=env,
            preexec_fn=parent_death_hook(),
        )
    finally:
        if fd is not None:
            os.close(fd)
    _register(proc)
    try:
        _, stderr = proc.communicate()
    finally:
        _unregister(proc)
    stderr = read_log(log) if log is not None else stderr
    return proc.returncode, stderr, time.time() - t


def _register(proc) -> None:
    with _RUNNING_LOCK:
        _RUNNING.add(proc)


def _unregister(proc) -> None:
    with _RUNNING_LOCK:
        _RUNNING.discard(proc)


#: the task processes this process started and that still run (the pool's threads start them): subprocesses, or
#: the warm server's forks (:class:`~cdrb_cli.orchestration.grid.warm.WarmTask`, the same four methods)
_RUNNING: set = set()
_RUNNING_LOCK = threading.Lock()
#: seconds between looks at the running tasks' logs (their progress, shown after the grid's bar)
PROGRESS_POLL = 5.0


def stop_running(grace: float = 5.0) -> None:
    """SIGTERM every running task process (a training keeps its last checkpoint and exits), SIGKILL what is left
    after ``grace`` seconds."""
    with _RUNNING_LOCK:
        procs = list(_RUNNING)
    for p in procs:
        if p.poll() is None:
            p.terminate()
    deadline = time.time() + grace
    for p in procs:
        try:
            p.wait(timeout=max(0.0, deadline - time.time()))
        except subprocess.TimeoutExpired:
            p.kill()


@dataclass
class TaskResult:
    id: str
    kind: str
    status: Literal["done", "up to date", "failed", "skipped"] = "skipped"
    attempts: int = 0
    seconds: float = 0.0
    stderr: list[str] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)


class PoolBackend:
    """N local workers, each running one task's process at a time: forked by a warm server that has imported cdrb
    once (:mod:`~cdrb_cli.orchestration.grid.warm`; ``CDRB_GRID_WARM=0``: a fresh process per task)."""

    name = "local pool"
    #: tasks write their stderr into the grid's folder (OUT/.grid/logs), where the grid reads their progress
    logs = True

    def __init__(self, workers: int, warm: bool | None = None):
        self.workers = workers
        #: tasks handed over at once: the grid keeps the rest and picks them in its own order (see run_grid)
        self.capacity = workers
        self.pool = cf.ThreadPoolExecutor(max_workers=workers)
        self.warm = os.environ.get("CDRB_GRID_WARM", "1") != "0" if warm is None else warm
        self._server = None
        self._retired: list = []  # servers of older code, finishing the tasks they run
        self._server_lock = threading.Lock()

    def check(self, spec: GridSpec) -> None:
        pass

    def _execute(self, payload: dict) -> dict:
        server = None
        if self.warm and sys.platform.startswith("linux"):
            with self._server_lock:
                if self._server is not None and self._server.stale():  # cdrb's code changed since it started
                    self._server.retire()
                    self._retired.append(self._server)
                    self._server = None
                if self._server is None:
                    from cdrb_cli.orchestration.grid.warm import WarmServer

                    self._server = WarmServer()
                server = self._server
        return execute(payload, server)

    def submit(self, payload: dict) -> cf.Future:
        return self.pool.submit(self._execute, payload)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)
        for server in [*self._retired, *([self._server] if self._server is not None else [])]:
            server.close()
        self._server, self._retired = None, []


class RayBackend:
    """Tasks as Ray tasks with the CPUs/GPUs of their kind; ``address`` None starts Ray on this machine."""

    name = "ray"

    def __init__(self, address: str | None, workers: int | None):
        import ray

        # Ray's own notices (its start-up, its token set-up) would interleave with the grid's progress on stderr;
        # its errors still show
        kwargs = {
            "include_dashboard": False,
            "log_to_driver": False,
            "ignore_reinit_error": True,
            "logging_level": logging.ERROR,
        }
        if address is None and workers:
            kwargs["num_cpus"] = workers
        # "local": a Ray of its own, whatever RAY_ADDRESS or the last `ray start` on this machine say (joining a
        # cluster is what --address is for)
        # Ray puts the driver's current folder first on its workers' sys.path (a `numpy.py` beside the grid would
        # run in every worker): it starts from an empty folder of its own (the tasks' paths are absolute)
        self.home = tempfile.mkdtemp(prefix="cdrb-ray-")
        here = os.getcwd()
        os.chdir(self.home)
        try:
            ray.init(address="local" if address is None else address, **kwargs)
        except BaseException:
            shutil.rmtree(self.home, ignore_errors=True)
            raise
        finally:
            os.chdir(here)
            # ray.init sets its own SIGTERM handler: Ctrl-C and SIGTERM stop the grid cleanly (exit 130) again
            interrupts.reinstall()
        self.ray = ray
        self.remote = ray.remote(max_retries=0)(execute)
        total = ray.cluster_resources()
        self.workers, self.gpus = int(total.get("CPU", 0)), float(total.get("GPU", 0))

    def check(self, spec: GridSpec) -> None:
        """A task asking for GPUs the cluster lacks would wait forever: refuse the grid instead."""
        for kind, res in spec.resources.items():
            if res.gpus > self.gpus:
                raise BadInput(
                    f"resources.{kind}.gpus = {res.gpus:g}, but the Ray cluster has {self.gpus:g} GPUs",
                    hint="lower it in the grid file or add GPU workers",
                )

    def submit(self, payload: dict) -> cf.Future:
        # a task may not ask for more CPUs than the whole cluster has (it would never be scheduled)
        cpus = min(payload["cpus"], self.workers) if self.workers else payload["cpus"]
        fn = self.remote.options(num_cpus=cpus, num_gpus=payload["gpus"])
        return fn.remote(payload).future()

    def close(self) -> None:
        self.ray.shutdown()
        shutil.rmtree(self.home, ignore_errors=True)


#: seconds `cdrb grid --address` waits for the cluster to answer before saying it does not
ADDRESS_TIMEOUT = 5.0


def _probe(address: str) -> None:
    """A TCP connection to ``address`` (HOST:PORT or ray://HOST:PORT) within :data:`ADDRESS_TIMEOUT` seconds, so an
    address nobody listens on is one line instead of Ray retrying for minutes."""
    import socket

    hostport = address.removeprefix("ray://")
    host, _, port = hostport.rpartition(":")
    host = host.strip("[]")
    try:
        socket.create_connection((host, int(port)), timeout=ADDRESS_TIMEOUT).close()
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or type(exc).__name__
        raise BadInput(
            f"--address {address}: no Ray cluster answers there within {ADDRESS_TIMEOUT:g} s ({reason})",
            hint="start the head node (`ray start --head`) or check the host and port",
        ) from None


def make_backend(backend: str, workers: int | None, address: str | None):
    """``auto``: Ray when it is installed, else the local pool."""
    if address is not None and not re.fullmatch(r"(ray://)?[A-Za-z0-9_.\-\[\]:]+:[0-9]{1,5}|auto", address):
        raise BadInput(
            f"--address {address[:100]!r}: not a Ray address",
            hint="use HOST:PORT (a head node's GCS port) or ray://HOST:PORT (Ray Client), or auto",
        )
    if backend in ("auto", "ray"):
        try:
            import ray  # noqa: F401
        except ImportError:
            if backend == "ray" or address:
                raise BadInput(
                    "--backend ray: Ray is not installed", hint='pip install "cdrb-cli[ray]", or use --backend pool'
                ) from None
            ui.log("Ray is not installed: running on a local pool")
            backend = "pool"
        else:
            if address not in (None, "auto"):
                _probe(address)
            return RayBackend(address, workers)
    if address:
        raise BadInput("--address needs the Ray backend", hint="drop --address or use --backend ray")
    return PoolBackend(workers or max(1, os.cpu_count() or 1))


@dataclass
class DryRun:
    """What a run would do: every task, and which of them it would skip as up to date."""

    tasks: list[Task]
    up_to_date: dict[str, bool]

    def pending(self) -> list[Task]:
        return [t for t in self.tasks if not self.up_to_date[t.id]]


@dataclass
class GridRun:
    results: list[TaskResult]
    summary: Path
    seconds: float
    backend: str

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)


def run_grid(
    spec: GridSpec,
    backend,
    retries: int = 1,
    on_event: Callable[[str, TaskResult], None] | None = None,
    tasks: list[Task] | None = None,
    on_progress: Callable[[str], None] | None = None,
) -> GridRun:
    """Execute the grid's tasks (``tasks``, default: the expanded grid) on ``backend``: each when its inputs are
    ready, skipped when its memo is current, retried ``retries`` times on failure; dependants of a failed task are
    skipped. A task reading another grid's file (``reuse``) fails if that file changed since the grid was expanded.
    A backend with a ``capacity`` (the local pool) is handed at most that many tasks at once, the ready task first
    in the grid's order (environment by environment, each model's evals, its variants' and snapshots' included,
    right after it): one environment's rows are finished before the next one's trainings start, so a grid stopped
    part-way leaves whole rows. With a backend whose tasks log into the grid's folder, ``on_progress`` is called
    every few seconds with the running tasks' last progress lines. Writes OUT/grid.json."""
    t0 = time.time()
    tasks = expand(spec) if tasks is None else tasks
    order = _run_order(tasks)
    capacity = getattr(backend, "capacity", None)
    queued: list[Task] = []  # ready to run, waiting for a free slot of the backend
    results = {t.id: TaskResult(t.id, t.kind, outputs=[str(p) for p in t.outputs]) for t in tasks}
    state = {t.id: "pending" for t in tasks}
    cache = spec._shas
    logs = getattr(backend, "logs", False)  # its tasks write their stderr where log_path says
    polled = on_progress is not None and logs
    running: dict[cf.Future, Task] = {}
    emit = on_event or (lambda *_: None)

    def submit(task: Task) -> None:
        changed = [p for p, sha in task.meta.get("expect", {}).items() if regular_sha(p, cache) != sha]
        if changed:  # another grid rewrote a file this one took from it (e.g. a curve trained on): never read it
            state[task.id], results[task.id].status = "failed", "failed"
            results[task.id].stderr = [f"{changed[0]}: changed since this grid took it from a finished run; run again"]
            emit("failed", results[task.id])
            return
        res = spec.resources[task.kind]
        argv = task.argv
        if task.kind in ("collect", "cluster", "eval", "report") and written_here(spec, task, cache):
            argv = [*argv, "--force"]  # this grid's own artifact, now out of date (its model was trained on)
        elif task.kind == "train" and written_here(spec, task, cache):
            # its own model: continued when the run is the same (a curve extended), else trained over (a setting
            # or the data changed since)
            argv = [*argv, OWN_MODEL]
        payload = {"argv": argv, "kind": task.kind, "outputs": [str(p) for p in task.outputs]}
        payload |= {"cpus": res.cpus, "gpus": res.gpus}
        if logs:  # made here, before the task is handed over, so no poll reads an earlier attempt's lines
            fresh_log(log_path(spec, task))
            payload["log"] = str(log_path(spec, task))
        results[task.id].attempts += 1
        state[task.id] = "running"
        running[backend.submit(payload)] = task

    while True:
        progressed = True
        while progressed:  # settle everything that needs no run: up-to-date tasks, dependants of failures
            progressed = False
            for task in tasks:
                if state[task.id] != "pending":
                    continue
                deps = [state[d] for d in task.deps]
                if any(s in ("failed", "skipped") for s in deps):
                    state[task.id] = "skipped"
                    results[task.id].stderr = [f"not run: {next(d for d in task.deps if state[d] != 'done')} failed"]
                    emit("skipped", results[task.id])
                    progressed = True
                elif all(s == "done" for s in deps):
                    if is_done(spec, task, cache):
                        state[task.id] = "done"
                        results[task.id].status = "up to date"
                        emit("up to date", results[task.id])
                        progressed = True
                    else:
                        state[task.id] = "queued"
                        queued.append(task)
            queued.sort(key=lambda t: order[t.id])
            while queued and (capacity is None or len(running) < capacity):
                task = queued.pop(0)
                submit(task)
                progressed = progressed or state[task.id] == "failed"  # settle its dependants next pass
        if not running:
            break
        finished, _ = cf.wait(list(running), timeout=PROGRESS_POLL if polled else None, return_when=cf.FIRST_COMPLETED)
        for fut in finished:
            task = running.pop(fut)
            res = results[task.id]
            out = _outcome(fut)
            res.seconds += out["seconds"]
            if out["rc"] == 0:  # (the hash cache is keyed by size and mtime: rewritten files are hashed afresh)
                write_memo(spec, task, cache)
                state[task.id], res.status, res.stderr = "done", "done", []
                _log_eval(task)
                emit("done", res)
            elif res.attempts <= retries and (out.get("error") or {}).get("exit_code") != EXIT_BAD_INPUT:
                # (a refused input is refused again: only a run that failed on its way is retried)
                res.stderr = _grid_hint(task, out)
                emit("retry", res)
                submit(task)
            else:
                state[task.id], res.status, res.stderr = "failed", "failed", _grid_hint(task, out)
                emit("failed", res)
        if polled:  # the tasks still running, after the finished ones are settled
            on_progress(_progress(spec, running.values()))
    ordered = [results[t.id] for t in tasks]
    return GridRun(ordered, _write_summary(spec, backend.name, ordered, t0), time.time() - t0, backend.name)


def _progress(spec: GridSpec, tasks) -> str:
    """The running tasks' last log lines, one clause each: what a long training is at, without opening its log."""
    lines = [(t.id, last_line(log_path(spec, t))) for t in tasks]
    return "; ".join(f"{tid}: {clip(line, 90)}" if line else tid for tid, line in lines)


def _run_order(tasks: list[Task]) -> dict[str, tuple[int, int, int]]:
    """Each task's rank among ready tasks: the grid's order, with every eval moved up to right after the training it
    reads (a variant's evals and a snapshot's too, which the grid lists after all of an environment's trainings), so
    a finished model is measured before the next one trains."""
    pos = {t.id: i for i, t in enumerate(tasks)}
    kind = {t.id: t.kind for t in tasks}
    order = {}
    for t in tasks:
        trains = [pos[d] for d in t.deps if kind.get(d) == "train"]
        order[t.id] = (max(trains), 1, pos[t.id]) if t.kind == "eval" and trains else (pos[t.id], 0, pos[t.id])
    return order


def _log_eval(task) -> None:
    """With ``tensorboard = true``: a finished eval's figures join its model's training curves (a log that cannot
    be written is said on stderr; the eval artifact is the record)."""
    if task.kind != "eval" or "log_dir" not in task.meta:
        return
    from cdrb_cli.stages.train_log import log_eval

    try:
        ev = artifacts.load(task.outputs[0], "eval")
        log_eval(Path(task.meta["log_dir"]), task.meta["variant"] or "base", task.meta["steps"], ev.manifest.summary)
    except Exception as exc:  # a view of the record, never a reason to fail the grid
        ui.warn(f"{task.id}: its figures were not logged to {task.meta['log_dir']} ({clip(str(exc), 120)})")


def _grid_hint(task: Task, out: dict) -> list[str]:
    """A failed task's stderr lines as the grid's user can act on them: where an output blocked the command (its
    error record names one), the command's own fix (pass ``--force``) becomes what to do here, since a grid passes
    ``--force`` only to its own artifacts and takes no such flag."""
    lines, error = list(out["stderr"]), out.get("error") or {}
    if not error.get("output_exists") or "--force" in task.argv:  # (its own artifact: the command's hint stands)
        return lines
    grid_hint = "a grid writes over no file it did not write itself: move or remove that one, or choose another `out`"
    said = f"{error.get('message')} ({error['hint']})" if error.get("hint") else str(error.get("message"))
    told = [i for i, line in enumerate(lines) if line.endswith(said)]
    line = f"error: {error.get('message')} ({grid_hint})"
    return [*lines[: told[-1]], line, *lines[told[-1] + 1 :]] if told else [*lines, line]


def _outcome(fut: cf.Future) -> dict:
    """A finished task's result: the worker's, or a failure naming why the worker itself died (Ray) or could not
    start the process."""
    try:
        return fut.result()
    except Exception as exc:
        return {"rc": -1, "seconds": 0.0, "stderr": [f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"]}


def _write_summary(spec: GridSpec, backend: str, ordered: list[TaskResult], t0: float) -> Path:
    """OUT/grid.json: every task's result and the counts by status."""
    summary = spec.out / "grid.json"
    spec.out.mkdir(parents=True, exist_ok=True)
    body = {
        "seconds": time.time() - t0,
        "backend": backend,
        "tasks": [r.__dict__ for r in ordered],
        "counts": {s: sum(r.status == s for r in ordered) for s in ("done", "up to date", "failed", "skipped")},
        "reused": spec._reused,
    }
    with artifacts.atomic_path(summary) as tmp:
        tmp.write_text(json.dumps(body, indent=1, default=str))
    return summary


def grid(
    path: Path,
    backend: str = "auto",
    workers: int | None = None,
    address: str | None = None,
    retries: int = 1,
    dry_run: bool = False,
    overrides: list[str] = (),
    includes: list[Path] = (),
) -> GridRun | DryRun:
    """Load, expand and run a grid file with a progress bar and one line per finished task (stderr)."""
    spec = load_grid(path, overrides, includes)
    tasks = expand(spec)
    if spec._reused:
        kinds = [t.split(" ", 1)[0] for t in spec._reused]
        ui.log(
            "taken from finished runs of "
            + ", ".join(str(f) for f in spec.reuse)
            + ": "
            + ", ".join(f"{kinds.count(k)} {k}" for k in REUSABLE if k in kinds)
            + " (not run here)"
        )
    check_outputs(spec, tasks)  # a dry run lists what a real one would do, so it is refused the same way
    if dry_run:
        return DryRun(tasks, up_to_date(spec, tasks, spec._shas))
    spec.out.mkdir(parents=True, exist_ok=True)
    with artifacts.claim_output(spec.out / "grid.json", force=True, flag=f"{path}: out ="):
        runner = make_backend(backend, workers, address)
        try:
            runner.check(spec)
        except BadInput:
            runner.close()
            raise
        ui.log(f"{len(tasks)} tasks on {runner.name} ({runner.workers} workers/CPUs), artifacts in {spec.out}")
        try:
            with ui.progress() as bar:
                # no eta from the rate of finished tasks: a grid's evals take seconds and its trainings hours
                job = bar.add_task("grid", total=len(tasks), info="", eta=False)

                def on_event(event: str, res: TaskResult) -> None:
                    if event == "retry":
                        why = res.stderr[-1] if res.stderr else "no stderr"
                        ui.log(f"retry   {res.id} (attempt {res.attempts} failed: {why})")
                        return
                    secs = f"{res.seconds:7.1f}s" if event == "done" else " " * 8
                    ui.log(f"{event:10s} {secs}  {res.id}")
                    bar.advance(job)

                def on_progress(info: str) -> None:
                    bar.update(job, info=clip(info, 200))

                run = run_grid(spec, runner, retries=retries, on_event=on_event, tasks=tasks, on_progress=on_progress)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the running tasks stop too, instead of being waited for
            stop_running()
            raise
        finally:
            runner.close()
    failed = [r for r in run.results if r.status == "failed"]
    for r in failed:
        said = "\n  ".join(r.stderr or ["(no stderr)"])
        ui.warn(f"{r.id} failed after {r.attempts} attempt{'s' * (r.attempts != 1)}:\n  {said}")
    if failed:
        raise RunFailed(
            f"{len(failed)} of {len(run.results)} grid tasks failed ({', '.join(r.id for r in failed[:3])}"
            f"{', ...' if len(failed) > 3 else ''}); {run.count('skipped')} skipped; details in {run.summary}"
        )
    return run
