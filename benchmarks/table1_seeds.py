"""Per-seed Table-1 rows from the eval artifacts of benchmarks/table1.py (issue 16's CSV: env, method, seed, success,
in_obstacle, collisions, ...), for whatever seeds have finished, so a grid run in parts can be reported as it stands.

    python benchmarks/table1_seeds.py --runs runs/fetch --envs fetch-reach,fetch-push-obstacle \
        --out docs/results/table1_fetch.csv
"""

from __future__ import annotations

import argparse
import csv
import re
from pathlib import Path

import numpy as np


def controller_label(c) -> str:
    """The controller's name and the settings that differ from its defaults: ``fetch-push-path tolerance=0.08``."""
    default = type(c).model_validate({"name": c.name}).model_dump()
    changed = [(k, v) for k, v in c.model_dump().items() if v != default[k]]
    return " ".join([c.name, *(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in changed)])


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=Path, required=True)
    ap.add_argument("--envs", required=True)
    ap.add_argument("--methods", default="mlp,diffuser,cdrb")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    from cdrb_cli import artifacts
    from cdrb_cli.envs.family import FAILURE_CAUSES

    rows = []
    for env in args.envs.split(","):
        for method in args.methods.split(","):
            paths = sorted((args.runs / env).glob(f"eval-{method}-tuned-s*.h5"))
            paths = [p for p in paths if re.fullmatch(rf"eval-{method}-tuned-s\d+\.h5", p.name)]
            for p in sorted(paths, key=lambda p: int(p.stem.rsplit("-s", 1)[1])):
                ev = artifacts.load(p, "eval")
                s, r = ev.manifest.summary, ev.manifest.summary.per_seed[0]
                rows.append(
                    {
                        "env": env,
                        "method": method,
                        "seed": r.seed,
                        "episodes": r.episodes,
                        "success": round(100 * r.success_rate, 2),
                        "in_obstacle": round(100 * (r.in_wall_fraction or 0.0), 3),
                        "plans_through_obstacle": None
                        if r.plan_crossing_rate is None
                        else round(100 * r.plan_crossing_rate, 2),
                        "collisions": round(100 * r.executed_collision_rate, 2),
                        "plan_ms": round(1000 * r.plan_seconds, 2),
                        "controller": controller_label(ev.manifest.config.controller),
                        "preset": s.model_preset,
                        **{f"failed_{c}": None if r.failures is None else r.failures[c] for c in FAILURE_CAUSES},
                    }
                )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with args.out.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    for env in args.envs.split(","):
        for method in args.methods.split(","):
            sel = [r for r in rows if r["env"] == env and r["method"] == method]
            if sel:
                succ = np.array([r["success"] for r in sel])
                std = succ.std(ddof=1) if len(succ) > 1 else float("nan")
                cross = np.mean([r["plans_through_obstacle"] or 0 for r in sel])
                print(
                    f"{env:22s} {method:9s} seeds {len(sel)}: success {succ.mean():6.2f} ± {std:5.2f}  in obstacle "
                    f"{np.mean([r['in_obstacle'] for r in sel]):6.3f}%  through {cross:6.2f}%  collisions "
                    f"{np.mean([r['collisions'] for r in sel]):6.2f}%"
                )


if __name__ == "__main__":
    main()
