"""Keyframes too dark for the detection curve (behaviors/scene_light.py): measured the same way in flight and
by `pod-curve` (cloudtrack/keyframe_light.py), laid as coverage but never as POD, and said to the operator."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from behaviors.camera_model import CameraModel
from behaviors.mission import MissionState, initial_state
from behaviors.mission_commands import StartMission
from behaviors.mission_config import MissionConfig
from behaviors.scene_light import MIN_MEAN_LUMA, low_light_note, too_dark
from behaviors.telemetry import Telemetry
from cloudtrack.coverage import CoverageMap
from cloudtrack.detection_curves import curve_for
from cloudtrack.keyframe_light import mean_luma
from cloudtrack.pod_map import PodMap, PodSettings
from companion.cloud.backend_worker import BackendAnswer
from companion.mission_runner import MissionRunner
from companion.operator_notices import OperatorNotices
from companion.search_coverage import _Maps


@pytest.mark.parametrize(
    ("luma", "dark"),
    [
        (0.0, True),
        (37.0, True),  # the dev set's night scene (uavdt_S1301: 35-39)
        (MIN_MEAN_LUMA - 0.1, True),
        (MIN_MEAN_LUMA, False),  # two stops under mid-grey: still judged
        (78.0, False),  # the darkest daylight sequence (wakeboard7: dark water, bright spray)
        (118.0, False),  # mid-grey
        (255.0, False),
    ],
)
def test_a_keyframe_two_stops_under_mid_grey_is_too_dark(luma: float, dark: bool) -> None:
    assert too_dark(luma) is dark


def test_the_note_says_why_the_map_claims_nothing() -> None:
    note = low_light_note(36.6, 4)
    assert "mean luma 37 < 60" in note and "claims nothing" in note and "4 so far" in note


@pytest.mark.parametrize(
    ("image", "luma"),
    [
        (np.full((48, 64), 100, np.uint8), 100.0),
        (np.full((48, 64, 3), 100, np.uint8), 100.0),
        (np.dstack([np.zeros((48, 64), np.uint8), np.full((48, 64), 255, np.uint8), np.zeros((48, 64), np.uint8)]),
         0.587 * 255),  # pure green, BGR
        (np.zeros((0, 0, 3), np.uint8), 0.0),
    ],
)  # fmt: skip
def test_mean_luma_weights_the_channels_as_the_grey_conversion(image: np.ndarray, luma: float) -> None:
    assert mean_luma(image) == pytest.approx(luma, abs=0.01)


AREA = [(47.3977, 8.5456), (47.3977, 8.5460), (47.3981, 8.5460), (47.3981, 8.5456)]
CAMERA = CameraModel.from_hfov(640, 480, 70.0, -90.0, stabilised=True)
OVER = Telemetry(time_s=1.0, lat_deg=47.3979, lon_deg=8.5458, height_agl=15.0)


def _maps() -> _Maps:
    pod = PodMap(AREA, CAMERA, 40.0, curve_for("person"), PodSettings())
    return _Maps(AREA, CoverageMap(AREA, CAMERA, 40.0), pod)


def _look(t: Telemetry, lit: bool) -> Any:
    return ((t.lat_deg, t.lon_deg, t.height_agl, t.yaw, t.roll, t.pitch), t.time_s, lit)


def test_a_dark_keyframe_lays_coverage_but_no_pod() -> None:
    dark = _maps()
    dark.lay(_look(OVER, lit=False))
    assert dark.cover.coverage() > 0.2  # the camera looked there and the back-end analysed it
    assert dark.pod is not None and dark.pod.mean() == 0.0 and dark.pod.looks == 0 and dark.dark_looks == 1
    lit = _maps()
    lit.lay(_look(OVER, lit=True))
    assert lit.pod is not None and lit.pod.mean() > 0.1 and lit.dark_looks == 0


class Coverage:
    pod_error = ""

    def __init__(self) -> None:
        self.looks: list[bool] = []

    def start(self, target_class: str = "") -> None: ...

    def stop(self) -> None: ...

    def update(self, telemetry: Telemetry) -> None: ...

    def add_look(self, pose: Telemetry, capture_time: float, lit: bool = True) -> None:
        self.looks.append(lit)

    def report(self) -> dict[str, Any] | None:
        return None


def test_the_operator_is_told_while_keyframes_are_too_dark() -> None:
    none: Any = None
    coverage = Coverage()
    notices = OperatorNotices()
    runner = MissionRunner(MissionConfig(), none, none, none, none, coverage=coverage, notices=notices)
    runner.state = replace(
        initial_state(MissionConfig()), mode=MissionState.SEARCHING, mission=StartMission("a person")
    )
    for luma in (30.0, 31.0, None, 120.0, 20.0):  # None: a keyframe whose luma was not measured
        runner._lay_look(BackendAnswer(1, 1.0, (), 0.1, {"query_id": 3}, True, mean_luma=luma), OVER)
        if luma == 31.0:
            assert "too dark" in notices.current() and "2 so far" in notices.current()
        if luma == 120.0:
            assert notices.current() == ""  # a lit keyframe again: the notice no longer holds
    assert coverage.looks == [False, False, True, True, False]
    assert "3 so far" in notices.current()
