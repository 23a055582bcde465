"""The real ArduCopter SITL binary as the scenarios' autopilot: find it, start it, bridge the companion to it.

`ArduCopterSitl` starts `arducopter` (the shared ArduPilot build, see ../shared/sitl/SOURCE.md) in its own
temporary working directory with wiped parameters, the project's defaults on top of the shipped
`copter.parm` (`GUID_TIMEOUT` 1 s and the MAVLink stream rates docs/operations.md recommends) and three TCP
serial ports, laid out as on a real flight controller:

    SERIAL0  GCS (the scripted pilot/GCS: arming, take-off, mode changes, RC override, fly-to)
    SERIAL1  a spare output the simulated camera follows (like `cloudtrack-sim camera --autopilot-url`)
    SERIAL2  TELEM2, the companion: reached through `CompanionBridge` (MAV3_* stream rates, 4.5+ names)
    SERIAL5  a second ground station (MAVLink 2): the operator's laptop running `cloudtrack-gcs survey`
             (SERIAL3 and SERIAL4 are the SITL's simulated GPS receivers)

`sitl.companion_bridge.CompanionBridge` relays the companion's UDP datagrams to SERIAL2's TCP stream and
back, records the companion's setpoints and cuts the link on demand.

The binary exits when its parent dies, so a crashed runner never leaves it flying.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import socket
import subprocess
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sitl.camera_server import PoseFollower
from sitl.companion_bridge import BridgedSetpoint, CompanionBridge
from sitl.shared_sitl import shared_sitl_path

log = logging.getLogger(__name__)

BINARY_ENV = "CLOUDTRACK_ARDUCOPTER"
GUID_TIMEOUT_S = 1.0  # docs/operations.md: a frozen companion coasts 1 s, not the default 3 s
TELEMETRY_HZ = 10  # MAVn_POSITION / EXTRA1 / EXTRA2 on the companion's and the camera's ports
# ArduCopter 4.5+ names its stream-rate parameters MAVn_* (n = SERIALn-1 + 1); SRn_* no longer exist.
STREAM_GROUPS = ("POSITION", "EXTRA1", "EXTRA2", "EXTRA3")
ARDUCOPTER_MODES = {
    "STABILIZE": 0,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "LAND": 9,
    "POSHOLD": 16,
    "BRAKE": 17,
}
# copter.parm's flight-mode switch: FLTMODE_CH 5, FLTMODE5 = LOITER (PWM 1621-1749), FLTMODE6 = STABILIZE.
RC_LOITER_PWM = 1685


class ArduCopterNotFound(RuntimeError):
    """The binary is not where the runner looks: the message says where to put it."""


def default_binary() -> Path:
    """$CLOUDTRACK_ARDUCOPTER, else $CLOUDTRACK_SHARED/sitl/arducopter, else ../shared/sitl/arducopter."""
    return shared_sitl_path(BINARY_ENV, "arducopter")


def find_binary(override: Path | None = None) -> Path:
    path = (override or default_binary()).expanduser()
    if path.is_file() and os.access(path, os.X_OK):
        return path.resolve()
    raise ArduCopterNotFound(
        f"ArduCopter SITL binary not found (or not executable) at {path}. Put the `arducopter` SITL build "
        f"(x86-64 Linux, GLIBC >= 2.34; see ../shared/sitl/SOURCE.md) at ../shared/sitl/arducopter beside "
        f"the repository, or point --arducopter-binary or ${BINARY_ENV} at it. The run does not fall back "
        f"to the mock autopilot."
    )


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


_TAKEN: set[int] = set()  # instances this process started (a fleet's second SITL must not share one)


def _free_instance() -> int:
    """A SITL instance number whose fixed UDP ports (5501+10i simulator input, 9005+10i IRLock) are free."""
    start = os.getpid() % 50
    for k in range(50):
        i = (start + k) % 50 + 1
        if i not in _TAKEN and _udp_free(5501 + 10 * i) and _udp_free(9005 + 10 * i):
            _TAKEN.add(i)
            return i
    raise RuntimeError("no free ArduCopter SITL instance number (ports 5511-6001 all in use)")


def project_parameters() -> dict[str, float]:
    """What the runner sets on top of copter.parm: the values docs/operations.md recommends."""
    params: dict[str, float] = {"GUID_TIMEOUT": GUID_TIMEOUT_S, "SERIAL5_PROTOCOL": 2}  # SERIAL5: MAVLink 2
    for n in (2, 3):  # SERIAL1 (camera) and SERIAL2 (companion, TELEM2)
        for group in STREAM_GROUPS:
            params[f"MAV{n}_{group}"] = TELEMETRY_HZ if group != "EXTRA3" else 2
    return params


@dataclass(frozen=True)
class SitlPorts:
    gcs: int
    camera: int
    companion: int
    ground: int  # SERIAL5: a second ground station (`cloudtrack-gcs survey`)


class ArduCopterSitl:
    """One `arducopter` process in its own working directory (eeprom.bin, logs/, terrain/ go there)."""

    def __init__(
        self,
        binary: Path,
        work_dir: Path,
        home: tuple[float, float, float, float],
        speedup: float = 1.0,
        extra_params: dict[str, float] | None = None,
        system_id: int = 1,
    ) -> None:
        self.binary = binary
        self.system_id = system_id
        self.work_dir = work_dir
        self.home = home  # lat, lon, alt (m AMSL), heading (deg)
        self.speedup = speedup
        self.params = {**project_parameters(), **(extra_params or {})}
        self.ports = SitlPorts(free_tcp_port(), free_tcp_port(), free_tcp_port(), free_tcp_port())
        self.instance = _free_instance()
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, timeout_s: float = 20.0) -> ArduCopterSitl:
        self.work_dir.mkdir(parents=True, exist_ok=True)
        parm = self.work_dir / "cloudtrack.parm"
        parm.write_text("".join(f"{k} {v:g}\n" for k, v in self.params.items()))
        defaults = (
            f"{self.binary.parent / 'copter.parm'},{parm}"
            if (self.binary.parent / "copter.parm").is_file()
            else str(parm)
        )
        lat, lon, alt, heading = self.home
        cmd = [
            str(self.binary),
            "--model",
            "+",
            "--speedup",
            f"{self.speedup:g}",
            "--slave",
            "0",
            "--sim-address=127.0.0.1",
            "--defaults",
            defaults,
            "-I",
            str(self.instance),
            "--home",
            f"{lat:.7f},{lon:.7f},{alt:.1f},{heading:.0f}",
            "--wipe",
            "--serial0",
            f"tcp:{self.ports.gcs}",
            "--serial1",
            f"tcp:{self.ports.camera}",
            "--serial2",
            f"tcp:{self.ports.companion}",
            "--serial5",
            f"tcp:{self.ports.ground}",
        ]
        if self.system_id != 1:
            # --sysid, not a parameter: 4.7 names it MAV_SYSID where 4.5 and 4.6 had SYSID_THISMAV.
            cmd += ["--sysid", str(self.system_id)]
        with open(self.work_dir / "arducopter.log", "wb") as out:
            self.process = subprocess.Popen(cmd, cwd=self.work_dir, stdout=out, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout_s
        for port in (self.ports.gcs, self.ports.camera, self.ports.companion, self.ports.ground):
            while not self._listening(port):
                if self.process.poll() is not None:
                    raise RuntimeError(
                        f"arducopter exited with {self.process.returncode} during start-up:\n"
                        + self.log_tail()
                    )
                if time.monotonic() > deadline:
                    raise RuntimeError(
                        f"arducopter did not open TCP port {port} in {timeout_s:.0f} s:\n" + self.log_tail()
                    )
                time.sleep(0.1)
        return self

    @staticmethod
    def _listening(port: int) -> bool:
        """True once SITL listens on the port. Probing would take the port's single client slot, so read
        the kernel's socket table instead of connecting."""
        hexport = f":{port:04X}"
        for table in ("/proc/net/tcp", "/proc/net/tcp6"):
            with contextlib.suppress(OSError), open(table) as f:
                for line in f.readlines()[1:]:
                    fields = line.split()
                    if fields[1].endswith(hexport) and fields[3] == "0A":  # 0A: LISTEN
                        return True
        return False

    def log_tail(self, lines: int = 20) -> str:
        try:
            return "\n".join(
                (self.work_dir / "arducopter.log").read_text(errors="replace").splitlines()[-lines:]
            )
        except OSError:
            return "(no arducopter log)"

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.release()

    def release(self) -> None:
        _TAKEN.discard(self.instance)

    def remove_work_dir(self) -> None:
        shutil.rmtree(self.work_dir, ignore_errors=True)


class RealAutopilot:
    """The real SITL behind the interface the scenario runner uses for the mock (`SimulatedAutopilot`).

    The pilot's actions go over the GCS link (`gcs`: a `sitl.scenarios.ScriptedGcs` on SERIAL0), never
    through the companion: arming, take-off, mode changes and the RC override are the pilot's.
    """

    name = "arducopter"
    system_id = 1
    offboard_mode = "GUIDED"
    takeover_mode = "LOITER"

    def __init__(
        self, sitl: ArduCopterSitl, gcs: Any, companion_port: int | None = None, system_id: int = 1
    ) -> None:
        self.system_id = system_id  # MAV_SYSID (--sysid): 1 unless a fleet gives each vehicle its own
        self.sitl = sitl
        self.gcs = gcs
        self.mode_history: list[tuple[float, str, str]] = []
        serial2 = socket.create_connection(("127.0.0.1", sitl.ports.companion), timeout=5.0)
        self.bridge = CompanionBridge(serial2, self.mode_name, companion_port).start()

    def reuse(self, companion_port: int | None) -> None:
        raise NotImplementedError("the scenarios start a fresh ArduCopter SITL for each run")

    def return_home(self, height_m: float, progress: Callable[[str], None] = print) -> float:
        raise NotImplementedError("the scenarios start a fresh ArduCopter SITL for each run")

    def ground_url(self) -> str:
        """SERIAL5 (MAVLink 2): the operator's laptop running `cloudtrack-gcs survey`."""
        return f"tcp:127.0.0.1:{self.sitl.ports.ground}"

    def describe(self) -> str:
        pid = self.sitl.process.pid if self.sitl.process else "?"
        return (
            f"ArduCopter SITL {self.sitl.binary} (pid {pid}, instance {self.sitl.instance}, system id "
            f"{self.system_id}, speed-up {self.sitl.speedup:g} until airborne)"
        )

    def camera_pose(self, origin: tuple[float, float]) -> PoseFollower:
        """SERIAL1, a spare output, followed like `cloudtrack-sim camera --autopilot-url` does."""
        return PoseFollower(f"tcp:127.0.0.1:{self.sitl.ports.camera}", origin=origin).start()

    def custom_mode(self, name: str) -> int:
        return ARDUCOPTER_MODES[name]

    def rc_takeover(self) -> None:
        """The pilot flips the flight-mode switch (channel 5) to LOITER."""
        self.rc_mode_switch(RC_LOITER_PWM, "LOITER")

    def gcs_fly_to(self, north: float, east: float, down: float) -> None:
        """GUIDED, then a LOCAL_NED position target (Mission Planner's "fly to here")."""
        self.gcs.set_mode(ARDUCOPTER_MODES["GUIDED"])
        time.sleep(0.1)
        self.gcs.fly_to(north, east, down)

    @property
    def setpoints(self) -> list[BridgedSetpoint]:
        return self.bridge.setpoints

    def mode_name(self) -> str:
        return self.mode_of(self.gcs.mode())

    def mode_of(self, custom_mode: int | None) -> str:
        return next((n for n, v in ARDUCOPTER_MODES.items() if v == custom_mode), str(custom_mode))

    def set_mode(self, name: str, source: str = "pilot") -> bool:
        self.mode_history.append((time.monotonic(), name, source))
        self.gcs.set_mode(ARDUCOPTER_MODES[name])
        return True

    def rc_mode_switch(self, pwm: int, name: str) -> None:
        self.mode_history.append((time.monotonic(), name, "pilot rc"))
        self.gcs.hold_rc_mode_switch(pwm)

    def set_link_down(self, name: str, down: bool) -> None:
        if name != "companion":
            raise ValueError(f"only the companion's link can be cut on the real autopilot, not {name!r}")
        self.bridge.set_down(down)

    def fly_up(
        self, height_m: float, timeout_s: float = 90.0, progress: Callable[[str], None] = print
    ) -> float:
        """Arm and take off in GUIDED as the pilot would, then run at real time; returns the seconds taken."""
        g = self.gcs
        started = time.monotonic()
        deadline = started + timeout_s
        for msg_id in (0, 32):  # HEARTBEAT (mode changes seen within 0.1 s), LOCAL_POSITION_NED
            g.request_interval(msg_id, 10.0)
        last_try = 0.0
        while not (g.modes and g.modes[-1][2]):  # armed
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"arducopter did not arm in {timeout_s:.0f} s (statustexts: "
                    f"{[t for _, t in g.statustexts[-5:]]}):\n{self.sitl.log_tail()}"
                )
            if time.monotonic() - last_try > 1.0:  # pre-arm checks pass once the EKF uses GPS
                g.set_mode(ARDUCOPTER_MODES["GUIDED"])
                g.arm()
                last_try = time.monotonic()
            time.sleep(0.1)
        progress(f"arducopter armed after {time.monotonic() - started:.1f} s; taking off to {height_m:g} m")
        g.takeoff(height_m)
        last_try = time.monotonic()
        while True:
            pos = g.position()
            if pos is not None and -pos[2] >= height_m - 0.3:
                break
            if time.monotonic() > deadline:
                raise RuntimeError(
                    f"arducopter did not reach {height_m} m (at {pos}):\n{self.sitl.log_tail()}"
                )
            if time.monotonic() - last_try > 3.0 and (pos is None or -pos[2] < 0.5):
                g.takeoff(height_m)  # the first one may have come before GUIDED took effect
                last_try = time.monotonic()
            time.sleep(0.1)
        g.hold_rc(
            3, 1500
        )  # the pilot's throttle at mid-stick from here on: LOITER after a takeover holds height
        if self.sitl.speedup != 1.0:
            g.params.pop("SIM_SPEEDUP", None)
            while g.params.get("SIM_SPEEDUP") != 1.0:
                if time.monotonic() > deadline:
                    raise RuntimeError("arducopter did not take SIM_SPEEDUP=1")
                g.set_param("SIM_SPEEDUP", 1.0)
                time.sleep(0.3)
        time.sleep(0.5)  # settle the climb's last decimetres at real time
        return time.monotonic() - started

    def close(self) -> None:
        self.bridge.close()
        self.sitl.stop()


def start_arducopter(
    binary: Path,
    work_dir: Path,
    home: tuple[float, float, float],
    companion_port: int | None,
    speedup: float = 10.0,
    extra_params: dict[str, float] | None = None,
    system_id: int = 1,
) -> RealAutopilot:
    """The binary in `work_dir`, its scripted GCS on SERIAL0 and the companion's bridge to SERIAL2; a
    `system_id` other than 1 is given as `--sysid` (a fleet's vehicles each have their own)."""
    from sitl.scenarios import ScriptedGcs

    lat, lon, alt = home
    sitl = ArduCopterSitl(binary, work_dir, (lat, lon, alt, 0.0), speedup, extra_params, system_id).start()
    try:
        gcs = ScriptedGcs(f"tcp:127.0.0.1:{sitl.ports.gcs}", target_system=system_id).start()
        return RealAutopilot(sitl, gcs, companion_port, system_id)
    except Exception:
        sitl.stop()
        raise
