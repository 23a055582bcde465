"""The search area and how much of it the camera has seen, in flight (issue 27: coverage).

The search area is the autopilot's own mission's: when a mission starts, the companion downloads the
autopilot's mission over its own link (`cloudtrack.mission_protocol.MissionClient`, in a background thread:
the main loop never waits on the autopilot) and takes the area the waypoints sweep
(`cloudtrack.coverage.area_from_waypoints`: their hull grown by half a lane), so a survey planned by
`cloudtrack-gcs survey`, QGroundControl or Mission Planner is covered the same way. A failed download is
tried again every `RETRY_S` while the mission runs; a mission without waypoints has no area (coverage is
then not reported).

Views: every telemetry sample while the mission runs is a camera pose; `cloudtrack.coverage.CoverageMap`
lays the camera's ground footprint (cut at `[camera] search_range_m`) on the area and keeps their union.
Poses that arrive before the area is known are kept (bounded) and laid down once it is. The figures for
the status report (area, share seen, the seen rings) are recomputed at most once per `REPORT_PERIOD_S`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

from behaviors.camera_model import CameraModel
from behaviors.mission_items import waypoint_positions
from behaviors.telemetry import Telemetry
from cloudtrack.coverage import CoverageMap, area_from_waypoints
from cloudtrack.mission_protocol import MissionClient, MissionError, MissionLink

log = logging.getLogger(__name__)

RETRY_S = 10.0
REPORT_PERIOD_S = 1.0
MAX_PENDING_POSES = 20_000  # poses kept while the area is unknown (about 30 min at 10 Hz)
AREA_MAX_VERTICES = 200  # VehicleStatusIn.search.area

Pose = tuple[float, float, float, float, float, float]  # lat, lon, height, yaw, roll, pitch


class SearchCoverage:
    """One mission's search area and coverage; `update`/`report` from the main loop, the download in its own
    thread. `mission_link()` gives a link the mission protocol can run over; `autopilot()` "ardupilot",
    "px4" or None while the autopilot is not known yet."""

    def __init__(
        self,
        camera: CameraModel,
        search_range_m: float,
        mission_link: Callable[[], MissionLink],
        autopilot: Callable[[], str | None],
        ids: tuple[int, int],  # (target system, our component)
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._camera = camera
        self._range = search_range_m
        self._mission_link = mission_link
        self._autopilot = autopilot
        self._ids = ids
        self._clock = clock
        self._lock = threading.Lock()
        self._map: CoverageMap | None = None
        self._pending: deque[Pose] = deque(maxlen=MAX_PENDING_POSES)
        self._running = False  # a mission is on: poses count
        self._generation = 0  # a new mission's download replaces an older one still running
        self._thread: threading.Thread | None = None
        self._report: dict[str, Any] | None = None
        self._reported_at = -float("inf")
        self.error = ""  # why there is no area (the last download's failure), for the log and the status

    # ------------------------------------------------------------------------------------- control
    def start(self) -> None:
        """A mission started: forget the last one's area and views, download the autopilot's mission."""
        with self._lock:
            self._generation += 1
            generation = self._generation
            self._map = None
            self._pending.clear()
            self._running = True
            self._report = None
            self._reported_at = -float("inf")
            self.error = ""
        self._thread = threading.Thread(
            target=self._download_until_known, args=(generation,), name="mission-download", daemon=True
        )
        self._thread.start()

    def stop(self) -> None:
        """The mission is over (aborted, stopped): no more views; the figures stay as they were."""
        with self._lock:
            self._running = False
            self._generation += 1

    # ------------------------------------------------------------------------------------ the loop
    def update(self, telemetry: Telemetry) -> None:
        """A camera pose while the mission runs (the vehicle's telemetry; a gimbal's roll and pitch are
        ignored by the footprint when the camera is stabilised)."""
        pose = (
            telemetry.lat_deg, telemetry.lon_deg, telemetry.height_agl,
            telemetry.yaw, telemetry.roll, telemetry.pitch,
        )  # fmt: skip
        with self._lock:
            if not self._running:
                return
            if self._map is None:
                self._pending.append(pose)
                return
            self._map.add_view(*pose)

    def report(self) -> dict[str, Any] | None:
        """`{area, coverage, covered}` for the status report (at most once per REPORT_PERIOD_S recomputed);
        None while the area is unknown."""
        now = self._clock()
        with self._lock:
            if self._map is None:
                return None
            if self._report is None or now - self._reported_at >= REPORT_PERIOD_S:
                self._report = {
                    "area": [[round(lat, 7), round(lon, 7)] for lat, lon in self._map.area_corners][
                        :AREA_MAX_VERTICES
                    ],
                    "coverage": round(self._map.coverage(), 4),
                    "covered": self._map.covered_rings(),
                }
                self._reported_at = now
            return dict(self._report)

    # ------------------------------------------------------------------------------ the download
    def _download_until_known(self, generation: int) -> None:
        while True:
            with self._lock:
                if generation != self._generation:
                    return
            try:
                area = self._download_area()
            except (MissionError, OSError, ValueError) as exc:
                with self._lock:
                    self.error = f"mission download: {exc}"
                log.warning("search area unknown (%s); trying again in %.0f s", exc, RETRY_S)
                time.sleep(RETRY_S)
                continue
            with self._lock:
                if generation != self._generation:
                    return
                if not area:
                    self.error = "the autopilot's mission has no waypoints spanning an area"
                    log.warning("search area unknown: %s", self.error)
                    return
                self._map = CoverageMap(area, self._camera, self._range)
                for pose in self._pending:
                    self._map.add_view(*pose)
                self._pending.clear()
                log.info("search area: %d corners from the autopilot's mission", len(area))
            return

    def _download_area(self) -> list[tuple[float, float]]:
        kind = self._autopilot()
        if kind is None:
            raise MissionError("the autopilot is not known yet")
        system, component = self._ids
        client = MissionClient(self._mission_link(), kind, target=(system, 1), source=(system, component))
        mission = client.download()
        return area_from_waypoints(waypoint_positions(list(mission.items)))
