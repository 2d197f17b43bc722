"""An eval kept without its plans (:func:`compact_eval`), and a model as a folder anyone can load without cdrb's HDF5
reader: ``model.safetensors`` (every array of the model artifact: the raw and EMA weights, the normaliser, CDRB's
buffer states, the loss curve and the optimiser state a resumed training needs), ``config.json`` (the model's
manifest: the resolved config, the environment spec, the provenance and any settings profile), a ``README.md`` model
card and ``SHA256SUMS``; and the folder back, refused unless every file is the one SHA256SUMS names. Nothing is
pickled: safetensors holds raw tensors and a JSON header."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.artifacts.outputs import check_output_folder, check_writable
from cdrb_cli.errors import BadInput, OutputExists
from cdrb_cli.files import read_input_text, replace_folder, sha256_file
from cdrb_cli.settings import clip

WEIGHTS, CONFIG, CARD, SUMS = "model.safetensors", "config.json", "README.md", "SHA256SUMS"
#: the files a model folder holds besides SHA256SUMS, each listed there
FILES = (WEIGHTS, CONFIG, CARD)
FORMAT = "cdrb-model"
MAX_CONFIG_BYTES = 16 << 20
MAX_SUMS_BYTES = 1 << 16


# ------------------------------------------------------------------------------------------------ export
def compact_eval(ev, out: Path) -> Path:
    """``ev`` (an eval artifact) without its plans, written as ``out``: the same manifest and per-episode records,
    and every measure `cdrb report` takes from the plans kept per episode (computed from them here for an eval
    written before evals stored them), so a report of the compact eval is the report of ``ev`` in a file a
    fraction of its size: the form in which a table's evals are kept beside it. An eval without plans (a policy's,
    or one written with ``--no-plans``) is copied as it was written."""
    from cdrb_cli.artifacts import RECOMPUTE_BEFORE, parse_version
    from cdrb_cli.stages.plan_metrics import plan_measures

    version, current = ev.manifest.schema_version, artifacts.SCHEMA_VERSIONS["eval"]
    if parse_version(version) > parse_version(current):
        raise BadInput(f"{ev.path}: written by eval schema {version}, newer than this cdrb's {current}",
                       hint="compact it with the cdrb that wrote it")  # fmt: skip
    if parse_version(version) < RECOMPUTE_BEFORE["eval"]:
        raise BadInput(f"{ev.path}: eval schema {version} measured less than today's evals, which grids redo",
                       hint="evaluate the model again (`cdrb eval`), then compact that eval")  # fmt: skip
    if "plans" not in ev.arrays:  # a policy's eval, or one written with --no-plans: nothing to drop, kept as written
        from cdrb_cli.files import atomic_path

        with atomic_path(out) as tmp:
            shutil.copyfile(ev.path, tmp)
        return Path(out)
    arrays = {name: a for name, a in ev.arrays.items() if name != "plans"}
    arrays = {**plan_measures(ev.manifest.env, ev.arrays["plans"]), **arrays}
    # the same eval (its provenance says when and by what it ran), in today's layout, which its reader migrated to
    manifest = ev.manifest.model_copy(update={"schema_version": current})
    artifacts.save(out, "eval", manifest, arrays)
    return Path(out)


def export_folder(model, folder: Path, evals: Sequence = (), force: bool = False) -> Path:
    """Write ``model`` (a model artifact) as the folder ``folder``, whole or not at all (written beside it, then
    renamed); ``evals``: eval artifacts of this model whose figures the model card lists."""
    folder = check_output_folder(folder, "--dir", [getattr(model, "path", None), *(ev.path for ev in evals)])
    if folder.is_dir() and any(folder.iterdir()) and not force:
        raise OutputExists(
            f"--dir {folder}: exists and is not empty", folder, hint="pass --force to replace it, or another --dir"
        )
    others = sorted(p.name for p in folder.iterdir() if p.name not in (*FILES, SUMS)) if folder.is_dir() else []
    if others:  # --force replaces a model folder, never a folder of other files (they would be deleted with it)
        raise BadInput(
            f"--dir {folder}: holds files a model folder does not ({', '.join(others[:3])})",
            hint="choose an empty or new --dir, or one an earlier export wrote",
        )
    seen = {}
    for ev in evals:
        if not any(p.kind == "model" and p.data_sha256 == model.data_sha256 for p in ev.manifest.parents):
            raise BadInput(f"--eval {ev.path}: evaluates another model", hint="pass the evals of this model")
        if ev.data_sha256 in seen:  # the card would list its figures twice, as if two evals agreed
            raise BadInput(f"--eval {ev.path}: the same eval as --eval {seen[ev.data_sha256]}", hint="pass it once")
        seen[ev.data_sha256] = ev.path
    parent = folder.absolute().parent  # as for every --out: its folder exists and takes new files
    if not parent.is_dir():
        raise BadInput(f"--dir {folder}: folder {parent} does not exist", hint="create it or choose another path")
    check_writable(parent, "--dir", folder)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        manifest = model.manifest.model_copy(update={"schema_version": artifacts.SCHEMA_VERSIONS["model"]})
        from safetensors.numpy import save_file

        # np.require keeps a 0-d array 0-d (an optimizer's step); np.ascontiguousarray would make it (1,)
        arrays = {name: np.require(a, requirements="C") for name, a in sorted(model.arrays.items())}
        meta = {"format": FORMAT, "schema_version": manifest.schema_version}
        save_file(arrays, str(tmp / WEIGHTS), metadata=meta)
        (tmp / CONFIG).write_text(json.dumps(manifest.model_dump(mode="json"), indent=1, sort_keys=True) + "\n")
        (tmp / CARD).write_text(model_card(model, evals))
        (tmp / SUMS).write_text("".join(f"{sha256_file(tmp / name)}  {name}\n" for name in FILES))
        for name in (*FILES, SUMS):
            with open(tmp / name, "rb") as fh:
                os.fsync(fh.fileno())
        replace_folder(tmp, folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder


def model_card(model, evals: Sequence = ()) -> str:
    """The folder's README: what the model is, what it was trained on and for how long, and what was measured."""
    m = model.manifest
    cfg, st = m.config, m.state
    demos = next((p for p in m.parents if p.kind == "demos"), None)
    lines = [
        f"# {cfg.method.name} on {m.env.id}",
        "",
        f"A cdrb model: `{cfg.method.name}` planning on `{m.env.id}` ({m.env.obs_dim}-dimensional states, plans of "
        f"{cfg.horizon} states every {cfg.stride} env steps), trained with cdrb {m.cdrb_version}.",
        "",
        "| what | value |",
        "|---|---|",
        f"| network | {cfg.net.kind}, {st.parameters:,} parameters |",
        f"| training | {st.step:,} of {cfg.steps:,} steps ({'finished' if st.finished else 'unfinished'}), preset "
        f"{cfg.preset}, seed {cfg.seed}, {st.wall_time_s:,.0f} s |",
        f"| loss | {st.loss:.4g}" + (f", validation {st.valid_loss:.4g}" if st.valid_loss is not None else "") + " |",
        f"| data | {Path(demos.path).name if demos else '(none recorded)'}"
        + (f" (data sha256 {demos.data_sha256 or demos.sha256})" if demos else "")
        + " |",
    ]
    if m.profile is not None:
        lines.append(f"| settings profile | {m.profile.file} ({m.profile.chosen or 'chosen'}) |")
    lines += ["", "## Measured", ""]
    if evals:
        lines += ["| protocol | pairs | success (%) | plans through an obstacle (%) |", "|---|---|---:|---:|"]
        for ev in evals:
            c, s = ev.manifest.config, ev.manifest.summary
            through = "" if s.plan_crossing_mean is None else f"{100 * s.plan_crossing_mean:.1f}"
            lines.append(
                f"| {c.protocol} | {c.stream}, seeds {','.join(map(str, c.seeds))} x {c.episodes} | "
                f"{100 * s.success_mean:.1f} ± {100 * s.success_std:.1f} | {through} |"
            )
    else:
        lines.append("No evaluation was exported with it (`cdrb export MODEL --dir DIR --eval EVAL.h5`).")
    lines += [
        "",
        "## Use",
        "",
        "```bash",
        "cdrb import model THIS_FOLDER --out model.h5     # the model artifact, bit for bit the same arrays",
        "cdrb plan model.h5 --pairs 4 --plot plans.png",
        "```",
        "",
        'or in Python, `cdrb_cli.api.Planner("THIS_FOLDER")`. `model.safetensors` holds every array by its '
        "artifact name (`ema/net/...` the weights plans use, `weights/net/...` the raw ones, `normalizer/low` and "
        "`high`, `buffer/points` for CDRB's buffer); `config.json` is the model's manifest; `SHA256SUMS` the files' "
        "sha256.",
        "",
    ]
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------ import
def _checked_files(folder: Path) -> None:
    """Every file of the folder is the one SHA256SUMS names (a changed, missing or extra listing is refused)."""
    if not folder.is_dir():
        raise BadInput(f"{folder}: not a folder", hint="pass the folder `cdrb export MODEL --dir DIR` wrote")
    text = read_input_text(folder / SUMS, "model folder", MAX_SUMS_BYTES, "checksum list", "export the model again")
    listed = {}
    for line in text.splitlines():
        sha, _, name = line.partition("  ")
        if len(sha) != 64 or name not in FILES or name in listed:
            raise BadInput(f"{folder / SUMS}: {clip(repr(line), 80)} is not a line it writes",
                           hint="export the model again")  # fmt: skip
        listed[name] = sha
    missing = [n for n in FILES if n not in listed]
    if missing:
        raise BadInput(f"{folder / SUMS}: does not list {missing[0]}", hint="export the model again")
    for name, sha in listed.items():
        path = folder / name
        if path.is_symlink():  # a folder is shared whole: a link would read a file from outside it
            raise BadInput(f"{path}: a symbolic link", hint="copy the file itself into the folder")
        if not path.is_file():
            raise BadInput(f"{path}: missing", hint="copy the whole folder `cdrb export` wrote")
        if sha256_file(path) != sha:
            raise BadInput(f"{path}: its sha256 is not the one {SUMS} lists: changed since it was exported",
                           hint="export the model again")  # fmt: skip


def read_folder(folder: Path):
    """The manifest and arrays of a model folder, checked against SHA256SUMS and the model schema."""
    from pydantic import ValidationError

    folder = Path(folder)
    _checked_files(folder)
    text = read_input_text(folder / CONFIG, "model folder", MAX_CONFIG_BYTES, "config", "export the model again")
    try:
        data = json.loads(text)
    except (ValueError, RecursionError):
        raise BadInput(f"{folder / CONFIG}: not JSON", hint="export the model again") from None
    if not isinstance(data, dict) or data.get("kind") != "model":
        raise BadInput(f"{folder / CONFIG}: not a model's manifest", hint="export the model again")
    try:
        manifest = artifacts.KINDS["model"].manifest_cls.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise BadInput(f"{folder / CONFIG}: {where}: {first['msg']}", hint="export the model again") from None
    from safetensors import SafetensorError
    from safetensors.numpy import load_file

    try:
        arrays = load_file(str(folder / WEIGHTS))
    except (SafetensorError, OSError, ValueError) as exc:
        raise BadInput(f"{folder / WEIGHTS}: not a safetensors file ({clip(str(exc), 80)})",
                       hint="export the model again") from None  # fmt: skip
    for name, arr in arrays.items():  # what every artifact refuses to hold, named here as the folder's fault
        if arr.dtype.kind == "f" and not artifacts.in_bounds(arr):
            raise BadInput(f"{folder / WEIGHTS}: tensor {clip(name, 60)} holds non-finite or out-of-range values",
                           hint="export the model again")  # fmt: skip
    return manifest, arrays


def import_folder(folder: Path, out: Path, force: bool = False):
    """The model folder written as the model artifact ``out`` (checked as every artifact read is: its arrays'
    shapes and their agreement with the manifest; and its weights load into the network its config builds, so an
    edited config is refused here, not at the first plan), whole or not at all."""
    from cdrb_cli.methods.checkpoint import load_method

    manifest, arrays = read_folder(folder)
    with artifacts.atomic_path(out) as tmp:
        artifacts.save(tmp, "model", manifest, arrays)
        model = artifacts.load(tmp, "model")
        try:
            load_method(model, "cpu")
        except BadInput as exc:
            said = exc.message.removeprefix(f"{model.path}: ")  # the temporary file's name means nothing here
            raise BadInput(
                f"{Path(folder) / CONFIG}: {said}", hint="export the model again: its config and weights disagree"
            ) from None
    model.path = Path(out)  # the same bytes, renamed into place
    return model


def check_finished(model, allow_partial: bool, flag: str = "--allow-partial") -> None:
    """Refuse a model whose training stopped before its last step (a checkpoint), unless ``allow_partial``; then
    only warn. ``flag`` names how the caller allows it (the CLI's flag, the API's argument)."""
    from cdrb_cli import ui

    st, steps = model.manifest.state, model.manifest.config.steps
    if st.finished:
        return
    if not allow_partial:
        raise BadInput(
            f"{model.path}: training stopped at step {st.step} of {steps} (an unfinished checkpoint)",
            hint=f"finish it with `cdrb train ... --resume`, or pass {flag}",
        )
    ui.warn(f"{model.path}: an unfinished training, used at its checkpoint (step {st.step} of {steps})")


def load_model(path: Path):
    """The model artifact at ``path``: a model file, or a folder of `cdrb export --dir` (read through a checked
    temporary artifact)."""
    path = Path(path)
    try:
        folder = path.is_dir()
    except OSError:  # e.g. a name too long: the artifact reader says so in its words
        folder = False
    if not folder:
        return artifacts.load(path, "model")
    with tempfile.TemporaryDirectory(prefix="cdrb-model-") as tmp:
        model = import_folder(path, Path(tmp) / "model.h5")
    model.path = path
    return model
