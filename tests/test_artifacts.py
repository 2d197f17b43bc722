"""The artifact format: round trips, validation order, and every kind of bad file."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from cdrb_cli import artifacts
from cdrb_cli.artifacts import core
from cdrb_cli.errors import ArtifactError, BadInput
from tests.factories import KINDS, build, tampered, write


def _same(a, b):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
        assert a[k].dtype == b[k].dtype, k


@pytest.mark.parametrize("kind", KINDS)
def test_round_trip_every_kind(tmp_path, kind):
    manifest, arrays = build(kind)
    path = artifacts.save(tmp_path / f"{kind}.h5", kind, manifest, arrays)
    art = artifacts.load(path)
    assert art.kind == kind and type(art) is artifacts.KINDS[kind]
    assert art.manifest == manifest
    _same(art.arrays, {k: np.asarray(v) for k, v in arrays.items()})
    assert len(art.sha256) == 64 and art.sha256 == artifacts.sha256_file(path)
    # the package-level API returns the same typed object
    import cdrb_cli

    assert type(cdrb_cli.load(path, kind=kind)) is type(art)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(kind=st.sampled_from(KINDS), n=st.integers(1, 12), seed=st.integers(0, 2**31 - 1))
def test_round_trip_property(tmp_path, kind, n, seed):
    manifest, arrays = build(kind, rng=np.random.default_rng(seed), n=n, seed=seed)
    path = artifacts.save(tmp_path / f"{kind}-{n}-{seed}.h5", kind, manifest, arrays)
    art = artifacts.load(path, kind)
    assert art.manifest == manifest
    assert art.manifest.seed == seed
    _same(art.arrays, {k: np.asarray(v) for k, v in arrays.items()})


def test_manifest_records_provenance(tmp_path):
    path = write(tmp_path / "d.h5", "demos")
    m = artifacts.load(path).manifest
    assert m.schema_version == artifacts.SCHEMA_VERSIONS["demos"]
    assert m.versions["cdrb"] and m.versions["numpy"] and m.versions["h5py"]
    assert m.env.id == "maze-tight" and m.created_at and m.argv


def test_parents_record_sha256(tmp_path):
    demos = artifacts.load(write(tmp_path / "d.h5", "demos"))
    manifest, arrays = build("buffer")
    manifest = manifest.model_copy(update={"parents": [artifacts.parent_ref(demos)]})
    buf = artifacts.load(artifacts.save(tmp_path / "b.h5", "buffer", manifest, arrays))
    assert buf.manifest.parents[0].sha256 == artifacts.sha256_file(tmp_path / "d.h5")
    assert buf.manifest.parents[0].kind == "demos"


# ------------------------------------------------------------------------------------------------ bad files
def _err(path, kind=None) -> str:
    with pytest.raises(ArtifactError) as info:
        artifacts.load(path, kind)
    msg = str(info.value)
    assert "\n" not in msg and str(path) in msg
    assert info.value.exit_code == 2
    return msg


def test_not_hdf5(tmp_path):
    p = tmp_path / "x.h5"
    p.write_bytes(b"this is not hdf5 at all" * 10)
    assert "not an HDF5 file" in _err(p)


def test_truncated(tmp_path):
    p = write(tmp_path / "d.h5", "demos", n=50)
    data = p.read_bytes()
    for cut in (len(data) // 2, len(data) - 100, 600):
        q = tmp_path / f"cut{cut}.h5"
        q.write_bytes(data[:cut])
        msg = _err(q)
        assert "truncated" in msg or "corrupt" in msg or "not an HDF5" in msg


def test_plain_hdf5_is_not_an_artifact(tmp_path):
    p = tmp_path / "plain.h5"
    with h5py.File(p, "w") as f:
        f["x"] = np.arange(3)
    assert "not a cdrb artifact (no cdrb_kind/cdrb_schema_version attributes)" in _err(p)


@pytest.mark.parametrize("name, value", [("cdrb_schema_version", 2.17), ("cdrb_kind", np.array([1, 2]))])
def test_a_marker_attribute_of_the_wrong_type_is_named(tmp_path, name, value):
    """The two marker attributes present but not text are said as such, not as missing."""
    p = write(tmp_path / "m.h5", "model")
    with h5py.File(p, "r+") as f:
        f.attrs[name] = value
    assert f"not a cdrb artifact ({name} not a text attribute)" in _err(p)


def test_wrong_kind(tmp_path):
    p = write(tmp_path / "b.h5", "buffer")
    msg = _err(p, "demos")
    assert "'buffer' artifact" in msg and "'demos'" in msg


def _rewrite_attr(p, name, value):
    with tampered(p) as f:
        f.attrs[name] = value


@pytest.mark.parametrize("value", [3e38, -1e30, 1e19])
def test_huge_finite_values_are_refused_on_read_and_write(tmp_path, value):
    """A re-signed file with a value far beyond anything cdrb writes (a buffer state of 3e38 would otherwise pass
    every check and break the ball sampler's KD-tree later) is one error naming the file and the dataset."""
    p = write(tmp_path / "b.h5", "buffer")
    with tampered(p) as f:
        points = f["points"][()]
        points[0, 0] = value
        del f["points"]
        f["points"] = points
    msg = _err(p)
    assert str(p) in msg and "/points" in msg and "beyond" in msg
    manifest, arrays = build("buffer")
    arrays["points"] = arrays["points"].copy()
    arrays["points"][0, 0] = value
    with pytest.raises(ValueError, match="beyond"):
        artifacts.save(tmp_path / "c.h5", "buffer", manifest, arrays)
    assert not (tmp_path / "c.h5").exists()


def test_newer_major_is_refused(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    _rewrite_attr(p, "cdrb_schema_version", "3.0")
    msg = _err(p)
    assert "newer" in msg and "upgrade cdrb" in msg


def _set_manifest(p, m, version):
    m["schema_version"] = version
    with tampered(p) as f:
        del f["manifest"]
        f["manifest"] = np.bytes_(json.dumps(m).encode())
        f.attrs["cdrb_schema_version"] = version


def test_newer_minor_with_unknown_field_is_read(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    with h5py.File(p, "r") as f:
        m = json.loads(f["manifest"][()].decode())
    m["future_field"] = {"x": 1}
    m["summary"]["future_stat"] = 3
    major, minor = artifacts.SCHEMA_VERSIONS["demos"].split(".")
    _set_manifest(p, m, f"{major}.{int(minor) + 1}")  # a newer minor version than this build writes
    art = artifacts.load(p)
    assert art.manifest.summary.episodes == 5
    # the same unknown field under the current minor version is an error
    _set_manifest(p, m, artifacts.SCHEMA_VERSIONS["demos"])
    msg = _err(p)
    assert "future_" in msg and "Extra inputs" in msg


def test_manifest_version_must_match_the_attribute(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    with tampered(p) as f:
        m = json.loads(f["manifest"][()].decode())
        m["schema_version"] = "2.9"
        del f["manifest"]
        f["manifest"] = np.bytes_(json.dumps(m).encode())
    assert "differs from cdrb_schema_version" in _err(p)


def test_older_major_without_a_migration_is_refused(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    _rewrite_attr(p, "cdrb_schema_version", "0.9")
    msg = _err(p)
    assert "older than this cdrb reads" in msg and "no migration" in msg


def test_invalid_manifest(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    with tampered(p) as f:
        m = json.loads(f["manifest"][()].decode())
        m["summary"]["episodes"] = "many"
        del f["manifest"]
        f["manifest"] = np.bytes_(json.dumps(m).encode())
    msg = _err(p)
    assert "summary.episodes" in msg


def test_manifest_not_json(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    with tampered(p) as f:
        del f["manifest"]
        f["manifest"] = np.bytes_(b"{not json")
    assert "not valid JSON" in _err(p)


@pytest.mark.parametrize("kind", KINDS)
def test_missing_dataset(tmp_path, kind):
    p = write(tmp_path / f"{kind}.h5", kind)
    manifest, arrays = build(kind)
    name = next(s.name for s in artifacts.KINDS[kind].datasets if s.required)
    with tampered(p) as f:
        del f[name]
    assert f"missing dataset /{name}" in _err(p)


def test_inconsistent_shapes(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    with tampered(p) as f:
        a = f["steps/actions"][()]
        del f["steps/actions"]
        f["steps/actions"] = a[:-1]
    assert "steps/actions" in _err(p)


def test_state_dimension_checked_against_env(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    with tampered(p) as f:
        o = f["steps/observations"][()]
        del f["steps/observations"]
        f["steps/observations"] = o[:, :3]
    assert "obs_dim" in _err(p)


def test_nan_in_data(tmp_path):
    p = write(tmp_path / "b.h5", "buffer")
    with tampered(p) as f:
        f["points"][0, 0] = np.nan
    assert "NaN" in _err(p)


def test_object_dtype_rejected(tmp_path):
    p = write(tmp_path / "b.h5", "buffer")
    with tampered(p) as f:
        f.create_dataset("evil", data=np.array([b"x", b"y"], dtype=object), dtype=h5py.string_dtype())
    assert "non-numeric dtype" in _err(p)


def test_huge_declared_shape_rejected_before_reading(tmp_path):
    p = write(tmp_path / "b.h5", "buffer")
    with tampered(p) as f:
        f.create_dataset("huge", shape=(10**6, 10**6), dtype="f4", chunks=(1, 1024))  # 4 TB declared, nothing stored
    msg = _err(p)
    assert "declare" in msg


def test_external_link_rejected(tmp_path):
    other = write(tmp_path / "other.h5", "buffer")
    p = write(tmp_path / "b.h5", "buffer")
    with tampered(p) as f:
        f["linked"] = h5py.ExternalLink(str(other), "/points")
    assert "link" in _err(p)


def test_missing_file_and_folder(tmp_path):
    with pytest.raises(BadInput, match="no such file"):
        artifacts.load(tmp_path / "absent.h5")
    with pytest.raises(BadInput, match="is a folder"):
        artifacts.load(tmp_path)


# ------------------------------------------------------------------------------------------------ atomic writes
def test_write_failure_leaves_previous_artifact(tmp_path):
    p = write(tmp_path / "d.h5", "demos", seed=1)
    before = p.read_bytes()
    manifest, arrays = build("demos", seed=2)
    arrays["steps/observations"] = arrays["steps/observations"].copy()
    arrays["steps/observations"][0, 0] = np.inf  # the writer refuses non-finite data mid-write
    with pytest.raises(ValueError):
        artifacts.save(p, "demos", manifest, arrays)
    assert p.read_bytes() == before
    assert [x.name for x in tmp_path.iterdir()] == ["d.h5"]  # no temp file left behind


def test_crash_between_write_and_rename_keeps_previous(tmp_path):
    p = write(tmp_path / "d.h5", "demos", seed=1)
    before = p.read_bytes()
    code = "from tests.factories import write; import sys; write(sys.argv[1], 'demos', seed=2, n=7)"
    env = dict(os.environ, CDRB_CRASH_BEFORE_RENAME="1")
    proc = subprocess.run([sys.executable, "-c", code, str(p)], env=env, cwd=os.getcwd(), capture_output=True)
    assert proc.returncode == 86  # the simulated crash
    assert p.read_bytes() == before
    assert artifacts.load(p).manifest.seed == 1
    leftovers = [x.name for x in tmp_path.iterdir() if x.name != "d.h5"]
    assert all(name.startswith(".d.h5.tmp-") for name in leftovers)


def _up_to_date(*args):
    return artifacts.existing(*args).up_to_date


def test_up_to_date_logic(tmp_path):
    demos = artifacts.load(write(tmp_path / "d.h5", "demos"))
    manifest, arrays = build("buffer")
    manifest = manifest.model_copy(update={"parents": [artifacts.parent_ref(demos)]})
    out = artifacts.save(tmp_path / "b.h5", "buffer", manifest, arrays)
    assert _up_to_date(out, "buffer", manifest.config, [demos])
    other_cfg = manifest.config.model_copy(update={"k": 7})
    assert not _up_to_date(out, "buffer", other_cfg, [demos])
    demos2 = artifacts.load(write(tmp_path / "d2.h5", "demos", seed=5))
    assert not _up_to_date(out, "buffer", manifest.config, [demos2])
    assert not _up_to_date(tmp_path / "missing.h5", "buffer", manifest.config, [demos])


def test_existing_is_the_one_rule_for_skip_and_resume(tmp_path):
    manifest, arrays = build("model")  # a finished model at step 10 of 10
    cfg = manifest.config
    out = artifacts.save(tmp_path / "m.h5", "model", manifest, arrays)
    assert artifacts.existing(out, "model", cfg).status == "up-to-date"
    assert artifacts.existing(out, "model", cfg.model_copy(update={"steps": 20})).status == "resumable"
    fewer = artifacts.existing(out, "model", cfg.model_copy(update={"steps": 5}))
    assert fewer.status == "different" and "past --steps" in fewer.reason
    assert artifacts.existing(out, "model", cfg.model_copy(update={"lr": 0.5})).status == "different"
    assert artifacts.existing(out, "model", cfg, [artifacts.load(write(tmp_path / "d.h5", "demos"))]).reason == (
        "it was made from other inputs"
    )
    state = manifest.state.model_copy(update={"finished": False, "step": 6})
    unfinished = artifacts.save(tmp_path / "u.h5", "model", manifest.model_copy(update={"state": state}), arrays)
    assert artifacts.existing(unfinished, "model", cfg).status == "resumable"
    (tmp_path / "junk.h5").write_bytes(b"not hdf5")
    assert artifacts.existing(tmp_path / "junk.h5", "model", cfg).status == "invalid"
    assert artifacts.existing(tmp_path / "none.h5", "model", cfg).status == "missing"


def test_virtual_and_external_storage_are_refused(tmp_path):
    """An 'artifact' whose dataset reads another file (external raw storage, or a virtual dataset) would leak
    that file's content and escape the artifact's sha256."""
    secret = tmp_path / "secret.bin"
    np.arange(10, dtype=np.float64).tofile(secret)
    external = write(tmp_path / "ext.h5", "eval")
    with tampered(external) as f:
        del f["episodes/final_distance"]
        f.create_dataset("episodes/final_distance", shape=(5,), dtype="f8", external=[(str(secret), 0, 40)])
    msg = _err(external)
    assert "outside the file" in msg and "final_distance" in msg
    virtual = write(tmp_path / "virt.h5", "eval")
    source = write(tmp_path / "src.h5", "eval")
    with tampered(virtual) as f:
        del f["episodes/final_distance"]
        layout = h5py.VirtualLayout(shape=(5,), dtype="f4")
        layout[:] = h5py.VirtualSource(str(source), "episodes/final_distance", shape=(5,))
        f.create_virtual_dataset("episodes/final_distance", layout)
    assert "outside the file" in _err(virtual)


@pytest.mark.parametrize(
    "kind, name, value, needle",
    [
        ("demos", "episodes/start", lambda a: a - 1, "do not tile the steps"),
        ("demos", "episodes/length", lambda a: a + 1, "do not tile the steps"),
        ("demos", "episodes/success", lambda a: ~a, "summary.success_rate is 1, but episodes/success gives 0"),
        ("demos", "episodes/valid", lambda a: ~a, "summary.train_episodes is 5, but the arrays hold 0"),
        ("demos", "episodes/seed", lambda a: a * 0 - 2, "seed below -1"),
        ("demos", "steps/observations", lambda a: a + 1e17, "far outside the environment's"),
        ("buffer", "source_index", lambda a: a - 10**6, "negative rows"),
        ("buffer", "points", lambda a: a + 1e17, "far outside the normalized range"),
        ("buffer", "normalizer/low", lambda a: a + 1e6, "normalizer/low exceeds"),
        ("model", "buffer/points", lambda a: a - 1e17, "far outside the normalized range"),
        ("model", "normalizer/high", lambda a: a - 1e6, "normalizer/low exceeds"),
        ("plans", "pair_index", lambda a: a + 100, "pair_index must lie"),
        ("plans", "plans", lambda a: a[..., :-1].copy(), "features per state"),
        ("model", "curve/step", lambda a: a[::-1].copy(), "curve/step must increase"),
        ("eval", "episodes/seed", lambda a: a + 7, "per seed of"),
        ("eval", "episodes/failure", lambda a: a + 9, "codes outside -1..4"),
        ("eval", "episodes/failure", lambda a: a + 1, "disagrees with episodes/success"),
    ],
)
def test_indices_that_point_outside_the_data_are_refused(tmp_path, kind, name, value, needle):
    """Shapes can be right while the indices or values are wrong (negative episode starts trained silently on wrong
    windows): each kind checks its arrays against each other and the manifest."""
    manifest, arrays = build(kind)
    arrays[name] = value(arrays[name])
    path = artifacts.save(tmp_path / f"{kind}.h5", kind, manifest, arrays)
    assert needle in _err(path)


@pytest.mark.parametrize(
    "part, field, value, needle",
    [
        ("summary", "episodes", 6, "summary.episodes is 6, but the arrays hold 5"),
        ("summary", "steps", 1, "summary.steps is 1"),
        ("summary", "max_length", 99, "summary.max_length is 99"),
        ("summary", "valid_episodes", 2, "summary.valid_episodes is 2"),
        ("summary", "success_rate", 0.5, "summary.success_rate is 0.5"),
        ("config", "episodes", 7, "config.episodes is 7"),
        ("config", "env", "umaze", "config.env 'umaze' is not the environment"),
    ],
)
def test_a_demos_manifest_that_contradicts_its_arrays_is_refused(tmp_path, part, field, value, needle):
    """Every writer computes the demos summary from the arrays it stores, so a summary (or a config) that says
    otherwise was edited: reports and splits would quote it, and it is refused on load."""
    manifest, arrays = build("demos")
    edited = getattr(manifest, part).model_copy(update={field: value})
    path = artifacts.save(tmp_path / "demos.h5", "demos", manifest.model_copy(update={part: edited}), arrays)
    assert needle in _err(path)
    assert artifacts.load(artifacts.save(tmp_path / "ok.h5", "demos", manifest, arrays), "demos").n_episodes == 5


def test_episode_lengths_whose_sums_wrap_around_are_refused(tmp_path):
    """Lengths near 2**62 whose int64 sums wrap back to the number of steps tile the steps as far as wrapped
    arithmetic can tell; each length must lie within the steps, or `cluster` reads far outside the arrays."""
    manifest, arrays = build("demos")
    length = arrays["episodes/length"].astype(np.int64)
    length[1:] += 2**62  # four extra 2**62: the total wraps by 2**64 back to the true count
    with np.errstate(over="ignore"):
        start = np.concatenate([[0], np.cumsum(length)[:-1]])
    assert int(np.sum(length)) == len(arrays["steps/observations"])  # the wrapped total fits
    arrays["episodes/length"], arrays["episodes/start"] = length, start
    path = artifacts.save(tmp_path / "demos.h5", "demos", manifest, arrays)
    assert "episodes/length must lie in 1.." in _err(path)


def test_an_evals_plans_must_have_the_environments_width(tmp_path):
    manifest, arrays = build("eval")
    e, env = len(arrays["episodes/seed"]), manifest.env
    for width, ok in [(env.obs_dim, True), (env.obs_dim + env.action_dim, True), (env.obs_dim + 1, False)]:
        path = artifacts.save(
            tmp_path / f"eval{width}.h5", "eval", manifest, arrays | {"plans": np.zeros((e, 6, width))}
        )
        if ok:
            assert artifacts.load(path).arrays["plans"].shape[-1] == width
        else:
            assert "features per state" in _err(path)


def test_content_checksum_rules(tmp_path):
    """From schema 2.1 the checksum is required; a 2.0 file (written before it existed) reads without one; a
    checksum that is present is always checked."""
    from cdrb_cli.artifacts.core import CHECKSUM_ATTR

    p = write(tmp_path / "d.h5", "demos")
    with h5py.File(p, "r+") as f:  # data changed behind the checksum's back
        f["steps/actions"][0, 0] += 1.0
    assert "does not match its checksum" in _err(p)
    with h5py.File(p, "r+") as f:
        del f.attrs[CHECKSUM_ATTR]
    assert "has no content checksum" in _err(p)
    with h5py.File(p, "r") as f:
        m = json.loads(f["manifest"][()].decode())
    _set_manifest(p, m, "2.0")
    with h5py.File(p, "r+") as f:  # as the 2.0 writer made it: no checksum attribute
        del f.attrs[CHECKSUM_ATTR]
    assert artifacts.load(p).manifest.schema_version == "2.0"
    with h5py.File(p, "r+") as f:
        f.attrs[CHECKSUM_ATTR] = "0" * 64
    assert "does not match its checksum" in _err(p)


def test_bytes_written_or_read_safely_here_skip_the_probe_and_others_do_not(tmp_path, monkeypatch):
    """The forked probe runs for content this process has neither written nor read safely; the same bytes again
    (the same file, or a copy) load without it, and a file changed in place is probed again."""
    probed = []
    real = artifacts._guarded_probe
    monkeypatch.setattr(artifacts, "_guarded_probe", lambda p, *rest: probed.append(p.name) or real(p, *rest))
    p = write(tmp_path / "d.h5", "demos")
    artifacts.load(p)
    assert probed == []  # written by this process
    monkeypatch.setattr(core, "_SAFE_CONTENT", set())  # as if another process had written it
    artifacts.load(p)
    shutil.copy(p, tmp_path / "copy.h5")
    assert artifacts.load(tmp_path / "copy.h5").sha256 == artifacts.load(p).sha256
    assert probed == ["d.h5"]  # probed once, then known by its bytes
    with tampered(p) as f:
        f.attrs["cdrb_kind"] = "model"
    with pytest.raises(ArtifactError):
        artifacts.load(p)
    with pytest.raises(ArtifactError):
        artifacts.load(p)
    assert probed == ["d.h5", "d.h5", "d.h5"]  # other bytes: probed, and a failed read is never taken as safe


def test_a_read_that_hangs_is_stopped_at_the_time_limit(tmp_path, monkeypatch):
    """The guard's child reads the file; one that never finishes is killed at CDRB_READ_TIMEOUT and the load is
    refused in one line, and a child that ends is waited for, its error (exit 2) left to the parent's own read."""
    import time

    p = write(tmp_path / "d.h5", "demos")
    monkeypatch.setattr(core, "_SAFE_CONTENT", set())  # bytes this process has not written or read
    monkeypatch.setenv("CDRB_READ_TIMEOUT", "0.5")
    real = artifacts._load
    monkeypatch.setattr(artifacts, "_load", lambda *a: time.sleep(60))  # what the forked child runs
    with pytest.raises(ArtifactError, match=r"d.h5: reading it did not finish in 0.5\d* s") as err:
        artifacts.load(p)
    assert "the limit CDRB_READ_TIMEOUT sets" in err.value.message  # the user's limit may be what is too short
    monkeypatch.delenv("CDRB_READ_TIMEOUT")
    monkeypatch.setattr(artifacts, "_read_timeout", lambda path: 0.5)
    with pytest.raises(ArtifactError, match="the file is corrupt or hostile"):
        artifacts.load(p)
    monkeypatch.setattr(artifacts, "_load", real)
    assert artifacts.load(p, "demos").manifest.kind == "demos"
    pid = os.fork()
    if pid == 0:
        os._exit(2)
    assert os.WEXITSTATUS(artifacts._wait_child(pid, 10.0)) == 2


def test_a_file_another_process_holds_open_for_writing_is_said_so_not_called_corrupt(tmp_path):
    path = write(tmp_path / "d.h5", "demos")
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            f"import h5py, time; f = h5py.File({str(path)!r}, 'a'); print(1, flush=True); time.sleep(60)",
        ],
        stdout=subprocess.PIPE,
        text=True,
        env={**os.environ, "HDF5_USE_FILE_LOCKING": "TRUE"},
    )
    try:
        assert holder.stdout.readline().strip() == "1"
        if os.environ.get("HDF5_USE_FILE_LOCKING", "").upper() == "FALSE":
            pytest.skip("HDF5 file locking is off in this environment")
        with pytest.raises(BadInput, match="another process is writing this file"):
            artifacts.load(path)
    finally:
        holder.kill()
        holder.wait()
    assert artifacts.load(path).manifest.kind == "demos"  # released: it reads


def test_load_refuses_what_is_no_path_or_no_kind(tmp_path):
    """The package's loader, called from Python: a kind that is none of the artifact kinds, or a path that is
    none, is one line, not a valid file called corrupt or a bare TypeError."""
    from cdrb_cli import load

    p = write(tmp_path / "d.h5", "demos")
    for path, kind, needle in ((p, 1, "kind = 1: not an artifact kind"), (p, "bogus", "not an artifact kind"),
                               (None, None, "path = None: not a path"), (b"d.h5", None, "not a path")):  # fmt: skip
        with pytest.raises(ArtifactError, match=needle):
            load(path, kind=kind)
    assert load(str(p), kind="demos").manifest.kind == "demos"


def _rewrite(path, name, dtype):
    """Store one dataset as ``dtype`` and re-sign the file, as another writer following docs/format.md would."""
    with tampered(path) as f:
        data = f[name][()]
        del f[name]
        f.create_dataset(name, data=data.astype(dtype))
    return data


def test_another_byte_order_or_half_floats_read_as_numbers(tmp_path, recwarn):
    """A big-endian dataset reads in this machine's byte order (torch takes no other) with its values and its
    checksum intact; half floats read without overflow warnings from the magnitude check."""
    p = write(tmp_path / "d.h5", "demos")
    want = _rewrite(p, "steps/observations", ">f4")
    got = artifacts.load(p, "demos").arrays["steps/observations"]
    assert got.dtype.isnative and np.array_equal(got, want)
    import torch

    assert torch.as_tensor(got).shape == want.shape
    _rewrite(p, "steps/observations", "f2")
    assert np.allclose(artifacts.load(p, "demos").arrays["steps/observations"], want, atol=1e-2)
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def test_a_manifest_nested_past_recursion_is_not_valid_json(tmp_path):
    p = write(tmp_path / "d.h5", "demos")
    with h5py.File(p, "r") as f:
        m = json.loads(f["manifest"][()].decode())
    m["summary"] = json.loads("[" * 50 + "]" * 50)
    _set_manifest(p, m, "2.7")
    with h5py.File(p, "r+") as f:
        text = f["manifest"][()].decode().replace("[" * 50 + "]" * 50, "[" * 100000 + "]" * 100000)
        del f["manifest"]
        f["manifest"] = np.bytes_(text)
    assert "/manifest is not valid JSON" in _err(p)


@pytest.mark.parametrize("seed", ["0", -1, True, 1.0, 2**32])
def test_a_manifest_seed_is_a_seed_the_commands_take(tmp_path, seed):
    """``--seed`` takes 0..2**32-1; a manifest whose seed is a string, a negative number, a bool or a float was not
    written by a command, and is refused rather than coerced."""
    from tests.factories import edit_manifest

    path = write(tmp_path / "m.h5", "model")
    with tampered(path) as f:
        edit_manifest(f, lambda m: m.update(seed=seed))
    assert "manifest field 'seed' is invalid" in _err(path)
