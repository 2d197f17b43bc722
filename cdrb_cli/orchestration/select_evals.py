"""Which evals `cdrb select` may score for a tuning grid's task: the eval the task's command makes, on the task's
environment, written for the task's place in the grid, of a model of the task's training length, and (where the
model is here) that model, trained as the grid trains it. Evals are read on machines other than the one that made
them, so files are compared by name and place, not by where they lie."""

from __future__ import annotations

import functools
from pathlib import Path

from cdrb_cli import artifacts
from cdrb_cli.errors import BadInput
from cdrb_cli.orchestration.grid import GridSpec, parse_command
from cdrb_cli.settings import clip


def _command(artifact) -> list[str]:
    """The `cdrb` command line an artifact records, from its command on: cdrb's own options (-q, --debug) before
    the command left out."""
    argv = list(artifact.manifest.argv[1:])
    while argv and argv[0].startswith("-"):
        argv.pop(0)
    return argv


def _without_length(argv: list[str]) -> list[str]:
    """A training's command line without how long it trains and where it keeps snapshots (a curve's stages differ
    in these alone; the eval's record of its model's steps is checked on its own)."""
    from cdrb_cli.orchestration.grid.commands import options
    from cdrb_cli.orchestration.grid.flags import walk_options

    kept = [argv[0]]
    for token, entry, value in walk_options(argv[1:], options("train")):
        if entry is not None and entry.param in ("steps", "snapshot_at"):
            continue
        if entry is not None and entry.param == "sets" and str(value).partition("=")[0].strip() == "steps":
            continue
        kept += [token] if entry is None or not entry.takes_value or "=" in token or value is None else [token, value]
    return kept


def checked_eval(
    spec: GridSpec,
    task,
    path: Path,
    unchecked: list[Path] | None = None,
    trains: dict | None = None,
    makers: dict | None = None,
):
    """The eval artifact at a task's output, refused unless it is what the task measures: the same command but for
    where files lie (:func:`grid.measure_difference`), a model of the task's training length (a run's final model
    keeps its name when a curve is extended), and, where the model it evaluated is here, that same model (the same
    bytes or, as every stage judges an input, the same data) trained as the grid's training task (``trains``: task
    by output) trains it, on the data the grid's collect and cluster tasks (``makers``: task by output) make, where
    those files are here (:func:`_check_data`). "Here" is the grid's own path, else the path the eval (or the
    model) records with the bytes it records: a model reused from another grid, or moved. An eval that records no
    training length, of a model that is not here, is appended to ``unchecked``."""
    from cdrb_cli.orchestration.grid import changed_input, file_sha, measure_difference

    ev = artifacts.load(path, "eval")
    made = _command(ev)
    why = measure_difference(made, task.argv)
    if why is not None:
        raise BadInput(
            f"{path}: not this grid's eval ({task.id}): {why}",
            hint="run `cdrb select` with the --set/--include the grid ran with; if they are the same, the grid "
            "measures this eval again once it is moved away",
        )
    # the command compares files by name: an eval copied from another env's, variant's or grid's folder reads the
    # same there, so the environment it ran and the place it was written for in its grid are compared too
    env, ran = task.meta.get("env"), ev.manifest.env.id
    # an eval among obstacles of its own (--scene) names the env it ran "<env>+<the scene's name>"
    in_scene = ran.startswith(f"{env}+") and parse_command(task.argv)[1].get("maze_map") is not None
    if env is not None and ran != env and not in_scene:
        raise BadInput(
            f"{path}: an eval on {clip(ran, 60)}, where this grid's task ({task.id}) measures {env}",
            hint="move it away and run `cdrb grid` on the same file, which measures the model there",
        )
    written, place = parse_command(made)[1].get("out"), _place(spec, path)
    if written is not None and place is not None and Path(written).parts[-len(place.parts) :] != place.parts:
        raise BadInput(
            f"{path}: written as {clip(written, 120)}, for another place in a grid than {place}",
            hint="an eval copied from another variant's or seed's folder: move it away and run `cdrb grid` on the "
            "same file, which measures the model there",
        )
    model = own = task.inputs[0]
    steps, trained = task.meta.get("steps"), ev.manifest.summary.model_steps
    if steps is not None and trained is not None and trained != steps:
        raise BadInput(
            f"{path}: evaluates {model.name} after {trained} training steps; this grid's task ({task.id}) measures "
            f"it after {steps}",
            hint="an eval from before the run was extended: move it away and run `cdrb grid` on the same file, which "
            "measures the model at its length",
        )
    parent = next((p for p in ev.manifest.parents if p.kind == "model"), None)
    here = file_sha(model, spec._shas)
    if here is None and parent is not None:  # none at the grid's path: the model the eval read, if it is here
        model, here = _recorded(parent, spec._shas) or (model, None)
    if steps is not None and trained is None and here is None and unchecked is not None:
        unchecked.append(path)
    train = (trains or {}).get(own)
    model_here = functools.cache(lambda: artifacts.load(model, "model"))  # read once, and only where it is asked for
    if parent is not None and here is not None and parent.sha256 != here:
        if not artifacts.same_inputs([parent], [model_here()]):
            raise BadInput(
                f"{path}: evaluates another {model.name} than the one in {model.parent}",
                hint="run `cdrb grid` on the same file (same --set/--include): it measures the model there again",
            )
    if train is not None and here is not None:  # the model here, trained with other flags than the grid's now
        trained_by = _command(model_here())
        why = measure_difference(_without_length(trained_by), _without_length(train.argv)) if trained_by else None
        if why is not None:
            raise BadInput(
                f"{path}: its model {model.name} was not trained as this grid's task ({train.id}) trains it: {why}",
                hint="run `cdrb select` with the --set/--include the grid ran with",
            )
    if train is not None and here is not None:
        for data in train.inputs:
            if data in (makers or {}):
                _check_data(spec, path, model_here(), data, makers[data])
    # the command compares a settings file (--config) by name: one edited since the grid ran the task changed
    # what the task asks for, as the grid's own memo of it tells
    for t in filter(None, (task, train)):
        edited = changed_input(spec, t, spec._shas)
        if edited is not None:
            raise BadInput(
                f"{path}: {clip(edited, 120)} changed since the grid ran {t.id} with it",
                hint="run `cdrb grid` on the same file first: it runs again what the change makes out of date",
            )
    return ev


def trained_alike(evals: list) -> None:
    """Refuse one candidate's evals (its training seeds) whose models were trained with other settings, by the
    digest each eval records of its model's training: caught even where the model files are no longer there."""
    first = next((ev for ev in evals if ev.manifest.summary.model_training is not None), None)
    for ev in evals:
        digest = ev.manifest.summary.model_training
        if first is not None and digest is not None and digest != first.manifest.summary.model_training:
            raise BadInput(
                f"{ev.path}: evaluates a model trained with other settings than {first.path}'s (net, learning rate, "
                "method parameters...), which this grid trains alike as seeds of one run",
                hint="run `cdrb grid` on the same file (same --set/--include): it trains and measures them again",
            )


#: the artifact kind each data-making task writes
_MADE = {"collect": "demos", "cluster": "buffer"}


def _check_data(spec: GridSpec, path: Path, model, data: Path, maker) -> None:
    """A file the grid's ``maker`` task writes (demos, a buffer) and the eval's ``model`` was trained on, where it
    is here: the model was trained on what it holds now, and it holds what the task's command makes (a setting of
    the data changed, as `--set demos=...`, makes both the data and the models out of date)."""
    from cdrb_cli.orchestration.grid import file_sha, measure_difference

    kind, sha = _MADE.get(maker.kind), file_sha(data, spec._shas)
    recorded = [p for p in model.manifest.parents if p.kind == kind]
    if kind is not None and sha is None and recorded:  # none at the grid's path: what the model read, if here
        data, sha = _recorded(recorded[0], spec._shas) or (data, None)
    if kind is None or sha is None:
        return
    held = _data(data, kind, sha)
    made = _command(held)
    why = measure_difference(made, maker.argv) if made else None
    if why is not None:
        raise BadInput(
            f"{path}: its model was trained on {data}, which was not made as this grid's task ({maker.id}) makes "
            f"it: {why}",
            hint="run `cdrb select` with the --set/--include the grid ran with, or run `cdrb grid` on it first",
        )
    if recorded and not artifacts.same_inputs(recorded[:1], [held]):
        raise BadInput(
            f"{path}: its model was trained on other {kind} than {data} holds now",
            hint="run `cdrb grid` on the same file: it trains and measures the models on the data there again",
        )


def _recorded(parent, cache: dict) -> tuple[Path, str] | None:
    """(path, sha256) of the input an artifact records, where that file is here with the bytes it read: the file a
    reused or moved artifact was made from when the grid's own path holds none."""
    from cdrb_cli.orchestration.grid import file_sha

    there = Path(parent.path)
    return (there, parent.sha256) if file_sha(there, cache) == parent.sha256 else None


@functools.lru_cache(maxsize=8)
def _data(path: Path, kind: str, sha: str):
    """A data artifact (``sha``: its file's, so a file rewritten since is read again), read once for all the evals
    whose models were trained on it."""
    return artifacts.load(path, kind)


def _place(spec: GridSpec, path: Path) -> Path | None:
    """``path`` relative to the grid's ``out`` (ENV/[VARIANT/]eval-...h5), or None outside it."""
    try:
        return Path(path).resolve().relative_to(Path(spec.out).resolve())
    except ValueError:
        return None
