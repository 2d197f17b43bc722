"""Cost of geodesic balls against the paper's Euclidean balls, at K = 1,000 and 10,000 buffer states.

What the pipeline cannot time on its own: the sampler alone, apart from the network. For each K the buffer is K
states drawn from the demonstrations (normalised as training does), its transition graph is built from the same
demonstrations (:func:`cdrb_cli.geodesic.transition_graph`, as `cdrb cluster` does), and both samplers run the two
calls CDRB makes: a training degradation (a batch of windows, k ~ U{1..T-1} per window) and a sampling degradation
(one k for the batch), at the batch sizes given. Also: the geodesic sampler's set-up (all-pairs shortest paths and
their sorted tables) and its memory.

Usage: python benchmarks/geodesic_balls.py DEMOS.h5 [--ks 1000,10000] [--repeats 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from functools import partial
from pathlib import Path

import numpy as np


def bench(fn, repeats: int) -> float:
    """Median seconds of ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main() -> None:
    from cdrb_cli import artifacts
    from cdrb_cli.buffer import BallSampler, Normalizer, radii
    from cdrb_cli.geodesic import GeodesicBalls, graph_diameter, transition_graph

    ap = argparse.ArgumentParser()
    ap.add_argument("demos", type=Path)
    ap.add_argument("--ks", default="1000,10000")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--horizon", type=int, default=168)
    ap.add_argument("--steps", type=int, default=32, help="diffusion steps T (the quick preset's)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    d = artifacts.load(args.demos, "demos")
    raw = d.observations.astype(np.float64)
    z = Normalizer.fit(raw).normalize(raw)
    episode = np.empty(len(raw), dtype=np.int64)  # each row's demonstration (rows of one are consecutive)
    for e, (s, n) in enumerate(zip(d.episode_start, d.episode_length)):
        episode[s : s + n] = e
    rng = np.random.default_rng(0)
    T, H = args.steps, args.horizon
    rows = []
    for K in (int(k) for k in args.ks.split(",")):
        pts = z[rng.choice(len(z), K, replace=False)]
        edges, weights = transition_graph(pts, z, episode)
        euclid_eps = radii("linear", float(np.linalg.norm(pts.max(0) - pts.min(0))), T)
        geo_eps = radii("linear", graph_diameter(K, edges, weights), T)
        t = time.perf_counter()
        geo = GeodesicBalls(pts, edges, weights, geo_eps)
        build = time.perf_counter() - t
        euc = BallSampler(pts, euclid_eps)
        table_mb = (geo.sorted.nbytes + geo.order.nbytes) / 2**20
        for regime, batch in (("training", 32), ("sampling", 1), ("sampling", 64)):
            x = z[rng.integers(len(z), size=(batch, H))]
            ks = rng.integers(1, T, size=batch) if regime == "training" else np.full(batch, T // 2)
            te = bench(partial(euc.degrade, x, ks, rng), args.repeats)
            tg = bench(partial(geo.degrade, x, ks, rng), args.repeats)
            row = {
                "K": K, "edges": int(len(edges)), "regime": regime, "batch": batch, "euclidean_ms": te * 1e3,
                "geodesic_ms": tg * 1e3, "ratio": tg / te, "geodesic_setup_s": build, "tables_MiB": table_mb,
            }  # fmt: skip
            rows.append(row)
            print(
                f"K={K:>6,} edges={len(edges):>7,} {regime:8s} batch {batch:>3}: Euclidean {te * 1e3:8.2f} ms, "
                f"geodesic {tg * 1e3:8.2f} ms ({tg / te:4.2f}x); set-up {build:6.2f} s, tables {table_mb:7.1f} MiB"
            )
    if args.json:
        meta = {"machine": platform.processor() or platform.machine(), "results": rows}
        args.json.write_text(json.dumps(meta, indent=2) + "\n")


if __name__ == "__main__":
    main()
