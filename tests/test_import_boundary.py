"""`behaviors/` is the functional core: it may import only the standard library and itself."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

BEHAVIORS = Path(__file__).resolve().parents[1] / "behaviors"
FORBIDDEN_STDLIB = {
    "socket",
    "threading",
    "asyncio",
    "subprocess",
    "time",
    "multiprocessing",
    "select",
    "http",
    "urllib",
}


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
            assert name == "behaviors" or name == "__future__" or name in sys.stdlib_module_names, (
                path,
                name,
            )
            assert name not in FORBIDDEN_STDLIB, (
                f"{path} imports {name}: no clocks, sockets or threads in behaviors"
            )


# --- The direction of imports between the packages (issue 16) -------------------------------------------
# behaviors is the pure core and imports nothing of ours (above); cloudtrack is the infrastructure every
# process shares and may use the core's value types; the process packages build on both and never on each
# other; sitl drives everything and nothing depends on it. Tests may import anything.
ROOT = BEHAVIORS.parent
PACKAGES = (
    "behaviors",
    "cloudtrack",
    "companion",
    "companion_tools",
    "gcs",
    "backend",
    "backend_tools",
    "sitl",
)
MAY_IMPORT: dict[str, set[str]] = {
    "behaviors": set(),
    "cloudtrack": {"behaviors"},
    "companion": {"cloudtrack", "behaviors"},
    "backend": {"cloudtrack", "behaviors"},
    # The ground tool shares the link code in cloudtrack, never the onboard process.
    "gcs": {"cloudtrack", "behaviors"},
    # The companion's tools (eval, bench, replay) sit on top: they run the back-end's detector and verifiers
    # in process; `cloudtrack-companion` finds them through entry points, never by import.
    "companion_tools": {"cloudtrack", "behaviors", "companion", "backend"},
    # The back-end's tools (bench, eval, detect, recall, quantisation, verifier table) sit on top of the
    # service as companion_tools sits on the companion; `cloudtrack-backend` finds them through entry points.
    "backend_tools": {"cloudtrack", "behaviors", "backend"},
    # The simulator flies with the VLM emulator (backend_tools) as the hosted VLM it cannot reach.
    "sitl": {"cloudtrack", "behaviors", "companion", "backend", "backend_tools"},
}
# The one import against the direction, and why: MAVProxy's `module load cloudtrack` imports the top-level
# package by the name the user types and calls its init(), which hands over to the ground tool.
MAVPROXY_HOOK = ("cloudtrack/__init__.py", "gcs")


def _cross_package_imports() -> set[tuple[str, str]]:
    """(module path, our package it imports) for every import of another of our packages, lazy ones too."""
    found: set[tuple[str, str]] = set()
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for name in _imports(path) & set(PACKAGES):
                if name != package:
                    found.add((path.relative_to(ROOT).as_posix(), name))
    return found


def test_import_direction_between_packages() -> None:
    found = _cross_package_imports()
    wrong = sorted(
        (module, name)
        for module, name in found
        if name not in MAY_IMPORT[module.split("/")[0]] and (module, name) != MAVPROXY_HOOK
    )
    assert wrong == [], (
        "imports against the direction cloudtrack/behaviors <- companion, backend, gcs <- tools, sitl"
    )


def test_the_mavproxy_hook_is_the_only_exception_and_still_needed() -> None:
    assert MAVPROXY_HOOK in _cross_package_imports()


def test_nothing_imports_sitl_and_the_process_packages_stay_apart() -> None:
    found = _cross_package_imports()
    assert sorted(m for m, name in found if name == "sitl") == []
    assert sorted(m for m, name in found if name == "backend_tools" and m.split("/")[0] != "sitl") == []
    assert sorted((m, name) for m, name in found if {m.split("/")[0], name} == {"companion", "backend"}) == []
