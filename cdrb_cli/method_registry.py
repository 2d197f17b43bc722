"""The method registry: name -> what cdrb needs to know about a method before (and for) running it.

Each method module declares, next to its code, a :class:`MethodParams` record with its hyper-parameters (its
``sampler`` field's ``Literal`` lists the samplers it offers) and registers a :class:`MethodEntry`. ``cdrb train``,
``plan``, ``eval``, ``quickstart``, ``report`` and the benchmarks read this registry: CLI choices, presets, which
methods need a buffer, which nets they accept. Built-in methods are listed in :data:`METHODS`'s table (one line
each; the order is the column order of reports); others register themselves (see :mod:`cdrb_cli.registry`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, get_args, get_origin

from pydantic import Field

from cdrb_cli.errors import BadInput
from cdrb_cli.registry import Registry
from cdrb_cli.schema_base import Record

DEFAULT_METHOD = "cdrb"


class MethodParams(Record):
    """Base of every method's hyper-parameters (stored in the model artifact as ``config.method``). Subclasses
    fix ``name`` with a ``Literal`` and give ``sampler`` a ``Literal`` of the samplers they offer (first =
    default)."""

    name: str
    sampler: str


class StartWeightParams(MethodParams):
    """The loss weighting of the planned states right after the pinned start, for the trajectory planners that
    share it (CDRB, Diffuser): declared once here."""

    start_weight: float = Field(
        1.0,
        ge=1,
        le=1000,
        description="loss weight of the planned states right after the pinned start (the first start_span), so the "
        "plan leaves the start as the data does; 1 = every state alike",
    )
    start_span: int = Field(4, ge=1, le=64, description="how many states after the start start_weight covers")


def start_weighted(sq, params: StartWeightParams):
    """Squared errors (B, H, F) with the ``start_span`` states after the start weighted ``start_weight`` (the mean
    weight kept at 1, so losses stay comparable); unchanged when the weight is 1."""
    if params.start_weight == 1.0:
        return sq
    import torch

    w = torch.ones(sq.shape[1], dtype=sq.dtype, device=sq.device)
    w[1 : 1 + params.start_span] = params.start_weight
    return sq * (w / w.mean())[None, :, None]


@dataclass(frozen=True)
class BufferInfo:
    """What config resolution needs to know about a replay buffer."""

    features: str
    diameter: float
    #: the largest shortest-path distance along the buffer's transition graph (None: no graph)
    graph_diameter: float | None = None
    #: the diagonal of the data's bounding box in normalized features (2 per feature that varies, in quadrature)
    box_diagonal: float | None = None


@dataclass(frozen=True)
class MethodEntry:
    """A registered method.

    * ``params``: its hyper-parameter record (its ``name`` Literal is the method's name, its ``sampler`` Literal
      the samplers it offers); ``method``: the class that trains and samples, a
      :class:`~cdrb_cli.methods.base.Planner` (whole trajectories, executed by a controller) or
      :class:`~cdrb_cli.methods.base.Policy` (acts every step) subclass;
    * ``needs_buffer``: training and sampling use the replay buffer (``cdrb train --buffer``);
    * ``nets``: the network kinds it accepts, default first;
    * ``presets``: preset name -> values of ``params`` fields;
    * ``data_defaults(spec, buffer)`` or ``(spec, buffer, settings)``: defaults that depend on the data (e.g. CDRB's
      d_max = buffer diameter, along the graph for geodesic balls);
    * ``train_defaults``: preset name -> training-config fields this method sets otherwise than the preset (a
      policy: state-action features, one action per chunk, its batch size and steps); the user's settings still win.
    """

    params: type[MethodParams]
    method: type
    needs_buffer: bool = False
    nets: tuple[str, ...] = ("unet", "transformer")
    presets: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    data_defaults: Callable[..., dict[str, Any]] | None = None
    train_defaults: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    description: str = ""

    @property
    def name(self) -> str:
        return self.params.model_fields["name"].default

    @property
    def kind(self) -> Literal["planner", "policy"]:
        return self.method.kind

    @property
    def samplers(self) -> tuple[str, ...]:
        """The values of the params' ``sampler`` Literal (the first is the default)."""
        annotation = self.params.model_fields["sampler"].annotation
        if get_origin(annotation) is Literal:
            return tuple(get_args(annotation))
        return (self.params.model_fields["sampler"].default,)

    @property
    def default_net(self) -> str:
        return self.nets[0]

    def check_sampler(self, sampler: str, flag: str = "--sampler") -> str:
        if sampler not in self.samplers:
            raise BadInput(f"{flag} {sampler}: {self.name} models use {', '.join(self.samplers)}")
        return sampler


METHODS: Registry[MethodEntry] = Registry(
    "method",
    {
        "mlp": "cdrb_cli.methods.mlp",
        "diffuser": "cdrb_cli.methods.diffuser",
        "cdrb": "cdrb_cli.methods.cdrb",
        "diffusion-bc": "cdrb_cli.methods.diffusion_bc",
        "diffusion-ql": "cdrb_cli.methods.diffusion_ql",
        "straight": "cdrb_cli.methods.straight",
    },
    MethodEntry,
)
