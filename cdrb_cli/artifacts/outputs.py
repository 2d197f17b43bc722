"""Output paths: the one rule every command follows before it writes a file (an artifact, a picture, a report).

:func:`check_output` (before any work): the folder exists and is writable (a file is created and removed there,
so a read-only filesystem or an immutable folder is found now, not after an hour of training); the path is not a
folder, not a symbolic link, not a device or FIFO; it is none of the run's inputs; an existing file is an error
unless ``--force``.

:func:`claim_output` (for the whole run): the same checks, then an exclusive lock on ``.NAME.lock`` beside the
output, so a second run writing the same path stops at once with the holder's pid instead of both "succeeding"
with one result lost; under the lock, temp files left by a killed writer of that path are removed.
"""

from __future__ import annotations

import contextlib
import os
import re
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from cdrb_cli.errors import BadInput, OutputExists, force_option
from cdrb_cli.settings import clip

try:
    import fcntl
except ImportError:  # pragma: no cover (Windows: no locking)
    fcntl = None


def _same(a: Path, b: Path) -> bool:
    try:
        return a.exists() and b.exists() and os.path.samefile(a, b)
    except OSError:
        return False


def names_a_folder(path: str | os.PathLike) -> bool:
    """Whether ``path`` as typed names a folder (``x.h5/``, ``x/.``, ``.``): ``Path`` drops a trailing slash, and
    writing the file ``x.h5`` would not be what was asked."""
    text = os.fsdecode(os.fspath(path))
    return text.endswith((os.sep, os.sep + ".")) or text in (".", "..")


#: the longest output file name: 255 bytes (most file systems) less the marks of its temp and lock files
MAX_NAME_BYTES = 200


def check_output(
    path: str | Path,
    force: bool,
    flag: str = "--out",
    inputs: Iterable[str | Path] = (),
    suffixes: tuple[str, ...] = (),
) -> Path:
    """Validate an output path before any work starts (see the module docstring); returns it as a Path."""
    name = f"a file name such as plot{suffixes[0]}" if suffixes else "a file name"
    if names_a_folder(path):
        raise BadInput(
            f"{flag} {os.fsdecode(os.fspath(path)) or repr('')}: names a folder, not a file",
            hint=f"give {name}",
        )
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    _refuse_control_characters(str(path), flag)
    if len(os.fsencode(path.name)) > MAX_NAME_BYTES:
        raise BadInput(
            f"{flag} {path.name[:40]}...: a file name of {len(os.fsencode(path.name))} bytes",
            hint=f"use a name of at most {MAX_NAME_BYTES} bytes: file systems allow 255, less the temp file's marks",
        )
    if suffixes and path.suffix.lower() not in suffixes:
        raise BadInput(f"{flag} {path}: unsupported file type", hint=f"use {', '.join(suffixes)}")
    try:  # a path past the system's limit (ENAMETOOLONG) makes stat itself fail: one line, not a traceback
        is_folder = folder.is_dir()
        path.exists()
    except OSError as exc:
        raise BadInput(
            f"{flag} {clip(path, 80)}: {exc.strerror or type(exc).__name__}", hint="choose a shorter path"
        ) from None
    if not is_folder:
        if folder.exists():
            raise BadInput(f"{flag} {path}: {folder} is a file, not a folder", hint="choose another path")
        raise BadInput(f"{flag} {path}: folder {folder} does not exist", hint="create it or choose another path")
    if path.is_symlink():
        raise BadInput(f"{flag} {path}: is a symbolic link", hint="pass the path of a regular file")
    if path.is_dir():
        raise BadInput(f"{flag} {path}: is a folder", hint=f"give {name} (in it, or elsewhere)")
    if path.exists():
        mode = path.stat().st_mode
        if not stat.S_ISREG(mode):
            raise BadInput(f"{flag} {path}: is not a regular file (a device or FIFO?)", hint="choose another path")
        for item in inputs:
            if _same(path, Path(item)):
                raise BadInput(f"{flag} {path}: is an input of this command", hint="write to another path")
        if not force:
            raise OutputExists(
                f"{flag} {path}: file exists",
                path,
                hint=f"pass {force_option(flag)} to overwrite it, or choose another path",
            )
    check_writable(folder, flag, path)
    return path


def has_control_character(text: str) -> bool:
    """Whether ``text`` holds a control character (a newline, a tab, DEL...): a path printed one per line, or named
    on a command line a task reads back, must not."""
    return any(ord(c) < 32 or ord(c) == 127 for c in text)


def _refuse_control_characters(text: str, flag: str) -> None:
    # stdout names the file written, a line per path: a newline inside one would read as two
    if has_control_character(text):
        raise BadInput(f"{flag} {text!r}: a control character (a newline?) in the path", hint="rename it")


def distinct_outputs(**outputs: Path | None) -> None:
    """Refuse two output flags (``out=..., table=...``; None: not given) that name the same file, before any work."""
    seen: dict[Path, str] = {}
    for name, path in outputs.items():
        if path is None:
            continue
        flag = "--" + name.replace("_", "-")
        key = Path(path).resolve()
        if key in seen:
            raise BadInput(f"{flag} {path}: the same file as {seen[key]}", hint="give each output its own path")
        seen[key] = flag


def check_can_make(path: Path, flag: str, shown: Path | str | None = None, hint: str | None = None) -> Path:
    """Files can be made on ``path``'s way: the nearest of it and its ancestors that exists is a folder a file can
    be made in (tried, see :func:`check_writable`), else a one-line error naming ``flag`` and ``shown`` (default
    ``path``). Returns that folder."""
    nearest = Path(path)
    while not nearest.exists() and nearest != nearest.parent:
        nearest = nearest.parent
    shown = path if shown is None else shown
    if not nearest.is_dir():
        raise BadInput(f"{flag} {shown}: {nearest} is not a folder", hint=hint or "choose a folder path")
    check_writable(nearest, flag, shown)
    return nearest


def check_writable(folder: Path, flag: str, path: Path | str) -> None:
    """A file can be made in the existing ``folder`` (tried and removed: permission bits do not tell everything,
    root passes them on /proc or a read-only mount), else a one-line error naming ``flag`` and ``path``. A fresh
    random name each time, so a probe an interrupted run left behind never collides with a later one."""
    try:
        fd, probe = tempfile.mkstemp(prefix=".cdrb-probe-", dir=folder)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise BadInput(
            f"{flag} {path}: cannot write in {folder} ({exc.strerror or type(exc).__name__})",
            hint="choose a writable folder",
        ) from None


@contextlib.contextmanager
def claim_output(
    path: str | Path, force: bool, flag: str = "--out", inputs: Iterable[str | Path] = ()
) -> Iterator[Path]:
    """:func:`check_output`, then hold an exclusive lock on the output for the ``with`` block."""
    path = check_output(path, force, flag, inputs)
    with _locked(path, flag):
        _remove_stale_temps(path)
        yield path


def locked(path: str | Path, flag: str):
    """An exclusive lock on ``path``'s ``.NAME.lock`` for a ``with`` block, for outputs that are not one file (a
    Minari dataset folder): a second writer stops with one line naming ``flag`` and the holder's pid."""
    return _locked(Path(path), flag)


def _lock_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.lock")


@contextlib.contextmanager
def _locked(path: Path, flag: str) -> Iterator[None]:
    if fcntl is None:  # pragma: no cover
        yield
        return
    lock = _lock_path(path)
    while True:
        try:  # never through a link: a planted link would have the pid written into (and truncate) its target
            fd = os.open(lock, os.O_CREAT | os.O_RDWR | os.O_NOFOLLOW | os.O_CLOEXEC | os.O_NONBLOCK, 0o644)
        except OSError as exc:
            raise BadInput(
                f"{flag} {path}: its lock file {lock} is not a regular file ({exc.strerror.lower()})",
                hint=f"remove {lock} (cdrb creates it while writing {path.name})",
            ) from None
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode) or st.st_nlink > 1:  # a hard link: the pid would overwrite another file
            os.close(fd)
            what = "not a regular file" if not stat.S_ISREG(st.st_mode) else "a hard link to another file"
            raise BadInput(
                f"{flag} {path}: its lock file {lock} is {what}",
                hint=f"remove {lock} (cdrb creates it while writing {path.name})",
            )
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 32).decode(errors="replace").strip() or "another process"
            os.close(fd)
            raise BadInput(
                f"{flag} {path}: another cdrb run is writing it (pid {holder})",
                hint="wait for it to finish, or write to another path",
            ) from None
        try:
            same = os.fstat(fd).st_ino == os.stat(lock).st_ino  # not a lock file its holder just removed
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    try:
        os.ftruncate(fd, 0)
        # the holder's pid, for the message another run gets; a full disk leaves it out (the lock is the flock)
        with contextlib.suppress(OSError):
            os.write(fd, str(os.getpid()).encode())
        yield
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(lock)
        os.close(fd)


#: the random part of a temp file's name (tempfile.mkstemp: 8 characters of this alphabet)
_TEMP_SUFFIX = re.compile(r"[a-z0-9_]{8}")


def _remove_stale_temps(path: Path) -> None:
    """Temp files of ``path`` left by a writer that was killed (we hold the lock: no other writer of ``path``
    exists): the names `atomic_path` gives, ``.NAME.tmp-`` and 8 random characters, matched literally (a name
    holding ``*`` or ``[`` is not a pattern, and another output's temp file is never one of them)."""
    prefix = f".{path.name}.tmp-"
    with contextlib.suppress(OSError):
        for entry in os.scandir(path.parent):
            if entry.name.startswith(prefix) and _TEMP_SUFFIX.fullmatch(entry.name[len(prefix) :]):
                with contextlib.suppress(OSError):
                    os.unlink(entry.path)


def check_output_folder(folder: str | Path, flag: str, inputs: Iterable[str | Path] = ()) -> Path:
    """Validate a folder an export replaces whole (``--force`` removes what was there): a plain folder or a new
    name, with no control character in its path, inside a folder; never the working folder or one above it, nor a
    folder holding one of the command's inputs (replacing it would delete them). Returns it as a Path."""
    text = os.fsdecode(os.fspath(folder))
    _refuse_control_characters(text, flag)
    folder = Path(folder)
    if folder.is_symlink():
        raise BadInput(f"{flag} {folder}: is a symbolic link", hint="name a plain folder, or a new one")
    if folder.exists() and not folder.is_dir():
        raise BadInput(f"{flag} {folder}: is a file", hint="name a folder to write into")
    parent = folder.absolute().parent
    if parent.exists() and not parent.is_dir():
        raise BadInput(f"{flag} {folder}: {parent} is not a folder", hint="choose a path inside a folder")
    where = folder.resolve()
    here = Path.cwd().resolve()
    if where == here or where in here.parents:
        raise BadInput(
            f"{flag} {text}: is the working folder or holds it", hint="name a folder of its own, e.g. exports/NAME"
        )
    for item in inputs:
        if item is not None and where in Path(item).resolve().parents:
            raise BadInput(
                f"{flag} {folder}: holds {item}, an input of this command (replacing the folder would delete it)",
                hint="write to another folder",
            )
    return folder
