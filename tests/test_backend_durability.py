"""The back-end as a real process (`cloudtrack-backend serve`): a SIGKILL after an acknowledged Reject loses
nothing (SQLite store), and 2,000 hostile requests leave its memory where it started. Select: -k durability.
"""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import requests

from backend_tools.fleet_services import BackendProcess
from tests.backend_fixtures import frame, jpeg

TOKENS = {"drone-1": "durability-drone-1-token", "drone-2": "durability-drone-2-token"}
SUPERVISOR = "durability-supervisor-token"
PROMPT = "the man in the green-and-white striped shirt"


def _settings(models_dir: Path, *extra: str) -> list[str]:
    return [f"detector.model_dir={json.dumps(str(models_dir))}", "detector.threads=1", *extra]


def _detect(url: str, keyframe: bytes, mission: str, vehicle: str = "drone-1") -> list[dict[str, Any]]:
    meta = {"vehicle_id": vehicle, "mission_id": mission, "prompt": PROMPT}
    response = requests.post(
        f"{url}/v1/detect",
        files={"image": ("k.jpg", keyframe, "image/jpeg")},
        data={"meta": json.dumps(meta)},
        headers={"Authorization": f"Bearer {TOKENS[vehicle]}"},
        timeout=60,
    )
    assert response.status_code == 200, response.text
    candidates: list[dict[str, Any]] = response.json()["candidates"]
    return candidates


@pytest.mark.slow
def test_durability_rejected_person_stays_rejected_after_sigkill(
    models_dir: Path, sequences_dir: Path, tmp_path: Path
) -> None:
    settings = _settings(models_dir, f"sessions.sqlite_path={json.dumps(str(tmp_path / 'sessions.sqlite3'))}")
    image = frame(sequences_dir)
    keyframe = jpeg(image)
    drone = {"Authorization": f"Bearer {TOKENS['drone-1']}"}
    with BackendProcess(settings, TOKENS, SUPERVISOR) as server:
        first = _detect(server.url, keyframe, "m-restart")
        best = max(first, key=lambda c: c["score"])
        x1, y1, x2, y2 = (int(v) for v in best["box"])
        crop = base64.b64encode(jpeg(image[y1:y2, x1:x2], 90)).decode()
        awaiting = {"candidate_id": best["candidate_id"], "box": best["box"], "crop_jpeg_b64": crop}
        status = {"mission_id": "m-restart", "state": "AWAITING_SUPERVISOR", "awaiting": awaiting}
        assert (
            requests.post(
                f"{server.url}/v1/vehicles/drone-1/status", json=status, headers=drone, timeout=10
            ).status_code
            == 200
        )
        url = f"{server.url}/v1/vehicles/drone-1/decisions?require_awaiting=true"
        reject = requests.post(
            url,
            json={"candidate_id": best["candidate_id"], "action": "reject", "note": "not him"},
            headers={"Authorization": f"Bearer {SUPERVISOR}"},
            timeout=10,
        )
        assert reject.status_code == 201, reject.text
        server.kill()  # right after the 201: nothing gets a chance to flush
    with BackendProcess(settings, TOKENS, SUPERVISOR) as restarted:
        again = _detect(restarted.url, keyframe, "m-restart")
        same = max(again, key=lambda c: c["score"])
        assert same["verifier"] == "rejection-memory" and same["verdict"] == "no", same
        decisions = requests.get(
            f"{restarted.url}/v1/vehicles/drone-1/decisions", headers=drone, timeout=10
        ).json()
        assert [(d["candidate_id"], d["action"], d["note"]) for d in decisions] == [
            (best["candidate_id"], "reject", "not him")
        ]
        # Another mission of the same vehicle starts with a clean memory.
        assert all(c["verifier"] != "rejection-memory" for c in _detect(restarted.url, keyframe, "m-other"))


def _header_bomb(width: int, height: int) -> bytes:
    data = bytearray(cv2.imencode(".jpg", np.full((16, 16, 3), 128, np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = height.to_bytes(2, "big") + width.to_bytes(2, "big")
    return bytes(data)


@pytest.mark.slow
def test_durability_memory_stays_flat_under_2000_hostile_requests(
    models_dir: Path, sequences_dir: Path, tmp_path: Path
) -> None:
    settings = _settings(
        models_dir,
        f"sessions.sqlite_path={json.dumps(str(tmp_path / 's.sqlite3'))}",
        "sessions.rate_limit_requests=100000",
    )  # let every hostile request reach its check
    keyframe = jpeg(frame(sequences_dir))
    bomb = _header_bomb(16000, 16000)
    crop_bomb = base64.b64encode(_header_bomb(8700, 8700)).decode()
    with BackendProcess(settings, TOKENS, SUPERVISOR) as server:
        for _ in range(3):  # warm up: models loaded, first allocations done
            _detect(server.url, keyframe, "warm")
        start_rss = server.rss_bytes()
        codes: dict[int, int] = {}
        with requests.Session() as http:
            http.headers["Authorization"] = f"Bearer {TOKENS['drone-2']}"
            for i in range(2000):
                kind = i % 4
                if kind == 0:  # keyframe bomb
                    meta = {"vehicle_id": "drone-2", "mission_id": "bombs", "prompt": PROMPT}
                    r = http.post(
                        f"{server.url}/v1/detect",
                        files={"image": ("b.jpg", bomb, "image/jpeg")},
                        data={"meta": json.dumps(meta)},
                        timeout=10,
                    )
                elif kind == 1:  # rejection crop bomb
                    r = http.post(
                        f"{server.url}/v1/missions/bombs/rejections",
                        json={"vehicle_id": "drone-2", "crop_jpeg_b64": crop_bomb},
                        timeout=10,
                    )
                else:  # a flood of new missions
                    r = http.post(
                        f"{server.url}/v1/vehicles/drone-2/status",
                        json={"mission_id": f"flood-{i}", "state": "SEARCH"},
                        timeout=10,
                    )
                codes[r.status_code] = codes.get(r.status_code, 0) + 1
        end_rss = server.rss_bytes()
    assert set(codes) <= {200, 413, 429}, codes
    assert codes.get(413, 0) == 1000 and codes.get(429, 0) >= 900, codes
    grown_mb = (end_rss - start_rss) / 1e6
    print(
        f"RSS {start_rss / 1e6:.1f} MB -> {end_rss / 1e6:.1f} MB after 2000 hostile requests ({grown_mb:+.1f} MB)"
    )
    assert grown_mb < 50, grown_mb
