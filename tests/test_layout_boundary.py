"""The layout inside the packages (issue 16): companion's capabilities stay apart, the tools stand apart from
the runtime, the ground side never imports the companion, and no module name repeats with another meaning.

tests/test_import_boundary.py checks the direction between the top-level packages; this checks the finer
rules the split of `companion/` adds (`python -m pytest -k layout`).
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]
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
CAPABILITIES = ("companion.mavlink", "companion.vision", "companion.cloud")
# The main loop's wiring: capabilities are parts it puts together, so they never import it back.
WIRING = ("companion.mission_runner", "companion.run_command", "companion.cli")
# MAVProxy loads `module load cloudtrack` by importing the package named `cloudtrack` and calling its
# `init`, so that hook (and only it) may hand over to the ground side's module, lazily.
ENTRY_POINT_HOOKS = {("cloudtrack/__init__.py", "gcs")}
# Each process and the tools on top of it, which it finds through an entry-point group, never by import.
TOOLS = {"companion": ("companion_tools", "cloudtrack.companion_commands"),
         "backend": ("backend_tools", "cloudtrack.backend_commands")}  # fmt: skip
# The only modules of a service package runnable on their own: its command line, and the pose model's
# installer (`make install` runs it). Anything else with a command line is a tool and lives in *_tools.
SERVICE_MAIN_MODULES = {"companion.cli", "backend.cli", "backend.verifiers.person_model"}
# Names that repeat with the same meaning in each package; any other repeat is a clash to rename.
SAME_MEANING = {
    "__init__": "each package's own",
    "cli": "each process's command line (companion, backend, sitl, gcs)",
    "config": "each process's configuration schema (companion, backend)",
    "eval_command": "the `eval` subcommand of each process's command line",
    "bench_command": "the `bench` subcommand of each process's command line",
    "service_command": "the `service` subcommand of each process's command line",
    "factory": "each plug-in family's factory (backend/detectors, backend/verifiers)",
    "interface": "each plug-in family's interface (backend/detectors, backend/verifiers)",
    "detection": "backend/routers/detection.py serves behaviors' Detection (routers named for their resource)",
}


def _modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of our packages."""
    found: dict[str, Path] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _imported(path: Path) -> set[str]:
    """Every dotted name `path` imports, lazy imports included; `from a import b` gives `a` and `a.b`."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def _within(name: str, package: str) -> bool:
    return name == package or name.startswith(package + ".")


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    return {module: _imported(path) for module, path in modules.items()}


def test_layout_packages_exist() -> None:
    modules = _modules()
    for package in (*CAPABILITIES, "companion_tools", "backend_tools", "gcs"):
        assert package in modules, f"{package}/__init__.py is missing"


def test_layout_capabilities_do_not_import_each_other_nor_the_wiring_nor_the_tools() -> None:
    wrong = sorted(
        (module, name)
        for module, names in _graph().items()
        for capability in CAPABILITIES
        if _within(module, capability)
        for name in names
        if any(_within(name, other) for other in CAPABILITIES if other != capability)
        or _within(name, "companion_tools")
        or any(_within(name, wiring) for wiring in WIRING)
    )
    assert wrong == [], "mavlink, vision and cloud are parts the runtime wires together, never each other"


def test_layout_runtime_never_imports_the_tools() -> None:
    """The tools may import the runtime; the runtime finds them only through entry points (its cli.py)."""
    for runtime, (tools, _) in TOOLS.items():
        wrong = sorted(
            (module, name)
            for module, names in _graph().items()
            if _within(module, runtime) and not _within(module, tools)
            for name in names
            if _within(name, tools)
        )
        assert wrong == [], runtime


def _entry_points() -> dict[str, dict[str, str]]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return dict(project["entry-points"])


def test_layout_each_tool_subcommand_is_declared_and_each_declared_one_exists() -> None:
    groups = _entry_points()
    modules = _modules()
    for tools, group in TOOLS.values():
        declared = groups[group]
        assert [m for m in declared.values() if m not in modules or not _within(m, tools)] == [], group
        commands = {m for m in modules if _within(m, tools) and m.endswith("_command")}
        assert commands == set(declared.values()), f"{tools}: every *_command module is a declared subcommand"
        # A subcommand's name may have a hyphen (pod-curve) where its module's has an underscore.
        assert all(
            m.rsplit(".", 1)[-1] == f"{name.replace('-', '_')}_command" for name, m in declared.items()
        ), group


def test_layout_service_packages_hold_no_tools() -> None:
    """A module with its own command line (`if __name__ == "__main__"`) in a service package is a tool."""
    runnable = sorted(
        module
        for module, path in _modules().items()
        if module.split(".")[0] in TOOLS and "__main__" in path.read_text()
    )
    assert set(runnable) <= SERVICE_MAIN_MODULES, set(runnable) - SERVICE_MAIN_MODULES


def test_layout_ground_side_and_companion_never_import_each_other() -> None:
    graph = _graph()
    ground = sorted(
        (m, n)
        for m, names in graph.items()
        if _within(m, "gcs")
        for n in names
        if n.split(".")[0] in {"companion", "backend", "sitl"}
    )
    assert ground == [], "gcs shares the wire protocol with the companion through cloudtrack only"
    into_ground = sorted(
        (_modules()[m].relative_to(ROOT).as_posix(), "gcs")
        for m, names in graph.items()
        if not _within(m, "gcs")
        for n in names
        if _within(n, "gcs")
    )
    assert set(into_ground) <= ENTRY_POINT_HOOKS, f"nothing runs the ground side: {into_ground}"


def test_layout_no_module_name_repeats_with_another_meaning() -> None:
    by_name: dict[str, list[str]] = {}
    for module, path in _modules().items():
        by_name.setdefault(path.stem, []).append(module)
    repeats = sorted(
        name for name, modules in by_name.items() if len(modules) > 1 and name not in SAME_MEANING
    )
    assert repeats == [], {name: by_name[name] for name in repeats}
    packages = {
        module.rsplit(".", 1)[-1] for module, path in _modules().items() if path.name == "__init__.py"
    }
    shadowing = sorted(m for m, p in _modules().items() if p.name != "__init__.py" and p.stem in packages)
    assert shadowing == [], "a module named like one of our packages reads as that package"


def test_layout_every_subcommand_module_ends_in_command() -> None:
    for cli in ("companion/cli.py", "backend/cli.py"):
        tree = ast.parse((ROOT / cli).read_text())
        listed = [
            elt.value
            for node in ast.walk(tree)
            if isinstance(node, ast.Assign)
            and any(getattr(t, "id", "") == "COMMAND_MODULES" for t in node.targets)
            for elt in getattr(node.value, "elts", [])
            if isinstance(elt, ast.Constant) and isinstance(elt.value, str)
        ]
        assert listed, f"{cli} has no COMMAND_MODULES"
        assert [m for m in listed if not m.endswith("_command")] == [], cli
        missing = [m for m in listed if m not in _modules()]
        assert missing == [], f"{cli} names modules that do not exist: {missing}"


def test_layout_every_package_says_what_it_owns() -> None:
    for path in _modules().values():
        if path.name == "__init__.py":
            assert ast.get_docstring(ast.parse(path.read_text())), f"{path}: say in 2-3 lines what it owns"
