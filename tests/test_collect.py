"""The scripted expert and `cdrb collect`."""

from __future__ import annotations

import os

import numpy as np
import pytest

from cdrb_cli import artifacts
from cdrb_cli.envs.family import Episode
from cdrb_cli.envs.geometry import in_boxes
from cdrb_cli.envs.pointmaze.env import PointMaze
from cdrb_cli.envs.pointmaze.expert import MazeExpert, PlannerExpertConfig
from cdrb_cli.envs.registry import make_spec
from cdrb_cli.stages.collect import collect, collect_config, rollout


@pytest.mark.parametrize("env_id", ["maze", "maze-tight"])
def test_expert_succeeds_without_touching_walls(env_id):
    spec = make_spec(env_id)
    env, expert = PointMaze(spec), MazeExpert(spec, PlannerExpertConfig())
    rng = np.random.default_rng(1)
    lengths = []
    for ep in range(40):
        s, g = env.geometry.draw_start_goal(rng)
        S, A, goal, ok = rollout(env, expert, spec, Episode(1000 + ep, tuple(s), tuple(g)), spec.episode_limit)
        assert ok, f"episode {ep} failed"
        assert not in_boxes(S, spec.obstacles).any()
        assert np.linalg.norm(S[-1, :2] - goal) < 0.05 and np.linalg.norm(S[-1, 2:]) < 0.1  # comes to rest
        assert np.all(np.abs(A) <= 1.0)
        lengths.append(len(S))
    # every demo fits in one plan of the default horizon
    assert max(lengths) <= spec.horizon * spec.plan_stride


def test_collect_artifact_and_multimodality(tmp_path):
    spec = make_spec("maze-tight")
    cfg = collect_config(spec, episodes=120, seed=3)
    demos = collect(spec, cfg, tmp_path / "d.h5")
    s = demos.manifest.summary
    assert s.success_rate == 1.0 and s.states_in_walls == 0
    assert s.train_episodes + s.valid_episodes == 120 and s.valid_episodes == 12
    # episodes index the flat arrays exactly
    assert demos.episode_start[0] == 0
    assert (demos.episode_start[1:] == np.cumsum(demos.episode_length)[:-1]).all()
    assert demos.observations.shape[0] == demos.episode_length.sum()
    # each goal is reached through more than one gap (the data is multimodal)
    for goal, routes in s.routes.items():
        assert len([k for k, v in routes.items() if v > 0]) >= 2, (goal, routes)
    # the same seed gives the same data
    again = collect(spec, cfg, tmp_path / "d2.h5")
    np.testing.assert_array_equal(again.observations, demos.observations)
    np.testing.assert_array_equal(again.episode_seed, demos.episode_seed)


def test_cli_collect_custom_map_end_to_end(tmp_path, cdrb):
    m = tmp_path / "corridor.txt"
    m.write_text("#######\n#S...G#\n#.###.#\n#.....#\n#######\n")
    out, png = tmp_path / "c.h5", tmp_path / "c.png"
    r = cdrb("collect", "--maze-map", m, "-n", "20", "--out", out, "--plot", png, "--seed", "4")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(out)  # stdout carries only the path
    assert png.stat().st_size > 1000
    demos = artifacts.load(out, "demos")
    assert demos.manifest.env.id == "map:corridor" and demos.manifest.env.scene.maze.rows[1] == "#S...G#"
    assert demos.manifest.summary.success_rate == 1.0 and demos.manifest.summary.states_in_walls == 0
    # re-running the same command is a no-op; a different command refuses to overwrite
    again = cdrb("collect", "--maze-map", m, "-n", "20", "--out", out, "--seed", "4")
    assert again.returncode == 0 and "up to date" in again.stderr
    other = cdrb("collect", "--maze-map", m, "-n", "21", "--out", out, "--seed", "4")
    assert other.returncode == 2 and "--force" in other.stderr


def test_cli_collect_bad_inputs(tmp_path, cdrb):
    bad = tmp_path / "bad.txt"
    bad.write_text("#####\n#S.G#\n###\n")
    fifo = tmp_path / "fifo.txt"
    os.mkfifo(fifo)  # reading it would hang
    huge = tmp_path / "huge.txt"
    huge.write_text("#" * (2 << 20))
    cases = [
        (("collect", "--maze-map", bad, "-n", "2"), "ragged"),
        (("collect", "moon", "-n", "2"), "unknown environment"),
        (("collect", "maze", "-n", "0"), "--episodes"),
        (("collect", "maze", "--expert", "sac", "-n", "2"), "--policy"),
        (("collect", "maze", "--expert", "magic", "-n", "2"), "--expert"),
        (("collect", "maze", "-n", "2", "--out", tmp_path / "no" / "d.h5"), "does not exist"),
        (("collect", "maze", "-n", "2000000"), "--episodes"),
        (("collect", "--maze-map", "/dev/zero", "-n", "2"), "not a regular file"),
        (("collect", "--maze-map", fifo, "-n", "2"), "not a regular file"),
        (("collect", "--maze-map", huge, "-n", "2"), "larger than 1 MiB"),
        (("collect", "maze", "-n", "2", "--workers", str(2 * (os.cpu_count() or 1) + 1)), "--workers"),
        (("collect", "maze", "--expert", "sac", "--policy", fifo, "-n", "2"), "--policy"),  # a FIFO: no read, no hang
        (("collect", "maze", "--expert", "sac", "--policy", bad, "-n", "2"), "not a stable-baselines3"),
        (("collect", "maze", "-n", "2", "--valid-fraction", "0.9"), "none is left to train on"),
        (("collect", "maze", "-n", "40", "--valid-fraction", "1"), "'--valid-fraction': 1 is not a share in [0, 1)"),
    ]
    for args, needle in cases:
        r = cdrb(*args, cwd=tmp_path)
        assert r.returncode == 2, (args, r.stderr)
        assert needle in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
        assert r.stdout == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.txt", "fifo.txt", "huge.txt"]  # nothing written


def test_sac_expert_train_and_collect_tiny_budget(tmp_path, cdrb, monkeypatch):
    """The SB3 SAC+HER path end to end on a tiny budget (a useful expert needs ~1M steps: docs/environments.md)."""
    import tempfile

    policy = tmp_path / "expert.zip"
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))  # SB3's default logger makes a folder there
    r = cdrb("expert", "train", "umaze", "--steps", "400", "--out", policy, "--seed", "1")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(policy) and policy.stat().st_size > 0
    assert not list(scratch.glob("SB3-*"))  # no log folder left behind
    out = tmp_path / "sac.h5"
    r = cdrb("collect", "umaze", "--expert", "sac", "--policy", policy, "-n", "2", "--out", out)
    assert r.returncode == 0, r.stderr
    demos = artifacts.load(out, "demos")
    cfg = demos.manifest.config.expert
    assert cfg.kind == "sac" and cfg.policy_sha256 == artifacts.sha256_file(policy)
    assert demos.n_episodes == 2 and demos.observations.shape[1] == 4
    # a file that is not an SB3 zip is refused with exit code 2
    r = cdrb("collect", "umaze", "--expert", "sac", "--policy", out, "-n", "2", "--out", tmp_path / "x.h5")
    assert r.returncode == 2 and "not a stable-baselines3" in r.stderr
    # a zip whose pickled entries would run code: nothing of it runs (replaced, or refused when unknown)
    _malicious_zips_run_nothing(policy, tmp_path, cdrb)


class _Payload:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (open, (self.marker, "w"))  # unpickling it creates the marker file


def _malicious_zips_run_nothing(policy, tmp_path, cdrb):
    import base64
    import json
    import pickle
    import zipfile

    marker = tmp_path / "pwned"
    evil = {":type:": "<class 'x'>", ":serialized:": base64.b64encode(pickle.dumps(_Payload(str(marker)))).decode()}
    for key, needle in (("observation_space", None), ("lr_schedule", None), ("surprise", "pickled entries")):
        bad = tmp_path / f"evil-{key}.zip"
        with zipfile.ZipFile(policy) as src, zipfile.ZipFile(bad, "w") as dst:
            for item in src.namelist():
                content = src.read(item)
                if item == "data":
                    data = json.loads(content)
                    data[key] = evil
                    content = json.dumps(data).encode()
                dst.writestr(item, content)
        r = cdrb("collect", "umaze", "--expert", "sac", "--policy", bad, "-n", "1", "--out", tmp_path / f"{key}.h5")
        assert not marker.exists(), f"the pickle in {key} ran"
        if needle is None:
            assert r.returncode == 0, r.stderr  # the replaced entry was never read
        else:
            assert r.returncode == 2 and needle in r.stderr


def test_names_from_files_are_printed_as_plain_text(tmp_path, cdrb):
    """Paths and names that look like rich markup or hold terminal escapes neither break a run nor reach the
    terminal raw."""
    m = tmp_path / "x\x1b[31m.txt"
    m.write_text("#######\n#S...G#\n#######\n")
    folder = tmp_path / "[" / "bold]"  # a picture path containing the markup closing tag "[/bold]"
    folder.mkdir(parents=True)
    r = cdrb("collect", "--maze-map", m, "-n", "2", "--out", tmp_path / "d.h5", "--plot", folder / "p.png")
    assert r.returncode == 0, r.stderr
    assert "map:x?[31m" in r.stderr and "\x1b" not in r.stderr and "[/bold]/p.png" in r.stderr


def test_an_out_path_that_is_not_utf8_works_and_is_recorded_readably(tmp_path):
    """POSIX paths are bytes: one that is not UTF-8 is written as given, echoed byte for byte on stdout, and
    recorded in the manifest with U+FFFD in place of the bad byte (a JSON manifest holds only Unicode)."""
    import subprocess
    import sys

    out = os.fsencode(tmp_path) + b"/d\xff.h5"
    r = subprocess.run(
        [sys.executable.encode(), b"-m", b"cdrb_cli", b"collect", b"maze", b"-n", b"2", b"--out", out],
        capture_output=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == out
    a = artifacts.load(os.fsdecode(out))
    assert "\ufffd" in " ".join(a.manifest.argv)


def test_parallel_collect_gives_the_same_demos(tmp_path, cdrb):
    """`cdrb collect --workers 2` (episodes rolled out in two spawned processes, through the real CLI entry point)
    writes the same demos, array for array, as one process; the worker count is not part of the config."""
    from cdrb_cli.stages.collect import collect_workers

    spec = make_spec("fetch-push-obstacle")
    serial = collect(spec, collect_config(spec, 45, seed=3), tmp_path / "one.h5", workers=1)
    r = cdrb("collect", "fetch-push-obstacle", "-n", 45, "--seed", 3, "--workers", 2, "--out", tmp_path / "two.h5")
    assert r.returncode == 0, r.stderr
    parallel = artifacts.load(tmp_path / "two.h5", "demos")
    assert parallel.manifest.config == serial.manifest.config
    assert serial.arrays.keys() == parallel.arrays.keys()
    for key in serial.arrays:
        np.testing.assert_array_equal(parallel.arrays[key], serial.arrays[key], err_msg=key)
    s, p = serial.manifest.summary, parallel.manifest.summary
    assert (s.success_rate, s.states_in_walls, s.routes) == (p.success_rate, p.states_in_walls, p.routes)
    # the default: one process per core, but never fewer than 100 episodes each
    assert collect_workers(150, None) == 1 and collect_workers(10_000, None) == min(os.cpu_count() or 1, 8)
    assert collect_workers(3, 16) == 3


def test_demos_that_start_anywhere(tmp_path, cdrb):
    """`--starts anywhere`: maze episodes start all over the free space, not only in the start region, the
    expert still reaches its goals without touching a wall, and the choice is recorded; the default keeps the
    protocol's starts; Fetch's start the gripper away from home; a name no family knows is refused in one line."""
    from cdrb_cli.envs.pointmaze.maze import MazeGeometry

    spec = make_spec("maze-tight")
    geom = MazeGeometry(spec.scene.maze)
    region = {tuple(c) for c in geom.start_cells.tolist()}

    def start_cells(demos):
        firsts = demos.arrays["steps/observations"][demos.arrays["episodes/start"], :2]
        return [tuple(c) for c in geom.xy_to_cell(firsts).tolist()]

    out = tmp_path / "any.h5"
    demos = collect(spec, collect_config(spec, 60, seed=0, starts="anywhere"), out)
    cells = start_cells(demos)
    assert sum(c not in region for c in cells) > len(cells) / 2
    assert demos.manifest.config.starts == "anywhere"
    assert demos.manifest.summary.success_rate >= 0.95 and demos.manifest.summary.states_in_walls == 0
    usual = collect(spec, collect_config(spec, 30, seed=0), tmp_path / "usual.h5")
    assert all(c in region for c in start_cells(usual)) and usual.manifest.config.starts == "protocol"
    r = cdrb("collect", "fetch-reach", "-n", "2", "--starts", "everywhere", "--out", tmp_path / "f.h5")
    assert r.returncode == 2 and "--starts 'everywhere'" in r.stderr and r.stderr.count("\n") == 1
    assert "protocol, anywhere" in r.stderr and not (tmp_path / "f.h5").exists()
    # Fetch: the gripper starts anywhere in the workspace in every other episode, at home in the others
    fetch = make_spec("fetch-reach-obstacle")
    demos = collect(fetch, collect_config(fetch, 4, seed=0, starts="protocol+anywhere"), tmp_path / "f.h5")
    grips = demos.arrays["steps/observations"][demos.arrays["episodes/start"], :3]
    away = np.linalg.norm(grips - np.array(fetch.scene.home), axis=1) > 0.02
    assert away.tolist() == [False, True, False, True] and demos.manifest.summary.success_rate >= 0.75


def _children(pid: int) -> set[int]:
    """Every live descendant of ``pid`` (from /proc)."""
    import pathlib

    parents = {}
    for stat in pathlib.Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if fields[0] != "Z":
            parents[int(stat.parent.name)] = int(fields[1])
    out, frontier = set(), {pid}
    while frontier:
        frontier = {c for c, p in parents.items() if p in frontier} - out
        out |= frontier
    return out


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_a_collect_killed_with_sigkill_leaves_no_worker(tmp_path):
    """kill -9 of `cdrb collect --workers 2` once its workers run: within 5 s no process it started is left (the
    workers and multiprocessing's resource tracker used to stay, 120 MB each)."""
    import signal
    import subprocess
    import sys
    import time

    proc = subprocess.Popen(
        [sys.executable, "-m", "cdrb_cli", "collect", "fetch-pick-place-obstacle", "-n", "4000", "--workers", "2",
         "--out", str(tmp_path / "d.h5")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.time() + 120
    kids: set[int] = set()
    while time.time() < deadline and len(kids) < 2:
        time.sleep(0.2)
        kids = _children(proc.pid)
    assert len(kids) >= 2, "the workers never started"
    time.sleep(2)  # past the workers' start-up
    kids = _children(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    deadline = time.time() + 5
    while time.time() < deadline and any(os.path.exists(f"/proc/{k}") and _children(1) & {k} for k in kids):
        time.sleep(0.2)
    alive = [k for k in kids if os.path.exists(f"/proc/{k}") and open(f"/proc/{k}/stat").read().split()[2] != "Z"]
    assert not alive, f"left running: {alive}"
    assert not (tmp_path / "d.h5").exists()


def test_cluster_refuses_demos_without_train_episodes_and_a_one_state_buffer(small_data, tmp_path, cdrb):
    """The normalizer is fitted on the train episodes (with --split all too), and CDRB's balls grow to the buffer's
    diameter: demos with none, or a buffer of one state, are one-line errors, and nothing is written."""
    from tests import factories

    demos = factories.write(tmp_path / "held-out.h5", "demos")
    with factories.tampered(demos) as f:
        f["episodes/valid"][...] = True
        factories.edit_manifest(f, lambda m: m["summary"].update(train_episodes=0, valid_episodes=5))
    r = cdrb("cluster", demos, "--split", "all", "--k", "2", "--out", tmp_path / "b.h5")
    assert r.returncode == 2 and "no train episodes" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = cdrb("cluster", small_data[0].path, "--k", "1", "--out", tmp_path / "b.h5")
    assert r.returncode == 2 and "--k 1: " in r.stderr and "diameter 0" in r.stderr
    assert not (tmp_path / "b.h5").exists()
    # demos that never move: the data is what is wrong, whatever --k (none given here), and said once
    still = factories.write(tmp_path / "still.h5", "demos")
    with factories.tampered(still) as f:
        f["steps/observations"][...] = 0.5
    r = cdrb("cluster", still, "--out", tmp_path / "b.h5")
    assert r.returncode == 2 and "every demonstration state is the same point" in r.stderr, r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "--k" not in errors[0], r.stderr
    # more clusters than distinct states: said in cdrb's words, without scikit-learn's warning
    r = cdrb("cluster", small_data[0].path, "--k", "200", "--out", tmp_path / "b.h5")
    assert "ConvergenceWarning" not in r.stderr, r.stderr


def test_starts_anywhere_get_the_time_the_farthest_free_cell_needs(tmp_path):
    """A map whose start cell sits beside its goal at one end of a long corridor: the episode limit sized from its
    start cells is far too short for a start at the other end. Starting anywhere (collect and the eval protocol)
    gets the limit of the farthest free cell, so the expert reaches every goal; the stock maps keep the paper's
    limit; and a run from the start cells keeps the short one."""
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.stages.collect import limit_spec

    row = "#SG" + "." * 20 + "#"
    path = tmp_path / "corridor.txt"
    path.write_text("\n".join(["#" * len(row), row, "#" * len(row)]) + "\n")
    spec = make_spec(None, path)
    family = family_of(spec)
    far = family.protocol_spec(spec, "anywhere")
    assert spec.episode_limit == 150 and far.episode_limit == 700  # 1 cell vs 20, at 28 steps a cell + 120
    assert limit_spec(spec, "anywhere").episode_limit == limit_spec(spec, "protocol+anywhere").episode_limit == 700
    assert limit_spec(spec, "protocol") is spec
    stock = make_spec("maze-tight")
    assert family.protocol_spec(stock, "anywhere") == stock
    same = tmp_path / "same.txt"  # the stock map as a scene: maze-tight+same keeps the paper's limit too
    same.write_text("\n".join(stock.scene.maze.rows) + "\n")
    in_scene = family.with_map(stock, same)
    assert in_scene.id == "maze-tight+same" and family.protocol_spec(in_scene, "anywhere").episode_limit == 400
    demos = collect(spec, collect_config(spec, 12, seed=0, starts="anywhere"), tmp_path / "any.h5")
    assert demos.manifest.summary.success_rate == 1.0 and demos.manifest.summary.max_length > 150
