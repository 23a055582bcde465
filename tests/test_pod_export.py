"""The POD map reaches the rescuers' tools: a vehicle reports real `PodMap` grids through the API, for its
search area and, after its survey is replaced, for the new one; the mission's GeoJSON (read with json and
shapely) and KML (read with a real XML parser) hold one polygon per POD band for each area, with the
band's `pod` / `pod_max`, the target, the area it belongs to, and in KML the band's style. Every cell the
grid has is checked: its centre lies in the polygon of its band, and a place nobody analysed (POD 0) or
outside the area lies in none. Select: -k pod_export."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import geojson
import numpy as np
import pytest
import shapely
from fastapi.testclient import TestClient
from shapely.geometry import MultiPolygon, Polygon, shape
from shapely.geometry.base import BaseGeometry

from backend.app import create_app
from backend.pod_layers import BAND_COLOURS
from cloudtrack.coverage import LocalFrame
from cloudtrack.pod_map import BANDS, decode_grid
from tests.backend_fixtures import SUPERVISOR, auth, backend_config
from tests.pod_fixtures import AREA, NEXT_AREA, pod_report

KML = "{http://www.opengis.net/kml/2.2}"
Band = tuple[float, float]


@pytest.fixture(scope="module")
def flown(models_dir: Path) -> Iterator[tuple[TestClient, dict[str, Any], dict[str, Any]]]:
    """drone-1 searches AREA (two lanes), then its survey is replaced by NEXT_AREA (one lane so far)."""
    first, second = pod_report(AREA, lanes=2), pod_report(NEXT_AREA, lanes=1)
    with TestClient(create_app(backend_config(models_dir))) as client:
        for area, grid in ((AREA, first), (NEXT_AREA, second)):
            status = {
                "mission_id": "m-pod",
                "state": "SEARCHING",
                "position": area[0],
                "search": {"area": area, "coverage": 0.3, "pod": grid},
            }
            assert client.post("/v1/vehicles/drone-1/status", headers=auth(), json=status).status_code == 200
        yield client, first, second


def _download(client: TestClient, kind: str) -> str:
    response = client.get(
        f"/v1/missions/m-pod/finds.{kind}",
        params={"vehicle_id": "drone-1"},
        headers={"Authorization": f"Bearer {SUPERVISOR}"},
    )
    assert response.status_code == 200, response.text
    return response.text


def _assert_bands_match_the_grid(bands: dict[Band, BaseGeometry], report: dict[str, Any]) -> None:
    """Each cell's centre in exactly the polygon of its band; POD 0 and outside the area in none; each
    band's area that of its cells."""
    grid = decode_grid(report)
    frame = LocalFrame(*report["origin"])
    cell = report["cell_m"]
    rows, cols = np.indices(grid.shape)
    centres = [
        frame.latlon((c + 0.5) * cell, (r + 0.5) * cell)
        for r, c in zip(rows.ravel(), cols.ravel(), strict=True)
    ]
    lat = np.array([p[0] for p in centres])
    lon = np.array([p[1] for p in centres])
    values = grid.ravel()
    assert np.any(values == 0) and np.any(np.isnan(values)) and np.any(values > 0)  # the test's grid has all
    holder = np.full(values.shape, -1)
    expected = set()
    for i, (low, high) in enumerate(BANDS):
        last = i == len(BANDS) - 1
        with np.errstate(invalid="ignore"):
            in_band = (values > low if low == 0 else values >= low) & (
                values <= high if last else values < high
            )
        if in_band.any():
            expected.add((low, high))
        geometry = bands.get((low, high))
        if geometry is None:
            continue
        inside = shapely.contains_xy(geometry, lon, lat)
        assert not np.any(inside & (holder >= 0)), "a place lies in two bands"
        holder[inside] = i
        assert np.array_equal(inside, in_band), (low, high)
        # Its area in metres is that of its cells (corners in the grid's frame).
        local = shapely.transform(geometry, lambda xy: np.array([frame.xy(y, x) for x, y in xy]))
        assert local.area == pytest.approx(in_band.sum() * cell * cell, rel=1e-3)
    assert set(bands) == expected
    with np.errstate(invalid="ignore"):
        assert np.all(holder[(values == 0) | np.isnan(values)] == -1)  # nobody looked: no POD claimed


def test_pod_export_geojson_holds_each_areas_pod_polygons(
    flown: tuple[TestClient, dict[str, Any], dict[str, Any]],
) -> None:
    client, first, second = flown
    text = _download(client, "geojson")
    assert geojson.loads(text).is_valid
    features = json.loads(text)["features"]
    areas = {f["properties"]["area"]: f for f in features if f["properties"]["kind"] == "search_area"}
    assert set(areas) == {"current", "earlier"}
    assert areas["current"]["geometry"]["coordinates"][0][0] in ([a[1], a[0]] for a in NEXT_AREA)
    assert areas["earlier"]["properties"]["replaced_at"].endswith("Z")
    for which, report in (("current", second), ("earlier", first)):
        pods = [f for f in features if f["properties"]["kind"] == "pod" and f["properties"]["area"] == which]
        bands: dict[Band, BaseGeometry] = {}
        for feature in pods:
            p = feature["properties"]
            assert (p["vehicle_id"], p["mission_id"], p["target"], p["posture"]) == (
                "drone-1", "m-pod", "person", "standing",
            )  # fmt: skip
            assert p["target_pod"] == report["target_pod"] and p["area_mean_pod"] == report["mean"]
            assert p["fill"] == BAND_COLOURS[[b[0] for b in BANDS].index(p["pod"])]
            geometry = shape(feature["geometry"])
            assert geometry.is_valid and feature["geometry"]["type"] in ("Polygon", "MultiPolygon")
            parts = geometry.geoms if isinstance(geometry, MultiPolygon) else [geometry]
            assert all(part.exterior.is_ccw for part in parts)  # RFC 7946
            bands[(p["pod"], p["pod_max"])] = geometry
        _assert_bands_match_the_grid(bands, report)


def _coordinates(ring: ET.Element) -> list[tuple[float, float]]:
    text = ring.findtext(f"{KML}LinearRing/{KML}coordinates") or ""
    return [(float(x), float(y)) for x, y, *_ in (point.split(",") for point in text.split())]


def test_pod_export_kml_holds_each_areas_pod_folder_styled_by_band(
    flown: tuple[TestClient, dict[str, Any], dict[str, Any]],
) -> None:
    client, first, second = flown
    root = ET.fromstring(_download(client, "kml"))
    styles = {s.get("id"): s for s in root.iter(f"{KML}Style")}
    folders = {f.findtext(f"{KML}name"): f for f in root.iter(f"{KML}Folder")}
    assert "POD map" in folders and "POD map, earlier area" in folders
    for name, report, which in (("POD map", second, "current"), ("POD map, earlier area", first, "earlier")):
        folder = folders[name]
        assert "blank = not analysed" in (folder.findtext(f"{KML}description") or "")
        bands: dict[Band, BaseGeometry] = {}
        fills = set()
        for placemark in folder.findall(f"{KML}Placemark"):
            data = {d.get("name"): d.findtext(f"{KML}value") for d in placemark.iter(f"{KML}Data")}
            assert (data["area"], data["target"], data["vehicle_id"]) == (which, "person", "drone-1")
            low, high = float(data["pod"] or "nan"), float(data["pod_max"] or "nan")
            assert placemark.findtext(f"{KML}name") == f"POD {low * 100:.0f}-{high * 100:.0f} %"
            style = styles[(placemark.findtext(f"{KML}styleUrl") or "").lstrip("#")]
            colour = style.findtext(f"{KML}PolyStyle/{KML}color") or ""
            rgb = BAND_COLOURS[[b[0] for b in BANDS].index(low)]
            assert colour[2:] == rgb[5:7] + rgb[3:5] + rgb[1:3] and int(colour[:2], 16) > 0  # aabbggrr
            fills.add(colour)
            polygons = [
                Polygon(
                    _coordinates(p.find(f"{KML}outerBoundaryIs")),  # type: ignore[arg-type]
                    [_coordinates(inner) for inner in p.findall(f"{KML}innerBoundaryIs")],
                )
                for p in placemark.iter(f"{KML}Polygon")
            ]
            assert polygons and all(p.is_valid for p in polygons)
            bands[(low, high)] = polygons[0] if len(polygons) == 1 else MultiPolygon(polygons)
        assert len(fills) == len(bands) > 1  # one colour a band
        _assert_bands_match_the_grid(bands, report)


def test_pod_export_a_hostile_target_name_is_text_in_both_documents(
    flown: tuple[TestClient, dict[str, Any], dict[str, Any]],
) -> None:
    client = flown[0]
    hostile = "<b>x</b> & <![CDATA[<script>]]>"
    status = {
        "mission_id": "m-hostile",
        "state": "SEARCHING",
        "search": {"area": AREA, "pod": {**pod_report(AREA, lanes=1), "target": hostile}},
    }
    assert client.post("/v1/vehicles/drone-1/status", headers=auth(), json=status).status_code == 200
    supervisor = {"Authorization": f"Bearer {SUPERVISOR}"}
    kml = client.get("/v1/missions/m-hostile/finds.kml", headers=supervisor)
    root = ET.fromstring(kml.text)  # well-formed
    targets = {d.findtext(f"{KML}value") for d in root.iter(f"{KML}Data") if d.get("name") == "target"}
    assert targets == {hostile}  # read back as sent
    descriptions = [d.text or "" for d in root.iter(f"{KML}description")]
    assert descriptions and not any("<" in d for d in descriptions)  # no markup for a reader to render
    features = client.get("/v1/missions/m-hostile/finds.geojson", headers=supervisor).json()["features"]
    assert {f["properties"]["target"] for f in features if f["properties"]["kind"] == "pod"} == {hostile}
