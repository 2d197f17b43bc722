"""Per-seed Table-1 rows from the eval artifacts of benchmarks/table1.py (issue 16's CSV: env, method, seed, success,
in_obstacle, collisions, ...), for whatever seeds have finished, so a grid run in parts can be reported as it stands.

    python benchmarks/table1_seeds.py --runs runs/fetch --envs fetch-reach,fetch-push-obstacle \
        --out docs/results/table1_fetch.csv [--merge] [--docs docs/benchmarks.md]

``--merge`` keeps the CSV's rows of the environments not listed (rows measured in earlier parts of the grid);
``--docs`` rewrites the block between ``<!-- fetch-rows:begin -->`` and ``<!-- fetch-rows:end -->`` of the file from
the whole CSV (mean ± sample std over the seeds, the paper's row beside ours).
"""

from __future__ import annotations

import argparse
import csv
import re
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from table1 import TABLE1_ENVS, replace_block  # noqa: E402

#: the CSV's columns, in order
FIELDS = (
    "env", "method", "seed", "episodes", "success", "in_obstacle", "plans_through_obstacle", "collisions",
    "success_no_collision", "plan_ms", "controller", "sample_steps", "preset",
    "failed_plan", "failed_grasp", "failed_collision", "failed_tracking",
)  # fmt: skip


def _order(env: str) -> int:
    """Table 1's row order (other environments after its eight)."""
    return TABLE1_ENVS.index(env) if env in TABLE1_ENVS else len(TABLE1_ENVS)


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
    ap.add_argument("--merge", action="store_true", help="keep the --out CSV's rows of the environments not listed")
    ap.add_argument("--docs", type=Path, default=None, help="rewrite this markdown file's fetch-rows block")
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
                        # successes whose executed path never touched an obstacle (a gripper blocked by a wall may
                        # still scrape over it and succeed: success alone does not show it)
                        "success_no_collision": round(
                            100
                            * float(np.mean(ev.arrays["episodes/success"] & ~ev.arrays["episodes/executed_collision"])),
                            2,
                        ),
                        "plan_ms": round(1000 * r.plan_seconds, 2),
                        "controller": controller_label(ev.manifest.config.controller),
                        "sample_steps": ev.manifest.config.sample_steps or "all",
                        "preset": s.model_preset,
                        **{f"failed_{c}": None if r.failures is None else r.failures[c] for c in FAILURE_CAUSES},
                    }
                )
    if not rows:  # a wrong --runs or nothing finished: leave the CSV and the docs as they are
        raise SystemExit(f"{args.runs}: no eval-METHOD-tuned-sN.h5 for {args.envs} / {args.methods}; nothing written")
    remeasured = {(e, m) for e in args.envs.split(",") for m in args.methods.split(",")}
    if args.merge and args.out.exists():
        with args.out.open() as f:
            kept = [r for r in csv.DictReader(f) if (r["env"], r["method"]) not in remeasured]
        for r in kept:  # rows from before a column existed: sampling steps were all of them then
            r["sample_steps"] = r.get("sample_steps") or "all"
        rows = kept + rows
    rows.sort(key=lambda r: (_order(r["env"]), r["env"], r["method"], int(r["seed"])))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with artifacts.atomic_path(args.out) as tmp, tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS, restval="")
        w.writeheader()
        w.writerows(rows)
    if args.docs is not None:
        text = replace_block(args.docs.read_text(), "fetch-rows", markdown(args.out))
        with artifacts.atomic_path(args.docs) as tmp:
            tmp.write_text(text)
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


def _failures(sel: list[dict]) -> str:
    """Failed episodes by cause over the seeds; rows from before the classification show "–"."""
    from cdrb_cli.envs.family import FAILURE_CAUSES

    cells = [[r.get(f"failed_{c}") for c in FAILURE_CAUSES] for r in sel]
    everything = all(_num(r["success"]) == 100.0 for r in sel)
    if any(v in (None, "") for row in cells for v in row):
        return "– (all succeeded)" if everything else "– (not classified)"
    totals = [sum(int(row[i]) for row in cells) for i in range(len(FAILURE_CAUSES))]
    return "– (all succeeded)" if everything and not sum(totals) else " / ".join(map(str, totals))


def _num(text) -> float:
    return float(text) if text not in (None, "") else 0.0


def _clean(sel: list[dict]) -> str:
    """Mean success without a collision over the seeds, "–" where rows from before that column lack it."""
    vals = [r.get("success_no_collision") for r in sel]
    if any(v in (None, "") for v in vals):
        return "–"
    return f"{np.mean([float(v) for v in vals]):.1f}"


def markdown(path: Path) -> str:
    """The Fetch rows of Table 1 from the per-seed CSV: one line per env and method, the paper's beside."""
    from cdrb_cli.envs.registry import family_of, make_spec
    from cdrb_cli.methods.registry import METHODS
    from cdrb_cli.stages.report import PAPER_TABLE1

    with path.open() as f:
        rows = list(csv.DictReader(f))
    head = (
        "| env | method | controller | training seeds x test pairs | success (%) | success without a collision (%) "
        "| planned states in obstacles (%) | plans through an obstacle (%) | executed collisions (%) | failed "
        "episodes: plan / grasp / collision / tracking | paper (%) |\n"
        "|---|---|---|---|---:|---:|---:|---:|---:|---|---:|"
    )
    lines = [head]
    order = {m: i for i, m in enumerate(METHODS.names())}  # the registry's order: Table 1's for the built-ins
    groups = dict.fromkeys((r["env"], r["method"]) for r in rows)
    for env, method in sorted(groups, key=lambda g: (_order(g[0]), g[0], order.get(g[1], 9))):
        sel = [r for r in rows if r["env"] == env and r["method"] == method]
        succ = np.array([_num(r["success"]) for r in sel])
        std = f"{succ.std(ddof=1):.1f}" if len(sel) > 1 else "–"
        controllers = sorted({r["controller"] for r in sel})
        steps = sorted({r.get("sample_steps") or "all" for r in sel})
        label = (
            "`" + " / ".join(controllers) + "`" + ("" if steps == ["all"] else f", {'/'.join(steps)} sampling steps")
        )
        spec = make_spec(env)
        paper = PAPER_TABLE1.get(env, {}).get(method)
        cells = [
            family_of(spec).display_name(env),
            "CDRB" if method == "cdrb" else method,
            label,
            f"{len(sel)} x {sel[0]['episodes']}",
            f"{succ.mean():.1f} ± {std}",
            _clean(sel),
            f"{np.mean([_num(r['in_obstacle']) for r in sel]):.2f}",
            f"{np.mean([_num(r['plans_through_obstacle']) for r in sel]):.1f}",
            f"{np.mean([_num(r['collisions']) for r in sel]):.1f}",
            _failures(sel),
            "–" if paper is None else f"{paper[0]:.2f} ± {paper[1]:.2f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
