"""Minari interop: datasets made here with Minari's own API import, train, plan and evaluate; exported
cdrb demos open with `minari.load_dataset`; import(export(demos)) keeps every array; bad datasets are one-line
errors. No network: every dataset lives under a temporary MINARI_DATASETS_PATH."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.files import temp_folder_at
from tests.conftest import call_cdrb

minari = pytest.importorskip("minari")


@pytest.fixture
def datasets(tmp_path, monkeypatch):
    root = tmp_path / "minari"
    monkeypatch.setenv("MINARI_DATASETS_PATH", str(root))
    return root


def _cli(*args, cwd=None):
    return call_cdrb(*args, cwd=cwd, env={"OMP_NUM_THREADS": "1"})


def _make_dataset(dataset_id: str, gym_id: str, episodes: int = 4, steps: int = 30, seed: int = 0, **kwargs):
    """A dataset written by Minari's own API from random actions in a gymnasium(-robotics) environment."""
    import gymnasium as gym
    from minari.data_collector.episode_buffer import EpisodeBuffer

    from cdrb_cli.envs.pointmaze.env import import_gymnasium_robotics

    import_gymnasium_robotics()
    # the maze XML gymnasium-robotics writes (here, and when Minari makes the env again) goes to a folder removed after
    with tempfile.TemporaryDirectory() as own, temp_folder_at(own):
        env = gym.make(gym_id, **kwargs)
        rng = np.random.default_rng(seed)
        buffers = []
        for e in range(episodes):
            obs, _ = env.reset(seed=seed + e)
            seen, acts = [obs], []
            for _ in range(steps):
                a = rng.uniform(-1, 1, size=env.action_space.shape).astype(np.float32)
                obs, *_ = env.step(a)
                seen.append(obs)
                acts.append(a)
            stacked = {k: np.array([o[k] for o in seen]) for k in seen[0]} if isinstance(obs, dict) else np.array(seen)
            buffers.append(
                EpisodeBuffer(
                    id=e,
                    seed=seed + e,
                    observations=stacked,
                    actions=np.array(acts),
                    rewards=[0.0] * steps,
                    terminations=[False] * steps,
                    truncations=[False] * (steps - 1) + [True],
                )
            )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            minari.create_dataset_from_buffers(
                dataset_id, buffers, env=env.spec, algorithm_name="random", data_format="hdf5"
            )
        env.close()
    return buffers


OWN_MAP = [[1, 1, 1, 1, 1], [1, 0, 0, 0, 1], [1, 0, 1, 0, 1], [1, 0, 0, 0, 1], [1, 1, 1, 1, 1]]


def test_a_pointmaze_dataset_imports_trains_plans_and_evaluates(tmp_path, datasets):
    buffers = _make_dataset("test/ring/random-v0", "PointMaze_UMaze-v3", maze_map=OWN_MAP, continuing_task=True)
    r = _cli("import", "minari", "test/ring/random-v0", "--out", tmp_path / "demos.h5")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(tmp_path / "demos.h5")
    demos = artifacts.load(tmp_path / "demos.h5", "demos")
    spec = demos.manifest.env
    assert spec.id == "map:test-ring-random-v0" and spec.scene.maze.rows[2] == "#C#C#"
    src = demos.manifest.config.expert
    assert (
        src.kind == "minari-dataset"
        and src.dataset_id == "test/ring/random-v0"
        and src.gym_env_id == "PointMaze_UMaze-v3"
    )
    assert {"data/main_data.hdf5", "data/metadata.json"} <= set(src.files)
    assert all(len(h) == 64 for h in src.files.values())
    # every step of every episode, in order; actions get the zero last row of cdrb's layout
    assert demos.n_episodes == 4 and list(demos.episode_length) == [31] * 4
    S, A = demos.episode(2)
    np.testing.assert_allclose(S, buffers[2].observations["observation"], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(A[:-1], buffers[2].actions, rtol=1e-6)
    assert (A[-1] == 0).all()
    assert list(demos.episode_seed) == [0, 1, 2, 3]
    info = _cli("inspect", tmp_path / "demos.h5")
    assert "Minari dataset test/ring/random-v0" in info.stdout
    # the imported data feeds the usual pipeline
    tiny = ["--steps", "10", "--set", "horizon=16", "--set", "stride=4", "--set", "batch_size=4"]
    tiny += ["--set", "net.dim=8", "--set", "net.dim_mults=1,2", "--set", "method.diffusion_steps=4"]
    assert _cli("cluster", tmp_path / "demos.h5", "--k", "20", "--out", tmp_path / "buf.h5").returncode == 0
    r = _cli(
        "train",
        tmp_path / "demos.h5",
        "--buffer",
        tmp_path / "buf.h5",
        "--method",
        "cdrb",
        *tiny,
        "--out",
        tmp_path / "m.h5",
        "--device",
        "cpu",
    )
    assert r.returncode == 0, r.stderr
    r = _cli("plan", tmp_path / "m.h5", "--pairs", "2", "--out", tmp_path / "p.h5", "--device", "cpu")
    assert r.returncode == 0, r.stderr
    r = _cli(
        "eval", tmp_path / "m.h5", "--seeds", "0", "--episodes", "2", "--out", tmp_path / "e.h5", "--device", "cpu"
    )
    assert r.returncode == 0, r.stderr
    assert artifacts.load(tmp_path / "e.h5", "eval").manifest.env.id == spec.id


def test_the_stock_maps_and_fetch_tasks_are_recognised(tmp_path, datasets):
    from cdrb_cli.stages.minari_io import import_minari

    _make_dataset("test/umaze-v1", "PointMaze_UMaze-v3", episodes=2, steps=5)  # the registered default map
    assert import_minari("test/umaze-v1", tmp_path / "u.h5").manifest.env.id == "umaze"
    _make_dataset("test/push-v0", "FetchPush-v4", episodes=2, steps=5)
    demos = import_minari("test/push-v0", tmp_path / "p.h5")
    assert demos.manifest.env.id == "fetch-push" and demos.observations.shape[1] == 25
    # by folder as well as by id
    folder = datasets / "test" / "push-v0"
    assert import_minari(str(folder), tmp_path / "p2.h5").manifest.env.id == "fetch-push"


@pytest.mark.parametrize("env", ["maze-tight", "fetch-push-obstacle"])
def test_export_opens_with_minari_and_import_of_export_is_the_same_demos(tmp_path, datasets, env, monkeypatch):
    r = _cli("collect", env, "-n", "3", "--seed", "1", "--workers", "1", "--out", tmp_path / "d.h5")
    assert r.returncode == 0, r.stderr
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    r = _cli("export", tmp_path / "d.h5", "--minari", "cdrb/demo")
    assert r.returncode == 0, r.stderr
    assert not list(scratch.iterdir())  # nothing left in the temp folder (a maze's XML, when Minari makes the env)
    assert Path(r.stdout.strip()) == datasets / "cdrb" / "demo-v0"
    ds = minari.load_dataset("cdrb/demo-v0")  # Minari's own reader
    assert ds.total_episodes == 3
    demos = artifacts.load(tmp_path / "d.h5", "demos")
    for e, ep in enumerate(ds.iterate_episodes()):
        S, A = demos.episode(e)
        assert ep.observations["observation"].shape == S.shape and ep.actions.shape == (len(S) - 1, A.shape[1])
        assert bool(ep.infos["success"].any()) == bool(demos.episode_success[e])
    if env == "maze-tight":
        assert ds.env_spec.id == "PointMaze_UMaze-v3" and ds.env_spec.kwargs["continuing_task"] is True
    else:  # walls no gymnasium registry has: no env_spec, the description names the cdrb environment
        assert ds.env_spec is None
    (tmp_path / "back.h5").write_text("my notes\n")  # not written over without --force
    r = _cli("import", "minari", "cdrb/demo-v0", "--out", tmp_path / "back.h5", "--seed", "1")
    assert r.returncode == 2 and "file exists" in r.stderr and (tmp_path / "back.h5").read_text() == "my notes\n"
    r = _cli("import", "minari", "cdrb/demo-v0", "--out", tmp_path / "back.h5", "--seed", "1", "--force")
    assert r.returncode == 0, r.stderr
    back = artifacts.load(tmp_path / "back.h5", "demos")
    assert back.manifest.env.id == env
    for key in (
        "steps/observations",
        "steps/actions",
        "steps/desired_goals",
        "episodes/start",
        "episodes/length",
        "episodes/seed",
        "episodes/success",
        "episodes/valid",
    ):
        np.testing.assert_array_equal(back.arrays[key], demos.arrays[key], err_msg=key)
    # a second export of the same name is refused unless forced
    r = _cli("export", tmp_path / "d.h5", "--minari", "cdrb/demo")
    assert r.returncode == 2 and "exists" in r.stderr and "--force" in r.stderr
    assert _cli("export", tmp_path / "d.h5", "--minari", "cdrb/demo", "--force").returncode == 0


def test_bad_datasets_are_one_line_errors(tmp_path, datasets):
    _make_dataset("test/pendulum-v0", "Pendulum-v1", episodes=1, steps=3)
    _make_dataset("test/umaze-v0", "PointMaze_UMaze-v3", episodes=1, steps=3)
    (tmp_path / "empty").mkdir()
    cases = [
        (["nobody/nothing-v0"], "cdrb never downloads"),
        ([tmp_path / "empty"], "not a Minari dataset folder"),
        (["test/pendulum-v0"], "no cdrb equivalent"),
        (["test/pendulum-v0", "--env", "maze"], "goal dict"),
        (["test/umaze-v0", "--env", "fetch-push"], "need (25,)"),
    ]
    for args, words in cases:
        r = _cli("import", "minari", *args, "--out", tmp_path / "x.h5")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and words in lines[0], (args, r.stderr)
        assert not (tmp_path / "x.h5").exists()
    r = _cli("collect", "maze-tight", "-n", "2", "--out", tmp_path / "d.h5")
    assert r.returncode == 0
    r = _cli("export", tmp_path / "d.h5", "--minari", "../escape")
    assert r.returncode == 2 and "not a dataset name" in r.stderr


def test_hostile_dataset_folders_are_refused_before_minari_reads_them(tmp_path, datasets):
    """A FIFO as the main data (which would hang the import), a link to a file outside the dataset (whose bytes
    would be read and hashed as the dataset's), a data file declaring 3 GB in a few KB, and a 2 MB metadata.json:
    each one line, exit 2, within seconds, nothing written."""
    import shutil
    import time

    import h5py

    _make_dataset("test/base-v0", "PointMaze_UMaze-v3", episodes=1, steps=3)
    base = datasets / "test" / "base-v0"

    def variant(name):
        folder = datasets / "test" / f"{name}-v0"
        shutil.copytree(base, folder)
        return folder, folder / "data" / "main_data.hdf5"

    folder, main = variant("fifo")
    main.unlink()
    os.mkfifo(main)
    folder, main = variant("link")
    (tmp_path / "secret.txt").write_text("not the dataset's")
    os.symlink(tmp_path / "secret.txt", folder / "data" / "extra.bin")
    folder, main = variant("bomb")
    with h5py.File(main, "a") as f:
        f.create_dataset("bomb", shape=(100_000_000, 4), dtype="f8")  # declared, never written: a sparse promise
    folder, main = variant("meta")
    meta = folder / "data" / "metadata.json"
    meta.write_text(meta.read_text()[:-1] + ', "pad": "' + "x" * (2 << 20) + '"}')
    # an episode count the data file does not hold: Minari would allocate by a billion, or drop episodes silently
    for name, count in [("many", 10**9), ("fewer", 0)]:
        folder, main = variant(name)
        meta = folder / "data" / "metadata.json"
        meta.write_text(re.sub(r'"total_episodes": *\d+', f'"total_episodes": {count}', meta.read_text()))
    cases = [("fifo", "not a regular file"), ("link", "is a link"), ("bomb", "declare"), ("meta", "larger than")]
    cases += [("many", "declares 1000000000 episodes, but main_data.hdf5 holds 1"), ("fewer", "declares 0 episodes")]
    for name, words in cases:
        t = time.time()
        r = _cli("import", "minari", f"test/{name}-v0", "--out", tmp_path / "x.h5")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and words in lines[0], (name, r.stderr[-800:])
        assert time.time() - t < 30 and not (tmp_path / "x.h5").exists()
    main = base / "data" / "main_data.hdf5"
    before = main.read_bytes()
    r = _cli("import", "minari", "test/base-v0", "--out", main, "--force")  # onto its own data file
    assert r.returncode == 2 and "inside the dataset" in r.stderr and main.read_bytes() == before
    r = _cli("import", "minari", "test/base-v0", "--out", tmp_path / "ok.h5")  # the untouched dataset still imports
    assert r.returncode == 0, r.stderr[-800:]


def test_export_never_deletes_or_races_another_dataset(tmp_path, datasets):
    """Two exports of one name at once: one writes, the other stops (no silent replace); a name nested inside an
    existing dataset is refused, and so is --force on a dataset holding another; a 300-character name or a --root
    that is a file is one line before any dataset is written."""
    r = _cli("collect", "maze-tight", "-n", "4", "--out", tmp_path / "d.h5")
    assert r.returncode == 0
    env = dict(os.environ, OMP_NUM_THREADS="1")
    cmd = [sys.executable, "-m", "cdrb_cli", "export", str(tmp_path / "d.h5"), "--minari", "race/same"]
    procs = [subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for _ in "ab"]
    results = [(p.wait(timeout=300), p.stderr.read()) for p in procs]
    assert sorted(rc for rc, _ in results) == [0, 2], results
    loser = next(err for rc, err in results if rc == 2)
    assert "another cdrb run" in loser or "exists" in loser
    assert (datasets / "race" / "same-v0" / "data" / "metadata.json").is_file()
    r = _cli("export", tmp_path / "d.h5", "--minari", "race/same-v0/inner")
    assert r.returncode == 2 and "inside the dataset" in r.stderr
    os.makedirs(datasets / "outer-v0" / "data")
    (datasets / "outer-v0" / "data" / "metadata.json").write_text("{}")
    nested = datasets / "outer-v0" / "sub" / "x-v0" / "data"
    os.makedirs(nested)
    (nested / "metadata.json").write_text("{}")
    r = _cli("export", tmp_path / "d.h5", "--minari", "outer", "--force")
    assert r.returncode == 2 and "holds other datasets" in r.stderr and (nested / "metadata.json").exists()
    for bad in ("n" * 300, "cdrb/.", "cdrb/..", "./x", "cdrb/..-v1"):
        r = _cli("export", tmp_path / "d.h5", "--minari", bad)
        assert r.returncode == 2 and "not a dataset name" in r.stderr and r.stderr.count("\n") == 1, (bad, r.stderr)
    (tmp_path / "afile").write_text("x")
    r = _cli("export", tmp_path / "d.h5", "--minari", "ok", "--root", tmp_path / "afile")
    assert r.returncode == 2 and "--root" in r.stderr and (tmp_path / "afile").read_text() == "x"
    # a folder below a file, a link loop, a folder no file can be made in: one line naming --root or the variable
    os.symlink(tmp_path / "loop-b", tmp_path / "loop-a")
    os.symlink(tmp_path / "loop-a", tmp_path / "loop-b")
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    for root, needle in (
        (tmp_path / "afile" / "x", "is not a folder"),
        (tmp_path / "loop-a", "cannot be followed"),
        *([(locked / "x", "cannot write in")] if os.geteuid() != 0 else []),
        ("/proc/no-such", "cannot write in"),
    ):
        r = _cli("export", tmp_path / "d.h5", "--minari", "ok", "--root", root)
        assert r.returncode == 2 and f"--root {root}" in r.stderr and needle in r.stderr, (root, r.stderr)
        assert r.stderr.count("\n") == 1
    r = call_cdrb("export", tmp_path / "d.h5", "--minari", "ok", env={"MINARI_DATASETS_PATH": str(tmp_path / "loop-b")})
    assert r.returncode == 2 and r.stderr.startswith("error: MINARI_DATASETS_PATH"), r.stderr
    # --force on the dataset folder that holds the demos being exported would delete them
    os.makedirs(datasets / "mine-v0")
    (datasets / "mine-v0" / "d.h5").write_bytes((tmp_path / "d.h5").read_bytes())
    r = _cli("export", datasets / "mine-v0" / "d.h5", "--minari", "mine", "--force")
    assert r.returncode == 2 and "an input of this command" in r.stderr and r.stderr.count("\n") == 1, r.stderr
    assert (datasets / "mine-v0" / "d.h5").read_bytes() == (tmp_path / "d.h5").read_bytes()


def test_a_relative_root_is_the_current_folders(tmp_path, datasets, monkeypatch):
    """--root given relative to the current folder: the dataset lands there (gymnasium would read a relative XML
    path as one in its own assets), and a failed export leaves no empty folders."""
    r = _cli("collect", "maze-tight", "-n", "2", "--out", tmp_path / "d.h5")
    assert r.returncode == 0, r.stderr
    r = _cli("export", tmp_path / "d.h5", "--minari", "cdrb/rel", "--root", "rel", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()) == tmp_path / "rel" / "cdrb" / "rel-v0"
    assert (tmp_path / "rel" / "cdrb" / "rel-v0" / "data" / "metadata.json").is_file()
    from cdrb_cli.stages import minari_io

    def broken(*args):
        raise OSError("disk full")

    monkeypatch.setattr(minari_io, "_write_dataset", broken)
    with pytest.raises(OSError, match="disk full"):
        minari_io.export_minari(artifacts.load(tmp_path / "d.h5", "demos"), "a/b", root=tmp_path / "new" / "root")
    assert not (tmp_path / "new").exists()


def test_damaged_episodes_are_one_line_naming_the_dataset(tmp_path, datasets):
    """NaN or values no artifact holds in the states, fewer actions than steps, a missing array, text where
    numbers belong, in an otherwise valid dataset: one line naming the dataset and the episode, exit 2, nothing
    written."""
    import shutil

    import h5py

    _make_dataset("test/good-v0", "PointMaze_UMaze-v3", episodes=1, steps=5)
    good = datasets / "test" / "good-v0"
    damages = ("nan", "actions", "huge", "no-actions", "text")
    for name, damage in zip(("nan", "short", "huge", "noacts", "text"), damages, strict=True):
        folder = datasets / "test" / f"{name}-v0"
        shutil.copytree(good, folder)
        with h5py.File(folder / "data" / "main_data.hdf5", "a") as f:
            ep = f["episode_0"]
            if damage == "no-actions":
                del ep["actions"]
            elif damage == "text":
                n = len(ep["observations/observation"])
                del ep["observations/observation"]
                ep["observations"].create_dataset("observation", data=np.array([b"abcd"] * n))
            elif damage in ("nan", "huge"):
                obs = ep["observations/observation"][()]
                obs[2, 0] = np.nan if damage == "nan" else 1e30
                ep["observations/observation"][...] = obs
            else:
                acts = ep["actions"][()]
                del ep["actions"]
                ep.create_dataset("actions", data=acts[:-2])
        r = _cli("import", "minari", f"test/{name}-v0", "--out", tmp_path / "x.h5")
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and f"test/{name}-v0: episode 0" in lines[0], r.stderr[-800:]
        assert not (tmp_path / "x.h5").exists()
