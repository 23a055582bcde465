"""`cloudtrack-companion replay RECORD_DIR`: re-run a recorded mission and report differing decisions."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm

from behaviors.mission_config import MissionConfig
from cloudtrack.config_files import ConfigError
from companion.config import load_companion_config
from companion_tools.replay import RecordError, load_recording, replay

EXAMPLES = """\
examples:
  cloudtrack-companion replay ~/.local/share/cloudtrack/records/20261121T203000Z_drone-1_m42
  cloudtrack-companion replay /var/lib/cloudtrack/records/20261121T203000Z_drone-1_m42   # under systemd
  cloudtrack-companion replay RECORD_DIR --set behavior.standoff_m=15     # what would change?
  cloudtrack-companion replay RECORD_DIR --config new.toml --json out/replay.json --show 50
Records are in [recording] dir; by default $XDG_DATA_HOME/cloudtrack/records (~/.local/share/...), or
$STATE_DIRECTORY/records (/var/lib/cloudtrack/records) under systemd.
exit status: 0 same decisions, 1 decisions differ, 2 the record or the configuration is unusable
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "replay",
        help="re-run a recorded mission through the behaviours and report where decisions differ",
        description="Feed a flight record's events through behaviors.mission.step and compare every "
        "resulting action and state with what was flown. Without --config/--set the recorded "
        "configuration is used, so a difference means the behaviour code changed.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "record_dir", type=Path, metavar="RECORD_DIR", help="one mission folder of the flight record"
    )
    parser.add_argument(
        "--config", type=Path, help="replay with this companion configuration instead of the recorded one"
    )
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override one value (implies a new configuration)",
    )
    parser.add_argument("--json", type=Path, metavar="FILE", help="also write the report as JSON")
    parser.add_argument(
        "--show", type=int, default=20, metavar="N", help="print at most N differences (default 20)"
    )
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    parser.set_defaults(func=_run)


def _mission_config(args: argparse.Namespace) -> MissionConfig | None:
    if args.config is None and not args.set:
        return None
    from companion.run_command import mission_config  # exactly the config `run` would fly with

    return mission_config(load_companion_config(args.config, args.set))


def _run(args: argparse.Namespace) -> int:
    try:
        config = _mission_config(args)
        recording = load_recording(args.record_dir)
        report = replay(
            recording,
            args.record_dir,
            config,
            progress=lambda steps: tqdm(
                steps, desc="replay", unit="step", disable=args.no_progress, file=sys.stderr
            ),
        )
    except (ConfigError, RecordError, ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report.to_json(), indent=1))
    source = "the recorded configuration" if config is None else "the given configuration"
    if report.identical:
        print(f"{args.record_dir}: {report.steps} steps replayed with {source}: no decision differs")
        return 0
    print(f"{args.record_dir}: {len(report.differences)} of {report.steps} steps differ with {source}")
    for difference in report.differences[: max(0, args.show)]:
        print(difference.describe())
    if len(report.differences) > args.show:
        print(f"... {len(report.differences) - args.show} more (see --json)")
    return 1
