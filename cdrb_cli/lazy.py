"""Deferred imports of heavy libraries.

``from cdrb_cli.lazy import torch`` binds a stand-in for the ``torch`` module without importing it: the import
happens on the first attribute access, through the normal import system (the standard library's ``LazyLoader``
puts a half-loaded module in ``sys.modules``, which torch's own start-up can trip over on Python 3.12). Method
modules use it so that their declarations (hyper-parameter records, registry entries) can be read (by ``cdrb
inspect``, the JSON Schemas, or the CLI's choices) without paying torch's 1-2 s start-up. Code that runs a method
touches ``torch.*`` and gets the real module; if torch was imported already, this is that module.
"""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType


class _Deferred(ModuleType):
    """A stand-in for a module not imported yet: the first attribute it lacks imports the real module (through the
    normal import system, so the module never sees a half-loaded object of its own) and copies its namespace."""

    def __getattr__(self, attr: str):
        module = importlib.import_module(self.__name__)
        self.__dict__.update({k: v for k, v in vars(module).items() if k != "__name__"})
        return getattr(module, attr)


def lazy_import(name: str) -> ModuleType:
    if name in sys.modules:
        return sys.modules[name]
    if importlib.util.find_spec(name) is None:
        raise ImportError(f"No module named {name!r}")
    return _Deferred(name)


torch = lazy_import("torch")
