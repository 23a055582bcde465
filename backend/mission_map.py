"""A mission's map from the vehicle's status reports: its track, decimated and bounded, and the search area,
covered area and POD map it last reported. Pure functions over `backend.schemas.MissionMap`.

A status that reports another search area than the one kept means the mission's survey was replaced: the
kept area is moved, with its covered area and POD map, to the mission's earlier areas (the last
`EARLIER_AREAS_KEPT`), and the new area starts with what the status says of it. A status without a POD map
keeps the one the area has (it says nothing of it); a new area starts without one.

The track keeps a point when the vehicle has moved `min_step_m` from the last one kept (hovering adds
nothing), and never more than `max_points`: when full, every other point of the older half is dropped, so
a long flight keeps its whole shape at a coarser step and the recent part in full.
"""

from __future__ import annotations

import math

from backend.schemas import EarlierArea, MissionMap
from cloudtrack.api_models import SearchStatus

TRACK_MIN_STEP_M = 3.0
TRACK_MAX_POINTS = 1000
EARLIER_AREAS_KEPT = 8
EARTH_RADIUS_M = 6_371_000.0


def distance_m(a: list[float], b: list[float]) -> float:
    """Great-circle distance between two [lat, lon] points in metres (haversine).

    The API refuses positions off the globe; one stored before it did (lat 135) makes h negative, which
    is clamped rather than raised on (a math domain error was a 500 on every later detect)."""
    lat1, lon1, lat2, lon2 = map(math.radians, (a[0], a[1], b[0], b[1]))
    h = math.sin((lat2 - lat1) / 2) ** 2 + math.cos(lat1) * math.cos(lat2) * math.sin((lon2 - lon1) / 2) ** 2
    return 2 * EARTH_RADIUS_M * math.asin(math.sqrt(min(1.0, max(0.0, h))))


def extend_track(
    track: list[list[float]],
    position: list[float],
    time_s: float,
    min_step_m: float = TRACK_MIN_STEP_M,
    max_points: int = TRACK_MAX_POINTS,
) -> list[list[float]] | None:
    """The track with `position` at `time_s` added, or None when it adds nothing (too close to the last)."""
    if track and distance_m(track[-1][:2], position) < min_step_m:
        return None
    grown = [*track, [position[0], position[1], time_s]]
    if len(grown) > max_points:
        half = len(grown) // 2
        grown = grown[:half:2] + grown[half:]
    return grown


def updated_map(
    current: MissionMap | None, position: list[float] | None, search: SearchStatus | None, time_s: float
) -> MissionMap | None:
    """The mission's map after one status report, or None when the report changes nothing."""
    base = current or MissionMap()
    changes: dict[str, object] = {}
    if position is not None:
        track = extend_track(base.track, position, time_s)
        if track is not None:
            changes["track"] = track
    if search is not None:
        if search.area and base.area and search.area != base.area:
            replaced = EarlierArea(
                area=base.area,
                covered=base.covered,
                coverage=base.coverage,
                pod=base.pod,
                since=base.area_since,
                replaced_at=time_s,
            )
            changes.update(
                earlier=[*base.earlier, replaced][-EARLIER_AREAS_KEPT:],
                area=search.area,
                area_since=time_s,
                covered=search.covered,
                coverage=search.coverage,
                pod=search.pod,
            )
        else:
            if search.area and not base.area:
                changes.update(area=search.area, area_since=time_s)
            if search.covered != base.covered or search.coverage != base.coverage:
                changes.update(covered=search.covered, coverage=search.coverage)
            if search.pod is not None and search.pod != base.pod:
                changes["pod"] = search.pod
    if not changes:
        return None
    return base.model_copy(update={**changes, "updated_at": time_s})
