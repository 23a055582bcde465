"""Issue 43 item 5, scale: a mission's merged map is merged at most once per `[fleet] merge_period_s`
however many vehicles report and however often the map endpoint and the supervisor page read it, off the
reads (a background worker in the server), the map kept served meanwhile with its age; and a fleet's
vehicles are sent to the page without their own covered areas and POD cells, which the merged map carries.
Merges are counted (`MergedMaps.merges`, `on_merged`), never timed."""

from __future__ import annotations

import base64
import math
import threading
import time
from typing import Any

from backend import merged_maps, mission_merge
from backend.sessions import SessionStore
from backend.supervisor_view import SupervisorView
from cloudtrack.api_models import VehicleStatusIn

LAT, LON = 47.3977, 8.5456
D = 0.0009  # about 100 m of latitude


def _part(i: int) -> list[list[float]]:
    west = LON + i * D
    return [[LAT, west], [LAT, west + D], [LAT + D, west + D], [LAT + D, west]]


def _grid(west: float, pod: float) -> dict[str, Any]:
    values = base64.b64encode(bytes([round(pod * 250)] * 100)).decode()
    return {
        "target": "person", "posture": "standing", "target_pod": 0.8, "origin": [LAT, west], "cell_m": 10.0,
        "rows": 10, "cols": 10, "values": values, "mean": pod, "at_target": 0.0, "looks": 3, "dark_looks": 0,
    }  # fmt: skip


def _report(store: SessionStore, i: int, step: int, pod: bool = True) -> None:
    """Vehicle i, `step` reports into its lane: the southern step/100 of its part covered (so its map changes
    with every report), at the top of what it covered."""
    part = _part(i)
    north = LAT + D * min(1.0, (step + 1) / 100)
    covered = [[part[0], part[1], [north, part[1][1]], [north, part[0][1]]]]
    search: dict[str, Any] = {"area": part, "covered": covered, "coverage": min(1.0, (step + 1) / 100)}
    if pod:
        search["pod"] = _grid(part[0][1], min(1.0, (step + 1) / 100))
    body = {
        "mission_id": "m-scale",
        "state": "SEARCHING",
        "prompt": "a man in a gray shirt",
        "position": [north, part[0][1] + D / 2],
        "search": search,
    }
    store.set_status(f"d{i:02d}", VehicleStatusIn.model_validate(body))


def test_many_reports_and_reads_merge_at_most_once_per_period() -> None:
    now = [1000.0]
    store = SessionStore(clock=lambda: now[0], merge_period_s=2.0)
    view = SupervisorView(store, clock=lambda: now[0])
    told: list[str] = []
    store.merged_maps.on_merged = told.append
    vehicles, seconds = 6, 12
    for second in range(seconds):  # every vehicle reports each second, each report changes its map
        for i in range(vehicles):
            _report(store, i, second)
            # ... and after each report the map is read and the page's state built, as often as can be
            assert store.merged_map("m-scale") is not None
            view.snapshot()
        now[0] += 1.0
    # 72 reports, 144 reads over 12 s: at most one merge per 2 s (the first read's, then one a period).
    merges = store.merged_maps.merges
    assert 2 <= merges <= math.ceil(seconds / 2.0) + 1, merges
    assert told == ["m-scale"] * merges
    # Meanwhile the map kept is served, no older than the period; once it is over, the last reports are in.
    merged = store.merged_map("m-scale")
    assert merged is not None and now[0] - merged.as_of <= 2.0
    now[0] += 2.0
    merged = store.merged_map("m-scale")
    assert merged is not None and merged.as_of == now[0] and store.merged_maps.merges == merges + 1
    assert sorted(merged.vehicles) == [f"d{i:02d}" for i in range(vehicles)]
    assert merged.coverage is not None and math.isclose(merged.coverage, seconds / 100, abs_tol=0.01)
    # Nothing changed since: a read past the period looks at the maps but merges nothing.
    now[0] += 5.0
    assert store.merged_map("m-scale") is not None and store.merged_maps.merges == merges + 1


def test_in_the_background_readers_never_merge_and_the_last_report_reaches_the_map(monkeypatch: Any) -> None:
    period = 0.3
    store = SessionStore(merge_period_s=period, merge_in_background=True)
    merged_at: list[float] = []  # when each merge started, and on which thread
    merged_on: list[str] = []

    def counted(*args: Any) -> Any:
        merged_at.append(store.merged_maps._kept["m-scale"].checked_at)  # the refresh's clock reading
        merged_on.append(threading.current_thread().name)
        return mission_merge.merged_map(*args)

    monkeypatch.setattr(merged_maps, "merged_map", counted)
    for i in range(4):
        _report(store, i, 0, pod=False)
    assert store.merged_map("m-scale") is not None  # the first read merges: nothing kept to serve yet
    assert store.merged_maps.merges == 1
    stop = threading.Event()
    reads = [0]

    def reader() -> None:
        while not stop.is_set():
            assert store.merged_map("m-scale") is not None
            reads[0] += 1
            time.sleep(0.001)

    readers = [threading.Thread(target=reader) for _ in range(4)]
    started = time.monotonic()
    for thread in readers:
        thread.start()
    try:
        for step in range(1, 40):
            for i in range(4):
                _report(store, i, step, pod=False)
    finally:
        stop.set()
        for thread in readers:
            thread.join()
    elapsed = time.monotonic() - started
    merges = store.merged_maps.merges
    assert reads[0] > merges  # many reads, served the kept map
    assert len(merged_at) == merges <= 2 + elapsed / period, (merges, elapsed)
    # Merges of the mission a period apart at least, all but the first read's on the worker, none on a
    # reader's thread.
    assert all(b - a >= period * 0.999 for a, b in zip(merged_at, merged_at[1:], strict=False)), merged_at
    assert merged_on[0] == "MainThread" and set(merged_on[1:]) <= {"mission-merge"}, merged_on
    # No read after the last report: the refresh it scheduled brings the last report in anyway.
    deadline = time.monotonic() + 10 * period + 5
    while time.monotonic() < deadline:
        merged = store.merged_maps._kept["m-scale"].merged
        if merged is not None and merged.coverage is not None and merged.coverage > 0.395:
            break
        time.sleep(0.05)
    merged = store.merged_maps._kept["m-scale"].merged
    assert merged is not None and math.isclose(merged.coverage or 0.0, 0.40, abs_tol=0.01)
    store.merged_maps.close()


def test_a_fleets_vehicles_leave_their_covered_area_and_pod_cells_to_the_merged_map() -> None:
    store = SessionStore()
    view = SupervisorView(store)
    for i in range(3):
        _report(store, i, 50)
    store.set_status(
        "solo", VehicleStatusIn.model_validate({
            "mission_id": "alone", "state": "SEARCHING", "position": [LAT, LON - D],
            "search": {"area": _part(-2), "covered": [_part(-2)], "coverage": 1.0, "pod": _grid(LON - 2 * D, 1)},
        })
    )  # fmt: skip
    snapshot = view.snapshot()
    by_id = {v.id: v for v in snapshot.vehicles}
    fleet = next(m for m in snapshot.missions if m.mission_id == "m-scale")
    assert fleet.covered and fleet.pod is not None and fleet.pod.values and fleet.as_of > 0
    for i in range(3):
        vehicle = by_id[f"d{i:02d}"]
        assert vehicle.on_mission_map
        assert vehicle.search is not None and vehicle.search.covered == [] and len(vehicle.search.area) == 4
        assert vehicle.search.coverage == 0.51  # its own figures stay
        assert vehicle.pod is not None and vehicle.pod.values == "" and vehicle.pod.mean == 0.51
    # A vehicle alone in its mission keeps its own.
    solo = by_id["solo"]
    assert not solo.on_mission_map and solo.search is not None and solo.search.covered
    assert solo.pod is not None and solo.pod.values
