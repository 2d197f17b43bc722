"""Reading artifacts written by older major schema versions: each migration turns an old manifest (JSON) and old
arrays into the current layout, in memory; the file on disk (and so its sha256) is never changed.

Schema 2 (cdrb 0.2, the families/registry redesign) changed, for every kind:

* ``env``: ``family``, ``maze`` and ``position_noise`` moved into ``env.scene`` (the family's own part);
* ``model``: tensors are kept per module (``weights/net/...``, ``ema/net/...``) and optimizer state per optimizer
  and module (``optim/net/net/<parameter>/...``), so methods with several networks and optimizers fit;
* ``eval``: the controller's settings moved into ``config.controller`` (a 1.0 file, written before the gated plan
  clock existed, followed plans on the environment's clock: ``max_lag`` null).

Minor versions that renamed values are migrated too (:func:`migrate_minor`): schema 2.2 renamed CDRB's radius
schedule ``log`` (log-spaced, convex) to ``geometric`` (``log`` is now the official code's concave schedule) and
the CDRB samplers ``alg1``/``alg2`` to ``paper``/``cold-improved``, and records for older CDRB models that the
action part of their end states was kept (``method.end_actions = "kept"``; only state-action models differ);
CDRB models before 2.8 drew 32 rejection candidates for every ball (``method.ball_candidates = "fixed"``);
before 2.14 geodesic radii were the schedule stretched to the graph's diameter (``method.geodesic_radii =
"scaled"``), and evals before 2.17 of geodesic models name that variant.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

Manifest = dict
Arrays = dict


def _env_v1(env: dict) -> dict:
    env = dict(env)
    scene = {"family": env.pop("family", "pointmaze")}
    for key in ("maze", "position_noise"):
        if key in env:
            scene[key] = env.pop(key)
    env["scene"] = scene
    return env


def _manifest_v1(kind: str, m: Manifest) -> Manifest:
    m = dict(m)
    if isinstance(m.get("env"), dict):
        m["env"] = _env_v1(m["env"])
    if kind == "eval" and isinstance(m.get("config"), dict):
        cfg = dict(m["config"])
        name = cfg.pop("controller", "pd")
        kp, kd = cfg.pop("kp", 10.0), cfg.pop("kd", 1.0)
        max_lag = cfg.pop("max_lag", None)
        controller = {"name": name, "max_lag": max_lag}
        if name == "pd":
            controller.update(kp=kp, kd=kd)
        cfg["controller"] = controller
        m["config"] = cfg
    return m


def _arrays_v1(kind: str, arrays: Arrays) -> Arrays:
    if kind != "model":
        return arrays
    out = {}
    for name, value in arrays.items():
        head, _, rest = name.partition("/")
        if head in ("weights", "ema"):
            name = f"{head}/net/{rest}"
        elif head == "optim":
            param, _, key = rest.rpartition("/")
            name = f"optim/net/net/{param}/{key}"
            if key == "step":  # stored as a float64 (1,) array; torch keeps a float32 scalar
                value = np.asarray(value, dtype=np.float32).reshape(())
        out[name] = value
    return out


#: kind -> {old major: (manifest migration, arrays migration)}
MIGRATIONS: dict[str, dict[int, tuple[Callable[[Manifest], Manifest], Callable[[Arrays], Arrays]]]] = {
    kind: {1: (lambda m, k=kind: _manifest_v1(k, m), lambda a, k=kind: _arrays_v1(k, a))}
    for kind in ("demos", "buffer", "model", "plans", "eval")
}


def can_migrate(kind: str, major: int) -> bool:
    return major in MIGRATIONS.get(kind, {})


def migrate_manifest(kind: str, major: int, manifest: Manifest) -> Manifest:
    return MIGRATIONS[kind][major][0](manifest)


def migrate_arrays(kind: str, major: int, arrays: Arrays) -> Arrays:
    return MIGRATIONS[kind][major][1](arrays)


_SAMPLERS_2_2 = {"alg1": "paper", "alg2": "cold-improved"}


def _renames_2_2(kind: str, m: Manifest) -> Manifest:
    m = dict(m)
    cfg = m.get("config")
    if not isinstance(cfg, dict):
        return m
    cfg = dict(cfg)
    if kind == "model" and isinstance(cfg.get("method"), dict) and cfg["method"].get("name") == "cdrb":
        method = dict(cfg["method"])
        if method.get("schedule") == "log":
            method["schedule"] = "geometric"
        if method.get("sampler") in _SAMPLERS_2_2:
            method["sampler"] = _SAMPLERS_2_2[method["sampler"]]
        method.setdefault("end_actions", "kept")  # before 2.2 the ends' action part was never degraded
        cfg["method"] = method
    if kind in ("plans", "eval") and cfg.get("sampler") in _SAMPLERS_2_2:
        cfg["sampler"] = _SAMPLERS_2_2[cfg["sampler"]]
    m["config"] = cfg
    return m


def _fetch_draws_2_4(kind: str, m: Manifest) -> Manifest:
    """Fetch scenes written before goals kept their distance from the start drew goals at any distance: their
    ``min_goal_distance`` is 0 (a file that records one keeps it; demos/buffer/model/plans 2.4, eval 2.6)."""
    env = m.get("env")
    scene = env.get("scene") if isinstance(env, dict) else None
    if not isinstance(scene, dict) or scene.get("family") != "fetch" or "min_goal_distance" in scene:
        return m
    return {**m, "env": {**env, "scene": {**scene, "min_goal_distance": 0.0}}}


def _checkpoint_seconds_2_5(kind: str, m: Manifest) -> Manifest:
    """Models written before training also checkpointed by time checkpointed by steps only: their
    ``checkpoint_seconds`` is 0 (model 2.5)."""
    cfg = m.get("config")
    if kind != "model" or not isinstance(cfg, dict) or "checkpoint_seconds" in cfg:
        return m
    return {**m, "config": {**cfg, "checkpoint_seconds": 0.0}}


def _ball_candidates_2_8(kind: str, m: Manifest) -> Manifest:
    """CDRB models written before the ball sampler sized its first rejection round by the ball's radius drew 32
    candidates for every ball: ``method.ball_candidates`` is ``fixed`` for them, so they sample (and resume
    training) with the very draws they made then (model 2.8)."""
    cfg = m.get("config")
    method = cfg.get("method") if isinstance(cfg, dict) else None
    if kind != "model" or not isinstance(method, dict) or method.get("name") != "cdrb":
        return m
    return {**m, "config": {**cfg, "method": {"ball_candidates": "fixed", **method}}}


def _geodesic_radii_2_14(kind: str, m: Manifest) -> Manifest:
    """CDRB models written before geodesic radii were matched to the paper's ball sizes stretched the schedule to
    the graph's diameter: ``method.geodesic_radii`` is ``scaled`` for them, so they degrade as they were trained
    (model 2.14)."""
    cfg = m.get("config")
    method = cfg.get("method") if isinstance(cfg, dict) else None
    if kind != "model" or not isinstance(method, dict) or method.get("ball") != "geodesic":
        return m  # Euclidean balls read no geodesic radii: their models stay equal to a new request's config
    return {**m, "config": {**cfg, "method": {"geodesic_radii": "scaled", **method}}}


def _geodesic_variant_2_17(kind: str, m: Manifest) -> Manifest:
    """Evals written before geodesic radii were matched evaluated models with the scaled radii, then the only ones,
    under the variant "geodesic balls": they read as "geodesic balls, scaled radii", what such a model is called now,
    so `cdrb report` keeps them apart from evals of matched-radii models (eval 2.17)."""
    summary = m.get("summary")
    variant = summary.get("variant") if isinstance(summary, dict) else None
    if kind != "eval" or not isinstance(variant, str) or not variant.startswith("geodesic balls"):
        return m
    return {
        **m,
        "summary": {**summary, "variant": variant.replace("geodesic balls", "geodesic balls, scaled radii", 1)},
    }


def _plan_batch_2_11(kind: str, m: Manifest) -> Manifest:
    """Plans written before the batch size was recorded: ``batch`` is null (unknown; the size sets the random
    streams), so no request counts such a file as up to date (plans 2.11)."""
    cfg = m.get("config")
    if kind != "plans" or not isinstance(cfg, dict) or "batch" in cfg:
        return m
    return {**m, "config": {**cfg, "batch": None}}


#: (version, manifest migration) for minor versions that renamed values or gave a recorded setting a default that
#: older files did not follow; applied to every older file in order
MINOR_MIGRATIONS: list[tuple[tuple[int, int], Callable[[str, Manifest], Manifest]]] = [
    ((2, 2), _renames_2_2),
    ((2, 5), _checkpoint_seconds_2_5),
    ((2, 6), _fetch_draws_2_4),
    ((2, 8), _ball_candidates_2_8),
    ((2, 11), _plan_batch_2_11),
    ((2, 14), _geodesic_radii_2_14),
    ((2, 17), _geodesic_variant_2_17),
]


def migrate_minor(kind: str, version: tuple[int, int], manifest: Manifest) -> Manifest:
    """Apply every value-renaming migration newer than ``version`` (the file's)."""
    for since, fn in MINOR_MIGRATIONS:
        if version < since:
            manifest = fn(kind, manifest)
    return manifest


def _eval_replans_2_4(arrays: Arrays) -> Arrays:
    """Before 2.4 an episode planned once (or called its policy step by step): no re-plans, and the episode's
    planning time is its one plan's."""
    n = len(arrays["episodes/seed"])
    return {
        "episodes/replans": np.zeros(n, dtype=np.int64),
        "episodes/planning_seconds": arrays["episodes/plan_seconds"],
    }


def _eval_failure_2_5(arrays: Arrays) -> Arrays:
    """Before 2.5 failed episodes were not classified by cause: code -1 (not measured) for every episode."""
    return {"episodes/failure": np.full(len(arrays["episodes/seed"]), -1, dtype=np.int64)}


#: kind -> (the minor version that added some optional datasets, their names, their meaning for a file without them
#: as a function of its arrays)
OPTIONAL_ARRAYS: dict[str, list[tuple[tuple[int, int], tuple[str, ...], Callable[[Arrays], Arrays]]]] = {
    "eval": [
        ((2, 4), ("episodes/replans", "episodes/planning_seconds"), _eval_replans_2_4),
        ((2, 5), ("episodes/failure",), _eval_failure_2_5),
    ]
}


def backfill_arrays(kind: str, arrays: Arrays, version: tuple[int, int] | None = None) -> Arrays:
    """``arrays`` with the optional datasets it lacks filled in with what their absence means, never replacing one
    it has: those added after ``version`` (the reader, for an older file), or with no version every one (what the
    eval stage computes from: a file may leave optional datasets out)."""
    for since, names, fn in OPTIONAL_ARRAYS.get(kind, []):
        if (version is None or version < since) and not all(n in arrays for n in names):
            arrays = {**fn(arrays), **arrays}
    return arrays
