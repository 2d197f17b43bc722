"""Reuse across grids: a finished run of another grid (the same command and inputs, or a snapshot of a longer
training) linked in instead of redone, and how two command lines differ in what they measure."""

from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path

from cdrb_cli import __version__
from cdrb_cli.errors import BadInput
from cdrb_cli.orchestration.grid.commands import keyed_params, options
from cdrb_cli.orchestration.grid.flags import last_value_wins, parse_command
from cdrb_cli.orchestration.grid.memo import cached_sha
from cdrb_cli.orchestration.grid.spec import GridSpec, Task, read_small
from cdrb_cli.settings import clip

# ------------------------------------------------------------------------------------------------ reuse
#: how long a training runs: matched apart (a snapshot at S steps is the model a run of S steps writes)
_LENGTH = ("steps", "snapshot_at")
REUSABLE = ("collect", "cluster", "train")


def _real(path: str | Path) -> str:
    """A file's path with links resolved (``runs`` may be a link to another disk): one spelling per file."""
    return os.path.realpath(path)


def regular_sha(path: str, cache: dict) -> str | None:
    """The sha256 of a regular file, else None (a folder, a FIFO or a missing file is never hashed)."""
    try:
        return cached_sha(Path(path), cache) if stat.S_ISREG(os.stat(path).st_mode) else None
    except OSError:
        return None


def file_sha(path: str | Path, cache: dict) -> str | None:
    """The sha256 of the regular file at ``path`` (links resolved), else None; ``cache`` is the grid's."""
    return regular_sha(_real(path), cache)


def _command_key(argv: list[str], written_by: dict[str, str], cache: dict) -> tuple[str, str | None, list[str]]:
    """What a collect/cluster/train command makes, independent of where and of how its flags are spelled
    (:func:`parse_command`, every file written by a task replaced by the key of the command that wrote it and every
    other file by its sha256, with only the options that change what it makes, its length apart); its ``--steps``;
    its ``--snapshot-at`` steps."""

    def file_key(value: str) -> str:
        real = _real(value)
        if real in written_by:
            return written_by[real]
        sha = regular_sha(real, cache)
        return f"sha256:{sha}" if sha else value

    positional, given, sets = parse_command(argv, file_key)
    steps = dict(sets).get("steps")
    sets = [(k, v) for k, v in sets if k != "steps"]
    snaps = [v.strip() for v in str(given.get("snapshot_at", "")).split(",") if v.strip()]
    keyed = keyed_params(argv[0])
    kept = {k: v for k, v in given.items() if k in keyed and k not in _LENGTH}
    key = json.dumps([argv[0], positional, sorted(kept.items()), sets], default=str)
    return key, None if steps is None else str(steps), snaps


def measure_difference(made: list[str], wanted: list[str]) -> str | None:
    """How the command that made an eval (``made``, as its manifest records it) differs in what it measures from the
    command a grid's task runs (``wanted``), or None: files are compared by name (evals are read on machines other
    than the one that ran them), and options that only say where the output goes, on what device, or what more it
    keeps (plans, videos) do not count."""
    if not made or made[0] != wanted[0]:
        what = f"`cdrb {clip(made[0], 40)}`" if made else "no cdrb command"
        return f"it records {what}, not `cdrb {wanted[0]}`"
    spelled = {}  # parameter name -> the option as the help spells it
    for option, info in reversed(list(options(wanted[0]).items())):
        if option.startswith("--"):
            spelled[info.param] = option
    keyed = keyed_params(wanted[0])
    (pos_a, opt_a, sets_a), (pos_b, opt_b, sets_b) = (
        parse_command(argv, lambda v: Path(v).name if os.sep in v else v) for argv in (made, wanted)
    )
    if pos_a != pos_b:
        return f"it reads {clip(' '.join(pos_a) or '(nothing)', 80)}, the grid's task {' '.join(pos_b)}"
    for name in sorted(set(opt_a) | set(opt_b)):
        a, b = opt_a.get(name), opt_b.get(name)
        if name in keyed and a != b:
            shown = ["(not given)" if v is None else clip(str(v), 40) for v in (a, b)]
            return f"{spelled.get(name, name)} {shown[0]} there, {shown[1]} in the grid"
    for key in sorted({k for k, _ in sets_a} | {k for k, _ in sets_b}):
        a, b = dict(sets_a).get(key), dict(sets_b).get(key)
        if a != b:
            shown = ["(not set)" if v is None else clip(v, 40) for v in (a, b)]
            return f"setting {clip(key, 60)}: {shown[0]} there, {shown[1]} in the grid"
    if sets_a != sets_b:
        return "its --set values come in another order"
    return None


def _is_step(text: str) -> bool:
    return text.isascii() and text.isdigit()


def _finished_elsewhere(folders: list[Path], cache: dict) -> list[dict]:
    """The finished collect/cluster/train tasks of the grids whose ``out`` folders are ``folders``, from their
    memos: each memo of this cdrb version whose input and output files are all regular files that still have the
    sha256 it recorded, collections first, then clusterings, then trainings (a key names what its inputs' tasks
    are, in whichever folder). A memo of any other shape is skipped."""
    found = []
    for folder in folders:
        memos = folder / ".grid"
        for memo_file in sorted(memos.glob("*.json")) if memos.is_dir() else []:
            text = read_small(memo_file)
            try:
                memo = json.loads(text) if text is not None else None
            except (ValueError, RecursionError):
                continue
            if not isinstance(memo, dict) or memo.get("cdrb") != __version__:
                continue
            argv, inputs, outputs = memo.get("argv"), memo.get("inputs"), memo.get("outputs")
            if not (isinstance(argv, list) and argv and all(isinstance(a, str) for a in argv)):
                continue
            files = [inputs, outputs]
            if argv[0] not in REUSABLE or not all(
                isinstance(f, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in f.items())
                for f in files
            ):
                continue
            if not outputs or any(regular_sha(p, cache) != v for p, v in {**inputs, **outputs}.items()):
                continue
            found.append(memo)
    return sorted(found, key=lambda m: REUSABLE.index(m["argv"][0]))


def _setting_file(token: str) -> tuple[str, str] | None:
    """(key, path) of a ``--set`` value that names a file as a JSON string (``avoid.route_buffer="/x/b.h5"``),
    else None."""
    key, eq, value = token.partition("=")
    if not eq or key.startswith("-") or not value.startswith('"'):
        return None
    try:
        text = json.loads(value)
    except ValueError:
        return None
    return (key, text) if isinstance(text, str) and text else None


def _replace_files(argv: list[str], moved: dict[str, str]) -> list[str]:
    """``argv`` with every file of ``moved`` (a token, the value of ``--flag=FILE``, or a setting's quoted value
    ``key="FILE"``) replaced."""
    out = []
    for a in argv:
        name, eq, value = a.partition("=")
        setting = _setting_file(a)
        if eq and name.startswith("--") and _real(value) in moved:
            out.append(f"{name}={moved[_real(value)]}")
        elif setting is not None and _real(setting[1]) in moved:
            out.append(f"{setting[0]}={json.dumps(moved[_real(setting[1])])}")
        else:
            out.append(moved.get(_real(a), a))
    return out


def reuse_finished(spec: GridSpec, tasks: list[Task]) -> list[Task]:
    """``tasks`` with every collection, clustering and training that a grid of ``spec.reuse`` has finished taken
    from there: the task is dropped and the tasks that read its artifact read the other grid's file. A training
    matches a finished one of the same command (:func:`_command_key`) whose final model or snapshots include every
    step this one writes. Records what was taken in ``spec._reused`` (task id -> file), and on every task that
    reads a taken file the sha256 it must still have when the task runs (``meta["expect"]``)."""
    cache = spec._shas
    spec._reused = {}
    written_by: dict[str, str] = {}  # a file of the other grids -> the key of what wrote it
    offers: dict[str, list[dict[str, str]]] = {}  # key -> [steps -> file]
    shas: dict[str, str] = {}  # a file of the other grids -> its sha256 as its memo recorded it
    for memo in _finished_elsewhere(spec.reuse, cache):
        key, steps, snaps = _command_key(memo["argv"], written_by, cache)
        outputs = list(memo["outputs"])
        points = {str(steps): outputs[0]}
        if memo["argv"][0] == "train":
            for s in filter(_is_step, snaps):
                snap = str(train_snapshot(Path(outputs[0]), int(s)))
                if snap in outputs:
                    points[s] = snap
        for p in outputs:
            written_by[_real(p)] = key
            shas[p] = memo["outputs"][p]
        offers.setdefault(key, []).append(points)

    own_written_by: dict[str, str] = {}
    moved: dict[str, str] = {}  # this grid's file (links resolved) -> the other grid's
    dropped: dict[str, list[str]] = {}  # task id -> its files
    for t in tasks:
        if t.kind not in REUSABLE:
            continue
        key, steps, snaps = _command_key(t.argv, own_written_by, cache)
        for p in t.outputs:
            own_written_by[_real(p)] = key
        if not all(map(_is_step, snaps)):
            continue
        wanted = [str(steps)] + (snaps if t.kind == "train" else [])
        files = [str(t.outputs[0])] + [str(train_snapshot(t.outputs[0], int(s))) for s in snaps]
        if len(files) != len(t.outputs):
            continue
        for points in offers.get(key, []):
            if all(w in points for w in wanted):
                moved.update({_real(f): points[w] for f, w in zip(files, wanted, strict=True)})
                dropped[t.id] = [_real(f) for f in files]
                break
    if not dropped:
        return tasks
    kept = []
    for t in tasks:
        if t.id in dropped:
            continue
        t.argv = _replace_files(t.argv, moved)
        t.inputs = [Path(moved.get(_real(p), p)) for p in t.inputs]
        t.deps = [d for d in t.deps if d not in dropped]
        expect = {str(p): shas[str(p)] for p in t.inputs if str(p) in shas}
        if expect:
            t.meta = t.meta | {"expect": expect}
        kept.append(t)
    # nothing kept may still name a file that is no longer written here
    gone = {f for files in dropped.values() for f in files}
    for t in kept:
        named = [a.partition("=")[2] if a.startswith("--") else a for a in t.argv] + [str(p) for p in t.inputs]
        named += [s[1] for s in map(_setting_file, t.argv) if s is not None]
        left = [n for n in named if n and _real(n) in gone]
        if left:
            raise BadInput(
                f"reuse: {t.id} still names {left[0]}, which a reused task no longer writes here",
                hint="drop `reuse` from the grid, or name the file in the grid as it names its outputs",
            )
    spec._reused = {tid: moved[files[0]] for tid, files in dropped.items()}
    return kept


def buffer_task(spec: GridSpec, env: str, flags: list[str], buffers: dict, tasks: list[Task]) -> tuple[str, Path]:
    """The cluster task and buffer of ``env``'s demos clustered with ``flags``, added to ``tasks`` on first use:
    runs with the same flags share one buffer (none: ``buffer-kK.h5``; else ``buffer-<hash of the flags>.h5``, since
    the flags may change k). An option named twice counts once, with its last value (:func:`last_value_wins`); a
    buffer a grid already made under the name the repeated flags give keeps that name, so its runs stay done."""
    given, flags = flags, last_value_wins(flags, "cluster")
    folder = spec.out / env
    key, tag = json.dumps(flags), _flags_tag(flags)
    if given != flags and (folder / f"buffer-{_flags_tag(given)}.h5").exists():
        # made before folding under the name of these very flags: that buffer (and the runs that read it) stays,
        # even where other flags of the grid fold to the same line and keep theirs
        key, tag = json.dumps(given), _flags_tag(given)
    if key not in buffers:
        demos = folder / "demos.h5"
        path = folder / (f"buffer-{tag}.h5" if flags else f"buffer-k{spec.k}.h5")
        task_id = f"cluster {env}" + (f"/{tag}" if tag else "")
        options = last_value_wins(["--k", str(spec.k), "--seed", str(spec.data_seed), *flags], "cluster")
        argv = ["cluster", str(demos), *options, "--out", str(path)]
        tasks.append(Task(task_id, "cluster", argv, [path], [f"collect {env}"], [demos]))
        buffers[key] = (task_id, path)
    return buffers[key]


def _flags_tag(flags: list[str]) -> str:
    return hashlib.sha256(json.dumps(flags).encode()).hexdigest()[:8] if flags else ""


def train_snapshot(model: Path, step: int) -> Path:
    from cdrb_cli.stages.train import snapshot_path

    return snapshot_path(model, step)
