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


#: the per-seed columns averaged over the seeds by :func:`aggregate`
MEAN_FIELDS = ("in_obstacle", "plans_through_obstacle", "collisions")


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
    from cdrb_cli.stages.report import controller_name, is_policy_eval

    rows = []
    for env in args.envs.split(","):
        for method in args.methods.split(","):
            paths = sorted((args.runs / env).glob(f"eval-{method}-tuned-s*.h5"))
            paths = [p for p in paths if re.fullmatch(rf"eval-{method}-tuned-s\d+\.h5", p.name)]
            for p in sorted(paths, key=lambda p: int(p.stem.rsplit("-s", 1)[1])):
                ev = artifacts.load(p, "eval")
                s, r = ev.manifest.summary, ev.manifest.summary.per_seed[0]
                policy = is_policy_eval(ev)  # no plans, so no plan measures ("n/a")
                rows.append(
                    {
                        "env": env,
                        "method": method,
                        "seed": r.seed,
                        "episodes": r.episodes,
                        "success": round(100 * r.success_rate, 2),
                        "in_obstacle": None if policy else round(100 * (r.in_wall_fraction or 0.0), 3),
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
                        "controller": controller_name(ev)  # `cdrb report`'s name: "closed loop (SAMPLER)"
                        if policy
                        else controller_label(ev.manifest.config.controller),
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
    for a in aggregate(rows):
        if (a["env"], a["method"]) in remeasured:
            std = float("nan") if a["success_std"] is None else a["success_std"]
            plan = (
                "no plans (closed-loop policy)"
                if a["in_obstacle"] is None
                else f"in obstacle {a['in_obstacle']:6.3f}%  through {_cell(a['plans_through_obstacle'], '6.2f')}%"
            )
            print(
                f"{a['env']:22s} {a['method']:9s} seeds {a['seeds']}: success {a['success_mean']:6.2f} ± {std:5.2f}  "
                f"{plan}  collisions {a['collisions']:6.2f}%"
            )


def aggregate(rows: list[dict]) -> list[dict]:
    """Per (env, method), in Table 1's order (methods in the registry's: Table 1's for the built-ins): the seeds'
    rows, their count, the mean and sample std of success (None with one seed), the mean obstacle and collision
    rates, and the controllers and sampling steps used. Values may be numbers or CSV text ("" counts as 0)."""
    from cdrb_cli.methods.registry import METHODS

    order = {m: i for i, m in enumerate(METHODS.names())}
    groups = dict.fromkeys((r["env"], r["method"]) for r in rows)
    out = []
    for env, method in sorted(groups, key=lambda g: (_order(g[0]), g[0], order.get(g[1], 9))):
        sel = [r for r in rows if r["env"] == env and r["method"] == method]
        succ = np.array([_num(r["success"]) for r in sel])
        out.append(
            {
                "env": env,
                "method": method,
                "rows": sel,
                "seeds": len(sel),
                "episodes": int(sel[0]["episodes"]),
                "success_mean": float(succ.mean()),
                "success_std": float(succ.std(ddof=1)) if len(sel) > 1 else None,
                **{k: _mean([r[k] for r in sel]) for k in MEAN_FIELDS},
                "controllers": sorted({str(r["controller"]) for r in sel}),
                "sample_steps": sorted({str(r.get("sample_steps") or "all") for r in sel}),
            }
        )
    return out


def steps_label(steps: list[str]) -> str:
    """ ", 8 sampling steps" for a method run with fewer denoising steps than its model has, "" with all of them."""
    return "" if steps == ["all"] else f", {'/'.join(steps)} sampling steps"


def _failures(sel: list[dict]) -> str:
    """Failed episodes by cause over the seeds; rows from before the classification show "–"."""
    from cdrb_cli.envs.family import FAILURE_CAUSES

    cells = [[r.get(f"failed_{c}") for c in FAILURE_CAUSES] for r in sel]
    everything = all(_num(r["success"]) == 100.0 for r in sel)
    if any(v in (None, "") for row in cells for v in row):
        return "– (all succeeded)" if everything else "– (not classified)"
    totals = [sum(int(row[i]) for row in cells) for i in range(len(FAILURE_CAUSES))]
    return "– (all succeeded)" if everything and not sum(totals) else " / ".join(map(str, totals))


def _mean(values: list) -> float | None:
    """The mean over the seeds; None where no seed has the value (a policy's plan measures)."""
    if all(v in (None, "") for v in values):
        return None
    return float(np.mean([_num(v) for v in values]))


def _cell(value: float | None, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


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
    for a in aggregate(rows):
        env, method, sel = a["env"], a["method"], a["rows"]
        std = "–" if a["success_std"] is None else f"{a['success_std']:.1f}"
        label = "`" + " / ".join(a["controllers"]) + "`" + steps_label(a["sample_steps"])
        spec = make_spec(env)
        paper = PAPER_TABLE1.get(env, {}).get(method)
        cells = [
            family_of(spec).display_name(env),
            "CDRB" if method == "cdrb" else method,
            label,
            f"{a['seeds']} x {a['episodes']}",
            f"{a['success_mean']:.1f} ± {std}",
            _clean(sel),
            _cell(a["in_obstacle"], ".2f"),
            _cell(a["plans_through_obstacle"], ".1f"),
            f"{a['collisions']:.1f}",
            _failures(sel),
            "–" if paper is None else f"{paper[0]:.2f} ± {paper[1]:.2f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
