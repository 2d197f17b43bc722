"""Cold Diffusion on the Replay Buffer (CDRB).

Training (the paper's Algorithm "Training the Noise Model"): draw a demonstration window tau with its ends as
start and goal, k ~ U{1..T-1}, degrade it with the ball sampler, tau_k = D(tau, k) (ends pinned), restore
R(tau_k, k), pin its ends, and minimize the L2 distance to tau.

Sampling, ``sampler = "paper"`` (the paper's appendix algorithm "Sampling Process", as released): tau_{T-1} =
random buffer states with start and goal pinned; for k = T-1 .. 1: x0 = R(tau_k, k), pin, tau_{k-1} = D(x0, k-1),
pin; the plan is the last x0 (D(., 0) is the identity). ``sampler = "cold-improved"`` is Cold Diffusion's
improved update (Bansal et al.'s Algorithm 2), tau_{k-1} = tau_k - D(x0, k) + D(x0, k-1), for ablations.
``steps`` < T-1 runs the same updates on an evenly spaced subsequence of k.

Plan repair (``repair``, for closed-loop evaluation): a previous plan, shifted to the current state, is degraded
to a small step k by the same ball sampler and restored from k down to 1 with the same updates.

A masked buffer (``mask``, for obstacles the data never saw): the buffer states inside them are removed before
sampling, so every degraded plan is made of free states; a restored state that still lies inside one is re-drawn
from the kept buffer states of the smallest ball around it that holds one.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.buffer import BallSampler, TorchBallSampler, radii
from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import Planner, SampleResult, keep_schedule
from cdrb_cli.methods.registry import METHODS, MethodEntry, StartWeightParams, start_weighted


class CDRBParams(StartWeightParams):
    name: Literal["cdrb"] = "cdrb"
    schedule: Literal["linear", "log", "geometric", "sqrt", "sigmoid"] = Field(
        "linear",
        description="how the ball radius eps_k grows with k: linear (the paper's and the official code's default), "
        "log (the official code's log option, concave), geometric (log-spaced, convex), sqrt, sigmoid",
    )
    d_max: float = Field(
        gt=0,
        le=1e6,
        description="largest ball radius, in normalized feature space (default: the buffer's diameter; for geodesic "
        "balls its diameter along the transition graph; at most 1e6, far past any buffer's)",
    )
    d_max_from: Literal["buffer", "data-box"] = Field(
        "buffer",
        description="where d_max comes from when not set: the buffer's diameter (the largest ball holds the whole "
        "buffer) or data-box, the diagonal of the data's bounding box in normalized features (the official Fetch "
        "code's, about 1.8x larger there)",
    )
    diffusion_steps: int = Field(gt=1, le=100_000, description="T, the number of diffusion steps")
    sampler: Literal["paper", "cold-improved"] = Field(
        "paper",
        description="paper: restore, then degrade to k-1 (the paper's sampling algorithm, as released); "
        "cold-improved: Cold Diffusion's improved update tau_k - D(x0, k) + D(x0, k-1)",
    )
    end_actions: Literal["degraded", "kept"] = Field(
        "degraded",
        description="state-action features: the action part of the pinned end states is degraded like any state "
        "(only the state is pinned, as at sampling), or kept (models before schema 2.2)",
    )
    loss_weight_power: float = Field(
        0.0,
        ge=0,
        le=16,
        description="weight each sample's loss by (eps_1 / eps_k)^p (the official code's option; 0 = off; at most 16, "
        "past which every weight but step 1's is zero)",
    )
    ball_candidates: Literal["adaptive", "fixed"] = Field(
        "adaptive",
        description="the ball sampler's first rejection round: adaptive (as many uniform candidates as a ball of "
        "that radius needs, 2 to 32) or fixed (32 for every ball; models before schema 2.8). The same law; "
        "another random stream, so a seed gives other draws",
    )
    ball: Literal["euclidean", "geodesic"] = Field(
        "euclidean",
        description="how a ball around a state is measured: euclidean (the paper's: distance in the normalized "
        "features) or geodesic (along the buffer's transition graph, the paths the demonstrations took: a "
        "degradation never swaps a state across a wall the demos went round; the buffer must carry its graph)",
    )
    geodesic_radii: Literal["matched", "scaled"] = Field(
        "matched",
        description="geodesic balls: each step's radius along the graph. matched: the least radius, not below the "
        "paper's Euclidean one of that step, whose balls around the buffer states hold as many members as the "
        "paper's balls (the schedule over the buffer's Euclidean diameter) hold among pairs of one component, so a "
        "step degrades as strongly as the paper's; scaled: the schedule stretched to d_max (models before schema "
        "2.14). The last radius is d_max either way, and none is above it",
    )


def _loss_weight_label(power: float) -> str:
    """The loss weight (eps_1 / eps_k)^p as a label: ``unweighted loss`` at p = 0, ``1/eps_k loss weight`` for the
    official code's p = 1."""
    if power == 0:
        return "unweighted loss"
    return "1/eps_k loss weight" if power == 1 else f"loss weight (eps_1/eps_k)^{power:g}"


class CDRB(Planner):
    def build(self, buffer_points) -> None:
        super().build(buffer_points)
        p = self.config.method
        if buffer_points is None or len(buffer_points) == 0:
            raise ValueError("CDRB needs buffer points")
        self.T = p.diffusion_steps
        self.points = np.asarray(buffer_points, dtype=np.float32)
        self.eps = radii(p.schedule, p.d_max, self.T)
        self.ball = self._sampler(self.points, self.buffer_graph)
        if p.ball == "geodesic" and p.geodesic_radii == "matched":  # needs the graph's tables the sampler built
            self.eps = self.ball.eps = self.ball.matched_radii(radii(p.schedule, 1.0, self.T), p.d_max)
        self._whole_ball = self.ball  # the unmasked sampler, which a mask takes its subset of
        self._torch_ball = None  # built on first use on a non-CPU device
        self._collides = None  # with a masked buffer: which normalized features collide (re-drawn after restoring)
        self.redrawn = 0  # restored states re-drawn from the masked buffer (counted over every sample call)
        self.unreachable = 0  # of those, states with no kept buffer state within the largest ball (left as restored)
        # the first and last planned states are left out of the degradation when pinning fixes every feature there;
        # when it fixes only some (spec.pinned_dims / pinned_end_dims, or the action part of state-action features)
        # they are degraded like the rest and pinning restores the pinned dims, so training sees the ends as sampling
        # does (whose ends start as random buffer features with only the pinned dims set)
        whole = self.feature_dim == self.obs_dim or p.end_actions == "kept"
        every = isinstance(self.pinned, slice) and isinstance(self.pinned_end, slice)
        self.kept = (0, -1) if every and whole else ()

    def _sampler(self, points, graph):
        """The degradation's sampler over ``points``: Euclidean balls, or geodesic ones along ``graph``."""
        p = self.config.method
        if p.ball == "euclidean":
            return BallSampler(points, self.eps, candidates=p.ball_candidates)
        if graph is None:
            raise ValueError("geodesic balls need the buffer's transition graph")
        from cdrb_cli.geodesic import GeodesicBalls

        return GeodesicBalls(points, *graph, eps=self.eps)

    def variant(self) -> str | None:
        m = self.config.method
        parts = [f"geodesic balls{', scaled radii' * (m.geodesic_radii == 'scaled')}"] if m.ball == "geodesic" else []
        parts += ["d_max of the data box"] if m.d_max_from == "data-box" else []
        preset = METHODS.get("cdrb").presets.get(self.config.preset, {})
        default = preset.get("loss_weight_power", CDRBParams.model_fields["loss_weight_power"].default)
        if m.loss_weight_power != default:  # the preset's own weight goes without saying in its label
            parts.append(_loss_weight_label(m.loss_weight_power))
        return ", ".join(parts) or None

    def extra_arrays(self):
        out = {"buffer/points": self.points}
        if self.buffer_graph is not None:  # the balls' graph, or the routes' (stages/routes.py TransitionRoutes)
            edges, weights = self.buffer_graph
            out |= {"buffer/graph/edges": np.asarray(edges, np.int64), "buffer/graph/weights": np.asarray(weights)}
        return out

    def _device_ball(self, device) -> TorchBallSampler | None:
        """The ball sampler that stays on ``device`` (same law), or None on the CPU, where the numpy sampler with
        its KD-tree is the faster one, and for geodesic balls (numpy tables on the CPU on every device)."""
        if torch.device(device).type == "cpu" or self.config.method.ball != "euclidean":
            return None
        if self._torch_ball is None or self._torch_ball.device != torch.device(device):
            self._torch_ball = TorchBallSampler(self.ball.points.astype(np.float32), self.eps, device=device)
        return self._torch_ball

    def _degrade(self, x: torch.Tensor, k, rng: np.random.Generator) -> torch.Tensor:
        ball = self._device_ball(x.device)
        if ball is not None:
            return ball.degrade(x.detach(), k, ball.generator(rng), pinned=self.kept)
        y = self.ball.degrade(x.detach().cpu().numpy(), k, rng, pinned=self.kept)
        return torch.from_numpy(y.astype(np.float32)).to(x.device)

    def loss(self, batch: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        B = batch.shape[0]
        start, goal = self.ends(batch, self.obs_dim)
        k = rng.integers(1, self.T, size=B)
        noisy = self.pin(self._degrade(batch, k, rng), start, goal)
        pred = self.pin(self.net(noisy, torch.as_tensor(k, device=batch.device)).float(), start, goal)
        sq = start_weighted((pred - batch) ** 2, self.config.method)
        per_sample = torch.mean(sq, dim=(1, 2))
        p = self.config.method.loss_weight_power
        if p > 0:
            w = torch.as_tensor((self.eps[1] / self.eps[k]) ** p, dtype=per_sample.dtype, device=per_sample.device)
            return torch.sum(w * per_sample) / torch.sum(w)
        return per_sample.mean()

    @staticmethod
    def _schedule(top: int, steps: int | None) -> np.ndarray:
        """The k of every restoration, from ``top`` down to 1 (``steps`` of them, evenly spaced, when fewer)."""
        ks = np.arange(top, 0, -1)
        if steps is not None and steps < len(ks):
            ks = np.unique(np.round(np.linspace(top, 1, steps)).astype(np.int64))[::-1]
        return ks

    def _restore(self, x, start, goal, ks, rng, sampler, keep_iterates) -> SampleResult:
        """Restore the pinned, degraded plans ``x`` through the steps ``ks`` (descending, ending at 1)."""
        P = start.shape[0]
        prev = np.append(ks[1:], 0)
        kept, keep = [], keep_schedule(len(ks), keep_iterates)
        x0 = x
        for i, (k, k_next) in enumerate(zip(ks, prev)):
            if i in keep:
                kept.append((int(k), x.clone()))
            kk = torch.full((P,), int(k), device=start.device, dtype=torch.long)
            x0 = self.pin(self.sample_net(x, kk), start, goal)
            if sampler == "paper":
                x = self._degrade(x0, int(k_next), rng)
            else:
                x = x - self._degrade(x0, int(k), rng) + self._degrade(x0, int(k_next), rng)
            x = self.pin(x, start, goal)
        if self._collides is not None:
            x0 = self._redraw(x0, rng)
        return SampleResult(plans=x0, iterates=kept)

    masks = True

    def mask(self, collides) -> dict[str, int]:
        """Remove the buffer states ``collides`` marks from what the ball sampler draws (the start of sampling and
        every degradation), and re-draw each restored state that collides from the kept buffer states in the
        smallest ball eps_k (k >= 1) that holds one (:meth:`_redraw`)."""
        keep = ~np.asarray(collides(self.points), dtype=bool)
        if not keep.any():
            raise ValueError("every buffer state collides in this scene")
        if self.config.method.ball == "geodesic":  # a removed state takes its edges with it
            self.ball = self._whole_ball.subset(keep)
        else:
            self.ball = self._sampler(self.points[keep], None)
        self._torch_ball = None
        self._collides = collides
        from scipy.spatial import cKDTree

        self._kept_tree = cKDTree(self.ball.points)
        return {"buffer_states": int(len(keep)), "removed": int((~keep).sum())}

    def _redraw(self, x0: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        """``x0`` with every planned state between the pinned ends that collides replaced by a uniform draw from the
        kept buffer states inside the smallest ball eps_k (k = 1..T-1) around it that holds one: the degradation at
        the least step that leaves the obstacle. A state with none within eps_{T-1} stays (counted)."""
        z = x0.detach().cpu().numpy().astype(np.float64)
        P, H, F = z.shape
        inner = z[:, 1:-1].reshape(-1, F)
        bad = np.flatnonzero(np.asarray(self._collides(inner), dtype=bool))
        if not bad.size:
            return x0
        nearest, _ = self._kept_tree.query(inner[bad])
        k = np.searchsorted(self.eps, nearest, side="right")  # the least k with eps_k > distance (strictly inside)
        ok = k < self.T
        self.redrawn += int(bad.size)
        self.unreachable += int((~ok).sum())
        rows = bad[ok]
        if rows.size:
            idx = self.ball.sample(inner[rows], self.eps[k[ok]], rng)  # never -1: the nearest kept state is inside
            inner[rows] = self.ball.points[idx]
        z[:, 1:-1] = inner.reshape(P, H - 2, F)
        return torch.from_numpy(z.astype(np.float32)).to(x0.device)

    #: whether sampling on a GPU may replay a CUDA graph of the whole loop (off: kernel by kernel; benchmarks
    #: compare both)
    cuda_graphs: bool = True
    #: the most (query, buffer point) pairs one degradation of a graphed loop may hold: its degradation looks at
    #: every pair (float64), so very large batches go the usual way
    GRAPH_PAIRS = 2**27

    def _graphable(self, start, sampler: str, keep_iterates: int) -> bool:
        free = self.horizon - len(self.kept)
        return (
            self.cuda_graphs
            and start.device.type == "cuda"
            and sampler == "paper"
            and not keep_iterates
            and self._collides is None
            and self.config.method.ball == "euclidean"
            and start.shape[0] * free * len(self.ball.points) <= self.GRAPH_PAIRS
        )

    def _free(self) -> slice:
        return slice(1, self.horizon - 1) if self.kept else slice(0, self.horizon)

    def graph_loop(self, x, start, goal, u, ks) -> torch.Tensor:
        """The paper sampler from the pinned random plans ``x`` through the steps ``ks`` with its randomness given
        (``u`` (len(ks), P, free states): the uniforms of every degradation, :meth:`TorchBallSampler.degrade_given`):
        the same law as :meth:`_restore`, as pure tensor work with static shapes, which a CUDA graph can hold.
        Returns the last restoration."""
        ball = self._device_ball(start.device)
        if ball is None:  # on the CPU (tests): the same tensor work, without a graph
            ball = self.__dict__.get("_cpu_dense_ball") or TorchBallSampler(self.ball.points, self.eps, device="cpu")
            self._cpu_dense_ball = ball
        P, free = start.shape[0], self._free()
        x0 = x
        for i, (k, k_next) in enumerate(zip(ks, np.append(ks[1:], 0))):
            kk = torch.full((P,), int(k), device=start.device, dtype=torch.long)
            x0 = self.pin(self.sample_net(x, kk), start, goal)
            x = self.pin(ball.degrade_given(x0, self.eps[k_next], u[i], free), start, goal) if k_next else x0
        return x0

    def _graphed(self, start, goal, rng, steps) -> SampleResult:
        """Plans from one replay of a CUDA graph of :meth:`graph_loop` (captured once per batch size and schedule,
        then reused): one launch instead of hundreds of kernels each step. The randomness is drawn first from
        ``rng``, so plans are deterministic given the seed (another random stream than the kernel-by-kernel path,
        the same law)."""
        P, dev = start.shape[0], start.device
        ks = self._schedule(self.T - 1, steps)
        ball = self._device_ball(dev)
        gen = ball.generator(rng)
        x = self.pin(ball.random_states((P, self.horizon), gen).to(start.dtype), start, goal)
        n_free = len(range(*self._free().indices(self.horizon)))
        u = torch.rand((len(ks), P, n_free), generator=gen, device=dev, dtype=torch.float64)
        graphs = self.__dict__.setdefault("_graphs", {})
        key = (P, tuple(int(k) for k in ks), str(dev), start.dtype)
        if key not in graphs:
            inputs = [x.clone(), start.clone(), goal.clone(), u.clone()]
            side = torch.cuda.Stream(dev)
            side.wait_stream(torch.cuda.current_stream(dev))
            with torch.cuda.stream(side):  # warm-up (the trace, cuDNN's choices) off the capture
                for _ in range(2):
                    self.graph_loop(*inputs, ks)
            torch.cuda.current_stream(dev).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                out = self.graph_loop(*inputs, ks)
            graphs[key] = (graph, inputs, out)
        graph, inputs, out = graphs[key]
        for slot, value in zip(inputs, (x, start, goal, u)):
            slot.copy_(value)
        graph.replay()
        return SampleResult(plans=out.clone())

    def _sample(self, start, goal, rng, sampler, steps, keep_iterates) -> SampleResult:
        if self._graphable(start, sampler, keep_iterates):
            return self._graphed(start, goal, rng, steps)
        P = start.shape[0]
        ball = self._device_ball(start.device)
        if ball is not None:
            x = ball.random_states((P, self.horizon), ball.generator(rng)).to(start.dtype)
        else:
            x = torch.from_numpy(self.ball.random_states((P, self.horizon), rng).astype(np.float32)).to(start.device)
        x = self.pin(x, start, goal)
        return self._restore(x, start, goal, self._schedule(self.T - 1, steps), rng, sampler, keep_iterates)

    repairs = True

    def repair_steps(self) -> int:
        return self.T - 1

    def repair(self, start, goal, previous, k, rng, sampler=None, steps=None) -> SampleResult:
        """Plan repair: the previous plan, degraded to step ``k`` by the ball sampler (ends pinned), restored from
        k down to 1 (a partly wrong plan is itself a degraded trajectory)."""
        if not 1 <= k <= self.T - 1:
            raise ValueError(f"repair step k = {k} outside 1..{self.T - 1}")
        with self.sampling_call(), torch.no_grad():
            x = self.pin(self._degrade(self.pin(previous, start, goal), int(k), rng), start, goal)
            ks = self._schedule(int(k), steps)
            return self._restore(x, start, goal, ks, rng, sampler or self.config.method.sampler, 0)


def _data_defaults(spec, buffer, settings) -> dict:
    """d_max, the radius at the last diffusion step: the buffer's diameter, so that ball holds the whole buffer and
    the last degradation is the sampling prior (uniform buffer states); measured along the transition graph for
    geodesic balls (their Euclidean diameter would leave the far states out of every ball); with ``method.d_max_from
    = "data-box"`` the diagonal of the data's bounding box, as the official Fetch code sets it."""
    if buffer is None:
        return {}
    from cdrb_cli.settings import lookup

    ball, source = lookup(settings, ("method", "ball")), lookup(settings, ("method", "d_max_from"))
    if source is not None and source.value == "data-box" and buffer.box_diagonal:
        return {"d_max": buffer.box_diagonal}
    if ball is not None and ball.value == "geodesic" and buffer.graph_diameter:
        return {"d_max": buffer.graph_diameter}
    return {"d_max": buffer.diameter}


METHODS.register(
    MethodEntry(
        params=CDRBParams,
        method=CDRB,
        needs_buffer=True,
        presets={
            "quick": {"diffusion_steps": 32, "loss_weight_power": 1.0},
            "paper": {"diffusion_steps": 128, "loss_weight_power": 0.0},
        },
        data_defaults=_data_defaults,
        description="cold diffusion through the replay buffer (the paper's method)",
    )
)
