"""Mock, real ArduCopter and real PX4 side by side: fly each scenario on each autopilot, one flight at a time,
and print the rows of docs/sitl.md's table from the runs' JSON.

    python -m sitl.side_by_side --out out/cmp                           # the whole matrix (about 25 min)
    python -m sitl.side_by_side --out out/cmp --scenarios search --autopilots px4-sitl
    python -m sitl.side_by_side --out out/cmp --table-only              # rows from the JSON already there
    python -m sitl.side_by_side --out out/cmp --wrap "flock /work/coord/locks/heavy"   # a shared machine

Each flight is `cloudtrack-sim run SCENARIO [--autopilot AUTOPILOT] --json OUT/SCENARIO-AUTOPILOT.json` in a
process of its own ("mock" is the scenario's own mock personality: no `--autopilot`); `--wrap` puts a command
in front of each (a lock, `nice`). A flight that fails still writes its JSON: its row says why.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

SCENARIOS = ("follow", "takeover", "takeover-rc", "abort-flyto", "stall", "link-drop", "flood", "search")
AUTOPILOTS = ("mock", "arducopter", "px4-sitl")
NAMES = {"mock": "mock", "arducopter": "ArduCopter", "px4-sitl": "PX4"}
HEADER = (
    "| scenario | autopilot | outcome | first candidate (s) | target in view | standoff RMSE (m) | geolocation "
    "error (m) | setpoints accepted / received | coasted after fault (m) | stop after takeover (ms) |\n"
    "|---|---|---|---|---|---|---|---|---|---|"
)


def command(scenario: str, autopilot: str, json_out: Path) -> list[str]:
    cmd = [sys.executable, "-m", "sitl.cli", "run", scenario, "--json", str(json_out)]
    return cmd if autopilot == "mock" else [*cmd, "--autopilot", autopilot]


def _num(value: Any, digits: int = 2) -> str:
    return (
        "–" if value is None else f"{value:.{digits}f}".rstrip("0").rstrip(".") if digits else f"{value:.0f}"
    )


def _notes(m: dict[str, Any]) -> list[str]:
    """The figure each fault is judged by, as the table's outcome column gives it."""
    notes = []
    if m.get("fly_to_progress_m") is not None:
        notes.append(f"fly-to {m['fly_to_progress_m']:.1f} m")
    first = m.get("first_setpoint_after_resume")
    if "stall_reported" in m:
        reported = m["stall_reported"]
        notes.append("stall reported" if reported else "stall NOT reported")
        if first is not None:
            notes.append(f"first after resume {first['speed_m_s']:.2f} m/s")
    during = m.get("autopilot_during_stall") or {}
    if (during.get("mode_change") or {}).get("mode"):
        notes.append(
            f"{during['mode_change']['mode']} {during['mode_change']['after_s']:.2f} s after the freeze"
        )
    if m.get("flood"):
        notes.append(f"{m['flood'].get('setpoints')} setpoints to flooders")
    if "mission_breaks" in m:
        breaks = ", ".join(f"{b['left_at']}->{b['resumed_at']}" for b in m["mission_breaks"]) or "none"
        notes.append(
            f"find {_num(m.get('time_to_find_s'), 1)} s, coverage {_num(m.get('coverage_at_find'), 3)}, "
            f"item left->resumed {breaks}"
        )
    return notes


def row(scenario: str, autopilot: str, results: dict[str, Any]) -> str:
    m = results["vehicles"]["drone-1"]
    outcome = "; ".join([results["outcome"], *_notes(m)])
    if results["outcome"] != "pass":
        outcome += " (" + "; ".join(f.removeprefix("vehicle 1: ") for f in results["failures"]) + ")"
    coasted = (
        ", ".join(f"{k.replace('_', ' ')} {v:.1f}" for k, v in (m.get("coasted_m") or {}).items()) or "–"
    )
    late = m.get("last_setpoint_after_takeover_s")
    cells = [
        f"`{scenario}`",
        NAMES.get(autopilot, autopilot),
        outcome,
        _num(m.get("time_to_first_candidate_s")),
        _num(m.get("target_in_view_ratio"), 3),
        _num(m.get("standoff_rmse_m")),
        _num(m.get("geolocation_error_m")),
        f"{m.get('setpoints_accepted', '–')} / {m.get('setpoints_received', '–')}",
        coasted,
        "–" if late is None else f"{late * 1000:.0f}",
    ]
    return "| " + " | ".join(cells) + " |"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sitl.side_by_side", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--out", type=Path, default=Path("out/cmp"), help="where the JSON go (default out/cmp)"
    )
    parser.add_argument("--scenarios", nargs="+", default=SCENARIOS, metavar="SCENARIO")
    parser.add_argument("--autopilots", nargs="+", default=AUTOPILOTS, choices=AUTOPILOTS)
    parser.add_argument("--wrap", default="", help="a command put in front of each flight, e.g. 'flock LOCK'")
    parser.add_argument("--table-only", action="store_true", help="fly nothing: rows from the JSON in --out")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for scenario in args.scenarios:
        for autopilot in args.autopilots:
            json_out = args.out / f"{scenario}-{autopilot}.json"
            if not args.table_only:
                cmd = [*shlex.split(args.wrap), *command(scenario, autopilot, json_out)]
                print("$ " + " ".join(cmd), file=sys.stderr, flush=True)
                subprocess.run(cmd, stdout=subprocess.DEVNULL, check=False)
            if not json_out.is_file():
                print(f"no {json_out}: not flown (or it could not start)", file=sys.stderr)
                continue
            rows.append(row(scenario, autopilot, json.loads(json_out.read_text())))
    print(HEADER)
    print("\n".join(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
