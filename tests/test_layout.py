"""phd_core is a pure library: it never imports web code, at any depth.

Two checks, because each misses what the other sees: every import statement in every
phd_core module (function-local ones included, which a run only meets on some paths), and
a fresh interpreter that imports every phd_core module and then looks at what got loaded
(imports made by the libraries phd_core uses).
"""

from __future__ import annotations

import ast
import json
import re
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
LAYERS = ["train", "uq", "executors", "renderers", "process", "data", "scene", "eval", "io"]
FOUNDATIONS = {"errors", "registry", "allocator"}   # modules every layer may use


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


def module_imports(path: Path) -> set[str]:
    """The phd_core modules one module names in its imports, function-local ones included
    ('renderers.families'); `from . import x` counts as the module x when x is one."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    package = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom) and node.level > 0:
            base = list(package[:len(package) - (node.level - 1)])
            target = base + (node.module.split(".") if node.module else [])
            for alias in node.names:
                as_module = ".".join(target + [alias.name])
                found.add(as_module if (ROOT / Path(*target, alias.name)).with_suffix(".py").is_file()
                          or (ROOT / Path(*target, alias.name)).is_dir() else ".".join(target))
    return {name for name in found if name}


def test_no_two_phd_core_modules_import_each_other() -> None:
    """The dependency between modules runs one way: no circle, even one hidden by a lazy import."""
    def name(path: Path) -> str:
        parts = path.relative_to(ROOT).with_suffix("").parts
        return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)

    graph = {name(p): module_imports(p) for p in ROOT.rglob("*.py")}
    circles = []

    def walk(node: str, trail: list[str]) -> None:
        for nxt in sorted(graph.get(node, ())):
            if nxt in trail:
                circles.append(trail[trail.index(nxt):] + [nxt])
            elif nxt not in seen:
                seen.add(nxt)
                walk(nxt, trail + [nxt])

    for start in sorted(graph):
        seen = {start}
        walk(start, [start])
    # A package's __init__ re-exporting its own modules is no circle between two modules.
    circles = [c for c in circles if not all(a.startswith(b + ".") or b.startswith(a + ".") or a == b
                                             for a, b in zip(c, c[1:]))]
    assert circles == []


# "A new family is one module plus one entry": the service and the CLI know families only
# through phd_core.renderers.FAMILIES, so their code names no family package, class or kind.
# Docstrings and comments may; help text that lists families is generated from the registry.
FAMILY_PACKAGES = {"gs3d", "gs2d", "nerf"}
FAMILY_KIND = re.compile(r"\b(3dgs(?!-output)|2dgs|nerf)\b", re.IGNORECASE)
FRONT_ENDS = [ROOT.parent / "service", ROOT.parent / "phd_cli"]


def family_names() -> set[str]:
    """The family packages and their public classes and constants (GaussianRenderer, SurfelModel,
    NeRFConfig, ...); their functions are reached through a package name, which is checked."""
    import importlib

    return {name for package in FAMILY_PACKAGES
            for name in importlib.import_module(f"phd_core.renderers.{package}").__all__
            if name[0].isupper()} | FAMILY_PACKAGES


def docstrings(tree: ast.AST) -> set[int]:
    """ids of the string constants that are docstrings."""
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                found.add(id(first.value))
    return found


def test_the_service_and_the_cli_name_no_family() -> None:
    names = family_names()
    found = {}
    for path in sorted(p for front in FRONT_ENDS for p in front.rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        skip = docstrings(tree)
        hits = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module:
                hits |= set(node.module.split(".")) & FAMILY_PACKAGES
                hits |= {alias.name for alias in node.names} & names
            elif isinstance(node, ast.Name) and node.id in names:
                hits.add(node.id)
            elif isinstance(node, ast.Attribute) and node.attr in names:
                hits.add(node.attr)
            elif isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in skip:
                hits |= {m.group(0) for m in FAMILY_KIND.finditer(node.value)}
        if hits:
            found[str(path.relative_to(ROOT.parent))] = sorted(hits)
    assert found == {}
