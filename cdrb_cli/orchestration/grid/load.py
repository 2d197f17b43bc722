"""`load_grid`: a grid file and the settings files it includes, validated into a :class:`GridSpec`."""

from __future__ import annotations

import json
import os
from pathlib import Path

from pydantic import (
    ValidationError,
)

from cdrb_cli import ui
from cdrb_cli.configs import MAX_SEED
from cdrb_cli.errors import BadInput
from cdrb_cli.orchestration.grid.checks import check_commands
from cdrb_cli.orchestration.grid.expansion import flags_for, model_variants
from cdrb_cli.orchestration.grid.flags import check_flags, parse_command
from cdrb_cli.orchestration.grid.spec import (
    MAX_TASKS,
    GridSpec,
    Scoped,
    Settings,
    SettingsFile,
    Variant,
    anchor_all,
    error_text,
    read_toml,
    validated,
)
from cdrb_cli.settings import clip

#: the most settings files one grid's includes may expand to (a file included twice counts twice), and the deepest
#: chain of includes: each file is read once, but fan-out (a file including the next 40 times, four levels down)
#: would otherwise expand to millions
MAX_INCLUDES = 1_000
MAX_INCLUDE_DEPTH = 32


def _included_settings(
    paths: list[Path], base: Path, chain: tuple[Path, ...], read: list[Path] | None = None, seen: dict | None = None
) -> list[Settings]:
    """The settings of ``paths`` (relative to ``base``) in order, each file's own includes first; every file read
    is appended to ``read``. ``seen``: the files already read (each is read once) and the includes expanded so far,
    shared by the whole grid."""
    seen = {"files": {}, "count": 0} if seen is None else seen
    out: list[Settings] = []
    if len(chain) > MAX_INCLUDE_DEPTH:
        raise BadInput(
            f"{chain[-1]}: includes nest more than {MAX_INCLUDE_DEPTH} files deep", hint="flatten the includes"
        )
    for rel in paths:
        given = Path(os.path.normpath(base / rel))
        path = given.resolve()
        if path in chain:
            raise BadInput(f"{chain[-1]}: include {rel}: includes itself (through {path.name})", hint="remove the loop")
        seen["count"] += 1
        if seen["count"] > MAX_INCLUDES:
            raise BadInput(
                f"{chain[-1]}: its includes expand to more than {MAX_INCLUDES} settings files (it includes "
                f"{len(paths)} files, and they include more)",
                hint="include each settings file once",
            )
        if path not in seen["files"]:
            seen["files"][path] = validated(SettingsFile, read_toml(given, "settings file"), path)
            if read is not None:
                read.append(path)
        sfile = seen["files"][path]
        out += _included_settings(sfile.include, path.parent, (*chain, path), read, seen)
        out += anchor_all(sfile.settings, path.parent)
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
    except (RecursionError, ValueError):  # nesting past the recursion limit; an integer of thousands of digits
        raise BadInput(
            f"--set {clip(text)}: the value nests arrays or tables too deep, or holds a number too long, to read",
            hint="e.g. --set 'seeds=[0, 1]'",
        ) from None


def _origin(path: Path, overrides: list[str], *keys) -> str:
    """Where a top-level key's value came from: the ``--set`` of the first of ``keys`` that was set (each key's
    last ``--set``), else the grid file."""
    given = {parse_override(t)[0]: t for t in overrides}
    for key in keys:
        if key in given:
            return f"--set {clip(given[key])}"
    return str(path)


def _check_selections(spec: GridSpec, path: Path, files: dict[Path, SettingsFile]) -> None:
    """Refuse a run its included selection should have chosen for and did not: an environment x method that the
    selection's tuning grid (``meta.tuning_grid``) tunes but the selection holds no choice for (it was written
    before that run was tuned), which would otherwise run with the defaults, unchosen."""
    for where, sfile in files.items():
        tuning = _tuning_grid(where, sfile.meta.get("tuning_grid"))
        if tuning is None:
            continue
        try:
            raw = read_toml(tuning, "grid file")
        except BadInput:
            continue  # provenance only: a tuning grid moved away is not this grid's error
        envs, methods = raw.get("envs"), raw.get("methods")
        if not all(isinstance(x, list) and all(isinstance(i, str) for i in x) for x in (envs, methods)):
            continue  # not a grid that names its runs: nothing to hold the selection to
        tuned = {(e, m) for e in envs for m in methods}
        chosen = {(s.env, s.method) for s in sfile.settings}
        out = where.relative_to(Path.cwd()) if where.is_relative_to(Path.cwd()) else where
        for env in spec.envs:
            for method in spec.methods:
                if (env, method) in tuned and (env, method) not in chosen:
                    raise BadInput(
                        f"{path}: {method} on {env}: {where.name} holds no choice for it, though "
                        f"{sfile.meta['tuning_grid']} tunes it",
                        hint=f"run `cdrb select {sfile.meta['tuning_grid']} --out {out}` once its runs are done, "
                        "or narrow the grid (--set envs=/methods=)",
                    )


def _tuning_grid(selection: Path, name: str | None) -> Path | None:
    """The tuning grid a selection names (as `cdrb select` was given it: relative to where it ran, the checkout's
    root for the shipped files), looked for beside the selection and up its folders; None when not found."""
    if not name or "\0" in name:
        return None
    given = Path(name)
    try:
        if given.is_absolute():
            return given if given.is_file() else None
        for folder in [Path.cwd(), *selection.parents]:
            if (folder / given).is_file():
                return folder / given
    except OSError:  # a name past the system's limits: no file
        return None
    return None


def load_grid(path: Path, overrides: list[str] = (), extra_includes: list[Path] = ()) -> GridSpec:
    """Read and check a grid file: unknown keys, environments and methods are one-line errors naming the file.

    ``include`` files' settings come first (in order), then the grid's own; ``extra_includes`` (`cdrb grid
    --include`, relative to the current folder) come last, so they override both. ``overrides`` (`cdrb grid --set
    KEY=VALUE`) replace top-level keys of the file; an ``out`` given so is relative to the current folder."""
    raw = read_toml(Path(path), "grid file")  # read as given: a link out of its folder is refused
    path = Path(path).resolve()
    cwd_out, set_keys, variant_names = _apply_overrides(raw, overrides)
    if isinstance(raw.get("out"), str) and not raw["out"].strip():  # "" is "." to a Path, " " a folder named so
        raise BadInput(f"{_origin(path, overrides, 'out')}: out = {raw['out']!r}: an empty path",
                       hint='name the folder of the grid\'s artifacts, e.g. out = "runs/NAME"')  # fmt: skip
    try:
        spec = GridSpec.model_validate(raw)
    except ValidationError as exc:
        err = exc.errors()[0]
        where = clip(".".join(str(p) for p in err["loc"]), 80) or "(top level)"
        msg = error_text(err)
        given, key = err.get("input"), err["loc"][0] if err["loc"] else ""
        if err.get("type") == "list_type" and len(err["loc"]) == 1:  # a TOML list, even of one value
            if str(given).lstrip().startswith("["):  # `--set` text that is no TOML: a list with wrong brackets
                msg += f" ({clip(given, 60)} is not a TOML list: write e.g. {key}=[0, 1])"
            else:
                msg += f" (a TOML list, e.g. {key}=[{clip(json.dumps(given, default=str), 60)}])"
        raise BadInput(f"{_origin(path, overrides, *err['loc'][:1])}: {where}: {msg}",
                       hint="see docs/cli.md, `cdrb grid`") from None  # fmt: skip
    read = [path]
    seen = {"files": {}, "count": 0}
    spec.settings = (
        _included_settings(spec.include, path.parent, (path,), read, seen)
        + anchor_all(spec.settings, path.parent)
        + _included_settings(list(extra_includes), Path.cwd(), (path,), read, seen)
    )
    spec._file_variants = anchor_all(spec.variants, path.parent)
    spec.variants = _pick_variants(spec._file_variants, variant_names, path, overrides)
    spec._sources = read
    spec.out = cwd_out or (path.parent / spec.out).resolve()
    if spec.out == (Path.cwd().resolve() if cwd_out else path.parent):  # its artifacts among the experiment files
        raise BadInput(f"{_origin(path, overrides, 'out')}: out = {spec.out}: the grid file's or the current folder, "
                       "not a folder of the grid's own", hint='e.g. out = "runs/NAME"')  # fmt: skip
    check_flags(spec, path)
    _check_out(spec.out, _origin(path, overrides, "out"))
    _check_reuse(spec, path, overrides, set_keys)
    _check_names_given(spec, path, overrides, set_keys)
    _check_lengths_and_seeds(spec, path, overrides, set_keys)
    _check_selections(spec, path, seen["files"])
    if spec.tensorboard:  # every training would fail on a missing extra: one line now
        from cdrb_cli.stages.train_log import summary_writer

        try:
            summary_writer()
        except BadInput as exc:
            raise BadInput(f"{_origin(path, overrides, 'tensorboard')}: tensorboard = true: {exc.message}",
                           hint=exc.hint) from None  # fmt: skip
    _warn_idle(spec, path, overrides, set_keys)
    return spec


#: top-level grid keys that hold tables, which `--set` does not replace
_NOT_SET = ("settings", "include", "resources")


def _apply_overrides(raw: dict, overrides: list[str]) -> tuple[Path | None, set[str], object]:
    """`cdrb grid --set KEY=VALUE` applied to the file's top-level keys: the ``out`` given so (relative to the
    current folder), the keys set, and the variant names ``--set variants=`` selects (None: every variant)."""
    cwd_out, set_keys, variant_names = None, set(), None
    for text in overrides:
        key, value = parse_override(text)
        set_keys.add(key)
        if key == "variants":  # names: run those of the file's variants only (one arm of an ablation)
            variant_names = value
            continue
        if key not in GridSpec.model_fields or key in _NOT_SET:
            raise BadInput(
                f"--set {clip(text)}: {clip(repr(key), 60)} is not a top-level grid key that --set can change",
                hint="one of "
                + ", ".join(k for k in GridSpec.model_fields if k not in _NOT_SET)
                + " (variants: a list of the file's variant names to run)",
            )
        raw[key] = value
        if key == "out":
            cwd_out = Path(str(value)).resolve()
    return cwd_out, set_keys, variant_names


def _pick_variants(variants: list, names, path: Path, overrides: list[str]) -> list:
    """The file's variants, or only those ``--set variants=[...]`` names (in the file's order)."""
    if names is None:
        return variants
    where = _origin(path, overrides, "variants")
    if isinstance(names, str):
        names = [names]
    known = [v.name for v in variants]
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise BadInput(f"{where}: variants: give a list of the file's variant names",
                       hint=f'e.g. --set \'variants=["{known[0] if known else "NAME"}"]\'')  # fmt: skip
    unknown = [n for n in names if n not in known]
    if unknown:
        raise BadInput(f"{where}: variants: {clip(', '.join(unknown), 80)}: no such variant in {path.name}",
                       hint="its variants: " + (", ".join(known) or "none"))  # fmt: skip
    return [v for v in variants if v.name in names]


def _check_reuse(spec: GridSpec, path: Path, overrides: list[str], set_keys: set[str]) -> None:
    """The ``reuse`` folders, made absolute: never the grid's own `out`, never a file; a missing one warned of."""
    if any(not str(r).strip() or str(r) == "." for r in spec.reuse):
        raise BadInput(f"{_origin(path, overrides, 'reuse')}: reuse: an empty path (it would name the grid file's "
                       "own folder)", hint="list other grids' `out` folders")  # fmt: skip
    spec.reuse = [(Path.cwd() if "reuse" in set_keys else path.parent).joinpath(r).resolve() for r in spec.reuse]
    if len(set(spec.reuse)) != len(spec.reuse):
        raise BadInput(f"{_origin(path, overrides, 'reuse')}: reuse: names a folder twice",
                       hint="list each folder once")  # fmt: skip
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
        elif not (folder / ".grid").is_dir():
            ui.warn(f"reuse: {folder}: no grid has run there (it has no .grid/), so nothing is reused from it")


def _warn_idle(spec: GridSpec, path: Path, overrides: list[str], set_keys: set[str]) -> None:
    """Warn, once the grid is known to be sound, of what it names but does not run: a method and environment no
    variant applies to, a ``demos_for`` entry for an environment it does not run (quiet where --set narrowed it)."""
    bare = [f"{m} on {e}" for e in spec.envs for m in spec.methods if not any(v.applies(e, m) for v in spec.variants)]
    if spec.variants and bare and not {"variants", "envs", "methods"} & set_keys:  # (narrowed on purpose: quiet)
        # with variants, only they run: a pair none of them covers is left out entirely
        ui.warn(f"{_origin(path, overrides, 'variants')}: no variant applies to {clip(', '.join(bare), 200)}, so "
                "the grid neither trains nor evaluates it")  # fmt: skip
    idle = [e for e in spec.demos_for if e not in spec.envs]
    if idle and "envs" not in set_keys:  # (a grid narrowed with --set envs leaves entries idle on purpose)
        ui.warn(f"{_origin(path, overrides, 'demos_for')}: demos_for: {', '.join(idle)}: not among the grid's "
                "environments, so it does nothing here")  # fmt: skip


def _check_names_given(spec: GridSpec, path: Path, overrides: list[str], set_keys: set[str]) -> None:
    """Every environment and method the grid, its settings and its variants name exists; variant names are
    distinct folders."""
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.methods.registry import METHODS

    for env in spec.envs:
        try:
            make_spec(env)
        except BadInput as exc:
            raise BadInput(f"{_origin(path, overrides, 'envs')}: envs: {exc.message}",
                           hint="`cdrb envs` lists them") from None  # fmt: skip
    for m in spec.methods:
        METHODS.get(m, f"{_origin(path, overrides, 'methods')}: methods")
    check_commands(spec, path)
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


def _check_lengths_and_seeds(spec: GridSpec, path: Path, overrides: list[str], set_keys: set[str]) -> None:
    """Seeds, snapshots and extensions are consistent, evaluation seeds stay in range and pool no seed twice, and
    the grid is not too large."""
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
        _check_extension_variants(where, ext, spec, path.name, narrowed=bool({"envs", "methods"} & set_keys))
    if spec.extend:
        _check_extension_order(spec, _origin(path, overrides, "extend", "steps"))
        _check_snapshot_steps(spec, _origin(path, overrides, "extend", "steps"))
    _check_train_steps(spec, _origin(path, overrides, "steps_cap", "steps"))
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
    per_run = 2 + len(spec.snapshot_at) + len(spec.extend)
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


def _check_extension_variants(where: str, ext, spec: GridSpec, file: str, narrowed: bool) -> None:
    """An [[extend]] entry's ``variants`` name variants of the file (also when --set variants=[...] runs only some
    of them), not an empty list, and, unless the run was narrowed with --set envs/methods, each names runs the
    entry's own envs and methods reach (else it would extend nothing, silently)."""
    declared = spec._file_variants if spec._file_variants is not None else spec.variants
    by_name = {v.name: v for v in declared}
    unknown = sorted(set(ext.variants or ()) - by_name.keys())
    if ext.variants == [] or unknown:
        raise BadInput(
            f"{where}: variants: {clip(', '.join(unknown), 80) or '[]'}: "
            + (f"no such variant in {file}" if unknown else "applies to nothing"),
            hint="name the grid's [[variants]], or leave variants out to mean all",
        )
    if narrowed:
        return
    for name in ext.variants or ():
        if not any(ext.applies(e, m) and by_name[name].applies(e, m) for e in spec.envs for m in spec.methods):
            raise BadInput(
                f"{where}: variants: {clip(name, 60)} has no runs in this entry's envs and methods, so it would "
                "extend nothing",
                hint="widen the entry's envs/methods to the variant's, or drop the name",
            )


def _check_extension_order(spec: GridSpec, where: str) -> None:
    """The [[extend]] entries that resume the same runs go in increasing steps: the last one ends the curve, so a
    later entry with fewer steps than an earlier one would cut off the points the earlier one paid for."""
    from cdrb_cli.orchestration.grid.expansion import BASE

    declared = spec._file_variants if spec._file_variants is not None else spec.variants
    for env in spec.envs:
        for method in spec.methods:
            for variant in [BASE, *(v for v in declared if v.own_model and v.applies(env, method))]:
                exts = spec.extensions_of(env, method, variant.name if variant is not BASE else "")
                for earlier, later in zip(exts, exts[1:]):
                    if later.steps < earlier.steps:
                        i, j = spec.extend.index(earlier), spec.extend.index(later)
                        run = f"{env} x {method}" + (f" ({variant.name})" if variant is not BASE else "")
                        raise BadInput(
                            f"{where}: extend[{j}]: steps {later.steps} is fewer than extend[{i}]'s {earlier.steps} "
                            f"for {run}: the last entry ends the curve, so it would drop the longer runs",
                            hint="list the entries in increasing steps, or remove the shorter one",
                        )


def _check_scope(where: str, item: Scoped, spec: GridSpec, narrowed: bool) -> None:
    """An empty ``methods``/``envs`` list is an error (it applies to nothing; leaving the key out means all), and an
    entry that applies to none of the grid's runs is said, unless the grid was ``narrowed`` with --set (which may
    leave entries idle on purpose)."""
    for key in ("methods", "envs"):
        if getattr(item, key) == []:
            raise BadInput(f"{where}: {key} = []: applies to nothing", hint=f"leave {key} out to mean all")
    if not narrowed and not any(item.applies(e, m) for e in spec.envs for m in spec.methods):
        ui.warn(f"{where}: applies to none of the grid's environments and methods, so it does nothing here")


def _check_out(out: Path, where: str) -> None:
    """The grid's ``out`` is a folder or can become one (no file on its path, files can be made in the nearest
    folder that exists), and its name has no control characters (every task's command line names files under it,
    one line per task)."""
    from cdrb_cli.artifacts.outputs import check_can_make, has_control_character

    if has_control_character(str(out)):
        raise BadInput(f"{where}: out {clip(repr(str(out)), 80)}: has a control character", hint="rename the folder")
    check_can_make(out, f"{where}: out =", hint="choose a folder for the grid's artifacts")


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


def _text(value: str) -> str:
    """A setting's value as :func:`parse_command` keys it (JSON, or the text that did not parse), as text."""
    try:
        return str(json.loads(value))
    except ValueError:
        return value


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
    preset = _text(dict(sets).get("preset", json.dumps(spec.preset)))
    if preset not in PRESETS:
        return None
    every = str(dict(sets).get("checkpoint_every", preset_training(METHODS.get(method), preset)["checkpoint_every"]))
    return snapshot_step(int(every)) if every.isascii() and every.isdigit() and int(every) > 0 else None


def _train_steps(spec: GridSpec, env: str, method: str, variant: Variant) -> tuple[int | None, str]:
    """How many steps ``method``'s training in ``variant`` runs when the grid sets no ``steps``, and what says so:
    its train flags' last ``--steps``/``--set steps=N``, else the preset's; None when a ``--config`` file may set it
    or the value is not a positive integer (`cdrb train` then says so)."""
    from cdrb_cli.methods.config import preset_training
    from cdrb_cli.methods.registry import METHODS
    from cdrb_cli.presets import PRESETS

    _, options, sets = parse_command(["train", *flags_for(spec, env, method, variant)[0]])
    if options.get("config_file") is not None:
        return None, ""
    given = dict(sets).get("steps")
    if given is not None:
        value, source = _text(given), "its train flags"
    else:
        preset = _text(dict(sets).get("preset", json.dumps(spec.preset)))
        if preset not in PRESETS:
            return None, ""
        value, source = str(preset_training(METHODS.get(method), preset)["steps"]), f"the {preset} preset"
    return (int(value), source) if value.isascii() and value.isdigit() and int(value) > 0 else (None, "")


def _check_train_steps(spec: GridSpec, origin: str) -> None:
    """Where the grid sets ``steps``, it replaces the training length a variant or a settings file gives (a tuned
    file's chosen length, a budget shrunk with ``--set steps=N``): said in one warning, not dropped silently. Where
    it sets none, each training's own length (its flags', else the preset's) is held to ``steps_cap``."""
    replaced = []
    for env in spec.envs:
        for method in spec.methods:
            for v in model_variants(spec, env, method):
                where = f"{method}'s training on {env}" + (f" in variant {v.name}" if v.name else "")
                if spec.steps is not None:
                    own = dict(parse_command(["train", *flags_for(spec, env, method, v)[0]])[2]).get("steps")
                    if own is not None and _text(own) != str(spec.steps):
                        replaced.append(f"{where}: {clip(_text(own), 20)}")
                    continue
                steps, source = _train_steps(spec, env, method, v)
                if spec.steps_cap is not None and steps is not None and steps > spec.steps_cap:
                    raise BadInput(
                        f"{origin}: {where} runs {steps} steps ({source}), beyond steps_cap = {spec.steps_cap}",
                        hint="set the grid's steps (at most the cap), or raise steps_cap",
                    )
    if replaced:
        more = f" and {len(replaced) - 2} more" if len(replaced) > 2 else ""
        ui.warn(
            f"{origin}: the grid's steps = {spec.steps} replaces the steps its train flags set ("
            + "; ".join(replaced[:2])
            + more
            + "); a longer curve for some runs is an [[extend]] entry"
        )


def _check_snapshot_steps(spec: GridSpec, origin: str) -> None:
    """Every snapshot step on each training's loss curve (the rule of `cdrb train --snapshot-at`), so a grid that
    would fail in every training fails when it is read; ``origin`` names where snapshot_at came from."""
    for env in spec.envs:
        for method in spec.methods:
            for v in model_variants(spec, env, method):
                snaps = spec.curve(env, method, v.name)[1]
                step = _snapshot_step(spec, env, method, v)
                bad = [s for s in snaps if step and s % step]
                if bad:
                    where = f"{method}'s training" + (f" in variant {v.name}" if v.name else "")
                    raise BadInput(
                        f"{origin}: snapshot_at: {bad[0]} is not a multiple of {step}, where {where} records its "
                        f"model (every gcd(50, checkpoint_every) steps)",
                        hint=f"use multiples of {step}, or set checkpoint_every in {method}'s train flags",
                    )
