"""`cloudtrack-backend`: the cloud service and its tools. Each subcommand lives in its own module."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from backend.config import CONFIG_FILE_NAME, BackendConfig, load_backend_config
from cloudtrack.command_line import add_command_modules, new_parser, run
from cloudtrack.config_files import config_search_help

EXAMPLES = """\
examples:
  cloudtrack-backend serve --config /etc/cloudtrack/backend.toml
  CLOUDTRACK_BACKEND_AUTH__TOKENS='{"drone-1": "s3cret"}' cloudtrack-backend serve --set server.port=9000
  cloudtrack-backend detect frame.jpg --prompt "an injured man in a gray shirt" --draw out.jpg
  cloudtrack-backend eval --coco set.json --images frames/ --verifier local --verifier none
  cloudtrack-backend bench --latency 1.0 --vehicles 1 4 16
  sudo cloudtrack-backend service install
"""

# Subcommand modules; each defines add_parser(subparsers) and sets `func` on its parser.
COMMAND_MODULES = (
    "backend.serve_command",
    "backend.service_command",
)
# The tools (detect, eval, bench: package backend_tools) declare their subcommands in this entry-point
# group (pyproject.toml), so the service never imports them, nor what they import (nginx and redis
# harnesses, the VLM emulator, the evaluation libraries).
TOOL_COMMANDS = "cloudtrack.backend_commands"


def add_config_flags(parser: argparse.ArgumentParser) -> None:
    """--config and --set, shared by every subcommand that reads the configuration."""
    parser.add_argument("--config", type=Path, help=config_search_help(CONFIG_FILE_NAME))
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one value, e.g. --set verifier.kind=cascade (repeatable)",
    )


def config_from_args(args: argparse.Namespace, *extra: str) -> BackendConfig:
    return load_backend_config(args.config, [*args.set, *extra])


def build_parser() -> argparse.ArgumentParser:
    parser, subparsers = new_parser(
        "cloudtrack-backend",
        "CloudTrack back-end: superset detection, 50 px crops and concurrent verification for many drones.",
        EXAMPLES,
    )
    add_command_modules(subparsers, COMMAND_MODULES, TOOL_COMMANDS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run(build_parser, argv)


if __name__ == "__main__":
    sys.exit(main())
