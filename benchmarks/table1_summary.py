"""All eight rows of Table 1 in one CSV and one markdown table: the maze rows (benchmarks/table1.py's report,
docs/results/table1.csv), the closed-loop policies' rows (the same report over their evals,
docs/results/table1_policies.csv, when it exists) and the Fetch rows (benchmarks/table1_seeds.py's per-seed CSV), one
line per environment and method, with the paper's figure beside ours.

    python benchmarks/table1_summary.py --out docs/results/table1_all.csv --readme README.md

``--readme`` (or any markdown file) rewrites the block between ``<!-- table1-all:begin -->`` and
``<!-- table1-all:end -->``: one line per Table-1 row, success (mean ± sample std over the training seeds) of each
method next to the paper's, and CDRB's planned-in-obstacle rates. Rows not measured yet show "–".
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from table1 import DOCS, TABLE1_ENVS, replace_block  # noqa: E402
from table1_seeds import MEAN_FIELDS, aggregate, steps_label  # noqa: E402

#: the CSV's columns, in order
FIELDS = (
    "env", "method", "training_seeds", "episodes_per_seed", "success_mean", "success_std", "in_obstacle",
    "plans_through_obstacle", "collisions", "paper_mean", "paper_std", "setting", "source",
)  # fmt: skip
METHODS = ("mlp", "diffuser", "diffusion-bc", "diffusion-ql", "cdrb")  # the paper's column order
#: the README block's column names
TITLES = {
    "mlp": "MLP",
    "diffuser": "Diffuser",
    "diffusion-bc": "Diffusion BC",
    "diffusion-ql": "Diffusion-QL",
    "cdrb": "CDRB",
}


def _f(text) -> float | None:
    return None if text in (None, "") else float(text)


def maze_rows(path: Path) -> list[dict]:
    """The maze rows of `cdrb report`'s CSV (already aggregated over the training seeds; percentages)."""
    with path.open() as f:
        rows = list(csv.DictReader(f))
    return [
        {
            "env": r["env"],
            "method": r["method"],
            "training_seeds": int(r["seeds"]),
            "episodes_per_seed": int(r["episodes"]),
            "success_mean": _f(r["success_mean"]),
            "success_std": _f(r["success_std"]),
            "in_obstacle": _f(r["in_wall_mean"]),
            "plans_through_obstacle": _f(r["crossing_mean"]),
            "collisions": _f(r["collision_mean"]),
            "setting": r["controller"],
            "source": path.name,
        }
        for r in rows
        if r["env"] in TABLE1_ENVS and r.get("protocol", "") != "official-code"
    ]


def fetch_rows(path: Path) -> list[dict]:
    """The per-seed rows of table1_seeds.py, aggregated per (env, method) as its own table is: mean and sample std
    over the seeds."""
    with path.open() as f:
        rows = list(csv.DictReader(f))
    return [
        {
            "env": a["env"],
            "method": a["method"],
            "training_seeds": a["seeds"],
            "episodes_per_seed": a["episodes"],
            "success_mean": a["success_mean"],
            "success_std": a["success_std"],
            **{k: a[k] for k in MEAN_FIELDS},
            "setting": " / ".join(a["controllers"]) + steps_label(a["sample_steps"]),
            "source": path.name,
        }
        for a in aggregate(rows)
    ]


def combine(mazes: list[dict], fetch: list[dict]) -> list[dict]:
    """Both sources in Table 1's order, the paper's figure on each row; a Fetch row wins over a maze-CSV row (the
    policies' report rows join ``mazes``)."""
    from cdrb_cli.stages.report import PAPER_TABLE1

    rows = {(r["env"], r["method"]): r for r in mazes}
    rows.update({(r["env"], r["method"]): r for r in fetch})
    out = []
    for (env, method), r in rows.items():
        paper = PAPER_TABLE1.get(env, {}).get(method)
        out.append(
            {**r, "paper_mean": None if paper is None else paper[0], "paper_std": None if paper is None else paper[1]}
        )
    rank = {m: i for i, m in enumerate(METHODS)}
    out.sort(key=lambda r: (TABLE1_ENVS.index(r["env"]), rank.get(r["method"], len(METHODS)), r["method"]))
    return out


def markdown(rows: list[dict]) -> str:
    """One line per Table-1 row: each method's success with the paper's in brackets, and CDRB's obstacle rates."""
    from cdrb_cli.envs.registry import family_of, make_spec
    from cdrb_cli.stages.report import PAPER_TABLE1

    def cell(r: dict | None, method: str) -> str:
        if r is None:
            return "–"
        std = "–" if r["success_std"] is None else f"{r['success_std']:.1f}"
        text = f"{r['success_mean']:.1f} ± {std}"
        return f"**{text}**" if method == "cdrb" else text

    lines = [
        "| Table 1 row | seeds x pairs | " + " | ".join(TITLES[m] for m in METHODS) + " | CDRB: planned states in "
        "obstacles / plans through one (%) | paper: " + " / ".join(TITLES[m] for m in METHODS) + " |",
        "|---|---|" + "---:|" * (len(METHODS) + 1) + "---|",
    ]
    by = {(r["env"], r["method"]): r for r in rows}
    for env in TABLE1_ENVS:
        got = [by.get((env, m)) for m in METHODS]
        present = [r for r in got if r is not None]
        name = family_of(make_spec(env)).display_name(env)
        size = (
            " / ".join(sorted({f"{r['training_seeds']} x {r['episodes_per_seed']}" for r in present}))
            if present
            else "not measured yet"
        )
        c = by.get((env, "cdrb"))
        obstacle = "–" if c is None else f"{c['in_obstacle']:.2f} / {c['plans_through_obstacle']:.1f}"
        paper = " / ".join(f"{PAPER_TABLE1[env][m][0]:.2f}" for m in METHODS)
        cells = [name, size, *(cell(r, m) for r, m in zip(got, METHODS, strict=True)), obstacle, paper]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mazes", type=Path, default=DOCS / "results" / "table1.csv")
    ap.add_argument(
        "--policies",
        type=Path,
        default=None,
        help="the policies' report CSV (default: docs/results/table1_policies.csv when it exists)",
    )
    ap.add_argument("--fetch", type=Path, default=DOCS / "results" / "table1_fetch.csv")
    ap.add_argument("--out", type=Path, default=DOCS / "results" / "table1_all.csv")
    ap.add_argument("--readme", type=Path, action="append", default=[], help="rewrite this file's table1-all block")
    args = ap.parse_args()
    from cdrb_cli import artifacts

    for p, flag in ((args.mazes, "--mazes"), (args.fetch, "--fetch")):
        if not p.is_file():
            raise SystemExit(
                f"{flag} {p}: no such file; give the CSV written by benchmarks/table1.py or table1_seeds.py"
            )
    if args.policies is not None and not args.policies.is_file():
        raise SystemExit(f"--policies {args.policies}: no such file; give the CSV `cdrb report` wrote over their evals")
    policies = args.policies or DOCS / "results" / "table1_policies.csv"
    mazes = maze_rows(args.mazes) + (maze_rows(policies) if policies.is_file() else [])
    rows = combine(mazes, fetch_rows(args.fetch))
    with artifacts.atomic_path(args.out) as tmp, tmp.open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        w.writerows({k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()} for r in rows)
    block = markdown(rows)
    for doc in args.readme:
        text = replace_block(doc.read_text(), "table1-all", block)
        with artifacts.atomic_path(doc) as tmp:
            tmp.write_text(text)
    print(args.out)


if __name__ == "__main__":
    main()
