"""`cdrb grid GRID.toml`: a declarative grid of runs, expanded into the stage graph and executed in parallel.

A grid file names environments x methods x seeds (and optional variants: named sets of extra flags, one more axis).
It expands into tasks, each one `cdrb` command that writes one artifact:

    collect ENV  ->  cluster ENV  ->  train ENV/[VARIANT/]METHOD-sSEED  ->  eval ...  ->  report [VARIANT]

A task runs when the tasks it reads from have finished. Tasks are executed as `python -m cdrb_cli ...` processes,
either on **Ray** (``ray.init()`` on this machine, or ``--address`` for a cluster; each task asks for the CPUs
and GPUs of its kind) or, without Ray, on a local pool of N workers. Every artifact is written atomically by the
command itself, so a killed task leaves either nothing or a valid artifact (a training leaves its last
checkpoint); a failed task is retried once (a training with ``--resume``), then reported with the tail of its
stderr, and the tasks that do not depend on it go on.

Re-running a grid does no work for a task whose memo (``OUT/.grid/TASK.json``: the command, the cdrb version and
the sha256 of every input and output artifact) still matches the files; any other task is handed to the command,
which skips it when its artifact is up to date (the CLI's own rule) and resumes an unfinished training.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import os
import re
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from cdrb_cli import __version__, artifacts, ui
from cdrb_cli.errors import BadInput, RunFailed

KINDS = ("collect", "cluster", "train", "eval", "report")
STDERR_LINES = 15


# ------------------------------------------------------------------------------------------------ the grid file
class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Settings(_Strict):
    """Extra `cdrb train` / `cdrb eval` flags for the runs of one environment and/or method (both optional:
    omitted means every one), and extra `cdrb collect` flags for an environment's demonstrations (an entry with
    ``collect`` names no method: the demos are shared by every method). Entries apply in order, so a later one can
    override an earlier one's flag."""

    env: str | None = None
    method: str | None = None
    collect: list[str] = Field(
        default_factory=list, description="extra `cdrb collect` flags, e.g. ['--set', 'expert.routes=[\"over\"]']"
    )
    train: list[str] = Field(default_factory=list, description="extra `cdrb train` flags, e.g. ['--steps', '4000']")
    eval: list[str] = Field(default_factory=list, description="extra `cdrb eval` flags, e.g. ['--max-lag', '0.6']")


class Variant(_Strict):
    """One more axis of the grid: a named set of extra flags; its runs go to OUT/ENV/NAME/ and get their own
    report."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.=-]*$", description="folder name of the variant's runs")
    methods: list[str] | None = Field(None, description="the methods this variant applies to (default: all)")
    train: list[str] = Field(default_factory=list)
    eval: list[str] = Field(default_factory=list)


class Resources(_Strict):
    cpus: float = Field(1.0, gt=0, description="CPU cores a task of this kind asks Ray for (and its torch threads)")
    gpus: float = Field(0.0, ge=0, description="GPUs a task of this kind asks Ray for (fractions share one GPU)")


def _default_resources() -> dict[str, Resources]:
    return {"collect": Resources(cpus=2)} | {k: Resources() for k in KINDS if k != "collect"}


class GridSpec(_Strict):
    """A grid file (TOML). Paths are relative to the file's folder."""

    out: Path = Field(description="folder for every artifact of the grid (shared storage on a cluster)")
    envs: list[str] = Field(min_length=1, description="environment ids (`cdrb envs`)")
    methods: list[str] = Field(min_length=1, description="methods (`cdrb methods`)")
    seeds: list[int] = Field(min_length=1, description="training seeds; each model is evaluated on the same seed")
    preset: str = Field("quick", description="training preset of every method")
    device: str = Field("cpu", description="training and evaluation device (cpu, cuda, auto)")
    demos: int = Field(1000, ge=2, description="demonstrations collected per environment")
    data_seed: int = Field(0, description="seed of `cdrb collect` and `cdrb cluster`")
    k: int = Field(1000, ge=0, description="replay-buffer clusters (`cdrb cluster --k`; 0 keeps the full buffer)")
    steps: int | None = Field(None, gt=0, description="training steps of every run (default: the preset's)")
    eval_episodes: int = Field(100, ge=1, description="evaluation episodes per model")
    eval_stream: Literal["tune", "test"] = Field("test", description="start/goal pairs: tune or test stream")
    settings: list[Settings] = Field(default_factory=list, description="per env/method extra flags")
    variants: list[Variant] = Field(default_factory=list, description="named flag sets: one more grid axis")
    resources: dict[str, Resources] = Field(default_factory=_default_resources)

    @field_validator("resources")
    @classmethod
    def _kinds(cls, value: dict[str, Resources]) -> dict[str, Resources]:
        unknown = sorted(set(value) - set(KINDS))
        if unknown:
            raise ValueError(f"resources.{unknown[0]}: not a task kind (use {', '.join(KINDS)})")
        return _default_resources() | value


def load_grid(path: Path) -> GridSpec:
    """Read and check a grid file: unknown keys, environments and methods are one-line errors naming the file."""
    import tomllib

    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.methods.registry import METHODS

    path = Path(path)
    if not path.is_file():
        raise BadInput(f"{path}: no such grid file", hint="see docs/cli.md, `cdrb grid`, for the format")
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BadInput(f"{path}: not valid TOML ({exc})", hint="fix the file") from None
    try:
        spec = GridSpec.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = ".".join(str(p) for p in err["loc"]) or "(top level)"
        raise BadInput(f"{path}: {where}: {err['msg']}", hint="see docs/cli.md, `cdrb grid`") from None
    if not spec.out.is_absolute():
        spec.out = (path.parent / spec.out).resolve()
    for env in spec.envs:
        try:
            make_spec(env)
        except BadInput as exc:
            raise BadInput(f"{path}: envs: {exc.message}", hint="`cdrb envs` lists them") from None
    for m in spec.methods:
        METHODS.get(m, f"{path}: methods")
    # settings may name envs and methods the grid does not run (one settings table for several grids), but every
    # name must exist: a typo would silently apply nothing
    for i, s in enumerate(spec.settings):
        if s.env is not None:
            try:
                make_spec(s.env)
            except BadInput as exc:
                raise BadInput(f"{path}: settings[{i}].env: {exc.message}", hint="`cdrb envs` lists them") from None
        if s.method is not None:
            METHODS.get(s.method, f"{path}: settings[{i}].method")
            if s.collect:
                raise BadInput(
                    f"{path}: settings[{i}]: collect flags apply to an environment's demos, which every method shares",
                    hint="put them in an entry without `method`",
                )
    names = [v.name for v in spec.variants]
    if len(set(names)) != len(names):
        raise BadInput(f"{path}: variants: names must differ (got {', '.join(names)})", hint="rename one")
    for v in spec.variants:
        for m in v.methods or []:
            if m not in spec.methods:
                raise BadInput(f"{path}: variant {v.name}: method {m!r} is not one of the grid's methods", hint="fix")
    if len(set(spec.seeds)) != len(spec.seeds) or len(set(spec.envs)) != len(spec.envs):
        raise BadInput(f"{path}: envs and seeds must each be listed once", hint="remove the repeats")
    return spec


# ------------------------------------------------------------------------------------------------ the stage graph
@dataclass
class Task:
    """One `cdrb` command of the grid."""

    id: str
    kind: str
    argv: list[str]
    outputs: list[Path]
    deps: list[str] = field(default_factory=list)
    inputs: list[Path] = field(default_factory=list)


def expand(spec: GridSpec) -> list[Task]:
    """The grid's tasks in an order where every task comes after the tasks it reads from."""
    from cdrb_cli.methods.registry import METHODS

    out, tasks = spec.out, []
    variants = spec.variants or [Variant.model_construct(name="", methods=None, train=[], eval=[])]
    evals: dict[str, list[tuple[str, Path]]] = {v.name: [] for v in variants}
    for env in spec.envs:
        folder = out / env
        demos, buffer = folder / "demos.h5", folder / f"buffer-k{spec.k}.h5"
        collect_id, cluster_id = f"collect {env}", f"cluster {env}"
        collect_extra = [f for s in spec.settings if s.env in (None, env) for f in s.collect]
        tasks.append(
            Task(
                collect_id,
                "collect",
                ["collect", env, "-n", str(spec.demos), "--seed", str(spec.data_seed), *collect_extra]
                + ["--out", str(demos)],
                [demos],
            )
        )
        if any(METHODS.get(m).needs_buffer for m in spec.methods):
            tasks.append(
                Task(
                    cluster_id,
                    "cluster",
                    ["cluster", str(demos), "--k", str(spec.k), "--seed", str(spec.data_seed)] + ["--out", str(buffer)],
                    [buffer],
                    [collect_id],
                    [demos],
                )
            )
        for v in variants:
            vfolder = folder if not v.name else folder / v.name
            for method in spec.methods:
                if v.methods is not None and method not in v.methods:
                    continue
                train_extra, eval_extra = [], []
                for s in spec.settings:
                    if s.env in (None, env) and s.method in (None, method):
                        train_extra += s.train
                        eval_extra += s.eval
                needs_buffer = METHODS.get(method).needs_buffer
                for seed in spec.seeds:
                    tag = f"{env}/{v.name + '/' if v.name else ''}{method}-s{seed}"
                    model, ev = vfolder / f"{method}-s{seed}.h5", vfolder / f"eval-{method}-s{seed}.h5"
                    argv = ["train", str(demos), "--method", method, "--preset", spec.preset, "--seed", str(seed)]
                    argv += ["--buffer", str(buffer)] if needs_buffer else []
                    argv += ["--steps", str(spec.steps)] if spec.steps else []
                    argv += [*train_extra, *v.train, "--out", str(model), "--device", spec.device]
                    deps = [collect_id] + ([cluster_id] if needs_buffer else [])
                    inputs = [demos] + ([buffer] if needs_buffer else [])
                    tasks.append(Task(f"train {tag}", "train", argv, [model], deps, inputs))
                    argv = ["eval", str(model), "--stream", spec.eval_stream, "--seeds", str(seed)]
                    argv += ["--episodes", str(spec.eval_episodes), *eval_extra, *v.eval]
                    argv += ["--out", str(ev), "--device", spec.device]
                    tasks.append(Task(f"eval {tag}", "eval", argv, [ev], [f"train {tag}"], [model]))
                    evals[v.name].append((f"eval {tag}", ev))
    for name, items in evals.items():
        if not items:
            continue
        report = out / ("report.md" if not name else f"report-{name}.md")
        argv = ["report", *[str(p) for _, p in items], "--out", str(report), "--force"]
        tasks.append(
            Task(
                "report" if not name else f"report {name}",
                "report",
                argv,
                [report],
                [i for i, _ in items],
                [p for _, p in items],
            )
        )
    return tasks


# ------------------------------------------------------------------------------------------------ memo
def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", text).strip("_")


def _sha(path: Path, cache: dict) -> str | None:
    if not path.exists():
        return None
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in cache:
        cache[key] = artifacts.sha256_file(path)
    return cache[key]


def memo_path(spec: GridSpec, task: Task) -> Path:
    return spec.out / ".grid" / f"{_slug(task.id)}.json"


def _fingerprint(task: Task, cache: dict) -> dict:
    return {
        "argv": task.argv,
        "cdrb": __version__,
        "inputs": {str(p): _sha(p, cache) for p in task.inputs},
        "outputs": {str(p): _sha(p, cache) for p in task.outputs},
    }


def is_done(spec: GridSpec, task: Task, cache: dict) -> bool:
    """The task's memo matches its command, the cdrb version and every input and output file."""
    path = memo_path(spec, task)
    try:
        memo = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    now = _fingerprint(task, cache)
    return memo == now and all(now["outputs"].values())


def _write_memo(spec: GridSpec, task: Task, cache: dict) -> None:
    path = memo_path(spec, task)
    path.parent.mkdir(parents=True, exist_ok=True)
    with artifacts.atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_fingerprint(task, cache), indent=1))


# ------------------------------------------------------------------------------------------------ execution
def execute(payload: dict) -> dict:
    """Run one task's `cdrb` command in a fresh process (on this machine or a Ray worker). A training whose
    checkpoint was left unfinished by an earlier attempt is continued with ``--resume``."""
    argv = list(payload["argv"])
    if payload["kind"] == "train" and artifacts.unfinished_model(payload["outputs"][0]):
        argv.append("--resume")
    for out in payload["outputs"]:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ, OMP_NUM_THREADS=str(max(1, int(payload["cpus"]))))
    t = time.time()
    proc = subprocess.run([sys.executable, "-m", "cdrb_cli", *argv], capture_output=True, text=True, env=env)
    tail = [ln for ln in proc.stderr.splitlines() if ln.strip()][-STDERR_LINES:]
    return {"rc": proc.returncode, "seconds": time.time() - t, "stderr": tail}


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
    """N local workers, each running one task's process at a time."""

    name = "local pool"

    def __init__(self, workers: int):
        self.workers = workers
        self.pool = cf.ThreadPoolExecutor(max_workers=workers)

    def check(self, spec: GridSpec) -> None:
        pass

    def submit(self, payload: dict) -> cf.Future:
        return self.pool.submit(execute, payload)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class RayBackend:
    """Tasks as Ray tasks with the CPUs/GPUs of their kind; ``address`` None starts Ray on this machine."""

    name = "ray"

    def __init__(self, address: str | None, workers: int | None):
        import ray

        kwargs = {"include_dashboard": False, "log_to_driver": False, "ignore_reinit_error": True}
        if address is None and workers:
            kwargs["num_cpus"] = workers
        ray.init(address=address, **kwargs)
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


def make_backend(backend: str, workers: int | None, address: str | None):
    """``auto``: Ray when it is installed, else the local pool."""
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
            return RayBackend(address, workers)
    if address:
        raise BadInput("--address needs the Ray backend", hint="drop --address or use --backend ray")
    return PoolBackend(workers or max(1, os.cpu_count() or 1))


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
) -> GridRun:
    """Execute the grid's tasks on ``backend``: each when its inputs are ready, skipped when its memo is current,
    retried ``retries`` times on failure; dependants of a failed task are skipped. Writes OUT/grid.json."""
    t0 = time.time()
    tasks = expand(spec)
    results = {t.id: TaskResult(t.id, t.kind, outputs=[str(p) for p in t.outputs]) for t in tasks}
    state = {t.id: "pending" for t in tasks}
    cache: dict = {}
    running: dict[cf.Future, Task] = {}
    emit = on_event or (lambda *_: None)

    def submit(task: Task) -> None:
        res = spec.resources[task.kind]
        payload = {"argv": task.argv, "kind": task.kind, "outputs": [str(p) for p in task.outputs]}
        payload |= {"cpus": res.cpus, "gpus": res.gpus}
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
                        submit(task)
        if not running:
            break
        finished, _ = cf.wait(list(running), return_when=cf.FIRST_COMPLETED)
        for fut in finished:
            task = running.pop(fut)
            res = results[task.id]
            try:
                out = fut.result()
            except Exception as exc:  # the worker itself died (Ray) or could not start the process
                out = {
                    "rc": -1,
                    "seconds": 0.0,
                    "stderr": [f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"],
                }
            res.seconds += out["seconds"]
            if out["rc"] == 0:  # (the hash cache is keyed by size and mtime: rewritten files are hashed afresh)
                _write_memo(spec, task, cache)
                state[task.id], res.status, res.stderr = "done", "done", []
                emit("done", res)
            elif res.attempts <= retries:
                res.stderr = out["stderr"]
                emit("retry", res)
                submit(task)
            else:
                state[task.id], res.status, res.stderr = "failed", "failed", out["stderr"]
                emit("failed", res)
    summary = spec.out / "grid.json"
    spec.out.mkdir(parents=True, exist_ok=True)
    ordered = [results[t.id] for t in tasks]
    body = {
        "seconds": time.time() - t0,
        "backend": backend.name,
        "tasks": [r.__dict__ for r in ordered],
        "counts": {s: sum(r.status == s for r in ordered) for s in ("done", "up to date", "failed", "skipped")},
    }
    with artifacts.atomic_path(summary) as tmp:
        tmp.write_text(json.dumps(body, indent=1, default=str))
    return GridRun(ordered, summary, time.time() - t0, backend.name)


def grid(
    path: Path,
    backend: str = "auto",
    workers: int | None = None,
    address: str | None = None,
    retries: int = 1,
    dry_run: bool = False,
) -> GridRun | list[Task]:
    """Load, expand and run a grid file with a progress bar and one line per finished task (stderr)."""
    spec = load_grid(path)
    tasks = expand(spec)
    if dry_run:
        return tasks
    spec.out.mkdir(parents=True, exist_ok=True)
    with artifacts.claim_output(spec.out / "grid.json", force=True):
        runner = make_backend(backend, workers, address)
        try:
            runner.check(spec)
        except BadInput:
            runner.close()
            raise
        ui.log(f"{len(tasks)} tasks on {runner.name} ({runner.workers} workers/CPUs), artifacts in {spec.out}")
        try:
            with ui.progress() as bar:
                job = bar.add_task("grid", total=len(tasks), info="")

                def on_event(event: str, res: TaskResult) -> None:
                    if event == "retry":
                        why = res.stderr[-1] if res.stderr else "no stderr"
                        ui.log(f"retry   {res.id} (attempt {res.attempts} failed: {why})")
                        return
                    secs = f"{res.seconds:7.1f}s" if event == "done" else " " * 8
                    ui.log(f"{event:10s} {secs}  {res.id}")
                    bar.advance(job)

                run = run_grid(spec, runner, retries=retries, on_event=on_event)
        finally:
            runner.close()
    failed = [r for r in run.results if r.status == "failed"]
    for r in failed:
        ui.warn(f"{r.id} failed after {r.attempts} attempts:\n  " + "\n  ".join(r.stderr or ["(no stderr)"]))
    if failed:
        raise RunFailed(
            f"{len(failed)} of {len(run.results)} grid tasks failed ({', '.join(r.id for r in failed[:3])}"
            f"{', ...' if len(failed) > 3 else ''}); {run.count('skipped')} skipped; details in {run.summary}"
        )
    return run
