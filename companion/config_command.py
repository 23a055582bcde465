"""`cloudtrack-companion config check|show`: validate a configuration file or print the effective values."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from cloudtrack.config_files import ConfigError, config_search_help, dump_toml
from companion.config import CONFIG_FILE_NAME, CompanionConfig, load_companion_config


def add_config_flags(parser: argparse.ArgumentParser) -> None:
    """--config and --set, shared by every subcommand that reads the configuration."""
    parser.add_argument("--config", type=Path, help=config_search_help(CONFIG_FILE_NAME))
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one value, e.g. --set safety.max_speed_m_s=2.5 (repeatable)",
    )


def load_from_args(args: argparse.Namespace) -> CompanionConfig:
    return load_companion_config(args.config, args.set)


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "config",
        help="check a configuration file or show the effective configuration",
        description="Validate configuration. Exit status 2 names the file, key and what is allowed.",
        epilog="examples:\n  cloudtrack-companion config check companion.toml\n"
        "  CLOUDTRACK_SAFETY__MAX_SPEED_M_S=2 cloudtrack-companion config show",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    check = actions.add_parser("check", help="validate FILE (with environment and --set overrides)")
    check.add_argument("file", type=Path)
    check.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE")
    check.set_defaults(func=_check)
    show = actions.add_parser("show", help="print the effective configuration as TOML")
    add_config_flags(show)
    show.set_defaults(func=_show)


def _check(args: argparse.Namespace) -> int:
    from companion.vision.camera_calibration import camera_model

    try:
        config = load_companion_config(args.file, args.set)
        camera_model(
            config.camera
        )  # a [camera] calibration_file that cannot be read fails here, not in flight
    except (ConfigError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.file}: ok")
    return 0


def _show(args: argparse.Namespace) -> int:
    try:
        config = load_from_args(args)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(dump_toml(config))
    return 0
