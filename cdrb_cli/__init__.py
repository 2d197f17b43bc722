"""cdrb: Cold Diffusion on the Replay Buffer, as a command-line toolkit.

The Python API: :mod:`cdrb_cli.api` plans and evaluates like `cdrb plan` and `cdrb eval`; :func:`load` opens and
validates any cdrb artifact and returns a typed object::

    import cdrb_cli
    demos = cdrb_cli.load("demos.h5")      # -> cdrb_cli.artifacts.Demos
    print(demos.manifest.summary)
"""

from __future__ import annotations

__version__ = "0.2.0"

#: the command's name
PROG = "cdrb"

__all__ = ["__version__", "load"]


def load(path, kind=None):
    """Open, validate and return the artifact at ``path`` (see :func:`cdrb_cli.artifacts.load`)."""
    from cdrb_cli.artifacts import load as _load

    return _load(path, kind=kind)
