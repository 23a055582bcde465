"""A search area's POD map as the rescuers' tools and the supervisor page draw it: one polygon per POD band
(`cloudtrack.pod_map.BANDS`, from the grid a vehicle reported), each with its band's colour and values.

GeoJSON features carry `pod` (the band's lower bound), `pod_max`, the target and the target POD, plus the
simplestyle keys (`fill`, `stroke`, `title`) CalTopo / SARTopo and geojson.io colour them by; QGIS styles
by `pod`. KML placemarks carry the same values as ExtendedData, styled by band, in a folder of their own
(Google Earth, CalTopo, QGIS, ATAK). Places nobody analysed (POD 0) and places outside the area are in no
polygon: blank on every map, never "searched".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any
from xml.sax.saxutils import escape

import numpy as np
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.base import BaseGeometry
from shapely.geometry.polygon import orient

from cloudtrack.api_models import PodGrid
from cloudtrack.pod_map import BANDS, pod_bands

# One colour per band, low POD to high: viridis reversed (colour-blind safe, even steps in lightness), so
# the darker a place, the more thoroughly it was searched. The page's legend shows the same.
BAND_COLOURS: tuple[str, ...] = ("#fde725", "#7ad151", "#22a884", "#2a788e", "#414487", "#440154")
FILL_OPACITY = 0.55
MEANING = (
    "POD (probability of detection): the chance the search would have found the {target} here had they been "
    "there; blank = not analysed"
)
DIGITS = 7  # about 1 cm: far below a cell


@dataclass(frozen=True)
class PodLayer:
    """One band of an area's POD map: the places whose POD is in [low, high), in longitude / latitude."""

    low: float
    high: float
    colour: str
    geometry: BaseGeometry

    @property
    def label(self) -> str:
        return f"POD {self.low * 100:.0f}-{self.high * 100:.0f} %"


def band_colour(low: float) -> str:
    return BAND_COLOURS[[b[0] for b in BANDS].index(low)]


def pod_layers(grid: PodGrid) -> list[PodLayer]:
    """The grid's bands that hold a place, lowest first (CPU work: call it off the event loop)."""
    return [PodLayer(low, high, band_colour(low), shape) for low, high, shape in pod_bands(grid.model_dump())]


def _words(text: str) -> str:
    """A vehicle's class or posture name for a sentence: letters, digits, spaces and hyphens only (KML readers
    render a description as HTML, and simplekml passes CDATA in one through unescaped)."""
    return "".join(ch if ch.isalnum() or ch in " -" else "?" for ch in text)


def meaning(grid: PodGrid) -> str:
    return MEANING.format(target=_words(f"{grid.posture} {grid.target}"))


def _polygons(geometry: BaseGeometry) -> list[Polygon]:
    """Counter-clockwise exteriors and clockwise holes (RFC 7946 section 3.1.6; KML's order too)."""
    parts = geometry.geoms if isinstance(geometry, MultiPolygon) else [geometry]
    return [orient(p, 1.0) for p in parts if isinstance(p, Polygon) and not p.is_empty]


def _ring(coords: Any) -> list[list[float]]:
    rounded: list[list[float]] = np.round(np.asarray(coords), DIGITS).tolist()
    return rounded


def layer_properties(grid: PodGrid, layer: PodLayer) -> dict[str, Any]:
    return {
        "kind": "pod",
        "pod": layer.low,
        "pod_max": layer.high,
        "target": grid.target,
        "posture": grid.posture,
        "target_pod": grid.target_pod,
        "area_mean_pod": grid.mean,
        "area_at_target": grid.at_target,
    }


def geojson_features(grid: PodGrid, owner: dict[str, Any]) -> list[dict[str, Any]]:
    """One Polygon / MultiPolygon feature per band; `owner` (vehicle, mission, which area) in each."""
    features = []
    for layer in pod_layers(grid):
        polygons = [
            [_ring(p.exterior.coords), *(_ring(r.coords) for r in p.interiors)]
            for p in _polygons(layer.geometry)
        ]
        geometry = (
            {"type": "Polygon", "coordinates": polygons[0]}
            if len(polygons) == 1
            else {"type": "MultiPolygon", "coordinates": polygons}
        )
        style = {
            "title": layer.label,
            "description": meaning(grid),
            "fill": layer.colour,
            "fill-opacity": FILL_OPACITY,
            "stroke": layer.colour,
            "stroke-width": 0,
        }
        features.append(
            {
                "type": "Feature",
                "geometry": geometry,
                "properties": {**layer_properties(grid, layer), **owner, **style},
            }
        )
    return features


def _kml_colour(hex_rgb: str, opacity: float) -> str:
    """'#rrggbb' as KML's aabbggrr."""
    r, g, b = hex_rgb[1:3], hex_rgb[3:5], hex_rgb[5:7]
    return f"{round(opacity * 255):02x}{b}{g}{r}"


def kml_folder(parent: Any, name: str, grid: PodGrid, owner: dict[str, Any]) -> None:
    """A folder `name` in `parent` (a simplekml Kml or Folder): one placemark per band, filled with the
    band's colour, its values (and `owner`'s) as ExtendedData."""
    folder = parent.newfolder(name=name)
    folder.description = meaning(grid)
    for layer in pod_layers(grid):
        placemark = folder.newmultigeometry(name=layer.label)
        placemark.description = meaning(grid)
        for polygon in _polygons(layer.geometry):
            placemark.newpolygon(
                outerboundaryis=_ring(polygon.exterior.coords),
                innerboundaryis=[_ring(r.coords) for r in polygon.interiors],
            )
        placemark.style.polystyle.color = _kml_colour(layer.colour, FILL_OPACITY)
        placemark.style.polystyle.outline = 0
        placemark.style.linestyle.color = _kml_colour(layer.colour, 1.0)
        for key, value in {**layer_properties(grid, layer), **owner}.items():
            # simplekml writes a Data value as given: escaped here, read back as sent.
            placemark.extendeddata.newdata(name=key, value=escape("" if value is None else str(value)))
