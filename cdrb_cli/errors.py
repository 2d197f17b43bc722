"""The project's error types and exit codes.

Every failure a user can cause is a :class:`BadInput` (exit code 2); a run that starts well but cannot finish is a
:class:`RunFailed` (exit code 1). Both carry a one-line message naming the file or flag and, where one exists, the fix.
"""

from __future__ import annotations

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130  # Ctrl-C or SIGTERM
EXIT_BROKEN_PIPE = 141  # the reader of stdout went away (128 + SIGPIPE)


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


class ArtifactError(BadInput):
    """A file is not a valid cdrb artifact of the expected kind and version."""


class RunFailed(CdrbError):
    """The inputs were valid but the run could not complete (e.g. a diverging loss). Exit code 1."""

    exit_code = EXIT_FAILED
