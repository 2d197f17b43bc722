"""Commands over many artifacts: report a comparison, and the quickstart pipeline."""

from __future__ import annotations

import sys
from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import (
    DeviceOpt,
    ForceOpt,
    SeedOpt,
    app,
    check_outputs,
    check_positive,
    choice,
    file_path,
    load_artifact,
    parse_seeds,
)
from cdrb_cli.errors import BadInput


# ------------------------------------------------------------------------------------------------ report
@app.command()
def report(
    evals: list[Path] = typer.Argument(
        ..., help="Eval artifacts (any number; rows = environments, columns = methods)."
    ),
    fmt: str = typer.Option(
        "table",
        "--format",
        parser=choice(lambda: ["table", "markdown", "summary", "csv", "json"], "format"),
        metavar="table|markdown|summary|csv|json",
        help="table, markdown, summary (markdown, a line per environment: the straight line's success as the floor, "
        "each method's success and weighted success, marked where it does not beat the floor), csv or json.",
    ),
    paper: bool = typer.Option(False, "--paper", help="Add the paper's Table 1 figures under ours."),
    paper_figures: Path | None = typer.Option(
        None, "--paper-figures", metavar="FILE", help="With --paper: read the figures from FILE (TOML) instead."
    ),
    per_seed: bool = typer.Option(
        False, "--per-seed", help="One row per eval file and evaluation seed instead of one per environment x method."
    ),
    docs: Path | None = typer.Option(
        None,
        "--docs",
        metavar="FILE",
        help="Write the markdown report into FILE between <!-- BLOCK:begin --> and <!-- BLOCK:end --> (with --block).",
        parser=file_path,
    ),
    block: str | None = typer.Option(None, "--block", metavar="NAME", help="The marked block of --docs to replace."),
    out: Path | None = typer.Option(
        None, "--out", "-o", help="Write the report to this file (else stdout).", parser=file_path
    ),
    plot: Path | None = typer.Option(
        None, "--plot", help="Bar chart of success and planned-in-obstacle rates (PNG).", parser=file_path
    ),
    plans_plot: Path | None = typer.Option(
        None, "--plans-plot", help="Every method's plans for the same pairs (PNG).", parser=file_path
    ),
    force: bool = ForceOpt,
) -> None:
    """Compare eval artifacts in a Table-1-style report (success mean ± std over seeds, plus planned states in
    obstacles, executed collisions, path length and planning time), with optional pictures.

    Evals of one environment must share a protocol (episodes, start/goal protocol, stream); the seeds of one
    method must also share every eval setting (controller, sampler...) and training; mixing is an error."""
    from cdrb_cli.stages import docs_blocks, report_figures
    from cdrb_cli.stages import report as rep
    from cdrb_cli.stages.report_summary import render_summary

    if (docs is None) != (block is None):
        raise BadInput("--docs and --block go together", hint="e.g. --docs docs/benchmarks.md --block table1-mazes")
    if block is not None:
        docs_blocks.check_block_name(block)
    if docs is not None and fmt not in ("markdown", "table", "summary"):
        raise BadInput(f"--docs writes markdown, not --format {fmt}", hint="drop --format or write it with --out")
    if paper_figures is not None and not paper:
        raise BadInput("--paper-figures goes with --paper", hint="add --paper, or drop --paper-figures")
    if paper and per_seed:
        raise BadInput(
            "--paper adds the paper's rows to the grouped report, and --per-seed lists one row per file and seed",
            hint="drop one of them (the paper's figures are means over seeds)",
        )
    read = [*evals, *([] if paper_figures is None else [paper_figures])]
    check_outputs(force, read, docs=docs, out=out, plot=plot, plans_plot=plans_plot)
    if out is not None:
        from cdrb_cli.artifacts import check_output

        check_output(out, force, "--out", read)
    figures = rep.paper_figures(paper_figures) if paper else False
    arts = [load_artifact(p, "eval") for p in evals]
    # per-seed rows list every file as it is; the grouped rows (and their bar chart) need one protocol per env
    rows = rep.collect_rows(arts) if not per_seed or plot is not None else []
    if per_seed:
        if fmt == "summary":
            raise BadInput("--per-seed has no summary format", hint="use --format table, markdown, csv or json")
        text = rep.render_seed_rows(rep.seed_rows(arts), fmt)
    elif fmt == "summary":
        text = render_summary(rows, paper=figures)
    else:
        text = rep.render(rows, "markdown" if docs is not None else fmt, paper=figures)
    # every check before the first file is written: a bad --docs block or evals without plans leave nothing behind
    if plans_plot is not None:
        report_figures.with_plans(arts)
    if docs is not None:
        docs_blocks.check_docs_block(docs, block, text, read)
    from cdrb_cli.files import together

    with together():  # the pictures, the page and the report land together or not at all
        if plot is not None:
            report_figures.plot_bars(rows, plot)
        if plans_plot is not None:
            report_figures.plot_side_by_side(arts, plans_plot)
        if docs is not None:
            docs_blocks.write_docs_block(docs, block, text, read)
        if out is not None:
            from cdrb_cli.artifacts import atomic_path, claim_output

            with claim_output(out, force, "--out", read), atomic_path(out) as tmp:
                tmp.write_text(text)
    for picture in (plot, plans_plot):
        if picture is not None:
            ui.log(f"picture: {picture}")
    if out is not None:
        ui.emit(out)
    elif docs is not None:
        ui.emit(docs)
    else:
        sys.stdout.write(text)


# ------------------------------------------------------------------------------------------------ quickstart
@app.command()
def quickstart(
    out: Path = typer.Option(Path("runs/quickstart"), "--out", "-o", help="Folder for every artifact and picture."),
    env: str | None = typer.Option(None, "--env", help="Environment id (default: Maze Tight; `cdrb envs`)."),
    episodes: int = typer.Option(
        2000,
        "--episodes",
        min=2,
        help="Demonstrations to collect (see --starts).",
    ),
    starts: str | None = typer.Option(
        None,
        "--starts",
        metavar="WHERE",
        help="Where demonstrations start: protocol+anywhere (default: half from the environment's starts, half "
        "anywhere, so the models also plan from where a re-plan finds the robot) or protocol (the paper's data).",
    ),
    k: int | None = typer.Option(None, "--k", min=0, help="Buffer size after k-means (default 1000; 0 = full)."),
    methods: str | None = typer.Option(
        None, "--methods", help="Methods to train and compare, comma-separated (default: CDRB and Diffuser)."
    ),
    seeds: str = typer.Option(
        "5,6,7",
        "--seeds",
        help="Evaluation seeds of the test stream (default 5,6,7: pairs no setting was chosen on; Table 1 uses 0-4).",
    ),
    eval_episodes: int = typer.Option(50, "--eval-episodes", min=1, help="Episodes per evaluation seed."),
    steps: int | None = typer.Option(None, "--steps", help="Training steps per method (quick preset: 3000)."),
    videos: int = typer.Option(0, "--videos", min=0, help="Rollout GIFs per method (0: none)."),
    device: str = DeviceOpt,
    seed: int = SeedOpt,
) -> None:
    """Run the whole pipeline on Maze Tight: collect -> cluster -> train CDRB and Diffuser (quick; the states after a
    plan's start weigh 10x, so plans leave from where the robot is) -> eval -> report. 3-9 minutes on 2 CPU cores.
    Re-running skips every stage that is up to date; an interrupted run resumes where it stopped. Prints the results
    table and the paths of the pictures."""
    if videos:
        from cdrb_cli.envs.render import choose_gl_backend

        choose_gl_backend()
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.orchestration.quickstart import DEFAULT_ENV, DEFAULT_METHODS, check_methods
    from cdrb_cli.orchestration.quickstart import quickstart as run_quickstart
    from cdrb_cli.torch_utils import setup_torch

    method_list = tuple(m.strip() for m in methods.split(",") if m.strip()) if methods is not None else DEFAULT_METHODS
    check_methods(method_list, "--methods")
    try:
        spec = make_spec(env or DEFAULT_ENV)
    except BadInput as exc:
        raise BadInput(f"--env {env}: {exc.message}", hint="`cdrb envs` lists them") from None
    if out.exists() and not out.is_dir():
        raise BadInput(f"--out {out}: exists and is not a folder", hint="pass a folder path")
    check_positive("--steps", steps)
    most = episodes * spec.episode_limit  # the states the demos can hold at most: a larger --k is a typo
    if k is not None and k > most:
        raise BadInput(f"--k {k}: more than the {most:,} states {episodes} demos can hold at most",
                       hint="use --k 1000, the default, or 0 for the full buffer")  # fmt: skip
    res = run_quickstart(
        out,
        env=env or DEFAULT_ENV,
        episodes=episodes,
        starts=starts,
        k=k,
        methods=method_list,
        seeds=tuple(parse_seeds(seeds, "--seeds")),
        eval_episodes=eval_episodes,
        steps=steps,
        seed=seed,
        device=setup_torch(device),
        videos=videos,
    )
    ui.log(f"done in {res.seconds / 60:.1f} min; artifacts in {res.folder}/")
    sys.stdout.write(res.report)
    sys.stdout.write("\n" + "\n".join(str(p) for p in res.pictures) + "\n")
