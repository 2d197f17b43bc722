"""A comparison fair to every method: settings chosen on the tuning stream, learning curves, equal budgets.

Every choice is made on start/goal pairs of the *tuning* stream (`cdrb eval --stream tune`); the test stream is used
only by `benchmarks/table1.py` for the reported tables (docs/design.md, "Choosing settings"). Three parts, each
resumable (every stage is skipped when its artifact is up to date, through the CLI's own rule):

    python benchmarks/comparison.py sweep  --out runs/cmp     # one-factor-at-a-time sweep per method
    python benchmarks/comparison.py clock  --out runs/cmp     # controller/clock settings per method
    python benchmarks/comparison.py curves --out runs/cmp     # learning curves of the chosen settings
    python benchmarks/comparison.py write  --out runs/cmp     # CSVs, plot and tuned.json into docs/results/

* ``curves``: per env, method and training seed, one run of the method's chosen sweep candidate to the largest step
  count with ``--snapshot-at`` the others (each snapshot is exactly the model a run of that length writes), each
  evaluated on the tuning stream; ``write`` picks the step count with the best mean tuning success.
* ``sweep``: per env and method, the quick preset and one change at a time along each method's axes (diffusion
  steps, width, horizon/stride, features), the same number of candidates and the same steps x batch for every
  method (the equal budget), training seed 0, evaluated on the tuning stream with the method's default clock.
* ``clock``: for each method's chosen model, the plan clock (none, gated, gated with a timeout) and the official
  executor, on the tuning stream; for a closed-loop policy (no plan, no clock) its action samplers instead.
* ``write``: picks, per env and method, the best candidate (success, then fewer plans through obstacles) and writes
  ``docs/results/tuning.csv``, ``docs/results/learning_curves.csv``, ``docs/figures/learning_curves.png`` and
  ``docs/results/tuned.json`` (the settings table1.py reads with ``--tuned``).
"""

from __future__ import annotations

import argparse
import csv
import json
import signal
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from table1 import DOCS, _without, copy_artifact, hardware, prepare_env, run, unfinished  # noqa: E402

METHODS = ("mlp", "diffuser", "cdrb")
ENVS = ("maze-tight", "maze")
TUNE_SEEDS = "0,1"  # evaluation seeds of the tuning stream (its own pairs: never the test pairs)

#: one change at a time around the quick preset; the same count of candidates for every method (equal budget)
SWEEP = {
    "cdrb": {
        "quick": [],
        "T=64": ["--set", "method.diffusion_steps=64"],
        "dim=32": ["--set", "net.dim=32"],
        "H=84,stride=4": ["--set", "horizon=84", "--set", "stride=4"],
        "state-action": ["--set", "features=state-action"],
        "plain (no residual, p=0)": ["--set", "net.residual=false", "--set", "method.loss_weight_power=0"],
    },
    "diffuser": {
        "quick": [],
        "T=64": ["--set", "method.diffusion_steps=64"],
        "dim=32": ["--set", "net.dim=32"],
        "H=84,stride=4": ["--set", "horizon=84", "--set", "stride=4"],
        "state-action": ["--set", "features=state-action"],
        "no residual": ["--set", "net.residual=false"],
    },
    "mlp": {
        "quick": [],
        "width=1024": ["--set", "net.hidden=1024,1024,1024"],
        "depth=5": ["--set", "net.hidden=512,512,512,512,512"],
        "H=84,stride=4": ["--set", "horizon=84", "--set", "stride=4"],
        "state-action": ["--set", "features=state-action"],
        "lr=3e-4": ["--set", "lr=3e-4"],
    },
}

#: the closed-loop policies: six candidates too, at their own quick preset (single transitions, batch 256); they have
#: no plan and no controller, so no clock is tuned for them
POLICY_SWEEP = {
    "diffusion-bc": {
        "quick": [],  # one action per step
        "chunk 4, every 2": ["--set", "horizon=4", "--set", "method.act_every=2"],
        "chunk 8, every 4": ["--set", "horizon=8", "--set", "method.act_every=4"],
        "relabel 0.5": ["--set", "method.relabel=0.5"],
        "paper width": ["--set", "net.embed_dim=128", "--set", "net.hidden=512"],
        "lr=1e-4": ["--set", "lr=1e-4"],
    },
    "diffusion-ql": {
        "quick": [],
        "eta=0.2": ["--set", "method.eta=0.2"],
        "eta=3": ["--set", "method.eta=3"],
        "relabel 0.2": ["--set", "method.relabel=0.2"],
        "relabel 0.8": ["--set", "method.relabel=0.8"],
        "reward unshaped": ["--set", "method.reward_tune=none"],
    },
}
SWEEP |= POLICY_SWEEP

#: Fetch: no sweep of the training settings (CPU budget; the same for every method: the quick preset)
FETCH_SWEEP = {m: {"quick": []} for m in SWEEP}

#: plan clocks tried for every method: (name, `cdrb eval` flags)
CLOCKS = {
    "time-indexed": ["--max-lag", "0"],
    "gated 0.6": ["--max-lag", "0.6"],
    "gated 0.6, wait<=10": ["--max-lag", "0.6", "--set", "controller.max_wait=10"],
    "gated 0.3, wait<=10": ["--max-lag", "0.3", "--set", "controller.max_wait=10"],
    "official executor": ["--controller", "waypoint"],
}


#: Fetch: the task's controllers tried for every method (the controller-ceiling candidates, docs/benchmarks.md §6)
FETCH_CONTROLLERS = {
    "reach": {
        "track K=2": ["--controller", "fetch-track"],
        "track K=1": ["--controller", "fetch-track", "--set", "controller.gain=1"],
    },
    "push": {
        "track K=2, follow block": ["--controller", "fetch-track"],
        "track K=2": ["--controller", "fetch-track", "--set", "controller.follow_block=false"],
        "push along the block path": ["--controller", "fetch-push-path"],
        # the pusher unsticks a block the wall's end stalls (up to 3 times a plan), the plan cut to corners within
        # 1.5 / 3 / 5 / 8 / 12 cm (a jittery planned path cut finely makes the pusher re-approach at every corner)
        **{
            f"push along the block path, corners {cm} cm, unstick 3": [
                "--controller",
                "fetch-push-path",
                "--set",
                f"controller.tolerance={cm / 100:g}",
                "--set",
                "controller.unstick=3",
            ]
            for cm in (1.5, 3, 5, 8, 12)
        },
    },
    "pick-place": {
        "track K=2": ["--controller", "fetch-track"],
        "track K=1": ["--controller", "fetch-track", "--set", "controller.gain=1"],
    },
}
#: Fetch: the denoising step counts tried besides all of them, for each controller, by every method that has
#: denoising steps (CDRB, Diffuser; docs/benchmarks.md §6.1: on Reach Obstacle, CDRB's quick-preset chain loses the
#: route at mid k and 2 restorations keep it; Push Obstacle's recorded tuning predates these candidates)
FETCH_SAMPLE_STEPS = (8, 4, 2)


def _fetch_task(env: str) -> str | None:
    from cdrb_cli.envs.registry import make_spec

    spec = make_spec(env)
    return spec.scene.task if spec.family == "fetch" else None


def sweep_for(env: str, limit: int | None = None) -> dict[str, dict[str, list]]:
    """Per method, the training-setting candidates tried on ``env`` (the first ``limit`` of each: a smaller budget,
    stated beside the figures, for a method whose training the machine cannot afford six times)."""
    by = FETCH_SWEEP if _fetch_task(env) else SWEEP
    return {m: dict(list(c.items())[:limit]) for m, c in by.items()} if limit else by


def has_denoising_steps(method: str) -> bool:
    """Whether the method's sampler runs denoising steps that `cdrb eval --sample-steps` can cut (CDRB, Diffuser)."""
    from cdrb_cli.methods.registry import METHODS

    return "diffusion_steps" in METHODS.get(method).params.model_fields


def clocks_for(env: str, method: str) -> dict[str, list]:
    """The controller/clock candidates tried on ``env`` for ``method``: on the mazes the same for every method; on
    Fetch the task's controllers, each also with fewer denoising steps for a method that has them; for a closed-loop
    policy its samplers."""
    if is_policy(method):
        return policy_samplers(method)
    task = _fetch_task(env)
    if not task:
        return CLOCKS
    out = dict(FETCH_CONTROLLERS[task])
    if has_denoising_steps(method):
        for name, flags in FETCH_CONTROLLERS[task].items():
            for n in FETCH_SAMPLE_STEPS:
                out[f"{name}, {n} sampling steps"] = [*flags, "--sample-steps", str(n)]
    return out


def policy_samplers(method: str) -> dict[str, list]:
    """A closed-loop policy's eval-time knob in place of a clock: every sampler its config allows, the default first
    (it keeps a tie). Diffusion-QL: q-softmax (one of 50 actions by the critics' softmax) or the plain DDPM sample;
    Diffusion BC: Pearce's Diffusion-X (extra denoising at the last step) or plain DDPM."""
    from typing import get_args

    from cdrb_cli.methods.registry import METHODS

    field = METHODS.get(method).params.model_fields["sampler"]
    names = [field.default] + [n for n in get_args(field.annotation) if n != field.default]
    return {n: [] if n == field.default else ["--sampler", n] for n in names}


def is_policy(method: str) -> bool:
    from cdrb_cli.methods.registry import METHODS

    return METHODS.get(method).kind == "policy"


def has_curves(env: str) -> bool:
    """Learning curves are run on the mazes; on Fetch the quick preset's step count is kept (CPU budget)."""
    return _fetch_task(env) is None


def eval_tune(model: Path, out: Path, args, log, flags=(), key="") -> Path:
    run(
        ["eval", model, "--stream", "tune", "--seeds", args.tune_seeds, "--episodes", args.episodes, *flags]
        + ["--out", out, "--device", args.device],
        log,
        key or f"eval-tune {out.name}",
    )
    return out


def train(model: Path, demos: Path, buffer: Path, method: str, seed: int, flags, args, log, snapshots=()) -> None:
    from cdrb_cli.methods.registry import METHODS

    cmd = ["train", demos, "--method", method, "--seed", seed, "--out", model, "--device", args.device, *flags]
    if METHODS.get(method).needs_buffer:
        cmd += ["--buffer", buffer]
    if snapshots:
        cmd += ["--snapshot-at", ",".join(map(str, snapshots))]
    if unfinished(model):
        cmd.append("--resume")
    tiny = _without(args.tiny_flags, ("horizon=", "stride=")) if is_policy(method) else args.tiny_flags
    run(cmd + tiny, log, f"train {model.parent.name} {model.name}")


def buffers(env: str, args, log) -> dict[str, tuple[Path, Path]]:
    """(demos, buffer) per feature space that the env's sweep uses."""
    flags = [f for m in args.methods for cand in sweep_for(env, args.candidates)[m].values() for f in cand]
    spaces = ("state", "state-action") if "features=state-action" in flags else ("state",)
    return {f: prepare_env(env, args.out, args, log, features=f) for f in spaces}


def curves(args, log) -> None:
    """Learning curves of each method's chosen sweep candidate (the quick preset before any sweep)."""
    points = [int(s) for s in args.curve_steps.split(",")]
    tuned = choose(args)
    for env in [e for e in args.envs if has_curves(e)]:
        data = buffers(env, args, log)
        for seed in args.curve_seeds:
            for method in args.methods:
                t = tuned.get(env, {}).get(method, {})
                flags = _without_steps(t.get("train_flags", []))  # the curve sets the step count
                demos, buffer = data["state-action" if "features=state-action" in flags else "state"]
                folder = _curve_folder(args, env, t)
                folder.mkdir(parents=True, exist_ok=True)
                final = max(points)
                model = _curve_model(folder, method, seed, final, final)
                snaps = [p for p in points if p != final]
                if model.exists() and not unfinished(model):
                    missing = [p for p in snaps if not _curve_model(folder, method, seed, p, final).exists()]
                    if missing:
                        raise SystemExit(f"{model}: finished without snapshots {missing}; delete it to redo the curve")
                    snaps = []
                flags += ["--steps", final]
                train(model, demos, buffer, method, seed, flags, args, log, snaps)
                for p in points:
                    m = _curve_model(folder, method, seed, p, final)
                    eval_tune(m, folder / f"eval-{method}-s{seed}-{p}.h5", args, log)


def sweep(args, log) -> None:
    for env in args.envs:
        data = buffers(env, args, log)
        for method in args.methods:
            for name, flags in sweep_for(env, args.candidates)[method].items():
                if args.tiny and any("horizon" in f or "net." in f for f in flags):
                    continue  # the smoke test sets these itself
                features = "state-action" if "features=state-action" in flags else "state"
                demos, buffer = data[features]
                folder = args.out / env / "sweep"
                folder.mkdir(parents=True, exist_ok=True)
                tag = f"{method}-{slug(name)}"
                train(folder / f"{tag}.h5", demos, buffer, method, 0, flags + args.sweep_steps + args.budget, args, log)
                eval_tune(folder / f"{tag}.h5", folder / f"eval-{tag}.h5", args, log)


def clock(args, log) -> None:
    tuned = choose(args)
    for env in args.envs:
        for method in args.methods:
            name = tuned[env][method]["candidate"]
            folder = args.out / env / "sweep"
            model = folder / f"{method}-{slug(name)}.h5"
            for cname, flags in clocks_for(env, method).items():
                dest = folder / f"clock-{method}-{slug(cname)}.h5"
                if flags:
                    eval_tune(model, dest, args, log, flags)
                else:  # the method's own default: the same command as the sweep's tuning eval of this model
                    reuse(folder / f"eval-{method}-{slug(name)}.h5", dest)


def reuse(src: Path, dest: Path) -> None:
    """``dest`` as a copy of the eval ``src`` (which ran the same command), unless a copy at least as new is there."""
    if dest.exists() and dest.stat().st_mtime >= src.stat().st_mtime:
        print(f"skip     0.0s  {dest.name}: the same eval as {src.name}", flush=True)
        return
    copy_artifact(src, dest)
    print(f"done     0.0s  {dest.name}: copied from {src.name} (the same eval command)", flush=True)


def slug(text: str) -> str:
    return "".join(c if c.isalnum() else "-" for c in text.lower()).strip("-")


def _summary(path: Path) -> dict:
    from cdrb_cli import artifacts
    from cdrb_cli.stages.report import per_seed

    ev = artifacts.load(path, "eval")
    per = per_seed(ev)

    def mean(name: str, scale: float = 100.0) -> float | None:  # None: a plan measure of a policy (no plans)
        vals = [getattr(p, name) for p in per]
        return None if None in vals else scale * sum(vals) / len(vals)

    return {
        "success": mean("success_rate"),
        "in_wall": mean("in_wall_fraction"),
        "crossing": mean("plan_crossing_rate"),
        "impossible_jump": mean("impossible_jump_rate"),
        "jump_ratio": mean("jump_ratio", 1.0),  # the largest step of a plan over what the dynamics allow, seed means
        "collision": mean("executed_collision_rate"),
        "plan_ms": mean("plan_seconds", 1000.0),  # a policy: the time of its act calls per episode
        "model": ev.manifest.parents[0].path,
    }


def choose(args) -> dict:
    """Per env and method: the sweep candidate with the highest tuning success, then the fewest crossings."""
    out: dict = {}
    for env in args.envs:
        for method in args.methods:
            rows, cands = [], sweep_for(env, args.candidates)[method]
            for name in cands:
                p = args.out / env / "sweep" / f"eval-{method}-{slug(name)}.h5"
                if p.exists():
                    rows.append((name, _summary(p)))
            if rows:
                name, s = max(rows, key=lambda r: (r[1]["success"], -(r[1]["crossing"] or 0), -r[1]["collision"]))
                # the training budget, if cut with --steps, is part of the setting: table1.py trains every seed so
                out.setdefault(env, {})[method] = {"candidate": name, "train_flags": cands[name] + args.budget, **s}
    return out


def _clock_rank(s: dict) -> tuple:
    """How a clock/controller candidate ranks: success, then fewer plans through obstacles (sampling steps change the
    plans), then fewer executed collisions (under one sampling setting the plans are the same for every controller)."""
    return (s["success"], -(s["crossing"] or 0), -s["collision"])


def write(args, log) -> None:
    from cdrb_cli import artifacts

    results, figures = (DOCS / "results", DOCS / "figures") if args.write_docs else (args.out, args.out)
    results.mkdir(parents=True, exist_ok=True)
    rows = []
    for env in args.envs:
        for method in args.methods:
            for name in sweep_for(env, args.candidates)[method]:
                p = args.out / env / "sweep" / f"eval-{method}-{slug(name)}.h5"
                if not p.exists():
                    continue
                model = artifacts.load(args.out / env / "sweep" / f"{method}-{slug(name)}.h5", "model")
                st, cfg = model.manifest.state, model.manifest.config
                rows.append(
                    {
                        "env": env,
                        "method": method,
                        "candidate": name,
                        "steps": cfg.steps,
                        "batch": cfg.batch_size,
                        "parameters": st.parameters,
                        "train_s": round(st.wall_time_s, 1),
                        **_rounded(_summary(p), exclude=("model",)),
                    }
                )
    if rows:
        _csv(results / "tuning.csv", rows, args)
    tuned = choose(args)
    clocks = []
    for env, by in tuned.items():
        for method, t in by.items():
            best, candidates = None, clocks_for(env, method)
            for cname in candidates:
                p = args.out / env / "sweep" / f"clock-{method}-{slug(cname)}.h5"
                if p.exists():
                    s = _summary(p)
                    clocks.append(
                        {
                            "env": env,
                            "method": method,
                            "clock": cname,
                            **_rounded(s, exclude=("model",)),
                        }
                    )
                    if best is None or _clock_rank(s) > _clock_rank(best[1]):
                        best = (cname, s)
            if best is not None:
                t["clock"], t["eval_flags"] = best[0], candidates[best[0]]
            # table1.py reuses the chosen sweep model (training seed 0) for seed 0; curve runs, where there are any,
            # replace it below with their models at the chosen step count
            t["curve_models"] = {"0": t["model"]}
    if clocks:
        _csv(results / "tuning_clock.csv", clocks, args)
    curve_rows = []
    for env in args.envs:
        for method in args.methods:  # the curves of each method's chosen candidate only
            folder = _curve_folder(args, env, tuned.get(env, {}).get(method, {}))
            for p in sorted(folder.glob(f"eval-{method}-s*.h5")) if folder.exists() else []:
                _, seed, steps = p.stem.removeprefix("eval-").rsplit("-", 2)
                curve_rows.append(
                    {
                        "method": method,
                        "env": env,
                        "seed": int(seed[1:]),
                        "steps": int(steps),
                        **_rounded(_summary(p), keep=("success", "in_wall", "crossing")),
                    }
                )
    if curve_rows:
        curve_rows.sort(key=lambda r: (r["env"], r["method"], r["seed"], r["steps"]))
        all_curves = _csv(results / "learning_curves.csv", curve_rows, args)
        plot_curves(all_curves, figures / "learning_curves.png")
        # training steps: the curve point with the best mean tuning success (ties: fewer steps, i.e. cheaper)
        for env, by in tuned.items():
            for method, t in by.items():
                sel = [r for r in curve_rows if r["env"] == env and r["method"] == method]
                if not sel:
                    continue
                by_steps = {}
                for r in sel:
                    by_steps.setdefault(r["steps"], []).append(r["success"])
                best = max(by_steps, key=lambda n: (sum(by_steps[n]) / len(by_steps[n]), -n))
                t["steps"] = best
                t["steps_success"] = sum(by_steps[best]) / len(by_steps[best])
                t["train_flags"] = [*_without_steps(t["train_flags"]), "--steps", str(best)]
                # the curve runs' models at that step count: table1.py reuses them for those training seeds
                # (a snapshot is bit for bit the model a run of that length writes; `cdrb train` skips it as up to
                # date, or refuses it if anything in its config or parents differs)
                folder = _curve_folder(args, env, t)
                t["curve_models"] = {
                    str(r["seed"]): str(_curve_model(folder, method, r["seed"], best, max(by_steps)))
                    for r in sel
                    if r["steps"] == best
                }
    meta = {"machine": hardware(), "tuning_stream_seeds": args.tune_seeds, "episodes_per_seed": args.episodes}
    path = results / "tuned.json"
    # the (env, method) pairs not tuned in this run keep their settings (Fetch and the mazes, planners and policies
    # are tuned in separate runs)
    settings = json.loads(path.read_text())["settings"] if path.exists() else {}
    for env in args.envs:
        by = {m: t for m, t in settings.get(env, {}).items() if m not in args.methods} | tuned.get(env, {})
        if by:
            settings[env] = by
    path.write_text(json.dumps({"meta": meta, "settings": settings}, indent=2) + "\n")
    print(path)


def _without_steps(flags: list) -> list:
    """``flags`` less any ``--steps N`` (a curve's step count replaces the sweep's budget)."""
    out, skip = [], False
    for f in flags:
        if skip or f == "--steps":
            skip = not skip
            continue
        out.append(f)
    return out


def _curve_folder(args, env: str, tuned: dict) -> Path:
    """The learning-curve runs of a method's chosen candidate (the quick preset before any sweep): one folder each."""
    return args.out / env / "curves" / slug(tuned.get("candidate", "quick"))


def _curve_model(folder: Path, method: str, seed: int, steps: int, final: int) -> Path:
    return folder / (f"{method}-s{seed}.h5" if steps == final else f"{method}-s{seed}.step{steps}.h5")


def _rounded(summary: dict, keep=None, exclude=()) -> dict:
    return {
        k: (None if v is None else round(v, 3))
        for k, v in summary.items()
        if (keep is None or k in keep) and k not in exclude
    }


def _csv(path: Path, rows: list[dict], args) -> list[dict]:
    """Write ``rows`` into the CSV at ``path``, keeping its rows of the (env, method) pairs this run did not cover
    (``args.envs`` x ``args.methods``); returns all rows."""
    if path.exists():
        with open(path, newline="") as fh:
            kept = [r for r in csv.DictReader(fh) if r["env"] not in args.envs or r["method"] not in args.methods]
        kept = [{k: _number(v) for k, v in r.items()} for r in kept]
        rows = kept + rows
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[-1]))
        w.writeheader()
        w.writerows(rows)
    print(path)
    return rows


def _number(text: str):
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def plot_curves(rows: list[dict], path: Path) -> None:
    import numpy as np

    from cdrb_cli.envs.render import pyplot, save_figure

    plt = pyplot()
    envs = list(dict.fromkeys(r["env"] for r in rows))
    fig, axes = plt.subplots(2, len(envs), figsize=(5.5 * len(envs), 7), squeeze=False)
    for j, env in enumerate(envs):
        for method in dict.fromkeys(r["method"] for r in rows):
            sel = [r for r in rows if r["env"] == env and r["method"] == method]
            steps = sorted({r["steps"] for r in sel})
            for i, key in enumerate(("success", "crossing")):
                vals = [[r[key] for r in sel if r["steps"] == s and r[key] not in (None, "")] for s in steps]
                if not all(vals):
                    continue  # a policy makes no plans: no crossing curve
                m = np.array([np.mean(v) for v in vals])
                sd = np.array([np.std(v, ddof=1) if len(v) > 1 else 0.0 for v in vals])
                axes[i][j].plot(steps, m, marker="o", label=f"{method} ({min(len(v) for v in vals)} seeds)")
                axes[i][j].fill_between(steps, np.clip(m - sd, 0, 100), np.clip(m + sd, 0, 100), alpha=0.2)  # rates
        for i, title in enumerate(("success (%), tuning stream", "plans through a wall (%)")):
            axes[i][j].set_xscale("log")
            axes[i][j].set_title(f"{env}: {title}", fontsize=10)
            axes[i][j].set_xlabel("training steps")
            axes[i][j].grid(alpha=0.3)
        axes[0][j].legend(fontsize=8)
    save_figure(fig, path)
    print(path)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("part", choices=["curves", "sweep", "clock", "write", "all"])
    ap.add_argument("--out", type=Path, default=Path("runs/cmp"))
    ap.add_argument("--envs", default=",".join(ENVS))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument(
        "--demos", type=int, default=None, help="demonstrations per env (default: 8000 on the mazes, 5000 on Fetch)"
    )
    ap.add_argument("--episodes", type=int, default=50, help="tuning episodes per tuning seed")
    ap.add_argument("--tune-seeds", default=TUNE_SEEDS)
    ap.add_argument(
        "--candidates",
        type=int,
        default=None,
        help="sweep only the first N candidates of each method (default: all six); state the budget beside the figures",
    )
    ap.add_argument(
        "--steps",
        type=int,
        default=None,
        help="train every sweep candidate N steps instead of its preset's count, and record it in tuned.json so "
        "table1.py trains every seed the same (a smaller budget for a method the machine cannot afford at its "
        "preset; state it beside the figures)",
    )
    ap.add_argument("--curve-seeds", default="0,1,2")
    ap.add_argument("--curve-steps", default="1000,2000,3000,6000,10000")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--tiny", action="store_true", help="smoke-test settings")
    ap.add_argument("--write-docs", action="store_true", help="write: into docs/results and docs/figures")
    args = ap.parse_args()
    if args.tiny and args.write_docs:
        ap.error("--tiny results never go into docs/")
    args.envs, args.methods = args.envs.split(","), args.methods.split(",")
    args.curve_seeds = [int(s) for s in args.curve_seeds.split(",")]
    args.tiny_flags, args.sweep_steps = [], []
    if args.tiny:
        args.sweep_steps = ["--steps", "50"]
        args.episodes = min(args.episodes, 3)
        args.tiny_flags = [a for kv in ("horizon=16", "stride=10", "batch_size=8") for a in ("--set", kv)]
        args.curve_steps = "50,100"
    args.budget = []
    if args.steps is not None:
        if args.steps < 1:
            ap.error(f"--steps {args.steps}: give a positive number of training steps")
        args.sweep_steps, args.budget = [], ["--steps", str(args.steps)]
    args.out.mkdir(parents=True, exist_ok=True)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    timings = args.out / "timings.json"
    log = json.loads(timings.read_text()) if timings.exists() else {}
    t0 = time.time()
    try:
        for part in ("sweep", "clock", "curves", "write") if args.part == "all" else (args.part,):
            globals()[part](args, log)
    finally:
        timings.write_text(json.dumps(log, indent=2))
    print(f"total {(time.time() - t0) / 60:.1f} min", flush=True)


if __name__ == "__main__":
    main()
