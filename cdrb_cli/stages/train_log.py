"""Training that can be watched while it runs: the loss, the validation loss, the learning rate and the steps per
second as TensorBoard event files (``tensorboard --logdir DIR``). The model file's loss curve stays the record;
these are a view of it as it grows, written only when asked for (`cdrb train --log-dir`)."""

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
