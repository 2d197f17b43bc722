"""Open loop vs re-planning vs plan repair (issue 18), every setting chosen on the tuning stream.

    python benchmarks/closed_loop.py tune  --env maze-tight --models runs/cmp/maze-tight --out runs/cl
    python benchmarks/closed_loop.py test  --env maze-tight --models runs/cmp/maze-tight --out runs/cl --seeds 0,1,2
    python benchmarks/closed_loop.py write --env maze-tight --out runs/cl [--write-docs]
    python benchmarks/closed_loop.py tune --env fetch-push-obstacle --models runs/fetch/fetch-push-obstacle \
        --tuned runs/fetch/tuned_fetch-push-obstacle.json --out runs/cl       (then test --seeds 0,1,2,3,4, write)

``--models`` holds each method's Table-1 models, METHOD-tuned-sSEED.h5 (benchmarks/table1.py), evaluated with the
method's own tuned clock (``--tuned``, docs/results/tuned.json). ``tune`` tries, on training seed 0's model and the
tuning stream, each re-planning trigger from scratch and with repair (the MLP has no partial degradation: its repair
re-predicts, so it is tried from scratch only) and picks per method the best from-scratch and the best repair setting
(success, then fewer plans through a wall, then less planning time). ``test`` evaluates open loop and the two picks
of every method on the test pairs, one eval per training seed (test seed = training seed, as Table 1). Each eval is a
`cdrb eval` run, skipped when up to date, so the script resumes. ``--picks FILE`` (a ``closed_loop_ENV_picks.json``
that ``write`` recorded) takes the picks from that file instead of the tuning evals, so more training seeds can be
tested with the settings chosen earlier, once their tuning evals are gone:

    python benchmarks/closed_loop.py test --env maze-tight --models runs/cmp/maze-tight --out runs/cl --seeds 3,4 \
        --picks docs/results/closed_loop_maze-tight_picks.json

``write --pool-with CSV`` then joins an earlier run's CSV (other training seeds, the same settings): each test row's
success becomes the mean and sample std over all the seeds (from the earlier row's mean, std and seed count: exact up
to its 2-decimal rounding), the other rates their seed-weighted means, the failure counts their sums; the earlier
tuning rows are kept where this run has none.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: the re-planning triggers tried, per environment family (the same list for every method: an equal tuning budget).
#: Maze episodes are 400 steps and the ball drifts by tenths of a metre; a Fetch task's are 50-100 steps (1-2 per
#: planned state) and the gripper or block must stay within centimetres of its path.
TRIGGERS = {
    "pointmaze": ["every:20", "every:40", "deviation:0.5"],
    "fetch": ["every:20", "every:30", "every:45", "deviation:0.15"],
}
REPAIRS = {"from scratch": [], "repair k=4": ["--repair-k", "4"]}
METHODS = ("mlp", "diffuser", "cdrb")


def cdrb(args: list, log: Path) -> None:
    t = time.time()
    proc = subprocess.run([sys.executable, "-m", "cdrb_cli", *map(str, args)], capture_output=True, text=True)
    line = f"{'done' if proc.returncode == 0 else 'FAILED'} {time.time() - t:7.1f}s cdrb {' '.join(map(str, args))}"
    print(line, flush=True)
    with log.open("a") as f:
        f.write(line + "\n")
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr[-3000:])
        raise SystemExit(1)


def slug(text: str) -> str:
    return text.replace(" ", "-").replace("=", "").replace(".", "")


def candidates(method: str, env: str = "maze-tight") -> dict[str, list]:
    from cdrb_cli.envs.registry import make_spec

    out = {"open loop": []}
    for t in TRIGGERS[make_spec(env).family]:
        for r, rf in REPAIRS.items():
            if method == "mlp" and rf:
                continue
            out[f"{t.replace(':', ' ')}, {r}"] = ["--replan", t, *rf]
    return out


def summary(path: Path) -> dict:
    from cdrb_cli import artifacts

    s = artifacts.load(path, "eval").manifest.summary
    return {
        "success": 100 * s.success_mean,
        "success_std": 100 * s.success_std,
        "crossing": None if s.plan_crossing_mean is None else 100 * s.plan_crossing_mean,
        "collision": 100 * s.executed_collision_mean,
        "replans": s.replans_mean or 0.0,
        "planning_ms": 1000 * (s.planning_seconds_mean if s.planning_seconds_mean is not None else s.plan_seconds_mean),
        "seeds": [r.seed for r in s.per_seed],
        "failures": s.failures,
    }


def clock(args, method: str) -> list:
    tuned = json.loads(Path(args.tuned).read_text())["settings"][args.env][method]
    return list(tuned["eval_flags"])


def tune(args) -> None:
    folder = args.out / args.env / "tune"
    folder.mkdir(parents=True, exist_ok=True)
    for method in args.methods:
        model = args.models / f"{method}-tuned-s0.h5"
        for name, flags in candidates(method, args.env).items():
            out = folder / f"{method}-{slug(name)}.h5"
            cdrb(
                [
                    "eval",
                    model,
                    "--stream",
                    "tune",
                    "--seeds",
                    args.tune_seeds,
                    "--episodes",
                    args.tune_episodes,
                    *clock(args, method),
                    *flags,
                    "--out",
                    out,
                    "--device",
                    "cpu",
                ],
                args.out / "log.txt",
            )


def picks(args) -> dict[str, dict[str, str]]:
    """Per method: the best closed-loop setting from scratch and with repair, on the tuning stream (or as ``--picks``
    recorded them)."""
    if args.picks is not None:
        recorded = json.loads(args.picks.read_text())
        missing = [m for m in args.methods if m not in recorded]
        if missing:
            raise SystemExit(f"--picks {args.picks}: no picks for {', '.join(missing)}; leave them out of --methods")
        return {m: recorded[m] for m in args.methods}
    folder = args.out / args.env / "tune"
    chosen = {}
    for method in args.methods:
        rows = {}
        for name in candidates(method, args.env):
            p = folder / f"{method}-{slug(name)}.h5"
            if p.exists():
                rows[name] = summary(p)
        key = lambda n, rows=rows: (-rows[n]["success"], rows[n]["crossing"] or 0.0, rows[n]["planning_ms"])  # noqa: E731
        pick = {"open loop": "open loop"}
        for r in REPAIRS:
            names = [n for n in rows if n.endswith(r)]
            if names:
                pick[r] = min(names, key=key)
        chosen[method] = pick
    return chosen


def test(args) -> None:
    folder = args.out / args.env / "test"
    folder.mkdir(parents=True, exist_ok=True)
    for method, pick in picks(args).items():
        for name in pick.values():
            flags = candidates(method, args.env)[name]
            for seed in args.seeds.split(","):
                out = folder / f"{method}-{slug(name)}-s{seed}.h5"
                model = args.models / f"{method}-tuned-s{seed}.h5"
                cdrb(
                    [
                        "eval",
                        model,
                        "--stream",
                        "test",
                        "--seeds",
                        seed,
                        "--episodes",
                        args.episodes,
                        *clock(args, method),
                        *flags,
                        "--out",
                        out,
                        "--device",
                        "cpu",
                    ],
                    args.out / "log.txt",
                )


def failed_by_cause(counts: list) -> dict:
    """Failed episodes per cause summed over evals, as ``failed_<cause>`` columns (None: an eval not classified)."""
    from cdrb_cli.envs.family import FAILURE_CAUSES
    from cdrb_cli.stages.evaluate import sum_failures

    total = sum_failures(counts)
    return {f"failed_{cause}": None if total is None else total[cause] for cause in FAILURE_CAUSES}


def read_rows(path: Path) -> list[dict]:
    """An earlier `write`'s CSV rows (numbers as floats, empty cells as None); a one-line error when unreadable."""
    try:
        with path.open(newline="") as f:
            rows = list(csv.DictReader(f))
    except OSError as e:
        raise SystemExit(f"--pool-with {path}: cannot read it ({e.strerror}); pass a closed_loop_ENV.csv") from None
    need = {"stage", "method", "setting", "training_seeds", "success", "success_std"}
    if not rows or not need <= set(rows[0]):
        raise SystemExit(f"--pool-with {path}: not a closed_loop_ENV.csv (needs the columns {', '.join(sorted(need))})")

    def value(k: str, v: str):
        if k in ("stage", "env", "method", "setting", "seeds") or v is None:
            return v
        return None if v == "" else float(v)

    return [{k: value(k, v) for k, v in r.items()} for r in rows]


def pool(n1: int, m1: float, s1: float, n2: int, m2: float, s2: float) -> tuple[float, float]:
    """Mean and sample std (ddof = 1) of two groups of n1 and n2 values, from each group's mean and sample std."""
    n = n1 + n2
    mean = (n1 * m1 + n2 * m2) / n
    squares = (n1 - 1) * s1**2 + n1 * m1**2 + (n2 - 1) * s2**2 + n2 * m2**2
    return mean, max(squares - n * mean**2, 0.0) ** 0.5 / (n - 1) ** 0.5 if n > 1 else 0.0


def pool_rows(rows: list[dict], earlier: list[dict]) -> list[dict]:
    """This run's rows joined with an earlier run's (see the module doc): test rows pooled over both runs' seeds."""
    key = lambda r: (r["stage"], r["method"], r["setting"])  # noqa: E731
    before = {key(r): r for r in earlier}
    mine = {key(r) for r in rows}
    out = [r for r in earlier if r["stage"] == "tune" and key(r) not in mine]
    for r in rows:
        e = before.get(key(r))
        if r["stage"] != "test" or e is None:
            out.append(r)
            continue
        common = set((e.get("seeds") or "").split()) & set(r["seeds"].split())
        if common:
            raise SystemExit(f"--pool-with: {r['method']} '{r['setting']}' has training seed(s) {sorted(common)} twice")
        n1, n2 = int(e["training_seeds"]), int(r["training_seeds"])
        mean, std = pool(n1, e["success"], e["success_std"], n2, r["success"], r["success_std"])
        joined = dict(r, training_seeds=n1 + n2, success=round(mean, 2), success_std=round(std, 2))
        joined["seeds"] = f"{e.get('seeds') or f'({n1} earlier)'} {r['seeds']}"
        for k, digits in (("crossing", 2), ("collision", 2), ("replans", 2), ("planning_ms", 1)):
            both = e.get(k) is not None and r[k] is not None
            joined[k] = round((n1 * e[k] + n2 * r[k]) / (n1 + n2), digits) if both else None
        for k in r:
            if k.startswith("failed_"):
                joined[k] = None if e.get(k) is None or r[k] is None else int(e[k]) + r[k]
        out.append(joined)
    return out


def write(args) -> None:
    import numpy as np

    from cdrb_cli import artifacts

    rows = []
    for name_ in ("tune", "test"):
        folder = args.out / args.env / name_
        for method in args.methods:
            for name in candidates(method, args.env):
                paths = sorted(
                    folder.glob(f"{method}-{slug(name)}.h5" if name_ == "tune" else f"{method}-{slug(name)}-s*.h5")
                )
                if not paths:
                    continue
                ss = [summary(p) for p in paths]
                succ = [s["success"] for s in ss]
                rows.append(
                    {
                        "stage": name_,
                        "env": args.env,
                        "method": method,
                        "setting": name,
                        "training_seeds": len(ss),
                        "seeds": " ".join(str(x) for s in ss for x in s["seeds"]),
                        "success": round(float(np.mean(succ)), 2),
                        "success_std": round(float(np.std(succ, ddof=1)) if len(succ) > 1 else ss[0]["success_std"], 2),
                        "crossing": round(float(np.mean([s["crossing"] or 0.0 for s in ss])), 2),
                        "collision": round(float(np.mean([s["collision"] for s in ss])), 2),
                        "replans": round(float(np.mean([s["replans"] for s in ss])), 2),
                        "planning_ms": round(float(np.mean([s["planning_ms"] for s in ss])), 1),
                        # test rows only: the causes are counted on the test pairs
                        **failed_by_cause([s["failures"] if name_ == "test" else None for s in ss]),
                    }
                )
    if not rows:
        raise SystemExit(f"{args.out / args.env}: no tune or test evals yet; run `tune` (and `test`) first")
    if args.pool_with is not None:
        rows = pool_rows(rows, read_rows(args.pool_with))
    dest = ROOT / "docs" / "results" if args.write_docs else args.out
    dest.mkdir(parents=True, exist_ok=True)
    path = dest / f"closed_loop_{args.env}.csv"
    with artifacts.atomic_path(path) as tmp, tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for r in rows for k in r)))
        w.writeheader()
        w.writerows(rows)
    with artifacts.atomic_path(dest / f"closed_loop_{args.env}_picks.json") as tmp:
        tmp.write_text(json.dumps(picks(args), indent=1))
    print(path)
    for r in rows:
        print(r)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("part", choices=["tune", "test", "write"])
    ap.add_argument("--env", default="maze-tight")
    ap.add_argument("--models", type=Path, default=Path("runs/cmp/maze-tight"))
    ap.add_argument("--tuned", type=Path, default=ROOT / "docs" / "results" / "tuned.json")
    ap.add_argument("--out", type=Path, default=Path("runs/cl"))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--tune-seeds", default="0")
    ap.add_argument("--tune-episodes", default="50")
    ap.add_argument("--seeds", default="0,1,2")
    ap.add_argument("--episodes", default="100")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument("--pool-with", type=Path, default=None, help="an earlier run's CSV to pool with (write)")
    ap.add_argument("--picks", type=Path, default=None, help="the picks recorded by an earlier `write` (test, write)")
    args = ap.parse_args()
    args.methods = args.methods.split(",")
    args.out.mkdir(parents=True, exist_ok=True)
    {"tune": tune, "test": test, "write": write}[args.part](args)


if __name__ == "__main__":
    main()
