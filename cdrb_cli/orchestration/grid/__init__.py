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

import importlib

#: each name the package offers -> the module that defines it, imported on first use: `cdrb` imports the grid's
#: command catalogue (grid.commands) at start-up, and every command but grid and select would otherwise pay for
#: the whole grid machinery (its configs, spec, runner) before it starts
_EXPORTS = {
    **dict.fromkeys(
        ["BASE", "cluster_flags_for", "collect_flags_for", "expand", "flags_for", "without_repeated_sets"], "expansion"
    ),
    **dict.fromkeys(["as_table", "parse_command", "walk_options", "without_setting"], "flags"),
    **dict.fromkeys(["load_grid", "parse_override"], "load"),
    **dict.fromkeys(["changed_input", "check_outputs", "is_done", "memo_path", "written_here"], "memo"),
    **dict.fromkeys(["file_sha", "measure_difference", "reuse_finished"], "reuse"),
    **dict.fromkeys(
        [
            "DryRun",
            "GridRun",
            "PoolBackend",
            "RayBackend",
            "TaskResult",
            "execute",
            "grid",
            "make_backend",
            "run_grid",
            "stop_running",
        ],
        "run",
    ),
    **dict.fromkeys(
        ["GridSpec", "KINDS", "MAX_TASKS", "Settings", "SettingsFile", "Task", "Variant", "read_toml", "table_flags"],
        "spec",
    ),
}


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])


__all__ = sorted(_EXPORTS)
