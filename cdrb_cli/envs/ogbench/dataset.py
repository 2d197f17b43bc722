"""An official OGBench dataset file (``.npz``) read as demonstrations (`cdrb import npz`).

OGBench writes each dataset with ``numpy.savez_compressed``: ``observations`` (N, obs), ``actions`` (N, act),
``terminals`` (N,), true on the last row of each episode, and for the maze datasets ``qpos`` and ``qvel``. Its loader
drops each episode's last action (no next observation follows it); so does this import (a demos episode ends with a
zero action row). The files hold no goals: each episode's goal is taken as its last state (the hindsight goal every
window of it is trained toward anyway), so its success is true by construction and says nothing. The file is read
with ``allow_pickle=False``, so a file with object arrays is refused, never unpickled.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from cdrb_cli.envs.family import ExpertConfig, ExpertEntry
from cdrb_cli.envs.registry import EXPERTS
from cdrb_cli.errors import BadInput

#: an OGBench dataset file's name: <env>-<dataset type>-v<N>[-val].npz
FILE_NAME = re.compile(r"^(pointmaze-[a-z]+-[a-z]+-v\d+)(-val)?\.npz$")
#: the largest file read (the official PointMaze files are about 20-40 MB)
MAX_BYTES = 2 * 1024**3
#: the largest magnitude of a value read (OGBench's mazes span tens of metres, actions [-1, 1])
MAX_VALUE = 1e6
#: the arrays an import reads
KEYS = ("observations", "actions", "terminals")


class OGBenchSourceConfig(ExpertConfig):
    """An OGBench dataset file imported by `cdrb import npz`: its name and sha256."""

    kind: Literal["ogbench-dataset"] = "ogbench-dataset"
    file: str = Field(max_length=4096, description="the file's name")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    goal_rule: str = Field("last state", description="what each episode's goal is (the files hold none)")

    def describe(self) -> str:
        return f"OGBench dataset file {self.file} (sha256 {self.sha256[:12]}; goals: each episode's last state)"


def _no_rollouts(spec, config):
    raise BadInput("--expert ogbench-dataset: imported episodes cannot be rolled out", hint="use ogbench-noisy")


def _configure(policy: Path | None):
    raise BadInput("--expert ogbench-dataset: use `cdrb import npz FILE.npz --out demos.h5`", hint="docs/cli.md")


EXPERTS.register(ExpertEntry(OGBenchSourceConfig, _no_rollouts, _configure, "episodes imported from an OGBench file"))


def env_for(path: Path) -> str | None:
    """The env id an OGBench dataset file's name says, or None."""
    m = FILE_NAME.match(Path(path).name)
    return m.group(1) if m else None


def _arrays(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise BadInput(f"{path}: no such file", hint="check the path")
    if path.stat().st_size > MAX_BYTES:
        raise BadInput(f"{path}: larger than {MAX_BYTES // 1024**3} GiB", hint="not an OGBench PointMaze file")
    try:
        f = np.load(path, allow_pickle=False)
        if not isinstance(f, np.lib.npyio.NpzFile):
            raise ValueError("one array, not an archive of named arrays")
        with f:
            return {k: np.asarray(f[k]) for k in KEYS if k in f.files}
    except Exception as exc:  # noqa: BLE001 - any damage (zip, deflate, .npy header, pickled objects): one line
        if "allow_pickle" in str(exc):  # numpy's refusal to unpickle an object array
            raise BadInput(
                f"{path}: holds object arrays, which are never unpickled", hint="save the arrays as numbers"
            ) from None
        said = f"{type(exc).__name__}: {' '.join(str(exc).split())[:100]}" if str(exc) else type(exc).__name__
        raise BadInput(f"{path}: not a readable .npz file ({said})", hint="check the file") from None


def _numbers(path: Path, name: str, a: np.ndarray, ndim: int) -> np.ndarray:
    """``a`` as float64 when it is a real numeric (or boolean) array of ``ndim`` dimensions with finite values of a
    sane size."""
    real = a.dtype == np.bool_ or np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating)
    if a.ndim != ndim or not real:
        raise BadInput(f"{path}: {name} is a {a.ndim}-d {a.dtype} array", hint=f"expected {ndim}-d numbers")
    a = a.astype(np.float64)
    if not np.isfinite(a).all() or (np.abs(a) > MAX_VALUE).any():
        raise BadInput(f"{path}: {name} has NaN, infinite or values beyond 1e6", hint="the file is damaged")
    return a


def read_episodes(spec, path: Path):
    """The episodes of an OGBench ``.npz`` file for ``spec``: (states, actions with a zero last row, goals, success,
    the source record), each list one entry per episode."""
    from cdrb_cli.envs.registry import family_of

    path = Path(path)
    a = _arrays(path)
    missing = [k for k in KEYS if k not in a]
    if missing:
        raise BadInput(f"{path}: no {', '.join(missing)} array", hint="an OGBench dataset has observations, "
                       "actions and terminals")  # fmt: skip
    obs = _numbers(path, "observations", a["observations"], 2)
    act = _numbers(path, "actions", a["actions"], 2)
    term = _numbers(path, "terminals", a["terminals"], 1)
    n = len(obs)
    if n < 2:
        raise BadInput(f"{path}: {n} rows, fewer than the two of one step", hint="the file is empty or damaged")
    if obs.shape != (n, spec.obs_dim) or act.shape != (n, spec.action_dim) or term.shape != (n,):
        raise BadInput(
            f"{path}: observations {obs.shape}, actions {act.shape}, terminals {term.shape}; {spec.id} needs "
            f"(N, {spec.obs_dim}), (N, {spec.action_dim}), (N,)",
            hint="name the right environment with --env",
        )
    ends = np.flatnonzero(term != 0)
    if not len(ends) or ends[-1] != n - 1:
        raise BadInput(f"{path}: the last row does not end an episode (terminals)", hint="the file is damaged")
    family, starts = family_of(spec), np.concatenate([[0], ends[:-1] + 1])
    states, actions, goals, success = [], [], [], []
    for a0, a1 in zip(starts, ends + 1):
        if a1 - a0 < 2:
            raise BadInput(f"{path}: an episode of one row (rows {a0}..{a1 - 1})", hint="the file is damaged")
        S = obs[a0:a1]
        states.append(S)
        actions.append(np.concatenate([act[a0 : a1 - 1], np.zeros((1, spec.action_dim))]))
        goals.append(np.repeat(S[-1:, spec.goal_dims], len(S), axis=0))
        success.append(bool(family.success(spec, S, goals[-1][0]).any()))
    source = OGBenchSourceConfig(file=path.name, sha256=hashlib.sha256(path.read_bytes()).hexdigest())
    return states, actions, goals, success, source
