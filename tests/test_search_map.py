"""The search map in flight: only keyframes the back-end analysed whole are laid on it (the main loop's rule),
the POD grid grows from them as the detection curve says (cloudtrack/pod_map.py, behaviors/apparent_size.py),
and the GCS hears the share of the area at the target POD. Select: -k search_map.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from behaviors.apparent_size import TargetShape, apparent_size_px
from behaviors.camera_model import CameraModel
from behaviors.detection_curve import DetectionCurve, empty_bins
from behaviors.mission import MissionState, initial_state
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from behaviors.telemetry import Telemetry
from cloudtrack.coverage import LocalFrame
from cloudtrack.pod_map import PodMap, PodSettings, decode_grid, grid_value, pod_bands, sizes_px
from companion.cloud.backend_worker import BackendAnswer
from companion.mission_runner import MissionRunner

CAMERA = CameraModel.from_hfov(640, 480, 70.0, -45.0)
FRAME = LocalFrame(47.3977, 8.5456)
AREA = [FRAME.latlon(0, 0), FRAME.latlon(60, 0), FRAME.latlon(60, 100), FRAME.latlon(0, 100)]


def curve(*shares: float) -> DetectionCurve:
    """A curve whose bins (from the smallest) find the target in these shares of 100 frames."""
    bins = tuple(
        replace(b, samples=100, proposed=round(100 * p), yes=round(100 * p))
        for b, p in zip(empty_bins(), (*shares, *(shares[-1],) * (10 - len(shares))), strict=True)
    )
    return DetectionCurve("person", bins)


@pytest.mark.parametrize(
    ("height", "north", "east", "posture"),
    [(10.0, 10.0, 0.0, "standing"), (20.0, 25.0, -8.0, "lying"), (35.0, 30.0, 12.0, "standing")],
)
def test_search_map_sizes_match_the_pure_model(
    height: float, north: float, east: float, posture: Any
) -> None:
    shape = TargetShape.person(posture)
    one = apparent_size_px(CAMERA, height, north, east, shape, yaw=0.4)
    many = sizes_px(CAMERA, height, np.array([north]), np.array([east]), shape, yaw=0.4)
    assert one > 0 and many[0] == pytest.approx(one, rel=1e-9)


def test_search_map_a_person_looks_smaller_from_higher_up_and_nothing_outside_the_image() -> None:
    shape = TargetShape.person()
    sizes = [apparent_size_px(CAMERA, h, h, 0.0, shape) for h in (10.0, 20.0, 40.0)]
    assert sizes[0] > sizes[1] > sizes[2] > 0
    assert apparent_size_px(CAMERA, 10.0, -10.0, 0.0, shape) == 0.0  # behind the vehicle
    assert apparent_size_px(CAMERA, 10.0, 10.0, 60.0, shape) == 0.0  # far off to the side


def look(pod: PodMap, north: float, east: float, t: float, height: float = 10.0, yaw: float = 0.0) -> int:
    return pod.add_look(*FRAME.latlon(east, north), height, yaw, t)


def test_search_map_a_pass_counts_its_best_look_and_passes_combine() -> None:
    pod = PodMap(AREA, CAMERA, 15.0, curve(0.5), PodSettings(pass_gap_s=10.0))
    place = FRAME.latlon(30, 40)  # (lat, lon) of east 30, north 40
    assert pod.pod_at(*place) == 0.0
    look(pod, 30.0, 30.0, t=0.0)  # 10 m short of the place, looking north
    assert pod.pod_at(*place) == pytest.approx(0.5, abs=0.01)
    look(pod, 31.0, 30.0, t=0.5)  # the same pass: no new evidence about that person
    assert pod.pod_at(*place) == pytest.approx(0.5, abs=0.01)
    look(pod, 30.0, 30.0, t=30.0)  # another pass
    assert pod.pod_at(*place) == pytest.approx(0.75, abs=0.01)
    assert pod.pod_at(*FRAME.latlon(30, 5)) == 0.0  # never in view


def test_search_map_grid_is_bounded_and_round_trips() -> None:
    big = [FRAME.latlon(0, 0), FRAME.latlon(3000, 0), FRAME.latlon(3000, 2000), FRAME.latlon(0, 2000)]
    pod = PodMap(big, CAMERA, 50.0, curve(0.95))
    assert pod.rows * pod.cols <= 4096 and pod.cell_m >= 2.0
    look(pod, 1000.0, 1500.0, t=0.0, height=30.0)
    report = pod.report()
    grid = decode_grid(report)
    assert grid.shape == (pod.rows, pod.cols)
    assert np.nanmax(grid) == pytest.approx(0.95, abs=0.01)
    assert grid_value(report, *FRAME.latlon(-50, -50)) is None  # outside the grid
    bands = pod_bands(report)
    assert [(lo, hi) for lo, hi, _ in bands] == [(0.9, 1.0)]  # bands hold their lower bound
    assert bands[0][2].area > 0
    with pytest.raises(ValueError, match="values"):
        decode_grid({**report, "values": report["values"][:-8]})


class Coverage:
    """The runner's side of `companion.search_coverage.SearchCoverage`: what it was given."""

    pod_error = ""

    def __init__(self, report: dict[str, Any] | None = None) -> None:
        self.looks: list[tuple[float, float]] = []
        self._report = report

    def start(self, target_class: str = "") -> None: ...

    def stop(self) -> None: ...

    def update(self, telemetry: Telemetry) -> None: ...

    def add_look(self, pose: Telemetry, capture_time: float, lit: bool = True) -> None:
        self.looks.append((pose.time_s, capture_time))

    def report(self) -> dict[str, Any] | None:
        return self._report


@pytest.mark.parametrize(
    ("final", "fields", "mode", "laid"),
    [
        (True, {"query_id": 3}, MissionState.SEARCHING, True),
        (False, {"query_id": 3}, MissionState.SEARCHING, False),  # the fast stage's answer: the final follows
        (True, {"query_id": 3, "roi": [1, 2, 3, 4]}, MissionState.LOST, False),  # a region, not the view
        (True, {"query_id": 3}, MissionState.IDLE, False),  # no search running
    ],
)
def test_search_map_only_whole_keyframes_the_back_end_analysed_are_laid(
    final: bool, fields: dict[str, Any], mode: MissionState, laid: bool
) -> None:
    none: Any = None
    coverage = Coverage()
    runner = MissionRunner(MissionConfig(), none, none, none, none, coverage=coverage)
    runner.state = replace(initial_state(MissionConfig()), mode=mode, mission=StartMission("a person"))
    pose = Telemetry(time_s=4.9, lat_deg=47.3977, lon_deg=8.5456, height_agl=10.0)
    answer = BackendAnswer(12, 5.0, (), 0.3, fields, final)
    runner._lay_look(answer, pose)
    runner._lay_look(answer, None)  # no pose that old: nothing to place it by
    assert coverage.looks == ([(4.9, 5.0)] if laid else [])


def test_search_map_the_gcs_hears_the_share_at_the_target_pod() -> None:
    said: list[str] = []

    class Vehicle:
        def send_value(self, name: str, value: float) -> None: ...

        def send_status(self, text: str, severity: int) -> None:
            said.append(text)

    none: Any = None
    vehicle: Any = Vehicle()
    clock = iter(float(t) for t in range(100))
    runner = MissionRunner(MissionConfig(), none, none, vehicle, none, clock=lambda: next(clock))
    runner._tell_coverage(0.12, {"at_target": 0.0, "target_pod": 0.8})
    runner._tell_coverage(0.15, {"at_target": 0.05, "target_pod": 0.8})  # neither reached a tenth more
    runner._tell_coverage(0.18, {"at_target": 0.11, "target_pod": 0.8})
    runner._tell_coverage(0.31, None)  # no POD map: the share seen alone
    assert said == [
        "COVERAGE 10% of the search area; 0% at POD >= 0.8",
        "COVERAGE 10% of the search area; 11% at POD >= 0.8",
        "COVERAGE 30% of the search area",
    ]


def test_search_map_the_gcs_hears_once_why_there_is_no_search_area() -> None:
    said: list[str] = []

    class Vehicle:
        def send_status(self, text: str, severity: int) -> None:
            said.append(text)

    none: Any = None
    vehicle: Any = Vehicle()
    runner = MissionRunner(MissionConfig(), none, none, vehicle, none)
    far = "the search area is 5660 km from the vehicle (47.397700,8.545600)"
    for why in ("", far, far, "", far):
        runner._tell_no_area(why)
    assert said == [f"NO SEARCH AREA: {far}", f"NO SEARCH AREA: {far}"]
