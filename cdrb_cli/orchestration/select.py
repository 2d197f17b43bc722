"""`cdrb select TUNING_GRID`: choose each method's settings on the tuning stream and write them as a settings file.

A tuning grid's candidates are its variants (training settings, or eval-only knobs on one trained model: controller,
plan clock, sampler, denoising steps, re-planning trigger) and, with ``snapshot_at``, its training lengths. For
every environment x method, every candidate's tuning evals (all its training seeds and evaluation seeds pooled) are
scored and one is chosen by :data:`RULE`. The chosen flags (the settings that applied in the tuning grid, the
variant's, and the chosen training length) are written as ``[[settings]]`` of a settings file that the test grid
``include``s: the one copy of every tuned setting. The test pairs are never read here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from datetime import date
from pathlib import Path

from cdrb_cli import artifacts, ui
from cdrb_cli.errors import BadInput
from cdrb_cli.methods.registry import METHODS
from cdrb_cli.orchestration.grid import (
    BASE,
    GridSpec,
    as_table,
    cluster_flags_for,
    expand,
    flags_for,
    without_setting,
)
from cdrb_cli.orchestration.select_evals import checked_eval, trained_alike
from cdrb_cli.settings import toml_string, toml_value
from cdrb_cli.stages.metrics import mean_or_none, std_or_none

RULE = (
    "highest tuning success, then fewest plans through an obstacle, then fewest executed collisions, "
    "then the grid's variant order, then fewest training steps; never a planner executed by a controller that "
    "reads the map"
)
#: with the grid's ``shared_budget``: how the planners of one environment share a training length
SHARED_BUDGET = (
    "the planners of one environment train to one length, the longest any of them is chosen at by the rule; each is "
    "then chosen by the rule among its candidates at that length"
)


@dataclass
class Candidate:
    """One setting tried for a method on an environment: a variant at a training length, with its tuning scores
    (per cent, pooled over every training and evaluation seed)."""

    env: str
    method: str
    variant: str
    order: int
    steps: int | None
    evals: list[Path] = field(default_factory=list)
    training_seeds: list[int] = field(default_factory=list)
    models: list[dict] = field(default_factory=list)
    success: float = 0.0
    success_std: float | None = None
    crossing: float | None = None
    collision: float = 0.0
    seeds: int = 0
    episodes: int = 0
    planner: bool = True  #: a planner (executed by a controller), not a policy
    map_aware: bool = False  #: executed by a controller that reads the map (never chosen: :data:`RULE`)

    @property
    def name(self) -> str:
        label = self.variant or "base"
        return label if self.steps is None else f"{label} @ {self.steps} steps"

    def rank(self) -> tuple:
        """Smaller is better (:data:`RULE`); a policy makes no plans, so no plan crosses an obstacle."""
        return (-self.success, self.crossing or 0.0, self.collision, self.order, self.steps or 0)


def candidates(spec: GridSpec, tasks: list | None = None) -> list[Candidate]:
    """Every (env, method, variant, training length) of the grid with its tuning scores, in the grid's order
    (``tasks``: the grid's expanded tasks, when the caller has them)."""
    from cdrb_cli.stages.results import per_seed

    order = {v.name: i for i, v in enumerate(spec.variants or [BASE])}
    found: dict[tuple, Candidate] = {}
    missing = []
    by_output, trains, makers = {}, {}, {}
    for task in expand(spec) if tasks is None else tasks:
        if task.kind == "train":
            trains |= dict.fromkeys(task.outputs, task)
        if task.kind in ("collect", "cluster"):
            makers |= dict.fromkeys(task.outputs, task)
        if task.kind != "eval":
            continue
        by_output[task.outputs[0]] = task
        m = task.meta
        if m["stream"] != "tune":
            raise BadInput(
                f"{task.id}: evaluates on the {m['stream']} stream; settings are chosen on the tuning stream only",
                hint='set eval_stream = "tune" in the tuning grid',
            )
        key = (m["env"], m["method"], m["variant"], m["steps"])
        cand = found.setdefault(key, Candidate(*key[:3], order[m["variant"]], m["steps"]))
        (cand.evals if task.outputs[0].exists() else missing).append(task.outputs[0])
        cand.training_seeds.append(m["seed"])
    if missing:
        raise BadInput(
            f"{len(missing)} of the grid's tuning evals are not there yet (e.g. {missing[0]})",
            hint="run `cdrb grid` on the same file (with the same --set/--include) first",
        )
    unchecked: list[Path] = []
    for cand in found.values():
        evals = [checked_eval(spec, by_output[p], p, unchecked, trains, makers) for p in cand.evals]
        trained_alike(evals)
        cand.models = [_model_scores(seed, per_seed(ev)) for seed, ev in zip(cand.training_seeds, evals, strict=True)]
        cand.success_std = seed_spread(cand.models)
        per = [r for ev in evals for r in per_seed(ev)]
        cand.seeds, cand.episodes = len(per), evals[0].manifest.config.episodes
        cand.success = 100 * mean_or_none(r.success_rate for r in per)
        crossing = mean_or_none(r.plan_crossing_rate for r in per)  # None: a policy makes no plans
        cand.crossing = None if crossing is None else 100 * crossing
        cand.collision = 100 * mean_or_none(r.executed_collision_rate for r in per)
        cand.planner = METHODS.get(cand.method).kind == "planner"
        cand.map_aware = cand.planner and any(_knows_map(ev) for ev in evals)
    if unchecked:
        ui.warn(
            f"{len(unchecked)} evals record no training length and their models are not here (e.g. {unchecked[0]}): "
            "each is taken to measure its model at the length the grid's task names"
        )
    return list(found.values())


def _knows_map(ev) -> bool:
    """Whether the eval's plans were executed by a controller that reads the map."""
    from cdrb_cli.envs.registry import CONTROLLERS

    return CONTROLLERS.get(ev.manifest.config.controller.name).knows_map


def seed_spread(models: list[dict]) -> float | None:
    """The sample std of success between training seeds (:func:`_model_scores` rows); None with fewer than two
    seeds, where there is no spread to state (a single run is not one that varies by 0)."""
    return std_or_none(m["success"] for m in models) if len(models) > 1 else None


def _model_scores(seed: int, per: list) -> dict:
    """One trained model's tuning scores (per cent, pooled over its evaluation seeds): a learning-curve point."""

    def pct(values) -> float | None:
        v = mean_or_none(values)
        return None if v is None else round(100 * v, 2)

    return {
        "seed": seed,
        "episodes": sum(r.episodes for r in per),
        "success": pct(r.success_rate for r in per),
        "weighted_success": pct(r.weighted_success_rate for r in per),
        "success_without_collision": pct(r.clean_success_rate for r in per),
        "plans_through_obstacle": pct(r.plan_crossing_rate for r in per),
        "collisions": pct(r.executed_collision_rate for r in per),
    }


def curve_rows(cands: list[Candidate]) -> list[dict]:
    """One row per candidate x training seed: the learning curves (a policy's planned columns are empty)."""
    return [
        {"env": c.env, "method": c.method, "candidate": c.variant or "base", "steps": c.steps} | m
        for c in cands
        for m in c.models
    ]


def choosable(cands: list[Candidate]) -> list[Candidate]:
    """The candidates :data:`RULE` may choose: none executed by a controller that reads the map."""
    return [c for c in cands if not c.map_aware]


def choose(cands: list[Candidate], shared_budget: bool = False) -> dict[tuple[str, str], Candidate]:
    """Per (env, method), the candidate :data:`RULE` ranks first; with ``shared_budget``, the planners of one
    environment at one training length (:data:`SHARED_BUDGET`)."""
    best: dict[tuple[str, str], Candidate] = {}
    allowed = choosable(cands)
    for c in allowed:
        key = (c.env, c.method)
        if key not in best or c.rank() < best[key].rank():
            best[key] = c
    missing = {(c.env, c.method) for c in cands} - set(best)
    if missing:
        env, method = sorted(missing)[0]
        raise BadInput(
            f"{env} / {method}: every candidate is executed by a controller that reads the map",
            hint="add a variant with a controller that executes the plan alone (`cdrb controllers`)",
        )
    if not shared_budget:
        return best
    for env in dict.fromkeys(env for env, _ in best):
        trained = [k for k, c in best.items() if k[0] == env and c.planner and c.steps is not None]
        length = max((best[k].steps for k in trained), default=None)
        for key in trained:
            at = [c for c in allowed if (c.env, c.method) == key and c.steps == length]
            if not at:
                raise BadInput(
                    f"{env} / {key[1]}: no candidate at {length} steps, the length its environment's planners share",
                    hint="extend its curve to that length (an [[extend]] entry naming every planner)",
                )
            best[key] = min(at, key=Candidate.rank)
    return best


#: when a learning curve is extended before anything is chosen from it
RISING = (
    "at the longest training length, the method's best candidate (by the rule) succeeds more often than the same "
    "candidate one length shorter, by more than the standard error of the mean gain (the gains of each training "
    "seed's run between the two lengths: the points are snapshots of the same runs), unless every training seed "
    "succeeds in every episode there (a curve at its ceiling has nothing left to gain); or its plans through an "
    "obstacle fall by more than the standard error of their mean fall, unless none is left; with the grid's "
    "shared_budget, a planner's curve that rises extends every planner of its environment"
)


def _paired_change(prev: Candidate, last: Candidate, field: str) -> tuple[float, float, list] | None:
    """The mean change of ``field`` (per cent) from ``prev`` to ``last`` over the training seeds both have (the
    points are snapshots of the same runs), its standard error, and the values at ``last``; None without two
    seeds measured at both."""
    before = {m["seed"]: m.get(field) for m in prev.models}
    pairs = [(m.get(field), before[m["seed"]]) for m in last.models if m["seed"] in before]
    if len(pairs) < 2 or any(a is None or b is None for a, b in pairs):
        return None
    changes = [a - b for a, b in pairs]
    return sum(changes) / len(changes), std_or_none(changes) / len(changes) ** 0.5, [a for a, _ in pairs]


@dataclass(frozen=True)
class Rise:
    """A curve :func:`still_rising` found still rising: its best candidate at the longest length, the paired change in
    success points over the previous length and that change's standard error (both 0 where success was not measured
    twice), and why it rises: ``"success"`` (success gained beyond its standard error), ``"crossings"`` (fewer plans
    through an obstacle) or ``"shared"`` (another planner of its environment rises, under a shared budget)."""

    best: Candidate
    gain: float
    se: float
    by: str

    def text(self) -> str:
        if self.by == "shared":
            return "(shared budget: another planner's curve rises)"
        change = f"{self.gain:+.1f} ± {self.se:.1f} success points"
        return change if self.by == "success" else f"{change}, fewer plans through an obstacle"


def rising_notes(rising: dict[tuple[str, str], Rise], cap: int | None) -> tuple[str | None, list[str]]:
    """What `cdrb select` says of the curves :func:`still_rising` found: one line for those that reached the grid's
    ``steps_cap`` (they stop there by the grid's own rule), and a warning for each other, with the [[extend]] entry
    that would run it further."""
    capped = {key: r for key, r in rising.items() if cap is not None and r.best.steps >= cap}
    line = None
    if capped:
        line = f"{len(capped)} curves still rise at the grid's cap of {cap} steps (steps_cap), where they stop: " + (
            "; ".join(f"{env} / {method} {r.text()}" for (env, method), r in capped.items())
        )
    warnings = []
    for (env, method), r in rising.items():
        if (env, method) in capped:
            continue
        c = r.best
        variant = f"variants = [{toml_string(c.variant)}], " if c.variant and r.by != "shared" else ""
        warnings.append(
            f"{env} / {method}: the curve still rises at {c.steps} steps ({c.name}: {r.text()}): extend it before "
            f"choosing from it (the same runs, resumed: an "
            f"[[extend]] entry in the grid file with envs = [{toml_string(env)}], methods = [{toml_string(method)}], "
            f"{variant}steps = {2 * c.steps if cap is None else min(2 * c.steps, cap)})"
        )
    return line, warnings


def still_rising(cands: list[Candidate], shared_budget: bool = False) -> dict[tuple[str, str], Rise]:
    """Per (env, method) whose curve still rises by :data:`RISING`, its :class:`Rise`: the curve of the best
    candidate at the method's longest length, or else of the candidate the rule chooses where that is its own
    curve's last point (a variant whose curve stops shorter, chosen over the longer ones, may still rise). A method
    with one length or one training seed has no curve to judge. A candidate the rule never chooses (executed by a
    controller that reads the map) is not the curve judged either."""
    out = {}
    cands = choosable(cands)
    for key in dict.fromkeys((c.env, c.method) for c in cands):
        mine = [c for c in cands if (c.env, c.method) == key and c.steps is not None]
        lengths = sorted({c.steps for c in mine})
        if len(lengths) < 2:
            continue
        last = min((c for c in mine if c.steps == lengths[-1]), key=Candidate.rank)
        chosen = min(mine, key=Candidate.rank)
        for judged in [last] if chosen is last else [last, chosen]:
            rise = _rise(judged, mine)
            if rise is not None:
                out[key] = rise
                break
    if shared_budget:  # one planner that rises extends its environment's others with it
        for env in {env for env, method in out if METHODS.get(method).kind == "planner"}:
            trained = [c for c in cands if c.env == env and c.planner and c.steps is not None]
            longest = max(c.steps for c in trained)
            for method in dict.fromkeys(c.method for c in trained if (env, c.method) not in out):
                last = min((c for c in trained if c.method == method and c.steps == longest), key=Candidate.rank,
                           default=None)  # fmt: skip
                if last is not None:
                    out[(env, method)] = Rise(last, 0.0, 0.0, "shared")
    return out


def _rise(last: Candidate, mine: list[Candidate]) -> Rise | None:
    """How ``last`` gained on the previous point of its own variant's curve (variants' curves may stop at different
    lengths), if by more than its paired standard error; None when it did not, or is not its curve's last point."""
    same = [c for c in mine if c.variant == last.variant]
    shorter = [c for c in same if c.steps < last.steps]
    if not shorter or any(c.steps > last.steps for c in same):
        return None
    prev = max(shorter, key=lambda c: c.steps)
    success = _paired_change(prev, last, "success")
    crossing = _paired_change(prev, last, "plans_through_obstacle")
    gains = success is not None and success[0] > success[1] and not all(v >= 100.0 for v in success[2])
    falls = crossing is not None and -crossing[0] > crossing[1] and not all(v <= 0.0 for v in crossing[2])
    if not (gains or falls):
        return None
    gain, se = success[:2] if success is not None else (0.0, 0.0)
    return Rise(last, gain, se, "success" if gains else "crossings")


def chosen_flags(spec: GridSpec, cand: Candidate) -> tuple[list[str], list[str], list[str]]:
    """The `cdrb cluster`, `cdrb train` and `cdrb eval` flags that reproduce ``cand``: what applied to it in the
    tuning grid (an eval-only variant's model is the base model), with its training length when the grid set one."""
    variant = next((v for v in spec.variants if v.name == cand.variant), BASE)
    model_variant = variant if variant.own_model else BASE
    cluster = cluster_flags_for(spec, cand.env, cand.method, model_variant)
    train = flags_for(spec, cand.env, cand.method, model_variant)[0]
    evaluate = flags_for(spec, cand.env, cand.method, variant)[1]
    if cand.steps is not None:
        train = [*without_setting(train, "train", "steps"), "--steps", str(cand.steps)]
    return cluster, train, evaluate


def _toml_list(items: list[str]) -> str:
    return "[" + ", ".join(toml_string(x) for x in items) + "]"


def _toml_flags(flags: list[str], command: str) -> str:
    """A command's chosen flags as a settings file writes them: the table of the settings they set, or the list
    of flags where they hold more than settings (:func:`as_table`)."""
    table = as_table(flags, command) if flags else None
    return toml_value(table) if table is not None else _toml_list(flags)


def relative_files(flags: list[str], command: str, folder: Path) -> list[str]:
    """``flags`` of ``command`` with every file it reads (absolute once a grid is read) written relative to
    ``folder``, the settings file's own: a grid that includes the file then finds the same files from anywhere."""
    import os

    from cdrb_cli.orchestration.grid.commands import map_input_files

    def relative(value: str) -> str:
        return os.path.relpath(os.path.normpath(value), folder) if os.path.isabs(value) else value

    return map_input_files(flags, command, relative)


def settings_text(
    spec: GridSpec, grid_file: Path, best: dict[tuple[str, str], Candidate], folder: Path | None = None
) -> str:
    """The settings file: a provenance table, then one ``[[settings]]`` entry per env x method (file flags relative
    to ``folder``, the file's own folder)."""
    seeds = ",".join(map(str, spec.eval_seeds)) if spec.eval_seeds else "those of training"
    lines = [
        "# Written by `cdrb select`: the settings chosen on the tuning stream, one entry per env x method.",
        "# Test grids `include` this file; re-run `cdrb select` rather than editing it.",
        "[meta]",
        f"rule = {toml_string(RULE)}",
        *([f"budget = {toml_string(SHARED_BUDGET)}"] if spec.shared_budget else []),
        f"tuning_grid = {toml_string(str(grid_file))}",
        f"stream = {toml_string('tune, seeds ' + seeds)}",
        f"written = {toml_string(date.today().isoformat())}",
        "",
    ]
    for (env, method), cand in best.items():
        cluster, train, evaluate = chosen_flags(spec, cand)
        if folder is not None:
            cluster, train, evaluate = (
                relative_files(f, c, folder) for f, c in ((cluster, "cluster"), (train, "train"), (evaluate, "eval"))
            )
        lines += [
            "[[settings]]",
            f"env = {toml_string(env)}",
            f"method = {toml_string(method)}",
            f"chosen = {toml_string(cand.name)}",
            *([f"cluster = {_toml_list(cluster)}"] if cluster else []),
            f"train = {_toml_flags(train, 'train')}",
            f"eval = {_toml_flags(evaluate, 'eval')}",
            "",
        ]
    return "\n".join(lines)


def table_rows(cands: list[Candidate], best: dict[tuple[str, str], Candidate]) -> list[dict]:
    rows = []
    for c in cands:
        rows.append(
            {
                "env": c.env,
                "method": c.method,
                "candidate": c.variant or "base",
                "steps": c.steps,
                "seeds": c.seeds,
                "episodes": c.episodes,
                "success": round(c.success, 2),
                "success_std": None if c.success_std is None else round(c.success_std, 2),
                "plans_through_obstacle": None if c.crossing is None else round(c.crossing, 2),
                "collisions": round(c.collision, 2),
                "chosen": best[(c.env, c.method)] is c,
            }
        )
    return rows


def table_text(rows: list[dict], fmt: str) -> str:
    """The candidates' scores as CSV or a markdown table (the chosen one marked)."""
    from cdrb_cli.stages.report import plain_table, render

    if fmt == "csv":
        return render(rows, "csv")
    return plain_table(rows, lambda v: "–" if v is None else "**yes**" if v is True else "" if v is False else str(v))


def _steps(n: int | None) -> str:
    """A training length as the README writes it: 1000 -> 1k, 2500 -> 2.5k (none for an eval-only knob)."""
    return "" if n is None else f" @{n / 1000:g}k" if n >= 1000 else f" @{n}"


def summary_text(cands: list[Candidate], best: dict[tuple[str, str], Candidate], rising: dict) -> str:
    """What was chosen, one markdown line per environment and a column per method: the chosen candidate's tuning
    success ± sample std over training seeds at its training length, its plans through an obstacle in brackets
    (a policy makes none), and * where the method's curve still rises at its longest length (``rising``, from
    :func:`still_rising`)."""
    from cdrb_cli.envs.registry import family_of, make_spec
    from cdrb_cli.stages.report import method_order

    envs = list(dict.fromkeys(env for env, _ in best))
    methods = method_order(dict.fromkeys(method for _, method in best))
    lines = ["| Task | " + " | ".join(methods) + " |", "|---|" + "---:|" * len(methods)]
    for env in envs:
        cells = []
        for method in methods:
            c = best.get((env, method))
            if c is None:
                cells.append("–")
                continue
            spread = "n/a" if c.success_std is None else f"{c.success_std:.1f}"
            through = "" if c.crossing is None else f" ({c.crossing:.0f}%)"
            mark = "*" if (env, method) in rising else ""
            cells.append(f"{c.success:.1f} ± {spread}{_steps(c.steps)}{mark}{through}")
        try:
            name = family_of(make_spec(env)).display_name(env)
        except BadInput:  # an environment of a plugin that is not installed here: its id
            name = env
        lines.append(f"| {ui.plain(name)} | " + " | ".join(cells) + " |")
    note = (
        "Each cell: the chosen setting's tuning success (%) ± sample std over training seeds, @ its training length, "
        "in brackets its plans through an obstacle; *: the curve still rises at its longest length."
    )
    return "\n".join(lines) + "\n\n" + note + "\n"


def select(
    grid_file: Path,
    out: Path,
    force: bool = False,
    table: Path | None = None,
    curves: Path | None = None,
    overrides: list[str] = (),
    includes: list[Path] = (),
    docs: Path | None = None,
    block: str | None = None,
) -> Path:
    """Score the tuning grid's evals, choose by :data:`RULE`, write the settings file (and the candidates' table,
    and with ``docs`` the choices' summary into that markdown file's ``block``)."""
    from cdrb_cli.artifacts.outputs import distinct_outputs
    from cdrb_cli.orchestration.grid import load_grid

    distinct_outputs(out=out, table=table, curves=curves, docs=docs)
    spec = load_grid(grid_file, overrides, includes)
    # every file the grid reads or writes is an input here: its settings files (included ones too) and the
    # artifacts under its `out` (demos, models, evals), none of which an output may replace
    inputs = [grid_file, *includes, *spec._sources]
    tasks = expand(spec)
    inputs += [p for task in tasks for p in (*task.inputs, *task.outputs)]
    artifacts.check_output(out, force, "--out", inputs)
    if Path(out).suffix.lower() != ".toml":  # the settings file test grids `include` and --config reads as TOML
        raise BadInput(f"--out {out}: select writes a TOML settings file", hint="name it with .toml, e.g. tuned.toml")
    for path, flag in ((table, "--table"), (curves, "--curves")):
        if path is not None:
            artifacts.check_output(path, force, flag, inputs)
    cands = candidates(spec, tasks)
    if not cands:
        raise BadInput(f"{grid_file}: the grid has no evals to choose from", hint="add envs, methods and variants")
    best, rising = choose(cands, spec.shared_budget), still_rising(cands, spec.shared_budget)
    if docs is not None:
        from cdrb_cli.stages.docs_blocks import check_docs_block

        summary = summary_text(cands, best, rising)
        check_docs_block(docs, block, summary, inputs)
    summary_line, warnings = rising_notes(rising, spec.steps_cap)
    if summary_line is not None:
        ui.log(summary_line)
    for line in warnings:
        ui.warn(line)
    for (env, method), c in best.items():
        ui.log(
            f"{env} / {method}: {c.name} (success {c.success:.1f}%, through an obstacle "
            f"{'n/a' if c.crossing is None else f'{c.crossing:.1f}%'}, collisions {c.collision:.1f}%)"
        )
    from cdrb_cli.files import together

    with together():  # the settings file, its tables and the page land together or not at all
        with artifacts.claim_output(out, force, "--out", inputs), artifacts.atomic_path(out) as tmp:
            tmp.write_text(settings_text(spec, Path(grid_file), best, Path(out).resolve().parent))
        if table is not None:
            fmt = "csv" if table.suffix == ".csv" else "markdown"
            with artifacts.claim_output(table, force, "--table", inputs), artifacts.atomic_path(table) as tmp:
                tmp.write_text(table_text(table_rows(cands, best), fmt))
        if curves is not None:
            from cdrb_cli.stages.report import render

            with artifacts.claim_output(curves, force, "--curves", inputs), artifacts.atomic_path(curves) as tmp:
                tmp.write_text(render(curve_rows(cands), "csv"))
        if docs is not None:
            from cdrb_cli.stages.docs_blocks import write_docs_block

            write_docs_block(docs, block, summary, inputs)
    return out
