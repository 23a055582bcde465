"""A mission's finds for the rescuers: GeoJSON and KML downloads with the track, the searched areas and their
POD maps.

  GET /v1/missions/{m}/finds.geojson?vehicle_id=V     application/geo+json
  GET /v1/missions/{m}/finds.kml?vehicle_id=V         application/vnd.google-earth.kml+xml

Supervisor token. Missions belong to a vehicle (MAVLink mission ids are 0-255 and meet by accident):
without `vehicle_id` the document holds every vehicle that flew a mission of that id, each feature
naming its vehicle.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated

from fastapi import APIRouter, HTTPException, Query, status
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from backend.dependencies import MissionId, Sessions, SupervisorCaller
from backend.find_export import geojson_text, kml_text
from backend.schemas import ERROR_RESPONSES, IDENTIFIER, MissionMap, StoredFind
from backend.sessions import SessionStore

router = APIRouter(prefix="/v1/missions/{mission_id}", tags=["finds"])

VehicleQuery = Annotated[
    str | None,
    Query(pattern=IDENTIFIER, description="whose mission; default: every vehicle that flew one of this id"),
]


def _gather(
    sessions: SessionStore, mission_id: str, vehicle_id: str | None
) -> tuple[list[StoredFind], dict[tuple[str, str], MissionMap]]:
    vehicles = [vehicle_id] if vehicle_id else sorted({s.vehicle_id for s in sessions.statuses()})
    finds: list[StoredFind] = []
    maps: dict[tuple[str, str], MissionMap] = {}
    for vehicle in vehicles:
        finds.extend(sessions.finds(vehicle, mission_id))
        mission_map = sessions.mission_map(vehicle, mission_id)
        if mission_map is not None:
            maps[(vehicle, mission_id)] = mission_map
    if not finds and not maps:
        who = f"vehicle {vehicle_id!r}" if vehicle_id else "any vehicle"
        raise HTTPException(status.HTTP_404_NOT_FOUND, f"no mission {mission_id!r} of {who} is known here")
    return sorted(finds, key=lambda f: f.time), maps


def _document(
    render: Callable[[list[StoredFind], dict[tuple[str, str], MissionMap], str], str],
    sessions: SessionStore,
    mission_id: str,
    vehicle_id: str | None,
) -> str:
    """The download's text, on a worker thread: the POD map's polygons take a while to build (docs/backend.md
    gives the time for a full grid)."""
    finds, maps = _gather(sessions, mission_id, vehicle_id)
    return render(finds, maps, f"CloudTrack mission {mission_id}")


def _download(body: str, media_type: str, name: str) -> Response:
    headers = {"Content-Disposition": f'attachment; filename="{name}"', "Cache-Control": "no-store"}
    return Response(body, media_type=media_type, headers=headers)


@router.get(
    "/finds.geojson",
    responses={**ERROR_RESPONSES, 200: {"content": {"application/geo+json": {}}}},
    response_class=Response,
)
async def finds_geojson(
    mission_id: MissionId, _: SupervisorCaller, sessions: Sessions, vehicle_id: VehicleQuery = None
) -> Response:
    """The mission's finds (points), the drone's track (a line) and the search and covered areas (polygons)."""
    body = await run_in_threadpool(_document, geojson_text, sessions, mission_id, vehicle_id)
    return _download(body, "application/geo+json", f"{mission_id}-finds.geojson")


@router.get(
    "/finds.kml",
    responses={**ERROR_RESPONSES, 200: {"content": {"application/vnd.google-earth.kml+xml": {}}}},
    response_class=Response,
)
async def finds_kml(
    mission_id: MissionId, _: SupervisorCaller, sessions: Sessions, vehicle_id: VehicleQuery = None
) -> Response:
    """The same as KML (Google Earth, ATAK, QGIS, Mission Planner)."""
    body = await run_in_threadpool(_document, kml_text, sessions, mission_id, vehicle_id)
    return _download(body, "application/vnd.google-earth.kml+xml", f"{mission_id}-finds.kml")
