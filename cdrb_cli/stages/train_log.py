"""Training that can be watched while it runs: the loss, the validation loss, the learning rate and the steps per
second as TensorBoard event files (``tensorboard --logdir DIR``), and in a grid the figures of each snapshot's
eval beside them. The model file's loss curve and the eval artifacts stay the record; these are a view of them as
they grow, written only when asked for (`cdrb train --log-dir`, a grid's ``tensorboard = true``)."""

from __future__ import annotations

import time
from pathlib import Path

from cdrb_cli.errors import BadInput


def summary_writer():
    """TensorBoard's event-file writer (the optional ``tensorboard`` extra), or a one-line error naming the fix."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        raise BadInput(
            "--log-dir writes TensorBoard event files, and the tensorboard package is not installed",
            hint="pip install 'cdrb-cli[tensorboard]' (or tensorboard), or drop --log-dir",
        ) from None
    return SummaryWriter


class TrainLog:
    """The scalars of one training in ``log_dir`` (None: nothing is written). A resumed training continues the
    same folder from its checkpoint's step: what an interrupted run wrote past it is dropped."""

    #: seconds between flushes to disk while training runs
    FLUSH_SECONDS = 10

    def __init__(self, log_dir: Path | None, step: int, lr: float):
        self.writer = None
        if log_dir is not None:
            # events past the checkpoint that a stopped run wrote are dropped; the checkpoint's own step is kept
            purge = step + 1 if step else None
            self.writer = summary_writer()(str(log_dir), purge_step=purge, flush_secs=self.FLUSH_SECONDS)
        self.lr, self.step, self.clock = lr, step, time.time()

    def point(self, step: int, loss: float, valid: float | None) -> None:
        """One point of the loss curve (a logged step)."""
        if self.writer is None:
            return
        now = time.time()
        self.writer.add_scalar("loss/train", loss, step)
        if valid is not None:
            self.writer.add_scalar("loss/valid", valid, step)
        self.writer.add_scalar("train/lr", self.lr, step)
        if now > self.clock and step > self.step:
            self.writer.add_scalar("train/steps_per_s", (step - self.step) / (now - self.clock), step)
        self.step, self.clock = step, now

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


def log_eval(log_dir: Path, name: str, step: int, summary) -> None:
    """An eval's figures beside its model's training curves, at the model's training length: success and, for a
    planner, plans through an obstacle (per cent), under ``eval/NAME/`` (NAME: the variant evaluated, or base)."""
    writer = summary_writer()(str(log_dir))
    try:
        writer.add_scalar(f"eval/{name}/success", 100 * summary.success_mean, step)
        if summary.plan_crossing_mean is not None:
            writer.add_scalar(f"eval/{name}/plans_through_obstacle", 100 * summary.plan_crossing_mean, step)
    finally:
        writer.close()
