"""phd_core is a pure library: it never imports web code, at any depth.

Two checks, because each misses what the other sees: every import statement in every
phd_core module (function-local ones included, which a run only meets on some paths), and
a fresh interpreter that imports every phd_core module and then looks at what got loaded
(imports made by the libraries phd_core uses).
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import phd_core

WEB = {"service", "client", "phd_cli", "fastapi", "uvicorn", "httpx", "starlette", "multipart"}
ROOT = Path(phd_core.__file__).resolve().parent


def imported_top_level_names(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_no_phd_core_module_names_web_code() -> None:
    offenders = {str(path.relative_to(ROOT)): sorted(imported_top_level_names(path) & WEB)
                 for path in sorted(ROOT.rglob("*.py"))}
    assert {k: v for k, v in offenders.items() if v} == {}


def test_importing_all_of_phd_core_loads_no_web_code() -> None:
    code = ("import importlib, json, pkgutil, sys, phd_core\n"
            "for info in pkgutil.walk_packages(phd_core.__path__, 'phd_core.'):\n"
            "    importlib.import_module(info.name)\n"
            "print(json.dumps(sorted({name.split('.')[0] for name in sys.modules})))")
    loaded = set(json.loads(subprocess.run([sys.executable, "-c", code], check=True, capture_output=True,
                                           text=True, cwd=ROOT.parent).stdout))
    assert "phd_core" in loaded
    assert loaded & WEB == set()


# docs/architecture.md draws these layers top to bottom; a layer imports only layers below it.
LAYERS = ["train", "uq", "executors", "renderers", "data", "scene", "eval", "io"]
FOUNDATIONS = {"errors", "registry"}   # modules every layer may use


def phd_core_imports(path: Path) -> set[str]:
    """The phd_core subpackages or top-level modules one module imports (relative or absolute)."""
    package = path.relative_to(ROOT).parts[:-1]
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = package[:len(package) - (node.level - 1)] if node.level > 1 else package
            target = list(base) + (node.module.split(".") if node.module else [])
            if not target and node.module is None:
                target = [alias.name for alias in node.names][:1]
            names.add(target[0] if target else "")
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("phd_core."):
            names.add(node.module.split(".")[1])
    return names - {""}


def test_each_layer_imports_only_the_layers_below_it() -> None:
    wrong = {}
    for rank, layer in enumerate(LAYERS):
        allowed = set(LAYERS[rank:]) | FOUNDATIONS
        for path in sorted((ROOT / layer).rglob("*.py")):
            if bad := phd_core_imports(path) - allowed:
                wrong[str(path.relative_to(ROOT))] = sorted(bad)
    assert wrong == {}
    assert {p.name for p in ROOT.iterdir() if p.is_dir() and p.name != "__pycache__"} == set(LAYERS)


def test_no_module_is_over_500_lines() -> None:
    long = {str(p.relative_to(ROOT)): n for p in ROOT.rglob("*.py") if (n := len(p.read_text().splitlines())) > 500}
    assert long == {}
