"""Files on the lowest floor: atomic writes (temp file, fsync, rename) and the guarded reads every input file
passes (a regular file, within a size limit, no link out of its folder, read from the descriptor that was checked).
Artifacts, settings files, maps, scenes and pictures all use these."""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from cdrb_cli import interrupts
from cdrb_cli.errors import BadInput


def sha256_file(path: str | Path, chunk: int = 2**20) -> str:
    """The sha256 of the file's bytes; a file that opens but cannot be read (an I/O error, /proc/self/mem) is a
    one-line error naming it."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        try:
            while block := f.read(chunk):
                h.update(block)
        except OSError as exc:
            raise BadInput(f"{path}: cannot be read ({exc.strerror or exc})", hint="check the file") from None
    return h.hexdigest()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success fsync it and rename it over ``path`` atomically.

    On any exception (or a crash) the previous content of ``path`` is untouched and the temporary file is removed
    (after a hard crash a ``.NAME.tmp-*`` file may remain; it is never mistaken for an artifact)."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.exists():
        raise BadInput(f"{path}: folder {folder} does not exist", hint="create it first or choose another --out")
    try:
        fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=folder)
    except OSError as exc:
        _raise_if_full(exc, path)
        raise
    os.fchmod(fd, 0o666 & ~_umask())  # mkstemp makes 0600; a written file honours the umask like any other
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        if _landing is not None:  # inside together(): it lands with the others
            _landing.append((tmp, path))
            return
        _before_rename_hook(tmp, path)
        os.replace(tmp, path)
        _fsync_dir(folder)
    except BaseException as exc:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        if isinstance(exc, OSError):
            _raise_if_full(exc, path)
        raise


#: the finished temp files of the innermost together() block, with the paths they are renamed to at its end
_landing: list[tuple[Path, Path]] | None = None


@contextmanager
def together() -> Iterator[None]:
    """The :func:`atomic_path` writes inside the block land together at its end, or none of them: each is written
    and fsynced to its temp file as it goes and renamed into place only once the block succeeds, so a command with
    several outputs (a report and its --docs page, a settings file and its tables) never leaves some of them when
    a later one fails (a full disk). Nothing inside the block may read back what it wrote. Nested blocks are one."""
    global _landing
    if _landing is not None:
        yield
        return
    _landing = []
    try:
        yield
        with interrupts.polled():  # Ctrl-C is answered after the renames, not between them
            for tmp, path in _landing:
                _before_rename_hook(tmp, path)
                os.replace(tmp, path)
        for folder in dict.fromkeys(path.parent for _, path in _landing):
            _fsync_dir(folder)
    except BaseException:
        for tmp, _ in _landing:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        raise
    finally:
        _landing = None


#: write errors that say the file does not fit (a full disk, a quota, the process's file-size limit), with the fix
_NO_ROOM = {
    errno.ENOSPC: "free some space there or write it to another folder",
    errno.EDQUOT: "free some of your quota there or write it to another folder",
    errno.EFBIG: "raise this shell's file-size limit (ulimit -f) or write a smaller file",
}


def _raise_if_full(exc: OSError, path: Path) -> None:
    """A write of ``path`` that did not fit (:data:`_NO_ROOM`), as one line; anything else is left to the caller."""
    if exc.errno in _NO_ROOM:
        raise BadInput(
            f"{path}: {os.strerror(exc.errno).lower()} while writing it; nothing was written", hint=_NO_ROOM[exc.errno]
        ) from None


def replace_file(new: str | Path, final: str | Path) -> None:
    """Rename the finished file ``new`` over ``final`` (the same folder) and make the rename durable."""
    os.replace(new, final)
    _fsync_dir(Path(final).parent)


def replace_folder(new: str | Path, final: str | Path) -> None:
    """Put the finished folder ``new`` (beside ``final``) at ``final``. A folder already there is first renamed
    aside to ``.NAME.old-*`` and removed only after the new one is in place, so a crash at any point leaves one
    whole folder (the old one, perhaps under its aside name), never none."""
    new, final = Path(new), Path(final)
    # the umask's modes, as for any folder and file a user makes (mkdtemp makes 0700, some writers 0600)
    mask = _umask()
    for path in [new, *new.rglob("*")]:
        if not path.is_symlink():
            path.chmod((0o777 if path.is_dir() else 0o666) & ~mask)
    aside = None
    try:
        # Ctrl-C between the two renames would leave the folder only under its aside name: within them a signal is
        # recorded and answered after the second
        with interrupts.polled():
            if final.exists():
                aside = Path(tempfile.mkdtemp(prefix=f".{final.name}.old-", dir=final.parent))
                os.replace(final, aside)  # an empty folder is replaced by the rename
            try:
                os.replace(new, final)
            except BaseException:
                if aside is not None:  # the old folder back in its place
                    os.replace(aside, final)
                    aside = None
                raise
            _fsync_dir(final.parent)
    finally:
        if aside is not None and final.exists():
            shutil.rmtree(aside, ignore_errors=True)


@contextmanager
def new_folder(folder: str | Path) -> Iterator[Path]:
    """``folder`` made (with its missing parents) for the block; when the block fails or is interrupted, the folders
    it made that are still empty are removed, innermost first, so a failed run leaves no empty folders behind."""
    folder = Path(folder)
    made = [d for d in (folder, *folder.parents) if not d.exists()]
    folder.mkdir(parents=True, exist_ok=True)
    try:
        yield folder
    except BaseException:
        for d in made:
            with contextlib.suppress(OSError):
                d.rmdir()
        raise


@contextmanager
def temp_folder_at(folder: str | Path) -> Iterator[None]:
    """Python's temp folder (``tempfile``'s) set to ``folder`` within the block, then back to what it was: for
    library calls that leave files in the temp folder (gymnasium-robotics' mazes write their XML there and never
    remove it), run with a folder the caller removes."""
    saved = tempfile.tempdir
    tempfile.tempdir = str(folder)
    try:
        yield
    finally:
        tempfile.tempdir = saved


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _before_rename_hook(tmp: Path, final: Path) -> None:
    """Test hook: ``CDRB_CRASH_BEFORE_RENAME=1`` simulates a crash between writing and renaming."""
    if os.environ.get("CDRB_CRASH_BEFORE_RENAME") == "1":
        os._exit(86)


def regular_fd(path: str | Path, flags: int) -> int:
    """``path`` opened with ``flags``, never through a link (its last component) and never blocking on a FIFO's
    open; OSError unless it is a regular file (a FIFO would block a read, a device never end)."""
    import stat

    fd = os.open(path, flags | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OSError(f"{path}: not a regular file")
    return fd


def guarded_fd(path: Path, flag: str, max_bytes: int, what: str, hint: str) -> int:
    """An open read-only descriptor of ``path`` after the checks every input file passes (see
    :func:`check_input_file`); the caller closes it."""
    import stat

    path = Path(path)
    source = f"{flag} {path}" if flag else str(path)
    if not os.path.lexists(path):
        raise BadInput(f"{source}: no such {what}", hint=hint)
    target = path
    if path.is_symlink():  # a link is followed only to a file in its own folder
        target = path.resolve()
        if target.parent != path.parent.resolve():
            raise BadInput(f"{source}: a link to a file outside its folder ({target})", hint=f"pass the {what} itself")
    try:
        fd = os.open(target, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError as exc:
        raise BadInput(f"{source}: cannot open it ({exc.strerror or type(exc).__name__})", hint=hint) from None
    st = os.fstat(fd)
    if not stat.S_ISREG(st.st_mode):  # a FIFO would block the read, a device never end, a folder is not a file
        os.close(fd)
        raise BadInput(f"{source}: not a regular file", hint=f"pass the {what} itself")
    if st.st_size > max_bytes:
        os.close(fd)
        raise BadInput(f"{source}: larger than {_size_text(max_bytes)}", hint=f"is this the {what}?")
    return fd


def _size_text(n: int) -> str:
    return f"{n >> 20:,} MiB" if n >= 1 << 20 else f"{n >> 10:,} KiB"


def check_input_file(path: str | Path, flag: str, max_bytes: int, what: str = "file", hint: str = "check the path"):
    """The one check every non-artifact input file passes before it is opened: it exists, is a regular file (a
    FIFO would block the read, a device never end, a folder is not a file), is at most ``max_bytes``, and is not a
    link to a file outside its folder; each failure is one line naming ``flag``. Returns the path."""
    os.close(guarded_fd(Path(path), flag, max_bytes, what, hint))
    return Path(path)


def read_input_text(
    path: str | Path, flag: str, max_bytes: int, what: str = "file", hint: str = "check the path"
) -> str:
    """The text (UTF-8) of an input file that passed :func:`check_input_file`'s checks, read from the descriptor
    that was checked (no race with a swapped file), never more than ``max_bytes``."""
    fd = guarded_fd(Path(path), flag, max_bytes, what, hint)
    source = f"{flag} {path}" if flag else str(path)
    try:
        with os.fdopen(fd, "rb", closefd=False) as fh:
            data = fh.read(max_bytes + 1)
    except OSError as exc:  # opened but unreadable: an I/O error, /proc/self/mem
        raise BadInput(f"{source}: cannot be read ({exc.strerror or exc})", hint=hint) from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:
        raise BadInput(f"{source}: larger than {_size_text(max_bytes)}", hint=f"is this the {what}?")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        raise BadInput(f"{source}: not a text file (not UTF-8)", hint=f"pass the {what} itself") from None


def parse_toml(text: str, source: str, hint: str) -> dict:
    """TOML text as a table; whatever the parser refuses is one :class:`BadInput` line naming ``source``: bad
    syntax, arrays or tables nested past the recursion limit, an integer of more digits than Python converts. A
    leading byte-order mark (some editors write one) is not part of the text."""
    import sys

    try:
        import tomllib
    except ImportError:  # Python 3.10
        import tomli as tomllib

    try:
        return tomllib.loads(text.removeprefix("\ufeff"))
    except RecursionError:  # the parser reads nested arrays and tables recursively
        raise BadInput(f"{source}: arrays or tables nested too deep to read", hint=hint) from None
    except ValueError as exc:  # TOMLDecodeError, and int()'s refusal of a number of thousands of digits
        if "integer string conversion" in str(exc):
            limit = getattr(sys, "get_int_max_str_digits", lambda: 4300)()  # (Python 3.10.7 on)
            raise BadInput(f"{source}: holds an integer of more than {limit} digits", hint=hint) from None
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BadInput(f"{source}: not valid TOML ({first[:160]})", hint=hint) from None
