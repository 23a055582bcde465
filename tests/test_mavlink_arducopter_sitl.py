"""After an abort the companion lets go, on the real ArduCopter (the shared SITL build, V4.7.0-dev).

The GCS (on SITL's first serial port) arms and takes off; the companion (second port) follows a forward
command in GUIDED; then it lets go as after a GCS abort. ArduCopter must end up in LOITER with the companion
silent, and a GCS "fly to" in GUIDED must move the vehicle (before the fix the zeros kept it pinned).
"""

from __future__ import annotations

import math
import os
import subprocess
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest

from behaviors.setpoint import Setpoint
from cloudtrack.autopilot_modes import AutopilotKind, mode_name
from cloudtrack.mavlink_connection import MavlinkEndpoint
from companion.config import MavlinkConfig, SafetyConfig
from companion.mavlink.vehicle_link import VehicleLink
from tests.mavlink_harness import MainLoop, wait_for

POSITION_ONLY_MASK = 0b110111111000


class Gcs:
    def __init__(self, endpoint: MavlinkEndpoint) -> None:
        self.endpoint = endpoint
        self.mode = ""
        self.armed = False
        self.position: tuple[float, ...] | None = None

    def pump(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        self.endpoint.send(lambda m: m.heartbeat_send(6, 8, 0, 0, 0))
        while time.monotonic() < end:
            msg = self.endpoint.receive(0.05)
            if msg is None:
                continue
            if msg.get_type() == "HEARTBEAT" and msg.get_srcComponent() == 1:
                self.mode = mode_name(AutopilotKind.ARDUPILOT, msg.custom_mode, msg.type)
                self.armed = bool(msg.base_mode & 128)
            elif msg.get_type() == "LOCAL_POSITION_NED":
                self.position = (msg.x, msg.y, msg.z, msg.vx, msg.vy)

    def command(self, command: int, *params: float) -> None:
        p = [float(v) for v in params] + [0.0] * (7 - len(params))
        self.endpoint.send(lambda m: m.command_long_send(1, 1, command, 0, *p))


@contextmanager
def _arducopter(shared: Path, workdir: Path) -> Iterator[int]:
    binary = shared / "sitl" / "arducopter"
    assert binary.exists(), f"{binary} missing (the shared ArduCopter SITL build, see its SOURCE.md)"
    instance = 20 + (os.getpid() + 7) % 40  # ports 5760 + 10 * instance (+2 for the second serial port)
    proc = subprocess.Popen(
        [str(binary), "--model", "+", "--speedup", "1", "--slave", "0", "--sim-address=127.0.0.1",
         "--defaults", str(shared / "sitl" / "copter.parm"), f"-I{instance}",
         "--home", "-35.363261,149.165230,584,90", "--wipe"],
        cwd=workdir, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        yield 5760 + 10 * instance
    finally:
        proc.kill()
        proc.wait(timeout=5)


def _connect(port: int) -> MavlinkEndpoint:
    deadline = time.monotonic() + 30
    while True:
        try:
            return MavlinkEndpoint.open(f"tcp:127.0.0.1:{port}", 255, 190)
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def _take_off(gcs: Gcs, height: float) -> None:
    gcs.pump(1.0)
    gcs.command(511, 32, 100_000)  # LOCAL_POSITION_NED at 10 Hz
    deadline = time.monotonic() + 120  # prearm checks pass once the EKF has GPS
    while not gcs.armed and time.monotonic() < deadline:
        gcs.command(176, 1, 4)  # GUIDED
        gcs.command(400, 1)  # arm (the GCS does; the companion never arms)
        gcs.pump(2.0)
    assert gcs.armed, "ArduCopter SITL never armed"
    gcs.command(22, 0, 0, 0, 0, 0, 0, height)
    deadline = time.monotonic() + 60
    while (gcs.position is None or -gcs.position[2] < height - 2) and time.monotonic() < deadline:
        gcs.pump(0.5)
    assert gcs.position is not None and -gcs.position[2] > height - 2


@pytest.mark.slow
def test_after_abort_on_real_arducopter_the_gcs_flies_the_vehicle(shared_dir: Path, tmp_path: Path) -> None:
    with _arducopter(shared_dir, tmp_path) as port:
        gcs = Gcs(_connect(port))
        _take_off(gcs, 20.0)
        link = VehicleLink(MavlinkConfig(connection=f"tcp:127.0.0.1:{port + 2}"), SafetyConfig())
        link.start()
        try:
            with MainLoop(link):
                assert wait_for(lambda: link.autopilot_kind is not None and link.telemetry() is not None, 10)
                link.request_offboard()
                link.set_velocity(Setpoint(1.5, 0.0, 0.0, 0.0))
                gcs.pump(6.0)
                assert gcs.mode == "GUIDED" and gcs.position is not None
                assert math.hypot(gcs.position[3], gcs.position[4]) > 1.0, "the companion never flew it"

                sent = link.setpoints_sent
                link.release_offboard("GCS abort")  # what the behaviour's ReleaseControl does
                gcs.pump(4.0)
                assert gcs.mode == "LOITER", gcs.mode
                assert math.hypot(gcs.position[3], gcs.position[4]) < 0.3
                after_abort = link.setpoints_sent - sent
                assert after_abort <= 3  # the explicit zero (and one more at most), then silence

                sent = link.setpoints_sent
                gcs.command(176, 1, 4)  # the GCS takes GUIDED and flies the vehicle 10 m north
                gcs.pump(1.0)
                start: Any = gcs.position
                gcs.endpoint.send(
                    lambda m: m.set_position_target_local_ned_send(
                        0,
                        1,
                        1,
                        1,
                        POSITION_ONLY_MASK,
                        start[0] + 10,
                        start[1],
                        start[2],
                        0,
                        0,
                        0,
                        0,
                        0,
                        0,
                        0,
                        0,
                    )
                )
                gcs.pump(12.0)
                moved = math.hypot(gcs.position[0] - start[0], gcs.position[1] - start[1])
                assert moved > 8.0, f"the GCS target moved the vehicle {moved:.1f} m"
                assert link.setpoints_sent == sent  # the companion stayed silent
                print(
                    f"\nreal ArduCopter: after the abort LOITER, {after_abort} setpoint(s) then silence; "
                    f"the GCS's 10 m target moved the vehicle {moved:.1f} m"
                )
        finally:
            link.close()
            gcs.endpoint.close()
