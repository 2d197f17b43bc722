"""Studies as files: run a grid of commands, and choose settings on the tuning stream (`cdrb select`)."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import (
    ForceOpt,
    GridIncludeOpt,
    GridSetOpt,
    JsonOpt,
    app,
    choice,
    file_path,
)
from cdrb_cli.errors import BadInput


# ------------------------------------------------------------------------------------------------ select
@app.command()
def select(
    grid_file: Path = typer.Argument(..., help="A tuning grid (TOML) whose evals `cdrb grid` has run."),
    out: Path = typer.Option(
        ...,
        "--out",
        "-o",
        metavar="FILE",
        help="The settings file to write (TOML), for test grids to include.",
        parser=file_path,
    ),
    table: Path | None = typer.Option(
        None,
        "--table",
        metavar="FILE",
        help="Also write every candidate's scores: CSV (.csv) or a markdown table (other names).",
        parser=file_path,
    ),
    curves: Path | None = typer.Option(
        None,
        "--curves",
        metavar="FILE",
        help="Also write the learning curves as CSV: one row per candidate, training length and training seed "
        "(success, weighted success, success without collision, plans through an obstacle, collisions; per cent).",
        parser=file_path,
    ),
    docs: Path | None = typer.Option(
        None,
        "--docs",
        metavar="FILE",
        help="Also write what was chosen (one line per environment, a column per method: tuning success ± std, "
        "training length, plans through an obstacle) into FILE between <!-- BLOCK:begin --> and "
        "<!-- BLOCK:end --> (with --block).",
        parser=file_path,
    ),
    block: str | None = typer.Option(None, "--block", metavar="NAME", help="The marked block of --docs to replace."),
    overrides: list[str] = GridSetOpt,
    includes: list[Path] = GridIncludeOpt,
    force: bool = ForceOpt,
) -> None:
    """Choose each method's settings on the tuning stream from a tuning grid's evals, and write them as a settings
    file that test grids `include`.

    Candidates are the grid's variants (training settings, or eval-only knobs on one model) at each training length
    of its learning curves (`snapshot_at`). The rule, per environment x method: highest tuning success, then fewest
    plans through an obstacle, then fewest executed collisions, then the grid's variant order, then fewest training
    steps. Prints the path of the settings file."""
    from cdrb_cli.orchestration.select import select as run_select

    if (docs is None) != (block is None):
        raise BadInput("--docs and --block go together", hint="e.g. --docs README.md --block tuning-fetch")
    if block is not None:
        from cdrb_cli.stages.docs_blocks import check_block_name

        check_block_name(block)
    options = dict(force=force, table=table, curves=curves, overrides=overrides, includes=includes)
    ui.emit(run_select(grid_file, out, docs=docs, block=block, **options))


# ------------------------------------------------------------------------------------------------ grid
@app.command()
def grid(
    grid_file: Path = typer.Argument(..., help="Grid file (TOML): envs x methods x seeds (x variants)."),
    backend: str = typer.Option(
        "auto",
        "--backend",
        parser=choice(lambda: ["auto", "ray", "pool"], "backend"),
        help='Where tasks run: ray (needs `pip install "cdrb-cli\\[ray]"`), pool (local processes), auto (Ray '
        "when installed).",
    ),
    workers: int | None = typer.Option(
        None, "--workers", "-j", min=1, help="Local pool: parallel tasks; local Ray: CPUs it may use (default: all)."
    ),
    address: str | None = typer.Option(
        None, "--address", help="A running Ray cluster, e.g. ray://head:10001 (default: start Ray on this machine)."
    ),
    retries: int = typer.Option(
        1,
        "--retries",
        min=0,
        help="Re-runs of a failed task before it is reported (one that refused its input, exit 2, is not re-run).",
    ),
    dry_run: bool = typer.Option(
        False,
        "--dry-run",
        help="Print the tasks' commands, one per line, those a run would skip as up to date after '# up to date: ' "
        "(with --json a list of tasks), and stop.",
    ),
    overrides: list[str] = GridSetOpt,
    includes: list[Path] = GridIncludeOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Run a grid of experiments: collect -> cluster -> train -> eval -> report for every environment, method,
    seed and variant of GRID_FILE, in parallel on Ray or a local pool.

    Tasks whose artifacts are up to date are not run again, so a grid stopped half-way continues where it
    stopped; a failed task is retried (a training resumes from its checkpoint) and then reported, while the
    others go on. Prints the path of the summary (OUT/grid.json). Format and examples: docs/cli.md.
    """
    from cdrb_cli.orchestration.grid import grid as run_grid_file

    res = run_grid_file(
        grid_file,
        backend=backend,
        workers=workers,
        address=address,
        retries=retries,
        dry_run=dry_run,
        overrides=overrides,
        includes=includes,
    )
    if dry_run:
        import shlex

        todo = res.pending()
        kinds = [t.kind for t in todo]
        ui.log(
            f"{len(res.tasks)} tasks: {len(res.tasks) - len(todo)} up to date, {len(todo)} to run"
            + (": " + ", ".join(f"{kinds.count(k)} {k}" for k in dict.fromkeys(kinds)) if kinds else "")
        )
        if as_json:  # one object per task: what it is, its command, what it writes, the tasks it waits for
            rows = [
                {
                    "id": t.id,
                    "kind": t.kind,
                    "argv": t.argv,
                    "outputs": [str(p) for p in t.outputs],
                    "deps": t.deps,
                    "up_to_date": res.up_to_date[t.id],
                }
                for t in res.tasks
            ]
            ui.emit(rows, as_json=True)
            return
        for task in res.tasks:  # a task a run would skip is a shell comment: the listing stays a runnable script
            mark = "# up to date: " if res.up_to_date[task.id] else ""
            sys.stdout.write(mark + "cdrb " + shlex.join(task.argv) + "\n")
        return
    ui.log(
        f"grid finished in {res.seconds / 60:.1f} min: {res.count('done')} run, {res.count('up to date')} up to date"
    )
    if as_json:
        import json

        ui.emit(json.loads(res.summary.read_text()), as_json=True)
    else:
        ui.emit(res.summary)
