"""The architecture's rules, checked on the source: layers import downwards only, no module reaches into another's
private helpers, the CLI names no method or sampler, benchmarks do not depend on tests, and reading the registries
costs no torch import."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "cdrb_cli"


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """Every import in a file (module level and inside functions): (module, names)."""
    tree = ast.parse(path.read_text())
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.append((node.module, [a.name for a in node.names]))
    return out


LOW_LAYERS = [PKG / "envs", PKG / "methods", PKG / "nets", PKG / "artifacts", PKG / "buffer.py"]


def _files(*places: Path) -> list[Path]:
    return [f for p in places for f in ([p] if p.is_file() else sorted(p.rglob("*.py")))]


@pytest.mark.parametrize("path", _files(*LOW_LAYERS), ids=lambda p: str(p.relative_to(ROOT)))
def test_low_layers_import_neither_stages_nor_the_cli(path):
    bad = [m for m, _ in _imports(path) if m.startswith(("cdrb_cli.stages", "cdrb_cli.cli"))]
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


@pytest.mark.parametrize(
    "path", _files(PKG / "orchestration", PKG / "stages", PKG / "api.py"), ids=lambda p: str(p.relative_to(ROOT))
)
def test_orchestration_stages_and_the_api_import_neither_the_cli_nor_typer(path):
    """The grid reads the commands it composes as data the CLI installs (orchestration/grid/commands.py), so the
    command line stays the top floor."""
    bad = [m for m, _ in _imports(path) if m.startswith(("cdrb_cli.cli", "typer", "click"))]
    assert not bad, f"{path.relative_to(ROOT)} imports {bad}"


@pytest.mark.parametrize("path", _files(PKG, ROOT / "benchmarks"), ids=lambda p: str(p.relative_to(ROOT)))
def test_no_module_imports_another_modules_private_names(path):
    bad = [
        (m, n)
        for m, names in _imports(path)
        for n in names
        if n[:1] == "_" and n[:2] != "__" and m.startswith("cdrb_cli")
    ]
    assert not bad, f"{path.relative_to(ROOT)} imports private names {bad}"


def test_benchmarks_do_not_import_tests():
    bad = [(f.name, m) for f in _files(ROOT / "benchmarks") for m, _ in _imports(f) if m.split(".")[0] == "tests"]
    assert not bad, bad


def _strings(path: Path) -> set[str]:
    return {
        n.value
        for n in ast.walk(ast.parse(path.read_text()))
        if isinstance(n, ast.Constant) and isinstance(n.value, str)
    }


def test_the_cli_names_no_method_sampler_expert_controller_or_environment():
    from cdrb_cli.envs.registry import CONTROLLERS, EXPERTS, FAMILIES, list_envs
    from cdrb_cli.methods.registry import METHODS

    names = set(METHODS.names()) | {s for e in METHODS.entries() for s in e.samplers}
    names |= set(EXPERTS.names()) | set(CONTROLLERS.names()) | set(FAMILIES.names()) | {r["id"] for r in list_envs()}
    for path in _files(PKG / "cli"):
        found = _strings(path) & names
        assert not found, f"{path.relative_to(ROOT)} spells registry names: {sorted(found)}"


def test_stages_name_no_environment_family_or_its_geometry():
    """The stages reach an environment only through its family: no PointMaze, no maze module, no obs[:2]."""
    for path in _files(PKG / "stages"):
        text = path.read_text()
        assert "pointmaze" not in text.lower(), path.name
        assert not re.search(r"(\[(:|\.\.\.),\s*:2\])|((obs|state|states)\[:2\])", text), path.name
        assert not [m for m, _ in _imports(path) if "pointmaze" in m or m.endswith(".maze")], path.name


def test_the_registries_read_without_importing_torch():
    code = (
        "import sys\n"
        "from cdrb_cli.methods.registry import METHODS\n"
        "from cdrb_cli.envs.registry import CONTROLLERS, EXPERTS, FAMILIES\n"
        "from cdrb_cli import artifacts\n"
        "for r in (METHODS, CONTROLLERS, EXPERTS, FAMILIES): r.entries()\n"
        "artifacts.load(sys.argv[1])\n"
        "t = sys.modules.get('torch')\n"
        "assert t is None or type(t).__name__ == '_LazyModule', type(t)\n"
    )
    model = ROOT / "tests" / "data" / "v1" / "model.h5"
    proc = subprocess.run([sys.executable, "-c", code, str(model)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
