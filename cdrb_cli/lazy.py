"""Deferred imports of heavy libraries.

``from cdrb_cli.lazy import torch`` binds the ``torch`` module without importing it (the standard library's
:class:`importlib.util.LazyLoader`): the import happens on the first attribute access. Method modules use it so
that their declarations (hyper-parameter records, registry entries) can be read (by ``cdrb inspect``, the JSON
Schemas, or the CLI's choices) without paying torch's 1-2 s start-up. Code that runs a method touches ``torch.*``
and gets the real module; if torch was imported already, this is that module.
"""

from __future__ import annotations

import importlib.util
import sys
from types import ModuleType


def lazy_import(name: str) -> ModuleType:
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    if spec is None or spec.loader is None:
        raise ImportError(f"No module named {name!r}")
    loader = importlib.util.LazyLoader(spec.loader)
    spec.loader = loader
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    loader.exec_module(module)
    return module


torch = lazy_import("torch")
