"""Helpers shared by the back-end tests: a configured app on the real YOLOX detector and real frames."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from backend.config import BackendConfig
from cloudtrack.config_files import load_config

TOKENS = {"drone-1": "drone-1-token-one", "drone-2": "drone-2-token-two"}
SUPERVISOR = "token-supervisor"


def backend_config(models_dir: Path, *settings: str) -> BackendConfig:
    return load_config(
        BackendConfig,
        None,
        environ={},
        assignments=[
            f"auth.tokens={json.dumps(TOKENS)}",
            f'auth.supervisor_token="{SUPERVISOR}"',
            f'detector.model_dir="{models_dir}"',
            "detector.threads=1",
            'sessions.sqlite_path=":memory:"',
            *settings,
        ],
    )


def frame(
    sequences_dir: Path,
    name: str = "uav123_person12_1",
    index: int = 1,
    size: tuple[int, int] | None = (640, 360),
) -> np.ndarray:
    image = cv2.imread(str(sequences_dir / name / "frames" / f"{index:06d}.jpg"))
    assert image is not None
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA) if size else image


def jpeg(image: np.ndarray, quality: int = 80) -> bytes:
    ok, data = cv2.imencode(".jpg", image, [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    assert ok
    return data.tobytes()


def auth(vehicle: str = "drone-1") -> dict[str, str]:
    return {"Authorization": f"Bearer {TOKENS[vehicle]}"}


def detect_parts(image_bytes: bytes, **meta: Any) -> dict[str, Any]:
    fields = {
        "vehicle_id": "drone-1",
        "mission_id": "m-1",
        "prompt": "the man in the green-and-white striped shirt",
    }
    fields.update(meta)
    return {"files": {"image": ("k.jpg", image_bytes, "image/jpeg")}, "data": {"meta": json.dumps(fields)}}
