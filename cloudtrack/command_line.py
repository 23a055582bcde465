"""The shape every CloudTrack console script shares: logging flags, one module per subcommand, main()."""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING

from cloudtrack.logging_setup import add_logging_flags, setup_logging

if TYPE_CHECKING:
    SubParsers = argparse._SubParsersAction[argparse.ArgumentParser]


def new_parser(prog: str, description: str, examples: str) -> tuple[argparse.ArgumentParser, SubParsers]:
    """A top-level parser with the logging flags and an empty, required set of subcommands."""
    parser = argparse.ArgumentParser(
        prog=prog,
        description=description,
        epilog=examples,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_logging_flags(parser)
    return parser, parser.add_subparsers(dest="command", required=True, metavar="COMMAND")


def add_command_modules(subparsers: SubParsers, module_names: Iterable[str], plugin_group: str = "") -> None:
    """Each module defines add_parser(subparsers) and sets `func` on the parser it adds. With
    `plugin_group`, the modules installed packages declare in that entry-point group come after them (in
    name order): tools on top of a process add its subcommands without the process importing them."""
    for module_name in module_names:
        importlib.import_module(module_name).add_parser(subparsers)
    if plugin_group:
        # One module per name: a package seen twice on the path (an editable install beside a copy) declares
        # the same entry points twice.
        modules = {entry.name: entry.value for entry in importlib.metadata.entry_points(group=plugin_group)}
        for name in sorted(modules):
            importlib.import_module(modules[name]).add_parser(subparsers)


def run(build_parser: Callable[[], argparse.ArgumentParser], argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    setup_logging(args.log_level, args.log_json)
    return int(args.func(args) or 0)
