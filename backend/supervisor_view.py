"""The supervisor page's view of the fleet: per vehicle its state and why, the newest keyframe with its boxes,
the candidate it awaits (with the decision that stands on it), search progress and coverage, the POD map
with its legend, the keyframes kept through outages, the mission's track, and its finds, which stay; and
per mission of the fleet the merged map (`MissionView`) the page's fleet map draws under every vehicle's
part, track and position, each vehicle in its colour (`cloudtrack.vehicle_colours`, as the exports) and
named by its id.

Bounded as the fleet grows: the tracks shown share `FLEET_TRACK_POINTS` (each at most `TRACK_SHOWN`, at
least `TRACK_SHOWN_MIN`), a part is the reported search area (the API caps its vertices), the merged map is
`backend.mission_merge`'s (rings and vertices capped, the POD grid at most `cloudtrack.pod_map.MAX_CELLS`),
the one `GET /v1/missions/{m}/map` serves (`SessionStore.merged_map`, `backend.merged_maps`): merged again
at most once per `[fleet] merge_period_s` and only when a vehicle's area, coverage or POD map changed, off
the page's build, which takes it as kept. A vehicle of a mission of several (`on_mission_map`) is sent
without its own covered area and POD cells (about 10 KB a vehicle): the mission's merged map carries them,
and its card draws that map under its part. The part a vehicle that left the search leaves unflown is its
area less the merged map's covered area (what the page draws), worked out again when either changes.

Built from the session store (the whole fleet, whichever replica answers); it remembers since when each
candidate waits, and forgets a candidate as soon as nobody waits on it, so it stays as small as the fleet.
Refused credentials are remembered here too (per process, for `AUTH_ERROR_KEEP_S`, until the vehicle's own
token is accepted again): a vehicle whose token the back-end refuses cannot report, so the page says so in
its place.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from backend.fleet_dropout import leaving, unflown_part
from backend.pod_layers import band_colour, meaning
from backend.schemas import (
    CandidateView,
    FindView,
    KeyframeCandidate,
    KeyframeView,
    LatLon,
    MissionMap,
    MissionView,
    PodBandView,
    PodGrid,
    PodView,
    SearchStatus,
    StoredFind,
    SupervisorSnapshot,
    UnflownView,
    VehicleStatus,
    VehicleView,
)
from backend.sessions import SessionStore
from backend.supersets import prompt_outside_superset
from behaviors.geometry import Box, iou
from cloudtrack.api_models import Decision
from cloudtrack.coverage import LocalFrame
from cloudtrack.cursor_on_target import seen_text
from cloudtrack.pod_map import BANDS
from cloudtrack.provenance import decided_via, decision_text
from cloudtrack.vehicle_colours import vehicle_colours

_STATUS = {"confirm": "confirmed", "reject": "rejected"}
TRACK_SHOWN = 300  # points of a vehicle's track the page draws (the download has them all)
FLEET_TRACK_POINTS = 6000  # points of all the tracks together: a large fleet's tracks are drawn coarser
TRACK_SHOWN_MIN = 60  # ... but never coarser than this many points a vehicle
AUTH_ERROR_KEEP_S = 60.0
SNAPSHOT_REUSE_S = 1.0
# An open page's stream builds the state at most this often: with a fleet reporting, the store changes all
# the time, and a stream rebuilding on every change kept a build running without end (the page redraws the
# fleet at most every 200 ms; a decision still shows within this).
STREAM_BUILD_MIN_S = 0.5
TRACK_MATCH_IOU = 0.2  # a keyframe box over the tracked box is the tracked one (as the companion matches)


def _shown(track: list[list[float]], most: int = TRACK_SHOWN) -> list[list[float]]:
    """At most `most` [lat, lon] points (one more: the newest is always kept), evenly spread."""
    step = max(1, -(-len(track) // most))
    kept = track[::step]
    if track and kept[-1] is not track[-1]:
        kept.append(track[-1])
    return [p[:2] for p in kept]


def _decided_by(decision: Decision) -> str:
    return decision_text(decided_via(decision.source, decision.via), decision.operator, decision.vehicle_id)


def find_view(find: StoredFind) -> FindView:
    return FindView(
        candidate_id=find.candidate_id,
        mission_id=find.mission_id,
        position=LatLon(lat=find.position[0], lon=find.position[1]),
        sigma_m=find.sigma_m,
        time=find.time,
        seen_at=find.seen_at,
        seen=seen_text(find.time, find.seen_at),
        prompt=find.prompt,
        confirmed_by=find.confirmed_by,
        decided_by=find.decided_by,
        decided_via=find.decided_via or "",
        crop_url=(
            f"/supervisor/api/vehicles/{find.vehicle_id}/finds/{find.mission_id}/{find.candidate_id}/crop.jpg"
            if find.crop_jpeg_b64
            else None
        ),
        crop_box=find.crop_box,
    )


def pod_view(grid: PodGrid) -> PodView:
    """The grid as the page draws it: a cell's side in degrees (from the grid's own frame) and the legend."""
    north, east = LocalFrame(*grid.origin).latlon(grid.cell_m, grid.cell_m)
    return PodView(
        **grid.model_dump(exclude={"cell_m"}),
        cell_deg=[north - grid.origin[0], east - grid.origin[1]],
        bands=[PodBandView(low=low, high=high, colour=band_colour(low)) for low, high in BANDS],
        meaning=meaning(grid),
    )


class SupervisorView:
    """Turns the session store into what the page shows, and remembers since when each candidate waits."""

    def __init__(
        self, store: SessionStore, clock: Callable[[], float] = time.time, map_tiles: str = ""
    ) -> None:
        self.store = store
        self._clock = clock
        self.map_tiles = map_tiles
        self._first_seen: dict[tuple[str, str], float] = {}
        self._auth_errors: dict[str, tuple[str, float]] = {}
        self._lock = threading.Lock()
        self._build_lock = threading.Lock()
        # (store version and merge generation, when built, when its build began (monotonic), the snapshot)
        self._cached: tuple[tuple[int, int], float, float, SupervisorSnapshot] | None = None
        # Per mission: what its vehicles' unflown parts were worked out from, and them.
        self._unflown: dict[str, tuple[tuple[object, ...], list[UnflownView]]] = {}

    def note_auth_failure(self, vehicle_id: str, reason: str) -> None:
        """A request for this vehicle was refused its credentials (401/403): shown on its card for a while."""
        with self._lock:
            self._auth_errors[vehicle_id] = (reason, self._clock())
            self._cached = None

    def clear_auth_failure(self, vehicle_id: str) -> None:
        """A request with this vehicle's token was accepted: whatever was refused before, its token works."""
        if vehicle_id in self._auth_errors:  # read without the lock: called on every vehicle request
            with self._lock:
                if self._auth_errors.pop(vehicle_id, None) is not None:
                    self._cached = None

    def _auth_error(self, vehicle_id: str, now: float) -> str | None:
        with self._lock:
            noted = self._auth_errors.get(vehicle_id)
            if noted is None:
                return None
            if now - noted[1] > AUTH_ERROR_KEEP_S:
                del self._auth_errors[vehicle_id]
                return None
            return noted[0]

    def snapshot(self) -> SupervisorSnapshot:
        """The fleet now. Every open page's stream asks on every change: one build serves them all until the
        store changes again, or a mission's map is merged anew (or a second passes, for the ages). A caller
        that waited for another's build takes that one when it began after the caller asked: it read the
        store later than the caller could have (so callers arriving during a build share the next, not one
        each)."""
        asked = time.monotonic()
        with self._build_lock:
            version = (self.store.state.version(), self.store.merged_maps.generation)
            cached = self._cached
            if cached is not None and (
                cached[2] >= asked or (cached[0] == version and self._clock() - cached[1] < SNAPSHOT_REUSE_S)
            ):
                return cached[3]
            began = time.monotonic()
            built = self._build()
            self._cached = (version, self._clock(), began, built)
            return built

    def _build(self) -> SupervisorSnapshot:
        now = self._clock()
        vehicles = []
        waiting: set[tuple[str, str]] = set()
        statuses = {s.vehicle_id: s for s in self.store.statuses()}
        with self._lock:
            refused = [v for v in self._auth_errors if v not in statuses]
        for vehicle_id in refused:
            error = self._auth_error(vehicle_id, now)
            if error is not None:
                vehicles.append(
                    VehicleView(
                        id=vehicle_id,
                        state="UNKNOWN",
                        reason=error,
                        mission_id=None,
                        prompt=None,
                        position=None,
                        altitude_m=None,
                        candidates=[],
                        auth_error=error,
                    )
                )
        members: dict[str, list[str]] = {}
        for status in statuses.values():
            if status.mission_id is not None:
                members.setdefault(status.mission_id, []).append(status.vehicle_id)
        colours = {m: vehicle_colours(ids) for m, ids in members.items()}
        track_points = max(TRACK_SHOWN_MIN, min(TRACK_SHOWN, FLEET_TRACK_POINTS // max(1, len(statuses))))
        maps: dict[str, list[tuple[str, MissionMap]]] = {}
        left: dict[str, str] = {}
        for status in statuses.values():
            colour = colours[status.mission_id][status.vehicle_id] if status.mission_id is not None else ""
            view = self._vehicle(status, now, waiting, colour, track_points, maps)
            if status.mission_id is not None:
                away = leaving(status.mission_id, status, status.updated_at, now, self.store.dropout_s)
                if away is not None:
                    # Worded without the seconds a silence lasts: the page counts them (the view stays put).
                    why = f"silent over {self.store.dropout_s:g} s" if away.kind == "silent" else away.reason
                    view = view.model_copy(update={"left": why})
                    left[status.vehicle_id] = why
            vehicles.append(view)
        vehicles.sort(key=lambda v: v.id)
        for key in [k for k in self._first_seen if k not in waiting]:
            del self._first_seen[key]
        missions = [
            self._mission(m, sorted(ids), maps.get(m, []), sorted(v for v in ids if v in left))
            for m, ids in sorted(members.items())
        ]
        for gone in [m for m in self._unflown if m not in members]:
            del self._unflown[gone]
        vehicles = _slimmed(vehicles, missions)
        return SupervisorSnapshot(
            server_time=now, vehicles=vehicles, missions=missions, map_tiles=self.map_tiles
        )

    def _mission(
        self,
        mission_id: str,
        vehicle_ids: list[str],
        maps: list[tuple[str, MissionMap]],
        left: list[str],
    ) -> MissionView:
        """The mission's merged map as kept (`SessionStore.merged_map`, shared with GET .../map: merged at
        most once per period, never here), and the unflown part of each vehicle in `left` (which left the
        search): its area less the merged covered area, worked out again only when that map, a left
        vehicle's area or who left changed."""
        merged = self.store.merged_map(mission_id) if maps else None
        if merged is None:
            return MissionView(mission_id=mission_id, vehicles=vehicle_ids)
        areas = {v: m.area for v, m in maps if v in left}
        key = (merged.as_of, merged.updated_at, tuple(left), tuple(str(areas.get(v)) for v in left))
        kept = self._unflown.get(mission_id)
        if kept is not None and kept[0] == key:
            unflown = kept[1]
        else:
            unflown = []
            for vehicle in left:
                if vehicle not in areas:
                    continue
                part = unflown_part(areas[vehicle], [merged.covered] if merged.covered else [])
                if part.rings:
                    unflown.append(UnflownView(vehicle_id=vehicle, rings=part.rings, area_m2=part.area_m2))
            self._unflown[mission_id] = (key, unflown)
        return MissionView(
            mission_id=mission_id,
            vehicles=vehicle_ids,
            area=merged.area,
            covered=merged.covered,
            coverage=merged.coverage,
            pod=pod_view(merged.pod) if merged.pod is not None else None,
            unflown=unflown,
            as_of=merged.as_of,
        )

    def _vehicle(
        self,
        status: VehicleStatus,
        now: float,
        waiting: set[tuple[str, str]],
        colour: str = "",
        track_points: int = TRACK_SHOWN,
        maps: dict[str, list[tuple[str, MissionMap]]] | None = None,
    ) -> VehicleView:
        vehicle_id = status.vehicle_id
        candidates = []
        awaiting = status.awaiting
        if awaiting is not None:
            key = (vehicle_id, awaiting.candidate_id)
            waiting.add(key)
            first = self._first_seen.setdefault(key, min(now, status.updated_at))
            standing = self.store.standing_decision(vehicle_id, status.mission_id, awaiting.candidate_id)
            reported = self.store.reported_decision(vehicle_id, status.mission_id, awaiting.candidate_id)
            candidates.append(
                CandidateView(
                    id=awaiting.candidate_id,
                    verdict=awaiting.verdict,
                    justification=awaiting.justification,
                    unjudged=awaiting.unjudged,
                    alike=awaiting.alike,
                    position=LatLon(lat=awaiting.position[0], lon=awaiting.position[1])
                    if awaiting.position
                    else None,
                    box=awaiting.box,
                    age_s=round(max(0.0, now - first), 1),
                    crop_url=(
                        f"/supervisor/api/vehicles/{vehicle_id}/candidates/{awaiting.candidate_id}/crop.jpg"
                        if awaiting.crop_jpeg_b64
                        else None
                    ),
                    crop_box=awaiting.crop_box,
                    status=_STATUS[standing.action] if standing else "awaiting",
                    decided_by=_decided_by(standing) if standing else "",
                    reported=(
                        f"{_STATUS[reported.action]} by {_decided_by(reported)}"
                        if reported is not None
                        else ""
                    ),
                )
            )
        keyframe = None
        record = self.store.state.keyframe(vehicle_id)
        finds = self.store.finds(vehicle_id)
        if record is not None and record.mission_id == status.mission_id:
            track_box = status.track_box if status.frame_id == record.frame_id else None
            found = {f.candidate_id for f in finds if f.mission_id == status.mission_id}
            awaiting_id = status.awaiting.candidate_id if status.awaiting is not None else ""
            keyframe = KeyframeView(
                frame_id=record.frame_id,
                url=f"/supervisor/api/vehicles/{vehicle_id}/keyframe.jpg?frame={record.frame_id}&t={record.received_at}",
                width=record.width,
                height=record.height,
                age_s=round(max(0.0, now - record.received_at), 1),
                candidates=self._boxes(status, record.candidates, track_box, found),
                track_box=track_box,
                track_id=status.track_id if track_box is not None else None,
                track_status=(
                    self._standing(status, status.track_id or "", awaiting_id, found)
                    if track_box is not None
                    else ""
                ),
            )
        search = status.search
        grid = search.pod if search is not None else None
        track: list[list[float]] = []
        earlier_areas = 0
        if status.mission_id is not None:
            mission_map = self.store.mission_map(vehicle_id, status.mission_id)
            if mission_map is not None:
                if maps is not None:
                    maps.setdefault(status.mission_id, []).append((vehicle_id, mission_map))
                track = _shown(mission_map.track, track_points)
                earlier_areas = len(mission_map.earlier)
                if search is None and (mission_map.area or mission_map.covered):
                    search = SearchStatus(
                        area=mission_map.area,
                        covered=mission_map.covered,
                        coverage=mission_map.coverage or 0.0,
                    )
                if grid is None and search is not None and search.area in ([], mission_map.area):
                    grid = mission_map.pod  # a status without the map says nothing of it: the area's stays
        if search is not None and search.pod is not None:
            search = search.model_copy(update={"pod": None})  # sent once, in `pod`
        return VehicleView(
            id=vehicle_id,
            state=status.state,
            reason=status.reason,
            mission_id=status.mission_id,
            prompt=status.prompt,
            prompt_warning=prompt_outside_superset(status.prompt, status.superset)
            if status.prompt and status.superset
            else None,
            position=status.position,
            altitude_m=status.altitude_m,
            heading_deg=status.heading_deg,
            age_s=round(max(0.0, now - status.updated_at), 1),
            candidates=candidates,
            awaiting_more=status.awaiting_more,
            dropped_undecided=status.dropped_undecided,
            progress=status.progress,
            search=search,
            pod=pod_view(grid) if grid is not None else None,
            earlier_areas=earlier_areas,
            keyframes=status.keyframes,
            track=track,
            keyframe=keyframe,
            finds=[find_view(f) for f in finds],
            auth_error=self._auth_error(vehicle_id, now),
            colour=colour,
        )

    def _boxes(
        self,
        status: VehicleStatus,
        boxes: list[KeyframeCandidate],
        track_box: list[float] | None,
        found: set[str],
    ) -> list[KeyframeCandidate]:
        """The keyframe's boxes named as the GCS, the card and the finds name them: the answer's own id where
        the vehicle kept it (the answer that first proposed the candidate), the tracked candidate's id on the
        box over the track; "" on a box put to no one. Each with where it stands with the supervisor."""
        awaiting = status.awaiting.candidate_id if status.awaiting is not None else ""
        known = {awaiting, *status.awaiting_more, *status.dropped_undecided, *found} - {""}
        on_track = -1
        if track_box is not None and status.track_id:
            tracked = Box.from_xyxy(*track_box)
            overlaps = [iou(Box.from_xyxy(*b.box), tracked) for b in boxes]
            best = max(range(len(boxes)), key=overlaps.__getitem__, default=-1)
            on_track = best if best >= 0 and overlaps[best] >= TRACK_MATCH_IOU else -1
        shown = []
        for i, b in enumerate(boxes):
            cid = (status.track_id or "") if i == on_track else (b.id if b.id in known else "")
            shown.append(
                b.model_copy(update={"id": cid, "status": self._standing(status, cid, awaiting, found)})
            )
        return shown

    def _standing(self, status: VehicleStatus, cid: str, awaiting: str, found: set[str]) -> str:
        if not cid:
            return ""
        if cid in found or (cid == status.track_id and status.state == "CONFIRMED"):
            return "confirmed"
        standing = self.store.standing_decision(status.vehicle_id, status.mission_id, cid)
        if standing is not None:
            return _STATUS[standing.action]
        if cid == awaiting or cid in status.awaiting_more:
            return "awaiting"
        return "tracked" if cid == status.track_id else ""


def _slimmed(vehicles: list[VehicleView], missions: list[MissionView]) -> list[VehicleView]:
    """Each vehicle of a mission of several, whose map is merged on the mission's (`missions`), without its
    own covered rings and POD cells: `on_mission_map`, its card draws the merged map (the rest of its POD
    view, its figures and legend, stays)."""
    merged = {m.mission_id: m for m in missions if len(m.vehicles) > 1 and m.area}
    slim = []
    for vehicle in vehicles:
        mission = merged.get(vehicle.mission_id or "")
        if mission is None or vehicle.search is None or len(vehicle.search.area) < 3:
            slim.append(vehicle)
            continue
        update: dict[str, object] = {"on_mission_map": True}
        update["search"] = vehicle.search.model_copy(update={"covered": []})
        if vehicle.pod is not None:
            update["pod"] = vehicle.pod.model_copy(update={"values": ""})
        slim.append(vehicle.model_copy(update=update))
    return slim


def view_content(vehicle: VehicleView) -> str:
    """A vehicle's view minus what changes every second, to tell a real change from time passing."""
    ages = {"age_s": True, "candidates": {"__all__": {"age_s"}}, "keyframe": {"age_s"}}
    return vehicle.model_dump_json(exclude=ages)  # type: ignore[arg-type]


def missions_content(snapshot: SupervisorSnapshot) -> str:
    """The fleet's merged maps as sent (the `fleet` event), to tell when they changed."""
    return "[" + ",".join(m.model_dump_json() for m in snapshot.missions) + "]"


def without_ages(snapshot: SupervisorSnapshot) -> str:
    """The snapshot's content minus what changes every second."""
    return (
        "\n".join(view_content(v) for v in snapshot.vehicles)
        + missions_content(snapshot)
        + snapshot.map_tiles
    )
