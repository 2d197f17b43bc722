"""A grid's commands resolved when the grid is read: every training's settings as `cdrb train` resolves them, and
every eval's as `cdrb eval` resolves them on the model that training will write. A setting a command would refuse
(an unknown key, a value out of range, a knob the method lacks, a scene that cannot be read) is then one line
naming the grid file, the method, the environment and the variant, before any task runs, `--dry-run` included,
instead of a failure of every eval hours later. Settings in a ``--config`` file are left to the command."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

from cdrb_cli.errors import BadInput
from cdrb_cli.orchestration.grid.expansion import (
    BASE,
    cluster_flags_for,
    collect_flags_for,
    flags_for,
    model_variants,
)
from cdrb_cli.orchestration.grid.flags import parse_command
from cdrb_cli.orchestration.grid.spec import GridSpec, Variant


def check_commands(spec: GridSpec, path: Path) -> None:
    """Every training's and every eval's settings resolve (see the module docstring)."""
    from cdrb_cli.envs.registry import make_spec

    for env in spec.envs:
        _, collect, collect_sets = parse_command(["collect", env, *collect_flags_for(spec, env)], fold=False)
        maze_map = collect.get("maze_map")
        if maze_map is not None:  # the command would refuse ENV and --maze-map both given, in every collection
            raise BadInput(
                f"{path}: collect on {env} is given --maze-map {maze_map}: a grid collects on its `envs` only",
                hint="drop --maze-map from the collect flags (an eval's unseen scene is its eval flag --maze-map); "
                "collect on a map file with `cdrb collect --maze-map FILE`",
            )
        env_spec = make_spec(env)
        _check_collect(spec, env_spec, env, collect, collect_sets, path)
        for method in spec.methods:
            configs = {}
            for v in model_variants(spec, env, method):
                configs[v.name] = _train_config(spec, env_spec, env, method, v, path)
            for v in spec.variants or [BASE]:  # the base model is evaluated on its own where no variant is given
                if not v.applies(env, method):
                    continue
                config = configs.get(v.name if v.own_model else BASE.name)
                if config is not None:
                    _check_eval(spec, env_spec, env, method, v, config, path)


def _check_collect(spec: GridSpec, env_spec, env: str, options: dict, sets: list, path: Path) -> None:
    """The collection's flags for ``env`` (``options`` and ``sets`` as :func:`parse_command` reads them, as typed)
    resolve as `cdrb collect` resolves them (its expert, split, starts and expert settings); one that reads a policy
    file is left to the command."""
    from cdrb_cli.settings import parse_set
    from cdrb_cli.stages.collect import collect_config

    if options.get("policy") is not None:
        return
    fraction = options.get("valid_fraction")
    try:
        collect_config(
            env_spec,
            spec.demos_of(env),
            seed=spec.data_seed,
            expert=options.get("expert"),
            valid_fraction=None if fraction is None else float(fraction),
            settings=parse_set([f"{k}={v}" for k, v in sets]),
            starts=options.get("starts") or "protocol",
        )
    except BadInput as exc:
        raise BadInput(f"{path}: collect on {env}: {exc.message}", hint=exc.hint) from None


def _where(path: Path, env: str, method: str, v: Variant) -> str:
    return f"{path}: {method} on {env}" + (f" in variant {v.name}" if v.name else "")


def _train_config(spec: GridSpec, env_spec, env: str, method: str, v: Variant, path: Path):
    """The TrainConfig `cdrb train` resolves for ``method`` on ``env`` in ``v`` (None: a ``--config`` file holds
    some of it)."""
    from cdrb_cli.methods.config import resolve_train_config, user_settings
    from cdrb_cli.methods.registry import METHODS, BufferInfo

    _, options, sets = parse_command(["train", *flags_for(spec, env, method, v)[0]], fold=False)
    if options.get("config_file") is not None:
        return None
    steps = None if options.get("steps") is None else int(options["steps"])
    preset = options.get("preset") or spec.preset
    try:
        items = user_settings(method, options.get("net"), preset, steps, sets=[f"{k}={x}" for k, x in sets])
    except BadInput as exc:  # a flag and a --set of one field: the command refuses it, so every training would
        raise BadInput(f"{_where(path, env, method, v)}: train flags: {exc.message}", hint=exc.hint) from None
    buffer = None
    if METHODS.get(method).needs_buffer:
        cluster = parse_command(["cluster", "demos.h5", *cluster_flags_for(spec, env, method, v)])[1]
        buffer = BufferInfo(features=str(cluster.get("features") or "state"), diameter=1.0)
    try:
        return resolve_train_config(env_spec, buffer, items)
    except BadInput as exc:
        raise BadInput(f"{_where(path, env, method, v)}: train flags: {exc.message}", hint=exc.hint) from None


def _check_eval(spec: GridSpec, env_spec, env: str, method: str, v: Variant, config, path: Path) -> None:
    """``v``'s eval flags for ``method`` on ``env`` resolve as `cdrb eval` resolves them on a model trained with
    ``config`` (a stand-in with the model's environment and settings: no model exists yet)."""
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.settings import Setting, setting_key
    from cdrb_cli.stages.configure import eval_config

    flags = flags_for(spec, env, method, v)[1]
    _, options, sets = parse_command(["eval", "MODEL", *flags])
    if options.get("config_file") is not None:
        return
    where = f"{_where(path, env, method, v)}: eval flags"
    _given_once(flags, "eval", where)
    settings = []
    for key, text in sets:
        if key.startswith("--"):  # an option's value the command refuses (check_flags names most of them)
            raise BadInput(f"{where}: {key} {text}: not a value it takes", hint=f"`cdrb eval --help` ({key})")
        try:
            value = json.loads(text)
        except ValueError:
            raise BadInput(f"{where}: --set {key}={text}: not a value", hint="e.g. --set avoid.best_of=4") from None
        source = f"--set {key}={text}"
        try:
            settings.append(Setting(setting_key(key, source), value, source))  # avoid.best-of is avoid.best_of
        except BadInput as exc:
            raise BadInput(f"{where}: {exc.message}", hint=exc.hint) from None
    model = SimpleNamespace(manifest=SimpleNamespace(env=env_spec, config=config, profile=None))
    scene_file = options.get("maze_map")
    try:
        scene = None if scene_file is None else family_of(env_spec).with_map(env_spec, Path(scene_file), "--scene")
        eval_config(model, settings, scene_file=None if scene_file is None else Path(scene_file), scene=scene)
    except BadInput as exc:
        raise BadInput(f"{where}: {exc.message}", hint=exc.hint) from None


def _given_once(flags: list[str], command: str, where: str) -> None:
    """Refuse the flags of a task in which an option and a ``--set`` reach one field (``--replan every:40`` from a
    variant, ``--set replan=...`` from a settings entry), as the command itself would, in every task."""
    from cdrb_cli.orchestration.grid.commands import options
    from cdrb_cli.orchestration.grid.flags import walk_options
    from cdrb_cli.settings import Setting, parse_set
    from cdrb_cli.stages.configure import given_once_anyhow

    given, sets = [], []
    for token, entry, value in walk_options(flags, options(command)):
        if entry is None:
            continue
        if entry.param == "sets":
            sets.append(str(value))
            continue
        value = value if entry.takes_value else entry.flag_value
        try:
            pair = entry.to_setting(value) if entry.to_setting is not None else None
        except Exception:  # a value the command refuses: the other checks name it
            pair = None
        if pair is not None:
            given.append(Setting(tuple(pair[0].split(".")), pair[1], f"{token.partition('=')[0]} {value}"))
    try:
        given_once_anyhow(given, parse_set(sets))
    except BadInput as exc:
        raise BadInput(f"{where}: {exc.message}", hint=exc.hint) from None
