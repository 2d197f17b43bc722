"""`cdrb eval|plan MODEL --config experiments/tuned/FILE.toml`: the eval settings that `cdrb select` chose on the
tuning stream for the model's environment and method, applied to one eval or one plan without a grid (a plan takes
those that are plan settings: the sampler, its steps, the weights, avoidance). `cdrb train DEMOS --config FILE`
trains what it chose and records the choice in the model, whose plans and evals then start from its eval settings.
A selection file stores each choice as a table of settings or as the flags the grid ran it with; they are read here
by the command itself, as on its own command line."""

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
    from cdrb_cli.orchestration.grid.spec import validated

    raw = read_toml(path, "settings file", "--config")
    if not (isinstance(raw.get("settings"), list) and isinstance(raw.get("meta"), dict)):
        return None
    return validated(SettingsFile, raw, path)


def _entries(sfile, path: Path, env: str, method: str, what: str = "the model's") -> list:
    """The entries of the selection ``sfile`` that apply to ``method`` on ``env`` (in order); a file that chose
    nothing for them is a one-line error naming what it has."""
    if not any(s.env == env and s.method == method for s in sfile.settings):
        chosen = ", ".join(f"{s.method} on {s.env}" for s in sfile.settings if s.env and s.method) or "nothing"
        raise BadInput(
            f"--config {path}: chooses nothing for {method} on {env} (it chooses for {clip(chosen, 200)})",
            hint=f"pass the selection file of {what} environment, or a file of settings",
        )
    return [s for s in sfile.settings if s.env in (None, env) and s.method in (None, method)]


def _context(command: str, argv: list[str], path: Path, flags: list[str]):
    """``cdrb command argv`` parsed as the command itself parses it (click's context). A file's flags may not ask
    for help (which would print it and stop) or name another settings file (whose settings would be dropped)."""
    import typer

    from cdrb_cli.cli.common import app

    where = f"--config {path}: {command} flags {clip(' '.join(flags), 200)}"
    cmd = typer.main.get_command(app).commands[command]
    if any(f in ("--help", "-h") for f in flags):
        raise BadInput(f"{where}: ask for help", hint=f"drop it; `cdrb {command} --help` prints it")
    try:
        ctx = cmd.make_context(command, argv)
    except Exception as exc:  # click's own usage errors: the flags are not a valid command line
        raise BadInput(f"{where}: {exc}", hint="re-run `cdrb select` to rewrite the file") from None
    if ctx.params.get("config_file") is not None:
        raise BadInput(f"{where}: name another settings file with --config",
                       hint="a selection holds its settings itself: write them into its entry")  # fmt: skip
    return ctx


def _eval_settings(entries: list, path: Path) -> tuple[list[Setting], dict]:
    """The eval settings of ``entries`` (each named ``--config FILE: FLAG``) and the other options they give."""
    from cdrb_cli.cli.options import EVAL_MOVED, EVERYDAY, everyday_flags, moved_name, moved_settings
    from cdrb_cli.settings import parse_set

    flags = [f for s in entries for f in s.eval]
    ctx = _context("eval", ["model.h5", *flags], path, flags)
    items = [Setting(tuple(k.split(".")), v, s) for s, k, v in everyday_flags({k: ctx.params[k] for k in EVERYDAY})]
    items += moved_settings({flag: ctx.params[moved_name(flag)] for flag in EVAL_MOVED}, warn=False)
    items += parse_set(ctx.params.get("sets") or [])
    return [Setting(s.path, s.value, f"--config {path}: {s.source}") for s in items], ctx.params


def selection_settings(sfile, path: Path, model) -> list[Setting]:
    """The eval settings that the selection ``sfile`` (read from ``path``) chose for ``model``'s environment and
    method (every entry that applies, in order), each named ``--config FILE: FLAG``."""
    env, method = model.manifest.env.id, model.manifest.config.method.name
    return _eval_settings(_entries(sfile, path, env, method), path)[0]


def selection_train(sfile, path: Path, env: str, method: str | None):
    """What `cdrb train --config SELECTION` trains: the train settings the selection chose for ``method`` (None:
    the default method) on ``env`` (each named ``--config FILE: FLAG``), and the
    :class:`~cdrb_cli.configs.SettingsProfile` the model records: the eval settings chosen with it, less those of
    one run (episodes, seeds, stream, protocol, the re-planning trigger), and none where the choice was made in a
    scene of its own."""
    from cdrb_cli.artifacts import sha256_file
    from cdrb_cli.configs import SettingsProfile
    from cdrb_cli.methods.config import DEFAULT_METHOD, user_settings

    entries = _entries(sfile, path, env, method or DEFAULT_METHOD, "the demos'")
    flags = [f for s in entries for f in s.train]
    ctx = _context("train", ["demos.h5", *flags], path, flags)
    p = ctx.params
    items = user_settings(p["method"], p["net"], p["preset"], p["steps"], None, p.get("sets") or [])
    train = [Setting(s.path, s.value, f"--config {path}: {s.source}") for s in items]
    evaluate, options = _eval_settings(entries, path)
    own_scene = options.get("maze_map") is not None
    kept = {} if own_scene else {s.key: s.value for s in evaluate if not _of_one_run(s)}
    chosen = next((s.chosen for s in reversed(entries) if s.chosen), None)
    return train, SettingsProfile(file=path.name, sha256=sha256_file(path), chosen=chosen, eval=kept)


#: eval settings that say which run (how many episodes, on which pairs, whether closed loop), not how the model is
#: used: a profile leaves them to each command
RUN_KEYS = ("episodes", "seeds", "stream", "protocol", "scene", "seed")
REPLAN_TRIGGER = (("replan",), ("replan", "mode"), ("replan", "every"), ("replan", "deviation"))


def _of_one_run(s: Setting) -> bool:
    return s.path[0] in RUN_KEYS or s.path in REPLAN_TRIGGER


def plan_part(settings: list[Setting]) -> list[Setting]:
    """The settings of an eval that are settings of a plan (the rest, such as the controller, re-planning or the
    episodes, are an eval's alone)."""
    from cdrb_cli.stages.configure import plan_keys

    keys = plan_keys()
    return [s for s in settings if s.path[0] in keys]
