"""The probability-of-detection (POD) map of a search area: per place, the chance that the search would have
found the described target there, from the keyframes the back-end actually analysed.

The area is cut into a grid of square cells (north-up, at most `MAX_CELLS`, no finer than `MIN_CELL_M`): a
bounded size whatever the area, exact values at every place, cheap to update per keyframe with numpy and
to send (one byte a cell). Polygons for the rescuers' tools are made from it where they are needed
(`pod_bands`: the back-end's GeoJSON / KML), not carried in every status.

A look is one analysed keyframe: for every cell its camera saw (the cell's centre inside the image and
within `search_range_m` of the vehicle), the target's size there (`behaviors.apparent_size`) gives the
detection curve's probability p (`behaviors.detection_curve`). Looks at a place during one pass are not
independent (the same person, pose and light a fraction of a second apart: a miss at one size is a miss at
that size again), so a pass counts its best look; a pass ends when the place has not been looked at for
`pass_gap_s`, and passes combine as independent looks: POD = 1 - prod(1 - best of each pass). A keyframe
that was not analysed adds nothing; a place nobody analysed stays at 0. A keyframe analysed late (kept
through a back-end outage, sent newest first) joins the pass of the place's latest look when it is older
than that: at worst two passes count as one, never one as two.

`report()` is the status report's `search.pod` (CONTRACT with `cloudtrack.api_models.PodGrid`): the grid's
south-west corner, cell size, rows (south to north) and columns (west to east), and the values as base64 of
one byte a cell, row by row from the south-west, `round(pod * 250)`, `OUTSIDE` (255) outside the area.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import shapely
import shapely.affinity
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.base import BaseGeometry

from behaviors.apparent_size import TargetShape, camera_frame
from behaviors.camera_model import CameraModel
from behaviors.detection_curve import DetectionCurve
from cloudtrack.coverage import LatLon, LocalFrame

MAX_CELLS = 4096
MIN_CELL_M = 2.0
PASS_GAP_S = 10.0  # a place unseen this long: the next look starts a new, independent pass
OUTSIDE = 255
SCALE = 250  # byte value of POD 1.0
# The bands the exports and the page draw: [low, high) except the last; a place at POD 0 is in none.
BANDS: tuple[tuple[float, float], ...] = (
    (0.0, 0.2),
    (0.2, 0.4),
    (0.4, 0.6),
    (0.6, 0.8),
    (0.8, 0.9),
    (0.9, 1.0),
)


@dataclass(frozen=True)
class PodSettings:
    """What the map is for: the target class and shape, what counts as found, the target POD the operator
    plans for, and the keyframes' width (the curve is in keyframe pixels)."""

    target_class: str = "person"
    posture: str = "standing"
    shape: TargetShape = TargetShape.person("standing")
    accept_uncertain: bool = False
    target_pod: float = 0.8
    keyframe_width: int = 640
    pass_gap_s: float = PASS_GAP_S


def sizes_px(
    camera: CameraModel,
    height_m: float,
    north: np.ndarray,
    east: np.ndarray,
    shape: TargetShape,
    roll: float = 0.0,
    pitch: float = 0.0,
    yaw: float = 0.0,
    keyframe_width: int = 640,
) -> np.ndarray:
    """`behaviors.apparent_size.apparent_size_px` for many places at once (numpy; tests hold them equal)."""
    project: Any = camera_frame  # its arithmetic is numpy's on arrays

    north = np.asarray(north, np.float64)
    east = np.asarray(east, np.float64)
    bearing = np.arctan2(east, north)
    cb, sb = np.cos(bearing), np.sin(bearing)
    total = np.zeros_like(north)
    seen = np.ones_like(north, dtype=bool)  # the whole target in the image, both ways round
    for along in (True, False):
        half_l, half_w = shape.length_m / 2, shape.width_m / 2
        if not along:
            half_l, half_w = half_w, half_l
        us, vs = [], []
        for dl in (-half_l, half_l):
            for dw in (-half_w, half_w):
                n = north + dl * cb - dw * sb
                e = east + dl * sb + dw * cb
                for up in (0.0, shape.height_m):
                    cf, cr, cd = project(camera, n, e, np.full_like(n, height_m - up), roll, pitch, yaw)
                    cf = np.asarray(cf)
                    seen &= cf > 1e-6
                    safe_f = np.where(cf > 1e-6, cf, 1.0)
                    us.append(camera.cx + camera.fx * np.asarray(cr) / safe_f)
                    vs.append(camera.cy + camera.fy * np.asarray(cd) / safe_f)
        u0, u1 = np.min(us, axis=0), np.max(us, axis=0)
        v0, v1 = np.min(vs, axis=0), np.max(vs, axis=0)
        seen &= (u0 >= 0) & (u1 < camera.width) & (v0 >= 0) & (v1 < camera.height)
        total += np.sqrt(np.maximum((u1 - u0) * (v1 - v0), 0.0))
    scale = min(1.0, keyframe_width / camera.width)
    return np.where(seen, scale * total / 2, 0.0)


def curve_probabilities(curve: DetectionCurve, sizes: np.ndarray, accept_uncertain: bool) -> np.ndarray:
    """`curve.probability` for many sizes at once."""
    fit = curve.fit(accept_uncertain)
    if fit is None:
        return np.zeros_like(sizes, dtype=np.float64)
    z = fit.intercept + fit.slope * np.log(np.maximum(sizes, 1e-9))
    return np.where(sizes >= fit.min_size_px, 1.0 / (1.0 + np.exp(-np.clip(z, -700, 700))), 0.0)


class PodMap:
    """One search area's POD grid, grown look by look. Not thread-safe (one owner)."""

    def __init__(
        self,
        area: Sequence[LatLon],
        camera: CameraModel,
        search_range_m: float,
        curve: DetectionCurve,
        settings: PodSettings = PodSettings(),
        max_cells: int = MAX_CELLS,
        min_cell_m: float = MIN_CELL_M,
    ) -> None:
        if len(area) < 3:
            raise ValueError("a search area needs at least 3 corners")
        self.area_corners = tuple((float(lat), float(lon)) for lat, lon in area)
        frame = LocalFrame(area[0][0], area[0][1])
        polygon = shapely.make_valid(frame.polygon(area))
        if polygon.area <= 0:
            raise ValueError("the search area has no area")
        minx, miny, maxx, maxy = polygon.bounds
        cell = max(min_cell_m, math.sqrt((maxx - minx) * (maxy - miny) / max_cells))
        while math.ceil((maxx - minx) / cell) * math.ceil((maxy - miny) / cell) > max_cells:
            cell *= 1.01
        self.cell_m = cell
        self.cols = max(1, math.ceil((maxx - minx) / cell))
        self.rows = max(1, math.ceil((maxy - miny) / cell))
        self.origin = frame.latlon(minx, miny)  # the grid's south-west corner
        self.frame = LocalFrame(*self.origin)
        # Cell centres in the grid's own frame (metres east / north of its south-west corner).
        xs = (np.arange(self.cols) + 0.5) * cell
        ys = (np.arange(self.rows) + 0.5) * cell
        self._x, self._y = np.meshgrid(xs, ys)  # [row, col]
        local = shapely.affinity.translate(polygon, -minx, -miny)
        self.inside = shapely.contains_xy(local, self._x, self._y)
        if not self.inside.any():  # a sliver thinner than a cell: the cells it touches
            self.inside = shapely.intersects_xy(local.buffer(cell / 2), self._x, self._y)
        self.camera = camera
        self.search_range_m = search_range_m
        self.curve = curve
        self.settings = settings
        self.looks = 0
        self._miss = np.ones((self.rows, self.cols))  # prod(1 - p) over the passes that have ended
        self._best = np.zeros((self.rows, self.cols))  # the best look of the pass under way
        self._last = np.full((self.rows, self.cols), -math.inf)  # when each cell was last looked at

    def add_look(
        self,
        lat: float,
        lon: float,
        height_m: float,
        yaw: float,
        time_s: float,
        roll: float = 0.0,
        pitch: float = 0.0,
    ) -> int:
        """One analysed keyframe, taken from this pose at `time_s`: the number of cells of the area it saw."""
        if not all(math.isfinite(v) for v in (lat, lon, height_m, yaw, time_s, roll, pitch)) or height_m <= 0:
            return 0
        x0, y0 = self.frame.xy(lat, lon)
        reach = self.search_range_m + self.cell_m
        c0, c1 = max(0, int((x0 - reach) / self.cell_m)), min(self.cols, int((x0 + reach) / self.cell_m) + 1)
        r0, r1 = max(0, int((y0 - reach) / self.cell_m)), min(self.rows, int((y0 + reach) / self.cell_m) + 1)
        if c0 >= c1 or r0 >= r1:
            return 0
        window = (slice(r0, r1), slice(c0, c1))
        east, north = self._x[window] - x0, self._y[window] - y0
        s = self.settings
        size = sizes_px(self.camera, height_m, north, east, s.shape, roll, pitch, yaw, s.keyframe_width)
        seen = (size > 0) & (np.hypot(north, east) <= self.search_range_m) & self.inside[window]
        if not seen.any():
            return 0
        p = curve_probabilities(self.curve, size, s.accept_uncertain)
        miss, best, last = self._miss[window], self._best[window], self._last[window]
        new_pass = seen & (time_s - last > s.pass_gap_s)
        miss[new_pass] *= 1.0 - best[new_pass]
        best[new_pass] = 0.0
        best[seen] = np.maximum(best[seen], p[seen])
        last[seen] = np.maximum(last[seen], time_s)
        self.looks += 1
        return int(seen.sum())

    def pod(self) -> np.ndarray:
        """POD per cell, [row (south to north), col (west to east)]; NaN outside the area."""
        values = 1.0 - self._miss * (1.0 - self._best)
        return np.where(self.inside, values, np.nan)

    def mean(self) -> float:
        return float(np.nanmean(self.pod()))

    def share_at_least(self, level: float) -> float:
        values = self.pod()[self.inside]
        return float(np.mean(values >= level - 1e-9)) if values.size else 0.0

    def pod_at(self, lat: float, lon: float) -> float | None:
        """POD of the cell at a place; None outside the area's grid."""
        return grid_value(self.report(), lat, lon)

    def report(self) -> dict[str, Any]:
        """The status report's `search.pod` (see the module doc)."""
        values = np.where(self.inside, np.rint(np.nan_to_num(self.pod()) * SCALE), OUTSIDE).astype(np.uint8)
        s = self.settings
        return {
            "target": s.target_class,
            "posture": s.posture,
            "target_pod": s.target_pod,
            "origin": [round(self.origin[0], 7), round(self.origin[1], 7)],
            "cell_m": round(self.cell_m, 3),
            "rows": self.rows,
            "cols": self.cols,
            "values": base64.b64encode(values.tobytes()).decode("ascii"),
            "mean": round(self.mean(), 4),
            "at_target": round(self.share_at_least(s.target_pod), 4),
            "looks": self.looks,
        }


def decode_grid(report: Mapping[str, Any]) -> np.ndarray:
    """A report's values as POD per cell [row, col], NaN outside the area; ValueError when malformed."""
    rows, cols = int(report["rows"]), int(report["cols"])
    if not (rows > 0 and cols > 0 and rows * cols <= MAX_CELLS):
        raise ValueError(f"a POD grid holds 1-{MAX_CELLS} cells")
    raw = base64.b64decode(str(report["values"]), validate=True)
    if len(raw) != rows * cols:
        raise ValueError(f"a POD grid of {rows} x {cols} needs {rows * cols} values, got {len(raw)}")
    cells = np.frombuffer(raw, np.uint8).reshape(rows, cols)
    if np.any((cells > SCALE) & (cells != OUTSIDE)):
        raise ValueError(f"POD values are 0-{SCALE}, or {OUTSIDE} outside the area")
    return np.where(cells == OUTSIDE, np.nan, cells / SCALE)


def grid_value(report: Mapping[str, Any], lat: float, lon: float) -> float | None:
    """The POD a report gives a place; None outside its grid or area."""
    grid = decode_grid(report)
    x, y = LocalFrame(*report["origin"]).xy(lat, lon)
    cell = float(report["cell_m"])
    col, row = math.floor(x / cell), math.floor(y / cell)
    if not (0 <= row < grid.shape[0] and 0 <= col < grid.shape[1]) or math.isnan(grid[row, col]):
        return None
    return float(grid[row, col])


def pod_bands(report: Mapping[str, Any]) -> list[tuple[float, float, BaseGeometry]]:
    """The map as polygons per POD band (`BANDS`), in longitude / latitude (x, y) as GeoJSON and KML want
    them: (low, high, geometry) for each band that holds a place; places at POD 0 are in none."""
    grid = decode_grid(report)
    frame = LocalFrame(*report["origin"])
    cell = float(report["cell_m"])
    out: list[tuple[float, float, BaseGeometry]] = []
    for i, (low, high) in enumerate(BANDS):
        last = i == len(BANDS) - 1
        with np.errstate(invalid="ignore"):
            mask = (grid > low if low == 0.0 else grid >= low) & ((grid <= high) if last else (grid < high))
        if not mask.any():
            continue
        rows, cols = np.nonzero(mask)
        # The cells share their edges exactly, so the coverage union merges them (a general union of a full
        # grid took seconds); simplify(0) drops the vertices left along straight edges.
        cells = shapely.box(cols * cell, rows * cell, (cols + 1) * cell, (rows + 1) * cell)
        merged = shapely.coverage_union_all(cells).simplify(0.0)
        out.append((low, high, _to_lonlat(merged, frame)))
    return out


def _to_lonlat(geometry: BaseGeometry, frame: LocalFrame) -> BaseGeometry:
    """Metres east / north of the frame's origin as longitude / latitude: `LocalFrame.latlon` is linear, so
    every vertex is mapped at once."""
    lat0, lon0 = frame.latlon(0.0, 0.0)
    span = 1000.0
    lat_per_m = (frame.latlon(0.0, span)[0] - lat0) / span
    lon_per_m = (frame.latlon(span, 0.0)[1] - lon0) / span
    lonlat = shapely.transform(
        geometry, lambda xy: np.column_stack([lon0 + xy[:, 0] * lon_per_m, lat0 + xy[:, 1] * lat_per_m])
    )
    parts = [lonlat] if isinstance(lonlat, Polygon) else list(getattr(lonlat, "geoms", ()))
    polygons = [p for p in parts if isinstance(p, Polygon) and not p.is_empty]
    return polygons[0] if len(polygons) == 1 else MultiPolygon(polygons)
