"""The grid file: its records (settings, variants, extensions, resources, the grid itself), reading them from
TOML with one-line errors, and file paths in flag lists anchored at the file that names them."""

from __future__ import annotations

import json
import os
from collections.abc import Collection
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

from cdrb_cli.configs import MAX_SEED
from cdrb_cli.errors import BadInput
from cdrb_cli.orchestration.grid.commands import map_input_files
from cdrb_cli.settings import NULL_KEY, clip

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
    flags (dotted keys in the table's order, values as JSON; the keys of a ``null`` list set to null, which TOML
    cannot write): the same command, so the same memo key."""
    if not isinstance(value, dict):
        return value
    flags: list[str] = []

    def walk(node: dict, prefix: str) -> None:
        for key, item in node.items():
            if key == NULL_KEY and isinstance(item, list) and all(isinstance(x, str) for x in item):
                flags.extend(x for name in item for x in ("--set", f"{prefix}{name}=null"))
            elif isinstance(item, dict):
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
    `cdrb select` chose on the tuning stream. ``meta`` is provenance (the rule, the tuning grid); a grid that
    includes a selection checks that it holds a choice for every run its tuning grid tunes."""

    include: list[Path] = Field(default_factory=list, description="more settings files, before this one's")
    settings: list[Settings] = Field(default_factory=list)
    meta: dict[str, str] = Field(default_factory=dict, description="provenance: the rule, the tuning grid")


class Scoped(_Strict):
    """An entry that applies to some environments and methods (``envs``/``methods`` None: all)."""

    def applies(self, env: str, method: str) -> bool:
        return (self.methods is None or method in self.methods) and (self.envs is None or env in self.envs)


class Variant(Scoped):
    """One more axis of the grid: a named set of extra flags; its evals go to OUT/ENV/NAME/ and get their own report.

    A variant with ``train`` flags trains its own models (in OUT/ENV/NAME/); one without is *eval-only*: it evaluates
    the grid's base models (OUT/ENV/METHOD-sSEED.h5, trained once with no variant flags), e.g. a controller, a plan
    clock, a sampler, denoising steps or a re-planning trigger tried on one trained model."""

    name: str = Field(
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.=-]*$",
        max_length=64,
        description="folder name of the variant's runs (at most 64 characters: it is also part of file names)",
    )
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


class Extension(Scoped):
    """A learning curve run past the grid's ``steps`` for some environments and methods (where `cdrb select` finds
    it still rising): the same runs, resumed to ``steps``; the grid's own ``steps`` and every earlier entry that
    applies to the same runs become snapshots, so each stage's final model stays a point of the curve. Entries that
    apply to the same runs go in increasing steps. It is written in the grid file, so the curve's length is part of
    the study it belongs to."""

    envs: list[str] | None = Field(None, description="the environments whose curves run further (default: all)")
    methods: list[str] | None = Field(None, description="the methods whose curves run further (default: all)")
    variants: list[str] | None = Field(
        None,
        description="the variants whose curves run further (default: all; an eval-only variant's name means the "
        "base models it evaluates)",
    )
    steps: Steps = Field(description="the curve's new last point (more than the grid's `steps`)")

    def extends(self, env: str, method: str, model_variant: str, base_names: Collection[str]) -> bool:
        """Whether the entry extends the runs of ``model_variant`` (the name of a variant with its own models, or
        "" for the base models, which ``base_names``, the eval-only variants of ``env`` x ``method``, stand for)."""
        if not self.applies(env, method):
            return False
        if self.variants is None:
            return True
        return model_variant in self.variants if model_variant else bool(set(base_names) & set(self.variants))


class Resources(_Strict):
    # strict: true is no count of cores and "2" no number (a grid file's values are read as written)
    cpus: float = Field(
        1.0,
        gt=0,
        le=1024,
        strict=True,
        allow_inf_nan=False,
        description="CPU cores a task of this kind asks Ray for (and its torch threads; at most 1024)",
    )
    gpus: float = Field(
        0.0,
        ge=0,
        le=64,
        strict=True,
        allow_inf_nan=False,
        description="GPUs a task of this kind asks Ray for (fractions share one GPU; at most 64)",
    )


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
    demos_for: dict[str, Annotated[int, Strict(), Field(ge=2, le=1_000_000)]] = Field(
        default_factory=dict,
        description="demonstrations for the environments whose datasets differ in size from `demos` (e.g. OGBench's "
        "giant navigate, 500; stitch, 5,000), by environment id",
    )
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
    steps_cap: Steps | None = Field(
        None,
        description="tuning grids: the longest any curve runs ([[extend]] entries stop here; without `steps`, each "
        "training's own length, its flags' or its preset's); `cdrb select` sums up in one line the curves that still "
        "rise at it instead of asking to extend each",
    )
    extend: list[Extension] = Field(
        default_factory=list,
        max_length=1000,
        description="learning curves run further for some envs/methods: [[extend]] entries (the last that applies "
        "wins); each such run trains to the entry's steps and `steps` becomes one more snapshot",
    )
    shared_budget: Bool = Field(
        False,
        description="tuning grids: the planners of one environment train to one length (`cdrb select` picks each at "
        "the longest length any of them is chosen at), and a curve that still rises extends them all",
    )
    report: Bool = Field(True, description="write OUT/report[-VARIANT].md (tuning grids are read by `cdrb select`)")
    tensorboard: Bool = Field(
        False,
        description="every training also writes TensorBoard event files to OUT/tensorboard/ENV/[VARIANT/]METHOD-sSEED "
        "as it runs (`tensorboard --logdir OUT/tensorboard`; the tensorboard extra)",
    )
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
    #: every variant the file declares, before `--set variants=[...]` narrows ``variants``: an [[extend]] entry's
    #: variant names mean the same runs whichever arms a run selects
    _file_variants: list[Variant] | None = PrivateAttr(default=None)
    #: sha256 of the files read, by (path, size, mtime): shared by reuse at expansion and the run's memo checks
    _shas: dict = PrivateAttr(default_factory=dict)

    def curve(self, env: str, method: str, model_variant: str = "") -> tuple[int | None, list[int]]:
        """The training length and the snapshot steps (sorted) of ``method``'s runs on ``env`` in ``model_variant``
        (a variant with its own models; "": the base models): the grid's, or those of the last :class:`Extension`
        that applies, whose steps end the curve; the grid's steps and those of the earlier extensions that stop
        short of it are snapshots, so each stage's final model stays a point of the curve when a later stage
        resumes it."""
        exts = self.extensions_of(env, method, model_variant)
        if not exts:
            return self.steps, sorted(self.snapshot_at)
        last = exts[-1].steps
        stages = {self.steps, *(e.steps for e in exts[:-1] if e.steps < last)}
        return last, sorted({*self.snapshot_at, *stages})

    def extensions_of(self, env: str, method: str, model_variant: str = "") -> list[Extension]:
        """The [[extend]] entries that resume ``method``'s runs on ``env`` in ``model_variant`` (see :meth:`curve`),
        judged on the file's variants, not only those a narrowed run selected."""
        variants = self.variants if self._file_variants is None else self._file_variants
        base_names = [v.name for v in variants if not v.own_model and v.applies(env, method)]
        return [e for e in self.extend if e.extends(env, method, model_variant, base_names)]

    def demos_of(self, env: str) -> int:
        """The demonstrations collected for ``env``."""
        return self.demos_for.get(env, self.demos)

    @field_validator("demos_for")
    @classmethod
    def _known_envs(cls, value: dict[str, int]) -> dict[str, int]:
        from cdrb_cli.envs.registry import make_spec

        for env in value:
            try:
                make_spec(env)
            except BadInput as exc:  # as pydantic's error, so the message names the file and the key
                raise ValueError(f"{exc.message} ({exc.hint})" if exc.hint else exc.message) from None
        return value

    @field_validator("steps_cap")
    @classmethod
    def _cap_at_least_steps(cls, value: int | None, info) -> int | None:
        steps = info.data.get("steps")
        if value is not None and steps is not None and value < steps:
            raise ValueError(f"steps_cap = {value} is below the grid's steps = {steps}: no run may pass the cap")
        return value

    @field_validator("extend")
    @classmethod
    def _under_the_cap(cls, value: list[Extension], info) -> list[Extension]:
        cap = info.data.get("steps_cap")
        over = next((e for e in value if cap is not None and e.steps > cap), None)
        if over is not None:
            raise ValueError(f"an [[extend]] entry trains to {over.steps} steps, beyond steps_cap = {cap}")
        return value

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


def read_small(path: Path, limit: int = MAX_FILE_BYTES) -> str | None:
    """The text of ``path`` through the guarded reader (a regular file of at most ``limit`` bytes, no link out of
    its folder, never blocking on a FIFO); None when it is not one."""
    from cdrb_cli.artifacts.core import read_input_text

    try:
        return read_input_text(path, "", limit)
    except BadInput:
        return None


def read_toml(path: Path, what: str, flag: str = "") -> dict:
    from cdrb_cli.files import parse_toml

    if not os.path.lexists(path):
        raise BadInput(f"{path}: no such {what}", hint="see docs/cli.md, `cdrb grid`, for the format")
    text = read_small(path)
    if text is None:
        raise BadInput(
            f"{path}: not a {what} (a regular text file of at most {MAX_FILE_BYTES >> 20} MiB, no link out of its "
            "folder)",
            hint="name the TOML file itself",
        )
    return parse_toml(text, f"{flag} {path}".strip(), hint="fix the file")


def error_text(err: dict) -> str:
    """A pydantic error of a grid or settings file in the file's own words: a key the format does not have, a path
    that is not text; pydantic's message otherwise."""
    if err.get("type") == "extra_forbidden":
        return "not a key of this file's format"
    if err.get("type") in ("path_type", "path_not_str"):
        return 'a path is written as a string, e.g. "runs/NAME"'
    return err["msg"]


def validated(model: type[BaseModel], raw: dict, path: Path):
    try:
        return model.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = clip(".".join(str(p) for p in err["loc"]), 80) or "(top level)"
        raise BadInput(f"{path}: {where}: {error_text(err)}", hint="see docs/cli.md, `cdrb grid`") from None


def _anchored(flags: list[str], command: str, base: Path) -> list[str]:
    """``flags`` of ``command`` with every relative file it reads made absolute against ``base`` (the folder of the
    file that declares them), as `out` is: a grid means the same files from whatever folder it is run."""
    return map_input_files(flags, command, lambda v: v if Path(v).is_absolute() else str(base / v))


def anchor_all(items: list, base: Path) -> list:
    """Settings or variants with their flag lists anchored at ``base``."""
    fields = ("collect", "cluster", "train", "eval")
    return [
        item.model_copy(update={k: _anchored(getattr(item, k), k, base) for k in fields if hasattr(item, k)})
        for item in items
    ]


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
