"""`cloudtrack-sim`: closed-loop scenarios (`run`, `list`), the mock autopilot (`autopilot`), the camera alone
(`camera`, also for an external autopilot) and the renderer's speed (`bench`)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from cloudtrack.command_line import add_command_modules, new_parser, run
from sitl.autopilot import PERSONALITIES
from sitl.flight_stack import REAL_AUTOPILOTS
from sitl.run_summary import summary_lines
from sitl.scenarios import SCENARIOS, Scenario

if TYPE_CHECKING:
    from sitl.scenario_runner import RunOptions

EXAMPLES = """\
examples:
  cloudtrack-sim list
  cloudtrack-sim up                         # everything on this machine, to drive by hand (docs/quickstart.md)
  cloudtrack-sim run follow --video out/demo.mp4 --plot out/demo.png --json out/demo.json
  cloudtrack-sim run reject --seed 3 --json out/reject.json
  cloudtrack-sim run follow --autopilot px4 --tracker vit --model-dir ../shared/models
  cloudtrack-sim run follow --autopilot arducopter --json out/follow-arducopter.json
  cloudtrack-sim run follow --autopilot px4-sitl --json out/follow-px4.json
  cloudtrack-sim run fleet-search --autopilot arducopter,px4-sitl --json out/fleet-mixed.json
  cloudtrack-sim autopilot --autopilot px4 --gcs udpout:127.0.0.1:14550
  cloudtrack-sim camera --autopilot-url udpin:0.0.0.0:14551 --backend-port 8080
  cloudtrack-sim bench
"""


def _add_run(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    run = subparsers.add_parser(
        "run",
        help="run one closed-loop scenario and write its metrics",
        description="Start the mock autopilot, the synthetic world and camera, the real back-end (loopback HTTP), "
        "the real companion process and a scripted GCS/supervisor; run SCENARIO; print and write the metrics. "
        "Exit status 0 when every check of the scenario passed, 1 when one failed, 2 when it could not run.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    run.add_argument("scenario", choices=sorted(SCENARIOS), metavar="SCENARIO", help=", ".join(SCENARIOS))
    run.add_argument(
        "--autopilot",
        type=_autopilot_list,
        metavar="NAME[,NAME...]",
        help="override the scenario's autopilot: a mock personality (ardupilot, px4), 'arducopter', "
        "the real ArduCopter SITL binary (see --arducopter-binary), or 'px4-sitl', the real PX4 with SIH "
        "physics (see --px4-package); a comma list gives each vehicle its own, in order "
        "(fleet-search --autopilot arducopter,px4-sitl: drone-1 ArduCopter, drone-2 PX4). fleet-search on "
        "one real autopilot flies two vehicles of it (docs/sitl.md)",
    )
    run.add_argument(
        "--arducopter-binary",
        type=Path,
        metavar="PATH",
        help="the ArduCopter SITL binary for --autopilot arducopter (default: $CLOUDTRACK_ARDUCOPTER, "
        "else $CLOUDTRACK_SHARED/sitl/arducopter, else ../shared/sitl/arducopter); a missing binary "
        "is an error, never a fall-back to the mock",
    )
    run.add_argument(
        "--px4-package",
        type=Path,
        metavar="DIR",
        help="the PX4 SITL package (bin/px4, etc/) for --autopilot px4-sitl (default: $CLOUDTRACK_PX4, else "
        "$CLOUDTRACK_SHARED/sitl/px4, else ../shared/sitl/px4); a missing package is an error, never a "
        "fall-back to the mock",
    )
    run.add_argument(
        "--speedup",
        type=float,
        default=10.0,
        metavar="X",
        help="with --autopilot arducopter: SITL speed-up while it boots, arms and takes off (default 10); "
        "the mission itself always runs at 1, since the world, the camera and the companion run in "
        "wall-clock time (PX4 takes its speed factor only at start-up, so px4-sitl always runs at 1)",
    )
    run.add_argument(
        "--companion-set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="one more companion setting, as `cloudtrack-companion run --set` takes it (repeatable), e.g. "
        "mavlink.use_mavsdk=true to fly PX4 through MAVSDK",
    )
    run.add_argument("--seed", type=int, default=1, help="world seed (default 1)")
    run.add_argument(
        "--place",
        choices=("fixed", "random"),
        default="fixed",
        help="the search scenario's people where the scenario puts them (fixed, default) or anywhere in the "
        "survey area, standing or lying, seeded by the seed (random: the detector then misses as the "
        "detection curve says and the survey is flown to its end, looking only)",
    )
    run.add_argument(
        "--seeds",
        metavar="N-M",
        help="a batch: run the scenario once per seed (N-M or a comma list, one after another) and report "
        "per seed and over all (with --place random: found, the POD at the person, their agreement)",
    )
    run.add_argument("--json", type=Path, metavar="OUT", help="write the metrics JSON here")
    run.add_argument(
        "--video", type=Path, metavar="OUT.mp4", help="write the first vehicle's camera view with overlays"
    )
    run.add_argument("--plot", type=Path, metavar="OUT.png", help="write a top-down trajectory plot")
    run.add_argument(
        "--tracker", help="companion tracker (default: nano if its weights are installed, else csrt)"
    )
    run.add_argument(
        "--model-dir", type=Path, help="weights folder (default: $CLOUDTRACK_MODEL_DIR, then the cache)"
    )
    run.add_argument(
        "--verifier",
        choices=("local", "local-hsv", "none", "cascade"),
        help="back-end verifier on the rendered crops (default: the scenario's, the local person verifier; "
        "with --place random local-hsv, the colour rules on the box, which judge rendered people at every "
        "size the survey gives (docs/sitl.md says where not); cascade: the local one, then a VLM emulator "
        "on loopback answering --vlm-latency-s late)",
    )
    run.add_argument(
        "--vlm-latency-s",
        type=float,
        default=2.0,
        help="with --verifier cascade: the emulated hosted VLM's answer time (default 2)",
    )
    run.add_argument(
        "--supervisor-delay-s",
        type=float,
        metavar="S",
        help="the scripted supervisor decides this long after a candidate is reported (default: the "
        "scenario's, 1 s); longer, a survey looking only flies on and the find's position ages",
    )
    run.add_argument(
        "--work-dir",
        type=Path,
        help="keep companion logs, event files, flight records and the SITL's "
        "files here (default: a temp dir, removed after the run)",
    )
    run.set_defaults(func=_run)


def _autopilot_list(text: str) -> str:
    """NAME or NAME,NAME,...: each a mock personality or a real autopilot."""
    known = (*PERSONALITIES, *REAL_AUTOPILOTS)
    names = [n.strip() for n in text.split(",")]
    bad = [n for n in names if n not in known]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"invalid choice: {', '.join(map(repr, bad)) or repr(text)} (choose from {', '.join(known)}, "
            "or a comma list of them, one per vehicle)"
        )
    return ",".join(names)


def _run(args: argparse.Namespace) -> int:
    from sitl.scenario_runner import RunOptions, run_scenario
    from sitl.scenarios import placed

    options = RunOptions(
        autopilot=args.autopilot,
        seed=args.seed,
        json_out=args.json,
        video_out=args.video,
        plot_out=args.plot,
        tracker=args.tracker,
        model_dir=args.model_dir,
        work_dir=args.work_dir,
        verifier=args.verifier,
        vlm_latency_s=args.vlm_latency_s,
        arducopter_binary=args.arducopter_binary,
        px4_package=args.px4_package,
        companion_settings=tuple(args.companion_set),
        speedup=args.speedup,
    )
    try:
        scenario = placed(SCENARIOS[args.scenario], args.place)
    except ValueError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    if args.autopilot is not None:
        from sitl.scenarios import autopilot_names

        try:
            autopilot_names(scenario, args.autopilot)
        except ValueError as exc:
            print(str(exc), file=sys.stderr)
            return 2
    if args.supervisor_delay_s is not None:
        if not 0.0 <= args.supervisor_delay_s <= 600.0:
            print(f"--supervisor-delay-s must be 0-600 s, not {args.supervisor_delay_s:g}", file=sys.stderr)
            return 2
        scenario = replace(scenario, supervisor_delay_s=args.supervisor_delay_s)
    if args.seeds is not None:
        return _run_batch(args, scenario, options)
    try:
        results = run_scenario(scenario, options, progress=lambda line: print(line, flush=True))
    except (RuntimeError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print()
    for line in summary_lines(results, scenario):
        print(line)
    for label, path in (("metrics", args.json), ("video", args.video), ("plot", args.plot)):
        if path is not None:
            print(f"  {label}: {path}")
    return 0 if results["outcome"] == "pass" else 1


def _run_batch(args: argparse.Namespace, scenario: Scenario, options: RunOptions) -> int:
    """`run --seeds`: one run per seed, one after another; the batch's JSON (runs, totals, each result)."""
    from sitl.pod_batch import format_totals, parse_seeds, run_batch
    from sitl.scenario_runner import run_scenario

    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as exc:
        print(str(exc), file=sys.stderr)
        return 2
    if args.video is not None or args.plot is not None:
        print("--video and --plot take one run: give --seed, not --seeds", file=sys.stderr)
        return 2

    def one(seed: int) -> dict[str, Any]:
        work = None if options.work_dir is None else options.work_dir / f"seed-{seed}"
        quiet = replace(options, seed=seed, json_out=None, work_dir=work)
        return run_scenario(scenario, quiet, progress=lambda line: None)

    print(
        f"{scenario.name} (place {scenario.place}) over seeds {args.seeds}: one run after another", flush=True
    )
    batch = run_batch(one, seeds, progress=lambda line: print(line, flush=True))
    verifier = options.verifier or scenario.verifier
    batch = {"scenario": scenario.name, "place": scenario.place, "verifier": verifier, **batch}
    print(format_totals(batch["totals"]))
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(batch, indent=2))
        print(f"  batch: {args.json}")
    return 0 if all(line["outcome"] == "pass" for line in batch["runs"]) else 1


def _list(args: argparse.Namespace) -> int:
    if args.json:
        print(json.dumps({name: s.summary for name, s in SCENARIOS.items()}, indent=2))
        return 0
    for name, s in SCENARIOS.items():
        print(f"{name:<15} {s.autopilot:<10} {s.summary}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser, subparsers = new_parser(
        "cloudtrack-sim",
        "CloudTrack software-in-the-loop: mock autopilot, synthetic camera world, closed-loop scenarios.",
        EXAMPLES,
    )
    _add_run(subparsers)
    listing = subparsers.add_parser(
        "list",
        help="list the scenarios",
        epilog="examples:\n  cloudtrack-sim list\n  cloudtrack-sim list --json",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    listing.add_argument("--json", action="store_true", help="as a JSON object name -> summary")
    listing.set_defaults(func=_list)
    add_command_modules(subparsers, ("sitl.autopilot_command", "sitl.up_command"))
    from sitl import camera_command

    camera_command.add_parsers(subparsers)  # `camera` and `bench`
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    return run(build_parser, argv)


if __name__ == "__main__":
    sys.exit(main())
