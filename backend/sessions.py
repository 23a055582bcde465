"""What the back-end remembers between requests: per-(vehicle, mission) rejections, vehicle status, decisions.

The logic lives here; the state lives in a `backend.state_store.StateStore` (SQLite by default, Redis for
several replicas), so a restart or a failover to another replica forgets nothing. Missions are stored by
(vehicle, mission); the vehicles searching the same mission id are one mission of the fleet (at most
`MISSION_VEHICLES` of them, the most recently seen, are read): a rejection holds for all of them where it
was made (a rejection without a place holds only for its own vehicle: mission ids are 0-255 and meet by
accident), a person several of them find is one find (`same_as`), and their maps merge
(`merged_map`, `backend.mission_merge`: kept per mission and merged again at most once per
`merge_period_s`, `backend.merged_maps`).

Rejection memory: when the supervisor rejects a candidate, its appearance (hue-saturation histogram)
and, when known, its position are kept for the mission. A later candidate in the same mission whose
appearance correlates at least `similarity` with a rejected one is answered "no" without asking the
verifier - unless both the rejection and the request carry positions and the vehicle is farther than
`radius_m` from the rejected place (a look-alike elsewhere is a new candidate).

Every crop is checked from its JPEG/PNG header before it is decoded (backend.images), and a crop a vehicle
reports for the supervisor must be a real JPEG: the page serves it as image/jpeg.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable

from backend.appearance import descriptor, similarity
from backend.fleet_dropout import leaving, unflown_parts
from backend.images import (
    JPEG_MAGIC,
    PNG_MAGIC,
    ImageError,
    b64_image_bytes,
    decode_image,
    image_size,
    is_jpeg,
)
from backend.merge_worker import MergeWorker
from backend.merged_maps import MergedMaps
from backend.mission_map import distance_m, updated_map
from backend.schemas import (
    Dropout,
    FleetOrder,
    KeyframeCandidate,
    KeyframeRecord,
    MergedMap,
    MissionDropouts,
    MissionMap,
    OnFind,
    StoredFind,
)
from backend.state_store import QuotaExceededError, SqliteStore, StateStore, vector_bytes, vector_from
from behaviors.geometry import Box
from cloudtrack.api_models import (
    FLEET_REJECTIONS_MAX,
    AwaitingCandidate,
    Decision,
    DecisionIn,
    Find,
    FleetRejection,
    Rejection,
    RejectionIn,
    VehicleStatus,
    VehicleStatusIn,
)
from cloudtrack.provenance import decided_via, decision_text

log = logging.getLogger(__name__)

MISSION_VEHICLES = 64  # the vehicles of one mission id read for its rejections, finds and map
SHARED_REJECTIONS = 400  # the newest of the other vehicles' rejections a candidate is matched against
FIND_SIGMA_UNKNOWN_M = 10.0  # a find without an uncertainty (made at a supervisor's confirm) is this sure
FIND_SAME_MIN_M = 5.0  # two finds closer than this are one person, however sure each is

__all__ = ["QuotaExceededError", "SessionStore", "UnknownCandidateError", "crop_descriptor", "distance_m"]


class UnknownCandidateError(LookupError):
    """A rejection names a candidate id the back-end does not know and carries no crop."""


def crop_descriptor(crop_jpeg_b64: str, crop_box: list[float] | None, max_pixels: int) -> list[float]:
    """Appearance of a crop sent by a client: the candidate's box inside it, or the whole crop.

    ImageError (with its HTTP status) when the crop is not base64, not JPEG/PNG, too large by its header
    (checked before decoding) or undecodable; ValueError when crop_box lies outside it.
    """
    image = decode_image(b64_image_bytes(crop_jpeg_b64), max_pixels)
    h, w = image.shape[:2]
    box = Box.from_xyxy(*crop_box) if crop_box else Box(0, 0, w, h)
    if not box.clamped(w, h).is_valid():
        raise ImageError(f"crop_box {crop_box} lies outside the {w}x{h} crop", 422)
    return descriptor(image, box)


def _what(data: bytes) -> str:
    """What a refused crop is, from its first bytes and header only (for the 422's detail)."""
    if not data.startswith(JPEG_MAGIC):
        return "a PNG" if data.startswith(PNG_MAGIC) else f"{len(data)} bytes without a JPEG signature"
    try:
        width, height = image_size(data)
    except ImageError as error:
        return str(error)
    return f"a JPEG of {width}x{height} pixels"


class SessionStore:
    def __init__(
        self,
        state: StateStore | None = None,
        similarity_threshold: float = 0.85,
        radius_m: float = 150.0,
        mission_ttl_s: float = 6 * 3600.0,
        max_rejections: int = 200,
        max_missions: int = 32,
        max_crop_pixels: int = 4_000_000,
        clock: Callable[[], float] = time.time,
        on_find: Callable[[StoredFind], None] | None = None,
        dropout_s: float = 30.0,
        merge_period_s: float = 2.0,
        merge_in_background: bool = False,
        merge_in_process: bool = False,
    ) -> None:
        self.state = state or SqliteStore()
        # [fleet] merge_period_s: each mission's merged map, shared by GET .../map and the supervisor page;
        # in the background (off the requests) in the server, in the reading call otherwise; in the server,
        # in a worker process (backend.merge_worker: a merge of 50 vehicles held the GIL for half a second).
        self.merged_maps = MergedMaps(
            self._mission_maps,
            merge_period_s,
            clock,
            background=merge_in_background,
            merge=MergeWorker() if merge_in_process else None,
        )
        self.dropout_s = dropout_s  # [fleet] dropout_s: a mission's vehicle silent longer has left its search
        self.similarity_threshold = similarity_threshold
        self.radius_m = radius_m
        self.mission_ttl_s = mission_ttl_s
        self.max_rejections = max_rejections
        self.max_missions = max_missions
        self.max_crop_pixels = max_crop_pixels
        self._clock = clock
        self.on_find = on_find  # told of every find stored or refined (Cursor-on-Target), off the request
        # Missions this process marked alive, and when: a mission touched less than `touch_interval_s` ago
        # is not written again (a keyframe and a status report each opened it: two commits with an fsync).
        self.touch_interval_s = min(60.0, mission_ttl_s / 10)
        self._touched: dict[tuple[str, str], float] = {}
        self._touched_lock = threading.Lock()

    def open_mission(self, vehicle_id: str, mission_id: str) -> None:
        """Mark the mission alive (QuotaExceededError for one too many) and forget the expired ones."""
        now = self._clock()
        key = (vehicle_id, mission_id)
        with self._touched_lock:
            if now - self._touched.get(key, -math.inf) < self.touch_interval_s:
                return  # alive, and written moments ago: its last-seen time lags by less than the interval
        self.state.expire(now - self.mission_ttl_s)  # an indexed range: only what expired is touched
        self.state.touch_mission(vehicle_id, mission_id, now, self.mission_ttl_s, self.max_missions)
        with self._touched_lock:
            if len(self._touched) >= 4096:  # keep only the recent ones
                self._touched = {k: t for k, t in self._touched.items() if now - t < self.touch_interval_s}
            self._touched[key] = now

    # Candidates and rejections

    def remember_candidates(
        self, vehicle_id: str, mission_id: str, candidates: list[tuple[str, list[float]]]
    ) -> None:
        """Keep the appearance of proposed candidates so a rejection by id can be matched later."""
        self.state.put_candidates(vehicle_id, mission_id, [(cid, vector_bytes(a)) for cid, a in candidates])

    def add_rejection(self, mission_id: str, rejection: RejectionIn) -> Rejection:
        """Record a rejected candidate; its appearance comes from the crop sent or the candidate id."""
        vehicle_id = rejection.vehicle_id
        appearance = (
            crop_descriptor(rejection.crop_jpeg_b64, rejection.crop_box, self.max_crop_pixels)
            if rejection.crop_jpeg_b64
            else None
        )
        self.open_mission(vehicle_id, mission_id)
        if appearance is None:
            known = (
                self.state.candidate(vehicle_id, mission_id, rejection.candidate_id)
                if rejection.candidate_id
                else None
            )
            if known is None:
                raise UnknownCandidateError(
                    f"candidate {rejection.candidate_id!r} is unknown in mission {mission_id!r} of {vehicle_id!r}; "
                    "send crop_jpeg_b64"
                )
            blob = known
        else:
            blob = vector_bytes(appearance)
        record = Rejection(
            rejection_id=0,
            mission_id=mission_id,
            vehicle_id=vehicle_id,
            candidate_id=rejection.candidate_id,
            position=rejection.position,
            reason=rejection.reason,
            created_at=self._clock(),
        )
        return self.state.add_rejection(vehicle_id, mission_id, record, blob, self.max_rejections)

    def rejections(self, vehicle_id: str, mission_id: str) -> list[Rejection]:
        return [r for r, _ in self.state.rejections(vehicle_id, mission_id)]

    def mission_vehicles(self, mission_id: str) -> list[str]:
        """The vehicles searching this mission id (the most recently seen first, at most MISSION_VEHICLES)."""
        return self.state.mission_vehicles(mission_id, MISSION_VEHICLES)

    def rejection_check(
        self, vehicle_id: str, mission_id: str, vehicle_position: list[float] | None
    ) -> Callable[[list[float]], str | None]:
        """A function telling whether a candidate's appearance matches a rejection of the mission: the
        vehicle's own, and another vehicle's of the same mission id made within `radius_m` of where this
        vehicle is (one without a place, or a vehicle without one, holds only for its own vehicle; the
        newest SHARED_REJECTIONS of the others are read, so a fleet's flood of them costs a bounded read)."""
        entries = [(r, vector_from(a)) for r, a in self.state.rejections(vehicle_id, mission_id)]
        if vehicle_position is not None:
            others = [v for v in self.mission_vehicles(mission_id) if v != vehicle_id]
            entries += [
                (r, vector_from(a))
                for r, a in self.state.mission_rejections(mission_id, others, SHARED_REJECTIONS)
                if r.position is not None and distance_m(r.position, vehicle_position) <= self.radius_m
            ]

        def check(appearance: list[float]) -> str | None:
            for record, rejected in entries:
                far = (
                    record.position is not None
                    and vehicle_position is not None
                    and distance_m(record.position, vehicle_position) > self.radius_m
                )
                if far:
                    continue
                score = similarity(appearance, rejected)
                if score >= self.similarity_threshold:
                    via = "" if record.vehicle_id == vehicle_id else f" via {record.vehicle_id}"
                    return (
                        f"looks like candidate {record.candidate_id or record.rejection_id} that the supervisor "
                        f"rejected{via} (appearance similarity {score:.2f})"
                    )
            return None

        return check

    # Vehicle status and supervisor decisions

    def set_status(self, vehicle_id: str, status: VehicleStatusIn) -> VehicleStatus:
        """Store the vehicle's report, extend its mission's map and keep its find; a crop that is not a JPEG
        within the crop size limit: ImageError."""
        awaiting = status.awaiting
        for field, sent in (
            ("awaiting.crop_jpeg_b64", awaiting.crop_jpeg_b64 if awaiting else None),
            ("find.crop_jpeg_b64", status.find.crop_jpeg_b64 if status.find else None),
        ):
            if sent is None:
                continue
            data = b64_image_bytes(sent, field)
            if not is_jpeg(data, self.max_crop_pixels):  # from its header: nothing is decoded here
                raise ImageError(
                    f"{field} must be a JPEG of at most {self.max_crop_pixels} pixels; got {_what(data)}", 422
                )
        if status.mission_id is not None:
            self.open_mission(vehicle_id, status.mission_id)
        now = self._clock()
        previous = self.state.status(vehicle_id)
        kept = previous.awaiting if previous is not None else None
        if (
            awaiting is not None
            and awaiting.crop_jpeg_b64 is None
            and kept is not None
            and kept.candidate_id == awaiting.candidate_id
        ):
            # Vehicles send a candidate's crop once; later reports about the same candidate keep it.
            crop = {"crop_jpeg_b64": kept.crop_jpeg_b64, "crop_box": kept.crop_box}
            status = status.model_copy(update={"awaiting": awaiting.model_copy(update=crop)})
        find = status.find
        if find is not None and find.crop_jpeg_b64 is not None:  # the find keeps its crop, not every status
            status = status.model_copy(update={"find": find.model_copy(update={"crop_jpeg_b64": None})})
        # Validated as the request's body already: built, not validated again (with its covered rings and
        # POD grid that was about 1 ms of CPU a report).
        record = VehicleStatus.model_construct(**dict(status), vehicle_id=vehicle_id, updated_at=now)
        self.state.set_status(record)
        if status.mission_id is not None and (status.position is not None or status.search is not None):
            mission_map = self.state.mission_map(vehicle_id, status.mission_id)
            changed = updated_map(mission_map, status.position, status.search, now)
            if changed is not None:
                self.state.set_mission_map(vehicle_id, status.mission_id, changed)
        if find is not None and status.mission_id is not None:
            self._vehicle_find(vehicle_id, status.mission_id, find, status.prompt, kept)
        return record

    def status(self, vehicle_id: str) -> VehicleStatus | None:
        return self.state.status(vehicle_id)

    def statuses(self) -> list[VehicleStatus]:
        return self.state.statuses()

    # Finds: stored once per (vehicle, mission, candidate), from the vehicle's status or a supervisor's confirm

    def _vehicle_find(
        self,
        vehicle_id: str,
        mission_id: str,
        find: Find,
        prompt: str | None,
        awaited: AwaitingCandidate | None,
    ) -> None:
        """A find the vehicle reports; it replaces one made at the supervisor's confirm (its geolocation is
        the vehicle's own) and records the confirm as the vehicle's report, once: who confirmed it at the
        GCS is the vehicle's word, so it never stands in the way of the supervisor's own decision."""
        known = {f.candidate_id: f for f in self.state.finds(vehicle_id, mission_id)}
        earlier = known.get(find.candidate_id)
        if earlier is not None and earlier.source == "vehicle":
            return  # reported with every status: stored once
        crop = {}
        if find.crop_jpeg_b64 is None:
            if awaited is not None and awaited.candidate_id == find.candidate_id and awaited.crop_jpeg_b64:
                crop = {"crop_jpeg_b64": awaited.crop_jpeg_b64, "crop_box": awaited.crop_box}
            elif earlier is not None:
                crop = {"crop_jpeg_b64": earlier.crop_jpeg_b64, "crop_box": earlier.crop_box}
        stored = StoredFind(
            **{**find.model_dump(), "prompt": find.prompt or prompt or "", **crop},
            vehicle_id=vehicle_id,
            mission_id=mission_id,
            received_at=self._clock(),
            source="vehicle",
        )
        self._keep_find(stored, replace_source="supervisor")
        confirm = DecisionIn(
            candidate_id=find.candidate_id,
            action="confirm",
            operator=find.confirmed_by[:64],
            note="the vehicle's find",
        )
        self.state.add_decision(vehicle_id, mission_id, confirm, self._clock(), source="vehicle")

    def _first_finder(self, find: StoredFind) -> StoredFind | None:
        """An earlier find of the mission of the same person, by another vehicle or by this one under another
        candidate id (a tracker that lost the person and found them again): within two sigma of the
        difference of the two positions (an unknown sigma counts as FIND_SIGMA_UNKNOWN_M), at most
        `radius_m` apart. The same candidate again is that find refined, not another."""
        sigma = find.sigma_m if find.sigma_m is not None else FIND_SIGMA_UNKNOWN_M
        candidates = [
            f
            for v in self.mission_vehicles(find.mission_id)
            for f in self.state.finds(v, find.mission_id)
            if f.same_as is None and (v, f.candidate_id) != (find.vehicle_id, find.candidate_id)
        ]
        for other in sorted(candidates, key=lambda f: f.received_at):
            theirs = other.sigma_m if other.sigma_m is not None else FIND_SIGMA_UNKNOWN_M
            reach = min(self.radius_m, max(FIND_SAME_MIN_M, 2 * math.hypot(sigma, theirs)))
            if distance_m(other.position, find.position) <= reach:
                return other
        return None

    def _keep_find(self, find: StoredFind, replace_source: str | None = None) -> None:
        first = self._first_finder(find)
        if first is not None:  # one person, one find: this vehicle's is kept as its sighting of it
            find = find.model_copy(update={"same_as": f"{first.vehicle_id}/{first.candidate_id}"})
        try:
            saved, changed = self.state.put_find(find, replace_source)
        except QuotaExceededError as exc:
            log.warning("find %s not stored: %s", find.candidate_id, exc)
            return
        if changed and saved.same_as is None:
            self.state.set_fleet(saved.mission_id, "found", f"{saved.vehicle_id}/{saved.candidate_id}")
            self._tell_find(saved)

    # What the fleet does on a confirmed find

    def set_on_find(self, mission_id: str, on_find: OnFind) -> str:
        """Set the mission's `on_find` unless one is set: the one that stands."""
        return self.state.set_fleet(mission_id, "on_find", on_find)

    def fleet_order(self, vehicle_id: str, mission_id: str) -> FleetOrder:
        """What the vehicle is to do now: "continue" until the mission's first find is confirmed, and always
        for the vehicle that found the person; then the mission's on_find for every other vehicle."""
        fleet = self.state.fleet(mission_id)
        raw = fleet.get("on_find", "continue")
        on_find: OnFind = "hold" if raw == "hold" else "return" if raw == "return" else "continue"
        found = fleet.get("found")
        finder = found.partition("/")[0] if found else None
        order: OnFind = on_find if found is not None and finder != vehicle_id else "continue"
        return FleetOrder(
            mission_id=mission_id,
            vehicle_id=vehicle_id,
            on_find=on_find,
            found=found,
            order=order,
            rejections=self.fleet_rejections(vehicle_id, mission_id),
        )

    def fleet_rejections(self, vehicle_id: str, mission_id: str) -> list[FleetRejection]:
        """The other vehicles' rejections of the mission that carry a place, newest first, at most
        FLEET_REJECTIONS_MAX: the companion keeps candidates standing there from being proposed (by place;
        `rejection_check`'s appearance match fails for a look-alike seen from another lane). A candidate
        rejected twice (the supervisor's reject, then its vehicle's report of it) is listed once."""
        others = [v for v in self.mission_vehicles(mission_id) if v != vehicle_id]
        # Twice the answer's length read: most rejections come in such pairs. Redis reads each vehicle's newest.
        read = self.state.mission_rejections(mission_id, others, 2 * FLEET_REJECTIONS_MAX)
        listed: list[FleetRejection] = []
        seen: set[tuple[str, str]] = set()
        for record, _ in sorted(read, key=lambda ra: -ra[0].rejection_id):
            key = (record.vehicle_id, record.candidate_id or f"#{record.rejection_id}")
            if record.position is None or key in seen:
                continue
            seen.add(key)
            listed.append(
                FleetRejection(
                    rejection_id=record.rejection_id,
                    vehicle_id=record.vehicle_id,
                    candidate_id=record.candidate_id,
                    position=list(record.position),
                )
            )
        return listed[:FLEET_REJECTIONS_MAX]

    def _tell_find(self, find: StoredFind) -> None:
        if self.on_find is not None:
            try:
                self.on_find(self.with_provenance(find))
            except Exception:  # telling the TAK server must never lose the find
                log.exception("find %s stored, but not forwarded", find.candidate_id)

    def with_provenance(self, find: StoredFind) -> StoredFind:
        """The find with who confirmed it and through what (`decided_via`, `decided_by`): the supervisor's
        standing confirm on its candidate when there is one, else the vehicle's report in the vehicle's name,
        whatever name the vehicle gave (a supervisor's reject standing on it is said too)."""
        vehicle = find.vehicle_id
        standing = self.state.standing_decision(vehicle, find.mission_id, find.candidate_id)
        if standing is not None and standing.action == "confirm":
            via = decided_via(standing.source, standing.via)
            text = decision_text(via, standing.operator, vehicle)
        elif find.source == "supervisor":  # made at a supervisor's confirm that is no longer kept
            via, text = "back-end API", decision_text("back-end API", find.confirmed_by, vehicle)
        else:
            via = "GCS via the vehicle"
            text = decision_text(via, find.confirmed_by, vehicle)
            if standing is not None:  # the supervisor rejected what the vehicle reports confirmed
                text += f"; rejected by {decision_text(decided_via(standing.source, standing.via), standing.operator, vehicle)}"
        return find.model_copy(update={"decided_via": via, "decided_by": text})

    def finds(self, vehicle_id: str, mission_id: str | None = None) -> list[StoredFind]:
        """The vehicle's finds, each with who confirmed it and through what; a person another vehicle of
        the mission found first is that vehicle's find, not listed here (`sightings` has it)."""
        return [
            self.with_provenance(f) for f in self.state.finds(vehicle_id, mission_id) if f.same_as is None
        ]

    def sightings(self, vehicle_id: str, mission_id: str | None = None) -> list[StoredFind]:
        """The vehicle's finds of persons another vehicle of the mission found first (`same_as`)."""
        return [f for f in self.state.finds(vehicle_id, mission_id) if f.same_as is not None]

    def mission_finds(self, mission_id: str) -> list[StoredFind]:
        """The mission's finds over every vehicle searching it: one per person, oldest first."""
        found = [f for v in self.mission_vehicles(mission_id) for f in self.finds(v, mission_id)]
        return sorted(found, key=lambda f: (f.time, f.received_at))

    def mission_map(self, vehicle_id: str, mission_id: str) -> MissionMap | None:
        return self.state.mission_map(vehicle_id, mission_id)

    def merged_map(self, mission_id: str) -> MergedMap | None:
        """The map of every vehicle searching the mission id, merged (backend.mission_merge); None when no
        vehicle has reported a map of it. As kept (`backend.merged_maps`): merged again at most once per
        `merge_period_s`, its `as_of` says when its vehicles' maps were read."""
        return self.merged_maps.get(mission_id)

    def _mission_maps(self, mission_id: str) -> list[tuple[str, MissionMap]]:
        maps = [(v, self.state.mission_map(v, mission_id)) for v in self.mission_vehicles(mission_id)]
        return [(v, m) for v, m in maps if m is not None]

    def dropouts(self, mission_id: str) -> MissionDropouts | None:
        """Who of the mission's vehicles left its search and the part of its area left unflown
        (`backend.fleet_dropout`), worked out from each vehicle's last status and map on every read (nothing
        is stored for it); None when no vehicle has reported a map of the mission. A vehicle that left before
        any status of it carried its part of the area is listed with `area_known` false: what it left unflown
        is unknown, which "0 m2 unflown" would hide."""
        now = self._clock()
        maps = [(v, self.state.mission_map(v, mission_id)) for v in self.mission_vehicles(mission_id)]
        kept = [(v, m) for v, m in maps if m is not None]
        if not kept:
            return None
        searching: list[str] = []
        left_search = []
        unknown: list[Dropout] = []  # left before reporting its part: what it left unflown is not known
        for vehicle, mission_map in sorted(maps, key=lambda vm: vm[0]):
            status = self.state.status(vehicle)
            if mission_map is None or len(mission_map.area) < 3:
                seen = mission_map.updated_at if mission_map is not None else None
                if seen is None and status is None:
                    continue
                left = leaving(mission_id, status, seen if seen is not None else 0.0, now, self.dropout_s)
                if left is not None:  # never "0 m2 unflown": its part is unknown, not flown
                    unknown.append(
                        Dropout(
                            vehicle_id=vehicle,
                            kind=left.kind,
                            reason=left.reason,
                            since=left.since,
                            area_known=False,
                        )
                    )
                continue  # searching without a part of the area: nothing of it to re-plan
            left = leaving(mission_id, status, mission_map.updated_at, now, self.dropout_s)
            if left is None:
                searching.append(vehicle)
            else:
                left_search.append((vehicle, mission_map, left))
        unflown = (
            unflown_parts([m.area for _, m, _ in left_search], [m.covered for _, m in kept if m.covered])
            if left_search
            else []
        )
        dropouts = [
            Dropout(
                vehicle_id=vehicle,
                kind=left.kind,
                reason=left.reason,
                since=left.since,
                unflown=part.rings,
                area_m2=part.area_m2,
            )
            for (vehicle, _, left), part in zip(left_search, unflown, strict=True)
        ]
        dropouts = sorted([*dropouts, *unknown], key=lambda d: d.vehicle_id)
        return MissionDropouts(
            mission_id=mission_id,
            dropout_s=self.dropout_s,
            dropouts=dropouts,
            searching=searching,
            server_time=now,
        )

    # The newest keyframe, for the supervisor's live view

    def set_keyframe(
        self,
        vehicle_id: str,
        mission_id: str,
        frame_id: int | None,
        data: bytes,
        size: tuple[int, int],
        candidates: list[KeyframeCandidate],
        took_s: float = 0.0,
    ) -> None:
        """Keep the keyframe as sent (a JPEG only: the page shows it as one) with the answer's boxes. `took_s`:
        how long the answer took, so its age on the page counts from when the keyframe arrived."""
        if not is_jpeg(data, size[0] * size[1] + 1):
            return
        record = KeyframeRecord(
            frame_id=frame_id,
            mission_id=mission_id,
            width=size[0],
            height=size[1],
            received_at=self._clock() - max(0.0, took_s),
            candidates=candidates,
        )
        self.state.set_keyframe(vehicle_id, record, data)

    # Supervisor decisions: the first on a candidate stands

    def add_decision(
        self, vehicle_id: str, decision: DecisionIn, source: str = "supervisor"
    ) -> tuple[Decision, bool]:
        """Record the supervisor's confirm/reject unless a decision on that candidate stands already (then
        that one, created False). A reject that stands enters the mission's rejection memory; a confirm
        that stands is kept as a find at the candidate's reported position.

        The decision is stored whatever happens to the rejection memory (an undecodable crop, a full
        mission): the companion must get the supervisor's word. Both are stored before this returns.
        """
        current = self.status(vehicle_id)
        mission_id = current.mission_id if current else None
        awaiting = current.awaiting if current else None
        same = awaiting if awaiting is not None and awaiting.candidate_id == decision.candidate_id else None
        record, created = self.state.add_decision(vehicle_id, mission_id, decision, self._clock(), source)
        if not created or mission_id is None:
            return record, created
        for find in self.state.finds(vehicle_id, mission_id):
            if (
                find.candidate_id == decision.candidate_id and find.same_as is None
            ):  # the vehicle's find: now the supervisor's word too
                self._tell_find(find)
        if decision.action == "reject":
            try:
                self.add_rejection(
                    mission_id,
                    RejectionIn(
                        vehicle_id=vehicle_id,
                        candidate_id=decision.candidate_id,
                        crop_jpeg_b64=same.crop_jpeg_b64 if same else None,
                        crop_box=same.crop_box if same else None,
                        position=same.position if same else None,
                        reason=decision.note or "rejected by the supervisor",
                    ),
                )
            except (UnknownCandidateError, ImageError, ValueError, QuotaExceededError) as exc:
                # Unknown candidate without a crop, a crop that cannot be read: nothing to match later.
                log.warning(
                    "reject of %s by the supervisor not remembered for matching: %s",
                    decision.candidate_id,
                    exc,
                )
        elif same is not None and same.position is not None:
            self._keep_find(
                StoredFind(
                    candidate_id=decision.candidate_id,
                    position=same.position,
                    sigma_m=None,  # the vehicle's own find, when it comes, says how sure it is
                    time=record.created_at,
                    seen_at=same.seen_at,
                    prompt=(current.prompt if current else None) or "",
                    confirmed_by=decision.operator or "supervisor",
                    crop_jpeg_b64=same.crop_jpeg_b64,
                    crop_box=same.crop_box,
                    vehicle_id=vehicle_id,
                    mission_id=mission_id,
                    received_at=record.created_at,
                    source="supervisor",
                )
            )
        return record, created

    def record_vehicle_reject(self, vehicle_id: str, mission_id: str, candidate_id: str) -> None:
        """A reject the vehicle took from its GCS over MAVLink (it reports it as a rejection): kept as the
        vehicle's report (the page shows it), never as the standing decision; the supervisor may still
        decide, and the vehicle gets that decision as any other."""
        reject = DecisionIn(
            candidate_id=candidate_id, action="reject", operator="gcs", note="reported by the vehicle"
        )
        self.state.add_decision(vehicle_id, mission_id, reject, self._clock(), source="vehicle")

    def standing_decision(
        self, vehicle_id: str, mission_id: str | None, candidate_id: str
    ) -> Decision | None:
        """The supervisor's decision that stands on the candidate; a vehicle's report is none."""
        return self.state.standing_decision(vehicle_id, mission_id, candidate_id)

    def reported_decision(
        self, vehicle_id: str, mission_id: str | None, candidate_id: str
    ) -> Decision | None:
        """What the vehicle reported was decided on the candidate at its GCS."""
        return self.state.reported_decision(vehicle_id, mission_id, candidate_id)

    def decisions(self, vehicle_id: str, after: int = 0) -> list[Decision]:
        return self.state.decisions(vehicle_id, after)

    def decisions_dropped(self, vehicle_id: str) -> int:
        """The highest decision_id dropped from the vehicle's list (0: none)."""
        return self.state.decisions_dropped(vehicle_id)
