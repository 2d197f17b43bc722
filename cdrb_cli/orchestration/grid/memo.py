"""Memos: what each task wrote (the key of what its command asks for, the cdrb version, the sha256 of every input
and output), so a rerun does no work for a task whose files still match, however its flags are spelled."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
from pathlib import Path

from cdrb_cli import __version__, artifacts
from cdrb_cli.errors import BadInput
from cdrb_cli.files import regular_fd
from cdrb_cli.orchestration.grid.commands import keyed_params
from cdrb_cli.orchestration.grid.flags import parse_command
from cdrb_cli.orchestration.grid.spec import GridSpec, Task, read_small


# ------------------------------------------------------------------------------------------------ memo
def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", text).strip("_")


def cached_sha(path: Path, cache: dict) -> str | None:
    if not path.exists():
        return None
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in cache:
        cache[key] = artifacts.sha256_file(path)
    return cache[key]


def memo_path(spec: GridSpec, task: Task) -> Path:
    return spec.out / ".grid" / f"{_slug(task.id)}.json"


def log_path(spec: GridSpec, task: Task) -> Path:
    """Where a local task's stderr goes while it runs and stays after it (its progress lines, its errors)."""
    return spec.out / ".grid" / "logs" / f"{_slug(task.id)}.log"


#: how much of the end of a task's log is read back: its last progress line, the lines a failure reports
LOG_TAIL = 64 << 10
#: terminal control sequences (CSI, OSC) and the other C0 controls a task may write into its log
_CONTROL = re.compile(
    r"\x1b\[[0-?]*[ -/]*[@-~]"  # CSI: colours, erase-line, cursor moves
    r"|\x1b\][^\x07\x1b]*(?:\x07|\x1b\\)?"  # OSC: links, titles
    r"|\x1b.?|[\x00-\x08\x0b\x0c\x0e-\x1f\x7f]"  # other escapes, C0 controls but tab and line ends
)


def _own_folder(folder: Path) -> None:
    """Make the grid's log folder (OUT/.grid/logs); a link at it or at OUT/.grid is refused, not followed."""
    for d in (folder.parent, folder):
        if d.is_symlink():
            raise BadInput(f"{d}: a link, not a folder of the grid's own", hint="remove it; the grid makes it")
        d.mkdir(exist_ok=True, parents=d == folder.parent)


def fresh_log(path: Path) -> None:
    """An empty log file at ``path`` for a task's next attempt, made by the grid before it hands the task over.
    The last attempt's log, a regular file, is kept beside it as ``NAME.1`` (why a retried task failed stays
    readable); a link or anything else planted at the name is removed, never written through."""
    _own_folder(path.parent)
    with contextlib.suppress(FileNotFoundError):
        if path.is_file() and not path.is_symlink():
            os.replace(path, path.with_name(path.name + ".1"))
        else:
            path.unlink()
    os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o644))


def open_log(path: str | Path) -> int:
    """A descriptor appending to the task log ``path`` (see :func:`~cdrb_cli.files.regular_fd`); the caller
    closes it."""
    return regular_fd(path, os.O_WRONLY | os.O_APPEND)


def read_log(path: str | Path, tail: int = LOG_TAIL) -> str:
    """The last ``tail`` bytes of a task's log as text, terminal control sequences removed ("" when it cannot be
    read as a regular file)."""
    try:
        fd = regular_fd(path, os.O_RDONLY)
    except OSError:
        return ""
    with os.fdopen(fd, "rb") as f:
        f.seek(max(0, f.seek(0, 2) - tail))
        data = f.read(tail)
    return _CONTROL.sub("", data.decode(errors="replace").replace("\r\n", "\n").replace("\r", "\n"))


def last_line(path: str | Path, tail: int = 4096) -> str:
    """The last non-blank line of a task's log (a live bar's redraws end with a carriage return, plain progress
    lines with a newline), or "" when there is none yet."""
    lines = [ln.strip() for ln in read_log(path, tail).split("\n")]
    return next((ln for ln in reversed(lines) if ln), "")


def _meaning(task: Task) -> dict:
    """What a command means beyond its words, where a release changed it, so a memo written when it meant something
    else is out of date: a plan or an eval in a scene avoids the new obstacles by default (the family's tuned
    avoidance), an eval that re-plans uses the family's choice for re-planning, and an eval under a protocol of
    starts anywhere the family's choice for plans from anywhere."""
    from cdrb_cli.envs.registry import FAMILIES

    if task.kind not in ("plan", "eval"):
        return {}
    _, given, sets = parse_command(task.argv)
    out = {}
    if given.get("maze_map") is not None:
        out["scene_avoid"] = "tuned by default"
    replans = [v for k, v in sets if k in ("replan", "replan.mode")]
    if any(v.strip("\"'") != "never" for v in replans):
        out["replan_tuned"] = "by default"
    tuned = [f for f in FAMILIES.builtin_entries() if f.start_tuned]
    anywhere = {p for f in tuned for p in f.start_protocols}
    if any(k == "protocol" and v.strip("\"'") in anywhere for k, v in sets):
        out["start_tuned"] = {f.name: f.start_tuned for f in tuned}  # a changed default makes the memo stale
    return out


def command_key(argv: list[str]) -> tuple[dict, str]:
    """What a task's command asks for, however its flags are spelled (:func:`parse_command`: its arguments, the
    options that change what it makes or measures, and its settings resolved to one value each), and the sha256 of
    that: the memo's key. The command resolves its full config from these settings, its input files (hashed beside
    the key) and the cdrb version (recorded beside it), so the same key with the same inputs is the same config."""
    positional, given, sets = parse_command(argv)
    keyed = keyed_params(argv[0])
    asked = {
        "command": argv[0],
        "args": positional,
        "options": {k: given[k] for k in sorted(given) if k in keyed},
        "settings": [list(kv) for kv in sets],
    }
    return asked, hashlib.sha256(json.dumps(asked, sort_keys=True, default=str).encode()).hexdigest()


def _fingerprint(task: Task, cache: dict) -> dict:
    asked, key = command_key(task.argv)
    return {
        "argv": task.argv,
        "key": key,
        "asked": asked,
        "cdrb": __version__,
        **_meaning(task),
        "inputs": {str(p): cached_sha(p, cache) for p in task.inputs},
        "outputs": {str(p): cached_sha(p, cache) for p in task.outputs},
    }


def _matches(memo: dict, now: dict) -> bool:
    """Whether a memo records what ``now`` would: the same key, version, meaning and files; the command line as
    spelled (``argv``, kept for the record) need not match. A memo written before memos had keys is judged by the
    key of the command line it records."""
    memo = dict(memo)
    argv = memo.get("argv")
    if "key" not in memo and isinstance(argv, list) and argv and all(isinstance(a, str) for a in argv):
        try:
            memo["asked"], memo["key"] = command_key(argv)
        except Exception:  # a command line this version cannot read: out of date
            return False
    return {k: v for k, v in memo.items() if k != "argv"} == {k: v for k, v in now.items() if k != "argv"}


def _memo(spec: GridSpec, task: Task) -> dict | None:
    """The task's memo, or None (a memo that is not a small regular file of JSON is stale: the task is redone)."""
    text = read_small(memo_path(spec, task))
    try:
        memo = json.loads(text) if text is not None else None
    except (ValueError, RecursionError):
        return None
    return memo if isinstance(memo, dict) else None


def is_done(spec: GridSpec, task: Task, cache: dict) -> bool:
    """The task's memo matches its command, the cdrb version and every input and output file."""
    memo = _memo(spec, task)
    if memo is None:
        return False
    now = _fingerprint(task, cache)
    return _matches(memo, now) and all(now["outputs"].values())


def changed_input(spec: GridSpec, task: Task, cache: dict) -> str | None:
    """An input file the task's memo recorded that is here now with other bytes (a settings file edited since the
    grid ran the task, data made again), or None; files not here, and tasks without a memo, are not judged."""
    from cdrb_cli.orchestration.grid.reuse import regular_sha  # it imports this module

    memo = _memo(spec, task)
    recorded = memo.get("inputs") if memo is not None else None
    for path, sha in recorded.items() if isinstance(recorded, dict) else ():
        now = regular_sha(path, cache) if isinstance(path, str) and isinstance(sha, str) else None
        if now is not None and now != sha:
            return path
    return None


def up_to_date(spec: GridSpec, tasks: list[Task], cache: dict) -> dict[str, bool]:
    """Which tasks a run would skip: those whose memo is current and whose dependencies would all be skipped too (a
    dependency that runs again may rewrite what the task read, so the task runs after it, as the run decides)."""
    by_id = {t.id: t for t in tasks}
    fresh: dict[str, bool] = {}

    def visit(task: Task) -> bool:
        if task.id not in fresh:
            deps = [by_id[d] for d in task.deps if d in by_id]
            fresh[task.id] = all(
                visit(d)
                or (all(visit(by_id[i]) for i in d.deps if i in by_id) and _reads_only_kept(spec, task, d, cache))
                for d in deps
            ) and is_done(spec, task, cache)  # (a dependency whose own inputs are redone keeps nothing)
        return fresh[task.id]

    for task in tasks:
        visit(task)
    return fresh


def _reads_only_kept(spec: GridSpec, task: Task, dep: Task, cache: dict) -> bool:
    """Whether ``task`` reads only outputs of ``dep`` that ``dep``, run again, leaves as they are: snapshots of a
    training that resumes (:func:`_kept_snapshot`), such as the evals of a learning curve's early points when the
    curve is extended."""
    read = [str(p) for p in task.inputs if p in dep.outputs]
    return bool(read) and all(_kept_snapshot(spec, dep, path, cache) for path in read)


def _kept_snapshot(spec: GridSpec, train: Task, path: str, cache: dict) -> bool:
    """Whether the training task ``train``, run again, keeps its output ``path``: a snapshot that the run its memo
    records wrote (the same bytes now), at a step before the one that run reached, when the command asks for what
    that run did up to its length and snapshots, with the same inputs (so it resumes that run, never starts over,
    and writes only snapshots past its checkpoint)."""
    import re

    found = re.search(r"\.step(\d+)\.h5$", path)
    memo = _memo(spec, train) if train.kind == "train" and found else None
    if memo is None or not isinstance(memo.get("asked"), dict) or not isinstance(memo.get("outputs"), dict):
        return False
    now = _fingerprint(train, cache)

    def run_of(asked: dict) -> dict:  # what a run is, whatever its length and snapshots
        options = asked.get("options") if isinstance(asked.get("options"), dict) else {}
        settings = asked.get("settings") if isinstance(asked.get("settings"), list) else []
        return {**asked, "options": {k: v for k, v in options.items() if k != "snapshot_at"},
                "settings": [kv for kv in settings if not (isinstance(kv, list) and kv[:1] == ["steps"])]}  # fmt: skip

    reached = [kv[1] for kv in memo["asked"].get("settings") or [] if isinstance(kv, list) and kv[:1] == ["steps"]]
    return (
        run_of(memo["asked"]) == run_of(now["asked"])
        and memo.get("inputs") == now["inputs"]
        and memo["outputs"].get(path) is not None
        and memo["outputs"].get(path) == now["outputs"].get(path)
        and len(reached) == 1
        and str(reached[0]).isdigit()
        and int(found.group(1)) < int(reached[0])
    )


def written_here(spec: GridSpec, task: Task, cache: dict) -> bool:
    """Whether the task's main output, and every other output that is here, is the file this grid's memo says the
    task wrote: the grid's own artifact, which it may replace when the task is out of date (a file the memo does
    not vouch for is never overwritten). The memo may list more or fewer outputs than the task has now (a training's
    snapshots asked for or dropped with another change)."""
    memo = _memo(spec, task)
    recorded = memo.get("outputs") if memo is not None else None
    if not isinstance(recorded, dict) or not task.outputs:
        return False
    now = {str(p): cached_sha(p, cache) for p in task.outputs}
    here = {p: sha for p, sha in now.items() if sha is not None}
    return str(task.outputs[0]) in here and all(recorded.get(p) == sha for p, sha in here.items())


def write_memo(spec: GridSpec, task: Task, cache: dict) -> None:
    path = memo_path(spec, task)
    path.parent.mkdir(parents=True, exist_ok=True)
    with artifacts.atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_fingerprint(task, cache), indent=1))


def check_outputs(spec: GridSpec, tasks: list[Task]) -> None:
    """Before any work: no task and no summary may write over the grid file or a settings file it read, and
    OUT/grid.json, which every run rewrites, must be a grid summary if it exists (not a file of the user's)."""
    if spec.out.exists() and not spec.out.is_dir():
        raise BadInput(f"out = {spec.out}: is a file, not a folder", hint="choose a folder for the grid's artifacts")
    sources = {p.resolve() for p in spec._sources}
    summary = spec.out / "grid.json"
    folders: set[Path] = set()
    for out in [summary] + [p for t in tasks for p in t.outputs]:
        if out.resolve() in sources:
            raise BadInput(f"{out}: the grid would write over its own input file", hint="choose another `out` folder")
        folders.update(f for f in out.parents if f.is_relative_to(spec.out) and f != spec.out)
    for folder in sorted(folders):  # an environment's or a variant's folder that is a file: every task there fails
        if folder.exists() and not folder.is_dir():
            raise BadInput(f"{folder}: is a file where the grid keeps a folder of artifacts",
                           hint="move the file away, or choose another `out` folder")  # fmt: skip
    if summary.exists():
        text = read_small(summary, 1 << 26)
        try:
            body = json.loads(text) if text is not None else None
        except (ValueError, RecursionError):
            body = None
        if not isinstance(body, dict) or not {"tasks", "counts"} <= body.keys():
            raise BadInput(
                f"{summary}: exists and is not a grid summary; a grid run writes its summary there",
                hint="move the file or choose another `out` folder",
            )
