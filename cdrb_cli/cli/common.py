"""What every command of the CLI shares: the typer app, the common options, choices read from the registries,
and the checks of inputs and outputs made before any work."""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path

import typer

from cdrb_cli import PROG, __version__, ui
from cdrb_cli.errors import BadInput

#: what `--help` shows for a value of each Python type typer names (a flag shows nothing)
READABLE = {"bool": "", "int": "N", "float": "X", "str": "TEXT", "path": "FILE", "file": "FILE", "directory": "DIR"}


def readable_help() -> None:
    """Help that names values as a person reads them (N, X, FILE, TEXT, DEMOS) instead of Python types (``<int>``,
    ``<list[str]>``, ``{demos}``). Typer has no hook for its type labels, so its two label methods are wrapped."""
    import re

    from typer import core

    base = getattr(core, "_TyperParameter", None)
    if base is None or not hasattr(core, "TyperArgument"):  # another typer layout: keep its own labels
        return
    label = base.display_type

    def display_type(self, ctx) -> str:
        text = label(self, ctx)
        m = re.fullmatch(r"<(list\[)?(\w+)(?: range)?\]?>", text)
        if m is None:
            return text
        word = READABLE.get(m.group(2).lower(), m.group(2).upper())
        return f"{word}..." if m.group(1) and word else word

    def usage_name(self) -> str:
        name = (self.metavar or self.name or "").upper()
        name = name if self.required else f"[{name}]"
        return name + ("..." if self.nargs != 1 else "")

    base.display_type = display_type
    core.TyperArgument._usage_display_name = usage_name


readable_help()

app = typer.Typer(
    name=PROG,
    help="Cold Diffusion on the Replay Buffer: plan robot trajectories through states the robot has visited.\n\n"
    "Pipeline: collect -> cluster -> train -> plan / eval -> report. Every stage writes a versioned HDF5 "
    "artifact (inspect any of them with `cdrb inspect FILE`). `cdrb quickstart` runs the whole pipeline.",
    add_completion=True,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    rich_markup_mode="rich",
    context_settings={"help_option_names": ["-h", "--help"]},
)

SeedOpt = typer.Option(
    0, "--seed", min=0, max=2**32 - 1, help="Random seed (32-bit); the same seed and inputs give the same artifact."
)
ForceOpt = typer.Option(False, "--force", help="Overwrite --out if it exists (otherwise an existing file is an error).")
JsonOpt = typer.Option(False, "--json", help="Print a JSON result on stdout instead of the path.")
ListJsonOpt = typer.Option(False, "--json", help="Print JSON on stdout instead of the table.")
GridSetOpt = typer.Option(
    [],
    "--set",
    metavar="KEY=VALUE",
    help="Replace a top-level key of the grid file, e.g. --set demos=40 --set 'seeds=[0]' --set out=runs/small "
    "(VALUE is read as TOML; `out` is then relative to the current folder). Repeatable; `cdrb select` takes the "
    "same --set as the `cdrb grid` run that made the evals.",
)
GridIncludeOpt = typer.Option(
    [],
    "--include",
    metavar="FILE",
    help="A settings file applied after the grid's own settings (e.g. smaller nets for a smoke run). Repeatable.",
)
DeviceOpt = typer.Option("auto", "--device", help="auto (CUDA when present), cpu or cuda.")


# ------------------------------------------------------------------------------------------------ choices
def file_path(value) -> Path:
    """A typer ``parser`` for an option naming a file to write: refused here when it names a folder
    (:func:`~cdrb_cli.artifacts.outputs.names_a_folder`), before ``Path`` drops its trailing slash."""
    from cdrb_cli.artifacts.outputs import names_a_folder

    text = os.fspath(value)
    if text == "-":  # the usual spelling of stdout, which would be written as a file named '-'
        raise ValueError("'-' would be a file named '-': leave the option out where the command writes to stdout")
    if names_a_folder(text):
        raise ValueError(f"{text!r} names a folder (it ends with {os.sep!r}); give a file name")
    return Path(text)


def choice(values: Callable[[], list[str]], what: str) -> Callable[[str], str]:
    """A typer ``parser`` accepting the strings ``values()`` gives when the option is parsed (not at start-up)."""

    def parse(value: str) -> str:
        allowed = values()
        if value not in allowed:
            raise ValueError(f"{value!r} is not a known {what} (choose one of {', '.join(allowed)})")
        return value

    return parse


def share_below_one(text: str) -> float:
    """A typer ``parser`` for a share of episodes held out: a number in [0, 1) (1 would hold out every one)."""
    value = float(text)
    if not 0 <= value < 1:
        raise ValueError(f"{text} is not a share in [0, 1)")
    return value


def registered(registry: Callable, what: str) -> Callable[[str], str]:
    """A typer ``parser`` accepting the names of a registry (plugins included)."""
    return choice(lambda: registry().names(), what)


def method_registry():
    from cdrb_cli.methods.registry import METHODS

    return METHODS


def expert_registry():
    from cdrb_cli.envs.registry import EXPERTS

    return EXPERTS


def controller_registry():
    from cdrb_cli.envs.registry import CONTROLLERS

    return CONTROLLERS


def net_names() -> list[str]:
    from cdrb_cli.configs import net_kinds

    return net_kinds()


def preset_names() -> list[str]:
    from cdrb_cli.presets import PRESETS

    return list(PRESETS)


def literal_values(model: str, field: str) -> Callable[[], list[str]]:
    """The values of a ``Literal`` field of a config record (``configs.<model>.<field>``)."""

    def values() -> list[str]:
        import typing

        from cdrb_cli import configs

        annotation = getattr(configs, model).model_fields[field].annotation
        return list(typing.get_args(annotation))

    return values


def _version(value: bool) -> None:
    if value:
        typer.echo(f"{PROG} {__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks for errors."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars or logs on stderr."),
) -> None:
    ui.set_quiet(quiet)


def load_artifact(path: Path, kind: str):
    from cdrb_cli.artifacts import load

    return load(path, kind)


def int_values(text: str, flag: str, what: str, example: str) -> list[int]:
    """A non-empty comma-separated list of integers, each written in ASCII digits (``what`` and ``example`` word the
    errors): an empty item (``0,,1``), ``1_0`` or other scripts' digits, which Python's int() reads, are typos."""
    from cdrb_cli.settings import clip, comma_items

    items = comma_items(text)
    if items == [""]:
        raise BadInput(f"{flag} is empty", hint=f"e.g. {example}")
    if not all(re.fullmatch(r"[+-]?[0-9]+", v) for v in items):
        raise BadInput(f"{flag} {clip(text)!r}: not a comma-separated list of {what}", hint=f"e.g. {example}")
    # (int() refuses numbers of thousands of digits, and no count or seed here has more than 20)
    if any(len(v.lstrip("+-")) > 20 for v in items):
        raise BadInput(f"{flag} {clip(text)!r}: a number of more than 20 digits", hint=f"e.g. {example}")
    return [int(v) for v in items]


def parse_seeds(text: str, flag: str) -> list[int]:
    from cdrb_cli.settings import clip

    values = int_values(text, flag, "integers", "0,1,2,3,4")
    if len(set(values)) != len(values):
        raise BadInput(f"{flag} {clip(text)!r}: repeated values", hint="list each seed once")
    if any(not 0 <= v < 2**32 for v in values):
        raise BadInput(f"{flag} {clip(text)!r}: seeds are 32-bit (0 to 4294967295)", hint="e.g. 0,1,2,3,4")
    return values


PICTURES = (".png", ".pdf", ".svg")


def check_outputs(force: bool, inputs=(), **outputs: Path | None) -> None:
    """Every output path of a command (``out=..., plot=...``), before any work: the rule of
    :func:`cdrb_cli.artifacts.check_output`, pictures with a picture suffix, and no two outputs the same."""
    from cdrb_cli.artifacts import check_output
    from cdrb_cli.artifacts.outputs import distinct_outputs

    distinct_outputs(**outputs)
    inputs = [p for p in inputs if p is not None]
    for name, path in outputs.items():
        if path is None:
            continue
        flag = "--" + name.replace("_", "-")
        if name == "docs":  # rewritten in place: the stage checks it (an existing text file, its markers)
            continue
        if name == "out":  # written and locked by the stage; here only: never one of the inputs
            check_output(Path(path), True, flag, inputs)
        else:
            check_output(Path(path), force, flag, inputs, suffixes=PICTURES)


def check_import_out(force: bool, out: Path, source: Path | None) -> None:
    """The ``--out`` of an import, before any work: an existing file only with ``--force``, and never the imported
    file or a file inside the imported folder (writing there would destroy what is read)."""
    from cdrb_cli.artifacts import check_output

    if source is not None and source.is_dir() and out.absolute().resolve().is_relative_to(source.resolve()):
        raise BadInput(f"--out {out}: inside the imported folder {source}", hint="write the artifact elsewhere")
    check_output(out, force, "--out", [source] if source is not None and source.is_file() else [])


def check_positive(flag: str, value) -> None:
    if value is not None and value <= 0:
        raise BadInput(f"{flag} {value}: must be positive", hint=f"pass {flag} N with N > 0")


def _check_can_make(folder: Path, flag: str) -> None:
    """``folder`` is a folder, or can be made: not a file, a device or a link to nothing, and its nearest existing
    ancestor is a folder something can be made in (tried, and removed)."""
    if folder.is_symlink() and not folder.exists():
        raise BadInput(f"{flag} {folder}: a link to nothing", hint="pass a folder path")
    if folder.exists() and not folder.is_dir():
        raise BadInput(f"{flag} {folder}: exists and is not a folder", hint="pass a folder path")
    from cdrb_cli.artifacts.outputs import check_can_make

    check_can_make(folder, flag, hint="pass a folder that can be made and written")


def gif_count(video: Path | None, videos: int | None) -> int:
    """How many GIFs a command writes: ``--videos`` (default 3) with ``--video``, none without; a ``--videos``
    without ``--video`` is refused (it would be ignored)."""
    if videos is not None and video is None:
        raise BadInput(f"--videos {videos}: goes with --video DIR", hint="add --video DIR, or drop --videos")
    return 0 if video is None else (3 if videos is None else videos)


def check_video_folder(video: Path, out: Path | None = None) -> None:
    """--video names a folder (made if missing), checked before any work: not an existing file, under a folder
    that can be made and written (not under a file), and not the folder of the run's own --out (a GIF could take
    the artifact's name)."""
    if out is not None and video.resolve() == Path(out).resolve():
        raise BadInput(f"--video {video}: the same path as --out", hint="give the GIFs a folder of their own")
    _check_can_make(video, "--video")
    if out is not None and Path(out).resolve().parent == video.resolve():
        raise BadInput(
            f"--out {out}: inside the --video folder {video}", hint="keep the artifact outside the GIFs' folder"
        )


def check_log_dir(log_dir: Path, out: Path) -> None:
    """--log-dir names a folder TensorBoard writes into (made if missing), checked before any work: not a file, a
    device or a dangling link, under a folder, and not the model's own --out path."""
    if log_dir.resolve() == Path(out).resolve():
        raise BadInput(f"--log-dir {log_dir}: the same path as --out", hint="give the logs a folder of their own")
    _check_can_make(log_dir, "--log-dir")


def report_gifs(video: Path, since: float, out: Path) -> None:
    """Say where the GIFs went, or that none were written (an up-to-date artifact is not re-run)."""
    written = [p for p in video.glob("*.gif") if p.stat().st_mtime >= since - 1] if video.is_dir() else []
    if written:
        ui.log(f"{len(written)} GIF(s) in {video}/")
    else:
        ui.log(f"no GIFs written: {out} is up to date, so nothing ran (--force re-runs it with --video)")


# ------------------------------------------------------------------------------------------------ plan
PartialOpt = typer.Option(
    False, "--allow-partial", help="Accept a model whose training did not finish (an interrupted checkpoint)."
)


def trained_model(path: Path, allow_partial: bool):
    from cdrb_cli.stages.share import check_finished

    m = load_artifact(path, "model")
    check_finished(m, allow_partial)
    return m
