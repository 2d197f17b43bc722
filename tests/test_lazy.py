"""Deferred imports: the stand-in imports the real module on first use, through the normal import system."""

from __future__ import annotations

import subprocess
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


def test_collect_cluster_and_inspect_never_import_torch(tmp_path):
    """Stages without a network never pay torch's import (seconds in a fresh process): a real process collects,
    clusters and inspects, then lists the torch modules it loaded."""
    import subprocess

    demos, buffer = tmp_path / "d.h5", tmp_path / "b.h5"
    code = (
        "import sys\n"
        "from cdrb_cli.cli import main\n"
        f"assert main(['collect', 'maze-tight', '-n', '4', '--seed', '0', '--out', {str(demos)!r}]) == 0\n"
        f"assert main(['cluster', {str(demos)!r}, '--k', '20', '--out', {str(buffer)!r}]) == 0\n"
        f"assert main(['inspect', {str(buffer)!r}]) == 0\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] == 'torch'))\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().splitlines()[-1] == "[]"
    assert demos.exists() and buffer.exists()


def test_the_command_line_loads_the_grid_machinery_only_when_a_grid_needs_it():
    """`cdrb --help` and every command but grid and select start without the grid's spec, expansion and runner (and
    the configs they read): the command line imports only the grid's command catalogue; the package's names load on
    first use, each the object its module defines."""
    code = (
        "import sys\n"
        "import cdrb_cli.cli\n"
        "heavy = [m for m in sys.modules if m.startswith('cdrb_cli.orchestration.grid.') and m[28:] != 'commands']\n"
        "print(sorted(heavy), 'cdrb_cli.configs' in sys.modules)\n"
        "from cdrb_cli.orchestration.grid import expand, load_grid\n"
        "import cdrb_cli.orchestration.grid.expansion as ex, cdrb_cli.orchestration.grid.load as ld\n"
        "assert expand is ex.expand and load_grid is ld.load_grid and callable(expand)\n"
        "from cdrb_cli.orchestration import grid\n"
        "assert grid.expand is ex.expand and 'run_grid' in dir(grid)\n"
        "try:\n"
        "    grid.nothing\n"
        "except AttributeError as exc:\n"
        "    print(exc)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    first, last = r.stdout.strip().splitlines()
    assert first == "[] False"
    assert "has no attribute 'nothing'" in last
