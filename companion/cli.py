"""`cloudtrack-companion`: the onboard process and its tools. Each subcommand lives in its own module."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from cloudtrack.command_line import add_command_modules, new_parser, run

EXAMPLES = """\
examples:
  cloudtrack-companion run --config /etc/cloudtrack/companion.toml
  cloudtrack-companion config check /etc/cloudtrack/companion.toml
  cloudtrack-companion config show --set mavlink.connection=/dev/ttyAMA0,921600
  cloudtrack-companion models list --model-dir ../shared/models
  cloudtrack-companion models download nano
  cloudtrack-companion eval ../shared/data/sequences/* --tracker nano --json out/eval.json
  cloudtrack-companion bench --tracker nano --sequence ../shared/data/sequences/uav123_person12_1
"""

# Subcommand modules; each defines add_parser(subparsers) and sets `func` on its parser.
COMMAND_MODULES = (
    "companion.config_command",
    "companion.models_command",
    "companion.run_command",
    "companion.service_command",
)
# The tools (eval, bench, replay: package companion_tools) declare their subcommands in this entry-point
# group (pyproject.toml), so the onboard process never imports them, nor what they import (the back-end).
TOOL_COMMANDS = "cloudtrack.companion_commands"


def build_parser() -> argparse.ArgumentParser:
    parser, subparsers = new_parser(
        "cloudtrack-companion",
        "CloudTrack onboard process: track a described person and fly to keep them in view.",
        EXAMPLES,
    )
    add_command_modules(subparsers, COMMAND_MODULES, TOOL_COMMANDS)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run(build_parser, argv)


if __name__ == "__main__":
    sys.exit(main())
