"""The project's error types and exit codes.

Every failure a user can cause is a :class:`BadInput` (exit code 2); a run that starts well but cannot finish is a
:class:`RunFailed` (exit code 1). Both carry a one-line message naming the file or flag and, where one exists, the fix.
"""

from __future__ import annotations

import contextlib

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # Ctrl-C or SIGTERM
EXIT_BROKEN_PIPE = 141  # the reader of stdout went away (128 + SIGPIPE)

#: the environment variable naming a file where a command that fails with a :class:`CdrbError` leaves
#: :meth:`CdrbError.record` as JSON: how a program running `cdrb` (the grid) reads the failure without parsing stderr
ERROR_FILE = "CDRB_ERROR_FILE"


def option(flag: str, value: object = True) -> str:
    """An option as its caller writes it, the dialect read from ``flag``: a command-line flag (``--force``,
    ``--device cpu``) or a Python keyword argument (``force=True``, ``device='cpu'``), so one message serves the CLI
    and the API."""
    if flag.startswith("-"):
        return flag if value is True else f"{flag} {value}"
    return f"{flag}={value!r}"


def force_option(flag: str) -> str:
    """How to overwrite the output named by ``flag`` in the same dialect: ``--force`` or ``force=True``."""
    return option("--force" if flag.startswith("-") else "force")


class CdrbError(Exception):
    """Base class of every error cdrb reports to a user. ``str(err)`` is a single line."""

    exit_code = EXIT_FAILED

    def __init__(self, message: str, hint: str | None = None):
        # pydantic prefixes a validator's own message with "Value error, ": the message is the user's, not pydantic's
        self.message = " ".join(str(message).split()).replace("Value error, ", "")
        self.hint = " ".join(hint.split()) if hint else None
        super().__init__(self.line())

    def line(self) -> str:
        return f"{self.message} ({self.hint})" if self.hint else self.message

    def __reduce__(self):
        # pickled by its parts, not its one line: an error raised in a worker process reaches the parent whole
        return type(self), (self.message, self.hint)

    def record(self) -> dict:
        """The error as data, for a program that ran the command (:data:`ERROR_FILE`): its line's parts and exit
        code, and ``output_exists`` (the path, else None) when an output blocks the run."""
        return {"message": self.message, "hint": self.hint, "exit_code": self.exit_code, "output_exists": None}


def leave_record(exc: CdrbError | dict) -> None:
    """Write the failure ``exc`` (a :class:`CdrbError` or its :meth:`~CdrbError.record`) as JSON to the file
    :data:`ERROR_FILE` names, when it names one, atomically as every file cdrb writes. Only a path that is free, or
    a regular file holding an earlier record (or nothing), is written: the variable is never a way to overwrite a
    device, a link or a file of the user's; a file that cannot be written leaves the failure to stderr alone."""
    import json
    import os
    import stat
    import sys

    from cdrb_cli.files import atomic_path  # (it imports this module)

    path = os.environ.get(ERROR_FILE, "")
    if not path:
        return
    record = exc.record() if isinstance(exc, CdrbError) else exc
    try:
        mode = os.lstat(path).st_mode
    except OSError:
        mode = None
    if mode is not None and not (stat.S_ISREG(mode) and _is_record(path)):
        sys.stderr.write(
            f"warning: {ERROR_FILE} {path}: not written, it is not an error record left by cdrb "
            "(name a new file, e.g. one in a temporary folder)\n"
        )
        return
    with contextlib.suppress(OSError, CdrbError), atomic_path(path) as tmp:
        tmp.write_text(json.dumps(record))


def _is_record(path: str) -> bool:
    """Whether the regular file ``path`` is empty or holds an error record (a JSON object with an exit code)."""
    import json

    try:
        with open(path, "rb") as f:
            head = f.read(65537)
    except OSError:
        return False
    if not head.strip():
        return True
    try:
        found = json.loads(head) if len(head) <= 65536 else None
    except (ValueError, RecursionError):
        return False
    return isinstance(found, dict) and "exit_code" in found and "message" in found


class BadInput(CdrbError):
    """A flag, argument or input file is wrong; nothing was written. Exit code 2."""

    exit_code = EXIT_BAD_INPUT


class NeedsScene(BadInput):
    """A protocol that runs among obstacles the training scene lacks (``detour``) was asked for without a scene:
    ``need`` says what to give, ``flag`` the command line's option for it; :meth:`in_python` says the same to a
    caller of the Python API, whose argument is ``scene``."""

    def __init__(self, message: str, need: str, flag: str):
        self.need, self.flag = need, flag
        super().__init__(message, hint=f"give {need}: {flag} FILE")

    def __reduce__(self):
        return type(self), (self.message, self.need, self.flag)

    def in_python(self) -> BadInput:
        return BadInput(self.message, hint=f"give {self.need}: scene=FILE")


class OutputExists(BadInput):
    """An output file is there that the command does not write over unless told to (``--force``, ``force=True``):
    one made otherwise, or a checkpoint it cannot continue. ``path`` names it, so a caller that never passes that
    flag (a grid, which writes over only its own files) can say what to do instead."""

    def __init__(self, message: str, path: object, hint: str | None = None):
        self.path = str(path)
        super().__init__(message, hint)

    def __reduce__(self):
        return type(self), (self.message, self.path, self.hint)

    def record(self) -> dict:
        return {**super().record(), "output_exists": self.path}


class ArtifactError(BadInput):
    """A file is not a valid cdrb artifact of the expected kind and version."""


class RunFailed(CdrbError):
    """The inputs were valid but the run could not complete (e.g. a diverging loss). Exit code 1."""

    exit_code = EXIT_FAILED
