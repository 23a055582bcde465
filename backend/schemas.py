"""The back-end's models: the API's (re-exported from `cloudtrack.api_models`, shared with the companion)
and the supervisor page's own (its snapshot of the fleet), plus the error answers every route documents."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field

from cloudtrack.api_models import (
    CANDIDATE_ID,
    ID_FIELD,
    IDENTIFIER,
    NOTE_MAX,
    ApiModel,
    AwaitingCandidate,
    Candidate,
    Decision,
    DecisionIn,
    DetectMeta,
    DetectResponse,
    ErrorResponse,
    Find,
    FleetOrder,
    GeoPoint,
    HealthResponse,
    KeyframeCounts,
    ModelNames,
    ModelsResponse,
    OnFind,
    OnFindIn,
    PodGrid,
    Rejection,
    RejectionIn,
    SearchProgress,
    SearchStatus,
    Timings,
    VehicleStatus,
    VehicleStatusIn,
)
from cloudtrack.provenance import Via

ERROR_RESPONSES: dict[int | str, dict[str, Any]] = {
    status: {"model": ErrorResponse} for status in (400, 401, 403, 404, 408, 413, 415, 422, 429)
}


# What the back-end keeps per mission beside the rejection memory: the finds and the map.


class StoredFind(Find):
    """A confirmed find as the back-end keeps it: once per (vehicle, mission, candidate)."""

    vehicle_id: str
    mission_id: str
    received_at: float
    source: Literal["vehicle", "supervisor"] = Field(
        description='"vehicle": from its status (its own geolocation); "supervisor": made at the supervisor\'s '
        "confirm from the candidate's reported position, replaced once by the vehicle's own"
    )
    same_as: str | None = Field(
        None,
        description='"<vehicle>/<candidate>": another vehicle of the mission found this person first (within '
        "the finds' uncertainty); this one is kept as that vehicle's sighting, never listed as a find of its own",
    )
    decided_via: Via | None = Field(
        None,
        description="who confirmed it and through what: the supervisor's standing decision on the candidate "
        '(its "supervisor page" or "back-end API") when there is one, else "GCS via the vehicle" (the '
        "vehicle's report); filled in when the find is read (backend.sessions)",
    )
    decided_by: str = Field(
        "",
        description='the same for a person: "supervisor page", "Ops through the back-end API (supervisor token)", ...',
    )


class EarlierArea(ApiModel):
    """A search area the mission flew before its survey was replaced, and what was searched of it."""

    area: list[list[float]]
    covered: list[list[list[float]]] = Field(default_factory=list)
    coverage: float | None = None
    pod: PodGrid | None = None
    since: float = Field(0.0, description="Unix time it was first reported (0: not known)")
    replaced_at: float = Field(description="Unix time a status first reported another area")


class MissionMap(ApiModel):
    """A mission's map: the vehicle's track (decimated, bounded), its search area, covered area and POD map,
    and the areas it searched before its survey was replaced (oldest first, the last few)."""

    track: list[list[float]] = Field(
        default_factory=list, description="[[lat, lon, unix time], ...], oldest first"
    )
    area: list[list[float]] = Field(default_factory=list)
    covered: list[list[list[float]]] = Field(default_factory=list)
    coverage: float | None = None
    pod: PodGrid | None = None
    area_since: float = Field(0.0, description="Unix time the area was first reported (0: not known)")
    earlier: list[EarlierArea] = Field(default_factory=list)
    updated_at: float = 0.0


class MergedMap(ApiModel):
    """The map of one mission of the fleet: every vehicle searching that mission id, merged
    (`backend.mission_merge`): the union of their search areas and covered areas, and one POD map."""

    mission_id: str
    vehicles: list[str] = Field(
        description="the vehicles whose maps are merged, the most recently seen first"
    )
    area: list[list[list[float]]] = Field(
        default_factory=list, description="the union of the vehicles' search areas, [lat, lon] rings"
    )
    covered: list[list[list[float]]] = Field(
        default_factory=list, description="the union of their covered areas"
    )
    coverage: float | None = Field(None, description="the share of the area covered by any vehicle (0..1)")
    pod: PodGrid | None = Field(
        None, description="per place 1 - prod(1 - POD of each vehicle), on one grid over every vehicle's grid"
    )
    updated_at: float = Field(0.0, description="when the newest of the merged vehicles' maps was updated")
    as_of: float = Field(
        0.0,
        description="server time the vehicles' maps were read for this map: it is merged again at most once "
        "per [fleet] merge_period_s, off the request, and served as kept meanwhile",
    )
    age_s: float = Field(0.0, description="how old the map was when served: server time minus as_of")


class Dropout(ApiModel):
    """A vehicle that left the mission's search (`backend.fleet_dropout`), and the part of its area left unflown."""

    vehicle_id: str
    kind: Literal["mode", "aborted", "moved", "silent"] = Field(
        description='"mode": it reports RTL/LAND (or PX4\'s RTL, LAND, RTGS); "aborted": its companion aborted '
        '(a pilot\'s takeover, the link lost); "moved": it reports another mission; "silent": no status for '
        "longer than [fleet] dropout_s"
    )
    reason: str = Field(description='one line, e.g. "mode RTL", "silent for 42 s (over 30 s)"')
    since: float = Field(description="Unix time of the last status that says so (silent: its last status)")
    unflown: list[list[list[float]]] = Field(
        default_factory=list,
        description="its part of the area that no vehicle of the mission has covered, [lat, lon] rings (outer "
        "counter-clockwise, holes clockwise; slivers and scraps left out)",
    )
    area_m2: float = Field(0.0, description="the unflown part's area")
    area_known: bool = Field(
        True,
        description="false: it left before any status of it carried its part of the area (`search.area`), so "
        "what it left unflown is unknown, not none: `unflown` is empty and `area_m2` 0 for that reason alone",
    )


class MissionDropouts(ApiModel):
    """`GET /v1/missions/{m}/dropouts`: who left the mission's search, and who still searches it."""

    mission_id: str
    dropout_s: float = Field(description="[fleet] dropout_s: silent longer than this is a drop-out")
    dropouts: list[Dropout] = Field(default_factory=list, description="the vehicles that left, by id")
    searching: list[str] = Field(
        default_factory=list, description="the vehicles with a part of the area that still search it, by id"
    )
    server_time: float


class KeyframeCandidate(ApiModel):
    id: str = Field(
        description="stored: the answer's id; shown: the candidate's id as the GCS, the card and the finds name "
        'it, "" for a box put to no one (the answer\'s ids are new every keyframe)'
    )
    box: list[float]
    verdict: Literal["yes", "no", "uncertain"]
    status: Literal["", "tracked", "awaiting", "confirmed", "rejected"] = Field(
        "", description='shown only: where the candidate stands with the supervisor ("": put to no one)'
    )


class KeyframeRecord(ApiModel):
    """The newest keyframe a vehicle sent to /v1/detect and the candidates the answer held (its pixels)."""

    frame_id: int | None
    mission_id: str
    width: int
    height: int
    received_at: float
    candidates: list[KeyframeCandidate]


# The supervisor page's snapshot (GET /supervisor/api/state and each `state` event of /supervisor/events).


class LatLon(ApiModel):
    lat: float
    lon: float


class CandidateView(ApiModel):
    """The candidate a vehicle awaits a decision on, as the page shows it."""

    id: str
    verdict: Literal["yes", "no", "uncertain"]
    justification: str
    unjudged: list[str] = Field(
        default_factory=list, description="what the back-end could not judge: for the supervisor to check"
    )
    alike: int = Field(0, description="others the search could have taken as well (chosen by score alone)")
    position: LatLon | None
    box: list[float]
    age_s: float = 0.0
    crop_url: str | None
    crop_box: list[float] | None = None
    status: Literal["awaiting", "confirmed", "rejected"]
    decided_by: str = Field("", description="who took the supervisor's standing decision and through what")
    reported: str = Field(
        "",
        description='what the vehicle reports was decided on it at its GCS ("confirmed by "Ops" at the GCS, '
        "as reported by drone-1\"): the vehicle's word, which leaves the supervisor's decision open",
    )


class KeyframeView(ApiModel):
    frame_id: int | None
    url: str
    width: int
    height: int
    age_s: float = 0.0
    candidates: list[KeyframeCandidate]
    track_box: list[float] | None = Field(
        None, description="the vehicle's tracked box, when in this keyframe"
    )
    track_id: str | None = Field(None, description="the tracked candidate's id, with `track_box`")
    track_status: str = Field("", description="where the tracked candidate stands, as a box's `status`")


class FindView(ApiModel):
    candidate_id: str
    mission_id: str
    position: LatLon
    sigma_m: float | None
    time: float
    seen_at: float | None = None  # when the position was observed (Unix s); None: not known
    seen: str = ""  # the same for a person: "position as seen at 14:39:15 UTC, 45 s before the confirmation"
    prompt: str
    confirmed_by: str
    decided_by: str = Field("", description="who confirmed it and through what (cloudtrack.provenance)")
    decided_via: str = Field("", description='"supervisor page", "back-end API" or "GCS via the vehicle"')
    crop_url: str | None
    crop_box: list[float] | None


class PodBandView(ApiModel):
    low: float
    high: float
    colour: str = Field(description='"#rrggbb", as the GeoJSON and KML downloads fill it')


class PodView(ApiModel):
    """The vehicle's POD map as the page draws it: the grid as reported, one cell's size in degrees (the grid
    is north-up, so a cell's corners are the origin plus whole steps) and the legend."""

    target: str
    posture: str
    target_pod: float
    mean: float
    at_target: float = Field(description="share of the area at or above target_pod")
    looks: int
    dark_looks: int = Field(
        0, description="analysed keyframes too dark for the detection curve (as reported)"
    )
    origin: list[float] = Field(description="[lat, lon] of the grid's south-west corner")
    cell_deg: list[float] = Field(description="[north, east]: one cell's side in degrees of lat and lon")
    rows: int
    cols: int
    values: str = Field(
        description="as in the status: base64, a byte a cell, 0-250 POD, 255 outside; empty in a vehicle's "
        "view whose cells are on its mission's merged map (`on_mission_map`)"
    )
    bands: list[PodBandView]
    meaning: str = Field(description="what POD means, one sentence for the legend")


class VehicleView(ApiModel):
    id: str
    state: str
    reason: str = ""
    mission_id: str | None
    prompt: str | None
    # The prompt's words name something outside the superset the GCS gave ("an orange life buoy", person).
    prompt_warning: str | None = None
    position: GeoPoint | None
    altitude_m: float | None
    heading_deg: float | None = None
    age_s: float = 0.0
    candidates: list[CandidateView]
    awaiting_more: list[str] = Field(
        default_factory=list, description="ids of further candidates awaiting a decision, oldest first"
    )
    dropped_undecided: list[str] = Field(
        default_factory=list, description="ids of candidates dropped undecided this mission (too many waited)"
    )
    progress: SearchProgress | None = None
    search: SearchStatus | None = Field(
        None, description="as reported, less its POD map (`pod`) and, with `on_mission_map`, its covered area"
    )
    pod: PodView | None = None
    on_mission_map: bool = Field(
        False,
        description="one of several vehicles of its mission: its covered area and POD cells are left out "
        "here (search.covered empty, pod.values empty), the mission's merged map (`missions`) carries them",
    )
    earlier_areas: int = Field(0, description="search areas of this mission before its survey was replaced")
    keyframes: KeyframeCounts | None = None
    track: list[list[float]] = Field(default_factory=list, description="[[lat, lon], ...] of this mission")
    keyframe: KeyframeView | None = None
    finds: list[FindView] = Field(default_factory=list, description="this vehicle's finds, oldest first")
    auth_error: str | None = Field(None, description="the back-end refused this vehicle's credentials")
    colour: str = Field(
        "",
        description='"#rrggbb": the vehicle\'s colour in its mission (cloudtrack.vehicle_colours, as in the '
        'exports), always shown beside its id; "" without a mission',
    )
    left: str = Field(
        "",
        description='why it left its mission\'s search (backend.fleet_dropout: "mode RTL", "aborted: ...", '
        '"silent over 30 s"); "" while it searches',
    )


class UnflownView(ApiModel):
    """The part of the area a vehicle that left the search leaves unflown (backend.fleet_dropout)."""

    vehicle_id: str
    rings: list[list[list[float]]] = Field(description="[lat, lon] rings, outer counter-clockwise")
    area_m2: float


class MissionView(ApiModel):
    """One mission of the fleet as the page's fleet map draws it: the merged map of the vehicles on the page
    searching it (`backend.mission_merge`, bounded as GET /v1/missions/{m}/map is); each vehicle's part,
    track and state are in its own view."""

    mission_id: str
    vehicles: list[str] = Field(description="the ids of the vehicles on the page searching it, sorted")
    area: list[list[list[float]]] = Field(default_factory=list, description="the union of their parts")
    covered: list[list[list[float]]] = Field(default_factory=list, description="the union of their covered")
    coverage: float | None = Field(None, description="the share of the area covered by any vehicle (0..1)")
    pod: PodView | None = Field(None, description="the merged POD map, 1 - prod(1 - POD of each vehicle)")
    unflown: list[UnflownView] = Field(
        default_factory=list, description="per vehicle that left the search, its part no vehicle covered"
    )
    as_of: float = Field(
        0.0,
        description="when the vehicles' maps were read for it (merged at most once per [fleet] merge_period_s)",
    )


class SupervisorSnapshot(ApiModel):
    server_time: float
    vehicles: list[VehicleView]
    missions: list[MissionView] = Field(
        default_factory=list, description="the fleet's missions on one map each (the merged map), by id"
    )
    map_tiles: str = Field("", description="[supervisor] map_tiles: the optional tile layer's URL template")


class SupervisorEnabled(ApiModel):
    enabled: bool


__all__ = [
    "CANDIDATE_ID",
    "ERROR_RESPONSES",
    "ID_FIELD",
    "IDENTIFIER",
    "NOTE_MAX",
    "OnFind",
    "OnFindIn",
    "ApiModel",
    "AwaitingCandidate",
    "Candidate",
    "CandidateView",
    "Decision",
    "DecisionIn",
    "DetectMeta",
    "DetectResponse",
    "EarlierArea",
    "ErrorResponse",
    "Find",
    "FindView",
    "GeoPoint",
    "HealthResponse",
    "KeyframeCandidate",
    "KeyframeCounts",
    "KeyframeRecord",
    "KeyframeView",
    "LatLon",
    "FleetOrder",
    "MergedMap",
    "MissionMap",
    "MissionView",
    "UnflownView",
    "ModelNames",
    "ModelsResponse",
    "PodBandView",
    "PodGrid",
    "PodView",
    "Rejection",
    "RejectionIn",
    "SearchProgress",
    "SearchStatus",
    "StoredFind",
    "SupervisorEnabled",
    "SupervisorSnapshot",
    "Timings",
    "VehicleStatus",
    "VehicleStatusIn",
    "VehicleView",
]
