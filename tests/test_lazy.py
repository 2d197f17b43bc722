"""Deferred imports: the stand-in imports the real module on first use, through the normal import system."""

from __future__ import annotations

import sys

import pytest

from cdrb_cli.lazy import lazy_import


def test_deferred_module_imports_on_first_attribute_and_never_enters_sys_modules_half_loaded():
    name = "json.tool"  # a standard-library module no cdrb import pulls in
    sys.modules.pop(name, None)
    mod = lazy_import(name)
    assert name not in sys.modules  # nothing half-loaded is registered
    assert callable(mod.main)  # first use imports it
    assert sys.modules[name].main is mod.main
    assert lazy_import(name) is sys.modules[name]  # once imported, the real module


def test_missing_module_is_an_import_error():
    with pytest.raises(ImportError):
        lazy_import("no_such_module_cdrb")
