"""The companion's BackendClient against a real uvicorn server on loopback."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import requests

from backend.app import create_app
from backend.serving import BackgroundServer
from backend_tools.vlm_emulator import VlmEmulator
from behaviors.detection import Verdict
from behaviors.geometry import Box, iou
from cloudtrack.api_client import BackendClient, BackendError, encode_keyframe
from tests.backend_fixtures import SUPERVISOR, TOKENS, backend_config, frame

PROMPT = "the man in the green-and-white striped shirt"


@pytest.fixture(scope="module")
def server(models_dir: Path) -> Iterator[BackgroundServer]:
    with BackgroundServer(create_app(backend_config(models_dir))) as running:
        yield running


@pytest.fixture()
def client(server: BackgroundServer) -> BackendClient:
    return BackendClient(
        server.url, TOKENS["drone-1"], timeout_s=10, vehicle_id="drone-1", mission_id="m-client"
    )


def test_full_size_frame_boxes_come_back_in_the_callers_pixels(
    client: BackendClient, sequences_dir: Path
) -> None:
    image = frame(sequences_dir, size=None)  # 1280x720, sent downscaled to 640 wide
    reply = client.detect_reply(image, PROMPT, frame_id=1, capture_time=12.5)
    truth = Box(490, 235, 34, 85)
    assert max(iou(truth, d.box) for d in reply.detections) >= 0.5
    assert all(d.candidate_id and d.verdict in Verdict for d in reply.detections)
    assert reply.models["detector"] == "yolox_nano"
    assert reply.raw is not None and reply.raw.image_size == [640, 360]


def test_keyframe_request_for_640x480_is_small(client: BackendClient, sequences_dir: Path) -> None:
    image = frame(sequences_dir, size=(640, 480))
    reply = client.detect_reply(image, PROMPT)
    print(f"640x480 keyframe: request {reply.request_bytes} B, JPEG {reply.jpeg_bytes} B (quality 80)")
    assert reply.request_bytes <= 100_000
    assert reply.request_bytes - reply.jpeg_bytes < 1_000  # multipart and meta overhead


def test_roi_is_scaled_into_the_sent_image(client: BackendClient, sequences_dir: Path) -> None:
    image = frame(sequences_dir, size=None)
    around = client.detect(image, PROMPT, roi=Box(400, 160, 240, 240))
    assert around and all(d.box.x >= 400 - 1 and d.box.x2 <= 640 + 1 for d in around)
    assert client.detect(image, PROMPT, roi=Box(900, 500, 300, 200)) == []


def test_wrong_token_raises_backend_error_with_status(server: BackgroundServer, sequences_dir: Path) -> None:
    bad = BackendClient(server.url, "wrong", vehicle_id="drone-1", mission_id="m")
    with pytest.raises(BackendError) as info:
        bad.detect(frame(sequences_dir), PROMPT)
    assert info.value.status == 401 and not info.value.retryable and "invalid bearer token" in str(info.value)


def test_bad_prompt_raises_422(client: BackendClient, sequences_dir: Path) -> None:
    with pytest.raises(BackendError, match="422"):
        client.detect(frame(sequences_dir), "?!")


def test_unreachable_and_silent_servers_raise_retryable_errors(sequences_dir: Path) -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    with pytest.raises(BackendError) as info:
        BackendClient(f"http://127.0.0.1:{port}", "t", timeout_s=2, vehicle_id="v", mission_id="m").detect(
            frame(sequences_dir), PROMPT
        )
    assert info.value.retryable and info.value.status is None
    with socket.socket() as silent:  # accepts the connection, never answers
        silent.bind(("127.0.0.1", 0))
        silent.listen()
        url = f"http://127.0.0.1:{silent.getsockname()[1]}"
        with pytest.raises(BackendError, match="no answer within 0.5 s") as info:
            BackendClient(url, "t", timeout_s=0.5, vehicle_id="v", mission_id="m").detect(
                frame(sequences_dir), PROMPT
            )
        assert info.value.retryable


def test_status_rejection_and_decisions_round_trip(
    server: BackgroundServer, client: BackendClient, sequences_dir: Path
) -> None:
    image = frame(sequences_dir)
    first = client.detect(image, PROMPT)
    best = max(first, key=lambda d: d.score)
    x, y = int(best.box.x), int(best.box.y)
    crop = image[y : y + int(best.box.h), x : x + int(best.box.w)]
    client.report_status(
        "AWAIT_SUPERVISOR", awaiting={"candidate_id": best.candidate_id, "box": list(best.box.xyxy())}
    )
    requests.post(
        f"{server.url}/v1/vehicles/drone-1/decisions",
        json={"candidate_id": best.candidate_id, "action": "reject"},
        headers={"Authorization": f"Bearer {SUPERVISOR}"},
        timeout=10,
    ).raise_for_status()
    decisions = client.decisions()
    assert [(d.candidate_id, d.action) for d in decisions] == [(best.candidate_id, "reject")]
    assert client.decisions(after=decisions[-1].decision_id) == []
    # The rejected person is not proposed again in this mission ...
    again = client.detect(image, PROMPT)
    same = max(again, key=lambda d: iou(d.box, best.box))
    assert same.verdict is Verdict.NO and "rejected" in same.justification
    # ... but is in another mission, and a rejection sent with a crop works without a known id.
    other = BackendClient(server.url, TOKENS["drone-1"], vehicle_id="drone-1", mission_id="m-other")
    assert all("rejected" not in d.justification for d in other.detect(image, PROMPT))
    other.reject(None, crop_bgr=crop, reason="wrong person")
    assert any("rejected" in d.justification for d in other.detect(image, PROMPT))


def test_worst_case_keyframe_stays_under_the_byte_budget(client: BackendClient) -> None:
    noise = np.random.default_rng(1).integers(0, 256, (480, 640, 3), dtype=np.uint8)  # JPEG's worst case
    jpeg, scale = encode_keyframe(noise, 640, 80, max_bytes=90_000)
    assert len(jpeg) <= 90_000 and 0 < scale < 1
    reply = client.detect_reply(noise, PROMPT)
    assert (
        reply.request_bytes <= 100_000
        and reply.raw is not None
        and reply.raw.image_size[0] == round(640 * scale)
    )
    assert all(d.box.x2 <= 640.5 for d in reply.detections)  # boxes back in the caller's pixels


def test_encode_keyframe_refuses_non_images() -> None:
    with pytest.raises(ValueError, match="BGR"):
        encode_keyframe(np.zeros((10, 10), np.uint8), 640, 80)


@pytest.mark.slow
def test_slow_and_garbage_vlm_answers_through_the_server(models_dir: Path, sequences_dir: Path) -> None:
    image = frame(sequences_dir)
    with VlmEmulator(latency_s=2.0) as slow, VlmEmulator(mode="garbage") as garbage:
        for vlm, settings, expected, reason in (
            (slow, ["verifier.timeout_s=0.4"], Verdict.UNCERTAIN, "timed out"),
            (garbage, ['verifier.uncertain_policy="yes"'], Verdict.YES, "quick brown fox"),
        ):
            config = backend_config(
                models_dir, 'verifier.kind="vlm"', f'vlm.base_url="{vlm.base_url}"', *settings
            )
            with BackgroundServer(create_app(config)) as server:
                client = BackendClient(
                    server.url, TOKENS["drone-1"], timeout_s=10, vehicle_id="drone-1", mission_id="m-vlm"
                )
                start = time.monotonic()
                reply = client.detect_reply(image, PROMPT)
                assert reply.detections and all(
                    d.verdict is expected and reason in d.justification for d in reply.detections
                )
                assert time.monotonic() - start < 1.9  # the slow VLM's 2 s answer was not awaited


def test_keyframe_sink_gets_exactly_the_bytes_sent_and_cannot_break_a_query() -> None:
    image = np.zeros((480, 640, 3), np.uint8)
    image[100:300, 200:260] = (30, 160, 40)
    recorded: list[tuple[bytes, int]] = []
    sent = encode_keyframe(image, 640, 80)[0]
    client = BackendClient(
        "http://127.0.0.1:9",
        "t",
        timeout_s=0.5,
        vehicle_id="v",
        mission_id="m",
        on_keyframe=lambda jpeg, fid: recorded.append((jpeg, fid)),
    )
    with pytest.raises(BackendError):  # nothing listens on port 9: the query fails, the keyframe is recorded
        client.detect(image, "a person", frame_id=42)
    assert recorded == [(sent, 42)]

    def full_disk(jpeg: bytes, fid: int) -> None:
        raise OSError(28, "No space left on device")

    broken = BackendClient(
        "http://127.0.0.1:9", "t", timeout_s=0.5, vehicle_id="v", mission_id="m", on_keyframe=full_disk
    )
    with pytest.raises(BackendError):  # the failure is the unreachable back-end, not the recorder
        broken.detect(image, "a person", frame_id=43)


def test_replies_are_validated_with_the_shared_models(sequences_dir: Path) -> None:
    """A reply that does not fit cloudtrack.api_models is refused, e.g. a candidate id that is a path."""
    import json as json_module
    import threading
    from http.server import BaseHTTPRequestHandler, HTTPServer

    def reply(candidate_id: str) -> bytes:
        candidate = {
            "candidate_id": candidate_id,
            "box": [1, 2, 30, 40],
            "body_box": [4, 6, 24, 40],
            "score": 0.9,
            "label": "person",
            "verdict": "yes",
            "justification": "",
            "judged": False,
            "placement_ok": False,
            "verifier": "none",
            "t_verify": 0.0,
        }
        timings = dict.fromkeys(("t_queue", "t_decode", "t_detect", "t_verify", "t_total"), 0.0)
        return json_module.dumps(
            {
                "vehicle_id": "v",
                "mission_id": "m",
                "frame_id": None,
                "capture_time": None,
                "image_size": [640, 360],
                "superset": "person",
                "candidates": [candidate],
                "timings": timings,
                "models": {"detector": "d", "verifier": "none"},
            }
        ).encode()

    answers = [reply("c-1"), reply("../../v1/vehicles?")]

    class Handler(BaseHTTPRequestHandler):
        def do_POST(self) -> None:  # noqa: N802 - http.server's name
            self.rfile.read(int(self.headers["Content-Length"]))
            body = answers.pop(0)
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = HTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        client = BackendClient(
            f"http://127.0.0.1:{server.server_port}", "t" * 16, vehicle_id="v", mission_id="m"
        )
        good = client.detect_reply(frame(sequences_dir), PROMPT)
        assert [d.candidate_id for d in good.detections] == ["c-1"] and good.raw is not None
        assert not good.detections[0].judged  # nothing judged past the class: a search may start on it
        assert good.detections[0].placement_ok is False
        scale = frame(sequences_dir).shape[1] / good.raw.image_size[0]
        body = good.detections[0].body_box  # a new track starts on the verifier's measure of the body
        assert body is not None and good.detections[0].start_box == body
        assert body.xyxy() == pytest.approx(tuple(v * scale for v in (4, 6, 24, 40)))
        with pytest.raises(BackendError, match="malformed answer: candidates.0.candidate_id"):
            client.detect(frame(sequences_dir), PROMPT)
    finally:
        server.shutdown()


def test_early_stage_answers_before_the_vlm_and_the_final_answer_is_the_vlms(
    models_dir: Path, sequences_dir: Path, client: BackendClient
) -> None:
    """A cascade back-end (local verifier, then a VLM that takes 0.8 s and says "no"): stage "early" is
    answered by the local verifier alone, marked not final; the full request carries the VLM's verdicts.
    A back-end without a slower stage answers an early request in full."""
    image = frame(sequences_dir)
    with VlmEmulator(latency_s=0.8, mode="no") as vlm:
        config = backend_config(models_dir, 'verifier.kind="cascade"', f'vlm.base_url="{vlm.base_url}"')
        with BackgroundServer(create_app(config)) as server:
            cascade = BackendClient(
                server.url, TOKENS["drone-1"], timeout_s=10, vehicle_id="drone-1", mission_id="m-early"
            )
            start = time.monotonic()
            early = cascade.detect_reply(image, PROMPT, frame_id=5, stage="early")
            early_s = time.monotonic() - start
            assert not early.final and early.raw is not None and early.raw.candidates
            assert {c.verifier for c in early.raw.candidates} <= {"local:person", "rejection-memory"}
            assert vlm.requests == 0
            full = cascade.detect_reply(image, PROMPT, frame_id=5)
            assert full.final and vlm.requests > 0
            judged_by_vlm = [d for d in full.detections if "fast check" in d.justification]
            assert judged_by_vlm and all(d.verdict is Verdict.NO for d in judged_by_vlm)
            print(f"early answer {early_s:.2f} s; VLM latency 0.8 s")
    found, final = client.detect_early(image, prompt=PROMPT)
    assert final and found
