"""The HTTP API in-process (FastAPI TestClient): auth, limits, validation, corrupt images, fuzzing."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from backend.app import create_app
from tests.backend_fixtures import SUPERVISOR, auth, backend_config, detect_parts, frame, jpeg


@pytest.fixture(scope="module")
def client(models_dir: Path) -> Iterator[TestClient]:
    app = create_app(
        backend_config(
            models_dir,
            "server.max_request_bytes=300000",
            "server.max_image_pixels=2000000",
            "sessions.rate_limit_requests=100000",  # every request counts: the module sends many
        )
    )
    with TestClient(app) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def keyframe(sequences_dir: Path) -> bytes:
    return jpeg(frame(sequences_dir))


def test_detect_places_candidates_against_the_vehicle_the_prompt_names(
    client: TestClient, sequences_dir: Path
) -> None:
    """uav123_wakeboard7, frame 1: the boat the description names apart from the wakeboarder holds two of
    the three people YOLOX finds (backend.scene); the boat itself is not a candidate."""
    image = jpeg(frame(sequences_dir, "uav123_wakeboard7"))
    prompt = "the wakeboarder being towed to the left of the boat's wake"
    response = client.post("/v1/detect", headers=auth(), **detect_parts(image, prompt=prompt))
    assert response.status_code == 200, response.text
    candidates = response.json()["candidates"]
    assert [c["label"] for c in candidates] == ["person"] * len(candidates)
    assert sorted(c["placement_ok"] for c in candidates) == [False, False, True]


def test_detect_finds_and_verifies_the_person(client: TestClient, keyframe: bytes) -> None:
    response = client.post(
        "/v1/detect", headers=auth(), **detect_parts(keyframe, frame_id=7, capture_time=1.5)
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["image_size"] == [640, 360] and body["superset"] == "person" and body["frame_id"] == 7
    assert body["models"] == {"detector": "yolox_nano", "verifier": "local:person"}
    assert body["candidates"], "YOLOX found nobody"
    # Ground truth of frame 1 is (490, 235, 34, 85) at 1280x720, i.e. about (245, 117, 262, 160) here.
    best = max(body["candidates"], key=lambda c: c["score"])
    x1, y1, x2, y2 = best["box"]
    assert 235 < (x1 + x2) / 2 < 275 and 120 < (y1 + y2) / 2 < 160
    assert {c["verdict"] for c in body["candidates"]} <= {"yes", "no", "uncertain"}
    assert all(c["judged"] for c in body["candidates"])  # the shirt is a colour the verifier checks
    plain = client.post("/v1/detect", headers=auth(), **detect_parts(keyframe, prompt="the injured person"))
    assert plain.status_code == 200, plain.text
    assert plain.json()["candidates"] and all(
        c["verdict"] == "uncertain" and not c["judged"] for c in plain.json()["candidates"]
    )  # nothing it names is visible to the local verifier: a search may start on the detector's word
    assert all(c["justification"] for c in body["candidates"])
    assert {c["placement_ok"] for c in body["candidates"]} == {None}  # the prompt names no vehicle
    assert set(body["timings"]) == {"t_queue", "t_decode", "t_detect", "t_verify", "t_total"}


def test_health_needs_no_token_and_models_does(client: TestClient) -> None:
    assert client.get("/health").json()["status"] == "ok"
    assert client.get("/v1/models").status_code == 401
    models = client.get("/v1/models", headers=auth()).json()
    assert "person" in models["supersets"] and models["verifier_kind"] == "local"


@pytest.mark.parametrize(
    "headers",
    [
        {},
        {"Authorization": "Bearer nope"},
        {"Authorization": "Basic dG9rZW4tb25l"},
        {"Authorization": "Bearer"},
    ],
)
def test_missing_or_wrong_token_is_401(client: TestClient, keyframe: bytes, headers: dict[str, str]) -> None:
    response = client.post("/v1/detect", headers=headers, **detect_parts(keyframe))
    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"


def test_token_of_another_vehicle_is_refused(client: TestClient, keyframe: bytes) -> None:
    response = client.post("/v1/detect", headers=auth("drone-2"), **detect_parts(keyframe))
    assert response.status_code == 403 and "drone-1" in response.json()["detail"]


def test_oversized_request_is_413_declared_or_streamed(client: TestClient) -> None:
    big = b"\xff\xd8\xff" + bytes(400_000)
    response = client.post("/v1/detect", headers=auth(), **detect_parts(big))
    assert response.status_code == 413 and "300000 bytes" in response.json()["detail"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: counted as it arrives
        yield b"--x\r\n"
        for _ in range(40):
            yield bytes(10_000)

    streamed = client.post(
        "/v1/detect", headers={**auth(), "Content-Type": "multipart/form-data; boundary=x"}, content=chunks()
    )
    assert streamed.status_code == 413


def test_too_many_pixels_is_413(client: TestClient) -> None:
    import cv2

    ok, png = cv2.imencode(".png", np.zeros((1500, 1500, 3), np.uint8))
    assert ok and len(png) < 300_000
    response = client.post("/v1/detect", headers=auth(), **detect_parts(png.tobytes()))
    assert response.status_code == 413 and "1500x1500" in response.json()["detail"]


@pytest.mark.parametrize(
    ("meta", "where"),
    [
        ({"prompt": ""}, "prompt"),
        ({"prompt": "1234 !!"}, "prompt"),
        ({"vehicle_id": "drone 1"}, "vehicle_id"),
        ({"roi": [10, 10, 5, 50]}, "roi"),
        ({"roi": [1, 2, 3]}, "roi"),
        ({"frame_id": -1}, "frame_id"),
        ({"stage": "fastest"}, "stage"),
        ({"unexpected": 1}, "unexpected"),
        ({"superset": "unicorn"}, "unicorn"),
        ({"prompt": "something shiny over there"}, "superset"),
    ],
)
def test_bad_fields_are_422_with_the_reason(
    client: TestClient, keyframe: bytes, meta: dict[str, object], where: str
) -> None:
    response = client.post("/v1/detect", headers=auth(), **detect_parts(keyframe, **meta))
    assert response.status_code == 422, response.text
    assert where in json.dumps(response.json()["detail"])


def test_meta_that_is_not_json_or_missing_parts_is_422(client: TestClient, keyframe: bytes) -> None:
    response = client.post(
        "/v1/detect",
        headers=auth(),
        files={"image": ("k.jpg", keyframe, "image/jpeg")},
        data={"meta": "{not json"},
    )
    assert response.status_code == 422
    response = client.post("/v1/detect", headers=auth(), data={"meta": "{}"})
    assert response.status_code == 422 and "image" in json.dumps(response.json()["detail"])


@pytest.mark.parametrize(
    ("data", "status", "reason"),
    [
        (b"", 400, "empty"),
        (b"GIF89a....", 415, "JPEG or PNG"),
        (b"\xff\xd8\xff\xe0" + bytes(500), 400, "could not be decoded"),
        (b"\x89PNG\r\n\x1a\n" + bytes(30), 400, "could not be decoded"),
    ],
)
def test_corrupt_image_is_4xx_with_reason(client: TestClient, data: bytes, status: int, reason: str) -> None:
    response = client.post("/v1/detect", headers=auth(), **detect_parts(data))
    assert response.status_code == status and reason in response.json()["detail"]


def test_truncated_jpeg_is_refused_or_answered_never_5xx(client: TestClient, keyframe: bytes) -> None:
    response = client.post("/v1/detect", headers=auth(), **detect_parts(keyframe[: len(keyframe) // 3]))
    assert response.status_code in (200, 400)


def test_roi_limits_the_search(client: TestClient, keyframe: bytes) -> None:
    inside = client.post(
        "/v1/detect", headers=auth(), **detect_parts(keyframe, roi=[200, 80, 320, 200])
    ).json()
    elsewhere = client.post(
        "/v1/detect", headers=auth(), **detect_parts(keyframe, roi=[400, 200, 640, 360])
    ).json()
    assert inside["candidates"] and all(
        c["box"][0] >= 200 and c["box"][2] <= 320 for c in inside["candidates"]
    )
    assert elsewhere["candidates"] == []


def test_openapi_documents_the_api(client: TestClient) -> None:
    schema = client.get("/openapi.json").json()
    assert {
        "/v1/detect",
        "/health",
        "/v1/models",
        "/v1/missions/{mission_id}/rejections",
        "/v1/vehicles/{vehicle_id}/status",
        "/v1/vehicles/{vehicle_id}/decisions",
    } <= set(schema["paths"])
    assert "DetectResponse" in schema["components"]["schemas"]


metas = st.fixed_dictionaries(
    {},
    optional={
        "vehicle_id": st.one_of(st.just("drone-1"), st.text(max_size=70), st.integers()),
        "mission_id": st.one_of(st.just("m-1"), st.text(max_size=70), st.none()),
        "prompt": st.one_of(st.just("a man in a red jacket"), st.text(max_size=600), st.floats()),
        "superset": st.one_of(st.just("person"), st.text(max_size=70), st.none()),
        "roi": st.one_of(
            st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=5), st.text(max_size=5)
        ),
        "frame_id": st.one_of(st.integers(min_value=-(2**60), max_value=2**60), st.text(max_size=5)),
        "capture_time": st.one_of(st.floats(), st.text(max_size=5)),
        "vehicle_position": st.lists(st.floats(), max_size=3),
    },
)


@settings(
    max_examples=60,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    meta=st.one_of(metas, st.text(max_size=50)), image=st.one_of(st.binary(max_size=200), st.just(b"VALID"))
)
@pytest.mark.slow
def test_fuzzed_requests_never_cause_a_server_error(
    client: TestClient, keyframe: bytes, meta: object, image: bytes
) -> None:
    payload = keyframe if image == b"VALID" else image
    text = meta if isinstance(meta, str) else json.dumps(meta)
    response = client.post(
        "/v1/detect", headers=auth(), files={"image": ("k.jpg", payload, "image/jpeg")}, data={"meta": text}
    )
    assert response.status_code < 500, response.text
    assert response.status_code in (200, 400, 403, 413, 415, 422)


def test_supervisor_endpoints_need_the_supervisor_token(client: TestClient) -> None:
    assert client.get("/v1/vehicles", headers=auth()).status_code == 403
    assert client.get("/v1/vehicles", headers={"Authorization": f"Bearer {SUPERVISOR}"}).status_code == 200
    decision = {"candidate_id": "c1", "action": "confirm"}
    assert client.post("/v1/vehicles/drone-1/decisions", headers=auth(), json=decision).status_code == 403


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=30),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4),
    max_leaves=12,
)
status_bodies = st.fixed_dictionaries(
    {"state": st.one_of(st.just("AWAIT_SUPERVISOR"), json_values)},
    optional={
        "mission_id": json_values,
        "position": json_values,
        "altitude_m": json_values,
        "reason": json_values,
        "track_box": json_values,
        "frame_id": json_values,
        "progress": json_values,
        "search": st.one_of(
            json_values,
            st.fixed_dictionaries(
                {}, optional={"area": json_values, "covered": json_values, "coverage": json_values}
            ),
        ),
        "find": st.one_of(
            json_values,
            st.fixed_dictionaries({"candidate_id": st.text(max_size=70), "position": json_values}),
        ),
        "awaiting": st.one_of(
            json_values,
            st.fixed_dictionaries(
                {"candidate_id": st.text(max_size=70), "box": json_values},
                optional={"crop_jpeg_b64": st.text(max_size=20)},
            ),
        ),
    },
)


@settings(
    max_examples=80,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(
    route=st.sampled_from(
        ["/v1/vehicles/drone-1/status", "/v1/missions/m-1/rejections", "/v1/vehicles/drone-1/decisions"]
    ),
    body=st.one_of(json_values, status_bodies),
    as_supervisor=st.booleans(),
)
def test_fuzzed_session_requests_never_cause_a_server_error(
    client: TestClient, route: str, body: object, as_supervisor: bool
) -> None:
    headers = {"Authorization": f"Bearer {SUPERVISOR}"} if as_supervisor else auth()
    # Serialised here: NaN and Infinity literals go out as Python writes them, for the server to refuse.
    response = client.post(
        route, headers={**headers, "Content-Type": "application/json"}, content=json.dumps(body)
    )
    assert response.status_code < 500, response.text
    assert response.status_code in (200, 201, 403, 404, 413, 422)


@pytest.mark.parametrize(
    "body",
    [
        b"Infinity",
        b'{"state": NaN}',
        b'{"state": "x", "altitude_m": Infinity}',
        b'{"state": "x", "position": [1e999, 2]}',
    ],
)
def test_non_finite_json_is_422_not_a_crash(client: TestClient, body: bytes) -> None:
    response = client.post(
        "/v1/vehicles/drone-1/status", headers={**auth(), "Content-Type": "application/json"}, content=body
    )
    assert response.status_code == 422 and response.json()["detail"]
