"""Plan and eval configs from settings: the one place a plan or an evaluation is configured, for the CLI, the
Python API, the quickstart and the grid alike.

A caller hands over a list of :class:`~cdrb_cli.settings.Setting` (``--config`` file keys, ``--set`` pairs, the
everyday flags, or keyword arguments of the API), each keeping how the user gave it; :func:`plan_config` and
:func:`eval_config` fill in what depends on the model (its sampler, its family's protocol and controller, the
avoidance its family chose for new obstacles) and validate the result against :class:`PlanConfig` /
:class:`EvalConfig`. Every error names the setting as the user gave it (``--set avoid.route_k=8``, ``--config
run.toml: avoid.route_k``) or, for a default, the field and its value.

Shortcuts a setting may use: ``replan = "every:50"`` (``never``, ``every:N``, ``deviation:D``) for the
``replan.mode`` fields, ``controller = "waypoint"`` for ``controller.name``, and ``avoid = "plain"`` (no avoidance)
or ``avoid = "tuned"`` (the family's choice for new obstacles; the default in a scene, see
:attr:`~cdrb_cli.envs.family.EnvFamily.scene_avoid`), applied before the ``avoid.<field>`` settings. An eval that
re-plans uses the family's choice for re-planning (:attr:`~cdrb_cli.envs.family.EnvFamily.replan_tuned`), and plans
that start away from the demonstrations' starts its choice for plans from anywhere
(:attr:`~cdrb_cli.envs.family.EnvFamily.start_tuned`), where the settings leave those fields alone.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Sequence
from pathlib import Path
from typing import Any

from cdrb_cli.configs import ROUTE_STEPS, AvoidConfig, EvalConfig, PlanConfig, ReplanConfig
from cdrb_cli.envs.registry import family_of
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.settings import Setting, apply, clip, from_api, from_mapping, given_once, lookup, validate

#: ``avoid = ...`` values
AVOID_MODES = ("plain", "tuned")
#: the eval defaults a setting may change (the CLI's flags have these defaults too)
EVAL_DEFAULTS: dict[str, Any] = {"episodes": 100, "seeds": [0, 1, 2, 3, 4], "stream": "test"}
#: fields given by their own argument (a file the stage reads and hashes; the seed of every command): the value it
#: takes, and what it is
_NOT_SETTINGS = {
    "scene": ("FILE", ", the scene file itself (a maze map with walls added, or a Fetch TOML file of boxes)"),
    "seed": ("N", ""),
}


def _own_argument(field: str, source: str) -> str:
    """How to give ``field`` in the dialect of the setting's ``source``: the API's ``settings`` dict names its
    keyword argument (``seed=N``), the CLI's ``--set`` and config files the flag (``--seed N``)."""
    value, what = _NOT_SETTINGS[field]
    return f"pass {field}={value}{what}" if from_api(source) else f"pass --{field} {value}{what}"


def named(settings: Sequence[Setting], path: tuple[str, ...], value: Any) -> str:
    """How the user gave the field at ``path`` (the setting's source), or the field and its default value."""
    s = lookup(settings, path)
    if s is not None:
        return s.source
    shown = str(value).lower() if isinstance(value, bool) else value
    return f"{'.'.join(path)} = {shown} (the default)"


#: the forms a ``replan`` setting takes, for its refusals
_REPLAN_HINT = "e.g. replan=every:20 or replan=deviation:0.5"


def expand(settings: Sequence[Setting]) -> list[Setting]:
    """``settings`` with the shortcuts written out (``replan``, ``controller``; ``avoid`` is kept for
    :func:`avoid_base`), and the fields that are not settings refused."""
    out: list[Setting] = []
    for s in settings:
        if s.path[0] in _NOT_SETTINGS:
            raise BadInput(f"{s.source}: {s.path[0]} is not a setting", hint=_own_argument(s.path[0], s.source))
        if s.path == ("replan",) and not isinstance(s.value, (str, dict)):
            raise BadInput(f"{s.source}: not never, every:N or deviation:D", hint=_REPLAN_HINT)
        if s.path == ("replan",) and isinstance(s.value, str):
            try:
                fields = ReplanConfig.parse(s.value)
            except ValueError as exc:
                raise BadInput(f"{clip(s.source)}: {clip(str(exc))}", hint=_REPLAN_HINT) from None
            out += [Setting(("replan", k), v, s.source) for k, v in fields.items()]
        elif s.path == ("controller",) and isinstance(s.value, str):
            out.append(Setting(("controller", "name"), s.value, s.source))
        else:
            out.append(s)
    return out


def fields_of(settings: Sequence[Setting]) -> list[Setting]:
    """``settings`` as the fields they write: shortcuts written out (:func:`expand`) and tables as one setting per
    field inside them (``replan={"mode": "every", "every": 5}`` is ``replan.mode`` and ``replan.every``), each named
    as it was given. ``avoid`` modes stay one setting: they choose a base, not a field."""
    out: list[Setting] = []
    todo = list(expand(settings))
    while todo:
        s = todo.pop(0)
        if isinstance(s.value, dict) and s.value:
            todo[:0] = [Setting((*s.path, str(k)), v, s.source) for k, v in s.value.items()]
        else:
            out.append(s)
    return out


def each_field_once(settings: Sequence[Setting]) -> None:
    """Refuse one source without an order (a config file) that reaches a field twice in different spellings
    (``controller = "pd"`` and ``controller.name = "waypoint"``, ``replan = "every:20"`` and ``replan.every = 30``):
    which would win is not what either says."""
    seen: dict[tuple[str, ...], Setting] = {}
    for s in fields_of(settings):
        if s.path in seen:
            a, b, field = seen[s.path].source, s.source, ".".join(s.path)
            cut = a.rfind(": ", 0, len(os.path.commonprefix([a, b]))) + 2  # one file named once: "F: x and x.y"
            where = f"{a} and {b[cut:]}" if cut > 1 else f"{a} with {b}"
            raise BadInput(f"{where} both set {field}", hint="give each setting once")
        seen[s.path] = s


def given_once_anyhow(first: Sequence[Setting], then: Sequence[Setting], sep: str = " with ") -> None:
    """:func:`~cdrb_cli.settings.given_once` over the fields written (:func:`fields_of`): a flag or keyword and a
    ``--set`` or settings entry that reach one field in different spellings (``--replan every:20`` and ``--set
    replan.every=30``, ``controller="pd"`` and ``{"controller": {"name": "waypoint"}}``) are refused too."""
    given_once(fields_of(first), fields_of(then), sep=sep)


def avoid_base(model, settings: Sequence[Setting], in_scene: bool) -> dict:
    """The avoidance fields before the ``avoid.<field>`` settings: the family's choice for new obstacles with this
    method when planning in a scene (or with ``avoid = "tuned"``), none with ``avoid = "plain"`` or outside a
    scene."""
    mode = lookup(settings, ("avoid",))
    if mode is not None and mode.value not in AVOID_MODES:
        raise BadInput(
            f"{mode.source}: avoid is {' or '.join(AVOID_MODES)}",
            hint="or set its fields, e.g. avoid.best_of=4 (`cdrb config plan` lists them)",
        )
    chosen = mode.value if mode is not None else ("tuned" if in_scene else "plain")
    if chosen == "plain":
        return {}
    out = dict(family_of(model.manifest.env).scene_avoid.get(model.manifest.config.method.name, {}))
    for key in ROUTE_STEPS:
        if out.get(key) is not None:
            out[key] = _repair_step(model, out[key])
    return out


def _repair_step(model, k: int) -> int:
    """A family default's repair step for ``model``: one with fewer diffusion steps repairs from its last."""
    steps = getattr(model.manifest.config.method, "diffusion_steps", None)
    return k if steps is None else max(1, min(k, steps - 1))


def replan_base(model, controller: str, settings: Sequence[Setting]) -> list[Setting]:
    """The settings an eval that re-plans from scratch uses unless ``settings`` give them: the family's choice for
    re-planning with this method (:attr:`~cdrb_cli.envs.family.EnvFamily.replan_tuned`), each controller field where
    ``controller`` has it (a look-ahead only on the gated clock: none where ``controller.max_lag`` is null), the
    ``avoid.`` ones unless ``avoid = "plain"``; none for one plan per episode or a repair."""
    from cdrb_cli.envs.registry import CONTROLLERS

    mode = lookup(settings, ("replan", "mode"))
    if mode is None or mode.value == "never" or lookup(settings, ("replan", "repair_k")) is not None:
        return []
    fields = CONTROLLERS.get(controller).config.model_fields
    lag = lookup(settings, ("controller", "max_lag"))
    time_indexed = lag is not None and lag.value is None  # no gated clock for a look-ahead to move

    def applies(path: tuple[str, ...], value) -> bool:
        return path[0] != "controller" or (path[1] in fields and not (path[1] == "look_ahead" and time_indexed))

    return _family_defaults(model, "replan_tuned", settings, "the default when re-planning", applies)


def start_base(model, settings: Sequence[Setting], avoid: dict) -> list[Setting]:
    """The settings plans that start away from the demonstrations' starts use unless ``settings`` give them: the
    family's choice for plans from anywhere with this method (:attr:`~cdrb_cli.envs.family.EnvFamily.start_tuned`),
    none with ``avoid = "plain"``, a best-of no smaller than the one ``avoid`` (the avoidance base) has, and the route
    itself as a last resort only with a second try (none where the settings turn the second try off)."""
    second = lookup(settings, ("avoid", "fallback_route_k"))

    def applies(path: tuple[str, ...], value) -> bool:
        if path == ("avoid", "fallback_route_itself"):
            return second is None or second.value is not None
        return path != ("avoid", "best_of") or avoid.get("best_of", 1) < value

    return _family_defaults(model, "start_tuned", settings, "the default for plans from anywhere", applies)


def _family_defaults(model, table: str, settings: Sequence[Setting], why: str, applies) -> list[Setting]:
    """The settings of the family's ``table`` (:attr:`~cdrb_cli.envs.family.EnvFamily.replan_tuned`, ``start_tuned``)
    for the model's method, as defaults named ``why``: each where ``settings`` leave it alone and ``applies(path,
    value)``, the ``avoid.`` ones unless ``avoid = "plain"``."""
    plain = getattr(lookup(settings, ("avoid",)), "value", None) == "plain"
    out = []
    for key, value in getattr(family_of(model.manifest.env), table).get(model.manifest.config.method.name, {}).items():
        path = tuple(key.split("."))
        if lookup(settings, path) is not None or (path[0] == "avoid" and plain) or not applies(path, value):
            continue
        if path[0] == "avoid" and path[-1] in ROUTE_STEPS:
            value = _repair_step(model, value)
        out.append(Setting(path, value, f"{key} = {value} ({why})"))
    return out


def route_buffer_path(settings: Sequence[Setting]) -> Path | None:
    """The buffer file of ``avoid.route_buffer`` as given (the config records its name)."""
    s = lookup(settings, ("avoid", "route_buffer"))
    return None if s is None or s.value is None else Path(str(s.value))


def _method(model):
    return METHODS.get(model.manifest.config.method.name)


def _sampler(model, settings: Sequence[Setting]) -> str:
    entry = _method(model)
    s = lookup(settings, ("sampler",))
    if s is None:
        return model.manifest.config.method.sampler
    if not isinstance(s.value, str) or s.value not in entry.samplers:
        raise BadInput(f"{s.source}: {entry.name} models use {', '.join(entry.samplers)}")
    return s.value


def _avoid_record(config):
    """``config`` with ``avoid.route_buffer`` cut to the file's name (its content is a hashed parent)."""
    rb = config.avoid.route_buffer
    if rb is None or Path(rb).name == rb:
        return config
    return config.model_copy(update={"avoid": config.avoid.model_copy(update={"route_buffer": Path(rb).name})})


def check_avoid(model, avoid: AvoidConfig, settings: Sequence[Setting] = ()) -> None:
    """Refuse an avoidance setting the model's method cannot apply (one line naming the setting as given)."""
    entry = _method(model)
    name = entry.name

    def where(field: str) -> str:
        return named(settings, ("avoid", field), getattr(avoid, field))

    if entry.kind != "planner":
        if avoid.model_copy(update={"route_buffer": None}) != AvoidConfig():  # a route buffer leads to waypoints
            given = next((s.source for s in settings if s.path[0] == "avoid"), "avoid")
            raise BadInput(f"{given}: {name} is a policy: it makes no plans to choose or guide", hint="drop it")
        return
    cls = entry.method
    if avoid.mask_buffer and not cls.masks:
        raise BadInput(
            f"{where('mask_buffer')}: {name} samples from no replay buffer it could mask",
            hint="drop it (avoid.best_of, or avoid.guide_scale for Diffuser, keep plans out of obstacles)",
        )
    for field in ROUTE_STEPS:
        if getattr(avoid, field) is not None and not cls.repairs:
            raise BadInput(
                f"{where(field)}: {name} cannot restore a plan from a part-way step (it has no repair)",
                hint="drop it (CDRB and Diffuser repair)",
            )
        if getattr(avoid, field) is not None and not entry.needs_buffer and avoid.route_buffer is None:
            raise BadInput(
                f"{where(field)}: {name} carries no replay buffer to route through",
                hint="add avoid.route_buffer=BUFFER.h5 (from `cdrb cluster` on the model's demos)",
            )
    if avoid.guide_scale > 0 and not cls.guides:
        raise BadInput(f"{where('guide_scale')}: {name} has no guided sampling", hint="drop it (Diffuser has it)")


def _check_steps(model, settings: Sequence[Setting], sample_steps: int | None, repair_k: int | None = None) -> None:
    from cdrb_cli.stages.plan import check_sample_steps

    check_sample_steps(model, sample_steps, named(settings, ("sample_steps",), sample_steps))
    steps = getattr(model.manifest.config.method, "diffusion_steps", None)
    if repair_k is not None and steps is not None and repair_k > steps - 1:
        raise BadInput(
            f"{named(settings, ('replan', 'repair_k'), repair_k)}: the model has T = {steps} diffusion steps, so a "
            f"repair restores from k = 1..{steps - 1}",
            hint=f"use replan.repair_k={max(1, min(steps - 1, steps // 8))} (a small k keeps more of the plan)",
        )


# ------------------------------------------------------------------------------------------------ plan
def plan_config(
    model,
    settings: Sequence[Setting] = (),
    *,
    seed: int = 0,
    scene_file: Path | None = None,
    starts=None,
    **fields: Any,
) -> PlanConfig:
    """The :class:`PlanConfig` of ``settings`` (then ``fields``, keyword settings such as ``n=8``) for ``model``,
    planning in ``scene_file`` when given; ``starts`` (raw start states, when known) away from the protocol's
    starts take the family's settings for plans from anywhere."""
    settings = [*profile_settings(model, plan_keys()), *expand([*settings, *keyword_settings(fields)])]
    base = {
        "sampler": _sampler(model, settings),
        "n": 1,
        "avoid": avoid_base(model, settings, scene_file is not None),
        "scene": None if scene_file is None else Path(scene_file).name,
        "seed": seed,
    }
    if starts is not None and family_of(model.manifest.env).off_protocol_starts(model.manifest.env, starts).any():
        settings = [*start_base(model, settings, base["avoid"]), *settings]
    given = [s for s in settings if s.path not in (("avoid",), ("sampler",))]
    config = _avoid_record(validate(PlanConfig, apply(base, given), settings, "plan"))
    if config.batch is None:  # null marks a plan file written before the size was recorded, not a size to plan with
        s = lookup(settings, ("batch",))
        raise BadInput(f"{s.source if s else 'plan batch'}: null is not a batch size",
                       hint="give the plans sampled together, e.g. batch=256")  # fmt: skip
    check_avoid(model, config.avoid, settings)
    _check_steps(model, settings, config.sample_steps)
    return config


# ------------------------------------------------------------------------------------------------ eval
#: the most planned states one `cdrb plan` writes (pairs x n x horizon; 8 GB of float64 features at 4 features): more
#: is a typo of --pairs or -n, refused before the sampler allocates for it
MAX_PLANNED_STATES = 250_000_000


def check_plan_count(model, pairs: int, config: PlanConfig) -> None:
    """Refuse a plan whose pairs x n (x best-of, sampled) x horizon states exceed :data:`MAX_PLANNED_STATES`."""
    samples = pairs * config.n * config.avoid.best_of
    states = samples * model.manifest.config.horizon
    if states > MAX_PLANNED_STATES:
        raise BadInput(
            f"{pairs} pairs x -n {config.n} x best_of {config.avoid.best_of} = {samples:,} plans of "
            f"{model.manifest.config.horizon} states: more than {MAX_PLANNED_STATES:,} planned states in one run",
            hint="plan fewer pairs (--pairs) or fewer plans per pair (-n), in several runs",
        )


def _controller_name(model, family, protocol: str, settings: Sequence[Setting]) -> str:
    s_name = lookup(settings, ("controller", "name"))
    prescribed = family.protocol_controller(protocol)
    name = s_name.value if s_name is not None else prescribed or family.controllers[0]
    if prescribed is not None and name != prescribed:
        raise BadInput(
            f"{s_name.source}: protocol {protocol} executes plans with the {prescribed} controller, not {name}",
            hint="drop it (the controller's settings may still be changed with controller.<field>)",
        )
    if name not in family.controllers:
        raise BadInput(
            f"{s_name.source}: not a controller of the {family.name} environments",
            hint=f"use {' or '.join(family.controllers)}",
        )
    return name


def _toward_waypoints(path: tuple[str, ...]) -> bool:
    """Is the setting at ``path`` one a policy takes toward waypoints (``replan.waypoint_reach``): the clock that
    gives the next waypoint, the route and the buffer it goes through."""
    if path == ("avoid", "route_buffer"):
        return True
    return path[:1] == ("replan",) and path[1:2] not in (("repair_k",), ("repair_steps",))


#: the most episodes one eval runs (episodes x seeds): days of simulation on a workstation, so more is a typo
MAX_EVAL_EPISODES = 1_000_000


def eval_config(
    model,
    settings: Sequence[Setting] = (),
    *,
    seed: int = 0,
    scene_file: Path | None = None,
    scene=None,
    **fields: Any,
) -> EvalConfig:
    """The :class:`EvalConfig` of ``settings`` (then ``fields``, keyword settings such as ``episodes=20`` or
    ``replan="every:50"``) for ``model``: the family's protocol and its controller (or the family's first), the
    model's sampler, the family's avoidance in a scene; ``scene_file`` the scene evaluated in (recorded by name),
    ``scene`` its spec when the caller built it already."""
    settings = expand([*settings, *keyword_settings(fields)])
    spec = model.manifest.env
    family = family_of(spec)
    entry = _method(model)
    if entry.kind == "policy":
        waypoints = (w := lookup(settings, ("replan", "waypoint_reach"))) is not None and w.value is not None
        for s in settings:
            if waypoints and _toward_waypoints(s.path):
                continue
            if s.path[0] in ("replan", "controller", "avoid"):
                what = {"replan": "has no plan to re-plan", "controller": "executes no plan with a controller"}
                raise BadInput(
                    f"{s.source}: {entry.name} is a policy that acts every step; it "
                    + what.get(s.path[0], "makes no plans to choose or guide"),
                    hint="drop it (`cdrb config eval` lists the settings)",
                )
    s_protocol = lookup(settings, ("protocol",))
    protocol = family.protocol if s_protocol is None else s_protocol.value
    if protocol not in family.protocols():
        raise BadInput(
            f"{s_protocol.source}: not a protocol of the {family.name} environments",
            hint=f"use {' or '.join(family.protocols())}",
        )
    settings = [*_eval_profile(model, family, protocol, entry.kind == "policy", settings), *settings]
    base = {
        **EVAL_DEFAULTS,
        "controller": {"name": _controller_name(model, family, protocol, settings)},
        "sampler": _sampler(model, settings),
        "protocol": protocol,
        "seed": seed,
        "scene": None if scene_file is None else Path(scene_file).name,
        "avoid": {} if entry.kind == "policy" else avoid_base(model, settings, scene_file is not None),
    }
    settings = [*replan_base(model, base["controller"]["name"], settings), *settings]
    if protocol in family.start_protocols and entry.kind != "policy":
        settings = [*start_base(model, settings, base["avoid"]), *settings]
    given = [s for s in settings if s.path not in (("avoid",), ("sampler",), ("protocol",))]
    config = _avoid_record(validate(EvalConfig, apply(base, given), settings, "eval"))
    if config.episodes * len(config.seeds) > MAX_EVAL_EPISODES:
        raise BadInput(
            f"{named(settings, ('episodes',), config.episodes)} x {len(config.seeds)} seeds = "
            f"{config.episodes * len(config.seeds):,} episodes: more than the {MAX_EVAL_EPISODES:,} one eval runs",
            hint="give fewer episodes or seeds, e.g. Table 1's 100 x 5, or split the seeds over several evals",
        )
    check_avoid(model, config.avoid, settings)
    if scene_file is not None or protocol in family.extra_protocols:  # a protocol that cannot draw fails here
        where = spec if scene_file is None else scene or family.with_map(spec, Path(scene_file))
        from cdrb_cli.seeding import EVAL_STREAMS

        family.draw_protocol_episodes(where, 1, config.seeds[0], EVAL_STREAMS[config.stream], protocol)
    _check_steps(model, settings, config.sample_steps, config.replan.repair_k)
    return config


def profile_settings(model, keys: Collection[str] | None = None) -> list[Setting]:
    """The eval settings of the :class:`~cdrb_cli.configs.SettingsProfile` the model was trained with (those whose
    first part is in ``keys``; None: all), named after its file: what a plan or an eval of the model starts from."""
    profile = getattr(model.manifest, "profile", None)
    if profile is None:
        return []
    out = []
    for key, value in profile.eval.items():
        path = tuple(key.split("."))
        if keys is None or path[0] in keys:
            out.append(Setting(path, value, f"the model's settings profile ({profile.file}): {key}={value!r}"))
    return expand(out)


def plan_keys() -> set[str]:
    """The first parts of the keys that are plan settings (the rest of an eval's, such as the controller or
    re-planning, are an eval's alone)."""
    return set(PlanConfig.model_fields) | {"avoid"}


def _eval_profile(model, family, protocol: str, policy: bool, settings: Sequence[Setting]) -> list[Setting]:
    """The profile settings an eval starts from: a policy takes none of the plan's; the controller's only where the
    eval executes plans with the controller the profile was chosen with (a protocol may prescribe its own, and a
    controller named on the command line replaces it with its defaults)."""
    out = profile_settings(model)
    if policy:
        out = [s for s in out if s.path[0] not in ("replan", "controller", "avoid")]
    if family.protocol_controller(protocol) is not None or lookup(settings, ("controller", "name")) is not None:
        out = [s for s in out if s.path[0] != "controller"]
    return out


def keyword_settings(values: dict[str, Any], source: str = "") -> list[Setting]:
    """Settings from Python keyword arguments (``{"episodes": 20, "avoid.best_of": 4}``), skipping None values;
    each is named ``key=value`` in errors."""
    given = {k: v for k, v in values.items() if v is not None}
    return [Setting(s.path, s.value, f"{source}{'.'.join(s.path)}={s.value!r}") for s in from_mapping(given)]
