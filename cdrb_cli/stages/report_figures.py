"""The pictures of a report: success and planned states in obstacles as bars per method and environment, and the
plans of every method for the same start/goal pairs side by side."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cdrb_cli.errors import BadInput
from cdrb_cli.stages.report import method_label, method_order, method_rank
from cdrb_cli.stages.report_summary import preset_columns


def plot_bars(rows: list[dict], path) -> Path:
    from cdrb_cli.envs.render import label, pyplot, save_figure

    plt = pyplot()
    rows, _ = preset_columns(rows)  # one bar colour per method across rows trained at different presets
    envs = list(dict.fromkeys(r["env"] for r in rows))
    methods = method_order(dict.fromkeys(r["method"] for r in rows))
    cell = {(r["env"], r["method"]): r for r in rows}
    name = {r["env"]: r["env_name"] for r in rows}
    many = len(envs) > 3  # long row names side by side: slant them and widen the figure
    fig, axes = plt.subplots(1, 2, figsize=(max(11.0, 2.2 * len(envs)), 4.6 if many else 4))
    width = 0.8 / max(len(methods), 1)
    x = np.arange(len(envs))
    for i, m in enumerate(methods):
        for ax, key, std in ((axes[0], "success_mean", "success_std"), (axes[1], "in_wall_mean", "in_wall_std")):
            vals = np.array([_num(cell[(e, m)][key]) if (e, m) in cell else np.nan for e in envs])
            errs = np.array([_num(cell[(e, m)][std], 0.0) if (e, m) in cell else 0 for e in envs])
            # a rate lies in [0, 100]: the bar's std whisker stops there instead of reaching below zero
            whisker = [np.minimum(errs, np.nan_to_num(vals)), np.minimum(errs, 100 - np.nan_to_num(vals))]
            ax.bar(x + (i - (len(methods) - 1) / 2) * width, vals, width, yerr=whisker, capsize=3, label=label(m))
    panels = ((axes[0], "success rate", "success (%)"), (axes[1], "planned states inside obstacles", "states (%)"))
    for ax, title, ylabel in panels:
        ax.set_xticks(x)
        ax.set_xticklabels([label(name[e]) for e in envs], rotation=25 if many else 0, ha="right" if many else "center")
        ax.set_title(title, fontsize=10)
        ax.set_ylabel(ylabel)
        ax.set_ylim(bottom=0)
        ax.grid(axis="y", alpha=0.3)
    if many:  # a legend row above the bars, which reach 100 in every group
        axes[0].set_ylim(0, 118)
        axes[0].set_yticks(range(0, 101, 20))
        axes[0].legend(fontsize=8, ncol=len(methods), loc="upper center")
    else:
        axes[0].set_ylim(0, 105)
        axes[0].legend(fontsize=8)
    seeds = sorted({int(r.get("seeds", 0) or 0) for r in rows})
    fig.text(
        0.5,
        0.0,
        f"mean over evaluation seeds ({', '.join(map(str, seeds))} per bar); whiskers: sample std, cut at 0 and 100",
        ha="center",
        va="top",
        fontsize=8,
    )
    return save_figure(fig, path)


def _num(v, missing=np.nan) -> float:
    return missing if v is None else v


def with_plans(evals) -> list:
    """The evals that :func:`plot_side_by_side` draws (those holding plans, of one environment), or why not."""
    evals = [ev for ev in evals if "plans" in ev.arrays]
    if not evals:
        raise BadInput(
            "--plans-plot: none of the eval files holds plans",
            hint="pass the evals a compact copy was made from (`cdrb export --compact` drops the plans), or run "
            "`cdrb eval` again without --no-plans",
        )
    envs = list(dict.fromkeys(ev.manifest.env.id for ev in evals))
    if len(envs) > 1:
        raise BadInput("--plans-plot needs evals of a single environment", hint=f"got {', '.join(envs)}")
    return evals


def plot_side_by_side(evals, path, n: int = 12) -> Path:
    """The plans of every method for the same start/goal pairs (the first ``n`` episodes of the first seed)."""
    from cdrb_cli.envs.registry import family_of
    from cdrb_cli.envs.render import draw_ends, draw_plans, draw_scene, plan_legend, pyplot, save_figure, set_title

    evals = sorted(with_plans(evals), key=lambda ev: method_rank(method_label(ev)))
    plt = pyplot()
    fig, axes = plt.subplots(1, len(evals), figsize=(4.6 * len(evals), 4.8), squeeze=False)
    for ax, ev in zip(axes[0], evals):
        spec = ev.manifest.env
        plans = ev.arrays["plans"][:n]
        draw_scene(ax, spec)
        draw_plans(ax, spec, plans, family_of(spec).in_collision(spec, plans[..., : spec.obs_dim]), markers=False)
        draw_ends(ax, spec, plans[:, 0, : spec.obs_dim], plans[:, -1, : spec.obs_dim])
        s = ev.manifest.summary  # the eval's own figures, to the report table's precision
        set_title(
            ax,
            f"{method_label(ev)}: success {100 * s.success_mean:.1f}%, "
            f"planned states in walls {100 * s.in_wall_mean:.2f}% (eval); {len(plans)} of its plans",
            8,
        )
    plan_legend(fig, loc="upper center", ncol=4, bbox_to_anchor=(0.5, 0.02))
    return save_figure(fig, path)
