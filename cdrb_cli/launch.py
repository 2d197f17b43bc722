"""The ``cdrb`` command's entry point, kept apart from :mod:`cdrb_cli.cli` so that it can catch what the CLI's own
imports cannot: those imports (typer, pydantic, every command's module) take a second or more, and a Ctrl-C during
them ends the command with the interrupt's one line and exit code 130, as a Ctrl-C at any later moment does, not a
traceback."""

from __future__ import annotations

import sys

from cdrb_cli.errors import EXIT_INTERRUPTED  # a few constants: loaded in a millisecond


def main() -> int:
    try:
        from cdrb_cli.cli import main as run
    except KeyboardInterrupt:
        sys.stderr.write("error: interrupted\n")
        return EXIT_INTERRUPTED
    return run()
