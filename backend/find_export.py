"""A mission's finds for the rescuers' own tools: GeoJSON (RFC 7946) and KML (simplekml), each with the finds
(points: time, when the position was seen, prompt, who confirmed it and through what, sigma), the drone's
track (a line), the search and covered areas (polygons) and the POD map (polygons per band,
`backend.pod_layers`), for the current search area and each earlier one of the mission (`area`: "current" /
"earlier"); and a find as the `cloudtrack.cursor_on_target.FindReport` a TAK map takes. Building them is CPU
work: off the event loop.

A mission flown by several vehicles holds every vehicle's part (the search area it reported) and track, each
named with its vehicle id and drawn in that vehicle's colour (`cloudtrack.vehicle_colours`): the GeoJSON
simplestyle keys (`title`, `stroke`, `fill`, ...) that CalTopo / SARTopo, geojson.io and QGIS draw by, and
a KML style per placemark. The id is always there, so nobody has to tell vehicles apart by colour alone.

GeoJSON positions are [lon, lat] and exterior rings run counter-clockwise (RFC 7946 section 3.1.6), so
strict readers accept them; a ring is closed here when the vehicle sent it open.

Text a vehicle or an operator wrote (the prompt, who confirmed, ids) is escaped where the KML is written,
whatever it holds: simplekml writes an ExtendedData value as given and passes a CDATA section in a
description through unescaped, and KML readers (Google Earth, CalTopo, ATAK) render a description as HTML.
So a Data value is XML-escaped (read back, it is the text as stored), a description is HTML-escaped before
simplekml XML-escapes it (the balloon shows the words, never an element or a link the vehicle wrote; an
address in it loses its `://`, which readers turn into a link), and each find's balloon shows its
description alone (`$[description]`), not the Data table. Control characters go in neither.
"""

from __future__ import annotations

import html
import json
import re
import threading
from datetime import datetime, timezone
from typing import Any
from xml.sax.saxutils import escape

import simplekml

from backend.pod_layers import geojson_features, kml_folder
from backend.schemas import EarlierArea, MissionMap, StoredFind
from cloudtrack.cursor_on_target import FindReport, seen_text
from cloudtrack.plain_text import without_controls
from cloudtrack.vehicle_colours import colour_name, kml_colour, vehicle_colours

# simplekml compiles through class-level state (Kmlable._compiling, _currentroot) and patches minidom while
# it pretty-prints: two downloads built at once on the thread pool would mix. One at a time.
_SIMPLEKML = threading.Lock()


def find_report(find: StoredFind) -> FindReport:
    return FindReport(
        candidate_id=find.candidate_id,
        lat=find.position[0],
        lon=find.position[1],
        sigma_m=find.sigma_m,
        time=find.time,
        prompt=find.prompt,
        confirmed_by=find.decided_by or find.confirmed_by,  # who and through what (backend.sessions)
        vehicle_id=find.vehicle_id,
        mission_id=find.mission_id,
        seen_at=find.seen_at,
    )


def _iso(unix: float) -> str:
    return datetime.fromtimestamp(unix, timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")


def _closed(ring: list[list[float]]) -> list[list[float]]:
    return ring if ring and ring[0] == ring[-1] else [*ring, ring[0]]


def _counter_clockwise(ring: list[list[float]]) -> list[list[float]]:
    """[lon, lat] ring, closed, counter-clockwise (shoelace sign)."""
    closed = _closed(ring)
    area = sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(closed, closed[1:], strict=False))
    return closed if area >= 0 else closed[::-1]


def _lon_lat(points: list[list[float]]) -> list[list[float]]:
    return [[p[1], p[0]] for p in points]


def searched_areas(mission_map: MissionMap) -> list[tuple[dict[str, Any], MissionMap | EarlierArea]]:
    """The mission's search areas, the current one first, each with the properties that say which it is."""
    areas: list[tuple[dict[str, Any], MissionMap | EarlierArea]] = [({"area": "current"}, mission_map)]
    for earlier in reversed(mission_map.earlier):
        areas.append(({"area": "earlier", "replaced_at": _iso(earlier.replaced_at)}, earlier))
    return areas


def find_properties(find: StoredFind) -> dict[str, Any]:
    return {
        "kind": "find",
        "vehicle_id": find.vehicle_id,
        "mission_id": find.mission_id,
        "candidate_id": find.candidate_id,
        "time": _iso(find.time),
        "seen_at": _iso(find.seen_at) if find.seen_at is not None else None,
        "prompt": find.prompt,
        "confirmed_by": find.confirmed_by,
        "decided_via": find.decided_via,
        "decided_by": find.decided_by,
        "sigma_m": find.sigma_m,
    }


def geojson_document(
    finds: list[StoredFind], maps: dict[tuple[str, str], MissionMap], title: str
) -> dict[str, Any]:
    """A FeatureCollection: one Point per find, and per (vehicle, mission) its track and areas."""
    features: list[dict[str, Any]] = [
        {
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": [f.position[1], f.position[0]]},
            "properties": {**find_properties(f), "title": _find_name(f)},
        }
        for f in finds
    ]
    colours = vehicle_colours(vehicle for vehicle, _ in maps)
    for (vehicle, mission), mission_map in maps.items():
        owner = {"vehicle_id": vehicle, "mission_id": mission}
        colour = colours[vehicle]
        if len(mission_map.track) >= 2:
            features.append(
                {
                    "type": "Feature",
                    "geometry": {"type": "LineString", "coordinates": _lon_lat(mission_map.track)},
                    "properties": {
                        "kind": "track",
                        **owner,
                        "start": _iso(mission_map.track[0][2]),
                        "end": _iso(mission_map.track[-1][2]),
                        **_track_style(vehicle, colour),
                    },
                }
            )
        for which, searched in searched_areas(mission_map):
            if len(searched.area) >= 3:
                features.append(
                    {
                        "type": "Feature",
                        "geometry": {
                            "type": "Polygon",
                            "coordinates": [_counter_clockwise(_lon_lat(searched.area))],
                        },
                        "properties": {
                            "kind": "search_area",
                            **owner,
                            **which,
                            **_area_style(vehicle, colour, which["area"] == "earlier"),
                        },
                    }
                )
            rings = [r for r in searched.covered if len(r) >= 3]
            if rings:
                features.append(
                    {
                        "type": "Feature",
                        "geometry": {
                            "type": "MultiPolygon",
                            "coordinates": [[_counter_clockwise(_lon_lat(r))] for r in rings],
                        },
                        "properties": {
                            "kind": "covered",
                            **owner,
                            **which,
                            "coverage": searched.coverage,
                            **_covered_style(vehicle, colour),
                        },
                    }
                )
            if searched.pod is not None:
                features.extend(geojson_features(searched.pod, {**owner, **which}))
    # A foreign member (RFC 7946 section 6.1), the legend: which colour is which vehicle.
    legend = [{"vehicle_id": v, "colour": c, "colour_name": colour_name(c)} for v, c in colours.items()]
    return {"type": "FeatureCollection", "name": title, "vehicles": legend, "features": features}


def _find_name(find: StoredFind) -> str:
    return f"FOUND {_iso(find.time)[11:16]} UTC ({find.vehicle_id})"


TRACK_WIDTH, AREA_WIDTH = 3, 2
AREA_FILL_OPACITY, COVERED_FILL_OPACITY = 0.08, 0.3


def _track_style(vehicle: str, colour: str) -> dict[str, Any]:
    return {"title": f"{vehicle} track", "stroke": colour, "stroke-width": TRACK_WIDTH, "stroke-opacity": 1}


def _area_style(vehicle: str, colour: str, earlier: bool) -> dict[str, Any]:
    return {
        "title": f"{vehicle} {'earlier search area' if earlier else 'search area'}",
        "stroke": colour,
        "stroke-width": AREA_WIDTH,
        "fill": colour,
        "fill-opacity": AREA_FILL_OPACITY,
    }


def _covered_style(vehicle: str, colour: str) -> dict[str, Any]:
    return {
        "title": f"{vehicle} covered",
        "stroke": colour,
        "stroke-width": 1,
        "fill": colour,
        "fill-opacity": COVERED_FILL_OPACITY,
    }


def geojson_text(finds: list[StoredFind], maps: dict[tuple[str, str], MissionMap], title: str) -> str:
    return json.dumps(geojson_document(finds, maps, title), indent=1)


def kml_data(value: object) -> str:
    """A Data value as simplekml must be given it: no control characters, XML-escaped (it writes it as is)."""
    return escape(without_controls("" if value is None else str(value)))


def balloon_text(lines: list[str]) -> str:
    """A description a KML reader shows as these lines of plain text (it renders descriptions as HTML):
    HTML-escaped (simplekml escapes it once more for the XML, and never meets a CDATA section in it), an
    address's `://` broken so that no reader links it, line breaks as <br>."""
    plain = [without_controls(line).replace("://", "[:]//") for line in lines]
    return "<br>".join(html.escape(line) for line in plain)


def kml_text(finds: list[StoredFind], maps: dict[tuple[str, str], MissionMap], title: str) -> str:
    """The same as a KML document (Google Earth, ATAK, QGIS, Mission Planner): folders of finds, tracks and
    areas."""
    with _SIMPLEKML:
        return _kml_text(finds, maps, title)


def _kml_text(finds: list[StoredFind], maps: dict[tuple[str, str], MissionMap], title: str) -> str:
    kml = simplekml.Kml(name=without_controls(title))
    colours = vehicle_colours(vehicle for vehicle, _ in maps)
    if colours:  # the legend: which colour is which vehicle
        kml.document.description = balloon_text([f"{v}: {colour_name(c)} ({c})" for v, c in colours.items()])
    folder = kml.newfolder(name="Finds")
    for find in finds:
        sigma = f"±{find.sigma_m:.1f} m" if find.sigma_m is not None else "accuracy unknown"
        point = folder.newpoint(
            name=without_controls(_find_name(find)),
            coords=[(find.position[1], find.position[0])],
            description=balloon_text(
                [
                    find.prompt,
                    f"confirmed by {find.decided_by or find.confirmed_by}; {sigma}",
                    seen_text(find.time, find.seen_at),
                    f"{find.vehicle_id}, mission {find.mission_id}, candidate {find.candidate_id}",
                ]
            ),
        )
        point.timestamp.when = _iso(find.time)
        point.style.iconstyle.color = simplekml.Color.red
        point.style.balloonstyle.text = "$[description]"  # the plain-text lines above, not the Data table
        for name, value in find_properties(find).items():
            point.extendeddata.newdata(name=name, value=kml_data(value))
    for (vehicle, mission), mission_map in maps.items():
        # Ids are identifiers (the API's pattern); the names go through the same cleaning as any text.
        sub = kml.newfolder(name=without_controls(f"{vehicle} mission {mission}"))
        colour = colours[vehicle]
        line_colour = kml_colour(colour)
        owner_data = {"vehicle_id": vehicle, "mission_id": mission, "colour": colour}
        if len(mission_map.track) >= 2:
            line = sub.newlinestring(
                name=without_controls(f"{vehicle} track"), coords=[(p[1], p[0]) for p in mission_map.track]
            )
            line.style.linestyle.width = TRACK_WIDTH
            line.style.linestyle.color = line_colour
            _kml_owner(line, {"kind": "track", **owner_data})
        for which, searched in searched_areas(mission_map):
            # The current area's placemarks in the mission's folder; each earlier one in a folder of its own.
            earlier = which["area"] == "earlier"
            place = sub.newfolder(name=f"earlier area, replaced {which['replaced_at']}") if earlier else sub
            if len(searched.area) >= 3:
                area = place.newpolygon(
                    name=without_controls(_area_style(vehicle, colour, earlier)["title"]),
                    outerboundaryis=_counter_clockwise(_lon_lat(searched.area)),
                )
                area.style.polystyle.fill = 0
                area.style.linestyle.color = line_colour
                area.style.linestyle.width = AREA_WIDTH
                _kml_owner(area, {"kind": "search_area", **owner_data, **which})
            for i, ring in enumerate(r for r in searched.covered if len(r) >= 3):
                covered = place.newpolygon(
                    name=without_controls(f"{vehicle} covered {i + 1}"),
                    outerboundaryis=_counter_clockwise(_lon_lat(ring)),
                )
                covered.style.polystyle.color = kml_colour(colour, round(COVERED_FILL_OPACITY * 255))
                covered.style.linestyle.color = line_colour
                _kml_owner(covered, {"kind": "covered", **owner_data, **which})
            if searched.pod is not None:
                owner = {"vehicle_id": vehicle, "mission_id": mission, **which}
                name = "POD map, earlier area" if earlier else "POD map"
                kml_folder(place, name, searched.pod, owner)
    return one_ring_per_inner_boundary(str(kml.kml()))


def _kml_owner(placemark: Any, values: dict[str, object]) -> None:
    """Whose placemark it is, as ExtendedData (QGIS and ATAK show and filter by it), escaped as a find's."""
    for name, value in values.items():
        placemark.extendeddata.newdata(name=name, value=kml_data(value))


_INNER = re.compile(r"<innerBoundaryIs>(.*?)</innerBoundaryIs>", re.S)
_RING = re.compile(r"<LinearRing\b.*?</LinearRing>", re.S)


def one_ring_per_inner_boundary(text: str) -> str:
    """simplekml writes a polygon's holes as several LinearRings in one innerBoundaryIs; KML 2.2 (OGC 07-147)
    gives each hole its own innerBoundaryIs, and readers that follow it (GDAL's, so QGIS) see only the first
    ring otherwise. Only simplekml's own geometry elements match: every text is escaped before."""
    return _INNER.sub(
        lambda m: "".join(f"<innerBoundaryIs>{ring}</innerBoundaryIs>" for ring in _RING.findall(m.group(1))),
        text,
    )
