"""`cdrb report`: a Table-1-style comparison of eval artifacts, and pictures.

Rows are environments, columns methods; cells are success rate mean ± std over seeds. A second table gives the
safety and efficiency columns: planned states inside walls, executed collisions, normalized path length and
planning time. Evals are only compared when their protocols match (same seeds, episodes per seed, protocol, pairs
stream and episode length); each method may use its own controller settings (chosen for it on the tuning stream,
shown in the detail table) but one per method. Anything else is an error, never a silent average.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import numpy as np

from cdrb_cli import artifacts, ui
from cdrb_cli.errors import BadInput
from cdrb_cli.settings import clip
from cdrb_cli.stages.metrics import ci95, mean_or_none, sample_std, std_or_none, sum_failures
from cdrb_cli.stages.plan_metrics import (
    body_crossing_rates,
    body_state_rates,
    body_text,
    first_step_ratio,
    new_crossing_rates,
    wall_crossing_rates,
)
from cdrb_cli.stages.results import failure_text, is_policy_eval, per_seed

PAPER_FIGURES = "paper_table1.toml"  # package data: the paper's Table 1, env id -> method -> (mean, std)


def paper_figures(path: Path | None = None) -> dict[str, dict[str, tuple[float, float]]]:
    """The paper's Table 1 figures (success %, mean and std) per environment id and method, from the shipped data
    file or from ``path`` (a TOML file of the same shape). Method names are the registry's, or those the file lists
    in a top-level ``others = [...]``: published methods this project does not implement (OGBench's six)."""
    from importlib import resources

    from cdrb_cli.artifacts.core import read_input_text
    from cdrb_cli.files import parse_toml

    where = path or PAPER_FIGURES
    if path is not None:
        text = read_input_text(path, "--paper-figures", 1 << 20, "figures file", "give a TOML file")
    else:
        text = resources.files("cdrb_cli").joinpath(PAPER_FIGURES).read_text()
    raw = parse_toml(text, f"--paper-figures {where}", hint="see cdrb_cli/paper_table1.toml for the shape")
    import math

    from cdrb_cli.envs.registry import make_spec
    from cdrb_cli.methods.registry import METHODS

    def percent(x) -> bool:
        return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) and 0 <= x <= 100

    others = raw.pop("others", [])
    if not isinstance(others, list) or not all(isinstance(o, str) and o.strip() for o in others):
        raise BadInput(
            f"--paper-figures {where}: others must be a list of method names",
            hint='e.g. others = ["QRL", "HIQL"]: published methods this project does not implement',
        )
    if not raw:
        raise BadInput(f"--paper-figures {where}: has no figures", hint="see cdrb_cli/paper_table1.toml for the shape")
    out = {}
    for env, by in raw.items():
        ok = isinstance(by, dict) and all(
            isinstance(v, list) and len(v) == 2 and all(percent(x) for x in v) for v in by.values()
        )
        if not ok:
            raise BadInput(
                f"--paper-figures {where}: [{clip(env, 40)}] is not a table of method = [mean, std], each a "
                "per cent between 0 and 100",
                hint="see cdrb_cli/paper_table1.toml for the shape",
            )
        try:
            make_spec(env)
        except BadInput as exc:
            raise BadInput(f"--paper-figures {where}: [{clip(env, 40)}]: {exc.message}",
                           hint="`cdrb envs` lists them") from None  # fmt: skip
        for m in by:
            if m not in others:
                METHODS.get(m, f"--paper-figures {where}: [{clip(env, 40)}] (or list it in others = [...])")
        out[env] = {m: (float(v[0]), float(v[1])) for m, v in by.items()}
    return out


def _env_name(spec) -> str:
    """The family's display name of an environment ("Maze Tight")."""
    from cdrb_cli.envs.registry import family_of

    return family_of(spec).display_name(spec.id)


def method_rank(method: str) -> tuple[int, str]:
    """Report columns follow the method registry's order (the paper's Table 1 order for the built-ins)."""
    from cdrb_cli.methods.registry import METHODS

    names = METHODS.names()
    base = method.split(" ")[0]
    return (names.index(base) if base in names else len(names), method)


def _protocol(ev) -> tuple:
    """What must match across methods: the pairs and how success is measured. The controller is not part of it:
    each method runs with the controller settings chosen for it on the tuning stream (one per method)."""
    c = ev.manifest.config
    return (c.episodes, c.protocol, c.extra_steps, ev.manifest.env.episode_limit, c.stream)


def _planning(ev) -> tuple:
    """How one method planned: these must agree across the seeds pooled into one row."""
    c = ev.manifest.config
    return (controller_name(ev), c.sampler, c.sample_steps, c.use_ema)


def controller_name(ev) -> str:
    """How an eval executed: the controller and its settings, or ``closed loop (SAMPLER)`` for a policy."""
    if is_policy_eval(ev):
        return f"closed loop ({ev.manifest.config.sampler})"
    c = ev.manifest.config.controller
    settings = ", ".join(f"{k} {v}" for k, v in c.model_dump().items() if k != "name")
    return f"{c.name} ({settings})"


def method_label(ev) -> str:
    """The method, its preset when not the quick one, how it was executed when closed loop and how it kept its plans
    out of obstacles (e.g. ``cdrb [every 20, repair k=4]``, ``cdrb [masked buffer, best of 4]``), and whether its
    controller reads the map: each is its own row."""
    return _label(ev, settings=True)


def _label(ev, settings: bool) -> str:
    """:func:`method_label`, or with ``settings`` false without the run's settings (re-planning, avoidance): what
    sets the method apart, the column a summary may give it when each row chose its own settings."""
    s = ev.manifest.summary
    label = s.method if s.model_preset == "quick" else f"{s.method} ({s.model_preset})"
    config = ev.manifest.config
    how = [s.variant] if getattr(s, "variant", None) else []
    how += _settings(ev) if settings else []
    if not is_policy_eval(ev) and _knows_map(config.controller.name):
        how.append("planner + map-aware controller")
    return f"{label} [{'; '.join(how)}]" if how else label


def _settings(ev) -> list[str]:
    """How an eval ran its method: its re-planning and its avoidance of obstacles, where not the plain ones."""
    config = ev.manifest.config
    how = [config.replan.label()] if config.replan.mode != "never" else []
    avoid = getattr(config, "avoid", None)
    if avoid is not None and avoid.label() != "plain":
        how.append(avoid.label())
    return how


def _scene(ev) -> str:
    """What an environment's name stands for: its walls and obstacles (a map's name is its file's name)."""
    spec = ev.manifest.env
    return json.dumps([spec.scene.model_dump(mode="json"), spec.obstacles.model_dump(mode="json")], sort_keys=True)


def _content(item) -> str:
    """What an artifact (or a manifest's parent reference) holds, as a hash: its data's, else its bytes'."""
    return item.data_sha256 or item.sha256


def _run(ev, training: bool) -> dict:
    """Everything about how an eval ran its model that seeds pooled into one row must share: its settings less the
    evaluation seeds, the sampling seed and the scene file's path (its content is the environment's), the route
    buffer by its content, the training length of the model evaluated and, with ``training``, the digest of its
    training settings."""
    config = ev.manifest.config.model_dump(mode="json")
    for key in ("seeds", "seed", "scene"):
        config.pop(key, None)
    if (config.get("avoid") or {}).get("route_buffer") is not None:
        shas = [_content(p) for p in ev.manifest.parents if p.kind == "buffer"]
        config["avoid"]["route_buffer"] = shas[0] if shas else config["avoid"]["route_buffer"]
    config["model_steps"] = ev.manifest.summary.model_steps
    if training:
        config["model_training"] = ev.manifest.summary.model_training
    return config


def _at(data: dict, key: str):
    """The value of a dotted ``key`` in nested dicts (None where a part is missing)."""
    for part in key.split("."):
        data = data.get(part) if isinstance(data, dict) else None
    return data


def two_names(a, b) -> tuple[str, str]:
    """How an error names two files: by name, or by path where the names are the same (two grids' folders)."""
    na, nb = a.path.name, b.path.name
    return (na, nb) if na != nb else (clip(str(a.path), 200), clip(str(b.path), 200))


def _same_runs(label: str, env_id: str, group: list) -> None:
    """Refuse, naming both files and the first setting that differs, evals pooled into one row that ran otherwise."""
    first = group[0]
    for ev in group[1:]:
        # the training digest is compared where both evals record it (older evals do not)
        training = None not in (first.manifest.summary.model_training, ev.manifest.summary.model_training)
        a, b = _run(first, training), _run(ev, training)
        one, other = two_names(first, ev)
        diff = next(iter(artifacts.differences(a, b)), None)
        if diff == "model_training":
            raise BadInput(
                f"{label} on {env_id}: {one} and {other} evaluate models trained with other "
                "settings (net, learning rate, method parameters...)",
                hint="pool as seeds only models trained alike: report the others as their own method (`cdrb report`"
                " of each set)",
            )
        if diff is not None:
            raise BadInput(
                f"{label} on {env_id}: {one} and {other} differ in {diff} "
                f"({clip(repr(_at(a, diff)), 40)} vs {clip(repr(_at(b, diff)), 40)})",
                hint="evaluate every seed of a method with the same settings, on models of the same training length",
            )


def models_of(group: list) -> int:
    """How many models the evals of a row evaluated (their model parents' content)."""
    return len({_content(p) for ev in group for p in ev.manifest.parents if p.kind == "model"})


def _knows_map(controller: str) -> bool:
    """Whether the controller reads the map to steer (its rows are not the planner's own)."""
    from cdrb_cli.envs.registry import CONTROLLERS

    return controller in CONTROLLERS and CONTROLLERS.get(controller).knows_map


def collect_rows(evals) -> list[dict]:
    """One row per (environment, method). Several evals of one method (e.g. one per training seed) are pooled as
    separate seeds; within an environment every method must use the same protocol and the same evaluation seeds,
    and a seed may appear once per method. Anything else is an error, never a silent average."""
    groups: dict[tuple[str, str], list] = {}
    for ev in evals:
        groups.setdefault((ev.manifest.env.id, method_label(ev)), []).append(ev)
    by_env: dict[str, dict[str, list]] = {}
    for (env_id, label), group in groups.items():
        by_env.setdefault(env_id, {})[label] = group
    rows = []
    for env_id, methods in by_env.items():
        protos = {_protocol(ev) for group in methods.values() for ev in group}
        if len(protos) > 1:
            first, second = sorted(protos, key=str)[:2]
            raise BadInput(
                f"eval files for {env_id} use different protocols ({_describe(first)} vs {_describe(second)})",
                hint="evaluate every model with the same --episodes, --protocol and --stream",
            )
        every = [ev for group in methods.values() for ev in group]
        scene = _scene(every[0])
        for ev in every[1:]:
            if _scene(ev) != scene:
                one, other = two_names(every[0], ev)
                raise BadInput(
                    f"{one} and {other}: both name the environment {env_id} but hold other walls or obstacles",
                    hint="give each map file its own name (the environment is named after it)",
                )
        seed_sets, pooled = {}, {}
        for label, group in methods.items():
            settings = sorted({_planning(ev) for ev in group}, key=str)
            if len(settings) > 1:
                a, b = settings[:2]
                what = "controllers" if a[0] != b[0] else "sampler settings (sampler, steps, EMA)"
                shown = (a[0], b[0]) if a[0] != b[0] else (a[1:], b[1:])
                raise BadInput(
                    f"{label} on {env_id}: its eval files use different {what} ({shown[0]} vs {shown[1]})",
                    hint="evaluate every seed of a method with the same settings",
                )
            _same_runs(label, env_id, group)
            pooled[label] = [r for ev in group for r in per_seed(ev)]
            seeds = [r.seed for r in pooled[label]]
            if len(seeds) != len(set(seeds)):
                dup = sorted({x for x in seeds if seeds.count(x) > 1})
                holding = [ev for ev in group if dup[0] in {r.seed for r in per_seed(ev)}]
                files = two_names(*holding[:2]) if len(holding) > 1 else [clip(holding[0].path.name, 40)]
                raise BadInput(
                    f"{label} on {env_id}: evaluation seed(s) {dup} appear in more than one eval file "
                    f"({', '.join(files)})",
                    hint="pass one eval per method and seed",
                )
            seed_sets[label] = tuple(sorted(seeds))
        if len(set(seed_sets.values())) > 1:
            (la, sa) = next(iter(seed_sets.items()))
            lb, sb = next((lb, sb) for lb, sb in seed_sets.items() if sb != sa)  # a method that differs from the first
            raise BadInput(
                f"eval files for {env_id} use different evaluation seeds ({list(sa)} for {la} vs {list(sb)} for {lb})",
                hint="evaluate every method on the same --seeds",
            )
        for label, group in methods.items():
            per = pooled[label]
            succ = np.array([r.success_rate for r in per])
            ratios = [r.path_length_ratio for r in per if r.path_length_ratio is not None]
            impossible = mean_or_none([r.impossible_jump_rate for r in per])
            new_rates = _pooled([new_crossing_rates(ev) for ev in group])
            wall_rates = _pooled([wall_crossing_rates(ev) for ev in group])
            first = group[0]
            rows.append(
                {
                    "env": ui.plain(env_id),
                    "method": ui.plain(label),
                    "base_method": ui.plain(first.manifest.summary.method),
                    "preset": ui.plain(first.manifest.summary.model_preset),
                    "pairs": first.manifest.config.stream,
                    "protocol": ui.plain(first.manifest.config.protocol),
                    "controller": ui.plain(controller_name(first)),
                    "seeds": len(per),
                    "models": models_of(group),
                    "episodes": first.manifest.config.episodes,
                    "success_mean": 100 * float(succ.mean()),
                    "success_std": 100 * sample_std(succ),
                    "success_ci95": 100 * ci95(succ),
                    **_rate("weighted_success", [r.weighted_success_rate for r in per]),
                    **_rate("clean_success", [r.clean_success_rate for r in per]),
                    **_rate("in_wall", [r.in_wall_fraction for r in per]),  # None for a policy: it makes no plans
                    **_rate("crossing", [r.plan_crossing_rate for r in per]),
                    **_rate("new_crossing", new_rates),  # None in the training scene
                    **_rate("wall_crossing", wall_rates),  # None where the walls are the whole test
                    "crossing_by_body": body_text([body_crossing_rates(ev) for ev in group]),
                    "in_wall_by_body": body_text([body_state_rates(ev) for ev in group], digits=2),
                    "jump_ratio": mean_or_none([r.jump_ratio for r in per]),
                    "first_step_ratio": first_step_ratio(group),
                    "impossible_jump_mean": None if impossible is None else 100 * impossible,
                    "collision_mean": 100 * float(np.mean([r.executed_collision_rate for r in per])),
                    "path_ratio": float(np.mean(ratios)) if ratios else None,
                    "plan_ms": 1000 * float(np.mean([r.plan_seconds for r in per])),
                    "replans": mean_or_none([r.replans for r in per]),
                    "episode_planning_ms": _ms(mean_or_none([r.planning_seconds for r in per])),
                    "failures": failure_text(sum_failures(r.failures for r in per)),
                    "path": ui.plain(";".join(str(ev.path) for ev in group)),
                    "env_name": ui.plain(_env_name(first.manifest.env)),
                    "column": ui.plain(_label(first, settings=False)),
                    "settings": ui.plain(", ".join(_settings(first))) or "plain",
                }
            )
    return rows


def _pooled(rates: list[list[float] | None]) -> list:
    """Every eval's per-seed rates in one list, or [None] when an eval of the group lacks them."""
    return [x for r in rates for x in r] if all(rates) else [None]


def _rate(name: str, values: list) -> dict:
    """``NAME_mean`` and ``NAME_std`` in percent over seeds; None when a seed did not measure it."""
    mean, std = mean_or_none(values), std_or_none(values)
    return {f"{name}_mean": None if mean is None else 100 * mean, f"{name}_std": None if std is None else 100 * std}


def _evaluation(ev) -> str:
    """An eval's whole provenance (when and by what it ran, its settings, its parents by content) less its layout's
    version: what an eval and its compact copy (`cdrb export --compact`) share, and no other two runs."""
    manifest = ev.manifest.model_dump(mode="json")
    manifest.pop("schema_version", None)
    return json.dumps(manifest, sort_keys=True, default=str)


def seed_rows(evals) -> list[dict]:
    """One row per eval file and evaluation seed (the per-seed table the docs keep beside each grouped row); the
    same eval given twice (a copy of its file, or its compact copy) is refused, as in the grouped rows."""
    rows, seen = [], {}
    for ev in evals:
        for key in (_content(ev), _evaluation(ev)):  # a hash and a JSON text: the two never meet
            other = seen.setdefault(key, ev)
            if other is not ev:
                one, two = two_names(other, ev)
                raise BadInput(
                    f"{one} and {two}: the same eval twice", hint="pass each eval once (a compact copy is one)"
                )
        c = ev.manifest.config
        new_rates, bodies, states = new_crossing_rates(ev), body_crossing_rates(ev), body_state_rates(ev)
        walls = wall_crossing_rates(ev)
        for i, r in enumerate(per_seed(ev)):
            rows.append(
                {
                    "env": ui.plain(ev.manifest.env.id),
                    "method": ui.plain(method_label(ev)),
                    "controller": ui.plain(controller_name(ev)),
                    "pairs": c.stream,
                    "protocol": ui.plain(c.protocol),
                    "seed": r.seed,
                    "episodes": r.episodes,
                    "success": 100 * r.success_rate,
                    "weighted_success": None if r.weighted_success_rate is None else 100 * r.weighted_success_rate,
                    "success_without_collision": 100 * r.clean_success_rate,
                    "in_obstacle": None if r.in_wall_fraction is None else 100 * r.in_wall_fraction,
                    "plans_through_obstacle": None if r.plan_crossing_rate is None else 100 * r.plan_crossing_rate,
                    "plans_through_a_wall": None if walls is None else 100 * walls[i],
                    "plans_through_new_obstacle": None if new_rates is None else 100 * new_rates[i],
                    "plans_through_obstacle_by_body": body_text([bodies], i),
                    "in_obstacle_by_body": body_text([states], i, digits=2),
                    "collisions": 100 * r.executed_collision_rate,
                    "plan_ms": 1000 * r.plan_seconds,
                    "failures": failure_text(r.failures),
                    "path": ui.plain(str(ev.path)),
                }
            )
    return rows


def plain_table(rows: list[dict], cell, skip: tuple[str, ...] = ()) -> str:
    """A markdown table of ``rows``: one column per key (less ``skip``), each value written by ``cell``."""
    keys = [k for k in rows[0] if k not in skip]
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(cell(r[k]) for k in keys) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def render_seed_rows(rows: list[dict], fmt: str) -> str:
    """Per-seed rows as CSV, JSON or a markdown table."""
    if fmt in ("json", "csv"):
        return render(rows, fmt)
    return plain_table(rows, lambda v: "–" if v is None else f"{v:.1f}" if isinstance(v, float) else str(v), ("path",))


def markdown_safe(row: dict) -> dict:
    """``row`` with every text value fit for one table cell: names come from artifacts, which anyone can write, and
    a line break, a ``|`` or a ``<!-- ... -->`` marker in one would break the table or the docs block it lands in."""
    return {
        k: " ".join(v.split()).replace("|", "\\|").replace("<", "&lt;") if isinstance(v, str) else v
        for k, v in row.items()
    }


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else 1000 * seconds


def _describe(p) -> str:
    extra = f" + {p[2]} extra" if p[2] else ""
    return f"{p[0]} episodes per seed, protocol {p[1]}, episodes of {p[3]}{extra} steps, {p[4]} pairs"


def method_order(methods) -> list[str]:
    """``methods`` (labels, a preset or variant after the name) in the method registry's order: the columns of
    every table and the bars of every chart."""
    return sorted(methods, key=method_rank)


def measured_here(rows: list[dict]) -> str:
    """The pairs and protocol of ``rows``, for a note set beside figures measured otherwise."""
    streams = ", ".join(sorted({str(r["pairs"]) for r in rows if r.get("pairs")}))
    protocols = ", ".join(sorted({str(r["protocol"]) for r in rows if r.get("protocol")}))
    return f" (the rows here: {streams} pairs, protocol {protocols})" if streams and protocols else ""


def _spread_known(row: dict) -> dict:
    """``row`` for a machine reader: a row of one seed has no spread (null), not a spread of 0."""
    if row.get("seeds", 2) > 1:
        return row
    return {k: None if k.endswith(("_std", "_ci95")) else v for k, v in row.items()}


def render(rows: list[dict], fmt: str, paper: bool | dict = False) -> str:
    figures = (paper if isinstance(paper, dict) else paper_figures()) if paper else {}
    if fmt in ("json", "csv"):
        rows = [_spread_known(r) for r in rows]
    if fmt == "json":
        return json.dumps(rows, indent=2)
    if fmt == "csv":
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=list(rows[0].keys()))
        w.writeheader()
        w.writerows(rows)
        return buf.getvalue()
    rows = [markdown_safe(r) for r in rows]
    envs = list(dict.fromkeys(r["env"] for r in rows))
    methods = method_order(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["env"], r["method"]): r for r in rows}
    name = {r["env"]: r["env_name"] for r in rows}
    lines = ["| Success rate (%) | " + " | ".join(methods) + " |", "|---|" + "---:|" * len(methods)]
    for env in envs:
        vals = []
        best = max((cell[(env, m)]["success_mean"] for m in methods if (env, m) in cell), default=None)
        for m in methods:
            r = cell.get((env, m))
            if r is None:
                vals.append("–")
                continue
            spread = f"{r['success_std']:.2f}" if r["seeds"] > 1 else "n/a"
            v = f"{r['success_mean']:.2f} ± {spread}"
            vals.append(f"**{v}**" if r["success_mean"] == best else v)
        lines.append(f"| {name[env]} | " + " | ".join(vals) + " |")
        if paper and env in figures:
            pv = [
                f"{figures[env][m.split(' ')[0]][0]:.2f} ± {figures[env][m.split(' ')[0]][1]:.2f}"
                if m.split(" ")[0] in figures[env]
                else "–"
                for m in methods
            ]
            lines.append(f"| {name[env]} (paper) | " + " | ".join(pv) + " |")
    if paper:
        lines.append(
            "\n(paper) rows are the paper's figures, measured with other experts, controllers, success radius, "
            f"horizon/stride and training budgets{measured_here(rows)}: see docs/benchmarks.md before comparing."
        )
    lines += [
        "",
        "| env | method | controller | pairs | seeds x episodes | success (%) ± std [95% CI] | "
        "weighted success (%) | success without collision (%) | planned states in walls (%) | "
        "plans through an obstacle (%) | through a new one (%) | first step / allowed (median) | "
        "largest jump / allowed | "
        "plans with an impossible jump (%) | "
        "executed collisions (%) | path length / expert | plan time (ms) | re-plans per episode | "
        "planning per episode (ms) | failed episodes by cause |",
        "|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|",
    ]

    def opt(v, f):
        return "–" if v is None else format(v, f)

    for env in envs:
        for m in methods:
            r = cell.get((env, m))
            if r is None:
                continue
            lines.append(
                f"| {name[env]} | {m} | {r['controller']} | {r['pairs']} | {r['seeds']} x {r['episodes']} | "
                f"{_success_cell(r)} | "
                f"{_pm(r['weighted_success_mean'], r['weighted_success_std'], r['seeds'])} | "
                f"{_pm(r['clean_success_mean'], r['clean_success_std'], r['seeds'])} | "
                f"{_pm(r['in_wall_mean'], r['in_wall_std'], r['seeds'])}{_bodies(r.get('in_wall_by_body'))} | "
                f"{_crossing_cell(r)} | "
                f"{opt(r.get('new_crossing_mean'), '.1f')} | "
                f"{opt(r['first_step_ratio'], '.2f')} | {opt(r['jump_ratio'], '.2f')} | "
                f"{opt(r['impossible_jump_mean'], '.1f')} | "
                f"{r['collision_mean']:.1f} | {opt(r['path_ratio'], '.2f')} | {r['plan_ms']:.1f} | "
                f"{opt(r['replans'], '.1f')} | {opt(r['episode_planning_ms'], '.1f')} | {r['failures'] or '–'} |"
            )
    lines += ["", COLUMN_NOTES]
    text = "\n".join(lines) + "\n"
    if fmt == "table":
        return text.replace("**", "")
    return text


def _crossing_cell(row: dict) -> str:
    """Plans through an obstacle (%), with the share of each body where the family moves several, and of the walls
    alone where the workspace's bounds count too."""
    if row["crossing_mean"] is None:
        return "–"
    walls = row.get("wall_crossing_mean")
    return f"{row['crossing_mean']:.1f}{_bodies(row.get('crossing_by_body'))}" + (
        "" if walls is None else f"; a wall {walls:.1f}"
    )


def _bodies(text: str | None) -> str:
    return f" ({text})" if text else ""


#: what the less obvious columns of the detailed table measure (printed under it)
COLUMN_NOTES = (
    "Weighted success: successful episodes whose plan has no state in an obstacle. Plans through an obstacle: a "
    "planned state in one, or a straight segment between two consecutive planned states that crosses one (a plan "
    "can have every state free and still jump a wall); both in brackets by body where a plan moves several "
    "(Fetch: gripper, block; one plan or state can count for both), and after them the plans through a wall alone "
    "where a body's leaving its workspace counts too (Fetch: a gripper planned under the table top); through a new "
    "one: the same for the obstacles the "
    "training scene did not have (`--scene`/`--maze-map`; – in the training scene). First step / allowed: how far "
    "a plan's first step leaves the start, against one plan step of the dynamics (near 1: the plan starts where "
    "the robot is). Largest jump / allowed and plans with an impossible jump: "
    "the longest step between consecutive planned states against the distance the dynamics allow in one plan step; "
    "planners output paths that the controller follows at its own pace, so almost every plan has a step longer "
    "than that (a learned plan's 100% here is expected and not a failure); a wall between two planned states is "
    "what the crossing column catches."
)


def _success_cell(r: dict) -> str:
    """``mean ± std [± 95% CI]`` over seeds; with one seed there is no spread to show (n/a, not a zero)."""
    if r["seeds"] < 2:
        return f"{r['success_mean']:.1f} ± n/a (1 seed)"
    return f"{r['success_mean']:.1f} ± {r['success_std']:.1f} [± {r['success_ci95']:.1f}]"


def _pm(mean, std, seeds: int = 2) -> str:
    """``mean ± std`` with 2 decimals (the spread n/a for one seed), or n/a (a policy's plan measures)."""
    if mean is None:
        return "n/a"
    return f"{mean:.2f} ± {std:.2f}" if seeds > 1 else f"{mean:.2f} ± n/a"
