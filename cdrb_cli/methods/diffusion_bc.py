"""Diffusion BC (Pearce et al., ICLR 2023), goal-conditioned: a DDPM over actions given (observation, goal).

A closed-loop policy, not a planner: every environment step (or every ``act_every`` steps, executing a chunk of
``horizon`` actions in between) it samples actions from the current state and the goal. Read top to bottom:

* data: transitions of the demonstrations (``data.TransitionSampler``): the state at a step t, the ``horizon``
  actions from t, and a goal state from the same episode (its final state, or a later one with probability
  ``relabel``: uniform over the rest, or about ``relabel_horizon`` steps ahead); everything min/max-normalized to
  [-1, 1] with the demonstrations' state-action normalizer; the condition is the normalized state and the goal's
  dims of the normalized goal state;
* the denoiser: the MLP Sieve (``nets/sieve.py``), fed the noisy actions, the step as t/T and the condition;
* training: epsilon prediction with an L2 loss, t uniform over the T steps, the reference's linear betas
  1e-4 .. 0.02 (diffusers' DDPMScheduler, ``fixed_small`` variance);
* acting: ancestral DDPM sampling from N(0, I) over the T steps, then ``extra_steps`` more denoising steps at the
  last step without noise ("Diffusion-X", which the reference found to sharpen actions onto the data), actions
  clamped to [-1, 1] in normalized space and mapped back to the environment's units.

Differences from the reference code (microsoft/Imitating-Human-Behaviour-w-Diffusion), each a deliberate choice:
LayerNorm instead of BatchNorm in the Sieve (acting on one state then uses the network that was trained), the
goal concatenated to the observation (the reference is not goal-conditioned), no classifier-free guidance (its
paper found it hurts in sequential control), and an EMA of the weights like every cdrb method.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import Policy
from cdrb_cli.methods.registry import METHODS, MethodEntry, MethodParams
from cdrb_cli.seeding import torch_generator


class DiffusionBCParams(MethodParams):
    name: Literal["diffusion-bc"] = "diffusion-bc"
    sampler: Literal["ddpm-x", "ddpm"] = Field(
        "ddpm-x", description="ddpm-x (DDPM, then extra_steps noise-free steps) or plain ddpm"
    )
    diffusion_steps: int = Field(50, gt=1, le=10_000, description="T, the number of diffusion steps")
    beta_start: float = Field(1e-4, gt=0, lt=1, description="the first beta of the linear schedule")
    beta_end: float = Field(0.02, gt=0, lt=1, description="the last beta of the linear schedule")
    extra_steps: int = Field(8, ge=0, le=1000, description="Diffusion-X: noise-free steps after the T steps")
    act_every: int = Field(
        1, gt=0, le=100_000, description="environment steps between samples (at most horizon: the chunk's actions)"
    )
    relabel: float = Field(
        0.0, ge=0, le=1, description="share of training goals relabelled to a later state of the episode"
    )
    relabel_horizon: float | None = Field(
        None,
        ge=1,
        le=1e7,
        description="relabelled goals lie a Geometric(1/h) number of steps ahead (mean h, cut at the episode's end), "
        "as with a discount 1 - 1/h; null: uniform over the rest of the episode",
    )


class DiffusionBC(Policy):
    def build(self, buffer_points) -> None:
        from diffusers.schedulers.scheduling_ddpm import DDPMScheduler

        p = self.config.method
        if p.act_every > self.horizon:
            from cdrb_cli.errors import BadInput

            raise BadInput(
                f"method.act_every {p.act_every}: more than the {self.horizon} actions a sample holds",
                hint=f"use --set method.act_every={self.horizon} or a longer --set horizon",
            )
        self.T = p.diffusion_steps
        self.act_dim = self.spec.action_dim
        self.goal_dims = list(self.spec.goal_dims)
        self.sched = DDPMScheduler(
            num_train_timesteps=self.T,
            beta_schedule="linear",
            beta_start=p.beta_start,
            beta_end=p.beta_end,
            prediction_type="epsilon",
            clip_sample=False,
            variance_type="fixed_small",
        )
        from cdrb_cli.nets import build_net

        cond_dim = self.obs_dim + len(self.goal_dims)
        self.net = build_net(self.config.net, self.act_dim, self.horizon, cond_dim=cond_dim).to(self.device)
        self._queue: torch.Tensor | None = None
        self._k = 0

    def data(self, demos, normalizer, split: str):
        from cdrb_cli.data import TransitionSampler

        return TransitionSampler(
            demos,
            self.config.features,
            normalizer,
            self.horizon,
            split,
            self.config.method.relabel,
            self.config.method.relabel_horizon,
        )

    # -------------------------------------------------------------- training
    def _split(self, batch):
        """(condition (B, obs + goal), actions (B, H * act)) of a normalized transition batch."""
        obs = batch[:, 0, : self.obs_dim]
        goal = batch[:, -1, self.goal_dims]
        actions = batch[:, : self.horizon, self.obs_dim :].reshape(batch.shape[0], -1)
        return torch.cat([obs, goal], dim=-1), actions

    def _eps(self, y, t, cond):
        return self.net(y, ((t.float() + 1) / self.T)[:, None], cond)

    def loss(self, batch, rng: np.random.Generator):
        cond, y = self._split(batch)
        t = torch.as_tensor(rng.integers(0, self.T, size=y.shape[0]), device=y.device)
        noise = torch.randn(y.shape, generator=torch_generator(rng), dtype=y.dtype).to(y.device)
        return torch.mean((self._eps(self.sched.add_noise(y, noise, t), t, cond) - noise) ** 2)

    # -------------------------------------------------------------- acting
    def reset(self, n: int, rng: np.random.Generator) -> None:
        self._queue, self._k = None, 0

    def act(self, states: np.ndarray, goals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        if self._queue is None or self._k % self.config.method.act_every == 0:
            self._queue = self.sample_actions(states, goals, rng)
            self._k = 0
        a = self._queue[:, self._k]
        self._k += 1
        return a

    def sample_actions(self, states, goals, rng, sampler: str | None = None) -> np.ndarray:
        """(n, horizon, act_dim) raw actions for raw states (n, obs_dim) and goals (n, goal_dim)."""
        norm = self.normalizer
        lo, hi = norm.low, norm.high
        from cdrb_cli.buffer import Normalizer

        obs = Normalizer(lo[: self.obs_dim], hi[: self.obs_dim]).normalize(np.asarray(states, dtype=np.float64))
        goal = Normalizer(lo[self.goal_dims], hi[self.goal_dims]).normalize(np.asarray(goals, dtype=np.float64))
        cond = torch.as_tensor(np.concatenate([obs, goal], axis=1), dtype=torch.float32, device=self.device)
        sampler = sampler or self.config.method.sampler
        gen = torch_generator(rng)
        n = cond.shape[0]
        with torch.no_grad():
            y = torch.randn((n, self.horizon * self.act_dim), generator=gen).to(self.device)
            self.sched.set_timesteps(self.T)
            for t in self.sched.timesteps:
                tt = torch.full((n,), int(t), device=self.device, dtype=torch.long)
                y = self.sched.step(self._eps(y, tt, cond), int(t), y, generator=gen).prev_sample
            if sampler == "ddpm-x":  # at the last step the scheduler adds no noise: the posterior mean, repeated
                zero = torch.zeros((n,), device=self.device, dtype=torch.long)
                for _ in range(self.config.method.extra_steps):
                    y = self.sched.step(self._eps(y, zero, cond), 0, y, generator=gen).prev_sample
            y = y.clamp(-1.0, 1.0).reshape(n, self.horizon, self.act_dim).cpu().numpy()
        act_norm = Normalizer(lo[self.obs_dim :], hi[self.obs_dim :])
        return act_norm.unnormalize(y.astype(np.float64))


_TRAIN = {
    "quick": dict(features="state-action", horizon=1, stride=1, batch_size=256, steps=5000, lr=1e-3),
    "paper": dict(features="state-action", horizon=1, stride=1, batch_size=256, steps=50000, lr=1e-4),
}

METHODS.register(
    MethodEntry(
        params=DiffusionBCParams,
        method=DiffusionBC,
        nets=("sieve",),
        train_defaults=_TRAIN,
        description="Goal-conditioned DDPM over actions, acting closed loop (Diffusion BC, Pearce et al. 2023)",
    )
)
