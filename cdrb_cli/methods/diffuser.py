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

import numpy as np
import torch

from cdrb_cli.methods.base import Method, SampleResult, keep_schedule
from cdrb_cli.seeding import torch_generator

_BETAS = {"cosine": "squaredcos_cap_v2", "linear": "linear"}


def _schedulers():
    from diffusers.schedulers.scheduling_ddim import DDIMScheduler
    from diffusers.schedulers.scheduling_ddpm import DDPMScheduler

    return DDPMScheduler, DDIMScheduler


class Diffuser(Method):
    name = "diffuser"
    samplers = ("ddpm", "ddim")

    def __init__(self, config, spec, normalizer, device="cpu"):
        super().__init__(config, spec, normalizer, device)
        p = config.method
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

    @torch.no_grad()
    def sample(self, net, start, goal, rng, sampler=None, steps=None, keep_iterates=0) -> SampleResult:
        sampler = sampler or self.config.method.sampler
        if sampler not in self.samplers:
            raise ValueError(f"Diffuser sampler must be one of {self.samplers}")
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
            out = net(x, tt)
            if self.config.method.predict == "x0":
                out = self.pin(out, start, goal)
            kwargs = {"eta": 0.0} if sampler == "ddim" else {}
            x = sched.step(out, int(t), x, generator=gen, **kwargs).prev_sample
            x = self.pin(x, start, goal)
        return SampleResult(plans=x, iterates=kept)
