"""The typed HDF5 artifact format (see docs/format.md).

``load(path, kind=None)`` validates and returns a typed artifact; ``save(path, kind, manifest, arrays)`` writes
one atomically; ``make_manifest`` fills the common provenance fields; ``find_up_to_date`` decides whether a stage
can be skipped.
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import time
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from cdrb_cli import __version__
from cdrb_cli.artifacts.core import (
    ArtifactBase,
    atomic_path,
    check_shapes,
    in_bounds,
    known_safe,
    load_arrays,
    mark_safe,
    native_order,
    parse_version,
    read_h5,
    sha256_file,
    validate_manifest,
    verify_content,
    write_h5,
)
from cdrb_cli.artifacts.kinds import (
    CHECKSUM_SINCE,
    KINDS,
    SCHEMA_VERSIONS,
    Buffer,
    BufferManifest,
    Demos,
    DemosManifest,
    Eval,
    EvalManifest,
    ManifestBase,
    Model,
    ModelManifest,
    ParentRef,
    Plans,
    PlansManifest,
)
from cdrb_cli.artifacts.migrations import (
    backfill_arrays,
    can_migrate,
    migrate_arrays,
    migrate_manifest,
    migrate_minor,
)
from cdrb_cli.artifacts.outputs import check_output, claim_output
from cdrb_cli.errors import ArtifactError, BadInput, CdrbError, OutputExists, force_option
from cdrb_cli.provenance import command_line, git_sha, library_versions, now_utc, text

__all__ = [
    "in_bounds",
    "differences",
    "load",
    "unfinished_model",
    "save",
    "make_manifest",
    "parent_ref",
    "existing",
    "Existing",
    "check_output",
    "claim_output",
    "produce",
    "find_up_to_date",
    "sha256_file",
    "atomic_path",
    "KINDS",
    "SCHEMA_VERSIONS",
    "ArtifactBase",
    "Demos",
    "Buffer",
    "Model",
    "Plans",
    "Eval",
    "ManifestBase",
    "DemosManifest",
    "BufferManifest",
    "ModelManifest",
    "PlansManifest",
    "EvalManifest",
    "ParentRef",
]


def load(path: str | Path, kind: str | None = None) -> ArtifactBase:
    """Open ``path``, validate it completely, and return the typed artifact. Raises :class:`ArtifactError`
    (a :class:`BadInput`, exit code 2) with a one-line message for anything that is not a valid artifact.

    The file is first read in a forked child process with a time limit (:func:`_guarded_probe`): the HDF5
    library can loop forever or crash on some corrupted files, and that must not hang or kill cdrb. Bytes this
    process wrote, or has read so before, skip the probe (:func:`~cdrb_cli.artifacts.core.known_safe`: by their
    sha256, which the artifact records anyway); a fork costs 30-60 ms in a process that has imported torch."""
    from cdrb_cli.settings import clip

    if not isinstance(path, (str, os.PathLike)) or isinstance(path, bytes):
        raise ArtifactError(f"path = {clip(repr(path), 60)}: not a path", hint="pass a str or a pathlib.Path")
    if kind is not None and kind not in KINDS:
        raise ArtifactError(f"kind = {clip(repr(kind), 60)}: not an artifact kind",
                            hint=f"one of {', '.join(KINDS)}, or None for any")  # fmt: skip
    path = Path(os.fsdecode(path))
    try:
        is_file = path.is_file()
    except OSError as exc:  # e.g. a name too long for the file system: no file there to read
        raise ArtifactError(f"{clip(path, 80)}: cannot be read ({exc.strerror})", hint="check the path") from None
    sha = sha256_file(path) if is_file else None  # a non-file: the reader's checks say what it is
    if not known_safe(sha) and _guarded_probe(path, kind, sha) and sha is not None:
        mark_safe(sha)
    return _load(path, kind, sha)


def _read_timeout(path: Path) -> float:
    from cdrb_cli.envvars import read_timeout

    base = read_timeout()
    try:
        size = path.stat().st_size
    except OSError:
        size = 0
    return base + size / 50e6  # plus a second per 50 MB


def _wait_child(pid: int, limit: float) -> int | None:
    """The wait status of the child ``pid`` once it ends, or None if it still runs after ``limit`` seconds. Where
    the kernel gives a process file descriptor (Linux >= 5.3) the wait wakes the moment the child ends; elsewhere it
    polls with a growing interval (up to 50 ms)."""
    deadline = time.monotonic() + limit
    fd = None
    with contextlib.suppress(AttributeError, OSError):
        fd = os.pidfd_open(pid)
    try:
        delay = 0.0005
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                return status
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            if fd is not None:
                select.select([fd], [], [], left)  # readable when the child has ended
            else:
                time.sleep(min(delay, left))
                delay = min(delay * 2, 0.05)
    finally:
        if fd is not None:
            os.close(fd)


def _guarded_probe(path: Path, kind: str | None, sha: str | None = None) -> bool:
    """Read and validate ``path`` in a forked child. If the child hangs past the time limit or dies from a
    signal, raise :class:`ArtifactError`; otherwise return whether it read a valid artifact (the caller then reads
    the file itself, and gets the same errors the child got). ``sha``: the file's sha256 when the caller has it (the
    child does not hash it again). Disabled (False) where ``os.fork`` is unavailable or ``CDRB_READ_GUARD=0``."""
    if not hasattr(os, "fork") or os.environ.get("CDRB_READ_GUARD") == "0" or not path.is_file():
        return False
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # fork with threads: the child only reads the file
        pid = os.fork()
    if pid == 0:  # child: read everything, report only through the exit status
        code = 0
        try:
            _load(path, kind, sha)
        except BadInput:
            code = 2
        except BaseException:
            code = 3
        os._exit(code)
    limit = _read_timeout(path)
    status = _wait_child(pid, limit)
    if status is None:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        if os.environ.get("CDRB_READ_TIMEOUT", "").strip():  # the user's limit may be what is too short
            raise ArtifactError(
                f"{path}: reading it did not finish in {limit:.3g} s, the limit CDRB_READ_TIMEOUT sets",
                hint="unset CDRB_READ_TIMEOUT for the default (30 s), or give the read more time; if it still does "
                "not finish, the file is corrupt or hostile",
            )
        raise ArtifactError(
            f"{path}: reading it did not finish in {limit:.3g} s; the file is corrupt or hostile",
            hint="re-create it with the command that wrote it",
        )
    if os.WIFSIGNALED(status):
        raise ArtifactError(
            f"{path}: the HDF5 library crashed reading it (signal {os.WTERMSIG(status)}); the file is corrupt",
            hint="re-create it with the command that wrote it",
        )
    return os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


def _load(path: Path, kind: str | None, sha: str | None = None) -> ArtifactBase:
    try:
        f, found_kind, version, manifest_data, datasets, lenient = read_h5(path, kind, SCHEMA_VERSIONS, can_migrate)
        try:
            cls = KINDS[found_kind]
            major = int(version.split(".")[0])
            old = major < int(SCHEMA_VERSIONS[found_kind].split(".")[0])
            if old:
                manifest_data = migrate_manifest(found_kind, major, manifest_data)
            manifest_data = migrate_minor(found_kind, parse_version(version), manifest_data)
            manifest = validate_manifest(path, cls.manifest_cls, manifest_data, lenient)
            check_shapes(path, datasets, cls.datasets, cls.groups, cls.dims(manifest))
            arrays = load_arrays(path, datasets)
            verify_content(path, f, arrays, required=parse_version(version) >= CHECKSUM_SINCE)
            arrays = native_order(arrays)
            if old:
                arrays = migrate_arrays(found_kind, major, arrays)
            arrays = backfill_arrays(found_kind, arrays, parse_version(version))
            problem = cls.check_data(manifest, arrays)
            if problem is not None:
                raise ArtifactError(f"{path}: {problem}", hint="the file is corrupt or hostile; re-create it")
        finally:
            f.close()
        art = cls(manifest, arrays, path=path, sha256=sha or sha256_file(path))
        art.migrated_from = version if old else None
        return art
    except CdrbError:  # our own errors (bad input, or a registry module that failed) keep their message
        raise
    except Exception as exc:  # anything else the HDF5 library raises on a damaged file
        raise ArtifactError(
            f"{path}: HDF5 file is corrupt ({type(exc).__name__})", hint="re-create it with the command that wrote it"
        ) from None


def save(path: str | Path, artifact_or_kind, manifest=None, arrays: Mapping[str, np.ndarray] | None = None) -> Path:
    """Write an artifact atomically (temp file in the same folder, fsync, rename). Accepts either an
    :class:`ArtifactBase` or ``(kind, manifest, arrays)``."""
    if isinstance(artifact_or_kind, ArtifactBase):
        kind, manifest, arrays = artifact_or_kind.kind, artifact_or_kind.manifest, artifact_or_kind.arrays
    else:
        kind = artifact_or_kind
    assert manifest is not None and arrays is not None
    if manifest.kind != kind:
        raise ValueError(f"manifest kind {manifest.kind} != {kind}")
    return write_h5(path, kind, SCHEMA_VERSIONS[kind], manifest, arrays)


def parent_ref(artifact: ArtifactBase) -> ParentRef:
    assert artifact.path is not None and artifact.sha256 is not None
    return ParentRef(
        kind=artifact.kind,
        path=text(artifact.path.resolve()),
        sha256=artifact.sha256,
        data_sha256=artifact.data_sha256,
    )


def make_manifest(kind: str, *, env, config, seed: int, parents: Sequence[ArtifactBase] = (), **fields: Any):
    """Build a manifest of ``kind`` with the common provenance fields filled in."""
    cls = KINDS[kind].manifest_cls
    return cls(
        kind=kind,
        schema_version=SCHEMA_VERSIONS[kind],
        cdrb_version=__version__,
        created_at=now_utc(),
        argv=command_line(),
        seed=seed,
        git_sha=git_sha(),
        versions=library_versions(),
        parents=[parent_ref(p) for p in parents],
        env=env,
        config=config,
        **fields,
    )


@dataclass(frozen=True)
class Existing:
    """What an output path holds, compared with the run about to write it (see :func:`existing`).

    ``status`` is one of ``missing`` (no file), ``invalid`` (not a valid artifact of the kind), ``different``
    (made by another config, environment or inputs), ``resumable`` (a training checkpoint this run may continue:
    same inputs and config up to the fields in ``resumable``, not past this run's steps) or ``up-to-date``
    (this very run, finished). ``reason`` says why it is not up to date."""

    status: str
    artifact: ArtifactBase | None = None
    reason: str = ""

    @property
    def up_to_date(self) -> bool:
        return self.status == "up-to-date"


#: kind -> schema version before which a file is redone rather than reused (it lacks what is measured now):
#: evals before 2.2 have no plan-crossing or jump measurements
RECOMPUTE_BEFORE = {"eval": (2, 2)}


def _same_array(art: ArtifactBase, name: str, value: np.ndarray) -> bool:
    """Whether ``art``'s array ``name`` holds ``value`` as it would be stored (in the array's own dtype)."""
    try:
        stored = np.asarray(art.arrays[name])
    except KeyError:
        return False
    value = np.asarray(value)
    return stored.shape == value.shape and np.array_equal(stored, value.astype(stored.dtype), equal_nan=True)


def same_inputs(recorded: Sequence[ParentRef], parents: Sequence[ArtifactBase]) -> bool:
    """Whether ``parents`` are the inputs ``recorded``: each the same bytes, or (recorded from schema 2.7 on) the
    same data, so an input deleted and made again by the same command still counts as the same."""
    if [r.kind for r in recorded] != [p.kind for p in parents]:
        return False
    return all(
        r.sha256 == p.sha256 or (r.data_sha256 is not None and r.data_sha256 == p.data_sha256)
        for r, p in zip(recorded, parents)
    )


def existing(
    path: str | Path,
    kind: str,
    config,
    parents: Sequence[ArtifactBase] = (),
    env=None,
    resumable: Sequence[str] = ("steps",),
    inputs: Mapping[str, np.ndarray] | None = None,
) -> Existing:
    """The one rule for "can this stage be skipped, or continued?", used by every command, quickstart and
    ``--resume``: same kind, config (and env), same parents (by sha256), the same ``inputs`` (arrays the command
    was given, such as the start states of a plan, compared with the file's arrays of those names as stored) and,
    for training, finished."""
    path = Path(path)
    if not path.is_file():
        return Existing("missing", reason="it does not exist")
    try:
        art = load(path, kind)
    except BadInput as exc:
        return Existing("invalid", reason=exc.message)
    if not same_inputs(art.manifest.parents, parents):
        return Existing("different", art, "it was made from other inputs")
    since = RECOMPUTE_BEFORE.get(kind)
    if since is not None and parse_version(art.manifest.schema_version) < since:
        return Existing(
            "different", art, f"it was written by schema {art.manifest.schema_version}, which measured less"
        )
    if env is not None and art.manifest.env != env:
        return Existing("different", art, "it was made for another environment")
    state = getattr(art.manifest, "state", None)
    # settings that only say when to save progress (never what is computed) do not make a file out of date
    same = {f: getattr(art.manifest.config, f) for f in getattr(config, "bookkeeping", ()) if hasattr(config, f)}
    config = config.model_copy(update=same) if same else config
    if art.manifest.config == config and (state is None or state.finished):
        other = [k for k, v in (inputs or {}).items() if not _same_array(art, k, v)]
        if other:
            return Existing("different", art, f"it was made for other {' and '.join(other)}")
        return Existing("up-to-date", art)
    if state is not None:
        mine = {f: getattr(config, f) for f in resumable}
        if art.manifest.config.model_copy(update=mine) == config:
            if state.step > getattr(config, "steps", state.step):
                return Existing("different", art, f"it is already at step {state.step}, past --steps")
            what = "a finished model" if state.finished else "a checkpoint"
            return Existing("resumable", art, f"it is {what} at step {state.step}")
    keys = differences(art.manifest.config.model_dump(mode="json"), config.model_dump(mode="json"))
    if state is not None:  # a checkpoint continues to a longer run: its length is no difference that blocks it
        keys = [k for k in keys if k not in resumable] or keys
    return Existing("different", art, f"it was made with other settings: {', '.join(keys[:4]) or 'config'}")


def differences(a, b, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two config dumps."""
    if isinstance(a, dict) and isinstance(b, dict):
        return [k for key in dict.fromkeys([*a, *b]) for k in differences(a.get(key), b.get(key), f"{prefix}{key}.")]
    return [] if a == b else [prefix.rstrip(".")]


def unfinished_model(path: str | Path) -> bool:
    """Whether ``path`` holds a training checkpoint that has not finished (what `cdrb train --resume` continues);
    False when there is no file or it is not a readable model (the command that reads it will say why)."""
    path = Path(path)
    if not path.exists():
        return False
    try:
        return not load(path, "model").manifest.state.finished
    except Exception:  # unreadable for any reason: not something to resume
        return False


def find_up_to_date(
    path: str | Path, kind: str, config, parents: Sequence[ArtifactBase] = (), env=None
) -> ArtifactBase | None:
    """The artifact at ``path`` when it is up to date for this run (:func:`existing`); else None."""
    found = existing(path, kind, config, parents, env)
    return found.artifact if found.up_to_date else None


def produce(
    path: str | Path, kind: str, force: bool, config, build, parents=(), env=None, flag: str = "--out", inputs=None
):
    """Run ``build()`` (which writes ``path`` and returns its artifact) unless ``path`` is already up to date
    (:func:`existing`, ``inputs`` included); return the artifact either way. An existing file made differently is
    an error unless ``force``."""
    from cdrb_cli import ui

    path = Path(path)
    if path.exists() and not force and not path.is_dir():
        found = existing(path, kind, config, parents, env, inputs=inputs)
        if not found.up_to_date:
            raise OutputExists(
                f"{flag} {path}: file exists and was not made by this exact command ({found.reason})",
                path,
                hint=f"pass {force_option(flag)} to overwrite it, or choose another path",
            )
        ui.log(f"{path} is up to date (same config and inputs): skipped; {force_option(flag)} redoes it")
        return found.artifact
    with claim_output(path, force=True, flag=flag, inputs=[p.path for p in parents]):
        return build()
