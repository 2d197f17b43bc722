"""`cdrb train`: learn a planner from demonstration windows; checkpoint into the model artifact; resume exactly.

Randomness at step s comes only from ``seed`` and ``s`` (batch choice, diffusion steps, degradations), and the
model artifact holds weights, EMA weights and Adam moments: so killing training and running ``--resume``
finishes with the same weights as an uninterrupted run (tests/test_train.py checks it bit for bit).
"""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts, ui
from cdrb_cli.buffer import Normalizer, demo_features, feature_dim, split_rows
from cdrb_cli.configs import CDRBParams, DiffuserParams, MLPParams, TrainConfig, TrainState
from cdrb_cli.data import WindowSampler
from cdrb_cli.errors import BadInput, RunFailed
from cdrb_cli.nets import horizon_multiple
from cdrb_cli.presets import cdrb_loss_weight_power, diffusion_steps, net_config, train_defaults
from cdrb_cli.seeding import STREAM_TRAIN, STREAM_VALID, step_rng


# ------------------------------------------------------------------------------------------------ config
def resolve_config(
    demos,
    buffer,
    method: str,
    preset: str = "quick",
    net: str | None = None,
    features: str | None = None,
    horizon: int | None = None,
    stride: int | None = None,
    diffusion: int | None = None,
    schedule: str = "linear",
    d_max: float | None = None,
    seed: int = 0,
    dim: int | None = None,
    dim_mults: list[int] | None = None,
    residual: bool | None = None,
    loss_weight_power: float | None = None,
    **overrides,
) -> TrainConfig:
    """The full TrainConfig from a method, a preset and any overrides, checked against the inputs."""
    spec = demos.manifest.env
    if method == "cdrb":
        if buffer is None:
            raise BadInput("--method cdrb needs --buffer BUFFER", hint="make one with `cdrb cluster DEMOS`")
        if features is not None and features != buffer.manifest.config.features:
            raise BadInput(
                f"--features {features}: the buffer was clustered on {buffer.manifest.config.features!r} features",
                hint="omit --features or re-cluster with the same --features",
            )
        features = buffer.manifest.config.features
    features = features or (buffer.manifest.config.features if buffer is not None else "state")
    if net is None:
        net = "mlp" if method == "mlp" else "unet"
    if method == "mlp" and net != "mlp":
        raise BadInput(f"--net {net}: the MLP method uses --net mlp", hint="omit --net")
    if method != "mlp" and net == "mlp":
        raise BadInput("--net mlp is only for --method mlp", hint="use --net unet or transformer")
    net_cfg = net_config(net, preset)
    if dim is not None or dim_mults is not None:
        if net != "unet":
            raise BadInput("--dim/--dim-mults apply to --net unet", hint="omit them")
        net_cfg = net_cfg.model_copy(update={k: v for k, v in (("dim", dim), ("dim_mults", dim_mults)) if v})
        if net_cfg.dim % net_cfg.groups or any(m <= 0 for m in net_cfg.dim_mults):
            raise BadInput(
                f"--dim {net_cfg.dim}: must be a multiple of {net_cfg.groups}, mults positive",
                hint="e.g. --dim 32 --dim-mults 1,4,8",
            )
    if residual is not None:
        if net != "unet":
            raise BadInput("--residual/--no-residual apply to --net unet", hint="omit them")
        net_cfg = net_cfg.model_copy(update={"residual": residual})
    horizon = horizon or spec.horizon
    stride = stride or spec.plan_stride
    mult = horizon_multiple(net_cfg)
    if horizon % mult:
        raise BadInput(
            f"--horizon {horizon}: the U-Net with {len(net_cfg.dim_mults)} levels needs a multiple of {mult}",
            hint=f"use {horizon + (-horizon) % mult}",
        )
    T = diffusion or diffusion_steps(preset)
    if T < 2:
        raise BadInput(f"--diffusion-steps {T}: must be at least 2", hint="use e.g. 32")
    if method == "cdrb":
        diam = buffer.manifest.summary.diameter
        params = CDRBParams(
            schedule=schedule,
            d_max=d_max or diam,
            diffusion_steps=T,
            loss_weight_power=cdrb_loss_weight_power(preset) if loss_weight_power is None else loss_weight_power,
        )
    elif method == "diffuser":
        params = DiffuserParams(diffusion_steps=T)
    elif method == "mlp":
        params = MLPParams()
    else:
        raise BadInput(f"--method {method!r}: unknown method", hint="use cdrb, diffuser or mlp")
    fields = train_defaults(preset)
    for key, value in overrides.items():
        if value is not None:
            fields[key] = value
    if not 0 <= fields.get("start_fraction", 0.9) <= 1:
        raise BadInput(f"--start-fraction {fields['start_fraction']}: must be in [0, 1]", hint="e.g. 0.5")
    for key in ("steps", "batch_size", "checkpoint_every"):
        if fields[key] <= 0:
            raise BadInput(f"--{key.replace('_', '-')} {fields[key]}: must be positive", hint="pass a positive integer")
    if fields["lr"] <= 0 or not math.isfinite(fields["lr"]):
        raise BadInput(f"--lr {fields['lr']}: must be a positive number", hint="e.g. 2e-4")
    return TrainConfig(
        method=params,
        net=net_cfg,
        preset=preset,
        features=features,
        horizon=horizon,
        stride=stride,
        seed=seed,
        **fields,
    )


def check_inputs(demos, buffer, features: str) -> Normalizer:
    """The normalizer training uses; refuses a buffer made for another env or other demos."""
    spec = demos.manifest.env
    rows = split_rows(demos, "train")
    if rows.size == 0:
        raise BadInput(f"{demos.path}: no training episodes", hint="collect more episodes")
    norm = Normalizer.fit(demo_features(demos, features)[rows])
    if buffer is None:
        return norm
    if buffer.manifest.env != spec:
        raise BadInput(
            f"--buffer {buffer.path}: made for env {buffer.manifest.env.id!r}, but the demos are {spec.id!r}"
            + (" (same id, different spec)" if buffer.manifest.env.id == spec.id else ""),
            hint="cluster these demos: `cdrb cluster DEMOS`",
        )
    bnorm = Normalizer(low=buffer.low, high=buffer.high)
    if not bnorm.allclose(norm):
        raise BadInput(
            f"--buffer {buffer.path}: its normalizer does not match these demos (it was clustered from other data)",
            hint="cluster these demos: `cdrb cluster DEMOS`",
        )
    if buffer.points.shape[1] != feature_dim(spec, features):
        raise BadInput(f"--buffer {buffer.path}: feature dimension mismatch", hint="re-cluster the demos")
    return bnorm


# ------------------------------------------------------------------------------------------------ state io
def _state_arrays(method, ema, opt, normalizer, curve) -> dict[str, np.ndarray]:
    arrays: dict[str, np.ndarray] = {}
    for name, t in method.net.state_dict().items():
        arrays[f"weights/{name}"] = t.detach().cpu().numpy()
    for name, t in ema.state_dict().items():
        arrays[f"ema/{name}"] = t.detach().cpu().numpy()
    names = {id(p): n for n, p in method.net.named_parameters()}
    for group in opt.param_groups:
        for p in group["params"]:
            st = opt.state.get(p)
            if not st:
                continue
            n = names[id(p)]
            arrays[f"optim/{n}/exp_avg"] = st["exp_avg"].detach().cpu().numpy()
            arrays[f"optim/{n}/exp_avg_sq"] = st["exp_avg_sq"].detach().cpu().numpy()
            arrays[f"optim/{n}/step"] = np.asarray(float(st["step"]), dtype=np.float64).reshape(1)
    arrays["normalizer/low"] = normalizer.low.astype(np.float32)
    arrays["normalizer/high"] = normalizer.high.astype(np.float32)
    steps = np.array([c[0] for c in curve], dtype=np.int64)
    arrays["curve/step"] = steps
    arrays["curve/loss"] = np.array([c[1] for c in curve], dtype=np.float64)
    checked = [c for c in curve if c[2] is not None]
    if checked:
        arrays["curve/valid_step"] = np.array([c[0] for c in checked], dtype=np.int64)
        arrays["curve/valid_loss"] = np.array([c[2] for c in checked], dtype=np.float64)
    arrays.update(method.extra_arrays())
    return arrays


def _load_tensors(module, tensors: dict[str, np.ndarray], where: str) -> None:
    import torch

    state = {k: torch.from_numpy(np.array(v)) for k, v in tensors.items()}
    try:
        module.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        raise BadInput(f"{where}: weights do not fit the network in its config ({str(exc).splitlines()[0]})") from None


def load_planner(model: artifacts.Model, device="cpu"):
    """Rebuild the method of a model artifact with its EMA weights (and raw weights on ``method.net``)."""
    from cdrb_cli.methods import build_method

    cfg, spec = model.manifest.config, model.manifest.env
    norm = Normalizer(low=model.arrays["normalizer/low"], high=model.arrays["normalizer/high"])
    points = model.arrays.get("buffer/points")
    if cfg.method.name == "cdrb" and points is None:
        raise BadInput(f"{model.path}: CDRB model without /buffer/points", hint="re-train it")
    method = build_method(cfg, spec, norm, points, device=device)
    _load_tensors(method.net, model.tensors("weights"), str(model.path))
    ema = copy.deepcopy(method.net)
    _load_tensors(ema, model.tensors("ema"), str(model.path))
    method.net.eval()
    ema.eval()
    return method, ema


# ------------------------------------------------------------------------------------------------ training
def train(demos, buffer, config: TrainConfig, out: Path, resume: bool = False, device="cpu") -> artifacts.Model:
    import torch

    from cdrb_cli.methods import build_method

    spec = demos.manifest.env
    normalizer = check_inputs(demos, buffer, config.features)
    points = buffer.points if (buffer is not None and config.method.name == "cdrb") else None
    torch.manual_seed(config.seed)  # network initialization
    method = build_method(config, spec, normalizer, points, device=device)
    windows = WindowSampler(
        demos, config.features, normalizer, config.horizon, config.stride, config.split, config.start_fraction
    )
    valid_batch = None
    if config.split == "train" and len(demos.episode_ids("valid")):
        vw = WindowSampler(demos, config.features, normalizer, config.horizon, config.stride, "valid")
        valid_batch = torch.from_numpy(vw.episode_windows(64)).to(device)
    ema = copy.deepcopy(method.net).requires_grad_(False)
    opt = torch.optim.Adam(method.net.parameters(), lr=config.lr)
    parents = [demos] + ([buffer] if buffer is not None else [])
    n_params = sum(p.numel() for p in method.net.parameters())
    log_every = math.gcd(50, config.checkpoint_every)
    step, curve, wall = 0, [], 0.0

    if resume:
        step, curve, wall = _restore(out, config, parents, method, ema, opt, device)

    def save(finished: bool, loss_value, valid_value) -> None:
        state = TrainState(
            step=step,
            finished=finished,
            wall_time_s=round(wall, 3),
            loss=loss_value,
            valid_loss=valid_value,
            parameters=n_params,
        )
        manifest = artifacts.make_manifest(
            "model", env=spec, config=config, seed=config.seed, parents=parents, state=state
        )
        artifacts.save(out, "model", manifest, _state_arrays(method, ema, opt, normalizer, curve))

    def valid_loss() -> float | None:
        if valid_batch is None:
            return None
        with torch.no_grad():
            rng = step_rng(config.seed, STREAM_VALID, 0)  # the same validation draws at every checkpoint
            return float(method.loss(valid_batch, rng))

    t0 = time.time() - wall
    running, count = 0.0, 0
    last_loss = curve[-1][1] if curve else None
    method.net.train()
    with ui.progress() as bar:
        task = bar.add_task(f"train {config.method.name}", total=config.steps, completed=step, info="")
        while step < config.steps:
            rng = step_rng(config.seed, STREAM_TRAIN, step)
            batch = torch.from_numpy(windows.sample(config.batch_size, rng)).to(device)
            loss = method.loss(batch, rng)
            if not torch.isfinite(loss):
                raise RunFailed(
                    f"training diverged at step {step + 1}: the loss is {float(loss.detach())}; "
                    f"{out} keeps the last good checkpoint (step {_saved_step(out)})",
                    hint="lower --lr, then `--resume` or `--force`",
                )
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if config.grad_clip:
                torch.nn.utils.clip_grad_norm_(method.net.parameters(), config.grad_clip)
            opt.step()
            step += 1
            with torch.no_grad():
                if step <= config.ema_start:
                    ema.load_state_dict(method.net.state_dict())
                elif step % config.ema_every == 0:
                    for e, p in zip(ema.parameters(), method.net.parameters()):
                        e.mul_(config.ema_decay).add_(p.detach(), alpha=1 - config.ema_decay)
            running += float(loss.detach())
            count += 1
            if step % log_every == 0 or step == config.steps:
                last_loss = running / count
                running, count = 0.0, 0
                ckpt = step % config.checkpoint_every == 0 or step == config.steps
                curve.append((step, last_loss, valid_loss() if ckpt else None))
                bar.update(task, completed=step, info=f"loss {last_loss:.4f}")
                if ckpt:
                    wall = time.time() - t0
                    save(step == config.steps, last_loss, curve[-1][2])
    return artifacts.load(out, "model")


def _saved_step(out: Path):
    try:
        return artifacts.load(out, "model").manifest.state.step
    except BadInput:
        return "none"


def _restore(out: Path, config: TrainConfig, parents, method, ema, opt, device):
    import torch

    if not Path(out).exists():
        raise BadInput(f"--resume: {out} does not exist", hint="run without --resume to start training")
    model = artifacts.load(out, "model")
    have = model.manifest.config
    if have.model_copy(update={"steps": config.steps}) != config:
        raise BadInput(f"--resume: {out} was trained with a different config", hint="use the same flags, or --force")
    if [p.sha256 for p in model.manifest.parents] != [p.sha256 for p in parents]:
        raise BadInput(f"--resume: {out} was trained from other demos/buffer", hint="use the same inputs, or --force")
    if model.manifest.state.step > config.steps:
        raise BadInput(f"--resume: {out} is already at step {model.manifest.state.step} > --steps {config.steps}")
    _load_tensors(method.net, model.tensors("weights"), str(out))
    _load_tensors(ema, model.tensors("ema"), str(out))
    names = [n for n, _ in method.net.named_parameters()]
    state = {}
    optim = model.tensors("optim")
    for i, n in enumerate(names):
        if f"{n}/exp_avg" not in optim:
            continue
        state[i] = {
            "step": torch.tensor(float(optim[f"{n}/step"][0])),
            "exp_avg": torch.from_numpy(np.array(optim[f"{n}/exp_avg"])).to(device),
            "exp_avg_sq": torch.from_numpy(np.array(optim[f"{n}/exp_avg_sq"])).to(device),
        }
    sd = opt.state_dict()
    sd["state"] = state
    opt.load_state_dict(sd)
    steps = model.arrays["curve/step"].tolist()
    losses = model.arrays["curve/loss"].tolist()
    checked = dict(
        zip(
            model.arrays.get("curve/valid_step", np.zeros(0)).tolist(),
            model.arrays.get("curve/valid_loss", np.zeros(0)).tolist(),
        )
    )
    curve = [(s_, l_, checked.get(s_)) for s_, l_ in zip(steps, losses)]
    ui.log(f"resuming {out} from step {model.manifest.state.step}")
    return model.manifest.state.step, curve, model.manifest.state.wall_time_s
