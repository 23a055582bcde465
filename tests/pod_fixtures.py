"""A real POD map for the back-end's tests: `cloudtrack.pod_map.PodMap` over a small search area, laid from
analysed keyframes of a survey that flew part of it (some places seen once, some twice, the rest never)."""

from __future__ import annotations

from typing import Any

from behaviors.camera_model import CameraModel
from cloudtrack.detection_curves import curve_for
from cloudtrack.pod_map import PodMap

HOME = (47.3977, 8.5456)
# A 150 x 110 m area, corners [lat, lon], clockwise as a vehicle sends them.
AREA = [[47.3970, 8.5450], [47.3970, 8.5470], [47.3980, 8.5470], [47.3980, 8.5450]]
# The area the mission is replaced by: 100 m farther north.
NEXT_AREA = [[47.3989, 8.5450], [47.3989, 8.5470], [47.3999, 8.5470], [47.3999, 8.5450]]


def pod_map(area: list[list[float]] = AREA, lanes: int = 2, max_cells: int = 4096) -> PodMap:
    """The area's POD map after a survey of its western `lanes` lanes (15 m apart, north then south, 25 m up,
    a keyframe every 6 m), and a second pass lower down over the first lane a minute later."""
    camera = CameraModel.from_hfov(640, 480, 70.0, mount_pitch_deg=-90.0)
    grid = PodMap([(a[0], a[1]) for a in area], camera, 60.0, curve_for("person"), max_cells=max_cells)
    south, west = min(a[0] for a in area), min(a[1] for a in area)
    north = max(a[0] for a in area)
    time_s = 0.0
    for lane in range(lanes):
        lon = west + 0.0001 + lane * 0.0002
        steps = 20
        for i in range(steps + 1):
            f = i / steps if lane % 2 == 0 else 1 - i / steps
            grid.add_look(south + f * (north - south), lon, 25.0, 0.0, time_s)
            time_s += 1.0
    time_s += 60.0
    for i in range(21):
        grid.add_look(south + i / 20 * (north - south), west + 0.0001, 15.0, 0.0, time_s)
        time_s += 1.0
    return grid


def pod_report(area: list[list[float]] = AREA, lanes: int = 2, max_cells: int = 4096) -> dict[str, Any]:
    return pod_map(area, lanes, max_cells).report()
