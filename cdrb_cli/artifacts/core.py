"""The generic machinery of the artifact format: layout checks, atomic writes, validated reads, hashing.

Layout (see docs/format.md for the full specification):

* root attributes ``cdrb_kind`` (str) and ``cdrb_schema_version`` ("MAJOR.MINOR");
* ``/manifest``: a scalar fixed-length byte string holding the manifest as ASCII JSON;
* numeric datasets (float, signed/unsigned integer or bool) at the paths each kind declares.

Reading checks, in order and before loading any array: that the file is HDF5, that it is a cdrb artifact, its
kind, its schema major version, the manifest (size, JSON, pydantic), every dataset's dtype and declared size, and
the shapes each kind requires. Only then are arrays read; float arrays must be finite.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import h5py
import numpy as np
from pydantic import ValidationError

from cdrb_cli.envvars import max_artifact_bytes
from cdrb_cli.errors import ArtifactError, BadInput
from cdrb_cli.files import atomic_path, check_input_file, read_input_text, sha256_file  # noqa: F401  (re-exported)
from cdrb_cli.schema_base import Record

KIND_ATTR = "cdrb_kind"
VERSION_ATTR = "cdrb_schema_version"
CHECKSUM_ATTR = "cdrb_content_sha256"
MANIFEST = "manifest"

#: the manifest is read only when its declared size is below this
MAX_MANIFEST_BYTES = 16 * 2**20
#: arrays are read only when their declared total size is below both this and FILE_EXPANSION x the file size
#: (``CDRB_MAX_ARTIFACT_BYTES`` sets another limit)
MAX_TOTAL_BYTES = 16 * 2**30
FILE_EXPANSION = 64
#: the largest magnitude a float in an artifact may have: far beyond any state, weight or count cdrb writes (a
#: float64 counter is exact to 2**53 ~ 9e15), and far enough below float32's range (~3e38) that squared distances
#: and normalizations of such values stay finite
MAX_MAGNITUDE = 1e18
#: at most this many objects (groups + datasets) per file
MAX_OBJECTS = 20_000

_ALLOWED_KINDS = "fiub"  # float, signed int, unsigned int, bool


@dataclass(frozen=True)
class DatasetSpec:
    """A dataset a kind requires (or allows): its path, numpy dtype kinds, and shape.

    A shape entry is an int (exact), a str naming a symbol (bound from the manifest, or by the first dataset that
    uses it, and then checked for consistency), or None (any length)."""

    name: str
    dtype: str
    shape: tuple[int | str | None, ...]
    required: bool = True


@dataclass(frozen=True)
class GroupSpec:
    """Every dataset under ``prefix`` must have one of the ``dtype`` kinds; ``required`` asks for at least one."""

    prefix: str
    dtype: str
    required: bool = True


def content_sha256(manifest_payload: bytes, arrays: Mapping[str, np.ndarray]) -> str:
    """The checksum of an artifact's content: the manifest's bytes, then every dataset (name, dtype, shape, bytes)
    in name order. Stored in the ``cdrb_content_sha256`` attribute and verified on every read, so a flipped bit
    anywhere in the data is an error instead of other numbers."""
    h = hashlib.sha256(manifest_payload)
    for name in sorted(arrays):
        arr = np.ascontiguousarray(arrays[name])
        h.update(f"\0{name}\0{arr.dtype.str}\0{arr.shape}\0".encode())
        h.update(arr.tobytes())
    return h.hexdigest()


def parse_version(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d{1,6})\.(\d{1,6})", text)
    if not m:
        raise ValueError(text)
    return int(m.group(1)), int(m.group(2))


# ------------------------------------------------------------------------------------------------ known-safe bytes
#: sha256 of every file content this process wrote as an artifact or has read without a hang or a crash of the
#: HDF5 library: the same bytes read the same way, so loading them again needs no forked, time-limited probe
_SAFE_CONTENT: set[str] = set()
_SAFE_MAX = 1 << 16  # a bound on the set's memory (64k hashes, ~8 MB); it starts again empty beyond it


def mark_safe(sha256: str) -> None:
    if len(_SAFE_CONTENT) >= _SAFE_MAX:
        _SAFE_CONTENT.clear()
    _SAFE_CONTENT.add(sha256)


def known_safe(sha256: str | None) -> bool:
    return sha256 is not None and sha256 in _SAFE_CONTENT


# ------------------------------------------------------------------------------------------------ writing
def write_h5(path: str | Path, kind: str, version: str, manifest: Record, arrays: Mapping[str, np.ndarray]) -> Path:
    """Write an artifact atomically. ``arrays`` maps dataset paths (``a/b``) to numeric arrays.

    The HDF5 file is built in memory (HDF5's core driver) and its image written to disk in one plain write: a disk
    that fills up then fails one Python write with a one-line error (:func:`cdrb_cli.files.atomic_path`), where
    HDF5 writing to the disk itself fails in its own flush and can crash the process as it closes the file."""
    path = Path(path)
    text = manifest.model_dump_json()
    payload = (
        text.encode("ascii", errors="strict")
        if text.isascii()
        else json.dumps(json.loads(text), ensure_ascii=True).encode("ascii")
    )
    arrays = {name: np.asarray(value) for name, value in arrays.items()}
    with atomic_path(path) as tmp:
        with h5py.File(tmp.name, "w", driver="core", backing_store=False, track_order=True) as f:
            f.attrs[KIND_ATTR] = kind
            f.attrs[VERSION_ATTR] = version
            f.attrs[CHECKSUM_ATTR] = content_sha256(payload, arrays)
            f.create_dataset(MANIFEST, data=np.bytes_(payload))
            # each parent group looked up once: h5py resolves a path's parents at every call otherwise, about a
            # fifth of writing a model's ~500 datasets (a checkpoint written every few seconds in short runs)
            groups: dict[str, h5py.Group] = {"": f}
            for name, value in arrays.items():
                arr = np.asarray(value)
                if arr.dtype.kind not in _ALLOWED_KINDS:
                    raise TypeError(f"dataset {name}: dtype {arr.dtype} is not numeric")
                if arr.dtype.kind == "f" and not in_bounds(arr):
                    what = "non-finite values" if not np.isfinite(arr).all() else f"values beyond +-{MAX_MAGNITUDE:g}"
                    raise ValueError(f"dataset {name}: refusing to write {what}")
                parent, _, leaf = name.rpartition("/")
                if parent not in groups:
                    groups[parent] = f.require_group(parent)
                groups[parent].create_dataset(leaf, data=arr)
            f.flush()
            image = f.id.get_file_image()
        with open(tmp, "wb") as out:
            out.write(image)
        mark_safe(hashlib.sha256(image).hexdigest())
    return path


def in_bounds(arr: np.ndarray) -> bool:
    """Every value finite and within +-MAX_MAGNITUDE: one pass over the array (NaN and inf fail the comparison).
    A half-precision float cannot hold the bound (it would overflow to inf): finite is enough there."""
    if arr.dtype.itemsize < 4:
        return bool(np.isfinite(arr).all())
    return bool((np.abs(arr) <= MAX_MAGNITUDE).all())


# ------------------------------------------------------------------------------------------------ reading
def _a(word: str) -> str:
    return "an" if word[:1].lower() in "aeiou" else "a"


def _open(path: Path) -> h5py.File:
    if not path.exists():
        raise BadInput(f"{path}: no such file", hint="check the path")
    if path.is_dir():
        raise BadInput(f"{path}: is a folder, not an artifact file", hint="pass the .h5 file")
    if not os.access(path, os.R_OK):
        raise BadInput(f"{path}: permission denied", hint="make the file readable")
    try:
        if not h5py.is_hdf5(str(path)):
            raise ArtifactError(f"{path}: not an HDF5 file", hint="pass a file written by a cdrb command")
        return h5py.File(path, "r")
    except ArtifactError:
        raise
    except BlockingIOError:  # HDF5's lock: another process holds the file open for writing
        raise BadInput(
            f"{path}: another process is writing this file (HDF5 holds it locked)",
            hint="wait for that command to finish (a training checkpoints into its --out), then read it",
        ) from None
    except Exception as exc:  # h5py raises OSError and friends for truncated / corrupt files
        raise ArtifactError(
            f"{path}: HDF5 file is truncated or corrupt ({type(exc).__name__})",
            hint="re-create it with the command that wrote it",
        ) from None


def _attr_str(f: h5py.File, name: str) -> str | None:
    if name not in f.attrs:
        return None
    value = f.attrs[name]
    if isinstance(value, bytes):
        value = value.decode("utf-8", errors="replace")
    if isinstance(value, np.ndarray) and value.shape == ():
        value = value.item()
        if isinstance(value, bytes):
            value = value.decode("utf-8", errors="replace")
    return value if isinstance(value, str) and len(value) < 64 else None


def _walk(f: h5py.File, max_objects: int = MAX_OBJECTS) -> dict[str, h5py.Dataset]:
    """All datasets by path, without following links out of the file; refuses files with too many objects."""
    found: dict[str, h5py.Dataset] = {}
    count = 0

    def visit(group: h5py.Group, prefix: str) -> None:
        nonlocal count
        for key in group.keys():
            count += 1
            if count > max_objects:
                raise ArtifactError(f"{f.filename}: more than {max_objects} HDF5 objects", hint="not a cdrb artifact")
            link = group.get(key, getlink=True)
            name = f"{prefix}{key}"
            if not isinstance(link, h5py.HardLink):
                raise ArtifactError(f"{f.filename}: {name} is an external or soft link", hint="links are not allowed")
            obj = group[key]
            if isinstance(obj, h5py.Group):
                visit(obj, name + "/")
            elif isinstance(obj, h5py.Dataset):
                # a virtual dataset, or one whose raw data lives in another file, would read outside this file
                # (and outside its sha256)
                if obj.is_virtual or obj.external:
                    raise ArtifactError(
                        f"{f.filename}: dataset /{name} keeps its data outside the file (virtual or external storage)",
                        hint="not a cdrb artifact",
                    )
                found[name] = obj

    visit(f, "")
    return found


def check_foreign_h5(path: Path, max_objects: int) -> None:
    """An HDF5 file cdrb did not write (a dataset's data) checked as artifacts are before anything is read: an
    HDF5 file, hard links only, no virtual or external storage, at most ``max_objects`` objects, and declared
    dataset sizes within :data:`FILE_EXPANSION` times the bytes the file occupies (a 1 MB file declaring 3 GB is
    refused, not allocated)."""
    f = _open(path)
    try:
        datasets = _walk(f, max_objects)
        declared = 0
        for ds in datasets.values():
            if ds.dtype.kind not in "biufc":
                continue  # strings and the like: read by their library, not by cdrb
            declared += int(np.prod(ds.shape, dtype=np.float64)) * ds.dtype.itemsize
        if declared > _expansion_limit(path):
            raise ArtifactError(
                f"{path}: its datasets declare {declared / 2**20:,.0f} MiB in a {_stored_bytes(path) / 2**20:,.1f} "
                "MiB file",
                hint="the file is damaged or hostile",
            )
    finally:
        f.close()


def _expansion_limit(path: Path) -> int:
    """The most bytes a file's datasets may declare: :data:`FILE_EXPANSION` times what it occupies, plus 1 MiB."""
    return FILE_EXPANSION * _stored_bytes(path) + 2**20


def _stored_bytes(path: Path) -> int:
    """Bytes the file really occupies: a sparse file's apparent size (a hole at its end) would lift the cap."""
    st = path.stat()
    blocks = getattr(st, "st_blocks", None)
    return st.st_size if blocks is None else min(st.st_size, 512 * blocks)


def read_h5(
    path: str | Path,
    expected_kind: str | None,
    current_versions: Mapping[str, str],
    can_migrate=lambda kind, major: False,
):
    """Open and validate the generic part of an artifact.

    Returns ``(file, kind, version, manifest_dict, datasets, lenient)`` where ``datasets`` maps dataset paths to
    open h5py datasets (the file stays open; the caller reads and closes it through :func:`load_arrays`). An older
    major version is accepted when ``can_migrate(kind, major)``; the caller then migrates what it read."""
    path = Path(path)
    f = _open(path)
    try:
        kind = _attr_str(f, KIND_ATTR)
        version_text = _attr_str(f, VERSION_ATTR)
        if kind is None or version_text is None:
            there = [a for a in (KIND_ATTR, VERSION_ATTR) if a in f.attrs and _attr_str(f, a) is None]  # not text
            raise ArtifactError(
                f"{path}: HDF5 file is not a cdrb artifact ("
                + (f"{'/'.join(there)} not a text attribute" if there else f"no {KIND_ATTR}/{VERSION_ATTR} attributes")
                + ")",
                hint="pass a file written by a cdrb command",
            )
        if kind not in current_versions:
            raise ArtifactError(f"{path}: unknown artifact kind {kind!r}", hint=f"known: {', '.join(current_versions)}")
        if expected_kind is not None and kind != expected_kind:
            raise ArtifactError(
                f"{path}: is {_a(kind)} '{kind}' artifact, but {_a(expected_kind)} '{expected_kind}' artifact is "
                "needed here",
                hint=f"pass the {expected_kind} file",
            )
        try:
            major, minor = parse_version(version_text)
        except ValueError:
            raise ArtifactError(
                f"{path}: malformed schema version {version_text!r}", hint="re-create the file"
            ) from None
        cur_major, cur_minor = parse_version(current_versions[kind])
        if major > cur_major:
            raise ArtifactError(
                f"{path}: {kind} schema {version_text} is newer than this cdrb reads ({current_versions[kind]})",
                hint=f"upgrade cdrb to a release that reads {kind} schema {major}.x",
            )
        if major < cur_major and not can_migrate(kind, major):
            raise ArtifactError(
                f"{path}: {kind} schema {version_text} is older than this cdrb reads ({current_versions[kind]})",
                hint="re-create the artifact with this cdrb version (no migration exists for it yet)",
            )
        lenient = major == cur_major and minor > cur_minor  # an old major is migrated, then read strictly
        datasets = _walk(f)
        man = datasets.pop(MANIFEST, None)
        if man is None:
            raise ArtifactError(
                f"{path}: has no /{MANIFEST} dataset", hint="re-create it with the command that wrote it"
            )
        if man.shape != () or man.dtype.kind != "S" or man.dtype.itemsize > MAX_MANIFEST_BYTES:
            raise ArtifactError(
                f"{path}: /{MANIFEST} must be a scalar byte string under {MAX_MANIFEST_BYTES} bytes",
                hint="re-create it with the command that wrote it",
            )
        try:
            manifest = json.loads(man[()].decode("ascii"))
        except (UnicodeDecodeError, ValueError, OSError, RecursionError):  # (nested deeper than Python follows)
            raise ArtifactError(f"{path}: /{MANIFEST} is not valid JSON", hint="re-create it") from None
        if not isinstance(manifest, dict):
            raise ArtifactError(f"{path}: /{MANIFEST} is not a JSON object", hint="re-create it")
        if manifest.get("kind") != kind:
            raise ArtifactError(f"{path}: manifest kind {manifest.get('kind')!r} differs from {KIND_ATTR} {kind!r}")
        if manifest.get("schema_version") != version_text:
            raise ArtifactError(
                f"{path}: manifest schema_version {str(manifest.get('schema_version'))[:20]!r} differs from "
                f"{VERSION_ATTR} {version_text!r}",
                hint="re-create the artifact",
            )
        total = 0
        for name, ds in datasets.items():
            dt = ds.dtype
            if dt.kind not in _ALLOWED_KINDS or dt.fields is not None or dt.subdtype is not None or dt.itemsize > 8:
                raise ArtifactError(f"{path}: dataset /{name} has non-numeric dtype {dt}", hint="not a cdrb artifact")
            if ds.shape is None:
                raise ArtifactError(f"{path}: dataset /{name} has no shape (empty dataspace)", hint="re-create it")
            total += int(np.prod(ds.shape, dtype=np.float64)) * dt.itemsize
        cap = max_artifact_bytes(MAX_TOTAL_BYTES)
        if total > cap and cap != MAX_TOTAL_BYTES:
            raise ArtifactError(
                f"{path}: datasets declare {total:,} bytes, more than CDRB_MAX_ARTIFACT_BYTES={cap:,}",
                hint="raise or unset CDRB_MAX_ARTIFACT_BYTES to read this file",
            )
        limit = min(cap, _expansion_limit(path))
        if total > limit:
            raise ArtifactError(
                f"{path}: datasets declare {total / 2**20:.0f} MiB, "
                f"more than this file can hold ({limit / 2**20:.0f} MiB)",
                hint="the file is corrupt or hostile; re-create it",
            )
        return f, kind, version_text, manifest, datasets, lenient
    except BaseException:
        f.close()
        raise


def check_shapes(
    path: Path,
    datasets: Mapping[str, h5py.Dataset],
    specs: tuple[DatasetSpec, ...],
    groups: tuple[GroupSpec, ...],
    dims: dict[str, int],
) -> None:
    """Check required datasets, their dtype kinds and their shapes against ``specs`` and the symbols ``dims``."""
    bound = dict(dims)
    for spec in specs:
        ds = datasets.get(spec.name)
        if ds is None:
            if spec.required:
                raise ArtifactError(f"{path}: missing dataset /{spec.name}", hint="re-create the artifact")
            continue
        if ds.dtype.kind not in spec.dtype:
            raise ArtifactError(f"{path}: dataset /{spec.name} has dtype {ds.dtype}, expected kind {spec.dtype!r}")
        if len(ds.shape) != len(spec.shape):
            raise ArtifactError(f"{path}: dataset /{spec.name} has shape {ds.shape}, expected {len(spec.shape)} dims")
        if spec.required and 0 in ds.shape:
            raise ArtifactError(f"{path}: dataset /{spec.name} is empty (shape {ds.shape})", hint="re-create it")
        for axis, (want, got) in enumerate(zip(spec.shape, ds.shape)):
            if want is None:
                continue
            if isinstance(want, str):
                if want not in bound:
                    bound[want] = got
                    continue
                want_n = bound[want]
            else:
                want_n = want
            if got != want_n:
                raise ArtifactError(
                    f"{path}: dataset /{spec.name} axis {axis} has length {got}, expected {want_n}"
                    + (f" ({want})" if isinstance(want, str) else "")
                )
    for group in groups:
        members = [n for n in datasets if n.startswith(group.prefix)]
        if group.required and not members:
            raise ArtifactError(f"{path}: no datasets under /{group.prefix}", hint="re-create the artifact")
        for name in members:
            if datasets[name].dtype.kind not in group.dtype:
                raise ArtifactError(f"{path}: dataset /{name} has dtype {datasets[name].dtype}")


def verify_content(path: Path, f: h5py.File, arrays: Mapping[str, np.ndarray], required: bool) -> None:
    """Check the content checksum; a file of a schema older than the checksum (``required`` False) may lack it,
    but one it carries is always checked."""
    if CHECKSUM_ATTR not in f.attrs and not required:
        return
    stored = f.attrs.get(CHECKSUM_ATTR)
    if isinstance(stored, bytes):
        stored = stored.decode("ascii", errors="replace")
    if not isinstance(stored, str):
        raise ArtifactError(f"{path}: has no content checksum ({CHECKSUM_ATTR})", hint="re-create the artifact")
    if stored != content_sha256(bytes(f[MANIFEST][()]), arrays):
        raise ArtifactError(
            f"{path}: content does not match its checksum (the file was changed or damaged)",
            hint="re-create it with the command that wrote it",
        )


def native_order(arrays: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The arrays in this machine's byte order (another writer's may differ; torch takes only the native one),
    converted after the checksum, which covers the bytes as stored."""
    return {k: v if v.dtype.isnative else v.astype(v.dtype.newbyteorder("=")) for k, v in arrays.items()}


def load_arrays(path: Path, datasets: Mapping[str, h5py.Dataset]) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for name, ds in datasets.items():
        try:
            arr = ds[()]
        except Exception as exc:
            raise ArtifactError(
                f"{path}: dataset /{name} cannot be read ({type(exc).__name__}); the file is corrupt"
            ) from None
        arr = np.asarray(arr)
        if arr.dtype.kind == "f" and not in_bounds(arr):
            if not np.isfinite(arr).all():
                raise ArtifactError(f"{path}: dataset /{name} contains NaN or inf", hint="re-create the artifact")
            raise ArtifactError(
                f"{path}: dataset /{name} holds values beyond +-{MAX_MAGNITUDE:g}, which no cdrb artifact does",
                hint="re-create the artifact",
            )
        out[name] = arr
    return out


def validate_manifest(path: Path, manifest_cls: type[Record], data: dict[str, Any], lenient: bool) -> Record:
    try:
        return manifest_cls.model_validate(data, context={"lenient": lenient})
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ())) or "(root)"
        raise ArtifactError(
            f"{path}: manifest field '{where}' is invalid: {first.get('msg', 'invalid')}"
            + (f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""),
            hint="re-create the artifact",
        ) from None


class ArtifactBase:
    """A validated artifact in memory: ``manifest`` (pydantic) and ``arrays`` (numpy, by dataset path)."""

    kind: ClassVar[str]
    manifest_cls: ClassVar[type[Record]]
    datasets: ClassVar[tuple[DatasetSpec, ...]] = ()
    groups: ClassVar[tuple[GroupSpec, ...]] = ()
    #: the schema version of the file when it was read through a migration (None: current)
    migrated_from: str | None = None

    def __init__(self, manifest, arrays: Mapping[str, np.ndarray], path: Path | None = None, sha256: str | None = None):
        self.manifest = manifest
        self.arrays = dict(arrays)
        self.path = Path(path) if path is not None else None
        self.sha256 = sha256

    @classmethod
    def dims(cls, manifest) -> dict[str, int]:
        """Symbols the dataset shapes are checked against, from the manifest."""
        return {}

    @classmethod
    def check_data(cls, manifest, arrays: Mapping[str, np.ndarray]) -> str | None:
        """What is inconsistent between the arrays and the manifest (a message), or None."""
        return None

    #: manifest fields that identify what an artifact holds (the rest say when, where, by which build it was
    #: written, or summarize timings)
    IDENTITY: ClassVar[tuple[str, ...]] = ("kind", "seed", "env", "config", "parents")

    @property
    def data_sha256(self) -> str:
        """The hash of what this artifact holds: its arrays and the manifest's :attr:`IDENTITY` fields, its parents
        by their own data hashes (their byte hash for a parent recorded before schema 2.7). A file deleted and made
        again by the same deterministic command has the same data hash, though its bytes (its timestamps) differ."""
        cached = getattr(self, "_data_sha256", None)
        if cached is None:
            m = self.manifest.model_dump(mode="json")
            ident = {k: m[k] for k in self.IDENTITY if k in m and k != "parents"}
            ident["parents"] = [[p["kind"], p.get("data_sha256") or p["sha256"]] for p in m.get("parents", [])]
            payload = json.dumps(ident, sort_keys=True, separators=(",", ":")).encode()
            cached = self._data_sha256 = content_sha256(payload, self.arrays)
        return cached

    def __getitem__(self, name: str) -> np.ndarray:
        return self.arrays[name]

    def __repr__(self) -> str:
        where = f" {self.path}" if self.path else ""
        return f"<cdrb {self.kind} artifact{where}: {len(self.arrays)} datasets>"
