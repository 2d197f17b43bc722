"""The Python API: what the CLI's plan and eval stages do, for notebooks and scripts, with typed results.

::

    from cdrb_cli import api

    planner = api.Planner("model.h5")                 # any planner's model artifact (CDRB, Diffuser, MLP, straight)
    plans = planner.plan(start=[0.0, 0.0], goal=[6.0, 6.0], n=8, seed=0)
    plans.states.shape                                 # (8, H, obs_dim), raw units, start and goal held exactly
    plans.through_obstacle.mean()                      # share of plans with a state or a step in an obstacle

    summary = api.evaluate("model.h5", "eval.h5", episodes=20, seeds=[0], stream="tune")
    summary.success_mean, summary.weighted_success_mean

Starts and goals are written as on the command line: the goal's coordinates (the state at rest there) or a full
state. Every call is deterministic given ``seed`` (and the torch thread count, see docs/cli.md).
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts
from cdrb_cli.configs import MAX_EVAL_SEEDS, EvalSummary
from cdrb_cli.envs.registry import family_of
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput, NeedsScene
from cdrb_cli.settings import clip

__all__ = ["Plans", "Planner", "evaluate"]


@dataclass(frozen=True)
class Plans:
    """Plans for one or more start/goal pairs."""

    #: (P, H, obs_dim) planned states, raw units
    states: np.ndarray
    #: (P, H, F) the planned features (the states, and actions for state-action models)
    features: np.ndarray
    #: (P,) which start/goal pair each plan is for
    pair_index: np.ndarray
    #: (P,) share of each plan's states inside an obstacle
    in_obstacle: np.ndarray
    #: (P,) a planned state in an obstacle, or a straight step between two states through one
    through_obstacle: np.ndarray
    #: seconds per sampled batch
    seconds: float
    #: (P, S, H, F) intermediate iterates of each plan, raw units, with the ``keep_iterates`` setting (else None)
    iterates: np.ndarray | None = None
    #: the diffusion step of each kept iterate (None without them)
    iterate_steps: list[int] | None = None
    #: where the network ran: ``torch``, ``onnx`` or ``compile`` (``torch`` too for a method without a network
    #: call in sampling, such as the MLP planner)
    runtime: str = "torch"


def _settings(settings: dict | None, **fields) -> list:
    """The plan/eval settings of an API call: ``settings`` (dotted keys, as ``--set`` takes them: ``{"avoid.best_of":
    8, "controller.look_ahead": 2}``) after the keyword arguments that were given (not None). A field both give is
    refused, and so is a field the dict gives twice: a dict cannot repeat a key, so two of its keys that reach one
    field are two spellings of it (``best_of`` and ``best-of``, ``controller`` and ``controller.name``)."""
    from cdrb_cli.settings import from_mapping, given_once
    from cdrb_cli.stages.configure import fields_of, keyword_settings

    given, extra = keyword_settings(fields), from_mapping(dict(settings or {}))
    written = fields_of(extra)  # the fields each entry reaches (a table's fields share its entry's name)
    for i, s in enumerate(written):
        given_once(written[:i], [s], sep=" and ")
    given_once(fields_of(given), written, sep=" and ")
    return given + extra


def _switch(value, name: str) -> bool:
    """A yes/no argument: True or False (numpy's too), not any value that happens to be truthy."""
    if not isinstance(value, (bool, np.bool_)):
        raise BadInput(f"{name} = {clip(repr(value), 40)}: not True or False", hint=f"pass {name}=True or False")
    return bool(value)


def _path(value, name: str) -> Path:
    """A file or folder argument: a str or os.PathLike, as a Path."""
    if not isinstance(value, (str, Path)) and not hasattr(value, "__fspath__"):
        raise BadInput(f"{name} = {clip(repr(value), 40)}: not a path", hint=f"pass {name} as a str or a Path")
    try:
        value = os.fsdecode(value)  # an os.PathLike may give bytes, which Path does not take
    except (TypeError, ValueError):
        raise BadInput(
            f"{name} = {clip(repr(value), 40)}: not a path", hint=f"pass {name} as a str or a Path"
        ) from None
    if not value.strip():  # Path("") is ".", the working folder: never what was meant
        raise BadInput(f"{name} = {value!r}: an empty path", hint=f"pass {name} as a file's path")
    return Path(value)


def _text(value, name: str, hint: str) -> str:
    if not isinstance(value, str):
        raise BadInput(f"{name} = {clip(repr(value), 40)}: not a string", hint=hint)
    return value


def _seed(value, name: str = "seed") -> int:
    """A seed argument: a whole number in 0..2**32-1 (numpy's too); not a setting, so its error names the argument."""
    from cdrb_cli.configs import MAX_SEED
    from cdrb_cli.settings import plain

    value = plain(value)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_SEED:
        raise BadInput(f"{name} = {clip(repr(value), 40)}: not a seed", hint="pass a whole number in 0..2**32-1")
    return value


def _seed_list(value) -> list[int]:
    """The ``seeds`` of an evaluation: an ordered collection (a list, tuple, range, 1-D array or iterator), not a
    str, a single number (a 0-d array too), a dict (whose keys would silently be taken) or a set (whose order is not
    the caller's)."""
    ordered = hasattr(value, "__iter__") and getattr(value, "ndim", 1) != 0
    if isinstance(value, (str, bytes, dict, set, frozenset)) or not ordered:
        raise BadInput(f"seeds = {clip(repr(value), 40)}: not a list of seeds", hint="e.g. seeds=[0, 1, 2]")
    return list(itertools.islice(value, MAX_EVAL_SEEDS + 1))  # an endless iterable: refused as too long


def _mapping(value, name: str = "settings") -> dict | None:
    if value is not None and not isinstance(value, dict):
        raise BadInput(
            f"{name} = {clip(repr(value), 40)}: not a dict", hint='pass dotted keys, e.g. {"avoid.best_of": 4}'
        )
    return value


def _device(device):
    """The torch device of an API call, its threads set as the CLI sets them (the caller's allocator left alone)."""
    from cdrb_cli.torch_utils import setup_torch

    return setup_torch(_text(device, "device", 'pass "cpu", "cuda" or "auto"'), allocator=False, flag="device")


def _avoid(**fields) -> dict:
    """The avoidance keyword arguments of :class:`Planner` and :func:`evaluate` as ``avoid.*`` settings."""
    return {f"avoid.{k}": v for k, v in fields.items()}


#: the avoidance settings a plan's start may change from call to call (the family's choice for plans from anywhere)
PER_CALL = ("best_of", "fallback_route_k", "fallback_route_itself", "first_step", "retime")


class Planner:
    """A planner loaded from a model artifact (``cdrb train``) or a model folder (``cdrb export --dir``), ready to
    plan on its environment."""

    def __init__(
        self,
        model: str | Path,
        device: str = "cpu",
        ema: bool = True,
        scene: str | Path | None = None,
        mask_buffer: bool | None = None,
        best_of: int | None = None,
        route_k: int | None = None,
        guide_scale: float | None = None,
        route_clearance: float | None = None,
        settings: dict | None = None,
        allow_partial: bool = False,
        runtime: str = "auto",
    ):
        """``scene``: plan among obstacles the data never saw (`cdrb plan --scene`: a maze map with walls added, a
        Fetch TOML file of boxes put down), avoiding them as `cdrb plan` does by default (``settings={"avoid":
        "plain"}``: as the model is); ``mask_buffer``, ``best_of``, ``route_k``, ``route_clearance``,
        ``guide_scale``: the ``avoid.*`` settings of those names; ``settings``: any plan setting by its dotted key
        (`cdrb config plan`); ``allow_partial``: plan with an unfinished training's checkpoint (a warning);
        ``runtime``: where the diffusion planners' network runs. ``"auto"`` (the default): a :meth:`plan` call
        whose first batch samples at most 16 plans on the CPU (``n``, times ``best_of`` where each plan is the best
        of several, at most the ``batch`` setting at once) runs in ONNX Runtime, faster there, and a larger one in
        torch, its retries and repairs included; ``"torch"``: always torch, as `cdrb plan` and `cdrb eval` run it;
        ``"onnx"``: always ONNX Runtime (CPU only; slower in large batches);
        ``"compile"``: through ``torch.compile`` on any device, faster on a GPU after tens of seconds of compiling
        at the first plan of each batch size. Plans in ONNX Runtime equal torch's to float rounding, not bit for
        bit; :attr:`Plans.runtime` says which ran (:mod:`cdrb_cli.nets.runtime`)."""
        from cdrb_cli.stages.avoid import load_route_buffer, prepare_planner
        from cdrb_cli.stages.configure import plan_config, route_buffer_path
        from cdrb_cli.stages.plan import load_planner, scene_spec
        from cdrb_cli.stages.share import check_finished, load_model

        given = _settings(
            _mapping(settings),
            **{"use_ema": None if _switch(ema, "ema") else False},
            **_avoid(
                mask_buffer=mask_buffer,
                best_of=best_of,
                route_k=route_k,
                guide_scale=guide_scale,
                route_clearance=route_clearance,
            ),
        )
        self.model = load_model(_path(model, "model"))
        check_finished(self.model, _switch(allow_partial, "allow_partial"), "allow_partial=True")
        scene = None if scene is None else _path(scene, "scene")
        self._spec = scene_spec(self.model, scene, "scene")
        #: the plan settings every :meth:`plan` uses (n, seed and the sampler are its arguments)
        self._given, self._scene_file = given, scene
        self.config = plan_config(self.model, given, scene_file=self._scene_file)
        self.device = _device(device)
        self.method = load_planner(self.model, device=self.device, ema=self.config.use_ema)
        self.method.use_runtime(_text(runtime, "runtime", 'pass "auto", "torch", "onnx" or "compile"'), "runtime")
        self._route = load_route_buffer(route_buffer_path(given))
        self.avoidance = prepare_planner(self.method, self._spec, self.config.avoid, self._route)

    @property
    def spec(self) -> EnvSpec:
        """The environment plans are made in: the model's, or its task in ``scene``."""
        return self._spec

    def state(self, point: Sequence[float] | np.ndarray, flag: str = "start") -> np.ndarray:
        """A full state from a point written as ``cdrb plan`` takes it (``flag``: ``start`` or ``goal``, or the CLI's
        ``--start``/``--goal``, which its errors name): goal
        coordinates at rest, a full state, or the family's own start form (Fetch: the block's x,y); checked to be
        free, with the CLI's one-line errors."""
        if flag not in ("start", "goal", "--start", "--goal"):
            raise BadInput(f"flag = {clip(repr(flag), 40)}: not a point's name", hint='pass "start" or "goal"')
        name = flag.lstrip("-")
        if type(point).__module__.split(".")[0] == "torch" and hasattr(point, "detach"):  # a tensor, maybe with grad
            if getattr(getattr(point, "device", None), "type", None) == "meta":
                raise BadInput(f"{name}: a tensor on the meta device (a shape, no values)", hint="e.g. [0.0, 0.0]")
            point = point.detach().cpu()
            if str(point.dtype) in ("torch.bfloat16", "torch.float16"):  # numpy has no bfloat16: widen it exactly
                point = point.double()
            point = point.numpy()
        if np.ma.isMaskedArray(point):  # the cast would take a masked entry's hidden value
            if np.ma.getmaskarray(point).any():
                raise BadInput(f"{name}: masked values, not numbers", hint="fill them first, e.g. point.filled(0.0)")
            point = np.ma.getdata(point)
        # a cast would read True as 1.0 or "1" as 1.0, drop an imaginary part, or a date's unit, without a word: the
        # array's kind and, in a list or an object array, each element's
        kinds = {
            "b": "booleans",
            "c": "complex numbers",
            "U": "strings",
            "S": "strings",
            "M": "dates",
            "m": "time spans",
        }
        items = point.ravel().tolist() if isinstance(point, np.ndarray) and point.dtype.kind == "O" else point
        try:
            kind = np.asarray(point).dtype.kind if isinstance(point, (np.ndarray, list, tuple)) else None
        except (TypeError, ValueError):  # a ragged list: the cast below refuses it
            kind = None
        if isinstance(items, (list, tuple)) and any(v is None for v in items):  # the cast would read it as NaN
            raise BadInput(f"{name}: None where a number belongs", hint="e.g. [0.0, 0.0]")
        if isinstance(items, (list, tuple)):
            odd = [v for v in items if isinstance(v, (bool, np.bool_, str, bytes, complex, np.complexfloating,
                                                      np.datetime64, np.timedelta64))]  # fmt: skip
            if odd:
                kind = np.asarray(odd[:1]).dtype.kind
        if kind in kinds:
            raise BadInput(f"{name}: {kinds[kind]}, not real numbers", hint="e.g. [0.0, 0.0]")
        try:
            values = np.asarray(point, dtype=np.float64)
        except (TypeError, ValueError, OverflowError):
            raise BadInput(f"{name} = {clip(repr(point), 60)}: not a list of numbers", hint="e.g. [0.0, 0.0]") from None
        if values.ndim != 1 or not len(values):
            raise BadInput(f"{name}: a flat list of numbers, not shape {values.shape}", hint="e.g. [0.0, 0.0]")
        if len(values) > self.spec.obs_dim:
            raise BadInput(
                f"{name}: {len(values):,} numbers, more than the {self.spec.obs_dim} of a {self.spec.id} state",
                hint="e.g. [0.0, 0.0]",
            )
        if not np.isfinite(values).all():
            raise BadInput(f"{name} = {clip(repr(values.tolist()), 60)}: not finite", hint="e.g. [0.0, 0.0]")
        return family_of(self.spec).parse_point(self.spec, ",".join(repr(float(v)) for v in values), flag)

    def plan(
        self,
        start: Sequence[float] | np.ndarray,
        goal: Sequence[float] | np.ndarray,
        n: int | None = None,
        seed: int = 0,
        sampler: str | None = None,
        steps: int | None = None,
    ) -> Plans:
        """``n`` plans from ``start`` to ``goal`` (1, or the ``n`` of the planner's settings; ``sampler`` and
        denoising ``steps``: the model's by default). A setting given here and in the planner's ``settings`` is
        refused (neither would silently win)."""
        from cdrb_cli.settings import given_once
        from cdrb_cli.stages.avoid import buffer_graph
        from cdrb_cli.stages.configure import plan_config
        from cdrb_cli.stages.plan import sample_plans

        # the same checks as `cdrb plan` (n a whole number in bounds, a 32-bit seed, steps 1..T, a known sampler)
        given = [  # errors name the argument: steps=..., not the setting's key
            replace(s, source=f"steps={steps!r}") if s.path == ("sample_steps",) else s
            for s in _settings(None, n=n, sampler=sampler, sample_steps=steps)
        ]
        given_once(self._given, given, sep=" and ")
        if steps is not None and getattr(self.model.manifest.config.method, "diffusion_steps", None) is None:
            raise BadInput(f"steps={steps!r}: a {self.method.name} model plans in one pass (no denoising steps)",
                           hint="leave steps out")  # fmt: skip
        seed = _seed(seed)
        s, g = self.state(start, "start")[None], self.state(goal, "goal")[None]  # errors name the arguments
        config = plan_config(self.model, [*self._given, *given], seed=seed, scene_file=self._scene_file, starts=s)
        # a start away from the data's starts may take a larger best-of and a second try from a buffer route (the
        # family's choice for plans from anywhere); otherwise the prepared avoidance itself, whose counters (e.g.
        # ``unrouted``) then keep counting every call
        avoid = self.avoidance
        change = {f: getattr(config.avoid, f) for f in PER_CALL if getattr(config.avoid, f) != getattr(avoid, f)}
        if change:
            avoid = replace(avoid, **change)
            if avoid.fallback_route_k is not None and avoid.graph is None:
                avoid.graph = buffer_graph(self.method, self.spec, config.avoid, self._route)
                self.avoidance.graph = avoid.graph  # built once: the same buffer and scene for every call
        with self.method.runtime_scope() as runtimes:  # one runtime for the whole call, its retries included
            out = sample_plans(
                self.method, s, g, config.n, config.seed, config.sampler, config.sample_steps, config.keep_iterates,
                batch_size=config.batch, device=self.device, avoid=avoid,
            )  # fmt: skip
        fam = family_of(self.spec)
        states = out.plans[..., : self.spec.obs_dim]
        return Plans(
            states=states,
            features=out.plans,
            pair_index=out.pair_index,
            in_obstacle=fam.in_collision(self.spec, states).mean(axis=-1),
            through_obstacle=fam.path_in_collision(self.spec, states),
            seconds=out.seconds,
            iterates=out.iterates,
            iterate_steps=out.iterate_steps,
            runtime="+".join(sorted(runtimes)) or "torch",
        )


def evaluate(
    model: str | Path,
    out: str | Path,
    episodes: int | None = None,
    seeds: Sequence[int] | None = None,
    stream: str | None = None,
    controller: str | None = None,
    protocol: str | None = None,
    device: str = "cpu",
    force: bool = False,
    scene: str | Path | None = None,
    mask_buffer: bool | None = None,
    best_of: int | None = None,
    route_k: int | None = None,
    guide_scale: float | None = None,
    route_clearance: float | None = None,
    replan: str | None = None,
    settings: dict | None = None,
    seed: int = 0,
    allow_partial: bool = False,
) -> EvalSummary:
    """``cdrb eval``: plan once per episode, execute, write the eval artifact ``out``, return its summary. The
    arguments are the eval settings of those names (``controller``: ``controller.name``; the avoidance ones
    ``avoid.*``, as in :class:`Planner`; ``replan``: ``never``, ``every:N`` or ``deviation:D``), checked as the
    CLI checks them, None for the CLI's default (``episodes``, ``seeds``, ``stream``: 100 episodes on seeds 0-4 from
    the test stream, as `cdrb config eval` lists); ``settings``: any other by its dotted key; ``scene`` with
    ``protocol="detour"`` for the pairs new obstacles lengthen; ``allow_partial``: evaluate an unfinished training's
    checkpoint (a warning; the eval records the step it stopped at)."""
    from cdrb_cli.artifacts import check_output
    from cdrb_cli.stages.avoid import load_route_buffer
    from cdrb_cli.stages.configure import eval_config, route_buffer_path
    from cdrb_cli.stages.evaluate import eval_artifact
    from cdrb_cli.stages.plan import scene_spec
    from cdrb_cli.stages.share import check_finished

    seeds = None if seeds is None else _seed_list(seeds)
    force = _switch(force, "force")
    given = _settings(
        _mapping(settings),
        episodes=episodes,
        seeds=seeds,
        stream=stream,
        protocol=protocol,
        replan=replan,
        **{"controller.name": controller},
        **_avoid(
            mask_buffer=mask_buffer,
            best_of=best_of,
            route_k=route_k,
            guide_scale=guide_scale,
            route_clearance=route_clearance,
        ),
    )
    m = artifacts.load(_path(model, "model"), "model")
    check_finished(m, _switch(allow_partial, "allow_partial"), "allow_partial=True")
    out = _path(out, "out")
    map_path = None if scene is None else _path(scene, "scene")
    where = scene_spec(m, map_path, "scene")
    try:
        config = eval_config(m, given, seed=_seed(seed), scene_file=map_path, scene=where)
    except NeedsScene as exc:
        raise exc.in_python() from None
    route = load_route_buffer(route_buffer_path(given))
    inputs = [m.path, *([] if map_path is None else [map_path]), *([] if route is None else [route.path])]
    check_output(out, True, "out", inputs)  # an existing file: up to date, or refused without force below
    device = _device(device)
    result = eval_artifact(m, config, out, force=force, device=device, scene=where, route_buffer=route, flag="out")
    return result.manifest.summary
