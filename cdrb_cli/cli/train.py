"""`cdrb train`: a method on demonstration windows, to a model artifact (checkpointed, resumable)."""

from __future__ import annotations

from pathlib import Path

import typer

from cdrb_cli import ui
from cdrb_cli.cli.common import (
    DeviceOpt,
    ForceOpt,
    JsonOpt,
    SeedOpt,
    app,
    check_log_dir,
    check_outputs,
    check_positive,
    file_path,
    int_values,
    load_artifact,
)
from cdrb_cli.cli.options import ConfigOpt, MethodOpt, NetOpt, PresetOpt, SetOpt
from cdrb_cli.cli.tuned import read_selection, selection_train
from cdrb_cli.errors import BadInput


@app.command()
def train(
    demos: Path = typer.Argument(..., help="Demos artifact from `cdrb collect`."),
    buffer: Path | None = typer.Option(
        None, "--buffer", help="Buffer artifact (for methods that diffuse through one)."
    ),
    method: str | None = MethodOpt,
    net: str | None = NetOpt,
    preset: str | None = PresetOpt,
    steps: int | None = typer.Option(
        None, "--steps", help="Gradient steps (default: the preset's; `cdrb config train`)."
    ),
    sets: list[str] = SetOpt,
    config_file: Path | None = ConfigOpt,
    dry_run: bool = typer.Option(False, "--dry-run", help="Print the resolved config as JSON and exit."),
    device: str = DeviceOpt,
    out: Path = typer.Option(
        Path("model.h5"), "--out", "-o", help="Model artifact to write (also the checkpoint).", parser=file_path
    ),
    resume: bool = typer.Option(False, "--resume", help="Continue the checkpoint in --out (same settings and inputs)."),
    own: bool = typer.Option(
        False,
        "--continue-or-replace",
        hidden=True,
        help="Continue --out when it is a checkpoint of this run, else train over it: how `cdrb grid` trains into a "
        "model file it wrote itself (a run of other settings is out of date there, never a user's file).",
    ),
    log_dir: Path | None = typer.Option(
        None,
        "--log-dir",
        help="Also write the loss, validation loss, learning rate and steps/s as TensorBoard event files here, as "
        "training runs (`tensorboard --logdir DIR`; the tensorboard extra).",
    ),
    snapshot_at: str | None = typer.Option(
        None,
        "--snapshot-at",
        metavar="STEPS",
        help="Also write the model after these steps (e.g. 1000,3000) to OUT.step<N>.h5, each what `--steps N` "
        "writes: a learning curve from one run. Steps that OUT is already past are made by one run from the start "
        "to the last of them, not the whole run again. A file there that is not this run's snapshot is refused "
        "(--force overwrites it, and retrains OUT too).",
    ),
    seed: int = SeedOpt,
    force: bool = ForceOpt,
    as_json: bool = JsonOpt,
) -> None:
    """Train a method on demonstration windows and write a [bold]model[/bold] artifact.

    CDRB learns R(tau_k, k) ~ tau_0 where tau_k replaces each state by a random buffer state within radius eps_k.
    Windows are HORIZON states every STRIDE env steps, padded with the demo's final (resting) state; start and goal
    are pinned. Every hyper-parameter is a config field: [cyan]--set KEY=VALUE[/cyan] or [cyan]--config FILE[/cyan]
    ([cyan]cdrb config train --method M[/cyan] lists them with their defaults); [cyan]--dry-run[/cyan] shows the
    resolved config. The model is checkpointed into --out: after a crash, [cyan]--resume[/cyan] continues to
    exactly the result of an uninterrupted run.
    Example: [cyan]cdrb train demos.h5 --buffer buffer.h5 --set horizon=128 --set net.dim=32[/cyan]"""
    from cdrb_cli.methods.config import buffer_info, resolve_train_config, user_settings
    from cdrb_cli.stages.train import train_or_resume
    from cdrb_cli.torch_utils import setup_torch

    check_positive("--steps", steps)
    if own and (resume or force):
        raise BadInput("--continue-or-replace decides itself whether to resume or start over",
                       hint="drop --resume and --force")  # fmt: skip
    if log_dir is not None:
        from cdrb_cli.stages.train_log import summary_writer

        summary_writer()  # before any work: a missing extra is one line now, not after the data are read
    selection = read_selection(config_file)
    settings = user_settings(method, net, preset, steps, None if selection else config_file, sets)
    check_outputs(force, [demos, buffer, config_file], out=out)
    if log_dir is not None:
        check_log_dir(log_dir, out)
    d = load_artifact(demos, "demos")
    profile = None
    if selection is not None:  # the choice of `cdrb select` for this env and method, under this command line's
        chosen, profile = selection_train(selection, config_file, d.manifest.env.id, method)
        settings = chosen + settings
    b = load_artifact(buffer, "buffer") if buffer is not None else None
    config = resolve_train_config(d.manifest.env, buffer_info(b), settings, seed=seed)
    from cdrb_cli.stages.train import TRAIN_BYTES_PER_PARAMETER, check_size, check_snapshots

    n_params = check_size(d, b, config)
    snapshots = int_values(snapshot_at, "--snapshot-at", "step counts", "1000,3000") if snapshot_at else []
    check_snapshots(config, snapshots)  # a dry run refuses what the run would
    if dry_run:
        from cdrb_cli.torch_utils import check_device_name

        check_device_name(device)
        ui.log(f"{n_params:,} parameters (about {n_params * TRAIN_BYTES_PER_PARAMETER / 2**20:,.0f} MiB to train)")
        ui.emit(config.model_dump(mode="json"), as_json=True)
        return
    model, done = train_or_resume(
        d,
        b,
        config,
        out,
        force=force,
        resume=resume,
        auto=own,
        device=setup_torch(device),
        snapshots=snapshots,
        profile=profile,
        log_dir=log_dir,
    )
    if done.startswith("up to date"):
        also = ", its missing snapshots trained" if done != "up to date" else ""
        ui.log(f"{out} is up to date (same config and inputs): skipped{also}; --force redoes it")
    st = model.manifest.state
    ui.log(
        f"{config.method.name}: {st.step} steps, loss {st.loss:.4f}"
        + (f", valid {st.valid_loss:.4f}" if st.valid_loss is not None else "")
        + f", {st.parameters:,} parameters, {st.wall_time_s:.0f}s"
    )
    ui.emit({"path": str(out), "state": st.model_dump()} if as_json else out, as_json=as_json)
