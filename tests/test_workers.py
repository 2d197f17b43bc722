"""Independent jobs side by side in worker processes: results in order, progress and logs drawn by the parent,
a user's error re-raised as its one line, and the cores shared out."""

from __future__ import annotations

import os
import time
from pathlib import Path

import pytest

from cdrb_cli import ui, workers
from cdrb_cli.errors import BadInput, RunFailed


def _job(payload):
    """A worker's job: report progress and a log line, then answer (or fail as the payload says). With a
    ``meet`` folder it first waits (up to 60 s) until two processes have started jobs there, so a quick worker
    cannot take every job before the other one is up."""
    if payload.get("meet"):
        meet = Path(payload["meet"])
        (meet / str(os.getpid())).touch()
        deadline = time.monotonic() + 60
        while len(list(meet.iterdir())) < 2 and time.monotonic() < deadline:
            time.sleep(0.01)
    with ui.progress() as bar:
        task = bar.add_task(f"job {payload['n']}", total=3, info="")
        for i in range(3):
            bar.update(task, completed=i + 1)
    ui.log(f"job {payload['n']} ran with {os.environ.get('OMP_NUM_THREADS')} thread(s) in {os.getpid()}")
    if payload.get("bad"):
        raise BadInput(f"job {payload['n']}: bad input", hint="fix it")
    if payload.get("failed"):
        raise RunFailed(f"job {payload['n']}: it failed")
    return payload["n"] * 10


def test_jobs_run_side_by_side_and_their_progress_comes_back(capfd, monkeypatch, tmp_path):
    monkeypatch.setenv("CDRB_PROGRESS_SECONDS", "0")
    jobs = [{"n": i, "meet": str(tmp_path)} for i in range(3)]
    assert workers.run(_job, jobs, processes=2, threads=1) == [0, 10, 20]
    err = capfd.readouterr().err
    for i in range(3):
        assert f"job {i}: 3/3 (100%)" in err
        assert f"job {i} ran with 1 thread(s)" in err
    pids = {line.rsplit(" ", 1)[1] for line in err.splitlines() if " thread(s) in " in line}
    assert len(pids) == 2 and str(os.getpid()) not in pids  # two worker processes, not this one


@pytest.mark.parametrize("flag, error", [("bad", BadInput), ("failed", RunFailed)])
def test_a_workers_error_comes_back_as_its_one_line(flag, error):
    with pytest.raises(error) as exc:
        workers.run(_job, [{"n": 0}, {"n": 1, flag: True}], processes=2, threads=1)
    assert exc.value.message.startswith("job 1:")


def test_one_process_runs_the_jobs_here_in_order():
    assert workers.run(_job, [{"n": 2}, {"n": 1}], processes=1, threads=2) == [20, 10]


@pytest.mark.parametrize(
    "cores, jobs, device, expected",
    [(2, 2, "cpu", (2, 1)), (2, 3, "cpu", (2, 1)), (8, 2, "cpu", (2, 4)), (1, 2, "cpu", (1, 1)), (2, 1, "cpu", (1, 2)),
     (8, 2, "cuda", (1, 8))],
)  # fmt: skip
def test_the_free_cores_are_shared_out(monkeypatch, cores, jobs, device, expected):
    from cdrb_cli import torch_utils

    monkeypatch.setattr(torch_utils, "cpu_threads", lambda: cores)
    assert workers.plan(jobs, device) == expected


def test_workers_spawned_under_sigint_ignored_start_with_it_ignored_and_the_parent_gets_its_handler_back():
    import signal
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    before = signal.getsignal(signal.SIGINT)
    with workers.sigint_ignored():
        pool = ProcessPoolExecutor(1, mp_context=get_context("spawn"))
        future = pool.submit(signal.getsignal, signal.SIGINT)
    try:
        assert future.result(timeout=120) == signal.SIG_IGN  # a Ctrl-C during the worker's imports does nothing there
    finally:
        pool.shutdown()
    assert signal.getsignal(signal.SIGINT) is before
    # without it, Python's own handler (the parent handling SIGINT: a shell's background job starts with it ignored)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        control = ProcessPoolExecutor(1, mp_context=get_context("spawn"))
        assert control.submit(signal.getsignal, signal.SIGINT).result(timeout=120) is not signal.SIG_IGN
    finally:
        control.shutdown()
        signal.signal(signal.SIGINT, before)


def test_a_ctrl_c_during_the_clis_imports_is_one_line_and_exit_130(monkeypatch, capsys):
    import sys
    import types

    from cdrb_cli import launch

    class Interrupted(types.ModuleType):
        def __getattr__(self, name):  # `from cdrb_cli.cli import main` halfway through its imports
            raise KeyboardInterrupt

    monkeypatch.setitem(sys.modules, "cdrb_cli.cli", Interrupted("cdrb_cli.cli"))
    assert launch.main() == 130
    assert capsys.readouterr().err == "error: interrupted\n"
    project = (Path(__file__).resolve().parent.parent / "pyproject.toml").read_text()
    assert '\ncdrb = "cdrb_cli.launch:main"\n' in project  # the console script goes through it


def _slow_load(marker: str, ran: str, seconds: float) -> dict:
    """Unpickling a :class:`SlowPayload` in a worker: says so in ``marker``, then takes ``seconds`` (a job whose
    imports are slow, with a Ctrl-C landing in them)."""
    (Path(marker) / str(os.getpid())).touch()
    time.sleep(seconds)
    return {"ran": ran}


class SlowPayload:
    def __init__(self, marker: str, ran: str, seconds: float):
        self.args = (marker, ran, seconds)

    def __reduce__(self):
        return _slow_load, self.args


def _record(payload: dict) -> int:
    (Path(payload["ran"]) / str(os.getpid())).touch()
    return os.getpid()


def _run_script(setup: str, jobs: str, fn: str) -> str:
    """A program that runs ``workers.run(fn, jobs, 2, 1)`` after ``setup`` and, interrupted, says `stopped` and
    exits 130."""
    return (
        f"import sys\nsys.path.insert(0, {str(Path(__file__).parent)!r})\nfrom cdrb_cli import workers\n{setup}\n"
        f"try:\n    workers.run({fn}, {jobs}, 2, 1)\n"
        "except KeyboardInterrupt:\n    sys.stderr.write('stopped\\n')\n    sys.exit(130)\n"
    )


def test_a_ctrl_c_while_the_workers_load_their_jobs_stops_every_job_with_no_traceback(tmp_path):
    import signal
    import subprocess
    import sys

    marker, ran = tmp_path / "loading", tmp_path / "ran"
    marker.mkdir()
    ran.mkdir()
    jobs = f"[SlowPayload({str(marker)!r}, {str(ran)!r}, 2.0) for _ in range(3)]"
    script = _run_script("from test_workers import SlowPayload, _record", jobs, "_record")
    proc = subprocess.Popen(
        [sys.executable, "-c", script],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # a process group of its own, as a terminal's foreground job
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    deadline = time.monotonic() + 120
    while not any(marker.iterdir()) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    assert any(marker.iterdir()), proc.communicate()[1]
    os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C: the whole group, while a worker unpickles its job
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip().endswith("stopped"), err
    assert not any(ran.iterdir())  # no job ran after the Ctrl-C, the queued third one included


def _long_job(payload: dict) -> int:
    (Path(payload["started"]) / str(os.getpid())).touch()
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        time.sleep(0.05)
    (Path(payload["done"]) / str(os.getpid())).touch()
    return 0


def test_a_parent_stopped_alone_stops_its_workers_jobs(tmp_path):
    """`kill PID` reaches the parent only (no Ctrl-C to the group): the parent's stop event makes each running job
    stop as a SIGTERM stops it, so the command ends in seconds, not when its jobs would have finished."""
    import signal
    import subprocess
    import sys

    started, done = tmp_path / "started", tmp_path / "done"
    started.mkdir()
    done.mkdir()
    jobs = f"[{{'started': {str(started)!r}, 'done': {str(done)!r}}}] * 2"
    setup = "from test_workers import _long_job\nfrom cdrb_cli import interrupts\ninterrupts.install()  # as the CLI"
    script = _run_script(setup, jobs, "_long_job")
    proc = subprocess.Popen([sys.executable, "-c", script], stderr=subprocess.PIPE, text=True, start_new_session=True)
    deadline = time.monotonic() + 120
    while len(list(started.iterdir())) < 2 and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.02)
    assert len(list(started.iterdir())) == 2, proc.communicate()[1]
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and time.monotonic() - t0 < 30, err
    assert "Traceback" not in err and not any(done.iterdir()), err
