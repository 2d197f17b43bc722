"""`cdrb cluster`: build the replay buffer CDRB diffuses through."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts, ui
from cdrb_cli.buffer import Normalizer, demo_features, diameter, kmeans_buffer, split_rows
from cdrb_cli.configs import ClusterConfig, ClusterSummary
from cdrb_cli.envs.registry import family_of
from cdrb_cli.errors import BadInput
from cdrb_cli.geodesic import graph_diameter, transition_graph


def fit_default_k(demos, config: ClusterConfig) -> ClusterConfig:
    """``config`` as a run on ``demos`` takes it: where ``k`` was left at its default and the demos hold fewer
    buffer states than that, every state is kept (``k = 0``: there is nothing to reduce); a ``k`` given larger than
    the states is refused by :func:`cluster`."""
    if "k" in config.model_fields_set or config.k == 0:
        return config
    states = split_rows(demos, "train" if config.split == "train" else "all").size
    if 0 < states < config.k:
        ui.log(f"{demos.path}: {states} buffer states, fewer than the default {config.k} clusters: keeping them all")
        return config.model_copy(update={"k": 0})
    return config


def cluster(demos, config: ClusterConfig, out: Path) -> artifacts.Buffer:
    """Normalize the demos' features (min-max to [-1, 1]), run k-means, snap centroids to real states, and join the
    buffer states consecutive demonstration states map to (the transition graph)."""
    t0 = time.time()
    feats = demo_features(demos, config.features).astype(np.float64)
    # the normalizer always comes from the training split, so it matches what `cdrb train` computes
    train_rows = split_rows(demos, "train")
    rows = train_rows if config.split == "train" else split_rows(demos, "all")
    if rows.size == 0:
        raise BadInput(f"{demos.path}: no {config.split} episodes to cluster", hint="collect more episodes")
    if train_rows.size == 0:
        raise BadInput(
            f"{demos.path}: no train episodes (the normalizer, shared with `cdrb train`, is fitted on them)",
            hint="collect more episodes, or collect with a smaller --valid-fraction",
        )
    norm = Normalizer.fit(feats[train_rows])
    z = norm.normalize(feats[rows])
    if not np.ptp(z, axis=0).any():  # every state the same: no buffer to diffuse over, whatever k
        raise BadInput(
            f"{demos.path}: every demonstration state is the same point, and CDRB's balls grow up to the buffer's "
            "diameter",
            hint="cluster demos that move; check how they were collected or imported",
        )
    if config.k > len(rows):
        raise BadInput(
            f"--k {config.k}: larger than the {len(rows)} buffer states", hint=f"use --k {len(rows)} or less (0 = all)"
        )
    inertia = None
    with ui.progress(transient=True) as bar:
        bar.add_task(f"k-means k={config.k}" if config.k else "full buffer", total=None, info="")
        if config.k == 0:
            keep = np.arange(len(rows))
        else:
            keep, inertia = kmeans_buffer(z, config.k, seed=config.seed, n_init=config.n_init, max_iter=config.max_iter)
    if config.k and len(keep) < config.k:
        ui.warn(f"--k {config.k}: the demos hold fewer distinct states, so the buffer has {len(keep)}")
    points = z[keep].astype(np.float32)
    extent = diameter(points)
    if extent <= 0:
        raise BadInput(
            f"--k {config.k}: every state of the buffer of {demos.path} would be the same point (diameter 0), and "
            f"CDRB's balls grow up to the buffer's diameter",
            hint="use --k 2 or more",
        )
    # which buffer states the demonstrations connect (geodesic balls measure along it): each row's episode
    episode = np.repeat(np.arange(len(demos.episode_start)), demos.episode_length)
    order = np.concatenate([np.arange(s, s + n) for s, n in zip(demos.episode_start, demos.episode_length)])
    row_episode = np.empty(len(order), dtype=np.int64)
    row_episode[order] = episode
    dims = family_of(demos.manifest.env).position_dims(demos.manifest.env) if config.graph_join == "position" else None
    edges, weights = transition_graph(points, z, row_episode[rows], dims)
    reach = graph_diameter(len(points), edges, weights)
    summary = ClusterSummary(
        points=int(len(points)),
        source_states=int(len(rows)),
        feature_dim=int(points.shape[1]),
        diameter=round(extent, 6),
        graph_diameter=None if reach is None else round(reach, 6),
        inertia=inertia,
        wall_time_s=round(time.time() - t0, 3),
    )
    manifest = artifacts.make_manifest(
        "buffer", env=demos.manifest.env, config=config, seed=config.seed, parents=[demos], summary=summary
    )
    arrays = {
        "points": points,
        "source_index": rows[keep].astype(np.int64),
        "normalizer/low": norm.low,
        "normalizer/high": norm.high,
        "graph/edges": edges,
        "graph/weights": weights.astype(np.float32),
    }
    artifacts.save(out, "buffer", manifest, arrays)
    return artifacts.load(out, "buffer")
