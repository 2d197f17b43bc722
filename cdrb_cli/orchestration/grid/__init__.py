"""`cdrb grid GRID.toml`: a declarative grid of runs, expanded into the stage graph and executed in parallel.

A grid file names environments x methods x seeds (and optional variants: named sets of extra flags, one more axis).
It expands into tasks, each one `cdrb` command that writes one artifact:

    collect ENV  ->  cluster ENV  ->  train ENV/[VARIANT/]METHOD-sSEED  ->  eval ...  ->  report [VARIANT]

A task runs when the tasks it reads from have finished, each in a process of its own: on **Ray** a `python -m
cdrb_cli ...` process (a local Ray of its own, or ``--address`` for a cluster; each task asks for the CPUs and
GPUs of its kind), on the local pool of N workers a fork of a warm server that imported cdrb and its libraries once
(:mod:`~cdrb_cli.orchestration.grid.warm`: 3-4 s less per task). Every artifact is written atomically by the
command itself, so a killed task leaves either nothing or a valid artifact (a training leaves its last
checkpoint); a failed task is retried once (a training with ``--resume``), then reported with the tail of its
stderr, and the tasks that do not depend on it go on.

Re-running a grid does no work for a task whose memo (``OUT/.grid/TASK.json``: the command, the cdrb version and
the sha256 of every input and output artifact) still matches the files; any other task is handed to the command,
which skips it when its artifact is up to date (the CLI's own rule) and resumes an unfinished training.
"""

from __future__ import annotations

from cdrb_cli.orchestration.grid.expand import (
    BASE,
    cluster_flags_for,
    collect_flags_for,
    expand,
    flags_for,
    without_repeated_sets,
)
from cdrb_cli.orchestration.grid.flags import as_table, parse_command, walk_options, without_setting
from cdrb_cli.orchestration.grid.load import load_grid, parse_override
from cdrb_cli.orchestration.grid.memo import check_outputs, is_done, memo_path, written_here
from cdrb_cli.orchestration.grid.reuse import file_sha, measure_difference, reuse_finished
from cdrb_cli.orchestration.grid.run import (
    DryRun,
    GridRun,
    PoolBackend,
    RayBackend,
    TaskResult,
    execute,
    grid,
    make_backend,
    run_grid,
    stop_running,
)
from cdrb_cli.orchestration.grid.spec import (
    KINDS,
    MAX_TASKS,
    GridSpec,
    Settings,
    SettingsFile,
    Task,
    Variant,
    read_toml,
    table_flags,
)

__all__ = [
    "BASE",
    "DryRun",
    "GridRun",
    "GridSpec",
    "KINDS",
    "MAX_TASKS",
    "PoolBackend",
    "RayBackend",
    "Settings",
    "SettingsFile",
    "Task",
    "TaskResult",
    "Variant",
    "as_table",
    "check_outputs",
    "cluster_flags_for",
    "collect_flags_for",
    "execute",
    "expand",
    "file_sha",
    "flags_for",
    "grid",
    "is_done",
    "load_grid",
    "make_backend",
    "measure_difference",
    "memo_path",
    "parse_command",
    "parse_override",
    "read_toml",
    "reuse_finished",
    "run_grid",
    "stop_running",
    "table_flags",
    "walk_options",
    "without_repeated_sets",
    "without_setting",
    "written_here",
]
