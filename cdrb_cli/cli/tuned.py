"""`cdrb eval MODEL --config experiments/tuned/FILE.toml`: the eval settings that `cdrb select` chose on the tuning
stream for the model's environment and method, applied to one eval without a grid. A selection file stores each
choice as the `cdrb eval` flags the grid ran it with; they are read here by the command itself, as on its own
command line."""

from __future__ import annotations

from pathlib import Path

from cdrb_cli.errors import BadInput
from cdrb_cli.settings import Setting, clip


def is_selection(path: Path | None) -> bool:
    """Whether ``path`` is a TOML settings file of `cdrb select` (``[[settings]]`` entries and a ``[meta]`` table)
    rather than a file of settings."""
    if path is None or path.suffix.lower() != ".toml":
        return False
    from cdrb_cli.orchestration.grid import read_toml

    raw = read_toml(path, "settings file")
    return isinstance(raw.get("settings"), list) and isinstance(raw.get("meta"), dict)


def selection_settings(path: Path, model) -> list[Setting]:
    """The eval settings ``path`` chose for ``model``'s environment and method (every entry that applies, in order),
    each named ``FILE: eval FLAG``; a file that chose nothing for them is a one-line error naming what it has."""
    import typer

    from cdrb_cli.cli.common import app
    from cdrb_cli.cli.evaluate import everyday_flags
    from cdrb_cli.cli.options import moved_settings
    from cdrb_cli.orchestration.grid import SettingsFile, read_toml
    from cdrb_cli.settings import parse_set

    sfile = SettingsFile.model_validate(read_toml(path, "settings file"))
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
    given = {k: ctx.params.get(k) for k in ("episodes", "seeds", "stream", "protocol", "replan")}
    moved = {flag: ctx.params.get(name) for flag, name in _moved_params(command).items()}
    items = [Setting(tuple(k.split(".")), v, s) for s, k, v in everyday_flags(given)]
    items += moved_settings(moved, warn=False) + parse_set(ctx.params.get("sets") or [])
    return [Setting(s.path, s.value, f"--config {path}: {s.source}") for s in items]


def _moved_params(command) -> dict[str, str]:
    """The hidden moved flags of ``command``: flag -> parameter name."""
    from cdrb_cli.cli.options import MOVED_FLAGS

    return {o: p.name for p in command.params for o in p.opts if o in MOVED_FLAGS}
