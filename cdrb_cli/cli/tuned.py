"""`cdrb eval|plan MODEL --config experiments/tuned/FILE.toml`: the eval settings that `cdrb select` chose on the
tuning stream for the model's environment and method, applied to one eval or one plan without a grid (a plan takes
those that are plan settings: the sampler, its steps, the weights, avoidance). A selection file stores each choice as
a table of settings or as the `cdrb eval` flags the grid ran it with; they are read here by the command itself, as
on its own command line."""

from __future__ import annotations

from pathlib import Path

from cdrb_cli.errors import BadInput
from cdrb_cli.settings import Setting, clip


def read_selection(path: Path | None):
    """The :class:`~cdrb_cli.orchestration.grid.SettingsFile` at ``path`` when it is a TOML settings file of
    `cdrb select` (``[[settings]]`` entries and a ``[meta]`` table), else None (a file of settings, or no file)."""
    if path is None or path.suffix.lower() != ".toml":
        return None
    from cdrb_cli.orchestration.grid import SettingsFile, read_toml

    raw = read_toml(path, "settings file")
    if not (isinstance(raw.get("settings"), list) and isinstance(raw.get("meta"), dict)):
        return None
    return SettingsFile.model_validate(raw)


def selection_settings(sfile, path: Path, model) -> list[Setting]:
    """The eval settings that the selection ``sfile`` (read from ``path``) chose for ``model``'s environment and
    method (every entry that applies, in order), each named ``--config FILE: FLAG``; a file that chose nothing for
    them is a one-line error naming what it has."""
    import typer

    from cdrb_cli.cli.common import app
    from cdrb_cli.cli.evaluate import EVERYDAY, everyday_flags
    from cdrb_cli.cli.options import EVAL_MOVED, moved_name, moved_settings
    from cdrb_cli.settings import parse_set

    env, method = model.manifest.env.id, model.manifest.config.method.name
    if not any(s.env == env and s.method == method for s in sfile.settings):
        chosen = ", ".join(f"{s.method} on {s.env}" for s in sfile.settings if s.env and s.method) or "nothing"
        raise BadInput(
            f"--config {path}: chooses nothing for {method} on {env} (it chooses for {clip(chosen, 200)})",
            hint="pass the selection file of the model's environment, or a file of settings",
        )
    flags = [f for s in sfile.settings if s.env in (None, env) and s.method in (None, method) for f in s.eval]
    command = typer.main.get_command(app).commands["eval"]
    try:
        ctx = command.make_context("eval", [str(model.path), *flags])
    except Exception as exc:  # click's own usage errors: the flags are not a valid `cdrb eval` line
        raise BadInput(f"--config {path}: eval flags {clip(' '.join(flags), 200)}: {exc}",
                       hint="re-run `cdrb select` to rewrite the file") from None  # fmt: skip
    items = [Setting(tuple(k.split(".")), v, s) for s, k, v in everyday_flags({k: ctx.params[k] for k in EVERYDAY})]
    items += moved_settings({flag: ctx.params[moved_name(flag)] for flag in EVAL_MOVED}, warn=False)
    items += parse_set(ctx.params.get("sets") or [])
    return [Setting(s.path, s.value, f"--config {path}: {s.source}") for s in items]


def plan_part(settings: list[Setting]) -> list[Setting]:
    """The settings of an eval that are settings of a plan (the rest, such as the controller, re-planning or the
    episodes, are an eval's alone)."""
    from cdrb_cli.configs import PlanConfig

    return [s for s in settings if s.path[0] in PlanConfig.model_fields or s.path == ("avoid",)]
