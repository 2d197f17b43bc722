"""`cdrb grid GRID.toml`: a declarative grid of runs, expanded into the stage graph and executed in parallel.

A grid file names environments x methods x seeds (and optional variants: named sets of extra flags, one more axis).
It expands into tasks, each one `cdrb` command that writes one artifact:

    collect ENV  ->  cluster ENV  ->  train ENV/[VARIANT/]METHOD-sSEED  ->  eval ...  ->  report [VARIANT]

A task runs when the tasks it reads from have finished. Tasks are executed as `python -m cdrb_cli ...` processes,
either on **Ray** (``ray.init()`` on this machine, or ``--address`` for a cluster; each task asks for the CPUs
and GPUs of its kind) or, without Ray, on a local pool of N workers. Every artifact is written atomically by the
command itself, so a killed task leaves either nothing or a valid artifact (a training leaves its last
checkpoint); a failed task is retried once (a training with ``--resume``), then reported with the tail of its
stderr, and the tasks that do not depend on it go on.

Re-running a grid does no work for a task whose memo (``OUT/.grid/TASK.json``: the command, the cdrb version and
the sha256 of every input and output artifact) still matches the files; any other task is handed to the command,
which skips it when its artifact is up to date (the CLI's own rule) and resumes an unfinished training.
"""

from __future__ import annotations

import concurrent.futures as cf
import functools
import hashlib
import json
import os
import re
import signal
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PrivateAttr,
    Strict,
    ValidationError,
    field_validator,
)

from cdrb_cli import __version__, artifacts, ui
from cdrb_cli.configs import MAX_SEED
from cdrb_cli.errors import BadInput, RunFailed
from cdrb_cli.settings import clip

KINDS = ("collect", "cluster", "train", "eval", "report")
#: integers and flags of a grid file are strict: `steps = true` or `seeds = [1.5]` is an error, not 1
Int = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
SeedValue = Annotated[int, Strict(), Field(ge=0, le=MAX_SEED)]
Steps = Annotated[int, Strict(), Field(gt=0, le=10_000_000)]
STDERR_LINES = 15


def table_flags(value):
    """A command's extra flags as a grid file gives them: a list of flags as typed (``["--scene", "x.txt"]``), or a
    table of settings (``{ avoid = { best_of = 4 }, replan = "every:40" }``), which becomes ``--set KEY=VALUE``
    flags (dotted keys in the table's order, values as JSON): the same command, so the same memo key."""
    if not isinstance(value, dict):
        return value
    flags: list[str] = []

    def walk(node: dict, prefix: str) -> None:
        for key, item in node.items():
            if isinstance(item, dict):
                walk(item, f"{prefix}{key}.")
            else:
                flags.extend(["--set", f"{prefix}{key}={json.dumps(item)}"])

    walk(value, "")
    return flags


#: extra flags of one command: a list of flags, or a table of settings (see :func:`table_flags`)
Flags = Annotated[list[str], BeforeValidator(table_flags)]


# ------------------------------------------------------------------------------------------------ the grid file
class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class Settings(_Strict):
    """Extra `cdrb train` / `cdrb eval` flags for the runs of one environment and/or method (both optional:
    omitted means every one), and extra `cdrb collect` flags for an environment's demonstrations (an entry with
    ``collect`` names no method: the demos are shared by every method). Entries apply in order, so a later one can
    override an earlier one's flag."""

    env: str | None = None
    method: str | None = None
    collect: Flags = Field(
        default_factory=list, description="extra `cdrb collect` flags, e.g. ['--set', 'expert.routes=[\"over\"]']"
    )
    cluster: Flags = Field(
        default_factory=list,
        description="extra `cdrb cluster` flags of the buffer the matching runs train with, e.g. "
        "['--features', 'state-action'] (runs with the same flags share one buffer)",
    )
    train: Flags = Field(
        default_factory=list, description="extra `cdrb train` flags or settings, e.g. ['--steps', '4000']"
    )
    eval: Flags = Field(
        default_factory=list,
        description="extra `cdrb eval` flags, or a table of settings, e.g. { controller = { max_lag = 0.6 } }",
    )
    chosen: str | None = Field(None, description="what `cdrb select` chose (candidate and steps); not a flag")


class SettingsFile(_Strict):
    """A settings file that grids (and other settings files) ``include``: shared data choices, or the settings
    `cdrb select` chose on the tuning stream. ``meta`` is free provenance (the rule, the tuning grid)."""

    include: list[Path] = Field(default_factory=list, description="more settings files, before this one's")
    settings: list[Settings] = Field(default_factory=list)
    meta: dict[str, str] = Field(default_factory=dict, description="provenance: not read by the grid")


class _Scoped(_Strict):
    """An entry that applies to some environments and methods (``envs``/``methods`` None: all)."""

    def applies(self, env: str, method: str) -> bool:
        return (self.methods is None or method in self.methods) and (self.envs is None or env in self.envs)


class Variant(_Scoped):
    """One more axis of the grid: a named set of extra flags; its evals go to OUT/ENV/NAME/ and get their own report.

    A variant with ``train`` flags trains its own models (in OUT/ENV/NAME/); one without is *eval-only*: it evaluates
    the grid's base models (OUT/ENV/METHOD-sSEED.h5, trained once with no variant flags), e.g. a controller, a plan
    clock, a sampler, denoising steps or a re-planning trigger tried on one trained model."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.=-]*$", description="folder name of the variant's runs")
    methods: list[str] | None = Field(None, description="the methods this variant applies to (default: all)")
    envs: list[str] | None = Field(None, description="the environments this variant applies to (default: all)")
    cluster: Flags = Field(
        default_factory=list, description="`cdrb cluster` flags of the variant's own buffer, e.g. ['--k', '100']"
    )
    train: Flags = Field(default_factory=list, description="`cdrb train` flags or a table of settings")
    eval: Flags = Field(
        default_factory=list, description="`cdrb eval` flags or a table of settings, e.g. { avoid = { best_of = 4 } }"
    )
    stream: Literal["tune", "test"] | None = Field(
        None, description="start/goal pairs of its evals (default: eval_stream)"
    )
    eval_settings: Bool = Field(
        True,
        description="false: the settings' eval flags do not apply to this variant (e.g. a protocol with its own "
        "executor, where a method's tuned controller flags do not belong)",
    )

    @property
    def own_model(self) -> bool:
        """Whether the variant trains models of its own (train or cluster flags); else it is eval-only and evaluates
        the grid's base models."""
        return bool(self.train or self.cluster)


class Extension(_Scoped):
    """A learning curve run past the grid's ``steps`` for some environments and methods (where `cdrb select` finds
    it still rising): the same runs, resumed to ``steps``, with the grid's own ``steps`` one more snapshot. It is
    written in the grid file, so the curve's length is part of the study it belongs to."""

    envs: list[str] | None = Field(None, description="the environments whose curves run further (default: all)")
    methods: list[str] | None = Field(None, description="the methods whose curves run further (default: all)")
    steps: Steps = Field(description="the curve's new last point (more than the grid's `steps`)")


class Resources(_Strict):
    cpus: float = Field(1.0, gt=0, description="CPU cores a task of this kind asks Ray for (and its torch threads)")
    gpus: float = Field(0.0, ge=0, description="GPUs a task of this kind asks Ray for (fractions share one GPU)")


def _default_resources() -> dict[str, Resources]:
    return {"collect": Resources(cpus=2)} | {k: Resources() for k in KINDS if k != "collect"}


class GridSpec(_Strict):
    """A grid file (TOML). Paths are relative to the file's folder."""

    include: list[Path] = Field(
        default_factory=list, description="settings files whose [[settings]] apply before this file's own"
    )
    out: Path = Field(description="folder for every artifact of the grid (shared storage on a cluster)")
    envs: list[str] = Field(min_length=1, description="environment ids (`cdrb envs`)")
    methods: list[str] = Field(min_length=1, description="methods (`cdrb methods`)")
    seeds: list[SeedValue] = Field(
        min_length=1, max_length=1000, description="training seeds; each model is evaluated on the same seed"
    )
    preset: Literal["quick", "paper"] = Field("quick", description="training preset of every method")
    device: str = Field(
        "cpu",
        pattern=r"^(cpu|auto|cuda(:[0-9]{1,2})?)$",
        description="training and evaluation device (cpu, cuda, auto)",
    )
    demos: Int = Field(1000, ge=2, le=1_000_000, description="demonstrations collected per environment")
    data_seed: SeedValue = Field(0, description="seed of `cdrb collect` and `cdrb cluster`")
    k: Int = Field(
        1000, ge=0, le=10_000_000, description="replay-buffer clusters (`cdrb cluster --k`; 0 keeps the full buffer)"
    )
    steps: Steps | None = Field(None, description="training steps of every run (default: the preset's)")
    eval_episodes: Int = Field(100, ge=1, le=100_000, description="evaluation episodes per model and seed")
    eval_stream: Literal["tune", "test"] = Field("test", description="start/goal pairs: tune or test stream")
    eval_seeds: list[SeedValue] | None = Field(
        None, min_length=1, description="evaluation seeds of every model (default: the model's own training seed)"
    )
    eval_seed_offset: SeedValue = Field(
        0,
        le=1_000_000,
        description="without eval_seeds: each model is evaluated on its training seed plus this (fresh pairs of the "
        "same stream, for a row re-measured after a choice made on seeing its test figures)",
    )
    snapshot_at: list[Steps] = Field(
        default_factory=list,
        description="learning curves: every training also writes its model at these steps (below `steps`), and each "
        "snapshot is evaluated like the final model",
    )
    extend: list[Extension] = Field(
        default_factory=list,
        max_length=1000,
        description="learning curves run further for some envs/methods: [[extend]] entries (the last that applies "
        "wins); each such run trains to the entry's steps and `steps` becomes one more snapshot",
    )
    report: Bool = Field(True, description="write OUT/report[-VARIANT].md (tuning grids are read by `cdrb select`)")
    reuse: list[Path] = Field(
        default_factory=list,
        max_length=16,
        description="`out` folders of other grids whose finished collections, clusterings and trainings this grid "
        "reads instead of running its own: a task is taken from there when a finished task there ran the same "
        "command up to its output path and device (a training also when it wrote a model at exactly this one's "
        "steps, as a snapshot or as its final model)",
    )
    settings: list[Settings] = Field(default_factory=list, description="per env/method extra flags")
    variants: list[Variant] = Field(default_factory=list, description="named flag sets: one more grid axis")
    resources: dict[str, Resources] = Field(default_factory=_default_resources)
    #: the grid file and every settings file it read: inputs a run must never write over
    _sources: list[Path] = PrivateAttr(default_factory=list)
    #: the tasks taken from the grids of ``reuse`` (task id -> the file read instead), set by :func:`expand`
    _reused: dict[str, str] = PrivateAttr(default_factory=dict)
    #: sha256 of the files read, by (path, size, mtime): shared by reuse at expansion and the run's memo checks
    _shas: dict = PrivateAttr(default_factory=dict)

    def curve(self, env: str, method: str) -> tuple[int | None, list[int]]:
        """The training length and the snapshot steps (sorted) of ``method``'s runs on ``env``: the grid's, or those
        of the last :class:`Extension` that applies (its steps, with the grid's steps one more snapshot)."""
        ext = next((e for e in reversed(self.extend) if e.applies(env, method)), None)
        if ext is None:
            return self.steps, sorted(self.snapshot_at)
        return ext.steps, sorted([*self.snapshot_at, self.steps])

    @field_validator("eval_seeds")
    @classmethod
    def _once(cls, value: list[int] | None) -> list[int] | None:
        if value is not None and len(set(value)) != len(value):
            raise ValueError("list each evaluation seed once")
        return value

    @field_validator("resources")
    @classmethod
    def _kinds(cls, value: dict[str, Resources]) -> dict[str, Resources]:
        unknown = sorted(set(value) - set(KINDS))
        if unknown:
            raise ValueError(f"resources.{unknown[0]}: not a task kind (use {', '.join(KINDS)})")
        return _default_resources() | value


#: the largest grid or settings file read, and the most tasks a grid may expand to
MAX_FILE_BYTES = 1 << 20
MAX_TASKS = 100_000


def _read_small(path: Path, limit: int = MAX_FILE_BYTES) -> str | None:
    """The text of ``path`` through the guarded reader (a regular file of at most ``limit`` bytes, no link out of
    its folder, never blocking on a FIFO); None when it is not one."""
    from cdrb_cli.artifacts.core import read_input_text

    try:
        return read_input_text(path, "", limit)
    except BadInput:
        return None


def _read_toml(path: Path, what: str) -> dict:
    import tomllib

    if not os.path.lexists(path):
        raise BadInput(f"{path}: no such {what}", hint="see docs/cli.md, `cdrb grid`, for the format")
    text = _read_small(path)
    if text is None:
        raise BadInput(
            f"{path}: not a {what} (a regular text file of at most {MAX_FILE_BYTES >> 20} MiB, no link out of its "
            "folder)",
            hint="name the TOML file itself",
        )
    try:
        return tomllib.loads(text)
    except (tomllib.TOMLDecodeError, RecursionError) as exc:
        raise BadInput(f"{path}: not valid TOML ({str(exc)[:200]})", hint="fix the file") from None


def _validated(model: type[BaseModel], raw: dict, path: Path):
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = clip(".".join(str(p) for p in err["loc"]), 80) or "(top level)"
        raise BadInput(f"{path}: {where}: {err['msg']}", hint="see docs/cli.md, `cdrb grid`") from None


#: flags whose value is a file: a relative one in a grid or settings file means relative to that file's folder
PATH_FLAGS = ("--maze-map", "--scene", "--policy", "--config", "--paper-figures", "--route-buffer")


def _anchored(flags: list[str], base: Path) -> list[str]:
    """``flags`` with every relative file value of :data:`PATH_FLAGS` made absolute against ``base`` (the folder of
    the file that declares them), as `out` is: a grid means the same files from whatever folder it is run."""
    out, i = [], 0
    while i < len(flags):
        f = flags[i]
        name, eq, value = f.partition("=")
        if name in PATH_FLAGS and eq and not Path(value).is_absolute():
            out.append(f"{name}={base / value}")
        elif f in PATH_FLAGS and i + 1 < len(flags) and not Path(flags[i + 1]).is_absolute():
            out += [f, str(base / flags[i + 1])]
            i += 1
        else:
            out.append(f)
        i += 1
    return out


def _anchor_all(items: list, base: Path) -> list:
    """Settings or variants with their flag lists anchored at ``base``."""
    fields = ("collect", "cluster", "train", "eval")
    return [
        item.model_copy(update={k: _anchored(getattr(item, k), base) for k in fields if hasattr(item, k)})
        for item in items
    ]


#: the options the grid sets itself from its own keys (data_seed, demos, preset, seeds, eval_stream, eval_episodes,
#: device, out...) and that settings and variants therefore may not pass: a repeated option's last value wins, so
#: ``train = ["--method", "diffuser"]`` would file a Diffuser under the grid's MLP name
GRID_OPTIONS = {
    "collect": {"episodes", "seed", "out"},
    "cluster": {"out"},
    "train": {"method", "preset", "seed", "buffer", "snapshot_at", "out", "device"},
    "eval": {"seeds", "stream", "episodes", "out", "device"},
}
#: the settings (``--set KEY``) behind those options
GRID_SETTINGS = {"train": {"method", "method.name", "preset", "seed"}, "eval": {"episodes", "seeds", "stream", "seed"}}
#: files a grid's flags name that no grid writes: missing, every task that reads one would fail
INPUT_FILE_FLAGS = ("--maze-map", "--scene", "--policy", "--config", "--paper-figures")


def _check_flag_list(flags: list[str], command: str, where: str) -> None:
    """One settings or variant flag list for ``cdrb command``: every option exists, is not one the grid sets, has
    its value, and an integer or number value parses; a controller is a known one; a file it names exists. A
    mistake is one line when the grid is read, not a failure of every task hours later."""
    import typing

    from cdrb_cli.envs.registry import CONTROLLERS

    table = _option_table(command)
    hints = typing.get_type_hints(_command(command).callback)
    for token, entry, inline in walk_options(flags, table):
        if entry is None:
            if token.startswith("-") and not _is_number(token):
                raise BadInput(f"{where}: {clip(repr(token), 60)} is not a `cdrb {command}` option",
                               hint=f"`cdrb {command} --help` lists them")  # fmt: skip
            raise BadInput(
                f"{where}: {clip(repr(token), 60)} is not the value of an option (the grid names the command's "
                "files itself)",
                hint='give each value right after its option, e.g. ["--steps", "4000"]',
            )
        pname, takes_value, _ = entry
        if pname in GRID_OPTIONS.get(command, ()):
            raise BadInput(
                f"{where}: {clip(repr(token), 60)}: the grid sets this `cdrb {command}` option itself",
                hint="use the grid's own key (seeds, eval_seeds, eval_stream, eval_episodes, demos, data_seed, preset, "
                "device, out, or a variant's stream)",
            )
        if not takes_value:
            continue
        key = (inline or "").partition("=")[0].strip().replace("-", "_")
        if pname == "sets" and key in GRID_SETTINGS.get(command, ()):
            raise BadInput(
                f"{where}: --set {clip(inline, 60)}: the grid sets {key} of `cdrb {command}` itself",
                hint="use the grid's own key (seeds, eval_seeds, eval_stream, eval_episodes, preset, or a variant's "
                "stream)",
            )
        if inline is None or ("=" not in token and inline.startswith("-") and inline in table):
            raise BadInput(f"{where}: {clip(repr(token), 60)} has no value",
                           hint=f"give it one: [{json.dumps(token)}, VALUE]")  # fmt: skip
        kind = hints.get(pname)
        base = next((t for t in typing.get_args(kind) if t is not type(None)), kind)
        if base in (int, float):
            try:
                base(inline)
            except ValueError:
                what = "an integer" if base is int else "a number"
                raise BadInput(f"{where}: {token} {clip(repr(inline), 40)}: not {what}",
                               hint=f"`cdrb {command} --help` says what it takes") from None  # fmt: skip
        if pname == "controller":
            CONTROLLERS.get(inline, f"{where}: --controller")
        option = token.partition("=")[0]
        if option in INPUT_FILE_FLAGS and not Path(inline).exists():
            raise BadInput(f"{where}: {option} {clip(inline, 300)}: no such file", hint="fix the path (relative to the "
                           "file that names it)")  # fmt: skip


@functools.cache
def _command(command: str):
    import typer

    from cdrb_cli.cli import app

    return typer.main.get_command(app).commands[command]


def _check_flags(spec: GridSpec, path: Path) -> None:
    """Every flag list of the grid's settings and variants, by :func:`_check_flag_list`."""
    items = [("settings", i, s) for i, s in enumerate(spec.settings)] + [
        ("variants", i, v) for i, v in enumerate(spec.variants)
    ]
    for kind, i, item in items:
        for command in ("collect", "cluster", "train", "eval"):
            _check_flag_list(getattr(item, command, []), command, f"{path}: {kind}[{i}].{command}")


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _included_settings(
    paths: list[Path], base: Path, chain: tuple[Path, ...], read: list[Path] | None = None
) -> list[Settings]:
    """The settings of ``paths`` (relative to ``base``) in order, each file's own includes first; every file read
    is appended to ``read``."""
    out: list[Settings] = []
    for rel in paths:
        given = Path(os.path.normpath(base / rel))
        path = given.resolve()
        if path in chain:
            raise BadInput(f"{chain[-1]}: include {rel}: includes itself (through {path.name})", hint="remove the loop")
        sfile = _validated(SettingsFile, _read_toml(given, "settings file"), path)
        if read is not None:
            read.append(path)
        out += _included_settings(sfile.include, path.parent, (*chain, path), read)
        out += _anchor_all(sfile.settings, path.parent)
    return out


def parse_override(text: str) -> tuple[str, object]:
    """``KEY=VALUE`` from `cdrb grid --set`: VALUE as a TOML value (``seeds=[0]``, ``demos=40``), else a string."""
    import tomllib

    key, sep, value = text.partition("=")
    if not sep or not key.strip():
        raise BadInput(f"--set {clip(text)}: expected KEY=VALUE", hint="e.g. --set demos=40 or --set 'seeds=[0]'")
    try:
        return key.strip(), tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        return key.strip(), value


def _origin(path: Path, overrides: list[str], *keys) -> str:
    """Where a top-level key's value came from: the ``--set`` of the first of ``keys`` that was set (each key's
    last ``--set``), else the grid file."""
    given = {parse_override(t)[0]: t for t in overrides}
    for key in keys:
        if key in given:
            return f"--set {clip(given[key])}"
    return str(path)


def load_grid(path: Path, overrides: list[str] = (), extra_includes: list[Path] = ()) -> GridSpec:
    """Read and check a grid file: unknown keys, environments and methods are one-line errors naming the file.

    ``include`` files' settings come first (in order), then the grid's own; ``extra_includes`` (`cdrb grid
    --include`, relative to the current folder) come last, so they override both. ``overrides`` (`cdrb grid --set
    KEY=VALUE`) replace top-level keys of the file; an ``out`` given so is relative to the current folder."""
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.methods.registry import METHODS

    raw = _read_toml(Path(path), "grid file")  # read as given: a link out of its folder is refused
    path = Path(path).resolve()
    cwd_out, set_keys = None, set()
    for text in overrides:
        key, value = parse_override(text)
        set_keys.add(key)
        if key not in GridSpec.model_fields or key in ("settings", "variants", "include", "resources"):
            raise BadInput(
                f"--set {clip(text)}: {clip(repr(key), 60)} is not a top-level grid key that --set can change",
                hint="one of "
                + ", ".join(
                    k for k in GridSpec.model_fields if k not in ("settings", "variants", "include", "resources")
                ),
            )
        raw[key] = value
        if key == "out":
            cwd_out = Path(str(value)).resolve()
    try:
        spec = GridSpec.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = clip(".".join(str(p) for p in err["loc"]), 80) or "(top level)"
        raise BadInput(f"{_origin(path, overrides, *err['loc'][:1])}: {where}: {err['msg']}",
                       hint="see docs/cli.md, `cdrb grid`") from None  # fmt: skip
    read = [path]
    spec.settings = (
        _included_settings(spec.include, path.parent, (path,), read)
        + _anchor_all(spec.settings, path.parent)
        + _included_settings(list(extra_includes), Path.cwd(), (path,), read)
    )
    spec.variants = _anchor_all(spec.variants, path.parent)
    _check_flags(spec, path)
    spec._sources = read
    spec.out = cwd_out or (path.parent / spec.out).resolve()
    _check_out(spec.out, _origin(path, overrides, "out"))
    spec.reuse = [(Path.cwd() if "reuse" in set_keys else path.parent).joinpath(r).resolve() for r in spec.reuse]
    if spec.out in spec.reuse:
        raise BadInput(f"{_origin(path, overrides, 'reuse', 'out')}: reuse: names the grid's own `out` folder",
                       hint="list other grids' `out` folders")  # fmt: skip
    for folder in spec.reuse:
        if folder.exists() and not folder.is_dir():
            raise BadInput(
                f"{_origin(path, overrides, 'reuse')}: reuse: {folder} is a file, not a grid's `out` folder",
                hint="list the `out` folders of other grids",
            )
        if not folder.exists():  # a grid may name the folder of one not run yet (Table 1 before its curves)
            ui.warn(f"reuse: {folder}: no such folder yet, so nothing is reused from it (a typo?)")
    for env in spec.envs:
        try:
            make_spec(env)
        except BadInput as exc:
            raise BadInput(f"{_origin(path, overrides, 'envs')}: envs: {exc.message}",
                           hint="`cdrb envs` lists them") from None  # fmt: skip
    for m in spec.methods:
        METHODS.get(m, f"{_origin(path, overrides, 'methods')}: methods")
    _check_train_configs(spec, path)
    # settings may name envs and methods the grid does not run (one settings table for several grids), but every
    # name must exist: a typo would silently apply nothing
    for i, s in enumerate(spec.settings):
        if s.env is not None:
            try:
                make_spec(s.env)
            except BadInput as exc:
                raise BadInput(f"{path}: settings[{i}].env: {exc.message}", hint="`cdrb envs` lists them") from None
        if s.method is not None:
            METHODS.get(s.method, f"{path}: settings[{i}].method")
            if s.collect:
                raise BadInput(
                    f"{path}: settings[{i}]: collect flags apply to an environment's demos, which every method shares",
                    hint="put them in an entry without `method`",
                )
    names = [v.name for v in spec.variants]
    if len({n.lower() for n in names}) != len(names):  # folders: one on a case-insensitive file system
        raise BadInput(f"{path}: variants: names must differ, also in case (got {', '.join(names)})",
                       hint="rename one")  # fmt: skip
    for v in spec.variants:
        if v.name.lower().endswith(".h5"):
            raise BadInput(f"{path}: variant {v.name}: a variant's folder lies beside the environment's artifacts, "
                           "so its name cannot end in .h5", hint="rename it")  # fmt: skip
    # a variant may name methods and envs the grid does not run (a grid narrowed with --set), but each must exist
    for i, v in enumerate(spec.variants):
        _check_names(f"{path}: variant {v.name}", v.methods, v.envs)
        _check_scope(f"{path}: variants[{i}] ({v.name})", v, spec, bool({"envs", "methods"} & set_keys))
    if any(len(set(v)) != len(v) for v in (spec.seeds, spec.envs, spec.methods)):
        raise BadInput(f"{_origin(path, overrides, 'envs', 'methods', 'seeds')}: envs, methods and seeds must each "
                       "be listed once", hint="remove the repeats")  # fmt: skip
    if spec.snapshot_at:
        if spec.steps is None or any(s <= 0 or s >= spec.steps for s in spec.snapshot_at):
            raise BadInput(
                f"{_origin(path, overrides, 'snapshot_at', 'steps')}: snapshot_at: every snapshot must lie between 0 "
                "and `steps` (the final model)",
                hint="set steps to the curve's last point and list the earlier ones in snapshot_at",
            )
        if len(set(spec.snapshot_at)) != len(spec.snapshot_at):
            raise BadInput(f"{_origin(path, overrides, 'snapshot_at')}: snapshot_at: list each step once",
                           hint="remove the repeats")  # fmt: skip
        _check_snapshot_steps(spec, _origin(path, overrides, "snapshot_at"))
    for i, ext in enumerate(spec.extend):
        where = f"{_origin(path, overrides, 'extend', 'steps')}: extend[{i}]"
        if spec.steps is None or ext.steps <= spec.steps:
            raise BadInput(
                f"{where}: steps {ext.steps} does not extend the curve (the grid's steps: {spec.steps})",
                hint="set the grid's `steps` and give the extension more",
            )
        _check_names(where, ext.methods, ext.envs)
        _check_scope(where, ext, spec, bool({"envs", "methods"} & set_keys))
    if spec.extend:
        _check_snapshot_steps(spec, _origin(path, overrides, "extend", "steps"))
    if spec.eval_seeds is not None and "eval_seed_offset" in spec.model_fields_set:
        raise BadInput(
            f"{_origin(path, overrides, 'eval_seed_offset', 'eval_seeds')}: eval_seeds and eval_seed_offset: the "
            "offset applies only without eval_seeds",
            hint="keep one of the two",
        )
    if spec.eval_seeds is None and max(spec.seeds) + spec.eval_seed_offset > MAX_SEED:
        where = _origin(path, overrides, "eval_seed_offset", "seeds")
        raise BadInput(
            f"{where}: eval_seed_offset {spec.eval_seed_offset}: training seed {max(spec.seeds)} plus it is past "
            f"the largest seed ({MAX_SEED})",
            hint="use smaller seeds or a smaller offset",
        )
    runs = len(spec.envs) * len(spec.methods) * len(spec.seeds) * max(1, len(spec.variants))
    per_run = 2 + len(spec.snapshot_at) + bool(spec.extend)
    if runs * per_run > MAX_TASKS:
        raise BadInput(
            f"{path}: the grid expands to about {runs * per_run:,} tasks (at most {MAX_TASKS:,})",
            hint="split it into several grid files",
        )
    if spec.report and spec.eval_seeds is not None and len(spec.seeds) > 1:
        raise BadInput(
            f"{_origin(path, overrides, 'eval_seeds', 'seeds', 'report')}: eval_seeds with several training seeds: "
            "a report would pool the same evaluation seeds twice",
            hint="set report = false and compare with `cdrb select`, or drop eval_seeds",
        )
    return spec


def _check_scope(where: str, item: _Scoped, spec: GridSpec, narrowed: bool) -> None:
    """An empty ``methods``/``envs`` list is an error (it applies to nothing; leaving the key out means all), and an
    entry that applies to none of the grid's runs is said, unless the grid was ``narrowed`` with --set (which may
    leave entries idle on purpose)."""
    for key in ("methods", "envs"):
        if getattr(item, key) == []:
            raise BadInput(f"{where}: {key} = []: applies to nothing", hint=f"leave {key} out to mean all")
    if not narrowed and not any(item.applies(e, m) for e in spec.envs for m in spec.methods):
        ui.warn(f"{where}: applies to none of the grid's environments and methods, so it does nothing here")


def _check_out(out: Path, where: str) -> None:
    """The grid's ``out`` is a folder or can become one (no file on its path), and its name has no control
    characters (every task's command line names files under it, one line per task)."""
    if any(ord(c) < 32 or ord(c) == 127 for c in str(out)):
        raise BadInput(f"{where}: out {clip(repr(str(out)), 80)}: has a control character", hint="rename the folder")
    for folder in (out, *out.parents):
        if folder.exists():
            if not folder.is_dir():
                raise BadInput(f"{where}: out = {out}: {folder} is a file, not a folder",
                               hint="choose a folder for the grid's artifacts")  # fmt: skip
            break


def _check_names(where: str, methods: list[str] | None, envs: list[str] | None) -> None:
    """Every method and environment a variant or an extension names exists (it may name ones the grid does not
    run: a grid narrowed with --set)."""
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.methods.registry import METHODS

    for m in methods or []:
        METHODS.get(m, f"{where}: methods")
    for e in envs or []:
        try:
            make_spec(e)
        except BadInput as exc:
            raise BadInput(f"{where}: envs: {exc.message}", hint="`cdrb envs` lists them") from None


def _snapshot_step(spec: GridSpec, env: str, method: str, variant: Variant) -> int | None:
    """Where ``method``'s training in ``variant`` records its model (:func:`train.snapshot_step` of its
    checkpoint_every: the preset's, the method's own, or its train flags' last ``--set checkpoint_every=N``); None
    when a ``--config`` file may set it or the value is not a positive integer (`cdrb train` then says so)."""
    from cdrb_cli.methods.config import preset_training
    from cdrb_cli.methods.registry import METHODS
    from cdrb_cli.presets import PRESETS
    from cdrb_cli.stages.train import snapshot_step

    _, options, sets = parse_command(["train", *flags_for(spec, env, method, variant)[0]])
    if options.get("config_file") is not None:
        return None
    preset = str(options.get("preset") or spec.preset)
    if preset not in PRESETS:
        return None
    every = str(dict(sets).get("checkpoint_every", preset_training(METHODS.get(method), preset)["checkpoint_every"]))
    return snapshot_step(int(every)) if every.isascii() and every.isdigit() and int(every) > 0 else None


def _check_train_configs(spec: GridSpec, path: Path) -> None:
    """Every training's settings resolve as `cdrb train` resolves them: on the environment's spec (of its
    ``--maze-map`` where the collect flags name one) and a buffer of the features its cluster flags ask for. An
    unknown ``--set`` key, a value of the wrong type or a net the method cannot use is then one line when the grid
    is read, not a failure of every training hours later. Settings in a ``--config`` file are left to the command."""
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.methods.config import resolve_train_config, user_settings
    from cdrb_cli.methods.registry import METHODS, BufferInfo

    for env in spec.envs:
        collect = collect_flags_for(spec, env)
        maze_map = parse_command(["collect", env, *collect])[1].get("maze_map")
        try:
            env_spec = make_spec(None if maze_map else env, maze_map)
        except BadInput:
            continue  # the collection says what is wrong with its map
        for method in spec.methods:
            entry = METHODS.get(method)
            for v in _model_variants(spec, env, method):
                _, options, sets = parse_command(["train", *flags_for(spec, env, method, v)[0]])
                if options.get("config_file") is not None:
                    continue
                steps = None if options.get("steps") is None else int(options["steps"])
                preset = options.get("preset") or spec.preset
                items = user_settings(method, options.get("net"), preset, steps, sets=[f"{k}={x}" for k, x in sets])
                buffer = None
                if entry.needs_buffer:
                    cluster = parse_command(["cluster", "demos.h5", *cluster_flags_for(spec, env, method, v)])[1]
                    buffer = BufferInfo(features=str(cluster.get("features") or "state"), diameter=1.0)
                try:
                    resolve_train_config(env_spec, buffer, items)
                except BadInput as exc:
                    where = f"{path}: {method} on {env}" + (f" in variant {v.name}" if v.name else "")
                    raise BadInput(f"{where}: train flags: {exc.message}", hint=exc.hint) from None


def _check_snapshot_steps(spec: GridSpec, origin: str) -> None:
    """Every snapshot step on each training's loss curve (the rule of `cdrb train --snapshot-at`), so a grid that
    would fail in every training fails when it is read; ``origin`` names where snapshot_at came from."""
    for env in spec.envs:
        for method in spec.methods:
            snaps = spec.curve(env, method)[1]
            for v in _model_variants(spec, env, method):
                step = _snapshot_step(spec, env, method, v)
                bad = [s for s in snaps if step and s % step]
                if bad:
                    where = f"{method}'s training" + (f" in variant {v.name}" if v.name else "")
                    raise BadInput(
                        f"{origin}: snapshot_at: {bad[0]} is not a multiple of {step}, where {where} records its "
                        f"model (every gcd(50, checkpoint_every) steps)",
                        hint=f"use multiples of {step}, or set checkpoint_every in {method}'s train flags",
                    )


# ------------------------------------------------------------------------------------------------ the stage graph
@dataclass
class Task:
    """One `cdrb` command of the grid. ``meta`` names what an eval measured (env, method, variant, seed, steps,
    stream), for `cdrb select`."""

    id: str
    kind: str
    argv: list[str]
    outputs: list[Path]
    deps: list[str] = field(default_factory=list)
    inputs: list[Path] = field(default_factory=list)
    meta: dict = field(default_factory=dict)


BASE = Variant.model_construct(
    name="", methods=None, envs=None, cluster=[], train=[], eval=[], stream=None, eval_settings=True
)


def collect_flags_for(spec: GridSpec, env: str) -> list[str]:
    """The extra `cdrb collect` flags of ``env``'s demos: those of every settings entry that applies to it."""
    return [f for s in spec.settings if s.env in (None, env) for f in s.collect]


def _model_variants(spec: GridSpec, env: str, method: str) -> list[Variant]:
    """The variants whose models ``method`` trains on ``env``: the base, then each variant with its own models."""
    return [BASE, *(v for v in spec.variants if v.own_model and v.applies(env, method))]


def cluster_flags_for(spec: GridSpec, env: str, method: str, variant: Variant = BASE) -> list[str]:
    """The extra `cdrb cluster` flags of the buffer ``method`` trains with on ``env`` in ``variant``: the settings'
    that apply, then the variant's."""
    return [f for s in spec.settings if s.env in (None, env) and s.method in (None, method) for f in s.cluster] + list(
        variant.cluster
    )


def flags_for(spec: GridSpec, env: str, method: str, variant: Variant = BASE) -> tuple[list[str], list[str]]:
    """The extra `cdrb train` and `cdrb eval` flags of ``method`` on ``env`` in ``variant``: the settings that
    apply, in order (included files first), then the variant's own."""
    train, evaluate = [], []
    for s in spec.settings:
        if s.env in (None, env) and s.method in (None, method):
            train += s.train
            evaluate += s.eval
    return (
        without_repeated_sets(train + variant.train),
        without_repeated_sets((evaluate if variant.eval_settings else []) + variant.eval),
    )


def without_repeated_sets(flags: list[str]) -> list[str]:
    """``flags`` less every ``--set KEY=VALUE`` that gives KEY the value it already has there (a settings file
    included beside another that states the same setting): the command means the same and reads once. A repeat
    that restores a value overridden in between (the key itself, or one above or inside it) is kept."""
    out, value = [], {}
    i = 0
    while i < len(flags):
        f = flags[i]
        if f == "--set" and i + 1 < len(flags):
            pair, width = flags[i + 1], 2
        elif f.startswith("--set="):
            pair, width = f.removeprefix("--set="), 1
        else:
            out.append(f)
            i += 1
            continue
        key, eq, val = pair.partition("=")
        key = key.strip()
        if not (eq and value.get(key) == val):
            out += flags[i : i + width]
            for other in [k for k in value if _nested(k, key)]:  # a setting above or inside it changed too
                del value[other]
            if eq:
                value[key] = val
        i += width
    return out


def expand(spec: GridSpec) -> list[Task]:
    """The grid's tasks in an order where every task comes after the tasks it reads from."""
    from cdrb_cli.methods.registry import METHODS

    out, tasks, trains = spec.out, [], set()
    variants = spec.variants or [BASE]
    evals: dict[str, list[tuple[str, Path]]] = {v.name: [] for v in variants}
    for env in spec.envs:
        folder = out / env
        demos = folder / "demos.h5"
        collect_id = f"collect {env}"
        collect_extra = collect_flags_for(spec, env)
        tasks.append(
            Task(
                collect_id,
                "collect",
                ["collect", env, "-n", str(spec.demos), "--seed", str(spec.data_seed), *collect_extra]
                + ["--out", str(demos)],
                [demos],
            )
        )
        buffers: dict[str, tuple[str, Path]] = {}  # cluster flags (JSON) -> (task id, buffer path)

        for method in spec.methods:
            needs_buffer = METHODS.get(method).needs_buffer
            for v in variants:
                if not v.applies(env, method):
                    continue
                own_model = v.own_model
                model_v = v if own_model else BASE  # whose training flags and buffer the models have
                if needs_buffer:
                    flags = cluster_flags_for(spec, env, method, model_v)
                    vcluster, vbuffer = _buffer(spec, env, flags, buffers, tasks)
                deps = [collect_id] + ([vcluster] if needs_buffer else [])
                inputs = [demos] + ([vbuffer] if needs_buffer else [])
                mfolder = folder / v.name if own_model else folder
                efolder = folder / v.name if v.name else folder
                vtag = f"{v.name}/" if own_model else ""
                train_extra, eval_extra = flags_for(spec, env, method, model_v)[0], flags_for(spec, env, method, v)[1]
                length, snaps = spec.curve(env, method)
                for seed in spec.seeds:
                    model = mfolder / f"{method}-s{seed}.h5"
                    train_id = f"train {env}/{vtag}{method}-s{seed}"
                    if train_id not in trains:
                        trains.add(train_id)
                        argv = ["train", str(demos), "--method", method, "--preset", spec.preset, "--seed", str(seed)]
                        argv += ["--buffer", str(vbuffer)] if needs_buffer else []
                        argv += train_extra
                        argv += ["--steps", str(length)] if length else []
                        if snaps:
                            argv += ["--snapshot-at", ",".join(map(str, snaps))]
                        argv += ["--out", str(model), "--device", spec.device]
                        outputs = [model] + [train_snapshot(model, s) for s in snaps]
                        tasks.append(Task(train_id, "train", argv, outputs, deps, inputs))
                    points = [(s, train_snapshot(model, s)) for s in snaps] + [(length, model)]
                    stream = v.stream or spec.eval_stream
                    seeds = spec.eval_seeds if spec.eval_seeds is not None else [seed + spec.eval_seed_offset]
                    for steps, m in points:
                        at = f".step{steps}" if m != model else ""
                        tag = f"{env}/{v.name + '/' if v.name else ''}{method}-s{seed}{at}"
                        ev = efolder / f"eval-{method}-s{seed}{at}.h5"
                        argv = ["eval", str(m), "--stream", stream, "--seeds", ",".join(map(str, seeds))]
                        argv += ["--episodes", str(spec.eval_episodes), *eval_extra]
                        argv += ["--out", str(ev), "--device", spec.device]
                        meta = {"env": env, "method": method, "variant": v.name, "seed": seed, "steps": steps}
                        tasks.append(
                            Task(f"eval {tag}", "eval", argv, [ev], [train_id], [m], meta | {"stream": stream})
                        )
                        if m == model:
                            evals[v.name].append((f"eval {tag}", ev))
    _link_flag_files(tasks)
    if spec.reuse:
        tasks = reuse_finished(spec, tasks)
    for name, items in evals.items():
        if not items or not spec.report:
            continue
        report = out / ("report.md" if not name else f"report-{name}.md")
        argv = ["report", *[str(p) for _, p in items], "--out", str(report), "--force"]
        tasks.append(
            Task(
                "report" if not name else f"report {name}",
                "report",
                argv,
                [report],
                [i for i, _ in items],
                [p for _, p in items],
            )
        )
    return tasks


def flag_files(argv: list[str]) -> list[Path]:
    """The files named by :data:`PATH_FLAGS` in a command line (``--flag FILE`` or ``--flag=FILE``)."""
    out = []
    for i, a in enumerate(argv):
        name, eq, value = a.partition("=")
        if name in PATH_FLAGS and eq:
            out.append(Path(value))
        elif a in PATH_FLAGS and i + 1 < len(argv):
            out.append(Path(argv[i + 1]))
    return out


def _link_flag_files(tasks: list[Task]) -> None:
    """Every file a task's flags name becomes one of its inputs (its memo then hashes it, so editing a map re-runs
    the evals that read it), and a task that writes such a file becomes one of its dependencies."""
    writer = {Path(os.path.normpath(p)): t.id for t in tasks for p in t.outputs}
    for t in tasks:
        for f in (Path(os.path.normpath(f)) for f in flag_files(t.argv)):
            if f not in t.inputs:
                t.inputs.append(f)
            if f in writer and writer[f] not in t.deps and writer[f] != t.id:
                t.deps.append(writer[f])


# ------------------------------------------------------------------------------------------------ reuse
#: what says where a task writes, on what hardware and how verbosely, and how long a training runs: not part of
#: what it makes (a training's length is matched apart: a snapshot at S steps is the model a run of S steps writes)
_UNKEYED = ("out", "device", "steps", "snapshot_at", "force", "resume", "as_json", "plot", "video", "videos", "workers")
_REUSABLE = ("collect", "cluster", "train")
#: what says where an eval writes, on what hardware, and what more it keeps: not part of what it measures
_UNMEASURED = ("out", "device", "force", "as_json", "keep_plans", "video", "videos", "replan_plot", "plot")


@functools.cache
def _option_table(command: str) -> dict[str, tuple[str, bool, bool]]:
    """``command``'s options, from the CLI itself: option string -> (parameter name, takes a value, the value a
    flag sets: True, or False for its ``--no-`` form)."""
    cmd = _command(command)
    table: dict[str, tuple[str, bool, bool]] = {}
    for p in cmd.params:
        if p.param_type_name != "option":
            continue
        flag = bool(getattr(p, "is_flag", False))
        for o in p.opts:
            table[o] = (p.name, not flag, True)
        for o in p.secondary_opts:
            table[o] = (p.name, False, False)
    return table


def _real(path: str | Path) -> str:
    """A file's path with links resolved (``runs`` may be a link to another disk): one spelling per file."""
    return os.path.realpath(path)


def _regular_sha(path: str, cache: dict) -> str | None:
    """The sha256 of a regular file, else None (a folder, a FIFO or a missing file is never hashed)."""
    try:
        return _sha(Path(path), cache) if stat.S_ISREG(os.stat(path).st_mode) else None
    except OSError:
        return None


def walk_options(tokens: list[str], table: dict[str, tuple[str, bool, bool]]):
    """Walk a command line's tokens (the command's name left off) over its option table (:func:`_option_table`):
    yield (token, entry, value) for each option, in the ``--x=y`` or the ``--x y`` form, with ``value`` its value
    (None where the line ends before it; an option without one yields None), and (token, None, token) for each token
    that is not an option."""
    i = 0
    while i < len(tokens):
        token = tokens[i]
        name, eq, inline = token.partition("=")
        entry = table.get(name if eq and name.startswith("--") else token)
        i += 1
        if entry is None:
            yield token, None, token
        elif not entry[1]:
            yield token, entry, None
        elif eq and name.startswith("--"):
            yield token, entry, inline
        else:
            yield token, entry, tokens[i] if i < len(tokens) else None
            i += 1


def parse_command(argv: list[str], file_key=str) -> tuple[list[str], dict[str, object], list[tuple[str, str]]]:
    """A command line as what it asks for, independent of how its flags are spelled: (its arguments, its options by
    parameter name with the last value winning as on the command line, its ``--set``s with each one overridden later
    by the same key dropped, sorted unless one key lies inside another). Every argument and option value goes
    through ``file_key`` (a file's stand-in: its sha256, the task that wrote it, its name)."""
    positional, options, sets = [], {}, []
    for token, entry, value in walk_options(argv[1:], _option_table(argv[0])):
        if entry is None:
            positional.append(file_key(token))
            continue
        pname, takes_value, flag_value = entry
        value = ("" if value is None else value) if takes_value else flag_value
        if pname == "sets":
            k, _, v = str(value).partition("=")
            sets.append((k.strip(), v.strip()))
        else:
            options[pname] = file_key(value) if isinstance(value, str) else value
    # a later --set of the same key replaces all an earlier one set, whatever came between: the earlier is moot;
    # the order of the rest matters only where one key lies inside another (net= then net.dim=)
    sets = [kv for j, kv in enumerate(sets) if all(kv[0] != later[0] for later in sets[j + 1 :])]
    if not any(_nested(a, b) for j, (a, _) in enumerate(sets) for b, _ in sets[j + 1 :]):
        sets.sort()
    return positional, options, sets


def file_sha(path: str | Path, cache: dict) -> str | None:
    """The sha256 of the regular file at ``path`` (links resolved), else None; ``cache`` is the grid's."""
    return _regular_sha(_real(path), cache)


def _command_key(argv: list[str], written_by: dict[str, str], cache: dict) -> tuple[str, str | None, list[str]]:
    """What a collect/cluster/train command makes, independent of where and of how its flags are spelled
    (:func:`parse_command`, every file written by a task replaced by the key of the command that wrote it and every
    other file by its sha256, without the :data:`_UNKEYED` options); its ``--steps``; its ``--snapshot-at``
    steps."""

    def file_key(value: str) -> str:
        real = _real(value)
        if real in written_by:
            return written_by[real]
        sha = _regular_sha(real, cache)
        return f"sha256:{sha}" if sha else value

    positional, options, sets = parse_command(argv, file_key)
    steps = options.get("steps")
    snaps = [v.strip() for v in str(options.get("snapshot_at", "")).split(",") if v.strip()]
    kept = {k: v for k, v in options.items() if k not in _UNKEYED}
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
    for option, (pname, _, _) in reversed(list(_option_table(wanted[0]).items())):
        if option.startswith("--"):
            spelled[pname] = option
    (pos_a, opt_a, sets_a), (pos_b, opt_b, sets_b) = (
        parse_command(argv, lambda v: Path(v).name if os.sep in v else v) for argv in (made, wanted)
    )
    if pos_a != pos_b:
        return f"it reads {clip(' '.join(pos_a) or '(nothing)', 80)}, the grid's task {' '.join(pos_b)}"
    for name in sorted(set(opt_a) | set(opt_b)):
        a, b = opt_a.get(name), opt_b.get(name)
        if name not in _UNMEASURED and a != b:
            shown = ["(not given)" if v is None else clip(str(v), 40) for v in (a, b)]
            return f"{spelled.get(name, name)} {shown[0]} there, {shown[1]} in the grid"
    for key in sorted({k for k, _ in sets_a} | {k for k, _ in sets_b}):
        a, b = dict(sets_a).get(key), dict(sets_b).get(key)
        if a != b:
            shown = ["(not set)" if v is None else f"{key}={clip(v, 40)}" for v in (a, b)]
            return f"--set {clip(shown[0], 60)} there, {shown[1]} in the grid"
    if sets_a != sets_b:
        return "its --set values come in another order"
    return None


def _nested(a: str, b: str) -> bool:
    """Whether one dotted settings key lies inside the other (``net`` and ``net.dim``)."""
    return a.startswith(b + ".") or b.startswith(a + ".")


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
            text = _read_small(memo_file)
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
            if argv[0] not in _REUSABLE or not all(
                isinstance(f, dict) and all(isinstance(k, str) and isinstance(v, str) for k, v in f.items())
                for f in files
            ):
                continue
            if not outputs or any(_regular_sha(p, cache) != v for p, v in {**inputs, **outputs}.items()):
                continue
            found.append(memo)
    return sorted(found, key=lambda m: _REUSABLE.index(m["argv"][0]))


def _replace_files(argv: list[str], moved: dict[str, str]) -> list[str]:
    """``argv`` with every file of ``moved`` (a token, or the value of ``--flag=FILE``) replaced."""
    out = []
    for a in argv:
        name, eq, value = a.partition("=")
        if eq and name.startswith("--") and _real(value) in moved:
            out.append(f"{name}={moved[_real(value)]}")
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
        if t.kind not in _REUSABLE:
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
        left = [n for n in named if n and _real(n) in gone]
        if left:
            raise BadInput(
                f"reuse: {t.id} still names {left[0]}, which a reused task no longer writes here",
                hint="drop `reuse` from the grid, or name the file in the grid as it names its outputs",
            )
    spec._reused = {tid: moved[files[0]] for tid, files in dropped.items()}
    return kept


def _buffer(spec: GridSpec, env: str, flags: list[str], buffers: dict, tasks: list[Task]) -> tuple[str, Path]:
    """The cluster task and buffer of ``env``'s demos clustered with ``flags``, added to ``tasks`` on first use:
    runs with the same flags share one buffer (none: ``buffer-kK.h5``; else ``buffer-<hash of the flags>.h5``, since
    the flags may change k)."""
    key = json.dumps(flags)
    if key not in buffers:
        folder = spec.out / env
        demos = folder / "demos.h5"
        tag = hashlib.sha256(key.encode()).hexdigest()[:8] if flags else ""
        path = folder / (f"buffer-{tag}.h5" if flags else f"buffer-k{spec.k}.h5")
        task_id = f"cluster {env}" + (f"/{tag}" if tag else "")
        argv = ["cluster", str(demos), "--k", str(spec.k), "--seed", str(spec.data_seed), *flags, "--out", str(path)]
        tasks.append(Task(task_id, "cluster", argv, [path], [f"collect {env}"], [demos]))
        buffers[key] = (task_id, path)
    return buffers[key]


def train_snapshot(model: Path, step: int) -> Path:
    from cdrb_cli.stages.train import snapshot_path

    return snapshot_path(model, step)


# ------------------------------------------------------------------------------------------------ memo
def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", text).strip("_")


def _sha(path: Path, cache: dict) -> str | None:
    if not path.exists():
        return None
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns)
    if key not in cache:
        cache[key] = artifacts.sha256_file(path)
    return cache[key]


def memo_path(spec: GridSpec, task: Task) -> Path:
    return spec.out / ".grid" / f"{_slug(task.id)}.json"


#: the scene flags of plan and eval
_SCENE_FLAGS = ("--scene", "--maze-map")


def _meaning(task: Task) -> dict:
    """What a command means beyond its words, where a release changed it: a plan or an eval in a scene avoids the
    new obstacles by default (the family's tuned avoidance), so a memo written when it meant the plain model is out
    of date."""
    if task.kind in ("plan", "eval") and any(a in _SCENE_FLAGS or a.split("=")[0] in _SCENE_FLAGS for a in task.argv):
        return {"scene_avoid": "tuned by default"}
    return {}


def _fingerprint(task: Task, cache: dict) -> dict:
    return {
        "argv": task.argv,
        "cdrb": __version__,
        **_meaning(task),
        "inputs": {str(p): _sha(p, cache) for p in task.inputs},
        "outputs": {str(p): _sha(p, cache) for p in task.outputs},
    }


def _memo(spec: GridSpec, task: Task) -> dict | None:
    """The task's memo, or None (a memo that is not a small regular file of JSON is stale: the task is redone)."""
    text = _read_small(memo_path(spec, task))
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
    return memo == now and all(now["outputs"].values())


def written_here(spec: GridSpec, task: Task, cache: dict) -> bool:
    """Whether every output of ``task`` is the file this grid's memo says the task wrote: the grid's own artifact,
    which it may replace when the task is out of date (a file the memo does not vouch for is never overwritten)."""
    memo = _memo(spec, task)
    recorded = memo.get("outputs") if memo is not None else None
    now = {str(p): _sha(p, cache) for p in task.outputs}
    return isinstance(recorded, dict) and recorded == now and all(now.values())


def _write_memo(spec: GridSpec, task: Task, cache: dict) -> None:
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
    for out in [summary] + [p for t in tasks for p in t.outputs]:
        if out.resolve() in sources:
            raise BadInput(f"{out}: the grid would write over its own input file", hint="choose another `out` folder")
    if summary.exists():
        text = _read_small(summary, 1 << 26)
        try:
            body = json.loads(text) if text is not None else None
        except (ValueError, RecursionError):
            body = None
        if not isinstance(body, dict) or not {"tasks", "counts"} <= body.keys():
            raise BadInput(
                f"{summary}: exists and is not a grid summary; a grid run writes its summary there",
                hint="move the file or choose another `out` folder",
            )


# ------------------------------------------------------------------------------------------------ execution
def execute(payload: dict) -> dict:
    """Run one task's `cdrb` command in a fresh process (on this machine or a Ray worker). A training whose model
    file is there is continued with ``--resume``: a checkpoint an earlier attempt left unfinished, or a finished
    shorter run of the same settings that the grid now trains longer (a curve extended to more steps); the command
    itself refuses a file of other settings."""
    argv = list(payload["argv"])
    if payload["kind"] == "train" and Path(payload["outputs"][0]).is_file():
        argv.append("--resume")
    for out in payload["outputs"]:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
    # PYTHONSAFEPATH: the task's `python -m` must not import modules from the current folder (a `typer.py` beside
    # the grid would run in every task); cdrb is imported from where it is installed
    env = dict(os.environ, OMP_NUM_THREADS=str(max(1, int(payload["cpus"]))), PYTHONSAFEPATH="1")
    t = time.time()
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdrb_cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        preexec_fn=_die_with_parent(),
    )
    with _RUNNING_LOCK:
        _RUNNING.add(proc)
    try:
        _, stderr = proc.communicate()
    finally:
        with _RUNNING_LOCK:
            _RUNNING.discard(proc)
    tail = [ln for ln in stderr.splitlines() if ln.strip()][-STDERR_LINES:]
    return {"rc": proc.returncode, "seconds": time.time() - t, "stderr": tail}


#: the task processes this process started and that still run (the pool's threads start them)
_RUNNING: set[subprocess.Popen] = set()
_RUNNING_LOCK = threading.Lock()


def _die_with_parent():
    """What a task's process runs before it starts (Linux): ask the kernel to send it SIGTERM when the thread that
    started it dies, so a grid killed with -9 leaves no training running and holding its output's lock. The
    function is looked up here, in the parent: the child only calls it."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    return lambda: prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def stop_running(grace: float = 5.0) -> None:
    """SIGTERM every running task process (a training keeps its last checkpoint and exits), SIGKILL what is left
    after ``grace`` seconds."""
    with _RUNNING_LOCK:
        procs = list(_RUNNING)
    for p in procs:
        if p.poll() is None:
            p.terminate()
    deadline = time.time() + grace
    for p in procs:
        try:
            p.wait(timeout=max(0.0, deadline - time.time()))
        except subprocess.TimeoutExpired:
            p.kill()


@dataclass
class TaskResult:
    id: str
    kind: str
    status: Literal["done", "up to date", "failed", "skipped"] = "skipped"
    attempts: int = 0
    seconds: float = 0.0
    stderr: list[str] = field(default_factory=list)
    outputs: list[str] = field(default_factory=list)


class PoolBackend:
    """N local workers, each running one task's process at a time."""

    name = "local pool"

    def __init__(self, workers: int):
        self.workers = workers
        #: tasks handed over at once: the grid keeps the rest and picks them in its own order (see run_grid)
        self.capacity = workers
        self.pool = cf.ThreadPoolExecutor(max_workers=workers)

    def check(self, spec: GridSpec) -> None:
        pass

    def submit(self, payload: dict) -> cf.Future:
        return self.pool.submit(execute, payload)

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class RayBackend:
    """Tasks as Ray tasks with the CPUs/GPUs of their kind; ``address`` None starts Ray on this machine."""

    name = "ray"

    def __init__(self, address: str | None, workers: int | None):
        import ray

        kwargs = {"include_dashboard": False, "log_to_driver": False, "ignore_reinit_error": True}
        if address is None and workers:
            kwargs["num_cpus"] = workers
        ray.init(address=address, **kwargs)
        self.ray = ray
        self.remote = ray.remote(max_retries=0)(execute)
        total = ray.cluster_resources()
        self.workers, self.gpus = int(total.get("CPU", 0)), float(total.get("GPU", 0))

    def check(self, spec: GridSpec) -> None:
        """A task asking for GPUs the cluster lacks would wait forever: refuse the grid instead."""
        for kind, res in spec.resources.items():
            if res.gpus > self.gpus:
                raise BadInput(
                    f"resources.{kind}.gpus = {res.gpus:g}, but the Ray cluster has {self.gpus:g} GPUs",
                    hint="lower it in the grid file or add GPU workers",
                )

    def submit(self, payload: dict) -> cf.Future:
        # a task may not ask for more CPUs than the whole cluster has (it would never be scheduled)
        cpus = min(payload["cpus"], self.workers) if self.workers else payload["cpus"]
        fn = self.remote.options(num_cpus=cpus, num_gpus=payload["gpus"])
        return fn.remote(payload).future()

    def close(self) -> None:
        self.ray.shutdown()


#: seconds `cdrb grid --address` waits for the cluster to answer before saying it does not
ADDRESS_TIMEOUT = 5.0


def _probe(address: str) -> None:
    """A TCP connection to ``address`` (HOST:PORT or ray://HOST:PORT) within :data:`ADDRESS_TIMEOUT` seconds, so an
    address nobody listens on is one line instead of Ray retrying for minutes."""
    import socket

    hostport = address.removeprefix("ray://")
    host, _, port = hostport.rpartition(":")
    host = host.strip("[]")
    try:
        socket.create_connection((host, int(port)), timeout=ADDRESS_TIMEOUT).close()
    except (OSError, ValueError) as exc:
        reason = getattr(exc, "strerror", None) or type(exc).__name__
        raise BadInput(
            f"--address {address}: no Ray cluster answers there within {ADDRESS_TIMEOUT:g} s ({reason})",
            hint="start the head node (`ray start --head`) or check the host and port",
        ) from None


def make_backend(backend: str, workers: int | None, address: str | None):
    """``auto``: Ray when it is installed, else the local pool."""
    if address is not None and not re.fullmatch(r"(ray://)?[A-Za-z0-9_.\-\[\]:]+:[0-9]{1,5}|auto", address):
        raise BadInput(
            f"--address {address[:100]!r}: not a Ray address",
            hint="use HOST:PORT (a head node's GCS port) or ray://HOST:PORT (Ray Client), or auto",
        )
    if backend in ("auto", "ray"):
        try:
            import ray  # noqa: F401
        except ImportError:
            if backend == "ray" or address:
                raise BadInput(
                    "--backend ray: Ray is not installed", hint='pip install "cdrb-cli[ray]", or use --backend pool'
                ) from None
            ui.log("Ray is not installed: running on a local pool")
            backend = "pool"
        else:
            if address not in (None, "auto"):
                _probe(address)
            return RayBackend(address, workers)
    if address:
        raise BadInput("--address needs the Ray backend", hint="drop --address or use --backend ray")
    return PoolBackend(workers or max(1, os.cpu_count() or 1))


@dataclass
class GridRun:
    results: list[TaskResult]
    summary: Path
    seconds: float
    backend: str

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.results)


def run_grid(
    spec: GridSpec,
    backend,
    retries: int = 1,
    on_event: Callable[[str, TaskResult], None] | None = None,
    tasks: list[Task] | None = None,
) -> GridRun:
    """Execute the grid's tasks (``tasks``, default: the expanded grid) on ``backend``: each when its inputs are
    ready, skipped when its memo is current, retried ``retries`` times on failure; dependants of a failed task are
    skipped. A task reading another grid's file (``reuse``) fails if that file changed since the grid was expanded.
    A backend with a ``capacity`` (the local pool) is handed at most that many tasks at once, the ready task first
    in the grid's order (environment by environment, each model's evals right after it): one environment's rows
    are finished before the next one's trainings start, so a grid stopped part-way leaves whole rows. Writes
    OUT/grid.json."""
    t0 = time.time()
    tasks = expand(spec) if tasks is None else tasks
    order = {t.id: i for i, t in enumerate(tasks)}
    capacity = getattr(backend, "capacity", None)
    queued: list[Task] = []  # ready to run, waiting for a free slot of the backend
    results = {t.id: TaskResult(t.id, t.kind, outputs=[str(p) for p in t.outputs]) for t in tasks}
    state = {t.id: "pending" for t in tasks}
    cache = spec._shas
    running: dict[cf.Future, Task] = {}
    emit = on_event or (lambda *_: None)

    def submit(task: Task) -> None:
        changed = [p for p, sha in task.meta.get("expect", {}).items() if _regular_sha(p, cache) != sha]
        if changed:  # another grid rewrote a file this one took from it (e.g. a curve trained on): never read it
            state[task.id], results[task.id].status = "failed", "failed"
            results[task.id].stderr = [f"{changed[0]}: changed since this grid took it from a finished run; run again"]
            emit("failed", results[task.id])
            return
        res = spec.resources[task.kind]
        argv = task.argv
        if task.kind in ("collect", "cluster", "eval") and written_here(spec, task, cache):
            argv = [*argv, "--force"]  # this grid's own artifact, now out of date (its model was trained on)
        payload = {"argv": argv, "kind": task.kind, "outputs": [str(p) for p in task.outputs]}
        payload |= {"cpus": res.cpus, "gpus": res.gpus}
        results[task.id].attempts += 1
        state[task.id] = "running"
        running[backend.submit(payload)] = task

    while True:
        progressed = True
        while progressed:  # settle everything that needs no run: up-to-date tasks, dependants of failures
            progressed = False
            for task in tasks:
                if state[task.id] != "pending":
                    continue
                deps = [state[d] for d in task.deps]
                if any(s in ("failed", "skipped") for s in deps):
                    state[task.id] = "skipped"
                    results[task.id].stderr = [f"not run: {next(d for d in task.deps if state[d] != 'done')} failed"]
                    emit("skipped", results[task.id])
                    progressed = True
                elif all(s == "done" for s in deps):
                    if is_done(spec, task, cache):
                        state[task.id] = "done"
                        results[task.id].status = "up to date"
                        emit("up to date", results[task.id])
                        progressed = True
                    else:
                        state[task.id] = "queued"
                        queued.append(task)
            queued.sort(key=lambda t: order[t.id])
            while queued and (capacity is None or len(running) < capacity):
                task = queued.pop(0)
                submit(task)
                progressed = progressed or state[task.id] == "failed"  # settle its dependants next pass
        if not running:
            break
        finished, _ = cf.wait(list(running), return_when=cf.FIRST_COMPLETED)
        for fut in finished:
            task = running.pop(fut)
            res = results[task.id]
            try:
                out = fut.result()
            except Exception as exc:  # the worker itself died (Ray) or could not start the process
                out = {
                    "rc": -1,
                    "seconds": 0.0,
                    "stderr": [f"{type(exc).__name__}: {' '.join(str(exc).split())[:300]}"],
                }
            res.seconds += out["seconds"]
            if out["rc"] == 0:  # (the hash cache is keyed by size and mtime: rewritten files are hashed afresh)
                _write_memo(spec, task, cache)
                state[task.id], res.status, res.stderr = "done", "done", []
                emit("done", res)
            elif res.attempts <= retries:
                res.stderr = out["stderr"]
                emit("retry", res)
                submit(task)
            else:
                state[task.id], res.status, res.stderr = "failed", "failed", out["stderr"]
                emit("failed", res)
    summary = spec.out / "grid.json"
    spec.out.mkdir(parents=True, exist_ok=True)
    ordered = [results[t.id] for t in tasks]
    body = {
        "seconds": time.time() - t0,
        "backend": backend.name,
        "tasks": [r.__dict__ for r in ordered],
        "counts": {s: sum(r.status == s for r in ordered) for s in ("done", "up to date", "failed", "skipped")},
        "reused": spec._reused,
    }
    with artifacts.atomic_path(summary) as tmp:
        tmp.write_text(json.dumps(body, indent=1, default=str))
    return GridRun(ordered, summary, time.time() - t0, backend.name)


def grid(
    path: Path,
    backend: str = "auto",
    workers: int | None = None,
    address: str | None = None,
    retries: int = 1,
    dry_run: bool = False,
    overrides: list[str] = (),
    includes: list[Path] = (),
) -> GridRun | list[Task]:
    """Load, expand and run a grid file with a progress bar and one line per finished task (stderr)."""
    spec = load_grid(path, overrides, includes)
    tasks = expand(spec)
    if spec._reused:
        kinds = [t.split(" ", 1)[0] for t in spec._reused]
        ui.log(
            "taken from finished runs of "
            + ", ".join(str(f) for f in spec.reuse)
            + ": "
            + ", ".join(f"{kinds.count(k)} {k}" for k in _REUSABLE if k in kinds)
            + " (not run here)"
        )
    check_outputs(spec, tasks)  # a dry run lists what a real one would do, so it is refused the same way
    if dry_run:
        return tasks
    spec.out.mkdir(parents=True, exist_ok=True)
    with artifacts.claim_output(spec.out / "grid.json", force=True, flag=f"{path}: out ="):
        runner = make_backend(backend, workers, address)
        try:
            runner.check(spec)
        except BadInput:
            runner.close()
            raise
        ui.log(f"{len(tasks)} tasks on {runner.name} ({runner.workers} workers/CPUs), artifacts in {spec.out}")
        try:
            with ui.progress() as bar:
                job = bar.add_task("grid", total=len(tasks), info="")

                def on_event(event: str, res: TaskResult) -> None:
                    if event == "retry":
                        why = res.stderr[-1] if res.stderr else "no stderr"
                        ui.log(f"retry   {res.id} (attempt {res.attempts} failed: {why})")
                        return
                    secs = f"{res.seconds:7.1f}s" if event == "done" else " " * 8
                    ui.log(f"{event:10s} {secs}  {res.id}")
                    bar.advance(job)

                run = run_grid(spec, runner, retries=retries, on_event=on_event, tasks=tasks)
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM: the running tasks stop too, instead of being waited for
            stop_running()
            raise
        finally:
            runner.close()
    failed = [r for r in run.results if r.status == "failed"]
    for r in failed:
        ui.warn(f"{r.id} failed after {r.attempts} attempts:\n  " + "\n  ".join(r.stderr or ["(no stderr)"]))
    if failed:
        raise RunFailed(
            f"{len(failed)} of {len(run.results)} grid tasks failed ({', '.join(r.id for r in failed[:3])}"
            f"{', ...' if len(failed) > 3 else ''}); {run.count('skipped')} skipped; details in {run.summary}"
        )
    return run
