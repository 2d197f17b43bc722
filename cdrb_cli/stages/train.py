"""`cdrb train`: learn a method from demonstrations; checkpoint into the model artifact; resume exactly.

Randomness at step s comes only from ``seed`` and ``s`` (batch choice, diffusion steps, degradations), and the
model artifact holds every module's weights, their EMA copies and every optimizer's state: so killing training
and running ``--resume`` finishes with the same weights as an uninterrupted run (tests/test_train.py checks it bit
for bit). The loop knows nothing of the method beyond :class:`cdrb_cli.methods.base.Method`: its modules, its
optimizers and its ``update``.
"""

from __future__ import annotations

import contextlib
import math
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from cdrb_cli import artifacts, interrupts, ui
from cdrb_cli.buffer import Normalizer, demo_features, feature_dim, split_rows
from cdrb_cli.configs import TrainConfig, TrainState
from cdrb_cli.errors import BadInput, OutputExists, RunFailed
from cdrb_cli.files import replace_file
from cdrb_cli.methods.base import NonFiniteLoss, build_method
from cdrb_cli.methods.checkpoint import checkpoint_arrays, make_ema, restore
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.seeding import STREAM_TRAIN, STREAM_VALID, step_rng
from cdrb_cli.stages.train_log import TrainLog


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


def native_cpu_bfloat16() -> bool:
    """Whether this CPU multiplies bfloat16 matrices natively (AVX-512 BF16 or AMX, as oneDNN sees it); elsewhere
    torch emulates them, far slower than float32 (on an AVX2-only CPU a (2,560 x 256) x (256 x 256) product took
    ~60x float32's time)."""
    import torch

    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a build without oneDNN: nothing native to use
        return False


def check_precision(config: TrainConfig, device) -> None:
    """Refuse bfloat16 arithmetic on a GPU that has none; on a CPU without native bfloat16 warn that it is
    emulated (it runs, slower than float32)."""
    import torch

    if config.precision != "bfloat16":
        return
    if torch.device(device).type != "cuda":
        if not native_cpu_bfloat16():
            ui.warn(
                "--set precision=bfloat16: this CPU has no native bfloat16 arithmetic (AVX-512 BF16 or AMX), so "
                "torch emulates it, many times slower than float32: train with --set precision=float32 (the default)"
            )
        return
    if torch.cuda.is_bf16_supported():
        return
    raise BadInput(
        f"--set precision=bfloat16: {torch.cuda.get_device_name(device)} has no bfloat16 arithmetic",
        hint="train with --set precision=float32 (the default)",
    )


def snapshot_path(out: Path, step: int) -> Path:
    """Where ``--snapshot-at STEP`` writes the model as it is after STEP steps: ``<out stem>.step<STEP>.h5``."""
    out = Path(out)
    return out.with_name(f"{out.stem}.step{step}{out.suffix or '.h5'}")


def log_interval(config: TrainConfig) -> int:
    """Steps between two points of the loss curve: every 50 steps, and at every checkpoint."""
    return snapshot_step(config.checkpoint_every)


def snapshot_step(checkpoint_every: int) -> int:
    """Where a training records its model (``--snapshot-at`` steps are multiples of this): the points of its loss
    curve, every 50 steps and at every checkpoint."""
    return math.gcd(50, checkpoint_every)


def check_snapshots(config: TrainConfig, steps: Sequence[int]) -> list[int]:
    """Snapshot steps, validated: below ``steps`` and on the loss curve (multiples of :func:`log_interval`), so
    that each snapshot is exactly the model a run of that many steps writes."""
    every = log_interval(config)
    fits = every * max(1, config.steps // (4 * every))
    hint = (
        f"e.g. --snapshot-at {fits}"
        if fits < config.steps
        else f"train longer than {every} steps, or --set checkpoint_every=N for snapshots every gcd(50, N) steps"
    )
    for s in steps:
        if not 0 < s < config.steps or s % every:
            raise BadInput(
                f"--snapshot-at {s}: must be below --steps ({config.steps}) and a multiple of {every} (snapshots "
                f"fall every gcd(50, checkpoint_every) steps)",
                hint=hint,
            )
    return sorted(set(steps))


def train_or_resume(
    demos,
    buffer,
    config: TrainConfig,
    out: Path,
    force: bool = False,
    resume: bool = False,
    device="cpu",
    auto=False,
    snapshots: Sequence[int] = (),
    profile=None,
    log_dir: Path | None = None,
) -> tuple[artifacts.Model, str]:
    """Train into ``out`` according to what it holds (:func:`cdrb_cli.artifacts.existing`): reuse it when up to
    date, continue it with ``resume`` (or ``auto``) when it is a checkpoint of this run, start over with ``force``
    (or ``auto``, for a file of another run); refuse anything else. Returns the model and what was done:
    ``up to date``, ``up to date, snapshots trained`` (snapshots it was past, :func:`_earlier_snapshots`),
    ``resumed`` or ``trained``. ``profile``: the :class:`~cdrb_cli.configs.SettingsProfile` the
    model records (the selection its settings came from); ``log_dir``: a folder for TensorBoard event files."""
    if resume and force:
        raise BadInput("--resume and --force together", hint="--resume continues --out; --force starts over")
    parents = [demos] + ([buffer] if buffer is not None else [])
    snapshots = check_snapshots(config, snapshots)
    inputs = [p.path for p in parents]
    with contextlib.ExitStack() as stack:
        stack.enter_context(artifacts.claim_output(out, force=True, inputs=inputs))
        for s in snapshots:  # each snapshot, and the hidden checkpoint of a run that makes snapshots up to it
            for path in (snapshot_path(out, s), earlier_path(Path(out), s)):
                stack.enter_context(artifacts.claim_output(path, True, "--snapshot-at", inputs))
        _check_snapshot_files(config, Path(out), parents, snapshots, replace=force or auto)
        run = dict(device=device, snapshots=snapshots, profile=profile, log_dir=log_dir)
        model, what = _train_or_resume(demos, buffer, config, Path(out), parents, force, resume, auto, run)
        made = _earlier_snapshots(demos, buffer, config, Path(out), parents, snapshots, run)
        if made and what == "up to date":
            what = "up to date, snapshots trained"
        return model, what


def earlier_path(out: Path, step: int) -> Path:
    """The hidden checkpoint of the run that makes the snapshots ``out`` was already past, up to ``step``
    (:func:`_earlier_snapshots`): renamed to that snapshot once finished, so an interrupted run never leaves a
    snapshot-named file unfinished. One per last step, so a request for fewer snapshots never trains over the work of
    one for more; its name is shorter than the snapshot's."""
    return out.with_name(f".{out.stem}.e{step}{out.suffix or '.h5'}")


def _check_snapshot_files(config, out: Path, parents, snapshots, replace: bool) -> None:
    """Refuse, before any work, a snapshot path holding anything but this run's own work there: its finished
    snapshot (kept, as a rerun would write the same) or an unfinished checkpoint of it (trained over), unless
    ``replace`` (``--force``, or quickstart's own outputs)."""
    if replace:
        return
    for s in snapshots:
        path = snapshot_path(out, s)
        found = artifacts.existing(path, "model", config.model_copy(update={"steps": s}), parents)
        if found.status in ("missing", "up-to-date") or _unfinished(found):
            continue
        reason = found.reason.removeprefix(f"{path}: ")
        raise OutputExists(
            f"--snapshot-at {s}: {path} exists and is not this run's snapshot ({reason})",
            path,
            hint=f"remove it or choose another --out (--force overwrites it, and retrains {out.name} too)",
        )


def _unfinished(found: artifacts.Existing) -> bool:
    """Whether ``found`` is an unfinished checkpoint of the run asked for (same inputs and settings)."""
    return found.status == "resumable" and not found.artifact.manifest.state.finished


def _earlier_snapshots(demos, buffer, config, out: Path, parents, snapshots, run: dict) -> list[int]:
    """Make the snapshots ``out`` was already past when they were asked for (a learning curve given earlier points
    after its runs finished), returning their steps. One run from the start to the last of them writes them all,
    the same computation as the runs of those lengths (the learning rate is constant, so nothing before a step
    depends on ``steps``), and costs only those steps, not the whole run again. It checkpoints into
    :func:`earlier_path`, which an interrupted call resumes, and which is renamed to the last snapshot once
    finished (so no snapshot-named file is ever unfinished). A hidden checkpoint is removed only once its own
    snapshot is there."""

    def config_at(s: int):
        return config.model_copy(update={"steps": s})

    made, trained = [], False
    while True:
        missing = [
            s
            for s in snapshots
            if not artifacts.existing(snapshot_path(out, s), "model", config_at(s), parents).up_to_date
        ]
        for s in set(snapshots) - set(missing):  # the hidden run to a snapshot that is there: nothing needs it
            earlier_path(out, s).unlink(missing_ok=True)
        if not missing:
            return sorted(set(made))
        # a finished run left unrenamed (killed between the two) is its snapshot: rename it, then look again
        done = next(
            (s for s in missing if artifacts.existing(earlier_path(out, s), "model", config_at(s), parents).up_to_date),
            None,
        )
        if done is not None:
            replace_file(earlier_path(out, done), snapshot_path(out, done))
            made.append(done)
            continue
        if trained:  # pragma: no cover - a snapshot this run wrote does not read as up to date: a bug, not input
            raise RunFailed(f"--snapshot-at: {snapshot_path(out, missing[0])} was written but is not up to date")
        top = max(missing)
        side = earlier_path(out, top)
        _adopt_checkpoint(snapshot_path(out, top), side, config_at(top), parents)
        found = artifacts.existing(side, "model", config_at(top), parents)
        # an unfinished checkpoint of this run that has not passed a snapshot still to write continues (the
        # snapshot at the step it stopped at may not have been written); anything else starts over
        resume = _unfinished(found) and found.artifact.manifest.state.step < min(missing)
        what = f"continuing from step {found.artifact.manifest.state.step}" if resume else "training from the start"
        listed = ",".join(map(str, missing))
        them = "it" if len(missing) == 1 else "them"
        ui.log(f"--snapshot-at {listed}: {out.name} was past {them}; {what} to step {top} (checkpoints in {side.name})")
        at = dict(run, snapshots=missing[:-1], log_dir=None, snapshot_to=lambda s: snapshot_path(out, s))
        train(demos, buffer, config_at(top), side, resume=found.artifact if resume else False, **at)
        replace_file(side, snapshot_path(out, top))
        made.extend(missing)
        trained = True


def _adopt_checkpoint(path: Path, side: Path, config, parents) -> None:
    """An unfinished checkpoint of this run under the last snapshot's own name (where an earlier version of this
    command trained it) moves to the hidden checkpoint, when that holds no unfinished checkpoint of its own, so the
    work is continued, not lost, and the snapshot's name never holds an unfinished model."""
    if not _unfinished(artifacts.existing(path, "model", config, parents)):
        return
    if not _unfinished(artifacts.existing(side, "model", config, parents)):
        replace_file(path, side)


def _train_or_resume(demos, buffer, config, out, parents, force, resume, auto, run: dict):
    found = artifacts.existing(out, "model", config, parents) if not force else artifacts.Existing("missing")
    if found.up_to_date:
        return found.artifact, "up to date"
    if found.status == "resumable" and (resume or auto):
        return train(demos, buffer, config, out, resume=found.artifact, **run), "resumed"
    if resume:
        if found.status == "invalid":  # not a model at all (its reason names the file): --force would write over it
            raise BadInput(f"--resume: {found.reason}", hint="--out names the checkpoint of `cdrb train` to continue")
        missing = found.status == "missing"
        hint = "run without --resume to start training" if missing else "use the same inputs and settings, or --force"
        raise BadInput(f"--resume: {out}: {found.reason}", hint=hint)
    if found.status != "missing" and not auto:
        hint = "pass --resume to continue it" if found.status == "resumable" else "pass --force to overwrite it"
        raise BadInput(f"--out {out}: file exists ({found.reason})", hint=hint)
    return train(demos, buffer, config, out, **run), "trained"


def train(
    demos,
    buffer,
    config: TrainConfig,
    out: Path,
    resume=False,
    device="cpu",
    snapshots: Sequence[int] = (),
    profile=None,
    log_dir: Path | None = None,
    snapshot_to: Callable[[int], Path] | None = None,
) -> artifacts.Model:
    """Train ``config`` on the demos (and buffer), checkpointing into ``out``. ``resume``: True continues the
    checkpoint in ``out`` (same inputs and config, up to ``steps``); or pass that checkpoint's artifact.
    ``snapshots``: steps at which the model is also written, finished, to :func:`snapshot_path` exactly as a run of
    that many steps writes it (the learning rate is constant, so nothing else depends on ``steps``); ``profile``:
    the settings profile the model records; ``log_dir``: a folder for TensorBoard event files (:class:`TrainLog`);
    ``snapshot_to``: where the snapshot at a step goes, if not beside ``out``."""
    import torch

    snapshot_to = snapshot_to or (lambda s: snapshot_path(out, s))

    spec = demos.manifest.env
    normalizer = check_inputs(demos, buffer, config.features)
    check_precision(config, device)
    entry = METHODS.get(config.method.name)
    entry.method.check_data(demos, config)
    points = buffer.points if (buffer is not None and entry.needs_buffer) else None
    torch.manual_seed(config.seed)  # network initialization
    method = build_method(config, spec, normalizer, points, device=device, buffer_graph=_graph(buffer, config))
    windows = method.data(demos, normalizer, config.split)
    valid_batch = _validation_batch(method, demos, normalizer, config, device)
    ema = make_ema(method)
    optimizers = method.make_optimizers()
    parents = [demos] + ([buffer] if buffer is not None else [])
    modules = method.modules()
    n_params = sum(p.numel() for m in modules.values() for p in m.parameters())
    log_every = log_interval(config)
    step, curve, wall = 0, [], 0.0
    resume = _checkpoint(out, config, parents) if resume is True else resume
    if resume:
        step, curve, wall = restore(resume, method, ema, optimizers, device)
        _resumed_snapshots(resume, out, step, snapshots, snapshot_to)
        if curve and curve[-1][0] == step and step % config.checkpoint_every:
            # a shorter run's last step: its validation point is not one this longer run makes
            curve[-1] = (*curve[-1][:2], None)

    def save(finished: bool, loss_value, valid_value, path=out, cfg=config, points=None) -> None:
        state = TrainState(
            step=step,
            finished=finished,
            wall_time_s=round(wall, 3),
            loss=loss_value,
            valid_loss=valid_value,
            parameters=n_params,
        )
        manifest = artifacts.make_manifest(
            "model", env=spec, config=cfg, seed=cfg.seed, parents=parents, state=state, profile=profile
        )
        artifacts.save(path, "model", manifest, checkpoint_arrays(method, ema, optimizers, points or curve))

    def valid_loss() -> float | None:
        if valid_batch is None:
            return None
        with torch.no_grad():
            rng = step_rng(config.seed, STREAM_VALID, 0)  # the same validation draws at every checkpoint
            return float(method.loss(valid_batch, rng))

    update_ema = _ema_updater(ema, modules, config)
    t0 = time.time() - wall
    last_save = time.time()
    saved = step if resume else None  # the step of this run's checkpoint in ``out`` (a --force run's old file: none)
    running, count = 0.0, 0
    last_loss = curve[-1][1] if curve else None
    for m in modules.values():
        m.train()
    log = TrainLog(log_dir, step, config.lr)
    with ui.progress() as bar, interrupts.polled(), contextlib.closing(log):
        task = bar.add_task(f"train {config.method.name}", total=config.steps, completed=step, info="")
        while step < config.steps:
            interrupts.check()
            rng = step_rng(config.seed, STREAM_TRAIN, step)
            batch = torch.from_numpy(windows.sample(config.batch_size, rng)).to(device)
            loss = _update(method, batch, rng, optimizers, step, out, saved)
            step += 1
            update_ema(step)
            running += loss
            count += 1
            if step % log_every == 0 or step == config.steps:
                last_loss = running / count
                running, count = 0.0, 0
                ckpt = step % config.checkpoint_every == 0 or step == config.steps
                # by time as well (no validation loss there, so the curve does not depend on the clock)
                timed = 0 < config.checkpoint_seconds <= time.time() - last_save and not ckpt
                snap = step in snapshots
                valid = valid_loss() if (ckpt or snap) else None
                curve.append((step, last_loss, valid if ckpt else None))
                log.point(step, last_loss, valid if ckpt else None)
                bar.update(task, completed=step, info=f"loss {last_loss:.4f}")
                if ckpt or snap or timed:
                    wall = time.time() - t0
                if snap:  # what a run of `step` steps writes at its end
                    cfg = config.model_copy(update={"steps": step})
                    save(True, last_loss, valid, snapshot_to(step), cfg, curve[:-1] + [(step, last_loss, valid)])
                if ckpt or timed:
                    save(step == config.steps, last_loss, curve[-1][2])
                    last_save, saved = time.time(), step
    return artifacts.load(out, "model")


def _checkpoint(out: Path, config: TrainConfig, parents):
    """The checkpoint in ``out`` that ``--resume`` continues: of the same inputs and settings, else a one-line error."""
    found = artifacts.existing(out, "model", config, parents)
    if found.status not in ("resumable", "up-to-date"):
        raise OutputExists(f"--resume: {out}: {found.reason}", out, hint="use the same inputs and settings, or --force")
    return found.artifact


def _validation_batch(method, demos, normalizer, config: TrainConfig, device):
    """The held-out windows the validation loss is measured on (None without validation episodes)."""
    import torch

    if config.split != "train" or not len(demos.episode_ids("valid")):
        return None
    return torch.from_numpy(method.data(demos, normalizer, "valid").validation_batch()).to(device)


def _update(method, batch, rng, optimizers, step: int, out: Path, saved: int | None) -> float:
    """One gradient step's loss; a loss that is not finite stops the run, naming the checkpoint of this run that
    ``out`` keeps (``saved``: its step, None when this run wrote none)."""
    try:
        return method.update(batch, rng, optimizers)
    except NonFiniteLoss as exc:
        kept = "no checkpoint was written" if saved is None else f"{out} keeps the last good checkpoint (step {saved})"
        then = " and run again" if saved is None else ", then `--resume` or `--force`"
        raise RunFailed(
            f"training diverged at step {step + 1}: the loss is {exc.value}; {kept}",
            hint=f"lower the learning rate (--set lr=...){then}",
        ) from None


def _resumed_snapshots(resume, out: Path, step: int, snapshots: Sequence[int], snapshot_to) -> None:
    """On resuming ``out`` at ``step``: a finished run of ``step`` steps is kept as the snapshot a longer run writes
    there; snapshots already past and never written are made after the run (:func:`_earlier_snapshots`)."""
    ui.log(f"resuming {out} from step {step}")
    if step in snapshots and resume.manifest.state.finished and not snapshot_to(step).exists():
        with artifacts.atomic_path(snapshot_to(step)) as tmp:
            shutil.copyfile(resume.path, tmp)


def _ema_updater(ema: dict, modules: dict, config: TrainConfig):
    """The per-step EMA update: the copies follow the weights exactly until ``ema_start``, then average every
    ``ema_every`` steps. One fused (``_foreach``) call per module and step instead of one per tensor: the same
    arithmetic, a handful of kernels on a GPU where a U-Net has hundreds of tensors."""
    import torch

    pairs = []
    for name, avg in ema.items():
        live = modules[name]
        # state_dict() tensors share storage with the modules' parameters and buffers: copies into them are copies
        # into the modules; every floating tensor is averaged, integer buffers (counters) are copied
        a, b = avg.state_dict(keep_vars=False), live.state_dict(keep_vars=False)
        keys = [k for k in a if a[k].is_floating_point()]
        pairs.append(
            (
                [a[k] for k in keys],
                [b[k] for k in keys],
                [(a[k], b[k]) for k in a if not a[k].is_floating_point()],
                [p for p in avg.parameters()],
                [p for p in live.parameters()],
            )
        )

    def update(step: int) -> None:
        with torch.no_grad():
            for avg_all, live_all, others, avg_params, live_params in pairs:
                if step <= config.ema_start:
                    torch._foreach_copy_(avg_all, live_all)
                    for x, y in others:
                        x.copy_(y)
                elif step % config.ema_every == 0:
                    torch._foreach_mul_(avg_params, config.ema_decay)
                    torch._foreach_add_(avg_params, live_params, alpha=1 - config.ema_decay)

    return update


#: bytes a float32 parameter costs in training: the weight, its EMA copy, its gradient and Adam's two moments
TRAIN_BYTES_PER_PARAMETER = 5 * 4


def _graph(buffer, config: TrainConfig):
    """The buffer's transition graph for a method that keeps its buffer: required where it measures its balls along
    it (a buffer without one is refused with the way to make one), else carried where the buffer has one (waypoint
    routes go along it); None for the other methods."""
    if buffer is None or not METHODS.get(config.method.name).needs_buffer:
        return None
    if getattr(config.method, "ball", "euclidean") == "geodesic":
        return buffer.graph()
    return buffer.graph() if "graph/edges" in buffer.arrays else None


def parameter_count(demos, buffer, config: TrainConfig) -> int:
    """The parameters of the network ``config`` builds, counted on torch's meta device (nothing is allocated, so
    a network too large for the machine is measured, not attempted)."""
    import torch

    normalizer = check_inputs(demos, buffer, config.features)
    entry = METHODS.get(config.method.name)
    points = buffer.points if (buffer is not None and entry.needs_buffer) else None
    with torch.device("meta"):
        method = build_method(
            config, demos.manifest.env, normalizer, points, device="meta", buffer_graph=_graph(buffer, config)
        )
    return sum(p.numel() for m in method.modules().values() for p in m.parameters())


def available_memory() -> int | None:
    """Bytes of memory the OS can still give (Linux MemAvailable; None where unknown)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


def check_size(demos, buffer, config: TrainConfig) -> int:
    """The network's parameter count; a network whose weights, EMA, gradients and Adam state alone exceed the
    memory available is refused before anything is allocated."""
    n = parameter_count(demos, buffer, config)
    need, free = n * TRAIN_BYTES_PER_PARAMETER, available_memory()
    if free is not None and need > free:
        raise BadInput(
            f"the network has {n:,} parameters: training needs at least {need / 2**30:,.1f} GiB (weights, EMA, "
            f"gradients, Adam), more than the {free / 2**30:,.1f} GiB available",
            hint="lower net.dim or net.dim_mults (`cdrb config train` lists them)",
        )
    return n
