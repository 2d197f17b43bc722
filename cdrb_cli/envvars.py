"""The environment variables cdrb reads as numbers, each parsed in one place: a value that is not one is a one-line
error naming the variable and the fix, never a Python error from deep inside a command (or, for OpenMP's own
variable, a crash of the library that reads it)."""

from __future__ import annotations

import math
import os

from cdrb_cli.errors import BadInput

#: the most OpenMP threads cdrb lets a process start (OpenMP runtimes crash on absurd counts, e.g. 99999)
MAX_OMP_THREADS = 1024


def number(
    name: str, default: float, *, integer: bool = False, most: float = math.inf, zero: bool = False, hint: str
) -> float:
    """``name``'s value (``default`` when unset or empty): a positive finite number (or 0 when ``zero``), a whole
    one when ``integer``, at most ``most``."""
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = int(text) if integer else float(text)
    except ValueError:
        value = math.nan
    limit = min(most, 2**63 - 1) if integer else most  # a whole number as any C library may take it
    if not (0 <= value <= limit and (zero or value > 0) and value != math.inf):
        what = "a whole number" if integer else "a number"
        bound = f" from 1 to {most:g}" if integer and math.isfinite(most) else (" from 0 up" if zero else " above 0")
        shown = text if len(text) <= 40 else text[:40] + "..."
        raise BadInput(f"{name}={shown!r}: not {what}{bound}", hint=hint)
    return value


def omp_threads() -> int | None:
    """``OMP_NUM_THREADS`` as cdrb takes it: None when unset, else a whole number of threads in bounds."""
    if not os.environ.get("OMP_NUM_THREADS", "").strip():
        return None
    return int(
        number(
            "OMP_NUM_THREADS",
            0,
            integer=True,
            most=MAX_OMP_THREADS,
            hint="unset it to use the cores free now, or give the threads per process, e.g. 2",
        )
    )


def progress_seconds(default: float) -> float:
    return number(
        "CDRB_PROGRESS_SECONDS", default, zero=True, hint="unset it, or give seconds between progress lines, e.g. 30"
    )


def max_artifact_bytes(default: int) -> int:
    return int(
        number(
            "CDRB_MAX_ARTIFACT_BYTES",
            default,
            integer=True,
            hint="unset it for the built-in limit, or give the most bytes an artifact's arrays may declare",
        )
    )


def read_timeout() -> float:
    """Seconds the read probe of an artifact may take before the file counts as hostile (scaled up for big files)."""
    return number("CDRB_READ_TIMEOUT", 30.0, hint="unset it, or give the seconds a read may take, e.g. 30")


def check() -> None:
    """Every variable at once, before a command starts its work."""
    omp_threads()
    progress_seconds(1.0)
    max_artifact_bytes(1)
    read_timeout()
    mujoco_gl()


#: MuJoCo's own values of MUJOCO_GL that turn rendering off, and those it takes on every system
_GL_OFF = ("disable", "disabled", "off", "false", "0")
_GL_ANY = ("enable", "enabled", "on", "true", "1", "glfw", "")
#: the backends MuJoCo offers by system, with the library each needs (None: nothing beyond MuJoCo's own)
_GL_SYSTEM = {
    "Linux": {"glx": None, "egl": "EGL", "osmesa": "OSMesa"},
    "Windows": {"wgl": None},
    "Darwin": {"cgl": None},
}


def mujoco_gl() -> str | None:
    """``MUJOCO_GL`` when set, checked as MuJoCo reads it on import (which fails with a bare error on a value it does
    not know, or on osmesa/egl when that library is absent), so a typo is one line before any work."""
    import ctypes.util
    import platform

    raw = os.environ.get("MUJOCO_GL")
    if raw is None:
        return None
    value = raw.lower().strip()
    system = _GL_SYSTEM.get(platform.system(), {})
    if value not in (*_GL_OFF, *_GL_ANY, *system):
        choices = ", ".join([*system, "glfw", "disable"])
        raise BadInput(
            f"MUJOCO_GL={raw[:40]!r}: not a MuJoCo rendering backend",
            hint=f"unset it, and cdrb picks one; or give one of {choices}",
        )
    library = system.get(value)
    if library is not None and ctypes.util.find_library(library) is None:
        raise BadInput(
            f"MUJOCO_GL={value}: the {library} library is not installed, so MuJoCo cannot start",
            hint="unset it, and cdrb picks a backend that is there"
            + ("; or install it: apt install libosmesa6" if library == "OSMesa" else ""),
        )
    return value
