"""One mission of the fleet on one map: the maps of every vehicle searching the same mission id, merged.

Each vehicle reports its own search area (its part of the split), covered area and POD grid
(`cloudtrack.pod_map`); the mission's map is their union:

- the area is the union of the vehicles' areas, the covered area the union of what each covered, and the
  coverage the share of the area that any vehicle covered;
- the POD map is one north-up grid over every vehicle's grid, at most `MAX_CELLS` cells (no finer than
  the finest vehicle grid, coarser when the grids lie far apart): each mission cell takes from each
  vehicle's grid the cell under its centre, and the vehicles' looks combine as independent searches,
  POD = 1 - prod(1 - POD of each vehicle). A cell no vehicle's area holds is outside.

The grids' frames differ only by their origins: they are placed in the first one's local frame by
translation, as `cloudtrack.coverage.LocalFrame` is meant for (a few km). Pure functions; the caller
bounds how many maps it passes (`backend.sessions.MISSION_VEHICLES`).
"""

from __future__ import annotations

import base64
import math
from collections.abc import Sequence

import numpy as np
import shapely
from shapely.geometry import Polygon
from shapely.geometry.base import BaseGeometry

from backend.schemas import MergedMap, MissionMap, PodGrid
from cloudtrack.api_models import POD_CELL_M, POD_EXTENT_MAX_M
from cloudtrack.coverage import LocalFrame, bounded_rings, geometry_from_rings
from cloudtrack.pod_map import MAX_CELLS, OUTSIDE, SCALE, decode_grid

MAX_RINGS = 20
MAX_VERTICES = 500


def merged_pod(grids: Sequence[PodGrid], max_cells: int = MAX_CELLS) -> PodGrid | None:
    """The grids as one (see the module doc); None without a grid that decodes, or when the grids lie so far
    apart that no cell size the API allows spans them."""
    decoded: list[tuple[PodGrid, np.ndarray]] = []
    for grid in grids:
        try:
            decoded.append((grid, decode_grid(grid.model_dump())))
        except (ValueError, KeyError):
            continue  # a grid that does not decode says nothing of the mission
    if not decoded:
        return None
    frame = LocalFrame(*decoded[0][0].origin)
    placed = []
    for grid, values in decoded:
        x0, y0 = frame.xy(*grid.origin)
        placed.append((x0, y0, grid.cell_m, values))
    minx = min(x for x, _, _, _ in placed)
    miny = min(y for _, y, _, _ in placed)
    maxx = max(x + c * v.shape[1] for x, _, c, v in placed)
    maxy = max(y + c * v.shape[0] for _, y, c, v in placed)
    width, height = maxx - minx, maxy - miny
    cell = max(min(c for _, _, c, _ in placed), math.sqrt(width * height / max_cells))
    while math.ceil(width / cell - 1e-9) * math.ceil(height / cell - 1e-9) > max_cells:
        cell *= 1.01
    cols = max(1, math.ceil(width / cell - 1e-9))
    rows = max(1, math.ceil(height / cell - 1e-9))
    if cell > POD_CELL_M[1] or max(rows, cols) * cell > POD_EXTENT_MAX_M:
        return None
    xs = minx + (np.arange(cols) + 0.5) * cell
    ys = miny + (np.arange(rows) + 0.5) * cell
    cx, cy = np.meshgrid(xs, ys)  # [row, col]
    missed = np.ones((rows, cols))
    inside = np.zeros((rows, cols), dtype=bool)
    for x0, y0, c, values in placed:
        col = np.floor((cx - x0) / c).astype(np.int64)
        row = np.floor((cy - y0) / c).astype(np.int64)
        ok = (row >= 0) & (row < values.shape[0]) & (col >= 0) & (col < values.shape[1])
        pod = np.full((rows, cols), np.nan)
        pod[ok] = values[row[ok], col[ok]]
        there = ~np.isnan(pod)
        inside |= there
        missed[there] *= 1.0 - pod[there]
    cells = np.where(inside, np.rint((1.0 - missed) * SCALE), OUTSIDE).astype(np.uint8)
    pods = (1.0 - missed)[inside]
    first = decoded[0][0]
    return PodGrid(
        target=first.target,
        posture=first.posture,
        target_pod=first.target_pod,
        origin=list(frame.latlon(minx, miny)),
        cell_m=cell,
        rows=rows,
        cols=cols,
        values=base64.b64encode(cells.tobytes()).decode(),
        mean=round(float(pods.mean()), 4) if pods.size else 0.0,
        at_target=round(float((pods >= first.target_pod).mean()), 4) if pods.size else 0.0,
        looks=min(2**31, sum(grid.looks for grid, _ in decoded)),
        dark_looks=min(2**31, sum(grid.dark_looks for grid, _ in decoded)),
    )


def _metres(geometry: BaseGeometry, frame: LocalFrame) -> BaseGeometry:
    """A lon/lat geometry in `frame`'s metres (east, north): `frame.xy` on every vertex at once. Its offsets
    are linear in the degrees from the origin (the radii are the origin's), so one degree's metres scale them
    all (a point at a time in Python was a third of a 50-vehicle merge)."""
    east_per_deg = frame.xy(frame.lat, frame.lon + 1.0)[0]
    north_per_deg = frame.xy(frame.lat + 1.0, frame.lon)[1]
    origin = np.array([frame.lon, frame.lat])
    scale = np.array([east_per_deg, north_per_deg])
    return shapely.transform(geometry, lambda lonlat: (lonlat - origin) * scale)


def merge_key(vehicle: str, mission_map: MissionMap) -> tuple[object, ...]:
    """What of a vehicle's map its mission's merged map depends on (its track does not): cheap to compare."""
    pod = mission_map.pod
    covered = mission_map.covered
    return (
        vehicle,
        mission_map.area_since,
        len(mission_map.area),
        mission_map.area[0] if mission_map.area else None,
        mission_map.coverage,
        sum(len(r) for r in covered),
        covered[-1][-1] if covered and covered[-1] else None,
        (pod.looks, pod.values, pod.origin) if pod is not None else None,
    )


def merged_map(mission_id: str, maps: Sequence[tuple[str, MissionMap]], now: float) -> MergedMap:
    """The mission's map from each vehicle's (vehicle id, its map of the mission): see the module doc."""
    corners = [m.area[0] for _, m in maps if len(m.area) >= 3]
    pod = merged_pod([m.pod for _, m in maps if m.pod is not None])
    if not corners:
        return MergedMap(mission_id=mission_id, vehicles=[v for v, _ in maps], pod=pod, updated_at=now)
    frame = LocalFrame(float(corners[0][0]), float(corners[0][1]))
    areas = [
        shapely.make_valid(Polygon([frame.xy(float(lat), float(lon)) for lat, lon in m.area]))
        for _, m in maps
        if len(m.area) >= 3
    ]
    area = shapely.union_all(areas)
    covered = shapely.union_all(
        [shapely.make_valid(_metres(geometry_from_rings(m.covered), frame)) for _, m in maps if m.covered]
    )
    coverage = float(min(1.0, covered.intersection(area).area / area.area)) if area.area > 0 else None
    return MergedMap(
        mission_id=mission_id,
        vehicles=[v for v, _ in maps],
        area=bounded_rings(area, frame, MAX_RINGS, MAX_VERTICES),
        covered=bounded_rings(covered.intersection(area), frame, MAX_RINGS, MAX_VERTICES),
        coverage=coverage,
        pod=pod,
        updated_at=now,
    )
