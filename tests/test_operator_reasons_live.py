"""Each case in which the operator used to get silence (issue 28), with the real companion process, the mock
autopilot, a live camera, the real back-end and `cloudtrack-gcs` on the GCS link: the reason appears on the
GCS link and on the supervisor page (its snapshot), and the companion's journal says it once.

- a prompt the back-end cannot search for: the start is DENIED, `START REFUSED: ...` names the nearest
  classes; the page's reason says the same;
- a companion whose token the back-end refuses: named as such on the GCS and on the page (never
  "unreachable");
- a back-end that is down at start-up: `waiting for the back-end at <url>: ...` on the GCS, one line in
  the journal (not urllib3's retries), `back-end answers` once it is up, and the page shows the vehicle;
- a wrong autopilot address: `waiting for the autopilot's HEARTBEAT on <address>` in the journal and on
  the page within seconds.
Select: -k reasons.
"""

from __future__ import annotations

import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, DetectorConfig, SessionConfig, VerifierConfig
from backend.serving import BackgroundServer
from tests.camera_stream import CAMERA_FPS, CameraStream
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, free_port, live_backend
from tests.mavlink_harness import autopilot

SUPERVISOR = {"Authorization": f"Bearer {SUPERVISOR_TOKEN}"}


@contextmanager
def companion(
    tmp_path: Path, models_dir: Path, link: str, camera_port: int, backend_url: str, token: str | None
) -> Iterator[tuple[subprocess.Popen[bytes], Path]]:
    settings = {
        "vehicle.id": "drone-1",
        "mavlink.connection": link,
        "camera.source": f"sim+tcp://127.0.0.1:{camera_port}",
        "camera.fps": CAMERA_FPS,
        "backend.url": backend_url,
        "tracker.name": "csrt",
        "recording.enabled": "false",
    }
    command = [sys.executable, "-m", "companion.cli", "run", "--model-dir", str(models_dir)]
    for key, value in settings.items():
        command += ["--set", f"{key}={value}"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("CLOUDTRACK_BACKEND__")}
    if token is not None:
        env["CLOUDTRACK_BACKEND__TOKEN"] = token
    log_path = tmp_path / "companion.log"
    with open(log_path, "wb") as log:
        process = subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        yield process, log_path
    finally:
        process.terminate()
        try:
            process.wait(timeout=15)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def gcs(sim: Any, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    connect = f"udpout:127.0.0.1:{sim.link_port('gcs')}"
    return subprocess.run(
        [sys.executable, "-m", "gcs.cli", "--connect", connect, "--timeout", "20", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )


class Watch:
    """`cloudtrack-gcs watch` running beside the test: started before the companion, so the GCS link hears
    the notices the companion says once; `until` reads its lines as they come."""

    def __init__(self, sim: Any) -> None:
        connect = f"udpout:127.0.0.1:{sim.link_port('gcs')}"
        self.process = subprocess.Popen(
            [sys.executable, "-m", "gcs.cli", "--connect", connect, "--timeout", "20", "watch"],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=dict(os.environ, PYTHONUNBUFFERED="1"),
        )
        self.lines: list[str] = []
        self._queue: queue.Queue[str] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self._queue.put(line)

    def until(self, text: str, timeout_s: float, log: Path) -> str:
        """All it printed so far, once a line holds `text`."""
        deadline = time.monotonic() + timeout_s
        while not any(text in line for line in self.lines):
            left = deadline - time.monotonic()
            try:
                self.lines.append(self._queue.get(timeout=max(left, 0.0)))
            except queue.Empty:
                raise AssertionError(
                    f"{text!r} not on the GCS within {timeout_s} s:\n{''.join(self.lines)}\n"
                    f"companion log:\n{log.read_text()[-3000:]}"
                ) from None
        return "".join(self.lines)

    def close(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=10)


@contextmanager
def watching(sim: Any) -> Iterator[Watch]:
    watch = Watch(sim)
    try:
        yield watch
    finally:
        watch.close()


def snapshot_reason(url: str) -> dict[str, Any]:
    (vehicle,) = [
        v
        for v in httpx.get(f"{url}/supervisor/api/state", headers=SUPERVISOR, timeout=10).json()["vehicles"]
        if v["id"] == "drone-1"
    ]
    return dict(vehicle)


def wait(predicate: Any, timeout_s: float, what: str, log: Path) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            value = predicate()
        except (httpx.HTTPError, ValueError, KeyError):
            value = None
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"{what} not within {timeout_s} s; companion log:\n{log.read_text()[-3000:]}")


@pytest.mark.slow
def test_reasons_a_prompt_the_back_end_cannot_search_for_is_refused_with_the_nearest_classes(
    tmp_path: Path, models_dir: Path, sequences_dir: Path
) -> None:
    with (
        live_backend(models_dir) as backend,
        autopilot("ardupilot") as sim,
        CameraStream(sequences_dir / "uav123_person12_1" / "frames", count=8) as camera,
        companion(
            tmp_path,
            models_dir,
            f"udpout:127.0.0.1:{sim.link_port('companion')}",
            camera.port,
            backend.url,
            VEHICLE_TOKENS["drone-1"],
        ) as (_, log),  # fmt: skip
    ):
        refused = gcs(sim, "start", "--prompt", "an orange life buoy", "--mission-id", "9")
        assert refused.returncode == 1, refused.stdout + refused.stderr
        assert "start: in progress (the companion asks the back-end)" in refused.stdout
        assert "refused by the companion: DENIED" in refused.stderr
        assert (
            "START REFUSED: the back-end cannot search for this: superset 'orange life buoy' has no COCO"
            in (refused.stdout)
        )
        # The page shows the companion's latest reason: its start-up one ("waiting for the autopilot's
        # HEARTBEAT") until the next status report carries the refusal.
        reason = wait(
            lambda: (r := snapshot_reason(backend.url)["reason"]).startswith("start refused") and r,
            15,
            "the refusal on the page",
            log,
        )
        assert reason.startswith(
            "start refused: the back-end cannot search for this: superset 'orange life buoy'"
        )
        accepted = gcs(sim, "start", "--prompt", "a man in a striped shirt", "--mission-id", "10")
        assert accepted.returncode == 0 and "MISSION 10 STARTED" in accepted.stdout, accepted.stderr
        wait(
            lambda: not snapshot_reason(backend.url)["reason"].startswith("start refused"), 15, "cleared", log
        )
    assert log.read_text().count("mission start 'an orange life buoy'") == 1


@pytest.mark.slow
def test_reasons_a_prompt_outside_its_superset_is_warned_of_on_the_gcs_and_the_page(
    tmp_path: Path, models_dir: Path, sequences_dir: Path
) -> None:
    with (
        live_backend(models_dir) as backend,
        autopilot("ardupilot") as sim,
        CameraStream(sequences_dir / "uav123_person12_1" / "frames", count=8) as camera,
        companion(
            tmp_path,
            models_dir,
            f"udpout:127.0.0.1:{sim.link_port('companion')}",
            camera.port,
            backend.url,
            VEHICLE_TOKENS["drone-1"],
        ) as (_, log),  # fmt: skip
    ):
        started = gcs(
            sim, "start", "--prompt", "an orange life buoy", "--superset", "person", "--mission-id", "11"
        )
        assert started.returncode == 0, started.stdout + started.stderr
        lines = started.stdout.splitlines()
        assert lines[-2] == "[1/191] MISSION 11 STARTED: an orange life buoy (person)", started.stdout
        warning = "PROMPT WARNING: the prompt's 'orange life buoy' is no person (nor any COCO class)"
        assert lines[-1].startswith(f"[1/191] {warning}"), started.stdout
        shown = wait(
            lambda: snapshot_reason(backend.url)["prompt_warning"], 15, "the warning on the page", log
        )
        assert shown.startswith(warning.removeprefix("PROMPT WARNING: ")), shown
        fits = gcs(
            sim, "start", "--prompt", "a man in a striped shirt", "--superset", "person", "--mission-id", "12"
        )
        assert fits.returncode == 0 and "WARNING" not in fits.stdout, fits.stdout
        wait(
            lambda: snapshot_reason(backend.url)["mission_id"] == "12",
            15,
            "the next mission on the page",
            log,
        )
        assert snapshot_reason(backend.url)["prompt_warning"] is None


@pytest.mark.slow
def test_reasons_a_refused_token_is_named_on_the_gcs_and_the_page(
    tmp_path: Path, models_dir: Path, sequences_dir: Path
) -> None:
    with (
        live_backend(models_dir) as backend,
        autopilot("ardupilot") as sim,
        CameraStream(sequences_dir / "uav123_person12_1" / "frames", count=8) as camera,
        watching(sim) as watch,
        companion(
            tmp_path,
            models_dir,
            f"udpout:127.0.0.1:{sim.link_port('companion')}",
            camera.port,
            backend.url,
            "not-the-token-of-drone-1",
        ) as (_, log),  # fmt: skip
    ):
        said = watch.until(
            "the back-end refused this vehicle's token (HTTP 401: invalid bearer token)", 20, log
        )
        assert "unreachable" not in said
        vehicle = wait(lambda: snapshot_reason(backend.url), 10, "drone-1 on the page", log)
        assert vehicle["state"] == "UNKNOWN" and "refused this vehicle's token (401" in vehicle["auth_error"]
    assert log.read_text().count("the back-end refused this vehicle's token") == 1


@pytest.mark.slow
def test_reasons_a_back_end_down_at_start_up_is_waited_for_by_name(
    tmp_path: Path, models_dir: Path, sequences_dir: Path
) -> None:
    port = free_port()
    url = f"http://127.0.0.1:{port}"
    with (
        autopilot("ardupilot") as sim,
        CameraStream(sequences_dir / "uav123_person12_1" / "frames", count=8) as camera,
        watching(sim) as watch,
        companion(
            tmp_path,
            models_dir,
            f"udpout:127.0.0.1:{sim.link_port('companion')}",
            camera.port,
            url,
            VEHICLE_TOKENS["drone-1"],
        ) as (_, log),  # fmt: skip
    ):
        watch.until(f"waiting for the back-end at {url}: connection refused", 20, log)
        config = BackendConfig(
            auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
            detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
            verifier=VerifierConfig(kind="none"),
            sessions=SessionConfig(sqlite_path=":memory:"),
        )
        with BackgroundServer(create_app(config), port=port):
            watch.until("back-end answers", 15, log)
            # The first report may have been written while the back-end was still silent; the next says so.
            wait(lambda: snapshot_reason(url)["reason"] == "", 10, "drone-1 on the page, no reason", log)
            journal = log.read_text()  # before the back-end stops again (the companion would say so)
    assert journal.count("waiting for the back-end at") == 1, journal[-3000:]
    assert (
        "urllib3" not in journal
        and "Max retries exceeded" not in journal
        and "HTTPConnectionPool" not in journal
    )


@pytest.mark.slow
def test_reasons_a_silent_autopilot_address_is_named_in_the_journal_and_on_the_page(
    tmp_path: Path, models_dir: Path, sequences_dir: Path
) -> None:
    silent = free_port()  # nothing answers there
    link = f"udpout:127.0.0.1:{silent}"
    with (
        live_backend(models_dir) as backend,
        CameraStream(sequences_dir / "uav123_person12_1" / "frames", count=8) as camera,
        companion(tmp_path, models_dir, link, camera.port, backend.url, VEHICLE_TOKENS["drone-1"]) as (
            _,
            log,
        ),
    ):
        started = time.monotonic()
        vehicle = wait(lambda: snapshot_reason(backend.url), 20, "drone-1 on the page", log)
        assert vehicle["reason"] == f"waiting for the autopilot's HEARTBEAT on {link}"
        wait(
            lambda: f"waiting for the autopilot's HEARTBEAT on {link}" in log.read_text(),
            5,
            "the journal",
            log,
        )
        assert time.monotonic() - started < 20
