"""Registries: name -> entry, for the things cdrb lets you add without editing it (environment families, methods,
experts, controllers).

A :class:`Registry` knows its built-in entries by name and the module that declares each (``{"cdrb":
"cdrb_cli.methods.cdrb"}``: one line per entry) and imports a module only when its name is first looked up; the
module registers its entry when imported. So listing the built-in names imports no built-in module, and looking
one up costs only that module's declarations. Other code adds entries with :meth:`Registry.register` (or
:meth:`Registry.added` for the length of a ``with`` block), or ships them as plugins: modules named by the
``cdrb.plugins`` entry-point group or by the ``CDRB_PLUGINS`` environment variable (comma-separated module names)
are imported before the first lookup of a name that is not built in.

:class:`Dispatch` makes a pydantic field whose record type is chosen by a registry from a key inside the value
(``{"name": "cdrb", ...}`` is validated as the params record that the ``cdrb`` method registered), so configs stay
fully typed while the set of types stays open.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any, Generic, TypeVar

from cdrb_cli.errors import BadInput, RunFailed

E = TypeVar("E")

PLUGIN_GROUP = "cdrb.plugins"
PLUGIN_ENV = "CDRB_PLUGINS"

_plugins_loaded = False


def load_plugins() -> None:
    """Import every plugin module once: the ``cdrb.plugins`` entry points, then ``$CDRB_PLUGINS``. A plugin that
    fails to import is reported (one line) at every lookup that needs plugins, never skipped silently."""
    global _plugins_loaded
    if _plugins_loaded:
        return
    from importlib.metadata import entry_points

    names = [(ep.value.split(":")[0], f"entry point {ep.name}") for ep in entry_points(group=PLUGIN_GROUP)]
    names += [(m.strip(), PLUGIN_ENV) for m in os.environ.get(PLUGIN_ENV, "").split(",") if m.strip()]
    from cdrb_cli import interrupts

    for module, source in names:
        signals = interrupts.delivered()
        try:
            importlib.import_module(module)
        except KeyboardInterrupt:
            if interrupts.delivered() != signals:
                raise  # the user's Ctrl-C or a SIGTERM: an interrupt, as anywhere else
            raise BadInput(
                f"plugin {module!r} ({source}) failed to import: it raised KeyboardInterrupt itself",
                hint=f"fix the plugin or remove it from {source}",
            ) from None
        except (Exception, SystemExit) as exc:
            raise BadInput(
                f"plugin {module!r} ({source}) failed to import: {type(exc).__name__}: {exc}",
                hint=f"fix the plugin or remove it from {source}",
            ) from None
    _plugins_loaded = True


class Registry(Generic[E]):
    """Entries of one kind (``what``, e.g. "method"), keyed by ``key(entry)``."""

    def __init__(
        self,
        what: str,
        builtins: Mapping[str, str],
        entry_type: type | None = None,
        key: Callable[[E], str] = lambda e: e.name,
    ):
        self.what = what
        self.builtins = dict(builtins)
        self.entry_type = entry_type
        self._key = key
        self._entries: dict[str, E] = {}

    # -------------------------------------------------------------- adding
    def register(self, entry: E, replace: bool = False) -> E:
        if self.entry_type is not None and not isinstance(entry, self.entry_type):
            raise TypeError(f"a {self.what} entry must be a {self.entry_type.__name__}, not {type(entry).__name__}")
        name = self._key(entry)
        if name in self._entries and not replace and self._entries[name] is not entry:
            raise ValueError(f"{self.what} {name!r} is registered already")
        self._entries[name] = entry
        return entry

    def unregister(self, name: str) -> None:
        self._entries.pop(name, None)

    @contextmanager
    def added(self, *entries: E) -> Iterator[None]:
        """Register ``entries`` (replacing same-named ones) for the duration of a ``with`` block (tests,
        notebooks); what was registered before under those names is restored afterwards."""
        before = {self._key(e): self._entries.get(self._key(e)) for e in entries}
        try:
            for e in entries:
                self.register(e, replace=True)
            yield
        finally:
            for name, previous in before.items():
                if previous is None:
                    self.unregister(name)
                else:
                    self.register(previous, replace=True)

    # -------------------------------------------------------------- looking up
    def _import(self, name: str) -> None:
        if name in self._entries:
            return
        if name in self.builtins:
            try:
                importlib.import_module(self.builtins[name])
            except Exception as exc:  # a broken installation: say which module, not "corrupt file"
                raise RunFailed(
                    f"the {self.what} {name!r} failed to load ({self.builtins[name]}): {type(exc).__name__}: {exc}",
                    hint="reinstall cdrb",
                ) from exc
        else:
            load_plugins()

    def get(self, name: str, flag: str | None = None) -> E:
        """The entry called ``name``; a one-line :class:`BadInput` naming ``flag`` (or the kind) otherwise."""
        self._import(str(name))
        try:
            return self._entries[name]
        except (KeyError, TypeError):
            where = f"{flag} {name!r}" if flag else f"{self.what} {name!r}"
            raise BadInput(f"{where}: unknown {self.what}", hint=f"choose one of {', '.join(self.names())}") from None

    def __contains__(self, name: object) -> bool:
        if not isinstance(name, str):
            return False
        try:
            self._import(name)
        except BadInput:
            return False
        return name in self._entries

    def names(self) -> list[str]:
        """Built-in names in their declared order, then every other registered name (plugins included)."""
        load_plugins()
        return list(self.builtins) + [n for n in self._entries if n not in self.builtins]

    def entries(self) -> list[E]:
        """Every entry, in the order of :meth:`names` (imports every built-in module)."""
        return [self.get(n) for n in self.names()]

    def builtin_entries(self) -> list[E]:
        """The built-in entries only (what the committed JSON Schemas describe)."""
        return [self.get(n) for n in self.builtins]


# ------------------------------------------------------------------------------------------------ pydantic
class Dispatch:
    """``Annotated[Base, Dispatch(REGISTRY, key="name", attr="params")]``: a field holding a record whose class is
    ``getattr(REGISTRY.get(value[key]), attr)`` (the entry itself without ``attr``). Validation accepts an instance
    of a registered class or a dict; serialization writes the record's own fields; the JSON Schema is the union of
    the built-in classes."""

    def __init__(self, registry: Registry, key: str, attr: str | None = None):
        self.registry, self.key, self.attr = registry, key, attr

    def record_type(self, name: str) -> type:
        entry = self.registry.get(name)
        return entry if self.attr is None else getattr(entry, self.attr)

    def __get_pydantic_core_schema__(self, source: Any, handler: Any) -> Any:
        from pydantic import BaseModel
        from pydantic_core import core_schema

        def validate(value: Any, info: Any) -> Any:
            if isinstance(value, BaseModel):
                name = getattr(value, self.key, None)
                cls = self._safe_type(name) if isinstance(name, str) else None
                if cls is not None and isinstance(value, cls):
                    return value
                value = value.model_dump()
            if not isinstance(value, dict):
                raise ValueError(f"expected an object with a {self.key!r} field")
            name = value.get(self.key)
            if not isinstance(name, str):
                raise ValueError(f"missing {self.key!r}")
            cls = self._safe_type(name)
            if cls is None:
                raise ValueError(f"unknown {self.registry.what} {name!r} (known: {', '.join(self.registry.names())})")
            if (info.context or {}).get("strict"):  # settings typed by a user: no coercion inside the record either
                import json

                return cls.model_validate_json(json.dumps(value), strict=True, context=info.context)
            return cls.model_validate(value, context=info.context)

        return core_schema.with_info_plain_validator_function(
            validate,
            serialization=core_schema.plain_serializer_function_ser_schema(
                lambda v, info: v.model_dump(mode=info.mode), info_arg=True
            ),
        )

    def _safe_type(self, name: str):
        try:
            return self.record_type(name)
        except BadInput:
            return None

    def __get_pydantic_json_schema__(self, schema: Any, handler: Any) -> Any:
        from pydantic_core import core_schema

        classes = [e if self.attr is None else getattr(e, self.attr) for e in self.registry.builtin_entries()]
        union = core_schema.union_schema([c.__pydantic_core_schema__ for c in classes])
        return handler(union)


class RegisteredName:
    """``Annotated[str, RegisteredName(REGISTRY, values=...)]``: a string that must be one of the registry's
    names (or, with ``values``, one of the strings ``values(entry)`` gives for some entry, e.g. a method's
    samplers). Its JSON Schema is an enum of the built-in values."""

    def __init__(self, registry: Registry, values: Callable[[Any], Any] | None = None, what: str | None = None):
        self.registry, self.values, self.what = registry, values, what or registry.what

    def allowed(self, builtin_only: bool = False) -> list[str]:
        entries = self.registry.builtin_entries() if builtin_only else self.registry.entries()
        if self.values is None:
            return [self.registry._key(e) for e in entries]
        return list(dict.fromkeys(v for e in entries for v in self.values(e)))

    def __get_pydantic_core_schema__(self, source: Any, handler: Any) -> Any:
        from pydantic_core import core_schema

        def check(value: str) -> str:
            ok = value in self.registry if self.values is None else value in self.allowed()
            if not ok:
                raise ValueError(f"unknown {self.what} {value!r} (known: {', '.join(self.allowed())})")
            return value

        return core_schema.no_info_after_validator_function(check, core_schema.str_schema())

    def __get_pydantic_json_schema__(self, schema: Any, handler: Any) -> Any:
        return {"type": "string", "enum": self.allowed(builtin_only=True)}
