"""Diffusion-QL (Wang, Hunt, Zhou, ICLR 2023), goal-conditioned: a small diffusion actor trained with behaviour
cloning plus a Q term, and twin critics on a sparse goal-reaching reward.

Read top to bottom:

* data: transitions (state s, action a, next state s') with a goal from the same episode: its final state, or with
  probability ``relabel`` a later state (hindsight relabelling, ``data.TransitionSampler``); the condition of actor
  and critics is the normalized state and the goal's dims of the normalized goal state;
* reward: 1 when s' passes the environment's own success test for the goal (``EnvFamily.success``: within the
  success radius in the goal dims), else 0; a success ends the episode (no bootstrap); with ``reward_tune =
  cql-antmaze`` the reward becomes (r - 0.5) * 4, the reference's setting for sparse goal-reaching data;
* actor: epsilon-prediction DDPM over actions with T = 5 steps and the reference's variance-preserving betas
  (b_min 0.1, b_max 10), an MLP (3 x 256, Mish) fed (noisy action, step embedding, condition); sampling clips the
  predicted action to [-1, 1]; diffusers' DDPMScheduler with these betas does the steps;
* critic loss: twin Q heads (3 x 256, Mish) regress on r + gamma * (1 - done) * min(Q1', Q2')(s', a'), a' drawn
  from the EMA actor; with ``max_q_backup`` 10 actions are drawn per s', the max taken per head, then the min;
  with ``target_clip`` the target is clipped to the returns the reward allows (``return_bounds``), as HER clips
  its targets: a critic that bootstraps from its own overestimates cannot then climb past the best return;
* actor loss: BC (the DDPM loss) + eta * q, q = -Q_i(s, a_new).mean() / |Q_j(s, a_new)|.mean() (detached; the head
  i picked at random, j the other), a_new sampled with gradients through the T-step chain;
* targets: critic targets by Polyak averaging (tau = 0.005) every step; the EMA actor (decay 0.995) copies the actor
  until step ``ema_start`` and averages every ``ema_every`` steps (the reference's 1000 / 5);
* acting: 50 candidate actions per state from the EMA actor, one chosen with probabilities softmax(min(Q1, Q2)) of
  the target critics.

All four networks, both optimizers and the update counter are in the checkpoint (resume is exact).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.lazy import torch
from cdrb_cli.methods.base import NonFiniteLoss, Policy
from cdrb_cli.methods.registry import METHODS, MethodEntry, MethodParams
from cdrb_cli.seeding import torch_generator
from cdrb_cli.torch_utils import adam


class DiffusionQLParams(MethodParams):
    name: Literal["diffusion-ql"] = "diffusion-ql"
    sampler: Literal["q-softmax", "ddpm"] = Field(
        "q-softmax", description="q-softmax (50 candidates, one drawn by softmax of Q) or one plain ddpm sample"
    )
    diffusion_steps: int = Field(
        5, gt=1, le=1000, description="T of the actor's diffusion (small: it is backpropagated)"
    )
    eta: float = Field(1.0, ge=0, le=1000, description="weight of the Q term in the actor loss")
    gamma: float = Field(0.99, gt=0, lt=1, description="discount")
    tau: float = Field(0.005, gt=0, le=1, description="Polyak rate of the critic targets")
    ema_decay: float = Field(0.995, ge=0, lt=1, description="decay of the EMA actor (target actions, acting)")
    ema_start: int = Field(1000, ge=0, description="the EMA actor copies the actor until this many updates")
    ema_every: int = Field(5, gt=0, description="update the EMA actor every this many updates")
    max_q_backup: bool = Field(True, description="target: max over 10 sampled next actions per head, then min")
    reward: Literal["success"] = Field(
        "success", description="r = 1 when the next state passes the env's success test for the goal; terminal then"
    )
    target_clip: bool = Field(
        False,
        description="clip the critic's target to the returns the sparse reward allows (HER's clip; off in the "
        "reference)",
    )
    reward_tune: Literal["none", "cql-antmaze"] = Field("cql-antmaze", description="cql-antmaze: r -> (r - 0.5) * 4")
    relabel: float = Field(0.5, ge=0, le=1, description="share of training goals relabelled to a later state")
    candidates: int = Field(50, gt=0, le=10_000, description="actions drawn per state when acting (q-softmax)")


def reward_values(reward_tune: str) -> tuple[float, float]:
    """(success reward, failure reward): 1 and 0, or (r - 0.5) * 4 of them with ``cql-antmaze``."""
    return (2.0, -2.0) if reward_tune == "cql-antmaze" else (1.0, 0.0)


def return_bounds(reward_tune: str, gamma: float) -> tuple[float, float]:
    """The lowest and highest discounted return of the sparse reward: an episode pays the failure reward r_f on n
    steps and then, maybe, the terminal success reward r_s, so its return (1 - gamma^n) r_f / (1 - gamma) +
    gamma^n r_s is a convex mix of r_f / (1 - gamma) (never succeeding) and r_s (succeeding at once)."""
    r_s, r_f = reward_values(reward_tune)
    never = r_f / (1 - gamma)
    return min(never, r_s), max(never, r_s)


def _vp_betas(T: int, b_min: float = 0.1, b_max: float = 10.0) -> np.ndarray:
    """The reference's discretized variance-preserving schedule."""
    t = np.arange(1, T + 1)
    alpha = np.exp(-b_min / T - 0.5 * (b_max - b_min) * (2 * t - 1) / T**2)
    return 1 - alpha


class DiffusionQL(Policy):
    def build(self, buffer_points) -> None:
        from diffusers.schedulers.scheduling_ddpm import DDPMScheduler

        from cdrb_cli.nets.qlearning import NoiseMLP, Targets, TwinCritic

        p = self.config.method
        self.T = p.diffusion_steps
        self.act_dim = self.spec.action_dim
        self.goal_dims = list(self.spec.goal_dims)
        cond_dim = self.obs_dim + len(self.goal_dims)
        hidden = list(self.config.net.hidden)  # actor and critic heads alike (the reference: 3 x 256)
        self.actor = NoiseMLP(self.act_dim, cond_dim, hidden).to(self.device)
        self.critic = TwinCritic(self.act_dim, cond_dim, hidden).to(self.device)
        self.targets = Targets(self.actor, self.critic).to(self.device)
        self.sched = DDPMScheduler(
            num_train_timesteps=self.T,
            trained_betas=_vp_betas(self.T).tolist(),
            prediction_type="epsilon",
            clip_sample=True,
            clip_sample_range=1.0,
            variance_type="fixed_small",
        )
        self.sched.set_timesteps(self.T)
        from cdrb_cli.envs.registry import family_of

        self.family = family_of(self.spec)

    def data(self, demos, normalizer, split: str):
        from cdrb_cli.data import TransitionSampler

        # rows: (s, a), (s', a'), goal state
        return TransitionSampler(demos, self.config.features, normalizer, 2, split, self.config.method.relabel)

    def modules(self):
        return {"actor": self.actor, "critic": self.critic, "targets": self.targets}

    def ema_modules(self):
        return ()  # the EMA actor is the method's own (in ``targets``): its targets need it during training

    def make_optimizers(self):
        lr = self.config.lr
        return {
            "actor": adam(self.actor.parameters(), lr=lr),
            "critic": adam(self.critic.parameters(), lr=lr),
        }

    # -------------------------------------------------------------- pieces
    def _parts(self, batch):
        """Normalized condition, action, next condition, and the raw next states and goals (for the reward)."""
        goal = batch[:, -1, self.goal_dims]
        cond = torch.cat([batch[:, 0, : self.obs_dim], goal], dim=-1)
        nxt = torch.cat([batch[:, 1, : self.obs_dim], goal], dim=-1)
        return cond, batch[:, 0, self.obs_dim :], nxt

    def reward(self, batch) -> tuple[torch.Tensor, torch.Tensor]:
        """(r, done) per transition: the environment's success test on the raw next state and goal."""
        raw = self.normalizer.unnormalize(batch.detach().cpu().numpy().astype(np.float64))
        done = self.family.success(self.spec, raw[:, 1, : self.obs_dim], raw[:, -1, self.goal_dims])
        r = np.where(done, *reward_values(self.config.method.reward_tune))
        as_t = lambda v: torch.as_tensor(v, dtype=batch.dtype, device=batch.device)[:, None]  # noqa: E731
        return as_t(r), as_t(done.astype(np.float64))

    def _sample(self, actor, cond, gen) -> torch.Tensor:
        """Actions (n, act_dim) in normalized space by the T-step DDPM chain (differentiable through ``actor``)."""
        a = torch.randn((cond.shape[0], self.act_dim), generator=gen).to(cond.device)
        for t in self.sched.timesteps:
            tt = torch.full((cond.shape[0],), int(t), device=cond.device, dtype=torch.long)
            a = self.sched.step(actor(a, tt, cond), int(t), a, generator=gen).prev_sample
        return a.clamp(-1.0, 1.0)

    def bc_loss(self, cond, a, rng) -> torch.Tensor:
        t = torch.as_tensor(rng.integers(0, self.T, size=a.shape[0]), device=a.device)
        noise = torch.randn(a.shape, generator=torch_generator(rng), dtype=a.dtype).to(a.device)
        return torch.mean((self.actor(self.sched.add_noise(a, noise, t), t, cond) - noise) ** 2)

    def critic_target(self, nxt, r, done, gen) -> torch.Tensor:
        """r + gamma (1 - done) min(Q1', Q2')(s', a'), a' from the EMA actor (max over 10 draws per head first),
        clipped to the reward's return bounds with ``target_clip``: the whole target, as HER clips it, so a bound
        that holds for every state's value (clipping the bootstrap value alone would bound a failing step's target
        tighter, by r_f + gamma r_s; that is another method)."""
        p = self.config.method
        with torch.no_grad():
            n = 10 if p.max_q_backup else 1
            rep = nxt.repeat_interleave(n, dim=0)
            q1, q2 = self.targets.critic(rep, self._sample(self.targets.actor, rep, gen))
            q1, q2 = q1.view(-1, n).max(dim=1, keepdim=True)[0], q2.view(-1, n).max(dim=1, keepdim=True)[0]
            target = r + p.gamma * (1 - done) * torch.min(q1, q2)
            return target.clamp(*return_bounds(p.reward_tune, p.gamma)) if p.target_clip else target

    # -------------------------------------------------------------- training
    def loss(self, batch, rng):
        """The validation loss: the BC (DDPM) loss of the actor."""
        cond, a, _ = self._parts(batch)
        return self.bc_loss(cond, a, rng)

    def update(self, batch, rng, optimizers) -> float:
        """Critic step, then actor step against the updated critic (the reference's order), then the targets.
        A non-finite loss raises before its own step (the checkpoint on disk is what a failed run keeps)."""
        p = self.config.method
        cond, a, nxt = self._parts(batch)
        r, done = self.reward(batch)
        gen = torch_generator(rng)
        with self.autocast(batch.device):
            q1, q2 = self.critic(cond, a)
            target = self.critic_target(nxt, r, done, gen).float()
            critic_loss = torch.mean((q1.float() - target) ** 2) + torch.mean((q2.float() - target) ** 2)
        self._step(optimizers["critic"], self.critic, critic_loss)
        with self.autocast(batch.device):
            bc = self.bc_loss(cond, a, rng).float()
            n1, n2 = self.critic(cond, self._sample(self.actor, cond, gen))  # gradients through the sampling chain
            n1, n2 = n1.float(), n2.float()
        if rng.random() < 0.5:
            n1, n2 = n2, n1
        self._step(optimizers["actor"], self.actor, bc + p.eta * (-n1.mean() / n2.abs().mean().detach()))
        self._update_targets()
        return float(bc.detach())

    def _step(self, opt, module, loss) -> None:
        if not torch.isfinite(loss):
            raise NonFiniteLoss(float(loss.detach()))
        opt.zero_grad(set_to_none=True)
        loss.backward(inputs=list(module.parameters()))
        if self.config.grad_clip:
            torch.nn.utils.clip_grad_norm_(module.parameters(), self.config.grad_clip)
        opt.step()

    def _update_targets(self) -> None:
        p = self.config.method
        tg = self.targets
        tg.updates += 1
        step = int(tg.updates)
        with torch.no_grad():
            for t, s in zip(tg.critic.parameters(), self.critic.parameters()):
                t.mul_(1 - p.tau).add_(s, alpha=p.tau)
            if step <= p.ema_start:
                for t, s in zip(tg.actor.parameters(), self.actor.parameters()):
                    t.copy_(s)
            elif step % p.ema_every == 0:
                for t, s in zip(tg.actor.parameters(), self.actor.parameters()):
                    t.mul_(p.ema_decay).add_(s, alpha=1 - p.ema_decay)

    # -------------------------------------------------------------- acting
    def act(self, states: np.ndarray, goals: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        from cdrb_cli.buffer import Normalizer

        lo, hi = self.normalizer.low, self.normalizer.high
        obs = Normalizer(lo[: self.obs_dim], hi[: self.obs_dim]).normalize(np.asarray(states, dtype=np.float64))
        goal = Normalizer(lo[self.goal_dims], hi[self.goal_dims]).normalize(np.asarray(goals, dtype=np.float64))
        cond = torch.as_tensor(np.concatenate([obs, goal], axis=1), dtype=torch.float32, device=self.device)
        gen = torch_generator(rng)
        n = cond.shape[0]
        with torch.no_grad():
            if self.config.method.sampler == "ddpm":
                a = self._sample(self.targets.actor, cond, gen)
            else:
                k = self.config.method.candidates
                rep = cond.repeat_interleave(k, dim=0)
                cand = self._sample(self.targets.actor, rep, gen)
                q = torch.min(*self.targets.critic(rep, cand)).view(n, k)
                # drawn on the CPU, where the seeded generator lives: the same pick on every device
                probs = torch.softmax(q, dim=1).cpu()
                pick = torch.multinomial(probs, 1, generator=gen).squeeze(1).to(cand.device)
                a = cand.view(n, k, -1)[torch.arange(n, device=cand.device), pick]
        return Normalizer(lo[self.obs_dim :], hi[self.obs_dim :]).unnormalize(a.cpu().numpy().astype(np.float64))


_NET = {"kind": "mlp", "hidden": [256, 256, 256]}
_TRAIN = {
    "quick": dict(features="state-action", horizon=1, stride=1, batch_size=256, steps=10000, lr=3e-4, net=_NET),
    "paper": dict(features="state-action", horizon=1, stride=1, batch_size=256, steps=100000, lr=3e-4, net=_NET),
}

METHODS.register(
    MethodEntry(
        params=DiffusionQLParams,
        method=DiffusionQL,
        nets=("mlp",),
        train_defaults=_TRAIN,
        description="Goal-conditioned diffusion actor + twin critics, acting closed loop (Diffusion-QL, Wang et al.)",
    )
)
