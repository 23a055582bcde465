"""`cloudtrack-backend bench --fleet-map N [N ...]`: one mission searched by N vehicles, what its merged map and
the supervisor page's state cost the back-end (issue 43, "Scale").

For each fleet size a fresh `cloudtrack-backend serve` on loopback (the SQLite store on disk by default, or
Debian's redis-server with `--fleet-store redis`), then N simulated vehicles, all searching ONE mission id,
each the companion's way at its default rates:

- every `[backend] status_interval_s` (1 s) a status report (`POST /v1/vehicles/{v}/status`) and a poll of
  its decisions (`GET .../decisions?after=N`), as `companion.cloud.backend_session` does each round;
- the report carries what the companion reports while searching: state, prompt, position, altitude,
  heading, progress, keyframe counts and `search` (area, coverage, covered area, POD grid), the maps laid
  from an analysed keyframe every `[backend] search_interval_s` (0.5 s) by the companion's own classes
  (`cloudtrack.coverage.CoverageMap`, `cloudtrack.pod_map.PodMap`: default camera, 50 m search range, the
  shipped person curve) along a survey of the vehicle's part planned by `behaviors.survey_planner`.

The shared area is a row of equal strips, one per vehicle (each its own part of the split, as
`cloudtrack-gcs survey` deals them out), the maps `warm_s` into the flight when the measured window starts
(so the covered area and the POD grid have their in-flight size), growing through the window. One strip's
flight is computed and shifted east for each vehicle (the strips are equal, so their maps are too).
No keyframes go to `/v1/detect`: what keyframes cost a fleet is `bench --capacity`; here the detector never
runs, and the figures are the map's and the page's.

Meanwhile a supervisor, as the page and a GCS would: one open `/supervisor/events` stream (the page's live
state: its bytes and events counted), and every `poll_s` `GET /supervisor/api/state` (the snapshot the page
loads, also the stream's `state` event) and `GET /v1/missions/{m}/map` (the merged map as kept: merged at
most once per `[fleet] merge_period_s`, off the requests; its `age_s` and the merges its `as_of` shows are
printed). Printed per fleet size: p50/p95 and bytes of both, the status report's p50/p95 (what one vehicle
waits while the fleet reports), the server's RSS and CPU, its merge worker's apart (`backend.merge_worker`),
the CPU of one merge, and 50 vs 1 ratios.
The end checks that every vehicle is on the merged map. Timings are printed, never asserted.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import requests

from backend.mission_map import updated_map
from backend.mission_merge import merged_map
from backend_tools.fleet_bench import SUPERVISOR_TOKEN, fleet_tokens
from backend_tools.fleet_services import BackendProcess, RedisServer
from behaviors.apparent_size import TargetShape
from behaviors.camera_model import CameraModel
from behaviors.survey_planner import SurveySettings, plan_survey
from cloudtrack.api_models import VehicleStatusIn
from cloudtrack.coverage import CoverageMap, LocalFrame
from cloudtrack.detection_curves import curve_for
from cloudtrack.model_store import ModelError, require
from cloudtrack.pod_map import PodMap, PodSettings
from cloudtrack.survey_pod import keyframe_poses

MISSION_ID = "fleet-map"
FINAL_WAIT_S = 30.0  # the end waits at most this for a merge holding every vehicle
PROMPT = "an injured man in a gray shirt"
ORIGIN = (47.3970, 8.5440)  # the shared area's south-west corner
ALTITUDE_M = 25.0  # `cloudtrack-gcs survey --altitude 25`, its examples' altitude
SPEED_M_S = 5.0  # the survey planner's cruise speed
OVERLAP = 0.2  # `cloudtrack-gcs survey`'s default side overlap
SEARCH_RANGE_M = 50.0  # [camera] search_range_m
CLOSED_SET_KINDS = ("yolox", "deimv2_atto", "deimv2_femto")  # the server loads one; it never runs here


@dataclass(frozen=True)
class FleetMapSettings:
    duration_s: float = 30.0  # measured per fleet size
    status_interval_s: float = 1.0  # companion [backend] status_interval_s
    search_interval_s: float = 0.5  # companion [backend] search_interval_s: an analysed keyframe each
    warm_s: float = 120.0  # into the flight when the window starts: the maps hold that much already
    poll_s: float = 1.0  # the supervisor's GET of the state and of the merged map, each
    part_width_m: float = 100.0  # each vehicle's strip, east-west
    part_length_m: float = 600.0  # and north-south
    store: str = "sqlite"  # or "redis" (Debian's redis-server on loopback)


def _percentiles(values: Sequence[float]) -> dict[str, float]:
    if not values:
        return {"p50_ms": float("nan"), "p95_ms": float("nan"), "count": 0}
    return {
        "p50_ms": 1000 * float(np.percentile(values, 50)),
        "p95_ms": 1000 * float(np.percentile(values, 95)),
        "count": len(values),
    }


def part_flight(settings: FleetMapSettings, steps: int) -> list[dict[str, Any]]:
    """The first strip's status fields at each of `steps` reports from `warm_s` into its flight: position,
    heading and `search` (area, coverage, covered, POD grid), laid as the companion lays them."""
    frame = LocalFrame(*ORIGIN)
    w, h = settings.part_width_m, settings.part_length_m
    area = [frame.latlon(x, y) for x, y in ((0.0, 0.0), (w, 0.0), (w, h), (0.0, h))]
    camera = CameraModel.from_hfov(640, 480, 70.0, -45.0, True)  # the [camera] defaults
    plan = plan_survey(
        area,
        SurveySettings(
            altitude_m=ALTITUDE_M,
            overlap=OVERLAP,
            camera=camera,
            search_range_m=SEARCH_RANGE_M,
            min_altitude_m=5.0,
            max_altitude_m=60.0,
            speed_m_s=SPEED_M_S,
        ),
    )
    poses = keyframe_poses(plan.waypoints, SPEED_M_S, settings.search_interval_s, frame)
    cover = CoverageMap(area, camera, SEARCH_RANGE_M)
    pod = PodMap(
        area,
        camera,
        SEARCH_RANGE_M,
        curve_for("person"),
        PodSettings(shape=TargetShape.for_class("person", "standing", 1.7)),
    )
    reports: list[dict[str, Any]] = []
    laid = 0
    for k in range(steps):
        t = settings.warm_s + k * settings.status_interval_s
        while laid < len(poses) and poses[laid][3] <= t:  # the keyframes analysed by now
            lat, lon, yaw, when = poses[laid]
            cover.add_view(lat, lon, ALTITUDE_M, yaw)
            pod.add_look(lat, lon, ALTITUDE_M, yaw, when)
            laid += 1
        lat, lon, yaw, _ = poses[max(0, laid - 1)]  # at the end of its lanes it holds there
        reports.append(
            {
                "position": [round(lat, 7), round(lon, 7)],
                "heading_deg": round(math.degrees(yaw) % 360.0, 1),
                "keyframes": laid,
                "search": {
                    "area": [[round(a, 7), round(b, 7)] for a, b in area],
                    "coverage": round(cover.coverage(), 4),
                    "covered": cover.covered_rings(),
                    "mission_item": 2,
                    "mission_items": len(plan.items),
                    "mode": "AUTO",
                    "pod": pod.report(),
                },
            }
        )
    return reports


def _shifted(fields: dict[str, Any], dlon: float) -> dict[str, Any]:
    """A strip's fields moved `dlon` degrees east (the next vehicle's strip)."""
    search = fields["search"]

    def move(point: list[float]) -> list[float]:
        return [point[0], round(point[1] + dlon, 7)]

    return {
        **fields,
        "position": move(fields["position"]),
        "search": {
            **search,
            "area": [move(p) for p in search["area"]],
            "covered": [[move(p) for p in ring] for ring in search["covered"]],
            "pod": {**search["pod"], "origin": move(search["pod"]["origin"])},
        },
    }


def status_bodies(flight: list[dict[str, Any]], n: int, part_width_m: float) -> list[list[bytes]]:
    """Each vehicle's status reports as JSON bodies, made before the window so the client stays light."""
    frame = LocalFrame(*ORIGIN)
    bodies = []
    for i in range(n):
        dlon = frame.latlon(i * part_width_m, 0.0)[1] - ORIGIN[1]  # x: metres east
        mine = []
        for fields in flight:
            moved = _shifted(fields, dlon)
            analysed = moved.pop("keyframes")
            body = {
                "mission_id": MISSION_ID,
                "state": "SEARCHING",
                "prompt": PROMPT,
                "superset": "person",
                "altitude_m": ALTITUDE_M,
                "reason": "searching the survey",
                "progress": {"keyframes": analysed, "detections": 0, "candidates": 0, "rejected": 0},
                "keyframes": {"analysed": analysed},
                **moved,
            }
            mine.append(json.dumps(body).encode())
        bodies.append(mine)
    return bodies


def detector_settings(model_dir: Path) -> list[str]:
    """A detector whose weights are here (the server loads one at its start; no keyframe reaches it)."""
    for kind in CLOSED_SET_KINDS:
        try:
            require(kind, model_dir)
        except ModelError:
            continue
        return [
            f'detector.kind="{kind}"',
            f"detector.model_dir={json.dumps(str(model_dir))}",
            "detector.threads=1",
        ]
    raise ModelError(f"no detector weights in {model_dir} (one of {', '.join(CLOSED_SET_KINDS)})")


class _Page:
    """The supervisor page's open event stream: bytes and events received."""

    def __init__(self, url: str) -> None:
        self.bytes = 0
        self.events = 0
        self.error = ""
        self._url = url
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._read, name="page-stream", daemon=True)
        self._response: requests.Response | None = None

    def start(self) -> _Page:
        self._thread.start()
        return self

    def _read(self) -> None:
        headers = {"Authorization": f"Bearer {SUPERVISOR_TOKEN}"}
        while not self._stop.is_set():  # the server ends a stream after max_stream_s: reconnect, as the page
            try:
                with requests.get(self._url, headers=headers, stream=True, timeout=30) as response:
                    self._response = response
                    for line in response.iter_lines(chunk_size=65536):
                        self.bytes += len(line) + 1
                        if line.startswith(b"event:"):
                            self.events += 1
                        if self._stop.is_set():
                            return
            except (requests.RequestException, AttributeError) as exc:  # closed under it by stop()
                if not self._stop.is_set():
                    self.error = str(exc)[:200]
                    time.sleep(0.5)

    def stop(self) -> None:
        self._stop.set()
        if self._response is not None:
            self._response.close()
        self._thread.join(timeout=5)


def cpu_seconds(pid: int) -> float:
    """User plus system CPU time of a process so far, from /proc (what it used, however busy the machine)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:  # a child gone meanwhile
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children(pid: int) -> list[int]:
    """The server's child processes (its merge worker, `backend.merge_worker`), from /proc."""
    found: list[int] = []
    for listed in Path(f"/proc/{pid}/task").glob("*/children"):
        try:
            found += [int(c) for c in listed.read_text().split()]
        except OSError:
            continue
    return found


def rss_bytes(pid: int) -> int:
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return 0
    return next((int(line.split()[1]) * 1024 for line in lines if line.startswith("VmRSS:")), 0)


def merge_cpu_ms(bodies: list[list[bytes]], repeats: int = 3) -> float:
    """CPU time of one merge of the vehicles' maps as they stand after their last reports (the merge the map
    endpoint and the page's state run), here in the bench's process: the merge's cost apart from the load."""
    maps = []
    for index, mine in enumerate(bodies):
        status = VehicleStatusIn.model_validate_json(mine[-1])
        kept = updated_map(None, status.position, status.search, 1.0)
        if kept is not None:
            maps.append((f"bench-{index}", kept))
    start = time.process_time()
    for _ in range(repeats):
        merged_map(MISSION_ID, maps, 1.0)
    return 1000 * (time.process_time() - start) / repeats


def fleet_map_run(
    server: BackendProcess, tokens: dict[str, str], bodies: list[list[bytes]], settings: FleetMapSettings
) -> dict[str, Any]:
    """N vehicles report for `duration_s` while a supervisor watches; the figures of one fleet size."""
    n = len(bodies)
    url = server.url
    status_s: list[float] = []
    decisions_s: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()
    stop = threading.Event()
    vehicles = list(tokens)[:n]
    start = time.monotonic() + 0.5

    def vehicle(index: int) -> None:
        vehicle_id = vehicles[index]
        session = requests.Session()
        session.headers.update(
            {"Authorization": f"Bearer {tokens[vehicle_id]}", "Content-Type": "application/json"}
        )
        due = start + settings.status_interval_s * index / n  # the fleet's reports spread over the period
        for body in bodies[index]:
            pause = due - time.monotonic()
            if pause > 0 and stop.wait(pause):
                break
            try:
                t0 = time.perf_counter()
                answer = session.post(f"{url}/v1/vehicles/{vehicle_id}/status", data=body, timeout=60)
                t1 = time.perf_counter()
                polled = session.get(
                    f"{url}/v1/vehicles/{vehicle_id}/decisions", params={"after": 0}, timeout=60
                )
                t2 = time.perf_counter()
                with lock:
                    if answer.status_code == 200:
                        status_s.append(t1 - t0)
                    else:
                        errors.append(f"status HTTP {answer.status_code}: {answer.text[:120]}")
                    if polled.status_code == 200:
                        decisions_s.append(t2 - t1)
                    else:
                        errors.append(f"decisions HTTP {polled.status_code}")
            except requests.RequestException as exc:
                with lock:
                    errors.append(str(exc)[:200])
            due += settings.status_interval_s
        session.close()

    supervisor = requests.Session()
    supervisor.headers["Authorization"] = f"Bearer {SUPERVISOR_TOKEN}"
    state_s: list[float] = []
    state_bytes: list[int] = []
    map_s: list[float] = []
    map_bytes: list[int] = []
    map_ages: list[float] = []
    map_as_of: set[float] = set()
    rss: list[int] = [server.rss_bytes()]
    worker_rss: list[int] = [0]
    cpu_before = cpu_seconds(server.pid)
    # The merge worker's CPU apart (a worker started in the window counts from its start, its imports too).
    workers_before = {c: cpu_seconds(c) for c in children(server.pid)}

    def poll() -> None:
        due = start + settings.poll_s / 2
        while not stop.is_set():
            pause = due - time.monotonic()
            if pause > 0 and stop.wait(pause):
                return
            due += settings.poll_s  # a poll that takes longer than poll_s delays the next, never doubles up
            try:
                t0 = time.perf_counter()
                state = supervisor.get(f"{url}/supervisor/api/state", timeout=60)
                t1 = time.perf_counter()
                merged = supervisor.get(f"{url}/v1/missions/{MISSION_ID}/map", timeout=60)
                t2 = time.perf_counter()
            except requests.RequestException as exc:
                with lock:
                    errors.append(str(exc)[:200])
                continue
            with lock:
                if state.status_code == 200:
                    state_s.append(t1 - t0)
                    state_bytes.append(len(state.content))
                else:
                    errors.append(f"state HTTP {state.status_code}")
                if merged.status_code == 200:
                    map_s.append(t2 - t1)
                    map_bytes.append(len(merged.content))
                    answer = merged.json()
                    map_ages.append(float(answer.get("age_s", 0.0)))
                    map_as_of.add(float(answer.get("as_of", 0.0)))
                elif merged.status_code != 404:  # 404 until a first vehicle has reported its map
                    errors.append(f"map HTTP {merged.status_code}")
                rss.append(server.rss_bytes())
                worker_rss.append(sum(rss_bytes(c) for c in children(server.pid)))

    page = _Page(f"{url}/supervisor/events").start()
    threads = [threading.Thread(target=vehicle, args=(i,), name=f"vehicle-{i}") for i in range(n)]
    poller = threading.Thread(target=poll, name="supervisor")
    for t in threads:
        t.start()
    poller.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - start
    server_cpu = cpu_seconds(server.pid) - cpu_before
    worker_cpu = sum(cpu_seconds(c) - workers_before.get(c, 0.0) for c in children(server.pid))
    stop.set()
    poller.join()
    page.stop()
    # The map is merged again at most once per [fleet] merge_period_s: the end's check waits (bounded) for
    # the merge that holds every vehicle's last report, as a supervisor would see it a moment later.
    expected = {f"bench-{i}" for i in range(n)}
    give_up = time.monotonic() + FINAL_WAIT_S
    while True:
        final = supervisor.get(f"{url}/v1/missions/{MISSION_ID}/map", timeout=60)
        held = set(final.json().get("vehicles", [])) if final.status_code == 200 else set()
        if held >= expected or time.monotonic() > give_up:
            break
        time.sleep(0.2)
    final_state = supervisor.get(f"{url}/supervisor/api/state", timeout=60)
    supervisor.close()
    merged = final.json() if final.status_code == 200 else {}
    snapshot = final_state.json() if final_state.status_code == 200 else {}
    rss.append(server.rss_bytes())
    pod = merged.get("pod") or {}
    return {
        "vehicles": n,
        "window_s": round(wall, 1),
        "status_reports": len(status_s),
        "status_bytes": float(np.mean([len(b) for b in bodies[0]])),
        "status": _percentiles(status_s),
        "decisions_poll": _percentiles(decisions_s),
        "state": {**_percentiles(state_s), "bytes": int(np.median(state_bytes)) if state_bytes else 0},
        "map": {
            **_percentiles(map_s),
            "bytes": int(np.median(map_bytes)) if map_bytes else 0,
            "age_p50_s": float(np.percentile(map_ages, 50)) if map_ages else float("nan"),
            "age_p95_s": float(np.percentile(map_ages, 95)) if map_ages else float("nan"),
            "as_of_seen": len(map_as_of),
        },
        "page_stream": {
            "bytes_per_s": page.bytes / wall if wall > 0 else 0.0,
            "events": page.events,
            "error": page.error,
        },
        "server_cpu": {
            "seconds": server_cpu,
            "per_wall_s": server_cpu / wall if wall > 0 else 0.0,
            "ms_per_status": 1000 * server_cpu / max(1, len(status_s)),
            "merge_worker_per_wall_s": worker_cpu / wall if wall > 0 else 0.0,
        },
        "merge_cpu_ms": merge_cpu_ms(bodies),
        "rss_mb": {
            "start": rss[0] / 2**20,
            "max": max(rss) / 2**20,
            "end": rss[-1] / 2**20,
            "merge_worker_max": max(worker_rss) / 2**20,
        },
        "errors": len(errors),
        "error_examples": errors[:3],
        "final": {
            "map_vehicles": sorted(merged.get("vehicles", [])),
            "map_coverage": merged.get("coverage"),
            "map_pod_cells": int(pod.get("rows", 0)) * int(pod.get("cols", 0)),
            "map_pod_cell_m": pod.get("cell_m"),
            "page_vehicles": len(snapshot.get("vehicles", [])),
            "map_bytes": len(final.content),
            "state_bytes": len(final_state.content),
        },
    }


def _server_settings(model_dir: Path, folder: Path, redis_url: str | None) -> list[str]:
    settings = [*detector_settings(model_dir), 'verifier.kind="none"', "sessions.rate_limit_requests=100000"]
    if redis_url is not None:
        return [*settings, 'sessions.store="redis"', f"sessions.redis_url={json.dumps(redis_url)}"]
    return [*settings, f"sessions.sqlite_path={json.dumps(str(folder / 'sessions.sqlite3'))}"]


def fleet_map_bench(
    sizes: Sequence[int], model_dir: Path, settings: FleetMapSettings, say: Callable[[str], None]
) -> dict[str, Any]:
    """Each fleet size against its own fresh server; the ratios of the largest to the smallest."""
    import tempfile

    steps = max(1, math.ceil(settings.duration_s / settings.status_interval_s))
    say(f"[fleet-map] laying one part's maps ({settings.warm_s:g} s in, {steps} reports) ...")
    flight = part_flight(settings, steps)
    report: dict[str, Any] = {
        "settings": {
            "duration_s": settings.duration_s,
            "status_interval_s": settings.status_interval_s,
            "search_interval_s": settings.search_interval_s,
            "warm_s": settings.warm_s,
            "poll_s": settings.poll_s,
            "part_m": [settings.part_width_m, settings.part_length_m],
            "store": settings.store,
        },
        "runs": [],
    }
    for n in sizes:
        say(f"[fleet-map] {n} vehicle(s), one mission, {settings.duration_s:g} s ...")
        bodies = status_bodies(flight, n, settings.part_width_m)
        tokens = fleet_tokens(n)
        with tempfile.TemporaryDirectory(prefix="cloudtrack-fleet-map-") as folder:
            redis = RedisServer().start() if settings.store == "redis" else None
            try:
                server_settings = _server_settings(model_dir, Path(folder), redis.url if redis else None)
                with BackendProcess(server_settings, tokens, SUPERVISOR_TOKEN) as server:
                    report["runs"].append(fleet_map_run(server, tokens, bodies, settings))
            finally:
                if redis is not None:
                    redis.stop()
    runs = report["runs"]
    if len(runs) >= 2:
        small, large = runs[0], runs[-1]

        def ratio(a: float, b: float) -> float:
            return a / b if b > 0 else float("nan")

        report["ratios"] = {
            "vehicles": f"{large['vehicles']} vs {small['vehicles']}",
            "map_p95": ratio(large["map"]["p95_ms"], small["map"]["p95_ms"]),
            "map_bytes": ratio(large["map"]["bytes"], small["map"]["bytes"]),
            "state_p95": ratio(large["state"]["p95_ms"], small["state"]["p95_ms"]),
            "state_bytes": ratio(large["state"]["bytes"], small["state"]["bytes"]),
            "status_p95": ratio(large["status"]["p95_ms"], small["status"]["p95_ms"]),
            "rss_max": ratio(large["rss_mb"]["max"], small["rss_mb"]["max"]),
            "merge_cpu": ratio(large["merge_cpu_ms"], small["merge_cpu_ms"]),
        }
    return report


def print_fleet_map(report: dict[str, Any]) -> None:
    s = report["settings"]
    print(
        f"One mission, N vehicles each reporting every {s['status_interval_s']:g} s (status + decisions poll), "
        f"maps laid from a keyframe every {s['search_interval_s']:g} s, {s['warm_s']:g} s into the flight; "
        f"a {s['part_m'][0]:g} x {s['part_m'][1]:g} m strip each; a supervisor GETs state and map every "
        f"{s['poll_s']:g} s with the page's event stream open; {s['duration_s']:g} s per size, store "
        f"{s['store']}:"
    )
    print(
        "| vehicles | status p50/p95 [ms] | decisions p95 [ms] | map p50/p95 [ms] | map bytes | "
        "state p50/p95 [ms] | state bytes | stream bytes/s | RSS start/max [MB] | server CPU [s/s] | "
        "merge worker CPU [s/s] / RSS [MB] | merge CPU [ms] | errors |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in report["runs"]:
        print(
            f"| {r['vehicles']} | {r['status']['p50_ms']:.1f} / {r['status']['p95_ms']:.1f} | "
            f"{r['decisions_poll']['p95_ms']:.1f} | {r['map']['p50_ms']:.1f} / {r['map']['p95_ms']:.1f} | "
            f"{r['map']['bytes']:,} | {r['state']['p50_ms']:.1f} / {r['state']['p95_ms']:.1f} | "
            f"{r['state']['bytes']:,} | {r['page_stream']['bytes_per_s']:,.0f} | "
            f"{r['rss_mb']['start']:.0f} / {r['rss_mb']['max']:.0f} | {r['server_cpu']['per_wall_s']:.2f} | "
            f"{r['server_cpu']['merge_worker_per_wall_s']:.2f} / {r['rss_mb']['merge_worker_max']:.0f} | "
            f"{r['merge_cpu_ms']:.0f} | {r['errors']} |"
        )
    for r in report["runs"]:
        f = r["final"]
        print(
            f"{r['vehicles']} vehicle(s): {r['status_reports']} status reports of {r['status_bytes']:,.0f} bytes, "
            f"due over {s['duration_s']:g} s, sent in {r['window_s']:g} s; "
            f"merged map holds {len(f['map_vehicles'])} vehicle(s), coverage {f['map_coverage']}, POD grid "
            f"{f['map_pod_cells']} cells of {f['map_pod_cell_m'] or 0:.1f} m; page shows {f['page_vehicles']}; "
            f"map served {r['map']['age_p50_s']:.2f} / {r['map']['age_p95_s']:.2f} s old (p50/p95), "
            f"{r['map']['as_of_seen']} different maps in {r['map']['count']} reads"
        )
    if "ratios" in report:
        q = report["ratios"]
        print(
            f"{q['vehicles']}: map p95 x{q['map_p95']:.2f}, map bytes x{q['map_bytes']:.2f}, state p95 "
            f"x{q['state_p95']:.2f}, state bytes x{q['state_bytes']:.2f}, status p95 x{q['status_p95']:.2f}, "
            f"RSS max x{q['rss_max']:.2f}, merge CPU x{q['merge_cpu']:.1f}"
        )
