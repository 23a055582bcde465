"""`cloudtrack-sim camera` and `cloudtrack-sim bench`: the synthetic camera on its own, and its render speed.

`camera` follows any autopilot over MAVLink (`--autopilot-url`: the mock, or a real ArduPilot/PX4 SITL
through a spare MAVLink output) and serves frames on sim+tcp://; with `--backend-port` it also runs the
real back-end with the simulated person detector on this world, so a companion started by hand
(`cloudtrack-companion run --set camera.source=sim+tcp://...`) closes the loop with that autopilot.
"""

from __future__ import annotations

import argparse
import math
import re
import signal
import sys
import threading
import time

from behaviors.camera_model import CameraModel
from cloudtrack.stop_signals import set_on_signals

CAMERA_EXAMPLES = """\
examples:
  cloudtrack-sim camera --autopilot-url udpin:0.0.0.0:14551 --port 5600
      (ArduPilot SITL: sim_vehicle.py ... --out udp:127.0.0.1:14551)
  cloudtrack-sim camera --autopilot-url tcp:127.0.0.1:5762 --port 5600 --backend-port 8080 --token "$(openssl rand -hex 24)"
  cloudtrack-companion run --set camera.source=sim+tcp://127.0.0.1:5600 --set backend.url=http://127.0.0.1:8080
"""
BENCH_EXAMPLES = """\
examples:
  cloudtrack-sim bench
  cloudtrack-sim bench --frames 600 --width 1280 --height 720
"""


def add_parsers(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    cam = subparsers.add_parser(
        "camera",
        help="serve the synthetic camera, following an autopilot's pose over MAVLink",
        description="Render the scenario world from the pose an autopilot reports (ATTITUDE, LOCAL_POSITION_NED) "
        "and serve 640x480 frames on sim+tcp://HOST:PORT. Stop with Ctrl-C.",
        epilog=CAMERA_EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    cam.add_argument(
        "--autopilot-url", required=True, metavar="URL", help="pymavlink connection to the autopilot"
    )
    cam.add_argument("--host", default="127.0.0.1", help="address to serve frames on (default 127.0.0.1)")
    cam.add_argument("--port", type=int, default=5600, help="sim+tcp port (default 5600)")
    cam.add_argument("--scenario", default="follow", help="whose world to render (default follow)")
    cam.add_argument("--seed", type=int, default=1)
    cam.add_argument(
        "--mount-pitch", type=float, default=-40.0, metavar="DEG", help="camera pitch (default -40)"
    )
    cam.add_argument(
        "--backend-port", type=int, help="also run the back-end (simulated detector) on this port"
    )
    cam.add_argument(
        "--token",
        default="sim-camera-vehicle-token",
        help="bearer token the back-end accepts for the vehicle (16+ characters)",
    )
    cam.add_argument(
        "--vehicle-id", default="drone-1", help="vehicle id the token is issued to (default drone-1)"
    )
    cam.add_argument(
        "--world-start",
        choices=("mission", "now"),
        default="mission",
        help="when the people start walking: 'mission' (default) holds them at their start until the "
        "companion's 'MISSION n STARTED' STATUSTEXT is heard on the link, so boot and take-off do not "
        "lose the target; 'now' starts them with the camera",
    )
    cam.set_defaults(func=run_camera)
    bench = subparsers.add_parser(
        "bench",
        help="measure the renderer's frame rate",
        description="Render FRAMES frames of the follow world along a moving pose and print frames per second "
        "(render only, and render + the sim+tcp packet).",
        epilog=BENCH_EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    bench.add_argument("--frames", type=int, default=300, help="frames to render (default 300)")
    bench.add_argument("--width", type=int, default=640, help="image width in pixels (default 640)")
    bench.add_argument("--height", type=int, default=480, help="image height in pixels (default 480)")
    bench.set_defaults(func=run_bench)


MISSION_START = re.compile(r"\bMISSION \d+ STARTED\b")


def is_mission_start(text: str) -> bool:
    """The companion's STATUSTEXT on a GCS mission start (cloudtrack/gcs_protocol.py), broadcast to every link."""
    return MISSION_START.search(text) is not None


def run_camera(args: argparse.Namespace) -> int:
    from sitl.camera_server import CameraServer, PoseFollower
    from sitl.scenarios import SCENARIOS

    if args.scenario not in SCENARIOS:
        print(f"error: unknown scenario {args.scenario!r}; known: {', '.join(SCENARIOS)}")
        return 2
    if args.backend_port is not None:
        from backend.config import MIN_TOKEN_CHARS

        if len(args.token) < MIN_TOKEN_CHARS:  # the back-end refuses it: say so before anything starts
            print(
                f"error: --token must be at least {MIN_TOKEN_CHARS} characters (got {len(args.token)}); "
                'e.g. --token "$(openssl rand -hex 24)"',
                file=sys.stderr,
            )
            return 2
    world = SCENARIOS[args.scenario].build_world(args.seed)
    camera = CameraModel.from_hfov(640, 480, 70.0, args.mount_pitch)
    servers: list[CameraServer] = []

    def on_text(text: str) -> None:
        if servers and is_mission_start(text) and math.isinf(servers[0].epoch):
            servers[0].epoch = time.monotonic()
            print(f"mission started ({text!r}): the people start walking", flush=True)

    try:
        follower = PoseFollower(args.autopilot_url, on_text=on_text).start()
        server = CameraServer(world, camera, follower.pose, host=args.host, port=args.port)
        if args.world_start == "mission":
            server.epoch = math.inf  # world time stays 0 until the mission starts
        servers.append(server.start())
    except (OSError, ValueError) as exc:
        print(f"error: {exc}")
        return 2
    if args.world_start == "mission":
        print("people hold their start positions until the companion reports 'MISSION n STARTED'", flush=True)
    backend = None
    if args.backend_port is not None:
        from backend.app import create_app
        from backend.config import AuthConfig, BackendConfig, ServerConfig, SessionConfig
        from backend.serving import BackgroundServer
        from sitl.simulated_detector import SimulatedPersonDetector

        config = BackendConfig(
            server=ServerConfig(port=args.backend_port),
            auth=AuthConfig(tokens={args.vehicle_id: args.token}),
            sessions=SessionConfig(sqlite_path=":memory:"),
        )
        backend = BackgroundServer(
            create_app(config, detector=SimulatedPersonDetector(server.truth)), port=args.backend_port
        ).start()
        print(f"back-end (simulated person detector, local verifier): {backend.url}")
    print(f"camera: {server.url} following {args.autopilot_url} (Ctrl-C stops)", flush=True)
    stop = threading.Event()
    set_on_signals(stop, (signal.SIGTERM,))
    try:
        while not stop.wait(5.0):
            print(f"  {server.frames_rendered} frames, pose age {follower.age_s():.1f} s", flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()
        follower.stop()
        if backend is not None:
            backend.stop()
    return 0


def run_bench(args: argparse.Namespace) -> int:
    from sitl.camera_render import Renderer, VehiclePose
    from sitl.frame_transport import encode_frame
    from sitl.scenarios import SCENARIOS

    world = SCENARIOS["follow"].build_world(1)
    camera = CameraModel.from_hfov(args.width, args.height, 70.0, -40.0)
    renderer = Renderer(world, camera)
    poses = [VehiclePose(0.05 * i, 0.0, -10.0, 0.02, -0.05, 0.002 * i) for i in range(args.frames)]
    started = time.perf_counter()
    for i, pose in enumerate(poses):
        renderer.render(pose, i / 30.0, i)
    render_s = time.perf_counter() - started
    started = time.perf_counter()
    for i, pose in enumerate(poses):
        encode_frame(i, i / 30.0, 0.0, renderer.render(pose, i / 30.0, i).image)
    total_s = time.perf_counter() - started
    print(
        f"{args.width}x{args.height}, {args.frames} frames, {len(world.people)} people, {len(world.blocks)} blocks"
    )
    print(
        f"  render:           {args.frames / render_s:7.1f} FPS ({1000 * render_s / args.frames:.2f} ms/frame)"
    )
    print(
        f"  render + packet:  {args.frames / total_s:7.1f} FPS ({1000 * total_s / args.frames:.2f} ms/frame)"
    )
    return 0
