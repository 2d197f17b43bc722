"""`cdrb quickstart`: the whole pipeline on an embedded default, resumable.

collect -> cluster -> train (CDRB and Diffuser, `quick`) -> eval -> report. Every stage writes its artifact
atomically and is skipped when that artifact is up to date (same config, same parents: the rule of
:func:`cdrb_cli.artifacts.existing`); an interrupted training resumes from its last checkpoint. So interrupting at
any point and re-running loses nothing.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from cdrb_cli import artifacts, ui, workers
from cdrb_cli.configs import ClusterConfig

#: the methods quickstart compares when none are given
DEFAULT_METHODS = ("cdrb", "diffuser")
DEFAULT_ENV = "maze-tight"
#: where the demonstrations start: half at the protocol's starts, half anywhere in free space (where the family
#: draws such starts), so the models also plan from where a re-plan finds the robot
STARTS = "protocol+anywhere"
#: training settings of the planners that have them: the states right after the start weigh 10x in the loss, so a
#: plan leaves from the start it is given rather than jumping to the data's usual path
PLANNER_SETTINGS = {"method.start_weight": 10.0}


def check_methods(methods: Sequence[str], flag: str = "methods") -> None:
    """Quickstart compares registered planners, each once."""
    from cdrb_cli.errors import BadInput
    from cdrb_cli.methods.registry import METHODS

    if not methods or len(set(methods)) != len(methods):
        raise BadInput(f"{flag} {','.join(methods)!r}: give each method once", hint=f"e.g. {','.join(DEFAULT_METHODS)}")
    for m in methods:
        if METHODS.get(m, flag).kind != "planner":
            raise BadInput(f"{flag} {m}: a policy; quickstart compares planners", hint="leave it out")


@dataclass
class QuickstartResult:
    folder: Path
    report: str
    pictures: list[Path] = field(default_factory=list)
    artifacts: dict[str, Path] = field(default_factory=dict)
    seconds: float = 0.0


def _stage(n: int, total: int, text: str) -> None:
    ui.log(f"[{n}/{total}] {text}")


def _reuse(path: Path, kind: str, config, parents=(), env=None):
    """The artifact at ``path`` if this run can reuse it (logged), else None."""
    art = artifacts.find_up_to_date(path, kind, config, parents, env)
    if art is not None:
        ui.log("  up to date")
    return art


def _side_by_side(jobs: list, processes: int, threads: int) -> str:
    """How the stage's jobs will run, for its log line."""
    if not jobs:
        return ": up to date"
    return f", {processes} at a time, {threads} thread{'s' if threads > 1 else ''} each" if processes > 1 else ""


def _train_and_evaluate(job: dict) -> str:
    """One method's training, when its model is not up to date, then its evaluation (in a worker process, or
    here): what the training did (``trained``, ``resumed``, ``model up to date``...)."""
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.methods.registry import METHODS
    from cdrb_cli.stages.configure import eval_config
    from cdrb_cli.stages.evaluate import evaluate
    from cdrb_cli.stages.train import train_or_resume

    device = _device(job)
    done = "model up to date"
    if job["train"]:
        demos = artifacts.load(Path(job["demos"]), "demos")
        buffer = artifacts.load(Path(job["buffer"]), "buffer") if METHODS.get(job["method"]).needs_buffer else None
        settings = _train_settings(job["method"], job["steps"])
        cfg = train_config(demos, buffer, job["method"], settings, seed=job["seed"])
        _, done = train_or_resume(demos, buffer, cfg, Path(job["model"]), device=device, auto=True)
    model = artifacts.load(Path(job["model"]), "model")
    ecfg = eval_config(model, episodes=job["episodes"], seeds=job["seeds"], seed=job["seed"])
    video_dir = Path(job["folder"]) / "videos" if job["videos"] else None
    evaluate(model, ecfg, Path(job["out"]), device=device, video_dir=video_dir, videos=job["videos"])
    return done


def _train_settings(method: str, steps: int | None) -> dict:
    """The quickstart's training settings of ``method``: :data:`PLANNER_SETTINGS` its config has, and ``steps``."""
    from cdrb_cli.methods.registry import METHODS

    fields = METHODS.get(method).params.model_fields
    out = {k: v for k, v in PLANNER_SETTINGS.items() if k.split(".")[1] in fields}
    return {**out, **({"steps": steps} if steps else {})}


def _starts(spec, starts: str | None) -> str:
    """Where the demonstrations start: ``starts`` as given, else :data:`STARTS` where the family draws other starts."""
    from cdrb_cli.envs.registry import family_of

    if starts is not None:
        return starts
    return STARTS if family_of(spec).start_protocols else "protocol"


def _device(job: dict):
    from cdrb_cli.torch_utils import setup_torch

    return setup_torch(job["device"])


def quickstart(
    folder: Path,
    env: str = DEFAULT_ENV,
    episodes: int = 2000,
    starts: str | None = None,
    k: int | None = None,
    methods: Sequence[str] = DEFAULT_METHODS,
    seeds: Sequence[int] = (5, 6, 7),
    eval_episodes: int = 50,
    steps: int | None = None,
    seed: int = 0,
    device="cpu",
    videos: int = 0,
) -> QuickstartResult:
    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.envs.render import plot_demos
    from cdrb_cli.methods.config import train_config
    from cdrb_cli.methods.registry import METHODS
    from cdrb_cli.stages.cluster import cluster, fit_default_k
    from cdrb_cli.stages.collect import collect, collect_config
    from cdrb_cli.stages.configure import eval_config
    from cdrb_cli.stages.report import collect_rows, render
    from cdrb_cli.stages.report_figures import plot_bars, plot_side_by_side

    t0 = time.time()
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    # one quickstart per folder at a time (the lock of its report covers the whole run)
    with artifacts.claim_output(folder / "report.md", force=True):
        total = 4
        step = 0
        spec = make_spec(env)
        paths: dict[str, Path] = {}

        step += 1
        where = _starts(spec, starts)
        _stage(step, total, f"collect {episodes} expert demos on {env} (starts: {where})")
        demos_path = paths["demos"] = folder / "demos.h5"
        ccfg = collect_config(spec, episodes, seed=seed, starts=where)
        demos = _reuse(demos_path, "demos", ccfg, env=spec) or collect(spec, ccfg, demos_path, workers=None)

        step += 1
        kcfg = fit_default_k(demos, ClusterConfig(seed=seed, **({"k": k} if k is not None else {})))
        _stage(step, total, f"cluster the replay buffer (k={kcfg.k})")
        buffer_path = paths["buffer"] = folder / "buffer.h5"
        buffer = _reuse(buffer_path, "buffer", kcfg, [demos]) or cluster(demos, kcfg, buffer_path)

        # each method's training and then its evaluation, one job per method, the jobs side by side when the
        # machine has the cores for them: a method that trains faster is evaluated while the other still trains
        jobs, evals = [], {}
        for method in methods:
            out = paths[f"model-{method}"] = folder / f"model-{method}.h5"
            paths[f"eval-{method}"] = folder / f"eval-{method}.h5"
            b = buffer if METHODS.get(method).needs_buffer else None
            cfg = train_config(demos, b, method, _train_settings(method, steps), seed=seed)
            model = artifacts.find_up_to_date(out, "model", cfg, [demos] + ([b] if b is not None else []))
            if model is not None:
                ecfg = eval_config(model, episodes=eval_episodes, seeds=list(seeds), seed=seed)
                evals[method] = artifacts.find_up_to_date(paths[f"eval-{method}"], "eval", ecfg, [model])
            if evals.get(method) is None:
                train = model is None
                jobs.append(dict(demos=str(demos.path), buffer=str(buffer.path), method=method, steps=steps, seed=seed,
                                 model=str(out), train=train, episodes=eval_episodes, seeds=list(seeds),
                                 out=str(paths[f"eval-{method}"]), device=str(device), videos=videos,
                                 folder=str(folder)))  # fmt: skip
        step += 1
        share = workers.plan(len(jobs), str(device))
        n = len(seeds)
        what = f"train {', '.join(methods)} (quick preset), then evaluate each: {n} seed{'s' * (n != 1)} x "
        _stage(step, total, f"{what}{eval_episodes} episodes{_side_by_side(jobs, *share)}")
        for job, done in zip(jobs, workers.run(_train_and_evaluate, jobs, *share)):
            if done != "trained":
                ui.log(f"  {job['method']}: {done}")
        evals = [evals.get(m) or artifacts.load(paths[f"eval-{m}"], "eval") for m in methods]

        step += 1
        _stage(step, total, "report")
        rows = collect_rows(evals)
        text = render(rows, "markdown", paper=True)
        with artifacts.atomic_path(folder / "report.md") as tmp:
            tmp.write_text(text)
        pictures = [plot_bars(rows, folder / "results.png"), plot_side_by_side(evals, folder / "plans.png")]
        pictures.append(plot_demos(demos, folder / "demos.png"))
        paths["report"] = folder / "report.md"
        seconds = time.time() - t0
        return QuickstartResult(folder=folder, report=text, pictures=pictures, artifacts=paths, seconds=seconds)
