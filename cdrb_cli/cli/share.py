"""`cdrb export` and `cdrb import model`: demonstrations as a Minari dataset, a model as a folder of safetensors
weights, its config as JSON and a model card, and such a folder back as a model artifact."""

from __future__ import annotations

from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import ForceOpt, JsonOpt, app, check_import_out, file_path, load_artifact
from cdrb_cli.cli.data import import_app
from cdrb_cli.errors import BadInput


@app.command("export")
def export_cmd(
    artifact: Path = typer.Argument(
        ..., help="A demos artifact (with --minari), a model artifact (with --dir) or an eval (with --compact)."
    ),
    minari: str | None = typer.Option(
        None, "--minari", help="Demos: the dataset name, [namespace/]name[-vN] (-v0 is added), e.g. cdrb/maze-tight."
    ),
    folder: Path | None = typer.Option(
        None, "--dir", help="A model: the folder to write (model.safetensors, config.json, README.md, SHA256SUMS)."
    ),
    evals: list[Path] = typer.Option(
        [], "--eval", help="With --dir: an eval artifact of this model, listed in the model card (repeatable)."
    ),
    root: Path | None = typer.Option(
        None, "--root", help="With --minari: the datasets folder (default: MINARI_DATASETS_PATH, else ~/.minari)."
    ),
    compact: Path | None = typer.Option(
        None,
        "--compact",
        help="An eval: the file to write it to without its plans, every figure of them kept.",
        parser=file_path,
    ),
    force: bool = typer.Option(False, "--force", help="Replace a dataset of the same name, a folder or a file."),
) -> None:
    """Export a [bold]demos[/bold] artifact as a Minari dataset, a [bold]model[/bold] as a folder anyone can
    load without cdrb's HDF5 reader, or an [bold]eval[/bold] without its plans.

    --minari NAME: observations are goal dicts (observation, achieved_goal, desired_goal), the reward is cdrb's
    success test (as a sparse reward) and infos["success"] has it per step; the env_spec is the gymnasium equivalent
    of the environment where one exists (PointMaze with this map, Fetch without walls); `minari.load_dataset(NAME)`
    opens it. --dir DIR: model.safetensors (every array by its artifact name: raw and EMA weights, normaliser,
    CDRB's buffer states), config.json (the manifest: resolved config, environment, provenance), a README model card
    (with --eval, the figures measured) and SHA256SUMS; `cdrb import model DIR` and `api.Planner(DIR)` load it.
    --compact FILE: an [bold]eval[/bold] without its plans (a tenth of a Fetch eval's size), with what `cdrb
    report` measures on them (first steps, plans through an obstacle by body and through new ones) kept per
    episode, so its report is the same: how a table's evals are kept beside it (one with no plans, e.g. a policy's,
    is copied as it is).
    Example: [cyan]cdrb export runs/t/eval-cdrb-s0.h5 --compact kept/eval-cdrb-s0.h5[/cyan]

    Prints the folder or file written."""
    if sum(x is not None for x in (minari, folder, compact)) != 1:
        raise BadInput("give one of --minari NAME (a demos artifact), --dir DIR (a model) or --compact FILE (an eval)",
                       hint="`cdrb export --help` says what each writes")  # fmt: skip
    if evals and folder is None:
        raise BadInput("--eval lists an eval in a model folder's card: it goes with --dir DIR",
                       hint="drop --eval, or export the model with --dir")  # fmt: skip
    if root is not None and minari is None:
        raise BadInput("--root is where Minari datasets go: it goes with --minari NAME", hint="drop --root")
    if compact is not None:
        from cdrb_cli.artifacts import check_output
        from cdrb_cli.stages.share import compact_eval

        check_output(compact, force, "--compact", [artifact])
        ev = load_artifact(artifact, "eval")
        out = compact_eval(ev, compact)
        kept = "without their plans" if "plans" in ev.arrays else "as they were (the eval holds no plans)"
        ui.log(f"{len(ev.arrays['episodes/seed'])} episodes written {kept}")
        ui.emit(out)
        return
    if minari is not None:
        from cdrb_cli.stages.minari_io import dataset_id_for, export_minari

        art = load_artifact(artifact, "demos")
        out = export_minari(art, minari, root=root, force=force)
        ui.log(f"{art.n_episodes} episodes written as Minari dataset {dataset_id_for(minari)}")
        ui.emit(out)
        return
    from cdrb_cli.stages.share import export_folder

    model = load_artifact(artifact, "model")
    ev = [load_artifact(p, "eval") for p in evals]
    out = export_folder(model, folder, ev, force=force)
    ui.log(f"{model.manifest.config.method.name} on {model.manifest.env.id} written to {out}")
    ui.emit(out)


@import_app.command("model")
def import_model(
    folder: Path = typer.Argument(..., help="A model folder of `cdrb export MODEL --dir DIR`."),
    out: Path = typer.Option(Path("model.h5"), "--out", "-o", help="Model artifact to write.", parser=file_path),
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Import a model folder (`cdrb export --dir`) as a [bold]model[/bold] artifact: the same arrays and manifest,
    so the same plans. Refused unless every file is the one its SHA256SUMS lists and the manifest and arrays are a
    valid model's. Example: [cyan]cdrb import model shared/cdrb-maze-tight --out model.h5[/cyan]"""
    from cdrb_cli.stages.share import import_folder

    check_import_out(force, out, folder)
    model = import_folder(folder, out)
    ui.log(f"{model.manifest.config.method.name} on {model.manifest.env.id}: {len(model.arrays)} arrays")
    ui.emit({"path": str(out), "data_sha256": model.data_sha256} if as_json else out, as_json=as_json)
