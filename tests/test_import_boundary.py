"""`behaviors/` is the functional core: it may import only the standard library and itself."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

BEHAVIORS = Path(__file__).resolve().parents[1] / "behaviors"
FORBIDDEN_STDLIB = {"socket", "threading", "asyncio", "subprocess", "time", "multiprocessing", "select", "http", "urllib"}


def _imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


def test_behaviors_imports_only_stdlib_and_itself() -> None:
    files = sorted(BEHAVIORS.rglob("*.py"))
    assert files
    for path in files:
        for name in _imports(path):
            assert name == "behaviors" or name == "__future__" or name in sys.stdlib_module_names, (path, name)
            assert name not in FORBIDDEN_STDLIB, f"{path} imports {name}: no clocks, sockets or threads in behaviors"
