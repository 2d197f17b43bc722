"""`cdrb config`: every setting of a stage's config, with its type, default and description, read from the config
records themselves (the single declaration of an option), as a table or as a TOML/JSON template for ``--config``."""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel

from cdrb_cli.settings import Setting, toml_key, toml_value, type_name

#: shown for defaults `cdrb train` fills in from its inputs
FROM_DATA = "(from the data)"


@dataclass(frozen=True)
class Row:
    key: str
    type: str
    default: Any
    description: str
    #: the default is a note for the reader (what fills it in), not a value a template may write
    placeholder: bool = False


def _note(key: str, text: str, description: str) -> Row:
    return Row(key, "str", text, description, placeholder=True)


def _rows(model: type[BaseModel], values: dict, prefix: str = "", skip=(), placeholders=None) -> list[Row]:
    rows = []
    placeholders = placeholders or {}
    for name, f in model.model_fields.items():
        if name in skip:
            continue
        key = prefix + name
        if isinstance(f.annotation, type) and issubclass(f.annotation, BaseModel) and name not in values:
            rows += _rows(f.annotation, {}, f"{key}.", placeholders=placeholders)  # a nested record: its fields
            continue
        note = False
        if name in values:
            default = values[name]
        elif key in placeholders:
            default, note = placeholders[key], True
        elif f.is_required():
            default, note = FROM_DATA, True
        else:
            default = f.get_default(call_default_factory=True)
        rows.append(Row(key, type_name(f.annotation), default, f.description or "", placeholder=note))
    return rows


def _train_rows(method: str | None, net: str | None, preset: str | None) -> list[Row]:
    from cdrb_cli.configs import TrainConfig, net_classes
    from cdrb_cli.methods.config import choose
    from cdrb_cli.presets import NETS, TRAIN

    given = [
        Setting(path, value, f"{flag} {value}")
        for path, value, flag in ((("method", "name"), method, "--method"), (("net", "kind"), net, "--net"))
        if value is not None
    ] + ([Setting(("preset",), preset, f"--preset {preset}")] if preset else [])
    entry, preset, net = choose(given)
    net_cls = next(c for c in net_classes() if c.model_fields["kind"].default == net)
    own = dict(entry.train_defaults.get(preset, {}))
    net_defaults = {**NETS[preset][net], **{k: v for k, v in own.pop("net", {}).items() if k != "kind"}}
    top = {**TRAIN[preset], "preset": preset, **own}
    rows = [
        Row("method.name", "str", entry.name, "the method (`cdrb methods`); --method sets it"),
        *_rows(entry.params, dict(entry.presets.get(preset, {})), "method.", skip=("name",)),
        Row("net.kind", "str", net, "the network; --net sets it"),
        *_rows(net_cls, net_defaults, "net.", skip=("kind",)),
        *_rows(TrainConfig, top, skip=("method", "net"), placeholders={"seed": "(--seed)"}),
    ]
    return rows


def _eval_rows(controller: str | None, every_controller: bool = True) -> list[Row]:
    from cdrb_cli.configs import EvalConfig
    from cdrb_cli.envs.registry import CONTROLLERS
    from cdrb_cli.stages.configure import EVAL_DEFAULTS

    placeholders = {"seed": "(--seed)", "scene": "(--scene)"}
    rows = _rows(EvalConfig, EVAL_DEFAULTS, skip=("controller", "sampler", "protocol"), placeholders=placeholders)
    rows += [
        _note("sampler", "(the model's)", "a sampler of the model's method (`cdrb methods`)"),
        _note("protocol", "(the env's)", "the start/goal protocol (`cdrb envs` lists each family's)"),
        _note("replan", "(shortcut)", "shortcut for replan.mode and its value: never, every:N or deviation:D"),
        _note("avoid", "(shortcut)", _AVOID_HELP),
    ]
    if not controller and not every_controller:  # a template holds one controller's settings: the env's by default
        about = "the env's default controller; `--controller NAME` adds a controller's settings to the template"
        return [*rows, _note("controller.name", "(the env's)", about)]
    entries = [CONTROLLERS.get(controller, "--controller")] if controller else CONTROLLERS.entries()
    for entry in entries:
        about = entry.description or "the controller (the first is the default)"
        rows.append(Row("controller.name", "str", entry.name, about))
        rows += _rows(entry.config, {}, "controller.", skip=("name",))
    return rows


_AVOID_HELP = (
    "shortcut: plain (no avoidance) or tuned (the settings chosen for new obstacles, the default with --scene), "
    "applied before the avoid.<field> settings"
)


def _plan_rows() -> list[Row]:
    from cdrb_cli.configs import PlanConfig

    rows = _rows(PlanConfig, {"n": 1}, skip=("sampler",), placeholders={"seed": "(--seed)", "scene": "(--scene)"})
    rows += [
        _note("sampler", "(the model's)", "a sampler of the model's method (`cdrb methods`)"),
        _note("avoid", "(shortcut)", _AVOID_HELP),
    ]
    return rows


def _collect_rows() -> list[Row]:
    """`cdrb collect --set expert.<field>`: every expert's fields (--expert picks the expert)."""
    from cdrb_cli.envs.registry import EXPERTS

    rows = []
    for entry in EXPERTS.entries():
        rows.append(Row("expert.kind", "str", entry.name, entry.description or "the expert; --expert"))
        rows += _rows(entry.config, {}, "expert.", skip=("kind",))
    return rows


def config_template(
    stage: str,
    method: str | None = None,
    net: str | None = None,
    preset: str | None = None,
    controller=None,
    every_controller: bool = True,
) -> list[Row]:
    """The settings of ``stage`` (train, plan, eval or collect) with their defaults for these choices; eval lists
    every controller's settings unless ``every_controller`` is false (a --config template: one controller)."""
    if stage == "collect":
        return _collect_rows()
    if stage == "plan":
        return _plan_rows()
    return _train_rows(method, net, preset) if stage == "train" else _eval_rows(controller, every_controller)


def settable_keys() -> list[str]:
    """Every key `cdrb train --set` accepts, for any method and network."""
    from cdrb_cli.configs import TrainConfig, net_classes
    from cdrb_cli.methods.registry import METHODS

    keys = [k for k in TrainConfig.model_fields if k not in ("method", "net")]
    keys += [f"method.{k}" for e in METHODS.entries() for k in e.params.model_fields]
    keys += [f"net.{k}" for c in net_classes() for k in c.model_fields]
    return list(dict.fromkeys(keys))


def _nested(rows: list[Row]) -> dict:
    """The settings with known defaults as nested objects (defaults that depend on the data are left out)."""
    out: dict = {}
    for r in rows:
        if r.placeholder:
            continue
        node = out
        *parents, leaf = r.key.split(".")
        for p in parents:
            node = node.setdefault(p, {})
        node[leaf] = r.default
    return out


#: the head of a plan/eval template, whose keys are all commented out
CHOSEN_ELSEWHERE = (
    "# every key is commented out: a plan or eval takes its defaults from the model's settings profile, its env's\n"
    "# choices (re-planning, plans from anywhere) and --scene before these static ones; uncomment a key to fix it"
)


def _toml(rows: list[Row], all_commented: bool = False) -> str:
    """A TOML template: top-level keys first, then one table per section; defaults that depend on the data, and
    null defaults (TOML has no null), are commented out, and every key with ``all_commented``."""
    lines = ["# cdrb settings (read with --config FILE); `cdrb config --format table` describes each key"]
    lines += [CHOSEN_ELSEWHERE, ""] if all_commented else [""]
    sections: dict[tuple[str, ...], list[Row]] = {}  # by the key's parent path: a record nested in a record too
    for r in rows:
        sections.setdefault(tuple(r.key.split(".")[:-1]), []).append(r)
    tops = list(dict.fromkeys(s[0] for s in sections if s))  # a record's table before the records nested in it
    for section in [(), *sorted((s for s in sections if s), key=lambda s: (tops.index(s[0]), len(s)))]:
        if section:
            lines += ["", f"[{'.'.join(toml_key(p) for p in section)}]"]
        for r in sections.get(section, []):
            leaf = toml_key(r.key.split(".")[-1])
            flag = r.default[1:-1] if r.placeholder and str(r.default).startswith("(--") else None
            if flag is not None:  # a field a flag sets (the seed, the scene): no key this file may hold
                text = f"# ({leaf}: give {flag}, not a key here)"
            elif _holds_null(r.default) or r.placeholder:
                text = f"# {leaf} = ...  {_one_line(_plain(r.default))}"
            else:
                text = f"{'# ' if all_commented else ''}{leaf} = {toml_value(r.default)}"
            about = _one_line(r.description)
            lines.append(f"{text:<40} # {about}" if about else text)
    return "\n".join(lines) + "\n"


def _one_line(text: str) -> str:
    """Text for a TOML comment: one line, no control characters."""
    return " ".join("".join(c if c.isprintable() else " " for c in text).split())


def _holds_null(v: Any) -> bool:
    """Whether a default is or contains None, which TOML cannot write."""
    if isinstance(v, dict):
        return any(_holds_null(x) for x in v.values())
    if isinstance(v, (list, tuple)):
        return any(_holds_null(x) for x in v)
    return v is None


def render_template(rows: list[Row], fmt: str, all_commented: bool = False) -> str:
    """The rows as a table, or as a JSON or TOML template for ``--config`` (TOML: every key commented out with
    ``all_commented``, for stages whose defaults come from elsewhere first)."""
    if fmt == "json":
        return json.dumps(_nested(rows), indent=2) + "\n"
    if fmt == "toml":
        return _toml(rows, all_commented)
    from rich.console import Console
    from rich.table import Table
    from rich.text import Text

    table = Table("key", "type", "default", "description", header_style="bold", box=None)
    for r in rows:
        table.add_row(Text(r.key), Text(r.type), Text(_plain(r.default)), Text(r.description))
    console = Console(record=True, width=160, force_terminal=False)
    with console.capture() as cap:
        console.print(table)
    return cap.get()


def _plain(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, bool):
        return str(v).lower()
    return "null" if v is None else str(v)
