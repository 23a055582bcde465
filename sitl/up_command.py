"""`cloudtrack-sim up`: the whole product on one machine, wired together, for a person to drive by hand.

It starts the real back-end (the simulated person detector on the rendered world, the local verifier, a
vehicle token and a supervisor token), an autopilot (the mock's ArduCopter or PX4 personality, hovering at
10 m, or the real ArduCopter SITL with `--autopilot arducopter`, the real PX4 SITL with `px4-sitl`), the
camera world rendered from the autopilot's pose, and the real companion process; then prints the supervisor
page's address, which world it renders (for the search world: its area and the survey altitude and range
that suit the camera) and the `cloudtrack-gcs` commands to type. Ctrl-C (or SIGTERM) stops everything it
started.

The autopilot serves ground stations on a UDP port (`--gcs-port`, 14550): any number of tools connect to
it (`cloudtrack-gcs --connect udpout:127.0.0.1:14550`, MAVProxy `--master udpout:...`, a QGroundControl
UDP link to that address), so `watch` and `confirm` can run side by side. The supervisor's token is
written to a file in the work folder (mode 0600), never printed. docs/quickstart.md walks through it.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from cloudtrack.stop_signals import set_on_signals
from sitl.camera_command import is_mission_start

EXAMPLES = """\
examples:
  cloudtrack-sim up                                   # mock ArduCopter, the 'follow' world
  cloudtrack-sim up --autopilot px4                   # the mock's PX4 personality
  cloudtrack-sim up --autopilot arducopter            # the real ArduCopter SITL (../shared/sitl/arducopter)
  cloudtrack-sim up --autopilot px4-sitl              # the real PX4 SITL (../shared/sitl/px4)
  cloudtrack-sim up --scenario search                 # the search world: survey it, then start the mission
  cloudtrack-sim up --backend-port 8081 --gcs-port 14560 --work-dir out/up
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    parser = subparsers.add_parser(
        "up",
        help="start back-end, autopilot, camera world and companion, wired together, to drive by hand",
        description="Start the back-end (with tokens), an autopilot (mock or the real ArduCopter SITL), the "
        "camera world and the companion on this machine; print the supervisor page's address and the "
        "cloudtrack-gcs commands to type. Ctrl-C stops everything. docs/quickstart.md walks through it.",
        epilog=EXAMPLES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "--autopilot",
        choices=("mock", "px4", "arducopter", "px4-sitl"),
        default="mock",
        help="mock (the mock autopilot's ArduCopter personality, the default), px4 (its PX4 personality), "
        "arducopter (the real ArduCopter SITL binary, see --arducopter-binary) or px4-sitl (the real PX4 "
        "SITL, see --px4-package)",
    )
    parser.add_argument("--arducopter-binary", type=Path, metavar="PATH", help="as for `cloudtrack-sim run`")
    parser.add_argument("--px4-package", type=Path, metavar="PATH", help="as for `cloudtrack-sim run`")
    parser.add_argument(
        "--scenario",
        default="follow",
        help="whose world to render (default follow; search: the area-search world, see docs/quickstart.md)",
    )
    parser.add_argument("--seed", type=int, default=1, help="world seed (default 1)")
    parser.add_argument("--backend-port", type=int, default=8080, help="the back-end's port (default 8080)")
    parser.add_argument(
        "--gcs-port",
        type=int,
        default=14550,
        help="UDP port the autopilot serves ground stations on (default 14550)",
    )
    parser.add_argument(
        "--tracker", help="companion tracker (default: nano if its weights are installed, else csrt)"
    )
    parser.add_argument(
        "--model-dir", type=Path, help="weights folder (default: $CLOUDTRACK_MODEL_DIR, then the cache)"
    )
    parser.add_argument(
        "--work-dir",
        type=Path,
        help="keep the logs, the flight record and the token here (default: a temp dir, removed on exit)",
    )
    parser.set_defaults(func=run_up)


def run_up(args: argparse.Namespace) -> int:
    from sitl.scenarios import SCENARIOS

    if args.scenario not in SCENARIOS:
        print(f"error: unknown world {args.scenario!r}; known: {', '.join(SCENARIOS)}", file=sys.stderr)
        return 2
    stack = LocalStack(args)
    stop = threading.Event()
    set_on_signals(stop)
    try:
        stack.start()
    except (RuntimeError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        stack.stop()
        return 2
    print(stack.instructions(), flush=True)
    code = 0
    try:
        while not stop.wait(1.0):
            if stack.companion_exited():
                print(f"error: the companion exited; its log: {stack.companion_log}", file=sys.stderr)
                code = 1
                break
    finally:
        print("stopping ...", flush=True)
        stack.stop()
        print("stopped", flush=True)
    return code


class LocalStack:
    """The back-end, the autopilot, the camera world and the companion of one vehicle, on loopback."""

    def __init__(self, args: argparse.Namespace) -> None:
        from sitl.scenarios import SCENARIOS

        self.args = args
        self.scenario = SCENARIOS[args.scenario]
        self._own_work = args.work_dir is None
        self.work: Path = args.work_dir or Path(tempfile.mkdtemp(prefix="cloudtrack-sim-up-"))
        self.work.mkdir(parents=True, exist_ok=True)
        self.vehicle_id = "drone-1"
        self.vehicle_token = secrets.token_hex(16)
        self.supervisor_token = secrets.token_hex(16)
        self.token_file = self.work / "supervisor-token"
        self.companion_log = self.work / "companion.log"
        self.backend_url = f"http://127.0.0.1:{args.backend_port}"
        self._parts: list[Any] = []  # stopped in reverse order
        self._companion: subprocess.Popen[bytes] | None = None
        self.autopilot_text = ""
        self.px4: Any = None  # the real PX4 (px4-sitl)
        self.world_extras: dict[str, Any] = {}
        self.system_id = 1  # PX4 SITL instance N is system N+1
        self.survey_config = self.work / "survey-camera.toml"

    def start(self) -> None:
        from behaviors.camera_model import CameraModel
        from sitl.camera_server import CameraServer, PoseFollower
        from sitl.scenario_runner import MOUNT_PITCH_DEG, VEHICLE_ORIGINS

        fd = os.open(self.token_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(self.supervisor_token + "\n")
        origin = VEHICLE_ORIGINS[0]
        world = self.scenario.build_world(self.args.seed)
        self.world_extras = world.extras
        camera_model = CameraModel.from_hfov(640, 480, 70.0, MOUNT_PITCH_DEG, stabilised=True)
        camera_url, companion_link = self._start_autopilot(origin)
        cameras: list[Any] = []

        def on_text(text: str) -> None:
            # People hold their start positions until the mission starts (as `cloudtrack-sim camera`).
            if cameras and is_mission_start(text) and math.isinf(cameras[0].epoch):
                cameras[0].epoch = time.monotonic()

        if self.px4 is not None:
            pose = self.px4.camera_pose(origin).pose
            self._parts.append(_TextWatch(self.px4.gcs, on_text).start())
        else:
            follower = PoseFollower(camera_url, origin=origin, on_text=on_text).start()
            self._parts.append(follower)
            pose = follower.pose
        camera = CameraServer(world, camera_model, pose, fps=30.0)
        camera.epoch = math.inf
        cameras.append(camera)
        self._start_backend(camera.truth, camera_model.width)
        camera.start()
        self._parts.append(camera)
        if self.scenario.survey is not None:
            # What `cloudtrack-gcs survey --companion-config` needs to size the lanes as the companion sees.
            self.survey_config.write_text(
                f"[camera]\nhfov_deg = 70.0\nmount_pitch_deg = {MOUNT_PITCH_DEG}\n"
                f"search_range_m = {self.scenario.survey.search_range_m:g}\n"
            )
        self._start_companion(camera.url, companion_link)

    def _start_backend(self, truth: Any, width: int) -> None:
        from backend.app import create_app
        from backend.config import AuthConfig, BackendConfig, ServerConfig, SessionConfig
        from backend.serving import BackgroundServer
        from sitl.simulated_detector import DetectorNoise, SimulatedPersonDetector

        config = BackendConfig(
            server=ServerConfig(port=self.args.backend_port),
            auth=AuthConfig(
                tokens={self.vehicle_id: self.vehicle_token}, supervisor_token=self.supervisor_token
            ),
            sessions=SessionConfig(sqlite_path=str(self.work / "sessions.sqlite3")),
        )
        survey = self.scenario.survey
        noise = DetectorNoise(
            miss_rate=self.scenario.miss_rate,
            look_range_m=survey.search_range_m if survey and self.scenario.detector_in_range else None,
        )
        detector = SimulatedPersonDetector(truth, width, noise, seed=self.args.seed)
        app = create_app(config, detector=detector)
        try:
            server = BackgroundServer(app, port=self.args.backend_port).start()
        except RuntimeError:
            raise RuntimeError(
                f"the back-end could not listen on 127.0.0.1:{self.args.backend_port} (in use?); "
                "choose another with --backend-port"
            ) from None
        self._parts.append(server)

    def _start_autopilot(self, origin: tuple[float, float]) -> tuple[str, str]:
        """The camera's and the companion's MAVLink addresses."""
        from sitl.autopilot_mission import MissionOptions
        from sitl.scenario_runner import ALTITUDE_M, GUID_TIMEOUT_S, _home

        lat, lon = _home(origin)
        gcs = f"udpin:127.0.0.1:{self.args.gcs_port}"
        if self.args.autopilot == "arducopter":
            return self._start_arducopter(lat, lon)
        if self.args.autopilot == "px4-sitl":
            return self._start_px4(lat, lon)
        from sitl.autopilot import AutopilotOptions, SimulatedAutopilot

        personality = "px4" if self.args.autopilot == "px4" else "ardupilot"
        survey = self.scenario.survey
        options = AutopilotOptions(
            personality=personality, start_height_m=ALTITUDE_M, home_lat=lat, home_lon=lon,
            guid_timeout_s=GUID_TIMEOUT_S,
            # The survey's speed, after a resume too (WPNAV_SPEED / MPC_XY_CRUISE).
            mission=MissionOptions(speed_m_s=survey.speed_m_s if survey is not None else None),
        )  # fmt: skip
        links = {"gcs": gcs, "companion": "udpin:127.0.0.1:0", "camera": "udpin:127.0.0.1:0"}
        try:
            autopilot = SimulatedAutopilot(options, links)
        except OSError as exc:
            raise RuntimeError(
                f"cannot open the GCS port {self.args.gcs_port} ({exc}); choose another with --gcs-port"
            ) from None
        autopilot.start()
        self._parts.append(autopilot)
        name = "PX4" if personality == "px4" else "ArduCopter"
        self.autopilot_text = f"mock autopilot ({name} personality), armed and hovering at {ALTITUDE_M:g} m"
        return (
            f"udpout:127.0.0.1:{autopilot.link_port('camera')}",
            f"udpout:127.0.0.1:{autopilot.link_port('companion')}",
        )

    def _start_arducopter(self, lat: float, lon: float) -> tuple[str, str]:
        from sitl.arducopter_sitl import ArduCopterSitl, RealAutopilot, find_binary
        from sitl.scenario_runner import ALTITUDE_M, HOME_ALT_M
        from sitl.scenarios import ScriptedGcs

        binary = find_binary(self.args.arducopter_binary)
        survey = self.scenario.survey
        # AUTO flies at WPNAV_SPEED (cm/s) after a resume: the survey's DO_CHANGE_SPEED no longer holds.
        params = {"WPNAV_SPEED": survey.speed_m_s * 100.0} if survey is not None else {}
        sitl = ArduCopterSitl(
            binary, self.work / "arducopter", (lat, lon, HOME_ALT_M, 0.0), speedup=5.0, extra_params=params
        ).start()
        self._parts.append(sitl)
        print(f"ArduCopter SITL {binary}: arming and taking off to {ALTITUDE_M:g} m ...", flush=True)
        pilot = ScriptedGcs(f"tcp:127.0.0.1:{sitl.ports.gcs}").start()
        self._parts.append(pilot)
        autopilot = RealAutopilot(sitl, pilot)
        self._parts.append(autopilot)
        autopilot.fly_up(ALTITUDE_M, progress=lambda line: print(line, flush=True))
        relay = UdpTcpRelay(self.args.gcs_port, sitl.ports.ground).start()  # SERIAL5: the ground tools
        self._parts.append(relay)
        self.autopilot_text = f"ArduCopter SITL ({binary}), armed and hovering at {ALTITUDE_M:g} m in GUIDED"
        return f"tcp:127.0.0.1:{sitl.ports.camera}", f"udpout:127.0.0.1:{autopilot.bridge.udp_port}"

    def _start_px4(self, lat: float, lon: float) -> tuple[str, str]:
        from sitl.px4_sitl import find_package, start_px4
        from sitl.scenario_runner import ALTITUDE_M, HOME_ALT_M

        package = find_package(self.args.px4_package)
        print(f"PX4 SITL {package}: booting, arming and taking off to {ALTITUDE_M:g} m ...", flush=True)
        px4 = start_px4(package, self.work / "px4", (lat, lon, HOME_ALT_M), None)
        self.px4 = px4
        self._parts.append(px4)
        self._parts.append(px4.gcs)  # stopped before the PX4 (reverse order)
        px4.fly_up(ALTITUDE_M, progress=lambda line: print(line, flush=True))
        # PX4's second GCS link, forwarding to and from the companion: the ground tools' link.
        ground = px4.sitl.start_ground_link(forward=True)
        relay = UdpUdpRelay(self.args.gcs_port, ground, px4.sitl.ports.ground).start()
        self._parts.append(relay)
        self.system_id = px4.system_id
        self.autopilot_text = (
            f"PX4 SITL ({package}, system id {px4.system_id}), armed and hovering at {ALTITUDE_M:g} m in HOLD"
        )
        return "", f"udpout:127.0.0.1:{px4.bridge.udp_port}"

    def _start_companion(self, camera_url: str, link: str) -> None:
        from cloudtrack.model_store import resolve_model_dir
        from sitl.scenario_runner import MOUNT_PITCH_DEG, STANDOFF_M, default_tracker

        model_dir = resolve_model_dir(self.args.model_dir)
        posture = self.world_extras.get("target_posture")
        settings = [
            f"vehicle.id={self.vehicle_id}",
            f"camera.source={camera_url}",
            f"camera.mount_pitch_deg={MOUNT_PITCH_DEG}",
            "camera.hfov_deg=70.0",
            f"mavlink.connection={link}",
            f"mavlink.target_system={self.system_id}",
            f"backend.url={self.backend_url}",
            f"tracker.name={self.args.tracker or default_tracker(model_dir)}",
            f"tracker.model_dir={model_dir}",
            f"behavior.standoff_m={STANDOFF_M}",
            f"recording.dir={self.work / 'records'}",
            *([f"search.posture={posture}"] if posture else []),
            *self.scenario.companion_settings,  # the search world's search range
        ]
        command = [sys.executable, "-m", "companion.cli", "--log-level", "INFO", "run"]
        for setting in settings:
            command += ["--set", setting]
        env = dict(os.environ, CLOUDTRACK_BACKEND__TOKEN=self.vehicle_token, PYTHONUNBUFFERED="1")
        env.pop("NOTIFY_SOCKET", None)
        with open(self.companion_log, "wb") as log:
            self._companion = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env)

    def companion_exited(self) -> bool:
        return self._companion is not None and self._companion.poll() is not None

    def instructions(self) -> str:
        connect = f"--connect udpout:127.0.0.1:{self.args.gcs_port}"
        if self.system_id != 1:
            connect += f" --system {self.system_id}"
        # PX4 hovers in HOLD/POSCTL: the companion may only fly once OFFBOARD is selected, which the start allows.
        px4 = self.args.autopilot in ("px4", "px4-sitl")
        survey = self.scenario.survey
        engage = " --allow-engage" if px4 or survey is not None else ""
        start = (
            f'  cloudtrack-gcs {connect} start --prompt "{self.scenario.prompt}" --superset person{engage}'
        )
        lines = [
            "CloudTrack is up on this machine (Ctrl-C stops everything):",
            f"  supervisor page  {self.backend_url}/supervisor",
            f"                   its token: cat {self.token_file}",
            f"  autopilot        {self.autopilot_text}; ground stations: udp 127.0.0.1:{self.args.gcs_port}",
            f"  camera world     '{self.scenario.name}' (seed {self.args.seed}): {self.scenario.prompt} among others",
        ]
        if survey is None:
            lines += [
                f"  companion        {self.vehicle_id}, log {self.companion_log}",
                "",
                "In another shell (source .venv/bin/activate), as the ground station:",
                start,
                f"  cloudtrack-gcs {connect} watch --until-candidate   # until a candidate awaits you",
                f"  cloudtrack-gcs {connect} status",
                f"  cloudtrack-gcs {connect} confirm        # the candidate awaiting the supervisor",
                f"  cloudtrack-gcs {connect} abort",
                "or confirm on the supervisor page.",
            ]
            return "\n".join(lines)
        from sitl.scenario_runner import VEHICLE_ORIGINS, _home

        (s_n, w_e), (n_n, e_e) = survey.area_ne
        o_n, o_e = VEHICLE_ORIGINS[0]
        lat, lon = _home((o_n + (s_n + n_n) / 2.0, o_e + (w_e + e_e) / 2.0))
        mode = "MISSION" if px4 else "AUTO"
        size = f"{e_e - w_e:g}x{n_n - s_n:g}"
        lines += [
            f"  search area      {size} m (east-west x north-south), {s_n:g}-{n_n:g} m north of home, centre "
            f"{lat:.6f},{lon:.6f}",
            f"  survey           at {survey.altitude_m:g} m with a {survey.search_range_m:g} m search range, "
            f"{survey.speed_m_s:g} m/s: the verifier judges a rendered person out to about 12 m from 10 m up "
            "(a survey at 20 m found nobody it would accept)",
            f"  companion        {self.vehicle_id}, search range {survey.search_range_m:g} m, log {self.companion_log}",
            "",
            "In another shell (source .venv/bin/activate), as the ground station:",
            f"  cloudtrack-gcs {connect} survey --centre {lat:.6f},{lon:.6f} --size {size} --altitude "
            f"{survey.altitude_m:g} --speed {survey.speed_m_s:g} --overlap {survey.overlap:g} "
            f"--companion-config {self.survey_config}",
            f"  cloudtrack-gcs {connect} mode {mode}          # the autopilot flies the survey",
            start,
            f"  cloudtrack-gcs {connect} watch --until-candidate   # until a candidate awaits you",
            f"  cloudtrack-gcs {connect} reject         # a look-alike: the survey resumes where it broke off",
            f"  cloudtrack-gcs {connect} confirm        # the described person",
            "or decide on the supervisor page.",
        ]
        return "\n".join(lines)

    def stop(self) -> None:
        companion = self._companion
        if companion is not None and companion.poll() is None:
            companion.send_signal(signal.SIGTERM)
            try:
                companion.wait(timeout=15)
            except subprocess.TimeoutExpired:
                companion.kill()
                companion.wait()
        for part in reversed(self._parts):
            stop = getattr(part, "stop", None) or getattr(part, "close", None)
            if stop is not None:
                try:
                    stop()
                except Exception as exc:  # stopping the rest matters more
                    print(f"warning: stopping {type(part).__name__}: {exc}", file=sys.stderr)
        self._parts.clear()
        if self._own_work:
            import shutil

            shutil.rmtree(self.work, ignore_errors=True)


class _GroundRelay:
    """Ground stations on a UDP port (any number: each sender is remembered) to one autopilot link and
    back; the link's kind is the subclass's (`_send`, `_receive`, `_close_link`)."""

    def __init__(self, udp_port: int) -> None:
        import socket

        self._udp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._udp.bind(("127.0.0.1", udp_port))
        self._udp.settimeout(0.2)
        self._clients: set[tuple[str, int]] = set()
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._uplink, name="gcs-relay-up", daemon=True),
            threading.Thread(target=self._downlink, name="gcs-relay-down", daemon=True),
        ]

    def start(self) -> _GroundRelay:
        for thread in self._threads:
            thread.start()
        return self

    def _send(self, data: bytes) -> bool:
        """To the autopilot; False when the link is gone for good."""
        raise NotImplementedError

    def _receive(self) -> bytes | None:
        """From the autopilot: b"" when nothing came this time, None when the link is gone for good."""
        raise NotImplementedError

    def _close_link(self) -> None:
        raise NotImplementedError

    def _uplink(self) -> None:
        while not self._stop.is_set():
            try:
                data, sender = self._udp.recvfrom(65536)
            except OSError:
                continue
            self._clients.add(sender)
            if not self._send(data):
                return

    def _downlink(self) -> None:
        while not self._stop.is_set():
            data = self._receive()
            if data is None:
                return
            for client in list(self._clients) if data else ():
                try:
                    self._udp.sendto(data, client)
                except OSError:
                    self._clients.discard(client)

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2)
        self._udp.close()
        self._close_link()


class UdpTcpRelay(_GroundRelay):
    """Ground stations to one TCP serial port of the SITL, bytes as they come: MAVLink parsers read a
    stream, whichever way it was cut."""

    def __init__(self, udp_port: int, tcp_port: int) -> None:
        import socket

        super().__init__(udp_port)
        self._tcp = socket.create_connection(("127.0.0.1", tcp_port), timeout=10)
        self._tcp.settimeout(0.2)

    def _send(self, data: bytes) -> bool:
        try:
            self._tcp.sendall(data)
        except OSError:
            return False
        return True

    def _receive(self) -> bytes | None:
        try:
            return self._tcp.recv(65536) or None
        except TimeoutError:
            return b""
        except OSError:
            return None

    def _close_link(self) -> None:
        self._tcp.close()


class UdpUdpRelay(_GroundRelay):
    """Ground stations to PX4's second GCS link, which sends to `local_port` from `remote_port`: datagrams
    as they come."""

    def __init__(self, udp_port: int, local_port: int, remote_port: int) -> None:
        import socket

        super().__init__(udp_port)
        self._px4 = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._px4.bind(("127.0.0.1", local_port))
        self._px4.settimeout(0.2)
        self._remote = ("127.0.0.1", remote_port)

    def _send(self, data: bytes) -> bool:
        with contextlib.suppress(OSError):  # PX4 not listening yet: the next datagram may get through
            self._px4.sendto(data, self._remote)
        return True

    def _receive(self) -> bytes | None:
        try:
            return self._px4.recv(65536)
        except OSError:
            return b""

    def _close_link(self) -> None:
        self._px4.close()


class _TextWatch:
    """The scripted pilot's STATUSTEXT lines to `on_text` (PX4: the camera follows SIH's truth, not a link)."""

    def __init__(self, gcs: Any, on_text: Any) -> None:
        self._gcs = gcs
        self._on_text = on_text
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="px4-texts", daemon=True)

    def start(self) -> _TextWatch:
        self._thread.start()
        return self

    def _run(self) -> None:
        seen = 0
        while not self._stop.wait(0.1):
            texts = list(self._gcs.statustexts)
            for _, text in texts[seen:]:
                self._on_text(text)
            seen = len(texts)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
