"""The search area and what the search has analysed of it, in flight (issue 27: coverage; issue 42: POD).

The search area is the autopilot's own mission's: when a mission starts, the companion downloads the
autopilot's mission over its own link (`cloudtrack.mission_protocol.MissionClient`, in a background thread:
the main loop never waits on the autopilot) and takes the area the waypoints sweep
(`cloudtrack.coverage.area_from_waypoints`: their hull grown by half a lane), so a survey planned by
`cloudtrack-gcs survey`, QGroundControl or Mission Planner is covered the same way. A failed download is
tried again every `RETRY_S` while the mission runs; a mission without waypoints has no area (coverage is
then not reported), and one farther than `[safety] max_survey_distance_m` from the vehicle is not mapped
(both said on the GCS). A mission replaced while the search runs is downloaded again: the autopilot's item
count changes (MISSION_CURRENT.total), or its current item goes back (a new survey starts at its first
item). The new area gets new maps; the back-end keeps the old area's map (`backend/mission_map.py`).

Looks: only a keyframe the back-end analysed counts (`add_look`: a final answer to a whole-frame query, at
the vehicle's pose when the keyframe was captured). A keyframe that was never sent, replaced under load, or
lost with the back-end adds nothing, so the map never calls searched what nobody analysed. Each look lays
the camera's footprint (`cloudtrack.coverage.CoverageMap`: the share seen) and the target's probability of
detection per place (`cloudtrack.pod_map.PodMap`, for the mission's superset class with the [search]
section's shape and target POD; a class without a detection curve gets coverage only, and the reason).
Looks are kept (bounded) so an area that arrives later, or a new one, is laid from all of them, off the
main loop. The figures for the status report are recomputed at most once per `REPORT_PERIOD_S`. The
report's `covered` is the seen ground within the search range of the area, not only inside it: a fleet's
vehicle sees into its neighbours' parts (lanes overlap), and the back-end's merged map and drop-outs count
what any vehicle saw of a part (the share, `coverage`, stays that of this vehicle's own area).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from behaviors.apparent_size import TargetShape
from behaviors.camera_model import CameraModel
from behaviors.detection_curve import CurveError
from behaviors.mission_items import waypoint_positions
from behaviors.survey_planner import too_far
from behaviors.telemetry import Telemetry
from cloudtrack.coverage import CoverageMap, LatLon, area_from_waypoints
from cloudtrack.detection_curves import curve_for
from cloudtrack.mission_protocol import MissionClient, MissionError, MissionLink
from cloudtrack.pod_map import PodMap, PodSettings
from cloudtrack.vehicle_config import SearchConfig

log = logging.getLogger(__name__)

RETRY_S = 10.0
REPORT_PERIOD_S = 1.0
MAX_LOOKS = 20_000  # analysed keyframes kept to lay a new area from (about 2.8 h at 2 a second)
AREA_MAX_VERTICES = 200  # VehicleStatusIn.search.area

Pose = tuple[float, float, float, float, float, float]  # lat, lon, height, yaw, roll, pitch
Look = tuple[Pose, float, bool]  # the pose a keyframe was captured from, when, and lit for the curve


class _Maps:
    """One area's maps: the footprint coverage and, where the class has a curve, the POD grid."""

    def __init__(self, area: Sequence[LatLon], cover: CoverageMap, pod: PodMap | None) -> None:
        self.area = tuple(area)
        self.cover = cover
        self.pod = pod
        self.dark_looks = 0  # analysed keyframes too dark for the curve, laid on the coverage only

    def lay(self, look: Look) -> None:
        (lat, lon, height, yaw, roll, pitch), when, lit = look
        self.cover.add_view(lat, lon, height, yaw, roll, pitch)
        if self.pod is not None:
            if lit:
                self.pod.add_look(lat, lon, height, yaw, when, roll, pitch)
            else:  # the detection curve cannot judge it (behaviors.scene_light): no place gains POD
                self.dark_looks += 1


class SearchCoverage:
    """One mission's search area, coverage and POD map; `update`/`add_look`/`report` from the main loop,
    the download and the laying of a new area in their own thread. `mission_link()` gives a link the
    mission protocol can run over; `autopilot()` "ardupilot", "px4" or None while the autopilot is not known
    yet."""

    def __init__(
        self,
        camera: CameraModel,
        search_range_m: float,
        mission_link: Callable[[], MissionLink],
        autopilot: Callable[[], str | None],
        ids: tuple[int, int],  # (target system, our component)
        search: SearchConfig | None = None,
        keyframe_width: int = 640,
        accept_uncertain: bool = False,
        max_distance_m: float = math.inf,  # [safety] max_survey_distance_m
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._camera = camera
        self._range = search_range_m
        self._mission_link = mission_link
        self._autopilot = autopilot
        self._ids = ids
        self._search = search or SearchConfig()
        self._keyframe_width = keyframe_width
        self._accept_uncertain = accept_uncertain
        self._max_distance_m = max_distance_m
        self._position: tuple[float, float] | None = None  # the vehicle's, from the last telemetry
        self._clock = clock
        self._lock = threading.Lock()
        self._maps: _Maps | None = None
        self._looks: deque[Look] = deque(maxlen=MAX_LOOKS)
        self._added = 0  # looks added since the start (the deque drops its oldest)
        self._running = False  # a mission is on: looks count
        self._generation = 0  # a newer download supersedes an older one still running
        self._target_class = self._search.target_class
        self._mission_seen: tuple[int | None, int | None] | None = None  # (item, items) last telemetry
        self._report: dict[str, Any] | None = None
        self._reported_at = -float("inf")
        self.error = ""  # why there is no area (the last download's failure), for the log and the status
        self.pod_error = ""  # why there is no POD map (no curve for the class)

    # ------------------------------------------------------------------------------------- control
    def start(self, target_class: str = "") -> None:
        """A mission started: forget the last one's area and looks, download the autopilot's mission.
        `target_class`: the mission's superset (empty: `[search] target_class`)."""
        with self._lock:
            self._maps = None
            self._looks.clear()
            self._added = 0
            self._running = True
            self._target_class = target_class.strip().lower() or self._search.target_class
            self._mission_seen = None
            self._report = None
            self._reported_at = -float("inf")
            self.error = ""
        self._download()

    def stop(self) -> None:
        """The mission is over (aborted, stopped): no more looks; the figures stay as they were."""
        with self._lock:
            self._running = False
            self._generation += 1

    # ------------------------------------------------------------------------------------ the loop
    def update(self, telemetry: Telemetry) -> None:
        """The vehicle's telemetry while the mission runs: a replaced mission is downloaded again."""
        seen = (telemetry.mission_item, telemetry.mission_items)
        with self._lock:
            if math.isfinite(telemetry.lat_deg) and math.isfinite(telemetry.lon_deg):
                self._position = (telemetry.lat_deg, telemetry.lon_deg)
            if not self._running:
                return
            before, self._mission_seen = self._mission_seen, seen
        if before is None or seen == before:
            return
        (item0, items0), (item1, items1) = before, seen
        went_back = item0 is not None and item1 is not None and item1 < item0
        if (items1 is not None and items1 != items0) or went_back:
            log.info("the autopilot's mission changed (item %s of %s): downloading it again", item1, items1)
            self._download()

    def add_look(self, pose: Telemetry, capture_time: float, lit: bool = True) -> None:
        """A keyframe the back-end analysed, captured from `pose` at `capture_time` (a gimbal's roll and
        pitch are ignored by the footprint when the camera is stabilised); not `lit`: too dark for the
        detection curve (`behaviors.scene_light`), so it lays coverage but no POD."""
        look: Look = (
            (pose.lat_deg, pose.lon_deg, pose.height_agl, pose.yaw, pose.roll, pose.pitch),
            capture_time,
            lit,
        )
        with self._lock:
            if not self._running:
                return
            self._looks.append(look)
            self._added += 1
            if self._maps is not None:
                self._maps.lay(look)

    def report(self) -> dict[str, Any] | None:
        """`{area, coverage, covered[, pod]}` for the status report (at most once per REPORT_PERIOD_S
        recomputed); None while the area is unknown."""
        now = self._clock()
        with self._lock:
            maps = self._maps
            if maps is None:
                return None
            if self._report is None or now - self._reported_at >= REPORT_PERIOD_S:
                report: dict[str, Any] = {
                    "area": [[round(lat, 7), round(lon, 7)] for lat, lon in maps.area][:AREA_MAX_VERTICES],
                    "coverage": round(maps.cover.coverage(), 4),
                    # what it saw of the ground around its area too: a neighbour's part (module doc)
                    "covered": maps.cover.covered_rings(beyond_m=self._range),
                }
                if maps.pod is not None:
                    report["pod"] = {**maps.pod.report(), "dark_looks": maps.dark_looks}
                self._report, self._reported_at = report, now
            return dict(self._report)

    # ------------------------------------------------------------------------------ the download
    def _download(self) -> None:
        with self._lock:
            self._generation += 1
            generation = self._generation
        threading.Thread(
            target=self._download_until_known, args=(generation,), name="mission-download", daemon=True
        ).start()

    def _current(self, generation: int) -> bool:
        with self._lock:
            return generation == self._generation

    def _download_until_known(self, generation: int) -> None:
        while self._current(generation):
            try:
                area = self._download_area()
            except (MissionError, OSError, ValueError) as exc:
                with self._lock:
                    self.error = f"mission download: {exc}"
                log.warning("search area unknown (%s); trying again in %.0f s", exc, RETRY_S)
                time.sleep(RETRY_S)
                continue
            with self._lock:
                position = self._position
            why = "the autopilot's mission has no waypoints spanning an area" if not area else None
            if area and position is not None:
                why = too_far(area, position, self._max_distance_m, "the vehicle")
            if why is not None:  # the map would claim nothing there, or somewhere nobody meant
                with self._lock:
                    if generation == self._generation:
                        self.error = why
                log.warning("search area not mapped: %s", why)
                return
            self._lay_area(generation, area)
            return

    def _lay_area(self, generation: int, area: list[LatLon]) -> None:
        """New maps for `area`, laid from every look so far, here (not on the main loop); swapped in with the
        looks that arrived meanwhile. The same area again keeps the maps it has."""
        with self._lock:
            if self._maps is not None and self._maps.area == tuple(area):
                return
            looks, added = list(self._looks), self._added
        maps = self._new_maps(area)
        for look in looks:
            maps.lay(look)
        with self._lock:
            if generation != self._generation:
                return
            since = min(self._added - added, len(self._looks))
            for look in list(self._looks)[len(self._looks) - since :] if since else ():
                maps.lay(look)
            self._maps = maps
            self._report = None
            self.error = ""
        log.info("search area: %d corners from the autopilot's mission", len(area))

    def _new_maps(self, area: Sequence[LatLon]) -> _Maps:
        cover = CoverageMap(area, self._camera, self._range)
        s = self._search
        try:
            curve = curve_for(self._target_class, Path(s.curve_file) if s.curve_file else None)
        except CurveError as exc:
            self.pod_error = str(exc)
            log.warning("no POD map: %s", exc)
            return _Maps(area, cover, None)
        self.pod_error = ""
        shape = TargetShape.for_class(self._target_class, s.posture, s.target_height_m)
        settings = PodSettings(
            target_class=self._target_class,
            posture=s.posture if self._target_class == "person" else "",
            shape=shape,
            accept_uncertain=self._accept_uncertain,
            target_pod=s.target_pod,
            keyframe_width=self._keyframe_width,
            pass_gap_s=s.pass_gap_s,
        )
        return _Maps(area, cover, PodMap(area, self._camera, self._range, curve, settings))

    def _download_area(self) -> list[LatLon]:
        kind = self._autopilot()
        if kind is None:
            raise MissionError("the autopilot is not known yet")
        system, component = self._ids
        client = MissionClient(self._mission_link(), kind, target=(system, 1), source=(system, component))
        mission = client.download()
        return area_from_waypoints(waypoint_positions(list(mission.items)))
