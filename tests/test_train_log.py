"""Training watched live (`cdrb train --log-dir`): TensorBoard event files whose scalars are the model's own loss
curve, continued (not repeated) by a resumed training, and a one-line error when the extra is missing."""

from __future__ import annotations

import os
import sys

import pytest

from cdrb_cli.errors import BadInput

pytest.importorskip("tensorboard")


def _scalars(folder) -> dict[str, list[tuple[int, float]]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(folder))
    acc.Reload()
    return {tag: [(e.step, e.value) for e in acc.Scalars(tag)] for tag in acc.Tags()["scalars"]}


def test_the_event_files_hold_the_models_loss_curve_and_a_resume_continues_them(small_data, tmp_path):
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train_or_resume
    from tests.test_train import tiny

    demos, buffer = small_data
    logs, out = tmp_path / "tb", tmp_path / "m.h5"
    cfg = train_config(demos, buffer, "cdrb", tiny("cdrb", steps=40, checkpoint_every=20))
    model, _ = train_or_resume(demos, buffer, cfg, out, log_dir=logs)
    got = _scalars(logs)
    curve = list(zip(model.arrays["curve/step"].tolist(), model.arrays["curve/loss"].tolist(), strict=True))
    assert [s for s, _ in got["loss/train"]] == [s for s, _ in curve] == [10, 20, 30, 40]  # every gcd(50, 20) steps
    assert [v for _, v in got["loss/train"]] == pytest.approx([v for _, v in curve], rel=1e-6)
    valid = list(zip(model.arrays["curve/valid_step"].tolist(), model.arrays["curve/valid_loss"].tolist(), strict=True))
    assert [s for s, _ in got["loss/valid"]] == [s for s, _ in valid]
    assert [v for _, v in got["loss/valid"]] == pytest.approx([v for _, v in valid], rel=1e-6)
    assert all(v == pytest.approx(cfg.lr) for _, v in got["train/lr"])
    assert all(v > 0 for _, v in got["train/steps_per_s"])

    longer = cfg.model_copy(update={"steps": 60})  # the same run trained further: its curve goes on
    train_or_resume(demos, buffer, longer, out, resume=True, log_dir=logs)
    assert [s for s, _ in _scalars(logs)["loss/train"]] == [10, 20, 30, 40, 50, 60]


def test_a_missing_tensorboard_is_one_line(monkeypatch, small_data, tmp_path, capsys):
    from cdrb_cli.cli import main
    from cdrb_cli.stages.train_log import summary_writer

    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)  # as if the extra were not installed
    with pytest.raises(BadInput, match="tensorboard package is not installed"):
        summary_writer()
    demos, _ = small_data
    capsys.readouterr()
    code = main(["train", str(demos.path), "--method", "mlp", "--log-dir", str(tmp_path / "tb"),
                 "--out", str(tmp_path / "m.h5")])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2 and "pip install 'cdrb-cli[tensorboard]'" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "m.h5").exists() and not (tmp_path / "tb").exists()


def test_a_log_dir_that_cannot_be_a_folder_is_one_line_before_training(small_data, tmp_path, capsys):
    """--log-dir is TensorBoard's folder: a file, a FIFO, a link to nothing, a path under a file or the model's own
    --out path is refused before any work, and no model is written."""
    pytest.importorskip("torch.utils.tensorboard")
    from cdrb_cli.cli import main

    demos, _ = small_data
    out = tmp_path / "m.h5"
    (tmp_path / "afile").write_text("x")
    os.mkfifo(tmp_path / "fifo")
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    cases = {
        "afile": "exists and is not a folder",
        "fifo": "exists and is not a folder",
        "dangling": "a link to nothing",
        "afile/sub": "is not a folder",
        "m.h5": "the same path as --out",
    }
    for name, message in cases.items():
        capsys.readouterr()
        code = main(["train", str(demos.path), "--method", "mlp", "--steps", "5", "--log-dir", str(tmp_path / name),
                     "--out", str(out)])  # fmt: skip
        err = capsys.readouterr().err
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1, (name, err)
        assert not out.exists()


def test_a_grid_with_tensorboard_gives_each_training_its_folder_and_keeps_its_memo_keys(tmp_path):
    import cdrb_cli.cli  # noqa: F401  (installs the description of the commands a grid composes)
    from cdrb_cli.orchestration.grid import expand, load_grid
    from cdrb_cli.orchestration.grid.memo import command_key

    text = 'out = "runs"\nenvs = ["maze-tight"]\nmethods = ["mlp", "cdrb"]\nseeds = [0, 1]\n'
    (tmp_path / "a.toml").write_text(text)
    (tmp_path / "b.toml").write_text(text + "tensorboard = true\n")
    plain, watched = (expand(load_grid(tmp_path / f"{n}.toml")) for n in "ab")
    folders = []
    for a, b in zip(plain, watched, strict=True):
        assert command_key(a.argv)[1] == command_key(b.argv)[1]  # the same runs: their memos still hold
        if b.kind == "train":
            folders.append(b.argv[b.argv.index("--log-dir") + 1])
    assert sorted(folders) == sorted(
        str(tmp_path / "runs" / "tensorboard" / "maze-tight" / f"{m}-s{s}") for m in ("mlp", "cdrb") for s in (0, 1)
    )
    (tmp_path / "c.toml").write_text(text + '[[settings]]\ntrain = ["--log-dir", "x"]\n')
    with pytest.raises(BadInput, match="the grid sets this `cdrb train` option itself"):
        load_grid(tmp_path / "c.toml")


def test_a_grid_logs_each_snapshots_eval_beside_its_training(tmp_path, monkeypatch):
    """``tensorboard = true`` on a learning curve: the training's event files hold its loss and, at each snapshot
    and at its end, the success its eval measured (the eval artifact's own figure)."""
    import cdrb_cli.cli  # noqa: F401
    from cdrb_cli import artifacts
    from cdrb_cli.orchestration.grid import PoolBackend, load_grid, run_grid

    grid = tmp_path / "g.toml"
    grid.write_text(
        'out = "runs"\nenvs = ["maze-tight"]\nmethods = ["mlp"]\nseeds = [0]\ndemos = 20\nsteps = 40\n'
        "snapshot_at = [20]\neval_episodes = 2\ntensorboard = true\nreport = false\n"
        "[[settings]]\ntrain = { horizon = 16, stride = 10, batch_size = 8, checkpoint_every = 20, "
        "net = { hidden = [16, 16] } }\n"
    )
    backend = PoolBackend(1)
    try:
        run = run_grid(load_grid(grid), backend)
    finally:
        backend.close()
    assert {r.status for r in run.results} == {"done"}
    got = _scalars(tmp_path / "runs" / "tensorboard" / "maze-tight" / "mlp-s0")
    assert [s for s, _ in got["loss/train"]][-1] == 40
    evals = {20: "eval-mlp-s0.step20.h5", 40: "eval-mlp-s0.h5"}
    want = {s: 100 * artifacts.load(tmp_path / "runs" / "maze-tight" / f, "eval").manifest.summary.success_mean
            for s, f in evals.items()}  # fmt: skip
    assert dict(got["eval/base/success"]) == pytest.approx(want)
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)
    with pytest.raises(BadInput, match="tensorboard = true: --log-dir writes TensorBoard event files"):
        load_grid(grid)
