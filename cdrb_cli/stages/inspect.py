"""`cdrb inspect`: validate an artifact and describe it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.table import Table
from rich.text import Text

from cdrb_cli import ui
from cdrb_cli.artifacts import load


def describe(path: str | Path) -> dict[str, Any]:
    art = load(path)
    m = art.manifest
    summary = getattr(m, "summary", None) or getattr(m, "state", None)
    return {
        "path": str(path),
        "kind": art.kind,
        "schema_version": m.schema_version,
        "migrated_from": art.migrated_from,
        "valid": True,
        "sha256": art.sha256,
        "created_at": m.created_at,
        "cdrb_version": m.cdrb_version,
        "git_sha": m.git_sha,
        "seed": m.seed,
        "argv": m.argv,
        "env": m.env.id,
        "family": m.env.family,
        "parents": [p.model_dump() for p in m.parents],
        "summary": summary.model_dump() if summary is not None else None,
        "config": m.config.model_dump(),
        "source": _source(m),
        "datasets": {k: {"shape": list(v.shape), "dtype": str(v.dtype)} for k, v in sorted(art.arrays.items())},
        "graph": _graph(art),
    }


def _graph(art) -> dict | None:
    """A buffer's transition graph in numbers (nodes, edges, components, degrees); None for other kinds or a
    buffer without one."""
    if art.kind != "buffer" or "graph/edges" not in art.arrays:
        return None
    from cdrb_cli.geodesic import graph_summary

    return graph_summary(len(art.arrays["points"]), art.arrays["graph/edges"])


def _source(manifest) -> str | None:
    """One line on where demonstrations came from (their expert record), or None for other kinds."""
    expert = getattr(manifest.config, "expert", None)
    return expert.describe() if expert is not None else None


def safe(value: Any, limit: int = 200) -> Text:
    """Untrusted manifest text for the terminal: no rich markup, no control characters (ANSI escapes), bounded."""
    text = "".join(ch if ch.isprintable() else "?" for ch in str(value))
    if len(text) > limit:
        text = text[:limit] + f"... ({len(text) - limit} more characters)"
    return Text(text)


def render(info: dict[str, Any]) -> None:
    """Human-readable description on stdout. Every string from the file goes through :func:`safe`."""
    out = ui.stdout_console()
    out.print(
        Text.assemble(
            safe(info["path"]),
            ": valid cdrb ",
            (str(info["kind"]), "bold"),
            f" artifact, schema {info['schema_version']}",
            " (read through a migration to the current schema)" if info.get("migrated_from") else "",
        )
    )
    meta = Table.grid(padding=(0, 2))
    for key in ("env", "family", "created_at", "cdrb_version", "git_sha", "seed", "sha256"):
        meta.add_row(key, safe(info[key]))
    meta.add_row("command", safe(" ".join(map(str, info["argv"])), 400))
    if info.get("source"):
        meta.add_row("source", safe(info["source"], 400))
    out.print(meta)
    if info["parents"]:
        out.print(Text("parents", "bold"))
        for p in info["parents"]:
            out.print(Text("  ") + safe(f"{p['kind']:7s} {p['sha256'][:12]}  {p['path']}"))
    if info["summary"]:
        out.print(Text("summary", "bold"))
        for k, v in info["summary"].items():
            if isinstance(v, float):
                v = f"{v:.4g}"
            out.print(Text("  ") + safe(f"{k}: {v}", 120))
    if info.get("graph"):
        g = info["graph"]
        out.print(Text("transition graph", "bold"))
        out.print(
            Text(
                f"  {g['nodes']} nodes, {g['edges']} edges, {g['components']} component(s) (largest "
                f"{g['largest_component']}), {g['isolated_nodes']} isolated; degree mean {g['mean_degree']}, "
                f"max {g['max_degree']}"
            )
        )
    table = Table("dataset", "shape", "dtype", box=None, header_style="bold")
    shown = [(k, v) for k, v in info["datasets"].items() if not k.startswith(("weights/", "ema/", "optim/"))]
    for k, v in shown:
        table.add_row(safe("/" + k), "x".join(map(str, v["shape"])) or "scalar", v["dtype"])
    hidden = len(info["datasets"]) - len(shown)
    if hidden:
        table.add_row(f"(+{hidden} weight/optimizer tensors)", "", "")
    out.print(table)


def plot_training(path: str | Path, out: Path) -> Path:
    """A model's training curve: the training loss at every logged step and the validation loss at every
    checkpoint (log scale), titled with the method, its steps and its wall time."""
    import numpy as np

    from cdrb_cli.envs.render import pyplot, save_figure
    from cdrb_cli.errors import BadInput

    art = load(path)
    if art.kind != "model":
        raise BadInput(
            f"--plot: {path} is {'an' if art.kind[0] in 'aeiou' else 'a'} {art.kind} artifact; --plot draws a "
            "model's training curve",
            hint="pass a model (.h5 written by `cdrb train`), or drop --plot",
        )
    steps = np.asarray(art.arrays.get("curve/step", np.zeros(0)))
    loss = np.asarray(art.arrays.get("curve/loss", np.zeros(0)))
    if not len(steps):
        raise BadInput(f"--plot: {path} records no training curve (a method with nothing to learn)", hint="drop --plot")
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 4))
    ax.plot(steps, loss, "-", lw=1.2, label="training loss (mean since the last log)")
    if "curve/valid_step" in art.arrays:
        ax.plot(art.arrays["curve/valid_step"], art.arrays["curve/valid_loss"], "o-", ms=4, lw=1.0,
                label="validation loss (held-out episodes)")  # fmt: skip
    if (loss > 0).all():
        ax.set_yscale("log")
    ax.set_xlabel("gradient step")
    ax.set_ylabel("loss")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    m, state = art.manifest, art.manifest.state
    done = "finished" if state.finished else "unfinished checkpoint"
    ax.set_title(f"{m.config.method.name} on {m.env.id}: {state.step} steps, {state.wall_time_s / 60:.1f} min ({done})",
                 fontsize=9)  # fmt: skip
    return save_figure(fig, out)
