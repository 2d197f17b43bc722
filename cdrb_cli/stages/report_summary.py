"""`cdrb report --format summary`: Table 1 in one line per environment, each method against the straight line's
floor (the best straight-line column of the row), one column per method across rows trained at other presets or
run with other settings, and the published figures beside them."""

from __future__ import annotations

from cdrb_cli.stages.report import markdown_safe, measured_here, method_order, paper_figures


def render_summary(rows: list[dict], paper: bool | dict = False) -> str:
    """Table 1 in one line per environment (markdown): the straight line's success, the floor, then every learned
    method's success ± std over seeds with its weighted success, each marked where it does not beat the floor
    (``≤ floor``: not above its mean; ``≈ floor``: above it by no more than seed noise, :func:`_above`), and
    with ``paper`` the paper's figures. A row without a straight-line eval says so instead of a floor."""
    figures = (paper if isinstance(paper, dict) else paper_figures()) if paper else {}
    rows, preset_note = preset_columns([markdown_safe(r) for r in rows])
    rows, settings_note = setting_columns(rows)
    envs = list(dict.fromkeys(r["env"] for r in rows))
    cell = {(r["env"], r["method"]): r for r in rows}
    floors = [m for m in method_order(dict.fromkeys(r["method"] for r in rows)) if m.split(" ")[0] == "straight"]
    methods = [m for m in method_order(dict.fromkeys(r["method"] for r in rows)) if m not in floors]
    floor_heads = [f"{m.replace('straight', 'straight line', 1)} (floor)" for m in floors] or ["straight line (floor)"]
    head = ["Table 1 row", "seeds x pairs", *floor_heads, *methods]
    paper_methods = [m for m in dict.fromkeys(m for env in envs for m in figures.get(env, {}))]
    # published figures as their source gives them: whole per cents (OGBench) or two decimals (the paper's Table 1)
    places = 0 if all(v[0].is_integer() for by in figures.values() for v in by.values()) else 2
    shown = bool(figures) and bool(paper_methods)  # no column of dashes where the paper has none of these rows
    if shown:
        head.append("paper: " + " / ".join(paper_methods))
    lines = ["| " + " | ".join(head) + " |", "|---|---|" + "---:|" * (len(head) - 2)]
    below = level = ceiling = False
    for env in envs:
        here = [cell[(env, m)] for m in floors + methods if (env, m) in cell]
        shapes = sorted({f"{r['seeds']} x {r['episodes']}" for r in here})
        mine = [cell[(env, m)] for m in floors if (env, m) in cell]
        floor = max(mine, key=lambda r: r["success_mean"]) if mine else None  # the highest floor: the one to beat
        vals = [here[0]["env_name"], " / ".join(shapes)]
        vals += [_summary_cell(cell[(env, m)]) if (env, m) in cell else "–" for m in floors] or ["no floor measured"]
        if floors and floor is None:
            vals[2] = "no floor measured"
        if floor is not None and floor["success_mean"] >= CEILING:
            vals[0] += " (floor = ceiling: no comparison)"
            ceiling = True
        for m in methods:
            r = cell.get((env, m))
            if r is None:
                vals.append("–")
                continue
            text = _summary_cell(r)
            if floor is not None and r["success_mean"] <= floor["success_mean"]:
                text += " ≤ floor"
                below = True
            elif floor is not None and not _above(r, floor):
                text += " ≈ floor"
                level = True
            vals.append(text)
        if shown:
            known = figures.get(env, {})
            vals.append(" / ".join(f"{known[m][0]:.{places}f}" if m in known else "–" for m in paper_methods))
        lines.append("| " + " | ".join(vals) + " |")
    over = "training seeds"
    if any(0 < r.get("models", 0) < r["seeds"] for r in rows):  # 0: evals that name no model
        over = "seeds (a model's evaluation seeds where a row has fewer models than seeds: `models`, --format csv)"
    notes = [
        f"Cells: success (%) ± sample std over {over}, then (in brackets) weighted success: successful "
        "episodes whose plan has no state in an obstacle (a policy makes no plan: n/a)."
    ]
    if below:
        notes.append(
            "≤ floor: the method does not beat the straight line from start to goal on that row (the best of its "
            "straight-line columns)."
        )
    if level:
        notes.append(
            f"≈ floor: above the straight line's mean, but not by more than seed noise (Welch's one-sided t-test "
            f"over training seeds, p ≥ {FLOOR_ALPHA})."
        )
    if ceiling:
        notes.append(
            f"floor = ceiling: the straight line from start to goal already solves {CEILING:g}% or more of the pairs, "
            "so the row cannot rank methods (it checks that none breaks what needs no plan)."
        )
    if preset_note:
        notes.append(preset_note)
    if settings_note:
        notes.append(settings_note)
    if shown:
        notes.append(
            "The paper's figures were measured with other experts, controllers, success radius, horizon/stride and "
            f"training budgets{measured_here(rows)}: see docs/benchmarks.md before comparing."
        )
    elif figures:
        notes.append("The paper gives no figures for these rows.")
    return "\n".join(lines) + "\n\n" + " ".join(notes) + "\n"


#: the significance level at which a method's success counts as above the straight line's
FLOOR_ALPHA = 0.05
#: a floor at or above this success (%) leaves a row nothing to rank
CEILING = 99.0


def _above(r: dict, floor: dict) -> bool:
    """Whether ``r``'s success is above ``floor``'s by more than seed noise: Welch's one-sided t-test over the
    training seeds of each (sample std, seed count) at :data:`FLOOR_ALPHA`. With one seed on either side there is
    no spread to test, and the means decide; with no spread on both sides, any difference is real."""
    if r["seeds"] < 2 or floor["seeds"] < 2:
        return r["success_mean"] > floor["success_mean"]
    if r["success_std"] == 0 and floor["success_std"] == 0:
        return r["success_mean"] > floor["success_mean"]
    from scipy.stats import ttest_ind_from_stats

    test = ttest_ind_from_stats(
        r["success_mean"], r["success_std"], r["seeds"], floor["success_mean"], floor["success_std"],
        floor["seeds"], equal_var=False, alternative="greater",
    )  # fmt: skip
    return bool(test.pvalue < FLOOR_ALPHA)


def preset_columns(rows: list[dict]) -> tuple[list[dict], str]:
    """``rows`` with each method's preset taken out of its column name (``mlp (paper)`` -> ``mlp``), so one
    method is one column across rows whose models were trained at different presets (each row's settings are its
    own), and a note naming the rows of each preset other than the quick one. Where two of one row's methods would
    then share a column, ``rows`` are kept as they are."""
    from cdrb_cli.presets import PRESETS

    merged, where = [], {}
    for r in rows:
        label = r["method"]
        for preset in PRESETS:
            if preset != "quick" and f" ({preset})" in label:
                label = label.replace(f" ({preset})", "", 1)
                where.setdefault(preset, {})[r["env"]] = r["env_name"]
                break
        merged.append({**r, "method": label})
    if len({(r["env"], r["method"]) for r in merged}) < len(merged):
        return rows, ""
    note = " ".join(
        f"The models of {', '.join(names.values())} were trained at the {preset} preset"
        + (", the others' at the quick one." if len(names) < len({r["env"] for r in rows}) else ".")
        for preset, names in where.items()
    )
    return merged, note


def setting_columns(rows: list[dict]) -> tuple[list[dict], str]:
    """``rows`` with each method's run settings (re-planning, avoidance) taken out of its column name (``cdrb [every
    80, waypoints 10 ahead]`` -> ``cdrb``), so one method is one column where each row chose its own settings (a
    tuned selection), and a note naming each column's settings row by row. What sets a method apart stays in its
    name (a variant such as geodesic balls, a map-aware controller). Where two of one row's methods would then
    share a column, ``rows`` are kept as they are."""
    if not rows or any("column" not in r for r in rows):
        return rows, ""
    merged = [{**r, "method": _strip_settings(r)} for r in rows]
    if len({(r["env"], r["method"]) for r in merged}) < len(merged):
        return rows, ""
    if all(r["method"] == o["method"] for r, o in zip(merged, rows)):
        return rows, ""
    columns = method_order(dict.fromkeys(r["method"] for r in merged))
    parts = []
    for column in sorted(columns, key=lambda c: c.split(" ")[0] != "straight"):  # the floors first, as the table
        by_setting: dict[str, list[str]] = {}
        for r in merged:
            if r["method"] == column:
                by_setting.setdefault(r["settings"], []).append(r["env_name"])
        name = column.replace("straight", "straight line", 1) if column.split(" ")[0] == "straight" else column
        most, *rest = sorted(by_setting, key=lambda k: -len(by_setting[k]))
        others = "; ".join(f"{k} on {', '.join(by_setting[k])}" for k in rest)
        parts.append(f"{name}: {most}" + (f" ({others})" if rest else " on every row"))
    return merged, "Each column's settings (re-planning, avoidance), as its row chose them: " + ". ".join(parts) + "."


def _strip_settings(row: dict) -> str:
    """The row's column name without its run settings, its preset taken out as :func:`preset_columns` did."""
    column = row["column"]
    base = row["method"].split(" [")[0]  # the method and its preset as the row's name has it
    return base + column[len(column.split(" [")[0]) :]


def _summary_cell(r: dict) -> str:
    spread = f"{r['success_std']:.1f}" if r["seeds"] > 1 else "n/a"
    weighted = "n/a" if r["weighted_success_mean"] is None else f"{r['weighted_success_mean']:.1f}"
    return f"{r['success_mean']:.1f} ± {spread} ({weighted})"
