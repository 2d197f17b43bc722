"""The paper's Table 1 maze rows (and an ablation table), run through the public CLI.

Grid: environments x methods x seeds. Per environment: `cdrb collect` (N demos), `cdrb cluster`; per method and
seed: `cdrb train --seed S` then `cdrb eval --seeds S --episodes E`; finally `cdrb report` over everything.
Every stage is skipped when its artifact is up to date (the CLI's own rule), and an unfinished training is
resumed, so the script can be stopped and restarted at any time. Wall time of every stage goes to
``OUT/table1_timings.json``.

    python benchmarks/table1.py --out runs/table1                         # quick preset, 5 seeds, 8k demos
    python benchmarks/table1.py --out runs/paper --preset paper           # the paper's settings (wants a GPU)
    python benchmarks/table1.py --out runs/tiny --tiny                    # a 2-minute smoke run of the same code
    python benchmarks/table1.py --out runs/table1 --ablations             # + the Maze Tight ablations
    python benchmarks/table1.py --out runs/table1 --write-docs            # + tables/figures into docs/

With --write-docs the Table 1 report replaces the block between ``<!-- table1:begin -->`` and
``<!-- table1:end -->`` of docs/benchmarks.md (ablations: ``<!-- ablations:... -->``); figures go to
docs/figures/ and CSVs to docs/results/.
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"

#: Table 1's rows in the paper's order
TABLE1_ENVS = (
    "maze",
    "maze-tight",
    "fetch-reach-obstacle",
    "fetch-pick-place-obstacle",
    "fetch-push-obstacle",
    "fetch-reach",
    "fetch-push",
    "fetch-pick-place",
)
#: demonstrations per environment family when --demos is not given (Fetch: the paper's 5,000 per task, §5)
DEMOS = {"pointmaze": 8000, "fetch": 5000}
#: expert settings per environment (`cdrb collect --set`). The tall-wall tasks (Reach Obstacle, Pick & Place
#: Obstacle): routes over the walls only, as the official data's trajectory lengths suggest (the reference's "over"
#: routes; going around an end works only near the arm's limits); docs/benchmarks.md §6.1 measures both datasets
#: on Reach Obstacle
COLLECT_SETTINGS = {env: ['expert.routes=["over"]'] for env in ("fetch-reach-obstacle", "fetch-pick-place-obstacle")}


def family(env: str) -> str:
    from cdrb_cli.envs.registry import make_spec

    return make_spec(env).family


def demos_for(env: str, args) -> int:
    n = args.demos if args.demos is not None else DEMOS.get(family(env), 1000)
    return min(n, 40) if getattr(args, "tiny", False) else n


# Maze Tight ablations the paper shows only as figures (quick preset; one training seed each):
# name -> (buffer k, buffer features, extra `cdrb train` flags)
ABLATIONS = {
    "k=1000 (default)": (1000, "state", []),
    "k=100": (100, "state", []),
    "full buffer": (0, "state", []),
    "log schedule (official)": (1000, "state", ["--set", "method.schedule=log"]),
    "geometric schedule": (1000, "state", ["--set", "method.schedule=geometric"]),
    "transformer": (1000, "state", ["--net", "transformer"]),
    "state-action": (1000, "state-action", []),
}


def run(cmd: list, log: dict, key: str) -> str:
    t = time.time()
    proc = subprocess.run([sys.executable, "-m", "cdrb_cli", *map(str, cmd)], capture_output=True, text=True)
    if proc.returncode != 0:
        sys.stderr.write(proc.stderr)
        raise SystemExit(f"failed: cdrb {' '.join(map(str, cmd))}")
    skipped = "up to date" in proc.stderr
    if not (skipped and key in log and not log[key]["skipped"]):  # keep the time of the run that made it
        log[key] = {"seconds": round(time.time() - t, 2), "skipped": skipped, "cmd": "cdrb " + " ".join(map(str, cmd))}
    print(f"{'skip' if skipped else 'done'} {time.time() - t:7.1f}s  cdrb {' '.join(map(str, cmd))}", flush=True)
    return proc.stdout.strip()


def copy_artifact(src: Path, dest: Path) -> None:
    """``src``'s bytes as ``dest``, written atomically (temp file, fsync, rename): no half-copied file is left."""
    from cdrb_cli import artifacts

    with artifacts.atomic_path(dest) as tmp:
        shutil.copyfile(src, tmp)


def unfinished(path: Path) -> bool:
    from cdrb_cli import artifacts

    return artifacts.unfinished_model(path)


def train_eval(
    folder: Path,
    demos: Path,
    buffer: Path,
    method: str,
    seed: int,
    args,
    log,
    tag: str,
    extra: list | None = None,
    timed: bool = False,
    eval_flags: list | None = None,
    protocol: str | None = None,
    reuse: Path | None = None,
) -> tuple[Path, Path | None]:
    """Train (or resume, or skip) one model and evaluate it on the test pairs (``eval_flags``: the method's tuned
    controller settings; ``protocol``: e.g. official-code); with ``timed`` also with the plan on the environment's
    clock. Returns the eval path(s)."""
    model = folder / f"{tag}-s{seed}.h5"
    cmd = [
        "train",
        demos,
        "--method",
        method,
        "--preset",
        args.preset,
        "--seed",
        seed,
        "--out",
        model,
        "--device",
        args.device,
    ]
    from cdrb_cli.methods.registry import METHODS

    entry = METHODS.get(method)
    if entry.needs_buffer:
        cmd += ["--buffer", buffer]
    unet = entry.default_net == "unet" and "transformer" not in (extra or [])
    diffusion = "diffusion_steps" in entry.params.model_fields
    extra_train = args.train_extra
    if entry.kind == "policy":  # a policy learns from single transitions: no plan horizon or stride to shrink
        extra_train = _without(extra_train, ("horizon=", "stride="))
    cmd += extra_train + (args.unet_extra if unet else []) + (args.diffusion_extra if diffusion else [])
    if args.tiny and "extra_steps" in entry.params.model_fields:  # a policy samples every env step: keep it short
        cmd += ["--set", "method.extra_steps=0"]
    cmd += list(extra or [])
    if reuse is not None and reuse.exists() and not model.exists():
        # a curve run's model of exactly this length (benchmarks/comparison.py): `cdrb train` below skips it as up
        # to date when its config and parents are the ones asked for, and refuses it otherwise
        copy_artifact(reuse, model)
        print(f"reused {reuse} as {model}", flush=True)
    if unfinished(model):
        cmd.append("--resume")
    run(cmd, log, f"train {folder.name} {tag} s{seed}")
    clocks = [("", list(eval_flags or []))] + ([("-timed", ["--max-lag", 0])] if timed else [])
    if protocol:
        clocks = [(f"-{protocol}", ["--protocol", protocol])]
    paths = []
    for suffix, clock_flags in clocks:
        ev = folder / f"eval-{tag}-s{seed}{suffix}.h5"
        run(
            ["eval", model, "--stream", "test", "--seeds", seed, "--episodes", args.eval_episodes, *clock_flags]
            + ["--out", ev, "--device", args.device],
            log,
            f"eval{suffix} {folder.name} {tag} s{seed}",
        )
        paths.append(ev)
    return paths[0], (paths[1] if timed else None)


def _without(flags: list, prefixes: tuple) -> list:
    """``flags`` without the ``--set KEY=VALUE`` pairs whose KEY=VALUE starts with one of ``prefixes``."""
    out, i = [], 0
    while i < len(flags):
        if flags[i] == "--set" and i + 1 < len(flags) and str(flags[i + 1]).startswith(prefixes):
            i += 2
            continue
        out.append(flags[i])
        i += 1
    return out


def prepare_env(env: str, out: Path, args, log, k: int = 1000, features: str = "state") -> tuple[Path, Path]:
    folder = out / env
    folder.mkdir(parents=True, exist_ok=True)
    demos = folder / "demos.h5"
    sets = [a for kv in COLLECT_SETTINGS.get(env, []) for a in ("--set", kv)]
    run(["collect", env, "-n", demos_for(env, args), "--seed", 0, *sets, "--out", demos], log, f"collect {env}")
    buffer = folder / f"buffer-k{k}-{features}.h5"
    run(
        ["cluster", demos, "--k", k, "--features", features, "--seed", 0, "--out", buffer],
        log,
        f"cluster {env} k{k} {features}",
    )
    return demos, buffer


def replace_block(text: str, name: str, block: str) -> str:
    pattern = re.compile(rf"<!-- {name}:begin -->.*?<!-- {name}:end -->", re.S)
    new = f"<!-- {name}:begin -->\n{block.rstrip()}\n<!-- {name}:end -->"
    if not pattern.search(text):
        return text.rstrip() + "\n\n" + new + "\n"
    return pattern.sub(lambda _: new, text)


def hardware() -> str:
    try:
        import torch

        if torch.cuda.is_available():
            return f"GPU {torch.cuda.get_device_name(0)}"
    except ImportError:
        pass
    import os

    return f"CPU only, {os.cpu_count()} cores ({platform.machine()})"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "table1")
    ap.add_argument("--envs", default="maze,maze-tight")
    ap.add_argument("--methods", default=None, help="comma-separated (default: every registered planner)")
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument(
        "--demos", type=int, default=None, help="demonstrations per env (default: 8000 on the mazes, 5000 on Fetch)"
    )
    ap.add_argument("--eval-episodes", type=int, default=100)
    ap.add_argument("--preset", default="quick", choices=["quick", "paper"])
    ap.add_argument("--device", default="auto")
    ap.add_argument("--tiny", action="store_true", help="smoke-test settings (tiny nets, few demos/episodes)")
    ap.add_argument("--ablations", action="store_true")
    ap.add_argument("--skip-grid", action="store_true", help="only the ablations")
    ap.add_argument("--write-docs", action="store_true")
    ap.add_argument(
        "--tuned",
        type=Path,
        default=None,
        help="settings chosen on the tuning stream (docs/results/tuned.json from benchmarks/comparison.py): "
        "per env and method, training flags and controller flags",
    )
    ap.add_argument(
        "--official-too",
        action="store_true",
        help="also evaluate every grid model under the official-code protocol (cell-centre goals, r = 0.55 m, the "
        "official executor)",
    )
    ap.add_argument(
        "--timed-too",
        action="store_true",
        help="also evaluate every grid model with the plan on the environment's clock (--max-lag 0)",
    )
    args = ap.parse_args()
    args.train_extra, args.unet_extra, args.diffusion_extra = [], [], []
    if args.tiny:
        args.eval_episodes = min(args.eval_episodes, 3)
        args.train_extra = ["--steps", "20"] + [
            a for kv in ("horizon=16", "stride=10", "batch_size=8") for a in ("--set", kv)
        ]
        args.unet_extra = [a for kv in ("net.dim=8", "net.dim_mults=1,2") for a in ("--set", kv)]
        args.diffusion_extra = ["--set", "method.diffusion_steps=8"]
    args.out.mkdir(parents=True, exist_ok=True)
    # a `kill` (SIGTERM) must still run the `finally` below that saves the timings
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    timings_path = args.out / "table1_timings.json"  # its own: comparison.py keeps timings.json in the same folder
    log = json.loads(timings_path.read_text()) if timings_path.exists() else {}
    seeds = [int(s) for s in args.seeds.split(",")]
    from cdrb_cli.methods.registry import METHODS

    methods = (
        args.methods.split(",") if args.methods else [m for m in METHODS.names() if METHODS.get(m).kind == "planner"]
    )
    tuned = json.loads(args.tuned.read_text())["settings"] if args.tuned else {}
    t0 = time.time()
    evals, timed_evals, official_evals = [], [], []
    try:
        if not args.skip_grid:
            for env in args.envs.split(","):
                for seed in seeds:
                    for method in methods:
                        t = tuned.get(env, {}).get(method)
                        if args.tuned and t is None:
                            raise SystemExit(f"{args.tuned}: no tuned settings for {method} on {env}")
                        train_flags = list(t["train_flags"]) if t else []
                        eval_flags = list(t.get("eval_flags", [])) if t else []
                        features = "state-action" if "features=state-action" in train_flags else "state"
                        demos, buffer = prepare_env(env, args.out, args, log, features=features)
                        tag = f"{method}-tuned" if t else method
                        common = (args.out / env, demos, buffer, method, seed, args, log, tag, train_flags)
                        reuse = (t or {}).get("curve_models", {}).get(str(seed))
                        reuse = Path(reuse) if reuse else None
                        policy = METHODS.get(method).kind == "policy"  # acts closed loop: no plan, no clock
                        # Fetch plans run on the env's clock
                        timed = args.timed_too and family(env) == "pointmaze" and not policy
                        ev, timed_ev = train_eval(*common, timed=timed, eval_flags=eval_flags, reuse=reuse)
                        evals.append(ev)
                        if timed_ev is not None:
                            timed_evals.append(timed_ev)
                        if args.official_too and family(env) == "pointmaze" and not policy:  # a maze protocol
                            official_evals.append(train_eval(*common, protocol="official-code")[0])
        ablation_evals = {}
        if args.ablations:
            env = "maze-tight"
            for name, (k, features, flags) in ABLATIONS.items():
                demos, buffer = prepare_env(env, args.out, args, log, k=k, features=features)
                default = not flags and k == 1000 and features == "state"
                tag = "cdrb" if default else "abl-" + re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")
                ablation_evals[name], _ = train_eval(
                    args.out / env, demos, buffer, "cdrb", seeds[0], args, log, tag, flags
                )
    finally:
        timings_path.write_text(json.dumps(log, indent=2))
    print(f"total {(time.time() - t0) / 60:.1f} min", flush=True)
    # the grid may be run in parts (`--envs` a few rows, `--methods` a few columns at a time): the report covers every
    # Table-1 row and every method with results
    for env in TABLE1_ENVS:
        if args.skip_grid:
            continue
        for seed in seeds:
            for method in METHODS.names():
                tag = f"{method}-tuned" if tuned.get(env, {}).get(method) else method
                ev = args.out / env / f"eval-{tag}-s{seed}.h5"
                if ev.exists() and ev not in evals:
                    evals.append(ev)
                official = ev.with_name(ev.stem + "-official-code.h5")
                if official.exists() and args.official_too and official not in official_evals:
                    official_evals.append(official)
    order = {e: i for i, e in enumerate(TABLE1_ENVS)}
    names = list(METHODS.names())

    def place(path: Path) -> tuple:  # Table 1's row order, then the registry's method order (the report's columns)
        tag = path.name.removeprefix("eval-").split("-s")[0].removesuffix("-tuned")
        return order.get(path.parent.name, len(order)), names.index(tag) if tag in names else len(names)

    evals.sort(key=place)
    official_evals.sort(key=place)

    report_md = args.out / "table1.md"
    if evals:
        figs = DOCS / "figures" if args.write_docs else args.out
        figs.mkdir(parents=True, exist_ok=True)
        run(
            ["report", *evals, "--format", "markdown", "--paper", "--out", report_md, "--plot", figs / "table1.png"]
            + ["--force"],
            log,
            "report",
        )
        csv = (DOCS / "results" if args.write_docs else args.out) / "table1.csv"
        csv.parent.mkdir(parents=True, exist_ok=True)
        run(["report", *evals, "--format", "csv", "--out", csv, "--force"], log, "report csv")
        if timed_evals:
            run(
                ["report", *timed_evals, "--format", "markdown", "--out", args.out / "table1-timed.md", "--force"],
                log,
                "report timed",
            )
        if official_evals:
            run(
                ["report", *official_evals, "--format", "markdown", "--out", args.out / "table1-official.md"]
                + ["--force"],
                log,
                "report official",
            )
            csv_official = csv.with_name("table1_official.csv")
            run(["report", *official_evals, "--format", "csv", "--out", csv_official, "--force"], log, "csv official")
    if args.write_docs:
        text = (DOCS / "benchmarks.md").read_text()
        if evals:
            stage_time = {}
            for key, v in log.items():
                stage = key.split(" ")[0]
                stage_time[stage] = stage_time.get(stage, 0.0) + (0 if v["skipped"] else v["seconds"])
            body = report_md.read_text()
            if official_evals:
                body += (
                    "\n**The same models under the official-code protocol** (`cdrb eval --protocol official-code`: "
                    "goals at cell centres, success within 0.55 m, the official executor):\n\n"
                    + (args.out / "table1-official.md").read_text()
                )
            if timed_evals:
                body += (
                    "\n**The same models with the plan on the environment's clock** (`cdrb eval --max-lag 0`; the "
                    "table above uses "
                    + (
                        "each method's tuned controller, see its controller column"
                        if args.tuned
                        else "the default gated clock, `--max-lag 0.6`"
                    )
                    + "):\n\n"
                    + (args.out / "table1-timed.md").read_text()
                )
            flags = (
                (f" --tuned {args.tuned}" if args.tuned else "")
                + (" --official-too" if args.official_too else "")
                + (" --timed-too" if args.timed_too else "")
                + (" --ablations" if args.ablations else "")
            )
            meta = (
                f"\n*Run: `python benchmarks/table1.py --envs {args.envs} --preset {args.preset}"
                + (f" --methods {args.methods}" if args.methods else "")
                + (f" --demos {args.demos}" if args.demos is not None else "")
                + f" --seeds "
                f"{args.seeds} --eval-episodes {args.eval_episodes}{flags}` on {hardware()}; wall time per stage "
                f"(summed): "
                + ", ".join(f"{k} {v / 60:.1f} min" for k, v in stage_time.items())
                + (" (train includes the ablation models)" if args.ablations else "")
                + ". Commands and per-stage times: docs/results/table1_timings.json.*\n"
            )
            text = replace_block(text, "table1", body + meta)
            (DOCS / "results" / "table1_timings.json").write_text(json.dumps(log, indent=2))
        if args.ablations:
            from cdrb_cli import artifacts

            lines = [
                "| Maze Tight ablation (CDRB, quick preset, seed 0) | success (%) | planned states in walls (%) "
                "| executed collisions (%) | plan time (ms) |",
                "|---|---:|---:|---:|---:|",
            ]
            for name, path in ablation_evals.items():
                s = artifacts.load(path, "eval").manifest.summary
                lines.append(
                    f"| {name} | {100 * s.success_mean:.1f} | {100 * s.in_wall_mean:.2f} | "
                    f"{100 * s.executed_collision_mean:.1f} | {1000 * s.plan_seconds_mean:.1f} |"
                )
            text = replace_block(text, "ablations", "\n".join(lines) + "\n")
        (DOCS / "benchmarks.md").write_text(text)


if __name__ == "__main__":
    main()
