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
