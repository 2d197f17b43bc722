"""The interface every method implements, and the defaults most of them use.

A method owns its networks (:meth:`Method.modules`), their optimizers (:meth:`Method.make_optimizers`), one
training update (:meth:`Method.update`: any number of losses, backward passes and optimizer steps), and its
sampler. The training loop (``stages/train.py``) and the checkpoint (``methods/checkpoint.py``) only go through
these, so a method with an actor, twin critics, target networks and two optimizers fits as well as a planner with
one network. Two kinds exist:

* a :class:`Planner` samples whole trajectories from a start to a goal (executed by the family's controller);
* a :class:`Policy` acts every environment step (``act``), closed loop.

Everything here runs in normalized feature space (``normalizer``: per-feature min/max to [-1, 1]); the state comes
first in a feature vector, then the action when ``features == "state-action"``.
"""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from cdrb_cli import ui
from cdrb_cli.buffer import Normalizer, feature_dim
from cdrb_cli.configs import TrainConfig
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.errors import BadInput
from cdrb_cli.lazy import torch
from cdrb_cli.nets import build_net
from cdrb_cli.torch_utils import adam


class NonFiniteLoss(Exception):
    """Raised by :meth:`Method.update` before any weight changes when a loss is NaN or infinite."""

    def __init__(self, value: float):
        super().__init__(value)
        self.value = value


@dataclass
class SampleResult:
    """Plans (P, H, F) in normalized space and, optionally, intermediate iterates [(k, (P, H, F))]."""

    plans: torch.Tensor
    iterates: list[tuple[int, torch.Tensor]] = field(default_factory=list)


class Method:
    """Networks, losses and a training update for one method (see the module docstring)."""

    kind: ClassVar[str] = "method"

    def __init__(
        self,
        config: TrainConfig,
        spec: EnvSpec,
        normalizer: Normalizer,
        buffer_points=None,
        device="cpu",
        buffer_graph: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        self.config = config
        #: the buffer's transition graph (edges, weights) where the method measures balls along it, else None
        self.buffer_graph = buffer_graph
        self.spec = spec
        self.normalizer = normalizer
        self.device = torch.device(device)
        self.obs_dim = spec.obs_dim
        self.feature_dim = feature_dim(spec, config.features)
        self.horizon = config.horizon
        every = list(range(self.obs_dim))
        self.pinned = slice(0, self.obs_dim) if spec.pin_dims == every else spec.pin_dims  # at the start
        self.pinned_end = slice(0, self.obs_dim) if spec.pin_end_dims == every else spec.pin_end_dims  # at the goal
        self.build(buffer_points)

    @property
    def name(self) -> str:
        """The method's registered name (its params record's ``name``)."""
        return self.config.method.name

    def variant(self) -> str | None:
        """What sets this model apart from its method as the paper defines it, in a few words that `cdrb report`
        adds to its row (e.g. "geodesic balls"); None: as the paper."""
        return None

    def build(self, buffer_points) -> None:
        """Create the networks (the default: one trajectory network ``self.net``)."""
        self.net = build_net(self.config.net, self.feature_dim, self.horizon, cond_dim=self.obs_dim).to(self.device)

    # -------------------------------------------------------------- training
    @staticmethod
    def check_data(demos, config) -> None:
        """Refuse ``demos`` that ``config``'s training windows cannot be drawn from sensibly (before any network
        is built): a planner's window spanning far more than the longest demonstration."""
        from cdrb_cli.data import check_window_span

        check_window_span(demos, config.horizon, config.stride)

    def data(self, demos, normalizer: Normalizer, split: str):
        """What training batches are drawn from (``.sample(n, rng)``, ``.validation_batch()``): plan windows."""
        from cdrb_cli.data import WindowSampler

        c = self.config
        return WindowSampler(
            demos, c.features, normalizer, c.horizon, c.stride, split, c.start_fraction if split != "valid" else 0.0
        )

    def modules(self) -> dict[str, torch.nn.Module]:
        """Every network whose weights the model artifact keeps, by name."""
        return {"net": self.net}

    def ema_modules(self) -> tuple[str, ...]:
        """The modules the training loop keeps an exponential moving average of (sampling uses the averages)."""
        return tuple(self.modules())

    def make_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        """Every optimizer the checkpoint keeps, by name."""
        return {"net": adam(self.net.parameters(), lr=self.config.lr)}

    def loss(self, batch: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        """The training loss of a batch (also the validation loss)."""
        raise NotImplementedError

    def update(self, batch: torch.Tensor, rng: np.random.Generator, optimizers: dict) -> float:
        """One training update; returns the loss to log. Raises :class:`NonFiniteLoss` before touching weights."""
        with self.autocast(batch.device):
            loss = self.loss(batch, rng).float()
        if not torch.isfinite(loss):
            raise NonFiniteLoss(float(loss.detach()))
        opt = optimizers["net"]
        opt.zero_grad(set_to_none=True)
        loss.backward()
        if self.config.grad_clip:
            torch.nn.utils.clip_grad_norm_(self.net.parameters(), self.config.grad_clip)
        opt.step()
        return float(loss.detach())

    def autocast(self, device: torch.device):
        """The context the forward passes of a training update run in: ``torch.autocast`` to bfloat16 when the
        training config asks for it (``precision``), else nothing. Backward passes and optimizer steps stay outside
        it, as torch recommends; they follow the dtypes the forward passes chose."""
        wanted = self.config.precision == "bfloat16"
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16, enabled=wanted)

    def extra_arrays(self) -> dict[str, np.ndarray]:
        """Arrays the model artifact must carry for sampling (e.g. the CDRB buffer)."""
        return {}

    def eval(self) -> Method:
        for m in self.modules().values():
            m.eval()
        return self

    #: whether :meth:`sample_net` may run a trace of the network (off: the module itself; benchmarks compare both)
    trace_sampling: ClassVar[bool] = True
    #: where :meth:`sample_net` runs the network: ``torch``, ``onnx`` (ONNX Runtime on the CPU), ``compile``
    #: (``torch.compile``) or ``auto`` (ONNX Runtime for small batches on the CPU, else torch; see
    #: :mod:`cdrb_cli.nets.runtime`; set by :meth:`use_runtime`)
    runtime: str = "torch"
    #: network calls made before :meth:`sample_net` traces it: the first trace in a process costs ~0.5 s of
    #: imports and tracing, which a few plans (one `cdrb plan`, one eval batch) would not earn back
    TRACE_AFTER: ClassVar[int] = 96

    def _call_state(self) -> threading.local:
        """This thread's view of the sampling call it is in (two threads may plan with one method at once): whether
        it is in one (``in_call``), whether ONNX Runtime's weights were checked in it (``checked``), ``auto``'s pick
        (``pick``), and inside :meth:`runtime_scope` (``scoped``) the runtimes that ran (``used``)."""
        state = self.__dict__.get("_call_local")
        return state if state is not None else self.__dict__.setdefault("_call_local", threading.local())

    @contextlib.contextmanager
    def sampling_call(self):
        """The span of one sampling call (a plan, a repair): :meth:`sample_net` looks at the network's weights at its
        first network call within it and trusts that answer until it ends (weights cannot change mid-call); outside
        one, every network call looks again. Outside a :meth:`runtime_scope`, ``auto`` picks its runtime anew for
        each sampling call."""
        state = self._call_state()
        state.in_call, state.checked = True, False
        if not getattr(state, "scoped", False):
            state.pick = None
        try:
            yield
        finally:
            state.in_call, state.checked = False, False
            if not getattr(state, "scoped", False):
                state.pick = None

    @contextlib.contextmanager
    def runtime_scope(self):
        """A span of sampling calls that ``auto`` runs in one runtime, picked at its first network call (an API
        plan: its batches, and the repairs and retries of some of its plans). Yields the set of runtimes that ran
        in it, filled as it runs."""
        state = self._call_state()
        state.scoped, state.pick, state.used = True, None, set()
        try:
            yield state.used
        finally:
            state.scoped, state.pick, state.used = False, None, None

    def sample_net(self, x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """``self.net(x, k)`` as sampling calls it. With the network in eval mode and no gradient wanted, once it
        has been called :data:`TRACE_AFTER` times, a trace of it (``torch.jit.trace``, made per device and dtype)
        runs instead: the same operations on the same parameters, so the same bits (tests/test_plan.py), without
        Python's cost per module call, which is most of a small network's time at batch 1 on a CPU (a re-planning
        robot, the Python API, closed-loop evals). Networks that declare ``traceable`` are traced. TorchScript is
        deprecated from torch 2.13 (FX graphs and torch.export keep the Python calls, so they do not help here):
        where tracing fails, the module itself runs, the same bits more slowly. With :attr:`runtime` ``onnx`` every
        call runs in ONNX Runtime instead (:class:`~cdrb_cli.nets.runtime.OnnxNet`), with ``compile`` through
        ``torch.compile`` (:class:`~cdrb_cli.nets.runtime.CompiledNet`; it reads the module's parameters at every
        call, so new weights need no check); with ``auto`` in the one :meth:`_auto_runtime` picks."""
        net = self.net
        if net.training or torch.is_grad_enabled():
            return net(x, k)
        state = self._call_state()
        used = getattr(state, "used", None)
        runtime = self.runtime
        if runtime == "auto":
            runtime = self._auto_runtime(x, state)
            if runtime == "onnx":
                try:
                    out = self._onnx_call(net, x, k, state)
                except BadInput as exc:  # an exporter or runtime that cannot take this network: torch runs it
                    reason = exc.message.removeprefix("runtime = 'onnx': ")
                    ui.warn(f"runtime 'auto': {reason}; planning with torch")
                    self._auto_onnx, state.pick, runtime = False, "torch", "torch"
                else:
                    if used is not None:
                        used.add(runtime)
                    return out
        if used is not None:
            used.add(runtime)
        if runtime == "compile":  # from the first call, as onnx
            compiled = self.__dict__.get("_compiled")
            if compiled is None or compiled[0] is not net:
                from cdrb_cli.nets.runtime import CompiledNet

                self._compiled = compiled = (net, CompiledNet(net))
            return compiled[1](x, k)
        if runtime == "onnx":  # from the first call, so a plan never depends on how many came before it
            return self._onnx_call(net, x, k, state)
        if not self.trace_sampling or not getattr(net, "traceable", False):
            return net(x, k)
        cache = self.__dict__.setdefault("_traces", {})
        key = (id(net), x.device, x.dtype)
        calls = self.__dict__.get("_net_calls", 0)
        if key not in cache and calls < self.TRACE_AFTER:
            self._net_calls = calls + 1
            return net(x, k)
        if key not in cache:
            import warnings

            with warnings.catch_warnings():
                # GroupNorm's check of its input size is a Python test on shapes that holds for any batch, and the
                # deprecation is answered above: nothing to warn a user of
                warnings.simplefilter("ignore", torch.jit.TracerWarning)
                warnings.simplefilter("ignore", DeprecationWarning)
                try:
                    cache[key] = torch.jit.trace(net, (x, k), check_trace=False)
                except Exception:  # noqa: BLE001 - a torch without TorchScript, or a net it cannot trace
                    cache[key] = None
        traced = cache[key]
        return net(x, k) if traced is None else traced(x, k)

    def _onnx_call(self, net, x: torch.Tensor, k: torch.Tensor, state) -> torch.Tensor:
        """``net(x, k)`` in ONNX Runtime, through a session rebuilt when the network or its weights changed; the
        weights are compared with the session's copy once per sampling call (they cannot change while it runs)."""
        from cdrb_cli.nets.runtime import OnnxNet

        onnx = self.__dict__.get("_onnx")
        if onnx is None or onnx[0] is not net or not getattr(state, "checked", False):
            if onnx is None or onnx[0] is not net or not onnx[1].holds(net):  # a new network, or new weights
                self._onnx = onnx = (net, OnnxNet(net, x, k))
            state.checked = getattr(state, "in_call", False)
        return onnx[1](x, k)

    def _auto_runtime(self, x: torch.Tensor, state) -> str:
        """``auto``'s pick: ``onnx`` where it is installed and the first network call of the sampling call (or of
        the :meth:`runtime_scope`) is on the CPU in float32 at a batch of at most
        :data:`~cdrb_cli.nets.runtime.AUTO_ONNX_BATCH`, else ``torch``; kept for the rest of the call or scope, so
        the same seed and batch give the same plans."""
        from cdrb_cli.nets.runtime import AUTO_ONNX_BATCH

        pick = getattr(state, "pick", None)
        if pick is None:
            small = x.device.type == "cpu" and x.dtype == torch.float32 and x.shape[0] <= AUTO_ONNX_BATCH
            pick = "onnx" if small and self.__dict__.get("_auto_onnx", False) else "torch"
            if getattr(state, "in_call", False) or getattr(state, "scoped", False):
                state.pick = pick
        return pick

    def use_runtime(self, runtime: str, flag: str = "runtime") -> None:
        """Run sampling's network calls in ``runtime`` (checked: one-line errors name ``flag``)."""
        from cdrb_cli.nets.runtime import check_runtime, onnx_available

        net = getattr(self, "net", None)
        self.runtime = check_runtime(runtime, net, self.device, self.name, flag)
        self._auto_onnx = self.runtime == "auto" and onnx_available(net, self.device)

    # -------------------------------------------------------------- pinning
    def pin(self, x: torch.Tensor, start: torch.Tensor, goal: torch.Tensor) -> torch.Tensor:
        """Overwrite the pinned dimensions of the first and last planned states (a new tensor; exact copies)."""
        x = x.clone()
        first, last = self._index(self.pinned, x.device), self._index(self.pinned_end, x.device)
        x[:, 0, first] = start[:, first]
        x[:, -1, last] = goal[:, last]
        return x

    def _index(self, dims, device):
        """``dims`` as an index: a slice as it is, a list as a tensor kept on ``device`` (indexing with a Python list
        would copy it to the device at every call, which a CUDA graph cannot hold)."""
        if isinstance(dims, slice):
            return dims
        cache = self.__dict__.setdefault("_indices", {})
        key = (tuple(dims), str(device))
        if key not in cache:
            cache[key] = torch.as_tensor(list(dims), dtype=torch.long, device=device)
        return cache[key]

    def pinned_only(self, start: torch.Tensor, goal: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Start and goal with every dimension that is not pinned zeroed: what a method may condition on (at
        sampling, the goal state's other dimensions are made up by the family, in training they come from data)."""
        if isinstance(self.pinned, slice) and isinstance(self.pinned_end, slice):
            return start, goal
        s, g = torch.zeros_like(start), torch.zeros_like(goal)
        s[:, self.pinned] = start[:, self.pinned]
        g[:, self.pinned_end] = goal[:, self.pinned_end]
        return s, g

    @staticmethod
    def ends(batch: torch.Tensor, obs_dim: int) -> tuple[torch.Tensor, torch.Tensor]:
        return batch[:, 0, :obs_dim], batch[:, -1, :obs_dim]


class Planner(Method):
    """A method that samples whole trajectories; the first and last states are pinned to the start and goal."""

    kind = "planner"

    def sample(
        self,
        start: torch.Tensor,
        goal: torch.Tensor,
        rng: np.random.Generator,
        sampler: str | None = None,
        steps: int | None = None,
        keep_iterates: int = 0,
    ) -> SampleResult:
        """Plans for normalized start and goal states (P, obs_dim), with the current weights."""
        with self.sampling_call(), torch.no_grad():
            return self._sample(start, goal, rng, sampler or self.config.method.sampler, steps, keep_iterates)

    def _sample(self, start, goal, rng, sampler: str, steps: int | None, keep_iterates: int) -> SampleResult:
        raise NotImplementedError

    #: whether :meth:`repair` restores from a partly degraded plan (False: it plans from scratch)
    repairs: ClassVar[bool] = False
    #: whether :meth:`mask` can keep sampling away from states (a method that samples from a buffer)
    masks: ClassVar[bool] = False
    #: whether sampling can follow the gradient of a cost (:meth:`set_guide`)
    guides: ClassVar[bool] = False
    #: (cost of normalized plans (P, H, F) -> (P,), scale) that :meth:`sample` follows, or None
    guide: tuple | None = None

    def mask(self, collides) -> dict[str, int]:
        """Keep sampling away from the states ``collides`` (normalized feature rows (N, F) -> bool (N,)) marks, for
        obstacles the training data never saw. Returns counts to report (e.g. buffer states removed)."""
        raise NotImplementedError(f"{self.name} samples from no buffer it could mask")

    def set_guide(self, cost, scale: float) -> None:
        """Follow ``cost`` (normalized plans (P, H, F) -> (P,), differentiable) down its gradient with step ``scale``
        while sampling (None or scale 0: off)."""
        if cost is not None and scale > 0 and not self.guides:
            raise NotImplementedError(f"{self.name} has no guided sampling")
        self.guide = (cost, float(scale)) if cost is not None and scale > 0 else None

    def repair_steps(self) -> int | None:
        """The largest degradation step ``k`` :meth:`repair` accepts (None: the method has no such step)."""
        return None

    def repair(
        self,
        start: torch.Tensor,
        goal: torch.Tensor,
        previous: torch.Tensor,
        k: int,
        rng: np.random.Generator,
        sampler: str | None = None,
        steps: int | None = None,
    ) -> SampleResult:
        """Plans that start from ``previous`` (P, H, F), normalized plans already shifted to the current state:
        degraded to step ``k`` and restored from there (``steps``: denoising steps, at most ``k``). A method
        without a degradation it can stop part way (the MLP) plans from scratch, which is what "re-predict" means
        for it."""
        return self.sample(start, goal, rng, sampler=sampler, steps=steps)


class Policy(Method):
    """A method that acts every environment step, closed loop: ``reset`` once per batch of episodes, then
    ``act`` with the current raw states and goals (n, obs_dim) / (n, goal_dim); returns raw actions."""

    kind = "policy"

    @staticmethod
    def check_data(demos, config) -> None:
        """Policies learn from transitions, never a plan's window: nothing to refuse here."""

    def reset(self, n: int, rng: np.random.Generator) -> None:
        """Start ``n`` episodes (clears any action chunk or history)."""

    def act(self, states: np.ndarray, goals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        raise NotImplementedError


def keep_schedule(total: int, keep: int) -> set[int]:
    """Which of ``total`` iterations to keep as iterates (evenly spaced, ``keep`` of them)."""
    if keep <= 0 or total <= 0:
        return set()
    return {int(round(i)) for i in np.linspace(0, total - 1, min(keep, total))}


def build_method(
    config: TrainConfig, spec: EnvSpec, normalizer: Normalizer, buffer_points=None, device="cpu", buffer_graph=None
):
    """The method a config names, built from the registry (``buffer_graph``: the buffer's transition graph, for a
    method that measures balls along it)."""
    from cdrb_cli.methods.registry import METHODS

    cls = METHODS.get(config.method.name).method
    if buffer_graph is None:
        return cls(config, spec, normalizer, buffer_points, device)
    return cls(config, spec, normalizer, buffer_points, device, buffer_graph=buffer_graph)
