"""The client side of the back-end API: send a keyframe, get verified candidates back.

Used by the companion on the drone and by the back-end's own benchmarks, so it lives here and neither
process package imports the other.

Keyframes are downscaled to `max_width` and JPEG-encoded before sending (a 640x480 keyframe is about
30-60 KB at quality 80, against 1.2 MB of pickled raw pixels in the reference code); boxes in the answer
are scaled back to the caller's pixels. Every HTTP, timeout or format problem raises `BackendError`.
Every reply is validated with the back-end's own response models (`cloudtrack.api_models`, pydantic only:
no server-side imports here, this runs on the drone); multipart bodies are built by urllib3's encoder.
"""

from __future__ import annotations

import base64
import json
import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import cv2
import numpy as np
import requests
from pydantic import TypeAdapter, ValidationError
from urllib3 import encode_multipart_formdata
from urllib3.fields import RequestField

from behaviors.detection import Detection, Verdict
from behaviors.geometry import Box
from cloudtrack.api_models import (
    Decision,
    DetectResponse,
    FleetOrder,
    HealthResponse,
    OnFindIn,
    PromptCheckAnswer,
    Rejection,
    VehicleStatus,
)
from cloudtrack.config_files import hide_url_secrets
from cloudtrack.connection_errors import connection_cause

T = TypeVar("T")

log = logging.getLogger(__name__)


class BackendError(Exception):
    """The back-end did not answer usefully. `status` is the HTTP status (None: no HTTP answer);
    `retryable` says whether the same request may succeed later (timeouts, 429, 5xx, connection)."""

    def __init__(
        self, message: str, status: int | None = None, retryable: bool = False, detail: str = ""
    ) -> None:
        super().__init__(message)
        self.status = status
        self.retryable = retryable
        self.detail = detail or message  # the back-end's own words (its `detail`), for a person


@dataclass(frozen=True)
class DetectReply:
    detections: list[Detection]  # boxes in the caller's pixels
    timings: dict[str, float]  # the back-end's t_queue, t_decode, t_detect, t_verify, t_total
    models: dict[str, str]
    request_bytes: int  # the whole multipart body
    jpeg_bytes: int
    raw: DetectResponse | None = None  # the validated answer
    final: bool = True  # false: the fast stage's verdicts (asked with stage "early")


@dataclass(frozen=True)
class EncodedKeyframe:
    """A keyframe as it goes on the wire: its JPEG bytes, the scale applied to the caller's pixels (<= 1)
    and the caller's image size (width, height). The companion keeps keyframes this way through a back-end
    outage (`companion.cloud.keyframe_store`) and sends them later as they are."""

    jpeg: bytes
    scale: float
    size: tuple[int, int]


def encode_keyframe(
    image: np.ndarray, max_width: int, jpeg_quality: int, max_bytes: int = 90_000
) -> tuple[bytes, float]:
    """JPEG bytes of the keyframe downscaled to at most `max_width`, and the scale applied (<= 1).

    A busy scene (foliage, water glare, sensor noise) can double a JPEG's size; past `max_bytes` the
    quality drops in steps to 40, then the frame shrinks, so one keyframe never clogs a 4G uplink.
    """
    if image.ndim != 3 or image.shape[2] != 3 or image.size == 0:
        raise ValueError(f"expected a BGR image H x W x 3, got shape {image.shape}")
    height, width = image.shape[:2]
    scale = min(1.0, max_width / width)
    quality = int(jpeg_quality)
    while True:
        sized = image
        if scale < 1.0:
            size = (max(1, round(width * scale)), max(1, round(height * scale)))
            sized = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        ok, buffer = cv2.imencode(".jpg", sized, [int(cv2.IMWRITE_JPEG_QUALITY), quality])
        if not ok:
            raise ValueError("JPEG encoding of the keyframe failed")
        if buffer.size <= max_bytes or sized.shape[1] <= 64:
            return buffer.tobytes(), sized.shape[1] / width
        if quality > 40:
            quality = max(40, quality - 15)
        else:
            scale = sized.shape[1] / width * 0.8


class BackendClient:
    def __init__(
        self,
        url: str,
        token: str,
        timeout_s: float = 5.0,
        jpeg_quality: int = 80,
        max_width: int = 640,
        vehicle_id: str | None = None,
        mission_id: str | None = None,
        max_keyframe_bytes: int = 90_000,
        on_keyframe: Callable[[bytes, int], object] | None = None,
    ) -> None:
        """`on_keyframe(jpeg, frame_id)` (the flight record) gets each keyframe's bytes exactly as sent."""
        self.url = url.rstrip("/")
        self.token = token
        self.timeout_s = timeout_s
        self.jpeg_quality = jpeg_quality
        self.max_width = max_width
        self.vehicle_id = vehicle_id
        self.mission_id = mission_id
        self.max_keyframe_bytes = max_keyframe_bytes
        self._on_keyframe = on_keyframe
        self._local = threading.local()
        self.last_reply: DetectReply | None = None

    def encode(self, image: np.ndarray) -> EncodedKeyframe:
        """The keyframe exactly as `detect` would send it."""
        jpeg, scale = encode_keyframe(image, self.max_width, self.jpeg_quality, self.max_keyframe_bytes)
        return EncodedKeyframe(jpeg, scale, (int(image.shape[1]), int(image.shape[0])))

    def _session(self) -> requests.Session:
        session = getattr(self._local, "session", None)
        if session is None:
            session = self._local.session = requests.Session()
            session.headers["Authorization"] = f"Bearer {self.token}"
            if self.vehicle_id:  # lets a load balancer keep a vehicle on one replica (docs/backend.md)
                session.headers["X-CloudTrack-Vehicle"] = self.vehicle_id
        return session

    def _call(self, method: str, path: str, reply: TypeAdapter[T], **kwargs: Any) -> T:
        """One request; the JSON answer validated as `reply` (BackendError when it does not fit)."""
        try:
            response = self._session().request(method, self.url + path, timeout=self.timeout_s, **kwargs)
        except requests.Timeout as exc:
            raise BackendError(
                f"back-end {hide_url_secrets(self.url)}: no answer within {self.timeout_s:.1f} s",
                retryable=True,
                detail=f"no answer within {self.timeout_s:.1f} s",
            ) from exc
        except requests.RequestException as exc:
            # The message may reach the GCS and the flight record: never a password of the URL.
            cause = connection_cause(exc)
            raise BackendError(
                hide_url_secrets(f"back-end {self.url} unreachable: {cause}"), retryable=True, detail=cause
            ) from exc
        if response.status_code >= 400:
            try:
                detail = response.json().get("detail", response.text)
            except ValueError:
                detail = response.text[:300]
            retryable = response.status_code == 429 or response.status_code >= 500
            raise BackendError(
                f"back-end {path}: HTTP {response.status_code}: {detail}",
                response.status_code,
                retryable,
                detail if isinstance(detail, str) else "; ".join(str(d.get("msg", d)) for d in detail)[:300],
            )
        try:
            return reply.validate_json(response.content)
        except ValidationError as exc:
            problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors()[:3])
            raise BackendError(
                f"back-end {path}: malformed answer: {problems}", response.status_code
            ) from exc

    def detect_reply(
        self,
        image: np.ndarray | EncodedKeyframe,
        prompt: str,
        superset: str | None = None,
        vehicle_id: str | None = None,
        mission_id: str | None = None,
        frame_id: int | None = None,
        capture_time: float | None = None,
        roi: Box | None = None,
        vehicle_position: Sequence[float] | None = None,
        stage: str = "final",
    ) -> DetectReply:
        """Send one keyframe; the full answer with timings and sizes. `stage` "early" asks for the fast
        stage's verdicts (see `DetectMeta.stage`). An `EncodedKeyframe` goes as it is (it was recorded when
        it was first tried)."""
        vehicle = vehicle_id or self.vehicle_id
        mission = mission_id or self.mission_id
        if not vehicle or not mission:
            raise ValueError("vehicle_id and mission_id are needed (per call or in the BackendClient)")
        encoded = image if isinstance(image, EncodedKeyframe) else self.encode(image)
        jpeg, scale = encoded.jpeg, encoded.scale
        if self._on_keyframe is not None and frame_id is not None and encoded is not image:
            try:
                self._on_keyframe(jpeg, int(frame_id))
            except OSError as exc:  # recording must never cost a query
                log.warning("keyframe not recorded: %s", exc)
        meta: dict[str, Any] = {"vehicle_id": vehicle, "mission_id": mission, "prompt": prompt}
        if superset:
            meta["superset"] = superset
        if frame_id is not None:
            meta["frame_id"] = int(frame_id)
        if capture_time is not None:
            meta["capture_time"] = float(capture_time)
        if roi is not None:
            meta["roi"] = [round(v * scale, 2) for v in roi.xyxy()]
        if vehicle_position is not None:
            meta["vehicle_position"] = [float(v) for v in vehicle_position]
        if stage != "final":
            meta["stage"] = stage
        body, content_type = _multipart(jpeg, json.dumps(meta))
        headers = {
            "Content-Type": content_type,
            "X-CloudTrack-Vehicle": vehicle,
            "X-CloudTrack-Mission": mission,
        }
        answer = self._call("POST", "/v1/detect", _DETECT, data=body, headers=headers)
        try:
            detections = [
                Detection(
                    box=Box.from_xyxy(*(v / scale for v in c.box)),
                    body_box=Box.from_xyxy(*(v / scale for v in c.body_box)) if c.body_box else None,
                    score=c.score,
                    label=c.label,
                    verdict=Verdict(c.verdict),
                    justification=c.justification,
                    candidate_id=c.candidate_id,
                    judged=c.judged,
                    placement_ok=c.placement_ok,
                    unjudged=tuple(c.unjudged),
                    singled_out=c.singled_out,
                )
                for c in answer.candidates
            ]
        except (TypeError, ValueError) as exc:  # e.g. a box that is not 4 numbers
            raise BackendError(f"back-end /v1/detect: malformed answer: {exc}") from exc
        reply = DetectReply(
            detections,
            answer.timings.model_dump(),
            answer.models.model_dump(),
            len(body),
            len(jpeg),
            answer,
            answer.final,
        )
        self.last_reply = reply
        return reply

    def detect(
        self,
        image: np.ndarray | EncodedKeyframe,
        prompt: str,
        superset: str | None = None,
        vehicle_id: str | None = None,
        mission_id: str | None = None,
        frame_id: int | None = None,
        capture_time: float | None = None,
        roi: Box | None = None,
        vehicle_position: Sequence[float] | None = None,
    ) -> list[Detection]:
        """Candidates for one keyframe, boxes in `image`'s pixels; raises BackendError on any failure."""
        return self.detect_reply(
            image, prompt, superset, vehicle_id, mission_id, frame_id, capture_time, roi, vehicle_position
        ).detections

    def detect_early(
        self, image: np.ndarray | EncodedKeyframe, **fields: Any
    ) -> tuple[list[Detection], bool]:
        """The fast stage's candidates for one keyframe and whether they are final (the back-end has no
        slower stage); as `detect` otherwise."""
        reply = self.detect_reply(image, stage="early", **fields)
        return reply.detections, reply.final

    def health(self) -> HealthResponse:
        return self._call("GET", "/health", _HEALTH)

    def check_prompt(self, prompt: str, superset: str | None = None) -> PromptCheckAnswer:
        """Whether the back-end would search for `prompt` (BackendError 422 with its reason when not)."""
        body = {"prompt": prompt, "superset": superset or None}
        return self._call("POST", "/v1/prompts/check", _PROMPT_CHECK, json=body)

    def report_status(self, state: str, vehicle_id: str | None = None, **fields: Any) -> VehicleStatus:
        """POST the companion's state (and `awaiting` candidate, see cloudtrack.api_models.VehicleStatusIn)."""
        vehicle = vehicle_id or self.vehicle_id
        body = {"state": state, "mission_id": fields.pop("mission_id", self.mission_id), **fields}
        return self._call("POST", f"/v1/vehicles/{vehicle}/status", _STATUS, json=body)

    def reject(
        self,
        candidate_id: str | None,
        crop_bgr: np.ndarray | None = None,
        position: Sequence[float] | None = None,
        reason: str = "",
        mission_id: str | None = None,
        crop_box: Box | None = None,
    ) -> Rejection:
        """Tell the back-end a candidate was rejected so it is not proposed again in this mission.

        `crop_bgr` (with `crop_box`, the candidate inside it) lets any replica match it without its id.
        """
        body: dict[str, Any] = {"vehicle_id": self.vehicle_id, "candidate_id": candidate_id, "reason": reason}
        if crop_bgr is not None:
            body["crop_jpeg_b64"] = crop_to_base64(crop_bgr)
        if crop_box is not None:
            body["crop_box"] = list(crop_box.xyxy())
        if position is not None:
            body["position"] = [float(v) for v in position]
        return self._call(
            "POST", f"/v1/missions/{mission_id or self.mission_id}/rejections", _REJECTION, json=body
        )

    def set_on_find(self, mission_id: str, on_find: str) -> OnFindIn:
        """Set what the fleet does on the mission's first confirmed find (BackendError 409 naming the
        setting that stands when another was set first)."""
        return self._call("PUT", f"/v1/missions/{mission_id}/on_find", _ON_FIND, json={"on_find": on_find})

    def fleet_order(self, mission_id: str) -> FleetOrder:
        """What this vehicle of the fleet mission is to do now (behaviors/fleet_order.py)."""
        return self._call("GET", f"/v1/missions/{mission_id}/fleet", _FLEET_ORDER)

    def decisions(self, after: int = 0, vehicle_id: str | None = None) -> list[Decision]:
        """Supervisor decisions for this vehicle newer than decision id `after`."""
        return self._call(
            "GET",
            f"/v1/vehicles/{vehicle_id or self.vehicle_id}/decisions",
            _DECISIONS,
            params={"after": after},
        )


def crop_to_base64(crop_bgr: np.ndarray, quality: int = 85) -> str:
    """A crop as base64 JPEG, the form the status and rejection endpoints take."""
    ok, buffer = cv2.imencode(".jpg", crop_bgr, [int(cv2.IMWRITE_JPEG_QUALITY), quality])
    if not ok:
        raise ValueError("JPEG encoding of the crop failed")
    return base64.b64encode(buffer.tobytes()).decode()


def _multipart(jpeg: bytes, meta_json: str) -> tuple[bytes, str]:
    """The multipart/form-data body, built by urllib3 (here, so its exact size is known and reported)."""
    meta = RequestField("meta", meta_json)
    meta.make_multipart(content_type="application/json")
    image = RequestField("image", jpeg, filename="keyframe.jpg")
    image.make_multipart(content_type="image/jpeg")
    return encode_multipart_formdata([meta, image])


_DETECT = TypeAdapter(DetectResponse)
_HEALTH = TypeAdapter(HealthResponse)
_PROMPT_CHECK = TypeAdapter(PromptCheckAnswer)
_STATUS = TypeAdapter(VehicleStatus)
_REJECTION = TypeAdapter(Rejection)
_DECISIONS = TypeAdapter(list[Decision])
_ON_FIND = TypeAdapter(OnFindIn)
_FLEET_ORDER = TypeAdapter(FleetOrder)
