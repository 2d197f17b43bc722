"""The five artifact kinds: their manifests, required datasets and typed accessors."""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from cdrb_cli.artifacts.core import ArtifactBase, DatasetSpec, GroupSpec
from cdrb_cli.configs import (
    MAX_SEED,
    ClusterConfig,
    ClusterSummary,
    CollectConfig,
    CollectSummary,
    EvalConfig,
    EvalSummary,
    PlanConfig,
    PlanSummary,
    SettingsProfile,
    TrainConfig,
    TrainState,
)
from cdrb_cli.envs.family import FAILURE_CAUSES
from cdrb_cli.envs.spec import EnvSpec
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.registry import RegisteredName
from cdrb_cli.schema_base import Record

#: current schema version of each kind ("MAJOR.MINOR"); bump MINOR for added optional fields, MAJOR otherwise (and
#: add a migration from the old major to artifacts/migrations.py)
SCHEMA_VERSIONS = {"demos": "2.7", "buffer": "2.8", "model": "2.17", "plans": "2.12", "eval": "2.20"}
#: files of this version and later must carry the content checksum (older ones may; one present is always checked)
CHECKSUM_SINCE = (2, 1)


def _feature_dim(manifest) -> int:
    """The width of a buffer's points: the state, and the action too when clustered on ``state-action``."""
    e = manifest.env
    return e.obs_dim + (e.action_dim if manifest.config.features == "state-action" else 0)


class ParentRef(Record):
    """An input artifact: its kind, the path it was read from, the sha256 of its bytes and of its data (what the
    file says, without when and how it was written: :meth:`~cdrb_cli.artifacts.core.ArtifactBase.data_sha256`)."""

    kind: str
    path: str
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    data_sha256: str | None = Field(
        None,
        pattern=r"^[0-9a-f]{64}$",
        description="the input's data hash: the same for a file re-made by the same deterministic command (null in "
        "files before schema 2.7: only the bytes' hash identifies the input)",
    )


class ManifestBase(Record):
    kind: str
    schema_version: str = Field(pattern=r"^\d+\.\d+$")
    cdrb_version: str
    created_at: str
    argv: list[str]
    seed: int = Field(ge=0, le=MAX_SEED, strict=True, description="the command's --seed")
    git_sha: str | None = None
    versions: dict[str, str]
    parents: list[ParentRef]
    env: EnvSpec


class DemosManifest(ManifestBase):
    kind: Literal["demos"] = "demos"
    config: CollectConfig
    summary: CollectSummary


class BufferManifest(ManifestBase):
    kind: Literal["buffer"] = "buffer"
    config: ClusterConfig
    summary: ClusterSummary


class ModelManifest(ManifestBase):
    kind: Literal["model"] = "model"
    config: TrainConfig
    state: TrainState
    profile: SettingsProfile | None = Field(
        None,
        description="the choice of `cdrb select` the model was trained with, whose eval settings plan and eval "
        "start from (None: the defaults)",
    )

    @model_validator(mode="after")
    def _consistent(self) -> ModelManifest:
        from cdrb_cli.methods.config import config_problem

        problem = config_problem(self.config)
        if problem is not None:
            raise ValueError(f"config.{'.'.join(problem[0])}: {problem[1]}")
        if self.state.step > self.config.steps:
            raise ValueError(f"state.step {self.state.step} is past config.steps {self.config.steps}")
        return self


class PlansManifest(ManifestBase):
    kind: Literal["plans"] = "plans"
    config: PlanConfig
    summary: PlanSummary
    method: Annotated[str, RegisteredName(METHODS)]


class EvalManifest(ManifestBase):
    kind: Literal["eval"] = "eval"
    config: EvalConfig
    summary: EvalSummary


# ------------------------------------------------------------------------------------------------ typed artifacts
class Demos(ArtifactBase):
    """Expert demonstrations: flat step arrays plus an episode index.

    Episode ``e`` occupies rows ``start[e] : start[e] + length[e]`` of every ``steps/*`` array; its rows are the
    states s_0..s_T, and ``actions[i]`` is the action taken in state ``observations[i]`` (zero on the final row)."""

    kind = "demos"
    manifest_cls = DemosManifest
    datasets = (
        DatasetSpec("steps/observations", "f", ("N", "obs_dim")),
        DatasetSpec("steps/actions", "f", ("N", "action_dim")),
        DatasetSpec("steps/desired_goals", "f", ("N", "goal_dim")),
        DatasetSpec("episodes/start", "i", ("E",)),
        DatasetSpec("episodes/length", "i", ("E",)),
        DatasetSpec("episodes/seed", "i", ("E",)),
        DatasetSpec("episodes/success", "b", ("E",)),
        DatasetSpec("episodes/valid", "b", ("E",)),
    )

    @classmethod
    def dims(cls, manifest):
        e = manifest.env
        return {"obs_dim": e.obs_dim, "action_dim": e.action_dim, "goal_dim": e.goal_dim}

    observations = property(lambda self: self.arrays["steps/observations"])
    actions = property(lambda self: self.arrays["steps/actions"])
    desired_goals = property(lambda self: self.arrays["steps/desired_goals"])
    episode_start = property(lambda self: self.arrays["episodes/start"])
    episode_length = property(lambda self: self.arrays["episodes/length"])
    episode_seed = property(lambda self: self.arrays["episodes/seed"])
    episode_success = property(lambda self: self.arrays["episodes/success"])
    episode_valid = property(lambda self: self.arrays["episodes/valid"])

    @classmethod
    def check_data(cls, manifest, arrays):
        start, length = arrays["episodes/start"], arrays["episodes/length"]
        n = arrays["steps/observations"].shape[0]
        if (length < 1).any() or (length > n).any():  # (bounded first, so the sums below cannot overflow)
            return f"episodes/length must lie in 1..{n} (the number of steps)"
        if start[0] != 0 or (start[1:] != np.cumsum(length)[:-1]).any():
            return "episodes/start and episodes/length do not tile the steps (episodes must follow each other)"
        if int(length.sum()) != n:
            return f"the episodes cover {int(length.sum())} steps, but there are {n}"
        return _demos_summary_problem(manifest, arrays) or _demos_states_problem(manifest, arrays)

    @property
    def n_episodes(self) -> int:
        return int(self.episode_start.shape[0])

    def episode(self, e: int) -> tuple[np.ndarray, np.ndarray]:
        s, n = int(self.episode_start[e]), int(self.episode_length[e])
        return self.observations[s : s + n], self.actions[s : s + n]

    def episode_ids(self, split: str) -> np.ndarray:
        if split == "all":
            return np.arange(self.n_episodes)
        mask = self.episode_valid if split == "valid" else ~self.episode_valid
        return np.flatnonzero(mask)


def _demos_summary_problem(manifest, arrays) -> str | None:
    """What the demos manifest says about its episodes that the arrays contradict (every writer computes the
    summary from the arrays it stores), or None."""
    length, success, valid = arrays["episodes/length"], arrays["episodes/success"], arrays["episodes/valid"]
    s, episodes = manifest.summary, len(length)
    if manifest.config.env != manifest.env.id:
        return f"config.env {manifest.config.env!r} is not the environment the file holds ({manifest.env.id!r})"
    counts = {
        "config.episodes": (manifest.config.episodes, episodes),
        "summary.episodes": (s.episodes, episodes),
        "summary.steps": (s.steps, int(length.sum())),
        "summary.max_length": (s.max_length, int(length.max())),
        "summary.train_episodes": (s.train_episodes, int((~valid).sum())),
        "summary.valid_episodes": (s.valid_episodes, int(valid.sum())),
    }
    for key, (said, held) in counts.items():
        if said != held:
            return f"{key} is {said}, but the arrays hold {held}"
    rate = float(np.mean(success))
    if not abs(s.success_rate - rate) <= 1e-9:
        return f"summary.success_rate is {s.success_rate:g}, but episodes/success gives {rate:g}"
    if (arrays["episodes/seed"] < -1).any():
        return "episodes/seed holds a seed below -1 (-1 marks an episode without one)"
    return None


def _demos_states_problem(manifest, arrays) -> str | None:
    """States far outside the environment (beyond its bounds by more than their own extent, in the dimensions
    its obstacles cover): no simulator step puts a robot there, and one such value skews every normalizer."""
    obstacles = manifest.env.obstacles
    low, high = np.asarray(obstacles.low), np.asarray(obstacles.high)
    span = high - low
    pts = arrays["steps/observations"][:, obstacles.dims]
    far = (pts < low - span) | (pts > high + span)
    if far.any():
        row, col = (int(v) for v in np.argwhere(far)[0])
        label = manifest.env.state_labels[obstacles.dims[col]]
        return (
            f"steps/observations row {row} puts {label} at {float(pts[row, col]):.3g}, far outside the "
            f"environment's [{low[col]:g}, {high[col]:g}]"
        )
    return None


#: how far outside the normalizer's [-1, 1] a stored buffer point may lie (a buffer of other demos than the model's
#: normalizer was fit on lies a little outside); beyond it the points were not normalized, and planning would
#: overflow turning them back into states
MAX_NORMALIZED = 1e3


def points_problem(points, name: str) -> str | None:
    """What is wrong with normalized buffer points ``points`` stored as ``name``, or None."""
    largest = float(np.abs(points).max()) if len(points) else 0.0
    if largest > MAX_NORMALIZED:
        return f"{name} lie far outside the normalized range [-1, 1] (up to {largest:.3g})"
    return None


def normalizer_problem(arrays) -> str | None:
    low, high = arrays["normalizer/low"], arrays["normalizer/high"]
    if (low > high).any():
        return "normalizer/low exceeds normalizer/high"
    return None


def plan_width_problem(manifest, width: int) -> str | None:
    """Plans of ``width`` features: a planner's features are its states, or states and actions."""
    e = manifest.env
    if width not in (e.obs_dim, e.obs_dim + e.action_dim):
        both = e.obs_dim + e.action_dim
        return f"plans have {width} features per state; {e.id} plans {e.obs_dim} (states) or {both} (with actions)"
    return None


def graph_problem(arrays, prefix: str, k: int) -> str | None:
    """What is wrong with the transition graph stored under ``prefix`` (``edges``, ``weights``) of a buffer of ``k``
    points, or None (also when there is none)."""
    if (f"{prefix}edges" in arrays) != (f"{prefix}weights" in arrays):
        return f"{prefix}edges and {prefix}weights come together"
    edges = arrays.get(f"{prefix}edges")
    if edges is not None and edges.size:
        if edges.min() < 0 or edges.max() >= k or (edges[:, 0] >= edges[:, 1]).any():
            return f"{prefix}edges must join two distinct points 0..{k - 1}, the lower index first"
        w = arrays[f"{prefix}weights"]
        if not np.isfinite(w).all() or (w < 0).any():
            return f"{prefix}weights must be finite and not negative"
    return None


class Buffer(ArtifactBase):
    """The replay buffer CDRB diffuses through: ``points`` (K, D) in normalized feature space, each a real
    demonstration state (``source_index`` rows of the demos), and the normalizer that defines that space."""

    kind = "buffer"
    manifest_cls = BufferManifest
    datasets = (
        DatasetSpec("points", "f", ("K", "feature_dim")),
        DatasetSpec("source_index", "i", ("K",)),
        DatasetSpec("normalizer/low", "f", ("feature_dim",)),
        DatasetSpec("normalizer/high", "f", ("feature_dim",)),
        DatasetSpec("graph/edges", "i", ("E", 2), required=False),
        DatasetSpec("graph/weights", "f", ("E",), required=False),
    )

    @classmethod
    def dims(cls, manifest):
        return {"feature_dim": _feature_dim(manifest)}

    @classmethod
    def check_data(cls, manifest, arrays):
        if (arrays["source_index"] < 0).any():
            return "source_index holds negative rows"
        return (
            normalizer_problem(arrays)
            or points_problem(arrays["points"], "points")
            or graph_problem(arrays, "graph/", len(arrays["points"]))
        )

    def graph(self) -> tuple[np.ndarray, np.ndarray]:
        """The buffer's transition graph (:func:`~cdrb_cli.geodesic.transition_graph`): (edges, weights). A buffer
        written before buffers carried one is refused with the way to make one."""
        if "graph/edges" not in self.arrays:
            from cdrb_cli.errors import BadInput

            raise BadInput(
                f"{self.path}: this buffer (schema {self.manifest.schema_version}) has no transition graph, which "
                "geodesic balls measure along",
                hint="run `cdrb cluster` on its demos again: buffers carry the graph since schema 2.7",
            )
        return self.arrays["graph/edges"], self.arrays["graph/weights"]

    points = property(lambda self: self.arrays["points"])
    source_index = property(lambda self: self.arrays["source_index"])
    low = property(lambda self: self.arrays["normalizer/low"])
    high = property(lambda self: self.arrays["normalizer/high"])


class Model(ArtifactBase):
    """A trained (or training) method: the weights of each of its modules (``weights/<module>/...``), their EMA
    copies, each optimizer's state, the normalizer, the training curve, and, for CDRB, the buffer points it
    diffuses through. Self-contained for ``plan`` and ``eval`` (see :mod:`cdrb_cli.methods.checkpoint`)."""

    kind = "model"
    manifest_cls = ModelManifest
    datasets = (
        DatasetSpec("normalizer/low", "f", ("feature_dim",)),
        DatasetSpec("normalizer/high", "f", ("feature_dim",)),
        DatasetSpec("curve/step", "i", ("C",)),
        DatasetSpec("curve/loss", "f", ("C",)),
        DatasetSpec("curve/valid_step", "i", ("V",), required=False),
        DatasetSpec("curve/valid_loss", "f", ("V",), required=False),
        DatasetSpec("buffer/points", "f", ("K", "feature_dim"), required=False),
        DatasetSpec("buffer/graph/edges", "i", ("E", 2), required=False),
        DatasetSpec("buffer/graph/weights", "f", ("E",), required=False),
    )
    # ema/ may be empty: a method whose averages are its own modules (Diffusion-QL) keeps none; weights/ only for a
    # method with no network (the straight line), whose state says 0 parameters
    groups = (
        GroupSpec("weights/", "f", required=False),
        GroupSpec("ema/", "f", required=False),
        GroupSpec("optim/", "fi", required=False),
    )

    @classmethod
    def dims(cls, manifest):
        return {"feature_dim": _feature_dim(manifest)}

    @classmethod
    def check_data(cls, manifest, arrays):
        problem = normalizer_problem(arrays) or points_problem(arrays.get("buffer/points", ()), "buffer/points")
        if problem:
            return problem
        if "buffer/graph/edges" in arrays or "buffer/graph/weights" in arrays:
            problem = graph_problem(arrays, "buffer/graph/", len(arrays.get("buffer/points", ())))
            if problem:
                return problem
        steps = arrays["curve/step"]
        if (np.diff(steps) <= 0).any() or (steps > manifest.state.step).any() or (steps < 1).any():
            return "curve/step must increase, from 1 to the model's step"
        if manifest.state.parameters > 0 and not any(k.startswith("weights/") for k in arrays):
            return f"no datasets under /weights/, but the model has {manifest.state.parameters} parameters"
        return None

    def tensors(self, prefix: str) -> dict[str, np.ndarray]:
        p = prefix.rstrip("/") + "/"
        return {k[len(p) :]: v for k, v in self.arrays.items() if k.startswith(p)}


class Plans(ArtifactBase):
    """Planned trajectories ``plans`` (P, H, D) in raw feature units, with the start/goal each pair was given."""

    kind = "plans"
    manifest_cls = PlansManifest
    datasets = (
        DatasetSpec("plans", "f", ("P", "H", "feature_dim")),
        DatasetSpec("pair_index", "i", ("P",)),
        DatasetSpec("starts", "f", ("Q", "obs_dim")),
        DatasetSpec("goals", "f", ("Q", "obs_dim")),
        DatasetSpec("in_wall", "b", ("P", "H")),
        DatasetSpec("iterates", "f", ("P", None, "H", "feature_dim"), required=False),
        DatasetSpec("iterate_steps", "i", (None,), required=False),
    )

    @classmethod
    def dims(cls, manifest):
        return {"obs_dim": manifest.env.obs_dim}

    @classmethod
    def check_data(cls, manifest, arrays):
        index, pairs = arrays["pair_index"], arrays["starts"].shape[0]
        if (index < 0).any() or (index >= pairs).any():
            return f"pair_index must lie in [0, {pairs})"
        return plan_width_problem(manifest, arrays["plans"].shape[-1])

    plans = property(lambda self: self.arrays["plans"])
    starts = property(lambda self: self.arrays["starts"])
    goals = property(lambda self: self.arrays["goals"])


class Eval(ArtifactBase):
    """Closed-loop evaluation: one row per episode (over all seeds) and a summary in the manifest."""

    kind = "eval"
    manifest_cls = EvalManifest
    datasets = (
        DatasetSpec("episodes/seed", "i", ("E",)),
        DatasetSpec("episodes/episode_seed", "i", ("E",)),
        DatasetSpec("episodes/success", "b", ("E",)),
        DatasetSpec("episodes/steps", "i", ("E",)),
        DatasetSpec("episodes/final_distance", "f", ("E",)),
        DatasetSpec("episodes/plan_in_wall_fraction", "f", ("E",), required=False),  # a policy's eval: no plans
        DatasetSpec("episodes/plan_crosses_obstacle", "b", ("E",), required=False),  # from schema 2.2
        DatasetSpec("episodes/plan_max_jump", "f", ("E",), required=False),
        DatasetSpec("episodes/plan_step_limit", "f", ("E",), required=False),
        DatasetSpec("episodes/executed_collision", "b", ("E",)),
        DatasetSpec("episodes/path_length", "f", ("E",)),
        DatasetSpec("episodes/expert_path_length", "f", ("E",)),
        DatasetSpec("episodes/plan_seconds", "f", ("E",)),
        DatasetSpec("episodes/replans", "i", ("E",), required=False),  # from schema 2.4
        DatasetSpec("episodes/planning_seconds", "f", ("E",), required=False),
        DatasetSpec("episodes/failure", "i", ("E",), required=False),  # from schema 2.5: why it failed
        DatasetSpec("episodes/start", "f", ("E", "obs_dim")),
        DatasetSpec("episodes/goal", "f", ("E", "goal_dim")),
        DatasetSpec("plans", "f", ("E", "H", "feature_dim"), required=False),
        # from schema 2.18, what `cdrb report` takes from the plans, per episode (stages/plan_metrics.py), so an
        # eval without its plans gives the same figures
        DatasetSpec("episodes/plan_states", "i", ("E",), required=False),
        DatasetSpec("episodes/plan_first_step", "f", ("E",), required=False),
        DatasetSpec("episodes/plan_crosses_new_obstacle", "b", ("E",), required=False),
        DatasetSpec("episodes/plan_crosses_wall", "b", ("E",), required=False),  # from schema 2.19
    )
    #: per body the family's collision test moves: bodies/<name>/crossing, bodies/<name>/states_in_obstacle
    groups = (GroupSpec("bodies/", "bi", required=False),)

    @classmethod
    def dims(cls, manifest):
        return {"obs_dim": manifest.env.obs_dim, "goal_dim": manifest.env.goal_dim}

    @classmethod
    def check_data(cls, manifest, arrays):
        cfg = manifest.config
        values, counts = np.unique(arrays["episodes/seed"], return_counts=True)
        if sorted(values.tolist()) != sorted(set(cfg.seeds)) or (counts != cfg.episodes).any():
            return f"the episodes are not {cfg.episodes} per seed of {cfg.seeds}"
        failure, top = arrays.get("episodes/failure"), len(FAILURE_CAUSES)  # codes: stages/metrics.FAILURE_CODES
        if failure is not None and ((failure < -1) | (failure > top)).any():
            return f"episodes/failure holds codes outside -1..{top}"
        if failure is not None and (failure >= 0).all() and ((failure == 0) != arrays["episodes/success"]).any():
            return f"episodes/failure disagrees with episodes/success (code 0 is a success, 1..{top} a failure's cause)"
        if "plans" in arrays and (problem := plan_width_problem(manifest, arrays["plans"].shape[-1])):
            return problem
        episodes, states = len(arrays["episodes/seed"]), arrays.get("episodes/plan_states")
        if states is not None and (np.asarray(states) <= 0).any():
            return "episodes/plan_states holds a plan of no states"
        for name, a in arrays.items():
            if not name.startswith("bodies/"):
                continue
            if np.shape(a) != (episodes,):
                return f"{name} has shape {np.shape(a)}: one entry per episode ({episodes}) expected"
            if name.endswith("/states_in_obstacle") and (
                states is None or (np.asarray(a) < 0).any() or (np.asarray(a) > np.asarray(states)).any()
            ):
                return f"{name}: counts of planned states need episodes/plan_states and must lie in 0..plan_states"
        return None


KINDS: dict[str, type[ArtifactBase]] = {c.kind: c for c in (Demos, Buffer, Model, Plans, Eval)}
