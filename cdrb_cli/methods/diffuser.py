"""Diffuser (Janner et al. 2022, maze2d branch): Gaussian DDPM over the same trajectories, as a faithful baseline.

* cosine beta schedule (s = 0.008, betas capped at 0.999: diffusers' ``squaredcos_cap_v2``), T steps;
* the network predicts x0 (``prediction_type="sample"``), clipped to [-1, 1] when sampling;
* in-painting: the start and goal states are written into the noisy input and into the prediction, in training
  and at every sampling step;
* sampling with the true DDPM posterior q(x_{t-1} | x_t, x0_hat) and its ``fixed_small`` variance (not the
  re-noise-from-x0 shortcut the official CDRB repository used for its Diffuser baseline), or DDIM (eta = 0) with
  fewer steps for lower latency;
* the same temporal U-Net as CDRB, so a comparison isolates the diffusion process;
* plan repair (``repair``, for closed-loop evaluation): a previous plan noised to timestep k and denoised from
  there, the Gaussian counterpart of CDRB's repair;
* guided sampling (``set_guide``): after every denoising step the plan moves down the gradient of a cost (a
  collision cost for obstacles the data never saw), as Diffuser guides with a value function.

The schedulers are the `diffusers` library's DDPMScheduler / DDIMScheduler.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import Planner, SampleResult, keep_schedule
from cdrb_cli.methods.registry import METHODS, MethodEntry, StartWeightParams, start_weighted
from cdrb_cli.seeding import torch_generator

_BETAS = {"cosine": "squaredcos_cap_v2", "linear": "linear"}


def _schedulers():
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler
    from diffusers.schedulers.scheduling_ddpm import DDPMScheduler

    return DDPMScheduler, DDIMScheduler


class DiffuserParams(StartWeightParams):
    name: Literal["diffuser"] = "diffuser"
    diffusion_steps: int = Field(gt=1, le=100_000, description="T, the number of diffusion steps")
    beta_schedule: Literal["cosine", "linear"] = Field("cosine", description="the DDPM noise schedule")
    predict: Literal["x0", "epsilon"] = Field("x0", description="what the network predicts")
    clip_denoised: bool = Field(True, description="clip the predicted x0 to [-1, 1] when sampling")
    sampler: Literal["ddpm", "ddim"] = Field("ddpm", description="ddpm (the true posterior) or ddim (eta = 0)")
    ddim_steps: int = Field(16, gt=0, description="steps of the ddim sampler when --sample-steps is not given")


class Diffuser(Planner):
    def build(self, buffer_points) -> None:
        super().build(buffer_points)
        p = self.config.method
        self.T = p.diffusion_steps
        self.train_sched = self._ddpm()

    def _common(self) -> dict:
        """The scheduler settings every sampler of this model shares (its T, betas, prediction and clipping)."""
        p = self.config.method
        return dict(
            num_train_timesteps=self.T,
            beta_schedule=_BETAS[p.beta_schedule],
            prediction_type="sample" if p.predict == "x0" else "epsilon",
            clip_sample=p.clip_denoised,
            clip_sample_range=1.0,
        )

    def _ddpm(self):
        """A DDPM scheduler with the true posterior's ``fixed_small`` variance."""
        ddpm_cls, _ = _schedulers()
        return ddpm_cls(variance_type="fixed_small", **self._common())

    def loss(self, batch: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        B = batch.shape[0]
        start, goal = self.ends(batch, self.obs_dim)
        t = torch.as_tensor(rng.integers(0, self.T, size=B), device=batch.device)
        gen = torch_generator(rng)
        noise = torch.randn(batch.shape, generator=gen, dtype=batch.dtype).to(batch.device)
        noisy = self.pin(self.train_sched.add_noise(batch, noise, t), start, goal)
        pred = self.net(noisy, t).float()
        if self.config.method.predict == "x0":
            return torch.mean(start_weighted((self.pin(pred, start, goal) - batch) ** 2, self.config.method))
        return torch.mean(start_weighted((pred - noise) ** 2, self.config.method))

    def _sampler(self, name: str, steps: int | None):
        p = self.config.method
        if name == "ddpm":
            sched = self._ddpm()
            sched.set_timesteps(self.T if steps is None else min(steps, self.T))
        else:
            _, ddim_cls = _schedulers()
            sched = ddim_cls(set_alpha_to_one=True, **self._common())
            sched.set_timesteps(min(steps or p.ddim_steps, self.T))
        return sched

    def _denoise(self, x, start, goal, sched, gen, sampler, keep_iterates) -> SampleResult:
        """Run ``sched``'s timesteps on the pinned noisy plans ``x`` (the posterior step, in-painting each time)."""
        P = start.shape[0]
        keep = keep_schedule(len(sched.timesteps), keep_iterates)
        kept = []
        for i, t in enumerate(sched.timesteps):
            if i in keep:
                kept.append((int(t), x.clone()))
            tt = torch.full((P,), int(t), device=start.device, dtype=torch.long)
            out = self.sample_net(x, tt)
            if self.config.method.predict == "x0":
                out = self.pin(out, start, goal)
            kwargs = {"eta": 0.0} if sampler == "ddim" else {}
            x = sched.step(out, int(t), x, generator=gen, **kwargs).prev_sample
            if self.guide is not None:
                x = self._guided(x)
            x = self.pin(x, start, goal)
        return SampleResult(plans=x, iterates=kept)

    guides = True

    def _guided(self, x: torch.Tensor) -> torch.Tensor:
        """One gradient step of the guide's cost (Diffuser's guided sampling, with a collision cost): x - scale
        grad cost(x)."""
        cost, scale = self.guide
        with torch.enable_grad():
            y = x.detach().requires_grad_(True)
            (grad,) = torch.autograd.grad(cost(y).sum(), y)
        return x - scale * grad

    def _sample(self, start, goal, rng, sampler, steps, keep_iterates) -> SampleResult:
        sched = self._sampler(sampler, steps)
        gen = torch_generator(rng)
        P = start.shape[0]
        x = torch.randn((P, self.horizon, self.feature_dim), generator=gen).to(start.device)
        x = self.pin(x, start, goal)
        return self._denoise(x, start, goal, sched, gen, sampler, keep_iterates)

    repairs = True

    def repair_steps(self) -> int:
        return self.T - 1

    def repair(self, start, goal, previous, k, rng, sampler=None, steps=None) -> SampleResult:
        """Plan repair: the previous plan noised to timestep ``k`` with q(x_k | x_0) (ends pinned), then denoised
        from k with the DDPM posterior on ``steps`` evenly spaced timesteps k .. 0 (default: all k + 1). Repair
        always takes posterior steps, whatever the sampler: they are exact for any spacing of the timesteps."""
        if not 1 <= k <= self.T - 1:
            raise ValueError(f"repair step k = {k} outside 1..{self.T - 1}")
        n = k + 1 if steps is None else max(1, min(int(steps), k + 1))
        timesteps = np.unique(np.round(np.linspace(k, 0, n)).astype(np.int64))[::-1]
        sched = self._ddpm()
        sched.set_timesteps(timesteps=[int(t) for t in timesteps])
        gen = torch_generator(rng)
        with self.sampling_call(), torch.no_grad():
            x0 = self.pin(previous, start, goal)
            noise = torch.randn(x0.shape, generator=gen).to(x0.device)
            t0 = torch.full((x0.shape[0],), int(timesteps[0]), dtype=torch.long)
            x = self.pin(self.train_sched.add_noise(x0, noise, t0.to(x0.device)), start, goal)
            return self._denoise(x, start, goal, sched, gen, "ddpm", 0)


METHODS.register(
    MethodEntry(
        params=DiffuserParams,
        method=Diffuser,
        presets={"quick": {"diffusion_steps": 32}, "paper": {"diffusion_steps": 128}},
        description="Gaussian DDPM over trajectories with in-painting (Janner et al. 2022)",
    )
)
