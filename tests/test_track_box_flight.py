"""A GCS track box (MAV_CMD_CAMERA_TRACK_RECTANGLE) flies the vehicle under the same rules as a mission:
the real companion process, the SITL autopilot over MAVLink, a live camera stream and `cloudtrack-gcs`."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from gcs import cli as gcs_cli
from tests.camera_stream import CAMERA_FPS, CameraStream
from tests.live_backend import free_port
from tests.mavlink_harness import autopilot, wait_for

# The person in the first frame of uav123_person12_1 (490,235,34,85 of 1280x720), normalised x1 y1 x2 y2.
PERSON_BOX = ("0.383", "0.326", "0.409", "0.444")


@pytest.fixture
def camera(sequences_dir: Path) -> Iterator[CameraStream]:
    stream = CameraStream(sequences_dir / "uav123_person12_1" / "frames")
    yield stream
    stream.close()


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_track_box_streams_only_once_the_pilot_selects_guided(
    tmp_path: Path, models_dir: Path, camera: CameraStream
) -> None:
    with autopilot("ardupilot") as sim:
        assert sim.set_mode("LOITER")
        settings = {
            "mavlink.connection": f"udpout:127.0.0.1:{sim.link_port('companion')}",
            "camera.source": f"sim+tcp://127.0.0.1:{camera.port}",
            "camera.fps": CAMERA_FPS,
            "backend.url": f"http://127.0.0.1:{free_port()}",  # an operator's box needs no back-end
            "recording.enabled": "false",
            "tracker.name": "nano",
        }
        command = [sys.executable, "-m", "companion.cli", "run", "--model-dir", str(models_dir)]
        for key, value in settings.items():
            command += ["--set", f"{key}={value}"]
        log_path = tmp_path / "companion.log"
        with open(log_path, "w") as log:
            proc = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
        try:
            gcs = ["--connect", f"udpout:127.0.0.1:{sim.link_port('gcs')}", "--timeout", "5"]
            # the companion answers the GCS once it is up (heartbeat, camera and link)
            assert wait_for(lambda: gcs_cli.main([*gcs, "track-box", *PERSON_BOX]) == 0, 60.0, 1.0), (
                log_path.read_text()[-3000:]
            )
            # No mission allowed engagement: the companion never selects GUIDED itself, so nothing streams.
            time.sleep(2.0)
            assert sim.mode == "LOITER" and sim.setpoints == [], log_path.read_text()[-3000:]
            # The pilot selects GUIDED: the operator's target is flown, at the configured setpoint rate.
            assert sim.set_mode("GUIDED", "pilot")
            selected = time.monotonic()
            assert wait_for(lambda: len(sim.setpoints) >= 10, 10.0), log_path.read_text()[-3000:]
            assert all(s.mode == "GUIDED" and s.time >= selected for s in sim.setpoints)
        finally:
            proc.terminate()
            proc.wait(timeout=10)
        assert proc.returncode == 0, log_path.read_text()[-3000:]
