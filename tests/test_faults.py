"""Faults: kill -9 at random points, crashes before rename, NaN losses, hostile files, fuzzed files."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from benchmarks.fault_harness import crash_before_rename, launcher, run_faults
from cdrb_cli import artifacts
from cdrb_cli.errors import BadInput
from tests.factories import KINDS, tampered, write

PACKAGE = Path(__file__).resolve().parent.parent / "cdrb_cli"


@pytest.mark.slow
def test_kill9_at_random_points_loses_nothing(tmp_path):
    # a 60-step training (six checkpoints) keeps kills landing before, between and after checkpoints; the script's
    # many-kill table uses 150. The commands are forks of a warm server: the kills land in their work, not in the
    # interpreter's imports (the script's default is fresh interpreters)
    with launcher(tmp_path, warm=sys.platform.startswith("linux")) as launch:
        stats = run_faults(tmp_path, launch, kills_per_stage=2, seed=0, train_steps=60)
        crashed = crash_before_rename(tmp_path, launch, train_steps=60)
    for name, s in stats.items():
        assert s.kills == 2 and s.failed_before_kill == 0, name
        assert s.output_corrupt == 0, name
        assert s.rerun_mismatch == 0, name
    assert all(crashed.values()), crashed


def test_no_pickle_anywhere_in_the_package():
    pattern = re.compile(r"\bpickle\b|torch\.load\(|joblib|cloudpickle|allow_pickle\s*=\s*True|dill\b")
    offenders = []
    for path in PACKAGE.rglob("*.py"):
        for i, line in enumerate(path.read_text().splitlines(), 1):
            if pattern.search(line) and not line.lstrip().startswith("#"):
                offenders.append(f"{path.name}:{i}: {line.strip()}")
    # the SB3 expert loader is the one documented exception: it loads a policy zip the user names, never an artifact
    offenders = [o for o in offenders if not o.startswith("sac.py")]
    assert not offenders, offenders


def _absurd_manifest(path, mutate):
    with tampered(path) as f:
        m = json.loads(f["manifest"][()].decode())
        mutate(m)
        del f["manifest"]
        f["manifest"] = np.bytes_(json.dumps(m).encode())


@pytest.mark.parametrize(
    "mutate, needle",
    [
        (lambda m: m["env"]["scene"]["maze"].update(rows=["#" * 5000] * 3), "env.scene.maze.rows"),
        (lambda m: m["env"]["scene"]["maze"].update(rows=["#####", "#S.G#", "#####"] * 40), "env.scene.maze.rows"),
        (lambda m: m["env"]["scene"].update(family="moon"), "unknown environment family 'moon'"),
        (lambda m: m["config"]["expert"].update(kind="oracle"), "unknown expert 'oracle'"),
        (lambda m: m["env"].update(id="x" * 10_000), "env.id"),
        (lambda m: m["env"]["obstacles"].update(centers=[[0, 0]] * 30_000), "env.obstacles.centers"),
        (lambda m: m["env"].update(obs_dim=10**9), "env.obs_dim"),
        (lambda m: m["env"]["obstacles"].update(low=[10, 10]), "env.obstacles"),
        (lambda m: m["env"]["scene"].update(maze=None), "env.scene"),
        (lambda m: m["summary"].update(success_rate=float("nan")), "summary.success_rate"),
        (lambda m: m["config"].update(valid_fraction=float("inf")), "config.valid_fraction"),
    ],
)
def test_absurd_manifests_are_refused(tmp_path, mutate, needle):
    p = write(tmp_path / "d.h5", "demos")
    _absurd_manifest(p, mutate)
    with pytest.raises(BadInput, match=re.escape(needle)):
        artifacts.load(p)


def test_inspect_neutralizes_markup_and_terminal_escapes(tmp_path, cdrb):
    p = write(tmp_path / "d.h5", "demos")
    _absurd_manifest(p, lambda m: m.update(argv=["[red]boom[/red]", "\x1b[2J\x1b[31mevil", "x" * 5000]))
    r = cdrb("inspect", p)
    assert r.returncode == 0
    assert "\x1b" not in r.stdout and "[red]boom[/red]" in r.stdout and "more characters" in r.stdout


@pytest.mark.parametrize(
    "kind, mutate, needle",
    [
        ("model", lambda m: m["config"]["method"].update(name="magic"), "magic"),
        ("eval", lambda m: m["config"]["controller"].update(name="joystick"), "joystick"),
    ],
)
def test_unknown_methods_and_controllers_in_manifests_are_refused(tmp_path, kind, mutate, needle):
    p = write(tmp_path / f"{kind}.h5", kind)
    _absurd_manifest(p, mutate)
    with pytest.raises(BadInput, match=needle):
        artifacts.load(p)


def test_empty_datasets_are_refused(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    with tampered(p) as f:
        for name in ("episodes/start", "episodes/length", "episodes/seed", "episodes/success", "episodes/valid"):
            dt = f[name].dtype
            del f[name]
            f.create_dataset(name, shape=(0,), dtype=dt)
    with pytest.raises(BadInput, match="is empty"):
        artifacts.load(p)


# ------------------------------------------------------------------------------------------------ fuzzing
@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    root = tmp_path_factory.mktemp("pristine")
    return {kind: write(root / f"{kind}.h5", kind) for kind in KINDS}


def _json_values():
    return st.recursive(
        st.none() | st.booleans() | st.integers(-(10**12), 10**12) | st.floats(allow_nan=True) | st.text(max_size=20),
        lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
        max_leaves=10,
    )


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


# derandomized: CI runs the same 300 cases every time (random campaigns are run by hand: --hypothesis-seed=N)
@settings(
    max_examples=300, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(data=st.data())
def test_fuzzed_files_give_an_artifact_or_our_error(pristine, tmp_path, data):
    kind = data.draw(st.sampled_from(KINDS))
    p = tmp_path / "f.h5"
    shutil.copy(pristine[kind], p)
    mutation = data.draw(
        st.sampled_from(["bytes", "truncate", "manifest", "attrs", "dataset", "storage", "sparse", "sizes"])
    )
    if mutation == "bytes":
        raw = bytearray(p.read_bytes())
        for _ in range(data.draw(st.integers(1, 8))):
            raw[data.draw(st.integers(0, len(raw) - 1))] = data.draw(st.integers(0, 255))
        p.write_bytes(bytes(raw))
    elif mutation == "truncate":
        raw = p.read_bytes()
        p.write_bytes(raw[: data.draw(st.integers(0, len(raw) - 1))])
    elif mutation == "manifest":
        with tampered(p) as f:
            m = json.loads(f["manifest"][()].decode())
            where = data.draw(st.sampled_from(list(_paths(m))[1:]))
            node = m
            for key in where[:-1]:
                node = node[key]
            if data.draw(st.booleans()) and isinstance(node, dict):
                del node[where[-1]]
            else:
                node[where[-1]] = data.draw(_json_values())
            del f["manifest"]
            f["manifest"] = np.bytes_(json.dumps(m).encode())
    elif mutation == "attrs":
        with tampered(p) as f:
            name = data.draw(st.sampled_from(["cdrb_kind", "cdrb_schema_version"]))
            # what HDF5 can store as a string attribute: no NUL, no lone surrogates
            no_nul = st.text(st.characters(blacklist_characters="\x00", blacklist_categories=("Cs",)), max_size=12)
            f.attrs[name] = data.draw(no_nul | st.sampled_from(["1.9", "0.1", "demos", "model"]))
    elif mutation == "storage":  # a dataset whose data lives in another file: virtual or external raw storage
        with tampered(p) as f:
            names = []
            f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) and n != "manifest" else None)
            name = data.draw(st.sampled_from(names))
            shape, dtype = f[name].shape, f[name].dtype
            del f[name]
            if data.draw(st.booleans()):
                layout = h5py.VirtualLayout(shape=shape, dtype=dtype)
                layout[...] = h5py.VirtualSource(str(pristine[kind]), name, shape=shape)
                f.create_virtual_dataset(name, layout)
            else:
                outside = tmp_path / "outside.bin"
                outside.write_bytes(b"\0" * (int(np.prod(shape)) * dtype.itemsize + 8))
                f.create_dataset(name, shape=shape, dtype=dtype, external=[(str(outside), 0, h5py.h5f.UNLIMITED)])
    elif mutation == "sparse":  # a hole at the end, and a chunked dataset declaring far more than is stored
        with tampered(p) as f:
            f.create_dataset("padding", shape=(data.draw(st.integers(10**5, 10**8)),), dtype="f8", chunks=(10**5,))
        os.truncate(p, p.stat().st_size + data.draw(st.integers(0, 2**31)))
    elif mutation == "sizes":  # a size in the config blown up (net widths, steps, horizon, T, k, ...)
        with tampered(p) as f:
            m = json.loads(f["manifest"][()].decode())
            ints = [w for w in _paths(m.get("config", {})) if w and isinstance(_get(m["config"], w), int)]
            if ints:
                where = data.draw(st.sampled_from(ints))
                node = m["config"]
                for key in where[:-1]:
                    node = node[key]
                node[where[-1]] = data.draw(st.sampled_from([10**9, 2**40, 40_000, -1]))
            del f["manifest"]
            f["manifest"] = np.bytes_(json.dumps(m).encode())
    else:
        with tampered(p) as f:
            names = []
            f.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) and n != "manifest" else None)
            name = data.draw(st.sampled_from(names))
            arr = f[name][()]
            del f[name]
            choice = data.draw(st.sampled_from(["drop", "shape", "dtype", "nan"]))
            if choice == "shape":
                f[name] = np.resize(arr, (max(arr.shape[0] - 1, 0),) + arr.shape[1:]) if arr.ndim else arr
            elif choice == "dtype":
                f[name] = arr.astype("S8") if arr.size else arr
            elif choice == "nan":
                f[name] = np.full(arr.shape, np.nan)
    try:
        art = artifacts.load(p)
        if art.kind == "model":  # what plan and eval do next: never allocate what the config claims unchecked
            from cdrb_cli.methods.checkpoint import load_method

            load_method(art)
    except BadInput as exc:
        assert "\n" not in str(exc)
        return
    assert art.kind in KINDS


def _get(obj, where):
    for key in where:
        obj = obj[key]
    return obj


def test_an_interrupt_before_the_first_checkpoint_does_not_advertise_resume(small_data, tmp_path):
    """Stopped before any checkpoint exists, a training has nothing for --resume to continue: the line says so."""
    from tests.test_train import TINY_FLAGS

    demos, buffer = small_data
    out = tmp_path / "m.h5"
    args = ["train", demos.path, "--buffer", buffer.path, "--steps", "100000", "--set", "checkpoint_every=50000"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdrb_cli", *map(str, args), *TINY_FLAGS, "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        time.sleep(8)  # started and training, far from step 50,000
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    last = stderr.strip().splitlines()[-1]
    assert proc.returncode == 130 and not out.exists(), stderr
    assert last.startswith("error: interrupted") and "--resume" not in last and "no checkpoint of" in last, last


def test_an_interrupt_after_the_model_was_written_does_not_say_none_was(tmp_path):
    """Ctrl-C between a finished model's write and the command's end: the advice names the file that is there,
    not "no checkpoint was written"."""
    from cdrb_cli.cli import _how_to_continue
    from tests.factories import write

    out = write(tmp_path / "m.h5", "model")
    said = _how_to_continue(["train", "d.h5", "--out", str(out)])
    assert "no checkpoint" not in said and str(out) in said and "--resume" not in said, said
    assert "no checkpoint of" in _how_to_continue(["train", "d.h5", "--out", str(tmp_path / "absent.h5")])


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupts_exit_130_with_one_line_and_partial_models_are_refused(small_data, tmp_path, cdrb, sig):
    """Ctrl-C (or SIGTERM) during training: exit 130, one line saying how to continue, no temp file; the unfinished
    checkpoint is not planned with unless asked (--allow-partial)."""
    from tests.test_train import TINY_FLAGS

    demos, buffer = small_data
    out = tmp_path / "m.h5"
    args = ["train", demos.path, "--buffer", buffer.path, "--steps", "100000", "--set", "checkpoint_every=5"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "cdrb_cli", "-q", *map(str, args), *TINY_FLAGS, "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a runner that starts the suite as a background job hands it SIGINT ignored (and Python then installs no
        # Ctrl-C handler); what is tested is a Ctrl-C that reaches the process, as in a terminal
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        deadline = time.time() + 120
        while not out.exists() and time.time() < deadline:
            time.sleep(0.05)
        time.sleep(0.5)
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:  # never leave a 100,000-step training running behind a failed test
            proc.kill()
            proc.wait()
    assert proc.returncode == 130 and stdout == "", (proc.returncode, stderr)
    assert stderr.startswith("error: interrupted") and "--resume" in stderr and stderr.count("\n") == 1, stderr
    assert [p.name for p in tmp_path.iterdir()] == ["m.h5"]
    assert not artifacts.load(out, "model").manifest.state.finished
    r = cdrb("plan", out, "--start", "0,0", "--goal", "6,6", "--out", tmp_path / "p.h5")
    assert r.returncode == 2 and "--allow-partial" in r.stderr and "unfinished" in r.stderr
    r = cdrb("plan", out, "--start", "0,0", "--goal", "6,6", "--allow-partial", "--out", tmp_path / "p.h5")
    assert r.returncode == 0 and "warning" in r.stderr and "an unfinished training" in r.stderr, r.stderr


def _rewrite_manifest(path, mutate):
    with tampered(path) as f:
        m = json.loads(f["manifest"][()].decode())
        mutate(m)
        del f["manifest"]
        f["manifest"] = np.bytes_(json.dumps(m).encode())


def test_a_sparse_tail_does_not_lift_the_size_cap(tmp_path):
    """64x the bytes the file really holds, not its apparent size: a hole at the end must not let a few KiB on disk
    declare hundreds of MB of (fill-value) data."""
    p = write(tmp_path / "d.h5", "demos")
    with tampered(p) as f:
        f.create_dataset("extra", shape=(50_000_000,), dtype="f8", chunks=(1_000_000,))  # 400 MB, nothing stored
    os.truncate(p, 200 * 2**20)  # a 200 MB apparent size, a few KiB on disk
    assert p.stat().st_size == 200 * 2**20 and p.stat().st_blocks * 512 < 2**20
    with pytest.raises(BadInput, match="more than this file can hold"):
        artifacts.load(p)


@pytest.fixture(scope="module")
def trained(small_data, tmp_path_factory):
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.stages.train import train
    from tests.test_train import tiny

    demos, buffer = small_data
    return train(
        demos, buffer, train_config(demos, buffer, "cdrb", tiny("cdrb", steps=2)), tmp_path_factory.mktemp("m") / "m.h5"
    )


@pytest.mark.parametrize(
    "mutate, needle",
    [
        (lambda m: m["config"]["net"].update(dim=40_000), "less than or equal to 4096"),
        (lambda m: m["config"]["method"].update(diffusion_steps=2_000_000_000), "less than or equal to 100000"),
        (lambda m: m["config"].update(method={"name": "mlp", "sampler": "direct"}), "the mlp method uses --net mlp"),
        (lambda m: m["config"].update(horizon=15), "multiple of 2"),
        (lambda m: m["state"].update(step=10**6), "past config.steps"),
    ],
)
def test_model_configs_are_checked_when_read(trained, tmp_path, mutate, needle):
    p = tmp_path / "m.h5"
    shutil.copy(trained.path, p)
    _rewrite_manifest(p, mutate)
    with pytest.raises(BadInput, match=re.escape(needle)):
        artifacts.load(p)


def test_a_config_that_does_not_fit_its_weights_is_refused_before_building(trained, tmp_path, cdrb):
    """net.dim 64 is a valid config, but the stored tensors were made with 8: refused from shapes alone (the
    network is never allocated), naming a tensor."""
    p = tmp_path / "m.h5"
    shutil.copy(trained.path, p)
    _rewrite_manifest(p, lambda m: m["config"]["net"].update(dim=64))
    r = cdrb("plan", p, "--start", "0,0", "--goal", "6,6", "--out", tmp_path / "p.h5")
    assert r.returncode == 2 and "has shape" in r.stderr and "its config builds" in r.stderr, r.stderr


@pytest.mark.parametrize("kind", ["demos", "model", "eval"])
def test_single_bit_flips_never_load_as_other_content(tmp_path, kind):
    """The content checksum: a flipped bit anywhere gives our error or (a bit nobody reads) the same content."""
    pristine = artifacts.load(write(tmp_path / "p.h5", kind, n=8))
    raw = (tmp_path / "p.h5").read_bytes()
    rng = np.random.default_rng(0)
    loaded = 0
    for i in range(50):
        flipped = bytearray(raw)
        at = int(rng.integers(len(raw)))
        flipped[at] ^= 1 << int(rng.integers(8))
        p = tmp_path / f"f{i}.h5"
        p.write_bytes(bytes(flipped))
        try:
            art = artifacts.load(p)
        except BadInput:
            continue
        loaded += 1
        assert art.manifest == pristine.manifest, at
        assert art.arrays.keys() == pristine.arrays.keys()
        for name in art.arrays:
            np.testing.assert_array_equal(art.arrays[name], pristine.arrays[name], err_msg=f"byte {at}: {name}")
    assert loaded < 50  # most flips land in data the checksum covers


def test_a_signal_inside_a_polled_loop_waits_for_the_check_and_is_never_lost():
    """In training the signal only raises a flag, answered at the next step: an interrupt raised inside a weakref
    callback or finalizer is dropped by Python ("Exception ignored in ..."), which once let a Ctrl-C'd training
    run on. Outside a polled loop the signal raises at once, as Python's own handler does."""
    import weakref

    from cdrb_cli import interrupts

    class Obj:
        pass

    restore = interrupts.install()
    try:
        with pytest.raises(KeyboardInterrupt), interrupts.polled():
            o = Obj()
            weakref.finalize(o, os.kill, os.getpid(), signal.SIGTERM)
            del o  # the signal arrives while a finalizer runs: only the flag is raised
            for _ in range(100):
                sum(range(1000))  # the handler has run; nothing was raised yet
            with pytest.raises(KeyboardInterrupt):
                interrupts.check()
            interrupts.check()  # answered once, not twice
            os.kill(os.getpid(), signal.SIGTERM)
            sum(range(1000))
        # outside a polled loop the signal raises at once ...
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):
                sum(range(1000))
        # ... and leaves nothing behind: a later polled loop (another run in this process) is not interrupted
        with interrupts.polled():
            interrupts.check()
    finally:
        restore()
    assert signal.getsignal(signal.SIGTERM) is not interrupts._handler


def test_a_planted_lock_file_link_or_fifo_is_refused_and_its_target_untouched(small_data, tmp_path, cdrb):
    """A symlink planted as an output's lock file (``.NAME.lock``) used to be followed: its target was truncated to
    the writer's pid. Now the run exits 2 naming the lock file, and the target keeps its content; a FIFO there is
    refused the same way (no hang)."""
    import os

    demos, _ = small_data
    precious = tmp_path / "p.txt"
    precious.write_text("precious\n")
    (tmp_path / ".b.h5.lock").symlink_to(precious)
    r = cdrb("cluster", demos.path, "--k", "5", "--out", tmp_path / "b.h5", timeout=60)
    assert r.returncode == 2 and ".b.h5.lock" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert precious.read_text() == "precious\n" and not (tmp_path / "b.h5").exists()
    os.mkfifo(tmp_path / ".c.h5.lock")
    r = cdrb("cluster", demos.path, "--k", "5", "--out", tmp_path / "c.h5", timeout=30)
    assert r.returncode == 2 and ".c.h5.lock" in r.stderr and not (tmp_path / "c.h5").exists()


def test_a_deleted_input_made_again_by_the_same_command_is_the_same_input(tmp_path, cdrb):
    """Demos deleted and collected again (new timestamps, so other bytes) are the same input of the buffer and the
    model made from them: both stay up to date. Demos of another seed are other inputs."""
    from tests.test_train import TINY_FLAGS

    demos, buffer, model = tmp_path / "d.h5", tmp_path / "b.h5", tmp_path / "m.h5"
    collect = ("collect", "maze-tight", "-n", "6", "--seed", "3", "--out", demos)
    cluster = ("cluster", demos, "--k", "20", "--out", buffer)
    train = ("train", demos, "--buffer", buffer, "--method", "cdrb", *TINY_FLAGS, "--steps", "4", "--out", model)
    for args in (collect, cluster, train):
        assert cdrb(*args).returncode == 0
    first = demos.read_bytes()
    demos.unlink()
    time.sleep(1.1)  # another created_at
    assert cdrb(*collect).returncode == 0
    assert demos.read_bytes() != first  # other bytes ...
    for args in (cluster, train):  # ... the same data: nothing to redo
        r = cdrb(*args)
        assert r.returncode == 0 and "up to date" in r.stderr, r.stderr
    other = tmp_path / "d2.h5"
    assert cdrb("collect", "maze-tight", "-n", "6", "--seed", "4", "--out", other).returncode == 0
    shutil.copyfile(other, demos)
    r = cdrb(*cluster)
    assert r.returncode == 2 and "made from other inputs" in r.stderr


def test_every_text_input_goes_through_the_guarded_reader(tmp_path, cdrb):
    """Maps, settings files and grid files: a link to a file outside its folder, a FIFO and a binary file are each
    refused with one line naming the flag, before any work and without blocking; a link inside the folder is read."""
    maps = tmp_path / "maps"
    maps.mkdir()
    outside = tmp_path / "secret.txt"
    outside.write_text("# not a map\n")
    (maps / "escape.txt").symlink_to(outside)
    os.mkfifo(maps / "fifo.txt")
    (maps / "binary.txt").write_bytes(b"\xff\xfe\x00#")
    (maps / "real.txt").write_text("#####\n#S.G#\n#####\n")
    (maps / "alias.txt").symlink_to(maps / "real.txt")
    link_out = "a link to a file outside its folder"
    cases = [
        (("collect", "--maze-map", maps / "escape.txt", "-n", "1"), "--maze-map", link_out),
        (("collect", "--maze-map", maps / "fifo.txt", "-n", "1"), "--maze-map", "not a regular file"),
        (("collect", "--maze-map", maps / "binary.txt", "-n", "1"), "--maze-map", "not a text file"),
        (("train", "x.h5", "--config", maps / "escape.txt"), "--config", link_out),
        (("train", "x.h5", "--config", maps / "fifo.txt"), "--config", "not a regular file"),
        (("grid", maps / "escape.txt"), "", "not a grid file"),
    ]
    for args, flag, needle in cases:
        t0 = time.time()
        r = cdrb(*args, "--out", tmp_path / "never.h5") if args[0] != "grid" else cdrb(*args)
        assert time.time() - t0 < 10
        assert r.returncode == 2, (args, r.stderr)
        assert needle in r.stderr and flag in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "never.h5").exists()
    from cdrb_cli.envs.pointmaze.maze import load_map_file

    assert load_map_file(maps / "alias.txt").rows == ["#####", "#S.G#", "#####"]


def test_a_write_that_does_not_fit_is_one_line_and_leaves_nothing(tmp_path):
    """A disk that fills up mid-write (here the process's file-size limit: for HDF5 the same failure as a full disk,
    a write refused partway) is one line naming the file, and neither the output nor a temporary file is left. HDF5
    writing to the disk itself fails in its own flush and can crash the interpreter as it closes the file."""
    import resource

    src = write(tmp_path / "eval.h5", "eval", n=40)
    limit = src.stat().st_size // 2

    def limited():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead of a signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    out = tmp_path / "out"
    out.mkdir()
    # an artifact written by the library (a model: HDF5 datasets), a copied file (an eval without plans), a text file
    library = (
        "import sys\nfrom cdrb_cli.errors import BadInput\nfrom tests.factories import write\n"
        "try:\n    write(sys.argv[1], 'model', n=40)\n"
        "except BadInput as e:\n    print(f'error: {e}', file=sys.stderr)\n    sys.exit(2)\n"
    )
    runs = [
        ["-c", library, out / "model.h5"],
        ["-m", "cdrb_cli", "export", src, "--compact", out / "copy.h5"],
        ["-m", "cdrb_cli", "report", src, "--per-seed", "--out", out / "report.md"],
    ]
    for args in runs:
        r = subprocess.run(
            [sys.executable, *map(str, args)], capture_output=True, text=True, preexec_fn=limited, timeout=300,
            cwd=Path(__file__).resolve().parent.parent, env={**os.environ, "OMP_NUM_THREADS": "1"},
        )  # fmt: skip
        if args[-1].name == "report.md" and r.returncode == 0:
            continue  # the report fit under the limit: nothing to check
        assert r.returncode == 2, (args[-1], r.returncode, r.stderr[-2000:])
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and "file too large while writing it; nothing was written" in lines[0], r.stderr
        assert str(args[-1]) in lines[0] and "ulimit -f" in lines[0]
        assert list(out.iterdir()) == [], list(out.iterdir())
