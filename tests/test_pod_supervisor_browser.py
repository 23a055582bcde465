"""The POD map on the supervisor page, in Debian's headless chromium with every request off loopback refused:
a status carrying a real `PodMap` grid, posted through the real API, is drawn as cells coloured by band
inside the search area with a legend (the bands' colours and what POD means); the coverage line says the
share at the target POD, the keyframes kept through an outage are counted, and after the survey is
replaced the map says the earlier area is in the downloads. A screenshot is kept in
out/test-artifacts/supervisor-pod.png. Select: -k pod_supervisor_browser."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from playwright.sync_api import Page, expect

from backend.app import create_app
from backend.config import AuthConfig, BackendConfig, DetectorConfig, SessionConfig
from backend.pod_layers import BAND_COLOURS
from cloudtrack.pod_map import BANDS, decode_grid
from tests.live_backend import SUPERVISOR_TOKEN, VEHICLE_TOKENS, serve
from tests.pod_fixtures import AREA, NEXT_AREA, pod_report
from tests.test_supervisor_console_browser import _log_in, offline_page  # noqa: F401 - the fixture

REPO = Path(__file__).resolve().parents[1]
SCREENSHOT = REPO / "out" / "test-artifacts" / "supervisor-pod.png"
DRONE = {"Authorization": f"Bearer {VEHICLE_TOKENS['drone-1']}"}
KEYFRAMES = {"analysed": 63, "stored": 12, "waiting": 0, "sent": 12, "dropped": 0}


def _status(area: list[list[float]], grid: dict[str, Any] | None) -> dict[str, Any]:
    search: dict[str, Any] = {"area": area, "coverage": 0.37, "mode": "AUTO"}
    if grid is not None:
        search["pod"] = grid
    return {
        "mission_id": "m-pod", "state": "SEARCHING", "prompt": "a man in a red jacket",
        "position": [area[0][0] + 0.0002, area[0][1] + 0.0002], "altitude_m": 25.0, "search": search,
        "keyframes": KEYFRAMES,
    }  # fmt: skip


@pytest.mark.slow
def test_pod_supervisor_browser_draws_the_pod_map_with_its_legend(
    offline_page: tuple[Page, list[str]],  # noqa: F811 - the imported fixture
    models_dir: Path,
) -> None:
    page, outside = offline_page
    grid = pod_report()
    values = decode_grid(grid)
    bands_held = {
        low
        for i, (low, high) in enumerate(BANDS)
        if np.any(
            (values > low if low == 0 else values >= low)
            & (values <= high if i == len(BANDS) - 1 else values < high)
        )
    }
    config = BackendConfig(
        auth=AuthConfig(tokens=VEHICLE_TOKENS, supervisor_token=SUPERVISOR_TOKEN),
        detector=DetectorConfig(kind="yolox", model_dir=str(models_dir)),
        sessions=SessionConfig(sqlite_path=":memory:"),
    )
    with serve(create_app(config)) as url:
        response = httpx.post(f"{url}/v1/vehicles/drone-1/status", json=_status(AREA, grid), headers=DRONE)
        assert response.status_code == 200, response.text
        _log_in(page, url)
        card = page.locator('section[data-vehicle="drone-1"]')
        legend = card.locator(".pod-legend")
        expect(legend).to_be_visible()
        expect(legend.locator(".pod-bands li")).to_have_count(len(BANDS))
        expect(legend.locator(".pod-bands li").last).to_have_text("90-100 %")
        swatches = legend.locator(".pod-swatch").evaluate_all(
            "els => els.map(e => getComputedStyle(e).backgroundColor)"
        )
        assert swatches == [
            f"rgb({int(c[1:3], 16)}, {int(c[3:5], 16)}, {int(c[5:7], 16)})" for c in BAND_COLOURS
        ]
        expect(legend.locator(".pod-meaning")).to_contain_text(
            "POD (probability of detection): the chance the search would have found the standing person here "
            "had they been there; blank = not analysed"
        )
        expect(card.locator(".coverage")).to_have_text(
            f"37 % of the area seen · {grid['at_target'] * 100:.0f} % at POD ≥ 0.8 · mean POD {grid['mean']:.2f}"
        )
        expect(card.locator(".keyframes")).to_have_text(
            "keyframes kept through a back-end outage: 12 stored · 12 sent · 0 dropped"
        )
        # The cells: coloured by band, one shape per run of a row, only bands the grid holds, inside the area.
        cells = card.locator("svg.map path.pod-cell")
        assert cells.count() > 0
        drawn = cells.evaluate_all("els => els.map(e => [Number(e.dataset.pod), e.getAttribute('fill')])")
        assert {pod for pod, _ in drawn} == bands_held
        assert all(fill == BAND_COLOURS[[b[0] for b in BANDS].index(pod)] for pod, fill in drawn)
        box = card.locator("svg.map path.area").evaluate(
            "e => { const b = e.getBBox(); return [b.x, b.y, b.width, b.height]; }"
        )
        pods = card.locator("svg.map g.pod").evaluate(
            "e => { const b = e.getBBox(); return [b.x, b.y, b.width, b.height]; }"
        )
        assert pods[0] >= box[0] - 1 and pods[1] >= box[1] - 1  # within the area, to a pixel
        assert pods[0] + pods[2] <= box[0] + box[2] + 1 and pods[1] + pods[3] <= box[1] + box[3] + 1
        assert pods[2] < box[2]  # two lanes of the area's width were flown: blank beside them
        # The survey is replaced: the new area has no map yet, the old one is in the downloads.
        response = httpx.post(
            f"{url}/v1/vehicles/drone-1/status", json=_status(NEXT_AREA, None), headers=DRONE
        )
        assert response.status_code == 200, response.text
        expect(card.locator(".map-info")).to_contain_text(
            "1 earlier search area of this mission in the downloads"
        )
        expect(legend).to_be_hidden()
        expect(cells).to_have_count(0)
        expect(card.locator(".downloads button")).to_have_count(
            2
        )  # the mission's GeoJSON and KML, no find yet
        response = httpx.post(
            f"{url}/v1/vehicles/drone-1/status",
            json=_status(NEXT_AREA, pod_report(NEXT_AREA, 1)),
            headers=DRONE,
        )
        assert response.status_code == 200
        expect(legend).to_be_visible()
        SCREENSHOT.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(SCREENSHOT), full_page=True)
        print(f"screenshot: {SCREENSHOT}")
        page.goto("about:blank")  # close the live stream before the back-end stops
    assert outside == []
