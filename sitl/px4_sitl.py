"""The real PX4 SITL (v1.16, SIH physics, no Gazebo) as the scenarios' autopilot: find it, start it, fly it.

`Px4Sitl` starts `bin/px4` of the shared package (../shared/sitl/px4, see its SOURCE.md) as `run-sih.sh`
does: airframe 10040 (SIH quadrotor X), a fresh work directory per run (parameters.bson, dataman, eeprom/),
parameters through the environment (`PX4_PARAM_<NAME>`), home where the scenario's vehicle starts. The
package's `px4-<module>` command links were flattened into 3-byte files when it was copied, so the work
directory gets its own `bin/` of symbolic links to the one binary (the start-up script calls `px4-param`
and friends through PATH).

Instance N (1-9, whichever is free) fixes every port (UDP, loopback):

    GCS link      PX4 18570+N; sends to the first local sender it hears, and to 14550 until then
    ground link   PX4 18590+N -> 18600+N: a second GCS link (the operator's laptop: `cloudtrack-gcs survey`
                  listens on 18600+N, `udpin`), started on first use
    onboard link  PX4 14580+N -> 14540+N: the companion, through `CompanionBridge`, which binds 14540+N
    SIH display   PX4 19450+N -> 19410+N: HIL_STATE_QUATERNION, SIH's ground truth, for the camera

and MAV_SYS_ID = N+1 (the start-up script sets it after the environment, so the companion and the GCS
address system N+1). Instance 0 is left alone: its onboard link sends to 14540, the companion's default
port; instances 10+ share 14549.

The GCS link's 14550: until a ground station speaks to 18570+N, PX4 streams to 127.0.0.1:14550, so
anything listening there (QGroundControl, `cloudtrack-gcs watch`, MAVProxy) sees this vehicle for a
moment, and a ground station that answers first becomes PX4's only GCS partner for good. The scripted
pilot therefore speaks to 18570+N from the moment the process starts (20 HEARTBEATs a second), and the
runner stops with a clear error when PX4 answers someone else.

`GroundTruthPose` reads SIH's ground truth: the camera renders the real vehicle while the companion sees
only PX4's estimate (EKF2), so geolocation error includes the estimator's.

The binary does not notice its parent dying, so it is started with PR_SET_PDEATHSIG: a crashed runner never
leaves a PX4 flying.
"""

from __future__ import annotations

import ctypes
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pymavlink import mavutil

from sitl.autopilot import PX4_MODES
from sitl.camera_render import VehiclePose
from sitl.companion_bridge import BridgedSetpoint, CompanionBridge
from sitl.shared_sitl import shared_sitl_path

log = logging.getLogger(__name__)

PACKAGE_ENV = "CLOUDTRACK_PX4"
AIRFRAME = 10040  # 10040_sihsim_quadx
INSTANCES = range(1, 10)
EARTH_RADIUS = 6_378_137.0
COM_OF_LOSS_T_S = 0.5  # docs/operations.md: offboard lost after 0.5 s of no setpoints
PX4_HOLD = 5  # COM_OBL_RC_ACT: Hold
RETURN_SPEED_M_S = 8.0  # the GCS's reposition back over home between scenarios
# The ground link's bytes/s (a telemetry radio's order): a mission upload needs little, and at the GCS link's
# 4 MB/s its streams would take CPU from the real-time SIH and the camera for nothing.
GROUND_LINK_RATE = 20_000
# What PX4's GCS link streams at ~45 Hz that the runner never reads (its own setpoint echo, attitude twice,
# the motors, the attitude target): stopped once the link is claimed.
TAKEOFF_DONE_WITHIN_M = 1.0  # PX4's NAV_MC_ALT_RAD (0.8 m) and the estimate's noise
GCS_STREAMS_UNREAD = (
    mavutil.mavlink.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED,
    mavutil.mavlink.MAVLINK_MSG_ID_ATTITUDE,
    mavutil.mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION,
    mavutil.mavlink.MAVLINK_MSG_ID_SERVO_OUTPUT_RAW,
    mavutil.mavlink.MAVLINK_MSG_ID_ATTITUDE_TARGET,
)


class Px4NotFound(RuntimeError):
    """The PX4 package is not where the runner looks: the message says where to put it."""


def default_package() -> Path:
    """$CLOUDTRACK_PX4, else $CLOUDTRACK_SHARED/sitl/px4, else ../shared/sitl/px4 beside the repository."""
    return shared_sitl_path(PACKAGE_ENV, "px4")


def find_package(override: Path | None = None) -> Path:
    """The package directory (bin/px4 and etc/init.d-posix/rcS); Px4NotFound says where to put it."""
    path = (override or default_package()).expanduser()
    binary = path / "bin" / "px4"
    if binary.is_file() and os.access(binary, os.X_OK) and (path / "etc" / "init.d-posix" / "rcS").is_file():
        return path.resolve()
    raise Px4NotFound(
        f"PX4 SITL package not found (or bin/px4 not executable) at {path}. Put the PX4 v1.16 SIH build "
        f"(bin/px4, etc/; x86-64 Linux, GLIBC >= 2.34; see ../shared/sitl/px4/SOURCE.md) at "
        f"../shared/sitl/px4 beside the repository, or point --px4-package or ${PACKAGE_ENV} at it. The run "
        f"does not fall back to the mock autopilot."
    )


def project_parameters() -> dict[str, float]:
    """What the runner sets through PX4_PARAM_*: the values docs/operations.md recommends, and the pilot's."""
    return {
        "COM_OF_LOSS_T": COM_OF_LOSS_T_S,
        "COM_OBL_RC_ACT": PX4_HOLD,
        "COM_RC_OVERRIDE": 3,  # the pilot's sticks take over from auto modes (bit 0) and from OFFBOARD (bit 1)
        "MIS_TAKEOFF_ALT": 10.0,  # the pilot's take-off height (the mock's vehicles start hovering at 10 m)
        "SDLOG_MODE": -1,  # no .ulg logs in the work directory
    }


@dataclass(frozen=True)
class Px4Ports:
    """Every UDP port of instance N (PX4 binds the first group; the second are where it sends)."""

    instance: int

    @property
    def gcs(self) -> int:
        return 18570 + self.instance

    @property
    def ground(self) -> int:
        return 18590 + self.instance

    @property
    def ground_remote(self) -> int:
        return 18600 + self.instance

    @property
    def onboard(self) -> int:
        return 14580 + self.instance

    @property
    def onboard_remote(self) -> int:
        return 14540 + self.instance

    @property
    def truth(self) -> int:
        return 19410 + self.instance

    @property
    def px4_binds(self) -> tuple[int, ...]:
        n = self.instance
        return (18570 + n, 18590 + n, 14580 + n, 14280 + n, 13030 + n, 19450 + n)

    @property
    def system_id(self) -> int:
        return self.instance + 1


def _udp_socket(port: int) -> socket.socket | None:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.bind(("127.0.0.1", port))
    except OSError:
        s.close()
        return None
    return s


def _udp_free(port: int) -> bool:
    s = _udp_socket(port)
    if s is None:
        return False
    s.close()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as any_address:  # PX4 binds 0.0.0.0
        try:
            any_address.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def _reserve_instance() -> tuple[Px4Ports, socket.socket, socket.socket]:
    """A free instance, with the two ports we receive on already bound: (ports, onboard, truth)."""
    start = os.getpid() % len(INSTANCES)
    for k in range(len(INSTANCES)):
        ports = Px4Ports(INSTANCES[(start + k) % len(INSTANCES)])
        if Path(f"/tmp/px4_lock-{ports.instance}").exists() and not _udp_free(ports.gcs):
            continue  # a PX4 of that instance is running
        if not all(_udp_free(p) for p in (*ports.px4_binds, ports.ground_remote)):
            continue
        onboard = _udp_socket(ports.onboard_remote)
        truth = _udp_socket(ports.truth)
        if onboard is not None and truth is not None:
            return ports, onboard, truth
        for s in (onboard, truth):
            if s is not None:
                s.close()
    raise RuntimeError(
        "no free PX4 SITL instance (1-9): each needs UDP 18570+N, 18590+N, 18600+N, 14580+N, 14280+N, 13030+N, "
        "19450+N, 14540+N and 19410+N free; `pgrep -a px4` shows running ones"
    )


def _die_with_parent() -> None:
    """In the child, before exec: SIGTERM when the process that started it dies (PR_SET_PDEATHSIG = 1)."""
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)


class Px4Sitl:
    """One `px4` process (SIH) in its own work directory, on a free instance."""

    def __init__(
        self,
        package: Path,
        work_dir: Path,
        home: tuple[float, float, float],
        extra_params: dict[str, float] | None = None,
        speed_factor: float = 1.0,
    ) -> None:
        self.package = package
        self.work_dir = work_dir
        self.home = home  # lat, lon (deg), alt (m AMSL)
        self.params = {**project_parameters(), **(extra_params or {})}
        self.speed_factor = speed_factor
        self.ports, onboard, truth = _reserve_instance()
        self._onboard_socket: socket.socket | None = onboard
        self._truth_socket: socket.socket | None = truth
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def instance(self) -> int:
        return self.ports.instance

    @property
    def system_id(self) -> int:
        return self.ports.system_id

    def take_onboard_socket(self) -> socket.socket:
        """The socket on 14540+N (PX4's onboard link sends there), connected to PX4's 14580+N."""
        s, self._onboard_socket = self._onboard_socket, None
        if s is None:
            raise RuntimeError("the onboard socket was already taken")
        s.connect(("127.0.0.1", self.ports.onboard))
        return s

    def take_truth_socket(self) -> socket.socket:
        s, self._truth_socket = self._truth_socket, None
        if s is None:
            raise RuntimeError("the ground-truth socket was already taken")
        return s

    def environment(self) -> dict[str, str]:
        lat, lon, alt = self.home
        env = dict(
            os.environ,
            PX4_SYS_AUTOSTART=str(AIRFRAME),
            PX4_SIMULATOR="sihsim",
            PX4_SIM_MODEL="quadx",
            HEADLESS="1",
            PX4_HOME_LAT=f"{lat:.7f}",
            PX4_HOME_LON=f"{lon:.7f}",
            PX4_HOME_ALT=f"{alt:.1f}",
            PATH=f"{self.work_dir / 'bin'}:{os.environ.get('PATH', '/usr/bin:/bin')}",
        )
        for name, value in self.params.items():
            env[f"PX4_PARAM_{name}"] = f"{value:g}"
        if self.speed_factor != 1.0:
            env["PX4_SIM_SPEED_FACTOR"] = f"{self.speed_factor:g}"
        else:
            env.pop("PX4_SIM_SPEED_FACTOR", None)
        return env

    def _link_commands(self) -> Path:
        """work/bin: px4 and every px4-<module> as symbolic links to the package's binary."""
        bin_dir = self.work_dir / "bin"
        bin_dir.mkdir(parents=True, exist_ok=True)
        binary = self.package / "bin" / "px4"
        for entry in (self.package / "bin").iterdir():
            link = bin_dir / entry.name
            link.unlink(missing_ok=True)
            target = entry if entry.name.endswith(".sh") else binary
            link.symlink_to(target)
        return bin_dir / "px4"

    def start(self) -> Px4Sitl:
        self.work_dir.mkdir(parents=True, exist_ok=True)
        px4 = self._link_commands()
        cmd = [str(px4), "-d", "-i", str(self.instance), "-w", str(self.work_dir), str(self.package / "etc")]
        with open(self.work_dir / "px4.log", "wb") as out:
            self.process = subprocess.Popen(
                cmd,
                cwd=self.work_dir,
                env=self.environment(),
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                preexec_fn=_die_with_parent,
            )
        return self

    def start_ground_link(self, forward: bool = False) -> int:
        """A sixth MAVLink instance (PX4 SITL's most) in the GCS's normal mode, as a second telemetry radio:
        PX4 binds 18590+N and sends to 127.0.0.1:18600+N, where the ground station listens. PX4 answers only
        the first address it hears from, so a ground station that sends from a fixed port (`udpin`) can
        come and go, as QGroundControl does on 14550. Needs the running PX4 (`mavlink` talks to its daemon);
        returns the port the ground station listens on. `forward`: it also carries the companion's traffic
        both ways (`-f`, as the GCS link), for `cloudtrack-gcs start` and friends."""
        self.check_running()
        done = subprocess.run(
            [str(self.work_dir / "bin" / "px4-mavlink"), "--instance", str(self.instance), "start", "-u",
             str(self.ports.ground), "-o", str(self.ports.ground_remote), "-r", str(GROUND_LINK_RATE),
             *(["-f"] if forward else [])],
            cwd=self.work_dir, env=self.environment(), capture_output=True, text=True, timeout=10,
        )  # fmt: skip
        if done.returncode != 0:
            raise RuntimeError(
                f"px4 (instance {self.instance}) did not start its ground link on UDP {self.ports.ground} "
                f"(exit {done.returncode}):\n{self.log_tail()}"
            )
        return self.ports.ground_remote

    def check_running(self) -> None:
        if self.process is not None and self.process.poll() is not None:
            raise RuntimeError(
                f"px4 exited with {self.process.returncode} (instance {self.instance}):\n{self.log_tail()}"
            )

    def log_tail(self, lines: int = 20) -> str:
        try:
            text = (self.work_dir / "px4.log").read_text(errors="replace")
        except OSError:
            return "(no px4 log)"
        return "\n".join(text.splitlines()[-lines:])

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        for s in (self._onboard_socket, self._truth_socket):
            if s is not None:
                s.close()
        self._onboard_socket = self._truth_socket = None

    def remove_work_dir(self) -> None:
        shutil.rmtree(self.work_dir, ignore_errors=True)


def quaternion_to_euler(w: float, x: float, y: float, z: float) -> tuple[float, float, float]:
    """Roll, pitch, yaw (rad) of a body-to-NED quaternion (MAVLink's order: w, x, y, z)."""
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


def truth_pose(
    msg: Any, home: tuple[float, float, float], origin: tuple[float, float] = (0.0, 0.0)
) -> VehiclePose:
    """A HIL_STATE_QUATERNION as the world pose: north/east from `home` plus the vehicle's `origin` in the
    world, down from home's altitude."""
    lat0, lon0, alt0 = home
    north = math.radians(msg.lat / 1e7 - lat0) * EARTH_RADIUS
    east = math.radians(msg.lon / 1e7 - lon0) * EARTH_RADIUS * math.cos(math.radians(lat0))
    roll, pitch, yaw = quaternion_to_euler(*msg.attitude_quaternion)
    return VehiclePose(north + origin[0], east + origin[1], -(msg.alt / 1000.0 - alt0), roll, pitch, yaw)


class GroundTruthPose:
    """The real vehicle: SIH's HIL_STATE_QUATERNION (25 Hz) as a `PoseFollower`-like pose source."""

    def __init__(
        self, sock: socket.socket, home: tuple[float, float, float], origin: tuple[float, float]
    ) -> None:
        self._sock = sock
        self._sock.settimeout(0.2)
        self.home = home
        self.origin = origin
        self._parser = mavutil.mavlink.MAVLink(None)
        self._parser.robust_parsing = True
        self._pose = VehiclePose(origin[0], origin[1], 0.0)
        self._pose_time = 0.0
        self._speed = 0.0
        self.history: list[tuple[float, VehiclePose]] = []  # (monotonic time, pose), for drift measurements
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="px4-ground-truth", daemon=True)

    def start(self) -> GroundTruthPose:
        self._thread.start()
        return self

    def pose(self) -> VehiclePose:
        with self._lock:
            return self._pose

    def age_s(self) -> float:
        with self._lock:
            return time.monotonic() - self._pose_time if self._pose_time else math.inf

    def speed(self) -> float:
        """Horizontal ground speed (m/s), SIH's."""
        with self._lock:
            return self._speed

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._sock.recv(65535)
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                time.sleep(0.05)
                continue
            try:
                msgs = self._parser.parse_buffer(data) or []
            except Exception:  # only SIH sends here; a bad datagram is dropped
                continue
            for msg in msgs:
                if msg.get_type() != "HIL_STATE_QUATERNION":
                    continue
                pose = truth_pose(msg, self.home, self.origin)
                now = time.monotonic()
                with self._lock:
                    self._pose, self._pose_time = pose, now
                    self._speed = math.hypot(msg.vx, msg.vy) / 100.0
                    self.history.append((now, pose))
                    if len(self.history) > 20000:
                        del self.history[:10000]

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2)
        self._sock.close()


def px4_custom_mode(name: str) -> int:
    main, sub = PX4_MODES[name]
    return main << 16 | sub << 24


def px4_mode_name(custom_mode: int | None) -> str:
    """PX4's custom_mode (main mode in byte 2, sub mode in byte 3) as the mock's mode name."""
    if custom_mode is None:
        return "?"
    numbers = ((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)
    return next((name for name, n in PX4_MODES.items() if n == numbers), f"MODE({numbers[0]}.{numbers[1]})")


class RealPx4:
    """The real PX4 behind the interface the scenario runner uses (`sitl.flight_stack.FlightStack`).

    The pilot's actions go over the GCS link (`gcs`: a `sitl.scenarios.ScriptedGcs` on 18570+N), never
    through the companion: arming, take-off, mode changes, the sticks and the reposition are the pilot's.
    The pilot's sticks are PX4's MAVLink joystick (MANUAL_CONTROL at 10 Hz, centred) from the start, as
    QGroundControl's virtual joystick: POSCTL needs manual control, and a stick deflection is the pilot's
    takeover by radio (COM_RC_OVERRIDE).
    """

    name = "px4-sitl"
    offboard_mode = "OFFBOARD"
    takeover_mode = "POSCTL"

    def __init__(self, sitl: Px4Sitl, gcs: Any, companion_port: int | None = None) -> None:
        self.sitl = sitl
        self.gcs = gcs
        self.system_id = sitl.system_id
        self.mode_history: list[tuple[float, str, str]] = []
        self.bridge = CompanionBridge(sitl.take_onboard_socket(), self.mode_name, companion_port).start()
        self.truth = GroundTruthPose(sitl.take_truth_socket(), sitl.home, (0.0, 0.0)).start()
        self.gcs.hold_sticks()
        self._ground_port: int | None = None

    @property
    def setpoints(self) -> list[BridgedSetpoint]:
        return self.bridge.setpoints

    def describe(self) -> str:
        pid = self.sitl.process.pid if self.sitl.process else "?"
        return (
            f"PX4 SITL {self.sitl.package} (pid {pid}, instance {self.sitl.instance}, system id "
            f"{self.system_id}, SIH at real time)"
        )

    def camera_pose(self, origin: tuple[float, float]) -> GroundTruthPose:
        """SIH's ground truth (the real vehicle, not PX4's estimate), placed with its home at `origin`."""
        self.truth.origin = origin
        return self.truth

    def mode_name(self) -> str:
        return px4_mode_name(self.gcs.mode())

    def mode_of(self, custom_mode: int | None) -> str:
        return px4_mode_name(custom_mode)

    def custom_mode(self, name: str) -> int:
        return px4_custom_mode(name)

    def set_mode(self, name: str, source: str = "pilot") -> bool:
        self.mode_history.append((time.monotonic(), name, source))
        main, sub = PX4_MODES[name]
        self.gcs.set_mode(main, sub)
        return True

    def rc_takeover(self) -> None:
        """The pilot moves the yaw stick past COM_RC_STICK_OV (30 %) for 0.3 s and lets it centre: PX4
        switches to POSCTL (COM_RC_OVERRIDE bit 1, offboard) and the vehicle holds where it is."""
        self.mode_history.append((time.monotonic(), "POSCTL", "pilot rc"))
        self.gcs.hold_sticks(yaw=600)
        time.sleep(0.3)
        self.gcs.hold_sticks()

    def gcs_fly_to(self, north: float, east: float, down: float) -> None:
        lat0, lon0, alt0 = self.sitl.home
        lat = lat0 + math.degrees(north / EARTH_RADIUS)
        lon = lon0 + math.degrees(east / (EARTH_RADIUS * math.cos(math.radians(lat0))))
        self.gcs.reposition(lat, lon, alt0 - down)

    def set_link_down(self, name: str, down: bool) -> None:
        if name != "companion":
            raise ValueError(f"only the companion's link can be cut on the real autopilot, not {name!r}")
        self.bridge.set_down(down)

    def ground_url(self) -> str:
        """The second GCS link (started on first use, once PX4 answers its GCS: booted)."""
        if self._ground_port is None:
            self.claim_gcs_link()
            self._ground_port = self.sitl.start_ground_link()
        return f"udpin:127.0.0.1:{self._ground_port}"

    def claim_gcs_link(self, timeout_s: float = 20.0) -> float:
        """Speak to PX4's GCS port until it answers us (it answers only its first local partner)."""
        started = time.monotonic()
        while not self.gcs.modes:
            self.sitl.check_running()
            if time.monotonic() - started > timeout_s:
                raise RuntimeError(
                    f"PX4 (instance {self.sitl.instance}) never answered the scripted GCS on UDP "
                    f"{self.sitl.ports.gcs}: another ground station on this machine (one listening on 14550, "
                    f"where PX4 sends until a GCS speaks to it) may have claimed its GCS link first.\n"
                    + self.sitl.log_tail()
                )
            self.gcs.heartbeat()
            time.sleep(0.05)
        return time.monotonic() - started

    def _quiet_gcs_link(self) -> None:
        """PX4's GCS link streams about 330 messages a second (six at ~45 Hz); the runner's Python process,
        which also renders and streams the camera, decodes every one. It reads positions at 10 Hz and
        nothing of the rest: about 40 a second remain."""
        for msg_id in GCS_STREAMS_UNREAD:
            self.gcs.stop_stream(msg_id)
        for msg_id in (
            mavutil.mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED,
            mavutil.mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
        ):
            self.gcs.request_interval(msg_id, 10.0)

    def fly_up(
        self, height_m: float, timeout_s: float = 90.0, progress: Callable[[str], None] = print
    ) -> float:
        """Arm and take off as the pilot would (AUTO.TAKEOFF to MIS_TAKEOFF_ALT, then HOLD); the seconds."""
        g = self.gcs
        started = time.monotonic()
        deadline = started + timeout_s
        self.claim_gcs_link()
        self._quiet_gcs_link()
        last_try = 0.0
        while not (g.modes and g.modes[-1][2]):  # armed
            self.sitl.check_running()
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"px4 did not arm in {timeout_s:.0f} s (statustexts: "
                    f"{[t for _, t in g.statustexts[-5:]]}):\n{self.sitl.log_tail()}"
                )
            if time.monotonic() - last_try > 1.0:  # pre-arm checks pass once the estimator has converged
                g.arm()
                last_try = time.monotonic()
            time.sleep(0.1)
        progress(f"px4 armed after {time.monotonic() - started:.1f} s; taking off to {height_m:g} m")
        g.takeoff_here()
        last_try = time.monotonic()
        while True:
            pos = g.position()
            # PX4 ends the take-off within NAV_MC_ALT_RAD (0.8 m) of its altitude and holds there: once it
            # held at 9.37 m of 10 (its estimate), so 0.3 m short would wait for a climb that never comes.
            if pos is not None and -pos[2] >= height_m - TAKEOFF_DONE_WITHIN_M and self.mode_name() == "HOLD":
                break
            self.sitl.check_running()
            if time.monotonic() > deadline:
                raise RuntimeError(f"px4 did not reach {height_m} m (at {pos}):\n{self.sitl.log_tail()}")
            if time.monotonic() - last_try > 3.0 and (pos is None or -pos[2] < 0.5):
                g.takeoff_here()
                last_try = time.monotonic()
            time.sleep(0.1)
        return time.monotonic() - started

    def reuse(self, companion_port: int | None) -> None:
        """For the next scenario on this vehicle (tests share one PX4 this way): the companion's link up
        and recorded afresh, the pilot's sticks centred. `return_home` then flies it back."""
        self.bridge.reset(companion_port)
        self.mode_history.clear()
        self.gcs.hold_sticks()

    def return_home(self, height_m: float, progress: Callable[[str], None] = print) -> float:
        """A vehicle a scenario has used, airborne in HOLD at `height_m` over home and facing north again
        (armed and taken off again if it landed); the seconds it took. The GCS's reposition also ends
        whatever mode the last scenario left, a failsafe's intended OFFBOARD included (it would come back
        with the next setpoint stream)."""
        started = time.monotonic()
        pos = self.gcs.position()
        if not (self.gcs.modes and self.gcs.modes[-1][2]) or pos is None or -pos[2] < height_m / 2:
            self.fly_up(height_m, progress=progress)
        lat0, lon0, alt0 = self.sitl.home
        deadline = time.monotonic() + 40.0
        last_sent = -math.inf
        while True:
            self.sitl.check_running()
            if time.monotonic() - last_sent > 3.0:  # again if a command was lost
                self.gcs.reposition(lat0, lon0, alt0 + height_m, yaw_deg=0.0, speed_m_s=RETURN_SPEED_M_S)
                last_sent = time.monotonic()
            pos = self.gcs.position()
            heading = self.gcs.estimates[-1][4] if self.gcs.estimates else math.nan
            if (
                pos is not None
                and self.mode_name() == "HOLD"
                and math.hypot(pos[0], pos[1]) < 1.5  # SIH's hover wanders about half a metre
                and abs(-pos[2] - height_m) < 1.0  # the local origin's altitude is not home's AMSL
                and abs(math.remainder(heading, 360.0)) < 5.0  # PX4's heading: the truth may differ
                and self.truth.speed() < 0.3
            ):
                break
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"px4 did not come back over home in 40 s (at {pos}, mode {self.mode_name()}, "
                    f"heading {heading:.0f} deg):\n{self.sitl.log_tail()}"
                )
            time.sleep(0.1)
        return time.monotonic() - started

    def close(self) -> None:
        self.bridge.close()
        self.truth.stop()
        self.sitl.stop()


def start_px4(
    package: Path,
    work_dir: Path,
    home: tuple[float, float, float],
    companion_port: int | None,
    extra_params: dict[str, float] | None = None,
) -> RealPx4:
    """PX4 on a free instance in `work_dir`, its scripted GCS on 18570+N (speaking at once, to claim the link)
    and the companion's bridge on 14540+N."""
    from sitl.scenarios import ScriptedGcs

    sitl = Px4Sitl(package, work_dir, home, extra_params)
    try:
        gcs = ScriptedGcs(f"udpout:127.0.0.1:{sitl.ports.gcs}", target_system=sitl.system_id).start()
        sitl.start()
        return RealPx4(sitl, gcs, companion_port)
    except Exception:
        sitl.stop()
        raise
