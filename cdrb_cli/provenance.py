"""What every artifact records about how it was made: versions, git sha, command line, time."""

from __future__ import annotations

import contextlib
import contextvars
import datetime as _dt
import functools
import platform
import subprocess
import sys
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path

from cdrb_cli import __version__

_TRACKED = (
    "numpy",
    "h5py",
    "pydantic",
    "torch",
    "mujoco",
    "gymnasium",
    "gymnasium-robotics",
    "stable-baselines3",
    "scikit-learn",
    "scipy",
    "diffusers",
)


@functools.lru_cache(maxsize=1)
def library_versions() -> dict[str, str]:
    """Versions of the libraries that shape results (read from package metadata; nothing is imported)."""
    out = {"cdrb": __version__, "python": platform.python_version()}
    for name in _TRACKED:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


@functools.lru_cache(maxsize=1)
def git_sha() -> str | None:
    """The git commit of the cdrb source tree, with ``-dirty`` when it has uncommitted changes; None outside git."""
    root = Path(__file__).resolve().parent.parent
    if not (root / ".git").exists():
        return None
    try:
        proc = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--verify", "-q", "HEAD"], capture_output=True, text=True, timeout=5
        )
        sha = proc.stdout.strip()
        if proc.returncode != 0 or len(sha) != 40:
            return None
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            timeout=5,
        ).stdout.strip()
        return sha + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def now_utc() -> str:
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def text(value) -> str:
    """A path or argument as valid Unicode (bytes that are not UTF-8 become U+FFFD), fit for a JSON manifest."""
    return str(value).encode("utf-8", "surrogateescape").decode("utf-8", "replace")


#: the command line of a CLI run inside another program (``cli.main(argv)``), which ``sys.argv`` does not hold
_COMMAND: contextvars.ContextVar[list[str] | None] = contextvars.ContextVar("cdrb_command", default=None)


@contextlib.contextmanager
def running(argv: list[str]) -> Iterator[None]:
    """Record ``argv`` (program name first) as the command line of the artifacts written inside the block."""
    token = _COMMAND.set(list(argv))
    try:
        yield
    finally:
        _COMMAND.reset(token)


def command_line() -> list[str]:
    """The command that is writing an artifact: the CLI's own arguments when run by ``cli.main(argv)``, else this
    process's ``sys.argv`` (program name without its folder)."""
    given = _COMMAND.get()
    argv = [text(a) for a in (sys.argv if given is None else given)]
    if argv:
        argv[0] = Path(argv[0]).name
    return argv
