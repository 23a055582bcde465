"""A vehicle that drops out of a fleet's search, and the part of its area it leaves unflown.

Pure functions over what the back-end already keeps per vehicle (its last status, its map of the mission):
nothing is stored for a drop-out, it is worked out on each read.

A vehicle of a mission has left the search (`leaving`) when
- its last status reports a flight mode that takes it home or down (`cloudtrack.autopilot_modes.RETURN_MODES`: ArduPilot's RTL, SMART_RTL,
  LAND, QRTL, QLAND, AUTO_RTL; PX4's RTL, LAND, RTGS, and "RETURN" as QGroundControl names PX4's RTL);
- its companion reports the mission ABORTED (a pilot's takeover, the autopilot link lost, the operator's abort:
  the status's reason says which);
- its last status names another mission (it was given another search);
- the back-end has had no status from it for longer than `dropout_s` (`[fleet] dropout_s`): its link or its
  companion is lost.
`since` is the time of the last status that says so (for a silent vehicle: its last status at all).

Its unflown part (`unflown_part`) is its own part of the area (the search area it reports: its part of the
split) less what any vehicle of the mission has covered, in metres in a local frame: slivers thinner than
`2 * SLIVER_M` (the camera footprints' ragged edges along the lanes) are opened away, and pieces smaller than
`MIN_PIECE_M2` dropped, so what is left is what a re-plan must fly. It is returned as at most `MAX_RINGS`
rings of at most `MAX_VERTICES` vertices (`cloudtrack.coverage.bounded_rings`), as the merged map bounds its own.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import shapely
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from backend.mission_merge import _metres
from cloudtrack.api_models import VehicleStatus
from cloudtrack.autopilot_modes import RETURN_MODES
from cloudtrack.coverage import LocalFrame, bounded_rings, geometry_from_rings

ABORTED_STATE = "ABORTED"
SLIVER_M = 4.0
MIN_PIECE_M2 = 50.0
MAX_RINGS = 20
MAX_VERTICES = 500
LeavingKind = Literal["mode", "aborted", "moved", "silent"]


@dataclass(frozen=True)
class Leaving:
    kind: LeavingKind
    reason: str  # one line for a person: "mode RTL", "aborted: pilot takeover LOITER", "silent for 42 s"
    since: float  # Unix time of the last status that says so


@dataclass(frozen=True)
class Unflown:
    rings: list[list[list[float]]]  # [lat, lon] rings, outer counter-clockwise, holes clockwise
    area_m2: float


def leaving(
    mission_id: str, status: VehicleStatus | None, last_seen: float, now: float, dropout_s: float
) -> Leaving | None:
    """Why the vehicle has left the mission's search, or None while it searches it (see the module doc).
    `status`: its last status (None: none kept); `last_seen`: when the back-end last heard of it in this
    mission (its status's time, else its map's)."""
    if status is not None and status.mission_id == mission_id:
        mode = (status.search.mode if status.search is not None else "").strip().upper()
        if mode in RETURN_MODES:
            return Leaving("mode", f"mode {mode}", status.updated_at)
        if status.state.strip().upper() == ABORTED_STATE:
            why = " ".join(status.reason.split())[:120]
            return Leaving("aborted", f"aborted: {why}" if why else "aborted", status.updated_at)
    elif status is not None and status.mission_id is not None:
        return Leaving("moved", f"now in mission {status.mission_id}", status.updated_at)
    seen = status.updated_at if status is not None else last_seen
    if now - seen > dropout_s:
        return Leaving("silent", f"silent for {now - seen:.0f} s (over {dropout_s:g} s)", seen)
    return None


def _opened(geometry: BaseGeometry, width_m: float) -> BaseGeometry:
    if geometry.is_empty or width_m <= 0:
        return geometry
    return geometry.buffer(-width_m, join_style="mitre").buffer(width_m, join_style="mitre")


def unflown_part(
    part: Sequence[Sequence[float]],
    covered: Sequence[Sequence[Sequence[Sequence[float]]]],
    sliver_m: float = SLIVER_M,
    min_piece_m2: float = MIN_PIECE_M2,
    max_rings: int = MAX_RINGS,
    max_vertices: int = MAX_VERTICES,
) -> Unflown:
    """The vehicle's `part` ([lat, lon] corners) less every vehicle's `covered` rings (each vehicle's list of
    [lat, lon] rings, as statuses report them): see the module doc. Empty for a part of fewer than 3 corners."""
    return unflown_parts([part], covered, sliver_m, min_piece_m2, max_rings, max_vertices)[0]


def unflown_parts(
    parts: Sequence[Sequence[Sequence[float]]],
    covered: Sequence[Sequence[Sequence[Sequence[float]]]],
    sliver_m: float = SLIVER_M,
    min_piece_m2: float = MIN_PIECE_M2,
    max_rings: int = MAX_RINGS,
    max_vertices: int = MAX_VERTICES,
) -> list[Unflown]:
    """`unflown_part` of each of `parts`, the covered rings merged once (in one local frame: a mission's
    parts lie within a few km)."""
    corners = [p for p in parts if len(p) >= 3]
    if not corners:
        return [Unflown([], 0.0) for _ in parts]
    frame = LocalFrame(float(corners[0][0][0]), float(corners[0][0][1]))
    reach = _bounds([q for p in corners for q in p])
    seen = [
        shapely.make_valid(_metres(geometry_from_rings(rings), frame))
        for rings in covered
        if rings and _meet(_bounds([q for ring in rings for q in ring]), reach)
    ]  # only what may meet a part is put in metres (a fleet of 50 reports 50 covered areas)
    tree = shapely.STRtree(seen)  # a part meets the covered areas of a few vehicles: its own, its neighbours'
    return [
        _unflown(part, seen, tree, frame, sliver_m, min_piece_m2, max_rings, max_vertices)
        if len(part) >= 3
        else Unflown([], 0.0)
        for part in parts
    ]


def _bounds(points: Sequence[Sequence[float]]) -> tuple[float, float, float, float]:
    lats = [float(p[0]) for p in points]
    lons = [float(p[1]) for p in points]
    return min(lats), min(lons), max(lats), max(lons)


def _meet(a: tuple[float, float, float, float], b: tuple[float, float, float, float]) -> bool:
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def _unflown(
    part: Sequence[Sequence[float]],
    seen: Sequence[BaseGeometry],
    tree: shapely.STRtree,
    frame: LocalFrame,
    sliver_m: float,
    min_piece_m2: float,
    max_rings: int,
    max_vertices: int,
) -> Unflown:
    area = shapely.make_valid(Polygon([frame.xy(float(lat), float(lon)) for lat, lon in part]))
    near = [seen[int(i)] for i in tree.query(area)]
    left = area.difference(shapely.union_all(near)) if near else area
    left = _opened(left, sliver_m).intersection(area)
    pieces = [p for p in getattr(left, "geoms", [left]) if isinstance(p, Polygon) and p.area >= min_piece_m2]
    kept = shapely.union_all(pieces) if pieces else Polygon()
    if kept.is_empty:
        return Unflown([], 0.0)
    return Unflown(bounded_rings(kept, frame, max_rings, max_vertices), round(float(kept.area), 1))
