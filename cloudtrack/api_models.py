"""The back-end's HTTP API as pydantic models, shared by the back-end (which serves them) and the companion
(which validates every reply with them). These classes are the API reference (see /docs).

Only pydantic here: the companion imports this module on the drone, without the server stack.
Boxes on the wire are `[x1, y1, x2, y2]` in the pixels of the image that was sent. Times are seconds.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from cloudtrack.plain_text import without_controls

IDENTIFIER = r"^[A-Za-z0-9_.-]{1,64}$"
ID_FIELD = Field(pattern=IDENTIFIER, description="letters, digits, '_', '.', '-'; 1-64 characters")
# Candidate ids become path segments of the supervisor page's URLs: the same safe alphabet, never '/'.
CANDIDATE_ID = Field(
    pattern=IDENTIFIER, description="as returned by /v1/detect (letters, digits, '_', '.', '-')"
)
NOTE_MAX = 500  # one limit for a supervisor's note, on the API and on the page
CROP_B64_MAX_CHARS = 400_000  # a crop in base64 (about 300 kB of JPEG); the route body limits follow it
ALIKE_MAX = 1000  # others alike a candidate, as a status says it (a detect answer has at most a few dozen)
PIXELS_MAX = 100_000  # no coordinate in pixels lies further out than this


# Text a vehicle, a verifier or an operator wrote: control characters (those XML 1.0 forbids among them) are
# stripped on the way in, so nothing the back-end stores or exports (page, KML, Cursor-on-Target) holds one.
PlainText = Annotated[str, AfterValidator(without_controls)]


class ApiModel(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def _lat_lon(value: list[float]) -> list[float]:
    if not (-90 <= value[0] <= 90 and -180 <= value[1] <= 180):
        raise ValueError("a position is [lat, lon] in degrees: lat in [-90, 90], lon in [-180, 180]")
    return value


# A checked [lat, lon]: two finite numbers (ApiModel refuses NaN/inf) within the globe's ranges.
LatLonPoint = Annotated[list[float], Field(min_length=2, max_length=2), AfterValidator(_lat_lon)]


def _pixel_box(value: list[float]) -> list[float]:
    if not all(-PIXELS_MAX <= v <= PIXELS_MAX for v in value):
        raise ValueError(f"box coordinates are pixels within +-{PIXELS_MAX}")
    if not (value[2] > value[0] and value[3] > value[1]):
        raise ValueError("a box is [x1, y1, x2, y2] with x2 > x1 and y2 > y1")
    return value


# A checked [x1, y1, x2, y2] in pixels: finite, ordered, within PIXELS_MAX.
PixelBox = Annotated[list[float], Field(min_length=4, max_length=4), AfterValidator(_pixel_box)]


class DetectMeta(ApiModel):
    """The JSON `meta` part of `POST /v1/detect`."""

    vehicle_id: str = ID_FIELD
    mission_id: str = ID_FIELD
    prompt: PlainText = Field(
        min_length=1, max_length=500, description='full description, e.g. "an injured man in a gray shirt"'
    )
    superset: PlainText | None = Field(
        None,
        min_length=1,
        max_length=64,
        description='detector class, e.g. "person"; default: derived from the prompt',
    )
    roi: PixelBox | None = Field(
        None, description="[x1, y1, x2, y2] region to search, in the sent image's pixels"
    )
    frame_id: int | None = Field(None, ge=0, le=2**53)
    capture_time: float | None = Field(None, description="Unix time the frame was captured (s)")
    vehicle_position: LatLonPoint | None = Field(
        None, description="[lat, lon] degrees, lets rejections be matched by place"
    )
    stage: Literal["final", "early"] = Field(
        "final",
        description='"early": verify with the back-end\'s fast stage only (its local verifier, before a '
        "hosted VLM) so a search can start moving while the final verdicts are on their way; the answer's "
        "`final` says whether it was the whole verifier",
    )

    @field_validator("prompt")
    @classmethod
    def _prompt_has_words(cls, value: str) -> str:
        text = " ".join(value.split())
        if not any(ch.isalpha() for ch in text):
            raise ValueError("the prompt must describe the target in words")
        return text

    @field_validator("capture_time")
    @classmethod
    def _finite_time(cls, value: float | None) -> float | None:
        if value is not None and not math.isfinite(value):
            raise ValueError("capture_time must be a finite number")
        return value


class PromptCheck(ApiModel):
    """`POST /v1/prompts/check`: would the back-end search for this prompt?"""

    prompt: PlainText = Field(min_length=1, max_length=500)
    superset: PlainText | None = Field(None, min_length=1, max_length=64)


class PromptCheckAnswer(ApiModel):
    superset: str = Field(description="the detector class the search will look for")
    detector: str
    warning: str | None = Field(
        None, description="the prompt's words name something outside the given superset (the search goes on)"
    )


class Candidate(ApiModel):
    candidate_id: str = CANDIDATE_ID
    box: list[float] = Field(description="[x1, y1, x2, y2] in the sent image's pixels")
    body_box: list[float] | None = Field(
        None,
        min_length=4,
        max_length=4,
        description="[x1, y1, x2, y2]: the person's extent as the verifier measured it (null: not measured); "
        "a new track starts on it",
    )
    score: float = Field(description="detector confidence 0-1")
    label: PlainText = Field(description="detector class")
    verdict: Literal["yes", "no", "uncertain"]
    justification: PlainText
    judged: bool = Field(
        True,
        description="false: nothing judged the description past the detector's class (no verifier, or it "
        'can check nothing the prompt names); the verdict is then "uncertain" and a search may start on it',
    )
    placement_ok: bool | None = Field(
        None,
        description="whether the candidate stands where the description places the target among what else "
        'is in view, and has the size it states ("the second from the left", "next to the red car", outside '
        '"the boat" a wakeboarder is towed behind, "the small truck"); null: nothing of that could be judged. '
        "A search prefers candidates that are true, then null, then false; it never rejects one for it",
    )
    singled_out: bool = Field(
        False,
        description='an ordinal in the description ("the second from the left", "closest to the camera", '
        '"first in the queue") picks this candidate alone among those of its kind not ruled out, and it fits '
        'the rest of where the description places it: a search may start on it while its verdict is "uncertain"',
    )
    unjudged: list[Annotated[PlainText, Field(max_length=200)]] = Field(
        default_factory=list,
        max_length=32,
        description='the description\'s words nothing judged for this candidate ("suv", "canopy roof", "next to '
        'the pier (the pier: not located)"): the verdict and placement hold for the rest only',
    )
    verifier: PlainText = Field(description='who decided: a verifier name, "none" or "rejection-memory"')
    t_verify: float
    previously_rejected: bool = Field(
        False, description="matches a candidate the supervisor rejected in this mission"
    )


class Timings(ApiModel):
    t_queue: float = Field(description="waiting for a detector slot")
    t_decode: float
    t_detect: float
    t_verify: float = Field(description="all candidates, verified concurrently")
    t_total: float = Field(description="from request received to answer")


class ModelNames(ApiModel):
    detector: str
    verifier: str


class DetectResponse(ApiModel):
    vehicle_id: str
    mission_id: str
    frame_id: int | None
    capture_time: float | None
    image_size: list[int] = Field(description="[width, height] of the sent image")
    superset: str
    candidates: list[Candidate]
    final: bool = Field(
        True,
        description='false: the verdicts are the fast stage\'s (asked with stage "early"); the final verifier '
        "may still judge the same keyframe otherwise",
    )
    timings: Timings
    models: ModelNames


class ErrorResponse(ApiModel):
    detail: str | list[dict[str, object]] = Field(
        description="the reason, or (422) the first few validation errors: {type, loc, msg}"
    )
    error_count: int | None = Field(None, description="422: how many validation errors there were")


class HealthResponse(ApiModel):
    status: Literal["ok"]
    version: str
    uptime_s: float
    models: ModelNames
    in_flight: int
    queued: int


class ModelsResponse(ApiModel):
    detector: str
    detector_kind: str
    supersets: list[str] = Field(
        description="superset names the detector maps; open-vocabulary detectors take any"
    )
    verifier: str
    verifier_kind: str


# Sessions: what the companion reports and what the supervisor decides.

GeoPoint = list[float]


class RejectionIn(ApiModel):
    """A candidate the supervisor rejected: never proposed again in this mission."""

    vehicle_id: str = ID_FIELD
    candidate_id: str | None = Field(None, pattern=IDENTIFIER, description="as returned by /v1/detect")
    crop_jpeg_b64: str | None = Field(
        None,
        max_length=CROP_B64_MAX_CHARS,
        description="the candidate's crop, when the back-end may not know the id",
    )
    crop_box: PixelBox | None = Field(
        None, description="[x1, y1, x2, y2] of the candidate inside the crop; default: all of it"
    )
    position: LatLonPoint | None = Field(None, description="[lat, lon] of the candidate")
    reason: PlainText = Field("", max_length=500)


class Rejection(ApiModel):
    rejection_id: int
    mission_id: str
    vehicle_id: str
    candidate_id: str | None
    position: GeoPoint | None
    reason: PlainText
    created_at: float


class AwaitingCandidate(ApiModel):
    candidate_id: str = CANDIDATE_ID
    box: PixelBox = Field(description="[x1, y1, x2, y2] in the keyframe")
    verdict: Literal["yes", "no", "uncertain"] = "yes"
    justification: PlainText = Field("", max_length=2000)
    unjudged: list[Annotated[PlainText, Field(max_length=200)]] = Field(
        default_factory=list,
        max_length=32,
        description="the description's words the back-end could not judge for this candidate: the supervisor "
        "checks them by eye",
    )
    alike: int = Field(
        0,
        ge=0,
        le=ALIKE_MAX,
        description="other candidates of the same answer the search could have taken as well (the same verdict "
        "and placement): it was chosen among them by the detector's score alone",
    )
    crop_jpeg_b64: str | None = Field(None, max_length=CROP_B64_MAX_CHARS)
    crop_box: PixelBox | None = Field(
        None, description="[x1, y1, x2, y2] of the candidate inside the crop; default: all of it"
    )
    position: LatLonPoint | None = Field(None, description="[lat, lon] estimate")
    seen_at: float | None = Field(
        None, ge=0.0, le=2**34, description="Unix time the position was observed (s); null: not known"
    )


SEARCH_AREA_MAX_VERTICES = 200
COVERED_MAX_RINGS = 20
COVERED_MAX_VERTICES = 500


class SearchProgress(ApiModel):
    """How far the mission's search has come (counted by the companion since the mission started)."""

    keyframes: int = Field(0, ge=0, le=2**31, description="keyframes the back-end checked this mission")
    detections: int | None = Field(
        None,
        ge=0,
        le=2**31,
        description="boxes the back-end returned, counted per keyframe (null: not counted)",
    )
    candidates: int = Field(
        0, ge=0, le=2**31, description="distinct candidates put to the supervisor (a decision asked for)"
    )
    rejected: int = Field(0, ge=0, le=2**31, description="candidates rejected (supervisor, GCS or memory)")


POD_MAX_CELLS = 4096  # cloudtrack.pod_map.MAX_CELLS (a test holds them equal)
POD_VALUES_MAX_CHARS = 4 * -(-POD_MAX_CELLS // 3)  # that many bytes in base64
POD_CELL_M = (0.1, 5000.0)
POD_EXTENT_MAX_M = 200_000.0  # a grid's longer side: far beyond any survey a vehicle flies


class PodGrid(ApiModel):
    """The search's probability-of-detection (POD) map: per place, the chance that the search would have found
    the target there had it been there, from the keyframes the back-end analysed (`cloudtrack.pod_map`).
    A north-up grid of square cells from its south-west corner; one byte a cell."""

    target: PlainText = Field(
        min_length=1, max_length=64, description='the target class it is for, e.g. "person"'
    )
    posture: PlainText = Field(min_length=1, max_length=32, description='e.g. "standing", "lying"')
    target_pod: float = Field(ge=0.0, le=1.0, description="the POD the operator plans for, e.g. 0.8")
    origin: LatLonPoint = Field(description="[lat, lon] of the grid's south-west corner")
    cell_m: float = Field(ge=POD_CELL_M[0], le=POD_CELL_M[1], description="a cell's side (m)")
    rows: int = Field(ge=1, le=POD_MAX_CELLS, description="cells south to north")
    cols: int = Field(
        ge=1, le=POD_MAX_CELLS, description=f"cells west to east; rows * cols <= {POD_MAX_CELLS}"
    )
    values: str = Field(
        min_length=4,
        max_length=POD_VALUES_MAX_CHARS,
        description="base64 of rows * cols bytes, row by row from the south-west: round(POD * 250), "
        "255 outside the search area",
    )
    mean: float = Field(ge=0.0, le=1.0, description="mean POD over the area")
    at_target: float = Field(ge=0.0, le=1.0, description="share of the area at or above target_pod")
    looks: int = Field(ge=0, le=2**31, description="analysed keyframes laid on the map")
    dark_looks: int = Field(
        0,
        ge=0,
        le=2**31,
        description="analysed keyframes too dark for the detection curve (mean luma two stops under "
        "mid-grey, behaviors.scene_light): they lay coverage but no POD",
    )

    @field_validator("cols")
    @classmethod
    def _cells_bounded(cls, value: int, info: ValidationInfo) -> int:
        rows = info.data.get("rows")
        if rows is not None and rows * value > POD_MAX_CELLS:
            raise ValueError(f"a POD grid holds at most {POD_MAX_CELLS} cells (rows * cols)")
        cell = info.data.get("cell_m")
        if rows is not None and cell is not None and max(rows, value) * cell > POD_EXTENT_MAX_M:
            raise ValueError(f"a POD grid spans at most {POD_EXTENT_MAX_M / 1000:g} km")
        return value

    @field_validator("values")
    @classmethod
    def _values_decode(cls, value: str, info: ValidationInfo) -> str:
        rows, cols = info.data.get("rows"), info.data.get("cols")
        if rows is None or cols is None:
            return value  # refused for rows / cols already
        if len(value) != 4 * -(-(rows * cols) // 3):
            raise ValueError(
                f"a POD grid of {rows} x {cols} is {4 * -(-(rows * cols) // 3)} base64 characters"
            )
        # Here, not at the top: the grid code needs numpy, which the models' other users do without.
        from cloudtrack.pod_map import decode_grid

        try:
            decode_grid({"rows": rows, "cols": cols, "values": value})
        except (ValueError, TypeError) as exc:  # binascii.Error is a ValueError
            raise ValueError(str(exc) if "POD" in str(exc) else "values is not base64") from None
        return value


class SearchStatus(ApiModel):
    """The area search: the polygon, how much of it the camera has seen, where the autopilot's mission is."""

    area: list[LatLonPoint] = Field(
        default_factory=list,
        max_length=SEARCH_AREA_MAX_VERTICES,
        description=f"the search polygon, [[lat, lon], ...] (at most {SEARCH_AREA_MAX_VERTICES} vertices)",
    )
    coverage: float = Field(0.0, ge=0.0, le=1.0, description="share of the area the camera has seen, 0..1")
    covered: list[list[LatLonPoint]] = Field(
        default_factory=list,
        max_length=COVERED_MAX_RINGS,
        description=f"the seen area, simplified: at most {COVERED_MAX_RINGS} rings of [lat, lon], "
        f"{COVERED_MAX_VERTICES} vertices in all",
    )
    mission_item: int | None = Field(None, ge=0, le=65535, description="the autopilot's current mission item")
    mission_items: int | None = Field(None, ge=0, le=65535, description="items in the autopilot's mission")
    mode: PlainText = Field(
        "", max_length=32, description='the autopilot\'s flight mode, e.g. "AUTO", "GUIDED"'
    )
    pod: PodGrid | None = Field(
        None, description="the POD map of the area (null: the companion keeps none, e.g. no detection curve)"
    )

    @field_validator("covered")
    @classmethod
    def _covered_bounded(cls, value: list[list[list[float]]]) -> list[list[list[float]]]:
        if sum(len(ring) for ring in value) > COVERED_MAX_VERTICES:
            raise ValueError(f"covered holds more than {COVERED_MAX_VERTICES} vertices in all")
        return value


class Find(ApiModel):
    """A confirmed find: where, when, what was searched for and who confirmed it."""

    candidate_id: str = CANDIDATE_ID
    position: LatLonPoint = Field(description="[lat, lon] of the person found")
    sigma_m: float | None = Field(
        ge=0.0, le=100_000.0, description="1-sigma horizontal uncertainty (m); null: not known"
    )
    time: float = Field(ge=0.0, le=2**34, description="Unix time of the confirmation (s)")
    seen_at: float | None = Field(
        None,
        ge=0.0,
        le=2**34,
        description="Unix time the position was observed (s): a person seen well a minute before the "
        "confirmation may have moved on since; null: not known",
    )
    prompt: PlainText = Field("", max_length=500)
    confirmed_by: PlainText = Field(
        max_length=64, description='"supervisor page", "gcs" or the operator\'s name'
    )
    crop_jpeg_b64: str | None = Field(
        None, max_length=CROP_B64_MAX_CHARS, description="the candidate's crop (JPEG)"
    )
    crop_box: PixelBox | None = Field(None, description="[x1, y1, x2, y2] of the person inside the crop")


QUEUE_IDS_MAX = 16  # candidate ids in a status's awaiting_more / dropped_undecided (the companion keeps 4)
CandidateId = Annotated[str, Field(pattern=IDENTIFIER)]


class KeyframeCounts(ApiModel):
    """The companion's keyframes since the mission started, and its store for the back-end's outages."""

    analysed: int = Field(
        0, ge=0, le=10**9, description="keyframes whose final answer came back and were laid on the map"
    )
    stored: int = Field(0, ge=0, le=10**9, description="kept while the back-end was unreachable")
    waiting: int = Field(0, ge=0, le=10**9, description="in the store now")
    sent: int = Field(0, ge=0, le=10**9, description="stored ones sent after the link came back")
    dropped: int = Field(
        0, ge=0, le=10**9, description="stored ones dropped, oldest first, by the store's byte or age bound"
    )


class VehicleStatusIn(ApiModel):
    mission_id: str | None = Field(None, pattern=IDENTIFIER)
    state: PlainText = Field(
        max_length=64, description="the companion's mission state, e.g. SEARCH, TRACK, AWAIT_SUPERVISOR"
    )
    prompt: PlainText | None = Field(None, max_length=500)
    superset: PlainText | None = Field(None, max_length=64, description="the superset the GCS gave, if any")
    position: LatLonPoint | None = Field(None, description="[lat, lon] of the vehicle")
    altitude_m: float | None = Field(None, ge=-1000.0, le=100_000.0)
    awaiting: AwaitingCandidate | None = None
    awaiting_more: list[CandidateId] = Field(
        default_factory=list,
        max_length=QUEUE_IDS_MAX,
        description="other candidates awaiting a decision, oldest first: each is shown (`awaiting`) once the "
        "one before it is decided",
    )
    dropped_undecided: list[CandidateId] = Field(
        default_factory=list,
        max_length=QUEUE_IDS_MAX,
        description="candidates this mission dropped undecided, newest last: more awaited a decision than "
        "the vehicle keeps",
    )
    reason: PlainText = Field(
        "",
        max_length=200,
        description="why the companion is in its state: the mission's reason, a refusal, or what it waits for "
        '("waiting for the autopilot\'s HEARTBEAT on udpin:0.0.0.0:14550")',
    )
    heading_deg: float | None = Field(None, ge=-360.0, le=360.0, description="vehicle heading (deg)")
    track_box: list[float] | None = Field(
        None,
        min_length=4,
        max_length=4,
        description="[x1, y1, x2, y2]: the tracked box in the pixels of keyframe `frame_id`",
    )
    frame_id: int | None = Field(None, ge=0, le=2**53, description="the keyframe `track_box` refers to")
    track_id: CandidateId | None = Field(
        None,
        description="the tracked candidate's id, as the GCS, the supervisor's card and the finds name it (the "
        "keyframe's own answer ids change every keyframe): the live view labels the box on `track_box` with it",
    )
    progress: SearchProgress | None = None
    search: SearchStatus | None = None
    keyframes: KeyframeCounts | None = None
    find: Find | None = Field(
        None, description="the mission's confirmed find, sent with every status while the mission holds it"
    )

    @field_validator("track_box")
    @classmethod
    def _box_ordered(cls, value: list[float] | None) -> list[float] | None:
        if value is not None and not (
            0 <= value[0] < value[2] <= 100_000 and 0 <= value[1] < value[3] <= 100_000
        ):
            raise ValueError(
                "track_box must be [x1, y1, x2, y2] in pixels with x2 > x1 >= 0 and y2 > y1 >= 0"
            )
        return value

    @model_validator(mode="after")
    def _box_names_its_frame(self) -> VehicleStatusIn:
        if self.track_box is not None and self.frame_id is None:
            raise ValueError("track_box needs the frame_id of the keyframe it is drawn in")
        return self


class VehicleStatus(VehicleStatusIn):
    vehicle_id: str
    updated_at: float


OPERATOR_MAX = 64


class DecisionIn(ApiModel):
    candidate_id: str = CANDIDATE_ID
    action: Literal["confirm", "reject"]
    note: PlainText = Field("", max_length=NOTE_MAX)
    operator: PlainText = Field(
        "", max_length=OPERATOR_MAX, description='who decides, e.g. "supervisor page" (default: "supervisor")'
    )
    via: Literal["supervisor page", "back-end API"] = Field(
        "back-end API",
        description='through what the supervisor decided: "supervisor page" (the page sends it) or "back-end '
        'API" (any other client with the supervisor token); shown with every find and decision',
    )


class Decision(DecisionIn):
    decision_id: int = Field(description="increasing across the session store; poll with ?after=<last id>")
    vehicle_id: str
    mission_id: str | None
    created_at: float
    source: Literal["supervisor", "vehicle"] = Field(
        "supervisor",
        description='"vehicle": the vehicle reported it (a GCS decision over MAVLink, a find it confirmed); it '
        "already acted on it, and the report is kept as the vehicle's, never as the standing decision: the "
        "supervisor's own decision on that candidate is still taken",
    )


OnFind = Literal["continue", "hold", "return"]


class OnFindIn(ApiModel):
    """What the fleet does on the mission's first confirmed find, set once at the start."""

    on_find: OnFind = Field(
        description='"continue": every vehicle searches on; "hold": the others hold where they are; '
        '"return": the others return to launch (the finder stays with the person either way)'
    )


# The newest of the other vehicles' placed rejections a /fleet answer lists: a search area holds few people, and
# the companion keeps this many in its memory of the fleet's rejections (its default capacity is twice this).
FLEET_REJECTIONS_MAX = 32


class FleetRejection(ApiModel):
    """A rejection by another vehicle of the same fleet mission, with the rejected candidate's place: the
    companion keeps candidates standing there from being proposed (the back-end's appearance match does not
    hold for a look-alike seen from another lane)."""

    rejection_id: int
    vehicle_id: str = Field(description="whose candidate the supervisor (or its GCS) rejected")
    candidate_id: str | None = Field(None, description="that vehicle's id of it (not this vehicle's)")
    position: LatLonPoint = Field(
        description="[lat, lon] of the rejected candidate, as its vehicle estimated it"
    )


class FleetOrder(ApiModel):
    """What one vehicle of the fleet mission is to do now (GET /v1/missions/{m}/fleet)."""

    mission_id: str
    vehicle_id: str
    on_find: OnFind = Field(description='the mission\'s setting ("continue" when none was set)')
    found: str | None = Field(
        None, description='the first confirmed find, "<vehicle>/<candidate>"; null: none yet'
    )
    order: OnFind = Field(
        description='what this vehicle is to do: "continue" until a find is confirmed, and always for the '
        "vehicle that found the person; else the mission's on_find"
    )
    rejections: list[FleetRejection] = Field(
        default_factory=list,
        max_length=FLEET_REJECTIONS_MAX,
        description="the other vehicles' rejections of the mission that carry a place, newest first (at most "
        f"{FLEET_REJECTIONS_MAX}; a candidate rejected twice, by the supervisor and by its vehicle, once)",
    )
