"""Diffuser (Janner et al. 2022, maze2d branch): Gaussian DDPM over the same trajectories, as a faithful baseline.

* cosine beta schedule (s = 0.008, betas capped at 0.999: diffusers' ``squaredcos_cap_v2``), T steps;
* the network predicts x0 (``prediction_type="sample"``), clipped to [-1, 1] when sampling;
* in-painting: the start and goal states are written into the noisy input and into the prediction, in training
  and at every sampling step;
* sampling with the true DDPM posterior q(x_{t-1} | x_t, x0_hat) and its ``fixed_small`` variance (not the
  re-noise-from-x0 shortcut the official CDRB repository used for its Diffuser baseline), or DDIM (eta = 0) with
  fewer steps for lower latency;
* the same temporal U-Net as CDRB, so a comparison isolates the diffusion process.

The schedulers are the `diffusers` library's DDPMScheduler / DDIMScheduler.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import Planner, SampleResult, keep_schedule
from cdrb_cli.methods.registry import METHODS, MethodEntry, MethodParams
from cdrb_cli.seeding import torch_generator

_BETAS = {"cosine": "squaredcos_cap_v2", "linear": "linear"}


def _schedulers():
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler
    from diffusers.schedulers.scheduling_ddpm import DDPMScheduler

    return DDPMScheduler, DDIMScheduler


class DiffuserParams(MethodParams):
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
        ddpm_cls, _ = _schedulers()
        self.train_sched = ddpm_cls(
            num_train_timesteps=self.T,
            beta_schedule=_BETAS[p.beta_schedule],
            prediction_type="sample" if p.predict == "x0" else "epsilon",
            clip_sample=p.clip_denoised,
            clip_sample_range=1.0,
            variance_type="fixed_small",
        )

    def loss(self, batch: torch.Tensor, rng: np.random.Generator) -> torch.Tensor:
        B = batch.shape[0]
        start, goal = self.ends(batch, self.obs_dim)
        t = torch.as_tensor(rng.integers(0, self.T, size=B), device=batch.device)
        gen = torch_generator(rng)
        noise = torch.randn(batch.shape, generator=gen, dtype=batch.dtype).to(batch.device)
        noisy = self.pin(self.train_sched.add_noise(batch, noise, t), start, goal)
        pred = self.net(noisy, t)
        if self.config.method.predict == "x0":
            return torch.mean((self.pin(pred, start, goal) - batch) ** 2)
        return torch.mean((pred - noise) ** 2)

    def _sampler(self, name: str, steps: int | None):
        p = self.config.method
        ddpm_cls, ddim_cls = _schedulers()
        common = dict(
            num_train_timesteps=self.T,
            beta_schedule=_BETAS[p.beta_schedule],
            prediction_type="sample" if p.predict == "x0" else "epsilon",
            clip_sample=p.clip_denoised,
            clip_sample_range=1.0,
        )
        if name == "ddpm":
            sched = ddpm_cls(variance_type="fixed_small", **common)
            sched.set_timesteps(self.T if steps is None else min(steps, self.T))
        else:
            sched = ddim_cls(set_alpha_to_one=True, **common)
            sched.set_timesteps(min(steps or p.ddim_steps, self.T))
        return sched

    def _sample(self, start, goal, rng, sampler, steps, keep_iterates) -> SampleResult:
        sched = self._sampler(sampler, steps)
        gen = torch_generator(rng)
        P = start.shape[0]
        x = torch.randn((P, self.horizon, self.feature_dim), generator=gen).to(start.device)
        x = self.pin(x, start, goal)
        keep = keep_schedule(len(sched.timesteps), keep_iterates)
        kept = []
        for i, t in enumerate(sched.timesteps):
            if i in keep:
                kept.append((int(t), x.clone()))
            tt = torch.full((P,), int(t), device=start.device, dtype=torch.long)
            out = self.net(x, tt)
            if self.config.method.predict == "x0":
                out = self.pin(out, start, goal)
            kwargs = {"eta": 0.0} if sampler == "ddim" else {}
            x = sched.step(out, int(t), x, generator=gen, **kwargs).prev_sample
            x = self.pin(x, start, goal)
        return SampleResult(plans=x, iterates=kept)


METHODS.register(
    MethodEntry(
        params=DiffuserParams,
        method=Diffuser,
        presets={"quick": {"diffusion_steps": 32}, "paper": {"diffusion_steps": 128}},
        description="Gaussian DDPM over trajectories with in-painting (Janner et al. 2022)",
    )
)
