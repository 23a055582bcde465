"""Issue 43 item 4: a mission flown by two vehicles downloads as one picture. The GeoJSON (read with json)
and the KML (read with a strict XML parser: lxml without recovery, and expat) hold each vehicle's part (the
search area it reported) and its track, each named with its vehicle id and drawn in its own colour."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from lxml import etree

from backend.app import create_app
from cloudtrack.vehicle_colours import kml_colour
from tests.backend_fixtures import SUPERVISOR, auth, backend_config

MISSION = "m-43"
# The area split in two: drone-1 flies the western part, drone-2 the eastern (as sent: clockwise).
PARTS = {
    "drone-1": [[47.3970, 8.5450], [47.3985, 8.5450], [47.3985, 8.5460], [47.3970, 8.5460]],
    "drone-2": [[47.3970, 8.5460], [47.3985, 8.5460], [47.3985, 8.5470], [47.3970, 8.5470]],
}
KML = "{http://www.opengis.net/kml/2.2}"


@pytest.fixture
def client(models_dir: Path) -> Iterator[TestClient]:
    with TestClient(create_app(backend_config(models_dir))) as running:
        yield running


def _fly(client: TestClient) -> None:
    """Both vehicles report their part, a few positions along it and what they covered."""
    for i in range(4):
        for vehicle, part in PARTS.items():
            west = part[0][1]
            status = {
                "mission_id": MISSION,
                "state": "SEARCHING",
                "position": [47.3971 + i * 0.0003, west + 0.0005],
                "search": {
                    "area": part,
                    "coverage": 0.1 * i,
                    "covered": [[[47.3970, west], [47.3971 + 0.0003 * i, west], [47.3970, west + 0.0005]]],
                    "mode": "AUTO",
                },
            }
            answer = client.post(f"/v1/vehicles/{vehicle}/status", headers=auth(vehicle), json=status)
            assert answer.status_code == 200, answer.text[:300]


def _strict(data: bytes) -> Any:
    ET.fromstring(data)
    return etree.fromstring(data, etree.XMLParser(recover=False, resolve_entities=False, no_network=True))


def test_geojson_of_a_two_vehicle_mission_carries_each_part_and_track_by_id_and_colour(
    client: TestClient,
) -> None:
    _fly(client)
    answer = client.get(
        f"/v1/missions/{MISSION}/finds.geojson", headers={"Authorization": f"Bearer {SUPERVISOR}"}
    )
    assert answer.status_code == 200, answer.text[:300]
    document = json.loads(answer.text)
    assert document["type"] == "FeatureCollection"
    features: dict[tuple[str, str], dict[str, Any]] = {}
    for feature in document["features"]:
        props = feature["properties"]
        features[(props["vehicle_id"], props["kind"])] = feature
    colours = {}
    for vehicle, part in PARTS.items():
        track, area, covered = (features[(vehicle, k)] for k in ("track", "search_area", "covered"))
        assert track["geometry"]["type"] == "LineString" and len(track["geometry"]["coordinates"]) == 4
        assert track["properties"]["title"] == f"{vehicle} track"
        assert area["properties"]["title"] == f"{vehicle} search area"
        assert covered["properties"]["title"] == f"{vehicle} covered"
        # The part it reported, [lon, lat], closed.
        ring = area["geometry"]["coordinates"][0]
        assert sorted(map(tuple, ring[:-1])) == sorted((lon, lat) for lat, lon in part)
        colour = track["properties"]["stroke"]
        assert colour.startswith("#") and len(colour) == 7
        assert area["properties"]["stroke"] == area["properties"]["fill"] == colour
        assert covered["properties"]["fill"] == colour
        colours[vehicle] = colour
    assert colours["drone-1"] != colours["drone-2"]
    # The legend (a foreign member): each vehicle's colour by id.
    assert {v["vehicle_id"]: v["colour"] for v in document["vehicles"]} == colours
    assert all(v["colour_name"] and not v["colour_name"].startswith("#") for v in document["vehicles"])


def test_kml_of_a_two_vehicle_mission_carries_each_part_and_track_by_id_and_colour(
    client: TestClient,
) -> None:
    _fly(client)
    answer = client.get(
        f"/v1/missions/{MISSION}/finds.kml", headers={"Authorization": f"Bearer {SUPERVISOR}"}
    )
    assert answer.status_code == 200, answer.text[:300]
    document = _strict(answer.content)
    styles = {style.get("id"): style for style in document.iter(f"{KML}Style")}
    placemarks = {p.findtext(f"{KML}name"): p for p in document.iter(f"{KML}Placemark")}
    geojson = json.loads(
        client.get(
            f"/v1/missions/{MISSION}/finds.geojson", headers={"Authorization": f"Bearer {SUPERVISOR}"}
        ).text
    )
    stroke = {
        f["properties"]["vehicle_id"]: f["properties"]["stroke"]
        for f in geojson["features"]
        if f["properties"]["kind"] == "track"
    }
    line_colours = {}
    for vehicle, part in PARTS.items():
        track, area = placemarks[f"{vehicle} track"], placemarks[f"{vehicle} search area"]
        assert placemarks[f"{vehicle} covered 1"] is not None
        coordinates = (track.findtext(f"{KML}LineString/{KML}coordinates") or "").split()
        assert len(coordinates) == 4
        ring = (area.findtext(f".//{KML}outerBoundaryIs/{KML}LinearRing/{KML}coordinates") or "").split()
        assert sorted({tuple(float(v) for v in c.split(",")[:2]) for c in ring}) == sorted(
            (lon, lat) for lat, lon in part
        )
        for placemark, kind in ((track, "track"), (area, "search_area")):
            data = {d.get("name"): d.findtext(f"{KML}value") for d in placemark.iter(f"{KML}Data")}
            assert data["vehicle_id"] == vehicle and data["kind"] == kind and data["mission_id"] == MISSION
        colours = set()
        for placemark in (track, area):
            style = styles[(placemark.findtext(f"{KML}styleUrl") or "").lstrip("#")]
            colours.add(style.findtext(f"{KML}LineStyle/{KML}color"))
        (colour,) = colours  # the track and the part in one colour
        assert colour == kml_colour(stroke[vehicle])  # the GeoJSON's, as KML writes it
        line_colours[vehicle] = colour
    assert line_colours["drone-1"] != line_colours["drone-2"]
    legend = document.find(f"{KML}Document/{KML}description")
    assert legend is not None and "drone-1: " in (legend.text or "") and "drone-2: " in (legend.text or "")
    folders = [f.findtext(f"{KML}name") for f in document.iter(f"{KML}Folder")]
    assert f"drone-1 mission {MISSION}" in folders and f"drone-2 mission {MISSION}" in folders
