"""`cloudtrack-sim autopilot`: the mock autopilot alone, for trying the companion or a GCS by hand."""

from __future__ import annotations

import argparse
import logging
import signal
import threading

from cloudtrack.stop_signals import set_on_signals
from sitl.autopilot import PERSONALITIES, AutopilotOptions, SimulatedAutopilot
from sitl.vehicle_dynamics import Wind

EXAMPLES = """\
examples:
  cloudtrack-sim autopilot
      ArduCopter personality; GCS link udpout:127.0.0.1:14550 (MAVProxy/QGC listen there),
      companion link udpout:127.0.0.1:14540 (cloudtrack-companion's default udpin:127.0.0.1:14540)
  cloudtrack-sim autopilot --autopilot px4 --gcs udpin:0.0.0.0:14560 --companion tcpin:0.0.0.0:5760
  cloudtrack-sim autopilot --guid-timeout 1 --wind 0 4     # short GUID_TIMEOUT, 4 m/s wind towards east
  mavproxy.py --master udpin:0.0.0.0:14550      # then: mode GUIDED, mode BRAKE, ...
"""

log = logging.getLogger(__name__)
DEFAULT_HEIGHT_M = AutopilotOptions.start_height_m


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "autopilot",
        help="run the mock MAVLink autopilot (ArduCopter or PX4 personality) on its own",
        description=(
            f"Run the simulated autopilot: armed and hovering at {DEFAULT_HEIGHT_M:g} m (--height), routing "
            "MAVLink between a GCS link and a companion link. It never arms for anyone. Stop with Ctrl-C."
        ),
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--autopilot", choices=PERSONALITIES, default="ardupilot", help="personality (default ardupilot)"
    )
    parser.add_argument(
        "--gcs",
        default="udpout:127.0.0.1:14550",
        metavar="URL",
        help="GCS link (pymavlink connection string)",
    )
    parser.add_argument(
        "--companion",
        default="udpout:127.0.0.1:14540",
        metavar="URL",
        help="companion link (pymavlink connection string)",
    )
    parser.add_argument(
        "--guid-timeout", type=float, default=3.0, metavar="S", help="ArduCopter GUID_TIMEOUT (default 3)"
    )
    parser.add_argument(
        "--offboard-loss", type=float, default=1.0, metavar="S", help="PX4 COM_OF_LOSS_T (default 1)"
    )
    parser.add_argument(
        "--wind", type=float, nargs=2, default=(0.0, 0.0), metavar=("N", "E"),
        help="steady wind towards north and east in m/s, 80%% rejected by the position controller (default 0 0)",
    )  # fmt: skip
    parser.add_argument(
        "--height",
        type=float,
        default=DEFAULT_HEIGHT_M,
        metavar="M",
        help=f"start hovering this high above home (default {DEFAULT_HEIGHT_M:g})",
    )
    parser.add_argument(
        "--duration", type=float, default=0.0, metavar="S", help="stop after S seconds (0: run until Ctrl-C)"
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    options = AutopilotOptions(
        personality=args.autopilot, guid_timeout_s=args.guid_timeout, offboard_loss_s=args.offboard_loss,
        wind=Wind(north=args.wind[0], east=args.wind[1]), start_height_m=args.height,
    )  # fmt: skip
    try:
        sim = SimulatedAutopilot(options, {"gcs": args.gcs, "companion": args.companion})
    except (OSError, ValueError) as exc:
        print(f"error: cannot open the autopilot links: {exc}")
        return 2
    stop = threading.Event()
    set_on_signals(stop, (signal.SIGTERM,))
    sim.start()
    print(
        f"{args.autopilot} autopilot simulator: gcs={args.gcs} companion={args.companion} (Ctrl-C stops)",
        flush=True,
    )
    try:
        stop.wait(args.duration if args.duration > 0 else None)
    except KeyboardInterrupt:
        pass
    finally:
        sim.close()
    return 0
