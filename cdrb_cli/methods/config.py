"""Resolving a training config: method + preset + the data + the user's settings -> one validated TrainConfig.

Layers, later ones winning: the preset's values (:mod:`cdrb_cli.presets`, and the method's own presets); the
defaults the data implies (horizon and stride from the environment, features from the buffer, and the method's
``data_defaults``, e.g. CDRB's d_max = buffer diameter); then the user's settings in the order given
(``--config`` file, ``--set``, the common flags). Errors name the setting the user typed.
"""

from __future__ import annotations

from collections.abc import Sequence

from cdrb_cli.configs import TrainConfig, UNetConfig, net_kinds
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.registry import DEFAULT_METHOD, METHODS, BufferInfo, MethodEntry
from cdrb_cli.nets import horizon_multiple
from cdrb_cli.presets import DEFAULT_PRESET, NETS, PRESETS, TRAIN
from cdrb_cli.settings import (
    Setting,
    apply,
    from_mapping,
    given_once,
    lookup,
    parse_set,
    read_config_file,
    validate,
)


def _source(setting: Setting | None, fallback: str) -> str:
    return setting.source if setting is not None else fallback


def choose(settings: Sequence[Setting]) -> tuple[MethodEntry, str, str]:
    """The method entry, preset and net kind the settings ask for (with their defaults)."""
    s_method = lookup(settings, ("method", "name"))
    name = s_method.value if s_method is not None else DEFAULT_METHOD
    if not isinstance(name, str) or name not in METHODS:
        raise BadInput(f"{_source(s_method, '--method')}: unknown method", hint=f"use {', '.join(METHODS.names())}")
    entry = METHODS.get(name)
    s_preset = lookup(settings, ("preset",))
    preset = s_preset.value if s_preset is not None else DEFAULT_PRESET
    if preset not in PRESETS:
        raise BadInput(f"{_source(s_preset, '--preset')}: unknown preset", hint=f"use {' or '.join(PRESETS)}")
    unknown = [n for n in entry.nets if n not in net_kinds()]
    if unknown:
        raise BadInput(
            f"the {entry.name} method lists unknown nets {unknown}", hint=f"nets are {', '.join(net_kinds())}"
        )
    s_net = lookup(settings, ("net", "kind"))
    net = s_net.value if s_net is not None else entry.default_net
    if net not in entry.nets:
        raise BadInput(
            f"{_source(s_net, '--net')}: the {entry.name} method uses --net {' or '.join(entry.nets)}",
            hint="omit --net" if len(entry.nets) == 1 else f"use {' or '.join(entry.nets)}",
        )
    return entry, preset, net


def defaults(
    entry: MethodEntry, preset: str, net: str, spec: EnvSpec, buffer: BufferInfo | None, seed: int, data: dict
) -> dict:
    """The config a preset gives for this method, net, data and seed, before the user's settings (``data``: the
    method's values that depend on the data, from ``entry.data_defaults``)."""
    method = {"name": entry.name, **entry.presets.get(preset, {})}
    method.update(data)
    return {
        "method": method,
        "net": {"kind": net, **NETS[preset][net]},
        "preset": preset,
        "features": buffer.features if buffer is not None else "state",
        "horizon": spec.horizon,
        "stride": spec.plan_stride,
        "seed": seed,
        **preset_training(entry, preset),
    }


def preset_training(entry: MethodEntry, preset: str) -> dict:
    """The training values (steps, batch, lr, EMA, checkpoints) a preset gives this method: the preset's, then
    the method's own for that preset (e.g. the straight line's 50 steps)."""
    return {**TRAIN[preset], **entry.train_defaults.get(preset, {})}


def _check_keys(settings: Sequence[Setting]) -> None:
    for s in settings:
        if s.path in (("method",), ("net",)):
            raise BadInput(
                f"{s.source}: set the fields of {s.key} one by one",
                hint=f"e.g. --set {s.key}.{'name' if s.key == 'method' else 'kind'}=... (or --{s.key})",
            )
        if s.path == ("seed",):
            raise BadInput(f"{s.source}: the seed is --seed", hint="pass --seed N")


def user_settings(method=None, net=None, preset=None, steps=None, config_file=None, sets=()) -> list[Setting]:
    """What `cdrb train` was asked for, in priority order: the ``--config`` file, the ``--set`` pairs, then the
    dedicated flags (``--method``, ``--net``, ``--preset``, ``--steps``; None: not given)."""
    items = read_config_file(config_file) if config_file is not None else []
    sets_ = parse_set(sets)
    flags = [
        Setting(path, value, f"{flag} {value}")
        for path, value, flag in (
            (("method", "name"), method, "--method"),
            (("net", "kind"), net, "--net"),
            (("preset",), preset, "--preset"),
            (("steps",), steps, "--steps"),
        )
        if value is not None
    ]
    given_once(flags, sets_)
    return items + sets_ + flags


def resolve_train_config(
    spec: EnvSpec, buffer: BufferInfo | None, settings: Sequence[Setting] = (), seed: int = 0
) -> TrainConfig:
    """The full TrainConfig for ``settings`` (``method.name``, ``preset``, ``net.kind`` and any field), checked
    against the environment and the buffer."""
    _check_keys(settings)
    entry, preset, net = choose(settings)
    if entry.needs_buffer and buffer is None:
        raise BadInput(f"--method {entry.name} needs --buffer BUFFER", hint="make one with `cdrb cluster DEMOS`")
    s_feat = lookup(settings, ("features",))
    valid_feature = s_feat is not None and s_feat.value in ("state", "state-action")  # else validation names it
    if buffer is not None and valid_feature and s_feat.value != buffer.features:
        raise BadInput(
            f"{s_feat.source}: the buffer was clustered on {buffer.features!r} features",
            hint="omit it, or re-cluster with the same --features",
        )
    data = _data_defaults(entry, spec, buffer, settings)
    for key, value in data.items():
        if isinstance(value, (int, float)) and value <= 0 and lookup(settings, ("method", key)) is None:
            raise BadInput(
                f"--buffer: gives {entry.name}'s method.{key} = {value} (its states are all one point)",
                hint=f"re-cluster with `cdrb cluster --k 2` or more, or --set method.{key}=VALUE",
            )
    given = defaults(entry, preset, net, spec, buffer, seed, data)
    config = validate(TrainConfig, apply(given, settings), settings, "train")
    if buffer is not None and config.features != buffer.features:  # a default of the method's, not a setting
        raise BadInput(
            f"--buffer: clustered on {buffer.features!r} features, but this training uses {config.features!r} (the "
            f"{entry.name} method's default)",
            hint=f"cluster with `--features {config.features}`, or leave --buffer out for a method that needs none",
        )
    _check_net(config, settings)
    return config


def _data_defaults(entry, spec, buffer, settings) -> dict:
    """The method's defaults that depend on the data: ``data_defaults(spec, buffer)``, or ``(spec, buffer,
    settings)`` for one whose data defaults also depend on a setting (CDRB's d_max: the buffer's diameter in the
    measure its balls use)."""
    import inspect

    if entry.data_defaults is None:
        return {}
    if len(inspect.signature(entry.data_defaults).parameters) >= 3:
        return entry.data_defaults(spec, buffer, settings)
    return entry.data_defaults(spec, buffer)


def config_problem(config: TrainConfig) -> tuple[tuple[str, ...], str, str] | None:
    """A constraint between fields that pydantic does not see, as (the key to blame, message, hint); None when
    the config is consistent. Checked when a config is resolved and when a model artifact is read."""
    entry = METHODS.get(config.method.name)
    net = config.net
    if net.kind not in entry.nets:
        return ("net", "kind"), f"the {entry.name} method uses --net {' or '.join(entry.nets)}", "re-train"
    if isinstance(net, UNetConfig) and net.dim % net.groups:
        return ("net", "dim"), f"must be a multiple of net.groups ({net.groups})", "e.g. --set net.dim=32"
    if net.kind == "transformer" and net.d_model % net.n_heads:
        return ("net", "d_model"), f"must be a multiple of net.n_heads ({net.n_heads})", "e.g. --set net.d_model=64"
    if entry.kind == "planner" and config.horizon < 2:
        return ("horizon",), "a plan needs at least 2 states (a start and a goal)", "e.g. --set horizon=64"
    if entry.kind == "policy" and config.features != "state-action":
        return ("features",), f"the {entry.name} policy learns actions: it needs state-action", "omit it"
    mult = horizon_multiple(net)
    if config.horizon % mult:
        return (
            ("horizon",),
            f"the U-Net with {len(net.dim_mults)} levels needs a horizon that is a multiple of {mult}",
            f"use --set horizon={config.horizon + (-config.horizon) % mult}",
        )
    return None


def _check_net(config: TrainConfig, settings: Sequence[Setting]) -> None:
    problem = config_problem(config)
    if problem is not None:
        key, message, hint = problem
        value = config.model_dump()
        for part in key:
            value = value[part]
        where = _source(lookup(settings, key), f"{'.'.join(key)} {value}")
        raise BadInput(f"{where}: {message}", hint=hint)


# ------------------------------------------------------------------------------------------------ from artifacts
def buffer_info(buffer) -> BufferInfo | None:
    """What resolution needs of a buffer artifact (None without one)."""
    if buffer is None:
        return None
    import numpy as np

    s = buffer.manifest.summary
    box = float(np.linalg.norm(np.where(np.asarray(buffer.high) > np.asarray(buffer.low), 2.0, 0.0)))
    return BufferInfo(
        features=buffer.manifest.config.features,
        diameter=s.diameter,
        graph_diameter=s.graph_diameter,
        box_diagonal=box,
    )


def train_config(demos, buffer=None, method: str | None = None, settings: dict | None = None, seed: int = 0):
    """The TrainConfig for a demos artifact (and buffer), a method and ``settings`` (dotted keys: ``{"steps": 40,
    "net.dim": 8, "preset": "paper"}``), as ``cdrb train DEMOS --buffer BUFFER --method M --set KEY=VALUE ...``
    resolves it."""
    items = from_mapping(settings or {})
    if method is not None:
        items.append(Setting(("method", "name"), method, f"--method {method}"))
    return resolve_train_config(demos.manifest.env, buffer_info(buffer), items, seed=seed)
