"""Settings: how a user sets any field of a typed config from the command line, without a flag per field.

* ``--set KEY=VALUE`` (repeatable): ``KEY`` is a dotted path into the config (``steps``, ``net.dim``,
  ``method.schedule``; dashes may stand for underscores); ``VALUE`` is read as JSON when it parses
  (``2e-4``, ``true``, ``null``, ``[1,4,8]``), as a list when it holds commas (``1,4,8``), else as text.
* ``--config FILE``: a TOML or JSON file of the same keys, nested (``[net]`` / ``dim = 32``) or dotted.

Every value keeps its *source* (``--set net.dim=7``, ``--config run.toml``, ``--steps``) so a value the config
rejects is reported against what the user typed. The config's own fields and descriptions are the only
declaration (``cdrb config`` lists them).
"""

from __future__ import annotations

import json
import re
import types
import typing
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, NoReturn

from pydantic import BaseModel, ValidationError

from cdrb_cli.errors import BadInput

Path_ = tuple[str, ...]

#: a --config file larger than this is refused (a settings file is a few lines)
MAX_CONFIG_BYTES = 1 << 20
#: the deepest setting name (``method.sampler.steps`` is 3): deeper is a mistake, and unbounded depth recurses
MAX_KEY_PARTS = 8
#: how much of a user's text an error line echoes
ECHO_CHARS = 120


#: how the Python API's ``settings`` dict names its settings in errors (``settings KEY=VALUE``), so a message can
#: name the caller's keyword arguments where the CLI names its flags
API_SOURCE = "settings"


def from_api(source: str) -> bool:
    """Whether a setting's ``source`` is the Python API's ``settings`` dict (else a ``--set`` or a config file)."""
    return source.startswith(API_SOURCE + " ")


def clip(text: str, n: int = ECHO_CHARS) -> str:
    """``text`` cut to ``n`` characters for an error line (a 5 KB key is named, not echoed)."""
    text = str(text)
    return text if len(text) <= n else f"{text[: n - 3]}..."


@dataclass(frozen=True)
class Setting:
    """One value for one config field, and how the user gave it."""

    path: Path_
    value: Any
    source: str
    #: from a settings file: checked even where a later setting overrides it (a file is reused as it is)
    from_file: bool = False

    @property
    def key(self) -> str:
        return ".".join(self.path)


def setting_key(text: str, source: str) -> Path_:
    """A dotted setting name as its parts, dashes read as underscores (``avoid.best-of`` is ``avoid.best_of``);
    a name that is not one is refused naming ``source``."""
    parts = tuple(p.strip().replace("-", "_") for p in text.split(".", MAX_KEY_PARTS))
    if len(parts) > MAX_KEY_PARTS:
        raise BadInput(
            f"{clip(source)}: a setting name has at most {MAX_KEY_PARTS} dotted parts",
            hint="`cdrb config COMMAND` lists the settings",
        )
    if not text.strip() or any(not p.isidentifier() for p in parts):
        raise BadInput(
            f"{clip(source)}: {clip(repr(text), 60)} is not a setting name",
            hint='use a dotted key, e.g. {"avoid.best_of": 4}'
            if from_api(source)
            else "write KEY=VALUE, e.g. --set net.dim=32",
        )
    return parts


class DuplicateKey(ValueError):
    """A JSON object gives one key twice."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict:
    """A JSON object's pairs -> a dict, refusing a key given twice (JSON's last-one-wins hides a mistake)."""
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise DuplicateKey(f"key {key[:80]!r} is given twice")
        out[key] = value
    return out


def loads_json(text: str) -> Any:
    """``json.loads`` that refuses duplicate keys (a ValueError naming the key)."""
    return json.loads(text, object_pairs_hook=_unique_keys)


#: a decimal number with a dot or an exponent, in the forms JSON refuses (no digit before or after the dot)
_DECIMAL = re.compile(r"[+-]?(\d+\.\d*|\.\d+)([eE][+-]?\d+)?")


def parse_value(text: str) -> Any:
    """``--set`` value text -> a Python value (JSON first, then a comma list, then the text itself)."""
    try:
        return loads_json(text)
    except DuplicateKey as exc:
        raise BadInput(f"--set value {clip(repr(text))}: {exc}", hint="give each key once") from None
    except ValueError:
        pass
    if _DECIMAL.fullmatch(text.strip()):  # what JSON refuses but a person writes: .001, 1., -.5e-3
        return float(text)
    if "," in text:
        return [parse_value(t.strip()) for t in text.split(",") if t.strip()]
    return text


def parse_set(items: Iterable[str], flag: str = "--set") -> list[Setting]:
    out = []
    for item in items:
        if "=" not in item:
            raise BadInput(f"{flag} {clip(repr(item))}: expected KEY=VALUE", hint=f"e.g. {flag} net.dim=32")
        key, text = item.split("=", 1)
        source = f"{flag} {clip(item)}"
        out.append(Setting(setting_key(key, source), parse_value(text.strip()), source))
    return out


def comma_items(text: str) -> list[str]:
    """The items of a comma-separated list as written on a command line, each stripped, one trailing comma dropped
    (as a list is often written): ``"0, 1,"`` is ``["0", "1"]``. An empty item elsewhere stays ``""`` for the caller
    to refuse (``"0,,1"``, ``",0"``); an empty text is ``[""]``."""
    items = [v.strip() for v in text.split(",")]
    if len(items) > 1 and not items[-1]:
        items.pop()
    return items


def from_mapping(values: dict[str, Any], source: str = API_SOURCE) -> list[Setting]:
    """Settings from a dict of dotted keys (``{"steps": 40, "net.dim": 8}``), for the Python API; numpy numbers
    and arrays are taken as the Python numbers and lists they hold."""
    out = []
    for k, v in values.items():
        v = plain(v)  # named by its repr: the string "2" is not the number 2, and an error says which it was given
        out.append(Setting(setting_key(str(k), f"{source} {k}"), v, f"{source} {k}={clip(repr(v), 60)}"))
    return out


def _odd_type(value: Any) -> str:
    """The name of the type in ``value`` that JSON has no form for: the value's own, or that of the first such item
    of a list (a list of tensors is refused for its tensors, not for being a list)."""
    if isinstance(value, list):
        for item in value:
            try:
                json.dumps(item)
            except (TypeError, ValueError, RecursionError):
                return _odd_type(item)
    return type(value).__name__


def plain(value: Any) -> Any:
    """``value`` with numpy scalars as Python numbers and numpy arrays, torch tensors, tuples and lists as lists of
    them (what a setting read from JSON or TOML would hold); anything else unchanged, for the settings' own
    checks."""
    kind = type(value).__module__
    if kind == "numpy" and hasattr(value, "item") and getattr(value, "ndim", None) == 0:
        return value.item()
    if kind == "numpy" and hasattr(value, "tolist"):
        return value.tolist()
    if kind.split(".")[0] == "torch" and hasattr(value, "tolist") and hasattr(value, "detach"):  # a tensor
        try:
            return value.detach().cpu().tolist()
        except (RuntimeError, NotImplementedError):  # a tensor with no values to read (the meta device)
            return value
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    return value


#: the key under which a TOML table lists its settings that are null (TOML has no null): ``null = ["max_lag"]``
NULL_KEY = "null"


def _flatten(data: dict, prefix: Path_, source: str) -> list[Setting]:
    out = []
    for k, v in data.items():
        if k == NULL_KEY and isinstance(v, list) and all(isinstance(x, str) for x in v):
            for x in v:
                out.append(Setting(prefix + setting_key(x, source), None, f"{source}: {'.'.join(prefix + (x,))}=null"))
            continue
        path = prefix + setting_key(str(k), source)
        if len(path) > MAX_KEY_PARTS:
            raise BadInput(
                f"{clip(source)}: {clip('.'.join(path), 60)}: a setting name has at most {MAX_KEY_PARTS} parts",
                hint="`cdrb config COMMAND` lists the settings",
            )
        if isinstance(v, dict):
            out += _flatten(v, path, source)
        else:
            out.append(Setting(path, v, f"{source}: {'.'.join(path)}"))
    return out


def read_config_file(path: str | Path, flag: str = "--config") -> list[Setting]:
    """Settings from a TOML (``.toml``) or JSON file."""
    from cdrb_cli.files import parse_toml, read_input_text

    path = Path(path)
    source = f"{flag} {path}"
    text = read_input_text(path, flag, MAX_CONFIG_BYTES, "settings file", "pass a TOML or JSON file")
    hint = "fix the file; `cdrb config` prints a template"
    if path.suffix.lower() != ".json":
        data = parse_toml(text, source, hint=hint)
    else:
        try:
            data = loads_json(text)
        except (ValueError, RecursionError) as exc:
            first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise BadInput(f"{source}: not valid JSON ({first})", hint=hint) from None
    if not isinstance(data, dict):
        raise BadInput(f"{source}: expected a table of settings", hint="write KEY = VALUE lines")
    settings = _flatten(data, (), source)
    seen: set[Path_] = set()
    for s in settings:  # {"net": {"dim": 8}, "net.dim": 16}: two spellings of one key, one of them silently lost
        if s.path in seen:
            raise BadInput(f"{source}: {clip(s.key, 60)} is given twice", hint="give each setting once")
        seen.add(s.path)
    return [replace(s, from_file=True) for s in settings]


def lookup(settings: Sequence[Setting], path: Path_) -> Setting | None:
    """The last setting for ``path`` (later settings override earlier ones)."""
    found = None
    for s in settings:
        if s.path == path:
            found = s
    return found


def given_once(first: Sequence[Setting], then: Sequence[Setting], sep: str = " with ") -> None:
    """Refuse a field that both ``first`` (a flag, a keyword argument) and ``then`` (``--set``, a settings dict) set:
    which would win is not what either says."""
    for s in then:
        clash = lookup(first, s.path)
        if clash is not None:
            raise BadInput(f"{clash.source}{sep}{s.source}", hint="give it once")


def apply(base: dict, settings: Iterable[Setting]) -> dict:
    """A deep copy of ``base`` with every setting written in (later ones win)."""
    out = json.loads(json.dumps(base))
    for s in settings:
        node = out
        for part in s.path[:-1]:
            if not isinstance(node.get(part), dict):
                node[part] = {}
            node = node[part]
        node[s.path[-1]] = s.value
    return out


def source_of(settings: Sequence[Setting], loc: Sequence[Any]) -> Setting | None:
    """The setting that wrote the field at ``loc`` (or a field inside it)."""
    loc = tuple(str(x) for x in loc)
    best = None
    for s in settings:
        n = min(len(s.path), len(loc))
        if s.path[:n] == loc[:n]:
            best = s
    return best


def validate(model: type[BaseModel], data: dict, settings: Sequence[Setting], what: str) -> BaseModel:
    """``model`` validated strictly from ``data`` as JSON (no coercion: ``true`` is not the number 1, ``1`` or
    ``"yes"`` not a boolean, ``3.5`` not an integer), with the first error reported against the setting that caused
    it."""
    try:
        text = json.dumps(data)
    except (TypeError, ValueError, RecursionError) as exc:
        hint = "values are numbers, booleans, strings or lists of them"
        for s in settings:  # name the setting whose value is no JSON value (a TOML date, a Python set or Path)
            try:
                json.dumps(s.value)
            except (TypeError, ValueError, RecursionError):
                shown = _odd_type(s.value)
                article = "an" if shown[:1].lower() in "aeiou" else "a"
                raise BadInput(f"{clip(s.source)}: {article} {shown} is not a setting value", hint=hint) from None
        raise BadInput(f"{what} settings: {exc}", hint=hint) from None
    try:
        config = model.model_validate_json(text, strict=True, context={"strict": True})
    except ValidationError as exc:
        _refuse(model, exc, settings, what)
    _check_overridden(model, data, settings, what)
    return config


def _check_overridden(model: type[BaseModel], data: dict, settings: Sequence[Setting], what: str) -> None:
    """A settings file's value that a later setting (a flag, ``--set``) overrides is still checked: the file is
    reused as it is, elsewhere without the override. Its own value is written over the one that won and the
    record validated again; only an error at that very field is its own (others belong to the whole)."""
    for s in settings:
        later = lookup(settings, s.path)
        if not s.from_file or later is s or not _holds(data, s.path, later.value):
            continue
        try:
            model.model_validate_json(json.dumps(apply(data, [s])), strict=True, context={"strict": True})
        except (ValidationError, TypeError, ValueError, RecursionError) as exc:
            errors = exc.errors() if isinstance(exc, ValidationError) else []
            mine = [e for e in errors if tuple(map(str, _field_loc(model, e.get("loc", ())))) == s.path]
            if mine or not isinstance(exc, ValidationError):
                msg = _message(mine[0], s.path) if mine else "not a setting value"
                raise BadInput(
                    f"{clip(s.source)}: {msg}",
                    hint=f"fix the file ({clip(later.source, 60)} overrides it here, not where the file is reused)",
                ) from None


def _holds(data: dict, path: Path_, value: Any) -> bool:
    """Whether ``data`` holds ``value`` at ``path`` (the setting that won was written there as it is)."""
    node: Any = data
    for part in path:
        if not isinstance(node, dict) or part not in node:
            return False
        node = node[part]
    return node == value and type(node) is type(value)


def _refuse(model: type[BaseModel], exc: ValidationError, settings: Sequence[Setting], what: str) -> NoReturn:
    """The first error of a validation, as one line against the setting that caused it."""
    err = exc.errors()[0]
    loc = _field_loc(model, err.get("loc", ()))  # tagged unions add the tag (("net", "unet", "dim")): dropped
    msg = _message(err, loc)
    setting = source_of(settings, loc)
    where = clip(setting.source if setting is not None else f"{what} {'.'.join(str(p) for p in loc)}")
    if err.get("type") == "value_error":  # a check across several fields of a record: name those it names
        inside = [s for s in settings if tuple(s.path[: len(loc)]) == tuple(map(str, loc))]
        named = [s for s in inside if _names(msg, s.path[len(loc) :])]
        given = list(dict.fromkeys(s.source for s in named or (inside if len(loc) else [])))
        if given:  # (one alone too: with an empty location the last setting applied is no clue)
            where = clip(" with ".join(given), 200)
        elif not given and setting is None and not loc:
            where = f"{what} settings"
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    raise BadInput(f"{where}: {msg}{more}", hint=f"`cdrb config {what}` lists every setting") from None


def _message(err: dict, loc: Sequence[Any]) -> str:
    """A validation error's message in the words of settings."""
    msg = err.get("msg", "invalid").replace("valid array", "valid list")  # JSON says array; settings say list
    if err.get("type") == "extra_forbidden":
        return f"unknown setting {clip(repr('.'.join(str(p) for p in loc)), 60)}"
    if err.get("type") == "list_type":
        msg += " (a list: write 1,4,8, or [512] for a single value)"
    return msg


def _names(message: str, path: Sequence[str]) -> bool:
    """Whether an error ``message`` names the setting at ``path`` (below the record it checks), by its dotted
    name or its last part as a word."""
    keys = {".".join(path), path[-1]} if path else set()
    return any(re.search(rf"(?<![\w.]){re.escape(k)}(?![\w])", message) for k in keys)


def _field_loc(model: type[BaseModel], loc: Sequence[Any]) -> list[Any]:
    out: list[Any] = []
    current: Any = model
    for part in loc:
        members = _union_members(current)
        if members and any(_tag(m) == part for m in members):
            current = next(m for m in members if _tag(m) == part)
            continue
        out.append(part)
        fields = getattr(current, "model_fields", {}) if isinstance(current, type) else {}
        current = fields[part].annotation if part in fields else None
    return out


def _union_members(tp: Any) -> list[type]:
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return _union_members(typing.get_args(tp)[0])
    if origin in (typing.Union, types.UnionType):
        return [a for a in typing.get_args(tp) if isinstance(a, type) and issubclass(a, BaseModel)]
    return []


def _tag(model: type[BaseModel]) -> str | None:
    for name in ("kind", "name"):
        f = model.model_fields.get(name)
        if f is not None and typing.get_origin(f.annotation) is typing.Literal:
            return typing.get_args(f.annotation)[0]
    return None


# ------------------------------------------------------------------------------------------------ listing
def type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return type_name(typing.get_args(tp)[0])
    if origin is typing.Literal:
        return " | ".join(str(a) for a in typing.get_args(tp))
    if origin in (typing.Union, types.UnionType):
        return " | ".join(type_name(a) for a in typing.get_args(tp))
    if origin is list:
        (inner,) = typing.get_args(tp) or (Any,)
        return f"list[{type_name(inner)}]"
    if tp is type(None):
        return "null"
    return getattr(tp, "__name__", str(tp))


_TOML_ESCAPES = {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def toml_string(text: str) -> str:
    """``text`` as a TOML basic string: quote, backslash and control characters escaped, everything else (any
    Unicode scalar value, emoji included) written as it is. A lone surrogate (a file name that was not valid UTF-8)
    has no TOML form: refused."""
    out = []
    for ch in text:
        code = ord(ch)
        if ch in _TOML_ESCAPES:
            out.append(_TOML_ESCAPES[ch])
        elif code < 0x20 or code == 0x7F:
            out.append(f"\\u{code:04x}")
        elif 0xD800 <= code <= 0xDFFF:
            raise BadInput(f"{text!r}: not valid Unicode, so a settings file cannot hold it", hint="rename it")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def toml_value(value: Any) -> str:
    """A settings value as TOML: a bool, a number, text, a list, or a table (inline, keys in its order). None has
    no TOML form: a file names its null settings in a ``null`` list (:data:`NULL_KEY`)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + " }" if value else "{}"
    if value is None:
        raise ValueError("TOML has no null: list the key under `null`")
    return toml_string(str(value))


def toml_key(key: str) -> str:
    """A key as TOML writes it: bare where it can be, else quoted."""
    return key if key and all(c.isascii() and (c.isalnum() or c in "_-") for c in key) else toml_string(key)
