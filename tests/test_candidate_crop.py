"""The candidate crop the companion sends with its status, so the supervisor page shows the person."""

from __future__ import annotations

import base64
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import requests

from behaviors.detection import Verdict
from behaviors.geometry import Box
from behaviors.mission import MissionState
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from companion.cloud.candidate_crop import MAX_B64_CHARS, MAX_SIDE_PX, candidate_crop, crop_window
from companion.mission_runner import MissionRunner
from companion.vision.frame_sources import Frame


def _first_frame(sequence: Path) -> tuple[np.ndarray, Box]:
    image = cv2.imread(str(sorted((sequence / "frames").glob("*.jpg"))[0]))
    assert image is not None
    x, y, w, h = (float(v) for v in (sequence / "groundtruth.txt").read_text().splitlines()[0].split(","))
    return image, Box(x, y, w, h)


def _decode(text: str) -> np.ndarray:
    image = cv2.imdecode(np.frombuffer(base64.b64decode(text, validate=True), np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image


def test_crop_of_a_real_person_is_small_and_frames_the_box(sequence_dirs: list[Path]) -> None:
    for sequence in sequence_dirs:
        image, box = _first_frame(sequence)
        crop = candidate_crop(image, box)
        assert crop is not None, sequence.name
        assert len(crop["crop_jpeg_b64"]) <= MAX_B64_CHARS
        decoded = _decode(crop["crop_jpeg_b64"])
        assert max(decoded.shape[:2]) <= MAX_SIDE_PX
        x1, y1, x2, y2 = crop["crop_box"]
        assert 0 <= x1 < x2 <= decoded.shape[1] + 0.5 and 0 <= y1 < y2 <= decoded.shape[0] + 0.5


def test_crop_is_native_resolution_with_the_verifiers_margin() -> None:
    """A person 12 px tall in the 640-px keyframe is 24 px in a 1280-px frame: the crop keeps those 24 px
    (twice the keyframe's detail) and the verifier's 50 keyframe-px margin, 100 native px."""
    frame = np.zeros((720, 1280, 3), np.uint8)
    frame[:, :, 1] = np.arange(1280, dtype=np.uint16)[None, :] % 256  # smooth: fits at full quality
    box = Box(600, 300, 10, 24)
    assert crop_window(1280, 720, box) == (500, 200, 710, 424)
    crop = candidate_crop(frame, box)
    assert crop is not None and len(crop["crop_jpeg_b64"]) <= MAX_B64_CHARS
    decoded = _decode(crop["crop_jpeg_b64"])
    assert decoded.shape[:2] == (224, 210)  # not scaled: native pixels
    x1, y1, x2, y2 = crop["crop_box"]
    assert (x1, y1, round(y2 - y1)) == (100, 100, 24)
    # A frame no wider than the keyframe: 50 px; a large box: half its longer side around it.
    assert crop_window(640, 480, Box(300, 200, 10, 24)) == (250, 150, 360, 274)
    assert crop_window(1280, 720, Box(400, 100, 200, 400)) == (200, 0, 800, 700)
    # A crop over MAX_SIDE_PX is scaled down, the box with it.
    big = candidate_crop(frame, Box(400, 100, 200, 400))
    assert big is not None
    shrunk = _decode(big["crop_jpeg_b64"])
    assert max(shrunk.shape[:2]) == MAX_SIDE_PX
    assert abs((big["crop_box"][3] - big["crop_box"][1]) - 400 * MAX_SIDE_PX / 700) < 1


def test_noise_is_squeezed_under_the_budget_and_bad_boxes_give_none() -> None:
    noise = np.random.default_rng(1).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    crop = candidate_crop(noise, Box(100, 100, 300, 300), max_b64_chars=12_000)
    assert crop is not None and len(crop["crop_jpeg_b64"]) <= 12_000
    # past the lowest quality it shrinks, the box with it: still inside the smaller crop
    decoded = _decode(crop["crop_jpeg_b64"])
    assert max(decoded.shape[:2]) < MAX_SIDE_PX and crop["crop_box"][3] <= decoded.shape[0] + 0.5
    assert candidate_crop(noise, Box(700, 500, 20, 40)) is None  # outside the image
    assert candidate_crop(noise, Box(10, 10, float("nan"), 40)) is None
    assert candidate_crop(noise[:, :, 0], Box(10, 10, 20, 40)) is None  # not BGR


def _runner_awaiting(image: np.ndarray, box: Box) -> tuple[MissionRunner, dict[str, Any]]:
    """The loop's status for a candidate report (only the behaviour state and the newest frame are read)."""
    from behaviors.mission import initial_state

    config = MissionConfig()
    none: Any = None
    runner = MissionRunner(config, none, none, none, none)
    runner.state = replace(
        initial_state(config),
        mode=MissionState.AWAITING_SUPERVISOR,
        mission=StartMission("a person in a green shirt", mission_id="m1"),
        target=_target("c7", box),
    )
    runner._latest = Frame(7, time.monotonic(), image)
    return runner, runner._status()


def test_status_carries_the_crop_once_encoded_per_candidate(sequence_dirs: list[Path]) -> None:
    image, box = _first_frame(sequence_dirs[0])
    runner, status = _runner_awaiting(image, box)
    awaiting = status["awaiting"]
    assert awaiting["candidate_id"] == "c7" and _decode(awaiting["crop_jpeg_b64"]).size > 0
    # the next report of the same candidate reuses the encoded crop, even from a newer (black) frame
    runner._latest = Frame(8, time.monotonic(), np.zeros_like(image))
    again = runner._status()
    assert again["awaiting"]["crop_jpeg_b64"] is awaiting["crop_jpeg_b64"]
    runner.state = replace(runner.state, target=_target("c8", box))
    other = runner._status()
    assert other["awaiting"]["candidate_id"] == "c8"
    assert other["awaiting"]["crop_jpeg_b64"] != awaiting["crop_jpeg_b64"]
    # Out of view, still awaiting a decision (the survey flew on): the crop it had, never the new frame's.
    runner.state = replace(
        runner.state, mode=MissionState.SEARCHING, target=None, pending=(_target("c7", box),)
    )
    pending = runner._status()["awaiting"]
    assert pending["candidate_id"] == "c7" and pending["crop_jpeg_b64"] is awaiting["crop_jpeg_b64"]
    runner.state = replace(runner.state, pending=(_target("c9", box),))
    assert "crop_jpeg_b64" not in runner._status()["awaiting"]


def _target(cid: str, box: Box) -> Any:
    from behaviors.mission import Target

    return Target(cid, "green shirt", Verdict.YES, box, 7, 0.0)


@pytest.mark.timeout(60)
def test_crop_reaches_the_back_end_store(sequence_dirs: list[Path]) -> None:
    from backend.app import create_app
    from backend.config import AuthConfig, BackendConfig, SessionConfig
    from backend.serving import BackgroundServer
    from cloudtrack.api_client import BackendClient
    from companion.cloud.backend_session import BackendSession
    from sitl.simulated_detector import SimulatedPersonDetector

    image, box = _first_frame(sequence_dirs[0])
    _, status = _runner_awaiting(image, box)
    config = BackendConfig(
        auth=AuthConfig(tokens={"drone-1": "drone-1-token-0001"}, supervisor_token="supervisor-token-0001"),
        sessions=SessionConfig(sqlite_path=":memory:"),
    )
    posted: list[dict[str, Any]] = []

    class RecordingClient(BackendClient):
        def report_status(self, state: str, vehicle_id: str | None = None, **fields: Any) -> dict[str, Any]:
            posted.append(fields)
            return super().report_status(state, vehicle_id, **fields)

    with BackgroundServer(create_app(config, detector=SimulatedPersonDetector(lambda fid: None))) as server:
        session = BackendSession(
            RecordingClient(server.url, "drone-1-token-0001", vehicle_id="drone-1"), period_s=0.05
        ).start()
        try:
            session.update(status)
            deadline = time.monotonic() + 10
            while len(posted) < 3 and time.monotonic() < deadline:
                time.sleep(0.05)
            stored = requests.get(
                f"{server.url}/v1/vehicles",
                headers={"Authorization": "Bearer supervisor-token-0001"},
                timeout=5,
            ).json()
        finally:
            session.close()
    # The crop went up once; later reports about the same candidate leave it out and the store keeps it.
    assert "crop_jpeg_b64" in posted[0]["awaiting"]
    assert all(
        "crop_jpeg_b64" not in p["awaiting"] and p["awaiting"]["candidate_id"] == "c7" for p in posted[1:3]
    )
    awaiting = stored[0]["awaiting"]
    assert awaiting["candidate_id"] == "c7"
    assert awaiting["crop_jpeg_b64"] == status["awaiting"]["crop_jpeg_b64"]
    assert _decode(awaiting["crop_jpeg_b64"]).shape[2] == 3 and len(awaiting["crop_box"]) == 4


def _header_bomb(width: int, height: int) -> bytes:
    """A real small JPEG whose frame header claims width x height."""
    data = bytearray(cv2.imencode(".jpg", np.full((16, 16, 3), 128, np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 7] = height.to_bytes(2, "big")
    data[sof + 7 : sof + 9] = width.to_bytes(2, "big")
    return bytes(data)


def test_hostile_crops_are_refused_clearly_and_the_candidate_shown_stays(sequence_dirs: list[Path]) -> None:
    """A vehicle's crop is checked from its header before anything decodes it; a refused one is a 422 (or
    413 past the body limit) naming the field and what it got, and the crop already shown stays served."""
    from fastapi.testclient import TestClient

    from backend.app import create_app
    from backend.config import AuthConfig, BackendConfig, SessionConfig
    from sitl.simulated_detector import SimulatedPersonDetector

    image, box = _first_frame(sequence_dirs[0])
    good = candidate_crop(image, box)
    assert good is not None
    config = BackendConfig(
        auth=AuthConfig(tokens={"drone-1": "drone-1-token-0001"}, supervisor_token="supervisor-token-0001"),
        sessions=SessionConfig(sqlite_path=":memory:"),
    )
    vehicle = {"Authorization": "Bearer drone-1-token-0001"}
    supervisor = {"Authorization": "Bearer supervisor-token-0001"}
    app = create_app(config, detector=SimulatedPersonDetector(lambda fid: None))
    with TestClient(app) as client:

        def status(crop: str, cid: str = "c1") -> Any:
            awaiting = {"candidate_id": cid, "box": [0, 0, 10, 10], "crop_jpeg_b64": crop}
            body = {"mission_id": "m1", "state": "AWAIT", "awaiting": awaiting}
            return client.post("/v1/vehicles/drone-1/status", json=body, headers=vehicle)

        assert status(good["crop_jpeg_b64"]).status_code == 200
        png = base64.b64encode(cv2.imencode(".png", image[:40, :40])[1].tobytes()).decode()
        refused = {
            "bomb": (base64.b64encode(_header_bomb(8700, 8700)).decode(), "a JPEG of 8700x8700 pixels"),
            "png": (png, "got a PNG"),
            "garbage": (base64.b64encode(b"GIF89a" + b"\0" * 64).decode(), "without a JPEG signature"),
            "not base64": ("%%%not-base64", "awaiting.crop_jpeg_b64 is not valid base64"),
            "truncated": (base64.b64encode(b"\xff\xd8\xff\xe0\0\x10JFIF").decode(), "no readable JPEG frame"),
        }
        for name, (crop, said) in refused.items():
            answer = status(crop, cid="c2")
            assert answer.status_code == 422 and said in answer.text, (name, answer.text)
        oversized = status("A" * 400_004, cid="c2")
        assert oversized.status_code in (413, 422), oversized.text
        # Nothing running lost: the candidate awaiting is the one before, its crop served byte for byte.
        stored = client.get("/v1/vehicles", headers=supervisor).json()[0]["awaiting"]
        assert stored["candidate_id"] == "c1" and stored["crop_jpeg_b64"] == good["crop_jpeg_b64"]
        served = client.get("/supervisor/api/vehicles/drone-1/candidates/c1/crop.jpg", headers=supervisor)
        assert served.status_code == 200 and served.content == base64.b64decode(good["crop_jpeg_b64"])
